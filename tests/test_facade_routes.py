"""``thermogrammetry facade``: ``--levelling offsets`` (both routes) and the homography route (``--images``,
``--plane-points``, ``--plane-measurements``) against ground truth.

Scene: an infinite flat wall y = 0 (plane coordinates u = x along, v = z up) carrying the smooth field
``T = 290 + 3 sin(1.3 x) + 2 cos(1.7 z)`` K, seen by pinhole cameras 5 m away (160 x 120 px, f = 150 px: 3.3 cm
pixels; the three stations of tests/test_texture_counts.py, each seeing nearly the whole 4 x 3 m wall). A frame is
the field at its pixel centres' rays (+ per-pixel noise + a per-image offset when said).

Levelling. Per-pixel Gaussian noise sigma_n; a cell value is a bilinear sample, whose noise has variance
sigma_n^2 E[sum w^2] = (4/9) sigma_n^2 for uniform sub-pixel positions, so a pair difference has
sd_d = sqrt(8/9) sigma_n = 0.94 sigma_n. Each image pair shares ~11 000 pixels of wall (12 m^2 / 0.033^2), so an
offset is fixed to ~sd_d / sqrt(11 000) ~ 0.01 sigma_n; the smooth field's bilinear error is <= h^2 f''/8
= 0.033^2 x 5.1 / 8 = 7e-4 K (K frames) and alternates in sign. Bands: 0.005 K for sigma_n = 0.05 K frames
(~10x the noise term, 7x the worst interpolation error), 0.5 count for sigma_n = 5 counts (f'' = 507 counts/m^2:
0.07 count interpolation error). Two-sided: the injected offsets are 0.5-0.8 K / 50-80 counts.

Homography. With exact point measurements the fitted H is the true plane->image map, so each cell must equal the
bilinear sample of its source frame at the TRUE projection of the cell centre (recomputed here, float64) within
float32 rounding (1e-3 K at 290 K). With 0.1 px measurement noise on 12 points the residual RMS (sqrt of the mean
squared 2D residual) has E[rms^2] = sigma^2 (2N - 8) / N = sigma^2 x 16/12, a chi-square with 16 dof: the 0.1 %-99.9 %
band is [0.060, 0.164] px; every corner residual component is < 5 sigma = 0.5 px.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_texture_counts import FOCAL, H, W, _bilinear64, _camera, _gdal_md, _poses  # noqa: E402

from thermogrammetry.cli.main import main  # noqa: E402


def _field_k(x, z):
    return 290.0 + 3.0 * np.sin(1.3 * x) + 2.0 * np.cos(1.7 * z)


def _project(pose, P):
    Xc = P @ pose.R.T + pose.t
    return np.column_stack([FOCAL * Xc[:, 0] / Xc[:, 2] + (W - 1) / 2, FOCAL * Xc[:, 1] / Xc[:, 2] + (H - 1) / 2])


def _render(pose, *, unit, offset, noise, rng):
    gy, gx = np.mgrid[0:H, 0:W].astype(float)
    d = np.stack([(gx - (W - 1) / 2) / FOCAL, (gy - (H - 1) / 2) / FOCAL, np.ones_like(gx)], -1) @ pose.R
    C = pose.center
    t = -C[1] / d[..., 1]
    P = C + t[..., None] * d
    f = _field_k(P[..., 0], P[..., 2])
    if unit == "counts":  # 100 counts per K around 20000
        return np.rint(20000 + 100 * (f - 290.0) + rng.normal(0, noise, f.shape) + offset).astype(np.uint16)
    return (f + rng.normal(0, noise, f.shape) + offset).astype(np.float32)


def _survey(folder, poses, *, unit, offsets, noise, seed=0):
    """An oriented survey folder (cameras.json + frames) with exact poses."""
    import tifffile

    from thermogrammetry.io.oriented import OrientedCameras, OrientedImage

    rng = np.random.default_rng(seed)
    (folder / "frames").mkdir(parents=True)
    ims = []
    for k, (pose, off) in enumerate(zip(poses, offsets)):
        tifffile.imwrite(folder / "frames" / f"t{k}.tif", _render(pose, unit=unit, offset=off, noise=noise, rng=rng))
        ims.append(OrientedImage(f"t{k}", "thermal", pose.R, pose.t, frame=f"frames/t{k}.tif", unit=unit))
    OrientedCameras({"thermal": _camera()}, ims).save(folder / "cameras.json")
    return folder


POINTS_UV = np.array([[u, v] for v in (0.3, 1.5, 2.7) for u in (0.3, 1.4, 2.6, 3.7)])  # 12 points, corners first/last


def _plane_inputs(folder, poses, *, unit, offsets, noise, point_noise_px, seed=0, names=None):
    """Stand-alone frames (float32 TIFFs without a unit, or uint16 counts), points.csv and m.csv."""
    import tifffile

    rng = np.random.default_rng(seed)
    (folder / "frames").mkdir(parents=True)
    names = names or [f"t{k}" for k in range(len(poses))]
    for name, pose, off in zip(names, poses, offsets):
        tifffile.imwrite(folder / "frames" / f"{name}.tif", _render(pose, unit=unit, offset=off, noise=noise, rng=rng))
    (folder / "points.csv").write_text("id,u,v\n" + "".join(f"p{i},{u},{v}\n" for i, (u, v) in enumerate(POINTS_UV)))
    rows = ["image,id,x,y"]
    for k, (name, pose) in enumerate(zip(names, poses)):
        P = np.column_stack([POINTS_UV[:, 0], np.zeros(len(POINTS_UV)), POINTS_UV[:, 1]])
        xy = _project(pose, P) + rng.normal(0, point_noise_px, (len(P), 2))
        label = f"{name}.tif" if k % 2 else name  # named with and without the extension
        rows += [f"{label},p{i},{float(x)!r},{float(y)!r}" for i, (x, y) in enumerate(xy)]
    (folder / "m.csv").write_text("\n".join(rows) + "\n")
    return folder


def _expected(out, frames_dir, poses, names):
    """Each filled cell recomputed independently: bilinear sample of its source frame at the true projection."""
    import tifffile

    d = json.loads((out / "facade.json").read_text())
    vals = tifffile.imread(out / "facade_temperature.tif")
    src = tifffile.imread(out / "facade_source.tif")
    g = d["grid"]
    h, w = g["shape"]
    A = g["a0"] + (np.arange(w) + 0.5) * g["cell"]
    B = g["b1"] - (np.arange(h) + 0.5) * g["cell"]
    AA, BB = np.meshgrid(A, B)
    if d["route"] == "oriented":
        pl = d["plane"]
        P = np.asarray(pl["origin"]) + AA[..., None] * np.asarray(pl["u"]) + BB[..., None] * np.asarray(pl["v"])
    else:  # plane coordinates u = x, v = z
        P = np.stack([AA, np.zeros_like(AA), BB], -1)
    exp = np.full(vals.shape, np.nan)
    for k, name in {int(k): v for k, v in d["index"].items()}.items():
        m = src == k
        if m.any():
            exp[m] = _bilinear64(tifffile.imread(frames_dir / f"{name}.tif"), _project(poses[names.index(name)], P[m]))[0]
    return d, vals, src, exp, AA, BB


# ---------------------------------------------------------------------------------------------------- levelling
CASES = {  # route, unit, injected offsets (frame unit), per-pixel noise, band for the recovered offsets
    "oriented_K": ("oriented", "K", (0.0, 0.8, -0.5), 0.05, 0.005),
    "oriented_counts": ("oriented", "counts", (0.0, 80.0, -50.0), 5.0, 0.5),
    "homography_K": ("homography", "K", (0.0, 0.8, -0.5), 0.05, 0.005),
}


@pytest.fixture(scope="module", params=list(CASES))
def levelled(request, tmp_path_factory):
    route, unit, offsets, noise, band = CASES[request.param]
    root = tmp_path_factory.mktemp(request.param)
    poses = _poses()
    if route == "oriented":
        s = _survey(root / "s", poses, unit=unit, offsets=offsets, noise=noise)
        args = ["facade", str(s), "--plane", "0,0,0,0,-1,0"]
    else:
        s = _plane_inputs(root / "s", poses, unit=unit, offsets=offsets, noise=noise, point_noise_px=0.0)
        args = ["facade", "--images", str(s / "frames"), "--plane-points", str(s / "points.csv"),
                "--plane-measurements", str(s / "m.csv"), "--input-unit", "K"]
    out, out0 = root / "lev", root / "raw"
    assert main([*args, "-o", str(out), "--cell", "0.05", "--levelling", "offsets"]) == 0
    assert main([*args, "-o", str(out0), "--cell", "0.05"]) == 0
    return route, unit, np.asarray(offsets), noise, band, s, poses, out, out0


def test_levelling_recovers_the_injected_offsets(levelled):
    route, unit, offsets, noise, band, s, poses, out, out0 = levelled
    d = json.loads((out / "facade.json").read_text())
    names = [f"t{k}" for k in range(3)]
    assert d["levelling"] == "offsets" and d["values_altered"] is True and "ADDED" in d["values"]
    held = names.index(d["offsets_fixed_image"])
    # the held image is the one supplying most cells
    assert d["cells_per_image"][d["offsets_fixed_image"]] == max(d["cells_per_image"].values())
    est = np.array([d["offsets"][n] for n in names])
    sig = np.array([d["offsets_sigma"][n] for n in names])
    # o_k levels image k onto the held one: T_k + o_k = T_held  ->  o_k = -(injected_k - injected_held)
    truth = -(offsets - offsets[held])
    assert est[held] == 0.0 and sig[held] == 0.0
    np.testing.assert_array_less(np.abs(est - truth), band)  # measured: see the note (figures per case)
    others = [k for k in range(3) if k != held]
    assert np.all((sig[others] > 0) & (sig[others] < band))
    rms_key = "offsets_rms_before_after_counts" if unit == "counts" else "offsets_rms_before_after_k"
    rb, ra = d[rms_key]
    sd_d = np.sqrt(8 / 9) * noise  # pair difference of two bilinear samples (module docstring)
    assert 0.8 * sd_d < ra < 1.25 * sd_d and rb > 5 * ra
    assert d["offsets_not_levelled"] == [] and d["offsets_cells_sampled"] > 1000


def test_levelled_cells_are_source_values_plus_their_offset(levelled):
    route, unit, offsets, noise, band, s, poses, out, out0 = levelled
    names = [f"t{k}" for k in range(3)]
    d, vals, src, exp, _, _ = _expected(out, s / "frames", poses, names)
    _, vals0, src0, _, _, _ = _expected(out0, s / "frames", poses, names)
    np.testing.assert_array_equal(src, src0)  # levelling changes values, not the image choice
    ok = src >= 0
    assert ok.mean() > 0.9
    off = np.array([d["offsets"][names[k]] for k in range(3)])
    tol = 0.004 if unit == "counts" else 1e-3  # float32 of ~2e4 counts / ~290 K
    assert np.max(np.abs(vals[ok] - (exp[ok] + off[src[ok]]))) < tol
    held = names.index(d["offsets_fixed_image"])
    h = src == held
    assert h.sum() > 1000 and np.array_equal(vals[h], vals0[h])  # the held image's cells are unchanged
    if unit == "counts":  # counts stay counts: labelled, in the count range, offsets in counts
        assert d["unit"] == "counts" and d["quantity"] == "raw_counts" and "offsets_rms_before_after_counts" in d
        assert 19000 < np.nanmin(vals) and np.nanmax(vals) < 21000
        assert "counts" in _gdal_md(out / "facade_temperature.tif") and "(counts)" in d["offsets_note"]
    else:
        assert d["unit"] == "K" and 280 < np.nanmin(vals) < np.nanmax(vals) < 300


def test_without_levelling_nothing_is_altered(levelled):
    route, unit, offsets, noise, band, s, poses, out, out0 = levelled
    d = json.loads((out0 / "facade.json").read_text())
    assert d["levelling"] == "none" and d["offsets"] is None and d["values_altered"] is False


# --------------------------------------------------------------------------------------------- homography route
@pytest.fixture(scope="module")
def homography(tmp_path_factory):
    from thermogrammetry.geometry import Pose

    root = tmp_path_factory.mktemp("homography")
    poses = _poses() + [Pose.look_at((5.0, -4.0, 2.0), (2.0, 0.0, 1.5)),  # oblique: a real perspective homography
                        Pose.look_at((2.0, -5.0, 1.5), (2.0, 0.0, 1.5)), Pose.look_at((1.0, -5.0, 1.5), (1.0, 0.0, 1.5))]
    names = ["t0", "t1", "t2", "obl", "three", "line"]
    s = _plane_inputs(root / "s", poses, unit="K", offsets=[0.0] * 6, noise=0.0, point_noise_px=0.1, names=names)
    # "three": only 3 measured points; "line": 4 points, three of them on the line v = 0.3
    m = [r for r in (s / "m.csv").read_text().splitlines()]
    keep_three = {"p0", "p5", "p11"}
    keep_line = {"p0", "p1", "p2", "p5"}
    m = [r for r in m if not r.startswith(("three", "line"))
         or (r.split(",")[0].startswith("three") and r.split(",")[1] in keep_three)
         or (r.split(",")[0].startswith("line") and r.split(",")[1] in keep_line)]
    (s / "m.csv").write_text("\n".join(m) + "\n")
    frames = [str(s / "frames" / f"{n}.tif") for n in names]
    out = root / "out"
    code = main(["facade", "--images", *frames, "--plane-points", str(s / "points.csv"), "--plane-measurements",
                 str(s / "m.csv"), "--input-unit", "K", "--cell", "0.05", "-o", str(out), "--unit", "C"])
    return s, poses, names, out, code


def test_homography_route_residuals_and_bad_images(homography, capsys):
    s, poses, names, out, code = homography
    assert code == 0
    d = json.loads((out / "facade.json").read_text())
    assert d["route"] == "homography" and d["unit"] == "C"
    skipped = {x["image"]: x["reason"] for x in d["skipped"]}
    assert set(skipped) == {"three", "line"}
    assert "at least 4" in skipped["three"] and "collinear" in skipped["line"]
    assert set(d["homographies"]) == {"t0", "t1", "t2", "obl"}
    for n, hm in d["homographies"].items():
        assert hm["points"] == 12
        assert 0.060 < hm["rms_px"] < 0.164  # 0.1 px noise, chi-square 16 dof (module docstring)
        for corner in ("p0", "p3", "p8", "p11"):
            assert np.all(np.abs(hm["residuals_px"][corner]) < 0.5)
    # no orientation: no viewing-angle raster, and facade.json says so
    assert not (out / "facade_angle.tif").exists() and "facade_angle.tif" not in d["files"] and "angle" in d
    for f in ("facade_temperature.tif", "facade_source.tif", "facade_resolution.tif", "facade.png"):
        assert (out / f).stat().st_size > 100


def test_homography_cells_equal_the_source_frame_at_the_true_projection(homography):
    """Noisy points: the fitted H moves the sampling point by < 0.5 px inside the points' hull; the field's gradient
    is <= 3 x 1.3 + 2 x 1.7 = 7.3 K/m = 0.24 K/px, so cells are within 0.12 K of the true-projection sample."""
    s, poses, names, out, code = homography
    d, vals, src, exp, AA, BB = _expected(out, s / "frames", poses, names)
    vals = vals + 273.15  # --unit C
    ok = src >= 0
    assert len(np.unique(src[ok])) >= 2 and ok.mean() > 0.8
    hull = ok & (AA > 0.3) & (AA < 3.7) & (BB > 0.3) & (BB < 2.7)
    err = np.abs(vals[hull] - exp[hull])
    assert hull.sum() > 2000 and err.max() < 0.12 and np.median(err) < 0.03


def test_homography_exact_points_give_the_frame_values(tmp_path):
    """Exact measurements: H is the true map and every cell equals the independent sample within float32."""
    from thermogrammetry.geometry import Pose

    poses = [_poses()[0], Pose.look_at((5.0, -4.0, 2.0), (2.0, 0.0, 1.5))]
    s = _plane_inputs(tmp_path / "s", poses, unit="K", offsets=[0, 0], noise=0.0, point_noise_px=0.0)
    out = tmp_path / "out"
    assert main(["facade", "--images", str(s / "frames" / "t0.tif"), str(s / "frames" / "t1.tif"), "--plane-points",
                 str(s / "points.csv"), "--plane-measurements", str(s / "m.csv"), "--input-unit", "K",
                 "--cell", "0.04", "-o", str(out)]) == 0
    d, vals, src, exp, AA, BB = _expected(out, s / "frames", poses, ["t0", "t1"])
    ok = src >= 0
    assert ok.mean() > 0.8 and set(np.unique(src[ok])) == {0, 1}
    assert np.max(np.abs(vals[ok] - exp[ok])) < 1e-3
    assert all(hm["rms_px"] < 1e-6 for hm in d["homographies"].values())


@pytest.mark.parametrize("points, meas, words", [
    ("id,u,v\np0,0.3,0.3\np1,abc,1\n", None, ["points.csv", "row 3", "'abc'"]),
    ("id,u\np0,0.3\n", None, ["points.csv", "missing column", "v"]),
    (None, "image,id,x,y\nt0,p0,10,10\nt0,p99,20,20\n", ["m.csv", "row 3", "'p99'"]),
    (None, "image,id,x,y\nt0,p0,10,zz\n", ["m.csv", "row 2", "'zz'"]),
])
def test_bad_csv_exit_2_naming_file_line_value(tmp_path, capsys, points, meas, words):
    s = _plane_inputs(tmp_path / "s", _poses()[:1], unit="K", offsets=[0], noise=0.0, point_noise_px=0.0)
    if points is not None:
        (s / "points.csv").write_text(points)
    if meas is not None:
        (s / "m.csv").write_text(meas)
    out = tmp_path / "out"
    assert main(["facade", "--images", str(s / "frames"), "--plane-points", str(s / "points.csv"),
                 "--plane-measurements", str(s / "m.csv"), "--input-unit", "K", "-o", str(out)]) == 2
    err = capsys.readouterr().err.replace("\n", " ")
    for w in words:
        assert w in err
    assert not out.exists()


def test_nothing_rectified_exit_1_names_every_image(tmp_path, capsys):
    s = _plane_inputs(tmp_path / "s", _poses()[:2], unit="K", offsets=[0, 0], noise=0.0, point_noise_px=0.0)
    rows = (s / "m.csv").read_text().splitlines()
    (s / "m.csv").write_text("\n".join(rows[:4]) + "\n")  # 3 points of t0, none of t1
    out = tmp_path / "out"
    assert main(["facade", "--images", str(s / "frames"), "--plane-points", str(s / "points.csv"),
                 "--plane-measurements", str(s / "m.csv"), "--input-unit", "K", "-o", str(out)]) == 1
    err = capsys.readouterr().err.replace("\n", " ")
    assert "t0: 3 point(s)" in err and "t1: no measurements" in err and not out.exists()


def test_float_tiff_without_unit_needs_input_unit(tmp_path, capsys):
    s = _plane_inputs(tmp_path / "s", _poses()[:1], unit="K", offsets=[0], noise=0.0, point_noise_px=0.0)
    out = tmp_path / "out"
    assert main(["facade", "--images", str(s / "frames"), "--plane-points", str(s / "points.csv"),
                 "--plane-measurements", str(s / "m.csv"), "-o", str(out)]) == 1
    assert "--input-unit" in capsys.readouterr().err and not out.exists()


@pytest.mark.parametrize("where", ["frames", "s", "frames-link"])
def test_out_in_or_around_the_image_folder_is_refused_first(tmp_path, capsys, where):
    """OUT inside the frames' folder, holding it, or a link to it: exit 2 before anything is read; the user's
    frames and files untouched."""
    s = _plane_inputs(tmp_path / "s", _poses()[:1], unit="K", offsets=[0], noise=0.0, point_noise_px=0.0)
    before = sorted((p.relative_to(s), p.stat().st_size) for p in s.rglob("*"))
    if where == "frames-link":
        out = tmp_path / "link"
        out.symlink_to(s / "frames")
    else:
        out = (s / "frames" / "out") if where == "frames" else s
    assert main(["facade", "--images", str(s / "frames"), "--plane-points", str(s / "points.csv"),
                 "--plane-measurements", str(s / "m.csv"), "--input-unit", "K", "-o", str(out)]) == 2
    err = capsys.readouterr().err.replace("\n", " ")
    assert "image folder" in err and str(s / "frames") in err, err
    assert sorted((p.relative_to(s), p.stat().st_size) for p in s.rglob("*")) == before


# ------------------------------------------------------------------------------------------ level_offsets itself
def test_level_offsets_sigma_matches_the_spread_and_unlinked_images_are_left_alone():
    """Rows with exactly two images (independent pairs, the case where the formal sigma is exact): over 300
    repetitions the spread of each estimated offset matches the mean formal sigma within 15 % (the sd of a
    300-sample sd is 4 %). Images 3 and 4 overlap only each other: not levelled, offset 0, sigma NaN."""
    from thermogrammetry.products.facade import level_offsets

    true = np.array([0.0, 0.7, -0.4, 5.0, 2.0])
    K, S, sd = 5, 600, 0.1
    est, sig = [], []
    for rep in range(300):
        rng = np.random.default_rng(rep)
        V = np.full((S, K), np.nan)
        pairs = [(0, 1), (1, 2), (0, 2), (3, 4)]
        for r in range(S):
            a, b = pairs[r % 4]
            V[r, a], V[r, b] = 300 - true[a] + rng.normal(0, sd), 300 - true[b] + rng.normal(0, sd)
        lev = level_offsets(V, cells_per_image=[900, 500, 400, 800, 100])
        est.append(lev.offsets)
        sig.append(lev.sigma)
    est, sig = np.array(est), np.array(sig)
    assert lev.fixed == 0 and list(lev.connected) == [True, True, True, False, False]
    np.testing.assert_allclose(est[:, 1:3].mean(axis=0), true[1:3], atol=4 * sd / np.sqrt(150 * 300))
    ratio = est[:, 1:3].std(axis=0) / sig[:, 1:3].mean(axis=0)
    assert np.all((ratio > 0.85) & (ratio < 1.15)), ratio
    assert np.all(est[:, 3:] == 0) and np.all(np.isnan(sig[:, 3:])) and np.all(sig[:, 0] == 0)
    assert "not levelled" in lev.note
