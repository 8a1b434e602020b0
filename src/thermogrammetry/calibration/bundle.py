"""Small self-calibrating bundle adjustment with precision: the calibration's problem, solved by the project's engines.

Everything the calibration needs from a solver goes through the single call :func:`solve_bundle`.
It has two back ends that solve the same least-squares problem:

* ``engine="adjustment"`` (default): the project's adjustment engine
  (:func:`thermogrammetry.adjustment.solve`, sparse LM + Schur with precision); the problem below is
  translated into its ``BundleProblem`` (cameras as :class:`thermogrammetry.Camera` in their block's
  model, poses, rig blocks, fixed or weighted points) and the result translated back;
* ``engine="dense"``: the same problem as one dense weighted least-squares problem for
  :func:`thermogrammetry.adjustment.dense.solve_dense` (Gauss–Newton/LM with covariance, σ0 and
  redundancy numbers); the Jacobian is assembled here from the camera model's analytic Jacobians.
  It is an independent cross-check of the engine's Schur route and of the translation to its
  problem (``tests/test_calibration_selfcal.py`` compares both), and finishes the job when the
  engine stops away from a minimum (:func:`thermogrammetry.calibration.bundle_engine.verify_engine`).

Model
-----
Observations are measured pixel coordinates (OpenCV convention) of object points seen by a camera
in a pose (``cam_from_world``), optionally through a rig offset (``cam_from_reference``)::

    Xc = R_rig (R_pose X + t_pose) + t_rig
    xy = project(Xc; camera parameters)   (thermogrammetry.camera.models, see :func:`project`)

Each camera block is in one of two models (:attr:`CameraBlock.model`): the correction
(photogrammetric) form of Brown (1971) and Fraser (1997), ``c x0 y0 K1..K5 P1 P2 B1 B2`` (the
default), or OpenCV's forward Brown form, ``fx fy cx cy skew k1 k2 p1 p2 k3 k4 k5 k6`` (the model
of ``cv2.calibrateCamera``, Bradski 2000; Zhang 2000). The parameter vector of a block has the
model's layout (:func:`param_names`).

Unknowns: the free intrinsic parameters of every camera, 6 per free pose (rotation increment δ with
``R ← exp([δ]×) R``, translation t), 6 per free rig offset, 3 per free object point (with an optional
a-priori standard deviation acting as a weighted pseudo-observation; a point without prior is fixed).

The estimate minimises ``Σ ((xy_obs − xy)/σ)²`` (Gauss–Markov model with uncorrelated image
coordinates of a-priori standard deviation σ, in px). Precision: ``Σxx = σ0² N⁻¹`` with
``σ0² = vᵀPv / r``; redundancy numbers ``r_i = 1 − (A N⁻¹ Aᵀ P)_ii``; Baarda's normalised
residuals ``w_i = v_i / (σ_i sqrt(r_i))`` (Baarda 1968; Förstner 1987).

References
----------
Baarda, W., 1968. A testing procedure for use in geodetic networks. Netherlands Geodetic Commission.
Brown, D.C., 1971. Close-range camera calibration. Photogramm. Eng. 37(8), 855–866.
Fraser, C.S., 1997. Digital camera self-calibration. ISPRS J. Photogramm. Remote Sens. 52, 149–159.
Triggs, B., McLauchlan, P., Hartley, R., Fitzgibbon, A., 2000. Bundle adjustment — a modern synthesis.
Zhang, Z., 2000. A flexible new technique for camera calibration. IEEE TPAMI 22(11), 1330–1334.
Bradski, G., 2000. The OpenCV library. Dr. Dobb's Journal of Software Tools (``calib3d`` camera model).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..camera import models as _cm
from ..results import Outcome, Termination

__all__ = ["PARAM_NAMES", "PARAM_UNITS", "N_PARAMS", "CALIBRATION_MODELS", "param_names", "param_units", "project",
           "CameraBlock", "BundleProblem", "BundleSolution", "solve_bundle", "residuals", "rotation_exp"]

# The calibration uses the camera package's models as they are (same parameter order).
_PHOTO = _cm.CameraModel.PHOTOGRAMMETRIC
_OPENCV = _cm.CameraModel.OPENCV
#: the models a calibration can estimate (the first is the default)
CALIBRATION_MODELS: tuple[_cm.CameraModel, ...] = (_PHOTO, _OPENCV)
#: parameter layout of the default (photogrammetric) model
PARAM_NAMES: tuple[str, ...] = _cm.PARAM_NAMES[_PHOTO]
PARAM_UNITS: tuple[str, ...] = tuple(_cm.PARAM_UNITS[_PHOTO][n] for n in PARAM_NAMES)
N_PARAMS = len(PARAM_NAMES)


def param_names(model=_PHOTO) -> tuple[str, ...]:
    """Parameter layout of a calibration model (``thermogrammetry.camera.models.PARAM_NAMES``)."""
    return _cm.PARAM_NAMES[_cm.CameraModel(model)]


def param_units(model=_PHOTO) -> tuple[str, ...]:
    """Units of :func:`param_names` (``"1"`` = unitless)."""
    m = _cm.CameraModel(model)
    return tuple(_cm.PARAM_UNITS[m][n] for n in _cm.PARAM_NAMES[m])

try:  # small dense problems run much faster on one BLAS thread than on contended cores
    from threadpoolctl import threadpool_limits as _threadpool_limits
except ImportError:  # pragma: no cover - optional
    _threadpool_limits = None


def project(points_cam: np.ndarray, params: np.ndarray, image_size, pitch_mm, *, jacobians: bool = True,
            model=_PHOTO):
    """Measured pixel coordinates of camera-frame points with a block's model, with Jacobians.

    A thin adapter over :func:`thermogrammetry.camera.models.photogrammetric_project_jacobian`
    (the model of ``docs/conventions.md``; Brown 1971, Fraser 1997) or, with ``model="opencv"``,
    :func:`thermogrammetry.camera.models.opencv_project_jacobian` (forward form): it takes the pixel
    pitch in mm as stored in :class:`CameraBlock` and adds the validity mask the bundle needs.

    Parameters
    ----------
    points_cam : (N, 3) float
        Points in the camera frame (x right, y down, z forward), metres.
    params : (P,) float
        Layout :func:`param_names` of ``model`` (12 photogrammetric, 13 opencv parameters).
    image_size : (w, h)
        Pixels.
    pitch_mm : (px, py)
        Pixel pitch in mm.
    jacobians : bool
        Also return the Jacobians.
    model : ``"photogrammetric"`` (default) or ``"opencv"``.

    Returns
    -------
    xy_px : (N, 2)
        OpenCV pixel coordinates of the measured (distorted) image points; NaN where not ``ok``.
    J_point : (N, 2, 3) or None
        d xy_px / d points_cam (zero where not ``ok``).
    J_params : (N, 2, P) or None
        d xy_px / d params.
    ok : (N,) bool
        In front of the camera and (photogrammetric) the model's Newton solve converged (main sheet).

    References
    ----------
    Brown, D.C., 1971. Close-range camera calibration. Photogramm. Eng. 37(8), 855–866.
    Fraser, C.S., 1997. Digital camera self-calibration. ISPRS J. Photogramm. Remote Sens. 52, 149–159.
    """
    X = np.asarray(points_cam, dtype=float)
    n = X.shape[0]
    model = _cm.CameraModel(model)
    pitch_um = (float(pitch_mm[0]) * 1e3, float(pitch_mm[1]) * 1e3)
    front = X[:, 2] > 1e-12
    xy = np.full((n, 2), np.nan)
    J_point = np.zeros((n, 2, 3)) if jacobians else None
    J_params = np.zeros((n, 2, len(params))) if jacobians else None
    if np.any(front):
        if model is _OPENCV:
            if jacobians:
                xy[front], J_point[front], J_params[front] = _cm.opencv_project_jacobian(params, X[front])
            else:
                xy[front] = _cm.opencv_project(params, X[front])
        elif jacobians:
            xy[front], J_point[front], J_params[front] = _cm.photogrammetric_project_jacobian(
                params, X[front], image_size, pitch_um)
        else:
            xy[front] = _cm.photogrammetric_project(params, X[front], image_size, pitch_um)
    ok = front & np.all(np.isfinite(xy), axis=1)
    if jacobians and not np.all(ok):
        J_point[~ok] = 0.0
        J_params[~ok] = 0.0
    return xy, J_point, J_params, ok


def _skew(v: np.ndarray) -> np.ndarray:
    """(N,3) -> (N,3,3) cross-product matrices."""
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1] = -v[..., 2]
    S[..., 0, 2] = v[..., 1]
    S[..., 1, 0] = v[..., 2]
    S[..., 1, 2] = -v[..., 0]
    S[..., 2, 0] = -v[..., 1]
    S[..., 2, 1] = v[..., 0]
    return S


def rotation_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vectors (N,3) (radians) -> rotation matrices (N,3,3)."""
    w = np.atleast_2d(w)
    th = np.linalg.norm(w, axis=1)
    S = _skew(w)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th**2 / 24.0, (1 - np.cos(ths)) / ths**2)
    return np.eye(3)[None] + a[:, None, None] * S + b[:, None, None] * (S @ S)


