"""``thermogrammetry facade``: thermal orthoimage of a flat facade from an oriented survey (seed 002).

::

    thermogrammetry facade SURVEY_DIR -o OUT [--plane auto | X,Y,Z,nx,ny,nz] [--cell M] [--unit K|C]
        [--tile M] [--occluders MESH]
        -> OUT/facade_temperature.tif (float32), facade_source.tif (int32, -1 = none), facade_angle.tif,
           facade_resolution.tif, facade.png (palette with its colour scale), facade.json

One image per cell (chosen per tile by the resolution on the facade and the distance from the image border),
values sampled from it, nothing blended or filled. Frames in raw counts give a mosaic of counts, labelled as
counts (``--unit`` refused). Exit 0 on success, 2 on unusable input (one paragraph, no traceback).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .app import app


@app.command("facade")
def facade(
    survey_dir: Path = typer.Argument(..., help="Survey folder (cameras.json + frames/ + sparse.ply) from `thermogrammetry survey`."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder."),
    plane: str = typer.Option("auto", "--plane", help="auto: fitted to the survey's sparse cloud (RANSAC, the dominant plane); "
                              "or X,Y,Z,nx,ny,nz: a point of the facade and its normal in the survey's coordinates."),
    cell: Optional[float] = typer.Option(None, "--cell", help="Cell size in metres (default: one pixel of the median image on the facade)."),
    unit: Optional[str] = typer.Option(None, "--unit", help="K or C for kelvin frames (default K); not allowed for raw counts."),
    tile: float = typer.Option(1.0, "--tile", help="Tile size in metres: the image choice is made per tile (seams follow tile edges)."),
    occluders: Optional[Path] = typer.Option(None, "--occluders", help="Mesh of what stands in front of the facade (balconies, trees): "
                                             "cells behind it are not taken from images that cannot see them."),
) -> None:
    """Thermal orthoimage of a flat facade: one image per cell, values kept, source of every cell."""
    from rich.console import Console

    from ..errors import ThermogrammetryError
    from ..pipeline.facade import run_facade

    console = Console(stderr=True)
    try:
        if unit is not None and unit.upper() not in ("K", "C"):
            raise ThermogrammetryError(f"--unit {unit!r}: expected K or C")
        if out.exists() and not out.is_dir():
            raise ThermogrammetryError(f"-o {out}: exists and is not a folder")
        d = run_facade(survey_dir, out, plane=plane, cell_m=cell, unit=None if unit is None else unit.upper(), tile_m=tile,
                       occluders_path=occluders)
    except (ThermogrammetryError, ValueError, OSError) as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
        raise typer.Exit(2)
    h, w = d["grid"]["shape"]
    console.print(f"facade {w} x {h} cells of {d['grid']['cell']:.4g}: {d['cells_filled']}/{d['cells_total']} filled from "
                  f"{d['images_used']} image(s), unit {d['unit']}; plane {d['plane']['how']}", highlight=False)
    console.print(f"outputs in {out}: facade_temperature.tif facade_source.tif facade_angle.tif facade_resolution.tif "
                  "facade.png facade.json", highlight=False)
