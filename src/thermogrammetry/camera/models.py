"""Camera models as pure, vectorised numpy functions with analytic Jacobians.

Three models; the parameter vector of each has a fixed, documented layout
(:data:`PARAM_NAMES`). Pixel coordinates follow the project convention
(``docs/conventions.md``): (0, 0) is the centre of the top-left pixel, x right,
y down. The camera frame is x right, y down, z forward; points are given in it
(``points_cam``, shape (N, 3), any length unit).

``pinhole`` (P = 4)
    ``fx fy cx cy`` (px)::

        u = fx X/Z + cx,   v = fy Y/Z + cy

``opencv`` -- forward Brown-Conrady form of OpenCV / COLMAP ``FULL_OPENCV`` (P = 13)
    ``fx fy cx cy skew`` (px), ``k1 k2 p1 p2 k3 k4 k5 k6`` (unitless, acting on
    normalised coordinates). Distortion is applied to the ideal normalised
    coordinates ``(xn, yn) = (X/Z, Y/Z)``::

        r2 = xn^2 + yn^2
        radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
        xd = xn radial + 2 p1 xn yn + p2 (r2 + 2 xn^2)
        yd = yn radial + p1 (r2 + 2 yn^2) + 2 p2 xn yn
        u = fx xd + skew yd + cx,   v = fy yd + cy

    The distortion-vector order ``k1 k2 p1 p2 k3 k4 k5 k6`` is OpenCV's
    (:data:`OPENCV_DIST_NAMES`).

``photogrammetric`` -- correction form of the references (P = 12)
    ``c_mm x0_mm y0_mm`` (mm), ``K1 K2 K3 K4 K5`` (mm^-2 ... mm^-10),
    ``P1 P2`` (mm^-1), ``B1 B2`` (unitless); needs the image size (w, h) and
    the pixel pitch (px, py) in micrometres. Measured pixel (u, v) is taken to
    photogrammetric image coordinates (mm, centre origin, y up)::

        x = (u - (w - 1)/2) px_mm,   y = -(v - (h - 1)/2) py_mm

    and the correction is evaluated at the *measured* coordinates (Brown 1971;
    Fraser 1997)::

        xb = x - x0,  yb = y - y0,  r2 = xb^2 + yb^2
        dr = K1 r2 + K2 r2^2 + K3 r2^3 + K4 r2^4 + K5 r2^5
        dx = xb dr + P1 (r2 + 2 xb^2) + 2 P2 xb yb + B1 xb + B2 yb
        dy = yb dr + 2 P1 xb yb + P2 (r2 + 2 yb^2)

    Collinearity (conventions.md; photo frame = diag(1, -1, -1) camera frame)::

        xb + dx = c X/Z,     yb + dy = -c Y/Z

    so ``unproject`` is closed form and ``project`` solves the 2x2 non-linear
    system for (xb, yb) by Newton's method; its Jacobians follow from the
    implicit-function theorem. Seed 003 eq. (1) prints ``2 P1 xy`` in the
    y-equation and seed 001 eq. (2) is garbled; we follow Brown (1971) and
    Fraser (1997) as above (P2 in the y cross-term, B1/B2 in x only).

Functions returning Jacobians give ``J_point`` of shape (N, 2, 3) (derivative
of (u, v) with respect to (X, Y, Z)) and ``J_params`` of shape (N, 2, P) in the
parameter order of :data:`PARAM_NAMES`.

Iterative solves (``opencv`` unproject/undistort, ``photogrammetric``
project) return NaN for points where Newton's method did not converge (far
outside the image where the polynomial folds over); the ``*_solve`` variants
also return the boolean convergence mask.

References
----------
Brown, D. C. (1971). Close-range camera calibration. Photogrammetric Engineering 37(8), 855-866.
Fraser, C. S. (1997). Digital camera self-calibration. ISPRS J. Photogramm. Remote Sens. 52, 149-159.
Bradski, G. OpenCV ``calib3d`` documentation: camera model with rational radial distortion.
Yastikli, N., Guler, E. (2013). Performance evaluation of thermographic cameras for photogrammetric
measurements. ISPRS Arch. XL-1/W1 (seed 001).
"""

