"""``thermogrammetry survey`` end to end: a rendered UAV block with the user's files only (GNSS CSV, GCPs, check
points and their noisy image measurements), bad inputs mixed in, and the real DJI M3T flight.

Accuracy bounds (issue 10): check-point RMSE <= 0.5 GSD in X and Y and <= 1 GSD in Z. The block is shaped
like a DJI M3T flight (61° field of view) at 80/60 % overlap; with 0.3 px marker noise, 3-5 cm GNSS and
the block's tie points the reported σ of the interior check points is 0.02 m (XY) and 0.06-0.1 m (Z), i.e.
0.15 and 0.5-0.8 GSD: the bounds hold with a margin of about 2σ, and each check point's error must also lie
within 4 of its own reported σ (two-sided consistency of the precision).
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from conftest import data_missing
from thermogrammetry.cli.main import main
from thermogrammetry.io.oriented import OrientedCameras
from thermogrammetry.pipeline.project import FolderProject


GNSS_BLUNDER = "T0020"  # its GNSS position is moved 0.60 m in X in the user's gnss.csv


@pytest.fixture(scope="module")
def block(scene_cache):
    """The rendered block with bad inputs mixed in and its survey (GNSS, GCPs, check points): built once per test
    run and shared by the xdist workers (``cached_scenes.uav_block``: a frame of another flight, a truncated file,
    ``gcps.csv`` among the frames, two frames without GNSS, a GCP "measured" in a frame where it is not visible)."""
    from cached_scenes import uav_block

    return uav_block(scene_cache)


def test_contract_files_and_counts(block):
    assert block["code"] == 0
    s = json.loads((block["out"] / "survey.json").read_text())
    n = len(block["scene"].frames)
    assert s["images_total"] == n + 2  # the frames, the other flight's frame and the truncated file; not gcps.csv
    assert any("gcps.csv" in n_ and "skipped" in n_ for n_ in s["notes"]), s["notes"]
    assert s["images_oriented"] == n  # every frame of the block, the frames without GNSS included
    assert s["components"] == [n]
    status = {im["name"]: im for im in s["images"]}
    assert not status["ZZ_other_flight"]["oriented"] and status["ZZ_other_flight"]["reason"]
    assert not status["T0005_truncated.tif"]["oriented"] and "T0005_truncated" in status["T0005_truncated.tif"]["reason"]
    assert all(status[d]["oriented"] for d in block["dropped"])
    assert any("without a GNSS position" in n_ and "T0010" in n_ for n_ in s["notes"]), s["notes"]
    assert s["crs"] == f"EPSG:{block['scene'].terrain.epsg}"
    for key in ("reprojection_rms_px", "seconds"):
        assert s[key] > 0
    for k in ("n", "rmse_x", "rmse_y", "rmse_z", "mae_x", "mae_y", "mae_z", "min_x", "max_z"):
        assert k in s["gcps"] and k in s["checkpoints"]
    # the wrong GCP measurement is found and named
    rej = s["gcp_rejected_measurements"]
    assert [(r["image"], r["id"]) for r in rej] == [(block["far"], "GCP01")]
    # cameras.json in the one schema, COLMAP text model, clouds with temperatures
    oc = OrientedCameras.load(block["out"] / "cameras.json")
    assert len(oc) == n and oc.crs == s["crs"]
    assert all(np.all(np.isfinite(im.center_std)) and np.all(im.center_std > 0) for im in oc)
    import laspy

    las = laspy.read(block["out"] / "sparse.las")
    assert len(las.points) == s["points"]
    t = np.asarray(las.temperature_k)
    assert 250 < np.median(t) < 350  # kelvin of a summer scene, not counts or °C


def test_contract_colmap_model_reads_in_pycolmap(block):
    """The COLMAP text model of the contract run, read by pycolmap (optional: its own test, so that a missing
    pycolmap skips only this check, at the start, never the contract's other asserts)."""
    pycolmap = pytest.importorskip("pycolmap")
    assert block["code"] == 0
    s = json.loads((block["out"] / "survey.json").read_text())
    rec = pycolmap.Reconstruction(str(block["out"] / "colmap"))
    assert rec.num_reg_images() == len(block["scene"].frames) and rec.num_points3D() == s["points"] > 0


@pytest.fixture(scope="module")
def block_gnss_blunder(block, scene_cache):
    """The same frames with one wrong GNSS tag: T0020 0.60 m off in X (20 σ of the RTK σ 3 cm); no GCPs."""
    from cached_scenes import survey_variant, tie_cache

    def build(folder):
        lines = (block["root"] / "survey" / "user" / "gnss.csv").read_text().splitlines()
        hdr = lines[0].split(",")
        for k, ln in enumerate(lines):
            v = ln.split(",")
            if v[0] == GNSS_BLUNDER:
                v[hdr.index("X")] = repr(float(v[hdr.index("X")]) + 0.60)
                lines[k] = ",".join(v)
        (folder / "gnss_blunder.csv").write_text("\n".join(lines) + "\n")
        return main(["survey", str(block["root"] / "survey" / "images"), "-o", str(folder / "out"), "--workers", "0",
                     "--gnss", str(folder / "gnss_blunder.csv"), "--crs", f"EPSG:{block['scene'].terrain.epsg}",
                     *tie_cache(scene_cache)])

    return survey_variant(scene_cache, "uav-block-seed0-gnss-blunder", {"image": GNSS_BLUNDER, "dx": 0.60}, build)


def test_gnss_blunder_is_named_and_left_out(block, block_gnss_blunder):
    """A wrong GNSS tag (0.60 m in X, 20 σ) among RTK positions: the frame is oriented from its tie points, its GNSS
    position is left out of the final adjustment and named with its misfit; no other frame is flagged.

    The misfit is the adjusted antenna position minus the given one: -0.60 m in X up to the frame's own error
    (centres within 3 cm RMS, 11 cm worst: test_pose_and_camera_accuracy), so ±0.11 m; Y and Z within 0.11 m.
    The consistent block (same frames, right tags) flags nothing."""
    code, out = block_gnss_blunder
    assert code == 0
    s0 = json.loads((block["out"] / "survey.json").read_text())
    assert s0["gnss_flagged"] == [] and all(im.get("gnss_used", True) for im in s0["images"])
    s = json.loads((out / "survey.json").read_text())
    flagged = s["gnss_flagged"]
    assert [g["image"] for g in flagged] == [GNSS_BLUNDER], flagged
    g = flagged[0]
    assert g["used"] is False and g["sigma"] > 5
    assert abs(g["dx"] + 0.60) <= 0.11 and abs(g["dy"]) <= 0.11 and abs(g["dz"]) <= 0.11, g
    assert any(GNSS_BLUNDER in n_ and "left out of the final adjustment" in n_ for n_ in s["notes"]), s["notes"]
    st = {im["name"]: im for im in s["images"]}
    assert st[GNSS_BLUNDER]["oriented"] and st[GNSS_BLUNDER]["gnss_used"] is False
    # the other frames: statistics of the used GNSS positions, every one within 5 σ, the frames without GNSS absent
    n_gnss = sum(1 for im in s["images"] if "gnss_residual_m" in im)
    assert n_gnss == len(block["scene"].frames) - len(block["dropped"])
    assert s["gnss"]["n"] == n_gnss - 1
    assert all(im["gnss_residual_sigma"] <= 5 for im in s["images"] if "gnss_residual_m" in im and im["name"] != GNSS_BLUNDER)
    for a in "xyz":  # RTK σ 3/3/5 cm; the adjusted centres agree with the GNSS to about that
        assert 0.005 < s["gnss"]["rmse_" + a] < 0.08, s["gnss"]
    assert "Camera centres against GNSS" in (out / "report.html").read_text()


def test_pose_and_camera_accuracy(block):
    """Camera centres and intrinsics against the scene's truth (never used in the estimate).

    Centres: the block must not be worse than its GNSS (σ 3 cm horizontal, 5 cm vertical per frame): RMS per
    axis <= 3 cm, worst <= 11 cm. Measured: RMS 2.6 / 2.9 / 0.8 cm, worst 10.5 cm (T0031: -10.5 cm in X with
    -0.11 deg about x, a shift-tilt trade of one frame that leaves its ground rays in place; ~10 cm before the
    SIFT keypoint convention fix too, which moved every tie observation by 0.25 px and so redrew the block's
    errors; /work/notes/rigfix.md). The reported centre σ (mean 1.4 / 1.3 /
    1.0 cm) is smaller than that scatter in plan by a factor of ~1.6 (tie-point errors of rendered frames are
    not independent); it is checked against that measured factor so that a regression shows."""
    scene = block["scene"]
    oc = OrientedCameras.load(block["out"] / "cameras.json")
    true = {f.name: f.pose for f in scene.frames}
    E = np.array([im.center - true[im.name].center for im in oc])
    S = np.array([im.center_std for im in oc])
    rms = np.sqrt(np.mean(E**2, axis=0))
    assert np.all(rms <= [0.03, 0.03, 0.03]), rms
    assert np.abs(E).max() <= 0.11
    ratio = np.sqrt(np.mean((E / S) ** 2, axis=0))
    assert np.all(ratio > 0.5) and np.all(ratio < 2.5), ratio
    cam = oc.cameras["thermal"]
    truth = scene.camera
    for p in ("fx", "cx", "cy", "k1"):
        sd = cam.param_std[cam.param_names.index(p)]
        assert abs(cam[p] - truth[p]) < 4.5 * sd, (p, cam[p], truth[p], sd)


def test_checkpoint_accuracy(block):
    s = json.loads((block["out"] / "survey.json").read_text())
    cfg = block["scene"].config
    gsd = cfg.flight_height_m * cfg.pixel_pitch_um * 1e-6 / (cfg.focal_mm * 1e-3)
    cp = s["checkpoints"]
    assert cp["n"] >= 6
    assert cp["rmse_x"] <= 0.5 * gsd and cp["rmse_y"] <= 0.5 * gsd, cp
    assert cp["rmse_z"] <= 1.0 * gsd, cp
    for c in s["checkpoint_errors"]:
        if "dx" in c:
            for a in "xyz":
                assert abs(c["d" + a]) < 4.0 * c["s" + a], c


def test_every_gcp_measurement_is_reported_with_its_residual(block):
    """Each of the user's GCP image measurements is in survey.json with its residual at the adjusted state, and the
    one left out says why; per GCP and per image the counts add up.

    The measurements carry 0.3 px of noise per axis (``write_user_files(marker_sigma_px=0.3)``); the σ estimated
    from their residuals (``sqrt(Σ|v|² / (2n − 3G))``, 76 degrees of freedom here) has a relative standard error of
    about 1/sqrt(2·76) = 8 %: 0.22-0.40 px is 0.3 px within about ±3.5 of those (the GCPs' 1-2 cm coordinates are
    counted as unknowns, so the estimate leans high; measured 0.358 px). The reported residuals are recomputed by
    projection and must give the adjustment's own estimate (the same state, to rounding)."""
    s = json.loads((block["out"] / "survey.json").read_text())
    rows = s["gcp_measurements"]
    given = (block["root"] / "survey" / "user" / "gcp_measurements.csv").read_text().strip().splitlines()[1:]
    assert len(rows) == len(given) and {(r["image"], r["id"]) for r in rows} == {tuple(ln.split(",")[:2]) for ln in given}
    left = [r for r in rows if not r["used"]]
    assert [(r["image"], r["id"]) for r in left] == [(block["far"], "GCP01")]
    assert "wrong identification" in left[0]["reason"] and left[0]["residual_px"] > 25.0
    used = [r for r in rows if r["used"]]
    # 5 σ (0.3 px per axis) of a residual's length: P(any of the ~47 > 1.5 px) = 47 exp(-12.5) ~ 2e-4 from the noise
    assert all(r["reason"] == "" and r["residual_px"] < 5.0 * 0.3 for r in used), max(r["residual_px"] for r in used)
    v = np.array([[r["dx_px"], r["dy_px"]] for r in used])
    ms = s["blocks"][0]["marker_sigma"]
    dof = 2 * len(used) - 3 * len({r["id"] for r in used})
    assert ms["dof"] == dof
    assert np.sqrt(np.sum(v**2) / dof) == pytest.approx(ms["estimated_px"], rel=1e-6)
    assert 0.22 <= ms["estimated_px"] <= 0.40, ms
    for key, table in (("id", s["gcp_measurements_by_gcp"]), ("image", s["gcp_measurements_by_image"])):
        assert sum(t["measurements"] for t in table) == len(rows) and sum(t["used"] for t in table) == len(used)
        for t in table:
            mine = [r["residual_px"] for r in used if r[key] == t[key]]
            assert t["used"] == len(mine)
            if mine:
                assert t["rms_px"] == pytest.approx(float(np.sqrt(np.mean(np.square(mine)))), rel=1e-9)
    assert "GCP image measurements" in (block["out"] / "report.html").read_text()


def test_report_header_point_table_ellipses_and_vectors_at_the_points(block):
    """The report's header (version, the command as typed, CRS, inputs, flying height near the scene's); survey.json
    carries what its maps need: the given coordinates of every GCP and check point (the vectors' map positions), the
    centres' covariance whose diagonal is cameras.json's σ², and the footprints' area and overlap."""
    import shlex

    import thermogrammetry
    from report_fields import header_fields
    from thermogrammetry.pipeline.survey.report_figures import control_points

    s = json.loads((block["out"] / "survey.json").read_text())
    page = (block["out"] / "report.html").read_text()
    f = header_fields(page)
    user = block["root"] / "survey" / "user"
    assert f["software"] == f"thermogrammetry {thermogrammetry.__version__}"
    assert f["command"].startswith(shlex.join(["thermogrammetry", "survey", str(block["root"] / "survey" / "images"),
                                               "-o", str(block["out"])]))
    assert f["crs"].startswith(f"EPSG:{block['scene'].terrain.epsg} (")
    assert f"{s['images_total']} thermal images in {(block['root'] / 'survey' / 'images').resolve()}" in f["inputs"]
    assert f"GCPs: {(user / 'gcps.csv').resolve()}" in f["inputs"]
    cfg = block["scene"].config
    assert abs(s["footprints"]["flying_height_m"] - cfg.flight_height_m) < 0.1 * cfg.flight_height_m
    gsd = cfg.flight_height_m * cfg.pixel_pitch_um * 1e-6 / (cfg.focal_mm * 1e-3)
    assert s["footprints"]["gsd_m"] == pytest.approx(gsd, rel=0.1) and s["footprints"]["images_per_cell_max"] >= 3
    # the map positions are the given coordinates, point by point (not list positions)
    given = {}
    for name in ("gcps.csv", "checkpoints.csv"):
        for ln in (user / name).read_text().strip().splitlines()[1:]:
            c = ln.split(",")
            given[c[0]] = (float(c[1]), float(c[2]))
    pts = control_points(s)
    assert len(pts) == s["gcps"]["n"] + s["checkpoints"]["n"] >= 6
    for p in pts:
        assert p["xy"] == pytest.approx(given[p["id"]], abs=1e-6), p["id"]
        assert f"<td class=l>{p['id']}</td>" in page
    # the ellipses' covariance: its diagonal is the σ² of cameras.json (one adjustment, one covariance)
    cams = {im.name: im for im in OrientedCameras.load(block["out"] / "cameras.json")}
    cov = {im["name"]: np.asarray(im["center_cov_m2"]) for im in s["images"] if "center_cov_m2" in im}
    assert len(cov) == s["images_oriented"]
    for n_, C in cov.items():
        np.testing.assert_allclose(np.sqrt(np.diag(C)), cams[n_].center_std, rtol=1e-9)
        assert np.all(np.linalg.eigvalsh(C) > 0)
    assert "error ellipses of the camera centres" in page and "magnified ×" in page


def test_the_block_says_how_well_it_determines_its_camera(block):
    """The UAV block (relief, GCPs at several heights, 56 frames) self-calibrates fx, fy and the distortion; its
    covariance determines the focal length to 0.06 % and separates it from the flying height (correlation 0.18,
    measured): bounds 0.5 % and |r| < 0.6. (A flat field controlled by GCPs alone correlates them near ±1,
    tests/test_determinability.py; with RTK GNSS on the cameras, benchmarks/survey_flatfield.py seed 0 gives r = 0.23.)"""
    s = json.loads((block["out"] / "survey.json").read_text())
    det = s["blocks"][0]["determinability"]["thermal"]
    assert 0 < det["focal_sigma_rel"] < 0.005 and abs(det["focal_height_correlation"]) < 0.6, det
    assert 0 < det["distortion_corner_sigma_px"] < 0.3 and 0 < det["mean_height_sigma_m"] < 0.1, det
    # the choice per camera: the files' EXIF focal length enters as a weighted prior while fx, fy are estimated
    cal = s["blocks"][0]["calibration"]["thermal"]
    assert cal["choice"] == "prior" and {"fx", "fy", "k1"} <= set(cal["estimated"]) and "± " in cal["reason"], cal


@pytest.fixture(scope="module")
def block_geoid(block, scene_cache):
    """The same block with every GNSS height 48.30 m higher (ellipsoidal GNSS heights against GCPs in national
    heights: the geoid is ~48-50 m above the ellipsoid in Switzerland, EPSG:2056) and X 1.50 m off."""
    from cached_scenes import survey_variant, tie_cache

    def build(folder):
        scene = block["scene"]
        user = block["root"] / "survey" / "user"
        lines = (user / "gnss.csv").read_text().splitlines()
        hdr = lines[0].split(",")
        ix, iz = hdr.index("X"), hdr.index("Z")
        out_lines = [lines[0]]
        for ln in lines[1:]:
            v = ln.split(",")
            v[ix], v[iz] = repr(float(v[ix]) + 1.50), repr(float(v[iz]) + 48.30)
            out_lines.append(",".join(v))
        (folder / "gnss_geoid.csv").write_text("\n".join(out_lines) + "\n")
        return main(["survey", str(block["root"] / "survey" / "images"), "-o", str(folder / "out"), "--workers", "0",
                     "--gnss", str(folder / "gnss_geoid.csv"), "--crs", f"EPSG:{scene.terrain.epsg}",
                     "--gcps", str(user / "gcps.csv"), "--gcp-measurements", str(user / "gcp_measurements.csv"),
                     "--checkpoints", str(user / "checkpoints.csv"),
                     "--check-measurements", str(user / "check_measurements.csv"), *tie_cache(scene_cache)])

    return survey_variant(scene_cache, "uav-block-seed0-gnss-geoid", {"dx": 1.50, "dz": 48.30}, build)


def test_gnss_datum_offset_against_the_gcps_is_found_and_removed(block, block_geoid):
    """GNSS and GCPs in different references: the offset is measured on an adjustment on the GCPs alone, the GNSS
    positions are shifted by it, and the block is no longer torn between GNSS (σ 3/5 cm) and GCPs 48 m apart.

    The offset is known to the common-mode error of a block adjusted on 6 GCPs: ~0.10-0.14 m per axis, its
    reported σ (median centre σ). Measured (seed 0): consistent GNSS (+0.11, -0.08, +0.13) m ± (0.10, 0.11, 0.14),
    not applied; with (+0.40, 0, +48.30) m added, Z found at -48.14 and applied, X (-0.29) below 5σ and left. The
    offset is checked at 3σ; what is left of it (<= 3σ ~ 0.4 m, typically 0.1-0.15 m) reaches the check points,
    so they are bounded by 1.5 GSD in X, Y and Z here instead of the 0.5/0.5/1 GSD of consistent GNSS."""
    code, out = block_geoid
    assert code == 0
    s = json.loads((out / "survey.json").read_text())
    off = s["blocks"][0]["gnss_offset"]
    o, sd = np.array(off["offset_m"]), np.array(off["std_m"])
    # X, Y: the common-mode error of 6 GCPs; Z also the lens's focal σ (5 %) x the 50 m flying height, hypot(., 2.5 m):
    # GCPs cannot separate a flying height from a focal length that is only the lens's nominal value
    assert np.all((sd[:2] > 0.02) & (sd[:2] < 0.3)) and 2.5 < sd[2] < np.hypot(0.3, 2.5), sd
    assert np.all(np.abs(o - [-1.50, 0.0, -48.30]) <= 3 * sd), (o, sd)
    assert off["applied_m"][1] == 0.0 and off["applied_m"][0] == pytest.approx(o[0]) and off["applied_m"][2] == pytest.approx(o[2])
    assert any("differ from the" in n_ and "GCPs by a constant" in n_ for n_ in s["notes"])
    cfg = block["scene"].config
    gsd = cfg.flight_height_m * cfg.pixel_pitch_um * 1e-6 / (cfg.focal_mm * 1e-3)
    cp = s["checkpoints"]
    assert max(cp["rmse_x"], cp["rmse_y"], cp["rmse_z"]) <= 1.5 * gsd, cp
    # the consistent block: the check ran and shifted nothing
    s0 = json.loads((block["out"] / "survey.json").read_text())
    off0 = s0["blocks"][0]["gnss_offset"]
    assert off0["applied_m"] == [0.0, 0.0, 0.0] and np.all(np.abs(off0["offset_m"]) < 5 * np.array(off0["std_m"])), off0


def test_bad_arguments_exit_2_and_write_nothing(tmp_path, block):
    out = tmp_path / "o"
    assert main(["survey", str(tmp_path / "nothing_here"), "-o", str(out), "--workers", "0"]) == 2
    assert not out.exists()
    assert main(["survey", str(block["root"] / "survey" / "images"), "-o", str(out), "--gcps", "x.csv"]) == 2
    assert main(["survey", str(block["root"] / "survey" / "images"), "-o", str(out), "--crs", "EPSG:99999999"]) == 2
    assert not out.exists()
    # a malformed row of a user's CSV stops the run before any frame is decoded (it was found in the matching step)
    bad = tmp_path / "gnss_bad.csv"
    bad.write_text("image,X,Y,Z\nT0000,np.float64(1.0),2,3\n")
    assert main(["survey", str(block["root"] / "survey" / "images"), "-o", str(out), "--gnss", str(bad)]) == 2
    bad_cp = tmp_path / "cp_bad.csv"
    bad_cp.write_text("id,X,Y\nA,1,2\n")
    user = block["root"] / "survey" / "user"
    assert main(["survey", str(block["root"] / "survey" / "images"), "-o", str(out), "--checkpoints", str(bad_cp),
                 "--check-measurements", str(user / "check_measurements.csv")]) == 2
    assert not out.exists()
    assert not list(tmp_path.glob(".o.partial-*"))


def test_workers_give_identical_results(tmp_path, block):
    """Features and matching on a local dask cluster equal the in-process run bit for bit."""
    from thermogrammetry.pipeline.survey import SurveyInput, SurveyOptions, step_features, step_inputs, step_matching

    imgs = sorted((block["root"] / "survey" / "images").glob("T000*.tif"))[:6]
    outs = []
    for w in (0, 2):
        proj = FolderProject(tmp_path / f"w{w}")
        opt = SurveyOptions(workers=w, gnss="none")
        step_inputs(proj, SurveyInput([str(p) for p in imgs]), opt)
        step_features(proj, opt)
        step_matching(proj, opt)
        outs.append(proj)
    a, b = outs
    keys = sorted(k for k in a.keys() if k.startswith(("features/", "matches/")))
    assert keys and keys == sorted(k for k in b.keys() if k.startswith(("features/", "matches/")))
    assert all(a.read_bytes(k) == b.read_bytes(k) for k in keys)


@pytest.fixture(scope="module")
def m3t(scene_cache, shared_data):
    """``survey`` on the shared M3T flight with its defaults, once per test run (shared by the xdist workers)."""
    from cached_scenes import survey_variant, tie_cache

    src = shared_data / "uav_m3t_flight" / "Test_image"
    if not src.is_dir():
        data_missing(f"{src} is absent")
    code, out = survey_variant(scene_cache, "m3t-survey", {"src": str(src)},
                               lambda folder: main(["survey", str(src), "-o", str(folder / "out"), "--workers", "0",
                                                    *tie_cache(scene_cache)]))
    return src, out, code, tie_cache(scene_cache)


@pytest.mark.realdata
def test_real_m3t_flight(m3t):
    """The shared DJI M3T flight: 32/32 frames oriented from raw counts, centres within a few cm of RTK but one."""
    src, out, code, cache = m3t
    assert code == 0
    s = json.loads((out / "survey.json").read_text())
    assert s["images_oriented"] == 32 and s["components"] == [32]
    assert s["frame_units"] == ["counts"] and not s["temperatures"]
    assert s["overlay"] is None  # raw counts carry no burned-in display: not searched
    # the default (mapper auto) keeps the incremental orientation, which holds >= 80 % in one block: global not tried
    assert s["mapper"] == "incremental" and "mapper_auto" not in s
    assert "orientation: incremental" in (out / "report.html").read_text()
    assert 0.2 < s["reprojection_rms_px"] < 0.7
    assert s["crs"] == "EPSG:32631"  # UTM zone 31N of the flight (4.43° E)
    # the adjusted centres against the RTK tags (σ from the files, ~1-2 cm): measured 1.9 / 1.4 / 1.6 cm RMS over 31
    # frames; frame 0022's tag is 3.01 m from where its ~2100 tie points put it (0.47 px there, 0.71 px when it was
    # forced onto the tag): left out and named
    assert [(g["image"], g["used"]) for g in s["gnss_flagged"]] == [("DJI_20240806173508_0022_T", False)]
    assert 2.8 < -s["gnss_flagged"][0]["dx"] < 3.2, s["gnss_flagged"]
    assert s["gnss"]["n"] == 31 and all(s["gnss"]["rmse_" + a] < 0.04 for a in "xyz"), s["gnss"]
    las_dims = __import__("laspy").read(out / "sparse.las").point_format.extra_dimension_names
    assert "raw_counts" in las_dims and "temperature_k" not in las_dims


def _rotvec_deg(Ra, Rb):
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(Ra @ np.swapaxes(Rb, -1, -2)).as_rotvec(degrees=True)


@pytest.mark.realdata
def test_real_m3t_gimbal_attitude_and_a_single_strip(m3t, tmp_path):
    """The DJI gimbal angles of the M3T frames as cam_from_world rotations (sfm.attitude), against the block oriented on
    RTK GNSS (rotation σ 0.04°); then one strip of the flight alone (16 frames on one straight line, EW): its GNSS
    cannot fix the rotation about the line, the gimbal attitude does (it stayed in a local frame before)."""
    from thermogrammetry.io.oriented import OrientedCameras
    from thermogrammetry.pipeline.survey import _attitudes

    src, out, code, cache = m3t
    assert code == 0
    ref = OrientedCameras.load(out / "cameras.json")
    inputs = json.loads((out / "work" / "inputs.json").read_text())
    att = _attitudes(inputs, ref.crs)
    names = [im["name"] for im in inputs["images"]]
    by_name = {im.name: im for im in ref.images}
    d = np.array([_rotvec_deg(by_name[n].R, att[k]) for k, n in enumerate(names) if n in by_name])
    # measured: 0.37-2.16° per frame, RMS 1.43°, mean (1.15, 0.55, 0.16)° about (E, N, up): a drifting gimbal tilt.
    # Without the meridian convergence (1.12° here) the vertical component would be ~1.3°, with a wrong axis
    # convention tens of degrees
    assert len(d) == 32
    assert np.sqrt(np.mean(np.sum(d**2, axis=1))) < 2.0
    assert abs(np.mean(d[:, 2])) < 0.6
    # the same comparison as the survey reports it (survey.json "attitude"): all 32, none flagged (> 10°)
    a = json.loads((out / "survey.json").read_text())["attitude"]
    assert a["n"] == 32 and a["flagged"] == [] and 1.0 < a["rms_deg"] < 2.0 and a["max_deg"] < 3.0
    # --- the first strip alone, with the camera as the whole flight calibrated it ----------------------------------
    strip = tmp_path / "strip"
    strip.mkdir()
    for k in range(8, 24):
        f = next(src.glob(f"DJI_*_{k:04d}_T.JPG"))
        (strip / f.name).symlink_to(f)
    (tmp_path / "camera.json").write_text(json.dumps(json.loads((out / "cameras.json").read_text())["cameras"]["thermal"]))
    o2 = tmp_path / "strip_out"
    assert main(["survey", str(strip), "-o", str(o2), "--workers", "0", "--camera", str(tmp_path / "camera.json"),
                 *cache]) == 0
    s = json.loads((o2 / "survey.json").read_text())
    assert s["crs"] == "EPSG:32631" and s["images_oriented"] == 16
    assert s["camera_file"] == {"file": str(tmp_path / "camera.json"), "format": "camera.json",
                                "conversion_max_residual_px": 0.0}
    assert "attitude" in s["blocks"][0]["datum"]
    est = OrientedCameras.load(o2 / "cameras.json")
    dr = np.array([_rotvec_deg(im.R, by_name[im.name].R) for im in est.images])
    dc = np.array([im.center - by_name[im.name].center for im in est.images])
    # measured: centres 3.0 cm RMS from the whole flight's (max 6.9 cm; RTK σ 1-2 cm), rotations 0.44° RMS; about
    # the line (east) -0.02° with a reported σ of 1.4° (one 2° attitude observation of the block's rotation)
    assert np.sqrt(np.mean(np.sum(dc**2, axis=1))) < 0.06
    assert np.sqrt(np.mean(np.sum(dr**2, axis=1))) < 1.0
    sd = np.array([im.rotation_std_deg for im in est.images])
    assert np.all((sd.max(axis=1) > 0.7) & (sd.max(axis=1) < 2.1))  # the line's rotation: not claimed better
    # --- the same strip without a camera file: the block cannot determine its focal length (flat ground, no GCPs) --
    # the focal length ran to ~2000 px; the old ladder then accepted fx/fy 738.6/714.9 px with the distortion held
    # (rotations 2.33° RMS off REF). Now focal length and principal point stay at EXIF's (758.3 px) and only the
    # distortion is self-calibrated: measured 0.28° RMS (max 0.38°), k1 -0.340 (REF -0.360)
    o3 = tmp_path / "strip_selfcal"
    assert main(["survey", str(strip), "-o", str(o3), "--workers", "0", *cache]) == 0
    s3 = json.loads((o3 / "survey.json").read_text())
    assert s3["images_oriented"] == 16 and set(s3["blocks"][0]["self_calibration"]) == {"k1", "k2", "p1", "p2"}
    assert "held at their start" in s3["blocks"][0]["self_calibration_steps"][0]
    est3 = OrientedCameras.load(o3 / "cameras.json")
    dr3 = np.array([_rotvec_deg(im.R, by_name[im.name].R) for im in est3.images])
    assert np.sqrt(np.mean(np.sum(dr3**2, axis=1))) < 0.8
    cam3, cam_ref = est3.cameras["thermal"].param_dict, ref.cameras["thermal"].param_dict
    assert abs(cam3["fx"] - 758.33) < 0.01 and abs(cam3["k1"] - cam_ref["k1"]) < 0.05


def test_error_messages_print_bracketed_user_values_literally(tmp_path, capsys):
    # a folder named like rich markup ("[red]...", "[nan, 1]"): printed as it is, not swallowed as a style tag
    bad = tmp_path / "[nan, 1] [bold]frames"
    bad.mkdir()
    assert main(["survey", str(bad), "-o", str(tmp_path / "out"), "--workers", "0"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "[nan, 1] [bold]frames" in err and err.startswith("error:")


def test_float_tiff_without_unit_names_the_flag(tmp_path, capsys):
    import tifffile

    from thermogrammetry.cli.main import main

    for k in range(2):
        tifffile.imwrite(tmp_path / f"f{k}.tif", np.full((32, 40), 300.0, np.float32))
    assert main(["survey", str(tmp_path / "f0.tif"), str(tmp_path / "f1.tif"), "-o", str(tmp_path / "out"), "--workers", "0"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "f0.tif" in err and "give --input-unit K or C" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("args, msg", [
    (["--lever-arm", "0.1,0.2"], "--lever-arm '0.1,0.2': expected 3 finite numbers"),
    (["--lever-arm", "a,b,c"], "expected comma-separated numbers"),
    (["--gnss-sigma", "0.02,-1"], "standard deviations must be > 0"),
    (["--rig", "rig.json"], "rig mode needs the RGB images"),
    (["--detector", "SURF"], "'SURF' is not a valid Detector; expected one of 'sift', 'orb', 'asift'"),
    (["--mapper", "hybrid"], "mapper='hybrid': expected one of 'auto', 'incremental', 'global'"),
])
def test_bad_flags_exit_2_with_the_value(tmp_path, capsys, args, msg):
    from thermogrammetry.cli.main import main

    (tmp_path / "in").mkdir()  # OUT beside the input folder (an OUT inside it is refused first)
    assert main(["survey", str(tmp_path / "in"), "-o", str(tmp_path / "out")] + args) == 2
    assert msg in " ".join(capsys.readouterr().err.split())
    assert not (tmp_path / "out").exists()


@pytest.mark.realdata
def test_dji_folder_with_visible_photographs(tmp_path, shared_data):
    """A DJI M3T folder holds the visible ``_V`` photographs next to the ``_T`` thermal frames: given as thermal
    input they are not thermal frames (another size than every radiometric frame: skipped with a note), and the
    radiometric ``_T`` files given to ``--rgb`` are not RGB images; an 8-bit rendering of the thermal frames' size
    is still taken (geometry only)."""
    import cv2

    from thermogrammetry.pipeline.project import MemoryProject
    from thermogrammetry.pipeline.survey import SurveyInput, SurveyOptions, step_inputs

    src = sorted((shared_data / "uav_m3t_flight" / "Test_image").glob("*_T.JPG"))[:3]
    if len(src) < 3:
        data_missing("uav_m3t_flight frames are absent")
    rng = np.random.default_rng(0)
    for f in src:
        shutil.copy(f, tmp_path / f.name)
        cv2.imwrite(str(tmp_path / f.name.replace("_T.", "_V.")), rng.integers(0, 255, (960, 1280, 3), dtype=np.uint8))
    cv2.imwrite(str(tmp_path / "palette_render.jpg"), rng.integers(0, 255, (512, 640, 3), dtype=np.uint8))
    proj = MemoryProject()
    step_inputs(proj, SurveyInput([str(tmp_path)]), SurveyOptions())
    rec = proj.read_json("work/inputs.json")
    got = {im["name"]: (im["unit"], im["width"]) for im in rec["images"]}
    assert got == {**{f.stem: ("counts", 640) for f in src}, "palette_render": ("dn", 640)}
    assert [im["name"] for im in rec["images"]][:3] == [f.stem for f in src]  # the inputs' order is kept
    assert not rec["failed"]
    assert any("3 ordinary 8-bit image(s)" in n and src[0].name.replace("_T.", "_V.") in n for n in rec["notes"])
    proj = MemoryProject()
    step_inputs(proj, SurveyInput([str(src[0])], rgb=[str(tmp_path)]), SurveyOptions())
    rec = proj.read_json("work/inputs.json")
    assert sorted((im["name"], im["sensor"]) for im in rec["images"]) == sorted(
        [(src[0].stem, "thermal")] + [(f.stem.replace("_T", "_V"), "rgb") for f in src] + [("palette_render", "rgb")])
    assert any("3 radiometric thermal file(s) among the RGB images" in n for n in rec["notes"])
