"""The final bundle adjustment of a georeferenced block: GNSS camera-centre priors and weighted GCPs.

On the engine (:mod:`thermogrammetry.adjustment`) with GNSS priors (σ per image, lever arm in the camera
frame), weighted GCPs (σ per coordinate, their image measurements with σ in px), manual ties, rig views
and attitude priors; the camera is self-calibrated (the named parameters free) unless a calibrated camera
was given. A first robust (Huber) solve finds blunders: tie observations above ``max_error_px``, GCP
measurements above ``max(gcp_reject_px, 5 σ)`` and a few GNSS positions far from the solution are
removed; the second, unweighted-loss solve gives σ0, the a-posteriori covariance of every camera
parameter and pose, and the residuals (:func:`final_adjustment`, one pass: :func:`_final_adjustment`).

References
----------
Förstner, W., Wrobel, B. P. (2016). Photogrammetric Computer Vision, §4.2.4 (propagation), §15.4.
Barazzetti, L., Erba, S., Previtali, M., Rosina, E., Scaioni, M. (2013). Mosaicking thermal images of
buildings (thermal images as rig views of RGB images, eq. 4-5).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._memory import release_free_heap
from .georef_control import ControlInputs
from .georef_datum import attitude_images
from .georef_gnss import GNSS_REJECT_SIGMA, gnss_misfit

__all__ = ["FinalAdjustment", "HUBER_K", "final_adjustment", "gcp_measurement_table", "MIN_FINAL_TRI_ANGLE_DEG",
           "parallel_ray_points"]


@dataclass
class FinalAdjustment:
    """Outcome of :func:`final_adjustment` (the engine's result plus the bookkeeping of the survey)."""

    result: object  # AdjustmentResult of the last solve
    images: np.ndarray
    view_of_image: dict
    tie_residuals: np.ndarray  # (K, 2) px of the used tie observations
    tie_obs_image: np.ndarray  # (K,) image index
    gcp_residuals_m: np.ndarray  # (G, 3) adjusted - given, NaN for unused GCPs
    gcp_used: np.ndarray  # (G,) bool
    gcp_rejected: list  # (image index, gcp id, residual px)
    gnss_residuals_m: np.ndarray  # (n_images_with_gnss, 3)
    covariance: np.ndarray | None
    param_names: list
    center_std: np.ndarray  # (n, 3) m, NaN where unknown
    rotation_std_deg: np.ndarray  # (n, 3)
    notes: list
    manual_ties: list = field(default_factory=list)  # dicts: id index, xyz, n_images, residuals px
    gnss_rejected: list = field(default_factory=list)  # image indices whose GNSS prior was left out (blunders)
    gnss_images: list = field(default_factory=list)  # image indices with a GNSS prior (used or rejected)
    #: the GCP image measurements' σ (px) given (median) and estimated from their residuals in the last solve
    #: (``sqrt(sum |v|^2 / (2 n - 3 G))``, n measurements of G GCPs) with its degrees of freedom; None when < 10
    marker_sigma: dict | None = None
    #: every GCP image measurement of the block's images (:func:`gcp_measurement_table`): image index, GCP id, its
    #: σ (px), the residual ``projected − measured`` (px) at the adjusted GCP and pose, whether the last solve used
    #: it and, when not, why
    gcp_measurements: list = field(default_factory=list)


#: degrees of freedom below which the GCP measurements' σ is not estimated from their residuals
MARKER_SIGMA_MIN_DOF = 10


def _marker_sigma(res, n_tie: int, gcp_obs: list) -> dict | None:
    """The GCP image measurements' σ: given (median of the measurements' σ, px) and estimated from their
    residuals of the last solve, ``sqrt(sum |v|^2 / (2 n - 3 G))`` (n measurements of G GCPs: each GCP's three
    coordinates counted as unknowns, which their 1-2 cm σ nearly are not: the estimate errs on the large side).
    None below :data:`MARKER_SIGMA_MIN_DOF` degrees of freedom."""
    n = len(gcp_obs)
    ng = len({o[1] for o in gcp_obs})
    dof = 2 * n - 3 * ng
    if dof < MARKER_SIGMA_MIN_DOF:
        return None
    v = np.asarray(res.image_residuals[n_tie:n_tie + n], float)
    if len(v) != n or not np.all(np.isfinite(v)):
        return None
    given = float(np.median([float(np.max(o[3])) for o in gcp_obs]))
    return {"given_px": given, "estimated_px": float(np.sqrt(np.sum(v**2) / dof)), "dof": int(dof)}


#: Huber's k (in σ of the tie points) of the robust final adjustment (95 % efficiency under Gaussian errors)
HUBER_K = 1.345


def _gnss_conflicts(rec, images, ctrl) -> list:
    """Images whose adjusted antenna position is more than :data:`GNSS_REJECT_SIGMA` σ from their GNSS."""
    return sorted(i for i, (d, z) in gnss_misfit(rec, images, ctrl).items() if np.max(z) > GNSS_REJECT_SIGMA)


def _apply_solution(rec, p, cam_block, view, pts, pidx, rig) -> None:
    """Copy a solved problem's cameras, poses, points (and rig) into ``rec``."""
    for c, b in cam_block.items():
        rec.cameras[c] = p.cameras[b]
    for i, v in view.items():
        rec.R[i], rec.t[i] = p.view_transform(v)
    rec.points[pts] = p.points[pidx]
    if rig is not None:
        rig.R, rig.t = p.rig_R[0].copy(), p.rig_t[0].copy()


def _state(rec, rig) -> tuple:
    """What an adjustment changes in ``rec`` (and the rig), to go back to it with :func:`_set_state`."""
    return (rec.R.copy(), rec.t.copy(), rec.points.copy(), rec.obs_valid.copy(), list(rec.cameras),
            None if rig is None else (np.copy(rig.R), np.copy(rig.t)))


def _set_state(rec, rig, st) -> None:
    rec.R[:], rec.t[:], rec.points[:], rec.obs_valid[:] = st[0], st[1], st[2], st[3]
    rec.cameras[:] = st[4]
    if st[5] is not None:
        rig.R, rig.t = np.copy(st[5][0]), np.copy(st[5][1])


def gcp_measurement_table(rec, ctrl: ControlInputs, in_block, adjusted_xyz: dict, used: set, reasons: dict) -> list:
    """Every GCP image measurement of the images in ``in_block`` with its residual at the adjusted state.

    Parameters
    ----------
    rec : Reconstruction with the adjusted poses and cameras
    ctrl : ControlInputs, ``gcp_obs`` = (image index, GCP index, (x, y) px, σ px) per measurement
    in_block : (n_images,) bool
    adjusted_xyz : {GCP index: (3,) adjusted coordinates}; GCPs not in the solve are projected from their given ones
    used : measurement indices the last solve used
    reasons : {measurement index: why it was left out}

    Returns
    -------
    list of dict: ``image`` (index), ``id``, ``sigma_px``, ``dx_px``, ``dy_px`` (projected − measured; None when the
    GCP is behind the camera), ``residual_px``, ``used`` and ``reason`` ("" when used)
    """
    rows = []
    for k, (i, gi, xy, s) in enumerate(ctrl.gcp_obs):
        if not in_block[i]:
            continue
        X = np.asarray(adjusted_xyz.get(gi, ctrl.gcp_xyz[gi]), float)
        Xc = rec.R[i] @ X + rec.t[i]
        d = None
        if Xc[2] > 0:
            with np.errstate(all="ignore"):
                pr = rec.cameras[rec.image_camera[i]].project(Xc[None, :])[0]
            if np.all(np.isfinite(pr)):
                d = pr - np.asarray(xy, float)
        use = k in used
        rows.append({"image": int(i), "id": ctrl.gcp_ids[gi], "sigma_px": float(np.max(s)),
                     "dx_px": None if d is None else float(d[0]), "dy_px": None if d is None else float(d[1]),
                     "residual_px": None if d is None else float(np.hypot(*d)), "used": bool(use),
                     "reason": "" if use else reasons.get(k, "its GCP was not in the adjustment")})
    return rows


def final_adjustment(rec, xy_by_image, images, ctrl: ControlInputs, *, robust_ties_on_conflict: bool = True,
                     **kw) -> FinalAdjustment:
    """Joint adjustment of the block with GNSS priors and weighted GCPs (see the module docstring).

    Least squares after a robust round (:func:`_final_adjustment`). When least squares leaves images more than
    :data:`GNSS_REJECT_SIGMA` σ from GNSS positions that passed the blunder test, tie observations with
    systematic errors that passed the blunder test (features on occluding edges — T-junctions —, repeated
    structure) outweigh those images' GNSS: the block is adjusted again from the same start with the ties under
    a robust loss to the end (Huber, k = :data:`HUBER_K` σ), and that solution is kept when it resolves the
    conflict (fewer such images, none new) without bending the block (median tie residual within 10 % of least
    squares'); otherwise the least-squares solution stays and the survey names the images. Only for a few such
    images (<= 10 % of those with GNSS): many mean a GNSS σ or datum that is wrong for the whole flight.
    Measured on the 64-station ring around the synthetic building (occluder in front of the south wall): the
    two stations facing the occluder 0.41 / 0.44 m (13 σ) from their RTK GNSS and 3.0° / 2.5° off under least
    squares; see ``tests/test_texture_survey_poses.py`` for the robust figures.
    Keyword arguments: those of :func:`_final_adjustment`.
    """
    rig = kw.get("rig")
    start = _state(rec, rig) if robust_ties_on_conflict else None
    fa = _final_adjustment(rec, xy_by_image, images, ctrl, **kw)
    if start is None or not kw.get("georeferenced", True) or len(fa.gnss_images) < 4:
        return fa
    used = [i for i in fa.gnss_images if i not in fa.gnss_rejected]
    before = _gnss_conflicts(rec, used, ctrl)
    if not before or len(before) > 0.1 * len(used):
        # none, or many: then the GNSS σ or datum is wrong for the whole flight, not a few images' tie points
        return fa
    ls = _state(rec, rig)
    _set_state(rec, rig, start)
    fa_r = _final_adjustment(rec, xy_by_image, images, ctrl, final_loss="huber", **kw)
    used_r = [i for i in fa_r.gnss_images if i not in fa_r.gnss_rejected]
    after = _gnss_conflicts(rec, used_r, ctrl)
    # the robust solution must not buy the GNSS fit by bending the block: the bulk of the tie points (median
    # residual) fits as well as under least squares (within 10 %)
    med = lambda v: float(np.nanmedian(np.linalg.norm(v, axis=1))) if len(v) else np.nan  # noqa: E731
    bulk_ok = med(fa_r.tie_residuals) <= 1.1 * med(fa.tie_residuals)
    if fa_r.result.success and bulk_ok and len(after) < len(before) and set(after) <= set(before):
        fa_r.notes.append(f"{len(before)} camera centre(s) more than {GNSS_REJECT_SIGMA:g} σ from their GNSS under least "
                          f"squares ({len(after)} after): the tie points were weighted by a robust loss (Huber, "
                          f"k = {HUBER_K:g} σ) to the end of the final adjustment")
        return fa_r
    _set_state(rec, rig, ls)
    return fa


#: when a solve of the final adjustment stops on a singular point block -- or on an undetermined camera side: one such
#: point's huge depth and tiny parallax leave the reduced camera system numerically singular (the held-out 48-station
#: building ring with ``--refine-ties lsm``: "condition 4.77e+300" on a 29-image block, rejected whole; one point
#: removed and it solves) --, the tie points whose rays meet at less than this angle (degrees) are left out and the
#: round is solved again: their depth is undetermined. The orientation creates points at >= 1.5°
#: (``min_tri_angle_deg``); points drift towards infinity in an adjustment (a block matched on noise: walk seed 4 had
#: 25 below 0.01°; the 64-station ring one at 0.0002°, which its solves carry). Only after such a stop, so that
#: blocks that solve keep every point.
MIN_FINAL_TRI_ANGLE_DEG = 0.1


def parallel_ray_points(rec, obs) -> np.ndarray:
    """Tracks (point indices) of ``rec`` whose observations ``obs`` (bool over ``rec.tracks``) have rays that meet at
    less than :data:`MIN_FINAL_TRI_ANGLE_DEG`: twice :func:`~thermogrammetry.sfm.reconstruction.ray_spread_deg`, as
    the orientation measures a track's intersection angle."""
    from .reconstruction import ray_spread_deg

    tr = rec.tracks
    o = np.flatnonzero(obs)
    if not len(o):
        return np.zeros(0, np.int64)
    t, i = tr.track[o], tr.image[o]
    C = -np.einsum("kji,kj->ki", rec.R[i], rec.t[i])
    amax = ray_spread_deg(t, len(rec.points), C, rec.points[t])
    seen = np.zeros(len(rec.points), bool)
    seen[t] = True
    # seen from one projection centre only (an RGB image and its thermal partner through a rig of zero base): the
    # adjustment moves such a point onto the centre, where its "rays" point anywhere
    lo = np.full((len(rec.points), 3), np.inf)
    hi = np.full((len(rec.points), 3), -np.inf)
    np.minimum.at(lo, t, C)
    np.maximum.at(hi, t, C)
    one_centre = seen & (np.max(hi - lo, axis=1) <= 1e-7 * max(float(np.ptp(C, axis=0).max()), 1e-300))
    return np.flatnonzero(seen & ((2.0 * amax < MIN_FINAL_TRI_ANGLE_DEG) | one_centre))


def _final_adjustment(rec, xy_by_image, images, ctrl: ControlInputs, *, self_calibrate=(), tie_sigma_px: float = 1.0,
                      max_error_px: float = 4.0, gcp_reject_px: float = 5.0, compute_covariance: bool = True,
                      georeferenced: bool = True, max_iterations: int = 50, rig=None, manual_ties=None,
                      final_loss: str = "trivial", attitude_priors: bool = False,
                      focal_priors: dict | None = None) -> FinalAdjustment:
    """One pass of :func:`final_adjustment`: a robust round, then ``final_loss`` rounds (least squares by default).

    ``rec`` is updated in place (cameras, poses, points).

    ``self_calibrate`` is a tuple of parameter names for every camera, or a dict camera index -> names.
    ``rig`` (:class:`~thermogrammetry.sfm.rig.RigViews`): its slave images of the block are rig views of
    their masters (Barazzetti et al. 2013, eq. 4-5); the rig is fixed or estimated (``rig.R, rig.t, rig.std`` updated).
    ``manual_ties``: list of (image index, tie index, (2,) xy px, σ px) -- points measured by hand in
    several images (RGB and thermal), unknown 3D points of the adjustment (at least 2 images of the block).
    ``attitude_priors``: the images' observed attitudes (``ctrl.attitude``) enter as priors, each with σ
    :data:`~.attitude.ATTITUDE_SIGMA_DEG` · sqrt(n) (together one observation of the block's rotation): the datum of a
    block whose GNSS positions lie on one line (:func:`similarity_start`).
    ``focal_priors``: camera index -> (focal length px, σ px), the lens's value (EXIF or the camera table): where fx
    and fy are self-calibrated they enter with this weighted prior (``BundleProblem.add_camera_prior``).
    """
    from ..adjustment import BundleProblem, SolverOptions, solve

    images = np.asarray(images)
    notes: list[str] = []
    tr = rec.tracks
    in_block = np.zeros(len(rec.registered), bool)
    in_block[images] = True
    gcp_active = [True] * len(ctrl.gcp_obs)
    rejected = []
    reasons: dict[int, str] = {}  # measurement index -> why it was left out
    if georeferenced and ctrl.gcp_obs:
        # gross errors first: a GCP "measured" in an image where it cannot be (wrong identification) is
        # found by projecting its coordinates with the georeferenced start, before it can bend the block
        res_px = np.full(len(ctrl.gcp_obs), np.nan)
        for k, (i, gi, xy, s_) in enumerate(ctrl.gcp_obs):
            if not in_block[i]:
                continue
            Xc = rec.R[i] @ ctrl.gcp_xyz[gi] + rec.t[i]
            if Xc[2] <= 0:
                res_px[k] = np.inf
                continue
            with np.errstate(all="ignore"):
                pr = rec.cameras[rec.image_camera[i]].project(Xc[None, :])[0]
            res_px[k] = float(np.linalg.norm(pr - np.asarray(xy, float))) if np.all(np.isfinite(pr)) else np.inf
        fin = res_px[np.isfinite(res_px)]
        if len(fin):
            gate = max(gcp_reject_px * 5.0, 5.0 * float(np.median(fin)))
            for k in np.nonzero(res_px > gate)[0]:
                i, gi = ctrl.gcp_obs[k][0], ctrl.gcp_obs[k][1]
                gcp_active[k] = False
                rejected.append((int(i), ctrl.gcp_ids[gi], float(res_px[k])))
                reasons[int(k)] = (f"{res_px[k]:.1f} px from the GCP's projection before the adjustment, gate {gate:.1f} px "
                                   "(a wrong identification?)")
    res = None
    gnss_active = np.ones(len(rec.registered), bool)
    gnss_rejected: list[int] = []
    gnss_screened = False
    start = _state(rec, rig)
    drop_parallel = False  # set when a solve stops on a singular point block: such points are left out, once
    for round_ in range(5):
        # the previous round's result (its problem, residuals) is released before the next problem is built
        res = p = v_img = pb = None
        release_free_heap()
        obs = rec.obs_valid & in_block[tr.image] & np.isfinite(rec.points[tr.track]).all(1)
        cnt = np.bincount(tr.track[obs], minlength=len(rec.points))
        obs &= cnt[tr.track] >= 2
        weak = parallel_ray_points(rec, obs) if drop_parallel else ()
        if len(weak):
            # points whose rays have become (nearly) parallel carry no depth and made the adjustment singular
            rec.obs_valid[np.isin(tr.track, weak) & obs] = False
            obs &= ~np.isin(tr.track, weak)
            notes.append(f"{len(weak)} tie point(s) with rays within {MIN_FINAL_TRI_ANGLE_DEG:g}° of parallel left out "
                          f"(round {round_ + 1})")
        pts = np.unique(tr.track[obs])
        have_gnss = np.all(np.isfinite(ctrl.gnss_xyz[images]), axis=1)
        use_gcp = [k for k, (i, gi, xy, s) in enumerate(ctrl.gcp_obs) if in_block[i] and gcp_active[k]]
        gcps_in = sorted({ctrl.gcp_obs[k][1] for k in use_gcp})
        control = georeferenced and (have_gnss.sum() >= 3 or len(gcps_in) >= 3)
        pb = BundleProblem(gauge="control" if control else "inner")
        cam_block = {}
        for c in np.unique(rec.image_camera[images]):
            cam = rec.cameras[c]
            sc = self_calibrate.get(int(c), ()) if isinstance(self_calibrate, dict) else self_calibrate
            free = {n.lower() for n in sc}
            fixed = [n for n in cam.param_names if n.lower() not in free]
            cam_block[int(c)] = pb.add_camera(cam, fixed=fixed if fixed else False, name=f"camera{c}")
            fpr = (focal_priors or {}).get(int(c))
            if fpr is not None and {"fx", "fy"} <= free:
                pb.add_camera_prior(cam_block[int(c)], {"fx": fpr[0], "fy": fpr[0]}, {"fx": fpr[1], "fy": fpr[1]})
        slaves = {} if rig is None else {int(s): int(m) for s, m in rig.master.items() if in_block[s] and in_block[m]}
        view = {int(i): pb.add_pose((rec.R[i], rec.t[i]), name=f"image{i}") for i in images if int(i) not in slaves}
        if slaves:
            rig_block = pb.add_rig((rig.R, rig.t), fixed=rig.fixed)
            for s_, m_ in slaves.items():
                view[s_] = pb.add_rig_view(rig_block, view[m_])
        pidx = pb.add_points(rec.points[pts]) if len(pts) else np.zeros(0, np.int64)
        pmap = np.full(len(rec.points), -1, np.int64)
        pmap[pts] = pidx
        order = np.nonzero(obs)[0]
        tie_rows = []  # (image index, its observation indices) in the order they enter the problem
        for i in images:
            o = order[tr.image[order] == i]
            if len(o) == 0:
                continue
            pb.add_image_points(cam_block[int(rec.image_camera[i])], view[int(i)], pmap[tr.track[o]],
                                xy_by_image[i][tr.feature[o]], sigma_px=tie_sigma_px)
            tie_rows.append((int(i), o))
        n_tie = int(sum(len(o) for _, o in tie_rows))
        # GCPs: weighted control points with their image measurements
        gcp_point = {}
        if gcps_in:
            gp = pb.add_points(ctrl.gcp_xyz[gcps_in])
            gcp_point = dict(zip(gcps_in, gp.tolist()))
            pb.add_control(gp, ctrl.gcp_xyz[gcps_in], ctrl.gcp_sigma[gcps_in])
            for k in use_gcp:
                i, gi, xy, s = ctrl.gcp_obs[k]
                pb.add_image_points(cam_block[int(rec.image_camera[i])], view[int(i)], np.array([gcp_point[gi]]),
                                    np.atleast_2d(xy), sigma_px=s)
        tie_pts = _add_manual_ties(pb, rec, manual_ties, in_block, view, cam_block) if manual_ties else {}
        have_gnss = have_gnss & ~np.isin(images, list(slaves)) & gnss_active[images]  # plain pose views only
        gnss_views = [view[int(i)] for i, h in zip(images, have_gnss) if h]
        if georeferenced and gnss_views:
            sel = images[have_gnss]
            pb.add_gnss(np.array(gnss_views), ctrl.gnss_xyz[sel], ctrl.gnss_sigma[sel], ctrl.lever_arm_m)
        att = [int(i) for i in attitude_images(ctrl, images) if int(i) not in slaves] if attitude_priors else []
        if georeferenced and att:
            from .attitude import ATTITUDE_SIGMA_DEG

            pb.add_attitude(np.array([view[i] for i in att]), ctrl.attitude[att],
                            np.radians(ATTITUDE_SIGMA_DEG) * np.sqrt(len(att)))
        robust = round_ == 0 or (round_ == 1 and bool(gnss_rejected))
        opt = SolverOptions(loss="huber" if robust else final_loss, loss_scale=2.0 if robust else HUBER_K,
                            max_iterations=max_iterations,
                            compute_covariance=(not robust) and compute_covariance, compute_redundancy=False,
                            function_tolerance=1e-8 if not robust else 1e-3)
        res = solve(pb, opt)
        if (not res.success and not drop_parallel and round_ < 4
                and any(w in str(res.reason) for w in ("point's normal block is singular", "undetermined",
                                                       # a singular point block seen only by the precision step: a
                                                       # point observed from one centre (rig of zero base)
                                                       "precision step failed", "not positive definite"))):
            notes.append(f"final adjustment (round {round_ + 1}) stopped: {res.reason}; solved again without the points "
                         f"whose rays meet at less than {MIN_FINAL_TRI_ANGLE_DEG:g}°")
            drop_parallel = True
            continue
        if not res.success:
            notes.append(f"final adjustment (round {round_ + 1}) stopped: {res.reason}")
            if res.problem is None:
                break
        p = res.problem
        _apply_solution(rec, p, cam_block, view, pts, pidx, rig if slaves else None)
        v_img = res.image_residuals
        changed = False
        if robust and not gnss_screened:
            gnss_screened = True
            # GNSS blunders (a wrong tag, another flight's position): few positions far from the robust solution are
            # left out, never many (then the GNSS σ is wrong, which the survey reports instead); the robust round is
            # then repeated from the start without them, so that they bend neither the block nor its tie rejection
            if georeferenced and len(gnss_views) >= 4:
                mis = gnss_misfit(rec, sel, ctrl)
                far = [i for i, (d, z) in mis.items() if np.max(z) > GNSS_REJECT_SIGMA]
                if far and len(far) <= 0.1 * len(mis) and len(mis) - len(far) >= 3:
                    gnss_active[far] = False
                    gnss_rejected += far
                    notes.append(f"{len(far)} GNSS position(s) more than {GNSS_REJECT_SIGMA:g} σ from the robust "
                                 "solution left out of the final adjustment (see gnss_flagged)")
                    _set_state(rec, rig, start)
                    continue
        if robust:
            # tie blunders
            tie_v = v_img[:n_tie]
            big = np.linalg.norm(tie_v, axis=1) > max_error_px
            # variance component of the tie points (Helmert, one step): their a-priori σ is replaced by
            # the estimate from their residuals and redundancy, so that GNSS and GCP weights stay in
            # proportion and σ0 of the final solve tests the whole model
            good = ~big
            n_obs = 2 * int(good.sum())
            n_unk = 3 * len(pts) + 6 * len(pb.pose_R) + int(sum((~np.asarray(f)).sum() for f in pb.camera_fixed))
            if n_obs > n_unk + 10:
                sig_hat = float(np.sqrt(np.sum(tie_v[good] ** 2) / (n_obs - n_unk)))
                notes.append(f"tie-point σ estimated from the residuals: {sig_hat:.3f} px (a priori {tie_sigma_px:g} px)")
                tie_sigma_px = float(np.clip(sig_hat, 0.02, 10.0))
            if big.any():
                rec.obs_valid[order[big]] = False
                changed = True
            # GCP measurements: the worst one per GCP above the threshold is rejected
            gv = v_img[n_tie:]
            worst = {}
            for r, k in enumerate(use_gcp):
                i, gi, xy, s = ctrl.gcp_obs[k]
                e = float(np.linalg.norm(gv[r]))
                if e > max(gcp_reject_px, 5.0 * float(np.max(s))) and (gi not in worst or e > worst[gi][1]):
                    worst[gi] = (k, e)
            for gi, (k, e) in worst.items():
                gcp_active[k] = False
                rejected.append((int(ctrl.gcp_obs[k][0]), ctrl.gcp_ids[gi], e))
                reasons[int(k)] = (f"{e:.1f} px in round {round_ + 1}, the largest of its GCP's and above "
                                   f"{max(gcp_reject_px, 5.0 * float(np.max(ctrl.gcp_obs[k][3]))):.1f} px "
                                   f"(max of {gcp_reject_px:g} px and 5 σ)")
                changed = True
            continue  # always a second, non-robust solve
        if not changed:
            break
    # bookkeeping of the last solve
    p = res.problem
    gcp_res = np.full((len(ctrl.gcp_ids), 3), np.nan)
    for gi, pi in gcp_point.items():
        gcp_res[gi] = p.points[pi] - ctrl.gcp_xyz[gi]
    used = np.zeros(len(ctrl.gcp_ids), bool)
    used[list(gcp_point)] = True
    n = len(rec.registered)
    cstd = np.full((n, 3), np.nan)
    rstd = np.full((n, 3), np.nan)
    if res.pose_std is not None:
        for i, v in view.items():
            if p.view_rig[v] >= 0:  # rig views: propagated below from the master pose and the rig
                continue
            pi = p.view_pose[v]
            cstd[i] = res.pose_std[pi, 3:]
            rstd[i] = np.degrees(res.pose_std[pi, :3])
    tie_obs_image = np.concatenate([np.full(len(o), i) for i, o in tie_rows]) if tie_rows else np.zeros(0, int)
    if res.image_residuals is not None:
        tie_v = res.image_residuals[:n_tie]
    else:  # the solve stopped without residuals: they are recomputed from the last state, not dropped
        tie_v = np.full((n_tie, 2), np.nan)
        k0 = 0
        for i, o in tie_rows:
            Xc = rec.points[tr.track[o]] @ rec.R[i].T + rec.t[i]
            with np.errstate(all="ignore"):
                tie_v[k0:k0 + len(o)] = rec.cameras[rec.image_camera[i]].project(Xc) - xy_by_image[i][tr.feature[o]]
            k0 += len(o)
    fa = FinalAdjustment(res, images, view, tie_v, tie_obs_image, gcp_res, used, rejected,
                         res.gnss_residuals if res.gnss_residuals is not None else np.zeros((0, 3)),
                         res.covariance, list(res.param_names or []), cstd, rstd, notes, gnss_rejected=gnss_rejected,
                         gnss_images=[int(i) for i in images[have_gnss | np.isin(images, gnss_rejected)]] if georeferenced else [])
    fa.marker_sigma = _marker_sigma(res, n_tie, [ctrl.gcp_obs[k] for k in use_gcp]) if res.image_residuals is not None \
        else None
    fa.gcp_measurements = gcp_measurement_table(rec, ctrl, in_block, {gi: p.points[pi] for gi, pi in gcp_point.items()},
                                                set(use_gcp), reasons)
    if tie_pts:
        fa.manual_ties = _manual_tie_results(res, p, tie_pts, n_tie + sum(1 for k in use_gcp), manual_ties, in_block)
    if slaves:
        from .rig import slave_std

        names_ = list(res.param_names or [])
        if res.std is not None and "rig0.wx" in names_ and not rig.fixed:
            k0 = names_.index("rig0.wx")
            rig.std = np.asarray(res.std[k0:k0 + 6], float)
            if res.covariance is not None:
                rig.covariance = np.asarray(res.covariance[k0:k0 + 6, k0:k0 + 6], float)
        for s_ in slaves:
            cstd[s_], rstd[s_] = slave_std(rig, rec, fa, s_)
    return fa


def _add_manual_ties(pb, rec, manual_ties, in_block, view, cam_block) -> dict:
    """Manual tie points (measured by hand in RGB and thermal images) as unknown points of ``pb``.

    Returns tie index -> (problem point index, list of manual_ties rows used); ties seen in fewer than 2
    images of the block, from one projection centre only, or whose rays do not intersect in front of the
    cameras, are left out.
    """
    from .reconstruction import triangulate_tracks

    by_id: dict[int, list] = {}
    for r, (i, ti, xy, s) in enumerate(manual_ties):
        if in_block[i] and int(i) in view:
            by_id.setdefault(int(ti), []).append(r)
    out = {}
    for ti, rows in sorted(by_id.items()):
        if len({manual_ties[r][0] for r in rows}) < 2:
            continue
        ii = np.array([manual_ties[r][0] for r in rows])
        xy = np.array([np.asarray(manual_ties[r][2], float) for r in rows])
        Rs = np.array([pb.view_transform(view[int(i)])[0] for i in ii])
        ts = np.array([pb.view_transform(view[int(i)])[1] for i in ii])
        rays = np.concatenate([rec.cameras[rec.image_camera[i]].unproject(xy[k:k + 1])[:, :2] for k, i in enumerate(ii)])
        X, _ = triangulate_tracks(np.array([0]), np.zeros(len(ii), int), Rs, ts, rays)
        X = X[0]
        if not np.isfinite(X).all() or np.any(np.einsum("kij,j->ki", Rs, X)[:, 2] + ts[:, 2] <= 0):
            continue
        # seen from one projection centre only (an RGB image and its thermal partner through a rig of zero base):
        # no intersection, a singular point block
        C = -np.einsum("kji,kj->ki", Rs, ts)
        if np.ptp(C, axis=0).max() <= 1e-6 * float(np.linalg.norm(X - C[0])):
            continue
        pi = int(pb.add_points(X[None, :])[0])
        for r, i in zip(rows, ii):
            pb.add_image_points(cam_block[int(rec.image_camera[i])], view[int(i)], np.array([pi]),
                                np.atleast_2d(xy[rows.index(r)]), sigma_px=manual_ties[r][3])
        out[ti] = (pi, rows)
    return out


def _manual_tie_results(res, p, tie_pts, offset, manual_ties, in_block) -> list:
    """Per manual tie point: adjusted coordinates, images and residuals (px), in the order they entered."""
    out = []
    k = offset
    v = res.image_residuals
    for ti, (pi, rows) in sorted(tie_pts.items()):
        r = v[k:k + len(rows)] if v is not None else np.full((len(rows), 2), np.nan)
        k += len(rows)
        out.append({"tie": ti, "xyz": p.points[pi].copy(), "images": [int(manual_ties[q][0]) for q in rows],
                    "residuals_px": np.asarray(r, float)})
    return out
