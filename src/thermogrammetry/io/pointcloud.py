"""Point-cloud readers for ``mesh``: LAS/LAZ (laspy, lazrs), PLY (plyfile), plain XYZ text, E57 (pye57, optional),
and the output folder of ``dense``; read in chunks, with the file's CRS and normals where it has them.

- **LAS/LAZ**: scaled coordinates as laspy applies them; the CRS from the WKT or GeoTIFF-keys VLR
  (``header.parse_crs()``); normals from extra dimensions ``normal_x/y/z`` (as ``dense`` writes them) or ``nx/ny/nz``.
- **PLY** (binary or ASCII): ``x y z`` (float or double) plus, when the header says ``comment offset X Y Z`` (as
  ``dense`` and ``mesh`` write it), that offset; ``comment crs ...`` gives the CRS; ``nx ny nz`` the normals.
- **XYZ** (``.xyz``, ``.txt``): one point a line, ``x y z`` separated by spaces, tabs, commas or semicolons; further
  columns (colour, intensity) are ignored; lines starting with ``#`` or ``//`` and blank lines are skipped. No CRS.
- **E57**: every scan of the file, in the file's common frame (each scan's pose applied), through ``pye57`` when it
  is installed (``pip install pye57``); without it an ``.e57`` is refused with that instruction. No CRS.
- **DENSE_DIR** (a folder with ``dense.json``): its ``cloud.ply`` (or ``cloud.las``/``cloud.laz``), the CRS of
  ``dense.json`` (``null`` = the survey's local frame).

A point's normal of (0, 0, 0) means none (``dense`` writes that where a depth map had no neighbours).
"""

from __future__ import annotations

import io as _io
import itertools
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError, CorruptFileError, DataFileError, UnsupportedFormatError

__all__ = ["CLOUD_SUFFIXES", "CloudSource", "open_cloud", "resolve_crs"]

#: the suffixes ``mesh`` reads (a folder with dense.json besides)
CLOUD_SUFFIXES = (".las", ".laz", ".ply", ".e57", ".xyz", ".txt")

_EXPECTED = "a cloud file (.las, .laz, .ply, .e57, .xyz) or the output folder of `thermogrammetry dense` (with dense.json)"


@dataclass
class CloudSource:
    """An opened cloud: ``path``, ``kind`` (las, ply, xyz, e57), ``count`` (None until read for XYZ), ``crs`` as
    the file states it (None: none stated; for a dense folder, dense.json's value), ``crs_stated`` (the file or
    dense.json names its CRS, possibly as null = a local frame), ``normals`` (the file carries normals)."""

    path: Path
    kind: str
    count: int | None
    crs: str | None
    crs_stated: bool
    normals: bool
    _reader: object = None

    def chunks(self, n: int = 1_000_000):
        """Yield ``(xyz (m, 3) float64, normals (m, 3) float32 or None)`` of at most ``n`` points at a time."""
        yield from self._reader(n)


def resolve_crs(file_crs: str | None, given: str | None, where: str) -> str | None:
    """The CRS of the mesh: ``given`` (``--crs``) or the file's; refused when they differ, when ``given`` is not a
    CRS, or when it is geographic (coordinates in degrees are not metres). Returned as ``EPSG:N`` when it has one."""
    import pyproj

    def parse(text, label):
        try:
            return pyproj.CRS.from_user_input(text)
        except Exception as exc:  # noqa: BLE001 - pyproj raises its own CRSError and others
            raise ConfigError(f"{label} {text!r}: not a coordinate reference system pyproj knows ({exc}); "
                              "expected e.g. EPSG:32633") from None
    g = parse(given, "--crs") if given is not None else None
    f = parse(file_crs, f"{where}: CRS") if file_crs else None
    if g is not None and f is not None and not g.equals(f, ignore_axis_order=True):
        raise ConfigError(f"--crs {given}: {where} states its CRS as {_name(f)}; expected the same CRS (reproject the "
                          "cloud, or leave --crs out to use the file's)")
    c = g if g is not None else f
    if c is None:
        return None
    if c.is_geographic:
        raise ConfigError(f"{where}: CRS {_name(c)} is geographic (degrees); expected a projected CRS in metres, the "
                          "survey's (e.g. its UTM zone)")
    return _name(c)


def _name(c) -> str:
    e = c.to_epsg()
    return f"EPSG:{e}" if e else c.to_wkt()


