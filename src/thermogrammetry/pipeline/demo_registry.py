"""The demo's vocabulary: rows (achieved vs bound), sections, options, the result, the section registry,
and :class:`PrefixedProject` (a section's own key prefix in the shared demo store).

Re-exported by :mod:`thermogrammetry.pipeline.demo` (import them from there).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Callable

from ..errors import ConfigError
from .project import ProjectStore
from .steps import StepReport

__all__ = [
    "DemoRow",
    "DemoSection",
    "DemoOptions",
    "DemoResult",
    "DEMO_SECTIONS",
    "SECTION_MODULES",
    "register_section",
    "PrefixedProject",
]


@dataclass
class DemoRow:
    """One achieved-vs-truth figure with its bound."""

    section: str
    check: str
    value: float
    bound: float | None
    unit: str = ""
    kind: str = "max"  # "max": value <= bound passes; "min": value >= bound; "info": never fails
    note: str = ""

    @property
    def passed(self) -> bool:
        if self.kind == "info" or self.bound is None:
            return True
        v = float(self.value)
        if not math.isfinite(v):
            return False
        return v <= self.bound if self.kind == "max" else v >= self.bound

    def to_dict(self) -> dict:
        d = asdict(self)
        d["passed"] = self.passed
        return d


@dataclass(frozen=True)
class DemoSection:
    name: str
    title: str
    run: Callable[[ProjectStore, "DemoOptions"], list[DemoRow]]


@dataclass(frozen=True)
class DemoOptions:
    """``seed``: every scene's seed offset; ``sections``: names to run (None = all); ``threads``."""

    seed: int = 0
    sections: tuple[str, ...] | None = None
    threads: int = 2


@dataclass
class DemoResult:
    rows: list[DemoRow]
    reports: list[StepReport]
    seconds: float

    @property
    def ok(self) -> bool:
        return all(r.passed for r in self.rows) and all(r.ok for r in self.reports)


#: the registry, in run order
DEMO_SECTIONS: list[DemoSection] = []

#: modules imported before a run so that their sections register themselves
SECTION_MODULES: tuple[str, ...] = ("thermogrammetry.pipeline.demo_survey",)


def register_section(section: DemoSection, *, replace: bool = True) -> None:
    """Add ``section`` to the registry (replacing one of the same name when ``replace``)."""
    for i, s in enumerate(DEMO_SECTIONS):
        if s.name == section.name:
            if not replace:
                raise ConfigError(f"demo section {section.name!r} is already registered")
            DEMO_SECTIONS[i] = section
            return
    DEMO_SECTIONS.append(section)


class PrefixedProject(ProjectStore):
    """A view of ``parent`` whose keys live under ``prefix`` (so a workflow writing ``inputs/...``
    can share a demo folder with the others)."""

    def __init__(self, parent: ProjectStore, prefix: str):
        self.parent = parent
        self.prefix = prefix.rstrip("/") + "/"

    def write_bytes(self, key, data):
        self.parent.write_bytes(self.prefix + key, data)

    def read_bytes(self, key):
        return self.parent.read_bytes(self.prefix + key)

    def exists(self, key):
        return self.parent.exists(self.prefix + key)

    def keys(self, prefix=""):
        n = len(self.prefix)
        return [k[n:] for k in self.parent.keys(self.prefix + prefix)]

    def describe(self, key):
        return self.parent.describe(self.prefix + key)

    def local_path(self, key):
        return self.parent.local_path(self.prefix + key)
