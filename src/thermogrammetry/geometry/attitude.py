"""Camera attitude from the gimbal angles that DJI writes (XMP ``drone-dji:Gimbal{Yaw,Pitch,Roll}Degree``), as
``cam_from_world`` rotations in a projected CRS, and the rotation of a block about a straight GNSS line taken from them.

Conventions (written once here)
-------------------------------
- DJI gimbal angles: yaw ψ from true north, clockwise seen from above; pitch θ from the horizon, −90° = nadir; roll φ
  about the optical axis; applied in that order (intrinsic Z-Y-X, aerospace) to a body frame x forward (the optical
  axis), y right, z down, in the local north-east-down (NED) frame. At ψ = θ = φ = 0 the camera looks north,
  horizontally, image x to the east. At nadir (θ = −90°) yaw and roll share one degree of freedom: DJI writes either
  (ψ, φ = 0) or (ψ − 180°, φ = 180°) for one heading; both give the same matrix here.
- Camera frame: x right, y down, z forward (the project's); ``cam_from_world`` maps CRS coordinates (x east, y north,
  z up, metres) to the camera frame.
- Grid north of a projected CRS differs from true north by the meridian convergence γ (pyproj
  ``Proj.get_factors(...).meridian_convergence``, degrees): a true azimuth ψ is the grid azimuth ψ − γ. For a
  geographic output CRS the convergence is taken as 0 (such output is not used for adjustment coordinates).

Accuracy measured on the shared DJI M3T flight (31 thermal frames whose orientation by ``survey`` on RTK GNSS has σ
0.04°): the gimbal's attitude differs from it by 0.37-2.16° (RMS 1.43°), mostly a slowly drifting tilt (mean
1.15° about east, 0.55° about north, 0.16° about the vertical): gimbal errors are correlated from frame to frame
(:data:`ATTITUDE_SIGMA_DEG`).

References
----------
DJI, *Mavic 3 Enterprise series / M30 series image XMP metadata* (``drone-dji`` namespace: GimbalYawDegree,
GimbalPitchDegree, GimbalRollDegree); J. Diebel, *Representing attitude: Euler angles, unit quaternions, and
rotation vectors*, Stanford 2006, §5.6 (Z-Y-X sequence).
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidInputError
from .rotations import matrix_from_axis_angle, skew

__all__ = ["ATTITUDE_SIGMA_DEG", "cam_from_world_from_gimbal", "gimbal_from_cam_from_world", "meridian_convergence_deg",
           "rotation_about_axis"]

#: σ (degrees, per rotation component) of one gimbal attitude as a prior on the block's rotation about a straight GNSS
#: line. Its errors are correlated (a drifting tilt, measured 1.3° on the M3T flight): every frame's prior gets
#: ``ATTITUDE_SIGMA_DEG · sqrt(n)`` so that the n priors together fix the block's common rotation to this σ, not to
#: ``σ / sqrt(n)`` (the per-frame scatter, ~0.5°, would claim a precision the tilt does not have)
ATTITUDE_SIGMA_DEG = 2.0

# body (x forward, y right, z down) from camera (x right, y down, z forward): columns = camera axes in the body frame
_BODY_FROM_CAM = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
# east-north-up from north-east-down (its own inverse)
_ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def _about(axis: int, a) -> np.ndarray:
    """Rotations (N, 3, 3) by the angles ``a`` (N,) (radians, right-handed) about coordinate axis ``axis``."""
    r = np.zeros(np.shape(a) + (3,))
    r[..., axis] = a
    return matrix_from_axis_angle(r)


def cam_from_world_from_gimbal(yaw_deg, pitch_deg, roll_deg, convergence_deg=0.0) -> np.ndarray:
    """``cam_from_world`` rotations (N, 3, 3) in a projected CRS from DJI gimbal angles (degrees, (N,) or scalars).

    ``convergence_deg``: meridian convergence γ at each position ((N,) or scalar, degrees; see the module docstring).
    Non-finite angles give NaN matrices.
    """
    y, p, r, g = np.broadcast_arrays(*(np.radians(np.asarray(v, float)) for v in (yaw_deg, pitch_deg, roll_deg,
                                                                                    convergence_deg)))
    y, p, r, g = (np.atleast_1d(v) for v in (y, p, r, g))
    ned_from_cam = _about(2, y) @ _about(1, p) @ _about(0, r) @ _BODY_FROM_CAM
    world_from_cam = _about(2, g) @ _ENU_FROM_NED @ ned_from_cam
    return np.swapaxes(world_from_cam, -1, -2)


def gimbal_from_cam_from_world(R, convergence_deg=0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`cam_from_world_from_gimbal`: (yaw, pitch, roll) in degrees, each (N,), yaw in (−180, 180].

    At nadir (|pitch| = 90°) the roll is returned as 0 and the heading goes into the yaw.
    """
    R = np.asarray(R, float).reshape(-1, 3, 3)
    g = np.radians(np.broadcast_to(np.asarray(convergence_deg, float), (len(R),)))
    ned_from_body = _ENU_FROM_NED @ _about(2, -g) @ np.swapaxes(R, -1, -2) @ _BODY_FROM_CAM.T
    # Z-Y-X: M = Rz(y) Ry(p) Rx(r); M[2,0] = -sin p, M[1,0] = cos p sin y, M[0,0] = cos p cos y, M[2,1] = cos p sin r
    p = -np.arcsin(np.clip(ned_from_body[:, 2, 0], -1.0, 1.0))
    lock = np.abs(np.cos(p)) < 1e-9
    y = np.where(lock, np.arctan2(-ned_from_body[:, 0, 1], ned_from_body[:, 1, 1]),
                 np.arctan2(ned_from_body[:, 1, 0], ned_from_body[:, 0, 0]))
    r = np.where(lock, 0.0, np.arctan2(ned_from_body[:, 2, 1], ned_from_body[:, 2, 2]))
    return np.degrees(y), np.degrees(p), np.degrees(r)


