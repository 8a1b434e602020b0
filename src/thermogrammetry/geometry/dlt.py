"""11-parameter Direct Linear Transformation (DLT) with Hartley normalisation, decomposition and
iterative least-squares refinement with additional (distortion) parameters.

The DLT (Abdel-Aziz & Karara 1971; seed 000 eq. 2)::

    x + v_x + Δx = (L1 X + L2 Y + L3 Z + L4) / (L9 X + L10 Y + L11 Z + 1)
    y + v_y + Δy = (L5 X + L6 Y + L7 Z + L8) / (L9 X + L10 Y + L11 Z + 1)

Image coordinates ``x, y`` are pixels in this project's convention (OpenCV origin, y down);
``L`` are the coefficients of the 3×4 projection matrix ``P = [[L1..L4], [L5..L8], [L9, L10, L11, 1]]``.

1. **Linear solution**: points are normalised (Hartley 1997: image centroid at 0, mean distance √2;
   object centroid at 0, mean distance √3), the homogeneous system is solved by SVD, then
   de-normalised. Needs ≥ 6 points that are not coplanar (for coplanar points the 11 coefficients
   are not determined: the 3×4 matrix has a one-parameter family of solutions).
2. **Refinement** (seed 000 eq. 3–4): Gauss–Newton/LM on the 11 coefficients and the chosen
   additional parameters, in the normalised frames. The systematic correction ``Δx, Δy`` is the
   Brown (1971) / Fraser (1997) correction form evaluated at the *measured* coordinates relative to
   the principal point ``x0(L), y0(L)``::

       x̄ = x − x0,  ȳ = y − y0,  r² = x̄² + ȳ²
       Δx = x̄ (K1 r² + K2 r⁴ + K3 r⁶) + P1 (r² + 2 x̄²) + 2 P2 x̄ ȳ
       Δy = ȳ (K1 r² + K2 r⁴ + K3 r⁶) + 2 P1 x̄ ȳ + P2 (r² + 2 ȳ²)

   with ``x0 = (L1 L9 + L2 L10 + L3 L11) / (L9² + L10² + L11²)`` (and ``y0`` with L5..L7), so the
   problem is non-linear (the principal point depends on L, and the denominator); the Jacobian is
   analytic including ``∂x0/∂L``. The seed's eq. 3–4 are the normal equations of this adjustment
   (its text garbles them: ``B̄ᵀ p̄ c̄`` is meant); we follow Abdel-Aziz & Karara (1971) and
   Marzan & Karara (1975) for the model and Brown (1971) for the correction terms.
3. **Decomposition** of ``P`` into ``K`` (fx, fy, skew, cx, cy; c = fx, aspect = fy/fx), the rotation
   ``R`` (cam_from_world), the projection centre ``X0`` and ω φ κ; with a pixel pitch and the image
   size also c, x0, y0 in millimetres (photogrammetric view, ``docs/conventions.md``) and the
   distortion parameters in the published units (K1 mm⁻², …, P1 mm⁻¹). Standard deviations of every
   derived quantity are propagated from the adjustment covariance (numerical Jacobian of the
   closed-form decomposition, central differences at 10⁻⁴ σ steps).

References
----------
Abdel-Aziz, Y. I., Karara, H. M. (1971). Direct linear transformation from comparator coordinates
into object space coordinates in close-range photogrammetry. Proc. ASP Symposium on Close-Range
Photogrammetry, Urbana, 1–18.
Marzan, G. T., Karara, H. M. (1975). A computer program for direct linear transformation solution of
the collinearity condition, and some applications of it. Proc. ASP Symposium on Close-Range
Photogrammetric Systems, 420–476.
Sawicki, P., Stein, R., Więcek, B. Directional emissivity correction by photogrammetric 3D object
reconstruction (seed 000), eq. 1–4.
Hartley, R. I. (1997). In defense of the eight-point algorithm. IEEE PAMI 19(6), 580–593.
Brown, D. C. (1971). Close-range camera calibration. Photogrammetric Engineering 37(8), 855–866.
Fraser, C. S. (1997). Digital camera self-calibration. ISPRS J. Photogramm. Remote Sens. 52, 149–159.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.linalg

from .._validate import as_array, as_points
from ..adjustment.dense import DenseOptions, DenseResult, solve_dense
from ..errors import DegenerateInputError, InvalidInputError, ShapeError, TooFewPointsError
from ..results import HasOutcome, Outcome, Termination
from . import rotations as rot
from ._common import sigma_per_coordinate
from .pose import Pose

__all__ = [
    "ADDITIONAL_PARAMETERS",
    "DLTResult",
    "dlt",
    "dlt_linear",
    "decompose_projection",
    "hartley_normalisation",
    "check_not_coplanar",
]

#: additional parameters the refinement can estimate (correction form, Brown 1971)
ADDITIONAL_PARAMETERS = ("K1", "K2", "K3", "P1", "P2")

_COPLANAR_TOL = 1e-5


def hartley_normalisation(points) -> np.ndarray:
    """Similarity ``T`` ((d+1)×(d+1)) moving the centroid to 0 and the mean distance to √d.

    Parameters
    ----------
    points : ndarray (N, d)

    Returns
    -------
    T : ndarray (d+1, d+1)
        ``[s·I, −s·mean; 0, 1]``.
    """
    d = points.shape[1]
    mean = points.mean(axis=0)
    dist = np.linalg.norm(points - mean, axis=1).mean()
    s = np.sqrt(d) / dist if dist > 0 else 1.0
    T = np.eye(d + 1)
    T[:d, :d] *= s
    T[:d, d] = -s * mean
    return T


def check_not_coplanar(points_world: np.ndarray, what: str = "control points") -> float:
    """Raise :class:`DegenerateInputError` when the points are (numerically) coplanar.

    Returns the flatness ratio ``s3/s1`` of the singular values of the centred points.
    """
    c = points_world - points_world.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    ratio = s[2] / s[0] if s[0] > 0 else 0.0
    if ratio < _COPLANAR_TOL:
        raise DegenerateInputError(
            f"the {points_world.shape[0]} {what} are coplanar (thickness/extent = {ratio:.2e} < {_COPLANAR_TOL:g}): "
            "the 11-parameter DLT is singular for a planar control field; use a space resection with known "
            "interior orientation (thermogrammetry.geometry.resection with a calibrated Camera) or add control "
            "points off the plane"
        )
    return float(ratio)


def _validate(points_world, xy_px):
    X = as_points(points_world, "points_world", 3)
    x = as_points(xy_px, "xy_px", 2)
    if X.shape[0] != x.shape[0]:
        raise ShapeError(
            f"points_world has {X.shape[0]} rows but xy_px has {x.shape[0]}; expected one image point per control point"
        )
    if X.shape[0] < 6:
        raise TooFewPointsError(
            f"the DLT needs at least 6 control points (11 unknowns, 2 equations per point), got {X.shape[0]}"
        )
    return X, x


def dlt_linear(points_world, xy_px) -> np.ndarray:
    """Linear DLT: the 3×4 projection matrix from ≥ 6 non-coplanar points (Hartley-normalised SVD).

    Parameters
    ----------
    points_world : array_like (N, 3)
        Object coordinates, metres.
    xy_px : array_like (N, 2)
        Image coordinates, pixels (OpenCV origin).

    Returns
    -------
    P : ndarray (3, 4)
        Scaled to unit Frobenius norm with ``det(P[:, :3]) > 0`` (points in front have w > 0).

    Raises
    ------
    TooFewPointsError, DegenerateInputError, ShapeError, NonFiniteError
    """
    X, x = _validate(points_world, xy_px)
    check_not_coplanar(X)
    Pn, T, U = _linear_normalised(X, x)
    P = np.linalg.inv(T) @ Pn @ U
    return _normalise_sign(P / np.linalg.norm(P))


def _linear_normalised(X, x):
    T = hartley_normalisation(x)
    U = hartley_normalisation(X)
    xn = x * T[0, 0] + T[:2, 2]
    Xn = X * U[0, 0] + U[:3, 3]
    Xh = np.hstack([Xn, np.ones((X.shape[0], 1))])
    n = X.shape[0]
    A = np.zeros((2 * n, 12))
    A[0::2, 0:4] = Xh
    A[0::2, 8:12] = -xn[:, :1] * Xh
    A[1::2, 4:8] = Xh
    A[1::2, 8:12] = -xn[:, 1:2] * Xh
    _, _, Vt = np.linalg.svd(A)
    Pn = Vt[-1].reshape(3, 4)
    return Pn, T, U


def _normalise_sign(P):
    return -P if np.linalg.det(P[:, :3]) < 0 else P


def decompose_projection(P) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decompose ``P ∝ K [R | −R C]`` (RQ decomposition).

    Parameters
    ----------
    P : array_like (3, 4)

    Returns
    -------
    K : ndarray (3, 3)
        Upper triangular, positive diagonal, ``K[2, 2] = 1`` (pixels).
    R : ndarray (3, 3)
        cam_from_world rotation (det +1).
    C : ndarray (3,)
        Projection centre (world units).
    """
    P = as_array(P, "P", shape=(3, 4))
    P = _normalise_sign(P)
    M = P[:, :3]
    if abs(np.linalg.det(M)) < 1e-14 * np.linalg.norm(M) ** 3:
        raise DegenerateInputError("P: the left 3×3 block is singular; expected a finite projective camera")
    Kr, Q = scipy.linalg.rq(M)
    D = np.diag(np.sign(np.diag(Kr)))
    K = Kr @ D
    R = D @ Q
    C = -np.linalg.solve(M, P[:, 3])
    return K / K[2, 2], R, C


