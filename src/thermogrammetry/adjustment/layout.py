"""Parameter layout of a :class:`~thermogrammetry.adjustment.problem.BundleProblem` for the solver.

:class:`Layout` numbers the free camera-side parameters (intrinsics, poses, rigs, planes and the points
coupled by distance observations; the columns of the reduced system) and the free points (3x3 blocks
eliminated by the Schur complement); :class:`State` holds the parameter values and applies a step
(left rotation increments, plane normals on their tangent plane); :class:`Data` holds the (active)
observations in flat arrays.
"""

from __future__ import annotations

import numpy as np

from ._so3 import rotation_matrices
from .linalg import tangent_basis
from .problem import BundleProblem

__all__ = ["Layout", "State", "Data"]


class Layout:
    def __init__(self, pb: BundleProblem):
        col = 0
        self.cam_cols = []
        names = []
        for i, (cam, fx) in enumerate(zip(pb.cameras, pb.camera_fixed)):
            cc = np.full(len(fx), -1, dtype=np.int64)
            for k in range(len(fx)):
                if not fx[k]:
                    cc[k] = col
                    col += 1
                    names.append(f"{pb.camera_names[i]}.{cam.param_names[k]}")
            self.cam_cols.append(cc)
        self.pose_col = np.full(len(pb.pose_R), -1, dtype=np.int64)
        for p in range(len(pb.pose_R)):
            if not pb.pose_fixed[p]:
                self.pose_col[p] = col
                col += 6
                names += [f"{pb.pose_names[p]}.{a}" for a in ("wx", "wy", "wz", "tx", "ty", "tz")]
        self.rig_col = np.full(len(pb.rig_R), -1, dtype=np.int64)
        for r in range(len(pb.rig_R)):
            if not pb.rig_fixed[r]:
                self.rig_col[r] = col
                col += 6
                names += [f"rig{r}.{a}" for a in ("wx", "wy", "wz", "tx", "ty", "tz")]
        self.plane_col = np.full(len(pb.plane_n), -1, dtype=np.int64)
        for k in range(len(pb.plane_n)):
            if not pb.plane_fixed[k]:
                self.plane_col[k] = col
                col += 3
                names += [f"plane{k}.{a}" for a in ("n1", "n2", "d")]
        # free points in distance observations are coupled: they join the camera side
        da, db, _, _ = pb.distance_observations()
        free = ~pb.point_fixed
        coupled = np.zeros(len(pb.points), dtype=bool)
        coupled[da] = True
        coupled[db] = True
        coupled &= free
        self.cs_points = np.nonzero(coupled)[0]
        self.point_col = np.full(len(pb.points), -1, dtype=np.int64)
        for p in self.cs_points:
            self.point_col[p] = col
            col += 3
            names += [f"point{p}.{a}" for a in ("X", "Y", "Z")]
        self.nc = col
        self.names = names
        free &= ~coupled
        self.free_points = np.nonzero(free)[0]
        self.point_slot = np.full(len(pb.points), -1, dtype=np.int64)
        self.point_slot[self.free_points] = np.arange(len(self.free_points))
        self.npf = len(self.free_points)


