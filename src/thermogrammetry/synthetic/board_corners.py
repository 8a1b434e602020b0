"""Corner sets of a planar chessboard projected by a known camera: exact image points for calibration tests.

No rendering: the board's inner corners are projected through the camera (any model of
:mod:`thermogrammetry.camera`, distortion included) from a set of varied poses, and noise is added to the
image coordinates (iid Gaussian, :func:`noisy_corners`). What a Monte-Carlo study of a calibration's
reported precision needs: many noise realisations of exactly the same geometry in milliseconds.

The views follow Zhang (2000)'s advice for planar calibration: the board tilted up to ~40 degrees in
varied directions, rolled, placed over different parts of the frame, at varied distances.

References
----------
Zhang, Z. (2000). A flexible new technique for camera calibration. IEEE TPAMI 22(11), 1330-1334.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .testfield import look_at_pose

__all__ = ["BoardCorners", "make_board_corners", "noisy_corners"]


@dataclass(frozen=True)
class BoardCorners:
    """Exact corners of a board in every view.

    Attributes
    ----------
    camera : the camera (thermogrammetry.Camera) that projected them.
    points_m : (M, 3) inner corners on the board, metres (z = 0), row-major from the first corner.
    poses : per view ``(R, t)`` cam_from_world.
    xy_px : per view (M, 2) exact projections, px (every corner inside the image by ``margin_px``).
    names : per view name.
    """

    camera: object
    points_m: np.ndarray
    poses: list
    xy_px: list
    names: list


def make_board_corners(camera, *, n_views: int = 15, corners: tuple[int, int] = (9, 6), square_mm: float = 40.0,
                       distance_m: tuple[float, float] = (0.45, 0.8), tilt_deg: float = 40.0, margin_px: float = 3.0,
                       seed: int = 0) -> BoardCorners:
    """``n_views`` views of a ``corners`` = (columns, rows) inner-corner chessboard of ``square_mm`` squares.

    Each view: camera centre at ``distance_m`` from the board centre in a direction up to ``tilt_deg`` off the
    board normal, aimed at a point up to a quarter of the board away from its centre, rolled up to 30 degrees.
    Views with a corner outside the image (by ``margin_px``) are drawn again. Seeded: the same arguments give
    the same views.
    """
    cols, rows = corners
    s = square_mm * 1e-3
    u, v = np.meshgrid(np.arange(cols) * s, np.arange(rows) * s)
    pts = np.column_stack([u.ravel(), v.ravel(), np.zeros(u.size)])
    centre = np.array([(cols - 1) * s / 2, (rows - 1) * s / 2, 0.0])
    w, h = camera.image_size
    rng = np.random.default_rng(seed)
    poses, xy, names = [], [], []
    tries = 0
    while len(poses) < n_views and tries < 100 * n_views:
        tries += 1
        az, el = np.deg2rad(rng.uniform(-tilt_deg, tilt_deg, 2))
        dist = rng.uniform(*distance_m)
        C = centre + dist * np.array([np.sin(az) * np.cos(el), np.sin(el), -np.cos(az) * np.cos(el)])
        aim = centre + np.array([rng.uniform(-0.25, 0.25) * cols * s, rng.uniform(-0.25, 0.25) * rows * s, 0.0])
        R, t = look_at_pose(C, aim, rng.uniform(-30, 30), up=(0, -1, 0))
        Xc = pts @ R.T + t
        if np.any(Xc[:, 2] <= 0):
            continue
        p = camera.project(Xc)
        if not (np.all(np.isfinite(p)) and np.all(p >= margin_px) and np.all(p[:, 0] <= w - 1 - margin_px)
                and np.all(p[:, 1] <= h - 1 - margin_px)):
            continue
        poses.append((R, t))
        xy.append(p)
        names.append(f"board{len(poses) - 1:02d}")
    return BoardCorners(camera, pts, poses, xy, names)


def noisy_corners(board: BoardCorners, sigma_px: float, rng: np.random.Generator) -> list[np.ndarray]:
    """One noise realisation: per view the exact corners plus iid Gaussian noise of ``sigma_px`` per coordinate."""
    return [p + rng.normal(0.0, sigma_px, p.shape) for p in board.xy_px]
