"""``products.texture`` and ``thermogrammetry texture`` on the synthetic building with an occluder.

Tests marked "true poses" orient the images with the renderer's poses (no estimation error).
Images are rendered noise-free (no NETD/FPN/PSF) unless stated, so that a texel must equal the
noise-free apparent temperature of its point in its source image up to the sampling error: bilinear
interpolation of 2x2-supersampled pixels of a field whose shortest wavelength is 0.7 m, with pixels of
~4 cm on the walls, errs by < 0.01 K; the issue's bound is 0.05 K.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from cached_scenes import building_images
from thermogrammetry.products.correction import CorrectionConfig
from thermogrammetry.products.texture import (TextureConfig, TextureView, estimate_offsets,
                                              face_view_scores, texture_mesh, thermal_poses_from_rig)
from thermogrammetry.synthetic.building import GROUPS, BuildingConfig, apparent_temperature, make_building

TEXEL_M = 0.04


@pytest.fixture(scope="module")
def scene():
    return make_building(BuildingConfig(ground_margin_m=1.0))


@pytest.fixture(scope="module")
def views(scene, scene_cache):
    images = building_images(scene_cache, scene)  # render_building_thermal(sensor=False), once per test run
    return [TextureView(n, scene.thermal, p, images[k]) for k, (n, p) in enumerate(scene.stations)]


@pytest.fixture(scope="module")
def result(scene, views, scene_cache):
    # computed once per test run, shared by the xdist workers (tests/_cache.py)
    return scene_cache.value("test_texture-result", {"config": dataclasses.asdict(scene.config), "texel": TEXEL_M},
                             lambda: texture_mesh(scene.vertices, scene.faces, views, TextureConfig(texel_size_m=TEXEL_M)))


def _segment_hits_box(A, B, lo, hi):
    """Analytic slab test: does the open segment A->B (N, 3) pass through the box [lo, hi]?"""
    d = B - A
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - A) / d
        t2 = (hi - A) / d
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    return (tmax > tmin) & (tmax > 1e-6) & (tmin < 1 - 1e-6)


def _occluder_box(scene):
    c = scene.config
    ox, oy, oz = c.occluder_size_m
    xc, yc = c.occluder_x_m, -c.occluder_distance_m
    return np.array([xc - ox / 2, yc - oy / 2, 0.0]), np.array([xc + ox / 2, yc + oy / 2, oz])


def test_texels_equal_noise_free_truth_true_poses(scene, views, result):
    sel, tx = result.texel_selection, result.texels
    ok = sel.source >= 0
    C = np.array([v.pose.center for v in views])[sel.source[ok]]
    truth = apparent_temperature(scene, tx.points[ok], tx.face[ok], C)
    err = sel.temperature_k[ok] - truth
    assert ok.sum() > 100_000
    assert np.max(np.abs(err)) < 0.05
    # the texture rasters hold the same numbers at the texel positions
    r, c = tx.rc[ok].T
    np.testing.assert_allclose(result.temperature_k[r, c], sel.temperature_k[ok].astype(np.float32))
    assert np.all(result.source[r, c] == sel.source[ok])
    # everything else is flagged, never filled
    untex = np.ones(result.source.shape, bool)
    untex[r, c] = False
    assert np.all(result.source[untex] == -1) and np.all(np.isnan(result.temperature_k[untex]))


def test_no_texel_from_a_view_where_it_is_occluded(scene, views, result):
    sel, tx = result.texel_selection, result.texels
    ok = np.flatnonzero(sel.source >= 0)
    lo, hi = _occluder_box(scene)
    C = np.array([v.pose.center for v in views])
    P = tx.points[ok]
    not_occ = tx.face[ok] != -1
    g = scene.face_group[tx.face[ok]]
    wall = g == GROUPS.index("wall")
    hidden = _segment_hits_box(C[sel.source[ok]][wall], P[wall], lo, hi)
    assert hidden.sum() == 0
    # the occluder really hides texels that the face score prefers: the selection had to switch views
    best = np.argmax(face_view_scores(scene.vertices, scene.faces, views).toarray(), axis=1)[tx.face[ok]]
    hidden_in_best = _segment_hits_box(C[best][wall], P[wall], lo, hi)
    assert hidden_in_best.sum() > 1000
    assert np.all(sel.source[ok][wall][hidden_in_best] != best[wall][hidden_in_best])
    assert result.occluded_texels.sum() > 1000
    assert not_occ.all()


def test_selection_in_chunks_equals_one_call(scene, views):
    """Chunks of texels (memory bounded by chunk x images) give exactly the one-call selection."""
    from thermogrammetry.products.texture import (_intersector, build_atlas, pixel_surfaces, rasterize_atlas,
                                                  select_and_sample, select_in_chunks)

    V, F = scene.vertices, scene.faces
    cfg = TextureConfig(texel_size_m=0.2)
    tx = rasterize_atlas(build_atlas(V, F, 0.2), V, F)
    inter = _intersector(V, F)
    surf = [pixel_surfaces(inter, V, F, v) for v in views]
    sc = face_view_scores(V, F, views)
    one = select_and_sample(inter, V, F, views, surf, sc, tx.points, tx.face, cfg)
    sample = np.zeros(len(tx.points), bool)
    sample[::7] = True
    done = []
    sel, occ, ak = select_in_chunks(inter, V, F, views, surf, sc, tx.points, tx.face, cfg, sample=sample,
                                    chunk_point_views=len(views) * 997, on_chunk=lambda d, n: done.append((d, n)))
    assert len(tx.points) > 5 * 997 and sel.occluded_in is None and sel.all_k is None
    # progress after every chunk: 997, 1994, ... up to every point
    n = len(tx.points)
    assert done == [(min(n, 997 * (i + 1)), n) for i in range(-(-n // 997))]
    assert np.array_equal(sel.source, one.source) and np.array_equal(sel.n_usable, one.n_usable)
    assert np.array_equal(sel.temperature_k, one.temperature_k, equal_nan=True)
    assert np.array_equal(occ, one.occluded_in.sum(axis=0)) and occ.sum() > 0
    assert np.array_equal(ak, one.all_k[sample], equal_nan=True)
    # the sparse (F, K) scores select exactly what their dense matrix selects
    dense = select_and_sample(inter, V, F, views, surf, sc.toarray(), tx.points, tx.face, cfg)
    assert np.array_equal(dense.source, one.source) and np.array_equal(dense.temperature_k, one.temperature_k, equal_nan=True)


def test_sparse_face_view_scores(scene, views):
    """face_view_scores keeps the positive scores only (a dense (F, K) float64 was 1.6 GB at 1 M faces x 200 images):
    same values as one image's column computed on its own; scores_at reads any faces of an image, absent = 0."""
    from thermogrammetry.products.texture import _check_mesh, _score_columns, _score_max_count, scores_at

    V, F = _check_mesh(scene.vertices, scene.faces)
    sc = face_view_scores(V, F, views)
    cols = dict(_score_columns(V, F, views, 75.0, 0.1))
    D = np.column_stack([cols[k] for k in range(len(views))])
    assert sc.shape == D.shape and sc.nnz == int(np.sum(D > 0)) and 0 < sc.nnz < 0.6 * D.size
    assert np.array_equal(sc.toarray(), D)
    rng = np.random.default_rng(0)
    fi = rng.integers(0, len(F), 5000)
    for k in range(len(views)):
        assert np.array_equal(scores_at(sc, k, fi), D[fi, k]) and np.array_equal(scores_at(D, k, fi), D[fi, k])
    best, n = _score_max_count(sc)
    assert np.array_equal(best, D.max(axis=1)) and np.array_equal(n, (D > 0).sum(axis=1))


