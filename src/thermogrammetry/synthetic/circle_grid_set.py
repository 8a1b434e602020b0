"""A synthetic mask circle-grid calibration set with strong barrel distortion.

Large circles close together (60 mm at 90 mm spacing, 4 x 3) seen by a 640 x 512 thermal camera with
a correction-form model whose distortion exceeds 30 px at the frame corners, from views that put the
grid into every part of the frame under perspective. Rendered by :func:`render_target_image`
(supersampled inverse mapping through the camera model, so the distortion is exactly the model's).

References
----------
Khodaei, B. et al. (2015) (seed 003: mask circle grid, K1-K5, P1, P2).
Heikkilä, J. (2000). Geometric camera calibration using circular control points. IEEE TPAMI 22(10).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import targets as _t
from ..errors import ConfigError
from ..targets import BOARD, FEATURE, SURROUND, CircleGridTarget
from .targets import HotSpot, RenderedTarget, render_target_image
from .testfield import look_at_pose

__all__ = ["CircleGridSet", "DisplacedCircleGrid", "DisplacedCodedCircleGrid", "make_circle_grid_set", "displace_centres_in_image",
           "render_circle_grid_view",
           "STRONG_BARREL_CAMERA"]

#: 640 x 512, 17 µm, c = 7.48 mm (fx 440 px); correction form with K1 such that the correction at the
#: frame corner is ~ 35 px (barrel), plus small K2, P1, P2
STRONG_BARREL_CAMERA = dict(c_mm=7.48, x0_mm=0.06, y0_mm=-0.04, K1=1.6e-3, K2=8e-6, P1=2e-5, P2=-1.5e-5)


@dataclass(frozen=True)
class DisplacedCircleGrid(CircleGridTarget):
    """A circle grid whose circles are *made* off their nominal centres (a manufacturing error of the
    mask, or an injected measurement error for a test): the circles are rendered at
    ``object_points()[:, :2] + offsets_mm``, while ``object_points()`` stays the nominal design that a
    calibration uses.

    Attributes
    ----------
    offsets_mm : ndarray (N, 2)
        Displacement of every circle in the target plane, millimetres, OpenCV point order; each must
        stay well below the gap between circles (checked: ``|offset| < (nn - d) / 4``).
    """

    offsets_mm: np.ndarray = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        super().__post_init__()
        n = type(self).__name__
        off = np.zeros((self.n_points, 2)) if self.offsets_mm is None else np.asarray(self.offsets_mm, np.float64)
        if off.shape != (self.n_points, 2) or not np.all(np.isfinite(off)):
            raise ConfigError(f"{n}.offsets_mm: expected a finite ({self.n_points}, 2) array in mm, got shape {off.shape}")
        gap = self.nearest_neighbour_mm - self._need_diameter()
        if np.linalg.norm(off, axis=1).max() >= 0.25 * gap:
            raise ConfigError(f"{n}.offsets_mm: largest displacement {np.linalg.norm(off, axis=1).max():.4g} mm; "
                              f"expected < a quarter of the gap between circles ({0.25 * gap:.4g} mm)")
        object.__setattr__(self, "offsets_mm", off)

    def circle_centres_mm(self) -> np.ndarray:
        """(N, 2) where the circles are actually made, mm."""
        return self.object_points()[:, :2] + self.offsets_mm

    def classify(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Part label (SURROUND=0, BOARD=1 mask, FEATURE=2 displaced circle) of target-plane points, int8."""
        x, y = np.asarray(x_mm, dtype=np.float64), np.asarray(y_mm, dtype=np.float64)
        r2 = (0.5 * self._need_diameter()) ** 2
        lab = np.where(_t._in_box(x, y, self.extent_mm()), BOARD, SURROUND).astype(np.int8)
        inside = np.zeros(lab.shape, dtype=bool)
        with np.errstate(invalid="ignore"):
            for cx, cy in self.circle_centres_mm():
                inside |= (x - cx) ** 2 + (y - cy) ** 2 <= r2
        lab[inside & np.isfinite(x) & np.isfinite(y)] = FEATURE
        return lab

    def outline_points(self, n: int = 16) -> np.ndarray:
        """(N·n, 3) mm: points on every (displaced) circle's rim (visibility checks)."""
        c = np.column_stack([self.circle_centres_mm(), np.zeros(self.n_points)])
        a = 2 * np.pi * np.arange(n) / n
        r = 0.5 * self._need_diameter()
        rim = np.stack([r * np.cos(a), r * np.sin(a), np.zeros(n)], axis=1)
        return (c[:, None, :] + rim[None, :, :]).reshape(-1, 3)


