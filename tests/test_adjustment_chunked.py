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
from thermogrammetry.adjustment import solver as S
from thermogrammetry.errors import ConfigError

FULL = 10**12  # chunked_min_observations: never chunked
CHUNKED = 0  # always chunked


@pytest.fixture
def small_chunks(monkeypatch):
    monkeypatch.setattr(S, "_SCHUR_CHUNK", 64)


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

    monkeypatch.setattr(S, "_ChunkedNormal", boom)
    pb, _ = build_block(n_lines=2, per_line=4, n_points=200)
    assert solve(pb, SolverOptions(compute_redundancy=False)).success
