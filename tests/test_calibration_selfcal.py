"""Self-calibration on the synthetic seed-001 test field (FLIR A320, Table 2 distortion, 0.4 px noise).

Tolerances are derived from the injected noise (σ = 0.4 px per image coordinate, iid Gaussian):
- a single calibration: every estimated parameter within 3 of its *reported* σ of the truth
  (P(|z| > 3) = 0.27 % per parameter);
- σx, σy (Table 4) estimated from ~1100 residual pairs: relative sampling error ≈ 1/sqrt(2 r) ≈ 2 %,
  so the ±10 % band asked by the issue is ~5 sampling σ wide;
- Monte-Carlo: the empirical standard deviation of n = 200 runs has relative sampling error
  ≈ 1/sqrt(2(n-1)) = 5 %, so the ±25 % band of the issue is ~5 sampling σ wide.
"""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry.calibration.bundle import PARAM_NAMES, project, rotation_exp
from thermogrammetry.calibration.selfcal import (
    CameraSetup,
    ImageMeasurements,
    SelfCalibrationOptions,
    calibrate,
)
from thermogrammetry.errors import ConfigError, InvalidInputError
from thermogrammetry.synthetic.testfield import make_testfield, resample_noise

NOISE_PX = 0.4
STAGE2 = ["c_mm", "x0_mm", "y0_mm", "K1", "K2", "K3", "P1", "P2"]


def _inputs(tf, xy=None, nominal_c=18.0):
    T = tf.truth
    xy = tf.xy_px if xy is None else xy
    cams = [CameraSetup("FLIR A320", T.image_size, T.pixel_pitch_um, {"c_mm": nominal_c})]
    ims = [ImageMeasurements(n, 0, tf.obs_point[tf.obs_image == f], xy[tf.obs_image == f]) for f, n in enumerate(T.image_names)]
    return cams, ims


@pytest.fixture(scope="module")
def field():
    return make_testfield(np.random.default_rng(2024), noise_px=NOISE_PX)


@pytest.fixture(scope="module")
def staged(field):
    cams, ims = _inputs(field)
    return calibrate(cams, field.truth.points, ims)


def test_testfield_layout(field):
    T = field.truth
    assert T.points.shape == (77, 3)
    depths = np.unique(T.points[:, 1])
    assert depths.size == 3 and np.allclose(np.diff(depths), 0.7)
    assert sorted(set(np.round(T.roll_deg))) == [0, 90, 180, 270]
    assert T.image_size == (320, 240) and T.pixel_pitch_um == 25.0
    # every image sees most of the field
    counts = np.bincount(field.obs_image)
    assert counts.min() >= 50
    # the injected noise is what we asked for (1000+ samples: ±10 %)
    d = field.xy_px - field.xy_true_px
    assert 0.9 * NOISE_PX < d.std() < 1.1 * NOISE_PX


def test_staged_selfcalibration_recovers_table2(staged, field):
    r = staged
    assert r.outcome.success, r.outcome.reason
    cam = r.cameras[0]
    truth = dict(zip(PARAM_NAMES, field.truth.params))
    for name in STAGE2:
        i = PARAM_NAMES.index(name)
        z = (cam.params[i] - truth[name]) / cam.std[i]
        assert abs(z) < 3.0, f"{name}: {cam.params[i]:.6g} vs truth {truth[name]:.6g}, z = {z:.2f}"
    # not estimated: stay exactly at nominal zero and carry no std
    for name in ("K4", "K5", "B1", "B2"):
        i = PARAM_NAMES.index(name)
        assert cam.params[i] == 0.0 and np.isnan(cam.std[i])
    # Table 4: σx, σy equal the injected noise within 10 % (px and µm)
    sx, sy = cam.sigma_xy_px
    assert 0.9 * NOISE_PX < sx < 1.1 * NOISE_PX
    assert 0.9 * NOISE_PX < sy < 1.1 * NOISE_PX
    assert cam.sigma_xy_um[0] == pytest.approx(sx * 25.0, rel=1e-12)
    # with unit a-priori weights σ0 is the image noise in px
    assert 0.9 * NOISE_PX < r.sigma0 < 1.1 * NOISE_PX
    # all 16 images used, none silently dropped
    assert len(r.images_used) == 16 and r.images_rejected == {}
    # stage 1 ran with the nominal 18 mm and was visibly worse than stage 2
    assert r.stage1["c_mm"] == [18.0]
    assert r.stage1["rms_px"] > 1.1 * r.rms_px
    # clean Gaussian data: data snooping at 3.29 flags ~0.1 % of coordinates, not more than ~1 %
    assert len(r.blunders) < 0.01 * field.xy_px.shape[0]


