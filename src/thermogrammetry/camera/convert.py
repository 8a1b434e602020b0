"""Conversion between camera models by a least-squares fit over the whole image.

The forward (OpenCV) and correction (photogrammetric) forms of Brown-Conrady distortion are not
exact inverses of each other: a correction polynomial evaluated at measured coordinates becomes an
infinite series when evaluated at ideal coordinates. :func:`convert_camera` therefore samples a
dense grid of pixels over the whole image (borders included), takes the source camera's ray through
each, and fits the target model so that it projects those rays back onto the same pixels; it reports
the maximum and RMS pixel residual over that grid.

References
----------
Brown, D. C. (1971). Close-range camera calibration. Photogrammetric Engineering 37(8), 855-866.
Fraser, C. S. (1997). Digital camera self-calibration. ISPRS J. Photogramm. Remote Sens. 52, 149-159.
Drap, P., Lefevre, J. (2016). An exact formula for calculating inverse radial lens distortions.
Sensors 16(6), 807 (why the two forms are not interchangeable in closed form).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError, InvalidInputError, ShapeError, TooFewPointsError
from ..results import Outcome, Termination
from . import models as M
from .camera import Camera
from .models import PARAM_NAMES, CameraModel

__all__ = ["CameraConversion", "convert_camera", "fit_camera", "image_grid", "default_free_params", "radial_kappa",
           "inside_area", "conversion_covariance", "KAPPA_MAX"]


@dataclass(frozen=True)
class CameraConversion:
    """Result of a model conversion / fit.

    Attributes
    ----------
    camera : Camera
        The fitted camera in the target model.
    max_residual_px : float
        Largest Euclidean reprojection difference over the fit grid, pixels.
    rms_residual_px : float
        RMS of the Euclidean differences, pixels.
    n_points : int
        Grid points used (source rays that exist).
    outcome : Outcome
        Termination and reason of the fit (a failed fit is a value, not an exception).
    free : tuple[str, ...]
        Parameters that were estimated; the others were held at their initial values.
    """

    camera: Camera
    max_residual_px: float
    rms_residual_px: float
    n_points: int = 0
    outcome: Outcome = field(default_factory=lambda: Outcome(Termination.CONVERGED, ""))
    free: tuple[str, ...] = ()
    area_max_residual_px: float = float("nan")
    area_rms_residual_px: float = float("nan")
    kappa: dict = field(default_factory=dict)

    @property
    def success(self) -> bool:
        return self.outcome.success

    def summary(self) -> dict:
        """The figures an export records: max/RMS residual over the whole frame and over the data area
        (``area_*``, NaN when no area was given), the conditioning (``kappa``) and the outcome."""
        def f(v):
            v = float(v)
            return v if np.isfinite(v) else None

        return {"max_residual_px": f(self.max_residual_px), "rms_residual_px": f(self.rms_residual_px),
                "area_max_residual_px": f(self.area_max_residual_px), "area_rms_residual_px": f(self.area_rms_residual_px),
                "kappa": {k: f(v) for k, v in self.kappa.items()},
                "termination": self.outcome.termination.value, "reason": self.outcome.reason}


#: largest allowed |k_i r_max^(2i)| (the contribution of a radial term at the frame corner, as a
#: fraction of the radius) of a forward-model fit; above it the coefficients are cancelling each
#: other (k2 = 1283, k3 = -12509 style) and the fit is regularised.
KAPPA_MAX = 1.0

_KAPPA_POW = {"k1": 1, "k2": 2, "k3": 3, "k4": 1, "k5": 2, "k6": 3}


def radial_kappa(camera: Camera, r2max: float) -> dict[str, float]:
    """``{k_i: k_i * r2max**n}`` for the radial terms of an OpenCV camera (empty for other models):
    each term's relative contribution at the largest normalised radius ``sqrt(r2max)`` of the frame."""
    if camera.model is not CameraModel.OPENCV:
        return {}
    p = camera.param_dict
    return {k: float(p[k] * r2max**n) for k, n in _KAPPA_POW.items()}


