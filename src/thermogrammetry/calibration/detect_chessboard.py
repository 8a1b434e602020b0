"""Chessboard corner detection on thermal images.

Thermal chessboards (heated boards, masked backgrounds, or a board in a cluttered unmasked scene) are
small, blurred and low in contrast; OpenCV's classic ``findChessboardCorners`` on the raw image finds
the 6x5 board of ``../shared/data/thermal_chessboard`` in only a few of the unmasked views. This module
runs a short cascade of passes and stops at the first that yields a geometrically consistent board:

1. percentile stretch (float/16-bit → 8 bit) + ``findChessboardCornersSB`` (EXHAUSTIVE | ACCURACY),
2. the same on a CLAHE-equalised image,
3. 2x upsampled image (small sensors, smaller side < 300 px),
4. the classic detector (adaptive threshold, normalisation, quad filter, fast check) on stretched /
   CLAHE / gamma / inverted images (heated boards can appear inverted; the classic detector needs
   dark squares in a bright frame).

Corners of the SB passes keep SB's own sub-pixel estimate (ACCURACY flag; better than
``cornerSubPix`` on the real thermal views, see :func:`detect_chessboard`); corners of the classic
detector are refined with ``cornerSubPix`` using a window matched to the local square size in pixels
(0.4 of a square: large enough to see both edges through the blur, small enough to stay inside the
four squares around the corner). All are put in a canonical OpenCV order (see
:func:`canonical_grid_order`).

References
----------
Duda, A., Frese, U. (2018). Accurate detection and localization of checkerboard corners for
calibration. BMVC (the algorithm of ``findChessboardCornersSB``).
Vidas, S. et al. (2012). A mask-based approach for the geometric calibration of thermal-infrared
cameras. IEEE TIM 61(6) 1625-1635 (contrast problems of thermal targets).
"""

from __future__ import annotations

import cv2
import numpy as np

from .detect_common import (
    ChessboardSpec,
    Detection,
    clahe_u8,
    flatten_background,
    image_size_of,
    normalize_to_u8,
    spec_of,
    to_gray_float,
)

__all__ = ["detect_chessboard", "canonical_grid_order", "refine_corners", "square_size_px"]

_SB_FLAGS = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY  # NORMALIZE_IMAGE loses boards here
_CLASSIC_FLAGS = (cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FILTER_QUADS
                  | cv2.CALIB_CB_FAST_CHECK)


def square_size_px(grid: np.ndarray) -> np.ndarray:
    """Local square size (px) at every corner of a (rows, cols, 2) grid: the median distance to its
    grid neighbours. Returns (rows, cols)."""
    rows, cols = grid.shape[:2]
    d = np.full((rows, cols, 4), np.nan)
    dx = np.linalg.norm(np.diff(grid, axis=1), axis=2)  # (rows, cols-1)
    dy = np.linalg.norm(np.diff(grid, axis=0), axis=2)  # (rows-1, cols)
    d[:, 1:, 0] = dx
    d[:, :-1, 1] = dx
    d[1:, :, 2] = dy
    d[:-1, :, 3] = dy
    return np.nanmedian(d, axis=2)


def refine_corners(u8: np.ndarray, points_px: np.ndarray, square_px: np.ndarray | float, *, window_frac: float = 0.4,
                   max_shift_frac: float = 0.25):
    """Sub-pixel corner refinement with ``cv2.cornerSubPix`` and a window matched to the square size.

    Parameters
    ----------
    u8 : ndarray (H, W) uint8
        Contrast-normalised image.
    points_px : ndarray (N, 2)
        Initial corners (OpenCV pixel convention).
    square_px : float or ndarray (N,)
        Local square size in pixels; the half window is ``clip(round(window_frac * square_px), 2, 12)``.
    window_frac : float
        Half window as a fraction of the square size (0.4: on synthetic blurred boards 0.3-0.4 give
        0.025-0.03 px RMS, 0.15 gives 0.05 px).
    max_shift_frac : float
        A refined corner that moved by more than this fraction of the square size keeps its
        initial position (the refinement wandered off to another feature).

    Returns
    -------
    refined : ndarray (N, 2) float64
    moved_too_far : ndarray (N,) bool
    """
    pts = np.asarray(points_px, np.float64).reshape(-1, 2)
    sq = np.broadcast_to(np.asarray(square_px, float), (pts.shape[0],))
    half = np.clip(np.rint(window_frac * sq), 2, 12).astype(int)
    out = pts.copy()
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    for h in np.unique(half):
        sel = np.flatnonzero(half == h)
        p = pts[sel].astype(np.float32).reshape(-1, 1, 2)
        r = cv2.cornerSubPix(u8, p, (int(h), int(h)), (-1, -1), crit)
        out[sel] = r.reshape(-1, 2)
    shift = np.linalg.norm(out - pts, axis=1)
    bad = shift > max_shift_frac * sq
    out[bad] = pts[bad]
    return out, bad


