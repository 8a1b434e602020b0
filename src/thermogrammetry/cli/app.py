"""The typer application object shared by every verb module."""

from __future__ import annotations

import re

import typer

from .. import __version__

app = typer.Typer(
    name="thermogrammetry",
    help="Thermal-infrared photogrammetry: calibrated cameras, oriented images and 3D products in kelvin.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


_SIZE = re.compile(r"^\s*(\d+)\s*[xX×]\s*(\d+)\s*$")


def parse_size(text: str | None) -> tuple[int, int] | None:
    """``"640x512"`` (also ``X`` or ``×``, spaces allowed) → (640, 512); None unless two positive integers."""
    m = _SIZE.match(text or "")
    if not m or int(m.group(1)) <= 0 or int(m.group(2)) <= 0:
        return None
    return int(m.group(1)), int(m.group(2))


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
