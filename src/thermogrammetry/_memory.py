"""Process memory: keep the C heap from holding on to freed blocks.

glibc's ``malloc`` serves blocks larger than its *mmap threshold* with their own ``mmap`` (returned to the
system on ``free``) and smaller ones from the heap. The threshold is dynamic: every freed mmapped block
raises it (up to 32 MiB), after which the large NumPy temporaries of the adjustment engine, dense matching
and gridding (0.1-32 MiB each, allocated and freed many times) come from the heap, whose free pages are
not returned to the system while a live block sits above them. The process then grows iteration after
iteration far beyond its live data (measured: the final adjustment of a 120-frame survey went from
660 MiB after the first linearisation to 1080 MiB at the end with the same live arrays).

:func:`bound_heap_growth` fixes the threshold at :data:`MMAP_THRESHOLD` bytes (which also turns off the
dynamic adjustment) and the trim threshold, for this process through ``mallopt`` and for the worker
processes it starts through the ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_`` environment
variables (read by glibc at their start). Results are unchanged (only where blocks live); elsewhere than
glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import os
import sys

from ._libc import libc_function

__all__ = ["bound_heap_growth", "release_free_heap", "MMAP_THRESHOLD"]

#: blocks of at least this many bytes get their own mapping (returned to the system when freed). NumPy advises
#: transparent huge pages for arrays of 4 MiB and more, so these mappings cost one page fault per 2 MiB; below
#: it every 4 KiB page of a fresh mapping faults (and is zeroed) on first touch: with 256 KiB the adjustment's
#: per-chunk temporaries (0.3-4 MiB, allocated every iteration) cost the M3T survey ~10 s of system time and ran
#: ~25 % slower (orient + georef 19.8 -> 14.4 s, same peak memory 372 MB; 16 and 32 MiB: 14.0 and 13.7 s)
MMAP_THRESHOLD = 4 * 1024 * 1024
#: free memory at the top of the heap above this many bytes is returned to the system
TRIM_THRESHOLD = 16 * 1024 * 1024

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_done = False


def bound_heap_growth() -> bool:
    """Set glibc's mmap and trim thresholds (see the module docstring); True when applied. Idempotent."""
    global _done
    if _done:
        return True
    if not sys.platform.startswith("linux"):
        return False
    os.environ.setdefault("MALLOC_MMAP_THRESHOLD_", str(MMAP_THRESHOLD))
    os.environ.setdefault("MALLOC_TRIM_THRESHOLD_", str(TRIM_THRESHOLD))
    mallopt = libc_function("mallopt", (ctypes.c_int, ctypes.c_int))
    if mallopt is None:
        return False
    ok = bool(mallopt(_M_MMAP_THRESHOLD, int(os.environ["MALLOC_MMAP_THRESHOLD_"])))
    ok &= bool(mallopt(_M_TRIM_THRESHOLD, int(os.environ["MALLOC_TRIM_THRESHOLD_"])))
    _done = ok
    return ok


def release_free_heap() -> None:
    """Return the free pages inside the C heap to the system (glibc ``malloc_trim(0)``); a no-op elsewhere.

    The trim threshold only returns free memory at the *top* of the heap. Blocks below the mmap threshold
    (most NumPy temporaries of the chunked adjustment, e.g. 8192 x 3 float64 = 192 KiB, scipy's sparse
    index arrays, Python objects) are freed in the middle of the heap, where a live block above them keeps
    their pages resident: measured on the 396-frame survey (mmap threshold 256 KiB), 683 MiB resident after
    a covariance step against 417 MiB after ``malloc_trim``. Called between chunks of the large adjustments and between survey
    steps (a few milliseconds each); results are unchanged (only which pages stay resident).
    """
    trim = libc_function("malloc_trim", (ctypes.c_size_t,))
    if trim is not None:
        trim(0)
