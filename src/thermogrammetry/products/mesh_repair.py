"""Stitching block meshes, removing small loose pieces and filling holes up to a given area.

Hole filling (after Liepa 2003): every boundary loop of the mesh is a candidate. A loop is filled when the patch
that closes it has an area of at most ``max_area_m2`` and it is a hole, not the border of an open sheet: seen from
the side the surface faces, the loop of a hole runs clockwise (its vector area points against the surrounding
faces' normals; a sheet's outer border runs the other way). The loop is projected on its best-fitting plane,
triangulated with interior points at the loop's edge length (Delaunay, kept where it respects the loop, else ear
clipping of the loop alone), and the interior points lifted off the plane by a harmonic interpolation of the loop's
heights (a membrane through the rim: exact for a planar hole). The patch's triangles are wound like the faces around
it and every one of them is flagged ``filled``.

References
----------
P. Liepa, "Filling holes in meshes", Eurographics Symposium on Geometry Processing 2003.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .mesh_surface import triangle_areas

__all__ = ["weld", "drop_small_components", "boundary_loops", "fill_holes", "HoleReport"]


def weld(vertex_chunks, face_chunks, h: float) -> tuple[np.ndarray, np.ndarray]:
    """One mesh from block meshes: vertices equal to 1e-6 cells merged (blocks compute the vertices on their shared
    faces from the same node values), degenerate and repeated triangles dropped."""
    if not vertex_chunks:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    offs = np.cumsum([0] + [len(v) for v in vertex_chunks])
    V = np.concatenate(vertex_chunks)
    F = np.concatenate([f + o for f, o in zip(face_chunks, offs[:-1])]) if face_chunks else np.zeros((0, 3), np.int64)
    q = np.round(V / (h * 1e-6)).astype(np.int64)
    _, first, inv = np.unique(q, axis=0, return_index=True, return_inverse=True)
    inv = inv.ravel()
    V = V[first]
    F = inv[F]
    ok = (F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])
    F = F[ok]
    key = np.sort(F, axis=1)
    _, keep = np.unique(key, axis=0, return_index=True)
    F = F[np.sort(keep)]
    return V, F


def _compact(V, F, *extra):
    used = np.unique(F)
    remap = np.full(len(V), -1, np.int64)
    remap[used] = np.arange(len(used))
    return (V[used], remap[F], *extra)


def face_components(F, n_vertices: int) -> np.ndarray:
    """(F,) label of the connected piece (faces sharing a vertex) of each face."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if len(F) == 0:
        return np.zeros(0, np.int64)
    r = np.r_[F[:, 0], F[:, 1]]
    c = np.r_[F[:, 1], F[:, 2]]
    g = coo_matrix((np.ones(len(r)), (r, c)), shape=(n_vertices, n_vertices))
    _, lab = connected_components(g, directed=False)
    return lab[F[:, 0]]


def drop_small_components(V, F, min_area_m2: float):
    """Remove connected pieces of less than ``min_area_m2``; returns ``(V, F, pieces removed, area removed m²)``."""
    if len(F) == 0:
        return V, F, 0, 0.0
    lab = face_components(F, len(V))
    area = np.bincount(lab, weights=triangle_areas(V, F))
    small = area < min_area_m2
    small_pieces = int(np.count_nonzero(small[np.unique(lab)]))
    drop = small[lab]
    removed = float(triangle_areas(V, F[drop]).sum())
    V, F = _compact(V, F[~drop])
    return V, F, small_pieces, removed


def boundary_loops(F) -> list[np.ndarray]:
    """Closed loops of boundary edges (edges of one triangle), each as the vertex sequence in the direction the
    edges run in their triangles. Boundary vertices where more than one loop meets are left out (their loops are
    not returned)."""
    if len(F) == 0:
        return []
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    key = np.minimum(e[:, 0], e[:, 1]) * (int(F.max()) + 1) + np.maximum(e[:, 0], e[:, 1])
    uk, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    b = e[cnt[inv.ravel()] == 1]
    if len(b) == 0:
        return []
    starts, ns = np.unique(b[:, 0], return_counts=True)
    bad = set(starts[ns > 1].tolist())
    nxt = {int(a): int(c) for a, c in b if int(a) not in bad}
    loops, seen = [], set()
    for s in list(nxt):
        if s in seen:
            continue
        loop, v, ok = [], s, True
        while True:
            if v in seen or v not in nxt:
                ok = v == s and len(loop) > 0
                break
            seen.add(v)
            loop.append(v)
            v = nxt[v]
            if v == s:
                break
        if ok and len(loop) >= 3 and v == s:
            loops.append(np.asarray(loop, np.int64))
    return loops


