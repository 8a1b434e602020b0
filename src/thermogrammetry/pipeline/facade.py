"""``facade`` workflow: thermal orthoimage of a flat facade without a mesh (seed 002), two routes.

**Oriented** (:func:`run_facade`): reads a survey folder (``cameras.json`` + frames) through :class:`~thermogrammetry.io.oriented.OrientedCameras`,
puts the facade plane in object space (given, or fitted to the survey's sparse cloud), and calls
:func:`thermogrammetry.products.facade.plane_mosaic` (image choice per tile by resolution on the surface and
distance from the image border, one image per cell, values sampled from it, nothing blended). Writes::

    facade_temperature.tif   float32 in the chosen unit (K or °C), or raw counts labelled as counts; NaN = none
    facade_source.tif        int32 index of the source image (facade.json "index"), -1 = none
    facade_angle.tif         float32 viewing angle of the source image (deg); oriented route only
    facade_resolution.tif    float32 resolution of the source image on the facade (px/m)
    facade.png               palette preview with its colour scale
    facade.json              plane (origin, u along, v up, normal), grid, unit, index -> image, coverage, notes

Raster convention: row 0 is the TOP of the facade; cell ``(row, col)`` is centred at plane coordinates
``a = a0 + (col + 0.5)·cell_m`` (along ``u``), ``b = b1 − (row + 0.5)·cell_m`` (along ``v``, up); object
coordinates ``X = origin + a·u + b·v`` in the survey's CRS (or its local frame).

The fitted plane (``plane="auto"``): RANSAC on ``sparse.ply`` (fixed seed), inlier band 1 % of the median
camera-to-point distance, refined by least squares on the inliers; normal towards the cameras; ``v`` is the
cameras' mean "up" (−y of the camera frame) projected on the plane, so a facade is upright whatever the
frame; extent: the 1st–99th percentile of the inliers in plane coordinates.

**Homography** (:func:`run_facade_homography`): stand-alone thermal frames read through the io layer (like
``survey``), each rectified by :func:`~thermogrammetry.products.facade.fit_facade_homography` from >= 4 points with
known facade coordinates (``points.csv``: ``id,u,v`` metres; measurements ``image,id,x,y`` px, (0, 0) the centre of
the top-left pixel, the survey's CSV rules), mosaicked by
:func:`~thermogrammetry.products.facade.homography_mosaic` with the same image-choice rule and source map; grid
``(u, v)`` = the points' coordinates. No orientation, so no viewing angle (``facade_angle.tif`` omitted, said in
``facade.json``). An image with < 4 points, no 4 in general position or unreadable is skipped with its reason;
:class:`NothingMosaickedError` (CLI exit 1) when none is left.

**Levelling** (both routes, ``levelling="offsets"``): per-image additive offsets from the cells that two or more
images can serve (:func:`~thermogrammetry.products.facade.level_offsets`, texture's estimator), ADDED to every cell
of their image; ``facade.json`` holds each offset with its formal σ, the held image, the pair counts and the overlap
RMS before/after, and ``values_altered: true``.

References
----------
.. [1] Barazzetti, Erba, Previtali, Rosina, Scaioni (2013), seed 002: thermal orthophotos of facades.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import DataFileError, InvalidInputError, ThermogrammetryError, TooFewPointsError

__all__ = ["NothingMosaickedError", "fit_facade_plane", "parse_plane", "read_plane_points", "run_facade", "run_facade_homography"]

#: RANSAC iterations of the plane fit (seeded: deterministic)
PLANE_RANSAC_ITERATIONS = 2000


def _up_vector(cameras) -> np.ndarray:
    ups = [im.pose.R.T @ np.array([0.0, -1.0, 0.0]) for im in cameras]
    return np.mean(ups, axis=0)


def _frame(normal, up, towards) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal (u, v, n): n the plane normal turned towards ``towards`` (a direction), v = ``up`` projected
    on the plane (or any in-plane direction when ``up`` is along the normal), u = v × n, so that u × v = n."""
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    if n @ towards < 0:
        n = -n
    v = np.asarray(up, float) - (np.asarray(up, float) @ n) * n
    if np.linalg.norm(v) < 1e-6:
        v = np.cross(n, [1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.cross(n, [0.0, 1.0, 0.0])
    v = v / np.linalg.norm(v)
    u = np.cross(v, n)
    return u / np.linalg.norm(u), v, n


def fit_facade_plane(points, cameras, *, seed: int = 0):
    """Plane of a facade fitted to sparse points (RANSAC, then least squares on the inliers).

    Parameters
    ----------
    points : (N, 3) array, object coordinates (metres or model units)
    cameras : OrientedCameras (their centres orient the normal, their mean "up" the plane's v axis)

    Returns
    -------
    (FacadePlane, (a0, a1, b0, b1) extent of the inliers, inlier count)
    """
    from ..products.facade import FacadePlane

    X = np.asarray(points, float)
    X = X[np.all(np.isfinite(X), axis=1)]
    if len(X) < 10:
        raise TooFewPointsError(f"facade plane: {len(X)} sparse points; expected at least 10 to fit a plane")
    C = np.array([im.center for im in cameras])
    dist = np.median(np.linalg.norm(X[:, None, :] - C[None, :min(len(C), 50), :], axis=2))
    band = 0.01 * dist
    rng = np.random.default_rng(seed)
    best, best_n, best_p = -1, None, None
    for _ in range(PLANE_RANSAC_ITERATIONS):
        p = X[rng.choice(len(X), 3, replace=False)]
        n = np.cross(p[1] - p[0], p[2] - p[0])
        nn = np.linalg.norm(n)
        if nn < 1e-12:
            continue
        n = n / nn
        c = int((np.abs((X - p[0]) @ n) < band).sum())
        if c > best:
            best, best_n, best_p = c, n, p[0]
    inl = np.abs((X - best_p) @ best_n) < band
    P = X[inl]
    cen = P.mean(axis=0)
    n = np.linalg.svd(P - cen, full_matrices=False)[2][2]
    u, v, n = _frame(n, _up_vector(cameras), C.mean(axis=0) - cen)
    ab = (P - cen) @ np.column_stack([u, v])
    lo, hi = np.percentile(ab, 1, axis=0), np.percentile(ab, 99, axis=0)
    return FacadePlane(tuple(cen), tuple(u), tuple(v)), (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])), int(inl.sum())


