"""Self-calibration in OpenCV's forward Brown model (``calibrate --model opencv``).

- Real thermal chessboard (../shared/data/thermal_chessboard): ours and ``cv2.calibrateCamera`` on the same
  detections with the same parameters free (flags = 0: fx fy cx cy k1 k2 p1 p2 k3; and ``CALIB_FIX_K3``).
  Both minimise the same sum of squared pixel residuals of the same model, so they reach the same minimum:
  "no larger" allows 1e-9 px of RMS (rounding), the parameters must agree to 1 % of their reported σ
  (convergence tolerances). cv2 takes float32 points: its RMS is that of its estimate on the points as given
  (float64), and where the detections are ours to choose they are rounded to float32 for both.
- Exports: every file is read back and its camera compared with camera.json's (residual ≤ 1e-6 px; the
  numbers are written with 17 significant digits, so ~1e-12 px is expected), no ``*_INACCURATE`` name.
- Monte-Carlo on a synthetic board (noisy corner coordinates of a projected 9x6 board, 12 views, σ = 0.3 px,
  the known camera in the OpenCV model): n = 200 runs from the truth without snooping, so every run has the
  same observations; the empirical σ of n = 200 estimates has a relative sampling error of
  1/sqrt(2 (n - 1)) = 5 %, so the ±25 % band is ~5 sampling σ wide (as in the photogrammetric model's test).
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from conftest import data_path

from thermogrammetry.calibration.bundle import BundleProblem, CameraBlock, residuals
from thermogrammetry.calibration.exports import readback_residual
from thermogrammetry.calibration.selfcal import (
    STAGE2_PARAMS_OPENCV,
    CameraSetup,
    ImageMeasurements,
    SelfCalibrationOptions,
    calibrate,
)
from thermogrammetry.calibration.workflow import CalibrationRun
from thermogrammetry.camera import Camera
from thermogrammetry.cli.main import main
from thermogrammetry.errors import ConfigError
from thermogrammetry.synthetic.board_corners import make_board_corners, noisy_corners

NOISE_PX = 0.3
TRUTH = {"fx": 650.0, "fy": 655.0, "cx": 327.0, "cy": 243.0, "k1": -0.35, "k2": 0.15, "p1": 1e-3, "p2": -5e-4,
         "k3": -0.03}
CHESS = ("thermal_chessboard", "Thermal camera calibration", "Thermal images cropped")


@pytest.fixture(scope="module")
def board():
    cam = Camera("opencv", (640, 480), TRUTH)
    b = make_board_corners(cam, n_views=12, seed=1)
    assert len(b.poses) == 12
    return b


def _ims(board, xy):
    return [ImageMeasurements(n, 0, np.arange(len(board.points_m)), p) for n, p in zip(board.names, xy)]


# ---------------------------------------------------------------------------------------------- options
def test_options_of_the_opencv_model():
    opt = SelfCalibrationOptions(model="OpenCV")  # case-insensitive
    assert opt.model.value == "opencv"
    assert opt.stage2_names() == STAGE2_PARAMS_OPENCV == ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    assert SelfCalibrationOptions(model="opencv", fixed=("k3",)).stage2_names() == STAGE2_PARAMS_OPENCV[:-1]
    assert SelfCalibrationOptions(model="opencv", rational=True).stage2_names()[-3:] == ("k4", "k5", "k6")
    with pytest.raises(ConfigError, match="'photogrammetric', 'opencv'"):
        SelfCalibrationOptions(model="fisheye")
    with pytest.raises(ConfigError, match="'photogrammetric', 'opencv'"):
        SelfCalibrationOptions(model="pinhole")
    with pytest.raises(ConfigError, match="K3"):  # a photogrammetric name under the opencv model
        SelfCalibrationOptions(model="opencv", fixed=("K3",))
    with pytest.raises(ConfigError, match="k45"):
        SelfCalibrationOptions(model="opencv", k45=True)
    with pytest.raises(ConfigError, match="rational"):
        SelfCalibrationOptions(rational=True)


def test_staged_calibration_recovers_the_camera(board):
    """From nothing but the image size (Zhang's focal length, centred principal point, no distortion) to the
    truth: every parameter within 3.5 of its reported σ (P(|z| > 3.5) = 0.05 % per parameter)."""
    rng = np.random.default_rng(3)
    r = calibrate([CameraSetup("c", (640, 480), 17.0)], board.points_m, _ims(board, noisy_corners(board, NOISE_PX, rng)),
                  options=SelfCalibrationOptions(model="opencv"))
    assert r.outcome.success, r.outcome.reason
    cc = r.cameras[0]
    assert cc.model.value == "opencv" and cc.param_names[:4] == ("fx", "fy", "cx", "cy")
    for n in STAGE2_PARAMS_OPENCV:
        v, s = cc.param_dict[n], cc.std_dict[n]
        assert abs(v - TRUTH[n]) < 3.5 * s, (n, v, TRUTH[n], s)
    for n in ("skew", "k4", "k5", "k6"):  # not estimated: exactly 0, no σ
        assert cc.param_dict[n] == 0.0 and np.isnan(cc.std_dict[n])
    # σ0 with unit a-priori weights is the image noise; the t tests are of the distortion terms
    assert 0.9 * NOISE_PX < r.sigma0 < 1.1 * NOISE_PX
    assert {t.name for t in cc.tests} == {"k1", "k2", "p1", "p2", "k3"}
    assert next(t for t in cc.tests if t.name == "k1").significant


def test_3d_test_field_route_in_the_opencv_model():
    """The staged route of Yastikli & Guler (2013) on the synthetic 3D test field (a non-planar target, resection by
    SQPnP, nominal c = 18 mm) in the opencv model: the forward polynomial fits the field's correction-form camera to the
    noise (σ0 within ±10 % of the injected 0.4 px, ~1100 coordinate pairs: sampling error ~2 %), every image used."""
    from thermogrammetry.synthetic.testfield import make_testfield

    tf = make_testfield(np.random.default_rng(2024), noise_px=0.4)
    T = tf.truth
    ims = [ImageMeasurements(n, 0, tf.obs_point[tf.obs_image == f], tf.xy_px[tf.obs_image == f])
           for f, n in enumerate(T.image_names)]
    r = calibrate([CameraSetup("A320", T.image_size, T.pixel_pitch_um, {"c_mm": 18.0})], T.points, ims,
                  options=SelfCalibrationOptions(model="opencv"))
    assert r.outcome.success, r.outcome.reason
    assert 0.9 * 0.4 < r.sigma0 < 1.1 * 0.4
    assert len(r.images_used) == 16 and r.stage1["c_mm"] == [18.0]
    assert r.cameras[0].model.value == "opencv"


def test_engine_and_dense_solver_agree(board):
    rng = np.random.default_rng(4)
    ims = _ims(board, noisy_corners(board, NOISE_PX, rng))
    kw = dict(initial={0: board.camera.params.copy()}, initial_poses=board.poses)
    a = calibrate([CameraSetup("c", (640, 480), 17.0)], board.points_m, ims,
                  options=SelfCalibrationOptions(model="opencv", snooping=False), **kw).cameras[0]
    b = calibrate([CameraSetup("c", (640, 480), 17.0)], board.points_m, ims,
                  options=SelfCalibrationOptions(model="opencv", snooping=False, solver="dense"), **kw).cameras[0]
    f = a.free
    assert np.all(np.abs(a.params[f] - b.params[f]) < 1e-3 * a.std[f])
    assert np.allclose(a.std[f], b.std[f], rtol=1e-3)


def test_bundle_projects_with_the_opencv_model(board):
    """The bundle's residuals at the truth are exactly the injected noise (the bundle projects with camera.models)."""
    rng = np.random.default_rng(5)
    xy = noisy_corners(board, NOISE_PX, rng)
    n = len(board.points_m)
    cb = CameraBlock(board.camera.params.copy(), np.zeros(13, bool), (640, 480), (0.017, 0.017), "c", "opencv")
    R = np.array([p[0] for p in board.poses])
    t = np.array([p[1] for p in board.poses])
    views = np.repeat(np.arange(len(xy)), n)
    prob = BundleProblem([cb], R, t, board.points_m, np.zeros(views.size, int), views, np.tile(np.arange(n), len(xy)),
                         np.concatenate(xy), np.full((views.size, 2), 1.0))
    res, ok = residuals(prob)
    assert ok.all()
    assert np.allclose(res, np.concatenate(xy) - np.concatenate(board.xy_px), atol=1e-9)


# ---------------------------------------------------------------------------------------------- σ vs Monte-Carlo
def test_reported_sigma_matches_monte_carlo(board):
    """200 noise realisations of the same board views, adjusted from the truth without snooping (dense solver;
    ``test_engine_and_dense_solver_agree`` shows the engine gives the same estimates and σ): the scatter of the
    estimates equals the reported σ within ±25 %, the estimates are unbiased (mean within 4 standard errors)."""
    n = 200
    rng = np.random.default_rng(99)
    opt = SelfCalibrationOptions(model="opencv", snooping=False, solver="dense")
    names = board.camera.param_names
    idx = [names.index(p) for p in STAGE2_PARAMS_OPENCV]
    est, rep, s0 = [], [], []
    for _ in range(n):
        r = calibrate([CameraSetup("c", (640, 480), 17.0)], board.points_m, _ims(board, noisy_corners(board, NOISE_PX, rng)),
                      options=opt, initial={0: board.camera.params.copy()}, initial_poses=board.poses)
        assert r.outcome.success
        est.append(r.cameras[0].params[idx])
        rep.append(r.cameras[0].std[idx])
        s0.append(r.sigma0)
    est, rep = np.array(est), np.array(rep)
    scatter = est.std(axis=0, ddof=1)
    reported = np.sqrt(np.mean(rep**2, axis=0))
    ratio = reported / scatter
    assert np.all((ratio > 0.75) & (ratio < 1.25)), dict(zip(STAGE2_PARAMS_OPENCV, np.round(ratio, 3)))
    bias_z = (est.mean(axis=0) - board.camera.params[idx]) / (scatter / np.sqrt(n))
    assert np.all(np.abs(bias_z) < 4.0), dict(zip(STAGE2_PARAMS_OPENCV, np.round(bias_z, 2)))
    assert 0.95 * NOISE_PX < np.mean(s0) < 1.05 * NOISE_PX


# ---------------------------------------------------------------------------------------------- exports
def test_exports_are_exact_and_read_back(board):
    from thermogrammetry.calibration.outputs import write_outputs
    from thermogrammetry.io.camera_file import read_camera_file
    from thermogrammetry.store import MemoryProject

    rng = np.random.default_rng(6)
    r = calibrate([CameraSetup("c", (640, 480), 17.0)], board.points_m, _ims(board, noisy_corners(board, NOISE_PX, rng)),
                  options=SelfCalibrationOptions(model="opencv"))
    mem = MemoryProject()
    info = write_outputs(mem, CalibrationRun(r, {"route": "target"}))["exports"]["c"]
    keys = mem.keys()
    for k in ("exports/opencv.yaml", "exports/opencv.json", "exports/colmap_cameras.txt", "exports/metashape.xml"):
        assert k in keys, keys
    for fmt in ("opencv", "colmap", "metashape"):
        assert info[fmt]["max_residual_px"] <= 1e-6 and info[fmt]["area_max_residual_px"] <= 1e-6, (fmt, info[fmt])
        assert not info[fmt]["warning"]
    cam = Camera.from_dict(mem.read_json("camera.json"))
    assert cam.model.value == "opencv" and cam.param_std is not None
    cc = r.cameras[0]
    assert np.array_equal(cam.params, cc.params)
    # the files hold the parameters themselves: cv2 reads the YAML; COLMAP's principal point is + 0.5
    fs = cv2.FileStorage(mem.read_bytes("exports/opencv.yaml").decode(), cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    K, dist = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat().ravel()
    fs.release()
    p = cc.param_dict
    assert np.array_equal(K, np.array([[p["fx"], 0, p["cx"]], [0, p["fy"], p["cy"]], [0, 0, 1]]))
    assert np.array_equal(dist, [p["k1"], p["k2"], p["p1"], p["p2"], p["k3"]])
    line = mem.read_bytes("exports/colmap_cameras.txt").decode().strip().splitlines()[-1].split()
    assert line[1] == "FULL_OPENCV" and float(line[6]) == p["cx"] + 0.5 and float(line[7]) == p["cy"] + 0.5
    oj = mem.read_json("exports/opencv.json")
    assert oj["covariance"]["params"] == list(STAGE2_PARAMS_OPENCV)
    sd = np.sqrt(np.diag(oj["covariance"]["matrix"]))
    assert np.allclose(sd, [cc.std_dict[n] for n in STAGE2_PARAMS_OPENCV], rtol=1e-12)
    # the other model is a conversion, with its (non-zero) residual, named by it; it is a camera.json of that model
    # (this camera's strong barrel distortion, k1 = -0.35, is beyond K1..K3 of the correction form at the corners)
    ph = info["photogrammetric"]
    assert ph["max_residual_px"] > 1e-3
    name = f"exports/photogrammetric{'_INACCURATE' if ph['max_residual_px'] > 1.0 else ''}.json"
    assert ph["files"] == [name.split("/")[1]] and name in keys
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as td:
        f = Path(td) / "photogrammetric.json"
        f.write_bytes(mem.read_bytes(name))
        pc = read_camera_file(f)
    assert pc.model.value == "photogrammetric"
    assert readback_residual(cam, pc)["max_residual_px"] == pytest.approx(ph["max_residual_px"], rel=1e-6)
    # calibration.json says which model and carries the opencv parameters with σ
    cal = mem.read_json("calibration.json")
    assert cal["model"] == "opencv" and set(cal["parameters"]) == set(cam.param_names)
    assert cal["parameters"]["k3"]["estimated"] and not cal["parameters"]["skew"]["estimated"]


def test_readback_residual_sees_a_changed_file(board):
    """The residual of an export is computed: a file with fx off by 0.01 px shows it, as 0.01 px times the largest
    |x_d| over the frame (the 0 of an exact export is measured, not set)."""
    cam = board.camera
    p = dict(cam.param_dict)
    p["fx"] += 0.01
    other = Camera("opencv", cam.image_size, p)
    r = readback_residual(cam, other)
    # u changes by 0.01 * xd: at most 0.01 * max |xd| over the frame's rays
    from thermogrammetry.camera.convert import image_grid

    rays = cam.unproject(image_grid(cam.image_size))
    xd = (cam.project(rays)[:, 0] - p["cx"]) / cam.param_dict["fx"]
    assert r["max_residual_px"] == pytest.approx(0.01 * np.max(np.abs(xd)), rel=1e-6)


# ---------------------------------------------------------------------------------------------- real chessboard
def _cv2(obj, img, size, flags):
    """cv2.calibrateCamera on the points (it takes float32); its RMS on the points as given (float64, through
    cv2.projectPoints with its estimate), and its parameters."""
    op = [o.astype(np.float32) for o in obj]
    ip = [i.astype(np.float32).reshape(-1, 1, 2) for i in img]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 300, 1e-15)
    _, K, dist, rv, tv = cv2.calibrateCamera(op, ip, size, None, None, flags=flags, criteria=crit)
    err = np.concatenate([cv2.projectPoints(np.asarray(o, float), a, b, K, dist)[0].reshape(-1, 2) - i
                          for o, i, a, b in zip(obj, img, rv, tv)])
    d = dist.ravel()
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1)))), {
        "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "k1": d[0], "k2": d[1], "p1": d[2], "p2": d[3],
        "k3": d[4]}


