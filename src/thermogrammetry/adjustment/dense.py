"""Dense weighted least squares for small problems (Gauss–Newton with Levenberg–Marquardt damping).

Used by the geometry kernels (DLT refinement, space resection, triangulation, Helmert, planes).
Big sparse problems (bundle adjustment) belong to the sparse engine in this package.

Model (Gauss–Markov, observation equations)::

    l + v = f(x),        P = σ0² Σ_ll⁻¹,        minimise  vᵀ P v
    subject to  h(x) = 0  (optional, hard constraints)

The caller supplies ``fun(x) -> (v, J)`` with the *misclosure* ``v = f(x) − l`` (shape (m,)) and
its analytic Jacobian ``J = ∂v/∂x`` (shape (m, n)) — derivative with respect to the *increment*
that ``update(x, dx)`` applies (additive by default; e.g. a rotation increment for poses).
At the solution ``v`` are the residuals (corrections to the observations).

Precision (Förstner & Wrobel 2016, §4.2; Mikhail 1976):

- cofactor matrix ``Q = N⁻¹`` (``N = JᵀPJ``), restricted to the null space of the constraints:
  ``Q = Z (Zᵀ N Z)⁻¹ Zᵀ`` with ``HZ = 0``;
- a posteriori ``σ̂0² = vᵀPv / r`` with redundancy ``r = m − n_free + n_constraints``;
- ``covariance = σ̂0² Q`` and ``covariance_prior = σ0² Q`` (σ0 = ``sigma0_prior``);
- redundancy numbers ``r_i = diag(I − J Q Jᵀ P)_i`` (sum = r).

Failures are values: a rank-deficient normal matrix (undetermined parameter combination) gives
``Termination.RANK_DEFICIENT`` with the parameters involved named in ``reason`` (estimate kept,
covariances NaN); running out of iterations gives ``MAX_ITERATIONS``; NaN/inf during the solve
gives ``NUMERICAL_FAILURE``. Bad *input* (shapes, non-finite start values) raises.

Also :func:`solve_dense_batch`: many independent problems of the same size solved at once
(vectorised over a leading batch axis; e.g. triangulating thousands of points).

References
----------
Levenberg, K. (1944); Marquardt, D. W. (1963). An algorithm for least-squares estimation of
nonlinear parameters. *J. SIAM* 11(2), 431–441.
Förstner, W., Wrobel, B. P. (2016). *Photogrammetric Computer Vision*, Springer, ch. 4.
Mikhail, E. M. (1976). *Observations and Least Squares*, IEP.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Callable, Sequence

import numpy as np

from .._validate import as_array
from ..errors import ConfigError, InvalidInputError, ShapeError
from ..results import HasOutcome, Outcome, Termination

__all__ = ["DenseOptions", "DenseResult", "DenseBatchResult", "solve_dense", "solve_dense_batch"]


@dataclass(frozen=True)
class DenseOptions:
    """How the dense solver iterates.

    Attributes
    ----------
    max_iterations : int
        Upper limit on Gauss–Newton/LM iterations.
    damping : {"lm", "gauss_newton"}
        ``"lm"``: Levenberg–Marquardt (Marquardt scaling by diag N); ``"gauss_newton"``: undamped steps.
    initial_lambda : float
        Starting LM damping relative to diag N.
    step_tol : float
        Converged when ``‖dx‖ ≤ step_tol · (‖x‖ + step_tol)``.
    cost_tol : float
        Converged when an accepted step lowers the cost by less than ``cost_tol`` relative.
    decrease_tol : float
        Converged when the undamped Gauss–Newton step would lower the cost by less than
        ``decrease_tol`` relative (``gᵀN⁻¹g ≤ decrease_tol · cost``): the estimate is at the
        minimum to within rounding; avoids futile damped trials there.
    rank_tol : float
        Rank deficient when the smallest eigenvalue of the Jacobi-scaled reduced normal matrix
        is below ``rank_tol`` times the largest.
    """

    max_iterations: int = 100
    damping: str = "lm"
    initial_lambda: float = 1e-4
    step_tol: float = 1e-12
    cost_tol: float = 1e-15
    decrease_tol: float = 1e-15
    rank_tol: float = 1e-13

    def __post_init__(self):
        if self.damping not in ("lm", "gauss_newton"):
            raise ConfigError(f"damping: {self.damping!r} is not valid; expected 'lm' or 'gauss_newton'")
        if int(self.max_iterations) < 1:
            raise ConfigError(f"max_iterations: {self.max_iterations!r}; expected an integer ≥ 1")
        for name in ("initial_lambda", "step_tol", "cost_tol", "decrease_tol", "rank_tol"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"{name}: {v!r}; expected a finite number ≥ 0")

    @classmethod
    def from_dict(cls, d: dict) -> "DenseOptions":
        """Build from a mapping; unknown keys raise :class:`ConfigError` listing the valid ones."""
        valid = {f.name for f in fields(cls)}
        bad = sorted(set(d) - valid)
        if bad:
            raise ConfigError(f"unknown dense solver option(s) {bad}; valid keys are {sorted(valid)}")
        return cls(**d)


@dataclass(frozen=True, eq=False)
class DenseResult(HasOutcome):
    """Outcome of :func:`solve_dense`.

    Attributes
    ----------
    x : ndarray (n,)
        Estimate (the last accepted iterate when not converged).
    param_names : tuple[str, ...]
    covariance : ndarray (n, n)
        ``σ̂0² Q`` (a posteriori); NaN when there is no redundancy or the problem is rank deficient.
        Rows/columns of fixed parameters are zero.
    covariance_prior : ndarray (n, n)
        ``σ0² Q`` with the a-priori σ0 (``sigma0_prior``).
    cofactor : ndarray (n, n)
        ``Q``.
    sigma0 : float
        A posteriori σ̂0 (NaN when the redundancy is 0).
    sigma0_prior : float
    residuals : ndarray (m,)
        ``v = f(x̂) − l`` in the units of the observations.
    redundancy_numbers : ndarray (m,)
        ``r_i``; NaN for rows with zero weight.
    redundancy : int
        Degrees of freedom ``r``.
    iterations : int
    cost : float
        ``vᵀ P v`` at the estimate.
    outcome : Outcome
    fixed : ndarray (n,) bool
    """

    x: np.ndarray
    param_names: tuple
    covariance: np.ndarray
    covariance_prior: np.ndarray
    cofactor: np.ndarray
    sigma0: float
    sigma0_prior: float
    residuals: np.ndarray
    redundancy_numbers: np.ndarray
    redundancy: int
    iterations: int
    cost: float
    outcome: Outcome
    fixed: np.ndarray = field(default=None)

    @property
    def std(self) -> np.ndarray:
        """A posteriori standard deviations ``σ̂0 √q_ii``."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0, None))

    @property
    def std_prior(self) -> np.ndarray:
        """A priori standard deviations ``σ0 √q_ii``."""
        return np.sqrt(np.clip(np.diag(self.covariance_prior), 0, None))

    @property
    def correlation(self) -> np.ndarray:
        """Correlation matrix of the estimate (from ``Q``; NaN for fixed parameters)."""
        d = np.sqrt(np.diag(self.cofactor))
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.cofactor / np.outer(d, d)

    def named(self) -> dict:
        """``{name: (value, std)}``."""
        return {n: (float(v), float(s)) for n, v, s in zip(self.param_names, self.x, self.std)}


