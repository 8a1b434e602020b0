"""7-parameter Helmert (similarity) transform ``Y = s·R·X + T``: closed form, then weighted least
squares with covariance; applying, inverting and composing.

The closed form is Umeyama's (1991) weighted SVD solution (equivalent to Horn 1987). The
least-squares model treats the *target* coordinates as observations (Gauss–Markov)::

    Y_i + v_i = s · exp([δ]×) R X_i + T

with parameters (δ — a small rotation about the target axes, T, s). Weights are per point or per
coordinate; ``sigma_m`` is the a-priori σ of a target coordinate. ``fix_scale=True`` gives the
6-parameter rigid transform. Collinear points leave the rotation about their line undetermined:
the result then carries ``Termination.RANK_DEFICIENT``.

References
----------
Umeyama, S. (1991). Least-squares estimation of transformation parameters between two point
patterns. IEEE PAMI 13(4), 376–380.
Horn, B. K. P. (1987). Closed-form solution of absolute orientation using unit quaternions.
JOSA A 4(4), 629–642.
Förstner, W., Wrobel, B. P. (2016). *Photogrammetric Computer Vision*, §10.5.4.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validate import as_array, as_points
from ..adjustment.dense import DenseOptions, DenseResult, solve_dense
from ..errors import InvalidInputError, ShapeError, TooFewPointsError
from ..results import HasOutcome, Outcome
from . import rotations as rot

__all__ = ["Similarity", "HelmertResult", "helmert", "umeyama", "similarity_residuals"]


@dataclass(frozen=True, eq=False)
class Similarity:
    """``Y = scale · R · X + translation`` (R proper rotation, scale > 0)."""

    scale: float
    R: np.ndarray
    translation: np.ndarray

    def __post_init__(self):
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise InvalidInputError(f"scale: {self.scale!r}; expected a finite number > 0")
        object.__setattr__(self, "R", rot.check_rotation(self.R, "R").copy())
        object.__setattr__(self, "translation", as_array(self.translation, "translation", shape=(3,)).copy())

    def apply(self, points) -> np.ndarray:
        """Transform (N, 3) points."""
        X = as_points(points, "points", 3)
        return self.scale * X @ self.R.T + self.translation

    __call__ = apply

    def inverse(self) -> "Similarity":
        """``X = (1/s) Rᵀ (Y − T)``."""
        return Similarity(1.0 / self.scale, self.R.T, -(self.R.T @ self.translation) / self.scale)

    def compose(self, other: "Similarity") -> "Similarity":
        """``self ∘ other`` (apply ``other`` first)."""
        return Similarity(self.scale * other.scale, self.R @ other.R, self.scale * self.R @ other.translation + self.translation)

    def matrix4(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.scale * self.R
        T[:3, 3] = self.translation
        return T


def umeyama(source, target, weights=None, *, fix_scale: bool = False) -> Similarity:
    """Weighted closed-form similarity (Umeyama 1991).

    Parameters
    ----------
    source, target : array_like (N, 3)
    weights : array_like (N,), optional
    fix_scale : bool
        Force ``scale = 1``.
    """
    X = as_points(source, "source", 3)
    Y = as_points(target, "target", 3)
    w = np.ones(X.shape[0]) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    mx = w @ X
    my = w @ Y
    Xc, Yc = X - mx, Y - my
    S = (Yc * w[:, None]).T @ Xc
    U, d, Vt = np.linalg.svd(S)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    varx = np.sum(w * np.sum(Xc**2, axis=1))
    s = 1.0 if fix_scale else float(np.trace(np.diag(d) @ D) / varx)
    return Similarity(s, R, my - s * R @ mx)


@dataclass(frozen=True, eq=False)
class HelmertResult(HasOutcome):
    """Result of :func:`helmert`.

    Attributes
    ----------
    transform : Similarity
    param_names : tuple
        ``("rx", "ry", "rz", "tx", "ty", "tz", "scale")``; rx..rz: small rotations (rad) about the
        target axes at the estimate.
    covariance, covariance_prior : ndarray (7, 7)
        A posteriori / a priori (``sigma_m``); scale row/column zero when fixed.
    std, std_prior : ndarray (7,)
    residuals : ndarray (N, 3)
        ``s R X + T − Y`` (metres).
    rms : ndarray (3,)
        Per-axis RMS of the residuals.
    sigma0 : float
    adjustment : DenseResult
    outcome : Outcome
    """

    transform: Similarity
    param_names: tuple
    covariance: np.ndarray
    covariance_prior: np.ndarray
    residuals: np.ndarray
    rms: np.ndarray
    sigma0: float
    adjustment: DenseResult
    outcome: Outcome

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance), 0, None))

    @property
    def std_prior(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance_prior), 0, None))

    def apply(self, points) -> np.ndarray:
        return self.transform.apply(points)

    def inverse(self) -> Similarity:
        return self.transform.inverse()

    def apply_with_covariance(self, points, *, prior: bool = False):
        """Transform points and propagate the parameter covariance: ``(Y (N,3), cov (N,3,3))``."""
        X = as_points(points, "points", 3)
        t = self.transform
        RX = X @ t.R.T
        Y = t.scale * RX + t.translation
        J = np.zeros((X.shape[0], 3, 7))
        J[:, :, 0:3] = -t.scale * rot.skew(RX)
        J[:, :, 3:6] = np.eye(3)
        J[:, :, 6] = RX
        C = self.covariance_prior if prior else self.covariance
        return Y, np.einsum("nij,jk,nlk->nil", J, C, J)


def similarity_residuals(params, source, target):
    """Misclosures ``s·R·X + T − Y`` (3N,) and analytic Jacobian (3N, 7).

    ``params = [rvec (3), T (3), s]``; derivatives w.r.t. the increment ``[δ, T, s]`` with
    ``R ← exp([δ]×)·R``: ``∂/∂δ = −s [R X]×``, ``∂/∂T = I``, ``∂/∂s = R X``.
    """
    R = rot.matrix_from_axis_angle(params[:3])
    s = params[6]
    RX = source @ R.T
    v = s * RX + params[3:6] - target
    n = source.shape[0]
    J = np.zeros((n, 3, 7))
    J[:, :, 0:3] = -s * rot.skew(RX)
    J[:, :, 3:6] = np.eye(3)
    J[:, :, 6] = RX
    return v.ravel(), J.reshape(3 * n, 7)


def helmert(
    source,
    target,
    *,
    weights=None,
    sigma_m: float = 1.0,
    fix_scale: bool = False,
    options: DenseOptions | None = None,
) -> HelmertResult:
    """Estimate ``target ≈ s R source + T`` (closed form, then least squares with covariance).

    Parameters
    ----------
    source, target : array_like (N, 3)
        Corresponding points (metres); N ≥ 3, not all collinear.
    weights : array_like (N,) or (N, 3), optional
        Relative weights of the target coordinates (per point or per coordinate).
    sigma_m : float
        A-priori σ of a target coordinate of weight 1 (metres).
    fix_scale : bool
        Rigid 6-parameter transform (scale fixed to 1).
    options : DenseOptions, optional

    Returns
    -------
    HelmertResult

    Raises
    ------
    TooFewPointsError, ShapeError, NonFiniteError, InvalidInputError
    """
    X = as_points(source, "source", 3)
    Y = as_points(target, "target", 3)
    if X.shape != Y.shape:
        raise ShapeError(f"source has shape {X.shape} but target has {Y.shape}; expected the same (N, 3)")
    n = X.shape[0]
    if n < 3:
        raise TooFewPointsError(f"a 7-parameter Helmert transform needs at least 3 points, got {n}")
    if weights is None:
        w = np.ones((n, 3))
    else:
        w = as_array(weights, "weights")
        if w.shape == (n,):
            w = np.repeat(w[:, None], 3, axis=1)
        if w.shape != (n, 3) or np.any(w < 0):
            raise ShapeError(f"weights: expected non-negative shape ({n},) or ({n}, 3), got {w.shape}")
    if not (np.isfinite(sigma_m) and sigma_m > 0):
        raise InvalidInputError(f"sigma_m: {sigma_m!r}; expected a positive number of metres")
    # centre the source for conditioning: Y = s R (X' + m) + T = s R X' + T'
    m = X.mean(0)
    Xc = X - m
    init = umeyama(Xc, Y, w.mean(1), fix_scale=fix_scale)

    def fun(p):
        return similarity_residuals(p, Xc, Y)

    def update(p, dp):
        R = rot.matrix_from_axis_angle(dp[:3]) @ rot.matrix_from_axis_angle(p[:3])
        return np.concatenate([rot.axis_angle_from_matrix(R), p[3:] + dp[3:]])

    p0 = np.concatenate([rot.axis_angle_from_matrix(init.R), init.translation, [init.scale]])
    names = ("rx", "ry", "rz", "tx", "ty", "tz", "scale")
    adj = solve_dense(fun, p0, weights=w.ravel() / sigma_m**2, update=update, param_names=names,
                      fixed=["scale"] if fix_scale else None, options=options)
    R = rot.matrix_from_axis_angle(adj.x[:3])
    s = float(adj.x[6])
    Tc = adj.x[3:6]
    # un-centre: T = T' − s R m; covariance of T picks up the rotation/scale terms
    T = Tc - s * R @ m
    G = np.eye(7)
    G[3:6, 0:3] = s * rot.skew(R @ m)  # dT/dδ = −s d(exp([δ]×) R m)/dδ = s [R m]×
    G[3:6, 6] = -R @ m
    cov = G @ adj.covariance @ G.T
    covp = G @ adj.covariance_prior @ G.T
    res = adj.residuals.reshape(n, 3)
    return HelmertResult(
        transform=Similarity(s, R, T), param_names=names, covariance=cov, covariance_prior=covp,
        residuals=res, rms=np.sqrt(np.mean(res**2, axis=0)), sigma0=float(adj.sigma0), adjustment=adj,
        outcome=adj.outcome,
    )
