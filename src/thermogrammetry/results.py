"""Outcome of an estimate: a failure is a value with a reason, not an exception.

Every solver in the project returns a result object that carries a
:class:`Termination` and a human-readable ``reason``. Bad input (wrong shapes,
NaN, too few points known before solving) raises from
:mod:`thermogrammetry.errors` instead.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

__all__ = ["Termination", "Outcome", "HasOutcome"]


class Termination(str, enum.Enum):
    """Why an estimate stopped."""

    CONVERGED = "converged"                      # a stopping rule on cost/step/gradient was met
    MAX_ITERATIONS = "max_iterations"            # ran out of iterations before converging
    DEGENERATE = "degenerate"                    # geometry does not determine the unknowns
    TOO_FEW_OBSERVATIONS = "too_few_observations"
    RANK_DEFICIENT = "rank_deficient"            # e.g. undefined gauge / datum
    DIVERGED = "diverged"
    NUMERICAL_FAILURE = "numerical_failure"      # NaN/inf during the solve, failed factorisation

    @property
    def success(self) -> bool:
        return self in (Termination.CONVERGED, Termination.MAX_ITERATIONS)

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class Outcome:
    """Termination plus an explanation; embed in result dataclasses."""

    termination: Termination
    reason: str = ""

    @property
    def success(self) -> bool:
        """True when an estimate is available (converged, or stopped at the iteration limit)."""
        return self.termination.success


class HasOutcome:
    """Mixin for result dataclasses with an ``outcome: Outcome`` field: exposes
    ``termination``, ``reason`` and ``success`` directly on the result."""

    outcome: Outcome

    @property
    def termination(self) -> Termination:
        return self.outcome.termination

    @property
    def reason(self) -> str:
        return self.outcome.reason

    @property
    def success(self) -> bool:
        return self.outcome.success
