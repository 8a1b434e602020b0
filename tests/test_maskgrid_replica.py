"""A replica of a real thermal mask circle-grid set (issue 13): 4 x 3 dark 60 mm circles at 90 mm in a
warm mask on a heated plate, 640 x 512, fx 440.7 px, ~80 px barrel distortion at the frame corners,
views tilted up to ~55°, the grid near the frame corners in some, a warmer plate rim, a cooler room
with a person-warm blob, a mild temperature gradient over mask and circles, PSF σ 0.5 px, NETD 0.05 K
(``thermogrammetry.synthetic.mask_grid_replica``).

Measured on the full 24-view set (supersample 6, 0.1 px injected centre noise; /work/notes/maskgrid.md):
24/24 found before and after the edge-polygon centres; centre error against the exact centroid 0.211 px
RMS / 3.0 px max with the moment window (f32; views near the frame border kept blob positions), 0.0057
px RMS / 0.013 px max with ``refine="edges"``; CLI RMS 0.1284 px against 0.1283 expected.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from thermogrammetry.calibration.detect_circles import detect_circle_grid
from thermogrammetry.cli.main import main
from thermogrammetry.synthetic.mask_grid_replica import (MASK_GRID_CAMERA, make_mask_grid_replica, quantize,
                                                         render_mask_grid_view)
from thermogrammetry.synthetic.radiance import BandPlanckCurve

N_VIEWS = 12
NOISE_PX = 0.1


def _aligned(p, truth, ids):
    """Detected points against the truth up to the 180° symmetry of a symmetric grid's numbering."""
    a, b = truth[ids], truth[::-1][ids]
    return a if np.abs(p - a).max() < np.abs(p - b).max() else b


def test_replica_geometry():
    """The set is what the issue describes: 24 views, plate filling 25-80 % of the frame, tilts up to
    ~55°, the grid near the frame corners in some views, distortion of tens of px there."""
    r = make_mask_grid_replica(views=[])
    assert len(r.poses) == 24 and r.camera.image_size == (640, 512)
    assert 440.0 < MASK_GRID_CAMERA["c_mm"] / 0.017 < 441.5
    fill, tilt = np.array(r.fill), np.array(r.tilt_deg)
    assert fill.min() >= 0.25 and fill.max() <= 0.8 and fill.max() > 0.6
    assert tilt.max() <= 55.0 and np.sum(tilt > 40) >= 4
    centres = np.array([p.mean(axis=0) for p in r.points_px])
    near_corner = (np.abs(centres[:, 0] - 319.5) > 170) & (np.abs(centres[:, 1] - 255.5) > 130)
    assert near_corner.sum() >= 4
    # the distortion of the corner pixel (where it would be without distortion): ~80 px
    from thermogrammetry.camera import Camera

    pinhole = Camera("photogrammetric", (640, 512), {k: MASK_GRID_CAMERA[k] for k in ("c_mm", "x0_mm", "y0_mm")},
                     pixel_pitch_um=17.0)
    for corner in ([0.0, 0.0], [639.0, 511.0]):
        ideal = pinhole.project(r.camera.unproject(np.array([corner]))[0][None])[0]
        assert 50.0 < np.linalg.norm(ideal - corner) < 120.0, ideal


def test_rendered_centroid_is_exact():
    """Supersample 6, no blur/noise/gradient: the area centroid of every rendered disc (radiance-linear
    coverage) agrees with the exact centroid of the projected outline to < 0.01 px."""
    import cv2

    r = make_mask_grid_replica(views=[])
    cur = BandPlanckCurve()
    k = 7  # tilted 44°, the largest centroid bias of the set (1.2 px)
    R, t = r.poses[k]
    im = render_mask_grid_view(r.camera, (R, t), r.target, supersample=6, psf_sigma_px=0.0, netd_k=0.0,
                               gradient=(0.0, 0.0, 0.0))
    s = cur.signal(im.astype(np.float64))
    frac = (cur.signal(313.0) - s) / (cur.signal(313.0) - cur.signal(299.0))
    a = np.linspace(0, 2 * np.pi, 256, endpoint=False)
    obj = r.target.object_points() * 1e-3
    truth = r.points_px[k] + r.centroid_bias_px[k]
    assert np.abs(r.centroid_bias_px[k]).max() > 0.5
    for i in range(12):
        rim = obj[i] + 0.033 * np.stack([np.cos(a), np.sin(a), 0 * a], 1)
        q = r.camera.project(rim @ R.T + t)
        m = np.zeros(im.shape, np.uint8)
        cv2.fillPoly(m, [np.round(q * 16).astype(np.int32)], 1, shift=4)
        yy, xx = np.nonzero(m)
        w = frac[yy, xx]
        c = np.array([np.sum(w * xx), np.sum(w * yy)]) / w.sum()
        assert np.linalg.norm(c - truth[i]) < 0.01, (i, c - truth[i])