@dataclass
class CameraBlock:
    """One camera (intrinsics) in a bundle: its model's parameters and which of them are free."""

    params: np.ndarray  # (P,) layout param_names(model)
    free: np.ndarray  # (P,) bool
    image_size: tuple[int, int]
    pitch_mm: tuple[float, float]
    name: str = ""
    model: _cm.CameraModel = _PHOTO

    def __post_init__(self):
        self.model = _cm.CameraModel(self.model)

    @property
    def param_names(self) -> tuple[str, ...]:
        return param_names(self.model)

    def like(self, params) -> "CameraBlock":
        """The same block with other parameter values."""
        return CameraBlock(params, self.free, self.image_size, self.pitch_mm, self.name, self.model)


@dataclass
class BundleProblem:
    """What is estimated (see module docstring). Arrays are copied by :func:`solve_bundle`."""

    cameras: list[CameraBlock]
    R: np.ndarray  # (F,3,3) cam_from_world rotations (reference sensor for rig frames)
    t: np.ndarray  # (F,3)
    points: np.ndarray  # (M,3) metres
    obs_camera: np.ndarray  # (N,) int
    obs_pose: np.ndarray  # (N,) int
    obs_point: np.ndarray  # (N,) int
    obs_xy: np.ndarray  # (N,2) px
    obs_sigma: np.ndarray  # (N,2) px
    obs_rig: np.ndarray | None = None  # (N,) int, -1 = no rig offset
    rig_R: np.ndarray | None = None  # (G,3,3) cam_from_reference
    rig_t: np.ndarray | None = None  # (G,3)
    pose_free: np.ndarray | None = None  # (F,) bool, default all free
    point_prior_std: np.ndarray | None = None  # (M,3) metres; None/NaN/0 = fixed point
    point_prior: np.ndarray | None = None  # (M,3) observed coordinates of weighted points (default: points)

    def __post_init__(self):
        n = self.obs_xy.shape[0]
        if self.obs_rig is None:
            self.obs_rig = -np.ones(n, dtype=int)
        if self.rig_R is None:
            self.rig_R = np.zeros((0, 3, 3))
            self.rig_t = np.zeros((0, 3))
        if self.pose_free is None:
            self.pose_free = np.ones(self.R.shape[0], dtype=bool)