# --------------------------------------------------------------------------------------------
def _distortion(xb, yb, k, names):
    """Correction Δ at (x̄, ȳ) and its partials. k: dict of the active parameters (others 0)."""
    K1, K2, K3 = k.get("K1", 0.0), k.get("K2", 0.0), k.get("K3", 0.0)
    P1, P2 = k.get("P1", 0.0), k.get("P2", 0.0)
    r2 = xb * xb + yb * yb
    rad = K1 * r2 + K2 * r2**2 + K3 * r2**3
    radp = K1 + 2 * K2 * r2 + 3 * K3 * r2**2  # d rad / d r²
    dx = xb * rad + P1 * (r2 + 2 * xb * xb) + 2 * P2 * xb * yb
    dy = yb * rad + 2 * P1 * xb * yb + P2 * (r2 + 2 * yb * yb)
    dxx = rad + 2 * xb * xb * radp + 6 * P1 * xb + 2 * P2 * yb
    dxy = 2 * xb * yb * radp + 2 * P1 * yb + 2 * P2 * xb
    dyx = dxy
    dyy = rad + 2 * yb * yb * radp + 2 * P1 * xb + 6 * P2 * yb
    # partials w.r.t. the additional parameters, in the order of `names`
    cols_x, cols_y = [], []
    for nme in names:
        if nme == "K1":
            cols_x.append(xb * r2), cols_y.append(yb * r2)
        elif nme == "K2":
            cols_x.append(xb * r2**2), cols_y.append(yb * r2**2)
        elif nme == "K3":
            cols_x.append(xb * r2**3), cols_y.append(yb * r2**3)
        elif nme == "P1":
            cols_x.append(r2 + 2 * xb * xb), cols_y.append(2 * xb * yb)
        elif nme == "P2":
            cols_x.append(2 * xb * yb), cols_y.append(r2 + 2 * yb * yb)
    return dx, dy, dxx, dxy, dyx, dyy, cols_x, cols_y


