"""Image sampling shared by the layers (sfm, dense, products): one bilinear sampler with the project's pixel convention,
and two fills of no-data pixels: by their nearest valid value, and smoothly from the valid pixels around them."""

from __future__ import annotations

import numpy as np


def bilinear(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``img`` (H, W) bilinear at pixel positions ``xy`` (N, 2) = (x, y), pixel centres at integers (OpenCV's
    convention); positions outside [0, W-1] x [0, H-1] are clamped to the border (callers mask them)."""
    h, w = img.shape
    x = np.clip(xy[:, 0], 0, w - 1)
    y = np.clip(xy[:, 1], 0, h - 1)
    x0 = np.clip(np.floor(x).astype(np.int64), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(np.int64), 0, h - 2)
    fx, fy = x - x0, y - y0
    a = img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx
    b = img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx
    return a * (1 - fy) + b * fy


def fill_nearest_valid(a: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(H, W) float32/float64 copy of ``a`` with every invalid pixel set to the value of a nearest valid pixel
    (L1 distance; OpenCV's labelled distance transform, exact for L1 with its 3x3 mask).

    The transform runs on windows, not on the whole frame: for each run of consecutive rows that hold invalid pixels,
    the bounding box of those pixels grown by one pixel. Every pixel just outside such a box is valid, and an L1
    shortest path from an invalid pixel to any valid pixel outside the box crosses that ring at no greater length,
    so the nearest distance is found inside the box (where several valid pixels are equally near, the one taken may
    differ from a whole-frame transform's). A rectified frame's no-data corners cost a few thousand pixels instead of
    the frame (benchmarks/dense.py)."""
    import cv2

    dt = np.float64 if a.dtype == np.float64 else np.float32
    out = np.array(a, dt, copy=True)
    inv = ~np.asarray(valid, bool)
    rows = np.flatnonzero(inv.any(axis=1))
    if rows.size == 0:
        return out
    h, w = inv.shape
    cut = np.flatnonzero(np.diff(rows) > 1)
    for r0, r1 in zip(rows[np.r_[0, cut + 1]], rows[np.r_[cut, rows.size - 1]]):
        cols = np.flatnonzero(inv[r0:r1 + 1].any(axis=0))
        y0, y1, x0, x1 = max(r0 - 1, 0), min(r1 + 2, h), max(cols[0] - 1, 0), min(cols[-1] + 2, w)
        sub_inv = inv[y0:y1, x0:x1]
        sub_ok = ~sub_inv
        if not sub_ok.any():  # no valid pixel in the window (the frame's invalid from edge to edge): whole frame
            y0, y1, x0, x1 = 0, h, 0, w
            sub_inv, sub_ok = inv, ~inv
            if not sub_ok.any():
                return out
        _, lab = cv2.distanceTransformWithLabels(np.ascontiguousarray(sub_inv).view(np.uint8), cv2.DIST_L1, 3,
                                                 labelType=cv2.DIST_LABEL_PIXEL)
        lut = np.zeros(int(np.count_nonzero(sub_ok)) + 1, dt)
        lut[1:] = out[y0:y1, x0:x1][sub_ok]
        out[y0:y1, x0:x1] = lut[lab]
        if (y0, y1, x0, x1) == (0, h, 0, w):
            break
    return out


def fill_smooth(a: np.ndarray, valid: np.ndarray, sigma_px: float = 8.0) -> np.ndarray:
    """(H, W) float32 copy of ``a`` with every invalid pixel set to the Gaussian-weighted mean (σ ``sigma_px``) of the
    valid pixels around it (normalised convolution), blending into the median of the valid pixels where none is
    near: no edge at a hole's border for a detector or a tracker to lock onto (a flat fill leaves one). All invalid:
    zeros."""
    import cv2

    x = np.asarray(a, np.float32)
    v = np.asarray(valid, bool)
    if v.all():
        return x.copy()
    if not v.any():
        return np.zeros(x.shape, np.float32)
    med = np.float32(np.median(x[v]))
    w = cv2.GaussianBlur(v.astype(np.float32), (0, 0), float(sigma_px))
    s = cv2.GaussianBlur(np.where(v, x, np.float32(0.0)), (0, 0), float(sigma_px))
    eps = np.float32(1e-3)
    return np.where(v, x, (s + eps * med) / (w + eps)).astype(np.float32)
