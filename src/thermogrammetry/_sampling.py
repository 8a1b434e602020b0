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
    """(H, W) float32/float64 copy of ``a`` with every invalid pixel set to the value of its nearest valid pixel
    (L1 distance; OpenCV's labelled distance transform numbers the valid pixels in raster order)."""
    import cv2

    _, lab = cv2.distanceTransformWithLabels((~valid).view(np.uint8), cv2.DIST_L1, 3,
                                             labelType=cv2.DIST_LABEL_PIXEL)
    lut = np.zeros(int(np.count_nonzero(valid)) + 1, np.float64 if a.dtype == np.float64 else np.float32)
    lut[1:] = a[valid]
    return lut[lab]


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