def inside_area(xy: np.ndarray, area_px) -> np.ndarray:
    """Mask of the points ``xy`` (N, 2) inside the convex hull of ``area_px`` (M, 2) (the area the
    calibration data covered)."""
    import cv2

    a = np.asarray(area_px, dtype=np.float64).reshape(-1, 2)
    a = a[np.all(np.isfinite(a), axis=1)]
    if len(a) < 3:
        return np.zeros(len(xy), bool)
    hull = cv2.convexHull(a.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    if len(hull) < 3:
        return np.zeros(len(xy), bool)
    # inside a convex polygon: same side of every edge
    e0, e1 = hull, np.roll(hull, -1, axis=0)
    cross = ((e1[:, 0] - e0[:, 0])[None] * (xy[:, 1:2] - e0[:, 1][None])
             - (e1[:, 1] - e0[:, 1])[None] * (xy[:, 0:1] - e0[:, 0][None]))
    return np.all(cross >= -1e-9, axis=1) | np.all(cross <= 1e-9, axis=1)


def image_grid(image_size, step_px: float | None = None) -> np.ndarray:
    """Regular grid (N, 2) over the whole image, from -0.5 to w-0.5 / h-0.5 (outer pixel borders).

    Default step: ``max(w, h) / 64`` pixels (about 65 points along the long side).
    """
    w, h = image_size
    step = float(step_px) if step_px is not None else max(w, h) / 64.0
    if not step > 0:
        raise InvalidInputError(f"grid_step_px: must be positive, got {step_px!r}")
    nx = max(2, int(np.ceil(w / step)) + 1)
    ny = max(2, int(np.ceil(h / step)) + 1)
    u, v = np.meshgrid(np.linspace(-0.5, w - 0.5, nx), np.linspace(-0.5, h - 0.5, ny))
    return np.column_stack([u.ravel(), v.ravel()])


def _initial_params(target: CameraModel, K: np.ndarray, image_size, pitch) -> dict[str, float]:
    fx, skew, cx = K[0]
    fy, cy = K[1, 1], K[1, 2]
    if target is CameraModel.PINHOLE:
        return {"fx": fx, "fy": fy, "cx": cx, "cy": cy}
    if target is CameraModel.OPENCV:
        return {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "skew": skew}
    sx, sy = pitch[0] * 1e-3, pitch[1] * 1e-3
    c = fy * sy
    w, h = image_size
    return {"c_mm": c, "x0_mm": (cx - 0.5 * (w - 1)) * sx, "y0_mm": -(cy - 0.5 * (h - 1)) * sy,
            "B1": c / (fx * sx) - 1.0, "B2": 0.0}


def default_free_params(source: Camera, target: CameraModel) -> tuple[str, ...]:
    """Parameters estimated by default when converting ``source`` to ``target``.

    pinhole: all; opencv: fx fy cx cy k1 k2 p1 p2 k3 (+ skew when the source has skew/B2,
    + k4 k5 k6 when the source is opencv with rational terms); photogrammetric: c x0 y0 K1 K2 K3
    P1 P2 B1 (+ B2 when the source has skew/B2, + K4 K5 when the source is photogrammetric with them).
    """
    target = CameraModel(target)
    p = source.param_dict
    has_skew = p.get("skew", 0.0) != 0.0 or p.get("B2", 0.0) != 0.0
    if target is CameraModel.PINHOLE:
        return PARAM_NAMES[target]
    if target is CameraModel.OPENCV:
        free = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"]
        if has_skew:
            free.append("skew")
        if source.model is CameraModel.OPENCV and any(p[k] != 0.0 for k in ("k4", "k5", "k6")):
            free += ["k4", "k5", "k6"]
        return tuple(free)
    free = ["c_mm", "x0_mm", "y0_mm", "K1", "K2", "K3", "P1", "P2", "B1"]
    if has_skew:
        free.append("B2")
    if source.model is CameraModel.PHOTOGRAMMETRIC and (p["K4"] != 0.0 or p["K5"] != 0.0):
        free += ["K4", "K5"]
    return tuple(free)


def fit_camera(target_model, image_size, rays, xy_px, *, init: dict | None = None, free: Sequence[str] | None = None,
               pixel_pitch_um=None, name: str = "", max_nfev: int = 200, ridge_px: float = 0.0) -> CameraConversion:
    """Fit a camera of ``target_model`` so that it projects ``rays`` (N, 3) onto ``xy_px`` (N, 2).

    Parameters
    ----------
    target_model : str or CameraModel
    image_size : (w, h)
    rays : (N, 3) camera-frame directions (z > 0).
    xy_px : (N, 2) pixels they must project to.
    init : dict, optional
        Initial parameter values by name (others 0; fx/fy/cx/cy or c_mm/x0_mm/y0_mm required).
    free : sequence of str, optional
        Parameters to estimate (default: all of the model except skew/B2 and K4/K5/k4..k6).
    pixel_pitch_um : needed for the photogrammetric model.
    ridge_px : float
        OpenCV target: Tikhonov regularisation of the higher radial terms k2, k3, k4, k5, k6 in their
        scaled form ``kappa_i = k_i r_max^(2i)``: each adds ``N (ridge_px kappa_i)^2`` to the cost
        (0 = plain least squares).

    Returns
    -------
    CameraConversion
        For a photogrammetric target the fit runs first in ray space (the closed-form unprojection,
        no Newton solves), then refines in pixel space; the residuals are always pixel reprojection
        differences ``project(rays) - xy_px``.
    """
    from scipy.optimize import least_squares

    target = CameraModel(target_model)
    names = PARAM_NAMES[target]
    rays = np.asarray(rays, dtype=np.float64)
    xy = np.asarray(xy_px, dtype=np.float64)
    if rays.ndim != 2 or rays.shape[1] != 3 or xy.shape != (rays.shape[0], 2):
        raise ShapeError(f"fit_camera: expected rays (N, 3) and xy_px (N, 2), got {rays.shape} and {xy.shape}")
    if free is None:
        free = tuple(k for k in names if k not in ("skew", "B2", "k4", "k5", "k6", "K4", "K5"))
    free = tuple(free)
    bad = [k for k in free if k not in names]
    if bad:
        raise ConfigError(f"free: unknown parameter(s) {', '.join(map(repr, bad))} for model {target.value!r}; "
                          f"expected names from: {' '.join(names)}")
    if len(rays) * 2 < len(free) or len(rays) < 3:
        raise TooFewPointsError(f"fit_camera: {len(rays)} points cannot determine {len(free)} parameters")
    base = Camera(target, image_size, dict(init or {}), pixel_pitch_um=pixel_pitch_um, name=name)
    idx = np.array([names.index(k) for k in free], dtype=int)
    p0 = base.params.copy()

    def full(theta):
        p = p0.copy()
        p[idx] = theta
        return p

    kw = {"image_size": base.image_size, "pixel_pitch_um": base.pixel_pitch_um}
    reason = ""
    theta = p0[idx].copy()
    if target is CameraModel.PHOTOGRAMMETRIC:
        # Stage 1: ray space (closed form, robust to poor starts); residual scaled to ~px by c/pitch.
        scale = base.K[1, 1]
        ray_n = rays[:, :2] / rays[:, 2:3]

        def res_rays(t):
            p = full(t)
            return ((M.photogrammetric_unproject(p, xy, **kw)[:, :2] - ray_n) * scale).ravel()

        sol = least_squares(res_rays, theta, method="lm", x_scale="jac", ftol=1e-14, xtol=1e-14, gtol=1e-14,
                            max_nfev=max_nfev * (len(free) + 1))
        theta = sol.x

    reg = []  # (position in theta, scale) of the regularised coefficients
    if ridge_px > 0 and target is CameraModel.OPENCV:
        r2max = float(np.max(np.sum((rays[:, :2] / rays[:, 2:3]) ** 2, axis=1)))
        w = ridge_px * np.sqrt(len(rays))
        reg = [(j, w * r2max ** _KAPPA_POW[k]) for j, k in enumerate(free) if k in ("k2", "k3", "k4", "k5", "k6")]

    def res_px(t):
        r = np.nan_to_num(M.project(target, full(t), rays, **kw) - xy, nan=1e6).ravel()
        if reg:
            r = np.concatenate([r, [sc * t[j] for j, sc in reg]])
        return r

    def jac_px(t):
        _, _, Jt = M.project_jacobian(target, full(t), rays, **kw)
        J = np.nan_to_num(Jt[:, :, idx].reshape(-1, len(idx)))
        if reg:
            R = np.zeros((len(reg), len(idx)))
            for row, (j, sc) in enumerate(reg):
                R[row, j] = sc
            J = np.vstack([J, R])
        return J

    sol = least_squares(res_px, theta, jac=jac_px, method="lm", x_scale="jac", ftol=1e-14, xtol=1e-14, gtol=1e-14,
                        max_nfev=max_nfev)
    term = Termination.CONVERGED if sol.status > 0 else Termination.MAX_ITERATIONS
    reason = sol.message
    try:
        cam = base.with_params(full(sol.x))
    except InvalidInputError as exc:  # e.g. a focal length driven negative by a hopeless fit
        return CameraConversion(base, float("inf"), float("inf"), len(rays),
                                Outcome(Termination.DIVERGED, f"fit left the valid parameter space: {exc}"), free)
    r = cam.project(rays) - xy
    d = np.linalg.norm(r, axis=1)
    if not np.all(np.isfinite(d)):
        nbad = int(np.sum(~np.isfinite(d)))
        return CameraConversion(cam, float("inf"), float("inf"), len(rays),
                                Outcome(Termination.NUMERICAL_FAILURE,
                                        f"{nbad} grid point(s) cannot be projected by the fitted camera"), free)
    return CameraConversion(cam, float(d.max()), float(np.sqrt(np.mean(d * d))), len(rays),
                            Outcome(term, reason), free)


def convert_camera(camera: Camera, target_model, *, free: Sequence[str] | None = None, pixel_pitch_um=None,
                   grid_step_px: float | None = None, rational: bool | None = None,
                   area_px=None) -> CameraConversion:
    """Convert ``camera`` to ``target_model`` by least squares over a dense grid over the whole image.

    Parameters
    ----------
    camera : Camera
        Source camera.
    target_model : {"pinhole", "opencv", "photogrammetric"}
    free : sequence of str, optional
        Target parameters to estimate (default :func:`default_free_params`); the others stay 0.
    pixel_pitch_um : float or (px, py), optional
        Pixel pitch of the target (default: the source's; required for a photogrammetric target).
    grid_step_px : float, optional
        Grid spacing in pixels (default ``max(w, h)/64``); the grid includes the outer pixel borders.
    rational : bool, optional
        OpenCV target only, when ``free`` is not given: also estimate the rational terms k4..k6.
        ``None`` (default) decides from the data: if the polynomial fit (k1..k3) leaves more than
        0.1 px, a rational fit is tried and kept when it at least halves the maximum residual and its
        denominator ``1 + k4 r2 + k5 r2^2 + k6 r2^3`` stays above 0.5 over the image (no pole near the
        frame) and every scaled radial term ``|k_i r_max^(2i)|`` stays <= :data:`KAPPA_MAX` (well
        conditioned). ``outcome.reason`` and ``free`` say which was kept.
    area_px : (M, 2) array, optional
        Pixels the calibration data covered (e.g. every measured target point); the residual is also
        reported over their convex hull (``area_max_residual_px``, ``area_rms_residual_px``).

    Notes
    -----
    An OpenCV fit whose scaled radial terms exceed :data:`KAPPA_MAX` (terms cancelling each other,
    e.g. k2 = 1283 with k3 = -12509) is refitted with an increasing ridge on k2..k6
    (:func:`fit_camera` ``ridge_px``) until they are bounded; the residual of the bounded fit is what is
    reported, and ``kappa`` holds the scaled terms.

    Returns
    -------
    CameraConversion
        ``camera``, ``max_residual_px`` and ``rms_residual_px`` over the grid (pixel distance
        between the source's measured pixel and the fitted camera's projection of the same ray).
        Source pixels whose ray does not exist (non-invertible distortion) are left out and
        counted in ``outcome.reason``.

    References
    ----------
    Brown (1971); Fraser (1997).
    """
    if not isinstance(camera, Camera):
        raise InvalidInputError(f"convert_camera: expected a Camera, got {type(camera).__name__}")
    target = CameraModel(target_model)
    pitch = pixel_pitch_um if pixel_pitch_um is not None else camera.pixel_pitch_um
    if target is CameraModel.PHOTOGRAMMETRIC and pitch is None:
        raise InvalidInputError(
            "convert_camera: the photogrammetric target needs pixel_pitch_um (the source camera has none)"
        )
    grid = image_grid(camera.image_size, grid_step_px)
    rays = camera.unproject(grid)
    ok = np.all(np.isfinite(rays), axis=1)
    auto_free = free is None
    if free is None:
        free = default_free_params(camera, target)
        if target is CameraModel.OPENCV and rational is not None:
            free = tuple(k for k in free if k not in ("k4", "k5", "k6")) + (("k4", "k5", "k6") if rational else ())
    pitch_tuple = None if pitch is None else tuple(np.broadcast_to(np.asarray(pitch, float), (2,)))
    init = _initial_params(target, camera.K, camera.image_size, pitch_tuple)
    if target is camera.model:  # same model: start at the source (an exact solution), not at zero distortion
        init = dict(camera.param_dict)
    if target is CameraModel.OPENCV and "skew" not in free:
        init["skew"] = 0.0
    if target is CameraModel.PHOTOGRAMMETRIC and "B2" not in free:
        init["B2"] = 0.0
    res = fit_camera(target, camera.image_size, rays[ok], grid[ok], init=init, free=free,
                     pixel_pitch_um=pitch, name=camera.name)
    if (auto_free and rational is None and target is CameraModel.OPENCV and "k4" not in free
            and res.success and res.max_residual_px > 0.1):
        rat = fit_camera(target, camera.image_size, rays[ok], grid[ok], init=res.camera.param_dict,
                         free=tuple(free) + ("k4", "k5", "k6"), pixel_pitch_um=pitch, name=camera.name)
        if rat.success and rat.max_residual_px < 0.5 * res.max_residual_px:
            p = rat.camera.param_dict
            r2 = np.sum((rays[ok][:, :2] / rays[ok][:, 2:3]) ** 2, axis=1)
            den = 1.0 + r2 * (p["k4"] + r2 * (p["k5"] + r2 * p["k6"]))
            if den.min() > 0.5:
                note = (f"rational k4..k6 kept: max residual {rat.max_residual_px:.3g} px instead of "
                        f"{res.max_residual_px:.3g} px with k1..k3 only")
                res = CameraConversion(rat.camera, rat.max_residual_px, rat.rms_residual_px, rat.n_points,
                                       Outcome(rat.outcome.termination, f"{note}; {rat.outcome.reason}"), rat.free)
    from dataclasses import replace as _replace

    r2max = float(np.max(np.sum((rays[ok][:, :2] / rays[ok][:, 2:3]) ** 2, axis=1))) if ok.any() else 0.0
    if target is CameraModel.OPENCV and res.success:
        def worst_of(r):
            k = radial_kappa(r.camera, r2max)
            return max((abs(v) for n, v in k.items() if n != "k1" and n in r.free), default=0.0)

        r2_all = np.sum((rays[ok][:, :2] / rays[ok][:, 2:3]) ** 2, axis=1)

        def den_ok(r):
            if "k4" not in r.free:
                return True
            p = r.camera.param_dict
            return bool((1.0 + r2_all * (p["k4"] + r2_all * (p["k5"] + r2_all * p["k6"]))).min() > 0.5)

        def bounded(free_set):
            """Smallest ridge (none first) that keeps every scaled radial term <= KAPPA_MAX (and a
            rational denominator > 0.5 over the frame)."""
            r = None
            for ridge in (0.0, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0):
                r = fit_camera(target, camera.image_size, rays[ok], grid[ok], init=init, free=free_set,
                               pixel_pitch_um=pitch, name=camera.name, ridge_px=ridge)
                if r.success and worst_of(r) <= KAPPA_MAX and den_ok(r):
                    return r, ridge
            return r, ridge

        worst = worst_of(res)
        if worst > KAPPA_MAX and auto_free:
            plain = res.max_residual_px
            cands = [bounded(res.free)]
            if "k4" in res.free and camera.model is not CameraModel.OPENCV:
                cands.append(bounded(tuple(k for k in res.free if k not in ("k4", "k5", "k6"))))
            good = []
            for r, ridge in cands:
                if r is None or not r.success or worst_of(r) > KAPPA_MAX or not den_ok(r):
                    continue
                good.append((r.max_residual_px, ridge, r))
            if good:
                _, ridge, best = min(good, key=lambda g: g[0])
                note = (f"plain fit ill-conditioned (cancelling radial terms, |k_i r_max^2i| up to {worst:.3g}, max "
                        f"residual {plain:.3g} px): regularised on k2..k6 (ridge {ridge:g} px, "
                        f"{'k1..k6' if 'k4' in best.free else 'k1..k3'}) to |k_i r_max^2i| <= {worst_of(best):.2f}, "
                        f"max residual {best.max_residual_px:.3g} px")
                res = _replace(best, outcome=Outcome(best.outcome.termination, f"{note}; {best.outcome.reason}"))
            else:
                res = _replace(res, outcome=Outcome(res.outcome.termination,
                                                    f"ill-conditioned fit (|k_i r_max^2i| up to {worst:.3g}) could not be "
                                                    f"bounded; {res.outcome.reason}"))
        kap = radial_kappa(res.camera, r2max)
        res = _replace(res, kappa=kap)
    nbad = int((~ok).sum())
    if nbad:
        reason = f"{res.outcome.reason}; {nbad} of {len(grid)} grid pixels have no ray in the source camera and were left out"
        res = _replace(res, outcome=Outcome(res.outcome.termination, reason))
    if area_px is not None and res.success:
        inside = inside_area(grid[ok], area_px)
        if inside.any():
            d = np.linalg.norm(res.camera.project(rays[ok][inside]) - grid[ok][inside], axis=1)
            res = _replace(res, area_max_residual_px=float(d.max()), area_rms_residual_px=float(np.sqrt(np.mean(d * d))))
    return res


def conversion_covariance(source: Camera, source_cov: np.ndarray, target_project, theta: np.ndarray, *,
                          grid_step_px: float | None = None, rel_step: float = 1e-6) -> np.ndarray:
    """Covariance of converted parameters ``theta`` by linear propagation of the source's covariance.

    The conversion makes ``target_project(theta, rays)`` equal to ``source.project(rays)`` over the
    frame grid in the least-squares sense, so ``dtheta = (J_t^T J_t)^-1 J_t^T J_s dp`` with ``J_t``
    the target's pixel Jacobian (numerical) and ``J_s`` the source's (analytic).

    Parameters
    ----------
    source : Camera
    source_cov : (P, P) covariance of ``source.params`` (its units; NaN rows = fixed, treated as 0).
    target_project : callable ``(theta (T,), rays (N, 3)) -> (N, 2)`` pixels.
    theta : (T,) the converted parameters.

    Returns
    -------
    (T, T) covariance of ``theta``.
    """
    grid = image_grid(source.image_size, grid_step_px)
    rays = source.unproject(grid)
    rays = rays[np.all(np.isfinite(rays), axis=1)]
    kw = {"image_size": source.image_size, "pixel_pitch_um": source.pixel_pitch_um}
    _, _, Js = M.project_jacobian(source.model, source.params, rays, **kw)
    Js = np.nan_to_num(Js.reshape(-1, Js.shape[-1]))
    theta = np.asarray(theta, float)
    base = np.asarray(target_project(theta, rays), float).ravel()
    Jt = np.empty((base.size, theta.size))
    for j in range(theta.size):
        h = rel_step * max(abs(theta[j]), 1e-3)
        t2 = theta.copy()
        t2[j] += h
        Jt[:, j] = (np.asarray(target_project(t2, rays), float).ravel() - base) / h
    A = np.linalg.lstsq(Jt, Js, rcond=None)[0]
    C = np.nan_to_num(np.asarray(source_cov, float))
    cov = A @ C @ A.T
    return 0.5 * (cov + cov.T)
