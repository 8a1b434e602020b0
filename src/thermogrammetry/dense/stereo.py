"""Semi-global matching of a rectified pair on the full dynamic range of thermal frames.

:func:`disparity` is the plain function for rectified pairs. OpenCV's SGBM (Hirschmüller 2008) works on
8-bit codes; a thermal frame's texture (tenths of a kelvin on a range of tens of kelvin, or a few hundred
counts out of 16 bits) would be flattened to a few grey levels by a global 8-bit rendering. We therefore
compute the 8-bit codes of a pair in float (:func:`matching_codes`) as a blend of two maps: a joint histogram
equalisation of both images (one monotonic map: the same temperature gets the same code in both, edges and
low frequencies kept, the codes go where the pixels are, so a hot object taking most of the range but few
pixels gets few codes) and a *local* normalisation of each image (Wallis-type filter: subtract the local mean,
divide by the local standard deviation over ``window_px``, so that every neighbourhood uses the whole 8-bit
range; alone it leaves halos of suppressed texture next to strong edges). Only then SGBM runs (3-way mode)
with its sub-pixel parabola fit, a left-right consistency check (``disp12MaxDiff``), a uniqueness test and a
speckle filter. Both code images get a few mirrored columns on the right before SGBM (cropped after), so that
the left image's last columns are matched like the others instead of locking onto the right image's border.
A coarse-to-fine variant (:func:`disparity_range`) finds the disparity search range of a pair at a quarter
resolution. The codes of the two images are computed on two threads when OpenCV may use two (same values as
one thread). Figures: benchmarks/dense.py.

References
----------
Hirschmüller H. (2008), Stereo processing by semiglobal matching and mutual information, IEEE PAMI 30(2).
Wallis R. (1976), An approach to the space variant restoration and enhancement of images.
Gonzalez R. C., Woods R. E., Digital Image Processing, histogram equalisation (§3.3).
Khodaei, Samadzadegan, Dadras Javan, Hasani (seed 003): multi-resolution dense matching of UAV thermal video.
"""

from __future__ import annotations

import numpy as np

from .._sampling import fill_nearest_valid
from ..errors import InvalidInputError

__all__ = ["disparity", "normalise_for_matching", "matching_codes", "disparity_range", "sgbm_matcher"]

EQUALISED_WEIGHT = 0.5

"""Weight of the joint histogram equalisation in :func:`matching_codes` (the rest is the local normalisation)
for 16-bit and float pairs (thermal frames on their full dynamic range)."""

EQUALISED_WEIGHT_8BIT = 1.0

"""The same weight for 8-bit pairs (photographs, 8-bit renderings: already mapped for display). Measured on the
Middlebury 2014 Motorcycle pair (741x500, scikit-image's ``data.stereo_motorcycle``, 64 disparities; bad pixels
> 1 px of the pixels with a true disparity and at least 64 px from the left border, invalid counted as bad):
w = 1 0.121 (window 7/15/31 px alike), w = 0.5 0.130-0.134, w = 0 0.137-0.148; plain OpenCV SGBM_3WAY 0.124 (grey)
/ 0.123 (colour). On the thermal pairs of benchmarks/dense.py w = 1 and w = 0.5 are within 0.002 of each other
(:func:`matching_codes`)."""


def _grey(img, name: str) -> np.ndarray:
    """(H, W) grey array in its own dtype (colour averaged in float32); float64 stays float64 (the mean is
    removed in float64 before the float32 normalisation, so tiny textures on a large offset survive)."""
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        if a.dtype.kind not in "uif" and a.dtype != bool:
            raise InvalidInputError(f"{name}: expected an integer or float image, got dtype {a.dtype}")
        if a.dtype not in (np.uint8, np.uint16, np.int16, np.float32):
            a = a[..., :3].mean(axis=2, dtype=np.float64 if a.dtype == np.float64 else np.float32)
        else:
            # the mean of the three channels in float32, ((c0 + c1) + c2) / 3 as NumPy's mean computes it (same
            # values), by OpenCV's channel split and adds: 10x faster than a reduction over the last axis
            import cv2

            c = cv2.split(np.ascontiguousarray(a[..., :3]))
            s = cv2.add(c[0], c[1], dtype=cv2.CV_32F) if a.dtype != np.float32 else cv2.add(c[0], c[1])
            s = cv2.add(s, c[2].astype(np.float32, copy=False))
            s /= np.float32(3.0)
            a = s
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
    of ``(x − m)²``; ``floor`` = 1e-4 × the mean of ``v`` keeps flat areas from amplifying pure quantisation. Computed in float32 after removing the image mean in the input's
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
    t, valid = _local_levels(img, window_px, clip_sigma)
    return t.astype(np.uint8), valid


