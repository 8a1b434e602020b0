"""Thermal textures of meshes: the best image per face, occlusion by ray casting, float temperatures.

Given a triangle mesh (any source: our dense cloud, an RGB photogrammetry package, a laser scanner, a
CAD model) and oriented thermal images (``cameras.json`` + frames), every texel of a texture atlas gets
the temperature of ONE image, sampled bilinearly at the texel's 3D point; which image is recorded in a
source-id texture. Nothing is blended and nothing is filled: a texel that no image sees cleanly stays
NaN with source −1, and the faces without any texel are listed.

View selection (documented score, per face)
-------------------------------------------
For face ``f`` (unit normal ``n``, centroid ``c``) and image ``k`` (centre ``C_k``, focal length ``f_k``
in pixels) with ``d = |C_k − c|`` and ``cos θ = n·(C_k − c)/d``:

    score(f, k) = (f_k cos θ / d) · min(1, b / b0)

``f_k cos θ / d`` is the image's resolution on the surface (pixels per metre along the steepest
direction of the face: it falls with distance and with the viewing angle θ), ``b`` is the distance in
pixels of the face's projected centroid from the nearest image border and
``b0 = border_fraction · min(W, H)`` (distortion and vignetting are largest near the border). A large face
(a ground cell beside a standing camera, a CAD wall of two triangles) can be seen at a grazing angle from its
centroid, or have its centroid outside the image, and still be partly seen well: when the centroid fails either
test, cos θ and ``b`` are the largest over a few points of the face (vertices, edge midpoints, the point nearest
to ``C_k`` -- where θ is smallest on a plane -- and three points from there towards the centroid, and where the
rays of a 4 x 4 grid of pixels meet the face), a generous test since each texel is tested on its own. Faces
seen at θ > ``max_angle_deg`` at all these points, behind the camera, or with all of them outside the image get
no score from that image (a face partly outside an image can still take texels from it: each texel is tested on
its own).
Every texel takes the highest-scoring image of its face **in which the texel itself
is usable**, so a face keeps one image unless an occlusion forces a change inside it.

A texel is usable in image ``k`` when
(1) its point projects inside the image with ``border_px`` to spare;
(2) it is in front and seen at θ ≤ ``max_angle_deg`` (θ from the face normal at the texel);
(3) it is **not occluded**: the ray from ``C_k`` through the point, cast against the whole mesh
    (trimesh with Embree), first hits the surface within ``occlusion_tol_m`` of the point;
(4) the image's pixels that the bilinear sample touches (and ``clean_radius_px`` around them, for the
    optics' blur) all see the texel's own surface: the same per-pixel ray casting gives each pixel's
    surface point and face, the point must lie within ``surface_tol_m`` of the texel face's plane and
    the face's normal within ``normal_tol_deg`` of the texel face's normal. This keeps mixed pixels at
    occlusion edges (an occluder's silhouette) and at folds (a building corner) out of the texture.

Optional steps (both change values and say so in ``texture.json``):

* ``levelling="offsets"``: per-image additive offsets ``o_k`` from the overlaps, least squares over
  texel pairs ``T_a(x) + o_a = T_b(x) + o_b`` with the image that supplies most texels held at 0
  (seam levelling for images with drifting offsets; it alters every temperature of the other images
  by its ``o_k``).
* ``correct=True``: per-texel inversion ``T0⁴ = τ[εT⁴ + (1−ε)Ta⁴] + (1−τ)Tatm⁴`` with ε(θ) from the
  mesh normal at the texel and τ over the real camera-to-texel distance: the products layer's
  per-pixel correction (:mod:`thermogrammetry.products.correction`, its :class:`CorrectionConfig`).

Rig mode: when only the RGB images were oriented, :func:`thermal_poses_from_rig` derives the thermal
poses through the constant relative orientation (seed 002 eq. 4–5, in our ``cam_from_world`` terms:
``R_IR = R_rel R_RGB``, ``t_IR = R_rel t_RGB + t_rel``; see :mod:`thermogrammetry.adjustment.problem`).

References
----------
.. [1] Barazzetti L., Erba S., Previtali M., Rosina E., Scaioni M. (2013), seed 002: thermal textures of
   building models from thermal + RGB images, bi-camera rig (eq. 4–5), best image per triangle.
.. [2] Sawicki P., Stein R., Więcek B. (seed 000) eq. 7–8: directional correction.
.. [3] Young J. et al., xatlas: mesh parameterisation and chart packing (github.com/jpcy/xatlas).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from .._sampling import bilinear
from ..enums import StrChoice
from ..errors import ConfigError, InvalidInputError, ShapeError
from .._validate import config_keys
from .correction import CorrectionConfig

__all__ = ["Levelling", "TextureConfig", "TextureView", "TextureResult", "face_view_scores", "scores_at",
           "any_face_seen", "build_atlas", "rasterize_atlas", "PixelSurface", "pixel_surfaces", "plane_ids", "usable_in_view", "select_and_sample",
           "select_in_chunks", "estimate_offsets", "texture_mesh", "thermal_poses_from_rig", "local_origin", "view_in_frame"]


class Levelling(StrChoice):
    NONE = "none"
    OFFSETS = "offsets"


@dataclass(frozen=True)
class TextureConfig:
    """How a mesh is textured. Unknown keys in :meth:`from_dict` are errors."""

    texel_size_m: float | None = None  # None: half the median surface pixel size of the chosen images
    max_texture_px: int = 4096
    padding_texels: int = 2
    max_angle_deg: float = 75.0
    border_px: float = 2.0
    border_fraction: float = 0.1
    occlusion_tol_m: float = 0.02
    surface_tol_m: float = 0.05
    normal_tol_deg: float = 30.0
    clean_radius_px: int = 1
    # faces with no texel usable at clean_radius_px take texels usable at the largest smaller radius down to this one
    # (None: no fallback)
    min_clean_radius_px: int | None = None
    levelling: Levelling = Levelling.NONE
    offsets_max_pairs: int = 200_000
    correct: bool = False
    correction: CorrectionConfig = field(default_factory=CorrectionConfig)

    def __post_init__(self):
        object.__setattr__(self, "levelling", Levelling(self.levelling))
        if self.texel_size_m is not None and not (np.isfinite(self.texel_size_m) and self.texel_size_m > 0):
            raise ConfigError(f"TextureConfig.texel_size_m={self.texel_size_m!r}: expected a positive number of metres or None")
        if not 0 < self.max_angle_deg < 90:
            raise ConfigError(f"TextureConfig.max_angle_deg={self.max_angle_deg!r}: expected degrees in (0, 90)")
        if int(self.max_texture_px) < 64:
            raise ConfigError(f"TextureConfig.max_texture_px={self.max_texture_px!r}: expected at least 64")
        if self.min_clean_radius_px is not None and not (int(self.min_clean_radius_px) == self.min_clean_radius_px
                                                         and self.min_clean_radius_px >= 0):
            raise ConfigError(f"TextureConfig.min_clean_radius_px={self.min_clean_radius_px!r}: expected an integer >= 0 or None")
        for k in ("border_px", "occlusion_tol_m", "surface_tol_m"):
            if not getattr(self, k) >= 0:
                raise ConfigError(f"TextureConfig.{k}={getattr(self, k)!r}: expected a number >= 0")
        if isinstance(self.correction, dict):
            object.__setattr__(self, "correction", CorrectionConfig.from_dict(self.correction))

    @classmethod
    def from_dict(cls, d: dict) -> "TextureConfig":
        return cls(**config_keys(cls, d))


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
    from vertices rounded by decimetres. Every computation of this module runs on ``vertices - origin`` with the
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


def _check_mesh(vertices, faces):
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


def _face_geometry(V, F):
    e1 = V[F[:, 1]] - V[F[:, 0]]
    e2 = V[F[:, 2]] - V[F[:, 0]]
    n = np.cross(e1, e2)
    area2 = np.linalg.norm(n, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        normals = n / area2[:, None]
    return normals, 0.5 * area2, V[F].mean(axis=1)


def _project(view: TextureView, X):
    """Pixel coordinates (N, 2) and depth (N,) of world points; NaN pixels behind the camera."""
    Xc = X @ view.pose.R.T + view.pose.t
    z = Xc[:, 2]
    xy = np.full((len(X), 2), np.nan)
    front = z > 1e-6
    if np.any(front):
        xy[front] = view.camera.project(Xc[front])
    return xy, z


def _focal_px(camera) -> float:
    K = camera.K
    return 0.5 * (K[0, 0] + K[1, 1])


def face_view_scores(vertices, faces, views: Sequence[TextureView], *, max_angle_deg: float = 75.0,
                     border_fraction: float = 0.1):
    """The documented per-face score (module docstring) of every image: (F, K) sparse, absent = unusable.

    Parameters
    ----------
    vertices : (V, 3) metres; faces : (F, 3) vertex indices; views : K oriented images.

    Returns
    -------
    ``scipy.sparse.csc_matrix`` (F, K) float64 holding the positive scores only (sorted row indices per image):
    ``f cos θ / d · min(1, b / b0)`` in pixels per metre; absent (0) where θ > ``max_angle_deg``, behind the
    camera or outside the image (a large face: see the module docstring). Occlusion is not part of the score (it is tested per
    texel). Sparse because each face is seen by a few of the images: a dense matrix was 1.6 GB at 1 M faces x
    200 images. ``.toarray()`` gives the dense matrix; :func:`scores_at` reads one image's scores of given faces.
    """
    import scipy.sparse as sp

    V, F = _check_mesh(vertices, faces)
    rows, vals, ptr = [], [], [0]
    for k, col in _score_columns(V, F, views, max_angle_deg, border_fraction):
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


def _score_max_count(scores) -> tuple[np.ndarray, np.ndarray]:
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
    V, F = _check_mesh(vertices, faces)
    return any(np.any(col > 0) for _, col in _score_columns(V, F, views, max_angle_deg, border_fraction))


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
    xy, z = _project(view, X)
    bx = np.minimum(xy[:, 0] + 0.5, w - 0.5 - xy[:, 0])
    by = np.minimum(xy[:, 1] + 0.5, h - 0.5 - xy[:, 1])
    return np.nan_to_num(np.where(z > 1e-6, np.minimum(bx, by), -np.inf), nan=-np.inf)


def _score_columns(V, F, views, max_angle_deg, border_fraction, large_faces: bool = True):
    """Yield ``(k, (F,) scores of image k)`` (see :func:`face_view_scores`); ``large_faces=False``: scored at the
    centroid only."""
    normals, _, cen = _face_geometry(V, F)
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
        # largest cos θ and border distance over a few points of the face count (module docstring). Only faces large
        # enough for that are looked at: seen from the centroid, no point of a face is more than its longest edge / d
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


# ---------------------------------------------------------------------------------------------- atlas
@dataclass
class Atlas:
    """An xatlas parameterisation: ``vmapping`` (N,) original vertex of each atlas vertex, ``faces`` (F, 3)
    atlas-vertex indices (same face order as the input), ``uv`` (N, 2) in [0, 1] with v measured from
    the TOP row of the texture (row = v · height), ``size`` (width, height) in texels."""

    vmapping: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    size: tuple[int, int]
    texel_size_m: float


def build_atlas(vertices, faces, texel_size_m: float, *, max_texture_px: int = 4096, padding: int = 2) -> Atlas:
    """Charts and packing with xatlas at ``texel_size_m``; coarsened until the atlas fits ``max_texture_px``."""
    import xatlas

    V, F = _check_mesh(vertices, faces)
    V32 = (V - local_origin(V)).astype(np.float32)  # xatlas works in float32: charts from local coordinates
    ts = float(texel_size_m)
    for _ in range(12):
        atlas = xatlas.Atlas()
        atlas.add_mesh(V32, F.astype(np.uint32))
        po = xatlas.PackOptions()
        po.texels_per_unit = 1.0 / ts
        po.padding = int(padding)
        po.bilinear = True
        po.blockAlign = False
        atlas.generate(xatlas.ChartOptions(), po)
        w, h = int(atlas.width), int(atlas.height)
        if max(w, h) <= max_texture_px and atlas.atlas_count == 1:
            vmap, idx, uv = atlas[0]
            idx = np.asarray(idx, np.int64)
            if len(idx) != len(F) or not np.array_equal(np.asarray(vmap, np.int64)[idx], F):
                raise InvalidInputError("xatlas changed the face order or topology; expected one atlas face per mesh face")
            return Atlas(np.asarray(vmap, np.int64), idx, np.asarray(uv, np.float64), (w, h), ts)
        ts *= max(1.25, max(w, h) / max_texture_px * 1.05)
    raise InvalidInputError(f"mesh too large for a {max_texture_px}-texel atlas even at {ts:.3g} m per texel")


@dataclass
class Texels:
    """Texel centres inside atlas triangles: ``rc`` (T, 2) row/col, ``face`` (T,), ``bary`` (T, 3), ``points`` (T, 3)."""

    rc: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    points: np.ndarray


def rasterize_atlas(atlas: Atlas, vertices, faces, *, chunk: int = 2_000_000) -> Texels:
    """Texel centres ``((col + 0.5)/W, (row + 0.5)/H)`` that fall inside each atlas triangle (vectorised).

    A texel on an edge shared by two triangles goes to the first; texels in the gutter belong to no face.
    """
    V, F = _check_mesh(vertices, faces)
    W, H = atlas.size
    P = atlas.uv[atlas.faces] * np.array([W, H])  # (F, 3, 2) in texel units
    lo = np.floor(P.min(axis=1) - 0.5).astype(np.int64)
    hi = np.ceil(P.max(axis=1) - 0.5).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [W - 1, H - 1])
    nx = np.maximum(hi[:, 0] - lo[:, 0] + 1, 0)
    ny = np.maximum(hi[:, 1] - lo[:, 1] + 1, 0)
    n = nx * ny
    out_f, out_rc, out_b = [], [], []
    starts = np.concatenate([[0], np.cumsum(n)])
    fi_all = np.arange(len(F))
    pos = 0
    while pos < len(F):
        end = int(np.searchsorted(starts, starts[pos] + chunk, side="right")) - 1
        end = max(end, pos + 1)
        fs = fi_all[pos:end]
        cnt = n[fs]
        f_rep = np.repeat(fs, cnt)
        local = np.arange(cnt.sum()) - np.repeat(starts[fs] - starts[pos], cnt)
        col = lo[f_rep, 0] + local % np.maximum(nx[f_rep], 1)
        row = lo[f_rep, 1] + local // np.maximum(nx[f_rep], 1)
        p = np.stack([col + 0.5, row + 0.5], axis=1)
        a, b, c = P[f_rep, 0], P[f_rep, 1], P[f_rep, 2]
        v0, v1, v2 = b - a, c - a, p - a
        den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
        with np.errstate(invalid="ignore", divide="ignore"):
            l1 = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
            l2 = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
        l0 = 1 - l1 - l2
        eps = -1e-9
        inside = (l0 >= eps) & (l1 >= eps) & (l2 >= eps) & np.isfinite(l1)
        out_f.append(f_rep[inside])
        out_rc.append(np.stack([row[inside], col[inside]], axis=1))
        out_b.append(np.stack([l0[inside], l1[inside], l2[inside]], axis=1))
        pos = end
    face = np.concatenate(out_f) if out_f else np.zeros(0, np.int64)
    rc = np.concatenate(out_rc) if out_rc else np.zeros((0, 2), np.int64)
    bary = np.concatenate(out_b) if out_b else np.zeros((0, 3))
    key = rc[:, 0] * W + rc[:, 1]
    _, first = np.unique(key, return_index=True)
    first.sort()
    face, rc, bary = face[first], rc[first], np.clip(bary[first], 0, 1)
    bary /= bary.sum(axis=1, keepdims=True)
    pts = np.einsum("tj,tjk->tk", bary, V[F[face]])
    return Texels(rc, face, bary, pts)


# ---------------------------------------------------------------------------------------------- visibility
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
    #: (n_faces,) int64, the plane of each face (:func:`plane_ids`, shared by the surfaces of one mesh) or None (each
    #: face its own): lets :func:`usable_in_view` pass texels whose pixels all see their own plane without testing each
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


def _intersector(V, F):
    import trimesh

    mesh = trimesh.Trimesh(V, F, process=False)
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        return RayMeshIntersector(mesh)
    except Exception:  # pragma: no cover - embreex missing: trimesh's pure-python intersector
        return mesh.ray


def plane_ids(vertices, faces) -> np.ndarray:
    """(n_faces,) int64: faces that lie in one plane share an id (unit normal and offset equal after rounding to 1e-9;
    faces of a triangulated CAD wall, not the nearly coplanar faces of a scanned mesh, which keep ids of their own)."""
    V, F = np.asarray(vertices, float), np.asarray(faces, np.int64)
    normals, _, _ = _face_geometry(V, F)
    d = np.einsum("ij,ij->i", normals, V[F[:, 0]])
    key = np.round(np.column_stack([normals, d]), 9)
    ok = np.all(np.isfinite(key), axis=1)  # degenerate faces (no normal): each an id of its own
    ids = np.arange(len(F), dtype=np.int64) + len(F)
    if ok.any():
        _, inv = np.unique(key[ok], axis=0, return_inverse=True)
        ids[ok] = inv.ravel()
    return ids


def pixel_surfaces(intersector, vertices, faces, view: TextureView, plane_of_face: np.ndarray | None = None) -> PixelSurface:
    """Cast the ray of every pixel centre of ``view`` against the whole mesh (``plane_of_face``: see
    :class:`PixelSurface`)."""
    V, F = np.asarray(vertices, float), np.asarray(faces, np.int64)
    w, h = view.camera.image_size
    gy, gx = np.mgrid[0:h, 0:w].astype(float)
    rays_c = view.camera.unproject(np.stack([gx.ravel(), gy.ravel()], axis=1))
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
    """Which points (on faces ``face_index``) are usable in ``view`` (conditions 1–4 of the module docstring).

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
    normals, _, _ = _face_geometry(V, F)
    n = normals[fi]
    w, h = view.camera.image_size
    C = view.pose.center
    dvec = C - X
    dist = np.linalg.norm(dvec, axis=1)
    cos_t = np.einsum("ij,ij->i", n, dvec) / dist
    xy, z = _project(view, X)
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