def _principal_point(L):
    a = L[8] ** 2 + L[9] ** 2 + L[10] ** 2
    x0 = (L[0] * L[8] + L[1] * L[9] + L[2] * L[10]) / a
    y0 = (L[4] * L[8] + L[5] * L[9] + L[6] * L[10]) / a
    dx0 = np.zeros(11)
    dy0 = np.zeros(11)
    dx0[0:3] = L[8:11] / a
    dy0[4:7] = L[8:11] / a
    dx0[8:11] = (L[0:3] - 2 * x0 * L[8:11]) / a
    dy0[8:11] = (L[4:7] - 2 * y0 * L[8:11]) / a
    return x0, y0, dx0, dy0


def _dlt_residuals(params, Xn, xn, names):
    """Misclosures f(L; X) − (x + Δx) (2N,) and Jacobian (2N, 11 + k), normalised frames."""
    L = params[:11]
    k = dict(zip(names, params[11:]))
    X, Y, Z = Xn[:, 0], Xn[:, 1], Xn[:, 2]
    den = L[8] * X + L[9] * Y + L[10] * Z + 1.0
    fx = (L[0] * X + L[1] * Y + L[2] * Z + L[3]) / den
    fy = (L[4] * X + L[5] * Y + L[6] * Z + L[7]) / den
    n = Xn.shape[0]
    J = np.zeros((2 * n, 11 + len(names)))
    Xh = np.stack([X, Y, Z, np.ones_like(X)], 1) / den[:, None]
    J[0::2, 0:4] = Xh
    J[1::2, 4:8] = Xh
    J[0::2, 8:11] = -fx[:, None] * Xh[:, :3]
    J[1::2, 8:11] = -fy[:, None] * Xh[:, :3]
    vx, vy = fx - xn[:, 0], fy - xn[:, 1]
    if names:
        x0, y0, dx0, dy0 = _principal_point(L)
        xb, yb = xn[:, 0] - x0, xn[:, 1] - y0
        ddx, ddy, dxx, dxy, dyx, dyy, cx, cy = _distortion(xb, yb, k, names)
        vx = vx - ddx
        vy = vy - ddy
        # v = f − x − Δ(x − x0(L)) → ∂v/∂L += ∂Δ/∂x̄ · ∂x0/∂L + ∂Δ/∂ȳ · ∂y0/∂L
        J[0::2, :11] += dxx[:, None] * dx0 + dxy[:, None] * dy0
        J[1::2, :11] += dyx[:, None] * dx0 + dyy[:, None] * dy0
        for j in range(len(names)):
            J[0::2, 11 + j] = -cx[j]
            J[1::2, 11 + j] = -cy[j]
    v = np.empty(2 * n)
    v[0::2] = vx
    v[1::2] = vy
    return v, J


