"""Benchmark: self-calibration vs cv2.calibrateCamera on the real thermal chessboard (same detections).

Data: ../shared/data/thermal_chessboard (47 views of a heated 6x5-inner-corner chessboard, 100 mm
squares, 640x480 thermal camera; masked and unmasked variants; 15 thermal/RGB pairs with 30
measured corners each). Run from the repository root::

    /work/venv/bin/python benchmarks/calibrate_chessboard.py [--data ../shared/data/thermal_chessboard]

Prints, for each image set, the number of views with corners (thermogrammetry's detector and
OpenCV's plain detector), then the RMS reprojection error sqrt(mean(vx²+vy²)) of

* ours: correction-form self-calibration, c x0 y0 K1 K2 K3 P1 P2 (8 intrinsics, square pixels),
  on all detections (no blunder removal) and after data snooping;
* OpenCV: cv2.calibrateCamera with the same number of intrinsics (CALIB_FIX_ASPECT_RATIO, fx = fy;
  k1 k2 p1 p2 k3) on exactly the same observations;
* the same with a free aspect ratio (ours + B1 affinity vs OpenCV with fx, fy free);
* ours in OpenCV's own (forward) model, ``calibrate --model opencv``: fx fy cx cy k1 k2 p1 p2 k3 against
  cv2.calibrateCamera with flags = 0, and both with k3 held (``fixed=("k3",)`` / CALIB_FIX_K3);

and the relative orientation of the thermal + RGB pair from the 15 measured pairs (rig adjustment).
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import cv2
import numpy as np

from thermogrammetry.calibration.detect_chessboard import detect_chessboard
from thermogrammetry.calibration.detect_common import ChessboardSpec, normalize_to_u8, to_gray_float
from thermogrammetry.calibration.selfcal import CameraSetup, ImageMeasurements, SelfCalibrationOptions, calibrate

SPEC = ChessboardSpec(6, 5, 100.0, corner0_square="any")
PITCH_UM = 17.0  # assumed (not published); results in px do not depend on it


def plain_opencv(img) -> bool:
    u8 = normalize_to_u8(to_gray_float(img))
    ok, _ = cv2.findChessboardCorners(u8, SPEC.pattern_size)
    return bool(ok)


def ours(dets, size, *, snooping, affinity=False, keep=None, model="photogrammetric", fixed=()):
    obj = SPEC.object_points() * 1e-3
    ims = []
    for k, d in enumerate(dets):
        ids = np.asarray(d.object_ids)
        xy = np.asarray(d.points_px, float)
        if keep is not None:
            m = keep[k]
            ids, xy = ids[m], xy[m]
        ims.append(ImageMeasurements(d.image_id, 0, ids, xy))
    opt = SelfCalibrationOptions(snooping=snooping, affinity=affinity, model=model, fixed=fixed)
    t0 = time.perf_counter()
    r = calibrate([CameraSetup("thermal", size, PITCH_UM)], obj, ims, options=opt)
    return r, time.perf_counter() - t0


def opencv(dets, size, *, fix_aspect, keep=None, extra_flags=0):
    obj = (SPEC.object_points()).astype(np.float32) * 1e-3
    op, ip = [], []
    for k, d in enumerate(dets):
        m = np.ones(len(d.object_ids), bool) if keep is None else keep[k]
        op.append(obj[np.asarray(d.object_ids)[m]])
        ip.append(np.asarray(d.points_px, np.float32)[m].reshape(-1, 1, 2))
    flags = (cv2.CALIB_FIX_ASPECT_RATIO if fix_aspect else 0) | extra_flags
    K0 = cv2.initCameraMatrix2D(op, ip, size, 1.0)
    if fix_aspect:
        f = 0.5 * (K0[0, 0] + K0[1, 1])
        K0[0, 0] = K0[1, 1] = f
    t0 = time.perf_counter()
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, rv, tv = cv2.calibrateCamera(op, ip, size, K0.copy(), None, flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS,
                                               criteria=crit)
    dt = time.perf_counter() - t0
    # its estimate's RMS on the points ours takes (float64 board and image points; cv2 fits their float32 rounding)
    obj64 = SPEC.object_points() * 1e-3
    err = []
    for k, (d, a, b) in enumerate(zip(dets, rv, tv)):
        m = np.ones(len(d.object_ids), bool) if keep is None else keep[k]
        err.append(cv2.projectPoints(obj64[np.asarray(d.object_ids)[m]], a, b, K, dist)[0].reshape(-1, 2)
                   - np.asarray(d.points_px, float)[m])
    err = np.concatenate(err)
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1)))), K, dist.ravel(), dt


def keep_mask(dets, result):
    blunder = {(b["image"], b["point"]) for b in result.blunders}
    return [np.array([(d.image_id, int(i)) not in blunder for i in d.object_ids]) for d in dets]


def run_set(folder: Path, label: str) -> list:
    files = sorted(folder.glob("*.jpg"))
    dets, n_plain = [], 0
    t0 = time.perf_counter()
    size = None
    for f in files:
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        size = (img.shape[1], img.shape[0])
        dets.append(detect_chessboard(img, SPEC, f.name))
        n_plain += plain_opencv(img)
    t_det = time.perf_counter() - t0
    found = [d for d in dets if d.found]
    print(f"\n== {label}: {folder}")
    print(f"views with corners: thermogrammetry {len(found)}/{len(files)}  |  plain cv2.findChessboardCorners {n_plain}/{len(files)}"
          f"  (detection {t_det:.1f} s)")
    if len(found) < 3:
        return found
    rows = []
    r_all, t_all = ours(found, size, snooping=False)
    rms_cv, K, dist, t_cv = opencv(found, size, fix_aspect=True)
    rows.append(("all detections, 8 intrinsics (fx=fy)", r_all.rms_px, t_all, rms_cv, t_cv, sum(d.n_points for d in found)))
    r_sn, t_sn = ours(found, size, snooping=True)
    keep = keep_mask(found, r_sn)
    rms_cv2, _, _, t_cv2 = opencv(found, size, fix_aspect=True, keep=keep)
    rows.append(("after our data snooping (same obs both)", r_sn.rms_px, t_sn, rms_cv2, t_cv2, int(sum(k.sum() for k in keep))))
    r_b1, t_b1 = ours(found, size, snooping=False, affinity=True)
    rms_cv3, K3, d3, t_cv3 = opencv(found, size, fix_aspect=False)
    rows.append(("all detections, + affinity / fx,fy free", r_b1.rms_px, t_b1, rms_cv3, t_cv3, sum(d.n_points for d in found)))
    r_o, t_o = ours(found, size, snooping=False, model="opencv")
    rows.append(("opencv model, all detections, flags=0", r_o.rms_px, t_o, rms_cv3, t_cv3, sum(d.n_points for d in found)))
    r_o3, t_o3 = ours(found, size, snooping=False, model="opencv", fixed=("k3",))
    rms_cv4, K4, d4, t_cv4 = opencv(found, size, fix_aspect=False, extra_flags=cv2.CALIB_FIX_K3)
    rows.append(("opencv model, k3 held (CALIB_FIX_K3)", r_o3.rms_px, t_o3, rms_cv4, t_cv4, sum(d.n_points for d in found)))
    r_os, t_os = ours(found, size, snooping=True, model="opencv")
    keep_o = keep_mask(found, r_os)
    rms_cv5, K5, d5, t_cv5 = opencv(found, size, fix_aspect=False, keep=keep_o)
    rows.append(("opencv model, after our data snooping", r_os.rms_px, t_os, rms_cv5, t_cv5, int(sum(k.sum() for k in keep_o))))
    cmp_o = [("flags=0", r_o, K3, d3), ("CALIB_FIX_K3", r_o3, K4, d4), ("after snooping", r_os, K5, d5)]
    print("(cv2's RMS: its estimate evaluated on the float64 points ours takes; cv2 fits their float32 rounding)")
    print(f"{'case':42s} {'points':>6s} {'ours RMS px':>14s} {'ours s':>7s} {'cv2 RMS px':>14s} {'cv2 s':>6s}  verdict")
    for name, a, ta, b, tb, n in rows:
        verdict = "ours <= cv2" if a <= b + 1e-9 else f"ours WORSE by {a - b:.2g} px"
        print(f"{name:42s} {n:6d} {a:14.10f} {ta:7.2f} {b:14.10f} {tb:6.2f}  {verdict}")
    for name, r, Ko, do in cmp_o:
        c = r.cameras[0]
        cv = dict(fx=Ko[0, 0], fy=Ko[1, 1], cx=Ko[0, 2], cy=Ko[1, 2], k1=do[0], k2=do[1], p1=do[2], p2=do[3], k3=do[4])
        z = max(abs(c.param_dict[k] - v) / c.std_dict[k] for k, v in cv.items() if c.free[c.param_names.index(k)])
        print(f"opencv model, {name}: max |ours - cv2| / σ over the estimated parameters {z:.1e}; "
              + ", ".join(f"{k} {c.param_dict[k]:.6g} ± {c.std_dict[k]:.2g}" for k in cv if c.free[c.param_names.index(k)]))
    c = r_sn.cameras[0]
    fx = c.parameters_px()
    print(f"ours (snooped): fx {fx['fx'][0]:.2f} ± {fx['fx'][1]:.2f} px, cx {fx['cx'][0]:.2f} ± {fx['cx'][1]:.2f}, "
          f"cy {fx['cy'][0]:.2f} ± {fx['cy'][1]:.2f}; sigma_x {c.sigma_xy_px[0]:.3f} px, sigma_y {c.sigma_xy_px[1]:.3f} px; "
          f"{len(r_sn.blunders)} blunders; images used {len(r_sn.images_used)}")
    print(f"cv2 (all):      fx {K[0, 0]:.2f} px, cx {K[0, 2]:.2f}, cy {K[1, 2]:.2f}, dist {np.array2string(dist, precision=4)}")
    return found


def rig(data: Path, thermal_dets: list):
    """Thermal + RGB: the 15 measured pairs (CornerPoints_*.csv, same corner order in both) tie the two
    cameras frame by frame.

    ``thermal_dets`` (detector output on the other thermal views) can be added to strengthen the thermal
    intrinsics, but the CornerPoints_IR measurements do not coincide with the corners of the published
    thermal images (offsets of 8-18 px on Img05, growing towards the border: they were probably measured
    on the author's undistorted images, which are not in the data), so by default they are not mixed."""
    reg = data / "Image registration"

    def load(fn):
        out = {}
        with open(reg / fn) as fh:
            for r in csv.DictReader(fh):
                out.setdefault(r["image"], []).append((int(r["point_index"]), float(r["x"]), float(r["y"])))
        return out

    ir, rgb = load("CornerPoints_IR.csv"), load("CornerPoints_RGB.csv")
    # corner order of the measured sheets: index = 5*b + a, a along one side (5 corners), b along the other (6)
    i = np.arange(30)
    obj_pairs = np.column_stack([(i // 5) * 0.1, (i % 5) * 0.1, np.zeros(30)])
    obj_det = SPEC.object_points() * 1e-3
    obj = np.vstack([obj_pairs, obj_det])  # the detector's labelling is kept apart (other frames only)
    ims = []
    for name in sorted(ir):
        a = np.array(ir[name]); b = np.array(rgb[name])
        ims.append(ImageMeasurements(name + "_ir", 0, a[:, 0].astype(int), a[:, 1:], frame=name))
        ims.append(ImageMeasurements(name + "_rgb", 1, b[:, 0].astype(int), b[:, 1:], frame=name))
    extra = [d for d in thermal_dets if Path(d.image_id).stem not in ir]
    for d in extra:
        ims.append(ImageMeasurements(d.image_id, 0, np.asarray(d.object_ids) + 30, np.asarray(d.points_px, float)))
    cams = [CameraSetup("thermal", (640, 480), PITCH_UM), CameraSetup("rgb", (4056, 3040), 1.55)]
    for is_rig in (False, True):
        t0 = time.perf_counter()
        r = calibrate(cams, obj, ims, rig=is_rig, options=SelfCalibrationOptions(snooping=False))
        dt = time.perf_counter() - t0
        print(f"\n== thermal ({len(ir)} measured pairs + {len(extra)} detected views) + RGB ({len(rgb)} views), "
              f"{'rig (relative orientation)' if is_rig else 'independent poses'}: {r.outcome.termination.value}, {dt:.2f} s")
        pair_rms = {}
        for k, v in enumerate(r.images):
            if v.used and k < 2 * len(ir):
                pair_rms.setdefault(v.camera, []).append(v.rms_px)
        for ci, c in enumerate(r.cameras):
            p = c.parameters_px()
            print(f"  {c.name:8s} RMS {c.rms_px:.3f} px (paired frames {np.sqrt(np.mean(np.square(pair_rms[ci]))):.3f} px)  "
                  f"sigma_x {c.sigma_xy_px[0]:.3f} sigma_y {c.sigma_xy_px[1]:.3f} px  fx {p['fx'][0]:.1f} ± {p['fx'][1]:.1f} px")
        for wtext in r.warnings:
            print(f"  WARNING: {wtext}")
        for ro in r.relative:
            ang = np.degrees(np.linalg.norm(cv2.Rodrigues(ro.R)[0]))
            print(f"  rgb_from_thermal: t = {np.array2string(ro.t * 1e3, precision=1)} mm ± {np.array2string(ro.std[3:] * 1e3, precision=1)} mm,"
                  f" rotation {ang:.3f} deg ± {np.degrees(np.linalg.norm(ro.std[:3])):.3f}, baseline {ro.baseline_m * 1e3:.1f} mm")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data" / "thermal_chessboard"))
    ap.add_argument("--skip-unmasked", action="store_true")
    args = ap.parse_args()
    data = Path(args.data)
    cal = data / "Thermal camera calibration"
    masked = run_set(cal / "Thermal images cropped", "masked (background flattened)")
    if not args.skip_unmasked:
        run_set(cal / "Thermal Images", "unmasked (raw views)")
    rig(data, [])  # see rig() for why the detected views are not mixed in


if __name__ == "__main__":
    main()
