"""Low-texture facade walk (synthetic.lowtexture_facade): the sequence tracker's ties against the true poses, and the
pose comparison used by the benchmark.

The scene is the hard case of issue 10: a plain wall with 0.15 K of smooth thermal contrast, a fixed pattern of
0.08 K (column stripes + pixel offsets) and 0.04 K NETD; SIFT and pycolmap find no usable pair on it
(``benchmarks/survey_lowtexture.py --synthetic``).
"""

from __future__ import annotations

import numpy as np
import pytest

from _cache import copy_entry
from cached_scenes import lowtexture_walk_folder, tie_cache
from thermogrammetry.synthetic.lowtexture_facade import (LowTextureFacadeConfig, make_lowtexture_facade, pose_errors,
                                                         render_lowtexture_frame)


@pytest.fixture(scope="module")
def walk():
    sc = make_lowtexture_facade(LowTextureFacadeConfig(n_frames=8))
    return sc, [render_lowtexture_frame(sc, k) for k in range(8)]


@pytest.fixture(scope="module")
def walk30(scene_cache):
    """The 30-frame walk (seed 0) and its frames' folder, written once per run (cached_scenes). Module-scoped so that
    the two surveys of it run on one worker, one after the other: the second reads the first's features, matches and
    tracked sequence from the shared tie cache (tests/conftest.py groups the tests of a module-scoped fixture)."""
    sc = make_lowtexture_facade(LowTextureFacadeConfig())
    return sc, lowtexture_walk_folder(scene_cache, sc)


def _true_pose_residuals(sc, st):
    """Reprojection residuals (px) of the tracks (>= 3 frames) triangulated with the TRUE poses."""
    from thermogrammetry.sfm.tracks import build_tracks

    t = build_tracks([len(x) for x in st.xy], [(a, b, m) for (a, b), m in st.matches.items()])
    order = np.argsort(t.track, kind="stable")
    tk, im, ft = t.track[order], t.image[order], t.feature[order]
    cuts = np.r_[0, np.nonzero(np.diff(tk))[0] + 1, len(tk)]
    cam, res = sc.camera, []
    for a, b in zip(cuts[:-1], cuts[1:]):
        if b - a < 3:
            continue
        A = []
        for q in range(a, b):
            p = sc.poses[im[q]]
            P = np.hstack([p.R, p.t[:, None]])
            r = cam.unproject(st.xy[im[q]][ft[q]][None])[0]
            A += [r[0] * P[2] - P[0], r[1] * P[2] - P[1]]
        X = np.linalg.svd(np.array(A))[2][-1]
        X = X[:3] / X[3]
        for q in range(a, b):
            p = sc.poses[im[q]]
            res.append(np.linalg.norm(cam.project((p.R @ X + p.t)[None])[0] - st.xy[im[q]][ft[q]]))
    return np.array(res)


def test_tracker_ties_on_a_plain_wall(walk):
    """Every consecutive pair is verified and the tracks agree with the true poses.

    Measured (30 frames of this scene, seeds 0/1, contrast 0.15/0.2/0.25 K): RMS 0.93/0.78/0.68 px of tracks of >= 3
    frames re-triangulated with the true poses; noise-free frames 0.54 px (the Lucas-Kanade floor on smooth texture).
    The band: at least 0.3 px (the frames carry 0.04 K NETD: a zero would mean the residuals are not computed on the
    tracks) and at most 1.3 px (40 % above the worst measured; a tracker locked on the sensor pattern or sliding along
    edges gives 2-5 px, measured before the fine-pattern estimate and the eigenvalue test).
    """
    from thermogrammetry.sfm.features import fixed_pattern
    from thermogrammetry.sfm.lowtexture import track_sequence

    sc, frames = walk
    pat = fixed_pattern(frames, highpass_sigma_px=8.0)
    st = track_sequence(lambda k: frames[k], len(frames), pattern=pat, cameras=[sc.camera] * len(frames))
    assert all(r == "" for r in st.reasons.values()), st.reasons
    assert min(len(m) for m in st.matches.values()) >= 100
    res = _true_pose_residuals(sc, st)
    rms = float(np.sqrt(np.mean(res ** 2)))
    print(f"tracks (>= 3 frames) against the true poses: {len(res)} observations, RMS {rms:.3f} px")
    assert len(res) > 1000
    assert 0.3 < rms < 1.3, rms
    assert np.mean(res > 4.0) < 0.01


