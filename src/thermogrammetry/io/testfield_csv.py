"""Read the 3D test-field CSV files (control points, image measurements) from disk.

The formats and all checks live in :mod:`thermogrammetry.calibration.testfield_csv`, whose
``parse_*`` functions work on text and a source name; this module only reads the file (UTF-8, a
byte-order mark is dropped) and passes the path as that name, so every error message names the
file and the row. File-level problems raise :class:`~thermogrammetry.errors.DataFileError`
(missing or unreadable) or :class:`~thermogrammetry.errors.UnsupportedFormatError` (not UTF-8 text).
"""

from __future__ import annotations

import os
from pathlib import Path

from ..calibration.testfield_csv import (
    ControlPoints,
    Measurements,
    parse_control_csv,
    parse_measurements_csv,
)
from ..errors import DataFileError, UnsupportedFormatError

__all__ = ["read_control_csv", "read_measurements_csv", "read_text"]


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
    :func:`thermogrammetry.calibration.testfield_csv.parse_control_csv`."""
    text, src = read_text(path)
    return parse_control_csv(text, src)


def read_measurements_csv(path: str | os.PathLike) -> Measurements:
    """Read a measurement file ``image,id,x,y[,sx,sy]`` (pixels, OpenCV convention); see
    :func:`thermogrammetry.calibration.testfield_csv.parse_measurements_csv`."""
    text, src = read_text(path)
    return parse_measurements_csv(text, src)
