"""Issue 12 with estimated poses on a held-out-like ring: the survey's poses fitted to the mesh being textured.

48 terrestrial stations around ``synthetic.building`` (seed 3, facade detail, an occluder 7 m in front of a wall,
1 m of ground; RTK GNSS 3/5 cm and the camera file; ``survey`` with its defaults, nothing from the truth). The
survey's rotations are 0.78 deg RMS off, 0.5 deg of it one common rotation about a horizontal world axis (centres
on their GNSS: a ring at one height hardly fixes that mode). The texture is taken from noise-free renderings of the
stations placed at the estimated poses -- the survey's, then those fitted to the true mesh by
``pipeline.texture.fit_views_to_mesh`` -- so that the texel errors measure the pose errors; last, the ``texture``
verb's own poses (mesh fit, then the photometric refinement on the survey's noisy frames: ``cameras_fitted.json``).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from thermogrammetry.geometry import Pose
from thermogrammetry.geometry.rotations import axis_angle_from_matrix
from thermogrammetry.io.oriented import OrientedCameras
from thermogrammetry.pipeline.texture import fit_views_to_mesh
from thermogrammetry.products.texture import TextureConfig, TextureView, texture_mesh
from cached_scenes import building_ring_survey
from thermogrammetry.synthetic.building import BuildingConfig, clean_wall_texel_errors, make_building, render_building_thermal


def _texels(sc, views, true_c):
    res = texture_mesh(sc.vertices, sc.faces, views, TextureConfig(texel_size_m=0.04, clean_radius_px=3))
    return res, clean_wall_texel_errors(sc, res, true_c)


@pytest.mark.slow
def test_poses_fitted_to_the_mesh_texture_the_ring_within_the_targets(tmp_path, scene_cache):
    from thermogrammetry.cli.main import main

    config = BuildingConfig(facade_detail=True, n_stations=48, seed=3, occluder_x_m=7.0, ground_margin_m=1.0)
    sc = make_building(config)
    # frames, camera file, GNSS and `survey` with its defaults: built once per test run (tests/cached_scenes.py; the
    # same survey as tests/test_survey_building_rings.py's ring of seed 3), copied to tmp_path / "out"
    _, out, code = building_ring_survey(scene_cache, config, copy_to=tmp_path / "out")
    assert code == 0
    cameras = OrientedCameras.load(out)
    est = {im.name: im for im in cameras}
    views, true_views, true_c = [], [], []
    for k, (name, pose) in enumerate(sc.stations):
        img = render_building_thermal(sc, k, sensor=False)["image_k"]
        true_views.append(TextureView(name, sc.thermal, pose, img))
        if name in est:
            views.append(TextureView(name, sc.thermal, Pose(est[name].R, est[name].t), img))
            true_c.append(pose.center)
    sigma = json.loads((out / "survey.json").read_text())["reprojection_rms_px"]
    # SURVEY_DIR given as its cameras.json: the same tie points (the COLMAP export beside it)
    from thermogrammetry.pipeline.texture import survey_tie_points

    t_dir, _ = survey_tie_points(out, [v.name for v in views])
    t_file, why = survey_tie_points(OrientedCameras.load(out / "cameras.json").root, [v.name for v in views])
    assert why is None and len(t_file.obs_xy) == len(t_dir.obs_xy) > 1000
    fitted, record = fit_views_to_mesh(cameras, views, sc.vertices, sc.faces, tie_sigma_px=sigma)
    assert record["applied"], record["reason"]
    # the tie points come onto the surface (measured median distance 5.4 -> 1.0 cm) without bending the block
    assert record["median_distance_m"]["after"] < 0.4 * record["median_distance_m"]["before"]
    assert record["tie_median_px"]["after"] <= 1.25 * record["tie_median_px"]["before"]
    truth = dict(sc.stations)

    def rot_rms(vs):
        a = [np.degrees(np.arccos(np.clip((np.trace(v.pose.R @ truth[v.name].R.T) - 1) / 2, -1, 1))) for v in vs]
        return float(np.sqrt(np.mean(np.square(a))))

    def common_and_scatter(vs):
        """The block's common rotation error (deg, norm of the mean rotation vector) and the per-camera scatter."""
        e = np.array([np.degrees(axis_angle_from_matrix(v.pose.R @ truth[v.name].R.T)) for v in vs])
        return float(np.linalg.norm(e.mean(axis=0))), float(np.sqrt(np.mean(np.sum((e - e.mean(axis=0)) ** 2, axis=1))))

    r0, r1 = rot_rms(views), rot_rms(fitted)
    (c0, s0), (c1, s1) = common_and_scatter(views), common_and_scatter(fitted)
    # The survey's poses depend on the CPU's floating-point paths (SIMD kernels of OpenCV and NumPy). Measured on the
    # machines of 2026-11-28: 0.78 deg RMS, 0.5 deg of it one common rotation about world Y (a ring at one height hardly
    # fixes that mode), fitted 0.59 deg, the common part 0.2 deg. On an AVX2-only AMD EPYC (2026-12-02): 0.518 deg RMS
    # with a common part of only 0.086 deg, fitted 0.502 deg (common 0.051, scatter 0.511 -> 0.499 deg). What the fit
    # is for: it takes out the common part down to what the per-camera scatter lets 48 cameras determine
    # (2 scatter / sqrt(48) = 0.14 deg), and makes no camera set worse
    assert c1 <= max(0.6 * c0, 2 * s1 / np.sqrt(len(fitted))), (c0, c1, s1)
    assert r1 <= 1.02 * r0 and s1 <= 1.02 * s0, (r0, r1, s0, s1)
    ref, _ = _texels(sc, true_views, [p.center for _, p in sc.stations])
    vis = ref.face_visible
    res0, e0 = _texels(sc, views, true_c)
    res1, e1 = _texels(sc, fitted, true_c)
    share0, share1 = np.mean(e0 <= 0.2), np.mean(e1 <= 0.2)
    # clean wall texels within 0.2 K of the noise-free truth: measured 91.3 % with the survey's poses, 97.1 % fitted;
    # median 0.051 -> 0.026 K. Issue 12's "within 0.2 K" (every texel) still fails for ~3 %: the per-camera
    # rotation errors that remain (0.3-0.4 deg, the GNSS noise of the centres traded against rotation)
    # (AVX2-only EPYC, the survey's poses without a common mode: 99.70 % -> 99.997 %, median 0.015 -> 0.018 K). The fit
    # keeps the share within 0.2 K; below 0.02 K (a tenth of that target) the median no longer measures the poses
    # (AVX-512 EPYC, 2026-12-02: survey 0.905 deg RMS, common part 0.17 deg; fitted 0.82 deg; 89.2 % -> 93.8 %.) The
    # survey's scatter differs by machine, so the absolute bound is the least measured share, less about two points
    assert share1 > 0.92 and share1 >= share0 - 0.001, (share0, share1, r0, r1, c0, c1, s0, s1)
    # median: 0.051 -> 0.026 K (2026-11-28), 0.015 -> 0.018 K (AVX2 EPYC), 0.0445 -> 0.0369 K (AVX-512 EPYC with the
    # packages of 2026-12-02 16:00, SciPy 1.17.1 / OpenCV 5.1: 0.83x): it falls wherever it measures the poses (above
    # 0.02 K, a tenth of the 0.2 K target), by at least 10 %, and stays below the largest measured, 0.04 K
    assert np.median(e1) < 0.04 and np.median(e1) < max(0.9 * np.median(e0), 0.02), (np.median(e0), np.median(e1))
    # visible faces (from the 48 true stations) textured: measured 97.4 % -> 97.7 % (98.4 % with the true poses)
    assert np.mean(res1.faces_textured[vis]) >= np.mean(res0.faces_textured[vis]) - 0.002
    assert np.mean(res1.faces_textured[vis]) > 0.97
    # the texture verb does the same by default, then refines the poses photometrically on the survey's (noisy) frames:
    # texture.json says so, cameras_fitted.json holds the poses used
    import trimesh

    mesh = tmp_path / "building.ply"
    trimesh.Trimesh(sc.vertices, sc.faces, process=False).export(mesh)
    assert main(["texture", str(out), "--mesh", str(mesh), "-o", str(tmp_path / "tex")]) == 0
    tj = json.loads((tmp_path / "tex" / "texture.json").read_text())
    assert tj["pose_fit"]["applied"] and tj["pose_fit"]["points_on_surface"] == record["points_on_surface"]
    ph = tj["photometric_fit"]
    assert ph["applied"], ph["reason"]
    # the images' disagreement on the mesh falls (measured 0.80x, and 0.0321 -> 0.0262 K = 0.82x on the AVX2-only EPYC)
    assert ph["robust_sigma_after"] < 0.9 * ph["robust_sigma_before"]
    fit_cams = OrientedCameras.load(tmp_path / "tex" / "cameras_fitted.json")
    assert fit_cams.read_frame(views[0].name).shape == (240, 320)
    verb = [TextureView(v.name, v.camera, Pose(fit_cams.image(v.name).R, fit_cams.image(v.name).t), v.image_k) for v in views]
    r2 = rot_rms(verb)
    res2, e2 = _texels(sc, verb, true_c)
    # measured: rotations 0.59 -> 0.14 deg RMS; clean wall texels within 0.2 K 97.1 % -> 100.0 %, median 0.026 -> 0.009 K,
    # p99 0.28 -> 0.05 K: issue 12's "within 0.2 K with estimated poses" on this ring
    # (AVX2-only EPYC: 0.50 -> 0.21 deg, 100.0 %, p99 0.062 K, median 0.018 -> 0.012 K)
    assert r2 < 0.5 * r1
    assert np.mean(e2 <= 0.2) > 0.995 and np.percentile(e2, 99) < 0.12 and np.median(e2) < max(0.6 * np.median(e1), 0.015)
    # visible faces (from the true stations) textured: the verb's own radius rule (3 sigma of the poses, fallback to the
    # configured radius) textures 99.6 % of them (measured)
    textured = np.ones(len(sc.faces), bool)
    textured[tj["faces_untextured"]] = False
    assert np.mean(textured[vis]) > 0.98
