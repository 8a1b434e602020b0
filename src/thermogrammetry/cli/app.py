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
