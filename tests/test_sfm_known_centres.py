"""Images with a known camera centre (RTK GNSS) added to an oriented block by rotation-only resection
(``sfm.reconstruction.rotation_from_directions`` and ``register_with_known_centres``)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from thermogrammetry.camera import Camera
from thermogrammetry.results import Outcome, Termination
from thermogrammetry.sfm.reconstruction import (ImageStatus, Reconstruction, register_with_known_centres,
                                                rotation_from_directions)
from thermogrammetry.sfm.tracks import Tracks


def _deg(R1, R2):
    return float(np.degrees(Rotation.from_matrix(R1 @ R2.T).magnitude()))


def test_rotation_from_directions_with_outliers_and_degenerate_input():
    rng = np.random.default_rng(0)
    R = Rotation.from_rotvec([0.3, -1.1, 0.4]).as_matrix()
    a = rng.normal(size=(30, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = a @ R.T + rng.normal(0, 0.2 / 500, (30, 3))  # 0.2 px at f = 500 px
    b[:9] = rng.normal(size=(9, 3))  # 30 % outliers
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    Rh, inl = rotation_from_directions(b, a, 2.0 / 500)
    assert _deg(Rh, R) < 0.05  # noise 0.2 px over ~90 deg of directions: ~0.005 deg
    assert not inl[:9].any() and inl[9:].all()
    R2, inl2 = rotation_from_directions(b, a, 2.0 / 500)
    assert np.array_equal(R2, Rh) and np.array_equal(inl2, inl)  # deterministic
    # one direction, or all directions parallel: no rotation
    assert rotation_from_directions(b[:1], a[:1], 0.01)[0] is None
    par = np.repeat(a[:1], 5, axis=0)
    assert rotation_from_directions(par @ R.T, par, 0.01)[0] is None


def _chain_block(noise_px=0.2, seed=1):
    """Cameras 0-3 oriented (x = 0..6 m, looking at a wall 10 m away); cameras 4-6 continue the line but share
    only 8 observations (2 of them wrong) with the block's points: too few for PnP (10); camera 7 sees nothing of
    the wall the block sees."""
    rng = np.random.default_rng(seed)
    cam = Camera("opencv", (640, 480), {"fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 239.5})
    gx, gy = np.meshgrid(np.arange(-6.0, 24.01, 0.5), np.arange(-3.0, 3.01, 1.0))
    X = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, 10.0)]
    C = np.array([[2.0 * k, 0.1 * np.sin(k), 0.05 * k] for k in range(7)] + [[60.0, 0.0, 0.0]])
    Rt = [Rotation.from_rotvec(rng.normal(0, 0.02, 3)).as_matrix() for _ in C]
    n = len(C)
    obs = []
    for k in range(n):
        Xc = (X - C[k]) @ Rt[k].T
        uv = cam.project(Xc)
        inside = (Xc[:, 2] > 0) & np.all((uv >= 0) & (uv < [640, 480]), axis=1)
        obs.append((np.nonzero(inside)[0], uv[inside] + rng.normal(0, noise_px, (int(inside.sum()), 2))))
    seen_block = np.zeros(len(X), int)
    for k in range(4):
        seen_block[obs[k][0]] += 1
    block_pt = seen_block >= 2
    # cameras 4-6: no observation of the block's points but 8 of camera 4's (2 of them moved by 40 px)
    for k in (4, 5, 6):
        p, uv = obs[k]
        keep = ~block_pt[p]
        if k == 4:
            keep[np.nonzero(block_pt[p])[0][::6][:8]] = True
        p, uv = p[keep], uv[keep].copy()
        if k == 4:
            w = np.nonzero(block_pt[p])[0][:2]
            uv[w] += 40.0
        obs[k] = (p, uv)
    track, image, feature, xy = [], [], [], []
    for k, (p, uv) in enumerate(obs):
        track += p.tolist()
        image += [k] * len(p)
        feature += list(range(len(p)))
        xy.append(uv)
    o = np.lexsort((np.array(image), np.array(track)))
    tr = Tracks(np.array(track)[o], np.array(image)[o], np.array(feature)[o])
    reg = np.arange(n) < 4
    R = np.stack(Rt)
    t = -np.einsum("nij,nj->ni", R, C)
    pts = np.where(block_pt[:, None], X, np.nan)
    rec = Reconstruction(Outcome(Termination.CONVERGED), [cam], np.zeros(n, np.int64), np.where(reg[:, None, None], R, np.eye(3)),
                         np.where(reg[:, None], t, 0.0), reg.copy(), np.where(reg, 0, -1), pts, tr,
                         np.ones(len(tr.track), bool), [ImageStatus(bool(r), 0 if r else -1, "") for r in reg])
    return rec, xy, C, R, X


def test_images_at_the_end_of_a_chain_are_added_one_after_the_other():
    rec, xy, C, R, X = _chain_block()
    added, why = register_with_known_centres(rec, xy, np.arange(4), C, np.arange(4, 8))
    # camera 4 from its 8 (6 right) observations of the block; then 5 and 6 from the points camera 4 triangulated
    assert added[0] == 4 and sorted(added.tolist()) == [4, 5, 6]
    assert all(rec.registered[k] and rec.component[k] == 0 for k in (4, 5, 6))
    err = [_deg(rec.R[k], R[k]) for k in (4, 5, 6)]
    # 0.2 px noise (0.023 deg per ray): camera 4 from 6 of the block's points, measured 0.016 deg; cameras 5 and 6
    # from points that camera 4 and the block triangulated over a 2 m base at 10 m (depth σ ~3 cm): 0.07 / 0.11 deg
    assert err[0] < 0.05 and max(err[1:]) < 0.3, err
    assert np.allclose(-np.einsum("ji,j->i", rec.R[5], rec.t[5]), C[5])  # the centre is the known one
    assert 7 in why and "sees 0" in why[7] and not rec.registered[7]
    # camera 4's two wrong observations are no longer used
    o4 = np.nonzero(rec.tracks.image == 4)[0]
    assert (~rec.obs_valid[o4]).sum() == 2
    # new points were triangulated where two registered cameras see them (2 m base at 10 m, 0.2 px: depth σ ~3 cm)
    new = np.isfinite(rec.points).all(axis=1) & (X[:, 0] > 10.4)
    e = np.linalg.norm(rec.points[new] - X[new], axis=1)
    assert new.sum() > 50 and np.sqrt(np.mean(e**2)) < 0.05 and e.max() < 0.15  # measured RMS ~0.03, max 0.085 m


def test_no_centre_or_too_few_points_adds_nothing():
    rec, xy, C, R, X = _chain_block()
    C2 = C.copy()
    C2[4] = np.nan  # camera 4 without GNSS: the chain cannot start
    added, why = register_with_known_centres(rec, xy, np.arange(4), C2, np.arange(4, 8))
    assert len(added) == 0 and not rec.registered[4:].any()
    assert 4 not in why  # not a candidate (no centre)


def test_nearest_rotation_is_the_kabsch_rotation_batched_or_not():
    from thermogrammetry.geometry.rotations import mean_rotation, nearest_rotation

    rng = np.random.default_rng(5)
    R = Rotation.from_rotvec(rng.normal(size=(4, 3))).as_matrix()
    a = rng.normal(size=(4, 10, 3))
    M = np.einsum("sij,skj,skl->sil", R, a, a)  # sum_k (R a_k) a_k^T
    Rb = nearest_rotation(M)
    assert np.allclose(Rb, R, atol=1e-12) and np.allclose(nearest_rotation(M[1]), R[1], atol=1e-12)
    # a reflection is never returned
    F = np.diag([1.0, 1.0, -1.0])
    assert np.isclose(np.linalg.det(nearest_rotation(F)), 1.0)
    assert np.allclose(mean_rotation(np.stack([R[0], R[0]])), R[0], atol=1e-12)
