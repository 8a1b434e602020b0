"""Honest precision of degenerate solves (issue 13): zero redundancy gives NaN standard deviations
with the reason, never 0."""

from __future__ import annotations

import numpy as np

from thermogrammetry import Camera
from thermogrammetry.adjustment import BundleProblem, solve
from thermogrammetry.geometry import Pose


def _resection(n_points, rng, free_intrinsics=False):
    """One view of ``n_points`` fixed points: 2 n equations, 6 pose unknowns (+ fx, cx when
    ``free_intrinsics``)."""
    cam = Camera("pinhole", (640, 480), dict(fx=600, fy=600, cx=319.5, cy=239.5))
    X = np.array([[-0.5, -0.4, 0.1], [0.6, -0.3, -0.2], [0.1, 0.5, 0.3], [-0.3, 0.2, -0.1], [0.4, 0.4, 0.0]])[:n_points]
    pose = Pose.look_at([0.2, -0.1, 4.0], [0, 0, 0], up=(0, 1, 0))
    xy = cam.project(pose.transform(X)) + rng.normal(0, 0.3, (n_points, 2))
    pb = BundleProblem()
    ic = pb.add_camera(cam, fixed=["fy", "cy"] if free_intrinsics else True)
    pts = pb.add_points(X, fixed=True)
    v = pb.add_pose(Pose.from_center(pose.R, pose.center + 0.05))
    pb.add_image_points(ic, v, pts, xy, sigma_px=0.3)
    return pb


def test_zero_redundancy_gives_nan_std_with_reason(rng):
    res = solve(_resection(3, rng))  # 6 equations, 6 unknowns
    assert res.redundancy == 0
    assert np.isnan(res.sigma0)
    assert res.std is not None and np.all(np.isnan(res.std))  # never 0
    assert np.all(np.isnan(res.pose_std[0]))
    assert "redundancy 0" in res.precision_reason
    assert "redundancy 0" in res.reason
    assert any("redundancy 0" in w for w in res.warnings)


def test_positive_redundancy_keeps_finite_std(rng):
    res = solve(_resection(5, rng))  # 10 equations, 6 unknowns
    assert res.redundancy == 4
    assert res.precision_reason == ""
    assert np.all(np.isfinite(res.std)) and np.all(res.std > 0)


def test_zero_redundancy_camera_std_is_nan_not_zero(rng):
    res = solve(_resection(4, rng, free_intrinsics=True))  # 8 equations, 6 + 2 unknowns
    assert res.redundancy == 0, res.reason
    cam = res.cameras[0]
    sd = dict(zip(cam.param_names, cam.param_std))
    assert np.isnan(sd["fx"]) and np.isnan(sd["cx"])  # estimated, precision undetermined
    assert sd["fy"] == 0.0 and sd["cy"] == 0.0  # held fixed


def test_lapack_failure_in_the_precision_step_is_a_result(rng, monkeypatch):
    """LAPACK raising inside the precision step (seen as 'LinAlgError: Internal Error' on a weak 8-image block of a
    40-station building ring) ends the solve with NUMERICAL_FAILURE and the reason, not an exception."""
    import scipy.linalg

    from thermogrammetry.results import Termination

    def broken(*a, **k):
        raise np.linalg.LinAlgError("Internal Error.")

    monkeypatch.setattr(scipy.linalg, "eigvalsh", broken)
    res = solve(_resection(5, rng))
    assert res.termination is Termination.NUMERICAL_FAILURE and not res.success
    assert "precision step failed" in res.reason and "Internal Error" in res.reason
