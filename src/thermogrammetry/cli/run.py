"""``thermogrammetry run IMAGES... -o PROJECT``: survey → dense → ortho in one project folder, steps skipped when
their inputs are unchanged.

Contract::

    thermogrammetry run IMAGES... -o PROJECT [survey's options] [--products ortho,dsm,cloud]
        [--rerun-from STEP] [--dji-sdk PATH] [--workers N | --scheduler ADDRESS]
        → PROJECT/{survey,dense,ortho}/ (each the verb's own outputs), PROJECT/report.html, PROJECT/run.log

The options are the survey's own (the same parameters as :func:`thermogrammetry.cli.survey.survey`, parsed by
:func:`~thermogrammetry.cli.survey.survey_inputs`) plus ``--products`` and ``--rerun-from``. Exit 0 when every
step ran or was skipped, 1 when a step failed (the steps before it stay finished), 2 on unusable input or
arguments (nothing written when the arguments are refused).
"""

from __future__ import annotations

import inspect
import shutil
import typing
from typing import Optional

import typer

from . import survey as _survey_cli
from .app import app

_PROJECT_HELP = "Project folder: survey/ dense/ ortho/ report.html run.log run.json (a user's own files in it are kept)."


def run(**kw) -> None:
    """Survey, DSM and cloud, orthophoto: one command, one project folder; steps whose inputs are unchanged are skipped.

    Exit status: 0 when every step ran or was skipped, 1 when a step failed (the steps before it stay finished; see PROJECT/run.log), 2 on unusable input or arguments (nothing written when the arguments are refused).
    """  # noqa: E501 (one line: typer keeps the docstring's line breaks in --help)
    from rich.console import Console

    from ..errors import ThermogrammetryError
    from ..pipeline.run import check_rerun_from, parse_products, run_project
    from ..pipeline.runlog import RunLog
    from ..pipeline.survey.workflow import check_survey_output
    from .progress import progress

    out = kw["out"]
    err = Console(stderr=True)

    def refuse(msg):
        # user data (file names, values such as "[nan, 1.0]") printed literally: no markup in them
        err.print("error:", style="red", end=" ", highlight=False)
        err.print(str(msg), markup=False, highlight=False, soft_wrap=True)
        err.print(f"nothing was written to {out}", markup=False, highlight=False)
        raise typer.Exit(2)

    try:
        products = parse_products(kw["products"])
        rerun_from = check_rerun_from(kw["rerun_from"], products)
        inp, opt = _survey_cli.survey_inputs(**{k: kw[k] for k in _survey_cli.SURVEY_ARGS})
        check_survey_output(out, inp, opt=opt)  # (as run_project does: checked here because run.log is opened first)
    except (ThermogrammetryError, ValueError, OSError) as exc:
        refuse(str(exc))
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        refuse(f"project folder {out}: cannot be created ({exc.strerror or exc})")
    with RunLog(out / "run.log") as log:
        console = Console(file=log.terminal)
        log.echo = lambda text: console.print(text, highlight=False, markup=False, soft_wrap=True)
        tasks: dict = {}
        try:
            with progress(console, "run", transient=True, elapsed=True) as bar, log.capture():
                def on_progress(step, stage, done, total):
                    key = (step, stage)
                    if key not in tasks:
                        tasks[key] = bar.add_task(f"{step} {stage}", total=total)
                    bar.update(tasks[key], completed=done, total=total)

                res = run_project(out, inp, opt, products=products, rerun_from=rerun_from, log=log, progress=on_progress)
        except (ThermogrammetryError, OSError, ValueError) as exc:
            for ln in log.captured_tail():
                console.print(ln, highlight=False, markup=False, soft_wrap=True)
            log.line(f"error: {exc}", echo=False)
            console.print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
            raise typer.Exit(2)
        if res.failed is not None:
            if not res.bad_input:  # the libraries' own messages, kept from the terminal while the run went well
                for ln in log.captured_tail():
                    console.print(ln, highlight=False, markup=False, soft_wrap=True)
            log.line(f"error: {res.failed.message}", echo=False)
            console.print(f"[red]error:[/red] {res.failed.message}", highlight=False, soft_wrap=True)
            if res.bad_input and created and [p.name for p in out.iterdir()] == ["run.log"]:
                console.print(f"nothing was written to {out}", highlight=False)
                log.close()  # unusable input in a new project: it is not left behind with only a log in it
                shutil.rmtree(out, ignore_errors=True)
            else:
                console.print(f"see {out / 'run.log'}", highlight=False)
            raise typer.Exit(2 if res.bad_input else 1)
        ran = [r.name for r in res.steps if r.status == "ran"]
        console.print(f"{'ran ' + ', '.join(ran) if ran else 'nothing to do: every step is up to date'}; outputs in {out}: "
                      + " ".join(f"{r.name}/" for r in res.steps) + " report.html run.log", highlight=False, soft_wrap=True)


def _signature() -> inspect.Signature:
    """The survey's parameters (its options, shared), ``-o`` as the project folder, then run's own."""
    hints = typing.get_type_hints(_survey_cli.survey)
    params = []
    for p in inspect.signature(_survey_cli.survey).parameters.values():
        p = p.replace(annotation=hints[p.name])
        if p.name == "out":
            p = p.replace(default=typer.Option(..., "-o", "--out", help=_PROJECT_HELP))
        params.append(p)
    own = {
        "products": (str, typer.Option("ortho,dsm,cloud", "--products", help="What to build: a comma-separated subset of "
                                       "ortho, dsm, cloud (dsm and cloud come from dense; ortho needs dense).")),
        "rerun_from": (Optional[str], typer.Option(None, "--rerun-from", help="Run this step (survey, dense or ortho) and "
                                                   "the steps after it even when their inputs are unchanged.")),
    }
    for name, (ann, default) in own.items():
        params.append(inspect.Parameter(name, inspect.Parameter.POSITIONAL_OR_KEYWORD, default=default, annotation=ann))
    return inspect.Signature(params, return_annotation=None)


run.__signature__ = _signature()
run.__annotations__ = {p.name: p.annotation for p in run.__signature__.parameters.values()} | {"return": None}
app.command("run")(run)
