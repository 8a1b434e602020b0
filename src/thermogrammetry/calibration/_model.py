"""Correction-form (photogrammetric) camera model used by the self-calibration, with analytic Jacobians.

This is the model of ``docs/conventions.md`` ("Correction form", Fraser 1997), written here as
pure vectorised functions so that the self-calibrating bundle adjustment has exact derivatives of
the *measured* image coordinates with respect to every parameter. It is the same model as
``thermogrammetry.camera`` model ``"photogrammetric"``; ``tests/test_calibration_model.py``
checks that both agree when the camera package is present.

Parameter layout (``PARAM_NAMES``; units of the published tables, e.g. seed 001 Table 2)::

    0 c_mm   principal distance (mm, positive)
    1 x0_mm  principal point, offset from the image centre, x right (mm)
    2 y0_mm  principal point, offset from the image centre, y UP (mm)
    3 K1 (mm^-2)  4 K2 (mm^-4)  5 K3 (mm^-6)  6 K4 (mm^-8)  7 K5 (mm^-10)
    8 P1 (mm^-1)  9 P2 (mm^-1)  10 B1 (-)  11 B2 (-)

Correction (evaluated at the measured coordinates, x̄ = x − x0, ȳ = y − y0, r² = x̄² + ȳ²)::

    Δx = x̄ (K1 r² + K2 r⁴ + K3 r⁶ + K4 r⁸ + K5 r¹⁰) + P1 (r² + 2 x̄²) + 2 P2 x̄ ȳ + B1 x̄ + B2 ȳ
    Δy = ȳ (K1 r² + K2 r⁴ + K3 r⁶ + K4 r⁸ + K5 r¹⁰) + 2 P1 x̄ ȳ + P2 (r² + 2 ȳ²)

and collinearity ``x − x0 + Δx = −c Xp/Zp = c Xc/Zc``, ``y − y0 + Δy = −c Yp/Zp = −c Yc/Zc`` with
the camera frame of the conventions (x right, y down, z forward; photo = diag(1, −1, −1) · cam).
Seed 001 eq. 2 is garbled in the conversion (it mixes the Δc / Δx0 terms into Δx); we follow
Brown (1971) / Fraser (1997) as above. Seed 003 eq. 1 repeats P1 where P2 is meant in Δy; we use
the standard ``2 P2 x̄ ȳ`` in Δx and ``P2 (r² + 2ȳ²)`` in Δy (Fraser 1997).

Projection solves ``x̄ + Δ(x̄) = a`` for the measured x̄ by Newton's method; the derivatives of the
measured coordinates follow from the implicit-function theorem
``dx̄ = (I + ∂Δ/∂x̄)⁻¹ (da − ∂Δ/∂θ dθ)``.

References
----------
Brown, D.C., 1971. Close-range camera calibration. Photogrammetric Engineering 37(8), 855–866.
Fraser, C.S., 1997. Digital camera self-calibration. ISPRS J. Photogramm. Remote Sens. 52, 149–159.
Yastikli, N., Guler, E., 2013. Performance evaluation of thermographic cameras for photogrammetric
measurements. ISPRS Arch. XL-1/W1 (seed 001).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "PARAM_NAMES",
    "PARAM_UNITS",
    "N_PARAMS",
    "px_to_mm",
    "mm_to_px",
    "correction",
    "correction_jacobians",
    "ideal_from_measured_mm",
    "measured_from_ideal_mm",
    "project",
]

PARAM_NAMES: tuple[str, ...] = ("c_mm", "x0_mm", "y0_mm", "K1", "K2", "K3", "K4", "K5", "P1", "P2", "B1", "B2")
PARAM_UNITS: tuple[str, ...] = ("mm", "mm", "mm", "mm^-2", "mm^-4", "mm^-6", "mm^-8", "mm^-10", "mm^-1", "mm^-1", "1", "1")
N_PARAMS = len(PARAM_NAMES)


def px_to_mm(xy_px: np.ndarray, image_size, pitch_mm) -> np.ndarray:
    """OpenCV pixel coordinates (N,2) -> photogrammetric image coordinates in mm (centre origin, y up)."""
    w, h = image_size
    px, py = pitch_mm
    xy_px = np.asarray(xy_px, dtype=float)
    return np.stack([(xy_px[..., 0] - (w - 1) / 2.0) * px, -(xy_px[..., 1] - (h - 1) / 2.0) * py], axis=-1)


def mm_to_px(xy_mm: np.ndarray, image_size, pitch_mm) -> np.ndarray:
    """Inverse of :func:`px_to_mm`."""
    w, h = image_size
    px, py = pitch_mm
    xy_mm = np.asarray(xy_mm, dtype=float)
    return np.stack([xy_mm[..., 0] / px + (w - 1) / 2.0, -xy_mm[..., 1] / py + (h - 1) / 2.0], axis=-1)


def correction(xb: np.ndarray, yb: np.ndarray, p: np.ndarray):
    """Δx, Δy (mm) at principal-point-reduced coordinates x̄, ȳ (mm); ``p`` is the (12,) layout."""
    K = p[3:8]
    P1, P2, B1, B2 = p[8], p[9], p[10], p[11]
    r2 = xb * xb + yb * yb
    rad = r2 * (K[0] + r2 * (K[1] + r2 * (K[2] + r2 * (K[3] + r2 * K[4]))))
    dx = xb * rad + P1 * (r2 + 2 * xb * xb) + 2 * P2 * xb * yb + B1 * xb + B2 * yb
    dy = yb * rad + 2 * P1 * xb * yb + P2 * (r2 + 2 * yb * yb)
    return dx, dy


def correction_jacobians(xb: np.ndarray, yb: np.ndarray, p: np.ndarray):
    """Derivatives of the correction.

    Returns
    -------
    D : (N, 2, 2)
        ∂(Δx, Δy)/∂(x̄, ȳ).
    Jp : (N, 2, 12)
        ∂(Δx, Δy)/∂p for the distortion entries (columns 3..11); columns 0..2 are zero
        (c does not enter Δ; x0, y0 enter through x̄, ȳ and are handled by the caller).
    """
    K = p[3:8]
    P1, P2, B1, B2 = p[8], p[9], p[10], p[11]
    r2 = xb * xb + yb * yb
    rad = r2 * (K[0] + r2 * (K[1] + r2 * (K[2] + r2 * (K[3] + r2 * K[4]))))
    drad = K[0] + r2 * (2 * K[1] + r2 * (3 * K[2] + r2 * (4 * K[3] + r2 * 5 * K[4])))
    n = xb.shape[0]
    D = np.empty((n, 2, 2))
    D[:, 0, 0] = rad + 2 * xb * xb * drad + 6 * P1 * xb + 2 * P2 * yb + B1
    D[:, 0, 1] = 2 * xb * yb * drad + 2 * P1 * yb + 2 * P2 * xb + B2
    D[:, 1, 0] = 2 * xb * yb * drad + 2 * P1 * yb + 2 * P2 * xb
    D[:, 1, 1] = rad + 2 * yb * yb * drad + 2 * P1 * xb + 6 * P2 * yb
    Jp = np.zeros((n, 2, N_PARAMS))
    rp = r2.copy()
    for i in range(5):
        Jp[:, 0, 3 + i] = xb * rp
        Jp[:, 1, 3 + i] = yb * rp
        rp = rp * r2
    Jp[:, 0, 8] = r2 + 2 * xb * xb
    Jp[:, 1, 8] = 2 * xb * yb
    Jp[:, 0, 9] = 2 * xb * yb
    Jp[:, 1, 9] = r2 + 2 * yb * yb
    Jp[:, 0, 10] = xb
    Jp[:, 0, 11] = yb
    return D, Jp


def ideal_from_measured_mm(xy_mm: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Corrected (ideal) coordinates ``x̄ + Δx`` (mm, relative to the principal point), closed form."""
    xb = xy_mm[:, 0] - p[1]
    yb = xy_mm[:, 1] - p[2]
    dx, dy = correction(xb, yb, p)
    return np.stack([xb + dx, yb + dy], axis=1)


