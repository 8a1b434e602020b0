"""Target detection on the real thermal data sets in ../shared/data (skipped when absent).

* thermal_chessboard: 47 views of a heated 6x5-inner-corner, 100 mm chessboard, 640x480, each view
  twice -- with the background masked by the author and unmasked (cluttered). OpenCV's plain
  ``findChessboardCorners`` finds the board in 3 of the unmasked views (7 with the author's gamma).
* ir_coded_checkerboard: 60 views (382x288) of the MRT coded target (11x9 corners, ArUco marker in
  the middle), often partly outside the frame; OpenCV's chessboard detectors find it in 1 of 60.

Issue 6 targets: >= 45/47 masked, >= 40/47 unmasked, >= 50/60 coded. The corner *quality* is checked
through ``cv2.calibrateCamera`` (pinhole + 5 distortion terms): a misidentified corner (wrong id,
a corner pulled onto the board outline) costs pixels of RMS, good corners give a few tenths.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from thermogrammetry.calibration.detect import ChessboardSpec, CodedCheckerboardSpec, detect_many
from thermogrammetry.calibration.detect_io import read_image

from conftest import data_path

CB_SPEC = ChessboardSpec(6, 5, 100.0)


def _load(folder, pattern):
    files = sorted(folder.glob(pattern))
    return [f.stem for f in files], [read_image(f) for f in files]


@pytest.fixture(scope="module")
def chessboard_detections(shared_data):
    root = data_path("thermal_chessboard", "Thermal camera calibration")
    out = {}
    for key, sub in (("masked", "Thermal images cropped"), ("unmasked", "Thermal Images")):
        names, images = _load(root / sub, "*.jpg")
        assert len(images) == 47
        out[key] = (names, images, detect_many(images, CB_SPEC, names))
    return out


@pytest.fixture(scope="module")
def coded_detections(shared_data):
    folder = data_path("ir_coded_checkerboard", "imageDataset")
    names, images = _load(folder, "*.png")
    assert len(images) == 60
    return names, images, detect_many(images, CodedCheckerboardSpec(), names)


def _calibrate(dets, spec, image_size):
    found = [d for d in dets if d.found]
    obj = [spec.object_points()[d.object_ids].astype(np.float32) for d in found]
    img = [d.points_px.astype(np.float32) for d in found]
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, image_size, None, None)
    return rms, K, dist, rvecs


def test_chessboard_found_counts(chessboard_detections):
    for key, need in (("masked", 45), ("unmasked", 40)):
        names, images, dets = chessboard_detections[key]
        assert len(dets) == 47 and all(d.reason for d in dets)  # every image has a verdict
        n = sum(d.found for d in dets)
        assert n >= need, (key, n, [(d.image_id, d.reason) for d in dets if not d.found])
    # the reference: OpenCV's plain detector on the unmasked views (the issue quotes 7 with gamma)
    names, images, _ = chessboard_detections["unmasked"]
    plain = sum(bool(cv2.findChessboardCorners(im, CB_SPEC.pattern_size)[0]) for im in images[:12])
    assert plain <= 6  # of the first 12 views: the plain detector misses most of them


def test_chessboard_masked_and_unmasked_views_agree(chessboard_detections):
    """The two versions of a view hold the same board pixels: same order, same corners."""
    _, _, masked = chessboard_detections["masked"]
    _, _, unmasked = chessboard_detections["unmasked"]
    both = [(a, b) for a, b in zip(masked, unmasked) if a.found and b.found]
    assert len(both) >= 40
    diffs = np.array([np.max(np.linalg.norm(a.points_px - b.points_px, axis=1)) for a, b in both])
    # measured: median 0.02 px, 95 % below 0.06 px (masking changes the image only off the board)
    assert np.all(diffs < 0.5), diffs.max()


def test_chessboard_corner_quality_and_consistent_order(chessboard_detections):
    _, _, dets = chessboard_detections["masked"]
    rms, K, dist, rvecs = _calibrate(dets, CB_SPEC, (640, 480))
    # measured 0.455 px (cornerSubPix refinement would give 0.65 px; the criterion compares
    # the final calibration with cv2.calibrateCamera on the same detections -- calibration engineer)
    assert 0.2 < rms < 0.6
    assert 600 < K[0, 0] < 720  # SOURCE.md: fx ~ 658 from the author's pipeline
    # consistent order: the board frame is right-handed with z away from the camera in every view
    # (camera z . board z > 0) and the board's x axis points the same way in the image in every view
    # (the board was held upright): a 180 deg flip in one view would show as a reversed x axis
    found = [d for d in dets if d.found]
    for d, rv in zip(found, rvecs):
        R = cv2.Rodrigues(rv)[0]
        assert R[2, 2] > 0.3, d.image_id
    xdir = np.array([d.points_px[5] - d.points_px[0] for d in found])
    xdir /= np.linalg.norm(xdir, axis=1, keepdims=True)
    mean = xdir.mean(axis=0)
    mean /= np.linalg.norm(mean)
    assert np.all(xdir @ mean > 0.3)


def test_coded_checkerboard_found_and_identified(coded_detections):
    names, images, dets = coded_detections
    n = sum(d.found for d in dets)
    assert n >= 50, [(d.image_id, d.reason) for d in dets if not d.found]
    spec = CodedCheckerboardSpec()
    valid = set(spec.valid_ids().tolist())
    counts = np.array([d.n_points for d in dets if d.found])
    assert np.median(counts) >= 50  # measured median 61.5 of 76 usable corners
    for d in dets:
        if d.found:
            assert set(d.object_ids.tolist()) <= valid
            assert np.all(np.diff(d.object_ids) > 0)
    rms, K, dist, _ = _calibrate(dets, spec, (382, 288))
    # measured 0.33 px over ~3580 corners (max residual 1.4 px); one misidentified corner (50 mm off)
    # would cost pixels
    assert 0.15 < rms < 0.5
    assert 330 < K[0, 0] < 420  # 382 px wide sensor, ~54 deg field of view


def test_coded_checkerboard_marker_found_in_every_view(coded_detections):
    _, _, dets = coded_detections
    assert all("marker found" in d.reason for d in dets)
    assert sum(d.extra.get("inverted", False) for d in dets) == 0  # the target appears as printed


def test_chessboard_on_downscaled_views(chessboard_detections):
    """Small sensors: the unmasked views reduced to 128x96 (squares ~8 px). Measured 47/47 (one by
    the upsampling pass); OpenCV's plain detector finds 2."""
    names, images, full = chessboard_detections["unmasked"]
    small = [cv2.resize(im, (128, 96), interpolation=cv2.INTER_AREA) for im in images]
    dets = detect_many(small, CB_SPEC, names)
    assert sum(d.found for d in dets) >= 40
    # same corners in the same order as at full resolution, scaled (pixel centres:
    # x_small = (x + 0.5) / 5 - 0.5). A different order would be off by a square (~8 px); the
    # accuracy at 8 px squares is a few tenths of a pixel (measured median per-view RMS ~0.3 px).
    d = [np.linalg.norm(s.points_px - ((f.points_px + 0.5) / 5.0 - 0.5), axis=1)
         for s, f in zip(dets, full) if s.found and f.found]
    assert max(x.max() for x in d) < 3.0
    assert np.median([np.sqrt(np.mean(x**2)) for x in d]) < 0.5


