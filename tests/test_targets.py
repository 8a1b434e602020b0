"""thermogrammetry.targets: the one description of each calibration target (mm), its aliases, the
colour convention of the chessboard, and order-robust comparison of detections with the truth."""

from __future__ import annotations

import numpy as np
import pytest

import thermogrammetry as tg
from thermogrammetry import targets as T
from thermogrammetry.errors import ConfigError
from thermogrammetry.geometry import Pose

cv2 = pytest.importorskip("cv2")


def _pinhole(w, h, f):
    return tg.Camera("pinhole", (w, h), dict(fx=f, fy=f, cx=(w - 1) / 2 + 0.37, cy=(h - 1) / 2 - 0.21))


# ------------------------------------------------------------------------------------------ layout
def test_object_points_opencv_order_in_mm_and_metres():
    cb = T.ChessboardTarget(6, 5, 100.0)
    p = cb.object_points()
    assert p.shape == (30, 3) and p.dtype == np.float64
    np.testing.assert_allclose(p[1], [100.0, 0, 0])  # along a row first
    np.testing.assert_allclose(p[6], [0, 100.0, 0])  # then the next row
    np.testing.assert_allclose(cb.object_points_m()[7], [0.1, 0.1, 0.0])
    a = T.CircleGridTarget(4, 3, 10.0, asymmetric=True).object_points()
    np.testing.assert_allclose(a[:6, :2], [[0, 0], [20, 0], [40, 0], [60, 0], [10, 10], [30, 10]])
    c = T.CodedCheckerboardTarget()
    np.testing.assert_allclose(c.object_points()[12], [50.5, 50.5, 0])  # 11 columns: index 12 = (1, 1)
    np.testing.assert_allclose(c.center_mm, [252.5, 202.0])


def test_old_names_are_the_same_descriptions():
    from thermogrammetry.calibration import detect, detect_common
    from thermogrammetry.synthetic import targets as S

    assert detect_common.ChessboardSpec is T.ChessboardTarget is detect.ChessboardSpec
    assert detect_common.CircleGridSpec is T.CircleGridTarget
    assert detect_common.CodedCheckerboardSpec is T.CodedCheckerboardTarget
    # the synthetic names are metre-unit views holding the mm description
    v = S.CircleGridTarget(7, 4, 0.05, 0.02)
    assert v.target == T.CircleGridTarget(7, 4, 50.0, diameter_mm=20.0)
    assert v.spacing_m == pytest.approx(0.05) and v.margin_m == pytest.approx(0.05)
    np.testing.assert_allclose(v.object_points(), v.target.object_points() * 1e-3, rtol=0, atol=1e-15)
    assert S.ChessboardTarget(6, 5, 0.1).target == T.ChessboardTarget(6, 5, 100.0, corner0_square="dark")
    coded = S.CodedCheckerboardTarget()
    assert coded.target == T.CodedCheckerboardTarget()
    np.testing.assert_array_equal(coded.valid_ids(), T.CodedCheckerboardTarget().valid_ids())
    np.testing.assert_allclose(coded.centre, [0.2525, 0.202], atol=1e-15)
    # the detectors take either; Detection.object_points is mm in both cases
    assert T.as_target(v) is v.target
    with pytest.raises(ConfigError, match="CircleGridSpec"):
        detect.detect_circle_grid(np.zeros((16, 16)), S.ChessboardTarget(6, 5, 0.1))


