"""DSM gridding: median height of the points in every cell, processed tile by tile.

Points arrive in any order and are spilled to per-tile files (:class:`TileSpill`, tiles of ``tile`` cells
aligned on multiples of ``tile · gsd`` in the CRS), so that gridding holds one tile's points at a time:
memory is bounded by the tile size, not by the survey size. Empty cells are nodata; on request
(:func:`fill_holes`) they are filled from the nearest valid cell within ``max_distance_px`` and flagged in
a mask band.

:func:`fill_surface` fills the holes of a DSM for the orthophoto's surface (``dsm_filled.tif``, the ortho's
default): every empty cell within half the largest hole size of a measured cell is interpolated by Laplace
(membrane) interpolation: the discrete Laplace equation on the 4-neighbour grid, the measured cells of the
hole's rim held fixed (Dirichlet), no flux across the grid border or into the cells left empty (Neumann).
The result is the smoothest surface through the rim: a plane is reproduced exactly, a hole's heights stay
within its rim's range (maximum principle), and a gap at the data's outer edge is continued flat from the
rim. Holes up to ``max_hole_px`` across are filled entirely; wider ones only within ``max_hole_px / 2`` of
their rim. A gap beyond the convex hull of the measured cells (the data's outer edge: the rim is on one side only,
so the gap's width across is its depth from the rim) is filled up to ``max_hole_px`` from the rim. The computation
holds the whole DSM in memory (about 30 bytes per cell while solving).

References
----------
Khodaei et al. (seed 003): DSM generation from the dense thermal point cloud.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator

import numpy as np

from .raster import Grid

__all__ = ["grid_median", "fill_holes", "fill_surface", "FILL_METHOD", "DEFAULT_MAX_HOLE_CELLS", "height_tags", "write_filled_dsm",
           "extended_grid", "TileSpill", "aligned_grid"]

#: the method of :func:`fill_surface`, as recorded in dense.json / ortho.json
FILL_METHOD = ("Laplace interpolation from the hole's rim (measured cells fixed; no flux across the grid border or into cells left empty); cells farther than max_hole_m / 2 from a measured cell stay empty (max_hole_m beyond the convex hull of the measured cells, where a gap has its rim on one side only)")
#: default largest hole (in DSM cells) that :func:`fill_surface` fills entirely
DEFAULT_MAX_HOLE_CELLS = 100

#: records read at a time from a spill tile (12 MB of dense-point records)
CHUNK_RECORDS = 1 << 18


def grid_median(x, y, z, grid: Grid, r0: int, c0: int, rows: int, cols: int) -> np.ndarray:
    """(rows, cols) median of ``z`` per cell of a window of ``grid``; NaN where a cell has no point.

    The median of an even count is the mean of the two middle values. Vectorised (one sort).
    """
    row, col = grid.cell_of(x, y)
    row, col = row - r0, col - c0
    inside = (row >= 0) & (row < rows) & (col >= 0) & (col < cols) & np.isfinite(z)
    cell = row[inside] * cols + col[inside]
    zz = np.asarray(z, float)[inside]
    out = np.full(rows * cols, np.nan)
    if len(cell) == 0:
        return out.reshape(rows, cols)
    order = np.lexsort((zz, cell))
    cell, zz = cell[order], zz[order]
    starts = np.flatnonzero(np.r_[True, cell[1:] != cell[:-1]])
    counts = np.diff(np.r_[starts, len(cell)])
    lo = starts + (counts - 1) // 2
    hi = starts + counts // 2
    out[cell[starts]] = 0.5 * (zz[lo] + zz[hi])
    return out.reshape(rows, cols)


def fill_holes(z, max_distance_px: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Fill NaN cells with the nearest valid cell's value (within ``max_distance_px``).

    Returns
    -------
    filled : (H, W) heights; mask : (H, W) uint8, 1 where the value was filled (not measured)
    """
    from scipy.ndimage import distance_transform_edt

    z = np.asarray(z, float)
    bad = ~np.isfinite(z)
    if not bad.any() or bad.all():
        return z.copy(), np.zeros(z.shape, np.uint8)
    dist, (ri, ci) = distance_transform_edt(bad, return_indices=True)
    fill = bad & (dist <= max_distance_px)
    out = z.copy()
    out[fill] = z[ri[fill], ci[fill]]
    return out, fill.astype(np.uint8)


