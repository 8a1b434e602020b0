"""``thermogrammetry calibrate``: camera calibration with standard deviations (Yastikli & Guler 2013; Khodaei et al. 2015).

Routes (public contract)::

    thermogrammetry calibrate IMAGES... --target chessboard --corners 6x5 --spacing-mm 100 -o OUT
    thermogrammetry calibrate IMAGES... --target circles --grid 7x4 --spacing-mm 50 [--asymmetric] -o OUT
    thermogrammetry calibrate IMAGES... --target circles --grid 7x4 --spacing-mm 50 --diameter-mm 20 \
        --coded-marks default -o OUT          (Khodaei et al. 2015: 28 circles, 4 ring-coded marks)
    thermogrammetry calibrate IMAGES... --target coded --corners 11x9 --spacing-mm 50.5 --marker-mm 161.5 -o OUT
    thermogrammetry calibrate IMAGES... --target coded --target-file parameters.yaml -o OUT
    thermogrammetry calibrate --control control.csv --measurements measurements.csv \\
        --image-size 320x240 --pixel-pitch-um 25 --focal-mm 18 -o OUT

IMAGES may be files or folders (8-bit JPEG/PNG, 16-bit TIFF/PNG, float TIFF). Everything is computed
in memory and written to OUT only at the end (each file atomically), so a failed run leaves OUT as
it was. Bad input exits with status 2 and a message naming the file (and row).
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import numpy as np
import typer

from .app import app, parse_size

_IMAGE_EXT = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".pgm", ".pnm"}


def _pair(text: str, flag: str) -> tuple[int, int]:
    pair = parse_size(text)
    if pair is None:
        raise typer.BadParameter(f"{flag} {text!r}: expected COLUMNSxROWS with positive integers, e.g. 6x5")
    return pair


def _expand(paths: List[Path]) -> list[Path]:
    from ..errors import DataFileError

    out: list[Path] = []
    for p in paths:
        if p.is_dir():
            files = sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() in _IMAGE_EXT)
            if not files:
                raise DataFileError(f"{p}: folder holds no image files ({', '.join(sorted(_IMAGE_EXT))})")
            out.extend(files)
        elif p.is_file():
            out.append(p)
        else:
            raise DataFileError(f"{p}: no such file or folder")
    return out


def read_image(path: Path) -> np.ndarray:
    """Read an 8-bit JPEG/PNG, a 16-bit TIFF/PNG or a float TIFF as an array (no rescaling).

    Delegates to the detection package's reader (:func:`thermogrammetry.calibration.detect_io.read_image`).
    """
    from ..calibration.detect_io import read_image as _read

    img = np.asarray(_read(path))
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    return img


def _detector(kind: str):
    """The detection engineer's function for ``kind`` (chessboard / circles)."""
    import importlib

    names = {"chessboard": [("detect_chessboard", "detect_chessboard"), ("detect", "detect_chessboard")],
             "coded": [("detect_coded", "detect_coded_checkerboard")],
             "circles": [("detect_circles", "detect_circle_grid"), ("detect_circlegrid", "detect_circle_grid"),
                         ("detect_circle_grid", "detect_circle_grid"), ("detect", "detect_circle_grid"),
                         ("detect_circles", "detect_circles")]}[kind]
    for mod, fn in names:
        try:
            m = importlib.import_module(f"thermogrammetry.calibration.{mod}")
        except ImportError:
            continue
        if hasattr(m, fn):
            return getattr(m, fn)
    return None


def _fallback_circles(image, spec, image_id):
    """INTERIM circle-grid detection (cv2.findCirclesGrid on a contrast-stretched image) used only
    while the detection engineer's circle-grid detector is absent."""
    import cv2

    from ..calibration.detect_common import Detection, normalize_to_u8, to_gray_float

    gray = to_gray_float(image, image_id)
    h, w = gray.shape
    u8 = normalize_to_u8(gray)
    flags = cv2.CALIB_CB_ASYMMETRIC_GRID if spec.asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
    for img in (u8, 255 - u8):
        ok, centers = cv2.findCirclesGrid(img, spec.pattern_size, flags=flags)
        if ok:
            return Detection(image_id, True, centers.reshape(-1, 2).astype(float), np.arange(spec.n_points), "cv2.findCirclesGrid (interim)",
                             (w, h), "interim")
    return Detection.failure(image_id, "cv2.findCirclesGrid found no grid (normal or inverted contrast)", (w, h))