@dataclass
class HoleReport:
    """Holes found and filled: counts, areas (m²) and the largest hole left open."""

    filled: int = 0
    filled_faces: int = 0
    filled_area_m2: float = 0.0
    left_open: int = 0
    left_open_area_m2: float = 0.0
    largest_open_m2: float = 0.0
    areas_filled_m2: list = field(default_factory=list)


def _vector_area(P) -> np.ndarray:
    c = P.mean(axis=0)
    Q = P - c
    return 0.5 * np.cross(Q, np.roll(Q, -1, axis=0)).sum(axis=0)


def _seg_intersections(P2) -> bool:
    """Whether the closed 2D polyline ``P2`` crosses itself (non-adjacent edges)."""
    n = len(P2)
    A, B = P2, np.roll(P2, -1, axis=0)
    i, j = np.triu_indices(n, k=2)
    keep = ~((i == 0) & (j == n - 1))
    i, j = i[keep], j[keep]

    def orient(p, q, r):
        return np.sign((q[:, 0] - p[:, 0]) * (r[:, 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (r[:, 0] - p[:, 0]))
    o1 = orient(A[i], B[i], A[j])
    o2 = orient(A[i], B[i], B[j])
    o3 = orient(A[j], B[j], A[i])
    o4 = orient(A[j], B[j], B[i])
    return bool(np.any((o1 * o2 < 0) & (o3 * o4 < 0)))


def _ear_clip(P2) -> np.ndarray:
    """Triangles (T, 3) of a simple counter-clockwise polygon by ear clipping (indices into ``P2``)."""
    idx = list(range(len(P2)))
    tris = []

    def area2(a, b, c):
        return (P2[b, 0] - P2[a, 0]) * (P2[c, 1] - P2[a, 1]) - (P2[b, 1] - P2[a, 1]) * (P2[c, 0] - P2[a, 0])
    guard = 0
    while len(idx) > 3 and guard < 10 * len(P2) ** 2:
        guard += 1
        m = len(idx)
        for k in range(m):
            a, b, c = idx[k - 1], idx[k], idx[(k + 1) % m]
            if area2(a, b, c) <= 1e-15:
                continue
            others = [v for v in idx if v not in (a, b, c)]
            if others:
                o = np.asarray(others)
                d1 = (P2[b, 0] - P2[a, 0]) * (P2[o, 1] - P2[a, 1]) - (P2[b, 1] - P2[a, 1]) * (P2[o, 0] - P2[a, 0])
                d2 = (P2[c, 0] - P2[b, 0]) * (P2[o, 1] - P2[b, 1]) - (P2[c, 1] - P2[b, 1]) * (P2[o, 0] - P2[b, 0])
                d3 = (P2[a, 0] - P2[c, 0]) * (P2[o, 1] - P2[c, 1]) - (P2[a, 1] - P2[c, 1]) * (P2[o, 0] - P2[c, 0])
                if np.any((d1 >= 0) & (d2 >= 0) & (d3 >= 0)):
                    continue
            tris.append((a, b, c))
            idx.pop(k)
            break
        else:
            break
    if len(idx) == 3:
        tris.append(tuple(idx))
    return np.asarray(tris, np.int64).reshape(-1, 3)


def _patch(P3, normal_out):
    """Vertices (rim first, then interior) and triangles of a patch closing the rim ``P3`` (the hole loop, (n, 3)),
    wound so that its normals point along ``normal_out``; None when the rim does not project to a simple polygon."""
    from matplotlib.path import Path as MplPath
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import spsolve
    from scipy.spatial import Delaunay

    n = len(P3)
    c = P3.mean(axis=0)
    w = normal_out / np.linalg.norm(normal_out)
    u = np.cross(w, [1.0, 0, 0] if abs(w[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    Q = P3 - c
    P2 = np.stack([Q @ u, Q @ v], axis=1)
    hgt = Q @ w
    if _seg_intersections(P2):
        return None
    # the hole loop runs clockwise seen from w: reverse it to a counter-clockwise polygon
    sgn = np.sum(P2[:, 0] * np.roll(P2[:, 1], -1) - np.roll(P2[:, 0], -1) * P2[:, 1])
    rev = sgn < 0
    ring = P2[::-1] if rev else P2
    order = np.arange(n)[::-1] if rev else np.arange(n)
    s = float(np.median(np.linalg.norm(np.roll(ring, -1, axis=0) - ring, axis=1)))
    lo, hi = ring.min(axis=0), ring.max(axis=0)
    gx = np.arange(lo[0] + s / 2, hi[0], s)
    gy = np.arange(lo[1] + s / 2, hi[1], s * np.sqrt(3) / 2)
    G = np.array([(x + (s / 2 if k % 2 else 0.0), y) for k, y in enumerate(gy) for x in gx]).reshape(-1, 2)
    poly = MplPath(ring)
    if len(G):
        G = G[poly.contains_points(G)]
    if len(G):  # at least 0.6 edge lengths from the rim
        A, B = ring, np.roll(ring, -1, axis=0)
        AB = B - A
        t = np.clip(((G[:, None, :] - A[None]) * AB[None]).sum(-1) / np.maximum((AB * AB).sum(-1), 1e-30)[None], 0, 1)
        dist = np.linalg.norm(G[:, None, :] - (A[None] + t[..., None] * AB[None]), axis=-1).min(axis=1)
        G = G[dist > 0.6 * s]
    tris = None
    if len(G):
        pts = np.vstack([ring, G])
        tri = Delaunay(pts).simplices
        cen = pts[tri].mean(axis=1)
        tri = tri[poly.contains_points(cen)]
        edges = {tuple(sorted(e)) for t_ in tri for e in ((t_[0], t_[1]), (t_[1], t_[2]), (t_[2], t_[0]))}
        rim_ok = all(tuple(sorted((k, (k + 1) % n))) in edges for k in range(n))
        if rim_ok and len(tri) == n - 2 + 2 * len(G):
            tris = tri
    if tris is None:
        G = np.zeros((0, 2))
        tris = _ear_clip(ring)
        if len(tris) != n - 2:
            return None
    pts = np.vstack([ring, G])
    # counter-clockwise in (u, v) = normals along w
    a2 = np.cross(np.c_[pts[tris[:, 1]] - pts[tris[:, 0]], np.zeros(len(tris))],
                  np.c_[pts[tris[:, 2]] - pts[tris[:, 0]], np.zeros(len(tris))])[:, 2]
    tris = np.where((a2 < 0)[:, None], tris[:, ::-1], tris)
    # heights: rim as measured, interior harmonic (uniform weights)
    m = len(G)
    H = np.zeros(n + m)
    H[:n] = hgt[order]
    if m:
        e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
        e = np.vstack([e, e[:, ::-1]])
        L = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n + m, n + m)).tocsr()
        L.data[:] = 1.0
        deg = np.asarray(L.sum(axis=1)).ravel()
        Lii = L[n:, n:]
        A_ = coo_matrix((deg[n:], (np.arange(m), np.arange(m))), shape=(m, m)).tocsr() - Lii
        rhs = L[n:, :n] @ H[:n]
        H[n:] = spsolve(A_.tocsc(), rhs)
    X = c + pts[:, :1] * u + pts[:, 1:2] * v + H[:, None] * w
    X[:n] = P3[order]
    return X, tris, order


def fill_holes(V, F, max_area_m2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, HoleReport]:
    """Fill the holes of at most ``max_area_m2`` (see the module docstring).

    Returns ``(V, F, filled (F,) bool, report)``: the new faces are appended after the old ones.
    """
    rep = HoleReport()
    filled = np.zeros(len(F), bool)
    if len(F) == 0:
        return V, F, filled, rep
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    vn = np.zeros_like(V)
    for k in range(3):
        np.add.at(vn, F[:, k], fn)
    newV, newF = [V], [F]
    nv = len(V)
    for loop in boundary_loops(F):
        P = V[loop]
        va = _vector_area(P)
        area = float(np.linalg.norm(va))
        around = vn[loop].sum(axis=0)
        na = np.linalg.norm(around)
        is_hole = area > 0 and na > 0 and float(va @ around) / (area * na) < 0.3
        if not is_hole:
            continue
        if area > max_area_m2 or len(loop) > 20000:
            rep.left_open += 1
            rep.left_open_area_m2 += area
            rep.largest_open_m2 = max(rep.largest_open_m2, area)
            continue
        res = _patch(P, -va)
        if res is None:
            rep.left_open += 1
            rep.left_open_area_m2 += area
            rep.largest_open_m2 = max(rep.largest_open_m2, area)
            continue
        X, tris, order = res
        n = len(loop)
        idx = np.r_[loop[order], nv + np.arange(len(X) - n)]
        newV.append(X[n:])
        nv += len(X) - n
        T = idx[tris]
        newF.append(T)
        rep.filled += 1
        rep.filled_faces += len(T)
        a = float(triangle_areas(X, tris).sum())
        rep.filled_area_m2 += a
        rep.areas_filled_m2.append(round(a, 4))
    V2 = np.vstack(newV)
    F2 = np.vstack(newF)
    filled = np.r_[filled, np.ones(len(F2) - len(F), bool)]
    return V2, F2, filled, rep
