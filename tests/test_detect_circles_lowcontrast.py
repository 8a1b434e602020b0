"""Low-contrast 16-bit circle grids under a heater's hot spot and vignetting (issue 13, item 3).

The 4 x 3 mask of 60 mm circles at 90 mm spacing through the strong-barrel camera
(``make_circle_grid_set``), holes 1 K above the mask (301 / 300 K, surround 298 K), an 8 K Gaussian
hot spot 1.5 spacings wide on the mask, 25 % signal vignetting, NETD 0.04 K, stored as uint16 counts of
0.01 K. The stretched image shows the hot spot, not the holes: the cascade before the flat-field
passes finds 4 of 6 views.
"""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry.calibration.circle_bias import circle_centroid_bias
from thermogrammetry.calibration.detect_circles import detect_circle_grid
from thermogrammetry.synthetic.circle_grid_set import make_circle_grid_set


@pytest.fixture(scope="module")
def lcset():
    cg = make_circle_grid_set(6, supersample=2, temperatures=(301.0, 300.0, 298.0), hot_spot_k=8.0, vignetting=0.25,
                              netd_k=0.04)
    counts = [np.clip(np.rint(v.image_k.astype(np.float64) * 100.0), 0, 65535).astype(np.uint16) for v in cg.views]
    return cg, counts


def test_flatfield_pass_finds_the_rest_and_leaves_found_views_alone(lcset):
    """Measured: the cascade without flat-field passes finds cg01, cg03-cg05 ("bright-ellipses"); with
    them cg00 and cg02 are found by "bright-flatfield-narrow+clustering" (σ = side/32; the side/16
    pass alone does not find them here); the views found before
    keep their centres bit for bit. Centre error against the exact (biased) centroid of each imaged
    circle: 0.18-0.34 px RMS, max 0.61 px (NETD 0.04 K on a 1 K contrast under an 8 K hot spot, which
    the plane background of the moment window follows only to first order); the bound 0.5 px RMS /
    1.0 px max is ~1.5x the worst view, far below a misidentified circle (> 60 px)."""
    cg, counts = lcset
    n_old = n_ff = 0
    for v, im, name in zip(cg.views, counts, cg.names):
        assert int(im.max()) - int(im.min()) > 800  # the hot spot spans > 8x the hole contrast (100 counts)
        old = detect_circle_grid(im, cg.target, name, perspective_correction=False, flatfield=False, partial=False)
        d = detect_circle_grid(im, cg.target, name, perspective_correction=False)
        assert d.found and d.n_points == 12, d.reason
        if old.found:
            n_old += 1
            assert d.method == old.method and np.array_equal(d.points_px, old.points_px), name
        else:
            n_ff += 1
            assert "flatfield" in d.method and d.method in d.reason, d.reason
        truth = v.points_px + circle_centroid_bias(cg.camera, v.pose.R, v.pose.t, v.points_target, 0.03)
        a = np.linalg.norm(d.points_px - truth, axis=1)
        b = np.linalg.norm(d.points_px[::-1] - truth, axis=1)  # a symmetric grid may be numbered from the other end
        err = a if a.max() < b.max() else b
        assert np.sqrt(np.mean(err**2)) < 0.5 and err.max() < 1.0, (name, err)
    assert n_old <= 4 and n_ff >= 2, (n_old, n_ff)