@dataclass
class BundleSolution:
    """Estimate and precision. ``covariance`` is σ0² N⁻¹ over the unknown vector described by ``layout``."""

    outcome: Outcome
    cameras: list[CameraBlock]
    R: np.ndarray
    t: np.ndarray
    rig_R: np.ndarray
    rig_t: np.ndarray
    points: np.ndarray
    residuals_px: np.ndarray  # (N,2) observed - computed
    redundancy: np.ndarray  # (N,2)
    sigma0: float  # a-posteriori σ0 (unitless, relative to obs_sigma)
    dof: int
    iterations: int
    cofactor: np.ndarray  # N^-1 (unknowns x unknowns)
    layout: dict = field(default_factory=dict)  # block name -> slice / index arrays
    camera_std: list = field(default_factory=list)  # per camera (P,) std (NaN where fixed)
    camera_cov: list = field(default_factory=list)  # per camera (P,P) covariance (0 where fixed)
    pose_std: np.ndarray | None = None  # (F,6) rot (rad), t (m)
    rig_std: np.ndarray | None = None  # (G,6)
    rig_cov: list = field(default_factory=list)  # (G) (6,6)

    @property
    def normalized_residuals(self) -> np.ndarray:
        """Baarda's w = v / (σ sqrt(r)) with the a-priori σ (N,2); NaN where r≈0."""
        return self._w


