"""Global orientation (``thermogrammetry.sfm.globalsfm``): rotation averaging, loop filter, rigid parts, centres.

The block: a walk past a wall (16 stations 0.6 m apart, 4 m from it, each camera turned +-15 deg towards its own
spot), 640x512 frames at f = 765 px, points seen by two consecutive frames or by three (15 %), 0.5 px noise and
5 % gross outliers. Tracks that rarely reach a third frame: the incremental orientation needs ten points that two
oriented frames triangulated to add a frame, and stalls.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from thermogrammetry import Camera
from thermogrammetry.sfm.globalsfm import (GlobalOptions, RelativePose, average_rotations, position_cameras,
                                           reconstruct_global, rigid_parts)
from thermogrammetry.sfm.reconstruction import ReconstructionOptions, reconstruct
from thermogrammetry.sfm.tracks import Tracks
from thermogrammetry.errors import ConfigError

CAM = Camera("opencv", (640, 512), dict(fx=765.0, fy=765.0, cx=319.5, cy=255.5))


def _look_at(c, target):
    z = target - c
    z /= np.linalg.norm(z)
    x = np.cross([0, 0, 1.0], z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def _walk(seed, n=16, noise_px=0.5, per_pair=150, outliers=0.05):
    rng = np.random.default_rng(seed)
    C = np.array([[0.6 * k, -4.0 + rng.normal(0, 0.2), 1.5 + rng.normal(0, 0.1)] for k in range(n)])
    R = np.array([_look_at(c, np.array([c[0] + rng.uniform(-2, 2), 0.0, 1.5 + rng.uniform(-0.5, 0.5)])) for c in C])
    t = -np.einsum("nij,nj->ni", R, C)
    track, image, feature, xy, pc = [], [], [], [[] for _ in range(n)], {}
    for i in range(n):
        for j in range(i + 1, min(n, i + 3)):
            for _ in range(per_pair):
                ims = list(range(i, j + 1)) if rng.random() < 0.15 else [i, j]
                mid = 0.5 * (C[i] + C[j])
                X = np.array([mid[0] + rng.uniform(-1.5, 1.5), rng.uniform(-0.3, 0.3), rng.uniform(0.3, 2.7)])
                Xc = np.einsum("aij,j->ai", R[ims], X) + t[ims]
                uv = CAM.project(Xc)
                if (Xc[:, 2] <= 0).any() or not ((uv >= 0).all() and (uv[:, 0] < 640).all() and (uv[:, 1] < 512).all()):
                    continue
                uv = uv + rng.normal(0, noise_px, uv.shape)
                if rng.random() < outliers:
                    uv[-1] = rng.uniform([0, 0], [640, 512])
                tid = len(set(track))
                for a, p in zip(ims, uv):
                    track.append(tid)
                    image.append(a)
                    feature.append(len(xy[a]))
                    xy[a].append(p)
                for p in range(len(ims)):
                    for q in range(p + 1, len(ims)):
                        pc[(ims[p], ims[q])] = pc.get((ims[p], ims[q]), 0) + 1
    return C, R, Tracks(np.array(track), np.array(image), np.array(feature)), [np.array(a) for a in xy], pc


def _angle_deg(R):
    return np.degrees(np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))


def _block_errors(rec, R, C, comp):
    """Relative rotation errors (deg) of every two frames of ``comp`` and centre errors (m) after a similarity."""
    a, b = np.triu_indices(len(comp), 1)
    ia, ib = comp[a], comp[b]
    rot = _angle_deg(np.einsum("nij,nkj,nkl,nml->nim", rec.R[ib], rec.R[ia], R[ia], R[ib]))
    Ce, Ct = rec.centers()[comp], C[comp]
    A, B = Ce - Ce.mean(0), Ct - Ct.mean(0)
    U, S, Vt = np.linalg.svd(B.T @ A)
    D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    s = np.trace(np.diag(S) @ D) / np.sum(A ** 2)
    ce = np.linalg.norm(s * A @ (U @ D @ Vt).T - B, axis=1)
    return rot, ce


@pytest.fixture(scope="module")
def walk():
    return _walk(0)


def test_global_orients_a_walk_the_incremental_orientation_stalls_on(walk):
    C, R, tracks, xy, pc = walk
    inc = reconstruct([CAM], np.zeros(len(C), int), xy, tracks, pc, ReconstructionOptions())
    rec = reconstruct_global([CAM], np.zeros(len(C), int), xy, tracks, pc, ReconstructionOptions())
    assert rec.success, rec.reason
    # measured: incremental 9 frames (blocks of 6 and 3), global 16 (rigid parts of 9 and 7: the walk has a place
    # where no track reaches a third frame and no triangle of pairs has a baseline angle, so the parts cannot be
    # scaled against each other and stay apart; seeds 1 and 2: incremental 3 and 14, global 10 and 16)
    assert int(inc.registered.sum()) <= 10
    assert 14 <= int(rec.registered.sum()) <= 16
    comps = rec.components()
    assert len(comps) >= 2 and all(len(c) >= 4 for c in comps)
    for comp in comps:
        rot, ce = _block_errors(rec, R, C, comp)
        # 0.5 px on 765 px: 0.04 deg per ray; the short bases (0.6 m at 4 m) leave 0.2-0.3 deg (measured medians
        # 0.19 / 0.30 deg, max 0.53 deg); centres 10-15 mm RMS for 0.6 m steps
        assert 0.05 < np.median(rot) < 0.6, np.median(rot)
        assert rot.max() < 1.5
        assert np.sqrt(np.mean(ce ** 2)) < 0.04
    # the observations the adjustment kept fit at the noise level
    ok = rec.obs_valid & rec.registered[tracks.image] & np.isfinite(rec.points[tracks.track]).all(1)
    i = tracks.image[ok]
    uv = CAM.project(np.einsum("nij,nj->ni", rec.R[i], rec.points[tracks.track[ok]]) + rec.t[i])
    meas = np.array([xy[a][f] for a, f in zip(i, tracks.feature[ok])])
    rms = np.sqrt(np.mean(np.sum((uv - meas) ** 2, axis=1)))
    assert 0.3 < rms < 0.8, rms  # 0.5 px per axis: 0.71 px per point minus the adjustment's share
    # a frame left out says why
    for k in np.nonzero(~rec.registered)[0]:
        assert rec.status[k].reason


def test_auto_mapper_keeps_the_larger_block(walk, monkeypatch):
    """``SurveyOptions(mapper="auto")``: global is tried when the incremental's largest block holds < 80 % of the
    frames, and kept only when its own largest block is larger."""
    from thermogrammetry.pipeline import survey as sv
    from thermogrammetry.pipeline.survey import orient as sv_orient  # where _auto_global looks its globals up

    C, R, tracks, xy, pc = walk
    ic = np.zeros(len(C), int)
    inc = reconstruct([CAM], ic, xy, tracks, pc, ReconstructionOptions())
    n_inc = max(len(c) for c in inc.components())
    alone = reconstruct_global([CAM], ic, xy, tracks, pc, ReconstructionOptions())
    rec, used, summary = sv._auto_global(inc, [CAM], ic, xy, tracks, pc, ReconstructionOptions(), None)
    # measured: incremental's largest block 6 of 16, global's 9 (rigid parts of 9 and 7)
    assert n_inc < 0.8 * len(C)
    assert used == "global" and rec is not inc
    assert summary["incremental_largest_block"] == n_inc and summary["images"] == len(C)
    assert summary["global_largest_block"] == max(len(c) for c in rec.components()) > n_inc
    assert summary["incremental_oriented"] == int(inc.registered.sum()) <= summary["global_oriented"]
    assert summary["kept"] == "global" and "mapper auto" in rec.log[0]
    from thermogrammetry.pipeline.survey_report import _mapper_auto_text

    text = _mapper_auto_text(summary)  # the report's clause
    assert f"largest block {n_inc}/16 images" in text and "global kept" in text
    # the same block as the global orientation run on its own: the incremental run changed none of the inputs
    assert np.array_equal(rec.registered, alone.registered)
    assert np.allclose(rec.R[rec.registered], alone.R[alone.registered], rtol=0, atol=1e-12)
    # an incremental block of >= 80 %: global not tried
    monkeypatch.setattr(sv_orient, "AUTO_GLOBAL_BELOW", n_inc / len(C))
    rec2, used2, summary2 = sv._auto_global(inc, [CAM], ic, xy, tracks, pc, ReconstructionOptions(), None)
    assert rec2 is inc and used2 == "incremental" and summary2 is None
    # tried, but no larger: the incremental block stays (a tie too)
    monkeypatch.setattr(sv_orient, "AUTO_GLOBAL_BELOW", 0.8)
    monkeypatch.setattr(sv_orient, "reconstruct_global", lambda *a, **k: inc)
    rec3, used3, summary3 = sv._auto_global(inc, [CAM], ic, xy, tracks, pc, ReconstructionOptions(), None)
    assert rec3 is inc and used3 == "incremental" and summary3["kept"] == "incremental"
    assert "incremental kept" in inc.log[-1]
    # a larger largest block but fewer images in all (the incremental's blocks are each georeferenced with GNSS):
    # the incremental stays
    big = copy.deepcopy(alone)
    first = big.components()[0][:-1]  # (8 of its 9 images: fewer than the incremental's 9 in all)
    big.registered[:] = False
    big.registered[first] = True
    big.component[:] = -1
    big.component[first] = 0
    assert len(first) > n_inc and int(big.registered.sum()) < int(inc.registered.sum())
    monkeypatch.setattr(sv_orient, "reconstruct_global", lambda *a, **k: big)
    rec4, used4, summary4 = sv._auto_global(inc, [CAM], ic, xy, tracks, pc, ReconstructionOptions(), None)
    assert rec4 is inc and used4 == "incremental" and summary4["kept"] == "incremental"


def test_relative_poses_are_refined_on_their_inliers(walk):
    from thermogrammetry.sfm.globalsfm import _exp, refine_relative_pose, relative_poses
    from thermogrammetry.sfm.reconstruction import _Builder

    C, R, tracks, xy, pc = walk
    b = _Builder([CAM], np.zeros(len(C), int), xy, tracks, pc, ReconstructionOptions(), None)
    poses = relative_poses(b, sorted(pc), min_inliers=15)
    rot = np.array([_angle_deg(p.R @ (R[p.j] @ R[p.i].T).T) for p in poses])
    tdir = []
    for p in poses:
        tt = R[p.j] @ (C[p.i] - C[p.j])
        tdir.append(np.degrees(np.arccos(np.clip(p.t @ tt / np.linalg.norm(tt), -1, 1))))
    # measured over 26 pairs (0.5 px noise, 0.6 m bases at 4 m): rotations 0.29 deg median, 0.76 at p90, baseline
    # directions 0.87 / 1.62 deg; straight from the essential matrix (no refinement) 0.74 / 1.64 and 2.11 / 4.12 deg
    assert len(poses) >= 20
    assert 0.15 < np.median(rot) < 0.45 and np.percentile(rot, 90) < 1.1
    assert np.median(tdir) < 1.3
    # exact rays from a start 1 deg / 5 deg off: the truth to the solver's tolerance (measured 1.7e-6 deg)
    rng = np.random.default_rng(0)
    Rt, tt = _exp(np.array([0.05, -0.2, 0.1])), np.array([1.0, 0.1, 0.05])
    X = rng.uniform([-2, -2, 4], [2, 2, 8], (60, 3))
    xi = X[:, :2] / X[:, 2:]
    Xj = X @ Rt.T + tt
    xj = Xj[:, :2] / Xj[:, 2:]
    R1, t1 = refine_relative_pose(_exp(np.radians([0.6, -0.5, 0.6])) @ Rt, tt + np.array([0, 0.08, -0.03]), xi, xj,
                                  scale=1 / 765)
    assert _angle_deg(R1 @ Rt.T) < 1e-4 and np.linalg.norm(t1 - tt / np.linalg.norm(tt)) < 1e-6


def test_rotation_averaging_recovers_rotations_past_a_wrong_pair():
    rng = np.random.default_rng(3)
    from scipy.spatial.transform import Rotation

    n = 12
    Rt = Rotation.random(n, random_state=4).as_matrix()
    edges = np.array([(i, j) for i in range(n) for j in range(i + 1, min(n, i + 4))])
    noise = Rotation.from_rotvec(rng.normal(0, np.radians(0.3) / np.sqrt(3), (len(edges), 3))).as_matrix()
    Rrel = np.einsum("eab,ebc,edc->ead", noise, Rt[edges[:, 1]], Rt[edges[:, 0]])
    bad = 5
    Rrel[bad] = Rotation.from_rotvec([0, np.radians(30), 0]).as_matrix() @ Rrel[bad]
    R, resid, part = average_rotations(n, edges, Rrel, np.full(len(edges), 100.0))
    assert (part == 0).all()
    # the Huber weights keep the wrong pair from dragging the rest: it stands out by its 30 deg (what
    # reconstruct_global drops before it averages again)
    assert int(np.argmax(resid)) == bad and 25 < resid[bad] < 35
    assert np.median(np.delete(resid, bad)) < 0.5
    keep = np.arange(len(edges)) != bad
    R, resid, part = average_rotations(n, edges[keep], Rrel[keep], np.full(int(keep.sum()), 100.0))
    # the estimate is the truth up to one global rotation: compare relative rotations of all frames
    a, b = np.triu_indices(n, 1)
    err = _angle_deg(np.einsum("nij,nkj,nkl,nml->nim", R[b], R[a], Rt[a], Rt[b]))
    assert err.max() < 0.5, err.max()  # 0.3 deg noise per pair, averaged over ~6 pairs per frame
    assert resid.max() < 1.5  # 0.3 deg per pair: the largest of 32 residuals


def test_rigid_parts_keep_two_triangles_that_share_one_frame_apart():
    # frames 0-1-2 and 2-3-4: each triangle of pairs is rigid (three baseline directions), the two share only frame 2
    C = np.array([[0, 0, 0], [1, 0, 0], [0.5, 0.8, 0], [1.5, 1.6, 0], [-0.5, 1.6, 0.1]], float)
    R = np.tile(np.eye(3), (5, 1, 1))
    poses = []
    for i, j in [(0, 1), (0, 2), (1, 2), (2, 3), (2, 4), (3, 4)]:
        d = C[j] - C[i]
        poses.append(RelativePose(i, j, np.eye(3), -(d / np.linalg.norm(d)), np.array([10 * i + j]), np.zeros(1, int),
                                  np.zeros(1, int)))
    part = rigid_parts(5, poses, R, min_triplet_tracks=3, min_triangle_angle_deg=5.0)
    assert part[0] == part[1] and part[3] == part[4] and part[0] != part[3]
    assert part[2] in (part[0], part[3])
    # collinear frames: a triangle of parallel baselines fixes nothing
    C[2] = [2.0, 0, 0]
    for p in poses:
        d = C[p.j] - C[p.i]
        p.t = -(d / np.linalg.norm(d))
    part = rigid_parts(5, poses, R, min_triplet_tracks=3, min_triangle_angle_deg=5.0)
    assert part[2] == part[3] == part[4] == 0  # the one rigid triangle left
    assert part[0] != 0 and part[1] != 0
    # ... unless three tracks run through frames 0, 1 and 2
    for p in poses[:3]:
        p.tracks = np.array([100, 101, 102])
    part = rigid_parts(5, poses, R, min_triplet_tracks=3, min_triangle_angle_deg=5.0)
    assert part[0] == part[1] and part[0] != part[3]


def test_centres_from_exact_rays_are_the_truth_up_to_scale():
    rng = np.random.default_rng(7)
    C = rng.uniform(-2, 2, (6, 3)) * [1, 1, 0.2]
    R = np.array([_look_at(c, np.array([0.0, 0.0, -10.0]) + rng.normal(0, 1, 3)) for c in C])
    X = np.c_[rng.uniform(-4, 4, 60), rng.uniform(-4, 4, 60), rng.uniform(-12, -8, 60)]
    ims = np.repeat(np.arange(6), 60)
    tid = np.tile(np.arange(60), 6)
    Xc = np.einsum("kij,kj->ki", R[ims], X[tid] - C[ims])
    ray = Xc[:, :2] / Xc[:, 2:3]
    Ce, Xe, res = position_cameras(np.arange(6), R, ims, tid, ray)
    A, B = Ce - Ce.mean(0), C - C.mean(0)
    s = np.sum(A * B) / np.sum(A * A)
    np.testing.assert_allclose(s * A, B, atol=1e-8)
    np.testing.assert_allclose(s * (Xe - Ce.mean(0)), X - C.mean(0), atol=1e-7)
    assert res.max() < 1e-5  # degrees: arccos near 1 resolves ~1e-8 rad


def test_global_options_are_checked():
    with pytest.raises(ConfigError, match="min_pair_inliers=3"):
        GlobalOptions(min_pair_inliers=3)
    with pytest.raises(ConfigError, match="unknown"):
        GlobalOptions.from_dict({"max_rotation_residual": 5})


def test_survey_options_carry_the_global_options():
    from thermogrammetry.pipeline.survey import SurveyOptions

    opt = SurveyOptions.from_dict({"mapper": "AUTO", "global_orientation": {"min_pair_inliers": 25}})
    assert opt.mapper == "auto" and opt.global_orientation == GlobalOptions(min_pair_inliers=25)
    assert SurveyOptions().global_orientation == GlobalOptions() and SurveyOptions().mapper == "auto"
    with pytest.raises(ConfigError, match="unknown"):
        SurveyOptions.from_dict({"global_orientation": {"min_inliers": 25}})