@pytest.mark.parametrize(
    "factory, match",
    [
        (lambda: T.ChessboardTarget(1, 5, 100.0), r"ChessboardTarget\.inner_columns=1"),
        (lambda: T.ChessboardTarget(6, 5, "abc"), r"square_mm='abc'"),
        (lambda: T.ChessboardTarget(6, 5, 100.0, margin_mm=-3.0), r"margin_mm=-3\.0"),
        (lambda: T.ChessboardTarget(6, 5, 100.0, corner0_square="hot"), r"corner0_square='hot'"),
        (lambda: T.CircleGridTarget(7, 4, 50.0, diameter_mm=50.0), r"diameter_mm=50\.0.*nearest-neighbour distance 50 mm"),
        # asymmetric: nearest neighbours are sqrt(2) s apart
        (lambda: T.CircleGridTarget(4, 11, 20.0, asymmetric=True, diameter_mm=28.5), r"diameter_mm=28\.5.*28\.2843 mm"),
        (lambda: T.CircleGridTarget(7, 4, 50.0, asymmetric="yes"), r"asymmetric='yes'"),
        (lambda: T.CodedCheckerboardTarget(inner_rows=8), r"inner_rows=8: expected an odd number"),
        (lambda: T.CodedCheckerboardTarget(hidden_squares=3), r"hidden_squares=3: expected an even number"),
        (lambda: T.CodedCheckerboardTarget(marker_id=1), r"marker_id=1"),
        (lambda: T.CodedCheckerboardTarget(top_left_square="white"), r"top_left_square='white'"),
        (lambda: T.CodedCheckerboardTarget.from_parameters({"gridSize": 50.5}), r"missing key"),
        (lambda: T.CodedCheckerboardTarget.from_parameters(
            {"gridSize": 50.5, "arucoSize": 161.5, "bottomLeftField": "grey", "gridMaxHeight": 9, "gridMaxWidth": 11,
             "aruCoHiddenSize": 4, "aruco_dict": "aruco.DICT_3X3_1"}), r"bottomLeftField='grey'"),
        (lambda: T.as_target("board"), r"target='board'"),
    ],
)
def test_bad_descriptions_name_the_value(factory, match):
    with pytest.raises(ConfigError, match=match):
        factory()


def test_asymmetric_circles_wider_than_the_row_pitch_are_classified_whole():
    """Circles of diameter 1.3 s (allowed: < sqrt(2) s) reach into the neighbouring rows' bands; their
    area must still be complete. Midpoint sampling at s/400 over 12 circles: the boundary error is
    random-sign, ~(perimeter/h)^0.5 h^2 per circle, i.e. ~1e-4 relative in total; bound 0.2 %."""
    s, d = 10.0, 13.0
    tgt = T.CircleGridTarget(3, 4, s, asymmetric=True, diameter_mm=d, margin_mm=20.0)
    h = s / 400
    xmin, xmax, ymin, ymax = tgt.extent_mm()
    x, y = np.meshgrid(np.arange(xmin + h / 2, xmax, h), np.arange(ymin + h / 2, ymax, h))
    area = np.count_nonzero(tgt.classify(x, y) == T.FEATURE) * h * h
    exact = tgt.n_points * np.pi * (d / 2) ** 2
    assert abs(area / exact - 1) < 2e-3, area / exact
    # the nearest-row-only rule of the old renderer lost the caps beyond +-s/2 (~10 % of the area here)
    assert np.all(tgt.classify(np.array([0.0]), np.array([0.6 * s])) == T.FEATURE)


# --------------------------------------------------------------------- chessboard colour convention
@pytest.fixture(scope="module")
def fronto_board():
    """6x5 inner corners, 30 mm squares (~20 px), fronto-parallel, noise-free, PSF 0.6 px: the part
    colours can be read off pixel centres >= 5 px from any edge (blur tail exp(-5²/(2·0.6²)) ~ 1e-15)."""
    from thermogrammetry.synthetic.targets import render_target_image

    cam = _pinhole(320, 240, 400.0)
    out = {}
    for colour in ("dark", "bright"):
        tgt = T.ChessboardTarget(6, 5, 30.0, corner0_square=colour)
        c = tgt.object_points_m().mean(axis=0)
        pose = Pose(np.eye(3), -(c + np.array([0.0, 0.0, -0.6])))
        out[colour] = (tgt, cam, pose, render_target_image(cam, pose, tgt, supersample=4, psf_sigma_px=0.6,
                                                                  temperatures=(305.0, 297.0, 290.0)))
    return out


