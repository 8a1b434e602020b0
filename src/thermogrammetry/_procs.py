"""Worker processes that die with their parent.

A forked worker of a process killed with SIGKILL would otherwise live on (re-parented to init) and keep
rendering.  :func:`die_with_parent`, called first in every worker initialiser, asks the Linux kernel to
send the worker SIGKILL when its parent dies (``prctl(PR_SET_PDEATHSIG)``); elsewhere, a daemon thread
polls the parent's pid once a second and exits the worker when it changes.
"""

from __future__ import annotations

import os
import signal
import threading
import time

__all__ = ["die_with_parent"]

_PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int | None = None) -> str:
    """Make this (worker) process end when its parent ends; returns the mechanism used.

    The worker also leaves Ctrl-C and SIGTERM to its parent (:func:`~thermogrammetry._interrupt.worker_ignores_sigint`),
    which ends it as it unwinds."""
    from ._interrupt import worker_ignores_sigint

    worker_ignores_sigint()
    parent = os.getppid() if parent_pid is None else int(parent_pid)
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0:
            if os.getppid() != parent:  # the parent died before prctl: nothing will signal us
                os._exit(1)
            return "prctl"
    except (OSError, AttributeError):
        pass

    def watch() -> None:
        while True:
            time.sleep(1.0)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()
    return "watchdog"
