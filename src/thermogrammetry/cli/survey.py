"""``thermogrammetry survey``: orient thermal frames (and RGB images) into one georeferenced block.

Contract::

    thermogrammetry survey IMAGES... -o OUT [--input-unit K|C] [--camera camera.json]
        [--rgb DIR] [--rig rig.json] [--gnss auto|none|gnss.csv] [--crs EPSG:N]
        [--gcps gcps.csv --gcp-measurements m.csv] [--checkpoints cp.csv --check-measurements cm.csv]
        [--workers N | --scheduler ADDRESS]

Exit 0 when a block was oriented (even with some frames left out), 1 when nothing could be oriented,
2 on unusable input with nothing written. The run works in a folder beside OUT and renames it into place
at the end, so OUT is either as it was or complete.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import List, Optional

import typer

from .app import app


class _Progress:
    """A rich progress bar on a terminal, plain lines (every 10 %) in a log."""

    def __init__(self, console):
        self.console = console
        self.tty = sys.stderr.isatty()
        self.bar = None
        self.tasks = {}
        self.last = {}
        if self.tty:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self.bar = Progress(TextColumn("{task.description:<9}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                                console=console, transient=False)

    def __enter__(self):
        if self.bar:
            self.bar.__enter__()
        return self

    def __exit__(self, *a):
        if self.bar:
            self.bar.__exit__(*a)

    def __call__(self, step, k, n):
        if self.bar:
            if step not in self.tasks:
                self.tasks[step] = self.bar.add_task(step, total=n)
            self.bar.update(self.tasks[step], completed=k, total=n)
            return
        pct = int(100 * k / max(n, 1)) // 10
        if self.last.get(step) != pct or k == n:
            self.last[step] = pct
            print(f"survey {step}: {k}/{n}", file=sys.stderr, flush=True)


@app.command("survey")
def survey(
    images: List[Path] = typer.Argument(..., help="Thermal frames: files and/or folders (R-JPEG, TIFF, SEQ/CSQ, 8-bit JPEG/PNG, videos)."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder (written as a whole at the end)."),
    input_unit: Optional[str] = typer.Option(None, "--input-unit", help="K or C: unit of float TIFFs that declare none."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="The camera's calibration, held fixed (else self-calibration): camera.json from `calibrate`, a Metashape XML, an OpenCV YAML/XML or a one-camera COLMAP cameras.txt."),
    rgb: List[Path] = typer.Option([], "--rgb", help="RGB images (folder or files) oriented in the same block."),
    rig: Optional[Path] = typer.Option(None, "--rig", help="rig.json (needs --rgb): thermal poses from the paired RGB poses through R, t, "
                                       "held or estimated (Barazzetti et al. 2013; see docs/verbs/survey.md)."),
    gnss: str = typer.Option("auto", "--gnss", help="auto (EXIF/XMP, RTK σ), none, or gnss.csv (image,X,Y,Z[,sX,sY,sZ] in --crs)."),
    crs: Optional[str] = typer.Option(None, "--crs", help="Output CRS, e.g. EPSG:2056 (default: UTM zone of the GNSS)."),
    gcps: Optional[Path] = typer.Option(None, "--gcps", help="gcps.csv: id,X,Y,Z[,sX,sY,sZ] (E,N,H accepted), metres in --crs."),
    gcp_measurements: Optional[Path] = typer.Option(None, "--gcp-measurements", help="image,id,x,y[,sx,sy] (px, (0,0) = centre of the "
                                                    "top-left pixel); ids in no control file are manual tie points (see docs/formats/csv.md)."),
    checkpoints: Optional[Path] = typer.Option(None, "--checkpoints", help="cp.csv: id,X,Y,Z — never used in the adjustment."),
    check_measurements: Optional[Path] = typer.Option(None, "--check-measurements", help="image,id,x,y of the check points."),
    workers: int = typer.Option(2, "--workers", help="Local dask worker processes for features and matching (0 or 1 = in this process)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Address of an existing dask scheduler (instead of --workers)."),
    lever_arm: Optional[str] = typer.Option(None, "--lever-arm", help="GNSS antenna offset X,Y,Z in metres in the camera "
                                            "frame (x right, y down, z forward); default 0,0,0."),
    gnss_sigma: Optional[str] = typer.Option(None, "--gnss-sigma", help="σ of every GNSS position, H,V or X,Y,Z in metres "
                                             "(overrides the RTK status / CSV columns)."),
    low_texture: str = typer.Option("auto", "--low-texture", help="auto (default): fallback tie points for weak thermal texture, its "
                                    "blocks refused when not flat; off: never (see docs/verbs/survey.md)."),
    refine_ties: str = typer.Option("off", "--refine-ties", help="lsm: affine least-squares matching of the tie points (measured "
                                    "mixed); off: keypoints (see docs/verbs/survey.md)."),
    detector: str = typer.Option("sift", "--detector", help="Tie-point detector: sift (default), asift (frames taken 30-60° "
                                 "apart; ~20x the feature time) or orb (see docs/verbs/survey.md)."),
    video_overlap: float = typer.Option(0.8, "--video-overlap", help="Forward overlap of the frames extracted from a "
                                        "video or SEQ/CSQ, measured from the images (see docs/verbs/survey.md)."),
    mapper: str = typer.Option("auto", "--mapper", help="incremental, global, or auto (default: global too when the "
                               "incremental's largest block holds < 80 % of the images; see docs/verbs/survey.md)."),
    dji_sdk: Optional[Path] = typer.Option(None, "--dji-sdk", help="DJI Thermal SDK library (libdirp.so) for DJI R-JPEGs: "
                                           "frames in kelvin instead of raw counts (also $THERMOGRAMMETRY_DJI_TSDK; docs/dji.md)."),
    cache: Optional[Path] = typer.Option(None, "--cache", help="Folder of features and verified matches kept by content: "
                                         "a later survey of the same frames reads them instead of computing them again "
                                         "(same outputs; see docs/verbs/survey.md)."),
) -> None:
    """Orient thermal frames (and RGB images) into one georeferenced block, with an accuracy report.

    Exit status: 0 when a block was oriented (some frames may be left out, each with its reason in survey.json and the report), 1 when nothing could be oriented (OUT still holds the report and the reasons), 2 on unusable input or arguments (nothing written).
    """  # noqa: E501 (one line: typer keeps the docstring's line breaks in --help)
    args = {k: v for k, v in locals().items() if k in SURVEY_ARGS}
    from rich.console import Console

    from ..errors import ThermogrammetryError
    from ..pipeline.survey import survey_to_folder

    console = Console(stderr=True)

    def fail(msg, code=2):
        # user data (file names, values such as "[nan, 1.0]") printed literally: no markup in them
        console.print("error:", style="red", end=" ", highlight=False)
        console.print(str(msg), markup=False, highlight=False, soft_wrap=True)
        console.print(f"nothing was written to {out}", markup=False, highlight=False)
        raise typer.Exit(code)

    try:
        inp, opt = survey_inputs(**args)
    except (ThermogrammetryError, ValueError, OSError) as exc:
        fail(str(exc))
    if inp.camera_file is not None:
        from ..io.camera_file import describe_camera_file

        console.print(describe_camera_file(inp.camera_file), markup=False, highlight=False, soft_wrap=True)
    t0 = time.perf_counter()
    try:
        with _Progress(console) as prog:
            run = survey_to_folder(out, inp, opt, progress=prog)
    except (ThermogrammetryError, OSError, ValueError) as exc:
        fail(str(exc))
    if run.failed is not None:
        r = run.failed
        first = r.error.strip().splitlines()[-1] if r.error else "failed"
        if r.name == "inputs":  # unusable input: exit 2
            fail(first.split(": ", 1)[-1] if first.startswith(("DataFileError", "UnsupportedFormatError")) else first)
        fail(f"step {r.name} failed: {first}", code=1)
    s = run.survey
    dt = time.perf_counter() - t0
    console.print(f"{s['images_oriented']}/{s['images_total']} images oriented in {len(s['components'])} block(s) "
                  f"{s['components']}, reprojection RMS {s['reprojection_rms_px'] or float('nan'):.3f} px, "
                  f"CRS {s['crs'] or 'local'} ({dt:.1f} s)", highlight=False, markup=False)
    for ax in ("checkpoints", "gcps"):
        d = s[ax]
        if d["n"]:
            console.print(f"{ax}: n={d['n']} RMSE X {d['rmse_x']:.3f} Y {d['rmse_y']:.3f} Z {d['rmse_z']:.3f} m", highlight=False, markup=False)
    bad = [im for im in s["images"] if not im["oriented"]]
    for im in bad:
        console.print(f"  not oriented: {im['name']}: {im['reason']}", highlight=False, soft_wrap=True, markup=False)
    console.print(f"outputs in {out}: cameras.json survey.json report.html colmap/ sparse.ply sparse.las", highlight=False, markup=False)
    if s["images_oriented"] == 0:
        raise typer.Exit(1)



#: the parameters of :func:`survey` that :func:`survey_inputs` reads (``run`` shares them)
SURVEY_ARGS = ("images", "out", "input_unit", "camera", "rgb", "rig", "gnss", "crs", "gcps", "gcp_measurements", "checkpoints",
               "check_measurements", "workers", "scheduler", "lever_arm", "gnss_sigma", "low_texture", "refine_ties", "detector",
               "video_overlap", "mapper", "dji_sdk", "cache")


def survey_inputs(*, images, out, input_unit, camera, rgb, rig, gnss, crs, gcps, gcp_measurements, checkpoints,
                  check_measurements, workers, scheduler, lever_arm, gnss_sigma, low_texture, refine_ties, detector,
                  video_overlap, mapper, dji_sdk, cache=None):
    """The survey's :class:`SurveyInput` and :class:`SurveyOptions` from its command-line arguments (also ``run``'s),
    every user file checked (and its CSV rows read) before any frame is decoded.

    Raises
    ------
    ThermogrammetryError, ValueError, OSError
        An unusable argument or file (the message names it); the caller exits with status 2.
    """
    from ..errors import ThermogrammetryError
    from ..io.camera_file import open_camera_file
    from ..pipeline.survey import SurveyInput, SurveyOptions

    if dji_sdk is not None:
        from ..io.dji_sdk import check_dji_sdk

        check_dji_sdk(dji_sdk)
    rig_file = None
    if rig is not None:
        from ..sfm.rig import read_rig

        if not rgb:
            raise ThermogrammetryError(f"--rig {rig}: rig mode needs the RGB images (--rgb DIR) whose poses the thermal "
                                       "images follow")
        rig_file = read_rig(rig)
    if gcps is not None and gcp_measurements is None:
        raise ThermogrammetryError("--gcps needs --gcp-measurements (the image measurements of the GCPs)")
    if (checkpoints is None) != (check_measurements is None):
        raise ThermogrammetryError("--checkpoints and --check-measurements go together")
    for p, flag in ((gcps, "--gcps"), (gcp_measurements, "--gcp-measurements"), (checkpoints, "--checkpoints"),
                    (check_measurements, "--check-measurements"), (camera, "--camera")):
        if p is not None and not p.is_file():
            raise ThermogrammetryError(f"{flag} {p}: no such file")
    if gnss.lower() not in ("auto", "none") and not Path(gnss).is_file():
        raise ThermogrammetryError(f"--gnss {gnss!r}: expected auto, none or the path of a gnss.csv; no such file")
    if out.exists() and not out.is_dir():
        raise ThermogrammetryError(f"-o {out}: exists and is not a folder")
    # the user's CSV files are read once here, so that a malformed row stops the run before any frame is decoded
    from ..io.testfield_csv import read_control_csv, read_gnss_csv, read_measurements_csv

    if gnss.lower() not in ("auto", "none"):
        read_gnss_csv(gnss)
    for p in (gcps, checkpoints):
        if p is not None:
            read_control_csv(p)
    for p in (gcp_measurements, check_measurements):
        if p is not None:
            read_measurements_csv(p)
    cam_file = open_camera_file(camera) if camera is not None else None
    cam = cam_file.camera if cam_file is not None else None
    extra = {}
    for flag, val, sizes in (("--lever-arm", lever_arm, (3,)), ("--gnss-sigma", gnss_sigma, (2, 3))):
        if val is None:
            continue
        try:
            v = [float(x) for x in val.split(",")]
        except ValueError:
            raise ThermogrammetryError(f"{flag} {val!r}: expected comma-separated numbers in metres") from None
        if len(v) not in sizes or not all(math.isfinite(x) and abs(x) < 1e3 for x in v):
            raise ThermogrammetryError(f"{flag} {val!r}: expected {' or '.join(str(k) for k in sizes)} finite numbers in metres")
        if flag == "--lever-arm":
            extra["lever_arm_m"] = tuple(v)
        else:
            if min(v) <= 0:
                raise ThermogrammetryError(f"{flag} {val!r}: standard deviations must be > 0")
            extra["gnss_sigma_m"] = tuple(v if len(v) == 3 else (v[0], v[0], v[1]))
    from ..sfm.features import ASIFT_MAX_FEATURES, Detector, FeatureOptions

    det = Detector(detector)
    extra["features"] = (FeatureOptions(detector=det, max_features=ASIFT_MAX_FEATURES) if det is Detector.ASIFT
                         else FeatureOptions(detector=det))
    if refine_ties.lower() not in ("off", "lsm"):
        raise ThermogrammetryError(f"--refine-ties {refine_ties!r}: expected off or lsm")
    if refine_ties.lower() == "lsm":
        from ..sfm.lsm import LsmOptions

        extra["tie_refinement"] = LsmOptions()
    if not (math.isfinite(video_overlap) and 0 <= video_overlap < 1):
        raise ThermogrammetryError(f"--video-overlap {video_overlap!r}: expected a fraction in [0, 1), e.g. 0.8")
    opt = SurveyOptions(input_unit=input_unit, gnss=gnss, crs=crs, low_texture=low_texture, mapper=mapper,
                        video_overlap=video_overlap, **extra, workers=workers if scheduler is None else 0,
                        scheduler=scheduler, dji_sdk=None if dji_sdk is None else str(dji_sdk),
                        cache=None if cache is None else str(cache))
    inp = SurveyInput([str(p) for p in images], [str(p) for p in rgb], cam, str(gcps) if gcps else None,
                      str(gcp_measurements) if gcp_measurements else None, str(checkpoints) if checkpoints else None,
                      str(check_measurements) if check_measurements else None, rig=rig_file,
                      camera_file=None if cam_file is None else cam_file.to_dict())
    return inp, opt