def test_coverage_of_visible_faces(scene, result):
    s = result.summary()
    seen = result.face_views > 0
    assert s["faces_seen"] == seen.sum() > 500
    vis = result.face_visible
    assert s["faces_visible"] == vis.sum() > 500 and not np.any(vis & ~seen)  # a visible texel needs a scored face
    share = np.mean(result.faces_textured[vis])
    assert share >= 0.98
    assert s["faces_visible_textured"] == int(np.sum(vis & result.faces_textured))
    assert not np.any(result.faces_textured & ~vis)  # a textured texel is a visible one
    wall = scene.face_group == GROUPS.index("wall")
    n_tex = np.bincount(result.texels.face, minlength=len(scene.faces))
    n_ok = np.bincount(result.texels.face[result.texel_selection.source >= 0], minlength=len(scene.faces))
    assert n_ok[wall].sum() / n_tex[wall].sum() > 0.9  # texel share on the walls (mixed-pixel strips excepted)
    assert len(s["faces_untextured"]) == len(scene.faces) - s["faces_textured"]


def test_vertex_temperatures_true_poses(scene, views, result):
    vt = result.vertex_temperature_k
    wall_v = np.unique(scene.faces[scene.face_group == GROUPS.index("wall")])
    fin = wall_v[np.isfinite(vt[wall_v])]
    assert len(fin) > 0.6 * len(wall_v)
    # a wall vertex away from the building's edges has one wall temperature; compare there
    c = scene.config
    P = scene.vertices[fin]
    corners = np.array([[0, 0], [c.length_m, 0], [c.length_m, c.depth_m], [0, c.depth_m]])
    edge = np.min(np.linalg.norm(P[:, None, :2] - corners[None], axis=2), axis=1)
    inner = (P[:, 2] > 0.5) & (P[:, 2] < c.height_m - 0.5) & (edge > 0.5)
    from thermogrammetry.synthetic.building import surface_temperature

    truth = surface_temperature(scene, P[inner], GROUPS.index("wall"))
    assert inner.sum() > 50
    assert np.max(np.abs(vt[fin][inner] - truth)) < 0.05


