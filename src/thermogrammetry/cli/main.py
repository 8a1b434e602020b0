"""Entry point of the ``thermogrammetry`` command.

Each verb lives in its own module under ``thermogrammetry.cli`` and registers
itself on :data:`thermogrammetry.cli.app.app` when imported; list it here.
"""

from __future__ import annotations

import importlib
import sys

from .app import app

#: verb modules, imported in this order (each adds its command(s) to ``app``)
VERB_MODULES: tuple[str, ...] = ("convert", "closerange", "correct", "calibrate", "survey", "plan", "dense", "ortho", "evaluate",
                                  "texture", "demo")


def _register() -> None:
    for name in VERB_MODULES:
        importlib.import_module(f"thermogrammetry.cli.{name}")


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit status."""
    _register()
    try:
        app(args=argv, prog_name="thermogrammetry", standalone_mode=True)
    except SystemExit as exc:  # typer/click exit
        code = exc.code
        return code if isinstance(code, int) else (0 if code is None else 1)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