@pytest.fixture(scope="module")
def chess_files():
    return sorted(data_path(*CHESS).glob("*.jpg"))[::4]  # 12 of the 47 views keep the tests short


@pytest.fixture(scope="module")
def chess_detections(chess_files):
    from thermogrammetry.calibration.detect import detect_chessboard
    from thermogrammetry.calibration.detect_common import ChessboardSpec

    spec = ChessboardSpec(6, 5, 100.0, corner0_square="any")
    found = [d for d in (detect_chessboard(cv2.imread(str(f), cv2.IMREAD_UNCHANGED), spec, f.name) for f in chess_files)
             if d.found]
    assert len(found) >= len(chess_files) - 1
    return spec, found


@pytest.mark.parametrize("fix_k3", [False, True])
def test_rms_and_parameters_as_cv2_calibrate_camera(chess_detections, fix_k3):
    spec, found = chess_detections
    obj = (spec.object_points() * 1e-3).astype(np.float32).astype(float)
    xy = [d.points_px.astype(np.float32).astype(float) for d in found]
    ims = [ImageMeasurements(d.image_id, 0, d.object_ids, p) for d, p in zip(found, xy)]
    opt = SelfCalibrationOptions(model="opencv", snooping=False, fixed=("k3",) if fix_k3 else ())
    r = calibrate([CameraSetup("thermal", (640, 480), 17.0)], obj, ims, options=opt)
    assert r.outcome.success, r.outcome.reason
    rms_cv, p_cv = _cv2([obj[d.object_ids] for d in found], xy, (640, 480), cv2.CALIB_FIX_K3 if fix_k3 else 0)
    assert r.rms_px <= rms_cv + 1e-9, (r.rms_px, rms_cv)
    cc = r.cameras[0]
    for n in opt.stage2_names():
        assert abs(cc.param_dict[n] - p_cv[n]) < 0.01 * cc.std_dict[n], (n, cc.param_dict[n], p_cv[n], cc.std_dict[n])
    if fix_k3:
        assert cc.param_dict["k3"] == 0.0 and p_cv["k3"] == 0.0


