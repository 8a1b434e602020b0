"""Entry point of the ``thermogrammetry`` command.

Each verb lives in its own module under ``thermogrammetry.cli`` and registers
itself on :data:`thermogrammetry.cli.app.app` when imported; list it here.
"""

from __future__ import annotations

import importlib
import sys

from ..errors import ThermogrammetryError
from .app import app

#: verb modules, imported in this order (each adds its command(s) to ``app``)
VERB_MODULES: tuple[str, ...] = ("convert", "closerange", "correct", "calibrate", "survey", "plan", "dense", "mesh", "ortho", "run", "evaluate",
                                  "texture", "facade", "demo")


def _register() -> None:
    for name in VERB_MODULES:
        importlib.import_module(f"thermogrammetry.cli.{name}")


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit status."""
    from .._interrupt import Interrupted, install_handlers, restore_handlers
    from .._memory import bound_heap_growth
    from ..reporting import cli_command

    bound_heap_growth()  # long numeric runs: freed temporaries go back to the system (results unchanged)
    _register()
    install_handlers()  # Ctrl-C / SIGTERM: one line, exit 130 / 143, OUT as before (see thermogrammetry._interrupt)
    try:
        with cli_command(sys.argv[1:] if argv is None else argv):  # the reports' command line: what the user typed
            app(args=argv, prog_name="thermogrammetry", standalone_mode=True)
    except SystemExit as exc:  # typer/click exit
        code = exc.code
        return code if isinstance(code, int) else (0 if code is None else 1)
    except Interrupted as exc:
        print(f"thermogrammetry: {exc}; stopped, nothing written to OUT by this run", file=sys.stderr, flush=True)
        return exc.exit_status
    except (ThermogrammetryError, MemoryError, OSError, UnicodeError) as exc:
        # last line of defence: a bad input a verb did not catch still ends in one paragraph and exit 2
        return _fail(exc)
    finally:
        restore_handlers()
    return 0


def _fail(exc: BaseException) -> int:
    if isinstance(exc, MemoryError):
        msg = "not enough memory for this input (an image or file larger than this machine can hold?)"
    elif isinstance(exc, UnicodeError):
        msg = f"a text input is not UTF-8 ({exc}); save it as UTF-8"
    elif isinstance(exc, OSError) and not isinstance(exc, ThermogrammetryError) and exc.filename:
        msg = f"{exc.filename}: {exc.strerror or exc}"
    else:
        msg = str(exc) or type(exc).__name__
    print(f"error: {msg}", file=sys.stderr, flush=True)
    return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
