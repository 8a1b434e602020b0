"""What comes out of :func:`~thermogrammetry.adjustment.solver.solve`: :class:`AdjustmentResult`."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..results import Termination
from .problem import BundleProblem

__all__ = ["AdjustmentResult"]


@dataclass
class AdjustmentResult:
    """Outcome of :func:`solve`.

    Attributes
    ----------
    termination, reason : Termination, str
    iterations : int
    initial_cost, final_cost : float
        ``1/2 sum rho(r_i^2)`` of the whitened residuals (``1/2 v^T P v`` without a robust loss).
    problem : BundleProblem
        Copy of the problem at the estimate (cameras carry ``param_std``); usable as the start
        of a further stage.
    sigma0 : float
        A posteriori standard deviation of unit weight.
    redundancy : int
    chi2 : dict
        ``statistic``, ``dof``, ``lower``, ``upper``, ``passed`` of the two-sided chi^2 test.
    param_names : list of str
        Camera-side parameters in covariance order: ``"<camera>.<param>"``,
        ``"<pose>.wx|wy|wz|X0|Y0|Z0"`` (rotation increments in rad, projection centre in m),
        ``"rig<i>.wx..tz"``.
    covariance : (n, n) array (a posteriori) or None
    correlation : (n, n) array or None
        Computed from ``covariance`` at each access (not stored: a second n x n matrix would double the
        memory of the precision step of large blocks).
    std : (n,) array or None
    camera_std : list of (P,) arrays (NaN where fixed)
    pose_std : (n_poses, 6) array
        Rotation (rad; the left increment ``R <- exp([dw]x) R``, i.e. small rotations about the
        camera-frame axes applied after R) and projection-centre ``X0 Y0 Z0`` standard
        deviations (m); NaN for fixed poses.
    point_covariance : (N, 3, 3) or None
        A posteriori, free points only (NaN elsewhere), when requested.
    image_residuals : (K, 2) px, ``measured - computed`` corrections v (0 for rejected)
    image_redundancy : (K, 2)
    image_w : (K, 2) w-test values (NaN for rejected)
    rejected : (K,) bool
    control_residuals : (Kc, 3) m
    gnss_residuals : (Kg, 3) m
    attitude_residuals : (Ka, 3) rad, rotation vectors of ``R_obs R^T`` (observed minus computed, camera frame)
    control_redundancy, control_w, gnss_redundancy, gnss_w : (K, 3)
        Redundancy numbers and w-tests of the control and GNSS observations (blunders in
        coordinates are reported, not rejected automatically).
    warnings : list of str
    precision_reason : str
        Why the standard deviations are NaN ("" when they are determined): redundancy <= 0 (sigma0
        undefined) or a singular normal matrix. They are never reported as 0 in that case.
    """

    termination: Termination
    reason: str
    iterations: int
    initial_cost: float
    final_cost: float
    problem: BundleProblem
    sigma0: float = float("nan")
    redundancy: int = 0
    chi2: dict = field(default_factory=dict)
    param_names: list = field(default_factory=list)
    covariance: np.ndarray | None = None
    std: np.ndarray | None = None
    camera_std: list = field(default_factory=list)
    pose_std: np.ndarray | None = None
    point_covariance: np.ndarray | None = None
    image_residuals: np.ndarray | None = None
    image_redundancy: np.ndarray | None = None
    image_w: np.ndarray | None = None
    rejected: np.ndarray | None = None
    control_residuals: np.ndarray | None = None
    gnss_residuals: np.ndarray | None = None
    attitude_residuals: np.ndarray | None = None
    control_redundancy: np.ndarray | None = None
    control_w: np.ndarray | None = None
    gnss_redundancy: np.ndarray | None = None
    gnss_w: np.ndarray | None = None
    warnings: list = field(default_factory=list)
    time_s: float = 0.0
    precision_reason: str = ""

    @property
    def success(self) -> bool:
        return self.termination.success

    @property
    def correlation(self) -> np.ndarray | None:
        """(n, n) correlation matrix ``cov_ij / (std_i std_j)``, from ``covariance`` (NaN where a std is 0)."""
        if self.covariance is None:
            return None
        std = np.sqrt(np.maximum(np.diag(self.covariance), 0.0))
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = self.covariance / std[:, None]
            corr /= std[None, :]
        return corr

    @property
    def points(self) -> np.ndarray:
        return self.problem.points

    @property
    def cameras(self) -> list:
        return self.problem.cameras

    @property
    def poses(self) -> list:
        return self.problem.poses()
