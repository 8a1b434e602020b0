"""Benchmark: thermal target detection vs OpenCV's plain detectors on the real data sets.

Prints, for each image set, how many views each method finds and the time per image:

* thermal_chessboard (6x5 inner corners, 100 mm): masked ("Thermal images cropped") and unmasked
  ("Thermal Images") views, and the unmasked views squeezed to ~7 grey levels with noise (a weakly
  heated board in 8 bit) -- ours (:func:`detect_chessboard`) vs ``cv2.findChessboardCorners``
  on the image as given (OpenCV plain) and vs ``findChessboardCornersSB`` (EXHAUSTIVE|ACCURACY);
* ir_coded_checkerboard (11x9 corners with an ArUco marker): ours
  (:func:`detect_coded_checkerboard`) vs ``findChessboardCornersSB`` 5x5 and 7x7 on the image or
  its inverse, as in the data set's SOURCE.md check.

Writes nothing. Usage::

    python benchmarks/detect_chessboard.py [--data ../shared/data] [--quick] [--circles]

``--quick`` skips the SB columns (the slow reference); ``--circles`` first prints the centre accuracy
of :func:`detect_circle_grid` on synthetic mask grids (160x120 and 640x480, blur + NETD noise).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from thermogrammetry.calibration.detect import (
    ChessboardSpec,
    CodedCheckerboardSpec,
    detect_chessboard,
    detect_coded_checkerboard,
)
from thermogrammetry.calibration.detect_io import read_image

ROOT = Path(__file__).resolve().parents[1]
SB = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def _low_contrast(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The view squeezed to ~7 grey levels around 100 with 0.5-level noise (a weakly heated board)."""
    g = img.astype(float)
    return np.clip(np.rint(100 + (g - g.mean()) * 0.03 + rng.normal(0, 0.5, g.shape)), 0, 255).astype(np.uint8)


def run_chessboard(folder: Path, quick: bool, low_contrast: bool = False):
    spec = ChessboardSpec(6, 5, 100.0)
    files = sorted(folder.glob("*.jpg"))
    rng = np.random.default_rng(0)
    stats = {"ours": [0, 0.0], "opencv plain": [0, 0.0], "opencv SB": [0, 0.0]}
    missed = []
    for f in files:
        img = read_image(f)
        gray = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        if low_contrast:
            img = gray = _low_contrast(gray, rng)
        d, t = _timed(lambda: detect_chessboard(img, spec, f.stem))
        stats["ours"][0] += d.found
        stats["ours"][1] += t
        if not d.found:
            missed.append(f"{f.stem}: {d.reason}")
        (ok, _), t = _timed(lambda: cv2.findChessboardCorners(gray, spec.pattern_size))
        stats["opencv plain"][0] += bool(ok)
        stats["opencv plain"][1] += t
        if not quick:
            (ok, _), t = _timed(lambda: cv2.findChessboardCornersSB(gray, spec.pattern_size, flags=SB))
            stats["opencv SB"][0] += bool(ok)
            stats["opencv SB"][1] += t
    return len(files), stats, missed


def run_coded(folder: Path, quick: bool):
    spec = CodedCheckerboardSpec()
    files = sorted(folder.glob("*.png"))
    stats = {"ours": [0, 0.0], "opencv SB 5x5/7x7 (+inv)": [0, 0.0]}
    n_corners = []
    missed = []
    for f in files:
        img = read_image(f)
        d, t = _timed(lambda: detect_coded_checkerboard(img, spec, f.stem))
        stats["ours"][0] += d.found
        stats["ours"][1] += t
        n_corners.append(d.n_points)
        if not d.found:
            missed.append(f"{f.stem}: {d.reason}")
        if not quick:
            def sb():
                for im in (img, 255 - img):
                    for pat in ((5, 5), (7, 7)):
                        if cv2.findChessboardCornersSB(im, pat, flags=SB)[0]:
                            return True
                return False

            ok, t = _timed(sb)
            stats["opencv SB 5x5/7x7 (+inv)"][0] += ok
            stats["opencv SB 5x5/7x7 (+inv)"][1] += t
    return len(files), stats, missed, np.array(n_corners)


