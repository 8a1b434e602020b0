"""What :func:`~thermogrammetry.calibration.selfcal.calibrate` returns: the calibrated cameras with their
precision and parameter tests, the verdict on every image, rig relative orientations, and the
:class:`CalibrationResult` assembled from the final bundle solution."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from ..camera.models import CameraModel
from ..results import Outcome
from .bundle import BundleSolution, param_names, param_units

__all__ = [
    "ParameterTest", "CameraCalibration", "ImageVerdict", "RelativeOrientation", "CalibrationResult", "ADDITIONAL",
    "ADDITIONAL_OPENCV", "assemble", "empty_result",
]

#: parameters given a significance test (H0: value = 0), photogrammetric model
ADDITIONAL = ("x0_mm", "y0_mm", "K1", "K2", "K3", "K4", "K5", "P1", "P2", "B1", "B2")
#: the same for the opencv model: the distortion terms and the skew (its principal point is measured from the
#: top-left pixel, so "cx = 0" is no hypothesis)
ADDITIONAL_OPENCV = ("skew", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


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
    """Calibrated intrinsics of one camera with precision, in the model that was estimated (``model``:
    the correction form in the references' units, or OpenCV's forward form in px)."""

    name: str
    image_size: tuple[int, int]
    pixel_pitch_um: tuple[float, float]
    params: np.ndarray  # (P,) layout param_names
    std: np.ndarray  # (P,) NaN where not estimated
    covariance: np.ndarray  # (P,P)
    free: np.ndarray  # (P,) bool
    sigma_xy_px: tuple[float, float]  # σx, σy of an image coordinate (Table 4), px
    rms_px: float
    n_observations: int
    tests: list[ParameterTest] = field(default_factory=list)
    correlation_warnings: list[tuple[str, str, float]] = field(default_factory=list)
    model: CameraModel = CameraModel.PHOTOGRAMMETRIC

    @property
    def param_names(self) -> tuple[str, ...]:
        return param_names(self.model)

    @property
    def param_units(self) -> tuple[str, ...]:
        return param_units(self.model)

    @property
    def param_dict(self) -> dict[str, float]:
        return dict(zip(self.param_names, map(float, self.params)))

    @property
    def std_dict(self) -> dict[str, float]:
        return dict(zip(self.param_names, map(float, self.std)))

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
        return [self.param_names[i] for i in idx], rho

    def parameters_px(self) -> dict[str, tuple[float, float, str]]:
        """The parameters expressed in pixels: name -> (value, std, unit).

        Photogrammetric model: c -> fx, fy (px); x0, y0 -> cx, cy (px, OpenCV origin); K_i -> K_i·pitch^(2i)
        (px^-2i); P_i -> P_i·pitch (px^-1); B unitless. Pitch = x pitch for the distortion terms.
        OpenCV model: the parameters as they are (fx fy cx cy skew in px, the distortion terms unitless).
        """
        if self.model is CameraModel.OPENCV:
            return {n: (float(v), float(s), u) for n, v, s, u in zip(self.param_names, self.params, self.std,
                                                                    self.param_units)}
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


def assemble(sol, sel, pose_keys, cameras, images, verdicts, obs_img, obs_pt, obs_xy, active, blunders, stage1, opt,
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
        names = cb.param_names
        for name in (ADDITIONAL_OPENCV if cb.model is CameraModel.OPENCV else ADDITIONAL):
            i = names.index(name)
            if cb.free[i]:
                if np.isfinite(std[i]) and std[i] > 0:
                    tv = abs(cb.params[i]) / std[i]
                else:  # undetermined precision: no test (never "significant" by a zero or NaN σ)
                    tv = float("nan")
                tests.append(ParameterTest(name, float(cb.params[i]), float(std[i]), float(tv), tcrit,
                                           bool(np.isfinite(tv) and tv > tcrit)))
        cc = CameraCalibration(cs.name, cs.image_size, cs.pixel_pitch_um, cb.params.copy(), std.copy(), cov.copy(),
                               cb.free.copy(), (sx, sy), rms, int(np.count_nonzero(m)), tests, model=cb.model)
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
    undet = [f"{cc.name}.{cc.param_names[i]}" for cc in cams_out for i in np.flatnonzero(cc.free) if not np.isfinite(cc.std[i])]
    if dof <= 0 or not np.isfinite(sol.sigma0) or undet:
        warns.append(f"precision undetermined (redundancy {dof}, sigma0 {sol.sigma0:.4g}): standard deviations are NaN"
                     + (f" for {', '.join(undet[:6])}{' ...' if len(undet) > 6 else ''}" if undet else ""))
    return CalibrationResult(
        sol.outcome, cams_out, verdicts, sol.sigma0, dof, rms, stage1, blunders, rel, oi, obs_pt[sel], obs_xy[sel], res,
        sol.redundancy, sol.normalized_residuals,
        "Baarda (a-priori sigma)" if use_apriori else "Pope tau (a-posteriori sigma0)", sol, warns)


def empty_result(verdicts, term, reason, stage1=None):
    for v in verdicts:
        if not v.reason:
            v.reason = f"calibration failed: {reason}"
    z = np.zeros((0, 2))
    return CalibrationResult(Outcome(term, reason), [], verdicts, float("nan"), 0, float("nan"), stage1 or {}, [], [],
                             np.zeros(0, int), np.zeros(0, int), z, z, z, z)