def select_in_chunks(intersector, vertices, faces, views, surfaces, scores, points, face_index, cfg: TextureConfig, *,
                     sample=None, chunk_point_views: int = CHUNK_POINT_VIEWS):
    """:func:`select_and_sample` over chunks of points, so that memory does not grow with points × images.

    Parameters
    ----------
    sample : optional (N,) bool, the points whose values in every usable view are kept (for levelling)
    chunk_point_views : points per chunk × number of views

    Returns
    -------
    selection : :class:`Selection` with ``occluded_in`` and ``all_k`` None (same per-point results as one call)
    occluded_per_view : (K,) int, points inside view k, facing it, hidden by other geometry
    sample_all_k : (S, K) float32 values of the ``sample`` points (in point order), or None
    """
    N, K = len(points), len(views)
    step = max(1, int(chunk_point_views) // max(K, 1))
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
    all_k = (np.concatenate(kept) if kept else np.zeros((0, K), np.float32)) if sample is not None else None
    return Selection(src, T, ang, dist, n_ok, None, None, n_vis), occluded, all_k


def _levelling_sample(n: int, size: int, seed: int = 0) -> np.ndarray:
    """(n,) bool: ``size`` points drawn without replacement (all of them when n <= size), seeded."""
    m = np.zeros(n, bool)
    if n <= size:
        m[:] = True
    else:
        m[np.random.default_rng(seed).choice(n, size, replace=False)] = True
    return m


def estimate_offsets(selection: Selection, n_views: int, *, max_pairs: int = 200_000, seed: int = 0,
                     fixed: int | None = None):
    """Least-squares per-image offsets from overlaps (module docstring), one image held at 0.

    ``fixed``: the image held at 0 (default: the one that supplies most points of ``selection``; a caller that
    passes a subsample of its points gives the image that supplies most of all of them).

    Returns ``(offsets_k (K,), fixed index, pairs per image (K,), rms_before_k, rms_after_k)``; images
    without overlap keep offset 0 (pairs = 0).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import lsqr

    src = selection.source
    rows = np.flatnonzero((src >= 0) & (selection.n_usable >= 2))
    rng = np.random.default_rng(seed)
    A = selection.all_k[rows]  # float32; differences are taken in float64 (exact)
    fin = np.isfinite(A)
    # pairs are numbered image pair by image pair (k < j), rows in order within a pair; only the pairs kept by the
    # subsample are materialised (all pairs of a 2.4 M-texel, 40-image wall took 7.4 GB before)
    blocks = [(k, j, int(np.count_nonzero(fin[:, k] & fin[:, j]))) for k in range(n_views) for j in range(k + 1, n_views)]
    blocks = [bl for bl in blocks if bl[2] > 0]
    counts = np.bincount(src[src >= 0], minlength=n_views)
    fixed = int(np.argmax(counts)) if fixed is None else int(fixed)
    if not blocks:
        return np.zeros(n_views), fixed, np.zeros(n_views, np.int64), float("nan"), float("nan")
    total = sum(bl[2] for bl in blocks)
    keep = np.sort(rng.choice(total, max_pairs, replace=False)) if total > max_pairs else None
    a_idx, b_idx, diff = [], [], []
    start = 0
    for k, j, n in blocks:
        if keep is None:
            take = slice(None)
        else:
            lo, hi = np.searchsorted(keep, [start, start + n])
            start += n
            if lo == hi:
                continue
            take = keep[lo:hi] - (start - n)
        r = np.flatnonzero(fin[:, k] & fin[:, j])[take]
        a_idx.append(np.full(len(r), k))
        b_idx.append(np.full(len(r), j))
        diff.append(A[r, k].astype(np.float64) - A[r, j].astype(np.float64))
    a = np.concatenate(a_idx)
    b = np.concatenate(b_idx)
    dd = np.concatenate(diff)
    pairs = np.bincount(a, minlength=n_views) + np.bincount(b, minlength=n_views)
    # T_a + o_a = T_b + o_b  ->  o_a - o_b = -(T_a - T_b); unknowns: all but the fixed image
    free = np.array([k for k in range(n_views) if k != fixed and pairs[k] > 0])
    col = -np.ones(n_views, np.int64)
    col[free] = np.arange(len(free))
    r = np.arange(len(dd))
    ra, rb = col[a] >= 0, col[b] >= 0
    M = coo_matrix((np.concatenate([np.ones(ra.sum()), -np.ones(rb.sum())]),
                    (np.concatenate([r[ra], r[rb]]), np.concatenate([col[a][ra], col[b][rb]]))),
                   shape=(len(dd), max(len(free), 1))).tocsr()
    x = lsqr(M, -dd, atol=1e-12, btol=1e-12)[0] if len(free) else np.zeros(0)
    off = np.zeros(n_views)
    off[free] = x
    rms_before = float(np.sqrt(np.mean(dd**2)))
    rms_after = float(np.sqrt(np.mean((dd + off[a] - off[b]) ** 2)))
    return off, fixed, pairs, rms_before, rms_after


def _correct(T, angle_deg, dist, cc: CorrectionConfig):
    """The products layer's per-pixel kernel (:func:`~thermogrammetry.products.correction.apply_correction`)
    at the texels: angle from the mesh normal, distance from the source camera."""
    from .correction import apply_correction

    on = np.isfinite(angle_deg) & np.isfinite(T)
    Tc, _, _, valid = apply_correction(np.where(on, T, 300.0), np.deg2rad(np.where(on, angle_deg, 0.0)),
                                       np.where(on, dist, 0.0), on, cc)
    return np.where(valid, Tc, np.nan)


# ---------------------------------------------------------------------------------------------- driver
@dataclass
class TextureResult:
    """A textured mesh.

    Attributes
    ----------
    vertices, faces : the input mesh
    atlas : :class:`Atlas` (uv per atlas vertex, ``vmapping`` to the input vertices)
    temperature_k : (H, W) float32 texture, NaN = no texel
    source : (H, W) int32 texture, view index, −1 = none
    angle_deg : (H, W) float32 viewing angle of the source image
    vertex_temperature_k : (V,) float64, NaN where no image sees the vertex cleanly
    face_coverage : (F,) fraction of each face's texels that are textured (NaN: face has no texel)
    face_views : (F,) number of images with a positive score for the face (a generous test: see the module
        docstring; a face may be scored and yet have no texel visible)
    face_source : (F,) the view most of the face's texels came from (−1 = none)
    view_names : list of K image names (source index -> name)
    offsets_k : (K,) applied per-image offsets (zeros without levelling); ``levelling_fixed`` index
    occluded_texels : (K,) texels inside view k and facing it but hidden by other geometry
    texels_total : number of texel centres inside triangles
    face_visible : (F,) bool, faces with a texel that some image sees (inside, within ``max_angle_deg``, not
        occluded: conditions 1–3), textured or not -- the denominator of the coverage
    face_min_radius : (F,) bool, faces textured only below ``clean_radius_px`` (none of their texels was clean at it;
        they took texels at the largest smaller radius, down to ``config.min_clean_radius_px``)
    """

    vertices: np.ndarray
    faces: np.ndarray
    atlas: Atlas
    temperature_k: np.ndarray
    source: np.ndarray
    angle_deg: np.ndarray
    vertex_temperature_k: np.ndarray
    face_coverage: np.ndarray
    face_views: np.ndarray
    face_source: np.ndarray
    view_names: list
    offsets_k: np.ndarray
    levelling_fixed: int | None
    levelling_rms_k: tuple | None
    occluded_texels: np.ndarray
    texels: Texels = field(repr=False)
    texel_selection: Selection = field(repr=False)
    config: TextureConfig = field(default_factory=TextureConfig)
    face_visible: np.ndarray | None = None
    face_min_radius: np.ndarray | None = None

    @property
    def faces_total(self) -> int:
        return int(len(self.faces))

    @property
    def faces_textured(self) -> np.ndarray:
        """(F,) bool: faces with at least one textured texel."""
        return np.nan_to_num(self.face_coverage) > 0

    def summary(self) -> dict:
        tex = self.texel_selection.source >= 0
        return {
            "faces_total": self.faces_total,
            "faces_textured": int(self.faces_textured.sum()),
            "faces_fully_textured": int(np.sum(np.nan_to_num(self.face_coverage) >= 1.0)),
            "faces_seen": int(np.sum(self.face_views > 0)),
            **({"faces_visible": int(self.face_visible.sum()),
                "faces_visible_textured": int(np.sum(self.face_visible & self.faces_textured))}
               if self.face_visible is not None else {}),
            **({"faces_textured_at_min_clean_radius": int(self.face_min_radius.sum())}
               if self.face_min_radius is not None and self.config.min_clean_radius_px is not None else {}),
            "faces_untextured": np.flatnonzero(~self.faces_textured).tolist(),
            "texels_total": int(len(tex)),
            "texels_textured": int(tex.sum()),
            "views_per_face_histogram": np.bincount(self.face_views, minlength=1).tolist(),
            "texel_size_m": self.atlas.texel_size_m,
            "texture_size": list(self.atlas.size),
        }


def majority_source(face, source, n_faces: int) -> np.ndarray:
    """(n_faces,) int64: the source image most of each face's texels came from (ties: the smallest index; −1 for
    a face without texels). Counts only the (face, image) pairs that occur: memory grows with the texels, not with
    faces × images (a dense count was 1.6 GB at 1 M faces × 200 images)."""
    face = np.asarray(face, np.int64)
    source = np.asarray(source, np.int64)
    out = np.full(int(n_faces), -1, np.int64)
    if len(face) == 0:
        return out
    base = int(source.max()) + 1
    u, cnt = np.unique(face * base + source, return_counts=True)
    uf, us = u // base, u % base
    order = np.lexsort((us, -cnt, uf))  # by face, then most texels, then smallest image index
    uf, us = uf[order], us[order]
    first = np.r_[True, uf[1:] != uf[:-1]]
    out[uf[first]] = us[first]
    return out


def _vertex_temperatures(intersector, V, F, views, surfaces, scores, cfg):
    """Per-vertex temperature: every face corner (pulled 1e-3 of the way to the centroid so that the ray
    test belongs to that face) is selected and sampled like a texel; a vertex averages its corners."""
    cen = V[F].mean(axis=1)
    corners = V[F] * (1 - 1e-3) + 1e-3 * cen[:, None, :]
    pts = corners.reshape(-1, 3)
    fi = np.repeat(np.arange(len(F)), 3)
    sel, _, _ = select_in_chunks(intersector, V, F, views, surfaces, scores, pts, fi, cfg)
    vid = F.reshape(-1)
    ok = np.isfinite(sel.temperature_k)
    s = np.bincount(vid[ok], weights=sel.temperature_k[ok], minlength=len(V))
    c = np.bincount(vid[ok], minlength=len(V))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = s / c
    return np.where(c > 0, out, np.nan), sel


def texture_mesh(vertices, faces, views: Sequence[TextureView], config: TextureConfig | None = None) -> TextureResult:
    """Texture a mesh with temperatures from oriented thermal images (module docstring).

    Parameters
    ----------
    vertices : (V, 3) metres, in the frame of the views' poses
    faces : (F, 3) vertex indices (normals by the right-hand rule point towards the cameras)
    views : K :class:`TextureView`, images in kelvin (or all in raw counts: values, offsets and the levelling RMS
        are then counts; ``correct`` needs kelvin)
    config : :class:`TextureConfig`

    Returns
    -------
    :class:`TextureResult`
    """
    cfg = config or TextureConfig()
    V_in, F = _check_mesh(vertices, faces)
    views = list(views)
    if not views:
        raise InvalidInputError("texture_mesh: no oriented images given; expected at least one view")
    # everything below runs in a local frame (Embree and xatlas compute in float32: local_origin)
    origin = local_origin(V_in)
    V = V_in - origin
    views = [view_in_frame(v, origin) for v in views]
    normals, area, cen = _face_geometry(V, F)
    scores = face_view_scores(V, F, views, max_angle_deg=cfg.max_angle_deg, border_fraction=cfg.border_fraction)
    _, face_views = _score_max_count(scores)
    ts = cfg.texel_size_m
    if ts is None:  # half the median surface pixel size of each face's best image, area weighted
        # (scored at the centroids: a large face seen only in part at a grazing angle would coarsen every texel)
        best = np.zeros(len(F))
        for _, col in _score_columns(V, F, views, cfg.max_angle_deg, cfg.border_fraction, large_faces=False):
            np.maximum(best, col, out=best)
        seen = best > 0
        if np.any(seen):
            px = 1.0 / best[seen]
            order = np.argsort(px)
            cw = np.cumsum(area[seen][order])
            ts = 0.5 * float(px[order][np.searchsorted(cw, 0.5 * cw[-1])])
        else:
            ts = float(np.sqrt(area.sum()) / 512)
    atlas = build_atlas(V, F, ts, max_texture_px=cfg.max_texture_px, padding=cfg.padding_texels)
    texels = rasterize_atlas(atlas, V, F)
    inter = _intersector(V, F)
    planes = plane_ids(V, F)
    surfaces = [pixel_surfaces(inter, V, F, v, planes) for v in views]
    K = len(views)
    levelling = cfg.levelling is Levelling.OFFSETS
    # levelling needs every usable view's value: kept for a seeded sample of texels only (2 per wanted pair)
    sample = _levelling_sample(len(texels.points), 2 * int(cfg.offsets_max_pairs)) if levelling else None
    sel, occluded, sample_k = select_in_chunks(inter, V, F, views, surfaces, scores, texels.points, texels.face, cfg,
                                               sample=sample)
    faces_min_radius = np.zeros(len(F), bool)
    if cfg.min_clean_radius_px is not None and cfg.min_clean_radius_px < cfg.clean_radius_px:
        # a face that no image sees cleanly at the wide radius (small faces along a silhouette) takes the texels
        # that are clean at the largest smaller radius down to min_clean_radius_px, rather than none: recorded per face
        for rr in range(int(cfg.clean_radius_px) - 1, int(cfg.min_clean_radius_px) - 1, -1):
            has = np.bincount(texels.face[sel.source >= 0], minlength=len(F)) > 0
            redo = np.flatnonzero(~has[texels.face] & (sel.n_visible > 0))
            if not len(redo):
                break
            s2, _, _ = select_in_chunks(inter, V, F, views, surfaces, scores, texels.points[redo], texels.face[redo],
                                        replace(cfg, clean_radius_px=rr))
            sel.source[redo], sel.temperature_k[redo], sel.angle_deg[redo] = s2.source, s2.temperature_k, s2.angle_deg
            sel.distance_m[redo], sel.n_usable[redo] = s2.distance_m, s2.n_usable
            faces_min_radius[texels.face[redo[s2.source >= 0]]] = True
    vtemp, vsel = _vertex_temperatures(inter, V, F, views, surfaces, scores, cfg)
    del surfaces
    offsets = np.zeros(K)
    fixed = None
    rms = None
    if levelling:
        sub = Selection(sel.source[sample], sel.temperature_k[sample], sel.angle_deg[sample], sel.distance_m[sample],
                        sel.n_usable[sample], None, sample_k)
        held = int(np.argmax(np.bincount(sel.source[sel.source >= 0], minlength=K)))  # most texels of ALL of them
        offsets, fixed, _, rb, ra = estimate_offsets(sub, K, max_pairs=cfg.offsets_max_pairs, fixed=held)
        rms = (rb, ra)
        ok = sel.source >= 0
        sel.temperature_k[ok] += offsets[sel.source[ok]]
        vok = vsel.source >= 0
        vsel.temperature_k[vok] += offsets[vsel.source[vok]]
        vid = F.reshape(-1)
        fin = np.isfinite(vsel.temperature_k)
        s = np.bincount(vid[fin], weights=vsel.temperature_k[fin], minlength=len(V))
        c = np.bincount(vid[fin], minlength=len(V))
        with np.errstate(invalid="ignore", divide="ignore"):
            vtemp = np.where(c > 0, s / c, np.nan)
    if cfg.correct:
        sel.temperature_k = _correct(sel.temperature_k, sel.angle_deg, sel.distance_m, cfg.correction)
        vc = _correct(vsel.temperature_k, vsel.angle_deg, vsel.distance_m, cfg.correction)
        vid = F.reshape(-1)
        fin = np.isfinite(vc)
        s = np.bincount(vid[fin], weights=vc[fin], minlength=len(V))
        c = np.bincount(vid[fin], minlength=len(V))
        with np.errstate(invalid="ignore", divide="ignore"):
            vtemp = np.where(c > 0, s / c, np.nan)
    W, H = atlas.size
    temp = np.full((H, W), np.nan, np.float32)
    src = np.full((H, W), -1, np.int32)
    angle = np.full((H, W), np.nan, np.float32)
    r, c_ = texels.rc[:, 0], texels.rc[:, 1]
    textured = (sel.source >= 0) & np.isfinite(sel.temperature_k)
    temp[r[textured], c_[textured]] = sel.temperature_k[textured]
    src[r[textured], c_[textured]] = sel.source[textured]
    angle[r[textured], c_[textured]] = sel.angle_deg[textured]
    n_tex = np.bincount(texels.face, minlength=len(F))
    n_ok = np.bincount(texels.face[textured], minlength=len(F))
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = np.where(n_tex > 0, n_ok / n_tex, np.nan)
    face_source = majority_source(texels.face[textured], sel.source[textured], len(F))
    face_visible = np.bincount(texels.face[sel.n_visible > 0], minlength=len(F)) > 0
    texels.points += origin  # back to the input's coordinates
    return TextureResult(V_in, F, atlas, temp, src, angle, vtemp, cov, face_views, face_source,
                         [v.name for v in views], offsets, fixed, rms, occluded, texels, sel, cfg, face_visible,
                         faces_min_radius)


def thermal_poses_from_rig(rgb_poses, relative):
    """Thermal ``cam_from_world`` poses from RGB poses and the rig (seed 002 eq. 4–5).

    Parameters
    ----------
    rgb_poses : sequence of :class:`~thermogrammetry.geometry.Pose` (cam_from_world of the RGB camera)
    relative : Pose ``cam_thermal_from_cam_rgb`` (``R_rel``, ``t_rel``); seed 002's ``R*`` is ``R_rel^T``
        and its base vector ``b`` (the thermal centre in the RGB camera frame) is ``-R_rel^T t_rel``.

    Returns
    -------
    list of Pose: ``R_IR = R_rel R_RGB``, ``t_IR = R_rel t_RGB + t_rel``
    (so ``C_IR = C_RGB + R_RGB^T b``, eq. 5).
    """
    from ..geometry import Pose

    rel = relative if isinstance(relative, Pose) else Pose(*relative)
    return [rel.compose(p) for p in rgb_poses]
