"""What fixes a block's datum, and what it was placed on: the control inputs of georeferencing as values.

:class:`ControlInputs` holds, per image index of the block, the GNSS positions and their σ, the lever
arm, the GCPs and check points with their image measurements, and the camera attitudes; :class:`Datum`
(:class:`DatumSource`) says what a block's start (:func:`~thermogrammetry.sfm.georef_datum.similarity_start`)
was placed on. No readers here: the survey fills them from its inputs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..enums import StrChoice

__all__ = ["ControlInputs", "DatumSource", "Datum"]


@dataclass
class ControlInputs:
    """What fixes the datum, per image index of the block.

    Attributes
    ----------
    gnss_xyz : (n, 3) m in the CRS, NaN rows where an image has none
    gnss_sigma : (n, 3) m
    lever_arm_m : (3,) antenna offset in the camera frame
    gcp_ids : list of str; gcp_xyz (G, 3); gcp_sigma (G, 3)
    gcp_obs : list of (image index, gcp index, (2,) xy px, sigma px)
    check_ids, check_xyz, check_obs : the same for check points (never adjusted)
    attitude : (n, 3, 3) cam_from_world rotations in the CRS observed by the camera's gimbal/IMU (NaN where an image has
        none; :mod:`.attitude`), or None. Used only for a block whose GNSS positions lie on one straight line or
        otherwise leave its rotation undetermined (:func:`similarity_start`).
    """

    gnss_xyz: np.ndarray
    gnss_sigma: np.ndarray
    lever_arm_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gcp_ids: list = field(default_factory=list)
    gcp_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    gcp_sigma: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    gcp_obs: list = field(default_factory=list)
    check_ids: list = field(default_factory=list)
    check_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    check_obs: list = field(default_factory=list)
    attitude: np.ndarray | None = None


class DatumSource(StrChoice):
    """What placed a block in the CRS (:class:`Datum`)."""

    GNSS = "gnss"
    GNSS_ATTITUDE = "gnss+attitude"
    GCPS = "gcps"
    NONE = "none"


@dataclass(frozen=True)
class Datum:
    """What a block's start (:func:`similarity_start`) was placed on, as a value rather than a sentence.

    Attributes
    ----------
    source : DatumSource
        ``GNSS`` (camera positions), ``GNSS_ATTITUDE`` (positions on one line, the rotation about it from the
        camera attitudes), ``GCPS`` (GCPs triangulated in the model) or ``NONE`` (a local frame of arbitrary scale).
    n_gnss, n_attitude, n_gcps : int
        Images with GNSS, images with an attitude, GCPs used.

    ``str(datum)`` is the sentence written to survey.json (``blocks[].datum``) and the report.
    """

    source: DatumSource
    n_gnss: int = 0
    n_attitude: int = 0
    n_gcps: int = 0

    @property
    def georeferenced(self) -> bool:
        return self.source is not DatumSource.NONE

    @property
    def from_gnss(self) -> bool:
        """Placed on GNSS positions (with or without attitudes)."""
        return self.source in (DatumSource.GNSS, DatumSource.GNSS_ATTITUDE)

    @property
    def from_attitude(self) -> bool:
        """The rotation about the GNSS line comes from the camera attitudes."""
        return self.source is DatumSource.GNSS_ATTITUDE

    def __str__(self) -> str:
        if self.source is DatumSource.GNSS:
            return f"GNSS of {self.n_gnss} images"
        if self.source is DatumSource.GNSS_ATTITUDE:
            return f"GNSS of {self.n_gnss} images + attitude of {self.n_attitude}"
        if self.source is DatumSource.GCPS:
            return f"{self.n_gcps} GCPs"
        return "none"
