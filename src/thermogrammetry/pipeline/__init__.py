"""Workflows as ordered steps over a project store (folder or in-memory twin).

One driver per verb lives here; the store itself (:mod:`thermogrammetry.store`) is in the foundation.
"""

from ..store import FolderProject, MemoryProject, ProjectStore, Step, StepReport, run_steps, write_atomic

__all__ = ["ProjectStore", "FolderProject", "MemoryProject", "write_atomic", "Step", "StepReport", "run_steps"]
