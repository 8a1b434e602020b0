"""``thermogrammetry closerange``: the multi-camera DLT workflow with directional correction of Sawicki, Stein & Więcek (1998)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from .app import app


@app.command("closerange")
def closerange(
    control: Path = typer.Option(..., "--control", help="control.csv: id,X,Y,Z (m)."),
    measurements: Path = typer.Option(..., "--measurements", help="measurements.csv: image,id,x,y (px, OpenCV origin) for all images."),
    thermal: str = typer.Option(..., "--thermal", help="Name of the thermal image in measurements.csv."),
    planes: Path = typer.Option(..., "--planes", help="planes.csv: name,id1,id2,id3[,...]."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder."),
    thermal_image: Optional[Path] = typer.Option(None, "--thermal-image", help="The thermal image (any format thermogrammetry reads)."),
    camera: List[str] = typer.Option([], "--camera", help="IMAGE_NAME=camera.json: known interior orientation (from `calibrate`)."),
    ambient_c: float = typer.Option(22.0, "--ambient-c", help="Reflected ambient temperature (°C)."),
    sigma_px: float = typer.Option(0.5, "--sigma-px", help="A-priori σ of the image measurements (px)."),
    thermal_unit: Optional[str] = typer.Option(None, "--thermal-unit", help="K or C, for a float image that does not declare its unit."),
    max_angle_deg: float = typer.Option(75.0, "--max-angle-deg", help="No correction beyond this viewing angle."),
    emissivity: str = typer.Option("cosine", "--emissivity", help="cosine (ε(θ) = ε_n cos θ, Sawicki, Stein & Więcek 1998, eq. 7-8) or fresnel (dielectric, --refractive-index)."),
    refractive_index: float = typer.Option(1.5, "--refractive-index", help="For --emissivity fresnel."),
    transmission: bool = typer.Option(False, "--transmission/--no-transmission", help="Atmospheric transmission over the per-pixel distance."),
    humidity: float = typer.Option(50.0, "--humidity", help="Relative humidity in percent, for --transmission."),
    control_sigma_mm: Optional[float] = typer.Option(None, "--control-sigma-mm", help="σ of the control coordinates (mm); default errorless."),
    bundle: bool = typer.Option(False, "--bundle/--no-bundle", help="Joint adjustment of all cameras and pass points after the sequential chain."),
    additional: str = typer.Option("", "--additional", help="With --bundle: distortion terms of the optical cameras, e.g. k1,p1,p2."),
) -> None:
    """Orient optical cameras by DLT, intersect pass points, position the thermal camera from pass
    points only, fit planes and correct the thermal image per pixel (Sawicki, Stein, Więcek)."""
    from rich.console import Console
    from rich.table import Table

    from ..closerange.workflow import CloseRangeConfig
    from ..errors import ThermogrammetryError
    from ..pipeline.closerange import run_closerange

    console = Console()
    try:
        cams = {}
        for spec in camera:
            if "=" not in spec:
                raise typer.BadParameter(f"--camera {spec!r}: expected IMAGE_NAME=camera.json")
            name, path = spec.split("=", 1)
            cams[name.strip()] = Path(path)
        cfg = CloseRangeConfig(ambient_c=ambient_c, sigma_px=sigma_px, max_angle_deg=max_angle_deg, bundle=bundle,
                               emissivity=emissivity, refractive_index=refractive_index, transmission=transmission,
                               relative_humidity=humidity / 100.0,
                               control_sigma_m=None if control_sigma_mm is None else control_sigma_mm / 1000.0,
                               additional_parameters=tuple(a for a in additional.split(",") if a.strip()))
        run = run_closerange(out, control=control, measurements=measurements, planes=planes, thermal=thermal,
                             config=cfg, cameras=cams, thermal_image=thermal_image, thermal_unit=thermal_unit,
                             ambient_c=ambient_c, sigma_px=sigma_px, humidity=humidity, max_angle_deg=max_angle_deg,
                             refractive_index=refractive_index,
                             on_step=lambda r: console.print(f"[{'green' if r.ok else 'red'}]{r.name}[/] {r.seconds:.2f} s"))
        if run.failed is not None:
            console.print(f"error in step {run.failed.name}: {run.error}", markup=False, highlight=False, soft_wrap=True)
            raise typer.Exit(2)
        planes_text = run.planes_csv
    except ThermogrammetryError as exc:
        console.print(f"error: {exc}", markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(2)
    t = Table(title="planes")
    lines = planes_text.strip().splitlines()
    for h in ("name", "angle_deg", "sigma_angle_deg", "distance_m"):
        t.add_column(h)
    head = lines[0].split(",")
    for ln in lines[1:]:
        c = dict(zip(head, ln.split(",")))
        t.add_row(c["name"], c["angle_deg"], c["sigma_angle_deg"], c["distance_m"])
    console.print(t)
    console.print(f"outputs in {out}: points.csv cameras.json orientation.json planes.csv"
                  + (" corrected.tif" if thermal_image is not None else "") + " report.html")
