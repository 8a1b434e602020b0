"""Complete orthophotos (the DSM's holes filled for the mosaic's surface, overviews resampled alike, the heights'
datum declared) and files other tools open (LAS 1.2, LAZ, RGB/intensity, WKT1/GeoTIFF keys, CloudCompare PLY
names with an offset, Y-up GLB at a local origin)."""

from __future__ import annotations

import io
import json
import struct
from types import SimpleNamespace

import numpy as np
import pytest
import rasterio

from survey_truth import write_true_dsm, write_true_survey
from thermogrammetry.cli.main import main

FRAMES = [k for line in (1, 2) for k in range(14 * line + 5, 14 * line + 8)]  # 2 lines x 3 frames


def _plane_with_holes():
    yy, xx = np.mgrid[0:120, 0:200].astype(float)
    z = 100.0 + 0.05 * xx - 0.03 * yy
    h = z.copy()
    h[30:70, 40:100] = np.nan  # 40 x 60 cells
    h[80:90, 150:160] = np.nan  # 10 x 10 cells
    h[:, :5] = np.nan  # a gap along the grid border (5 cells wide)
    return z, h


def test_fill_surface_reproduces_a_plane_and_flags_exactly_the_holes():
    """Laplace interpolation reproduces any plane exactly in a hole enclosed by measured cells (a linear function
    is discrete-harmonic). Tolerance 1e-6 m: a sparse direct solve of a 4-neighbour Laplacian is exact to
    ~1e-12 m here (measured 1.2e-13). The gap along the grid border has no rim on three sides (no flux): it is
    continued flat from its rim column, within the rim's range (maximum principle); away from the gap's ends
    (whose no-flux condition bends it) equal to the rim column (measured 2.3e-5 m over rows 30-90)."""
    from thermogrammetry.products.dsm import fill_surface

    z, h = _plane_with_holes()
    holes = ~np.isfinite(h)
    f, m = fill_surface(h, max_hole_px=100)
    assert int(m.sum()) == int(holes.sum()) and np.array_equal(m == 1, holes)
    interior = holes.copy()
    interior[:, :5] = False
    assert np.max(np.abs(f[interior] - z[interior])) < 1e-6
    assert z[:, 5].min() <= f[:, :5].min() and f[:, :5].max() <= z[:, 5].max()
    assert np.max(np.abs(f[30:90, :5] - z[30:90, 5:6])) < 1e-3
    # max hole size honoured: 30 cells fills the 10-cell hole and the border gap, the 40 x 60 hole within 15
    # cells of its rim only
    f30, m30 = fill_surface(h, max_hole_px=30)
    assert m30[80:90, 150:160].all() and m30[:, :5].all()
    assert np.isnan(f30[50, 70]) and m30[30:70, 40:100].sum() == 40 * 60 - 10 * 30
    f0, m0 = fill_surface(h, max_hole_px=0)
    assert m0.sum() == 0 and np.array_equal(np.isnan(f0), holes)


def test_filled_dsm_file_and_the_heights_datum(tmp_path):
    from thermogrammetry.products.dsm import HEIGHTS_AS_INPUT, height_tags, write_filled_dsm
    from thermogrammetry.products.raster import Grid, write_cog

    _, h = _plane_with_holes()
    g = Grid(500000.0, 5200000.0, 0.5, h.shape[1], h.shape[0], 64)
    for crs, want in (("EPSG:32633", HEIGHTS_AS_INPUT), ("EPSG:32633+5773", "EGM96 height")):
        src, dst = tmp_path / "dsm.tif", tmp_path / f"filled_{len(crs)}.tif"
        write_cog(src, g, np.float32, lambda r0, c0, r, c: h[r0:r0 + r, c0:c0 + c], crs=crs, nodata=float("nan"),
                  unit="m", tags=height_tags(crs))
        rec = write_filled_dsm(src, dst, 50.0, crs)  # 100 cells
        assert rec["filled_cells"] == int((~np.isfinite(h)).sum()) and rec["max_hole_m"] == 50.0
        with rasterio.open(dst) as s:
            assert s.count == 2 and s.tags()["vertical_datum"] == want
            assert int(np.nansum(s.read(2))) == rec["filled_cells"]
        with rasterio.open(src) as s:
            assert s.tags()["vertical_datum"] == want and np.isnan(s.read(1)).sum() == rec["filled_cells"]
            if "+" in crs:
                assert s.crs.to_wkt().startswith("COMPD_CS") and "EGM96" in s.crs.to_wkt()


