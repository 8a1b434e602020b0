"""``thermogrammetry texture`` on frames in raw sensor counts (DJI R-JPEGs without the closed SDK, Workswell TIFFs).

A flat wall (y = 0, 4 m × 3 m, normal towards −y) seen by three pinhole cameras 5 m away (160 × 120 px,
f = 150 px: 3.3 cm pixels). Each frame is uint16 counts of one world field, sampled at the pixel centres'
rays: ``rint(20000 + 400 sin(1.3 x) + 250 cos(1.7 z))`` with a constant patch of 23456 counts over
x ∈ [1.5, 2.5] m, z ∈ [1, 2] m. Poses are exact (no estimation), so a texel must equal the bilinear sample of
its source frame at its own projection: that is recomputed here independently (float64, from the uint16
frame) and compared within float32 rounding (|value| < 2.4e4: one ulp is 0.002 count); inside the constant
patch, where the four pixels of the bilinear footprint are equal, the texel equals the integer count exactly.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

W, H, FOCAL = 160, 120, 150.0
PATCH = 23456


def _field(x, z):
    v = np.rint(20000 + 400 * np.sin(1.3 * x) + 250 * np.cos(1.7 * z))
    return np.where((x >= 1.5) & (x <= 2.5) & (z >= 1.0) & (z <= 2.0), PATCH, v)


def _camera():
    from thermogrammetry.camera.camera import Camera

    return Camera("pinhole", (W, H), dict(fx=FOCAL, fy=FOCAL, cx=(W - 1) / 2, cy=(H - 1) / 2))


def _wall_mesh(nx=8, nz=6):
    xs, zs = np.linspace(0, 4, nx + 1), np.linspace(0, 3, nz + 1)
    X, Z = np.meshgrid(xs, zs)
    V = np.c_[X.ravel(), np.zeros(X.size), Z.ravel()]
    F = []
    for j in range(nz):
        for i in range(nx):
            a = j * (nx + 1) + i
            b, c, d = a + 1, a + nx + 1, a + nx + 2
            F += [(a, b, c), (b, d, c)]  # e_x × e_z = −y: normals towards the cameras
    return V, np.array(F)


def _render_counts(cam, pose, offset=0):
    """uint16 counts of the wall field seen through each pixel centre (the ray's hit on y = 0)."""
    gy, gx = np.mgrid[0:H, 0:W].astype(float)
    d = np.stack([(gx - (W - 1) / 2) / FOCAL, (gy - (H - 1) / 2) / FOCAL, np.ones_like(gx)], -1) @ pose.R
    C = pose.center
    t = -C[1] / d[..., 1]
    P = C + t[..., None] * d
    return (_field(P[..., 0], P[..., 2]) + offset).astype(np.uint16)


def _poses():
    from thermogrammetry.geometry import Pose

    return [Pose.look_at((x, -5.0, 1.5), (x, 0.0, 1.5)) for x in (1.2, 2.0, 2.8)]


def _write(folder, *, unit="counts", offsets=(0, 0, 0), extra_k=False):
    import tifffile

    from thermogrammetry.io.oriented import OrientedCameras, OrientedImage

    (folder / "frames").mkdir(parents=True)
    cam = _camera()
    ims = []
    for k, (pose, off) in enumerate(zip(_poses(), offsets)):
        img = _render_counts(cam, pose, off)
        if unit == "K":
            img = img.astype(np.float32) / 100.0
        tifffile.imwrite(folder / "frames" / f"t{k}.tif", img)
        ims.append(OrientedImage(f"t{k}", "thermal", pose.R, pose.t, frame=f"frames/t{k}.tif", unit=unit))
        if extra_k:  # the same station also in kelvin: a survey with both units
            tifffile.imwrite(folder / "frames" / f"k{k}.tif", img.astype(np.float32) / 100.0)
            ims.append(OrientedImage(f"k{k}", "thermal", pose.R, pose.t, frame=f"frames/k{k}.tif", unit="K"))
    OrientedCameras({"thermal": cam}, ims).save(folder / "cameras.json")
    V, F = _wall_mesh()
    lines = [f"v {x} {y} {z}" for x, y, z in V] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in F]
    (folder / "mesh.obj").write_text("\n".join(lines) + "\n")
    return folder


