"""GeoTIFF products: tiled Cloud-Optimised GeoTIFFs with overviews, unit, nodata and description.

:class:`Grid` is a north-up raster grid (pixel-corner transform, GDAL convention; the centre of cell
(row, col) is ``(x0 + (col + ½) gsd, y0 − (row + ½) gsd)``, docs/conventions.md) cut into square tiles.
:func:`write_cog` writes a raster tile by tile into a temporary tiled GeoTIFF and copies it to a COG
(GDAL's COG driver: internal tiling, overviews, atomically renamed into place), so memory stays bounded
by the tile size.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .._atomic import make_temp

from ..errors import DataFileError

__all__ = ["Grid", "RasterSpec", "RasterInfo", "write_cog", "write_cogs", "read_raster", "read_window", "inspect_raster",
           "check_north_up"]


def same_horizontal_crs(a: str | None, b: str | None) -> bool:
    """Whether two CRS descriptions (EPSG codes, WKT, PROJ strings) have the same horizontal CRS.

    Compound CRSs are compared by their horizontal part (``EPSG:2056+5728`` and ``EPSG:2056`` agree); axis
    order is ignored. A missing CRS or one pyproj cannot read is not judged (True)."""
    if not a or not b:
        return True
    try:
        from pyproj import CRS

        ca, cb = CRS.from_user_input(a), CRS.from_user_input(b)
    except Exception:  # noqa: BLE001
        return True
    ha = ca.sub_crs_list[0] if ca.is_compound else ca
    hb = cb.sub_crs_list[0] if cb.is_compound else cb
    return bool(ha.equals(hb, ignore_axis_order=True))


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


@dataclass
class RasterSpec:
    """One output raster of :func:`write_cogs`: path, dtype, bands and band metadata."""

    path: Path
    dtype: object
    bands: int = 1
    nodata: float | int | None = None
    unit: str = ""
    description: str | list = ""
    tags: dict | None = None
    scale: float | None = None
    offset: float | None = None
    resampling: str = "average"


#: GDAL block cache while products are written (MB). GDAL's default is 5 % of the machine's RAM, which
#: the tiled writes and the COG copy fill with blocks of the whole raster: the process then grows with
#: the raster (1.2 GB on a 24 GB machine) although every tile is written once. A small cache bounds it.
GDAL_CACHE_MB = 64


def write_cogs(grid: Grid, specs: dict, tile_fn: Callable[[int, int, int, int], dict], *, crs=None,
               tiles=None) -> None:
    """Write several rasters of one grid tile by tile, then copy each to a COG with overviews (atomic).

    ``tile_fn(r0, c0, rows, cols)`` returns ``{key: (rows, cols) or (bands, rows, cols) array}`` for the
    keys of ``specs`` (:class:`RasterSpec`); ``tiles`` optionally gives the per-tile results as an iterator
    in :meth:`Grid.tiles` order instead (for results computed elsewhere, e.g. on a dask cluster).
    GDAL's block cache is limited to :data:`GDAL_CACHE_MB` meanwhile (memory bounded by the tiles, not the
    raster).
    """
    import rasterio

    with rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_MB):
        _write_cogs(grid, specs, tile_fn, crs=crs, tiles=tiles)


def _write_cogs(grid: Grid, specs: dict, tile_fn, *, crs=None, tiles=None) -> None:
    import rasterio
    import rasterio.shutil
    from rasterio.windows import Window

    tmps, dsts = {}, {}
    blk = 256 if min(grid.width, grid.height) >= 256 else 16 * max(1, min(grid.width, grid.height) // 16)
    try:
        for key, sp in specs.items():
            sp.path = Path(sp.path)
            sp.path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = make_temp(sp.path, suffix=".tmp.tif")
            tmp = str(tmp)
            os.close(fd)
            tmps[key] = tmp
            dsts[key] = rasterio.open(tmp, "w", driver="GTiff", width=grid.width, height=grid.height, count=sp.bands,
                                      dtype=np.dtype(sp.dtype).name, transform=grid.transform, crs=_crs(crs),
                                      nodata=sp.nodata, tiled=True, blockxsize=max(16, blk), blockysize=max(16, blk),
                                      compress="deflate", BIGTIFF="IF_SAFER")
        src = tiles if tiles is not None else (tile_fn(*w) for w in grid.tiles())
        for (r0, c0, rows, cols), res in zip(grid.tiles(), src):
            for key, sp in specs.items():
                a = np.asarray(res[key]).astype(sp.dtype, copy=False)
                dsts[key].write(a[None] if a.ndim == 2 else a, window=Window(c0, r0, cols, rows))
        for key, sp in specs.items():
            dst = dsts[key]
            descs = [sp.description] * sp.bands if isinstance(sp.description, str) else list(sp.description)
            for b in range(sp.bands):
                if descs[b]:
                    dst.set_band_description(b + 1, descs[b])
                if sp.unit:
                    dst.update_tags(b + 1, unit=sp.unit)
            if sp.unit:
                dst.units = tuple([sp.unit] * sp.bands)
            if sp.scale is not None:
                dst.scales = tuple([float(sp.scale)] * sp.bands)
                dst.offsets = tuple([float(sp.offset or 0.0)] * sp.bands)
            if sp.tags:
                dst.update_tags(**{k: str(v) for k, v in sp.tags.items()})
            dst.close()
        for key, sp in specs.items():
            fd, tmp2 = make_temp(sp.path, suffix=".cog.tif")
            tmp2 = str(tmp2)
            os.close(fd)
            try:
                rasterio.shutil.copy(tmps[key], tmp2, driver="COG", COMPRESS="DEFLATE", OVERVIEWS="AUTO",
                                     OVERVIEW_RESAMPLING=sp.resampling.upper(), BLOCKSIZE=256, BIGTIFF="IF_SAFER")
                os.replace(tmp2, sp.path)
            finally:
                if os.path.exists(tmp2):
                    os.unlink(tmp2)
    except _raster_errors() as exc:
        raise DataFileError(f"{', '.join(str(sp.path) for sp in specs.values())}: cannot write GeoTIFF "
                            f"({_gdal_reason(exc)}; a full disk?)") from None
    except OSError as exc:
        raise DataFileError(f"{', '.join(str(sp.path) for sp in specs.values())}: cannot write GeoTIFF "
                            f"({exc.strerror or exc})") from None
    finally:
        for key, d in dsts.items():
            try:
                d.close()
            except Exception:
                pass
        for t in tmps.values():
            try:
                os.unlink(t)
            except OSError:
                pass


def write_cog(path, grid: Grid, dtype, tile_fn: Callable[[int, int, int, int], np.ndarray], *, crs=None,
              nodata=None, unit: str = "", description: str | list[str] = "", bands: int = 1,
              tags: dict | None = None, scale: float | None = None, offset: float | None = None,
              resampling: str = "average") -> Path:
    """Write one raster tile by tile as a COG with overviews (see :func:`write_cogs`).

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
    spec = RasterSpec(Path(path), dtype, bands, nodata, unit, description, tags, scale, offset, resampling)
    write_cogs(grid, {"a": spec}, lambda *w: {"a": tile_fn(*w)}, crs=crs)
    return Path(path)


