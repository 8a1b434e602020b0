"""Facade mosaics without a mesh (``products.facade``) on the synthetic building's south wall (true poses).

Images are noise-free; the wall is a black body (apparent = true temperature), so a mosaic cell must equal
the wall's true temperature up to the sampling error (< 0.01 K, see test_texture.py) unless an object in
front of the wall contaminates it. Homography points are measured with 0.1 px noise: at ~4 cm per pixel
a 0.1 px error moves a cell by ~4 mm, i.e. < 0.02 K on the steepest thermal bridge flank (3.6 K/m).
"""

from __future__ import annotations

import numpy as np
import pytest

from cached_scenes import building_images
from thermogrammetry.errors import DegenerateInputError, TooFewPointsError
from thermogrammetry.products.facade import (FacadeGrid, FacadePlane, fit_facade_homography, homography_mosaic,
                                             plane_mosaic)
from thermogrammetry.products.texture import TextureView
from thermogrammetry.synthetic.building import GROUPS, BuildingConfig, make_building, surface_temperature

PLANE = FacadePlane((0, 0, 0), (1, 0, 0), (0, 0, 1))  # south wall y = 0, a = x, b = z; normal -y (towards the street)
GRID = FacadeGrid(0.0, 12.0, 0.0, 7.0, 0.05)


@pytest.fixture(scope="module")
def wall(scene_cache):
    s = make_building(BuildingConfig(ground_margin_m=1.0))
    ks = [0, 1, 13]  # two stations in front of the south wall and one at its south-west corner
    images = building_images(scene_cache, s, ks)  # render_building_thermal(sensor=False), once per test run
    views = [TextureView(s.stations[k][0], s.thermal, s.stations[k][1], img) for k, img in zip(ks, images)]
    A, B = GRID.centres()
    truth = surface_temperature(s, PLANE.points(A, B).reshape(-1, 3), GROUPS.index("wall")).reshape(A.shape)
    occ = s.face_group == GROUPS.index("occluder")
    used = np.unique(s.faces[occ])
    remap = -np.ones(len(s.vertices), int)
    remap[used] = np.arange(len(used))
    # cells hidden by the occluder from a view: analytic slab test of the segment centre -> cell
    c = s.config
    ox, oy, oz = c.occluder_size_m
    lo = np.array([c.occluder_x_m - ox / 2, -c.occluder_distance_m - oy / 2, 0.0])
    hi = np.array([c.occluder_x_m + ox / 2, -c.occluder_distance_m + oy / 2, oz])
    return s, views, truth, (s.vertices[used], remap[s.faces[occ]]), (lo, hi)


def _hidden(C, P, lo, hi):
    d = P - C
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - C) / d, (hi - C) / d
    tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
    return (tmax > tmin) & (tmax > 0) & (tmin < 1)


def test_plane_mosaic_with_occluder_geometry_equals_truth(wall):
    s, views, truth, occ, (lo, hi) = wall
    m = plane_mosaic(views, PLANE, GRID, occluders=occ)
    ok = m.source >= 0
    assert ok.mean() > 0.95
    assert np.nanmax(np.abs(m.temperature_k - truth)) < 0.05
    A, B = GRID.centres()
    P = PLANE.points(A, B)
    C = np.array([v.pose.center for v in views])
    hid = _hidden(C[np.maximum(m.source, 0)], P, lo, hi)
    assert not np.any(hid & ok)  # no cell taken from a view in which the occluder hides it
    assert len(np.unique(m.source[ok])) == 3 and "occlusion" in m.notes
    assert np.all(np.isnan(m.temperature_k[~ok]))


def test_plane_mosaic_without_geometry_says_occluders_are_not_excluded(wall):
    s, views, truth, occ, (lo, hi) = wall
    m = plane_mosaic(views, PLANE, GRID)
    A, B = GRID.centres()
    C = np.array([v.pose.center for v in views])
    hid = _hidden(C[np.maximum(m.source, 0)], PLANE.points(A, B), lo, hi) & (m.source >= 0)
    err = np.abs(m.temperature_k - truth)
    assert hid.sum() > 1000 and np.nanmedian(err[hid]) > 2.0  # the warm column is in the mosaic...
    from scipy.ndimage import binary_dilation

    near = binary_dilation(hid, iterations=3)  # the silhouette's mixed pixels
    assert np.nanmax(err[~near & (m.source >= 0)]) < 0.05  # ...and only there
    assert "not excluded" in m.notes


def test_homography_rectification_and_mosaic(wall, rng):
    s, views, truth, occ, (lo, hi) = wall
    ab = np.array([[1, 1], [11, 1], [11, 6], [1, 6], [6, 3.5], [3, 5]], float)
    fits = []
    for v in views:
        P = PLANE.points(ab[:, 0], ab[:, 1])
        front = v.pose.transform(P)[:, 2] > 0
        xy = v.camera.project(v.pose.transform(P[front]))
        fits.append(fit_facade_homography(ab[front], xy + rng.normal(0, 0.1, xy.shape), camera=v.camera))
    for f in fits:
        assert 0.0 < f.rms_px < 0.3  # 0.1 px noise on 2x(N-4) degrees of freedom
    # the fitted homography reproduces the true projection of the whole wall within a pixel fraction
    A, B = GRID.centres()
    xy_true = views[0].camera.project(views[0].pose.transform(PLANE.points(A, B).reshape(-1, 3))).reshape(A.shape + (2,))
    assert np.nanmax(np.linalg.norm(fits[0].to_pixels(A, B) - xy_true, axis=-1)[::10, ::10]) < 0.3
    m = homography_mosaic([v.image_k for v in views], fits, GRID, names=[v.name for v in views])
    ok = m.source >= 0
    C = np.array([v.pose.center for v in views])
    hid = _hidden(C[np.maximum(m.source, 0)], PLANE.points(A, B), lo, hi) & ok
    err = np.abs(m.temperature_k - truth)
    clean = ok & ~hid
    # away from the occluder's silhouette (2 cells) and the wall's edges (mixed pixels with sky/ground/corner)
    from scipy.ndimage import binary_dilation

    edge = np.zeros_like(ok)
    edge[:4], edge[-4:], edge[:, :4], edge[:, -4:] = True, True, True, True
    clean &= ~binary_dilation(hid, iterations=3) & ~edge
    assert clean.mean() > 0.7 and np.max(err[clean]) < 0.05
    assert m.names == [v.name for v in views] and "not excluded" in m.notes


def test_homography_bad_input():
    with pytest.raises(TooFewPointsError, match="at least 4"):
        fit_facade_homography(np.zeros((3, 2)), np.zeros((3, 2)))
    with pytest.raises(DegenerateInputError, match="collinear"):
        fit_facade_homography([[0, 0], [1, 0], [2, 0], [3, 0]], [[0, 0], [1, 0], [2, 0], [3, 0]])