def _layout(problem: BundleProblem):
    idx = 0
    cam_slices = []
    for cb in problem.cameras:
        k = int(np.count_nonzero(cb.free))
        cam_slices.append(np.arange(idx, idx + k))
        idx += k
    F = problem.R.shape[0]
    pose_index = -np.ones(F, dtype=int)
    for f in range(F):
        if problem.pose_free[f]:
            pose_index[f] = idx
            idx += 6
    G = problem.rig_R.shape[0]
    rig_index = np.arange(idx, idx + 6 * G, 6) if G else np.zeros(0, dtype=int)
    idx += 6 * G
    M = problem.points.shape[0]
    point_index = -np.ones(M, dtype=int)
    ps = problem.point_prior_std
    if ps is not None:
        ps = np.asarray(ps, float)
        free_pts = np.all(np.isfinite(ps) & (ps > 0), axis=1)
        # only points that are observed can be free
        observed = np.zeros(M, dtype=bool)
        observed[problem.obs_point] = True
        for m in np.nonzero(free_pts & observed)[0]:
            point_index[m] = idx
            idx += 3
    return {"cameras": cam_slices, "pose": pose_index, "rig": rig_index, "point": point_index, "n": idx}


def _evaluate(problem, cams, R, t, rigR, rigt, pts, lay, want_jac=True):
    """Residuals (N,2) px (obs - computed), validity, and the Jacobian of computed xy wrt unknowns (2N, n)."""
    N = problem.obs_xy.shape[0]
    n = lay["n"]
    Xw = pts[problem.obs_point]
    Rf = R[problem.obs_pose]
    RX = (Rf @ Xw[:, :, None])[:, :, 0]
    Y = RX + t[problem.obs_pose]
    has_rig = problem.obs_rig >= 0
    Xc = Y.copy()
    Rr = np.broadcast_to(np.eye(3), (N, 3, 3)).copy()
    if np.any(has_rig):
        g = problem.obs_rig[has_rig]
        Rr[has_rig] = rigR[g]
        Xc[has_rig] = (rigR[g] @ Y[has_rig][:, :, None])[:, :, 0] + rigt[g]
    xy = np.empty((N, 2))
    ok = np.zeros(N, dtype=bool)
    Jpt = np.zeros((N, 2, 3))
    J = np.zeros((2 * N, n)) if want_jac else None
    for ci, cb in enumerate(cams):
        sel = np.nonzero(problem.obs_camera == ci)[0]
        if sel.size == 0:
            continue
        xyc, Jp3, Jpar, okc = project(Xc[sel], cb.params, cb.image_size, cb.pitch_mm, jacobians=want_jac, model=cb.model)
        xy[sel] = xyc
        ok[sel] = okc
        if want_jac:
            Jpt[sel] = Jp3
            cols = lay["cameras"][ci]
            if cols.size:
                Jf = Jpar[:, :, cb.free]
                J[2 * sel, cols[0] : cols[-1] + 1] = Jf[:, 0, :]
                J[2 * sel + 1, cols[0] : cols[-1] + 1] = Jf[:, 1, :]
    res = problem.obs_xy - xy
    if not want_jac:
        return res, ok, None
    rows = np.arange(N)
    # pose block
    pidx = lay["pose"][problem.obs_pose]
    has_pose = pidx >= 0
    if np.any(has_pose):
        JR = Jpt @ Rr  # d xy / d Y
        Jrot = -(JR @ _skew(RX))
        r = rows[has_pose]
        cols = pidx[has_pose][:, None] + np.arange(6)[None, :]
        blk = np.concatenate([Jrot[has_pose], JR[has_pose]], axis=2)  # (k,2,6)
        J[(2 * r)[:, None], cols] = blk[:, 0, :]
        J[(2 * r + 1)[:, None], cols] = blk[:, 1, :]
    if np.any(has_rig):
        gidx = lay["rig"][problem.obs_rig[has_rig]]
        RY = (Rr[has_rig] @ Y[has_rig][:, :, None])[:, :, 0]
        Jrot = -(Jpt[has_rig] @ _skew(RY))
        blk = np.concatenate([Jrot, Jpt[has_rig]], axis=2)
        r = rows[has_rig]
        cols = gidx[:, None] + np.arange(6)[None, :]
        J[(2 * r)[:, None], cols] = blk[:, 0, :]
        J[(2 * r + 1)[:, None], cols] = blk[:, 1, :]
    qidx = lay["point"][problem.obs_point]
    has_pt = qidx >= 0
    if np.any(has_pt):
        blk = Jpt[has_pt] @ (Rr[has_pt] @ Rf[has_pt])
        r = rows[has_pt]
        cols = qidx[has_pt][:, None] + np.arange(3)[None, :]
        J[(2 * r)[:, None], cols] = blk[:, 0, :]
        J[(2 * r + 1)[:, None], cols] = blk[:, 1, :]
    return res, ok, J


