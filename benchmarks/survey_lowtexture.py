"""Benchmark: low-texture thermal frames of a real wall, judged against the synchronised RGB frames.

Data: ``shared/data/rgb_thermal_frescoes`` (Thermitage, Arco Castle): 40 captures of frescoed walls by a
hand-held Workswell WIRIS Pro, 16-bit radiometric TIFF thermal frames (640x512, EXIF focal 13 mm / 17 um)
and 1920x1080 RGB frames from the same housing at the same instant. There is no reference geometry in the
data, so the RGB frames (rich texture) are oriented first by ``thermogrammetry survey`` and serve as the
reference: the thermal camera sits in the same housing, so the relative motion between two captures is the
same rigid motion for both sensors up to the unknown rig rotation R* (a degree or two) and the rig's few-cm
base.

Thermal runs: ``--low-texture off``, ``--low-texture auto`` (the default) and ``--detector asift`` (SIFT on simulated
tilted views). Checks, per thermal run:

- images oriented, components, and the verified thermal pairs;
- each verified pair against the RGB relative pose: median epipolar distance (px) of its matches under the
  essential matrix of the RGB motion with the thermal camera's EXIF focal (no distortion modelled). A right
  pair lands within a few px (R* and the rig base leave ~2-5 px); a pair matched on the wrong structure sits
  at 20-150 px (shuffled matches: ~140 px);
- oriented thermal frames: angle between the thermal and RGB relative rotations of every pair of frames in
  one block (R* cancels to first order);
- the RGB + thermal rig run (``--rgb VisJPG --rig rig.json`` with ``estimate: true``): thermal frames oriented through
  R*, t registered on the edges both bands see (``sfm.rigreg``), the registration's figures, and the RMS of the
  thermal frames' own tie points under it.

pycolmap (SIFT, exhaustive matching, incremental mapping on the CPU) gets the same thermal frames as 8-bit
PNGs stretched per frame between the 0.5 and 99.5 percentiles (what a user would feed it; COLMAP reduces
16-bit TIFFs to their high byte, a flat image).

``--scene wall320``: the same wall at 320x256 px (34 um pitch, same footprint per pixel) 2 m away, 20 frames: no ground
in view, a single plane. ``--scene facade [--stations 14]``: ``synthetic.facade`` (15 windows whose glass reflects the
sky, 320x240, no EXIF focal length) -- the guard's cases: a wrong block must not come out.

``--synthetic``: the synthetic low-texture facade walk instead (``thermogrammetry.synthetic.lowtexture_facade``: a
plain wall with a smooth thermal field of ``--contrast`` K, 0.08 K fixed pattern, 0.04 K NETD, 30 float32-K frames
640x512 at 80 % forward overlap, hand-held jitter, EXIF focal length, no GNSS), with exact truth: our survey with
``--low-texture off`` and ``auto`` and pycolmap on the same frames (8-bit PNG, per-frame percentile stretch), in the same
run; share of the frames in the largest block and its poses against the truth after a similarity (rotation error,
centre error relative to the block's length). ``--seed`` and ``--contrast`` take several values.

Usage::

    python benchmarks/survey_lowtexture.py [--data ../shared/data] [--no-colmap] [--keep DIR]
    python benchmarks/survey_lowtexture.py --synthetic [--seed 0 1] [--contrast 0.15 0.25] [--no-colmap]
    python benchmarks/survey_lowtexture.py --synthetic --scene wall320|facade [--stations 14] --no-colmap
    python benchmarks/survey_lowtexture.py --synthetic [--gnss-sigma 0.03] [--render8 grey|palette] --no-colmap

Exit status 2 when the data is absent.
"""

from __future__ import annotations

import argparse
import importlib.util
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


def _survey(images: Path, out: Path, *extra, gnss: tuple = ("--gnss", "none")) -> dict:
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "thermogrammetry", "survey", str(images), "-o", str(out), "--workers", "0",
                        *gnss, *extra], capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(REPO / "src")})
    wall = time.perf_counter() - t0
    if not (out / "survey.json").is_file():
        return {"error": (p.stderr or p.stdout)[-600:], "wall": wall, "code": p.returncode}
    return {"wall": wall, "code": p.returncode, "survey": json.loads((out / "survey.json").read_text()), "out": out}