def _bilinear64(img, xy):
    img = np.asarray(img, np.float64)
    x0 = np.floor(xy[:, 0]).astype(int)
    y0 = np.floor(xy[:, 1]).astype(int)
    fx, fy = xy[:, 0] - x0, xy[:, 1] - y0
    a = img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx
    b = img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx
    return a * (1 - fy) + b * fy, (img[y0, x0] == img[y0, x0 + 1]) & (img[y0, x0] == img[y0 + 1, x0]) & (
        img[y0, x0] == img[y0 + 1, x0 + 1])


def _gdal_md(path) -> str:
    import tifffile

    with tifffile.TiffFile(path) as tf:
        return str(tf.pages[0].tags[42112].value)


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    return _write(tmp_path_factory.mktemp("counts_survey"))


@pytest.fixture(scope="module")
def cli_out(survey, tmp_path_factory):
    from thermogrammetry.cli.main import main

    out = tmp_path_factory.mktemp("counts_tex") / "out"
    rc = main(["texture", str(survey), "--mesh", str(survey / "mesh.obj"), "-o", str(out), "--texel-size", "0.02"])
    assert rc == 0
    return out


def test_cli_prints_a_progress_line_for_each_texturing_stage(survey, tmp_path, capsys):
    """Every stage that grows with the mesh or the images reports as it goes (plain lines in a log), each ending at its
    total: the photometric fit and the ray casting per view (3), the texels (texture.json's texels_total) and the
    face corners of the per-vertex values (3 per face)."""
    from thermogrammetry.cli.main import main

    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["texture", str(survey), "--mesh", str(survey / "mesh.obj"), "-o", str(out), "--texel-size", "0.02"]) == 0
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("texture: ")]
    d = json.loads((out / "texture.json").read_text())
    last = {}
    for ln in lines:
        stage, frac = ln[len("texture: "):].rsplit(" ", 1)
        last.setdefault(stage, []).append(tuple(int(x) for x in frac.split("/")))
    assert list(last) == ["photometric pose fit (views)", "visibility (views)", "texels", "vertex corners"], lines
    assert last["visibility (views)"] == [(0, 3), (1, 3), (2, 3), (3, 3)]
    assert last["photometric pose fit (views)"][-1] == (3, 3)
    assert last["texels"][-1] == (d["texels_total"], d["texels_total"]) and d["texels_total"] > 10_000
    assert last["vertex corners"][-1] == (3 * d["faces_total"], 3 * d["faces_total"]) and d["faces_total"] == 96


@pytest.fixture(scope="module")
def library_result(survey):
    from thermogrammetry.io.oriented import OrientedCameras
    from thermogrammetry.pipeline.texture import load_views, read_mesh
    from thermogrammetry.products.texture import TextureConfig, texture_mesh

    cams = OrientedCameras.load(survey)
    views, skipped = load_views(cams)
    assert [v.name for v in views] == ["t0", "t1", "t2"] and skipped == []
    V, F = read_mesh(survey / "mesh.obj")
    return texture_mesh(V, F, views, TextureConfig(texel_size_m=0.02)), views