def parse_plane(text: str, cameras):
    """``"X,Y,Z,nx,ny,nz"``: a point of the plane and its normal (object coordinates) -> FacadePlane."""
    from ..products.facade import FacadePlane

    try:
        vals = [float(x) for x in str(text).split(",")]
    except ValueError:
        vals = []
    if len(vals) != 6 or not np.all(np.isfinite(vals)) or np.linalg.norm(vals[3:]) == 0:
        raise InvalidInputError(f"--plane {text!r}: expected 'auto' or six numbers X,Y,Z,nx,ny,nz (a point of the "
                                "facade plane and its normal, in the survey's coordinates)")
    C = np.array([im.center for im in cameras])
    u, v, n = _frame(vals[3:], _up_vector(cameras), C.mean(axis=0) - np.array(vals[:3]))
    return FacadePlane(tuple(vals[:3]), tuple(u), tuple(v))


def _extent_from_views(plane, views) -> tuple[float, float, float, float]:
    """Plane extent covered by the image centres' rays and corners (when no sparse cloud bounds it)."""
    o, n = np.asarray(plane.origin, float), plane.normal
    U = np.column_stack([plane.u, plane.v])
    ab = []
    for vw in views:
        w, h = vw.camera.image_size
        px = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1], [(w - 1) / 2, (h - 1) / 2]], float)
        rays = vw.camera.unproject(px)
        d = np.column_stack([rays[:, :2], np.ones(len(rays))]) @ vw.pose.R  # world directions (rows)
        Cc = vw.pose.center
        den = d @ n
        t = ((o - Cc) @ n) / np.where(np.abs(den) > 1e-9, den, np.nan)
        pts = Cc + t[:, None] * d
        ok = t > 0
        ab.append(((pts[ok] - o) @ U))
    ab = np.concatenate(ab) if ab else np.zeros((0, 2))
    if len(ab) < 3:
        raise InvalidInputError("facade: no image looks at the plane; check --plane")
    lo, hi = np.percentile(ab, 5, axis=0), np.percentile(ab, 95, axis=0)
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def _check_common(cell_m, tile_m, levelling):
    if not (cell_m is None or (np.isfinite(cell_m) and cell_m > 0)):
        raise InvalidInputError(f"--cell {cell_m!r}: expected a cell size in metres > 0")
    if not (np.isfinite(tile_m) and tile_m > 0):
        raise InvalidInputError(f"--tile {tile_m!r}: expected a tile size in metres > 0")
    if str(levelling).lower() not in ("none", "offsets"):
        raise InvalidInputError(f"--levelling {levelling!r}: expected none or offsets")
    return str(levelling).lower()