@dataclass(frozen=True, eq=False)
class DLTResult(HasOutcome):
    """Result of :func:`dlt`.

    Attributes
    ----------
    P : ndarray (3, 4)
        Projection matrix in pixels, scaled so that ``P[2, 3] = 1`` (then ``L = P.ravel()[:11]``);
        if the world origin lies (nearly) on the camera's principal plane this scaling is undefined
        and ``P`` has unit norm instead (``L`` is NaN).
    L : ndarray (11,)
        DLT coefficients L1..L11 (pixel and world units).
    K, R, center : ndarray
        Decomposition (pixels; cam_from_world; metres).
    pose : Pose
    omega, phi, kappa : float
        Radians (photogrammetric view).
    additional : dict
        Estimated additional parameters in pixel units (y down): ``K1 px⁻², K2 px⁻⁴, K3 px⁻⁶, P1, P2 px⁻¹``.
    additional_mm : dict or None
        Same in the published units (mm, y up; needs a square pixel pitch): ``P2_mm = −P2_px / pitch``.
    values, std, std_prior : dict
        Every derived quantity (fx, fy, skew, cx, cy, c_px, aspect, X0, Y0, Z0, omega, phi, kappa,
        c_mm, x0_mm, y0_mm when available, L1..L11, and the additional parameters ``K1_px``…,
        ``K1_mm``…) with its a-posteriori and a-priori (``sigma_px``) standard deviation.
    derived_names : tuple, derived_covariance : ndarray
        A-posteriori covariance of ``values`` in that order.
    residuals_px : ndarray (N, 2)
        ``v`` in pixels: DLT(X) − (x + Δx).
    rms_px : float
    sigma0 : float
        A posteriori σ0 (unitless, relative to ``sigma_px``).
    adjustment : DenseResult or None
        The refinement (normalised frames); None when ``refine=False``.
    outcome : Outcome
    """

    P: np.ndarray
    L: np.ndarray
    K: np.ndarray
    R: np.ndarray
    center: np.ndarray
    pose: Pose
    omega: float
    phi: float
    kappa: float
    additional: dict
    additional_mm: dict | None
    values: dict
    std: dict
    std_prior: dict
    derived_names: tuple
    derived_covariance: np.ndarray
    residuals_px: np.ndarray
    rms_px: float
    sigma0: float
    adjustment: DenseResult | None
    outcome: Outcome
    image_size: tuple | None = None
    pixel_pitch_um: tuple | None = None

    def project(self, points_world, *, iterations: int = 20) -> np.ndarray:
        """Project with the refined DLT including the additional parameters (pixels).

        The correction form is implicit in the measured coordinates: ``x + Δx(x) = DLT(X)`` is
        solved by Newton's method (converges to < 1e-12 px for realistic distortion).
        """
        X = as_points(points_world, "points_world", 3)
        Xh = np.hstack([X, np.ones((X.shape[0], 1))]) @ self.P.T
        xi = Xh[:, :2] / Xh[:, 2:3]
        if not self.additional:
            return xi
        x0, y0 = self.K[0, 2], self.K[1, 2]
        x = xi.copy()
        for _ in range(iterations):
            xb, yb = x[:, 0] - x0, x[:, 1] - y0
            dx, dy, dxx, dxy, dyx, dyy, _, _ = _distortion(xb, yb, self.additional, ())
            fx = x[:, 0] + dx - xi[:, 0]
            fy = x[:, 1] + dy - xi[:, 1]
            a, b, c, d = 1 + dxx, dxy, dyx, 1 + dyy
            det = a * d - b * c
            x[:, 0] -= (d * fx - b * fy) / det
            x[:, 1] -= (-c * fx + a * fy) / det
            if max(np.abs(fx).max(), np.abs(fy).max()) < 1e-13:
                break
        return x

    def to_camera(self, model: str = "auto", *, tol_px: float = 0.01, name: str = ""):
        """The decomposed interior orientation as a :class:`thermogrammetry.Camera`.

        Parameters
        ----------
        model : {"auto", "photogrammetric", "opencv"}
            ``"photogrammetric"`` (correction form, needs ``pixel_pitch_um`` (square) and ``image_size``):
            ``c_mm = fy·pitch``, ``x0_mm``, ``y0_mm``, the additional parameters in mm units, and the
            DLT's affinity as ``B1 = fy/fx − 1``, ``B2 = skew/fx``. This is exact when aspect = 1
            and skew = 0 or without additional parameters; otherwise it neglects
            ``(fy/fx − 1)·Δx + (skew/fx)·Δy`` (checked over the image against ``tol_px``).
            ``"opencv"``: ``fx fy cx cy skew``; only without additional parameters (they are in the
            correction form; use ``thermogrammetry.camera.convert_camera`` to fit a forward model).
            ``"auto"``: photogrammetric when a pixel pitch is known, else opencv.
        tol_px : float
            Largest acceptable neglected term (px) for the photogrammetric conversion.

        Raises
        ------
        InvalidInputError
            Missing image size / pitch, or a conversion that cannot represent the result.
        """
        from ..camera import Camera

        if self.image_size is None:
            raise InvalidInputError("to_camera: the DLT was run without image_size; pass image_size=(w, h) to dlt()")
        if model == "auto":
            model = "photogrammetric" if self.pixel_pitch_um is not None else "opencv"
        K = self.K
        fx, fy, s = K[0, 0], K[1, 1], K[0, 1]
        if model == "opencv":
            if self.additional:
                raise InvalidInputError(
                    f"to_camera('opencv'): the additional parameters {sorted(self.additional)} are in the correction "
                    "form; use model='photogrammetric' (needs pixel_pitch_um) or fit a forward model with convert_camera"
                )
            return Camera("opencv", self.image_size, dict(fx=fx, fy=fy, cx=K[0, 2], cy=K[1, 2], skew=s), name=name)
        if model != "photogrammetric":
            raise InvalidInputError(f"to_camera: model {model!r}; expected 'auto', 'photogrammetric' or 'opencv'")
        pitch = self.pixel_pitch_um
        if pitch is None or abs(pitch[0] - pitch[1]) > 1e-9 * pitch[0]:
            raise InvalidInputError(f"to_camera('photogrammetric'): needs a square pixel pitch, got pixel_pitch_um={pitch}")
        a = pitch[0] / 1000.0
        w, h = self.image_size
        params = dict(c_mm=fy * a, x0_mm=(K[0, 2] - (w - 1) / 2.0) * a, y0_mm=-(K[1, 2] - (h - 1) / 2.0) * a,
                      B1=fy / fx - 1.0, B2=s / fx)
        params.update(self.additional_mm or {})
        if self.additional:
            gx, gy = np.meshgrid(np.linspace(0, w - 1, 33), np.linspace(0, h - 1, 25))
            xb, yb = gx.ravel() - K[0, 2], gy.ravel() - K[1, 2]
            dx, dy, *_ = _distortion(xb, yb, self.additional, ())
            neglected = np.abs((fy / fx - 1.0) * dx + (s / fx) * dy).max()
            if neglected > tol_px:
                raise InvalidInputError(
                    f"to_camera('photogrammetric'): aspect {fy / fx:.6f} and skew {s:.3g} px with the distortion give a "
                    f"model difference of {neglected:.3g} px > tol_px={tol_px}"
                )
        return Camera("photogrammetric", self.image_size, params, pixel_pitch_um=pitch[0], name=name)

    def project_ideal(self, points_world) -> np.ndarray:
        """Project with the 3×4 matrix only (no additional parameters), pixels."""
        X = as_points(points_world, "points_world", 3)
        Xh = np.hstack([X, np.ones((X.shape[0], 1))]) @ self.P.T
        return Xh[:, :2] / Xh[:, 2:3]


