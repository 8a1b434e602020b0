"""Rotations and Pose: round trips, agreement with OpenCV/SciPy, conventions.md sign checks."""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from thermogrammetry.errors import DegenerateInputError, InvalidInputError, NonFiniteError, ShapeError
from thermogrammetry.geometry import Pose, project_points, rotations as rot


def _random_rvecs(rng, n):
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    ang = rng.uniform(0, np.pi, n)
    ang[:3] = [0.0, 1e-9, np.pi - 1e-9]  # edge cases: identity, tiny, near π
    return axes * ang[:, None]


def test_axis_angle_matches_opencv_and_round_trips(rng):
    r = _random_rvecs(rng, 200)
    R = rot.matrix_from_axis_angle(r)
    R_cv = np.stack([cv2.Rodrigues(v)[0] for v in r])
    assert np.abs(R - R_cv).max() < 5e-14  # measured 7.2e-16
    r2 = rot.axis_angle_from_matrix(R)
    # near π the vector is defined up to sign; compare matrices there, vectors elsewhere
    far = np.linalg.norm(r, axis=1) < np.pi - 1e-6
    assert np.abs(r2[far] - r[far]).max() < 5e-14  # measured 6.7e-16 rad
    assert np.abs(rot.matrix_from_axis_angle(r2) - R).max() < 5e-14  # measured 8.9e-16


def test_quaternion_matches_scipy_hamilton_w_first(rng):
    r = _random_rvecs(rng, 200)
    R = rot.matrix_from_axis_angle(r)
    q = rot.quaternion_from_matrix(R)
    assert np.all(q[:, 0] >= 0)
    assert np.abs(np.linalg.norm(q, axis=1) - 1).max() < 1e-14
    qs = Rotation.from_matrix(R).as_quat()  # (x, y, z, w)
    qs = np.hstack([qs[:, 3:], qs[:, :3]])
    qs *= np.sign(qs[:, :1] + (qs[:, :1] == 0))
    near_pi = np.abs(q[:, 0]) < 1e-6
    assert np.abs(q[~near_pi] - qs[~near_pi]).max() < 2e-14  # measured 2.2e-16
    assert np.abs(rot.matrix_from_quaternion(q) - R).max() < 5e-14  # measured 8.9e-16
    # a known value: 90° about z
    q90 = rot.quaternion_from_matrix(rot.matrix_from_axis_angle([0, 0, np.pi / 2]))
    assert np.allclose(q90, [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], rtol=0, atol=1e-15)  # measured 1.1e-16


def test_opk_definition_and_round_trip(rng):
    # conventions.md: ω = φ = κ = 0 looks straight down −Z with image x along +X
    p = Pose.from_opk(0.0, 0.0, 0.0, [10.0, 20.0, 100.0])
    assert np.allclose(p.axis, [0, 0, -1]) and np.allclose(p.R[0], [1, 0, 0])
    # M = Rκ Rφ Rω written out element by element (Wolf & Dewitt C-33)
    o, f, k = 0.3, -0.4, 1.1
    co, so, cf, sf, ck, sk = np.cos(o), np.sin(o), np.cos(f), np.sin(f), np.cos(k), np.sin(k)
    M_ref = np.array(
        [
            [cf * ck, so * sf * ck + co * sk, -co * sf * ck + so * sk],
            [-cf * sk, -so * sf * sk + co * ck, co * sf * sk + so * ck],
            [sf, -so * cf, co * cf],
        ]
    )
    assert np.abs(rot.matrix_from_opk(o, f, k) - M_ref).max() < 1e-15
    # world_from_photo = Rx(ω) Ry(φ) Rz(κ) with active elementary rotations
    act = Rotation.from_euler("XYZ", [o, f, k]).as_matrix()
    assert np.abs(M_ref.T - act).max() < 1e-14
    ang = rng.uniform([-np.pi, -np.pi / 2 + 1e-3, -np.pi], [np.pi, np.pi / 2 - 1e-3, np.pi], (500, 3))
    M = rot.matrix_from_opk(ang[:, 0], ang[:, 1], ang[:, 2])
    o2, f2, k2 = rot.opk_from_matrix(M)
    assert np.abs(np.stack([o2, f2, k2], 1) - ang).max() < 2e-14  # measured 2.2e-16 rad
    # gimbal lock: φ = 90° still reproduces the matrix
    Ml = rot.matrix_from_opk(0.2, np.pi / 2, 0.5)
    assert np.abs(rot.matrix_from_opk(*rot.opk_from_matrix(Ml)) - Ml).max() < 2e-15  # measured 2.9e-17


