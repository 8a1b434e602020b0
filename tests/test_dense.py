"""Dense least-squares kernel: textbook answers, precision, failures as values."""

import numpy as np
import pytest

from thermogrammetry.adjustment.dense import DenseOptions, solve_dense, solve_dense_batch
from thermogrammetry.errors import ConfigError, ShapeError
from thermogrammetry.results import Termination


def _line(t, y, w=None):
    def fun(x):
        return x[0] + x[1] * t - y, np.stack([np.ones_like(t), t], 1)

    return fun


def test_linear_matches_textbook(rng):
    t = np.linspace(0, 10, 25)
    y = 2.0 + 0.5 * t + rng.normal(0, 0.1, t.size)
    w = rng.uniform(0.5, 2.0, t.size)
    res = solve_dense(_line(t, y), [0.0, 0.0], weights=w, param_names=["a", "b"])
    assert res.termination is Termination.CONVERGED
    A = np.stack([np.ones_like(t), t], 1)
    N = A.T @ (w[:, None] * A)
    x = np.linalg.solve(N, A.T @ (w * y))
    assert np.allclose(res.x, x, rtol=0, atol=1e-10)
    v = A @ x - y
    s02 = (v * w) @ v / (t.size - 2)
    assert abs(res.sigma0**2 / s02 - 1) < 1e-9
    assert np.allclose(res.covariance, s02 * np.linalg.inv(N), rtol=1e-9, atol=0)
    assert np.allclose(res.covariance_prior, np.linalg.inv(N), rtol=1e-9, atol=0)
    assert res.redundancy == t.size - 2
    assert abs(np.sum(res.redundancy_numbers) - res.redundancy) < 1e-9
    assert np.all((res.redundancy_numbers > 0) & (res.redundancy_numbers < 1))
    assert set(res.named()) == {"a", "b"}


def test_full_covariance_equals_whitening(rng):
    t = np.linspace(0, 1, 8)
    y = 1 + 3 * t + rng.normal(0, 0.05, t.size)
    B = rng.normal(size=(8, 8)) * 0.01
    S = B @ B.T + np.eye(8) * 0.0025
    res = solve_dense(_line(t, y), [0.0, 0.0], cov=S, sigma0_prior=1.0)
    A = np.stack([np.ones_like(t), t], 1)
    P = np.linalg.inv(S)
    N = A.T @ P @ A
    x = np.linalg.solve(N, A.T @ P @ y)
    assert np.allclose(res.x, x, atol=1e-10)
    assert np.allclose(res.covariance_prior, np.linalg.inv(N), rtol=1e-9)
    Qvv = S - A @ np.linalg.inv(N) @ A.T
    assert np.allclose(res.redundancy_numbers, np.diag(Qvv @ P), atol=1e-9)


def test_nonlinear_monte_carlo_matches_prior_covariance():
    # y = a·exp(b·t) + noise σ = 0.02; scatter of 400 seeded runs vs σ0²·N⁻¹
    t = np.linspace(0, 2, 15)
    a, b, sig = 1.5, -0.7, 0.02
    rng = np.random.default_rng(7)
    Y = a * np.exp(b * t) + rng.normal(0, sig, (400, t.size))

    def fun(X, idx):
        e = np.exp(X[:, 1:2] * t)
        V = X[:, :1] * e - Y[idx]
        J = np.stack([e, X[:, :1] * t * e], -1)
        return V, J

    res = solve_dense_batch(fun, np.tile([1.0, -0.5], (400, 1)), weights=np.full((400, t.size), 1 / sig**2))
    assert res.outcome.termination is Termination.CONVERGED
    sd_mc = res.x.std(axis=0, ddof=1)
    sd_rep = np.sqrt(np.diagonal(res.covariance_prior.mean(0)))
    # 400 runs: relative sampling error of a std ≈ 1/√(2·399) ≈ 3.5 % → ±12 % is > 3σ
    assert np.all(np.abs(sd_mc / sd_rep - 1) < 0.12), (sd_mc, sd_rep)
    # a-posteriori σ0 averages to 1 (its own scatter is √(1/(2·13)) ≈ 0.2 per run → mean over 400 within 3 %)
    assert abs(np.mean(res.sigma0**2) - 1) < 0.08
    # single solve agrees with the batch solve
    def f1(x):
        V, J = fun(x[None], np.array([0]))
        return V[0], J[0]
    r1 = solve_dense(f1, [1.0, -0.5], weights=np.full(t.size, 1 / sig**2))
    assert np.allclose(r1.x, res.x[0], atol=1e-9)
    assert np.allclose(r1.covariance, res.covariance[0], rtol=1e-6)


