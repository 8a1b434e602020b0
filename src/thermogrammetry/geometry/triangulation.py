"""n-view triangulation: linear (homogeneous DLT on undistorted rays), then least squares in the
image with each camera's full model (distortion included), covariance per point.

Vectorised over points: the linear step is one batched SVD, the refinement one batched
Gauss–Newton/LM (:func:`thermogrammetry.adjustment.dense.solve_dense_batch`) over all points.

Degenerate geometry is reported per point, never raised:

- ``parallel``: the largest angle between the observing rays is below ``min_angle_deg``
  (or the normal matrix is rank deficient) → ``Termination.DEGENERATE``;
- ``behind``: the estimate lies behind (depth ≤ 0) at least one observing camera →
  ``Termination.DEGENERATE``;
- fewer than 2 observing views → ``Termination.TOO_FEW_OBSERVATIONS``.

References
----------
Hartley, R., Zisserman, A. (2004). *Multiple View Geometry*, 2nd ed., §12.2 (linear triangulation).
Förstner, W., Wrobel, B. P. (2016). *Photogrammetric Computer Vision*, §13.4 (precision).
Sawicki, Stein, Więcek (seed 000): 3D pass points from ≥ 2 oriented cameras (eq. 1–2).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .._validate import as_array, check_finite
from ..adjustment.dense import DenseOptions, solve_dense_batch
from ..errors import ShapeError
from ..results import Outcome, Termination
from ._camera import as_camera, point_jacobian
from ._common import sigma_per_coordinate
from .pose import Pose

__all__ = ["TriangulationResult", "triangulate", "triangulate_linear", "reprojection_residuals"]


@dataclass(frozen=True, eq=False)
class TriangulationResult:
    """Result of :func:`triangulate` for N points.

    Attributes
    ----------
    points : ndarray (N, 3)
        World coordinates, metres (NaN where no estimate exists).
    covariance : ndarray (N, 3, 3)
        A posteriori ``σ̂0² Q`` per point (NaN when the point is degenerate). With 2 views the
        redundancy is 1, so σ̂0 of a single point is a poor estimate: prefer ``covariance_prior``
        with a known image precision, or a σ0 pooled over many points.
    covariance_prior : ndarray (N, 3, 3)
        ``σ² Q`` with the a-priori image precision ``sigma_px``.
    sigma0 : ndarray (N,)
    residuals_px : ndarray (V, N, 2)
        Reprojection residuals (projected − measured), NaN where not observed.
    n_views : ndarray (N,) int
    angle_deg : ndarray (N,)
        Largest angle between two observing rays.
    behind : ndarray (N,) bool
    parallel : ndarray (N,) bool
    termination : ndarray (N,) of Termination
    outcome : Outcome
        Summary over all points.
    """

    points: np.ndarray
    covariance: np.ndarray
    covariance_prior: np.ndarray
    sigma0: np.ndarray
    residuals_px: np.ndarray
    n_views: np.ndarray
    angle_deg: np.ndarray
    behind: np.ndarray
    parallel: np.ndarray
    termination: np.ndarray
    outcome: Outcome

    @property
    def ok(self) -> np.ndarray:
        """(N,) True where the point converged and is not degenerate."""
        return np.array([t is Termination.CONVERGED or t is Termination.MAX_ITERATIONS for t in self.termination])

    @property
    def std(self) -> np.ndarray:
        """(N, 3) a-priori standard deviations (from ``sigma_px``)."""
        return np.sqrt(np.clip(np.diagonal(self.covariance_prior, axis1=1, axis2=2), 0, None))

    @property
    def std_posterior(self) -> np.ndarray:
        """(N, 3) a-posteriori standard deviations."""
        return np.sqrt(np.clip(np.diagonal(self.covariance, axis1=1, axis2=2), 0, None))


def _inputs(cameras, poses, xy_px, mask):
    if isinstance(poses, Pose):
        raise ShapeError("poses: expected a sequence of ≥ 2 Pose objects, got a single Pose")
    poses = list(poses)
    V = len(poses)
    if V < 2:
        raise ShapeError(f"poses: expected a sequence of at least 2 poses, got {V}")
    for i, p in enumerate(poses):
        if not isinstance(p, Pose):
            raise ShapeError(f"poses[{i}]: expected a Pose, got {type(p).__name__}")
    if isinstance(cameras, (list, tuple)) and np.shape(np.asarray(cameras, dtype=object)) == (3, 3):
        cameras = np.asarray(cameras, dtype=float)  # a single K written as nested lists
    if isinstance(cameras, (list, tuple)):
        if len(cameras) != V:
            raise ShapeError(f"cameras: {len(cameras)} cameras for {V} poses; expected one per pose (or one shared)")
        cams = [as_camera(c, f"cameras[{i}]") for i, c in enumerate(cameras)]
    else:
        c = as_camera(cameras, "cameras")
        cams = [c] * V
    xy = as_array(xy_px, "xy_px", finite=False)
    if xy.ndim == 2 and xy.shape[-1] == 2 and xy.shape[0] == V:
        xy = xy[:, None, :]
    if xy.ndim != 3 or xy.shape[0] != V or xy.shape[2] != 2:
        raise ShapeError(f"xy_px: expected shape ({V}, N, 2) (views, points, xy), got {xy.shape}")
    N = xy.shape[1]
    if mask is None:
        m = np.ones((V, N), bool)
    else:
        m = np.asarray(mask)
        if m.shape != (V, N) or m.dtype != bool:
            raise ShapeError(f"mask: expected a boolean array of shape ({V}, {N}), got {m.shape} {m.dtype}")
    if np.any(m):
        check_finite(np.where(m[..., None], xy, 0.0), "xy_px")
    return cams, poses, xy, m


def triangulate_linear(cameras, poses: Sequence[Pose], xy_px, *, mask=None):
    """Linear n-view triangulation (homogeneous DLT on undistorted normalised rays).

    Parameters
    ----------
    cameras : Camera, (3, 3) K, or a sequence of them (one per view)
    poses : sequence of Pose (V ≥ 2), cam_from_world
    xy_px : array_like (V, N, 2)
        Measured pixels; entries where ``mask`` is False are ignored (may be NaN).
    mask : array_like (V, N) bool, optional

    Returns
    -------
    points : ndarray (N, 3)
        NaN where fewer than 2 views observe the point.
    w : ndarray (N,)
        Homogeneous coordinate of the normalised solution (≈ 0: intersection at infinity).
    """
    cams, poses, xy, m = _inputs(cameras, poses, xy_px, mask)
    return _linear(cams, poses, xy, m)


def _unproject_all(cams, xy, m):
    """(V, N, 3) undistorted camera-frame rays with z = 1 (zeros where not observed)."""
    V, N = m.shape
    rays = np.zeros((V, N, 3))
    for v, c in enumerate(cams):
        if np.any(m[v]):
            rays[v, m[v]] = c.unproject(xy[v, m[v]])
    return rays


def _linear(cams, poses, xy, m, rays_all=None):
    V, N = m.shape
    centers = np.stack([p.center for p in poses])
    origin = centers.mean(0)
    scale = max(np.linalg.norm(centers - origin, axis=1).mean(), 1e-9)
    A = np.zeros((N, 2 * V, 4))
    if rays_all is None:
        rays_all = _unproject_all(cams, xy, m)
    for v, p in enumerate(poses):
        sel = m[v]
        rays = rays_all[v]
        Pm = np.hstack([scale * p.R, (p.R @ origin + p.t)[:, None]])  # acts on (X'·, 1), X = origin + scale X'
        r1 = rays[:, :1] * Pm[2] - Pm[0]
        r2 = rays[:, 1:2] * Pm[2] - Pm[1]
        # normalise rows so that every view carries equal weight
        r1 /= np.maximum(np.linalg.norm(r1, axis=1, keepdims=True), 1e-300)
        r2 /= np.maximum(np.linalg.norm(r2, axis=1, keepdims=True), 1e-300)
        A[:, 2 * v] = np.where(sel[:, None], r1, 0.0)
        A[:, 2 * v + 1] = np.where(sel[:, None], r2, 0.0)
    _, _, Vt = np.linalg.svd(A)
    h = Vt[:, -1, :]
    w = h[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        Xp = h[:, :3] / w[:, None]
    pts = origin + scale * Xp
    pts[m.sum(0) < 2] = np.nan
    return pts, w


def reprojection_residuals(points_world, cameras, poses, xy_px, mask):
    """Reprojection misclosures of N points in V views and the analytic Jacobian w.r.t. the points.

    Parameters
    ----------
    points_world : ndarray (N, 3)
    cameras : sequence of V Camera-like
    poses : sequence of V Pose
    xy_px : ndarray (V, N, 2)
    mask : ndarray (V, N) bool

    Returns
    -------
    v : ndarray (N, 2V)
        projected − measured (px), per point ordered (view0 x, view0 y, view1 x, ...); 0 where masked.
    J : ndarray (N, 2V, 3)
        ``∂v/∂X = J_cam(X_cam) · R``; 0 where masked.
    """
    N = points_world.shape[0]
    V = len(poses)
    Vr = np.zeros((N, V, 2))
    J = np.zeros((N, V, 2, 3))
    for v in range(V):
        ok = mask[v]
        if not np.any(ok):
            continue
        R, t = poses[v].R, poses[v].t
        if ok.all():  # common case: no fancy indexing (copies) of the whole batch
            uv, Jp = point_jacobian(cameras[v], points_world @ R.T + t)
            Vr[:, v] = uv - xy_px[v]
            J[:, v] = Jp @ R
            continue
        Xc = points_world[ok] @ R.T + t
        uv, Jp = point_jacobian(cameras[v], Xc)
        Vr[ok, v] = uv - xy_px[v, ok]
        J[ok, v] = Jp @ R
    return Vr.reshape(N, 2 * V), J.reshape(N, 2 * V, 3)


def triangulate(
    cameras,
    poses: Sequence[Pose],
    xy_px,
    *,
    mask=None,
    sigma_px: float = 1.0,
    refine: bool = True,
    min_angle_deg: float = 0.01,
    options: DenseOptions | None = None,
) -> TriangulationResult:
    """Triangulate N points from V ≥ 2 oriented cameras, with covariance per point.

    Parameters
    ----------
    cameras : Camera, (3, 3) K, or a sequence of V of them
        Camera models (their distortion is used in the refinement).
    poses : sequence of V Pose
        cam_from_world.
    xy_px : array_like (V, N, 2)
        Measured image coordinates, pixels (OpenCV origin).
    mask : array_like (V, N) bool, optional
        True where view v observes point n; default all. Masked-out entries may be NaN.
    sigma_px : float or array_like (V, N) or (V, N, 2)
        A-priori standard deviation of an image coordinate (px) for the weights and
        ``covariance_prior``; entries where ``mask`` is False are ignored.
    refine : bool
        Least-squares refinement in the image (default). Without it the linear solution is returned
        with the covariance of the linearised model evaluated at it.
    min_angle_deg : float
        Rays meeting at a smaller largest angle are flagged ``parallel``.
    options : DenseOptions, optional

    Returns
    -------
    TriangulationResult

    Raises
    ------
    ShapeError, NonFiniteError
        Wrong shapes; NaN/inf in an observed entry of ``xy_px``.
    """
    cams, poses, xy, m = _inputs(cameras, poses, xy_px, mask)
    V, N = m.shape
    sig = np.asarray(sigma_px, float)
    if sig.shape == (V, N):  # entries of unobserved points are ignored (may be NaN)
        sig = np.where(m, sig, 1.0)
    elif sig.shape == (V, N, 2):
        sig = np.where(m[..., None], sig, 1.0)
    sig = sigma_per_coordinate(sig, (V, N))
    rays_all = _unproject_all(cams, xy, m)
    X0, w = _linear(cams, poses, xy, m, rays_all)
    nviews = m.sum(0)
    few = nviews < 2
    # ray directions (world) for the intersection angle
    dirs = np.zeros((V, N, 3))
    for v, (c, p) in enumerate(zip(cams, poses)):
        if np.any(m[v]):
            r = rays_all[v, m[v]]
            d = r @ p.R  # Rᵀ r
            dirs[v, m[v]] = d / np.linalg.norm(d, axis=1, keepdims=True)
    cosmin = np.ones(N)
    for a in range(V):
        for b in range(a + 1, V):
            both = m[a] & m[b]
            cab = np.einsum("ij,ij->i", dirs[a], dirs[b])
            cosmin = np.where(both, np.minimum(cosmin, cab), cosmin)
    angle = np.degrees(np.arccos(np.clip(cosmin, -1, 1)))
    at_infinity = ~np.isfinite(X0).all(1) | (np.abs(w) < 1e-12)
    parallel = ((angle < min_angle_deg) | at_infinity) & ~few
    X0 = np.where(np.isfinite(X0), X0, 0.0)
    # (N, 2V) in the residual order (view0 x, view0 y, view1 x, ...); 0 where not observed
    weights = np.where(m[..., None], 1.0 / sig**2, 0.0).transpose(1, 0, 2).reshape(N, 2 * V)
    Rs = np.stack([p.R for p in poses])
    ts = np.stack([p.t for p in poses])
    mT = m.T

    def fun(Xb, idx):
        with np.errstate(all="ignore"):  # trial steps may put a point on a camera's principal plane
            return reprojection_residuals(Xb, cams, poses, xy[:, idx], m[:, idx])

    # problems with < 2 views or an intersection at infinity are not solved (kept out of the batch)
    solve_idx = np.flatnonzero(~few & ~at_infinity)
    pts = np.full((N, 3), np.nan)
    cov = np.full((N, 3, 3), np.nan)
    covp = np.full((N, 3, 3), np.nan)
    s0 = np.full(N, np.nan)
    term = np.empty(N, object)
    term[:] = Termination.TOO_FEW_OBSERVATIONS
    resid = np.full((V, N, 2), np.nan)
    if solve_idx.size:
        sub_x = X0[solve_idx]

        def fun_sub(Xb, idx):
            return fun(Xb, solve_idx[idx])

        opt = options or DenseOptions(max_iterations=30 if refine else 1)
        if refine:
            br = solve_dense_batch(fun_sub, sub_x, weights=weights[solve_idx], sigma0_prior=1.0, options=opt)
            Xs, Vres = br.x, br.residuals
            Q, tsub = br.cofactor, br.termination
            s0[solve_idx] = br.sigma0
            cov[solve_idx] = br.covariance  # σ̂0² Q; weights 1/σ² so Q is the a-priori covariance
        else:
            Vres, Jb = fun_sub(sub_x, np.arange(solve_idx.size))
            Jw = Jb * np.sqrt(weights[solve_idx])[..., None]
            N_ = np.einsum("bmi,bmj->bij", Jw, Jw)
            Q = np.linalg.pinv(N_)
            Xs = sub_x
            tsub = np.array([Termination.CONVERGED] * solve_idx.size, object)
        pts[solve_idx] = Xs
        covp[solve_idx] = Q
        term[solve_idx] = tsub
        resid[:, solve_idx] = np.where(mT[solve_idx, :, None], Vres.reshape(-1, V, 2), np.nan).transpose(1, 0, 2)
    # behind-camera test at the estimate
    depth = np.einsum("vij,nj->vni", Rs, np.nan_to_num(pts))[..., 2] + ts[:, None, 2]
    behind = np.any(m & (depth <= 0), axis=0) & ~few
    rank_def = np.array([t is Termination.RANK_DEFICIENT for t in term])
    parallel = parallel | rank_def
    term[parallel | behind] = Termination.DEGENERATE
    cov[parallel | behind] = np.nan
    covp[parallel] = np.nan
    counts = {}
    for t in term:
        counts[t] = counts.get(t, 0) + 1
    if all(t is Termination.CONVERGED for t in term):
        outcome = Outcome(Termination.CONVERGED, f"all {N} points triangulated")
    else:
        first = next(t for t in counts if t is not Termination.CONVERGED)
        detail = ", ".join(f"{t.value}={c}" for t, c in counts.items())
        extra = []
        if parallel.any():
            extra.append(f"{int(parallel.sum())} with (near-)parallel rays (< {min_angle_deg}°)")
        if behind.any():
            extra.append(f"{int(behind.sum())} behind a camera")
        outcome = Outcome(first, detail + ("; " + "; ".join(extra) if extra else ""))
    return TriangulationResult(
        points=pts, covariance=cov, covariance_prior=covp, sigma0=s0, residuals_px=resid,
        n_views=nviews, angle_deg=angle, behind=behind, parallel=parallel, termination=term, outcome=outcome,
    )
