"""``texture`` workflow: survey folder (``cameras.json`` + frames) + mesh file -> textured products.

Reads through :class:`~thermogrammetry.io.oriented.OrientedCameras`, calls
:func:`thermogrammetry.products.texture.texture_mesh` and writes, through a project store::

    textured.glb, textured.obj, textured.mtl, textured.png   (palette preview; values in the TIFFs)
    temperature_texture.tif      float32 in the chosen unit (K or °C), NaN = no texel
    temperature_texture_u16.tif  16-bit codes, value = code * scale + offset (GDAL metadata), 0 = none
    source_texture.tif           int32 image index (texture.json "index"), -1 = none
    angle_texture.tif            float32 viewing angle of the source image (degrees)
    vertices.ply                 per-vertex temperature_k
    texture.json                 counts, index -> image name, unit, offsets, what altered the values, pose_fit
    cameras_fitted.json          the poses used, when they were fitted (``fit_poses="auto"`` or ``"mesh"``; not in rig mode)
    frames/                      the frames of cameras_fitted.json (hard links to the survey's, or copies)
    report.html                  coverage, views per face, offsets, a rendered view in °C
    viewer.html                  the GLB in a self-contained WebGL page (offline, no libraries)

Frames: thermal images in kelvin (``unit: K``) are used when the survey has any; otherwise thermal
images in raw sensor counts (``unit: counts``, e.g. DJI R-JPEGs without the closed SDK, Workswell TIFFs).
One texture never mixes the two: with both present the count frames are listed as skipped. With counts,
every product holds the counts as sampled and says so (``raw_counts``, never a temperature):
``temperature_texture.tif`` (file name kept: it is a public contract) is float32 counts with GDAL unit
``counts``; ``temperature_texture_u16.tif`` holds the counts rounded to the nearest integer (scale 1,
offset 0, code 0 = no texel); ``vertices.ply`` has ``raw_counts`` instead of ``temperature_k``;
``texture.json`` says ``unit: "counts"``; the report's colour scale says "raw counts". A temperature
unit (``unit="K"``/``"C"``) and ``correct`` are refused for counts (no documented conversion);
``levelling="offsets"`` works and its offsets are in counts. RGB images and display numbers (``dn``)
are listed as skipped. Rig mode (``rig``): thermal poses derived from the oriented RGB images through
the rig's relative orientation (seed 002 eq. 4–5); its frames are read by the io layer (kelvin where the
format documents a conversion, float TIFFs without a unit tag as kelvin, else raw counts, with the same
counts outputs as above).

Poses fitted to the mesh (``fit_poses="auto"``, the default; :mod:`thermogrammetry.sfm.meshfit`): the survey's tie
points (``SURVEY_DIR/colmap``) are made to lie on the mesh in one bundle adjustment (intrinsics held, the survey's
camera centres as priors with their σ), which removes what the survey's datum left free (a ring of stations at one
height turns in common about a horizontal axis). Kept only when the mesh and the tie points meet and the fit
converges without bending the block; ``texture.json`` ``pose_fit`` says what happened either way. Never in rig mode.
Then (``auto``; also in rig mode) the poses are refined photometrically (:mod:`thermogrammetry.products.photofit`):
points on the mesh seen cleanly by >= 2 images, each view's pose moved until the images agree on their temperatures
(the survey's σ as priors, the block's mean centre held); kept when the images' robust disagreement falls and no image
turns by more than 3°; ``texture.json`` ``photometric_fit`` (in rig mode also the refined thermal poses, under
``poses``: the thermal frames are not images of cameras.json, so no cameras_fitted.json is written). Poses only: no
value is changed. ``fit_poses="mesh"`` runs the first step alone, ``"off"`` neither.

Mesh winding: the texture needs each triangle's normal (right-hand rule) towards the images. When no face
faces any image but the reversed mesh does (a plane fitted to a sparse cloud has an arbitrary normal sign),
every triangle's vertex order is reversed and ``texture.json`` says so (``mesh_winding``).
"""

from __future__ import annotations

import json
import os
import posixpath
import shutil
import time
from pathlib import Path

import numpy as np

from ..errors import ConfigError, DataFileError, InvalidInputError, ThermogrammetryError, UnsupportedFormatError
from ..reporting import ReportHeader, command_line, figure_png, header_html, python_call

__all__ = ["DEFAULT_MAX_FACES", "read_mesh", "frames_unit", "load_views", "check_views_unit", "load_rig_views", "run_texture", "texture_report_html"]

#: ``fit_poses`` choices: ``auto`` = tie points onto the mesh, then the photometric refinement; ``mesh`` = the first
#: only; ``off`` = the poses of cameras.json
FIT_POSES = ("auto", "mesh", "off")

#: frame units that a texture can be made of: temperatures, or raw sensor counts labelled as such
TEXTURE_UNITS = ("K", "counts")


#: triangles a mesh may have for ``texture`` (``max_faces``): a building's model has 10^4-10^6; a 5 M-face scan
#: ran for minutes at 4.5 GB with no progress. Raise it with ``--max-faces N`` (or decimate the mesh).
DEFAULT_MAX_FACES = 2_000_000