def _gnss_csv(scene, path: Path, sigma_m: float) -> Path:
    """A GNSS CSV of the true centres + seeded N(0, sigma) noise (vertical 1.5 sigma), in EPSG:2056 coordinates."""
    rng = np.random.default_rng(1)
    rows = ["image,X,Y,Z,sX,sY,sZ"]
    for name, p in zip(scene.names, scene.poses):
        c = p.center + rng.normal(0.0, sigma_m, 3) * [1.0, 1.0, 1.5] + [2600000.0, 1200000.0, 400.0]
        rows.append(f"{name},{c[0]:.4f},{c[1]:.4f},{c[2]:.4f},{sigma_m:g},{sigma_m:g},{1.5 * sigma_m:g}")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(rows) + "\n")
    return path


def _render8(frames: Path, dst: Path, mode: str, overlay: bool = False) -> Path:
    """The frames as 8-bit JPEGs (quality 92) with a per-frame 1-99 % stretch (an AGC), grey or through matplotlib's
    'inferno' palette, without EXIF (no focal length): what a camera's exported JPEGs give. ``overlay``: the camera's
    display burned in (:func:`thermogrammetry.synthetic.display.burn_display`)."""
    import tifffile
    from PIL import Image

    from thermogrammetry.synthetic.display import render_8bit

    dst.mkdir(parents=True, exist_ok=True)
    for p in sorted(frames.glob("*.tif")):
        img = render_8bit(tifffile.imread(p), mode=mode, display=overlay)
        Image.fromarray(img).save(dst / (p.stem + ".jpg"), quality=92)
    return dst


def _write_video(scene, path: Path, render8: str | None, overlay: bool) -> Path:
    """Every frame of ``scene`` as a 25 fps video: lossless 16-bit kelvin (``synthetic``'s FFV1 with the
    THERMOGRAMMETRY_* mapping) or, with ``render8``, 8-bit grey frames (per-frame stretch; ``overlay``: the display
    burned in), a screen recording. No focal length travels with a video."""
    import av

    from thermogrammetry.synthetic.display import render_8bit
    from thermogrammetry.synthetic.lowtexture_facade import render_lowtexture_frame
    from thermogrammetry.synthetic.survey import _VideoWriter

    path.parent.mkdir(parents=True, exist_ok=True)
    w, h = scene.camera.image_size
    if render8 is None:
        wr = _VideoWriter(25.0)
        for k in range(len(scene.poses)):
            wr.add(render_lowtexture_frame(scene, k), k / 25.0)
        path.write_bytes(wr.finish())
        return path
    with av.open(str(path), mode="w", format="matroska") as c:
        st = c.add_stream("ffv1", rate=25)
        st.width, st.height, st.pix_fmt = w, h, ("gray" if render8 == "grey" else "rgb24")
        for k in range(len(scene.poses)):
            img = render_8bit(render_lowtexture_frame(scene, k), mode=render8, display=overlay)
            fr = av.VideoFrame.from_ndarray(img, format="gray" if img.ndim == 2 else "rgb24")
            fr.pts = k
            c.mux(st.encode(fr))
        c.mux(st.encode())
    return path


def _poses(out: Path, suffix: str) -> dict:
    """stem (without the sensor suffix) -> (R, t) cam_from_world of the oriented images."""
    cams = json.loads((out / "cameras.json").read_text())
    return {im["name"].replace(suffix, ""): (np.array(im["cam_from_world"]["R"]), np.array(im["cam_from_world"]["t"]))
            for im in cams["images"]}


def _angle_deg(R) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def _epipolar_px(K, Ri, ti, Rj, tj, xi, xj) -> np.ndarray:
    R = Rj @ Ri.T
    t = tj - R @ ti
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Ki = np.linalg.inv(K)
    F = Ki.T @ tx @ R @ Ki
    a = np.c_[xi, np.ones(len(xi))]
    b = np.c_[xj, np.ones(len(xj))]
    line = a @ F.T
    return np.abs(np.sum(line * b, axis=1)) / np.hypot(line[:, 0], line[:, 1])


