"""The close-range workflow's input tables, parsed from text (callers read the files).

- ``control.csv``: ``id,X,Y,Z[,sX,sY,sZ]`` (m), one control point per row, and
- ``measurements.csv``: ``image,id,x,y[,sx,sy]`` (px, OpenCV origin: (0, 0) is the centre of the
  top-left pixel) for every image, optical and thermal — both read by the project's one parser of
  these formats, :mod:`thermogrammetry.io.testfield_csv`;
- ``planes.csv``: ``name,id1,id2,id3[,...]`` — a plane picked by 3 or more marked points; empty
  trailing cells are allowed.

Headers are required (case-insensitive); blank lines and lines starting with ``#`` are skipped.
Errors name the source, the row and the expected form.
"""

from __future__ import annotations

import csv
import io
import math

from ..errors import DataFileError, InvalidInputError
from ..io.testfield_csv import parse_control_csv, parse_measurements_csv

__all__ = ["parse_control", "parse_measurements", "parse_planes"]


def _rows(text: str, source: str):
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise DataFileError(f"{source}: empty file; expected a header row and data rows")
    reader = csv.reader(io.StringIO("\n".join(ln for _, ln in lines)))
    out = [[c.strip() for c in row] for row in reader]
    return [n for n, _ in lines], out


def _float(v: str, source: str, row: int, col: str) -> float:
    try:
        x = float(v)
    except ValueError:
        raise InvalidInputError(f"{source} row {row}: {col}={v!r} is not a number") from None
    if not math.isfinite(x):
        raise InvalidInputError(f"{source} row {row}: {col}={v!r}; expected a finite number")
    return x


def _header(head: list[str], want: list[str], source: str) -> list[int]:
    low = [h.lower() for h in head]
    idx = []
    for w in want:
        if w.lower() not in low:
            raise DataFileError(f"{source}: header {head} lacks column {w!r}; expected columns {','.join(want)}")
        idx.append(low.index(w.lower()))
    return idx


def parse_control(text: str, source: str = "control.csv") -> dict[str, tuple[float, float, float]]:
    """``id,X,Y,Z[,sX,sY,sZ]`` → {id: (X, Y, Z)} (m).

    The format and its checks are the project's one control-point CSV
    (:func:`thermogrammetry.io.testfield_csv.parse_control_csv`); this adapter keeps the coordinates.
    """
    ctl = parse_control_csv(text, source)
    return {pid: tuple(float(v) for v in xyz) for pid, xyz in zip(ctl.ids, ctl.xyz)}


def parse_measurements(text: str, source: str = "measurements.csv") -> list[tuple[str, str, float, float]]:
    """``image,id,x,y[,sx,sy]`` → list of (image, id, x, y) in px.

    The format and its checks are the project's one image-measurement CSV
    (:func:`thermogrammetry.io.testfield_csv.parse_measurements_csv`).
    """
    m = parse_measurements_csv(text, source)  # refuses a file without measurements
    return [(im, pid, float(x), float(y)) for im, pid, (x, y) in zip(m.image, m.id, m.xy)]


def parse_planes(text: str, source: str = "planes.csv") -> dict[str, tuple[str, ...]]:
    """``name,id1,id2,id3[,...]`` → {name: ids}; a plane needs at least 3 ids."""
    nums, rows = _rows(text, source)
    head = [h.lower() for h in rows[0]]
    if not head or head[0] != "name" or len(head) < 4:
        raise DataFileError(f"{source}: header {rows[0]}; expected name,id1,id2,id3[,...]")
    out: dict[str, tuple[str, ...]] = {}
    for n, r in zip(nums[1:], rows[1:]):
        name = r[0]
        ids = tuple(c for c in r[1:] if c)
        if not name:
            raise InvalidInputError(f"{source} row {n}: empty plane name")
        if name in out:
            raise InvalidInputError(f"{source} row {n}: plane {name!r} given twice")
        if len(ids) < 3:
            raise InvalidInputError(f"{source} row {n}: plane {name!r} has {len(ids)} point id(s) {list(ids)}; "
                                    "expected at least 3")
        if len(set(ids)) != len(ids):
            raise InvalidInputError(f"{source} row {n}: plane {name!r} repeats a point id: {list(ids)}")
        out[name] = ids
    if not out:
        raise DataFileError(f"{source}: no planes; expected rows name,id1,id2,id3")
    return out
