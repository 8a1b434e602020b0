"""Seed 000's camera network: DLT cameras, triangulated pass points, a thermal camera from pass points.

Everything here is a pure function of arrays. Each estimate is also returned *linearised*: its
Jacobian with respect to one global vector of image observations (every measured ``x, y`` of every
image, in a fixed order). With the observations' covariance ``Σ_obs`` the covariance of any derived
quantity ``q`` (pass points, the thermal camera, a plane normal, the angle η of a pixel) is
``J_q Σ_obs J_qᵀ``, *including* the correlations the sequential workflow creates (all pass points
share the optical cameras' errors; the thermal camera inherits the pass points' errors). For a
least-squares estimate ``θ̂ = argmin ‖r(θ, o)‖²`` the Jacobian follows from the implicit function
theorem, ``dθ̂/do = −(JᵀJ)⁻¹ Jᵀ ∂r/∂o``.

Model (seed 000 eq. 2, Abdel-Aziz & Karara 1971), in a normalised object frame
``X̃ = (X − c) / s`` (``c`` the centroid and ``s`` the RMS radius of the control points, so the
denominator is well conditioned — at X̃ = 0 it is 1 by construction):

    x = (L1 X̃ + L2 Ỹ + L3 Z̃ + L4) / (L9 X̃ + L10 Ỹ + L11 Z̃ + 1)
    y = (L5 X̃ + L6 Ỹ + L7 Z̃ + L8) / (L9 X̃ + L10 Ỹ + L11 Z̃ + 1)

``x, y`` are pixels (OpenCV origin). The 11 coefficients are found linearly (Hartley-normalised
algebraic solution), then refined by Gauss–Newton on the image residuals — seed 000 eq. 3–4, whose
text is garbled (eq. 4 reads ``BᵀpBL + Bpc``); we follow the standard normal equations
``BᵀpB ΔL = −Bᵀp c`` of Abdel-Aziz & Karara / Karara's iterative DLT and say so here.

References
----------
Abdel-Aziz Y.I., Karara H.M. (1971), Direct linear transformation from comparator coordinates into
object space coordinates in close-range photogrammetry. Sawicki, Stein, Więcek (seed 000) eq. 1–6.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DegenerateInputError, TooFewPointsError
from ..results import Outcome, Termination

__all__ = [
    "Frame",
    "dlt_project",
    "dlt_jacobians",
    "dlt_linear",
    "check_dlt_geometry",
    "RefinedCamera",
    "refine_dlt",
    "triangulate_point",
    "dlt_matrix",
    "decompose_projection",
    "camera_axis_center",
    "L_from_pose",
    "resect_known_interior",
]


@dataclass(frozen=True)
class Frame:
    """Normalised object frame ``X̃ = (X − origin) / scale`` (m → unitless)."""

    origin: np.ndarray
    scale: float

    @classmethod
    def from_points(cls, X) -> "Frame":
        X = np.asarray(X, float)
        c = X.mean(axis=0)
        s = float(np.sqrt(((X - c) ** 2).sum(axis=1).mean()))
        return cls(c, s if s > 0 else 1.0)

    def to_norm(self, X) -> np.ndarray:
        return (np.asarray(X, float) - self.origin) / self.scale

    def to_world(self, Xn) -> np.ndarray:
        return np.asarray(Xn, float) * self.scale + self.origin

    def world_matrix(self) -> np.ndarray:
        """4×4 ``T`` with ``X̃h = T Xh``: a normalised-frame projection ``P̃`` is ``P̃ T`` in the world."""
        T = np.eye(4) / self.scale
        T[3, 3] = 1.0
        T[:3, 3] = -self.origin / self.scale
        return T


def dlt_matrix(L) -> np.ndarray:
    """(11,) DLT coefficients → 3×4 projection matrix (``L12 = 1``)."""
    L = np.asarray(L, float)
    return np.append(L, 1.0).reshape(3, 4)


def dlt_project(L, Xn) -> np.ndarray:
    """Seed 000 eq. 2 without corrections: (N, 3) normalised points → (N, 2) px."""
    P = dlt_matrix(L)
    Xn = np.asarray(Xn, float)
    h = Xn @ P[:, :3].T + P[:, 3]
    return h[:, :2] / h[:, 2:3]


def dlt_jacobians(L, Xn) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Analytic Jacobians of :func:`dlt_project`.

    Returns
    -------
    xy : (N, 2) px
    J_L : (N, 2, 11) d(x, y)/dL
    J_X : (N, 2, 3) d(x, y)/dX̃
    """
    P = dlt_matrix(L)
    Xn = np.asarray(Xn, float)
    N = len(Xn)
    h = Xn @ P[:, :3].T + P[:, 3]
    w = h[:, 2]
    xy = h[:, :2] / w[:, None]
    Xh = np.column_stack([Xn, np.ones(N)])
    J_L = np.zeros((N, 2, 11))
    J_L[:, 0, 0:4] = Xh / w[:, None]
    J_L[:, 1, 4:8] = Xh / w[:, None]
    J_L[:, 0, 8:11] = -xy[:, 0:1] * Xn / w[:, None]
    J_L[:, 1, 8:11] = -xy[:, 1:2] * Xn / w[:, None]
    J_X = (P[None, :2, :3] - xy[:, :, None] * P[None, 2:3, :3]) / w[:, None, None]
    return xy, J_L, J_X


