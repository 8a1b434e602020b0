"""``thermogrammetry correct``: per-pixel angle, distance and corrected temperature of an oriented thermal image.

The driver is :func:`thermogrammetry.pipeline.correct.run_correct`; this module parses and prints.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from .app import app


@app.command("correct")
def correct(
    thermal_image: Path = typer.Option(..., "--thermal-image", help="Thermal image (any format thermogrammetry reads)."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder."),
    cameras: Optional[Path] = typer.Option(None, "--cameras", help="cameras.json: oriented cameras (thermogrammetry/cameras v1, written by survey and closerange; closerange's former format is also read); with --thermal."),
    thermal: Optional[str] = typer.Option(None, "--thermal", help="Image/camera name in --cameras."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="Interior orientation: camera.json (from `calibrate`), a Metashape XML, an OpenCV YAML/XML or a one-camera COLMAP cameras.txt."),
    pose: Optional[Path] = typer.Option(None, "--pose", help="pose.json: R,t (cam_from_world) or omega/phi/kappa_deg + X0,Y0,Z0."),
    planes: Optional[Path] = typer.Option(None, "--planes", help="planes.csv with normal_x,normal_y,normal_z,d_m."),
    points: Optional[Path] = typer.Option(None, "--points", help="points.csv (id,X,Y,Z): with --planes that list their ids, correct only inside each plane's outline."),
    plane: List[str] = typer.Option([], "--plane", help="A,B,C,D of a plane A X + B Y + C Z + D = 0 (m); repeatable."),
    mesh: Optional[Path] = typer.Option(None, "--mesh", help="Triangle mesh (OBJ/PLY/STL) in the object frame."),
    dsm: Optional[Path] = typer.Option(None, "--dsm", help="DSM GeoTIFF (heights in m) in the object frame."),
    ambient_c: float = typer.Option(22.0, "--ambient-c", help="Reflected ambient temperature (°C)."),
    emissivity: str = typer.Option("cosine", "--emissivity", help="cosine (ε(θ) = ε_n cos θ, Sawicki, Stein & Więcek 1998, eq. 7-8) or fresnel (dielectric, --refractive-index)."),
    refractive_index: float = typer.Option(1.5, "--refractive-index", help="For --emissivity fresnel."),
    transmission: bool = typer.Option(False, "--transmission/--no-transmission", help="Atmospheric transmission over the per-pixel distance."),
    humidity: float = typer.Option(50.0, "--humidity", help="Relative humidity in percent, for --transmission."),
    thermal_unit: Optional[str] = typer.Option(None, "--thermal-unit", help="K or C, for a float image that does not declare its unit."),
    max_angle_deg: float = typer.Option(75.0, "--max-angle-deg", help="No correction beyond this viewing angle."),
    sigma_angle_deg: Optional[float] = typer.Option(None, "--sigma-angle-deg", help="σ of the viewing angle (°) for sigma_k.tif."),
) -> None:
    """Correct an oriented thermal image for viewing angle, directional emissivity and distance over planes, a mesh or a DSM."""
    from rich.console import Console

    from ..errors import ThermogrammetryError
    from ..pipeline.correct import run_correct

    console = Console()
    try:
        res = run_correct(thermal_image, out, cameras=cameras, thermal=thermal, camera=camera, pose=pose, planes=planes,
                          points=points, plane=plane, mesh=mesh, dsm=dsm, ambient_c=ambient_c, emissivity=emissivity,
                          refractive_index=refractive_index, transmission=transmission, humidity=humidity,
                          thermal_unit=thermal_unit, max_angle_deg=max_angle_deg, sigma_angle_deg=sigma_angle_deg)
        n_ok, unit = res["pixels_corrected"], res["unit"]
    except ThermogrammetryError as exc:
        console.print(f"error: {exc}", markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(2)
    if "camera_file" in res:
        from ..io.camera_file import describe_camera_file

        console.print(describe_camera_file(res["camera_file"]), markup=False, highlight=False, soft_wrap=True)
    console.print(f"{n_ok} pixels corrected; outputs in {out}: corrected.tif ({unit}) angle_deg.tif "
                  "distance_m.tif valid.tif")