def evaluate(run: dict, ref: dict, suffix: str = "-radiometric") -> dict:
    out = run["out"]
    inputs = json.loads((out / "work" / "inputs.json").read_text())["images"]
    names = [im["name"] for im in inputs]
    guess = inputs[0].get("camera_guess") or {}
    f = float(guess.get("f_px", 765.0))
    K = np.array([[f, 0, inputs[0]["width"] / 2 - 0.5], [0, f, inputs[0]["height"] / 2 - 0.5], [0, 0, 1.0]])
    pairs = json.loads((out / "work" / "pairs.json").read_text())["pairs"]
    checked = []
    for i, j, _, nv, reason in pairs:
        if reason:
            continue
        si, sj = names[i].replace(suffix, ""), names[j].replace(suffix, "")
        if si not in ref or sj not in ref:
            continue
        fi = np.load(out / "features" / f"{names[i]}.npz")
        fj = np.load(out / "features" / f"{names[j]}.npz")
        idx = np.load(out / "matches" / f"{i}_{j}.npz")["idx"]
        e = _epipolar_px(K, *ref[si], *ref[sj], fi["xy"][idx[:, 0]], fj["xy"][idx[:, 1]])
        checked.append((names[i], names[j], int(nv), float(np.median(e))))
    rot = []
    if (out / "cameras.json").is_file():
        th = _poses(out, suffix)
        comp = {im["name"].replace(suffix, ""): im.get("block") for im in run["survey"].get("images", [])}
        keys = sorted(k for k in th if k in ref)
        for a in range(len(keys)):
            for b in range(a + 1, len(keys)):
                ka, kb = keys[a], keys[b]
                if comp.get(ka) != comp.get(kb):
                    continue
                Rt = th[kb][0] @ th[ka][0].T
                Rr = ref[kb][0] @ ref[ka][0].T
                rot.append(_angle_deg(Rt @ Rr.T))
    return {"verified_pairs": len(checked), "consistent_pairs": sum(1 for c in checked if c[3] < 5.0),
            "pairs": checked, "rotation_error_deg": rot}