def _apply(problem, cams, R, t, rigR, rigt, pts, lay, dx):
    cams2 = []
    for ci, cb in enumerate(cams):
        p = cb.params.copy()
        cols = lay["cameras"][ci]
        p[cb.free] += dx[cols]
        cams2.append(cb.like(p))
    R2 = R.copy()
    t2 = t.copy()
    fr = np.nonzero(lay["pose"] >= 0)[0]
    if fr.size:
        d = dx[lay["pose"][fr][:, None] + np.arange(6)[None, :]]
        R2[fr] = rotation_exp(d[:, :3]) @ R[fr]
        t2[fr] = t[fr] + d[:, 3:]
    rigR2 = rigR.copy()
    rigt2 = rigt.copy()
    if rigR.shape[0]:
        d = dx[lay["rig"][:, None] + np.arange(6)[None, :]]
        rigR2 = rotation_exp(d[:, :3]) @ rigR
        rigt2 = rigt + d[:, 3:]
    pts2 = pts.copy()
    fp = np.nonzero(lay["point"] >= 0)[0]
    if fp.size:
        pts2[fp] = pts[fp] + dx[lay["point"][fp][:, None] + np.arange(3)[None, :]]
    return cams2, R2, t2, rigR2, rigt2, pts2


def residuals(problem: BundleProblem) -> tuple[np.ndarray, np.ndarray]:
    """Observed − computed image coordinates (N,2) px at the problem's current values, and validity (N,)."""
    lay = _layout(problem)
    res, ok, _ = _evaluate(problem, problem.cameras, problem.R, problem.t, problem.rig_R, problem.rig_t,
                           problem.points, lay, want_jac=False)
    return res, ok


def solve_bundle(problem: BundleProblem, *, max_iterations: int = 200, tolerance: float = 1e-10,
                 engine: str = "adjustment") -> BundleSolution:
    """Solve the bundle; returns the estimate with precision.

    ``engine``: ``"adjustment"`` (the project's sparse engine) or ``"dense"``
    (:func:`thermogrammetry.adjustment.dense.solve_dense` on the dense Jacobian).
    Failure to converge or a singular normal matrix is reported through ``solution.outcome``
    (:class:`~thermogrammetry.results.Termination`), never raised.
    """
    if engine == "adjustment":
        from .bundle_engine import solve_engine, verify_engine

        sol = solve_engine(problem, max_iterations)
        return verify_engine(problem, sol, max_iterations, tolerance)
    if engine != "dense":
        from ..errors import ConfigError

        raise ConfigError(f"engine={engine!r}; expected 'adjustment' or 'dense'")
    if _threadpool_limits is not None:
        with _threadpool_limits(limits=1, user_api="blas"):
            return _solve_bundle(problem, max_iterations, tolerance)
    return _solve_bundle(problem, max_iterations, tolerance)


def _param_names(problem: BundleProblem, lay: dict) -> list[str]:
    """Names of the unknowns in layout order (used in rank-deficiency messages)."""
    names = [""] * lay["n"]
    for ci, cb in enumerate(problem.cameras):
        for j, k in zip(lay["cameras"][ci], np.nonzero(cb.free)[0]):
            names[j] = f"cam{ci}.{cb.param_names[k]}"
    comp = ("wx", "wy", "wz", "tx", "ty", "tz")
    for f in np.nonzero(lay["pose"] >= 0)[0]:
        for k, c in enumerate(comp):
            names[lay["pose"][f] + k] = f"pose{f}.{c}"
    for g, i in enumerate(lay["rig"]):
        for k, c in enumerate(comp):
            names[i + k] = f"rig{g}.{c}"
    for m in np.nonzero(lay["point"] >= 0)[0]:
        for k, c in enumerate("XYZ"):
            names[lay["point"][m] + k] = f"point{m}.{c}"
    return names


