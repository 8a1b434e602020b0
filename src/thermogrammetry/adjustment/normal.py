"""Normal equations of the full-Jacobian path: :class:`Normal` (``U``, ``W``, ``V``, the gradient and the
Schur complement on the 3x3 point blocks) at one linearisation."""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from .layout import Layout
from .linalg import csr_product, gram

__all__ = ["Normal"]


class Normal:
    """Normal-equation pieces at one linearisation (whitened, robust-weighted)."""

    def __init__(self, r, jac: list, pslot, lay: Layout, w, threads: int = 1):
        """``jac = [Jc, jp]`` of :func:`evaluate`; the list is emptied so that the unweighted Jacobian is freed
        as soon as its weighted copy exists (when the caller holds no other reference). ``threads``: for the
        products ``J_c^T J_c`` and ``H B^T`` (:func:`csr_product`; the same values with any count)."""
        self.lay = lay
        m = len(r)
        rw = r * w
        Jc, jp = jac
        jac.clear()
        if lay.nc and np.any(w != 1.0):
            # (= ``sp.diags(w) @ Jc``: the same kernel on the same CSR operands, without the symbolic count)
            Jcw = csr_product(sp.diags(w).tocsr(), Jc, int(np.max(np.diff(Jc.indptr), initial=0)), threads)
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
        self.U = gram(Jcw, threads) if lay.nc else np.zeros((0, 0))
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
                HB = csr_product(H, self._Bt, nc, self.threads)
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
