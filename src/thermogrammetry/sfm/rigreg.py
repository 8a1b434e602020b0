"""The relative orientation of an RGB + thermal rig from image registration (seed 002 §2.3, eq. 4-5).

Where the thermal frames of a rig have too few features of their own to be tied (low-texture walls, the
frescoes of ``shared/data/rgb_thermal_frescoes``), ``R*, t`` cannot be estimated in the block from tie
points (:mod:`thermogrammetry.sfm.rig`), yet both sensors see the same *edges*: a floor line, a room
corner, survey poles, targets on a wall. This module estimates ``cam_thermal_from_cam_rgb`` = (R, t) and a
focal-length scale of the thermal camera by maximising the agreement of those edges over all pairs at
once, with the RGB images already oriented:

* each RGB image's oriented sparse points give its depth (inverse depth interpolated linearly between
  them over the image, the nearest point's outside their hull), so that a sample at RGB pixel ``u`` with
  depth ``Z`` is the camera-frame point ``X = Z * ray(u)`` (distortion included);
* the *structure image* of both sensors is the gradient magnitude of the percentile-stretched image after
  a Gaussian blur of ``blur_px`` thermal pixels; the RGB image is first reduced to the thermal camera's
  angular resolution (INTER_AREA, factor ``f_thermal / f_rgb``);
* a thermal sample is the thermal structure image at ``u_t = c + s (pi_T(R X + t) - c)`` (``pi_T`` the
  thermal camera, ``c`` its principal point, ``s`` the focal scale), bilinear;
* the score of a pair is the normalised cross-correlation (NCC) of the RGB and thermal structure samples
  (their sign and contrast differ between the bands, their *position* does not), the objective the mean
  NCC over the pairs.

The search: a grid over the rig's pan and tilt (``grid_deg``, coarse blur) from the start, then
Nelder-Mead over rotation, the translation across the optical axis (as a fraction of the median scene depth;
along the axis it is held: its magnification traded freely with the focal scale) and the focal scale at each
blur of ``blur_px``. Then every pair alone (rotation only, t and s held): the rotation of each pair about
the joint one gives the spread of the estimate (1.4826 x median angle) and its σ (spread / sqrt(n) per
axis). When t is free, its σ and the focal scale's come from a delete-group jackknife over the used pairs
(``JACKKNIFE_GROUPS`` folds, each the joint fit at the finest blur without one group of pairs). The estimate
is refused -- a result with its reason, never a guess -- when fewer than ``min_pairs`` pairs show structure in
common (their NCC at the joint solution below ``min_ncc``), when the spread exceeds ``max_spread_deg`` or when
the solution lies on the border of the grid.

What it does not do: the translation comes from the parallax between near and far pairs; a block at one
depth (inverse depths within 30 % of each other) leaves it tied to the rotation: t is then held at its start
(``t_determined`` False) and R absorbs the parallax (0.11 deg for a 0.1 m base at 50 m in tests/test_rigreg.py).
With pairs 6-51 m deep (tests/test_rigreg.py, a 0.1 m base) t across the axis came out 3.4 / 1.0 mm (seed 0) and
19 / 2.7 mm (seed 3) from the truth, within 1.1 σ; in seed 1 the fit settles in the valley where the base trades
against the rotation about the other axis (t 0.10 m off, 0.26 deg): the jackknife σ (0.034 m, 3.1 σ) says the
estimate is weak there, the curvature of the objective at the solution did not (a sandwich covariance: 0.011 m).
Thermal distortion is held at the start camera's; the registration runs on the structure, not on the
temperatures, so raw counts do as well as kelvin.

Measured: the synthetic rig block of ``tests/rig_block.py`` (t given), rotation within 0.05 deg and focal scale
within 0.1 % of the truth; the real frescoes (``shared/data/rgb_thermal_frescoes``, 40 Workswell pairs), 33 of 40
pairs agree, R* 0.95 deg, per-pair spread 0.42 deg, σ 0.03 / 0.02 / 0.05 deg, two starts 1.2 deg apart end within
0.06 deg of each other, ~140 s on two cores.

References
----------
Barazzetti, L., Brumana, R., Oreni, D., Previtali, M., Roncoroni, F. (2013). Mosaicking thermal images of
buildings. Proc. SPIE 8783 (seed 002, §2.3: the bi-camera rig).
Lewis, J. P. (1995). Fast normalized cross-correlation. Vision Interface.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._sampling import bilinear
from ..errors import ConfigError
from ..geometry.rotations import axis_angle_from_matrix, matrix_from_axis_angle
from ..results import HasOutcome, Outcome, Termination

__all__ = ["RigRegistrationOptions", "RigPairSamples", "RigRegistration", "structure_image", "pair_samples",
           "register_rig"]


@dataclass(frozen=True)
class RigRegistrationOptions:
    """How the rig is registered (see the module docstring).

    Attributes
    ----------
    blur_px : tuple of float
        Gaussian blur of the structure images, in thermal pixels, coarse to fine.
    grid_deg : float
        Half-width of the pan/tilt grid searched around the start (degrees); step ``grid_step_deg``.
    samples_per_pair : int
        RGB samples per pair (a seeded random subset of the RGB pixels at the thermal resolution).
    estimate_translation, estimate_focal : bool
        Whether t and the thermal focal scale are estimated (else held at the start / 1).
    max_pairs : int
        At most this many pairs are registered (callers pick them evenly over the block: the cost grows with
        pairs x samples x ~4000 evaluations, ~140 s for 40 pairs).
    min_pairs : int
        Pairs with structure in common needed for an estimate.
    min_ncc : float
        A pair shows structure in common when its NCC at the joint solution reaches this.
    max_spread_deg : float
        Largest accepted spread of the per-pair rotations about the joint one.
    seed : int
        Seed of the sample subset.
    """

    blur_px: tuple = (3.0, 1.5)
    grid_deg: float = 4.0
    grid_step_deg: float = 0.5
    samples_per_pair: int = 20000
    estimate_translation: bool = True
    estimate_focal: bool = True
    max_pairs: int = 40
    min_pairs: int = 3
    min_ncc: float = 0.05
    max_spread_deg: float = 0.5
    seed: int = 0

    def __post_init__(self):
        if not self.blur_px or any(not (float(b) > 0) for b in self.blur_px):
            raise ConfigError(f"RigRegistrationOptions.blur_px: got {self.blur_px!r}, expected positive pixel values")
        for k in ("grid_deg", "grid_step_deg", "max_spread_deg"):
            if not (float(getattr(self, k)) > 0):
                raise ConfigError(f"RigRegistrationOptions.{k}: got {getattr(self, k)!r}, expected > 0")
        if int(self.samples_per_pair) < 100 or int(self.min_pairs) < 1 or int(self.max_pairs) < int(self.min_pairs):
            raise ConfigError(f"RigRegistrationOptions: samples_per_pair {self.samples_per_pair!r} (>= 100) / "
                              f"min_pairs {self.min_pairs!r} (>= 1) / max_pairs {self.max_pairs!r} (>= min_pairs)")


@dataclass
class RigPairSamples:
    """One RGB/thermal pair prepared for registration.

    Attributes
    ----------
    name : str
        The pair's name (the RGB image's).
    points_cam : (N, 3) float
        Sample points in the RGB camera frame (model units).
    rgb_structure : dict blur -> (N,) float32
        RGB structure value at each sample per blur.
    thermal_structure : dict blur -> (H, W) float32
        The thermal structure image per blur.
    depth_median : float
        Median sample depth (model units).
    """

    name: str
    points_cam: np.ndarray
    rgb_structure: dict
    thermal_structure: dict
    depth_median: float


@dataclass
class RigRegistration(HasOutcome):
    """Result of :func:`register_rig` (``success`` False with the reason when refused).

    Attributes
    ----------
    R, t : (3, 3), (3,)
        ``cam_thermal_from_cam_rgb`` (t in the model units of ``points_cam``).
    focal_scale : float
        Factor applied to the thermal camera's focal length (about its principal point).
    rotation_std_deg : (3,)
        σ of R per axis (the per-pair spread / sqrt(n)).
    spread_deg : float
        1.4826 x median angle of the per-pair rotations about the joint one.
    ncc : dict name -> float
        Each pair's NCC at the joint solution (finest blur).
    pair_offsets_deg : dict name -> float
        Angle of each used pair's own rotation from the joint one.
    pairs_used : list of str
    t_determined : bool
        False when the pairs' depths are too uniform to separate t from R (t held at the start).
    translation_std : (3,)
        σ of t (model units) from a delete-group jackknife over the used pairs; NaN for a component held (along the
        optical axis always; all three when ``t_determined`` is False).
    focal_scale_std : float
        σ of ``focal_scale`` from the same jackknife (NaN when the scale is held or t is not determined: no
        jackknife runs then).
    evaluations : int
    """

    outcome: Outcome
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    focal_scale: float = 1.0
    rotation_std_deg: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    spread_deg: float = float("nan")
    ncc: dict = field(default_factory=dict)
    pair_offsets_deg: dict = field(default_factory=dict)
    pairs_used: list = field(default_factory=list)
    t_determined: bool = False
    translation_std: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    focal_scale_std: float = float("nan")
    evaluations: int = 0
    n_pairs: int = 0

    def summary(self) -> dict:
        """JSON-ready figures."""
        return {"success": bool(self.success), "reason": self.reason, "R": np.asarray(self.R).tolist(),
                "t": np.asarray(self.t).tolist(), "focal_scale": float(self.focal_scale),
                "rotation_std_deg": [float(x) for x in self.rotation_std_deg], "spread_deg": float(self.spread_deg),
                "pairs_used": len(self.pairs_used), "pairs": int(self.n_pairs), "t_determined": bool(self.t_determined),
                "translation_std": [None if not np.isfinite(x) else float(x) for x in self.translation_std],
                "focal_scale_std": None if not np.isfinite(self.focal_scale_std) else float(self.focal_scale_std),
                "ncc_median": float(np.median(list(self.ncc.values()))) if self.ncc else None,
                "evaluations": int(self.evaluations)}


# ------------------------------------------------------------------------------------------------
def _gray(arr) -> np.ndarray:
    a = np.asarray(arr)
    if a.ndim == 3:
        a = a[..., :3].astype(np.float32).mean(axis=2)
    if a.ndim != 2:
        raise ConfigError(f"structure_image: got an array of shape {np.shape(arr)}, expected (H, W) or (H, W, C)")
    return a.astype(np.float32)


def _stretch(a: np.ndarray) -> np.ndarray:
    fin = np.isfinite(a)
    if not fin.any():
        return np.zeros(a.shape, np.float32)
    lo, hi = np.percentile(a[fin], [0.5, 99.5])
    out = np.where(fin, a, lo)
    return np.clip((out - lo) / max(float(hi - lo), 1e-12), 0.0, 1.0).astype(np.float32)


def structure_image(arr, blur_px: float) -> np.ndarray:
    """Gradient magnitude (H, W) float32 of the percentile-stretched (0.5-99.5 %) grey image after a Gaussian
    blur of ``blur_px`` pixels (colour images: the mean of the channels)."""
    import cv2

    a = cv2.GaussianBlur(_stretch(_gray(arr)), (0, 0), float(blur_px))
    gx = cv2.Sobel(a, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(a, cv2.CV_32F, 0, 1, ksize=3)
    return np.sqrt(gx * gx + gy * gy)


def _focal(camera) -> float:
    K = camera.K
    return float(np.sqrt(K[0, 0] * K[1, 1]))


def pair_samples(name: str, rgb, thermal, rgb_camera, thermal_camera, points_cam, *,
                 options: RigRegistrationOptions | None = None) -> tuple[RigPairSamples | None, str]:
    """Prepare one pair: samples of the RGB image with their depth, structure images of both.

    Parameters
    ----------
    rgb : (H, W[, 3]) array
        The RGB image (any dtype).
    thermal : (h, w) array
        The thermal frame (counts or kelvin; only its structure is used).
    rgb_camera, thermal_camera : Camera
    points_cam : (M, 3) float
        The RGB image's oriented sparse points in its camera frame (model units).

    Returns
    -------
    (RigPairSamples or None, reason) -- None with the reason when the pair cannot be used.
    """
    import cv2
    from scipy.interpolate import LinearNDInterpolator
    from scipy.spatial import cKDTree

    opt = options or RigRegistrationOptions()
    P = np.asarray(points_cam, float).reshape(-1, 3)
    P = P[np.isfinite(P).all(axis=1) & (P[:, 2] > 0)]
    W, H = rgb_camera.image_size
    if len(P) < 8:
        return None, f"{name}: {len(P)} oriented point(s) in front of the RGB camera (at least 8 give its depth)"
    uv = rgb_camera.project(P)
    inside = np.isfinite(uv).all(axis=1) & (uv[:, 0] > -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < H - 0.5)
    P, uv = P[inside], uv[inside]
    if len(P) < 8:
        return None, f"{name}: {len(P)} oriented point(s) inside the RGB image (at least 8 give its depth)"
    ratio = _focal(thermal_camera) / _focal(rgb_camera)  # thermal pixels per RGB pixel
    gray = _gray(rgb)
    if gray.shape != (H, W):
        return None, f"{name}: RGB image of {gray.shape[1]}x{gray.shape[0]} px, its camera says {W}x{H}"
    w_s, h_s = max(8, int(round(W * ratio))), max(8, int(round(H * ratio)))
    small = cv2.resize(gray, (w_s, h_s), interpolation=cv2.INTER_AREA) if ratio < 1 else gray
    sx, sy = W / small.shape[1], H / small.shape[0]
    rng = np.random.default_rng([int(opt.seed), small.shape[0], small.shape[1]])
    n = min(int(opt.samples_per_pair), small.size)
    idx = np.sort(rng.choice(small.size, n, replace=False))
    r_s, c_s = np.divmod(idx, small.shape[1])
    u = np.column_stack([(c_s + 0.5) * sx - 0.5, (r_s + 0.5) * sy - 0.5])
    inv = LinearNDInterpolator(uv, 1.0 / P[:, 2])(u) if len(P) >= 3 else np.full(len(u), np.nan)
    miss = ~np.isfinite(inv)
    if miss.any():
        _, j = cKDTree(uv).query(u[miss])
        inv[miss] = 1.0 / P[j, 2]
    rays = rgb_camera.unproject(u)
    X = rays / inv[:, None]
    ok = np.isfinite(X).all(axis=1)
    rgb_st = {}
    th_st = {}
    for b in opt.blur_px:
        s_img = structure_image(small, float(b))
        rgb_st[float(b)] = s_img[r_s[ok], c_s[ok]].astype(np.float32)
        th_st[float(b)] = structure_image(thermal, float(b))
    return RigPairSamples(name, X[ok], rgb_st, th_st, float(np.median(X[ok, 2]))), ""


# ------------------------------------------------------------------------------------------------
class _Objective:
    """Mean NCC over the pairs for a parameter vector (rotation vector deg, t / depth, log focal scale)."""

    def __init__(self, pairs, thermal_camera, blur, depth_ref, stride: int = 1):
        self.pairs = pairs
        self.cam = thermal_camera
        self.blur = float(blur)
        self.depth_ref = depth_ref
        K = thermal_camera.K
        self.c = np.array([K[0, 2], K[1, 2]])
        w, h = thermal_camera.image_size
        self.w, self.h = int(w), int(h)
        self.X = np.concatenate([p.points_cam[::stride] for p in pairs])
        self.g = np.concatenate([p.rgb_structure[self.blur][::stride] for p in pairs]).astype(np.float64)
        self.pid = np.concatenate([np.full(len(p.points_cam[::stride]), k) for k, p in enumerate(pairs)])
        self.stack = np.concatenate([p.thermal_structure[self.blur] for p in pairs]).astype(np.float32)
        self.n = np.bincount(self.pid, minlength=len(pairs)).astype(float)
        self.evaluations = 0

    def per_pair(self, p) -> np.ndarray:
        self.evaluations += 1
        R = matrix_from_axis_angle(np.deg2rad(p[:3]))
        t = np.asarray(p[3:6]) * self.depth_ref
        X, g, pid = self.X, self.g, self.pid
        Xt = X @ R.T + t
        front = Xt[:, 2] > 1e-9
        uv = np.full((len(X), 2), -1e9)
        if front.any():
            uv[front] = self.cam.project(Xt[front])
        uv = self.c + np.exp(p[6]) * (uv - self.c)
        ok = front & np.isfinite(uv).all(axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] <= self.w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= self.h - 1)
        v = bilinear(self.stack, np.column_stack([uv[ok, 0], uv[ok, 1] + pid[ok] * self.h]))
        a, k = g[ok], pid[ok]
        m = len(self.pairs)
        cnt = np.bincount(k, minlength=m).astype(float)
        sa, sb = np.bincount(k, a, m), np.bincount(k, v, m)
        saa, sbb, sab = np.bincount(k, a * a, m), np.bincount(k, v * v, m), np.bincount(k, a * v, m)
        with np.errstate(invalid="ignore", divide="ignore"):
            cov = sab - sa * sb / cnt
            va, vb = saa - sa * sa / cnt, sbb - sb * sb / cnt
            ncc = cov / np.sqrt(va * vb)
        # a pair that sees too little of the thermal frame (< 20 % of its samples) scores nothing
        ncc[~np.isfinite(ncc) | (cnt < 0.2 * np.maximum(self.n, 1))] = 0.0
        return ncc

    def __call__(self, p) -> float:
        return -float(np.mean(self.per_pair(p)))


#: groups of the delete-group jackknife that gives the σ of t and of the focal scale (fewer pairs: one per group)
JACKKNIFE_GROUPS = 6
#: each fold on a subset of about JACKKNIFE_SAMPLES_PER_PAIR samples a pair (every k-th), at most
#: JACKKNIFE_ITERATIONS Nelder-Mead iterations: the folds' spread comes mostly from the pairs left out (all samples
#: and 300 iterations: 520 s of jackknife on the frescoes' 33 pairs of 20 000 samples; 2000 a pair inflated σ of t
#: 4-10x on the 5-50 m test block, 4000 by at most 3x)
JACKKNIFE_SAMPLES_PER_PAIR = 4000
JACKKNIFE_ITERATIONS = 150


def _nelder_mead(f, x0, steps, free, max_iter=600, xatol=1e-3):
    from scipy.optimize import minimize

    free = np.asarray(free, bool)
    x0 = np.asarray(x0, float)

    def g(y):
        x = x0.copy()
        x[free] = y
        return f(x)

    y0 = x0[free]
    simplex = np.vstack([y0] + [y0 + np.eye(len(y0))[i] * np.asarray(steps, float)[free][i] for i in range(len(y0))])
    r = minimize(g, y0, method="Nelder-Mead",
                 options=dict(initial_simplex=simplex, xatol=xatol, fatol=1e-6, maxiter=max_iter, maxfev=2 * max_iter))
    x = x0.copy()
    x[free] = r.x
    return x, r


def register_rig(pairs: list, thermal_camera, *, R0=None, t0=None,
                 options: RigRegistrationOptions | None = None) -> RigRegistration:
    """Estimate ``cam_thermal_from_cam_rgb`` and the thermal focal scale from RGB/thermal pairs.

    Parameters
    ----------
    pairs : list of RigPairSamples
        From :func:`pair_samples` (same options).
    thermal_camera : Camera
        The thermal camera's start (its principal point and distortion are kept).
    R0, t0 : (3, 3), (3,), optional
        Start (default identity, zero).
    options : RigRegistrationOptions

    Returns
    -------
    RigRegistration
    """
    usable = [p for p in pairs if p is not None]
    out = _register_rig(usable, thermal_camera, R0=R0, t0=t0, options=options)
    out.n_pairs = len(usable)
    return out


def _register_rig(pairs: list, thermal_camera, *, R0=None, t0=None,
                  options: RigRegistrationOptions | None = None) -> RigRegistration:
    opt = options or RigRegistrationOptions()
    R0 = np.eye(3) if R0 is None else np.asarray(R0, float)
    t0 = np.zeros(3) if t0 is None else np.asarray(t0, float)
    if len(pairs) < int(opt.min_pairs):
        return RigRegistration(Outcome(Termination.TOO_FEW_OBSERVATIONS,
                                       f"{len(pairs)} usable RGB/thermal pair(s); the registration needs {opt.min_pairs}"))
    depths = np.array([p.depth_median for p in pairs])
    depth_ref = float(np.median(depths))
    # t is separable from R only when the pairs see the scene at different depths (parallax ~ 1/Z)
    inv = 1.0 / depths
    t_free = bool(opt.estimate_translation) and float(np.ptp(inv) / max(np.median(inv), 1e-12)) > 0.3
    x0 = np.concatenate([np.degrees(axis_angle_from_matrix(R0)), t0 / depth_ref, [0.0]])
    blurs = [float(b) for b in opt.blur_px]
    evals = 0
    # 1. pan/tilt grid at the coarsest blur (rotation about the camera's y and x axes), every 4th sample
    coarse = _Objective(pairs, thermal_camera, blurs[0], depth_ref, stride=4)
    steps = np.arange(-opt.grid_deg, opt.grid_deg + 1e-9, opt.grid_step_deg)
    best, best_x = -np.inf, x0
    for dy in steps:
        for dx in steps:
            x = x0.copy()
            x[0] += dx
            x[1] += dy
            s = float(np.mean(coarse.per_pair(x)))
            if s > best:
                best, best_x = s, x
    evals += coarse.evaluations
    if max(abs(best_x[0] - x0[0]), abs(best_x[1] - x0[1])) >= opt.grid_deg - 1e-9:
        return RigRegistration(Outcome(Termination.DEGENERATE,
                                       f"the best pan/tilt lies on the border of the ±{opt.grid_deg:g}° grid "
                                       f"(no edge agreement between the bands inside it)"), evaluations=evals)
    # 2. Nelder-Mead per blur: rotation, t (as a fraction of the median depth), focal scale
    # t along the optical axis is held: its effect (a magnification (Z + tz) / Z) is the focal scale's to within
    # the depth range, and the two traded freely in tests (tz 2.6 cm vs focal +4 %); a rig's lenses sit side by side
    free = np.array([True] * 3 + [t_free, t_free, False] + [bool(opt.estimate_focal)])
    step = np.array([0.5, 0.5, 0.5, 0.01, 0.01, 0.01, 0.01])
    x = best_x
    res = fine = None
    for b in blurs:
        fine = _Objective(pairs, thermal_camera, b, depth_ref)  # the last one is the finest
        x, res = _nelder_mead(fine, x, step, free)
        step = step / 2
        evals += fine.evaluations
    ncc = fine.per_pair(x)
    evals += 1
    names = [p.name for p in pairs]
    good = [k for k in range(len(pairs)) if ncc[k] >= opt.min_ncc]
    # 3. each pair alone (rotation only) about the joint solution: the spread and σ of R
    offsets = {}
    rvecs = []
    for k in good:
        one = _Objective([pairs[k]], thermal_camera, blurs[-1], depth_ref)
        xk, _ = _nelder_mead(one, x, step, [True] * 3 + [False] * 4, max_iter=200)
        evals += one.evaluations
        Rk = matrix_from_axis_angle(np.deg2rad(xk[:3]))
        d = axis_angle_from_matrix(Rk @ matrix_from_axis_angle(np.deg2rad(x[:3])).T)
        rvecs.append(np.degrees(d))
        offsets[names[k]] = float(np.degrees(np.linalg.norm(d)))
    R = matrix_from_axis_angle(np.deg2rad(x[:3]))
    t = x[3:6] * depth_ref
    out = RigRegistration(Outcome(Termination.CONVERGED, ""), R, t, float(np.exp(x[6])),
                          ncc={n: float(v) for n, v in zip(names, ncc)}, pair_offsets_deg=offsets,
                          pairs_used=[names[k] for k in good], t_determined=t_free, evaluations=evals)
    if len(good) < int(opt.min_pairs):
        out.outcome = Outcome(Termination.TOO_FEW_OBSERVATIONS,
                              f"{len(good)} of {len(pairs)} pair(s) show edges in common (NCC >= {opt.min_ncc:g} at the "
                              f"solution); the registration needs {opt.min_pairs}")
        return out
    # 4. t and the focal scale: a delete-group jackknife over the used pairs (each fold the joint fit without one
    # group, from the joint solution, at the finest blur): it also spreads when the joint fit sits in a wrong basin of
    # the valley where a base across the axis trades against a rotation (the sandwich covariance at the solution
    # did not: 0.011 m reported for a t 0.10 m off, see the module docstring)
    if t_free and len(good) >= 3:
        groups = min(len(good), JACKKNIFE_GROUPS)
        stride = max(1, int(np.median([len(pairs[k].points_cam) for k in good])) // JACKKNIFE_SAMPLES_PER_PAIR)
        folds = []
        for g in range(groups):
            obj = _Objective([pairs[k] for i, k in enumerate(good) if i % groups != g], thermal_camera, blurs[-1],
                             depth_ref, stride=stride)
            folds.append(_nelder_mead(obj, x, step, free, max_iter=JACKKNIFE_ITERATIONS, xatol=1e-5)[0])
            evals += obj.evaluations
        xs = np.array(folds)
        sd = np.sqrt((groups - 1) / groups * np.sum((xs - xs.mean(axis=0)) ** 2, axis=0))
        out.translation_std = np.where(free[3:6], sd[3:6] * depth_ref, np.nan)
        out.focal_scale_std = float(sd[6] * np.exp(x[6])) if free[6] else float("nan")
        out.evaluations = evals
    rv = np.array(rvecs)
    med = np.median(rv, axis=0)
    out.spread_deg = float(1.4826 * np.median(np.linalg.norm(rv - med, axis=1)))
    out.rotation_std_deg = 1.4826 * np.median(np.abs(rv - med), axis=0) / np.sqrt(len(rv))
    if not (out.spread_deg <= opt.max_spread_deg):
        out.outcome = Outcome(Termination.DEGENERATE,
                              f"the pairs disagree: their own rotations spread {out.spread_deg:.2f}° about the joint one "
                              f"(accepted up to {opt.max_spread_deg:g}°)")
    elif res is not None and not res.success:
        out.outcome = Outcome(Termination.MAX_ITERATIONS, f"Nelder-Mead stopped: {res.message}")
    return out