def _system(problem: BundleProblem, lay: dict, cams, R, t, rigR, rigt, pts):
    """Misclosures ``v = computed − observed`` and their Jacobian w.r.t. the unknowns of ``lay``.

    Rows: the image coordinates (2N, px; NaN where an observation is not ``ok``), then the
    a-priori coordinates of the weighted object points (3 per free point, m). Returns
    ``(v (m,), J (m, n), ok (N,))``.
    """
    res, ok, J = _evaluate(problem, cams, R, t, rigR, rigt, pts, lay, want_jac=True)
    v = -res.ravel()
    v[np.repeat(~ok, 2)] = np.nan
    fp = np.nonzero(lay["point"] >= 0)[0]
    if fp.size:
        prior = problem.points if problem.point_prior is None else problem.point_prior
        v = np.concatenate([v, (pts[fp] - np.asarray(prior, float)[fp]).ravel()])
        Jp = np.zeros((3 * fp.size, lay["n"]))
        cols = (lay["point"][fp][:, None] + np.arange(3)[None, :]).ravel()
        Jp[np.arange(3 * fp.size), cols] = 1.0
        J = np.vstack([J, Jp])
    return v, J, ok


def _weights(problem: BundleProblem, lay: dict) -> np.ndarray:
    """Weights of the rows of :func:`_system`: 1/σ² (image coordinates), 1/σ_X² (weighted points)."""
    fp = np.nonzero(lay["point"] >= 0)[0]
    pstd = np.asarray(problem.point_prior_std, float)[fp] if fp.size else np.zeros((0, 3))
    return np.concatenate([1.0 / np.asarray(problem.obs_sigma, float).ravel() ** 2, 1.0 / pstd.ravel() ** 2])


def _solve_bundle(problem: BundleProblem, max_iterations: int, tolerance: float) -> BundleSolution:
    """The dense route: this problem handed to :func:`thermogrammetry.adjustment.dense.solve_dense`.

    The unknown vector ``x`` (layout :func:`_layout`) accumulates the increments from the start
    values: camera parameters, translations and points additively, rotations as ``R = exp([w]×) R0``.
    The Jacobian of :func:`_evaluate` is taken with respect to a left rotation increment, so
    ``update`` composes ``exp([δ]×) exp([w]×)`` and takes the rotation vector of the product.
    Observations: the image coordinates (weights 1/σ²) and, for weighted object points, their
    a-priori coordinates (weights 1/σ_X²); σ0 a priori = 1.
    """
    from ..adjustment.dense import DenseOptions, solve_dense
    from ..geometry.rotations import axis_angle_from_matrix

    cams0 = [CameraBlock(np.asarray(c.params, float).copy(), np.asarray(c.free, bool).copy(), tuple(c.image_size),
                         tuple(c.pitch_mm), c.name, c.model) for c in problem.cameras]
    R0 = np.asarray(problem.R, float).copy()
    t0 = np.asarray(problem.t, float).copy()
    rigR0 = np.asarray(problem.rig_R, float).copy()
    rigt0 = np.asarray(problem.rig_t, float).copy()
    pts0 = np.asarray(problem.points, float).copy()
    lay = _layout(problem)
    n = lay["n"]
    sig = np.asarray(problem.obs_sigma, float)
    Nobs = problem.obs_xy.shape[0]
    n_prior = 3 * int(np.count_nonzero(lay["point"] >= 0))
    rot_starts = np.concatenate([lay["pose"][lay["pose"] >= 0], lay["rig"]]).astype(int)
    rot_cols = (rot_starts[:, None] + np.arange(3)[None, :])

    def state(x):
        return _apply(problem, cams0, R0, t0, rigR0, rigt0, pts0, lay, x)

    def fun(x):  # NaN rows (behind a camera / beyond the model's range) make solve_dense reject the step
        v, J, _ = _system(problem, lay, *state(x))
        return v, J

    def update(x, dx):
        x2 = x + dx
        if rot_cols.size:
            w = x[rot_cols]
            x2[rot_cols] = axis_angle_from_matrix(rotation_exp(dx[rot_cols]) @ rotation_exp(w))
        return x2

    # the start must be valid: every observation in front of its camera and inside the model's range
    res, ok, _ = _evaluate(problem, cams0, R0, t0, rigR0, rigt0, pts0, lay, want_jac=False)
    nobs = 2 * Nobs + n_prior
    if nobs - n <= 0:
        return _fail(problem, cams0, R0, t0, rigR0, rigt0, pts0, res, Termination.TOO_FEW_OBSERVATIONS,
                     f"{nobs} observations for {n} unknowns: redundancy {nobs - n} <= 0", lay)
    if not np.all(ok):
        return _fail(problem, cams0, R0, t0, rigR0, rigt0, pts0, res, Termination.DEGENERATE,
                     f"{np.count_nonzero(~ok)} observations project behind a camera or outside the model's range at the start", lay)
    weights = _weights(problem, lay)
    # small initial damping: self-calibration normal matrices have tiny eigenvalues along the
    # correlated K1-K3 directions, and a larger λ would turn Gauss-Newton into slow gradient steps.
    # Stops on a relative cost change below ``tolerance`` or when the undamped step would lower the
    # cost by less than 1e-15 of it (solve_dense's decrease_tol: the step is ~1e-6 σ there).
    opts = DenseOptions(max_iterations=max_iterations, initial_lambda=1e-9, cost_tol=tolerance, rank_tol=1e-14)
    dr = solve_dense(fun, np.zeros(n), weights=weights, update=update, param_names=_param_names(problem, lay),
                     options=opts)
    cams, R, t, rigR, rigt, pts = state(dr.x)
    res = -dr.residuals[: 2 * Nobs].reshape(Nobs, 2)
    if not dr.success or not np.all(np.isfinite(dr.covariance)):
        term = dr.termination if not dr.success else Termination.NUMERICAL_FAILURE
        return _fail(problem, cams, R, t, rigR, rigt, pts, res, term, dr.reason, lay)
    rnum = np.clip(dr.redundancy_numbers[: 2 * Nobs], 0.0, 1.0).reshape(Nobs, 2)
    sol = BundleSolution(Outcome(dr.termination, dr.reason), cams, R, t, rigR, rigt, pts, res, rnum, float(dr.sigma0),
                         int(dr.redundancy), int(dr.iterations), dr.cofactor, lay)
    _fill_std(sol, dr.covariance)
    with np.errstate(divide="ignore", invalid="ignore"):
        sol._w = np.where(rnum > 1e-6, res / (sig * np.sqrt(rnum)), np.nan)
    return sol


