"""Input checks for public boundaries: shapes, finiteness, echoing the bad value."""

from __future__ import annotations

import re

import numpy as np

from .errors import NonFiniteError, ShapeError

__all__ = ["as_points", "as_array", "check_finite", "config_keys", "parse_size"]


def _describe(a) -> str:
    try:
        arr = np.asarray(a)
        return f"array of shape {arr.shape} and dtype {arr.dtype}"
    except Exception:  # pragma: no cover - exotic objects
        return repr(type(a))


def as_array(a, name: str, *, shape: tuple | None = None, dtype=np.float64, finite: bool = True) -> np.ndarray:
    """Convert to an array and check its shape (``None`` entries match any size)."""
    try:
        arr = np.asarray(a, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise ShapeError(f"{name}: cannot convert {_describe(a)} to {np.dtype(dtype).name}: {exc}") from None
    if shape is not None:
        ok = arr.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, arr.shape))
        if not ok:
            want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
            raise ShapeError(f"{name}: expected shape {want}, got {arr.shape}")
    if finite:
        check_finite(arr, name)
    return arr


def as_points(a, name: str, dim: int, *, min_count: int = 0, finite: bool = True) -> np.ndarray:
    """Return a float64 (N, dim) array; a single point of shape (dim,) is promoted to (1, dim)."""
    arr = as_array(a, name, finite=False)
    if arr.ndim == 1 and arr.shape[0] == dim:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ShapeError(f"{name}: expected shape (N, {dim}), got {arr.shape}")
    if arr.shape[0] < min_count:
        from .errors import TooFewPointsError

        raise TooFewPointsError(f"{name}: need at least {min_count} points, got {arr.shape[0]}")
    if finite:
        check_finite(arr, name)
    return arr


def check_finite(arr: np.ndarray, name: str) -> None:
    """Raise :class:`NonFiniteError` naming the first bad entry."""
    if arr.dtype.kind in "fc" and not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))
        first = tuple(int(i) for i in bad[0])
        raise NonFiniteError(
            f"{name}: {len(bad)} non-finite value(s), first at index {first} = {arr[first]!r}; expected finite numbers"
        )


def config_keys(cls, d, what: str | None = None) -> dict:
    """A copy of the mapping ``d`` after checking that each key is a field of the dataclass ``cls``.

    Raises :class:`~thermogrammetry.errors.ConfigError` naming ``what`` (default: the class name), the unknown
    keys and the valid ones; the ``from_dict`` of every typed configuration starts with it.
    """
    from collections.abc import Mapping
    from dataclasses import fields

    from .errors import ConfigError

    what = what or cls.__name__
    if not isinstance(d, Mapping):
        raise ConfigError(f"{what}: expected a mapping of options, got {type(d).__name__}")
    known = {f.name for f in fields(cls)}
    bad = sorted(set(d) - known, key=str)
    if bad:
        raise ConfigError(f"{what}: unknown key(s) {bad}; valid: {sorted(known)}")
    return dict(d)


_SIZE = re.compile(r"^\s*(\d+)\s*[xX×]\s*(\d+)\s*$")


def parse_size(text: str | None) -> tuple[int, int] | None:
    """``"640x512"`` (also ``X`` or ``×``, spaces allowed) → (640, 512); None unless two positive integers."""
    m = _SIZE.match(text or "")
    if not m or int(m.group(1)) <= 0 or int(m.group(2)) <= 0:
        return None
    return int(m.group(1)), int(m.group(2))