def test_texels_are_the_frames_counts_as_sampled(library_result):
    res, views = library_result
    sel, tx = res.texel_selection, res.texels
    ok = np.flatnonzero(sel.source >= 0)
    assert len(ok) > 0.9 * len(sel.source) > 20_000  # the wall is inside all three frames
    exact_patch = 0
    for k, v in enumerate(views):
        idx = ok[sel.source[ok] == k]
        assert len(idx) > 1000
        Xc = tx.points[idx] @ v.pose.R.T + v.pose.t
        xy = v.camera.project(Xc)
        expect, flat = _bilinear64(v.image_k, xy)  # image_k holds the uint16 counts as float32 (exact)
        got = res.temperature_k[tx.rc[idx, 0], tx.rc[idx, 1]]
        assert np.max(np.abs(got - expect)) <= 0.004  # float32 rounding of a 2e4 value (ulp 0.002)
        patch = flat & (v.image_k[np.floor(xy[:, 1]).astype(int), np.floor(xy[:, 0]).astype(int)] == PATCH)
        assert np.all(got[patch] == PATCH)  # equal footprint pixels: the integer count, bit for bit
        exact_patch += int(patch.sum())
    # the 1 m² patch holds 2500 texels of 2 cm; those within a pixel (3.3 cm) of its edge have a mixed footprint
    assert 2000 < exact_patch <= 2500
    # value range: the field's counts, not temperatures
    fin = res.temperature_k[np.isfinite(res.temperature_k)]
    assert 19_300 <= fin.min() and fin.max() <= PATCH


def test_cli_writes_counts_labelled_as_counts(cli_out, library_result):
    import tifffile
    import trimesh
    from plyfile import PlyData
    from PIL import Image

    res, views = library_result
    out = cli_out
    for f in ("textured.glb", "textured.obj", "textured.mtl", "textured.png", "temperature_texture.tif", "source_texture.tif",
              "vertices.ply", "texture.json", "report.html", "temperature_texture_u16.tif", "angle_texture.tif", "viewer.html"):
        assert (out / f).is_file(), f
    d = json.loads((out / "texture.json").read_text())
    assert d["unit"] == "counts" and d["quantity"] == "raw_counts" and d["values_altered"] is False
    assert "raw sensor counts" in d["values_note"] and d["skipped"] == []
    assert d["index"] == {"0": "t0", "1": "t1", "2": "t2"} and d["faces_textured"] == d["faces_total"] == 96
    # the float texture: the library's counts, bit for bit, labelled counts (never K / °C)
    t = tifffile.imread(out / "temperature_texture.tif")
    src = tifffile.imread(out / "source_texture.tif")
    assert t.dtype == np.float32 and t.shape == res.temperature_k.shape
    np.testing.assert_array_equal(t, res.temperature_k)
    np.testing.assert_array_equal(src, res.source)
    md = _gdal_md(out / "temperature_texture.tif")
    assert "counts" in md and "raw_counts" in md and ">K<" not in md and "°C" not in md and "temperature (" not in md
    # 16-bit: code = round(count), scale 1 / offset 0, 0 = no texel
    m = d["uint16_mapping"]
    assert (m["scale"], m["offset"], m["unit"], m["nodata_code"]) == (1.0, 0.0, "counts", 0)
    codes = tifffile.imread(out / "temperature_texture_u16.tif")
    assert codes.dtype == np.uint16
    assert np.all(codes[src < 0] == 0) and np.all(codes[src >= 0] > 0)
    assert np.max(np.abs(codes[src >= 0] * m["scale"] + m["offset"] - t[src >= 0])) <= 0.5
    md16 = _gdal_md(out / "temperature_texture_u16.tif")
    assert "counts" in md16 and ">K<" not in md16
    # per-vertex counts under their own name, as in the dense cloud
    ply = PlyData.read(str(out / "vertices.ply"))
    names = [p.name for p in ply["vertex"].properties]
    assert "raw_counts" in names and "temperature_k" not in names
    vc = np.asarray(ply["vertex"]["raw_counts"])
    # the 7 × 5 inner vertices of the 9 × 7 grid; a border vertex's footprint reaches past the mesh (not clean)
    assert np.isfinite(vc).sum() == 35 and 19_300 <= np.nanmin(vc) and np.nanmax(vc) <= PATCH
    np.testing.assert_array_equal(vc, res.vertex_temperature_k.astype(np.float32))
    # report and previews: the colour scale says raw counts, never °C
    rep = (out / "report.html").read_text()
    assert "raw counts" in rep and "°C" not in rep
    png = Image.open(out / "textured.png")
    assert png.info["thermogrammetry:unit"] == "counts" and "raw counts" in png.info["Description"]
    pal = d["preview_palette"]
    assert pal["unit"] == "counts" and 19_300 <= pal["min"] < pal["max"] <= PATCH
    glb = trimesh.load(out / "textured.glb", force="mesh")
    assert len(glb.faces) == 96
    assert b"raw counts" in (out / "textured.glb").read_bytes()  # the palette's label in the glTF extras


