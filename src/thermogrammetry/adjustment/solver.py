"""How a :class:`~thermogrammetry.adjustment.problem.BundleProblem` is solved, and what comes out.

Levenberg-Marquardt (Ceres-style trust region, see :mod:`thermogrammetry.adjustment.bal`) on the
whitened residuals ``r_i / sigma_i``; the normal equations are reduced to the non-point parameters
by the Schur complement on the 3x3 point blocks, built with sparse products and solved by dense
Cholesky (the reduced system of calibration and close-range networks is small).

Large blocks (``SolverOptions.chunked_min_observations`` image observations and more, e.g. survey
blocks) never hold the block's Jacobian (~1 KB per observation): the observations are grouped by
point and evaluated chunk by chunk; each chunk adds its share of ``U``, the gradient, the point blocks
``V`` and the Schur complement ``W V^-1 W^T`` to the reduced camera system and is dropped; after the
Cholesky solve a second pass over the chunks back-substitutes the point steps (and gives the
iterative-refinement residual). Memory then grows with the number of cameras (the dense reduced
matrix) and points, not with the observations; the solution is that of the full path up to rounding.

Precision and reliability (Foerstner & Wrobel 2016, ch. 4; Baarda 1968):

- ``sigma0^2 = v^T P v / r`` with redundancy ``r = m - n (+ d for a free network)`` and the
  two-sided chi^2 test of ``r sigma0^2 / sigma0_prior^2`` at ``alpha``;
- cofactor matrix ``Q = S^-1`` of the non-point parameters (intrinsics, poses, rigs); a
  posteriori covariance ``sigma0^2 Q``; standard deviations and correlations; point
  covariances ``V^-1 + V^-1 W^T Q W V^-1`` on request; for a free network the inner-constraint
  cofactor ``P N^- P^T`` with ``P = I - G (E^T G)^-1 E^T`` (S-transformation onto minimum trace
  of the points; Baarda 1973);
- redundancy numbers ``r_i = 1 - (J Q J^T)_ii`` of every whitened observation row;
- Baarda's data snooping: ``w_i = v_i / (sigma_i sqrt(r_i))`` with the a priori sigma (w-test,
  normal critical value for ``snooping_alpha``), iterative rejection of image points; warnings
  for ``|rho| > correlation_warning`` and for additional parameters whose t-value
  ``|x| / sigma_x`` is below the Student-t critical value (insignificant).

Robust losses (Huber, Cauchy) act on image points by iteratively re-weighted rows
(``sqrt(rho'(s))``, Triggs et al. 2000, sec. 3.3).

References
----------
Baarda, W. (1968). A testing procedure for use in geodetic networks. Netherlands Geodetic
Commission, Publications on Geodesy 2(5).
Baarda, W. (1973). S-transformations and criterion matrices. NGC, Publ. on Geodesy 5(1).
Foerstner, W., Wrobel, B. P. (2016). Photogrammetric Computer Vision. Springer, ch. 4.
Fraser, C. S. (1997). Digital camera self-calibration. ISPRS J. 52, 149-159.
Triggs, B. et al. (2000). Bundle adjustment - a modern synthesis. LNCS 1883.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field, fields

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.special

from .._memory import release_free_heap
from ..enums import StrChoice
from ..errors import ConfigError, InvalidInputError
from ..results import Termination
from ._so3 import axis_angles, rotation_matrices, skew
from .problem import BundleProblem, Gauge

__all__ = ["Loss", "SolverOptions", "AdjustmentResult", "solve"]

# intrinsics that are "additional parameters" (tested for significance), per model
_ADDITIONAL = {
    "k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2", "skew",
    "K1", "K2", "K3", "K4", "K5", "P1", "P2", "B1", "B2",
}


class Loss(StrChoice):
    TRIVIAL = "trivial"
    HUBER = "huber"
    CAUCHY = "cauchy"


@dataclass(frozen=True)
class SolverOptions:
    """How the adjustment is solved (the problem says what is estimated).

    Attributes
    ----------
    max_iterations : int
        LM steps (accepted + rejected) per solve.
    function_tolerance, gradient_tolerance, parameter_tolerance : float
        Ceres-style stopping rules (see :mod:`thermogrammetry.adjustment.bal`); also converged
        when the predicted decrease is below ``function_tolerance * cost``. The cost is
        ``chi^2 / 2``: a relative change of 1e-8 moves well-determined parameters by far less
        than 0.01 sigma in networks of up to ~1e5 observations.
    initial_trust_region_radius : float
    loss : Loss
        Robust loss on image points (``trivial``, ``huber``, ``cauchy``).
    loss_scale : float
        Scale of the loss in units of the whitened residual norm (i.e. in sigmas).
    sigma0_prior : float
        A priori standard deviation of unit weight (1 when the stated sigmas are right).
    compute_covariance : bool
    compute_point_covariance : bool
    compute_redundancy : bool
        Redundancy numbers and w-tests (needs the covariance).
    data_snooping : bool
        Iteratively reject image points whose w-test fails.
    snooping_alpha : float
        Two-sided significance level of a single w-test (0.001 -> 3.29).
    max_snooping_rounds : int
    correlation_warning : float
        Warn for |rho| above this between camera-side parameters.
    significance_alpha : float
        Two-sided level of the t-test of additional parameters.
    rank_tolerance : float
        Smallest eigenvalue / largest of the Jacobi-scaled reduced normal matrix below which the
        problem is rank deficient.
    max_dense_inner : int
        Largest parameter count for which the free-network (inner constraint) covariance is
        computed (dense).
    chunked_min_observations : int
        Number of (active) image observations from which the normal equations are built chunk by
        chunk of points without holding the block's Jacobian (memory independent of the number of
        observations, instead of ~1 KB per observation; a second pass over the Jacobians per LM
        step, and one per rejected step). Same solution up to rounding. 0: always; a huge number:
        never. The covariance step falls back to the full Jacobian when it needs it (redundancy
        numbers, point covariances, free-network covariance).
    num_threads : int
        Threads for the largest sparse products of the normal equations on the full-Jacobian path (rows split
        over threads; the same values, bit for bit, with any count).
    """

    max_iterations: int = 100
    function_tolerance: float = 1e-8
    gradient_tolerance: float = 1e-12
    parameter_tolerance: float = 1e-10
    initial_trust_region_radius: float = 1e4
    loss: Loss = Loss.TRIVIAL
    loss_scale: float = 3.0
    sigma0_prior: float = 1.0
    compute_covariance: bool = True
    compute_point_covariance: bool = False
    compute_redundancy: bool = True
    data_snooping: bool = False
    snooping_alpha: float = 0.001
    max_snooping_rounds: int = 50
    correlation_warning: float = 0.9
    significance_alpha: float = 0.05
    rank_tolerance: float = 1e-12
    max_dense_inner: int = 4000
    chunked_min_observations: int = 100_000
    num_threads: int = 2

    def __post_init__(self):
        object.__setattr__(self, "loss", Loss(self.loss))
        if self.max_iterations < 0:
            raise ConfigError(f"max_iterations={self.max_iterations!r}; expected an integer >= 0")
        if self.num_threads < 1:
            raise ConfigError(f"num_threads={self.num_threads!r}; expected an integer >= 1")
        if self.chunked_min_observations < 0:
            raise ConfigError(f"chunked_min_observations={self.chunked_min_observations!r}; expected an integer >= 0")
        for name in ("loss_scale", "sigma0_prior", "snooping_alpha", "significance_alpha"):
            v = getattr(self, name)
            if not (v > 0):
                raise ConfigError(f"{name}={v!r}; expected a number > 0")

    @classmethod
    def from_dict(cls, d: dict) -> "SolverOptions":
        known = {f.name for f in fields(cls)}
        bad = set(d) - known
        if bad:
            raise ConfigError(f"unknown solver option(s) {sorted(bad)}; expected some of {sorted(known)}")
        return cls(**d)


@dataclass
class AdjustmentResult:
    """Outcome of :func:`solve`.

    Attributes
    ----------
    termination, reason : Termination, str
    iterations : int
    initial_cost, final_cost : float
        ``1/2 sum rho(r_i^2)`` of the whitened residuals (``1/2 v^T P v`` without a robust loss).
    problem : BundleProblem
        Copy of the problem at the estimate (cameras carry ``param_std``); usable as the start
        of a further stage.
    sigma0 : float
        A posteriori standard deviation of unit weight.
    redundancy : int
    chi2 : dict
        ``statistic``, ``dof``, ``lower``, ``upper``, ``passed`` of the two-sided chi^2 test.
    param_names : list of str
        Camera-side parameters in covariance order: ``"<camera>.<param>"``,
        ``"<pose>.wx|wy|wz|X0|Y0|Z0"`` (rotation increments in rad, projection centre in m),
        ``"rig<i>.wx..tz"``.
    covariance : (n, n) array (a posteriori) or None
    correlation : (n, n) array or None
        Computed from ``covariance`` at each access (not stored: a second n x n matrix would double the
        memory of the precision step of large blocks).
    std : (n,) array or None
    camera_std : list of (P,) arrays (NaN where fixed)
    pose_std : (n_poses, 6) array
        Rotation (rad; the left increment ``R <- exp([dw]x) R``, i.e. small rotations about the
        camera-frame axes applied after R) and projection-centre ``X0 Y0 Z0`` standard
        deviations (m); NaN for fixed poses.
    point_covariance : (N, 3, 3) or None
        A posteriori, free points only (NaN elsewhere), when requested.
    image_residuals : (K, 2) px, ``measured - computed`` corrections v (0 for rejected)
    image_redundancy : (K, 2)
    image_w : (K, 2) w-test values (NaN for rejected)
    rejected : (K,) bool
    control_residuals : (Kc, 3) m
    gnss_residuals : (Kg, 3) m
    attitude_residuals : (Ka, 3) rad, rotation vectors of ``R_obs R^T`` (observed minus computed, camera frame)
    control_redundancy, control_w, gnss_redundancy, gnss_w : (K, 3)
        Redundancy numbers and w-tests of the control and GNSS observations (blunders in
        coordinates are reported, not rejected automatically).
    warnings : list of str
    precision_reason : str
        Why the standard deviations are NaN ("" when they are determined): redundancy <= 0 (sigma0
        undefined) or a singular normal matrix. They are never reported as 0 in that case.
    """

    termination: Termination
    reason: str
    iterations: int
    initial_cost: float
    final_cost: float
    problem: BundleProblem
    sigma0: float = float("nan")
    redundancy: int = 0
    chi2: dict = field(default_factory=dict)
    param_names: list = field(default_factory=list)
    covariance: np.ndarray | None = None
    std: np.ndarray | None = None
    camera_std: list = field(default_factory=list)
    pose_std: np.ndarray | None = None
    point_covariance: np.ndarray | None = None
    image_residuals: np.ndarray | None = None
    image_redundancy: np.ndarray | None = None
    image_w: np.ndarray | None = None
    rejected: np.ndarray | None = None
    control_residuals: np.ndarray | None = None
    gnss_residuals: np.ndarray | None = None
    attitude_residuals: np.ndarray | None = None
    control_redundancy: np.ndarray | None = None
    control_w: np.ndarray | None = None
    gnss_redundancy: np.ndarray | None = None
    gnss_w: np.ndarray | None = None
    warnings: list = field(default_factory=list)
    time_s: float = 0.0
    precision_reason: str = ""

    @property
    def success(self) -> bool:
        return self.termination.success

    @property
    def correlation(self) -> np.ndarray | None:
        """(n, n) correlation matrix ``cov_ij / (std_i std_j)``, from ``covariance`` (NaN where a std is 0)."""
        if self.covariance is None:
            return None
        std = np.sqrt(np.maximum(np.diag(self.covariance), 0.0))
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = self.covariance / std[:, None]
            corr /= std[None, :]
        return corr

    @property
    def points(self) -> np.ndarray:
        return self.problem.points

    @property
    def cameras(self) -> list:
        return self.problem.cameras

    @property
    def poses(self) -> list:
        return self.problem.poses()


# ------------------------------------------------------------------------------------------------
# internal: parameter layout, evaluation, linear algebra
# ------------------------------------------------------------------------------------------------
class _Layout:
    def __init__(self, pb: BundleProblem):
        col = 0
        self.cam_cols = []
        names = []
        for i, (cam, fx) in enumerate(zip(pb.cameras, pb.camera_fixed)):
            cc = np.full(len(fx), -1, dtype=np.int64)
            for k in range(len(fx)):
                if not fx[k]:
                    cc[k] = col
                    col += 1
                    names.append(f"{pb.camera_names[i]}.{cam.param_names[k]}")
            self.cam_cols.append(cc)
        self.pose_col = np.full(len(pb.pose_R), -1, dtype=np.int64)
        for p in range(len(pb.pose_R)):
            if not pb.pose_fixed[p]:
                self.pose_col[p] = col
                col += 6
                names += [f"{pb.pose_names[p]}.{a}" for a in ("wx", "wy", "wz", "tx", "ty", "tz")]
        self.rig_col = np.full(len(pb.rig_R), -1, dtype=np.int64)
        for r in range(len(pb.rig_R)):
            if not pb.rig_fixed[r]:
                self.rig_col[r] = col
                col += 6
                names += [f"rig{r}.{a}" for a in ("wx", "wy", "wz", "tx", "ty", "tz")]
        self.plane_col = np.full(len(pb.plane_n), -1, dtype=np.int64)
        for k in range(len(pb.plane_n)):
            if not pb.plane_fixed[k]:
                self.plane_col[k] = col
                col += 3
                names += [f"plane{k}.{a}" for a in ("n1", "n2", "d")]
        # free points in distance observations are coupled: they join the camera side
        da, db, _, _ = pb.distance_observations()
        free = ~pb.point_fixed
        coupled = np.zeros(len(pb.points), dtype=bool)
        coupled[da] = True
        coupled[db] = True
        coupled &= free
        self.cs_points = np.nonzero(coupled)[0]
        self.point_col = np.full(len(pb.points), -1, dtype=np.int64)
        for p in self.cs_points:
            self.point_col[p] = col
            col += 3
            names += [f"point{p}.{a}" for a in ("X", "Y", "Z")]
        self.nc = col
        self.names = names
        free &= ~coupled
        self.free_points = np.nonzero(free)[0]
        self.point_slot = np.full(len(pb.points), -1, dtype=np.int64)
        self.point_slot[self.free_points] = np.arange(len(self.free_points))
        self.npf = len(self.free_points)


class _State:
    def __init__(self, pb: BundleProblem):
        self.cam_params = [c.params.copy() for c in pb.cameras]
        self.R = np.array(pb.pose_R).reshape(-1, 3, 3)
        self.t = np.array(pb.pose_t).reshape(-1, 3)
        self.rR = np.array(pb.rig_R).reshape(-1, 3, 3)
        self.rt = np.array(pb.rig_t).reshape(-1, 3)
        self.pn = np.array(pb.plane_n, dtype=float).reshape(-1, 3)
        self.pd = np.array(pb.plane_d, dtype=float).reshape(-1)
        self.X = pb.points.copy()

    def plus(self, lay: _Layout, dc: np.ndarray, dp: np.ndarray) -> "_State":
        s = object.__new__(_State)
        s.cam_params = []
        for p, cc in zip(self.cam_params, lay.cam_cols):
            q = p.copy()
            m = cc >= 0
            q[m] += dc[cc[m]]
            s.cam_params.append(q)
        s.R, s.t = self.R.copy(), self.t.copy()
        fp = np.nonzero(lay.pose_col >= 0)[0]
        if len(fp):
            d = dc[lay.pose_col[fp][:, None] + np.arange(6)]
            s.R[fp] = rotation_matrices(d[:, :3]) @ self.R[fp]
            s.t[fp] = self.t[fp] + d[:, 3:]
        s.pn, s.pd = self.pn.copy(), self.pd.copy()
        fpl = np.nonzero(lay.plane_col >= 0)[0]
        for k in fpl:
            c = lay.plane_col[k]
            n = self.pn[k] + _tangent_basis(self.pn[k]) @ dc[c : c + 2]
            s.pn[k] = n / np.linalg.norm(n)
            s.pd[k] = self.pd[k] + dc[c + 2]
        s.rR, s.rt = self.rR.copy(), self.rt.copy()
        fr = np.nonzero(lay.rig_col >= 0)[0]
        if len(fr):
            d = dc[lay.rig_col[fr][:, None] + np.arange(6)]
            s.rR[fr] = rotation_matrices(d[:, :3]) @ self.rR[fr]
            s.rt[fr] = self.rt[fr] + d[:, 3:]
        s.X = self.X.copy()
        if lay.npf:
            s.X[lay.free_points] += dp.reshape(-1, 3)
        if len(lay.cs_points):
            s.X[lay.cs_points] += dc[lay.point_col[lay.cs_points][:, None] + np.arange(3)]
        return s

    def write_to(self, pb: BundleProblem) -> None:
        pb.cameras = [c if np.array_equal(c.params, p) else c.with_params(p) for c, p in zip(pb.cameras, self.cam_params)]
        pb.pose_R = [r.copy() for r in self.R]
        pb.pose_t = [t.copy() for t in self.t]
        pb.rig_R = [r.copy() for r in self.rR]
        pb.rig_t = [t.copy() for t in self.rt]
        pb.plane_n = [n.copy() for n in self.pn]
        pb.plane_d = [float(d) for d in self.pd]
        pb.points = self.X.copy()


class _Data:
    """Observations (with the active mask for image points) in flat arrays."""

    def __init__(self, pb: BundleProblem, active: np.ndarray):
        img = pb.image_observations()  # (the problem's own concatenated arrays: shared, never written)
        a = np.nonzero(active)[0]
        self.img_idx = a
        uniform_sig = len(a) and not any(img.sigma.strides)  # one sigma for every observation (a broadcast)
        uniform_cam = len(a) and not any(img.camera.strides)
        if len(a) == len(active):  # all active: the problem's arrays themselves (no second copy)
            self.img_idx = slice(None)  # (the same rows as ``a``, without 8 B per observation)
            self.cam, self.view, self.pt, self.xy, self.sig = img.camera, img.view, img.point, img.xy, img.sigma
        else:
            self.cam = np.broadcast_to(img.camera[:1], (len(a),)) if uniform_cam else img.camera[a]
            self.view = img.view[a]
            self.pt = img.point[a]
            self.xy = img.xy[a]
            self.sig = np.broadcast_to(img.sigma[:1], (len(a), 2)) if uniform_sig else img.sigma[a]
        del img
        # int32 (pose and rig counts are far below 2^31); without rig views the pose of a view is the view itself
        # when views and poses are numbered alike, and no view has a rig: no array per observation then
        vp = np.asarray(pb.view_pose, dtype=np.int32)
        vr = np.asarray(pb.view_rig, dtype=np.int32)
        if not len(a):
            self.vpose = self.vrig = np.zeros(0, np.int32)
        else:
            if np.array_equal(vp, np.arange(len(vp))):
                self.vpose = self.view
            else:
                self.vpose = vp[self.view]
            self.vrig = np.broadcast_to(np.int32(-1), (len(a),)) if np.all(vr == -1) else vr[self.view]
        # the view is only needed for vpose/vrig; the camera block is compared per chunk (int32)
        self.view = None
        if not uniform_cam:
            self.cam = self.cam.astype(np.int32, copy=False)
        self.K = len(a)
        del a
        self.c_pt, self.c_xyz, self.c_sig = pb.control_observations()
        self.g_pose, self.g_xyz, self.g_sig, self.g_lever = pb.gnss_observations()
        self.d_a, self.d_b, self.d_len, self.d_sig = pb.distance_observations()
        self.pl_k, self.pl_pt, self.pl_sig = pb.plane_observations()
        self.a_pose, self.a_R, self.a_sig = pb.attitude_observations()
        self.m = (2 * self.K + 3 * len(self.c_pt) + 3 * len(self.g_pose) + len(self.d_a) + len(self.pl_k)
                  + 3 * len(self.a_pose))
        # the LM's last full-path linearisation (state, r, w, _Normal), for the precision step at the same state
        self.linearisation = None


#: image observations per chunk in :func:`_evaluate` (bounds its temporaries: ~1.5 KB per observation)
_EVAL_CHUNK = 32768
#: the same for residuals only (the LM's trial steps, ~0.4 KB per observation): smaller, since the residuals of
#: large blocks are evaluated while the factor of the reduced system is held
_EVAL_CHUNK_RES = 8192


def _evaluate(pb, lay: _Layout, st: _State, data: _Data, want_jac: bool, sel=None, extra: bool = True):
    """Whitened residuals r (m,), and (if wanted) the camera-side Jacobian (CSR, whitened), the point
    Jacobian rows (m, 3) and their free-point slots (m,). Residual = (computed - observed) / sigma.

    By default all rows: the active image observations (two rows each, in order), then control,
    GNSS, plane and distance rows. ``sel`` (int array) restricts the image rows to those observations
    (in that order; rows ``2k, 2k+1`` for ``sel[k]``), ``extra=False`` leaves out the other rows
    (the chunked normal equations evaluate the block in pieces)."""
    obs = sel  # (the name ``sel`` is reused below for the observations of one camera)
    K = data.K if obs is None else len(obs)
    m = data.m - 2 * data.K + 2 * K if extra else 2 * K
    r = np.empty(m)
    rows, cols, vals = [], [], []
    jp = np.zeros((m, 3)) if want_jac else None  # (residuals only: no per-row Jacobian arrays)
    pslot = np.full(m, -1, dtype=np.int64) if want_jac else None
    idx = np.int32 if max(m, lay.nc) < 2**31 - 1 else np.int64

    def trip(row0, ncomp, J, start, valid):
        # J (n, ncomp, w) for rows row0 + ncomp*k + a, columns start[k] + j
        n, _, w = J.shape
        if n == 0 or not np.any(valid):
            return
        k = np.nonzero(valid)[0]
        # index triplets in int32 when they fit (scipy's CSR uses int32 then anyway): half the memory
        rr = (row0[k, None, None].astype(idx) + np.arange(ncomp, dtype=idx)[None, :, None])
        cc = (start[k, None, None].astype(idx) + np.arange(w, dtype=idx)[None, None, :])
        rows.append(np.broadcast_to(rr, (len(k), ncomp, w)).ravel())
        cols.append(np.broadcast_to(cc, (len(k), ncomp, w)).ravel())
        vals.append(J[k].ravel())

    blocks = []

    def flush(r0, r1):
        # triplets of rows [r0, r1) -> one CSR block (rows relative to r0)
        if rows:
            ra, ca, va = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
            ra -= r0
        else:
            ra = ca = np.zeros(0, idx)
            va = np.zeros(0)
        rows.clear()
        cols.clear()
        vals.clear()
        blocks.append(sp.csr_matrix((va, (ra, ca)), shape=(r1 - r0, lay.nc)))

    # image observations in chunks of observations: the temporaries (projections, Jacobians, index
    # triplets) are bounded by the chunk, not by the block; each chunk's rows become one CSR block
    chunk = _EVAL_CHUNK if want_jac else _EVAL_CHUNK_RES
    for a in range(0, K, chunk):
        b = min(K, a + chunk)
        nk = b - a
        ii = slice(a, b) if obs is None else obs[a:b]
        vpose, vrig = data.vpose[ii], data.vrig[ii]
        Rm = st.R[vpose]
        tm = st.t[vpose]
        X = st.X[data.pt[ii]]
        Xm = np.einsum("kij,kj->ki", Rm, X) + tm
        isrig = vrig >= 0
        Rr = np.broadcast_to(np.eye(3), (nk, 3, 3)).copy()
        tr = np.zeros((nk, 3))
        if np.any(isrig):
            Rr[isrig] = st.rR[vrig[isrig]]
            tr[isrig] = st.rt[vrig[isrig]]
        Xc = np.einsum("kij,kj->ki", Rr, Xm) + tr
        xy = np.empty((nk, 2))
        Jx = np.empty((nk, 2, 3)) if want_jac else None
        rowbase = 2 * np.arange(a, b)
        sig = data.sig[ii]
        for c, cam in enumerate(pb.cameras):
            sel = np.nonzero(data.cam[ii] == c)[0]
            if not len(sel):
                continue
            camc = cam.with_params(st.cam_params[c]) if not np.array_equal(st.cam_params[c], cam.params) else cam
            if want_jac:
                cc = lay.cam_cols[c]
                free = np.nonzero(cc >= 0)[0]
                # the parameter Jacobian only when some intrinsics are free (same projection either way)
                xyc, jpt, jint = camc.project_jacobian(Xc[sel], params=bool(len(free)))
                xy[sel] = xyc
                Jx[sel] = jpt
                if len(free):
                    Jw = jint[:, :, free] / sig[sel][:, :, None]
                    n = len(sel)
                    rr = rowbase[sel][:, None, None].astype(idx) + np.arange(2, dtype=idx)[None, :, None]
                    ccol = np.broadcast_to(cc[free].astype(idx)[None, None, :], (n, 2, len(free)))
                    rows.append(np.broadcast_to(rr, (n, 2, len(free))).ravel())
                    cols.append(ccol.ravel())
                    vals.append(Jw.ravel())
            else:
                xy[sel] = camc.project(Xc[sel])
        res = (xy - data.xy[ii]) / sig
        r[2 * a : 2 * b] = res.ravel()
        if want_jac:
            Jxw = Jx / sig[:, :, None]
            JxR = Jxw @ Rr  # d/dXm
            # master pose: dXm/dw = -[Rm X]x, dXm/dt = I
            Jw_m = -JxR @ skew(np.einsum("kij,kj->ki", Rm, X))
            pc = lay.pose_col[vpose]
            trip(rowbase, 2, np.concatenate([Jw_m, JxR], axis=2), pc, pc >= 0)
            # rig: dXc/dw_r = -[Rr Xm]x, dXc/dt_r = I
            if np.any(isrig):
                rc = np.where(isrig, lay.rig_col[np.maximum(vrig, 0)], -1)
                Jw_r = -Jxw @ skew(np.einsum("kij,kj->ki", Rr, Xm))
                trip(rowbase, 2, np.concatenate([Jw_r, Jxw], axis=2), rc, rc >= 0)
            Jpt = JxR @ Rm
            slot = lay.point_slot[data.pt[ii]]
            jp[2 * a : 2 * b] = Jpt.reshape(-1, 3)
            pslot[2 * a : 2 * b] = np.repeat(slot, 2)
            pcol = lay.point_col[data.pt[ii]]
            trip(rowbase, 2, Jpt, pcol, pcol >= 0)
        if want_jac:
            flush(2 * a, 2 * b)
    row = 2 * K
    nc_ = len(data.c_pt) if extra else 0
    if nc_:
        X = st.X[data.c_pt]
        r[row : row + 3 * nc_] = ((X - data.c_xyz) / data.c_sig).ravel()
        if want_jac:
            slot = lay.point_slot[data.c_pt]
            eye = np.eye(3)[None] / data.c_sig[:, :, None]
            jp[row : row + 3 * nc_] = eye.reshape(-1, 3)
            pslot[row : row + 3 * nc_] = np.repeat(slot, 3)
            pcol = lay.point_col[data.c_pt]
            trip(row + 3 * np.arange(nc_), 3, eye, pcol, pcol >= 0)
        row += 3 * nc_
    ng = len(data.g_pose) if extra else 0
    if ng:
        R = st.R[data.g_pose]
        t = st.t[data.g_pose]
        lt = data.g_lever - t
        A = np.einsum("kji,kj->ki", R, lt)  # R^T (l - t)
        r[row : row + 3 * ng] = ((A - data.g_xyz) / data.g_sig).ravel()
        if want_jac:
            RT = np.swapaxes(R, 1, 2)
            J = np.concatenate([RT @ skew(lt), -RT], axis=2) / data.g_sig[:, :, None]
            pc = lay.pose_col[data.g_pose]
            trip(row + 3 * np.arange(ng), 3, J, pc, pc >= 0)
        row += 3 * ng
    npl = len(data.pl_k) if extra else 0
    if npl:
        rws = row + np.arange(npl)
        n = st.pn[data.pl_k]
        X = st.X[data.pl_pt]
        r[rws] = (np.einsum("ki,ki->k", n, X) - st.pd[data.pl_k]) / data.pl_sig
        if want_jac:
            slot = lay.point_slot[data.pl_pt]
            jp[rws] = n / data.pl_sig[:, None]
            pslot[rws] = slot
            pcol = lay.point_col[data.pl_pt]
            trip(rws, 1, (n / data.pl_sig[:, None])[:, None, :], pcol, pcol >= 0)
            Bt = np.stack([_tangent_basis(v) for v in st.pn])[data.pl_k] if len(st.pn) else np.zeros((0, 3, 2))
            Jpl = np.concatenate([np.einsum("ki,kij->kj", X, Bt), -np.ones((npl, 1))], axis=1) / data.pl_sig[:, None]
            plc = lay.plane_col[data.pl_k]
            trip(rws, 1, Jpl[:, None, :], plc, plc >= 0)
        row += npl
    nd = len(data.d_a) if extra else 0
    if nd:
        diff = st.X[data.d_a] - st.X[data.d_b]
        L = np.linalg.norm(diff, axis=1)
        r[row : row + nd] = (L - data.d_len) / data.d_sig
        if want_jac:
            u = (diff / L[:, None] / data.d_sig[:, None])[:, None, :]
            rws = row + np.arange(nd)
            for pts_, sgn in ((data.d_a, 1.0), (data.d_b, -1.0)):
                pcol = lay.point_col[pts_]
                trip(rws, 1, sgn * u, pcol, pcol >= 0)
        row += nd
    na = len(data.a_pose) if extra else 0
    if na:
        # attitude priors: e = log(R R_obs^T); with R <- exp([dw]x) R, de = J_l^-1(e) dw
        e = axis_angles(st.R[data.a_pose] @ np.swapaxes(data.a_R, 1, 2))
        r[row : row + 3 * na] = (e / data.a_sig).ravel()
        if want_jac:
            J = np.concatenate([_so3_left_jacobian_inv(e), np.zeros((na, 3, 3))], axis=2) / data.a_sig[:, :, None]
            pc = lay.pose_col[data.a_pose]
            trip(row + 3 * np.arange(na), 3, J, pc, pc >= 0)
        row += 3 * na
    if not want_jac:
        return r
    flush(2 * K, m)
    Jc = blocks[0] if len(blocks) == 1 else sp.vstack(blocks, format="csr")
    return r, Jc, jp, pslot


def _so3_left_jacobian_inv(e: np.ndarray) -> np.ndarray:
    """Inverse left Jacobian of SO(3) at rotation vectors ``e`` (K, 3) -> (K, 3, 3):
    ``I - [e]x / 2 + (1/θ² - (1 + cos θ) / (2 θ sin θ)) [e]x²`` (1/12 as θ -> 0)."""
    th = np.linalg.norm(e, axis=1)
    small = th < 1e-6
    ts = np.where(small, 1.0, th)
    c = np.where(small, 1.0 / 12.0, 1.0 / ts**2 - (1.0 + np.cos(ts)) / (2.0 * ts * np.sin(ts)))
    S = skew(e)
    return np.eye(3)[None] - 0.5 * S + c[:, None, None] * (S @ S)


#: image observations per piece of :func:`_robust` (its temporaries: ~80 B per observation of a piece)
_ROBUST_CHUNK = 65536


def _robust(r, K, opt: SolverOptions, weights: bool = True):
    """Per-row sqrt weights and the robust cost 1/2 sum rho (weights None when not ``weights``: a trial
    step needs only the cost).

    The per-observation terms are computed in pieces of ``_ROBUST_CHUNK`` observations (element by element:
    the same values as over the whole block) into one array, summed once as before."""
    if opt.loss is Loss.TRIVIAL or K == 0:
        # unit weights as a read-only broadcast (16 B per observation less; nothing writes into the weights)
        return (np.broadcast_to(1.0, r.shape) if weights else None), 0.5 * float(r @ r)
    w = np.ones_like(r) if weights else None
    c2 = opt.loss_scale**2
    rho = np.empty(K)
    for a in range(0, K, _ROBUST_CHUNK):
        b = min(K, a + _ROBUST_CHUNK)
        s = r[2 * a : 2 * b].reshape(b - a, 2)
        s = np.sum(s * s, axis=1)
        if opt.loss is Loss.HUBER:
            big = s > c2
            rho[a:b] = np.where(big, 2.0 * np.sqrt(c2 * s) - c2, s)
            d1 = np.where(big, np.sqrt(c2 / np.maximum(s, 1e-300)), 1.0)
        else:
            rho[a:b] = c2 * np.log1p(s / c2)
            d1 = 1.0 / (1.0 + s / c2)
        if weights:
            w[2 * a : 2 * b] = np.repeat(np.sqrt(d1), 2)
    rest = r[2 * K :]
    return w, 0.5 * (float(np.sum(rho)) + float(rest @ rest))


class _Normal:
    """Normal-equation pieces at one linearisation (whitened, robust-weighted)."""

    def __init__(self, r, jac: list, pslot, lay: _Layout, w, threads: int = 1):
        """``jac = [Jc, jp]`` of :func:`_evaluate`; the list is emptied so that the unweighted Jacobian is freed
        as soon as its weighted copy exists (when the caller holds no other reference). ``threads``: for the
        products ``J_c^T J_c`` and ``H B^T`` (:func:`_csr_product`; the same values with any count)."""
        self.lay = lay
        m = len(r)
        rw = r * w
        Jc, jp = jac
        jac.clear()
        if lay.nc and np.any(w != 1.0):
            # (= ``sp.diags(w) @ Jc``: the same kernel on the same CSR operands, without the symbolic count)
            Jcw = _csr_product(sp.diags(w).tocsr(), Jc, int(np.max(np.diff(Jc.indptr), initial=0)), threads)
        else:
            Jcw = Jc
        del Jc
        jpw = jp * w[:, None]
        del jp
        has = pslot >= 0
        self.has = has
        prow = np.nonzero(has)[0]
        npf = lay.npf
        self.Jc = Jcw
        self.threads = threads
        self.U = _gram(Jcw, threads) if lay.nc else np.zeros((0, 0))
        self.gc = Jcw.T @ rw if lay.nc else np.zeros(0)
        # point side
        ps = pslot[prow]
        jpp = jpw[prow]
        V = np.zeros((npf, 9))
        gp = np.zeros((npf, 3))
        for k in range(9):  # one product column at a time (no (rows, 9) array of outer products)
            V[:, k] = np.bincount(ps, weights=jpp[:, k // 3] * jpp[:, k % 3], minlength=npf)
        for k in range(3):
            gp[:, k] = np.bincount(ps, weights=jpp[:, k] * rw[prow], minlength=npf)
        self.V = V.reshape(npf, 3, 3)
        self.gp = gp
        colsp = (3 * ps[:, None] + np.arange(3)).ravel()
        rowsp = np.repeat(prow, 3)
        self.Jp = sp.csr_matrix((jpp.ravel(), (rowsp, colsp)), shape=(m, 3 * npf))
        # B = J_c^T J_p: scipy's product is CSC, whose arrays are B^T in CSR (rows in the kernel's order); H B^T
        # takes them as they are (each row of B^T holds a column at most once, so the order of a row changes
        # only the order in which H B^T stores its entries, not their values)
        Bcsc = Jcw.T @ self.Jp if lay.nc else None
        self.B = Bcsc.tocsr() if lay.nc else sp.csr_matrix((0, 3 * npf))
        self._Bt = sp.csr_matrix((Bcsc.data, Bcsc.indices, Bcsc.indptr), shape=(3 * npf, lay.nc)) \
            if lay.nc and sp.isspmatrix_csc(Bcsc) else None
        del Bcsc
        self.dU = np.clip(np.diag(self.U), 1e-6, 1e32) if lay.nc else np.zeros(0)
        self.dV = np.clip(np.diagonal(self.V, axis1=1, axis2=2), 1e-6, 1e32)
        self._Bc = None
        # work of the sparse Schur product W V^-1 W^T (sum over point columns of their non-zeros squared);
        # the dense slab product costs nc^2 * 3 npf: sparse wins when each point touches few parameters
        # (survey blocks: ~4 of 32 poses per point)
        col_nnz = np.bincount(self.B.indices, minlength=3 * npf) if lay.nc and npf else np.zeros(0)
        self.sparse_flops = float(np.sum(col_nnz.astype(float) ** 2))
        self.grad_max = max(float(np.max(np.abs(self.gc))) if lay.nc else 0.0, float(np.max(np.abs(gp))) if npf else 0.0)

    def schur(self, lam, want_H=False):
        """Reduced matrix, its rhs and V^-1 blocks for damping lam (0 = undamped); the sparse
        ``H = W V^-1`` too when ``want_H``."""
        npf = self.lay.npf
        Vd = self.V.copy()
        if lam:
            Vd[:, [0, 1, 2], [0, 1, 2]] += lam * self.dV
        if npf:
            try:
                Vinv = np.linalg.inv(Vd)
                ok = np.all(np.isfinite(Vinv))
            except np.linalg.LinAlgError:
                Vinv, ok = None, False
        else:
            Vinv, ok = np.zeros((0, 3, 3)), True
        if not ok:
            return None
        # Fortran order: the Cholesky factorisation then works in place (no copy of the reduced matrix);
        # the values are the same whatever the memory layout
        S = self.U.copy(order="F")
        nc = self.lay.nc
        if lam and nc:
            S[np.diag_indices_from(S)] += lam * self.dU
        rhs = -self.gc.copy()
        H = None
        if nc and npf:
            if want_H or nc * nc * 3 * npf > 5e9 or nc * nc * 3 * npf > 10.0 * self.sparse_flops:
                Vsp = sp.bsr_matrix((Vinv, np.arange(npf), np.arange(npf + 1)), shape=(3 * npf, 3 * npf)).tocsr()
                H = (self.B @ Vsp).tocsr()
                if self._Bt is None:
                    self._Bt = self.B.T.tocsr()
                HB = _csr_product(H, self._Bt, nc, self.threads)
                # subtracted in row blocks: no second dense nc x nc matrix (same values as one subtraction)
                step = max(1, int(4e6 // max(nc, 1)))
                for a in range(0, nc, step):
                    S[a : a + step] -= HB[a : a + step].toarray()
                del HB
                rhs += H @ self.gp.ravel()
            else:
                # dense slabs of points: S -= (B_k V_k^-1) B_k^T with BLAS (small reduced systems)
                if self._Bc is None:
                    self._Bc = self.B.tocsc()
                k = max(1, int(4e6 // (3 * nc)))
                gp = self.gp.ravel()
                for a in range(0, npf, k):
                    b = min(npf, a + k)
                    Bd = self._Bc[:, 3 * a : 3 * b].toarray()
                    Hd = np.einsum("cpi,pij->cpj", Bd.reshape(nc, b - a, 3), Vinv[a:b]).reshape(nc, -1)
                    S -= Hd @ Bd.T
                    rhs += Hd @ gp[3 * a : 3 * b]
        return S, rhs, Vinv, H

    def solve_with(self, cf, Vinv, gc, gp, rhs=None):
        """Solve the (damped) normal equations for gradient (gc, gp) with a factored reduced
        matrix; returns the full step (camera side, then points)."""
        nc, npf = self.lay.nc, self.lay.npf
        if rhs is None:
            rhs = -gc
            if nc and npf:
                rhs = rhs + self.B @ np.einsum("nij,nj->ni", Vinv, gp).ravel()
        dc = np.zeros(0) if isinstance(cf[0], str) else scipy.linalg.cho_solve(cf, rhs, check_finite=False)
        if not npf:
            return dc
        rp = -gp
        if nc:
            rp = rp - (self.B.T @ dc).reshape(npf, 3)
        return np.concatenate([dc, np.einsum("nij,nj->ni", Vinv, rp).ravel()])



#: relative size of the iterative-refinement correction of the camera-side step below which the
#: chunked path keeps the unrefined step (a third pass over the Jacobians would change it by less
#: than this fraction; the old path always refines)
_REFINE_RTOL = 1e-6


# quantiles by the special functions behind scipy.stats' ``norm``, ``chi2`` and ``t`` (whose ``ppf`` is ``_ppf``
# times 1 plus 0 there): the same values without importing scipy.stats (~0.5 s)
def _norm_ppf(q):
    """Quantile of the standard normal distribution (``scipy.stats.norm.ppf``)."""
    return scipy.special.ndtri(q)


def _chi2_ppf(q, df):
    """Quantile of the chi-square distribution with ``df`` degrees of freedom (``scipy.stats.chi2.ppf``)."""
    return 2 * scipy.special.gammaincinv(np.asarray(df) / 2, q)


def _t_ppf(q, df):
    """Quantile of Student's t distribution with ``df`` degrees of freedom (``scipy.stats.t.ppf``)."""
    return scipy.special.stdtrit(df, q)


