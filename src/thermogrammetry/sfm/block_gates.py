"""Accept/reject gates of an adjusted block and its GNSS policy: tie RMS, rotation σ against the datum, GNSS
agreement, a GNSS-vs-GCP datum offset, images added at their GNSS positions, GNSS-contradicting images pruned,
the camera attitudes of the files checked. Pure functions over a :class:`~thermogrammetry.sfm.reconstruction.Reconstruction`
and the :class:`~thermogrammetry.sfm.georef.ControlInputs` (no store, no paths)."""

from __future__ import annotations

import numpy as np

from .._memory import release_free_heap
from .reconstruction import restore_to, snapshot_of
from .selfcal_ladder import adjust_block

__all__ = ["BLOCK_RMS_GATE_PX", "GNSS_FLAG_SIGMA", "BLOCK_GNSS_FAR_SHARE", "BLOCK_ROTATION_SIGMA_DEG",
           "PRECISE_GNSS_SIGMA_M", "tie_rms", "precise_datum", "block_rotation_sigma", "gnss_far_share",
           "block_rejection", "check_gnss_offset", "unregister_images", "GNSS_RESECTION_MAX_DEG", "extend_with_gnss",
           "prune_gnss_contradicting", "ATTITUDE_FLAG_DEG", "attitude_check", "unconverged_sigma", "refuse_sigma"]


#: a block whose final tie-point reprojection RMS exceeds this is rejected (reported, not exported)
BLOCK_RMS_GATE_PX = 3.0


#: an image whose adjusted antenna position is more than this many GNSS σ from its GNSS position (on any axis) is
#: named in survey.json (``gnss_flagged``) and in the notes: its orientation or its GNSS tag is wrong
GNSS_FLAG_SIGMA = 5.0


#: a GNSS-georeferenced block whose final adjustment stops at its iteration limit with more than this share of its
#: camera centres beyond GNSS_FLAG_SIGMA from their GNSS positions is rejected: on a synthetic 40-station building
#: ring (seed 0, default options) a 20-image block 5.6 deg RMS / 19 deg max off its true rotations ended so (8 of 20
#: centres at 5-100 σ, 50 iterations); right blocks converge with their centres within ~4 σ (48-station ring, M3T)
BLOCK_GNSS_FAR_SHARE = 0.25


#: a block georeferenced on RTK-grade GNSS (median horizontal σ <= PRECISE_GNSS_SIGMA_M) or on GCPs whose cameras'
#: rotation σ (median over its images of the largest axis) exceeds this is rejected: its datum (positions nearly on a
#: line or a short arc, GCPs close together) does not fix its rotation, and the block's own shape errors then tilt
#: it by several σ. 40-station building rings (RTK σ 3/5 cm): a 4-image block on a 27 deg arc, σ 5.3 deg, 6.6-7.3
#: deg off; a 7-image block on a 63 deg arc, σ 1.5 deg, 4.9-6.7 deg off; right blocks of the same rings σ 0.2-0.7 deg
#: and 0.2-1.6 deg off; the M3T flight 0.04 deg. With coarse GNSS (σ of metres) the rotation σ is the GNSS's and is
#: reported, not gated
BLOCK_ROTATION_SIGMA_DEG = 1.0


PRECISE_GNSS_SIGMA_M = 0.10


def tie_rms(v) -> float:
    """Root mean square of the lengths of residual vectors ``v`` (K, 2) px (NaN rows skipped; NaN when empty)."""
    v = np.asarray(v, float)
    return float(np.sqrt(np.nanmean(np.sum(v**2, axis=1)))) if len(v) else float("nan")


def precise_datum(datum, ctrl, images) -> bool:
    """Whether a block's datum (:class:`~thermogrammetry.sfm.georef.Datum`) is precise enough for the rotation-σ
    gate: GCPs, or RTK-grade GNSS."""
    if not datum.from_gnss:
        return True
    if datum.from_attitude:  # the rotation about a GNSS line comes from the gimbal: its σ is reported, not gated
        return False
    s = np.asarray(ctrl.gnss_sigma, float)[np.asarray(images, np.int64)][:, :2]
    s = s[np.isfinite(s)]
    return bool(len(s)) and float(np.median(s)) <= PRECISE_GNSS_SIGMA_M


