"""mkdocs hook: ``cli.md`` generated at build time from the typer app, so that it cannot go stale.

Every verb's ``--help`` is rendered by typer itself (``CliRunner().invoke(app, [verb, "--help"])``, plain text,
not rich boxes) and put into the page as a code block; the page is added to the site's files in memory
(nothing is written into ``docs/``). The verbs are the modules of ``thermogrammetry.cli.main.VERB_MODULES``, in
that order. The source tree next to ``mkdocs.yml`` (``src/``) is imported first, so the reference describes the
code being documented.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

#: the pages per verb (docs/verbs/<verb>.md), linked from each verb's section
VERB_PAGES = "verbs/{verb}.md"
WIDTH = 100


def render_cli() -> str:
    """Markdown of ``thermogrammetry --help`` and of every verb's ``--help``."""
    import typer.core
    from typer.testing import CliRunner

    from thermogrammetry.cli.app import app
    from thermogrammetry.cli.main import VERB_MODULES

    for name in VERB_MODULES:
        importlib.import_module(f"thermogrammetry.cli.{name}")
    runner = CliRunner()
    has_rich = typer.core.HAS_RICH
    typer.core.HAS_RICH = False  # plain click help (read by typer at format time)
    try:
        def helptext(args: list[str]) -> str:
            r = runner.invoke(app, args, prog_name="thermogrammetry", terminal_width=WIDTH)
            if r.exit_code != 0:
                raise RuntimeError(f"thermogrammetry {' '.join(args)} exited {r.exit_code}: {r.output}")
            return r.output.rstrip()

        parts = ["# CLI reference", "",
                 "Generated at build time from the command itself (`docs/hooks.py` renders `thermogrammetry --help` "
                 "and every verb's `--help`); what each verb does and why its defaults are what they are is on the "
                 "verb's page.", "", "```text", helptext(["--help"]), "```", ""]
        for verb in VERB_MODULES:
            parts += [f"## {verb}", "", f"See [{verb}]({VERB_PAGES.format(verb=verb)}).", "",
                      "```text", helptext([verb, "--help"]), "```", ""]
    finally:
        typer.core.HAS_RICH = has_rich
    return "\n".join(parts)


def on_config(config, **kwargs):
    src = Path(config["config_file_path"]).resolve().parent / "src"
    if src.is_dir() and str(src) not in sys.path:
        sys.path.insert(0, str(src))
    return config


def on_files(files, config, **kwargs):
    from mkdocs.structure.files import File

    files.append(File.generated(config, "cli.md", content=render_cli()))
    return files