@pytest.fixture(scope="module")
def holed_ortho(tmp_path_factory):
    """A 6-frame survey on true poses, its true DSM with a 3 m x 3 m hole in the middle of the overlap, the
    ortho with the default fill and with --no-fill."""
    root = tmp_path_factory.mktemp("fill")
    sc, sv = write_true_survey(root / "survey", frames=FRAMES)
    write_true_dsm(root / "true.tif", sc, 0.2)
    with rasterio.open(root / "true.tif") as s:
        z, prof = s.read(1), s.profile
        tr = s.transform
    C = np.array([json.loads((sv / "cameras.json").read_text())["images"][k]["center"] for k in range(len(FRAMES))])
    cx, cy = C[:, 0].mean(), C[:, 1].mean()
    r, c = int((tr.f - cy) / 0.2), int((cx - tr.c) / 0.2)
    hole = (slice(r - 7, r + 8), slice(c - 7, c + 8))
    z[hole] = np.nan
    prof.update(driver="GTiff")
    with rasterio.open(root / "dsm.tif", "w", **prof) as d:
        d.write(z, 1)
    for name, extra in (("fill", []), ("nofill", ["--no-fill"])):
        assert main(["ortho", str(sv), "--dsm", str(root / "dsm.tif"), "-o", str(root / name), "--workers", "0"]
                    + extra) == 0
    return root, hole


def test_ortho_fills_the_dsm_hole_and_flags_it(holed_ortho):
    root, hole = holed_ortho
    with rasterio.open(root / "nofill" / "ortho.tif") as s:
        a = s.read(1)
    with rasterio.open(root / "fill" / "ortho.tif") as s:
        b = s.read(1)
    with rasterio.open(root / "fill" / "ortho_filled_mask.tif") as s:
        m = s.read(1)
        assert s.nodata == 255
    assert not (root / "nofill" / "ortho_filled_mask.tif").exists()
    assert json.loads((root / "nofill" / "ortho.json").read_text())["fill"] is None
    # ortho and DSM share the grid (0.2 m): the hole's 15 x 15 cells, plus the ring whose bilinear height uses them
    assert np.isnan(a[hole]).all() and np.isfinite(b[hole]).all()
    rep = json.loads((root / "fill" / "ortho.json").read_text())["fill"]
    assert rep["filled_cells"] == 225
    flagged = m == 1
    assert flagged[hole].all() and 225 <= flagged.sum() <= 17 * 17 and rep["ortho_cells_on_filled"] == flagged.sum()
    assert np.array_equal(m == 255, np.isnan(b))
    # elsewhere the same mosaic, bit for bit, but near the hole, where the filled surface now occludes or frees
    # a few views
    same = np.isfinite(a) & ~flagged
    eq = a[same].view(np.uint32) == b[same].view(np.uint32)
    assert same.sum() > 10_000 and eq.mean() > 0.99
    gained = ~np.isfinite(a) & np.isfinite(b) & ~flagged  # on measured heights a view the hole's edge had hidden
    assert gained.sum() < 0.2 * flagged.sum()