def _value_at(r, cam, pose, xy_mm):
    p = cam.project(pose.transform(np.array([[xy_mm[0] * 1e-3, xy_mm[1] * 1e-3, 0.0]])))[0]
    return float(r.image_k[int(round(p[1])), int(round(p[0]))])


def test_chessboard_top_left_square_is_the_cool_board_part(fronto_board):
    """ChessboardTarget docstring, classify() and the detector agree: for corner0_square="dark" the
    square diagonally outside corner 0 (x, y < 0) is a BOARD part (board_k = 297 K, the darker one,
    same colour as the border); its edge neighbours are FEATURE squares (305 K). "bright" swaps them.
    Pixels ~6 px inside a square of ~20 px, no blur: the value is the part temperature (float32 rounding)."""
    tgt, cam, pose, r = fronto_board["dark"]
    assert tgt.classify(np.array([-15.0]), np.array([-15.0]))[0] == T.BOARD
    assert _value_at(r, cam, pose, (-15, -15)) == pytest.approx(297.0, abs=1e-3)   # top-left square
    assert _value_at(r, cam, pose, (15, -15)) == pytest.approx(305.0, abs=1e-3)    # right of it
    assert _value_at(r, cam, pose, (-15, 15)) == pytest.approx(305.0, abs=1e-3)    # below it
    assert _value_at(r, cam, pose, (15, 15)) == pytest.approx(297.0, abs=1e-3)     # diagonal: same colour
    assert _value_at(r, cam, pose, (-45, -45)) == pytest.approx(297.0, abs=1e-3)   # border
    tgt_b, cam, pose, rb = fronto_board["bright"]
    assert tgt_b.classify(np.array([-15.0]), np.array([-15.0]))[0] == T.FEATURE
    assert _value_at(rb, cam, pose, (-15, -15)) == pytest.approx(305.0, abs=1e-3)
    assert _value_at(rb, cam, pose, (-45, -45)) == pytest.approx(297.0, abs=1e-3)
    with pytest.raises(ConfigError, match="corner0_square='any'"):
        T.ChessboardTarget(6, 5, 30.0, corner0_square="any").classify(np.zeros(1), np.zeros(1))


def test_detector_numbers_the_board_as_described(fronto_board):
    """The 6x5 board is not colour-symmetric, so the description fixes corner 0: detecting each render
    with its own description gives corner k at the true projection of object point k (index by index).
    This checks numbering, not accuracy: the default corner estimator (findChessboardCornersSB) has a
    sub-pixel-phase dependent error, measured up to 0.4 px on these axis-aligned edges (0.09 px RMS
    in test_detect); any wrongly numbered corner is at least one square (~20 px) away, the board
    reversed ~100 px. Bound 1 px sits between the two."""
    from thermogrammetry.calibration.detect import detect

    for colour in ("dark", "bright"):
        tgt, cam, pose, r = fronto_board[colour]
        d = detect(r.image_k, tgt, colour)
        assert d.found, d.reason
        err = np.linalg.norm(d.points_px - r.points_px[d.object_ids], axis=1)
        assert err.max() < 1.0, (colour, err.max())
        np.testing.assert_array_equal(d.object_ids, np.arange(30))


# ------------------------------------------------------------- rendering from the one description
def test_render_from_mm_description_equals_metre_view():
    from thermogrammetry.synthetic.targets import CircleGridTarget, render_target_image

    cam = _pinhole(96, 72, 120.0)
    view = CircleGridTarget(5, 4, 0.06, 0.014)
    c = view.object_points().mean(axis=0)
    pose = Pose.look_at(c + np.array([0.1, -0.05, -0.9]), c, up=(0, -1, 0))
    a = render_target_image(cam, pose, view, supersample=2)
    b = render_target_image(cam, pose, view.target, supersample=2)
    np.testing.assert_array_equal(a.image_k, b.image_k)
    np.testing.assert_array_equal(a.points_px, b.points_px)
    np.testing.assert_allclose(b.points_target, view.target.object_points() * 1e-3, atol=1e-15)  # metres
    assert b.target is view.target
    with pytest.raises(ConfigError, match="diameter_mm=None"):
        render_target_image(cam, pose, T.CircleGridTarget(5, 4, 60.0), supersample=1)


