"""Image sampling shared by the layers (sfm, dense, products): one bilinear sampler with the project's pixel convention,
and one fill of no-data pixels by their nearest valid value."""

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