from __future__ import annotations

import numpy as np

from ..enums import StrChoice
from ..errors import ConfigError, InvalidInputError, UnknownModelError

__all__ = [
    "CameraModel",
    "PARAM_NAMES",
    "PARAM_UNITS",
    "REQUIRED_PARAMS",
    "OPENCV_DIST_NAMES",
    "opencv_distort_normalized",
    "opencv_distort_normalized_jacobian",
    "opencv_undistort_normalized",
    "pinhole_project",
    "pinhole_project_jacobian",
    "pinhole_unproject",
    "opencv_project",
    "opencv_project_jacobian",
    "opencv_unproject",
    "opencv_unproject_solve",
    "px_to_mm",
    "mm_to_px",
    "photogrammetric_correction",
    "photogrammetric_correction_jacobian",
    "photogrammetric_unproject",
    "photogrammetric_project",
    "photogrammetric_project_solve",
    "photogrammetric_project_jacobian",
    "project",
    "project_jacobian",
    "unproject",
    "ideal_K",
]


class CameraModel(StrChoice):
    """Camera model names (case-insensitive)."""

    PINHOLE = "pinhole"
    OPENCV = "opencv"  # forward form (OpenCV / COLMAP)
    PHOTOGRAMMETRIC = "photogrammetric"  # correction form (Brown 1971; Fraser 1997)

    @classmethod
    def _missing_(cls, value):
        try:
            return super()._missing_(value)
        except ConfigError as exc:
            raise UnknownModelError(f"unknown camera model {value!r}; expected one of "
                                    + ", ".join(repr(m.value) for m in cls)) from exc


