"""Image sampling shared by the layers (sfm, products): one bilinear sampler with the project's pixel convention."""

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
