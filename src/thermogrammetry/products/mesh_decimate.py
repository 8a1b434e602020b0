"""Decimation of a mesh to a face count or an edge length, with the geometric error it made; point-to-mesh distances.

Decimation is quadric edge collapse (Garland & Heckbert 1997) as implemented by Fast-Quadric-Mesh-Simplification
(the ``fast-simplification`` package), the open border kept in place. Its error is measured, not assumed: the
distance from points on the mesh before (its vertices, at most ``samples`` of them, chosen with a fixed seed) to the
mesh after (:func:`point_mesh_distance`), reported as RMS and maximum. Face flags (``filled``) follow the faces:
a face after decimation is flagged when the face before nearest to its centroid (point-to-triangle distance), or to
any of the three points half-way from its centroid to its corners, was flagged (a face made partly by filling is
flagged).

References
----------
M. Garland, P. S. Heckbert, "Surface simplification using quadric error metrics", SIGGRAPH 1997.
C. Ericson, "Real-Time Collision Detection", Morgan Kaufmann 2004, §5.1.5 (closest point on a triangle).
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .mesh_surface import triangle_areas

__all__ = ["target_faces", "decimate", "closest_point_on_triangles", "point_mesh_distance"]


def target_faces(V, F, *, edge_m: float | None = None, faces: int | None = None) -> int | None:
    """The face count asked for: ``faces``, or the surface area over the area of an equilateral triangle of side
    ``edge_m``; None when neither is given."""
    if edge_m is not None and faces is not None:
        raise ConfigError("--edge and --faces: give one of them (a target edge length or a face count)")
    if faces is not None:
        return int(faces)
    if edge_m is not None:
        area = float(triangle_areas(V, F).sum())
        return max(4, int(np.ceil(area / (np.sqrt(3) / 4 * float(edge_m) ** 2))))
    return None


def closest_point_on_triangles(P, A, B, C) -> np.ndarray:
    """(M, 3) closest point of triangle ``(A[i], B[i], C[i])`` to ``P[i]`` (Ericson 2004, §5.1.5), vectorised."""
    ab, ac, ap = B - A, C - A, P - A
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = P - B
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = P - C
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        den = va + vb + vc
        v = vb / den
        w = vc / den
        out = A + ab * v[:, None] + ac * w[:, None]  # inside the face
        # edges
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    out = np.where(m[:, None], A + ab * t_ab[:, None], out)
    m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    out = np.where(m[:, None], A + ac * t_ac[:, None], out)
    m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    out = np.where(m[:, None], B + (C - B) * t_bc[:, None], out)
    # vertices
    out = np.where(((d1 <= 0) & (d2 <= 0))[:, None], A, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[:, None], B, out)
    out = np.where(((d6 >= 0) & (d5 <= d6))[:, None], C, out)
    return out


def point_mesh_distance(P, V, F, *, candidates: int = 16, chunk: int = 200_000, return_face: bool = False):
    """(M,) distance (m) of each point to the mesh ``(V, F)``: the least distance to the ``candidates`` triangles
    whose centroids are nearest (exact when the mesh's triangles are small against the distances, as after
    decimation of a fine mesh or on a subdivided reference; an upper bound otherwise). With ``return_face`` also the
    (M,) index of that triangle."""
    from scipy.spatial import cKDTree

    P = np.asarray(P, float)
    cen = V[F].mean(axis=1)
    tree = cKDTree(cen)
    k = min(candidates, len(F))
    out = np.empty(len(P))
    face = np.empty(len(P), np.int64)
    for s in range(0, len(P), chunk):
        p = P[s:s + chunk]
        _, idx = tree.query(p, k=k)
        idx = idx.reshape(len(p), k)
        best = np.full(len(p), np.inf)
        bf = idx[:, 0].copy()
        for j in range(k):
            t = F[idx[:, j]]
            q = closest_point_on_triangles(p, V[t[:, 0]], V[t[:, 1]], V[t[:, 2]])
            dj = np.linalg.norm(p - q, axis=1)
            better = dj < best
            best = np.where(better, dj, best)
            bf = np.where(better, idx[:, j], bf)
        out[s:s + chunk] = best
        face[s:s + chunk] = bf
    return (out, face) if return_face else out


def decimate(V, F, flags, n_faces: int, *, samples: int = 200_000, seed: int = 0):
    """Decimate ``(V, F)`` to about ``n_faces`` triangles (quadric edge collapse, border kept).

    Returns ``(V, F, flags, report)``; ``report``: ``faces_before``, ``faces_after``, ``rms_m`` and ``max_m`` (distance
    of the mesh before to the mesh after, see the module docstring). With ``n_faces`` at or above the face count
    the mesh is returned as it is (``rms_m`` 0).
    """
    n0 = len(F)
    rep = {"faces_before": int(n0), "faces_after": int(n0), "rms_m": 0.0, "max_m": 0.0, "decimated": False}
    if n_faces >= n0 or n0 < 8:
        return V, F, flags, rep
    import fast_simplification

    red = 1.0 - float(n_faces) / n0
    V2, F2 = fast_simplification.simplify(np.ascontiguousarray(V, np.float64), np.ascontiguousarray(F, np.int64),
                                          target_reduction=red, agg=7, preserve_border=True)
    V2 = np.asarray(V2, float)
    F2 = np.asarray(F2, np.int64)
    if len(F2) == 0:
        return V, F, flags, rep
    fl = np.asarray(flags, bool)
    c2 = V2[F2].mean(axis=1)
    flags2 = fl[point_mesh_distance(c2, V, F, return_face=True)[1]]
    for k in range(3):  # and half-way from the centroid to each corner: a face partly made by filling is flagged
        flags2 |= fl[point_mesh_distance(0.5 * (c2 + V2[F2[:, k]]), V, F, return_face=True)[1]]
    rng = np.random.default_rng(seed)
    pick = np.arange(len(V)) if len(V) <= samples else np.sort(rng.choice(len(V), samples, replace=False))
    d = point_mesh_distance(V[pick], V2, F2)
    rep.update(faces_after=int(len(F2)), rms_m=float(np.sqrt(np.mean(d ** 2))), max_m=float(d.max()), decimated=True)
    return V2, F2, flags2, rep
