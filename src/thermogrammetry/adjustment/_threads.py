"""BLAS thread control for the solvers.

The solvers issue many small BLAS calls; OpenBLAS's own worker threads then only spin against the
solver's threads (and other processes) on few cores. Inside a solve BLAS runs single-threaded;
the controller is built once because scanning the loaded libraries costs milliseconds.
"""

from __future__ import annotations

import contextlib

_CONTROLLER = None


def blas_single_thread():
    """Context manager limiting BLAS libraries to one thread (no-op without threadpoolctl)."""
    global _CONTROLLER
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency
        return contextlib.nullcontext()
    if _CONTROLLER is None:
        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=1, user_api="blas")
