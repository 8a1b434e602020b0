"""Ctrl-C and SIGTERM: the verb stops, says so in one line and exits 130 / 143; OUT is as it was before the run.

The command's process turns SIGINT and SIGTERM into :class:`Interrupted` (a :class:`BaseException`, so no
``except Exception`` of a library swallows it and click does not turn it into "Aborted!"). It unwinds the verb as
any error does: the output set's staging folder is removed (:class:`~thermogrammetry._atomic.OutputSet`), a local
cluster is closed, and the command prints one line and exits ``128 + signal`` (the shell's convention: 130 for
SIGINT, 143 for SIGTERM). A second signal while that clean-up runs ends the process at once with the same status;
the next run removes what it left (stale staging folders are cleaned when an output set is opened).

Worker processes do not handle Ctrl-C: a terminal sends SIGINT to the whole foreground process group, and a
worker that raised KeyboardInterrupt would print its own traceback. Forked workers call :func:`worker_ignores_sigint`
first; worker processes started by a program (a dask local cluster) are started inside
:func:`children_ignore_sigint`, whose SIG_IGN they inherit through ``exec`` (Python keeps an ignored SIGINT
ignored at start-up). Their parent ends them when it unwinds.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from typing import Iterator

__all__ = ["Interrupted", "install_handlers", "restore_handlers", "children_ignore_sigint", "worker_ignores_sigint"]

_HANDLED = (signal.SIGINT, signal.SIGTERM)
_previous: dict[int, object] = {}
_received: list[int] = []


class Interrupted(BaseException):
    """The run was stopped by a signal (Ctrl-C or SIGTERM); ``exit_status`` is ``128 + signum``."""

    def __init__(self, signum: int):
        self.signum = int(signum)
        self.signal_name = signal.Signals(self.signum).name
        super().__init__(f"interrupted by {self.signal_name}")

    @property
    def exit_status(self) -> int:
        return 128 + self.signum


def _handler(signum, frame) -> None:
    if _received:  # a second signal while the first one's clean-up runs: stop now
        os._exit(128 + _received[0])
    _received.append(int(signum))
    raise Interrupted(signum)


def install_handlers() -> bool:
    """Turn SIGINT and SIGTERM into :class:`Interrupted` in this process (main thread only; returns False
    elsewhere, where Python cannot set signal handlers). A SIGINT that the parent ignores (a job started with
    ``nohup`` or in the background) stays ignored."""
    if threading.current_thread() is not threading.main_thread():
        return False
    _received.clear()
    for s in _HANDLED:
        prev = signal.getsignal(s)
        if s == signal.SIGINT and prev == signal.SIG_IGN:
            continue
        _previous[s] = prev
        signal.signal(s, _handler)
    return True


def restore_handlers() -> None:
    """Put back the handlers :func:`install_handlers` replaced."""
    if threading.current_thread() is not threading.main_thread():
        return
    for s, prev in list(_previous.items()):
        signal.signal(s, prev if prev is not None else signal.SIG_DFL)
        del _previous[s]


@contextlib.contextmanager
def children_ignore_sigint() -> Iterator[None]:
    """Processes started inside the block inherit an ignored SIGINT (a Ctrl-C reaches their parent only).

    A SIGTERM inside the block is held and raised when it ends; a Ctrl-C inside it (the few seconds the processes
    take to start) is ignored, as it must be for the children to inherit it ignored: press it again.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    prev = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    prev_term = signal.getsignal(signal.SIGTERM)
    if prev_term is _handler:
        signal.signal(signal.SIGTERM, lambda s, f: held.append(s))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, prev if prev is not None else signal.SIG_DFL)
        signal.signal(signal.SIGTERM, prev_term if prev_term is not None else signal.SIG_DFL)
        if held and prev_term is _handler:
            _handler(held[0], None)


def worker_ignores_sigint() -> None:
    """In a forked worker: ignore SIGINT and take the default action on SIGTERM (the parent's handlers, copied
    by ``fork``, would raise :class:`Interrupted` in the worker and print its traceback)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