def test_ortho_float_and_u16_overviews_agree(holed_ortho):
    """Both overviews are averages: decoded 16-bit overview = float overview within one code step (they were
    nearest vs average: up to tens of K apart at roof edges)."""
    root, _ = holed_ortho
    with rasterio.open(root / "fill" / "ortho.tif") as s:
        f = s.read(1, out_shape=(s.height // 2, s.width // 2), masked=True)  # the first overview level
        assert s.overviews(1)[0] == 2
    with rasterio.open(root / "fill" / "ortho_u16.tif") as s:
        u = s.read(1, out_shape=(s.height // 2, s.width // 2), masked=True)
        scale, offset = s.scales[0], s.offsets[0]
    both = ~f.mask & ~u.mask
    assert both.sum() > 3000
    d = np.abs(u.data[both] * scale + offset - f.data[both])
    assert d.max() <= 1.01 * scale  # rounding of the average code (half a step) + the codes' own half step


def _points(n, rng):
    from thermogrammetry.dense.fusion import POINT_DTYPE

    p = np.zeros(n, POINT_DTYPE)
    p["x"], p["y"] = 500000.0 + rng.uniform(0, 50, n), 5200000.0 + rng.uniform(0, 50, n)
    p["z"] = 400.0 + rng.uniform(0, 5, n)
    p["value"] = np.linspace(280.0, 300.0, n)
    p["views"], p["source"], p["nz"] = 3, 1, 1.0
    return p


@pytest.mark.parametrize("version,laz", [("1.2", False), ("1.4", True)])
def test_cloud_las_version_rgb_intensity_crs_and_laz(tmp_path, version, laz):
    import laspy

    from thermogrammetry.products.cloud import CloudOptions, CloudWriter

    p = _points(2000, np.random.default_rng(1))
    w = CloudWriter(tmp_path / "c.las", tmp_path / "c.ply", unit="K", crs="EPSG:32633", offset_xyz=(500025, 5200025, 400),
                    options=CloudOptions(laz=laz, las_version=version), value_limits=(282.0, 298.0))
    w.write(p[:1000])
    w.write(p[1000:])
    w.close()
    path = tmp_path / ("c.laz" if laz else "c.las")
    assert w.files[0] == path.name and path.exists() and not (tmp_path / ("c.las" if laz else "c.laz")).exists()
    las = laspy.read(path)
    assert str(las.header.version) == version
    raw = path.read_bytes()
    if version == "1.2":  # what a LAS 1.2-only reader checks: header size 227, point format 3 (+ extra bytes)
        assert raw[24:26] == b"\x01\x02" and struct.unpack_from("<H", raw, 94)[0] == 227 and raw[104] == 3
        assert struct.unpack_from("<H", raw, 105)[0] >= 34
    assert las.header.point_format.id == (3 if version == "1.2" else 7)
    assert np.allclose(las.x, p["x"], atol=6e-4) and np.array_equal(np.asarray(las["temperature_k"]), p["value"])
    assert las.header.parse_crs().to_epsg() == 32633
    kinds = {type(v).__name__ for v in las.header.vlrs}
    if version == "1.2":
        assert "GeoKeyDirectoryVlr" in kinds and "WktCoordinateSystemVlr" not in kinds
    else:
        wkt = next(v for v in las.header.vlrs if type(v).__name__ == "WktCoordinateSystemVlr").string
        assert wkt.startswith("PROJCS[") and "32633" in wkt  # OGC WKT1, not WKT2
    # intensity: the value on 282..298 K; RGB: the thermal palette (dark = cold, bright = warm)
    it = np.asarray(las.intensity, float)
    assert it[0] == 0 and it[-1] == 65535 and np.all(np.diff(it) >= 0)
    mid = np.argmin(np.abs(p["value"] - 290.0))
    assert abs(it[mid] - 32767.5) < 300
    bright = np.asarray(las.red, float) + las.green + las.blue
    assert bright[-1] > 5 * bright[0] and np.corrcoef(bright, p["value"])[0, 1] > 0.9


def test_ply_scalar_fields_and_offset(tmp_path):
    import plyfile

    from thermogrammetry.products.cloud import CloudWriter

    p = _points(500, np.random.default_rng(2))
    w = CloudWriter(tmp_path / "c.las", tmp_path / "c.ply", unit="K", crs="EPSG:32633", offset_xyz=(500025.4, 5200025.6, 400.2))
    w.write(p)
    w.close()
    ply = plyfile.PlyData.read(str(tmp_path / "c.ply"))
    names = [q.name for q in ply["vertex"].properties]
    for n in ("x", "temperature_k", "views", "source_image", "scalar_temperature_k", "scalar_views", "red"):
        assert n in names
    off = [c for c in ply.comments if c.startswith("offset ")][0].split()[1:]
    assert [float(o) for o in off] == list(w.ply_offset) == [500025.0, 5200026.0, 400.0]
    v = ply["vertex"]
    assert np.abs(v["x"]).max() < 30 and np.allclose(v["x"] + w.ply_offset[0], p["x"], atol=1e-9)
    # float32 viewers keep mm: relative coordinates survive the cast
    assert np.max(np.abs(v["y"].astype(np.float32).astype(float) + w.ply_offset[1] - p["y"])) < 1e-5
    assert np.array_equal(v["scalar_temperature_k"], v["temperature_k"])


def test_glb_is_y_up_at_a_local_origin_with_offset_and_crs(tmp_path):
    import trimesh

    from thermogrammetry.products.texture_export import glb_bytes

    # a 10 m x 6 m wall facing south (normal -y), 4 m high, at UTM coordinates
    V = np.array([[0, 0, 0], [10, 0, 0], [10, 0, 4], [0, 0, 4], [0, 6, 0], [10, 6, 0]], float) + [500123.0, 5200456.0, 380.0]
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 4, 5], [0, 5, 1]])
    atlas = SimpleNamespace(vmapping=np.arange(6), uv=np.random.default_rng(3).uniform(0, 1, (6, 2)), faces=faces)
    res = SimpleNamespace(vertices=V, atlas=atlas)
    glb = glb_bytes(res, np.full((8, 8, 3), 200, np.uint8), crs="EPSG:32633")
    n = struct.unpack_from("<I", glb, 12)[0]
    doc = json.loads(glb[20:20 + n])
    info = doc["asset"]["extras"]["thermogrammetry"]
    assert info["crs"] == "EPSG:32633" and "Y-up" in info["axes"]
    assert all("translation" not in nd and "matrix" not in nd for nd in doc["nodes"])  # model at the origin
    mesh = trimesh.load(io.BytesIO(glb), file_type="glb", force="scene").to_geometry()
    P = np.asarray(mesh.vertices)
    assert np.abs(P).max() < 20  # local coordinates
    ox, oy, oz = info["offset"]
    back = np.column_stack([P[:, 0] + ox, -P[:, 2] + oy, P[:, 1] + oz])
    assert np.max(np.abs(back - V)) < 1e-4
    # upright: the wall's 4 m height is along +Y; the ground (z = 380) at the lowest Y
    assert abs(np.ptp(P[:, 1]) - 4.0) < 1e-5 and np.argmin(P[:, 1]) in (0, 1, 4, 5)


def test_cameras_geopackage_points_and_footprints(holed_ortho):
    """cameras.gpkg read back with sqlite3 as a GeoPackage reader does: the required tables, the SRS, the binary
    geometry header and ISO WKB; camera points at the centres, footprints the corners' rays on the plane."""
    import sqlite3

    from thermogrammetry.io.oriented import OrientedCameras
    from thermogrammetry.products.gpkg import cameras_gpkg_bytes

    root, _ = holed_ortho
    oc = OrientedCameras.load(root / "survey")
    path = root / "cameras.gpkg"
    path.write_bytes(cameras_gpkg_bytes(oc, 0.0))
    db = sqlite3.connect(path)
    assert db.execute("PRAGMA application_id").fetchone()[0] == 0x47504B47
    assert {r[0] for r in db.execute("SELECT srs_id FROM gpkg_spatial_ref_sys")} == {-1, 0, 4326, 32633}
    assert sorted(db.execute("SELECT table_name, geometry_type_name, srs_id, z FROM gpkg_geometry_columns")) == [
        ("cameras", "POINT", 32633, 1), ("footprints", "POLYGON", 32633, 0)]
    pts = db.execute("SELECT name, geom FROM cameras ORDER BY fid").fetchall()
    assert len(pts) == len(oc.images) == len(FRAMES)
    for (name, g), im in zip(pts, oc.images):
        assert g[:2] == b"GP" and struct.unpack_from("<i", g, 4)[0] == 32633
        bo, kind, x, y, z = struct.unpack_from("<BIddd", g, 8 + 32)
        assert name == im.name and kind == 1001 and np.allclose([x, y, z], im.center, atol=1e-9)
    feet = db.execute("SELECT name, geom, area_m2 FROM footprints ORDER BY fid").fetchall()
    assert len(feet) == len(FRAMES)
    for (name, g, area), im in zip(feet, oc.images):
        bo, kind, nring, npt = struct.unpack_from("<BIII", g, 40)
        ring = np.frombuffer(g, "<f8", count=2 * npt, offset=53).reshape(npt, 2)
        assert kind == 3 and nring == 1 and npt == 5 and np.array_equal(ring[0], ring[-1])
        # nadir-ish frame: the footprint contains the camera's ground point, its size = height x the sensor's angle
        cam = oc.camera_of(im)
        w, h = cam.image_size
        H = im.center[2]
        want = (H * (w - 1) / cam.K[0, 0]) * (H * (h - 1) / cam.K[1, 1])
        assert 0.8 * want < area < 1.25 * want
        assert ring[:, 0].min() < im.center[0] < ring[:, 0].max() and ring[:, 1].min() < im.center[1] < ring[:, 1].max()


def test_ortho_refuses_a_max_angle_outside_0_90_and_a_negative_hole_size(holed_ortho):
    root, _ = holed_ortho
    for extra in (["--max-angle", "95"], ["--fill-max-hole", "-1"]):
        out = root / f"bad{len(extra[1])}"
        assert main(["ortho", str(root / "survey"), "--dsm", str(root / "dsm.tif"), "-o", str(out), "--workers", "0"]
                    + extra) == 2
        assert not out.exists()


def test_dense_refuses_an_unknown_las_version_before_writing(holed_ortho):
    root, _ = holed_ortho
    out = root / "dense_bad"
    assert main(["dense", str(root / "survey"), "-o", str(out), "--las-version", "1.3", "--workers", "0"]) == 2
    assert not out.exists()
