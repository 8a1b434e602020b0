"""SO(3) helpers of the adjustment engine: the names it uses for the one implementation
in :mod:`thermogrammetry.geometry.rotations` (Rodrigues, same convention as ``cv2.Rodrigues``).
"""

from __future__ import annotations

from ..geometry.rotations import axis_angle_from_matrix as axis_angles
from ..geometry.rotations import matrix_from_axis_angle as rotation_matrices
from ..geometry.rotations import skew

__all__ = ["rotation_matrices", "axis_angles", "skew"]
