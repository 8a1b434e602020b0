"""Camera calibration: target detection, 3D test fields, staged self-calibration, reports.

Public entry points (imported lazily so that ``import thermogrammetry.calibration`` stays light):

- :func:`calibrate` / :class:`SelfCalibrationOptions` / :class:`CameraSetup` /
  :class:`ImageMeasurements` — staged self-calibrating bundle adjustment (seed 001 strategy), in
  :mod:`thermogrammetry.calibration.selfcal`;
- the 3D test-field CSV formats (control points, image measurements) are read by
  :mod:`thermogrammetry.io.testfield_csv`;
- :func:`prepare_testfield` / :func:`prepare_detections` (checks and inputs) and
  :func:`calibrate_testfield` / :func:`calibrate_detections`, in :mod:`thermogrammetry.calibration.workflow`;
- :func:`calibration_steps` — the calibrate workflow as pipeline steps, in
  :mod:`thermogrammetry.calibration.pipeline`;
- :func:`write_outputs` — camera.json, calibration.json, report.html and exports into a project
  store, in :mod:`thermogrammetry.calibration.outputs`;
- target detection (``detect*.py``) is written by the detection engineer.
"""

from __future__ import annotations

_LAZY = {
    "calibrate": "selfcal",
    "SelfCalibrationOptions": "selfcal",
    "CameraSetup": "selfcal",
    "ImageMeasurements": "selfcal",
    "CalibrationResult": "selfcal",
    "CameraCalibration": "selfcal",
    "write_outputs": "outputs",
    "prepare_testfield": "workflow",
    "prepare_detections": "workflow",
    "calibrate_testfield": "workflow",
    "calibrate_detections": "workflow",
    "calibration_steps": "pipeline",
    "observations_dict": "pipeline",
}

__all__ = sorted(_LAZY)


def __getattr__(name):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'thermogrammetry.calibration' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f"{__name__}.{mod}"), name)
