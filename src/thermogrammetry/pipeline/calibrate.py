"""The ``calibrate`` verb's driver: target images or a surveyed 3D test field → observations → self-calibration → OUT.

Routes (see ``thermogrammetry calibrate --help`` and the calibrate page of the docs): chessboards, circle grids
(optionally with ring-coded marks and the circle-centre bias removed, Khodaei et al. 2015), coded checkerboards,
and the staged self-calibration on a 3D test field of Yastikli & Guler 2013. The detection and the adjustment are
in :mod:`thermogrammetry.calibration` and take arrays; this module reads the files, runs the two steps
(:func:`thermogrammetry.calibration.calibration_steps`) in memory and writes OUT as one output set
(:class:`~thermogrammetry._atomic.OutputSet`): a failed run leaves OUT as it was.

References
----------
N. Yastikli, E. Guler, "Performance evaluation of thermographic cameras for photogrammetric measurements",
ISPRS Archives, 2013. B. Khodaei, F. Samadzadegan, F. Dadras Javan, H. Hasani, "3D surface generation from aerial
thermal imagery".
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import List

import numpy as np

from .._validate import parse_size
from ..errors import ConfigError
from ..reporting import ReportHeader, command_line, folders_of, insert_header, python_call

__all__ = ["CalibrateRun", "CalibrateUsageError", "run_calibrate", "read_image"]

_IMAGE_EXT = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".pgm", ".pnm"}


class CalibrateUsageError(ConfigError):
    """A flag missing, contradicting another or malformed (the command line, not a file, is wrong)."""


@dataclass
class CalibrateRun:
    """What :func:`run_calibrate` did: the step reports; the failed step (OUT unchanged) or ``calibration.json``
    and the keys written to OUT."""

    reports: list
    failed: object | None = None
    calibration: dict = field(default_factory=dict)
    keys: list = field(default_factory=list)


class _NoProgress:
    def add_task(self, *a, **k):
        return 0

    def advance(self, *a, **k):
        pass

    def update(self, *a, **k):
        pass


@contextlib.contextmanager
def _no_progress():
    yield _NoProgress()


def _pair(text: str, flag: str) -> tuple[int, int]:
    pair = parse_size(text)
    if pair is None:
        raise CalibrateUsageError(f"{flag} {text!r}: expected COLUMNSxROWS with positive integers, e.g. 6x5")
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
            raise CalibrateUsageError(f"--bottom-left-square {bl!r}: expected white or black")
        bl_dark = b in ("black", "dark")
        kw["top_left_square"] = "dark" if (bl_dark if rows % 2 == 0 else not bl_dark) else "bright"
    elif tf is None and "inner_rows" in kw:
        # default: bottom-left square white (the MRT target), whatever the number of rows
        kw["top_left_square"] = "dark" if rows % 2 == 1 else "bright"
    if tf is None and (corners is None or spacing_mm is None or coded.get("marker_mm") is None):
        missing = [f for f, v in (("--corners", corners), ("--spacing-mm", spacing_mm), ("--marker-mm", coded.get("marker_mm")))
                   if v is None]
        raise CalibrateUsageError(f"--target coded needs {', '.join(missing)} (e.g. --corners 11x9 --spacing-mm 50.5 "
                                 "--marker-mm 161.5) or --target-file parameters.yaml")
    return CodedCheckerboardSpec(**kw)


def _coded_marks(value: str, cols: int, rows: int, diameter_mm) -> tuple:
    """``--coded-marks`` as ((column, row, code id), ...); BadParameter naming the value otherwise."""
    import re

    from ..targets import SEED003_MARKS

    text = str(value).strip()
    if diameter_mm is None:
        raise CalibrateUsageError(f"--coded-marks {value!r} needs --diameter-mm (the rings are sized from the circle "
                                 "diameter, e.g. --diameter-mm 20)")
    if text.lower() in ("default", "seed003", "seed-003"):
        if (cols, rows) != (7, 4):
            raise CalibrateUsageError(f"--coded-marks {value!r} is the layout of Khodaei et al. 2015 on a 7x4 grid, but --grid is "
                                     f"{cols}x{rows}: give the marks as COLUMNxROW=CODE,... (e.g. 1x1=0,3x2=1)")
        return SEED003_MARKS
    marks = []
    for entry in text.split(","):
        m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*=\s*(\d+)\s*", entry)
        if m is None:
            raise CalibrateUsageError(f"--coded-marks {value!r}: entry {entry.strip()!r}: expected COLUMNxROW=CODE with "
                                     "non-negative integers (0-based column and row of the marked circle, the ring's "
                                     "code id), e.g. 1x1=0, or 'default'")
        marks.append(tuple(int(g) for g in m.groups()))
    return tuple(marks)


def _options(model, k45: bool, affinity: bool, fix_k3: bool, rational: bool):
    """The self-calibration's options from the flags; CalibrateUsageError naming the flag and the valid values."""
    from ..calibration.selfcal import SelfCalibrationOptions
    from ..calibration.selfcal_inputs import calibration_model
    from ..camera.models import CameraModel

    try:
        m = calibration_model(model)
    except ConfigError:
        from ..calibration.bundle import CALIBRATION_MODELS

        raise CalibrateUsageError(f"--model {model!r}: expected one of "
                                  + ", ".join(v.value for v in CALIBRATION_MODELS)) from None
    if m is CameraModel.OPENCV and (k45 or affinity):
        flags = " and ".join(f for f, v in (("--k45", k45), ("--affinity", affinity)) if v)
        raise CalibrateUsageError(f"{flags}: K4, K5, B1 and B2 are parameters of the photogrammetric model; with --model "
                                  "opencv fx and fy are estimated apart already, and --rational adds k4, k5, k6")
    if m is CameraModel.PHOTOGRAMMETRIC and rational:
        raise CalibrateUsageError("--rational: k4, k5, k6 are parameters of the opencv model; use it with --model opencv "
                                  "(the photogrammetric model takes --k45 for K4, K5)")
    fixed = (("k3",) if m is CameraModel.OPENCV else ("K3",)) if fix_k3 else ()
    return SelfCalibrationOptions(model=m, k45=k45, affinity=affinity, rational=rational, fixed=fixed)