#: stored entries of the left factor from which :func:`_csr_product` splits its rows over threads
_THREAD_MIN_NNZ = 200_000


def _csr_product(A, B, nnz_row_max: int, threads: int = 1):
    """``A @ B`` for two CSR matrices whose product has at most ``nnz_row_max`` entries per row (e.g. the
    columns of a small result), by scipy's own kernel behind ``@`` (sparsetools ``csr_matmat``, Gustavson's
    algorithm): the same entries in the same order, bit for bit, without scipy's symbolic pass that first
    counts the entries (``csr_matmat_maxnnz``: a third of the time of ``H B^T`` on a survey block, 200 reduced
    parameters and 16 k points). With ``threads`` > 1 and a large ``A``, row ranges of ``A`` (balanced by
    its entries) are multiplied in threads (the kernel releases the GIL; every row of the product is computed
    by the same loop either way, so the values do not depend on the thread count). Falls back to ``A @ B``
    when that kernel cannot be imported or the bound needs 64-bit indices.

    Parameters
    ----------
    A : scipy.sparse.csr_matrix, shape (M, K)
    B : scipy.sparse.csr_matrix, shape (K, N)
    nnz_row_max : int
        Upper bound of the stored entries of one row of the product (``N`` always is one).
    threads : int
        Threads for the row ranges (1: in the calling thread).

    Returns
    -------
    scipy.sparse.csr_matrix, shape (M, N)
    """
    M, N = A.shape[0], B.shape[1]
    try:
        from scipy.sparse._sparsetools import csr_matmat
    except ImportError:  # (a scipy that moved its private kernels)
        return (A @ B).tocsr()
    arrays = (A.indptr, A.indices, B.indptr, B.indices)
    nnz_row_max = max(1, min(int(nnz_row_max), N))
    if not (all(a.dtype == np.int32 for a in arrays) and M * nnz_row_max < 2**31 - 1):
        return (A @ B).tocsr()
    dtype = np.result_type(A.dtype, B.dtype)

    def rows(a, b):
        # rows [a, b) of A @ B: (indptr from 0, indices, values)
        p0, p1 = int(A.indptr[a]), int(A.indptr[b])
        ip = A.indptr[a : b + 1] - np.int32(p0)
        indptr = np.empty(b - a + 1, dtype=np.int32)
        n = max(1, (b - a) * nnz_row_max)
        indices = np.empty(n, dtype=np.int32)
        data = np.empty(n, dtype=dtype)
        csr_matmat(b - a, N, ip, A.indices[p0:p1], A.data[p0:p1], B.indptr, B.indices, B.data, indptr, indices, data)
        k = int(indptr[-1])
        return indptr, indices[:k], data[:k]

    nt = max(1, min(int(threads), M))
    if nt == 1 or A.nnz < _THREAD_MIN_NNZ:
        parts = [rows(0, M)]
    else:
        from concurrent.futures import ThreadPoolExecutor

        cuts = np.searchsorted(A.indptr, np.arange(1, nt) * (A.nnz / nt))
        bounds = np.unique(np.concatenate([[0], np.clip(cuts, 0, M), [M]]))
        with ThreadPoolExecutor(max_workers=nt) as ex:
            parts = list(ex.map(lambda ab: rows(*ab), zip(bounds[:-1], bounds[1:])))
    if len(parts) == 1:
        indptr, indices, data = parts[0]
    else:
        offs = np.cumsum([0] + [int(p[0][-1]) for p in parts[:-1]])
        indptr = np.concatenate([[0]] + [p[0][1:] + np.int32(o) for p, o in zip(parts, offs)]).astype(np.int32)
        indices = np.concatenate([p[1] for p in parts])
        data = np.concatenate([p[2] for p in parts])
    return sp.csr_matrix((data, indices, indptr), shape=(M, N))