def outside_hull(ok) -> np.ndarray:
    """(H, W) bool: the cells whose centre lies outside the convex hull of the cells where ``ok`` is True (the
    hull of the cell centres; all False when those cells are collinear or fewer than 3)."""
    from scipy.spatial import ConvexHull, QhullError

    ok = np.asarray(ok, bool)
    H, W = ok.shape
    rows = np.flatnonzero(ok.any(axis=1))
    cols = np.flatnonzero(ok.any(axis=0))
    if len(rows) < 2 or len(cols) < 2:
        return np.zeros(ok.shape, bool)
    # the hull of all the cells is the hull of each row's and each column's first and last cell
    first_c, last_c = ok[rows].argmax(axis=1), W - 1 - ok[rows, ::-1].argmax(axis=1)
    first_r, last_r = ok[:, cols].argmax(axis=0), H - 1 - ok[::-1, cols].argmax(axis=0)
    pts = np.unique(np.concatenate([np.column_stack([first_c, rows]), np.column_stack([last_c, rows]),
                                    np.column_stack([cols, first_r]), np.column_stack([cols, last_r])]), axis=0)
    try:
        eq = ConvexHull(pts.astype(float)).equations  # a·x + b·y + c <= 0 inside
    except QhullError:
        return np.zeros(ok.shape, bool)
    out = np.zeros(ok.shape, bool)
    cc = np.arange(W, dtype=float)
    for r in range(H):  # row by row: memory of one row times the hull's facets
        v = eq[:, 0:1] * cc[None] + eq[:, 1:2] * float(r) + eq[:, 2:3]
        out[r] = (v > 1e-9).any(axis=0)
    return out


