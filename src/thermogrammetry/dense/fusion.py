"""Pair selection, depth maps of a reference image and their multi-view fusion.

For a reference image ``i`` the neighbours ``j`` are ranked by a quarter-resolution match of the rectified
pair (:func:`.stereo.disparity_range`): the coarse valid fraction is the overlap and the coarse median depth
gives the base/height ratio ``B/H``. Pairs with ``B/H`` in ``[min_bh, max_bh]`` and overlap ≥ ``min_overlap``
are scored ``overlap · min(1, (B/H) / bh_target)`` (a wider base is more precise up to ``bh_target``,
beyond it the images differ too much); the ranking is greedy with diversity (a partner whose baseline
points within 45° of a better partner's has its score halved: it covers the same part of the reference
image); the best ``pairs_per_image`` are matched at full resolution.

Each pair's disparity gives a depth map in the reference image's own pixel grid (the rectified disparity
is sampled at the rectified position of every original pixel). Fusion keeps a pixel where at least
``min_consistent`` pair depths agree within their own precision ``σ_Z = Z² σ_d / (f B)`` (k = 2.5, σ_d =
``sigma_disparity_px``), i.e. the point is seen consistently in at least ``min_consistent + 1`` views
(geometric consistency across ≥ 3 views by default); the fused depth is the precision-weighted mean of the
agreeing depths. Pixels within ``edge_px`` of a depth jump larger than ``edge_jump`` × depth are dropped
(SGBM's block fattening of foreground edges); other images see those surfaces from a better angle.
Thinning: a point is kept only by the ``keep_nearest`` reference images whose centres are horizontally
nearest to it.

References
----------
Khodaei et al. (seed 003): multi-resolution dense matching and DSM generation from UAV thermal frames.
Schönberger J.L., Zheng E., Pollefeys M., Frahm J.-M. (2016), Pixelwise view selection for unstructured
multi-view stereo (geometric consistency filtering).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DegenerateInputError
from .rectify import _mul, rectify_pair, remap_frame
from .stereo import disparity, disparity_range
from .._validate import config_keys

__all__ = ["DenseConfig", "PairCandidate", "rank_pairs", "pair_depth", "fuse_depths", "reference_points",
           "POINT_DTYPE"]

POINT_DTYPE = np.dtype([("x", "f8"), ("y", "f8"), ("z", "f8"), ("value", "f4"), ("nx", "f4"), ("ny", "f4"),
                        ("nz", "f4"), ("views", "u1"), ("source", "i4")])


@dataclass(frozen=True)
class DenseConfig:
    """Options of dense matching (typed; unknown keys are errors in :meth:`from_dict`)."""

    pairs_per_image: int = 8
    candidates: int = 10
    min_bh: float = 0.05
    max_bh: float = 0.8
    bh_target: float = 0.3
    min_overlap: float = 0.3
    min_consistent: int = 2
    sigma_disparity_px: float = 0.5
    block_size: int = 5
    stride_px: int = 1
    keep_nearest: int = 3
    edge_jump: float = 0.01
    edge_px: int = 2
    max_angle_deg: float = 30.0

    @classmethod
    def from_dict(cls, d) -> "DenseConfig":
        return cls(**config_keys(cls, d))


@dataclass
class PairCandidate:
    j: int
    overlap: float
    bh: float
    depth_m: float
    score: float
    disparity_min: int
    disparity_num: int
    rectified: object = None  # the RectifiedPair (reused by pair_depth)


_RAYS: dict = {}


def pixel_rays(cam) -> np.ndarray:
    """(H·W, 3) camera-frame rays (z = 1) of every pixel centre of ``cam`` (cached per camera)."""
    key = (id(cam), cam.image_size)
    if key not in _RAYS:
        if len(_RAYS) > 4:
            _RAYS.clear()
        w, h = cam.image_size
        u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
        _RAYS[key] = (cam, np.asarray(cam.unproject(np.column_stack([u.ravel(), v.ravel()])), float))
    return _RAYS[key][1]


def _as_float(frame) -> np.ndarray:
    a = np.asarray(frame)
    if a.ndim == 3:
        a = a[..., :3].astype(np.float32).mean(axis=2)
    return a.astype(np.float32)


def rank_pairs(i, cameras, poses, frames, config: DenseConfig | None = None) -> list[PairCandidate]:
    """Candidate partners of image ``i`` ranked by the documented score (module docstring).

    Parameters
    ----------
    i : index of the reference image
    cameras : list of Camera per image; poses : list of (R, t); frames : callable index -> (H, W) frame
    """
    cfg = config or DenseConfig()
    C = np.array([-R.T @ t for R, t in poses])
    ax = np.array([R[2] for R, _ in poses])
    dist = np.linalg.norm(C - C[i], axis=1)
    dist[i] = np.inf
    order = [j for j in np.argsort(dist, kind="stable")
             if np.isfinite(dist[j]) and np.degrees(np.arccos(np.clip(ax[i] @ ax[j], -1, 1))) < cfg.max_angle_deg]
    out = []
    fi = _as_float(frames(i))
    for j in order[: cfg.candidates]:
        try:
            rp = rectify_pair(cameras[i], *poses[i], cameras[j], *poses[j])
        except DegenerateInputError:
            continue
        L = remap_frame(fi, rp.map_left)
        R = remap_frame(_as_float(frames(j)), rp.map_right)
        off = rp.cx_left - rp.cx_right  # raw disparity at infinite depth
        rng = disparity_range(L, R, min_disparity=int(np.floor(off)), max_disparity=int(np.floor(off)) + rp.size[0] // 2)
        if rng is None:
            continue
        mn, num, frac = rng
        dmid = mn + num / 2.0
        Z = float(rp.depth_from_disparity(np.array([dmid]))[0])
        if not np.isfinite(Z):
            continue
        bh = rp.baseline_m / Z
        if not (cfg.min_bh <= bh <= cfg.max_bh) or frac < cfg.min_overlap:
            continue
        out.append(PairCandidate(int(j), frac, bh, Z, frac * min(1.0, bh / cfg.bh_target), 0, num, rp.shifted(mn)))
    out.sort(key=lambda p: (-p.score, p.j))
    # diversity: a partner whose baseline points the same way (within 45°) as a better one covers the same
    # part of the reference image; its score is halved before the final ranking
    chosen, rest = [], list(out)
    while rest:
        def adj(p):
            b = C[p.j] - C[i]
            same = any(np.dot(b, C[q.j] - C[i]) > np.cos(np.pi / 4) * np.linalg.norm(b) * np.linalg.norm(C[q.j] - C[i])
                       for q in chosen)
            return p.score * (0.5 if same else 1.0)
        best = max(rest, key=lambda p: (adj(p), -p.j))
        chosen.append(best)
        rest.remove(best)
    return chosen


def pair_depth(i, j, cameras, poses, frames, *, min_disparity: int, num_disparities: int,
               config: DenseConfig | None = None, rectified=None) -> tuple[np.ndarray, np.ndarray]:
    """Depth map of image ``i`` from the pair (i, j) in ``i``'s original pixel grid.

    Returns
    -------
    depth : (H, W) float64, camera-``i`` z (m), NaN where unmatched
    sigma : (H, W) float64, its precision σ_Z = Z² σ_d / (f B) (m)
    """
    cfg = config or DenseConfig()
    cam = cameras[i]
    rp = rectified if rectified is not None else rectify_pair(cam, *poses[i], cameras[j], *poses[j])
    L = remap_frame(_as_float(frames(i)), rp.map_left)
    R = remap_frame(_as_float(frames(j)), rp.map_right)
    d = disparity(L, R, min_disparity, num_disparities, block_size=cfg.block_size)
    w, h = cam.image_size
    Ri, ti = poses[i]
    rays_cam = pixel_rays(cam)
    rays_world = _mul(rays_cam, Ri)
    uv = rp.rect_coords_left(rays_world).astype(np.float32).reshape(h, w, 2)
    dd = remap_frame(d, uv)  # bilinear; NaN next to an invalid disparity
    Zr = rp.depth_from_disparity(dd.astype(float)).ravel()
    # rectified depth Z along the rectified axis -> point -> camera-i z
    d_rect = _mul(rays_world, rp.R_rect.T)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = Zr / d_rect[:, 2]  # point = C + s * rays_world
        z_i = s * rays_cam[:, 2]
        fB = rp.f_px * rp.baseline_m
        sig = Zr**2 * cfg.sigma_disparity_px / fB * (z_i / Zr)
    return z_i.reshape(h, w), sig.reshape(h, w)


def fuse_depths(depths, sigmas, *, min_consistent: int = 2, k: float = 2.5):
    """Fuse K depth maps of one reference image by geometric consistency.

    Parameters
    ----------
    depths, sigmas : (K, H, W) depth (m) and σ (m), NaN = none

    Returns
    -------
    depth : (H, W) fused depth (NaN where fewer than ``min_consistent`` estimates agree)
    n_agree : (H, W) int, number of agreeing pair depths (views = n_agree + 1)
    """
    D = np.asarray(depths, float)
    S = np.asarray(sigmas, float)
    K = D.shape[0]
    with np.errstate(invalid="ignore"):
        agree = np.abs(D[:, None] - D[None, :]) <= k * np.hypot(S[:, None], S[None, :])  # (K, K, H, W)
        count = agree.sum(axis=1)  # for each estimate, how many agree with it (itself included)
    count = np.where(np.isfinite(D), count, 0)
    best = np.argmax(count, axis=0)  # ties: lowest index (deterministic)
    nbest = np.take_along_axis(count, best[None], 0)[0]
    sel = np.take_along_axis(agree, best[None, None].repeat(K, axis=1), 0)[0] & np.isfinite(D)  # (K, H, W)
    w = np.where(sel, 1.0 / np.maximum(S, 1e-12) ** 2, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        fused = np.sum(np.where(sel, D, 0.0) * w, axis=0) / np.sum(w, axis=0)
    ok = nbest >= min_consistent
    del K
    return np.where(ok, fused, np.nan), np.where(ok, nbest, 0)


def reference_points(i, cameras, poses, frames, config: DenseConfig | None = None, *, pairs=None) -> tuple[np.ndarray, dict]:
    """Fused, consistent points of reference image ``i`` with the exact frame value at each point's pixel.

    Returns
    -------
    points : structured array :data:`POINT_DTYPE` (world x, y, z in m; ``value`` = frame value at the pixel,
        bit-exact for float32 kelvin and uint16 counts; unit normal towards the camera; views; source = i)
    info : dict with the pairs used and counts
    """
    cfg = config or DenseConfig()
    cands = rank_pairs(i, cameras, poses, frames, cfg) if pairs is None else pairs
    use = cands[: cfg.pairs_per_image]
    info = {"image": i, "pairs": [{"j": p.j, "overlap": round(p.overlap, 3), "bh": round(p.bh, 3)} for p in use]}
    if len(use) < cfg.min_consistent:
        info["note"] = f"{len(use)} usable pair(s); {cfg.min_consistent} needed for the consistency check"
        return np.zeros(0, POINT_DTYPE), info
    Ds, Ss = zip(*(pair_depth(i, p.j, cameras, poses, frames, min_disparity=p.disparity_min,
                              num_disparities=p.disparity_num, config=cfg, rectified=p.rectified) for p in use))
    depth, n_agree = fuse_depths(np.stack(Ds), np.stack(Ss), min_consistent=cfg.min_consistent)
    if cfg.edge_jump:
        # depth discontinuities: SGBM's blocks fatten foreground objects by about half a block; pixels within
        # ``edge_px`` of a jump larger than ``edge_jump`` × depth are dropped (they are seen from other images)
        import cv2

        k = 2 * int(cfg.edge_px) + 1
        big = np.where(np.isfinite(depth), depth, -np.inf).astype(np.float32)
        small = np.where(np.isfinite(depth), depth, np.inf).astype(np.float32)
        hi = cv2.dilate(big, np.ones((k, k), np.uint8))
        lo = cv2.erode(small, np.ones((k, k), np.uint8))
        with np.errstate(invalid="ignore", over="ignore"):
            jump = np.isfinite(hi) & np.isfinite(lo) & (hi - lo > cfg.edge_jump * depth)
        depth = np.where(jump, np.nan, depth)
    cam = cameras[i]
    R, t = poses[i]
    C = -R.T @ t
    w, h = cam.image_size
    rays = pixel_rays(cam).reshape(h, w, 3)
    Xc = rays * depth[..., None]  # camera frame (z = depth)
    # normals from the depth map's neighbours (central differences over ±3 px), towards the camera
    def _normals(q):
        dx = np.full_like(Xc, np.nan)
        dy = np.full_like(Xc, np.nan)
        dx[:, q:-q] = Xc[:, 2 * q:] - Xc[:, : -2 * q]
        dy[q:-q] = Xc[2 * q:] - Xc[: -2 * q]
        nn = np.cross(dx, dy)
        with np.errstate(invalid="ignore", divide="ignore"):
            return nn / np.linalg.norm(nn, axis=-1, keepdims=True)

    # ±3 px: a longer base than the depth noise; ±1 px where the wider neighbours are missing
    n = _normals(3)
    n = np.where(np.isfinite(n).all(axis=-1, keepdims=True), n, _normals(1))
    with np.errstate(invalid="ignore"):
        flip = np.sum(n * Xc, axis=-1) > 0
    n[flip] *= -1
    s = max(1, int(cfg.stride_px))
    keep = np.zeros((h, w), bool)
    keep[s // 2::s, s // 2::s] = True
    keep &= np.isfinite(depth)
    frame = np.asarray(frames(i))
    if frame.ndim == 3:
        frame = frame[..., 0]
    yy, xx = np.nonzero(keep)
    Xw = _mul(Xc[yy, xx], R) + C  # R^T X_cam + C
    nw = _mul(n[yy, xx], R)
    if cfg.keep_nearest:
        # thinning: a point is kept by the reference images among the ``keep_nearest`` whose centres are
        # nearest to it horizontally (each surface point comes from the most nadir views, not from all)
        Call = np.array([-Rk.T @ tk for Rk, tk in poses])
        near = np.argsort(np.linalg.norm(Call[:, :2] - C[:2], axis=1), kind="stable")[: 12 * cfg.keep_nearest]
        dmine = np.hypot(Xw[:, 0] - C[0], Xw[:, 1] - C[1])
        closer = np.zeros(len(Xw), np.int32)
        for k in near:
            if k != i:
                closer += np.hypot(Xw[:, 0] - Call[k, 0], Xw[:, 1] - Call[k, 1]) < dmine
        sel = closer < cfg.keep_nearest
        yy, xx, Xw, nw = yy[sel], xx[sel], Xw[sel], nw[sel]
    pts = np.zeros(len(yy), POINT_DTYPE)
    pts["x"], pts["y"], pts["z"] = Xw[:, 0], Xw[:, 1], Xw[:, 2]
    pts["value"] = frame[yy, xx].astype(np.float32)
    pts["nx"], pts["ny"], pts["nz"] = (np.nan_to_num(nw[:, k]).astype(np.float32) for k in range(3))
    pts["views"] = np.minimum(n_agree[yy, xx] + 1, 255)
    pts["source"] = i
    info["points"] = int(len(pts))
    info["fused_fraction"] = round(float(np.isfinite(depth).mean()), 4)
    info["depth_m"] = float(np.nanmedian(depth)) if np.isfinite(depth).any() else float("nan")
    return pts, info