def test_significance_and_correlation_reports(staged):
    cam = staged.cameras[0]
    tests = {t.name: t for t in cam.tests}
    assert set(tests) == {"x0_mm", "y0_mm", "K1", "K2", "K3", "P1", "P2"}
    # K1 of Table 2 is ~9 of its σ away from zero: must be found significant
    assert tests["K1"].significant and tests["K1"].t > tests["K1"].critical
    for t in tests.values():
        assert t.t == pytest.approx(abs(t.value) / t.std)
    # the radial terms of a polynomial are highly correlated: K2-K3 must be flagged
    pairs = {(a, b) for a, b, _ in cam.correlation_warnings}
    assert ("K2", "K3") in pairs
    for _, _, rho in cam.correlation_warnings:
        assert 0.9 < abs(rho) <= 1.0


def test_blunders_are_found(field):
    xy = field.xy_px.copy()
    rng = np.random.default_rng(7)
    bad = rng.choice(xy.shape[0], 8, replace=False)
    xy[bad] += rng.choice([-1, 1], size=(8, 2)) * rng.uniform(4.0, 8.0, size=(8, 2))  # 10-20 σ
    cams, ims = _inputs(field, xy)
    r = calibrate(cams, field.truth.points, ims)
    assert r.outcome.success
    found = {(b["image"], b["point"]) for b in r.blunders}
    planted = {(field.truth.image_names[field.obs_image[i]], int(field.obs_point[i])) for i in bad}
    assert planted <= found
    assert len(found) <= len(planted) + 0.01 * xy.shape[0]
    assert 0.9 * NOISE_PX < r.cameras[0].sigma_xy_px[0] < 1.1 * NOISE_PX


def test_reported_sigma_matches_monte_carlo(field):
    """200 noise realisations of the same geometry, adjusted from the truth (no snooping, so
    every run uses the same observations): the scatter of the estimates equals the reported σ.

    The runs use the dense solver (``solve_dense`` on the dense Jacobian; 2-3x faster here than the
    sparse engine on this small problem);
    ``test_engine_and_dense_solver_agree`` shows that the engine returns the same estimates and σ
    (to 1e-4 σ and 0.1 %), so the check carries over to the default solver."""
    n = 200
    T = field.truth
    rng = np.random.default_rng(99)
    xy_all = resample_noise(field, rng, n)
    opt = SelfCalibrationOptions(snooping=False, solver="dense")
    est, rep, s0 = [], [], []
    idx = [PARAM_NAMES.index(p) for p in STAGE2]
    poses = list(zip(T.R, T.t))
    for k in range(n):
        cams, ims = _inputs(field, xy_all[k])
        r = calibrate(cams, T.points, ims, options=opt, initial={0: T.params.copy()}, initial_poses=poses)
        assert r.outcome.success
        est.append(r.cameras[0].params[idx])
        rep.append(r.cameras[0].std[idx])
        s0.append(r.sigma0)
    est = np.array(est)
    rep = np.array(rep)
    scatter = est.std(axis=0, ddof=1)
    reported = np.sqrt(np.mean(rep**2, axis=0))
    ratio = reported / scatter
    assert np.all((ratio > 0.75) & (ratio < 1.25)), dict(zip(STAGE2, np.round(ratio, 3)))
    # unbiased: the mean is within 4 standard errors of the truth (standard error = scatter/sqrt(n))
    bias_z = (est.mean(axis=0) - T.params[idx]) / (scatter / np.sqrt(n))
    assert np.all(np.abs(bias_z) < 4.0), dict(zip(STAGE2, np.round(bias_z, 2)))
    assert 0.95 * NOISE_PX < np.mean(s0) < 1.05 * NOISE_PX


