"""Tracks by union-find (sfm.tracks): inconsistent tracks split."""

from __future__ import annotations

import numpy as np

from thermogrammetry.sfm.tracks import build_tracks


def _as_sets(tr):
    return sorted(sorted(zip(tr.image[tr.track == t].tolist(), tr.feature[tr.track == t].tolist()))
                  for t in range(tr.n_tracks))


def test_wrong_match_chain_is_split():
    # 0:0 - 1:0 - 2:0 and 0:1 - 2:0: image 0 twice in one track -> its observations dropped, the rest kept
    pairs = [(0, 1, np.array([[0, 0]])), (1, 2, np.array([[0, 0]])), (0, 2, np.array([[1, 0]]))]
    tr = build_tracks([2, 1, 1], pairs)
    assert tr.n_split == 1
    assert _as_sets(tr) == [[(1, 0), (2, 0)]]


def test_triangulation_leaves_out_non_finite_rays():
    """A keypoint whose ray is NaN (outside the domain where the distortion can be inverted) used to make the whole
    batch fail (LinAlgError in eigh: a synthetic low-texture walk, seed 4, stopped the survey). It is left out:
    its track is triangulated from its other rays, a track with no usable ray is NaN, the rest is exact."""
    from thermogrammetry.sfm.reconstruction import triangulate_tracks

    rng = np.random.default_rng(0)
    X = rng.uniform([-2, -2, 8], [2, 2, 12], (5, 3))
    C = np.array([[-1.0, 0, 0], [0, 0.2, 0], [1.0, 0, 0]])
    R = np.repeat(np.eye(3)[None], 3, axis=0)
    t = -C  # cam_from_world with R = I
    track = np.repeat(np.arange(5), 3)
    image = np.tile(np.arange(3), 5)
    pc = X[track] - C[image]
    ray = pc[:, :2] / pc[:, 2:3]
    ray[1] = np.nan  # track 0 keeps two rays
    ray[12:15] = np.nan  # track 4 has none left
    P, ang = triangulate_tracks(np.arange(5), track, R[image], t[image], ray)
    np.testing.assert_allclose(P[:4], X[:4], atol=1e-9)
    assert np.all(np.isnan(P[4])) and np.all(ang[:4] > 1.0)


def test_final_adjustment_leaves_out_points_with_parallel_rays():
    """sfm.georef._parallel_ray_points: twice the largest angle between a ray and the mean ray, against
    MIN_FINAL_TRI_ANGLE_DEG (0.1°). Two cameras 1 m apart looking down +Z; points at 10 m (5.7°), 500 m (0.115°) and
    1000 m (0.057°) depth in the middle, and a point at 10 m seen by one camera only twice (no second centre)."""
    from types import SimpleNamespace

    from thermogrammetry.sfm.georef import MIN_FINAL_TRI_ANGLE_DEG, _parallel_ray_points
    from thermogrammetry.sfm.tracks import Tracks

    assert MIN_FINAL_TRI_ANGLE_DEG == 0.1
    R = np.stack([np.eye(3), np.eye(3)])
    t = np.array([[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0]])  # centres at x = -0.5 and +0.5
    points = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 500.0], [0.0, 0.0, 1000.0], [0.3, 0.0, 10.0]])
    tr = Tracks(np.array([0, 0, 1, 1, 2, 2, 3, 3]), np.array([0, 1, 0, 1, 0, 1, 0, 0]), np.arange(8))
    rec = SimpleNamespace(R=R, t=t, points=points, tracks=tr)
    obs = np.ones(8, bool)
    assert _parallel_ray_points(rec, obs).tolist() == [2, 3]
    obs[4:6] = False  # point 2 without observations is not named
    assert _parallel_ray_points(rec, obs).tolist() == [3]


def test_gnss_collinear_within_its_sigma():
    """sfm.georef._collinear: a line of positions whose scatter across it is the GNSS noise cannot fix the rotation
    about the line (a hand-held walk along a facade with 3 m GNSS); a 40 x 25 m grid with the same GNSS, or two
    flight lines 12 m apart with RTK, can."""
    from thermogrammetry.sfm.georef import _collinear

    rng = np.random.default_rng(0)
    x = np.linspace(0.0, 19.4, 30)
    walk = np.column_stack([x, 0.08 * rng.standard_normal(30), 1.6 + 0.04 * rng.standard_normal(30)])
    sig = np.array([3.0, 3.0, 4.5])
    lines = [_collinear(walk + rng.normal(0.0, 1.0, walk.shape) * sig, sig) for _ in range(50)]
    assert not _collinear(walk + rng.normal(0.0, 1.0, walk.shape) * sig)  # by geometry alone: not a line
    assert all(lines)  # ... but within the positions' σ (0.8-1.25 σ measured over 200 draws, bound 1.5)
    assert _collinear(walk + rng.normal(0.0, 0.03, walk.shape), [0.03, 0.03, 0.05])  # RTK walk: a line (< 2 %)
    grid = np.array([(gx, gy, 30.0) for gy in np.linspace(0, 25, 5) for gx in np.linspace(0, 40, 6)])
    assert not any(_collinear(grid + rng.normal(0.0, 1.0, grid.shape) * [3, 3, 5], [3, 3, 5]) for _ in range(50))
    two_lines = np.vstack([np.column_stack([x * 8, np.zeros(30), np.full(30, 75.0)]),
                           np.column_stack([x * 8, np.full(30, 12.0), np.full(30, 75.0)])])
    assert not _collinear(two_lines + rng.normal(0.0, 0.02, two_lines.shape), [0.02, 0.02, 0.03])
    assert _collinear(two_lines + rng.normal(0.0, 0.02, two_lines.shape), [5.0, 5.0, 5.0])  # 6 m across, σ 5 m
