"""``thermogrammetry mesh DENSE_DIR | CLOUD -o OUT``: a triangle mesh from a dense cloud or a scan.

Contract::

    thermogrammetry mesh DENSE_DIR | CLOUD.{las,laz,ply,e57,xyz} -o OUT [--crs EPSG:N] [--edge M | --faces N]
        [--fill-holes M2] [--workers N | --scheduler ADDRESS]
        -> OUT/mesh.ply (vertices in the survey's CRS, face property ``filled``), OUT/mesh.obj, OUT/mesh.json

Exit 0 on success, 2 on unusable input (one paragraph, no traceback; OUT not created).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .app import app, print_error, print_plain


@app.command("mesh")
def mesh(
    source: Path = typer.Argument(..., help="The output folder of `thermogrammetry dense` (dense.json + cloud), or a cloud "
                                  "file: .las .laz .ply .e57 .xyz (a scan in the survey's CRS)."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder: mesh.ply mesh.obj mesh.json."),
    crs: Optional[str] = typer.Option(None, "--crs", help="CRS of a cloud that states none (EPSG:N, the survey's); "
                                      "refused when the file states another."),
    edge: Optional[float] = typer.Option(None, "--edge", help="Decimate to this target edge length (m); the error is "
                                         "reported (decimation_rms_m)."),
    faces: Optional[int] = typer.Option(None, "--faces", help="Decimate to this many triangles (instead of --edge)."),
    fill_holes: float = typer.Option(1.0, "--fill-holes", help="Fill holes up to this area (m²); every filled face is "
                                     "flagged (0 = fill none)."),
    cell: Optional[float] = typer.Option(None, "--cell", help="Lattice cell of the surface (m; default 3 x the "
                                         "cloud's median point spacing, at least 2.5 x its noise)."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Local dask worker processes (0 or 1 = in this process; "
                                          "default 1: each block holds its points; at most the cores)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Address of an existing dask scheduler (instead of --workers)."),
) -> None:
    """Mesh a point cloud: outliers removed, holes filled and flagged, unsupported surface trimmed, optional decimation."""
    from rich.console import Console

    from ..errors import ThermogrammetryError
    from ..pipeline.mesh import run_mesh
    from ..products.mesh import MeshConfig
    from ..products.mesh_surface import SurfaceConfig
    from .progress import progress

    console = Console(stderr=True)
    try:
        cfg = MeshConfig(surface=SurfaceConfig(cell_m=cell), fill_holes_m2=fill_holes, edge_m=edge, faces=faces)
        if out.exists() and not out.is_dir():
            raise ThermogrammetryError(f"-o {out}: exists and is not a folder; expected an output folder")
        with progress(console, "mesh") as prog:
            tasks: dict[str, int] = {}

            def on_step(stage, done, total):
                if stage not in tasks:
                    tasks[stage] = prog.add_task(stage, total=total)
                prog.update(tasks[stage], completed=done, total=total)
            rep = run_mesh(source, out, crs=crs, config=cfg, workers=1 if workers is None else workers,
                           scheduler=scheduler, progress=on_step)
    except (ThermogrammetryError, OSError, ValueError) as exc:
        print_error(console, exc)
        raise typer.Exit(2)
    console.print(f"{rep['faces']} faces from {rep['points']} points (cell {rep['cell_m']:.4g} m, "
                  f"{rep['outliers_removed']} outliers removed); {rep['filled_faces']} faces filled "
                  f"({rep['filled_area_m2']:.3g} m²), {rep['trimmed_area_m2']:.3g} m² trimmed"
                  + (f", decimation RMS {1000 * rep['decimation_rms_m']:.1f} mm" if rep["decimation"]["decimated"] else "")
                  + f"; {rep['seconds']:.1f} s", highlight=False)
    for n in rep["notes"]:
        print_plain(console, f"note: {n}")
    print_plain(console, f"outputs in {out}: mesh.ply mesh.obj mesh.json")
