"""Visibility: per-pixel ray casting (trimesh with Embree), occlusion and the clean-pixel test of a texel.

Conditions 1–4 of a usable texel are described in :mod:`thermogrammetry.products.texture`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .texture_config import TextureConfig
from .texture_mesh import TextureView, face_geometry, project_to_view

__all__ = ["PixelSurface", "ray_intersector", "pixel_surfaces", "usable_in_view"]


@dataclass
class PixelSurface:
    """Per-pixel ray casting of one image: the first surface hit of every pixel's ray.

    ``offsets`` (H, W, 3) float32: hit point minus ``center`` (NaN = none), ``center`` (3,) float64 the
    camera centre, ``face`` (H, W) int32 (−1 = none). Offsets from the camera keep float32's relative
    precision (6e-5 m at 1 km) at half the memory of float64 points (a texture holds one per image).
    """

    offsets: np.ndarray
    center: np.ndarray
    face: np.ndarray
    #: (n_faces,) int64, the plane of each face (:func:`~.texture_mesh.plane_ids`, shared by the surfaces of one mesh)
    #: or None (each face its own): lets :func:`usable_in_view` pass texels whose pixels all see their own plane without
    #: testing each
    plane_of_face: np.ndarray | None = None

    def points_at(self, rows, cols) -> np.ndarray:
        """(N, 3) float64 hit points of pixels ``(rows, cols)`` (NaN where the ray hits nothing)."""
        return self.center + self.offsets[rows, cols].astype(np.float64)



def _ray_first(intersector, V, F, origins, dirs):
    """First hit of rays: (face (N,), distance along the unit direction (N,), NaN where none)."""
    tri = np.asarray(intersector.intersects_first(ray_origins=origins, ray_directions=dirs), np.int64)
    dist = np.full(len(dirs), np.nan)
    hit = tri >= 0
    if np.any(hit):
        v0 = V[F[tri[hit], 0]]
        n = np.cross(V[F[tri[hit], 1]] - v0, V[F[tri[hit], 2]] - v0)
        den = np.einsum("ij,ij->i", dirs[hit], n)
        with np.errstate(invalid="ignore", divide="ignore"):
            dist[hit] = np.einsum("ij,ij->i", v0 - origins[hit], n) / den
    return tri, dist



def ray_intersector(V, F):
    import trimesh

    mesh = trimesh.Trimesh(V, F, process=False)
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        return RayMeshIntersector(mesh)
    except Exception:  # pragma: no cover - embreex missing: trimesh's pure-python intersector
        return mesh.ray



#: the camera rays of every pixel centre, per camera (:func:`_pixel_grid_rays`): a few cameras, frames up to this size
_GRID_RAYS: dict = {}
_GRID_RAYS_CAMERAS = 4
_GRID_RAYS_MAX_PIXELS = 2**21


def _pixel_grid_rays(camera) -> np.ndarray:
    """``camera.unproject`` of every pixel centre, row-major, (h * w, 3): computed once per camera (its model, size,
    parameters and pitch) and shared by its views (read-only). Each row is computed from its pixel alone, so the
    shared array holds the same values as a new call."""
    w, h = camera.image_size
    key = (str(camera.model), (w, h), np.asarray(camera.params, np.float64).tobytes(), repr(camera.pixel_pitch_um))
    rays = _GRID_RAYS.get(key)
    if rays is None:
        gy, gx = np.mgrid[0:h, 0:w].astype(float)
        rays = np.asarray(camera.unproject(np.stack([gx.ravel(), gy.ravel()], axis=1)))
        if w * h <= _GRID_RAYS_MAX_PIXELS:
            rays.setflags(write=False)
            while len(_GRID_RAYS) >= _GRID_RAYS_CAMERAS:
                _GRID_RAYS.pop(next(iter(_GRID_RAYS)))
            _GRID_RAYS[key] = rays
    return rays


def pixel_surfaces(intersector, vertices, faces, view: TextureView, plane_of_face: np.ndarray | None = None) -> PixelSurface:
    """Cast the ray of every pixel centre of ``view`` against the whole mesh (``plane_of_face``: see
    :class:`PixelSurface`)."""
    V, F = np.asarray(vertices, float), np.asarray(faces, np.int64)
    w, h = view.camera.image_size
    rays_c = _pixel_grid_rays(view.camera)
    d = rays_c @ view.pose.R
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(view.pose.center, d.shape).copy()
    tri, dist = _ray_first(intersector, V, F, o, d)
    off = (dist[:, None] * d).astype(np.float32)
    return PixelSurface(off.reshape(h, w, 3), np.asarray(view.pose.center, np.float64), tri.astype(np.int32).reshape(h, w),
                        plane_of_face)



def _window_face_range(face: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest face (or plane) index (-1 = none) over the window of rows ``y - r .. y + r + 1`` and columns
    ``x - r .. x + r + 1`` of every pixel ``(y, x)``, the image's border replicated (float32 holds face indices below
    2**24 exactly; larger meshes get an exact sliding minimum/maximum instead)."""
    import cv2

    k = 2 * r + 2
    if face.size and int(face.max()) < 2**24:
        f = face.astype(np.float32)
        kernel = np.ones((k, k), np.uint8)
        lo = cv2.erode(f, kernel, anchor=(r, r), borderType=cv2.BORDER_REPLICATE)
        hi = cv2.dilate(f, kernel, anchor=(r, r), borderType=cv2.BORDER_REPLICATE)
        return lo.astype(np.int64), hi.astype(np.int64)
    from scipy.ndimage import maximum_filter, minimum_filter

    # scipy's window of even size k centred at k // 2 = r + 1: origin -1 shifts it to y - r .. y + r + 1
    return (minimum_filter(face, size=k, mode="nearest", origin=-1).astype(np.int64),
            maximum_filter(face, size=k, mode="nearest", origin=-1).astype(np.int64))



