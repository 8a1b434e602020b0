"""``thermogrammetry plan``: flight height, line spacing, trigger distance, video extraction rate, waypoints.

::

    thermogrammetry plan (--camera camera.json | --focal-px F --image-size WxH) (--gsd M | --height M)
        (--area area.geojson | --corners "E,N E,N E,N ...") [--crs EPSG:N] [--forward 0.8] [--sidelap 0.6]
        [--heading DEG] [--speed M/S] [--fps HZ] [--ground-z M] -o OUT
      → OUT/plan.json, OUT/waypoints.csv, OUT/waypoints.kml (when the CRS is known)
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from .._validate import parse_size
from .app import app, print_error, print_plain


@app.command("plan")
def plan(
    out: Path = typer.Option(..., "-o", "--out", help="Output folder: plan.json, waypoints.csv, waypoints.kml."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="camera.json (from calibrate): focal length and image size."),
    focal_px: Optional[float] = typer.Option(None, "--focal-px", help="Focal length in pixels (instead of --camera)."),
    image_size: Optional[str] = typer.Option(None, "--image-size", help="WxH in pixels, e.g. 640x512 (instead of --camera)."),
    gsd: Optional[float] = typer.Option(None, "--gsd", help="Target ground sampling distance (m)."),
    height: Optional[float] = typer.Option(None, "--height", help="Flight height above ground (m)."),
    area: Optional[Path] = typer.Option(None, "--area", help="GeoJSON polygon (WGS 84 lon/lat per RFC 7946)."),
    corners: Optional[str] = typer.Option(None, "--corners", help='Polygon corners "E,N E,N E,N ..." in metres in --crs.'),
    crs: Optional[str] = typer.Option(None, "--crs", help="Projected CRS of the plan, e.g. EPSG:2056 (default for "
                                                       "a GeoJSON area: its UTM zone)."),
    forward: float = typer.Option(0.8, "--forward", help="Forward overlap (fraction); 0.8 for thermal UAV flights."),
    sidelap: float = typer.Option(0.6, "--sidelap", help="Sidelap (fraction); 0.6 for thermal UAV flights."),
    heading: Optional[float] = typer.Option(None, "--heading", help="Line direction, degrees from north (default: "
                                                                 "along the area's longest side)."),
    speed: Optional[float] = typer.Option(None, "--speed", help="Ground speed (m/s): flight time and trigger interval."),
    fps: Optional[float] = typer.Option(None, "--fps", help="Video frame rate (Hz): frame-extraction stride and rate."),
    ground_z: float = typer.Option(0.0, "--ground-z", help="Ground elevation (m) added to the height in waypoints.csv."),
    max_photos: Optional[int] = typer.Option(None, "--max-photos", help="Refuse a plan needing more photos than this "
                                                                      "(default 200000)."),
) -> None:
    """Plan a survey flight: height from the GSD, lines, triggers, video extraction rate (Khodaei et al. 2015)."""
    import numpy as np
    from rich.console import Console

    from .._atomic import OutputSet, write_atomic_text
    from ..errors import ConfigError, DataFileError, ThermogrammetryError
    from ..sfm.plan import plan_flight, read_area, utm_epsg, waypoints_csv, waypoints_kml

    console = Console(stderr=True)
    try:
        if camera is not None:
            from ..camera import Camera

            cam = Camera.load(camera)
            f_px, size = float(cam.K[0, 0]), cam.image_size
        elif focal_px is not None and image_size is not None:
            size = parse_size(image_size)
            if size is None:
                raise ConfigError(f"--image-size {image_size!r}: expected WxH in pixels, e.g. 640x512")
            f_px = focal_px
        else:
            raise ConfigError("give --camera camera.json, or --focal-px and --image-size")
        if (area is None) == (corners is None):
            raise ConfigError("give exactly one of --area area.geojson and --corners \"E,N E,N E,N ...\"")
        from pyproj import CRS, Transformer
        from pyproj.exceptions import CRSError

        if crs is not None:
            try:
                crs_obj = CRS.from_user_input(crs)
            except CRSError:
                raise ConfigError(f"--crs {crs!r}: not a CRS pyproj knows (expected e.g. EPSG:2056)") from None
            if not crs_obj.is_projected:
                raise ConfigError(f"--crs {crs!r}: a geographic CRS; expected a projected one in metres (e.g. a UTM zone)")
        if area is not None:
            try:
                text = area.read_text(encoding="utf-8")
            except (OSError, UnicodeDecodeError) as exc:
                raise DataFileError(f"{area}: cannot read ({getattr(exc, 'strerror', None) or exc})") from None
            ll, area_crs = read_area(text, str(area))
            src = CRS.from_user_input(area_crs)
            if crs is None:
                if src.is_geographic:
                    c = ll.mean(axis=0)
                    crs = f"EPSG:{utm_epsg(float(c[0]), float(c[1]))}"
                else:
                    crs = area_crs
            tr = Transformer.from_crs(src, CRS.from_user_input(crs), always_xy=True)
            xy = np.c_[tr.transform(ll[:, 0], ll[:, 1])]
        else:
            try:
                xy = np.array([[float(v) for v in c.split(",")] for c in corners.split()])
            except ValueError:
                raise ConfigError(f"--corners {corners!r}: expected \"E,N E,N E,N ...\" (metres)") from None
            if xy.ndim != 2 or xy.shape[1] != 2:
                raise ConfigError(f"--corners {corners!r}: expected pairs E,N separated by spaces")
        p = plan_flight(f_px, size, xy, gsd_m=gsd, height_m=height, forward_overlap=forward, sidelap=sidelap,
                        heading_deg=heading, speed_mps=speed, video_fps=fps, ground_z_m=ground_z, crs=crs,
                        max_photos=max_photos)
        lonlat = None
        if crs is not None and p.waypoints:
            tr = Transformer.from_crs(CRS.from_user_input(crs), 4326, always_xy=True)
            lonlat = np.c_[tr.transform([w.x for w in p.waypoints], [w.y for w in p.waypoints])]
        else:
            p.notes.append("no CRS: waypoints are in the local frame of --corners; no KML written")
        with OutputSet(out, "plan") as stage:  # OUT complete or absent; a user's own files in OUT kept
            write_atomic_text(stage.path("waypoints.csv"), waypoints_csv(p, lonlat))
            if lonlat is not None:
                write_atomic_text(stage.path("waypoints.kml"), waypoints_kml(p, lonlat))
            write_atomic_text(stage.path("plan.json"), json.dumps(p.summary(), indent=1) + "\n")
            stage.commit()
    except (ThermogrammetryError, OSError, ValueError) as exc:
        print_error(console, exc)
        raise typer.Exit(2)
    console.print(f"height {p.height_m:.1f} m above ground, GSD {p.gsd_m * 100:.2f} cm, footprint "
                  f"{p.footprint_across_m:.1f} x {p.footprint_along_m:.1f} m", highlight=False)
    console.print(f"{p.n_lines} lines {p.line_spacing_m:.2f} m apart (heading {p.heading_deg:.1f} deg), trigger every "
                  f"{p.trigger_distance_m:.2f} m, {p.n_photos} photos, {p.flight_length_m:.0f} m of flight", highlight=False)
    if p.extract_every_n_frames:
        console.print(f"video at {p.video_fps:g} Hz and {p.speed_mps:g} m/s: keep every {p.extract_every_n_frames}th frame "
                      f"({p.extraction_rate_hz:.3g} Hz)", highlight=False)
    for n in p.notes:
        print_plain(console, f"note: {n}")
    console.print(f"outputs in {out}", highlight=False)
