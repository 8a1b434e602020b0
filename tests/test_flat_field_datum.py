"""Flat-field blocks: what GCPs on flat ground cannot separate, and what the survey then does.

- The GNSS-vs-GCP datum offset (sfm.georef_gnss.gnss_offset): over flat ground a Z offset is as uncertain as the
  focal length times the flying height (f -> s f with the cameras at s times their height leaves every image point
  in place), so a focal length that is only the lens's nominal value widens its σ (sfm.block_gates).
- The GCP measurements' σ estimated from their residuals (sfm.georef_adjustment._marker_sigma), which the check
  points' intersection takes when it is larger than the σ given.

The end-to-end figures are in ``benchmarks/survey_flatfield.py``."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from thermogrammetry.sfm.block_gates import _focal_height_std
from thermogrammetry.sfm.georef_adjustment import MARKER_SIGMA_MIN_DOF, _marker_sigma
from thermogrammetry.sfm.georef_gnss import gnss_offset
from thermogrammetry.sfm.selfcal_ladder import FocalKnown


def _centres(rng, n=56, dz=0.0, h=50.0):
    C = np.c_[rng.uniform(0, 100, (n, 2)), np.full(n, 400.0 + h)]
    G = C + rng.normal(0, [0.03, 0.03, 0.05], (n, 3))
    C = C + [0.0, 0.0, dz]
    S = np.tile([0.08, 0.09, 0.35], (n, 1))  # the centres' σ of an adjustment on the GCPs alone (flat field, measured)
    return C, S, G, np.tile([0.03, 0.03, 0.05], (n, 1))


def test_a_z_offset_of_a_few_metres_over_flat_ground_is_not_taken_for_a_datum_difference():
    rng = np.random.default_rng(4)
    # the flat field of benchmarks/survey_flatfield.py, seed 0: -2.78 m +- 0.35 m "found" (8 sigma) with a focal
    # length 5 % off, where the truth is no offset at all
    C, S, G, GS = _centres(rng, dz=-2.78)
    assert gnss_offset(C, S, G, GS).significant[2]
    # the lens's 5 % at 50 m: sigma_Z 2.5 m -> 2.78 m is 1.1 sigma: not applied
    off = gnss_offset(C, S, G, GS, extra_std_m=(0.0, 0.0, 0.05 * 50.0))
    assert not off.significant[2] and abs(off.std_m[2] - np.hypot(0.35, 2.5)) < 1e-9
    # a geoid-sized difference (48.3 m) still is
    C, S, G, GS = _centres(rng, dz=-48.3)
    assert gnss_offset(C, S, G, GS, extra_std_m=(0.0, 0.0, 2.5)).significant[2]


def test_the_focal_height_sigma_needs_a_self_calibrated_lens_value():
    rec = SimpleNamespace(image_camera=np.zeros(4, int), centers=lambda: np.c_[np.zeros((4, 2)), np.full(4, 450.0)])
    ctrl = SimpleNamespace(gcp_xyz=np.array([[0.0, 0.0, 399.0], [1.0, 0.0, 401.0], [2.0, 0.0, 400.0]]))
    fk = FocalKnown({0: True}, {0: 379.2}, {0: 18.96})
    assert abs(_focal_height_std(rec, np.arange(4), ctrl, fk, ("fx", "fy", "k1")) - 0.05 * 50.0) < 1e-3
    # a camera held from a calibration (nothing self-calibrated) or without a lens value: no such term
    assert _focal_height_std(rec, np.arange(4), ctrl, fk, ()) == 0.0
    assert _focal_height_std(rec, np.arange(4), ctrl, FocalKnown({0: False}), ("fx", "fy")) == 0.0


def test_marker_sigma_from_the_gcp_residuals():
    rng = np.random.default_rng(7)
    n_tie, ng, per = 30, 8, 6
    obs = [(k, g, np.zeros(2), np.array([0.5, 0.5])) for g in range(ng) for k in range(per)]
    v = rng.normal(0, 1.0, (len(obs), 2))
    res = SimpleNamespace(image_residuals=np.vstack([np.zeros((n_tie, 2)), v]))
    ms = _marker_sigma(res, n_tie, obs)
    dof = 2 * len(obs) - 3 * ng
    assert ms["dof"] == dof and ms["given_px"] == 0.5
    assert abs(ms["estimated_px"] - np.sqrt(np.sum(v**2) / dof)) < 1e-12
    # too few measurements (3 GCPs in 2 images each: 12 - 9 = 3 degrees of freedom): not estimated
    few = [(k, g, np.zeros(2), np.array([0.5, 0.5])) for g in range(3) for k in range(2)]
    assert 2 * len(few) - 9 < MARKER_SIGMA_MIN_DOF
    assert _marker_sigma(SimpleNamespace(image_residuals=np.zeros((n_tie + 6, 2))), n_tie, few) is None
