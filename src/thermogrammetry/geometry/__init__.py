"""Geometry kernels: rotations, poses, DLT, resection, triangulation, Helmert, planes.

Pure vectorised numpy; conventions in ``docs/conventions.md`` (cam_from_world poses,
x right / y down / z forward, OpenCV pixel origin, ω φ κ with M = R_κ R_φ R_ω).
Every estimator returns a result object with an :class:`~thermogrammetry.results.Outcome`
and its precision; bad input raises from :mod:`thermogrammetry.errors`.

Name shadowing (kept on purpose: other code calls these public names)
-------------------------------------------------------------------
The functions :func:`dlt` and :func:`resection` are re-exported here under the same names as
their submodules ``geometry/dlt.py`` and ``geometry/resection.py``, so after import the package
attributes ``thermogrammetry.geometry.dlt`` / ``.resection`` are the *functions*, not the
modules. Consequences:

- ``from thermogrammetry.geometry import dlt`` and even
  ``import thermogrammetry.geometry.dlt as m`` give the function;
- to reach anything else in those modules use ``from thermogrammetry.geometry.dlt import
  DLTResult`` (``from package.module import name`` resolves the module through
  ``sys.modules``), or ``importlib.import_module("thermogrammetry.geometry.dlt")`` for the
  module object.
"""

from __future__ import annotations

from . import rotations
from .pose import Pose, project_points
from .dlt import DLTResult, decompose_projection, dlt, dlt_linear
from .resection import ResectionResult, resection
from .triangulation import TriangulationResult, triangulate, triangulate_linear
from .helmert import HelmertResult, Similarity, helmert, umeyama
from .planes import (
    Plane,
    angle_to_camera_axis,
    distance_along_axis,
    distance_along_rays,
    plane_from_3_points,
    plane_from_points,
    ray_angles,
)

__all__ = [
    "rotations",
    "Pose",
    "project_points",
    "DLTResult",
    "dlt",
    "dlt_linear",
    "decompose_projection",
    "ResectionResult",
    "resection",
    "TriangulationResult",
    "triangulate",
    "triangulate_linear",
    "HelmertResult",
    "Similarity",
    "helmert",
    "umeyama",
    "Plane",
    "plane_from_3_points",
    "plane_from_points",
    "angle_to_camera_axis",
    "ray_angles",
    "distance_along_axis",
    "distance_along_rays",
]
