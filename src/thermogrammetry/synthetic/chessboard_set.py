"""Low-contrast 16-bit thermal chessboards under a heater hot spot and vignetting.

A heated 9 x 6 (inner corners) chessboard whose squares differ by a few tenths of a kelvin, with a warm
patch from the heater several kelvin strong on one side of the board and vignetting of the optics, seen
by a 640 x 512 camera and stored as 16-bit counts of 0.01 K (the "TLinear" radiometric output of many
thermal cores: counts = T / 0.01 K). A global contrast stretch spends the 8-bit range on the hot spot
and the vignetting, so the squares are left with a few grey levels.

References
----------
Vidas, S. et al. (2012). A mask-based approach for the geometric calibration of thermal-infrared
cameras. IEEE TIM 61(6) 1625-1635 (contrast problems of thermal targets).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..targets import ChessboardTarget
from .targets import HotSpot, TargetTemperatures, render_target_image
from .testfield import look_at_pose

__all__ = ["LowContrastChessboardSet", "make_low_contrast_chessboard_set", "COUNTS_PER_K"]

#: 16-bit radiometric counts per kelvin (0.01 K per count)
COUNTS_PER_K = 100.0


@dataclass
class LowContrastChessboardSet:
    """Rendered views: ``images`` (uint16 counts, 0.01 K), ``points_px`` truth per view (N, 2)."""

    camera: object
    target: ChessboardTarget
    images: list
    points_px: list
    names: list
    poses: list


def make_low_contrast_chessboard_set(n_views: int = 16, seed: int = 5, *, image_size=(640, 512), focal_px: float = 620.0,
                                     square_mm: float = 40.0, contrast_k: float = 0.35, hot_spot_k: float = 8.0,
                                     vignetting: float = 0.25, psf_sigma_px: float = 0.9, netd_k: float = 0.04,
                                     supersample: int = 2) -> LowContrastChessboardSet:
    """Render ``n_views`` views of a 9 x 6 chessboard with squares ``contrast_k`` apart, a hot spot of
    ``hot_spot_k`` (Gaussian, 1.2 squares wide... see below) and signal vignetting ``vignetting``.

    The hot spot sits on a different part of the board in every view (the heater is behind one side of
    the board; views turn the board round), its width is 2.5 squares. Views are 0.55-0.8 m away, tilted
    up to 35 degrees, rolled up to 20 degrees, aimed so the board covers different parts of the frame.
    Seeded: the same arguments give the same images.
    """
    from ..camera import Camera

    w, h = image_size
    cam = Camera("pinhole", (w, h), {"fx": focal_px, "fy": focal_px, "cx": (w - 1) / 2, "cy": (h - 1) / 2})
    tgt = ChessboardTarget(9, 6, square_mm, corner0_square="dark")
    temps = TargetTemperatures(feature_k=300.0 + contrast_k, board_k=300.0, surround_k=295.0)
    rng = np.random.default_rng(seed)
    centre = np.array([5 * square_mm, 3.5 * square_mm, 0.0]) * 1e-3
    images, pts, names, poses = [], [], [], []
    tries = 0
    while len(images) < n_views and tries < 500:
        tries += 1
        az, el = np.deg2rad(rng.uniform(-35, 35)), np.deg2rad(rng.uniform(-30, 30))
        dist = rng.uniform(0.55, 0.8)
        C = centre + dist * np.array([np.sin(az) * np.cos(el), np.sin(el), -np.cos(az) * np.cos(el)])
        aim = centre + np.array([rng.uniform(-0.06, 0.06), rng.uniform(-0.05, 0.05), 0.0])
        R, t = look_at_pose(C, aim, rng.uniform(-20, 20), up=(0, -1, 0))
        rim = cam.project(1e-3 * tgt.outline_points() @ R.T + t)
        if not (np.all(np.isfinite(rim)) and np.all(rim >= 2) and np.all(rim[:, 0] <= w - 3) and np.all(rim[:, 1] <= h - 3)):
            continue
        a = rng.uniform(0, 2 * np.pi)
        spot = HotSpot(centre[0] * 1e3 + 2.5 * square_mm * np.cos(a), centre[1] * 1e3 + 2.0 * square_mm * np.sin(a),
                       2.5 * square_mm, hot_spot_k)
        r = render_target_image(cam, (R, t), tgt, temperatures=temps, supersample=supersample, psf_sigma_px=psf_sigma_px,
                                netd_k=netd_k, vignetting=vignetting, seed=len(images), hot_spot=spot)
        if not r.all_visible:
            continue
        images.append(np.clip(np.rint(r.image_k.astype(np.float64) * COUNTS_PER_K), 0, 65535).astype(np.uint16))
        pts.append(r.points_px)
        names.append(f"lc{len(images) - 1:02d}")
        poses.append((R, t))
    return LowContrastChessboardSet(cam, tgt, images, pts, names, poses)
