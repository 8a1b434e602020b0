"""``thermogrammetry ortho SURVEY_DIR --dsm DSM.tif -o OUT``: true orthophoto mosaic that keeps the frames' values."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .app import app, print_error, print_plain


@app.command("ortho")
def ortho(
    survey_dir: Path = typer.Argument(..., help="Output folder of `thermogrammetry survey` (cameras.json + frames/)."),
    dsm: Path = typer.Option(..., "--dsm", help="DSM GeoTIFF (from `thermogrammetry dense`), in the survey's CRS."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder."),
    gsd: Optional[float] = typer.Option(None, "--gsd", help="Cell size in metres (default: the DSM's)."),
    unit: Optional[str] = typer.Option(None, "--unit", help="K or C for temperature frames (default K); not allowed for raw counts."),
    sampling: str = typer.Option("nearest", "--sampling", help="nearest (bit-exact copy of the source pixel) or bilinear."),
    max_angle: float = typer.Option(60.0, "--max-angle", help="Largest viewing angle to the DSM normal (deg) of a source pixel."),
    correct: bool = typer.Option(False, "--correct", help="Correct for viewing angle, directional emissivity and transmission (DSM normals and distances)."),
    ambient_c: float = typer.Option(22.0, "--ambient-c", help="Reflected ambient temperature (°C), for --correct."),
    emissivity: str = typer.Option("cosine", "--emissivity", help="cosine (Sawicki et al.) or fresnel, for --correct."),
    refractive_index: float = typer.Option(1.5, "--refractive-index", help="For --emissivity fresnel."),
    transmission: bool = typer.Option(False, "--transmission/--no-transmission", help="Atmospheric transmission over the distance, for --correct."),
    humidity: float = typer.Option(50.0, "--humidity", help="Relative humidity in percent, for --transmission."),
    fill: bool = typer.Option(True, "--fill/--no-fill", help="Fill the DSM's holes for the mosaic's surface (Laplace "
                              "interpolation from the rim; flagged in ortho_filled_mask.tif). --no-fill: the DSM as given."),
    max_hole: Optional[float] = typer.Option(None, "--fill-max-hole", help="Largest hole filled entirely, in metres "
                                             "across (default 100 DSM cells); farther than half of it from data stays empty "
                                             "(beyond the data's outer edge: farther than all of it)."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Local dask worker processes (0 or 1 = in this process; "
                                          "default 2, or 1 on a single core; at most the cores)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Address of an existing dask scheduler (instead of --workers)."),
    max_cells: Optional[int] = typer.Option(None, "--max-cells", help="Cap on the cells of the DSM and of the mosaic "
                                            "(default: sized for this machine's memory, or $THERMOGRAMMETRY_MAX_CELLS)."),
    dji_sdk: Optional[Path] = typer.Option(None, "--dji-sdk", help="DJI Thermal SDK library (libdirp.so): a survey of DJI R-JPEGs "
                                           "decoded as raw counts is read again in kelvin (also $THERMOGRAMMETRY_DJI_TSDK; docs/dji.md)."),
) -> None:
    """Orthophoto mosaic with z-buffer visibility, a documented image choice and no blending; 16-bit, source, angle,
    distance and gradient rasters beside it."""
    from rich.console import Console

    from ..errors import ThermogrammetryError
    from ..products.correction import CorrectionConfig
    from ..pipeline.ortho import run_ortho
    from ..tasks import default_workers

    console = Console(stderr=True)
    try:
        corr = CorrectionConfig(ambient_c=ambient_c, emissivity=emissivity, refractive_index=refractive_index,
                                transmission=transmission, relative_humidity=humidity / 100.0) if correct else None
        from ..products.ortho import OrthoConfig

        rep = run_ortho(survey_dir, dsm, out, gsd=gsd, unit=unit, sampling=sampling, correct=correct, correction=corr,
                        config=OrthoConfig(sampling=sampling, max_angle_deg=max_angle),
                        workers=default_workers(workers), scheduler=scheduler, fill=fill, max_hole_m=max_hole,
                        dji_sdk=None if dji_sdk is None else str(dji_sdk), max_cells=max_cells)
    except (ThermogrammetryError, OSError, ValueError) as exc:
        print_error(console, exc)
        raise typer.Exit(2)
    console.print(f"ortho {rep['width']}×{rep['height']} cells at {rep['gsd_m']} m in {rep['unit']}, {rep['cells']} cells "
                  f"from {rep['images_used']} images ({rep['sampling']}), {rep['seconds']:.1f} s", highlight=False)
    fp = rep.get("footprint")
    if fp and fp.get("cells"):
        console.print(f"coverage: {100 * fp['covered']:.1f} % of the {fp['cells']} cells the frames see", highlight=False)
    if rep.get("fill"):
        f = rep["fill"]
        beyond = f.get("filled_beyond_dsm_cells")
        console.print(f"surface: {f['filled_cells']} DSM cells interpolated (holes up to {f['max_hole_m']:g} m"
                      + (f"; {beyond} beyond the DSM's box, into the frames' footprints" if beyond else "")
                      + f"), {f['ortho_cells_on_filled']} mosaic cells on them (ortho_filled_mask.tif)", highlight=False)
    for n in rep["notes"]:
        print_plain(console, f"note: {n}")
    if rep.get("sigma"):
        sg = rep["sigma"]["total"]
        print_plain(console, f"σ per cell (ortho_sigma.tif): median {sg['median']:.3g}, p95 {sg['p95']:.3g} {rep['unit']} "
                             f"(sensor noise {rep['sigma']['netd']:.3g} {rep['unit']}: "
                             f"{rep['sigma']['netd_source']['method'].split(' (')[0]})")
    print_plain(console, f"outputs in {out}: ortho.tif ortho.qml ortho_u16.tif ortho_source.tif ortho.json ortho_angle.tif "
                         "ortho_distance.tif ortho_gradient.tif" + (" ortho_filled_mask.tif" if rep.get("fill") else "")
                         + (" ortho_sigma.tif" if rep.get("sigma") else "") + " report.html")