@pytest.mark.parametrize("unit", ["C", "K"])
def test_cli_refuses_a_temperature_unit_for_counts(survey, tmp_path, capsys, unit):
    from thermogrammetry.cli.main import main

    rc = main(["texture", str(survey), "--mesh", str(survey / "mesh.obj"), "-o", str(tmp_path / "o"), "--unit", unit,
               "--texel-size", "0.05"])
    assert rc == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "raw counts (no documented conversion)" in err and "a temperature unit cannot be applied" in err
    assert "Traceback" not in err and not (tmp_path / "o" / "texture.json").exists()


def test_cli_refuses_correct_for_counts(survey, tmp_path, capsys):
    from thermogrammetry.cli.main import main

    rc = main(["texture", str(survey), "--mesh", str(survey / "mesh.obj"), "-o", str(tmp_path / "o"), "--correct",
               "--texel-size", "0.05"])
    assert rc == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "--correct" in err and "raw counts" in err and "needs temperatures" in err


def test_levelling_offsets_in_counts(tmp_path):
    """Frame t1 reads 40 counts high: the offsets (counts) put it back, relative to the image holding most texels."""
    from thermogrammetry.cli.main import main

    s = _write(tmp_path / "s", offsets=(0, 40, 0))
    out = tmp_path / "lev"
    assert main(["texture", str(s), "--mesh", str(s / "mesh.obj"), "-o", str(out), "--levelling", "offsets",
                 "--texel-size", "0.05"]) == 0
    d = json.loads((out / "texture.json").read_text())
    assert d["unit"] == "counts" and d["values_altered"] is True
    off, fixed = d["offsets"], d["offsets_fixed_image"]
    inj = {"t0": 0, "t1": 40, "t2": 0}
    for name, o in off.items():
        # o_k = -(inj_k - inj_fixed); the overlaps agree to interpolation error (field gradient <= 17 counts/px)
        assert abs(o - (-(inj[name] - inj[fixed]))) < 1.0, (name, o, fixed)
    before, after = d["offsets_rms_before_after_counts"]
    assert after < 3.0 < 20.0 < before
    assert "offsets_rms_before_after_k" not in d
    rep = (out / "report.html").read_text()
    assert "offset (counts)" in rep and "°C" not in rep


def test_kelvin_frames_win_over_counts(tmp_path):
    """Both units in one survey: the kelvin frames are textured, the count frames listed as skipped with the reason."""
    from thermogrammetry.cli.main import main

    s = _write(tmp_path / "s", extra_k=True)
    out = tmp_path / "o"
    assert main(["texture", str(s), "--mesh", str(s / "mesh.obj"), "-o", str(out), "--texel-size", "0.05"]) == 0
    d = json.loads((out / "texture.json").read_text())
    assert d["unit"] == "K" and set(d["index"].values()) == {"k0", "k1", "k2"}
    sk = {x["image"]: x["reason"] for x in d["skipped"]}
    assert set(sk) == {"t0", "t1", "t2"} and all("never mixes" in r for r in sk.values())
    from plyfile import PlyData

    assert "temperature_k" in [p.name for p in PlyData.read(str(out / "vertices.ply"))["vertex"].properties]
    assert 190 < np.nanmin(np.asarray(PlyData.read(str(out / "vertices.ply"))["vertex"]["temperature_k"])) < 240


