"""What is estimated: parameter blocks, observations, weights and the datum (gauge).

A :class:`BundleProblem` collects

- **cameras** (intrinsics, one block per sensor, shared by all its images) -- any
  :class:`thermogrammetry.Camera`; every parameter free, fixed, or a named subset fixed;
- **poses** (``cam_from_world``, updated on the rotation manifold ``R <- exp([dw]x) R``,
  ``t <- t + dt``), free or fixed;
- **rigs** (constant relative orientation between two cameras across frames, seed 002
  eq. 4-5): a rig block ``(R_rel, t_rel)`` and *derived* views ``R_s = R_rel R_m``,
  ``t_s = R_rel t_m + t_rel`` of a master pose. Seed 002 writes eq. 4 as ``R* = R_RGB^T R_IR``;
  that product is constant only when ``R`` denotes the world_from_camera rotation (``R^T`` in
  our ``cam_from_world`` terms; with photo_from_world matrices it would change with the rig's
  attitude), and then ``R* = R_m R_s^T = R_rel^T``. Eq. 5, ``X0_IR = R_RGB t + X0_RGB`` with the
  same world_from_camera ``R_RGB``, is ``C_s = C_m + R_m^T b`` with a constant base vector ``b``
  in the master camera frame, i.e. ``t_rel = -R_rel b``. (The seed's text is garbled here; this
  follows the standard rigid-rig formulation.)
- **points** (3D, metres), free or fixed;
- **observations**: image points (px) with sigma per observation, per axis or per sensor;
  control-point coordinates (weighted, sigma in m); GNSS camera-centre priors with a lever arm
  (antenna offset in the camera frame, m); pose priors are GNSS priors with zero lever arm;
  attitude priors (an observed ``cam_from_world`` rotation per view, e.g. a gimbal's IMU attitude,
  residual ``log(R R_obs^T)`` in the camera frame, sigma in radians per axis);
  distances between points (scale bars); points on a common plane (a plane block: unit normal
  with 2 degrees of freedom and offset, estimated or fixed).

The **gauge** (datum) is either given by control/fixed parameters/priors
(``Gauge.CONTROL``) or by inner constraints on the free points (``Gauge.INNER``, free network:
minimum trace of the point covariance; Granshaw 1980).

The problem is solved by :func:`thermogrammetry.adjustment.solve` with
:class:`thermogrammetry.adjustment.SolverOptions` (how it is solved).

References
----------
Granshaw, S. I. (1980). Bundle adjustment methods in engineering photogrammetry.
Photogrammetric Record 10(56), 181-207.
Barazzetti, L. et al. (2013). Mosaicking thermal images of buildings. Proc. SPIE 8783 (seed 002).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from .._validate import as_array, as_points
from ..enums import StrChoice
from ..errors import ConfigError, InvalidInputError, ShapeError

__all__ = ["Gauge", "BundleProblem"]


class Gauge(StrChoice):
    """How the datum is defined."""

    CONTROL = "control"  # control points, fixed parameters and/or GNSS priors define it
    INNER = "inner"  # free network: inner constraints (minimum trace) on the free points


def _check_rotation(R, name):
    R = as_array(R, name, shape=(3, 3))
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InvalidInputError(f"{name}: not a proper rotation matrix (R R^T = I, det R = +1 expected)")
    return R


def _pose_arrays(pose, name):
    """Accept a geometry.Pose, an (R, t) tuple or a (3, 4) [R | t] matrix."""
    if hasattr(pose, "R") and hasattr(pose, "t"):
        R, t = pose.R, pose.t
    elif isinstance(pose, (tuple, list)) and len(pose) == 2:
        R, t = pose
    else:
        arr = np.asarray(pose, dtype=float)
        if arr.shape != (3, 4):
            raise ShapeError(f"{name}: expected a Pose, an (R, t) pair or a (3, 4) [R|t] matrix, got {arr.shape}")
        R, t = arr[:, :3], arr[:, 3]
    return _check_rotation(R, f"{name}.R").copy(), as_array(t, f"{name}.t", shape=(3,)).copy()


def _sigma(sigma, n, k, name):
    """Broadcast sigma to (n, k): scalar, (n,), (k,) for per-axis or (n, k)."""
    s = np.asarray(sigma, dtype=float)
    if s.ndim == 0:
        s = np.full((n, k), float(s))
    elif s.shape == (n,):
        s = np.repeat(s[:, None], k, axis=1)
    elif s.shape == (k,) and n != k:
        s = np.broadcast_to(s, (n, k)).copy()
    elif s.shape == (n, k):
        s = s.copy()
    else:
        raise ShapeError(f"{name}: expected a scalar, shape ({n},), ({k},) or ({n}, {k}); got {s.shape}")
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise InvalidInputError(f"{name}: standard deviations must be finite and > 0, got min {s.min()!r}")
    return s


@dataclass
class _ImageObs:
    camera: np.ndarray  # (K,) camera block
    view: np.ndarray  # (K,) view index
    point: np.ndarray  # (K,) point index
    xy: np.ndarray  # (K, 2) px
    sigma: np.ndarray  # (K, 2) px
    compact: bool = False  # the concatenated form of :meth:`BundleProblem.image_observations`


def _uniform(parts, field):
    """The common value of ``field`` when every part holds it as a broadcast of one value (stride 0), else None."""
    val = None
    for o in parts:
        a = getattr(o, field)
        if len(a) == 0:
            continue
        if any(s != 0 for s in a.strides):
            return None
        v = a.reshape(-1)[:1] if a.ndim == 1 else a[0]
        if val is None:
            val = v
        elif not np.array_equal(v, val):
            return None
    return val


def _concat_obs(parts: list, index_dtype) -> _ImageObs:
    """One :class:`_ImageObs` from the per-call ones, in their order (values unchanged): indices in
    ``index_dtype``, and camera block / sigma as read-only broadcasts when one value holds for every
    observation (a single camera, one sigma for all: 0 B per observation instead of 4 and 16)."""
    K = sum(len(o.point) for o in parts)
    cam0, sig0 = _uniform(parts, "camera"), _uniform(parts, "sigma")
    camera = np.broadcast_to(np.asarray(cam0, dtype=index_dtype).reshape(()), (K,)) if cam0 is not None and K else None
    sigma = np.broadcast_to(np.asarray(sig0, dtype=float).reshape(2), (K, 2)) if sig0 is not None and K else None
    out = {f: np.empty(K, index_dtype) for f in ("camera", "view", "point") if not (f == "camera" and camera is not None)}
    out["xy"] = np.empty((K, 2))
    if sigma is None:
        out["sigma"] = np.empty((K, 2))
    a = 0
    for o in parts:
        b = a + len(o.point)
        for f, arr in out.items():
            arr[a:b] = getattr(o, f)
        a = b
    for arr in out.values():
        arr.flags.writeable = False  # (shared with the solver's working copy and its data: never written)
    if camera is not None:
        out["camera"] = camera
    if sigma is not None:
        out["sigma"] = sigma
    return _ImageObs(out["camera"], out["view"], out["point"], out["xy"], out["sigma"], compact=True)


class BundleProblem:
    """The description of an adjustment: blocks, observations, weights, gauge.

    All ``add_*`` methods return indices that later calls refer to. Shapes and units:
    image coordinates in px (OpenCV convention), object coordinates and sigmas in metres,
    poses ``cam_from_world``.

    Parameters
    ----------
    gauge : Gauge or str
        ``"control"`` (default) or ``"inner"`` (free network).
    """

    def __init__(self, gauge: Gauge | str = Gauge.CONTROL):
        self.gauge = Gauge(gauge)
        self.cameras: list = []
        self.camera_fixed: list[np.ndarray] = []  # bool mask per camera parameter
        self.camera_names: list[str] = []
        self.pose_R: list[np.ndarray] = []
        self.pose_t: list[np.ndarray] = []
        self.pose_fixed: list[bool] = []
        self.pose_names: list[str] = []
        self.rig_R: list[np.ndarray] = []
        self.rig_t: list[np.ndarray] = []
        self.rig_fixed: list[bool] = []
        # views: (pose index, rig index or -1); a plain pose has a view of its own
        self.view_pose: list[int] = []
        self.view_rig: list[int] = []
        self.points = np.zeros((0, 3))
        self.point_fixed = np.zeros(0, dtype=bool)
        self._img: list[_ImageObs] = []
        self._ctrl: list[tuple] = []  # (point idx (K,), xyz (K,3), sigma (K,3))
        self._gnss: list[tuple] = []  # (pose idx (K,), xyz (K,3), sigma (K,3), lever (K,3))
        self._dist: list[tuple] = []  # (point a (K,), point b (K,), distance (K,), sigma (K,))
        self._att: list[tuple] = []  # (pose idx (K,), R_obs (K,3,3) cam_from_world, sigma (K,3) rad)
        self._cprior: list[tuple] = []  # (camera (K,), parameter index (K,), value (K,), sigma (K,))
        self.plane_n: list[np.ndarray] = []  # unit normals
        self.plane_d: list[float] = []  # offsets: n . X = d (m)
        self.plane_fixed: list[bool] = []
        self._plane_obs: list[tuple] = []  # (plane (K,), point (K,), sigma (K,))

    # ---------------------------------------------------------------- blocks
    def add_camera(self, camera, *, fixed=False, name: str | None = None) -> int:
        """Add an intrinsics block.

        Parameters
        ----------
        camera : thermogrammetry.Camera
        fixed : bool or sequence of parameter names
            ``True`` fixes all, ``False`` frees all, a list of names (e.g. ``["K3", "B1", "B2"]``)
            fixes only those (the rest is free).
        name : str, optional
            Used in parameter names of the result (``"<name>.<param>"``); default ``camera.name``
            or ``"camera<i>"``.
        """
        if not hasattr(camera, "project_jacobian") or not hasattr(camera, "param_names"):
            raise InvalidInputError(f"camera: expected a thermogrammetry.Camera, got {type(camera).__name__}")
        i = len(self.cameras)
        self.cameras.append(camera)
        self.camera_fixed.append(np.zeros(len(camera.param_names), dtype=bool))
        self.camera_names.append(name or getattr(camera, "name", "") or f"camera{i}")
        self.set_camera_fixed(i, fixed)
        return i

    def set_camera_fixed(self, camera: int, fixed=True) -> None:
        """Fix (``True``), free (``False``) or fix exactly the named parameters of a camera."""
        cam = self.cameras[self._check_index(camera, len(self.cameras), "camera")]
        names = tuple(cam.param_names)
        if fixed is True or fixed is False:
            self.camera_fixed[camera] = np.full(len(names), bool(fixed))
            return
        if isinstance(fixed, str):
            fixed = [fixed]
        mask = np.zeros(len(names), dtype=bool)
        lower = {n.lower(): k for k, n in enumerate(names)}
        for n in fixed:
            k = lower.get(str(n).lower())
            if k is None:
                raise ConfigError(f"camera {camera}: unknown parameter {n!r}; expected one of {', '.join(names)}")
            mask[k] = True
        self.camera_fixed[camera] = mask

    def free_camera_params(self, camera: int, names) -> None:
        """Free the named parameters (keeping the others as they are) -- staged self-calibration."""
        cam = self.cameras[self._check_index(camera, len(self.cameras), "camera")]
        lower = {n.lower(): k for k, n in enumerate(cam.param_names)}
        for n in [names] if isinstance(names, str) else names:
            k = lower.get(str(n).lower())
            if k is None:
                raise ConfigError(f"camera {camera}: unknown parameter {n!r}; expected one of {', '.join(cam.param_names)}")
            self.camera_fixed[camera][k] = False

    def add_pose(self, pose, *, fixed: bool = False, name: str | None = None) -> int:
        """Add a ``cam_from_world`` pose (``Pose``, ``(R, t)`` or ``[R|t]``); returns its view index."""
        R, t = _pose_arrays(pose, "pose")
        self.pose_R.append(R)
        self.pose_t.append(t)
        self.pose_fixed.append(bool(fixed))
        self.pose_names.append(name or f"pose{len(self.pose_R) - 1}")
        self.view_pose.append(len(self.pose_R) - 1)
        self.view_rig.append(-1)
        return len(self.view_pose) - 1

    def add_rig(self, relative_pose, *, fixed: bool = False) -> int:
        """Add a rig block: the constant ``slave_from_master`` transform ``(R_rel, t_rel)``."""
        R, t = _pose_arrays(relative_pose, "relative_pose")
        self.rig_R.append(R)
        self.rig_t.append(t)
        self.rig_fixed.append(bool(fixed))
        return len(self.rig_R) - 1

    def add_rig_view(self, rig: int, master_view: int) -> int:
        """A view of the rig's second camera, derived from a master view (a plain pose).

        Returns a view index usable in :meth:`add_image_points`.
        """
        self._check_index(rig, len(self.rig_R), "rig")
        self._check_index(master_view, len(self.view_pose), "master_view")
        if self.view_rig[master_view] != -1:
            raise InvalidInputError(f"master_view {master_view} is itself a rig view; expected a plain pose view")
        self.view_pose.append(self.view_pose[master_view])
        self.view_rig.append(rig)
        return len(self.view_pose) - 1

    def add_points(self, points_world, *, fixed: bool = False) -> np.ndarray:
        """Add 3D points (N, 3) in metres; returns their indices (N,)."""
        pts = as_points(points_world, "points_world", 3)
        start = len(self.points)
        self.points = np.concatenate([self.points, pts])
        self.point_fixed = np.concatenate([self.point_fixed, np.full(len(pts), bool(fixed))])
        return np.arange(start, start + len(pts))

    def set_points_fixed(self, indices, fixed: bool = True) -> None:
        idx = self._check_indices(indices, len(self.points), "indices")
        self.point_fixed[idx] = bool(fixed)

    # ---------------------------------------------------------------- observations
    def add_image_points(self, camera: int, view: int, points, xy_px, sigma_px=1.0) -> None:
        """Image measurements of points in one view.

        Parameters
        ----------
        camera : int
            Camera (intrinsics) block.
        view : int
            View from :meth:`add_pose` or :meth:`add_rig_view`.
        points : (K,) int
            Point indices.
        xy_px : (K, 2) float
            Measured pixel coordinates (OpenCV convention).
        sigma_px : float, (K,), (2,) or (K, 2)
            Standard deviation of the measurements (px).
        """
        self._check_index(camera, len(self.cameras), "camera")
        self._check_index(view, len(self.view_pose), "view")
        idx = self._check_indices(points, len(self.points), "points")
        xy = as_points(xy_px, "xy_px", 2)
        if len(xy) != len(idx):
            raise ShapeError(f"xy_px: {len(xy)} rows for {len(idx)} point indices; expected equal counts")
        k = len(idx)
        s0 = np.asarray(sigma_px, dtype=float)
        if s0.ndim == 0 and np.isfinite(s0) and s0 > 0:
            # one sigma for the call: a read-only broadcast (no 16 B per observation; nothing writes to it)
            sig = np.broadcast_to(s0, (k, 2))
        else:
            sig = _sigma(sigma_px, k, 2, "sigma_px")
        # camera and view are constant per call: read-only broadcasts too (the solver concatenates)
        self._img.append(_ImageObs(np.broadcast_to(np.int64(camera), (k,)), np.broadcast_to(np.int64(view), (k,)), idx,
                                   xy, sig))

    def add_control(self, points, xyz, sigma_m) -> None:
        """Weighted control: observed coordinates (K, 3) of points with sigma (m, scalar/(K,)/(3,)/(K,3)).

        For error-free control use ``add_points(..., fixed=True)`` instead.
        """
        idx = self._check_indices(points, len(self.points), "points")
        xyz = as_points(xyz, "xyz", 3)
        if len(xyz) != len(idx):
            raise ShapeError(f"xyz: {len(xyz)} rows for {len(idx)} point indices; expected equal counts")
        self._ctrl.append((idx, xyz, _sigma(sigma_m, len(idx), 3, "sigma_m")))

    def add_gnss(self, views, antenna_xyz, sigma_m, lever_arm_m=(0.0, 0.0, 0.0)) -> None:
        """GNSS antenna positions observed for views (K,): ``C + R^T lever_arm = antenna``.

        Parameters
        ----------
        views : (K,) int
            Plain pose views.
        antenna_xyz : (K, 3) m
        sigma_m : float, (K,), (3,) or (K, 3)
        lever_arm_m : (3,) or (K, 3)
            Antenna offset from the projection centre in the camera frame (x right, y down, z
            forward), metres.
        """
        v = self._check_indices(views, len(self.view_pose), "views")
        if np.any(np.asarray(self.view_rig)[v] != -1):
            raise InvalidInputError("views: GNSS priors are supported on plain pose views, not rig views")
        poses = np.asarray(self.view_pose)[v]
        xyz = as_points(antenna_xyz, "antenna_xyz", 3)
        if len(xyz) != len(v):
            raise ShapeError(f"antenna_xyz: {len(xyz)} rows for {len(v)} views; expected equal counts")
        lever = np.broadcast_to(as_array(lever_arm_m, "lever_arm_m"), (len(v), 3)).copy()
        self._gnss.append((poses, xyz, _sigma(sigma_m, len(v), 3, "sigma_m"), lever))

    def add_attitude(self, views, R_cam_from_world, sigma_rad) -> None:
        """Observed rotations of views (K,): priors on the attitude, e.g. from a gimbal's IMU.

        Three residuals per view: the rotation vector of ``R R_obs^T`` (the camera frame, x right, y down,
        z forward) divided by ``sigma_rad``. Its Jacobian with respect to the pose update ``R <- exp([dw]x) R``
        is the inverse left Jacobian of SO(3) at the residual (exact, not the small-angle identity).

        Parameters
        ----------
        views : (K,) int
            Plain pose views.
        R_cam_from_world : (K, 3, 3)
            Observed rotations (orthonormal, det +1).
        sigma_rad : float, (K,), (3,) or (K, 3)
            Standard deviation of each rotation-vector component, radians.
        """
        v = self._check_indices(views, len(self.view_pose), "views")
        if np.any(np.asarray(self.view_rig)[v] != -1):
            raise InvalidInputError("views: attitude priors are supported on plain pose views, not rig views")
        R = np.asarray(R_cam_from_world, dtype=float)
        if R.shape != (len(v), 3, 3):
            raise ShapeError(f"R_cam_from_world: shape {R.shape}; expected ({len(v)}, 3, 3)")
        for k in range(len(v)):
            _check_rotation(R[k], f"R_cam_from_world[{k}]")
        self._att.append((np.asarray(self.view_pose)[v], R.copy(), _sigma(sigma_rad, len(v), 3, "sigma_rad")))

    def add_camera_prior(self, camera: int, values: dict, sigmas: dict) -> None:
        """Weighted priors on intrinsic parameters of camera block ``camera`` (a calibration's values with their
        σ, or a lens's nominal focal length): one residual ``(θ - value) / σ`` per parameter, in the parameter's
        own unit (px for ``fx``, ``fy``, ``cx``, ``cy``; unitless for distortion). A prior on a parameter held
        fixed has no effect on the estimate (its residual is constant).

        Parameters
        ----------
        camera : int
            Camera block index (:meth:`add_camera`).
        values, sigmas : dict
            Parameter name -> prior value, and -> its standard deviation (> 0, finite); the same names in both.
        """
        c = self._check_indices([camera], len(self.cameras), "camera")[0]
        names = list(self.cameras[c].param_names)
        if set(values) != set(sigmas):
            raise InvalidInputError(f"camera prior: values for {sorted(values)} but sigmas for {sorted(sigmas)}; "
                                    "expected the same parameter names")
        unknown = [n for n in values if n not in names]
        if unknown:
            raise InvalidInputError(f"camera prior: {unknown} are not parameters of camera {c} "
                                    f"(model parameters: {', '.join(names)})")
        k = np.array([names.index(n) for n in values], dtype=np.int64)
        v = np.array([float(values[n]) for n in values])
        sg = np.array([float(sigmas[n]) for n in values])
        if not (np.all(np.isfinite(v)) and np.all(np.isfinite(sg)) and np.all(sg > 0)):
            raise InvalidInputError(f"camera prior: values {v.tolist()} and sigmas {sg.tolist()}; expected finite "
                                    "values and finite sigmas > 0")
        self._cprior.append((np.full(len(k), c, dtype=np.int64), k, v, sg))

    def camera_prior_observations(self):
        if not self._cprior:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
        return tuple(np.concatenate([a[j] for a in self._cprior]) for j in range(4))

    def attitude_observations(self):
        if not self._att:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3, 3)), np.zeros((0, 3))
        return tuple(np.concatenate([a[k] for a in self._att]) for k in range(3))

    def add_distance(self, points_a, points_b, distance_m, sigma_m) -> None:
        """Observed distances between pairs of points (scale bars, taped distances), metres.

        Points in distance observations are solved together with the camera-side parameters
        (they are coupled and leave the block-diagonal point system).
        """
        a = self._check_indices(points_a, len(self.points), "points_a")
        b = self._check_indices(points_b, len(self.points), "points_b")
        if len(a) != len(b):
            raise ShapeError(f"points_b: {len(b)} indices for {len(a)} in points_a; expected equal counts")
        if np.any(a == b):
            raise InvalidInputError(f"points_a/points_b: a distance needs two different points, got {int(a[a == b][0])} twice")
        d = np.broadcast_to(as_array(distance_m, "distance_m"), (len(a),)).copy()
        if np.any(d <= 0):
            raise InvalidInputError(f"distance_m: distances must be > 0, got {d.min()!r}")
        sig = _sigma(sigma_m, len(a), 1, "sigma_m")[:, 0]
        self._dist.append((a, b, d, sig))

    def add_plane(self, points, sigma_m, *, normal=None, offset_m=None, fixed: bool = False) -> int:
        """Points lying on a common plane ``n . X = d`` (facades, floors): one condition per point
        with sigma ``sigma_m`` (m, scalar or (K,)) for the point-to-plane distance.

        The plane is a parameter block (unit normal, 2 degrees of freedom, and offset) unless
        ``fixed``; without ``normal``/``offset_m`` it starts as the least-squares plane through
        the current coordinates of the points. Returns the plane index.
        """
        idx = self._check_indices(points, len(self.points), "points")
        if normal is None or offset_m is None:
            if len(idx) < 3:
                raise InvalidInputError(f"points: a plane needs at least 3 points to start from, got {len(idx)}")
            P = self.points[idx]
            c = P.mean(axis=0)
            _, sv, vt = np.linalg.svd(P - c)
            if sv[1] < 1e-9 * max(sv[0], 1e-300):
                raise InvalidInputError("points: collinear points do not define a plane; expected >= 3 non-collinear points")
            n = vt[2]
            d = float(n @ c)
        else:
            n = as_array(normal, "normal", shape=(3,))
            nn = np.linalg.norm(n)
            if nn == 0:
                raise InvalidInputError("normal: zero vector; expected a plane normal")
            n = n / nn
            d = float(offset_m)
        self.plane_n.append(n)
        self.plane_d.append(d)
        self.plane_fixed.append(bool(fixed))
        k = len(self.plane_n) - 1
        sig = _sigma(sigma_m, len(idx), 1, "sigma_m")[:, 0]
        self._plane_obs.append((np.full(len(idx), k), idx, sig))
        return k

    def plane_observations(self):
        if not self._plane_obs:
            z = np.zeros(0, dtype=np.int64)
            return z, z, np.zeros(0)
        return tuple(np.concatenate([g[k] for g in self._plane_obs]) for k in range(3))

    def distance_observations(self):
        if not self._dist:
            z = np.zeros(0, dtype=np.int64)
            return z, z, np.zeros(0), np.zeros(0)
        return tuple(np.concatenate([g[k] for g in self._dist]) for k in range(4))

    # ---------------------------------------------------------------- helpers
    @staticmethod
    def _check_index(i, n, name):
        if not isinstance(i, (int, np.integer)) or not 0 <= int(i) < n:
            raise InvalidInputError(f"{name}: index {i!r} out of range; expected an integer in [0, {n - 1}]")
        return int(i)

    @staticmethod
    def _check_indices(idx, n, name):
        a = np.atleast_1d(np.asarray(idx))
        if a.dtype.kind not in "iu":
            raise InvalidInputError(f"{name}: expected integer indices, got dtype {a.dtype}")
        bad = (a < 0) | (a >= n)
        if np.any(bad):
            raise InvalidInputError(f"{name}: index {a[bad][0]!r} out of range; expected integers in [0, {n - 1}]")
        return a.astype(np.int64)

    def image_observations(self) -> _ImageObs:
        """All image observations concatenated in the order they were added (read-only arrays).

        The concatenation becomes the problem's own storage (the per-call arrays are dropped, later calls
        of :meth:`add_image_points` append to it): the solver shares it instead of holding a second copy.
        Camera, view and point indices are int32 when the blocks fit (int64 otherwise); the camera block and
        sigma are read-only broadcasts when a single value holds for every observation."""
        if not self._img:
            z = np.zeros(0, dtype=np.int64)
            return _ImageObs(z, z, z, np.zeros((0, 2)), np.zeros((0, 2)))
        if len(self._img) > 1 or not self._img[0].compact:
            big = max(len(self.cameras), len(self.view_pose), len(self.points)) >= 2**31 - 1
            self._img = [_concat_obs(self._img, np.int64 if big else np.int32)]
        return self._img[0]

    def control_observations(self):
        if not self._ctrl:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3))
        return tuple(np.concatenate([c[k] for c in self._ctrl]) for k in range(3))

    def gnss_observations(self):
        if not self._gnss:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))
        return tuple(np.concatenate([g[k] for g in self._gnss]) for k in range(4))

    @property
    def num_views(self) -> int:
        return len(self.view_pose)

    def copy(self) -> "BundleProblem":
        return copy.deepcopy(self)

    def poses(self):
        """Current poses as :class:`thermogrammetry.geometry.Pose` (one per pose block)."""
        from ..geometry.pose import Pose

        return [Pose(R, t) for R, t in zip(self.pose_R, self.pose_t)]

    def view_transform(self, view: int):
        """``(R, t)`` of a view (derived for rig views)."""
        p, r = self.view_pose[view], self.view_rig[view]
        R, t = self.pose_R[p], self.pose_t[p]
        if r < 0:
            return R, t
        return self.rig_R[r] @ R, self.rig_R[r] @ t + self.rig_t[r]
