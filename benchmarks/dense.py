"""Benchmark: our dense matcher (:func:`thermogrammetry.dense.disparity`) against plain OpenCV SGBM_3WAY.

Pairs of 640×512 float-kelvin frames with a KNOWN disparity field d(x, y) = a + b·x + c·y (a slanted
plane), texture of thermal ground (spatially correlated, std ``amp``·~0.2 K on 300 K), sensor noise, and
optionally a hot block (+60 K) that takes most of the frame's range, as a heater, a roof in the sun or a
chimney does. Plain OpenCV is run the way a user would: both frames mapped to 8 bits with one global
stretch over the pair, then ``StereoSGBM`` (MODE_SGBM_3WAY, same block size, penalties, uniqueness, speckle
and left-right settings as ours). Ours maps each frame locally in float (Wallis-type) before SGBM.

Scores (left image, columns ≥ num_disparities): bad = share of pixels with |d − truth| > 1 px, invalid
pixels counted as bad; valid share; median error of the valid pixels; time per pair (median of
``--repeats``). Both run in this process, interleaved.

Usage::

    python benchmarks/dense.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

H, W = 512, 640


def make_pair(a=22.0, b=0.02, c=0.01, noise_k=0.02, seed=0, hot=True, amp=1.0):
    from scipy.ndimage import gaussian_filter, map_coordinates

    rng = np.random.default_rng(seed)
    big = 300 + amp * (gaussian_filter(rng.normal(size=(H + 40, W + 200)), 1.5) * 0.8
                       + gaussian_filter(rng.normal(size=(H + 40, W + 200)), 6) * 3)
    if hot:
        big[40:140, 420:600] += 60.0
    y, x = np.mgrid[0:H, 0:W].astype(float)
    d = a + b * x + c * y
    left = map_coordinates(big, [y + 10, x + 100], order=3)
    xl = (x + a + c * y) / (1 - b)
    right = map_coordinates(big, [y + 10, xl + 100], order=3)
    return ((left + rng.normal(0, noise_k, left.shape)).astype(np.float32),
            (right + rng.normal(0, noise_k, left.shape)).astype(np.float32), d)


def score(d, truth, band):
    e = np.abs(d - truth)[:, band:]
    ok = np.isfinite(e)
    return float(np.mean(~(e <= 1.0))), float(ok.mean()), float(np.median(e[ok])) if ok.any() else float("nan")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    from thermogrammetry.dense import disparity
    from thermogrammetry.dense.stereo import sgbm_matcher

    nd = 64
    cases = [("thermal ground, hot block (+60 K), texture std ~0.02 K", dict(hot=True, amp=0.1)),
             ("thermal ground, hot block (+60 K), texture std ~0.06 K", dict(hot=True, amp=0.3)),
             ("thermal ground, hot block, texture std ~0.2 K", dict(hot=True, amp=1.0)),
             ("thermal ground, no hot block, texture std ~0.06 K", dict(hot=False, amp=0.3))]
    print(f"pairs {W}x{H} float kelvin, known planar disparity 22..40 px, num_disparities {nd}, {args.repeats} repeats\n")
    print("| pair | matcher | bad > 1 px | valid | median error px | s per pair | time ours / OpenCV |")
    print("|---|---|---|---|---|---|---|")
    for title, kw in cases:
        L, R, truth = make_pair(**kw)
        lo, hi = min(L.min(), R.min()), max(L.max(), R.max())
        t_ours, t_cv = [], []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            g8 = [np.rint((a - lo) / (hi - lo) * 255).astype(np.uint8) for a in (L, R)]
            raw = sgbm_matcher(0, nd).compute(*g8)
            d_cv = np.where(raw >= 0, raw / 16.0, np.nan)
            t_cv.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            d = disparity(L, R, 0, nd)
            t_ours.append(time.perf_counter() - t0)
        so, sc = score(d, truth, nd), score(d_cv, truth, nd)
        mo, mc = statistics.median(t_ours), statistics.median(t_cv)
        print(f"| {title} | ours | {so[0]:.3f} | {so[1]:.3f} | {so[2]:.3f} | {mo:.3f} | {mo / mc:.2f} |")
        print(f"| | OpenCV SGBM_3WAY, global 8-bit | {sc[0]:.3f} | {sc[1]:.3f} | {sc[2]:.3f} | {mc:.3f} | 1 |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
