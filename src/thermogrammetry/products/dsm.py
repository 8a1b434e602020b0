"""DSM gridding: median height of the points in every cell, processed tile by tile.

Points arrive in any order and are spilled to per-tile files (:class:`TileSpill`, tiles of ``tile`` cells
aligned on multiples of ``tile · gsd`` in the CRS), so that gridding holds one tile's points at a time:
memory is bounded by the tile size, not by the survey size. Empty cells are nodata; on request
(:func:`fill_holes`) they are filled from the nearest valid cell within ``max_distance_px`` and flagged in
a mask band.

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

__all__ = ["grid_median", "fill_holes", "TileSpill", "aligned_grid"]

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
