"""Chunked normal equations of the adjustment engine (issue 11: survey memory must not grow with the block).

Above ``SolverOptions.chunked_min_observations`` image observations, :func:`thermogrammetry.adjustment.solve`
builds the reduced camera system chunk by chunk of points without holding the block's Jacobian
(``solver._ChunkedNormal``). It solves the same normal equations as the full-Jacobian path; only the
order of the floating-point sums differs. The block (tests/chunked_block.py) has what the survey needs:
shared intrinsics (two cameras, one with free distortion), GNSS priors, weighted control, a rig, a
plane and a scale bar (rows outside the image chunks), gross errors under a robust loss, covariance.
The chunk size is lowered to 64 observations so that the 3-4 k observations fall into ~60 chunks.

Tolerances: both paths take the same LM steps (same iteration count) and end at the same minimum; the
parameters differ by rounding only, measured 1e-13 m on ~100 m coordinates, so 1e-9 relative to the
coordinate scale (1e-7 m) is far from a real difference yet far below the standard deviations (cm). The
standard deviations come from the inverse of the reduced matrix, whose condition (~1e8 here: focal length
against flying height with 3 cm GNSS priors) amplifies the ~1e-16 summation-order rounding: measured
< 5e-10 relative, asserted 1e-7.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from chunked_block import build_block
from thermogrammetry.adjustment import SolverOptions, solve
from thermogrammetry.adjustment import normal_chunked, precision, trust_region
from thermogrammetry.adjustment import solver as S
from thermogrammetry.errors import ConfigError
from thermogrammetry.results import Termination

FULL = 10**12  # chunked_min_observations: never chunked
CHUNKED = 0  # always chunked


@pytest.fixture
def small_chunks(monkeypatch):
    monkeypatch.setattr(normal_chunked, "_SCHUR_CHUNK", 64)


def _centres(res):
    return np.array([-p.R.T @ p.t for p in res.poses])


def _compare(ra, rb, cov=True):
    assert ra.termination == rb.termination and ra.success
    assert ra.iterations == rb.iterations
    assert rb.final_cost == pytest.approx(ra.final_cost, rel=1e-12)
    scale = 100.0  # m, size of the block's coordinates
    np.testing.assert_allclose(rb.points, ra.points, rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(_centres(rb), _centres(ra), rtol=0, atol=1e-9 * scale)
    for a, b in zip(ra.poses, rb.poses):
        np.testing.assert_allclose(b.R, a.R, rtol=0, atol=1e-12)
    for a, b in zip(ra.cameras, rb.cameras):
        np.testing.assert_allclose(b.params, a.params, rtol=1e-9, atol=1e-12)
    for a, b in zip(ra.problem.rig_t, rb.problem.rig_t):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-9)
    assert rb.sigma0 == pytest.approx(ra.sigma0, rel=1e-10)
    if cov:
        assert ra.param_names == rb.param_names
        np.testing.assert_allclose(rb.std, ra.std, rtol=1e-7)
        np.testing.assert_allclose(rb.pose_std, ra.pose_std, rtol=1e-7)
        for a, b in zip(ra.camera_std, rb.camera_std):
            np.testing.assert_allclose(b, a, rtol=1e-7)
        np.testing.assert_allclose(rb.correlation, ra.correlation, rtol=0, atol=1e-7)


def test_georeferenced_block_with_rig_same_solution_and_sigmas(small_chunks):
    pb, truth = build_block(rig=True)
    opt = dict(loss="huber", loss_scale=3.0, compute_redundancy=False)
    ra = solve(pb, SolverOptions(chunked_min_observations=FULL, **opt))
    rb = solve(pb, SolverOptions(chunked_min_observations=CHUNKED, **opt))
    _compare(ra, rb)
    np.testing.assert_allclose(rb.gnss_residuals, ra.gnss_residuals, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rb.image_residuals, ra.image_residuals, rtol=0, atol=1e-9)
    # and the chunked solution is right: centres within their sigmas of the truth (GNSS 3 cm, 0.3 px)
    Ce = _centres(rb)
    z = (Ce - truth["C"]) / rb.pose_std[:, 3:]
    assert np.max(np.abs(z)) < 4.5  # 72 normalised errors: |z| < 4.5 with probability ~0.9995
    assert 0.3 < np.sqrt(np.mean(z**2)) < 2.0  # the sigmas are neither far too small nor far too large


def test_free_network_cauchy_without_covariance(small_chunks):
    """As in the orientation (sfm/reconstruction.py): free network, robust loss, no covariance."""
    pb, _ = build_block(gauge="inner", seed=7)
    opt = dict(loss="cauchy", loss_scale=2.0, compute_covariance=False, compute_redundancy=False)
    ra = solve(pb, SolverOptions(chunked_min_observations=FULL, **opt))
    rb = solve(pb, SolverOptions(chunked_min_observations=CHUNKED, **opt))
    _compare(ra, rb, cov=False)
    assert ra.std is None and rb.std is None


def test_redundancy_and_point_covariance_fall_back_to_the_full_jacobian(small_chunks):
    """The LM steps are chunked, the precision step (redundancy numbers, point covariances) is not."""
    pb, _ = build_block(seed=11)
    opt = dict(compute_redundancy=True, compute_point_covariance=True)
    ra = solve(pb, SolverOptions(chunked_min_observations=FULL, **opt))
    rb = solve(pb, SolverOptions(chunked_min_observations=CHUNKED, **opt))
    _compare(ra, rb)
    np.testing.assert_allclose(rb.image_redundancy, ra.image_redundancy, rtol=0, atol=1e-9)
    free = np.all(np.isfinite(ra.point_covariance), axis=(1, 2))
    np.testing.assert_allclose(rb.point_covariance[free], ra.point_covariance[free], rtol=1e-7, atol=1e-16)


def test_reduced_system_and_step_equal_the_full_path(small_chunks):
    """One linearisation, two dampings (the second is the pass of a rejected LM step): reduced matrix,
    right-hand side and refined step of the chunked path equal those of the full Jacobian."""
    pb, _ = build_block(rig=True, seed=13)
    opt = SolverOptions(loss="huber")
    pb = pb.copy()
    lay = S._Layout(pb)
    st = S._State(pb)
    data = S._Data(pb, np.ones(sum(len(o.point) for o in pb._img), dtype=bool))
    r = S._evaluate(pb, lay, st, data, False)
    w, _ = S._robust(r, data.K, opt)
    ch = S._ChunkedNormal(pb, lay, st, data, r, w, 1e-3)
    r2, *jac, pslot = S._evaluate(pb, lay, st, data, True)
    np.testing.assert_allclose(r2, r, rtol=1e-10, atol=1e-12)  # project() and project_jacobian(): rounding apart
    full = S._Normal(r2, jac, pslot, lay, w)
    np.testing.assert_allclose(ch.gc, full.gc, rtol=1e-12, atol=1e-9 * np.max(np.abs(full.gc)))
    np.testing.assert_allclose(ch.gp, full.gp, rtol=1e-12, atol=1e-9 * np.max(np.abs(full.gp)))
    np.testing.assert_allclose(ch.V, full.V, rtol=1e-12, atol=1e-12 * np.max(np.abs(full.V)))
    np.testing.assert_allclose(ch.U.toarray(), full.U, rtol=1e-12, atol=1e-12 * np.max(np.abs(full.U)))
    for lam in (1e-3, 1e-1):  # the first comes from the construction pass, the second from a new pass
        Sc, rc, Vc, _ = ch.schur(lam)
        Sf, rf, Vf, _ = full.schur(lam)
        assert sp.issparse(Sc) and isinstance(Sf, np.ndarray)  # sparse reduced matrix in the chunked path only
        big = np.max(np.abs(Sf))
        np.testing.assert_allclose(Sc.toarray(), Sf, rtol=0, atol=1e-12 * big)
        np.testing.assert_allclose(rc, rf, rtol=0, atol=1e-12 * np.max(np.abs(rf)))
        np.testing.assert_allclose(Vc, Vf, rtol=1e-12, atol=0)
        cf = S._cho_factor(Sc)
        d = ch.step(cf, Vc, rc, lam)
        cff = S._cho_factor(Sf)
        dref = full.solve_with(cff, Vf, full.gc, full.gp, rf)
        # the exact solution of the damped system: both within rounding of it
        np.testing.assert_allclose(d, dref, rtol=0, atol=1e-8 * np.max(np.abs(dref)))


def test_chunks_cover_every_observation_and_point_once(small_chunks):
    pb, _ = build_block(rig=True)
    lay = S._Layout(pb)
    data = S._Data(pb, np.ones(sum(len(o.point) for o in pb._img), dtype=bool))
    order, chunks = S._point_chunks(lay, data)
    np.testing.assert_array_equal(np.sort(order), np.arange(data.K))
    slot = lay.point_slot[data.pt]
    seen_pts = np.zeros(lay.npf, int)
    covered = np.zeros(data.K, int)
    assert len(chunks) > 20
    for o0, o1, p0, p1 in chunks:
        covered[o0:o1] += 1
        s = slot[order[o0:o1]]
        if p0 < 0:
            assert np.all(s < 0)
        else:
            assert np.all((s >= p0) & (s < p1))
            seen_pts[p0:p1] += 1
    np.testing.assert_array_equal(covered, 1)
    np.testing.assert_array_equal(seen_pts, 1)
    # every observation of a free point lies in the chunk of its point
    assert np.sum(slot >= 0) == sum(o1 - o0 for o0, o1, p0, _ in chunks if p0 >= 0)


def test_threshold_option(monkeypatch):
    with pytest.raises(ConfigError, match="chunked_min_observations"):
        SolverOptions(chunked_min_observations=-1)
    # small problems keep the full-Jacobian path by default
    assert SolverOptions().chunked_min_observations > 10_000

    def boom(*a, **k):
        raise AssertionError("chunked path used below the threshold")

    monkeypatch.setattr(trust_region, "ChunkedNormal", boom)  # (where the LM and the precision step look it up)
    monkeypatch.setattr(precision, "ChunkedNormal", boom)
    pb, _ = build_block(n_lines=2, per_line=4, n_points=200)
    assert solve(pb, SolverOptions(compute_redundancy=False)).success


def test_sparse_reduced_system_gives_the_dense_solution_and_pose_sigmas(small_chunks, monkeypatch):
    """The chunked path's reduced camera system is sparse (camera-camera blocks only where two frames share
    points; SuperLU with a symmetric ordering) and gives the solution and the pose sigmas of the full path's
    dense Cholesky. A wider block (8 lines of 5 frames) so that most frame pairs share no point.

    Tolerances as in :func:`_compare`: both factorisations are backward stable on a positive definite matrix,
    so the steps differ by the matrix's condition times 1e-16 (measured: centres 1e-13 m, sigmas < 1e-9
    relative), far below the asserted 1e-7 m / 1e-7 relative and far below the sigmas themselves (cm)."""
    pb, truth = build_block(n_lines=8, per_line=5, n_points=900, seed=21, plane=False)
    seen = []
    orig = S._SparseFactor.__init__

    def spy(self, A):
        seen.append((A.nnz, A.shape[0]))
        orig(self, A)

    monkeypatch.setattr(S._SparseFactor, "__init__", spy)
    opt = dict(loss="huber", compute_redundancy=False)
    ra = solve(pb, SolverOptions(chunked_min_observations=FULL, **opt))
    assert not seen  # the full path keeps its dense Cholesky
    rb = solve(pb, SolverOptions(chunked_min_observations=CHUNKED, **opt))
    assert seen  # every LM step and the precision step factor the sparse matrix
    nnz, nc = seen[0]
    assert nnz < 0.6 * nc * nc  # sparse indeed: frames far apart share no point
    _compare(ra, rb)
    np.testing.assert_allclose(rb.covariance, ra.covariance, rtol=1e-7, atol=1e-7 * np.max(np.abs(ra.covariance)))
    # and the sigmas are right: centres within their sigmas of the truth
    z = (_centres(rb) - truth["C"]) / rb.pose_std[:, 3:]
    assert np.max(np.abs(z)) < 4.5  # 120 normalised errors: |z| < 4.5 with probability ~0.999
    assert 0.3 < np.sqrt(np.mean(z**2)) < 2.0


def test_datum_defect_is_reported_by_the_sparse_path(small_chunks):
    """No GNSS, no control: the precision step finds the 7-parameter defect on the sparse reduced matrix (the
    dense path's eigenvalue test, here by Lanczos on the matrix and on solves with its factor)."""
    pb, _ = build_block(datum=False, plane=False, outliers=0, seed=5)
    for chunked in (FULL, CHUNKED):
        res = solve(pb, SolverOptions(chunked_min_observations=chunked, compute_redundancy=False))
        assert res.termination is Termination.RANK_DEFICIENT, (chunked, res.reason)
        assert "undetermined" in res.reason and "null direction involves" in res.reason


def test_sparse_rank_test_against_the_eigenvalues():
    """``_sparse_rank_test`` against numpy's eigenvalues: a well-conditioned matrix passes, a singular one
    (graph Laplacian of a path: null vector = ones) and a nearly singular one fail, with their condition."""
    rng = np.random.default_rng(0)
    n = 60
    A = sp.random(n, n, density=0.05, random_state=1) + sp.eye(n) * 3.0
    M = (A.T @ A).tocsc()
    d = np.sqrt(M.diagonal())
    Mn = (sp.diags(1 / d) @ M @ sp.diags(1 / d)).tocsc()
    assert S._sparse_rank_test(Mn, 1e-12) is None
    L = sp.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tolil()
    L[0, 0] = L[n - 1, n - 1] = 1.0  # path Laplacian: singular
    L = L.tocsc()
    out = S._sparse_rank_test((L / 2.0).tocsc(), 1e-12)
    assert out is not None and out[0] > 1e12
    # nearly singular: smallest eigenvalue 1e-14 of the largest; the condition is reported within Lanczos' 1e-8
    Qr, _ = np.linalg.qr(rng.normal(size=(n, n)))
    ev = np.geomspace(1e-14, 1.0, n)
    N = sp.csc_matrix((Qr * ev) @ Qr.T)
    out = S._sparse_rank_test(N, 1e-12)
    assert out is not None
    assert out[0] == pytest.approx(1e14, rel=1e-2)  # (rounding of the dense matrix: 1e-16 absolute on 1e-14)
    assert S._sparse_rank_test(N, 1e-15) is None
