"""Planes picked by marked points (seed 000 eq. 5–6), with precision propagated from the network.

A plane ``A X + B Y + C Z + D = 0`` (eq. 5) is fitted to 3 or more points by total least squares
(unit normal = the singular vector of the centred points with the smallest singular value; exact for
3 points). The angle η between a camera's axis and the normal follows eq. 6,

    cos η = |[A B C] · a| / ‖[A B C]‖,     a = unit viewing axis (``R[2]``, world),

(the paper writes ``a = m⁻¹ [0 0 1]ᵀ`` with ``m`` its rotation matrix; the absolute value makes η
independent of the normal's sign, which we orient towards the thermal camera).

References
----------
Sawicki, Stein, Więcek (seed 000) eq. 5–6.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..errors import DegenerateInputError, TooFewPointsError

__all__ = ["fit_plane", "check_plane_points", "angle_to_axis", "PlaneEstimate", "plane_jacobian"]


def check_plane_points(points, name: str, ids: Sequence[str] | None = None, *, rel_tol: float = 1e-6) -> None:
    """Raise when the points of plane ``name`` cannot define a plane (< 3 points or collinear)."""
    P = np.asarray(points, float).reshape(-1, 3)
    idtxt = f" ({', '.join(map(str, ids))})" if ids is not None else ""
    if len(P) < 3:
        raise TooFewPointsError(f"plane {name!r}: {len(P)} point(s){idtxt}; a plane needs 3 or more points")
    sv = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    if sv[1] <= rel_tol * max(sv[0], 1e-300):
        raise DegenerateInputError(
            f"plane {name!r}: its points{idtxt} are collinear (second/first spread {sv[1] / max(sv[0], 1e-300):.1e}); "
            "pick 3 points that span a triangle on the surface"
        )


def fit_plane(points) -> tuple[np.ndarray, float, float]:
    """Total-least-squares plane through (N ≥ 3, 3) points (m).

    Returns
    -------
    normal : (3,) unit normal ``[A B C]``
    d : float, ``D`` with ``normal · X + d = 0``
    rms_m : RMS distance of the points from the plane (0 for 3 points)
    """
    P = np.asarray(points, float)
    c = P.mean(axis=0)
    _, sv, vt = np.linalg.svd(P - c)
    n = vt[-1]
    rms = float(sv[-1] / np.sqrt(len(P))) if len(P) > 3 else 0.0
    return n, float(-n @ c), rms


def plane_jacobian(points, n_ref) -> np.ndarray:
    """(4, 3N) derivative of ``(normal, d)`` (normal sign aligned with ``n_ref``) w.r.t. the stacked points.

    Central differences on :func:`fit_plane` (the SVD is smooth for a well-defined plane).
    """
    P = np.asarray(points, float)
    flat = P.ravel()
    G = np.zeros((4, flat.size))
    h = 1e-7

    def f(x):
        n, d, _ = fit_plane(x.reshape(-1, 3))
        if n @ n_ref < 0:
            n, d = -n, -d
        return np.append(n, d)

    for k in range(flat.size):
        e = np.zeros_like(flat)
        e[k] = h
        G[:, k] = (f(flat + e) - f(flat - e)) / (2 * h)
    return G


def angle_to_axis(normal, axis) -> np.ndarray:
    """Seed 000 eq. 6: angle η (rad) between unit viewing axes (..., 3) and plane normals (..., 3)."""
    n = np.asarray(normal, float)
    a = np.asarray(axis, float)
    c = np.abs(np.sum(n * a, axis=-1)) / (np.linalg.norm(n, axis=-1) * np.linalg.norm(a, axis=-1))
    return np.arccos(np.clip(c, 0.0, 1.0))


@dataclass
class PlaneEstimate:
    """A plane of the object with its geometry relative to the thermal camera.

    Attributes
    ----------
    name, ids : the plane and its marked points
    normal : (3,) unit normal, oriented towards the thermal camera
    d : offset (m), ``normal · X + d = 0``
    centroid : (3,) m
    rms_m : residual of the fit (m)
    angle_rad, sigma_angle_rad : η between the thermal camera's axis and the normal (eq. 6) and its σ
    los_angle_rad : angle between the line of sight to the centroid and the normal
    distance_m, sigma_distance_m : thermal projection centre → centroid
    perpendicular_m : distance of the projection centre from the plane
    cov_normal : (3, 3) covariance of the normal
    J_nd : (4, n_obs) derivative of (normal, d) w.r.t. the observations
    """

    name: str
    ids: tuple[str, ...]
    normal: np.ndarray
    d: float
    centroid: np.ndarray
    rms_m: float
    angle_rad: float
    sigma_angle_rad: float
    los_angle_rad: float
    distance_m: float
    sigma_distance_m: float
    perpendicular_m: float
    cov_normal: np.ndarray
    J_nd: np.ndarray