@app.command("calibrate")
def calibrate(
    images: Optional[List[Path]] = typer.Argument(None, help="Images (or folders of images) of a target."),
    target: Optional[str] = typer.Option(None, "--target", help="Target kind: chessboard, circles or coded (checkerboard with an ArUco marker on its central corner, Schramm et al. 2021)."),
    corners: Optional[str] = typer.Option(None, "--corners", help="Chessboard / coded checkerboard inner corners COLUMNSxROWS (OpenCV patternSize), e.g. 6x5 or 11x9."),
    marker_mm: Optional[float] = typer.Option(None, "--marker-mm", help="Coded target: side of the ArUco marker (outer black border) in mm, e.g. 161.5."),
    hidden_squares: Optional[int] = typer.Option(None, "--hidden-squares", help="Coded target: the marker blanks NxN squares around the central corner (default 4)."),
    marker_bits: Optional[int] = typer.Option(None, "--marker-bits", help="Coded target: inner bits per marker side of the custom dictionary (default 3: custom_dictionary(1, 3))."),
    dictionary: Optional[str] = typer.Option(None, "--dictionary", help="Coded target: a predefined cv2.aruco dictionary (e.g. DICT_4X4_50) instead of the custom one."),
    marker_id: Optional[int] = typer.Option(None, "--marker-id", help="Coded target: id of the marker in its dictionary (default 0)."),
    bottom_left_square: Optional[str] = typer.Option(None, "--bottom-left-square", help="Coded target: colour of the board's bottom-left square as printed, white or black (default white)."),
    target_file: Optional[Path] = typer.Option(None, "--target-file", help="Coded target: its own description (MRT parameters.yaml); flags given as well override it."),
    grid: Optional[str] = typer.Option(None, "--grid", help="Circle grid COLUMNSxROWS of centres, e.g. 7x4."),
    spacing_mm: Optional[float] = typer.Option(None, "--spacing-mm", help="Square size / centre spacing in mm."),
    asymmetric: bool = typer.Option(False, "--asymmetric", help="Asymmetric (staggered) circle grid."),
    diameter_mm: Optional[float] = typer.Option(None, "--diameter-mm", help="Circle diameter in mm: each circle's centroid bias is removed, iterated with the calibration (see docs/verbs/calibrate.md)."),
    coded_marks: Optional[str] = typer.Option(None, "--coded-marks", help="Ring-coded marks on the circle grid: 'default' (Khodaei et al. 2015's 7x4 layout) or COLUMNxROW=CODE,...; needs --diameter-mm (see docs/verbs/calibrate.md)."),
    control: Optional[Path] = typer.Option(None, "--control", help="Control points CSV: id,X,Y,Z[,sX,sY,sZ] (metres)."),
    measurements: Optional[Path] = typer.Option(None, "--measurements", help="Image measurements CSV: image,id,x,y[,sx,sy] (pixels)."),
    image_size: Optional[str] = typer.Option(None, "--image-size", help="WIDTHxHEIGHT in pixels (CSV route), e.g. 320x240."),
    pixel_pitch_um: Optional[float] = typer.Option(None, "--pixel-pitch-um", help="Pixel pitch in micrometres."),
    focal_mm: Optional[float] = typer.Option(None, "--focal-mm", help="Nominal focal length in mm (required for the CSV route)."),
    output: Path = typer.Option(..., "-o", "--output", help="Output folder."),
    k45: bool = typer.Option(False, "--k45", help="Also estimate K4, K5 (as Khodaei et al. 2015 do)."),
    affinity: bool = typer.Option(False, "--affinity", help="Also estimate affinity/shear B1, B2."),
    name: str = typer.Option("camera", "--name", help="Camera name written into camera.json."),
) -> None:
    """Calibrate a (thermal) camera: parameters with standard deviations, report and exports in OUT."""
    from rich.console import Console

    from ..errors import ThermogrammetryError

    err = Console(stderr=True, soft_wrap=True)
    try:
        coded = dict(marker_mm=marker_mm, hidden_squares=hidden_squares, marker_bits=marker_bits, dictionary=dictionary,
                     marker_id=marker_id, bottom_left_square=bottom_left_square, target_file=target_file,
                     coded_marks=coded_marks)
        run = _run(images, target, corners, grid, spacing_mm, asymmetric, diameter_mm, control, measurements, image_size,
                   pixel_pitch_um, focal_mm, output, k45, affinity, name, coded)
    except typer.BadParameter as exc:
        err.print(f"[bold red]error:[/] {exc}", markup=True, highlight=False)
        raise typer.Exit(2) from None
    except ThermogrammetryError as exc:
        err.print(f"[bold red]error:[/] {type(exc).__name__}: {exc}", markup=True, highlight=False)
        err.print(f"nothing was written to {output}", highlight=False)
        raise typer.Exit(2) from None
    if run is None:
        raise typer.Exit(1)