def _prepare_weights(m: int, weights, cov, sigma0_prior: float):
    """Return (W, kind, valid) where W whitens: rw = W @ v (kind 'full') or w * v (kind 'diag')."""
    if weights is not None and cov is not None:
        raise InvalidInputError("give either weights or cov (observation covariance), not both")
    if cov is None:
        if weights is None:
            w = np.ones(m)
        else:
            w = as_array(weights, "weights")
            if w.shape != (m,):
                raise ShapeError(f"weights: expected shape ({m},) (one per observation), got {w.shape}")
            if np.any(w < 0):
                raise InvalidInputError(f"weights: negative weight {w[w < 0][0]!r}; expected weights ≥ 0")
        return np.sqrt(w), "diag", w > 0
    S = as_array(cov, "cov")
    if S.shape == (m,):
        if np.any(S <= 0):
            raise InvalidInputError(f"cov: non-positive variance {S[S <= 0][0]!r}; expected variances > 0")
        return sigma0_prior / np.sqrt(S), "diag", np.ones(m, bool)
    if S.shape != (m, m):
        raise ShapeError(f"cov: expected shape ({m},) variances or ({m}, {m}), got {S.shape}")
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        raise InvalidInputError("cov: observation covariance is not positive definite") from None
    W = sigma0_prior * np.linalg.inv(L)  # WᵀW = σ0² Σ⁻¹ = P
    return W, "full", np.ones(m, bool)


