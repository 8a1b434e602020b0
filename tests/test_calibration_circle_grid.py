"""Circle grids under strong barrel distortion and perspective, with unbiased centres (issue 13).

The set: 24 views of a 4 x 3 mask grid of 60 mm circles at 90 mm spacing, 640 x 512, distortion
~40 px at the frame corners (``thermogrammetry.synthetic.circle_grid_set``), PSF 0.8 px, NETD 50 mK.
A second rendering of the same views puts every circle off its nominal place by a known N(0, σ²)
image shift per coordinate (σ = 0.15 px): the "injected noise" against which the residual RMS is judged.
"""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry.calibration.bundle import PARAM_NAMES
from thermogrammetry.calibration.circle_bias import calibrate_circle_grid, circle_centroid_bias
from thermogrammetry.calibration.detect_circles import detect_circle_grid
from thermogrammetry.calibration.selfcal import SelfCalibrationOptions
from thermogrammetry.synthetic.circle_grid_set import (
    STRONG_BARREL_CAMERA,
    DisplacedCircleGrid,
    displace_centres_in_image,
    make_circle_grid_set,
)

CENTRE_NOISE_PX = 0.15  # sigma of the injected centre shift, px per image coordinate
OPTIONS = SelfCalibrationOptions(fixed=("B1", "B2"))


@pytest.fixture(scope="module")
def cgset():
    return make_circle_grid_set(24, supersample=2)


@pytest.fixture(scope="module")
def raw_dets(cgset):
    return [detect_circle_grid(v.image_k, cgset.target, n, perspective_correction=False)
            for v, n in zip(cgset.views, cgset.names)]


@pytest.fixture(scope="module")
def clean_cal(cgset, raw_dets):
    return calibrate_circle_grid(raw_dets, cgset.target, pixel_pitch_um=17.0, options=OPTIONS)


@pytest.fixture(scope="module")
def noisy_set():
    return make_circle_grid_set(24, supersample=2, centre_noise_px=CENTRE_NOISE_PX)


def _aligned(d, truth):
    """Detected points in the truth's numbering (a symmetric grid may be numbered from the other end)."""
    a, b = d.points_px - truth, d.points_px[::-1] - truth
    return d.points_px if np.abs(a).max() < np.abs(b).max() else d.points_px[::-1]


def test_set_has_strong_distortion(cgset):
    cam = cgset.camera
    g = np.array([[-0.5, -0.5], [639.5, -0.5], [-0.5, 511.5], [639.5, 511.5]])
    rays = cam.unproject(g)
    ideal = (rays[:, :2] / rays[:, 2:3]) @ cam.K[:2, :2].T + cam.K[:2, 2]
    assert np.linalg.norm(ideal - g, axis=1).min() >= 30.0
    assert len(cgset.views) == 24


def test_all_24_found_and_identified(cgset, raw_dets):
    assert all(d.found for d in raw_dets), [d.reason for d in raw_dets if not d.found]
    for d, v in zip(raw_dets, cgset.views):
        # raw centroids are biased by up to ~1.3 px (close oblique views of 60 mm circles: perspective +
        # distortion), never by a spacing (> 50 px here): every circle identified
        assert np.abs(_aligned(d, v.points_px) - v.points_px).max() < 3.0, d.image_id


def test_unbiased_calibration_recovers_truth(cgset, raw_dets, clean_cal):
    run, hist, bias = clean_cal
    r = run.result
    assert r.outcome.success and len(r.images_used) == 24
    c = r.cameras[0]
    for i, n in enumerate(PARAM_NAMES):
        if c.free[i]:
            assert abs(c.params[i] - STRONG_BARREL_CAMERA.get(n, 0.0)) < 3 * c.std[i], n
    # bias left: the bias subtracted in the last round against the exact one (true camera and poses)
    left, noise = [], []
    for d, v in zip(raw_dets, cgset.views):
        true_b = circle_centroid_bias(cgset.camera, v.pose.R, v.pose.t, v.points_target, 0.03)
        sign_ok = np.abs(d.points_px - v.points_px).max() < np.abs(d.points_px[::-1] - v.points_px).max()
        b = bias[d.image_id] if sign_ok else bias[d.image_id][::-1]
        raw = _aligned(d, v.points_px)
        left.append(b - true_b)
        noise.append(raw - true_b - v.points_px)  # the centroid error that is not bias: image noise
    left = np.concatenate(left)
    assert np.abs(left).max() <= 0.02
    noise = np.concatenate(noise)
    sigma = np.sqrt(np.mean(np.sum(noise**2, axis=1)))
    # the centroid error left after the exact bias (measured 0.035 px RMS) is partly per-view systematic
    # (absorbed by the poses), so the residual RMS (measured 0.015 px) lies below the white-noise
    # expectation sigma * sqrt(redundancy / observations) (0.030 px); it can never exceed sigma
    assert 0.2 * sigma < r.rms_px < sigma * np.sqrt(r.dof / noise.size) * 1.1, (r.rms_px, sigma)


