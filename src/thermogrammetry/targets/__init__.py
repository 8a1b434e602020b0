"""Calibration targets: the one description used by rendering (:mod:`thermogrammetry.synthetic.targets`)
and detection (:mod:`thermogrammetry.calibration.detect`).

Units and frames (binding)
--------------------------
* Every length is in **millimetres** and says so in its name (``square_mm``, ``spacing_mm``,
  ``diameter_mm``, ``margin_mm``, ``marker_mm``).
* The target frame: plane z = 0, origin at object point 0 (the top-left inner corner / circle
  centre), x to the right along a row, y down the columns.
* :meth:`object_points` returns ``(N, 3)`` float64 **millimetres** in OpenCV order (row-major:
  ``index = row * columns + column``), so ``cv2.findChessboardCorners`` / ``cv2.findCirclesGrid``
  results with ``patternSize = (columns, rows)`` line up index by index;
  :meth:`object_points_m` is the same in metres (``× 1e-3``), the unit of poses.

  - symmetric circle grid: point ``i·columns + j`` at ``(j·s, i·s, 0)``;
  - asymmetric circle grid (``CALIB_CB_ASYMMETRIC_GRID``): point ``i·columns + j`` at
    ``((2j + i mod 2)·s, i·s, 0)`` — circles in a row ``2s`` apart, rows ``s`` apart;
  - chessboard / coded checkerboard: inner corner ``i·inner_columns + j`` at ``(j·s, i·s, 0)``.

* :meth:`classify` labels target-plane points (mm) as :data:`SURROUND` (beside the board),
  :data:`BOARD` or :data:`FEATURE`; the renderer gives each part its own temperature.

The old names stay importable: ``calibration.detect_common.ChessboardSpec`` / ``CircleGridSpec`` /
``CodedCheckerboardSpec`` *are* these classes (same millimetre fields), and
``synthetic.targets.ChessboardTarget`` / ... are thin metre-unit views (``spacing_m`` etc.) whose
``.target`` is one of these.

References
----------
.. [1] OpenCV 4.x, "Camera calibration With OpenCV" tutorial, ``calcBoardCornerPositions`` in
   samples/cpp/tutorial_code/calib3d/camera_calibration/camera_calibration.cpp (object-point order).
.. [2] Schramm, S., Ebert, J., Rangel, J., Schmoll, R., Kroll, A. (2021). Iterative corner detection of a
   coded checkerboard target for the geometric calibration of infrared cameras. J. Sens. Sens. Syst.
   10(2), 207-218 (MRT coded checkerboard, ``parameters.yaml``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError

__all__ = [
    "circle_centroid_bias",
    "SURROUND",
    "BOARD",
    "FEATURE",
    "ChessboardTarget",
    "CircleGridTarget",
    "CodedCheckerboardTarget",
    "Target",
    "as_target",
]

#: labels returned by ``classify``
SURROUND, BOARD, FEATURE = 0, 1, 2


def _int(owner: str, name: str, value, minimum: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or int(value) < minimum:
        raise ConfigError(f"{owner}.{name}={value!r}: expected an integer >= {minimum}")
    return int(value)


def _length(owner: str, name: str, value, unit: str = "millimetres") -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    if not np.isfinite(v) or v <= 0:
        raise ConfigError(f"{owner}.{name}={value!r}: expected a positive finite length in {unit}")
    return v


def _grid(rows: int, columns: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column index of every point in OpenCV (row-major) order, as float64."""
    r, c = np.mgrid[0:rows, 0:columns]
    return r.ravel().astype(np.float64), c.ravel().astype(np.float64)


def _in_box(x, y, box):
    xmin, xmax, ymin, ymax = box
    with np.errstate(invalid="ignore"):
        return (x >= xmin) & (x <= xmax) & (y >= ymin) & (y <= ymax)


def _corner_neighbours(corners_mm: np.ndarray, square_mm: float) -> np.ndarray:
    h = 0.5 * square_mm
    d = np.array([[h, 0, 0], [-h, 0, 0], [0, h, 0], [0, -h, 0]], dtype=np.float64)
    return (corners_mm[:, None, :] + d[None]).reshape(-1, 3)


