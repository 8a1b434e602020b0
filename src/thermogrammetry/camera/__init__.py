"""Camera models: pinhole, forward Brown-Conrady (OpenCV) and correction form (photogrammetric).

Pure vectorised functions with analytic Jacobians live in :mod:`.models`; the thin
:class:`Camera` class composes them; :func:`convert_camera` fits one form to another.
Conventions (pixel origin, frames, formulas): ``docs/conventions.md``.
"""

from __future__ import annotations

from .camera import Camera
from .models import PARAM_NAMES, PARAM_UNITS, CameraModel

__all__ = ["Camera", "CameraModel", "PARAM_NAMES", "PARAM_UNITS", "convert_camera", "CameraConversion"]


def __getattr__(name):  # lazy: the conversion imports scipy
    if name in ("convert_camera", "CameraConversion"):
        from . import convert

        return getattr(convert, name)
    raise AttributeError(f"module 'thermogrammetry.camera' has no attribute {name!r}")