def test_k45_and_affinity_on_request(field):
    cams, ims = _inputs(field)
    r = calibrate(cams, field.truth.points, ims, options=SelfCalibrationOptions(k45=True, affinity=True))
    assert r.outcome.success
    cam = r.cameras[0]
    for name in ("K4", "K5", "B1", "B2"):
        i = PARAM_NAMES.index(name)
        assert cam.free[i] and np.isfinite(cam.std[i]) and cam.std[i] > 0
        # truth is 0: the estimate must be compatible with it
        assert abs(cam.params[i]) < 3.5 * cam.std[i]
    assert {t.name for t in cam.tests} >= {"K4", "K5", "B1", "B2"}


def test_options_are_validated():
    with pytest.raises(ConfigError, match="SelfCalibrationOptions: unknown key"):
        SelfCalibrationOptions.from_dict({"k45": True, "kk": 1})
    with pytest.raises(ConfigError, match="Q9"):
        SelfCalibrationOptions(fixed=("Q9",))
    with pytest.raises(InvalidInputError, match="pixel_pitch_um"):
        CameraSetup("x", (320, 240), -1.0)


def test_image_with_too_few_points_gets_a_verdict(field):
    cams, ims = _inputs(field)
    ims[3] = ImageMeasurements(ims[3].name, 0, ims[3].point_index[:4], ims[3].xy_px[:4])
    r = calibrate(cams, field.truth.points, ims)
    assert r.outcome.success
    assert "only 4 measured points" in r.images_rejected[ims[3].name]
    assert len(r.images_used) == 15


def _rig_inputs(field):
    """Thermal images of the field plus a second (RGB-like) camera rigidly mounted beside the
    thermal one in the same frames (0.3 px noise); returns cameras, images and the true rig offset."""
    T = field.truth
    rng = np.random.default_rng(5)
    R_rel = rotation_exp(np.array([[0.01, -0.03, 0.02]]))[0]
    t_rel = np.array([-0.08, 0.01, 0.005])  # 8 cm baseline
    p2 = np.zeros(12)
    p2[0], p2[1], p2[2] = 8.0, 0.05, -0.03
    p2[3] = -1e-3
    size2, pitch2 = (1280, 960), 6.0
    ims = []
    for f, n in enumerate(T.image_names):
        m = field.obs_image == f
        ims.append(ImageMeasurements(n, 0, field.obs_point[m], field.xy_px[m], frame=n))
        R2 = R_rel @ T.R[f]
        t2 = R_rel @ T.t[f] + t_rel
        Xc = T.points @ R2.T + t2
        xy, _, _, ok = project(Xc, p2, size2, (pitch2 * 1e-3,) * 2, jacobians=False)
        vis = ok & (xy[:, 0] > 0) & (xy[:, 0] < size2[0] - 1) & (xy[:, 1] > 0) & (xy[:, 1] < size2[1] - 1)
        idx = np.nonzero(vis)[0]
        ims.append(ImageMeasurements(n + "_rgb", 1, idx, xy[idx] + rng.normal(0, 0.3, (idx.size, 2)), frame=n))
    cams = [CameraSetup("thermal", T.image_size, T.pixel_pitch_um, {"c_mm": 18.0}),
            CameraSetup("rgb", size2, pitch2, {"c_mm": 7.5})]
    return cams, ims, R_rel, t_rel


