"""Global orientation of an image block: rotation averaging, then camera centres from the tie points' rays.

The incremental scheme (:mod:`thermogrammetry.sfm.reconstruction`) adds an image only when it sees ten or more
points that two already oriented images triangulated: every image needs tracks that span three frames. Frames
taken far apart on a low-texture wall (a hand-held walk past frescoes, 10-50 deg between captures) give verified
pairs whose tracks rarely reach a third frame; the incremental block stops after a few frames while the pairs
would connect most of them. The global scheme uses every verified pair at once:

1. **Relative rotations** of every verified pair: essential matrix (OpenCV USAC MAGSAC++, seeded) on the
   normalised rays of its common tracks, decomposed by the cheirality test, then refined on all its inliers
   (Sampson distances, Huber loss: :func:`refine_relative_pose`).
2. **Rotation averaging**: pairs whose relative rotation closes no triangle of pairs within
   ``max_rotation_residual_deg`` are dropped first (Zach et al. 2010); a maximum spanning tree of the view graph
   (weights: inliers) gives a first rotation per image, refined on all pairs by iteratively reweighted least squares
   in the tangent space (Huber weights, Chatterjee & Govindu 2013); while a pair disagrees with the averaged
   rotations by more than ``max_rotation_residual_deg``, the worst one is dropped and the averaging repeated.
3. **Rigid parts**: two pairs that share an image belong to the same rigid part when enough tracks run through
   all three images, or when the third pair is verified too (a triangle of baseline directions fixes the
   ratio of its sides). Parts that share only an image cannot be scaled against each other: they become separate
   components, never forced together.
4. **Camera centres and points** with the rotations fixed: every observation says that the point lies on the
   ray ``c_i + d v_ik`` (``v_ik`` = the ray in the world frame, ``d >= 1``); centres, points and depths minimise the
   sum of the unsquared deviations (LUD, Özyeşil & Singer 2015, with points as in GLOMAP), by iteratively reweighted
   least squares (:func:`position_cameras`).
5. **Bundle adjustment** on the project's engine (Huber loss, free network), outlier observations removed,
   tracks re-triangulated, adjusted again; images left with too few points are returned as not oriented with
   their reason.

The result is a :class:`~thermogrammetry.sfm.reconstruction.Reconstruction` like the incremental one's (model
frame: first image of each component at the origin, arbitrary scale), which georeferencing takes as it is.

References
----------
Chatterjee, A., Govindu, V. M. (2013). Efficient and robust large-scale rotation averaging. ICCV.
Özyeşil, O., Singer, A. (2015). Robust camera location estimation by convex programming. CVPR.
Zach, C., Klopschitz, M., Pollefeys, M. (2010). Disambiguating visual relations using loop constraints. CVPR.
Pan, L., Baráth, D., Pollefeys, M., Schönberger, J. L. (2024). Global structure-from-motion revisited (GLOMAP). ECCV.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import ConfigError
from ..results import Outcome, Termination
from .._validate import config_keys
from .reconstruction import ImageStatus, Reconstruction, ReconstructionOptions, _Builder, _gather, finish_components
from .tracks import Tracks

__all__ = ["GlobalOptions", "RelativePose", "relative_poses", "refine_relative_pose", "average_rotations", "rigid_parts",
           "position_cameras", "reconstruct_global"]


@dataclass(frozen=True)
class GlobalOptions:
    """What the global orientation keeps (unknown keys refused by :meth:`from_dict`).

    min_pair_inliers : a pair enters the view graph with at least this many essential-matrix inliers
    max_rotation_residual_deg : a pair whose relative rotation disagrees with the averaged rotations by more is dropped
    min_triplet_tracks : two pairs through one image are in one rigid part with this many tracks through all three
    min_triangle_angle_deg : ... or when the third pair is verified and the triangle of baseline directions has no
        angle below this
    min_image_points : an image keeps its orientation with at least this many valid observations after the adjustment
    min_part_images : a rigid part is positioned with at least this many images: a part of three images is one
        triangle of pairs, whose loop check cannot tell a consistently wrong triple (the frescoes' thermal frames: a
        triple 8.9 deg off against the RGB reference; a synthetic ring's triple 32 deg off, refused by georeferencing)
    max_far_ray_share : a rigid part is refused when more than this share of its rays are more than 5 deg from the
        directions to their points after the camera centres were computed: its rotations or tie points do not fit one
        configuration (measured: the M3T flight 0.25 %, the 64-station ring's parts 3.9 % and 2.5 %, the synthetic
        walk 0 %; with the earlier linear positioning the collapsed parts of that ring had 19-21 %)
    """

    min_pair_inliers: int = 15
    max_rotation_residual_deg: float = 5.0
    min_triplet_tracks: int = 3
    min_triangle_angle_deg: float = 5.0
    min_image_points: int = 8
    min_part_images: int = 4
    max_far_ray_share: float = 0.05

    def __post_init__(self):
        if self.min_pair_inliers < 5:
            raise ConfigError(f"GlobalOptions: min_pair_inliers={self.min_pair_inliers!r}: expected >= 5 (the essential "
                              "matrix's minimal sample)")
        if not 0 < self.max_rotation_residual_deg < 90:
            raise ConfigError(f"GlobalOptions: max_rotation_residual_deg={self.max_rotation_residual_deg!r}: expected "
                              "a number in (0, 90)")

    @classmethod
    def from_dict(cls, d: dict) -> "GlobalOptions":
        return cls(**config_keys(cls, d))


@dataclass
class RelativePose:
    """One verified pair's relative orientation: ``x_j = R x_i + t`` in camera coordinates (``|t| = 1``)."""

    i: int
    j: int
    R: np.ndarray
    t: np.ndarray
    tracks: np.ndarray  # (m,) the common tracks that are inliers of its essential matrix
    obs_i: np.ndarray  # (m,) their observations in image i
    obs_j: np.ndarray  # (m,) ... and in image j


# ------------------------------------------------------------------------------------------------
# small SO(3) helpers
# ------------------------------------------------------------------------------------------------
def _log(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def _exp(w: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(w).as_matrix()


# ------------------------------------------------------------------------------------------------
# 1. relative poses
# ------------------------------------------------------------------------------------------------
def relative_poses(b: _Builder, pairs, *, min_inliers: int, threshold_px: float = 1.5, seed: int = 0) -> list[RelativePose]:
    """Relative orientation of every pair from the normalised rays of its common tracks.

    Parameters
    ----------
    b : the incremental builder's lookup tables (rays per image, observations per image)
    pairs : iterable of (i, j), i < j
    min_inliers : pairs with fewer inliers are left out
    threshold_px : RANSAC threshold (px), turned into normalised units by the focal length of image i

    Returns
    -------
    list of RelativePose
    """
    import cv2

    out = []
    for i, j in pairs:
        common, oi, oj = b._shared(i, j)
        if len(common) < min_inliers:
            continue
        ri = b.rays[i][b.tr.feature[oi]]
        rj = b.rays[j][b.tr.feature[oj]]
        fin = np.isfinite(ri).all(1) & np.isfinite(rj).all(1)
        common, oi, oj, ri, rj = common[fin], oi[fin], oj[fin], ri[fin], rj[fin]
        if len(common) < min_inliers:
            continue
        f = float(np.mean(np.diag(b.rec.cameras[b.rec.image_camera[i]].K)[:2]))
        cv2.setRNGSeed(seed)
        E, mask = cv2.findEssentialMat(ri, rj, np.eye(3), method=cv2.USAC_MAGSAC, prob=0.9999, threshold=threshold_px / f)
        if E is None or E.shape != (3, 3):
            continue
        _, R, t, mask2 = cv2.recoverPose(E, ri, rj, np.eye(3), mask=mask.copy())
        m = mask2.ravel() > 0
        if m.sum() < min_inliers:
            continue
        R, t = refine_relative_pose(R, t.ravel(), ri[m], rj[m], scale=1.0 / f)
        out.append(RelativePose(int(i), int(j), R, t, common[m], oi[m], oj[m]))
    return out


def _sampson(R: np.ndarray, t: np.ndarray, ri: np.ndarray, rj: np.ndarray) -> np.ndarray:
    """Sampson distances (normalised image units) of ray pairs under ``E = [t]x R`` (``x_j^T E x_i = 0``)."""
    E = np.cross(t, R.T).T  # [t]x R: column k is t x R[:, k]
    x1 = np.column_stack([ri, np.ones(len(ri))])
    x2 = np.column_stack([rj, np.ones(len(rj))])
    Ex1 = x1 @ E.T
    Etx2 = x2 @ E
    den = np.sqrt(Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2)
    return np.sum(x2 * Ex1, axis=1) / np.maximum(den, 1e-300)


def refine_relative_pose(R: np.ndarray, t: np.ndarray, ri: np.ndarray, rj: np.ndarray, *, scale: float) -> tuple:
    """Relative orientation refined on its inliers: least squares of their Sampson distances with a Huber loss.

    The essential matrix of the RANSAC comes from minimal samples and their consensus; the five parameters (rotation as
    a left increment ``exp([w]x) R``, the baseline direction as a step in the tangent plane of ``t``) are then fitted to
    every inlier. On the synthetic walk of ``tests/test_sfm_global.py`` (0.5 px noise, 25-27 pairs per seed) the pairs'
    rotation errors go from 0.74 / 1.24 / 0.65 deg median (seeds 0-2) to 0.29 / 0.54 / 0.38 deg.

    Parameters
    ----------
    R : (3, 3), t : (3,)
        Start: ``x_j = R x_i + t`` (camera coordinates; ``|t|`` is not used).
    ri, rj : (m, 2) normalised image coordinates of the inliers in image i and j
    scale : float
        Huber threshold in normalised units (1 px / focal length).

    Returns
    -------
    (R (3, 3), t (3,) unit) ; the start (``t`` made unit) when the fit fails.

    References
    ----------
    Hartley, R., Zisserman, A. (2004). Multiple View Geometry in Computer Vision, 2nd ed., §11.4.3 (Sampson error).
    """
    from scipy.optimize import least_squares

    t0 = np.asarray(t, float) / np.linalg.norm(t)
    B = np.linalg.svd(t0[None, :])[2][1:]  # (2, 3): the tangent plane of t0

    def pose(x):
        tt = t0 + x[3:] @ B
        return _exp(x[:3]) @ R, tt / np.linalg.norm(tt)

    def fun(x):
        return _sampson(*pose(x), ri, rj) / scale

    try:
        # (trust-region reflective accepts only steps that lower the cost: the result is never worse than the start)
        res = least_squares(fun, np.zeros(5), loss="huber", f_scale=1.0, method="trf")
    except (ValueError, np.linalg.LinAlgError):
        return R, t0
    if not (res.success and np.all(np.isfinite(res.x))):
        return R, t0
    return pose(res.x)


# ------------------------------------------------------------------------------------------------
# 2. rotation averaging
# ------------------------------------------------------------------------------------------------
def average_rotations(n: int, edges: np.ndarray, R_rel: np.ndarray, weights: np.ndarray, *, huber_deg: float = 2.0,
                      iterations: int = 50) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Absolute rotations from relative ones (``R_rel[e] ≈ R[j] R[i]^T`` for edge ``e = (i, j)``).

    Parameters
    ----------
    n : number of images
    edges : (E, 2) int image pairs
    R_rel : (E, 3, 3) relative rotations (cam_j from cam_i)
    weights : (E,) positive weights (e.g. inlier counts)
    huber_deg : residual (deg) beyond which an edge's weight falls off as 1/residual

    Returns
    -------
    R : (n, 3, 3) cam_from_world rotations (identity for images on no edge); the root of each connected part
        (its best-connected image) keeps the identity
    residual_deg : (E,) angle between each edge's relative rotation and the averaged one
    part : (n,) int, connected part of each image in the view graph (-1: on no edge)
    """
    from scipy.sparse import coo_matrix, identity
    from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
    from scipy.sparse.linalg import spsolve

    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    R = np.tile(np.eye(3), (n, 1, 1))
    part = np.full(n, -1, np.int64)
    if len(edges) == 0:
        return R, np.zeros(0), part
    w = np.asarray(weights, float)
    # spanning tree on 1/weight: the strongest pairs first
    G = coo_matrix((1.0 / w, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()
    T = minimum_spanning_tree(G + G.T)
    T = T + T.T
    ncomp, lab = connected_components(T, directed=False)
    on_edge = np.zeros(n, bool)
    on_edge[edges.ravel()] = True
    lookup = {(int(a), int(b)): k for k, (a, b) in enumerate(edges)}
    strength = np.bincount(edges.ravel(), weights=np.repeat(w, 2), minlength=n)
    roots = []
    for c in range(ncomp):
        members = np.nonzero((lab == c) & on_edge)[0]
        if len(members) == 0:
            continue
        root = int(members[np.argmax(strength[members])])
        roots.append(root)
        part[members] = len(roots) - 1
        order, pred = breadth_first_order(T, root, directed=False)
        for k in order[1:]:
            p = int(pred[k])
            if (p, int(k)) in lookup:
                R[k] = R_rel[lookup[(p, int(k))]] @ R[p]
            else:
                R[k] = R_rel[lookup[(int(k), p)]].T @ R[p]
    # IRLS in the tangent space: R_i <- R_i exp(d_i), d_j - d_i = log(R_j^T R_ij R_i)
    free = np.ones(n, bool)
    free[roots] = False
    free &= on_edge
    col = np.full(n, -1, np.int64)
    col[free] = np.arange(int(free.sum()))
    nf = int(free.sum())
    huber = np.radians(huber_deg)
    i, j = edges[:, 0], edges[:, 1]
    for _ in range(iterations if nf else 0):
        r = _log(np.einsum("eba,ebc,ecd->ead", R[j], R_rel, R[i]))  # (E, 3)
        norm = np.linalg.norm(r, axis=1)
        ww = w * np.minimum(1.0, huber / np.maximum(norm, 1e-12))
        rows, cols, vals = [], [], []
        for node, sign in ((j, 1.0), (i, -1.0)):
            c = col[node]
            ok = c >= 0
            for a in range(3):
                rows.append(3 * np.nonzero(ok)[0] + a)
                cols.append(3 * c[ok] + a)
                vals.append(np.full(int(ok.sum()), sign))
        A = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                       shape=(3 * len(edges), 3 * nf)).tocsr()
        Wd = np.repeat(ww, 3)
        N = (A.T.multiply(Wd) @ A).tocsc()
        g = A.T @ (Wd * r.ravel())
        N = (N + 1e-9 * identity(3 * nf)).tocsc()  # parts made of the root alone leave no singular columns, but keep it safe
        d = np.asarray(spsolve(N, g)).reshape(-1, 3)
        R[free] = np.einsum("nab,nbc->nac", R[free], _exp(d))
        if np.max(np.linalg.norm(d, axis=1)) < 1e-7:
            break
    r = _log(np.einsum("eba,ebc,ecd->ead", R[j], R_rel, R[i]))
    return R, np.degrees(np.linalg.norm(r, axis=1)), part


# ------------------------------------------------------------------------------------------------
# 3. rigid parts
# ------------------------------------------------------------------------------------------------
def rigid_parts(n: int, poses: list[RelativePose], R: np.ndarray, *, min_triplet_tracks: int,
                min_triangle_angle_deg: float) -> np.ndarray:
    """Which images can be scaled against each other: (n,) int part per image (-1: in no part), largest part 0.

    Pairs are the nodes of a graph; two pairs through one image are joined when ``min_triplet_tracks`` tracks run
    through all three images, or when the third pair is in ``poses`` too and the triangle of the three baseline
    directions (world frame, from ``R``) has all angles of at least ``min_triangle_angle_deg``. An image takes the
    part of its pairs with the most pairs.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    E = len(poses)
    if E == 0:
        return np.full(n, -1, np.int64)
    key = {(p.i, p.j): e for e, p in enumerate(poses)}
    # baseline directions c_j - c_i in the world frame: -R_j^T t
    u = np.array([-(R[p.j].T @ p.t) for p in poses])
    by_image: dict[int, list[int]] = {}
    for e, p in enumerate(poses):
        by_image.setdefault(p.i, []).append(e)
        by_image.setdefault(p.j, []).append(e)
    track_sets = [set(p.tracks.tolist()) for p in poses]
    cos_min = np.cos(np.radians(min_triangle_angle_deg))
    ra, rb = [], []
    for img, es in by_image.items():
        for a in range(len(es)):
            for b in range(a + 1, len(es)):
                ea, eb = es[a], es[b]
                pa, pb = poses[ea], poses[eb]
                other_a = pa.j if pa.i == img else pa.i
                other_b = pb.j if pb.i == img else pb.i
                join = len(track_sets[ea] & track_sets[eb]) >= min_triplet_tracks
                if not join:
                    k = key.get((min(other_a, other_b), max(other_a, other_b)))
                    if k is not None:
                        # directions from img to the two others and between them
                        da = u[ea] if pa.i == img else -u[ea]
                        db = u[eb] if pb.i == img else -u[eb]
                        dc = u[k] if poses[k].i == other_a else -u[k]  # from other_a to other_b
                        angs = (da @ db, -da @ dc, db @ dc)  # cosines of the triangle's angles at img, other_a, other_b
                        join = all(c < cos_min for c in angs) and abs(np.linalg.det(np.c_[da, db, dc])) < 0.1
                if join:
                    ra.append(ea)
                    rb.append(eb)
    G = coo_matrix((np.ones(len(ra)), (ra, rb)), shape=(E, E))
    _, lab = connected_components(G, directed=False)
    size_edges = np.bincount(lab)
    part = np.full(n, -1, np.int64)
    best = np.full(n, -1, np.int64)
    for e, p in enumerate(poses):
        for img in (p.i, p.j):
            if size_edges[lab[e]] > best[img]:
                best[img], part[img] = size_edges[lab[e]], lab[e]
    # renumber by images, largest first
    ids = [c for c in np.unique(part) if c >= 0]
    ids.sort(key=lambda c: -int(np.sum(part == c)))
    out = np.full(n, -1, np.int64)
    for k, c in enumerate(ids):
        out[part == c] = k
    return out


# ------------------------------------------------------------------------------------------------
# 4. camera centres from rays with known rotations
# ------------------------------------------------------------------------------------------------
def position_cameras(images: np.ndarray, R: np.ndarray, obs_image: np.ndarray, obs_track: np.ndarray, obs_ray: np.ndarray,
                     *, iterations: int = 100, tolerance: float = 1e-6, polish_iterations: int = 10
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera centres and points from rays when the rotations are known (up to a similarity).

    Least unsquared deviations with points (LUD, Özyeşil & Singer 2015, in the camera-to-point form of GLOMAP):
    ``min sum_k |X_t(k) - c_i(k) - d_k v_k|`` over centres ``c``, points ``X`` and depths ``d_k >= 1`` (``v_k`` = the
    observation's ray in the world frame; the bound fixes the scale and keeps the solution from collapsing onto a
    point, which the plain linear cross-product form does as soon as a few rays are gross). Solved by iteratively
    reweighted least squares (weights ``1 / max(|r_k|, 1e-3)``), alternating between centres + points for fixed
    depths (points eliminated: one weighted graph-Laplacian system on the centres) and the depths. That alternation
    is robust but slow to converge, so it is polished on the rays that agree with it (angle below 3x the median or
    0.5 deg) by least squares with the depths solved jointly through an active set: a free depth is eliminated (the
    part of ``X - c`` across the ray remains), a depth at its bound leaves ``X - c - v``; the points are eliminated
    per track and the centres solved from the reduced 3n x 3n system. The first image is put at the origin.

    Parameters
    ----------
    images : (n,) image indices to position (the first is put at the origin)
    R : (N, 3, 3) cam_from_world rotations of all images
    obs_image, obs_track : (K,) observations (image index in ``R``, track id); each track needs >= 2
    obs_ray : (K, 2) normalised image coordinates

    Returns
    -------
    centres : (n, 3), unit RMS distance from their mean
    points : (T, 3) for ``np.unique(obs_track)``
    residual_deg : (K,) angle between each ray and the direction to its point

    References
    ----------
    Özyeşil, O., Singer, A. (2015). Robust camera location estimation by convex programming. CVPR.
    Pan, L., Baráth, D., Pollefeys, M., Schönberger, J. L. (2024). Global structure-from-motion revisited. ECCV.
    """
    images = np.asarray(images, np.int64)
    n = len(images)
    slot = np.full(int(max(images.max(), obs_image.max())) + 1, -1, np.int64)
    slot[images] = np.arange(n)
    s = slot[obs_image]
    ut, tk = np.unique(obs_track, return_inverse=True)
    T, K = len(ut), len(s)
    v = np.c_[obs_ray, np.ones(K)]
    v = np.einsum("kba,kb->ka", R[obs_image], v)  # world-frame rays R^T [x, y, 1]
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    P = np.eye(3)[None] - np.einsum("ka,kb->kab", v, v)  # across the ray
    # every two observations of a track (tracks are short: a self-join per track length)
    order = np.argsort(tk, kind="stable")
    starts = np.searchsorted(tk[order], np.arange(T + 1))
    lens = np.diff(starts)
    a_idx, b_idx = [], []
    for L in np.unique(lens):
        base = starts[np.nonzero(lens == L)[0]]
        for p in range(L):
            for q in range(L):
                a_idx.append(order[base + p])
                b_idx.append(order[base + q])
    a_idx, b_idx = np.concatenate(a_idx), np.concatenate(b_idx)
    # 1. robust start: L1 by IRLS, alternating between centres + points (depths fixed) and depths
    cell = s[a_idx] * n + s[b_idx]
    diag = s * n + s
    w, d = np.ones(K), np.ones(K)
    C, X = np.zeros((n, 3)), np.zeros((T, 3))
    prev = np.inf
    for _ in range(iterations):
        W = np.bincount(tk, weights=w, minlength=T)
        # sum_k w_k |X_t - c_s - d_k v_k|^2: X_t = mean_w(c_s + d v) eliminated; isotropic, one n x n system
        M = (np.bincount(diag, weights=w, minlength=n * n)
             - np.bincount(cell, weights=w[a_idx] * w[b_idx] / W[tk[a_idx]], minlength=n * n)).reshape(n, n)
        bk = d[:, None] * v
        Bt = np.zeros((T, 3))
        np.add.at(Bt, tk, w[:, None] * bk)
        Bt /= W[:, None]
        g = np.zeros((n, 3))
        np.add.at(g, s, w[:, None] * (Bt[tk] - bk))
        C = np.r_[np.zeros((1, 3)), np.linalg.solve(M[1:, 1:] + 1e-12 * np.eye(n - 1), g[1:])]
        Cm = np.zeros((T, 3))
        np.add.at(Cm, tk, w[:, None] * C[s])
        X = Cm / W[:, None] + Bt
        e = X[tk] - C[s]
        d = np.maximum(1.0, np.einsum("ka,ka->k", e, v))
        r = np.linalg.norm(e - d[:, None] * v, axis=1)
        cost = float(r.sum())
        w = 1.0 / np.maximum(r, 1e-3)
        if abs(prev - cost) <= tolerance * max(cost, 1e-12):
            break
        prev = cost
    # 2. polish on the rays that agree (the alternation converges slowly): least squares with the depths solved
    # jointly -- a free depth eliminated (the part of X - c across the ray), a depth at its bound leaving X - c - v;
    # two rounds, the agreeing rays chosen again with every point intersected from the polished centres
    PA = np.zeros((T, 3, 3))
    np.add.at(PA, tk, P)
    PA_inv = np.linalg.inv(PA + 1e-9 * np.eye(3))
    for _round in range(2 if polish_iterations else 0):
        e = X[tk] - C[s]
        ang = np.arccos(np.clip(np.einsum("ka,ka->k", e, v) / np.maximum(np.linalg.norm(e, axis=1), 1e-300), -1, 1))
        inl = ang < max(3.0 * float(np.median(ang)), np.radians(0.5))
        cnt = np.bincount(tk[inl], minlength=T)
        inl &= cnt[tk] >= 2
        cnt = np.bincount(tk[inl], minlength=T)
        if inl.sum() < 6 or np.bincount(s[inl], minlength=n).min() < 2:
            break
        C, X = _polish(C, X, inl, cnt, P, v, s, tk, a_idx, b_idx, n, T, polish_iterations)
        # every point (also those of rays left out) intersected from the polished centres
        rhs = np.zeros((T, 3))
        np.add.at(rhs, tk, np.einsum("kab,kb->ka", P, C[s]))
        X = np.where((cnt >= 2)[:, None], X, np.einsum("tab,tb->ta", PA_inv, rhs))
    scale = np.sqrt(np.mean(np.sum((C - C.mean(0)) ** 2, axis=1)))
    if scale > 0:
        C, X = C / scale, X / scale
    e = X[tk] - C[s]
    with np.errstate(invalid="ignore", divide="ignore"):
        cosang = np.einsum("ka,ka->k", e, v) / np.linalg.norm(e, axis=1)
    res = np.degrees(np.arccos(np.clip(np.nan_to_num(cosang, nan=-1.0), -1, 1)))
    return C, X, res


def _polish(C, X, inl, cnt, P, v, s, tk, a_idx, b_idx, n, T, iterations):
    """Least squares on the agreeing rays ``inl`` with an active set for the depth bound (see :func:`position_cameras`);
    returns the centres and points (points of tracks without two agreeing rays are left as they were)."""
    w = inl.astype(float)
    # the scale: the nearest agreeing point at depth 1, at its bound (a polish without any bound depth would be
    # scale-free and fall to zero or to the mirror image)
    proj = np.einsum("ka,ka->k", X[tk] - C[s], v)
    k0 = np.nonzero(inl)[0][np.argmin(proj[inl])]
    if proj[k0] > 0:
        C, X = C / proj[k0], X / proj[k0]
    bound = inl & (np.einsum("ka,ka->k", X[tk] - C[s], v) <= 1.0 + 1e-9)
    bound[k0] = True
    for _ in range(iterations):
        Q = np.where(bound[:, None, None], np.eye(3)[None], P) * w[:, None, None]
        bvec = np.where(bound[:, None], v, 0.0)
        A = np.zeros((T, 3, 3))
        np.add.at(A, tk, Q)
        A[cnt < 2] += np.eye(3)  # tracks without two agreeing rays: not used
        Ainv = np.linalg.inv(A)
        Qb = np.einsum("kab,kb->ka", Q, bvec)
        sQb = np.zeros((T, 3))
        np.add.at(sQb, tk, Qb)
        S = np.zeros((n, 3, n, 3))
        np.add.at(S, (s, slice(None), s), Q)
        np.add.at(S, (s[a_idx], slice(None), s[b_idx]), -(Q[a_idx] @ Ainv[tk[a_idx]] @ Q[b_idx]))
        gg = np.zeros((n, 3))
        np.add.at(gg, s, np.einsum("kab,kb->ka", Q @ Ainv[tk], sQb[tk]) - Qb)
        S = S.reshape(3 * n, 3 * n)
        try:
            Cn = np.linalg.solve(S[3:, 3:], gg.ravel()[3:])
        except np.linalg.LinAlgError:
            break
        Cn = np.r_[np.zeros(3), Cn].reshape(n, 3)
        rhs = np.zeros((T, 3))
        np.add.at(rhs, tk, np.einsum("kab,kb->ka", Q, Cn[s]))
        Xn = np.einsum("tab,tb->ta", Ainv, rhs + sQb)
        dn = np.einsum("ka,ka->k", Xn[tk] - Cn[s], v)
        nb = inl & (dn <= 1.0)
        if not nb.any():
            nb[np.nonzero(inl)[0][np.argmin(dn[inl])]] = True
        C, X = Cn, np.where((cnt >= 2)[:, None], Xn, X)
        if np.array_equal(nb, bound):
            break
        bound = nb
    return C, X


# ------------------------------------------------------------------------------------------------
# 5. the whole scheme
# ------------------------------------------------------------------------------------------------
def reconstruct_global(cameras, image_camera, xy_by_image, tracks: Tracks, pair_counts: dict,
                       options: ReconstructionOptions | None = None, global_options: GlobalOptions | None = None,
                       *, on_progress: Callable | None = None) -> Reconstruction:
    """Orient an image block globally (rotation averaging, centres from rays, bundle adjustment).

    Parameters and result as :func:`~thermogrammetry.sfm.reconstruction.reconstruct`; ``options`` gives the
    triangulation and filtering thresholds, the free intrinsics and the seed, ``global_options`` what the view graph
    keeps. ``termination`` is ``degenerate`` with the reason when no rigid part of three or more images is left.
    """
    opt = options or ReconstructionOptions()
    gopt = global_options or GlobalOptions()
    t0 = time.perf_counter()
    b = _Builder(cameras, image_camera, xy_by_image, tracks, pair_counts, opt, None)
    rec = b.rec
    n = b.n
    poses = relative_poses(b, sorted(pair_counts), min_inliers=gopt.min_pair_inliers, seed=opt.seed)
    b.log(f"global: {len(poses)} of {len(pair_counts)} pairs with >= {gopt.min_pair_inliers} essential-matrix inliers")
    poses, n_loop = _loop_filter(poses, gopt.max_rotation_residual_deg)
    b.log(f"global: {n_loop} pairs dropped that close no triangle of pairs within {gopt.max_rotation_residual_deg:g} deg")
    while poses:
        edges = np.array([(p.i, p.j) for p in poses])
        Rrel = np.array([p.R for p in poses])
        wts = np.array([len(p.tracks) for p in poses], float)
        Rabs, resid, _ = average_rotations(n, edges, Rrel, wts)
        worst = int(np.argmax(resid))
        if resid[worst] <= gopt.max_rotation_residual_deg:
            b.log(f"global: rotation averaging over {len(poses)} pairs, residual median {np.median(resid):.2f} deg, "
                  f"max {resid[worst]:.2f} deg")
            break
        poses = poses[:worst] + poses[worst + 1:]  # the worst pair out, then averaged again
    if not poses:
        rec.outcome = Outcome(Termination.DEGENERATE, "global orientation: no pair with a relative orientation")
        no_pose = "no verified pair with a usable relative orientation"
        finish_components(rec, pair_counts, no_pose, no_pose)
        rec.seconds = time.perf_counter() - t0
        return rec
    part = rigid_parts(n, poses, Rabs, min_triplet_tracks=gopt.min_triplet_tracks,
                       min_triangle_angle_deg=gopt.min_triangle_angle_deg)
    # observations that are inliers of a kept pair
    inl = np.zeros(len(tracks.track), bool)
    for p in poses:
        inl[p.obs_i] = True
        inl[p.obs_j] = True
    rec.obs_valid[:] = inl
    comp = 0
    for pid in range(int(part.max()) + 1):
        imgs = np.nonzero(part == pid)[0]
        if len(imgs) < max(opt.min_component_images, gopt.min_part_images):
            for i in imgs:
                rec.status[i] = ImageStatus(False, -1, f"global orientation: in a rigid part of {len(imgs)} images "
                                                       f"(< {gopt.min_part_images}: too few loops to check its pairs)")
            continue
        ok = _position_part(b, imgs, Rabs, comp, opt, gopt)
        if ok:
            comp += 1
        if on_progress:
            on_progress(int(rec.registered.sum()), n)
    comps = finish_components(rec, pair_counts, "not in a rigid part of the view graph (its pairs share too few tracks "
                                                "with a third image, or their rotations disagree)")
    rec.seconds = time.perf_counter() - t0
    if not rec.registered.any():
        rec.outcome = Outcome(Termination.DEGENERATE, "global orientation: no rigid part of "
                              f"{opt.min_component_images} or more images could be positioned")
    else:
        rec.outcome = Outcome(Termination.CONVERGED, f"global orientation: {int(rec.registered.sum())} of {n} images in "
                                                     f"{len(comps)} component(s)")
    return rec


def _loop_filter(poses: list[RelativePose], max_deg: float) -> tuple[list[RelativePose], int]:
    """Pairs whose relative rotation closes no triangle of verified pairs within ``max_deg``: out, and so are pairs
    in no triangle (nothing can check them). A wrong relative orientation (few inliers badly spread, a planar
    scene's twin solution) fits its own matches as well as the right one does, but it rarely closes a loop with two
    others (Zach, Klopschitz & Pollefeys 2010). Returns (kept pairs, number dropped)."""
    key = {(p.i, p.j): p.R for p in poses}
    nb: dict[int, set] = {}
    for p in poses:
        nb.setdefault(p.i, set()).add(p.j)
        nb.setdefault(p.j, set()).add(p.i)

    def rel(a, c):  # cam_c from cam_a
        return key[(a, c)] if (a, c) in key else key[(c, a)].T

    cos_max = np.cos(np.radians(max_deg))
    kept = []
    for p in poses:
        third = nb[p.i] & nb[p.j]
        # closure of i -> j -> k -> i
        if any((np.trace(rel(k, p.i) @ rel(p.j, k) @ p.R) - 1) / 2 >= cos_max for k in third):
            kept.append(p)
    return kept, len(poses) - len(kept)


def _position_part(b: _Builder, imgs: np.ndarray, Rabs: np.ndarray, comp: int, opt: ReconstructionOptions,
                   gopt: GlobalOptions) -> bool:
    """Centres, points and adjustment of one rigid part; registers its images in ``comp``. False when it fails."""
    rec, tr = b.rec, b.tr
    inpart = np.zeros(b.n, bool)
    inpart[imgs] = True
    o = np.nonzero(rec.obs_valid & inpart[tr.image] & ~rec.registered[tr.image])[0]
    rays = _gather(b.rays, tr.image[o], tr.feature[o])
    fin = np.isfinite(rays).all(1)
    o, rays = o[fin], rays[fin]
    cnt = np.bincount(tr.track[o], minlength=tr.n_tracks)
    two = cnt[tr.track[o]] >= 2
    o, rays = o[two], rays[two]
    if len(o) < 20:
        for i in imgs:
            rec.status[i] = ImageStatus(False, -1, "global orientation: its rigid part has too few tie points")
        return False
    # the images that actually have observations left, the best-connected first (the origin)
    per = np.bincount(tr.image[o], minlength=b.n)
    imgs = imgs[per[imgs] > 0]
    imgs = imgs[np.argsort(-per[imgs], kind="stable")]
    C, X, res = position_cameras(imgs, Rabs, tr.image[o], tr.track[o], rays)
    for k, i in enumerate(imgs):
        rec.R[i] = Rabs[i]
        rec.t[i] = -Rabs[i] @ C[k]
        rec.registered[i] = True
        rec.component[i] = comp
    # adjusted on the essential matrices' inliers first; then every observation of the part's
    # frames is tried again with the adjusted camera: the essential matrices judged them on the starting camera
    # (no distortion: 1.5 px excludes the corners of a lens with k1 = -0.35, and an adjustment without them
    # determines neither the distortion nor the focal length well); the reprojection filter (``max_error_px``)
    # and the adjustment's robust loss judge them now
    ut = np.unique(tr.track[o])
    far = res > 5.0
    rec.obs_valid[o[far]] = False
    b.log(f"global: rigid part of {len(imgs)} images positioned from {len(o)} rays on {len(ut)} tracks, "
          f"ray residual median {np.median(res):.2f} deg, {int(far.sum())} above 5 deg")
    if far.mean() > gopt.max_far_ray_share:
        for i in imgs:
            rec.registered[i] = False
            rec.component[i] = -1
            rec.status[i] = ImageStatus(False, -1, f"global orientation: the camera centres of its rigid part of {len(imgs)} "
                                                   f"images leave {far.mean():.0%} of its rays more than 5 deg from their "
                                                   f"points (> {gopt.max_far_ray_share:.0%}): its pairs' rotations or tie "
                                                   "points do not fit one configuration")
        rec.obs_valid[o] = False
        return False
    # the points triangulated anew from the centres and rotations, with the incremental orientation's checks
    # (intersection angle, reprojection error, in front): the positioning's points include tracks of tiny parallax
    # that leave an adjustment undetermined
    b._triangulate(ut, comp)
    b.ba(comp)  # the loose stopping rule of the incremental orientation's intermediate adjustments
    of_part = np.nonzero(inpart[tr.image])[0]
    rec.obs_valid[of_part] = True
    for i in imgs:
        b.exclude_foreign(i, comp)
    b.filter(comp)
    tids = np.unique(tr.track[of_part])
    b._triangulate(tids[~np.isfinite(rec.points[tids]).all(1)], comp)
    for _ in range(3):
        b.ba(comp, full=True)
        members = np.nonzero(rec.registered & (rec.component == comp))[0]
        tids = np.unique(tr.track[np.isin(tr.image, members) & rec.obs_valid])
        b._triangulate(tids[~np.isfinite(rec.points[tids]).all(1)], comp)
        # images left with too few valid observations are not oriented
        valid = rec.obs_valid & np.isfinite(rec.points[tr.track]).all(1)
        nobs = np.bincount(tr.image[valid], minlength=b.n)
        weak = members[nobs[members] < gopt.min_image_points]
        if len(weak) == 0:
            break
        for i in weak:
            rec.registered[i] = False
            rec.component[i] = -1
            rec.status[i] = ImageStatus(False, -1, f"global orientation: {int(nobs[i])} valid tie points after the "
                                                   f"adjustment (< {gopt.min_image_points})")
            rec.obs_valid[b.obs_of_image[i]] = False
    members = np.nonzero(rec.registered & (rec.component == comp))[0]
    if len(members) < opt.min_component_images:
        for i in members:
            rec.registered[i] = False
            rec.component[i] = -1
            rec.status[i] = ImageStatus(False, -1, f"global orientation: its rigid part kept {len(members)} images "
                                                   f"(< {opt.min_component_images})")
        gone = b.point_comp == comp
        rec.points[gone] = np.nan
        b.point_comp[gone] = -1
        return False
    b.log(f"global: component {comp} with {len(members)} images adjusted")
    return True
