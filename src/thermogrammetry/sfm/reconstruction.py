"""Incremental orientation of an image block from tracks (structure from motion).

The classic incremental scheme (Snavely et al. 2006; Schönberger & Frahm 2016), on the project's
adjustment engine:

1. **Initial pair**: among the best-connected pairs, the one whose essential matrix (MAGSAC++) gives the
   most triangulated points with a median triangulation angle above ``min_init_angle_deg``.
2. **Resection**: the unregistered image that sees the most triangulated tracks is oriented by PnP in a
   seeded RANSAC on normalised (undistorted) coordinates, then refined (Levenberg-Marquardt).
3. **Triangulation** of the tracks it adds (linear n-view on normalised rays), kept when every ray is in
   front of its camera, the largest intersection angle exceeds ``min_tri_angle_deg`` and every
   reprojection error is below ``max_error_px``.
4. **Bundle adjustment** (``thermogrammetry.adjustment``, Huber loss, free network) each time the block
   has grown by ``ba_growth``; then observations with reprojection errors above ``max_error_px`` are
   removed and tracks re-triangulated.

Images that cannot be added become a result with their reason; images that connect to each other but not
to the first block start a new *component*, reported separately and never forced together.

Frames: poses are ``cam_from_world`` in the model's own frame (first image at the origin, arbitrary
scale) until :mod:`thermogrammetry.sfm.georef` transforms them.

References
----------
Snavely, N., Seitz, S. M., Szeliski, R. (2006). Photo tourism. ACM SIGGRAPH.
Schönberger, J. L., Frahm, J.-M. (2016). Structure-from-motion revisited. CVPR.
Hartley, R., Zisserman, A. (2004). Multiple View Geometry, 2nd ed., §12.2 (linear triangulation).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .._memory import release_free_heap
from ..errors import ConfigError
from ..results import HasOutcome, Outcome, Termination
from .tracks import Tracks
from .._validate import config_keys

__all__ = ["ReconstructionOptions", "Reconstruction", "ImageStatus", "reconstruct", "triangulate_tracks", "bundle_adjust",
           "register_with_known_centres", "rotation_from_directions", "finish_components", "snapshot_of",
           "restore_to"]


@dataclass(frozen=True)
class ReconstructionOptions:
    """How the incremental orientation proceeds (unknown keys refused by :meth:`from_dict`)."""

    min_init_angle_deg: float = 3.0
    min_init_points: int = 50
    min_tri_angle_deg: float = 1.5
    max_error_px: float = 4.0
    # resection needs this many 2D-3D correspondences and PnP inliers (and min_pnp_inlier_ratio of them inliers).
    # 10, not 12: on a synthetic 40-station building ring (seed 1, 320 x 240 frames with ~200 SIFT features each)
    # one station had 10 inliers of 27, the ring broke there and 19/40 stations were oriented; with 10, 38/40
    # (rotations 0.57 deg RMS off, as the rest of the ring), while 36-, 48- and 56-station rings and the M3T flight
    # came out the same
    min_pnp_points: int = 10
    min_pnp_inlier_ratio: float = 0.25
    ba_growth: float = 1.25
    free_intrinsics: tuple[str, ...] = ("k1", "k2")  # refined in the incremental BAs (focal waits for the datum)
    min_component_images: int = 3
    seed: int = 0

    def __post_init__(self):
        if self.max_error_px <= 0 or self.min_tri_angle_deg <= 0:
            raise ConfigError("ReconstructionOptions: max_error_px and min_tri_angle_deg must be > 0")

    @classmethod
    def from_dict(cls, d: dict) -> "ReconstructionOptions":
        return cls(**config_keys(cls, d))


@dataclass
class ImageStatus:
    registered: bool = False
    component: int = -1
    reason: str = ""


@dataclass
class Reconstruction(HasOutcome):
    """State and result of an incremental orientation.

    Attributes
    ----------
    cameras : list of Camera (refined)
    image_camera : (n,) int
    R, t : (n, 3, 3), (n, 3) cam_from_world (valid where ``registered``)
    registered : (n,) bool
    component : (n,) int, -1 for unregistered
    points : (T, 3) float, NaN for tracks without a point
    tracks : Tracks
    obs_valid : (K,) bool, per track observation: used (not filtered as outlier)
    status : list of ImageStatus
    log : list of str
    """

    outcome: Outcome
    cameras: list
    image_camera: np.ndarray
    R: np.ndarray
    t: np.ndarray
    registered: np.ndarray
    component: np.ndarray
    points: np.ndarray
    tracks: Tracks
    obs_valid: np.ndarray
    status: list = field(default_factory=list)
    log: list = field(default_factory=list)
    seconds: float = 0.0

    def components(self) -> list[np.ndarray]:
        """Image indices of each component, largest first."""
        comps = [np.nonzero(self.component == c)[0] for c in np.unique(self.component[self.component >= 0])]
        return sorted(comps, key=len, reverse=True)

    def centers(self) -> np.ndarray:
        return -np.einsum("nji,nj->ni", self.R, self.t)

    def snapshot(self) -> dict:
        """What the final adjustment and its policy change, copied (:func:`snapshot_of`): :meth:`restore` puts it back."""
        return snapshot_of(self)

    def restore(self, snap: dict) -> None:
        """Put the reconstruction back as :meth:`snapshot` saw it (:func:`restore_to`)."""
        restore_to(self, snap)


def snapshot_of(rec) -> dict:
    """What the final adjustment and its policy change in ``rec`` (poses, registration, components, points, valid
    observations, cameras, status), copied: :func:`restore_to` puts it back (to undo a refused step). ``rec``: a
    :class:`Reconstruction` or anything with its attributes."""
    return {"R": rec.R.copy(), "t": rec.t.copy(), "registered": rec.registered.copy(), "component": rec.component.copy(),
            "points": rec.points.copy(), "obs_valid": rec.obs_valid.copy(), "cameras": list(rec.cameras),
            "status": [(s.registered, s.component, s.reason) for s in rec.status]}


def restore_to(rec, snap: dict) -> None:
    """Put ``rec`` back as :func:`snapshot_of` saw it (in place: the arrays keep their identity)."""
    rec.R[:], rec.t[:], rec.registered[:], rec.component[:] = snap["R"], snap["t"], snap["registered"], snap["component"]
    rec.points[:], rec.obs_valid[:] = snap["points"], snap["obs_valid"]
    rec.cameras[:] = snap["cameras"]
    for st, (r_, c_, w_) in zip(rec.status, snap["status"]):
        st.registered, st.component, st.reason = r_, c_, w_


# ------------------------------------------------------------------------------------------------
# small vectorised geometry
# ------------------------------------------------------------------------------------------------
def _rays(cameras, image_camera, xy_by_image):
    """Normalised rays (x, y) of all features, per image."""
    return [cameras[image_camera[i]].unproject(xy)[:, :2] if len(xy) else np.zeros((0, 2)) for i, xy in enumerate(xy_by_image)]


def triangulate_tracks(track_ids, obs_track, obs_R, obs_t, obs_ray):
    """Linear n-view triangulation of many tracks at once.

    Parameters
    ----------
    track_ids : (T,) int, the tracks to triangulate (values of ``obs_track``)
    obs_track : (K,) int, track of each observation
    obs_R, obs_t : (K, 3, 3), (K, 3), cam_from_world of the observing image
    obs_ray : (K, 2), normalised image coordinates (distortion removed)

    Returns
    -------
    X : (T, 3) world points (NaN where undetermined)
    max_angle_deg : (T,) largest angle between two rays of the track

    Observations with a non-finite ray or pose (a keypoint outside the domain where the distortion model can be
    inverted, e.g. with a poorly self-calibrated k1) are left out; a track left without a usable system is NaN.
    """
    obs_track = np.asarray(obs_track)
    obs_R, obs_t, obs_ray = np.asarray(obs_R, float), np.asarray(obs_t, float), np.asarray(obs_ray, float)
    fin = np.isfinite(obs_ray).all(axis=1) & np.isfinite(obs_t).all(axis=1) & np.isfinite(obs_R).all(axis=(1, 2))
    if not fin.all():
        obs_track, obs_R, obs_t, obs_ray = obs_track[fin], obs_R[fin], obs_t[fin], obs_ray[fin]
    uid, inv = np.unique(obs_track, return_inverse=True)
    # about a local origin: homogeneous solutions of CRS-sized coordinates (1e6 m) lose their precision
    origin = -np.einsum("kji,kj->i", obs_R, obs_t) / max(len(obs_t), 1)
    obs_t = obs_t + obs_R @ origin
    P = np.concatenate([obs_R, obs_t[:, :, None]], axis=2)  # (K, 3, 4)
    r1 = obs_ray[:, 0:1] * P[:, 2] - P[:, 0]
    r2 = obs_ray[:, 1:2] * P[:, 2] - P[:, 1]
    # Hartley-style conditioning per row (unit rows) keeps the 4x4 normal matrix well scaled
    r1 /= np.linalg.norm(r1, axis=1, keepdims=True)
    r2 /= np.linalg.norm(r2, axis=1, keepdims=True)
    A = np.einsum("ki,kj->kij", r1, r1) + np.einsum("ki,kj->kij", r2, r2)
    N = np.zeros((len(uid), 4, 4))
    np.add.at(N, inv, A)
    good = np.isfinite(N).all(axis=(1, 2))  # a zero-length row (ray along the image plane) gives NaN
    if not good.all():
        N[~good] = np.eye(4)
    w, v = np.linalg.eigh(N)
    Xh = v[:, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:4]
    X[~good] = np.nan
    X[~np.isfinite(X).all(axis=1)] = np.nan
    # angles of the rays from the camera centres to the points (robust to the measured ray noise)
    C = -np.einsum("kji,kj->ki", obs_R, obs_t)
    amax = ray_spread_deg(inv, len(uid), C, X[inv])
    pos = {int(u): k for k, u in enumerate(uid)}
    sel = np.array([pos.get(int(t), -1) for t in np.asarray(track_ids)], dtype=np.int64)
    Xo = np.full((len(sel), 3), np.nan)
    ao = np.zeros(len(sel))
    ok = sel >= 0
    Xo[ok] = X[sel[ok]] + origin
    ao[ok] = 2.0 * amax[sel[ok]]
    return Xo, ao


def ray_spread_deg(group, n_groups: int, centers, points) -> np.ndarray:
    """Per group of rays, the largest angle (degrees) between a ray and the group's mean ray direction: about half
    the largest angle between two of its rays (the intersection angle of a track is twice it).

    Parameters
    ----------
    group : (K,) int, the group (track, point) of each ray, in ``[0, n_groups)``
    n_groups : int
    centers, points : (K, 3) camera centre and point of each ray (the ray runs from the centre to the point)

    Returns
    -------
    (n_groups,) float64 degrees, 0 for a group without rays
    """
    dp = np.asarray(points, float) - centers
    dp /= np.maximum(np.linalg.norm(dp, axis=1, keepdims=True), 1e-300)
    mp = np.zeros((int(n_groups), 3))
    np.add.at(mp, group, dp)
    mp /= np.maximum(np.linalg.norm(mp, axis=1, keepdims=True), 1e-300)
    ang = np.degrees(np.arccos(np.clip(np.einsum("ki,ki->k", dp, mp[group]), -1, 1)))
    amax = np.zeros(int(n_groups))
    np.maximum.at(amax, group, ang)
    return amax


def _reproj_error(cameras, cam_idx, R, t, X, xy):
    """Pixel reprojection error (K,) and depth (K,) of observations with per-observation pose."""
    Xc = np.einsum("kij,kj->ki", R, X) + t
    err = np.full(len(X), np.inf)
    depth = Xc[:, 2]
    for c in np.unique(cam_idx):
        m = (cam_idx == c) & (depth > 0) & np.isfinite(depth)
        if m.any():
            with np.errstate(all="ignore"):
                proj = cameras[c].project(Xc[m])
            e = np.linalg.norm(proj - xy[m], axis=1)
            e[~np.isfinite(e)] = np.inf
            err[m] = e
    return err, depth


# ------------------------------------------------------------------------------------------------
# bundle adjustment on the engine
# ------------------------------------------------------------------------------------------------
def bundle_adjust(rec: Reconstruction, xy_by_image, images, *, free_intrinsics=(), fix_intrinsics_all=False,
                  loss: str = "huber", compute_covariance: bool = False, max_iterations: int = 30,
                  function_tolerance: float = 1e-6):
    """Adjust the registered images of ``images`` and the points they see (free network, robust loss).

    Updates ``rec`` in place; returns the engine's :class:`AdjustmentResult`.
    """
    from ..adjustment import BundleProblem, SolverOptions, solve

    images = np.asarray(images)
    tr = rec.tracks
    obs = rec.obs_valid & np.isin(tr.image, images) & np.isfinite(rec.points[tr.track]).all(axis=1)
    # points need >= 2 used observations
    cnt = np.bincount(tr.track[obs], minlength=len(rec.points))
    obs &= cnt[tr.track] >= 2
    if obs.sum() < 20:
        return None
    pts = np.unique(tr.track[obs])
    pb = BundleProblem(gauge="inner")
    cams_used = np.unique(rec.image_camera[images])
    cam_block = {}
    for c in cams_used:
        cam = rec.cameras[c]
        if fix_intrinsics_all:
            fixed = True
        else:
            free = {n.lower() for n in free_intrinsics}
            fixed = [n for n in cam.param_names if n.lower() not in free]
        cam_block[int(c)] = pb.add_camera(cam, fixed=fixed if fixed else False, name=f"camera{c}")
    view = {}
    for i in images:
        view[int(i)] = pb.add_pose((rec.R[i], rec.t[i]), name=f"image{i}")
    pidx = pb.add_points(rec.points[pts])
    pmap = np.full(len(rec.points), -1, np.int64)
    pmap[pts] = pidx
    order = np.nonzero(obs)[0]
    for i in images:
        o = order[tr.image[order] == i]
        if len(o) == 0:
            continue
        pb.add_image_points(cam_block[int(rec.image_camera[i])], view[int(i)], pmap[tr.track[o]],
                            xy_by_image[i][tr.feature[o]], sigma_px=1.0)
    opt = SolverOptions(loss=loss, loss_scale=2.0, max_iterations=max_iterations, compute_covariance=compute_covariance,
                        compute_redundancy=False, function_tolerance=function_tolerance)
    res = solve(pb, opt)
    if not res.success:
        return res
    p = res.problem
    for c, b in cam_block.items():
        rec.cameras[c] = p.cameras[b]
    for i, v in view.items():
        R, t = p.view_transform(v)
        rec.R[i], rec.t[i] = R, t
    rec.points[pts] = p.points[pidx]
    return res


# ------------------------------------------------------------------------------------------------
# the incremental loop
# ------------------------------------------------------------------------------------------------
class _Builder:
    def __init__(self, cameras, image_camera, xy_by_image, tracks: Tracks, pair_counts: dict, opt: ReconstructionOptions,
                 on_progress: Callable | None):
        n, nT = len(xy_by_image), tracks.n_tracks
        rec = Reconstruction(
            Outcome(Termination.CONVERGED), [c for c in cameras], np.asarray(image_camera, np.int64),
            np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)), np.zeros(n, bool), np.full(n, -1),
            np.full((nT, 3), np.nan), tracks, np.ones(len(tracks.track), bool), [ImageStatus() for _ in range(n)])
        self._attach(rec, xy_by_image, opt, pair_counts, on_progress)

    @classmethod
    def around(cls, rec: Reconstruction, xy_by_image, opt: ReconstructionOptions) -> "_Builder":
        """A builder that goes on from an existing reconstruction (its points belong to the component of the
        registered images that observe them)."""
        self = cls.__new__(cls)
        self._attach(rec, xy_by_image, opt, {}, None)
        tr = rec.tracks
        seen = rec.obs_valid & rec.registered[tr.image] & np.isfinite(rec.points[tr.track]).all(1)
        self.point_comp[tr.track[seen]] = rec.component[tr.image[seen]]
        return self

    def _attach(self, rec: Reconstruction, xy_by_image, opt, pair_counts, on_progress):
        tracks = rec.tracks
        self.opt = opt
        self.n = len(xy_by_image)
        self.xy = xy_by_image
        self.tr = tracks
        self.pair_counts = dict(pair_counts)
        self.on_progress = on_progress
        self.rec = rec
        self.rays = _rays(rec.cameras, rec.image_camera, xy_by_image)
        # observation lookup per image (ascending observation indices per image, as np.nonzero(image == i) gives)
        order = np.argsort(tracks.image, kind="stable")
        starts = np.searchsorted(tracks.image[order], np.arange(self.n + 1))
        self.obs_of_image = [order[starts[k]:starts[k + 1]] for k in range(self.n)]
        self.obs_of_track_start = np.searchsorted(tracks.track, np.arange(tracks.n_tracks + 1))
        self.failed_attempts = np.zeros(self.n, np.int64)
        self.last_count = np.zeros(self.n, np.int64)
        # component whose images triangulated each point (-1: none): a later component's images never use another
        # component's points, which are in that component's frame
        self.point_comp = np.full(tracks.n_tracks, -1, np.int64)

    def exclude_foreign(self, i, comp):
        """Observations of image ``i`` (registered in ``comp``) of points of other components: not used."""
        o = self.obs_of_image[i]
        t = self.tr.track[o]
        foreign = (self.point_comp[t] >= 0) & (self.point_comp[t] != comp) & np.isfinite(self.rec.points[t]).all(1)
        self.rec.obs_valid[o[foreign]] = False

    def log(self, msg):
        self.rec.log.append(msg)

    def refresh_rays(self):
        self.rays = _rays(self.rec.cameras, self.rec.image_camera, self.xy)

    # -- initial pair ------------------------------------------------------------------------
    def _shared(self, i, j):
        oi, oj = self.obs_of_image[i], self.obs_of_image[j]
        ti, tj = self.tr.track[oi], self.tr.track[oj]
        common, ai, aj = np.intersect1d(ti, tj, return_indices=True)
        return common, oi[ai], oj[aj]

    def try_init(self, allowed: np.ndarray) -> bool:
        import cv2

        cands = [(c, i, j) for (i, j), c in self.pair_counts.items() if allowed[i] and allowed[j]]
        cands.sort(key=lambda x: (-x[0], x[1], x[2]))
        best = None
        for c, i, j in cands[:30]:
            common, oi, oj = self._shared(i, j)
            if len(common) < self.opt.min_init_points:
                continue
            ri = self.rays[i][self.tr.feature[oi]]
            rj = self.rays[j][self.tr.feature[oj]]
            fin = np.isfinite(ri).all(axis=1) & np.isfinite(rj).all(axis=1)  # rays that could not be undistorted
            if not fin.all():
                common, oi, oj, ri, rj = common[fin], oi[fin], oj[fin], ri[fin], rj[fin]
                if len(common) < self.opt.min_init_points:
                    continue
            f = float(np.mean(np.diag(self.rec.cameras[self.rec.image_camera[i]].K)[:2]))
            cv2.setRNGSeed(self.opt.seed)
            E, mask = cv2.findEssentialMat(ri, rj, np.eye(3), method=cv2.USAC_MAGSAC, prob=0.9999, threshold=1.5 / f)
            if E is None or E.shape != (3, 3):
                continue
            n_in, R, tvec, mask2 = cv2.recoverPose(E, ri, rj, np.eye(3), mask=mask.copy())
            m = mask2.ravel() > 0
            if m.sum() < self.opt.min_init_points:
                continue
            Rs = np.stack([np.eye(3), R])
            ts = np.stack([np.zeros(3), tvec.ravel()])
            K = int(m.sum())
            obs_track = np.concatenate([common[m], common[m]])
            obs_R = np.concatenate([np.repeat(Rs[:1], K, 0), np.repeat(Rs[1:], K, 0)])
            obs_t = np.concatenate([np.repeat(ts[:1], K, 0), np.repeat(ts[1:], K, 0)])
            obs_ray = np.concatenate([ri[m], rj[m]])
            X, ang = triangulate_tracks(common[m], obs_track, obs_R, obs_t, obs_ray)
            good = np.isfinite(X).all(1) & (ang >= self.opt.min_tri_angle_deg)
            if good.sum() < self.opt.min_init_points:
                continue
            med = float(np.median(ang[good]))
            score = good.sum() * min(med / 8.0, 1.0)
            if med < self.opt.min_init_angle_deg:
                score *= 0.1
            if best is None or score > best[0]:
                best = (score, i, j, R, tvec.ravel(), med, int(good.sum()))
            if best[0] >= 0.8 * c and med >= self.opt.min_init_angle_deg:
                break
        if best is None:
            return False
        _, i, j, R, tv, med, ng = best
        comp = int(self.rec.component.max()) + 1
        self.rec.R[i], self.rec.t[i] = np.eye(3), np.zeros(3)
        self.rec.R[j], self.rec.t[j] = R, tv
        for k in (i, j):
            self.rec.registered[k] = True
            self.rec.component[k] = comp
            self.rec.status[k] = ImageStatus(True, comp, "")
            self.exclude_foreign(k, comp)
        self.log(f"component {comp}: initial pair {i}-{j}, {ng} points, median intersection angle {med:.1f} deg")
        self.triangulate_image(i, comp)
        self.ba(comp, full=True)
        return True

    # -- triangulation -------------------------------------------------------------------------
    def triangulate_image(self, i, comp):
        """(Re)triangulate the tracks of image i that have no point yet, using all registered views."""
        tr = self.tr
        o = self.obs_of_image[i]
        tids = np.unique(tr.track[o])
        tids = tids[~np.isfinite(self.rec.points[tids]).all(1)]
        self._triangulate(tids, comp)

    def _obs_of_tracks(self, tids) -> np.ndarray:
        """Indices of every observation of the tracks ``tids`` (grouped by track)."""
        starts, ends = self.obs_of_track_start[tids], self.obs_of_track_start[tids + 1]
        lens = ends - starts
        return np.repeat(starts, lens) + (np.arange(lens.sum()) - np.repeat(np.cumsum(lens) - lens, lens))

    def _triangulate(self, tids, comp):
        if len(tids) == 0:
            return 0
        tr = self.tr
        obs = self._obs_of_tracks(tids)
        im = tr.image[obs]
        use = self.rec.registered[im] & (self.rec.component[im] == comp) & self.rec.obs_valid[obs]
        obs = obs[use]
        cnt = np.bincount(tr.track[obs], minlength=len(self.rec.points))
        obs = obs[cnt[tr.track[obs]] >= 2]
        if len(obs) == 0:
            return 0
        im = tr.image[obs]
        rays = np.concatenate([self.rays[k][tr.feature[obs[im == k]]] for k in np.unique(im)])
        # keep obs in the same order as rays
        order = np.concatenate([obs[im == k] for k in np.unique(im)])
        tid = tr.track[order]
        imo = tr.image[order]
        X, ang = triangulate_tracks(np.unique(tid), tid, self.rec.R[imo], self.rec.t[imo], rays)
        ut = np.unique(tid)
        Xo = X[np.searchsorted(ut, tid)]
        err, depth = _reproj_error(self.rec.cameras, self.rec.image_camera[imo], self.rec.R[imo], self.rec.t[imo], Xo,
                                   np.concatenate([self.xy[k][tr.feature[obs[im == k]]] for k in np.unique(im)]))
        bad_obs = (err > self.opt.max_error_px) | (depth <= 0)
        bad_track = np.zeros(len(ut), bool)
        np.logical_or.at(bad_track, np.searchsorted(ut, tid), bad_obs)
        ok = np.isfinite(X).all(1) & (ang >= self.opt.min_tri_angle_deg) & ~bad_track
        self.rec.points[ut[ok]] = X[ok]
        self.point_comp[ut[ok]] = comp
        # their observations by images of other (earlier) components are not used: the point is in this one's frame
        allo = self._obs_of_tracks(ut[ok])
        imo_all = tr.image[allo]
        other = self.rec.registered[imo_all] & (self.rec.component[imo_all] != comp)
        self.rec.obs_valid[allo[other]] = False
        return int(ok.sum())

    # -- resection -----------------------------------------------------------------------------
    def candidates(self, comp):
        tr = self.tr
        has_pt = np.isfinite(self.rec.points[tr.track]).all(1) & self.rec.obs_valid
        # the point must belong to this component (triangulated by its images)
        counts = np.bincount(tr.image[has_pt & (self.point_comp[tr.track] == comp)], minlength=self.n)
        counts[self.rec.registered] = 0
        return counts

    def try_register(self, i, comp) -> tuple[bool, str]:
        import cv2

        tr = self.tr
        o = self.obs_of_image[i]
        o = o[np.isfinite(self.rec.points[tr.track[o]]).all(1) & np.isfinite(self.rays[i][tr.feature[o]]).all(1)
              & (self.point_comp[tr.track[o]] == comp)]
        if len(o) < self.opt.min_pnp_points:
            return False, f"sees {len(o)} oriented points < {self.opt.min_pnp_points}"
        X = self.rec.points[tr.track[o]]
        r = self.rays[i][tr.feature[o]]
        cam = self.rec.cameras[self.rec.image_camera[i]]
        f = float(np.mean(np.diag(cam.K)[:2]))
        cv2.setRNGSeed(self.opt.seed + int(i))
        ok, rvec, tvec, inl = cv2.solvePnPRansac(X, r, np.eye(3), None, iterationsCount=2000,
                                                 reprojectionError=self.opt.max_error_px / f, confidence=0.9999,
                                                 flags=cv2.SOLVEPNP_SQPNP)
        if not ok or inl is None:
            return False, f"no pose from {len(o)} 2D-3D correspondences (PnP RANSAC failed)"
        inl = inl.ravel()
        if len(inl) < self.opt.min_pnp_points or len(inl) < self.opt.min_pnp_inlier_ratio * len(o):
            return False, f"PnP: {len(inl)} inliers of {len(o)} correspondences"
        rvec, tvec = cv2.solvePnPRefineLM(X[inl], r[inl], np.eye(3), None, rvec, tvec)
        R, _ = cv2.Rodrigues(rvec)
        self.rec.R[i], self.rec.t[i] = R, tvec.ravel()
        self.rec.registered[i] = True
        self.rec.component[i] = comp
        self.rec.status[i] = ImageStatus(True, comp, "")
        self.exclude_foreign(i, comp)
        # observations that are PnP outliers are not used for this image
        out = np.setdiff1d(np.arange(len(o)), inl)
        self.rec.obs_valid[o[out]] = False
        return True, ""

    # -- adjustment + filtering ---------------------------------------------------------------------
    def ba(self, comp, full=False):
        images = np.nonzero(self.rec.registered & (self.rec.component == comp))[0]
        free = self.opt.free_intrinsics if len(images) >= 4 else ()
        # intermediate adjustments only need to keep the block consistent: loose stopping rule
        res = bundle_adjust(self.rec, self.xy, images, free_intrinsics=free, max_iterations=30 if full else 12,
                            function_tolerance=1e-6 if full else 1e-4)
        release_free_heap()  # the adjustment's freed temporaries: pages back before the block grows further
        if res is not None and not res.success:
            self.log(f"bundle adjustment with {len(images)} images stopped: {res.reason}")
        if free:
            self.refresh_rays()
        self.filter(comp)
        return res

    def filter(self, comp):
        tr = self.tr
        rec = self.rec
        obs = np.nonzero(rec.obs_valid & rec.registered[tr.image] & (rec.component[tr.image] == comp)
                         & np.isfinite(rec.points[tr.track]).all(1))[0]
        if len(obs) == 0:
            return
        # in chunks of observations: the per-observation poses (72 B each for R alone) and projections of a
        # large block are never held whole (the same values: each observation is computed on its own)
        bad = np.zeros(len(obs), bool)
        for a in range(0, len(obs), _FILTER_CHUNK):
            o = obs[a:a + _FILTER_CHUNK]
            im = tr.image[o]
            err, depth = _reproj_error(rec.cameras, rec.image_camera[im], rec.R[im], rec.t[im], rec.points[tr.track[o]],
                                       _gather(self.xy, im, tr.feature[o]))
            bad[a:a + len(o)] = (err > self.opt.max_error_px) | (depth <= 0)
        rec.obs_valid[obs[bad]] = False
        # points with fewer than 2 valid registered observations lose their coordinates
        valid = rec.obs_valid & rec.registered[tr.image] & (rec.component[tr.image] == comp)
        cnt = np.bincount(tr.track[valid], minlength=len(rec.points))
        touched = np.unique(tr.track[obs])
        lost = touched[cnt[touched] < 2]
        rec.points[lost] = np.nan

    def grow(self, comp, t0):
        last_ba = int(np.sum(self.rec.registered & (self.rec.component == comp)))
        while True:
            counts = self.candidates(comp)
            order = np.argsort(-counts, kind="stable")
            added = False
            for i in order[:8]:
                if counts[i] < self.opt.min_pnp_points:
                    break
                if self.failed_attempts[i] >= 3 and counts[i] <= self.last_count[i]:
                    continue
                ok, why = self.try_register(int(i), comp)
                if ok:
                    self.triangulate_image(int(i), comp)
                    added = True
                    nreg = int(np.sum(self.rec.registered & (self.rec.component == comp)))
                    if nreg >= self.opt.ba_growth * last_ba or nreg <= 4:
                        self.ba(comp)
                        # retriangulate everything of this component that lost or never had a point
                        imgs = np.nonzero(self.rec.registered & (self.rec.component == comp))[0]
                        tids = np.unique(self.tr.track[np.isin(self.tr.image, imgs)])
                        self._triangulate(tids[~np.isfinite(self.rec.points[tids]).all(1)], comp)
                        last_ba = nreg
                    if self.on_progress:
                        self.on_progress(int(self.rec.registered.sum()), self.n)
                    break
                self.failed_attempts[i] += 1
                self.last_count[i] = counts[i]
                self.rec.status[i] = ImageStatus(False, -1, why)
            if not added:
                break
        self.ba(comp, full=True)


#: observations per chunk of :meth:`_Builder.filter` (bounds its temporaries, ~0.3 KB per observation)
_FILTER_CHUNK = 65536


def _gather(xy_by_image, im, feat):
    out = np.empty((len(im), 2))
    for k in np.unique(im):
        m = im == k
        out[m] = xy_by_image[k][feat[m]]
    return out


def reconstruct(cameras, image_camera, xy_by_image, tracks: Tracks, pair_counts: dict, options: ReconstructionOptions | None = None,
                *, on_progress: Callable | None = None) -> Reconstruction:
    """Orient an image block incrementally.

    Parameters
    ----------
    cameras : list of Camera
        Starting intrinsics, one per sensor.
    image_camera : (n,) int
        Camera of each image.
    xy_by_image : list of (N_i, 2) arrays, feature positions (px)
    tracks : Tracks
    pair_counts : dict (i, j) -> number of verified matches (initial pair choice)
    options : ReconstructionOptions

    Returns
    -------
    Reconstruction
        ``termination`` is ``converged`` when at least one component was built, ``degenerate`` (with the
        reason) when no initial pair could be found.
    """
    opt = options or ReconstructionOptions()
    t0 = time.perf_counter()
    b = _Builder(cameras, image_camera, xy_by_image, tracks, pair_counts, opt, on_progress)
    comp = 0
    while True:
        allowed = ~b.rec.registered
        if allowed.sum() < 2 or not b.try_init(allowed):
            break
        comp = int(b.rec.component.max())
        b.grow(comp, t0)
        size = int(np.sum(b.rec.component == comp))
        if size < opt.min_component_images:
            # too small to keep: release the images
            m = b.rec.component == comp
            b.rec.registered[m] = False
            b.rec.component[m] = -1
            # its points are in its own frame: gone with it (a later component triangulates those tracks anew)
            gone = b.point_comp == comp
            b.rec.points[gone] = np.nan
            b.point_comp[gone] = -1
            for k in np.nonzero(m)[0]:
                b.rec.status[k] = ImageStatus(False, -1, f"only connected to a block of {size} images")
            b.log(f"component {comp} with {size} images dropped (< {opt.min_component_images})")
            # forbid this init from recurring: mark the images as tried by removing their pair counts
            for key in [k for k in b.pair_counts if m[k[0]] or m[k[1]]]:
                b.pair_counts.pop(key)
            continue
    rec = b.rec
    comps = finish_components(rec, pair_counts, "could not be added to any block (too few oriented tie points)")
    rec.seconds = time.perf_counter() - t0
    if not rec.registered.any():
        rec.outcome = Outcome(Termination.DEGENERATE, "no initial image pair with enough verified matches and intersection angle")
    else:
        rec.outcome = Outcome(Termination.CONVERGED, f"{int(rec.registered.sum())} of {b.n} images in {len(comps)} component(s)")
    return rec


def finish_components(rec: Reconstruction, pair_counts: dict, unplaced_reason: str,
                      no_match_reason: str = "no verified matches with any other image") -> list[np.ndarray]:
    """Renumber ``rec``'s components largest first and give every image its status: registered ones their
    component, unregistered ones without a reason yet ``no_match_reason`` (on no pair of ``pair_counts``) or
    ``unplaced_reason``. Returns the components (image indices, largest first)."""
    comps = rec.components()
    newc = np.full(rec.component.shape, -1)
    for k, idx in enumerate(comps):
        newc[idx] = k
    rec.component = newc
    for i in range(len(rec.status)):
        if rec.registered[i]:
            rec.status[i] = ImageStatus(True, int(newc[i]), "")
        elif not rec.status[i].reason:
            has = any((i in key) for key in pair_counts)
            rec.status[i] = ImageStatus(False, -1, unplaced_reason if has else no_match_reason)
    return comps


# images with a known camera centre (GNSS): sfm.known_centres (re-exported here, where they were)
from .known_centres import MIN_CENTRE_RESECTION_POINTS, register_with_known_centres, rotation_from_directions  # noqa: E402
