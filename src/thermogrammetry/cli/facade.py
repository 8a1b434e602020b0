"""``thermogrammetry facade``: thermal orthoimage of a flat facade, without a mesh (Barazzetti et al. 2013).

Two routes, the same outputs::

    thermogrammetry facade SURVEY_DIR -o OUT [--plane auto | X,Y,Z,nx,ny,nz] [--cell M] [--unit K|C]
        [--tile M] [--occluders MESH] [--levelling none|offsets]
    thermogrammetry facade --images IMAGES... --plane-points points.csv --plane-measurements m.csv -o OUT
        [--cell M] [--unit K|C] [--input-unit K|C] [--camera camera.json] [--extent U0,U1,V0,V1] [--tile M]
        [--levelling none|offsets]
        -> OUT/facade_temperature.tif (float32), facade_source.tif (int32, -1 = none), facade_angle.tif (oriented
           route only), facade_resolution.tif, facade.png (palette with its colour scale), facade.json

The first route takes an oriented survey and a plane; the second rectifies each frame by a homography from
>= 4 points of known facade coordinates (``points.csv``: ``id,u,v`` metres, u along, v up) measured in it
(``m.csv``: ``image,id,x,y`` pixels, (0, 0) = centre of the top-left pixel), no orientation needed.
One image per cell (chosen per tile by the resolution on the facade and the distance from the image border),
values sampled from it, nothing blended or filled. Frames in raw counts give a mosaic of counts, labelled as
counts (``--unit`` refused). Exit 0 on success, 1 when no image could be rectified (each named with the reason;
nothing written), 2 on unusable input (one paragraph naming file, line and value; nothing written).
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from .app import app, print_error, print_plain


@app.command("facade")
def facade(
    inputs: Optional[List[Path]] = typer.Argument(None, metavar="SURVEY_DIR | IMAGES...", help="Survey folder (cameras.json + frames/ + sparse.ply) from "
                                                  "`thermogrammetry survey`; with --plane-points: more thermal frames "
                                                  "(so that --images *.jpg works)."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder."),
    plane: str = typer.Option("auto", "--plane", help="Oriented route. auto: fitted to the survey's sparse cloud; or "
                              "X,Y,Z,nx,ny,nz: a point of the facade and its normal."),
    cell: Optional[float] = typer.Option(None, "--cell", help="Cell size in metres (default: one pixel of the median image on the facade)."),
    unit: Optional[str] = typer.Option(None, "--unit", help="K or C for temperature frames (default K); not allowed for raw counts."),
    tile: float = typer.Option(1.0, "--tile", help="Tile size in metres: the image choice is made per tile (seams follow tile edges)."),
    occluders: Optional[Path] = typer.Option(None, "--occluders", help="Oriented route. Mesh of what stands in front of the "
                                             "facade (balconies, trees): cells behind it are not taken from images that "
                                             "cannot see them."),
    levelling: str = typer.Option("none", "--levelling", help="none: values as sampled. offsets: per-image offsets from the "
                                  "overlaps ADDED: this ALTERS the values (see docs/verbs/facade.md)."),
    images: List[Path] = typer.Option([], "--images", help="Homography route. Thermal frames: files and/or folders (FLIR/DJI "
                                      "R-JPEG, TIFF incl. float kelvin, SEQ/CSQ); repeat the flag or list them after it."),
    plane_points: Optional[Path] = typer.Option(None, "--plane-points", help="Homography route. points.csv: id,u,v in metres "
                                                "on the facade plane (u along, v up)."),
    plane_measurements: Optional[Path] = typer.Option(None, "--plane-measurements", help="Homography route. image,id,x,y "
                                                      "in pixels ((0,0) = centre of the top-left pixel), image named with "
                                                      "or without extension; >= 4 points per image, no 3 on a line."),
    input_unit: Optional[str] = typer.Option(None, "--input-unit", help="Homography route. K or C: unit of float TIFFs that declare none."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="Homography route. camera.json from `calibrate` for the lens "
                                          "distortion (default: frames taken as distortion-free)."),
    extent: Optional[str] = typer.Option(None, "--extent", help="Homography route. u0,u1,v0,v1 in metres (default: the "
                                         "images' footprints, clipped to the points' bounding box grown by half its size)."),
) -> None:
    """Thermal orthoimage of a flat facade: one image per cell, values kept, source of every cell.

    From an oriented survey and a plane (SURVEY_DIR), or from frames rectified by homographies from >= 4 points of known facade coordinates (--images, --plane-points, --plane-measurements; no orientation needed). Exit 0 on success, 1 when no image could be rectified (each named with its reason), 2 on unusable input (nothing written).
    """  # noqa: E501 (one line: typer keeps the docstring's line breaks in --help)
    from rich.console import Console

    from ..errors import ThermogrammetryError
    from ..pipeline.facade import NothingMosaickedError, run_facade, run_facade_homography

    console = Console(stderr=True)
    inputs = list(inputs or [])
    homography = plane_points is not None or plane_measurements is not None or bool(images)
    try:
        if unit is not None and unit.upper() not in ("K", "C"):
            raise ThermogrammetryError(f"--unit {unit!r}: expected K or C")
        if input_unit is not None and input_unit.upper().lstrip("°") not in ("K", "C"):
            raise ThermogrammetryError(f"--input-unit {input_unit!r}: expected K or C")
        if out.exists() and not out.is_dir():
            raise ThermogrammetryError(f"-o {out}: exists and is not a folder")
        u = None if unit is None else unit.upper()
        if homography:
            if plane_points is None or plane_measurements is None:
                raise ThermogrammetryError("the homography route needs both --plane-points points.csv (id,u,v) and "
                                           "--plane-measurements m.csv (image,id,x,y)")
            frames = list(images) + inputs
            if not frames:
                raise ThermogrammetryError("--plane-points: no thermal frames given; expected --images IMAGES...")
            for flag, given in (("--plane", plane != "auto"), ("--occluders", occluders is not None)):
                if given:
                    raise ThermogrammetryError(f"{flag} belongs to the oriented route (SURVEY_DIR); the homography route "
                                               "takes the plane from --plane-points")
            for p, flag in ((plane_points, "--plane-points"), (plane_measurements, "--plane-measurements"), (camera, "--camera")):
                if p is not None and not p.is_file():
                    raise ThermogrammetryError(f"{flag} {p}: no such file")
            d = run_facade_homography(frames, plane_points, plane_measurements, out, cell_m=cell, unit=u,
                                      input_unit=None if input_unit is None else input_unit.upper().lstrip("°"),
                                      tile_m=tile, levelling=levelling, camera_path=camera, extent=extent)
        else:
            if len(inputs) != 1:
                raise ThermogrammetryError(f"expected one SURVEY_DIR (got {len(inputs)}), or the homography route "
                                           "(--images, --plane-points, --plane-measurements)")
            for flag, given in (("--input-unit", input_unit), ("--camera", camera), ("--extent", extent)):
                if given is not None:
                    raise ThermogrammetryError(f"{flag} belongs to the homography route (--plane-points); a survey's "
                                               "frames and cameras come from its cameras.json")
            d = run_facade(inputs[0], out, plane=plane, cell_m=cell, unit=u, tile_m=tile, occluders_path=occluders,
                           levelling=levelling)
    except NothingMosaickedError as exc:
        print_error(console, exc)
        console.print(f"nothing was written to {out}", highlight=False)
        raise typer.Exit(1)
    except (ThermogrammetryError, ValueError, OSError) as exc:
        print_error(console, exc)
        raise typer.Exit(2)
    h, w = d["grid"]["shape"]
    console.print(f"facade {w} x {h} cells of {d['grid']['cell']:.4g}: {d['cells_filled']}/{d['cells_total']} filled from "
                  f"{d['images_used']} image(s), unit {d['unit']}; plane {d['plane']['how']}", highlight=False)
    if d["route"] == "homography":
        for n, hm in d["homographies"].items():
            console.print(f"  {n}: {hm['points']} points, homography residual RMS {hm['rms_px']:.3g} px", highlight=False)
    for s in d["skipped"][:5]:
        print_plain(console, f"  skipped {s['image']}: {s['reason']}")
    if len(d["skipped"]) > 5:
        console.print(f"  ... {len(d['skipped']) - 5} more skipped (facade.json \"skipped\")", highlight=False)
    if d["levelling"] == "offsets":
        vu = "counts" if d["unit"] == "counts" else "K"
        rb, ra = d.get("offsets_rms_before_after_counts" if vu == "counts" else "offsets_rms_before_after_k")
        console.print(f"levelling: offsets ADDED per image (held: {d['offsets_fixed_image']}), overlap RMS {rb:.3g} -> "
                      f"{ra:.3g} {vu}; values altered", highlight=False)
    console.print(f"outputs in {out}: {' '.join(d['files'])}" + ("" if "angle" not in d else " (no facade_angle.tif: no "
                                                                  "orientation, no viewing angle)"), highlight=False)
