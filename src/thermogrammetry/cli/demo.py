"""``thermogrammetry demo [DIR]``: synthetic scenes with exact truth, every workflow end to end, a report.

Writes everything under DIR (default ``./thermogrammetry-demo``): the scenes' inputs and ground truth,
each workflow's outputs, ``demo/*.json`` (rows per section), ``reports/*.json`` (step timing) and
``report.html``. Exit status: 0 when every check is within its bound, 1 when any check misses its
bound or a section fails, 2 for bad options. The sections and how to add one are described in
:mod:`thermogrammetry.pipeline.demo`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .app import app


@app.command("demo")
def demo(
    directory: Path = typer.Argument(Path("thermogrammetry-demo"), help="Output folder (created if missing)."),
    sections: Optional[str] = typer.Option(None, "--sections", help="Comma-separated section names to run (default: all)."),
    seed: int = typer.Option(0, "--seed", help="Seed offset of every synthetic scene."),
    threads: int = typer.Option(2, "--threads", min=1, help="Parallel render workers (forked processes)."),
    list_sections: bool = typer.Option(False, "--list", help="List the sections and exit."),
) -> None:
    """Run the synthetic end-to-end demo and report achieved accuracy against the truth."""
    from rich.console import Console
    from rich.table import Table

    from .._atomic import OutputSet
    from ..errors import ConfigError, ThermogrammetryError
    from ..pipeline import FolderProject
    from ..pipeline.demo import DemoOptions, all_sections, run_demo

    console = Console(soft_wrap=True)
    if list_sections:
        for s in all_sections():
            console.print(f"{s.name:24s} {s.title}")
        raise typer.Exit(0)
    names = tuple(n.strip() for n in sections.split(",") if n.strip()) if sections else None
    try:
        opt = DemoOptions(seed=seed, sections=names, threads=threads)
        # written as a set: a staging folder beside DIR, renamed/moved into DIR at the end (demo-manifest.json last)
        stage = OutputSet(directory, "demo")
    except ThermogrammetryError as exc:
        console.print(f"error: {exc}", markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(2)
    project = FolderProject(stage.stage)

    def show(rep, rows):
        tab = Table(title=f"{rep.name}  ({rep.seconds:.1f} s)", title_justify="left", show_lines=False)
        for col, just in (("check", "left"), ("achieved", "right"), ("bound", "right"), ("unit", "left"), ("", "left")):
            tab.add_column(col, justify=just)
        for r in rows:
            rel = {"max": "≤ ", "min": "≥ "}.get(r.kind, "")
            verdict = "[dim]info[/]" if r.kind == "info" else ("[green]pass[/]" if r.passed else "[bold red]FAIL[/]")
            tab.add_row(r.check, f"{r.value:.4g}", f"{rel}{r.bound:g}" if r.bound is not None else "", r.unit, verdict)
        console.print(tab)

    with stage:
        try:
            res = run_demo(project, opt, on_section=show)
        except ConfigError as exc:
            console.print(f"error: {exc}", markup=False, highlight=False, soft_wrap=True)
            raise typer.Exit(2)
        try:
            stage.commit({"ok": bool(res.ok), "seed": seed, "sections": list(names) if names else "all"})
        except ThermogrammetryError as exc:
            console.print(f"error: {exc}", markup=False, highlight=False, soft_wrap=True)
            raise typer.Exit(2)
    n_fail = sum(1 for r in res.rows if not r.passed)
    status = "[green]all checks within their bounds[/]" if res.ok else f"[bold red]{n_fail} check(s) failed[/]"
    console.print(f"{status} in {res.seconds:.1f} s; report: {directory / 'report.html'}")
    raise typer.Exit(0 if res.ok else 1)
