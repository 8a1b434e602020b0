"""One lookup of functions of the C library (glibc on Linux) for the few calls Python's ``os`` lacks.

Used by :mod:`thermogrammetry._atomic` (``renameat2``, ``syncfs``) and :mod:`thermogrammetry._memory`
(``mallopt``, ``malloc_trim``).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import sys

__all__ = ["libc_function"]


@functools.lru_cache(maxsize=None)
def _libc():
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    except OSError:
        return None


@functools.lru_cache(maxsize=None)
def libc_function(name: str, argtypes: tuple, restype=ctypes.c_int):
    """The C library's function ``name`` with its signature set (looked up once), or None (not Linux, or a C library
    without it)."""
    lib = _libc()
    fn = getattr(lib, name, None) if lib is not None else None
    if fn is None:
        return None
    fn.argtypes = list(argtypes)
    fn.restype = restype
    return fn