def test_opk_derivatives_central_differences(rng):
    ang = rng.uniform(-1.2, 1.2, 3)
    dM = rot.opk_derivatives(*ang)
    h = 1e-6
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        fd = (rot.matrix_from_opk(*(ang + e)) - rot.matrix_from_opk(*(ang - e))) / (2 * h)
        assert np.abs(dM[i] - fd).max() < 1e-9
    # increment Jacobian: R(opk + dθ) ≈ R(opk) exp([A dθ]×)
    A = rot.opk_to_increment_jacobian(*ang)
    d = rng.normal(size=3) * 1e-6
    R0 = rot.PHOTO_FROM_CAM @ rot.matrix_from_opk(*ang)
    R1 = rot.PHOTO_FROM_CAM @ rot.matrix_from_opk(*(ang + d))
    delta = rot.axis_angle_from_matrix(R0.T @ R1)
    assert np.abs(delta - A @ d).max() < 5e-12  # measured 7.0e-14


def test_pose_basics(rng):
    R = rot.matrix_from_axis_angle(rng.normal(size=3))
    C = rng.normal(size=3) * 5
    p = Pose.from_center(R, C)
    assert np.allclose(p.center, C, rtol=0, atol=5e-14)  # measured 6.7e-16 m
    X = rng.normal(size=(10, 3))
    Xc = p.transform(X)
    assert np.allclose(Xc, (X - C) @ R.T, rtol=0, atol=2e-14)  # measured 2.6e-16 m
    assert np.allclose(p.inverse().transform(Xc), X, rtol=0, atol=1e-13)  # measured 2.2e-15 m
    q = Pose.from_rvec(rng.normal(size=3), rng.normal(size=3))
    assert np.allclose(p.compose(q).transform(X), p.transform(q.transform(X)), rtol=0, atol=5e-14)  # measured 8.9e-16 m
    o, f, k, X0 = p.to_opk()
    assert Pose.from_opk(o, f, k, X0).allclose(p, atol=1e-12)
    la = Pose.look_at([0, -10, 2], [0, 0, 2])  # looking north (+Y), horizontally
    assert np.allclose(la.axis, [0, 1, 0]) and np.allclose(la.R[0], [1, 0, 0]) and np.allclose(la.R[1], [0, 0, -1])
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    xy = project_points(K, la, [[1.0, 0.0, 2.0], [0.0, 0.0, 3.0]])
    assert np.allclose(xy, [[320 + 50, 240], [320, 240 - 50]], rtol=0, atol=1e-12)  # +X right, +Z up on image


def test_pose_bad_input():
    with pytest.raises(InvalidInputError, match="R: not a proper rotation"):
        Pose(np.diag([1.0, 1.0, -1.0]), np.zeros(3))
    with pytest.raises(ShapeError, match=r"t: expected shape \(3\)"):
        Pose(np.eye(3), np.zeros(4))
    with pytest.raises(NonFiniteError, match="points_world"):
        Pose.identity().transform([[0, 0, np.nan]])
    with pytest.raises(ShapeError, match="points_world"):
        Pose.identity().transform(np.zeros((4, 2)))
    with pytest.raises(DegenerateInputError, match="up"):
        Pose.look_at([0, 0, 10], [0, 0, 0])
    with pytest.raises(ShapeError, match="rvec"):
        rot.matrix_from_axis_angle([1.0, 2.0])
