"""``thermogrammetry texture``: temperatures on a 3D mesh from an oriented survey.

Contract::

    thermogrammetry texture SURVEY_DIR --mesh MESH -o OUT [--unit K|C] [--correct] [--levelling none|offsets]
        -> OUT/textured.glb, OUT/textured.obj (+ .mtl, preview PNG), OUT/temperature_texture.tif (float32),
           OUT/source_texture.tif (int32, -1 = none), OUT/vertices.ply (per-vertex temperature_k),
           OUT/texture.json (faces_total, faces_textured, index -> image name, unit, offsets)

Frames in kelvin are used when the survey has any, else frames in raw sensor counts (DJI R-JPEGs without
the closed SDK, Workswell TIFFs): then every product holds counts labelled as counts (``unit: "counts"``,
``raw_counts`` in vertices.ply), and ``--unit`` and ``--correct`` are refused (exit 2).

Extra: ``--rig rig.json`` (thermal poses from RGB poses, Barazzetti et al. 2013, eq. 4-5), ``--texel-size`` (m).
Exit 0 on success, 2 on unusable input (one paragraph, no traceback).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .app import app, print_error, print_plain


@app.command("texture")
def texture(
    survey_dir: Path = typer.Argument(..., help="Survey folder (cameras.json + frames/) from `thermogrammetry survey`, or a cameras.json."),
    mesh: Path = typer.Option(..., "--mesh", help="Mesh in the survey's frame: OBJ, PLY, glTF/GLB, STL, OFF."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder."),
    unit: Optional[str] = typer.Option(None, "--unit", help="K or C: unit of temperature_texture.tif (default K; vertices.ply "
                                       "is always kelvin); refused for frames in raw counts."),
    correct: bool = typer.Option(False, "--correct", help="Per-texel angle/emissivity/transmission correction (alters values; "
                                 "needs frames in kelvin)."),
    levelling: str = typer.Option("none", "--levelling", help="none, or offsets: per-image offsets from overlaps (alters values)."),
    rig: Optional[Path] = typer.Option(None, "--rig", help="rig.json: thermal frames + cam_thermal_from_cam_rgb for oriented RGB images."),
    texel_size: Optional[float] = typer.Option(None, "--texel-size", help="Texel size in metres (default: half the surface pixel size)."),
    fit_poses: str = typer.Option("auto", "--fit-poses", help="auto: fit the poses to the mesh, then refine them photometrically "
                                  "(poses only); mesh: the first step; off: as they are (see docs/verbs/texture.md)."),
    max_faces: Optional[int] = typer.Option(None, "--max-faces", help="Refuse a mesh of more triangles than this "
                                                                    "(default 2000000)."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="The thermal camera's calibration for the texturing, in place "
                                          "of the survey's: camera.json, a Metashape XML, an OpenCV YAML/XML or a one-camera "
                                          "COLMAP cameras.txt."),
) -> None:
    """Texture a mesh with temperatures: best image per face, occlusion by ray casting, source of every texel."""
    from rich.console import Console

    from ..errors import ThermogrammetryError
    from ..pipeline.texture import run_texture
    from ..products.texture import Levelling, TextureConfig
    from ..radiometry.encoding import TemperatureUnit

    from .progress import progress

    console = Console(stderr=True)
    try:
        u = None if unit is None else TemperatureUnit(unit.upper() if unit.lower() in ("k", "c") else unit)
        lev = Levelling(levelling)
        cfg = TextureConfig(texel_size_m=texel_size)
        if out.exists() and not out.is_dir():
            raise ThermogrammetryError(f"-o {out}: exists and is not a folder")
        with progress(console, "texture") as prog:
            d = run_texture(survey_dir, mesh, out, unit=None if u is None else u.value, correct=correct, levelling=lev.value, rig_path=rig, config=cfg, max_faces=max_faces,
                            fit_poses=fit_poses, progress=_stage_lines(prog), camera=camera)
    except (ThermogrammetryError, ValueError, OSError) as exc:
        print_error(console, exc)
        raise typer.Exit(2)
    if d.get("camera_file"):
        from ..io.camera_file import describe_camera_file

        print_plain(console, describe_camera_file(d["camera_file"]) + f", in place of the survey's {', '.join(d['camera_file']['replaces'])}")
    vis = d.get("faces_visible", d["faces_seen"])
    console.print(f"textured {d['faces_textured']}/{d['faces_total']} faces ({100 * d.get('faces_visible_textured', d['faces_textured']) / max(vis, 1):.1f} % "
                  f"of the {vis} visible), {d['texels_textured']}/{d['texels_total']} texels; wrote {out}", highlight=False)
    if d.get("unit") == "counts":
        console.print("values: raw sensor counts (frames have no documented conversion), labelled as counts", highlight=False)
    pf = d.get("pose_fit") or {}
    if pf.get("applied"):
        md, rc = pf["median_distance_m"], pf["rotation_change_deg"]
        console.print(f"poses fitted to the mesh: {pf['points_on_surface']} tie points, median distance to the mesh "
                      f"{md['before']:.3f} -> {md['after']:.3f} m, rotations changed by {rc['median']:.2f} deg (median, "
                      f"max {rc['max']:.2f}); cameras_fitted.json", highlight=False)
    elif pf.get("reason") and not str(pf["reason"]).startswith("off"):
        console.print(f"poses not fitted to the mesh: {pf['reason']}", highlight=False)
    if d.get("mesh_winding"):
        console.print(f"mesh: {d['mesh_winding']['reason']}", highlight=False)
    if d["skipped"]:
        print_plain(console, f"skipped {len(d['skipped'])} image(s): "
                    + "; ".join(f"{s['image']}: {s['reason']}" for s in d["skipped"][:5]))


def _stage_lines(prog):
    """``progress(stage, done, total)`` for :func:`run_texture`: one task of ``prog`` per stage, added when the stage
    first reports (a refusal before the work prints no progress line)."""
    tasks: dict[str, int] = {}

    def on_step(stage: str, done: int, total: int) -> None:
        if stage not in tasks:
            tasks[stage] = prog.add_task(stage, total=total)
        prog.update(tasks[stage], completed=done, total=total)
    return on_step