def run_calibrate(images, target, corners, grid, spacing_mm, asymmetric, diameter_mm, control, measurements, image_size,
                  pixel_pitch_um, focal_mm, output, k45, affinity, name, coded=None, *, model="photogrammetric",
                  fix_k3: bool = False, rational: bool = False, progress=None) -> CalibrateRun:
    """Calibrate from target images (chessboard, circle grid, coded checkerboard) or a surveyed 3D test field and
    write OUT (``camera.json``, ``calibration.json``, ``report.html``, exports) as one output set.

    ``model``: the camera model estimated, ``"photogrammetric"`` (correction form) or ``"opencv"`` (forward form, as
    ``cv2.calibrateCamera``: fx fy cx cy k1 k2 p1 p2 k3); ``fix_k3`` holds K3 / k3 at 0 (``cv2.CALIB_FIX_K3``);
    ``rational`` (opencv) also estimates k4, k5, k6 (``cv2.CALIB_RATIONAL_MODEL``).

    ``progress()`` gives a context manager with ``add_task(description, total)``, ``advance(task)`` and
    ``update(task, ...)`` (a rich Progress); None shows nothing. Usage errors raise :class:`CalibrateUsageError`,
    bad input a :class:`~thermogrammetry.errors.ThermogrammetryError`, before anything is written. A failed
    adjustment is a result (``failed``), OUT unchanged.
    """
    call, t0 = python_call(run_calibrate, locals()), time.perf_counter()  # (the report's command line and time)
    coded = coded or {}
    progress = progress or _no_progress
    from ..calibration.outputs import flush
    from ..calibration.pipeline import calibration_steps, observations_dict
    from ..calibration.workflow import prepare_detections, prepare_testfield
    from ..io.testfield_csv import read_control_csv, read_measurements_csv
    from ..store import FolderProject, MemoryProject, run_steps

    opt = _options(model, k45, affinity, fix_k3, rational)
    if output.exists() and not output.is_dir():
        raise CalibrateUsageError(f"-o {output}: exists and is not a folder")
    csv_route = control is not None or measurements is not None
    if csv_route:
        if images:
            raise CalibrateUsageError("give either IMAGES with --target, or --control and --measurements, not both")
        if control is None or measurements is None:
            raise CalibrateUsageError("the test-field route needs both --control and --measurements")
        missing = [f for f, v in (("--image-size", image_size), ("--pixel-pitch-um", pixel_pitch_um), ("--focal-mm", focal_mm)) if v is None]
        if missing:
            raise CalibrateUsageError(f"the test-field route needs {', '.join(missing)} (e.g. --image-size 320x240 --pixel-pitch-um 25 --focal-mm 18)")
        if pixel_pitch_um <= 0 or focal_mm <= 0:
            raise CalibrateUsageError(f"--pixel-pitch-um {pixel_pitch_um} / --focal-mm {focal_mm}: expected positive numbers")
        size = _pair(image_size, "--image-size")
        ctl = read_control_csv(control)
        meas = read_measurements_csv(measurements)
        cams, pts, pstd, ims, meta = prepare_testfield(ctl, meas, image_size=size, pixel_pitch_um=pixel_pitch_um,
                                                       focal_mm=focal_mm, camera_name=name)
        obs = observations_dict(cams, pts, ims, point_std=pstd, point_ids=ctl.ids, meta=meta)
        n_images = len(ims)
    else:
        if not images:
            raise CalibrateUsageError("no IMAGES given (or use --control/--measurements for a 3D test field)")
        if target is None:
            raise CalibrateUsageError("--target is required with IMAGES: chessboard, circles or coded")
        kind = target.strip().lower()
        if kind in ("circle", "circlegrid", "circle-grid"):
            kind = "circles"
        if kind in ("coded-checkerboard", "coded_checkerboard", "aruco"):
            kind = "coded"
        if kind not in ("chessboard", "circles", "coded"):
            raise CalibrateUsageError(f"--target {target!r}: expected chessboard, circles or coded")
        if kind != "circles" and coded.get("coded_marks") is not None:
            raise CalibrateUsageError(f"--coded-marks {coded['coded_marks']!r} describes ring-coded marks on a circle grid: "
                                     "use it with --target circles")
        if kind != "coded" and coded.get("target_file") is not None:
            raise CalibrateUsageError("--target-file describes a coded checkerboard: use it with --target coded")
        if not (kind == "coded" and coded.get("target_file") is not None) and (spacing_mm is None or spacing_mm <= 0):
            raise CalibrateUsageError("--spacing-mm is required and must be positive (square size or centre spacing in mm)")
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
                raise CalibrateUsageError("--corners COLUMNSxROWS is required for --target chessboard (inner corners, e.g. 6x5)")
            cols, rows = _pair(corners, "--corners")
            spec = ChessboardSpec(cols, rows, spacing_mm, corner0_square="any")
            desc = f"chessboard {cols}x{rows} inner corners, {spacing_mm:g} mm squares"
        else:
            if grid is None:
                raise CalibrateUsageError("--grid COLUMNSxROWS is required for --target circles (circle centres, e.g. 7x4)")
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
                    raise CalibrateUsageError(f"--coded-marks {coded['coded_marks']!r}: {exc}") from None
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
        with progress() as prog:
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

            with progress() as prog:
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
    with progress() as prog:
        task = prog.add_task("resection", total=max(n_images, 1))

        def cb(stage, done, total):
            prog.update(task, description=stage, completed=done if stage == "resection" else n_images)

        reports = run_steps(mem, calibration_steps(obs, opt, progress=cb))
    failed = [r for r in reports if not r.ok]
    if failed:
        return CalibrateRun(reports, failed=failed[0])
    from .._atomic import OutputSet

    inputs = ([(n_images, "target images", folders_of(images))] if not csv_route else
              [(n_images, "images measured", []), (None, "control points", [str(Path(control).resolve())]),
               (None, "image measurements", [str(Path(measurements).resolve())])])
    mem.write_text("report.html", insert_header(mem.read_text("report.html"), ReportHeader(
        "calibrate", inputs=inputs, command=command_line() or call, seconds=time.perf_counter() - t0)))
    # the whole set or nothing: staged beside OUT, moved into place, calibrate-manifest.json written last
    with OutputSet(output, "calibrate") as stage:
        keys = flush(mem, FolderProject(stage.stage))
        stage.commit()
    return CalibrateRun(reports, calibration=mem.read_json("calibration.json"), keys=keys)


