"""n-view triangulation: exact, Monte-Carlo precision, degenerate rays, bad input."""

import numpy as np
import pytest

from thermogrammetry import Camera
from thermogrammetry.errors import NonFiniteError, ShapeError
from thermogrammetry.geometry import Pose, project_points, triangulate, triangulate_linear
from thermogrammetry.results import Termination

CAM = Camera("opencv", (640, 480), dict(fx=600, fy=600, cx=320, cy=240, k1=-0.2, k2=0.05, p1=1e-3, p2=-5e-4))
POSES = [Pose.look_at(c, [0.0, 0.0, 0.0]) for c in ([-2.0, -8.0, 1.0], [2.0, -8.0, 1.5], [0.0, -7.0, 3.0])]


def _obs(X, poses=POSES, cam=CAM):
    return np.stack([project_points(cam, p, X) for p in poses])


def test_exact_with_distortion(rng):
    X = rng.uniform(-1, 1, (200, 3))
    r = triangulate(CAM, POSES, _obs(X))
    assert r.outcome.termination is Termination.CONVERGED
    assert np.abs(r.points - X).max() < 2e-13  # measured 2.6e-15 m
    assert np.all(r.n_views == 3) and not r.behind.any() and not r.parallel.any()
    # the linear step alone ignores nothing (rays are undistorted first): also exact
    Xl, w = triangulate_linear(CAM, POSES, _obs(X))
    assert np.abs(Xl - X).max() < 5e-13  # measured 1.0e-14 m


def test_monte_carlo_scatter_matches_reported_std():
    rng = np.random.default_rng(99)
    X = rng.uniform(-1, 1, (30, 3))
    runs, sig = 400, 0.5
    Xr = np.tile(X, (runs, 1))
    xy = _obs(Xr) + rng.normal(0, sig, (3, Xr.shape[0], 2))
    r = triangulate(CAM, POSES, xy, sigma_px=sig)
    assert r.outcome.termination is Termination.CONVERGED
    pts = r.points.reshape(runs, 30, 3)
    sd_mc = pts.std(axis=0, ddof=1)
    sd_rep = r.std.reshape(runs, 30, 3).mean(axis=0)
    ratio = sd_mc / sd_rep
    # 400 runs: sampling error of each std ≈ 1/√798 = 3.5 %; ±20 % per point and axis is > 5σ
    assert np.all(np.abs(ratio - 1) < 0.2), (ratio.min(), ratio.max())
    assert abs(ratio.mean() - 1) < 0.03  # pooled over 90 point-axes: ≈ 0.4 % sampling error
    # a-posteriori σ0² averages 1 (redundancy 3 per point)
    assert abs(np.mean(r.sigma0**2) - 1) < 0.05
    print(f"triangulation MC/reported σ: min {ratio.min():.3f} max {ratio.max():.3f} mean {ratio.mean():.4f}")


def test_mask_and_too_few_views(rng):
    X = rng.uniform(-1, 1, (5, 3))
    xy = _obs(X)
    mask = np.ones((3, 5), bool)
    mask[0, 1] = False
    mask[:2, 2] = False  # only one view
    xy[0, 1] = np.nan  # ignored where masked
    xy[:2, 2] = np.nan
    r = triangulate(CAM, POSES, xy, mask=mask)
    assert r.termination[2] is Termination.TOO_FEW_OBSERVATIONS and np.all(np.isnan(r.points[2]))
    ok = [0, 1, 3, 4]
    assert np.abs(r.points[ok] - X[ok]).max() < 5e-14  # measured 7.2e-16 m
    assert r.n_views.tolist() == [3, 2, 1, 3, 3]
    assert np.all(np.isnan(r.residuals_px[0, 1]))


def test_degenerate_rays_are_flagged():
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    # parallel: both cameras at the same centre (pure rotation) → no intersection
    p1 = Pose.look_at([0, -5, 0], [0, 0, 0])
    p2 = Pose.look_at([0, -5, 0], [0.3, 0, 0.2])
    X = np.array([[0.1, 0.0, 0.0], [0.0, 0.0, 0.2]])
    r = triangulate(K, [p1, p2], _obs(X, [p1, p2], K))
    assert r.parallel.all() and all(t is Termination.DEGENERATE for t in r.termination)
    assert "parallel" in r.outcome.reason
    # behind: a point behind both cameras projects mathematically but is flagged
    q1 = Pose.look_at([-1, -5, 0], [-1, 0, 0])
    q2 = Pose.look_at([1, -5, 0], [1, 0, 0])
    Xb = np.array([[0.0, -12.0, 0.3], [0.0, 1.0, 0.3]])
    xyb = np.stack([(q.transform(Xb) @ K.T)[:, :2] / (q.transform(Xb) @ K.T)[:, 2:] for q in (q1, q2)])
    r = triangulate(K, [q1, q2], xyb)
    assert r.behind.tolist() == [True, False]
    assert r.termination[0] is Termination.DEGENERATE and r.termination[1] is Termination.CONVERGED
    assert "behind" in r.outcome.reason


def test_bad_input():
    X = np.zeros((4, 3)) + [0, 0, 0.1]
    xy = _obs(X)
    bad = xy.copy()
    bad[1, 2, 0] = np.inf
    with pytest.raises(NonFiniteError, match="xy_px"):
        triangulate(CAM, POSES, bad)
    with pytest.raises(ShapeError, match=r"xy_px: expected shape \(3, N, 2\)"):
        triangulate(CAM, POSES, xy[:2])
    with pytest.raises(ShapeError, match="at least 2 poses"):
        triangulate(CAM, POSES[:1], xy[:1])
    with pytest.raises(ShapeError, match="cameras: 2 cameras for 3 poses"):
        triangulate([CAM, CAM], POSES, xy)
    with pytest.raises(ShapeError, match="mask"):
        triangulate(CAM, POSES, xy, mask=np.ones((3, 3), bool))


def test_linear_only_and_nested_list_K(rng):
    K = [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]  # one shared K as nested lists
    X = rng.uniform(-1, 1, (10, 3))
    xy = _obs(X, POSES, np.array(K))
    noisy = xy + rng.normal(0, 0.5, xy.shape)
    lin = triangulate(K, POSES, noisy, refine=False, sigma_px=0.5)
    ref = triangulate(K, POSES, noisy, sigma_px=0.5)
    assert np.abs(lin.points - X).max() < 0.05 and np.all(np.isfinite(lin.std))
    # the least-squares refinement lowers the image residuals (it minimises them)
    assert np.nansum(ref.residuals_px**2) < np.nansum(lin.residuals_px**2)
    # linearised precision at the two estimates agrees to first order
    assert np.allclose(lin.std, ref.std, rtol=0.01)


def test_per_observation_sigma(rng):
    # σ per view: the view with 10× larger σ has 100× less weight; precision follows the weights
    X = rng.uniform(-1, 1, (4, 3))
    xy = _obs(X)
    sig = np.ones((3, 4))
    sig[2] = 10.0
    r = triangulate(CAM, POSES, xy, sigma_px=sig)
    r2 = triangulate(CAM, POSES[:2], xy[:2])
    assert np.all(r.std < r2.std) and np.all(r.std > 0.95 * r2.std)  # third view adds only a little
    with pytest.raises(ShapeError, match="sigma_px"):
        triangulate(CAM, POSES, xy, sigma_px=np.ones(4))
