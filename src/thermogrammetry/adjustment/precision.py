"""Precision and reliability of an adjusted block (Foerstner & Wrobel 2016, ch. 4; Baarda 1968), and the gauge
of a free network.

- ``sigma0^2 = v^T P v / r`` with redundancy ``r = m - n (+ d for a free network)`` and the
  two-sided chi^2 test of ``r sigma0^2 / sigma0_prior^2`` at ``alpha``;
- cofactor matrix ``Q = S^-1`` of the non-point parameters (intrinsics, poses, rigs); a
  posteriori covariance ``sigma0^2 Q``; standard deviations and correlations; point
  covariances ``V^-1 + V^-1 W^T Q W V^-1`` on request; for a free network the inner-constraint
  cofactor ``P N^- P^T`` with ``P = I - G (E^T G)^-1 E^T`` (S-transformation onto minimum trace
  of the points; Baarda 1973);
- redundancy numbers ``r_i = 1 - (J Q J^T)_ii`` of every whitened observation row and the w-tests
  ``w_i = v_i / (sigma_i sqrt(r_i))`` with the a priori sigma (data snooping,
  :func:`thermogrammetry.adjustment.solver.solve`); warnings for ``|rho| > correlation_warning`` and for
  additional parameters whose t-value ``|x| / sigma_x`` is below the Student-t critical value (insignificant).

References
----------
Baarda, W. (1968). A testing procedure for use in geodetic networks. Netherlands Geodetic
Commission, Publications on Geodesy 2(5).
Baarda, W. (1973). S-transformations and criterion matrices. NGC, Publ. on Geodesy 5(1).
Foerstner, W., Wrobel, B. P. (2016). Photogrammetric Computer Vision. Springer, ch. 4.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.special

from .._memory import release_free_heap
from ..results import Termination
from ._so3 import skew
from .linalg import sparse_rank_test, spd_inverse_inplace, symmetrise_inplace, tangent_basis
from .normal import Normal
from .normal_chunked import ChunkedNormal
from .problem import Gauge
from .residuals import evaluate, robust

__all__ = ["precision", "scale_observed", "norm_ppf"]

# intrinsics that are "additional parameters" (tested for significance), per model
_ADDITIONAL = {
    "k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2", "skew",
    "K1", "K2", "K3", "K4", "K5", "P1", "P2", "B1", "B2",
}


# quantiles by the special functions behind scipy.stats' ``norm``, ``chi2`` and ``t`` (whose ``ppf`` is ``_ppf``
# times 1 plus 0 there): the same values without importing scipy.stats (~0.5 s)
def norm_ppf(q):
    """Quantile of the standard normal distribution (``scipy.stats.norm.ppf``)."""
    return scipy.special.ndtri(q)


def _chi2_ppf(q, df):
    """Quantile of the chi-square distribution with ``df`` degrees of freedom (``scipy.stats.chi2.ppf``)."""
    return 2 * scipy.special.gammaincinv(np.asarray(df) / 2, q)


def _t_ppf(q, df):
    """Quantile of Student's t distribution with ``df`` degrees of freedom (``scipy.stats.t.ppf``)."""
    return scipy.special.stdtrit(df, q)


def scale_observed(pb) -> bool:
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
        Bt = tangent_basis(n)
        G[c : c + 2, 3:6] = -Bt.T @ skew(n)  # rotation dth: dn = dth x n
        G[c + 2, 0:3] = n  # translation dX: dd = n . dX
        G[c + 2, 6] = d  # scale: dd = s d
    if scale_observed(pb):  # observed distances or a fixed rig baseline define the scale
        G, E = G[:, :6], E[:, :6]
    return G, E


def _eigvalsh(A: np.ndarray) -> np.ndarray:
    """Ascending eigenvalues of the symmetric ``A`` (n, n), of a copy (``A`` is kept). LAPACK's default driver
    (``syevr``) can stop without converging on an ill-conditioned reduced matrix ("Internal Error", seen with
    SciPy 1.17 on a 20-station ring whose solve had converged); the divide-and-conquer (``syevd``) and QR
    (``syev``) drivers are tried next, and the error is raised only when all three fail."""
    bad = int(A.size - np.count_nonzero(np.isfinite(A)))
    if bad:
        raise np.linalg.LinAlgError(f"the reduced normal matrix has {bad} non-finite entries of {A.size}")
    err = None
    for driver in ("evr", "evd", "ev"):
        try:
            return scipy.linalg.eigvalsh(A.copy(order="F"), overwrite_a=True, check_finite=False, driver=driver)
        except (np.linalg.LinAlgError, scipy.linalg.LinAlgError) as exc:
            err = exc
    raise err


