"""Common pieces of target detection: the result type, target descriptions, image normalisation.

Conventions (binding for every detector in :mod:`thermogrammetry.calibration.detect`):

* Pixel coordinates are OpenCV's: (0, 0) is the centre of the top-left pixel, x right, y down
  (``docs/conventions.md``).
* Target object points are in **millimetres** in the target's own plane frame (z = 0), x along the
  columns, y along the rows, returned in OpenCV order (row-major: ``index = row * columns + column``).
  Multiply by ``1e-3`` for metres.
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

__all__ = [
    "Detection",
    "ChessboardSpec",
    "CircleGridSpec",
    "CodedCheckerboardSpec",
    "to_gray_float",
    "normalize_to_u8",
    "clahe_u8",
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
        """(N, 3) object points (mm) of the measured points, aligned with ``points_px``."""
        return spec.object_points()[self.object_ids]


# --------------------------------------------------------------------------------------------------
# target descriptions
# --------------------------------------------------------------------------------------------------
def _positive_int(name: str, value, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) < minimum:
        raise ConfigError(f"{name}: expected an integer >= {minimum}, got {value!r}")
    return int(value)


def _positive_float(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: expected a positive number, got {value!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise ConfigError(f"{name}: expected a positive finite number, got {value!r}")
    return v


@dataclass(frozen=True)
class ChessboardSpec:
    """A chessboard described by its **inner** corners (OpenCV ``patternSize = (columns, rows)``).

    Parameters
    ----------
    inner_columns, inner_rows : int
        Inner corners per row and per column (``--corners 6x5`` → columns=6, rows=5).
    square_mm : float
        Side of one square in millimetres.
    corner0_square : {"dark", "bright", "any"}
        Colour (in the image as given) of the board square diagonally outside corner 0. Used to
        resolve the 180° ambiguity of boards whose two diagonal corner squares differ in colour
        (one of ``inner_columns``, ``inner_rows`` even). A heated board may appear inverted; set
        "bright" then, or "any" to keep the geometric rule only (corner 0 nearest the image's
        top-left). Ignored for colour-symmetric boards.
    """

    inner_columns: int
    inner_rows: int
    square_mm: float
    corner0_square: str = "dark"

    def __post_init__(self):
        _positive_int("inner_columns", self.inner_columns, 2)
        _positive_int("inner_rows", self.inner_rows, 2)
        object.__setattr__(self, "square_mm", _positive_float("square_mm", self.square_mm))
        if self.corner0_square not in ("dark", "bright", "any"):
            raise ConfigError(f"corner0_square: expected 'dark', 'bright' or 'any', got {self.corner0_square!r}")

    @property
    def pattern_size(self) -> tuple[int, int]:
        return (self.inner_columns, self.inner_rows)

    @property
    def n_points(self) -> int:
        return self.inner_columns * self.inner_rows

    def object_points(self) -> np.ndarray:
        """(columns*rows, 3) float64 corner coordinates in mm, OpenCV order (row-major), z = 0."""
        r, c = np.mgrid[0 : self.inner_rows, 0 : self.inner_columns]
        return np.column_stack([c.ravel() * self.square_mm, r.ravel() * self.square_mm, np.zeros(r.size)])


@dataclass(frozen=True)
class CircleGridSpec:
    """A grid of circles (mask holes or printed dots), OpenCV ``patternSize = (columns, rows)``.

    Parameters
    ----------
    columns, rows : int
        Circles per row and number of rows (``--grid 7x4``).
    spacing_mm : float
        Symmetric grid: distance between neighbouring centres. Asymmetric grid: OpenCV's
        ``squareSize`` convention -- the row pitch; centres are at ``((2 j + i % 2) s, i s)``, so
        neighbours in one row are ``2 s`` apart.
    asymmetric : bool
        OpenCV asymmetric (staggered) grid.
    diameter_mm : float or None
        Circle diameter; needed for the perspective-bias correction (seed 003: 20 mm holes at 50 mm
        spacing). ``None`` disables that correction.
    """

    columns: int
    rows: int
    spacing_mm: float
    asymmetric: bool = False
    diameter_mm: float | None = None

    def __post_init__(self):
        _positive_int("columns", self.columns, 2)
        _positive_int("rows", self.rows, 2)
        object.__setattr__(self, "spacing_mm", _positive_float("spacing_mm", self.spacing_mm))
        if not isinstance(self.asymmetric, (bool, np.bool_)):
            raise ConfigError(f"asymmetric: expected True or False, got {self.asymmetric!r}")
        if self.diameter_mm is not None:
            d = _positive_float("diameter_mm", self.diameter_mm)
            pitch = self.spacing_mm * (np.sqrt(2.0) if self.asymmetric else 1.0)
            if d >= pitch:
                raise ConfigError(f"diameter_mm={d} must be smaller than the nearest-neighbour distance {pitch:.3f} mm")
            object.__setattr__(self, "diameter_mm", d)

    @property
    def pattern_size(self) -> tuple[int, int]:
        return (self.columns, self.rows)

    @property
    def n_points(self) -> int:
        return self.columns * self.rows

    def object_points(self) -> np.ndarray:
        """(columns*rows, 3) float64 centre coordinates in mm, OpenCV order, z = 0."""
        i, j = np.mgrid[0 : self.rows, 0 : self.columns]
        i, j = i.ravel(), j.ravel()
        s = self.spacing_mm
        if self.asymmetric:
            x = (2 * j + i % 2) * s
        else:
            x = j * s
        return np.column_stack([x.astype(float), (i * s).astype(float), np.zeros(i.size)])


@dataclass(frozen=True)
class CodedCheckerboardSpec:
    """Checkerboard with an ArUco marker in its middle (Schramm et al. 2021, MRT coded target).

    The default values describe the 60x45 cm target of ``../shared/data/ir_coded_checkerboard``
    (``parameters.yaml``: gridSize 50.5 mm, arucoSize 161.5 mm, 11 x 9 inner corners, 4 x 4 squares
    blanked around the marker, dictionary ``custom_dictionary(1, 3)`` = ``extendDictionary(1, 3)``,
    bottom-left square white).

    Object frame (mm): origin at the top-left inner corner of the 11 x 9 grid as seen on the artwork
    (marker upright), x right along the columns, y down along the rows, z = 0; ``object_points()``
    returns all ``inner_columns * inner_rows`` grid corners in row-major order, including the ones
    hidden by the marker area, which are never reported (``valid_ids()`` lists the usable ones).

    Parameters
    ----------
    inner_columns, inner_rows : int
        Inner corners of the full grid (odd numbers; the marker sits on the central corner).
    square_mm : float
        Square side.
    marker_mm : float
        Side of the ArUco marker (outer black border), centred on the central corner.
    hidden_squares : int
        The marker area blanks ``hidden_squares x hidden_squares`` squares centred on the central
        corner.
    marker_bits : int
        Inner bits per side of the marker (3 for ``DICT_3X3_1``).
    marker_id : int
        Id in the dictionary.
    dictionary_size : int
        Markers in the custom dictionary (``extendDictionary(dictionary_size, marker_bits, seed 0)``).
    predefined_dictionary : str
        Name of a predefined ``cv2.aruco`` dictionary (e.g. "DICT_4X4_1000") to use instead of the
        custom one; "" (default) for the custom dictionary.
    top_left_square : {"dark", "bright"}
        Colour of the board square diagonally outside corner 0 (top-left), in the printed artwork.
        The MRT target: bottom-left square white with 9 corner rows → top-left square black.
    """

    inner_columns: int = 11
    inner_rows: int = 9
    square_mm: float = 50.5
    marker_mm: float = 161.5
    hidden_squares: int = 4
    marker_bits: int = 3
    marker_id: int = 0
    dictionary_size: int = 1
    top_left_square: str = "dark"
    predefined_dictionary: str = ""

    def __post_init__(self):
        for n in ("inner_columns", "inner_rows"):
            v = _positive_int(n, getattr(self, n), 3)
            if v % 2 == 0:
                raise ConfigError(f"{n}: the marker sits on the central corner, expected an odd number, got {v}")
        _positive_float("square_mm", self.square_mm)
        _positive_float("marker_mm", self.marker_mm)
        _positive_int("hidden_squares", self.hidden_squares, 0)
        _positive_int("marker_bits", self.marker_bits, 3)
        _positive_int("dictionary_size", self.dictionary_size, 1)
        if not 0 <= int(self.marker_id) < int(self.dictionary_size):
            raise ConfigError(f"marker_id: expected 0 <= id < {self.dictionary_size}, got {self.marker_id!r}")
        if self.top_left_square not in ("dark", "bright"):
            raise ConfigError(f"top_left_square: expected 'dark' or 'bright', got {self.top_left_square!r}")
        if self.predefined_dictionary and not (
            self.predefined_dictionary.startswith("DICT_") and hasattr(cv2.aruco, self.predefined_dictionary)
        ):
            raise ConfigError(f"predefined_dictionary: {self.predefined_dictionary!r} is not a cv2.aruco dictionary "
                              "(expected e.g. 'DICT_4X4_1000', or '' for the custom one)")

    @classmethod
    def from_parameters(cls, params: dict) -> "CodedCheckerboardSpec":
        """Build from the MRT ``parameters.yaml`` mapping (keys gridSize, arucoSize, gridMaxHeight,
        gridMaxWidth, aruCoHiddenSize, aruco_dict, bottomLeftField; other keys are ignored as they
        describe that project's calibration runs, not the target)."""
        need = ("gridSize", "arucoSize", "gridMaxHeight", "gridMaxWidth", "aruCoHiddenSize", "aruco_dict", "bottomLeftField")
        missing = [k for k in need if k not in params]
        if missing:
            raise ConfigError(f"coded checkerboard parameters: missing key(s) {missing}; expected {list(need)}")
        d = str(params["aruco_dict"]).replace("aruco.", "").upper()
        if not d.startswith("DICT_") or "X" not in d:
            raise ConfigError(f"aruco_dict: expected 'aruco.DICT_<b>X<b>_<n>', got {params['aruco_dict']!r}")
        bits, n = d[5:].split("X", 1)[0], d.rsplit("_", 1)[1]
        # the MRT code builds DICT_3X3_1 as custom_dictionary(1, 3); other names are OpenCV's
        # predefined dictionaries (aruco.Dictionary_get)
        predefined = "" if d == "DICT_3X3_1" or not hasattr(cv2.aruco, d) else d
        rows = int(params["gridMaxHeight"])
        bl = str(params["bottomLeftField"]).lower()
        if bl not in ("white", "black"):
            raise ConfigError(f"bottomLeftField: expected 'white' or 'black', got {params['bottomLeftField']!r}")
        # the squares diagonally outside the bottom-left and the top-left corner are `rows` squares
        # apart along the column: same colour when rows is even.
        bl_dark = bl == "black"
        tl_dark = bl_dark if rows % 2 == 0 else not bl_dark
        return cls(
            inner_columns=int(params["gridMaxWidth"]),
            inner_rows=rows,
            square_mm=float(params["gridSize"]),
            marker_mm=float(params["arucoSize"]),
            hidden_squares=int(params["aruCoHiddenSize"]),
            marker_bits=int(bits),
            predefined_dictionary=predefined,
            dictionary_size=int(n),
            top_left_square="dark" if tl_dark else "bright",
        )

    @property
    def n_points(self) -> int:
        return self.inner_columns * self.inner_rows

    @property
    def center_mm(self) -> np.ndarray:
        """(2,) position of the central corner (= marker centre) in mm."""
        return np.array([(self.inner_columns - 1) / 2, (self.inner_rows - 1) / 2]) * self.square_mm

    def object_points(self) -> np.ndarray:
        """(columns*rows, 3) float64 grid corners in mm, row-major, z = 0 (hidden ones included)."""
        r, c = np.mgrid[0 : self.inner_rows, 0 : self.inner_columns]
        return np.column_stack([c.ravel() * self.square_mm, r.ravel() * self.square_mm, np.zeros(r.size)])

    def marker_corners_mm(self) -> np.ndarray:
        """(4, 2) marker corners in mm in ArUco order (top-left, top-right, bottom-right, bottom-left
        of the upright marker)."""
        h = self.marker_mm / 2
        return self.center_mm + np.array([[-h, -h], [h, -h], [h, h], [-h, h]])

    def square_is_dark(self, col_idx: np.ndarray, row_idx: np.ndarray) -> np.ndarray:
        """Colour of the square whose top-left corner is inner corner (col_idx, row_idx); indices may
        run from -1 (the squares outside the first row/column)."""
        first_dark = self.top_left_square == "dark"  # the square at (-1, -1)
        parity = (np.asarray(col_idx) + np.asarray(row_idx)) % 2 == 0
        return parity == first_dark

    def _square_blank(self, col_idx, row_idx) -> np.ndarray:
        """True for squares inside the blank area around the marker (square indices as above)."""
        h = self.hidden_squares
        cc, cr = (self.inner_columns - 1) // 2, (self.inner_rows - 1) // 2
        lo_c, lo_r = cc - h // 2, cr - h // 2
        col_idx, row_idx = np.asarray(col_idx), np.asarray(row_idx)
        return (col_idx >= lo_c) & (col_idx < lo_c + h) & (row_idx >= lo_r) & (row_idx < lo_r + h)

    def square_color_dark(self, col_idx, row_idx) -> np.ndarray:
        """Effective colour (True = dark) of squares, with the blank area around the marker bright."""
        return self.square_is_dark(col_idx, row_idx) & ~self._square_blank(col_idx, row_idx)

    def valid_ids(self) -> np.ndarray:
        """Indices of the grid corners that are true checkerboard saddles: their four squares keep
        the alternating pattern once the blank area around the marker (bright) is accounted for."""
        r, c = np.mgrid[0 : self.inner_rows, 0 : self.inner_columns]
        r, c = r.ravel(), c.ravel()
        tl = self.square_color_dark(c - 1, r - 1)
        tr = self.square_color_dark(c, r - 1)
        bl = self.square_color_dark(c - 1, r)
        br = self.square_color_dark(c, r)
        ok = (tl == br) & (tr == bl) & (tl != tr)
        return np.flatnonzero(ok)


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


def image_size_of(gray: np.ndarray) -> tuple[int, int]:
    return (int(gray.shape[1]), int(gray.shape[0]))
