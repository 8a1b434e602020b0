"""Semi-global matching of a rectified pair on the full dynamic range of thermal frames.

:func:`disparity` is the plain function for rectified pairs. OpenCV's SGBM (Hirschmüller 2008) works on
8-bit codes; a thermal frame's texture (tenths of a kelvin on a range of tens of kelvin, or a few hundred
counts out of 16 bits) would be flattened to a few grey levels by a global 8-bit rendering. We therefore
normalise each image *locally* in float (Wallis-type filter: subtract the local mean, divide by the local
standard deviation over ``window_px``), so that every neighbourhood uses the whole 8-bit range before the
quantisation, and only then run SGBM (3-way mode) with its sub-pixel parabola fit, a left-right
consistency check (``disp12MaxDiff``), a uniqueness test and a speckle filter. Both code images get a few
mirrored columns on the right before SGBM (cropped after), so that the left image's last columns are matched
like the others instead of locking onto the right image's border. A coarse-to-fine variant
(:func:`disparity_range`) finds the disparity search range of a pair at a quarter resolution.

References
----------
Hirschmüller H. (2008), Stereo processing by semiglobal matching and mutual information, IEEE PAMI 30(2).
Wallis R. (1976), An approach to the space variant restoration and enhancement of images.
Khodaei, Samadzadegan, Dadras Javan, Hasani (seed 003): multi-resolution dense matching of UAV thermal video.
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidInputError

__all__ = ["disparity", "normalise_for_matching", "disparity_range", "sgbm_matcher"]


def _grey(img, name: str) -> np.ndarray:
    """(H, W) grey array in its own dtype (colour averaged in float32); float64 stays float64 (the mean is
    removed in float64 before the float32 normalisation, so tiny textures on a large offset survive)."""
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        if a.dtype.kind not in "uif" and a.dtype != bool:
            raise InvalidInputError(f"{name}: expected an integer or float image, got dtype {a.dtype}")
        a = a[..., :3].mean(axis=2, dtype=np.float64 if a.dtype == np.float64 else np.float32)
    elif a.ndim != 2:
        raise InvalidInputError(f"{name}: expected a (H, W) grey or (H, W, 3) colour image, got shape {a.shape}")
    if a.dtype.kind not in "uif" and a.dtype != bool:
        raise InvalidInputError(f"{name}: expected an integer or float image, got dtype {a.dtype}")
    if a.dtype == bool:
        a = a.astype(np.float32)
    return a


def normalise_for_matching(img, *, window_px: int = 15, clip_sigma: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Local (Wallis-type) normalisation of a grey image to 8-bit codes, computed in float.

    ``z = (x − m) / sqrt(v + floor)`` with ``m`` the box mean of ``x`` over ``window_px`` and ``v`` the box mean
    of ``(x − m)²``; ``floor`` = 1e-4 × the median of ``v`` (taken on every 4th row and column) keeps flat areas
    from amplifying pure quantisation. Computed in float32 after removing the image mean in the input's
    precision (float32 resolves 3e-5 K on 300 K; the box sums of OpenCV accumulate in float64).

    Parameters
    ----------
    img : (H, W) array of any numeric dtype (float kelvin, uint16 counts, uint8), NaN = invalid
    window_px : side of the box window of the local mean and standard deviation (px)
    clip_sigma : local z-scores are clipped to ±clip_sigma and mapped linearly onto 0..255

    Returns
    -------
    codes : (H, W) uint8; valid : (H, W) bool (finite input)
    """
    import cv2

    a = np.asarray(img)
    if a.ndim != 2:
        raise InvalidInputError(f"image: expected a (H, W) grey array, got shape {a.shape}")
    if a.dtype.kind == "f":
        valid = np.isfinite(a)
        all_valid = bool(valid.all())
    else:
        valid = np.ones(a.shape, bool)
        all_valid = True
    if not all_valid and not valid.any():
        return np.zeros(a.shape, np.uint8), valid
    wdt = np.float64 if a.dtype == np.float64 else np.float32
    k = (int(window_px), int(window_px))
    rb = cv2.BORDER_REFLECT
    if all_valid:
        fill = float(a.mean(dtype=np.float64))
        x = np.subtract(a, wdt(fill), dtype=wdt).astype(np.float32, copy=False)
        m = cv2.blur(x, k, borderType=rb)
    else:
        fill = float(np.mean(a[valid], dtype=np.float64))
        x = np.where(valid, np.subtract(a, wdt(fill), dtype=wdt), 0).astype(np.float32, copy=False)
        vf = valid.astype(np.float32)
        w = cv2.blur(vf, k, borderType=rb)
        m = cv2.blur(x, k, borderType=rb) / np.maximum(w, np.float32(1e-6))
        np.copyto(x, m, where=~valid)
    d = x - m
    v = cv2.blur(d * d, k, borderType=rb)
    np.maximum(v, 0.0, out=v)
    floor = max(float(np.median(v[::4, ::4])) * 1e-4, 1e-20)
    # codes = round((z / clip + 1) * 127.5) clipped to 0..255, as floor(t + 0.5) with t >= 0
    v += np.float32(floor)
    cv2.sqrt(v, v)
    t = cv2.divide(d, v, scale=127.5 / float(clip_sigma))
    t += np.float32(128.0)
    np.clip(t, 0.0, 255.0, out=t)
    return t.astype(np.uint8), valid


