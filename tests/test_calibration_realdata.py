"""Real thermal chessboard (../shared/data/thermal_chessboard): our self-calibration vs cv2.calibrateCamera.

The comparison is on exactly the same observations and with the same number of intrinsics (ours:
c, x0, y0, K1-K3, P1, P2 with square pixels; OpenCV: fx = fy (CALIB_FIX_ASPECT_RATIO), cx, cy,
k1, k2, p1, p2, k3). Both minimise the sum of squared pixel residuals, so "no worse" allows only
rounding (1e-4 px); the correction and forward distortion forms differ, so the minima differ a little.

Not used here: the 15 hand-measured corner sets of ``Image registration/CornerPoints_IR.csv`` do not
coincide with the published thermal images (8-18 px offsets) and their weak geometry leaves the
principal point undetermined (OpenCV puts cy at 45 px, i.e. near the top edge).
"""

from __future__ import annotations

import cv2
import numpy as np

from conftest import data_path

from thermogrammetry.calibration.selfcal import CameraSetup, ImageMeasurements, SelfCalibrationOptions, calibrate


def _cv2_rms(obj_list, img_list, size):
    op = [o.astype(np.float32) for o in obj_list]
    ip = [i.astype(np.float32).reshape(-1, 1, 2) for i in img_list]
    K0 = cv2.initCameraMatrix2D(op, ip, size, 1.0)
    f = 0.5 * (K0[0, 0] + K0[1, 1])
    K0[0, 0] = K0[1, 1] = f
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 300, 1e-14)
    rms, K, dist, _, _ = cv2.calibrateCamera(op, ip, size, K0, None,
                                             flags=cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_USE_INTRINSIC_GUESS, criteria=crit)
    return rms, K


def test_detected_chessboard_rms_no_worse_than_opencv():
    from thermogrammetry.calibration.detect import detect_chessboard
    from thermogrammetry.calibration.detect_common import ChessboardSpec

    folder = data_path("thermal_chessboard", "Thermal camera calibration", "Thermal images cropped")
    files = sorted(folder.glob("*.jpg"))[::4]  # 12 of the 47 views keep the test short
    spec = ChessboardSpec(6, 5, 100.0, corner0_square="any")
    dets = [detect_chessboard(cv2.imread(str(f), cv2.IMREAD_UNCHANGED), spec, f.name) for f in files]
    found = [d for d in dets if d.found]
    assert len(found) >= len(files) - 1
    obj = spec.object_points() * 1e-3
    ims = [ImageMeasurements(d.image_id, 0, d.object_ids, d.points_px) for d in found]
    r = calibrate([CameraSetup("thermal", (640, 480), 17.0)], obj, ims, options=SelfCalibrationOptions(snooping=False))
    assert r.outcome.success
    rms_cv, _ = _cv2_rms([obj[d.object_ids] for d in found], [d.points_px for d in found], (640, 480))
    assert r.rms_px <= rms_cv + 1e-4, (r.rms_px, rms_cv)
    # with blunder elimination every image is still used and the image noise is sub-pixel
    r2 = calibrate([CameraSetup("thermal", (640, 480), 17.0)], obj, ims)
    assert len(r2.images_used) == len(found)
    assert 0.1 < r2.cameras[0].sigma_xy_px[0] < 1.0
