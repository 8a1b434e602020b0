"""Benchmark: texture of a synthetic building from the poses of ``survey``, as they are and fitted to the mesh (issue 12).

A ring of terrestrial stations around ``synthetic.building`` (facade detail; seed 3 = an occluder 7 m in front of a
wall and 1 m of ground, the held-out-like scene) is rendered; ``thermogrammetry survey`` orients it from what a user
has (float32 kelvin frames, the camera file, an RTK GNSS CSV with 3 cm noise; CLI defaults). The texture is then taken
from noise-free renderings of the stations placed at three sets of poses -- the TRUE ones (reference row, marked as
such), the survey's, and the survey's fitted to the true mesh (``sfm.meshfit`` through
``pipeline.texture.fit_views_to_mesh``, what ``thermogrammetry texture`` does by default) -- so that the texel errors
measure the pose errors alone. Clean wall texels (>= 2 pixel footprints from a window/door edge) against the scene's
apparent temperature; faces textured among those visible from the true stations (at clean radius 3 px, no fallback).
Last, the ``texture`` verb itself (``run_texture``, default texel size, poses fitted to the mesh and then refined
photometrically on the survey's noisy frames): its poses (``cameras_fitted.json``) as one more row, the share of the
true-visible faces it textured, its wall time.

Usage::

    python benchmarks/texture_ring.py [--seed 3] [--stations 48] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--stations", type=int, default=48)
    ap.add_argument("--keep", default=None, help="keep the rendered frames, the survey and the texture in this folder")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO / "src"))
    import trimesh

    from thermogrammetry.cli.main import main as cli
    from thermogrammetry.geometry import Pose
    from thermogrammetry.io.oriented import OrientedCameras
    from thermogrammetry.pipeline.project import FolderProject
    from thermogrammetry.pipeline.texture import fit_views_to_mesh, run_texture
    from thermogrammetry.products.texture import TextureConfig, TextureView, texture_mesh
    from thermogrammetry.synthetic.building import (BuildingConfig, clean_wall_texel_errors, make_building,
                                                    render_building_thermal, write_building_survey, write_building_user_files)

    kw = dict(facade_detail=True, n_stations=args.stations, seed=args.seed)
    if args.seed == 3:
        kw.update(occluder_x_m=7.0, ground_margin_m=1.0)
    sc = make_building(BuildingConfig(**kw))
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_texture_ring_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        project = FolderProject(work)
        write_building_survey(project, sc)
        write_building_user_files(project, sc)
        out = work / "survey"
        t0 = time.perf_counter()
        code = cli(["survey", str(work / "frames"), "-o", str(out), "--input-unit", "K", "--camera", str(work / "camera.json"),
                    "--gnss", str(work / "gnss.csv"), "--workers", "0"])
        t_survey = time.perf_counter() - t0
        if code != 0:
            print(f"survey failed (exit {code})")
            return 1
        cameras = OrientedCameras.load(out)
        est = {im.name: im for im in cameras}
        truth = dict(sc.stations)
        true_views, views, true_c = [], [], []
        for k, (name, pose) in enumerate(sc.stations):
            img = render_building_thermal(sc, k, sensor=False)["image_k"]
            true_views.append(TextureView(name, sc.thermal, pose, img))
            if name in est:
                views.append(TextureView(name, sc.thermal, Pose(est[name].R, est[name].t), img))
                true_c.append(pose.center)
        sigma = json.loads((out / "survey.json").read_text())["reprojection_rms_px"]
        t0 = time.perf_counter()
        fitted, record = fit_views_to_mesh(cameras, views, sc.vertices, sc.faces, tie_sigma_px=sigma)
        t_fit = time.perf_counter() - t0

        def evaluate(vs, centres):
            res = texture_mesh(sc.vertices, sc.faces, vs, TextureConfig(texel_size_m=0.04, clean_radius_px=3))
            return res, clean_wall_texel_errors(sc, res, centres)

        def rot(vs):
            a = np.array([np.degrees(np.arccos(np.clip((np.trace(v.pose.R @ truth[v.name].R.T) - 1) / 2, -1, 1))) for v in vs])
            return np.sqrt(np.mean(a**2)), a.max()

        ref, e_true = evaluate(true_views, [p.center for _, p in sc.stations])
        vis = ref.face_visible
        rows = [("TRUE poses (reference, from the scene's truth)", (0.0, 0.0), ref, e_true)]
        rows.append(("survey poses", rot(views), *evaluate(views, true_c)))
        if record["applied"]:
            rows.append(("survey poses fitted to the mesh", rot(fitted), *evaluate(fitted, true_c)))
        mesh = work / "building.ply"
        trimesh.Trimesh(sc.vertices, sc.faces, process=False).export(mesh)
        t0 = time.perf_counter()
        tj = run_texture(out, mesh, work / "texture")
        t_texture = time.perf_counter() - t0
        ph = tj["photometric_fit"]
        if (work / "texture" / "cameras_fitted.json").exists():
            verb_cams = OrientedCameras.load(work / "texture" / "cameras_fitted.json")
            verb_views = [TextureView(v.name, v.camera, Pose(verb_cams.image(v.name).R, verb_cams.image(v.name).t), v.image_k)
                          for v in views]
            rows.append(("the texture verb's poses (+ photometric on noisy frames)", rot(verb_views),
                         *evaluate(verb_views, true_c)))
        textured_verb = np.ones(len(sc.faces), bool)
        textured_verb[tj["faces_untextured"]] = False
        s = json.loads((out / "survey.json").read_text())
        print(f"\nsynthetic.building seed {args.seed}, {args.stations} stations: survey {s['images_oriented']}/{s['images_total']} "
              f"in {s['components']}, RMS {s['reprojection_rms_px']:.3f} px, {t_survey:.0f} s")
        md = record.get("median_distance_m", {})
        print(f"fit to the mesh: applied {record['applied']} {record.get('reason', '')}; tie points on the surface "
              f"{record.get('points_on_surface')} of {record.get('points')}, median distance {md.get('before', float('nan')):.3f} -> "
              f"{md.get('after', float('nan')):.3f} m, {t_fit:.1f} s\n")
        print(f"{'poses':<58}{'rot RMS/max deg':>17}{'texels':>9}{'<=0.2 K':>9}{'median K':>10}{'p99 K':>8}{'faces textured':>16}")
        for label, (rr, rm), res, e in rows:
            print(f"{label:<58}{rr:>9.2f}/{rm:<7.2f}{len(e):>9}{100 * np.mean(e <= 0.2):>8.1f}%{np.median(e):>10.3f}"
                  f"{np.percentile(e, 99):>8.2f}{100 * np.mean(res.faces_textured[vis]):>15.1f}%")
        print(f"\nphotometric refinement in the verb: applied {ph['applied']} {ph.get('reason', '')}; robust disagreement "
              f"{ph.get('robust_sigma_before', float('nan')):.4f} -> {ph.get('robust_sigma_after', float('nan')):.4f} K, "
              f"{ph.get('points')} points, {ph.get('seconds')} s")
        print(f"thermogrammetry texture (run_texture, default texel size, poses fitted): {t_texture:.0f} s; visible faces "
              f"(true stations) textured by it: {100 * np.mean(textured_verb[vis]):.1f} % (its clean radius "
              f"{tj['clean_radius_px']['value']} px, fallback down to 0 px)")
        return 0
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