def test_offsets_levelling_recovers_injected_offsets(scene, views):
    inj = np.zeros(len(views))
    inj[3], inj[7], inj[12] = 0.5, -0.3, 0.2
    shifted = [TextureView(v.name, v.camera, v.pose, v.image_k + np.float32(inj[k])) for k, v in enumerate(views)]
    res = texture_mesh(scene.vertices, scene.faces, shifted, TextureConfig(texel_size_m=0.08, levelling="offsets"))
    f = res.levelling_fixed
    est = res.offsets_k
    # T_k + o_k is level: o_k = -(inj_k - inj_fixed) for every image with overlaps
    assert res.offsets_k[f] == 0.0
    has = np.array([k for k in range(len(views)) if k != f and abs(est[k]) > 0 or inj[k] != 0])
    np.testing.assert_allclose(est[has], -(inj[has] - inj[f]), atol=0.02)
    assert res.levelling_rms_k[1] < 0.05 < res.levelling_rms_k[0]


def test_estimate_offsets_needs_overlap():
    from thermogrammetry.products.texture import Selection

    n = 10
    sel = Selection(np.zeros(n, int), np.ones(n), np.zeros(n), np.ones(n), np.ones(n, int), np.zeros((n, 2), bool),
                    np.c_[np.ones(n), np.full(n, np.nan)].astype(np.float32))
    off, fixed, pairs, rb, ra = estimate_offsets(sel, 2)
    assert fixed == 0 and np.all(off == 0) and np.all(pairs == 0) and np.isnan(rb)


def test_correction_uses_texel_angle_and_distance(scene, views):
    from thermogrammetry.products.correction import correct_temperature
    from thermogrammetry.radiometry.atmosphere import atmospheric_transmission
    from thermogrammetry.radiometry.directional import fresnel_emissivity

    cc = CorrectionConfig(emissivity="fresnel", refractive_index=1.8, ambient_c=260.0 - 273.15, air_c=281.0 - 273.15,
                          transmission=True, relative_humidity=0.6)
    raw = texture_mesh(scene.vertices, scene.faces, views, TextureConfig(texel_size_m=0.1))
    cor = texture_mesh(scene.vertices, scene.faces, views, TextureConfig(texel_size_m=0.1, correct=True, correction=cc))
    s0, tx = raw.texel_selection, raw.texels
    ok = s0.source >= 0
    C = np.array([v.pose.center for v in views])[s0.source[ok]]
    P = tx.points[ok]
    n = scene.face_normals[tx.face[ok]]
    d = np.linalg.norm(C - P, axis=1)
    theta = np.arccos(np.einsum("ij,ij->i", n, (C - P) / d[:, None]))
    eps = fresnel_emissivity(theta, 1.8)
    expect = correct_temperature(s0.temperature_k[ok], eps, 260.0, transmission=atmospheric_transmission(d, 281.0, 0.6),
                                 atmosphere_k=281.0)
    np.testing.assert_allclose(cor.texel_selection.temperature_k[ok], expect, atol=1e-6)
    assert np.nanmean(cor.texel_selection.temperature_k[ok] - s0.temperature_k[ok]) > 0.5  # ε < 1: warmer


def test_rig_poses_from_rgb_poses_seed002_eq45():
    from thermogrammetry.synthetic.facade import FacadeConfig, make_facade

    fac = make_facade(FacadeConfig(n_stations=3))
    got = thermal_poses_from_rig([p for _, p, _ in fac.stations], fac.rig_relative)
    for (name, p_rgb, p_ir), g in zip(fac.stations, got):
        np.testing.assert_allclose(g.R, p_ir.R, atol=1e-12)
        np.testing.assert_allclose(g.t, p_ir.t, atol=1e-12)
        # eq. 5: C_IR = C_RGB + R_RGB^T b with b the thermal centre in the RGB frame
        b = -fac.rig_relative.R.T @ fac.rig_relative.t
        np.testing.assert_allclose(g.center, p_rgb.center + p_rgb.R.T @ b, atol=1e-12)
        # eq. 4: R* = R_RGB^T-convention product is constant = R_rel^T
        np.testing.assert_allclose(p_rgb.R @ g.R.T, fac.rig_relative.R.T, atol=1e-12)