def _coded_spec(corners, spacing_mm, coded: dict):
    """The coded checkerboard from ``--target-file`` (if given), then the explicit flags, then the MRT
    defaults (:class:`thermogrammetry.targets.CodedCheckerboardTarget`)."""
    from ..calibration.detect_common import CodedCheckerboardSpec
    from ..errors import ConfigError, DataFileError

    kw: dict = {}
    tf = coded.get("target_file")
    if tf is not None:
        import yaml

        try:
            text = Path(tf).read_text()
        except OSError as exc:
            raise DataFileError(f"--target-file {tf}: cannot read ({exc.strerror or exc})") from None
        try:
            params = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise DataFileError(f"--target-file {tf}: not valid YAML ({str(exc).splitlines()[0]})") from None
        try:
            base = CodedCheckerboardSpec.from_parameters(params)
        except ConfigError as exc:
            raise ConfigError(f"--target-file {tf}: {exc}") from None
        kw = {k: getattr(base, k) for k in ("inner_columns", "inner_rows", "square_mm", "marker_mm", "hidden_squares",
                                            "marker_bits", "marker_id", "dictionary_size", "top_left_square",
                                            "predefined_dictionary")}
    if corners is not None:
        kw["inner_columns"], kw["inner_rows"] = _pair(corners, "--corners")
    if spacing_mm is not None:
        kw["square_mm"] = spacing_mm
    for flag, key in (("marker_mm", "marker_mm"), ("hidden_squares", "hidden_squares"), ("marker_bits", "marker_bits"),
                      ("marker_id", "marker_id")):
        if coded.get(flag) is not None:
            kw[key] = coded[flag]
    if coded.get("dictionary") is not None:
        d = str(coded["dictionary"]).replace("aruco.", "").upper()
        kw["predefined_dictionary"] = "" if d in ("", "CUSTOM", "DICT_3X3_1") else d
    rows = kw.get("inner_rows", CodedCheckerboardSpec.inner_rows)
    bl = coded.get("bottom_left_square")
    if bl is not None:
        b = str(bl).strip().lower()
        if b not in ("white", "black", "bright", "dark"):
            raise typer.BadParameter(f"--bottom-left-square {bl!r}: expected white or black")
        bl_dark = b in ("black", "dark")
        kw["top_left_square"] = "dark" if (bl_dark if rows % 2 == 0 else not bl_dark) else "bright"
    elif tf is None and "inner_rows" in kw:
        # default: bottom-left square white (the MRT target), whatever the number of rows
        kw["top_left_square"] = "dark" if rows % 2 == 1 else "bright"
    if tf is None and (corners is None or spacing_mm is None or coded.get("marker_mm") is None):
        missing = [f for f, v in (("--corners", corners), ("--spacing-mm", spacing_mm), ("--marker-mm", coded.get("marker_mm")))
                   if v is None]
        raise typer.BadParameter(f"--target coded needs {', '.join(missing)} (e.g. --corners 11x9 --spacing-mm 50.5 "
                                 "--marker-mm 161.5) or --target-file parameters.yaml")
    return CodedCheckerboardSpec(**kw)