def test_rig_relative_orientation(field):
    """A second (RGB-like) camera rigidly mounted beside the thermal one, same frames."""
    T = field.truth
    cams, ims, R_rel, t_rel = _rig_inputs(field)
    r = calibrate(cams, T.points, ims, rig=True)
    assert r.outcome.success, r.outcome.reason
    assert len(r.relative) == 1
    ro = r.relative[0]
    dt = ro.t - t_rel
    ang = np.linalg.norm(rotation_exp(np.zeros((1, 3)))[0] - ro.R @ R_rel.T)
    # within 4 reported σ per translation component; rotation close at the σ level
    assert np.all(np.abs(dt) < 4 * ro.std[3:]), (dt, ro.std[3:])
    assert ang < 4 * np.linalg.norm(ro.std[:3])
    assert ro.baseline_m == pytest.approx(np.linalg.norm(t_rel), abs=4 * np.linalg.norm(ro.std[3:]))
    c2 = r.cameras[1]
    assert abs(c2.params[0] - 8.0) < 4 * c2.std[0]
    assert not any("rig does not fit" in w for w in r.warnings), r.warnings  # a true rig fits


def test_rig_that_does_not_fit_warns(field):
    """Pairs mislabelled (the second camera's frames shifted by one): the rig constraint cannot hold,
    its residuals are far above the independent-pose ones, and calibrate says so (issue 13)."""
    T = field.truth
    cams, ims, _, _ = _rig_inputs(field)
    frames = [im.frame for im in ims if im.camera == 1]
    shifted = frames[1:] + frames[:1]
    k = 0
    for im in ims:
        if im.camera == 1:
            im.frame = shifted[k]
            k += 1
    r = calibrate(cams, T.points, ims, rig=True, options=SelfCalibrationOptions(snooping=False))
    assert r.outcome.success, r.outcome.reason
    warn = [w for w in r.warnings if "rig does not fit" in w]
    assert warn, (r.warnings, [c.rms_px for c in r.cameras], len(r.relative), r.images_rejected)


def test_engine_and_dense_solver_agree(field):
    """The sparse adjustment engine (Schur route, its own problem translation) and the dense kernel
    ``solve_dense`` on this module's Jacobian give the same estimate and σ."""
    T = field.truth
    cams, ims = _inputs(field)
    kw = dict(initial={0: T.params.copy()}, initial_poses=list(zip(T.R, T.t)))
    a = calibrate(cams, T.points, ims, options=SelfCalibrationOptions(snooping=False, solver="adjustment"), **kw)
    b = calibrate(cams, T.points, ims, options=SelfCalibrationOptions(snooping=False, solver="dense"), **kw)
    assert a.outcome.success and b.outcome.success
    ca, cb = a.cameras[0], b.cameras[0]
    free = ca.free
    # same minimum: differences far below the precision (1e-4 σ), same σ to 0.1 %
    assert np.all(np.abs(ca.params[free] - cb.params[free]) < 1e-4 * ca.std[free])
    assert np.allclose(ca.std[free], cb.std[free], rtol=1e-3)
    assert a.sigma0 == pytest.approx(b.sigma0, rel=1e-6)
    assert np.allclose(a.redundancy, b.redundancy, atol=1e-6)


