"""Sparse and dense linear algebra of the engine: bit-exact sparse products (scipy's own kernel), sums of
sparse Schur complements, the sparse and dense factors of the reduced system, the SPD inverse, the sparse
rank test, and the tangent basis of a plane normal."""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse as sp

__all__ = [
    "csr_product", "gram", "SparseSum", "add_diagonal", "factor_solve", "symmetrise_inplace",
    "spd_inverse_inplace", "sparse_rank_test", "tangent_basis", "cho_factor",
]


#: stored entries of the left factor from which :func:`csr_product` splits its rows over threads
_THREAD_MIN_NNZ = 200_000


def csr_product(A, B, nnz_row_max: int, threads: int = 1):
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


def gram(J, threads: int = 1):
    """``(J.T @ J).toarray()`` for a CSR matrix ``J`` (m, n) with small n, bit for bit as scipy computes it (the
    transpose converted to CSR, the product by :func:`csr_product`, transposed back as scipy's CSC result
    is): (n, n) dense, C order."""
    n = J.shape[1]
    R = csr_product(J.T.tocsr(), J, n, threads)  # (scipy: J^T J in CSR arrays, read as CSC, i.e. transposed)
    return np.ascontiguousarray(R.toarray().T)


def _add_sparse(A, M, sign=1.0):
    """``A += sign * M`` for a dense ``A`` and a sparse ``M`` without repeated entries (a sparse product or
    sum, or after ``sum_duplicates``)."""
    M = M.tocoo()
    if M.nnz:
        A[M.row, M.col] += M.data if sign == 1.0 else sign * M.data


class SparseSum:
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


def add_diagonal(S, d):
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


def factor_solve(cf, b):
    """Solve with the factor of a reduced matrix (:func:`cho_factor`): dense Cholesky, sparse, or empty."""
    if isinstance(cf, _SparseFactor):
        return cf.solve(b)
    if isinstance(cf[0], str):
        return np.zeros(0)
    return scipy.linalg.cho_solve(cf, b, check_finite=False)



def _symmetrised(A):
    """``0.5 (A + A^T)`` with one temporary instead of two (same values)."""
    B = A + A.T
    del A
    B *= 0.5
    return B


def symmetrise_inplace(A, step=512):
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


def spd_inverse_inplace(S):
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


def sparse_rank_test(Sn, tol):
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


def tangent_basis(n):
    """(3, 2) orthonormal basis of the plane orthogonal to the unit vector n (deterministic)."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(n, u)], axis=1)


def cho_factor(S):
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
