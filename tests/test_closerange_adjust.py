"""Joint adjustment of the close-range network (optional step), on the seed 000 replica."""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry.closerange.adjust import adjust_network
from thermogrammetry.closerange.solve import Observations, solve_network
from thermogrammetry.closerange.workflow import CloseRangeConfig
from thermogrammetry.errors import ConfigError
from thermogrammetry.synthetic.closerange import make_closerange_scene, measure


def _net(s, rng, sigma=0.5):
    return solve_network(s.control, Observations.from_rows(measure(s, sigma, rng), 0.5), s.thermal)


def test_joint_adjustment_monte_carlo_matches_sigma():
    # 200 runs: relative standard error of an empirical sigma is 5 %, ±20 % is a 4-sigma band
    s = make_closerange_scene()
    rng = np.random.default_rng(99)
    X, sig, C, sC, sig_seq = [], [], [], [], []
    for _ in range(200):
        net = _net(s, rng)
        a = adjust_network(net)
        assert a.cameras["thermal"].outcome.success
        X.append(a.points_world)
        sig.append(a.point_sigmas)
        sig_seq.append(net.point_sigmas)
        c, cc = a.thermal_center()
        C.append(c)
        sC.append(np.sqrt(np.diag(cc)))
    X, sig, C, sC = map(np.array, (X, sig, C, sC))
    r = X.std(axis=0, ddof=1) / sig.mean(axis=0)
    assert 0.8 < r.min() and r.max() < 1.2, r
    rc = C.std(axis=0, ddof=1) / sC.mean(axis=0)
    assert 0.8 < rc.min() and rc.max() < 1.2, rc
    # the pass points' tie observations strengthen the optical cameras: smaller sigma on average
    assert np.mean(sig) < np.mean(sig_seq)


def test_additional_parameters_remove_distortion_error():
    # optical cameras with radial distortion (about 2.4 px at the object's corners), noise-free data:
    # without additional parameters the points are off by the model error; with k1 it is gone
    s = make_closerange_scene(optical_distortion={"k1": -0.3})
    net = _net(s, np.random.default_rng(4), sigma=0.0)
    truth = np.array([s.passpoints[i] for i in net.pass_ids])
    plain = adjust_network(net)
    with_k = adjust_network(net, additional=("k1", "k2", "p1", "p2"))
    e_plain = np.abs(plain.points_world - truth).max()
    e_k = np.abs(with_k.points_world - truth).max()
    assert e_plain > 2e-4  # the unmodelled distortion costs ~0.5 mm
    assert e_k < 0.02 * e_plain
    assert with_k.cameras["opt1"].sigma0_px < 0.01 * plain.cameras["opt1"].sigma0_px
    extra = with_k.cameras["opt1"].extra
    assert set(extra["additional_parameters"]) == {"k1", "k2", "p1", "p2"}
    assert extra["additional_parameters"]["k1"] > 0  # correction form: opposite sign to the forward k1


def test_noise_free_adjustment_is_a_fixed_point():
    s = make_closerange_scene()
    net = _net(s, np.random.default_rng(0), sigma=0.0)
    a = adjust_network(net)
    assert np.abs(a.points_world - net.points_world).max() < 1e-10


def test_config_requires_bundle_for_additional_parameters():
    with pytest.raises(ConfigError, match="bundle"):
        CloseRangeConfig(additional_parameters=("k1",))
    with pytest.raises(ConfigError, match="'k9'"):
        CloseRangeConfig(bundle=True, additional_parameters=("k9",))
    with pytest.raises(ConfigError, match="CloseRangeConfig: unknown key"):
        CloseRangeConfig.from_dict({"ambient": 3})
    assert CloseRangeConfig(bundle=True, additional_parameters=("K1",)).additional_parameters == ("k1",)


@pytest.mark.parametrize("joint", [False, True])
def test_weighted_control_monte_carlo(joint):
    # control coordinates known to 1 mm (perturbed each run) + 0.5 px image noise: the propagated
    # sigma of pass points, thermal centre and control points matches the scatter (200 runs, ±20 %)
    s = make_closerange_scene()
    rng = np.random.default_rng(17 + joint)
    sc = 0.001
    X, sig, C, sC, Xc, sXc = [], [], [], [], [], []
    for _ in range(200):
        ctrl = {k: v + sc * rng.standard_normal(3) for k, v in s.control.items()}
        net = solve_network(ctrl, Observations.from_rows(measure(s, 0.5, rng), 0.5), s.thermal, control_sigma_m=sc)
        if joint:
            net = adjust_network(net)
        X.append(net.points_world)
        sig.append(net.point_sigmas)
        c, cc = net.thermal_center()
        C.append(c)
        sC.append(np.sqrt(np.diag(cc)))
        Xc.append(net.point("8"))
        sXc.append(np.sqrt(np.diag(net.cov(net.point_jacobian("8")))))
    X, sig, C, sC, Xc, sXc = map(np.array, (X, sig, C, sC, Xc, sXc))
    r = X.std(axis=0, ddof=1) / sig.mean(axis=0)
    assert 0.8 < r.min() and r.max() < 1.2, r
    rc = C.std(axis=0, ddof=1) / sC.mean(axis=0)
    assert 0.8 < rc.min() and rc.max() < 1.2, rc
    rx = Xc.std(axis=0, ddof=1) / sXc.mean(axis=0)
    assert 0.8 < rx.min() and rx.max() < 1.2, rx
    if joint:  # the adjusted control point is better than its given 1 mm in at least one axis
        assert sXc.mean(axis=0).min() < 0.95 * sc
    else:
        assert np.allclose(sXc, sc)