def check_dlt_geometry(Xn, *, what: str = "control points", ids=None, image: str = "") -> None:
    """Raise when the points cannot determine an 11-parameter DLT (< 6 points or coplanar).

    Coplanar object points make the DLT's design matrix singular (a plane only fixes a homography);
    the message suggests a resection with known interior orientation instead.
    """
    Xn = np.asarray(Xn, float)
    where = f" on image {image!r}" if image else ""
    names = f" ({', '.join(map(str, ids))})" if ids is not None else ""
    if len(Xn) < 6:
        raise TooFewPointsError(
            f"{len(Xn)} {what}{where}{names}: the 11-parameter DLT needs at least 6 points with known "
            "object coordinates (not all in one plane)"
        )
    c = Xn - Xn.mean(axis=0)
    sv = np.linalg.svd(c, compute_uv=False)
    if sv[-1] <= 1e-3 * sv[0]:
        raise DegenerateInputError(
            f"the {len(Xn)} {what}{where}{names} are coplanar (smallest/largest spread "
            f"{sv[-1] / sv[0]:.1e}): the DLT is singular for coplanar points. Give control points that "
            "span three dimensions, or a known interior orientation (--camera IMAGE=camera.json from "
            "`thermogrammetry calibrate`) so the camera is found by space resection"
        )


def dlt_linear(Xn, xy) -> np.ndarray:
    """Linear (algebraic) DLT with Hartley normalisation of the image points.

    Parameters
    ----------
    Xn : (N ≥ 6, 3) normalised object points
    xy : (N, 2) px

    Returns
    -------
    L : (11,) coefficients with ``L12 = 1``.
    """
    Xn = np.asarray(Xn, float)
    xy = np.asarray(xy, float)
    m = xy.mean(axis=0)
    sc = np.sqrt(2.0) / max(np.sqrt(((xy - m) ** 2).sum(axis=1)).mean(), 1e-12)
    Ti = np.array([[sc, 0, -sc * m[0]], [0, sc, -sc * m[1]], [0, 0, 1.0]])
    q = (xy - m) * sc
    N = len(Xn)
    Xh = np.column_stack([Xn, np.ones(N)])
    A = np.zeros((2 * N, 12))
    A[0::2, 0:4] = Xh
    A[0::2, 8:12] = -q[:, 0:1] * Xh
    A[1::2, 4:8] = Xh
    A[1::2, 8:12] = -q[:, 1:2] * Xh
    _, sv, vt = np.linalg.svd(A)
    Pn = vt[-1].reshape(3, 4)
    P = np.linalg.solve(Ti, Pn)
    if abs(P[2, 3]) < 1e-12 * np.abs(P).max():
        raise DegenerateInputError("DLT: the object-frame origin lies in the camera's principal plane")
    P = P / P[2, 3]
    return P.ravel()[:11]