def block_rotation_sigma(fa, images) -> float:
    """Median over the block's images of their largest rotation σ (degrees); 0 when no σ was computed."""
    r = np.asarray(fa.rotation_std_deg, float)[np.asarray(images, np.int64)]
    m = np.max(r, axis=1) if len(r) else np.zeros(0)
    m = m[np.isfinite(m)]
    return float(np.median(m)) if len(m) else 0.0


def gnss_far_share(rec, images, ctrl) -> float:
    """Share of the block's images with GNSS whose adjusted centre is more than GNSS_FLAG_SIGMA from it (any axis)."""
    from .georef import gnss_misfit

    z = [float(np.max(zz)) for _, zz in gnss_misfit(rec, images, ctrl).values()]
    return float(np.mean(np.array(z) > GNSS_FLAG_SIGMA)) if z else 0.0


def block_rejection(rms: float, far: float, rot_sigma: float, result, *, pruned: bool = False,
                    stopped_at_limit: bool | None = None) -> str:
    """Why an adjusted block is not an orientation, or ``""``: its tie RMS ``rms`` (px) above
    :data:`BLOCK_RMS_GATE_PX`; a share ``far`` of its centres beyond :data:`GNSS_FLAG_SIGMA` from their GNSS above
    :data:`BLOCK_GNSS_FAR_SHARE` after the GNSS-contradicting images were left out (``pruned``) or with an adjustment
    (``result``) stopped at its iteration limit; its median rotation σ ``rot_sigma`` (degrees) above
    :data:`BLOCK_ROTATION_SIGMA_DEG` (0 when the datum is not precise enough to gate it, :func:`precise_datum`).
    ``stopped_at_limit``: whether the adjustment stopped at its iteration limit, also when adjusted again from there
    (default: ``result``'s termination)."""
    from ..results import Termination

    why = ""
    if not rms <= BLOCK_RMS_GATE_PX:
        # a block whose tie points do not fit is not an orientation: it is reported, never exported
        why = (f"reprojection RMS {rms:.2f} px after the final adjustment (> {BLOCK_RMS_GATE_PX:g} px; inconsistent "
               "tie points, e.g. repeated structure or too little texture)")
    elif far > BLOCK_GNSS_FAR_SHARE and pruned:
        # already adjusted again without the images that contradicted the GNSS: still contradicting it, converged
        # or not, the rest is no orientation either
        why = (f"after leaving out the images that contradicted their GNSS, {100 * far:.0f} % of its camera centres "
               f"are still more than {GNSS_FLAG_SIGMA:g} σ from their GNSS positions: its tie points contradict the "
               "GNSS (a wrong relative orientation)")
    elif rot_sigma > BLOCK_ROTATION_SIGMA_DEG:
        why = (f"its camera rotations have σ {rot_sigma:.1f}° (median over its images, > "
               f"{BLOCK_ROTATION_SIGMA_DEG:g}°): its GNSS/GCP datum does not fix its rotation (positions nearly on "
               "a line or a short arc)")
    elif far > BLOCK_GNSS_FAR_SHARE and (result.termination is Termination.MAX_ITERATIONS if stopped_at_limit is None
                                         else stopped_at_limit):
        # the tie points and the GNSS disagree across the block and the adjustment finds no minimum: a wrong
        # relative orientation held together by GNSS, not an orientation
        why = (f"the final adjustment did not converge ({result.reason}) and {100 * far:.0f} % of its camera "
               f"centres are more than {GNSS_FLAG_SIGMA:g} σ from their GNSS positions: its tie points contradict "
               "the GNSS (a wrong relative orientation)")
    return why


def unconverged_sigma(fa) -> str:
    """Why an accepted block's σ cannot be reported, or ``""``: its final adjustment (already adjusted again once
    from where it stopped, :func:`~thermogrammetry.sfm.selfcal_ladder.adjust_block`) did not converge. The
    covariance of a solve that stopped short of its minimum describes no estimate: σ of cameras, centres and check
    points would be reported as if it had converged."""
    from ..results import Termination

    t = fa.result.termination
    if t is Termination.CONVERGED:
        return ""
    return (f"the final adjustment did not converge ({t.value}: {fa.result.reason or 'no reason given'}), also "
            "when adjusted again from where it stopped: its σ (cameras, camera centres and rotations, check points, "
            "σ0) are not reported")