def test_tracker_is_deterministic(walk):
    from thermogrammetry.sfm.lowtexture import track_sequence

    sc, frames = walk
    a = track_sequence(lambda k: frames[k], 3, cameras=[sc.camera] * 3)
    b = track_sequence(lambda k: frames[k], 3, cameras=[sc.camera] * 3)
    for x, y in zip(a.xy, b.xy):
        np.testing.assert_array_equal(x, y)
    assert a.matches.keys() == b.matches.keys()


def test_tracker_finds_nothing_in_noise():
    """Frames of pure noise (no scene) verify no pair: the fallback must not invent a block."""
    from thermogrammetry.sfm.lowtexture import track_sequence

    rng = np.random.default_rng(5)
    frames = [284.0 + 0.05 * rng.standard_normal((256, 320)).astype(np.float32) for _ in range(5)]
    st = track_sequence(lambda k: frames[k], len(frames))
    assert not st.matches, {k: len(v) for k, v in st.matches.items()}
    assert all(st.reasons.values())


def test_fine_fixed_pattern_leaves_the_scene(walk):
    """The pattern's fine part (highpass_sigma_px) is recovered; the whole-frame estimate carries the scene.

    Measured on the 30-frame walk: in the tracker's band (σ 2-20 px) the residual of the whole-frame estimate is
    0.090 K against 0.019 K of true pattern, of the fine estimate (σ 8 px) 0.007 K. Here 8 frames: bound 0.012 K
    (below the true pattern in the band, which a useless estimate would leave), and the whole-frame estimate is worse.
    """
    import cv2

    from thermogrammetry.sfm.features import fixed_pattern
    from thermogrammetry.synthetic.sensor import fixed_pattern as true_pattern

    sc, frames = walk
    c = sc.config
    tru = true_pattern(c.image_size, c.fpn_k, int(c.seed) + 11)

    def band(x):
        x = np.asarray(x, np.float32)
        return (cv2.GaussianBlur(x, (0, 0), 2) - cv2.GaussianBlur(x, (0, 0), 20))[20:-80, 20:-20]

    fine = float(band(fixed_pattern(frames, highpass_sigma_px=8.0) - tru).std())
    whole = float(band(fixed_pattern(frames) - tru).std())
    print(f"residual pattern in the tracking band: fine {fine:.4f} K, whole {whole:.4f} K, true {band(tru).std():.4f} K")
    assert fine < 0.012 < float(band(tru).std())
    assert whole > fine


def test_pose_errors_under_a_similarity(walk):
    """A block that is the truth under a similarity has zero errors and the inverse scale; a rotated image is seen."""
    from thermogrammetry.geometry.rotations import matrix_from_axis_angle

    sc, _ = walk
    truth = {n: (p.R, p.t) for n, p in zip(sc.names, sc.poses)}
    Q = matrix_from_axis_angle(np.array([0.3, -0.2, 1.1]))
    s, q = 0.37, np.array([5.0, -2.0, 1.0])
    est = {}
    for n, (R, t) in truth.items():
        C = -R.T @ t
        Ce = s * Q @ C + q  # the estimate's world = a similarity of the true world
        Re = R @ Q.T
        est[n] = (Re, -Re @ Ce)
    e = pose_errors(truth, est)
    assert e["n"] == 8 and e["scale"] == pytest.approx(1 / s, rel=1e-9)
    assert e["center_err_m"].max() < 1e-9 and e["rot_err_deg"].max() < 1e-6
    R0, t0 = est[sc.names[3]]
    dR = matrix_from_axis_angle(np.array([0.0, np.deg2rad(2.0), 0.0]))
    est[sc.names[3]] = (dR @ R0, dR @ t0)  # same centre, turned by 2 deg
    e = pose_errors(truth, est)
    # the block's rotation is the mean over the images: one turned image moves it by ~2/8 deg, which the others show
    assert e["rot_err_deg"][3] == pytest.approx(2.0, abs=0.3)
    assert np.delete(e["rot_err_deg"], 3).max() < 0.3
    assert e["center_rms_rel"] < 0.005


