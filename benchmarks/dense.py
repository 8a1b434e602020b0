"""Benchmark: our dense matcher (:func:`thermogrammetry.dense.disparity`) against plain OpenCV SGBM_3WAY.

Pairs of 640×512 float-kelvin frames with a KNOWN disparity field d(x, y) = a + b·x + c·y (a slanted
plane, :func:`thermogrammetry.synthetic.stereo.make_stereo_pair`), texture of thermal ground (spatially
correlated, std ``amp``·~0.2 K on 300 K), sensor noise, and optionally a hot block (+60 K) that takes most
of the frame's range, as a heater, a roof in the sun or a chimney does; and a rendered thermal pair: two
consecutive frames of synthetic M3T-like surveys (terrain, buildings, trees, roads; 512×640 portrait
frames so that the along-track rectified pair is 640 px wide; NETD 0.05 K, fixed-pattern noise, PSF,
vignetting) rectified with their TRUE poses by :func:`thermogrammetry.dense.rectify.rectify_pair` and
cropped to 640×512, the true disparity of every rectified left pixel from ray casting the true surface;
pixels hidden from the right camera (occlusions) are not scored. Plain OpenCV is run the way a user would:
both frames mapped to 8 bits with one global stretch over the pair, then ``StereoSGBM`` (MODE_SGBM_3WAY,
block 5, P1 = 8·25, P2 = 32·25 as OpenCV's documentation suggests, uniquenessRatio 10, speckle window 100 /
range 2 px, disp12MaxDiff 1: ours' settings, written out here so that tuning ours does not move the
baseline). Ours computes the 8-bit codes of the pair in float (joint histogram equalisation blended with a
local Wallis-type normalisation, :func:`thermogrammetry.dense.stereo.matching_codes`) before the same SGBM.

Scores (left image, columns ≥ the largest searched disparity; rendered pairs: of those, the pixels whose
surface both cameras see): bad = share of pixels with |d − truth| > 1 px, invalid pixels counted as bad;
valid share; median error of the valid pixels; time per pair (median of ``--repeats``; both run in this process, interleaved, the 8-bit mapping
inside OpenCV's time). The machine's load average is printed before and after.

Part 2 (``--chain N [N ...]``): the whole chain on a synthetic block of about N frames shaped like a DJI M3T
flight (the terrain grows with N so that the flight plan has N frames): ``survey`` (GNSS CSV, GCPs, check
points) → ``dense`` → ``ortho``, each verb in its own process; wall time and peak memory (max RSS) of each
step (the step's process and its dask workers, started from a small launcher process so that this
benchmark's own size does not count), and the peak-memory ratio per step between the largest and the
smallest block (goal ≤ 1.5: memory bounded by tiles and per-image work, not by the block). ``--keep DIR``
keeps the blocks in DIR/n<N> (inputs reused on later runs), ``--steps`` runs only some steps on kept blocks.

Usage::

    python benchmarks/dense.py [--repeats 5]     # matcher table (planar pairs, rendered survey pairs, Middlebury)
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


def plain_sgbm(min_disparity: int, num_disparities: int):
    """Plain OpenCV StereoSGBM (3-way mode, documented penalties), written out independently of our settings."""
    import cv2

    b = 5
    return cv2.StereoSGBM_create(minDisparity=int(min_disparity), numDisparities=int(num_disparities), blockSize=b,
                                 P1=8 * b * b, P2=32 * b * b, disp12MaxDiff=1, uniquenessRatio=10,
                                 speckleWindowSize=100, speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)


def rendered_pair(i: int = 2, j: int = 3, seed: int = 0):
    """Rectified 640×512 pair from frames i, j of a synthetic M3T-like survey with TRUE poses.

    Returns (left, right, truth, scored, (min_disparity, num_disparities)): float32 K with NaN outside the
    frames, float64 px disparity (NaN where no surface), bool mask of the scored pixels (surface seen by both
    cameras, matched right pixel inside the right frame's data, columns >= the largest searched disparity),
    and a search range that holds the truth with 8 px to spare on each side.
    """
    from thermogrammetry.dense.rectify import rectify_pair, remap_frame
    from thermogrammetry.synthetic.stereo import rectified_disparity_truth
    from thermogrammetry.synthetic.survey import make_survey, render_frame
    from thermogrammetry.synthetic.survey_files import uav_thermal_config

    sc = make_survey(uav_thermal_config(seed=seed, image_size=(512, 640), pixel_pitch_um=6.0))
    a, b = sc.frames[i], sc.frames[j]
    rp = rectify_pair(sc.camera, a.pose.R, a.pose.t, sc.camera, b.pose.R, b.pose.t)
    w, h = rp.size
    if w < W or h < H:
        raise RuntimeError(f"rectified pair {rp.size} smaller than {W}x{H}")
    c0, r0 = (w - W) // 2, (h - H) // 2
    L = remap_frame(render_frame(sc, i)["image_k"].astype(np.float32), rp.map_left)[r0:r0 + H, c0:c0 + W]
    R = remap_frame(render_frame(sc, j)["image_k"].astype(np.float32), rp.map_right)[r0:r0 + H, c0:c0 + W]
    u, v = np.meshgrid(np.arange(c0, c0 + W, dtype=float), np.arange(r0, r0 + H, dtype=float))
    truth, seen = rectified_disparity_truth(sc, rp.R_rect, rp.C_left, rp.C_right, rp.f_px, rp.cx_left, rp.cx_right,
                                            rp.cy, u, v)
    ur = u - truth  # right rectified column (uncropped)
    xr = np.rint(ur - c0)
    inside = np.isfinite(xr) & (xr >= 0) & (xr < W)
    okr = np.zeros((H, W), bool)
    yy, xx = np.nonzero(inside)
    okr[yy, xx] = np.isfinite(R[yy, xr[yy, xx].astype(int)])
    scored = seen & np.isfinite(truth) & np.isfinite(L) & okr
    lo, hi = np.percentile(truth[scored], [0, 100])
    mn = int(np.floor(lo)) - 8
    num = -(-(int(np.ceil(hi)) + 8 - mn) // 16) * 16
    scored[:, : mn + num] = False  # as for the planar pairs: SGBM leaves columns < max disparity invalid
    return L, R, truth, scored, (mn, num)


def score(d, truth, band):
    """(bad share, valid share, median error of the valid) over columns >= band, or over a bool mask."""
    e = np.abs(d - truth)[band] if isinstance(band, np.ndarray) else np.abs(d - truth)[:, band:]
    ok = np.isfinite(e)
    return float(np.mean(~(e <= 1.0))), float(ok.mean()), float(np.median(e[ok])) if ok.any() else float("nan")


#: runs the chain's commands for :func:`_run` from a small process. Linux keeps a process's peak RSS across
#: ``exec`` and a forked child starts as a copy of its parent, so a step started directly from this benchmark
#: (which holds the synthetic scene: ~380 MiB at 120 frames, ~1.5 GB at 644) reported at least this
#: process's size as its "peak" (dense and ortho both showed exactly that floor). The launcher is started
#: before the scene exists (~15 MiB), so each step's max RSS is its own (and its dask workers').
_LAUNCHER = r"""
import json, os, subprocess, sys, threading, time
for line in sys.stdin:
    cmd = json.loads(line)
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    buf = []
    th = threading.Thread(target=lambda: buf.append(p.stderr.read()), daemon=True)
    th.start()
    _, status, ru = os.wait4(p.pid, 0)
    th.join(10)
    err = buf[0].decode(errors="replace")[-4000:] if buf else ""
    print(json.dumps([time.perf_counter() - t0, ru.ru_maxrss / 1024.0, os.waitstatus_to_exitcode(status), err]), flush=True)
"""
_launcher = None


def _run(cmd):
    """Run a command through the launcher; (wall s, peak RSS MiB of the command and its children, return code)."""
    import json
    import subprocess

    global _launcher
    if _launcher is None:
        _launcher = subprocess.Popen([sys.executable, "-c", _LAUNCHER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True, bufsize=1)
    _launcher.stdin.write(json.dumps([str(c) for c in cmd]) + "\n")
    _launcher.stdin.flush()
    t, mem, rc, err = json.loads(_launcher.stdout.readline())
    if rc != 0:
        print(f"  {' '.join(cmd[:3])}... exit {rc}: {err.strip().splitlines()[-1] if err.strip() else ''}")
    return t, mem, rc


def _plan_frames(s: float) -> int:
    """Frames of the flight plan of :func:`thermogrammetry.synthetic.survey.make_survey` on the benchmark's terrain
    of ``130 s x 100 s`` m with :func:`uav_thermal_config` (its line and exposure count, without building the
    terrain; :func:`chain` prints the count of the plan actually made)."""
    from thermogrammetry.synthetic.survey import _gsd_footprint
    from thermogrammetry.synthetic.survey_files import uav_thermal_config

    cfg = uav_thermal_config(seed=0)
    across, along = _gsd_footprint(cfg)
    margin = cfg.flight_height_m * np.tan(3 * np.deg2rad(cfg.attitude_sigma_deg)) + 1.0
    W, H = 130.0 * s, 100.0 * s
    if W - along - 2 * margin <= 0 or H - across - 2 * margin <= 0:
        return 0
    n_lines = max(1, int(np.ceil((H - across - 2 * margin) / (across * (1 - cfg.sidelap)))) + 1)
    step = along * (1 - cfg.overlap)
    n_along = max(1, int(np.floor((W - along - 2 * margin) / step + 1e-9)) + 1)
    return n_lines * n_along


def chain_scale(n: int) -> tuple[float, int]:
    """Terrain scale ``s`` (terrain ``130 s x 100 s`` m, the aspect of :func:`uav_thermal_config`'s) whose flight
    plan has the frame count nearest to ``n`` (the smallest such ``s``), and that count.

    The plan has ``lines x exposures`` frames, both counted over the terrain minus one footprint and two margins,
    so the count grows faster than the area: ``s = sqrt(n / 56)`` (56 frames at s = 1) gave 120 frames for 100
    and 644 for 400. Only products of the two counts are possible, hence "nearest"."""
    grid = np.arange(1.0, 12.0, 0.0005)
    counts = np.array([_plan_frames(float(s)) for s in grid])
    k = int(np.argmin(np.abs(counts - n)))
    return float(grid[k]), int(counts[k])


def chain(sizes, workers: int, keep: str | None = None, steps_only=None) -> int:
    import contextlib
    import tempfile

    from thermogrammetry.pipeline.project import FolderProject
    from thermogrammetry.synthetic.survey import make_survey, write_survey
    from thermogrammetry.synthetic.survey_files import uav_thermal_config, write_user_files
    from thermogrammetry.synthetic.terrain import TerrainConfig

    exe = [sys.executable, "-m", "thermogrammetry"]
    _run([sys.executable, "-c", "pass"])  # starts the launcher while this process is still small
    rows = []
    for n in sizes:
        s, planned = chain_scale(n)
        ter = TerrainConfig(width_m=130.0 * s, height_m=100.0 * s, n_buildings=max(1, round(5 * s * s)),
                            n_trees=max(1, round(10 * s * s)), n_roads=max(1, round(s)))
        scene = make_survey(uav_thermal_config(seed=0, terrain=ter))
        print(f"--chain {n}: terrain scale {s:.4f} ({130.0 * s:.1f} x {100.0 * s:.1f} m), flight plan of "
              f"{len(scene.frames)} frames (predicted {planned})", flush=True)
        if keep:
            ctx = contextlib.nullcontext(str(Path(keep) / f"n{n}"))
        else:
            ctx = tempfile.TemporaryDirectory(prefix="tg_bench_chain_")
        with ctx as tmp:
            root = Path(tmp)
            t0 = time.perf_counter()
            if not (keep and (root / "input" / "user" / "checkpoints.csv").exists()):
                root.mkdir(parents=True, exist_ok=True)
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
                if steps_only and name not in steps_only:
                    continue
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
        print(f"\n| step | peak RSS MiB, {rows[0][1]} frames | peak RSS MiB, {rows[-1][1]} frames | ratio (goal <= 1.5) "
              f"| wall s ratio |")
        print("|---|---|---|---|---|")
        for name in a:
            if name in b:
                print(f"| {name} | {a[name][1]:.0f} | {b[name][1]:.0f} | {b[name][1] / a[name][1]:.2f} "
                      f"| {b[name][0] / a[name][0]:.2f} |")
        if all(name in b for name in a):
            pa, pb = max(r[1] for r in a.values()), max(r[1] for r in b.values())
            print(f"| survey to ortho (max of the steps) | {pa:.0f} | {pb:.0f} | {pb / pa:.2f} | |")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--chain", type=int, nargs="+", help="survey -> dense -> ortho on synthetic blocks of ~N frames")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--keep", metavar="DIR", help="--chain: keep the blocks in DIR/n<N> (inputs are reused when present)")
    ap.add_argument("--steps", nargs="+", choices=["survey", "dense", "ortho"],
                    help="--chain: run only these steps (the others' outputs must be in --keep)")
    args = ap.parse_args(argv)
    if args.chain:
        return chain(args.chain, args.workers, args.keep, args.steps)
    import os

    from thermogrammetry.dense import disparity

    nd = 64
    cases = [("planar, hot block (+60 K), texture std ~0.02 K", dict(hot=True, amp=0.1)),
             ("planar, hot block (+60 K), texture std ~0.06 K", dict(hot=True, amp=0.3)),
             ("planar, hot block, texture std ~0.2 K", dict(hot=True, amp=1.0)),
             ("planar, no hot block, texture std ~0.06 K", dict(hot=False, amp=0.3)),
             ("rendered survey pair (seed 0, frames 2-3, true poses)", (2, 3, 0)),
             ("rendered survey pair (seed 1, frames 10-11, true poses)", (10, 11, 1))]
    print(f"pairs {W}x{H} float kelvin; planar: known disparity 22..40 px, num_disparities {nd}; "
          f"{args.repeats} repeats; load average {' '.join(f'{x:.2f}' for x in os.getloadavg())} "
          f"on {os.cpu_count()} CPUs\n")
    print("| pair | matcher | bad > 1 px | valid | median error px | s per pair | time ours / OpenCV |")
    print("|---|---|---|---|---|---|---|")
    for title, kw in cases:
        if isinstance(kw, tuple):
            L, R, truth, band, (mn, num) = rendered_pair(*kw)
            title += f", {int(band.sum())} scored px, search {mn}..{mn + num}"
        else:
            L, R, truth = make_pair(**kw)
            band, mn, num = nd, 0, nd
        lo, hi = float(min(np.nanmin(L), np.nanmin(R))), float(max(np.nanmax(L), np.nanmax(R)))
        t_ours, t_cv = [], []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            g8 = [np.nan_to_num(np.rint((a - lo) / (hi - lo) * 255), nan=0.0).astype(np.uint8) for a in (L, R)]
            raw = plain_sgbm(mn, num).compute(*g8)
            d_cv = np.where(raw >= mn * 16, raw / 16.0, np.nan)
            t_cv.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            d = disparity(L, R, mn, num)
            t_ours.append(time.perf_counter() - t0)
        so, sc = score(d, truth, band), score(d_cv, truth, band)
        mo, mc = statistics.median(t_ours), statistics.median(t_cv)
        print(f"| {title} | ours | {so[0]:.4f} | {so[1]:.4f} | {so[2]:.3f} | {mo:.4f} | {mo / mc:.2f} |")
        print(f"| | OpenCV SGBM_3WAY, global 8-bit | {sc[0]:.4f} | {sc[1]:.4f} | {sc[2]:.3f} | {mc:.4f} | 1 |")
    middlebury(args.repeats)
    print(f"\nload average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


def middlebury(repeats: int) -> None:
    """A public photograph pair with ground truth: Middlebury 2014 Motorcycle as bundled by scikit-image (741x500,
    8-bit RGB, true disparities 7-60 px; 64 searched). OpenCV gets the grey pair (no stretch needed: 8-bit)."""
    import cv2

    from thermogrammetry.dense import disparity

    try:
        from skimage.data import stereo_motorcycle
    except ImportError:
        print("| Middlebury 2014 Motorcycle | (scikit-image not installed: pip install -e '.[test]') | | | | | |")
        return
    L, R, gt = stereo_motorcycle()
    gt = np.asarray(gt, float)
    band = np.isfinite(gt) & (gt > 0)
    band[:, :64] = False
    t_ours, t_cv = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        raw = plain_sgbm(0, 64).compute(cv2.cvtColor(L, cv2.COLOR_RGB2GRAY), cv2.cvtColor(R, cv2.COLOR_RGB2GRAY))
        d_cv = np.where(raw >= 0, raw / 16.0, np.nan)
        t_cv.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        d = disparity(L, R, 0, 64)
        t_ours.append(time.perf_counter() - t0)
    so, sc = score(d, gt, band), score(d_cv, gt, band)
    mo, mc = statistics.median(t_ours), statistics.median(t_cv)
    title = f"Middlebury 2014 Motorcycle (photographs, 741x500 RGB, {int(band.sum())} scored px, search 0..64)"
    print(f"| {title} | ours | {so[0]:.4f} | {so[1]:.4f} | {so[2]:.3f} | {mo:.4f} | {mo / mc:.2f} |")
    print(f"| | OpenCV SGBM_3WAY, grey | {sc[0]:.4f} | {sc[1]:.4f} | {sc[2]:.3f} | {mc:.4f} | 1 |")


if __name__ == "__main__":
    sys.exit(main())
