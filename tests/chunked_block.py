"""A small synthetic survey block for the chunked normal equations (tests/test_adjustment_chunked.py).

Nadir grid of frames over rolling ground, one shared camera with free intrinsics (a second camera
for two frames), GNSS priors on the centres, weighted control points, a plane of points, a scale bar,
gross errors on a few image points (for the robust loss). Deterministic (seeded).
"""

from __future__ import annotations

import numpy as np

from thermogrammetry import Camera
from thermogrammetry.adjustment import BundleProblem
from thermogrammetry.geometry.rotations import matrix_from_axis_angle


def build_block(n_lines=4, per_line=6, n_points=500, seed=3, gauge="control", outliers=8, rig=False, plane=True,
                datum=True):
    """Returns (problem, truth) with truth = dict(C=(F, 3) centres, P=(N, 3) points, camera=Camera).

    ``datum=False`` leaves out the GNSS priors, the control points and the scale bar (a datum defect of 7 with
    the gauge ``"control"``)."""
    rng = np.random.default_rng(seed)
    cam = Camera("opencv", (640, 512), dict(fx=758.0, fy=758.0, cx=319.5, cy=255.5, k1=-0.1, k2=0.05))
    cam2 = Camera("opencv", (640, 512), dict(fx=700.0, fy=700.0, cx=320.0, cy=256.0))
    H = 75.0
    foot_x, foot_y = 640 / 758 * H, 512 / 758 * H
    C = np.array([[li * 0.4 * foot_x, k * 0.2 * foot_y, H] for li in range(n_lines) for k in range(per_line)])
    C[:, 2] += rng.normal(0, 1.0, len(C))
    R0 = np.diag([1.0, -1.0, -1.0])
    Rs = np.array([matrix_from_axis_angle(rng.normal(0, 0.02, 3)) @ R0 for _ in C])
    P = np.column_stack([rng.uniform(-foot_x / 3, C[:, 0].max() + foot_x / 3, n_points),
                         rng.uniform(-foot_y / 3, C[:, 1].max() + foot_y / 3, n_points),
                         rng.normal(0, 2.0, n_points)])
    n_plane = 12
    P[:n_plane, 2] = 0.05 * P[:n_plane, 0] + 1.0  # points on a tilted plane
    pb = BundleProblem(gauge=gauge)
    c1 = pb.add_camera(cam.with_params(cam.params * (1 + rng.normal(0, 2e-3, len(cam.params)))), fixed=["skew", "k3", "k4", "k5", "k6"])
    c2 = pb.add_camera(cam2, fixed=["skew", "k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2"])
    views = []
    for k in range(len(C)):
        Rn = matrix_from_axis_angle(rng.normal(0, 3e-3, 3)) @ Rs[k]
        views.append(pb.add_pose((Rn, -Rn @ (C[k] + rng.normal(0, 0.3, 3)))))
    pidx = pb.add_points(P + rng.normal(0, 0.3, P.shape))
    seen = np.zeros(len(P), int)
    obs = []
    for k in range(len(C)):
        camk = cam2 if k in (1, len(C) - 2) else cam
        Xc = P @ Rs[k].T - Rs[k] @ C[k]
        xy = camk.project(Xc)
        ok = (Xc[:, 2] > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < 640) & (xy[:, 1] >= 0) & (xy[:, 1] < 512)
        i = np.nonzero(ok)[0]
        obs.append((k, c2 if camk is cam2 else c1, i, xy[i] + rng.normal(0, 0.3, (len(i), 2))))
        seen[i] += 1
    nbad = 0
    for k, ci, i, xy in obs:
        keep = seen[i] >= 2
        i, xy = i[keep], xy[keep]
        if nbad < outliers and len(i) > 10:
            xy[3] += 25.0  # gross error
            nbad += 1
        pb.add_image_points(ci, views[k], pidx[i], xy, sigma_px=0.3)
    if rig:  # a second sensor on a rig (5 cm to the right, slightly turned) seen from a few frames
        R_rel = matrix_from_axis_angle(np.array([0.0, 0.01, 0.0]))
        t_rel = -R_rel @ np.array([0.05, 0.0, 0.0])
        ir = pb.add_rig((matrix_from_axis_angle(np.array([0.0, 0.0, 0.002])) @ R_rel, t_rel + 0.01))
        for k in range(0, len(C), 4):
            Rk = R_rel @ Rs[k]
            Xc = P @ Rk.T + R_rel @ (-Rs[k] @ C[k]) + t_rel
            xy = cam2.project(Xc)
            i = np.nonzero((Xc[:, 2] > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < 640) & (xy[:, 1] >= 0) & (xy[:, 1] < 512) & (seen >= 2))[0]
            pb.add_image_points(c2, pb.add_rig_view(ir, views[k]), pidx[i], xy[i] + rng.normal(0, 0.3, (len(i), 2)), sigma_px=0.3)
    pb.set_points_fixed(np.nonzero(seen < 2)[0])
    if not datum:
        return pb, dict(C=C, P=P, camera=cam)
    pb.add_gnss(np.arange(len(C)), C + rng.normal(0, 0.03, C.shape), 0.03)
    ctrl = np.nonzero(seen >= 3)[0][n_plane: n_plane + 6]
    pb.add_control(ctrl, P[ctrl] + rng.normal(0, 0.01, (len(ctrl), 3)), 0.01)
    if plane:  # a plane of points and a scale bar
        on_plane = np.nonzero(seen[:n_plane] >= 2)[0]
        pb.add_plane(on_plane, 0.02)
        a, b = ctrl[0], ctrl[1]
        pb.add_distance([a], [b], np.linalg.norm(P[a] - P[b]) + rng.normal(0, 0.005), 0.005)
    return pb, dict(C=C, P=P, camera=cam)