class _PlanarTarget:
    """Shared unit helpers (the subclasses define ``object_points`` in mm)."""

    def object_points_m(self) -> np.ndarray:
        """(N, 3) float64 object points in **metres** (:meth:`object_points` × 1e-3), OpenCV order."""
        return self.object_points() * 1e-3


class _SquareGrid(_PlanarTarget):
    """Layout shared by the boards of squares (fields ``inner_columns``, ``inner_rows``, ``square_mm``,
    ``margin_mm``): inner corners row-major, board extent, visibility points."""

    @property
    def pattern_size(self) -> tuple[int, int]:
        """OpenCV ``patternSize`` (inner_columns, inner_rows)."""
        return (self.inner_columns, self.inner_rows)

    @property
    def n_points(self) -> int:
        return self.inner_columns * self.inner_rows

    def object_points(self) -> np.ndarray:
        """(inner_columns·inner_rows, 3) float64 inner corners in **mm**, OpenCV (row-major) order, z = 0."""
        r, c = _grid(self.inner_rows, self.inner_columns)
        s = self.square_mm
        return np.column_stack([c * s, r * s, np.zeros(r.size)])

    def extent_mm(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the board including the border, mm."""
        s, m = self.square_mm, self.margin_mm
        return (-s - m, self.inner_columns * s + m, -s - m, self.inner_rows * s + m)

    def outline_points(self) -> np.ndarray:
        """(4N, 3) mm: each inner corner's neighbours half a square away (visibility checks)."""
        return _corner_neighbours(self.object_points(), self.square_mm)


# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ChessboardTarget(_SquareGrid):
    """A chessboard described by its **inner** corners (OpenCV ``patternSize = (inner_columns, inner_rows)``).

    ``(inner_columns + 1) × (inner_rows + 1)`` squares, colours alternating, surrounded by a border of
    width ``margin_mm`` in the *board* colour.

    Parameters
    ----------
    inner_columns, inner_rows : int
        Inner corners per row and per column (``--corners 6x5`` → 6, 5); at least 2 each.
    square_mm : float
        Side of one square, millimetres.
    corner0_square : {"dark", "bright", "any"}
        Colour, in the image, of the square diagonally outside inner corner 0 (the top-left square,
        x < 0 and y < 0). "dark" (default): it is a *board* part — the cool/low-signal colour of a
        heated board, also the colour of the border — so it shares its colour with the border and
        the squares diagonal to it; "bright": it is a *feature* (hot) square. The detector uses it to
        resolve the 180° ambiguity of boards whose two diagonal corner squares differ in colour (one
        of ``inner_columns``, ``inner_rows`` even); "any" keeps the geometric rule only (corner 0
        nearest the image's top-left) and cannot be rendered.
    margin_mm : float or None
        Border around the squares (default: one square).

    Notes
    -----
    ``classify`` and the detector agree on "dark": with the default temperatures
    (``feature_k > board_k``) the top-left square of a ``corner0_square="dark"`` board is rendered at
    ``board_k`` and is the darker one in the image.
    """

    inner_columns: int
    inner_rows: int
    square_mm: float
    corner0_square: str = "dark"
    margin_mm: float | None = None

    def __post_init__(self):
        n = type(self).__name__
        object.__setattr__(self, "inner_columns", _int(n, "inner_columns", self.inner_columns, 2))
        object.__setattr__(self, "inner_rows", _int(n, "inner_rows", self.inner_rows, 2))
        s = _length(n, "square_mm", self.square_mm)
        object.__setattr__(self, "square_mm", s)
        if self.corner0_square not in ("dark", "bright", "any"):
            raise ConfigError(f"{n}.corner0_square={self.corner0_square!r}: expected 'dark', 'bright' or 'any'")
        m = s if self.margin_mm is None else _length(n, "margin_mm", self.margin_mm)
        object.__setattr__(self, "margin_mm", m)

    def classify(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Part label (SURROUND=0, BOARD=1, FEATURE=2) of target-plane points, int8, shape of ``x_mm``.

        Square ``(a, b)``, ``a = floor(x/s) + 1`` in 0..inner_columns, ``b = floor(y/s) + 1``, is a
        BOARD (dark) square when ``a + b`` is even and ``corner0_square == "dark"`` (so the top-left
        square ``(0, 0)`` is BOARD), FEATURE otherwise; the "bright" board is the opposite.
        """
        if self.corner0_square == "any":
            raise ConfigError(f"{type(self).__name__}.corner0_square='any' leaves the square colours open; "
                              "expected 'dark' or 'bright' to render the board")
        x, y = np.asarray(x_mm, dtype=np.float64), np.asarray(y_mm, dtype=np.float64)
        s = self.square_mm
        lab = np.where(_in_box(x, y, self.extent_mm()), BOARD, SURROUND).astype(np.int8)
        with np.errstate(invalid="ignore"):
            a = np.floor(x / s) + 1
            b = np.floor(y / s) + 1
            squares = (a >= 0) & (a <= self.inner_columns) & (b >= 0) & (b <= self.inner_rows)
            even = np.mod(a + b, 2) == 0
            feature = squares & (~even if self.corner0_square == "dark" else even)
        lab[feature & np.isfinite(x) & np.isfinite(y)] = FEATURE
        return lab


# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CircleGridTarget(_PlanarTarget):
    """A grid of circles (mask holes in front of a warm emitter, or printed dots), OpenCV
    ``patternSize = (columns, rows)``.

    Parameters
    ----------
    columns, rows : int
        Circles per row and number of rows (``--grid 7x4``); at least 2 each.
    spacing_mm : float
        Symmetric grid: distance between neighbouring centres. Asymmetric grid: OpenCV's
        ``squareSize`` — rows are ``spacing_mm`` apart, centres at ``((2j + i mod 2)·s, i·s)``, so
        neighbours in one row are ``2·s`` apart and the nearest neighbours ``√2·s``.
    asymmetric : bool
        OpenCV asymmetric (staggered) grid.
    diameter_mm : float or None
        Circle diameter; smaller than the nearest-neighbour distance. Needed to render the grid and
        for the detector's perspective-bias correction (seed 003: 20 mm holes at 50 mm spacing);
        ``None`` disables that correction and cannot be rendered.
    margin_mm : float or None
        Mask border around the outermost circle centres (default: one spacing).

    The circles are FEATURE parts (the warm emitter seen through the holes), the mask is BOARD.
    """

    columns: int
    rows: int
    spacing_mm: float
    asymmetric: bool = False
    diameter_mm: float | None = None
    margin_mm: float | None = None

    def __post_init__(self):
        n = type(self).__name__
        object.__setattr__(self, "columns", _int(n, "columns", self.columns, 2))
        object.__setattr__(self, "rows", _int(n, "rows", self.rows, 2))
        s = _length(n, "spacing_mm", self.spacing_mm)
        object.__setattr__(self, "spacing_mm", s)
        if not isinstance(self.asymmetric, (bool, np.bool_)):
            raise ConfigError(f"{n}.asymmetric={self.asymmetric!r}: expected True or False")
        object.__setattr__(self, "asymmetric", bool(self.asymmetric))
        if self.diameter_mm is not None:
            d = _length(n, "diameter_mm", self.diameter_mm)
            if d >= self.nearest_neighbour_mm:
                raise ConfigError(f"{n}.diameter_mm={d!r}: expected < the nearest-neighbour distance "
                                  f"{self.nearest_neighbour_mm:.6g} mm (circles would touch)")
            object.__setattr__(self, "diameter_mm", d)
        m = s if self.margin_mm is None else _length(n, "margin_mm", self.margin_mm)
        object.__setattr__(self, "margin_mm", m)

    @property
    def pattern_size(self) -> tuple[int, int]:
        """OpenCV ``patternSize`` (columns, rows)."""
        return (self.columns, self.rows)

    @property
    def n_points(self) -> int:
        return self.columns * self.rows

    @property
    def nearest_neighbour_mm(self) -> float:
        """Distance between nearest circle centres: ``s`` (symmetric) or ``√2·s`` (asymmetric)."""
        return self.spacing_mm * (np.sqrt(2.0) if self.asymmetric else 1.0)

    def object_points(self) -> np.ndarray:
        """(columns·rows, 3) float64 circle centres in **mm**, OpenCV order, z = 0."""
        i, j = _grid(self.rows, self.columns)
        s = self.spacing_mm
        x = (2.0 * j + np.mod(i, 2)) * s if self.asymmetric else j * s
        return np.column_stack([x, i * s, np.zeros(i.size)])

    def extent_mm(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the mask, mm."""
        p = self.object_points()
        m = self.margin_mm
        return (p[:, 0].min() - m, p[:, 0].max() + m, p[:, 1].min() - m, p[:, 1].max() + m)

    def _need_diameter(self) -> float:
        if self.diameter_mm is None:
            raise ConfigError(f"{type(self).__name__}.diameter_mm=None: the circle size is needed here; "
                              "expected a diameter in millimetres")
        return self.diameter_mm

    def classify(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Part label (SURROUND=0, BOARD=1 mask, FEATURE=2 circle) of target-plane points, int8."""
        r2 = (0.5 * self._need_diameter()) ** 2
        x, y = np.asarray(x_mm, dtype=np.float64), np.asarray(y_mm, dtype=np.float64)
        s = self.spacing_mm
        lab = np.where(_in_box(x, y, self.extent_mm()), BOARD, SURROUND).astype(np.int8)
        inside = np.zeros(lab.shape, dtype=bool)
        with np.errstate(invalid="ignore"):
            # a circle (radius < s/2 symmetric, < s/√2 asymmetric) can reach at most the two rows
            # around y; within a row only the nearest column
            i0 = np.floor(y / s)
            for i in (i0, i0 + 1):
                i = np.clip(i, 0, self.rows - 1)
                if self.asymmetric:
                    shift = np.mod(i, 2) * s
                    j = np.clip(np.rint((x - shift) / (2 * s)), 0, self.columns - 1)
                    cx = 2 * j * s + shift
                else:
                    j = np.clip(np.rint(x / s), 0, self.columns - 1)
                    cx = j * s
                inside |= (x - cx) ** 2 + (y - i * s) ** 2 <= r2
        lab[inside & np.isfinite(x) & np.isfinite(y)] = FEATURE
        return lab

    def outline_points(self, n: int = 16) -> np.ndarray:
        """(N·n, 3) mm: points on every circle's rim (visibility checks)."""
        c = self.object_points()
        a = 2 * np.pi * np.arange(n) / n
        r = 0.5 * self._need_diameter()
        rim = np.stack([r * np.cos(a), r * np.sin(a), np.zeros(n)], axis=1)
        return (c[:, None, :] + rim[None, :, :]).reshape(-1, 3)


# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CodedCheckerboardTarget(_SquareGrid):
    """Checkerboard with an ArUco marker on its central corner (Schramm et al. 2021, MRT coded target).

    The defaults describe the 60x45 cm target of ``../shared/data/ir_coded_checkerboard``
    (``parameters.yaml``: gridSize 50.5 mm, arucoSize 161.5 mm, 11 x 9 inner corners, 4 x 4 squares
    blanked around the marker, dictionary ``custom_dictionary(1, 3)`` = ``extendDictionary(1, 3)``,
    bottom-left square white); :meth:`from_parameters` reads that file's mapping.

    Object frame (mm): origin at the top-left inner corner as seen on the artwork (marker upright), x
    right, y down, z = 0; :meth:`object_points` returns all ``inner_columns·inner_rows`` grid corners
    row-major, including those hidden by the marker area, which are never reported
    (:meth:`valid_ids` lists the usable ones).

    Parts for rendering: *bright* parts (light squares, the blank area, white marker cells, the
    border) are FEATURE, *dark* parts (dark squares, black marker cells) are BOARD — a heated print
    whose dark ink emits differently (swap the temperatures for the opposite polarity).

    Parameters
    ----------
    inner_columns, inner_rows : int
        Inner corners of the full grid (odd; the marker sits on the central corner).
    square_mm : float
        Square side.
    marker_mm : float
        Side of the ArUco marker (outer black border), centred on the central corner.
    hidden_squares : int
        The marker area blanks ``hidden_squares × hidden_squares`` squares centred on the central
        corner (even, 0 for none).
    marker_bits : int
        Inner bits per side of the marker (3 for ``DICT_3X3_1``).
    marker_id : int
        Id in the dictionary.
    dictionary_size : int
        Markers in the custom dictionary (``extendDictionary(dictionary_size, marker_bits, seed 0)``).
    top_left_square : {"dark", "bright"}
        Colour of the square diagonally outside corner 0 in the artwork. MRT: bottom-left square
        white with 9 corner rows → top-left square dark.
    predefined_dictionary : str
        A predefined ``cv2.aruco`` dictionary name (e.g. "DICT_4X4_1000") instead of the custom one;
        "" (default) for the custom dictionary.
    margin_mm : float or None
        Bright border around the squares (default: one square).
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
    margin_mm: float | None = None

    def __post_init__(self):
        n = type(self).__name__
        for name in ("inner_columns", "inner_rows"):
            v = _int(n, name, getattr(self, name), 3)
            if v % 2 == 0:
                raise ConfigError(f"{n}.{name}={v}: expected an odd number (the marker sits on the central corner)")
            object.__setattr__(self, name, v)
        s = _length(n, "square_mm", self.square_mm)
        object.__setattr__(self, "square_mm", s)
        object.__setattr__(self, "marker_mm", _length(n, "marker_mm", self.marker_mm))
        h = _int(n, "hidden_squares", self.hidden_squares, 0)
        if h % 2:
            raise ConfigError(f"{n}.hidden_squares={h}: expected an even number (the blank area is centred on a corner)")
        object.__setattr__(self, "hidden_squares", h)
        object.__setattr__(self, "marker_bits", _int(n, "marker_bits", self.marker_bits, 3))
        object.__setattr__(self, "dictionary_size", _int(n, "dictionary_size", self.dictionary_size, 1))
        mid = _int(n, "marker_id", self.marker_id, 0)
        if not self.predefined_dictionary and mid >= self.dictionary_size:
            raise ConfigError(f"{n}.marker_id={mid}: expected 0 <= id < dictionary_size={self.dictionary_size}")
        object.__setattr__(self, "marker_id", mid)
        if self.top_left_square not in ("dark", "bright"):
            raise ConfigError(f"{n}.top_left_square={self.top_left_square!r}: expected 'dark' or 'bright'")
        if self.predefined_dictionary:
            import cv2

            name = self.predefined_dictionary
            if not (isinstance(name, str) and name.startswith("DICT_") and hasattr(cv2.aruco, name)):
                raise ConfigError(f"{n}.predefined_dictionary={name!r}: not a cv2.aruco dictionary "
                                  "(expected e.g. 'DICT_4X4_1000', or '' for the custom one)")
        m = s if self.margin_mm is None else _length(n, "margin_mm", self.margin_mm)
        object.__setattr__(self, "margin_mm", m)

    @classmethod
    def from_parameters(cls, params: dict) -> "CodedCheckerboardTarget":
        """Build from the MRT ``parameters.yaml`` mapping.

        Keys used: gridSize (mm), arucoSize (mm), gridMaxHeight, gridMaxWidth, aruCoHiddenSize,
        aruco_dict, bottomLeftField; other keys are ignored (they describe that project's calibration
        runs, not the target). A missing key or a bad value raises :class:`ConfigError` naming it.
        """
        if not isinstance(params, dict):
            raise ConfigError(f"coded checkerboard parameters: expected a mapping, got {type(params).__name__}")
        need = ("gridSize", "arucoSize", "gridMaxHeight", "gridMaxWidth", "aruCoHiddenSize", "aruco_dict", "bottomLeftField")
        missing = [k for k in need if k not in params]
        if missing:
            raise ConfigError(f"coded checkerboard parameters: missing key(s) {missing}; expected {list(need)}")
        d = str(params["aruco_dict"]).replace("aruco.", "").upper()
        if not d.startswith("DICT_") or "X" not in d or "_" not in d[5:]:
            raise ConfigError(f"aruco_dict={params['aruco_dict']!r}: expected 'aruco.DICT_<b>X<b>_<n>'")
        bits, n = d[5:].split("X", 1)[0], d.rsplit("_", 1)[1]
        try:
            bits_i, n_i = int(bits), int(n)
        except ValueError:
            raise ConfigError(f"aruco_dict={params['aruco_dict']!r}: expected 'aruco.DICT_<b>X<b>_<n>'") from None
        import cv2

        # the MRT code builds DICT_3X3_1 as custom_dictionary(1, 3); other names are OpenCV's
        # predefined dictionaries (aruco.Dictionary_get)
        predefined = "" if d == "DICT_3X3_1" or not hasattr(cv2.aruco, d) else d
        bl = str(params["bottomLeftField"]).lower()
        if bl not in ("white", "black"):
            raise ConfigError(f"bottomLeftField={params['bottomLeftField']!r}: expected 'white' or 'black'")

        def _as_int(key):
            try:
                return int(params[key])
            except (TypeError, ValueError):
                raise ConfigError(f"{key}={params[key]!r}: expected an integer") from None

        rows = _as_int("gridMaxHeight")
        # the squares diagonally outside the bottom-left and the top-left corner are `rows` squares
        # apart along the column: same colour when rows is even
        bl_dark = bl == "black"
        tl_dark = bl_dark if rows % 2 == 0 else not bl_dark
        return cls(
            inner_columns=_as_int("gridMaxWidth"),
            inner_rows=rows,
            square_mm=params["gridSize"],
            marker_mm=params["arucoSize"],
            hidden_squares=_as_int("aruCoHiddenSize"),
            marker_bits=bits_i,
            predefined_dictionary=predefined,
            dictionary_size=n_i,
            top_left_square="dark" if tl_dark else "bright",
        )

    @property
    def center_mm(self) -> np.ndarray:
        """(2,) position of the central corner (= marker centre), mm."""
        return np.array([(self.inner_columns - 1) / 2, (self.inner_rows - 1) / 2]) * self.square_mm

    def marker_corners_mm(self) -> np.ndarray:
        """(4, 2) marker corners, mm, ArUco order (top-left, top-right, bottom-right, bottom-left)."""
        h = self.marker_mm / 2
        return self.center_mm + np.array([[-h, -h], [h, -h], [h, h], [-h, h]])

    def square_is_dark(self, col_idx, row_idx) -> np.ndarray:
        """Artwork colour of the square whose top-left corner is inner corner (col_idx, row_idx);
        indices may run from -1 (the squares outside the first row/column)."""
        first_dark = self.top_left_square == "dark"  # the square at (-1, -1)
        parity = (np.asarray(col_idx) + np.asarray(row_idx)) % 2 == 0
        return parity == first_dark

    def _square_blank(self, col_idx, row_idx) -> np.ndarray:
        h = self.hidden_squares
        lo_c = (self.inner_columns - 1) // 2 - h // 2
        lo_r = (self.inner_rows - 1) // 2 - h // 2
        col_idx, row_idx = np.asarray(col_idx), np.asarray(row_idx)
        return (col_idx >= lo_c) & (col_idx < lo_c + h) & (row_idx >= lo_r) & (row_idx < lo_r + h)

    def square_color_dark(self, col_idx, row_idx) -> np.ndarray:
        """Effective colour (True = dark) of squares, the blank area around the marker bright."""
        return self.square_is_dark(col_idx, row_idx) & ~self._square_blank(col_idx, row_idx)

    def valid_ids(self) -> np.ndarray:
        """Indices of the grid corners that are true checkerboard saddles (their four squares keep the
        alternating pattern once the blank area around the marker is accounted for)."""
        r, c = np.mgrid[0 : self.inner_rows, 0 : self.inner_columns]
        r, c = r.ravel(), c.ravel()
        tl = self.square_color_dark(c - 1, r - 1)
        tr = self.square_color_dark(c, r - 1)
        bl = self.square_color_dark(c - 1, r)
        br = self.square_color_dark(c, r)
        return np.flatnonzero((tl == br) & (tr == bl) & (tl != tr))

    def dictionary(self):
        """The ``cv2.aruco.Dictionary`` of the marker (predefined, or the MRT custom one)."""
        import cv2

        if self.predefined_dictionary:
            return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.predefined_dictionary))
        # cv2.aruco.custom_dictionary(n, bits) of OpenCV < 4.7 is extendDictionary(n, bits, Dictionary(), 0)
        return cv2.aruco.extendDictionary(int(self.dictionary_size), int(self.marker_bits), cv2.aruco.Dictionary(), 0)

    def marker_bits_matrix(self) -> np.ndarray:
        """(bits+2, bits+2) uint8 cells of the marker, 1 = white, including the black border."""
        import cv2

        n = self.marker_bits + 2
        img = cv2.aruco.generateImageMarker(self.dictionary(), int(self.marker_id), n, borderBits=1)
        return (img > 127).astype(np.uint8)

    def classify(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Part label of target-plane points (mm): FEATURE = bright, BOARD = dark, SURROUND outside."""
        x, y = np.asarray(x_mm, dtype=np.float64), np.asarray(y_mm, dtype=np.float64)
        s = self.square_mm
        lab = np.where(_in_box(x, y, self.extent_mm()), FEATURE, SURROUND).astype(np.int8)
        with np.errstate(invalid="ignore"):
            ci = np.floor(x / s)  # square index: its top-left corner is inner corner (ci, ri)
            ri = np.floor(y / s)
            squares = (ci >= -1) & (ci < self.inner_columns) & (ri >= -1) & (ri < self.inner_rows)
            ci_s = np.where(squares, ci, 0).astype(np.intp)
            ri_s = np.where(squares, ri, 0).astype(np.intp)
            dark = squares & self.square_color_dark(ci_s, ri_s)
            bits = self.marker_bits_matrix()
            n = bits.shape[0]
            cell = self.marker_mm / n
            x0, y0 = self.center_mm - self.marker_mm / 2
            u = np.floor((x - x0) / cell)
            v = np.floor((y - y0) / cell)
            inm = (u >= 0) & (u < n) & (v >= 0) & (v < n)
            ui = np.where(inm, u, 0).astype(np.intp)
            vi = np.where(inm, v, 0).astype(np.intp)
            dark = np.where(inm, bits[vi, ui] == 0, dark)
        lab[dark & np.isfinite(x) & np.isfinite(y)] = BOARD
        return lab


#: any of the target descriptions
Target = ChessboardTarget | CircleGridTarget | CodedCheckerboardTarget
_TARGET_TYPES = (ChessboardTarget, CircleGridTarget, CodedCheckerboardTarget)


def as_target(obj, name: str = "target"):
    """The millimetre description behind ``obj``: ``obj`` itself when it is one of the target classes,
    ``obj.target`` for the metre-unit views of :mod:`thermogrammetry.synthetic.targets`.

    Raises
    ------
    ConfigError
        Anything else.
    """
    if isinstance(obj, _TARGET_TYPES):
        return obj
    inner = getattr(obj, "target", None)
    if isinstance(inner, _TARGET_TYPES):
        return inner
    raise ConfigError(f"{name}={obj!r}: expected a ChessboardTarget, CircleGridTarget or CodedCheckerboardTarget "
                      "(thermogrammetry.targets)")


def circle_centroid_bias(camera, R: np.ndarray, t: np.ndarray, centres_m: np.ndarray, radius_m: float,
                         n_outline: int = 256) -> np.ndarray:
    """Centroid of each imaged circle minus the image of its centre, (N, 2) px.

    Parameters
    ----------
    camera : thermogrammetry.Camera (any model; its ``project`` includes the distortion)
    R, t : cam_from_target rotation (3, 3) and translation (3,), metres.
    centres_m : (N, 3) circle centres in the target plane (z = 0), metres.
    radius_m : circle radius, metres.
    n_outline : points on each outline (the polygon's area centroid converges as 1/n²).
    """
    a = np.linspace(0.0, 2 * np.pi, n_outline, endpoint=False)
    ring = np.column_stack([np.cos(a), np.sin(a), np.zeros_like(a)]) * radius_m
    c = np.asarray(centres_m, float)
    pts = (c[:, None, :] + ring[None]).reshape(-1, 3)
    xy = camera.project(pts @ R.T + t).reshape(len(c), n_outline, 2)
    x, y = xy[..., 0], xy[..., 1]
    x1, y1 = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cr = x * y1 - x1 * y
    A = 0.5 * cr.sum(axis=1)
    cx = ((x + x1) * cr).sum(axis=1) / (6 * A)
    cy = ((y + y1) * cr).sum(axis=1) / (6 * A)
    centre = camera.project(c @ R.T + t)
    return np.column_stack([cx, cy]) - centre


# ring-coded marks on a circle grid (seed 003); imported last: the module builds on CircleGridTarget
from .coded_marks import (  # noqa: E402
    SEED003_MARKS,
    CodedCircleGridTarget,
    code_bits_of,
    match_ring_code,
    ring_codes,
    seed003_coded_grid,
)

__all__ += ["CodedCircleGridTarget", "SEED003_MARKS", "ring_codes", "code_bits_of", "match_ring_code",
            "seed003_coded_grid"]
