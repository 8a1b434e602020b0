"""Photometric pose refinement on a surface: the views' poses moved until they agree on the temperatures of the mesh.

A texture takes every texel from one image; where two images' poses put the same wall point at different places of
their images, the texture shows the pose error as a seam and as wrong temperatures next to every edge of the wall's
pattern (window frames, joints, thermal bridges). The survey's tie points fix the poses to ~1 px (their RMS); this
step uses every usable pixel of the images instead: points sampled on the mesh, each seen cleanly by >= 2 images,
and per view the six pose parameters (and an additive offset) that bring its samples to the points' consensus
temperatures (Zhou and Koltun's colour map optimisation [1]_ with the geometry held, for float temperatures):

    minimise  sum_k sum_p rho( I_k(pi_k(X_p)) + o_k - T_p )  +  sum_k |D_k^-1 (xi_k - xi_k0)|^2

over the view parameters ``xi_k = (omega_k, C_k)`` (a rotation about the camera centre, ``R_k = exp([omega_k]x) R_k0``,
and the centre), the offsets ``o_k`` and the points' temperatures ``T_p``, jointly: Levenberg-Marquardt on the
camera system reduced by the Schur complement over the ``T_p`` (their normal block is diagonal; the reduced matrix is
summed from dense 7 x 7 products per pair of views over their shared points). ``rho`` is Huber's loss at 1.345 robust
sigmas (fixed per level), ``D_k`` the survey's σ of the view's rotation and centre (so that directions the images do
not determine stay where the survey put them), and the block's mean centre is held at the start's (a common shift of
every camera along the walls moves every view's samples alike and is nearly invisible to the images; the survey's
GNSS/GCP datum fixes it). ``pi_k`` is the camera model with its distortion; the derivative of a sample with respect to
``xi_k`` is analytic: the image gradient (central differences of the blurred image) times ``d pi / d X_cam`` (the
camera's ``project_point_jacobian``) times ``d X_cam / d xi = [-[X_cam]x, -R]``. Coarse to fine over Gaussian blurs
(``blurs_px`` for the median view, scaled per view by its footprint so that every view blurs the surface by one width:
a blur in pixels smooths near and far views differently and the fit bends the poses to match).

The result is kept only when the images' robust disagreement at the finest level (1.4826 MAD of the samples about
the points' mean values, at the start and at the end) falls by ``min_improvement`` and no view turns by more than
``max_rotation_change_deg``; otherwise nothing changes and the reason says why.

Which samples: visibility by ray casting against the whole mesh with the texture's rules
(:func:`thermogrammetry.products.texture.usable_in_view`, the clean radius covering the start's error), computed
once at the start poses; points seen by fewer than two images do not take part, and views with fewer than
``min_samples`` samples keep their poses (only their offsets are estimated).

The step changes poses only, never a temperature: the texture is then taken from the images as always.

References
----------
.. [1] Zhou Q.-Y., Koltun V. (2014), Color map optimization for 3D reconstruction with consumer depth cameras,
   ACM Transactions on Graphics 33(4), 155.
.. [2] Barazzetti L. et al. (2013), seed 002: thermal textures of building models (the one-image-per-triangle texture
   this step serves).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from .._sampling import bilinear, fill_nearest_valid
from .._validate import config_keys
from ..errors import ConfigError, InvalidInputError
from ..geometry.rotations import axis_angle_from_matrix, matrix_from_axis_angle, skew

__all__ = ["PhotoFitOptions", "PhotoFitResult", "photometric_pose_fit"]


@dataclass(frozen=True)
class PhotoFitOptions:
    """How the poses are refined. Unknown keys in :meth:`from_dict` are errors."""

    #: Gaussian blurs (px, coarse to fine) of the images for the levels; the first should exceed the start's error
    blurs_px: tuple = (2.0, 1.0, 0.5)
    #: Gauss-Newton iterations per level (stops earlier when the largest rotation step is below ``tol_deg``)
    iterations: int = 15
    tol_deg: float = 1e-4
    #: surface samples: spacing as a multiple of the median pixel footprint, at most ``max_points`` (seeded)
    spacing_px: float = 1.5
    max_points: int = 300_000
    #: clean radius (px) of the visibility test: samples within it of a silhouette or fold are left out
    clean_radius_px: int = 3
    max_angle_deg: float = 70.0
    #: views need this many samples (surface points they see cleanly, shared with another view) to be refined
    min_samples: int = 200
    #: σ of the rotation (deg) and centre (m) priors used where a view has none from the survey
    default_rotation_std_deg: float = 1.0
    default_center_std_m: float = 0.1
    #: the refinement is kept only when the images' robust disagreement at the finest level falls by this share
    min_improvement: float = 0.02
    #: the refinement is refused when a view would turn by more than this (a wrong basin, not a pose error)
    max_rotation_change_deg: float = 3.0
    seed: int = 0

    def __post_init__(self):
        b = tuple(float(x) for x in np.atleast_1d(self.blurs_px))
        if not b or not all(np.isfinite(x) and x >= 0 for x in b):
            raise ConfigError(f"PhotoFitOptions.blurs_px={self.blurs_px!r}: expected blurs (px) >= 0, coarse to fine")
        object.__setattr__(self, "blurs_px", b)
        for k in ("iterations", "max_points", "min_samples"):
            if int(getattr(self, k)) < 1:
                raise ConfigError(f"PhotoFitOptions.{k}={getattr(self, k)!r}: expected an integer >= 1")
        for k in ("spacing_px", "default_rotation_std_deg", "default_center_std_m", "tol_deg", "max_rotation_change_deg"):
            if not (np.isfinite(getattr(self, k)) and getattr(self, k) > 0):
                raise ConfigError(f"PhotoFitOptions.{k}={getattr(self, k)!r}: expected a positive number")
        if not 0 <= self.min_improvement < 1:
            raise ConfigError(f"PhotoFitOptions.min_improvement={self.min_improvement!r}: expected a share in [0, 1)")
        if not 0 < self.max_angle_deg < 90:
            raise ConfigError(f"PhotoFitOptions.max_angle_deg={self.max_angle_deg!r}: expected degrees in (0, 90)")
        if int(self.clean_radius_px) < 0:
            raise ConfigError(f"PhotoFitOptions.clean_radius_px={self.clean_radius_px!r}: expected an integer >= 0")

    @classmethod
    def from_dict(cls, d: dict) -> "PhotoFitOptions":
        return cls(**config_keys(cls, d))


@dataclass
class PhotoFitResult:
    """Outcome of :func:`photometric_pose_fit`.

    ``applied`` False with ``reason`` when nothing was changed (the views keep their poses); ``views`` the views with
    the refined poses (or the input ones); ``offsets`` (K,) the per-view additive offsets estimated alongside (NOT
    applied to any temperature: the texture stays as the images give it); ``figures``: samples, points, the robust
    disagreement (1.4826 MAD) before/after and per level, per-view rotation and centre changes, seconds."""

    applied: bool
    reason: str
    views: list
    offsets: np.ndarray
    figures: dict = field(default_factory=dict)


def _surface_samples(V, F, area, spacing_m: float, max_points: int, seed: int):
    """Area-weighted (``area`` (F,) m²), seeded points on the faces: (points (N, 3), face (N,))."""
    a = area
    total = float(a.sum())
    n = int(min(max_points, max(1, total / spacing_m**2)))
    rng = np.random.default_rng(seed)
    fi = rng.choice(len(F), size=n, p=a / total)
    u = rng.random((n, 2))
    flip = u.sum(axis=1) > 1
    u[flip] = 1 - u[flip]
    v0 = V[F[fi, 0]]
    X = v0 + u[:, :1] * (V[F[fi, 1]] - v0) + u[:, 1:] * (V[F[fi, 2]] - v0)
    return X, fi


def _blurred_with_gradient(img, blur_px: float):
    """(image, d/dx, d/dy) float32 of the blurred image (NaN pixels: filled by the nearest valid value first, so that
    a NaN border does not spread; samples there are masked by the caller through visibility)."""
    import cv2

    a = np.asarray(img, np.float32)
    valid = np.isfinite(a)
    if not valid.all():
        a = fill_nearest_valid(a, valid)
    if blur_px > 0:
        a = cv2.GaussianBlur(a, (0, 0), sigmaX=blur_px, sigmaY=blur_px, borderType=cv2.BORDER_REPLICATE)
    gx = cv2.Sobel(a, cv2.CV_32F, 1, 0, ksize=1, borderType=cv2.BORDER_REPLICATE) * 0.5
    gy = cv2.Sobel(a, cv2.CV_32F, 0, 1, ksize=1, borderType=cv2.BORDER_REPLICATE) * 0.5
    return a, gx, gy


#: Huber's tuning constant (robust sigmas): 95 % efficiency for Gaussian residuals
HUBER_K = 1.345


def _huber_w(r, s):
    c = HUBER_K * s
    a = np.abs(r)
    return np.where(a <= c, 1.0, c / np.maximum(a, 1e-300))


def photometric_pose_fit(vertices, faces, views: Sequence, *, rotation_std_deg=None, center_std_m=None,
                         options: PhotoFitOptions | None = None, progress=None) -> PhotoFitResult:
    """Refine the poses of ``views`` so that they agree on the temperatures of the mesh (module docstring).

    Parameters
    ----------
    vertices : (V, 3) metres, faces : (F, 3), the mesh in the views' frame
    views : K :class:`thermogrammetry.products.texture.TextureView` (camera, ``cam_from_world`` pose, image)
    rotation_std_deg : optional (K,) or (K, 3) σ of each view's rotation (deg; the largest axis is used), NaN = unknown
    center_std_m : optional (K,) or (K, 3) σ of each view's centre (m; per axis when (K, 3)), NaN = unknown
    options : :class:`PhotoFitOptions`

    Returns
    -------
    :class:`PhotoFitResult`
    """
    from ..geometry import Pose
    from .texture_config import TextureConfig
    from .texture_mesh import check_mesh, face_geometry, local_origin, plane_ids, view_in_frame
    from .texture_visibility import pixel_surfaces, ray_intersector, usable_in_view

    opt = options or PhotoFitOptions()
    t_start = time.perf_counter()
    V_in, F = check_mesh(vertices, faces)
    views = list(views)
    K = len(views)
    if K < 2:
        return PhotoFitResult(False, f"{K} view(s): at least 2 are needed", views, np.zeros(K))
    origin = local_origin(V_in)
    V = V_in - origin
    lv = [view_in_frame(v, origin) for v in views]

    def _per_view(a, default, name):
        if a is None:
            return np.full((K, 3), default)
        a = np.asarray(a, float)
        if a.shape == (K,):
            a = np.repeat(a[:, None], 3, axis=1)
        if a.shape != (K, 3):
            raise InvalidInputError(f"photometric_pose_fit: {name} of shape {a.shape}; expected ({K},) or ({K}, 3)")
        return np.where(np.isfinite(a) & (a > 0), a, default)

    rot_sd = np.deg2rad(_per_view(rotation_std_deg, opt.default_rotation_std_deg, "rotation_std_deg").max(axis=1))
    cen_sd = _per_view(center_std_m, opt.default_center_std_m, "center_std_m")

    # samples on the surface, spaced by the median pixel footprint
    foot = []
    _, area, cen = face_geometry(V, F)
    for v in lv:
        f = 0.5 * (v.camera.K[0, 0] + v.camera.K[1, 1])
        d = np.linalg.norm(cen - v.pose.center, axis=1)
        foot.append(np.median(d) / f)
    X, fi = _surface_samples(V, F, area, opt.spacing_px * float(np.median(foot)), opt.max_points, opt.seed)
    inter = ray_intersector(V, F)
    planes = plane_ids(V, F)
    cfg = TextureConfig(texel_size_m=1.0, clean_radius_px=int(opt.clean_radius_px), max_angle_deg=opt.max_angle_deg)
    vis_idx = []
    for k, v in enumerate(lv):
        surf = pixel_surfaces(inter, V, F, v, planes)
        ok, *_ = usable_in_view(inter, V, F, v, surf, X, fi, cfg)
        vis_idx.append(np.flatnonzero(ok))
        del surf
        if progress is not None:
            progress(k + 1, K)
    count = np.zeros(len(X), np.int64)
    for idx in vis_idx:
        count[idx] += 1
    shared = count >= 2
    vis_idx = [idx[shared[idx]] for idx in vis_idx]
    keep = np.flatnonzero(shared)
    if len(keep) == 0:
        return PhotoFitResult(False, "no surface point is seen cleanly by two images", views, np.zeros(K),
                              {"points": 0, "seconds": round(time.perf_counter() - t_start, 2)})
    remap = np.full(len(X), -1, np.int64)
    remap[keep] = np.arange(len(keep))
    Xs = X[keep]
    vis_idx = [remap[idx] for idx in vis_idx]
    P = len(Xs)

    R0 = [v.pose.R.copy() for v in lv]
    C0 = [v.pose.center.copy() for v in lv]
    n_vis = np.array([len(i) for i in vis_idx])
    active = n_vis >= opt.min_samples
    if active.sum() == 0:
        return PhotoFitResult(False, f"no view sees {opt.min_samples} shared surface points cleanly (most: {n_vis.max()})",
                              views, np.zeros(K), {"points": int(P), "seconds": round(time.perf_counter() - t_start, 2)})
    state = _State([r.copy() for r in R0], [c.copy() for c in C0], np.zeros(K), None)
    prior = _Prior(R0, C0, rot_sd, cen_sd)
    # one blur on the surface for every view: a view twice as far blurs half as many pixels (a blur in pixels
    # smooths the surface by different widths in different views, which the fit would then bend the poses to match)
    vfoot = np.array([np.median(np.linalg.norm(Xs[i] - C0[k], axis=1)) / (0.5 * (lv[k].camera.K[0, 0] + lv[k].camera.K[1, 1]))
                      if len(i) else np.nan for k, i in enumerate(vis_idx)])
    blur_scale = np.clip(np.nanmedian(vfoot) / np.where(np.isfinite(vfoot), vfoot, np.nanmedian(vfoot)), 1 / 3, 3)
    pairs = _view_pairs(vis_idx, P)
    levels = []
    for blur in opt.blurs_px:
        imgs = [_blurred_with_gradient(v.image_k, blur * blur_scale[k]) for k, v in enumerate(lv)]
        prob = _Problem(lv, imgs, Xs, vis_idx, active, prior, pairs)
        samples = prob.sample(state)
        if state.T is None:
            state.T = prob.point_means(samples)
        s = prob.robust_sigma(samples, state.T)
        cost = prob.cost(samples, state, s)
        lam = 1e-3
        hist = [s]
        it = 0
        for it in range(1, opt.iterations + 1):
            step = prob.solve(samples, state, s, lam)
            if step is None:
                break
            trial = prob.apply(state, step)
            t_samples = prob.sample(trial)
            t_cost = prob.cost(t_samples, trial, s)
            if t_cost < cost:
                state, samples, cost = trial, t_samples, t_cost
                lam = max(lam / 3, 1e-7)
                hist.append(prob.robust_sigma(samples, state.T))
                if float(np.degrees(np.abs(step[0]).max())) < opt.tol_deg:
                    break
            else:
                lam *= 4
                if lam > 1e6:
                    break
        levels.append({"blur_px": blur, "robust_sigma": [round(float(x), 5) for x in hist], "iterations": it,
                       "cost": round(float(cost), 6)})
    R, C, off = state.R, state.C, state.offsets
    # the disagreement at the finest level, before and after, each with the points' robust mean temperatures
    s0 = prob.sample(_State(R0, C0, np.zeros(K), None))
    s_before = prob.robust_sigma(s0, prob.point_means(s0))
    fin = prob.sample(state)
    s_after = prob.robust_sigma(fin, prob.point_means(fin))
    out = []
    rot_change, cen_change = [], []
    for k, v in enumerate(views):
        t = -R[k] @ (C[k] + origin)
        out.append(replace(v, pose=Pose(R[k], t)))
        rot_change.append(float(np.degrees(np.linalg.norm(axis_angle_from_matrix(R[k] @ R0[k].T)))))
        cen_change.append(float(np.linalg.norm(C[k] - C0[k])))
    rc, cc = np.array(rot_change), np.array(cen_change)
    figures = {"points": int(P), "samples": int(sum(len(i) for i in vis_idx)), "views": K,
               "views_refined": int(active.sum()), "robust_sigma_before": round(float(s_before), 6),
               "robust_sigma_after": round(float(s_after), 6), "levels": levels,
               "rotation_change_deg": {"median": round(float(np.median(rc)), 4), "max": round(float(rc.max()), 4)},
               "center_change_m": {"median": round(float(np.median(cc)), 4), "max": round(float(cc.max()), 4)},
               "per_view": [{"image": v.name, "rotation_change_deg": round(a, 4), "center_change_m": round(b, 4),
                             "offset": round(float(o), 5)} for v, a, b, o in zip(views, rot_change, cen_change, off)],
               "seconds": round(time.perf_counter() - t_start, 2)}
    if not s_after < (1 - opt.min_improvement) * s_before:
        return PhotoFitResult(False, f"the images did not come to agree better (robust disagreement {s_before:.4g} -> "
                              f"{s_after:.4g} at the finest level; a fall of at least {100 * opt.min_improvement:g} % is "
                              "asked before poses are changed)", views, np.zeros(K), figures)
    if rc.max() > opt.max_rotation_change_deg:
        k = int(np.argmax(rc))
        return PhotoFitResult(False, f"image {views[k].name!r} would turn by {rc[k]:.2f} deg (more than "
                              f"max_rotation_change_deg = {opt.max_rotation_change_deg:g}): a wrong match of the images "
                              "to the mesh is more likely than such a pose error", views, np.zeros(K), figures)
    return PhotoFitResult(True, "", out, off, figures)


@dataclass
class _State:
    """Current estimate: rotations, centres (local frame), offsets (K,), point temperatures (P,)."""

    R: list
    C: list
    offsets: np.ndarray
    T: np.ndarray | None


@dataclass
class _Prior:
    R0: list
    C0: list
    rot_sd: np.ndarray  # (K,) rad
    cen_sd: np.ndarray  # (K, 3) m


class _Problem:
    """One blur level: samples, robust cost and the Schur-reduced Gauss-Newton step over (views, point temperatures).

    Per sample (point p in view k): ``r = I_k(pi_k(X_p)) + o_k - T_p``; view parameters ``(omega, C, o)`` (7 per
    view), point temperatures eliminated (their normal block is diagonal)."""

    def __init__(self, views, imgs, X, vis_idx, active, prior: _Prior, pairs):
        self.views, self.imgs, self.X, self.vis, self.active, self.prior = views, imgs, X, vis_idx, active, prior
        self.K, self.P = len(views), len(X)
        self.pairs = pairs

    def sample(self, st: _State):
        out = []
        for k, v in enumerate(self.views):
            idx = self.vis[k]
            Xc = (self.X[idx] - st.C[k]) @ st.R[k].T
            xy, J = v.camera.project_point_jacobian(Xc)
            w, h = v.camera.image_size
            ok = (Xc[:, 2] > 1e-6) & np.all(np.isfinite(xy), axis=1) & (xy[:, 0] >= 0) & (xy[:, 0] <= w - 1) \
                & (xy[:, 1] >= 0) & (xy[:, 1] <= h - 1)
            val = np.where(ok, bilinear(self.imgs[k][0], np.nan_to_num(xy)).astype(np.float64), np.nan)
            out.append((val, xy, J, Xc, ok))
        return out

    def residuals(self, samples, st: _State):
        return [samples[k][0] + st.offsets[k] - st.T[self.vis[k]] for k in range(self.K)]

    def point_means(self, samples):
        """(P,) the mean of each point's samples (the start of its temperature; NaN for a point no view samples)."""
        s_sum = np.zeros(self.P)
        n = np.zeros(self.P)
        for k in range(self.K):
            val = samples[k][0]
            m = np.isfinite(val)
            s_sum += np.bincount(self.vis[k][m], weights=val[m], minlength=self.P)
            n += np.bincount(self.vis[k][m], minlength=self.P)
        with np.errstate(invalid="ignore", divide="ignore"):
            return s_sum / n

    def robust_sigma(self, samples, T) -> float:
        r = np.concatenate([samples[k][0] - T[self.vis[k]] for k in range(self.K)])
        r = r[np.isfinite(r)]
        return 1.4826 * float(np.median(np.abs(r - np.median(r)))) + 1e-12 if len(r) else 1.0

    def _prior_terms(self, st: _State, s: float):
        """The priors towards the start, in units of the samples' robust σ ``s``: per view the weights (K, 6) and the
        deviations (K, 6) of (rotation vector of ``R R0^T``, centre); and the block's mean-centre term: the active
        views, its weights (3,) and the summed centre deviation (3,) (stiff: 1e-3 of the views' mean centre σ)."""
        pr = self.prior
        w = np.empty((self.K, 6))
        d = np.empty((self.K, 6))
        for k in range(self.K):
            w[k, :3] = (s / pr.rot_sd[k]) ** 2
            w[k, 3:] = (s / pr.cen_sd[k]) ** 2
            d[k, :3] = axis_angle_from_matrix(st.R[k] @ pr.R0[k].T)
            d[k, 3:] = st.C[k] - pr.C0[k]
        act = np.flatnonzero(self.active)
        wm = (s / (1e-3 * np.mean(pr.cen_sd[act], axis=0))) ** 2 / len(act) ** 2 if len(act) else np.zeros(3)
        dmean = sum((st.C[k] - pr.C0[k] for k in act), np.zeros(3))
        return w, d, act, wm, dmean

    def cost(self, samples, st: _State, s: float) -> float:
        c = HUBER_K * s
        tot = 0.0
        for r in self.residuals(samples, st):
            a = np.abs(r[np.isfinite(r)])
            tot += float(np.sum(np.where(a <= c, 0.5 * a * a, c * a - 0.5 * c * c)))
        w, d, _, wm, dmean = self._prior_terms(st, s)
        tot += 0.5 * float(np.sum(wm * dmean**2))
        return tot + 0.5 * float(np.sum(w * d**2)) + 0.5 * float(np.sum((1e-3 * st.offsets) ** 2))

    def solve(self, samples, st: _State, s: float, lam: float):
        """LM step ``(d_omega (K, 3), d_C (K, 3), d_offsets (K,), d_T (P,))`` or None."""
        K, P = self.K, self.P
        Hvv = np.zeros((7 * K, 7 * K))
        bv = np.zeros(7 * K)
        Wp = np.zeros(P)
        bp = np.zeros(P)
        hv = [None] * K  # per view: (n_k, 7) the column blocks of H_vp, -w A (zero rows for unusable samples)
        res = self.residuals(samples, st)
        for k, v in enumerate(self.views):
            val, xy, J, Xc, ok = samples[k]
            r = res[k]
            m = ok & np.isfinite(r)
            if not m.any():
                continue
            idx = self.vis[k][m]
            w = _huber_w(r[m], s)
            if self.active[k]:
                g = np.stack([bilinear(self.imgs[k][1], xy[m]), bilinear(self.imgs[k][2], xy[m])], axis=1).astype(np.float64)
                Jg = np.einsum("ni,nij->nj", g, J[m])  # d value / d X_cam
                A = np.column_stack([-np.einsum("nj,njk->nk", Jg, skew(Xc[m])),  # d X_cam / d omega = -[X_cam]x
                                     -Jg @ st.R[k],  # d X_cam / d C = -R
                                     np.ones(len(idx))])
            else:  # only the offset
                A = np.zeros((len(idx), 7))
                A[:, 6] = 1.0
            sl = slice(7 * k, 7 * k + 7)
            Hvv[sl, sl] += A.T @ (A * w[:, None])
            bv[sl] -= A.T @ (w * r[m])
            Wp += np.bincount(idx, weights=w, minlength=P)
            bp += np.bincount(idx, weights=w * r[m], minlength=P)
            h = np.zeros((len(self.vis[k]), 7))
            h[m] = -(A * w[:, None])
            hv[k] = h
        pw, pd, act, wm, dmean = self._prior_terms(st, s)
        for k in range(K):
            sl = 7 * k
            Hvv[sl:sl + 6, sl:sl + 6] += np.diag(pw[k])
            bv[sl:sl + 6] -= pw[k] * pd[k]
            Hvv[sl + 6, sl + 6] += 1e-6
            bv[sl + 6] -= 1e-6 * st.offsets[k]
            if not self.active[k]:
                Hvv[sl:sl + 6, sl:sl + 6] += np.eye(6) * 1e12  # held
        # the block's mean centre stays where the start put it (the photometric cost hardly sees a common shift of
        # every camera along the walls: coarse levels drift there; the survey's GNSS/GCP datum fixes it)
        if len(act):
            ci = (7 * act[:, None] + 3 + np.arange(3)[None, :])  # (n, 3) centre columns
            for a in range(3):
                Hvv[np.ix_(ci[:, a], ci[:, a])] += wm[a]
                bv[ci[:, a]] -= wm[a] * dmean[a]
        seen = Wp > 0
        Wp_d = np.where(seen, Wp, 1.0) * (1 + lam)
        # reduced camera system: H_vv - sum_p h_p h_p^T / W_p, by view pairs over their shared points (dense 7 x 7
        # products; the sum over a point's pairs is what a sparse U^T U would do, at BLAS speed)
        inv_sqrt = 1.0 / np.sqrt(Wp_d)
        u = [None if hv[k] is None else hv[k] * inv_sqrt[self.vis[k], None] for k in range(K)]
        Hred = Hvv + lam * np.diag(np.diag(Hvv))
        bred = bv.copy()
        g = bp * inv_sqrt
        for k in range(K):
            if u[k] is not None:
                bred[7 * k:7 * k + 7] -= u[k].T @ g[self.vis[k]]
        for k, l, ik, il in self.pairs:
            if u[k] is None or u[l] is None:
                continue
            blk = u[k][ik].T @ u[l][il]
            Hred[7 * k:7 * k + 7, 7 * l:7 * l + 7] -= blk
            if k != l:
                Hred[7 * l:7 * l + 7, 7 * k:7 * k + 7] -= blk.T
        try:
            dv = np.linalg.solve(Hred, bred)
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(dv)):
            return None
        hdv = np.zeros(P)
        for k in range(K):
            if hv[k] is not None:
                hdv += np.bincount(self.vis[k], weights=hv[k] @ dv[7 * k:7 * k + 7], minlength=P)
        dT = np.where(seen, (bp - hdv) / Wp_d, 0.0)
        dv = dv.reshape(K, 7)
        return dv[:, :3], dv[:, 3:6], dv[:, 6], dT

    def apply(self, st: _State, step) -> _State:
        dw, dc, do, dT = step
        R = [matrix_from_axis_angle(dw[k]) @ st.R[k] for k in range(self.K)]
        C = [st.C[k] + dc[k] for k in range(self.K)]
        return _State(R, C, st.offsets + do, st.T + dT)


def _view_pairs(vis_idx, n_points: int) -> list:
    """``(k, l, ik, il)`` for every pair of views (k <= l) that share points: the positions of the shared points in
    each view's sorted index list (pairs found from the co-occurrence counts, so that K^2 intersections are not run)."""
    from scipy import sparse

    K = len(vis_idx)
    rows = np.concatenate(vis_idx)
    cols = np.concatenate([np.full(len(i), k) for k, i in enumerate(vis_idx)])
    M = sparse.csr_matrix((np.ones(len(rows), np.float32), (rows, cols)), shape=(n_points, K))
    co = (M.T @ M).tocoo()
    out = []
    for k, l in sorted(zip(co.row.tolist(), co.col.tolist())):
        if k > l:
            continue
        if k == l:
            a = np.arange(len(vis_idx[k]))
            out.append((k, k, a, a))
        else:
            _, ik, il = np.intersect1d(vis_idx[k], vis_idx[l], assume_unique=True, return_indices=True)
            out.append((k, l, ik, il))
    return out