def _fill_std(sol: BundleSolution, cov: np.ndarray) -> None:
    lay = sol.layout
    sol.camera_std = []
    sol.camera_cov = []
    for ci, cb in enumerate(sol.cameras):
        P = len(cb.params)
        std = np.full(P, np.nan)
        C = np.zeros((P, P))
        cols = lay["cameras"][ci]
        fi = np.nonzero(cb.free)[0]
        if cols.size:
            std[fi] = np.sqrt(np.diag(cov)[cols])
            C[np.ix_(fi, fi)] = cov[np.ix_(cols, cols)]
        sol.camera_std.append(std)
        sol.camera_cov.append(C)
    F = sol.R.shape[0]
    ps = np.full((F, 6), np.nan)
    for f in range(F):
        i = lay["pose"][f]
        if i >= 0:
            ps[f] = np.sqrt(np.diag(cov)[i : i + 6])
    sol.pose_std = ps
    G = sol.rig_R.shape[0]
    sol.rig_std = np.full((G, 6), np.nan)
    sol.rig_cov = []
    for g in range(G):
        i = lay["rig"][g]
        sol.rig_std[g] = np.sqrt(np.diag(cov)[i : i + 6])
        sol.rig_cov.append(cov[i : i + 6, i : i + 6])


def _fail(problem, cams, R, t, rigR, rigt, pts, res, term, reason, lay):
    N = problem.obs_xy.shape[0]
    sol = BundleSolution(Outcome(term, reason), cams, R, t, rigR, rigt, pts, res, np.full((N, 2), np.nan), float("nan"), 0, 0,
                         np.zeros((0, 0)), lay)
    sol.camera_std = [np.full(len(c.params), np.nan) for c in cams]
    sol.camera_cov = [np.zeros((len(c.params), len(c.params))) for c in cams]
    sol.pose_std = np.full((R.shape[0], 6), np.nan)
    sol.rig_std = np.full((rigR.shape[0], 6), np.nan)
    sol._w = np.full((N, 2), np.nan)
    return sol
