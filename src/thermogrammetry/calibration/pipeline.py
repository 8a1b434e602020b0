"""The calibrate workflow as pipeline steps over a project store.

Two steps share nothing in memory (``thermogrammetry.pipeline``):

1. ``observations`` writes ``observations.json``: cameras (image size, pixel pitch, nominal values),
   object points (m), per-image measured points (px, OpenCV convention) and the verdict of every
   image whose target was not detected;
2. ``selfcal`` reads ``observations.json``, runs the staged self-calibration and writes
   ``camera.json``, ``calibration.json``, ``report.html`` and ``exports/``
   (:func:`~thermogrammetry.calibration.outputs.write_outputs`). A failed adjustment raises inside
   the step, so :func:`~thermogrammetry.pipeline.run_steps` reports the step as failed.

``run_steps`` also writes ``reports/<step>.json`` (status, wall time, summary).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from ..errors import CorruptFileError
from ..store import ProjectStore, Step
from .selfcal import CameraSetup, ImageMeasurements, ImageVerdict, SelfCalibrationOptions, calibrate
from .workflow import CalibrationRun

__all__ = ["observations_dict", "calibration_steps", "OBSERVATIONS_KEY"]

OBSERVATIONS_KEY = "observations.json"


def observations_dict(
    cameras: Sequence[CameraSetup],
    points: np.ndarray,
    images: Sequence[ImageMeasurements],
    *,
    point_std: np.ndarray | None = None,
    point_ids: Sequence[str] | None = None,
    not_detected: dict[str, str] | None = None,
    meta: dict[str, Any] | None = None,
    rig: bool = False,
) -> dict[str, Any]:
    """JSON-ready description of a calibration's inputs (see module docstring)."""
    return {
        "format": "thermogrammetry.calibration.observations",
        "version": 1,
        "cameras": [{"name": c.name, "image_size": list(c.image_size), "pixel_pitch_um": list(c.pixel_pitch_um),
                     "nominal": dict(c.nominal)} for c in cameras],
        "points_m": np.asarray(points, float).tolist(),
        "point_std_m": None if point_std is None else np.asarray(point_std, float).tolist(),
        "point_ids": None if point_ids is None else list(point_ids),
        "images": [{"name": im.name, "camera": int(im.camera), "point_index": np.asarray(im.point_index, int).tolist(),
                    "xy_px": np.asarray(im.xy_px, float).tolist(),
                    "sigma_px": None if im.sigma_px is None else np.asarray(im.sigma_px, float).tolist(),
                    "frame": im.frame} for im in images],
        "not_detected": dict(not_detected or {}),
        "rig": bool(rig),
        "meta": dict(meta or {}),
    }


def _from_dict(d: dict, source: str):
    try:
        cams = [CameraSetup(c["name"], tuple(c["image_size"]), tuple(c["pixel_pitch_um"]), dict(c["nominal"])) for c in d["cameras"]]
        pts = np.asarray(d["points_m"], float).reshape(-1, 3)
        pstd = None if d.get("point_std_m") is None else np.asarray(d["point_std_m"], float).reshape(-1, 3)
        ims = [ImageMeasurements(i["name"], int(i["camera"]), np.asarray(i["point_index"], int),
                                 np.asarray(i["xy_px"], float).reshape(-1, 2),
                                 None if i.get("sigma_px") is None else np.asarray(i["sigma_px"], float).reshape(-1, 2),
                                 i.get("frame")) for i in d["images"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise CorruptFileError(f"{source}: not a calibration observations file ({type(exc).__name__}: {exc})") from None
    return cams, pts, pstd, ims


def calibration_steps(observations: dict[str, Any], options: SelfCalibrationOptions | None = None, *,
                      progress=None) -> list[Step]:
    """The two steps of the calibrate workflow (see module docstring)."""
    opt = options or SelfCalibrationOptions()

    def write_obs(project: ProjectStore) -> dict:
        project.write_json(OBSERVATIONS_KEY, observations)
        return {"images": len(observations["images"]), "not_detected": len(observations["not_detected"]),
                "points": len(observations["points_m"])}

    def selfcal(project: ProjectStore) -> dict:
        from .outputs import write_outputs

        d = project.read_json(OBSERVATIONS_KEY)
        cams, pts, pstd, ims = _from_dict(d, project.describe(OBSERVATIONS_KEY))
        res = calibrate(cams, pts, ims, point_std=pstd, options=opt, rig=bool(d.get("rig")), progress=progress)
        for name, why in d.get("not_detected", {}).items():
            res.images.append(ImageVerdict(name, 0, False, f"target not detected: {why}"))
        meta = dict(d.get("meta", {}))
        if d.get("point_ids"):
            meta["point_ids"] = d["point_ids"]
        run = CalibrationRun(res, meta, dict(d.get("not_detected", {})))
        if not res.outcome.success or not res.cameras:
            raise RuntimeError(f"self-calibration failed: {res.outcome.termination.value}: {res.outcome.reason}")
        summary = write_outputs(project, run)
        return {"rms_px": res.rms_px, "sigma0": res.sigma0, "images_used": len(res.images_used),
                "images_rejected": len(res.images_rejected), "exports": summary["exports"]}

    return [Step("observations", write_obs, "measured image points and target description"),
            Step("selfcal", selfcal, "staged self-calibration, outputs and report")]