def test_config_rejects_unknown_keys():
    from thermogrammetry.errors import ConfigError

    with pytest.raises(ConfigError, match="unknown key"):
        TextureConfig.from_dict({"texel_size": 0.1})
    with pytest.raises(ConfigError, match="Levelling"):
        TextureConfig(levelling="blend")


# ------------------------------------------------------------------------------------------- CLI
def _write_survey(tmp, scene, views):
    """A survey folder from the renderer's TRUE poses (survey not involved)."""
    import tifffile

    from thermogrammetry.io.oriented import OrientedCameras, OrientedImage

    (tmp / "frames").mkdir(parents=True)
    ims = []
    for v in views:
        tifffile.imwrite(tmp / "frames" / f"{v.name}.tif", v.image_k)
        ims.append(OrientedImage(v.name, "thermal", v.pose.R, v.pose.t, frame=f"frames/{v.name}.tif", unit="K"))
    OrientedCameras({"thermal": scene.thermal}, ims).save(tmp / "cameras.json")
    lines = [f"v {x} {y} {z}" for x, y, z in scene.vertices] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in scene.faces]
    (tmp / "mesh.obj").write_text("\n".join(lines) + "\n")
    return tmp


@pytest.fixture(scope="module")
def cli_out(scene_cache, scene, views):
    # built once per test run, shared by the xdist workers (tests/_cache.py); the tests read it (or copy it)
    folder, rc = scene_cache.folder("test_texture-cli_out", dataclasses.asdict(scene.config),
                                    lambda folder: _cli_run(folder, scene, views))
    assert rc == 0
    return folder / "survey", folder / "tex" / "out"


def _cli_run(folder, scene, views):
    from thermogrammetry.cli.main import main

    survey = _write_survey(folder / "survey", scene, views)
    out = folder / "tex" / "out"
    return main(["texture", str(survey), "--mesh", str(survey / "mesh.obj"), "-o", str(out), "--unit", "C", "--texel-size", "0.05"])


def test_cli_texture_outputs(cli_out, scene, views):
    import tifffile
    import trimesh
    from plyfile import PlyData

    survey, out = cli_out
    for f in ("textured.glb", "textured.obj", "textured.mtl", "textured.png", "temperature_texture.tif", "source_texture.tif",
              "vertices.ply", "texture.json", "report.html", "temperature_texture_u16.tif", "angle_texture.tif"):
        assert (out / f).is_file(), f
    d = json.loads((out / "texture.json").read_text())
    assert d["unit"] == "C" and d["offsets"] is None and d["values_altered"] is False
    assert d["index"] == {str(i): v.name for i, v in enumerate(views)}
    assert d["faces_total"] == len(scene.faces) and d["faces_visible_textured"] >= 0.98 * d["faces_visible"] > 500
    t = tifffile.imread(out / "temperature_texture.tif")
    src = tifffile.imread(out / "source_texture.tif")
    assert t.dtype == np.float32 and src.dtype == np.int32 and t.shape == src.shape
    assert np.all(np.isnan(t[src == -1])) and np.all(np.isfinite(t[src >= 0]))
    assert src.max() < len(views) and (src >= 0).sum() == d["texels_textured"]
    # values in °C: plausible wall/occluder range of the scene (276-290 K)
    assert 2.0 < np.nanmin(t) and np.nanmax(t) < 17.0
    # the 16-bit texture decodes to the float one within half a step
    m = d["uint16_mapping"]
    codes = tifffile.imread(out / "temperature_texture_u16.tif")
    dec = codes * m["scale"] + m["offset"]
    assert np.max(np.abs(dec[src >= 0] - t[src >= 0])) <= m["scale"] / 2 + 1e-4
    ply = PlyData.read(str(out / "vertices.ply"))
    vt = np.asarray(ply["vertex"]["temperature_k"])
    assert len(vt) == len(scene.vertices) and 270 < np.nanmin(vt) and np.nanmax(vt) < 300
    glb = trimesh.load(out / "textured.glb", force="mesh")
    assert len(glb.faces) == len(scene.faces) and glb.visual.uv.shape == (len(glb.vertices), 2)
    # the preview's colour scale is recorded (°C here) and the GLB's material is unlit: viewers show those colours
    pal = d["preview_palette"]
    assert pal["unit"] == "°C" and pal["quantity"] == "temperature" and pal["colormap"] == "inferno"
    fin = t[np.isfinite(t)]
    np.testing.assert_allclose([pal["min"], pal["max"]], np.percentile(fin, [1, 99]), rtol=0, atol=1e-4)
    raw = (out / "textured.glb").read_bytes()
    doc = json.loads(raw[20:20 + int.from_bytes(raw[12:16], "little")])
    assert doc["extensionsUsed"] == ["KHR_materials_unlit"]
    assert all("KHR_materials_unlit" in m["extensions"] for m in doc["materials"])
    assert "°C" in (out / "report.html").read_text()
    import shlex

    from report_fields import header_fields

    f = header_fields((out / "report.html").read_text())  # the report's header: the command as typed, the inputs
    assert f["command"] == shlex.join(["thermogrammetry", "texture", str(survey), "--mesh", str(survey / "mesh.obj"), "-o",
                                       str(out), "--unit", "C", "--texel-size", "0.05"])
    assert f"mesh: {(survey / 'mesh.obj').resolve()}" in f["inputs"] and f["inputs"].endswith("obj")
    assert f["inputs"].startswith(f"{len(views)} images of the survey in {survey.resolve()}")
    assert "map_Kd textured.png" in (out / "textured.mtl").read_text()