@pytest.fixture(scope="module")
def replica_run(tmp_path_factory):
    import tifffile

    r = make_mask_grid_replica(supersample=3, centre_noise_px=NOISE_PX, views=list(range(N_VIEWS)))
    d = tmp_path_factory.mktemp("mg")
    names = r.names[:N_VIEWS]
    u8, u16 = [], []
    for name, im in zip(names, r.images_k[:N_VIEWS]):
        u8.append(quantize(im, 8))
        u16.append(quantize(im, 16))
        tifffile.imwrite(d / f"{name}.tif", u16[-1])
    out = d / "OUT"
    rc = main(["calibrate", str(d), "--target", "circles", "--grid", "4x3", "--spacing-mm", "90", "--diameter-mm",
               "60", "--pixel-pitch-um", "17", "-o", str(out)])
    return r, names, u8, u16, out, rc


def test_edge_centres_on_8_and_16_bit(replica_run):
    """Every view found, in 8-bit (AGC stretch) and 16-bit (0.01 K counts); the raw centres against the
    exact centroid of each imaged (displaced) circle: measured 0.0094 px RMS, max 0.027 px in both
    (render error at supersample 3 included); bound 0.03 / 0.08 px. The moment window on the same
    views: 0.19 px (8-bit) / 0.13 px (16-bit) RMS, max 2.0 / 1.0 px (a temperature gradient across the
    discs, windows too small for tilted discs, blob positions at the frame border) -- the bias the
    edge polygon removes, checked > 0.04."""
    r, names, u8, u16, out, rc = replica_run
    for imgs in (u8, u16):
        err, err_m = [], []
        for k, (name, im) in enumerate(zip(names, imgs)):
            d = detect_circle_grid(im, r.target, name, perspective_correction=False)
            assert d.found and d.n_points == 12, (name, d.reason)
            truth = _aligned(d.points_px, r.points_px[k] + r.centroid_bias_px[k], d.object_ids)
            err.append(np.linalg.norm(d.points_px - truth, axis=1))
            dm = detect_circle_grid(im, r.target, name, perspective_correction=False, refine="moments")
            err_m.append(np.linalg.norm(dm.points_px - _aligned(dm.points_px, r.points_px[k] + r.centroid_bias_px[k],
                                                                  dm.object_ids), axis=1))
        e, em = np.concatenate(err), np.concatenate(err_m)
        assert np.sqrt(np.mean(e**2)) < 0.03 and e.max() < 0.08, (np.sqrt(np.mean(e**2)), e.max())
        assert np.sqrt(np.mean(em**2)) > 0.04


def test_cli_calibration_matches_injected_noise_and_truth(replica_run):
    """`thermogrammetry calibrate ... --target circles --diameter-mm 60` on the 16-bit views: all used;
    RMS against sqrt(2 σ² r / n_obs) from the realised centre shifts (σ their RMS per coordinate), within
    ±12 % (≈ 2.5 σ of the RMS of r = 208 squared residuals; measured 0.1240 vs 0.1270, ratio 0.976);
    every free parameter within 3 σ of the truth (measured: c at -2.54 σ, the others within 1.9 σ; the
    same 12 views without the injected shifts give c at +0.96 σ of their own, 40x smaller σ -- so the
    -2.54 is this noise draw, not a bias)."""
    r, names, u8, u16, out, rc = replica_run
    assert rc == 0
    cal = json.loads((out / "calibration.json").read_text())
    assert len(cal["images_used"]) == N_VIEWS
    sig = float(np.sqrt(np.mean(np.concatenate(r.centre_shifts_px[:N_VIEWS]) ** 2)))
    n_obs = 2 * sum(row["n_points"] for row in cal["per_image"] if row["used"])
    expected = np.sqrt(2 * sig**2 * cal["dof"] / n_obs)
    assert 0.88 < cal["rms_px"] / expected < 1.12, (cal["rms_px"], expected)
    for name, p in cal["parameters"].items():
        if p["estimated"]:
            z = (p["value"] - MASK_GRID_CAMERA.get(name, 0.0)) / p["std"]
            assert abs(z) < 3.0, (name, p["value"], p["std"], z)


def test_low_contrast_views_no_gross_errors_and_completed_grid():
    """Set C of the note (2 K circle contrast, 330 K plate rim, rolls to ±60°, 8-bit): view 13's blob
    detector put one circle 17 px off (kept at that position before: "found" with a gross error); it is
    now measured again from the other circles' prediction; view 7's candidate passes found 11 circles (the
    smallest disc fell outside the size group), the 12th is now added where the others predict it. All
    circles within 0.1 px of the exact centroid (measured 0.042 / 0.030 px max; supersample 2)."""
    r = make_mask_grid_replica(supersample=2, roll_deg=60, seed=11, temperatures=(306.0, 308.0, 330.0, 294.0, 309.0),
                               gradient=(0.8, -0.5, 1.5), views=[7, 13])
    for k, note in ((7, "added where the others predict"), (13, "measured again from the grid's prediction")):
        im = quantize(r.images_k[k], 8)
        d = detect_circle_grid(im, r.target, r.names[k], perspective_correction=False)
        assert d.found and d.n_points == 12 and note in d.reason, (k, d.reason)
        truth = _aligned(d.points_px, r.points_px[k] + r.centroid_bias_px[k], d.object_ids)
        assert np.linalg.norm(d.points_px - truth, axis=1).max() < 0.1, k
