"""Analytic Jacobians of the geometry kernels vs central finite differences (relative 1e-6 per column)."""

import numpy as np

from thermogrammetry import Camera
from thermogrammetry.geometry import Pose
from thermogrammetry.geometry import rotations as rot
from thermogrammetry.geometry.dlt import _dlt_residuals
from thermogrammetry.geometry.helmert import similarity_residuals
from thermogrammetry.geometry.resection import collinearity_residuals
from thermogrammetry.geometry.triangulation import reprojection_residuals

CAM = Camera("opencv", (640, 480), dict(fx=600, fy=590, cx=322, cy=238, k1=-0.2, k2=0.05, p1=1e-3, p2=-5e-4, k3=0.01))


def _fd_check(fun, x, update, h):
    v, J = fun(x)
    for i in range(x.size):
        e = np.zeros(x.size)
        e[i] = h[i]
        fd = (fun(update(x, e))[0] - fun(update(x, -e))[0]) / (2 * h[i])
        err = np.linalg.norm(J[:, i] - fd)
        assert err <= 1e-6 * np.linalg.norm(fd) + 1e-12, (i, err, np.linalg.norm(fd))


def _add(x, dx):
    return x + dx


def test_dlt_residual_jacobian_with_additional_parameters(rng):
    Xn = rng.normal(size=(20, 3))
    xn = rng.normal(size=(20, 2)) * 0.8
    L = np.array([1.1, 0.1, -0.2, 0.05, -0.1, 1.05, 0.15, -0.04, 0.05, -0.03, 0.08])
    names = ("K1", "K2", "K3", "P1", "P2")
    p = np.concatenate([L, [0.05, -0.01, 0.002, 0.003, -0.004]])
    _fd_check(lambda q: _dlt_residuals(q, Xn, xn, names), p, _add, np.full(p.size, 1e-6))


def test_collinearity_jacobian_rotation_increment_and_interior(rng):
    pose = Pose.look_at([1.0, -6.0, 2.0], [0.0, 0.0, 0.0])
    X = rng.uniform(-1, 1, (15, 3))
    xy = CAM.project(pose.transform(X)) + rng.normal(0, 1, (15, 2))
    idx = [CAM.param_names.index(n) for n in ("fx", "cx", "k1", "p2")]
    p = np.concatenate([rot.axis_angle_from_matrix(pose.R), pose.center, CAM.params[idx]])

    def update(q, dq):  # the solver's increment: R ← R·exp([δ]×)
        R = rot.matrix_from_axis_angle(q[:3]) @ rot.matrix_from_axis_angle(dq[:3])
        return np.concatenate([rot.axis_angle_from_matrix(R), q[3:] + dq[3:]])

    h = np.array([1e-6] * 6 + [1e-3, 1e-3, 1e-6, 1e-8])
    _fd_check(lambda q: collinearity_residuals(q, CAM, X, xy, idx), p, update, h)


def test_similarity_jacobian(rng):
    X = rng.normal(size=(10, 3)) * 5
    Y = rng.normal(size=(10, 3))
    p = np.concatenate([[0.3, -0.2, 1.0], [1.0, 2.0, 3.0], [1.3]])

    def update(q, dq):  # R ← exp([δ]×)·R
        R = rot.matrix_from_axis_angle(dq[:3]) @ rot.matrix_from_axis_angle(q[:3])
        return np.concatenate([rot.axis_angle_from_matrix(R), q[3:] + dq[3:]])

    _fd_check(lambda q: similarity_residuals(q, X, Y), p, update, np.full(7, 1e-6))


def test_reprojection_jacobian(rng):
    poses = [Pose.look_at(c, [0.0, 0.0, 0.0]) for c in ([-2.0, -8.0, 1.0], [2.0, -8.0, 1.5])]
    cams = [CAM, Camera("pinhole", (320, 240), dict(fx=300, fy=300, cx=160, cy=120))]
    X = rng.uniform(-1, 1, (6, 3))
    xy = rng.uniform(0, 300, (2, 6, 2))
    mask = np.ones((2, 6), bool)
    mask[1, 2] = False
    for n in range(6):
        def fun(x, n=n):
            v, J = reprojection_residuals(x[None], cams, poses, xy[:, n:n + 1], mask[:, n:n + 1])
            return v[0], J[0]

        _fd_check(fun, X[n], _add, np.full(3, 1e-6))


def test_collinearity_jacobian_fixed_interior_point_only_path(rng):
    """Fixed interior orientation uses the cameras' point-only Jacobian (Camera and a bare K)."""
    from thermogrammetry.geometry._camera import PinholeK

    pose = Pose.look_at([1.0, -6.0, 2.0], [0.0, 0.0, 0.0])
    X = rng.uniform(-1, 1, (15, 3))
    K = np.array([[600.0, 0.0, 322.0], [0.0, 590.0, 238.0], [0.0, 0.0, 1.0]])
    p = np.concatenate([rot.axis_angle_from_matrix(pose.R), pose.center])

    def update(q, dq):
        R = rot.matrix_from_axis_angle(q[:3]) @ rot.matrix_from_axis_angle(dq[:3])
        return np.concatenate([rot.axis_angle_from_matrix(R), q[3:] + dq[3:]])

    for cam in (CAM, PinholeK(K)):
        xy = cam.project(pose.transform(X)) + rng.normal(0, 1, (15, 2))
        _fd_check(lambda q, cam=cam, xy=xy: collinearity_residuals(q, cam, X, xy), p, update, np.full(6, 1e-6))
    pk = PinholeK(K)
    xy0, jp0, jk0 = pk.project_jacobian(pose.transform(X))
    xy1, jp1, none = pk.project_jacobian(pose.transform(X), params=False)
    assert none is None and jk0.shape == (15, 2, 4)
    assert np.abs(jp1 - jp0).max() <= 1e-12 * np.abs(jp0).max()
    assert np.abs(pk.project_point_jacobian(pose.transform(X))[1] - jp0).max() <= 1e-12 * np.abs(jp0).max()