def run_circles():
    """Synthetic mask grids (seed 003: 20 mm holes, 50 mm spacing, 7x4; asymmetric 30 mm pitch),
    rendered by thermogrammetry.synthetic (PSF 1 px, NETD 0.05 K); centre RMS vs exact projections."""
    from thermogrammetry import Camera
    from thermogrammetry.calibration.detect import detect_circle_grid
    from thermogrammetry.geometry import Pose
    from thermogrammetry.pipeline.demo import match_to_truth
    from thermogrammetry.synthetic.targets import render_target_image
    from thermogrammetry.targets import CircleGridTarget

    rows = []
    for w, h, f, ss in ((640, 480, 1000.0, 8), (160, 120, 250.0, 8)):
        cam = Camera("pinhole", (w, h), {"fx": f, "fy": f, "cx": (w - 1) / 2, "cy": (h - 1) / 2})
        for asym in (False, True):
            # one description (mm) for rendering and detection
            tgt = CircleGridTarget(7, 4, 30.0 if asym else 50.0, asymmetric=asym, diameter_mm=20.0)
            c = tgt.object_points_m().mean(axis=0)
            for view, off in (("frontal", np.array([0.0, 0.0, -0.7])), ("oblique", np.array([0.3, -0.25, -0.6]))):
                pose = Pose.look_at(c + off * (1.4 if asym else 1.0), c, up=(0, -1, 0))
                errs = {True: [], False: []}
                for seed in range(3):
                    r = render_target_image(cam, pose, tgt, psf_sigma_px=1.0, netd_k=0.05, seed=seed, supersample=ss)
                    for pc in (True, False):
                        d = detect_circle_grid(r.image_k, tgt, perspective_correction=pc)
                        if d.found:  # paired by position: a symmetric grid may be numbered from the other end
                            errs[pc].append(d.points_px - r.points_px[match_to_truth(d.points_px, r.points_px)[1]])
                for pc in (True, False):
                    e = np.concatenate(errs[pc]) if errs[pc] else np.full((1, 2), np.nan)
                    rms = float(np.sqrt(np.mean(np.sum(e**2, axis=1))))
                    rows.append((f"{w}x{h}", "asym" if asym else "sym", view, "yes" if pc else "no", len(errs[pc]), rms))
    print(f"{'size':8s} {'grid':5s} {'view':8s} {'persp.corr':10s} {'found':>5s} {'RMS px':>8s}")
    for r in rows:
        print(f"{r[0]:8s} {r[1]:5s} {r[2]:8s} {r[3]:10s} {r[4]:3d}/3 {r[5]:8.4f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=os.environ.get("THERMOGRAMMETRY_DATA", str(ROOT.parent / "shared" / "data")))
    ap.add_argument("--quick", action="store_true", help="skip the slow OpenCV SB reference columns")
    ap.add_argument("--circles", action="store_true", help="also print synthetic circle-grid centre accuracy")
    args = ap.parse_args(argv)
    if args.circles:
        run_circles()
        print()
    data = Path(args.data)
    cb = data / "thermal_chessboard" / "Thermal camera calibration"
    coded = data / "ir_coded_checkerboard" / "imageDataset"
    if not cb.is_dir() and not coded.is_dir():
        print(f"no data under {data}", file=sys.stderr)
        return 1
    print(f"{'image set':34s} {'method':26s} {'found':>9s} {'ms/image':>9s}")
    print("-" * 82)
    for label, sub, low in (("chessboard 6x5, masked", "Thermal images cropped", False),
                            ("chessboard 6x5, unmasked", "Thermal Images", False),
                            ("chessboard 6x5, unmasked, 7 levels", "Thermal Images", True)):
        if not (cb / sub).is_dir():
            continue
        n, stats, missed = run_chessboard(cb / sub, args.quick, low)
        for m, (k, t) in stats.items():
            if m == "opencv SB" and args.quick:
                continue
            print(f"{label:34s} {m:26s} {k:4d}/{n:<4d} {1000 * t / max(n, 1):9.1f}")
        for line in missed:
            print(f"    not found: {line}")
    if coded.is_dir():
        n, stats, missed, nc = run_coded(coded, args.quick)
        for m, (k, t) in stats.items():
            if m.startswith("opencv") and args.quick:
                continue
            print(f"{'coded checkerboard 11x9 + ArUco':34s} {m:26s} {k:4d}/{n:<4d} {1000 * t / max(n, 1):9.1f}")
        found = nc[nc > 0]
        if found.size:
            print(f"    corners identified per found view: min {found.min()}, median {np.median(found):.0f}, "
                  f"max {found.max()} (of {CodedCheckerboardSpec().valid_ids().size} usable)")
        for line in missed:
            print(f"    not found: {line}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