def measured_from_ideal_mm(a: np.ndarray, b: np.ndarray, p: np.ndarray, *, iterations: int = 30, tol_mm: float = 1e-12,
                           start: np.ndarray | None = None):
    """Solve ``x̄ + Δx(x̄, ȳ) = a``, ``ȳ + Δy(x̄, ȳ) = b`` for x̄, ȳ (mm) by Newton's method.

    ``start`` (N,2): optional starting values of x̄, ȳ (e.g. the measured point); default ``(a, b)``.
    Returns ``(xb, yb, D, converged)`` with ``D = ∂Δ/∂x̄`` at the solution and ``converged`` (N,) bool.
    """
    if start is None:
        xb = a.copy()
        yb = b.copy()
    else:
        xb = np.array(start[:, 0], dtype=float)
        yb = np.array(start[:, 1], dtype=float)
    converged = np.zeros(a.shape[0], dtype=bool)
    for _ in range(iterations):
        dx, dy = correction(xb, yb, p)
        fx = xb + dx - a
        fy = yb + dy - b
        D = _correction_D(xb, yb, p)
        a11 = 1 + D[:, 0, 0]
        a12 = D[:, 0, 1]
        a21 = D[:, 1, 0]
        a22 = 1 + D[:, 1, 1]
        det = a11 * a22 - a12 * a21
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        sx = (a22 * fx - a12 * fy) / det
        sy = (-a21 * fx + a11 * fy) / det
        xb = xb - sx
        yb = yb - sy
        step = np.maximum(np.abs(sx), np.abs(sy))
        converged = step < tol_mm
        if np.all(converged):
            break
    D = _correction_D(xb, yb, p)
    ok = converged & np.isfinite(xb) & np.isfinite(yb)
    return xb, yb, D, ok


