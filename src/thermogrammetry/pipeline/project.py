"""Moved to :mod:`thermogrammetry.store`; this name keeps working."""

from ..store import FolderProject, MemoryProject, ProjectStore, write_atomic

__all__ = ["ProjectStore", "FolderProject", "MemoryProject", "write_atomic"]
