"""thermogrammetry: thermal-infrared photogrammetry whose 3D products are still temperatures.

Conventions (frames, pixel origin, rotations, units) are in ``docs/conventions.md``.
"""

from __future__ import annotations

__version__ = "0.1.0"

from .errors import ThermogrammetryError  # noqa: E402

__all__ = ["__version__", "ThermogrammetryError", "Camera"]


def __getattr__(name):  # lazy: keep ``import thermogrammetry`` light for the CLI
    if name == "Camera":
        from .camera import Camera

        return Camera
    raise AttributeError(f"module 'thermogrammetry' has no attribute {name!r}")