# ---------------------------------------------------------- order-robust comparison with the truth
def test_match_to_truth_pairs_by_position():
    from thermogrammetry.pipeline.demo import match_to_truth

    rng = np.random.default_rng(5)
    truth = np.c_[np.tile(np.arange(7) * 20.0, 4), np.repeat(np.arange(4) * 20.0, 7)] + 50
    perm = rng.permutation(28)[:20]
    noise = rng.normal(0, 0.1, (20, 2))  # << half the 20 px spacing: the pairing is unambiguous
    err, idx = match_to_truth(truth[perm] + noise, np.r_[truth, [[np.nan, np.nan]]])
    np.testing.assert_array_equal(idx, perm)
    np.testing.assert_allclose(err, np.linalg.norm(noise, axis=1), rtol=1e-12)
    with pytest.raises(ConfigError, match="finite true points"):
        match_to_truth(truth, truth[:5])


def test_symmetric_grid_upside_down_compared_by_position():
    """A symmetric 7x4 circle grid turned 180° in the image: the detector's canonical order starts at
    the image's top-left, i.e. at the target's last circle. Index-by-index comparison reports the grid
    size as error; pairing by position gives the detection error. Blob centroids with 0.05 K NETD on
    a 7 K contrast and PSF 0.6 px: ~0.05 px; bound 0.3 px (as in the detector tests)."""
    from thermogrammetry.calibration.detect import detect
    from thermogrammetry.pipeline.demo import match_to_truth
    from thermogrammetry.synthetic.targets import render_target_image

    cam = _pinhole(320, 240, 600.0)
    tgt = T.CircleGridTarget(7, 4, 50.0, diameter_mm=20.0)
    c = tgt.object_points_m().mean(axis=0)
    pose = Pose.look_at(c + np.array([0.25, 0.2, -1.6]), c, up=(0, 1, 0))  # image up = target +y: upside down
    r = render_target_image(cam, pose, tgt, supersample=4, psf_sigma_px=0.6, netd_k=0.05, seed=11,
                            temperatures=(303.15, 296.15, 295.15))
    assert r.all_visible
    d = detect(r.image_k, tgt, "upside-down")
    assert d.found, d.reason
    naive = np.linalg.norm(d.points_px - r.points_px[d.object_ids], axis=1)
    assert naive.max() > 50.0  # the orders differ (spacing is ~19 px, grid ~115 px)
    err, idx = match_to_truth(d.points_px, r.points_px)
    assert err.max() < 0.3, err.max()
    np.testing.assert_array_equal(idx, 27 - d.object_ids)  # exactly the 180° renumbering


# ------------------------------------------------------------------------------------------ layering
def test_targets_and_synthetic_do_not_import_calibration():
    """thermogrammetry.targets is the lowest layer (errors + numpy); synthetic must not import the
    calibration layer for targets. Static check of every import statement (testfield.py belongs to the
    calibration engineer's simulator and is excluded), plus a fresh interpreter that loads the
    renderer and the descriptions and must not have pulled in thermogrammetry.calibration."""
    import ast
    import subprocess
    import sys
    from pathlib import Path

    import thermogrammetry

    root = Path(thermogrammetry.__file__).parent
    files = sorted((root / "targets").glob("*.py")) + [p for p in (root / "synthetic").glob("*.py") if p.name != "testfield.py"]
    bad = []
    for p in files:
        for node in ast.walk(ast.parse(p.read_text())):
            mods = []
            if isinstance(node, ast.ImportFrom):
                mods = [("." * node.level) + (node.module or "")] + [a.name for a in node.names]
            elif isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            if any("calibration" in m for m in mods):
                bad.append(f"{p.name}:{node.lineno}")
    assert not bad, bad
    code = ("import sys, thermogrammetry.targets, thermogrammetry.synthetic.targets; "
            "print([m for m in sys.modules if m.startswith('thermogrammetry.calibration')])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]", out