def precision(pb, lay, st, data, opt, active, warnings):
    """Precision and reliability at the adjusted state ``st`` (see the module docstring).

    Returns a dict of :class:`~thermogrammetry.adjustment.result.AdjustmentResult` fields (sigma0, chi^2 test,
    residuals, covariance, standard deviations, redundancy numbers, w-tests), or ``(termination, reason)``
    when the normal matrix is singular; appends its findings to ``warnings``.
    """
    # the chunked normal equations give the reduced matrix (enough for the covariance of the camera side);
    # redundancy numbers, point covariances and the free-network covariance need the whole Jacobian
    chunked = data.K >= opt.chunked_min_observations and not (
        opt.compute_covariance and (pb.gauge is Gauge.INNER or opt.compute_redundancy or opt.compute_point_covariance))
    lin, data.linearisation = data.linearisation, None
    if chunked:
        release_free_heap()  # (the LM's freed temporaries)
        r = evaluate(pb, lay, st, data, False)
        w, cost = robust(r, data.K, opt)
        # the normal equations (for the covariance) are built after the residual outputs below
    elif lin is not None and lin[0] is st and not opt.compute_redundancy:
        # the LM stopped at the state of its last linearisation (predicted decrease or step below tolerance, or
        # the gradient): the same residuals, weights and normal equations as evaluating them again
        _, r, w, ne = lin
    else:
        r, Jc, jp, pslot = evaluate(pb, lay, st, data, True)
        w, cost = robust(r, data.K, opt)
        jac = [Jc, jp]
        del Jc  # the normal equations are built only for the covariance (ne keeps the weighted Jacobian)
        if opt.compute_covariance:
            ne = Normal(r, jac, pslot, lay, w, opt.num_threads)
        jac.clear()
    del lin
    n = lay.nc + 3 * lay.npf
    defect = (6 if scale_observed(pb) else 7) if pb.gauge is Gauge.INNER else 0
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
        ne = ChunkedNormal(pb, lay, st, data, r, w, 0.0)
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
        bad = sparse_rank_test(Sn, opt.rank_tolerance)
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
        Q = spd_inverse_inplace(Sd)
        del Sd
        Q /= d[:, None]
        Q /= d[None, :]
        Qfull = None
    else:
        if nc:
            # Jacobi scaling in place: Sn = D^-1 S D^-1 (unit diagonal), S^-1 = D^-1 Sn^-1 D^-1
            dS = np.diag(S)
            neg = np.nonzero(~(dS > 0))[0]
            if len(neg):
                # S = U - W V^-1 W^T cannot have a diagonal <= 0 in exact arithmetic: some points' 3x3 normal blocks
                # are too near singular for their inverse (rays nearly parallel, points near infinity)
                return (
                    Termination.NUMERICAL_FAILURE,
                    f"the reduced normal matrix is not positive definite ({len(neg)} diagonal entries <= 0: "
                    f"{', '.join(lay.names[i] for i in neg[np.argsort(dS[neg])][:4])}): points whose normal blocks are "
                    "numerically singular (rays nearly parallel or points near infinity)",
                )
            d = np.sqrt(dS)
            Sn = S
            del S
            Sn /= d[:, None]
            Sn /= d[None, :]
            # eigenvalues only, of a copy (the eigenvectors and their LAPACK workspace are 3 more nc x nc
            # matrices); the null direction is computed only when the test fails
            ev = _eigvalsh(Sn)
            if ev[0] <= opt.rank_tolerance * ev[-1]:
                ev, evec = np.linalg.eigh(Sn)
                k = np.argsort(-np.abs(evec[:, 0]))[:4]
                involved = ", ".join(lay.names[i] for i in k)
                return (
                    Termination.RANK_DEFICIENT,
                    f"datum or parameters undetermined (condition {ev[-1] / max(ev[0], 1e-300):.3g}); "
                    f"null direction involves {involved}",
                )
            Q = spd_inverse_inplace(Sn)  # in the memory of Sn (Fortran order from schur)
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
    symmetrise_inplace(cov)
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
