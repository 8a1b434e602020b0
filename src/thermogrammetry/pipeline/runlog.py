"""The ``run`` verb's log and fingerprints: ``PROJECT/run.log`` (progress lines, dask's own messages) and the hashes
that decide whether a step's inputs changed.

:class:`RunLog` appends time-stamped lines to ``run.log`` and echoes the progress lines to the terminal. While
:meth:`RunLog.capture` is active, what anything writes to the process's standard error -- the worker processes of
a local dask cluster inherit it, Python warnings and the ``distributed``/``dask``/``tornado`` loggers write there --
goes to ``run.log`` instead of the user's terminal; the terminal keeps a stream of its own
(:attr:`RunLog.terminal`). When a run fails, the captured lines are shown on the terminal too
(:meth:`RunLog.captured_tail`).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import sys
import time
from contextlib import contextmanager
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Callable

__all__ = ["RunLog", "file_digest", "stat_digest", "options_digest", "digest"]

#: loggers whose records go to run.log (not the terminal) while a run captures
CAPTURED_LOGGERS = ("distributed", "dask", "tornado", "asyncio", "bokeh", "py.warnings")


def digest(obj) -> str:
    """sha256 (hex) of the canonical JSON of ``obj`` (sorted keys; other objects by :func:`repr`)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=_plain).encode("utf-8")).hexdigest()


def _plain(o):
    if is_dataclass(o) and not isinstance(o, type):
        return {f.name: getattr(o, f.name) for f in fields(o)}
    if hasattr(o, "tolist"):
        return o.tolist()
    if hasattr(o, "value") and isinstance(getattr(o, "value"), (str, int)):
        return o.value
    if isinstance(o, (set, frozenset)):
        return sorted(map(str, o))
    if isinstance(o, Path):
        return str(o)
    return repr(o)


def file_digest(path) -> str | None:
    """sha256 of a file's bytes (None when it does not exist)."""
    p = Path(path)
    if not p.is_file():
        return None
    h = hashlib.sha256()
    with open(p, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def stat_digest(path) -> list | None:
    """``[resolved path, size, mtime (ns)]`` of a file (a change of content without a change of size and mtime is
    not seen: the cheap fingerprint of image files); None when it does not exist."""
    p = Path(path)
    try:
        st = p.stat()
    except OSError:
        return None
    return [str(p.resolve()), st.st_size, st.st_mtime_ns]


def options_digest(opt, leave_out=("workers", "scheduler", "cache")) -> str:
    """sha256 of a typed options object's fields without those that do not change the outputs (how the work
    is spread: ``workers``, ``scheduler``; the survey's tie-point ``cache``)."""
    d = {f.name: getattr(opt, f.name) for f in fields(opt) if f.name not in leave_out}
    return digest(d)


class RunLog:
    """``PROJECT/run.log``: time-stamped lines appended; :meth:`line` echoes to the terminal too.

    Parameters
    ----------
    path : path of run.log (its folder is created)
    echo : callable(str) or None
        Where :meth:`line` prints on the terminal (default: :attr:`terminal`).
    """

    def __init__(self, path, echo: Callable[[str], None] | None = None):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fh = open(self.path, "a", encoding="utf-8", buffering=1)
        self._term_fd = os.dup(sys.stderr.fileno()) if _has_fd(sys.stderr) else None
        self.terminal = (os.fdopen(self._term_fd, "w", buffering=1, encoding="utf-8", errors="replace")
                         if self._term_fd is not None else sys.stderr)
        self.echo = echo
        self._capture_start: int | None = None

    def write(self, text: str) -> None:
        """Append ``text`` as one or more time-stamped lines (not echoed)."""
        stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        for ln in str(text).splitlines() or [""]:
            self.fh.write(f"{stamp}  {ln}\n")
        self.fh.flush()

    def line(self, text: str, *, echo: bool = True) -> None:
        """Append ``text`` to run.log and, with ``echo``, print it on the terminal."""
        self.write(text)
        if echo:
            if self.echo is not None:
                self.echo(text)
            else:
                print(text, file=self.terminal, flush=True)

    @contextmanager
    def capture(self):
        """Standard error (fd 2: this process, its worker processes, warnings, the dask loggers) into run.log."""
        self.fh.flush()
        self._capture_start = self.path.stat().st_size
        saved_fd = None
        handler = logging.StreamHandler(self.fh)
        handler.setFormatter(logging.Formatter("%(asctime)s  %(name)s %(levelname)s: %(message)s", "%Y-%m-%dT%H:%M:%SZ"))
        handler.formatter.converter = time.gmtime
        saved_loggers = []
        for name in CAPTURED_LOGGERS:
            lg = logging.getLogger(name)
            saved_loggers.append((lg, list(lg.handlers), lg.propagate))
            for h in list(lg.handlers):
                if isinstance(h, logging.StreamHandler) and getattr(h, "stream", None) in (sys.stderr, sys.__stderr__):
                    lg.removeHandler(h)
            lg.addHandler(handler)
            lg.propagate = False
        logging.captureWarnings(True)
        try:
            if _has_fd(sys.stderr):
                sys.stderr.flush()
                saved_fd = os.dup(2)
                os.dup2(self.fh.fileno(), 2)
            yield self
        finally:
            try:
                sys.stderr.flush()
            except (OSError, ValueError):
                pass
            if saved_fd is not None:
                os.dup2(saved_fd, 2)
                os.close(saved_fd)
            logging.captureWarnings(False)
            for lg, handlers, propagate in saved_loggers:
                lg.removeHandler(handler)
                for h in handlers:
                    if h not in lg.handlers:
                        lg.addHandler(h)
                lg.propagate = propagate
            self.fh.flush()

    def captured_tail(self, n: int = 40) -> list[str]:
        """The last ``n`` lines that the last :meth:`capture` wrote to run.log (messages of the run's libraries)."""
        if self._capture_start is None:
            return []
        with open(self.path, encoding="utf-8", errors="replace") as fh:
            fh.seek(self._capture_start)
            lines = fh.read().splitlines()
        return lines[-n:]

    def close(self) -> None:
        self.fh.close()
        if self._term_fd is not None:
            try:
                self.terminal.close()
            except OSError:
                pass
            self._term_fd = None

    def __enter__(self) -> "RunLog":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _has_fd(stream) -> bool:
    try:
        stream.fileno()
        return True
    except (AttributeError, OSError, ValueError):
        return False
