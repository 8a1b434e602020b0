"""What :func:`~thermogrammetry.calibration.selfcal.calibrate` takes: its options, the cameras to calibrate
and the measured image points."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from .._validate import config_keys
from ..camera.models import CameraModel
from ..errors import ConfigError, InvalidInputError
from .bundle import CALIBRATION_MODELS, PARAM_NAMES, param_names

__all__ = ["SelfCalibrationOptions", "CameraSetup", "ImageMeasurements", "STAGE2_PARAMS", "STAGE2_PARAMS_OPENCV",
           "calibration_model"]

#: estimated in stage 2 by default, photogrammetric model (Yastikli & Guler 2013)
STAGE2_PARAMS = ("c_mm", "x0_mm", "y0_mm", "K1", "K2", "K3", "P1", "P2")
#: estimated in stage 2 by default, OpenCV model: what ``cv2.calibrateCamera`` estimates with flags = 0
STAGE2_PARAMS_OPENCV = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def calibration_model(value) -> CameraModel:
    """``value`` as one of the models a calibration estimates (case-insensitive); ConfigError listing them otherwise."""
    valid = ", ".join(repr(m.value) for m in CALIBRATION_MODELS)
    try:
        m = CameraModel(value)
    except (InvalidInputError, ValueError):
        m = None
    if m not in CALIBRATION_MODELS:
        raise ConfigError(f"model {value!r}: a calibration estimates one of {valid}")
    return m


@dataclass(frozen=True)
class SelfCalibrationOptions:
    """Typed options of :func:`calibrate` (``from_dict`` rejects unknown keys).

    Attributes
    ----------
    model : what is estimated: ``"photogrammetric"`` (the correction form of Brown 1971 / Fraser 1997;
        stage 2 frees :data:`STAGE2_PARAMS`) or ``"opencv"`` (the forward form of ``cv2.calibrateCamera``;
        stage 2 frees :data:`STAGE2_PARAMS_OPENCV`, as OpenCV does with flags = 0).
    k45 : photogrammetric model: also estimate K4, K5 (Khodaei et al. 2015).
    affinity : photogrammetric model: also estimate B1, B2.
    rational : opencv model: also estimate k4, k5, k6 (``cv2.CALIB_RATIONAL_MODEL``).
    fixed : names of parameters (of ``model``) to keep at their nominal value in stage 2 (e.g. ``("P1", "P2")``;
        ``("k3",)`` is ``cv2.CALIB_FIX_K3``).
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

    model: CameraModel = CameraModel.PHOTOGRAMMETRIC
    k45: bool = False
    affinity: bool = False
    rational: bool = False
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
        object.__setattr__(self, "model", calibration_model(self.model))
        object.__setattr__(self, "fixed", tuple(self.fixed))
        if self.solver not in ("adjustment", "dense"):
            raise ConfigError(f"solver = {self.solver!r}: expected 'adjustment' or 'dense'")
        names = param_names(self.model)
        bad = [n for n in self.fixed if n not in names]
        if bad:
            raise ConfigError(f"fixed: unknown parameter(s) {bad} of the {self.model.value} model; expected names from "
                              f"{list(names)}")
        if self.model is CameraModel.OPENCV and (self.k45 or self.affinity):
            flag = "k45" if self.k45 else "affinity"
            raise ConfigError(f"{flag} = True: K4, K5, B1 and B2 are parameters of the photogrammetric model; the opencv "
                              "model estimates fx and fy apart already and takes rational = True for k4, k5, k6")
        if self.model is CameraModel.PHOTOGRAMMETRIC and self.rational:
            raise ConfigError("rational = True: k4, k5, k6 are parameters of the opencv model; the photogrammetric model "
                              "takes k45 = True for K4, K5")
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

    @property
    def param_names(self) -> tuple[str, ...]:
        """Parameter layout of :attr:`model`."""
        return param_names(self.model)

    def stage2_names(self) -> tuple[str, ...]:
        """The parameters stage 2 estimates, in layout order."""
        if self.model is CameraModel.OPENCV:
            names = list(STAGE2_PARAMS_OPENCV) + (["k4", "k5", "k6"] if self.rational else [])
        else:
            names = list(STAGE2_PARAMS) + (["K4", "K5"] if self.k45 else []) + (["B1", "B2"] if self.affinity else [])
        return tuple(n for n in self.param_names if n in names and n not in self.fixed)

    def stage2_free(self) -> np.ndarray:
        """(P,) bool over :attr:`param_names`: what stage 2 estimates."""
        names = self.stage2_names()
        return np.array([n in names for n in self.param_names])


@dataclass
class CameraSetup:
    """A camera to calibrate: image size (px), pixel pitch (µm; scalar or (x, y)) and nominal values.

    ``nominal`` maps parameter names to starting values: the correction-form names, or for a calibration
    in the opencv model the names of that model (``fx``, ``k1``, ...); ``c_mm`` (the nominal focal length
    in mm, either model) is required unless the target is planar (then it may be ``None`` and is
    initialised from the images by Zhang's method, ``cv2.initCameraMatrix2D``).
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
        known = set(PARAM_NAMES) | set(param_names(CameraModel.OPENCV))
        bad = set(self.nominal) - known
        if bad:
            raise ConfigError(f"camera {self.name!r}: unknown parameter(s) {sorted(bad)}; expected names of the "
                              f"photogrammetric model {list(PARAM_NAMES)} or of the opencv model "
                              f"{list(param_names(CameraModel.OPENCV))}")

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
