"""The store: the one object that knows where a workflow's files live, and the steps that use it.

Algorithms never touch paths: steps read and write *keys* (``"calibration/camera.json"``)
through a :class:`ProjectStore`. :class:`FolderProject` maps keys to files under a
root folder and writes atomically (temp file in the same folder, then ``os.replace``);
:class:`MemoryProject` is its in-memory twin for tests.

Keys are relative POSIX paths without ``..``; they double as file names.

A pipeline is a list of small steps that share nothing in memory. Each :class:`Step` reads its
inputs from the store and writes its outputs there; :func:`run_steps` times each one and writes
``reports/<step>.json`` with its status, wall time and the small summary the step returned. A
failing step stops the pipeline and is reported, with the steps before it kept.

This module is part of the foundation layer: every other layer may use it.
"""

from __future__ import annotations

import io
import json
import os
import time
import traceback
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from ._atomic import write_atomic
from .errors import DataFileError, InvalidInputError

__all__ = ["ProjectStore", "FolderProject", "MemoryProject", "Step", "StepReport", "run_steps", "write_atomic"]


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


@dataclass(frozen=True)
class Step:
    """A named unit of work: ``run(project) -> summary dict`` (small, JSON-serialisable)."""

    name: str
    run: Callable[[ProjectStore], dict[str, Any] | None]
    description: str = ""


@dataclass
class StepReport:
    name: str
    status: str  # "ok" | "failed"
    seconds: float
    summary: dict[str, Any] = field(default_factory=dict)
    error: str = ""

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def run_steps(
    project: ProjectStore,
    steps: Sequence[Step],
    *,
    on_step: Callable[[StepReport], None] | None = None,
    report_prefix: str = "reports",
) -> list[StepReport]:
    """Run ``steps`` in order; stop at the first failure. Returns one report per step run."""
    reports: list[StepReport] = []
    for step in steps:
        t0 = time.perf_counter()
        try:
            summary = step.run(project) or {}
            rep = StepReport(step.name, "ok", time.perf_counter() - t0, dict(summary))
        except Exception as exc:  # a failed step is reported, not swallowed: the caller sees status
            rep = StepReport(
                step.name,
                "failed",
                time.perf_counter() - t0,
                error=f"{type(exc).__name__}: {exc}",
                summary={"traceback": traceback.format_exc(limit=8)},
            )
        project.write_json(f"{report_prefix}/{step.name}.json", asdict(rep))
        reports.append(rep)
        if on_step is not None:
            on_step(rep)
        if not rep.ok:
            break
    return reports
