"""Normal equations of large blocks, built chunk by chunk of points without the block's Jacobian:
:class:`ChunkedNormal` (see :mod:`thermogrammetry.adjustment.solver` for when it is used)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .._memory import release_free_heap
from .layout import Data, Layout, State
from .linalg import SparseSum, add_diagonal, factor_solve
from .residuals import evaluate

__all__ = ["ChunkedNormal"]


#: relative size of the iterative-refinement correction of the camera-side step below which the
#: chunked path keeps the unrefined step (a third pass over the Jacobians would change it by less
#: than this fraction; the old path always refines)
_REFINE_RTOL = 1e-6


#: image observations per chunk of :class:`ChunkedNormal` (bounds the temporaries of a chunk's Jacobian, sparse
#: products and Schur contribution: ~3 KB per observation)
_SCHUR_CHUNK = 8192
#: the chunked passes return the heap's free pages to the system every this many chunks
#: (:func:`thermogrammetry._memory.release_free_heap`)
_TRIM_EVERY = 8


def _point_chunks(lay: Layout, data: Data):
    """Image observations grouped for :class:`ChunkedNormal`: ``order`` (K,) sorts them by free point
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


class ChunkedNormal:
    """The reduced camera system built chunk by chunk, without the block's Jacobian.

    Same normal equations as :class:`Normal` (``U, W, V``, gradient, damping ``lam D``) but the image
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
        Whitened residuals at ``st`` (:func:`evaluate`) and the robust square-root weights (:func:`robust`).
    lam : float
        Damping of the first reduced system (built in the same pass as ``U``, ``V`` and the gradient).
    """

    def __init__(self, pb, lay: Layout, st: State, data: Data, r, w, lam: float):
        self.pb, self.lay, self.st, self.data = pb, lay, st, data
        self.r, self.w = r, w
        self.order, self.chunks = _point_chunks(lay, data)
        nc, npf = lay.nc, lay.npf
        K = data.K
        # rows other than image observations: small, evaluated and kept once per linearisation
        _, Je, jpe, pse = evaluate(pb, lay, st, data, True, sel=np.zeros(0, dtype=np.int64), extra=True)
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
            first = (add_diagonal(first[0], lam * self.dU),) + first[1:]
        self._first = (lam, first)  # handed out (once) by schur(lam)
        self.grad_max = max(float(np.max(np.abs(self.gc))) if nc else 0.0, float(np.max(np.abs(gp))) if npf else 0.0)

    def _chunk(self, o0, o1, p0, p1):
        """Robust-weighted camera-side Jacobian (CSR), point Jacobian as CSR over the chunk's point
        columns ``3 (p - p0) + j`` (or None), and weighted residuals of one chunk."""
        idx = self.order[o0:o1]
        _, Jc, jp, pslot = evaluate(self.pb, self.lay, self.st, self.data, True, sel=idx, extra=False)
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
        acc = SparseSum(nc)  # accumulates W V^-1 W^T (sparse), turned into U - W V^-1 W^T at the end
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
                out = (add_diagonal(out[0], lam * self.dU),) + out[1:]
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
        :class:`Normal`); the refinement's extra pass over the Jacobians is made only when its
        correction exceeds ``_REFINE_RTOL`` of the step."""
        nc, npf = self.lay.nc, self.lay.npf
        dc = factor_solve(cf, rhs)
        if not npf:
            if nc:
                res = -self.gc - self.U @ dc - lam * self.dU * dc
                if np.all(np.isfinite(res)) and np.linalg.norm(res) > 1e-14 * np.linalg.norm(self.gc):
                    dc = dc + factor_solve(cf, res)
            return dc
        if not nc:
            dp, _ = self._back(dc, Vinv)
            return dp.ravel()
        dp, Wdp = self._back(dc, Vinv, refine_lam=lam)
        res = -self.gc - self.U @ dc - lam * self.dU * dc - Wdp
        if np.all(np.isfinite(res)):
            corr = factor_solve(cf, res)
            if np.linalg.norm(corr) > _REFINE_RTOL * np.linalg.norm(dc):
                dc = dc + corr
                dp, _ = self._back(dc, Vinv)
        return np.concatenate([dc, dp.ravel()])
