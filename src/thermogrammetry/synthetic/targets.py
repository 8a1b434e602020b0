"""Calibration target images as a thermal camera sees them, with exact ground truth.

The targets themselves are described once, in :mod:`thermogrammetry.targets` (millimetre fields,
``object_points()`` in mm, OpenCV order); :func:`render_target_image` takes those directly. The
classes of the same names here, :class:`CircleGridTarget`, :class:`ChessboardTarget`,
:class:`CodedCheckerboardTarget`, are the older **metre**-unit views (``spacing_m``, ``square_m``,
``object_points()`` in metres) kept for existing callers; each holds its millimetre description in
``.target``, which the detectors of :mod:`thermogrammetry.calibration.detect` take.

Targets lie in the plane z = 0 of their own frame (x right along a row, y down the columns); a pose is
``cam_from_target`` in **metres**. Rendering is by **supersampled inverse mapping**: every pixel is
split into S×S sub-pixel samples, each sample is unprojected through the camera model (so distortion is
the model's, exactly), intersected with the target plane and classified (feature / board / surround,
:meth:`thermogrammetry.targets.ChessboardTarget.classify` and friends). The pixel's *signal* is the
area-weighted mean of the parts' signals (radiance-linear, not temperature); the sensor then blurs,
vignettes, converts to apparent temperature and adds noise (:mod:`thermogrammetry.synthetic.sensor`).

Object-point order is OpenCV's (see :mod:`thermogrammetry.targets`), so ``cv2.findCirclesGrid`` /
``cv2.findChessboardCorners`` results with ``patternSize = (columns, rows)`` line up with the returned
``points_px`` index by index — up to the 180° ambiguity of grids that look the same turned half way
round (symmetric circle grids, chessboards), for which a detector may number from the other end.

The returned ``points_px`` are the camera model's projections of the exact circle centres / corners.
(For circles of finite size the centre of the imaged ellipse differs from the projected centre by the
perspective eccentricity, ~``f r² sin 2α / (2 Z²)`` px; that is a property of the measurement, not of the
rendering, and a detector's business.)

References
----------
.. [1] OpenCV 4.x documentation, "Camera calibration With OpenCV" tutorial and ``calcBoardCornerPositions``
   in samples/cpp/tutorial_code/calib3d/camera_calibration/camera_calibration.cpp (object-point order).
.. [2] Khodaei et al. (seed 003): mask circle grid held in front of a warm emitter (emissivity contrast).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import targets as _t
from ..errors import ConfigError
from ..targets import BOARD, FEATURE, SURROUND, as_target
from ._render import as_pose, camera_size, iter_sample_rays
from .radiance import BandPlanckCurve, SignalCurve
from .sensor import SensorEffects, apply_sensor_effects

__all__ = [
    "CircleGridTarget",
    "ChessboardTarget",
    "CodedCheckerboardTarget",
    "TargetTemperatures",
    "HotSpot",
    "RenderedTarget",
    "render_target_image",
    "render_target_signal",
    "SURROUND",
    "BOARD",
    "FEATURE",
]


def _metres(owner: str, name: str, v) -> float:
    return _t._length(owner, name, v, "metres")


def _mm(v):
    return None if v is None else 1e3 * v


class _MetreView:
    """Metre-unit view of a :mod:`thermogrammetry.targets` description (held in ``.target``, mm)."""

    def _build(self, cls, **kw):
        try:
            object.__setattr__(self, "target", cls(**kw))
        except ConfigError as exc:
            raise ConfigError(f"{type(self).__name__} (lengths given in metres, checked in mm): {exc}") from None

    @property
    def pattern_size(self) -> tuple[int, int]:
        return self.target.pattern_size

    @property
    def n_points(self) -> int:
        return self.target.n_points

    def object_points(self) -> np.ndarray:
        """(N, 3) object points in **metres**, OpenCV order, z = 0 (``self.target.object_points_m()``)."""
        return self.target.object_points_m()

    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the board in metres."""
        return tuple(1e-3 * v for v in self.target.extent_mm())

    def classify(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Part label (SURROUND=0, BOARD=1, FEATURE=2) of target-plane points ``x, y`` in **metres**."""
        return self.target.classify(1e3 * np.asarray(x, dtype=np.float64), 1e3 * np.asarray(y, dtype=np.float64))

    def outline_points(self) -> np.ndarray:
        """Visibility-check points (metres)."""
        return 1e-3 * self.target.outline_points()


@dataclass(frozen=True)
class CircleGridTarget(_MetreView):
    """Metre-unit mask circle grid; ``.target`` is the :class:`thermogrammetry.targets.CircleGridTarget`.

    Attributes
    ----------
    columns, rows : int
        Circles per row and number of rows (OpenCV ``patternSize`` width × height).
    spacing_m : float
        Symmetric: centre distance in a row and between rows. Asymmetric: OpenCV's "square size" —
        rows are ``spacing_m`` apart and circles in a row ``2·spacing_m`` apart.
    diameter_m : float
        Circle diameter (smaller than the nearest-neighbour distance).
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
    target: _t.CircleGridTarget = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        n = type(self).__name__
        s = _metres(n, "spacing_m", self.spacing_m)
        d = _metres(n, "diameter_m", self.diameter_m)
        m = None if self.margin_m is None else _metres(n, "margin_m", self.margin_m)
        self._build(_t.CircleGridTarget, columns=self.columns, rows=self.rows, spacing_mm=_mm(s),
                    asymmetric=self.asymmetric, diameter_mm=_mm(d), margin_mm=_mm(m))
        for k, v in (("columns", self.target.columns), ("rows", self.target.rows), ("spacing_m", s),
                     ("diameter_m", d), ("asymmetric", self.target.asymmetric), ("margin_m", s if m is None else m)):
            object.__setattr__(self, k, v)

    def outline_points(self, n: int = 16) -> np.ndarray:
        """(N·n, 3) points on every circle's rim, metres (visibility checks)."""
        return 1e-3 * self.target.outline_points(n)


@dataclass(frozen=True)
class ChessboardTarget(_MetreView):
    """Metre-unit heated chessboard; ``.target`` is the :class:`thermogrammetry.targets.ChessboardTarget`.

    ``inner_columns × inner_rows`` inner corners (OpenCV ``patternSize``), squares of ``square_m``.
    The top-left square (diagonally outside inner corner 0) is a *board* (cool) square, as is the
    border of width ``margin_m`` (default one square); the squares sharing an edge with it are
    *feature* (hot) squares — ``corner0_square="dark"`` of the detector. (An earlier docstring said the
    top-left square was hot; the renderer has always made it cool and the detector tests rely on it.)
    """

    inner_columns: int
    inner_rows: int
    square_m: float
    margin_m: float | None = None
    target: _t.ChessboardTarget = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        n = type(self).__name__
        s = _metres(n, "square_m", self.square_m)
        m = None if self.margin_m is None else _metres(n, "margin_m", self.margin_m)
        self._build(_t.ChessboardTarget, inner_columns=self.inner_columns, inner_rows=self.inner_rows,
                    square_mm=_mm(s), corner0_square="dark", margin_mm=_mm(m))
        for k, v in (("inner_columns", self.target.inner_columns), ("inner_rows", self.target.inner_rows),
                     ("square_m", s), ("margin_m", s if m is None else m)):
            object.__setattr__(self, k, v)


@dataclass(frozen=True)
class CodedCheckerboardTarget(_MetreView):
    """Metre-unit MRT coded checkerboard; ``.target`` is the
    :class:`thermogrammetry.targets.CodedCheckerboardTarget` (see there for the layout and parts).
    The defaults are the MRT 60x45 cm board."""

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
    target: _t.CodedCheckerboardTarget = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        n = type(self).__name__
        s = _metres(n, "square_m", self.square_m)
        mk = _metres(n, "marker_m", self.marker_m)
        m = None if self.margin_m is None else _metres(n, "margin_m", self.margin_m)
        self._build(_t.CodedCheckerboardTarget, inner_columns=self.inner_columns, inner_rows=self.inner_rows,
                    square_mm=_mm(s), marker_mm=_mm(mk), hidden_squares=self.hidden_squares,
                    marker_bits=self.marker_bits, marker_id=self.marker_id, dictionary_size=self.dictionary_size,
                    top_left_square=self.top_left_square, margin_mm=_mm(m))
        for k, v in (("square_m", s), ("marker_m", mk), ("margin_m", s if m is None else m)):
            object.__setattr__(self, k, v)

    @property
    def centre(self) -> np.ndarray:
        """(2,) central corner (= marker centre), metres."""
        return 1e-3 * self.target.center_mm

    def valid_ids(self) -> np.ndarray:
        """Usable corners (:meth:`thermogrammetry.targets.CodedCheckerboardTarget.valid_ids`)."""
        return self.target.valid_ids()

    def marker_bits_matrix(self) -> np.ndarray:
        return self.target.marker_bits_matrix()


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
        The same points in the target frame (OpenCV order), **metres** (``target.object_points_m()``).
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


@dataclass(frozen=True)
class HotSpot:
    """A warm patch on the target from its heater: a Gaussian temperature excess on the board and its
    features (not on the surround), in the target frame.

    Attributes
    ----------
    x_mm, y_mm : centre in the target plane, millimetres (target frame of :mod:`thermogrammetry.targets`).
    sigma_mm : Gaussian width, millimetres.
    delta_k : temperature excess at the centre, kelvin (added to every part of the board).
    """

    x_mm: float
    y_mm: float
    sigma_mm: float
    delta_k: float

    def __post_init__(self):
        for name in ("x_mm", "y_mm", "sigma_mm", "delta_k"):
            v = getattr(self, name)
            try:
                f = float(v)
            except (TypeError, ValueError):
                raise ConfigError(f"HotSpot.{name}={v!r}: expected a number") from None
            if not np.isfinite(f):
                raise ConfigError(f"HotSpot.{name}={v!r}: expected a finite number")
            object.__setattr__(self, name, f)
        if self.sigma_mm <= 0:
            raise ConfigError(f"HotSpot.sigma_mm={self.sigma_mm!r}: expected a width > 0 mm")

    def excess_k(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Temperature excess (K) at target-plane points (mm)."""
        r2 = ((np.asarray(x_mm) - self.x_mm) ** 2 + (np.asarray(y_mm) - self.y_mm) ** 2) / self.sigma_mm**2
        return self.delta_k * np.exp(-0.5 * r2)


def render_target_signal(camera, pose, target, temperatures=None, *, supersample: int = 8, curve: SignalCurve | None = None,
                         hot_spot: HotSpot | None = None) -> np.ndarray:
    """Pixel-integrated signal image (H, W) of ``target`` (no sensor effects). See :func:`render_target_image`."""
    tgt = as_target(target)
    pose = as_pose(pose)
    temps = TargetTemperatures.coerce(temperatures)
    curve = curve or BandPlanckCurve()
    if hot_spot is not None and not isinstance(hot_spot, HotSpot):
        raise ConfigError(f"hot_spot: expected a thermogrammetry.synthetic.targets.HotSpot, got {type(hot_spot).__name__}")
    t_part = np.array([temps.surround_k, temps.board_k, temps.feature_k])
    s_part = np.asarray(curve.signal(t_part), dtype=np.float64)
    if hot_spot is not None:
        # signal of the heated parts from a table (the band integral per sample is slow); 2048 nodes over
        # the range: linear interpolation error ~ s'' dT^2 / 8, below 1e-6 K equivalent here
        lo, hi = float(t_part.min()) + min(hot_spot.delta_k, 0.0), float(t_part.max()) + max(hot_spot.delta_k, 0.0)
        t_tab = np.linspace(lo, hi + 1e-9, 2048)
        s_tab = np.asarray(curve.signal(t_tab), dtype=np.float64)
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
        lab = tgt.classify(1e3 * x, 1e3 * y)  # the description is in mm, the pose in metres
        lab[~ok] = SURROUND
        if hot_spot is None:
            out[rows] = s_part[lab].mean(axis=-1)
        else:
            on = lab != SURROUND
            tk = t_part[lab] + np.where(on, hot_spot.excess_k(np.where(on, 1e3 * x, 0.0), np.where(on, 1e3 * y, 0.0)), 0.0)
            out[rows] = np.interp(tk, t_tab, s_tab).mean(axis=-1)
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
    hot_spot: HotSpot | None = None,
) -> RenderedTarget:
    """Render a calibration target as a thermal camera sees it.

    Parameters
    ----------
    camera : thermogrammetry.Camera
        Any model; only ``image_size``, ``unproject`` (pixel → z = 1 ray) and ``project`` are used.
    pose : thermogrammetry.geometry.Pose or (R, t)
        ``cam_from_target`` (target frame: plane z = 0, see :class:`CircleGridTarget`).
    target : thermogrammetry.targets.CircleGridTarget, ChessboardTarget or CodedCheckerboardTarget
        The millimetre description, or one of the metre-unit views of this module.
    temperatures : TargetTemperatures, dict, (feature_k, board_k[, surround_k]) or None (defaults)
        Apparent temperatures in kelvin.
    supersample : int
        S: S×S samples per pixel (area integration by the midpoint rule).
    psf_sigma_px, netd_k, fpn_k, vignetting, fpn_seed : see :class:`SensorEffects`.
    seed : int
        Seed of the temporal noise of this image.
    curve : SignalCurve, optional
        Signal curve in which parts are mixed (default: Planck radiance over 7.5–13.5 µm).
    hot_spot : HotSpot, optional
        A warm patch of the heated board (temperature excess on board and features, target frame).

    Returns
    -------
    RenderedTarget
        ``image_k`` (H, W) float32 K, ``points_px`` (N, 2), ``points_target`` (N, 3), ``visible`` (N,).
    """
    tgt = as_target(target)
    pose = as_pose(pose)
    curve = curve or BandPlanckCurve()
    effects = SensorEffects(psf_sigma_px=psf_sigma_px, netd_k=netd_k, fpn_k=fpn_k, vignetting=vignetting, fpn_seed=fpn_seed)
    signal = render_target_signal(camera, pose, target, temperatures, supersample=supersample, curve=curve, hot_spot=hot_spot)
    image = apply_sensor_effects(signal, curve, effects, np.random.default_rng(seed))
    pts = tgt.object_points_m()
    xy, front = _project_with_depth(camera, pose, pts)
    w, h = camera_size(camera)
    rim = 1e-3 * tgt.outline_points()
    rim_xy, rim_front = _project_with_depth(camera, pose, rim)
    with np.errstate(invalid="ignore"):
        inside = rim_front & (rim_xy[:, 0] >= -0.5) & (rim_xy[:, 0] <= w - 0.5) & (rim_xy[:, 1] >= -0.5) & (rim_xy[:, 1] <= h - 0.5)
    visible = front & inside.reshape(len(pts), -1).all(axis=1)
    if hasattr(tgt, "valid_ids"):
        usable = np.zeros(len(pts), dtype=bool)
        usable[tgt.valid_ids()] = True
        visible &= usable
    return RenderedTarget(image, xy, pts, visible, camera, pose, target, signal)
