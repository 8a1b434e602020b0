"""Common pieces of target detection: the result type, target descriptions, image normalisation.

Conventions (binding for every detector in :mod:`thermogrammetry.calibration.detect`):

* Pixel coordinates are OpenCV's: (0, 0) is the centre of the top-left pixel, x right, y down
  (``docs/conventions.md``).
* Targets are described by :mod:`thermogrammetry.targets` (``ChessboardSpec`` etc. here are the same
  classes). Object points are in **millimetres** in the target's own plane frame (z = 0), x along
  the columns, y along the rows, returned in OpenCV order (row-major: ``index = row * columns +
  column``); ``object_points_m()`` gives metres.
* ``Detection.object_ids`` index into ``spec.object_points()``.
* Every image gets a :class:`Detection` with ``found`` and a human-readable ``reason`` -- a missed
  target is a value, never an exception. Bad input (wrong dtype, shape, empty or constant image)
  raises :class:`~thermogrammetry.errors.InvalidInputError` subclasses.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import ConfigError, InvalidInputError, ShapeError
from ..targets import ChessboardTarget, CircleGridTarget, CodedCheckerboardTarget

__all__ = [
    "Detection",
    "ChessboardSpec",
    "CircleGridSpec",
    "CodedCheckerboardSpec",
    "ChessboardTarget",
    "CircleGridTarget",
    "CodedCheckerboardTarget",
    "spec_of",
    "to_gray_float",
    "normalize_to_u8",
    "clahe_u8",
    "flatten_background",
]


# --------------------------------------------------------------------------------------------------
# result type
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Detection:
    """The verdict of one image (compared by identity: it holds arrays).

    Attributes
    ----------
    image_id : str
        The caller's name of the image (file name, frame index, ...).
    found : bool
        True when the target was found and ``points_px`` holds its measured points.
    points_px : ndarray, shape (N, 2), float64
        Measured image points in pixels, OpenCV convention ((0, 0) = centre of the top-left pixel).
        ``(0, 2)`` when not found.
    object_ids : ndarray, shape (N,), int64
        Index of each point into ``spec.object_points()``.
    reason : str
        Why the target was (not) found: which detector/preprocessing succeeded, or why all failed.
    image_size : tuple of int
        ``(width, height)`` of the image in pixels.
    method : str
        Short name of the successful detector pass ("" when not found).
    """

    image_id: str
    found: bool
    points_px: np.ndarray
    object_ids: np.ndarray
    reason: str
    image_size: tuple[int, int] = (0, 0)
    method: str = ""
    extra: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def n_points(self) -> int:
        return int(self.points_px.shape[0])

    @staticmethod
    def failure(image_id: str, reason: str, image_size: tuple[int, int] = (0, 0)) -> "Detection":
        return Detection(
            image_id=str(image_id),
            found=False,
            points_px=np.zeros((0, 2)),
            object_ids=np.zeros(0, dtype=np.int64),
            reason=reason,
            image_size=image_size,
        )

    def object_points(self, spec) -> np.ndarray:
        """(N, 3) object points (mm) of the measured points, aligned with ``points_px``.

        ``spec``: the target description the detection was made with (a metre-unit view of
        :mod:`thermogrammetry.synthetic.targets` is unwrapped, so the result is always mm)."""
        from ..targets import as_target

        return as_target(spec, "spec").object_points()[self.object_ids]


# --------------------------------------------------------------------------------------------------
# target descriptions: one definition in thermogrammetry.targets (millimetres); the detector-side
# names are the same classes
# --------------------------------------------------------------------------------------------------
#: :class:`thermogrammetry.targets.ChessboardTarget` (millimetres; ``corner0_square`` resolves the 180° ambiguity)
ChessboardSpec = ChessboardTarget
#: :class:`thermogrammetry.targets.CircleGridTarget` (millimetres; ``diameter_mm`` optional)
CircleGridSpec = CircleGridTarget
#: :class:`thermogrammetry.targets.CodedCheckerboardTarget` (millimetres; ``from_parameters`` reads parameters.yaml)
CodedCheckerboardSpec = CodedCheckerboardTarget


def spec_of(spec, cls, name: str):
    """``spec`` as a millimetre :mod:`thermogrammetry.targets` description of type ``cls`` (metre-unit
    views from :mod:`thermogrammetry.synthetic.targets` are unwrapped); ConfigError naming ``name``
    (the detector-side alias, e.g. "ChessboardSpec") otherwise."""
    inner = spec if isinstance(spec, cls) else getattr(spec, "target", None)
    if not isinstance(inner, cls):
        raise ConfigError(f"spec: expected a {name} (thermogrammetry.targets.{cls.__name__}, millimetres), "
                          f"got {type(spec).__name__}")
    return inner


# --------------------------------------------------------------------------------------------------
# image normalisation
# --------------------------------------------------------------------------------------------------
def to_gray_float(image, name: str = "image") -> np.ndarray:
    """Validate an image and return it as a 2-D float32 array.

    Accepts uint8, uint16 (and other integer types) and float images, single channel (H, W) or
    (H, W, 1), or (H, W, 3/4) colour (converted with OpenCV's BGR luminance weights).
    Non-finite pixels (masked areas in float images) are replaced by the median of the finite ones.

    Raises
    ------
    ShapeError
        Not 2-D / 3-D, empty, or smaller than 8 x 8 pixels.
    InvalidInputError
        Unsupported dtype (bool, complex, object), no finite pixel, or a constant image.
    """
    try:
        arr = np.asarray(image)
    except Exception as exc:  # pragma: no cover - exotic objects
        raise InvalidInputError(f"{name}: cannot convert {type(image)!r} to an array: {exc}") from None
    if arr.dtype.kind not in "uif":
        raise InvalidInputError(
            f"{name}: unsupported dtype {arr.dtype}; expected an 8-bit, 16-bit (unsigned) integer or float image"
        )
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        a = arr[:, :, :3].astype(np.float32)
        arr = 0.114 * a[:, :, 0] + 0.587 * a[:, :, 1] + 0.299 * a[:, :, 2]
    if arr.ndim != 2:
        raise ShapeError(f"{name}: expected a (H, W) or (H, W, 1|3|4) image, got shape {arr.shape}")
    if arr.shape[0] < 8 or arr.shape[1] < 8:
        raise ShapeError(f"{name}: image of shape {arr.shape} is empty or too small; expected at least 8 x 8 pixels")
    out = arr.astype(np.float32, copy=True)
    finite = np.isfinite(out)
    if not finite.all():
        if not finite.any():
            raise InvalidInputError(f"{name}: no finite pixel in the image; expected at least some finite values")
        out[~finite] = np.median(out[finite])
    if float(out.max()) - float(out.min()) <= 0:
        raise InvalidInputError(f"{name}: constant image (all pixels = {float(out.flat[0])!r}); expected some contrast")
    return out


def normalize_to_u8(gray: np.ndarray, low_pct: float = 0.5, high_pct: float = 99.5) -> np.ndarray:
    """Percentile stretch of a float image to uint8 (low percentile → 0, high → 255, clipped).

    Thermal images use a small part of their dynamic range; 16-bit and float (kelvin) images must
    be mapped to 8 bit for OpenCV's detectors. Falls back to min/max when the percentiles coincide.
    """
    lo, hi = np.percentile(gray, [low_pct, high_pct])
    if hi <= lo:
        lo, hi = float(gray.min()), float(gray.max())
    scaled = (gray - lo) * (255.0 / (hi - lo))
    return np.clip(np.rint(scaled), 0, 255).astype(np.uint8)


def clahe_u8(u8: np.ndarray, clip_limit: float = 2.0, tiles: int = 8) -> np.ndarray:
    """Contrast-limited adaptive histogram equalisation (OpenCV CLAHE) of a uint8 image."""
    return cv2.createCLAHE(clipLimit=clip_limit, tileGridSize=(tiles, tiles)).apply(u8)


def flatten_background(gray: np.ndarray, sigma_px: float, *, clip_sd: float = 3.0) -> np.ndarray:
    """Local background removal and contrast normalisation of a float image, to uint8.

    ``hp = gray - G_sigma * gray`` (flat-field by a large Gaussian blur: removes a heater's hot spot,
    vignetting and other slowly varying backgrounds), then ``hp / sqrt(G_sigma * hp²)`` (local
    contrast normalisation: a pattern of a few tenths of a kelvin beside a board edge of several
    kelvin gets the same range), clipped at ``±clip_sd`` and mapped linearly to 0..255. Both steps
    are smooth, so the saddle points of a chessboard and the centroids of small discs stay put to
    first order.

    Parameters
    ----------
    gray : ndarray (H, W) float
    sigma_px : float
        Gaussian σ of the background (px); it should span a few squares / circle spacings.
    clip_sd : float
        Normalised values beyond ±clip_sd are clipped.

    Returns
    -------
    ndarray (H, W) uint8

    References
    ----------
    Vidas, S. et al. (2012). A mask-based approach for the geometric calibration of thermal-infrared
    cameras. IEEE TIM 61(6) 1625-1635 (low contrast of thermal targets).
    """
    g = np.asarray(gray, np.float32)
    hp = g - cv2.GaussianBlur(g, (0, 0), float(sigma_px), borderType=cv2.BORDER_REFLECT)
    sd = np.sqrt(cv2.GaussianBlur(hp * hp, (0, 0), float(sigma_px), borderType=cv2.BORDER_REFLECT))
    floor = max(float(np.median(sd)) * 0.05, 1e-12)
    z = hp / np.maximum(sd, floor)
    u = (np.clip(z, -clip_sd, clip_sd) + clip_sd) * (255.0 / (2 * clip_sd))
    return np.clip(np.rint(u), 0, 255).astype(np.uint8)


def image_size_of(gray: np.ndarray) -> tuple[int, int]:
    return (int(gray.shape[1]), int(gray.shape[0]))