def _gram(J, threads: int = 1):
    """``(J.T @ J).toarray()`` for a CSR matrix ``J`` (m, n) with small n, bit for bit as scipy computes it (the
    transpose converted to CSR, the product by :func:`_csr_product`, transposed back as scipy's CSC result
    is): (n, n) dense, C order."""
    n = J.shape[1]
    R = _csr_product(J.T.tocsr(), J, n, threads)  # (scipy: J^T J in CSR arrays, read as CSC, i.e. transposed)
    return np.ascontiguousarray(R.toarray().T)


def _add_sparse(A, M, sign=1.0):
    """``A += sign * M`` for a dense ``A`` and a sparse ``M`` without repeated entries (a sparse product or
    sum, or after ``sum_duplicates``)."""
    M = M.tocoo()
    if M.nnz:
        A[M.row, M.col] += M.data if sign == 1.0 else sign * M.data


class _SparseSum:
    """Sum of sparse ``nc x nc`` matrices (the chunks' Schur complements ``W_p V_p^-1 W_p^T``), kept as a list of
    COO parts merged into one CSR matrix whenever the parts hold more than ``_SPARSE_MERGE`` entries (memory
    bounded by the result and one batch, cost ~ one merge per batch instead of one sparse sum per chunk)."""

    def __init__(self, n):
        self.n = n
        self.S = sp.csr_matrix((n, n))
        self.parts = []
        self.size = 0

    def add(self, M):
        M = M.tocoo()
        if M.nnz:
            self.parts.append((M.row.astype(np.int32), M.col.astype(np.int32), M.data))
            self.size += M.nnz
        if self.size > _SPARSE_MERGE:
            self._merge()

    def _merge(self):
        if self.parts:
            r, c, v = (np.concatenate(x) for x in zip(*self.parts))
            self.parts.clear()
            self.size = 0
            self.S = (self.S + sp.csr_matrix((v, (r, c)), shape=(self.n, self.n))).tocsr()

    def total(self):
        self._merge()
        self.S.sum_duplicates()
        return self.S


