"""Benchmark: ``thermogrammetry survey`` against pycolmap's CPU pipeline, in the same run.

Part 1 (default): the shared DJI M3T flight (32 thermal R-JPEGs). Ours reads the raw 16-bit counts; pycolmap
reads the same files as any COLMAP user would (the 8-bit palette rendering DJI stores as the JPEG image),
with SIFT extraction, exhaustive matching and incremental mapping on the CPU. Both are scored the same way:
images registered, reprojection RMS = sqrt(mean |v|^2) over all observations of the final model (and
COLMAP's mean |v|), wall time. Ours also reports the camera centres against the RTK GNSS after the
adjustment (GNSS as priors). (A similarity-only fit of the incremental block to the RTK centres is no check of the
final geometry: that block still has the starting intrinsics, and is off by 0.9/0.1/2.1 m RMS.)

``--refine-ties lsm`` runs our survey with the least-squares tie-point refinement (``sfm/lsm.py``).

Part 2 (``--scale N``): the final bundle adjustment of a synthetic block of N frames (nadir grid, 80/60 %
overlap, tie points seen in 2-12 frames, GNSS priors), on our engine: time and peak memory.

Usage::

    python benchmarks/survey.py [--data ../shared/data] [--workers 2] [--no-colmap] [--refine-ties off|lsm]
    python benchmarks/survey.py --scale 2000

Exit status 2 when the data is absent (with the reason).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _colmap_child(img_dir: str, out: str) -> None:
    import pycolmap

    db = os.path.join(out, "db.db")
    t0 = time.perf_counter()
    pycolmap.extract_features(db, img_dir, camera_mode=pycolmap.CameraMode.SINGLE, device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
    maps = pycolmap.incremental_mapping(db, img_dir, out)
    dt = time.perf_counter() - t0
    best = max(maps.values(), key=lambda r: r.num_reg_images()) if maps else None
    res = {"seconds": dt, "models": len(maps), "registered": 0, "rms_px": None, "mean_px": None, "points": 0}
    if best is not None:
        errs = []
        for img in best.images.values():
            cam = best.cameras[img.camera_id]
            cfw = img.cam_from_world() if callable(img.cam_from_world) else img.cam_from_world
            for p2 in img.points2D:
                if not p2.has_point3D():
                    continue
                X = best.points3D[p2.point3D_id].xyz
                xy = cam.img_from_cam(cfw * X)
                errs.append(np.linalg.norm(np.asarray(xy).ravel()[:2] - np.asarray(p2.xy)))
        e = np.array(errs)
        res.update(registered=best.num_reg_images(), rms_px=float(np.sqrt(np.mean(e**2))), mean_px=float(e.mean()),
                   points=best.num_points3D(), f_px=[float(x) for x in best.cameras[next(iter(best.cameras))].params[:1]])
    print(json.dumps(res))


def run_colmap(img_dir: Path) -> dict:
    out = tempfile.mkdtemp(prefix="bench_colmap_")
    try:
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, __file__, "--colmap-child", str(img_dir), out], capture_output=True, text=True)
        wall = time.perf_counter() - t0
        line = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
        if p.returncode or not line:
            return {"error": (p.stderr or p.stdout)[-400:], "wall": wall}
        d = json.loads(line[-1])
        d["wall"] = wall
        return d
    finally:
        shutil.rmtree(out, ignore_errors=True)


def run_ours(img_dir: Path, workers: int, extra=()) -> dict:
    out = Path(tempfile.mkdtemp(prefix="bench_ours_")) / "out"
    try:
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "thermogrammetry", "survey", str(img_dir), "-o", str(out), "--workers", str(workers), *extra],
                           capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(REPO / "src")})
        wall = time.perf_counter() - t0
        if p.returncode:
            return {"error": p.stderr[-600:], "wall": wall}
        s = json.loads((out / "survey.json").read_text())
        cams = json.loads((out / "cameras.json").read_text())
        return {"wall": wall, "survey": s, "cameras": cams}
    finally:
        shutil.rmtree(out.parent, ignore_errors=True)


def _gnss_of(img_dir: Path, crs: str) -> dict:
    from pyproj import Transformer

    from thermogrammetry.io import read_thermal

    tf = Transformer.from_crs("EPSG:4979", crs, always_xy=True)
    out = {}
    for f in sorted(img_dir.glob("*.JPG")):
        g = read_thermal(f).metadata.geotag
        out[f.stem] = np.array(tf.transform(g.longitude_deg, g.latitude_deg, g.altitude_m))
    return out


def part1(args) -> int:
    data = Path(args.data or os.environ.get("THERMOGRAMMETRY_DATA") or REPO.parent / "shared" / "data")
    img_dir = data / "uav_m3t_flight" / "Test_image"
    if not img_dir.is_dir():
        print(f"data absent: {img_dir} (set --data or THERMOGRAMMETRY_DATA)", file=sys.stderr)
        return 2
    n = len(list(img_dir.glob("*.JPG")))
    ours = run_ours(img_dir, args.workers, ("--refine-ties", args.refine_ties))
    col = None if args.no_colmap else run_colmap(img_dir)
    print(f"\nDJI M3T flight, {n} frames 640x512 (shared/data/uav_m3t_flight), machine: {os.cpu_count()} cores")
    print(f"{'pipeline':<34}{'oriented':>10}{'RMS px':>9}{'mean px':>9}{'points':>9}{'time s':>9}")
    if "error" in ours:
        print(f"{'thermogrammetry survey':<34} FAILED: {ours['error']}")
        return 1
    s = ours["survey"]
    tie = None
    print(f"{'thermogrammetry survey (16-bit)':<34}{s['images_oriented']:>7}/{s['images_total']:<2}{s['reprojection_rms_px']:>9.3f}"
          f"{'':>9}{s['points']:>9}{ours['wall']:>9.1f}")
    if col is not None:
        if "error" in col:
            print(f"{'pycolmap (8-bit JPEG)':<34} FAILED: {col['error']}")
        else:
            print(f"{'pycolmap CPU (8-bit JPEG)':<34}{col['registered']:>7}/{n:<2}{col['rms_px'] or float('nan'):>9.3f}"
                  f"{col['mean_px'] or float('nan'):>9.3f}{col['points']:>9}{col['wall']:>9.1f}")
            print(f"time ours / pycolmap: {ours['wall'] / col['wall']:.2f}")
    # camera centres vs RTK GNSS
    g = _gnss_of(img_dir, s["crs"])
    C = {im["name"]: np.array(im["center"]) for im in ours["cameras"]["images"]}
    out_ = {f["image"]: f for f in s.get("gnss_flagged", []) if not f["used"]}
    D = np.array([C[k] - g[k] for k in C if k not in out_])
    print(f"centres - RTK GNSS after the adjustment (GNSS as priors, {len(D)} images): RMS X "
          f"{np.sqrt(np.mean(D[:, 0]**2)) * 100:.1f} Y {np.sqrt(np.mean(D[:, 1]**2)) * 100:.1f} "
          f"Z {np.sqrt(np.mean(D[:, 2]**2)) * 100:.1f} cm")
    for k, f in out_.items():
        print(f"  GNSS left out as a blunder: {k} (adjusted - GNSS {f['dx']:+.3f}, {f['dy']:+.3f}, {f['dz']:+.3f} m, "
              f"{f['sigma']:.0f} sigma)")
    print("steps (s): " + ", ".join(f"{st['name']} {st['seconds']:.1f}" for st in s["steps"]))
    cam = s["cameras"]["thermal"]
    print("camera: " + ", ".join(f"{k} {v:.4g} ± {cam['std'][k]:.2g}" for k, v in cam["params"].items() if cam["std"].get(k)))
    return 0


def part2(n_frames: int, seed: int = 0) -> int:
    """Final adjustment of an N-frame synthetic block on the engine: time and peak memory."""
    from thermogrammetry import Camera
    from thermogrammetry.adjustment import BundleProblem, SolverOptions, solve
    from thermogrammetry.geometry.rotations import matrix_from_axis_angle

    rng = np.random.default_rng(seed)
    cam = Camera("opencv", (640, 512), dict(fx=758.0, fy=758.0, cx=319.5, cy=255.5, k1=-0.1, k2=0.05))
    H = 75.0
    foot_x, foot_y = 640 / 758 * H, 512 / 758 * H
    step, line = 0.2 * foot_y, 0.4 * foot_x
    n_lines = int(np.ceil(np.sqrt(n_frames * step / line)))
    per = int(np.ceil(n_frames / n_lines))
    C = np.array([[li * line, k * step, H] for li in range(n_lines) for k in range(per)])[:n_frames]
    R0 = np.diag([1.0, -1.0, -1.0])
    Rs = np.array([matrix_from_axis_angle(rng.normal(0, 0.01, 3)) @ R0 for _ in C])
    # tie points: ~400 per frame area, on a gently rolling ground
    area = (C[:, 0].max() + foot_x) * (C[:, 1].max() + foot_y)
    n_pts = int(400 * n_frames * step * line / (foot_x * foot_y) * 2.5)
    P = np.column_stack([rng.uniform(-foot_x / 2, C[:, 0].max() + foot_x / 2, n_pts),
                         rng.uniform(-foot_y / 2, C[:, 1].max() + foot_y / 2, n_pts), rng.normal(0, 2.0, n_pts)])
    pb = BundleProblem()
    ci = pb.add_camera(cam, fixed=["skew", "k3", "k4", "k5", "k6"])
    t = -np.einsum("nij,nj->ni", Rs, C)
    noisy_R = [matrix_from_axis_angle(rng.normal(0, 2e-3, 3)) @ R for R in Rs]
    views = [pb.add_pose((noisy_R[k], -noisy_R[k] @ (C[k] + rng.normal(0, 0.2, 3)))) for k in range(len(C))]
    pidx = pb.add_points(P + rng.normal(0, 0.3, P.shape))
    from scipy.spatial import cKDTree

    tree = cKDTree(C[:, :2])
    n_obs = 0
    obs_by_view = [[] for _ in C]
    for k, nb in enumerate(tree.query_ball_point(P[:, :2], r=0.5 * np.hypot(foot_x, foot_y))):
        for v in nb:
            Xc = Rs[v] @ P[k] + t[v]
            xy = cam.project(Xc[None])[0]
            if 0 <= xy[0] < 640 and 0 <= xy[1] < 512:
                obs_by_view[v].append((k, xy + rng.normal(0, 0.3, 2)))
    keep = np.zeros(len(P), int)
    for v, obs in enumerate(obs_by_view):
        for k, _ in obs:
            keep[k] += 1
    for v, obs in enumerate(obs_by_view):
        obs = [(k, xy) for k, xy in obs if keep[k] >= 2]
        if obs:
            pb.add_image_points(ci, views[v], pidx[[k for k, _ in obs]], np.array([xy for _, xy in obs]), sigma_px=0.3)
            n_obs += len(obs)
    lonely = np.nonzero(keep < 2)[0]
    if len(lonely):
        pb.set_points_fixed(lonely)
    pb.add_gnss(np.arange(len(C)), C + rng.normal(0, 0.03, C.shape), 0.03)
    print(f"\nsynthetic block: {len(C)} frames, {int((keep >= 2).sum())} tie points, {n_obs} observations")
    t0 = time.perf_counter()
    res = solve(pb, SolverOptions(loss="huber", max_iterations=30, compute_covariance=False, compute_redundancy=False))
    dt = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    Ce = np.array([-p.R.T @ p.t for p in res.poses])
    print(f"{'frames':>8}{'observations':>14}{'iterations':>12}{'time s':>9}{'peak RSS MiB':>14}{'centre RMS m':>14}  termination")
    print(f"{len(C):>8}{n_obs:>14}{res.iterations:>12}{dt:>9.1f}{peak:>14.0f}{np.sqrt(np.mean((Ce - C) ** 2)):>14.4f}  {res.termination.value}")
    return 0 if res.success else 1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--no-colmap", action="store_true")
    ap.add_argument("--refine-ties", default="off", help="passed to our survey (off | lsm)")
    ap.add_argument("--scale", type=int, default=0, help="final-adjustment benchmark of a synthetic block of N frames")
    ap.add_argument("--colmap-child", nargs=2, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.colmap_child:
        _colmap_child(*a.colmap_child)
        return 0
    if a.scale:
        return part2(a.scale)
    return part1(a)


if __name__ == "__main__":
    sys.path.insert(0, str(REPO / "src"))
    sys.exit(main())
