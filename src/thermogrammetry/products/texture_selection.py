"""Per texel: the usable image with the highest face score and its bilinear temperature, in chunks of points.

See :mod:`thermogrammetry.products.texture` (view selection).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._sampling import bilinear
from .texture_config import TextureConfig
from .texture_scores import scores_at
from .texture_visibility import usable_in_view

__all__ = ["Selection", "select_and_sample", "select_in_chunks", "CHUNK_POINT_VIEWS"]


@dataclass
class Selection:
    """Per point: ``source`` (N,) view index or −1, ``temperature_k`` (N,), ``angle_deg`` (N,),
    ``distance_m`` (N,), ``n_usable`` (N,) number of usable views, ``occluded_in`` (N, K) bool, and the
    values of every usable view ``all_k`` (N, K) (NaN where unusable), for levelling; ``n_visible`` (N,) the
    number of views in which the point is visible (usable or not: conditions 1–3).

    The two (N, K) arrays grow with points × images: :func:`select_in_chunks` holds them for one chunk of
    points at a time and returns None for them (with per-view occlusion counts and a levelling sample)."""

    source: np.ndarray
    temperature_k: np.ndarray
    angle_deg: np.ndarray
    distance_m: np.ndarray
    n_usable: np.ndarray
    occluded_in: np.ndarray | None
    all_k: np.ndarray | None
    n_visible: np.ndarray | None = None



def select_and_sample(intersector, vertices, faces, views, surfaces, scores, points, face_index,
                      cfg: TextureConfig) -> Selection:
    """For each point, the usable view with the highest face score and its bilinear temperature."""
    N, K = len(points), len(views)
    fi = np.asarray(face_index, np.int64)
    best_score = np.zeros(N)
    src = np.full(N, -1, np.int64)
    T = np.full(N, np.nan)
    ang = np.full(N, np.nan)
    dist = np.full(N, np.nan)
    n_ok = np.zeros(N, np.int64)
    n_vis = np.zeros(N, np.int64)
    occl = np.zeros((N, K), bool)
    all_k = np.full((N, K), np.nan, np.float32)
    for k, v in enumerate(views):
        s = scores_at(scores, k, fi)
        cand = np.flatnonzero(s > 0)
        if not len(cand):
            continue
        ok, xy, cos_t, d, oc, vis = usable_in_view(intersector, vertices, faces, v, surfaces[k], points[cand], fi[cand], cfg)
        occl[cand, k] = oc
        n_vis[cand[vis]] += 1
        sel = cand[ok]
        vals = bilinear(v.image_k, xy[ok]).astype(np.float64)
        finite = np.isfinite(vals)
        sel, vals = sel[finite], vals[finite]
        cs, ds = cos_t[ok][finite], d[ok][finite]
        all_k[sel, k] = vals
        n_ok[sel] += 1
        better = s[sel] > best_score[sel]
        b = sel[better]
        best_score[b] = s[b]
        src[b] = k
        T[b] = vals[better]
        ang[b] = np.degrees(np.arccos(np.clip(cs[better], -1, 1)))
        dist[b] = ds[better]
    return Selection(src, T, ang, dist, n_ok, occl, all_k, n_vis)



#: points × images per chunk of :func:`select_in_chunks` (the chunk's (N, K) float32 values and bool occlusion
#: flags: ~250 MB at this size)
CHUNK_POINT_VIEWS = 50_000_000
#: at most this many points per chunk, whatever the number of images: a mesh seen by few images still reports
#: progress (``on_chunk``) every million texels rather than once at the end
CHUNK_MAX_POINTS = 1_000_000



def select_in_chunks(intersector, vertices, faces, views, surfaces, scores, points, face_index, cfg: TextureConfig, *,
                     sample=None, chunk_point_views: int = CHUNK_POINT_VIEWS, on_chunk=None):
    """:func:`select_and_sample` over chunks of points, so that memory does not grow with points × images.

    Parameters
    ----------
    sample : optional (N,) bool, the points whose values in every usable view are kept (for levelling)
    chunk_point_views : points per chunk × number of views
    on_chunk : optional callable ``on_chunk(done, N)``, called after each chunk with the points done so far (progress)

    Returns
    -------
    selection : :class:`Selection` with ``occluded_in`` and ``all_k`` None (same per-point results as one call)
    occluded_per_view : (K,) int, points inside view k, facing it, hidden by other geometry
    sample_all_k : (S, K) float32 values of the ``sample`` points (in point order), or None
    """
    N, K = len(points), len(views)
    step = max(1, min(int(chunk_point_views) // max(K, 1), CHUNK_MAX_POINTS))
    src = np.full(N, -1, np.int64)
    T = np.full(N, np.nan)
    ang = np.full(N, np.nan)
    dist = np.full(N, np.nan)
    n_ok = np.zeros(N, np.int64)
    n_vis = np.zeros(N, np.int64)
    occluded = np.zeros(K, np.int64)
    kept = []
    fi = np.asarray(face_index, np.int64)
    for i0 in range(0, N, step):
        sl = slice(i0, min(N, i0 + step))
        s = select_and_sample(intersector, vertices, faces, views, surfaces, scores, points[sl], fi[sl], cfg)
        src[sl], T[sl], ang[sl], dist[sl], n_ok[sl] = s.source, s.temperature_k, s.angle_deg, s.distance_m, s.n_usable
        n_vis[sl] = s.n_visible
        occluded += s.occluded_in.sum(axis=0)
        if sample is not None:
            kept.append(s.all_k[np.asarray(sample[sl], bool)])
        del s
        if on_chunk is not None:
            on_chunk(sl.stop, N)
    all_k = (np.concatenate(kept) if kept else np.zeros((0, K), np.float32)) if sample is not None else None
    return Selection(src, T, ang, dist, n_ok, None, None, n_vis), occluded, all_k
