"""Workflows as ordered steps over a project store (folder or in-memory twin)."""

from .project import FolderProject, MemoryProject, ProjectStore, write_atomic
from .steps import Step, StepReport, run_steps

__all__ = ["ProjectStore", "FolderProject", "MemoryProject", "write_atomic", "Step", "StepReport", "run_steps"]