def test_cli_clean_radius_follows_the_pose_uncertainty(cli_out, tmp_path):
    """cameras.json with rotation σ (as survey writes it): the clean-pixel radius becomes 3 σ in pixels."""
    import shutil

    from thermogrammetry.cli.main import main

    survey, _ = cli_out
    s2 = tmp_path / "survey"
    shutil.copytree(survey, s2)
    d = json.loads((s2 / "cameras.json").read_text())
    for im in d["images"]:
        im["rotation_std_deg"] = [0.1, 0.2, 0.15]
    (s2 / "cameras.json").write_text(json.dumps(d))
    out = tmp_path / "out"
    assert main(["texture", str(s2), "--mesh", str(s2 / "mesh.obj"), "-o", str(out), "--texel-size", "0.1"]) == 0
    cr = json.loads((out / "texture.json").read_text())["clean_radius_px"]
    assert cr["value"] == int(np.ceil(3 * 285.0 * np.deg2rad(0.2))) == 3 and "σ" in cr["reason"]  # median of per-view max σ
    ref = json.loads((cli_out[1] / "texture.json").read_text())["clean_radius_px"]
    assert ref == {"value": 1, "reason": "default"}  # true poses without σ: unchanged


def test_cli_texture_levelling_offsets_reported(cli_out, tmp_path):
    from thermogrammetry.cli.main import main

    survey, _ = cli_out
    out = tmp_path / "lev"
    assert main(["texture", str(survey), "--mesh", str(survey / "mesh.obj"), "-o", str(out), "--levelling", "offsets",
                 "--texel-size", "0.1"]) == 0
    d = json.loads((out / "texture.json").read_text())
    assert d["values_altered"] is True and d["offsets"][d["offsets_fixed_image"]] == 0.0
    assert max(abs(v) for v in d["offsets"].values()) < 0.02  # noise-free images agree: offsets ~ 0


