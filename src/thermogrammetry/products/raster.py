"""GeoTIFF products: tiled Cloud-Optimised GeoTIFFs with overviews, unit, nodata and description.

:class:`Grid` is a north-up raster grid (pixel-corner transform, GDAL convention; the centre of cell
(row, col) is ``(x0 + (col + ½) gsd, y0 − (row + ½) gsd)``, docs/conventions.md) cut into square tiles.
:func:`write_cog` writes a raster tile by tile into a temporary tiled GeoTIFF and copies it to a COG
(GDAL's COG driver: internal tiling, overviews, atomically renamed into place), so memory stays bounded
by the tile size.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from ..errors import DataFileError

__all__ = ["Grid", "write_cog", "read_raster", "read_window"]


@dataclass(frozen=True)
class Grid:
    """North-up grid: top-left corner ``(x0, y0)`` (m), cell ``gsd`` (m), ``width`` × ``height`` cells, tiles of
    ``tile`` cells."""

    x0: float
    y0: float
    gsd: float
    width: int
    height: int
    tile: int = 512

    @classmethod
    def covering(cls, xmin, ymin, xmax, ymax, gsd, tile: int = 512) -> "Grid":
        """The grid aligned on multiples of ``gsd`` that covers the box."""
        x0 = np.floor(xmin / gsd) * gsd
        y0 = np.ceil(ymax / gsd) * gsd
        w = int(np.ceil((xmax - x0) / gsd)) + 1
        h = int(np.ceil((y0 - ymin) / gsd)) + 1
        return cls(float(x0), float(y0), float(gsd), max(w, 1), max(h, 1), int(tile))

    @property
    def transform(self):
        from rasterio.transform import Affine

        return Affine(self.gsd, 0.0, self.x0, 0.0, -self.gsd, self.y0)

    def tiles(self) -> Iterator[tuple[int, int, int, int]]:
        """(row0, col0, rows, cols) of every tile, row-major."""
        for r in range(0, self.height, self.tile):
            for c in range(0, self.width, self.tile):
                yield r, c, min(self.tile, self.height - r), min(self.tile, self.width - c)

    def cell_centres(self, r0, c0, rows, cols) -> tuple[np.ndarray, np.ndarray]:
        """(rows, cols) x and y of the cell centres of a window (m)."""
        x = self.x0 + (c0 + np.arange(cols) + 0.5) * self.gsd
        y = self.y0 - (r0 + np.arange(rows) + 0.5) * self.gsd
        return np.meshgrid(x, y)

    def cell_of(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) integer cell index of points (m); may fall outside the grid."""
        col = np.floor((np.asarray(x) - self.x0) / self.gsd).astype(np.int64)
        row = np.floor((self.y0 - np.asarray(y)) / self.gsd).astype(np.int64)
        return row, col


def _crs(crs):
    if crs is None:
        return None
    from rasterio.crs import CRS

    return CRS.from_user_input(crs)


def write_cog(path, grid: Grid, dtype, tile_fn: Callable[[int, int, int, int], np.ndarray], *, crs=None,
              nodata=None, unit: str = "", description: str | list[str] = "", bands: int = 1,
              tags: dict | None = None, scale: float | None = None, offset: float | None = None,
              resampling: str = "average") -> Path:
    """Write a raster tile by tile as a COG with overviews.

    Parameters
    ----------
    path : output file (written atomically)
    grid : :class:`Grid`
    dtype : numpy dtype of the bands
    tile_fn : (row0, col0, rows, cols) -> (rows, cols) or (bands, rows, cols) array
    crs : "EPSG:n" or None (local frame: no CRS written)
    nodata, unit, description : band metadata (unit shown by QGIS/GDAL, e.g. "K", "°C", "m", "counts")
    tags : dataset metadata items
    scale, offset : GDAL band scale/offset (``value = code · scale + offset``)
    resampling : overview resampling ("average", "nearest", "mode")
    """
    import rasterio
    import rasterio.shutil

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    descs = [description] * bands if isinstance(description, str) else list(description)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp.tif", dir=path.parent)
    os.close(fd)
    fd2, tmp2 = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".cog.tif", dir=path.parent)
    os.close(fd2)
    blk = 256 if min(grid.width, grid.height) >= 256 else 16 * max(1, min(grid.width, grid.height) // 16)
    profile = dict(driver="GTiff", width=grid.width, height=grid.height, count=bands, dtype=np.dtype(dtype).name,
                   transform=grid.transform, crs=_crs(crs), nodata=nodata, tiled=True, blockxsize=max(16, blk),
                   blockysize=max(16, blk), compress="deflate", BIGTIFF="IF_SAFER")
    try:
        with rasterio.open(tmp, "w", **profile) as dst:
            for r0, c0, rows, cols in grid.tiles():
                a = np.asarray(tile_fn(r0, c0, rows, cols)).astype(dtype, copy=False)
                if a.ndim == 2:
                    a = a[None]
                dst.write(a, window=rasterio.windows.Window(c0, r0, cols, rows))
            for b in range(bands):
                if descs[b]:
                    dst.set_band_description(b + 1, descs[b])
                if unit:
                    dst.update_tags(b + 1, unit=unit)
            if unit:
                dst.units = tuple([unit] * bands)
            if scale is not None:
                dst.scales = tuple([float(scale)] * bands)
                dst.offsets = tuple([float(offset or 0.0)] * bands)
            if tags:
                dst.update_tags(**{k: str(v) for k, v in tags.items()})
        rasterio.shutil.copy(tmp, tmp2, driver="COG", COMPRESS="DEFLATE", OVERVIEWS="AUTO",
                             OVERVIEW_RESAMPLING=resampling.upper(), BLOCKSIZE=256, BIGTIFF="IF_SAFER")
        os.replace(tmp2, path)
    except rasterio.errors.RasterioError as exc:
        raise DataFileError(f"{path}: cannot write GeoTIFF ({exc})") from None
    finally:
        for t in (tmp, tmp2):
            try:
                os.unlink(t)
            except OSError:
                pass
    return path


def read_raster(path, band: int = 1) -> tuple[np.ndarray, Grid, str | None, dict]:
    """A whole band as float64 (nodata → NaN), its :class:`Grid`, CRS string and tags (with ``unit``)."""
    import rasterio

    try:
        with rasterio.open(path) as src:
            a = src.read(band, masked=True).astype(np.float64).filled(np.nan)
            tr = src.transform
            if abs(tr.b) > 1e-12 or abs(tr.d) > 1e-12 or abs(abs(tr.a) - abs(tr.e)) > 1e-9 * abs(tr.a):
                raise DataFileError(f"{path}: expected a north-up raster with square cells, got transform {tuple(tr)[:6]}")
            g = Grid(tr.c, tr.f, tr.a, src.width, src.height)
            crs = src.crs.to_string() if src.crs else None
            tags = dict(src.tags())
            tags.update(src.tags(band))
            if src.units and src.units[band - 1]:
                tags.setdefault("unit", src.units[band - 1])
    except rasterio.errors.RasterioIOError as exc:
        raise DataFileError(f"{path}: cannot read GeoTIFF ({exc}); expected a DSM or product GeoTIFF") from None
    return a, g, crs, tags


def read_window(path, r0, c0, rows, cols, band: int = 1) -> np.ndarray:
    """A window of a band as float64 with nodata → NaN; cells outside the raster are NaN."""
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(path) as src:
        a = src.read(band, window=Window(c0, r0, cols, rows), boundless=True, masked=True)
        return a.astype(np.float64).filled(np.nan)
