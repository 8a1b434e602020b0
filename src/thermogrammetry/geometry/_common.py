"""Small shared helpers of the geometry kernels."""

from __future__ import annotations

import numpy as np

from ..errors import InvalidInputError, ShapeError

__all__ = ["sigma_per_coordinate"]


def sigma_per_coordinate(sigma, shape: tuple, name: str = "sigma_px") -> np.ndarray:
    """Broadcast an a-priori σ (scalar, per point, or per coordinate) to ``shape + (2,)``.

    Accepts a scalar, an array of ``shape`` (one σ per image point) or of ``shape + (2,)``
    (σx, σy). Raises :class:`ShapeError` / :class:`InvalidInputError` naming ``name``.
    """
    s = np.asarray(sigma, dtype=float)
    full = tuple(shape) + (2,)
    if s.ndim == 0:
        out = np.full(full, float(s))
    elif s.shape == tuple(shape):
        out = np.repeat(s[..., None], 2, axis=-1)
    elif s.shape == full:
        out = s.copy()
    else:
        want = ", ".join(str(d) for d in shape)
        raise ShapeError(f"{name}: expected a scalar, shape ({want}) or ({want}, 2), got {s.shape}")
    if not np.all(np.isfinite(out) & (out > 0)):
        bad = out[~(np.isfinite(out) & (out > 0))][0]
        raise InvalidInputError(f"{name}: {bad!r} is not a positive finite standard deviation in pixels")
    return out