def _null_space(H: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal basis Z of null(H) (n × (n−k)) and pseudo-inverse of H."""
    if H.shape[0] == 0:
        return np.eye(n), np.zeros((n, 0))
    U, s, Vt = np.linalg.svd(H)
    k = int(np.sum(s > 1e-12 * max(s.max(), 1e-300)))
    Z = Vt[k:].T
    Hpinv = np.linalg.pinv(H, rcond=1e-12)
    return Z, Hpinv


def solve_dense(
    fun: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    x0,
    *,
    weights=None,
    cov=None,
    sigma0_prior: float = 1.0,
    fixed=None,
    constraints: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
    update: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    param_names: Sequence[str] | None = None,
    options: DenseOptions | None = None,
) -> DenseResult:
    """Weighted least squares by Gauss–Newton / Levenberg–Marquardt with full precision output.

    Parameters
    ----------
    fun : callable
        ``fun(x) -> (v, J)``: misclosures ``f(x) − l`` (m,) and Jacobian (m, n) w.r.t. the increment.
    x0 : array_like (n,)
        Start values.
    weights : array_like (m,), optional
        Diagonal weights ``p_i = σ0²/σ_i²`` (0 excludes a row). Default: all 1.
    cov : array_like (m,) or (m, m), optional
        Observation variances or covariance matrix (units² of the observations); then
        ``P = σ0² Σ⁻¹``. Mutually exclusive with ``weights``.
    sigma0_prior : float
        A-priori standard deviation of unit weight σ0.
    fixed : array_like (n,) bool or sequence of int/str, optional
        Parameters kept at their start values.
    constraints : callable, optional
        ``h(x) -> (h (k,), H (k, n))``: hard constraints ``h(x) = 0`` with Jacobian w.r.t. the increment.
    update : callable, optional
        ``update(x, dx) -> x_new``; default ``x + dx``.
    param_names : sequence of str, optional
    options : DenseOptions, optional

    Returns
    -------
    DenseResult
    """
    opt = options or DenseOptions()
    x = as_array(x0, "x0").astype(float).copy()
    if x.ndim != 1:
        raise ShapeError(f"x0: expected shape (n,), got {x.shape}")
    n = x.size
    names = tuple(param_names) if param_names is not None else tuple(f"x{i}" for i in range(n))
    if len(names) != n:
        raise ShapeError(f"param_names: {len(names)} names for {n} parameters")
    if not (np.isfinite(sigma0_prior) and sigma0_prior > 0):
        raise InvalidInputError(f"sigma0_prior: {sigma0_prior!r}; expected a finite number > 0")
    fixed_mask = np.zeros(n, bool)
    if fixed is not None:
        fx = list(fixed) if not isinstance(fixed, np.ndarray) else fixed
        if isinstance(fx, np.ndarray) and fx.dtype == bool:
            if fx.shape != (n,):
                raise ShapeError(f"fixed: boolean mask of shape {fx.shape}; expected ({n},)")
            fixed_mask = fx.copy()
        else:
            for f in fx:
                if isinstance(f, str):
                    if f not in names:
                        raise InvalidInputError(f"fixed: unknown parameter {f!r}; expected one of {names}")
                    fixed_mask[names.index(f)] = True
                else:
                    fixed_mask[int(f)] = True
    free = np.flatnonzero(~fixed_mask)
    upd = update or (lambda xx, dx: xx + dx)

    def evaluate(xx):
        v, J = fun(xx)
        v = np.asarray(v, float).ravel()
        J = np.asarray(J, float)
        return v, J

    v, J = evaluate(x)
    m = v.size
    if J.shape != (m, n):
        raise ShapeError(f"fun: Jacobian has shape {J.shape}; expected ({m}, {n}) for {m} observations and {n} parameters")
    W, kind, valid = _prepare_weights(m, weights, cov, sigma0_prior)

    def whiten(v, J):
        if kind == "diag":
            return W * v, W[:, None] * J
        return W @ v, W @ J

    def cons(xx):
        if constraints is None:
            return np.zeros(0), np.zeros((0, n))
        h, H = constraints(xx)
        return np.asarray(h, float).ravel(), np.asarray(H, float).reshape(-1, n)

    def fail(term, reason, it):
        nanm = np.full((n, n), np.nan)
        return DenseResult(x, names, nanm, nanm.copy(), nanm.copy(), np.nan, sigma0_prior, v, np.full(m, np.nan),
                           0, it, np.nan, Outcome(term, reason), fixed_mask)

    if not (np.all(np.isfinite(v)) and np.all(np.isfinite(J))):
        return fail(Termination.NUMERICAL_FAILURE, "non-finite residuals or Jacobian at the start values", 0)
    h, H = cons(x)
    k_cons = h.size
    n_obs = int(np.sum(valid))
    redundancy = n_obs - free.size + k_cons
    if n_obs + k_cons < free.size:
        return fail(Termination.TOO_FEW_OBSERVATIONS,
                    f"{n_obs} observations and {k_cons} constraints for {free.size} free parameters", 0)

    rw, Jw = whiten(v, J)
    cost = float(rw @ rw)
    rho = 1e8 * max(cost, 1.0)  # penalty weight of constraint violation in the acceptance test
    merit = cost + rho * float(h @ h)
    lam = opt.initial_lambda if opt.damping == "lm" else 0.0
    term, reason = Termination.MAX_ITERATIONS, f"no convergence within {opt.max_iterations} iterations"
    it = 0
    for it in range(1, opt.max_iterations + 1):
        Jf = Jw[:, free]
        N = Jf.T @ Jf
        g = Jf.T @ rw
        d = np.diag(N).copy()
        d[d <= 0] = 1.0
        Ds = 1.0 / np.sqrt(d)
        Ns = N * np.outer(Ds, Ds)
        gs = g * Ds
        Hs = H[:, free] * Ds[None, :]
        Z, Hpinv = _null_space(Hs, free.size)
        yp = -Hpinv @ h if k_cons else np.zeros(free.size)
        if k_cons == 0 or float(h @ h) <= 1e-24:
            A0 = Z.T @ Ns @ Z
            b0 = -Z.T @ gs
            try:
                pred = float(b0 @ np.linalg.solve(A0, b0))
            except np.linalg.LinAlgError:
                pred = np.inf
            if np.isfinite(pred) and pred <= opt.decrease_tol * cost:
                term, reason = Termination.CONVERGED, "predicted decrease below decrease_tol (at the minimum)"
                it -= 1
                break
        accepted = False
        for _ in range(30):
            A = Z.T @ (Ns + lam * np.eye(free.size)) @ Z
            b = -Z.T @ (gs + (Ns + lam * np.eye(free.size)) @ yp)
            try:
                w = np.linalg.solve(A, b)
            except np.linalg.LinAlgError:
                w = np.linalg.lstsq(A, b, rcond=None)[0]
            dxf = Ds * (yp + Z @ w)
            dx = np.zeros(n)
            dx[free] = dxf
            if not np.all(np.isfinite(dx)):
                return fail(Termination.NUMERICAL_FAILURE, "non-finite step (singular normal equations)", it)
            x_new = upd(x, dx)
            try:
                v_new, J_new = evaluate(x_new)
                h_new, H_new = cons(x_new)
            except (FloatingPointError, np.linalg.LinAlgError):
                v_new = np.full(m, np.nan)
                J_new = J
                h_new, H_new = h, H
            ok = np.all(np.isfinite(v_new)) and np.all(np.isfinite(J_new))
            if ok:
                rw_new, Jw_new = whiten(v_new, J_new)
                cost_new = float(rw_new @ rw_new)
                merit_new = cost_new + rho * float(h_new @ h_new)
            if ok and (merit_new <= merit * (1 + 1e-12) or opt.damping == "gauss_newton"):
                accepted = True
                break
            if opt.damping == "gauss_newton":
                return fail(Termination.NUMERICAL_FAILURE, "non-finite residuals after a Gauss-Newton step", it)
            lam = max(lam * 10.0, 1e-8)
        if not accepted:
            term, reason = Termination.CONVERGED, "no further decrease of the cost possible (damping exhausted)"
            break
        step_small = np.linalg.norm(dx) <= opt.step_tol * (np.linalg.norm(x) + opt.step_tol)
        cost_small = (merit - merit_new) <= opt.cost_tol * max(merit, 1e-300)
        x, v, J, rw, Jw, h, H = x_new, v_new, J_new, rw_new, Jw_new, h_new, H_new
        merit, cost = merit_new, cost_new
        if opt.damping == "lm":
            lam = max(lam / 10.0, 1e-12)
        if step_small or cost_small or cost < 1e-30 * max(m, 1):
            term, reason = Termination.CONVERGED, "step below step_tol" if step_small else "cost change below cost_tol"
            break
        if opt.damping == "gauss_newton" and not np.isfinite(cost):
            return fail(Termination.DIVERGED, "cost became non-finite", it)

    # ---- precision at the estimate --------------------------------------------------------------
    Jf = Jw[:, free]
    N = Jf.T @ Jf
    d = np.diag(N).copy()
    zero_cols = d <= 0
    d[zero_cols] = 1.0
    Ds = 1.0 / np.sqrt(d)
    Ns = N * np.outer(Ds, Ds)
    Z, _ = _null_space(H[:, free] * Ds[None, :], free.size)
    Nr = Z.T @ Ns @ Z
    ev, evec = np.linalg.eigh(Nr)
    Q = np.full((n, n), np.nan)
    deficient = zero_cols.any() or ev.size == 0 or ev[0] <= opt.rank_tol * max(ev[-1], 1e-300)
    if deficient:
        if zero_cols.any():
            involved = [names[free[i]] for i in np.flatnonzero(zero_cols)]
        else:
            nullvec = Z @ evec[:, 0]
            big = np.abs(nullvec) > 0.1 * np.abs(nullvec).max()
            involved = [names[free[i]] for i in np.flatnonzero(big)]
        rw_final = rw
        nanm = np.full((n, n), np.nan)
        return DenseResult(
            x, names, nanm, nanm.copy(), nanm.copy(), float(np.sqrt(rw_final @ rw_final / redundancy)) if redundancy > 0 else np.nan,
            sigma0_prior, v, np.full(m, np.nan), redundancy, it, cost,
            Outcome(Termination.RANK_DEFICIENT,
                    f"normal matrix is rank deficient (condition {ev[-1] / max(ev[0], 1e-300):.3g}); "
                    f"undetermined combination of {involved}"),
            fixed_mask,
        )
    Qr = (evec / ev) @ evec.T
    Qf = (Ds[:, None] * (Z @ Qr @ Z.T)) * Ds[None, :]
    Q = np.zeros((n, n))
    Q[np.ix_(free, free)] = Qf
    # redundancy numbers diag(I − J Q Jᵀ P) computed in whitened form: 1 − diag(Jw Q Jwᵀ) for diagonal P
    if kind == "diag":
        JQJ = ((Jf @ Qf) * Jf).sum(axis=1)  # diag(J Q Jᵀ) through BLAS
        rn = np.where(valid, 1.0 - JQJ, np.nan)
    else:
        Jl = J[:, free]
        P = W.T @ W
        rn = 1.0 - ((Jl @ Qf @ Jl.T) * P.T).sum(axis=1)  # diag(J Q Jᵀ P)
    if redundancy > 0:
        s02 = cost / redundancy
        cov_post = s02 * Q
        sigma0 = float(np.sqrt(s02))
    else:
        cov_post = np.full((n, n), np.nan)
        sigma0 = np.nan
        reason = reason + "; no redundancy: a-posteriori sigma0 undefined"
    return DenseResult(x, names, cov_post, sigma0_prior**2 * Q, Q, sigma0, float(sigma0_prior), v, rn,
                       int(redundancy), it, cost, Outcome(term, reason), fixed_mask)


# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class DenseBatchResult:
    """Outcome of :func:`solve_dense_batch` for B independent problems.

    Attributes
    ----------
    x : ndarray (B, n)
    covariance, covariance_prior, cofactor : ndarray (B, n, n)
        NaN for rank-deficient problems; ``covariance`` NaN where the redundancy is 0.
    sigma0 : ndarray (B,)
    residuals, redundancy_numbers : ndarray (B, m)
    redundancy : ndarray (B,) int
    iterations : int
    termination : ndarray (B,) object of Termination
    outcome : Outcome
        Overall: CONVERGED when every problem converged, otherwise the first failure kind with counts.
    """

    x: np.ndarray
    covariance: np.ndarray
    covariance_prior: np.ndarray
    cofactor: np.ndarray
    sigma0: np.ndarray
    sigma0_prior: float
    residuals: np.ndarray
    redundancy_numbers: np.ndarray
    redundancy: np.ndarray
    iterations: int
    termination: np.ndarray
    condition: np.ndarray
    outcome: Outcome

    @property
    def success(self) -> np.ndarray:
        return np.array([t.success for t in self.termination], bool)


def solve_dense_batch(
    fun: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    x0,
    *,
    weights=None,
    sigma0_prior: float = 1.0,
    options: DenseOptions | None = None,
) -> DenseBatchResult:
    """Solve B independent small least-squares problems of equal size at once.

    Parameters
    ----------
    fun : callable
        ``fun(X (b, n), idx (b,)) -> (V (b, m), J (b, m, n))`` for the problems ``idx`` (indices into
        the batch; the solver evaluates only the problems still iterating). Additive parameters.
    x0 : array_like (B, n)
    weights : array_like (B, m), optional
        Diagonal weights (0 marks a missing observation); default 1.
    sigma0_prior : float
    options : DenseOptions, optional

    Returns
    -------
    DenseBatchResult
        Per-problem termination: CONVERGED, MAX_ITERATIONS, RANK_DEFICIENT (condition of the scaled
        normal matrix above ``1/rank_tol``), TOO_FEW_OBSERVATIONS or NUMERICAL_FAILURE.
    """
    opt = options or DenseOptions()
    X = as_array(x0, "x0").astype(float).copy()
    if X.ndim != 2:
        raise ShapeError(f"x0: expected shape (B, n), got {X.shape}")
    B, n = X.shape
    V, J = fun(X, np.arange(B))
    m = V.shape[1]
    if J.shape != (B, m, n):
        raise ShapeError(f"fun: Jacobian has shape {J.shape}; expected ({B}, {m}, {n})")
    if weights is None:
        w = np.ones((B, m))
    else:
        w = as_array(weights, "weights")
        if w.shape != (B, m):
            raise ShapeError(f"weights: expected shape ({B}, {m}), got {w.shape}")
        if np.any(w < 0):
            raise InvalidInputError("weights: negative weight; expected weights ≥ 0")
    sw = np.sqrt(w)
    valid = w > 0
    n_obs = valid.sum(1)
    redundancy = n_obs - n

    def cost_of(V, sel):
        Vm = np.where(valid[sel], V, 0.0)
        with np.errstate(over="ignore", invalid="ignore"):
            c = np.sum(w[sel] * Vm**2, axis=1)
        return np.where(np.all(np.isfinite(Vm), axis=1), c, np.inf)

    V = np.where(valid, V, 0.0)
    J = np.where(valid[..., None], J, 0.0)
    cost = cost_of(V, np.arange(B))
    active = np.isfinite(cost) & (redundancy >= 0)
    lam = np.full(B, opt.initial_lambda if opt.damping == "lm" else 0.0)
    done = ~active
    conv = np.zeros(B, bool)
    eye = np.eye(n)
    it = 0
    for it in range(1, opt.max_iterations + 1):
        idx = np.flatnonzero(~done)
        if idx.size == 0:
            break
        Jw = sw[idx, :, None] * J[idx]
        rw = sw[idx] * V[idx]
        JwT = Jw.transpose(0, 2, 1)
        N = JwT @ Jw  # batched matmul: much faster than einsum for these small blocks
        g = (JwT @ rw[..., None])[..., 0]
        d = np.diagonal(N, axis1=1, axis2=2).copy()
        d[d <= 0] = 1.0
        Ds = 1.0 / np.sqrt(d)
        Ns = N * Ds[:, :, None] * Ds[:, None, :]
        gs = g * Ds
        # at the minimum already (the Gauss–Newton step would not lower the cost measurably)?
        try:
            ygn = np.linalg.solve(Ns + 1e-14 * eye, -gs[..., None])[..., 0]
            pred = -np.einsum("bi,bi->b", gs, ygn)
        except np.linalg.LinAlgError:
            pred = np.full(idx.size, np.inf)
        at_min = np.isfinite(pred) & (pred <= opt.decrease_tol * cost[idx])
        if np.any(at_min):
            conv[idx[at_min]] = True
            done[idx[at_min]] = True
            keep = ~at_min
            idx, Ns, gs, Ds = idx[keep], Ns[keep], gs[keep], Ds[keep]
            if idx.size == 0:
                break
        pending = np.ones(idx.size, bool)
        X_new = X[idx].copy()
        V_new = V[idx].copy()
        J_new = J[idx].copy()
        c_new = cost[idx].copy()
        dx_all = np.zeros((idx.size, n))
        for _ in range(30):
            p = np.flatnonzero(pending)
            if p.size == 0:
                break
            A = Ns[p] + lam[idx[p], None, None] * eye
            try:
                y = np.linalg.solve(A, -gs[p][..., None])[..., 0]
            except np.linalg.LinAlgError:
                y = np.einsum("bij,bj->bi", np.linalg.pinv(A), -gs[p])
            dx = y * Ds[p]
            Xt = X[idx[p]] + dx
            Vt, Jt = fun(Xt, idx[p])
            Vt = np.where(valid[idx[p]], Vt, 0.0)
            Jt = np.where(valid[idx[p]][..., None], Jt, 0.0)
            ct = cost_of(Vt, idx[p])
            acc = (ct <= cost[idx[p]] * (1 + 1e-12)) | (opt.damping == "gauss_newton")
            acc &= np.isfinite(ct) & np.all(np.isfinite(Jt), axis=(1, 2))
            a = p[acc]
            X_new[a], V_new[a], J_new[a], c_new[a], dx_all[a] = Xt[acc], Vt[acc], Jt[acc], ct[acc], dx[acc]
            pending[a] = False
            rej = p[~acc]
            lam[idx[rej]] = np.maximum(lam[idx[rej]] * 10.0, 1e-8)
        stalled = pending  # damping exhausted: cannot decrease -> converged at a minimum
        step_small = np.linalg.norm(dx_all, axis=1) <= opt.step_tol * (np.linalg.norm(X_new, axis=1) + opt.step_tol)
        cost_small = (cost[idx] - c_new) <= opt.cost_tol * np.maximum(cost[idx], 1e-300)
        tiny = c_new < 1e-30 * m
        X[idx], V[idx], J[idx], cost[idx] = X_new, V_new, J_new, c_new
        if opt.damping == "lm":
            lam[idx] = np.maximum(lam[idx] / 10.0, 1e-12)
        fin = stalled | step_small | (cost_small & ~pending) | tiny
        conv[idx[fin]] = True
        done[idx[fin]] = True

    term = np.empty(B, object)
    term[:] = Termination.MAX_ITERATIONS
    term[conv] = Termination.CONVERGED
    term[~np.isfinite(cost)] = Termination.NUMERICAL_FAILURE
    term[redundancy < 0] = Termination.TOO_FEW_OBSERVATIONS

    Jw = sw[..., None] * J
    N = Jw.transpose(0, 2, 1) @ Jw
    d = np.diagonal(N, axis1=1, axis2=2).copy()
    zero = np.any(d <= 0, axis=1)
    d[d <= 0] = 1.0
    Ds = 1.0 / np.sqrt(d)
    Ns = N * Ds[:, :, None] * Ds[:, None, :]
    Ns = np.where(np.isfinite(Ns), Ns, 0.0)
    ev, evec = np.linalg.eigh(Ns)
    with np.errstate(divide="ignore", invalid="ignore"):
        condition = ev[:, -1] / ev[:, 0]
    deficient = zero | (ev[:, 0] <= opt.rank_tol * np.maximum(ev[:, -1], 1e-300))
    ok_term = np.array([t in (Termination.CONVERGED, Termination.MAX_ITERATIONS) for t in term], bool)
    term[deficient & ok_term] = Termination.RANK_DEFICIENT
    evs = np.where(deficient[:, None], 1.0, ev)
    Qs = (evec / evs[:, None, :]) @ evec.transpose(0, 2, 1)
    Q = Qs * Ds[:, :, None] * Ds[:, None, :]
    Q[deficient] = np.nan
    JQJ = np.sum((Jw @ Q) * Jw, axis=2)
    rn = np.where(valid, 1.0 - JQJ, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        s02 = np.where(redundancy > 0, cost / np.maximum(redundancy, 1), np.nan)
    cov_post = s02[:, None, None] * Q
    counts = {t: int(np.sum(term == t)) for t in Termination if np.any(term == t)}
    if all(t == Termination.CONVERGED for t in term):
        outcome = Outcome(Termination.CONVERGED, f"all {B} problems converged")
    else:
        worst = next(t for t in counts if t != Termination.CONVERGED)
        outcome = Outcome(worst, "per-problem terminations: " + ", ".join(f"{t.value}={c}" for t, c in counts.items()))
    return DenseBatchResult(X, cov_post, sigma0_prior**2 * Q, Q, np.sqrt(s02), float(sigma0_prior), V, rn,
                            redundancy, it, term, condition, outcome)