def _coded_marks(value: str, cols: int, rows: int, diameter_mm) -> tuple:
    """``--coded-marks`` as ((column, row, code id), ...); BadParameter naming the value otherwise."""
    import re

    from ..targets import SEED003_MARKS

    text = str(value).strip()
    if diameter_mm is None:
        raise typer.BadParameter(f"--coded-marks {value!r} needs --diameter-mm (the rings are sized from the circle "
                                 "diameter, e.g. --diameter-mm 20)")
    if text.lower() in ("default", "seed003", "seed-003"):
        if (cols, rows) != (7, 4):
            raise typer.BadParameter(f"--coded-marks {value!r} is the seed-003 layout of a 7x4 grid, but --grid is "
                                     f"{cols}x{rows}: give the marks as COLUMNxROW=CODE,... (e.g. 1x1=0,3x2=1)")
        return SEED003_MARKS
    marks = []
    for entry in text.split(","):
        m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*=\s*(\d+)\s*", entry)
        if m is None:
            raise typer.BadParameter(f"--coded-marks {value!r}: entry {entry.strip()!r}: expected COLUMNxROW=CODE with "
                                     "non-negative integers (0-based column and row of the marked circle, the ring's "
                                     "code id), e.g. 1x1=0, or 'default'")
        marks.append(tuple(int(g) for g in m.groups()))
    return tuple(marks)


