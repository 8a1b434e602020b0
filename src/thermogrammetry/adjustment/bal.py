"""BAL camera model and a fast Levenberg-Marquardt bundle adjuster with the Schur complement.

Camera model (Agarwal et al. 2010; BAL conventions, see :mod:`thermogrammetry.io.bal`)::

    P = R(r) X + t,     p = -P[:2] / P[2],     x = f (1 + k1 |p|^2 + k2 |p|^4) p

Per camera 9 parameters ``rx ry rz tx ty tz f k1 k2``; per point 3.

Solver (:func:`solve_bal`)
--------------------------
Levenberg-Marquardt with the trust-region strategy of Ceres Solver (Agarwal, Mierle et al.):
the step solves ``(J^T J + D / radius) d = -J^T r`` with ``D = clip(diag(J^T J), 1e-6, 1e32)``;
a step is accepted when the gain ratio ``rho > min_relative_decrease`` and the radius then
grows by ``1 / max(1/3, 1 - (2 rho - 1)^3)``; a rejected step divides it by a factor that
doubles on every consecutive rejection (Nielsen 1999).

The linear system is reduced to the cameras by the Schur complement on the 3x3 point blocks
(Triggs et al. 2000, sec. 6.1): ``S = U - W V^-1 W^T``. Observations are stored camera-major, so
camera blocks are contiguous slices (one BLAS product per camera, no copies) and the sums over a
point's observations (``V``, ``g_p``, back-substitution) are one sparse 0/1 matrix product.
``S`` is assembled directly: diagonal blocks per camera, off-diagonal blocks from the pairs of
observations that share a point, grouped by camera pair (one BLAS product per pair, chunks in
worker threads -- numpy and BLAS release the GIL), scattered with one vectorised assignment
per chunk (no ``np.add.at``). ``S`` is small (9 x number of cameras) and solved by dense
Cholesky. BLAS runs single-threaded inside the solve; work buffers are reused across iterations.
Rotations are updated on the manifold, ``R <- exp([dw]x) R``; the result is returned in BAL's
axis-angle form.

Stopping rules (identical names and meaning to Ceres' ``Solver::Options``):

- ``function_tolerance``: ``|cost_old - cost_new| <= function_tolerance * cost_old`` after an
  accepted step;
- ``gradient_tolerance``: ``max |J^T r| <= gradient_tolerance``;
- ``parameter_tolerance``: ``|d| <= parameter_tolerance * (|x| + parameter_tolerance)``;
- ``max_iterations`` (accepted plus rejected steps, as Ceres counts them).

References
----------
Agarwal, S., Snavely, N., Seitz, S. M., Szeliski, R. (2010). Bundle adjustment in the large. ECCV.
Triggs, B., McLauchlan, P., Hartley, R., Fitzgibbon, A. (2000). Bundle adjustment - a modern
synthesis. Vision Algorithms: Theory and Practice, LNCS 1883, 298-372.
Nielsen, H. B. (1999). Damping parameter in Marquardt's method. IMM-REP-1999-05, DTU.
Agarwal, S., Mierle, K. et al. Ceres Solver, "Solving Non-linear Least Squares" (trust region
strategies), http://ceres-solver.org.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from ..results import Termination
from ._so3 import axis_angles, rotation_matrices

__all__ = [
    "BALSolverOptions",
    "BALResult",
    "bal_project",
    "bal_project_jacobian",
    "bal_cost",
    "solve_bal",
    "rotation_matrices",
]


# ----------------------------------------------------------------------------------------------
# camera model
# ----------------------------------------------------------------------------------------------
def bal_project(cameras: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Project points with BAL cameras, one camera per point.

    Parameters
    ----------
    cameras : (M, 9) float64
        ``rx ry rz tx ty tz f k1 k2`` per observation (axis-angle in rad, f in px).
    points : (M, 3) float64

    Returns
    -------
    (M, 2) image coordinates (px, origin at the principal point, y up).
    """
    cameras = np.asarray(cameras, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    R = rotation_matrices(cameras[:, :3])
    P = np.einsum("mij,mj->mi", R, points) + cameras[:, 3:6]
    p = -P[:, :2] / P[:, 2:3]
    n2 = np.sum(p * p, axis=1)
    d = 1.0 + cameras[:, 7] * n2 + cameras[:, 8] * n2 * n2
    return (cameras[:, 6] * d)[:, None] * p


def _proj_jac(Q, t, f, k1, k2, obs, want_jac=True):
    """Residuals and Jacobians from rotated points ``Q = R X`` (M, 3) and per-observation
    camera values. Returns r (M, 2) and, if wanted, A = dr/dP (M, 2, 3) and dr/d(f, k1, k2) (M, 2, 3)."""
    P0 = Q[:, 0] + t[:, 0]
    P1 = Q[:, 1] + t[:, 1]
    P2 = Q[:, 2] + t[:, 2]
    iz = 1.0 / P2
    px = -P0 * iz
    py = -P1 * iz
    n2 = px * px + py * py
    d = 1.0 + n2 * (k1 + k2 * n2)
    fd = f * d
    r = np.empty((Q.shape[0], 2))
    r[:, 0] = fd * px - obs[:, 0]
    r[:, 1] = fd * py - obs[:, 1]
    if not want_jac:
        return r
    e = f * (2.0 * k1 + 4.0 * k2 * n2)
    # B = dr/dp = f (d I + (2 k1 + 4 k2 n2) p p^T);  dp/dP = -(1/z) [[1, 0, px], [0, 1, py]]
    b01 = e * px * py
    b00 = fd + e * px * px
    b11 = fd + e * py * py
    A = np.empty((Q.shape[0], 2, 3))
    A[:, 0, 0] = -iz * b00
    A[:, 0, 1] = -iz * b01
    A[:, 0, 2] = -iz * (b00 * px + b01 * py)
    A[:, 1, 0] = -iz * b01
    A[:, 1, 1] = -iz * b11
    A[:, 1, 2] = -iz * (b01 * px + b11 * py)
    Jk = np.empty((Q.shape[0], 2, 3))
    Jk[:, 0, 0] = d * px
    Jk[:, 1, 0] = d * py
    fn2 = f * n2
    Jk[:, 0, 1] = fn2 * px
    Jk[:, 1, 1] = fn2 * py
    fn4 = fn2 * n2
    Jk[:, 0, 2] = fn4 * px
    Jk[:, 1, 2] = fn4 * py
    return r, A, Jk


def bal_project_jacobian(cameras: np.ndarray, points: np.ndarray):
    """Projection and analytic Jacobians of the BAL model, one camera per point.

    Parameters
    ----------
    cameras : (M, 9) float64
    points : (M, 3) float64

    Returns
    -------
    xy : (M, 2) projections (px)
    J_camera : (M, 2, 9) derivatives w.r.t. ``rx ry rz tx ty tz f k1 k2`` (exact derivative w.r.t.
        the axis-angle vector, via the left Jacobian of SO(3))
    J_point : (M, 2, 3) derivatives w.r.t. the point.
    """
    cameras = np.asarray(cameras, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    rv = cameras[:, :3]
    R = rotation_matrices(rv)
    Q = np.einsum("mij,mj->mi", R, points)
    zero = np.zeros((len(points), 2))
    r, A, Jk = _proj_jac(Q, cameras[:, 3:6], cameras[:, 6], cameras[:, 7], cameras[:, 8], zero)
    # d(R(r) X)/dr = -[R X]x J_l(r), J_l the left Jacobian of SO(3)
    th2 = np.sum(rv * rv, axis=1)
    th = np.sqrt(th2)
    small = th2 < 1e-12
    ths = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    b = np.where(small, 1.0 / 6.0 - th2 / 120.0, (ths - np.sin(ths)) / ths**3)
    from ._so3 import skew

    K = skew(rv)
    Jl = np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)
    dP_dr = -skew(Q) @ Jl
    Jc = np.empty((len(points), 2, 9))
    Jc[:, :, 0:3] = A @ dP_dr
    Jc[:, :, 3:6] = A
    Jc[:, :, 6:9] = Jk
    return r, Jc, A @ R


def bal_cost(problem) -> float:
    """Plain BAL cost ``1/2 sum |x(camera, point) - observation|^2`` over ALL observations
    (points behind a camera included), in px^2."""
    r = bal_project(problem.cameras[problem.camera_index], problem.points[problem.point_index]) - problem.observations
    return float(0.5 * np.sum(r * r))


# ----------------------------------------------------------------------------------------------
# options / result
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BALSolverOptions:
    """How :func:`solve_bal` solves (defaults are Ceres Solver's defaults).

    Attributes
    ----------
    max_iterations : int
        Accepted plus rejected steps.
    function_tolerance, gradient_tolerance, parameter_tolerance : float
        Stopping rules, see the module docstring.
    initial_trust_region_radius, max_trust_region_radius, min_trust_region_radius : float
    min_relative_decrease : float
        Minimum gain ratio for accepting a step.
    min_lm_diagonal, max_lm_diagonal : float
        Clamp of the LM damping diagonal.
    num_threads : int
        Worker threads for assembling the reduced camera system (numpy/BLAS release the GIL).
    max_pairs_per_chunk : int
        Observation pairs gathered at once while assembling the reduced system (bounds memory).
    """

    max_iterations: int = 100
    function_tolerance: float = 1e-6
    gradient_tolerance: float = 1e-10
    parameter_tolerance: float = 1e-8
    initial_trust_region_radius: float = 1e4
    max_trust_region_radius: float = 1e16
    min_trust_region_radius: float = 1e-32
    min_relative_decrease: float = 1e-3
    min_lm_diagonal: float = 1e-6
    max_lm_diagonal: float = 1e32
    num_threads: int = 2
    max_pairs_per_chunk: int = 6000

    def __post_init__(self):
        from ..errors import ConfigError

        if self.max_iterations < 0:
            raise ConfigError(f"max_iterations={self.max_iterations!r}; expected an integer >= 0")
        for name in ("function_tolerance", "gradient_tolerance", "parameter_tolerance"):
            v = getattr(self, name)
            if not (v >= 0.0):
                raise ConfigError(f"{name}={v!r}; expected a number >= 0")
        if self.num_threads < 1:
            raise ConfigError(f"num_threads={self.num_threads!r}; expected an integer >= 1")


@dataclass
class BALResult:
    """Outcome of :func:`solve_bal`.

    Attributes
    ----------
    problem : BALProblem
        Final state (cameras in BAL axis-angle form).
    initial_cost, final_cost : float
        Plain BAL cost ``1/2 sum r^2`` (px^2) before and after.
    iterations : int
        Accepted plus rejected LM steps.
    successful_steps : int
    termination : Termination
    reason : str
    time_s : float
        Wall time of the solve (s).
    cost_history : list of float
        Cost after every accepted step.
    """

    problem: object
    initial_cost: float
    final_cost: float
    iterations: int
    successful_steps: int
    termination: Termination
    reason: str
    time_s: float
    cost_history: list = field(default_factory=list)

    @property
    def success(self) -> bool:
        return self.termination.success


# ----------------------------------------------------------------------------------------------
# the solver
# ----------------------------------------------------------------------------------------------
class _Structure:
    """Index structures that depend only on which camera sees which point.

    Observations are stored camera-major (sorted by camera, then point): camera blocks are
    contiguous slices. Sums over the observations of a point use a sparse 0/1 matrix
    ``P`` (points x observations), i.e. one compiled sparse product instead of a scatter.
    """

    def __init__(self, ci, pi, ncam, npt, max_pairs):
        order = np.lexsort((pi, ci))  # by camera, then point
        self.order = order
        ci = ci[order]
        pi = pi[order]
        self.ci, self.pi = ci, pi
        M = len(ci)
        counts = np.bincount(pi, minlength=npt)
        self.seen = counts > 0
        slot = np.full(npt, -1, dtype=np.int64)
        slot[self.seen] = np.arange(int(self.seen.sum()))
        self.slot = slot[pi]  # point slot of each observation
        nseen = int(self.seen.sum())
        self.P = sp.csr_matrix((np.ones(M), (self.slot, np.arange(M))), shape=(nseen, M))
        ccounts = np.bincount(ci, minlength=ncam)
        self.cbounds = [int(v) for v in np.concatenate([[0], np.cumsum(ccounts)])]
        # pairs (i < j) of observations of the same point (the diagonal pairs i == j are summed
        # per camera without any gather); built in point-major order, stored camera-major
        pperm = np.argsort(pi, kind="stable")  # point-major position -> camera-major position
        cnt = counts[self.seen]
        starts = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        rank = np.arange(M) - np.repeat(starts, cnt)
        npart = np.repeat(cnt, cnt) - rank - 1
        I = np.repeat(np.arange(M), npart)
        J = I + (np.arange(I.size) - np.repeat(np.cumsum(npart) - npart, npart) + 1)
        I = pperm[I]
        J = pperm[J]
        key = ci[I] * ncam + ci[J]
        korder = np.lexsort((I, key))
        self.I = I[korder].astype(np.int32 if M < 2**31 else np.int64)
        self.J = J[korder].astype(self.I.dtype)
        key = key[korder]
        del I, J, korder
        ukeys, kstart = np.unique(key, return_index=True)
        kstart = np.append(kstart, key.size)
        kc1 = ukeys // ncam
        kc2 = ukeys % ncam
        self.npairs = int(key.size)
        # chunks of keys with at most max_pairs pairs (a single key may exceed it); per chunk
        # (pair start, pair end, [(local start, local end, c1, c2), ...]) as Python ints
        chunks = []
        s = 0
        nk = len(ukeys)
        while s < nk:
            e = s + 1
            while e < nk and kstart[e + 1] - kstart[s] <= max_pairs:
                e += 1
            ps = int(kstart[s])
            chunks.append(
                (
                    ps,
                    int(kstart[e]),
                    [(int(kstart[k]) - ps, int(kstart[k + 1]) - ps) for k in range(s, e)],
                    kc1[s:e].copy(),
                    kc2[s:e].copy(),
                )
            )
            s = e
        self.chunks = chunks


def _sym3_inv(V):
    """Inverse of symmetric 3x3 blocks (N, 3, 3) by the adjugate; returns (inv, ok)."""
    a, b, c = V[:, 0, 0], V[:, 0, 1], V[:, 0, 2]
    d, e, f_ = V[:, 1, 1], V[:, 1, 2], V[:, 2, 2]
    A = d * f_ - e * e
    B = c * e - b * f_
    C = b * e - c * d
    det = a * A + b * B + c * C
    ok = det > 1e-300
    idet = 1.0 / np.where(ok, det, 1.0)
    out = np.empty_like(V)
    out[:, 0, 0] = A * idet
    out[:, 0, 1] = out[:, 1, 0] = B * idet
    out[:, 0, 2] = out[:, 2, 0] = C * idet
    out[:, 1, 1] = (a * f_ - c * c) * idet
    out[:, 1, 2] = out[:, 2, 1] = (b * c - a * e) * idet
    out[:, 2, 2] = (a * d - b * b) * idet
    return out, ok


def solve_bal(problem, options: BALSolverOptions | None = None) -> BALResult:
    """Minimise the BAL reprojection cost by Levenberg-Marquardt with the Schur complement.

    Parameters
    ----------
    problem : thermogrammetry.io.bal.BALProblem
        Initial state; it is not modified.
    options : BALSolverOptions, optional
        Stopping rules and threads (defaults: Ceres Solver's defaults, 2 threads).

    Returns
    -------
    BALResult
        ``.initial_cost``, ``.final_cost`` (plain BAL cost, px^2), ``.iterations``,
        ``.termination``, ``.reason``, ``.problem`` (final state). Never raises for numerical
        trouble: no observations give ``TOO_FEW_OBSERVATIONS``, a non-finite initial cost
        ``NUMERICAL_FAILURE``, running out of iterations ``MAX_ITERATIONS``.

    Notes
    -----
    See the module docstring for the algorithm, the damping strategy and the stopping rules.
    """
    from ._threads import blas_single_thread

    # BLAS calls inside are small; OpenBLAS's own threads only spin against ours on few cores.
    with blas_single_thread(), np.errstate(all="ignore"):
        return _solve_bal(problem, options)


_TIMERS: dict = {}  # internal profiling: accumulated wall time per solver phase (s)


def _tick(name, t):
    now = time.perf_counter()
    _TIMERS[name] = _TIMERS.get(name, 0.0) + now - t
    return now


def _solve_bal(problem, options: BALSolverOptions | None = None) -> BALResult:
    opt = options or BALSolverOptions()
    t0 = time.perf_counter()
    ncam, npt = problem.num_cameras, problem.num_points
    if problem.num_observations == 0:
        return BALResult(
            problem.copy(), 0.0, 0.0, 0, 0, Termination.TOO_FEW_OBSERVATIONS, "the problem has no observations",
            time.perf_counter() - t0, [0.0],
        )
    st = _Structure(problem.camera_index, problem.point_index, ncam, npt, opt.max_pairs_per_chunk)
    obs = problem.observations[st.order]
    ci, pi, slot, Pm = st.ci, st.pi, st.slot, st.P
    cb = st.cbounds
    M = len(ci)
    cam = problem.cameras
    R = rotation_matrices(cam[:, :3])
    t = cam[:, 3:6].copy()
    intr = cam[:, 6:9].copy()
    X = problem.points.copy()
    pts_seen = np.nonzero(st.seen)[0]
    nseen = len(pts_seen)
    counts_c = np.diff(cb)
    cams_used = [c for c in range(ncam) if counts_c[c] > 0]
    pool = ThreadPoolExecutor(opt.num_threads) if opt.num_threads > 1 else None

    def rotate(R, X):
        Xg = np.take(X, pi, axis=0)
        Q = np.empty_like(Xg)
        for c in cams_used:
            s_, e_ = cb[c], cb[c + 1]
            np.matmul(Xg[s_:e_], R[c].T, out=Q[s_:e_])
        return Q

    def residuals(R, t, intr, X, want_jac):
        Q = rotate(R, X)
        tt_ = np.repeat(t, counts_c, axis=0)
        ic = np.repeat(intr, counts_c, axis=0)
        return Q, _proj_jac(Q, tt_, ic[:, 0], ic[:, 1], ic[:, 2], obs, want_jac)

    def cost_of(r):
        return 0.5 * float(np.einsum("ij,ij->", r, r))

    Q, r = residuals(R, t, intr, X, False)
    cost = cost_of(r)
    initial_cost = cost

    def finish(term, reason, it, nsucc, hist):
        if pool is not None:
            pool.shutdown(wait=False)
        out = problem.copy()
        out.cameras = np.concatenate([axis_angles(R), t, intr], axis=1)
        out.points = X
        return BALResult(out, initial_cost, cost, it, nsucc, term, reason, time.perf_counter() - t0, hist)

    if M == 0:
        return finish(Termination.TOO_FEW_OBSERVATIONS, "the problem has no observations", 0, 0, [cost])
    if not np.isfinite(cost):
        return finish(Termination.NUMERICAL_FAILURE, "initial cost is not finite", 0, 0, [])

    radius = opt.initial_trust_region_radius
    decrease = 2.0
    it = 0
    nsucc = 0
    hist = [cost]
    need_jac = True
    nc9 = 9 * ncam
    diag3 = ([0, 1, 2], [0, 1, 2])
    # work buffers reused across iterations (steady memory, no allocator churn)
    Jc_buf = np.empty((M, 2, 9))
    Jp_buf = np.empty((M, 2, 3))
    WT = np.empty((M, 3, 9))
    YT = np.empty((M, 3, 9))

    while True:
        tt = time.perf_counter()
        if need_jac:
            V = gp = None  # release the previous linearisation before building the next
            Q, (r, A, Jk) = residuals(R, t, intr, X, True)
            tt = _tick("jac_eval", tt)
            # camera Jacobian (M, 2, 9): [d/dw (left perturbation), d/dt, d/d(f,k1,k2)]
            Jc = Jc_buf
            q0, q1, q2 = Q[:, 0:1], Q[:, 1:2], Q[:, 2:3]
            a0, a1, a2 = A[:, :, 0], A[:, :, 1], A[:, :, 2]
            Jc[:, :, 0] = q1 * a2 - q2 * a1  # -A [Q]x, row-wise cross(Q, A_a)
            Jc[:, :, 1] = q2 * a0 - q0 * a2
            Jc[:, :, 2] = q0 * a1 - q1 * a0
            Jc[:, :, 3:6] = A
            Jc[:, :, 6:9] = Jk
            del Jk, Q
            Jp = Jp_buf
            for c in cams_used:
                s_, e_ = cb[c], cb[c + 1]
                np.matmul(A[s_:e_].reshape(-1, 3), R[c], out=Jp[s_:e_].reshape(-1, 3))
            del A
            tt = _tick("jac_assemble", tt)
            # camera blocks U and gradient g_c: one BLAS product per camera (contiguous)
            U = np.zeros((ncam, 9, 9))
            gc = np.zeros((ncam, 9))
            Jcf = Jc.reshape(-1, 9)
            rf = r.reshape(-1)
            for c in cams_used:
                s_, e_ = 2 * cb[c], 2 * cb[c + 1]
                blk = Jcf[s_:e_]
                U[c] = blk.T @ blk
                gc[c] = blk.T @ rf[s_:e_]
            tt = _tick("U", tt)
            # point blocks V, g_p: sparse sums over each point's observations
            JpT = Jp.transpose(0, 2, 1)
            V = np.asarray(Pm @ np.einsum("mai,maj->mij", Jp, Jp).reshape(M, 9)).reshape(nseen, 3, 3)
            gp = np.asarray(Pm @ np.einsum("mka,mk->ma", Jp, r))
            np.matmul(JpT, Jc, out=WT)  # (M, 3, 9) = (Jc^T Jp)^T per observation
            del Jc, Jcf, Jp, JpT
            gmax = max(float(np.max(np.abs(gc))), float(np.max(np.abs(gp))) if nseen else 0.0)
            if gmax <= opt.gradient_tolerance:
                return finish(Termination.CONVERGED, f"gradient tolerance reached: max|g| = {gmax:.3g}", it, nsucc, hist)
            dU = np.clip(np.diagonal(U, axis1=1, axis2=2), opt.min_lm_diagonal, opt.max_lm_diagonal)
            dV = np.clip(np.diagonal(V, axis1=1, axis2=2), opt.min_lm_diagonal, opt.max_lm_diagonal)
            need_jac = False
            tt = _tick("V_W", tt)

        if it >= opt.max_iterations:
            return finish(Termination.MAX_ITERATIONS, f"stopped after {it} iterations", it, nsucc, hist)
        it += 1
        # ---- damped Schur solve
        lam = 1.0 / radius
        Vd = V.copy()
        Vd[:, diag3[0], diag3[1]] += lam * dV
        Vinv, okv = _sym3_inv(Vd)
        # YT (M, 3, 9): V^-1 W^T per observation, built in slabs into the work buffer
        for s_ in range(0, M, 16384):
            np.matmul(np.take(Vinv, slot[s_ : s_ + 16384], axis=0), WT[s_ : s_ + 16384], out=YT[s_ : s_ + 16384])
        YTf = YT.reshape(M, 27)
        WTf = WT.reshape(M, 27)
        # reduced camera system S = U + D_c/radius - sum_points W V^-1 W^T
        Sm = np.zeros((nc9, nc9))
        for c in range(ncam):
            s_, e_ = cb[c], cb[c + 1]
            blk = U[c]
            if e_ > s_:
                blk = blk - YTf[s_:e_].reshape(-1, 9).T @ WTf[s_:e_].reshape(-1, 9)
            Sm[9 * c : 9 * c + 9, 9 * c : 9 * c + 9] = blk

        def do_chunk(ch):
            ps, pe, keys, kc1, kc2 = ch
            Yg = np.take(YTf, st.I[ps:pe], axis=0)
            Wg = np.take(WTf, st.J[ps:pe], axis=0)
            # sum over shared points of W_i V^-1 W_j^T = sum (V^-1 W_i^T)^T W_j^T
            blocks = np.empty((len(keys), 9, 9))
            for k, (a, b) in enumerate(keys):
                np.matmul(Yg[a:b].reshape(-1, 9).T, Wg[a:b].reshape(-1, 9), out=blocks[k])
            return kc1, kc2, blocks

        if pool is not None and len(st.chunks) > 1:
            results = pool.map(do_chunk, st.chunks)
        else:
            results = map(do_chunk, st.chunks)
        S4 = Sm.reshape(ncam, 9, ncam, 9)
        for kc1, kc2, blocks in results:
            # every camera pair (c1 < c2) occurs in exactly one chunk: plain assignment
            off = kc1 != kc2
            S4[kc1[off], :, kc2[off], :] = -blocks[off]
            S4[kc2[off], :, kc1[off], :] = -blocks[off].transpose(0, 2, 1)
            for k in np.nonzero(~off)[0]:  # the same camera twice on one point (duplicates)
                c = kc1[k]
                Sm[9 * c : 9 * c + 9, 9 * c : 9 * c + 9] -= blocks[k] + blocks[k].T
        Sm[np.arange(nc9), np.arange(nc9)] += lam * dU.reshape(-1)
        tt = _tick("S", tt)
        # rhs: -g_c + sum_obs (V^-1 W^T)^T g_p
        y = np.einsum("mkc,mk->mc", YT, np.take(gp, slot, axis=0))
        del YTf
        yb = np.zeros((ncam, 9))
        for c in cams_used:
            yb[c] = y[cb[c] : cb[c + 1]].sum(axis=0)
        b = (-gc + yb).reshape(-1)
        del y, Vd
        tt = _tick("rhs", tt)
        step_ok = bool(np.all(okv))
        if step_ok:
            try:
                cf = scipy.linalg.cho_factor(Sm, lower=False, check_finite=False)
                dc = scipy.linalg.cho_solve(cf, b, check_finite=False)
                step_ok = bool(np.all(np.isfinite(dc)))
            except (np.linalg.LinAlgError, ValueError):
                step_ok = False
        tt = _tick("chol", tt)
        if step_ok:
            dcb = dc.reshape(ncam, 9)
            # back-substitution: dp = V^-1 (-g_p - sum W^T dc)
            wdc = np.einsum("mkc,mc->mk", WT, np.repeat(dcb, counts_c, axis=0))
            rp = -gp - np.asarray(Pm @ wdc)
            del wdc
            dp = np.einsum("nij,nj->ni", Vinv, rp)
            # model cost reduction: 1/2 (-g^T d + d^T D d / radius)
            gd = float(np.dot(gc.ravel(), dc) + np.einsum("ij,ij->", gp, dp))
            dDd = float(np.dot(dU.ravel(), dc * dc) + np.einsum("ij,ij->", dV, dp * dp))
            model = 0.5 * (-gd + lam * dDd)
            # parameter tolerance
            step_norm = float(np.sqrt(np.dot(dc, dc) + np.einsum("ij,ij->", dp, dp)))
            x_norm = float(np.sqrt(np.sum(axis_angles(R) ** 2) + np.sum(t * t) + np.sum(intr * intr) + np.sum(X * X)))
            if step_norm <= opt.parameter_tolerance * (x_norm + opt.parameter_tolerance):
                return finish(Termination.CONVERGED, f"parameter tolerance reached: |dx| = {step_norm:.3g}", it, nsucc, hist)
            R_new = rotation_matrices(dcb[:, 0:3]) @ R
            t_new = t + dcb[:, 3:6]
            intr_new = intr + dcb[:, 6:9]
            X_new = X.copy()
            X_new[pts_seen] += dp
            tt = _tick("backsub", tt)
            _, r_new = residuals(R_new, t_new, intr_new, X_new, False)
            cost_new = cost_of(r_new)
            tt = _tick("eval", tt)
            rho = (cost - cost_new) / model if model > 0 else -1.0
            step_ok = np.isfinite(cost_new) and rho > opt.min_relative_decrease
        if step_ok:
            change = cost - cost_new
            R, t, intr, X = R_new, t_new, intr_new, X_new
            del r_new
            cost = cost_new
            nsucc += 1
            hist.append(cost)
            radius = min(opt.max_trust_region_radius, radius / max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3))
            decrease = 2.0
            need_jac = True
            if abs(change) <= opt.function_tolerance * (cost + change):
                return finish(
                    Termination.CONVERGED,
                    f"function tolerance reached: |dcost|/cost = {abs(change) / (cost + change):.3g}",
                    it,
                    nsucc,
                    hist,
                )
        else:
            radius /= decrease
            decrease *= 2.0
            if radius < opt.min_trust_region_radius:
                return finish(
                    Termination.CONVERGED,
                    f"trust region radius {radius:.3g} below the minimum; no further decrease possible",
                    it,
                    nsucc,
                    hist,
                )