@dataclass
class RefinedCamera:
    """A DLT camera after least-squares refinement (seed 000 eq. 3–4).

    Attributes
    ----------
    L : (11,) coefficients (normalised object frame)
    normal : (11, 11) normal matrix ``JᵀJ`` (px⁻² not applied)
    dL_dobs : (11, 2N) derivative with respect to this camera's observations, ordered x0, y0, x1, ...
    dL_dX : (11, 3N) derivative with respect to the normalised object points
    residuals : (N, 2) px, ``projected − measured``
    sigma0_px : a-posteriori σ of unit weight (px), NaN without redundancy
    outcome : Outcome
    """

    L: np.ndarray
    normal: np.ndarray
    dL_dobs: np.ndarray
    dL_dX: np.ndarray
    residuals: np.ndarray
    sigma0_px: float
    iterations: int
    outcome: Outcome


def refine_dlt(L0, Xn, xy, *, max_iterations: int = 50, tol: float = 1e-12) -> RefinedCamera:
    """Gauss–Newton refinement of the 11 DLT coefficients on the image residuals.

    Parameters
    ----------
    L0 : (11,) start (from :func:`dlt_linear`)
    Xn : (N, 3) normalised object points, xy : (N, 2) px

    Returns
    -------
    RefinedCamera, with the implicit-function derivatives for error propagation.
    """
    Xn = np.asarray(Xn, float)
    xy = np.asarray(xy, float)
    L = np.asarray(L0, float).copy()
    N = len(Xn)
    term = Termination.MAX_ITERATIONS
    reason = f"no convergence in {max_iterations} iterations"
    it = 0
    for it in range(1, max_iterations + 1):
        proj, JL, _ = dlt_jacobians(L, Xn)
        r = (proj - xy).ravel()
        J = JL.reshape(2 * N, 11)
        col = np.linalg.norm(J, axis=0)
        col[col == 0] = 1.0
        Js = J / col
        try:
            step_s, *_ = np.linalg.lstsq(Js, -r, rcond=None)
        except np.linalg.LinAlgError:
            term, reason = Termination.NUMERICAL_FAILURE, "least-squares step failed"
            break
        step = step_s / col
        L = L + step
        if not np.all(np.isfinite(L)):
            term, reason = Termination.DIVERGED, "non-finite coefficients"
            break
        if np.linalg.norm(step_s) < tol * (1 + np.linalg.norm(L * col)):
            term, reason = Termination.CONVERGED, f"step below {tol:g} after {it} iterations"
            break
    proj, JL, JX = dlt_jacobians(L, Xn)
    res = proj - xy
    J = JL.reshape(2 * N, 11)
    Nm = J.T @ J
    col = np.sqrt(np.diag(Nm))
    col[col == 0] = 1.0
    Ninv = np.linalg.pinv(Nm / np.outer(col, col)) / np.outer(col, col)
    dL_dobs = Ninv @ J.T  # ∂r/∂obs = −I
    JXb = np.zeros((2 * N, 3 * N))
    for i in range(N):
        JXb[2 * i:2 * i + 2, 3 * i:3 * i + 3] = JX[i]
    dL_dX = -Ninv @ J.T @ JXb
    red = 2 * N - 11
    s0 = float(np.sqrt((res**2).sum() / red)) if red > 0 else float("nan")
    return RefinedCamera(L, Nm, dL_dobs, dL_dX, res, s0, it, Outcome(term, reason))


