"""``thermogrammetry evaluate --dsm DSM.tif [--reference REF.tif] [--checkpoints cp.csv] -o OUT``."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .app import app, print_error, print_plain


@app.command("evaluate")
def evaluate(
    dsm: Path = typer.Option(..., "--dsm", help="DSM GeoTIFF to evaluate."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder: evaluate.json (+ evaluate_histogram.png)."),
    reference: Optional[Path] = typer.Option(None, "--reference", help="Reference DSM GeoTIFF in the same CRS."),
    checkpoints: Optional[Path] = typer.Option(None, "--checkpoints", help="cp.csv: id,X,Y,Z (m, the DSM's CRS)."),
    ortho: Optional[Path] = typer.Option(None, "--ortho", help="ortho.tif: check-point markers located in it give ΔX, ΔY."),
    max_cells: Optional[int] = typer.Option(None, "--max-cells", help="Cap on the cells of each raster read (default: "
                                            "sized for this machine's memory, or $THERMOGRAMMETRY_MAX_CELLS)."),
) -> None:
    """DSM against a reference DSM (difference statistics and histogram) and against check points (per axis)."""
    from rich.console import Console

    from ..errors import ThermogrammetryError
    from ..pipeline.evaluate import run_evaluate

    console = Console(stderr=True)
    try:
        rep = run_evaluate(dsm, out, reference=reference, checkpoints=checkpoints, ortho=ortho, max_cells=max_cells)
    except (ThermogrammetryError, OSError, ValueError) as exc:
        print_error(console, exc)
        raise typer.Exit(2)
    if rep["dsm_vs_reference"] and rep["dsm_vs_reference"]["n"]:
        s = rep["dsm_vs_reference"]
        console.print(f"DSM − reference: n={s['n']} mean {s['mean']:+.3f} std {s['std']:.3f} RMSE {s['rmse']:.3f} "
                      f"MAE {s['mae']:.3f} p95|Δ| {s['p95_abs']:.3f} m", highlight=False)
    if rep["checkpoints"]:
        c = rep["checkpoints"]
        f = lambda v: "—" if v is None else f"{v:.3f}"  # noqa: E731
        console.print(f"check points: n={c['n']} RMSE X {f(c['rmse_x'])} Y {f(c['rmse_y'])} Z {f(c['rmse_z'])} m", highlight=False)
    print_plain(console, f"outputs in {out}: evaluate.json")