#: entries of the chunks' Schur complements gathered before they are merged into the sparse sum (16 B each)
_SPARSE_MERGE = 1 << 18


def _add_diagonal(S, d):
    """``S + diag(d)`` for a sparse (returned in the same format) or dense (modified in place) square matrix."""
    if sp.issparse(S):
        return (S + sp.diags(d, format=S.format)).asformat(S.format)
    S[np.diag_indices_from(S)] += d
    return S


class _SparseFactor:
    """Factor of a sparse symmetric positive definite matrix: SuperLU with a symmetric fill-reducing ordering
    (minimum degree on ``A^T + A``) and diagonal pivots (``SymmetricMode``, pivot threshold 0), i.e. ``P A P^T =
    L D L^T`` stored as ``L U``; positive definiteness is checked on the pivots (``U``'s diagonal), as a
    Cholesky factorisation would fail."""

    def __init__(self, S):
        import scipy.sparse.linalg as spla

        self.lu = spla.splu(sp.csc_matrix(S), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                            options=dict(SymmetricMode=True))
        piv = self.lu.U.diagonal()
        if not (np.all(np.isfinite(piv)) and np.all(piv > 0)):
            raise np.linalg.LinAlgError("reduced camera matrix not positive definite")
        self.n = S.shape[0]

    def solve(self, b):
        return self.lu.solve(np.asarray(b, dtype=float))


def _factor_solve(cf, b):
    """Solve with the factor of a reduced matrix (:func:`_cho_factor`): dense Cholesky, sparse, or empty."""
    if isinstance(cf, _SparseFactor):
        return cf.solve(b)
    if isinstance(cf[0], str):
        return np.zeros(0)
    return scipy.linalg.cho_solve(cf, b, check_finite=False)


