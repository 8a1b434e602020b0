"""View scores: the documented per-face score of every image (the best image per face).

The score ``f cos θ / d · min(1, b / b0)`` and the large-face test are described in
:mod:`thermogrammetry.products.texture`; occlusion is not part of the score (:mod:`.texture_visibility` tests it
per texel).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .texture_mesh import TextureView, check_mesh, face_geometry, project_to_view

__all__ = ["face_view_scores", "scores_at", "score_max_count", "any_face_seen", "score_columns"]


def _focal_px(camera) -> float:
    K = camera.K
    return 0.5 * (K[0, 0] + K[1, 1])



def face_view_scores(vertices, faces, views: Sequence[TextureView], *, max_angle_deg: float = 75.0,
                     border_fraction: float = 0.1):
    """The documented per-face score (:mod:`thermogrammetry.products.texture`) of every image: (F, K) sparse,
    absent = unusable.

    Parameters
    ----------
    vertices : (V, 3) metres; faces : (F, 3) vertex indices; views : K oriented images.

    Returns
    -------
    ``scipy.sparse.csc_matrix`` (F, K) float64 holding the positive scores only (sorted row indices per image):
    ``f cos θ / d · min(1, b / b0)`` in pixels per metre; absent (0) where θ > ``max_angle_deg``, behind the
    camera or outside the image (a large face: see :mod:`thermogrammetry.products.texture`). Occlusion is not part
    of the score (it is tested per texel). Sparse because each face is seen by a few of the images: a dense matrix was 1.6 GB at 1 M faces x
    200 images. ``.toarray()`` gives the dense matrix; :func:`scores_at` reads one image's scores of given faces.
    """
    import scipy.sparse as sp

    V, F = check_mesh(vertices, faces)
    rows, vals, ptr = [], [], [0]
    for k, col in score_columns(V, F, views, max_angle_deg, border_fraction):
        nz = np.flatnonzero(col > 0)
        rows.append(nz.astype(np.int32))
        vals.append(col[nz])
        ptr.append(ptr[-1] + len(nz))
    data = np.concatenate(vals) if vals else np.zeros(0)
    idx = np.concatenate(rows) if rows else np.zeros(0, np.int32)
    return sp.csc_matrix((data, idx, np.asarray(ptr, np.int64)), shape=(len(F), len(views)))



def scores_at(scores, k: int, face_index) -> np.ndarray:
    """Scores of image ``k`` for the faces ``face_index`` (N,): from the sparse (F, K) matrix of
    :func:`face_view_scores` (its sorted row indices: a binary search, no dense column) or a dense (F, K) array."""
    fi = np.asarray(face_index, np.int64)
    if isinstance(scores, np.ndarray):
        return scores[fi, k]
    a, b = int(scores.indptr[k]), int(scores.indptr[k + 1])
    rows, vals = scores.indices[a:b], scores.data[a:b]
    if not len(rows):
        return np.zeros(len(fi))
    pos = np.minimum(np.searchsorted(rows, fi), len(rows) - 1)
    return np.where(rows[pos] == fi, vals[pos], 0.0)



def score_max_count(scores) -> tuple[np.ndarray, np.ndarray]:
    """Per face: the best image's score and the number of images with a positive score ((F,), (F,) int)."""
    if isinstance(scores, np.ndarray):
        return scores.max(axis=1, initial=0.0), (scores > 0).sum(axis=1)
    r = scores.tocsr()
    best = np.zeros(r.shape[0])
    n = np.diff(r.indptr)
    has = n > 0
    if np.any(has):
        best[has] = np.maximum.reduceat(r.data, r.indptr[:-1][has])
    return best, n



def any_face_seen(vertices, faces, views: Sequence[TextureView], *, max_angle_deg: float = 75.0,
                  border_fraction: float = 0.1) -> bool:
    """Whether some face has a positive :func:`face_view_scores` score in some image (one image at a time: no
    (F, K) matrix; stops at the first image that sees a face)."""
    V, F = check_mesh(vertices, faces)
    return any(np.any(col > 0) for _, col in score_columns(V, F, views, max_angle_deg, border_fraction))