def read_mesh(path, *, max_faces: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and triangles (F, 3) of an OBJ, PLY, STL, glTF/GLB or OFF file (trimesh).

    Scenes are concatenated in their world placement; quads are split into triangles. A mesh of more than
    ``max_faces`` triangles (default: no cap; the texture verb passes :data:`DEFAULT_MAX_FACES`) is refused,
    naming the file, its face count and the cap.
    """
    import trimesh

    p = Path(path)
    if not p.is_file():
        raise DataFileError(f"{p}: mesh file not found; expected an OBJ, PLY, glTF/GLB, STL or OFF mesh")
    try:
        m = trimesh.load(p, force="mesh", process=False)
    except Exception as exc:
        raise UnsupportedFormatError(f"{p}: cannot read a mesh ({type(exc).__name__}: {exc}); expected OBJ, PLY, glTF/GLB, STL or OFF") from None
    V = np.asarray(getattr(m, "vertices", np.zeros((0, 3))), float)
    F = np.asarray(getattr(m, "faces", np.zeros((0, 3))), np.int64)
    if len(V) < 3 or len(F) < 1:
        raise InvalidInputError(f"{p}: the mesh has {len(V)} vertices and {len(F)} faces; expected a triangle mesh")
    bad = np.flatnonzero(~np.all(np.isfinite(V), axis=1))
    if len(bad):
        k = int(bad[0])
        raise InvalidInputError(f"{p}: {len(bad)} of its {len(V)} vertices have non-finite coordinates (vertex {k}, "
                                f"1-based {k + 1}: {V[k].tolist()}); expected finite coordinates in metres")
    if max_faces is not None and len(F) > int(max_faces):
        raise InvalidInputError(f"{p}: the mesh has {len(F)} triangles, above the cap of {int(max_faces)}; decimate it "
                                f"(a texel grid is finer than the faces anyway) or raise the cap (--max-faces N)")
    return V, F


def frames_unit(cameras, *, names=None) -> str | None:
    """The unit a texture of this survey is made of: ``"K"`` when any thermal frame is in kelvin, else
    ``"counts"`` when any is in raw counts, else ``None`` (K and counts are never mixed in one texture)."""
    units = {im.unit.value for im in cameras
             if (names is None or im.name in names) and im.sensor.value == "thermal"}
    for u in TEXTURE_UNITS:
        if u in units:
            return u
    return None


def load_views(cameras, *, names=None, unit: str | None = None):
    """:class:`TextureView` of every thermal image whose frame unit is ``unit`` (``"K"`` or ``"counts"``;
    default :func:`frames_unit`: kelvin when the survey has any, else counts); returns
    ``(views, skipped[(name, reason)])``. Count frames are kept as their numbers (float32, exact for uint16)."""
    from ..products.texture import TextureView

    unit = frames_unit(cameras, names=names) if unit is None else unit
    views, skipped = [], []
    for im in cameras:
        if names is not None and im.name not in names:
            continue
        if im.sensor.value != "thermal":
            skipped.append((im.name, f"sensor {im.sensor.value}: only thermal images carry temperatures or counts"))
            continue
        if im.unit.value != unit:
            if im.unit.value == "counts" and unit == "K":
                why = ("frame unit 'counts' (raw sensor counts) while the survey has kelvin frames: one texture never mixes "
                       "temperatures and counts; the kelvin frames are used")
            else:
                why = (f"frame unit {im.unit.value!r}; expected kelvin or raw counts (re-run survey with temperature or "
                       "count frames)")
            skipped.append((im.name, why))
            continue
        try:
            img = cameras.read_frame(im)
        except DataFileError as exc:
            skipped.append((im.name, str(exc)))
            continue
        if img.ndim != 2:
            skipped.append((im.name, f"frame shape {img.shape}; expected a single-band "
                                     + ("temperature" if unit == "K" else "raw count") + " image"))
            continue
        views.append(TextureView(im.name, cameras.camera_of(im), im.pose, img))
    return views, skipped


def check_views_unit(views, skipped, frame_unit, survey_dir, unit, product: str) -> bool:
    """Whether the views hold raw counts; :class:`InvalidInputError` when there is no usable view, or when a
    temperature ``unit`` is asked of count frames (``product`` names what would hold the counts)."""
    if not views:
        why = "; ".join(f"{n}: {r}" for n, r in skipped[:5])
        raise InvalidInputError(f"{survey_dir}: no usable thermal image in kelvin or raw counts ({why or 'cameras.json lists none'})")
    counts = frame_unit == "counts"
    if counts and unit is not None:
        raise InvalidInputError(f"--unit {unit}: the thermal frames of {survey_dir} are raw counts (no documented "
                                f"conversion); a temperature unit cannot be applied. Omit --unit: the {product} then "
                                "holds the counts, labelled as counts")
    return counts


def load_rig_views(cameras, rig: dict, *, source: str = "rig.json"):
    """Rig mode: thermal views from oriented RGB images (seed 002 eq. 4–5).

    ``rig`` (JSON)::

        {"format": "thermogrammetry/rig", "cam_thermal_from_cam_rgb": {"R": 3x3, "t": [3]},
         "thermal_camera": <camera JSON>, "frames": {"<rgb image name>": "thermal/frame.tif", ...}}

    Frame paths are relative to the cameras file's folder. Frames are read by the io layer
    (:func:`thermogrammetry.io.read_thermal`): radiometric files (R-JPEG, FLIR/Workswell TIFF, ...) give kelvin where
    their format documents the conversion, else their raw counts; float TIFFs without a unit tag are taken as kelvin,
    16-bit TIFFs without a calibration as raw counts. One texture never mixes the two: kelvin when any frame is in
    kelvin (count frames skipped with the reason), else counts.

    Returns
    -------
    views : list of TextureView
    skipped : list of (name, reason)
    unit : "K" | "counts" | None
        What the views hold (None when there is none).
    """
    from ..geometry import Pose
    from ..io import read_thermal
    from ..products.texture import TextureView, thermal_poses_from_rig
    from ..sfm.rig import parse_rig
    from .survey import frame_values

    # one rig schema for texture and survey (thermogrammetry.sfm.rig); texture needs R, t, the camera and frames
    rf = parse_rig(rig, source=source, require_relative=True, require_camera=True, require_frames=True)
    rel = Pose(rf.R, rf.t)
    cam = rf.thermal_camera
    frames = rf.frames
    found, skipped = [], []
    for name, rel_path in frames.items():
        try:
            im = cameras.image(name)
        except KeyError:
            skipped.append((name, "not in cameras.json"))
            continue
        pose = thermal_poses_from_rig([im.pose], rel)[0]
        p = Path(rel_path)
        p = p if p.is_absolute() or cameras.root is None else cameras.root / p
        if not p.exists():
            skipped.append((name, f"{p}: thermal frame missing"))
            continue
        try:
            _, img, unit = frame_values(read_thermal(p, unit="K"), p, counts_dtype=np.float32)
        except ThermogrammetryError as exc:
            skipped.append((name, f"{p}: {exc}" if str(p) not in str(exc) else str(exc)))
            continue
        w, h = cam.image_size
        if img.shape != (h, w):
            skipped.append((name, f"{p}: frame shape {img.shape}; the rig's thermal camera expects ({h}, {w})"))
            continue
        found.append((name, unit, TextureView(f"{name}:thermal", cam, pose, img)))
    units = {u for _, u, _ in found}
    unit = next((u for u in TEXTURE_UNITS if u in units), None)
    views = []
    for name, u, v in found:
        if u == unit:
            views.append(v)
        else:
            skipped.append((name, "frame in raw counts while other rig frames are in kelvin: one texture never mixes "
                                  "temperatures and counts; the kelvin frames are used"))
    return views, skipped, unit


def _default_viewpoint(result, views):
    """A virtual camera behind the best-covering image, pulled back 30 % to show context."""
    V = result.vertices
    counts = np.bincount(result.source[result.source >= 0], minlength=len(views))
    k = int(np.argmax(counts)) if counts.sum() else 0
    C = views[k].pose.center
    used = np.unique(result.faces[result.face_source >= 0])
    target = V[used].mean(axis=0) if len(used) else V.mean(axis=0)
    C = target + 1.3 * (C - target)
    return C, target


def texture_report_html(result, views, skipped, unit: str, pose_fit: dict | None = None,
                        photometric_fit: dict | None = None, header=None) -> str:
    """The report page. ``unit``: unit of the written texture (``K``, ``C`` or ``counts``); the result holds kelvin
    for temperature frames (shown in °C) and the frames' raw counts for count frames (shown as "raw counts").
    ``header``: the :class:`~thermogrammetry.reporting.ReportHeader` shown under the title (None: none)."""
    import html

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    counts = unit == "counts"
    vu = "counts" if counts else "K"  # unit of offsets and levelling RMS
    s = result.summary()
    C, target = _default_viewpoint(result, views)
    up = (0, 0, 1)
    try:
        from ..products.texture_export import render_view

        rv = render_view(result, C, target, up=up)
    except Exception as exc:  # a degenerate viewpoint must not lose the report
        rv = None
        skipped = list(skipped) + [("report view", f"not rendered: {exc}")]
    figs = []
    if rv is not None:
        fig, ax = plt.subplots(figsize=(7, 5))
        # the result's texture is in kelvin (the report shows °C) or in raw counts (shown as they are)
        shown = rv if counts else rv - 273.15
        im = ax.imshow(shown, cmap="inferno")
        ax.set_axis_off()
        ax.set_title("textured mesh (untextured and background: white)")
        fig.colorbar(im, ax=ax, label="raw counts (not a temperature)" if counts else "temperature (°C)")
        figs.append(figure_png(fig, dpi=100))
    fig, ax = plt.subplots(figsize=(6, 3))
    h = s["views_per_face_histogram"]
    ax.bar(range(len(h)), h)
    ax.set_xlabel("images with a positive score")
    ax.set_ylabel("faces")
    figs.append(figure_png(fig, dpi=100))
    cnt = np.bincount(result.source[result.source >= 0], minlength=len(views))
    rows = "".join(f"<tr><td>{i}</td><td>{html.escape(v.name)}</td><td>{int(cnt[i])}</td><td>{int(result.occluded_texels[i])}</td>"
                   f"<td>{result.offsets_k[i]:+.3f}</td></tr>" for i, v in enumerate(views))
    sk = "".join(f"<li>{html.escape(n)}: {html.escape(r)}</li>" for n, r in skipped)
    lev = result.config.levelling.value
    lev_note = ("<p><b>Levelling: per-image offsets were estimated from the overlaps (least squares, image "
                f"{html.escape(views[result.levelling_fixed].name)} held at 0) and ADDED to every texel of their image: "
                "the values are altered.</b> RMS of overlap differences before/after: "
                f"{result.levelling_rms_k[0]:.3f} / {result.levelling_rms_k[1]:.3f} {vu}.</p>") if lev == "offsets" else \
        f"<p>No seam levelling: every texel holds the {'raw counts' if counts else 'temperature'} of one image as sampled.</p>"
    counts_note = ("<p><b>The frames are raw sensor counts (no documented conversion to temperature): every texture "
                   "value is a count as sampled, not a temperature.</b></p>") if counts else ""
    corr = "<p><b>Per-texel angle/emissivity/transmission correction applied.</b></p>" if result.config.correct else ""
    vis = s.get("faces_visible", s["faces_seen"])
    share = s.get("faces_visible_textured", s["faces_textured"]) / max(vis, 1)
    pf = pose_fit or {}
    if pf.get("applied"):
        md, rc, cc = pf["median_distance_m"], pf["rotation_change_deg"], pf["center_change_m"]
        fit_note = (f"<p><b>Poses fitted to the mesh</b> ({pf['points_on_surface']} of the survey's {pf['points']} tie "
                    f"points on its surface, σ {pf['surface_sigma_m'] * 100:.1f} cm): their median distance to the mesh "
                    f"{md['before'] * 100:.1f} → {md['after'] * 100:.1f} cm; rotations changed by {rc['median']:.2f}° "
                    f"(median; max {rc['max']:.2f}°), centres by {cc['median'] * 100:.1f} cm (max {cc['max'] * 100:.1f}); "
                    "the poses used are in cameras_fitted.json.</p>")
    elif pf.get("reason"):
        fit_note = f"<p>Poses as in cameras.json (not fitted to the mesh: {html.escape(str(pf['reason']))}).</p>"
    else:
        fit_note = ""
    ph = photometric_fit or {}
    if ph.get("applied"):
        rc, cc = ph["rotation_change_deg"], ph["center_change_m"]
        vu = "counts" if unit == "counts" else "K"
        fit_note += (f"<p><b>Poses refined photometrically</b> ({ph['views_refined']} of {ph['views']} images, "
                     f"{ph['points']} surface points seen cleanly by ≥ 2 images, {ph['samples']} samples): the images' "
                     f"robust disagreement on the mesh {ph['robust_sigma_before']:.4f} → {ph['robust_sigma_after']:.4f} {vu}; "
                     f"rotations changed by {rc['median']:.2f}° (median; max {rc['max']:.2f}°), centres by "
                     f"{cc['median'] * 100:.1f} cm (max {cc['max'] * 100:.1f}), the block's mean centre held. Only the "
                     "poses changed: every texel is still one image's value.</p>")
    elif ph.get("reason"):
        fit_note += f"<p>No photometric pose refinement: {html.escape(str(ph['reason']))}.</p>"
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>thermogrammetry texture</title>
<style>body{{font-family:sans-serif;max-width:60em;margin:2em auto}}td,th{{padding:2px 8px;border-bottom:1px solid #ddd}}</style></head><body>
<h1>Thermal texture</h1>{header_html(header) if header is not None else ''}
<h2>Coverage</h2>
<table><tr><th>faces</th><td>{s['faces_total']}</td></tr><tr><th>faces scored by an image</th><td>{s['faces_seen']}</td></tr>
<tr><th>faces visible (a texel inside an image, within the angle limit, not occluded)</th><td>{vis}</td></tr>
<tr><th>faces textured (≥ 1 texel)</th><td>{s['faces_textured']} ({100 * share:.1f} % of the visible ones textured)</td></tr>
<tr><th>faces fully textured</th><td>{s['faces_fully_textured']}</td></tr>
<tr><th>faces textured only below the clean radius ({result.config.clean_radius_px} px; their pixels may also see a neighbouring surface)</th><td>{s.get('faces_textured_at_min_clean_radius', 0)}</td></tr>
<tr><th>texels textured / inside faces</th><td>{s['texels_textured']} / {s['texels_total']}</td></tr>
<tr><th>texel size</th><td>{s['texel_size_m'] * 100:.2f} cm ({s['texture_size'][0]} × {s['texture_size'][1]})</td></tr></table>
<p>Untextured texels are NaN (source −1) in the TIFFs: nothing is filled.</p>
{counts_note}{lev_note}{corr}{fit_note}
<h2>Rendered view (colour scale in {'raw counts' if counts else '°C'})</h2>{figs[0] if rv is not None else '<p>(no view)</p>'}
<h2>Views per face</h2>{figs[-1]}
<h2>Images</h2><table><tr><th>index</th><th>image</th><th>texels</th><th>texels occluded</th><th>offset ({vu})</th></tr>{rows}</table>
{('<h2>Skipped</h2><ul>' + sk + '</ul>') if sk else ''}
</body></html>"""


def clean_radius_from_poses(cfg, cameras, views, *, n_sigma: float = 3.0, max_px: int = 8):
    """Widen the texture's clean-pixel test by the pose uncertainty of the survey (``rotation_std_deg``).

    A texel is taken from an image only when the pixels around its footprint (``clean_radius_px``) see the
    texel's own surface; with estimated poses, a silhouette (the occluder, the building's edge against the sky)
    lands a few pixels away from where the mesh puts it. The radius becomes ``ceil(n_sigma · f · σ_rot)`` with the
    median over the views of each view's largest rotation σ (px, at least the configured radius, at most
    ``max_px``). The largest σ of the block instead (1.37 px there) gave radius 5 and only 94.2 % of the seen faces
    textured.

    Measured on the 64-view synthetic building ring with survey poses (rotations 0.43° RMS off, reported σ
    0.1–0.35°): radius 1 left texels up to 31 K wrong (through the occluder's edge) and 99.73 % within 0.2 K;
    radius 3 gave a 1.8 K maximum and 99.89 % within 0.2 K, with 99.45 % of the seen faces still textured.
    A face with no texel clean at the widened radius (small faces along a silhouette) takes the texels clean at the
    largest smaller radius (``TextureConfig.min_clean_radius_px``, which ``run_texture`` sets to 0): on a held-out
    48-station ring with survey poses (radius 4), 40 of the 744 visible faces were untextured without it (94.6 %), none
    with a fallback to 1 px; their 2240 texels were within 0.072 K of the noise-free truth, and every other texel is
    unchanged. The last step, 0 px (only the bilinear footprint must see the face), textures the narrow faces that no
    image sees cleanly even at the true poses: on the 40-station ring of seed 1, 18 faces of the occluder (97.5 % ->
    100 % of the visible faces), their texels within 0.004 K median of the truth but 0.46 K at the 90th percentile
    (pixels that also see the neighbouring surface).

    Returns ``(config, note or None)``.
    """
    from dataclasses import replace

    names = {v.name for v in views}
    px = []
    for im in cameras:
        if im.name in names and im.rotation_std_deg is not None and np.all(np.isfinite(im.rotation_std_deg)):
            cam = cameras.camera_of(im)
            px.append(float(np.mean(np.diag(cam.K)[:2])) * np.deg2rad(float(np.max(im.rotation_std_deg))))
    if not px:
        return cfg, None
    med = float(np.median(px))
    r = int(min(max_px, max(cfg.clean_radius_px, np.ceil(n_sigma * med))))
    if r == cfg.clean_radius_px:
        return cfg, None
    return replace(cfg, clean_radius_px=r), (
        f"{n_sigma:g} × the median pose rotation σ ({med:.2f} px) from cameras.json: texels within that distance of a "
        f"silhouette are not taken, except on faces with no texel clean at that radius (those take texels clean at "
        f"the largest smaller radius, down to 0 px; texture.json faces_textured_at_min_clean_radius)")


def check_mesh_meets_cameras(V, F, views, cfg, mesh_path, survey_dir, crs, *, textured: int | None = None) -> None:
    """Raise :class:`InvalidInputError` when no face of the mesh is in front of any image, or (``textured=0``,
    after texturing) when not one texel could be taken from any image. ``F`` is the winding chosen by
    :func:`orient_mesh_to_views` (which already tried the reversed one).

    The usual cause is a mesh in another coordinate system than ``cameras.json`` (a local model against a
    georeferenced survey, or another CRS): a building kilometres away may still project into some image, but
    far below a pixel, so that no pixel sees its surface. The message gives both extents.
    """
    from ..products.texture import any_face_seen

    if textured is None:
        kw = dict(max_angle_deg=cfg.max_angle_deg, border_fraction=cfg.border_fraction)
        if any_face_seen(V, F, views, **kw):
            return
        what = "is in front of"
    else:
        what = "could be textured (no image pixel sees its surface) from"
    C = np.array([v.pose.center for v in views])

    def box(a):
        lo, hi = a.min(axis=0), a.max(axis=0)
        return "[" + ", ".join(f"{x:.2f}..{y:.2f}" for x, y in zip(lo, hi)) + "]"

    raise InvalidInputError(
        f"{mesh_path}: no face of the mesh ({len(F)} faces) {what} any of the {len(views)} images of {survey_dir}: "
        f"mesh X, Y, Z {box(V)} m; camera centres {box(C)} m (cameras.json crs {crs or 'local frame'}); expected the "
        "mesh in the same coordinate system as cameras.json and within the images' view")


def orient_mesh_to_views(V, F, views, cfg):
    """Reverse the triangles' winding when no face faces any image but the reversed mesh does.

    The texture takes a face's normal by the right-hand rule and needs it towards the cameras; a mesh exported
    with the opposite convention (or a plane fitted to a cloud, whose normal sign is arbitrary) would otherwise
    give an empty texture. Only an all-or-nothing case is changed: with at least one face seen, the mesh is used
    as given. Returns ``(faces, note or None)``.
    """
    from ..products.texture import any_face_seen, face_view_scores

    kw = dict(max_angle_deg=cfg.max_angle_deg, border_fraction=cfg.border_fraction)
    if any_face_seen(V, F, views, **kw):
        return F, None
    Fr = np.ascontiguousarray(F[:, ::-1])
    seen = int(np.sum(face_view_scores(V, Fr, views, **kw).getnnz(axis=1) > 0))
    if not seen:
        return F, None
    return Fr, (f"no face's normal (right-hand rule) pointed towards any of the {len(views)} images; with the winding "
                f"reversed {seen} of {len(F)} faces face them: every triangle's vertex order was reversed "
                "(the written OBJ/GLB/PLY carry the reversed order)")


def survey_tie_points(survey_dir, names):
    """The survey's tie points and their observations in ``names`` (its COLMAP export, ``survey_dir/colmap``;
    ``survey_dir`` is the folder of its cameras.json, :attr:`OrientedCameras.root`).

    Returns ``(TiePoints, None)``, or ``(None, reason)`` when the survey folder has no such export (a
    ``cameras.json`` from elsewhere) or it shares no image with ``names``.
    """
    from ..io.colmap import read_colmap_images, read_colmap_points3d
    from ..sfm.meshfit import TiePoints

    folder = Path(survey_dir) / "colmap"
    if not (folder / "images.txt").is_file() or not (folder / "points3D.txt").is_file():
        return None, f"{folder}: no COLMAP export with the survey's tie points (images.txt, points3D.txt)"
    ims = read_colmap_images(folder / "images.txt")
    pts = read_colmap_points3d(folder / "points3D.txt")
    index = {n: k for k, n in enumerate(names)}
    row = {int(i): r for r, i in enumerate(pts.ids)}
    op, oi, oxy = [], [], []
    for im in ims.values():
        k = index.get(im.name, index.get(Path(im.name).stem))
        if k is None:
            continue
        ok = np.flatnonzero(im.point3d_ids >= 0)
        ok = ok[[int(p) in row for p in im.point3d_ids[ok]]]
        if not len(ok):
            continue
        op.append(np.array([row[int(p)] for p in im.point3d_ids[ok]], np.int64))
        oi.append(np.full(len(ok), k, np.int64))
        oxy.append(im.xy_px[ok])
    if not op:
        return None, f"{folder}: no tie point observed in the textured images"
    return TiePoints(pts.xyz, np.concatenate(op), np.concatenate(oi), np.concatenate(oxy)), None


def fit_views_to_mesh(cameras, views, V, F, *, tie_sigma_px: float | None = None):
    """Refine the views' poses so that the survey's tie points lie on the mesh (:mod:`thermogrammetry.sfm.meshfit`);
    the tie points are those of the COLMAP export beside ``cameras``' file (:attr:`OrientedCameras.root`).

    Returns ``(views, record)``: the views with the fitted poses when the fit was kept (else unchanged), and what
    ``texture.json`` records under ``pose_fit`` (``applied``, ``reason``, the figures).
    """
    from dataclasses import replace as dc_replace

    from ..geometry import Pose
    from ..sfm.meshfit import MeshFitOptions, fit_poses_to_mesh

    names = [v.name for v in views]
    if cameras.root is None:
        return views, {"applied": False, "reason": "the cameras were not read from a survey folder (no tie points)"}
    ties, why = survey_tie_points(cameras.root, names)
    if ties is None:
        return views, {"applied": False, "reason": why}
    ims = [cameras.image(n) for n in names]
    opt = MeshFitOptions(tie_sigma_px=float(tie_sigma_px) if tie_sigma_px and np.isfinite(tie_sigma_px) else 1.0)
    res = fit_poses_to_mesh(names, cameras.cameras, [im.camera_id for im in ims], [(im.R, im.t) for im in ims],
                            [im.center_std for im in ims], ties, V, F, opt)
    record = {"applied": bool(res.applied), "reason": res.reason, **res.figures}
    if not res.applied:
        return views, record
    out = []
    for v in views:
        if v.name in res.poses:
            R, t = res.poses[v.name]
            v = dc_replace(v, pose=Pose(R, t))
        out.append(v)
    return out, record


def photometric_fit_views(cameras, views, V, F, cfg, *, rig: bool = False, progress=None):
    """Refine the views' poses so that the images agree on the mesh's temperatures
    (:func:`thermogrammetry.products.photofit.photometric_pose_fit`), with the survey's σ of every view as its priors
    (none in rig mode: the options' defaults) and a visibility test at the texture's clean radius (at least 3 px).

    Returns ``(views, record)``: the refined views when the refinement was kept (else unchanged) and what
    ``texture.json`` records under ``photometric_fit``.
    """
    from ..products.photofit import PhotoFitOptions, photometric_pose_fit

    by_name = {} if rig else {im.name: im for im in cameras}
    rot, cen = [], []
    for v in views:
        im = by_name.get(v.name)
        rot.append(np.full(3, np.nan) if im is None or im.rotation_std_deg is None else im.rotation_std_deg)
        cen.append(np.full(3, np.nan) if im is None or im.center_std is None else im.center_std)
    opt = PhotoFitOptions(clean_radius_px=max(3, int(cfg.clean_radius_px)), max_angle_deg=min(70.0, cfg.max_angle_deg))
    res = photometric_pose_fit(V, F, views, rotation_std_deg=np.array(rot, float), center_std_m=np.array(cen, float),
                               options=opt, progress=progress)
    record = {"applied": bool(res.applied), "reason": res.reason, **res.figures,
              "note": "poses only: the per-image offsets estimated alongside are not applied to any value"}
    return (res.views if res.applied else views), record


def _survey_tie_sigma(survey_dir) -> float | None:
    """The survey's tie-point reprojection RMS (``survey_dir/survey.json``), or None."""
    try:
        v = json.loads((Path(survey_dir) / "survey.json").read_text(encoding="utf-8")).get("reprojection_rms_px")
        return float(v) if v is not None and np.isfinite(float(v)) and float(v) > 0 else None
    except (OSError, ValueError, TypeError):
        return None


def _link_frame(cameras, im: dict, store) -> str:
    """The frame of image ``im`` placed beside ``cameras_fitted.json`` at the same relative path as in the survey's
    cameras.json (a hard link where the file system allows it, else a copy; the survey's file is never moved), so
    that the file reads like any cameras.json. The path is returned. ``cameras`` was loaded with its frames confined
    to its folder, so ``im["frame"]`` is relative and stays inside."""
    rel = posixpath.normpath(str(im["frame"]).replace("\\", "/"))
    src, dst = cameras.frame_path(im["name"]), store.local_path(rel)
    if src.is_file() and not dst.exists():
        try:
            os.link(src, dst)
        except OSError:
            shutil.copy2(src, dst)
    return rel


#: the progress stage of the photometric pose fit (:func:`run_texture`)
STAGE_PHOTOMETRIC_FIT = "photometric pose fit (views)"


def with_camera_file(cameras, camera_file):
    """``cameras`` (OrientedCameras) with the thermal camera(s) of the same image size replaced by the camera of
    ``camera_file`` (:class:`~thermogrammetry.io.camera_file.CameraFile`: a lab calibration held for the texturing);
    returns ``(cameras, record)`` with ``record = {**camera_file.to_dict(), "replaces": [camera ids]}``. A camera of
    another image size than every thermal camera is refused (:class:`ConfigError` naming both sizes)."""
    from dataclasses import replace

    size = tuple(camera_file.camera.image_size)
    ids = sorted({im.camera_id for im in cameras.images if str(getattr(im.sensor, "value", im.sensor)) == "thermal"})
    hit = [cid for cid in ids if tuple(cameras.cameras[cid].image_size) == size]
    if not hit:
        sizes = sorted({tuple(cameras.cameras[cid].image_size) for cid in ids})
        raise ConfigError(f"--camera {camera_file.path}: image size {size[0]}x{size[1]}; the survey's thermal cameras "
                          f"are {', '.join(f'{w}x{h}' for w, h in sizes) or 'none'}; expected the calibration of the "
                          "thermal camera at its frames' size")
    new = dict(cameras.cameras)
    for cid in hit:
        new[cid] = camera_file.camera
    return replace(cameras, cameras=new), {**camera_file.to_dict(), "replaces": hit}


def run_texture(survey_dir, mesh_path, out_dir, *, unit: str | None = None, correct: bool = False, levelling: str = "none",
                rig_path=None, config=None, progress=None, fit_poses: str = "auto", max_faces: int | None = None,
                camera=None) -> dict:
    """The ``texture`` verb as a function; returns the ``texture.json`` content as a dict.

    ``unit``: ``"K"`` or ``"C"`` for kelvin frames (default ``"K"``); must stay ``None`` for frames in raw counts
    (the texture then holds counts, labelled as such; :class:`InvalidInputError` otherwise, as for ``correct``).
    ``fit_poses``: ``"auto"`` (default) refines the poses so that the survey's tie points lie on the mesh
    (:func:`fit_views_to_mesh`; kept only when the mesh and the tie points meet and the fit converges without
    bending the block; ``texture.json`` ``pose_fit`` says what happened, ``cameras_fitted.json`` holds the poses
    used), then refines them photometrically (:func:`photometric_fit_views`, ``texture.json`` ``photometric_fit``);
    ``"mesh"``: the first step only; ``"off"``: the survey's poses as they are. ``max_faces``: the mesh's triangle cap
    (default :data:`DEFAULT_MAX_FACES`). ``camera``: a camera file (camera.json, Metashape XML, OpenCV YAML/XML, COLMAP
    cameras.txt) whose calibration replaces the survey's thermal camera of the same size (:func:`with_camera_file`;
    ``texture.json`` ``camera_file``). ``progress``: optional callable ``progress(stage, done, total)`` called as the
    work goes: :data:`STAGE_PHOTOMETRIC_FIT` after each view of the photometric pose fit, then the stages of
    :func:`thermogrammetry.products.texture.texture_mesh` (per view, per chunk of texels and of face corners).
    """
    from dataclasses import replace

    from ..io.oriented import OrientedCameras
    from ..io.tiff import encode_temperature_tiff
    from ..products import texture_export as tx
    from ..products.texture import TextureConfig, texture_mesh
    from ..products.texture_atlas import check_texel_size
    from ..radiometry.encoding import TemperatureUnit, from_kelvin
    from .._atomic import OutputSet, check_output_apart, sync_folder
    from ..store import FolderProject

    call, t0 = python_call(run_texture, locals()), time.perf_counter()  # (the report's command line and time)
    check_output_apart(out_dir, [("survey folder", survey_dir)])
    cameras = OrientedCameras.load(survey_dir)
    camera_record = None
    if camera is not None:
        from ..io.camera_file import open_camera_file

        cameras, camera_record = with_camera_file(cameras, open_camera_file(camera))
    if max_faces is not None and (isinstance(max_faces, bool) or int(max_faces) != max_faces or max_faces < 1):
        raise ConfigError(f"max_faces={max_faces!r}: expected a positive number of triangles")
    V, F = read_mesh(mesh_path, max_faces=DEFAULT_MAX_FACES if max_faces is None else int(max_faces))
    if rig_path is not None:
        try:
            rig = json.loads(Path(rig_path).read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise DataFileError(f"{rig_path}: rig file not found") from None
        except json.JSONDecodeError as exc:
            raise UnsupportedFormatError(f"{rig_path}: not valid JSON ({exc.msg}, line {exc.lineno})") from None
        views, skipped, frame_unit = load_rig_views(cameras, rig, source=str(rig_path))
    else:
        frame_unit = frames_unit(cameras)
        views, skipped = load_views(cameras, unit=frame_unit or "K")
    fit_poses = str(fit_poses).lower()
    if fit_poses not in FIT_POSES:
        raise ConfigError(f"fit_poses={fit_poses!r}: expected one of {', '.join(FIT_POSES)}")
    counts = check_views_unit(views, skipped, frame_unit, survey_dir, unit, "texture")
    if counts:
        if correct:
            raise InvalidInputError(f"--correct: the thermal frames of {survey_dir} are raw counts (no documented conversion "
                                    "to temperature); the angle/emissivity/transmission correction needs temperatures "
                                    "(frames in kelvin)")
    u = None if counts else TemperatureUnit(unit or "K")
    unit_out = "counts" if counts else u.value
    cfg = config or TextureConfig()
    if cfg.texel_size_m is not None:
        check_texel_size(V, F, cfg.texel_size_m, cfg.max_texture_px, str(mesh_path))
    cfg = replace(cfg, correct=bool(correct), levelling=levelling)
    cfg, clean_note = clean_radius_from_poses(cfg, cameras, views)  # only ever widens the configured radius
    if cfg.min_clean_radius_px is None:
        # a face that no image sees cleanly even at the configured radius (a narrow face seen at a grazing angle, every
        # texel within a pixel of an edge) takes the pixels that see it, flagged per face, rather than none
        cfg = replace(cfg, min_clean_radius_px=0)
    if fit_poses == "off":
        pose_fit = {"applied": False, "reason": "off (fit_poses)"}
    elif rig_path is not None:
        pose_fit = {"applied": False, "reason": "rig mode: the thermal poses follow the RGB images through the rig"}
    else:
        views, pose_fit = fit_views_to_mesh(cameras, views, V, F, tie_sigma_px=_survey_tie_sigma(cameras.root))
    F, winding_note = orient_mesh_to_views(V, F, views, cfg)
    check_mesh_meets_cameras(V, F, views, cfg, mesh_path, survey_dir, cameras.crs)
    if fit_poses == "auto":
        per_view = None if progress is None else (lambda k, n: progress(STAGE_PHOTOMETRIC_FIT, k, n))
        views, photo_fit = photometric_fit_views(cameras, views, V, F, cfg, rig=rig_path is not None, progress=per_view)
    else:
        photo_fit = {"applied": False, "reason": f"{fit_poses} (fit_poses)"}
    result = texture_mesh(V, F, views, cfg, progress=progress)
    if not np.any(result.faces_textured):
        check_mesh_meets_cameras(V, F, views, cfg, mesh_path, survey_dir, cameras.crs, textured=0)
    with OutputSet(out_dir, "texture") as outputs:  # OUT complete or absent; a user's own files in OUT kept
        store = FolderProject(outputs.stage, durable=False)
        # result.temperature_k holds kelvin for temperature frames and the frames' raw counts for count frames
        t_unit = result.temperature_k.astype(np.float32) if counts else from_kelvin(result.temperature_k, u).astype(np.float32)
        preview = tx.preview_rgb(t_unit)
        lo, hi = tx.palette_range(t_unit)
        if counts:
            palette = {"colormap": "inferno", "quantity": "raw_counts", "unit": "counts", "label": "raw counts",
                       "min": lo, "max": hi, "note": "colours span the 1st-99th percentile of the raw counts (not temperatures)"}
        else:
            uname = {"K": "K", "C": "°C"}.get(u.value, u.value)
            palette = {"colormap": "inferno", "quantity": "temperature", "unit": uname, "label": "temperature",
                       "min": lo, "max": hi, "note": f"colours span the 1st-99th percentile of the temperatures ({uname})"}
        store.write_bytes("textured.png", tx.png_bytes(preview, text=tx.palette_png_text(palette)))
        glb = tx.glb_bytes(result, preview, extras=palette, crs=cameras.crs)
        store.write_bytes("textured.glb", glb)
        store.write_text("viewer.html", tx.viewer_html(glb))
        store.write_text("textured.obj", tx.obj_text(result, quantity="raw counts" if counts else "temperatures"))
        store.write_text("textured.mtl", tx.mtl_text("textured.png"))
        mapping = None
        u16_info = None
        if counts:
            store.write_bytes("temperature_texture.tif", tx.counts_float_tiff_bytes(t_unit))
            if np.any(np.isfinite(t_unit)):
                store.write_bytes("temperature_texture_u16.tif", tx.counts_u16_tiff_bytes(t_unit))
                u16_info = {"scale": 1.0, "offset": 0.0, "unit": "counts", "nodata_code": 0,
                            "max_quantisation_error": 0.5,
                            "note": "counts rounded to the nearest integer (bilinear samples are fractional), clipped to 1..65535"}
        else:
            data, _ = encode_temperature_tiff(result.temperature_k, unit=u.value, encoding="float32")
            store.write_bytes("temperature_texture.tif", data)
            if np.any(np.isfinite(result.temperature_k)):
                data16, mapping = encode_temperature_tiff(result.temperature_k, unit=u.value, encoding="uint16")
                store.write_bytes("temperature_texture_u16.tif", data16)
                u16_info = {"scale": mapping.scale, "offset": mapping.offset, "unit": u.value, "nodata_code": 0}
        if photo_fit.get("applied") and rig_path is not None:
            # rig mode: the thermal views are not images of cameras.json; their refined poses are listed here instead
            photo_fit["poses"] = {v.name: {"cam_from_world": {"R": np.asarray(v.pose.R).tolist(), "t": np.asarray(v.pose.t).tolist()},
                                           "center": np.asarray(v.pose.center).tolist()} for v in views}
        if (pose_fit.get("applied") or photo_fit.get("applied")) and rig_path is None:
            fitted = {v.name: v.pose for v in views}
            doc = cameras.to_dict()
            for im in doc["images"]:
                if im["name"] in fitted:
                    pz = fitted[im["name"]]
                    im["cam_from_world"] = {"R": np.asarray(pz.R).tolist(), "t": np.asarray(pz.t).tolist()}
                    im["center"] = np.asarray(pz.center).tolist()
                if im.get("frame"):
                    im["frame"] = _link_frame(cameras, im, store)
            store.write_text("cameras_fitted.json", json.dumps(doc, indent=1) + "\n")
        store.write_bytes("source_texture.tif", tx.int32_tiff_bytes(result.source))
        store.write_bytes("angle_texture.tif", tx.float32_tiff_bytes(result.angle_deg))
        store.write_bytes("vertices.ply", tx.ply_bytes(V, F, result.vertex_temperature_k,
                                                       name="raw_counts" if counts else "temperature_k"))
        extra = {"skipped": [{"image": n, "reason": r} for n, r in skipped],
                 "uint16_mapping": u16_info,
                 "rig": None if rig_path is None else str(rig_path),
                 "clean_radius_px": {"value": int(cfg.clean_radius_px), "reason": clean_note or "default"},
                 "pose_fit": pose_fit, "photometric_fit": photo_fit, "camera_file": camera_record}
        if winding_note:
            extra["mesh_winding"] = {"reversed": True, "reason": winding_note}
        extra["preview_palette"] = palette
        text = tx.texture_json(result, unit_out, mesh_source=str(mesh_path), survey_source=str(survey_dir), extra=extra)
        store.write_text("texture.json", text)
        header = ReportHeader("texture", inputs=[(len(views), "images of the survey", [str(Path(survey_dir).resolve())]),
                                                 (None, "mesh", [str(Path(mesh_path).resolve())])],
                              crs=cameras.crs, georeferenced=cameras.crs is not None, command=command_line() or call,
                              seconds=time.perf_counter() - t0)
        store.write_text("report.html", texture_report_html(result, views, skipped, unit_out, pose_fit, photo_fit, header))
        sync_folder(outputs.stage)
        outputs.commit()

    return json.loads(text)