def test_display_numbers_only_are_refused(tmp_path, capsys):
    from thermogrammetry.cli.main import main

    s = _write(tmp_path / "s", unit="dn")
    assert main(["texture", str(s), "--mesh", str(s / "mesh.obj"), "-o", str(tmp_path / "o")]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "no usable thermal image in kelvin or raw counts" in err and "'dn'" in err


def test_mesh_facing_away_is_reversed_and_said(tmp_path):
    """A plane whose triangles' normals point away from every camera (a plane fitted to a cloud has an arbitrary
    normal sign): the winding is reversed, recorded, and the texture is the same as with the right winding."""
    from thermogrammetry.cli.main import main

    s = _write(tmp_path / "s")
    V, F = _wall_mesh()
    lines = [f"v {x} {y} {z}" for x, y, z in V] + [f"f {a + 1} {c + 1} {b + 1}" for a, b, c in F]
    (s / "flipped.obj").write_text("\n".join(lines) + "\n")
    d = {}
    for m in ("mesh", "flipped"):
        assert main(["texture", str(s), "--mesh", str(s / f"{m}.obj"), "-o", str(tmp_path / m), "--texel-size", "0.05"]) == 0
        d[m] = json.loads((tmp_path / m / "texture.json").read_text())
    assert "mesh_winding" not in d["mesh"]
    assert d["flipped"]["mesh_winding"]["reversed"] is True and "reversed" in d["flipped"]["mesh_winding"]["reason"]
    assert d["flipped"]["faces_textured"] == d["mesh"]["faces_textured"] == 96
    assert d["flipped"]["texels_textured"] == d["mesh"]["texels_textured"]


def _write_rig(folder, *, kelvin_first=False):
    """Rig mode: RGB images oriented (cameras.json), thermal frames in a rig file. The thermal camera sits 8 cm to
    the right of the RGB camera, turned 1° about its y axis; its frames (uint16 counts) are rendered at the poses the
    rig gives (seed 002 eq. 4-5). ``kelvin_first``: the first frame is a float32 TIFF (kelvin) instead."""
    import tifffile

    from thermogrammetry.geometry import Pose
    from thermogrammetry.geometry.rotations import matrix_from_axis_angle
    from thermogrammetry.io.oriented import OrientedCameras, OrientedImage
    from thermogrammetry.products.texture import thermal_poses_from_rig

    (folder / "thermal").mkdir(parents=True)
    cam = _camera()
    R_rel = matrix_from_axis_angle(np.array([0.0, np.radians(1.0), 0.0]))
    rel = Pose(R_rel, -R_rel @ np.array([0.08, 0.0, 0.0]))
    rgb_poses = [Pose.look_at((x, -5.0, 1.5), (x, 0.0, 1.5)) for x in (1.1, 1.9, 2.7)]
    rgb = [OrientedImage(f"rgb{k}", "rgb", p.R, p.t, frame=f"rgb{k}.jpg", unit="dn") for k, p in enumerate(rgb_poses)]
    OrientedCameras({"rgb": cam}, rgb).save(folder / "cameras.json")
    frames = {}
    for k, pose in enumerate(thermal_poses_from_rig(rgb_poses, rel)):
        img = _render_counts(cam, pose)
        if kelvin_first and k == 0:
            img = img.astype(np.float32) / 100.0
        tifffile.imwrite(folder / "thermal" / f"t{k}.tif", img)
        frames[f"rgb{k}"] = f"thermal/t{k}.tif"
    rig = {"format": "thermogrammetry/rig", "cam_thermal_from_cam_rgb": {"R": rel.R.tolist(), "t": rel.t.tolist()},
           "thermal_camera": cam.to_dict(), "frames": frames}
    (folder / "rig.json").write_text(json.dumps(rig))
    V, F = _wall_mesh()
    (folder / "mesh.obj").write_text("\n".join([f"v {x} {y} {z}" for x, y, z in V]
                                               + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in F]) + "\n")
    return folder, rel, rgb_poses


