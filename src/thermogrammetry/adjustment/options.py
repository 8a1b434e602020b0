"""How an adjustment is solved: :class:`SolverOptions` (the problem, :class:`~thermogrammetry.adjustment.problem.BundleProblem`,
says what is estimated) and the robust :class:`Loss` on image points."""

from __future__ import annotations

from dataclasses import dataclass, fields

from ..enums import StrChoice
from ..errors import ConfigError

__all__ = ["Loss", "SolverOptions"]


class Loss(StrChoice):
    TRIVIAL = "trivial"
    HUBER = "huber"
    CAUCHY = "cauchy"


@dataclass(frozen=True)
class SolverOptions:
    """How the adjustment is solved (the problem says what is estimated).

    Attributes
    ----------
    max_iterations : int
        LM steps (accepted + rejected) per solve.
    function_tolerance, gradient_tolerance, parameter_tolerance : float
        Ceres-style stopping rules (see :mod:`thermogrammetry.adjustment.bal`); also converged
        when the predicted decrease is below ``function_tolerance * cost``. The cost is
        ``chi^2 / 2``: a relative change of 1e-8 moves well-determined parameters by far less
        than 0.01 sigma in networks of up to ~1e5 observations.
    initial_trust_region_radius : float
    loss : Loss
        Robust loss on image points (``trivial``, ``huber``, ``cauchy``).
    loss_scale : float
        Scale of the loss in units of the whitened residual norm (i.e. in sigmas).
    sigma0_prior : float
        A priori standard deviation of unit weight (1 when the stated sigmas are right).
    compute_covariance : bool
    compute_point_covariance : bool
    compute_redundancy : bool
        Redundancy numbers and w-tests (needs the covariance).
    data_snooping : bool
        Iteratively reject image points whose w-test fails.
    snooping_alpha : float
        Two-sided significance level of a single w-test (0.001 -> 3.29).
    max_snooping_rounds : int
    correlation_warning : float
        Warn for |rho| above this between camera-side parameters.
    significance_alpha : float
        Two-sided level of the t-test of additional parameters.
    rank_tolerance : float
        Smallest eigenvalue / largest of the Jacobi-scaled reduced normal matrix below which the
        problem is rank deficient.
    max_dense_inner : int
        Largest parameter count for which the free-network (inner constraint) covariance is
        computed (dense).
    chunked_min_observations : int
        Number of (active) image observations from which the normal equations are built chunk by
        chunk of points without holding the block's Jacobian (memory independent of the number of
        observations, instead of ~1 KB per observation; a second pass over the Jacobians per LM
        step, and one per rejected step). Same solution up to rounding. 0: always; a huge number:
        never. The covariance step falls back to the full Jacobian when it needs it (redundancy
        numbers, point covariances, free-network covariance).
    num_threads : int
        Threads for the largest sparse products of the normal equations on the full-Jacobian path (rows split
        over threads; the same values, bit for bit, with any count).
    """

    max_iterations: int = 100
    function_tolerance: float = 1e-8
    gradient_tolerance: float = 1e-12
    parameter_tolerance: float = 1e-10
    initial_trust_region_radius: float = 1e4
    loss: Loss = Loss.TRIVIAL
    loss_scale: float = 3.0
    sigma0_prior: float = 1.0
    compute_covariance: bool = True
    compute_point_covariance: bool = False
    compute_redundancy: bool = True
    data_snooping: bool = False
    snooping_alpha: float = 0.001
    max_snooping_rounds: int = 50
    correlation_warning: float = 0.9
    significance_alpha: float = 0.05
    rank_tolerance: float = 1e-12
    max_dense_inner: int = 4000
    chunked_min_observations: int = 400_000
    num_threads: int = 2

    def __post_init__(self):
        object.__setattr__(self, "loss", Loss(self.loss))
        if self.max_iterations < 0:
            raise ConfigError(f"max_iterations={self.max_iterations!r}; expected an integer >= 0")
        if self.num_threads < 1:
            raise ConfigError(f"num_threads={self.num_threads!r}; expected an integer >= 1")
        if self.chunked_min_observations < 0:
            raise ConfigError(f"chunked_min_observations={self.chunked_min_observations!r}; expected an integer >= 0")
        for name in ("loss_scale", "sigma0_prior", "snooping_alpha", "significance_alpha"):
            v = getattr(self, name)
            if not (v > 0):
                raise ConfigError(f"{name}={v!r}; expected a number > 0")

    @classmethod
    def from_dict(cls, d: dict) -> "SolverOptions":
        known = {f.name for f in fields(cls)}
        bad = set(d) - known
        if bad:
            raise ConfigError(f"unknown solver option(s) {sorted(bad)}; expected some of {sorted(known)}")
        return cls(**d)
