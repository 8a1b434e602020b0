"""Staged self-calibration of one or more cameras from targets with known coordinates.

Strategy of seed 001 (Yastikli & Guler 2013, §3), extended as issue 6 asks:

1. **Stage 1** — nominal principal distance, principal point at the image centre, no distortion;
   only the exterior orientations are estimated (initialised per image by resection,
   ``cv2.solvePnP``). Gross blunders are eliminated here. Because uncorrected distortion inflates the
   residuals at this stage (seed 001's camera has up to ~20 px of distortion in the corners), the
   test uses the a-posteriori σ0 and a conservative critical value (``stage1_critical``, default 5),
   so that only gross errors go. After stage 2 has converged, every stage-1 reject within 10 σ of
   the full model is re-admitted and re-tested by the stage-2 data snooping (otherwise valid
   corner points, the most informative on distortion, would stay out).
2. **Stage 2** — x0, y0, c, K1–K3, P1, P2 free (K4, K5 and B1, B2 on request, seed 003). Data
   snooping (Baarda 1968) with the a-priori σ of the measurements when every measurement carries
   one, otherwise Pope's τ test with the a-posteriori σ0; critical value 3.29 (α0 = 0.1 %,
   two-sided); at most one observation (image point) is removed per image and round.
3. **Tests** — Student-t significance test of every additional parameter (H0: value = 0, α = 5 %,
   two-sided, degrees of freedom = redundancy) and warnings for |ρ| > 0.9 between intrinsic
   parameters.

Several cameras are calibrated together (each has its own intrinsics; images are tied together by
the common object points). When images of different cameras share a ``frame`` key and ``rig=True``,
the second camera's poses are the first camera's pose composed with a constant relative orientation
``cam2_from_cam1`` (estimated, with precision): the relative orientation of a thermal + RGB pair.

The solve is one call, :func:`thermogrammetry.calibration.bundle.solve_bundle`: by default the
project's adjustment engine (:mod:`thermogrammetry.adjustment`), or the dense kernel
:func:`thermogrammetry.adjustment.dense.solve_dense` on the same problem, kept as a cross-check.

References
----------
Yastikli, N., Guler, E., 2013. Performance evaluation of thermographic cameras for photogrammetric
measurements. ISPRS Arch. XL-1/W1 (seed 001).
Khodaei, B. et al., 2015. 3D surface generation from aerial thermal imagery (seed 003: K4, K5).
Fraser, C.S., 1997. Digital camera self-calibration. ISPRS J. Photogramm. Remote Sens. 52, 149–159.
Baarda, W., 1968. A testing procedure for use in geodetic networks.
Pope, A.J., 1976. The statistics of residuals and the detection of outliers. NOAA TR NOS 65 NGS 1.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import cv2
import numpy as np
from scipy import stats

from ..errors import ConfigError, InvalidInputError, TooFewPointsError
from ..geometry.rotations import mean_rotation
from ..results import Outcome, Termination
from .bundle import N_PARAMS, PARAM_NAMES, BundleProblem, BundleSolution, CameraBlock, residuals, solve_bundle
from .._validate import config_keys

__all__ = [
    "SelfCalibrationOptions",
    "CameraSetup",
    "ImageMeasurements",
    "ParameterTest",
    "CameraCalibration",
    "ImageVerdict",
    "RelativeOrientation",
    "CalibrationResult",
    "calibrate",
    "STAGE2_PARAMS",
]

STAGE2_PARAMS = ("c_mm", "x0_mm", "y0_mm", "K1", "K2", "K3", "P1", "P2")
ADDITIONAL = ("x0_mm", "y0_mm", "K1", "K2", "K3", "K4", "K5", "P1", "P2", "B1", "B2")


@dataclass(frozen=True)
class SelfCalibrationOptions:
    """Typed options of :func:`calibrate` (``from_dict`` rejects unknown keys).

    Attributes
    ----------
    k45 : also estimate K4, K5 (seed 003).
    affinity : also estimate B1, B2.
    fixed : names of parameters to keep at their nominal value in stage 2 (e.g. ``("P1", "P2")``).
    default_sigma_px : a-priori σ of an image coordinate when the measurements carry none (px).
    stage1_critical : critical value of the stage-1 gross-error test (a-posteriori σ0).
    critical_value : critical value of data snooping in stage 2 (3.29 = α0 0.1 % two-sided).
    max_snooping_rounds : limit on remove-and-resolve rounds per stage.
    significance_alpha : two-sided level of the t-test of additional parameters.
    correlation_warning : |ρ| above which a pair of intrinsic parameters is reported.
    min_points_per_image : images with fewer usable points are rejected (≥ 4; 6 for a 3D field).
    max_image_rms_factor : after stage 2, an image whose RMS exceeds this factor times the median
        image RMS (and 1 px) is rejected and the solve repeated.
    snooping : disable to run the adjustment without blunder elimination (Monte-Carlo studies).
    solver : ``"adjustment"`` (the project's engine, default) or ``"dense"`` (the dense Jacobian of
        :mod:`~thermogrammetry.calibration.bundle` solved by :func:`thermogrammetry.adjustment.dense.solve_dense`).
    rig_rms_warning_factor : with ``rig=True`` the cameras are also calibrated with independent poses,
        and a warning is given when a rig camera's RMS exceeds this factor times its independent RMS
        (the rig constraint does not hold: unsynchronised frames, a moving target, mislabelled pairs).
        0 disables the check (and the extra solve).
    """

    k45: bool = False
    affinity: bool = False
    fixed: tuple[str, ...] = ()
    default_sigma_px: float = 1.0
    stage1_critical: float = 5.0
    critical_value: float = 3.29
    max_snooping_rounds: int = 30
    significance_alpha: float = 0.05
    correlation_warning: float = 0.9
    min_points_per_image: int = 6
    max_image_rms_factor: float = 5.0
    snooping: bool = True
    solver: str = "adjustment"
    rig_rms_warning_factor: float = 2.0

    def __post_init__(self):
        if self.solver not in ("adjustment", "dense"):
            raise ConfigError(f"solver = {self.solver!r}: expected 'adjustment' or 'dense'")
        bad = [n for n in self.fixed if n not in PARAM_NAMES]
        if bad:
            raise ConfigError(f"fixed: unknown parameter(s) {bad}; expected names from {list(PARAM_NAMES)}")
        if self.default_sigma_px <= 0:
            raise ConfigError(f"default_sigma_px = {self.default_sigma_px}: expected a positive number of pixels")
        if self.min_points_per_image < 4:
            raise ConfigError(f"min_points_per_image = {self.min_points_per_image}: expected >= 4")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "SelfCalibrationOptions":
        d = config_keys(cls, d)
        if "fixed" in d:
            d["fixed"] = tuple(d["fixed"])
        return cls(**d)

    def stage2_free(self) -> np.ndarray:
        names = list(STAGE2_PARAMS)
        if self.k45:
            names += ["K4", "K5"]
        if self.affinity:
            names += ["B1", "B2"]
        return np.array([n in names and n not in self.fixed for n in PARAM_NAMES])


@dataclass
class CameraSetup:
    """A camera to calibrate: image size (px), pixel pitch (µm; scalar or (x, y)) and nominal values.

    ``nominal`` maps correction-form parameter names to starting values; ``c_mm`` is required
    unless the target is planar (then it may be ``None`` and is initialised from the images by
    Zhang's method, ``cv2.initCameraMatrix2D``).
    """

    name: str
    image_size: tuple[int, int]
    pixel_pitch_um: float | tuple[float, float]
    nominal: dict[str, float] = field(default_factory=dict)

    def __post_init__(self):
        w, h = self.image_size
        if int(w) <= 0 or int(h) <= 0:
            raise InvalidInputError(f"camera {self.name!r}: image_size {self.image_size}: expected positive (width, height)")
        self.image_size = (int(w), int(h))
        pp = self.pixel_pitch_um
        pp = (float(pp), float(pp)) if np.isscalar(pp) else (float(pp[0]), float(pp[1]))
        if not (pp[0] > 0 and pp[1] > 0):
            raise InvalidInputError(f"camera {self.name!r}: pixel_pitch_um {self.pixel_pitch_um}: expected positive micrometres")
        self.pixel_pitch_um = pp
        bad = set(self.nominal) - set(PARAM_NAMES)
        if bad:
            raise ConfigError(f"camera {self.name!r}: unknown parameter(s) {sorted(bad)}; expected {list(PARAM_NAMES)}")

    @property
    def pitch_mm(self) -> tuple[float, float]:
        return (self.pixel_pitch_um[0] * 1e-3, self.pixel_pitch_um[1] * 1e-3)


@dataclass
class ImageMeasurements:
    """Measured image points of one image: indices into the object-point array and pixels.

    ``sigma_px`` (n,2) optional a-priori standard deviations; ``frame`` groups images of
    different cameras taken at the same instant (rig / relative orientation).
    """

    name: str
    camera: int
    point_index: np.ndarray  # (n,) int
    xy_px: np.ndarray  # (n,2)
    sigma_px: np.ndarray | None = None
    frame: str | None = None


@dataclass(frozen=True)
class ParameterTest:
    name: str
    value: float
    std: float
    t: float
    critical: float
    significant: bool


@dataclass
class CameraCalibration:
    """Calibrated intrinsics of one camera with precision (correction form, references' units)."""

    name: str
    image_size: tuple[int, int]
    pixel_pitch_um: tuple[float, float]
    params: np.ndarray  # (12,)
    std: np.ndarray  # (12,) NaN where not estimated
    covariance: np.ndarray  # (12,12)
    free: np.ndarray  # (12,) bool
    sigma_xy_px: tuple[float, float]  # σx, σy of an image coordinate (Table 4), px
    rms_px: float
    n_observations: int
    tests: list[ParameterTest] = field(default_factory=list)
    correlation_warnings: list[tuple[str, str, float]] = field(default_factory=list)

    @property
    def param_dict(self) -> dict[str, float]:
        return dict(zip(PARAM_NAMES, map(float, self.params)))

    @property
    def std_dict(self) -> dict[str, float]:
        return dict(zip(PARAM_NAMES, map(float, self.std)))

    @property
    def sigma_xy_um(self) -> tuple[float, float]:
        return (self.sigma_xy_px[0] * self.pixel_pitch_um[0], self.sigma_xy_px[1] * self.pixel_pitch_um[1])

    def correlation(self) -> tuple[list[str], np.ndarray]:
        """Names of the estimated parameters and their correlation matrix."""
        idx = np.nonzero(self.free)[0]
        C = self.covariance[np.ix_(idx, idx)]
        s = np.sqrt(np.diag(C))
        with np.errstate(invalid="ignore", divide="ignore"):
            rho = C / s[:, None] / s[None, :]
        return [PARAM_NAMES[i] for i in idx], rho

    def parameters_px(self) -> dict[str, tuple[float, float, str]]:
        """The parameters expressed in pixels: name -> (value, std, unit).

        c -> fx, fy (px); x0, y0 -> cx, cy (px, OpenCV origin); K_i -> K_i·pitch^(2i) (px^-2i);
        P_i -> P_i·pitch (px^-1); B unitless. Pitch = x pitch for the distortion terms.
        """
        px, py = (v * 1e-3 for v in self.pixel_pitch_um)
        w, h = self.image_size
        p, s = self.params, self.std
        out = {
            "fx": (p[0] / px, s[0] / px, "px"),
            "fy": (p[0] / py, s[0] / py, "px"),
            "cx": ((w - 1) / 2 + p[1] / px, s[1] / px, "px"),
            "cy": ((h - 1) / 2 - p[2] / py, s[2] / py, "px"),
        }
        for i in range(5):
            f = px ** (2 * (i + 1))
            out[f"K{i + 1}"] = (p[3 + i] * f, s[3 + i] * f, f"px^-{2 * (i + 1)}")
        out["P1"] = (p[8] * px, s[8] * px, "px^-1")
        out["P2"] = (p[9] * px, s[9] * px, "px^-1")
        out["B1"] = (p[10], s[10], "1")
        out["B2"] = (p[11], s[11], "1")
        return out


@dataclass
class ImageVerdict:
    """What happened to one image (no silent drops)."""

    name: str
    camera: int
    used: bool
    reason: str = ""
    n_points: int = 0
    n_blunders: int = 0
    rms_px: float = float("nan")
    R: np.ndarray | None = None  # cam_from_world
    t: np.ndarray | None = None
    pose_std: np.ndarray | None = None  # (6,) rotation increment (rad) and position (m): the projection
    # centre with the engine (its convention), the translation t with the dense LM


@dataclass
class RelativeOrientation:
    """``cam_from_reference`` of a rig member, with standard deviations (rotation rad, translation m)."""

    camera: int
    reference_camera: int
    R: np.ndarray
    t: np.ndarray
    std: np.ndarray  # (6,)
    n_frames: int

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(-self.R.T @ self.t))


@dataclass
class CalibrationResult:
    """Outcome of :func:`calibrate`. A failed solve is a value: check ``outcome``."""

    outcome: Outcome
    cameras: list[CameraCalibration]
    images: list[ImageVerdict]
    sigma0: float
    dof: int
    rms_px: float
    stage1: dict
    blunders: list[dict]
    relative: list[RelativeOrientation]
    obs_image: np.ndarray  # (N,) index into images (final used observations)
    obs_point: np.ndarray
    obs_xy: np.ndarray
    residuals_px: np.ndarray  # (N,2) observed - computed
    redundancy: np.ndarray  # (N,2)
    normalized_residuals: np.ndarray  # (N,2)
    snooping_test: str = ""
    solution: BundleSolution | None = None
    warnings: list[str] = field(default_factory=list)

    @property
    def images_used(self) -> list[str]:
        return [v.name for v in self.images if v.used]

    @property
    def images_rejected(self) -> dict[str, str]:
        return {v.name: v.reason for v in self.images if not v.used}


# ----------------------------------------------------------------------------------------------
def _nominal_vector(setup: CameraSetup, c_mm: float) -> np.ndarray:
    p = np.zeros(N_PARAMS)
    for k, v in setup.nominal.items():
        if v is not None:
            p[PARAM_NAMES.index(k)] = float(v)
    p[0] = c_mm
    return p


def _is_planar(xyz: np.ndarray) -> bool:
    if xyz.shape[0] < 4:
        return True
    c = xyz - xyz.mean(0)
    s = np.linalg.svd(c, compute_uv=False)
    return s[2] < 1e-6 * max(s[0], 1e-12)


def _pinhole_K(p: np.ndarray, setup: CameraSetup) -> np.ndarray:
    px, py = setup.pitch_mm
    w, h = setup.image_size
    return np.array([[p[0] / px, 0, (w - 1) / 2 + p[1] / px], [0, p[0] / py, (h - 1) / 2 - p[2] / py], [0, 0, 1.0]])


def _init_focal_planar(setup: CameraSetup, obj: list[np.ndarray], img: list[np.ndarray]) -> float | None:
    """Zhang initialisation of the focal length from views of a plane (cv2.initCameraMatrix2D)."""
    op = [o.astype(np.float32) for o in obj if o.shape[0] >= 4]
    ip = [i.astype(np.float32).reshape(-1, 1, 2) for o, i in zip(obj, img) if o.shape[0] >= 4]
    if len(op) < 2:
        return None
    # initCameraMatrix2D expects the plane as Z=0 in the object points' own frame
    op2 = []
    for o in op:
        c = o.mean(0)
        _, _, Vt = np.linalg.svd(o - c)
        op2.append(((o - c) @ Vt.T * np.array([1, 1, 0])).astype(np.float32))
    K = cv2.initCameraMatrix2D(op2, ip, setup.image_size, 1.0)
    f = 0.5 * (K[0, 0] + K[1, 1])
    if not np.isfinite(f) or f <= 0:
        return None
    return float(f * setup.pitch_mm[0])


def _resect(xyz: np.ndarray, xy: np.ndarray, K: np.ndarray, planar: bool):
    """Initial cam_from_world by PnP; returns (R, t) or None with reason."""
    obj = np.ascontiguousarray(xyz, dtype=np.float64)
    im = np.ascontiguousarray(xy, dtype=np.float64).reshape(-1, 1, 2)
    try:
        if planar:
            ok, rvec, tvec = cv2.solvePnP(obj, im, K, None, flags=cv2.SOLVEPNP_IPPE)
        else:
            ok, rvec, tvec = cv2.solvePnP(obj, im, K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return None, "resection (solvePnP) failed"
        rvec, tvec = cv2.solvePnPRefineLM(obj, im, K, None, rvec, tvec)
    except cv2.error as exc:
        return None, f"resection (solvePnP) failed: {str(exc).strip().splitlines()[-1]}"
    R, _ = cv2.Rodrigues(rvec)
    t = tvec.ravel()
    z = obj @ R.T + t
    if np.any(z[:, 2] <= 0):
        return None, "resection put target points behind the camera"
    return (R, t), ""


def calibrate(
    cameras: Sequence[CameraSetup],
    points: np.ndarray,
    images: Sequence[ImageMeasurements],
    *,
    point_std: np.ndarray | None = None,
    options: SelfCalibrationOptions | None = None,
    rig: bool = False,
    progress=None,
    initial: Mapping[int, np.ndarray] | None = None,
    initial_poses: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
) -> CalibrationResult:
    """Self-calibrate ``cameras`` from measured images of known object ``points``.

    Parameters
    ----------
    cameras : setups (image size, pixel pitch, nominal values; ``nominal['c_mm']`` required unless
        every image of that camera sees a planar target).
    points : (M, 3) object coordinates, metres.
    images : per-image measurements (indices into ``points``, pixels in the OpenCV convention).
    point_std : (M, 3) a-priori standard deviations of the object coordinates (m); points with
        finite positive values are adjusted as weighted unknowns, others are fixed.
    options : :class:`SelfCalibrationOptions`.
    rig : model images of different cameras sharing a ``frame`` as a rigid rig (first camera in
        each frame is the reference) and estimate the relative orientation. The cameras are then
        also solved with independent poses, and ``warnings`` says when a rig camera's RMS is more
        than ``options.rig_rms_warning_factor`` times its independent RMS.
    progress : optional callable ``progress(stage: str, done: int, total: int)``.
    initial : optional {camera index: (12,) parameters} to start stage 2 from (skips stage 1's
        nominal model for that camera; used by Monte-Carlo studies started at the truth).
    initial_poses : optional per-image (R, t) to skip resection.

    Returns
    -------
    CalibrationResult. Bad input raises (``InvalidInputError`` family); a failed solve is returned
    with ``outcome.success == False`` and the reason. ``warnings`` lists undetermined precision
    (standard deviations NaN, never 0) and a rig that does not fit.

    References
    ----------
    Fraser, C. S. (1997). Digital camera self-calibration. ISPRS J. Photogramm. Remote Sens. 52, 149-159.
    """
    opt = options or SelfCalibrationOptions()
    kw = dict(point_std=point_std, options=opt, progress=progress, initial=initial, initial_poses=initial_poses)
    res = _calibrate_once(cameras, points, images, rig=rig, **kw)
    if rig and res.relative and res.outcome.success and opt.rig_rms_warning_factor > 0:
        indep = _calibrate_once(cameras, points, images, rig=False, **kw)
        if indep.outcome.success:
            for ci, (cr, cs) in enumerate(zip(res.cameras, indep.cameras)):
                if np.isfinite(cr.rms_px) and np.isfinite(cs.rms_px) and cr.rms_px > opt.rig_rms_warning_factor * cs.rms_px:
                    fx_r = cr.parameters_px()["fx"][0]
                    fx_s = cs.parameters_px()["fx"][0]
                    res.warnings.append(
                        f"rig does not fit camera {cr.name!r}: RMS {cr.rms_px:.3f} px with the rig constraint against "
                        f"{cs.rms_px:.3f} px with independent poses (> {opt.rig_rms_warning_factor:g}x; fx {fx_r:.1f} "
                        f"against {fx_s:.1f} px); check frame synchronisation and pairing")
            lost = sorted(set(indep.images_used) - set(res.images_used))
            if lost:
                res.warnings.append(
                    f"rig does not fit {len(lost)} image(s) that independent poses use ({', '.join(lost[:5])}"
                    f"{' ...' if len(lost) > 5 else ''}): rejected under the rig constraint; check frame "
                    "synchronisation and pairing")
    return res


def _calibrate_once(
    cameras: Sequence[CameraSetup],
    points: np.ndarray,
    images: Sequence[ImageMeasurements],
    *,
    point_std: np.ndarray | None = None,
    options: SelfCalibrationOptions | None = None,
    rig: bool = False,
    progress=None,
    initial: Mapping[int, np.ndarray] | None = None,
    initial_poses: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
) -> CalibrationResult:
    """One solve of :func:`calibrate` (rig or independent poses); see there."""
    opt = options or SelfCalibrationOptions()
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidInputError(f"points: expected shape (M, 3) in metres, got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise InvalidInputError("points: non-finite object coordinates")
    if not cameras:
        raise InvalidInputError("cameras: expected at least one CameraSetup")
    if not images:
        raise TooFewPointsError("images: no image measurements given")
    M = points.shape[0]
    verdicts: list[ImageVerdict] = []
    usable: list[int] = []
    for k, im in enumerate(images):
        if not (0 <= im.camera < len(cameras)):
            raise InvalidInputError(f"image {im.name!r}: camera index {im.camera} out of range 0..{len(cameras) - 1}")
        pi = np.asarray(im.point_index, dtype=int)
        xy = np.asarray(im.xy_px, dtype=float)
        if xy.shape != (pi.size, 2):
            raise InvalidInputError(f"image {im.name!r}: xy_px shape {xy.shape} does not match {pi.size} point indices")
        if pi.size and (pi.min() < 0 or pi.max() >= M):
            raise InvalidInputError(f"image {im.name!r}: point index out of range 0..{M - 1}")
        v = ImageVerdict(im.name, im.camera, False, n_points=int(pi.size))
        finite = np.all(np.isfinite(xy), axis=1)
        if np.count_nonzero(finite) < opt.min_points_per_image:
            v.reason = f"only {int(np.count_nonzero(finite))} measured points (need >= {opt.min_points_per_image})"
        else:
            usable.append(k)
        verdicts.append(v)

    # nominal principal distance per camera
    cam_p: list[np.ndarray] = []
    for ci, cs in enumerate(cameras):
        if initial is not None and ci in initial:
            cam_p.append(np.asarray(initial[ci], float).copy())
            continue
        c = cs.nominal.get("c_mm")
        if c is None:
            ks = [k for k in usable if images[k].camera == ci]
            c = _init_focal_planar(cs, [points[np.asarray(images[k].point_index)] for k in ks],
                                   [np.asarray(images[k].xy_px, float) for k in ks])
            if c is None:
                for k in ks:
                    verdicts[k].reason = "camera has no nominal focal length and too few planar views to initialise it"
                usable = [k for k in usable if images[k].camera != ci]
                c = 1.0
        cam_p.append(_nominal_vector(cs, float(c)))

    # resection of every usable image
    poses: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for n_done, k in enumerate(list(usable)):
        im = images[k]
        if initial_poses is not None:
            poses[k] = (np.asarray(initial_poses[k][0], float), np.asarray(initial_poses[k][1], float))
            continue
        pi = np.asarray(im.point_index, int)
        xy = np.asarray(im.xy_px, float)
        fin = np.all(np.isfinite(xy), axis=1)
        xyz = points[pi[fin]]
        planar = _is_planar(xyz)
        if not planar and xyz.shape[0] < 6:
            verdicts[k].reason = f"only {xyz.shape[0]} non-coplanar points (need >= 6 for resection)"
            usable.remove(k)
            continue
        K = _pinhole_K(cam_p[im.camera], cameras[im.camera])
        Rt, why = _resect(xyz, xy[fin], K, planar)
        if Rt is None:
            verdicts[k].reason = why
            usable.remove(k)
            continue
        poses[k] = Rt
        if progress is not None:
            progress("resection", n_done + 1, len(images))
    if not usable:
        return _empty_result(verdicts, Termination.TOO_FEW_OBSERVATIONS, "no usable image: " +
                             "; ".join(f"{v.name}: {v.reason}" for v in verdicts[:5]))

    # observation table
    obs_img, obs_pt, obs_xy, obs_sig = [], [], [], []
    have_sigma = all(images[k].sigma_px is not None for k in usable)
    for k in usable:
        im = images[k]
        pi = np.asarray(im.point_index, int)
        xy = np.asarray(im.xy_px, float)
        sg = np.asarray(im.sigma_px, float) if im.sigma_px is not None else np.full(xy.shape, opt.default_sigma_px)
        fin = np.all(np.isfinite(xy), axis=1) & np.all(np.isfinite(sg) & (sg > 0), axis=1)
        obs_img.append(np.full(np.count_nonzero(fin), k))
        obs_pt.append(pi[fin])
        obs_xy.append(xy[fin])
        obs_sig.append(sg[fin])
    obs_img = np.concatenate(obs_img)
    obs_pt = np.concatenate(obs_pt)
    obs_xy = np.concatenate(obs_xy)
    obs_sig = np.concatenate(obs_sig)
    active = np.ones(obs_img.size, dtype=bool)
    blunders: list[dict] = []

    # rig structure
    frames_of = {k: images[k].frame for k in usable}
    rig_members: dict[int, int] = {}  # camera -> rig index
    ref_cam: int | None = None
    if rig:
        ref_cam = min(images[k].camera for k in usable)
        others = sorted({images[k].camera for k in usable} - {ref_cam})
        for ci in others:
            both = [f for f in {frames_of[k] for k in usable if images[k].camera == ci}
                    if f is not None and any(frames_of[j] == f and images[j].camera == ref_cam for j in usable)]
            if both:
                rig_members[ci] = len(rig_members)

    def build(cam_params, free_masks, active_mask):
        sel = np.nonzero(active_mask)[0]
        used_imgs = sorted(set(obs_img[sel].tolist()))
        # pose table
        pose_keys: list = []
        pose_of_img: dict[int, int] = {}
        rig_of_img: dict[int, int] = {}
        if rig and rig_members:
            frame_pose: dict[str, int] = {}
            for k in used_imgs:
                im = images[k]
                f = frames_of[k]
                if im.camera in rig_members and f is not None and any(
                        frames_of[j] == f and images[j].camera == ref_cam for j in used_imgs):
                    continue
                if im.camera == ref_cam and f is not None:
                    frame_pose[f] = len(pose_keys)
                pose_of_img[k] = len(pose_keys)
                pose_keys.append(k)
            for k in used_imgs:
                if k not in pose_of_img:
                    pose_of_img[k] = frame_pose[frames_of[k]]
                    rig_of_img[k] = rig_members[images[k].camera]
        else:
            for k in used_imgs:
                pose_of_img[k] = len(pose_keys)
                pose_keys.append(k)
        R = np.array([poses[k][0] for k in pose_keys])
        t = np.array([poses[k][1] for k in pose_keys])
        blocks = [CameraBlock(cam_params[ci], free_masks[ci], cameras[ci].image_size, cameras[ci].pitch_mm, cameras[ci].name)
                  for ci in range(len(cameras))]
        oc = np.array([images[k].camera for k in obs_img[sel]], dtype=int)
        op = np.array([pose_of_img[k] for k in obs_img[sel]], dtype=int)
        orig = np.array([rig_of_img.get(k, -1) for k in obs_img[sel]], dtype=int)
        G = len(rig_members)
        rigR = np.array([rig_init[g][0] for g in range(G)]) if G else None
        rigt = np.array([rig_init[g][1] for g in range(G)]) if G else None
        prob = BundleProblem(blocks, R, t, points, oc, op, obs_pt[sel], obs_xy[sel], obs_sig[sel], obs_rig=orig,
                             rig_R=rigR, rig_t=rigt, point_prior_std=point_std)
        return prob, sel, pose_keys

    rig_init: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def init_rig():
        for ci, g in rig_members.items():
            rels = []
            for k in usable:
                if images[k].camera != ci or frames_of[k] is None:
                    continue
                refs = [j for j in usable if images[j].camera == ref_cam and frames_of[j] == frames_of[k]]
                if refs:
                    R1, t1 = poses[refs[0]]
                    R2, t2 = poses[k]
                    Rr = R2 @ R1.T
                    rels.append((Rr, t2 - Rr @ t1))
            Rm = mean_rotation(np.array([r[0] for r in rels]))
            tm = np.median(np.array([r[1] for r in rels]), axis=0)
            rig_init[g] = (Rm, tm)

    def store(sol: BundleSolution, pose_keys):
        for j, k in enumerate(pose_keys):
            poses[k] = (sol.R[j], sol.t[j])
        for g in range(sol.rig_R.shape[0]):
            rig_init[g] = (sol.rig_R[g], sol.rig_t[g])

    def snoop(cam_params, free_masks, critical, use_apriori, stage_name):
        nonlocal active
        sol = None
        for rnd in range(opt.max_snooping_rounds + 1):
            prob, sel, pose_keys = build(cam_params, free_masks, active)
            sol = solve_bundle(prob, engine=opt.solver)
            if not sol.outcome.success:
                return sol, sel, pose_keys
            store(sol, pose_keys)
            cam_params = [cb.params for cb in sol.cameras]
            if not opt.snooping or rnd == opt.max_snooping_rounds:
                break
            w = sol.normalized_residuals
            if not use_apriori:
                w = w / sol.sigma0
            wmax = np.nanmax(np.abs(w), axis=1)
            wmax = np.where(np.isfinite(wmax), wmax, 0.0)
            bad = wmax > critical
            if not np.any(bad):
                break
            # the worst observation of each image
            removed = 0
            for k in set(obs_img[sel][bad].tolist()):
                cand = np.nonzero(bad & (obs_img[sel] == k))[0]
                j = cand[np.argmax(wmax[cand])]
                gi = sel[j]
                # keep at least the minimum per image
                if np.count_nonzero(active & (obs_img == k)) <= opt.min_points_per_image:
                    continue
                active[gi] = False
                removed += 1
                blunders.append({"stage": stage_name, "image": images[k].name, "point": int(obs_pt[gi]),
                                 "w": float(wmax[j]), "residual_px": [float(v) for v in sol.residuals_px[j]]})
            if removed == 0:
                break
        return sol, sel, pose_keys

    # ---- stage 1: nominal interior orientation, poses only --------------------------------
    fixed_masks = [np.zeros(N_PARAMS, dtype=bool) for _ in cameras]
    if rig_members:
        init_rig()
    stage1 = {}
    if initial is None:
        sol1, sel1, pk1 = snoop(cam_p, fixed_masks, opt.stage1_critical, False, "stage1")
        if progress is not None:
            progress("stage 1", 1, 1)
        if not sol1.outcome.success:
            return _empty_result(verdicts, sol1.outcome.termination, "stage 1: " + sol1.outcome.reason)
        rms1 = float(np.sqrt(np.mean(np.sum(sol1.residuals_px**2, axis=1))))
        stage1 = {"sigma0": sol1.sigma0, "rms_px": rms1, "n_observations": int(sel1.size),
                  "n_blunders": sum(1 for b in blunders if b["stage"] == "stage1"),
                  "c_mm": [float(p[0]) for p in cam_p]}

    # ---- stage 2: additional parameters free, data snooping --------------------------------
    free2 = opt.stage2_free()
    free_masks = [free2.copy() for _ in cameras]
    use_apriori = have_sigma
    crit = opt.critical_value
    for attempt in range(5):
        sol, sel, pose_keys = snoop(cam_p, free_masks, crit, use_apriori, "stage2")
        if progress is not None:
            progress("stage 2", 1, 1)
        if not sol.outcome.success:
            break
        cam_p = [cb.params for cb in sol.cameras]
        # per-image RMS; reject inconsistent images and repeat
        rms_img = {}
        for k in set(obs_img[sel].tolist()):
            m = obs_img[sel] == k
            rms_img[k] = float(np.sqrt(np.mean(np.sum(sol.residuals_px[m] ** 2, axis=1))))
        med = float(np.median(list(rms_img.values())))
        worst = [k for k, r in rms_img.items() if r > max(opt.max_image_rms_factor * med, 1.0)]
        if not worst or len(rms_img) - len(worst) < 2:
            break
        for k in worst:
            verdicts[k].reason = f"inconsistent: RMS {rms_img[k]:.2f} px after stage 2 (median of images {med:.2f} px)"
            active[obs_img == k] = False
    if sol.outcome.success and opt.snooping:
        # re-admit observations rejected in stage 1 that fit the full model (they were flagged
        # because the nominal model could not explain distortion, not because they are wrong)
        s1 = [i for i, b in enumerate(blunders) if b["stage"] == "stage1"]
        if s1:
            cam_p = [cb.params for cb in sol.cameras]
            inact = ~active & np.isin(obs_img, list({k for k in obs_img[sel]}))
            prob, isel, _ = build(cam_p, free_masks, active | inact)
            res_all, ok_all = residuals(prob)
            # re-admit everything that is not grossly wrong under the full model (|v| < 10 σ); the
            # stage-2 data snooping below then tests them properly (w with redundancy numbers).
            # A threshold at the critical value itself would keep out valid corner points whose
            # raw |v| exceeds it only because their redundancy is low.
            w = np.abs(res_all) / (obs_sig[isel] * (sol.sigma0 if not use_apriori else 1.0))
            back = isel[(np.max(w, axis=1) < 10.0) & ok_all & inact[isel]]
            if back.size:
                active[back] = True
                readm = {(images[obs_img[g]].name, int(obs_pt[g])) for g in back}
                blunders[:] = [b for b in blunders if (b["image"], b["point"]) not in readm]
                sol, sel, pose_keys = snoop(cam_p, free_masks, crit, use_apriori, "stage2")
    if not sol.outcome.success:
        return _empty_result(verdicts, sol.outcome.termination, "stage 2: " + sol.outcome.reason, stage1=stage1)
    return _assemble(sol, sel, pose_keys, cameras, images, verdicts, obs_img, obs_pt, obs_xy, active, blunders, stage1,
                     opt, rig_members, ref_cam, use_apriori)


def _assemble(sol, sel, pose_keys, cameras, images, verdicts, obs_img, obs_pt, obs_xy, active, blunders, stage1, opt,
              rig_members, ref_cam, use_apriori):
    res = sol.residuals_px
    oi = obs_img[sel]
    # image verdicts
    pose_of = {k: j for j, k in enumerate(pose_keys)}
    for k, v in enumerate(verdicts):
        m = oi == k
        if np.any(m):
            v.used = True
            v.reason = ""
            v.rms_px = float(np.sqrt(np.mean(np.sum(res[m] ** 2, axis=1))))
            v.n_blunders = int(np.count_nonzero((obs_img == k) & ~active))
            if k in pose_of:
                j = pose_of[k]
                v.R, v.t, v.pose_std = sol.R[j], sol.t[j], sol.pose_std[j]
        elif not v.reason:
            v.reason = "no observation left after blunder elimination"
    # per-camera statistics
    cams_out = []
    dof = sol.dof
    tcrit = float(stats.t.ppf(1 - opt.significance_alpha / 2, max(dof, 1)))
    cam_of_obs = np.array([images[k].camera for k in oi], dtype=int)
    for ci, cs in enumerate(cameras):
        m = cam_of_obs == ci
        cb = sol.cameras[ci]
        if np.any(m):
            # Table 4: σx, σy of an image coordinate from the residuals and their redundancy numbers
            sx = float(np.sqrt(np.sum(res[m, 0] ** 2) / max(np.sum(sol.redundancy[m, 0]), 1e-12)))
            sy = float(np.sqrt(np.sum(res[m, 1] ** 2) / max(np.sum(sol.redundancy[m, 1]), 1e-12)))
            rms = float(np.sqrt(np.mean(np.sum(res[m] ** 2, axis=1))))
        else:
            sx = sy = rms = float("nan")
        std = sol.camera_std[ci]
        cov = sol.camera_cov[ci]
        tests = []
        for name in ADDITIONAL:
            i = PARAM_NAMES.index(name)
            if cb.free[i]:
                if np.isfinite(std[i]) and std[i] > 0:
                    tv = abs(cb.params[i]) / std[i]
                else:  # undetermined precision: no test (never "significant" by a zero or NaN σ)
                    tv = float("nan")
                tests.append(ParameterTest(name, float(cb.params[i]), float(std[i]), float(tv), tcrit,
                                           bool(np.isfinite(tv) and tv > tcrit)))
        cc = CameraCalibration(cs.name, cs.image_size, cs.pixel_pitch_um, cb.params.copy(), std.copy(), cov.copy(),
                               cb.free.copy(), (sx, sy), rms, int(np.count_nonzero(m)), tests)
        names, rho = cc.correlation()
        for a in range(len(names)):
            for b in range(a + 1, len(names)):
                if abs(rho[a, b]) > opt.correlation_warning:
                    cc.correlation_warnings.append((names[a], names[b], float(rho[a, b])))
        cams_out.append(cc)
    rel = []
    for ci, g in rig_members.items():
        n_frames = len({images[k].frame for k in set(oi.tolist()) if images[k].camera == ci})
        rel.append(RelativeOrientation(ci, ref_cam, sol.rig_R[g], sol.rig_t[g], sol.rig_std[g], n_frames))
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    warns = []
    undet = [f"{cc.name}.{PARAM_NAMES[i]}" for cc in cams_out for i in np.flatnonzero(cc.free) if not np.isfinite(cc.std[i])]
    if dof <= 0 or not np.isfinite(sol.sigma0) or undet:
        warns.append(f"precision undetermined (redundancy {dof}, sigma0 {sol.sigma0:.4g}): standard deviations are NaN"
                     + (f" for {', '.join(undet[:6])}{' ...' if len(undet) > 6 else ''}" if undet else ""))
    return CalibrationResult(
        sol.outcome, cams_out, verdicts, sol.sigma0, dof, rms, stage1, blunders, rel, oi, obs_pt[sel], obs_xy[sel], res,
        sol.redundancy, sol.normalized_residuals,
        "Baarda (a-priori sigma)" if use_apriori else "Pope tau (a-posteriori sigma0)", sol, warns)


def _empty_result(verdicts, term, reason, stage1=None):
    for v in verdicts:
        if not v.reason:
            v.reason = f"calibration failed: {reason}"
    z = np.zeros((0, 2))
    return CalibrationResult(Outcome(term, reason), [], verdicts, float("nan"), 0, float("nan"), stage1 or {}, [], [],
                             np.zeros(0, int), np.zeros(0, int), z, z, z, z)
