"""The two no-data fills of ``thermogrammetry._sampling``: nearest valid pixel (dense matching's codes, photofit) and a
smooth fill (feature detection and tracking under a masked display or NaN)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from thermogrammetry._sampling import fill_nearest_valid, fill_smooth


def _masks():
    h, w = 64, 80
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[:h, :w]
    out = {
        "rectified corners": (xx + 0.6 * yy > 100) | (yy < 6) & (xx > 50) | (yy > 60) & (xx < 12),
        "left columns": xx < 5,
        "blobs": cv2.dilate((rng.random((h, w)) < 0.01).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool),
        "specks": rng.random((h, w)) < 0.2,
        "all but a corner": (yy > 2) | (xx > 2),
        "one valid pixel": np.ones((h, w), bool),
    }
    out["one valid pixel"][40, 70] = False
    return out


@pytest.mark.parametrize("name", list(_masks()))
def test_nearest_valid_fill_takes_a_nearest_pixel(name):
    """Every invalid pixel gets the value of a valid pixel at the smallest L1 distance (values are unique, so the
    pixel taken is known); valid pixels are unchanged; float64 stays float64."""
    invalid = _masks()[name]
    h, w = invalid.shape
    a = np.random.default_rng(0).permutation(h * w).reshape(h, w).astype(np.float64) + 0.5
    a[invalid] = np.nan
    out = fill_nearest_valid(a, ~invalid)
    assert out.dtype == np.float64 and np.isfinite(out).all()
    assert np.array_equal(out[~invalid], a[~invalid])
    pos = {v: divmod(k, w) for k, v in enumerate(a.ravel()) if np.isfinite(v)}
    vy, vx = np.nonzero(~invalid)
    for y, x in zip(*np.nonzero(invalid)):
        ty, tx = pos[out[y, x]]
        best = np.min(np.abs(vy - y) + np.abs(vx - x))
        assert abs(ty - y) + abs(tx - x) == best, (y, x)


def test_nearest_valid_fill_equals_the_whole_frame_transform_where_unambiguous():
    """Against OpenCV's labelled transform over the whole frame: the same values wherever the nearest valid pixel is
    unique; where several are equally near the window's transform may take another (measured: 100 % equal on this
    mask, 9 % of it invalid)."""
    invalid = _masks()["rectified corners"]
    a = np.random.default_rng(1).normal(300.0, 1.0, invalid.shape).astype(np.float32)
    _, lab = cv2.distanceTransformWithLabels(invalid.view(np.uint8), cv2.DIST_L1, 3, labelType=cv2.DIST_LABEL_PIXEL)
    lut = np.r_[np.float32(0), a[~invalid]]
    whole = lut[lab]
    out = fill_nearest_valid(a, ~invalid)
    same = out == whole
    assert same[~invalid].all()
    assert same.mean() > 0.97


def test_smooth_fill_leaves_no_edge():
    """A 19 x 19 px hole in a ramp of 0.1 per pixel filled smoothly: largest step between neighbours 0.27 (measured;
    the flat median fill makes a step of 1.1 at the hole's border), within 0.38 of the ramp inside; valid pixels
    unchanged; no valid pixel at all gives zeros."""
    yy, xx = np.mgrid[:100, :120].astype(np.float32)
    a = 290.0 + 0.1 * xx
    hole = (np.abs(xx - 60) < 10) & (np.abs(yy - 50) < 10)
    out = fill_smooth(np.where(hole, np.nan, a), ~hole)
    assert np.array_equal(out[~hole], a[~hole])
    step = np.abs(np.diff(out, axis=1))
    assert step.max() < 0.4
    assert np.abs(out[hole] - a[hole]).max() < 0.5
    assert not fill_smooth(a, np.zeros(a.shape, bool)).any()
