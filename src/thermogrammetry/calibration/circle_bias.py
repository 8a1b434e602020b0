"""Unbiased circle centres: the centroid of an imaged circle is not the image of its centre.

Perspective (conic projection) and lens distortion both move the centroid of the imaged disc away
from the projection of the circle's centre. Given a calibration (camera with distortion, and the
pose of every view), the bias of every circle is computed exactly: the circle's outline is projected
through the full camera model and the area centroid of the projected polygon is compared with the
projection of the centre. Subtracting it from the measured (uncorrected) centroids and calibrating
again, iterated, removes the bias (Heikkilä 2000 for the perspective part; the distortion part is
what a homography-based correction misses under strong distortion).

References
----------
Heikkilä, J. (2000). Geometric camera calibration using circular control points. IEEE TPAMI 22(10),
1066-1077.
Khodaei, B. et al. (2015) (seed 003: mask circle grid calibration of a UAV thermal camera).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..errors import InvalidInputError
from ..targets import circle_centroid_bias  # noqa: F401  (public here too; pure geometry, lives in the lowest layer)
from .selfcal import SelfCalibrationOptions

__all__ = ["circle_centroid_bias", "unbias_circle_detections", "calibrate_circle_grid"]


def _free_parameters(cc) -> dict:
    """{name: [value, std]} of the estimated parameters of a CameraCalibration (for the round history)."""
    return {n: [float(cc.params[i]), float(cc.std[i])] for i, n in enumerate(cc.param_names) if cc.free[i]}


def unbias_circle_detections(detections: Sequence, spec, *, pixel_pitch_um=None, focal_mm=None,
                             options: SelfCalibrationOptions | None = None, iterations: int = 3,
                             camera_name: str = "camera", progress=None):
    """Remove the centroid bias from circle-grid detections, iterated with the calibration.

    ``detections`` must hold the *uncorrected* centroids (``detect_circle_grid(...,
    perspective_correction=False)``). Round 0 subtracts the homography (perspective-only) bias
    (:func:`~thermogrammetry.calibration.detect_circles.ellipse_centre_bias`); each of the
    ``iterations`` rounds calibrates on the corrected centroids, computes :func:`circle_centroid_bias`
    from that camera (with its distortion) and the poses of the views, and subtracts it from the raw
    centroids. The final calibration on the returned detections is the caller's (the CLI runs it as
    its ``selfcal`` pipeline step); :func:`calibrate_circle_grid` does it in memory.

    Parameters
    ----------
    detections : sequence of Detection (raw centroids, px)
    spec : CircleGridSpec with ``diameter_mm``
    pixel_pitch_um, focal_mm, options, camera_name : as :func:`~thermogrammetry.calibration.workflow.calibrate_detections`
    iterations : number of calibrate-then-re-estimate rounds (3: the bias change falls ~25x per round,
        0.25 -> 0.01 -> 0.0003 px on the 24-view strong-barrel set)
    progress : callable(round, iterations), optional

    Returns
    -------
    (detections, history, bias) -- the detections with ``points_px`` = raw - bias (not-found ones
    unchanged); history lists per calibration round its RMS (px), the largest change of the bias (px),
    whether it succeeded and the estimated parameters ``{name: [value, std]}`` (round 0 is the
    homography-corrected calibration); bias maps image id -> (N, 2) px.
    Views a round did not use keep their previous bias (the homography one at worst).
    """
    from dataclasses import replace

    from .detect_circles import _fit_h, ellipse_centre_bias
    from .outputs import camera_from_calibration
    from .workflow import calibrate_detections

    if spec.diameter_mm is None:
        raise InvalidInputError("circle-centre bias: the circle diameter (spec.diameter_mm, --diameter-mm) is needed")
    obj_mm = spec.object_points()
    r_mm = 0.5 * spec.diameter_mm
    raw = {d.image_id: np.asarray(d.points_px, float) for d in detections if d.found}
    ids = {d.image_id: d for d in detections if d.found}
    bias = {}
    for d in detections:
        if d.found:
            H = _fit_h(obj_mm[d.object_ids, :2], raw[d.image_id])
            bias[d.image_id] = ellipse_centre_bias(H, obj_mm[d.object_ids, :2], r_mm)

    def corrected():
        return [replace(d, points_px=raw[d.image_id] - bias[d.image_id]) if d.found else d for d in detections]

    history = []
    for it in range(iterations):
        if progress is not None:
            progress(it, iterations)
        run = calibrate_detections(corrected(), obj_mm * 1e-3, target={"kind": "circles", "bias": "conic+distortion"},
                                   pixel_pitch_um=pixel_pitch_um, focal_mm=focal_mm, options=options,
                                   camera_name=camera_name)
        r = run.result
        if not r.outcome.success or not r.cameras:
            history.append({"round": it, "rms_px": float(r.rms_px), "bias_change_px": None, "success": False})
            break
        cam = camera_from_calibration(r.cameras[0])
        change = 0.0
        for v in r.images:
            if not v.used or v.R is None or v.name not in ids:
                continue
            d = ids[v.name]
            b = circle_centroid_bias(cam, v.R, v.t, obj_mm[d.object_ids] * 1e-3, r_mm * 1e-3)
            change = max(change, float(np.abs(b - bias[v.name]).max()))
            bias[v.name] = b
        history.append({"round": it, "rms_px": float(r.rms_px), "bias_change_px": change, "success": True,
                        "parameters": _free_parameters(r.cameras[0])})
    return corrected(), history, bias


def calibrate_circle_grid(detections: Sequence, spec, *, pixel_pitch_um=None, focal_mm=None,
                          options: SelfCalibrationOptions | None = None, iterations: int = 3, camera_name: str = "camera"):
    """Calibrate from circle-grid detections with the centroid bias removed, iterated.

    :func:`unbias_circle_detections` (``iterations`` rounds), then the final calibration on the
    corrected centroids.

    Returns
    -------
    (CalibrationRun, history, bias) -- history lists per round the RMS (px) and the largest change
    of the bias (px) (the final round's change is None); bias maps image id -> (N, 2) px, the bias
    subtracted in the last round.
    """
    from .workflow import calibrate_detections

    dets, history, bias = unbias_circle_detections(detections, spec, pixel_pitch_um=pixel_pitch_um, focal_mm=focal_mm,
                                                   options=options, iterations=iterations, camera_name=camera_name)
    run = calibrate_detections(dets, spec.object_points() * 1e-3, target={"kind": "circles", "bias": "conic+distortion"},
                               pixel_pitch_um=pixel_pitch_um, focal_mm=focal_mm, options=options, camera_name=camera_name)
    r = run.result
    history.append({"round": len(history), "rms_px": float(r.rms_px), "bias_change_px": None,
                    "success": bool(r.outcome.success),
                    "parameters": _free_parameters(r.cameras[0]) if r.outcome.success and r.cameras else {}})
    return run, history, bias
