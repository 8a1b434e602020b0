"""Vectorised SO(3) helpers used inside the adjustment engine (axis-angle <-> matrix).

Kept local so the engine does not depend on the import order of ``geometry``; the formulas are the
standard Rodrigues formula and its inverse (same convention as OpenCV ``cv2.Rodrigues``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["rotation_matrices", "axis_angles", "skew"]


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) vectors -> (..., 3, 3) cross-product matrices ``[v]_x``."""
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def rotation_matrices(rvec: np.ndarray) -> np.ndarray:
    """Rodrigues: (..., 3) axis-angle vectors (rad) -> (..., 3, 3) rotation matrices.

    Uses the Taylor expansion below 1e-8 rad so that the map is smooth at zero.
    """
    r = np.asarray(rvec, dtype=np.float64)
    th2 = np.sum(r * r, axis=-1)
    th = np.sqrt(th2)
    small = th2 < 1e-16
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(ths)) / (ths * ths))
    K = skew(r)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def axis_angles(R: np.ndarray) -> np.ndarray:
    """Inverse Rodrigues: (..., 3, 3) rotation matrices -> (..., 3) axis-angle vectors (rad).

    Robust near 0 and near pi (uses the symmetric part of R there).
    """
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R, axis1=-2, axis2=-1)
    c = np.clip((tr - 1.0) * 0.5, -1.0, 1.0)
    th = np.arccos(c)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = np.sin(th)
    small = th < 1e-6
    near_pi = th > np.pi - 1e-3
    fac = np.where(small, 0.5 + th * th / 12.0, th / (2.0 * np.where(small | near_pi, 1.0, s)))
    out = v * fac[..., None]
    if np.any(near_pi):
        idx = np.nonzero(near_pi)
        Rp = R[idx]
        B = (Rp + np.swapaxes(Rp, -1, -2)) * 0.5 - np.eye(3) * c[idx][..., None, None]
        # columns of B are proportional to axis * axis^T (1 - cos th); take the largest column
        k = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        col = np.take_along_axis(B, k[..., None, None].repeat(3, -1), axis=-1)[..., 0]
        ax = col / np.linalg.norm(col, axis=-1, keepdims=True)
        sign = np.sign(np.sum(ax * v[idx], axis=-1))
        sign = np.where(sign == 0, 1.0, sign)
        out[idx] = ax * (sign * th[idx])[..., None]
    return out
