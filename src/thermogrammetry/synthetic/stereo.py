"""Rectified thermal stereo pairs with a known disparity field (for dense-matching tests and benchmarks).

:func:`make_stereo_pair` renders a float-kelvin pair whose left-image disparity is the slanted plane
``d(x, y) = a + b·x + c·y`` (rows are epipolar lines, ``x_right = x_left − d(x_left, y)``). The scene is
thermal ground: spatially correlated texture (two Gaussian-filtered white-noise layers, σ 1.5 px and 6 px)
of standard deviation ≈ 0.2 K × ``amp`` on 300 K, optionally a hot block (+60 K: a heater, a roof in the
sun, a chimney) that takes most of the frame's global range, and white sensor noise (NETD) added to each
frame independently. Both frames are sampled from one texture by cubic interpolation, so the disparity of
every left pixel is exact up to the interpolation.

:func:`rectified_disparity_truth` gives the true disparity of a rectified pair of frames rendered from a
survey scene (terrain, buildings, trees), by ray casting the true surface, and which pixels the right camera
sees.

References
----------
Scharstein D., Szeliski R. (2002), A taxonomy and evaluation of dense two-frame stereo correspondence
algorithms, IJCV 47 — the "bad pixels > 1 px" score computed against such a known disparity.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..errors import InvalidInputError

__all__ = ["StereoPair", "make_stereo_pair", "rectified_disparity_truth"]


class StereoPair(NamedTuple):
    """A rectified pair with its true disparity (unpacks as ``left, right, disparity``)."""

    left: np.ndarray
    """(H, W) float32 left frame, kelvin."""
    right: np.ndarray
    """(H, W) float32 right frame, kelvin."""
    disparity: np.ndarray
    """(H, W) float64 true disparity of each left pixel, px (``x_right = x_left − d``)."""


def make_stereo_pair(shape: tuple[int, int] = (512, 640), *, a: float = 22.0, b: float = 0.02, c: float = 0.01,
                     noise_k: float = 0.02, seed: int = 0, hot: bool = True, amp: float = 1.0,
                     hot_box: tuple[int, int, int, int] = (30, 130, 320, 500), hot_k: float = 60.0,
                     margin_cols: int = 100) -> StereoPair:
    """Float-kelvin rectified pair with the known planar disparity ``d(x, y) = a + b·x + c·y``.

    Parameters
    ----------
    shape : (H, W) of each frame (px)
    a, b, c : disparity plane: ``a`` px at the top-left pixel, ``b`` px per px along x, ``c`` px per px along y;
        ``b < 1`` (the right frame must be a one-to-one resampling of the rows)
    noise_k : standard deviation of the white sensor noise added to each frame (K)
    seed : seed of the texture and the noise (``numpy.random.default_rng``)
    hot : add the hot block
    amp : texture amplitude factor (texture standard deviation ≈ 0.2 K × ``amp``; 0.3 ≈ thermal ground at
        NETD 0.02 K)
    hot_box : ``(row0, row1, col0, col1)`` of the hot block in LEFT-frame pixel coordinates (half-open; the default
        sits in the upper right of a 640×512 frame; it may extend outside the frame)
    hot_k : temperature added inside the hot block (K)
    margin_cols : columns of texture on each side of the left frame (px); they must cover the right frame's
        reach ``(W − 1 + a + c·(H − 1)) / (1 − b) − W + 2`` (the texture also has 10 rows above the frame
        and 30 below)

    Returns
    -------
    StereoPair(left (H, W) float32 K, right (H, W) float32 K, disparity (H, W) float64 px)

    Raises
    ------
    InvalidInputError
        ``shape`` not two positive sizes, ``b ≥ 1``, or ``margin_cols`` too small for the disparity range.
    """
    h, w = (int(s) for s in shape)
    if h < 1 or w < 1:
        raise InvalidInputError(f"shape={shape!r}: expected two positive sizes (H, W) in px")
    if not b < 1.0:
        raise InvalidInputError(f"b={b!r}: expected < 1 (the disparity must grow slower than x)")
    my, mx = 10, int(margin_cols)
    lo = (a + min(0.0, c * (h - 1))) / (1 - b)  # right frame's columns in left-frame coordinates
    hi = (w - 1 + a + max(0.0, c * (h - 1))) / (1 - b)
    if lo + mx < 1 or hi + mx > w + 2 * mx - 2:
        raise InvalidInputError(f"margin_cols={margin_cols!r}: the right frame reaches columns {lo:.1f}..{hi:.1f} "
                                f"of the left frame; expected a margin of at least "
                                f"{int(np.ceil(max(1 - lo, hi - w + 2)))} px")
    from scipy.ndimage import gaussian_filter, map_coordinates

    rng = np.random.default_rng(seed)
    size = (h + 40, w + 2 * mx)
    big = 300 + amp * (gaussian_filter(rng.normal(size=size), 1.5) * 0.8 + gaussian_filter(rng.normal(size=size), 6) * 3)
    if hot:
        r0, r1, c0, c1 = hot_box
        big[max(0, r0 + my):max(0, r1 + my), max(0, c0 + mx):max(0, c1 + mx)] += hot_k
    y, x = np.mgrid[0:h, 0:w].astype(float)
    d = a + b * x + c * y
    left = map_coordinates(big, [y + my, x + mx], order=3)
    xl = (x + a + c * y) / (1 - b)  # the left pixel seen at right column x: x = x_l − d(x_l, y)
    right = map_coordinates(big, [y + my, xl + mx], order=3)
    return StereoPair((left + rng.normal(0, noise_k, left.shape)).astype(np.float32),
                      (right + rng.normal(0, noise_k, left.shape)).astype(np.float32), d)


def rectified_disparity_truth(scene, R_rect, C_left, C_right, f_px: float, cx_left: float, cx_right: float,
                              cy: float, u, v) -> tuple[np.ndarray, np.ndarray]:
    """True disparity of rectified left pixels of a rendered survey scene, by ray casting its true surface.

    The rectified pair is described by plain numbers (as :class:`thermogrammetry.dense.rectify.RectifiedPair`
    holds them), so that this bottom layer does not import ``dense``: both rectified cameras have the world-to-
    rectified rotation ``R_rect``, the focal length ``f_px`` and the row of the principal point ``cy``; their
    centres and principal-point columns differ.

    Parameters
    ----------
    scene : :class:`thermogrammetry.synthetic.survey.SurveyScene`
    R_rect : (3, 3) world-to-rectified rotation
    C_left, C_right : (3,) camera centres, world coordinates (m)
    f_px, cx_left, cx_right, cy : rectified focal length and principal point (px)
    u, v : (H, W) rectified left pixel columns and rows (px)

    Returns
    -------
    disparity : (H, W) float64 ``u_left − u_right`` (px), NaN where the ray misses the surface
    seen : (H, W) bool, the surface point is also visible from the right camera (not occluded, 5 cm tolerance)
    """
    from .survey import _cast

    u = np.asarray(u, float)
    v = np.asarray(v, float)
    if u.shape != v.shape or u.ndim != 2:
        raise InvalidInputError(f"u {u.shape} and v {v.shape}: expected two (H, W) arrays of the same shape")
    R = np.asarray(R_rect, float)
    rays = np.stack([(u - cx_left) / f_px, (v - cy) / f_px, np.ones_like(u)], -1).reshape(-1, 3)
    Cl = scene.terrain.to_local(np.asarray(C_left, float))
    Cr = scene.terrain.to_local(np.asarray(C_right, float))
    pts, hit = _cast(scene, Cl, rays @ R)
    Xr = (pts - Cr) @ R.T
    with np.errstate(invalid="ignore", divide="ignore"):
        ur = f_px * Xr[:, 0] / Xr[:, 2] + cx_right
    pr, hr = _cast(scene, Cr, np.where(hit[:, None], pts - Cr, [0.0, 0.0, -1.0]))
    seen = hit & hr & (np.linalg.norm(np.where(hit[:, None], pr - pts, np.inf), axis=1) < 0.05)
    return (u.ravel() - ur).reshape(u.shape), seen.reshape(u.shape)
