"""R*, t of an RGB + thermal rig by image registration (sfm.rigreg), on the synthetic rig block of rig_block.py.

The block: 12 RGB frames of the UAV terrain scene (8-bit, the same fine texture as the thermal field, ±25 %,
Lambert shading, 2 DN noise) and 12 thermal frames (float kelvin, NETD 0.05 K, FPN, PSF) taken through a known
rig: rotation (0.5, -0.4, 0.3) deg, base (0.10, 0.02, -0.01) m. The RGB poses and the depth points are the TRUTH
here (this tests the registration alone; the survey supplies them from its own orientation). The block is flown
at one height, so t cannot be separated from R (parallax 0.1 m at ~50 m): t is given (the truth) and held, which
the result reports (``t_determined`` False).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from rig_block import write_rig_block  # noqa: E402


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    return write_rig_block(tmp_path_factory.mktemp("rigreg"), n_frames=12)


def _samples(block, *, thermal_override=None, focal_error=1.0):
    import cv2

    import tifffile

    from thermogrammetry.sfm.rigreg import pair_samples
    from thermogrammetry.synthetic.survey import tie_points

    scene = block["scene"]
    pts, _ = tie_points(scene, 3000, seed=1, min_views=1)
    P = np.array(list(pts.values()))
    tcam = block["thermal_camera"]
    tcam0 = tcam.replace(fx=tcam.K[0, 0] * focal_error, fy=tcam.K[1, 1] * focal_error)
    rcam = block["rgb_camera"]
    out = []
    for k, (name, pose) in enumerate(sorted(block["rgb_poses"].items())):
        rgb = cv2.imread(str(block["root"] / "rgb" / f"{name}.png"))
        th = tifffile.imread(block["root"] / "thermal" / f"{k:04d}_ir.tif")
        if thermal_override is not None:
            th = thermal_override(th, k)
        Xc = P @ pose.R.T + pose.t
        uv = rcam.project(Xc)
        w, h = rcam.image_size
        vis = (Xc[:, 2] > 0) & (uv[:, 0] > 0) & (uv[:, 0] < w - 1) & (uv[:, 1] > 0) & (uv[:, 1] < h - 1)
        s, why = pair_samples(name, rgb, th, rcam, tcam0, Xc[vis])
        assert s is not None, why
        out.append(s)
    return out, tcam0


def test_rotation_and_focal_scale_recovered(block):
    """Start: identity rotation (0.74 deg from the truth) and a thermal focal length 2 % short.
    Measured: rotation error 0.047 deg (seed 0; mostly about the optical axis, 2.1 σ) and 0.022 deg (seed 1),
    focal scale 0.09 % / 0.04 % from the truth, spread 0.10 / 0.07 deg; with t started at 0 instead of the truth
    the rotation absorbs the parallax of the 0.1 m base: 0.12 / 0.11 deg. Bounds: 0.1 deg (at most 0.7 px at the
    thermal image's border, half the finest 1.5 px blur), each axis within 4 σ, focal scale 0.3 % (0.5 px at the
    corner), spread below 0.2 deg."""
    from thermogrammetry.geometry.rotations import axis_angle_from_matrix
    from thermogrammetry.sfm.rigreg import register_rig

    pairs, tcam0 = _samples(block, focal_error=0.98)
    truth = block["rig"]
    r = register_rig(pairs, tcam0, t0=truth.t)
    assert r.success, r.reason
    assert r.t_determined is False  # one flying height: t held at its start
    np.testing.assert_allclose(r.t, truth.t, atol=1e-12)
    err = np.degrees(np.linalg.norm(axis_angle_from_matrix(r.R @ truth.R.T)))
    assert err < 0.1, err
    dr = np.degrees(axis_angle_from_matrix(r.R @ truth.R.T))
    assert np.all(np.abs(dr) <= 4 * r.rotation_std_deg), (dr, r.rotation_std_deg)
    assert abs(r.focal_scale * 0.98 - 1.0) < 0.003, r.focal_scale
    assert len(r.pairs_used) == 12
    assert 0.0 < r.spread_deg < 0.2, r.spread_deg
    assert np.all((r.rotation_std_deg > 1e-4) & (r.rotation_std_deg < 0.05)), r.rotation_std_deg
    # t held: no σ for it and no jackknife run (the focal scale's σ is not computed either)
    assert np.all(np.isnan(r.translation_std)) and np.isnan(r.focal_scale_std)
    assert r.summary()["translation_std"] == [None, None, None] and r.summary()["focal_scale_std"] is None


def test_no_structure_in_common_is_refused_with_the_reason(block):
    """Thermal frames of pure noise: nothing agrees with the RGB edges, the estimate is a refusal, not a guess."""
    from thermogrammetry.sfm.rigreg import register_rig

    def noise(th, k):
        return np.random.default_rng(k).normal(300.0, 1.0, th.shape).astype(np.float32)

    pairs, tcam0 = _samples(block, thermal_override=noise)
    r = register_rig(pairs, tcam0, t0=block["rig"].t)
    assert not r.success
    assert "pair" in r.reason or "grid" in r.reason, r.reason


def test_too_few_pairs_and_bad_options():
    from thermogrammetry.camera import Camera
    from thermogrammetry.errors import ConfigError
    from thermogrammetry.sfm.rigreg import RigRegistrationOptions, pair_samples, register_rig

    cam = Camera("pinhole", (64, 48), dict(fx=60.0, fy=60.0, cx=31.5, cy=23.5))
    r = register_rig([], cam)
    assert not r.success and "usable" in r.reason
    s, why = pair_samples("a", np.zeros((48, 64)), np.zeros((48, 64)), cam, cam, np.array([[0, 0, 1.0]] * 3))
    assert s is None and "a:" in why and "3 oriented point" in why
    with pytest.raises(ConfigError, match="blur_px"):
        RigRegistrationOptions(blur_px=(0.0,))
    with pytest.raises(ConfigError, match="max_pairs"):
        RigRegistrationOptions(max_pairs=2, min_pairs=3)
    with pytest.raises(ConfigError, match="max_spread_deg"):
        RigRegistrationOptions(max_spread_deg=-1)


@pytest.fixture(scope="module")
def depth_pairs():
    """The rig block's 12 poses brought down to 5-50 m above the ground (heights 12 / 20 / 35 / 50 m in turn), frames
    rendered in memory: pairs at different depths, so that t across the optical axis is separable from R."""
    from dataclasses import replace

    import rig_block

    from thermogrammetry.geometry import Pose
    from thermogrammetry.sfm.rigreg import RigRegistrationOptions, pair_samples
    from thermogrammetry.synthetic.survey import make_survey, render_frame, render_rgb_frame, tie_points
    from thermogrammetry.synthetic.survey_files import uav_thermal_config
    from thermogrammetry.synthetic.terrain import TerrainConfig

    cfg = uav_thermal_config(seed=0, terrain=TerrainConfig(width_m=80.0, height_m=64.0, n_buildings=3, n_trees=6, n_roads=1),
                             n_gcp=4, n_check=0, max_frames=12)
    scene = make_survey(cfg)
    frames = []
    for k, f in enumerate(scene.frames):
        C = f.pose.center.copy()
        C[2] -= cfg.flight_height_m - (12.0, 20.0, 35.0, 50.0)[k % 4]
        frames.append(replace(f, pose=Pose(f.pose.R, -f.pose.R @ C)))
    scene = replace(scene, frames=frames)
    rig = rig_block.truth_rig()
    th_scene = replace(scene, frames=[replace(f, pose=rig.compose(f.pose)) for f in frames])
    rcam, tcam = rig_block.rgb_camera(), scene.camera
    opt = RigRegistrationOptions(samples_per_pair=8000)
    pts, _ = tie_points(scene, 3000, seed=1, min_views=1)
    P = np.array(list(pts.values()))
    pairs = []
    for k, f in enumerate(frames):
        Xc = P @ f.pose.R.T + f.pose.t
        uv = rcam.project(Xc)
        w, h = rcam.image_size
        vis = (Xc[:, 2] > 0) & (uv[:, 0] > 0) & (uv[:, 0] < w - 1) & (uv[:, 1] > 0) & (uv[:, 1] < h - 1)
        s, why = pair_samples(f"{k:04d}", render_rgb_frame(scene, f.pose, rcam, seed=k),
                              render_frame(th_scene, k)["image_k"], rcam, tcam, Xc[vis], options=opt)
        assert s is not None, why
        pairs.append(s)
    return pairs, tcam, rig, opt


def test_translation_across_the_axis_with_its_jackknife_sigma(depth_pairs):
    """Pairs 6-51 m deep: t is determined across the optical axis (along it held at the start, 0 here; the truth's
    9 mm there is the focal scale's to trade). Measured (seed 0, 8000 samples a pair): t − truth 3.4 / 1.0 mm with
    jackknife σ 11.4 / 2.2 mm, rotation 0.022 deg from the truth, focal scale 0.9990 ± 0.0004; other seeds of the
    same set-up: 19 / 2.7 mm against σ 19 / 2.5 mm (seed 3) and, the weak case, 104 / 1.9 mm against 34 / 16 mm
    (seed 1, a wrong basin: see the module docstring). Bounds: each axis within 3 σ and 1 cm, σ between 0.3 mm and
    2 cm (not a σ that nothing can fail), rotation 0.05 deg, focal scale 0.3 % as in the one-depth test."""
    from thermogrammetry.geometry.rotations import axis_angle_from_matrix
    from thermogrammetry.sfm.rigreg import register_rig

    pairs, tcam, truth, opt = depth_pairs
    r = register_rig(pairs, tcam, options=opt)
    assert r.success, r.reason
    assert r.t_determined is True
    err = r.t - truth.t
    sd = r.translation_std
    assert np.isnan(sd[2]) and r.t[2] == 0.0  # along the axis: held at the start
    assert np.all(np.abs(err[:2]) <= 3 * sd[:2]) and np.all(np.abs(err[:2]) < 0.01), (err, sd)
    assert np.all((sd[:2] > 3e-4) & (sd[:2] < 0.02)), sd
    assert np.degrees(np.linalg.norm(axis_angle_from_matrix(r.R @ truth.R.T))) < 0.05
    assert abs(r.focal_scale - 1.0) < 0.003 and 0 < r.focal_scale_std < 0.002, (r.focal_scale, r.focal_scale_std)
    s = r.summary()
    assert s["translation_std"][2] is None and s["translation_std"][0] == pytest.approx(sd[0])



def test_registered_rig_sigma_reaches_the_thermal_centres():
    """A fixed registered rig: the thermal view's centre σ carries the registration's σ of t (C_s = C_m − R_sᵀ t, so
    with an exactly known master pose Cov(C_s) = R_sᵀ diag(σ_t²) R_s) and its rotation σ the registration's σ of R."""
    from types import SimpleNamespace

    from thermogrammetry.geometry.rotations import matrix_from_axis_angle
    from thermogrammetry.sfm.rig import RigViews, slave_std

    Rm = matrix_from_axis_angle(np.deg2rad([178.0, 3.0, 40.0]))  # a nadir-looking RGB camera
    Cm = np.array([2600010.0, 1200020.0, 450.0])
    Rr = matrix_from_axis_angle(np.deg2rad([0.5, -0.4, 0.3]))
    tr = np.array([-0.10, -0.02, 0.0])
    rec = SimpleNamespace(R=np.array([Rm, Rr @ Rm]), t=np.array([-Rm @ Cm, Rr @ (-Rm @ Cm) + tr]))
    names = [f"image0.{a}" for a in ("wx", "wy", "wz", "X0", "Y0", "Z0")]
    fa = SimpleNamespace(param_names=names, covariance=np.eye(6) * 1e-16)
    sd_t = np.array([0.012, 0.003, np.nan])  # along the axis held: not known, modelled as 0
    sd_r = np.deg2rad([0.03, 0.02, 0.05])
    c_sd, _ = slave_std(RigViews({1: 0}, Rr, tr, fixed=True, prior_translation_std=sd_t), rec, fa, 1)
    Rs = Rr @ Rm
    expect = np.sqrt(np.diag(Rs.T @ np.diag(np.nan_to_num(sd_t) ** 2) @ Rs))
    np.testing.assert_allclose(c_sd, expect, rtol=1e-6, atol=1e-9)
    # with the rotation σ as well: the rotation's share of the centre is |t| σ_R (5e-5 m here)
    c_sd2, r_sd = slave_std(RigViews({1: 0}, Rr, tr, fixed=True, prior_rotation_std=sd_r, prior_translation_std=sd_t),
                            rec, fa, 1)
    np.testing.assert_allclose(r_sd, np.degrees(sd_r), rtol=1e-3)
    assert np.all(np.abs(np.sqrt(np.abs(c_sd2 ** 2 - c_sd ** 2))) < np.linalg.norm(tr) * sd_r.max() * 1.01)
    # without the translation σ: the master's (~1e-8 m here) and the rotation's share only
    c0, _ = slave_std(RigViews({1: 0}, Rr, tr, fixed=True, prior_rotation_std=sd_r), rec, fa, 1)
    assert np.all(c0 < np.linalg.norm(tr) * sd_r.max() * 1.01), c0
