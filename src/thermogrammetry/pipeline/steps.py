"""Moved to :mod:`thermogrammetry.store`; this name keeps working."""

from ..store import Step, StepReport, run_steps

__all__ = ["Step", "StepReport", "run_steps"]
