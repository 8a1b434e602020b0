"""``facade`` workflow: thermal orthoimage of a flat facade from an oriented survey, without a mesh (seed 002).

Reads a survey folder (``cameras.json`` + frames) through :class:`~thermogrammetry.io.oriented.OrientedCameras`,
puts the facade plane in object space (given, or fitted to the survey's sparse cloud), and calls
:func:`thermogrammetry.products.facade.plane_mosaic` (image choice per tile by resolution on the surface and
distance from the image border, one image per cell, values sampled from it, nothing blended). Writes::

    facade_temperature.tif   float32 in the chosen unit (K or °C), or raw counts labelled as counts; NaN = none
    facade_source.tif        int32 index of the source image (facade.json "index"), -1 = none
    facade_angle.tif         float32 viewing angle of the source image (deg)
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

References
----------
.. [1] Barazzetti, Erba, Previtali, Rosina, Scaioni (2013), seed 002: thermal orthophotos of facades.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import DataFileError, InvalidInputError, TooFewPointsError

__all__ = ["fit_facade_plane", "parse_plane", "run_facade"]

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


def run_facade(survey_dir, out_dir, *, plane: str = "auto", cell_m: float | None = None, unit: str | None = None,
               tile_m: float = 1.0, occluders_path=None) -> dict:
    """The ``facade`` verb as a function; returns the ``facade.json`` content as a dict.

    ``unit``: ``"K"`` or ``"C"`` for kelvin frames (default K); must stay None for frames in raw counts (the
    mosaic then holds counts, labelled as such).
    """
    from ..io.oriented import OrientedCameras
    from ..io.tiff import encode_raster_tiff, encode_temperature_tiff
    from ..products import texture_export as tx
    from ..products.facade import FacadeGrid, plane_mosaic
    from ..radiometry.encoding import TemperatureUnit, from_kelvin
    from .project import FolderProject
    from .texture import check_views_unit, frames_unit, load_views, read_mesh

    if not (cell_m is None or (np.isfinite(cell_m) and cell_m > 0)):
        raise InvalidInputError(f"--cell {cell_m!r}: expected a cell size in metres > 0")
    if not (np.isfinite(tile_m) and tile_m > 0):
        raise InvalidInputError(f"--tile {tile_m!r}: expected a tile size in metres > 0")
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
    mos = plane_mosaic(views, pl, grid, occluders=occ, tile_m=tile_m)
    store = FolderProject(out_dir)
    vals = mos.temperature_k.astype(np.float32) if counts else from_kelvin(mos.temperature_k, u_t).astype(np.float32)
    if counts:
        store.write_bytes("facade_temperature.tif", tx.counts_float_tiff_bytes(vals))
    else:
        data, _ = encode_temperature_tiff(mos.temperature_k, unit=u_t.value, encoding="float32")
        store.write_bytes("facade_temperature.tif", data)
    store.write_bytes("facade_source.tif", tx.int32_tiff_bytes(mos.source))
    store.write_bytes("facade_angle.tif", encode_raster_tiff(mos.angle_deg, unit="deg",
                                                             description="viewing angle of the source image (deg); NaN = none"))
    store.write_bytes("facade_resolution.tif", encode_raster_tiff(mos.resolution_px_per_m, unit="px/m",
                                                                  description="resolution of the source image on the facade"))
    unit_out = "counts" if counts else u_t.value
    store.write_bytes("facade.png", _preview_png(vals, unit_out))
    filled = int((mos.source >= 0).sum())
    used = sorted({int(s) for s in np.unique(mos.source) if s >= 0})
    out = {"format": "thermogrammetry/facade", "version": 1, "survey": str(survey_dir), "unit": unit_out,
           "quantity": "raw_counts" if counts else "temperature",
           "plane": {"origin": list(map(float, pl.origin)), "u": list(map(float, pl.u)), "v": list(map(float, pl.v)),
                     "normal": pl.normal.tolist(), "how": how},
           "grid": {"a0": a0, "a1": a1, "b0": b0, "b1": b1, "cell": cell_m, "shape": list(grid.shape),
                    "convention": "row 0 at the top; cell (r, c) centred at a = a0 + (c + 0.5) cell, "
                                  "b = b1 - (r + 0.5) cell; X = origin + a u + b v"},
           "cells_total": int(mos.source.size), "cells_filled": filled,
           "index": {str(k): n for k, n in enumerate(mos.names)}, "images_used": len(used),
           "skipped": [{"image": n, "reason": r} for n, r in skipped],
           "tile": tile_m, "notes": mos.notes,
           "values": "each cell's value is sampled (bilinear) from one image, chosen per tile; nothing blended or filled"}
    store.write_text("facade.json", json.dumps(out, indent=1))
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
