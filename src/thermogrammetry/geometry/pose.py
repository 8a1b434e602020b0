"""Camera poses (``cam_from_world``) and projection of world points.

``X_cam = R · X_world + t``; projection centre ``C = −Rᵀ t``; the viewing axis in the
world frame is ``R[2]``. Camera frame: x right, y down, z forward (``docs/conventions.md``).
The photogrammetric exterior orientation (ω φ κ, X0) converts by
``R = diag(1, −1, −1) · M(ω, φ, κ)``, ``C = X0``.

References
----------
Hartley, R., Zisserman, A. (2004). *Multiple View Geometry in Computer Vision*, 2nd ed., §6.1.
Kraus, K. (2007). *Photogrammetry*, 2nd ed., §2.1 (ω φ κ).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validate import as_array, as_points
from ..errors import DegenerateInputError
from . import rotations as rot
from ._camera import as_camera

__all__ = ["Pose", "project_points"]


@dataclass(frozen=True, eq=False)
class Pose:
    """Rigid ``cam_from_world`` transform.

    Parameters
    ----------
    R : array_like, shape (3, 3)
        Proper rotation (validated to 1e-6), world → camera.
    t : array_like, shape (3,)
        Translation in metres: ``X_cam = R X_world + t``.
    """

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self):
        R = rot.check_rotation(self.R, "R")
        if R.shape != (3, 3):
            from ..errors import ShapeError

            raise ShapeError(f"R: expected shape (3, 3), got {R.shape}")
        t = as_array(self.t, "t", shape=(3,))
        R = R.copy()
        t = t.copy()
        R.flags.writeable = False
        t.flags.writeable = False
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    # -- constructors -------------------------------------------------------------------------
    @classmethod
    def identity(cls) -> "Pose":
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_center(cls, R, C) -> "Pose":
        """Pose from the rotation ``R`` (cam_from_world) and the projection centre ``C`` (world, m)."""
        R = rot.check_rotation(R, "R")
        C = as_array(C, "C", shape=(3,))
        return cls(R, -R @ C)

    @classmethod
    def look_at(cls, center, target, up=(0.0, 0.0, 1.0)) -> "Pose":
        """Camera at ``center`` looking at ``target``; image x to the right of ``up``, image y down.

        Raises :class:`DegenerateInputError` when the viewing direction is parallel to ``up`` or
        ``target`` equals ``center``.
        """
        C = as_array(center, "center", shape=(3,))
        T = as_array(target, "target", shape=(3,))
        u = as_array(up, "up", shape=(3,))
        z = T - C
        nz = np.linalg.norm(z)
        if nz < 1e-12:
            raise DegenerateInputError(f"target {T.tolist()} equals center {C.tolist()}; expected distinct points")
        z = z / nz
        x = np.cross(z, u)
        nx = np.linalg.norm(x)
        if nx < 1e-9 * max(np.linalg.norm(u), 1e-300):
            raise DegenerateInputError(
                f"up {u.tolist()} is parallel to the viewing direction {z.tolist()}; give another up vector"
            )
        x = x / nx
        y = np.cross(z, x)
        return cls.from_center(np.stack([x, y, z]), C)

    @classmethod
    def from_opk(cls, omega: float, phi: float, kappa: float, X0) -> "Pose":
        """Pose from photogrammetric ω φ κ (radians) and projection centre ``X0`` (m)."""
        M = rot.matrix_from_opk(omega, phi, kappa)
        if M.shape != (3, 3):
            from ..errors import ShapeError

            raise ShapeError(f"omega, phi, kappa: expected scalars, got shape {M.shape[:-2]}")
        return cls.from_center(rot.PHOTO_FROM_CAM @ M, X0)

    @classmethod
    def from_rvec(cls, rvec, tvec) -> "Pose":
        """Pose from OpenCV's ``rvec, tvec`` (same meaning: cam_from_world)."""
        return cls(rot.matrix_from_axis_angle(as_array(rvec, "rvec").reshape(3)), as_array(tvec, "tvec").reshape(3))

    @classmethod
    def from_quaternion(cls, q, t) -> "Pose":
        """Pose from a ``(w, x, y, z)`` quaternion and ``t`` (COLMAP ``images.txt`` order)."""
        return cls(rot.matrix_from_quaternion(as_array(q, "q", shape=(4,))), t)

    @classmethod
    def from_matrix(cls, T) -> "Pose":
        """Pose from a (3, 4) ``[R | t]`` or (4, 4) homogeneous matrix."""
        T = as_array(T, "T")
        if T.shape not in ((3, 4), (4, 4)):
            from ..errors import ShapeError

            raise ShapeError(f"T: expected shape (3, 4) or (4, 4), got {T.shape}")
        return cls(T[:3, :3], T[:3, 3])

    # -- properties / conversions ------------------------------------------------------------
    @property
    def center(self) -> np.ndarray:
        """Projection centre ``C = −Rᵀ t`` (world, m), shape (3,)."""
        return -self.R.T @ self.t

    @property
    def axis(self) -> np.ndarray:
        """Unit viewing direction (camera +z) in the world frame, ``R[2]``."""
        return self.R[2].copy()

    def matrix(self) -> np.ndarray:
        """(3, 4) ``[R | t]``."""
        return np.hstack([self.R, self.t[:, None]])

    def matrix4(self) -> np.ndarray:
        """(4, 4) homogeneous ``cam_from_world``."""
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t
        return T

    def to_opk(self) -> tuple[float, float, float, np.ndarray]:
        """``(omega, phi, kappa, X0)``: radians and the projection centre (m)."""
        o, p, k = rot.opk_from_matrix(rot.PHOTO_FROM_CAM @ self.R)
        return float(o), float(p), float(k), self.center

    def to_rvec(self) -> tuple[np.ndarray, np.ndarray]:
        """OpenCV ``(rvec, tvec)``."""
        return rot.axis_angle_from_matrix(self.R), self.t.copy()

    def quaternion(self) -> np.ndarray:
        """``(w, x, y, z)`` of ``R`` with ``w ≥ 0``."""
        return rot.quaternion_from_matrix(self.R)

    # -- operations ---------------------------------------------------------------------------
    def transform(self, points_world) -> np.ndarray:
        """World points (N, 3) → camera-frame points (N, 3); a single (3,) point gives (1, 3)."""
        X = as_points(points_world, "points_world", 3)
        return X @ self.R.T + self.t

    def inverse(self) -> "Pose":
        """The inverse transform (``world_from_cam`` as a Pose object)."""
        return Pose(self.R.T, -self.R.T @ self.t)

    def compose(self, other: "Pose") -> "Pose":
        """``self ∘ other``: apply ``other`` first, then ``self``.

        If ``self`` is cam_from_world and ``other`` is world_from_body, the result is cam_from_body.
        """
        return Pose(self.R @ other.R, self.R @ other.t + self.t)

    def __matmul__(self, other: "Pose") -> "Pose":
        return self.compose(other)

    def __repr__(self) -> str:
        o, p, k, C = self.to_opk()
        return (
            f"Pose(C={np.array2string(C, precision=4)}, omega_deg={np.degrees(o):.4f}, "
            f"phi_deg={np.degrees(p):.4f}, kappa_deg={np.degrees(k):.4f})"
        )

    def allclose(self, other: "Pose", rtol: float = 0.0, atol: float = 1e-9) -> bool:
        return bool(np.allclose(self.R, other.R, rtol, atol) and np.allclose(self.t, other.t, rtol, atol))


def project_points(camera, pose: Pose, points_world) -> np.ndarray:
    """Project world points to pixels (OpenCV origin).

    Parameters
    ----------
    camera : thermogrammetry.Camera or array_like (3, 3)
        Camera model (with its distortion) or a pinhole ``K`` in pixels.
    pose : Pose
        ``cam_from_world``.
    points_world : array_like, shape (N, 3)
        Metres.

    Returns
    -------
    xy_px : ndarray, shape (N, 2)
        Points behind the camera (z ≤ 0) are projected by the model as well; check
        ``pose.transform(points)[:, 2] > 0`` when it matters.
    """
    cam = as_camera(camera)
    return cam.project(pose.transform(points_world))