def _run(images, target, corners, grid, spacing_mm, asymmetric, diameter_mm, control, measurements, image_size,
         pixel_pitch_um, focal_mm, output, k45, affinity, name, coded=None):
    coded = coded or {}
    from rich.console import Console
    from ..calibration.outputs import flush
    from .progress import progress
    from ..calibration.pipeline import calibration_steps, observations_dict
    from ..calibration.selfcal import SelfCalibrationOptions
    from ..calibration.workflow import prepare_detections, prepare_testfield
    from ..io.testfield_csv import read_control_csv, read_measurements_csv
    from ..pipeline import FolderProject, MemoryProject, run_steps

    console = Console(soft_wrap=True)
    opt = SelfCalibrationOptions(k45=k45, affinity=affinity)
    if output.exists() and not output.is_dir():
        raise typer.BadParameter(f"-o {output}: exists and is not a folder")
    csv_route = control is not None or measurements is not None
    if csv_route:
        if images:
            raise typer.BadParameter("give either IMAGES with --target, or --control and --measurements, not both")
        if control is None or measurements is None:
            raise typer.BadParameter("the test-field route needs both --control and --measurements")
        missing = [f for f, v in (("--image-size", image_size), ("--pixel-pitch-um", pixel_pitch_um), ("--focal-mm", focal_mm)) if v is None]
        if missing:
            raise typer.BadParameter(f"the test-field route needs {', '.join(missing)} (e.g. --image-size 320x240 --pixel-pitch-um 25 --focal-mm 18)")
        if pixel_pitch_um <= 0 or focal_mm <= 0:
            raise typer.BadParameter(f"--pixel-pitch-um {pixel_pitch_um} / --focal-mm {focal_mm}: expected positive numbers")
        size = _pair(image_size, "--image-size")
        ctl = read_control_csv(control)
        meas = read_measurements_csv(measurements)
        cams, pts, pstd, ims, meta = prepare_testfield(ctl, meas, image_size=size, pixel_pitch_um=pixel_pitch_um,
                                                       focal_mm=focal_mm, camera_name=name)
        obs = observations_dict(cams, pts, ims, point_std=pstd, point_ids=ctl.ids, meta=meta)
        n_images = len(ims)
    else:
        if not images:
            raise typer.BadParameter("no IMAGES given (or use --control/--measurements for a 3D test field)")
        if target is None:
            raise typer.BadParameter("--target is required with IMAGES: chessboard, circles or coded")
        kind = target.strip().lower()
        if kind in ("circle", "circlegrid", "circle-grid"):
            kind = "circles"
        if kind in ("coded-checkerboard", "coded_checkerboard", "aruco"):
            kind = "coded"
        if kind not in ("chessboard", "circles", "coded"):
            raise typer.BadParameter(f"--target {target!r}: expected chessboard, circles or coded")
        if kind != "circles" and coded.get("coded_marks") is not None:
            raise typer.BadParameter(f"--coded-marks {coded['coded_marks']!r} describes ring-coded marks on a circle grid: "
                                     "use it with --target circles")
        if kind != "coded" and coded.get("target_file") is not None:
            raise typer.BadParameter("--target-file describes a coded checkerboard: use it with --target coded")
        if not (kind == "coded" and coded.get("target_file") is not None) and (spacing_mm is None or spacing_mm <= 0):
            raise typer.BadParameter("--spacing-mm is required and must be positive (square size or centre spacing in mm)")
        from ..calibration.detect_common import ChessboardSpec, CircleGridSpec

        if kind == "coded":
            spec = _coded_spec(corners, spacing_mm, coded)
            cols, rows = spec.inner_columns, spec.inner_rows
            spacing_mm = spec.square_mm
            desc = (f"coded checkerboard {cols}x{rows} inner corners, {spec.square_mm:g} mm squares, ArUco marker "
                    f"{spec.marker_mm:g} mm ({spec.predefined_dictionary or f'custom {spec.marker_bits}x{spec.marker_bits}-bit'} "
                    f"id {spec.marker_id}), {spec.hidden_squares}x{spec.hidden_squares} squares hidden")
        elif kind == "chessboard":
            if corners is None:
                raise typer.BadParameter("--corners COLUMNSxROWS is required for --target chessboard (inner corners, e.g. 6x5)")
            cols, rows = _pair(corners, "--corners")
            spec = ChessboardSpec(cols, rows, spacing_mm, corner0_square="any")
            desc = f"chessboard {cols}x{rows} inner corners, {spacing_mm:g} mm squares"
        else:
            if grid is None:
                raise typer.BadParameter("--grid COLUMNSxROWS is required for --target circles (circle centres, e.g. 7x4)")
            cols, rows = _pair(grid, "--grid")
            spec = CircleGridSpec(cols, rows, spacing_mm, asymmetric=asymmetric, diameter_mm=diameter_mm)
            desc = f"{'asymmetric' if asymmetric else 'symmetric'} circle grid {cols}x{rows}, {spacing_mm:g} mm spacing"
            if coded.get("coded_marks") is not None:
                from ..errors import ConfigError
                from ..targets import CodedCircleGridTarget

                marks = _coded_marks(coded["coded_marks"], cols, rows, diameter_mm)
                try:
                    spec = CodedCircleGridTarget(cols, rows, spacing_mm, asymmetric=asymmetric, diameter_mm=diameter_mm,
                                                 marks=marks)
                except ConfigError as exc:
                    raise typer.BadParameter(f"--coded-marks {coded['coded_marks']!r}: {exc}") from None
                desc += (f", {len(marks)} ring-coded marks ("
                         + ", ".join(f"{c}x{r}={i}" for c, r, i in spec.marks) + ")")
        detect = _detector(kind)
        interim = detect is None
        # circles of known size: raw centroids, then the bias iterated with the calibration
        # (calibration.circle_bias) instead of the per-image homography correction of the detector
        unbias = kind == "circles" and diameter_mm is not None and not interim
        det_kw = {"perspective_correction": False} if unbias else {}
        if interim:
            detect = _fallback_circles
        files = _expand(images)
        from ..errors import InvalidInputError

        dets = []
        first_size = None
        with progress(console, "calibrate") as prog:
            task = prog.add_task("detecting target", total=len(files))
            for f in files:
                img = read_image(f)
                size = (int(img.shape[1]), int(img.shape[0]))
                if first_size is None:
                    first_size = (size, f)
                elif size != first_size[0]:
                    raise InvalidInputError(
                        f"mixed image sizes: {f} is {size[0]}x{size[1]} but {first_size[1]} is "
                        f"{first_size[0][0]}x{first_size[0][1]}; calibrate the images of one camera (one size) per run")
                dets.append(detect(img, spec, f.name, **det_kw))
                prog.advance(task)
        bias_meta = None
        if unbias and any(d.found for d in dets):
            from ..calibration.circle_bias import unbias_circle_detections

            with progress(console, "calibrate") as prog:
                task = prog.add_task("circle-centre bias", total=3)
                dets, history, bias = unbias_circle_detections(
                    dets, spec, pixel_pitch_um=pixel_pitch_um, focal_mm=focal_mm, options=opt, iterations=3,
                    camera_name=name, progress=lambda k, n: prog.update(task, completed=k,
                                                                       description=f"circle-centre bias, round {k + 1}/{n}"))
            bias_meta = {"method": "centroid of each circle's outline projected through the calibrated camera (with "
                                   "distortion) and pose, minus its projected centre; subtracted from the raw centroids "
                                   "and re-calibrated, iterated (Heikkilä 2000); round 0 starts from the homography bias",
                         "rounds": history,
                         "max_bias_px": max((float(np.abs(b).max()) for b in bias.values()), default=0.0)}
        prog_desc = {"kind": kind, "description": desc, "pattern": [cols, rows], "spacing_mm": spacing_mm,
                     "asymmetric": bool(asymmetric) if kind == "circles" else None,
                     **({"marker_mm": spec.marker_mm, "hidden_squares": spec.hidden_squares} if kind == "coded" else {}),
                     "detector": "interim cv2.findCirclesGrid" if interim else f"{detect.__module__}.{detect.__name__}"}
        if kind == "circles":
            prog_desc["centre_bias"] = bias_meta or {"method": "none: give --diameter-mm to correct the centroid bias "
                                                               "of large circles"}
        prog_desc["detections"] = {d.image_id: {"found": bool(d.found), "method": d.method, "reason": d.reason}
                                   for d in dets}
        if getattr(spec, "marks", ()):
            prog_desc["coded_marks"] = [list(m) for m in spec.marks]
            for d in dets:
                cm = d.extra.get("coded_marks", {})
                prog_desc["detections"][d.image_id]["coded_marks"] = {
                    "decoded": sorted(int(k) for k in cm.get("decoded", {})),
                    "undecoded": int(cm.get("undecoded", 0)),
                    "ordering": cm.get("ordering", ""),
                }
        cams, pts, ims, not_detected, meta = prepare_detections(dets, spec.object_points() * 1e-3, target=prog_desc,
                                                                pixel_pitch_um=pixel_pitch_um, focal_mm=focal_mm,
                                                                camera_name=name)
        obs = observations_dict(cams, pts, ims, not_detected=not_detected, meta=meta)
        n_images = len(dets)
    mem = MemoryProject()
    with progress(console, "calibrate") as prog:
        task = prog.add_task("resection", total=max(n_images, 1))

        def cb(stage, done, total):
            prog.update(task, description=stage, completed=done if stage == "resection" else n_images)

        reports = run_steps(mem, calibration_steps(obs, opt, progress=cb))
    failed = [r for r in reports if not r.ok]
    if failed:
        Console(stderr=True, soft_wrap=True).print(f"[bold red]calibration failed[/] in step {failed[0].name!r}: {failed[0].error}; "
                                                   f"nothing was written to {output}", highlight=False)
        return None
    from .._atomic import OutputSet

    # the whole set or nothing: staged beside OUT, moved into place, calibrate-manifest.json written last
    with OutputSet(output, "calibrate") as stage:
        keys = flush(mem, FolderProject(stage.stage))
        stage.commit()
    _summary(console, mem.read_json("calibration.json"), output, keys)
    return reports


