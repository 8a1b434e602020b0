"""Geometry kernels: rotations, poses, DLT, resection, triangulation, Helmert, planes.

Pure vectorised numpy; conventions in ``docs/conventions.md`` (cam_from_world poses,
x right / y down / z forward, OpenCV pixel origin, ω φ κ with M = R_κ R_φ R_ω).
"""

from __future__ import annotations

from . import rotations
from .pose import Pose, project_points

__all__ = ["rotations", "Pose", "project_points"]