PARAM_NAMES: dict[CameraModel, tuple[str, ...]] = {
    CameraModel.PINHOLE: ("fx", "fy", "cx", "cy"),
    CameraModel.OPENCV: ("fx", "fy", "cx", "cy", "skew", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    CameraModel.PHOTOGRAMMETRIC: ("c_mm", "x0_mm", "y0_mm", "K1", "K2", "K3", "K4", "K5", "P1", "P2", "B1", "B2"),
}

#: Parameters that must be given explicitly; the others default to 0.
REQUIRED_PARAMS: dict[CameraModel, tuple[str, ...]] = {
    CameraModel.PINHOLE: ("fx", "fy", "cx", "cy"),
    CameraModel.OPENCV: ("fx", "fy", "cx", "cy"),
    CameraModel.PHOTOGRAMMETRIC: ("c_mm", "x0_mm", "y0_mm"),
}

#: Units of every parameter ("1" = unitless).
PARAM_UNITS: dict[CameraModel, dict[str, str]] = {
    CameraModel.PINHOLE: {"fx": "px", "fy": "px", "cx": "px", "cy": "px"},
    CameraModel.OPENCV: {
        "fx": "px", "fy": "px", "cx": "px", "cy": "px", "skew": "px",
        **{k: "1" for k in ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")},
    },
    CameraModel.PHOTOGRAMMETRIC: {
        "c_mm": "mm", "x0_mm": "mm", "y0_mm": "mm",
        "K1": "mm^-2", "K2": "mm^-4", "K3": "mm^-6", "K4": "mm^-8", "K5": "mm^-10",
        "P1": "mm^-1", "P2": "mm^-1", "B1": "1", "B2": "1",
    },
}

OPENCV_DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")

# Newton settings shared by the iterative solves.
_MAX_ITER = 60


def _xyz(points_cam):
    p = np.asarray(points_cam, dtype=np.float64)
    return p[..., 0], p[..., 1], p[..., 2]


# ----------------------------------------------------------------------------------------------
# pinhole
# ----------------------------------------------------------------------------------------------
def pinhole_project(params, points_cam):
    """Project (N, 3) camera-frame points with ``params = (fx, fy, cx, cy)``; returns (N, 2) px."""
    fx, fy, cx, cy = np.asarray(params, dtype=np.float64)
    X, Y, Z = _xyz(points_cam)
    return np.stack([fx * X / Z + cx, fy * Y / Z + cy], axis=-1)


def pinhole_project_jacobian(params, points_cam, wrt_params: bool = True):
    """Projection and its Jacobians ``(xy (N,2), J_point (N,2,3), J_params (N,2,4))``.

    ``wrt_params=False`` skips the parameter Jacobian (returned as None).
    """
    fx, fy, cx, cy = np.asarray(params, dtype=np.float64)
    X, Y, Z = _xyz(points_cam)
    n = X.shape[0]
    iz = 1.0 / Z
    xn, yn = X * iz, Y * iz
    xy = np.stack([fx * xn + cx, fy * yn + cy], axis=-1)
    Jp = np.zeros((n, 2, 3))
    Jp[:, 0, 0] = fx * iz
    Jp[:, 0, 2] = -fx * xn * iz
    Jp[:, 1, 1] = fy * iz
    Jp[:, 1, 2] = -fy * yn * iz
    if not wrt_params:
        return xy, Jp, None
    Jt = np.zeros((n, 2, 4))
    Jt[:, 0, 0] = xn
    Jt[:, 1, 1] = yn
    Jt[:, 0, 2] = 1.0
    Jt[:, 1, 3] = 1.0
    return xy, Jp, Jt


def pinhole_unproject(params, xy_px):
    """Rays (N, 3) with z = 1 through pixels (N, 2)."""
    fx, fy, cx, cy = np.asarray(params, dtype=np.float64)
    xy = np.asarray(xy_px, dtype=np.float64)
    return np.stack([(xy[:, 0] - cx) / fx, (xy[:, 1] - cy) / fy, np.ones(xy.shape[0])], axis=-1)


# ----------------------------------------------------------------------------------------------
# opencv (forward form)
# ----------------------------------------------------------------------------------------------
def _opencv_radial(dist, r2):
    k1, k2, p1, p2, k3, k4, k5, k6 = dist
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    return num, den


def opencv_distort_normalized(dist, xn):
    """Apply OpenCV distortion ``dist = (k1, k2, p1, p2, k3, k4, k5, k6)`` to normalised (N, 2) coordinates."""
    dist = np.asarray(dist, dtype=np.float64)
    k1, k2, p1, p2, k3, k4, k5, k6 = dist
    x, y = xn[:, 0], xn[:, 1]
    r2 = x * x + y * y
    num, den = _opencv_radial(dist, r2)
    rad = num / den
    xd = x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def opencv_distort_normalized_jacobian(dist, xn, wrt_dist: bool = True):
    """Distorted normalised coordinates and Jacobians ``(xd (N,2), J_xn (N,2,2), J_dist (N,2,8))``.

    ``J_dist`` columns follow :data:`OPENCV_DIST_NAMES`; ``wrt_dist=False`` skips it (None).
    """
    dist = np.asarray(dist, dtype=np.float64)
    k1, k2, p1, p2, k3, k4, k5, k6 = dist
    x, y = xn[:, 0], xn[:, 1]
    n = x.shape[0]
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    num, den = _opencv_radial(dist, r2)
    rad = num / den
    dnum = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r4
    dden = k4 + 2.0 * k5 * r2 + 3.0 * k6 * r4
    drad = (dnum * den - num * dden) / (den * den)  # d radial / d r2
    xd = x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    Jx = np.empty((n, 2, 2))
    Jx[:, 0, 0] = rad + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
    Jx[:, 0, 1] = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
    Jx[:, 1, 0] = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
    Jx[:, 1, 1] = rad + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
    if not wrt_dist:
        return np.stack([xd, yd], axis=-1), Jx, None
    # d radial / d k
    inv_den = 1.0 / den
    dr_dk = np.stack(
        [r2 * inv_den, r4 * inv_den, r6 * inv_den,
         -num * r2 * inv_den**2, -num * r4 * inv_den**2, -num * r6 * inv_den**2], axis=-1
    )  # k1 k2 k3 k4 k5 k6
    Jd = np.zeros((n, 2, 8))
    for col, j in zip((0, 1, 4, 5, 6, 7), range(6)):
        Jd[:, 0, col] = x * dr_dk[:, j]
        Jd[:, 1, col] = y * dr_dk[:, j]
    Jd[:, 0, 2] = 2.0 * x * y
    Jd[:, 1, 2] = r2 + 2.0 * y * y
    Jd[:, 0, 3] = r2 + 2.0 * x * x
    Jd[:, 1, 3] = 2.0 * x * y
    return np.stack([xd, yd], axis=-1), Jx, Jd


def opencv_undistort_normalized(dist, xd, *, max_iter: int = _MAX_ITER):
    """Invert :func:`opencv_distort_normalized` by Newton's method.

    Returns ``(xn (N, 2), converged (N,) bool)``; non-converged rows are NaN.
    Converged means the distortion of the result reproduces ``xd`` to 1e-12
    (normalised units; about 1e-9 px for f = 1000 px).
    """
    xd = np.asarray(xd, dtype=np.float64)
    xn = xd.copy()
    active = np.ones(xd.shape[0], dtype=bool)
    for _ in range(max_iter):
        if not active.any():
            break
        idx = np.flatnonzero(active)
        f, J, _ = opencv_distort_normalized_jacobian(dist, xn[idx], wrt_dist=False)
        res = f - xd[idx]
        step = _solve2(J, res)
        xn[idx] -= step
        bad = ~np.all(np.isfinite(xn[idx]), axis=1)
        small = np.max(np.abs(step), axis=1) <= 1e-15 * (1.0 + np.max(np.abs(xn[idx]), axis=1))
        active[idx[small | bad]] = False
    f = opencv_distort_normalized(dist, xn)
    resid = np.max(np.abs(f - xd), axis=1)
    converged = np.isfinite(resid) & (resid <= 1e-12 * (1.0 + np.max(np.abs(xd), axis=1)))
    xn[~converged] = np.nan
    return xn, converged


def _solve2(J, r):
    """Solve the batched 2x2 systems ``J s = r``."""
    a, b, c, d = J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], J[:, 1, 1]
    det = a * d - b * c
    with np.errstate(divide="ignore", invalid="ignore"):
        s0 = (d * r[:, 0] - b * r[:, 1]) / det
        s1 = (a * r[:, 1] - c * r[:, 0]) / det
    return np.stack([s0, s1], axis=-1)


def _inv2(J):
    a, b, c, d = J[..., 0, 0], J[..., 0, 1], J[..., 1, 0], J[..., 1, 1]
    det = a * d - b * c
    inv = np.empty_like(J)
    inv[..., 0, 0] = d / det
    inv[..., 0, 1] = -b / det
    inv[..., 1, 0] = -c / det
    inv[..., 1, 1] = a / det
    return inv


def opencv_project(params, points_cam):
    """Project (N, 3) points with the 13 ``opencv`` parameters; returns (N, 2) px."""
    p = np.asarray(params, dtype=np.float64)
    fx, fy, cx, cy, skew = p[:5]
    X, Y, Z = _xyz(points_cam)
    xn = np.stack([X / Z, Y / Z], axis=-1)
    xd = opencv_distort_normalized(p[5:], xn)
    return np.stack([fx * xd[:, 0] + skew * xd[:, 1] + cx, fy * xd[:, 1] + cy], axis=-1)


def opencv_project_jacobian(params, points_cam, wrt_params: bool = True):
    """Projection and Jacobians ``(xy (N,2), J_point (N,2,3), J_params (N,2,13))``.

    ``wrt_params=False`` skips the parameter Jacobian (returned as None).
    """
    p = np.asarray(params, dtype=np.float64)
    fx, fy, cx, cy, skew = p[:5]
    X, Y, Z = _xyz(points_cam)
    n = X.shape[0]
    iz = 1.0 / Z
    xn = np.stack([X * iz, Y * iz], axis=-1)
    xd, Jx, Jd = opencv_distort_normalized_jacobian(p[5:], xn, wrt_dist=wrt_params)
    xy = np.stack([fx * xd[:, 0] + skew * xd[:, 1] + cx, fy * xd[:, 1] + cy], axis=-1)
    A = np.array([[fx, skew], [0.0, fy]])
    # J_point = A · Jx · Jn with Jn = d xn / d X = [[1/Z, 0, -xn/Z], [0, 1/Z, -yn/Z]], written out
    # elementwise (a three-operand einsum over N 2x2x3 blocks is several times slower)
    M = np.empty((n, 2, 2))
    M[:, 0, 0] = fx * Jx[:, 0, 0] + skew * Jx[:, 1, 0]
    M[:, 0, 1] = fx * Jx[:, 0, 1] + skew * Jx[:, 1, 1]
    M[:, 1, 0] = fy * Jx[:, 1, 0]
    M[:, 1, 1] = fy * Jx[:, 1, 1]
    Jp = np.empty((n, 2, 3))
    Jp[:, :, 0] = M[:, :, 0] * iz[:, None]
    Jp[:, :, 1] = M[:, :, 1] * iz[:, None]
    Jp[:, :, 2] = -(M[:, :, 0] * xn[:, 0:1] + M[:, :, 1] * xn[:, 1:2]) * iz[:, None]
    if not wrt_params:
        return xy, Jp, None
    Jt = np.zeros((n, 2, 13))
    Jt[:, 0, 0] = xd[:, 0]
    Jt[:, 1, 1] = xd[:, 1]
    Jt[:, 0, 2] = 1.0
    Jt[:, 1, 3] = 1.0
    Jt[:, 0, 4] = xd[:, 1]
    Jt[:, :, 5:] = np.einsum("ij,njk->nik", A, Jd)
    return xy, Jp, Jt


def opencv_unproject_solve(params, xy_px):
    """Rays (N, 3), z = 1, and the convergence mask of the iterative undistortion."""
    p = np.asarray(params, dtype=np.float64)
    fx, fy, cx, cy, skew = p[:5]
    xy = np.asarray(xy_px, dtype=np.float64)
    yd = (xy[:, 1] - cy) / fy
    xd = (xy[:, 0] - cx - skew * yd) / fx
    xn, ok = opencv_undistort_normalized(p[5:], np.stack([xd, yd], axis=-1))
    return np.concatenate([xn, np.ones((xn.shape[0], 1))], axis=1), ok


def opencv_unproject(params, xy_px):
    """Rays (N, 3) with z = 1 through distorted pixels (N, 2); NaN where the inversion fails."""
    return opencv_unproject_solve(params, xy_px)[0]


# ----------------------------------------------------------------------------------------------
# photogrammetric (correction form)
# ----------------------------------------------------------------------------------------------
def _pitch_mm(pixel_pitch_um):
    if pixel_pitch_um is None:
        raise InvalidInputError("the photogrammetric model needs pixel_pitch_um (a number or (px, py) in micrometres)")
    pp = np.broadcast_to(np.asarray(pixel_pitch_um, dtype=np.float64), (2,))
    return pp[0] * 1e-3, pp[1] * 1e-3


def _centre(image_size):
    w, h = image_size
    return 0.5 * (w - 1), 0.5 * (h - 1)


def px_to_mm(xy_px, image_size, pixel_pitch_um):
    """Pixel (N, 2) -> photogrammetric image coordinates (N, 2) in mm (centre origin, y up)."""
    sx, sy = _pitch_mm(pixel_pitch_um)
    u0, v0 = _centre(image_size)
    xy = np.asarray(xy_px, dtype=np.float64)
    return np.stack([(xy[:, 0] - u0) * sx, -(xy[:, 1] - v0) * sy], axis=-1)


def mm_to_px(xy_mm, image_size, pixel_pitch_um):
    """Inverse of :func:`px_to_mm`."""
    sx, sy = _pitch_mm(pixel_pitch_um)
    u0, v0 = _centre(image_size)
    xy = np.asarray(xy_mm, dtype=np.float64)
    return np.stack([xy[:, 0] / sx + u0, -xy[:, 1] / sy + v0], axis=-1)


def photogrammetric_correction(params, xb):
    """Correction (dx, dy) in mm at reduced measured coordinates ``xb = (x - x0, y - y0)`` (N, 2) mm."""
    p = np.asarray(params, dtype=np.float64)
    K1, K2, K3, K4, K5, P1, P2, B1, B2 = p[3:]
    x, y = xb[:, 0], xb[:, 1]
    r2 = x * x + y * y
    dr = r2 * (K1 + r2 * (K2 + r2 * (K3 + r2 * (K4 + r2 * K5))))
    dx = x * dr + P1 * (r2 + 2.0 * x * x) + 2.0 * P2 * x * y + B1 * x + B2 * y
    dy = y * dr + 2.0 * P1 * x * y + P2 * (r2 + 2.0 * y * y)
    return np.stack([dx, dy], axis=-1)


def photogrammetric_correction_jacobian(params, xb, wrt_params: bool = True):
    """``F = xb + correction(xb)`` with Jacobians ``(F (N,2), dF/dxb (N,2,2), dF/dparams (N,2,12))``.

    ``dF/dparams`` is zero in the columns of c, x0, y0 (``xb`` is the variable); ``wrt_params=False``
    skips it (None).
    """
    p = np.asarray(params, dtype=np.float64)
    K1, K2, K3, K4, K5, P1, P2, B1, B2 = p[3:]
    x, y = xb[:, 0], xb[:, 1]
    n = x.shape[0]
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    r8 = r4 * r4
    r10 = r8 * r2
    dr = K1 * r2 + K2 * r4 + K3 * r6 + K4 * r8 + K5 * r10
    ddr = K1 + 2.0 * K2 * r2 + 3.0 * K3 * r4 + 4.0 * K4 * r6 + 5.0 * K5 * r8  # d dr / d r2
    Fx = x + x * dr + P1 * (r2 + 2.0 * x * x) + 2.0 * P2 * x * y + B1 * x + B2 * y
    Fy = y + y * dr + 2.0 * P1 * x * y + P2 * (r2 + 2.0 * y * y)
    Js = np.empty((n, 2, 2))
    cross = 2.0 * x * y * ddr + 2.0 * P1 * y + 2.0 * P2 * x
    Js[:, 0, 0] = 1.0 + dr + 2.0 * x * x * ddr + 6.0 * P1 * x + 2.0 * P2 * y + B1
    Js[:, 0, 1] = cross + B2
    Js[:, 1, 0] = cross
    Js[:, 1, 1] = 1.0 + dr + 2.0 * y * y * ddr + 2.0 * P1 * x + 6.0 * P2 * y
    if not wrt_params:
        return np.stack([Fx, Fy], axis=-1), Js, None
    Jt = np.zeros((n, 2, 12))
    for col, rk in zip(range(3, 8), (r2, r4, r6, r8, r10)):
        Jt[:, 0, col] = x * rk
        Jt[:, 1, col] = y * rk
    Jt[:, 0, 8] = r2 + 2.0 * x * x
    Jt[:, 1, 8] = 2.0 * x * y
    Jt[:, 0, 9] = 2.0 * x * y
    Jt[:, 1, 9] = r2 + 2.0 * y * y
    Jt[:, 0, 10] = x
    Jt[:, 0, 11] = y
    return np.stack([Fx, Fy], axis=-1), Js, Jt


def photogrammetric_unproject(params, xy_px, image_size, pixel_pitch_um):
    """Closed-form rays (N, 3) with z = 1 through measured pixels (N, 2)."""
    p = np.asarray(params, dtype=np.float64)
    c, x0, y0 = p[:3]
    xy_mm = px_to_mm(xy_px, image_size, pixel_pitch_um)
    xb = xy_mm - np.array([x0, y0])
    F = xb + photogrammetric_correction(p, xb)
    return np.stack([F[:, 0] / c, -F[:, 1] / c, np.ones(F.shape[0])], axis=-1)


def _photogrammetric_solve(p, target, max_iter=_MAX_ITER):
    """Newton solve of ``xb + correction(xb) = target`` (N, 2) mm; returns (xb, converged)."""
    xb = target.copy()
    active = np.ones(target.shape[0], dtype=bool)
    for _ in range(max_iter):
        if not active.any():
            break
        idx = np.flatnonzero(active)
        F, Js, _ = photogrammetric_correction_jacobian(p, xb[idx], wrt_params=False)
        step = _solve2(Js, F - target[idx])
        xb[idx] -= step
        bad = ~np.all(np.isfinite(xb[idx]), axis=1)
        small = np.max(np.abs(step), axis=1) <= 1e-15 * (1.0 + np.max(np.abs(xb[idx]), axis=1))
        active[idx[small | bad]] = False
    F = xb + photogrammetric_correction(p, xb)
    resid = np.max(np.abs(F - target), axis=1)
    scale = 1.0 + np.max(np.abs(target), axis=1)
    converged = np.isfinite(resid) & (resid <= 1e-12 * scale)
    # Accept only the main sheet of the map: its Jacobian must have positive determinant and
    # trace there (near the centre it is ~identity). Beyond the fold of the polynomial Newton can
    # land on a mirrored branch with det > 0 but both eigenvalues negative.
    if converged.any():
        _, Js, _ = photogrammetric_correction_jacobian(p, xb[converged], wrt_params=False)
        det = Js[:, 0, 0] * Js[:, 1, 1] - Js[:, 0, 1] * Js[:, 1, 0]
        tr = Js[:, 0, 0] + Js[:, 1, 1]
        converged[np.flatnonzero(converged)[(det <= 0) | (tr <= 0)]] = False
    xb[~converged] = np.nan
    return xb, converged


def photogrammetric_project_solve(params, points_cam, image_size, pixel_pitch_um):
    """Projected pixels (N, 2) and the convergence mask (N,) of the Newton solve."""
    p = np.asarray(params, dtype=np.float64)
    c, x0, y0 = p[:3]
    X, Y, Z = _xyz(points_cam)
    target = np.stack([c * X / Z, -c * Y / Z], axis=-1)
    xb, ok = _photogrammetric_solve(p, target)
    return mm_to_px(xb + np.array([x0, y0]), image_size, pixel_pitch_um), ok


def photogrammetric_project(params, points_cam, image_size, pixel_pitch_um):
    """Project (N, 3) points with the correction-form model; (N, 2) px, NaN where Newton fails."""
    return photogrammetric_project_solve(params, points_cam, image_size, pixel_pitch_um)[0]


def photogrammetric_project_jacobian(params, points_cam, image_size, pixel_pitch_um, wrt_params: bool = True):
    """Projection and Jacobians ``(xy (N,2), J_point (N,2,3), J_params (N,2,12))``.

    ``wrt_params=False`` skips the parameter Jacobian (returned as None).

    Implicit-function theorem on ``G(xb, theta, X) = xb + d(xb; theta) - T(theta, X) = 0``
    with ``T = (c X/Z, -c Y/Z)``: ``d xb = (dG/dxb)^-1 (dT - dd/dtheta dtheta)``; then
    ``u = (x0 + xb)/px_mm + (w-1)/2``, ``v = -(y0 + yb)/py_mm + (h-1)/2``.
    """
    p = np.asarray(params, dtype=np.float64)
    c, x0, y0 = p[:3]
    sx, sy = _pitch_mm(pixel_pitch_um)
    X, Y, Z = _xyz(points_cam)
    n = X.shape[0]
    iz = 1.0 / Z
    xn, yn = X * iz, Y * iz
    target = np.stack([c * xn, -c * yn], axis=-1)
    xb, _ = _photogrammetric_solve(p, target)
    _, Js, Jd = photogrammetric_correction_jacobian(p, xb, wrt_params=wrt_params)
    Jinv = _inv2(Js)
    # d T / d X
    JT = np.zeros((n, 2, 3))
    JT[:, 0, 0] = c * iz
    JT[:, 0, 2] = -c * xn * iz
    JT[:, 1, 1] = -c * iz
    JT[:, 1, 2] = c * yn * iz
    dxb_dX = Jinv @ JT
    S = np.array([1.0 / sx, -1.0 / sy])[None, :, None]
    xy = mm_to_px(xb + np.array([x0, y0]), image_size, pixel_pitch_um)
    if not wrt_params:
        return xy, dxb_dX * S, None
    # d T / d theta minus d correction / d theta (only c enters T)
    rhs = -Jd
    rhs[:, 0, 0] += xn
    rhs[:, 1, 0] += -yn
    dxb_dt = Jinv @ rhs
    dxb_dt[:, 0, 1] += 1.0  # x = x0 + xb
    dxb_dt[:, 1, 2] += 1.0  # y = y0 + yb
    return xy, dxb_dX * S, dxb_dt * S


# ----------------------------------------------------------------------------------------------
# dispatch
# ----------------------------------------------------------------------------------------------
def project(model, params, points_cam, *, image_size=None, pixel_pitch_um=None):
    """Project (N, 3) camera-frame points to (N, 2) pixels with any model."""
    model = CameraModel(model)
    if model is CameraModel.PINHOLE:
        return pinhole_project(params, points_cam)
    if model is CameraModel.OPENCV:
        return opencv_project(params, points_cam)
    return photogrammetric_project(params, points_cam, image_size, pixel_pitch_um)


def project_jacobian(model, params, points_cam, *, image_size=None, pixel_pitch_um=None, wrt_params: bool = True):
    """``(xy (N,2), J_point (N,2,3), J_params (N,2,P))`` for any model.

    ``wrt_params=False``: point Jacobian only, ``J_params`` is None (cheaper; what triangulation
    and resection with fixed interior orientation need).
    """
    model = CameraModel(model)
    if model is CameraModel.PINHOLE:
        return pinhole_project_jacobian(params, points_cam, wrt_params)
    if model is CameraModel.OPENCV:
        return opencv_project_jacobian(params, points_cam, wrt_params)
    return photogrammetric_project_jacobian(params, points_cam, image_size, pixel_pitch_um, wrt_params)


def unproject(model, params, xy_px, *, image_size=None, pixel_pitch_um=None):
    """Rays (N, 3) with z = 1 (undistorted) through (N, 2) measured pixels."""
    model = CameraModel(model)
    if model is CameraModel.PINHOLE:
        return pinhole_unproject(params, xy_px)
    if model is CameraModel.OPENCV:
        return opencv_unproject(params, xy_px)
    return photogrammetric_unproject(params, xy_px, image_size, pixel_pitch_um)


def ideal_K(model, params, *, image_size=None, pixel_pitch_um=None):
    """(3, 3) ideal pinhole matrix in px: ``[[fx, skew, cx], [0, fy, cy], [0, 0, 1]]``.

    For the photogrammetric model ``fx = c/px_mm``, ``fy = c/py_mm``,
    ``cx = (w-1)/2 + x0/px_mm``, ``cy = (h-1)/2 - y0/py_mm``, skew = 0.
    """
    model = CameraModel(model)
    p = np.asarray(params, dtype=np.float64)
    if model is CameraModel.PINHOLE:
        fx, fy, cx, cy = p
        skew = 0.0
    elif model is CameraModel.OPENCV:
        fx, fy, cx, cy, skew = p[:5]
    else:
        c, x0, y0 = p[:3]
        sx, sy = _pitch_mm(pixel_pitch_um)
        u0, v0 = _centre(image_size)
        fx, fy, cx, cy, skew = c / sx, c / sy, u0 + x0 / sx, v0 - y0 / sy, 0.0
    return np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