def run_facade(survey_dir, out_dir, *, plane: str = "auto", cell_m: float | None = None, unit: str | None = None,
               tile_m: float = 1.0, occluders_path=None, levelling: str = "none") -> dict:
    """The ``facade`` verb as a function; returns the ``facade.json`` content as a dict.

    ``unit``: ``"K"`` or ``"C"`` for kelvin frames (default K); must stay None for frames in raw counts (the
    mosaic then holds counts, labelled as such). ``levelling``: ``"none"`` (default) or ``"offsets"``
    (per-image additive offsets from the overlaps, :func:`thermogrammetry.products.facade.level_offsets`:
    they alter the values, and are reported in ``facade.json``).
    """
    from ..io.oriented import OrientedCameras
    from ..products.facade import FacadeGrid, plane_mosaic
    from ..radiometry.encoding import TemperatureUnit
    from .texture import check_views_unit, frames_unit, load_views, read_mesh

    from .._atomic import check_output_apart

    check_output_apart(out_dir, [("survey folder", survey_dir)])
    levelling = _check_common(cell_m, tile_m, levelling)
    cameras = OrientedCameras.load(survey_dir)
    frame_unit = frames_unit(cameras)
    views, skipped = load_views(cameras, unit=frame_unit or "K")
    counts = check_views_unit(views, skipped, frame_unit, survey_dir, unit, "mosaic")
    u_t = None if counts else TemperatureUnit(unit or "K")
    root = Path(survey_dir)
    root = root.parent if root.is_file() else root
    n_inliers = None
    if str(plane).lower() == "auto":
        ply = root / "sparse.ply"
        if not ply.is_file():
            raise DataFileError(f"{ply}: not found; --plane auto fits the facade to the survey's sparse cloud. Give the "
                                "plane as X,Y,Z,nx,ny,nz instead")
        from plyfile import PlyData

        vtx = PlyData.read(str(ply))["vertex"]
        pts = np.column_stack([vtx["x"], vtx["y"], vtx["z"]]).astype(float)
        pl, ext, n_inliers = fit_facade_plane(pts, list(cameras))
        how = f"fitted to {n_inliers} of {len(pts)} sparse points ({ply.name}, RANSAC, band 1 % of the viewing distance)"
    else:
        pl = parse_plane(plane, list(cameras))
        ext = _extent_from_views(pl, views)
        how = "given (--plane X,Y,Z,nx,ny,nz)"
    if cell_m is None:
        # one pixel of the median view at the plane, along the optical axis
        o, n = np.asarray(pl.origin, float), pl.normal
        fp = []
        for vw in views:
            d = vw.pose.R.T @ np.array([0.0, 0.0, 1.0])
            den = d @ n
            if abs(den) > 1e-6:
                t = ((o - vw.pose.center) @ n) / den
                if t > 0:
                    fp.append(t / (0.5 * (vw.camera.K[0, 0] + vw.camera.K[1, 1])))
        if not fp:
            raise InvalidInputError("facade: no image looks at the plane; check --plane")
        cell_m = float(np.median(fp))
    a0, a1, b0, b1 = ext
    if (a1 - a0) / cell_m * (b1 - b0) / cell_m > 60e6:
        raise InvalidInputError(f"facade: {a1 - a0:.2f} x {b1 - b0:.2f} at {cell_m:g} per cell is over 60 million cells; "
                                "give a larger --cell")
    grid = FacadeGrid(a0, a1, b0, b1, cell_m)
    occ = read_mesh(occluders_path) if occluders_path is not None else None
    mos = plane_mosaic(views, pl, grid, occluders=occ, tile_m=tile_m, levelling=levelling)
    head = {"route": "oriented", "survey": str(survey_dir),
            "plane": {"origin": list(map(float, pl.origin)), "u": list(map(float, pl.u)), "v": list(map(float, pl.v)),
                      "normal": pl.normal.tolist(), "how": how}}
    grid_conv = ("row 0 at the top; cell (r, c) centred at a = a0 + (c + 0.5) cell, b = b1 - (r + 0.5) cell; "
                 "X = origin + a u + b v")
    return _write_outputs(out_dir, mos, counts, u_t, head, grid_conv, skipped, tile_m)