def _sample(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear samples of a float image at (N, 2) positions (clamped to the image)."""
    h, w = img.shape
    x = np.clip(xy[:, 0], 0, w - 1.001)
    y = np.clip(xy[:, 1], 0, h - 1.001)
    x0 = np.floor(x).astype(int)
    y0 = np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    return (
        img[y0, x0] * (1 - fx) * (1 - fy)
        + img[y0, x0 + 1] * fx * (1 - fy)
        + img[y0 + 1, x0] * (1 - fx) * fy
        + img[y0 + 1, x0 + 1] * fx * fy
    )


def _corner0_contrast(img: np.ndarray, grid: np.ndarray) -> float:
    """Brightness of the first inner square (corners [0,0],[0,1],[1,0],[1,1]) minus that of the last
    one (at the opposite corner of the grid). Negative → the square diagonally outside corner 0 is
    dark: it lies across corner 0 from the first inner square, and squares meeting diagonally at a
    corner have the same colour."""
    first = grid[:2, :2].reshape(-1, 2).mean(axis=0)
    last = grid[-2:, -2:].reshape(-1, 2).mean(axis=0)
    v = _sample(img, np.array([first, last]))
    return float(v[0] - v[1])


def canonical_grid_order(grid: np.ndarray, image: np.ndarray | None = None, corner0_square: str = "any", *,
                         allow_transpose: bool = False, colour_distinct: bool = True):
    """Put a (rows, cols, 2) grid of image points into a canonical order.

    OpenCV returns a chessboard / circle grid in row-major order but the start corner depends on the
    view. The rules, applied to the candidate orderings that keep the pattern size (identity, row
    flip, column flip, 180° rotation; plus the transposes when ``allow_transpose`` for square grids):

    1. handedness: the board frame (x along a row, y down the columns) must be right-handed with z
       pointing away from the camera, i.e. the image cross product ``dx × dy`` is positive (image y
       down) -- a mirrored order would need the camera behind the board;
    2. colour (when ``image`` is given, ``corner0_square`` is "dark"/"bright" and the board's two
       diagonal corner squares differ in colour): the square diagonally outside corner 0 has the
       requested colour;
    3. otherwise the candidate whose corner 0 is nearest the image's top-left (smallest x + y).

    Returns
    -------
    grid : ndarray (rows, cols, 2) reordered
    index : ndarray (rows, cols) int -- position of each output point in the input's row-major order
    """
    rows, cols = grid.shape[:2]
    idx = np.arange(rows * cols).reshape(rows, cols)
    cands = [idx, idx[::-1, :], idx[:, ::-1], idx[::-1, ::-1]]
    if allow_transpose and rows == cols:
        cands += [c.T for c in cands]
    flat = grid.reshape(-1, 2)

    def handed(ix):
        g = flat[ix]
        dx = g[:, -1] - g[:, 0]
        dy = g[-1, :] - g[0, :]
        return float(np.sum(dx[:, None, 0] * dy[None, :, 1] - dx[:, None, 1] * dy[None, :, 0]))

    cands = [c for c in cands if handed(c) > 0] or cands
    if image is not None and corner0_square in ("dark", "bright") and colour_distinct:
        want_dark = corner0_square == "dark"
        keep = []
        for c in cands:
            contrast = _corner0_contrast(image, flat[c])
            if (contrast < 0) == want_dark:
                keep.append(c)
        cands = keep or cands
    best = min(cands, key=lambda c: float(flat[c[0, 0]].sum()))
    return flat[best], best


def _homography_check(grid: np.ndarray, spec_xy: np.ndarray, square_px: float) -> tuple[bool, float]:
    """RMS residual of a homography fit (object → image); a board with a wrong order or a wrong
    corner has residuals of a sizeable fraction of a square."""
    H, _ = cv2.findHomography(spec_xy.astype(np.float64), grid.reshape(-1, 2).astype(np.float64), 0)
    if H is None:
        return False, np.inf
    p = cv2.perspectiveTransform(spec_xy.reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)
    res = np.linalg.norm(p - grid.reshape(-1, 2), axis=1)
    rms = float(np.sqrt(np.mean(res**2)))
    # lens distortion of thermal lenses bends a board by up to a few % of its size; wrong orders by
    # a whole square. 0.15 square max separates the two.
    return bool(res.max() < 0.15 * square_px + 0.5), rms


def detect_chessboard(image, spec: ChessboardSpec, image_id: str = "", *, refine: bool = False,
                      try_classic: bool = True, try_upsample: bool | str = "auto", try_flatfield: bool = True) -> Detection:
    """Find the inner corners of a chessboard in a thermal image.

    Parameters
    ----------
    image : array_like (H, W) or (H, W, 1|3|4), uint8 / uint16 / float
        The image; contrast normalisation happens inside.
    spec : ChessboardSpec
        Inner corners and square size.
    image_id : str
        Name carried into the result.
    refine : bool
        Also apply :func:`refine_corners` to corners from ``findChessboardCornersSB``. Off by
        default: SB with ACCURACY is already sub-pixel, and on the real thermal views it is the
        better of the two (``cv2.calibrateCamera`` RMS on the 47 masked views 0.455 px with SB
        corners, 0.65 px after ``cornerSubPix``, 0.8-1.3 px after a local saddle-point fit).
        The heated board of that data set is built from separate tiles: every square boundary is
        a 3-4 px band of intermediate temperature, so the neighbourhood of a corner is a grey
        cross rather than a saddle, which biases local estimators; SB's fit over a whole square
        is not fooled. On sharp synthetic boards (1 px PSF) the order is reversed: SB has a
        sub-pixel-phase error of ~0.1 px, ``cornerSubPix`` ~0.05 px. Corners of the classic
        detector are always refined.
    try_classic : bool
        Fall back to the classic detector when the SB passes fail.
    try_upsample : bool or "auto"
        Try a 2x upsampled image; "auto" does so when the smaller side is below 300 px.
    try_flatfield : bool
        Also try images with the background removed and the local contrast normalised
        (:func:`~thermogrammetry.calibration.detect_common.flatten_background`): low-contrast boards
        under a heater's hot spot or vignetting, where a global stretch leaves the squares a few grey
        levels apart ("sb-flatfield", "sb-flatfield-wide", "classic-flatfield[-inverted]").

    Returns
    -------
    Detection
        ``points_px`` (columns*rows, 2) in canonical order (:func:`canonical_grid_order`),
        ``object_ids = arange(N)``; or a failure with the reason.
    """
    spec = spec_of(spec, ChessboardSpec, "ChessboardSpec")
    gray = to_gray_float(image, f"image {image_id!r}" if image_id else "image")
    size = image_size_of(gray)
    u8 = normalize_to_u8(gray)
    cl = clahe_u8(u8)
    pattern = spec.pattern_size
    obj = spec.object_points()[:, :2]

    # SB finds saddles, which do not change under inversion (the order is fixed afterwards), so
    # the inverted image is only tried with the classic detector, which needs dark squares in a
    # bright frame. Costs on a 640x480 frame without a board: SB 1.0 s, SB+CLAHE 1.5 s, 2x
    # upsampled SB 3.8 s, classic with FAST_CHECK 0.25 s.
    passes = [("sb-stretch", u8, 1), ("sb-clahe", cl, 1)]
    if try_flatfield:
        # low-contrast boards under a hot spot / vignetting: background removed by a large blur and
        # local contrast normalised before the stretch. σ = 1/64 of the larger side (10 px at 640: a
        # third of a 30 px square) and 1/32: a wider background lets the step between board and
        # surround (several K against a few tenths between squares) leak into the squares next to
        # the border and bend the saddles there (measured on 640x512 boards with 30-45 px squares,
        # 0.35 K contrast, 8 K hot spot: σ 10 px finds 6/6 at 0.13-0.16 px RMS, σ 20 px 2/6 at
        # 0.75-0.86 px, σ 28-80 px none)
        big = max(gray.shape)
        ff = {s: flatten_background(gray, big / s) for s in (64, 32)}
        passes += [("sb-flatfield", ff[64], 1), ("sb-flatfield-wide", ff[32], 1)]
    up = try_upsample if isinstance(try_upsample, bool) else min(gray.shape) < 300
    if up:
        passes.append(("sb-upsampled", cv2.resize(cl, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC), 2))
    if try_classic:
        lut = np.clip(255.0 * (np.arange(256) / 255.0) ** 0.5, 0, 255).astype(np.uint8)
        passes += [("classic-stretch", u8, 1), ("classic-clahe", cl, 1), ("classic-gamma", cv2.LUT(u8, lut), 1),
                   ("classic-inverted", 255 - cl, 1)]
        if try_flatfield:
            passes += [("classic-flatfield", ff[64], 1), ("classic-flatfield-inverted", 255 - ff[64], 1)]

    tried = []
    for name, img, scale in passes:
        if name.startswith("sb"):
            ok, corners = cv2.findChessboardCornersSB(img, pattern, flags=_SB_FLAGS)
        else:
            ok, corners = cv2.findChessboardCorners(img, pattern, flags=_CLASSIC_FLAGS)
        if not ok or corners is None:
            tried.append(name)
            continue
        pts = corners.reshape(-1, 2).astype(np.float64)
        if scale != 1:
            # pixel centres: x_small = (x_big + 0.5) / s - 0.5
            pts = (pts + 0.5) / scale - 0.5
        grid = pts.reshape(pattern[1], pattern[0], 2)
        sq = square_size_px(grid)
        if refine or name.startswith("classic"):
            pts, _ = refine_corners(img if "flatfield" in name else u8, pts, sq.ravel())
            grid = pts.reshape(pattern[1], pattern[0], 2)
        ok_h, rms_h = _homography_check(grid, obj, float(np.median(sq)))
        if not ok_h:
            tried.append(f"{name} (rejected: homography residual RMS {rms_h:.2f} px)")
            continue
        colour_distinct = (spec.inner_columns % 2 == 0) != (spec.inner_rows % 2 == 0)
        # square colours from the image the board was found in when it is background-flattened (a hot
        # spot can make a cool square brighter than a hot one far away in the stretched image)
        col = (255 - img if name.endswith("inverted") else img) if "flatfield" in name else u8
        grid, _ = canonical_grid_order(grid, cv2.GaussianBlur(col.astype(np.float32), (0, 0), 1.5), spec.corner0_square,
                                       allow_transpose=spec.inner_columns == spec.inner_rows,
                                       colour_distinct=colour_distinct)
        reason = f"found by {name}" + (f" after {', '.join(tried)} failed" if tried else "")
        return Detection(
            image_id=str(image_id), found=True, points_px=np.ascontiguousarray(grid.reshape(-1, 2)),
            object_ids=np.arange(spec.n_points, dtype=np.int64), reason=reason, image_size=size, method=name,
            extra={"homography_rms_px": rms_h, "square_px": float(np.median(sq))},
        )
    return Detection.failure(
        image_id, f"no {pattern[0]}x{pattern[1]} chessboard found (tried: {', '.join(tried)})", size
    )
