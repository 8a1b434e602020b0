"""Test helper: synthetic scenes rendered (and surveyed) once per test run, shared by the tests that read them.

Rendering a building ring (40-64 stations of ray-cast, supersampled frames) or surveying it takes minutes; several
test files use the same scene with the same seed. :class:`SceneCache` keeps one copy per test run under a
session-wide folder, keyed by the scene's parameters:

- the folder is ``<basetemp>/scene-cache`` -- with pytest-xdist the workers' basetemps (``popen-gwN``) share their
  parent, so the parent is used and every worker sees the same cache; a new test run has a new basetemp, hence a
  new, empty cache (nothing is reused across runs);
- one worker builds an entry while holding an exclusive ``fcntl.flock`` on ``<key>.lock``; a worker that asks for
  the same entry meanwhile waits for the lock and then reads the finished entry;
- an entry counts as finished only once its result file has been written (to a temporary name, then
  ``os.replace``): a builder that failed half-way leaves no result file, and the next caller builds it again.

The builder of an entry must not depend on which test asks first: it receives only its own empty folder and the
parameters the key is made of. Consumers treat an entry as read-only (copy it with :func:`copy_entry` when a test
writes beside it).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import pickle
import shutil
from pathlib import Path
from typing import Any, Callable

RESULT = ".cache-result.pkl"


def _key(name: str, params: Any) -> str:
    blob = json.dumps(params, sort_keys=True, default=repr)
    return f"{name}-{hashlib.sha1(blob.encode()).hexdigest()[:16]}"


@contextlib.contextmanager
def _locked(path: Path):
    with open(path, "a+") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


class SceneCache:
    """A session-wide cache of built folders / values (see the module docstring)."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self._memo: dict[str, tuple[Path, Any]] = {}

    @classmethod
    def for_session(cls, tmp_path_factory) -> "SceneCache":
        base = tmp_path_factory.getbasetemp()
        if os.environ.get("PYTEST_XDIST_WORKER"):
            base = base.parent  # shared by the xdist workers of this run
        return cls(base / "scene-cache")

    def folder(self, name: str, params: Any, build: Callable[[Path], Any]) -> tuple[Path, Any]:
        """``(folder, value)``: ``value = build(folder)`` run once per test run for ``(name, params)``.

        ``build`` fills the empty ``folder`` and returns a picklable value (or None).
        """
        key = _key(name, params)
        if key in self._memo:
            return self._memo[key]
        folder = self.root / key
        with _locked(self.root / f"{key}.lock"):
            done = folder / RESULT
            if not done.is_file():
                shutil.rmtree(folder, ignore_errors=True)  # a builder that failed half-way
                folder.mkdir()
                value = build(folder)
                tmp = folder / f"{RESULT}.{os.getpid()}.tmp"
                tmp.write_bytes(pickle.dumps(value))
                os.replace(tmp, done)
            value = pickle.loads(done.read_bytes())
        self._memo[key] = (folder, value)
        return folder, value

    def value(self, name: str, params: Any, build: Callable[[], Any]) -> Any:
        """``build()`` (a picklable value, e.g. rendered frames) once per test run for ``(name, params)``."""
        return self.folder(name, params, lambda _folder: build())[1]


def copy_entry(src: Path, dst: Path) -> Path:
    """A test's own copy of a cache entry's folder (without the cache's result file)."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns(RESULT, f"{RESULT}.*"))
    return dst
