"""Calibration target images as a thermal camera sees them, with exact ground truth.

Targets lie in the plane z = 0 of their own frame (x right along a row, y down the columns, metres);
a pose is ``cam_from_target``. Rendering is by **supersampled inverse mapping**: every pixel is split
into S×S sub-pixel samples, each sample is unprojected through the camera model (so distortion is the
model's, exactly), intersected with the target plane and classified (feature / board / surround). The
pixel's *signal* is the area-weighted mean of the parts' signals (radiance-linear, not temperature);
the sensor then blurs, vignettes, converts to apparent temperature and adds noise
(:mod:`thermogrammetry.synthetic.sensor`).

Object-point order is OpenCV's, so ``cv2.findCirclesGrid`` / ``cv2.findChessboardCorners`` results with
``patternSize = (columns, rows)`` line up with :meth:`object_points` index by index:

* symmetric circle grid: point ``i·columns + j`` at ``(j·s, i·s, 0)``;
* asymmetric circle grid (OpenCV's ``CALIB_CB_ASYMMETRIC_GRID``): point ``i·columns + j`` at
  ``((2j + i mod 2)·s, i·s, 0)`` — circles in a row are ``2s`` apart, rows are ``s`` apart and every
  other row is shifted by ``s`` (the convention of OpenCV's calibration sample and ``acircles_pattern``);
* chessboard: inner corner ``i·inner_columns + j`` at ``(j·s, i·s, 0)``.

The returned ``points_px`` are the camera model's projections of the exact circle centres / corners.
(For circles of finite size the centre of the imaged ellipse differs from the projected centre by the
perspective eccentricity, ~``f r² sin 2α / (2 Z²)`` px; that is a property of the measurement, not of the
rendering, and a detector's business.)

References
----------
.. [1] OpenCV 4.x documentation, "Camera calibration With OpenCV" tutorial and ``calcBoardCornerPositions``
   in samples/cpp/tutorial_code/calib3d/camera_calibration/camera_calibration.cpp (object-point order).
.. [2] Khodaei et al. (seed 003): mask circle grid held in front of a warm monitor (emissivity contrast).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError, InvalidInputError
from ._render import as_pose, camera_size, iter_sample_rays
from .radiance import BandPlanckCurve, SignalCurve
from .sensor import SensorEffects, apply_sensor_effects

__all__ = [
    "CircleGridTarget",
    "ChessboardTarget",
    "CodedCheckerboardTarget",
    "TargetTemperatures",
    "RenderedTarget",
    "render_target_image",
    "render_target_signal",
]

SURROUND, BOARD, FEATURE = 0, 1, 2


def _pos_int(v, name):
    if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 1:
        raise ConfigError(f"{name}={v!r}: expected a positive integer")
    return int(v)


def _pos_float(v, name):
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}={v!r}: expected a positive number (metres)") from None
    if not np.isfinite(f) or f <= 0:
        raise ConfigError(f"{name}={v!r}: expected a positive number (metres)")
    return f


@dataclass(frozen=True)
class CircleGridTarget:
    """Mask circle grid (holes in a cool mask in front of a warm emitter), OpenCV ``patternSize=(columns, rows)``.

    Attributes
    ----------
    columns, rows : int
        Circles per row and number of rows (OpenCV ``patternSize`` width × height).
    spacing_m : float
        Symmetric: centre distance in a row and between rows. Asymmetric: OpenCV's "square size" —
        rows are ``spacing_m`` apart and circles in a row ``2·spacing_m`` apart.
    diameter_m : float
        Circle diameter (must be smaller than ``spacing_m`` so circles never touch).
    asymmetric : bool
    margin_m : float or None
        Mask border around the outermost circle centres (default: one spacing).
    """

    columns: int
    rows: int
    spacing_m: float
    diameter_m: float
    asymmetric: bool = False
    margin_m: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "columns", _pos_int(self.columns, "CircleGridTarget.columns"))
        object.__setattr__(self, "rows", _pos_int(self.rows, "CircleGridTarget.rows"))
        s = _pos_float(self.spacing_m, "CircleGridTarget.spacing_m")
        d = _pos_float(self.diameter_m, "CircleGridTarget.diameter_m")
        if d >= s:
            raise ConfigError(f"CircleGridTarget.diameter_m={d!r}: expected < spacing_m={s!r} (circles would touch)")
        object.__setattr__(self, "spacing_m", s)
        object.__setattr__(self, "diameter_m", d)
        object.__setattr__(self, "asymmetric", bool(self.asymmetric))
        m = s if self.margin_m is None else _pos_float(self.margin_m, "CircleGridTarget.margin_m")
        object.__setattr__(self, "margin_m", m)

    @property
    def pattern_size(self) -> tuple[int, int]:
        """OpenCV ``patternSize`` (columns, rows)."""
        return (self.columns, self.rows)

    def object_points(self) -> np.ndarray:
        """(columns·rows, 3) circle centres in OpenCV order (row-major over ``rows``), metres, z = 0."""
        i, j = np.meshgrid(np.arange(self.rows), np.arange(self.columns), indexing="ij")
        i = i.ravel().astype(np.float64)
        j = j.ravel().astype(np.float64)
        s = self.spacing_m
        x = (2.0 * j + (i % 2)) * s if self.asymmetric else j * s
        return np.stack([x, i * s, np.zeros_like(x)], axis=1)

    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the mask in metres."""
        p = self.object_points()
        m = self.margin_m
        return (p[:, 0].min() - m, p[:, 0].max() + m, p[:, 1].min() - m, p[:, 1].max() + m)

    def classify(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Label (SURROUND=0, BOARD=1, FEATURE=2) of target-plane points ``x, y`` (metres, any shape)."""
        s = self.spacing_m
        r2 = (0.5 * self.diameter_m) ** 2
        xmin, xmax, ymin, ymax = self.extent()
        lab = np.where((x >= xmin) & (x <= xmax) & (y >= ymin) & (y <= ymax), BOARD, SURROUND).astype(np.int8)
        # nearest row centre; diameter < spacing means only that row can contain the point
        i = np.clip(np.rint(y / s), 0, self.rows - 1)
        if self.asymmetric:
            shift = (i % 2) * s
            j = np.clip(np.rint((x - shift) / (2 * s)), 0, self.columns - 1)
            cx = (2 * j) * s + shift
        else:
            j = np.clip(np.rint(x / s), 0, self.columns - 1)
            cx = j * s
        inside = (x - cx) ** 2 + (y - i * s) ** 2 <= r2
        lab[inside & np.isfinite(x)] = FEATURE
        return lab

    def outline_points(self, n: int = 16) -> np.ndarray:
        """(N·n, 3) points on every circle's rim (for visibility checks)."""
        c = self.object_points()
        a = 2 * np.pi * np.arange(n) / n
        r = 0.5 * self.diameter_m
        rim = np.stack([r * np.cos(a), r * np.sin(a), np.zeros(n)], axis=1)
        return (c[:, None, :] + rim[None, :, :]).reshape(-1, 3)


@dataclass(frozen=True)
class ChessboardTarget:
    """Heated chessboard with ``inner_columns × inner_rows`` inner corners (OpenCV ``patternSize``).

    Squares: (inner_columns+1) × (inner_rows+1); the square whose lower-right corner is inner corner 0
    (the top-left square) is a *feature* (hot, absorbing) square, colours alternate; a border of the
    *board* (cool, reflective) colour of width ``margin_m`` (default one square) surrounds them.
    """

    inner_columns: int
    inner_rows: int
    square_m: float
    margin_m: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "inner_columns", _pos_int(self.inner_columns, "ChessboardTarget.inner_columns"))
        object.__setattr__(self, "inner_rows", _pos_int(self.inner_rows, "ChessboardTarget.inner_rows"))
        s = _pos_float(self.square_m, "ChessboardTarget.square_m")
        object.__setattr__(self, "square_m", s)
        m = s if self.margin_m is None else _pos_float(self.margin_m, "ChessboardTarget.margin_m")
        object.__setattr__(self, "margin_m", m)

    @property
    def pattern_size(self) -> tuple[int, int]:
        return (self.inner_columns, self.inner_rows)

    def object_points(self) -> np.ndarray:
        """(inner_columns·inner_rows, 3) inner corners in OpenCV order, metres, z = 0."""
        i, j = np.meshgrid(np.arange(self.inner_rows), np.arange(self.inner_columns), indexing="ij")
        s = self.square_m
        return np.stack([j.ravel() * s, i.ravel() * s, np.zeros(i.size)], axis=1).astype(np.float64)

    def extent(self) -> tuple[float, float, float, float]:
        s, m = self.square_m, self.margin_m
        return (-s - m, self.inner_columns * s + m, -s - m, self.inner_rows * s + m)

    def classify(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        s = self.square_m
        xmin, xmax, ymin, ymax = self.extent()
        lab = np.where((x >= xmin) & (x <= xmax) & (y >= ymin) & (y <= ymax), BOARD, SURROUND).astype(np.int8)
        with np.errstate(invalid="ignore"):
            a = np.floor(x / s) + 1  # square column 0..inner_columns
            b = np.floor(y / s) + 1
            squares = (a >= 0) & (a <= self.inner_columns) & (b >= 0) & (b <= self.inner_rows)
            hot = squares & (np.mod(a + b, 2) == 1)
        lab[hot & np.isfinite(x)] = FEATURE
        return lab

    def outline_points(self, n: int = 4) -> np.ndarray:
        """Inner corners and their neighbours half a square away (visibility check)."""
        c = self.object_points()
        h = 0.5 * self.square_m
        d = np.array([[h, 0, 0], [-h, 0, 0], [0, h, 0], [0, -h, 0]], dtype=np.float64)
        return (c[:, None, :] + d[None]).reshape(-1, 3)


@dataclass(frozen=True)
class CodedCheckerboardTarget:
    """Checkerboard with an ArUco marker on its central corner (MRT coded target, Schramm et al. 2021).

    Same layout as :class:`thermogrammetry.calibration.detect_common.CodedCheckerboardSpec` (metres
    here): origin at the top-left inner corner, ``object_points()`` = all inner corners row-major
    (including those hidden by the marker area; :meth:`valid_ids` lists the usable ones);
    ``hidden_squares``² squares around the central corner are blank (bright) and carry the marker of
    side ``marker_m`` (black border + ``marker_bits``² bits of ``extendDictionary(dictionary_size,
    marker_bits, seed 0)``, id ``marker_id``). ``top_left_square`` is the colour of the square diagonally
    outside corner 0. *Bright* parts (light squares, blank area, white bits, border) take the
    ``feature_k`` temperature, *dark* parts (dark squares, black marker cells) ``board_k`` — the board
    as a heated print whose dark ink absorbs less (swap the temperatures for the opposite polarity).
    Every edge is analytic, so corners are exact.
    """

    inner_columns: int = 11
    inner_rows: int = 9
    square_m: float = 0.0505
    marker_m: float = 0.1615
    hidden_squares: int = 4
    marker_bits: int = 3
    marker_id: int = 0
    dictionary_size: int = 1
    top_left_square: str = "dark"
    margin_m: float | None = None

    def __post_init__(self):
        for n in ("inner_columns", "inner_rows"):
            v = _pos_int(getattr(self, n), f"CodedCheckerboardTarget.{n}")
            if v % 2 == 0:
                raise ConfigError(f"CodedCheckerboardTarget.{n}={v}: expected an odd number (the marker sits on the central corner)")
        object.__setattr__(self, "square_m", _pos_float(self.square_m, "CodedCheckerboardTarget.square_m"))
        object.__setattr__(self, "marker_m", _pos_float(self.marker_m, "CodedCheckerboardTarget.marker_m"))
        if self.marker_m > self.hidden_squares * self.square_m:
            raise ConfigError(f"CodedCheckerboardTarget.marker_m={self.marker_m}: larger than the blank area "
                              f"({self.hidden_squares} x {self.square_m} m)")
        if self.top_left_square not in ("dark", "bright"):
            raise ConfigError(f"CodedCheckerboardTarget.top_left_square={self.top_left_square!r}: expected 'dark' or 'bright'")
        m = self.square_m if self.margin_m is None else _pos_float(self.margin_m, "CodedCheckerboardTarget.margin_m")
        object.__setattr__(self, "margin_m", m)

    @property
    def pattern_size(self) -> tuple[int, int]:
        return (self.inner_columns, self.inner_rows)

    @property
    def centre(self) -> np.ndarray:
        return np.array([(self.inner_columns - 1) / 2 * self.square_m, (self.inner_rows - 1) / 2 * self.square_m])

    def object_points(self) -> np.ndarray:
        i, j = np.meshgrid(np.arange(self.inner_rows), np.arange(self.inner_columns), indexing="ij")
        s = self.square_m
        return np.stack([j.ravel() * s, i.ravel() * s, np.zeros(i.size)], axis=1).astype(np.float64)

    def _square_dark(self, a, b) -> np.ndarray:
        """Square (a, b) = the square whose lower-right corner is inner corner (a, b) − 1 (a, b >= 0);
        dark unless blanked by the marker area (blank squares count as bright)."""
        s = self.square_m
        xc = (np.asarray(a) - 0.5) * s
        yc = (np.asarray(b) - 0.5) * s
        half = self.hidden_squares / 2 * s
        blank = (np.abs(xc - self.centre[0]) < half) & (np.abs(yc - self.centre[1]) < half)
        dark = (np.mod(np.asarray(a) + np.asarray(b), 2) == 0) == (self.top_left_square == "dark")
        return dark & ~blank

    def valid_ids(self) -> np.ndarray:
        """Corners that are true saddles (their four squares alternate once the blank area is bright),
        the definition of ``CodedCheckerboardSpec.valid_ids``."""
        r, c = np.mgrid[0:self.inner_rows, 0:self.inner_columns]
        r, c = r.ravel(), c.ravel()
        tl, tr = self._square_dark(c, r), self._square_dark(c + 1, r)
        bl, br = self._square_dark(c, r + 1), self._square_dark(c + 1, r + 1)
        return np.flatnonzero((tl == br) & (tr == bl) & (tl != tr))

    def marker_bits_matrix(self) -> np.ndarray:
        """(bits+2, bits+2) uint8, 1 = white cell, including the black border."""
        import cv2

        d = cv2.aruco.extendDictionary(int(self.dictionary_size), int(self.marker_bits), cv2.aruco.Dictionary(), 0)
        n = self.marker_bits + 2
        img = cv2.aruco.generateImageMarker(d, int(self.marker_id), n, borderBits=1)
        return (img > 127).astype(np.uint8)

    def extent(self) -> tuple[float, float, float, float]:
        s, m = self.square_m, self.margin_m
        return (-s - m, self.inner_columns * s + m, -s - m, self.inner_rows * s + m)

    def classify(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """FEATURE = bright, BOARD = dark, SURROUND outside the board (see the class docstring)."""
        s = self.square_m
        xmin, xmax, ymin, ymax = self.extent()
        lab = np.where((x >= xmin) & (x <= xmax) & (y >= ymin) & (y <= ymax), FEATURE, SURROUND).astype(np.int8)
        with np.errstate(invalid="ignore"):
            a = np.floor(x / s) + 1
            b = np.floor(y / s) + 1
            squares = (a >= 0) & (a <= self.inner_columns) & (b >= 0) & (b <= self.inner_rows)
            tl_dark = self.top_left_square == "dark"
            dark = squares & ((np.mod(a + b, 2) == 0) == tl_dark)
            cx, cy = self.centre
            half = self.hidden_squares / 2 * s
            blank = (np.abs(x - cx) < half) & (np.abs(y - cy) < half)
            dark &= ~blank
            bits = self.marker_bits_matrix()
            n = bits.shape[0]
            cell = self.marker_m / n
            u = np.floor((x - (cx - self.marker_m / 2)) / cell)
            v = np.floor((y - (cy - self.marker_m / 2)) / cell)
            inm = (u >= 0) & (u < n) & (v >= 0) & (v < n)
            ui = np.where(inm, u, 0).astype(np.intp)
            vi = np.where(inm, v, 0).astype(np.intp)
            dark |= inm & (bits[vi, ui] == 0)
        lab[dark & np.isfinite(x)] = BOARD
        return lab

    def outline_points(self, n: int = 4) -> np.ndarray:
        c = self.object_points()
        h = 0.5 * self.square_m
        d = np.array([[h, 0, 0], [-h, 0, 0], [0, h, 0], [0, -h, 0]], dtype=np.float64)
        return (c[:, None, :] + d[None]).reshape(-1, 3)


@dataclass(frozen=True)
class TargetTemperatures:
    """Apparent (blackbody-equivalent) temperatures of the target parts, kelvin.

    ``feature_k``: circles (the warm emitter seen through the mask holes) or the hot chessboard squares;
    ``board_k``: the mask / cool squares and border; ``surround_k``: whatever is seen beside the target.
    Defaults give the low contrast of a real mask target (a few kelvin).
    """

    feature_k: float = 303.15
    board_k: float = 296.15
    surround_k: float = 293.15

    def __post_init__(self):
        for name in ("feature_k", "board_k", "surround_k"):
            v = getattr(self, name)
            try:
                f = float(v)
            except (TypeError, ValueError):
                raise ConfigError(f"TargetTemperatures.{name}={v!r}: expected kelvin > 0") from None
            if not np.isfinite(f) or f <= 0:
                raise ConfigError(f"TargetTemperatures.{name}={v!r}: expected kelvin > 0")
            object.__setattr__(self, name, f)

    @classmethod
    def coerce(cls, value) -> "TargetTemperatures":
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        if isinstance(value, dict):
            unknown = sorted(set(value) - {"feature_k", "board_k", "surround_k"})
            if unknown:
                raise ConfigError(f"temperatures: unknown key(s) {unknown}; valid: feature_k, board_k, surround_k")
            return cls(**value)
        try:
            vals = [float(v) for v in value]
        except TypeError:
            raise ConfigError(f"temperatures={value!r}: expected TargetTemperatures, a dict or (feature_k, board_k[, surround_k])") from None
        if len(vals) not in (2, 3):
            raise ConfigError(f"temperatures={value!r}: expected (feature_k, board_k[, surround_k])")
        return cls(*vals)


@dataclass
class RenderedTarget:
    """A rendered target image with its exact ground truth.

    Attributes
    ----------
    image_k : ndarray (H, W) float32
        Apparent temperature in kelvin.
    points_px : ndarray (N, 2)
        Camera-model projections of the circle centres / inner corners (OpenCV pixel origin), NaN
        where behind the camera.
    points_target : ndarray (N, 3)
        The same points in the target frame (OpenCV order), metres.
    visible : ndarray (N,) bool
        True when the point is in front of the camera and its whole circle (or a half-square
        neighbourhood of the corner) projects inside the image.
    camera, pose, target : the inputs (pose is ``cam_from_target``).
    signal : ndarray (H, W) float64
        Noise-free, blur-free pixel-integrated signal (units of the signal curve).
    """

    image_k: np.ndarray
    points_px: np.ndarray
    points_target: np.ndarray
    visible: np.ndarray
    camera: object
    pose: object
    target: object
    signal: np.ndarray = field(repr=False, default=None)

    @property
    def all_visible(self) -> bool:
        return bool(np.all(self.visible))


def _project_with_depth(camera, pose, points):
    pc = pose.transform(points)
    z = pc[:, 2]
    out = np.full((len(points), 2), np.nan)
    front = z > 1e-9
    if np.any(front):
        out[front] = camera.project(pc[front])
    return out, front


def render_target_signal(camera, pose, target, temperatures=None, *, supersample: int = 8, curve: SignalCurve | None = None) -> np.ndarray:
    """Pixel-integrated signal image (H, W) of ``target`` (no sensor effects). See :func:`render_target_image`."""
    pose = as_pose(pose)
    temps = TargetTemperatures.coerce(temperatures)
    curve = curve or BandPlanckCurve()
    s_part = np.asarray(curve.signal(np.array([temps.surround_k, temps.board_k, temps.feature_k])), dtype=np.float64)
    w, h = camera_size(camera)
    out = np.empty((h, w), dtype=np.float64)
    R, C = pose.R, pose.center
    for rows, rays in iter_sample_rays(camera, supersample):
        d = np.einsum("...i,ij->...j", rays, R)  # world (target) directions: R^T d for each ray
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = -C[2] / d[..., 2]
            ok = np.isfinite(lam) & (lam > 0) & np.all(np.isfinite(rays), axis=-1)
            x = np.where(ok, C[0] + lam * d[..., 0], np.nan)
            y = np.where(ok, C[1] + lam * d[..., 1], np.nan)
        lab = target.classify(x, y)
        lab[~ok] = SURROUND
        out[rows] = s_part[lab].mean(axis=-1)
    return out


def render_target_image(
    camera,
    pose,
    target,
    *,
    temperatures=None,
    supersample: int = 8,
    psf_sigma_px: float = 0.0,
    netd_k: float = 0.0,
    fpn_k: float = 0.0,
    vignetting: float = 0.0,
    seed: int = 0,
    fpn_seed: int = 0,
    curve: SignalCurve | None = None,
) -> RenderedTarget:
    """Render a calibration target as a thermal camera sees it.

    Parameters
    ----------
    camera : thermogrammetry.Camera
        Any model; only ``image_size``, ``unproject`` (pixel → z = 1 ray) and ``project`` are used.
    pose : thermogrammetry.geometry.Pose or (R, t)
        ``cam_from_target`` (target frame: plane z = 0, see :class:`CircleGridTarget`).
    target : CircleGridTarget or ChessboardTarget
    temperatures : TargetTemperatures, dict, (feature_k, board_k[, surround_k]) or None (defaults)
        Apparent temperatures in kelvin.
    supersample : int
        S: S×S samples per pixel (area integration by the midpoint rule).
    psf_sigma_px, netd_k, fpn_k, vignetting, fpn_seed : see :class:`SensorEffects`.
    seed : int
        Seed of the temporal noise of this image.
    curve : SignalCurve, optional
        Signal curve in which parts are mixed (default: Planck radiance over 7.5–13.5 µm).

    Returns
    -------
    RenderedTarget
        ``image_k`` (H, W) float32 K, ``points_px`` (N, 2), ``points_target`` (N, 3), ``visible`` (N,).
    """
    if not hasattr(target, "classify") or not hasattr(target, "object_points"):
        raise InvalidInputError(f"target={target!r}: expected a CircleGridTarget or ChessboardTarget")
    pose = as_pose(pose)
    curve = curve or BandPlanckCurve()
    effects = SensorEffects(psf_sigma_px=psf_sigma_px, netd_k=netd_k, fpn_k=fpn_k, vignetting=vignetting, fpn_seed=fpn_seed)
    signal = render_target_signal(camera, pose, target, temperatures, supersample=supersample, curve=curve)
    image = apply_sensor_effects(signal, curve, effects, np.random.default_rng(seed))
    pts = target.object_points()
    xy, front = _project_with_depth(camera, pose, pts)
    w, h = camera_size(camera)
    rim = target.outline_points()
    rim_xy, rim_front = _project_with_depth(camera, pose, rim)
    with np.errstate(invalid="ignore"):
        inside = rim_front & (rim_xy[:, 0] >= -0.5) & (rim_xy[:, 0] <= w - 0.5) & (rim_xy[:, 1] >= -0.5) & (rim_xy[:, 1] <= h - 0.5)
    visible = front & inside.reshape(len(pts), -1).all(axis=1)
    if hasattr(target, "valid_ids"):
        usable = np.zeros(len(pts), dtype=bool)
        usable[target.valid_ids()] = True
        visible &= usable
    return RenderedTarget(image, xy, pts, visible, camera, pose, target, signal)