def usable_in_view(intersector, vertices, faces, view: TextureView, surface: PixelSurface, points, face_index,
                   cfg: TextureConfig):
    """Which points (on faces ``face_index``) are usable in ``view`` (conditions 1–4 of :mod:`thermogrammetry.products.texture`).

    Returns
    -------
    usable : (N,) bool
    xy : (N, 2) pixel coordinates
    cos_theta : (N,) cosine of the viewing angle
    distance_m : (N,) camera-to-point distance
    occluded : (N,) bool, inside the image and facing the camera but hidden by other geometry
    in_view : (N,) bool, conditions 1–3 (inside, facing within ``max_angle_deg``, not occluded): the point is
        visible in the image, usable or not (condition 4 leaves out mixed pixels at edges and folds)
    """
    V, F = np.asarray(vertices, float), np.asarray(faces, np.int64)
    X = np.asarray(points, float)
    fi = np.asarray(face_index, np.int64)
    normals, _, _ = face_geometry(V, F)
    n = normals[fi]
    w, h = view.camera.image_size
    C = view.pose.center
    dvec = C - X
    dist = np.linalg.norm(dvec, axis=1)
    cos_t = np.einsum("ij,ij->i", n, dvec) / dist
    xy, z = project_to_view(view, X)
    m = cfg.border_px
    inside = (z > 1e-6) & np.isfinite(xy[:, 0]) & (xy[:, 0] >= m) & (xy[:, 0] <= w - 1 - m) & (xy[:, 1] >= m) & (xy[:, 1] <= h - 1 - m)
    facing = cos_t >= np.cos(np.deg2rad(cfg.max_angle_deg))
    cand = inside & facing
    visible = np.zeros(len(X), bool)
    idx = np.flatnonzero(cand)
    if len(idx):
        u = -dvec[idx] / dist[idx, None]
        o = np.broadcast_to(C, u.shape).copy()
        tri, tdist = _ray_first(intersector, V, F, o, u)
        visible[idx] = np.isfinite(tdist) & (tdist >= dist[idx] - cfg.occlusion_tol_m)
    occluded = cand & ~visible
    usable = cand & visible
    in_view = usable.copy()
    # (4) the pixels under the bilinear footprint (+ clean_radius_px) see the texel's plane
    idx = np.flatnonzero(usable)
    if len(idx):
        r = int(cfg.clean_radius_px)
        x0 = np.floor(xy[idx, 0]).astype(np.int64)
        y0 = np.floor(xy[idx, 1]).astype(np.int64)
        clean = np.ones(len(idx), bool)
        cmin = np.cos(np.deg2rad(cfg.normal_tol_deg))
        # a pixel that sees the texel's own plane is clean (its point lies in that plane, its normal is the texel's).
        # Texels whose whole window of pixels sees their own plane are therefore clean: the smallest and largest plane
        # index over each window (rows y0 - r .. y0 + r + 1, columns alike, borders replicated as np.clip does) by a
        # morphological erosion and dilation. Only the texels of mixed windows are tested pixel by pixel, and there
        # only the pixels that see another plane or nothing (the same result as testing every pixel)
        pof = surface.plane_of_face
        plane_img = surface.face.astype(np.int64) if pof is None else np.where(surface.face >= 0, pof[np.maximum(surface.face, 0)], -1)
        own = fi[idx] if pof is None else pof[fi[idx]]
        lo, hi = _window_face_range(plane_img, r)
        rest = np.flatnonzero((lo[y0, x0] != own) | (hi[y0, x0] != own))
        if len(rest):
            y0r, x0r, own_r = y0[rest], x0[rest], own[rest]
            ni = n[idx[rest]]
            d0 = np.einsum("ij,ij->i", ni, X[idx[rest]])
            ok = np.ones(len(rest), bool)
            for dy in range(-r, 2 + r):
                yy = np.clip(y0r + dy, 0, h - 1)
                for dx in range(-r, 2 + r):
                    xx = np.clip(x0r + dx, 0, w - 1)
                    pf = surface.face[yy, xx]
                    k = np.flatnonzero((plane_img[yy, xx] != own_r) & ok)
                    if not len(k):
                        continue
                    p = surface.points_at(yy[k], xx[k])
                    off = np.abs(np.einsum("ij,ij->i", ni[k], p) - d0[k])
                    agree = np.einsum("ij,ij->i", ni[k], normals[np.maximum(pf[k], 0)]) >= cmin
                    ok[k] &= np.isfinite(off) & (off <= cfg.surface_tol_m) & (pf[k] >= 0) & agree
            clean[rest] = ok
        usable[idx] = clean
    return usable, xy, cos_t, dist, occluded, in_view