def refuse_sigma(fa, why: str) -> None:
    """Mark the σ of a final adjustment ``fa`` as not available (in place): centres', rotations' and cameras' σ NaN
    (null in the outputs), no covariance (check points then carry none), ``fa.sigma_refused = why``."""
    fa.center_std = np.full_like(np.asarray(fa.center_std, float), np.nan)
    fa.rotation_std_deg = np.full_like(np.asarray(fa.rotation_std_deg, float), np.nan)
    fa.covariance = None
    res = fa.result
    res.camera_std = [np.full_like(np.asarray(c, float), np.nan) for c in (res.camera_std or [])]
    fa.sigma_refused = why


def check_gnss_offset(rec, xy, images, ctrl, self_cal, focal_known=None, **kw) -> tuple[dict | None, list[str]]:
    """Look for a constant GNSS-vs-GCP datum offset in a GNSS-placed block with >= 3 GCPs
    (:func:`~thermogrammetry.sfm.georef.gnss_offset`): one adjustment on the GCPs alone (GNSS σ × 1000; its
    self-calibration on the ladder of :func:`~thermogrammetry.sfm.selfcal_ladder.adjust_block`), the
    block restored afterwards; the GNSS positions (and the block's start) are shifted by the significant axes.
    Returns the report entry and notes."""
    from dataclasses import replace as dc_replace

    from .georef import GNSS_OFFSET_MIN_GCPS, apply_similarity, final_adjustment, gnss_offset, similarity_start

    images = np.asarray(images)
    in_block = set(images.tolist())
    gcps = {gi for (i, gi, xy_, s_) in ctrl.gcp_obs if i in in_block}
    if len(gcps) < GNSS_OFFSET_MIN_GCPS:
        return None, []
    if len(images) > 2500:  # the centres' σ need the covariance, which large blocks skip (as the final adjustment does)
        return None, [f"GNSS against the GCPs: not checked for a datum offset ({len(images)} images: no covariance "
                      "above 2500)"]
    snap = snapshot_of(rec)
    weak = dc_replace(ctrl, gnss_sigma=ctrl.gnss_sigma * 1e3)
    try:
        # GCP measurement blunders first, on the block with its cameras held: with a datum of a few GCPs and
        # self-calibration, a wrong measurement (a GCP "measured" where it is not) can bend the block until it fits
        # within the rejection threshold (seen: focal length -8 %, the GNSS offset 4.8 m off in Z)
        fa0 = final_adjustment(rec, xy, images, weak, self_calibrate=(), compute_covariance=False, **kw)
        bad = {(int(i), gid) for i, gid, _e in fa0.gcp_rejected}
        fa0 = None  # (its problem and residuals) not held through the next adjustment
        restore_to(rec, snap)
        if bad:
            weak = dc_replace(weak, gcp_obs=[o for o in weak.gcp_obs if (int(o[0]), ctrl.gcp_ids[o[1]]) not in bad])
        # with the self-calibration ladder and its focal-length guard (``focal_known``): a focal length run away on a
        # flat block (a projective twin) would move the heights, and the GNSS with them
        fa, _, _ = adjust_block(rec, xy, images, weak, self_cal, focal_known=focal_known, compute_covariance=True, **kw)
        # a focal length that is not a user's calibration (the lens's nominal value, held or self-calibrated against
        # it) leaves the flying height, hence the Z offset, as uncertain as itself on flat ground
        fz = _focal_height_std(rec, images, ctrl, focal_known, self_cal)
        off = gnss_offset(rec.centers()[images], fa.center_std[images], ctrl.gnss_xyz[images], ctrl.gnss_sigma[images],
                          extra_std_m=(0.0, 0.0, fz)) if fa.result.success else None
    finally:
        restore_to(rec, snap)
    if off is None:
        return None, ["GNSS against the GCPs: not checked for a datum offset (the adjustment on the GCPs alone "
                      "did not give centres with σ)"]
    shift = np.where(off.significant, off.offset_m, 0.0)  # added to the GNSS: GCP datum = GNSS + shift
    fmt = lambda v: "(" + ", ".join(f"{x:+.3f}" for x in v) + ")"  # noqa: E731
    entry = {"offset_m": off.offset_m.tolist(), "std_m": off.std_m.tolist(), "n_gcps": len(gcps),
             "applied_m": shift.tolist(),
             "meaning": "GCP datum minus GNSS datum, from the camera centres of an adjustment on the GCPs alone"}
    if not off.significant.any():
        return entry, [f"GNSS against {len(gcps)} GCPs: no datum offset (GCP − GNSS {fmt(off.offset_m)} m "
                       f"± {fmt(off.std_m)} m)"]
    have = np.all(np.isfinite(ctrl.gnss_xyz[images]), axis=1)
    ctrl.gnss_xyz[images[have]] += shift
    S, _, _ = similarity_start(rec, images, ctrl)
    if S is not None:
        apply_similarity(rec, images, S)
    axes = ", ".join(a for a, f in zip("XYZ", off.significant) if f)
    return entry, [f"GNSS positions differ from the {len(gcps)} GCPs by a constant {fmt(off.offset_m)} m ± "
                   f"{fmt(off.std_m)} m (GCP − GNSS): a datum or height-reference difference (ellipsoidal vs geoid or "
                   f"national heights, take-off altitude) or an antenna offset; the GNSS positions are shifted in "
                   f"{axes} by {fmt(shift)} m before the adjustment"]


