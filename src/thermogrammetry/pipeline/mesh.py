"""The ``mesh`` verb's driver: a point cloud (a ``dense`` folder or a scan file) → ``mesh.ply``, ``mesh.obj``, ``mesh.json``.

Memory is bounded by blocks of space, not by the cloud. The cloud is read once in chunks into a scratch folder of
the run's own (``.mesh.spill-<pid>-<random>`` inside the staging folder: raw float64 coordinates and float32
normals on disk, memory-mapped), its scale measured on a few complete neighbourhoods
(:func:`~thermogrammetry.products.mesh.cloud_scale`), the points sorted on disk by the block of the lattice they
fall in, coarse representatives taken block by block and oriented once for the whole cloud, and every block meshed
from the points of its core and margin alone (:func:`~thermogrammetry.products.mesh_surface.mesh_block`); the
blocks run on the task runner (:mod:`thermogrammetry.tasks`: in this process for ``workers`` 0 or 1, on a local
dask cluster for 2 or more, or on ``scheduler``) and are collected in block order, so the mesh is the same however
they ran. What stays in memory across blocks is the block index (16 bytes a point), the representatives and the
mesh being built.

Coordinates: every computation is in float64 relative to a local origin (the cloud's bounding-box centre rounded to
the metre, ``mesh.json`` ``local_origin``); ``mesh.ply`` stores each vertex as doubles in the CRS's coordinates
(origin added back: 0.1 µm resolution at UTM northings), ``mesh.obj`` as decimal text with 4 decimals (0.1 mm).

Outputs (one :class:`~thermogrammetry._atomic.OutputSet`: OUT appears complete or not at all, a user's own files in
OUT are kept): ``mesh.ply`` (binary; face property ``filled``, 1 = made by hole filling), ``mesh.obj``,
``mesh.json`` (:doc:`docs/formats/mesh_json.md`).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from .._atomic import OutputSet, check_output_apart, spill_folder
from ..errors import ConfigError, DataFileError, InvalidInputError, TooFewPointsError
from ..products.mesh import MIN_POINTS, MeshConfig

__all__ = ["run_mesh"]

#: points read and written per chunk
CHUNK = 1_000_000
#: seeds of the neighbourhoods the cloud's scale is measured on, and the points wanted around each
SEEDS, SEED_POINTS = 24, 3000


def run_mesh(source, out_dir, *, crs: str | None = None, config: MeshConfig | None = None, workers: int = 1,
             scheduler: str | None = None, progress=None) -> dict:
    """Mesh a cloud (see the module docstring). Returns the ``mesh.json`` dict.

    ``source``: a ``dense`` output folder or a cloud file (.las .laz .ply .e57 .xyz); ``crs``: ``--crs`` (the CRS of
    a cloud that states none; refused when it contradicts the file's). ``progress(stage, done, total)`` is called as
    the work advances. Checked before any work (OUT is not created when refused): OUT apart from the input, the
    options, the workers, the file's format and CRS; then, after reading, the points (finite, at least
    :data:`~thermogrammetry.products.mesh.MIN_POINTS`).
    """
    from ..io.pointcloud import open_cloud, resolve_crs
    from ..tasks import check_workers

    t0 = time.perf_counter()
    cfg = config or MeshConfig()
    src_path = Path(source)
    check_output_apart(out_dir, [("dense folder" if src_path.is_dir() else "cloud file", src_path)])
    check_workers(workers, scheduler)
    src = open_cloud(src_path)
    where = str(src.path)
    out_crs = resolve_crs(src.crs, crs, where)
    if src.count is not None and src.count < MIN_POINTS:
        raise TooFewPointsError(f"{where}: {src.count} point(s); expected at least {MIN_POINTS} to mesh a surface")
    step = progress or (lambda stage, done, total: None)
    with OutputSet(out_dir, "mesh") as stage:
        spill = spill_folder(stage.stage, "mesh")
        try:
            report = _mesh(Path(stage.stage), spill, src, out_crs, crs, cfg, workers, scheduler, step, t0)
        finally:
            import shutil

            shutil.rmtree(spill, ignore_errors=True)
        stage.commit({"seconds": report["seconds"]})
    return report


def _read_into(spill: Path, src, step) -> tuple[int, np.ndarray, np.ndarray, bool]:
    """Read the cloud into ``spill/raw.xyz`` (float64) and ``spill/raw.nrm`` (float32); count, box, any normals."""
    n, lo, hi, any_n = 0, np.full(3, np.inf), np.full(3, -np.inf), False
    total = src.count or 0
    with open(spill / "raw.xyz", "wb") as fx, open(spill / "raw.nrm", "wb") as fn:
        for xyz, nrm in src.chunks(CHUNK):
            bad = ~np.all(np.isfinite(xyz), axis=1)
            if bad.any():
                k = int(np.flatnonzero(bad)[0])
                raise InvalidInputError(f"{src.path}: point {n + k} (0-based) has non-finite coordinates "
                                        f"{xyz[k].tolist()}; expected finite coordinates in metres")
            fx.write(np.ascontiguousarray(xyz, "<f8").tobytes())
            if nrm is None:
                nrm = np.zeros((len(xyz), 3), np.float32)
            else:
                nrm = np.nan_to_num(nrm.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
                any_n |= bool(np.any(nrm != 0))
            fn.write(np.ascontiguousarray(nrm, "<f4").tobytes())
            if len(xyz):
                lo, hi = np.minimum(lo, xyz.min(axis=0)), np.maximum(hi, xyz.max(axis=0))
            n += len(xyz)
            step("reading points", n, max(total, n))
    return n, lo, hi, any_n


def _neighbourhoods(P, origin, lo, hi, n):
    """Complete neighbourhoods of ``SEEDS`` seeds (every ``n // SEEDS``-th point): the radius grown or shrunk until
    about ``SEED_POINTS`` points lie within it (each pass one read of the memory-mapped points)."""
    seeds = np.asarray(P[np.linspace(0, n - 1, SEEDS).astype(np.int64)]) - origin
    diag = float(np.linalg.norm(hi - lo)) or 1.0
    r = diag * np.sqrt(SEED_POINTS / max(n, 1))
    for _ in range(40):
        counts = np.zeros(len(seeds), np.int64)
        for s in range(0, n, CHUNK):
            x = np.asarray(P[s:s + CHUNK]) - origin
            for j, sd in enumerate(seeds):
                counts[j] += int(np.count_nonzero(np.sum((x - sd) ** 2, axis=1) <= r * r))
        med = float(np.median(counts))
        if med > 8 * SEED_POINTS:
            r *= 0.5
        elif med < SEED_POINTS / 2 and r < diag:
            r *= 2.0 if med < SEED_POINTS / 8 else 1.4
        else:
            break
    got = [[] for _ in seeds]
    for s in range(0, n, CHUNK):
        x = np.asarray(P[s:s + CHUNK]) - origin
        for j, sd in enumerate(seeds):
            m = np.sum((x - sd) ** 2, axis=1) <= r * r
            if m.any():
                got[j].append(x[m])
    return [(sd, np.concatenate(g)) for sd, g in zip(seeds, got) if g]


def _sort_by_block(spill: Path, P, Nr, n, origin, lattice):
    """Points and normals sorted by block into ``spill/sorted.*``; returns ``{block: (start, stop)}``."""
    bid = np.empty(n, np.int64)
    nx, ny, nz = lattice.shape
    for s in range(0, n, CHUNK):
        b = lattice.block_of(np.asarray(P[s:s + CHUNK]) - origin)
        bid[s:s + CHUNK] = (b[:, 0] * ny + b[:, 1]) * nz + b[:, 2]
    order = np.argsort(bid, kind="stable")
    bid = bid[order]
    Ps = np.lib.format.open_memmap(spill / "sorted_xyz.npy", mode="w+", dtype="<f8", shape=(n, 3))
    Ns = np.lib.format.open_memmap(spill / "sorted_nrm.npy", mode="w+", dtype="<f4", shape=(n, 3))
    for s in range(0, n, CHUNK):
        o = order[s:s + CHUNK]
        srt = np.argsort(o)  # read the raw files in increasing position, then put each point in its place
        tgt_p = np.empty((len(o), 3))
        tgt_n = np.empty((len(o), 3), np.float32)
        tgt_p[srt] = np.asarray(P[o[srt]]) - origin
        tgt_n[srt] = np.asarray(Nr[o[srt]])
        Ps[s:s + len(o)] = tgt_p
        Ns[s:s + len(o)] = tgt_n
    Ps.flush()
    Ns.flush()
    del Ps, Ns, order
    keys, starts = np.unique(bid, return_index=True)
    stops = np.r_[starts[1:], n]
    index = {}
    for k, a, b in zip(keys.tolist(), starts.tolist(), stops.tolist()):
        index[(k // (ny * nz), (k // nz) % ny, k % nz)] = (a, b)
    return index


def _gather(spill: str, index: dict, lattice, b, margin: float, with_normals: bool):
    """The points (and normals) within ``margin`` of block ``b``'s cubes, from the sorted files."""
    Ps = np.load(os.path.join(spill, "sorted_xyz.npy"), mmap_mode="r")
    Ns = np.load(os.path.join(spill, "sorted_nrm.npy"), mmap_mode="r")
    lo, hi = lattice.block_box(b)
    lo, hi = lo - margin, hi + margin
    reach = int(np.ceil(margin / (lattice.h * lattice.block)))
    ps, ns = [], []
    for di in range(-reach, reach + 1):
        for dj in range(-reach, reach + 1):
            for dk in range(-reach, reach + 1):
                r = index.get((b[0] + di, b[1] + dj, b[2] + dk))
                if r is None:
                    continue
                x = np.asarray(Ps[r[0]:r[1]])
                m = np.all((x >= lo) & (x <= hi), axis=1)
                ps.append(x[m])
                if with_normals:
                    ns.append(np.asarray(Ns[r[0]:r[1]])[m])
    P = np.concatenate(ps) if ps else np.zeros((0, 3))
    N = (np.concatenate(ns) if ns else np.zeros((0, 3), np.float32)) if with_normals else None
    return P, N


def _block_task(spill: str, index: dict, lattice, b, margin: float, with_normals: bool, rep_pts, rep_nrm, cfg,
                thr: float, bound: float):
    from ..products.mesh_surface import mesh_block

    P, N = _gather(spill, index, lattice, b, margin, with_normals)
    return mesh_block(P, N, rep_pts, rep_nrm, lattice, b, cfg, thr, bound)


def _mesh(out: Path, spill: Path, src, out_crs, crs_given, cfg: MeshConfig, workers, scheduler, step, t0) -> dict:
    from ..products.mesh import cloud_scale, finish_mesh, make_lattice
    from ..products.mesh_surface import block_margin, block_representatives, orient_representatives
    from ..tasks import open_client, ordered_results

    n, lo, hi, any_n = _read_into(spill, src, step)
    if n < MIN_POINTS:
        raise TooFewPointsError(f"{src.path}: {n} point(s); expected at least {MIN_POINTS} to mesh a surface")
    origin = np.round(0.5 * (lo + hi))
    P = np.memmap(spill / "raw.xyz", dtype="<f8", mode="r", shape=(n, 3))
    Nr = np.memmap(spill / "raw.nrm", dtype="<f4", mode="r", shape=(n, 3))
    step("measuring the cloud's spacing", 0, 1)
    scale = cloud_scale(_neighbourhoods(P, origin, lo, hi, n), cfg.surface)
    step("measuring the cloud's spacing", 1, 1)
    h = scale.cell_m
    span = hi - lo
    if np.any(span / h > 2e6):
        raise ConfigError(f"{src.path}: the cloud spans {span.round(1).tolist()} m, over 2,000,000 lattice cells of "
                          f"{h:.4g} m along an axis; expected one site (a stray point far away? a CRS mix-up?), "
                          "or give a larger --cell")
    lattice = make_lattice(lo - origin, hi - origin, h, cfg.surface.block)
    index = _sort_by_block(spill, P, Nr, n, origin, lattice)
    del P, Nr
    for f in ("raw.xyz", "raw.nrm"):
        os.unlink(spill / f)
    # coarse representatives, block by block, oriented once
    Ps = np.load(spill / "sorted_xyz.npy", mmap_mode="r")
    Ns = np.load(spill / "sorted_nrm.npy", mmap_mode="r")
    reps, sums = [], []
    for k, (b, (a, e)) in enumerate(sorted(index.items())):
        _, mean, _, ns = block_representatives(np.asarray(Ps[a:e]), np.asarray(Ns[a:e]) if any_n else None,
                                               lattice, cfg.surface)
        reps.append(mean)
        sums.append(ns)
        step("representatives", k + 1, len(index))
    del Ps, Ns
    reps = np.concatenate(reps)
    sums = np.concatenate(sums)
    step("orienting normals", 0, 1)
    rep_n, orient = orient_representatives(reps, sums)
    step("orienting normals", 1, 1)
    margin = block_margin(h, cfg.surface, scale.outlier_bound_m)
    rmargin = margin + 3.0 * h * cfg.surface.rep_cells
    blocks = sorted(index)
    args_reps = []
    for b in blocks:
        blo, bhi = lattice.block_box(b)
        m = np.all((reps >= blo - rmargin) & (reps <= bhi + rmargin), axis=1)
        args_reps.append((reps[m], rep_n[m]))
    client = open_client(workers, scheduler)
    results = []
    try:
        nb = len(blocks)
        lists = ([str(spill)] * nb, [index] * nb, [lattice] * nb, blocks, [margin] * nb, [any_n] * nb,
                 [r[0] for r in args_reps], [r[1] for r in args_reps], [cfg.surface] * nb,
                 [scale.outlier_threshold_m] * nb, [scale.outlier_bound_m] * nb)
        it = (ordered_results(client, _block_task, *lists) if client is not None
              else (_block_task(*(lst[i] for lst in lists)) for i in range(nb)))
        for k, res in enumerate(it):
            results.append(res)
            step("meshing blocks", k + 1, nb)
    finally:
        if client is not None:
            client.close()
    points_used = int(sum(r.points_core - r.outliers_core for r in results))
    outliers = int(sum(r.outliers_core for r in results))
    if sum(len(r.faces) for r in results) == 0:
        raise DataFileError(f"{src.path}: the {n} points gave no surface at a lattice cell of {h:.4g} m (points too "
                            "sparse or scattered for a surface?); expected points sampling surfaces, or try a larger --cell")

    def on_step(name):
        step(name, 0, 1)
    V, F, filled, fin = finish_mesh(results, lattice, cfg, on_step=on_step)
    del results
    if len(F) == 0:
        raise DataFileError(f"{src.path}: no surface left after removing loose pieces below "
                            f"{fin['pieces_removed']['below_m2']:.3g} m²; expected points sampling surfaces")
    step("writing", 0, 1)
    _write_ply(out / "mesh.ply", V, F, filled, origin, out_crs)
    _write_obj(out / "mesh.obj", V, F, origin, out_crs)
    notes = []
    if out_crs is None:
        notes.append("the cloud states no CRS and no --crs was given: the mesh is in the cloud's own coordinates "
                     "(a local frame); give --crs EPSG:N for a scan in a survey's projected CRS"
                     if not src.crs_stated else "the dense folder's survey is in a local frame (no CRS)")
    if orient["from_cloud_normals"] == 0 and orient["seeded_parts"]:
        notes.append(f"the cloud has no normals: their signs were propagated from {orient['seeded_parts']} seed(s) "
                     "(the highest near-horizontal surface of each connected part taken to face up)")
    if fin["holes"]["left_open"]:
        notes.append(f"{fin['holes']['left_open']} hole(s) left open (larger than --fill-holes "
                     f"{cfg.fill_holes_m2:g} m² or not fillable; the largest {fin['holes']['largest_open_m2']:.3g} m²)")
    report = {
        "points": points_used,
        "faces": int(len(F)),
        "filled_faces": int(filled.sum()),
        "filled_area_m2": round(fin["filled_area_m2"], 4),
        "trimmed_area_m2": round(fin["trimmed_area_m2"], 4),
        "decimation_rms_m": round(fin["decimation"]["rms_m"], 6),
        "crs": out_crs,
        "seconds": round(time.perf_counter() - t0, 2),
        "vertices": int(len(V)),
        "local_origin": [float(x) for x in origin],
        "area_m2": round(fin["area_m2"], 4),
        "points_read": int(n),
        "outliers_removed": outliers,
        "input": {"path": str(src.path), "kind": src.kind, "crs_in_file": src.crs, "crs_given": crs_given,
                  "normals_in_file": bool(any_n)},
        "method": "signed distance to the points' tangent planes on a lattice near the points, marching cubes, "
                  "in blocks (docs/verbs/mesh.md)",
        "cell_m": round(h, 6),
        "scale": scale.as_dict(),
        "blocks": {"count": len(blocks), "cells_per_side": lattice.block, "margin_m": round(margin, 4),
                   "lattice_shape": list(lattice.shape)},
        "normals": orient,
        "pieces_removed": fin["pieces_removed"],
        "holes": fin["holes"],
        "decimation": {**fin["decimation"], "rms_m": round(fin["decimation"]["rms_m"], 6),
                       "max_m": round(fin["decimation"]["max_m"], 6)},
        "fill_holes_m2": cfg.fill_holes_m2,
        "files": ["mesh.ply", "mesh.obj", "mesh.json"],
        "workers": int(workers) if not scheduler else None,
        "scheduler": scheduler,
        "notes": notes,
    }
    (out / "mesh.json").write_text(json.dumps(report, indent=1, default=float) + "\n", encoding="utf-8")
    step("writing", 1, 1)
    return report


def _write_ply(path: Path, V, F, filled, origin, crs) -> None:
    """Binary PLY: vertex ``double x y z`` in the CRS's coordinates, face ``vertex_indices`` + ``uchar filled``."""
    hdr = ("ply\nformat binary_little_endian 1.0\ncomment thermogrammetry mesh\n"
           + (f"comment crs {crs}\n" if crs else "")
           + f"comment local_origin {origin[0]:.3f} {origin[1]:.3f} {origin[2]:.3f}\n"
           + "comment x y z are the CRS's coordinates (doubles); filled = 1: a face made by hole filling\n"
           + f"element vertex {len(V)}\nproperty double x\nproperty double y\nproperty double z\n"
           + f"element face {len(F)}\nproperty list uchar int vertex_indices\nproperty uchar filled\nend_header\n")
    vx = np.ascontiguousarray(V + origin, "<f8")
    fd = np.zeros(len(F), np.dtype([("n", "u1"), ("v", "<i4", (3,)), ("filled", "u1")]))
    fd["n"] = 3
    fd["v"] = F
    fd["filled"] = filled.astype(np.uint8)
    with open(path, "wb") as fh:
        fh.write(hdr.encode("ascii"))
        fh.write(vx.tobytes())
        fh.write(fd.tobytes())


def _write_obj(path: Path, V, F, origin, crs) -> None:
    """Wavefront OBJ: ``v`` in the CRS's coordinates with 4 decimals (0.1 mm), ``f`` 1-based."""
    with open(path, "w", encoding="ascii") as fh:
        fh.write("# thermogrammetry mesh" + (f" (crs {crs})" if crs else " (local frame)")
                 + "; vertices in the CRS's coordinates, faces wound outwards (towards the side the surface was seen from)\n")
        X = V + origin
        for s in range(0, len(X), 500_000):
            np.savetxt(fh, X[s:s + 500_000], fmt="v %.4f %.4f %.4f")
        for s in range(0, len(F), 500_000):
            np.savetxt(fh, F[s:s + 500_000] + 1, fmt="f %d %d %d")
