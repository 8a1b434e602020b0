"""Point clouds with the exact frame value of every point: LAS 1.4 (laspy) and binary PLY, written in chunks.

Every point carries the value of its source frame at its pixel, copied (not resampled): a float
``temperature_k`` extra dimension for kelvin frames, ``raw_counts`` for raw sensor counts (never labelled
as a temperature), nothing for display-number frames (geometry only). Also: unit normal (``normal_x/y/z``; 0, 0, 0 where the depth map had no neighbours to estimate it),
number of consistent views (``views``) and the source image index (``source_image``; the lookup table of
names is in ``dense.json``). LAS coordinates are scaled integers (1 mm) about an offset; the CRS is written
as a WKT VLR. PLY is binary little-endian with double coordinates (read by plyfile, CloudCompare, MeshLab).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .._atomic import make_temp

__all__ = ["value_dimension", "CloudWriter"]


def value_dimension(unit: str) -> str | None:
    """Name of the per-point value dimension for a frame unit: ``temperature_k``, ``raw_counts`` or None."""
    return {"K": "temperature_k", "counts": "raw_counts"}.get(str(unit))


class CloudWriter:
    """Write LAS and PLY side by side from chunks of :data:`thermogrammetry.dense.fusion.POINT_DTYPE` records.

    The PLY vertex count is patched into a fixed-width header at :meth:`close`; both files are written to
    temporary names and renamed into place at the end (atomic).
    """

    def __init__(self, las_path, ply_path, *, unit: str, crs: str | None, offset_xyz, scale_m: float = 0.001):
        import laspy

        self.las_path, self.ply_path = Path(las_path), Path(ply_path)
        self.dim = value_dimension(unit)
        hdr = laspy.LasHeader(point_format=6, version="1.4")
        extra = [laspy.ExtraBytesParams(name=n, type=np.float32) for n in ("normal_x", "normal_y", "normal_z")]
        extra += [laspy.ExtraBytesParams(name="views", type=np.uint8),
                  laspy.ExtraBytesParams(name="source_image", type=np.int32)]
        if self.dim:
            extra.insert(0, laspy.ExtraBytesParams(name=self.dim, type=np.float32,
                                                   description="kelvin" if self.dim == "temperature_k" else "raw sensor counts"))
        hdr.add_extra_dims(extra)
        hdr.offsets = np.round(np.asarray(offset_xyz, float), 0)
        hdr.scales = np.array([scale_m] * 3)
        if crs:
            import pyproj

            hdr.add_crs(pyproj.CRS.from_user_input(crs))
        self.header = hdr
        self.las_path.parent.mkdir(parents=True, exist_ok=True)
        fd, self._las_tmp = make_temp(self.las_path)
        self._las_tmp = str(self._las_tmp)
        os.close(fd)
        self._las = laspy.open(self._las_tmp, mode="w", header=hdr)
        fd, self._ply_tmp = make_temp(self.ply_path)
        self._ply_tmp = str(self._ply_tmp)
        self._ply = os.fdopen(fd, "wb")
        props = [("double", "x"), ("double", "y"), ("double", "z")]
        if self.dim:
            props.append(("float", self.dim))
        props += [("float", "nx"), ("float", "ny"), ("float", "nz"), ("uchar", "views"), ("int", "source_image")]
        self._ply_props = props
        self._header_text = lambda n: ("ply\nformat binary_little_endian 1.0\ncomment thermogrammetry dense cloud"
                                       + (f"\ncomment crs {crs}" if crs else "") + (f"\ncomment unit {unit}")
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
        for name, v in ((self.dim, pts["value"] if self.dim else None), ("normal_x", pts["nx"]), ("normal_y", pts["ny"]),
                        ("normal_z", pts["nz"]), ("views", pts["views"]), ("source_image", pts["source"])):
            if name and len(v):
                lo, hi = np.nanmin(v), np.nanmax(v)
                r = self._ranges.setdefault(name, [lo, hi])
                r[0], r[1] = min(r[0], lo), max(r[1], hi)
        self._las.write_points(rec)
        out = np.zeros(n, self._ply_dtype)
        for name in ("x", "y", "z"):
            out[name] = pts[name]
        if self.dim:
            out[self.dim] = pts["value"]
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
