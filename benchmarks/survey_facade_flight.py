"""Benchmark: close-range UAV thermal facade flights (M2ED-like palette JPEGs) through the public CLI, against the truth.

Scene: :mod:`thermogrammetry.synthetic.facade_flight` -- a brick facade (running bond 0.25 x 0.065 m, 12 mm joints,
0.35 K per brick, joints 0.5 K warmer, a 0.6 K smooth field), a grid of identical windows (1.0 x 1.45 m every 2.2 x
3.0 m, glass 9 K colder recessed 0.15 m), two downpipes; a camera like the DJI Mavic 2 Enterprise Dual's thermal one
(160x120 core upscaled to 640x480, 57° HFOV through k1 -0.35 / k2 0.06), 5 lawnmower strips of 10 frames 2.5-3.5 m
from the wall at 75 % forward / 70 % side overlap, attitude jitter 1.5°; frames written as iron-palette 8-bit JPEGs
(per-frame 1-99 % AGC) with EXIF Make DJI / Model M2ED, no focal length, GPS of a consumer GNSS (bias σ 2.5 m per
axis, AR(1) wander σ 1 m).

Each seed: ``python -m thermogrammetry survey FRAMES -o OUT --workers 0`` (GNSS from the EXIF, as a user runs it).
Scores, on the largest oriented block after a similarity to the truth
(:func:`thermogrammetry.synthetic.lowtexture_facade.pose_errors`): share of the frames in it, rotation RMS / max (deg),
centre RMS as a percentage of the mean distance to the wall; and what ``survey.json`` gives as refusal reasons.

Usage::

    python benchmarks/survey_facade_flight.py [--seed 0 1 2] [--strips 5] [--per-strip 10] [--keep DIR] [-- EXTRA SURVEY ARGS]

Baseline (main at 0ff41c6, 2026-12-04, 2 cores; ``python benchmarks/survey_facade_flight.py``)::

    seed        oriented  blocks in block  rot RMS/max deg  centre RMS % dist    f px     k1  time s
    seed0         50/50     [50]     100%        3.18/5.41             2.63 %     597 -0.258      79
    seed1         50/50     [50]     100%        1.09/1.92             1.35 %     604 -0.287     137
    seed2         50/50     [50]     100%        3.51/6.39             2.49 %     595 -0.251      94

  Every frame is oriented in one block (the synthetic flight does not reproduce the real flight's 0 of 93), but the
  block misses the accuracy asked for (0.5°, 1 %): the self-calibrated focal length stays near the camera table's
  start (589 ± 38 px from the 57° HFOV as a pinhole; the lens's true value through its barrel distortion is 653 px)
  and k1 near -0.26 (true -0.35) -- a fronto-parallel flight over a plane hardly determines the focal length. Seed 0,
  same code, diagnostic runs (the survey patched in-process):

  =========================================================  =================  ===========  ============
  seed 0                                                      rot RMS/max deg    centre %     f px / k1
  =========================================================  =================  ===========  ============
  as above (table start 589 ± 38 px)                          3.18/5.41          2.63         597 / -0.258
  start and prior 589 ± 300 px                                3.09/4.99          2.53         605 / -0.268
  start and prior 653 ± 38 px (the true value)                1.64/2.75          1.53         662 / -0.338
  ``--camera`` the true camera (held)                         0.73/1.90          1.27         653 / -0.350
  true camera held + wrong pairs removed by the truth         0.60/1.31          0.97         653 / -0.350
  =========================================================  =================  ===========  ============

  Noise, seed 0, true camera held: no recess of the glass 0.68/1.47° 1.18 %; no fixed pattern 0.54/1.71° 0.94 %; no
  fixed pattern and no NETD 0.33/1.33° 0.54 % -- with the camera right, the sensor's noise and pattern are what is
  left.

  After the restart from the self-calibration (``pipeline.survey.camera_start.restart_camera``: the camera table's
  field of view through the self-calibrated distortion as the start of a second orientation and final adjustment,
  the first pass's matches kept), same command::

    seed0         50/50     [50]     100%        1.26/2.20             1.23 %     656 -0.339      89
    seed1         50/50     [50]     100%        1.24/2.50             1.36 %     643 -0.329     124
    seed2         50/50     [50]     100%        0.84/1.44             1.23 %     654 -0.344     122
    seed3         50/50     [50]     100%        1.47/2.86             1.60 %     661 -0.345      98

  seed 3 on main: 50/50, 1.11/2.20°, 1.68 %, f 616 px, k1 -0.306. The focal length is now within 10 px of the truth
  on the four seeds (37-58 px short before), the centres better or equal on all four, the rotations better on seeds
  0 and 2 and worse on 1 and 3 (mean RMS 2.22° -> 1.20°): the block still misses 0.5° and 1 %.

  Matching again in the restart (verification through the first pass's distortion) was worse on every seed:
  1.67/1.49/1.05° RMS, 1.68/1.88/1.48 % for seeds 0/1/2 (seed 3: 1.34°, 1.67 %); not kept.

  ``-- --refine-ties lsm`` with the restart: seed 0 2.32/4.08°, 1.91 %; seed 1 0.86/1.76°, 1.07 % (mixed).

  The sensor's fixed pattern estimated from the frames (``_fixed_pattern``, as the low-texture fallback does) and
  removed before the primary features (an in-process experiment, not kept): seed 0 4.79/24.96°, 8.58 % (one frame
  oriented 25° off inside the block), seed 2 47/50 in the block, 1.84/3.48°, 2.32 % -- worse.

  12 of the 321 verified pairs of seed 0 are wrong (matched one window period apart: transfer error through the
  true wall plane 340-1700 px; the shift lies along the epipolar lines of the sideways motion, so the essential
  matrix passes it). With the true camera the rotation errors are a smooth bend: pitch +0.9° on the lowest strip,
  -0.6° on the top one.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _survey(frames: Path, out: Path, extra) -> dict:
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "thermogrammetry", "survey", str(frames), "-o", str(out), "--workers", "0",
                        *extra], capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(REPO / "src")})
    wall = time.perf_counter() - t0
    if not (out / "survey.json").is_file():
        return {"error": (p.stderr or p.stdout)[-600:], "wall": wall, "code": p.returncode}
    return {"wall": wall, "code": p.returncode, "survey": json.loads((out / "survey.json").read_text()), "out": out}


def _reasons(sv: dict) -> list[str]:
    """Refusal reasons and notes worth reading in survey.json (blocks rejected, low-texture checks, warnings)."""
    out = []
    for b in sv.get("blocks", []) or []:
        if b.get("rejected"):
            out.append(f"block of {b.get('images', '?')} rejected: {str(b['rejected'])[:220]}")
    lt = sv.get("low_texture") or {}
    for c in lt.get("check", []) or []:
        if c.get("refused"):
            out.append(f"low-texture check refused: {str(c.get('reason', c))[:220]}")
    for w in (sv.get("warnings") or [])[:6]:
        out.append(f"warning: {str(w)[:220]}")
    return out


def _score(out: Path, truth: dict, dist: dict) -> dict:
    from survey_lowtexture import _block_errors  # the largest block against the truth, as for the walks

    e = _block_errors(out, truth)
    if not e.get("n"):
        return {"n": 0}
    if e["n"] >= 3:
        e["centre_rms_pct_dist"] = 100 * float(np.sqrt(np.mean(e["center_err_m"] ** 2))) / float(
            np.mean([dist[n] for n in e["names"]]))
    cam = json.loads((out / "cameras.json").read_text()).get("cameras") or {}
    e["camera"] = next(iter(cam.values())) if cam else None
    return e


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    extra = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--strips", type=int, default=5)
    ap.add_argument("--per-strip", type=int, default=10)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="FacadeFlightConfig overrides (numbers), e.g. --set brick_k=0.2 mortar_k=0.2")
    ap.add_argument("--keep", default=None, help="keep frames and survey outputs in this folder")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO / "src"))
    from thermogrammetry.pipeline.project import FolderProject
    from thermogrammetry.synthetic.facade_flight import FacadeFlightConfig, make_facade_flight, write_facade_flight

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_facade_flight_"))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    try:
        for seed in args.seed:
            tag = f"seed{seed}"
            over = {k: float(v) for k, v in (kv.split("=", 1) for kv in args.set)}
            tag = "_".join([tag] + [f"{k}{v:g}" for k, v in over.items()])
            sc = make_facade_flight(FacadeFlightConfig(seed=seed, n_strips=args.strips, n_per_strip=args.per_strip, **over))
            if not (work / tag / "frames").is_dir() or len(list((work / tag / "frames").glob("*.jpg"))) != len(sc.names):
                write_facade_flight(FolderProject(work / tag), sc)
            truth = {n: (p.R, p.t) for n, p in zip(sc.names, sc.poses)}
            dist = dict(zip(sc.names, sc.distances))
            out = work / tag / "out"
            shutil.rmtree(out, ignore_errors=True)
            run = _survey(work / tag / "frames", out, extra)
            if "error" in run:
                rows.append((tag, len(truth), None, run, [run["error"][-300:]]))
                continue
            rows.append((tag, len(truth), _score(out, truth, dist), run, _reasons(run["survey"])))
        print(f"\nSynthetic M2ED-like facade flights ({args.strips} x {args.per_strip} frames, 640x480 iron-palette JPEGs, "
              f"GNSS in EXIF), {os.cpu_count()} cores" + (f", extra survey args {extra}" if extra else ""))
        print(f"{'seed':<24}{'oriented':>9}{'blocks':>8}{'in block':>9}{'rot RMS/max deg':>17}{'centre RMS % dist':>19}"
              f"{'f px':>8}{'k1':>7}{'time s':>8}")
        for tag, n, e, run, why in rows:
            if e is None:
                print(f"{tag:<24}{'FAILED':>9}{'':>8}{'':>9}{'':>17}{'':>19}{'':>8}{'':>7}{run['wall']:>8.0f}")
            else:
                sv = run["survey"]
                if e.get("n", 0) >= 3:
                    rot = e["rot_err_deg"]
                    rs = f"{np.sqrt(np.mean(rot ** 2)):.2f}/{rot.max():.2f}"
                    cs = f"{e['centre_rms_pct_dist']:.2f} %"
                    share = f"{e['n'] / n:.0%}"
                    cam = e.get("camera") or {}
                    p = cam.get("params") or {}
                    fpx = f"{p.get('fx', float('nan')):.0f}" if isinstance(p, dict) else "-"
                    k1 = f"{p.get('k1', float('nan')):.3f}" if isinstance(p, dict) else "-"
                else:
                    rs = cs = fpx = k1 = "-"
                    share = "0%"
                print(f"{tag:<24}{sv['images_oriented']:>5}/{n:<3}{str(sv.get('components')):>8}{share:>9}{rs:>17}{cs:>19}"
                      f"{fpx:>8}{k1:>7}{run['wall']:>8.0f}")
            for w in why:
                print(f"    {w}")
        print("\nin block = share of the frames in the largest block; rot = angle between true and estimated rotation "
              "after the block's mean rotation; centre = RMS centre error after a similarity / mean distance to the wall. "
              "Truth: f 653.4 px, k1 -0.35, k2 0.06.")
        return 0
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    raise SystemExit(main())
