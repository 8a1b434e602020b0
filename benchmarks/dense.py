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

Part 2 (``--chain N [N ...]``): the whole chain on a synthetic block of about N frames shaped like a DJI M3T
flight (the terrain grows with N so that the flight plan has N frames): ``survey`` (GNSS CSV, GCPs, check
points) → ``dense`` → ``ortho``, each verb in its own process; wall time and peak memory (max RSS) of each
step, and the peak-memory ratio between the largest and the smallest block (goal ≤ 1.5: memory bounded by
tiles and per-image work, not by the block).

Usage::

    python benchmarks/dense.py [--repeats 5]
    python benchmarks/dense.py --chain 100 400 [--workers 2]
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


def make_pair(**kw):
    """640×512 pair with its true disparity: :func:`thermogrammetry.synthetic.stereo.make_stereo_pair`."""
    from thermogrammetry.synthetic.stereo import make_stereo_pair

    return make_stereo_pair((H, W), **kw)


def score(d, truth, band):
    e = np.abs(d - truth)[:, band:]
    ok = np.isfinite(e)
    return float(np.mean(~(e <= 1.0))), float(ok.mean()), float(np.median(e[ok])) if ok.any() else float("nan")


def _run(cmd):
    """Run a command; (wall s, peak RSS MiB of the child, return code)."""
    import os
    import subprocess

    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, ru = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    err = p.stderr.read().decode(errors="replace")
    if p.returncode not in (0,):
        print(f"  {' '.join(cmd[:3])}... exit {p.returncode}: {err.strip().splitlines()[-1] if err.strip() else ''}")
    return time.perf_counter() - t0, ru.ru_maxrss / 1024.0, p.returncode


def chain(sizes, workers: int) -> int:
    import tempfile

    from thermogrammetry.pipeline.project import FolderProject
    from thermogrammetry.synthetic.survey import make_survey, write_survey
    from thermogrammetry.synthetic.survey_files import uav_thermal_config, write_user_files
    from thermogrammetry.synthetic.terrain import TerrainConfig

    exe = [sys.executable, "-m", "thermogrammetry"]
    rows = []
    for n in sizes:
        s = float(np.sqrt(n / 56.0))
        ter = TerrainConfig(width_m=130.0 * s, height_m=100.0 * s, n_buildings=max(1, round(5 * s * s)),
                            n_trees=max(1, round(10 * s * s)), n_roads=max(1, round(s)))
        scene = make_survey(uav_thermal_config(seed=0, terrain=ter))
        with tempfile.TemporaryDirectory(prefix="tg_bench_chain_") as tmp:
            root = Path(tmp)
            t0 = time.perf_counter()
            write_survey(FolderProject(root), scene, prefix="input", threads=2)
            write_user_files(FolderProject(root), scene, prefix="input")
            t_render = time.perf_counter() - t0
            u = root / "input" / "user"
            steps = {
                "survey": exe + ["survey", str(root / "input" / "images"), "-o", str(root / "s"), "--gnss", str(u / "gnss.csv"),
                                 "--gcps", str(u / "gcps.csv"), "--gcp-measurements", str(u / "gcp_measurements.csv"),
                                 "--checkpoints", str(u / "checkpoints.csv"), "--check-measurements",
                                 str(u / "check_measurements.csv"), "--crs", f"EPSG:{scene.terrain.epsg}",
                                 "--workers", str(workers)],
                "dense": exe + ["dense", str(root / "s"), "-o", str(root / "d"), "--workers", str(workers)],
                "ortho": exe + ["ortho", str(root / "s"), "--dsm", str(root / "d" / "dsm.tif"), "-o", str(root / "o"),
                                "--workers", str(workers)],
            }
            res = {}
            for name, cmd in steps.items():
                res[name] = _run(cmd)
                if res[name][2] != 0:
                    break
            rows.append((n, len(scene.frames), t_render, res))
    print(f"\nsurvey -> dense -> ortho on synthetic M3T-like blocks (320x256 float kelvin, GNSS + GCPs), "
          f"--workers {workers}\n")
    print("| frames | step | wall s | peak RSS MiB | exit |")
    print("|---|---|---|---|---|")
    for n, nf, tr, res in rows:
        print(f"| {nf} | render + files (not timed in the chain) | {tr:.0f} | | |")
        tot = 0.0
        for name, (t, m, rc) in res.items():
            tot += t
            print(f"| {nf} | {name} | {t:.0f} | {m:.0f} | {rc} |")
        print(f"| {nf} | survey to ortho | {tot:.0f} | {max(r[1] for r in res.values()):.0f} | |")
    if len(rows) >= 2:
        a, b = rows[0][3], rows[-1][3]
        for name in a:
            if name in b:
                print(f"peak memory ratio {name} ({rows[-1][1]} vs {rows[0][1]} frames): {b[name][1] / a[name][1]:.2f}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--chain", type=int, nargs="+", help="survey -> dense -> ortho on synthetic blocks of ~N frames")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    if args.chain:
        return chain(args.chain, args.workers)
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
