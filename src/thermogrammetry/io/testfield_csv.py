"""CSV formats of the 3D test-field route: surveyed control points and image measurements.

Control file (metres)::

    id,X,Y,Z[,sX,sY,sZ]

Measurement file (pixels, OpenCV convention: (0, 0) is the centre of the top-left pixel,
``docs/conventions.md``)::

    image,id,x,y[,sx,sy]

A header row naming the columns is expected (any order, case-insensitive); a file without a header
is read positionally when its first row already holds numbers where coordinates belong. Blank lines
and lines starting with ``#`` are skipped. Separators: comma, semicolon or tab (from the header).

Every problem raises an error from :mod:`thermogrammetry.errors` naming the file (the ``source``
string) and the row (1-based line number in the file, the header being row 1): missing columns, non-numbers, non-positive standard
deviations, duplicate IDs, measurements of IDs that are not in the control file.

The ``parse_*`` functions work on text and a ``source`` name for messages (no file access).
Reading from disk: :func:`read_control_csv` and :func:`read_measurements_csv` read the file (UTF-8, a
byte-order mark is dropped) and pass its path as the source name, so every error names the file and
the row; a missing or unreadable file raises :class:`~thermogrammetry.errors.DataFileError`, a file
that is not UTF-8 text :class:`~thermogrammetry.errors.UnsupportedFormatError`.
"""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import CorruptFileError, DataFileError, UnsupportedFormatError

__all__ = [
    "ControlPoints",
    "Measurements",
    "parse_control_csv",
    "parse_measurements_csv",
    "check_measurement_ids", "read_control_csv", "read_measurements_csv", "read_text",
    "GnssPositions", "parse_gnss_csv", "read_gnss_csv", "Readings", "parse_readings_csv", "read_readings_csv"]

CONTROL_COLUMNS = ("id", "X", "Y", "Z")
CONTROL_OPTIONAL = ("sX", "sY", "sZ")
MEAS_COLUMNS = ("image", "id", "x", "y")
MEAS_OPTIONAL = ("sx", "sy")


@dataclass(frozen=True)
class ControlPoints:
    """Surveyed control points: ``ids`` (M,) str, ``xyz`` (M,3) m, ``std`` (M,3) m or None."""

    ids: tuple[str, ...]
    xyz: np.ndarray
    std: np.ndarray | None
    source: str = ""

    def index(self) -> dict[str, int]:
        return {k: i for i, k in enumerate(self.ids)}


@dataclass(frozen=True)
class Measurements:
    """Image measurements: per row ``image`` name, point ``id``, ``xy`` (N,2) px, ``std`` (N,2) px or None;
    ``lines`` (N,) are the 1-based line numbers in the source (for messages)."""

    image: tuple[str, ...]
    id: tuple[str, ...]
    xy: np.ndarray
    std: np.ndarray | None
    lines: tuple[int, ...]
    source: str = ""

    def images(self) -> list[str]:
        """Image names in order of first appearance."""
        return list(dict.fromkeys(self.image))