def open_cloud(path) -> CloudSource:
    """Open a cloud file or a ``dense`` output folder (see the module docstring); refuses, naming the path, what
    cannot be read."""
    p = Path(path)
    if p.is_dir():
        return _open_dense_dir(p)
    if not p.exists():
        raise DataFileError(f"{p}: no such file or folder; expected {_EXPECTED}")
    suf = p.suffix.lower()
    if suf in (".las", ".laz"):
        return _open_las(p)
    if suf == ".ply":
        return _open_ply(p)
    if suf in (".xyz", ".txt"):
        return _open_xyz(p)
    if suf == ".e57":
        return _open_e57(p)
    raise UnsupportedFormatError(f"{p}: unknown cloud suffix {p.suffix!r}; expected {_EXPECTED}")


def _open_dense_dir(d: Path) -> CloudSource:
    j = d / "dense.json"
    if not j.is_file():
        raise DataFileError(f"{d}: a folder without dense.json; expected {_EXPECTED}")
    try:
        meta = json.loads(j.read_text(encoding="utf-8"))
    except (OSError, UnicodeError, ValueError) as exc:
        raise CorruptFileError(f"{j}: not readable JSON ({exc}); expected the dense.json that `dense` writes") from None
    if not isinstance(meta, dict):
        raise CorruptFileError(f"{j}: expected a JSON object (dense.json), got {type(meta).__name__}")
    files = meta.get("cloud_files") or ["cloud.ply", "cloud.las", "cloud.laz"]
    order = sorted((str(f) for f in files), key=lambda f: (not f.endswith(".ply"), f))
    for f in order:
        c = d / Path(f).name
        if c.is_file():
            src = open_cloud(c)
            src.crs = meta.get("crs") or None
            src.crs_stated = "crs" in meta
            return src
    raise DataFileError(f"{d}: dense.json lists {files} but none of them is in the folder; expected the cloud "
                        "files `dense` wrote")


def _open_las(p: Path) -> CloudSource:
    import laspy

    try:
        fh = laspy.open(str(p))
        hdr = fh.header
        fh.close()
    except Exception as exc:  # noqa: BLE001 - laspy raises several types for a damaged file
        raise CorruptFileError(f"{p}: cannot read as LAS/LAZ ({type(exc).__name__}: {exc})") from None
    crs = None
    try:
        c = hdr.parse_crs()
        crs = None if c is None else _name(c)
    except Exception:  # noqa: BLE001 - an unparseable CRS VLR is reported as no CRS
        crs = None
    names = set(hdr.point_format.dimension_names)
    nn = next((t for t in (("normal_x", "normal_y", "normal_z"), ("nx", "ny", "nz")) if set(t) <= names), None)

    def reader(n):
        try:
            with laspy.open(str(p)) as f:
                for pts in f.chunk_iterator(n):
                    xyz = np.stack([np.asarray(pts.x, float), np.asarray(pts.y, float), np.asarray(pts.z, float)], axis=1)
                    nrm = None if nn is None else np.stack([np.asarray(pts[k], np.float32) for k in nn], axis=1)
                    yield xyz, nrm
        except (laspy.errors.LaspyException, ValueError, OSError) as exc:
            raise CorruptFileError(f"{p}: LAS/LAZ point records cannot be read ({type(exc).__name__}: {exc}); "
                                   "a truncated or damaged file?") from None
    return CloudSource(p, "las", int(hdr.point_count), crs, crs is not None, nn is not None, reader)


def _open_ply(p: Path) -> CloudSource:
    from plyfile import PlyData

    try:
        ply = PlyData.read(str(p), mmap="r")
        vert = ply["vertex"]
        names = {q.name for q in vert.properties}
    except Exception as exc:  # noqa: BLE001 - plyfile raises PlyParseError, KeyError, ValueError...
        raise CorruptFileError(f"{p}: cannot read as PLY ({type(exc).__name__}: {exc}); expected a PLY with a "
                               "vertex element of x y z") from None
    if not {"x", "y", "z"} <= names:
        raise CorruptFileError(f"{p}: the PLY vertex element has {sorted(names)}; expected x y z")
    off = np.zeros(3)
    crs = None
    for c in ply.comments:
        w = c.split()
        if len(w) == 4 and w[0] == "offset":
            try:
                off = np.array([float(x) for x in w[1:]])
            except ValueError:
                raise CorruptFileError(f"{p}: header 'comment {c}': expected three numbers") from None
        elif len(w) >= 2 and w[0] == "crs":
            crs = " ".join(w[1:])
    has_n = {"nx", "ny", "nz"} <= names
    count = int(vert.count)

    def reader(n):
        try:
            data = vert.data
            for s in range(0, count, n):
                blk = data[s:s + n]
                xyz = np.stack([np.asarray(blk[k], float) for k in ("x", "y", "z")], axis=1) + off
                nrm = np.stack([np.asarray(blk[k], np.float32) for k in ("nx", "ny", "nz")], axis=1) if has_n else None
                yield xyz, nrm
        except (ValueError, OSError) as exc:
            raise CorruptFileError(f"{p}: PLY vertex data cannot be read ({exc}); a truncated file?") from None
    return CloudSource(p, "ply", count, crs, crs is not None, has_n, reader)


