"""The mesh and the oriented images of a texture in one local frame: checks, face geometry, planes, projection.

Embree and xatlas compute in float32, so every texturing step runs on ``vertices - local_origin(vertices)`` with
the views moved accordingly (:func:`view_in_frame`); see :mod:`thermogrammetry.products.texture`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError, ShapeError

__all__ = ["TextureView", "local_origin", "view_in_frame", "check_mesh", "face_geometry", "plane_ids", "project_to_view"]


@dataclass
class TextureView:
    """One oriented thermal image: ``camera`` (a :class:`~thermogrammetry.Camera`), ``pose``
    (``cam_from_world`` :class:`~thermogrammetry.geometry.Pose`) and ``image_k`` (H, W) kelvin — or the frame's
    raw sensor counts (uint16 -> float32, exact) when the survey has no temperature frames; the texture then
    holds counts throughout (``temperature_k`` fields included) and the caller labels them (pipeline.texture).
    All views of one texture share one unit."""

    name: str
    camera: object
    pose: object
    image_k: np.ndarray

    def __post_init__(self):
        img = np.asarray(self.image_k)
        w, h = self.camera.image_size
        if img.shape != (h, w):
            raise ShapeError(f"view {self.name!r}: image shape {img.shape}; expected (H, W) = ({h}, {w}) from its camera")
        self.image_k = img.astype(np.float32, copy=False)



def local_origin(vertices) -> np.ndarray:
    """A float64 origin near a mesh for the libraries that compute in float32 (Embree's ray casting, xatlas).

    Coordinates in a projected CRS are large (EPSG:2056 eastings ~2.6e6 m, UTM northings ~5e6 m): their float32
    spacing is 0.25-0.5 m, so rays cast against such a mesh hit the wrong triangle or miss and charts are built
    from vertices rounded by decimetres. Every computation of the texturing runs on ``vertices - origin`` with the
    poses moved accordingly (:func:`view_in_frame`); results are returned in the input's coordinates.

    Returns
    -------
    (3,) float64: the centre of the vertices' bounding box, rounded to whole metres
    """
    V = np.asarray(vertices, dtype=np.float64)
    return np.round(0.5 * (V.min(axis=0) + V.max(axis=0)))



def view_in_frame(view: "TextureView", origin) -> "TextureView":
    """The same view with its pose expressed for points ``X - origin``: ``t' = t + R·origin`` (same ``R``)."""
    from ..geometry import Pose

    o = np.asarray(origin, dtype=np.float64)
    return TextureView(view.name, view.camera, Pose(view.pose.R, view.pose.t + view.pose.R @ o), view.image_k)



def check_mesh(vertices, faces):
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) < 3:
        raise ShapeError(f"mesh vertices: expected (V, 3) with V >= 3, got shape {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or len(F) < 1:
        raise ShapeError(f"mesh faces: expected (F, 3) triangles, got shape {F.shape}")
    F = F.astype(np.int64)
    if F.min() < 0 or F.max() >= len(V):
        raise InvalidInputError(f"mesh faces: vertex index out of range [0, {len(V) - 1}] (min {F.min()}, max {F.max()})")
    if not np.all(np.isfinite(V)):
        raise InvalidInputError("mesh vertices: non-finite coordinates")
    return V, F



def face_geometry(V, F):
    e1 = V[F[:, 1]] - V[F[:, 0]]
    e2 = V[F[:, 2]] - V[F[:, 0]]
    n = np.cross(e1, e2)
    area2 = np.linalg.norm(n, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        normals = n / area2[:, None]
    return normals, 0.5 * area2, V[F].mean(axis=1)



def plane_ids(vertices, faces) -> np.ndarray:
    """(n_faces,) int64: faces that lie in one plane share an id (unit normal and offset equal after rounding to 1e-9;
    faces of a triangulated CAD wall, not the nearly coplanar faces of a scanned mesh, which keep ids of their own)."""
    V, F = np.asarray(vertices, float), np.asarray(faces, np.int64)
    normals, _, _ = face_geometry(V, F)
    d = np.einsum("ij,ij->i", normals, V[F[:, 0]])
    key = np.round(np.column_stack([normals, d]), 9)
    ok = np.all(np.isfinite(key), axis=1)  # degenerate faces (no normal): each an id of its own
    ids = np.arange(len(F), dtype=np.int64) + len(F)
    if ok.any():
        _, inv = np.unique(key[ok], axis=0, return_inverse=True)
        ids[ok] = inv.ravel()
    return ids



def project_to_view(view: TextureView, X):
    """Pixel coordinates (N, 2) and depth (N,) of world points; NaN pixels behind the camera."""
    Xc = X @ view.pose.R.T + view.pose.t
    z = Xc[:, 2]
    xy = np.full((len(X), 2), np.nan)
    front = z > 1e-6
    if np.any(front):
        xy[front] = view.camera.project(Xc[front])
    return xy, z
