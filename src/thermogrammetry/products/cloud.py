"""Point clouds with the exact frame value of every point: LAS 1.4 or 1.2, or LAZ (laspy, lazrs), and binary PLY,
written in chunks.

Every point carries the value of its source frame at its pixel, copied (not resampled): a float
``temperature_k`` extra dimension for kelvin frames, ``raw_counts`` for raw sensor counts (never labelled
as a temperature), nothing for display-number frames (geometry only). Also: unit normal (``normal_x/y/z``; 0, 0, 0 where the depth map had no neighbours to estimate it),
number of consistent views (``views``) and the source image index (``source_image``; the lookup table of
names is in ``dense.json``). LAS coordinates are scaled integers (1 mm) about an offset.

For viewers that ignore extra bytes, every LAS point also has an RGB colour from the thermal palette
(:data:`~thermogrammetry.products.qml.THERMAL_PALETTE`, the ortho's QGIS style) and an intensity from its
value, both over the value limits given to the writer (``value_limits``: the 2nd and 98th percentiles of the
cloud's values in ``dense``; intensity ``= round(65535 · (value − lo) / (hi − lo))``, clipped). LAS 1.4
(default): point format 7, the CRS as an OGC WKT1 VLR (the LAS 1.4 specification's WKT; GeoTIFF keys are not
allowed with formats 6-10). LAS 1.2 (``las_version="1.2"``, for readers that refuse 1.4): point format 3, the
CRS as GeoTIFF keys (GeoKeyDirectory VLR); the extra bytes are kept (readers of 1.2 skip them). LAZ
(``laz=True``): the same records compressed by lazrs (``cloud.laz``).

PLY is binary little-endian, coordinates in double **relative to the stated offset** (``comment offset x y z``
in the header, the LAS offset, also in ``dense.json``: a float32 viewer keeps mm precision); the value is also
stored as ``scalar_<name>`` (and the view count as ``scalar_views``), the names CloudCompare loads as scalar
fields, and the palette colour as ``red``/``green``/``blue`` (read by plyfile, CloudCompare, MeshLab).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dataclasses import dataclass

from .._atomic import make_temp
from ..errors import ConfigError

__all__ = ["value_dimension", "CloudWriter", "CloudOptions", "palette_rgb16"]


@dataclass(frozen=True)
class CloudOptions:
    """Cloud file options: ``laz`` (LAZ instead of LAS), ``las_version`` ("1.4": point format 7; "1.2": point
    format 3)."""

    laz: bool = False
    las_version: str = "1.4"

    def __post_init__(self):
        v = str(self.las_version).strip()
        if v not in ("1.4", "1.2"):
            raise ConfigError(f"--las-version {self.las_version!r}: expected 1.4 or 1.2")
        object.__setattr__(self, "las_version", v)

    @property
    def las_name(self) -> str:
        return "cloud.laz" if self.laz else "cloud.las"


def palette_rgb16(values, lo: float, hi: float) -> np.ndarray:
    """(N, 3) uint16 RGB (LAS scale 0..65535) of values on the thermal palette between ``lo`` and ``hi``
    (clipped; NaN → black)."""
    from .qml import THERMAL_PALETTE

    pos = np.array([p for p, _ in THERMAL_PALETTE])
    cols = np.array([[int(c[k:k + 2], 16) for k in (1, 3, 5)] for _, c in THERMAL_PALETTE], float)
    t = _unit_scale(values, lo, hi)
    rgb = np.stack([np.interp(t, pos, cols[:, k]) for k in range(3)], axis=1)
    rgb[~np.isfinite(np.asarray(values, float))] = 0
    return np.round(rgb * 257.0).astype(np.uint16)


def _unit_scale(values, lo, hi) -> np.ndarray:
    v = np.asarray(values, float)
    span = float(hi) - float(lo)
    t = (v - float(lo)) / span if span > 0 else np.full(v.shape, 0.5)
    return np.clip(np.nan_to_num(t, nan=0.0), 0.0, 1.0)


def value_dimension(unit: str) -> str | None:
    """Name of the per-point value dimension for a frame unit: ``temperature_k``, ``raw_counts`` or None."""
    return {"K": "temperature_k", "counts": "raw_counts"}.get(str(unit))


class CloudWriter:
    """Write LAS and PLY side by side from chunks of :data:`thermogrammetry.dense.fusion.POINT_DTYPE` records.

    The PLY vertex count is patched into a fixed-width header at :meth:`close`; both files are written to
    temporary names and renamed into place at the end (atomic).
    """

    def __init__(self, las_path, ply_path, *, unit: str, crs: str | None, offset_xyz, scale_m: float = 0.001,
                 options: CloudOptions | None = None, value_limits=None):
        import laspy

        self.options = opts = options or CloudOptions()
        las_path = Path(las_path)
        if opts.laz and las_path.suffix.lower() == ".las":
            las_path = las_path.with_suffix(".laz")
        self.las_path, self.ply_path = las_path, Path(ply_path)
        self.files = [self.las_path.name, self.ply_path.name]
        self.dim = value_dimension(unit)
        self.value_limits = (0.0, 1.0) if value_limits is None else (float(value_limits[0]), float(value_limits[1]))
        v14 = opts.las_version == "1.4"
        hdr = laspy.LasHeader(point_format=7 if v14 else 3, version=opts.las_version)
        extra = [laspy.ExtraBytesParams(name=n, type=np.float32) for n in ("normal_x", "normal_y", "normal_z")]
        extra += [laspy.ExtraBytesParams(name="views", type=np.uint8),
                  laspy.ExtraBytesParams(name="source_image", type=np.int32)]
        if self.dim:
            extra.insert(0, laspy.ExtraBytesParams(name=self.dim, type=np.float32,
                                                   description="kelvin" if self.dim == "temperature_k" else "raw sensor counts"))
        hdr.add_extra_dims(extra)
        hdr.offsets = np.round(np.asarray(offset_xyz, float), 0)
        hdr.scales = np.array([scale_m] * 3)
        self.ply_offset = tuple(float(o) for o in hdr.offsets)
        if crs:
            import pyproj
            from pyproj.enums import WktVersion

            c = pyproj.CRS.from_user_input(crs)
            if v14:  # OGC WKT1 (the LAS 1.4 specification's), not pyproj's default WKT2
                from laspy.vlrs.known import WktCoordinateSystemVlr

                hdr.vlrs.append(WktCoordinateSystemVlr(c.to_wkt(WktVersion.WKT1_GDAL)))
                hdr.global_encoding.wkt = True
            else:
                hdr.add_crs(c)  # GeoKeyDirectory (+ ascii/double params) VLRs
        self.header = hdr
        self.las_path.parent.mkdir(parents=True, exist_ok=True)
        fd, self._las_tmp = make_temp(self.las_path)
        self._las_tmp = str(self._las_tmp)
        os.close(fd)
        if opts.laz:
            self._las = laspy.open(self._las_tmp, mode="w", header=hdr, do_compress=True,
                                   laz_backend=laspy.LazBackend.Lazrs)
        else:
            self._las = laspy.open(self._las_tmp, mode="w", header=hdr)
        fd, self._ply_tmp = make_temp(self.ply_path)
        self._ply_tmp = str(self._ply_tmp)
        self._ply = os.fdopen(fd, "wb")
        props = [("double", "x"), ("double", "y"), ("double", "z")]
        if self.dim:
            props.append(("float", self.dim))
        props += [("float", "nx"), ("float", "ny"), ("float", "nz"), ("uchar", "views"), ("int", "source_image")]
        if self.dim:
            props.append(("float", f"scalar_{self.dim}"))
        props += [("float", "scalar_views"), ("uchar", "red"), ("uchar", "green"), ("uchar", "blue")]
        self._ply_props = props
        ox, oy, oz = self.ply_offset
        self._header_text = lambda n: ("ply\nformat binary_little_endian 1.0\ncomment thermogrammetry dense cloud"
                                       + (f"\ncomment crs {crs}" if crs else "") + (f"\ncomment unit {unit}")
                                       + f"\ncomment offset {ox:.3f} {oy:.3f} {oz:.3f}"
                                       + "\ncomment x y z are relative to the offset (add it for the CRS's coordinates)"
                                       + f"\nelement vertex {n:>15d}\n"
                                       + "".join(f"property {t} {p}\n" for t, p in props) + "end_header\n")
        self._ply.write(self._header_text(0).encode("ascii"))
        self.count = 0
        self._ranges: dict = {}  # extra dimension -> [min, max] over every chunk written
        self._ply_dtype = np.dtype([(p, {"double": "<f8", "float": "<f4", "uchar": "u1", "int": "<i4"}[t]) for t, p in props])

    def write(self, pts) -> None:
        import laspy

        n = len(pts)
        if n == 0:
            return
        rec = laspy.ScaleAwarePointRecord.zeros(n, header=self.header)
        rec.x, rec.y, rec.z = pts["x"], pts["y"], pts["z"]
        if self.dim:
            rec[self.dim] = pts["value"]
        rec["normal_x"], rec["normal_y"], rec["normal_z"] = pts["nx"], pts["ny"], pts["nz"]
        rec["views"] = pts["views"]
        rec["source_image"] = pts["source"]
        rgb = palette_rgb16(pts["value"], *self.value_limits)
        rec.red, rec.green, rec.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
        rec.intensity = np.round(65535.0 * _unit_scale(pts["value"], *self.value_limits)).astype(np.uint16)
        for name, v in ((self.dim, pts["value"] if self.dim else None), ("normal_x", pts["nx"]), ("normal_y", pts["ny"]),
                        ("normal_z", pts["nz"]), ("views", pts["views"]), ("source_image", pts["source"])):
            if name and len(v):
                lo, hi = np.nanmin(v), np.nanmax(v)
                r = self._ranges.setdefault(name, [lo, hi])
                r[0], r[1] = min(r[0], lo), max(r[1], hi)
        self._las.write_points(rec)
        out = np.zeros(n, self._ply_dtype)
        for name, o in zip(("x", "y", "z"), self.ply_offset):
            out[name] = pts[name] - o
        if self.dim:
            out[self.dim] = pts["value"]
            out[f"scalar_{self.dim}"] = pts["value"]
        out["scalar_views"] = pts["views"]
        out["red"], out["green"], out["blue"] = (rgb[:, 0] // 257), (rgb[:, 1] // 257), (rgb[:, 2] // 257)
        out["nx"], out["ny"], out["nz"] = pts["nx"], pts["ny"], pts["nz"]
        out["views"] = pts["views"]
        out["source_image"] = pts["source"]
        self._ply.write(out.tobytes())
        self.count += n

    def close(self) -> None:
        self._las.close()
        _patch_extra_bytes_ranges(self._las_tmp, self._ranges)
        self._ply.seek(0)
        self._ply.write(self._header_text(self.count).encode("ascii"))
        self._ply.flush()
        os.fsync(self._ply.fileno())
        self._ply.close()
        os.replace(self._las_tmp, self.las_path)
        os.replace(self._ply_tmp, self.ply_path)

    def abort(self) -> None:
        for f in (self._las, self._ply):
            try:
                f.close()
            except Exception:
                pass
        for t in (self._las_tmp, self._ply_tmp):
            try:
                os.unlink(t)
            except OSError:
                pass


# LAS 1.4 extra-bytes descriptor (R14 §2.6.2, 192 bytes): reserved u2, data_type u1, options u1, name 32s,
# unused 4, no_data 24, min 24, max 24, scale 24, offset 24, description 32. Options bit 1 = min, bit 2 = max.
_EB_FLOAT, _EB_SIGNED = {9, 10}, {2, 4, 6, 8}


def _patch_extra_bytes_ranges(path, ranges: dict) -> None:
    """Write the min/max of every extra dimension over the whole cloud into the LAS file's extra-bytes VLR.

    laspy fills these fields from the points it holds when the header is written, which for a file written
    in chunks is not the whole cloud (measured: ``temperature_k`` 280-304 K written in three chunks was
    described as 280-300 K). The VLR is patched in place; its size does not change.
    """
    import struct

    with open(path, "r+b") as f:
        head = f.read(375)
        header_size = struct.unpack_from("<H", head, 94)[0]
        n_vlr = struct.unpack_from("<I", head, 100)[0]
        pos = header_size
        for _ in range(n_vlr):
            f.seek(pos)
            vh = f.read(54)
            user_id = vh[2:18].rstrip(b"\0")
            record_id, length = struct.unpack_from("<HH", vh, 18)
            if user_id == b"LASF_Spec" and record_id == 4:
                for k in range(length // 192):
                    at = pos + 54 + 192 * k
                    f.seek(at)
                    d = bytearray(f.read(192))
                    name = bytes(d[4:36]).rstrip(b"\0").decode("ascii", "replace")
                    if name not in ranges:
                        continue
                    dtype = d[2]
                    fmt = "<d" if dtype in _EB_FLOAT else ("<q" if dtype in _EB_SIGNED else "<Q")
                    lo, hi = ranges[name]
                    cast = float if fmt == "<d" else int
                    d[3] |= 0b110
                    d[64:88] = struct.pack(fmt, cast(lo)) + bytes(16)
                    d[88:112] = struct.pack(fmt, cast(hi)) + bytes(16)
                    f.seek(at)
                    f.write(bytes(d))
            pos += 54 + length