def _closest_on_triangles(p, a, b, c) -> np.ndarray:
    """(N, 3) point of each triangle ``(a, b, c)`` (each (N, 3)) nearest to ``p`` (N, 3): the Voronoi-region
    test of Ericson, Real-Time Collision Detection (2005) §5.1.5, vectorised."""
    dot = lambda u, v: np.einsum("ij,ij->i", u, v)  # noqa: E731
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp, cp = p - b, p - c
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    vc, vb, va = d1 * d4 - d3 * d2, d5 * d2 - d1 * d6, d3 * d6 - d5 * d4
    out = np.empty_like(a)
    left = np.ones(len(a), bool)

    def put(m, x):
        m = m & left
        out[m] = x[m]
        left[m] = False

    with np.errstate(invalid="ignore", divide="ignore"):
        put((d1 <= 0) & (d2 <= 0), a)
        put((d3 >= 0) & (d4 <= d3), b)
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + (d1 / (d1 - d3))[:, None] * ab)
        put((d6 >= 0) & (d5 <= d6), c)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + (d2 / (d2 - d6))[:, None] * ac)
        put((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[:, None] * (c - b))
        den = va + vb + vc
        put(np.ones(len(a), bool), a + (vb / den)[:, None] * ab + (vc / den)[:, None] * ac)
    return out



def _in_frustum(view, V, tri) -> np.ndarray:
    """(n,) bool: triangles ``tri`` (n, 3) not wholly outside one side of the view's frustum (the planes through the
    rays of the image corners, 5 % beyond them for the lens distortion) or wholly behind the camera."""
    w, h = view.camera.image_size
    mx, my = 0.05 * w, 0.05 * h
    cor = np.array([[-0.5 - mx, -0.5 - my], [w - 0.5 + mx, -0.5 - my], [w - 0.5 + mx, h - 0.5 + my], [-0.5 - mx, h - 0.5 + my]])
    d = view.camera.unproject(cor) @ view.pose.R  # world directions of the corner rays
    axis = view.pose.R[2]
    X = V[tri] - view.pose.center  # (n, 3, 3)
    keep = np.any(X @ axis > 0, axis=1)
    for i in range(4):
        nrm = np.cross(d[i], d[(i + 1) % 4])
        if nrm @ axis < 0:
            nrm = -nrm
        keep &= np.any(X @ nrm >= 0, axis=1)
    return keep



def _large_face_candidates(view, V, F, normals, faces, cmax):
    """For faces (indices ``faces``) not scorable at their centroid: the largest cos θ and the largest border
    distance ``b`` (px) over a few points of the face (not necessarily the same point: a generous test, each texel
    is tested on its own later) -- its vertices and edge midpoints, its point nearest to the camera (smallest θ on a
    plane) and three points from there to the centroid, and where the rays of a 4 x 4 grid of pixels meet it.

    Returns ``(cos_t (n,), b (n,), found (n,) bool)``."""
    w, h = view.camera.image_size
    C = view.pose.center
    n = len(faces)
    A, B, Cc = V[F[faces, 0]], V[F[faces, 1]], V[F[faces, 2]]
    nrm = normals[faces]
    near = _closest_on_triangles(np.broadcast_to(C, (n, 3)), A, B, Cc)
    cen = (A + B + Cc) / 3
    pts = [A, B, Cc, near, (A + B) / 2, (B + Cc) / 2, (Cc + A) / 2]
    pts += [near + f * (cen - near) for f in (0.25, 0.5, 0.75)]  # from where θ is smallest towards the middle
    gx, gy = np.meshgrid((np.arange(4) + 0.5) * w / 4 - 0.5, (np.arange(4) + 0.5) * h / 4 - 0.5)
    rays = view.camera.unproject(np.column_stack([gx.ravel(), gy.ravel()])) @ view.pose.R  # (16, 3) world directions
    ab, ac = B - A, Cc - A
    for d in rays:
        den = nrm @ d
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.einsum("ij,ij->i", nrm, A - C) / den
        X = C + t[:, None] * d
        # barycentric test
        ap = X - A
        d00, d01, d11 = np.einsum("ij,ij->i", ab, ab), np.einsum("ij,ij->i", ab, ac), np.einsum("ij,ij->i", ac, ac)
        d20, d21 = np.einsum("ij,ij->i", ap, ab), np.einsum("ij,ij->i", ap, ac)
        with np.errstate(invalid="ignore", divide="ignore"):
            den2 = d00 * d11 - d01 * d01
            bv = (d11 * d20 - d01 * d21) / den2
            bw = (d00 * d21 - d01 * d20) / den2
        inside = (t > 0) & (bv >= 0) & (bw >= 0) & (bv + bw <= 1)
        pts.append(np.where(inside[:, None], X, np.nan))
    best_c = np.full(n, -np.inf)
    best_b = np.full(n, -np.inf)
    for X in pts:
        dx = C - X
        with np.errstate(invalid="ignore"):
            c = np.einsum("ij,ij->i", nrm, dx) / np.linalg.norm(dx, axis=1)
        fin = np.all(np.isfinite(X), axis=1)
        best_c = np.where(fin & (c > best_c), c, best_c)
        best_b = np.where(fin, np.maximum(best_b, _border_distance(view, np.where(fin[:, None], X, 0.0), w, h)), best_b)
    found = (best_c >= cmax) & (best_b > 0)
    return best_c, best_b, found



def _border_distance(view, X, w, h) -> np.ndarray:
    """(N,) distance in pixels of the projections of ``X`` from the nearest image border (pixel edges: −0.5 and
    W − 0.5); ≤ 0 outside the image, −inf behind the camera."""
    xy, z = project_to_view(view, X)
    bx = np.minimum(xy[:, 0] + 0.5, w - 0.5 - xy[:, 0])
    by = np.minimum(xy[:, 1] + 0.5, h - 0.5 - xy[:, 1])
    return np.nan_to_num(np.where(z > 1e-6, np.minimum(bx, by), -np.inf), nan=-np.inf)



def score_columns(V, F, views, max_angle_deg, border_fraction, large_faces: bool = True):
    """Yield ``(k, (F,) scores of image k)`` (see :func:`face_view_scores`); ``large_faces=False``: scored at the
    centroid only."""
    normals, _, cen = face_geometry(V, F)
    cmax = np.cos(np.deg2rad(max_angle_deg))
    amax = np.deg2rad(max_angle_deg)
    edge = np.max(np.linalg.norm(V[F] - V[F[:, [1, 2, 0]]], axis=2), axis=1)  # longest edge of each face (m)
    for k, v in enumerate(views):
        w, h = v.camera.image_size
        C = v.pose.center
        dvec = C - cen
        d = np.linalg.norm(dvec, axis=1)
        cos_t = np.einsum("ij,ij->i", normals, dvec) / d
        b = _border_distance(v, cen, w, h)
        ok = np.isfinite(cos_t) & (cos_t >= cmax) & (b > 0)
        # a large face (a ground cell beside a standing camera, a CAD wall of two triangles) can be seen at a grazing
        # angle from its centroid, or have its centroid outside the image, and still be partly seen well: then the
        # largest cos θ and border distance over a few points of the face count (products.texture's docstring). Only
        # faces large enough for that are looked at: seen from the centroid, no point of a face is more than its longest edge / d
        # radians off in angle, nor more than ~f times that off in the image
        span = edge / d
        need = np.flatnonzero(large_faces & np.isfinite(cos_t) & (cos_t > 0) & ~ok
                              & (np.arccos(np.clip(cos_t, -1, 1)) - amax <= span)
                              & (b > -1.5 * _focal_px(v.camera) * span))
        need = need[_in_frustum(v, V, F[need])] if len(need) else need
        if len(need):
            cb, bb, good = _large_face_candidates(v, V, F, normals, need, cmax)
            cos_t[need[good]], b[need[good]] = cb[good], bb[good]
            ok[need[good]] = True
        b0 = max(1e-9, border_fraction * min(w, h))
        yield k, np.where(ok, _focal_px(v.camera) * np.clip(cos_t, 0, 1) / d * np.minimum(1.0, np.maximum(b, 0) / b0), 0.0)
