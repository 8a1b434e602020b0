"""Helmert similarity and planes (seed 000 eq. 5–6): exact answers, precision, degeneracies."""

import numpy as np
import pytest

from thermogrammetry.errors import DegenerateInputError, ShapeError, TooFewPointsError
from thermogrammetry.geometry import (
    Plane,
    Pose,
    Similarity,
    angle_to_camera_axis,
    distance_along_axis,
    distance_along_rays,
    helmert,
    plane_from_3_points,
    plane_from_points,
    ray_angles,
)
from thermogrammetry.geometry import rotations as rot
from thermogrammetry.results import Termination

R_TRUE = rot.matrix_from_axis_angle([0.4, -1.1, 2.0])
T_TRUE = np.array([512000.0, 5400000.0, 230.0])  # a UTM-like target frame
S_TRUE = 1.37


def test_helmert_exact_inverse_compose(rng):
    X = rng.uniform(-20, 20, (8, 3))
    Y = S_TRUE * X @ R_TRUE.T + T_TRUE
    h = helmert(X, Y)
    assert h.termination is Termination.CONVERGED
    t = h.transform
    # target coordinates ≈ 5e6 m carry ≈ 1e-9 m rounding; over a 40 m extent that is ≈ 3e-11 (rad, relative)
    assert abs(t.scale - S_TRUE) < 1e-10 and np.abs(t.R - R_TRUE).max() < 1e-10
    # translations ~5.4e6 m: one ulp is 9.3e-10 m, so the bound is a few ulps (measured 5e-12 m: the large
    # components came out exact)
    assert np.abs(t.translation - T_TRUE).max() < 5e-9
    assert np.abs(h.apply(X) - Y).max() < 1e-8
    assert np.abs(h.inverse().apply(Y) - X).max() < 1e-8
    other = Similarity(0.5, rot.matrix_from_axis_angle([0.1, 0.2, 0.3]), [1.0, 2.0, 3.0])
    assert np.abs(t.compose(other).apply(X) - t.apply(other.apply(X))).max() < 1e-8
    rigid = helmert(X, X @ R_TRUE.T + T_TRUE, fix_scale=True)
    assert rigid.transform.scale == 1.0 and rigid.covariance[6, 6] == 0.0


def test_helmert_monte_carlo_precision():
    rng = np.random.default_rng(11)
    X = rng.uniform(-50, 50, (6, 3))
    Y = S_TRUE * X @ R_TRUE.T + T_TRUE
    sig = 0.02
    est, rep = [], []
    for _ in range(250):
        h = helmert(X, Y + rng.normal(0, sig, Y.shape), sigma_m=sig)
        dR = rot.axis_angle_from_matrix(h.transform.R @ R_TRUE.T)  # small rotation about target axes
        est.append(np.concatenate([dR, h.transform.translation, [h.transform.scale]]))
        rep.append(h.std_prior)
    ratio = np.std(est, axis=0, ddof=1) / np.mean(rep, axis=0)
    # 250 runs: ≈ 4.5 % sampling error of a std; ±20 % > 4σ
    assert np.all(np.abs(ratio - 1) < 0.2), ratio
    print("Helmert MC/reported σ (rx ry rz tx ty tz s):", np.round(ratio, 3))


def test_helmert_degenerate_and_bad_input(rng):
    line = np.outer(np.linspace(-1, 1, 5), [1.0, 2.0, 0.5])
    h = helmert(line, line * 2 + 1)
    assert h.termination is Termination.RANK_DEFICIENT and "undetermined" in h.outcome.reason
    with pytest.raises(TooFewPointsError, match="at least 3 points, got 2"):
        helmert(line[:2], line[:2])
    with pytest.raises(ShapeError, match="source has shape"):
        helmert(line, line[:4])