def _focal_height_std(rec, images, ctrl, focal_known, self_cal) -> float:
    """σ (m) of the flying height from the focal length's prior: the largest relative σ of the block's cameras'
    lens focal lengths (:class:`~thermogrammetry.sfm.selfcal_ladder.FocalKnown` ``priors()``) whose focal length
    the survey was asked to self-calibrate (``self_cal``), times the median height of the camera centres above the
    median GCP height; 0 without such a camera (a camera file held fixed)."""
    pri = focal_known.priors() if hasattr(focal_known, "priors") else {}
    cams = {int(c) for c in rec.image_camera[np.asarray(images)]}

    def asked(c):
        want = self_cal.get(c, ()) if isinstance(self_cal, dict) else (self_cal or ())
        return "fx" in {str(n).lower() for n in want}

    rel = [sg / f for c, (f, sg) in pri.items() if c in cams and f > 0 and asked(c)]
    if not rel or not len(ctrl.gcp_xyz):
        return 0.0
    h = float(np.median(rec.centers()[images][:, 2]) - np.median(np.asarray(ctrl.gcp_xyz)[:, 2]))
    return float(max(rel) * abs(h)) if np.isfinite(h) else 0.0


def unregister_images(rec, images) -> None:
    """Drop the orientation of ``images`` (their block was rejected) and the points only they determined (in their
    block's frame, not the CRS's), keeping their status reasons."""
    images = np.asarray(images, np.int64)
    if not len(images):
        return
    tr = rec.tracks
    rec.registered[images] = False
    rec.component[images] = -1
    for i in images:
        rec.status[i].registered, rec.status[i].component = False, -1
    touched = np.unique(tr.track[np.isin(tr.image, images)])
    live = rec.obs_valid & rec.registered[tr.image]
    cnt = np.bincount(tr.track[live], minlength=len(rec.points))
    rec.points[touched[cnt[touched] < 2]] = np.nan


#: an image is added to a georeferenced block at its GNSS position (rotation-only resection) only when its GNSS σ
#: seen from the block's points is at most this angle (degrees): RTK on a UAV or a pole, not metre-level GNSS
GNSS_RESECTION_MAX_DEG = 1.0


