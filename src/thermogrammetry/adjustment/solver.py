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

The engine along its seams: :mod:`~thermogrammetry.adjustment.options` (how it is solved),
:mod:`~thermogrammetry.adjustment.result` (what comes out), :mod:`~thermogrammetry.adjustment.layout`
(parameter columns, state, observation arrays), :mod:`~thermogrammetry.adjustment.residuals` (whitened
residuals, Jacobians, robust weights), :mod:`~thermogrammetry.adjustment.normal` and
:mod:`~thermogrammetry.adjustment.normal_chunked` (normal equations), :mod:`~thermogrammetry.adjustment.linalg`
(sparse and dense linear algebra), :mod:`~thermogrammetry.adjustment.trust_region` (Levenberg-Marquardt) and
:mod:`~thermogrammetry.adjustment.precision` (covariance, redundancy, tests, gauge); this module drives them.

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

import numpy as np
import scipy.linalg

from .._memory import release_free_heap
from ..errors import InvalidInputError
from ..results import Termination
from .layout import Data, Layout, State
from .options import Loss, SolverOptions
from .precision import norm_ppf, precision, scale_observed
from .problem import BundleProblem, Gauge
from .result import AdjustmentResult
from .trust_region import lm

# the engine's internals under their names before the split into modules (tests use them). A test that patches
# a name patches it where it is looked up now: e.g. ``normal_chunked._SCHUR_CHUNK``, ``linalg._THREAD_MIN_NNZ``,
# ``residuals._ROBUST_CHUNK``, ``trust_region.ChunkedNormal``, ``solver.precision``
from .linalg import _SparseFactor  # noqa: F401
from .linalg import cho_factor as _cho_factor  # noqa: F401
from .linalg import csr_product as _csr_product  # noqa: F401
from .linalg import gram as _gram  # noqa: F401
from .linalg import sparse_rank_test as _sparse_rank_test  # noqa: F401
from .normal import Normal as _Normal  # noqa: F401
from .normal_chunked import ChunkedNormal as _ChunkedNormal  # noqa: F401
from .normal_chunked import _point_chunks  # noqa: F401
from .precision import _chi2_ppf, _t_ppf  # noqa: F401
from .precision import norm_ppf as _norm_ppf  # noqa: F401
from .residuals import _so3_left_jacobian_inv  # noqa: F401
from .residuals import evaluate as _evaluate  # noqa: F401
from .residuals import robust as _robust  # noqa: F401

_Layout, _State, _Data = Layout, State, Data

__all__ = ["Loss", "SolverOptions", "AdjustmentResult", "solve"]


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
    lay = Layout(pb)
    K_all = sum(len(o.point) for o in pb._img)  # (without concatenating the observations)
    active = np.ones(K_all, dtype=bool)
    st = State(pb)
    n = lay.nc + 3 * lay.npf
    defect = (6 if scale_observed(pb) else 7) if pb.gauge is Gauge.INNER else 0
    warnings: list[str] = []

    def result(term, reason, it, c0, c1, **kw):
        st.write_to(pb)
        _shift_world(pb, origin)
        return AdjustmentResult(term, reason, it, c0, c1, pb, warnings=warnings, time_s=time.perf_counter() - t0, **kw)

    data = Data(pb, active)
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
            data = Data(pb, active)
        st, c0, cost, it, term, reason = lm(pb, lay, st, data, opt)
        total_it += it
        if cost0 is None:
            cost0 = c0
        if not term.success:
            return result(term, reason, total_it, cost0, cost)
        try:
            out = precision(pb, lay, st, data, opt, active, warnings)
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
        k = norm_ppf(1 - opt.snooping_alpha / 2)
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
        data_chk = Data(pb, active)
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