def test_displaced_circles_move_their_projection_by_the_wanted_shift(cgset):
    v = cgset.views[3]
    shift = np.random.default_rng(5).normal(0.0, 0.2, (12, 2))
    off = displace_centres_in_image(cgset.camera, v.pose.R, v.pose.t, cgset.target.object_points(), shift)
    moved = np.column_stack([cgset.target.object_points()[:, :2] + off, np.zeros(12)]) * 1e-3
    got = cgset.camera.project(moved @ v.pose.R.T + v.pose.t) - v.points_px
    assert np.abs(got - shift).max() < 1e-6
    # ~0.2 px at 0.45-0.7 m and fx 440 px is ~0.2-0.3 mm on the target
    assert 0.05 < np.abs(off).max() < 1.0
    g = DisplacedCircleGrid(4, 3, 90.0, diameter_mm=60.0, offsets_mm=off)
    c = g.circle_centres_mm()
    lab = g.classify(c[:, 0] + 29.9, c[:, 1])  # just inside every displaced circle's rim
    assert np.all(lab == 2)
    assert np.all(g.classify(c[:, 0] + 30.1, c[:, 1]) == 1)
    with pytest.raises(Exception, match="offsets_mm"):
        DisplacedCircleGrid(4, 3, 90.0, diameter_mm=60.0, offsets_mm=np.full((12, 2), 6.0))


def test_residual_rms_matches_injected_centre_noise(noisy_set, clean_cal):
    """Residual RMS against the injected centre noise, and parameters against the truth.

    Every circle of every view is rendered where its projected centre moves by a known shift
    ``d ~ N(0, σ²)`` per coordinate (σ = 0.15 px, seeded); the calibration is told the nominal grid.
    For white errors of σ per coordinate the a-posteriori residuals satisfy
    ``E[Σ|v|²] = σ² · r`` (r: redundancy), so the residual RMS per point (``rms_px`` = sqrt(mean |v|²))
    is expected at ``sqrt(2 σ² r / n_obs + rms_0²)`` with ``n_obs`` the number of coordinates and
    ``rms_0`` the residual RMS of the same views rendered without the shifts (the detector's own
    error after the bias removal: measured 0.015 px, it adds 0.3 % here).

    Measured (24 views, 288 points, r = 424): expected 0.1826 px, rms 0.1817 px (ratio 0.995);
    the realised shifts have a 2-D RMS of 0.2119 px (nominal 0.2121). The tolerance: the RMS of
    ``r`` squared normal residuals fluctuates by 1/sqrt(2 r) = 3.4 % (1 σ), so ±10 % is ~3 σ, and
    a detector error comparable with the injected one (not seen: 0.029 px 2-D after the exact bias)
    or an unremoved centre bias (0.25 px before the conic correction) would break it.
    Parameters: within 3 of their σ of the truth (measured: largest 1.8 σ, P2).
    """
    run0 = clean_cal[0].result
    dets = [detect_circle_grid(v.image_k, noisy_set.target, n, perspective_correction=False)
            for v, n in zip(noisy_set.views, noisy_set.names)]
    assert all(d.found for d in dets), [d.reason for d in dets if not d.found]
    run, hist, bias = calibrate_circle_grid(dets, noisy_set.target, pixel_pitch_um=17.0, options=OPTIONS)
    r = run.result
    assert r.outcome.success and len(r.images_used) == 24
    n_obs = r.residuals_px.size
    expected = np.sqrt(2 * CENTRE_NOISE_PX**2 * r.dof / n_obs + run0.rms_px**2)
    assert abs(r.rms_px / expected - 1.0) < 0.10, (r.rms_px, expected, r.dof, n_obs)
    # the shifts were really injected at the nominal sigma (a check of the test set, not the code)
    d2 = np.concatenate(noisy_set.centre_shifts_px)
    assert abs(np.sqrt(np.mean(d2**2)) / CENTRE_NOISE_PX - 1.0) < 0.1
    # and the clean set is far below: the residuals are the injected noise, not the detector's
    assert run0.rms_px < 0.2 * r.rms_px
    c = r.cameras[0]
    for i, n in enumerate(PARAM_NAMES):
        if c.free[i]:
            assert abs(c.params[i] - STRONG_BARREL_CAMERA.get(n, 0.0)) < 3 * c.std[i], (n, c.params[i], c.std[i])