def test_plane_from_3_points_and_eq5_eq6():
    p = plane_from_3_points([0, 0, 1], [1, 0, 1], [0, 1, 1], name="plane 'lid'")
    assert np.allclose(p.normal, [0, 0, 1]) and abs(p.d + 1) < 1e-15
    with pytest.raises(DegenerateInputError, match=r"plane 'wall'.*collinear"):
        plane_from_3_points([0, 0, 0], [1, 1, 1], [2, 2, 2], name="plane 'wall'")
    # a plane tilted 30° about X, camera looking straight down (ω = φ = κ = 0): η = 30°
    tilt = np.radians(30)
    plane = Plane.from_abcd(0.0, -np.sin(tilt), np.cos(tilt), -2.0)
    pose = Pose.from_opk(0.0, 0.0, 0.0, [0.0, 0.0, 10.0])
    eta, _ = angle_to_camera_axis(plane, pose)
    assert abs(np.degrees(eta) - 30) < 5e-13  # measured 7.1e-15 deg
    # eq. 6 written literally: cos η = [A B C] m⁻¹ [0 0 1]ᵀ / ‖[A B C]‖ with m = M (photo_from_world)
    o, f, k = 0.2, -0.3, 0.7
    pose = Pose.from_opk(o, f, k, [1.0, 2.0, 10.0])
    ABC = np.array([0.3, -0.5, 2.0])
    m = rot.matrix_from_opk(o, f, k)
    cos_eta = ABC @ np.linalg.inv(m) @ [0, 0, 1] / np.linalg.norm(ABC)
    eta, _ = angle_to_camera_axis(Plane.from_abcd(*ABC, 4.0), pose)
    assert abs(eta - np.arccos(abs(cos_eta))) < 2e-14  # measured 2.2e-16 rad
    # distances: nadir camera 10 m above the plane z = 1 → 9 m; rays to points on the plane
    pose = Pose.from_opk(0.0, 0.0, 0.0, [0.0, 0.0, 10.0])
    flat = Plane.from_abcd(0, 0, 2.0, -2.0)
    assert abs(distance_along_axis(flat, pose) - 9.0) < 1e-13  # measured 0 (ulp of 9 m: 1.8e-15)
    pts = np.array([[3.0, 4.0, 1.0], [-1.0, 2.0, 1.0]])
    dist, hit = distance_along_rays(flat, pose, points_world=pts)
    assert np.allclose(dist, np.linalg.norm(pts - pose.center, axis=1)) and np.allclose(hit, pts)
    ang = ray_angles(flat, pose, points_world=pts)
    assert np.allclose(np.cos(ang), 9.0 / dist)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    d_px, _ = distance_along_rays(flat, pose, camera=K, xy_px=[[320.0, 240.0]])
    assert abs(d_px[0] - 9.0) < 1e-13  # measured 0
    side = Pose.look_at([0, 0, 10], [10, 0, 10])
    assert distance_along_axis(flat, side) == np.inf


def test_plane_from_points_precision_and_angle_std():
    rng = np.random.default_rng(3)
    n_true = np.array([0.3, -0.2, 1.0])
    n_true /= np.linalg.norm(n_true)
    u = np.cross(n_true, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n_true, u)
    ab = rng.uniform(-1, 1, (20, 2))
    base = 2.0 * n_true + ab[:, :1] * u + ab[:, 1:] * v  # plane n·X = 2
    pose = Pose.look_at([1.0, -2.0, 8.0], 2.0 * n_true)
    sig = 0.002
    normals, stds, etas, eta_std = [], [], [], []
    for _ in range(250):
        p = plane_from_points(base + rng.normal(0, sig, 20)[:, None] * n_true, sigma_m=sig)
        assert p.outcome.termination is Termination.CONVERGED
        normals.append(p.normal * np.sign(p.normal @ n_true))
        stds.append(np.sqrt(np.diag(p.covariance_prior)[:3]))
        e, s = angle_to_camera_axis(p, pose, prior=True)
        etas.append(e)
        eta_std.append(s)
    ratio = np.std(normals, axis=0, ddof=1) / np.mean(stds, axis=0)
    assert np.all(np.abs(ratio - 1) < 0.2), ratio
    r_eta = np.std(etas, ddof=1) / np.mean(eta_std)
    assert abs(r_eta - 1) < 0.2, r_eta
    assert abs(np.mean(normals, axis=0) @ n_true - 1) < 1e-4
    print("plane normal MC/reported σ:", np.round(ratio, 3), " η:", round(r_eta, 3))
    with pytest.raises(DegenerateInputError, match="roof.*collinear"):
        plane_from_points(np.outer(np.arange(5.0), [1, 1, 0]), name="roof")
    with pytest.raises(TooFewPointsError, match="got 2"):
        plane_from_points(np.zeros((2, 3)))


def test_non_finite_and_shapes_are_named():
    from thermogrammetry.errors import NonFiniteError

    X = np.eye(3) * 2.0
    with pytest.raises(NonFiniteError, match="target"):
        helmert(X, X + [[np.nan, 0, 0], [0, 0, 0], [0, 0, 0]])
    with pytest.raises(ShapeError, match=r"source: expected shape \(N, 3\)"):
        helmert(X[:, :2], X)
    with pytest.raises(NonFiniteError, match="p2"):
        plane_from_3_points([0, 0, 0], [1, np.inf, 0], [0, 1, 0])
    with pytest.raises(NonFiniteError, match="points"):
        plane_from_points([[0, 0, 0], [1, 0, 0], [0, 1, 0], [np.nan, 1, 1]])
