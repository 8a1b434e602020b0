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
poses through the constant relative orientation (Barazzetti et al. 2013, eq. 4–5, in our ``cam_from_world`` terms:
``R_IR = R_rel R_RGB``, ``t_IR = R_rel t_RGB + t_rel``; see :mod:`thermogrammetry.adjustment.problem`).

Modules
-------
This module keeps the driver (:func:`texture_mesh`, :class:`TextureResult`, :func:`thermal_poses_from_rig`)
and re-exports the steps, one module each: :mod:`.texture_config` (:class:`TextureConfig`, :class:`Levelling`),
:mod:`.texture_mesh` (checks, local origin, face geometry, planes, :class:`TextureView`), :mod:`.texture_scores`
(the per-face view score), :mod:`.texture_atlas` (xatlas charts, texel centres), :mod:`.texture_visibility`
(ray casting, occlusion, clean pixels), :mod:`.texture_selection` (the best usable image per texel) and
:mod:`.texture_levelling` (per-image offsets).

References
----------
.. [1] Barazzetti L., Erba S., Previtali M., Rosina E., Scaioni M. (2013): thermal textures of
   building models from thermal + RGB images, bi-camera rig (eq. 4–5), best image per triangle.
.. [2] Sawicki P., Stein R., Więcek B., eq. 7–8: directional correction.
.. [3] Young J. et al., xatlas: mesh parameterisation and chart packing (github.com/jpcy/xatlas).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from ..errors import InvalidInputError
from .correction import CorrectionConfig
# the steps of the texturing, one module each (re-exported: import them from here or from their module)
from .texture_atlas import Atlas, Texels, build_atlas, rasterize_atlas
from .texture_config import Levelling, TextureConfig
from .texture_levelling import estimate_offsets, levelling_sample
from .texture_mesh import (TextureView, check_mesh, face_geometry, local_origin, plane_ids,  # noqa: F401
                           project_to_view, view_in_frame)
from .texture_scores import any_face_seen, face_view_scores, score_columns, score_max_count, scores_at
from .texture_selection import CHUNK_POINT_VIEWS, Selection, select_and_sample, select_in_chunks  # noqa: F401
from .texture_visibility import PixelSurface, pixel_surfaces, ray_intersector, usable_in_view

# the old private names, still used by tests and products.facade
_check_mesh = check_mesh
_face_geometry = face_geometry
_intersector = ray_intersector
_levelling_sample = levelling_sample
_score_columns = score_columns
_score_max_count = score_max_count

__all__ = ["Levelling", "TextureConfig", "TextureView", "TextureResult", "face_view_scores", "scores_at",
           "any_face_seen", "build_atlas", "rasterize_atlas", "PixelSurface", "pixel_surfaces", "plane_ids", "usable_in_view", "select_and_sample",
           "select_in_chunks", "estimate_offsets", "texture_mesh", "thermal_poses_from_rig", "local_origin", "view_in_frame"]



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



def _vertex_temperatures(intersector, V, F, views, surfaces, scores, cfg, on_chunk=None):
    """Per-vertex temperature: every face corner (pulled 1e-3 of the way to the centroid so that the ray
    test belongs to that face) is selected and sampled like a texel; a vertex averages its corners."""
    cen = V[F].mean(axis=1)
    corners = V[F] * (1 - 1e-3) + 1e-3 * cen[:, None, :]
    pts = corners.reshape(-1, 3)
    fi = np.repeat(np.arange(len(F)), 3)
    sel, _, _ = select_in_chunks(intersector, V, F, views, surfaces, scores, pts, fi, cfg, on_chunk=on_chunk)
    vid = F.reshape(-1)
    ok = np.isfinite(sel.temperature_k)
    s = np.bincount(vid[ok], weights=sel.temperature_k[ok], minlength=len(V))
    c = np.bincount(vid[ok], minlength=len(V))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = s / c
    return np.where(c > 0, out, np.nan), sel



#: stage names of :func:`texture_mesh`'s ``progress`` (what a progress line prints)
STAGE_VISIBILITY = "visibility (views)"
STAGE_TEXELS = "texels"
STAGE_CORNERS = "vertex corners"


