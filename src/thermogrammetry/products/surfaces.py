"""Per-pixel geometry against a triangle mesh or a DSM (general case of ``thermogrammetry correct``).

Every pixel's line of sight is cast against the mesh (trimesh; Embree through ``embreex`` when
installed, else trimesh's numpy intersector). The first hit gives the face; the angle is taken
between the line of sight and that face's normal and the distance is recomputed in float64 from the
face's plane (Embree intersects in float32). A DSM is turned into a mesh of two triangles per cell
between pixel centres (GeoTIFF transforms address pixel corners: the centre of pixel (col, row) is
``transform * (col + 0.5, row + 0.5)``, docs/conventions.md); cells with a NaN corner are left out.
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidInputError
from .correction import PlaneRaster

__all__ = ["dsm_to_mesh", "mesh_rasters"]


def dsm_to_mesh(z, transform) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate a DSM grid.

    Parameters
    ----------
    z : (H, W) heights (m), NaN = no data
    transform : (a, b, c, d, e, f) GDAL/rasterio affine: ``x = a col + b row + c``, ``y = d col + e row + f``
        addressing pixel corners.

    Returns
    -------
    vertices : (H·W, 3) m; faces : (F, 3) int
    """
    z = np.asarray(z, float)
    if z.ndim != 2 or min(z.shape) < 2:
        raise InvalidInputError(f"DSM: expected a 2D grid of at least 2×2 cells, got shape {z.shape}")
    a, b, c, d, e, f = (float(v) for v in tuple(transform)[:6])
    H, W = z.shape
    col, row = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    x = a * col + b * row + c
    y = d * col + e * row + f
    V = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    idx = np.arange(H * W).reshape(H, W)
    q00, q01, q10, q11 = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.concatenate([np.column_stack([q00, q10, q01]), np.column_stack([q01, q10, q11])])
    ok = np.all(np.isfinite(V[F, 2]), axis=1)
    return V, F[ok]


def mesh_rasters(C, rays, axis, vertices, faces) -> PlaneRaster:
    """Cast every pixel's ray (h, w, 3 unit, world) from ``C`` against a triangle mesh.

    Returns a :class:`PlaneRaster` whose ``plane`` holds the index of the face hit (−1: none),
    ``inset_px`` is +inf where hit (no polygon edges) and ``cover`` is 1 where hit.
    """
    import trimesh

    V = np.asarray(vertices, float)
    Fc = np.asarray(faces, int)
    if V.ndim != 2 or V.shape[1] != 3 or Fc.ndim != 2 or Fc.shape[1] != 3 or len(Fc) == 0:
        raise InvalidInputError(f"mesh: expected vertices (V, 3) and faces (F ≥ 1, 3), got {V.shape} and {Fc.shape}")
    rays = np.asarray(rays, float)
    h, w, _ = rays.shape
    # Embree casts in float32: the mesh is moved so that the camera is at the origin (projected-CRS coordinates
    # such as EPSG:2056 or UTM have a float32 spacing of 0.25-0.5 m); distances and angles do not change
    C = np.asarray(C, float)
    V = V - C
    mesh = trimesh.Trimesh(vertices=V, faces=Fc, process=False)
    d = rays.reshape(-1, 3)
    o = np.zeros_like(d)
    tri = mesh.ray.intersects_first(ray_origins=o, ray_directions=d)
    hit = tri >= 0
    n = np.zeros_like(d)
    tri_hit = tri[hit]
    v0, v1, v2 = V[Fc[tri_hit, 0]], V[Fc[tri_hit, 1]], V[Fc[tri_hit, 2]]
    nn = np.cross(v1 - v0, v2 - v0)
    nn /= np.linalg.norm(nn, axis=1, keepdims=True)
    n[hit] = nn
    den = np.einsum("ij,ij->i", d[hit], nn)
    s = np.einsum("ij,ij->i", v0 - o[hit], nn) / den
    dist = np.full(len(d), np.nan)
    dist[hit] = s
    angle = np.full(len(d), np.nan)
    angle[hit] = np.arccos(np.clip(np.abs(den), 0, 1))
    axang = np.full(len(d), np.nan)
    axang[hit] = np.arccos(np.clip(np.abs(nn @ np.asarray(axis, float)), 0, 1))
    return PlaneRaster(
        plane=np.where(hit, tri, -1).reshape(h, w),
        angle_rad=angle.reshape(h, w),
        axis_angle_rad=axang.reshape(h, w),
        distance_m=dist.reshape(h, w),
        inset_px=np.where(hit, np.inf, np.nan).reshape(h, w),
        cover=hit.astype(int).reshape(h, w),
    )
