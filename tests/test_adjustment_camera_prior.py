"""Weighted priors on intrinsics in the adjustment engine (``BundleProblem.add_camera_prior``): a lens's nominal focal
length with its σ combines with what the block determines as two independent measurements would."""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry import Camera
from thermogrammetry.adjustment import BundleProblem, solve
from thermogrammetry.adjustment._so3 import rotation_matrices
from thermogrammetry.errors import InvalidInputError
from thermogrammetry.geometry import Pose
from thermogrammetry.results import Termination

F_TRUE = 600.0


def _block(seed=5, sig_px=0.5):
    """Two nadir strips of 6 views, 2.6 and 3.4 m above a field with 1.2 m of relief, GNSS 5 mm: fx, fy free. (Views
    at one height leave f and the depths an exact twin, whatever the relief: f -> s f, Z -> s Z keeps every image
    point; the two heights break it.)"""
    rng = np.random.default_rng(seed)
    cam = Camera("opencv", (640, 480), dict(fx=F_TRUE, fy=F_TRUE, cx=319.5, cy=239.5))
    g = np.stack(np.meshgrid(np.linspace(-1.2, 1.2, 13), np.linspace(-1.0, 1.0, 11)), -1).reshape(-1, 2)
    X = np.c_[g, 1.2 * np.sin(2 * g[:, 0]) * np.cos(2 * g[:, 1])]
    centres = [(x, y, z) for y, z in ((-0.3, 2.6), (0.3, 3.4)) for x in np.linspace(-0.6, 0.6, 6)]
    poses = [Pose.look_at(c, (c[0], c[1], 0.0), up=(0, 1, 0)) for c in centres]
    pb = BundleProblem()
    ic = pb.add_camera(cam.with_params(cam.params * np.r_[1.03, 1.03, 1, 1, np.ones(len(cam.params) - 4)]
                                       if len(cam.params) > 4 else cam.params * np.r_[1.03, 1.03, 1, 1]))
    pb.set_camera_fixed(ic, [n for n in cam.param_names if n not in ("fx", "fy")])
    pts = pb.add_points(X + rng.normal(0, 0.02, X.shape))
    views = []
    for p in poses:
        v = pb.add_pose(Pose.from_center(rotation_matrices(rng.normal(0, 0.005, 3)) @ p.R, p.center + rng.normal(0, 0.02, 3)))
        xy = cam.project(p.transform(X))
        pb.add_image_points(ic, v, pts, xy + rng.normal(0, sig_px, xy.shape), sigma_px=sig_px)
        views.append(v)
    pb.add_gnss(views, np.array([p.center for p in poses]) + rng.normal(0, 0.005, (len(poses), 3)), 0.005)
    return pb, ic


def _fx(res, pb, ic):
    k = list(pb.cameras[ic].param_names).index("fx")
    return float(res.cameras[ic].params[k]), float(res.camera_std[ic][k])


def _fxfy_cofactor(res):
    # the (fx, fy) block of the a posteriori covariance over σ0²: the cofactor matrix (a priori weights)
    k = [res.param_names.index(f"camera0.{n}") for n in ("fx", "fy")]
    return res.covariance[np.ix_(k, k)] / res.sigma0**2


def test_a_prior_combines_with_the_block_as_an_independent_measurement():
    pb, ic = _block()
    res = solve(pb)
    assert res.termination is Termination.CONVERGED, res.reason
    f_d, s_d = _fx(res, pb, ic)
    assert 1.0 < s_d < 200.0, s_d  # the block alone determines fx only weakly (measured 67 px), fy with it (ρ ~ 1)
    Qd = _fxfy_cofactor(res)
    # a prior on fx and fy, as uncertain as the block and more or less: in the linearised system the posterior
    # cofactor of (fx, fy) is (Qd^-1 + Qp^-1)^-1 exactly; the two solutions' linearisation points differ by some px
    # of focal length (measured within 1 %: 3 % asserted)
    for ratio in (0.5, 1.0, 3.0):
        s_p = ratio * s_d
        pb2, ic2 = _block()
        pb2.add_camera_prior(ic2, {"fx": F_TRUE + 2.0, "fy": F_TRUE + 2.0}, {"fx": s_p, "fy": s_p})
        res2 = solve(pb2)
        assert res2.termination is Termination.CONVERGED, res2.reason
        expect = np.linalg.inv(np.linalg.inv(Qd) + np.eye(2) / s_p**2)
        got = _fxfy_cofactor(res2)
        assert np.sqrt(got[0, 0]) == pytest.approx(np.sqrt(expect[0, 0]), rel=0.03), (ratio, got, expect)
        assert np.sqrt(got[1, 1]) == pytest.approx(np.sqrt(expect[1, 1]), rel=0.03), (ratio, got, expect)
        # the estimate lies between the block's and the prior's (weighted: nearer the prior the tighter it is)
        f2 = _fx(res2, pb2, ic2)[0]
        lo, hi = sorted((f_d, F_TRUE + 2.0))
        assert lo - 0.1 * s_d < f2 < hi + 0.1 * s_d, (ratio, f_d, f2)


def test_a_tight_prior_holds_the_value_and_bad_priors_are_refused():
    pb, ic = _block()
    pb.add_camera_prior(ic, {"fx": 605.0, "fy": 605.0}, {"fx": 1e-3, "fy": 1e-3})
    res = solve(pb)
    f, s = _fx(res, pb, ic)
    assert abs(f - 605.0) < 0.01 and s < 1.1e-3
    with pytest.raises(InvalidInputError, match="not parameters of camera 0"):
        pb.add_camera_prior(ic, {"focal": 600.0}, {"focal": 5.0})
    with pytest.raises(InvalidInputError, match="sigmas > 0"):
        pb.add_camera_prior(ic, {"fx": 600.0}, {"fx": 0.0})
    with pytest.raises(InvalidInputError, match="the same parameter names"):
        pb.add_camera_prior(ic, {"fx": 600.0}, {"fy": 5.0})
