"""Epipolar rectification of an oriented pair with our own camera model (distortion included).

The rectified frame of a pair (i, j) rotates both cameras about their centres so that the x axis points
from ``C_i`` to ``C_j`` and the z axis is the mean viewing direction made orthogonal to the baseline
(Fusiello, Trucco, Verri 2000). Both rectified cameras share the focal length ``f`` (the original mean
focal, px) and the row coordinate ``cy``; each keeps its own ``cx`` so that the images stay compact, hence
``d_raw = u_i − u_j = f B / Z + (cx_i − cx_j)``. The resampling maps go *rectified pixel → ray → original
camera → Camera.project* (the camera's own distortion model, no OpenCV approximation), so any model that
``thermogrammetry.camera`` implements rectifies exactly.

References
----------
Fusiello A., Trucco E., Verri A. (2000), A compact algorithm for rectification of stereo pairs,
Machine Vision and Applications 12.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DegenerateInputError

__all__ = ["RectifiedPair", "rectify_pair", "remap_frame"]


@dataclass
class RectifiedPair:
    """Geometry of a rectified pair.

    Attributes
    ----------
    R_rect : (3, 3) rect_from_world rotation (rows: baseline, y, mean viewing axis)
    C_left, C_right : (3,) centres (m); baseline_m = |C_right − C_left|
    f_px, cx_left, cx_right, cy : rectified intrinsics (px)
    size : (w, h) of both rectified images
    map_left, map_right : (h, w, 2) float32 original-pixel coordinates of every rectified pixel
    """

    R_rect: np.ndarray
    C_left: np.ndarray
    C_right: np.ndarray
    f_px: float
    cx_left: float
    cx_right: float
    cy: float
    size: tuple[int, int]
    map_left: np.ndarray
    map_right: np.ndarray

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.C_right - self.C_left))

    def depth_from_disparity(self, d_raw) -> np.ndarray:
        """Rectified-frame depth Z (m) from raw disparity ``u_left − u_right`` (px); NaN where not positive."""
        dd = np.asarray(d_raw, float) - (self.cx_left - self.cx_right)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(dd > 0, self.f_px * self.baseline_m / dd, np.nan)

    def shifted(self, s: int) -> "RectifiedPair":
        """The same pair with the right image shifted by ``s`` px (``cx_right + s``): raw disparities drop by ``s``.

        Used to bring a pair's disparity range to start at 0, so that SGBM's unmatched left band is only as
        wide as the search range.
        """
        s = int(s)
        m = np.full_like(self.map_right, -1e6)
        w = self.map_right.shape[1]
        if s >= 0:
            m[:, s:] = self.map_right[:, : w - s] if s < w else m[:, s:]
        else:
            m[:, : w + s] = self.map_right[:, -s:]
        return RectifiedPair(self.R_rect, self.C_left, self.C_right, self.f_px, self.cx_left, self.cx_right + s,
                             self.cy, self.size, self.map_left, m)

    def rect_coords_left(self, rays_world) -> np.ndarray:
        """Rectified left pixel coordinates (N, 2) of world rays (N, 3) from ``C_left``."""
        d = _mul(np.asarray(rays_world, float), self.R_rect.T)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.f_px * d[:, 0] / d[:, 2] + self.cx_left
            v = self.f_px * d[:, 1] / d[:, 2] + self.cy
        return np.column_stack([np.where(d[:, 2] > 0, u, np.nan), np.where(d[:, 2] > 0, v, np.nan)])


def _mul(X, M) -> np.ndarray:
    """``X @ M`` for (N, 3) × (3, 3) without BLAS threads (slow for this shape on a shared machine)."""
    return np.einsum("ij,jk->ik", X, M)


def _edge_pixels(w, h, n=24):
    s = np.linspace(0, 1, n)
    xs, ys = s * (w - 1), s * (h - 1)
    return np.concatenate([np.column_stack([xs, np.zeros(n)]), np.column_stack([xs, np.full(n, h - 1.0)]),
                           np.column_stack([np.zeros(n), ys]), np.column_stack([np.full(n, w - 1.0), ys])])


def rectify_pair(cam_left, R_left, t_left, cam_right, R_right, t_right, *, max_scale: float = 1.5) -> RectifiedPair:
    """Rectifying rotations, common intrinsics and resampling maps of an oriented pair.

    Parameters
    ----------
    cam_left, cam_right : ``thermogrammetry.Camera``
    R_*, t_* : ``cam_from_world`` poses
    max_scale : the rectified images are at most ``max_scale`` × the original width/height

    Raises
    ------
    DegenerateInputError : coincident centres or a baseline along the viewing axis
    """
    Rl, Rr = np.asarray(R_left, float), np.asarray(R_right, float)
    Cl, Cr = -Rl.T @ np.asarray(t_left, float), -Rr.T @ np.asarray(t_right, float)
    b = Cr - Cl
    B = float(np.linalg.norm(b))
    if B < 1e-9:
        raise DegenerateInputError("rectification: the two projection centres coincide (no baseline)")
    e1 = b / B
    z = Rl[2] + Rr[2]
    e3 = z - (z @ e1) * e1
    if np.linalg.norm(e3) < 1e-3 * np.linalg.norm(z):
        raise DegenerateInputError("rectification: the baseline is along the viewing direction")
    e3 /= np.linalg.norm(e3)
    e2 = np.cross(e3, e1)
    R = np.vstack([e1, e2, e3])
    f = float(0.5 * (cam_left.K[0, 0] + cam_left.K[1, 1]) * 0.5 + 0.5 * (cam_right.K[0, 0] + cam_right.K[1, 1]) * 0.5)

    def bbox(cam, Rc):
        w, h = cam.image_size
        rays = _mul(cam.unproject(_edge_pixels(w, h)), Rc @ R.T)  # camera -> world -> rect
        rays = rays[rays[:, 2] > 0]
        return f * rays[:, 0] / rays[:, 2], f * rays[:, 1] / rays[:, 2]

    ul, vl = bbox(cam_left, Rl)
    ur, vr = bbox(cam_right, Rr)
    wmax = int(max_scale * max(cam_left.image_size[0], cam_left.image_size[1]))
    v0, v1 = max(vl.min(), vr.min()), min(vl.max(), vr.max())
    if v1 - v0 < 8:
        raise DegenerateInputError("rectification: the two images share no rows (no overlap)")
    h = int(min(np.ceil(v1 - v0) + 1, wmax))
    cy = -v0 if h > np.ceil(v1 - v0) else -(0.5 * (v0 + v1)) + (h - 1) / 2
    wl = int(min(np.ceil(ul.max() - ul.min()) + 1, wmax))
    wr = int(min(np.ceil(ur.max() - ur.min()) + 1, wmax))
    w = max(wl, wr)
    cxl = -ul.min() if wl > np.ceil(ul.max() - ul.min()) else -(0.5 * (ul.min() + ul.max())) + (w - 1) / 2
    cxr = -ur.min() if wr > np.ceil(ur.max() - ur.min()) else -(0.5 * (ur.min() + ur.max())) + (w - 1) / 2

    def maps(cam, Rc, cx):
        u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
        d_rect = np.stack([(u - cx) / f, (v - cy) / f, np.ones_like(u)], axis=-1).reshape(-1, 3)
        d_cam = _mul(d_rect, R @ Rc.T)  # rect -> world -> camera
        xy = np.asarray(cam.project(d_cam), float)
        return xy.reshape(h, w, 2).astype(np.float32)

    return RectifiedPair(R, Cl, Cr, f, float(cxl), float(cxr), float(cy), (w, h),
                         maps(cam_left, Rl, cxl), maps(cam_right, Rr, cxr))


def remap_frame(frame, xy_map) -> np.ndarray:
    """Resample a frame (H, W) at float pixel coordinates (h, w, 2) bilinearly; NaN outside or next to no data."""
    import cv2

    a = np.asarray(frame, np.float32)
    return cv2.remap(a, xy_map[..., 0], xy_map[..., 1], interpolation=cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))