def _levelling_json(mos, counts: bool) -> dict:
    lev = mos.levelling
    key = "offsets_rms_before_after_counts" if counts else "offsets_rms_before_after_k"
    if lev is None:
        return {"levelling": "none", "offsets": None, "offsets_sigma": None, "offsets_fixed_image": None, key: None}
    names = mos.names
    return {"levelling": "offsets",
            "offsets": {n: float(o) for n, o in zip(names, lev.offsets)},
            "offsets_sigma": {n: (float(s) if np.isfinite(s) else None) for n, s in zip(names, lev.sigma)},
            "offsets_fixed_image": names[lev.fixed],
            key: [lev.rms_before, lev.rms_after],
            "offsets_pairs": {n: int(p) for n, p in zip(names, lev.pairs)},
            "offsets_not_levelled": [n for n, c in zip(names, lev.connected) if not c],
            "offsets_cells_sampled": lev.cells_sampled,
            "offsets_note": ("per-image additive offsets (" + ("counts" if counts else "K") + ") from the overlaps: least "
                             "squares over pairs of images' values at sampled cells that both can serve, the image "
                             "supplying most cells held at 0; each offset was ADDED to every cell of its image. sigma: "
                             "formal, treating the pairs as independent (a lower bound)" + (f"; {lev.note}" if lev.note else ""))}


