"""``thermogrammetry closerange``: the multi-camera DLT workflow with directional correction of Sawicki, Stein & Więcek (1998)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import List, Optional

import typer

from .app import app


def _unit_of(img) -> str:
    """Unit the input file stored its temperatures in (K unless the reader says °C)."""
    m = img.metadata.extra.get("uint16_mapping") if img.metadata.extra else None
    if m is not None:
        return str(getattr(m, "unit", "K")).upper().lstrip("°")[:1]
    for note in img.metadata.notes:
        if note.strip().endswith(" in C"):
            return "C"
    return "K"


def read_text(path: Path, what: str) -> str:
    from ..errors import DataFileError

    from ..errors import CorruptFileError

    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise DataFileError(f"{what} {path}: cannot be read ({exc.strerror or exc})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise CorruptFileError(f"{what} {path}: not UTF-8 text (line {line}, byte {exc.start}: "
                               f"{data[exc.start:exc.start + 1]!r}); save it as UTF-8") from None


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

    from ..closerange.pipeline import closerange_steps, write_inputs
    from ..closerange.workflow import CloseRangeConfig
    from .._atomic import OutputSet
    from ..closerange.tables import parse_control, parse_measurements, parse_planes
    from ..errors import ConfigError, ThermogrammetryError
    from ..pipeline import FolderProject, run_steps

    console = Console()
    try:
        cams = {}
        for spec in camera:
            if "=" not in spec:
                raise typer.BadParameter(f"--camera {spec!r}: expected IMAGE_NAME=camera.json")
            name, path = spec.split("=", 1)
            from ..camera import Camera

            cams[name.strip()] = Camera.load(Path(path)).to_dict()
        thermal_k, unit = None, "K"
        if thermal_image is not None:
            from ..io import read_thermal

            img = read_thermal(thermal_image, unit=thermal_unit)
            thermal_k = img.require_temperature()
            unit = (thermal_unit or _unit_of(img)).upper().lstrip("°")
        cfg = CloseRangeConfig(ambient_c=ambient_c, sigma_px=sigma_px, max_angle_deg=max_angle_deg, bundle=bundle,
                               emissivity=emissivity, refractive_index=refractive_index, transmission=transmission,
                               relative_humidity=humidity / 100.0,
                               control_sigma_m=None if control_sigma_mm is None else control_sigma_mm / 1000.0,
                               additional_parameters=tuple(a for a in additional.split(",") if a.strip()))
        texts = {"control": read_text(control, "control file"), "measurements": read_text(measurements, "measurements file"),
                 "planes": read_text(planes, "planes file")}
        # validated here, so messages name the user's files and a bad input leaves nothing behind
        parse_control(texts["control"], str(control))
        rows = parse_measurements(texts["measurements"], str(measurements))
        parse_planes(texts["planes"], str(planes))
        images = sorted({r[0] for r in rows})
        if thermal not in images:
            raise ConfigError(f"--thermal {thermal!r}: no such image in {measurements}; images: {', '.join(images)}")
        for name, v, ok in (("--ambient-c", ambient_c, ambient_c > -273.15), ("--sigma-px", sigma_px, sigma_px > 0),
                            ("--humidity", humidity, 0 <= humidity <= 100),
                            ("--max-angle-deg", max_angle_deg, 0 < max_angle_deg < 90),
                            ("--refractive-index", refractive_index, refractive_index > 1)):
            if not math.isfinite(v) or not ok:
                raise ConfigError(f"{name} {v}: out of range (ambient above absolute zero, sigma > 0, humidity 0-100 %, "
                                  "max angle in (0, 90) deg, refractive index > 1; all finite)")
        with OutputSet(out, "closerange") as stage:
            project = FolderProject(stage.stage)
            write_inputs(project, control_csv=texts["control"], measurements_csv=texts["measurements"],
                         planes_csv=texts["planes"], thermal=thermal, config=cfg, cameras=cams,
                         thermal_k=thermal_k, thermal_unit=unit)
            reports = run_steps(project, closerange_steps(),
                                on_step=lambda r: console.print(f"[{'green' if r.ok else 'red'}]{r.name}[/] {r.seconds:.2f} s"))
            failed = [r for r in reports if not r.ok]
            if failed:
                err = str(failed[0].error).replace(str(stage.stage), str(out))
                console.print(f"error in step {failed[0].name}: {err}", markup=False, highlight=False, soft_wrap=True)
                raise typer.Exit(2)
            planes_text = project.read_text("planes.csv")
            stage.commit({"thermal": thermal})
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
