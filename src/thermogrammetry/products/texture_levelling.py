"""Seam levelling: per-image additive offsets from the overlaps (``levelling="offsets"``).

Least squares over texel pairs ``T_a(x) + o_a = T_b(x) + o_b`` with one image held at 0; see
:mod:`thermogrammetry.products.texture`.
"""

from __future__ import annotations

import numpy as np

from .texture_selection import Selection

__all__ = ["levelling_sample", "estimate_offsets"]


def levelling_sample(n: int, size: int, seed: int = 0) -> np.ndarray:
    """(n,) bool: ``size`` points drawn without replacement (all of them when n <= size), seeded."""
    m = np.zeros(n, bool)
    if n <= size:
        m[:] = True
    else:
        m[np.random.default_rng(seed).choice(n, size, replace=False)] = True
    return m



def estimate_offsets(selection: Selection, n_views: int, *, max_pairs: int = 200_000, seed: int = 0,
                     fixed: int | None = None):
    """Least-squares per-image offsets from overlaps (:mod:`thermogrammetry.products.texture`), one image held at 0.

    ``fixed``: the image held at 0 (default: the one that supplies most points of ``selection``; a caller that
    passes a subsample of its points gives the image that supplies most of all of them).

    Returns ``(offsets_k (K,), fixed index, pairs per image (K,), rms_before_k, rms_after_k)``; images
    without overlap keep offset 0 (pairs = 0).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import lsqr

    src = selection.source
    rows = np.flatnonzero((src >= 0) & (selection.n_usable >= 2))
    rng = np.random.default_rng(seed)
    A = selection.all_k[rows]  # float32; differences are taken in float64 (exact)
    fin = np.isfinite(A)
    # pairs are numbered image pair by image pair (k < j), rows in order within a pair; only the pairs kept by the
    # subsample are materialised (all pairs of a 2.4 M-texel, 40-image wall took 7.4 GB before)
    blocks = [(k, j, int(np.count_nonzero(fin[:, k] & fin[:, j]))) for k in range(n_views) for j in range(k + 1, n_views)]
    blocks = [bl for bl in blocks if bl[2] > 0]
    counts = np.bincount(src[src >= 0], minlength=n_views)
    fixed = int(np.argmax(counts)) if fixed is None else int(fixed)
    if not blocks:
        return np.zeros(n_views), fixed, np.zeros(n_views, np.int64), float("nan"), float("nan")
    total = sum(bl[2] for bl in blocks)
    keep = np.sort(rng.choice(total, max_pairs, replace=False)) if total > max_pairs else None
    a_idx, b_idx, diff = [], [], []
    start = 0
    for k, j, n in blocks:
        if keep is None:
            take = slice(None)
        else:
            lo, hi = np.searchsorted(keep, [start, start + n])
            start += n
            if lo == hi:
                continue
            take = keep[lo:hi] - (start - n)
        r = np.flatnonzero(fin[:, k] & fin[:, j])[take]
        a_idx.append(np.full(len(r), k))
        b_idx.append(np.full(len(r), j))
        diff.append(A[r, k].astype(np.float64) - A[r, j].astype(np.float64))
    a = np.concatenate(a_idx)
    b = np.concatenate(b_idx)
    dd = np.concatenate(diff)
    pairs = np.bincount(a, minlength=n_views) + np.bincount(b, minlength=n_views)
    # T_a + o_a = T_b + o_b  ->  o_a - o_b = -(T_a - T_b); unknowns: all but the fixed image
    free = np.array([k for k in range(n_views) if k != fixed and pairs[k] > 0])
    col = -np.ones(n_views, np.int64)
    col[free] = np.arange(len(free))
    r = np.arange(len(dd))
    ra, rb = col[a] >= 0, col[b] >= 0
    M = coo_matrix((np.concatenate([np.ones(ra.sum()), -np.ones(rb.sum())]),
                    (np.concatenate([r[ra], r[rb]]), np.concatenate([col[a][ra], col[b][rb]]))),
                   shape=(len(dd), max(len(free), 1))).tocsr()
    x = lsqr(M, -dd, atol=1e-12, btol=1e-12)[0] if len(free) else np.zeros(0)
    off = np.zeros(n_views)
    off[free] = x
    rms_before = float(np.sqrt(np.mean(dd**2)))
    rms_after = float(np.sqrt(np.mean((dd + off[a] - off[b]) ** 2)))
    return off, fixed, pairs, rms_before, rms_after