def test_survey_orients_the_walk_in_one_block(tmp_path, scene_cache, walk30):
    """``survey`` with DEFAULT options (``low_texture="auto"``) on the 30-frame walk (seed 0, 0.15 K): pycolmap builds no
    model and ``off`` orients nothing (benchmarks/survey_lowtexture.py --synthetic); ``auto`` tracks the sequence and
    its guard keeps the block (plane parallax 0.42 x the RMS, bound 0.85; planar share 0.85, bound 0.55).

    Measured: 30/30 in one block, rotations 0.87 deg RMS (max 1.51) after the block's mean rotation, centres 0.30 % of
    the block's 19.4 m after a similarity. Bounds: >= 80 % of the frames in one block (issue 10), rotation RMS < 2 deg
    and centres < 1 % (about twice and three times the measured; seed 2 of the same scene gives 3.4 deg / 0.87 %, so
    the bounds hold for this seed only -- a regression guard, not a claim about every wall).
    """
    from thermogrammetry.pipeline import FolderProject
    from thermogrammetry.pipeline.survey import SurveyInput, SurveyOptions, run_survey

    sc, folder = walk30
    copy_entry(folder, tmp_path / "scene")  # write_lowtexture_facade, once per run
    project = FolderProject(tmp_path / "out")
    run_survey(project, SurveyInput(images=[str(tmp_path / "scene" / "frames")]),
               SurveyOptions(gnss="none", cache=tie_cache(scene_cache)[1]))
    s = project.read_json("survey.json")
    assert s["components"] and s["components"][0] >= 0.8 * s["images_total"], s["components"]
    assert project.read_json("work/pairs.json")["features"]["low_texture"]["sequence"] is True
    assert s["low_texture"]["kept"] is True and not s["low_texture"]["check"][0]["refused"], s["low_texture"]
    block = {im["name"]: im.get("block") for im in s["images"]}
    cams = project.read_json("cameras.json")["images"]
    first = max(set(block.values()) - {None}, key=lambda b: sum(v == b for v in block.values()))
    est = {im["name"]: (np.array(im["cam_from_world"]["R"]), np.array(im["cam_from_world"]["t"])) for im in cams
           if block.get(im["name"]) == first}
    e = pose_errors({n: (p.R, p.t) for n, p in zip(sc.names, sc.poses)}, est)
    rot = float(np.sqrt(np.mean(e["rot_err_deg"] ** 2)))
    print(f"{e['n']}/{len(sc.names)} in one block, rotations {rot:.2f} deg RMS, centres {100 * e['center_rms_rel']:.2f} %")
    assert e["n"] >= 24
    assert rot < 2.0 and e["center_rms_rel"] < 0.01


def test_fallback_runs_when_the_final_adjustment_rejects_the_primary_block(tmp_path):
    """Walk seed 4 (0.15 K): SIFT matches on the noise and the sensor's pattern connect all 30 frames into one block,
    so the fallback is not triggered by the orientation; the final adjustment then finds that block undetermined
    (a rank defect beyond the datum, after leaving out points whose rays had become parallel) and orients nothing.
    With ``auto`` the fallback then runs (trigger ``adjustment``) and ``georef`` runs again on its block.

    Measured: the first georef 0/30 (a singular point block; solved again without the 66 points whose rays meet at
    < 0.1°: "rank defect larger than the 7 datum parameters"); after the fallback 30/30 in one block, rotations 2.59 deg RMS (max 4.34), centres 0.64 % of
    the block's length; guard ratio 0.48, planar share 0.86. Before: 0/30, exit 1 (the fallback never ran). Bounds:
    >= 80 % in one block (issue 10); rotation RMS < 4 deg and centres < 1.5 % (1.5-2.3x the measured; right walks of
    this scene measure 0.5-3.4 deg, wrong blocks 6-36 deg)."""
    from thermogrammetry.pipeline import FolderProject
    from thermogrammetry.pipeline.survey import SurveyInput, SurveyOptions, run_survey
    from thermogrammetry.synthetic.lowtexture_facade import write_lowtexture_facade

    sc = make_lowtexture_facade(LowTextureFacadeConfig(seed=4))
    write_lowtexture_facade(FolderProject(tmp_path / "scene"), sc)
    project = FolderProject(tmp_path / "out")
    reports = run_survey(project, SurveyInput(images=[str(tmp_path / "scene" / "frames")]), SurveyOptions(gnss="none"))
    names = [r.name for r in reports]
    assert names == ["inputs", "features", "matching", "orient", "georef", "orient_low_texture", "georef_low_texture"], names
    assert reports[3].summary["oriented"] == 30 and reports[4].summary["images_oriented"] == 0
    s = project.read_json("survey.json")
    assert s["low_texture"]["ran"] is True and s["low_texture"]["trigger"] == "adjustment" and s["low_texture"]["kept"] is True
    assert project.read_json("work/pairs.json")["features"]["low_texture"]["trigger"].startswith("adjustment")
    assert s["components"] and s["components"][0] >= 0.8 * s["images_total"], s["components"]
    assert [st["name"] for st in s["steps"]] == names
    cams = project.read_json("cameras.json")["images"]
    est = {im["name"]: (np.array(im["cam_from_world"]["R"]), np.array(im["cam_from_world"]["t"])) for im in cams}
    e = pose_errors({n: (p.R, p.t) for n, p in zip(sc.names, sc.poses)}, est)
    rot = float(np.sqrt(np.mean(e["rot_err_deg"] ** 2)))
    assert e["n"] >= 24 and rot < 4.0 and e["center_rms_rel"] < 0.015, (e["n"], rot, e["center_rms_rel"])


