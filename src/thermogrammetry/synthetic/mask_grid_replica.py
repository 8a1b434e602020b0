"""A replica of a real thermal mask circle-grid calibration set.

What a user shoots with a 640 x 512 thermal camera (fx ≈ 440.7 px, strong barrel distortion) and a
4 x 3 grid of 60 mm circles at 90 mm spacing cut into a mask in front of a heated plate: the circles
appear dark (cold), the mask warm with a mild non-uniform temperature, the mask's outer border and a
warmer plate rim around it are visible, beyond it a cooler room with a smooth gradient and a
person-warm blob. 24 views with the plate at various distances (filling ~25-80 % of the frame),
tilted up to ~50°, the grid put near the frame corners in some views (where the distortion is
strongest). Sharp optics (Gaussian PSF σ 0.5 px), NETD noise, and 8-bit (AGC-stretched) or 16-bit
(0.01 K counts) images as cameras write them.

Rendering: every pixel is split into S x S samples, each unprojected through the camera model (the
distortion is exactly the model's), intersected with the target plane and given the temperature of
what it sees; the pixel's signal is the mean band radiance of its samples (radiance-linear mixing),
then blur, temperature conversion, noise and quantisation. The truth is the projection of every
circle's centre through the full model (``points_px``); the area centroid of each imaged circle
(what a centroid or edge-polygon measurement converges to) is ``points_px +``
:func:`~thermogrammetry.targets.circle_centroid_bias` of the true camera and pose.
The rendered discs' radiance-coverage centroids agree with that to < 0.012 px at S = 4, < 0.01 px at
S = 6 (the default; ``tests/test_maskgrid_replica.py``) and < 0.002 px at S = 12.

References
----------
Vidas, S. et al. (2012). A mask-based approach for the geometric calibration of thermal-infrared
cameras. IEEE TIM 61(6), 1625-1635.
Heikkilä, J. (2000). Geometric camera calibration using circular control points. IEEE TPAMI 22(10).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import ConfigError
from ..targets import CircleGridTarget
from ._render import iter_sample_rays
from .radiance import BandPlanckCurve
from .sensor import SensorEffects, apply_sensor_effects
from .circle_grid_set import displace_centres_in_image
from .testfield import look_at_pose

__all__ = ["MASK_GRID_CAMERA", "MaskGridReplica", "make_mask_grid_replica", "render_mask_grid_view", "quantize"]

#: 640 x 512, 17 µm, c = 7.492 mm (fx 440.7 px), correction form: the correction reaches ~80 px at the
#: frame corners and ~10 px at the middle of the long edges (an OpenCV forward model k1 ≈ -0.4, k2 ≈ 0.2
#: bends a straight line by about as much)
MASK_GRID_CAMERA = dict(c_mm=440.7 * 0.017, x0_mm=0.05, y0_mm=-0.07, K1=3.0e-3, K2=2.0e-5, K3=0.0,
                        P1=1.5e-5, P2=-1.0e-5)


@dataclass
class MaskGridReplica:
    """The rendered views with their truth.

    Attributes
    ----------
    camera : thermogrammetry.Camera (the truth)
    target : thermogrammetry.targets.CircleGridTarget (4 x 3, 90 mm, 60 mm circles)
    images_k : list of (512, 640) float32 apparent temperature, K
    poses : list of (R, t) cam_from_target, metres
    points_px : list of (12, 2) projections of the circle centres (OpenCV order), px
    centroid_bias_px : list of (12, 2) area centroid of each imaged circle minus ``points_px`` (the truth of
        a raw centroid measurement; includes ``centre_shifts_px``)
    centre_shifts_px : list of (12, 2) injected centre shifts (zeros without ``centre_noise_px``)
    names : list of str
    """

    camera: object
    target: CircleGridTarget
    images_k: list
    poses: list
    points_px: list
    centroid_bias_px: list
    names: list
    fill: list = field(default_factory=list)
    centre_shifts_px: list = field(default_factory=list)
    tilt_deg: list = field(default_factory=list)


def quantize(image_k: np.ndarray, bits: int, *, lo_k: float | None = None, hi_k: float | None = None) -> np.ndarray:
    """An image as a camera writes it.

    ``bits=8``: a linear AGC stretch of [lo_k, hi_k] (default: the 0.5-99.5 percentiles) to 0..255,
    uint8; ``bits=16``: radiometric counts of 0.01 K (``round(100 T)``), uint16.
    """
    t = np.asarray(image_k, np.float64)
    if bits == 16:
        return np.clip(np.round(100.0 * t), 0, 65535).astype(np.uint16)
    if bits != 8:
        raise ConfigError(f"bits={bits!r}: expected 8 or 16")
    lo = np.percentile(t, 0.5) if lo_k is None else lo_k
    hi = np.percentile(t, 99.5) if hi_k is None else hi_k
    return np.clip(np.round(255.0 * (t - lo) / max(hi - lo, 1e-9)), 0, 255).astype(np.uint8)


def _scene_temperature(x_mm, y_mm, on_plane, rays, tgt, plate_rim_mm, temps, gradient, centres_mm):
    """Apparent temperature (K) of every sample: circle, mask (non-uniform), plate rim, room."""
    t_circle, t_mask, t_rim, t_room, t_person = temps
    xmin, xmax, ymin, ymax = tgt.extent_mm()
    xs, ys = np.where(on_plane, x_mm, 1e9), np.where(on_plane, y_mm, 1e9)
    in_mask = (xs >= xmin) & (xs <= xmax) & (ys >= ymin) & (ys <= ymax)
    in_plate = (xs >= xmin - plate_rim_mm) & (xs <= xmax + plate_rim_mm) & (ys >= ymin - plate_rim_mm) & \
        (ys <= ymax + plate_rim_mm)
    r2 = (0.5 * tgt.diameter_mm) ** 2
    in_circle = np.zeros(xs.shape, bool)
    # each circle tested on the samples whose x lies within its radius (samples sorted by x once): the same mask
    xf, yf, flat = xs.reshape(-1), ys.reshape(-1), in_circle.reshape(-1)
    order = np.argsort(xf, kind="stable")
    x_sorted = xf[order]
    r = float(np.sqrt(r2)) * (1 + 1e-9) + 1e-9  # (a hair wider: the exact test decides)
    for cx, cy in centres_mm:
        near = order[np.searchsorted(x_sorted, cx - r, side="left"):np.searchsorted(x_sorted, cx + r, side="right")]
        flat[near] |= (xf[near] - cx) ** 2 + (yf[near] - cy) ** 2 <= r2
    in_circle &= in_mask
    # mild non-uniform plate/mask temperature: a linear gradient plus a broad warm patch (target frame)
    gx, gy, bump = gradient
    cxm, cym = 0.5 * (xmin + xmax), 0.5 * (ymin + ymax)
    dmask = gx * (xs - cxm) / 100.0 + gy * (ys - cym) / 100.0 + bump * np.exp(-((xs - cxm - 60) ** 2 + (ys - cym + 40) ** 2)
                                                                              / (2 * 150.0**2))
    # room: a smooth gradient over the ray directions, and a person-warm blob
    u, v = rays[..., 0], rays[..., 1]
    room = t_room + 1.5 * v - 0.8 * u + (t_person - t_room) * np.exp(-((u - 0.55) ** 2 / 0.02 + (v + 0.1) ** 2 / 0.12))
    t = np.where(in_plate, t_rim + 0.5 * dmask, room)
    t = np.where(in_mask, t_mask + dmask, t)
    t = np.where(in_circle, t_circle + 0.3 * dmask, t)
    return t


def render_mask_grid_view(camera, pose, target: CircleGridTarget, *, supersample: int = 4, psf_sigma_px: float = 0.5,
                          netd_k: float = 0.05, seed: int = 0, temperatures=(299.0, 313.0, 318.0, 294.0, 305.0),
                          gradient=(0.4, -0.3, 0.8), plate_rim_mm: float = 45.0, centres_mm=None) -> np.ndarray:
    """One view of the mask grid scene, (H, W) float32 apparent temperature in kelvin.

    Parameters
    ----------
    camera : thermogrammetry.Camera
    pose : (R, t) cam_from_target, metres
    target : CircleGridTarget (mm); its ``margin_mm`` is the mask border around the outer circle centres
    supersample : S x S samples per pixel
    psf_sigma_px, netd_k : Gaussian PSF σ (px) and temporal noise (K)
    seed : seed of the noise
    temperatures : (circle, mask, plate rim, room, person) K
    gradient : (K per 100 mm in x, in y, broad warm patch K) of the mask's non-uniform temperature
    plate_rim_mm : width of the heated plate visible around the mask
    centres_mm : (N, 2) where the circles are made (default: the target's nominal centres)
    """
    R, t = np.asarray(pose[0], float), np.asarray(pose[1], float)
    C = -R.T @ t
    centres = target.object_points()[:, :2] if centres_mm is None else np.asarray(centres_mm, float)
    curve = BandPlanckCurve()
    lo, hi = min(temperatures) - 3.0, max(temperatures) + 3.0
    t_tab = np.linspace(lo, hi, 4096)
    s_tab = np.asarray(curve.signal(t_tab), np.float64)
    w, h = camera.image_size
    signal = np.empty((h, w))
    for rows, rays in iter_sample_rays(camera, supersample):
        d = np.einsum("...i,ij->...j", rays, R)
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = -C[2] / d[..., 2]
            ok = np.isfinite(lam) & (lam > 0)
            x = np.where(ok, 1e3 * (C[0] + lam * d[..., 0]), np.nan)
            y = np.where(ok, 1e3 * (C[1] + lam * d[..., 1]), np.nan)
        tk = _scene_temperature(x, y, ok, rays, target, plate_rim_mm, temperatures, gradient, centres)
        signal[rows] = np.interp(np.clip(tk, lo, hi), t_tab, s_tab).mean(axis=-1)
    eff = SensorEffects(psf_sigma_px=psf_sigma_px, netd_k=netd_k)
    return apply_sensor_effects(signal, curve, eff, np.random.default_rng(seed))


def _aim(camera, R, t, centre, ax, ay):
    """Rotate the camera about its centre so that the target point ``centre`` images at (ax, ay) px."""
    ray = camera.unproject(np.array([[ax, ay]]))[0]
    ray = ray / np.linalg.norm(ray)
    pc = R @ centre + t
    pc = pc / np.linalg.norm(pc)
    v = np.cross(pc, ray)
    s, c = np.linalg.norm(v), float(pc @ ray)
    if s < 1e-12:
        return R, t
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    Rr = np.eye(3) + vx + vx @ vx * ((1 - c) / s**2)  # rotates pc onto ray
    return Rr @ R, Rr @ t


def make_mask_grid_replica(n_views: int = 24, seed: int = 2026, *, supersample: int = 6, psf_sigma_px: float = 0.5,
                           netd_k: float = 0.05, params: dict | None = None, views: list | None = None,
                           centre_noise_px: float = 0.0, centre_noise_seed: int = 2027,
                           fill_range=(0.25, 0.80), roll_deg: float = 20.0, seed_tilt_deg: float = 52.0,
                           **scene) -> MaskGridReplica:
    """Render the replica set (see the module docstring).

    Poses: the camera looks at the grid from azimuth/elevation up to ±50° (tilt of the plate against
    the image plane up to ~50°), 0.24-0.62 m away, rolled ±20° around landscape; the grid centre is
    put at aim points spread over the frame, a third of them near the corners. A pose is kept when
    every circle (plus 4 px) is inside the frame. Seeded: the same arguments give the same set.

    Parameters
    ----------
    n_views : number of views (24 as the real set)
    seed : pose seed (the noise of view k is seeded ``seed + k``)
    supersample, psf_sigma_px, netd_k : see :func:`render_mask_grid_view`
    params : camera parameters (default :data:`MASK_GRID_CAMERA`)
    views : indices of the views to render (the poses of the others are drawn, not rendered), or None
    centre_noise_px : σ (px per coordinate) of a known centre error: every circle is made displaced in the
        target plane so that its projected centre moves by an N(0, σ²) shift
        (:func:`~thermogrammetry.synthetic.circle_grid_set.displace_centres_in_image`); ``points_px``
        stay the nominal grid's projections (the calibration's truth), ``centre_shifts_px`` hold the
        shifts, ``centroid_bias_px`` is the displaced circles' centroid minus ``points_px``
    centre_noise_seed : seed of those shifts
    roll_deg : the camera is rolled by up to ± this about its axis (± 90: portrait views as well)
    seed_tilt_deg : the viewing direction is drawn up to this far off the plate normal
    **scene : ``temperatures``, ``gradient``, ``plate_rim_mm`` of :func:`render_mask_grid_view`
    fill_range : (min, max) fraction of the frame covered by the plate (its distorted image, clipped by the frame)
    """
    from ..targets import circle_centroid_bias
    from ..camera import Camera

    cam = Camera("photogrammetric", (640, 512), dict(params or MASK_GRID_CAMERA), pixel_pitch_um=17.0)
    tgt = CircleGridTarget(4, 3, 90.0, diameter_mm=60.0, margin_mm=75.0)
    obj_m = tgt.object_points() * 1e-3
    centre = obj_m.mean(axis=0)
    if not (np.isfinite(centre_noise_px) and centre_noise_px >= 0):
        raise ConfigError(f"centre_noise_px={centre_noise_px!r}: expected a standard deviation >= 0 px")
    rng = np.random.default_rng(seed)
    noise_rng = np.random.default_rng(centre_noise_seed)
    w, h = cam.image_size
    aims = [(0.5, 0.5), (0.3, 0.3), (0.7, 0.7), (0.7, 0.3), (0.3, 0.7), (0.5, 0.35), (0.5, 0.65), (0.35, 0.5),
            (0.65, 0.5), (0.2, 0.22), (0.8, 0.78), (0.8, 0.22), (0.2, 0.78)]
    out = MaskGridReplica(cam, tgt, [], [], [], [], [])
    xmin, xmax, ymin, ymax = tgt.extent_mm()
    # the plate's outline, densely (its image is curved by the distortion), for the frame fill
    e = np.linspace(0.0, 1.0, 64, endpoint=False)[:, None]
    corners = np.array([[xmin - 45, ymin - 45], [xmax + 45, ymin - 45], [xmax + 45, ymax + 45], [xmin - 45, ymax + 45]])
    outline = np.vstack([corners[i] + e * (corners[(i + 1) % 4] - corners[i]) for i in range(4)])
    plate = 1e-3 * np.column_stack([outline, np.zeros(len(outline))])
    k = tries = 0
    while len(out.poses) < n_views and tries < 20000:
        tries += 1
        ax, ay = aims[k % len(aims)]
        tilt = np.deg2rad(rng.uniform(0, seed_tilt_deg))
        phi = rng.uniform(0, 2 * np.pi)
        az, el = tilt * np.cos(phi), tilt * np.sin(phi)
        dist = rng.uniform(0.24, 0.62)
        Cw = centre + dist * np.array([np.sin(az) * np.cos(el), np.sin(el), -np.cos(az) * np.cos(el)])
        R, t = look_at_pose(Cw, centre, rng.uniform(-roll_deg, roll_deg), up=(0, -1, 0))
        R, t = _aim(cam, R, t, centre, ax * (w - 1), ay * (h - 1))
        # the rim of every circle, 4 px clear of the border
        a = np.linspace(0, 2 * np.pi, 48, endpoint=False)
        rim = (obj_m[:, None, :] + 0.03 * np.stack([np.cos(a), np.sin(a), 0 * a], 1)[None]).reshape(-1, 3)
        pc = rim @ R.T + t
        if np.any(pc[:, 2] <= 0.05):
            continue
        xy = cam.project(pc)
        if not (np.all(np.isfinite(xy)) and xy[:, 0].min() >= 4 and xy[:, 1].min() >= 4 and xy[:, 0].max() <= w - 5
                and xy[:, 1].max() <= h - 5):
            continue
        # how much of the frame the plate fills (its curved image, clipped by the frame)
        q = cam.project(plate @ R.T + t)
        if not np.all(np.isfinite(q)):
            continue
        m = np.zeros((h, w), np.uint8)
        cv2.fillPoly(m, [np.round(np.clip(q, -4 * w, 4 * w) * 4).astype(np.int32)], 1, shift=2)
        fill = float(m.mean())
        if not fill_range[0] <= fill <= fill_range[1]:
            continue
        ang = np.degrees(np.arccos(abs((R @ [0, 0, 1.0])[2])))  # plate normal vs optical axis
        if ang > 55.0:
            continue
        idx = len(out.poses)
        out.poses.append((R, t))
        out.names.append(f"mg{idx:02d}")
        out.fill.append(float(fill))
        out.tilt_deg.append(float(ang))
        nominal = cam.project(obj_m @ R.T + t)
        shift = noise_rng.normal(0.0, centre_noise_px, (tgt.n_points, 2)) if centre_noise_px > 0 else np.zeros((tgt.n_points, 2))
        made = tgt.object_points()[:, :2]
        if centre_noise_px > 0:
            made = made + displace_centres_in_image(cam, R, t, tgt.object_points(), shift)
        made_m = np.column_stack([made, np.zeros(len(made))]) * 1e-3
        out.points_px.append(nominal)
        out.centre_shifts_px.append(cam.project(made_m @ R.T + t) - nominal)
        out.centroid_bias_px.append(cam.project(made_m @ R.T + t) - nominal
                                    + circle_centroid_bias(cam, R, t, made_m, 0.03, n_outline=1024))
        if views is None or idx in views:
            out.images_k.append(render_mask_grid_view(cam, (R, t), tgt, supersample=supersample,
                                                      psf_sigma_px=psf_sigma_px, netd_k=netd_k, seed=seed + idx,
                                                      centres_mm=made, **scene))
        else:
            out.images_k.append(None)
        k += 1
    if len(out.poses) < n_views:
        raise ConfigError(f"make_mask_grid_replica: only {len(out.poses)} of {n_views} poses keep the grid in the frame")
    return out