def _correction_D(xb, yb, p):
    """∂(Δx, Δy)/∂(x̄, ȳ) only (N,2,2) -- the part Newton's method needs."""
    K = p[3:8]
    P1, P2, B1, B2 = p[8], p[9], p[10], p[11]
    r2 = xb * xb + yb * yb
    rad = r2 * (K[0] + r2 * (K[1] + r2 * (K[2] + r2 * (K[3] + r2 * K[4]))))
    drad = K[0] + r2 * (2 * K[1] + r2 * (3 * K[2] + r2 * (4 * K[3] + r2 * 5 * K[4])))
    D = np.empty((xb.shape[0], 2, 2))
    cross = 2 * xb * yb * drad + 2 * P1 * yb + 2 * P2 * xb
    D[:, 0, 0] = rad + 2 * xb * xb * drad + 6 * P1 * xb + 2 * P2 * yb + B1
    D[:, 0, 1] = cross + B2
    D[:, 1, 0] = cross
    D[:, 1, 1] = rad + 2 * yb * yb * drad + 2 * P1 * xb + 6 * P2 * yb
    return D


def project(points_cam: np.ndarray, p: np.ndarray, image_size, pitch_mm, *, jacobians: bool = True,
            start_px: np.ndarray | None = None):
    """Measured pixel coordinates of camera-frame points, with Jacobians.

    Parameters
    ----------
    points_cam : (N, 3) float, metres, camera frame (x right, y down, z forward).
    p : (12,) parameters, layout ``PARAM_NAMES``.
    image_size : (w, h) pixels.
    pitch_mm : (px, py) pixel pitch in mm.

    Returns
    -------
    xy_px : (N, 2) OpenCV pixel coordinates of the *measured* (distorted) image point.
    J_point : (N, 2, 3) ∂xy_px/∂points_cam (only when ``jacobians``).
    J_params : (N, 2, 12) ∂xy_px/∂p (only when ``jacobians``).
    ok : (N,) bool, in front of the camera and Newton converged.

    ``start_px`` (N,2): optional starting pixels for Newton's method (the measured points are an
    excellent start inside an adjustment); the solution does not depend on it.
    """
    X, Y, Z = points_cam[:, 0], points_cam[:, 1], points_cam[:, 2]
    c = p[0]
    front = Z > 1e-12
    Zs = np.where(front, Z, 1.0)
    xn = X / Zs
    yn = Y / Zs
    a = c * xn
    b = -c * yn
    w, h = image_size
    pxm, pym = pitch_mm
    start = None
    if start_px is not None:
        start = np.stack([(start_px[:, 0] - (w - 1) / 2.0) * pxm - p[1], -(start_px[:, 1] - (h - 1) / 2.0) * pym - p[2]], axis=1)
    xb, yb, D, ok = measured_from_ideal_mm(a, b, p, start=start)
    ok &= front
    u = (xb + p[1]) / pxm + (w - 1) / 2.0
    v = -(yb + p[2]) / pym + (h - 1) / 2.0
    xy = np.stack([u, v], axis=1)
    if not jacobians:
        return xy, None, None, ok
    n = X.shape[0]
    # M = (I + D)^-1
    a11 = 1 + D[:, 0, 0]
    a12 = D[:, 0, 1]
    a21 = D[:, 1, 0]
    a22 = 1 + D[:, 1, 1]
    det = a11 * a22 - a12 * a21
    Minv = np.empty((n, 2, 2))
    Minv[:, 0, 0] = a22 / det
    Minv[:, 0, 1] = -a12 / det
    Minv[:, 1, 0] = -a21 / det
    Minv[:, 1, 1] = a11 / det
    # d(a, b)/d(points_cam)
    Jab = np.zeros((n, 2, 3))
    Jab[:, 0, 0] = c / Zs
    Jab[:, 0, 2] = -c * X / Zs**2
    Jab[:, 1, 1] = -c / Zs
    Jab[:, 1, 2] = c * Y / Zs**2
    # d(a, b)/dp and -dΔ/dp
    _, Jd = correction_jacobians(xb, yb, p)
    Jrhs = -Jd
    Jrhs[:, 0, 0] = xn
    Jrhs[:, 1, 0] = -yn
    Jxb_p = Minv @ Jrhs  # d(xb, yb)/dp
    Jxb_pt = Minv @ Jab
    # measured x = xb + x0, y = yb + y0
    Jxb_p[:, 0, 1] += 1.0
    Jxb_p[:, 1, 2] += 1.0
    scale = np.array([1.0 / pxm, -1.0 / pym])
    J_params = Jxb_p * scale[None, :, None]
    J_point = Jxb_pt * scale[None, :, None]
    return xy, J_point, J_params, ok
