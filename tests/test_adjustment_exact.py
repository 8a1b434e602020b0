"""Speed paths of the adjustment engine's full-Jacobian path that must not change a single bit.

The survey's final adjustment reacts to rounding in the reduced system (a different rounding of the Schur
complement flipped tie-point rejections on the 64-station ring of tests/test_texture_survey_poses.py), so
these paths are checked for exact equality, not within a tolerance:

- :func:`linalg.csr_product` (scipy's own CSR product kernel with a bound on the entries per row instead of
  scipy's symbolic count, rows optionally split over threads) against scipy's ``@``;
- :func:`linalg.gram` against ``(J.T @ J).toarray()``;
- the quantiles by ``scipy.special`` against ``scipy.stats``;
- whole solves with 1, 2 or 3 threads, and with the precision step's reuse of the LM's last linearisation
  switched off, on the block of tests/chunked_block.py (two cameras with free intrinsics, GNSS priors,
  weighted control, a rig, a plane, a scale bar, robust loss, covariance).
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.stats

from chunked_block import build_block
from thermogrammetry.adjustment import SolverOptions, solve
from thermogrammetry.adjustment import linalg
from thermogrammetry.adjustment import solver as S
from thermogrammetry.errors import ConfigError

FULL = 10**12  # chunked_min_observations: the full-Jacobian path


def _same_csr(a, b):
    """Same shape, same entries in the same storage order, same values (bit for bit)."""
    assert a.shape == b.shape
    np.testing.assert_array_equal(a.indptr, b.indptr)
    np.testing.assert_array_equal(a.indices, b.indices)
    assert np.array_equal(a.data, b.data)


def _random_csr(rng, m, n, density, empty_rows=()):
    A = sp.random(m, n, density=density, format="csr", random_state=rng, data_rvs=lambda k: rng.normal(0, 1, k))
    A = A.tolil()
    for i in empty_rows:
        A[i, :] = 0
    A = A.tocsr()
    A.eliminate_zeros()
    return A


@pytest.mark.parametrize("threads", [1, 2, 3, 7])
def test_csr_product_equals_scipy_bit_for_bit(monkeypatch, threads):
    rng = np.random.default_rng(5)
    monkeypatch.setattr(linalg, "_THREAD_MIN_NNZ", 0)  # split even these small products
    A = _random_csr(rng, 40, 900, 0.05, empty_rows=(0, 17, 39))
    B = _random_csr(rng, 900, 30, 0.1, empty_rows=(3, 4))
    # B with unsorted rows (as a kernel's product stores them): only the order of the result's entries may follow
    Bu = (B.T @ sp.identity(B.shape[0], format="csc")).T  # a product of scipy's, rows in the kernel's order
    for right in (B, sp.csr_matrix(Bu)):
        ref = (A @ right).tocsr()
        got = S._csr_product(A, right, right.shape[1], threads)
        _same_csr(got, ref)
    # the cancellation of a sum to exactly 0 drops the entry, as scipy's kernel does
    A0 = sp.csr_matrix(np.array([[1.0, 1.0], [0.0, 2.0]]))
    B0 = sp.csr_matrix(np.array([[1.0, 3.0], [-1.0, 0.0]]))
    _same_csr(S._csr_product(A0, B0, 2, threads), (A0 @ B0).tocsr())
    assert S._csr_product(A0, B0, 2, threads).nnz == 2  # [[0, 3], [-2, 0]]: the 0 is not stored
    # a product without entries
    Z = sp.csr_matrix((5, 900))
    _same_csr(S._csr_product(Z, B, B.shape[1], threads), (Z @ B).tocsr())


def test_gram_equals_scipy_bit_for_bit(monkeypatch):
    rng = np.random.default_rng(6)
    J = _random_csr(rng, 3000, 60, 0.08, empty_rows=(10, 11))
    ref = (J.T @ J).toarray()
    for t in (1, 2):
        monkeypatch.setattr(linalg, "_THREAD_MIN_NNZ", 0 if t > 1 else 10**9)
        got = S._gram(J, t)
        assert np.array_equal(got, ref) and got.flags.c_contiguous


def test_quantiles_equal_scipy_stats():
    for df in list(range(1, 200)) + [999, 4321, 146_000, 400_001]:
        assert np.array_equal(S._chi2_ppf(np.array([0.025, 0.975]), df), scipy.stats.chi2.ppf([0.025, 0.975], df))
        assert S._t_ppf(0.975, df) == scipy.stats.t.ppf(0.975, df)
    for a in (0.05, 0.01, 0.001, 1e-4):
        assert S._norm_ppf(1 - a / 2) == scipy.stats.norm.ppf(1 - a / 2)


def _same_result(ra, rb):
    assert ra.termination == rb.termination and ra.reason == rb.reason and ra.iterations == rb.iterations
    assert ra.final_cost == rb.final_cost and ra.sigma0 == rb.sigma0
    assert np.array_equal(ra.points, rb.points)
    for a, b in zip(ra.poses, rb.poses):
        assert np.array_equal(a.R, b.R) and np.array_equal(a.t, b.t)
    for a, b in zip(ra.cameras, rb.cameras):
        assert np.array_equal(a.params, b.params)
    for a, b in zip(ra.problem.rig_t, rb.problem.rig_t):
        assert np.array_equal(a, b)
    for name in ("std", "covariance", "image_residuals", "gnss_residuals", "control_residuals"):
        x, y = getattr(ra, name), getattr(rb, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert np.array_equal(x, y, equal_nan=True), name
    assert ra.warnings == rb.warnings


@pytest.mark.parametrize("loss", ["trivial", "huber"])
def test_thread_count_and_linearisation_reuse_change_no_bit(monkeypatch, loss):
    pb, _ = build_block(rig=True, seed=13)
    monkeypatch.setattr(linalg, "_THREAD_MIN_NNZ", 0)
    base = dict(chunked_min_observations=FULL, loss=loss, loss_scale=2.0, compute_redundancy=False)
    r1 = solve(pb, SolverOptions(num_threads=1, **base))
    assert r1.success and r1.covariance is not None
    for t in (2, 3):
        _same_result(r1, solve(pb, SolverOptions(num_threads=t, **base)))
    # the precision step without the LM's last linearisation: evaluates and builds the normal equations again
    precision = S.precision
    reused = []

    def fresh(pb_, lay, st, data, *a, **k):
        reused.append(data.linearisation is not None and data.linearisation[0] is st)
        data.linearisation = None
        return precision(pb_, lay, st, data, *a, **k)

    monkeypatch.setattr(S, "precision", fresh)  # (looked up by solver._solve)
    r0 = solve(pb, SolverOptions(num_threads=2, **base))
    _same_result(r1, r0)
    assert r1.reason == r0.reason
    # (whether the LM stopped at its last linearisation depends on the stopping rule that fired)
    assert reused == [r1.reason.startswith(("predicted decrease", "parameter tolerance", "gradient"))]


def test_num_threads_option_checked():
    with pytest.raises(ConfigError, match="num_threads"):
        SolverOptions(num_threads=0)