def _write_outputs(out_dir, mos, counts: bool, u_t, head: dict, grid_conv: str, skipped, tile_m: float,
                   extra: dict | None = None) -> dict:
    """Write the rasters, the preview and facade.json of a mosaic; returns facade.json as a dict."""
    from ..io.tiff import encode_raster_tiff, encode_temperature_tiff
    from ..products import texture_export as tx
    from ..radiometry.encoding import from_kelvin
    from .._atomic import OutputSet, sync_folder
    from ..store import FolderProject

    grid = mos.grid
    with OutputSet(out_dir, "facade") as outputs:  # OUT complete or absent; a user's own files in OUT kept
        store = FolderProject(outputs.stage, durable=False)
        vals = mos.temperature_k.astype(np.float32) if counts else from_kelvin(mos.temperature_k, u_t).astype(np.float32)
        if counts:
            store.write_bytes("facade_temperature.tif", tx.counts_float_tiff_bytes(vals))
        else:
            data, _ = encode_temperature_tiff(mos.temperature_k, unit=u_t.value, encoding="float32")
            store.write_bytes("facade_temperature.tif", data)
        store.write_bytes("facade_source.tif", tx.int32_tiff_bytes(mos.source))
        files = ["facade_temperature.tif", "facade_source.tif"]
        if mos.angle_deg is not None:
            store.write_bytes("facade_angle.tif", encode_raster_tiff(mos.angle_deg, unit="deg",
                                                                     description="viewing angle of the source image (deg); NaN = none"))
            files.append("facade_angle.tif")
        store.write_bytes("facade_resolution.tif", encode_raster_tiff(mos.resolution_px_per_m, unit="px/m",
                                                                      description="resolution of the source image on the facade"))
        unit_out = "counts" if counts else u_t.value
        store.write_bytes("facade.png", _preview_png(vals, unit_out))
        files += ["facade_resolution.tif", "facade.png", "facade.json"]
        filled = int((mos.source >= 0).sum())
        used = sorted({int(s) for s in np.unique(mos.source) if s >= 0})
        lev = mos.levelling
        out = {"format": "thermogrammetry/facade", "version": 1, **head, "unit": unit_out,
               "quantity": "raw_counts" if counts else "temperature",
               "grid": {"a0": grid.a0, "a1": grid.a1, "b0": grid.b0, "b1": grid.b1, "cell": grid.cell_m, "shape": list(grid.shape),
                        "convention": grid_conv},
               "cells_total": int(mos.source.size), "cells_filled": filled,
               "index": {str(k): n for k, n in enumerate(mos.names)}, "images_used": len(used),
               "cells_per_image": {n: int(c) for n, c in zip(mos.names, np.bincount(mos.source[mos.source >= 0],
                                                                                   minlength=len(mos.names)))},
               "skipped": [{"image": n, "reason": r} for n, r in skipped],
               "tile": tile_m, "notes": mos.notes,
               **_levelling_json(mos, counts),
               "values_altered": lev is not None,
               "values": ("each cell's value is sampled (bilinear) from one image, chosen per tile; nothing blended or filled"
                          + ("; per-image offsets ADDED (levelling=offsets)" if lev is not None else "")),
               "files": files}
        if mos.angle_deg is None:
            out["angle"] = ("facade_angle.tif not written: without an orientation (homography route) the viewing angle "
                            "is not known")
        if extra:
            out.update(extra)
        store.write_text("facade.json", json.dumps(out, indent=1))
        sync_folder(outputs.stage)
        outputs.commit()
    return out


def _preview_png(vals, unit: str) -> bytes:
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fin = vals[np.isfinite(vals)]
    lo, hi = (np.percentile(fin, [1, 99]) if len(fin) else (0.0, 1.0))
    h, w = vals.shape
    fig, ax = plt.subplots(figsize=(8, max(2.5, 8 * h / max(w, 1))), dpi=100)
    im = ax.imshow(vals, cmap="inferno", vmin=lo, vmax=hi)
    ax.set_xticks([])
    ax.set_yticks([])
    label = {"K": "temperature (K)", "C": "temperature (°C)", "counts": "raw counts (not a temperature)"}.get(unit, unit)
    fig.colorbar(im, ax=ax, label=label, fraction=0.046, pad=0.04)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


# ------------------------------------------------------------------------------------------------ homography route
class NothingMosaickedError(ThermogrammetryError):
    """No image could be rectified (every one lacked points, was degenerate or unreadable): exit 1."""


def read_plane_points(path):
    """``points.csv``: ``id,u,v`` (metres on the facade plane: u along, v up), the rules of
    :mod:`thermogrammetry.io.testfield_csv` (header any order, case-insensitive; ``#`` comments; comma,
    semicolon or tab). Returns ``(ids tuple, uv (M, 2) float, source)``; errors name the file, row and value."""
    from ..errors import UnsupportedFormatError
    from ..io.testfield_csv import _header, _num, _rows, _unique_id_rows, read_text

    text, source = read_text(path)
    _, rows = _rows(text)
    if not rows:
        raise UnsupportedFormatError(f"{source}: empty file; expected a header id,u,v (metres on the facade plane) and "
                                     "one row per point")
    cmap, data = _header(rows, ("id", "u", "v"), (), source, "plane")
    if not data:
        raise UnsupportedFormatError(f"{source}: no points after the header")
    ids, uv = [], []
    for n, pid, row in _unique_id_rows(data, cmap, source):
        ids.append(pid)
        uv.append([_num(row, cmap, c, n, source, "metres on the facade plane") for c in ("u", "v")])
    return tuple(ids), np.array(uv, float), source