def _local_levels(img, window_px: int, clip_sigma: float, gain: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """``gain`` × the float levels (0..255.5, floor = the rounded code) of :func:`normalise_for_matching`, and
    the valid mask."""
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
        return np.zeros(a.shape, np.float32), valid
    wdt = np.float64 if a.dtype == np.float64 else np.float32
    k = (int(window_px), int(window_px))
    rb = cv2.BORDER_REFLECT
    if all_valid:
        fill = float(cv2.mean(a)[0]) if a.dtype in (np.float32, np.float64) else float(a.mean(dtype=np.float64))
        x = np.subtract(a, wdt(fill), dtype=wdt).astype(np.float32, copy=False)
        m = cv2.blur(x, k, borderType=rb)
    else:
        invalid = ~valid
        src = a if a.dtype in (np.float32, np.float64) else a.astype(np.float32)
        fill = float(cv2.mean(src, mask=valid.view(np.uint8))[0])
        x = np.subtract(a, wdt(fill), dtype=wdt).astype(np.float32, copy=False)
        np.copyto(x, np.float32(0.0), where=invalid)
        w = cv2.blur(valid.view(np.uint8).astype(np.float32), k, borderType=rb)
        np.maximum(w, np.float32(1e-6), out=w)
        m = cv2.divide(cv2.blur(x, k, borderType=rb), w)
        np.copyto(x, m, where=invalid)
    d = cv2.subtract(x, m)
    v = cv2.sqrBoxFilter(d, cv2.CV_32F, k, borderType=rb)  # box mean of d², >= 0
    floor = max(float(cv2.mean(v)[0]) * 1e-4, 1e-20)  # flat areas: no amplification of pure quantisation
    # levels (z / clip + 1) * 127.5 clipped to 0..255 (+ 0.5: the codes are floor(t), i.e. rounded)
    g = float(gain)
    v += np.float32(floor)
    cv2.sqrt(v, v)
    t = cv2.divide(d, v, scale=127.5 * g / float(clip_sigma))
    t += np.float32(128.0 * g)
    np.clip(t, 0.0, 255.5 * g, out=t)
    return t, valid


def _equalised_levels(L, R, vl=None, vr=None, gain: float = 1.0,
                      bins: int = 65536, threads: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Joint histogram equalisation of a pair: one monotonic map of the values of both images onto 0..255.

    The map is the mid-rank of each value in the pooled histogram (``bins`` equal bins between the pair's
    minimum and maximum; the histogram of every other row and column), so that the same temperature gets the
    same level in both images, steps and low frequencies are kept (no halo), and the levels go where the pixels
    are: a hot object taking most of the range but few pixels gets few levels. ``L``, ``R`` must be finite
    (no-data already filled); ``vl``, ``vr`` (bool, optional) restrict the histogram to the valid pixels.
    Returns ``gain`` × float32 levels in 0..255.5 (floor = the rounded code). ``threads``: the two images' passes
    on two threads (:func:`_run_pair`).
    """
    pair = _run_pair if threads else (lambda fn, a, b: (fn(a), fn(b)))
    lo = float(min(L.min(), R.min()))
    hi = float(max(L.max(), R.max()))
    g = float(gain)
    if not hi > lo:
        return np.full(L.shape, 128.0 * g, np.float32), np.full(R.shape, 128.0 * g, np.float32)
    sc = (bins - 1) / (hi - lo)
    idx = pair(lambda a: _bin_index(a, lo, sc, bins), L, R)
    h = np.zeros(bins, np.intp)
    for i, v in ((idx[0], vl), (idx[1], vr)):
        sub = i[::2, ::2]
        h += np.bincount(sub.ravel() if v is None else sub[v[::2, ::2]], minlength=bins)
    c = np.cumsum(h)
    lut = ((c - 0.5 * h) * (255.0 * g / max(int(c[-1]), 1)) + 0.5 * g).astype(np.float32)
    return tuple(pair(lambda i: np.take(lut, i), *idx))


def _bin_index(a: np.ndarray, lo: float, sc: float, bins: int) -> np.ndarray:
    """Histogram bin of every pixel, ``floor((a − lo) · sc)`` in the input's float precision (float32 unless
    float64), as uint16 when ``bins`` <= 65536 (half the memory traffic of an index array; bitwise the same
    bins as a conversion to intp: the truncation of the same float values)."""
    f = np.subtract(a, lo, dtype=np.float64 if a.dtype == np.float64 else np.float32)
    f *= sc
    if bins <= 65536:
        np.minimum(f, bins - 1, out=f)  # (hi − lo) · sc may round up past the last bin
        return f.astype(np.uint16)
    return f.astype(np.intp)


def _threaded(a) -> bool:
    """Whether a pair of images of ``a``'s size is coded on two threads (OpenCV allowed more than one)."""
    import cv2

    return cv2.getNumThreads() >= 2 and a.size >= _THREADED_MIN_PIXELS


def _run_pair(fn, a, b) -> tuple:
    """``(fn(a), fn(b))``, the two calls on two threads when OpenCV may use more than one (OpenCV and NumPy
    release the GIL in these array passes; the results are those of two calls in a row). ``a``, ``b``: arrays,
    or tuples whose first item is the image (its size decides)."""
    if not _threaded(a[0] if isinstance(a, tuple) else a):
        return fn(a), fn(b)
    fut = _thread_pool().submit(fn, b)
    return fn(a), fut.result()


#: pairs smaller than this (pixels per image) are coded in one thread (thread hand-over costs ~0.1 ms)
_THREADED_MIN_PIXELS = 65536
_POOL: list = [None, None]  # [executor, pid that created it]


def _thread_pool():
    """A two-thread executor of this process (made again after a fork: a child has no threads of its parent)."""
    import os
    from concurrent.futures import ThreadPoolExecutor

    if _POOL[0] is None or _POOL[1] != os.getpid():
        _POOL[0], _POOL[1] = ThreadPoolExecutor(max_workers=2, thread_name_prefix="tg-codes"), os.getpid()
    return _POOL[0]


def matching_codes(left, right, *, window_px: int = 15, clip_sigma: float = 3.0,
                   equalised_weight: float = EQUALISED_WEIGHT):
    """8-bit codes of a rectified pair for SGBM: ``w`` × joint histogram equalisation + (1 − ``w``) × local
    (Wallis-type) normalisation, computed in float and rounded once.

    The local part (:func:`normalise_for_matching`) gives every neighbourhood the whole 8-bit range but
    removes low frequencies and leaves a halo of suppressed texture within ``window_px``/2 of strong edges
    (tree crowns, roof edges); the equalised part (:func:`_equalised_levels`) keeps edges and low frequencies
    and is the same monotonic map for both images. No-data pixels take the value of their nearest valid
    pixel before both (no artificial edge at a rectified frame's border).

    Measured (bad pixels > 1 px against the true disparity, invalid counted as bad; benchmarks/dense.py:
    4 planar pairs / 2 rendered 640x512 survey pairs): w = 0.5 (default) 0.150 0.0010 0.0001 0.0011 /
    0.0862 0.0193; plain OpenCV on a global 8-bit stretch 0.741 0.0098 0.0010 0.0033 / 0.0871 0.0200. While
    choosing w (codes filled by nearest code, floor by median): local only (w = 0) 0.159 0.0014 0.0002
    0.0013 / 0.0880 0.0260; w = 0.5 0.155 0.0011 0.0001 0.0011 / 0.0863 0.0192; w = 0.7 0.155 0.0009 0.0001
    0.0009 / 0.0857 0.0176; equalised only (w = 1, no fill) 0.157 0.0010 0.0001 0.0010 / 0.0873 0.0196. w = 0.5
    rather than 0.7: on the 16-frame block of tests/test_dense.py (true poses) the DSM's ground RMSE was
    0.105 m at w = 0.5 (0.103 at w = 0) but 0.112 m, above its 1-GSD bound of 0.11 m, at w = 0.7; now
    (w = 0.5, fill by value) ground 0.094 m, overall 0.456 m, completeness 0.936.

    Parameters
    ----------
    left, right : (H, W) grey arrays of the same shape, any numeric dtype, NaN = no data
    window_px, clip_sigma : of the local normalisation
    equalised_weight : ``w`` in 0..1

    Returns
    -------
    codes_left, codes_right : (H, W) uint8; valid_left, valid_right : (H, W) bool
    """
    w = float(equalised_weight)
    if not 0.0 <= w <= 1.0:
        raise InvalidInputError(f"equalised_weight={equalised_weight!r}: expected a number in 0..1")
    L, R = np.asarray(left), np.asarray(right)
    if L.shape != R.shape or L.ndim != 2:
        raise InvalidInputError(f"left {L.shape} and right {R.shape}: expected two (H, W) arrays of the same size")
    vl = np.isfinite(L) if L.dtype.kind == "f" else np.ones(L.shape, bool)
    vr = np.isfinite(R) if R.dtype.kind == "f" else np.ones(R.shape, bool)
    all_l, all_r = bool(vl.all()), bool(vr.all())
    if not (vl.any() and vr.any()):
        return np.zeros(L.shape, np.uint8), np.zeros(R.shape, np.uint8), vl, vr
    # no-data pixels (outside a rectified frame) take the value of their nearest valid pixel: no artificial
    # edge at the frame's border for SGBM to lock onto (5 rendered survey pairs of 320x256 px, bad pixels > 1 px:
    # 0.0505 0.0399 0.0424 0.0197 0.0491 -> 0.0441 0.0391 0.0364 0.0109 0.0406, tests/test_dense.py), and the
    # all-valid (fast) paths below
    Lf, Rf = _run_pair(lambda ab: ab[0] if ab[2] else fill_nearest_valid(ab[0], ab[1]), (L, vl, all_l), (R, vr, all_r))
    masks = (None if all_l else vl, None if all_r else vr)
    if 0.0 < w < 1.0 and _threaded(Lf):
        # the two local normalisations on the two pool threads while this thread equalises (same values)
        fl, fr = (_thread_pool().submit(_local_levels, a, window_px, clip_sigma, 1.0 - w) for a in (Lf, Rf))
        el, er = _equalised_levels(Lf, Rf, *masks, gain=w, threads=False)
        tl, tr = fl.result()[0], fr.result()[0]
    elif w < 1.0:
        (tl, _), (tr, _) = _run_pair(lambda a: _local_levels(a, window_px, clip_sigma, gain=1.0 - w), Lf, Rf)
        el = er = None
        if w > 0.0:
            el, er = _equalised_levels(Lf, Rf, *masks, gain=w)
    else:  # the local part has weight 0: not computed
        tl, tr = _equalised_levels(Lf, Rf, *masks, gain=w)
        el = er = None
    if 0.0 < w < 1.0:
        tl += el
        tr += er
    return tl.astype(np.uint8), tr.astype(np.uint8), vl, vr


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
              window_px: int = 15, penalty_scale: float = 1.0, equalised_weight: float | None = None) -> np.ndarray:
    """Disparity of the left image of a rectified pair, sub-pixel, NaN where invalid.

    ``x_right = x_left − d`` on the same row (rows are epipolar lines).

    Parameters
    ----------
    left, right : (H, W) or (H, W, 3) arrays, uint8 / uint16 / float (NaN = no data); the full dynamic range
        is used (8-bit codes computed in float by :func:`matching_codes`, see the module docstring)
    min_disparity : smallest disparity searched (px, may be negative)
    num_disparities : size of the search range (px; rounded up to a multiple of 16 internally, results
        outside ``[min_disparity, min_disparity + num_disparities)`` are set invalid)
    block_size : SGBM matching block (odd, px)
    window_px : window of the local normalisation (px)
    penalty_scale : factor on SGBM's smoothness penalties (see :func:`sgbm_matcher` for the measured trade-off)
    equalised_weight : weight of the joint equalisation in the codes (:func:`matching_codes`; None:
        :data:`EQUALISED_WEIGHT_8BIT` when both images are uint8, else :data:`EQUALISED_WEIGHT`)

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
    if equalised_weight is None:
        eight_bit = np.asarray(left).dtype == np.uint8 and np.asarray(right).dtype == np.uint8
        equalised_weight = EQUALISED_WEIGHT_8BIT if eight_bit else EQUALISED_WEIGHT
    cl, cr, vl, vr = matching_codes(L, R, window_px=window_px, equalised_weight=equalised_weight)
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
    d = raw.astype(np.float32)
    d *= np.float32(1.0 / 16.0)
    # d = raw / 16 exactly (int16 / 16 in float32), so the range test runs on the integers
    bad = raw < int(min_disparity) * 16
    bad |= raw >= (int(min_disparity) + num) * 16
    bad |= ~vl
    np.copyto(d, np.float32(np.nan), where=bad)
    # the matched right pixel (nearest) must hold data too: checked on the rows where the right image has no-data
    # pixels or a match lands within half a pixel of its side borders (elsewhere every match lands on data)
    if not vr.all():
        w = d.shape[1]
        xr = np.arange(w, dtype=np.float32)[None, :] - d  # NaN where bad (d is NaN there)
        with np.errstate(invalid="ignore"):
            near_border = ((xr < 0.5) | (xr > w - 1.5)).any(axis=1)
        rows = np.flatnonzero(near_border | ~vr.all(axis=1))
        if rows.size:
            sub = xr[rows]
            np.copyto(sub, np.float32(-1.0), where=np.isnan(sub))
            yr = np.ascontiguousarray(np.broadcast_to(rows.astype(np.float32)[:, None], sub.shape))
            good = cv2.remap(vr.view(np.uint8), sub, yr, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                             borderValue=0)
            dr = d[rows]
            dr[good == 0] = np.nan
            d[rows] = dr
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
    # local normalisation only at the coarse level: with the equalisation there too the 16-frame block of
    # tests/test_dense.py loses DSM completeness (measured 0.931 -> 0.897)
    d = disparity(Ls, Rs, lo_c, num, window_px=9, equalised_weight=0.0)
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
