"""Adapter so the geometry kernels accept a :class:`thermogrammetry.Camera` or a bare 3×3 ``K``.

A pinhole ``K`` (pixels, OpenCV origin) is wrapped in :class:`PinholeK`, which offers the
subset of the Camera API the kernels use (``project``, ``project_jacobian``, ``unproject``,
``undistort``, ``K``, ``param_names``, ``params``, ``with_params``). Anything else is used as
is, duck-typed against the Camera contract in the project brief.
"""

from __future__ import annotations

import numpy as np

from .._validate import as_array
from ..errors import InvalidInputError, ShapeError

__all__ = ["PinholeK", "as_camera", "point_jacobian"]


class PinholeK:
    """Ideal pinhole camera from an upper-triangular ``K`` (fx, fy, cx, cy, skew; pixels).

    Parameters are ``fx fy cx cy`` (skew is kept fixed). No distortion.
    """

    param_names = ("fx", "fy", "cx", "cy")

    def __init__(self, K, image_size=None):
        K = as_array(K, "K", shape=(3, 3))
        if abs(K[2, 2]) < 1e-15 or abs(K[1, 0]) > 1e-12 * abs(K[2, 2]) or abs(K[2, 0]) > 1e-12 or abs(K[2, 1]) > 1e-12:
            raise InvalidInputError(f"K: expected an upper-triangular camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
        K = K / K[2, 2]
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InvalidInputError(f"K: focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        self._K = K
        self.image_size = image_size
        self.model = "pinhole"
        self.param_std = None

    @property
    def K(self) -> np.ndarray:
        return self._K.copy()

    @property
    def params(self) -> np.ndarray:
        K = self._K
        return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])

    def with_params(self, p) -> "PinholeK":
        K = self._K.copy()
        K[0, 0], K[1, 1], K[0, 2], K[1, 2] = p
        return PinholeK(K, self.image_size)

    def project(self, points_cam) -> np.ndarray:
        X = np.asarray(points_cam, float)
        xn = X[:, :2] / X[:, 2:3]
        K = self._K
        return np.stack([K[0, 0] * xn[:, 0] + K[0, 1] * xn[:, 1] + K[0, 2], K[1, 1] * xn[:, 1] + K[1, 2]], -1)

    def project_jacobian(self, points_cam, params: bool = True):
        """``(xy (N,2), J_point (N,2,3), J_params (N,2,4) or None when params=False)``."""
        X = np.asarray(points_cam, float)
        K = self._K
        z = X[:, 2]
        xn, yn = X[:, 0] / z, X[:, 1] / z
        uv = np.stack([K[0, 0] * xn + K[0, 1] * yn + K[0, 2], K[1, 1] * yn + K[1, 2]], -1)
        n = X.shape[0]
        Jn = np.zeros((n, 2, 3))  # d(xn, yn)/dX
        Jn[:, 0, 0] = 1 / z
        Jn[:, 0, 2] = -xn / z
        Jn[:, 1, 1] = 1 / z
        Jn[:, 1, 2] = -yn / z
        A = K[:2, :2]
        Jp = np.einsum("ij,njk->nik", A, Jn)
        if not params:
            return uv, Jp, None
        Jk = np.zeros((n, 2, 4))
        Jk[:, 0, 0] = xn
        Jk[:, 1, 1] = yn
        Jk[:, 0, 2] = 1.0
        Jk[:, 1, 3] = 1.0
        return uv, Jp, Jk

    def project_point_jacobian(self, points_cam):
        """``(xy (N,2), J_point (N,2,3))``."""
        xy, jp, _ = self.project_jacobian(points_cam, params=False)
        return xy, jp

    def undistort(self, xy_px) -> np.ndarray:
        return np.array(xy_px, float)

    def distort(self, xy_px) -> np.ndarray:
        return np.array(xy_px, float)

    def unproject(self, xy_px) -> np.ndarray:
        xy = np.asarray(xy_px, float)
        K = self._K
        yn = (xy[:, 1] - K[1, 2]) / K[1, 1]
        xn = (xy[:, 0] - K[0, 2] - K[0, 1] * yn) / K[0, 0]
        return np.stack([xn, yn, np.ones_like(xn)], -1)


def point_jacobian(camera, points_cam):
    """``(xy (N,2), J_point (N,2,3))`` of a Camera-like: the point-only path when the camera has
    one (``project_point_jacobian``), else the full ``project_jacobian`` with the parameter part dropped."""
    f = getattr(camera, "project_point_jacobian", None)
    if f is not None:
        return f(points_cam)
    xy, jp, _ = camera.project_jacobian(points_cam)
    return xy, jp


def as_camera(camera, name: str = "camera"):
    """Return ``camera`` if it looks like a Camera, else wrap a (3, 3) ``K`` in :class:`PinholeK`."""
    if isinstance(camera, PinholeK):
        return camera
    if hasattr(camera, "project") and hasattr(camera, "unproject"):
        return camera
    arr = np.asarray(camera) if not isinstance(camera, (str, bytes)) else None
    if arr is not None and arr.shape == (3, 3):
        return PinholeK(arr)
    raise ShapeError(
        f"{name}: expected a thermogrammetry.Camera or a (3, 3) pinhole matrix K, got {type(camera).__name__}"
        + (f" of shape {arr.shape}" if arr is not None else "")
    )
