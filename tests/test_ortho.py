"""ortho and evaluate on survey folders built from TRUE poses and the TRUE DSM (tests/survey_truth.py):
they test the mosaic alone, not orientation or dense matching."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import rasterio
import tifffile

from survey_truth import small_survey_config, true_height, write_true_dsm, write_true_survey
from thermogrammetry.cli.main import main

FRAMES = [k for line in (1, 2) for k in range(14 * line + 4, 14 * line + 9)]  # 2 lines x 5 frames


@pytest.fixture(scope="module")
def ortho_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("ortho")
    sc, sv = write_true_survey(root / "survey", frames=FRAMES)
    write_true_dsm(root / "dsm.tif", sc, 0.1)
    assert main(["ortho", str(sv), "--dsm", str(root / "dsm.tif"), "-o", str(root / "o"), "--workers", "0"]) == 0
    return sc, sv, root


def _read(p, band=None):
    from types import SimpleNamespace

    with rasterio.open(p) as s:
        a = s.read() if band is None else s.read(band)
        tr = s.transform
        meta = SimpleNamespace(units=s.units, nodata=s.nodata, crs=s.crs, overviews=s.overviews(1), dtypes=s.dtypes,
                               scales=s.scales, offsets=s.offsets, descriptions=s.descriptions, res=s.res,
                               width=s.width, block=s.block_shapes[0],
                               xy=lambda r, c: (tr.c + (c + 0.5) * tr.a, tr.f + (r + 0.5) * tr.e))
    return a, meta


def test_ortho_values_are_bitwise_copies_of_their_source_pixels(ortho_run):
    sc, sv, root = ortho_run
    o = root / "o"
    v, s = _read(o / "ortho.tif", 1)
    assert s.units == ("K",) and np.isnan(s.nodata) and s.crs.to_epsg() == 32633 and s.overviews
    assert s.block == (256, 256)
    src, s2 = _read(o / "ortho_source.tif")
    assert s2.dtypes[0] == "int32" and s2.nodata == -1
    rep = json.loads((o / "ortho.json").read_text())
    ok = src[0] >= 0
    assert ok.sum() > 50_000 and np.array_equal(ok, np.isfinite(v))  # 10 frames cover ~30 % of the scene
    for k in np.unique(src[0][ok]):
        m = src[0] == k
        fr = tifffile.imread(sv / "frames" / f"{rep['images'][str(k)]}.tif")
        assert np.array_equal(fr[src[1][m], src[2][m]].view(np.uint32), v[m].view(np.uint32))


def test_ortho_source_pixel_is_the_projection_of_the_cell_and_choice_is_near_nadir(ortho_run):
    from thermogrammetry.io.oriented import OrientedCameras

    sc, sv, root = ortho_run
    o = root / "o"
    src, s = _read(o / "ortho_source.tif")
    ang, _ = _read(o / "ortho_angle.tif", 1)
    dist, _ = _read(o / "ortho_distance.tif", 1)
    rep = json.loads((o / "ortho.json").read_text())
    oc = OrientedCameras.load(sv)
    rr, cc = np.nonzero(src[0] >= 0)
    pick = np.random.default_rng(0).choice(len(rr), 200, replace=False)
    for p in pick:
        r, c = rr[p], cc[p]
        x, y = s.xy(r, c)  # cell centre
        z = true_height(sc, np.array([x]), np.array([y]))[0]
        im = oc.image(rep["images"][str(src[0, r, c])])
        Xc = im.R @ np.array([x, y, z]) + im.t
        u, w = oc.camera_of(im).project(Xc[None])[0]
        assert (int(round(w)), int(round(u))) == (src[1, r, c], src[2, r, c])
        assert dist[r, c] == pytest.approx(np.linalg.norm(Xc), rel=1e-5)
    # flight 45 m, attitude 1 deg, footprint ±10 m, relief: median angle below 20 deg, none beyond the 60 deg limit
    assert np.nanmedian(ang) < 20 and np.nanmax(ang) < 60
    assert 44 < np.nanmedian(dist) < 50


def _hidden_picks(sc, sv, o):
    """Cells whose chosen frame does not see the cell's true surface point: the frame's rendered depth at all
    four pixels around the point's projection differs from the point's depth by more than 1 %."""
    from thermogrammetry.synthetic.survey import render_frame

    src, s = _read(o / "ortho_source.tif")
    rep = json.loads((o / "ortho.json").read_text())
    index = {f.name: i for i, f in enumerate(sc.frames)}
    hidden = total = 0
    for k in np.unique(src[0][src[0] >= 0]):
        rr, cc = np.nonzero(src[0] == k)
        x, y = s.xy(rr, cc)
        P = np.column_stack([x, y, true_height(sc, np.asarray(x), np.asarray(y))])
        fi = index[rep["images"][str(k)]]
        depth = render_frame(sc, fi, with_truth=True, sensor=False)["depth_m"]
        Pc = sc.frames[fi].pose.transform(P)
        uv = sc.camera.project(Pc)
        h, w = depth.shape
        x0 = np.clip(np.floor(uv[:, 0]).astype(int), 0, w - 2)
        y0 = np.clip(np.floor(uv[:, 1]).astype(int), 0, h - 2)
        seen = np.zeros(len(P), bool)
        for dy in (0, 1):
            for dx in (0, 1):
                seen |= np.abs(depth[y0 + dy, x0 + dx] - Pc[:, 2]) <= 0.01 * Pc[:, 2]
        hidden += int((~seen).sum())
        total += len(P)
    return hidden, total


def test_ortho_never_takes_a_value_from_a_frame_where_the_true_point_is_hidden(ortho_run, tmp_path):
    """True poses and true DSM: the z-buffer alone decides visibility. A DSM cell of 0.12 m projects to ~1.9 px
    here, as the dense DSM's cell does in the survey-sfm demo (0.251 m at 0.132 m image GSD). With occluders at
    the cell centres only, nothing stood between the last roof centre and the first ground centre, and ground
    cells hidden by the roof's edge took the roof's temperature: 79 of 58 254 cells here (0.14 %), 0.47 % in
    the survey-sfm scene. With the surface sampled between the centres at height steps: 17 here (0.03 %),
    0.09 % there (pixels mixing roof and ground, which the 1 % depth test counts as hidden). Bound 0.05 %."""
    sc, sv, root = ortho_run
    write_true_dsm(tmp_path / "dsm.tif", sc, 0.12)
    assert main(["ortho", str(sv), "--dsm", str(tmp_path / "dsm.tif"), "-o", str(tmp_path / "o"),
                 "--workers", "0"]) == 0
    hidden, total = _hidden_picks(sc, sv, tmp_path / "o")
    assert total > 50_000
    assert hidden <= 0.0005 * total, f"{hidden} of {total} cells took their value from a frame that does not see them"


def test_ortho_occluder_sampling_fills_the_zbuffer_bins():
    from thermogrammetry.products.ortho import occluder_subdivision, occluders
    from thermogrammetry.products.raster import Grid

    assert occluder_subdivision(1.4, 2) == 1 and occluder_subdivision(1.9, 2) == 2 and occluder_subdivision(50, 2) == 4
    assert occluder_subdivision(float("nan"), 2) == 1
    dg = Grid(100.0, 200.0, 0.5, 10, 10)
    D = np.zeros((4, 5))
    one = occluders(D, dg, 2, 3, 1)  # the cell centres
    assert len(one) == 20 and np.allclose(one[0], [101.75, 198.75, 0.0])
    assert len(occluders(D, dg, 2, 3, 2, min_span_m=0.5)) == 20  # flat: the centres stand for the surface
    D[3, 4] = 2.0  # a step in the last square: it and its neighbours get 2 x 2 points (3 new each), bilinear
    two = occluders(D, dg, 2, 3, 2, min_span_m=0.5)
    assert len(two) == 20 + 4 * 3
    new = two[20:]
    x, y = 100.0 + (3 + 3.5 + 0.5) * 0.5, 200.0 - (2 + 2.5 + 0.5) * 0.5
    corner = new[np.isclose(new[:, 0], x) & np.isclose(new[:, 1], y)]
    assert np.allclose(corner[:, 2], [0.5])  # centre of the last square: a quarter of the 2 m step
    D[0, 0] = np.nan  # squares with a missing corner are skipped
    assert not np.isnan(occluders(D, dg, 2, 3, 2, min_span_m=0.0)[:, 2]).any()


def test_ortho_u16_encoding_inverts_within_half_a_step(ortho_run):
    sc, sv, root = ortho_run
    v, _ = _read(root / "o" / "ortho.tif", 1)
    u, s = _read(root / "o" / "ortho_u16.tif", 1)
    rep = json.loads((root / "o" / "ortho.json").read_text())
    assert s.scales[0] == rep["scale"] and s.offsets[0] == rep["offset"] and s.nodata == 0
    dec = np.where(u > 0, u * rep["scale"] + rep["offset"], np.nan)
    assert np.array_equal(np.isnan(dec), np.isnan(v))
    assert np.nanmax(np.abs(dec - v)) <= rep["scale"] / 2 + 1e-4


# the analytic linear field of the gradient tests: T = T0 + GE (E - E0) + GN (N - N0), GE = 0.3 K/m east and
# GN = -0.4 K/m north, so |grad T| = hypot(0.3, 0.4) = 0.5 K/m exactly and the direction of increase, clockwise from
# grid north, is atan2(GE, GN) = 180 - atan(0.3 / 0.4) = 143.130 deg (south-east).  No two of the usual convention
# errors give the same angle: north sign flipped 36.87, east sign flipped 216.87, axes swapped (atan2(GN, GE))
# 306.87, counter-clockwise from east -53.13 = 306.87, both signs 323.13 deg.
GRAD_E, GRAD_N = 0.3, -0.4
GRAD_MAG, GRAD_DIR_DEG = 0.5, 143.13010235415598


def test_gradient_of_an_analytic_linear_field():
    from thermogrammetry.products.ortho import gradient
    from thermogrammetry.products.raster import Grid

    g = Grid(500000.0, 5600040.0, 0.25, 30, 20)
    E, N = g.cell_centres(0, 0, 20, 30)  # rows southwards, as every north-up raster of the project
    v = 300.0 + GRAD_E * (E - 500000.0) + GRAD_N * (N - 5600000.0)
    v[7, 11] = np.nan  # a missing cell: its four neighbours' gradients are undefined, nothing else
    mag, direc = gradient(v, g.gsd)
    ok = np.isfinite(mag)
    assert ok.sum() == 18 * 28 - 4 and not ok[0].any() and not ok[:, -1].any()
    # central differences of a linear field are exact: only float64 rounding (1e-13 K over 0.5 m) remains
    assert np.max(np.abs(mag[ok] - GRAD_MAG)) < 1e-9
    assert np.max(np.abs(direc[ok] - GRAD_DIR_DEG)) < 1e-6
    assert np.array_equal(np.isfinite(direc), ok)


def _nadir_linear_frame_survey(folder, *, T0=300.0, alpha=0.03, beta=0.04):
    """One pinhole frame (f = 500 px, 320 x 256) looking straight down from H = 50 m above a flat DSM at 100 m,
    image x = east, image y = south; its pixels hold the linear image T0 + alpha (u - cx) + beta (v - cy) (K,
    noise-free).  A pixel (u, v) sees the ground point E = Ec + (u - cx) H / f, N = Nc - (v - cy) H / f, so the
    ground field is T0 + alpha f/H (E - Ec) - beta f/H (N - Nc): with f/H = 10 px/m, 0.3 K/m east and -0.4 K/m
    north (GRAD_E, GRAD_N).  Returns (survey folder, DSM path, field(E, N))."""
    import tifffile

    from thermogrammetry.camera import Camera
    from thermogrammetry.io.oriented import OrientedCameras, OrientedImage
    from thermogrammetry.products.raster import Grid, write_cog

    f, w, h, H, zg = 500.0, 320, 256, 50.0, 100.0
    cx, cy = (w - 1) / 2, (h - 1) / 2
    Ec, Nc = 500016.05, 5600012.85  # not on a cell boundary of the DSM below
    cam = Camera("pinhole", (w, h), {"fx": f, "fy": f, "cx": cx, "cy": cy})
    R = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # camera x east, y south, z down
    t = -R @ np.array([Ec, Nc, zg + H])
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    sv = folder / "survey"
    (sv / "frames").mkdir(parents=True)
    tifffile.imwrite(sv / "frames" / "N0.tif", (T0 + alpha * (u - cx) + beta * (v - cy)).astype(np.float32))
    OrientedCameras({"thermal": cam}, [OrientedImage("N0", "thermal", R, t, frame="frames/N0.tif", unit="K")],
                    crs="EPSG:32633", notes="one exact nadir frame (test)").save(sv / "cameras.json")
    grid = Grid(500000.0, 5600030.0, 0.1, 330, 300)  # 33 x 30 m, larger than the 32 x 25.6 m footprint
    write_cog(folder / "flat.tif", grid, "float32", lambda r0, c0, rows, cols: np.full((rows, cols), zg, np.float32),
              crs="EPSG:32633", nodata=float("nan"), unit="m")
    k = f / H
    return sv, folder / "flat.tif", lambda E, N: T0 + alpha * k * (E - Ec) - beta * k * (N - Nc)


def test_ortho_gradient_raster_of_an_analytic_linear_field(tmp_path):
    """The verb's own gradient raster on a ground field known in closed form (see _nadir_linear_frame_survey):
    magnitude 0.5 K/m, direction 143.13 deg clockwise from grid north, in every cell whose 4 neighbours have a
    value.  Bilinear sampling reproduces a linear image exactly, so the ortho is the field itself up to float32
    storage (frame and ortho values near 300 K: ulp 3e-5 K, so 3e-5 K each; bound 1e-3 K) and the central
    difference over 2 cells (0.2 m) errs by at most 2 x 3e-5 / 0.2 = 3e-4 K/m in each component: bound 1e-3 K/m on
    the magnitude and 1e-3 / 0.5 rad = 0.12 deg on the direction (bound 0.2 deg)."""
    sv, dsm, field = _nadir_linear_frame_survey(tmp_path)
    assert main(["ortho", str(sv), "--dsm", str(dsm), "-o", str(tmp_path / "o"), "--sampling", "bilinear",
                 "--workers", "0"]) == 0
    v, s = _read(tmp_path / "o" / "ortho.tif", 1)
    g, _ = _read(tmp_path / "o" / "ortho_gradient.tif")
    rr, cc = np.mgrid[0:v.shape[0], 0:v.shape[1]]
    E, N = s.xy(rr, cc)
    ok = np.isfinite(v)
    assert ok.sum() > 0.7 * 320 * 256  # the footprint (~32 x 25.6 m) at 0.1 m, bar its one-pixel rim
    assert np.max(np.abs(v[ok] - field(E[ok], N[ok]))) < 1e-3
    gok = np.isfinite(g[0])
    assert gok.sum() > 0.95 * ok.sum()
    assert np.max(np.abs(g[0][gok] - GRAD_MAG)) < 1e-3
    ddir = (g[1][gok] - GRAD_DIR_DEG + 180.0) % 360.0 - 180.0
    assert np.max(np.abs(ddir)) < 0.2


def test_ortho_gradient_raster_is_the_gradient_of_the_whole_mosaic(ortho_run):
    """Tile by tile with a one-cell halo, the gradient raster equals the gradient of the whole mosaic at once (the
    formula itself is checked on an analytic field above)."""
    from thermogrammetry.products.ortho import gradient

    sc, sv, root = ortho_run
    v, s = _read(root / "o" / "ortho.tif", 1)
    g, _ = _read(root / "o" / "ortho_gradient.tif")
    mag, direc = gradient(v.astype(float), s.res[0])
    assert np.array_equal(np.isfinite(g[0]), np.isfinite(mag)) and np.isfinite(mag).sum() > 50_000
    ok = np.isfinite(mag)
    assert np.allclose(g[0][ok], mag[ok], rtol=1e-6, atol=1e-5)  # float32 storage
    sel = ok & (mag > 1)  # direction well defined (float32 storage of a >= 1 K/m gradient: < 1e-3 deg)
    assert np.max(np.abs((g[1][sel] - direc[sel] + 180) % 360 - 180)) < 1e-2


def test_ortho_in_celsius_is_labelled_and_dask_gives_identical_rasters(ortho_run, tmp_path):
    sc, sv, root = ortho_run
    assert main(["ortho", str(sv), "--dsm", str(root / "dsm.tif"), "-o", str(tmp_path / "c"), "--unit", "C",
                 "--workers", "2"]) == 0
    vc, s = _read(tmp_path / "c" / "ortho.tif", 1)
    assert s.units == ("°C",)
    vk, _ = _read(root / "o" / "ortho.tif", 1)
    assert np.allclose(vc, vk - 273.15, atol=1e-4, equal_nan=True)
    a, _ = _read(tmp_path / "c" / "ortho_source.tif")
    b, _ = _read(root / "o" / "ortho_source.tif")
    assert np.array_equal(a, b)  # the same choices from a 2-worker local dask cluster


def test_ortho_of_raw_counts_is_labelled_counts_never_celsius(tmp_path):
    sc, sv = write_true_survey(tmp_path / "s", frames=FRAMES[:3] + FRAMES[5:8], unit="counts")
    write_true_dsm(tmp_path / "dsm.tif", sc, 0.15)
    assert main(["ortho", str(sv), "--dsm", str(tmp_path / "dsm.tif"), "-o", str(tmp_path / "o"), "--workers", "0"]) == 0
    v, s = _read(tmp_path / "o" / "ortho.tif", 1)
    assert s.units == ("counts",) and "not a temperature" in s.descriptions[0]
    src, _ = _read(tmp_path / "o" / "ortho_source.tif")
    rep = json.loads((tmp_path / "o" / "ortho.json").read_text())
    assert rep["unit"] == "counts" and any("counts" in n for n in rep["notes"])
    k = int(np.unique(src[0][src[0] >= 0])[0])
    m = src[0] == k
    fr = tifffile.imread(sv / "frames" / f"{rep['images'][str(k)]}.tif")
    assert fr.dtype == np.uint16 and np.array_equal(fr[src[1][m], src[2][m]].astype(np.float32), v[m])
    assert main(["ortho", str(sv), "--dsm", str(tmp_path / "dsm.tif"), "-o", str(tmp_path / "c"), "--unit", "C",
                 "--workers", "0"]) == 2
    assert not (tmp_path / "c" / "ortho.tif").exists()


def test_ortho_takes_no_value_from_a_burned_in_display(tmp_path):
    """8-bit frames with a camera display burned in (``synthetic.display``), its mask recorded as ``survey`` records
    it (``work/overlay.json``, ``features/overlay.npz`` from ``sfm.features.static_overlay``): the ortho's cells avoid
    the display's pixels, and every value is still its source pixel's. Measured: 0.04 % of the cells from a display
    pixel with the record (edges of the changing range readings in a corner that the mask misses: it covers ~98 % of
    what the display draws over these 10 frames), 1.15 % without it (the cross-hair sits at the frame centre, which the
    image choice favours). Bounds: < 0.1 % and > 0.5 %."""
    from thermogrammetry.sfm.features import static_overlay

    sc, sv = write_true_survey(tmp_path / "s", unit="dn", display=True, frames=FRAMES)
    _, plain = write_true_survey(tmp_path / "p", unit="dn", display=False, frames=FRAMES)
    write_true_dsm(tmp_path / "dsm.tif", sc, 0.15)
    frames = {p.stem: tifffile.imread(p) for p in sorted((sv / "frames").glob("*.tif"))}
    # the display's pixels: where it changed a frame by more than 20 grey levels
    drawn = {k: np.abs(f.astype(int) - tifffile.imread(plain / "frames" / f"{k}.tif")) > 20 for k, f in frames.items()}
    mask = static_overlay(list(frames.values()))
    assert mask is not None
    counts = {}
    unrecorded = Path(shutil.copytree(sv, tmp_path / "s_unrecorded"))  # another folder (surveys are cached by path)
    for recorded in (True, False):
        s = sv if recorded else unrecorded
        if recorded:
            (s / "features").mkdir()
            np.savez(s / "features" / "overlay.npz", mask=mask)
            (s / "work").mkdir()
            (s / "work" / "overlay.json").write_text(json.dumps({"found": True, "key": "features/overlay.npz"}))
        out = tmp_path / f"o{int(recorded)}"
        assert main(["ortho", str(s), "--dsm", str(tmp_path / "dsm.tif"), "-o", str(out), "--workers", "0"]) == 0
        v, _ = _read(out / "ortho.tif", 1)
        src, _ = _read(out / "ortho_source.tif")
        rep = json.loads((out / "ortho.json").read_text())
        names = rep["images"]
        assert any("camera display burned into the frames" in n for n in rep["notes"]) == recorded
        on_display = 0
        for k in np.unique(src[0][src[0] >= 0]):
            m = src[0] == k
            r, c = src[1][m], src[2][m]
            assert np.array_equal(frames[names[str(int(k))]][r, c].astype(np.float32), v[m])
            on_display += int(drawn[names[str(int(k))]][r, c].sum())
        counts[recorded] = on_display / max(1, int((src[0] >= 0).sum()))
    assert counts[True] < 0.001 and counts[False] > 0.005, counts


def test_ortho_refuses_a_dsm_of_another_crs_or_place(ortho_run, tmp_path, capsys):
    """A DSM in another CRS than cameras.json, or one that no camera sees, exits 2 naming both; nothing written."""
    sc, sv, root = ortho_run
    with rasterio.open(root / "dsm.tif") as s:
        z, prof = s.read(1), s.profile
    cases = {"crs": dict(crs="EPSG:32632"),  # the neighbouring UTM zone: same numbers, another CRS
             "far": dict(transform=rasterio.Affine(prof["transform"].a, 0.0, prof["transform"].c + 50_000.0, 0.0,
                                                   prof["transform"].e, prof["transform"].f))}
    words = {"crs": ["EPSG:32632", "EPSG:32633", "reproject"], "far": ["no camera", "camera centres"]}
    for name, change in cases.items():
        p = tmp_path / f"dsm_{name}.tif"
        with rasterio.open(p, "w", **{**prof, **change}) as d:
            d.write(z, 1)
        out = tmp_path / f"o_{name}"
        assert main(["ortho", str(sv), "--dsm", str(p), "-o", str(out), "--workers", "0"]) == 2
        err = capsys.readouterr().err
        assert str(p.name) in err and all(w in err for w in words[name]) and "Traceback" not in err, err
        assert not out.exists()


def test_ortho_correct_raises_temperatures_of_low_emissivity_views(ortho_run, tmp_path):
    sc, sv, root = ortho_run
    assert main(["ortho", str(sv), "--dsm", str(root / "dsm.tif"), "-o", str(tmp_path / "k"), "--correct",
                 "--ambient-c", "-38", "--emissivity", "fresnel", "--workers", "0"]) == 0
    vk, _ = _read(tmp_path / "k" / "ortho.tif", 1)
    v0, _ = _read(root / "o" / "ortho.tif", 1)
    ok = np.isfinite(vk) & np.isfinite(v0)
    # cold sky (235 K) reflected by an emissivity < 1 surface: the corrected temperature is above the apparent one
    assert np.median(vk[ok] - v0[ok]) > 0.5
    assert json.loads((tmp_path / "k" / "ortho.json").read_text())["corrected"] is True


def test_evaluate_dsm_against_reference_and_checkpoints(ortho_run, tmp_path):
    from thermogrammetry.products.raster import Grid, write_cog

    sc, sv, root = ortho_run
    ref = root / "dsm.tif"
    with rasterio.open(ref) as s:
        z = s.read(1).astype(float)
        tr = s.transform
    g = Grid(tr.c, tr.f, tr.a, z.shape[1], z.shape[0])
    rng = np.random.default_rng(5)
    noisy = z + rng.normal(0.05, 0.1, z.shape)  # +5 cm bias, 10 cm noise
    write_cog(tmp_path / "test_dsm.tif", g, "float32", lambda r0, c0, h, w: noisy[r0:r0 + h, c0:c0 + w],
              crs="EPSG:32633", nodata=float("nan"))
    cps = [(n, *p) for n, p in sc.checks.items()] + [(n, *p) for n, p in sc.gcps.items()]
    (tmp_path / "cp.csv").write_text("id,X,Y,Z\n" + "".join(f"{n},{x},{y},{zz}\n" for n, x, y, zz in cps))
    assert main(["evaluate", "--dsm", str(tmp_path / "test_dsm.tif"), "--reference", str(ref), "--checkpoints",
                 str(tmp_path / "cp.csv"), "-o", str(tmp_path / "e")]) == 0
    rep = json.loads((tmp_path / "e" / "evaluate.json").read_text())
    d = rep["dsm_vs_reference"]
    # float32 storage and bilinear sampling at the same cell centres: only the injected error remains
    assert d["n"] > 0.9 * z.size
    assert 0.045 < d["mean"] < 0.055 and 0.095 < d["std"] < 0.105
    assert d["rmse"] == pytest.approx(np.hypot(0.05, 0.1), rel=0.05)
    assert d["p95_abs"] > d["mae"]
    c = rep["checkpoints"]
    # Check-point bounds from the injected error e = DSM - truth ~ N(b = 0.05, s = 0.1) per cell, i.i.d.  The
    # scene's 5 points (3 GCPs, 2 checks) lie on cell corners (measured: bilinear weights 1/4 each, sum w^2 = 1/4)
    # where the true DSM is planar (its own discretisation error < 5e-5 m, measured): dz_i ~ N(b, s^2/4) =
    # N(0.05, 0.05^2). Per point, two-sided at 4 sigma: 0.05 +- 0.20 m. Their RMSE^2 has mean b^2 + s^2/4 = 0.005 and
    # sd sqrt((2 (s/2)^4 + 4 b^2 (s/2)^2) / 5) = 0.0027: at 4 sigma RMSE <= sqrt(0.005 + 0.011) = 0.126 m (with 5
    # points no useful lower bound).
    assert c["n"] == len(cps) == 5 and c["rmse_x"] is None
    assert all(-0.15 < r["dz"] < 0.25 for r in c["points"]), c["points"]
    assert 0.0 < c["rmse_z"] < 0.126, c
    assert (tmp_path / "e" / "evaluate_histogram.png").exists()
    # 400 seeded cell centres (away from the edge): there bilinear sampling returns the cell itself, so dz is the
    # injected error of that cell exactly (float32 storage: |dz - e| < 1e-6 m) and dz ~ N(0.05, 0.1^2), i.i.d.  Mean:
    # 0.05 +- 4 s / sqrt(400) = [0.03, 0.07] (a sign error gives -0.05).  RMSE^2: mean b^2 + s^2 = 0.0125, sd
    # sqrt((2 s^4 + 4 b^2 s^2) / 400) = 8.7e-4; 4 sigma: RMSE in [sqrt(0.0090), sqrt(0.0160)] = [0.095, 0.126] m
    # (an "RMSE" that is the MAE gives 0.092 here: the lower bound matters).
    rows_, cols_ = rng.integers(5, z.shape[0] - 5, 400), rng.integers(5, z.shape[1] - 5, 400)
    keep = np.unique(rows_ * z.shape[1] + cols_, return_index=True)[1]  # distinct cells: independent errors
    rows_, cols_ = rows_[keep], cols_[keep]
    assert rows_.size > 390
    cx, cy = tr.c + (cols_ + 0.5) * tr.a, tr.f + (rows_ + 0.5) * tr.e
    (tmp_path / "cc.csv").write_text("id,X,Y,Z\n" + "".join(
        f"c{k},{float(x)!r},{float(y)!r},{float(z[r, q])!r}\n" for k, (x, y, r, q) in enumerate(zip(cx, cy, rows_, cols_))))
    assert main(["evaluate", "--dsm", str(tmp_path / "test_dsm.tif"), "--checkpoints", str(tmp_path / "cc.csv"),
                 "-o", str(tmp_path / "g")]) == 0
    cc = json.loads((tmp_path / "g" / "evaluate.json").read_text())["checkpoints"]
    dz = np.array([r["dz"] for r in cc["points"]], float)
    injected = noisy.astype(np.float32).astype(float)[rows_, cols_] - z[rows_, cols_]
    assert cc["n"] == rows_.size
    assert 0.03 < dz.mean() < 0.07, dz.mean()
    assert 0.095 < cc["rmse_z"] < 0.126, cc["rmse_z"]
    assert np.max(np.abs(dz - injected)) < 1e-6
    assert main(["evaluate", "--dsm", str(ref), "-o", str(tmp_path / "f")]) == 2
