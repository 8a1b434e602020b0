"""Temperature matrices in CSV or NPY files, with an explicit unit.

A matrix file holds only numbers, so the unit must be declared: ``read_thermal(path, unit="C")``.  Without
it the reader refuses the file (:class:`ConfigError`) rather than guess between kelvin and °C.  CSV: comma,
semicolon, tab or whitespace separated rows of equal length; a first line that does not parse as numbers
is taken as a header and skipped; empty cells / ``nan`` are no-data.
"""

from __future__ import annotations

import io
import re
from pathlib import Path
from typing import Iterator

import numpy as np

from ..errors import ConfigError, CorruptFileError, UnsupportedFormatError
from ..radiometry.encoding import to_kelvin
from .limits import check_image_size
from .thermal import ReadOptions, ThermalImage, ThermalMetadata, register_reader

__all__ = ["read_matrix", "read_emissivity_table"]


def _need_unit(path: Path, opts: ReadOptions) -> str:
    if opts.unit is None:
        raise ConfigError(f"{path}: a temperature matrix carries no unit; pass unit='K' or unit='C' (--unit)")
    return opts.unit


def _parse_csv(path: Path, text: str) -> np.ndarray:
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        for sep in (",", ";", "\t", None):
            cells = s.split(sep) if sep else s.split()
            if len(cells) > 1 or sep is None:
                break
        try:
            vals = [float(c) if c.strip() else np.nan for c in cells]
        except ValueError:
            if not rows:  # header line
                continue
            raise CorruptFileError(f"{path}: line {lineno} has a non-numeric cell: {s[:80]!r}") from None
        if any(np.isinf(v) for v in vals):
            raise CorruptFileError(f"{path}: line {lineno} has an infinite value ({s[:80]!r}); expected finite "
                                   "numbers (empty or nan for no data)")
        rows.append(vals)
        if len(rows[-1]) != len(rows[0]):
            raise CorruptFileError(f"{path}: line {lineno} has {len(rows[-1])} values, the first row has {len(rows[0])}")
    if not rows:
        raise CorruptFileError(f"{path}: no numeric rows")
    return np.asarray(rows, dtype=np.float64)


def read_matrix(path: Path, data: bytes, opts: ReadOptions) -> Iterator[ThermalImage]:
    """Reader for ``.npy`` / ``.csv`` / ``.txt`` temperature matrices (registered)."""
    unit = _need_unit(path, opts)
    data = bytes(data)
    if data.startswith(b"\x93NUMPY"):
        try:
            fh = io.BytesIO(data)
            major, _minor = np.lib.format.read_magic(fh)
            read_header = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
            shape, _, dtype = read_header(fh)
        except Exception as exc:
            raise CorruptFileError(f"{path}: NPY header cannot be read ({exc})") from None
        if len(shape) != 2 or dtype.kind not in "fiu":
            raise UnsupportedFormatError(f"{path}: expected a 2-D numeric matrix, got shape {shape} dtype {dtype}")
        check_image_size(shape[1], shape[0], str(path))  # before np.load allocates
        need = int(np.prod(shape)) * dtype.itemsize
        if len(data) - fh.tell() < need:
            raise CorruptFileError(f"{path}: NPY data holds {len(data) - fh.tell()} bytes, {need} needed for "
                                   f"{shape} {dtype}: truncated file")
        try:
            arr = np.load(io.BytesIO(data), allow_pickle=False)
        except Exception as exc:
            raise CorruptFileError(f"{path}: NPY file cannot be read ({exc}): truncated?") from None
    else:
        arr = _parse_csv(path, data.decode("utf-8", "replace"))
    if arr.ndim != 2 or arr.dtype.kind not in "fiu":
        raise UnsupportedFormatError(f"{path}: expected a 2-D numeric matrix, got shape {arr.shape} dtype {arr.dtype}")
    if arr.dtype.kind == "f" and np.isinf(arr).any():
        raise CorruptFileError(f"{path}: {int(np.isinf(arr).sum())} infinite value(s); expected finite numbers "
                               "(NaN for no data)")
    md = ThermalMetadata(source_path=str(path), reader="matrix", notes=[f"temperature matrix declared in {unit}"])
    yield ThermalImage(None, to_kelvin(arr, unit), md)


_NUMERIC_LINE = re.compile(rb"^\s*[-+0-9.eEnaN]+(\s*[,;\t ]\s*[-+0-9.eEnaN]*)+\s*$")


def read_emissivity_table(path: str | Path):
    """Directional emissivity table from a CSV file: two columns, angle from the normal in degrees and
    emissivity (a header line is allowed), e.g. measured values from the literature for the material.

    Returns
    -------
    :class:`~thermogrammetry.radiometry.TabulatedEmissivity` (validated: increasing angles, values in (0, 1]).
    """
    from ..radiometry.directional import TabulatedEmissivity

    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise CorruptFileError(f"{p}: cannot read emissivity table ({exc.strerror or exc})") from None
    arr = _parse_csv(p, text)
    if arr.shape[1] != 2:
        raise UnsupportedFormatError(f"{p}: emissivity table needs 2 columns (angle_deg, emissivity), found {arr.shape[1]}")
    try:
        return TabulatedEmissivity(tuple(arr[:, 0].tolist()), tuple(arr[:, 1].tolist()))
    except ValueError as exc:
        raise type(exc)(f"{p}: {exc}") from None


def _number_row(head: bytes) -> bytes | None:
    """The first row of numbers within the first two lines of a text file's first 4 KiB (comments and blank lines
    skipped), or None."""
    lines = [ln for ln in head[:4096].splitlines()[:3] if ln.strip() and not ln.lstrip().startswith(b"#")]
    return next((ln for ln in lines[:2] if _NUMERIC_LINE.match(ln)), None)


def _sniff(head: bytes, path: Path) -> bool:
    if head.startswith(b"\x93NUMPY"):
        return True
    if path.suffix.lower() not in (".csv", ".txt", ".tsv"):
        return False
    return _number_row(head) is not None  # a number row within the first two lines


#: a folder scan (:func:`thermogrammetry.pipeline.survey.expand_inputs`) takes a CSV for a temperature matrix only
#: with at least this many values in a row: a side file (GCPs, GNSS, measurements: ``id,X,Y,Z``) has fewer
MIN_MATRIX_COLUMNS = 8


def looks_like_matrix(path: str | Path) -> bool:
    """Whether a ``.csv``/``.txt``/``.tsv`` file looks like a temperature matrix: a row of at least
    :data:`MIN_MATRIX_COLUMNS` numbers within its first two lines (a header line allowed), the row the reader's
    sniffer finds. Reads 4 KiB; an unreadable file gives True (its reader then says why)."""
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return True
    if head.startswith(b"\x93NUMPY"):  # as :func:`_sniff` decides
        return True
    if p.suffix.lower() not in (".csv", ".txt", ".tsv"):
        return False
    row = _number_row(head)
    return row is not None and len(re.split(rb"\s*[,;\t ]\s*", row.strip())) >= MIN_MATRIX_COLUMNS


register_reader("matrix", _sniff, read_matrix, priority=0, description="CSV/NPY temperature matrix with explicit unit")
