"""Progress for long CLI work: a rich bar on a terminal, plain lines in a log (every 10 % and at the end)."""

from __future__ import annotations

import sys
import time


class LogProgress:
    """The subset of :class:`rich.progress.Progress` the verbs use, printing plain lines to stderr.

    A line is printed when a task starts, when it crosses a further 10 % of its total, when its description
    changes (a new stage) and when it completes, so a run from a log or a pipe is never silent.
    """

    def __init__(self, prefix: str, *, file=None, elapsed: bool = False):
        self.prefix = prefix
        self.file = file
        self.elapsed = elapsed
        self.tasks: dict[int, dict] = {}

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def _emit(self, t: dict, force: bool = False) -> None:
        total = max(int(t["total"] or 0), 1)
        done = min(int(t["completed"]), total)
        decile = int(10 * done / total)
        if force or decile != t["decile"] or t["desc"] != t["printed_desc"]:
            t["decile"], t["printed_desc"] = decile, t["desc"]
            dt = f" ({time.perf_counter() - t['t0']:.1f} s)" if self.elapsed else ""
            print(f"{self.prefix}: {t['desc']} {done}/{total}{dt}", file=self.file or sys.stderr, flush=True)

    def add_task(self, description: str, total: float | None = None, **_) -> int:
        k = len(self.tasks)
        self.tasks[k] = {"desc": description, "total": total, "completed": 0, "decile": -1, "printed_desc": None,
                         "t0": time.perf_counter()}
        self._emit(self.tasks[k], force=True)
        return k

    def advance(self, task: int, advance: float = 1) -> None:
        self.update(task, advance=advance)

    def update(self, task: int, *, completed: float | None = None, advance: float | None = None,
               description: str | None = None, total: float | None = None, **_) -> None:
        t = self.tasks[task]
        if total is not None:
            t["total"] = total
        if completed is not None:
            t["completed"] = completed
        if advance is not None:
            t["completed"] += advance
        if description is not None:
            t["desc"] = description
        self._emit(t)


def progress(console, prefix: str, *, transient: bool = True, elapsed: bool = False):
    """A rich progress bar when ``console`` is a terminal, else a :class:`LogProgress` with ``prefix`` printing to the
    console's stream (``elapsed``: each line with the task's elapsed time)."""
    if not console.is_terminal:
        # progress goes to stderr, or to the console's own stream when that is not stdout (a run's log stream)
        stream = getattr(console, "file", None)
        return LogProgress(prefix, file=None if stream is sys.stdout else stream, elapsed=elapsed)
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    console=console, transient=transient)