def test_chessboard_colour_rule_decides_the_order(chessboard_detections):
    """corner0_square="bright" must give exactly the reversed order of the default "dark" on the real
    board (6x5: the two diagonal corner squares differ in colour) -- the colour, not the geometric
    tie-break, decides."""
    names, images, dets = chessboard_detections["masked"]
    for k in range(0, 47, 12):
        bright = detect_many([images[k]], ChessboardSpec(6, 5, 100.0, corner0_square="bright"), [names[k]])[0]
        assert bright.found and dets[k].found
        np.testing.assert_allclose(bright.points_px, dets[k].points_px[::-1], atol=1e-9)


def test_chessboard_on_low_contrast_8bit_views(chessboard_detections):
    """A thermal camera's 8-bit output of a weakly heated board: the unmasked views squeezed to ~7
    grey levels around 100 with 0.5-level noise. The percentile stretch restores the contrast
    (measured 47/47, same corners); findChessboardCornersSB on the raw frames finds none."""
    names, images, full = chessboard_detections["unmasked"]
    rng = np.random.default_rng(0)
    low = [np.clip(np.rint(100 + (im.astype(float) - im.mean()) * 0.03 + rng.normal(0, 0.5, im.shape)), 0, 255)
           .astype(np.uint8) for im in images]
    dets = detect_many(low, CB_SPEC, names)
    assert sum(d.found for d in dets) >= 40
    both = [(d, f) for d, f in zip(dets, full) if d.found and f.found]
    # same order; the quantisation to 7 levels costs accuracy (measured per-view RMS median 0.27 px,
    # max 0.48 px against the full-contrast corners)
    rms = [np.sqrt(np.mean(np.sum((d.points_px - f.points_px) ** 2, axis=1))) for d, f in both]
    assert max(rms) < 1.5 and np.median(rms) < 0.5
    sb_raw = sum(bool(cv2.findChessboardCornersSB(im, CB_SPEC.pattern_size, flags=cv2.CALIB_CB_EXHAUSTIVE)[0])
                 for im in low[:8])
    assert sb_raw <= 2
