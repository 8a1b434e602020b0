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


def test_fill_surface_reaches_twice_as_far_beyond_the_datas_outer_edge():
    """A gap beyond the convex hull of the measured cells has its rim on one side only: its width across is its depth
    from the rim, so it is filled up to max_hole_px from the rim (a hole inside the hull: max_hole_px / 2, as the test
    above checks). The data: a plane on columns 40..199 of a 120 x 200 grid (hull = that block), a 40-column gap on
    the west (no data beyond it) and an interior hole 40 cells wide. max_hole_px = 60: the west gap is filled
    entirely (depth 40 <= 60), continued flat from its rim column (Neumann at the grid border) within the rim's
    range; the interior hole (40 <= 60) entirely. With open_edges=False the gap is filled within 30 cells of its rim
    only, as before."""
    from thermogrammetry.products.dsm import fill_surface, outside_hull

    yy, xx = np.mgrid[0:120, 0:200].astype(float)
    z = 100.0 + 0.05 * xx - 0.03 * yy
    h = z.copy()
    h[:, :40] = np.nan
    h[40:80, 100:140] = np.nan
    hull_out = outside_hull(np.isfinite(h))
    assert hull_out[:, :40].all() and not hull_out[:, 40:].any()
    f, m = fill_surface(h, max_hole_px=60)
    assert m[:, :40].all() and m[40:80, 100:140].all() and int(m.sum()) == int((~np.isfinite(h)).sum())
    assert np.max(np.abs(f[40:80, 100:140] - z[40:80, 100:140])) < 1e-6  # a plane, exactly
    assert z[:, 40].min() - 1e-9 <= f[:, :40].min() and f[:, :40].max() <= z[:, 40].max() + 1e-9
    f_old, m_old = fill_surface(h, max_hole_px=60, open_edges=False)
    assert m_old[:, 10:40].all() and not m_old[:, :10].any() and np.isnan(f_old[:, :10]).all()
    # a hull of collinear cells (one measured row) has no inside: nothing is "beyond" it
    one = np.full((5, 6), np.nan)
    one[2] = 1.0
    assert not outside_hull(np.isfinite(one)).any()


def test_extended_grid_and_the_filled_dsm_on_it(tmp_path):
    """extended_grid grows a grid by whole cells towards a box, capped per side, never shrinking it; write_filled_dsm
    on that grid places the DSM cell for cell and fills beyond its box like any gap (reported apart)."""
    from thermogrammetry.products.dsm import extended_grid, write_filled_dsm
    from thermogrammetry.products.raster import Grid, write_cog

    g = Grid(1000.0, 2000.0, 0.5, 40, 30, 64)  # x 1000..1020, y 1985..2000
    e = extended_grid(g, (997.2, 1986.0, 1030.0, 2000.4), 10)
    # west: ceil(2.8 / 0.5) = 6 cells; east: 10 m = 20 cells, capped at 10; north: ceil(0.4 / 0.5) = 1; south: none
    assert (e.x0, e.y0, e.gsd, e.width, e.height) == (997.0, 2000.5, 0.5, 40 + 6 + 10, 30 + 1)
    assert extended_grid(g, (1005.0, 1990.0, 1010.0, 1995.0), 10) == g  # a box inside: unchanged
    yy, xx = np.mgrid[0:30, 0:40].astype(float)
    h = 50.0 + 0.1 * xx
    h[10:14, 10:14] = np.nan
    src, dst = tmp_path / "dsm.tif", tmp_path / "surface.tif"
    write_cog(src, g, np.float32, lambda r0, c0, r, c: h[r0:r0 + r, c0:c0 + c], crs="EPSG:32633", nodata=float("nan"),
              unit="m")
    rec = write_filled_dsm(src, dst, 10.0, "EPSG:32633", grid=e)  # 20 cells
    with rasterio.open(dst) as s:
        z, m = s.read(1), s.read(2)
        assert (s.width, s.height) == (e.width, e.height) and s.transform.c == e.x0 and s.transform.f == e.y0
    inner = (slice(1, 31), slice(6, 46))
    np.testing.assert_array_equal(z[inner][np.isfinite(h)], h[np.isfinite(h)].astype(np.float32))
    assert rec["grid"] == {"x0": e.x0, "y0": e.y0, "width": e.width, "height": e.height}
    assert rec["filled_beyond_dsm_cells"] == e.width * e.height - g.width * g.height  # all within reach of the data
    assert rec["filled_cells"] == rec["filled_beyond_dsm_cells"] + 16 and int(np.nansum(m)) == rec["filled_cells"]
    with pytest.raises(ValueError, match="does not hold"):
        write_filled_dsm(src, tmp_path / "x.tif", 10.0, None, grid=Grid(1000.25, 2000.0, 0.5, 50, 40))


