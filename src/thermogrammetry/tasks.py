"""The one task runner: where a verb's per-image, per-pair and per-tile tasks run.

Every verb that runs tasks takes the same two settings and gives them one meaning:

- ``workers`` 0 or 1 (and no scheduler): the tasks run one after the other in this process;
- ``workers`` N >= 2: a local dask.distributed cluster of N single-threaded worker processes, started for the
  run and closed after it;
- ``scheduler`` ADDRESS (``tcp://host:8786``): the tasks run on an existing cluster that the user started
  (``dask scheduler`` and ``dask worker`` processes); ``workers`` is then ignored.

Results always come back in task order, so the outputs are the same whichever way the tasks ran. At most a
bounded number of tasks are submitted and not yet collected, and each result is released as soon as it is
collected: the scheduler's and the workers' memory do not grow with the block.
"""

from __future__ import annotations

import contextlib
import itertools
from typing import Any, Callable, Iterator, Sequence

__all__ = ["in_process", "local_cluster", "open_client", "ordered_results", "run_tasks", "check_workers", "cores", "default_workers",
           "TASKS_IN_FLIGHT"]

#: tasks submitted to a cluster and not yet collected, at most (:func:`run_tasks`)
TASKS_IN_FLIGHT = 64


def cores() -> int:
    """The cores this process may run on (its CPU affinity; ``os.cpu_count()`` where that is not known)."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


#: worker processes allowed on any machine (the verbs' default ``--workers 2``, which a single-core machine runs too)
ALWAYS_ALLOWED_WORKERS = 2


def check_workers(workers, scheduler: str | None = None) -> int:
    """``workers`` as an int after checking it: >= 0, and at most :func:`cores` (or :data:`ALWAYS_ALLOWED_WORKERS`
    where there are fewer cores) unless a ``scheduler`` is given (a cluster's workers are the cluster's business).
    Raises :class:`~thermogrammetry.errors.ConfigError` naming the value and the core count."""
    from .errors import ConfigError

    if isinstance(workers, bool) or not isinstance(workers, (int, float)) or int(workers) != workers or workers < 0:
        raise ConfigError(f"--workers {workers!r}: expected a whole number >= 0 (0 or 1 = in this process)")
    n = int(workers)
    limit = max(cores(), ALWAYS_ALLOWED_WORKERS)
    if scheduler is None and n > limit:
        raise ConfigError(f"--workers {n}: more worker processes than the {cores()} core(s) of this machine; expected "
                          f"at most {limit} (or --scheduler ADDRESS to run on a cluster of your own)")
    return n


def default_workers(workers: int | None) -> int:
    """``workers`` when given, else the verbs' default: 2 local worker processes, 1 (in this process) on a single core."""
    return min(2, cores()) if workers is None else workers


def in_process(workers: int, scheduler: str | None = None) -> bool:
    """True when the tasks run in this process (``workers`` 0 or 1 and no scheduler)."""
    return scheduler is None and int(workers) <= 1


@contextlib.contextmanager
def local_cluster(workers: int, scheduler: str | None = None) -> Iterator[str | None]:
    """The scheduler address the tasks run on, for the length of the ``with`` block.

    Yields ``scheduler`` when one was given, None when the tasks run in this process (``workers`` <= 1),
    else the address of a local cluster of ``workers`` processes started here and closed on exit. One
    cluster serves every step inside the block (starting one costs 2-4 s).
    """
    if scheduler is not None:
        yield scheduler
        return
    if in_process(workers):
        yield None
        return
    check_workers(workers, scheduler)
    from distributed import LocalCluster

    from ._interrupt import children_ignore_sigint

    with children_ignore_sigint():  # a Ctrl-C reaches this process, which closes the cluster (no worker tracebacks)
        cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True, dashboard_address=":0",
                               silence_logs=50)  # CRITICAL: task errors reach the caller as exceptions; a closing
                               # cluster's heartbeat errors are noise
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()


def open_client(workers: int = 1, scheduler: str | None = None):
    """A dask.distributed client on ``scheduler`` or on a new local cluster of ``workers`` processes, or None
    when the tasks run in this process (``workers`` 0 or 1). The caller closes it (a local cluster closes with it)."""
    if scheduler:
        from distributed import Client

        return Client(scheduler)
    if not in_process(workers):
        check_workers(workers, scheduler)
        from distributed import Client, LocalCluster

        from ._interrupt import children_ignore_sigint

        with children_ignore_sigint():
            cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True, dashboard_address=":0",
                                   silence_logs=50)  # CRITICAL: task errors reach the caller as exceptions; a closing
                               # cluster's heartbeat errors are noise
        return Client(cluster)
    return None


def ordered_results(client, fn, *arg_lists, window: int | None = None):
    """Results of ``fn(*args)`` over the argument lists, in order, with at most ``window`` tasks in flight.

    Each future is released as soon as its result has been fetched, so finished results do not pile up in
    the workers' memory (``client.map`` over all tasks kept every result alive until the list of futures
    was dropped: worker memory grew with the block). ``window`` defaults to 2 × the workers + 2.
    """
    from collections import deque

    n = len(arg_lists[0]) if arg_lists else 0
    if window is None:
        try:
            nw = len(client.scheduler_info().get("workers", {}))
        except Exception:  # noqa: BLE001 - any scheduler without the info: a fixed window
            nw = 2
        window = 2 * max(1, nw) + 2
    q: deque = deque()
    nxt = 0
    for _ in range(n):
        while nxt < n and len(q) < window:
            q.append(client.submit(fn, *(a[nxt] for a in arg_lists), pure=False))
            nxt += 1
        f = q.popleft()
        res = f.result()
        f.release()
        del f
        yield res


def run_tasks(fn: Callable[[Any], Any], tasks: Sequence, *, workers: int = 0, scheduler: str | None = None,
              progress: Callable[[int, int], None] | None = None) -> list:
    """``[fn(t) for t in tasks]``, in task order, run as the module docstring says.

    ``progress(done, total)`` is called after each task. On a cluster the tasks complete in any order; at most
    :data:`TASKS_IN_FLIGHT` are submitted and not yet collected, and each result is released once collected.
    """
    n = len(tasks)
    if n == 0:
        return []
    if in_process(workers, scheduler):
        out = []
        for k, t in enumerate(tasks):
            out.append(fn(t))
            if progress:
                progress(k + 1, n)
        return out
    from distributed import Client, as_completed

    with local_cluster(workers, scheduler) as address:  # a cluster of its own only when the caller did not start one
        client = Client(address)
        try:
            pending = iter(enumerate(tasks))
            pos = {}
            ac = as_completed()

            def submit(count):
                for k, t in itertools.islice(pending, count):
                    f = client.submit(fn, t, pure=False)
                    pos[f.key] = k
                    ac.add(f)

            submit(TASKS_IN_FLIGHT)
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
