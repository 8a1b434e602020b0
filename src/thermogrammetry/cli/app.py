"""The typer application object shared by every verb module."""

from __future__ import annotations

import typer

from .. import __version__

app = typer.Typer(
    name="thermogrammetry",
    help="Thermal-infrared photogrammetry: calibrated cameras, oriented images and 3D products in kelvin.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"thermogrammetry {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", callback=_version_callback, is_eager=True, help="Print the version and exit."
    ),
) -> None:
    """Thermal-infrared photogrammetry toolkit."""


def print_error(console, msg, prefix: str = "error:", style: str = "bold red") -> None:
    """``error: <msg>`` on ``console`` with the prefix in red and ``msg`` printed literally: a value in brackets
    (``got [nan, 1]``) is user data, never rich markup. ``prefix="warning:", style="yellow"`` for warnings."""
    from rich.text import Text

    console.print(Text.assemble((prefix, style), " ", str(msg)), highlight=False, soft_wrap=True)


def print_plain(console, msg) -> None:
    """``msg`` printed literally (no markup, no highlighting): notes and summaries that carry names and values."""
    console.print(str(msg), markup=False, highlight=False, soft_wrap=True)