def sgbm_matcher(min_disparity: int, num_disparities: int, *, block_size: int = 5, consistency: bool = True,
                 penalty_scale: float = 1.0):
    """The OpenCV SGBM object with this module's settings (3-way mode; ``num_disparities`` a multiple of 16).

    Penalties ``P1 = 8·s·b²``, ``P2 = 32·s·b²`` (``b`` the block size, ``s`` = ``penalty_scale``, default 1:
    OpenCV's usual settings). The local normalisation stretches every neighbourhood over the 8-bit range, so its
    matching costs are larger than on a photograph and larger penalties smooth more: measured on
    benchmarks/dense.py, s = 3 cuts the bad pixels (> 1 px) of the planar pairs 0.159 / 0.0014 / 0.0002 / 0.0013
    -> 0.035 / 0.0002 / 0.0000 / 0.0001 and of two rendered survey pairs 0.088 -> 0.083 and 0.026 -> 0.022, but
    fattens tall objects consistently across views: on the 16-frame block of tests/test_dense.py (true poses)
    the DSM's overall RMSE grows 0.47 -> 0.64 m (cells > 2 m off 472 -> 633) while the ground RMSE falls
    0.103 -> 0.095 m; s = 2 and P1-only increases sit in between (overall 0.50-0.53 m). Hence the default 1.
    ``consistency=False`` gives the plain matcher (no left-right check, uniqueness or speckle filter).
    """
    import cv2

    cn = 1
    p = float(penalty_scale) * cn * block_size**2
    kw = dict(minDisparity=int(min_disparity), numDisparities=int(num_disparities), blockSize=block_size,
              P1=int(round(8 * p)), P2=int(round(32 * p)), mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    if consistency:
        kw.update(disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100, speckleRange=2)
    return cv2.StereoSGBM_create(**kw)


def disparity(left, right, min_disparity: int = 0, num_disparities: int = 64, *, block_size: int = 5,
              window_px: int = 15, penalty_scale: float = 1.0) -> np.ndarray:
    """Disparity of the left image of a rectified pair, sub-pixel, NaN where invalid.

    ``x_right = x_left − d`` on the same row (rows are epipolar lines).

    Parameters
    ----------
    left, right : (H, W) or (H, W, 3) arrays, uint8 / uint16 / float (NaN = no data); the full dynamic range
        is used (local normalisation in float before SGBM, see the module docstring)
    min_disparity : smallest disparity searched (px, may be negative)
    num_disparities : size of the search range (px; rounded up to a multiple of 16 internally, results
        outside ``[min_disparity, min_disparity + num_disparities)`` are set invalid)
    block_size : SGBM matching block (odd, px)
    window_px : window of the local normalisation (px)
    penalty_scale : factor on SGBM's smoothness penalties (see :func:`sgbm_matcher` for the measured trade-off)

    Returns
    -------
    (H, W) float32 disparity in px, NaN where invalid (failed left-right check, not unique, speckle, outside the
    search range, no data, or the left border where the range leaves the right image)

    References
    ----------
    Hirschmüller (2008); seed 003 (multi-resolution dense matching of thermal frames).
    """
    import cv2

    L = _grey(left, "left")
    R = _grey(right, "right")
    if L.shape != R.shape:
        raise InvalidInputError(f"left {L.shape} and right {R.shape}: a rectified pair must have the same size")
    num = int(num_disparities)
    if num < 1:
        raise InvalidInputError(f"num_disparities={num_disparities!r}: expected a positive number of pixels")
    if block_size < 1 or block_size % 2 == 0:
        raise InvalidInputError(f"block_size={block_size!r}: expected an odd number of pixels")
    num16 = -(-num // 16) * 16
    if num16 + block_size >= L.shape[1]:
        raise InvalidInputError(f"num_disparities={num_disparities!r}: the search range (rounded to {num16}) must be "
                                f"smaller than the image width {L.shape[1]} px")
    cl, vl = normalise_for_matching(L, window_px=window_px)
    cr, vr = normalise_for_matching(R, window_px=window_px)
    # OpenCV's x-Sobel prefilter gives the last column a zero derivative and the right-to-left path starts
    # there cold: on locally normalised (high-contrast) codes that column then matches the right image's last
    # column (d = min_disparity) uniquely instead of being left invalid. A few mirrored columns on the right
    # of both images move that border out of the frame (cropped after matching; +0.6 % of SGBM's work at
    # 640 px); bad pixels of the last 6 columns measured 664 -> 54 of 3072 (benchmarks/dense.py, pair 3).
    pad = block_size // 2 + 2
    cl = cv2.copyMakeBorder(cl, 0, 0, 0, pad, cv2.BORDER_REFLECT)
    cr = cv2.copyMakeBorder(cr, 0, 0, 0, pad, cv2.BORDER_REFLECT)
    raw = sgbm_matcher(int(min_disparity), num16, block_size=block_size,
                       penalty_scale=penalty_scale).compute(cl, cr)[:, : L.shape[1]]
    d = raw.astype(np.float32) / 16.0
    bad = (raw < (int(min_disparity)) * 16) | (d >= min_disparity + num) | ~vl
    d[bad] = np.nan
    # the matched right pixel must hold data too
    h, w = d.shape
    ok = np.isfinite(d)
    if ok.any() and not vr.all():
        yy, xx = np.nonzero(ok)
        xr = np.rint(xx - d[ok]).astype(int)
        inside = (xr >= 0) & (xr < w)
        good = np.zeros(len(xr), bool)
        good[inside] = vr[yy[inside], xr[inside]]
        d[yy[~good], xx[~good]] = np.nan
    del cv2
    return d


def disparity_range(left, right, *, factor: int = 4, min_disparity: int = 0, max_disparity: int | None = None,
                    margin_px: int = 16) -> tuple[int, int, float] | None:
    """Search range of a rectified pair from matching at 1/``factor`` resolution.

    Parameters
    ----------
    left, right : rectified pair (full resolution)
    min_disparity, max_disparity : bounds of the coarse search at full resolution (px; default 0 .. width)

    Returns
    -------
    ``(min_disparity, num_disparities, valid_fraction)`` at full resolution (``num`` a multiple of 16);
    ``valid_fraction`` is the share of left pixels with data, inside the searchable columns, that matched.
    None where the coarse level found too few matches (< 5 %: no overlap).
    """
    import cv2

    L = _grey(left, "left")
    R = _grey(right, "right")
    h, w = L.shape

    def down(a):
        v = np.isfinite(a)
        size = (max(1, w // factor), max(1, h // factor))
        s = cv2.resize(np.where(v, a, 0.0), size, interpolation=cv2.INTER_AREA)
        c = cv2.resize(v.astype(np.float64), size, interpolation=cv2.INTER_AREA)
        return np.where(c > 0.5, s / np.maximum(c, 1e-9), np.nan)

    Ls, Rs = down(L), down(R)
    lo_c = int(np.floor(min_disparity / factor))
    hi_c = int(np.ceil((w if max_disparity is None else max_disparity) / factor))
    num = int(min(max(16, -(-(hi_c - lo_c) // 16) * 16), 256, ((Ls.shape[1] - 8) // 16) * 16))
    if num < 16:
        return None
    d = disparity(Ls, Rs, lo_c, num, window_px=9)
    ok = np.isfinite(d)
    searchable = np.isfinite(Ls)
    searchable[:, : max(0, lo_c + num)] = False
    frac = float(ok.sum() / max(1, searchable.sum()))
    if frac < 0.05 or ok.sum() < 20:
        return None
    lo, hi = np.percentile(d[ok], [1, 99]) * factor
    mn = int(np.floor(lo)) - margin_px
    n = int(np.ceil(hi)) + margin_px - mn
    return mn, -(-n // 16) * 16, min(frac, 1.0)