def test_engine_and_dense_solver_agree_with_rig_and_weighted_points(field):
    """Both routes also agree on the blocks the case above does not have: a rig offset (rotation
    increments composed in solve_dense's update) and object points with a-priori σ (weighted
    pseudo-observations). Same bounds as above: a common minimum to 1e-4 σ, σ to 0.1 %."""
    T = field.truth
    cams, ims, _, _ = _rig_inputs(field)
    rng = np.random.default_rng(8)
    pts = T.points + rng.normal(0, 0.001, T.points.shape)
    kw = dict(rig=True, point_std=np.full(T.points.shape, 0.001))
    a = calibrate(cams, pts, ims, options=SelfCalibrationOptions(snooping=False, solver="adjustment"), **kw)
    b = calibrate(cams, pts, ims, options=SelfCalibrationOptions(snooping=False, solver="dense"), **kw)
    assert a.outcome.success and b.outcome.success, (a.outcome.reason, b.outcome.reason)
    for ca, cb in zip(a.cameras, b.cameras):
        free = ca.free
        assert np.all(np.abs(ca.params[free] - cb.params[free]) < 1e-4 * ca.std[free])
        assert np.allclose(ca.std[free], cb.std[free], rtol=1e-3)
    ra, rb = a.relative[0], b.relative[0]
    assert np.all(np.abs(ra.t - rb.t) < 1e-4 * ra.std[3:])
    assert np.linalg.norm(ra.R @ rb.R.T - np.eye(3)) < 1e-4 * np.linalg.norm(ra.std[:3])
    assert np.allclose(ra.std, rb.std, rtol=1e-3)
    # adjusted control points: same to 1e-4 of their 1 mm a-priori σ
    assert np.max(np.abs(a.solution.points - b.solution.points)) < 1e-7
    assert a.sigma0 == pytest.approx(b.sigma0, rel=1e-6)


def test_model_matches_camera_package():
    """The calibration's projection adapter (pixel pitch in mm, validity mask) equals
    thermogrammetry.Camera('photogrammetric') (pitch in µm), values and Jacobians."""
    from thermogrammetry.camera import Camera

    from thermogrammetry.synthetic.testfield import flir_a320_table2_params

    p = flir_a320_table2_params()
    p.update(K4=1e-7, K5=-1e-9, B1=2e-4, B2=-1e-4)
    cam = Camera("photogrammetric", (320, 240), p, pixel_pitch_um=25.0)
    rng = np.random.default_rng(3)
    X = np.column_stack([rng.uniform(-0.9, 0.9, 200), rng.uniform(-0.7, 0.7, 200), rng.uniform(5, 8, 200)])
    ours, _, J, ok = project(X, np.array([p[k] for k in PARAM_NAMES]), (320, 240), (0.025, 0.025))
    assert ok.all()
    theirs = cam.project(X)
    assert np.max(np.abs(ours - theirs)) < 1e-8
    _, _, Jt = cam.project_jacobian(X)
    assert np.allclose(J, Jt, rtol=1e-6, atol=1e-8 * np.abs(J).max(axis=(0, 1)))


def test_weighted_control_points(field):
    """Control coordinates with a-priori σ (1 mm) are adjusted as weighted unknowns: the camera is
    still recovered and the adjusted control points move towards the truth."""
    T = field.truth
    cams, ims = _inputs(field)
    rng = np.random.default_rng(8)
    sig = 0.001
    pts = T.points + rng.normal(0, sig, T.points.shape)
    r = calibrate(cams, pts, ims, point_std=np.full(T.points.shape, sig))
    assert r.outcome.success, r.outcome.reason
    cam = r.cameras[0]
    for name in STAGE2:
        i = PARAM_NAMES.index(name)
        assert abs(cam.params[i] - T.params[i]) < 3.0 * cam.std[i], name
    assert 0.9 * NOISE_PX < cam.sigma_xy_px[0] < 1.1 * NOISE_PX
    # the images add information to the 1 mm control: each target is seen in ~15 images with 0.4 px
    # (≈ 4 mm at 7 m per ray, but the poses are estimated from the same points), so the adjusted
    # points are closer to the truth than the control (expected ratio ≈ 0.9; 231 coordinates give
    # a sampling spread of the ratio of ~3 %)
    err_before = np.sqrt(np.mean((pts - T.points) ** 2))
    err_after = np.sqrt(np.mean((r.solution.points - T.points) ** 2))
    assert err_after < 0.98 * err_before, (err_after, err_before)
    assert err_after > 0.5 * err_before  # and not implausibly better