def test_rank_deficient_is_a_result_naming_parameters():
    t = np.linspace(0, 1, 10)

    def fun(x):  # a and c enter only as a + c
        return x[0] + x[2] + x[1] * t - t, np.stack([np.ones_like(t), t, np.ones_like(t)], 1)

    res = solve_dense(fun, [0.1, 0.0, 0.2], param_names=["a", "b", "c"])
    assert res.termination is Termination.RANK_DEFICIENT
    assert "a" in res.reason and "c" in res.reason and "'b'" not in res.reason
    assert np.all(np.isnan(res.covariance))
    # fixing c removes the deficiency
    res2 = solve_dense(fun, [0.1, 0.0, 0.2], param_names=["a", "b", "c"], fixed=["c"])
    assert res2.termination is Termination.CONVERGED
    assert abs(res2.x[0] + 0.2) < 1e-10 and res2.x[2] == 0.2 and res2.covariance[2, 2] == 0


def test_linear_constraint_matches_lagrange(rng):
    t = np.linspace(0, 1, 12)
    y = 0.3 + 0.6 * t + rng.normal(0, 0.01, t.size)
    A = np.stack([np.ones_like(t), t], 1)
    C = np.array([[1.0, 1.0]])
    res = solve_dense(_line(t, y), [0.0, 0.0], constraints=lambda x: (C @ x - 1.0, C))
    N = A.T @ A
    K = np.block([[N, C.T], [C, np.zeros((1, 1))]])
    sol = np.linalg.solve(K, np.r_[A.T @ y, 1.0])
    assert np.allclose(res.x, sol[:2], atol=1e-10)
    Qc = np.linalg.inv(K)[:2, :2]
    assert np.allclose(res.cofactor, Qc, atol=1e-12)
    assert res.redundancy == t.size - 2 + 1


def test_max_iterations_and_too_few():
    t = np.linspace(0, 2, 10)
    y = 2 * np.exp(-t)

    def fun(x):
        e = np.exp(x[1] * t)
        return x[0] * e - y, np.stack([e, x[0] * t * e], 1)

    r = solve_dense(fun, [0.5, 0.5], options=DenseOptions(max_iterations=1))
    assert r.termination is Termination.MAX_ITERATIONS and "1 iterations" in r.reason
    r = solve_dense(fun, [0.5, 0.5])
    assert r.termination is Termination.CONVERGED and np.allclose(r.x, [2, -1], atol=1e-9)
    r = solve_dense(lambda x: (x[:1] - 1, np.array([[1.0, 1.0]])), [0.0, 0.0])
    assert r.termination is Termination.TOO_FEW_OBSERVATIONS


def test_bad_options_and_shapes():
    with pytest.raises(ConfigError, match="unknown dense solver option"):
        DenseOptions.from_dict({"max_iter": 3})
    with pytest.raises(ConfigError, match="damping"):
        DenseOptions(damping="dogleg")
    with pytest.raises(ShapeError, match="weights"):
        solve_dense(_line(np.arange(3.0), np.arange(3.0)), [0, 0], weights=[1, 1])
    with pytest.raises(ShapeError, match="Jacobian"):
        solve_dense(lambda x: (np.zeros(3), np.zeros((3, 3))), [0, 0])


def test_start_at_minimum_stops_without_trials(rng):
    t = np.linspace(0, 10, 25)
    y = 2.0 + 0.5 * t + rng.normal(0, 0.1, t.size)
    A = np.stack([np.ones_like(t), t], 1)
    x = np.linalg.lstsq(A, y, rcond=None)[0]
    calls = []

    def fun(p):
        calls.append(1)
        return A @ p - y, A

    res = solve_dense(fun, x)
    assert res.termination is Termination.CONVERGED and res.iterations == 0 and "decrease" in res.reason
    assert len(calls) == 1  # no damped trial steps were evaluated
    assert np.all(np.isfinite(res.covariance))
