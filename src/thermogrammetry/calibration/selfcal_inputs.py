"""What :func:`~thermogrammetry.calibration.selfcal.calibrate` takes: its options, the cameras to calibrate
and the measured image points."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from .._validate import config_keys
from ..errors import ConfigError, InvalidInputError
from .bundle import PARAM_NAMES

__all__ = ["SelfCalibrationOptions", "CameraSetup", "ImageMeasurements", "STAGE2_PARAMS"]

STAGE2_PARAMS = ("c_mm", "x0_mm", "y0_mm", "K1", "K2", "K3", "P1", "P2")


@dataclass(frozen=True)
class SelfCalibrationOptions:
    """Typed options of :func:`calibrate` (``from_dict`` rejects unknown keys).

    Attributes
    ----------
    k45 : also estimate K4, K5 (Khodaei et al. 2015).
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
