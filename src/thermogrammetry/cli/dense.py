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
    surface_fill: bool = typer.Option(True, "--fill-surface/--no-fill", help="Also write dsm_filled.tif: the DSM's holes "
                                      "filled by Laplace interpolation from the rim (band 2 flags them); dsm.tif stays as measured."),
    max_hole: Optional[float] = typer.Option(None, "--fill-max-hole", help="Largest hole filled entirely in dsm_filled.tif, "
                                             "in metres across (default 100 DSM cells)."),
    laz: bool = typer.Option(False, "--laz", help="Write the cloud as LAZ (cloud.laz, compressed with lazrs) instead of cloud.las."),
    las_version: str = typer.Option("1.4", "--las-version", help="1.4 (point format 7: RGB, extra bytes, WKT CRS) or 1.2 "
                                    "(point format 3: RGB, GeoTIFF keys; for readers that refuse LAS 1.4)."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Local dask worker processes (0 or 1 = in this process; "
                                          "default 2, or 1 on a single core; at most the cores)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Address of an existing dask scheduler (instead of --workers)."),
    max_cells: Optional[int] = typer.Option(None, "--max-cells", help="Cap on the DSM's cells (default: sized for this "
                                            "machine's memory, or $THERMOGRAMMETRY_MAX_CELLS)."),
    dji_sdk: Optional[Path] = typer.Option(None, "--dji-sdk", help="DJI Thermal SDK library (libdirp.so): a survey of DJI R-JPEGs "
                                           "decoded as raw counts is read again in kelvin (also $THERMOGRAMMETRY_DJI_TSDK; docs/dji.md)."),
) -> None:
    """Dense matching of an oriented survey: point cloud with each point's frame value, and a DSM GeoTIFF."""
    from rich.console import Console

    from ..pipeline.dense import run_dense
    from ..products.cloud import CloudOptions
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
            opts = CloudOptions(laz=laz, las_version=las_version)
            rep = run_dense(survey_dir, out, gsd=gsd, workers=default_workers(workers), scheduler=scheduler, fill=fill,
                            surface_fill=surface_fill, max_hole_m=max_hole, cloud_options=opts,
                            dji_sdk=None if dji_sdk is None else str(dji_sdk), on_image=on_image, max_cells=max_cells)
    except (ThermogrammetryError, OSError, ValueError) as exc:
        _fail(console, str(exc))
    console.print(f"{rep['points']} points, DSM {rep['dsm']['width']}×{rep['dsm']['height']} cells at {rep['gsd_m']} m, "
                  f"completeness {100 * rep['completeness']:.1f} %, {rep['seconds']:.1f} s", highlight=False)
    for n in rep["notes"]:
        print_plain(console, f"note: {n}")
    files = " ".join(rep["cloud_files"] + ["dsm.tif"] + (["dsm_filled.tif"] if rep.get("dsm_filled") else []) + ["dense.json", "report.html"])
    print_plain(console, f"outputs in {out}: {files}")
