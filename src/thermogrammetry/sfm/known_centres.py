"""Images with a known camera centre (GNSS) added to a georeferenced block: a rotation-only resection from the
directions to the block's points, then their tracks triangulated with the block (re-exported by
:mod:`thermogrammetry.sfm.reconstruction`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..geometry.rotations import nearest_rotation

if TYPE_CHECKING:
    from .reconstruction import Reconstruction, ReconstructionOptions

__all__ = ["MIN_CENTRE_RESECTION_POINTS", "rotation_from_directions", "register_with_known_centres"]


#: rotation-only resection: at least this many inlier 2D-3D correspondences (PnP needs ``min_pnp_points``; with the
#: centre known three unknowns are left)
MIN_CENTRE_RESECTION_POINTS = 6


def rotation_from_directions(b: np.ndarray, a: np.ndarray, threshold_rad: float, *, seed: int = 0,
                             max_samples: int = 2000) -> tuple[np.ndarray | None, np.ndarray]:
    """Camera rotation from directions known in both frames: ``b_k ≈ R a_k`` (a resection with a known centre).

    Two-point RANSAC (every pair when there are at most ``max_samples`` of them, else a seeded sample), the
    rotation of each sample from its two directions and their cross product
    (:func:`~thermogrammetry.geometry.rotations.nearest_rotation`, Kabsch), refined on the inliers.

    Parameters
    ----------
    b : (K, 3) unit rays in the camera frame (from the image points)
    a : (K, 3) unit directions from the known centre to the 3D points, world frame
    threshold_rad : an inlier's angle between ``b_k`` and ``R a_k``

    Returns
    -------
    R : (3, 3) cam_from_world rotation or None (fewer than 2 directions, or all samples degenerate)
    inliers : (K,) bool
    """
    K = len(b)
    if K < 2:
        return None, np.zeros(K, bool)
    i, j = np.triu_indices(K, 1)
    if len(i) > max_samples:
        pick = np.random.default_rng(seed).choice(len(i), max_samples, replace=False)
        i, j = i[np.sort(pick)], j[np.sort(pick)]
    ca = np.cross(a[i], a[j])
    cb = np.cross(b[i], b[j])
    na, nb = np.linalg.norm(ca, axis=1), np.linalg.norm(cb, axis=1)
    ok = (na > np.sin(np.radians(1.0))) & (nb > np.sin(np.radians(1.0)))  # the two directions must not be parallel
    if not ok.any():
        return None, np.zeros(K, bool)
    i, j, ca, cb, na, nb = i[ok], j[ok], ca[ok], cb[ok], na[ok], nb[ok]
    A = np.stack([a[i], a[j], ca / na[:, None]], axis=1)  # (S, 3, 3) rows
    B = np.stack([b[i], b[j], cb / nb[:, None]], axis=1)
    Rs = nearest_rotation(np.einsum("sik,sil->skl", B, A))
    cos_thr = np.cos(threshold_rad)
    # inlier counts of every sample, in chunks of samples (K x S dot products)
    best, best_n = -1, -1
    for s0 in range(0, len(Rs), 256):
        Ra = np.einsum("skl,nl->snk", Rs[s0:s0 + 256], a)
        n_in = (np.einsum("snk,nk->sn", Ra, b) >= cos_thr).sum(axis=1)
        k = int(np.argmax(n_in))
        if n_in[k] > best_n:
            best, best_n = s0 + k, int(n_in[k])
    R = Rs[best]
    inl = (np.einsum("nk,nk->n", a @ R.T, b) >= cos_thr)
    for _ in range(3):  # refine on the inliers, then take the inliers of the refined rotation
        if inl.sum() < 2:
            break
        R = nearest_rotation(b[inl].T @ a[inl])
        new = (np.einsum("nk,nk->n", a @ R.T, b) >= cos_thr)
        if np.array_equal(new, inl):
            break
        inl = new
    return R, inl


def register_with_known_centres(rec: Reconstruction, xy_by_image, block_images, centres, candidates, *,
                                options: ReconstructionOptions | None = None) -> tuple[np.ndarray, dict]:
    """Add images whose camera centre is known (GNSS, in the block's frame) to an oriented block.

    An image whose tie points reach too few of the block's points for a resection (``min_pnp_points``) can still
    be oriented when its centre is known: three unknowns are left, fixed by the directions to
    :data:`MIN_CENTRE_RESECTION_POINTS` or more points (:func:`rotation_from_directions`, threshold
    ``max_error_px``). Its tracks are then triangulated with the block (as in the incremental orientation), which
    may give the next image enough points: images at the end of a chain (a ring's stations behind an occluder, the
    last frames of a facade pass) are added one after the other, the best-connected first. The caller adjusts the
    block again with them (GNSS priors, robust loss) and judges the result.

    Parameters
    ----------
    rec : Reconstruction, the block georeferenced (points and poses in the frame of ``centres``)
    block_images : image indices of the block (registered, one component)
    centres : (n, 3) known camera centres (NaN rows: unknown)
    candidates : image indices that may be added (unregistered)

    Returns
    -------
    added : (m,) image indices in the order they were added
    why : dict image -> reason for each candidate that was tried and not added
    """
    from .reconstruction import ImageStatus, ReconstructionOptions, _Builder  # (it re-exports this module)

    opt = options or ReconstructionOptions()
    block_images = np.asarray(block_images, np.int64)
    comp = int(rec.component[block_images[0]])
    tr = rec.tracks
    b = _Builder.around(rec, xy_by_image, opt)
    cand = [int(i) for i in candidates if not rec.registered[i] and np.isfinite(centres[i]).all()]
    added: list[int] = []
    why: dict[int, str] = {}
    while cand:
        best = None
        for i in cand:
            o = b.obs_of_image[i]
            t = tr.track[o]
            o = o[(b.point_comp[t] == comp) & np.isfinite(rec.points[t]).all(1)
                  & np.isfinite(b.rays[i][tr.feature[o]]).all(1)]
            if len(o) < MIN_CENTRE_RESECTION_POINTS:
                why[i] = f"sees {len(o)} of the block's points (< {MIN_CENTRE_RESECTION_POINTS} with its GNSS centre)"
                continue
            if best is None or len(o) > len(best[1]):
                best = (i, o)
        if best is None:
            break
        i, o = best
        cand.remove(i)
        cam = rec.cameras[rec.image_camera[i]]
        f = float(np.mean(np.diag(cam.K)[:2]))
        r = b.rays[i][tr.feature[o]]
        bvec = np.c_[r, np.ones(len(r))]
        bvec /= np.linalg.norm(bvec, axis=1, keepdims=True)
        d = rec.points[tr.track[o]] - centres[i]
        a = d / np.linalg.norm(d, axis=1, keepdims=True)
        R, inl = rotation_from_directions(bvec, a, opt.max_error_px / f, seed=opt.seed + i)
        n_in = int(inl.sum())
        if R is None or n_in < MIN_CENTRE_RESECTION_POINTS or n_in < opt.min_pnp_inlier_ratio * len(o):
            why[i] = f"rotation at its GNSS centre: {n_in} inliers of {len(o)} directions to the block's points"
            continue
        xy_in = xy_by_image[i][tr.feature[o[inl]]]
        w, h = cam.image_size
        if np.ptp(xy_in[:, 0]) < 0.1 * w and np.ptp(xy_in[:, 1]) < 0.1 * h:
            why[i] = f"its {n_in} points with the block lie within 10 % of the frame: the rotation is not determined"
            continue
        rec.R[i], rec.t[i] = R, -R @ centres[i]
        rec.registered[i] = True
        rec.component[i] = comp
        rec.status[i] = ImageStatus(True, comp, "")
        rec.obs_valid[o[~inl]] = False
        b.triangulate_image(i, comp)
        added.append(i)
        why.pop(i, None)
    return np.asarray(added, np.int64), why