def _gdal_reason(exc: BaseException) -> str:
    """The GDAL message behind a rasterio error ("Read failed. See previous exception" names none): the chained
    cause's text when there is one."""
    parts = [f"{type(exc).__name__}: {exc}"]
    cause = exc.__cause__ or exc.__context__
    if cause is not None and str(cause) and str(cause) not in str(exc):
        parts.insert(0, str(cause))
    return "; ".join(parts)


def _raster_errors() -> tuple:
    """The exception classes rasterio and GDAL raise on damaged files or a full disk."""
    import rasterio.errors

    try:
        from rasterio._err import CPLE_BaseError
    except ImportError:  # pragma: no cover - another rasterio layout
        return (rasterio.errors.RasterioError,)
    return (rasterio.errors.RasterioError, CPLE_BaseError)


def check_north_up(src, path, what: str = "raster") -> Grid:
    """The :class:`Grid` of an open rasterio dataset, or :class:`DataFileError` naming the file and the transform when
    it is not a north-up grid of square cells (rotated, sheared, south-up, mirrored, not georeferenced)."""
    tr = src.transform
    terms = tuple(float(v) for v in tuple(tr)[:6])
    if src.crs is None and tr.is_identity:
        raise DataFileError(f"{path}: the {what} has no georeferencing (no geotransform, no CRS); expected a GeoTIFF "
                            "with a north-up transform in the survey's CRS")
    if not all(np.isfinite(terms)):
        raise DataFileError(f"{path}: the {what}'s transform {terms} has non-finite terms; expected a north-up transform")
    if abs(tr.b) > 1e-12 * max(1.0, abs(tr.a)) or abs(tr.d) > 1e-12 * max(1.0, abs(tr.e)):
        raise DataFileError(f"{path}: the {what} is rotated or sheared (transform {terms}, rotation terms b = {tr.b:g}, "
                            f"d = {tr.d:g}); expected a north-up grid (resample it, e.g. gdalwarp -t_srs with the same CRS)")
    if tr.e >= 0:
        raise DataFileError(f"{path}: the {what}'s rows run south-up (pixel height {tr.e:g} >= 0 in transform {terms}); "
                            "expected a north-up grid with a negative pixel height (gdalwarp writes one)")
    if tr.a <= 0:
        raise DataFileError(f"{path}: the {what}'s columns run westwards (pixel width {tr.a:g} <= 0 in transform "
                            f"{terms}); expected a north-up grid with a positive pixel width")
    if abs(abs(tr.a) - abs(tr.e)) > 1e-9 * abs(tr.a):
        raise DataFileError(f"{path}: the {what}'s cells are {tr.a:g} x {-tr.e:g} m; expected square cells")
    return Grid(tr.c, tr.f, tr.a, src.width, src.height)