def _colmap(frames_dir: Path) -> dict:
    spec = importlib.util.spec_from_file_location("bench_survey", REPO / "benchmarks" / "survey.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    import cv2
    import tifffile

    tmp = Path(tempfile.mkdtemp(prefix="bench_lt_png_"))
    try:
        for fpath in sorted(frames_dir.glob("*.tif*")):
            a = tifffile.imread(fpath).astype(np.float32)
            lo, hi = np.percentile(a, [0.5, 99.5])
            cv2.imwrite(str(tmp / (fpath.stem + ".png")), np.clip((a - lo) * 255.0 / max(hi - lo, 1e-6), 0, 255).astype(np.uint8))
        return mod.run_colmap(tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _block_errors(out: Path, truth: dict) -> dict:
    """Largest oriented block of a survey against the truth (pose_errors)."""
    from thermogrammetry.synthetic.lowtexture_facade import pose_errors

    s = json.loads((out / "survey.json").read_text())
    if not (out / "cameras.json").is_file() or not s.get("images_oriented"):
        return {"n": 0}
    block = {im["name"]: im.get("block") for im in s.get("images", [])}
    est: dict = {}
    for im in json.loads((out / "cameras.json").read_text())["images"]:
        est.setdefault(block.get(im["name"]), {})[im["name"]] = (np.array(im["cam_from_world"]["R"]),
                                                                 np.array(im["cam_from_world"]["t"]))
    best = max(est.values(), key=len)
    return pose_errors(truth, best)


def synthetic(args) -> int:
    from thermogrammetry.pipeline.project import FolderProject
    from thermogrammetry.synthetic.lowtexture_facade import (LowTextureFacadeConfig, make_lowtexture_facade,
                                                             write_lowtexture_facade)

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_lowtexture_syn_"))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    try:
        for seed in args.seed:
            for contrast in args.contrast:
                gnss = ("--gnss", "none")
                if args.scene == "facade":
                    from thermogrammetry.synthetic.facade import FacadeConfig, make_facade, write_facade

                    tag = f"facade{args.stations}_seed{seed}"
                    fsc = make_facade(FacadeConfig(n_stations=args.stations, seed=seed))
                    write_facade(FolderProject(work / tag), fsc)
                    truth = {name: (pt.R, pt.t) for name, _, pt in fsc.stations}
                    frames = work / tag / "facade" / "thermal"
                else:
                    extra = (dict(image_size=(320, 256), pixel_pitch_um=34.0, distance_m=2.0, n_frames=20)
                             if args.scene == "wall320" else {})
                    tag = f"{'wall320_' if extra else ''}seed{seed}_c{contrast:g}"
                    if args.video:
                        # a walk filmed at 25 fps: 1/40 of the frame width a frame, 30 frames' worth at 80 % overlap
                        sc = make_lowtexture_facade(LowTextureFacadeConfig(seed=seed, contrast_k=contrast, n_frames=250,
                                                                           overlap=0.975, jitter_deg=0.3, supersample=1,
                                                                           **extra))
                        tag += "_video" + (f"8{args.render8[0]}{'_hud' if args.overlay else ''}" if args.render8 else "K")
                        frames = _write_video(sc, work / tag / "walk.mkv", args.render8, args.overlay)
                        sc.camera.save(work / tag / "camera.json")
                        truth = {f"walk_f{k:06d}": (p.R, p.t) for k, p in enumerate(sc.poses)}
                        n = None
                        for label, more in (("ours, no camera file", ()),
                                            ("ours, --camera (true)", ("--camera", str(work / tag / "camera.json")))):
                            run = _survey(frames, work / tag / f"out_{len(more)}", *more, gnss=gnss)
                            if "error" in run:
                                rows.append((tag, label, 0, None, run["wall"], run["error"][-120:]))
                                continue
                            sv = run["survey"]
                            rows.append((tag, label, sv["images_total"], (sv["images_oriented"], sv["components"],
                                                                          _block_errors(run["out"], truth)),
                                         run["wall"], f"exit {run['code']}; frames extracted from {len(sc.poses)}"))
                        continue
                    sc = make_lowtexture_facade(LowTextureFacadeConfig(seed=seed, contrast_k=contrast, **extra))
                    write_lowtexture_facade(FolderProject(work / tag), sc)
                    truth = {n: (p.R, p.t) for n, p in zip(sc.names, sc.poses)}
                    frames = work / tag / "frames"
                    if args.render8:
                        hud = "_hud" if args.overlay else ""
                        frames = _render8(frames, work / tag / f"frames8_{args.render8}{hud}", args.render8,
                                          overlay=args.overlay)
                        tag += f"_8bit{args.render8[0]}{hud}"
                    if args.gnss_sigma is not None:
                        gnss = ("--gnss", str(_gnss_csv(sc, work / tag / "gnss.csv", args.gnss_sigma)), "--crs", "EPSG:2056")
                        tag += f"_gnss{args.gnss_sigma:g}"
                n = len(truth)
                for mode in ("off", "auto"):
                    run = _survey(frames, work / tag / f"out_{mode}", "--low-texture", mode, gnss=gnss)
                    if "error" in run:
                        rows.append((tag, f"ours --low-texture {mode}", n, None, run["wall"], run["error"][-120:]))
                        continue
                    sv = run["survey"]
                    e = _block_errors(run["out"], truth)
                    lt = sv.get("low_texture") or {}
                    chk = "; ".join(f"check: ratio {c['ratio']:.2f} planar {c['planar_share']:.2f}"
                                    + (" REFUSED" if c["refused"] else "") for c in lt.get("check", [])
                                    if c.get("ratio") is not None and c.get("planar_share") is not None)
                    rows.append((tag, f"ours --low-texture {mode}", n, (sv["images_oriented"], sv["components"], e), run["wall"],
                                 f"exit {run['code']}" + (f"; {chk}" if chk else "")))
                if not args.no_colmap:
                    col = _colmap(frames)
                    if "error" in col:
                        rows.append((tag, "pycolmap CPU (8-bit PNG)", n, None, col["wall"], col["error"][-120:]))
                    else:
                        rows.append((tag, "pycolmap CPU (8-bit PNG)", n, (col["registered"], f"{col['models']} model(s)", None),
                                     col["wall"], ""))
        what = {"walk": "plain wall, 30 frames 640x512, 0.08 K pattern, 0.04 K NETD",
                "wall320": "plain wall without ground, 20 frames 320x256 (34 um), 2 m, 0.08 K pattern, 0.04 K NETD",
                "facade": f"synthetic.facade, {args.stations} stations 320x240, windows reflecting the sky, no EXIF focal"}
        if args.video and args.scene != "facade":
            what[args.scene] += ("; filmed as a 25 fps video of 250 frames, 1/40 of the frame width apart, "
                                 + (f"8-bit {args.render8}" + (" with the display" if args.overlay else "") if args.render8
                                    else "16-bit kelvin"))
        print(f"\nSynthetic low-texture scene ({what[args.scene]}), {os.cpu_count()} cores")
        print(f"{'scene':<20}{'run':<28}{'oriented':>9}{'blocks':>12}{'in block':>9}{'rot RMS/max deg':>17}"
              f"{'centre RMS/len':>15}{'time s':>8}  note")
        for tag, label, n, r, wall, note in rows:
            if r is None:
                print(f"{tag:<20}{label:<28}{'FAILED':>9}{'':>12}{'':>9}{'':>17}{'':>15}{wall:>8.0f}  {note}")
                continue
            oriented, comps, e = r
            if e and e.get("n", 0) >= 3:
                rot = e["rot_err_deg"]
                share = f"{e['n'] / n:.0%}"
                rs = f"{np.sqrt(np.mean(rot ** 2)):.2f}/{rot.max():.2f}"
                cs = f"{100 * e['center_rms_rel']:.2f} %"
            else:
                share, rs, cs = ("0%" if not oriented else "-"), "-", "-"
            print(f"{tag:<20}{label:<28}{oriented:>6}/{n:<2}{str(comps):>12}{share:>9}{rs:>17}{cs:>15}{wall:>8.0f}  {note}")
        print("\nin block = share of the frames in the largest block; rot = angle between true and estimated rotation "
              "after the block's mean rotation; centre = RMS centre error after a similarity / largest distance "
              "between the block's true centres.")
        return 0
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


def _rig_rows(rig: dict, ref: dict) -> None:
    """The RGB + thermal rig run (``--rgb VisJPG --rig rig.json``, ``estimate: true``): R*, t by image registration."""
    label = "RGB + thermal rig, R* registered"
    if "error" in rig:
        print(f"{label:<38} FAILED: {rig['error'][:200]}")
        return
    sv = rig["survey"]
    th = [im for im in sv["images"] if im.get("sensor") == "thermal"]
    n_th = sum(bool(im["oriented"]) for im in th)
    print(f"{label:<38}{n_th:>6}/{len(th):<2}{str(sv['components']):>14}{'':>10}{'':>11}{'':>17}{rig['code']:>6}"
          f"{rig['wall']:>8.0f}")
    from thermogrammetry.sfm.rig import t_with_sigma_text

    reg = sv.get("rig", {}).get("registration")
    if not reg:
        print("    (no registration: the rig was estimated from tie points or not at all)")
        return
    if not reg["success"]:
        print(f"    registration refused: {reg['reason']}")
        return
    ang = float(np.degrees(np.arccos(np.clip((np.trace(np.array(reg["R"])) - 1) / 2, -1, 1))))
    print(f"    registration: {reg['pairs_used']}/{reg['pairs']} pairs agree, R* {ang:.2f} deg, σ "
          f"{', '.join(f'{x:.3f}' for x in reg['rotation_std_deg'])} deg, spread {reg['spread_deg']:.2f} deg, "
          + (f"t {t_with_sigma_text(reg['t'], reg['translation_std'])} model units"
             if reg.get("t_determined") else f"t {np.round(reg['t'], 3).tolist()} held (pairs at one depth)")
          + f", thermal focal x {reg['focal_scale']:.4f}, "
          f"median NCC {reg['ncc_median']:.3f}, {reg['seconds']:.0f} s")
    own = [(im["name"], im["tie_points"], im["rms_px"]) for im in th if im.get("tie_points")]
    if own:
        print("    thermal frames with tie points of their own under the registered rig (RMS px): "
              + ", ".join(f"{n[:12]} {k} pts {r:.2f}" for n, k, r in own))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--no-colmap", action="store_true")
    ap.add_argument("--keep", default=None, help="keep the survey outputs in this folder")
    ap.add_argument("--synthetic", action="store_true", help="the synthetic low-texture facade walk (exact truth)")
    ap.add_argument("--seed", type=int, nargs="+", default=[0])
    ap.add_argument("--contrast", type=float, nargs="+", default=[0.15], help="K, standard deviation of the wall's field")
    ap.add_argument("--scene", choices=("walk", "wall320", "facade"), default="walk",
                    help="--synthetic scene: walk (640x512, 4 m, ground in view), wall320 (320x256, 34 um, 2 m, 20 frames, "
                         "a single plane), facade (synthetic.facade: windows reflecting the sky, no EXIF focal length)")
    ap.add_argument("--stations", type=int, default=14, help="--scene facade: stations")
    ap.add_argument("--gnss-sigma", type=float, default=None, metavar="M",
                    help="--scene walk|wall320: give the survey GNSS (true centres + N(0, M) noise, EPSG:2056)")
    ap.add_argument("--render8", choices=("grey", "palette"), default=None,
                    help="--scene walk|wall320: the frames as 8-bit JPEGs (per-frame stretch, no EXIF focal length)")
    ap.add_argument("--overlay", action="store_true",
                    help="with --render8: a hand-held camera's display burned in (text, cross-hair, colour bar)")
    ap.add_argument("--video", action="store_true",
                    help="--scene walk|wall320: the walk filmed as a 25 fps video (250 frames, kelvin, or 8-bit with "
                         "--render8 [--overlay]); survey extracts frames at 80 %% overlap, without and with the true "
                         "camera file")
    args = ap.parse_args(argv)
    if args.synthetic:
        sys.path.insert(0, str(REPO / "src"))
        return synthetic(args)
    data = Path(args.data or os.environ.get("THERMOGRAMMETRY_DATA") or REPO.parent / "shared" / "data")
    base = data / "rgb_thermal_frescoes"
    if not (base / "RadTIFF").is_dir():
        print(f"data absent: {base} (set --data or THERMOGRAMMETRY_DATA)", file=sys.stderr)
        return 2
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_lowtexture_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        rgb = _survey(base / "VisJPG", work / "rgb")
        if "error" in rgb:
            print(f"RGB reference failed: {rgb['error']}")
            return 1
        ref = _poses(work / "rgb", "-visible")
        rows = []
        for label, key, extra in (("thermogrammetry, --low-texture off", "off", ("--low-texture", "off")),
                                  ("thermogrammetry, --low-texture auto", "auto", ("--low-texture", "auto")),
                                  ("thermogrammetry, --detector asift", "asift", ("--detector", "asift"))):
            run = _survey(base / "RadTIFF", work / f"thermal_{key}", *extra)
            rows.append((label, None if "error" in run else evaluate(run, ref), run))
        rig_json = work / "rig.json"
        rig_json.write_text(json.dumps({"format": "thermogrammetry/rig", "estimate": True,
                                        "pairing": {"rgb_suffix": "-visible", "thermal_suffix": "-radiometric"}}))
        rig = _survey(base / "RadTIFF", work / "rig", "--rgb", str(base / "VisJPG"), "--rig", str(rig_json))
        col = None if args.no_colmap else _colmap(base / "RadTIFF")
        s = rgb["survey"]
        n = 40
        print(f"\nThermitage fresco walls, {n} hand-held Workswell frames (16-bit thermal 640x512 + RGB 1920x1080), "
              f"{os.cpu_count()} cores")
        print(f"RGB reference (thermogrammetry survey on the RGB frames): {s['images_oriented']}/{s['images_total']} "
              f"oriented, components {s['components']}, RMS {s['reprojection_rms_px']:.3f} px, {rgb['wall']:.0f} s\n")
        print(f"{'thermal run':<38}{'oriented':>9}{'blocks':>14}{'verified':>10}{'consistent':>11}{'rot err med/max':>17}"
              f"{'exit':>6}{'time s':>8}")
        for label, ev, run in rows:
            if ev is None:
                print(f"{label:<38} FAILED: {run['error'][:200]}")
                continue
            sv = run["survey"]
            rot = ev["rotation_error_deg"]
            rs = f"{np.median(rot):.1f}/{np.max(rot):.1f}" if rot else "-"
            print(f"{label:<38}{sv['images_oriented']:>6}/{sv['images_total']:<2}{str(sv['components']):>14}"
                  f"{ev['verified_pairs']:>10}{ev['consistent_pairs']:>11}{rs:>17}{run['code']:>6}{run['wall']:>8.0f}")
            for b in sv.get("blocks", []):
                if b.get("rejected"):
                    print(f"    rejected: {b['rejected'][:160]}")
        if col is not None:
            if "error" in col:
                print(f"{'pycolmap CPU (8-bit PNG)':<38} FAILED: {col['error'][-200:]}")
            else:
                print(f"{'pycolmap CPU (8-bit PNG)':<38}{col['registered']:>6}/{n:<2}{str(col['models']) + ' model(s)':>14}"
                      f"{'':>10}{'':>11}{'':>17}{'':>6}{col['wall']:>8.0f}")
        _rig_rows(rig, ref)
        print("\nverified = thermal pairs that passed our geometric verification; consistent = their median epipolar "
              "distance under the RGB motion < 5 px;\nrot err = angle between thermal and RGB relative rotations of "
              "the oriented thermal frames (same block).")
        for label, ev, run in rows:
            if ev and ev["pairs"]:
                print(f"\n{label}: verified pairs, median epipolar distance under the RGB motion (px)")
                print("  " + ", ".join(f"{a[:8]}-{b[:8]} {e:.1f}" for a, b, _, e in ev["pairs"]))
        return 0
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--colmap-child":
        raise SystemExit("run benchmarks/survey.py --colmap-child instead")
    raise SystemExit(main())
