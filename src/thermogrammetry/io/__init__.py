"""Readers and writers (R-JPEG, TIFF, CSV, video frames, EXIF/XMP, GeoTIFF, LAS, PLY, OBJ, BAL).

Exports are lazy (module ``__getattr__``) so that importing one reader does not import the
heavy dependencies of the others.
"""

from __future__ import annotations

import importlib

_LAZY = {
    # camera formats (camera engineer)
    "read_colmap_cameras": ".colmap",
    "write_colmap_cameras": ".colmap",
    "read_colmap_images": ".colmap",
    "write_colmap_images": ".colmap",
    "read_colmap_points3d": ".colmap",
    "write_colmap_points3d": ".colmap",
    "read_metashape_calibration": ".metashape",
    "write_metashape_calibration": ".metashape",
    "MetashapeCalibration": ".metashape",
    "read_camera_file": ".camera_file",
    "read_bal": ".bal",
    "BALProblem": ".bal",
    "read_thermal": ".thermal",
    "iter_thermal": ".thermal",
    "ThermalImage": ".thermal",
    "ThermalMetadata": ".thermal",
    "write_temperature_tiff": ".tiff",
}


def __getattr__(name):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'thermogrammetry.io' has no attribute {name!r}")
    return getattr(importlib.import_module(mod, __name__), name)
