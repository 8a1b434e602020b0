"""The one least-squares adjustment engine: blocks, observations, weights, solver, precision, blunders.

*What* is estimated is a :class:`BundleProblem` (parameter blocks -- cameras/intrinsics,
poses, rigs, points -- each free, fixed or partly fixed; observations with sigmas; the gauge);
*how* it is solved is :class:`SolverOptions`; :func:`solve` returns an :class:`AdjustmentResult`
(termination and reason, iterations, initial/final cost, sigma0 with its chi^2 test, standard
deviations and correlations, point covariances on request, residuals, redundancy numbers,
w-tests, rejected blunders, warnings). Failures are values, never exceptions; bad input raises.

Self-calibration with a 3D test field (shared intrinsics, many poses, fixed or weighted target
points, staged freeing of parameters)::

    import numpy as np
    from thermogrammetry import Camera
    from thermogrammetry.adjustment import BundleProblem, SolverOptions, solve

    cam = Camera("photogrammetric", (320, 240), dict(c_mm=18.0), pixel_pitch_um=25.0)
    pb = BundleProblem()                                   # gauge "control" (default)
    ic = pb.add_camera(cam, fixed=["K1", "K2", "K3", "K4", "K5", "P1", "P2", "B1", "B2"])
    targets = pb.add_points(field_xyz_m, fixed=True)       # error-free control, (N, 3) m
    # or: targets = pb.add_points(field_xyz_m); pb.add_control(targets, field_xyz_m, sigma_m=0.001)
    for pose, (idx, xy) in zip(initial_poses, measurements):   # pose: geometry.Pose (cam_from_world)
        v = pb.add_pose(pose)
        pb.add_image_points(ic, v, targets[idx], xy, sigma_px=0.3)
    res = solve(pb)                                         # stage 1: c, x0, y0 + poses
    # (no data snooping while the model lacks the distortion: it would reject good points)
    pb2 = res.problem                                       # estimate as the next start
    pb2.free_camera_params(ic, ["K1", "K2", "K3", "P1", "P2"])   # stage 2: distortion
    res = solve(pb2, SolverOptions(data_snooping=True))
    res.termination, res.sigma0, res.chi2["passed"]
    res.cameras[ic].params, res.camera_std[ic]              # estimates and a-posteriori sigmas
    res.param_names, res.correlation, res.warnings          # |rho| > 0.9, insignificant APs
    res.pose_std                                            # (n_poses, 6): rotation rad, X0 Y0 Z0 m
    res.image_residuals, res.image_redundancy, res.image_w, res.rejected

Other blocks and observations: ``pb.add_rig(relative_pose)`` + ``pb.add_rig_view(rig,
master_view)`` (constant relative orientation, seed 002 eq. 4-5), ``pb.add_gnss(views, xyz,
sigma_m, lever_arm_m)``, ``pb.add_distance(a, b, distance_m, sigma_m)`` (scale bars),
``pb.add_plane(points, sigma_m)`` (points on a common, estimated plane),
``BundleProblem(gauge="inner")`` for a free network (inner constraints on the free points),
``SolverOptions(loss="huber", loss_scale=3)`` for robust estimation,
``SolverOptions(compute_point_covariance=True)``.

BAL problems (Bundle Adjustment in the Large) have a dedicated fast path:
``solve_bal(thermogrammetry.io.read_bal(path))`` -> ``.initial_cost``, ``.final_cost``,
``.iterations``, ``.termination`` (see :mod:`thermogrammetry.adjustment.bal`).

``thermogrammetry.adjustment.dense`` (owned by the geometry kernels) is the small dense
weighted least-squares kernel for DLT, resection, triangulation and Helmert.
"""

from __future__ import annotations

import importlib

_LAZY = {
    "solve_bal": ".bal",
    "BALResult": ".bal",
    "BALSolverOptions": ".bal",
    "bal_cost": ".bal",
    "BundleProblem": ".problem",
    "Gauge": ".problem",
    "SolverOptions": ".options",
    "AdjustmentResult": ".result",
    "Loss": ".options",
    "solve": ".solver",
}

__all__ = sorted(_LAZY)


def __getattr__(name):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'thermogrammetry.adjustment' has no attribute {name!r}")
    return getattr(importlib.import_module(mod, __name__), name)
