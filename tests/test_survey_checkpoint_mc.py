"""Monte-Carlo check of the check points' reported σ (issue 10: within ±25 % of the scatter).

The survey's final adjustment (``sfm.georef.final_adjustment``: self-calibration fx fy cx cy k1 k2 p1 p2,
GNSS priors, weighted GCPs, tie-point variance component) and the check-point intersection with full
propagation of the pose and camera covariance (``intersect_check_points``) are run on many noise
realisations of ONE synthetic block shaped like a DJI M3T flight. Tie points are the renderer's exact
correspondences (the matcher is not under test here; each run STARTS FROM the true poses and points, which
does not change a least-squares solution that converges). Noise injected per run: tie points and marker
measurements 0.3 px, GNSS 3/3/5 cm, GCP coordinates 1 cm (their stated σ).

The scatter of each check point's estimate around its true position over the runs is compared with the σ
the adjustment reports, pooled over the check points per axis: 24 runs × 8 check points give the ratio
to about ±5 % (1σ), so the ±25 % band is wide enough not to fail by chance and narrow enough to catch a
covariance that forgets the pose/camera part (that would report σ several times too small).
"""

from __future__ import annotations

import numpy as np
import pytest

N_RUNS = 24


@pytest.fixture(scope="module")
def block():
    from thermogrammetry.synthetic.survey import make_survey, marker_observations, tie_points
    from thermogrammetry.synthetic.survey_files import uav_thermal_config

    scene = make_survey(uav_thermal_config(seed=0))
    pts, obs = tie_points(scene, 700, seed=1)
    return scene, pts, obs, marker_observations(scene)


def _one_run(scene, pts, obs, markers, rng):
    from thermogrammetry.results import Outcome, Termination
    from thermogrammetry.sfm.georef import ControlInputs, final_adjustment, intersect_check_points
    from thermogrammetry.sfm.reconstruction import ImageStatus, Reconstruction
    from thermogrammetry.sfm.tracks import Tracks

    names = [f.name for f in scene.frames]
    index = {n: k for k, n in enumerate(names)}
    pnames = sorted(pts)
    pindex = {n: k for k, n in enumerate(pnames)}
    xy_by_image = [[] for _ in names]
    track, image, feature = [], [], []
    for im, pn, x, y in obs:
        i = index[im]
        feature.append(len(xy_by_image[i]))
        xy_by_image[i].append((x, y))
        track.append(pindex[pn])
        image.append(i)
    xy_by_image = [np.asarray(a, float).reshape(-1, 2) + rng.normal(0, 0.3, (len(a), 2)) for a in xy_by_image]
    tr = Tracks(np.array(track), np.array(image), np.array(feature))
    n = len(names)
    R = np.array([f.pose.R for f in scene.frames])
    t = np.array([f.pose.t for f in scene.frames])
    P = np.array([pts[k] for k in pnames], float)
    rec = Reconstruction(Outcome(Termination.CONVERGED), [scene.camera], np.zeros(n, np.int64), R.copy(), t.copy(),
                         np.ones(n, bool), np.zeros(n, np.int64), P.copy(), tr, np.ones(len(track), bool),
                         [ImageStatus(True, 0, "") for _ in range(n)])
    cfg = scene.config
    gsig = np.array([cfg.gnss_sigma_h_m, cfg.gnss_sigma_h_m, cfg.gnss_sigma_v_m])
    centres = np.array([f.pose.center for f in scene.frames])
    gcp_ids, check_ids = list(scene.gcps), list(scene.checks)
    gxyz = np.array([scene.gcps[k] for k in gcp_ids], float)
    cxyz = np.array([scene.checks[k] for k in check_ids], float)
    gcp_obs, check_obs = [], []
    for im, mk, x, y in markers:
        xy = np.array([x, y]) + rng.normal(0, 0.3, 2)
        if mk in scene.gcps:
            gcp_obs.append((index[im], gcp_ids.index(mk), xy, np.array([0.3, 0.3])))
        else:
            check_obs.append((index[im], check_ids.index(mk), xy, np.array([0.3, 0.3])))
    ctrl = ControlInputs(centres + rng.normal(0, gsig, centres.shape), np.tile(gsig, (n, 1)), np.zeros(3),
                         gcp_ids, gxyz + rng.normal(0, 0.01, gxyz.shape), np.full(gxyz.shape, 0.01), gcp_obs,
                         check_ids, cxyz, check_obs)
    from thermogrammetry.pipeline.survey import SELF_CALIBRATION

    fa = final_adjustment(rec, xy_by_image, np.arange(n), ctrl, self_calibrate=SELF_CALIBRATION, tie_sigma_px=0.3)
    assert fa.result.success, fa.result.reason
    cps = intersect_check_points(rec, fa, ctrl)
    err = np.array([c["error"] for c in cps], float)
    std = np.array([c["std"] for c in cps], float)
    return err, std


def test_checkpoint_sigma_matches_monte_carlo_scatter(block):
    scene, pts, obs, markers = block
    errs, stds = [], []
    for r in range(N_RUNS):
        e, s = _one_run(scene, pts, obs, markers, np.random.default_rng([2024, r]))
        errs.append(e)
        stds.append(s)
    E = np.array(errs)  # (runs, checks, 3)
    S = np.array(stds)
    assert np.isfinite(E).all() and np.isfinite(S).all() and E.shape[1] == len(scene.checks)
    # scatter about the mean over the runs (the datum from noisy GNSS/GCPs is part of the random error: the
    # true position is the reference, so the scatter is taken about the truth)
    scatter = np.sqrt(np.mean(E**2, axis=(0, 1)))
    reported = np.sqrt(np.mean(S**2, axis=(0, 1)))
    ratio = scatter / reported
    print(f"\ncheck points: MC scatter {np.round(scatter, 4)} m, reported σ {np.round(reported, 4)} m, ratio {np.round(ratio, 3)}")
    assert np.all((ratio > 0.75) & (ratio < 1.25)), ratio