def _pitch_pair(pixel_pitch_um):
    if pixel_pitch_um is None:
        return None
    p = np.atleast_1d(as_array(pixel_pitch_um, "pixel_pitch_um"))
    if p.shape not in ((1,), (2,)) or np.any(p <= 0):
        raise InvalidInputError(f"pixel_pitch_um: {pixel_pitch_um!r}; expected a positive number or (px, py) in µm")
    return (float(p[0]), float(p[-1]))


def _derived(P, add_px, image_size, pitch):
    """Ordered dict of derived quantities from P (pixels) and pixel-unit additional parameters."""
    K, R, C = decompose_projection(P)
    o, f, k = rot.opk_from_matrix(rot.PHOTO_FROM_CAM @ R)
    out = {
        "fx": K[0, 0], "fy": K[1, 1], "skew": K[0, 1], "cx": K[0, 2], "cy": K[1, 2],
        "c_px": K[0, 0], "aspect": K[1, 1] / K[0, 0],
        "X0": C[0], "Y0": C[1], "Z0": C[2], "omega": float(o), "phi": float(f), "kappa": float(k),
    }
    if pitch is not None:
        px_mm, py_mm = pitch[0] / 1000.0, pitch[1] / 1000.0
        out["c_mm"] = K[0, 0] * px_mm
        if image_size is not None:
            w, h = image_size
            out["x0_mm"] = (K[0, 2] - (w - 1) / 2.0) * px_mm
            out["y0_mm"] = -(K[1, 2] - (h - 1) / 2.0) * py_mm
    if abs(P[2, 3] - 1.0) < 1e-12:
        for i, val in enumerate(P.ravel()[:11]):
            out[f"L{i + 1}"] = val
    for nme, val in add_px.items():
        out[nme + "_px"] = val
    if pitch is not None and add_px and abs(pitch[0] - pitch[1]) <= 1e-9 * pitch[0]:
        a = pitch[0] / 1000.0
        conv = {"K1": a**-2, "K2": a**-4, "K3": a**-6, "P1": 1 / a, "P2": -1 / a}
        for nme, val in add_px.items():
            out[nme + "_mm"] = val * conv[nme]
    return out