@dataclass(frozen=True)
class DisplacedCodedCircleGrid(DisplacedCircleGrid):
    """:class:`DisplacedCircleGrid` whose marked circles carry the ring codes of ``coded`` (a
    :class:`~thermogrammetry.targets.CodedCircleGridTarget`), each ring moved with its disc (the
    whole mark is made off its nominal place).

    Attributes
    ----------
    coded : CodedCircleGridTarget -- the nominal coded grid (same columns, rows, spacing, diameter).
    """

    coded: _t.CodedCircleGridTarget = field(default=None, compare=False, repr=False)

    def classify(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Part label (SURROUND=0, BOARD=1 mask, FEATURE=2 displaced circle or cut-out ring sector), int8."""
        lab = super().classify(x_mm, y_mm)
        if self.coded is None or not self.coded.marks:
            return lab
        x, y = np.asarray(x_mm, dtype=np.float64), np.asarray(y_mm, dtype=np.float64)
        cen = self.circle_centres_mm()[self.coded.mark_point_ids]
        ring = self.coded.ring_mask(x, y, cen) & (lab == BOARD)
        lab[ring & np.isfinite(x) & np.isfinite(y)] = FEATURE
        return lab


def displace_centres_in_image(camera, R: np.ndarray, t: np.ndarray, centres_mm: np.ndarray, shift_px: np.ndarray,
                              iterations: int = 4) -> np.ndarray:
    """Target-plane offsets (mm) that move the projections of ``centres_mm`` by ``shift_px``.

    Newton iteration on ``project(R (c + o) + t) - project(R c + t) = shift`` with a numerical 2 x 2
    Jacobian per point (the projection includes the camera's distortion).

    Parameters
    ----------
    camera : thermogrammetry.Camera
    R, t : cam_from_target, metres.
    centres_mm : (N, 2) or (N, 3) target-plane points, mm (z = 0).
    shift_px : (N, 2) wanted image displacement, px.

    Returns
    -------
    offsets_mm : (N, 2) -- the realised shift agrees with ``shift_px`` to < 1e-6 px for sub-pixel shifts.
    """
    c = np.asarray(centres_mm, np.float64)[:, :2]
    want = np.asarray(shift_px, np.float64)

    def proj(xy_mm):
        p = np.column_stack([xy_mm, np.zeros(len(xy_mm))]) * 1e-3
        return camera.project(p @ np.asarray(R).T + np.asarray(t))

    base = proj(c)
    off = np.zeros_like(c)
    h = 1e-3  # mm
    for _ in range(iterations):
        cur = proj(c + off)
        jx = (proj(c + off + [h, 0.0]) - cur) / h
        jy = (proj(c + off + [0.0, h]) - cur) / h
        J = np.stack([jx, jy], axis=2)  # (N, 2, 2): d px / d mm
        off = off + np.linalg.solve(J, (want - (cur - base))[:, :, None])[:, :, 0]
    return off


def render_circle_grid_view(camera, pose, target: CircleGridTarget, *, centre_noise_px: float = 0.0, rng=None,
                            **render_kw):
    """One view of a circle grid, optionally with a known centre error.

    Parameters
    ----------
    camera, pose : as :func:`~thermogrammetry.synthetic.targets.render_target_image` (pose: (R, t), metres).
    target : CircleGridTarget (mm) -- the nominal grid; a
        :class:`~thermogrammetry.targets.CodedCircleGridTarget` is drawn with its ring-coded marks (with
        centre noise each ring moves with its disc: :class:`DisplacedCodedCircleGrid`).
    centre_noise_px : float
        σ (px per image coordinate) of an N(0, σ²) shift of every circle's projected centre, made by
        rendering the circle displaced in the target plane (:func:`displace_centres_in_image`).
    rng : numpy Generator for the shifts (required when ``centre_noise_px > 0``).
    **render_kw : passed to ``render_target_image`` (supersample, psf_sigma_px, netd_k, seed, ...).

    Returns
    -------
    (RenderedTarget, shift_px (N, 2)) -- the view's ``target`` and ``points_px`` are the nominal
    grid's (the truth a calibration is told); ``shift_px`` the injected image shifts (zeros without noise).
    """
    R, t = pose
    shift = np.zeros((target.n_points, 2))
    draw = target
    if centre_noise_px > 0:
        if rng is None:
            raise ConfigError("render_circle_grid_view: centre_noise_px > 0 needs rng (a seeded numpy Generator)")
        shift = rng.normal(0.0, centre_noise_px, (target.n_points, 2))
        off = displace_centres_in_image(camera, R, t, target.object_points(), shift)
        if getattr(target, "marks", ()):
            # a coded grid: each mark's ring moves with its disc
            draw = DisplacedCodedCircleGrid(target.columns, target.rows, target.spacing_mm,
                                            asymmetric=target.asymmetric, diameter_mm=target.diameter_mm,
                                            margin_mm=target.margin_mm, offsets_mm=off, coded=target)
        else:
            draw = DisplacedCircleGrid(target.columns, target.rows, target.spacing_mm, asymmetric=target.asymmetric,
                                       diameter_mm=target.diameter_mm, margin_mm=target.margin_mm, offsets_mm=off)
    r = render_target_image(camera, (R, t), draw, **render_kw)
    r.target = target  # object points and points_px are the nominal grid's in either case
    return r, shift


@dataclass
class CircleGridSet:
    """Rendered views with their truth.

    ``centre_shifts_px`` (one (N, 2) array per view, OpenCV point order): the image displacement of
    each circle's projected centre made by rendering it off its nominal position
    (``make_circle_grid_set(centre_noise_px=...)``); zeros when no noise was injected. The views'
    ``points_px`` remain the projections of the *nominal* centres (the calibration's truth).
    """

    camera: object
    target: CircleGridTarget
    views: list  # RenderedTarget
    names: list
    centre_shifts_px: list = field(default_factory=list)

    @property
    def images(self):
        return [v.image_k for v in self.views]


def make_circle_grid_set(n_views: int = 24, seed: int = 13, *, supersample: int = 3, psf_sigma_px: float = 0.8,
                         netd_k: float = 0.05, params: dict | None = None, centre_noise_px: float = 0.0,
                         centre_noise_seed: int = 1013, temperatures=None, hot_spot_k: float = 0.0,
                         vignetting: float = 0.0) -> CircleGridSet:
    """Render ``n_views`` views of a 4 x 3 grid of 60 mm circles at 90 mm spacing (dark... bright holes on
    a warm emitter behind the mask) through :data:`STRONG_BARREL_CAMERA`.

    Every view shows the whole grid (all circle outlines inside the frame); views alternate between
    the frame centre and its corners/edges, 0.45-0.75 m away, tilted up to ~40 degrees, rolled freely.
    Seeded: the same arguments give the same images.

    Parameters
    ----------
    centre_noise_px : float
        σ (px, per image coordinate) of a known centre error: in every view each circle is rendered
        where its projected centre moves by an independent N(0, σ²) shift in x and y (the circle is
        displaced in the target plane by :func:`displace_centres_in_image`, so its image is a true
        projection of a circle), while the truth (``points_px``, ``target``) stays the nominal grid.
        The realised shifts are in ``CircleGridSet.centre_shifts_px``. 0: the nominal grid.
    centre_noise_seed : int
        Seed of those shifts (independent of the pose seed, so the poses are the same with and without).
    temperatures : TargetTemperatures, dict or tuple, optional
        Apparent temperatures of holes, mask and surround (default: 303.15 / 296.15 / 293.15 K).
    hot_spot_k : float
        A heater's hot spot on the mask: a Gaussian excess of this many kelvin, 1.5 spacings wide,
        at a different place on the mask in every view (drawn from ``centre_noise_seed + 1``, so the
        poses do not change). 0: none.
    vignetting : float
        Signal vignetting of :class:`~thermogrammetry.synthetic.sensor.SensorEffects`.
    """
    from ..camera import Camera

    cam = Camera("photogrammetric", (640, 512), dict(params or STRONG_BARREL_CAMERA), pixel_pitch_um=17.0)
    tgt = CircleGridTarget(4, 3, 90.0, diameter_mm=60.0)
    if not (np.isfinite(centre_noise_px) and centre_noise_px >= 0):
        raise ConfigError(f"centre_noise_px={centre_noise_px!r}: expected a standard deviation >= 0 px")
    noise_rng = np.random.default_rng(centre_noise_seed)
    spot_rng = np.random.default_rng(centre_noise_seed + 1)
    shifts = []
    rng = np.random.default_rng(seed)
    centre = np.array([0.135, 0.09, 0.0])
    views, names = [], []
    w, h = cam.image_size
    # aim points in the image (fractions of the frame) so that the grid covers corners and edges
    aims = [(0.5, 0.5), (0.28, 0.3), (0.72, 0.3), (0.28, 0.7), (0.72, 0.7), (0.5, 0.3), (0.5, 0.7), (0.3, 0.5), (0.7, 0.5)]
    k = tries = 0
    while len(views) < n_views and tries < 4000:
        tries += 1
        ax, ay = aims[k % len(aims)]
        az, el = np.deg2rad(rng.uniform(-40, 40)), np.deg2rad(rng.uniform(-35, 35))
        dist = rng.uniform(0.42, 0.7)
        C = centre + dist * np.array([np.sin(az) * np.cos(el), np.sin(el), -np.cos(az) * np.cos(el)])
        R, t = look_at_pose(C, centre, rng.uniform(0, 360), up=(0, -1, 0))
        # rotate the camera so the grid centre lands at the aim point of the frame
        ray = cam.unproject(np.array([[ax * (w - 1), ay * (h - 1)]]))[0]
        ray /= np.linalg.norm(ray)
        z = np.array([0.0, 0.0, 1.0])
        v = np.cross(ray, z)
        s, c = np.linalg.norm(v), float(ray @ z)
        if s > 1e-12:
            vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
            Rr = np.eye(3) + vx + vx @ vx * ((1 - c) / s**2)  # rotates the optical axis z onto the ray
            Ra = Rr.T  # apply to camera frame: points on the old axis go to the ray direction
            Ra = np.linalg.inv(Rr) if False else Rr  # noqa: SIM222 - explicit choice below
            R2 = Rr @ R
            t2 = Rr @ t
            # check which way round brings the grid centre to the aim (choose the one that does)
            pc = R2 @ centre + t2
            if pc[2] <= 0 or np.linalg.norm(cam.project(pc[None])[0] - [ax * (w - 1), ay * (h - 1)]) > 5:
                R2, t2 = Rr.T @ R, Rr.T @ t
            R, t = R2, t2
        rim = cam.project(1e-3 * tgt.outline_points() @ R.T + t)
        if not (np.all(np.isfinite(rim)) and np.all(rim >= 2) and np.all(rim[:, 0] <= w - 3) and np.all(rim[:, 1] <= h - 3)):
            continue
        extra = {}
        if hot_spot_k:
            a = spot_rng.uniform(0, 2 * np.pi)
            extra["hot_spot"] = HotSpot(1e3 * centre[0] + 90.0 * np.cos(a), 1e3 * centre[1] + 60.0 * np.sin(a), 135.0,
                                        hot_spot_k)
        r, shift = render_circle_grid_view(cam, (R, t), tgt, centre_noise_px=centre_noise_px, rng=noise_rng,
                                           supersample=supersample, psf_sigma_px=psf_sigma_px, netd_k=netd_k,
                                           seed=len(views), temperatures=temperatures, vignetting=vignetting, **extra)
        if not r.visible.all():
            continue
        shifts.append(shift)
        views.append(r)
        names.append(f"cg{len(views) - 1:02d}")
        k += 1
    return CircleGridSet(cam, tgt, views, names, shifts)
