"""A synthetic mask circle-grid calibration set with strong barrel distortion (issue 13).

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

from dataclasses import dataclass

import numpy as np

from ..targets import CircleGridTarget
from .targets import RenderedTarget, render_target_image
from .testfield import look_at_pose

__all__ = ["CircleGridSet", "make_circle_grid_set", "STRONG_BARREL_CAMERA"]

#: 640 x 512, 17 µm, c = 7.48 mm (fx 440 px); correction form with K1 such that the correction at the
#: frame corner is ~ 35 px (barrel), plus small K2, P1, P2
STRONG_BARREL_CAMERA = dict(c_mm=7.48, x0_mm=0.06, y0_mm=-0.04, K1=1.6e-3, K2=8e-6, P1=2e-5, P2=-1.5e-5)


@dataclass
class CircleGridSet:
    """Rendered views with their truth."""

    camera: object
    target: CircleGridTarget
    views: list  # RenderedTarget
    names: list

    @property
    def images(self):
        return [v.image_k for v in self.views]


def make_circle_grid_set(n_views: int = 24, seed: int = 13, *, supersample: int = 3, psf_sigma_px: float = 0.8,
                         netd_k: float = 0.05, params: dict | None = None) -> CircleGridSet:
    """Render ``n_views`` views of a 4 x 3 grid of 60 mm circles at 90 mm spacing (dark... bright holes on
    a warm emitter behind the mask) through :data:`STRONG_BARREL_CAMERA`.

    Every view shows the whole grid (all circle outlines inside the frame); views alternate between
    the frame centre and its corners/edges, 0.45-0.75 m away, tilted up to ~40 degrees, rolled freely.
    Seeded: the same arguments give the same images.
    """
    from ..camera import Camera

    cam = Camera("photogrammetric", (640, 512), dict(params or STRONG_BARREL_CAMERA), pixel_pitch_um=17.0)
    tgt = CircleGridTarget(4, 3, 90.0, diameter_mm=60.0)
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
        r = render_target_image(cam, (R, t), tgt, supersample=supersample, psf_sigma_px=psf_sigma_px, netd_k=netd_k,
                                seed=len(views))
        if not r.visible.all():
            continue
        views.append(r)
        names.append(f"cg{len(views) - 1:02d}")
        k += 1
    return CircleGridSet(cam, tgt, views, names)
