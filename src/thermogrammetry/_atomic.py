"""Atomic file writes: the one implementation every writer in the project uses.

A temp file is written beside the target, flushed and fsync'ed, then renamed over
it with :func:`os.replace`; a reader never sees a half-written file, and on failure
the previous content (if any) is untouched and no temp file is left behind.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from .errors import DataFileError

__all__ = ["write_atomic", "write_atomic_text"]


def write_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically, creating missing parent folders.

    Raises
    ------
    DataFileError
        When the folder cannot be created or the file cannot be written; names the path.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise DataFileError(f"{path}: cannot write ({exc.strerror or exc})") from exc
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path


def write_atomic_text(path: str | os.PathLike, text: str) -> Path:
    """UTF-8 text with ``\\n`` line ends, written by :func:`write_atomic`."""
    return write_atomic(path, text.encode("utf-8"))