def test_engine_stopping_early_is_caught(field):
    """If the engine stops away from a minimum (here: 2 iterations from a perturbed start), the
    Gauss-Newton check finds it and the dense LM finishes; the outcome says so."""
    from thermogrammetry.calibration.bundle import BundleProblem, CameraBlock, solve_bundle

    T = field.truth
    free = np.zeros(12, bool)
    free[[PARAM_NAMES.index(n) for n in STAGE2]] = True
    p0 = T.params.copy()
    p0[0] += 0.3  # 0.3 mm off in c: ~8 σ
    cb = CameraBlock(p0, free, T.image_size, (0.025, 0.025))
    prob = BundleProblem([cb], T.R.copy(), T.t.copy(), T.points, np.zeros(field.obs_image.size, int), field.obs_image,
                         field.obs_point, field.xy_px, np.ones_like(field.xy_px))
    early = solve_bundle(prob, max_iterations=2, engine="adjustment")
    full = solve_bundle(prob, engine="dense")
    assert early.outcome.success
    assert "continued with the dense LM" in early.outcome.reason
    assert early.layout["gn_step_sigma_at_engine_solution"] > 1e-3
    assert abs(early.cameras[0].params[0] - full.cameras[0].params[0]) < 1e-3 * full.camera_std[0][0]
    # and a converged engine run passes the check without the dense LM
    done = solve_bundle(prob, engine="adjustment")
    assert done.layout["engine"] == "adjustment" and done.layout["gn_step_sigma_at_engine_solution"] < 1e-3


def _monte_carlo_table(n: int, staged: bool, solver: str) -> None:  # pragma: no cover - manual report
    """Print the Monte-Carlo table of the seed-001 case (see ``__main__`` below)."""
    field = make_testfield(np.random.default_rng(2024), noise_px=NOISE_PX)
    T = field.truth
    idx = [PARAM_NAMES.index(p) for p in STAGE2]
    xy_all = resample_noise(field, np.random.default_rng(99), n)
    est, rep, s0, sx, sy = [], [], [], [], []
    for k in range(n):
        cams, ims = _inputs(field, xy_all[k])
        if staged:
            r = calibrate(cams, T.points, ims, options=SelfCalibrationOptions(solver=solver))
        else:
            r = calibrate(cams, T.points, ims, options=SelfCalibrationOptions(snooping=False, solver=solver),
                          initial={0: T.params.copy()}, initial_poses=list(zip(T.R, T.t)))
        c = r.cameras[0]
        est.append(c.params[idx])
        rep.append(c.std[idx])
        s0.append(r.sigma0)
        sx.append(c.sigma_xy_px[0])
        sy.append(c.sigma_xy_px[1])
    est, rep = np.array(est), np.array(rep)
    sc = est.std(0, ddof=1)
    rp = np.sqrt(np.mean(rep**2, 0))
    print(f"solver={solver} staged={staged} n={n} observations={field.xy_px.shape[0]}")
    print(f"{'param':6s} {'truth':>12s} {'MC mean':>12s} {'MC scatter':>11s} {'reported':>11s} {'ratio':>6s} {'bias z':>7s} {'|z|<3':>6s}")
    for j, p in enumerate(STAGE2):
        z = (est[:, j] - T.params[idx[j]]) / rep[:, j]
        print(f"{p:6s} {T.params[idx[j]]:12.5g} {est[:, j].mean():12.5g} {sc[j]:11.3g} {rp[j]:11.3g} {rp[j] / sc[j]:6.3f} "
              f"{(est[:, j].mean() - T.params[idx[j]]) / (sc[j] / np.sqrt(n)):7.2f} {np.mean(np.abs(z) < 3):6.3f}")
    print(f"sigma0 {np.mean(s0):.4f}; sigma_x {np.mean(sx):.4f} px, sigma_y {np.mean(sy):.4f} px (injected {NOISE_PX})")


if __name__ == "__main__":  # pragma: no cover
    # python tests/test_calibration_selfcal.py [N] [staged] [adjustment|dense]
    import sys

    args = sys.argv[1:]
    _monte_carlo_table(int(args[0]) if args else 200, "staged" in args, "dense" if "dense" in args else "adjustment")