def _stage_callback(progress):
    """``stage -> callable(done, total)`` forwarding to ``progress(stage, done, total)`` (a no-op without one)."""
    def for_stage(stage):
        if progress is None:
            return lambda done, total: None
        return lambda done, total: progress(stage, int(done), int(total))
    return for_stage


def texture_mesh(vertices, faces, views: Sequence[TextureView], config: TextureConfig | None = None, *,
                 progress=None) -> TextureResult:
    """Texture a mesh with temperatures from oriented thermal images (:mod:`thermogrammetry.products.texture`).

    Parameters
    ----------
    vertices : (V, 3) metres, in the frame of the views' poses
    faces : (F, 3) vertex indices (normals by the right-hand rule point towards the cameras)
    views : K :class:`TextureView`, images in kelvin (or all in raw counts: values, offsets and the levelling RMS
        are then counts; ``correct`` needs kelvin)
    config : :class:`TextureConfig`
    progress : optional callable ``progress(stage, done, total)`` for the steps that grow with the mesh and the
        images: :data:`STAGE_VISIBILITY` after each view's ray casting (``done`` of K views), :data:`STAGE_TEXELS`
        after each chunk of texels and :data:`STAGE_CORNERS` after each chunk of face corners (the per-vertex
        values; ``done`` of 3 F)

    Returns
    -------
    :class:`TextureResult`
    """
    cfg = config or TextureConfig()
    V_in, F = check_mesh(vertices, faces)
    views = list(views)
    if not views:
        raise InvalidInputError("texture_mesh: no oriented images given; expected at least one view")
    # everything below runs in a local frame (Embree and xatlas compute in float32: local_origin)
    origin = local_origin(V_in)
    V = V_in - origin
    views = [view_in_frame(v, origin) for v in views]
    normals, area, cen = face_geometry(V, F)
    scores = face_view_scores(V, F, views, max_angle_deg=cfg.max_angle_deg, border_fraction=cfg.border_fraction)
    _, face_views = score_max_count(scores)
    ts = cfg.texel_size_m
    if ts is None:  # half the median surface pixel size of each face's best image, area weighted
        # (scored at the centroids: a large face seen only in part at a grazing angle would coarsen every texel)
        best = np.zeros(len(F))
        for _, col in score_columns(V, F, views, cfg.max_angle_deg, cfg.border_fraction, large_faces=False):
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
    inter = ray_intersector(V, F)
    planes = plane_ids(V, F)
    step = _stage_callback(progress)
    surfaces = []
    for k, v in enumerate(views):
        surfaces.append(pixel_surfaces(inter, V, F, v, planes))
        step(STAGE_VISIBILITY)(k + 1, len(views))
    K = len(views)
    levelling = cfg.levelling is Levelling.OFFSETS
    # levelling needs every usable view's value: kept for a seeded sample of texels only (2 per wanted pair)
    sample = levelling_sample(len(texels.points), 2 * int(cfg.offsets_max_pairs)) if levelling else None
    sel, occluded, sample_k = select_in_chunks(inter, V, F, views, surfaces, scores, texels.points, texels.face, cfg,
                                               sample=sample, on_chunk=step(STAGE_TEXELS))
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
    vtemp, vsel = _vertex_temperatures(inter, V, F, views, surfaces, scores, cfg, on_chunk=step(STAGE_CORNERS))
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
    """Thermal ``cam_from_world`` poses from RGB poses and the rig (Barazzetti et al. 2013, eq. 4–5).

    Parameters
    ----------
    rgb_poses : sequence of :class:`~thermogrammetry.geometry.Pose` (cam_from_world of the RGB camera)
    relative : Pose ``cam_thermal_from_cam_rgb`` (``R_rel``, ``t_rel``); Barazzetti et al.'s ``R*`` is ``R_rel^T``
        and its base vector ``b`` (the thermal centre in the RGB camera frame) is ``-R_rel^T t_rel``.

    Returns
    -------
    list of Pose: ``R_IR = R_rel R_RGB``, ``t_IR = R_rel t_RGB + t_rel``
    (so ``C_IR = C_RGB + R_RGB^T b``, eq. 5).
    """
    from ..geometry import Pose

    rel = relative if isinstance(relative, Pose) else Pose(*relative)
    return [rel.compose(p) for p in rgb_poses]
