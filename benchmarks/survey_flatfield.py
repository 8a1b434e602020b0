"""Benchmark: ``thermogrammetry survey`` on a flat-field UAV block with ground control, self-calibrating and with the
camera held, over several noise realisations.

A flat field flown at one height is the block that cannot determine its focal length: f -> s f with every flying
height Z -> s Z leaves every image point where it is, and 1 m of relief barely breaks that twin. The scene: the
M3T-like block of ``synthetic.survey_files.uav_thermal_config`` (320x256 px, 4.55 mm / 12 µm, 50 m above ground,
GSD 0.132 m, 80/60 % overlap) over terrain with ``--relief`` m of relief and no buildings or trees, GNSS 3/5 cm,
``--gcps`` control and ``--checks`` check points measured in the frames with ``--marker-sigma`` px of noise
(users' marker measurements scatter by ~1 px), GCP coordinates with 1 cm noise.

Rows per run:

- ``self-calibration``: what a user has (the frames with their EXIF focal length, GNSS, GCPs, check points);
- ``camera held (true camera)``: ``--camera`` with the scene's exact camera -- a calibration without error. This
  row starts from the truth on purpose: it isolates what the block does with a perfect calibration.

Scored on the product: ``survey.json``'s check-point errors (X, Y, Z RMSE in m and in GSD) and their reported σ
against the scatter of the errors over the runs (ratio RMS(error) / RMS(σ) per axis: 1 when σ is honest).

Usage::

    python benchmarks/survey_flatfield.py [--seeds 3] [--relief 1.0] [--out /tmp/flatfield]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _render(root: Path, seed: int, relief_m: float, n_gcp: int, n_check: int, marker_sigma_px: float):
    from thermogrammetry.store import FolderProject
    from thermogrammetry.synthetic.survey import make_survey, write_survey
    from thermogrammetry.synthetic.survey_files import uav_thermal_config, write_user_files
    from thermogrammetry.synthetic.terrain import TerrainConfig

    cfg = uav_thermal_config(seed=seed, terrain=TerrainConfig(width_m=130.0, height_m=100.0, relief_m=relief_m,
                                                              n_buildings=0, n_trees=0, n_roads=1),
                             n_gcp=n_gcp, n_check=n_check)
    scene = make_survey(cfg)
    project = FolderProject(root)
    write_survey(project, scene, threads=2)
    write_user_files(project, scene, marker_sigma_px=marker_sigma_px, seed=seed)
    cam = scene.camera
    cam.save(root / "true_camera.json")
    gsd = cfg.flight_height_m * cfg.pixel_pitch_um * 1e-3 / cfg.focal_mm
    return gsd


def _survey(root: Path, out: Path, camera: Path | None) -> dict:
    from thermogrammetry.cli.main import main

    user = root / "survey" / "user"
    args = ["survey", str(root / "survey" / "images"), "-o", str(out), "--workers", "0",
            "--gnss", str(user / "gnss.csv"), "--gcps", str(user / "gcps.csv"),
            "--gcp-measurements", str(user / "gcp_measurements.csv"),
            "--checkpoints", str(user / "checkpoints.csv"), "--check-measurements", str(user / "check_measurements.csv")]
    if camera is not None:
        args += ["--camera", str(camera)]
    t0 = time.perf_counter()
    code = main(args)
    dt = time.perf_counter() - t0
    s = json.loads((out / "survey.json").read_text())
    errs = [c for c in s.get("checkpoint_errors", []) if c.get("dx") is not None]
    e = np.array([[c["dx"], c["dy"], c["dz"]] for c in errs]) if errs else np.zeros((0, 3))
    sd = np.array([[c["sx"] if c["sx"] is not None else np.nan, c["sy"] if c["sy"] is not None else np.nan,
                    c["sz"] if c["sz"] is not None else np.nan] for c in errs]) if errs else np.zeros((0, 3))
    from thermogrammetry.camera import Camera

    cams = json.loads((out / "cameras.json").read_text())["cameras"] if (out / "cameras.json").exists() else {}
    fx = [float(Camera.from_dict(c).param_dict["fx"]) for c in cams.values()]
    blocks = s.get("blocks", [])
    return {"code": code, "seconds": dt, "oriented": s.get("images_oriented"), "images": s.get("images_total"),
            "errors": e, "sigma": sd, "fx": fx[0] if fx else None,
            "self_calibration": blocks[0].get("self_calibration") if blocks else None,
            "focal_prior": blocks[0].get("focal_prior") if blocks else None,
            "determinability": blocks[0].get("determinability") if blocks else None,
            "steps": blocks[0].get("self_calibration_steps") if blocks else None}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--relief", type=float, default=1.0)
    ap.add_argument("--gcps", type=int, default=8)
    ap.add_argument("--checks", type=int, default=8)
    ap.add_argument("--marker-sigma", type=float, default=1.0)
    ap.add_argument("--out", type=Path, default=Path("/tmp/flatfield"))
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    rows: dict[str, list] = {"self-calibration": [], "camera held (true camera)": []}
    gsd = None
    for seed in range(a.seeds):
        root = a.out / f"scene{seed}"
        if not (root / "survey" / "user" / "gnss.csv").exists():
            shutil.rmtree(root, ignore_errors=True)
            gsd = _render(root, seed, a.relief, a.gcps, a.checks, a.marker_sigma)
        else:
            from thermogrammetry.synthetic.survey_files import uav_thermal_config

            c = uav_thermal_config(seed=seed)
            gsd = c.flight_height_m * c.pixel_pitch_um * 1e-3 / c.focal_mm
        for label, cam in (("self-calibration", None), ("camera held (true camera)", root / "true_camera.json")):
            out = a.out / f"out{seed}_{'self' if cam is None else 'held'}"
            shutil.rmtree(out, ignore_errors=True)
            r = _survey(root, out, cam)
            rows[label].append(r)
            rm = np.sqrt(np.mean(r["errors"] ** 2, axis=0)) if len(r["errors"]) else [np.nan] * 3
            print(f"seed {seed} {label}: exit {r['code']}, {r['oriented']}/{r['images']} oriented, fx {r['fx']}, "
                  f"check RMSE {rm[0]:.3f}/{rm[1]:.3f}/{rm[2]:.3f} m, self-calibration {r['self_calibration']}, "
                  f"focal prior {r['focal_prior']}, determinability {r['determinability']}, {r['seconds']:.0f} s", flush=True)
    print(f"\nflat field, relief {a.relief} m, {a.gcps} GCPs, {a.checks} check points, markers {a.marker_sigma} px, "
          f"GSD {gsd:.3f} m, {a.seeds} noise realisations\n")
    print("| row | oriented | check RMSE X / Y / Z (m) | in GSD | RMS(error)/RMS(σ) X / Y / Z | fx (px) |")
    print("|---|---|---|---|---|---|")
    for label, rs in rows.items():
        e = np.concatenate([r["errors"] for r in rs]) if rs else np.zeros((0, 3))
        s = np.concatenate([r["sigma"] for r in rs]) if rs else np.zeros((0, 3))
        rm = np.sqrt(np.mean(e**2, axis=0)) if len(e) else np.full(3, np.nan)
        rs_ = np.sqrt(np.nanmean(s**2, axis=0)) if len(s) and np.isfinite(s).any() else np.full(3, np.nan)
        fx = [r["fx"] for r in rs if r["fx"] is not None]
        print(f"| {label} | {sum(r['oriented'] or 0 for r in rs)}/{sum(r['images'] or 0 for r in rs)} | "
              f"{rm[0]:.3f} / {rm[1]:.3f} / {rm[2]:.3f} | {rm[0] / gsd:.2f} / {rm[1] / gsd:.2f} / {rm[2] / gsd:.2f} | "
              f"{rm[0] / rs_[0]:.2f} / {rm[1] / rs_[1]:.2f} / {rm[2] / rs_[2]:.2f} | "
              f"{', '.join(f'{v:.1f}' for v in fx)} |")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(REPO / "src"))
    raise SystemExit(main())