def _open_xyz(p: Path) -> CloudSource:
    def reader(n):
        try:
            fh = open(p, encoding="utf-8")
        except OSError as exc:
            raise DataFileError(f"{p}: cannot open ({exc.strerror or exc})") from None
        line_no = 0
        with fh:
            while True:
                try:
                    lines = list(itertools.islice(fh, n))
                except UnicodeDecodeError as exc:
                    raise CorruptFileError(f"{p}: not UTF-8 text after line {line_no} ({exc.reason}); expected lines "
                                           "of x y z numbers") from None
                if not lines:
                    return
                text = "".join(lines)
                line_no += len(lines)
                try:  # the fast path: numbers only (comment lines skipped by loadtxt)
                    a = np.loadtxt(_io.StringIO(text.replace(",", " ").replace(";", " ")), dtype=float, ndmin=2,
                                   comments=("#", "//"), usecols=(0, 1, 2))
                    if len(a):
                        yield a, None
                    continue
                except (ValueError, IndexError):
                    line_no -= len(lines)
                rows, nums = [], []
                for k, ln in enumerate(lines, line_no + 1):
                    s = ln.strip()
                    if not s or s.startswith("#") or s.startswith("//"):
                        continue
                    rows.append(k)
                    nums.append(s.replace(",", " ").replace(";", " ").replace("\t", " "))
                line_no += len(lines)
                if not nums:
                    continue
                try:
                    a = np.loadtxt(_io.StringIO("\n".join(" ".join(x.split()[:3]) for x in nums)),
                                   dtype=float, ndmin=2)
                except ValueError:
                    for r, x in zip(rows, nums):
                        w = x.split()
                        try:
                            if len(w) < 3:
                                raise ValueError
                            [float(v) for v in w[:3]]
                        except ValueError:
                            raise CorruptFileError(f"{p}, line {r}: {x[:60]!r}; expected at least three numbers "
                                                   "x y z") from None
                    raise CorruptFileError(f"{p}: lines {rows[0]}-{rows[-1]}: expected at least three numbers per "
                                           "line") from None
                if a.shape[1] < 3:
                    raise CorruptFileError(f"{p}, line {rows[0]}: {nums[0][:60]!r}; expected at least three numbers x y z")
                yield a[:, :3], None
    return CloudSource(p, "xyz", None, None, False, False, reader)


def _open_e57(p: Path) -> CloudSource:
    try:
        import pye57
    except ImportError:
        raise UnsupportedFormatError(f"{p}: reading E57 needs the pye57 package, which is not installed: pip install "
                                     "pye57 (or pip install 'thermogrammetry[e57]'); or convert the scan to LAS/LAZ or "
                                     "PLY") from None
    try:
        e = pye57.E57(str(p))
        counts = [int(e.get_header(i).point_count) for i in range(e.scan_count)]
    except Exception as exc:  # noqa: BLE001 - libE57 raises its own exceptions
        raise CorruptFileError(f"{p}: cannot read as E57 ({type(exc).__name__}: {exc})") from None

    def reader(n):
        for i in range(len(counts)):
            try:
                d = e.read_scan(i, ignore_missing_fields=True, transform=True)
            except Exception as exc:  # noqa: BLE001
                raise CorruptFileError(f"{p}: scan {i} cannot be read ({type(exc).__name__}: {exc})") from None
            xyz = np.stack([np.asarray(d[k], float) for k in ("cartesianX", "cartesianY", "cartesianZ")], axis=1)
            for s in range(0, len(xyz), n):
                yield xyz[s:s + n], None
    return CloudSource(p, "e57", int(sum(counts)), None, False, False, reader)
