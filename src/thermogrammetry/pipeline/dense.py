"""The ``dense`` verb's driver: a survey folder → depth maps per reference image → fused cloud → DSM.

Unit of work: one reference image (rank its partners, match its pairs, fuse its depth maps; the algorithms are
in :mod:`thermogrammetry.dense.fusion`). Work units run on the task runner (:mod:`thermogrammetry.tasks`: in
this process for ``workers`` 0 or 1, on a local dask.distributed cluster for ``workers`` >= 2, or on an existing
scheduler); results are collected in image order, so the cloud and the DSM are identical whichever way they
ran. Points are spilled to per-tile files (in a scratch folder of the run's own, ``.dense.spill-<pid>-<random>``
inside the staging folder: concurrent runs into one OUT never share one, and a killed run's is removed by the next
run once its process is gone); the DSM and the cloud files are then written tile by tile, the spill
files read in chunks (memory bounded by the tile size); worker results are released as soon as they are fetched.

Outputs in ``out`` (one output set, :class:`~thermogrammetry._atomic.OutputSet`: OUT appears complete or not at
all, a user's own files in OUT are kept): ``cloud.las``, ``cloud.ply``, ``dsm.tif`` (COG; band 1 height in m,
nodata NaN, as measured; with ``fill=True`` a band 2 flags cells filled from their nearest neighbour),
``dsm_filled.tif`` (unless ``surface_fill=False``: the DSM's holes filled by
:func:`~thermogrammetry.products.dsm.fill_surface`, band 2 = 1 where interpolated), ``dense.json``, ``report.html``
(:mod:`thermogrammetry.pipeline.product_reports`).

References
----------
M. Khodaei, F. Samadzadegan, F. Dadras Javan, H. Hasani, "3D surface generation from aerial thermal imagery".
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from .._atomic import OutputSet, spill_folder
from ..dense.fusion import POINT_DTYPE, DenseConfig, rank_pairs, reference_points
from ..errors import ConfigError, DataFileError
from ..tasks import open_client, ordered_results
from .frames import SurveyFrames, open_survey

__all__ = ["run_dense"]



def _reference_task(survey_path: str, i: int, config: DenseConfig, skip: tuple[str, ...] = (),
                    dji_sdk: str | None = None):
    sv = open_survey(survey_path, skip, dji_sdk)
    cands = rank_pairs(i, sv.cameras, sv.poses, sv, config)
    pts, info = reference_points(i, sv.cameras, sv.poses, sv, config, pairs=cands)
    depth = info.get("depth_m", float("nan"))
    if np.isfinite(depth):
        cam = sv.cameras[i]
        R, t = sv.poses[i]
        w, h = cam.image_size
        rays = np.asarray(cam.unproject(np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)))
        info["footprint"] = ((rays * depth) @ R + (-R.T @ t))[:, :2].tolist()
    return pts, info


def _in_quad(px, py, quad) -> np.ndarray:
    """Points inside a convex quadrilateral (either orientation)."""
    q = np.asarray(quad, float)
    area2 = sum(q[k, 0] * q[(k + 1) % 4, 1] - q[(k + 1) % 4, 0] * q[k, 1] for k in range(4))
    sgn = 1.0 if area2 >= 0 else -1.0
    inside = np.ones(np.shape(px), bool)
    for k in range(4):
        a, b = q[k], q[(k + 1) % 4]
        inside &= ((b[0] - a[0]) * (py - a[1]) - (b[1] - a[1]) * (px - a[0])) * sgn >= 0
    return inside


def run_dense(survey_dir, out_dir, *, gsd: float | None = None, config: DenseConfig | None = None,
              workers: int = 1, scheduler: str | None = None, fill: bool = False, tile: int = 512,
              on_image=None, dji_sdk: str | None = None, surface_fill: bool = True,
              max_hole_m: float | None = None, cloud_options=None, max_cells: int | None = None) -> dict:
    """Dense cloud and DSM of a survey folder (see the module docstring). Returns the ``dense.json`` dict.

    ``surface_fill``: also write ``dsm_filled.tif`` (holes up to ``max_hole_m`` across filled; default
    :data:`~thermogrammetry.products.dsm.DEFAULT_MAX_HOLE_CELLS` cells). ``cloud_options``: a
    :class:`~thermogrammetry.products.cloud.CloudOptions` (LAZ, LAS version; default LAS 1.4 + PLY).

    ``on_image(done, total)`` is called after each reference image (progress). ``dji_sdk``: DJI's Thermal SDK
    library, for a survey of DJI R-JPEGs decoded as raw counts: the cloud's values are then temperatures read again
    from the R-JPEGs through the SDK (:class:`~thermogrammetry.pipeline.frames.SurveyFrames`).

    Checked before any work (OUT is not created when refused): the workers
    (:func:`~thermogrammetry.tasks.check_workers`), ``cameras.json`` and its frames (:class:`SurveyFrames`: a frame
    that does not decode is skipped by name and listed), ``gsd``, and the DSM's size against ``max_cells``
    (:func:`~thermogrammetry.io.limits.max_cells`) as far as the cameras' extent tells it; the DSM grid is checked
    again once the points give its extent.
    """
    from ..reporting import driver_call

    with driver_call(run_dense, locals()):  # the report's command line when called from Python
        return _run_dense(survey_dir, out_dir, gsd, config, workers, scheduler, fill, tile, on_image, dji_sdk,
                          surface_fill, max_hole_m, cloud_options, max_cells)


def _run_dense(survey_dir, out_dir, gsd, config, workers, scheduler, fill, tile, on_image, dji_sdk, surface_fill,
               max_hole_m, cloud_options, max_cells) -> dict:
    from .._atomic import check_output_apart
    from ..io.limits import check_cells
    from ..tasks import check_workers

    t0 = time.perf_counter()
    check_output_apart(out_dir, [("survey folder", survey_dir)])
    cfg = config or DenseConfig()
    check_workers(workers, scheduler)
    sv = SurveyFrames(survey_dir, dji_sdk=dji_sdk, need=3, verb="dense")
    if gsd is not None and not (np.isfinite(gsd) and gsd > 0):
        raise ConfigError(f"--gsd {gsd!r}: expected a positive ground sampling distance in metres")
    if max_hole_m is not None and not (np.isfinite(max_hole_m) and max_hole_m >= 0):
        raise ConfigError(f"--fill-max-hole {max_hole_m!r}: expected a hole size in metres >= 0")
    if gsd is not None:  # the DSM covers at least the camera centres' extent: refuse a grid above the cap now
        C = np.array([im.center for im in sv.images])
        span = C[:, :2].max(axis=0) - C[:, :2].min(axis=0)
        check_cells(int(np.ceil(span[0] / gsd)) + 1, int(np.ceil(span[1] / gsd)) + 1,
                    f"DSM of {survey_dir} at --gsd {gsd:g} m (at least the cameras' extent, {span[0]:.1f} x {span[1]:.1f} m)",
                    cap=max_cells, what="DSM")
    fill_opts = (surface_fill, max_hole_m, cloud_options)
    with OutputSet(out_dir, "dense", obsolete=(".dense_tiles",)) as stage:  # the fixed-name spill of older versions
        report = _write_dense(Path(stage.stage), sv, survey_dir, gsd, cfg, workers, scheduler, fill, tile, on_image, t0,
                              fill_opts, max_cells)
        stage.commit({"seconds": report["seconds"]})
    return report


def _write_dense(out: Path, sv: SurveyFrames, survey_dir, gsd, cfg: DenseConfig, workers, scheduler, fill: bool,
                 tile: int, on_image, t0: float, fill_opts=(True, None, None), max_cells: int | None = None) -> dict:
    """The cloud, the DSM and ``dense.json`` of :func:`run_dense`, written into the staging folder ``out``."""
    from .._atomic import write_atomic_text
    from ..products.cloud import CloudWriter, value_dimension
    from ..products.dsm import TileSpill, fill_holes, grid_median, height_tags, write_filled_dsm
    from ..products.qml import robust_limits
    from ..products.raster import Grid
    from ..products.raster import write_cog

    from ..io.limits import check_cells

    n = len(sv)
    skip = tuple(name for name, _ in sv.skipped)
    client = open_client(workers, scheduler)
    infos: list[dict] = []
    spill = None
    try:
        path = str(Path(survey_dir).resolve())
        if client is not None:
            it = ordered_results(client, _reference_task, [path] * n, list(range(n)), [cfg] * n, [skip] * n,
                                 [sv.dji_sdk] * n)
        else:
            it = (_reference_task(path, i, cfg, skip, sv.dji_sdk) for i in range(n))
        # the DSM gsd needs the image GSD: collect the first results before spilling
        pending = []
        for i, (pts, info) in enumerate(it):
            infos.append(info)
            if spill is None:
                pending.append(pts)
                depths = [x["depth_m"] for x in infos if np.isfinite(x.get("depth_m", np.nan))]
                if depths and (len(pending) >= min(n, 3) or i == n - 1):
                    f_px = float(np.mean([c.K[0, 0] for c in sv.cameras]))
                    image_gsd = float(np.median(depths)) / f_px
                    gsd = float(gsd) if gsd is not None else float(np.round(2.0 * image_gsd, 3))
                    spill = TileSpill(spill_folder(out, "dense"), POINT_DTYPE, gsd, tile)  # a name of this run's own
                    for p in pending:
                        spill.append(p)
                    pending = []
            else:
                spill.append(pts)
            if on_image:
                on_image(i + 1, n)
    finally:
        if client is not None:
            client.close()
    if spill is None or spill.count == 0:
        raise DataFileError(f"{survey_dir}: dense matching produced no consistent points (no image had ≥ "
                            f"{cfg.min_consistent} usable partners); check overlap and orientation")
    feet = [x["footprint"] for x in infos if "footprint" in x]
    # extent: the points' box clipped to the images' footprints (stray points far outside are not gridded)
    fx = np.array([p for q in feet for p in q])
    xmin, ymin, xmax, ymax = spill.bbox
    if len(fx):
        xmin, ymin = max(xmin, fx[:, 0].min()), max(ymin, fx[:, 1].min())
        xmax, ymax = min(xmax, fx[:, 0].max()), min(ymax, fx[:, 1].max())
    check_cells(int(np.ceil((xmax - xmin) / spill.gsd)) + 1, int(np.ceil((ymax - ymin) / spill.gsd)) + 1,
                f"DSM of {survey_dir} at {spill.gsd:g} m ({xmax - xmin:.1f} x {ymax - ymin:.1f} m)", cap=max_cells, what="DSM")
    grid = Grid.covering(xmin, ymin, xmax, ymax, spill.gsd, tile)
    offset = (0.5 * (xmin + xmax), 0.5 * (ymin + ymax), 0.0)
    surface_fill, max_hole_m, cloud_options = fill_opts
    # the colour/intensity limits: 2nd and 98th percentiles of every 16th point's value (one read of the spill)
    sample = [c["value"][::16] for key in sorted(spill.keys) for c in spill.iter_chunks(key)]
    limits = robust_limits(np.concatenate(sample).astype(np.float64)) if sample else (0.0, 1.0)
    cw = CloudWriter(out / "cloud.las", out / "cloud.ply", unit=sv.unit, crs=sv.crs, offset_xyz=offset,
                     options=cloud_options, value_limits=limits)
    stats = {"valid": 0, "covered": 0, "valid_covered": 0, "filled": 0}

    def dsm_tile(r0, c0, rows, cols):
        x, y, zp = spill.window_xyz(grid, r0, c0, rows, cols)
        z = grid_median(x, y, zp, grid, r0, c0, rows, cols)
        del x, y, zp
        X, Y = grid.cell_centres(r0, c0, rows, cols)
        cover = np.zeros((rows, cols), np.int32)
        for q in feet:
            cover += _in_quad(X, Y, q)
        covered = cover >= 1 + cfg.min_consistent
        ok = np.isfinite(z)
        stats["valid"] += int(ok.sum())
        stats["covered"] += int(covered.sum())
        stats["valid_covered"] += int((ok & covered).sum())
        if fill:
            zf, m = fill_holes(z, max_distance_px=8)
            zf = np.where(covered, zf, z)
            m = np.where(covered, m, 0)
            stats["filled"] += int(m.sum())
            return np.stack([zf, m.astype(float)]).astype(np.float32)
        return z.astype(np.float32)

    try:
        for key in sorted(spill.keys):
            for chunk in spill.iter_chunks(key):  # arrival order, as one read of the tile
                cw.write(chunk)
        write_cog(out / "dsm.tif", grid, np.float32, dsm_tile, crs=sv.crs, nodata=float("nan"), unit="m",
                  bands=2 if fill else 1,
                  description=["height (m), median of the dense points per cell", "1 = filled (not measured)"]
                  if fill else "height (m), median of the dense points per cell",
                  tags={"product": "thermogrammetry dense DSM", "gsd_m": grid.gsd, **height_tags(sv.crs)})
        cw.close()
    except BaseException:
        cw.abort()
        raise
    finally:
        spill.cleanup()
    if stats["valid"] == 0:
        raise DataFileError(f"{survey_dir}: the {int(cw.count)} dense point(s) fill no cell of the {grid.width}x{grid.height} "
                            f"DSM at {grid.gsd:g} m; expected points inside the images' footprints")
    filled = write_filled_dsm(out / "dsm.tif", out / "dsm_filled.tif", max_hole_m, sv.crs) if surface_fill else None
    completeness = stats["valid_covered"] / max(1, stats["covered"])
    notes = []
    if sv.skipped:
        notes.append(f"{len(sv.skipped)} frame(s) skipped (damaged or unreadable): "
                     + "; ".join(f"{name}: {why}" for name, why in sv.skipped))
    if sv.unit == "dn":
        notes.append("frames are display numbers of an 8-bit rendering: the cloud carries geometry only, no temperature")
    if sv.unit == "counts":
        notes.append("frames are raw sensor counts: the cloud's value dimension is raw_counts, not a temperature")
    report = {
        "points": int(cw.count),
        "gsd_m": grid.gsd,
        "completeness": round(float(completeness), 4),
        "seconds": round(time.perf_counter() - t0, 2),
        "unit": sv.unit,
        "value_dimension": value_dimension(sv.unit),
        "crs": sv.crs,
        "dsm": {"width": grid.width, "height": grid.height, "x0": grid.x0, "y0": grid.y0, "valid_cells": stats["valid"],
                "filled_cells": stats["filled"] if fill else None, "vertical": height_tags(sv.crs)},
        "dsm_filled": filled,
        "cloud_files": cw.files,
        "cloud_offset": list(cw.ply_offset),
        "cloud_colour": {"palette": "thermal (as ortho.qml)", "value_limits": list(limits),
                         "intensity": "round(65535 * (value - lo) / (hi - lo)), clipped to 0..65535",
                         "las_version": cw.options.las_version, "point_format": cw.header.point_format.id},
        "completeness_definition": "share of DSM cells inside >= min_consistent + 1 (default 3) image footprints (at each image's matched depth) "
                                   "that hold a measured height",
        "images": sv.names,
        "skipped_frames": [{"name": name, "reason": why} for name, why in sv.skipped],
        "pairs": infos,
        "config": {k: getattr(cfg, k) for k in cfg.__dataclass_fields__},
        "workers": int(workers) if not scheduler else None,
        "scheduler": scheduler,
        "notes": notes,
        "dji_sdk": sv.dji_sdk,
    }
    write_atomic_text(out / "dense.json", json.dumps(report, indent=1, default=float) + "\n")
    from .product_reports import dense_report_html

    write_atomic_text(out / "report.html", dense_report_html(out, report, sv, survey_dir))
    return report
