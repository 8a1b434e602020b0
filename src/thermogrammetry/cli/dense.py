"""``thermogrammetry dense SURVEY_DIR -o OUT``: fused point cloud with temperatures (LAS/PLY) and a DSM."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .app import app, print_error, print_plain


def _fail(console, msg, code=2):
    print_error(console, msg)
    raise typer.Exit(code)


@app.command("dense")
def dense(
    survey_dir: Path = typer.Argument(..., help="Output folder of `thermogrammetry survey` (cameras.json + frames/)."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder: cloud.las cloud.ply dsm.tif dense.json."),
    gsd: Optional[float] = typer.Option(None, "--gsd", help="DSM cell size in metres (default: 2 × the images' GSD)."),
    fill: bool = typer.Option(False, "--fill", help="Fill DSM holes from the nearest cell (flagged in band 2)."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Local dask worker processes (0 or 1 = in this process; "
                                          "default 2, or 1 on a single core; at most the cores)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Address of an existing dask scheduler (instead of --workers)."),
    max_cells: Optional[int] = typer.Option(None, "--max-cells", help="Cap on the DSM's cells (default: sized for this "
                                            "machine's memory, or $THERMOGRAMMETRY_MAX_CELLS)."),
) -> None:
    """Dense matching of an oriented survey: point cloud with each point's frame value, and a DSM GeoTIFF."""
    from rich.console import Console

    from ..pipeline.dense import run_dense
    from ..errors import ThermogrammetryError

    from ..tasks import default_workers
    from .progress import progress

    console = Console(stderr=True)
    try:
        with progress(console, "dense") as prog:
            task = []  # added at the first reference image: a refusal before the matching prints no progress line

            def on_image(k, n):
                if not task:
                    task.append(prog.add_task("reference images", total=n))
                prog.update(task[0], completed=k, total=n)
            rep = run_dense(survey_dir, out, gsd=gsd, workers=default_workers(workers), scheduler=scheduler, fill=fill,
                            on_image=on_image, max_cells=max_cells)
    except (ThermogrammetryError, OSError, ValueError) as exc:
        _fail(console, str(exc))
    console.print(f"{rep['points']} points, DSM {rep['dsm']['width']}×{rep['dsm']['height']} cells at {rep['gsd_m']} m, "
                  f"completeness {100 * rep['completeness']:.1f} %, {rep['seconds']:.1f} s", highlight=False)
    for n in rep["notes"]:
        print_plain(console, f"note: {n}")
    print_plain(console, f"outputs in {out}: cloud.las cloud.ply dsm.tif dense.json")
