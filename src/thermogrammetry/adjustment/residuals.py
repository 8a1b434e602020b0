"""Whitened residuals and their Jacobians (the cost functions of the engine), and the robust weights.

:func:`evaluate` gives ``(computed - observed) / sigma`` of every observation (image points, control,
GNSS, planes, distances, attitude priors) and, on request, the camera-side Jacobian (CSR) and the
point Jacobian rows; :func:`robust` the square-root weights and the cost of the robust loss on image
points (iteratively re-weighted rows, Triggs et al. 2000, sec. 3.3).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ._so3 import axis_angles, skew
from .layout import Data, Layout, State
from .linalg import tangent_basis
from .options import Loss, SolverOptions

__all__ = ["evaluate", "robust"]


#: image observations per chunk in :func:`evaluate` (bounds its temporaries: ~1.5 KB per observation)
_EVAL_CHUNK = 32768
#: the same for residuals only (the LM's trial steps, ~0.4 KB per observation): smaller, since the residuals of
#: large blocks are evaluated while the factor of the reduced system is held
_EVAL_CHUNK_RES = 8192


def evaluate(pb, lay: Layout, st: State, data: Data, want_jac: bool, sel=None, extra: bool = True):
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
            Bt = np.stack([tangent_basis(v) for v in st.pn])[data.pl_k] if len(st.pn) else np.zeros((0, 3, 2))
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
    nq = len(data.q_cam) if extra else 0
    if nq:
        # priors on intrinsics: (θ - θ0) / σ, d/dθ = 1 / σ where θ is free
        th = np.array([st.cam_params[c][k] for c, k in zip(data.q_cam, data.q_k)])
        r[row : row + nq] = (th - data.q_val) / data.q_sig
        if want_jac:
            qc = np.array([lay.cam_cols[c][k] for c, k in zip(data.q_cam, data.q_k)], dtype=np.int64)
            trip(row + np.arange(nq), 1, (1.0 / data.q_sig)[:, None, None], qc, qc >= 0)
        row += nq
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


#: image observations per piece of :func:`robust` (its temporaries: ~80 B per observation of a piece)
_ROBUST_CHUNK = 65536


def robust(r, K, opt: SolverOptions, weights: bool = True):
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
