"""Benchmark: the mask circle-grid replica (issue 13) through the detector and ``thermogrammetry calibrate``.

Renders :func:`thermogrammetry.synthetic.mask_grid_replica.make_mask_grid_replica` (24 views of a 4 x 3
grid of dark 60 mm circles at 90 mm in a warm mask, 640 x 512, fx 440.7 px, ~80 px barrel distortion at
the corners) as float32 kelvin TIFFs, 8-bit PNGs (AGC stretch) and 16-bit TIFFs (0.01 K counts), then
for each variant prints: views found, the detector's raw centre error against the exact centroid of
each imaged circle (RMS / max, px), and the CLI calibration (RMS against the value expected from the
injected centre noise, fx ± σ against the truth, every free parameter's offset from the truth in σ).
Run from the repository root::

    PYTHONPATH=$PWD/src /work/main/.venv/bin/python benchmarks/maskgrid_replica.py OUTDIR \
        [--noise-px 0.1] [--supersample 6] [--refine edges] [--variants f32 u8 u16] \
        [--scene "dict(temperatures=(306.0, 308.0, 330.0, 294.0, 309.0))"]

(``--scene`` takes keyword arguments of ``make_mask_grid_replica``, e.g. ``roll_deg``, ``params``,
``temperatures``, ``gradient``, ``psf_sigma_px``, ``netd_k``.)
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
import time
from pathlib import Path

import numpy as np


def render(out: Path, noise_px: float, supersample: int, scene: dict):
    import cv2
    import tifffile

    from thermogrammetry.synthetic.mask_grid_replica import make_mask_grid_replica, quantize

    t0 = time.time()
    r = make_mask_grid_replica(supersample=supersample, centre_noise_px=noise_px, **scene)
    for v in ("f32", "u8", "u16"):
        (out / v).mkdir(parents=True, exist_ok=True)
    for n, im in zip(r.names, r.images_k):
        tifffile.imwrite(out / "f32" / f"{n}.tif", im)
        cv2.imwrite(str(out / "u8" / f"{n}.png"), quantize(im, 8))
        tifffile.imwrite(out / "u16" / f"{n}.tif", quantize(im, 16))
    print(f"rendered {len(r.names)} views in {time.time() - t0:.0f} s (fill {min(r.fill):.2f}-{max(r.fill):.2f}, "
          f"tilt up to {max(r.tilt_deg):.0f} deg)")
    return r


def detect(r, out: Path, var: str, refine: str):
    from thermogrammetry.calibration.detect_circles import detect_circle_grid
    from thermogrammetry.calibration.detect_io import read_image

    ext = "png" if var == "u8" else "tif"
    errs, found = [], 0
    for k, n in enumerate(r.names):
        d = detect_circle_grid(read_image(out / var / f"{n}.{ext}"), r.target, n, perspective_correction=False,
                               refine=refine)
        if not d.found:
            print(f"  {n}: not found: {d.reason[:300]}")
            continue
        found += 1
        truth = r.points_px[k] + r.centroid_bias_px[k]
        a, b = truth[d.object_ids], truth[::-1][d.object_ids]
        t = a if np.abs(d.points_px - a).max() < np.abs(d.points_px - b).max() else b
        errs.append(np.linalg.norm(d.points_px - t, axis=1))
    e = np.concatenate(errs)
    print(f"{var} detection ({refine}): found {found}/{len(r.names)}, centre error RMS {np.sqrt(np.mean(e**2)):.4f} "
          f"max {e.max():.4f} px")


def calibrate(r, out: Path, var: str, truth: dict):
    from thermogrammetry.cli.main import main

    res = out / f"OUT_{var}"
    rc = main(["calibrate", str(out / var), "--target", "circles", "--grid", "4x3", "--spacing-mm", "90",
               "--diameter-mm", "60", "--pixel-pitch-um", "17", "-o", str(res)])
    cal = json.loads((res / "calibration.json").read_text())
    sig = float(np.sqrt(np.mean(np.concatenate(r.centre_shifts_px) ** 2)))
    n_obs = 2 * sum(row["n_points"] for row in cal["per_image"] if row["used"])
    exp = np.sqrt(2 * sig**2 * cal["dof"] / n_obs)
    P = cal["parameters"]
    z = {k: (P[k]["value"] - truth.get(k, 0.0)) / P[k]["std"] for k in P if P[k]["estimated"]}
    print(f"{var} calibrate (exit {rc}): used {len(cal['images_used'])}, RMS {cal['rms_px']:.4f} px (expected "
          f"{exp:.4f} from the injected {sig:.3f} px: ratio {cal['rms_px'] / exp if exp else float('nan'):.3f}), "
          f"fx {P['c_mm']['value'] / 0.017:.2f} ± {P['c_mm']['std'] / 0.017:.2f} px (truth {truth['c_mm'] / 0.017:.2f}); "
          "offsets in sigma: " + ", ".join(f"{k} {v:+.2f}" for k, v in z.items()))


def main(argv=None):
    from thermogrammetry.synthetic.mask_grid_replica import MASK_GRID_CAMERA

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--noise-px", type=float, default=0.1)
    ap.add_argument("--supersample", type=int, default=6)
    ap.add_argument("--refine", default="edges")
    ap.add_argument("--variants", nargs="+", default=["f32", "u8", "u16"])
    ap.add_argument("--scene", default="{}")
    ap.add_argument("--no-calibrate", action="store_true")
    a = ap.parse_args(argv)
    scene = ast.literal_eval(a.scene) if a.scene.strip().startswith("{") else eval(a.scene, {"dict": dict})  # noqa: S307
    r = render(a.out, a.noise_px, a.supersample, scene)
    truth = dict(MASK_GRID_CAMERA, **scene.get("params", {}))
    for var in a.variants:
        detect(r, a.out, var, a.refine)
        if not a.no_calibrate:
            calibrate(r, a.out, var, truth)
    return 0


if __name__ == "__main__":
    sys.exit(main())