def _rows(text: str):
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines())]
    lines = [(n, ln) for n, ln in lines if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        return None, []
    first = lines[0][1]
    delim = "," if "," in first else (";" if ";" in first else ("\t" if "\t" in first else ","))
    out = []
    for n, ln in lines:
        row = next(csv.reader(io.StringIO(ln), delimiter=delim))
        out.append((n, [c.strip() for c in row]))
    return delim, out


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


# accepted alternative column names (surveyors' E,N,H; the synthetic scenes' long names)
_ALIASES = {
    ("control", "id"): ("name", "point"),
    ("control", "X"): ("E", "easting"), ("control", "Y"): ("N", "northing"), ("control", "Z"): ("H", "height"),
    ("control", "sX"): ("sE",), ("control", "sY"): ("sN",), ("control", "sZ"): ("sH",),
    ("measurements", "id"): ("name", "point"), ("measurements", "x"): ("x_px",), ("measurements", "y"): ("y_px",),
    ("gnss", "image"): ("name",),
    ("gnss", "X"): ("E", "easting"), ("gnss", "Y"): ("N", "northing"), ("gnss", "Z"): ("H", "height"),
    ("gnss", "sX"): ("sE",), ("gnss", "sY"): ("sN",), ("gnss", "sZ"): ("sH",),
}


def _header(rows, required, optional, source, what):
    """Column map name -> index, and the data rows."""
    n0, first = rows[0]
    coord_col = 2 if what == "measurements" else 1
    if len(first) > coord_col and _is_number(first[coord_col]):  # no header: positional
        cols = list(required) + list(optional)
        ncol = len(first)
        if ncol not in (len(required), len(required) + len(optional)):
            raise UnsupportedFormatError(
                f"{source}, row {n0}: {ncol} columns and no header row; expected "
                f"{','.join(required)}[,{','.join(optional)}]")
        return {c: i for i, c in enumerate(cols[:ncol])}, rows
    lower = [c.lower() for c in first]
    # case-insensitive, but X/x are different columns in neither file, so match on lower case
    cmap = {}
    for name in list(required) + list(optional):
        for alias in (name,) + _ALIASES.get((what, name), ()):
            if alias.lower() in lower:
                cmap[name] = lower.index(alias.lower())
                break
    missing = [c for c in required if c not in cmap]
    if missing:
        raise UnsupportedFormatError(
            f"{source}, row {n0}: missing column(s) {', '.join(missing)} in header {','.join(first)!r}; "
            f"expected {','.join(required)}[,{','.join(optional)}]")
    got_opt = [c for c in optional if c in cmap]
    if got_opt and len(got_opt) != len(optional):
        raise UnsupportedFormatError(
            f"{source}, row {n0}: standard deviation columns must come together ({', '.join(optional)}); "
            f"found only {', '.join(got_opt)}")
    return cmap, rows[1:]


def _num(row, cmap, col, n, source, unit, positive=False) -> float:
    i = cmap[col]
    if i >= len(row) or row[i] == "":
        raise CorruptFileError(f"{source}, row {n}: column {col} is missing; expected a number in {unit}")
    try:
        v = float(row[i])
    except ValueError:
        raise CorruptFileError(f"{source}, row {n}: {col} = {row[i]!r} is not a number; expected {unit}") from None
    if not math.isfinite(v):
        raise CorruptFileError(f"{source}, row {n}: {col} = {row[i]!r} is not finite; expected {unit}")
    if positive and v <= 0:
        raise CorruptFileError(f"{source}, row {n}: {col} = {row[i]!r} must be positive ({unit})")
    return v


def _text(row, cmap, col, n, source) -> str:
    i = cmap[col]
    if i >= len(row) or row[i] == "":
        raise CorruptFileError(f"{source}, row {n}: column {col} is empty")
    return row[i]



def _unique_id_rows(data, cmap, source):
    """``(row number, id, row)`` of every data row; a point id on two rows is an error naming both rows."""
    seen = {}
    for n, row in data:
        pid = _text(row, cmap, "id", n, source)
        if pid in seen:
            raise CorruptFileError(f"{source}, row {n}: duplicate point id {pid!r} (first on row {seen[pid]})")
        seen[pid] = n
        yield n, pid, row

def parse_control_csv(text: str, source: str = "control.csv") -> ControlPoints:
    """Parse ``id,X,Y,Z[,sX,sY,sZ]`` (metres). See the module docstring for the rules."""
    _, rows = _rows(text)
    if not rows:
        raise UnsupportedFormatError(f"{source}: empty file; expected a header id,X,Y,Z[,sX,sY,sZ] and one row per point")
    cmap, data = _header(rows, CONTROL_COLUMNS, CONTROL_OPTIONAL, source, "control")
    if not data:
        raise UnsupportedFormatError(f"{source}: no control points after the header")
    has_std = "sX" in cmap
    ids, xyz, std = [], [], []
    for n, pid, row in _unique_id_rows(data, cmap, source):
        ids.append(pid)
        xyz.append([_num(row, cmap, c, n, source, "metres") for c in ("X", "Y", "Z")])
        if has_std:
            std.append([_num(row, cmap, c, n, source, "metres", positive=True) for c in CONTROL_OPTIONAL])
    return ControlPoints(tuple(ids), np.array(xyz, float), np.array(std, float) if has_std else None, source)


def parse_measurements_csv(text: str, source: str = "measurements.csv") -> Measurements:
    """Parse ``image,id,x,y[,sx,sy]`` (pixels, OpenCV convention)."""
    _, rows = _rows(text)
    if not rows:
        raise UnsupportedFormatError(f"{source}: empty file; expected a header image,id,x,y[,sx,sy] and one row per measurement")
    cmap, data = _header(rows, MEAS_COLUMNS, MEAS_OPTIONAL, source, "measurements")
    if not data:
        raise UnsupportedFormatError(f"{source}: no measurements after the header")
    has_std = "sx" in cmap
    img, ids, xy, std, lines, seen = [], [], [], [], [], {}
    for n, row in data:
        im = _text(row, cmap, "image", n, source)
        pid = _text(row, cmap, "id", n, source)
        key = (im, pid)
        if key in seen:
            raise CorruptFileError(f"{source}, row {n}: point {pid!r} measured twice in image {im!r} (first on row {seen[key]})")
        seen[key] = n
        img.append(im)
        ids.append(pid)
        xy.append([_num(row, cmap, c, n, source, "pixels") for c in ("x", "y")])
        if has_std:
            std.append([_num(row, cmap, c, n, source, "pixels", positive=True) for c in MEAS_OPTIONAL])
        lines.append(n)
    return Measurements(tuple(img), tuple(ids), np.array(xy, float), np.array(std, float) if has_std else None,
                        tuple(lines), source)


@dataclass(frozen=True)
class GnssPositions:
    """Camera positions per image: ``image`` (M,) str, ``xyz`` (M,3) m, ``std`` (M,3) m or None."""

    image: tuple[str, ...]
    xyz: np.ndarray
    std: np.ndarray | None
    source: str = ""


def parse_gnss_csv(text: str, source: str = "gnss.csv") -> GnssPositions:
    """Parse ``image,X,Y,Z[,sX,sY,sZ]`` (metres, in the survey's CRS; ``E,N,H`` accepted for ``X,Y,Z``)."""
    _, rows = _rows(text)
    if not rows:
        raise UnsupportedFormatError(f"{source}: empty file; expected a header image,X,Y,Z[,sX,sY,sZ] and one row per image")
    cmap, data = _header(rows, ("image", "X", "Y", "Z"), CONTROL_OPTIONAL, source, "gnss")
    if not data:
        raise UnsupportedFormatError(f"{source}: no positions after the header")
    has_std = "sX" in cmap
    img, xyz, std, seen = [], [], [], {}
    for n, row in data:
        im = _text(row, cmap, "image", n, source)
        if im in seen:
            raise CorruptFileError(f"{source}, row {n}: image {im!r} listed twice (first on row {seen[im]})")
        seen[im] = n
        img.append(im)
        xyz.append([_num(row, cmap, c, n, source, "metres") for c in ("X", "Y", "Z")])
        if has_std:
            std.append([_num(row, cmap, c, n, source, "metres", positive=True) for c in CONTROL_OPTIONAL])
    return GnssPositions(tuple(img), np.array(xyz, float), np.array(std, float) if has_std else None, source)


def read_gnss_csv(path: str | os.PathLike) -> GnssPositions:
    """Read ``image,X,Y,Z[,sX,sY,sZ]``; see :func:`parse_gnss_csv`."""
    text, src = read_text(path)
    return parse_gnss_csv(text, src)


@dataclass(frozen=True)
class Readings:
    """Contact temperature readings: ``ids`` (M,) str, ``xy`` (M,2) m, ``z`` (M,) m or None, ``value`` (M,) in the
    readings' unit, ``std`` (M,) or None; ``lines`` (M,) the 1-based line numbers in the source (for messages)."""

    ids: tuple[str, ...]
    xy: np.ndarray
    z: np.ndarray | None
    value: np.ndarray
    std: np.ndarray | None
    lines: tuple[int, ...]
    source: str = ""


#: column names of a readings file (lower case), first the canonical one
READINGS_COLUMNS = {"id": ("id", "name", "point"), "X": ("x", "e", "easting"), "Y": ("y", "n", "northing"),
                    "Z": ("z", "h", "height"), "T": ("t", "temperature", "reading", "value"),
                    "sT": ("st", "sigma", "sigma_t", "std")}


def parse_readings_csv(text: str, source: str = "readings.csv") -> Readings:
    """Parse contact readings ``[id,]X,Y[,Z],T[,sT]`` (metres in the ortho's CRS; the temperature and its σ in one
    unit, > 0 for σ). A header row is required (the columns are optional in different combinations); without an
    ``id`` column the points are named by their row number."""
    _, rows = _rows(text)
    if not rows:
        raise UnsupportedFormatError(f"{source}: empty file; expected a header [id,]X,Y[,Z],T[,sT] and one row per reading")
    n0, first = rows[0]
    lower = [c.lower() for c in first]
    cmap = {k: lower.index(a) for k, names in READINGS_COLUMNS.items() for a in names[::-1] if a in lower}
    missing = [k for k in ("X", "Y", "T") if k not in cmap]
    if missing:
        hint = " (no header row? the first row holds numbers)" if first and _is_number(first[0]) else ""
        raise UnsupportedFormatError(
            f"{source}, row {n0}: missing column(s) {', '.join(missing)} in header {','.join(first)!r}{hint}; expected "
            "[id,]X,Y[,Z],T[,sT] (aliases E/N/H, temperature/reading/value, sigma)")
    data = rows[1:]
    if not data:
        raise UnsupportedFormatError(f"{source}: no readings after the header")
    ids, xy, z, val, std, lines, seen = [], [], [], [], [], [], {}
    for n, row in data:
        pid = _text(row, cmap, "id", n, source) if "id" in cmap else f"row{n}"
        if pid in seen:
            raise CorruptFileError(f"{source}, row {n}: duplicate point id {pid!r} (first on row {seen[pid]})")
        seen[pid] = n
        ids.append(pid)
        xy.append([_num(row, cmap, c, n, source, "metres") for c in ("X", "Y")])
        if "Z" in cmap:
            z.append(_num(row, cmap, "Z", n, source, "metres"))
        val.append(_num(row, cmap, "T", n, source, "a temperature"))
        if "sT" in cmap:
            std.append(_num(row, cmap, "sT", n, source, "the reading's standard deviation", positive=True))
        lines.append(n)
    return Readings(tuple(ids), np.array(xy, float), np.array(z, float) if z else None, np.array(val, float),
                    np.array(std, float) if std else None, tuple(lines), source)


def read_readings_csv(path: str | os.PathLike) -> Readings:
    """Read contact readings ``[id,]X,Y[,Z],T[,sT]``; see :func:`parse_readings_csv`."""
    text, src = read_text(path)
    return parse_readings_csv(text, src)


def check_measurement_ids(meas: Measurements, control: ControlPoints) -> np.ndarray:
    """Indices of the measured IDs into ``control``; an unknown ID raises naming file and line."""
    idx = control.index()
    out = np.empty(len(meas.id), dtype=int)
    for k, (pid, n) in enumerate(zip(meas.id, meas.lines)):
        j = idx.get(pid)
        if j is None:
            raise CorruptFileError(
                f"{meas.source}, row {n}: point id {pid!r} (image {meas.image[k]!r}) is not in the control file "
                f"{control.source or 'control.csv'}; known ids: {', '.join(control.ids[:8])}{' ...' if len(control.ids) > 8 else ''}")
        out[k] = j
    return out


def read_text(path: str | os.PathLike) -> tuple[str, str]:
    """Content of a UTF-8 text file and its path as a string (for messages).

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    text : str
    source : str
        ``str(path)``.
    """
    p = Path(path)
    try:
        return p.read_text(encoding="utf-8-sig"), str(p)
    except FileNotFoundError:
        raise DataFileError(f"{p}: no such file") from None
    except IsADirectoryError:
        raise DataFileError(f"{p}: is a folder; expected a CSV file") from None
    except UnicodeDecodeError as exc:
        raise UnsupportedFormatError(f"{p}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise DataFileError(f"{p}: cannot read ({exc.strerror or exc})") from None


def read_control_csv(path: str | os.PathLike) -> ControlPoints:
    """Read a control file ``id,X,Y,Z[,sX,sY,sZ]`` (metres); see
    :func:`parse_control_csv`."""
    text, src = read_text(path)
    return parse_control_csv(text, src)


def read_measurements_csv(path: str | os.PathLike) -> Measurements:
    """Read a measurement file ``image,id,x,y[,sx,sy]`` (pixels, OpenCV convention); see
    :func:`parse_measurements_csv`."""
    text, src = read_text(path)
    return parse_measurements_csv(text, src)