def test_cli_opencv_model_on_the_thermal_chessboard(chess_files, tmp_path, capsys):
    """The verb as a user runs it: RMS no larger than cv2.calibrateCamera on the observations the calibration kept
    (the detections less the blunders data snooping removed), exports exact and not *_INACCURATE."""
    out = tmp_path / "OUT"
    rc = main(["calibrate", *map(str, chess_files), "--target", "chessboard", "--corners", "6x5", "--spacing-mm", "100",
               "--model", "OpenCV", "-o", str(out)])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "OpenCV export: residual of the file read back max" in text
    cal = json.loads((out / "calibration.json").read_text())
    obs = json.loads((out / "observations.json").read_text())
    cam = Camera.load(out / "camera.json")
    assert cam.model.value == "opencv"
    files = sorted(p.name for p in (out / "exports").iterdir())
    assert files[:4] == ["colmap_cameras.txt", "metashape.xml", "opencv.json", "opencv.yaml"], files
    assert files[4:] == cal_files(out, "photogrammetric")
    for fmt in ("opencv", "colmap", "metashape"):
        e = cal["exports"]["camera"][fmt]
        assert e["max_residual_px"] <= 1e-6 and e["area_max_residual_px"] <= 1e-6, (fmt, e)
    # the observations the calibration kept
    dropped = {(b["image"], b["point"]) for b in cal["blunders"]}
    pts = np.asarray(obs["points_m"], float)
    used = set(cal["images_used"])
    op, ip = [], []
    for im in obs["images"]:
        if im["name"] not in used:
            continue
        keep = [k for k, pi in enumerate(im["point_index"]) if (im["name"], pi) not in dropped]
        op.append(pts[np.asarray(im["point_index"])[keep]])
        ip.append(np.asarray(im["xy_px"], float)[keep])
    assert sum(len(i) for i in ip) == cal["cameras"][0]["n_observations"]
    rms_cv, p_cv = _cv2(op, ip, (640, 480), 0)
    assert cal["rms_px"] <= rms_cv + 1e-9, (cal["rms_px"], rms_cv)
    par = cal["parameters"]
    for n in STAGE2_PARAMS_OPENCV:
        assert abs(par[n]["value"] - p_cv[n]) < 0.05 * par[n]["std"], (n, par[n], p_cv[n])


def cal_files(out, fmt):
    return json.loads((out / "calibration.json").read_text())["exports"]["camera"][fmt]["files"]


# ---------------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("extra, words", [
    (["--model", "fisheye"], ["--model 'fisheye'", "photogrammetric, opencv"]),
    (["--model", "opencv", "--k45"], ["--k45", "photogrammetric model", "--rational"]),
    (["--rational"], ["--rational", "--model opencv"]),
])
def test_cli_bad_model_flags_exit_2_and_write_nothing(tmp_path, capsys, extra, words):
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    cv2.imwrite(str(imgs / "a.png"), np.full((48, 64), 128, np.uint8))
    out = tmp_path / "OUT"
    rc = main(["calibrate", str(imgs), "--target", "chessboard", "--corners", "6x5", "--spacing-mm", "100", "-o", str(out),
               *extra])
    err = " ".join(capsys.readouterr().err.split())
    assert rc == 2
    for w in words:
        assert w in err, (w, err)
    assert not out.exists()
