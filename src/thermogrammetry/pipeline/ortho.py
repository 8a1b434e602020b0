"""The ``ortho`` verb's driver: a survey folder + its DSM file → the true orthophoto and its companion rasters.

The algorithms (visibility, image choice, sampling, the 16-bit encoding, the gradient) are in
:mod:`thermogrammetry.products.ortho` and take arrays; this module knows the files: it reads the survey
folder (:class:`~thermogrammetry.pipeline.frames.SurveyFrames`) and the DSM GeoTIFF, runs one task per tile on
the task runner (:mod:`thermogrammetry.tasks`), and writes the rasters, ``ortho.json`` and ``report.html``
(:mod:`thermogrammetry.pipeline.product_reports`) as one output set
(:class:`~thermogrammetry._atomic.OutputSet`: OUT appears complete or not at all; a user's own files in OUT
are kept). The method is described in :mod:`thermogrammetry.products.ortho`.

References
----------
L. Barazzetti, S. Erba, M. Previtali, E. Rosina, M. Scaioni, "Mosaicking thermal images of buildings",
Proc. SPIE, 2013 (temperature-preserving mosaics, invertible 16-bit encoding, gradient analysis).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from .._atomic import OutputSet, write_atomic_text
from ..products.ortho import (SCORE_DOC, OrthoConfig, bilinear, gradient, occluder_subdivision, occluders, ortho_tile,
                              project_world, surface_normals)
from ..products.raster import Grid, read_window
from ..tasks import open_client, ordered_results
from .frames import SurveyFrames, open_survey

__all__ = ["run_ortho", "check_dsm_matches_survey"]



def _ortho_task(survey_path: str, dsm_path: str, grid: Grid, window, cfg: OrthoConfig, margin_m: float,
                correction=None, unit_out: str = "K", dji_sdk: str | None = None, filled_band: int | None = None,
                dsm_grid: Grid | None = None, skip: tuple[str, ...] = (), sigma: dict | None = None,
                zmid: float | None = None):
    sv = open_survey(survey_path, skip, dji_sdk)
    r0, c0, rows, cols = window
    # ortho cells (with a one-cell pad for the normals) and their DSM heights
    X, Y = grid.cell_centres(r0 - 1, c0 - 1, rows + 2, cols + 2)
    dg = dsm_grid if dsm_grid is not None else _dsm_meta(dsm_path)["grid"]
    pad = int(np.ceil(margin_m / dg.gsd)) + 2
    xa, xb = X.min(), X.max()
    ya, yb = Y.min(), Y.max()
    dc0 = int(np.floor((xa - dg.x0) / dg.gsd)) - pad
    dr0 = int(np.floor((dg.y0 - yb) / dg.gsd)) - pad
    dc1 = int(np.ceil((xb - dg.x0) / dg.gsd)) + pad
    dr1 = int(np.ceil((dg.y0 - ya) / dg.gsd)) + pad
    D = read_window(dsm_path, dr0, dc0, dr1 - dr0, dc1 - dc0)
    Z = bilinear(D, (dg.y0 - Y) / dg.gsd - 0.5 - dr0, (X - dg.x0) / dg.gsd - 0.5 - dc0)
    filled = None
    if filled_band:  # a cell whose height leans on an interpolated DSM cell (any bilinear weight on one)
        F = np.nan_to_num(read_window(dsm_path, dr0, dc0, dr1 - dr0, dc1 - dc0, band=filled_band), nan=0.0)
        filled = bilinear(F, (dg.y0 - Y) / dg.gsd - 0.5 - dr0, (X - dg.x0) / dg.gsd - 0.5 - dc0)[1:-1, 1:-1] > 0
    nrm = surface_normals(Z, grid.gsd)  # Horn's 3 x 3 slope; border of the surface: horizontal
    X, Y, Z, nrm = X[1:-1, 1:-1], Y[1:-1, 1:-1], Z[1:-1, 1:-1], nrm[1:-1, 1:-1]
    # candidate images: the tile's box (at the DSM's height range) projects into the frame
    images = []
    cell_px = 0.0  # largest projected DSM cell (px) among the candidates
    if np.isfinite(Z).any():
        zlo, zhi = np.nanmin(Z), np.nanmax(Z)
        corners = np.array([[x, y, z] for x in (xa, xb) for y in (ya, yb) for z in (zlo, zhi)])
        for k in range(len(sv)):
            cam, (R, t) = sv.cameras[k], sv.poses[k]
            uv, z = project_world(cam, R, t, corners)
            if not (z > 0).all() or not np.isfinite(uv).all():
                continue
            W, H = cam.image_size
            if uv[:, 0].max() < -0.5 or uv[:, 0].min() > W - 0.5 or uv[:, 1].max() < -0.5 or uv[:, 1].min() > H - 0.5:
                continue
            images.append((k, cam, R, t))
            cell_px = max(cell_px, dg.gsd * max(cam.K[0, 0], cam.K[1, 1]) / float(z.min()))
    # between the centres only at height steps: a square spanning less than half the smallest visibility
    # tolerance is represented by its corners to within that (its points hide no cell its corners do not)
    tol_min = cfg.tolerance_m if cfg.tolerance_m is not None else 4 * grid.gsd
    occ = occluders(D, dg, dr0, dc0, occluder_subdivision(cell_px, cfg.bin_px), min_span_m=0.5 * tol_min)
    res = ortho_tile(X, Y, Z, nrm, occ, images, sv, cfg, gsd=grid.gsd, masks=sv.display_mask)
    if zmid is not None and images and not np.isfinite(Z).all():  # no surface height: the footprint at the mid height
        hole = ~np.isfinite(Z)
        P = np.column_stack([X[hole], Y[hole], np.full(int(hole.sum()), float(zmid))])
        seen = np.zeros(len(P), bool)
        for _k, cam, R, t in images:
            uv, z = project_world(cam, R, t, P)
            W, H = cam.image_size
            with np.errstate(invalid="ignore"):
                seen |= (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < H - 0.5)
        res["in_frame"][hole] = seen
    v = res["value"]
    parts = None
    if sigma is not None:  # the σ model (products.ortho_sigma): sensor, geometry, correction
        from ..products.ortho_sigma import correction_sigma, tile_sigma

        parts = tile_sigma(res, X, Y, Z, sv, sv.cameras, sv.poses,
                           lambda k: (sv.images[k].center_std, sv.images[k].rotation_std_deg),
                           str(cfg.sampling), sigma["netd"], sigma["z_std"])
    notes = 0
    if correction is not None:
        from ..products.correction import apply_correction

        on = res["source"] >= 0
        Tc, eps, tau, valid = apply_correction(v, np.radians(res["angle_deg"]), res["distance_m"], on, correction)
        notes = int((on & ~valid).sum())
        if parts is not None:
            dtc, sc = correction_sigma(v, np.radians(res["angle_deg"]), res["distance_m"], on, correction,
                                       sigma["config"], sigma["z_std"])
            parts = np.stack([parts[0] * np.abs(dtc), parts[1] * np.abs(dtc), sc])
        v = np.where(valid, Tc, np.nan)
    if parts is not None:
        parts = np.where(np.isfinite(v), parts, np.nan)
        res["sigma"] = np.concatenate([np.sqrt((parts ** 2).sum(axis=0))[None], parts]).astype(np.float32)
    if unit_out == "C":
        v = v - 273.15
    res["value"] = v.astype(np.float32)
    res["uncorrected"] = notes
    if filled is not None:
        res["filled"] = np.where(np.isfinite(res["value"]), filled.astype(np.uint8), 255).astype(np.uint8)
    return res




def _write_style(out: Path, label: str) -> dict:
    """``ortho.qml`` beside ``ortho.tif``: QGIS's default style of the mosaic (thermal palette between the 2nd and
    98th percentiles of the values, read from a decimated copy, legend in ``label``). Returns its ``ortho.json`` entry."""
    import rasterio

    from ..products.qml import robust_limits, thermal_qml

    with rasterio.open(out / "ortho.tif") as src:
        k = max(1, int(np.ceil(max(src.width, src.height) / 2048)))
        v = src.read(1, out_shape=(max(1, src.height // k), max(1, src.width // k)), masked=True)
    lo, hi = robust_limits(np.asarray(v.astype(np.float64).filled(np.nan)))
    write_atomic_text(out / "ortho.qml", thermal_qml(lo, hi, label))
    return {"file": "ortho.qml", "min": lo, "max": hi, "unit": label, "limits": "2nd and 98th percentiles of the values"}


def _sigma_report(rec: dict, kept: list) -> dict:
    """``ortho.json``'s ``sigma``: the model's inputs and the figures of ``ortho_sigma.tif``."""
    from ..products.ortho_sigma import summarise

    vals = np.concatenate(kept, axis=1) if kept else np.zeros((4, 0), np.float32)
    return {"file": "ortho_sigma.tif", "bands": ["total random", "sensor", "geometry", "correction"],
            **rec, **summarise(vals.astype(np.float64))}


_DSM_META: dict = {}


def _dsm_meta(path):
    key = str(path)
    if key not in _DSM_META:
        import rasterio

        with rasterio.open(path) as src:
            tr = src.transform
            g = Grid(tr.c, tr.f, tr.a, src.width, src.height)
            ov = src.read(1, out_shape=(max(1, src.height // 8), max(1, src.width // 8)), masked=True)
            crs = src.crs.to_string() if src.crs else None
        vals = np.asarray(ov.astype(float).filled(np.nan))
        _DSM_META.clear()
        _DSM_META[key] = {"grid": g, "crs": crs, "zmin": float(np.nanmin(vals)) if np.isfinite(vals).any() else 0.0,
                          "zmax": float(np.nanmax(vals)) if np.isfinite(vals).any() else 0.0}
    return _DSM_META[key]


def check_dsm_matches_survey(meta: dict, sv, dsm_path, survey_dir) -> None:
    """Raise :class:`~thermogrammetry.errors.ConfigError` when the DSM cannot belong to the survey: another
    horizontal CRS than ``cameras.json``'s (or a CRS on one side only), heights above every camera, or an extent
    that no camera can see (the ground within ``max(200 m, 5 × flying height above the DSM)`` of a camera centre,
    i.e. up to ~79° off nadir). ``meta``: ``grid``, ``crs``, ``zmin`` (and ``zmax``) of the DSM."""
    from ..errors import ConfigError
    from ..products.raster import same_horizontal_crs

    a, b = meta.get("crs"), sv.crs
    cams = sv.root / "cameras.json"
    if a is None and b is not None:
        raise ConfigError(f"{dsm_path}: the DSM has no CRS, the survey {cams} is in {b}; expected the DSM in the "
                          f"survey's CRS (assign it if that is what it is: gdal_edit.py -a_srs {b})")
    if a is not None and b is None:
        raise ConfigError(f"{dsm_path}: the DSM is in {a}, the survey {cams} has no CRS (a local frame); expected a DSM "
                          "in the survey's local frame (as 'thermogrammetry dense' writes it, without a CRS)")
    if not same_horizontal_crs(a, b):
        raise ConfigError(f"{dsm_path}: the DSM is in {a}, the survey {survey_dir} in {b}; expected the DSM in the "
                          f"survey's CRS (reproject it first, e.g. gdalwarp -t_srs {b})")
    g = meta["grid"]
    dx0, dx1 = g.x0, g.x0 + g.width * g.gsd
    dy0, dy1 = g.y0 - g.height * g.gsd, g.y0
    C = np.array([im.center for im in sv.images])
    top = float(np.max(C[:, 2]))
    if float(meta["zmin"]) >= top:
        raise ConfigError(f"{dsm_path}: every height of the DSM ({float(meta['zmin']):.2f}..{float(meta.get('zmax', meta['zmin'])):.2f} m) "
                          f"is at or above the highest camera of {survey_dir} (Z {top:.2f} m); expected the ground below "
                          "the cameras (a DSM of another height reference or unit?)")
    height = max(0.0, float(np.max(C[:, 2])) - float(meta["zmin"]))
    reach = max(200.0, 5.0 * height)
    cx0, cy0 = C[:, :2].min(axis=0) - reach
    cx1, cy1 = C[:, :2].max(axis=0) + reach
    if dx1 < cx0 or dx0 > cx1 or dy1 < cy0 or dy0 > cy1:
        raise ConfigError(f"{dsm_path}: the DSM covers X {dx0:.2f}..{dx1:.2f}, Y {dy0:.2f}..{dy1:.2f} m, which no camera of "
                          f"{survey_dir} sees (camera centres X {C[:, 0].min():.2f}..{C[:, 0].max():.2f}, Y "
                          f"{C[:, 1].min():.2f}..{C[:, 1].max():.2f} m, crs {b or 'local frame'}); expected a DSM of the "
                          "surveyed area in the survey's coordinates")


def footprints_box(sv, z: float, samples: int = 9):
    """(xmin, ymin, xmax, ymax): the box of the images' footprints on the horizontal plane at height ``z`` (m), each
    frame's border (``samples`` points per edge) cast from its camera; rays that do not reach the plane (above the
    horizon) are left out. None when no ray reaches it."""
    pts = []
    for k in range(len(sv)):
        cam, (R, t) = sv.cameras[k], sv.poses[k]
        w, h = cam.image_size
        s = np.linspace(0.0, 1.0, samples)
        border = np.concatenate([np.column_stack([s * (w - 1), np.zeros_like(s)]),
                                 np.column_stack([np.full_like(s, w - 1), s * (h - 1)]),
                                 np.column_stack([s * (w - 1), np.full_like(s, h - 1)]),
                                 np.column_stack([np.zeros_like(s), s * (h - 1)])])
        d = np.asarray(cam.unproject(border), float) @ np.asarray(R, float)  # world directions (rows)
        C = -np.asarray(R, float).T @ np.asarray(t, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (float(z) - C[2]) / d[:, 2]
        ok = np.isfinite(lam) & (lam > 0)
        pts.append(C[None, :2] + lam[ok, None] * d[ok, :2])
    P = np.concatenate(pts) if pts else np.zeros((0, 2))
    if not len(P):
        return None
    return float(P[:, 0].min()), float(P[:, 1].min()), float(P[:, 0].max()), float(P[:, 1].max())


def run_ortho(survey_dir, dsm_path, out_dir, *, gsd: float | None = None, unit: str | None = None,
              sampling: str = "nearest", correct: bool = False, correction=None, workers: int = 1,
              scheduler: str | None = None, tile: int = 512, config: OrthoConfig | None = None, on_tile=None,
              dji_sdk: str | None = None, fill: bool = True, max_hole_m: float | None = None,
              max_cells: int | None = None, sigma=True) -> dict:
    """``thermogrammetry ortho``: the mosaic and its companion rasters in ``out_dir``; returns ``ortho.json``.

    ``fill`` (default): the mosaic's surface is the DSM with its holes filled
    (:func:`~thermogrammetry.products.dsm.fill_surface`, holes up to ``max_hole_m`` across, default
    :data:`~thermogrammetry.products.dsm.DEFAULT_MAX_HOLE_CELLS` DSM cells); the cells on filled heights are
    flagged in ``ortho_filled_mask.tif`` and counted in ``ortho.json``. ``fill=False``: the DSM as given.

    ``on_tile(done, total)`` is called after each mosaic tile (progress). ``dji_sdk``: DJI's Thermal SDK library,
    for a survey of DJI R-JPEGs decoded as raw counts: the mosaic then holds temperatures read again from the
    R-JPEGs through the SDK (:class:`~thermogrammetry.pipeline.frames.SurveyFrames`).

    Every input is checked before any work (OUT is not created when one is refused): the workers
    (:func:`~thermogrammetry.tasks.check_workers`), ``cameras.json`` and its frames (:class:`SurveyFrames`; a frame
    that does not decode is skipped by name), the DSM (:func:`~thermogrammetry.products.raster.inspect_raster`,
    :func:`check_dsm_matches_survey`) and the size of the ortho grid (``max_cells``, default
    :func:`~thermogrammetry.io.limits.max_cells`). A mosaic without any cell is refused with its reason.

    ``sigma``: ``ortho_sigma.tif`` with the σ model of :mod:`thermogrammetry.products.ortho_sigma` (True, or a
    :class:`~thermogrammetry.products.ortho_sigma.SigmaConfig`); False: not written.
    """
    from ..reporting import driver_call

    with driver_call(run_ortho, locals()):  # the report's command line when called from Python
        return _run_ortho(survey_dir, dsm_path, out_dir, gsd, unit, sampling, correct, correction, workers, scheduler,
                          tile, config, on_tile, dji_sdk, fill, max_hole_m, max_cells, sigma)


def _run_ortho(survey_dir, dsm_path, out_dir, gsd, unit, sampling, correct, correction, workers, scheduler, tile,
               config, on_tile, dji_sdk, fill, max_hole_m, max_cells, sigma) -> dict:
    from ..errors import ConfigError, DataFileError
    from ..io.limits import check_cells
    from ..products.correction import as_correction_config
    from ..products.raster import inspect_raster
    from .._atomic import check_output_apart
    from ..tasks import check_workers

    t0 = time.perf_counter()
    check_output_apart(out_dir, [("survey folder", survey_dir)])
    check_workers(workers, scheduler)
    sv = SurveyFrames(survey_dir, dji_sdk=dji_sdk, need=1, verb="ortho")
    if not Path(dsm_path).exists():
        raise DataFileError(f"{dsm_path}: no such DSM; expected the dsm.tif written by 'thermogrammetry dense'")
    info = inspect_raster(dsm_path, "DSM", max_cells=max_cells)
    meta = {"grid": info.grid, "crs": info.crs, "zmin": info.zmin, "zmax": info.zmax}
    check_dsm_matches_survey(meta, sv, dsm_path, survey_dir)
    cfg = config or OrthoConfig(sampling=sampling)
    notes = []
    if sv.unit == "K":
        unit_out = (unit or "K").upper().lstrip("°")
        if unit_out not in ("K", "C"):
            raise ConfigError(f"--unit {unit!r}: expected K or C")
        label = "K" if unit_out == "K" else "°C"
        if unit_out == "C":
            notes.append("values converted to °C (value − 273.15 in float32): equal to the source within float32 "
                         "rounding, not bit-exact; use --unit K for bit-exact copies")
    else:
        if unit not in (None, sv.unit):
            raise ConfigError(f"--unit {unit}: the frames of {survey_dir} are {sv.unit!r} "
                              f"({'raw sensor counts' if sv.unit == 'counts' else 'display numbers'}), not temperatures; "
                              "omit --unit")
        unit_out = sv.unit
        label = "counts" if sv.unit == "counts" else "dn"
        notes.append("frames are raw sensor counts: the mosaic holds counts, not temperatures (labelled 'counts')"
                     if sv.unit == "counts" else
                     "frames are display numbers of an 8-bit rendering: geometry-only product, no temperature")
        if sv.display_mask(0) is not None:
            notes.append("a camera display burned into the frames (found by survey: work/overlay.json): its pixels "
                         "are never a source, the cells take their value from another image")
        if correct:
            raise ConfigError("--correct needs temperature frames (unit K); these frames are "
                              f"{sv.unit!r}")
    corr = as_correction_config(correction) if correct else None
    g = gsd if gsd is not None else meta["grid"].gsd
    if not (np.isfinite(g) and g > 0):
        raise ConfigError(f"--gsd {gsd!r}: expected a positive cell size in metres")
    if max_hole_m is not None and not (np.isfinite(max_hole_m) and max_hole_m >= 0):
        raise ConfigError(f"--fill-max-hole {max_hole_m!r}: expected a hole size in metres >= 0")
    dg = meta["grid"]
    gw, gh = int(np.ceil(dg.width * dg.gsd / g)), int(np.ceil(dg.height * dg.gsd / g))
    if min(gw, gh) < 2:  # a cell larger than the DSM: no mosaic (and its one-cell pad would read a window of that size)
        raise ConfigError(f"--gsd {float(g):g} m: the DSM {dsm_path} covers {dg.width * dg.gsd:.4g} x "
                          f"{dg.height * dg.gsd:.4g} m, an ortho grid of {gw} x {gh} cell(s) at that size; expected a "
                          f"cell size giving at least 2 x 2 cells (at most {min(dg.width, dg.height) * dg.gsd / 2:.4g} m)")
    what = f"ortho grid of {dsm_path} at {float(g):g} m" + (" (--gsd)" if gsd is not None else "")
    check_cells(gw, gh, what, cap=max_cells, what="mosaic")
    if fill:
        # the surface (and so the mosaic) reaches beyond the DSM's box into the images' footprints, as far as the
        # fill can give heights (a gap beyond the data's outer edge: up to the largest hole from the rim): a DSM cut
        # to its points' box leaves out the edges of the block that the frames see
        from ..products.dsm import DEFAULT_MAX_HOLE_CELLS, extended_grid

        max_px = DEFAULT_MAX_HOLE_CELLS if max_hole_m is None else float(max_hole_m) / dg.gsd
        box = footprints_box(sv, meta["zmin"])
        if box is not None:
            dg = extended_grid(dg, box, int(np.floor(max_px)))
            check_cells(dg.width, dg.height, f"surface of {dsm_path} grown into the images' footprints", cap=max_cells,
                        what="DSM")
            gw, gh = int(np.ceil(dg.width * dg.gsd / g)), int(np.ceil(dg.height * dg.gsd / g))
            check_cells(gw, gh, what + ", grown into the images' footprints", cap=max_cells, what="mosaic")
        meta = {**meta, "surface_grid": dg}
    grid = Grid(dg.x0, dg.y0, float(g), gw, gh, tile)
    if not 0.0 < float(cfg.max_angle_deg) < 90.0:
        raise ConfigError(f"--max-angle {cfg.max_angle_deg!r}: expected a viewing angle in degrees between 0 and 90")
    margin_m = min(50.0, (meta["zmax"] - meta["zmin"]) * np.tan(np.radians(cfg.max_angle_deg)))
    with OutputSet(out_dir, "ortho") as stage:
        report = _write_ortho(Path(stage.stage), sv, grid, meta, cfg, margin_m, corr, unit_out, label, notes, correct,
                              survey_dir, dsm_path, workers, scheduler, t0, on_tile, (bool(fill), max_hole_m),
                              sigma_cfg=False if sigma is False else (None if sigma is True else sigma))
        stage.commit({"seconds": report["seconds"]})
    return report


def _write_ortho(out: Path, sv, grid, meta, cfg, margin_m, corr, unit_out, label, notes, correct, survey_dir, dsm_path,
                 workers, scheduler, t0, on_tile=None, fill_opts=(True, None), sigma_cfg=False) -> dict:
    """The rasters and ``ortho.json`` of :func:`run_ortho`, written into the staging folder ``out``."""
    from ..products.dsm import write_filled_dsm
    from ..radiometry.encoding import choose_uint16_mapping, encode_uint16
    from ..products.raster import RasterSpec, read_window, write_cogs

    spath = str(Path(survey_dir).resolve())
    dpath = str(Path(dsm_path).resolve())
    surface = out / ".ortho_surface.tif"  # the filled DSM the tiles read (removed once the mosaic is written)
    fill_rec, band, sig, sig_rec = None, None, None, None
    if sigma_cfg is not False:
        from ..products.ortho_sigma import prepare_sigma

        sig, sig_rec = prepare_sigma(sv, dpath, sigma_cfg, label)
        sig_keep = []
        sig_stride = max(1, grid.width * grid.height // 4_000_000)
    dg = meta.get("surface_grid", meta["grid"])  # the grid of the surface the tiles read
    if fill_opts[0]:
        fill_rec = write_filled_dsm(dpath, surface, fill_opts[1], sv.crs, grid=dg)
        fill_rec.pop("file")
        dpath, band = str(surface.resolve()), 2
    client = open_client(workers, scheduler)
    windows = list(grid.tiles())
    zmid = 0.5 * (float(meta["zmin"]) + float(meta["zmax"]))  # where the surface has no height (for the footprint)
    skip = tuple(n for n, _ in sv.skipped)
    stats = {"lo": np.inf, "hi": -np.inf, "cells": 0, "uncorrected": 0, "filled": 0}
    sources: set = set()

    def collect(res):
        v = res["value"]
        if np.isfinite(v).any():
            stats["lo"] = min(stats["lo"], float(np.nanmin(v)))
            stats["hi"] = max(stats["hi"], float(np.nanmax(v)))
        stats["cells"] += int(np.isfinite(v).sum())
        stats["uncorrected"] += res["uncorrected"]
        stats["in_frame"] = stats.get("in_frame", 0) + int(res["in_frame"].sum())
        stats["in_frame_covered"] = stats.get("in_frame_covered", 0) + int((res["in_frame"] & np.isfinite(v)).sum())
        sources.update(int(s) for s in np.unique(res["source"]) if s >= 0)
        stats["tiles"] = stats.get("tiles", 0) + 1
        if on_tile:
            on_tile(stats["tiles"], len(windows))
        got = {"value": v, "source": np.stack([res["source"], res["row"], res["col"]]), "angle": res["angle_deg"].astype(np.float32),
               "distance": res["distance_m"].astype(np.float32)}
        if sig is not None:
            got["sigma"] = res["sigma"]
            s4 = res["sigma"].reshape(4, -1)
            sig_keep.append(s4[:, np.isfinite(s4[0])][:, ::sig_stride])
        if band:
            got["filled"] = res["filled"]
            stats["filled"] += int((res["filled"] == 1).sum())
        return got

    try:
        if client is not None:
            nt = len(windows)
            tiles = (collect(r) for r in ordered_results(client, _ortho_task, [spath] * nt, [dpath] * nt, [grid] * nt,
                                                         windows, [cfg] * nt, [margin_m] * nt, [corr] * nt,
                                                         [unit_out] * nt, [sv.dji_sdk] * nt, [band] * nt, [dg] * nt,
                                                         [skip] * nt, [sig] * nt, [zmid] * nt))
        else:
            tiles = (collect(_ortho_task(spath, dpath, grid, w, cfg, margin_m, corr, unit_out, sv.dji_sdk, band, dg, skip,
                                         sig, zmid))
                     for w in windows)
        crs = sv.crs
        specs = {
            "value": RasterSpec(out / "ortho.tif", np.float32, nodata=float("nan"), unit=label,
                                description=("temperature" if sv.unit == "K" else
                                             "raw sensor counts (not a temperature)" if sv.unit == "counts" else
                                             "display numbers (not a temperature)") + f" [{label}]",
                                tags={"product": "thermogrammetry ortho", "unit": label}),
            "source": RasterSpec(out / "ortho_source.tif", np.int32, bands=3, nodata=-1, resampling="nearest",
                                 description=["source image index (lookup table in ortho.json; -1 = none)",
                                              "source pixel row (nearest sampling: the value is frame[row, col])",
                                              "source pixel column"]),
            "angle": RasterSpec(out / "ortho_angle.tif", np.float32, nodata=float("nan"), unit="deg",
                                description="viewing angle to the DSM normal (deg)"),
            "distance": RasterSpec(out / "ortho_distance.tif", np.float32, nodata=float("nan"), unit="m",
                                   description="camera-to-surface distance (m)"),
        }
        if sig is not None:
            specs["sigma"] = RasterSpec(out / "ortho_sigma.tif", np.float32, bands=4, nodata=float("nan"), unit=label,
                                        description=[f"{b} standard deviation [{label}]" for b in
                                                     ("total random", "sensor", "geometry", "correction")],
                                        tags={"product": "thermogrammetry ortho sigma", "unit": label,
                                              "systematic": "unknown",
                                              "systematic_note": sig_rec["systematic_note"],
                                              "netd": f"{sig_rec['netd']:.6g}", "dsm_sigma_m": f"{sig_rec['dsm_sigma_m']:.6g}"})
        if band:
            specs["filled"] = RasterSpec(out / "ortho_filled_mask.tif", np.uint8, nodata=255, resampling="nearest",
                                         description="1 = the cell lies on interpolated DSM heights (a filled hole), "
                                                     "0 = on measured heights; 255 = no value")
        write_cogs(grid, specs, None, crs=crs, tiles=tiles)
    finally:
        if client is not None:
            client.close()
        _DSM_META.clear()
        surface.unlink(missing_ok=True)
    if stats["cells"] == 0:
        from ..errors import DataFileError

        raise DataFileError(f"{dsm_path}: no cell of the {grid.width}x{grid.height} ortho grid is seen by any of the "
                            f"{len(sv)} image(s) of {survey_dir}; expected a DSM of the surveyed ground below the "
                            "cameras (check its heights, extent and CRS)")
    style = _write_style(out, label)
    # 16-bit encoding with one mapping for the whole mosaic
    if np.isfinite(stats["lo"]):
        if sv.unit == "K":
            lo_k = stats["lo"] + (273.15 if unit_out == "C" else 0.0)
            hi_k = stats["hi"] + (273.15 if unit_out == "C" else 0.0)
            mapping = choose_uint16_mapping(np.array([lo_k, hi_k]), unit_out)
            scale, offset = mapping.scale, mapping.offset

            def enc(v):
                return encode_uint16(v + (273.15 if unit_out == "C" else 0.0), mapping)
        else:
            scale, offset = 1.0, 0.0

            def enc(v):
                return np.where(np.isfinite(v), np.clip(v, 1, 65535), 0).astype(np.uint16)
    else:
        scale, offset = 1.0, 0.0

        def enc(v):
            return np.zeros(v.shape, np.uint16)

    def u16_tile(r0, c0, rows, cols):
        v = read_window(out / "ortho.tif", r0, c0, rows, cols)
        return {"u16": enc(v)}

    def grad_tile(r0, c0, rows, cols):
        v = read_window(out / "ortho.tif", r0 - 1, c0 - 1, rows + 2, cols + 2)
        mag, direc = gradient(v, grid.gsd)
        return {"grad": np.stack([mag[1:-1, 1:-1], direc[1:-1, 1:-1]]).astype(np.float32)}

    write_cogs(grid, {"u16": RasterSpec(out / "ortho_u16.tif", np.uint16, nodata=0, unit=label, scale=scale, offset=offset,
                                        description=f"{label} = code * {scale:g} + {offset:g}; 0 = no data",
                                        resampling="average")}, u16_tile, crs=sv.crs)
    write_cogs(grid, {"grad": RasterSpec(out / "ortho_gradient.tif", np.float32, bands=2, nodata=float("nan"),
                                         description=[f"gradient magnitude ({label}/m)",
                                                      "gradient direction (deg clockwise from grid north, uphill)"])},
               grad_tile, crs=sv.crs)
    if stats["uncorrected"]:
        notes.append(f"{stats['uncorrected']} cells left empty by --correct (no valid correction: angle ≥ "
                     f"{corr.max_angle_deg}° or no real solution)")
    if sv.crs is None:
        notes.append("cameras.json has no CRS: rasters are in the survey's local frame (no CRS written)")
    if sv.skipped:
        notes.append(f"{len(sv.skipped)} frame(s) skipped (damaged or unreadable): "
                     + "; ".join(f"{n}: {r}" for n, r in sv.skipped))
    report = {
        "images": {str(k): sv.names[k] for k in range(len(sv))},
        "unit": label,
        "scale": scale,
        "offset": offset,
        "u16_nodata": 0,
        "sampling": str(cfg.sampling),
        "max_angle_deg": float(cfg.max_angle_deg),
        "normals": "Horn's 3 x 3 slope of the surface (Horn 1981); vertical where a neighbour has no height",
        "score": SCORE_DOC,
        "gsd_m": grid.gsd,
        "width": grid.width,
        "height": grid.height,
        "crs": sv.crs,
        "cells": stats["cells"],
        "footprint": {"cells": stats.get("in_frame", 0),
                      "covered": round(stats.get("in_frame_covered", 0) / max(1, stats.get("in_frame", 0)), 4),
                      "definition": "cells of the grid whose surface point projects into at least one frame (where the "
                                    "surface has no height: at the DSM's mid height); covered = the share of them with "
                                    "a value"},
        "images_used": len(sources),
        "skipped_frames": [{"name": n, "reason": r} for n, r in sv.skipped],
        "corrected": bool(correct),
        "correction": None if corr is None else {k: str(getattr(corr, k)) for k in corr.__dataclass_fields__},
        "seconds": round(time.perf_counter() - t0, 2),
        "style": style,
        "overview_resampling": "average (temperature, 16-bit codes, angle, distance, gradient); nearest (source, filled mask)",
        "fill": None if fill_rec is None else {**fill_rec, "ortho_cells_on_filled": stats["filled"],
                                               "mask": "ortho_filled_mask.tif"},
        "dji_sdk": sv.dji_sdk,
        "sigma": None if sig is None else _sigma_report(sig_rec, sig_keep),
        "notes": notes,
    }
    write_atomic_text(out / "ortho.json", json.dumps(report, indent=1) + "\n")
    from .product_reports import ortho_report_html

    write_atomic_text(out / "report.html", ortho_report_html(out, report, sv, survey_dir, dsm_path))
    return report