def test_horn_normals_of_a_plane_and_their_noise():
    """surface_normals: exact for a plane (Horn's estimator is exact for linear heights); on independent height
    noise σ the slope's standard deviation is sqrt(12)/8 σ/gsd = 0.433 σ/gsd per axis (central differences of two
    cells: 0.707). 200 x 200 cells of N(0, 1) heights: the sample std of ~39,000 values is within ±3 % of that
    (the estimates of neighbouring cells share heights: the effective count is a few thousand, 3 % is > 3 of its
    standard errors), far from 0.707."""
    from thermogrammetry.products.ortho import surface_normals

    yy, xx = np.mgrid[0:20, 0:30].astype(float)
    gsd = 0.5
    Z = 3.0 + 0.4 * xx * gsd - 0.2 * (-yy * gsd)  # dz/dx = 0.4, dz/dy(north) = -0.2 (row 0 is north: y = -row * gsd)
    n = surface_normals(Z, gsd)
    want = np.array([-0.4, 0.2, 1.0]) / np.linalg.norm([-0.4, 0.2, 1.0])
    np.testing.assert_allclose(n[1:-1, 1:-1].reshape(-1, 3), np.broadcast_to(want, (18 * 28, 3)), atol=1e-12)
    assert np.array_equal(n[0, 0], [0.0, 0.0, 1.0])  # the border: vertical
    rng = np.random.default_rng(5)
    N = surface_normals(rng.normal(0, 1, (200, 200)), 1.0)[1:-1, 1:-1]
    sx = np.std(-N[..., 0] / N[..., 2])
    assert abs(sx / (np.sqrt(12) / 8) - 1) < 0.03


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


def test_ortho_reaches_beyond_a_dsm_smaller_than_the_footprints(holed_ortho):
    """A DSM cut to its east half (x >= 500032 m; the frames see the ground from x ~ 500017 m): the ortho's grid
    grows west into the images' footprints (at most the fill limit beyond the DSM's box), its surface there continued
    from the DSM's edge; those cells are flagged as filled. Of the strip's cells that the ortho on the whole DSM
    covers, the one on the cut DSM covers >= 95 % (measured 96.7 %, deterministic: true poses, rendered frames; the
    rest lies by the strip's buildings, which the continued surface does not have, so that the z-buffer and the
    angle differ there); with --no-fill the grid is the DSM's and the strip is empty."""
    root, _ = holed_ortho
    with rasterio.open(root / "true.tif") as s:
        z, prof, tr = s.read(1), s.profile, s.transform
    c_cut = int(round((500032.0 - tr.c) / tr.a))
    prof.update(driver="GTiff", width=z.shape[1] - c_cut, transform=rasterio.Affine(tr.a, 0, tr.c + c_cut * tr.a, 0, tr.e, tr.f))
    with rasterio.open(root / "cut.tif", "w", **prof) as d:
        d.write(z[:, c_cut:], 1)
    for name, extra in (("cut", []), ("cut_nofill", ["--no-fill"])):
        assert main(["ortho", str(root / "survey"), "--dsm", str(root / "cut.tif"), "-o", str(root / name),
                     "--workers", "0"] + extra) == 0
    with rasterio.open(root / "cut" / "ortho.tif") as s:
        cut, tc = s.read(1), s.transform
    with rasterio.open(root / "cut" / "ortho_filled_mask.tif") as s:
        mask = s.read(1)
    with rasterio.open(root / "cut_nofill" / "ortho.tif") as s:
        assert (s.width, s.transform.c) == (z.shape[1] - c_cut, 500032.0)
    with rasterio.open(root / "fill" / "ortho.tif") as s:
        ref, tf = s.read(1), s.transform
    fill = json.loads((root / "cut" / "ortho.json").read_text())["fill"]
    assert 500032.0 - fill["max_hole_m"] - 1e-6 <= tc.c < 500032.0 - 5.0 and fill["filled_beyond_dsm_cells"] > 0
    strip = np.zeros(cut.shape, bool)
    strip[:, :int(round((500032.0 - tc.c) / tc.a))] = True
    assert np.isfinite(cut[strip]).sum() > 5000 and np.all(mask[strip & np.isfinite(cut)] == 1)
    dc, dr = int(round((tc.c - tf.c) / tf.a)), int(round((tf.f - tc.f) / tf.a))
    sub = ref[dr:dr + cut.shape[0], dc:dc + cut.shape[1]]
    seen = strip & np.isfinite(sub)
    assert seen.sum() > 5000 and np.isfinite(cut[seen]).mean() >= 0.95
    # the frames' footprint on the surface: every cell with a value is in it. The 15 x 15-cell hole of the holed DSM
    # lies in the middle of the overlap: without the fill its cells (no height: taken at the DSM's mid height) are in
    # the footprint all the same, and empty
    reps = {n: json.loads((root / n / "ortho.json").read_text()) for n in ("cut", "cut_nofill", "fill", "nofill")}
    for r in reps.values():
        fp = r["footprint"]
        assert fp["cells"] >= r["cells"] and fp["covered"] == round(r["cells"] / fp["cells"], 4)
    a, b = reps["fill"], reps["nofill"]
    assert abs(a["footprint"]["cells"] - b["footprint"]["cells"]) <= 50 and a["cells"] - b["cells"] >= 225
    assert b["footprint"]["covered"] < a["footprint"]["covered"]


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
