"""The ``closerange`` verb's driver: the user's CSV files, cameras and thermal image → the workflow's steps → OUT.

The workflow of Sawicki, Stein & Więcek (optical cameras by DLT, pass points by intersection with precision, the
thermal camera from pass points only, planes, per-pixel angle/emissivity/transmission-corrected temperatures) is a
list of steps over a store (:func:`thermogrammetry.closerange.closerange_steps`). This driver reads and validates
the user's files first, so that the messages name them and a bad input leaves nothing behind, then runs the steps
in a staging folder and publishes OUT as one output set (:class:`~thermogrammetry._atomic.OutputSet`).

References
----------
P. Sawicki, R. Stein, B. Więcek, "Directional emissivity correction by photogrammetric 3D object reconstruction".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

__all__ = ["CloseRangeRun", "run_closerange", "read_text"]


@dataclass
class CloseRangeRun:
    """What :func:`run_closerange` did: the step reports, the first failed step (None when all ran; OUT is then
    unchanged) with its message, and ``planes.csv`` of a finished run."""

    reports: list
    failed: object | None = None
    error: str = ""
    planes_csv: str = ""


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


def run_closerange(out, *, control, measurements, planes, thermal: str, config, cameras: dict | None = None,
                   thermal_image=None, thermal_unit: str | None = None, ambient_c: float = 22.0, sigma_px: float = 0.5,
                   humidity: float = 50.0, max_angle_deg: float = 75.0, refractive_index: float = 1.5,
                   on_step: Callable | None = None) -> CloseRangeRun:
    """Run the close-range workflow into ``out``.

    ``cameras`` maps image names to camera files (known interior orientations, from ``calibrate``). Bad input raises
    a :class:`~thermogrammetry.errors.ThermogrammetryError` naming the file before anything is written.
    """
    from .._atomic import OutputSet
    from ..camera import Camera
    from ..closerange.pipeline import closerange_steps, write_inputs
    from ..closerange.tables import parse_control, parse_measurements, parse_planes
    from ..errors import ConfigError
    from ..store import FolderProject, run_steps

    cams = {name: Camera.load(Path(path)).to_dict() for name, path in (cameras or {}).items()}
    thermal_k, unit = None, "K"
    if thermal_image is not None:
        from ..io import read_thermal

        img = read_thermal(thermal_image, unit=thermal_unit)
        thermal_k = img.require_temperature()
        unit = (thermal_unit or _unit_of(img)).upper().lstrip("°")
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
                     planes_csv=texts["planes"], thermal=thermal, config=config, cameras=cams,
                     thermal_k=thermal_k, thermal_unit=unit)
        reports = run_steps(project, closerange_steps(), on_step=on_step)
        failed = [r for r in reports if not r.ok]
        if failed:
            return CloseRangeRun(reports, failed[0], str(failed[0].error).replace(str(stage.stage), str(out)))
        planes_text = project.read_text("planes.csv")
        stage.commit({"thermal": thermal})
    return CloseRangeRun(reports, planes_csv=planes_text)
