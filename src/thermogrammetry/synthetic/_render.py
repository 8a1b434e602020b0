"""Shared rendering helpers: pose coercion and supersampled pixel rays through a camera model."""

from __future__ import annotations

from typing import Iterator

import numpy as np

from ..errors import InvalidInputError

__all__ = ["as_pose", "sample_offsets", "iter_sample_rays", "camera_size"]


def as_pose(pose):
    """Accept a :class:`thermogrammetry.geometry.Pose` or an ``(R, t)`` pair; return a Pose."""
    from ..geometry import Pose

    if isinstance(pose, Pose):
        return pose
    if hasattr(pose, "R") and hasattr(pose, "t"):
        return Pose(np.asarray(pose.R, float), np.asarray(pose.t, float))
    try:
        R, t = pose
    except (TypeError, ValueError):
        raise InvalidInputError(f"pose={pose!r}: expected a thermogrammetry.geometry.Pose or an (R, t) pair") from None
    return Pose(np.asarray(R, float), np.asarray(t, float))


def camera_key(camera) -> tuple:
    """Exact identity of a camera model for caches: model, size, parameter bytes, pixel pitch."""
    params = getattr(camera, "params", None)
    pb = np.asarray(params, dtype=np.float64).tobytes() if params is not None else repr(camera).encode()
    return (str(getattr(camera, "model", type(camera).__name__)), camera_size(camera), pb,
            repr(getattr(camera, "pixel_pitch_um", None)))


def camera_size(camera) -> tuple[int, int]:
    w, h = camera.image_size
    return int(w), int(h)


def sample_offsets(supersample: int) -> np.ndarray:
    """(S,) sub-pixel offsets in [−0.5, 0.5): the centres of an S×S regular grid inside a pixel."""
    ss = int(supersample)
    if ss < 1:
        raise InvalidInputError(f"supersample={supersample!r}: expected an integer >= 1")
    return (np.arange(ss) + 0.5) / ss - 0.5


def iter_sample_rays(camera, supersample: int, *, max_samples: int = 2_000_000) -> Iterator[tuple[slice, np.ndarray]]:
    """Yield ``(row_slice, rays)`` for blocks of image rows.

    ``rays`` has shape (rows, W, S*S, 3): camera-frame ray directions (z = 1) of the S×S sub-pixel samples
    of every pixel, obtained by unprojecting the sample positions through the camera model (so the lens
    distortion is exactly the model's). OpenCV pixel origin: pixel (col, row) covers [col ± 0.5] × [row ± 0.5].
    """
    w, h = camera_size(camera)
    key = (camera_key(camera), int(supersample))
    cached = _RAY_CACHE.get(key)
    if cached is not None:
        for r0, r1, rays in cached:
            yield slice(r0, r1), rays
        return
    total = w * h * int(supersample) ** 2
    store = [] if total * 24 <= _RAY_CACHE_BYTES else None
    off = sample_offsets(supersample)
    oy, ox = np.meshgrid(off, off, indexing="ij")
    ox = ox.ravel()
    oy = oy.ravel()
    per_row = w * ox.size
    rows_per_block = max(1, int(max_samples // per_row))
    cols = np.arange(w, dtype=np.float64)
    for r0 in range(0, h, rows_per_block):
        r1 = min(h, r0 + rows_per_block)
        rows = np.arange(r0, r1, dtype=np.float64)
        x = cols[None, :, None] + ox[None, None, :] + 0.0 * rows[:, None, None]
        y = rows[:, None, None] + oy[None, None, :] + 0.0 * cols[None, :, None]
        xy = np.stack([x.ravel(), y.ravel()], axis=1)
        rays = unproject_fast(camera, xy).reshape(r1 - r0, w, ox.size, 3)
        if store is not None:
            rays.flags.writeable = False
            store.append((r0, r1, rays))
        yield slice(r0, r1), rays
    if store is not None:
        if len(_RAY_CACHE) >= 2:
            _RAY_CACHE.pop(next(iter(_RAY_CACHE)))
        _RAY_CACHE[key] = store


#: camera rays of recently rendered (camera, supersample) pairs, for image series of one camera
_RAY_CACHE: dict = {}
_RAY_CACHE_BYTES = 64 * 1024 * 1024


_LATTICE_CACHE: dict = {}


def _lattice(camera):
    """Exact rays at pixel centres on the grid x = −1..w, y = −1..h (one pixel beyond the border)."""
    key = camera_key(camera)
    hit = _LATTICE_CACHE.get(key)
    if hit is not None:
        return hit
    w, h = camera_size(camera)
    gx, gy = np.meshgrid(np.arange(-1, w + 1, dtype=np.float64), np.arange(-1, h + 1, dtype=np.float64))
    rays = np.asarray(camera.unproject(np.stack([gx.ravel(), gy.ravel()], axis=1)), dtype=np.float64)
    lat = rays[:, :2].reshape(h + 2, w + 2, 2)
    if len(_LATTICE_CACHE) > 8:
        _LATTICE_CACHE.clear()
    _LATTICE_CACHE[key] = lat
    return lat


def unproject_fast(camera, xy_px, *, tol_px: float = 1e-6) -> np.ndarray:
    """``camera.unproject`` for many points inside the image, to ``tol_px`` of the exact inverse.

    For models whose ``project`` is closed form and ``unproject`` iterative (OpenCV forward form), rays
    are interpolated bilinearly from an exact lattice at pixel centres and then polished by Newton steps
    on ``camera.project`` (the Jacobian of the bilinear interpolant stands in for the inverse Jacobian);
    points whose re-projection still misses by more than ``tol_px`` are unprojected exactly. Other models
    call ``camera.unproject`` directly. Returns (N, 3) rays with z = 1.
    """
    xy = np.asarray(xy_px, dtype=np.float64)
    if str(getattr(camera, "model", "")) != "opencv":
        return np.asarray(camera.unproject(xy), dtype=np.float64)
    w, h = camera_size(camera)
    lat = _lattice(camera)
    u = np.clip(xy[:, 0] + 1.0, 0.0, w + 1 - 1e-9)
    v = np.clip(xy[:, 1] + 1.0, 0.0, h + 1 - 1e-9)
    i0 = np.minimum(np.floor(u).astype(np.intp), w)
    j0 = np.minimum(np.floor(v).astype(np.intp), h)
    fu = (u - i0)[:, None]
    fv = (v - j0)[:, None]
    a = lat[j0, i0]
    b = lat[j0, i0 + 1]
    c = lat[j0 + 1, i0]
    d = lat[j0 + 1, i0 + 1]
    ray = a + fu * (b - a) + fv * (c - a) + fu * fv * (a - b - c + d)
    du = (b - a) + fv * (a - b - c + d)  # d ray / d x_px
    dv = (c - a) + fu * (a - b - c + d)  # d ray / d y_px
    out = np.empty((len(xy), 3))
    out[:, 2] = 1.0
    for _ in range(2):
        out[:, :2] = ray
        res = np.asarray(camera.project(out), dtype=np.float64) - xy
        ray = ray - du * res[:, :1] - dv * res[:, 1:2]
    out[:, :2] = ray
    res = np.asarray(camera.project(out), dtype=np.float64) - xy
    bad = ~(np.abs(res).max(axis=1) <= tol_px)
    if np.any(bad):
        out[bad] = np.asarray(camera.unproject(xy[bad]), dtype=np.float64)
    return out