def triangulate_point(Ls, xys) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray], Outcome]:
    """Least-squares intersection of one point seen by ≥ 2 DLT cameras.

    Parameters
    ----------
    Ls : list of (11,) DLT coefficients
    xys : (M, 2) px, one measurement per camera

    Returns
    -------
    Xn : (3,) normalised point
    dX_dobs : (3, 2M) derivative with respect to the measurements (x0, y0, x1, y1, ...)
    dX_dL : list of (3, 11), one per camera
    residuals : list of (2,) px
    outcome : Outcome (DEGENERATE when the rays are parallel)
    """
    xys = np.asarray(xys, float)
    M = len(Ls)
    A = []
    for L, (x, y) in zip(Ls, xys):
        P = dlt_matrix(L)
        A.append(x * P[2] - P[0])
        A.append(y * P[2] - P[1])
    A = np.asarray(A)
    _, sv, vt = np.linalg.svd(A)
    Xh = vt[-1]
    if abs(Xh[3]) < 1e-12 or sv[-2] < 1e-12 * sv[0]:
        return (np.full(3, np.nan), np.full((3, 2 * M), np.nan), [np.full((3, 11), np.nan)] * M, [],
                Outcome(Termination.DEGENERATE, "rays do not intersect (parallel or point at infinity)"))
    X = Xh[:3] / Xh[3]
    outcome = Outcome(Termination.MAX_ITERATIONS, "no convergence")
    for it in range(30):
        J = np.zeros((2 * M, 3))
        r = np.zeros(2 * M)
        for j, L in enumerate(Ls):
            p, _, JX = dlt_jacobians(L, X[None])
            J[2 * j:2 * j + 2] = JX[0]
            r[2 * j:2 * j + 2] = p[0] - xys[j]
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        X = X + step
        if np.linalg.norm(step) < 1e-14 * (1 + np.linalg.norm(X)):
            outcome = Outcome(Termination.CONVERGED, f"converged in {it + 1} iterations")
            break
    J = np.zeros((2 * M, 3))
    res = []
    dX_dL = []
    JLs = []
    for j, L in enumerate(Ls):
        p, JL, JX = dlt_jacobians(L, X[None])
        J[2 * j:2 * j + 2] = JX[0]
        JLs.append(JL[0])
        res.append(p[0] - xys[j])
    Ninv = np.linalg.inv(J.T @ J)
    dX_dobs = Ninv @ J.T
    for j in range(M):
        dX_dL.append(-Ninv @ J[2 * j:2 * j + 2].T @ JLs[j])
    return X, dX_dobs, dX_dL, res, outcome


def camera_axis_center(P) -> tuple[np.ndarray, np.ndarray]:
    """Viewing axis (unit, world) and projection centre of a 3×4 projection matrix.

    ``P = [M | p4]``; ``C = −M⁻¹ p4``; with ``P`` scaled so that ``det M > 0`` the third row of ``M``
    is ``K33 · R[2]``, the camera axis (seed 000 eq. 6 writes it ``m⁻¹ [0 0 1]ᵀ``).
    """
    P = np.asarray(P, float)
    M = P[:, :3]
    if np.linalg.det(M) < 0:
        M = -M
        P = -P
    C = -np.linalg.solve(M, P[:, 3])
    a = M[2] / np.linalg.norm(M[2])
    return a, C