def fill_surface(z, max_hole_px: float = DEFAULT_MAX_HOLE_CELLS, *, open_edges: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Fill the holes of a DSM by Laplace interpolation from their rim (see the module docstring).

    Parameters
    ----------
    z : (H, W) heights (m), NaN = no data
    max_hole_px : largest hole filled entirely, in cells (its width across); empty cells farther than
        ``max_hole_px / 2`` from every measured cell stay empty. Beyond the convex hull of the measured cells (a gap
        at the data's outer edge, its rim on one side only: its width across is its depth from the rim) the limit
        is ``max_hole_px`` from the rim (``open_edges``; False: ``max_hole_px / 2`` there too). 0 fills nothing.

    Returns
    -------
    filled : (H, W) float64 heights; mask : (H, W) uint8, 1 where the height was interpolated (not measured)
    """
    import scipy.sparse as sp
    from scipy.ndimage import distance_transform_edt, label
    from scipy.sparse.linalg import spsolve

    z = np.asarray(z, float)
    ok = np.isfinite(z)
    out = z.copy()
    none = np.zeros(z.shape, np.uint8)
    if ok.all() or not ok.any() or not max_hole_px > 0:
        return out, none
    dist = distance_transform_edt(~ok)
    # a hole inside the measured cells' convex hull has its rim all around: filled within half its width of the rim;
    # a gap beyond the hull (the data's outer edge) has its rim on one side only: filled within its width
    reach = np.where(outside_hull(ok) if open_edges else False, float(max_hole_px), 0.5 * float(max_hole_px))
    todo = ~ok & (dist <= reach)
    # 4-neighbour pieces that touch no measured cell have no rim: left empty (only reachable diagonally)
    lab, n = label(todo)
    H, W = z.shape
    rim = np.zeros(z.shape, bool)
    rim[1:] |= ok[:-1]
    rim[:-1] |= ok[1:]
    rim[:, 1:] |= ok[:, :-1]
    rim[:, :-1] |= ok[:, 1:]
    keep = np.zeros(n + 1, bool)
    keep[np.unique(lab[todo & rim])] = True
    keep[0] = False
    todo = keep[lab]
    if not todo.any():
        return out, none
    idx = np.full(z.shape, -1, np.int64)
    rr, cc = np.nonzero(todo)
    m = len(rr)
    idx[rr, cc] = np.arange(m)
    diag = np.zeros(m)
    b = np.zeros(m)
    rows, cols = [], []
    for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        r2, c2 = rr + dr, cc + dc
        inside = (r2 >= 0) & (r2 < H) & (c2 >= 0) & (c2 < W)
        r2, c2 = np.where(inside, r2, 0), np.where(inside, c2, 0)
        meas = inside & ok[r2, c2]
        other = inside & todo[r2, c2]
        diag += meas | other
        b += np.where(meas, z[r2, c2], 0.0)
        rows.append(np.flatnonzero(other))
        cols.append(idx[r2, c2][other])
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    A = sp.csr_matrix((np.r_[diag, -np.ones(len(rows))], (np.r_[np.arange(m), rows], np.r_[np.arange(m), cols])),
                      shape=(m, m))
    out[rr, cc] = spsolve(A.tocsc(), b)
    return out, todo.astype(np.uint8)


#: the GeoTIFF tag of a DSM whose CRS declares no vertical datum
HEIGHTS_AS_INPUT = ("as in the input files: the survey's CRS declares no vertical datum (GNSS heights are usually "
                    "ellipsoidal; the datum is unknown to the software)")


def height_tags(crs) -> dict:
    """GeoTIFF metadata on the DSM's heights: ``vertical_datum`` (the vertical CRS's name when ``crs`` is compound,
    i.e. the heights' datum is known and written as a compound CRS; else :data:`HEIGHTS_AS_INPUT`)."""
    if crs:
        try:
            from pyproj import CRS

            c = CRS.from_user_input(crs)
            if c.is_compound and len(c.sub_crs_list) > 1:
                return {"vertical_datum": c.sub_crs_list[1].name}
        except Exception:  # noqa: BLE001 - an unreadable CRS is written as given, its heights not judged
            pass
    return {"vertical_datum": HEIGHTS_AS_INPUT}


def extended_grid(g: Grid, box, max_cells: int) -> Grid:
    """``g`` grown by whole cells towards ``box`` = (xmin, ymin, xmax, ymax) (m), at most ``max_cells`` cells on each
    side (never shrunk): the same cell size and cell edges, so that ``g``'s cells are cells of the result."""
    xmin, ymin, xmax, ymax = (float(v) for v in box)
    n = max(0, int(max_cells))

    def grow(d):
        return int(min(n, max(0, np.ceil(d / g.gsd - 1e-9)))) if np.isfinite(d) else 0

    left, right = grow(g.x0 - xmin), grow(xmax - (g.x0 + g.width * g.gsd))
    top, bottom = grow(ymax - g.y0), grow((g.y0 - g.height * g.gsd) - ymin)
    return Grid(g.x0 - left * g.gsd, g.y0 + top * g.gsd, g.gsd, g.width + left + right, g.height + top + bottom, g.tile)


def write_filled_dsm(src, dst, max_hole_m: float | None, crs, *, grid: Grid | None = None) -> dict:
    """Write ``dst``: the DSM ``src`` with its holes filled (:func:`fill_surface`); band 1 height (m), band 2 =
    1 where interpolated. Returns the record of ``dense.json``/``ortho.json`` (file, method, cells filled).

    ``grid``: a grid holding the DSM's (:func:`extended_grid`): the DSM is placed in it, the cells beyond its box
    empty, and filled like any other empty cell (from the measured cells within ``max_hole_m / 2``, continued flat
    towards the grid's border), so that the surface reaches the parts of the images' footprints that the DSM's box
    leaves out."""
    from .raster import read_raster, write_cog

    z, g, _, _ = read_raster(src)
    max_px = DEFAULT_MAX_HOLE_CELLS if max_hole_m is None else float(max_hole_m) / g.gsd
    beyond = np.zeros(z.shape, bool)  # cells of the surface's grid outside the DSM's box
    if grid is not None:
        fc, fr = (g.x0 - grid.x0) / g.gsd, (grid.y0 - g.y0) / g.gsd
        c0, r0 = int(round(fc)), int(round(fr))
        if (abs(grid.gsd - g.gsd) > 1e-9 * g.gsd or abs(fc - c0) > 1e-6 or abs(fr - r0) > 1e-6 or c0 < 0 or r0 < 0
                or c0 + g.width > grid.width or r0 + g.height > grid.height):
            raise ValueError(f"write_filled_dsm: grid {grid} does not hold the DSM's grid {g} cell for cell")
        big = np.full((grid.height, grid.width), np.nan)
        big[r0:r0 + g.height, c0:c0 + g.width] = z
        beyond = np.ones(big.shape, bool)
        beyond[r0:r0 + g.height, c0:c0 + g.width] = False
        z, g = big, grid
    zf, mask = fill_surface(z, max_px)
    g = Grid(g.x0, g.y0, g.gsd, g.width, g.height, 512)
    both = np.stack([zf, mask.astype(float)]).astype(np.float32)
    both[1][~np.isfinite(zf)] = np.nan
    write_cog(dst, g, np.float32, lambda r0, c0, rows, cols: both[:, r0:r0 + rows, c0:c0 + cols], crs=crs,
              nodata=float("nan"), unit="m", bands=2,
              description=["height (m): measured, holes interpolated (band 2)", "1 = interpolated (not measured), 0 = measured"],
              tags={"product": "thermogrammetry filled DSM", "gsd_m": g.gsd, "fill_method": FILL_METHOD,
                    "max_hole_m": max_px * g.gsd, **height_tags(crs)})
    rec = {"file": Path(dst).name, "method": FILL_METHOD, "max_hole_m": round(max_px * g.gsd, 4),
           "filled_cells": int(mask.sum()), "measured_cells": int(np.isfinite(z).sum()),
           "empty_cells": int((~np.isfinite(zf)).sum())}
    if grid is not None:
        rec["grid"] = {"x0": g.x0, "y0": g.y0, "width": g.width, "height": g.height}
        rec["filled_beyond_dsm_cells"] = int((mask.astype(bool) & beyond).sum())
    return rec


def aligned_grid(xmin, ymin, xmax, ymax, gsd: float, tile: int) -> Grid:
    """Grid covering the box whose tiles start on multiples of ``tile · gsd`` (the spill's tiling)."""
    T = tile * gsd
    x0 = np.floor(xmin / T) * T
    y0 = np.ceil(ymax / T) * T
    w = int(np.ceil((xmax - x0) / gsd)) + 1
    h = int(np.ceil((y0 - ymin) / gsd)) + 1
    return Grid(float(x0), float(y0), float(gsd), max(w, 1), max(h, 1), int(tile))


class TileSpill:
    """Append-only per-tile files of structured point records in a scratch folder.

    Tiles are keyed ``(kx, ky) = (floor(x / T), floor(y / T))`` with ``T = tile · gsd``. Records keep their
    arrival order inside a tile (deterministic when chunks arrive in a fixed order).
    """

    def __init__(self, folder, dtype, gsd: float, tile: int):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.dtype = np.dtype(dtype)
        self.T = float(tile) * float(gsd)
        self.gsd, self.tile = float(gsd), int(tile)
        self.bbox = [np.inf, np.inf, -np.inf, -np.inf]
        self.count = 0
        self.keys: set[tuple[int, int]] = set()

    def _path(self, key) -> Path:
        return self.folder / f"tile_{key[0]}_{key[1]}.bin"

    def append(self, pts) -> None:
        if len(pts) == 0:
            return
        kx = np.floor(pts["x"] / self.T).astype(np.int64)
        ky = np.floor(pts["y"] / self.T).astype(np.int64)
        self.bbox = [min(self.bbox[0], float(pts["x"].min())), min(self.bbox[1], float(pts["y"].min())),
                     max(self.bbox[2], float(pts["x"].max())), max(self.bbox[3], float(pts["y"].max()))]
        key = kx * 1_000_003 + ky
        order = np.argsort(key, kind="stable")
        key, kx, ky, pts = key[order], kx[order], ky[order], pts[order]
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        ends = np.r_[starts[1:], len(key)]
        for s, e in zip(starts, ends):
            k = (int(kx[s]), int(ky[s]))
            with open(self._path(k), "ab") as fh:
                fh.write(pts[s:e].tobytes())
            self.keys.add(k)
        self.count += len(pts)

    def read(self, key) -> np.ndarray:
        p = self._path(key)
        if not p.exists():
            return np.zeros(0, self.dtype)
        return np.fromfile(p, dtype=self.dtype)

    def iter_chunks(self, key, chunk: int = CHUNK_RECORDS) -> Iterator[np.ndarray]:
        """The records of one tile in arrival order, ``chunk`` records at a time (memory bounded by the chunk,
        not by the tile)."""
        p = self._path(key)
        if not p.exists():
            return
        size = self.dtype.itemsize
        n = p.stat().st_size // size
        for a in range(0, n, int(chunk)):
            yield np.fromfile(p, dtype=self.dtype, count=min(int(chunk), n - a), offset=a * size)

    def _window_keys(self, grid: Grid, r0: int, c0: int, rows: int, cols: int) -> list:
        xa, xb = grid.x0 + c0 * grid.gsd, grid.x0 + (c0 + cols) * grid.gsd
        ya, yb = grid.y0 - (r0 + rows) * grid.gsd, grid.y0 - r0 * grid.gsd
        return [(kx, ky)
                for kx in range(int(np.floor(xa / self.T)), int(np.floor(xb / self.T)) + 1)
                for ky in range(int(np.floor(ya / self.T)), int(np.floor(yb / self.T)) + 1)
                if (kx, ky) in self.keys]

    def read_window(self, grid: Grid, r0: int, c0: int, rows: int, cols: int) -> np.ndarray:
        """All records of the spill tiles that intersect a window of ``grid`` (any grid)."""
        parts = [self.read(k) for k in self._window_keys(grid, r0, c0, rows, cols)]
        return np.concatenate(parts) if parts else np.zeros(0, self.dtype)

    def window_xyz(self, grid: Grid, r0: int, c0: int, rows: int, cols: int,
                   chunk: int = CHUNK_RECORDS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, y, z (m) of the records whose cell of ``grid`` (:meth:`Grid.cell_of`) lies in the window.

        The intersecting spill tiles are read in chunks and filtered, so memory holds the window's
        coordinates only (not the spill tiles' whole records, which reach 4 tiles × the tile's records when
        the window straddles tile corners). Same points in the same order as :meth:`read_window` filtered to
        the window, hence the same :func:`grid_median`.
        """
        xs, ys, zs = [], [], []
        for k in self._window_keys(grid, r0, c0, rows, cols):
            for c in self.iter_chunks(k, chunk):
                row, col = grid.cell_of(c["x"], c["y"])
                m = (row >= r0) & (row < r0 + rows) & (col >= c0) & (col < c0 + cols)
                xs.append(c["x"][m])
                ys.append(c["y"][m])
                zs.append(c["z"][m])
        if not xs:
            return np.zeros(0), np.zeros(0), np.zeros(0)
        return np.concatenate(xs), np.concatenate(ys), np.concatenate(zs)

    def cleanup(self) -> None:
        for k in self.keys:
            try:
                os.unlink(self._path(k))
            except OSError:
                pass
        try:
            self.folder.rmdir()
        except OSError:
            pass