def _decode_frames(images, input_unit):
    """Files/folders -> ([(name, array float32, unit 'K'|'counts', source path)], skipped[(name, reason)], notes)."""
    from ..io import iter_thermal
    from .survey import expand_inputs, frame_values

    files, notes = expand_inputs([str(p) for p in images])
    frames, skipped, used = [], [], set()
    for path in files:
        try:
            got = [frame_values(im, path, counts_dtype=np.float32) for im in iter_thermal(path, unit=input_unit)]
        except (ThermogrammetryError, OSError, ValueError) as exc:
            reason = str(exc).replace("pass unit='K' or unit='C'", "give --input-unit K or C")
            skipped.append((Path(path).name, f"not read: {reason}"))
            continue
        for sfx, arr, u in got:
            name = Path(path).stem + sfx
            base, k = name, 1
            while name in used:
                k += 1
                name = f"{base}_{k}"
            used.add(name)
            frames.append((name, arr, u, str(path)))
    return frames, skipped, notes


def _footprint_extent(fits, shapes, pts_uv):
    """Union of the images' footprints on the plane (their corners through H^-1, images whose four corners all
    map in front), clipped to the points' bounding box grown by half its size on every side."""
    lo_p, hi_p = pts_uv.min(axis=0), pts_uv.max(axis=0)
    span = np.maximum(hi_p - lo_p, 1e-6)
    lo_c, hi_c = lo_p - 0.5 * span, hi_p + 0.5 * span
    ab = [pts_uv]
    for fit, (h, w) in zip(fits, shapes):
        c = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]], float)
        if fit.camera is not None:
            c = fit.camera.undistort(c)
        q = np.c_[c, np.ones(4)] @ np.linalg.inv(fit.H).T
        if np.all(q[:, 2] > 0) or np.all(q[:, 2] < 0):  # all four corners on the plane in front of the camera
            ab.append(q[:, :2] / q[:, 2:3])
    ab = np.clip(np.concatenate(ab), lo_c, hi_c)
    lo, hi = ab.min(axis=0), ab.max(axis=0)
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def run_facade_homography(images, points_csv, measurements_csv, out_dir, *, cell_m: float | None = None,
                          unit: str | None = None, input_unit: str | None = None, tile_m: float = 1.0,
                          levelling: str = "none", camera_path=None, extent: str | None = None) -> dict:
    """The ``facade --images`` route: rectify thermal frames by homographies from points of known plane
    coordinates (no orientation), mosaic them with the image-choice rule of the oriented route.

    Parameters
    ----------
    images : files and/or folders of thermal frames (read by :func:`thermogrammetry.io.iter_thermal`: FLIR/DJI
        R-JPEG, TIFF incl. float kelvin/°C with ``input_unit``, SEQ/CSQ, CSV/NPY matrices)
    points_csv : ``id,u,v`` metres on the facade plane (:func:`read_plane_points`)
    measurements_csv : ``image,id,x,y[,sx,sy]`` pixels, (0, 0) the centre of the top-left pixel; image named with
        or without extension (:func:`thermogrammetry.io.testfield_csv.read_measurements_csv`)
    out_dir : output folder (written only when a mosaic was made)
    cell_m : cell size (m); default the median over the images of one pixel on the plane at the image centre
    unit : ``"K"``/``"C"`` for temperature frames (default K), None for raw counts (the mosaic holds counts)
    input_unit : ``"K"``/``"C"``: unit of float TIFFs that declare none
    levelling : ``"none"`` or ``"offsets"`` (see :func:`run_facade`)
    camera_path : optional ``camera.json`` (from ``calibrate``): measured points are undistorted and the lens
        distortion re-applied when sampling; without it the frames are taken as distortion-free
    extent : optional ``"u0,u1,v0,v1"`` (m); default: the images' footprints on the plane, clipped to the points'
        bounding box grown by half its size on every side

    Returns
    -------
    dict, the ``facade.json`` content. Images without 4 usable points, with a degenerate configuration or
    unreadable are listed in ``skipped`` with the reason; :class:`NothingMosaickedError` when none is left.
    """
    from ..errors import CorruptFileError
    from ..io.testfield_csv import read_measurements_csv
    from ..products.facade import FacadeGrid, fit_facade_homography, homography_mosaic
    from ..radiometry.encoding import TemperatureUnit
    from .._atomic import check_output_apart

    check_output_apart(out_dir, [("image folder" if Path(p).is_dir() else "image", p) for p in images]
                       + [("plane points", points_csv), ("measurements", measurements_csv)])
    levelling = _check_common(cell_m, tile_m, levelling)
    if input_unit is not None and str(input_unit).upper() not in ("K", "C"):
        raise InvalidInputError(f"--input-unit {input_unit!r}: expected K or C")
    ext = None
    if extent is not None:
        try:
            ext = [float(x) for x in str(extent).split(",")]
        except ValueError:
            ext = []
        if len(ext) != 4 or not np.all(np.isfinite(ext)) or not (ext[1] > ext[0] and ext[3] > ext[2]):
            raise InvalidInputError(f"--extent {extent!r}: expected u0,u1,v0,v1 in metres on the facade plane with "
                                    "u1 > u0 and v1 > v0")
    ids, uv, p_src = read_plane_points(points_csv)
    meas = read_measurements_csv(measurements_csv)
    pid = {k: i for i, k in enumerate(ids)}
    for r, (im, m_id) in enumerate(zip(meas.image, meas.id)):
        if m_id not in pid:
            raise CorruptFileError(f"{meas.source}, row {meas.lines[r]}: point id {m_id!r} (image {im!r}) is not in "
                                   f"{p_src}; known ids: {', '.join(ids[:8])}{' ...' if len(ids) > 8 else ''}")
    camera = None
    if camera_path is not None:
        from ..camera import Camera

        camera = Camera.load(camera_path)
    frames, skipped, notes = _decode_frames(images, None if input_unit is None else str(input_unit).upper())
    units = {u for _, _, u, _ in frames}
    frame_unit = "K" if "K" in units else ("counts" if "counts" in units else None)
    if frame_unit == "K" and "counts" in units:
        skipped += [(n, "raw counts: the mosaic is made of the kelvin frames (units are never mixed)")
                    for n, _, u, _ in frames if u == "counts"]
        frames = [f for f in frames if f[2] == "K"]
    counts = frame_unit == "counts"
    if counts and unit is not None:
        raise InvalidInputError(f"--unit {unit}: the thermal frames are raw counts (no documented conversion); a "
                                "temperature unit cannot be applied. Omit --unit: the mosaic then holds the counts, "
                                "labelled as counts")
    u_t = None if counts else TemperatureUnit(unit or "K")
    # measurements per frame: the image column names the frame with or without its extension
    by_name: dict[str, list[int]] = {}
    for r, im in enumerate(meas.image):
        by_name.setdefault(im, []).append(r)
    matched = set()
    fits, kept, shapes, homs = [], [], [], {}
    for name, arr, u, path in frames:
        keys = [k for k in by_name if k in (name, Path(path).name) or Path(k).stem == name]
        rows = [r for k in keys for r in by_name[k]]
        matched.update(keys)
        if camera is not None and tuple(camera.image_size) != (arr.shape[1], arr.shape[0]):
            skipped.append((name, f"{arr.shape[1]} x {arr.shape[0]} px; --camera is {camera.image_size[0]} x "
                                  f"{camera.image_size[1]} px"))
            continue
        if not rows:
            skipped.append((name, f"no measurements in {meas.source}"))
            continue
        P = uv[[pid[meas.id[r]] for r in rows]]
        X = meas.xy[rows]
        try:
            fit = fit_facade_homography(P, X, camera=camera)
        except (InvalidInputError, np.linalg.LinAlgError) as exc:
            skipped.append((name, f"{len(rows)} point(s): {exc}"))
            continue
        fits.append(fit)
        kept.append((name, arr))
        shapes.append(arr.shape)
        homs[name] = {"points": len(rows), "rms_px": fit.rms_px, "H": fit.H.tolist(),
                      "residuals_px": {meas.id[r]: [float(fit.residuals_px[i, 0]), float(fit.residuals_px[i, 1])]
                                       for i, r in enumerate(rows)}}
    unknown = sorted(set(by_name) - matched)
    if unknown:
        notes.append(f"{meas.source}: measurements of {len(unknown)} image(s) that are not inputs, ignored: "
                     f"{', '.join(unknown[:5])}{' ...' if len(unknown) > 5 else ''}")
    if not fits:
        why = "; ".join(f"{n}: {r}" for n, r in skipped[:8]) or "no input image"
        raise NothingMosaickedError(f"facade: no image could be rectified ({why})")
    if ext is None:
        ext = _footprint_extent(fits, shapes, uv[[pid[i] for i in sorted({meas.id[r] for r in range(len(meas.id))})]])
    if cell_m is None:  # one pixel of the median image on the plane, at the point seen at the image centre
        fp = []
        for fit, (h, w) in zip(fits, shapes):
            c = np.array([[(w - 1) / 2, (h - 1) / 2]])
            if fit.camera is not None:
                c = fit.camera.undistort(c)
            q = np.array([c[0, 0], c[0, 1], 1.0]) @ np.linalg.inv(fit.H).T
            if q[2] != 0:
                sv = float(fit.jacobian_min_sv(q[0] / q[2], q[1] / q[2]))
                if np.isfinite(sv) and sv > 0:
                    fp.append(1.0 / sv)
        cell_m = float(np.median(fp)) if fp else float(max(ext[1] - ext[0], ext[3] - ext[2]) / 1000)
    a0, a1, b0, b1 = ext
    if (a1 - a0) / cell_m * (b1 - b0) / cell_m > 60e6:
        raise InvalidInputError(f"facade: {a1 - a0:.2f} x {b1 - b0:.2f} at {cell_m:g} per cell is over 60 million cells; "
                                "give a larger --cell or an --extent")
    grid = FacadeGrid(a0, a1, b0, b1, cell_m)
    names = [n for n, _ in kept]
    mos = homography_mosaic([a for _, a in kept], fits, grid, names=names, tile_m=tile_m, levelling=levelling)
    if not np.any(mos.source >= 0):
        raise NothingMosaickedError(f"facade: the {len(fits)} rectified image(s) cover no cell of the extent "
                                    f"u {a0:g}..{a1:g}, v {b0:g}..{b1:g} m")
    for n, f in zip(names, fits):
        homs[n]["max_residual_px"] = float(np.max(np.linalg.norm(f.residuals_px, axis=1)))
    head = {"route": "homography", "images": [str(p) for p in images], "plane_points": str(points_csv),
            "plane_measurements": str(measurements_csv), "camera": None if camera_path is None else str(camera_path),
            "plane": {"how": "the facade plane's own coordinates (u along, v up, metres) from " + str(points_csv),
                      "extent": "given (--extent)" if extent is not None else
                      "the images' footprints, clipped to the points' bounding box grown by half its size"},
            "homographies": homs, "input_notes": notes}
    grid_conv = ("row 0 at the top; cell (r, c) centred at u = a0 + (c + 0.5) cell, v = b1 - (r + 0.5) cell "
                 "(u, v: the coordinates of points.csv)")
    return _write_outputs(out_dir, mos, counts, u_t, head, grid_conv, skipped, tile_m)
