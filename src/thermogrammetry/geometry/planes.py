"""Planes: from 3 points, from N points (least squares with the precision of the normal), the angle
between a camera's axis (or each ray) and the plane normal (seed 000 eq. 5–6), and the
camera-to-surface distance along the axis and along rays.

A plane is ``A X + B Y + C Z + D = 0`` (seed 000 eq. 5), stored with a unit normal
``n = (A, B, C)/‖(A, B, C)‖`` and ``d = D/‖(A, B, C)‖``.

Seed 000 eq. 6::

    cos η = [A B C] · m⁻¹ · [0 0 1]ᵀ / ‖[A B C]‖

with ``m`` the photogrammetric rotation (photo_from_world, ``M = diag(1,−1,−1)·R``), so
``m⁻¹ [0 0 1]ᵀ = Mᵀ e3`` is the image-space z axis in the world (pointing *back* from the
scene to the camera). The sign of ``cos η`` depends on the orientation of the normal, which for
a plane through 3 picked points is arbitrary; the functions return ``η = arccos |cos η|`` in
[0, π/2] — the viewing angle used by the directional-emissivity correction (eq. 7–8).

References
----------
Sawicki, P., Stein, R., Więcek, B. Directional emissivity correction by photogrammetric 3D object
reconstruction (seed 000), eq. 5–7.
Förstner, W., Wrobel, B. P. (2016). *Photogrammetric Computer Vision*, §10.5.2 (plane fitting and its precision).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._validate import as_array, as_points
from ..adjustment.dense import DenseOptions, solve_dense
from ..errors import DegenerateInputError, InvalidInputError, TooFewPointsError
from ..results import Outcome, Termination
from . import rotations as rot
from ._camera import as_camera
from .pose import Pose

__all__ = [
    "Plane",
    "plane_from_3_points",
    "plane_from_points",
    "angle_to_camera_axis",
    "ray_angles",
    "distance_along_axis",
    "distance_along_rays",
]

_COLLINEAR_TOL = 1e-9


@dataclass(frozen=True, eq=False)
class Plane:
    """``normal · X + d = 0`` with a unit normal.

    Attributes
    ----------
    normal : ndarray (3,)
    d : float
        Metres; ``−d`` is the signed distance of the origin along ``normal``.
    covariance : ndarray (4, 4) or None
        A posteriori covariance of ``(n_x, n_y, n_z, d)`` (rank 3: the normal has unit length).
    covariance_prior : ndarray (4, 4) or None
        With the a-priori point σ.
    sigma0 : float
        A posteriori σ0 (NaN for 3 points).
    rms_m : float
        RMS of the point-to-plane distances.
    residuals_m : ndarray (N,)
        Signed distances of the fitted points.
    name : str
    outcome : Outcome
    """

    normal: np.ndarray
    d: float
    covariance: np.ndarray | None = None
    covariance_prior: np.ndarray | None = None
    sigma0: float = float("nan")
    rms_m: float = 0.0
    residuals_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    name: str = "plane"
    outcome: Outcome = Outcome(Termination.CONVERGED, "")

    def __post_init__(self):
        n = as_array(self.normal, "normal", shape=(3,))
        nn = np.linalg.norm(n)
        if nn < 1e-300:
            raise DegenerateInputError(f"{self.name}: zero normal vector; expected a non-zero (A, B, C)")
        object.__setattr__(self, "normal", n / nn)
        object.__setattr__(self, "d", float(self.d) / nn)

    @classmethod
    def from_abcd(cls, A, B, C, D, name: str = "plane") -> "Plane":
        """From the coefficients of ``A X + B Y + C Z + D = 0`` (seed 000 eq. 5)."""
        return cls(np.array([A, B, C], float), float(D), name=name)

    @property
    def abcd(self) -> np.ndarray:
        """(4,) ``(A, B, C, D)`` with unit ``(A, B, C)``."""
        return np.append(self.normal, self.d)

    def signed_distance(self, points) -> np.ndarray:
        """(N,) signed distances (m) of points from the plane (positive on the normal's side)."""
        X = as_points(points, "points", 3)
        return X @ self.normal + self.d

    def project(self, points) -> np.ndarray:
        """Orthogonal projection of (N, 3) points onto the plane."""
        X = as_points(points, "points", 3)
        return X - (X @ self.normal + self.d)[:, None] * self.normal

    @property
    def normal_std_deg(self) -> float:
        """A posteriori angular σ of the normal (degrees, RMS over the two tilt directions); NaN if unknown."""
        if self.covariance is None or not np.all(np.isfinite(self.covariance)):
            return float("nan")
        return float(np.degrees(np.sqrt(np.trace(self.covariance[:3, :3]) / 2.0)))


def plane_from_3_points(p1, p2, p3, *, name: str = "plane") -> Plane:
    """Plane through three points (seed 000: "groups of 3 points marked by the user").

    Parameters
    ----------
    p1, p2, p3 : array_like (3,)
        Metres. Their order fixes the normal's direction: ``n ∝ (p2 − p1) × (p3 − p1)``.
    name : str
        Used in error messages (e.g. ``"plane 'roof'"``).

    Raises
    ------
    DegenerateInputError
        The points are collinear (or coincide): the plane is undefined.
    """
    a = as_array(p1, f"{name}: p1", shape=(3,))
    b = as_array(p2, f"{name}: p2", shape=(3,))
    c = as_array(p3, f"{name}: p3", shape=(3,))
    n = np.cross(b - a, c - a)
    scale = max(np.linalg.norm(b - a) * np.linalg.norm(c - a), np.linalg.norm(b - a) ** 2, np.linalg.norm(c - b) ** 2)
    if scale == 0 or np.linalg.norm(n) <= _COLLINEAR_TOL * scale:
        raise DegenerateInputError(
            f"{name}: the 3 points {a.tolist()}, {b.tolist()}, {c.tolist()} are collinear or coincide; "
            "a plane needs 3 points that span a triangle"
        )
    nn = n / np.linalg.norm(n)
    return Plane(nn, -float(nn @ a), name=name, residuals_m=np.zeros(3),
                 outcome=Outcome(Termination.CONVERGED, "exact plane through 3 points (no redundancy)"))


def plane_from_points(points, *, sigma_m: float = 1.0, weights=None, name: str = "plane",
                      options: DenseOptions | None = None) -> Plane:
    """Least-squares plane through N ≥ 3 points (orthogonal distances) with the precision of the normal.

    Closed form from the eigenvector of the smallest eigenvalue of the (weighted) scatter matrix,
    then a constrained Gauss–Markov adjustment (observations: point-to-plane distances, constraint
    ``‖n‖ = 1``) giving the covariance of ``(n, d)``.

    Parameters
    ----------
    points : array_like (N, 3)
        Metres.
    sigma_m : float
        A-priori σ of a point-to-plane distance (m) for ``covariance_prior``.
    weights : array_like (N,), optional
    name : str
        Used in error messages.

    Raises
    ------
    TooFewPointsError, DegenerateInputError (collinear points), ShapeError, NonFiniteError
    """
    X = as_points(points, f"{name}: points", 3)
    n_pts = X.shape[0]
    if n_pts < 3:
        raise TooFewPointsError(f"{name}: a plane needs at least 3 points, got {n_pts}")
    w = np.ones(n_pts) if weights is None else as_array(weights, f"{name}: weights", shape=(n_pts,))
    if np.any(w < 0) or w.sum() <= 0:
        raise InvalidInputError(f"{name}: weights must be ≥ 0 and not all zero")
    if not (np.isfinite(sigma_m) and sigma_m > 0):
        raise InvalidInputError(f"sigma_m: {sigma_m!r}; expected a positive number of metres")
    mean = (w @ X) / w.sum()
    Xc = X - mean
    S = (Xc * w[:, None]).T @ Xc
    ev, evec = np.linalg.eigh(S)
    if ev[1] <= _COLLINEAR_TOL * max(ev[2], 1e-300) or ev[2] <= 0:
        raise DegenerateInputError(
            f"{name}: the {n_pts} points are collinear (or coincide); a plane needs points that span an area"
        )
    n0 = evec[:, 0]
    if n_pts == 3:
        return plane_from_3_points(X[0], X[1], X[2], name=name)
    # parameters (n, d') with d' relative to the centroid (conditioning): n·(X − mean) + d' = 0
    p0 = np.append(n0, 0.0)

    def fun(p):
        v = Xc @ p[:3] + p[3]
        return v, np.hstack([Xc, np.ones((n_pts, 1))])

    def cons(p):
        return np.array([p[:3] @ p[:3] - 1.0]), np.append(2 * p[:3], 0.0)[None, :]

    adj = solve_dense(fun, p0, weights=w / sigma_m**2, constraints=cons, param_names=["nx", "ny", "nz", "d"],
                      options=options)
    n = adj.x[:3] / np.linalg.norm(adj.x[:3])
    # back to the origin: d = d' − n·mean
    G = np.eye(4)
    G[3, :3] = -mean
    cov = G @ adj.covariance @ G.T
    covp = G @ adj.covariance_prior @ G.T
    d = float(adj.x[3] - n @ mean)
    res = X @ n + d
    return Plane(n, d, cov, covp, float(adj.sigma0), float(np.sqrt(np.mean(res**2))), res, name, adj.outcome)


def _photo_axis(pose: Pose) -> np.ndarray:
    """``m⁻¹ [0 0 1]ᵀ`` of seed 000 eq. 6: the image-space z axis in the world (= −viewing axis)."""
    M = rot.PHOTO_FROM_CAM @ pose.R
    return M.T @ np.array([0.0, 0.0, 1.0])


def angle_to_camera_axis(plane: Plane, pose: Pose, *, rotation_covariance=None, prior: bool = False):
    """Angle η between the camera axis and the plane normal (seed 000 eq. 6), radians in [0, π/2].

    Parameters
    ----------
    plane : Plane
    pose : Pose
        cam_from_world.
    rotation_covariance : array_like (3, 3), optional
        Covariance of the camera's world-frame rotation increment (e.g.
        ``ResectionResult.covariance_increment[:3, :3]``), propagated into ``std``.
    prior : bool
        Use the plane's a-priori covariance instead of the a-posteriori one.

    Returns
    -------
    eta : float
        Radians; 0 when the camera looks straight at the plane.
    std : float
        σ of η (radians) from the plane's covariance (and ``rotation_covariance``); NaN if unknown.
        Near η = 0 the linearisation is poor (η is not differentiable there).
    """
    z = _photo_axis(pose)
    c = float(plane.normal @ z)  # eq. 6 (the normal is unit length)
    eta = float(np.arccos(min(1.0, abs(c))))
    sgn = 1.0 if c >= 0 else -1.0
    s = np.sin(eta)
    std = float("nan")
    C = plane.covariance_prior if prior else plane.covariance
    if C is not None and s > 1e-12:
        g_n = -sgn * z / s  # dη/dn
        var = g_n @ C[:3, :3] @ g_n
        if rotation_covariance is not None:
            Rc = as_array(rotation_covariance, "rotation_covariance", shape=(3, 3))
            a = pose.R[2]
            # axis a(δ) = (R exp([δ]×))[2]: da/dδ = [a]×, and z = −a
            g_d = -sgn * (-(plane.normal @ rot.skew(a))) / s
            var += g_d @ Rc @ g_d
        std = float(np.sqrt(max(var, 0.0)))
    return eta, std


def _ray_dirs(pose, camera=None, xy_px=None, points_world=None):
    if (points_world is None) == (xy_px is None):
        raise InvalidInputError("give either points_world or (camera, xy_px) to define the rays")
    if points_world is not None:
        P = as_points(points_world, "points_world", 3)
        d = P - pose.center
    else:
        cam = as_camera(camera)
        xy = as_points(xy_px, "xy_px", 2)
        d = cam.unproject(xy) @ pose.R  # Rᵀ r for each ray
    n = np.linalg.norm(d, axis=1, keepdims=True)
    if np.any(n == 0):
        raise DegenerateInputError("a ray target coincides with the projection centre")
    return d / n


def ray_angles(plane: Plane, pose: Pose, *, camera=None, xy_px=None, points_world=None) -> np.ndarray:
    """Per-ray angle (radians, [0, π/2]) between each viewing ray and the plane normal.

    Rays are given by image points (``camera`` + ``xy_px``, distortion removed) or by world points.
    """
    d = _ray_dirs(pose, camera, xy_px, points_world)
    return np.arccos(np.clip(np.abs(d @ plane.normal), 0.0, 1.0))


def distance_along_axis(plane: Plane, pose: Pose) -> float:
    """Distance (m) from the projection centre along the viewing axis to the plane.

    ``inf`` when the axis is parallel to the plane; negative when the plane is behind the camera.
    """
    a = pose.R[2]
    den = float(plane.normal @ a)
    num = -(float(plane.normal @ pose.center) + plane.d)
    if abs(den) < 1e-15:
        return float("inf")
    return num / den


def distance_along_rays(plane: Plane, pose: Pose, *, camera=None, xy_px=None, points_world=None):
    """Distances (m) from the projection centre along each ray to the plane, and the hit points.

    Returns
    -------
    distance_m : ndarray (N,)
        ``inf`` for rays parallel to the plane, negative where the plane is behind the camera.
    points : ndarray (N, 3)
        Intersection points (NaN for parallel rays).
    """
    d = _ray_dirs(pose, camera, xy_px, points_world)
    C = pose.center
    den = d @ plane.normal
    num = -(plane.normal @ C + plane.d)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(np.abs(den) < 1e-15, np.inf, num / den)
    pts = np.where(np.isfinite(t)[:, None], C + t[:, None] * d, np.nan)
    return t, pts
