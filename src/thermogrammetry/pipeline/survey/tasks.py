"""Units of work run in-process or on a dask cluster (the ``inputs``, ``features`` and ``matching`` steps)."""

from __future__ import annotations

import contextlib
import itertools
from dataclasses import replace
from typing import Callable

from ..._memory import release_free_heap
from .options import SurveyOptions
from .store import _NPZ_CACHE


#: tasks submitted to the cluster and not yet collected, at most (:func:`_run_tasks`)
_TASKS_IN_FLIGHT = 64


def _run_tasks(fn, tasks, opt: SurveyOptions, progress: Callable | None, what: str):
    """Run tasks in-process, on a local dask cluster (``workers``) or on ``scheduler``; results in task order."""
    n = len(tasks)
    if n == 0:
        return []
    if opt.scheduler is None and opt.workers == 0:
        out = []
        for k, t in enumerate(tasks):
            out.append(fn(t))
            if progress:
                progress(k + 1, n)
        return out
    from distributed import Client, as_completed

    with _local_cluster(opt) as run_opt:  # a cluster of its own only when the caller did not start one
        client = Client(run_opt.scheduler)
        try:
            # at most _TASKS_IN_FLIGHT tasks submitted and not yet collected: the scheduler's and the workers'
            # state per task (its arguments, its result) does not grow with the block; tasks are submitted in
            # their order and each result is released as soon as it is collected
            pending = iter(enumerate(tasks))
            pos = {}
            ac = as_completed()

            def submit(count):
                for k, t in itertools.islice(pending, count):
                    f = client.submit(fn, t, pure=False)
                    pos[f.key] = k
                    ac.add(f)

            submit(_TASKS_IN_FLIGHT)
            out = [None] * n
            for done, fut in enumerate(ac, 1):
                out[pos.pop(fut.key)] = fut.result()
                fut.release()
                del fut
                submit(1)
                if progress:
                    progress(done, n)
            return out
        finally:
            client.close()


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

    Yields the options with ``scheduler`` set to its address; unchanged when ``workers`` is 0 or a
    scheduler was given.
    """
    if opt.scheduler is not None or opt.workers == 0:
        yield opt
        return
    from distributed import LocalCluster

    cluster = LocalCluster(n_workers=int(opt.workers), threads_per_worker=1, processes=True, dashboard_address=":0",
                           silence_logs=40)
    try:
        yield replace(opt, scheduler=cluster.scheduler_address)
    finally:
        cluster.close()
