"""A pipeline is a list of small steps that share nothing in memory.

Each :class:`Step` reads its inputs from the project store and writes its outputs
there; :func:`run_steps` times each one and writes ``reports/<step>.json`` with its
status, wall time and the small summary the step returned. A failing step stops the
pipeline and is reported, with the steps before it kept.
"""

from __future__ import annotations

import time
import traceback
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Sequence

from .project import ProjectStore

__all__ = ["Step", "StepReport", "run_steps"]


@dataclass(frozen=True)
class Step:
    """A named unit of work: ``run(project) -> summary dict`` (small, JSON-serialisable)."""

    name: str
    run: Callable[[ProjectStore], dict[str, Any] | None]
    description: str = ""


@dataclass
class StepReport:
    name: str
    status: str  # "ok" | "failed"
    seconds: float
    summary: dict[str, Any] = field(default_factory=dict)
    error: str = ""

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def run_steps(
    project: ProjectStore,
    steps: Sequence[Step],
    *,
    on_step: Callable[[StepReport], None] | None = None,
    report_prefix: str = "reports",
) -> list[StepReport]:
    """Run ``steps`` in order; stop at the first failure. Returns one report per step run."""
    reports: list[StepReport] = []
    for step in steps:
        t0 = time.perf_counter()
        try:
            summary = step.run(project) or {}
            rep = StepReport(step.name, "ok", time.perf_counter() - t0, dict(summary))
        except Exception as exc:  # a failed step is reported, not swallowed: the caller sees status
            rep = StepReport(
                step.name,
                "failed",
                time.perf_counter() - t0,
                error=f"{type(exc).__name__}: {exc}",
                summary={"traceback": traceback.format_exc(limit=8)},
            )
        project.write_json(f"{report_prefix}/{step.name}.json", asdict(rep))
        reports.append(rep)
        if on_step is not None:
            on_step(rep)
        if not rep.ok:
            break
    return reports
