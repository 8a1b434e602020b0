"""Units of work run in-process or on a dask cluster (the ``inputs``, ``features`` and ``matching`` steps)."""

from __future__ import annotations

import contextlib
from dataclasses import replace
from typing import Callable

from ..._memory import release_free_heap
from ...tasks import TASKS_IN_FLIGHT, local_cluster, run_tasks
from .options import SurveyOptions
from .store import _NPZ_CACHE


#: tasks submitted to the cluster and not yet collected, at most (:func:`thermogrammetry.tasks.run_tasks`)
_TASKS_IN_FLIGHT = TASKS_IN_FLIGHT


def _run_tasks(fn, tasks, opt: SurveyOptions, progress: Callable | None, what: str):
    """Run tasks on the task runner (:func:`thermogrammetry.tasks.run_tasks`: in this process for ``workers`` 0 or 1,
    a local dask cluster for ``workers`` >= 2, or ``scheduler``); results in task order."""
    return run_tasks(fn, tasks, workers=opt.workers, scheduler=opt.scheduler, progress=progress)


#: the survey's steps that run tasks on the local cluster (:func:`run_survey`), in their order
_TASK_STEPS = ("inputs", "features", "matching")


def _release_task_state() -> None:
    """After the steps that run tasks: this process's feature cache and matching work arrays, the cluster's and the tasks' freed objects
    (``gc``), and the heap's free pages (:func:`thermogrammetry._memory.release_free_heap`)."""
    import gc

    from ...sfm.matching import release_scratch

    _NPZ_CACHE.clear()
    release_scratch()
    gc.collect()
    release_free_heap()


@contextlib.contextmanager
def _local_cluster(opt: SurveyOptions):
    """One local dask cluster for every step that runs tasks (started once, not per step: ~2-4 s each).

    Yields the options with ``scheduler`` set to its address; unchanged when the tasks run in this process
    (``workers`` 0 or 1) or a scheduler was given (:func:`thermogrammetry.tasks.local_cluster`).
    """
    with local_cluster(opt.workers, opt.scheduler) as address:
        yield opt if address is None or address == opt.scheduler else replace(opt, scheduler=address)
