"""Rotation parameterisations: matrix, axis-angle, quaternion and ω φ κ.

All functions are vectorised: a leading batch shape ``(...)`` is carried
through (``(..., 3)`` vectors, ``(..., 4)`` quaternions, ``(..., 3, 3)``
matrices). Angles are in radians.

Conventions (binding; ``docs/conventions.md``):

- **axis-angle** is the Rodrigues vector ``r = θ·axis`` (OpenCV's ``rvec``);
  ``matrix_from_axis_angle(r)`` is the *active* rotation by θ about ``axis``.
- **quaternion** ``(w, x, y, z)``, Hamilton convention, unit norm, returned with
  ``w ≥ 0`` (COLMAP's ``QW QX QY QZ`` order).
- **ω φ κ**: ``M = R_κ · R_φ · R_ω`` is *photo_from_world* with::

      R_ω = [[1, 0, 0], [0, cos ω, sin ω], [0, −sin ω, cos ω]]
      R_φ = [[cos φ, 0, −sin φ], [0, 1, 0], [sin φ, 0, cos φ]]
      R_κ = [[cos κ, sin κ, 0], [−sin κ, cos κ, 0], [0, 0, 1]]

  and the computer-vision rotation is ``R_cam_from_world = diag(1, −1, −1) · M``
  (:data:`PHOTO_FROM_CAM`).

References
----------
Kraus, K. (2007). *Photogrammetry: Geometry from Images and Laser Scans*, 2nd ed., de Gruyter, §2.1.
Wolf, P. R., Dewitt, B. A. (2000). *Elements of Photogrammetry*, 3rd ed., McGraw-Hill, appendix C.
Shepperd, S. W. (1978). Quaternion from rotation matrix. *J. Guidance and Control* 1(3), 223–224.
"""

from __future__ import annotations

import numpy as np

from .._validate import as_array
from ..errors import InvalidInputError, ShapeError

__all__ = [
    "PHOTO_FROM_CAM",
    "skew",
    "matrix_from_axis_angle",
    "axis_angle_from_matrix",
    "mean_rotation",
    "nearest_rotation",
    "matrix_from_quaternion",
    "quaternion_from_matrix",
    "matrix_from_opk",
    "opk_from_matrix",
    "opk_derivatives",
    "opk_to_increment_jacobian",
    "is_rotation",
    "check_rotation",
]

#: ``photo = PHOTO_FROM_CAM · cam``: flips y (down → up) and z (forward → backward). Its own inverse.
PHOTO_FROM_CAM = np.diag([1.0, -1.0, -1.0])


def _vec(a, name: str, n: int) -> np.ndarray:
    arr = as_array(a, name)
    if arr.ndim < 1 or arr.shape[-1] != n:
        raise ShapeError(f"{name}: expected shape (..., {n}), got {arr.shape}")
    return arr


def _mat(a, name: str) -> np.ndarray:
    arr = as_array(a, name)
    if arr.ndim < 2 or arr.shape[-2:] != (3, 3):
        raise ShapeError(f"{name}: expected shape (..., 3, 3), got {arr.shape}")
    return arr


def skew(v) -> np.ndarray:
    """Cross-product matrix ``[v]×`` with ``[v]× w = v × w``.

    Parameters
    ----------
    v : array_like, shape (..., 3)

    Returns
    -------
    ndarray, shape (..., 3, 3)
    """
    v = _vec(v, "v", 3)
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


def is_rotation(R, tol: float = 1e-6) -> np.ndarray:
    """True where ``R`` is proper orthonormal within ``tol`` (max abs deviation of RᵀR from I)."""
    R = np.asarray(R, dtype=float)
    err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-2, -1))
    return (err < tol) & (np.linalg.det(R) > 0)


