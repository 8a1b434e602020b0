"""Reader for "Bundle Adjustment in the Large" (BAL) problem files, plain or ``.bz2``.

File layout (Agarwal et al. 2010, grail.cs.washington.edu/projects/bal)::

    <num_cameras> <num_points> <num_observations>
    <camera_index> <point_index> <x> <y>          (num_observations lines)
    <camera parameter>                            (9 per camera: rx ry rz tx ty tz f k1 k2)
    <point coordinate>                            (3 per point: X Y Z)

BAL conventions differ from ours (``docs/conventions.md``) and are kept as they are in the
problem object, because the BAL camera model is defined on them:

- the camera looks down **−z**: ``P = R(r) X + t``, ``p = −P[:2] / P[2]``;
- image coordinates have their origin at the principal point and **y up**;
- ``r`` is a Rodrigues (axis-angle) vector in radians; ``R(r) X`` is a rotation of ``X``.

Conversion to a ``cam_from_world`` pose of ours (z forward, y down) is
``R_ours = diag(1, -1, -1) R(r)``, ``t_ours = diag(1, -1, -1) t`` and image coordinates
``(x, y)_ours = (x_bal, -y_bal)`` relative to the principal point; :meth:`BALProblem.to_cv`
performs it.

References
----------
Agarwal, S., Snavely, N., Seitz, S. M., Szeliski, R. (2010). Bundle adjustment in the large.
ECCV 2010, LNCS 6312, 29-42.
"""

from __future__ import annotations

import bz2
import os
from dataclasses import dataclass

import numpy as np

from ..errors import CorruptFileError, DataFileError

__all__ = ["BALProblem", "read_bal"]


@dataclass
class BALProblem:
    """A BAL problem: initial state and observations (BAL conventions, see module docstring).

    Attributes
    ----------
    cameras : (C, 9) float64
        Per camera ``rx ry rz`` (axis-angle, rad), ``tx ty tz``, ``f`` (px), ``k1``, ``k2``.
    points : (N, 3) float64
        Initial 3D points.
    camera_index : (M,) int64
        Camera of each observation.
    point_index : (M,) int64
        Point of each observation.
    observations : (M, 2) float64
        Measured image coordinates (px, origin at the principal point, y up).
    name : str
        File name the problem came from.
    """

    cameras: np.ndarray
    points: np.ndarray
    camera_index: np.ndarray
    point_index: np.ndarray
    observations: np.ndarray
    name: str = ""

    @property
    def num_cameras(self) -> int:
        return int(self.cameras.shape[0])

    @property
    def num_points(self) -> int:
        return int(self.points.shape[0])

    @property
    def num_observations(self) -> int:
        return int(self.observations.shape[0])

    def copy(self) -> "BALProblem":
        return BALProblem(
            self.cameras.copy(),
            self.points.copy(),
            self.camera_index.copy(),
            self.point_index.copy(),
            self.observations.copy(),
            self.name,
        )

    def to_cv(self):
        """Poses and image points in our conventions (camera z forward, y down).

        Returns
        -------
        R : (C, 3, 3) cam_from_world rotations
        t : (C, 3) translations (m, or the problem's unit)
        f, k1, k2 : (C,) focal length (px) and BAL radial coefficients
        xy : (M, 2) image coordinates relative to the principal point, y down (px)
        """
        from ..geometry.rotations import matrix_from_axis_angle

        R = matrix_from_axis_angle(self.cameras[:, :3])
        flip = np.array([1.0, -1.0, -1.0])
        return (
            R * flip[None, :, None],
            self.cameras[:, 3:6] * flip,
            self.cameras[:, 6].copy(),
            self.cameras[:, 7].copy(),
            self.cameras[:, 8].copy(),
            self.observations * np.array([1.0, -1.0]),
        )


def _read_text(path: str) -> str:
    try:
        if path.endswith(".bz2"):
            with bz2.open(path, "rt") as f:
                return f.read()
        with open(path, "rt") as f:
            return f.read()
    except (OSError, EOFError) as exc:
        raise DataFileError(f"{path}: cannot read BAL file: {exc}") from None


def read_bal(path) -> BALProblem:
    """Read a BAL problem file (plain text or ``.bz2``).

    Parameters
    ----------
    path : str or os.PathLike
        File name; ``.bz2`` files are decompressed on the fly.

    Returns
    -------
    BALProblem

    Raises
    ------
    DataFileError
        The file cannot be opened.
    CorruptFileError
        Header missing or not three non-negative integers, wrong number of values, indices out
        of range, or non-finite numbers; the message names the file and what was expected.
    """
    path = os.fspath(path)
    text = _read_text(path)
    head, _, body = text.lstrip().partition("\n")
    parts = head.split()
    try:
        if len(parts) != 3:
            raise ValueError
        nc, npt, nobs = (int(p) for p in parts)
        if min(nc, npt, nobs) < 0:
            raise ValueError
    except ValueError:
        raise CorruptFileError(
            f"{path}: line 1 is {head[:80]!r}; expected a BAL header '<num_cameras> <num_points> <num_observations>'"
        ) from None
    try:
        values = np.array(body.split(), dtype=np.float64)
    except ValueError as exc:
        raise CorruptFileError(f"{path}: non-numeric value in the BAL body ({exc}); expected numbers only") from None
    expected = 4 * nobs + 9 * nc + 3 * npt
    if values.size != expected:
        raise CorruptFileError(
            f"{path}: {values.size} numbers after the header; expected 4*{nobs} + 9*{nc} + 3*{npt} = {expected}"
        )
    if not np.all(np.isfinite(values)):
        k = int(np.argmax(~np.isfinite(values)))
        raise CorruptFileError(f"{path}: non-finite value {values[k]!r} at number {k + 1} after the header")
    obs = values[: 4 * nobs].reshape(nobs, 4)
    cams = values[4 * nobs : 4 * nobs + 9 * nc].reshape(nc, 9).copy()
    pts = values[4 * nobs + 9 * nc :].reshape(npt, 3).copy()
    ci = obs[:, 0].astype(np.int64)
    pi = obs[:, 1].astype(np.int64)
    for name, idx, n, col in (("camera", ci, nc, 0), ("point", pi, npt, 1)):
        bad = (idx < 0) | (idx >= n) | (idx != obs[:, col])
        if np.any(bad):
            k = int(np.argmax(bad))
            raise CorruptFileError(
                f"{path}: observation line {k + 2} has {name} index {obs[k, col]!r}; expected an integer in [0, {n - 1}]"
            )
    return BALProblem(cams, pts, ci, pi, obs[:, 2:4].copy(), name=os.path.basename(path))