def dlt(
    points_world,
    xy_px,
    *,
    additional: Sequence[str] = (),
    sigma_px: float = 1.0,
    image_size: tuple[int, int] | None = None,
    pixel_pitch_um=None,
    refine: bool = True,
    options: DenseOptions | None = None,
) -> DLTResult:
    """11-parameter DLT: linear solution, least-squares refinement, decomposition, precision.

    Parameters
    ----------
    points_world : array_like (N, 3)
        Control point coordinates, metres; N ≥ 6, not coplanar.
    xy_px : array_like (N, 2)
        Measured image coordinates, pixels (OpenCV origin: (0, 0) centre of the top-left pixel).
    additional : sequence of {"K1", "K2", "K3", "P1", "P2"}
        Additional parameters estimated in the refinement (seed 000 eq. 2: Δx, Δy).
    sigma_px : float or array_like (N,) or (N, 2)
        A-priori standard deviation of an image coordinate (pixels); sets the weights and
        ``std_prior``.
    image_size : (w, h), optional
        Needed for x0, y0 in millimetres.
    pixel_pitch_um : float or (px, py), optional
        Needed for c, x0, y0 and the additional parameters in millimetre units.
    refine : bool
        Run the iterative least-squares refinement (default). Without it, no precision is reported.
    options : DenseOptions, optional

    Returns
    -------
    DLTResult

    Raises
    ------
    TooFewPointsError
        Fewer than 6 points (the message names the count).
    DegenerateInputError
        Coplanar control points (the DLT is singular there; use a space resection with a known
        interior orientation instead), or 2N < 11 + number of additional parameters.
    ShapeError, NonFiniteError, InvalidInputError
        Wrong shapes, NaN/inf, unknown additional parameter names.

    References
    ----------
    Abdel-Aziz & Karara (1971); seed 000 eq. 2–4; Hartley (1997); Brown (1971).
    """
    X, x = _validate(points_world, xy_px)
    names = tuple(str(a).upper() for a in additional)
    bad = [a for a in names if a not in ADDITIONAL_PARAMETERS]
    if bad or len(set(names)) != len(names):
        raise InvalidInputError(
            f"additional: {tuple(additional)!r} contains unknown or repeated names {bad}; expected a subset of {ADDITIONAL_PARAMETERS}"
        )
    names = tuple(a for a in ADDITIONAL_PARAMETERS if a in names)
    if 2 * X.shape[0] < 11 + len(names):
        raise TooFewPointsError(
            f"{X.shape[0]} points give {2 * X.shape[0]} equations for {11 + len(names)} unknowns (11 DLT + {list(names)})"
        )
    sig = sigma_per_coordinate(sigma_px, (X.shape[0],))
    if image_size is not None:
        iw, ih = (int(v) for v in image_size)
        image_size = (iw, ih)
    pitch = _pitch_pair(pixel_pitch_um)
    check_not_coplanar(X)
    Pn, T, U = _linear_normalised(X, x)
    Tinv = np.linalg.inv(T)
    s_T = T[0, 0]
    xn = x * s_T + T[:2, 2]
    Xn = X * U[0, 0] + U[:3, 3]
    if abs(Pn[2, 3]) < 1e-9 * np.linalg.norm(Pn):
        # centroid of the control points on the principal plane: the L-form of the DLT is undefined
        P = _normalise_sign(Tinv @ Pn @ U)
        P /= np.linalg.norm(P)
        return _finish(P, {}, None, X, x, image_size, pitch, sigma_px, T, U, names,
                       Outcome(Termination.DEGENERATE, "the control points' centroid lies on the camera's principal "
                               "plane; the 11-parameter form is undefined"), None)
    Ln = (Pn / Pn[2, 3]).ravel()[:11]
    adj = None
    params = np.concatenate([Ln, np.zeros(len(names))])
    if refine:
        sig_n = sig.ravel() * s_T
        adj = solve_dense(
            lambda p: _dlt_residuals(p, Xn, xn, names),
            params,
            weights=np.full(2 * X.shape[0], 1.0 / sig_n**2),
            param_names=[f"L{i}" for i in range(1, 12)] + list(names),
            options=options,
        )
        params = adj.x
        outcome = adj.outcome
    else:
        outcome = Outcome(Termination.CONVERGED, "linear solution only (refine=False)")
    return _finish(None, params, adj, X, x, image_size, pitch, sigma_px, T, U, names, outcome, s_T)