def test_rig_mode_reads_count_frames_as_counts(tmp_path):
    """Rig mode with uint16 frames: the texture holds counts labelled as counts (it took them as kelvin before),
    each texel the bilinear sample of its frame at its projection through the rig's thermal pose."""
    import tifffile

    from thermogrammetry.cli.main import main
    from thermogrammetry.io.oriented import OrientedCameras
    from thermogrammetry.pipeline.texture import load_rig_views, read_mesh
    from thermogrammetry.products.texture import TextureConfig, texture_mesh, thermal_poses_from_rig

    folder, rel, rgb_poses = _write_rig(tmp_path / "rig")
    views, skipped, unit = load_rig_views(OrientedCameras.load(folder), json.loads((folder / "rig.json").read_text()))
    assert unit == "counts" and skipped == [] and len(views) == 3
    for v, p in zip(views, thermal_poses_from_rig(rgb_poses, rel)):
        np.testing.assert_allclose(v.pose.R, p.R, atol=1e-12)
        np.testing.assert_allclose(v.pose.t, p.t, atol=1e-12)
    V, F = read_mesh(folder / "mesh.obj")
    res = texture_mesh(V, F, views, TextureConfig(texel_size_m=0.02))
    sel, tx = res.texel_selection, res.texels
    ok = np.flatnonzero(sel.source >= 0)
    assert len(ok) > 20_000
    for k, v in enumerate(views):
        idx = ok[sel.source[ok] == k]
        xy = v.camera.project(tx.points[idx] @ v.pose.R.T + v.pose.t)
        expect, _ = _bilinear64(tifffile.imread(folder / "thermal" / f"t{k}.tif"), xy)
        assert np.max(np.abs(res.temperature_k[tx.rc[idx, 0], tx.rc[idx, 1]] - expect)) <= 0.004
    out = tmp_path / "out"
    assert main(["texture", str(folder), "--mesh", str(folder / "mesh.obj"), "-o", str(out), "--rig",
                 str(folder / "rig.json"), "--texel-size", "0.02"]) == 0
    d = json.loads((out / "texture.json").read_text())
    assert d["unit"] == "counts" and d["quantity"] == "raw_counts"
    t = tifffile.imread(out / "temperature_texture.tif")
    fin = t[np.isfinite(t)]
    assert 19_300 <= fin.min() and fin.max() <= PATCH  # counts, not kelvin
    assert "°C" not in (out / "report.html").read_text()
    # the photometric refinement runs in rig mode too; on these three views of flat count patches it finds no better
    # agreement (measured 0.11 -> 0.89 counts) and changes nothing; rig mode never writes cameras_fitted.json
    ph = d["photometric_fit"]
    assert ph["applied"] is False and "did not come to agree better" in ph["reason"] and "poses" not in ph
    assert not (out / "cameras_fitted.json").exists()
    assert main(["texture", str(folder), "--mesh", str(folder / "mesh.obj"), "-o", str(tmp_path / "outC"), "--rig",
                 str(folder / "rig.json"), "--unit", "C"]) == 2  # no temperature unit for counts


def test_rig_mode_never_mixes_kelvin_and_count_frames(tmp_path):
    """One float32 frame (kelvin, as the rig schema documents for float TIFFs without a unit) and two uint16
    frames: the kelvin frame is used, the count frames are listed as skipped with the reason."""
    from thermogrammetry.io.oriented import OrientedCameras
    from thermogrammetry.pipeline.texture import load_rig_views

    folder, _, _ = _write_rig(tmp_path / "rig", kelvin_first=True)
    views, skipped, unit = load_rig_views(OrientedCameras.load(folder), json.loads((folder / "rig.json").read_text()))
    assert unit == "K" and [v.name for v in views] == ["rgb0:thermal"]
    assert [n for n, _ in skipped] == ["rgb1", "rgb2"] and all("never mixes" in r for _, r in skipped)
    assert 193.0 <= float(np.nanmin(views[0].image_k)) and float(np.nanmax(views[0].image_k)) <= PATCH / 100.0
