"""``thermogrammetry correct``: per-pixel angle, distance and corrected temperature of an oriented thermal image.

Surfaces: planes (``--plane A,B,C,D`` or a ``planes.csv`` with ``normal_x,normal_y,normal_z,d_m`` as
written by ``closerange``), a triangle mesh (``--mesh`` OBJ/PLY/STL, read by trimesh) or a DSM GeoTIFF
(``--dsm``, read by rasterio; triangulated between pixel centres). The mesh/DSM must be in the same
object frame as the camera pose.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import List, Optional

import numpy as np
import typer

from .app import app


def _pose_from_json(d: dict, source: str):
    from ..errors import ConfigError
    from ..geometry import Pose

    if "R" in d and "t" in d:
        return np.asarray(d["R"], float), np.asarray(d["t"], float)
    if "R_cam_from_world" in d and "center_m" in d:
        R = np.asarray(d["R_cam_from_world"], float)
        return R, -R @ np.asarray(d["center_m"], float)
    keys = {"omega_deg", "phi_deg", "kappa_deg", "X0", "Y0", "Z0"}
    if keys <= set(d):
        p = Pose.from_opk(*(np.radians(float(d[k])) for k in ("omega_deg", "phi_deg", "kappa_deg")),
                          [float(d["X0"]), float(d["Y0"]), float(d["Z0"])])
        return p.R, p.t
    raise ConfigError(f"{source}: expected a pose with R and t (cam_from_world), or R_cam_from_world and center_m, "
                      f"or omega_deg, phi_deg, kappa_deg, X0, Y0, Z0; got keys {sorted(d)}")


def _planes_csv(text: str, source: str):
    from ..errors import DataFileError

    rows = list(csv.DictReader(io.StringIO(text)))
    need = {"normal_x", "normal_y", "normal_z", "d_m"}
    if not rows or not need <= set(rows[0]):
        raise DataFileError(f"{source}: expected columns name,normal_x,normal_y,normal_z,d_m (closerange planes.csv)")
    return [(r.get("name", f"plane{i}"), [float(r["normal_x"]), float(r["normal_y"]), float(r["normal_z"])],
             float(r["d_m"]), (r.get("ids") or "").split()) for i, r in enumerate(rows)]


@app.command("correct")
def correct(
    thermal_image: Path = typer.Option(..., "--thermal-image", help="Thermal image (any format thermogrammetry reads)."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder."),
    cameras: Optional[Path] = typer.Option(None, "--cameras", help="cameras.json written by `closerange` (use with --thermal)."),
    thermal: Optional[str] = typer.Option(None, "--thermal", help="Camera name in --cameras."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="camera.json (interior orientation, from `calibrate`)."),
    pose: Optional[Path] = typer.Option(None, "--pose", help="pose.json: R,t (cam_from_world) or omega/phi/kappa_deg + X0,Y0,Z0."),
    planes: Optional[Path] = typer.Option(None, "--planes", help="planes.csv with normal_x,normal_y,normal_z,d_m."),
    points: Optional[Path] = typer.Option(None, "--points", help="points.csv (id,X,Y,Z): with --planes that list their ids, correct only inside each plane's outline."),
    plane: List[str] = typer.Option([], "--plane", help="A,B,C,D of a plane A X + B Y + C Z + D = 0 (m); repeatable."),
    mesh: Optional[Path] = typer.Option(None, "--mesh", help="Triangle mesh (OBJ/PLY/STL) in the object frame."),
    dsm: Optional[Path] = typer.Option(None, "--dsm", help="DSM GeoTIFF (heights in m) in the object frame."),
    ambient_c: float = typer.Option(22.0, "--ambient-c", help="Reflected ambient temperature (°C)."),
    emissivity: str = typer.Option("cosine", "--emissivity", help="cosine (seed 000 eq. 8) or fresnel."),
    refractive_index: float = typer.Option(1.5, "--refractive-index", help="For --emissivity fresnel."),
    transmission: bool = typer.Option(False, "--transmission/--no-transmission", help="Atmospheric transmission over the per-pixel distance."),
    humidity: float = typer.Option(50.0, "--humidity", help="Relative humidity in percent, for --transmission."),
    thermal_unit: Optional[str] = typer.Option(None, "--thermal-unit", help="K or C, for a float image that does not declare its unit."),
    max_angle_deg: float = typer.Option(75.0, "--max-angle-deg", help="No correction beyond this viewing angle."),
    sigma_angle_deg: Optional[float] = typer.Option(None, "--sigma-angle-deg", help="σ of the viewing angle (°) for sigma_k.tif."),
) -> None:
    """Correct an oriented thermal image for viewing angle, directional emissivity and distance over planes, a mesh or a DSM."""
    from rich.console import Console

    from ..closerange import network as nw
    from ..closerange.pipeline import _tif_bytes
    from ..closerange.workflow import CloseRangeConfig
    from ..products.correction import correct_oriented_image
    from ..errors import ConfigError, ThermogrammetryError
    from ..io import read_thermal
    from ..pipeline import FolderProject
    from .closerange import _unit_of, read_text

    console = Console()
    try:
        if cameras is not None:
            if not thermal:
                raise ConfigError("--cameras needs --thermal NAME (the camera to use)")
            d = json.loads(read_text(cameras, "cameras file"))
            if thermal not in d.get("cameras", {}):
                raise ConfigError(f"{cameras}: no camera {thermal!r}; cameras: {sorted(d.get('cameras', {}))}")
            c = d["cameras"][thermal]
            if "camera" in c:  # positioned with a known interior orientation: keep its distortion
                from ..camera import Camera

                cam = Camera.from_dict(c["camera"], source=f"{cameras}: {thermal}")
                R = np.asarray(c["R_cam_from_world"], float)
                t = -R @ np.asarray(c["center_m"], float)
            else:
                P = nw.dlt_matrix(c["dlt_L_world"])
                K, R, C = nw.decompose_projection(P)
                cam, t = K, -R @ C
        elif camera is not None and pose is not None:
            from ..camera import Camera

            cam = Camera.load(camera)
            R, t = _pose_from_json(json.loads(read_text(pose, "pose file")), str(pose))
        else:
            raise ConfigError("give the orientation: --cameras cameras.json --thermal NAME, or --camera camera.json --pose pose.json")
        pl = []
        outlines = None
        if planes is not None:
            rows = _planes_csv(read_text(planes, "planes file"), str(planes))
            pl += [(n, dd) for _, n, dd, _ in rows]
            if points is not None:
                pts = {r["id"]: [float(r["X"]), float(r["Y"]), float(r["Z"])]
                       for r in csv.DictReader(io.StringIO(read_text(points, "points file")))}
                outlines = []
                for name, _, _, ids in rows:
                    missing = [i for i in ids if i not in pts]
                    if len(ids) < 3 or missing:
                        raise ConfigError(f"plane {name!r} in {planes}: ids {ids} not all in {points} (missing {missing})")
                    outlines.append(np.array([pts[i] for i in ids]))
        if plane and outlines is not None:
            raise ConfigError("--plane has no outline: use it without --points, or put the plane in planes.csv")
        for spec in plane:
            try:
                a, b, cc, dd = (float(x) for x in spec.split(","))
            except ValueError:
                raise ConfigError(f"--plane {spec!r}: expected A,B,C,D") from None
            pl.append(([a, b, cc], dd))
        surf = None
        if mesh is not None:
            import trimesh

            try:
                m = trimesh.load(mesh, force="mesh", process=False)
            except Exception as exc:  # trimesh raises many kinds
                from ..errors import DataFileError

                raise DataFileError(f"mesh {mesh}: cannot be read ({type(exc).__name__}: {exc})") from None
            surf = (np.asarray(m.vertices, float), np.asarray(m.faces, int))
        if dsm is not None:
            import rasterio

            from ..products.surfaces import dsm_to_mesh

            with rasterio.open(dsm) as src:
                z = src.read(1, masked=True).astype(float).filled(np.nan)
                tr = src.transform
            surf = dsm_to_mesh(z, (tr.a, tr.b, tr.c, tr.d, tr.e, tr.f))
        if sum(x is not None for x in (mesh, dsm)) + bool(pl) != 1:
            raise ConfigError("give exactly one kind of surface: --planes/--plane, --mesh or --dsm")
        img = read_thermal(thermal_image, unit=thermal_unit)
        T0 = img.require_temperature()
        unit = (thermal_unit or _unit_of(img)).upper().lstrip("°")
        cfg = CloseRangeConfig(ambient_c=ambient_c, emissivity=emissivity, refractive_index=refractive_index,
                               transmission=transmission, relative_humidity=humidity / 100.0,
                               max_angle_deg=max_angle_deg)
        image_size = (T0.shape[1], T0.shape[0])
        if hasattr(cam, "image_size") and tuple(cam.image_size) != image_size:
            raise ConfigError(f"camera image size {cam.image_size} differs from the thermal image's {image_size}")
        cr = correct_oriented_image(T0, cam, R, t, pl or None, cfg, mesh=surf, polygons_world=outlines,
                                    sigma_angle_rad=None if sigma_angle_deg is None else np.radians(sigma_angle_deg))
        from ..io.tiff import encode_temperature_tiff

        project = FolderProject(out)
        project.write_bytes("corrected.tif", encode_temperature_tiff(cr.corrected_k.astype(np.float32), unit=unit,
                                                                     encoding="float32")[0])
        project.write_bytes("angle_deg.tif", _tif_bytes(np.degrees(cr.angle_rad).astype(np.float32)))
        project.write_bytes("distance_m.tif", _tif_bytes(cr.distance_m.astype(np.float32)))
        project.write_bytes("valid.tif", _tif_bytes(cr.valid.astype(np.uint8)))
        if sigma_angle_deg is not None:
            project.write_bytes("sigma_k.tif", _tif_bytes(cr.sigma_k.astype(np.float32)))
    except ThermogrammetryError as exc:
        console.print(f"[red]error:[/] {exc}")
        raise typer.Exit(2)
    console.print(f"{int(cr.valid.sum())} pixels corrected; outputs in {out}: corrected.tif ({unit}) angle_deg.tif "
                  "distance_m.tif valid.tif")