#: image observations per chunk of :class:`_ChunkedNormal` (bounds the temporaries of a chunk's Jacobian, sparse
#: products and Schur contribution: ~3 KB per observation)
_SCHUR_CHUNK = 8192
#: the chunked passes return the heap's free pages to the system every this many chunks
#: (:func:`thermogrammetry._memory.release_free_heap`)
_TRIM_EVERY = 8


def _point_chunks(lay: _Layout, data: _Data):
    """Image observations grouped for :class:`_ChunkedNormal`: ``order`` (K,) sorts them by free point
    (observations of fixed and camera-side points first) and ``chunks`` lists ``(o0, o1, p0, p1)``:
    observations ``order[o0:o1]`` are all those of the free-point slots ``[p0, p1)`` (``p0 = p1 = -1`` for
    the observations without a free point). A chunk holds about ``_SCHUR_CHUNK`` observations, whole points
    only; every free point lies in exactly one chunk (points without image observations too)."""
    cached = getattr(data, "_point_chunks", None)
    if cached is not None:
        return cached
    slot = lay.point_slot[data.pt]
    order = np.argsort(slot, kind="stable")
    if 2 * len(order) < 2**31 - 1:  # held for the whole solve: int32 (4 B per observation less)
        order = order.astype(np.int32)
    n0 = int(np.sum(slot < 0))
    chunks = [(a, min(n0, a + _SCHUR_CHUNK), -1, -1) for a in range(0, n0, _SCHUR_CHUNK)]
    npf = lay.npf
    if npf:
        counts = np.bincount(slot[slot >= 0], minlength=npf)
        cum = np.concatenate([[0], np.cumsum(counts)])
        cuts = np.searchsorted(cum, np.arange(_SCHUR_CHUNK, cum[-1], _SCHUR_CHUNK), side="left")
        bounds = np.unique(np.concatenate([[0], cuts, [npf]]))
        chunks += [(n0 + int(cum[p0]), n0 + int(cum[p1]), int(p0), int(p1)) for p0, p1 in zip(bounds[:-1], bounds[1:])]
    data._point_chunks = (order, chunks)
    return data._point_chunks