class State:
    def __init__(self, pb: BundleProblem):
        self.cam_params = [c.params.copy() for c in pb.cameras]
        self.R = np.array(pb.pose_R).reshape(-1, 3, 3)
        self.t = np.array(pb.pose_t).reshape(-1, 3)
        self.rR = np.array(pb.rig_R).reshape(-1, 3, 3)
        self.rt = np.array(pb.rig_t).reshape(-1, 3)
        self.pn = np.array(pb.plane_n, dtype=float).reshape(-1, 3)
        self.pd = np.array(pb.plane_d, dtype=float).reshape(-1)
        self.X = pb.points.copy()

    def plus(self, lay: Layout, dc: np.ndarray, dp: np.ndarray) -> "State":
        s = object.__new__(State)
        s.cam_params = []
        for p, cc in zip(self.cam_params, lay.cam_cols):
            q = p.copy()
            m = cc >= 0
            q[m] += dc[cc[m]]
            s.cam_params.append(q)
        s.R, s.t = self.R.copy(), self.t.copy()
        fp = np.nonzero(lay.pose_col >= 0)[0]
        if len(fp):
            d = dc[lay.pose_col[fp][:, None] + np.arange(6)]
            s.R[fp] = rotation_matrices(d[:, :3]) @ self.R[fp]
            s.t[fp] = self.t[fp] + d[:, 3:]
        s.pn, s.pd = self.pn.copy(), self.pd.copy()
        fpl = np.nonzero(lay.plane_col >= 0)[0]
        for k in fpl:
            c = lay.plane_col[k]
            n = self.pn[k] + tangent_basis(self.pn[k]) @ dc[c : c + 2]
            s.pn[k] = n / np.linalg.norm(n)
            s.pd[k] = self.pd[k] + dc[c + 2]
        s.rR, s.rt = self.rR.copy(), self.rt.copy()
        fr = np.nonzero(lay.rig_col >= 0)[0]
        if len(fr):
            d = dc[lay.rig_col[fr][:, None] + np.arange(6)]
            s.rR[fr] = rotation_matrices(d[:, :3]) @ self.rR[fr]
            s.rt[fr] = self.rt[fr] + d[:, 3:]
        s.X = self.X.copy()
        if lay.npf:
            s.X[lay.free_points] += dp.reshape(-1, 3)
        if len(lay.cs_points):
            s.X[lay.cs_points] += dc[lay.point_col[lay.cs_points][:, None] + np.arange(3)]
        return s

    def write_to(self, pb: BundleProblem) -> None:
        pb.cameras = [c if np.array_equal(c.params, p) else c.with_params(p) for c, p in zip(pb.cameras, self.cam_params)]
        pb.pose_R = [r.copy() for r in self.R]
        pb.pose_t = [t.copy() for t in self.t]
        pb.rig_R = [r.copy() for r in self.rR]
        pb.rig_t = [t.copy() for t in self.rt]
        pb.plane_n = [n.copy() for n in self.pn]
        pb.plane_d = [float(d) for d in self.pd]
        pb.points = self.X.copy()


class Data:
    """Observations (with the active mask for image points) in flat arrays."""

    def __init__(self, pb: BundleProblem, active: np.ndarray):
        img = pb.image_observations()  # (the problem's own concatenated arrays: shared, never written)
        a = np.nonzero(active)[0]
        self.img_idx = a
        uniform_sig = len(a) and not any(img.sigma.strides)  # one sigma for every observation (a broadcast)
        uniform_cam = len(a) and not any(img.camera.strides)
        if len(a) == len(active):  # all active: the problem's arrays themselves (no second copy)
            self.img_idx = slice(None)  # (the same rows as ``a``, without 8 B per observation)
            self.cam, self.view, self.pt, self.xy, self.sig = img.camera, img.view, img.point, img.xy, img.sigma
        else:
            self.cam = np.broadcast_to(img.camera[:1], (len(a),)) if uniform_cam else img.camera[a]
            self.view = img.view[a]
            self.pt = img.point[a]
            self.xy = img.xy[a]
            self.sig = np.broadcast_to(img.sigma[:1], (len(a), 2)) if uniform_sig else img.sigma[a]
        del img
        # int32 (pose and rig counts are far below 2^31); without rig views the pose of a view is the view itself
        # when views and poses are numbered alike, and no view has a rig: no array per observation then
        vp = np.asarray(pb.view_pose, dtype=np.int32)
        vr = np.asarray(pb.view_rig, dtype=np.int32)
        if not len(a):
            self.vpose = self.vrig = np.zeros(0, np.int32)
        else:
            if np.array_equal(vp, np.arange(len(vp))):
                self.vpose = self.view
            else:
                self.vpose = vp[self.view]
            self.vrig = np.broadcast_to(np.int32(-1), (len(a),)) if np.all(vr == -1) else vr[self.view]
        # the view is only needed for vpose/vrig; the camera block is compared per chunk (int32)
        self.view = None
        if not uniform_cam:
            self.cam = self.cam.astype(np.int32, copy=False)
        self.K = len(a)
        del a
        self.c_pt, self.c_xyz, self.c_sig = pb.control_observations()
        self.g_pose, self.g_xyz, self.g_sig, self.g_lever = pb.gnss_observations()
        self.d_a, self.d_b, self.d_len, self.d_sig = pb.distance_observations()
        self.pl_k, self.pl_pt, self.pl_sig = pb.plane_observations()
        self.q_cam, self.q_k, self.q_val, self.q_sig = pb.camera_prior_observations()
        self.a_pose, self.a_R, self.a_sig = pb.attitude_observations()
        # rows: image observations, control, GNSS, planes, distances, camera priors, attitude (the last)
        self.m = (2 * self.K + 3 * len(self.c_pt) + 3 * len(self.g_pose) + len(self.d_a) + len(self.pl_k)
                  + len(self.q_cam) + 3 * len(self.a_pose))
        # the LM's last full-path linearisation (state, r, w, Normal), for the precision step at the same state
        self.linearisation = None
