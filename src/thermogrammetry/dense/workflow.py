"""Moved: the ``dense`` verb's driver is :mod:`thermogrammetry.pipeline.dense`, the survey folder's frames are
:mod:`thermogrammetry.pipeline.frames`, and the task runner is :mod:`thermogrammetry.tasks`.

This module keeps the old import path working (``from thermogrammetry.dense.workflow import run_dense``); the
dense-matching algorithms stay in :mod:`thermogrammetry.dense` (``fusion``, ``rectify``, ``stereo``).
"""

from __future__ import annotations

from ..tasks import open_client, ordered_results

__all__ = ["SurveyFrames", "run_dense", "open_client", "ordered_results"]

_MOVED = {"run_dense": "thermogrammetry.pipeline.dense", "SurveyFrames": "thermogrammetry.pipeline.frames",
          "_reference_task": "thermogrammetry.pipeline.dense"}


def __getattr__(name):
    """Compatibility re-export of the names that moved up to the driver layer (see the module docstring)."""
    if name == "_survey":  # the per-process survey cache is pipeline.frames.open_survey now
        import importlib

        return getattr(importlib.import_module("thermogrammetry.pipeline.frames"), "open_survey")
    if name in _MOVED:
        import importlib

        return getattr(importlib.import_module(_MOVED[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