def _params_to_P_add(params, T, U, names):
    Tinv = np.linalg.inv(T)
    Pn = np.append(params[:11], 1.0).reshape(3, 4)
    P = Tinv @ Pn @ U
    if abs(P[2, 3]) > 1e-12 * np.linalg.norm(P):
        P = P / P[2, 3]
    else:
        P = _normalise_sign(P) / np.linalg.norm(P)
    s = T[0, 0]
    pw = {"K1": 2, "K2": 4, "K3": 6, "P1": 1, "P2": 1}
    add = {nme: float(v) * s ** pw[nme] for nme, v in zip(names, params[11:])}
    return P, add


def _finish(P, params, adj, X, x, image_size, pitch, sigma_px, T, U, names, outcome, s_T):
    if P is None:
        P, add = _params_to_P_add(params, T, U, names)
    else:
        add = {}
    K, R, C = decompose_projection(P)
    pose = Pose(R, -R @ C)
    o, f, k = rot.opk_from_matrix(rot.PHOTO_FROM_CAM @ R)
    L = P.ravel()[:11].copy() if abs(P[2, 3] - 1.0) < 1e-12 else np.full(11, np.nan)
    values = _derived(P, add, image_size, pitch)
    dnames = tuple(values)
    nd = len(dnames)
    cov_d = np.full((nd, nd), np.nan)
    cov_dp = np.full((nd, nd), np.nan)
    if adj is not None and np.all(np.isfinite(adj.cofactor)):
        Q = adj.cofactor
        std_p = np.sqrt(np.clip(np.diag(Q), 0, None))
        Jd = np.zeros((nd, params.size))
        for i in range(params.size):
            h = 1e-4 * std_p[i] if std_p[i] > 0 else 1e-8
            e = np.zeros(params.size)
            e[i] = h
            vp = _derived(*_params_to_P_add(params + e, T, U, names), image_size, pitch)
            vm = _derived(*_params_to_P_add(params - e, T, U, names), image_size, pitch)
            dv = np.array([vp[n] for n in dnames]) - np.array([vm[n] for n in dnames])
            for j, nme in enumerate(dnames):  # angles: wrap differences
                if nme in ("omega", "phi", "kappa"):
                    dv[j] = (dv[j] + np.pi) % (2 * np.pi) - np.pi
            Jd[:, i] = dv / (2 * h)
        cov_dp = Jd @ (adj.covariance_prior) @ Jd.T
        cov_d = Jd @ adj.covariance @ Jd.T
    sd = np.sqrt(np.clip(np.diag(cov_d), 0, None)) if np.all(np.isfinite(np.diag(cov_d))) else np.full(nd, np.nan)
    sdp = np.sqrt(np.clip(np.diag(cov_dp), 0, None)) if np.all(np.isfinite(np.diag(cov_dp))) else np.full(nd, np.nan)
    if adj is not None:
        res_px = (adj.residuals / T[0, 0]).reshape(-1, 2)
        sigma0 = adj.sigma0
    else:
        Xh = np.hstack([X, np.ones((X.shape[0], 1))]) @ P.T
        res_px = Xh[:, :2] / Xh[:, 2:3] - x
        sigma0 = np.nan
    add_mm = None
    if pitch is not None and add and abs(pitch[0] - pitch[1]) <= 1e-9 * pitch[0]:
        add_mm = {nme: values[nme + "_mm"] for nme in add}
    return DLTResult(
        P=P, L=L, K=K, R=R, center=C, pose=pose, omega=float(o), phi=float(f), kappa=float(k),
        additional=add, additional_mm=add_mm,
        values={n: float(values[n]) for n in dnames},
        std={n: float(s) for n, s in zip(dnames, sd)},
        std_prior={n: float(s) for n, s in zip(dnames, sdp)},
        derived_names=dnames, derived_covariance=cov_d,
        residuals_px=res_px, rms_px=float(np.sqrt(np.mean(res_px**2))), sigma0=float(sigma0),
        adjustment=adj, outcome=outcome, image_size=image_size, pixel_pitch_um=pitch,
    )
