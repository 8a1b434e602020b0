"""DJI gimbal angles <-> cam_from_world in a projected CRS, and the rotation of a block about a straight GNSS line taken
from camera attitudes (sfm.attitude; the real check against an RTK-oriented flight is in tests/test_survey.py)."""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry.errors import InvalidInputError
from thermogrammetry.geometry.rotations import matrix_from_axis_angle
from thermogrammetry.sfm.attitude import (cam_from_world_from_gimbal, gimbal_from_cam_from_world,
                                          meridian_convergence_deg, rotation_about_axis)


def test_gimbal_conventions_on_named_cases():
    # level, looking north: optical axis (camera z) north, image x east, image y down
    R = cam_from_world_from_gimbal(0.0, 0.0, 0.0)[0]
    np.testing.assert_allclose(R.T, [[1, 0, 0], [0, 0, 1], [0, -1, 0]], atol=1e-12)
    # nadir, heading east (yaw 90): optical axis down, image top (-y) forward = east, image x south
    R = cam_from_world_from_gimbal(90.0, -90.0, 0.0)[0]
    np.testing.assert_allclose(R.T @ [0, 0, 1], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(R.T @ [0, -1, 0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(R.T @ [1, 0, 0], [0, -1, 0], atol=1e-12)
    # DJI writes one nadir heading either way: (yaw, roll 0) and (yaw - 180, roll 180)
    np.testing.assert_allclose(cam_from_world_from_gimbal(-91.3, -90.0, 180.0), cam_from_world_from_gimbal(88.7, -90.0, 0.0),
                               atol=1e-12)
    # grid north east of true north by γ: a camera looking true north looks γ west of grid north
    R = cam_from_world_from_gimbal(0.0, 0.0, 0.0, convergence_deg=2.0)[0]
    z = R.T @ [0, 0, 1]
    assert np.degrees(np.arctan2(z[0], z[1])) == pytest.approx(-2.0, abs=1e-9)


def test_gimbal_round_trip():
    rng = np.random.default_rng(0)
    y, p, r = rng.uniform(-179, 179, 50), rng.uniform(-89, 30, 50), rng.uniform(-20, 20, 50)
    g = rng.uniform(-3, 3, 50)
    R = cam_from_world_from_gimbal(y, p, r, g)
    y2, p2, r2 = gimbal_from_cam_from_world(R, g)
    np.testing.assert_allclose(cam_from_world_from_gimbal(y2, p2, r2, g), R, atol=1e-12)
    np.testing.assert_allclose(p2, p, atol=1e-9)
    # at nadir the heading goes into the yaw
    R = cam_from_world_from_gimbal(30.0, -90.0, 12.0)
    y3, p3, r3 = gimbal_from_cam_from_world(R)
    assert r3[0] == 0.0 and p3[0] == pytest.approx(-90.0)
    np.testing.assert_allclose(cam_from_world_from_gimbal(y3, p3, r3), R, atol=1e-9)


def test_meridian_convergence():
    # UTM 31N at 4.43° E, 51.40° N (the M3T flight): γ = (λ - λ0) sin φ to first order = 1.43 * 0.781 = 1.118°
    assert meridian_convergence_deg("EPSG:32631", 4.4302, 51.4024)[0] == pytest.approx(1.118, abs=0.002)
    assert meridian_convergence_deg("EPSG:4326", 4.43, 51.4)[0] == 0.0
    with pytest.raises(InvalidInputError, match="EPSG:999999"):
        meridian_convergence_deg("EPSG:999999", 4.43, 51.4)


def test_rotation_about_axis_recovers_a_turn_despite_one_wrong_attitude():
    rng = np.random.default_rng(4)
    axis = np.array([0.8, 0.6, 0.0])
    R_true = np.array([matrix_from_axis_angle(rng.normal(0, 0.5, 3)) for _ in range(9)])
    turn = np.radians(25.0)
    # the block turned by -25° about the axis: R_est = R_true Q(turn) (cam_from_world of a block rotated by Q(-turn))
    R_est = R_true @ matrix_from_axis_angle(turn * axis)
    R_obs = np.array([matrix_from_axis_angle(rng.normal(0, np.radians(0.5), 3)) @ R for R in R_true])
    R_obs[3] = matrix_from_axis_angle([0.0, 0.0, 1.5]) @ R_true[3]  # a wrong tag
    a, per = rotation_about_axis(R_est, R_obs, axis)
    # 8 attitudes with 0.5° noise (0.5° / sqrt(8) ~ 0.2° for the mean; the median ~1.25x that): 0.6° is > 2.5σ
    assert np.degrees(a) == pytest.approx(25.0, abs=0.6)
    assert len(per) == 9
    with pytest.raises(InvalidInputError, match="equal counts"):
        rotation_about_axis(R_est[:2], R_obs[:3], axis)


def test_survey_names_an_image_far_from_its_attitude():
    from types import SimpleNamespace

    from thermogrammetry.pipeline.survey import ATTITUDE_FLAG_DEG, _attitude_check

    rng = np.random.default_rng(1)
    R = np.array([matrix_from_axis_angle(rng.normal(0, 1, 3)) for _ in range(6)])
    # attitudes 1.5° off about x (a common tilt) except image 4 (a wrong resection: 25° off); image 5 has none
    att = np.array([r @ matrix_from_axis_angle(np.radians([1.5, 0, 0])) for r in R])
    att[4] = R[4] @ matrix_from_axis_angle(np.radians([0, 25.0, 0]))
    att[5] = np.nan
    status = [{} for _ in range(6)]
    a = _attitude_check(SimpleNamespace(R=R), [(0, np.arange(6), None, "GNSS", True)], SimpleNamespace(attitude=att),
                        [f"I{k}" for k in range(6)], status)
    assert a["n"] == 5 and a["median_deg"] == pytest.approx(1.5, abs=1e-9)
    assert [f["image"] for f in a["flagged"]] == ["I4"] and a["flagged"][0]["deviation_deg"] > ATTITUDE_FLAG_DEG
    assert status[0]["attitude_deviation_deg"] == pytest.approx(1.5, abs=1e-9) and "attitude_deviation_deg" not in status[5]
    # R_att = R_adj E: E's mean rotation vector, world frame
    np.testing.assert_allclose(a["mean_deg"], [1.2, 5.0, 0.0], atol=1e-9)
    # a convention the files do not describe (every attitude 40° off about the same world axis) names nobody
    att2 = np.array([r @ matrix_from_axis_angle(np.radians([0, 0, 40.0 + k])) for k, r in enumerate(R)])
    a2 = _attitude_check(SimpleNamespace(R=R), [(0, np.arange(6), None, "GNSS", True)], SimpleNamespace(attitude=att2),
                         [f"I{k}" for k in range(6)], [{} for _ in range(6)])
    assert a2["median_deg"] > ATTITUDE_FLAG_DEG and a2["flagged"] == []