def check_rotation(R, name: str = "R", tol: float = 1e-6) -> np.ndarray:
    """Validate a (..., 3, 3) rotation matrix; raise :class:`InvalidInputError` naming it if not proper orthonormal."""
    R = _mat(R, name)
    ok = is_rotation(R, tol)
    if not np.all(ok):
        dev = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-2, -1))
        det = np.linalg.det(R)
        raise InvalidInputError(
            f"{name}: not a proper rotation matrix (max |RᵀR − I| = {np.max(dev):.3g}, det = "
            f"{np.min(det) if np.ndim(det) else det:.6g}); expected orthonormal 3×3 with det = +1 (tolerance {tol})"
        )
    return R


def matrix_from_axis_angle(rvec) -> np.ndarray:
    """Rotation matrix from a Rodrigues vector (same as ``cv2.Rodrigues``).

    Parameters
    ----------
    rvec : array_like, shape (..., 3)
        Rotation axis times angle, radians.

    Returns
    -------
    R : ndarray, shape (..., 3, 3)
        ``R = I + sin θ/θ [r]× + (1 − cos θ)/θ² [r]×²`` (series near θ = 0).
    """
    r = _vec(rvec, "rvec", 3)
    th2 = np.sum(r * r, axis=-1)
    th = np.sqrt(th2)
    small = th2 < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - np.cos(ths)) / (ths * ths))
    K = skew(r)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def nearest_rotation(M) -> np.ndarray:
    """The rotation nearest to ``M`` (..., 3, 3) in the Frobenius norm, by its SVD: ``U diag(1, 1, ±1) Vᵀ`` with
    the sign of ``det(U Vᵀ)``. With ``M = Σ b_k a_kᵀ`` it is the rotation that best turns directions ``a_k`` into
    ``b_k`` (Kabsch / Wahba); with ``M = Σ R_k`` the chordal mean (:func:`mean_rotation`).

    References
    ----------
    Kabsch, W. (1976). A solution for the best rotation to relate two sets of vectors. Acta Cryst. A32, 922-923.
    """
    U, _, Vt = np.linalg.svd(np.asarray(M, float))
    d = np.where(np.linalg.det(U @ Vt) < 0, -1.0, 1.0)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def mean_rotation(Rs) -> np.ndarray:
    """Chordal L2 mean of rotations: the sum of ``Rs`` (K, 3, 3) projected on SO(3) (:func:`nearest_rotation`).

    References
    ----------
    Hartley, R., Trumpf, J., Dai, Y., Li, H. (2013). Rotation averaging. IJCV 103(3), 267-305, §5.3.
    """
    return nearest_rotation(np.asarray(Rs, float).reshape(-1, 3, 3).sum(axis=0))


