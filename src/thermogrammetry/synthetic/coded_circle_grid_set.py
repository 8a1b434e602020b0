"""A synthetic seed-003-like calibration set: a mask circle grid with ring-coded marks.

Seed 003 calibrates its UAV thermal camera on a mask of 28 circles (20 mm at 50 mm) with 4 coded
targets, held in front of a powered-on monitor. Here: the 7 x 4 grid with four ring-coded marks of
:meth:`thermogrammetry.targets.CodedCircleGridTarget.seed003`, seen by the 640 x 512 strong-barrel
camera of :mod:`thermogrammetry.synthetic.circle_grid_set` (correction form, ~35 px at the frame
corners), from whole views (the grid and every ring inside the frame, rolled through the full
circle, so half of them show the grid upside down) and close partial views (part of the grid outside
the frame). Both polarities (hot cut-outs on a cold mask as in the seed, and the reverse) and the
three ways a camera writes images (float kelvin, 16-bit counts of 0.01 K, 8-bit AGC) alternate.

Rendering is :func:`~thermogrammetry.synthetic.circle_grid_set.render_circle_grid_view`: supersampled
inverse mapping through the full camera model (distortion included), radiance-linear mixing, PSF
blur, NETD noise; an optional known centre error moves each circle (with its ring) in the target
plane.

References
----------
Khodaei, B. et al. (2015). 3D surface generation from aerial thermal imagery (seed 003, section 3.2).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from ..targets import CodedCircleGridTarget
from .circle_grid_set import STRONG_BARREL_CAMERA, render_circle_grid_view
from .mask_grid_replica import quantize
from .testfield import look_at_pose

__all__ = ["CodedCircleGridSet", "make_coded_circle_grid_set", "HOT_CUTOUTS_K", "COLD_CUTOUTS_K"]

#: (feature = cut-out, board = mask, surround) apparent temperatures, K: a monitor behind a cold mask
HOT_CUTOUTS_K = (303.15, 296.15, 293.15)
#: the reverse polarity: a cold background behind a warm mask
COLD_CUTOUTS_K = (291.15, 298.15, 294.15)


@dataclass
class CodedCircleGridSet:
    """Rendered views with their truth (one entry per view in every list).

    Attributes
    ----------
    camera : thermogrammetry.Camera (the truth)
    target : CodedCircleGridTarget (mm)
    images : list of (512, 640) arrays as written: float32 K, uint16 counts (0.01 K) or uint8 (AGC)
    names : list of str
    poses : list of (R, t) cam_from_target, metres
    points_px : list of (N, 2) projections of the nominal circle centres (OpenCV order), px
    visible : list of (N,) bool -- the circle's whole outline inside the frame
    mark_visible : list of (M,) bool -- the mark's whole ring inside the frame (``target.marks`` order)
    centre_shifts_px : list of (N, 2) injected centre shifts (zeros without noise)
    polarity : list of "bright" (hot cut-outs) / "dark"
    kind : list of "whole" / "partial"
    bits : list of None (float K), 16 or 8
    """

    camera: object
    target: CodedCircleGridTarget
    images: list = field(default_factory=list)
    names: list = field(default_factory=list)
    poses: list = field(default_factory=list)
    points_px: list = field(default_factory=list)
    visible: list = field(default_factory=list)
    mark_visible: list = field(default_factory=list)
    centre_shifts_px: list = field(default_factory=list)
    polarity: list = field(default_factory=list)
    kind: list = field(default_factory=list)
    bits: list = field(default_factory=list)


def _inside(xy, w, h, margin=2.0):
    return np.isfinite(xy).all(axis=1) & (xy[:, 0] >= margin) & (xy[:, 0] <= w - 1 - margin) & \
        (xy[:, 1] >= margin) & (xy[:, 1] <= h - 1 - margin)


def make_coded_circle_grid_set(n_views: int = 24, n_partial: int = 8, seed: int = 3, *, target=None, params=None,
                               supersample: int = 2, psf_sigma_px: float = 0.8, netd_k: float = 0.05,
                               centre_noise_px: float = 0.0, centre_noise_seed: int = 1003,
                               bits=(None, 16, 8), polarities=("bright", "dark")) -> CodedCircleGridSet:
    """Render a seed-003-like coded circle-grid set.

    Parameters
    ----------
    n_views : int
        Views in all; the last ``n_partial`` are partial.
    n_partial : int
        Close views aimed off the grid's centre so that 8-24 of the 28 circles are whole in the frame.
    seed : int
        Seed of the poses (same arguments, same images).
    target : CodedCircleGridTarget, optional
        Default :meth:`CodedCircleGridTarget.seed003`.
    params : dict, optional
        Correction-form camera parameters (default :data:`~thermogrammetry.synthetic.circle_grid_set.STRONG_BARREL_CAMERA`).
    supersample, psf_sigma_px, netd_k : rendering (S x S samples per pixel, PSF σ in px, NETD in K).
    centre_noise_px : float
        σ (px per coordinate) of a known N(0, σ²) shift of every circle's projected centre (the circle
        and its ring are rendered displaced in the target plane); the truth stays nominal.
    centre_noise_seed : int
        Seed of those shifts.
    bits : sequence of {None, 8, 16}
        Cycled over the views: None = float32 K, 16 = uint16 counts of 0.01 K, 8 = uint8 AGC stretch.
    polarities : sequence of {"bright", "dark"}
        Cycled over the views: "bright" = hot cut-outs (:data:`HOT_CUTOUTS_K`), "dark" = :data:`COLD_CUTOUTS_K`.
    """
    from ..camera import Camera

    if not (0 <= int(n_partial) <= int(n_views)):
        raise ConfigError(f"n_partial={n_partial!r}: expected 0 <= n_partial <= n_views={n_views!r}")
    for b in bits:
        if b not in (None, 8, 16):
            raise ConfigError(f"bits: {b!r}: expected None, 8 or 16")
    for p in polarities:
        if p not in ("bright", "dark"):
            raise ConfigError(f"polarities: {p!r}: expected 'bright' or 'dark'")
    if not (np.isfinite(centre_noise_px) and centre_noise_px >= 0):
        raise ConfigError(f"centre_noise_px={centre_noise_px!r}: expected a standard deviation >= 0 px")
    tgt = CodedCircleGridTarget.seed003() if target is None else target
    if not isinstance(tgt, CodedCircleGridTarget) or not tgt.marks:
        raise ConfigError(f"target={target!r}: expected a CodedCircleGridTarget with marks")
    cam = Camera("photogrammetric", (640, 512), dict(params or STRONG_BARREL_CAMERA), pixel_pitch_um=17.0)
    w, h = cam.image_size
    rng = np.random.default_rng(seed)
    noise_rng = np.random.default_rng(centre_noise_seed)
    obj = tgt.object_points() * 1e-3
    rims = tgt.outline_points().reshape(tgt.n_points, -1, 3) * 1e-3
    rings = tgt.mark_outline_points().reshape(len(tgt.marks), -1, 3) * 1e-3
    xmin, xmax, ymin, ymax = tgt.extent_mm()
    centre = 1e-3 * np.array([0.5 * (obj[:, 0].max() + obj[:, 0].min()) * 1e3, 0.5 * (obj[:, 1].max() + obj[:, 1].min()) * 1e3, 0.0])
    out = CodedCircleGridSet(cam, tgt)
    n_whole = int(n_views) - int(n_partial)
    tries = 0
    while len(out.images) < n_views and tries < 20000:
        tries += 1
        partial = len(out.images) >= n_whole
        az, el = np.deg2rad(rng.uniform(-35, 35)), np.deg2rad(rng.uniform(-30, 30))
        if partial:
            dist = rng.uniform(0.2, 0.3)
            aim = centre + np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.075, 0.075), 0.0])
        else:
            dist = rng.uniform(0.36, 0.55)
            aim = centre + np.array([rng.uniform(-0.07, 0.07), rng.uniform(-0.05, 0.05), 0.0])
        C = aim + dist * np.array([np.sin(az) * np.cos(el), np.sin(el), -np.cos(az) * np.cos(el)])
        R, t = look_at_pose(C, aim, rng.uniform(0, 360), up=(0, -1, 0))
        if np.any(obj @ R.T[:, 2] + t[2] <= 0.05):
            continue
        rim_xy = cam.project((rims.reshape(-1, 3) @ R.T + t)).reshape(tgt.n_points, -1, 2)
        vis = np.array([_inside(r, w, h).all() for r in rim_xy])
        ring_xy = cam.project((rings.reshape(-1, 3) @ R.T + t)).reshape(len(tgt.marks), -1, 2)
        mvis = np.array([_inside(r, w, h).all() for r in ring_xy])
        if partial:
            if not (8 <= vis.sum() <= 24):
                continue
        elif not (vis.all() and mvis.all()):
            continue
        k = len(out.images)
        pol = polarities[k % len(polarities)]
        temps = HOT_CUTOUTS_K if pol == "bright" else COLD_CUTOUTS_K
        r, shift = render_circle_grid_view(cam, (R, t), tgt, centre_noise_px=centre_noise_px, rng=noise_rng,
                                           supersample=supersample, psf_sigma_px=psf_sigma_px, netd_k=netd_k,
                                           seed=500 + k, temperatures=temps)
        b = bits[k % len(bits)]
        img = r.image_k.astype(np.float32) if b is None else quantize(r.image_k, b)
        out.images.append(img)
        out.names.append(f"{'part' if partial else 'cc'}{k:02d}")
        out.poses.append((R, t))
        out.points_px.append(r.points_px)
        out.visible.append(vis)
        out.mark_visible.append(mvis)
        out.centre_shifts_px.append(shift)
        out.polarity.append(pol)
        out.kind.append("partial" if partial else "whole")
        out.bits.append(b)
    if len(out.images) < n_views:
        raise ConfigError(f"make_coded_circle_grid_set: only {len(out.images)} of {n_views} views found valid poses")
    return out