def test_cli_texture_bad_input(cli_out, tmp_path, capsys):
    from thermogrammetry.cli.main import main

    survey, _ = cli_out
    assert main(["texture", str(survey), "--mesh", str(tmp_path / "nope.obj"), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "nope.obj" in err and "Traceback" not in err
    (tmp_path / "empty").mkdir()  # a folder without cameras.json (OUT beside it: an OUT inside it is refused first)
    assert main(["texture", str(tmp_path / "empty"), "--mesh", str(survey / "mesh.obj"), "-o", str(tmp_path / "o")]) == 2
    assert "cameras.json" in capsys.readouterr().err
    assert main(["texture", str(survey), "--mesh", str(survey / "mesh.obj"), "-o", str(tmp_path / "o"), "--levelling", "blend"]) == 2
    capsys.readouterr()
    # a mesh in another coordinate system (here: LV95 coordinates against a local survey) meets no image: exit 2
    import trimesh

    m = trimesh.load(survey / "mesh.obj", process=False)
    m.vertices += [2_600_000.0, 1_200_000.0, 0.0]
    far = tmp_path / "far.obj"
    m.export(far)
    assert main(["texture", str(survey), "--mesh", str(far), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "far.obj" in err and "no face of the mesh" in err and "camera centres" in err and "Traceback" not in err
    assert "2600" in err  # the mesh extent in the message
    assert not (tmp_path / "o").exists()
    # a mesh above the face cap is refused before any work, naming the file, its count and the cap
    n_faces = len(m.faces)
    assert main(["texture", str(survey), "--mesh", str(survey / "mesh.obj"), "-o", str(tmp_path / "o"),
                 "--max-faces", str(n_faces - 1)]) == 2
    err = capsys.readouterr().err
    assert "mesh.obj" in err and f"{n_faces} triangles, above the cap of {n_faces - 1}" in err and "--max-faces" in err
    assert not (tmp_path / "o").exists()
    assert main(["texture", str(survey), "--mesh", str(survey / "mesh.obj"), "-o", str(tmp_path / "o"),
                 "--max-faces", "0"]) == 2
    assert "max_faces=0" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------- browser
def _chromium():
    import shutil

    for name in ("chromium-headless-shell", "chromium", "chromium-browser", "google-chrome", "headless_shell"):
        p = shutil.which(name)
        if p:
            return p
    return None


def test_textured_glb_renders_in_headless_chromium(cli_out, tmp_path):
    """The GLB in a real browser: viewer.html (plain WebGL, GLB embedded) in headless Chromium with
    SwiftShader; the screenshot must show textured pixels (palette colours) over the green background."""
    import os
    import shutil
    import subprocess

    import cv2

    exe = _chromium()
    if exe is None:
        pytest.skip("no Chromium binary on PATH (apt-get install chromium-headless-shell); the GLB browser check needs one")
    survey, out = cli_out
    shot = tmp_path / "texture_browser.png"
    cmd = [exe, "--headless", "--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
           "--window-size=800,600", "--virtual-time-budget=5000", f"--screenshot={shot}", (out / "viewer.html").as_uri()]
    subprocess.run(cmd, cwd=tmp_path, capture_output=True, timeout=120)
    assert shot.is_file(), "chromium wrote no screenshot"
    img = cv2.cvtColor(cv2.imread(str(shot)), cv2.COLOR_BGR2RGB).astype(int)
    green = (img[..., 0] < 30) & (img[..., 1] > 225) & (img[..., 2] < 30)
    grey = np.all(np.abs(img - 128) <= 3, axis=-1)  # untextured texels in the preview
    textured = ~green & ~grey
    assert green.mean() > 0.3  # the background is there: the page drew a model, not a full-screen quad
    assert textured.mean() > 0.03
    # the textured pixels carry the palette's range of colours (not one flat colour)
    lum = img[textured].mean(axis=1)
    assert np.percentile(lum, 95) - np.percentile(lum, 5) > 60
    keep = os.environ.get("THERMOGRAMMETRY_SCREENSHOT_DIR")
    if keep:
        shutil.copy(shot, keep)


def test_majority_source_equals_a_dense_count():
    from thermogrammetry.products.texture import majority_source

    rng = np.random.default_rng(3)
    n_faces, K = 500, 7
    face = rng.integers(0, n_faces - 50, 20_000)  # the last 50 faces have no texel
    src = np.minimum(rng.integers(0, K, len(face)), rng.integers(0, K, len(face)))  # skewed: ties and majorities
    cnt = np.zeros((n_faces, K), np.int64)
    np.add.at(cnt, (face, src), 1)
    want = np.where(cnt.sum(axis=1) > 0, np.argmax(cnt, axis=1), -1)  # argmax: ties to the smallest index
    assert np.array_equal(majority_source(face, src, n_faces), want)
    assert np.all(majority_source(np.zeros(0, int), np.zeros(0, int), 4) == -1)


def test_large_faces_seen_only_in_part_are_textured():
    """Two 40 x 40 m ground triangles (a CAD-like ground of one square) seen by a camera 1.7 m above them, looking
    along their common diagonal, 15 deg down: both centroids are seen at > 80 deg (beyond max_angle_deg) and outside
    the image, yet the near ground on both sides of the diagonal is in view at < 75 deg. Scored at their centroids
    only, neither face was textured (0 texels); now both are, and every texel equals the image at its own projection
    (the image is linear in the pixel coordinates, so bilinear sampling is exact up to float32) and was seen within
    max_angle_deg."""
    from scipy.spatial.transform import Rotation

    from thermogrammetry import Camera
    from thermogrammetry.geometry import Pose

    V = np.array([[-20.0, -20, 0], [20, -20, 0], [20, 20, 0], [-20, 20, 0]])
    F = np.array([[0, 1, 2], [0, 2, 3]])
    cam = Camera("opencv", (160, 120), dict(fx=150.0, fy=150.0, cx=79.5, cy=59.5, k1=-0.1))
    level = np.column_stack([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # columns: camera axes in world, looking +y
    R_wc = Rotation.from_euler("z", -45, degrees=True).as_matrix() @ Rotation.from_euler("x", -15, degrees=True).as_matrix() @ level
    R = R_wc.T
    C = np.array([-12.0, -12.0, 1.7])
    pose = Pose(R, -R @ C)
    u, v = np.meshgrid(np.arange(160.0), np.arange(120.0))
    img = (290.0 + 0.05 * u - 0.03 * v).astype(np.float32)
    res = texture_mesh(V, F, [TextureView("g", cam, pose, img)], TextureConfig(texel_size_m=0.1, max_texture_px=1024))
    cen = V[F].mean(axis=1)
    assert np.all(np.degrees(np.arccos(1.7 / np.linalg.norm(cen - C, axis=1))) > 80)  # the scene is as described
    xy_c = cam.project(cen @ R.T + pose.t)
    assert np.all((xy_c[:, 0] < 0) | (xy_c[:, 0] > 159))
    assert res.faces_textured.all()
    sel = res.texel_selection
    ok = sel.source >= 0
    assert np.bincount(res.texels.face[ok], minlength=2).min() > 500
    xy = cam.project(res.texels.points[ok] @ R.T + pose.t)
    expect = 290.0 + 0.05 * xy[:, 0] - 0.03 * xy[:, 1]
    assert np.max(np.abs(sel.temperature_k[ok] - expect)) < 2e-3
    assert np.max(sel.angle_deg[ok]) <= 75.0 + 1e-9


def test_min_clean_radius_fallback_textures_silhouette_faces(scene, views):
    """With a wide clean-pixel radius (the CLI widens it by the pose σ), small faces along a silhouette have no texel
    clean at that radius and stayed untextured although visible (on a held-out ring with survey poses: 40 of 744
    visible faces at radius 4). ``min_clean_radius_px`` gives exactly those faces the texels clean at the smaller
    radius; every other texel is unchanged, and the fallback texels equal the noise-free truth (true poses) as
    closely as any other texel."""
    wide = texture_mesh(scene.vertices, scene.faces, views, TextureConfig(texel_size_m=TEXEL_M, clean_radius_px=4))
    fb = texture_mesh(scene.vertices, scene.faces, views,
                      TextureConfig(texel_size_m=TEXEL_M, clean_radius_px=4, min_clean_radius_px=1))
    gained = fb.faces_textured & ~wide.faces_textured
    assert gained.sum() > 0 and np.array_equal(gained, fb.face_min_radius)
    share_wide, share_fb = np.mean(wide.faces_textured[wide.face_visible]), np.mean(fb.faces_textured[fb.face_visible])
    assert share_fb > share_wide and share_fb >= 0.98
    a, b = wide.texel_selection, fb.texel_selection
    was = a.source >= 0
    assert np.array_equal(a.source[was], b.source[was]) and np.array_equal(a.temperature_k[was], b.temperature_k[was])
    new = (b.source >= 0) & ~was
    assert np.all(fb.face_min_radius[fb.texels.face[new]])
    C = np.array([v.pose.center for v in views])[b.source[new]]
    err = b.temperature_k[new] - apparent_temperature(scene, fb.texels.points[new], fb.texels.face[new], C)
    assert new.sum() > 100 and np.max(np.abs(err)) < 0.05
    assert fb.summary()["faces_textured_at_min_clean_radius"] == int(gained.sum())
    # down to 0 px (what the verb asks): the radii are tried from the largest down, so the faces gained at 1 px or above
    # keep texels at least as clean, and no face textured before is lost
    fb0 = texture_mesh(scene.vertices, scene.faces, views,
                       TextureConfig(texel_size_m=TEXEL_M, clean_radius_px=4, min_clean_radius_px=0))
    assert np.all(fb0.faces_textured[fb.faces_textured])
    assert np.mean(fb0.faces_textured[fb0.face_visible]) >= share_fb
    c = fb0.texel_selection
    assert np.array_equal(a.source[was], c.source[was]) and np.array_equal(a.temperature_k[was], c.temperature_k[was])
    new0 = (c.source >= 0) & ~was & (b.source >= 0)
    err0 = c.temperature_k[new0] - apparent_temperature(scene, fb0.texels.points[new0], fb0.texels.face[new0],
                                                        np.array([v.pose.center for v in views])[c.source[new0]])
    assert new0.sum() > 100 and np.max(np.abs(err0)) < 0.05


@pytest.mark.parametrize("radius", [1, 4])
def test_clean_pixel_shortcut_equals_the_pixel_by_pixel_test(scene, views, radius):
    """usable_in_view passes texels whose whole window of pixels sees their own plane (or face) without testing each
    pixel: the same verdict as testing every pixel of the window (the rule as first written)."""
    from dataclasses import replace

    from thermogrammetry.products.texture import (_face_geometry, _intersector, build_atlas, pixel_surfaces, plane_ids,
                                                  rasterize_atlas, usable_in_view)

    V, F = np.asarray(scene.vertices, float), np.asarray(scene.faces, np.int64)
    cfg = TextureConfig(texel_size_m=0.08, clean_radius_px=radius)
    tx = rasterize_atlas(build_atlas(V, F, 0.08), V, F)
    inter = _intersector(V, F)
    planes = plane_ids(V, F)
    assert len(np.unique(planes)) < len(F)  # walls of several coplanar triangles: the plane shortcut has work to do
    normals, _, _ = _face_geometry(V, F)
    n_checked = 0
    for view in views[::7]:
        with_planes = pixel_surfaces(inter, V, F, view, planes)
        faces_only = replace(with_planes, plane_of_face=None)
        u1, xy, *_ = usable_in_view(inter, V, F, view, with_planes, tx.points, tx.face, cfg)
        u2, *_ = usable_in_view(inter, V, F, view, faces_only, tx.points, tx.face, cfg)
        # reference: conditions 1-3 from a zero-radius call, then every pixel of the window tested
        base, *_ = usable_in_view(inter, V, F, view, faces_only, tx.points, tx.face, replace(cfg, clean_radius_px=0,
                                                                                              surface_tol_m=np.inf,
                                                                                              normal_tol_deg=180.0))
        idx = np.flatnonzero(base)
        w, h = view.camera.image_size
        x0, y0 = np.floor(xy[idx, 0]).astype(int), np.floor(xy[idx, 1]).astype(int)
        n = normals[tx.face[idx]]
        d0 = np.einsum("ij,ij->i", n, tx.points[idx])
        ref = np.zeros(len(tx.points), bool)
        ok = np.ones(len(idx), bool)
        for dy in range(-radius, 2 + radius):
            for dx in range(-radius, 2 + radius):
                yy, xx = np.clip(y0 + dy, 0, h - 1), np.clip(x0 + dx, 0, w - 1)
                p = with_planes.points_at(yy, xx)
                pf = with_planes.face[yy, xx]
                off = np.abs(np.einsum("ij,ij->i", n, p) - d0)
                agree = np.einsum("ij,ij->i", n, normals[np.maximum(pf, 0)]) >= np.cos(np.deg2rad(cfg.normal_tol_deg))
                ok &= np.isfinite(off) & (off <= cfg.surface_tol_m) & (pf >= 0) & agree
        ref[idx] = ok
        np.testing.assert_array_equal(u1, ref)
        np.testing.assert_array_equal(u2, ref)
        n_checked += int(ref.sum()) + int((base & ~ref).sum())
    assert n_checked > 10_000


def test_cli_texture_photometric_fit_recorded_and_choices(cli_out, tmp_path, capsys):
    """True poses and noise-free frames: the photometric refinement finds nothing worth a change and changes nothing
    (texture.json says why; no cameras_fitted.json: the poses used are those of cameras.json). ``--fit-poses mesh``
    skips it and says so; an unknown choice lists the valid ones."""
    from thermogrammetry.cli.main import main

    survey, out = cli_out
    d = json.loads((out / "texture.json").read_text())
    ph = d["photometric_fit"]
    assert ph["applied"] is False and "did not come to agree better" in ph["reason"]
    # measured 0.000872 -> 0.000867 K (rotations would move by 0.006 deg median): less than the 2 % asked
    assert ph["robust_sigma_after"] > 0.98 * ph["robust_sigma_before"] and ph["views"] == len(d["index"])
    assert not (out / "cameras_fitted.json").exists()
    o2 = tmp_path / "mesh_only"
    assert main(["texture", str(survey), "--mesh", str(survey / "mesh.obj"), "-o", str(o2), "--texel-size", "0.1",
                 "--fit-poses", "MESH"]) == 0
    assert json.loads((o2 / "texture.json").read_text())["photometric_fit"] == {"applied": False, "reason": "mesh (fit_poses)"}
    assert main(["texture", str(survey), "--mesh", str(survey / "mesh.obj"), "-o", str(tmp_path / "x"),
                 "--fit-poses", "photo"]) == 2
    assert "auto, mesh, off" in capsys.readouterr().err
