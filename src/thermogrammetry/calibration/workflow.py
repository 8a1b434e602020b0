"""Calibration workflows: from detections of a planar target, or from a surveyed 3D test field.

Thin functions that turn inputs into :func:`~thermogrammetry.calibration.selfcal.calibrate` calls and
describe the run (``meta``) for the outputs. No file access here: the CLI reads images and CSV files
and passes arrays / parsed tables; :func:`thermogrammetry.calibration.outputs.write_outputs`
writes through a project store.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..errors import InvalidInputError, TooFewPointsError
from .selfcal import CalibrationResult, CameraSetup, ImageMeasurements, SelfCalibrationOptions, calibrate
from ..io.testfield_csv import ControlPoints, Measurements, check_measurement_ids

__all__ = ["CalibrationRun", "prepare_testfield", "calibrate_testfield", "prepare_detections", "calibrate_detections",
           "DEFAULT_PIXEL_PITCH_UM"]

#: pitch assumed when a target calibration is run without ``pixel_pitch_um``: the common pitch of
#: uncooled microbolometer arrays. Pixel-unit results do not depend on it; mm values scale with it.
DEFAULT_PIXEL_PITCH_UM = 17.0


@dataclass
class CalibrationRun:
    """A result plus what is needed to describe it (target, inputs, per-image detection verdicts)."""

    result: CalibrationResult
    meta: dict[str, Any] = field(default_factory=dict)
    detection_verdicts: dict[str, str] = field(default_factory=dict)  # image -> reason when not detected


def prepare_testfield(
    control: ControlPoints,
    meas: Measurements,
    *,
    image_size: tuple[int, int],
    pixel_pitch_um: float | tuple[float, float],
    focal_mm: float,
    camera_name: str = "camera",
) -> tuple[list[CameraSetup], np.ndarray, np.ndarray | None, list[ImageMeasurements], dict[str, Any]]:
    """Validate and assemble the inputs of a 3D test-field calibration (seed 001).

    Unknown point IDs raise (naming the measurement file and row); measurements outside the image
    (by more than 3 px) raise naming the row. Returns ``(cameras, points, point_std, images, meta)``.
    """
    if focal_mm is None or not np.isfinite(focal_mm) or focal_mm <= 0:
        raise InvalidInputError(f"focal_mm = {focal_mm!r}: expected the nominal focal length in mm (e.g. --focal-mm 18)")
    idx = check_measurement_ids(meas, control)
    w, h = image_size
    # a few pixels of slack: a noisy measurement of a target on the border may fall just outside
    tol = 3.0
    outside = (meas.xy[:, 0] < -0.5 - tol) | (meas.xy[:, 0] > w - 0.5 + tol) | (meas.xy[:, 1] < -0.5 - tol) | (meas.xy[:, 1] > h - 0.5 + tol)
    if np.any(outside):
        k = int(np.nonzero(outside)[0][0])
        raise InvalidInputError(
            f"{meas.source}, row {meas.lines[k]}: x, y = {meas.xy[k, 0]:g}, {meas.xy[k, 1]:g} px is outside the "
            f"{w}x{h} image (pixel centres 0..{w - 1}, 0..{h - 1}; OpenCV convention); check --image-size")
    cam = CameraSetup(camera_name, (w, h), pixel_pitch_um, {"c_mm": float(focal_mm)})
    images = []
    names = meas.images()
    img_arr = np.array(meas.image)
    for name in names:
        m = img_arr == name
        images.append(ImageMeasurements(name, 0, idx[m], meas.xy[m], None if meas.std is None else meas.std[m]))
    meta = {
        "route": "testfield",
        "control": {"source": control.source, "n_points": len(control.ids), "weighted": control.std is not None},
        "measurements": {"source": meas.source, "n_rows": len(meas.id), "n_images": len(names)},
        "nominal_focal_mm": float(focal_mm),
        "pixel_pitch_um": list(cam.pixel_pitch_um),
        "pixel_pitch_assumed": False,
        "point_ids": list(control.ids),
    }
    return [cam], control.xyz, control.std, images, meta


def calibrate_testfield(
    control: ControlPoints,
    meas: Measurements,
    *,
    image_size: tuple[int, int],
    pixel_pitch_um: float | tuple[float, float],
    focal_mm: float,
    options: SelfCalibrationOptions | None = None,
    camera_name: str = "camera",
    progress=None,
) -> CalibrationRun:
    """Self-calibration on a 3D test field (control CSV + measurement CSV), seed 001.

    Control points with sX, sY, sZ are adjusted as weighted unknowns; without them they are fixed.
    See :func:`prepare_testfield` for the checks.
    """
    cams, pts, pstd, images, meta = prepare_testfield(control, meas, image_size=image_size, pixel_pitch_um=pixel_pitch_um,
                                                      focal_mm=focal_mm, camera_name=camera_name)
    res = calibrate(cams, pts, images, point_std=pstd, options=options, progress=progress)
    return CalibrationRun(res, meta)


def prepare_detections(
    detections: Sequence[Any],
    object_points_m: np.ndarray,
    *,
    target: dict[str, Any],
    pixel_pitch_um: float | tuple[float, float] | None = None,
    focal_mm: float | None = None,
    camera_name: str = "camera",
) -> tuple[list[CameraSetup], np.ndarray, list[ImageMeasurements], dict[str, str], dict[str, Any]]:
    """Validate per-image detections of a planar target and assemble the calibration inputs.

    Parameters
    ----------
    detections : sequence of :class:`~thermogrammetry.calibration.detect_common.Detection`
        (``image_id``, ``found``, ``points_px`` (N,2), ``object_ids`` (N,), ``reason``, ``image_size``).
    object_points_m : (M,3) target points in metres (``spec.object_points() * 1e-3``).
    target : description for the report (kind, pattern, spacing).
    pixel_pitch_um : sensor pitch; when None :data:`DEFAULT_PIXEL_PITCH_UM` is assumed and flagged.
    focal_mm : nominal focal length; when None it is initialised from the views (Zhang).

    Returns
    -------
    ``(cameras, points, images, not_detected {image: reason}, meta)``

    Raises
    ------
    TooFewPointsError
        when the target was found in no image (the message lists the first reasons).
    InvalidInputError
        when the images do not all have the same size.
    """
    if not detections:
        raise TooFewPointsError("no images given")
    sizes = {}
    for d in detections:
        sz = tuple(int(v) for v in d.image_size)
        if sz != (0, 0):
            sizes.setdefault(sz, d.image_id)
    if len(sizes) > 1:
        desc = "; ".join(f"{w}x{h} (e.g. {name})" for (w, h), name in sizes.items())
        raise InvalidInputError(f"mixed image sizes: {desc}; calibrate the images of one camera (one size) per run")
    found = [d for d in detections if d.found]
    verdicts = {d.image_id: d.reason or "target not found" for d in detections if not d.found}
    if not found:
        first = "; ".join(f"{k}: {v}" for k, v in list(verdicts.items())[:3])
        raise TooFewPointsError(
            f"the target ({target.get('description', target.get('kind', 'target'))}) was not found in any of the "
            f"{len(detections)} images ({first}{' ...' if len(verdicts) > 3 else ''})")
    (size,) = sizes.keys()
    assumed = pixel_pitch_um is None
    pitch = DEFAULT_PIXEL_PITCH_UM if assumed else pixel_pitch_um
    nominal = {} if focal_mm is None else {"c_mm": float(focal_mm)}
    cam = CameraSetup(camera_name, size, pitch, nominal)
    images = [ImageMeasurements(d.image_id, 0, np.asarray(d.object_ids, int), np.asarray(d.points_px, float)) for d in found]
    meta = {
        "route": "target",
        "target": target,
        "n_images": len(detections),
        "n_detected": len(found),
        "nominal_focal_mm": focal_mm,
        "pixel_pitch_um": list(cam.pixel_pitch_um),
        "pixel_pitch_assumed": assumed,
    }
    return [cam], np.asarray(object_points_m, float), images, verdicts, meta


def calibrate_detections(
    detections: Sequence[Any],
    object_points_m: np.ndarray,
    *,
    target: dict[str, Any],
    pixel_pitch_um: float | tuple[float, float] | None = None,
    focal_mm: float | None = None,
    options: SelfCalibrationOptions | None = None,
    camera_name: str = "camera",
    progress=None,
) -> CalibrationRun:
    """Self-calibration from per-image detections of a planar target (see :func:`prepare_detections`)."""
    cams, pts, images, verdicts, meta = prepare_detections(detections, object_points_m, target=target,
                                                           pixel_pitch_um=pixel_pitch_um, focal_mm=focal_mm,
                                                           camera_name=camera_name)
    res = calibrate(cams, pts, images, options=options, progress=progress)
    from .selfcal import ImageVerdict

    for name, why in verdicts.items():  # images where detection failed get their verdict too
        res.images.append(ImageVerdict(name, 0, False, f"target not detected: {why}"))
    return CalibrationRun(res, meta, verdicts)
