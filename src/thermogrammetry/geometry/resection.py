"""Space resection: exterior orientation of one image from control points, known (or partly
unknown) interior orientation, with the covariance of the six parameters and of the projection centre.

1. **Initial pose**: a linear DLT on the undistorted normalised rays (≥ 6 non-coplanar points;
   Abdel-Aziz & Karara 1971), or — for few, coplanar or nearly coplanar points — *every* start
   of OpenCV's SQPnP (Terzakis & Lourakis 2020), both IPPE solutions on the best-fitting plane
   (Collins & Bartoli 2014) and, for 4 points, P3P; or a pose given by the caller.
   Each start is refined (step 2) and the refined pose with the smallest vᵀPv and all points in
   front of the camera is kept. A (nearly) planar field seen under weak perspective has two
   local minima, the second a reflection of the first (the "flip" ambiguity); when a distinct
   second minimum also passes the global test (vᵀPv ≤ χ²₀.₉₉(r)·max(1, σ̂0²)), the result is
   ``Termination.DEGENERATE`` with reason "ambiguous pose: ..." and both poses are reported
   (``alternatives``) instead of a confident, possibly mirrored, estimate.
2. **Least squares** on the collinearity equations in the image (the camera's full model, distortion
   included): parameters are a world-frame rotation increment δ (``R ← R·exp([δ]×)``) and the
   projection centre ``C``; optionally interior parameters of the camera (e.g. c, x0, y0).
3. **Precision**: covariance of (δ, C) from the adjustment; converted to (ω, φ, κ, X0, Y0, Z0) with
   the analytic Jacobian of :func:`~thermogrammetry.geometry.rotations.opk_to_increment_jacobian`.

References
----------
Kraus, K. (2007). *Photogrammetry*, 2nd ed., §4.2 (spatial resection).
Abdel-Aziz, Y. I., Karara, H. M. (1971). Direct linear transformation ... (seed 000 ref. [1]).
Collins, T., Bartoli, A. (2014). Infinitesimal plane-based pose estimation. *IJCV* 109, 252–286 (IPPE).
Terzakis, G., Lourakis, M. (2020). A consistently fast and globally optimal solution to the
perspective-n-point problem. ECCV 2020 (SQPnP).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .._validate import as_points
from ..adjustment.dense import DenseOptions, DenseResult, solve_dense
from ..errors import InvalidInputError, ShapeError, TooFewPointsError
from ..results import HasOutcome, Outcome, Termination
from . import rotations as rot
from ._camera import as_camera, point_jacobian
from .dlt import _COPLANAR_TOL, decompose_projection, dlt_linear
from ._common import sigma_per_coordinate
from .pose import Pose

__all__ = ["ResectionResult", "resection", "collinearity_residuals"]

_DEFAULT_INTERIOR = {
    "photogrammetric": ("c_mm", "x0_mm", "y0_mm"),
    "opencv": ("fx", "fy", "cx", "cy"),
    "pinhole": ("fx", "fy", "cx", "cy"),
}


@dataclass(frozen=True, eq=False)
class ResectionResult(HasOutcome):
    """Result of :func:`resection`.

    Attributes
    ----------
    pose : Pose
        cam_from_world.
    camera : Camera-like
        The camera (with refined interior parameters when they were free).
    omega, phi, kappa : float
        Radians; ``center`` (3,) metres.
    covariance_opk : ndarray (6, 6)
        A posteriori covariance of (ω, φ, κ, X0, Y0, Z0) (rad², m²).
    covariance_opk_prior : ndarray (6, 6)
        Same with the a-priori image precision ``sigma_px``.
    covariance_increment : ndarray (6, 6)
        A posteriori covariance of (δx, δy, δz, X0, Y0, Z0), δ a small world-frame rotation (no gimbal lock).
    center_covariance, center_covariance_prior : ndarray (3, 3)
    interior_names : tuple, interior : ndarray, interior_std, interior_std_prior : ndarray
        Free interior parameters (empty when the interior orientation was fixed).
    residuals_px : ndarray (N, 2)
    rms_px, sigma0 : float
    init_method : str
        ``"dlt"``, ``"sqpnp"`` (minimal/planar starts) or ``"given"``.
    adjustment : DenseResult
    outcome : Outcome
        ``Termination.DEGENERATE`` with a reason starting ``"ambiguous pose"`` when ``ambiguous``.
    start : str
        The start the returned estimate was refined from: ``"dlt"``, ``"sqpnp"``, ``"ippe"``,
        ``"p3p"`` or ``"given"``.
    ambiguous : bool
        A distinct pose with all points in front fits the observations about as well (flip
        ambiguity of (nearly) coplanar points; test in :func:`_alternatives`). The best pose is
        still returned, but ``success`` is False.
    alternatives : tuple of (Pose, rms_px, centre_distance_m, cost)
        The other distinct refined local minima, best first.
    """

    pose: Pose
    camera: object
    omega: float
    phi: float
    kappa: float
    center: np.ndarray
    covariance_opk: np.ndarray
    covariance_opk_prior: np.ndarray
    covariance_increment: np.ndarray
    center_covariance: np.ndarray
    center_covariance_prior: np.ndarray
    interior_names: tuple
    interior: np.ndarray
    interior_std: np.ndarray
    interior_std_prior: np.ndarray
    residuals_px: np.ndarray
    rms_px: float
    sigma0: float
    init_method: str
    adjustment: DenseResult
    outcome: Outcome
    start: str = ""
    ambiguous: bool = False
    alternatives: tuple = ()

    @property
    def center_std(self) -> np.ndarray:
        """A posteriori σ of X0, Y0, Z0 (m)."""
        return np.sqrt(np.clip(np.diag(self.center_covariance), 0, None))

    @property
    def center_std_prior(self) -> np.ndarray:
        """A priori σ of X0, Y0, Z0 (m) from ``sigma_px``."""
        return np.sqrt(np.clip(np.diag(self.center_covariance_prior), 0, None))

    @property
    def opk_std(self) -> np.ndarray:
        """A posteriori σ of (ω, φ, κ) in radians."""
        return np.sqrt(np.clip(np.diag(self.covariance_opk)[:3], 0, None))


# Control fields flatter than this (smallest / largest singular value of the centred points) also
# get the planar starts (IPPE, SQPnP) next to the DLT: the DLT is ill-conditioned there and a
# near-planar field has a second, mirrored pose that fits almost as well (see ``resection``).
_FLAT_RATIO = 0.1
# Ambiguity test level: a distinct alternative pose whose weighted squared residual sum passes the
# global test at this level is as compatible with the observations as the best one.
_AMBIGUITY_ALPHA = 0.01


def _pose_from_cv(rvec, tvec, A, origin):
    """World pose from an OpenCV pose of the points ``Xp = A (X − origin)`` (A orthonormal)."""
    rv, tv = np.asarray(rvec, float).ravel(), np.asarray(tvec, float).ravel()
    if not (np.all(np.isfinite(rv)) and np.all(np.isfinite(tv))):
        return None
    R = rot.matrix_from_axis_angle(rv) @ A
    return Pose(R, tv - R @ origin)


def _start_candidates(cam, X, x, method):
    """Start poses ``[(Pose, name), ...]`` and the family name (``"dlt"`` or ``"sqpnp"``).

    ``"dlt"``: the linear DLT (≥ 6 non-coplanar points). ``"sqpnp"`` (few, coplanar or nearly
    coplanar points): SQPnP, both IPPE solutions of the points projected onto their best-fitting
    plane (Collins & Bartoli 2014: a planar pose has two local minima, the second one a reflection
    about a plane), and for exactly 4 points all P3P solutions. ``"auto"`` on a flat field
    (``s3/s1 < _FLAT_RATIO``) with ≥ 6 points tries the DLT and the planar starts.
    """
    rays = cam.unproject(x)
    xn = rays[:, :2] / rays[:, 2:3]
    if not np.all(np.isfinite(xn)):
        return [], "sqpnp"
    origin = X.mean(0)
    c = X - origin
    _, sv, Vt = np.linalg.svd(c, full_matrices=False)
    ratio = sv[2] / sv[0] if sv[0] > 0 else 0.0
    coplanar = ratio < _COPLANAR_TOL
    if method == "auto":
        method = "dlt" if (X.shape[0] >= 6 and not coplanar) else "sqpnp"
        planar_too = method == "dlt" and ratio < _FLAT_RATIO
    else:
        planar_too = False
    cands = []
    if method == "dlt":
        P = dlt_linear(X, xn)
        _, R, C = decompose_projection(P)
        cands.append((Pose.from_center(R, C), "dlt"))
        if not planar_too:
            return cands, "dlt"
    import cv2

    xn64 = np.ascontiguousarray(xn, np.float64)
    eye = np.eye(3)
    ident = np.eye(3)
    try:
        n_sol, rvecs, tvecs, _ = cv2.solvePnPGeneric(np.ascontiguousarray(c), xn64, eye, None, flags=cv2.SOLVEPNP_SQPNP)
        cands += [(_pose_from_cv(rv, tv, ident, origin), "sqpnp") for rv, tv in zip(rvecs[:n_sol], tvecs[:n_sol])]
    except cv2.error:
        pass
    if X.shape[0] >= 4 and sv[1] > 1e-9 * sv[0]:
        # IPPE works on exactly planar points: use the in-plane coordinates of the best-fitting plane
        A = Vt if np.linalg.det(Vt) > 0 else Vt * np.array([1.0, 1.0, -1.0])[:, None]
        plane = c @ A.T
        plane[:, 2] = 0.0
        try:
            n_sol, rvecs, tvecs, _ = cv2.solvePnPGeneric(np.ascontiguousarray(plane), xn64, eye, None, flags=cv2.SOLVEPNP_IPPE)
            cands += [(_pose_from_cv(rv, tv, A, origin), "ippe") for rv, tv in zip(rvecs[:n_sol], tvecs[:n_sol])]
        except cv2.error:
            pass
    if X.shape[0] == 4:
        try:
            n_sol, rvecs, tvecs, _ = cv2.solvePnPGeneric(np.ascontiguousarray(c), xn64, eye, None, flags=cv2.SOLVEPNP_P3P)
            cands += [(_pose_from_cv(rv, tv, ident, origin), "p3p") for rv, tv in zip(rvecs[:n_sol], tvecs[:n_sol])]
        except cv2.error:
            pass
    good = [(p, nm) for p, nm in cands if p is not None]
    return good, "dlt" if method == "dlt" else "sqpnp"


def _rodrigues(r):
    """(3, 3) rotation from one Rodrigues vector: :func:`rotations.matrix_from_axis_angle` without
    the input validation and batching (called in every iteration)."""
    x, y, z = r
    th2 = x * x + y * y + z * z
    if th2 < 1e-8:
        a = 1.0 - th2 / 6.0 + th2 * th2 / 120.0
        b = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
    else:
        th = np.sqrt(th2)
        a = np.sin(th) / th
        b = (1.0 - np.cos(th)) / th2
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + a * K + b * (K @ K)


def _rvec(R):
    """Rodrigues vector of one rotation matrix (Shepperd's quaternion, then ``2 atan2(|v|, w)``):
    :func:`rotations.axis_angle_from_matrix` without validation and batching."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    tr = r00 + r11 + r22
    if tr >= max(r00, r11, r22):
        w4 = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        w, x, y, z = w4 / 4, (r21 - r12) / w4, (r02 - r20) / w4, (r10 - r01) / w4
    elif r00 >= r11 and r00 >= r22:
        x4 = 2.0 * math.sqrt(max(1.0 + r00 - r11 - r22, 0.0))
        w, x, y, z = (r21 - r12) / x4, x4 / 4, (r01 + r10) / x4, (r02 + r20) / x4
    elif r11 >= r22:
        y4 = 2.0 * math.sqrt(max(1.0 - r00 + r11 - r22, 0.0))
        w, x, y, z = (r02 - r20) / y4, (r01 + r10) / y4, y4 / 4, (r12 + r21) / y4
    else:
        z4 = 2.0 * math.sqrt(max(1.0 - r00 - r11 + r22, 0.0))
        w, x, y, z = (r10 - r01) / z4, (r02 + r20) / z4, (r12 + r21) / z4, z4 / 4
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    sv = math.sqrt(x * x + y * y + z * z)
    if sv < 1e-300:
        return np.zeros(3)
    f = 2.0 * math.atan2(sv, w) / sv
    return np.array([x * f, y * f, z * f])


def _flatness(X):
    s = np.linalg.svd(X - X.mean(0), compute_uv=False)
    return s[2] / s[0] if s[0] > 0 else 0.0


def _alternatives(refined, best_i, X, adj):
    """Distinct refined poses other than the best, and those that make the result ambiguous.

    Distinct: projection centre more than ``max(3 σ_C, 1e-6 D)`` away from the best one (σ_C the
    a-priori standard deviation of the best centre along the difference, D the mean distance to the
    points), or the rotation differs by more than ``max(3 σ_rot, 1e-6)`` rad. Ambiguous: such a pose
    has all points in front and its weighted squared residual sum passes the global test,
    ``vᵀPv ≤ χ²_{1−α}(r) · max(1, σ̂0²)`` with σ̂0² of the best pose (``r`` = redundancy, at least 1;
    α = ``_AMBIGUITY_ALPHA``): at the stated image precision — or at the precision the best pose
    shows, when that is worse — the observations do not tell the two poses apart.

    Returns ``([(Pose, rms_px, centre_distance_m, cost), ...] sorted by cost, ambiguous subset)``.
    """
    if len(refined) < 2:
        return [], []
    from scipy.stats import chi2  # only here: importing scipy.stats costs ~0.5 s

    Cb = adj.x[3:6]
    Rb = rot.matrix_from_axis_angle(adj.x[:3])
    D = float(np.mean(np.linalg.norm(X - Cb, axis=1)))
    covC = adj.covariance_prior[3:6, 3:6]
    covR = adj.covariance_prior[:3, :3]
    r = max(int(adj.redundancy), 1)
    s02 = adj.cost / adj.redundancy if adj.redundancy > 0 else 0.0
    limit = chi2.ppf(1 - _AMBIGUITY_ALPHA, r) * max(1.0, s02)
    alts, amb = [], []
    seen = [(Cb, Rb)]
    for i, (behind, cost, _, a, Rc) in sorted(enumerate(refined), key=lambda t: t[1][1]):
        if i == best_i or not np.isfinite(cost):
            continue
        Ca = a.x[3:6]
        distinct = True
        for Cs, Rs in seen:
            dC = Ca - Cs
            nC = float(np.linalg.norm(dC))
            sC = float(np.sqrt(max(dC @ covC @ dC, 0.0))) / nC if nC > 0 and np.all(np.isfinite(covC)) else 0.0
            dR = rot.axis_angle_from_matrix(Rs.T @ Rc)
            nR = float(np.linalg.norm(dR))
            sR = float(np.sqrt(max(dR @ covR @ dR, 0.0))) / nR if nR > 0 and np.all(np.isfinite(covR)) else 0.0
            if nC <= max(3 * sC, 1e-6 * D) and nR <= max(3 * sR, 1e-6):
                distinct = False
                break
        if not distinct:
            continue
        seen.append((Ca, Rc))
        rms = float(np.sqrt(np.mean(a.residuals**2)))
        entry = (Pose.from_center(Rc, Ca), rms, float(np.linalg.norm(Ca - Cb)), cost)
        alts.append(entry)
        if not behind and a.outcome.success and cost <= limit:
            amb.append(entry)
    return alts, amb


def _camera_with(cam, iidx, values):
    if len(iidx) == 0:
        return cam
    p = np.asarray(cam.params, float).copy()
    p[iidx] = values
    return cam.with_params(p)


def collinearity_residuals(params, camera, points_world, xy_px, interior_idx=()):
    """Collinearity misclosures and their analytic Jacobian for one image.

    Parameters
    ----------
    params : ndarray (6 + k,)
        ``[rvec (3), C (3), interior values (k)]``; ``rvec`` is the cam_from_world rotation as a
        Rodrigues vector, ``C`` the projection centre (m), the interior values replace
        ``camera.params[interior_idx]``.
    camera : Camera-like
    points_world : ndarray (N, 3)
    xy_px : ndarray (N, 2)
    interior_idx : sequence of int

    Returns
    -------
    v : ndarray (2N,)
        projected − measured, pixels, ordered (x0, y0, x1, y1, ...).
    J : ndarray (2N, 6 + k)
        Derivatives w.r.t. the increment ``[δ (world-frame rotation, R ← R·exp([δ]×)), C, interior]``:
        ``∂X_cam/∂δ = −R [X − C]×``, ``∂X_cam/∂C = −R``.
    """
    iidx = np.asarray(interior_idx, int)
    R = _rodrigues(params[:3])
    C = params[3:6]
    c = _camera_with(camera, iidx, params[6:])
    d = points_world - C
    Xc = d @ R.T
    if iidx.size:
        uv, Jp, Jk = c.project_jacobian(Xc)
    else:  # fixed interior orientation: the point Jacobian is all that is needed
        uv, Jp = point_jacobian(c, Xc)
    n = points_world.shape[0]
    J = np.zeros((n, 2, 6 + iidx.size))
    A = Jp @ R  # ∂uv/∂X_world
    # Jp·(−R[d]×) = −A[d]×, whose rows are −(a × d) = d × a
    J[:, :, 0:3] = np.cross(d[:, None, :], A)
    J[:, :, 3:6] = -A
    if iidx.size:
        J[:, :, 6:] = Jk[:, :, iidx]
    return (uv - xy_px).ravel(), J.reshape(2 * n, -1)


def resection(
    camera,
    points_world,
    xy_px,
    *,
    sigma_px: float = 1.0,
    method: str = "auto",
    initial_pose: Pose | None = None,
    free_interior: bool | Sequence[str] = False,
    options: DenseOptions | None = None,
) -> ResectionResult:
    """Exterior orientation of one image from control points (space resection).

    Parameters
    ----------
    camera : Camera or (3, 3) K
        Interior orientation (kept fixed unless ``free_interior``).
    points_world : array_like (N, 3)
        Control points, metres. N ≥ 3 (≥ 4 for a unique solution; ≥ 6 non-coplanar for the DLT start).
    xy_px : array_like (N, 2)
        Measured image coordinates, pixels (OpenCV origin).
    sigma_px : float or array_like (N,) or (N, 2)
        A-priori σ of an image coordinate (px).
    method : {"auto", "dlt", "sqpnp"}
        Initialisation; ``"auto"``: DLT for ≥ 6 non-coplanar points (plus the planar starts when the
        field is flat, smallest/largest singular value < 0.1), else the minimal/planar starts
        (SQPnP, IPPE ×2, P3P for 4 points), each refined, best kept. Ignored when ``initial_pose``
        is given.
    initial_pose : Pose, optional
    free_interior : bool or sequence of str
        Estimate interior parameters too: ``True`` frees c, x0, y0 (``c_mm x0_mm y0_mm`` for the
        photogrammetric model, ``fx fy cx cy`` for pinhole/OpenCV), or name camera parameters.
        Needs non-coplanar points; an undetermined set gives ``Termination.RANK_DEFICIENT``.
    options : DenseOptions, optional

    Returns
    -------
    ResectionResult

    Raises
    ------
    TooFewPointsError, ShapeError, NonFiniteError, InvalidInputError
    """
    cam = as_camera(camera)
    X = as_points(points_world, "points_world", 3)
    x = as_points(xy_px, "xy_px", 2)
    if X.shape[0] != x.shape[0]:
        raise ShapeError(f"points_world has {X.shape[0]} rows but xy_px has {x.shape[0]}; expected one image point per control point")
    if method not in ("auto", "dlt", "sqpnp"):
        raise InvalidInputError(f"method: {method!r}; expected 'auto', 'dlt' or 'sqpnp'")
    sig = sigma_per_coordinate(sigma_px, (X.shape[0],))
    if free_interior is True:
        model = str(getattr(cam, "model", "pinhole"))
        model = getattr(getattr(cam, "model", None), "value", model)
        inames = _DEFAULT_INTERIOR.get(model, ("fx", "fy", "cx", "cy"))
    elif free_interior is False or free_interior is None:
        inames = ()
    else:
        inames = tuple(free_interior)
    pnames = tuple(cam.param_names)
    for nm in inames:
        if nm not in pnames:
            raise InvalidInputError(f"free_interior: {nm!r} is not a parameter of this camera; expected some of {pnames}")
    iidx = np.array([pnames.index(nm) for nm in inames], int)
    need = 3 if not inames else int(np.ceil((6 + len(inames)) / 2))
    if X.shape[0] < need:
        raise TooFewPointsError(
            f"space resection needs at least {need} control points for {6 + len(inames)} unknowns "
            f"(4 or more for a unique pose), got {X.shape[0]}"
        )
    if initial_pose is not None:
        if not isinstance(initial_pose, Pose):
            raise ShapeError(f"initial_pose: expected a Pose, got {type(initial_pose).__name__}")
        cands, init = [(initial_pose, "given")], "given"
    else:
        if method == "dlt" and X.shape[0] < 6:
            raise TooFewPointsError(f"method='dlt' needs at least 6 control points, got {X.shape[0]}")
        cands, init = _start_candidates(cam, X, x, method)
        if not cands:
            nan6 = np.full((6, 6), np.nan)
            return ResectionResult(Pose.identity(), cam, np.nan, np.nan, np.nan, np.full(3, np.nan), nan6, nan6, nan6,
                                   nan6[:3, :3], nan6[:3, :3], inames, np.full(len(inames), np.nan),
                                   np.full(len(inames), np.nan), np.full(len(inames), np.nan),
                                   np.full(x.shape, np.nan), np.nan, np.nan, init, None,
                                   Outcome(Termination.DEGENERATE, "SQPnP/IPPE found no pose for these points"))
    p_int0 = np.asarray(cam.params, float)[iidx] if inames else np.zeros(0)

    def fun(p):
        return collinearity_residuals(p, cam, X, x, iidx)

    def update(p, dp):
        R = _rodrigues(p[:3]) @ _rodrigues(dp[:3])
        return np.concatenate([_rvec(R), p[3:6] + dp[3:6], p[6:] + dp[6:]])

    names = ["dx_rot", "dy_rot", "dz_rot", "X0", "Y0", "Z0", *inames]
    w = 1.0 / sig.ravel() ** 2
    # refine every start (parameter vector: rvec (3, absolute, updated multiplicatively), C (3),
    # interior (k)); candidates are ranked by vᵀPv, those with points behind the camera last
    refined = []
    scale = float(np.mean(np.linalg.norm(X - X.mean(0), axis=1))) + 1e-300
    for pose0, cname in cands:
        # a start within 1e-3 (relative / rad) of a minimum already found converges to it: skip
        if any(np.linalg.norm(pose0.center - r_[3].x[3:6]) < 1e-3 * scale
               and np.linalg.norm(rot.axis_angle_from_matrix(r_[4].T @ pose0.R)) < 1e-3 for r_ in refined):
            continue
        x0 = np.concatenate([rot.axis_angle_from_matrix(pose0.R), pose0.center, p_int0])
        a = solve_dense(fun, x0, weights=w, update=update, param_names=names, options=options)
        Rc = rot.matrix_from_axis_angle(a.x[:3])
        n_behind = int(np.sum((X - a.x[3:6]) @ Rc[2] <= 0))
        cost = float(a.cost) if np.isfinite(a.cost) else np.inf
        refined.append((n_behind > 0, cost, cname, a, Rc))
    order = sorted(range(len(refined)), key=lambda i: (refined[i][0], refined[i][1], i))
    # ties (same minimum reached from several starts) go to the first start in the list
    best_i = order[0]
    for i in order:
        if refined[i][0] == refined[best_i][0] and refined[i][1] <= refined[best_i][1] * (1 + 1e-9) + 1e-18:
            best_i = min(best_i, i)
    _, cost_best, start_name, adj, _ = refined[best_i]
    alternatives, ambiguous = _alternatives(refined, best_i, X, adj)
    R = rot.matrix_from_axis_angle(adj.x[:3])
    C = adj.x[3:6]
    pose = Pose.from_center(R, C)
    cam_out = _camera_with(cam, iidx, adj.x[6:])
    o, f, k = (float(a) for a in rot.opk_from_matrix(rot.PHOTO_FROM_CAM @ R))
    A = rot.opk_to_increment_jacobian(o, f, k)
    T = np.eye(6)
    with np.errstate(all="ignore"):
        try:
            T[:3, :3] = np.linalg.inv(A)
        except np.linalg.LinAlgError:
            T[:3, :3] = np.nan
    cov_inc = adj.covariance[:6, :6]
    cov_opk = T @ cov_inc @ T.T
    cov_opk_p = T @ adj.covariance_prior[:6, :6] @ T.T
    outcome = adj.outcome
    depth = (X - C) @ R[2]
    if outcome.success and np.any(depth <= 0):
        outcome = Outcome(Termination.DEGENERATE,
                          f"{int(np.sum(depth <= 0))} of {X.shape[0]} control points lie behind the estimated camera")
    elif outcome.success and ambiguous:
        alt = ambiguous[0]
        outcome = Outcome(
            Termination.DEGENERATE,
            f"ambiguous pose: flip ambiguity of {'nearly ' if _flatness(X) > _COPLANAR_TOL else ''}coplanar control "
            f"points — a second pose with all points in front fits almost as well (RMS {alt[1]:.3g} px vs "
            f"{float(np.sqrt(np.mean(adj.residuals**2))):.3g} px, centre {alt[2]:.3g} m away; both pass the "
            f"global test at {100 * (1 - _AMBIGUITY_ALPHA):.0f} %). Best estimate returned; add control points "
            f"off the plane or more points, or give initial_pose")
    res = adj.residuals.reshape(-1, 2)
    istd = np.sqrt(np.clip(np.diag(adj.covariance)[6:], 0, None))
    istd_p = np.sqrt(np.clip(np.diag(adj.covariance_prior)[6:], 0, None))
    return ResectionResult(
        pose=pose, camera=cam_out, omega=o, phi=f, kappa=k, center=C.copy(),
        covariance_opk=cov_opk, covariance_opk_prior=cov_opk_p, covariance_increment=cov_inc,
        center_covariance=adj.covariance[3:6, 3:6], center_covariance_prior=adj.covariance_prior[3:6, 3:6],
        interior_names=inames, interior=adj.x[6:].copy(), interior_std=istd, interior_std_prior=istd_p,
        residuals_px=res, rms_px=float(np.sqrt(np.mean(res**2))), sigma0=float(adj.sigma0),
        init_method=init, adjustment=adj, outcome=outcome,
        start=start_name, ambiguous=bool(ambiguous), alternatives=tuple(alternatives),
    )