class _ChunkedNormal:
    """The reduced camera system built chunk by chunk, without the block's Jacobian.

    Same normal equations as :class:`_Normal` (``U, W, V``, gradient, damping ``lam D``) but the image
    observations are evaluated in chunks of whole points (:func:`_point_chunks`); each chunk's
    Jacobian gives its share of ``U``, ``g_c``, the point blocks ``V_p``, ``g_p`` and of the Schur
    complement ``W_p (V_p + lam D_p)^-1 W_p^T`` and is dropped. Kept: ``U`` and the reduced matrix
    (dense ``nc x nc``), ``V``, ``V^-1`` (3x3 per free point) and the Jacobian of the few rows that are
    not image observations (control, GNSS, planes, distances). Memory is independent of the number of
    image observations beyond their residuals; the price is a second pass over the Jacobians for the
    back-substitution of the point steps (and one more pass per rejected LM step, whose new damping
    changes the Schur complement).

    Parameters
    ----------
    r, w : (m,) arrays
        Whitened residuals at ``st`` (:func:`_evaluate`) and the robust square-root weights (:func:`_robust`).
    lam : float
        Damping of the first reduced system (built in the same pass as ``U``, ``V`` and the gradient).
    """

    def __init__(self, pb, lay: _Layout, st: _State, data: _Data, r, w, lam: float):
        self.pb, self.lay, self.st, self.data = pb, lay, st, data
        self.r, self.w = r, w
        self.order, self.chunks = _point_chunks(lay, data)
        nc, npf = lay.nc, lay.npf
        K = data.K
        # rows other than image observations: small, evaluated and kept once per linearisation
        _, Je, jpe, pse = _evaluate(pb, lay, st, data, True, sel=np.zeros(0, dtype=np.int64), extra=True)
        we = w[2 * K :]
        rwe = r[2 * K :] * we
        if nc and np.any(we != 1.0):
            Je = (sp.diags(we) @ Je).tocsr()
        jpe = jpe * we[:, None]
        has = pse >= 0
        prow = np.nonzero(has)[0]
        ps = pse[prow]
        jpp = jpe[prow]
        # U is block sparse (6x6 per pose, intrinsics and rig rows): kept sparse, only S is dense
        self.U = (Je.T @ Je).tocsr() if nc else sp.csr_matrix((0, 0))
        self.gc = np.zeros(nc)
        if nc:
            self.gc += Je.T @ rwe
        V = np.zeros((npf, 9))
        gp = np.zeros((npf, 3))
        for k in range(9):
            V[:, k] = np.bincount(ps, weights=jpp[:, k // 3] * jpp[:, k % 3], minlength=npf)
        for k in range(3):
            gp[:, k] = np.bincount(ps, weights=jpp[:, k] * rwe[prow], minlength=npf)
        self.V = V.reshape(npf, 3, 3)
        self.gp = gp
        Jpe = sp.csr_matrix((jpp.ravel(), (np.repeat(prow, 3), (3 * ps[:, None] + np.arange(3)).ravel())),
                            shape=(len(pse), 3 * npf))
        self.Be = (Je.T @ Jpe).tocsc() if nc else sp.csc_matrix((0, 3 * npf))
        self.Vinv = np.zeros((npf, 3, 3))
        self.dV = np.zeros((npf, 3))
        first = self._pass(lam, build=True)
        self.dU = np.clip(self.U.diagonal(), 1e-6, 1e32) if nc else np.zeros(0)
        if first is not None and lam and nc:
            first = (_add_diagonal(first[0], lam * self.dU),) + first[1:]
        self._first = (lam, first)  # handed out (once) by schur(lam)
        self.grad_max = max(float(np.max(np.abs(self.gc))) if nc else 0.0, float(np.max(np.abs(gp))) if npf else 0.0)

    def _chunk(self, o0, o1, p0, p1):
        """Robust-weighted camera-side Jacobian (CSR), point Jacobian as CSR over the chunk's point
        columns ``3 (p - p0) + j`` (or None), and weighted residuals of one chunk."""
        idx = self.order[o0:o1]
        _, Jc, jp, pslot = _evaluate(self.pb, self.lay, self.st, self.data, True, sel=idx, extra=False)
        rows = (2 * idx[:, None] + np.arange(2)).ravel()
        wk = self.w[rows]
        rw = self.r[rows] * wk
        if self.lay.nc and np.any(wk != 1.0):
            Jc = (sp.diags(wk) @ Jc).tocsr()
        if p0 < 0:
            return Jc, None, None, rw
        jp = jp * wk[:, None]
        ls = pslot - p0
        Jp = sp.csr_matrix((jp.ravel(), (np.repeat(np.arange(len(ls)), 3), (3 * ls[:, None] + np.arange(3)).ravel())),
                           shape=(len(ls), 3 * (p1 - p0)))
        return Jc, Jp, (jp, ls), rw

    def _pass(self, lam, build):
        """One pass over the chunks: (when ``build``) ``U``, ``g_c``, ``V``, ``g_p``, and the damped
        Schur complement ``S`` (without ``lam dU``, added by the caller), its right-hand side and ``V^-1``.
        None when a damped point block is singular."""
        nc = self.lay.nc
        acc = _SparseSum(nc)  # accumulates W V^-1 W^T (sparse), turned into U - W V^-1 W^T at the end
        rhs = np.zeros(nc)
        ok = True
        for ci, (o0, o1, p0, p1) in enumerate(self.chunks):
            if ci % _TRIM_EVERY == _TRIM_EVERY - 1:
                release_free_heap()  # the chunks' freed temporaries lie between live blocks: pages back
            if o1 > o0:
                Jc, Jp, jpl, rw = self._chunk(o0, o1, p0, p1)
                if build and nc:
                    self.U = (self.U + Jc.T @ Jc).tocsr()
                    self.gc += Jc.T @ rw
            else:
                Jc = Jp = jpl = None
            if p0 < 0:
                continue
            n = p1 - p0
            if build and jpl is not None:
                jp, ls = jpl
                V = self.V[p0:p1].reshape(n, 9)
                for k in range(9):
                    V[:, k] += np.bincount(ls, weights=jp[:, k // 3] * jp[:, k % 3], minlength=n)
                for k in range(3):
                    self.gp[p0:p1, k] += np.bincount(ls, weights=jp[:, k] * rw, minlength=n)
            if build:
                self.dV[p0:p1] = np.clip(np.diagonal(self.V[p0:p1], axis1=1, axis2=2), 1e-6, 1e32)
            Vd = self.V[p0:p1].copy()
            if lam:
                Vd[:, [0, 1, 2], [0, 1, 2]] += lam * self.dV[p0:p1]
            try:
                Vinv = np.linalg.inv(Vd)
            except np.linalg.LinAlgError:
                ok = False
                if build:
                    continue  # U, V and the gradient are still completed
                return None
            if not np.all(np.isfinite(Vinv)):
                ok = False
                if build:
                    continue
                return None
            self.Vinv[p0:p1] = Vinv
            if not nc:
                continue
            B = self.Be[:, 3 * p0 : 3 * p1]
            if Jc is not None:
                B = B + Jc.T @ Jp
            B = B.tocsr()
            Vsp = sp.bsr_matrix((Vinv, np.arange(n), np.arange(n + 1)), shape=(3 * n, 3 * n)).tocsr()
            H = (B @ Vsp).tocsr()
            acc.add(H @ B.T)
            rhs += H @ self.gp[p0:p1].ravel()
        if not ok:
            return None
        release_free_heap()  # (the last chunks' temporaries: not yet returned by the trim every _TRIM_EVERY chunks)
        if build:
            self.U.sum_duplicates()
        S = (self.U - acc.total()).tocsc()
        del acc
        rhs -= self.gc
        return S, rhs, self.Vinv

    def schur(self, lam, want_H=False):
        """Reduced matrix (sparse, CSC: camera-camera blocks only where cameras share points), its right-hand
        side and ``V^-1`` for the damping ``lam`` (a new pass over the Jacobians unless it is the first reduced system of this
        linearisation); None when a damped point block is singular."""
        if want_H:
            raise ValueError("the chunked normal equations do not keep W V^-1 (memory per observation)")
        if self._first is not None and lam == self._first[0]:
            out = self._first[1]
            self._first = None
        else:
            self._first = None
            out = self._pass(lam, build=False)
            if out is not None and lam and self.lay.nc:
                out = (_add_diagonal(out[0], lam * self.dU),) + out[1:]
        if out is None:
            return None
        S, rhs, Vinv = out
        return S, rhs, Vinv, None

    def _back(self, dc, Vinv, refine_lam=None):
        """Point steps ``dp = V^-1 (-g_p - W^T dc)`` (one pass over the Jacobians); with ``refine_lam``
        also ``W dp`` for the camera-side residual of the full damped system."""
        nc, npf = self.lay.nc, self.lay.npf
        dp = np.zeros((npf, 3))
        ye = (self.Be.T @ dc).reshape(npf, 3) if nc else np.zeros((npf, 3))
        Wdp = np.zeros(nc)
        for ci, (o0, o1, p0, p1) in enumerate(self.chunks):
            if ci % _TRIM_EVERY == _TRIM_EVERY - 1:
                release_free_heap()
            if p0 < 0:
                continue
            n = p1 - p0
            y = ye[p0:p1].copy()
            if o1 > o0 and nc:
                Jc, Jp, (jp, ls), _ = self._chunk(o0, o1, p0, p1)
                Jdc = Jc @ dc
                for k in range(3):
                    y[:, k] += np.bincount(ls, weights=jp[:, k] * Jdc, minlength=n)
            else:
                Jc = None
            dpk = np.einsum("nij,nj->ni", Vinv[p0:p1], -self.gp[p0:p1] - y)
            dp[p0:p1] = dpk
            if refine_lam is not None and Jc is not None:
                Wdp += Jc.T @ (Jp @ dpk.ravel())
        release_free_heap()  # (the last chunks' temporaries)
        if refine_lam is None:
            return dp, None
        if nc:
            Wdp += self.Be @ dp.ravel()
        return dp, Wdp

    def step(self, cf, Vinv, rhs, lam):
        """The full damped step (camera side, then points) from the factored reduced matrix, with one step
        of iterative refinement of the camera side against ``U + lam dU`` and the exact ``W`` (as
        :class:`_Normal`); the refinement's extra pass over the Jacobians is made only when its
        correction exceeds ``_REFINE_RTOL`` of the step."""
        nc, npf = self.lay.nc, self.lay.npf
        dc = _factor_solve(cf, rhs)
        if not npf:
            if nc:
                res = -self.gc - self.U @ dc - lam * self.dU * dc
                if np.all(np.isfinite(res)) and np.linalg.norm(res) > 1e-14 * np.linalg.norm(self.gc):
                    dc = dc + _factor_solve(cf, res)
            return dc
        if not nc:
            dp, _ = self._back(dc, Vinv)
            return dp.ravel()
        dp, Wdp = self._back(dc, Vinv, refine_lam=lam)
        res = -self.gc - self.U @ dc - lam * self.dU * dc - Wdp
        if np.all(np.isfinite(res)):
            corr = _factor_solve(cf, res)
            if np.linalg.norm(corr) > _REFINE_RTOL * np.linalg.norm(dc):
                dc = dc + corr
                dp, _ = self._back(dc, Vinv)
        return np.concatenate([dc, dp.ravel()])


def _symmetrised(A):
    """``0.5 (A + A^T)`` with one temporary instead of two (same values)."""
    B = A + A.T
    del A
    B *= 0.5
    return B


def _symmetrise_inplace(A, step=512):
    """``A <- 0.5 (A + A^T)`` in place, by blocks of rows and columns (no nc x nc temporary)."""
    n = A.shape[0]
    for a in range(0, n, step):
        b = min(n, a + step)
        blk = A[a:b, a:b]
        A[a:b, a:b] = 0.5 * (blk + blk.T)
        if b < n:
            m = 0.5 * (A[a:b, b:] + A[b:, a:b].T)
            A[a:b, b:] = m
            A[b:, a:b] = m.T


def _spd_inverse_inplace(S):
    """Inverse of a symmetric positive definite matrix by Cholesky (LAPACK potrf + potri), in the memory of
    ``S`` when it is in Fortran order (``S`` is then overwritten); the full symmetric inverse is returned.

    Falls back to ``numpy.linalg.inv`` (symmetrised) when the Cholesky factorisation fails (not positive
    definite in floating point); ``S`` is restored first (potrf and potri only write the upper triangle)."""
    n = S.shape[0]
    diag = np.diag(S).copy()
    lapack = scipy.linalg.lapack
    c, info = lapack.dpotrf(S, lower=0, clean=0, overwrite_a=1)
    if info == 0:
        c, info = lapack.dpotri(c, lower=0, overwrite_c=1)
    if info != 0:
        A = c if np.shares_memory(c, S) else S
        for a in range(0, n, 512):  # upper triangle back from the untouched lower one
            b = min(n, a + 512)
            blk = A[a:b, a:b]
            A[a:b, a:b] = np.tril(blk) + np.tril(blk, -1).T
            if b < n:
                A[a:b, b:] = A[b:, a:b].T
        A[np.diag_indices(n)] = diag
        return _symmetrised(np.linalg.inv(A))
    for a in range(0, n, 512):  # lower triangle from the upper one
        b = min(n, a + 512)
        blk = c[a:b, a:b]
        c[a:b, a:b] = np.triu(blk) + np.triu(blk, 1).T
        if b < n:
            c[b:, a:b] = c[a:b, b:].T
    return c


def _sparse_rank_test(Sn, tol):
    """Rank test of a Jacobi-scaled sparse reduced matrix without forming it dense: None when its smallest
    eigenvalue is above ``tol`` times its largest (as the dense test with all eigenvalues), otherwise
    ``(condition, indices of the 4 largest components of the null direction)``.

    The largest eigenvalue by Lanczos on ``Sn``, the smallest as the inverse of the largest of ``Sn^-1`` (Lanczos
    on solves with the sparse factor, which also gives the null direction), both to a relative 1e-8 (the test
    compares their ratio with ``tol``, 1e-12 by default). A matrix whose factorisation fails (no positive
    pivots) is deficient; its null direction then comes from the dense eigen decomposition (an error case
    only)."""
    import scipy.sparse.linalg as spla

    n = Sn.shape[0]
    if n == 0:
        return None
    v0 = np.ones(n) / np.sqrt(n)  # deterministic start
    try:
        f = _SparseFactor(Sn)
    except (np.linalg.LinAlgError, RuntimeError, ValueError):
        f = None
    if f is not None and n <= 2:
        f = None  # (Lanczos needs n > k + 1: tiny systems go the dense way)
    if f is not None:
        try:
            lmax = float(spla.eigsh(Sn, k=1, which="LA", v0=v0, tol=1e-8, return_eigenvectors=False)[0])
            inv = spla.LinearOperator((n, n), matvec=f.solve, dtype=float)
            mu, vec = spla.eigsh(inv, k=1, which="LA", v0=v0, tol=1e-8)
        except spla.ArpackError:
            f = None
    if f is None:
        ev, evec = np.linalg.eigh(Sn.toarray())
        if ev[0] > tol * ev[-1]:
            return None
        return ev[-1] / max(ev[0], 1e-300), np.argsort(-np.abs(evec[:, 0]))[:4]
    lmin = 1.0 / float(mu[0]) if mu[0] > 0 else 0.0
    if lmin > tol * lmax:
        return None
    return lmax / max(lmin, 1e-300), np.argsort(-np.abs(vec[:, 0]))[:4]


def _tangent_basis(n):
    """(3, 2) orthonormal basis of the plane orthogonal to the unit vector n (deterministic)."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(n, u)], axis=1)


def _cho_factor(S):
    """Cholesky factor of the reduced matrix, computed in place when ``S`` is in Fortran order (``S`` is
    then overwritten: the callers do not use it afterwards); a :class:`_SparseFactor` when ``S`` is sparse
    (chunked path). None when ``S`` is not positive definite."""
    if S.shape[0] == 0:
        return ("empty",)
    if sp.issparse(S):
        try:
            return _SparseFactor(S)
        except (np.linalg.LinAlgError, RuntimeError, ValueError):
            return None
    try:
        cf = scipy.linalg.cho_factor(S, check_finite=False, overwrite_a=S.flags.f_contiguous)
    except (np.linalg.LinAlgError, ValueError):
        return None
    if not np.all(np.isfinite(cf[0])):
        return None
    return cf


def _lm(pb, lay, st, data, opt: SolverOptions):
    """Returns (state, cost0, cost, iterations, termination, reason, last linearisation)."""
    r = _evaluate(pb, lay, st, data, False)
    w, cost = _robust(r, data.K, opt)
    cost0 = cost
    if not np.isfinite(cost):
        return st, cost0, cost, 0, Termination.NUMERICAL_FAILURE, "initial residuals are not finite"
    radius = opt.initial_trust_region_radius
    decrease = 2.0
    it = 0
    need = True
    chunked = data.K >= opt.chunked_min_observations
    while True:
        if need:
            # the previous linearisation (and the factor of its reduced matrix) is released before the next is built
            ne = cf = Vinv = rhs = None
            data.linearisation = None
            if chunked:
                release_free_heap()  # (the previous linearisation's pages)
                # r, w, cost: of the current state (from the start or the accepted trial step)
                ne = _ChunkedNormal(pb, lay, st, data, r, w, 1.0 / radius)
            else:
                r, *jac, pslot = _evaluate(pb, lay, st, data, True)
                w, cost = _robust(r, data.K, opt)
                ne = _Normal(r, jac, pslot, lay, w, opt.num_threads)  # takes the Jacobian over (weighted, sparse)
                data.linearisation = (st, r, w, ne)
            need = False
            if ne.grad_max <= opt.gradient_tolerance:
                return st, cost0, cost, it, Termination.CONVERGED, f"gradient tolerance reached (max|g| = {ne.grad_max:.3g})"
        if it >= opt.max_iterations:
            return st, cost0, cost, it, Termination.MAX_ITERATIONS, f"stopped after {it} iterations"
        it += 1
        lam = 1.0 / radius
        cf = Vinv = rhs = None  # (a rejected step's factor: released before the next reduced matrix is built)
        sch = ne.schur(lam)
        ok = sch is not None
        if ok:
            S, rhs, Vinv, _ = sch
            del sch
            cf = _cho_factor(S)  # overwrites S
            del S
            ok = cf is not None
        if ok:
            D = np.concatenate([ne.dU, ne.dV.ravel()])
            g = np.concatenate([ne.gc, ne.gp.ravel()])
            if chunked:
                d = ne.step(cf, Vinv, rhs, lam)
            else:
                d = ne.solve_with(cf, Vinv, ne.gc, ne.gp, rhs)
                # one step of iterative refinement against the exact operator J^T J + lam D: forming
                # S = U - W V^-1 W^T cancels digits when parameters are nearly dependent
                Jd = ne.Jc @ d[: lay.nc] + ne.Jp @ d[lay.nc :] if lay.nc else ne.Jp @ d
                Ad = np.concatenate([ne.Jc.T @ Jd, ne.Jp.T @ Jd]) + lam * D * d
                res = -g - Ad
                if np.all(np.isfinite(res)) and np.linalg.norm(res) > 1e-14 * np.linalg.norm(g):
                    d = d + ne.solve_with(cf, Vinv, -res[: lay.nc], -res[lay.nc :].reshape(-1, 3))
            ok = bool(np.all(np.isfinite(d)))
        if ok:
            dc, dp = d[: lay.nc], d[lay.nc :]
            model = 0.5 * (-(g @ d) + lam * float(D @ (d * d)))
            if 0 <= model <= opt.function_tolerance * cost:
                return st, cost0, cost, it, Termination.CONVERGED, "predicted decrease below the function tolerance"
            xn = np.sqrt(sum(float(p @ p) for p in st.cam_params) + float(np.sum(st.t**2)) + float(np.sum(st.X**2)))
            dn = float(np.sqrt(d @ d))
            if dn <= opt.parameter_tolerance * (xn + opt.parameter_tolerance):
                return st, cost0, cost, it, Termination.CONVERGED, f"parameter tolerance reached (|dx| = {dn:.3g})"
            st_new = st.plus(lay, dc, dp)
            try:
                r_new = _evaluate(pb, lay, st_new, data, False)
            except InvalidInputError:
                # the step left the camera model's domain (e.g. a focal length <= 0): rejected like a step
                # that increases the cost, so the trust region shrinks
                r_new = None
            if r_new is None:
                cost_new, rho, ok = float("inf"), -1.0, False
            else:
                _, cost_new = _robust(r_new, data.K, opt, weights=False)  # (weights only if accepted)
                rho = (cost - cost_new) / model if model > 0 else -1.0
                ok = bool(np.isfinite(cost_new)) and rho > 1e-3
        if ok:
            change = cost - cost_new
            st, cost = st_new, cost_new
            r = r_new
            del r_new
            if chunked:
                # the accepted step's linearisation is rebuilt below: the old one (its residuals, weights, point
                # blocks) and the factor are released before the new weights are computed
                ne = cf = Vinv = rhs = sch = None
                d = dc = dp = st_new = None
            # the chunked path linearises at these residuals; the full path re-evaluates them with the Jacobian
            w = _robust(r, data.K, opt)[0] if chunked else None
            radius = min(1e16, radius / max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3))
            decrease = 2.0
            need = True
            if abs(change) <= opt.function_tolerance * (cost + change):
                return st, cost0, cost, it, Termination.CONVERGED, "function tolerance reached"
        else:
            radius /= decrease
            decrease *= 2.0
            if radius < 1e-32:
                return st, cost0, cost, it, Termination.CONVERGED, "trust region collapsed: no further decrease possible"


def _scale_observed(pb) -> bool:
    """Whether the observations fix the scale of a free network: observed distances, or a fixed rig with a
    non-zero baseline that some rig view uses (its ``t_rel`` is a length in object units)."""
    if len(pb.distance_observations()[0]):
        return True
    used = {r for r in pb.view_rig if r >= 0}
    return any(pb.rig_fixed[r] and np.linalg.norm(pb.rig_t[r]) > 0 for r in used)


def _gauge_basis(pb, lay, st):
    """Null-space basis G (n, 7) of a free network (3 translations, 3 rotations, scale) and the
    selector E (rows of the free points)."""
    n = lay.nc + 3 * lay.npf
    G = np.zeros((n, 7))
    for p in range(len(st.R)):
        c = lay.pose_col[p]
        if c < 0:
            continue
        R, t = st.R[p], st.t[p]
        G[c + 3 : c + 6, 0:3] = -R  # world translation dX: dt = -R dX
        G[c : c + 3, 3:6] = -R  # world rotation dth: dw = -R dth
        G[c + 3 : c + 6, 6] = t  # scale: dt = s t
    for r in range(len(st.rR)):
        c = lay.rig_col[r]
        if c >= 0:
            G[c + 3 : c + 6, 6] = st.rt[r]
    E = np.zeros_like(G)
    rows_pts = [(slice(base_ + 3 * k, base_ + 3 * k + 3), p) for base_, plist in ((lay.nc, lay.free_points),) for k, p in enumerate(plist)]
    rows_pts += [(slice(int(lay.point_col[p]), int(lay.point_col[p]) + 3), p) for p in lay.cs_points]
    for rows, p in rows_pts:
        Xp = st.X[p]
        G[rows, 0:3] = np.eye(3)
        G[rows, 3:6] = -skew(Xp)
        G[rows, 6] = Xp
        E[rows] = G[rows]
    for k in range(len(st.pn)):
        c = lay.plane_col[k]
        if c < 0:
            continue
        n, d = st.pn[k], st.pd[k]
        Bt = _tangent_basis(n)
        G[c : c + 2, 3:6] = -Bt.T @ skew(n)  # rotation dth: dn = dth x n
        G[c + 2, 0:3] = n  # translation dX: dd = n . dX
        G[c + 2, 6] = d  # scale: dd = s d
    if _scale_observed(pb):  # observed distances or a fixed rig baseline define the scale
        G, E = G[:, :6], E[:, :6]
    return G, E


def solve(problem: BundleProblem, options: SolverOptions | None = None) -> AdjustmentResult:
    """Adjust a :class:`BundleProblem`; see the module docstring for what is reported.

    Never raises for numerical trouble: too few observations, an undefined datum (rank
    deficiency), non-finite residuals or non-convergence come back as a result whose
    ``termination`` and ``reason`` say so.
    """
    from ._threads import blas_single_thread

    opt = options or SolverOptions()
    if not isinstance(problem, BundleProblem):
        raise InvalidInputError(f"problem: expected a BundleProblem, got {type(problem).__name__}")
    with blas_single_thread(), np.errstate(all="ignore"):
        return _solve(problem, opt)


def _world_offset(pb: BundleProblem) -> np.ndarray:
    """A local origin for the solve: mean of the projection centres and points (georeferenced
    coordinates of ~1e6 m would otherwise couple rotations and translations numerically)."""
    parts = [np.asarray(pb.points).reshape(-1, 3)]
    if pb.pose_R:
        R = np.array(pb.pose_R)
        t = np.array(pb.pose_t)
        parts.append(-np.einsum("kji,kj->ki", R, t))
    allp = np.concatenate(parts)
    allp = allp[np.all(np.isfinite(allp), axis=1)]
    return allp.mean(axis=0) if len(allp) else np.zeros(3)


def _shift_world(pb: BundleProblem, s: np.ndarray) -> None:
    """Translate the world frame in place: X -> X + s (poses, points, control, GNSS, planes)."""
    if not np.any(s):
        return
    pb.points = pb.points + s
    pb.pose_t = [t - R @ s for R, t in zip(pb.pose_R, pb.pose_t)]
    pb._ctrl = [(i, xyz + s, sig) for i, xyz, sig in pb._ctrl]
    pb._gnss = [(v, xyz + s, sig, lev) for v, xyz, sig, lev in pb._gnss]
    pb.plane_d = [float(d + n @ s) for n, d in zip(pb.plane_n, pb.plane_d)]


def _solve(problem: BundleProblem, opt: SolverOptions) -> AdjustmentResult:
    t0 = time.perf_counter()
    # the working copy (returned as result.problem) shares the image observations' arrays with the input:
    # nothing modifies them and the copy would cost ~24-56 B per observation. They are concatenated first (the
    # problem's own storage from then on): the solver's data uses the same arrays
    problem.image_observations()
    memo = {id(a): a for o in problem._img for a in (o.camera, o.view, o.point, o.xy, o.sigma)}
    pb = copy.deepcopy(problem, memo)
    origin = _world_offset(pb)
    _shift_world(pb, -origin)
    lay = _Layout(pb)
    K_all = sum(len(o.point) for o in pb._img)  # (without concatenating the observations)
    active = np.ones(K_all, dtype=bool)
    st = _State(pb)
    n = lay.nc + 3 * lay.npf
    defect = (6 if _scale_observed(pb) else 7) if pb.gauge is Gauge.INNER else 0
    warnings: list[str] = []

    def result(term, reason, it, c0, c1, **kw):
        st.write_to(pb)
        _shift_world(pb, origin)
        return AdjustmentResult(term, reason, it, c0, c1, pb, warnings=warnings, time_s=time.perf_counter() - t0, **kw)

    data = _Data(pb, active)
    if data.K >= opt.chunked_min_observations:
        # the per-call observation arrays (dropped when the problem concatenated them) and what the caller freed
        # while building the problem lie in the heap: pages back before the large adjustment's arrays
        release_free_heap()
    red = data.m - n + defect
    if n == 0:
        return result(Termination.TOO_FEW_OBSERVATIONS, "no free parameters", 0, np.nan, np.nan)
    if red < 0:
        return result(
            Termination.TOO_FEW_OBSERVATIONS,
            f"{data.m} observation equations for {n} unknowns (datum defect {defect}): redundancy {red} < 0",
            0,
            np.nan,
            np.nan,
        )
    # free points observed too rarely cannot be determined
    nobs_pt = np.bincount(data.pt, minlength=len(pb.points)) + np.bincount(data.c_pt, minlength=len(pb.points))
    weak = np.concatenate([lay.free_points, lay.cs_points])
    weak = weak[nobs_pt[weak] < 2]
    weak = weak[np.bincount(data.c_pt, minlength=len(pb.points))[weak] == 0]
    if len(weak):
        return result(
            Termination.RANK_DEFICIENT,
            f"{len(weak)} free point(s) seen in fewer than 2 images and without control, e.g. point {int(weak[0])}",
            0,
            np.nan,
            np.nan,
        )
    total_it = 0
    rounds = 0
    cost0 = None
    while True:
        if rounds:  # after a data-snooping round; the first round uses the data built above
            data = None  # released before the next is built
            data = _Data(pb, active)
        st, c0, cost, it, term, reason = _lm(pb, lay, st, data, opt)
        total_it += it
        if cost0 is None:
            cost0 = c0
        if not term.success:
            return result(term, reason, total_it, cost0, cost)
        try:
            out = _precision(pb, lay, st, data, opt, active, warnings)
        except (np.linalg.LinAlgError, scipy.linalg.LinAlgError, FloatingPointError, ValueError) as exc:
            # LAPACK on a reduced matrix with non-finite entries (a weak block): the estimate has no precision
            out = (Termination.NUMERICAL_FAILURE, f"precision step failed: {type(exc).__name__}: {exc}")
        if isinstance(out, tuple):  # failure
            return result(out[0], out[1], total_it, cost0, cost)
        if not (opt.data_snooping and opt.compute_redundancy) or rounds >= opt.max_snooping_rounds:
            break
        w = out.get("image_w")
        if w is None:
            warnings.append("data snooping skipped: no redundancy numbers (covariance not available)")
            break
        k = _norm_ppf(1 - opt.snooping_alpha / 2)
        wmax = np.max(np.nan_to_num(np.abs(w), nan=0.0), axis=1) if len(w) else np.zeros(0)
        cand = np.nonzero(wmax > k)[0]
        if not len(cand):
            break
        cand = cand[np.argsort(-wmax[cand])]
        img = pb.image_observations()
        used_pt, used_view = set(), set()
        reject = []
        for i in cand:
            p, v = int(img.point[i]), int(img.view[i])
            if p in used_pt or v in used_view:
                continue
            used_pt.add(p)
            used_view.add(v)
            reject.append(i)
        active[reject] = False
        rounds += 1
        # a rejection must not leave a free point undetermined
        data_chk = _Data(pb, active)
        cnt = np.bincount(data_chk.pt, minlength=len(pb.points)) + np.bincount(data_chk.c_pt, minlength=len(pb.points))
        lost = lay.free_points[cnt[lay.free_points] < 2]
        if len(lost):
            warnings.append(f"data snooping stopped: rejecting further points would leave point {int(lost[0])} undetermined")
            active[reject] = True
            break
    if rounds:
        warnings.append(f"data snooping rejected {int(np.sum(~active))} image point(s) in {rounds} round(s)")
    if out.get("precision_reason"):
        reason = f"{reason}; {out['precision_reason']}" if reason else out["precision_reason"]
    return result(term, reason, total_it, cost0, cost, **out)


def _precision(pb, lay, st, data, opt, active, warnings):
    # the chunked normal equations give the reduced matrix (enough for the covariance of the camera side);
    # redundancy numbers, point covariances and the free-network covariance need the whole Jacobian
    chunked = data.K >= opt.chunked_min_observations and not (
        opt.compute_covariance and (pb.gauge is Gauge.INNER or opt.compute_redundancy or opt.compute_point_covariance))
    lin, data.linearisation = data.linearisation, None
    if chunked:
        release_free_heap()  # (the LM's freed temporaries)
        r = _evaluate(pb, lay, st, data, False)
        w, cost = _robust(r, data.K, opt)
        # the normal equations (for the covariance) are built after the residual outputs below
    elif lin is not None and lin[0] is st and not opt.compute_redundancy:
        # the LM stopped at the state of its last linearisation (predicted decrease or step below tolerance, or
        # the gradient): the same residuals, weights and normal equations as evaluating them again
        _, r, w, ne = lin
    else:
        r, Jc, jp, pslot = _evaluate(pb, lay, st, data, True)
        w, cost = _robust(r, data.K, opt)
        jac = [Jc, jp]
        del Jc  # the normal equations are built only for the covariance (ne keeps the weighted Jacobian)
        if opt.compute_covariance:
            ne = _Normal(r, jac, pslot, lay, w, opt.num_threads)
        jac.clear()
    del lin
    n = lay.nc + 3 * lay.npf
    defect = (6 if _scale_observed(pb) else 7) if pb.gauge is Gauge.INNER else 0
    red = data.m - n + defect
    rw = r * w
    vtpv = float(np.sum(np.square(rw, out=rw)))  # (the same values as (r w)^2, one temporary)
    del rw
    sigma0 = float(np.sqrt(vtpv / red)) if red > 0 else float("nan")
    out: dict = {"sigma0": sigma0, "redundancy": int(red)}
    if red <= 0:
        why = (f"redundancy {int(red)} <= 0 ({data.m} observation equations for {n} unknowns, datum defect {defect}): "
               "sigma0 is undetermined, every standard deviation is NaN")
        out["precision_reason"] = why
        warnings.append(why)
    K_all = len(active)
    img_res = np.zeros((K_all, 2))
    img_res[data.img_idx] = -r[: 2 * data.K].reshape(-1, 2) * data.sig  # v = observed - computed
    out["image_residuals"] = img_res
    out["rejected"] = ~active
    nc_ = len(data.c_pt)
    out["control_residuals"] = -r[2 * data.K : 2 * data.K + 3 * nc_].reshape(-1, 3) * data.c_sig
    ng = len(data.g_pose)
    g0 = 2 * data.K + 3 * nc_  # GNSS rows (plane and distance rows follow them)
    out["gnss_residuals"] = -r[g0 : g0 + 3 * ng].reshape(-1, 3) * data.g_sig if ng else np.zeros((0, 3))
    na = len(data.a_pose)
    a0 = data.m - 3 * na  # attitude rows are the last
    out["attitude_residuals"] = -r[a0 : a0 + 3 * na].reshape(-1, 3) * data.a_sig if na else np.zeros((0, 3))
    if red > 0:
        stat = red * sigma0**2 / opt.sigma0_prior**2
        lo, hi = _chi2_ppf(np.array([0.025, 0.975]), red)
        out["chi2"] = dict(statistic=stat, dof=int(red), lower=float(lo), upper=float(hi), passed=bool(lo <= stat <= hi))
    if not opt.compute_covariance:
        return out
    if chunked:
        # (the chunked path never computes redundancy numbers: r and w are needed only by ne, which holds them
        # until it is released below)
        ne = _ChunkedNormal(pb, lay, st, data, r, w, 0.0)
        r = w = None
    sch = ne.schur(0.0, want_H=not chunked)
    if sch is None:
        return (Termination.RANK_DEFICIENT, "a free point's normal block is singular (too few or parallel rays)")
    S, _, Vinv, H = sch
    del sch
    ne.U = None  # not needed any more (dense nc x nc)
    if pb.gauge is not Gauge.INNER and not opt.compute_redundancy:
        # the Jacobians and B (~0.6 KB per image observation) serve only the inner-constraint covariance and the
        # redundancy numbers: released before the nc x nc work (eigenvalues, inverse, covariance, correlation)
        ne = None
        if not opt.compute_point_covariance:
            H = Vinv = None  # (V^-1: 72 B per free point, used only for the point covariances)
    nc = lay.nc
    if pb.gauge is Gauge.INNER:
        if n > opt.max_dense_inner:
            warnings.append(f"free network with {n} unknowns > max_dense_inner={opt.max_dense_inner}: no covariance")
            return out
        J = sp.hstack([ne.Jc, ne.Jp]).tocsr()
        N = (J.T @ J).toarray()
        G, E = _gauge_basis(pb, lay, st)
        try:
            N0 = np.linalg.inv(N + E @ E.T)
            P = np.eye(n) - G @ np.linalg.solve(E.T @ G, E.T)
        except np.linalg.LinAlgError:
            return (Termination.RANK_DEFICIENT, f"free network: normal matrix singular beyond the {defect} datum parameters")
        Qfull = P @ N0 @ P.T
        # check: N Q N = N within rounding; otherwise the defect is larger than 7
        if np.max(np.abs(N @ Qfull @ N - N)) > 1e-6 * np.max(np.abs(N)):
            return (Termination.RANK_DEFICIENT, f"free network: rank defect larger than the {defect} datum parameters")
        Q = Qfull[:nc, :nc]
        Qpp_full = Qfull[nc:, nc:]
    elif sp.issparse(S):  # chunked path: sparse reduced matrix
        d = np.sqrt(np.maximum(S.diagonal(), 1e-300))
        Dm = sp.diags(1.0 / d)
        Sn = (Dm @ S @ Dm).tocsc()
        del S, Dm
        bad = _sparse_rank_test(Sn, opt.rank_tolerance)
        if bad is not None:
            cond, k = bad
            involved = ", ".join(lay.names[i] for i in k)
            return (
                Termination.RANK_DEFICIENT,
                f"datum or parameters undetermined (condition {cond:.3g}); null direction involves {involved}",
            )
        release_free_heap()  # (the passes' freed temporaries) before the one dense nc x nc
        Sd = Sn.toarray(order="F")  # the inverse is dense: the one nc x nc matrix of the precision step
        del Sn
        Q = _spd_inverse_inplace(Sd)
        del Sd
        Q /= d[:, None]
        Q /= d[None, :]
        Qfull = None
    else:
        if nc:
            # Jacobi scaling in place: Sn = D^-1 S D^-1 (unit diagonal), S^-1 = D^-1 Sn^-1 D^-1
            d = np.sqrt(np.maximum(np.diag(S), 1e-300))
            Sn = S
            del S
            Sn /= d[:, None]
            Sn /= d[None, :]
            # eigenvalues only, of a copy (the eigenvectors and their LAPACK workspace are 3 more nc x nc
            # matrices); the null direction is computed only when the test fails
            ev = scipy.linalg.eigvalsh(Sn.copy(order="F"), overwrite_a=True, check_finite=False)
            if ev[0] <= opt.rank_tolerance * ev[-1]:
                ev, evec = np.linalg.eigh(Sn)
                k = np.argsort(-np.abs(evec[:, 0]))[:4]
                involved = ", ".join(lay.names[i] for i in k)
                return (
                    Termination.RANK_DEFICIENT,
                    f"datum or parameters undetermined (condition {ev[-1] / max(ev[0], 1e-300):.3g}); "
                    f"null direction involves {involved}",
                )
            Q = _spd_inverse_inplace(Sn)  # in the memory of Sn (Fortran order from schur)
            del Sn
            Q /= d[:, None]
            Q /= d[None, :]
        else:
            Q = np.zeros((0, 0))
        Qfull = None
    s2 = sigma0**2 if np.isfinite(sigma0) else float("nan")
    # report poses as (rotation increment, projection centre): dC = -R^T [t]x dw - R^T dt
    names = list(lay.names)
    for p in range(len(st.R)):
        c = int(lay.pose_col[p])
        if c < 0:
            continue
        for k, a in enumerate(("X0", "Y0", "Z0")):
            names[c + 3 + k] = f"{pb.pose_names[p]}.{a}"
    if Qfull is None and not (lay.npf and opt.compute_point_covariance) and not opt.compute_redundancy:
        cov = Q  # Q is not needed below: the covariance takes its memory
        del Q
    else:
        cov = Q.copy(order="F")
    # cov = s2 T Q T^T; T is the identity but for the centre rows c+3:c+6 of each pose: [-R^T [t]x, -R^T]
    blocks = [(int(lay.pose_col[p]), -st.R[p].T @ skew(st.t[p]), -st.R[p].T) for p in range(len(st.R)) if lay.pose_col[p] >= 0]
    for c, A, B in blocks:  # rows first (T Q), then columns ((T Q) T^T)
        cov[c + 3 : c + 6, :] = A @ cov[c : c + 3, :] + B @ cov[c + 3 : c + 6, :]
    for c, A, B in blocks:
        cov[:, c + 3 : c + 6] = cov[:, c : c + 3] @ A.T + cov[:, c + 3 : c + 6] @ B.T
    cov *= s2
    _symmetrise_inplace(cov)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    out.update(param_names=names, covariance=cov, std=std)  # (the correlation is computed on access)
    kind = np.zeros(nc, dtype=np.int8)  # 1 = intrinsics or rig (findings), 0 = pose or point
    for cc in lay.cam_cols:
        kind[cc[cc >= 0]] = 1
    for c in lay.rig_col[lay.rig_col >= 0]:
        kind[c : c + 6] = 1
    # per-camera and per-pose std
    cam_std = []
    for c, cc in enumerate(lay.cam_cols):
        sd = np.full(len(cc), np.nan)
        m = cc >= 0
        sd[m] = std[cc[m]]
        cam_std.append(sd)
    out["camera_std"] = cam_std
    pose_std = np.full((len(st.R), 6), np.nan)
    for p in range(len(st.R)):
        c = lay.pose_col[p]
        if c < 0:
            continue
        pose_std[p] = std[c : c + 6]
    out["pose_std"] = pose_std
    # warnings: correlations and insignificant additional parameters
    if nc > 1:
        # strict upper triangle, row by row (as np.triu_indices), in row blocks of ~1e6 entries (8 MB per
        # temporary: no nc^2 ones; the warnings come in the same order whatever the block size)
        step = max(1, int(1e6 // nc))
        for a0 in range(0, nc, step):
            with np.errstate(invalid="ignore", divide="ignore"):
                corr = cov[a0 : a0 + step] / std[a0 : a0 + step, None]
                corr /= std[None, :]
            big = np.triu(np.abs(corr) > opt.correlation_warning, a0 + 1)
            for a, b in zip(*np.nonzero(big)):
                if kind[a + a0] or kind[b]:  # pose-pose correlations are block geometry, not a finding
                    warnings.append(f"high correlation {corr[a, b]:+.3f} between {names[a + a0]} and {names[b]}")
            del corr
    if red > 0:
        tcrit = _t_ppf(1 - opt.significance_alpha / 2, red)
        for c, cc in enumerate(lay.cam_cols):
            for k, col in enumerate(cc):
                name = pb.cameras[c].param_names[k]
                if col >= 0 and name in _ADDITIONAL and std[col] > 0:
                    tval = abs(st.cam_params[c][k]) / std[col]
                    if tval < tcrit:
                        warnings.append(
                            f"additional parameter {lay.names[col]} insignificant: t = {tval:.2f} < {tcrit:.2f}"
                        )
    # write std into the cameras: 0 for parameters held fixed, NaN (never 0) for estimated parameters
    # whose precision is undetermined (redundancy <= 0)
    for c, sd in enumerate(cam_std):
        fixed = lay.cam_cols[c] < 0
        pb.cameras[c] = pb.cameras[c].with_params(st.cam_params[c], param_std=np.where(fixed, 0.0, sd))
    st.cam_params = [c.params.copy() for c in pb.cameras]
    npf = lay.npf
    Qpp = np.zeros((0, 3, 3))
    if npf and opt.compute_point_covariance:
        if Qfull is not None:
            Qpp = np.stack([Qpp_full[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] for k in range(npf)])
        else:
            Qpp = Vinv.copy()
            if nc:
                Hd = H.toarray().reshape(nc, npf, 3)
                QH = np.einsum("ij,jpk->ipk", Q, Hd)
                Qpp += np.einsum("ipa,ipb->pab", Hd, QH)
    if opt.compute_point_covariance:
        pc = np.full((len(pb.points), 3, 3), np.nan)
        pc[lay.free_points] = s2 * Qpp
        for p in lay.cs_points:
            c0 = int(lay.point_col[p])
            pc[p] = cov[c0 : c0 + 3, c0 : c0 + 3]
        out["point_covariance"] = pc
    if opt.compute_redundancy:
        # h_i = J_i Q J_i^T for every whitened row
        m = data.m
        if Qfull is not None:
            J = sp.hstack([ne.Jc, ne.Jp]).tocsr()
            Jd = J.toarray()
            h = np.einsum("ij,ij->i", Jd @ Qfull, Jd)
        else:
            h = np.zeros(m)
            has = ne.has
            if nc:
                u = ne.Jc
                if npf:
                    u = (u - ne.Jp @ H.T).tocsr()
                step = max(1, int(2e6 // max(nc, 1)))
                for s in range(0, m, step):
                    blk = u[s : s + step].toarray()
                    h[s : s + step] = np.einsum("ij,ij->i", blk @ Q, blk)
            if npf:
                jpw = jp * w[:, None]
                rows = np.nonzero(has)[0]
                slot = pslot[rows]
                h[rows] += np.einsum("ri,rij,rj->r", jpw[rows], Vinv[slot], jpw[rows])
        rnum = np.clip(1.0 - h, 0.0, 1.0)
        K = data.K
        img_r = np.full((len(active), 2), np.nan)
        img_r[data.img_idx] = rnum[: 2 * K].reshape(-1, 2)
        out["image_redundancy"] = img_r
        wt = np.full((len(active), 2), np.nan)
        with np.errstate(divide="ignore", invalid="ignore"):
            wv = (r[: 2 * K] * w[: 2 * K]) / (opt.sigma0_prior * np.sqrt(rnum[: 2 * K]))
        wt[data.img_idx] = np.where(rnum[: 2 * K] > 1e-10, wv, np.nan).reshape(-1, 2)
        out["image_w"] = -wt  # sign of v = observed - computed
        nc_ = len(data.c_pt)
        ng = len(data.g_pose)
        base = 2 * K
        with np.errstate(divide="ignore", invalid="ignore"):
            wall = -(r * w) / (opt.sigma0_prior * np.sqrt(rnum))
        wall = np.where(rnum > 1e-10, wall, np.nan)
        out["control_redundancy"] = rnum[base : base + 3 * nc_].reshape(-1, 3)
        out["control_w"] = wall[base : base + 3 * nc_].reshape(-1, 3)
        base += 3 * nc_
        out["gnss_redundancy"] = rnum[base : base + 3 * ng].reshape(-1, 3)
        out["gnss_w"] = wall[base : base + 3 * ng].reshape(-1, 3)
    return out