def decompose_projection(P) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RQ decomposition ``P ∝ K R [I | −C]`` → ``K`` (upper triangular, K33 = 1, positive diagonal),
    ``R`` (proper rotation, cam_from_world) and ``C`` (projection centre)."""
    P = np.asarray(P, float)
    if np.linalg.det(P[:, :3]) < 0:
        P = -P
    M = P[:, :3]
    C = -np.linalg.solve(M, P[:, 3])
    # RQ via QR of the flipped transpose
    F = np.eye(3)[::-1]
    Q, U = np.linalg.qr((F @ M).T)
    K = F @ U.T @ F
    R = F @ Q.T
    D = np.diag(np.sign(np.diag(K)))
    K = K @ D
    R = D @ R
    if np.linalg.det(R) < 0:  # cannot happen with det M > 0 and positive diag(K); guard anyway
        R = -R
        K = -K
    K = K / K[2, 2]
    return K, R, C


def _rot(w) -> np.ndarray:
    """Rodrigues: axis-angle (3,) → rotation matrix."""
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * Kx + (1 - np.cos(th)) * Kx @ Kx


def L_from_pose(K, R, C, frame: Frame) -> np.ndarray:
    """DLT coefficients (normalised frame) of the pinhole camera ``K R [I | −C]`` (world)."""
    P = np.asarray(K, float) @ np.hstack([R, -(R @ np.asarray(C, float))[:, None]])
    Pn = P @ np.linalg.inv(frame.world_matrix())
    return (Pn / Pn[2, 3]).ravel()[:11]


def resect_known_interior(K, Xn, xy_ideal, frame: Frame, *, R0=None, C0=None, max_iterations: int = 50):
    """Space resection with known interior orientation (ideal pinhole ``K``; distortion removed).

    Unknowns: a rotation increment (axis-angle on ``R0``) and the projection centre ``C`` (world, m).
    The start comes from ``R0, C0`` or from OpenCV's ``solvePnP`` (works for coplanar points, where
    the 11-parameter DLT is singular).

    Returns
    -------
    RefinedCamera whose ``L`` is the equivalent DLT of the resected camera, with ``dL_dobs`` and
    ``dL_dX`` for error propagation through the 6 pose parameters; plus ``(R, C)`` as a tuple.
    """
    import cv2

    Xn = np.asarray(Xn, float)
    xy = np.asarray(xy_ideal, float)
    K = np.asarray(K, float)
    N = len(Xn)
    if N < 4:
        raise TooFewPointsError(f"{N} points: a resection with known interior orientation needs at least 4")
    Xw = frame.to_world(Xn)
    if R0 is None or C0 is None:
        ok, rvec, tvec = cv2.solvePnP(Xw, xy, K, None, flags=cv2.SOLVEPNP_SQPNP if N >= 3 else 0)
        if not ok:
            raise DegenerateInputError("space resection: OpenCV solvePnP found no start pose")
        R0 = cv2.Rodrigues(rvec)[0]
        C0 = (-R0.T @ tvec).ravel()
    R0 = np.asarray(R0, float)
    C0 = np.asarray(C0, float)

    def L_of(p):
        return L_from_pose(K, _rot(p[:3]) @ R0, C0 + p[3:], frame)

    def jac_p(p):
        G = np.zeros((11, 6))
        for k in range(6):
            e = np.zeros(6)
            e[k] = 1e-7
            G[:, k] = (L_of(p + e) - L_of(p - e)) / 2e-7
        return G

    p = np.zeros(6)
    term, reason, it = Termination.MAX_ITERATIONS, f"no convergence in {max_iterations} iterations", 0
    for it in range(1, max_iterations + 1):
        L = L_of(p)
        proj, JL, _ = dlt_jacobians(L, Xn)
        J = JL.reshape(2 * N, 11) @ jac_p(p)
        step = np.linalg.lstsq(J, -(proj - xy).ravel(), rcond=None)[0]
        p = p + step
        if np.linalg.norm(step) < 1e-13 * (1 + np.linalg.norm(p)):
            term, reason = Termination.CONVERGED, f"step below 1e-13 after {it} iterations"
            break
    L = L_of(p)
    Gp = jac_p(p)
    proj, JL, JX = dlt_jacobians(L, Xn)
    J = JL.reshape(2 * N, 11) @ Gp
    Ninv = np.linalg.pinv(J.T @ J)
    JXb = np.zeros((2 * N, 3 * N))
    for i in range(N):
        JXb[2 * i:2 * i + 2, 3 * i:3 * i + 3] = JX[i]
    dL_dobs = Gp @ Ninv @ J.T
    dL_dX = -Gp @ Ninv @ J.T @ JXb
    res = proj - xy
    red = 2 * N - 6
    s0 = float(np.sqrt((res**2).sum() / red)) if red > 0 else float("nan")
    rc = RefinedCamera(L, J.T @ J, dL_dobs, dL_dX, res, s0, it, Outcome(term, reason))
    return rc, (_rot(p[:3]) @ R0, C0 + p[3:])
