"""The one object that knows where a workflow's files live.

Algorithms never touch paths: steps read and write *keys* (``"calibration/camera.json"``)
through a :class:`ProjectStore`. :class:`FolderProject` maps keys to files under a
root folder and writes atomically (temp file in the same folder, then ``os.replace``);
:class:`MemoryProject` is its in-memory twin for tests.

Keys are relative POSIX paths without ``..``; they double as file names.
"""

from __future__ import annotations

import io
import json
import os
from abc import ABC, abstractmethod
from pathlib import Path, PurePosixPath
from typing import Any, Iterator

import numpy as np

from .._atomic import write_atomic
from ..errors import DataFileError, InvalidInputError

__all__ = ["ProjectStore", "FolderProject", "MemoryProject", "write_atomic"]


def _check_key(key: str) -> str:
    if not isinstance(key, str) or not key:
        raise InvalidInputError(f"project key {key!r}: expected a non-empty relative path such as 'calibration/camera.json'")
    p = PurePosixPath(key)
    if p.is_absolute() or ".." in p.parts or "\\" in key:
        raise InvalidInputError(f"project key {key!r}: expected a relative POSIX path without '..'")
    return str(p)


def _json_default(o: Any):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "value") and isinstance(getattr(o, "value"), str):  # enums
        return o.value
    raise TypeError(f"object of type {type(o).__name__} is not JSON serialisable")


class ProjectStore(ABC):
    """Key-value view of a workflow's files. Subclasses implement the four byte-level methods."""

    # -- byte level -------------------------------------------------------------------------
    @abstractmethod
    def write_bytes(self, key: str, data: bytes) -> None: ...

    @abstractmethod
    def read_bytes(self, key: str) -> bytes: ...

    @abstractmethod
    def exists(self, key: str) -> bool: ...

    @abstractmethod
    def keys(self, prefix: str = "") -> list[str]: ...

    # -- typed helpers ----------------------------------------------------------------------
    def write_text(self, key: str, text: str) -> None:
        self.write_bytes(key, text.encode("utf-8"))

    def read_text(self, key: str) -> str:
        return self.read_bytes(key).decode("utf-8")

    def write_json(self, key: str, obj: Any) -> None:
        self.write_text(key, json.dumps(obj, indent=2, default=_json_default, allow_nan=True) + "\n")

    def read_json(self, key: str) -> Any:
        text = self.read_text(key)
        try:
            return json.loads(text)
        except json.JSONDecodeError as exc:
            raise DataFileError(f"{self.describe(key)}: not valid JSON ({exc})") from None

    def write_array(self, key: str, array: np.ndarray) -> None:
        buf = io.BytesIO()
        np.save(buf, np.asarray(array), allow_pickle=False)
        self.write_bytes(key, buf.getvalue())

    def read_array(self, key: str) -> np.ndarray:
        return np.load(io.BytesIO(self.read_bytes(key)), allow_pickle=False)

    def describe(self, key: str) -> str:
        """Human-readable location of ``key`` for messages."""
        return key

    def local_path(self, key: str) -> Path | None:
        """A real file path for libraries that need one (GDAL), or None for in-memory stores."""
        return None


class FolderProject(ProjectStore):
    """Keys are files under ``root``; writes are atomic.

    ``durable=False``: files are not fsync'ed one by one (a staging folder that the caller flushes once with
    :func:`thermogrammetry._atomic.sync_folder` before publishing it)."""

    def __init__(self, root: str | os.PathLike, *, durable: bool = True):
        self.root = Path(root)
        self.durable = bool(durable)

    def _path(self, key: str) -> Path:
        return self.root / _check_key(key)

    def write_bytes(self, key: str, data: bytes) -> None:
        write_atomic(self._path(key), data, durable=self.durable)

    def read_bytes(self, key: str) -> bytes:
        p = self._path(key)
        try:
            return p.read_bytes()
        except FileNotFoundError:
            raise DataFileError(f"{p}: no such file in project {self.root}") from None

    def exists(self, key: str) -> bool:
        return self._path(key).exists()

    def keys(self, prefix: str = "") -> list[str]:
        if not self.root.is_dir():
            return []
        out = []
        for p in sorted(self.root.rglob("*")):
            if p.is_file() and not p.name.startswith("."):
                k = p.relative_to(self.root).as_posix()
                if k.startswith(prefix):
                    out.append(k)
        return out

    def describe(self, key: str) -> str:
        return str(self._path(key))

    def local_path(self, key: str) -> Path:
        p = self._path(key)
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def __repr__(self) -> str:
        return f"FolderProject({str(self.root)!r})"


class MemoryProject(ProjectStore):
    """In-memory twin of :class:`FolderProject` for tests."""

    def __init__(self, files: dict[str, bytes] | None = None):
        self.files: dict[str, bytes] = {}
        for k, v in (files or {}).items():
            self.write_bytes(k, v)

    def write_bytes(self, key: str, data: bytes) -> None:
        self.files[_check_key(key)] = bytes(data)

    def read_bytes(self, key: str) -> bytes:
        try:
            return self.files[_check_key(key)]
        except KeyError:
            raise DataFileError(f"{key}: no such key in memory project") from None

    def exists(self, key: str) -> bool:
        return _check_key(key) in self.files

    def keys(self, prefix: str = "") -> list[str]:
        return sorted(k for k in self.files if k.startswith(prefix))

    def __iter__(self) -> Iterator[str]:
        return iter(self.keys())

    def __repr__(self) -> str:
        return f"MemoryProject({len(self.files)} files)"