def meridian_convergence_deg(crs: str, lon_deg, lat_deg) -> np.ndarray:
    """Meridian convergence γ (degrees, (N,)) of the projected ``crs`` at the given positions; 0 for a geographic CRS.

    Raises :class:`~thermogrammetry.errors.InvalidInputError` for a CRS that pyproj does not know.
    """
    from pyproj import CRS, Proj
    from pyproj.exceptions import CRSError

    lon = np.atleast_1d(np.asarray(lon_deg, float))
    lat = np.atleast_1d(np.asarray(lat_deg, float))
    try:
        c = CRS.from_user_input(crs)
    except CRSError as e:
        raise InvalidInputError(f"crs: {crs!r} is not a CRS pyproj knows ({e}); expected e.g. 'EPSG:32632'") from e
    if not c.is_projected:
        return np.zeros(len(lon))
    out = np.full(len(lon), np.nan)
    ok = np.isfinite(lon) & np.isfinite(lat)
    if ok.any():
        out[ok] = np.asarray(Proj(c).get_factors(lon[ok], lat[ok]).meridian_convergence, float)
    return out


def rotation_about_axis(R_est, R_obs, axis) -> tuple[float, np.ndarray]:
    """The rotation α (radians) about the unit world ``axis`` that best brings a block's cameras to observed attitudes.

    Finds α such that ``R_est[i] · Q(α)ᵀ ≈ R_obs[i]`` (``Q(α)`` the world rotation by α about ``axis``): for each
    frame, ``Q_i = R_obs[i]ᵀ R_est[i]`` and α_i maximises ``tr(Q(α)ᵀ Q_i)``, i.e.
    ``α_i = atan2(tr([a]×ᵀ Q_i), tr Q_i − aᵀ Q_i a)``; α is their median (a frame with a wrong attitude tag does not
    move it).

    Parameters
    ----------
    R_est, R_obs : (N, 3, 3) cam_from_world (the block after its start similarity; the attitudes), N >= 1
    axis : (3,) the line's direction in the world frame

    Returns
    -------
    (alpha_rad, alpha_i_rad (N,))
    """
    R_est = np.asarray(R_est, float).reshape(-1, 3, 3)
    R_obs = np.asarray(R_obs, float).reshape(-1, 3, 3)
    if len(R_est) != len(R_obs) or not len(R_est):
        raise InvalidInputError(f"R_est, R_obs: {len(R_est)} and {len(R_obs)} rotations; expected equal counts >= 1")
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    Q = np.swapaxes(R_obs, 1, 2) @ R_est
    A = np.trace(Q, axis1=1, axis2=2) - np.einsum("i,kij,j->k", a, Q, a)
    B = np.einsum("ij,kij->k", skew(a), Q)
    al = np.arctan2(B, A)
    # median on the circle: around the circular mean
    m = np.angle(np.mean(np.exp(1j * al)))
    return float(m + np.median(np.angle(np.exp(1j * (al - m))))), al