def test_sequence_order_ratio():
    """Consecutive frames of a walk are neighbours (ratio ~1); the same frames shuffled are not (7-11 measured)."""
    from thermogrammetry.pipeline.survey import SEQUENCE_ORDER_RATIO, _sequence_order_ratio

    sc = make_lowtexture_facade(LowTextureFacadeConfig())
    C = np.array([p.center for p in sc.poses])
    assert 0.95 <= _sequence_order_ratio(C) <= 1.2  # measured 1.05 (frames 0.65 m apart, hand-held jitter)
    rng = np.random.default_rng(0)
    assert _sequence_order_ratio(C + rng.normal(0, 0.03, C.shape)) <= 1.2  # RTK noise: 1.04-1.07
    shuffled = [_sequence_order_ratio(rng.permutation(C)) for _ in range(5)]
    assert min(shuffled) > SEQUENCE_ORDER_RATIO, shuffled
    C[3] = np.nan  # a frame without a position is left out
    assert 0.95 <= _sequence_order_ratio(C) <= 1.3
    assert _sequence_order_ratio(C[:2]) is None and _sequence_order_ratio(np.zeros((5, 3))) is None


def test_walk_with_gnss_is_tracked_as_a_sequence(tmp_path, scene_cache, walk30):
    """The 30-frame walk (seed 0) with RTK GNSS (σ 3 cm, in EPSG:2056 coordinates): the positions say the frames are
    a sequence (order ratio ~1), so the fallback tracks them as without positions. Before: positions sent the fallback
    to SIFT with homography-guided matching, whose blocks were rejected: 0/30, exit 1.

    Measured: 30/30 in one block, rotations 0.92 deg RMS, centres 0.30 % (as without GNSS: the GNSS line is straight,
    so the block stays in a local frame, which survey.json says). Bounds as in the walk test above."""
    from thermogrammetry.cli.main import main
    from thermogrammetry.pipeline import FolderProject

    sc, folder = walk30
    copy_entry(folder, tmp_path / "scene")  # write_lowtexture_facade, once per run
    rng = np.random.default_rng(1)
    rows = ["image,X,Y,Z,sX,sY,sZ"]
    for n, p in zip(sc.names, sc.poses):
        c = p.center + rng.normal(0, 0.03, 3) + [2600000.0, 1200000.0, 400.0]
        rows.append(f"{n},{c[0]:.4f},{c[1]:.4f},{c[2]:.4f},0.03,0.03,0.05")
    (tmp_path / "gnss.csv").write_text("\n".join(rows) + "\n")
    out = tmp_path / "out"
    code = main(["survey", str(tmp_path / "scene" / "frames"), "-o", str(out), "--gnss", str(tmp_path / "gnss.csv"),
                 "--crs", "EPSG:2056", "--workers", "0", *tie_cache(scene_cache)])
    assert code == 0
    project = FolderProject(out)
    print("read from the tie cache:", {k: project.read_json(f"reports/{k}.json").get("summary", {}).get("from_cache")
                                       for k in ("matching", "orient") if project.exists(f"reports/{k}.json")})
    lt = project.read_json("work/pairs.json")["features"]["low_texture"]
    assert lt["sequence"] is True and 0.95 <= lt["order_ratio"] <= 1.2, lt
    s = project.read_json("survey.json")
    assert s["components"] and s["components"][0] >= 0.8 * s["images_total"], s["components"]
    assert any("collinear" in n_ for n_ in s["notes"]), s["notes"]
    cams = project.read_json("cameras.json")["images"]
    est = {im["name"]: (np.array(im["cam_from_world"]["R"]), np.array(im["cam_from_world"]["t"])) for im in cams}
    e = pose_errors({n: (p.R, p.t) for n, p in zip(sc.names, sc.poses)}, est)
    rot = float(np.sqrt(np.mean(e["rot_err_deg"] ** 2)))
    assert e["n"] >= 24 and rot < 2.0 and e["center_rms_rel"] < 0.01, (e["n"], rot, e["center_rms_rel"])