@dataclass(frozen=True)
class RasterInfo:
    """What :func:`inspect_raster` found: the grid, the CRS, the finite heights' range and count."""

    path: str
    grid: Grid
    crs: str | None
    zmin: float
    zmax: float
    finite: int


def inspect_raster(path, what: str = "DSM", *, max_cells: int | None = None, band: int = 1) -> RasterInfo:
    """Check a height raster before any work and describe it: readable, north-up with square cells
    (:func:`check_north_up`), at least 2 x 2 cells, at most the cell cap (:func:`~thermogrammetry.io.limits.check_cells`),
    finite heights somewhere and no infinite one. Read block by block (memory bounded by a block).

    Raises
    ------
    DataFileError
        Naming the file, the value found and what was expected.
    """
    import rasterio

    from ..io.limits import check_cells

    p = Path(path)
    if not p.exists():
        raise DataFileError(f"{what} {path}: no such file")
    import warnings

    try:
        with warnings.catch_warnings():  # an ungeoreferenced file is reported below, not as a rasterio warning
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            src = rasterio.open(p)
        with src:
            if src.count < band:
                raise DataFileError(f"{path}: the {what} has {src.count} band(s); expected band {band} with heights")
            if src.width < 2 or src.height < 2:
                raise DataFileError(f"{path}: the {what} is {src.width} x {src.height} cell(s); expected at least 2 x 2 "
                                    "cells of heights")
            check_cells(src.width, src.height, f"{path}", cap=max_cells, what=what)
            g = check_north_up(src, path, what)
            crs = src.crs.to_string() if src.crs else None
            zmin, zmax, finite, inf, first_inf = np.inf, -np.inf, 0, 0, None
            for _, win in src.block_windows(band):
                a = src.read(band, window=win, masked=True)
                v = np.asarray(a.astype(np.float64).filled(np.nan))
                ok = np.isfinite(v)
                if ok.any():
                    finite += int(ok.sum())
                    zmin, zmax = min(zmin, float(v[ok].min())), max(zmax, float(v[ok].max()))
                bad = np.isinf(v)
                if bad.any():
                    inf += int(bad.sum())
                    if first_inf is None:
                        r, c = np.argwhere(bad)[0]
                        first_inf = (int(r + win.row_off), int(c + win.col_off), float(v[r, c]))
    except _raster_errors() as exc:
        raise DataFileError(f"{what} {path}: cannot be read as a GeoTIFF ({_gdal_reason(exc)}); expected a complete "
                            "GeoTIFF (a truncated or damaged file?)") from None
    if inf:
        r, c, val = first_inf
        raise DataFileError(f"{path}: the {what} holds {inf} infinite height(s), the first at row {r}, column {c} "
                            f"({val}); expected finite heights in metres (NaN or nodata where there is none)")
    if not finite:
        raise DataFileError(f"{path}: the {what} has no finite height (all {g.width * g.height} cells are nodata or "
                            "NaN); expected heights in metres")
    return RasterInfo(str(path), g, crs, float(zmin), float(zmax), int(finite))


def read_raster(path, band: int = 1, *, max_cells: int | None = None) -> tuple[np.ndarray, Grid, str | None, dict]:
    """A whole band as float64 (nodata → NaN), its :class:`Grid`, CRS string and tags (with ``unit``).

    Refused before reading: a transform that is not north-up (:func:`check_north_up`), more cells than the cap
    (``max_cells``, :func:`~thermogrammetry.io.limits.check_cells`)."""
    import rasterio

    from ..io.limits import check_cells

    try:
        with rasterio.open(path) as src:
            check_cells(src.width, src.height, f"{path}", cap=max_cells)
            g = check_north_up(src, path)
            a = src.read(band, masked=True).astype(np.float64).filled(np.nan)
            crs = src.crs.to_string() if src.crs else None
            tags = dict(src.tags())
            tags.update(src.tags(band))
            if src.units and src.units[band - 1]:
                tags.setdefault("unit", src.units[band - 1])
    except _raster_errors() as exc:
        raise DataFileError(f"{path}: cannot read GeoTIFF ({_gdal_reason(exc)}); expected a DSM or product GeoTIFF") from None
    return a, g, crs, tags


def read_window(path, r0, c0, rows, cols, band: int = 1) -> np.ndarray:
    """A window of a band as float64 with nodata → NaN; cells outside the raster are NaN."""
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(path) as src:
        a = src.read(band, window=Window(c0, r0, cols, rows), boundless=True, masked=True)
        return a.astype(np.float64).filled(np.nan)