def quaternion_from_matrix(R) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` with ``w ≥ 0`` from a rotation matrix (Shepperd's method).

    Parameters
    ----------
    R : array_like, shape (..., 3, 3)
        Proper rotation matrix (validated to 1e-6).

    Returns
    -------
    q : ndarray, shape (..., 4)
    """
    R = check_rotation(R, "R")
    m = R.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    d = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], -1)
    k = np.argmax(d, axis=1)
    q = np.empty((m.shape[0], 4))
    # case w largest
    s = np.sqrt(np.maximum(1.0 + tr, 0.0)) * 2.0
    c0 = np.stack([0.25 * s, (m[:, 2, 1] - m[:, 1, 2]), (m[:, 0, 2] - m[:, 2, 0]), (m[:, 1, 0] - m[:, 0, 1])], -1)
    c0[:, 1:] /= np.where(s == 0, 1, s)[:, None]
    s1 = np.sqrt(np.maximum(1.0 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2], 0.0)) * 2.0
    s1z = np.where(s1 == 0, 1, s1)
    c1 = np.stack([(m[:, 2, 1] - m[:, 1, 2]) / s1z, 0.25 * s1, (m[:, 0, 1] + m[:, 1, 0]) / s1z, (m[:, 0, 2] + m[:, 2, 0]) / s1z], -1)
    s2 = np.sqrt(np.maximum(1.0 + m[:, 1, 1] - m[:, 0, 0] - m[:, 2, 2], 0.0)) * 2.0
    s2z = np.where(s2 == 0, 1, s2)
    c2 = np.stack([(m[:, 0, 2] - m[:, 2, 0]) / s2z, (m[:, 0, 1] + m[:, 1, 0]) / s2z, 0.25 * s2, (m[:, 1, 2] + m[:, 2, 1]) / s2z], -1)
    s3 = np.sqrt(np.maximum(1.0 + m[:, 2, 2] - m[:, 0, 0] - m[:, 1, 1], 0.0)) * 2.0
    s3z = np.where(s3 == 0, 1, s3)
    c3 = np.stack([(m[:, 1, 0] - m[:, 0, 1]) / s3z, (m[:, 0, 2] + m[:, 2, 0]) / s3z, (m[:, 1, 2] + m[:, 2, 1]) / s3z, 0.25 * s3], -1)
    q = np.choose(k[:, None], [c0, c1, c2, c3])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(R.shape[:-2] + (4,))


def matrix_from_quaternion(q) -> np.ndarray:
    """Rotation matrix from a quaternion ``(w, x, y, z)`` (Hamilton); the quaternion is normalised first.

    Parameters
    ----------
    q : array_like, shape (..., 4)
        Non-zero quaternion; ``q`` and ``−q`` give the same matrix.

    Returns
    -------
    R : ndarray, shape (..., 3, 3)
    """
    q = _vec(q, "q", 4)
    n = np.linalg.norm(q, axis=-1)
    if np.any(n < 1e-12):
        raise InvalidInputError(f"q: zero quaternion {q[n < 1e-12][0]!r}; expected a non-zero (w, x, y, z)")
    q = q / n[..., None]
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def axis_angle_from_matrix(R) -> np.ndarray:
    """Rodrigues vector (angle in [0, π]) from a rotation matrix; inverse of :func:`matrix_from_axis_angle`.

    Computed through the quaternion, which is stable at θ → 0 and θ → π.

    Parameters
    ----------
    R : array_like, shape (..., 3, 3)

    Returns
    -------
    rvec : ndarray, shape (..., 3)
    """
    q = quaternion_from_matrix(R)
    w = q[..., 0]
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1)
    small = s < 1e-8
    ss = np.where(small, 1.0, s)
    # θ = 2 atan2(|v|, w);  r = v θ/|v|  → 2 v / w (1 − |v|²/(3 w²)) for |v| → 0
    f = np.where(small, 2.0 / np.maximum(w, 1e-300) * (1.0 - s * s / 3.0), 2.0 * np.arctan2(s, w) / ss)
    return v * f[..., None]


def _opk_elementary(omega, phi, kappa):
    co, so = np.cos(omega), np.sin(omega)
    cp, sp = np.cos(phi), np.sin(phi)
    ck, sk = np.cos(kappa), np.sin(kappa)
    o, z = np.ones_like(co), np.zeros_like(co)
    Rw = np.stack([np.stack([o, z, z], -1), np.stack([z, co, so], -1), np.stack([z, -so, co], -1)], -2)
    Rp = np.stack([np.stack([cp, z, -sp], -1), np.stack([z, o, z], -1), np.stack([sp, z, cp], -1)], -2)
    Rk = np.stack([np.stack([ck, sk, z], -1), np.stack([-sk, ck, z], -1), np.stack([z, z, o], -1)], -2)
    dRw = np.stack([np.stack([z, z, z], -1), np.stack([z, -so, co], -1), np.stack([z, -co, -so], -1)], -2)
    dRp = np.stack([np.stack([-sp, z, -cp], -1), np.stack([z, z, z], -1), np.stack([cp, z, -sp], -1)], -2)
    dRk = np.stack([np.stack([-sk, ck, z], -1), np.stack([-ck, -sk, z], -1), np.stack([z, z, z], -1)], -2)
    return Rw, Rp, Rk, dRw, dRp, dRk


def _opk_args(omega, phi, kappa):
    o = as_array(omega, "omega")
    p = as_array(phi, "phi")
    k = as_array(kappa, "kappa")
    try:
        return np.broadcast_arrays(o, p, k)
    except ValueError:
        raise ShapeError(
            f"omega, phi, kappa: shapes {o.shape}, {p.shape}, {k.shape} do not broadcast; expected equal shapes"
        ) from None


def matrix_from_opk(omega, phi, kappa) -> np.ndarray:
    """Photogrammetric rotation ``M = R_κ R_φ R_ω`` (photo_from_world) from ω φ κ in radians.

    Parameters
    ----------
    omega, phi, kappa : array_like, broadcastable shapes (...)
        Radians.

    Returns
    -------
    M : ndarray, shape (..., 3, 3)
        ``M[2] = (sin φ, −cos φ sin ω, cos φ cos ω)``. ``R_cam_from_world = PHOTO_FROM_CAM @ M``.
    """
    o, p, k = _opk_args(omega, phi, kappa)
    Rw, Rp, Rk, *_ = _opk_elementary(o, p, k)
    return Rk @ Rp @ Rw


def opk_from_matrix(M, *, gimbal_tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ω φ κ (radians) from a photo_from_world matrix ``M``; inverse of :func:`matrix_from_opk`.

    φ ∈ [−π/2, π/2], ω, κ ∈ (−π, π]. At gimbal lock (|cos φ| < ``gimbal_tol``) κ is set to 0
    and ω carries the whole remaining rotation.

    Parameters
    ----------
    M : array_like, shape (..., 3, 3)

    Returns
    -------
    omega, phi, kappa : ndarray, shape (...)
    """
    M = check_rotation(M, "M")
    sp = np.clip(M[..., 2, 0], -1.0, 1.0)
    phi = np.arcsin(sp)
    cp = np.sqrt(np.maximum(0.0, M[..., 2, 1] ** 2 + M[..., 2, 2] ** 2))
    lock = cp < gimbal_tol
    omega = np.where(lock, np.arctan2(M[..., 1, 2], M[..., 1, 1]), np.arctan2(-M[..., 2, 1], M[..., 2, 2]))
    kappa = np.where(lock, 0.0, np.arctan2(-M[..., 1, 0], M[..., 0, 0]))
    # use atan2 for φ too (more accurate near ±π/2)
    phi = np.where(lock, phi, np.arctan2(sp, cp))
    return omega, phi, kappa


def opk_derivatives(omega, phi, kappa) -> np.ndarray:
    """Analytic partial derivatives of ``M(ω, φ, κ)``.

    Returns
    -------
    dM : ndarray, shape (..., 3, 3, 3)
        ``dM[..., i, :, :] = ∂M/∂(ω, φ, κ)[i]``.
    """
    o, p, k = _opk_args(omega, phi, kappa)
    Rw, Rp, Rk, dRw, dRp, dRk = _opk_elementary(o, p, k)
    return np.stack([Rk @ Rp @ dRw, Rk @ dRp @ Rw, dRk @ Rp @ Rw], -3)


def opk_to_increment_jacobian(omega, phi, kappa) -> np.ndarray:
    """Jacobian ``A = ∂δ/∂(ω, φ, κ)`` of the world-frame rotation increment δ used by the solvers.

    The solvers perturb a cam_from_world rotation as ``R(δ) = R · exp([δ]×)``; since
    ``R = PHOTO_FROM_CAM · M``, ``[dδ]× = Mᵀ dM``. A covariance ``C_δ`` of δ converts to
    ``C_opk = A⁻¹ C_δ A⁻ᵀ`` (singular at gimbal lock, cos φ = 0).

    Returns
    -------
    A : ndarray, shape (..., 3, 3)
        Columns are ``vee(Mᵀ ∂M/∂ω)``, ``vee(Mᵀ ∂M/∂φ)``, ``vee(Mᵀ ∂M/∂κ)``.
    """
    M = matrix_from_opk(omega, phi, kappa)
    dM = opk_derivatives(omega, phi, kappa)
    S = np.swapaxes(M, -1, -2)[..., None, :, :] @ dM  # (..., 3, 3, 3), each skew-symmetric
    vee = np.stack([S[..., 2, 1], S[..., 0, 2], S[..., 1, 0]], -1)  # (..., 3 params, 3 comps)
    return np.swapaxes(vee, -1, -2)