def extend_with_gnss(rec, xy, images, ctrl, names, ci, self_cal, adjust_kw, options, adjusted, rms, far):
    """Images the orientation could not add (too few tie points to the block for a resection) placed at their
    GNSS position and turned to the block's points (:func:`~thermogrammetry.sfm.reconstruction.register_with_known_centres`),
    then the block adjusted again with them. Kept when that adjustment converges with a reprojection RMS and a
    GNSS agreement no worse than the block's own and the added images' rotations have σ below 2°; otherwise ``rec``
    is restored. ``options``: the :class:`~thermogrammetry.sfm.reconstruction.ReconstructionOptions` of the
    resection. ``adjusted``: the block's ``(fa, cal_used, cal_steps)`` without them. Returns ``(images, fa,
    cal_used, cal_steps, notes)``: the block's own when nothing was added or kept.

    Measured on the 48-station synthetic building ring (seed 3, occluder at 7 m, RTK σ 3/5 cm), where the stations
    T47-T02 share 20-30 verified matches with their neighbours but too few oriented points for PnP (10): see
    benchmarks/README.md (survey_building.py).
    """
    from ..results import Termination
    from .reconstruction import register_with_known_centres

    images = np.asarray(images, np.int64)
    fa, cal_used, cal_steps = adjusted
    same = (images, fa, cal_used, cal_steps, [])
    cand = np.nonzero(~rec.registered & np.all(np.isfinite(ctrl.gnss_xyz), axis=1))[0]
    if len(cand) == 0:
        return same
    # the block's typical camera-to-point distance: a GNSS σ that is more than GNSS_RESECTION_MAX_DEG there is too coarse
    tr = rec.tracks
    ob = np.nonzero(rec.obs_valid & np.isin(tr.image, images) & np.isfinite(rec.points[tr.track]).all(1))[0]
    if len(ob) == 0:
        return same
    ob = ob[:: max(1, len(ob) // 20000)]
    dist = float(np.median(np.linalg.norm(rec.points[tr.track[ob]] - rec.centers()[tr.image[ob]], axis=1)))
    sig = np.nanmax(ctrl.gnss_sigma[cand], axis=1)
    cand = cand[sig <= np.tan(np.radians(GNSS_RESECTION_MAX_DEG)) * dist]
    if len(cand) == 0:
        return same
    snap = snapshot_of(rec)
    added, _ = register_with_known_centres(rec, xy, images, ctrl.gnss_xyz, cand, options=options)
    if len(added) == 0:
        restore_to(rec, snap)
        return same
    both = np.concatenate([images, added])
    fa2, cal2, steps2 = adjust_block(rec, xy, both, ctrl, self_cal, compute_covariance=len(both) <= 2500, **adjust_kw)
    release_free_heap()
    v = fa2.tie_residuals
    rms2 = tie_rms(v)
    far2 = gnss_far_share(rec, both, ctrl)
    rot = (np.asarray(fa2.rotation_std_deg, float)[added] if fa2.rotation_std_deg is not None
           else np.full((len(added), 3), np.nan))
    nm = ", ".join(names[i] for i in added)
    why = ""
    if not fa2.result.success or fa2.result.termination is Termination.MAX_ITERATIONS:
        why = f"the adjustment with them did not converge ({fa2.result.reason or fa2.result.termination.value})"
    elif {c: tuple(v) for c, v in cal2.items()} != {c: tuple(v) for c, v in cal_used.items()}:
        why = "the block's self-calibration would step down with them"
    elif not rms2 <= max(rms * 1.1, rms + 0.05):
        why = f"reprojection RMS {rms2:.2f} px with them ({rms:.2f} px without)"
    elif far2 > far:
        why = (f"{100 * far2:.0f} % of the centres beyond {GNSS_FLAG_SIGMA:g} σ of their GNSS with them "
               f"({100 * far:.0f} % without)")
    elif not np.all(np.nanmax(rot, axis=1) < 2.0):
        why = f"rotation σ up to {np.nanmax(rot):.1f}° for the added images"
    else:
        # each added image must fit as the block does: enough observations left, residuals like the block's
        from .reconstruction import MIN_CENTRE_RESECTION_POINTS

        for i in added:
            vi = v[fa2.tie_obs_image == i] if len(v) else np.zeros((0, 2))
            ri = tie_rms(vi)
            if len(vi) < MIN_CENTRE_RESECTION_POINTS or not ri <= max(2.0 * rms2, 1.0):
                why = f"{names[i]} keeps {len(vi)} tie observations at {ri:.2f} px RMS (the block {rms2:.2f} px)"
                break
    if why:
        restore_to(rec, snap)
        return (*same[:4], [f"block {ci + 1}: {nm} placed at their GNSS positions and turned to the block's points, "
                            f"not kept: {why}"])
    return both, fa2, cal2, steps2, [f"block {ci + 1}: {len(added)} image(s) with too few tie points to the block for "
                                     f"a resection added at their GNSS positions (rotation from the directions to the "
                                     f"block's points, then the block adjusted again): {nm}"]


def prune_gnss_contradicting(rec, pre, images, ctrl, names, ci, why):
    """Images of a block rejected for contradicting its GNSS that no similarity of the block (as the orientation
    left it, ``pre``) puts near their GNSS positions (:func:`~thermogrammetry.sfm.georef.gnss_consensus`).

    When there are such images and the rest (>= 4 images, >= half of the block) agree, ``rec`` is restored to
    ``pre``, those images are taken out of the block with their reason, and ``(kept images, notes)`` is returned;
    otherwise ``(None, [])`` and ``rec`` is left as it is.
    """
    from .georef import gnss_consensus

    images = np.asarray(images, np.int64)
    C = -np.einsum("nji,nj->ni", pre["R"][images], pre["t"][images])
    cons = gnss_consensus(C, ctrl.gnss_xyz[images], ctrl.gnss_sigma[images])
    if cons is None:
        return None, []
    drop = ~cons.inliers
    n_keep = int((~drop).sum())
    if not drop.any() or n_keep < 4 or n_keep < 0.5 * len(images):
        return None, []
    restore_to(rec, pre)
    for i, r in zip(images[drop], cons.residuals_m[drop]):
        rec.registered[i] = False
        rec.component[i] = -1
        st = rec.status[i]
        st.registered, st.component = False, -1
        dist = f"{r:.2f} m" if np.isfinite(r) else "an unknown distance (no GNSS)"
        st.reason = (f"left out of block {ci + 1}: after its orientation this image's centre is {dist} from its GNSS "
                     f"position where the other {n_keep} images agree with theirs within {cons.tolerance_m:.2f} m "
                     "(a wrong resection)")
    gone = ", ".join(names[i] for i in images[drop])
    return images[~drop], [f"block {ci + 1}: {why}; {int(drop.sum())} image(s) whose centres the block put "
                           f"{', '.join(f'{r:.2f}' for r in cons.residuals_m[drop])} m from their GNSS while the other "
                           f"{n_keep} agree within {cons.tolerance_m:.2f} m (wrong resections) left out and the block "
                           f"adjusted again: {gone}"]


#: an oriented image whose attitude in its file differs from its adjusted rotation by more than this (degrees) beyond
#: the block's common difference is named (``survey.json`` ``attitude.flagged``): gimbal attitudes are good to ~1-2°
#: (the M3T flight: 0.4-2.2°), a wrong resection is tens of degrees off. A common difference above it (every image) is
#: a convention or mounting the files do not describe, said once, not blamed on each image
ATTITUDE_FLAG_DEG = 10.0


def attitude_check(rec, fa_all, ctrl, names, status) -> dict:
    """Adjusted rotations of the georeferenced blocks against the camera attitudes in the files (DJI gimbal angles):
    per image ``attitude_deviation_deg`` in ``status``; summary n, median, RMS, max (degrees), ``mean_deg`` the mean of
    the world-frame rotation vectors of ``R_adjᵀ R_att`` (CRS x, y, z ~ east, north, up: a gimbal's common tilt), and
    the images whose ``R_adjᵀ R_att`` is more than :data:`ATTITUDE_FLAG_DEG` from the block's mean rotation (chordal
    mean), with that distance. Empty without attitudes."""
    from ..geometry.rotations import axis_angle_from_matrix, matrix_from_axis_angle, mean_rotation
    from .georef import attitude_images

    rows = []
    for ci, images, fa, datum, geo in fa_all:
        if not geo:
            continue
        for i in attitude_images(ctrl, images):
            # world-frame rotation E with R_att = R_adj E
            w = np.degrees(axis_angle_from_matrix(rec.R[i].T @ ctrl.attitude[i]))
            status[i]["attitude_deviation_deg"] = float(np.linalg.norm(w))
            rows.append((int(i), w))
    if not rows:
        return {}
    W = np.array([w for _, w in rows])
    dev = np.linalg.norm(W, axis=1)
    E = matrix_from_axis_angle(np.radians(W))
    rel = np.degrees(np.linalg.norm(axis_angle_from_matrix(E @ mean_rotation(E).T), axis=1))
    return {"n": len(rows), "median_deg": float(np.median(dev)), "rms_deg": float(np.sqrt(np.mean(dev**2))),
            "max_deg": float(dev.max()), "mean_deg": [float(x) for x in W.mean(axis=0)],
            "flagged": [{"image": names[i], "deviation_deg": float(dev[k]), "from_common_deg": float(rel[k])}
                        for k, (i, w) in enumerate(rows) if rel[k] > ATTITUDE_FLAG_DEG]}