def _summary(console, cal: dict, output, keys) -> None:
    """One screen: parameters with σ and t-test, σx σy, warnings, rejected images, files written."""
    from rich.table import Table

    n_img = len(cal["per_image"])
    dets = cal["run"].get("target", {}).get("detections") if isinstance(cal.get("run"), dict) else None
    if dets:
        from collections import Counter

        cnt = Counter(v["method"] for v in dets.values() if v.get("found"))
        console.print(f"target found in {sum(cnt.values())}/{len(dets)} images"
                      + (f" ({', '.join(f'{m}: {k}' for m, k in sorted(cnt.items(), key=lambda x: -x[1]))})" if cnt else ""),
                      highlight=False)
        coded = [v["coded_marks"] for v in dets.values() if v.get("found") and "coded_marks" in v]
        if coded:
            n_dec = sum(len(c["decoded"]) for c in coded)
            n_num = sum(c["ordering"] == "coded marks" for c in coded)
            console.print(f"coded marks: {n_dec} decoded in {len(coded)} images; numbering fixed by them in {n_num}/"
                          f"{len(coded)}" + (" (the others keep the geometric numbering)" if n_num < len(coded) else ""),
                          highlight=False)
    cb = cal["run"].get("target", {}).get("centre_bias") if isinstance(cal.get("run"), dict) else None
    if cb and cb.get("rounds"):
        ch = ", ".join(f"{h['bias_change_px']:.4f}" for h in cb["rounds"] if h.get("bias_change_px") is not None)
        console.print(f"circle-centre bias: max {cb['max_bias_px']:.3f} px, change per round {ch} px", highlight=False)
    console.print(f"[bold]calibration[/] {cal['termination']}: {len(cal['images_used'])}/{n_img} images used, "
                  f"RMS {cal['rms_px']:.3f} px, σ0 {cal['sigma0']:.3f}, redundancy {cal['dof']}", highlight=False)
    for wtext in cal.get("warnings", []):
        console.print(f"[yellow]warning:[/] {wtext}", highlight=False)
    assumed = cal["run"].get("pixel_pitch_assumed")
    for cam in cal["cameras"]:
        w, h = cam["image_size"]
        t = Table(title=f"{cam['name']} {w}x{h}, pitch {cam['pixel_pitch_um'][0]:g} µm" + (" (assumed)" if assumed else ""),
                  show_edge=False)
        for col in ("parameter", "value", "std", "unit", "t", "signif."):
            t.add_column(col, justify="right")
        for n, p in cam["parameters"].items():
            if p["estimated"]:
                t.add_row(n, f"{p['value']:.6g}", f"{p['std']:.2g}", p["unit"], "" if "t" not in p else f"{p['t']:.1f}",
                          "" if "significant" not in p else ("yes" if p["significant"] else "no"))
        console.print(t)
        console.print(f"σx {cam['sigma_x_px']:.3f} px ({cam['sigma_x_um']:.2f} µm), σy {cam['sigma_y_px']:.3f} px "
                      f"({cam['sigma_y_um']:.2f} µm)", highlight=False)
        for wv in cam["correlation_warnings"]:
            console.print(f"[yellow]warning:[/] |ρ({wv['a']}, {wv['b']})| = {abs(wv['rho']):.3f} > 0.9", highlight=False)
    rej = cal["images_rejected"]
    if rej:
        console.print(f"[yellow]{len(rej)} image(s) rejected[/]:", highlight=False)
        for k, (nm, why) in enumerate(rej.items()):
            if k == 5:
                console.print(f"  ... and {len(rej) - 5} more (see calibration.json)")
                break
            console.print(f"  {nm}: {why}", highlight=False)
    if cal["blunders"]:
        console.print(f"{len(cal['blunders'])} observation(s) rejected as blunders ({cal['blunder_test']})", highlight=False)
    for info in cal.get("exports", {}).values():
        for fmt, key in (("OpenCV/COLMAP", "opencv"), ("Metashape", "metashape")):
            o = info.get(key, {})
            if o.get("max_residual_px") is not None:
                area = o.get("area_max_residual_px")
                console.print(f"{fmt} export: conversion residual max {o['max_residual_px']:.3f} px / RMS "
                              f"{o['rms_residual_px']:.3f} px over the whole frame"
                              + (f", max {area:.3f} px / RMS {o['area_rms_residual_px']:.3f} px over the data area"
                                 if area is not None else ""), highlight=False)
            if o.get("warning"):
                console.print(f"[yellow]warning:[/] {o['warning']}", highlight=False)
    console.print(f"wrote {len(keys)} files to {output}: {', '.join(k for k in keys if '/' not in k)}", highlight=False)
