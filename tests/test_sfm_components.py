"""Blocks that the incremental orientation keeps apart, and their georeferencing one by one.

Two groups of four cameras see their own points and share six tie points -- too few for a resection across the groups,
so the orientation builds two components, each in its own frame. A point belongs to the component whose images
triangulated it: another component's images must not use it (their frames differ), and a block's similarity to the
GNSS must move only its own points. Exact projections, no noise: every figure below is decided by the geometry.
"""

from __future__ import annotations

import numpy as np

from thermogrammetry import Camera
from thermogrammetry.geometry import Similarity
from thermogrammetry.sfm.georef import apply_similarity, gnss_consensus
from thermogrammetry.sfm.reconstruction import ReconstructionOptions, reconstruct
from thermogrammetry.sfm.tracks import Tracks

CAM = Camera("opencv", (640, 480), dict(fx=500.0, fy=500.0, cx=319.5, cy=239.5))


def _two_groups(seed=0):
    rng = np.random.default_rng(seed)
    centers = np.array([[0, 0, 0], [1.2, 0.1, 0], [2.4, -0.1, 0], [3.6, 0, 0],
                        [30, 0, 0], [31.2, 0.1, 0], [32.4, -0.1, 0], [33.6, 0, 0]], float)
    R = np.tile(np.eye(3), (8, 1, 1))  # all look along +Z
    t = -np.einsum("nij,nj->ni", R, centers)
    own_a = np.c_[rng.uniform(-2, 6, 120), rng.uniform(-2.5, 2.5, 120), rng.uniform(8, 14, 120)]
    own_b = own_a + [30, 0, 0]
    shared = np.c_[rng.uniform(15, 19, 6), rng.uniform(-1, 1, 6), rng.uniform(40, 60, 6)]  # far: seen by all eight
    pts = np.vstack([own_a, own_b, shared])
    seen = [list(range(4))] * 120 + [list(range(4, 8))] * 120 + [list(range(8))] * 6
    track, image, feature, xy = [], [], [], [[] for _ in range(8)]
    for k, (X, ims) in enumerate(zip(pts, seen)):
        for i in ims:
            uv = CAM.project((R[i] @ X + t[i])[None])[0]
            track.append(k)
            image.append(i)
            feature.append(len(xy[i]))
            xy[i].append(uv)
    tracks = Tracks(np.array(track), np.array(image), np.array(feature))
    pairs = {}
    for i in range(8):
        for j in range(i + 1, 8):
            pairs[(i, j)] = 120 + 6 if (i < 4) == (j < 4) else 6
    return centers, R, t, pts, tracks, [np.array(a) for a in xy], pairs


def test_components_never_share_points():
    centers, R, t, pts, tracks, xy, pairs = _two_groups()
    rec = reconstruct([CAM], np.zeros(8, int), xy, tracks, pairs, ReconstructionOptions())
    assert rec.registered.all()
    comps = rec.components()
    assert sorted(len(c) for c in comps) == [4, 4]  # six shared points (< 10 for a resection): two blocks
    comp_of = np.where(rec.registered, rec.component, -1)
    c_obs = comp_of[tracks.image]
    ok = rec.obs_valid & np.isfinite(rec.points[tracks.track]).all(1)
    # no point has used observations in two components (it is in one component's frame)
    for k in range(len(pts)):
        assert len(set(c_obs[ok & (tracks.track == k)])) <= 1, k
    # and every used observation fits its point in its own component's frame (exact data: far below a pixel)
    i = tracks.image[ok]
    Xc = np.einsum("nij,nj->ni", rec.R[i], rec.points[tracks.track[ok]]) + rec.t[i]
    uv = CAM.project(Xc)
    meas = np.array([xy[a][f] for a, f in zip(i, tracks.feature[ok])])
    assert np.max(np.linalg.norm(uv - meas, axis=1)) < 0.01


def test_a_block_similarity_moves_only_that_block():
    centers, R, t, pts, tracks, xy, pairs = _two_groups()
    rec = reconstruct([CAM], np.zeros(8, int), xy, tracks, pairs, ReconstructionOptions())
    a, b = rec.components()
    before = rec.points.copy()
    S = Similarity(2.0, np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), np.array([100.0, 5.0, -3.0]))
    apply_similarity(rec, a, S)
    ok = rec.obs_valid & np.isfinite(before[tracks.track]).all(1)
    of_b = np.unique(tracks.track[ok & np.isin(tracks.image, b)])
    of_a = np.unique(tracks.track[ok & np.isin(tracks.image, a)])
    assert len(of_a) >= 100 and len(of_b) >= 100
    np.testing.assert_array_equal(rec.points[of_b], before[of_b])  # the other block's points did not move
    np.testing.assert_allclose(rec.points[of_a], S(before[of_a]), atol=1e-9)


def test_gnss_consensus_finds_the_wrongly_placed_images():
    rng = np.random.default_rng(3)
    ang = np.radians(np.arange(20) * 9.0)
    G = np.c_[9 * np.cos(ang), 9 * np.sin(ang), np.full(20, 1.7)] + [2_600_000.0, 1_200_000.0, 450.0]
    sig = np.tile([0.03, 0.03, 0.05], (20, 1))
    S = Similarity(0.37, np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]]), np.array([1.0, 2.0, 3.0]))
    # the block in its model frame, S(C) = G + the GNSS noise; rows: R^T x = x @ R
    C = ((G + rng.normal(0, 0.03, G.shape)) - S.translation) @ S.R / S.scale
    C[[0, 1, 2]] += np.array([[7.0, 0, 0], [0, 3.5, 0], [0, 0, 1.2]]) @ S.R / S.scale  # three wrong resections
    cons = gnss_consensus(C, G, sig)
    assert cons is not None
    np.testing.assert_array_equal(np.nonzero(~cons.inliers)[0], [0, 1, 2])
    # tolerance: 6 % of the positions' spread (9 m ring of 171 deg: ~6.4 m RMS) -> ~0.39 m, above 5 σ (0.15 m)
    assert 0.3 < cons.tolerance_m < 0.5
    np.testing.assert_allclose(cons.residuals_m[[0, 1, 2]], [7.0, 3.5, 1.2], rtol=0.1)
    assert np.max(cons.residuals_m[3:]) < 0.15  # 3 cm noise on 17 positions
    # deterministic, and no verdict from fewer than 4 positions
    np.testing.assert_array_equal(gnss_consensus(C, G, sig).inliers, cons.inliers)
    assert gnss_consensus(C[:3], G[:3], sig[:3]) is None
