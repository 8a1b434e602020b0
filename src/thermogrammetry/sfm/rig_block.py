"""Rig blocks of the survey's final adjustment: a refused rig undone, a block without datum scaled by the rig
baseline, R*, t by image registration when the ties cannot estimate it (:mod:`thermogrammetry.sfm.rigreg`).
Pure functions over a :class:`~thermogrammetry.sfm.reconstruction.Reconstruction` (frames through a callable)."""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from .._memory import release_free_heap
from .reconstruction import restore_to, snapshot_of
from .selfcal_ladder import adjust_block

__all__ = ["rig_own_before", "rig_refuse", "rig_by_registration", "scaled_focal_params", "rig_scale_local"]


def rig_own_before(rec, rigv, images, manual_obs) -> dict:
    """Own observations per rig view before the adjustment: valid observations of triangulated points + manual."""
    from .rig import own_observations

    tr = rec.tracks
    ok = rec.obs_valid & np.isfinite(rec.points[tr.track]).all(1)
    return own_observations(rigv, images, tr.image[ok], manual_obs or ())


def rig_refuse(rec, snap, rigv, block_images, names, why, ci, S=None) -> np.ndarray:
    """Undo the rig views of a block; returns its images: the RGB block plus the thermal frames that were oriented
    on their own in the same component (they keep that orientation, moved by the block's datum similarity ``S``
    like the block). Other thermal partners: reason set."""
    restore_to(rec, snap)
    block_images = np.asarray(block_images, np.int64)
    comp = int(rec.component[block_images[0]]) if len(block_images) else -1
    keep = []
    for s_, m_ in sorted(rigv.master.items()):
        if m_ not in set(block_images.tolist()):
            continue
        if rec.registered[s_] and int(rec.component[s_]) == comp:
            keep.append(s_)
        else:
            rec.status[s_].reason = (f"rig R*, t not estimated in block {ci + 1} ({why}); no orientation of its own "
                                     f"(partner {names[m_]})")
    if keep and S is not None:  # the block was moved to the datum without them (plan_rig_blocks took them out)
        k = np.asarray(keep, np.int64)
        Cn = S(rec.centers()[k])
        rec.R[k] = rec.R[k] @ S.R.T
        rec.t[k] = -np.einsum("nij,nj->ni", rec.R[k], Cn)
    return np.unique(np.concatenate([block_images, np.asarray(keep, np.int64)]))


def rig_by_registration(read_frame: Callable, rec, rig, master: dict, names: list, comps: list, *,
                         thermal_camera_given: bool, xy, ctrl, self_cal, adjust_kw: dict) -> tuple:
    """R*, t by image registration where the block cannot estimate it from tie points (:mod:`..sfm.rigreg`).

    Runs when the rig file asks for an estimate and fewer than ``RIG_EST_MIN_FRAMES`` thermal images were
    oriented together with their RGB partners in the largest block that holds RGB partners (low-texture thermal
    frames: their ties do not reach the RGB block). The RGB images of that block are first adjusted on their own
    (self-calibrating, in the model frame: the registration measures the thermal camera against the RGB camera's
    rays, so these must be close to the final ones -- with the orientation's RGB focal length the thermal one came
    out 2.5 % off on the frescoes); the pairs are sampled in that state, ``rec`` is put back as the orientation left
    it (the final adjustment starts from there with its datum), and the pairs are registered on the edges both bands
    see; when that pre-adjustment does not converge below σ0 3 (a 12-frame nadir block without datum: σ0 518) the
    orientation's state is sampled instead. An accepted estimate is held fixed in the final adjustment (``RigFile.registered``), and so is the thermal camera, its focal length scaled by
    the estimated factor unless it was given (a few thermal ties of their own must not self-calibrate it: k1 = -1.4
    from 58 observations on the frescoes). A refused estimate changes nothing (the reason is in the notes and in
    ``survey.json`` ``rig.registration``). At most ``RigRegistrationOptions.max_pairs`` pairs, evenly over the block.

    Returns (rig to use, registration summary or None, notes, self-calibration to use).
    """
    from dataclasses import replace as dc_replace

    from ..geometry.rotations import axis_angle_from_matrix
    from .rig import RIG_EST_MIN_FRAMES, _co_pairs, t_with_sigma_text
    from .rigreg import RigRegistrationOptions, pair_samples, register_rig

    if not rig.estimate or not master:
        return rig, None, [], self_cal
    block = next((c for c in comps if any(m in set(np.asarray(c).tolist()) for m in master.values())), None)
    if block is None:
        return rig, None, [], self_cal
    co = _co_pairs(rec, master, block)
    if len(co) >= RIG_EST_MIN_FRAMES:
        return rig, None, [], self_cal
    t0 = time.perf_counter()
    inb = set(np.asarray(block).tolist())
    pairs_im = [(s, m) for s, m in sorted(master.items(), key=lambda x: x[1]) if m in inb and rec.registered[m]]
    if not pairs_im:
        return rig, None, [], self_cal
    rgb_block = np.array([i for i in np.asarray(block).tolist() if i not in master], np.int64)
    snap = snapshot_of(rec)
    fa0, _, steps0 = adjust_block(rec, xy, rgb_block, ctrl, self_cal, georeferenced=False, compute_covariance=False,
                                   **adjust_kw)
    pre = [f"rig: the {len(rgb_block)} RGB image(s) adjusted on their own before the registration "
           f"({fa0.result.termination.value}, σ0 {float(fa0.result.sigma0):.2f})"] + [f"rig: {x}" for x in steps0]
    release_free_heap()
    if fa0.result.termination.value != "converged" or not (float(fa0.result.sigma0) < 3.0):
        # (a 12-frame nadir block without datum: stopped at its iteration limit with σ0 518) sampled in the
        # orientation's state instead
        restore_to(rec, snap)
        pre.append("rig: the registration samples the orientation's state instead (that adjustment did not converge "
                   "to a σ0 below 3)")
    tcam_k = int(rec.image_camera[pairs_im[0][0]])
    tcam = rec.cameras[tcam_k]
    obs_img, obs_trk = rec.tracks.image, rec.tracks.track
    usable_obs = rec.obs_valid & np.isfinite(rec.points).all(axis=1)[obs_trk]
    samples, why = [], []
    reg_opt = RigRegistrationOptions(estimate_focal=not thermal_camera_given)
    if len(pairs_im) > reg_opt.max_pairs:  # evenly over the block (in image order)
        pick = np.unique(np.round(np.linspace(0, len(pairs_im) - 1, reg_opt.max_pairs)).astype(int))
        pre.append(f"rig: {len(pick)} of {len(pairs_im)} pairs registered (evenly over the block)")
        pairs_im = [pairs_im[k] for k in pick]
    for s_, m_ in pairs_im:
        sel = usable_obs & (obs_img == m_)
        Xc = rec.points[obs_trk[sel]] @ rec.R[m_].T + rec.t[m_]
        p_, w_ = pair_samples(names[m_], read_frame(names[m_]), read_frame(names[s_]),
                              rec.cameras[int(rec.image_camera[m_])], tcam, Xc)
        samples.append(p_)
        if w_:
            why.append(w_)
    # the block goes back to the orientation's state (the final adjustment starts from it, with its datum)
    restore_to(rec, snap)
    del snap
    reg = register_rig(samples, tcam, R0=rig.R, options=reg_opt)
    summary = {**reg.summary(), "seconds": round(time.perf_counter() - t0, 2), "skipped_pairs": why,
               "ncc": {k: round(v, 4) for k, v in reg.ncc.items()},
               "pair_offsets_deg": {k: round(v, 3) for k, v in reg.pair_offsets_deg.items()}}
    head = (f"rig: {len(co)} thermal image(s) oriented with their RGB partners (< {RIG_EST_MIN_FRAMES}): R*, t by "
            f"image registration of {len(pairs_im)} pair(s)")
    if not reg.success:
        return rig, summary, pre + [f"{head} refused: {reg.reason}"], self_cal
    notes = pre + [f"{head}: {len(reg.pairs_used)} pair(s) agree, rotation {np.degrees(np.linalg.norm(axis_angle_from_matrix(reg.R))):.2f} deg "
             f"(σ {', '.join(f'{x:.3f}' for x in reg.rotation_std_deg)} deg, spread {reg.spread_deg:.2f} deg), "
             f"thermal focal x {reg.focal_scale:.4f}"
             + (f", t {t_with_sigma_text(reg.t, reg.translation_std)} model units"
                if reg.t_determined else ", t held (pairs at one depth)")
             + "; held fixed in the adjustment"]
    if not thermal_camera_given and abs(reg.focal_scale - 1.0) > 1e-9:
        K = tcam.K
        rec.cameras[tcam_k] = tcam.with_params(scaled_focal_params(tcam, reg.focal_scale))
        notes.append(f"rig: thermal focal length {np.sqrt(K[0, 0] * K[1, 1]):.1f} -> "
                     f"{np.sqrt(K[0, 0] * K[1, 1]) * reg.focal_scale:.1f} px from the registration, held fixed")
    n_cams = len(rec.cameras)
    self_cal = {k: (() if k == tcam_k else (self_cal.get(k, ()) if isinstance(self_cal, dict) else self_cal))
                for k in range(n_cams)}
    return dc_replace(rig, R=reg.R, t=reg.t, estimate=False, registered=summary), summary, notes, self_cal


def scaled_focal_params(camera, scale: float) -> np.ndarray:
    """The camera's parameter vector with its focal length(s) multiplied by ``scale``."""
    p = np.array(camera.params, float)
    for k, n in enumerate(camera.param_names):
        if n in ("fx", "fy", "c_mm"):
            p[k] *= scale
    return p


def rig_scale_local(rec, images, rig, master, rigv) -> list:
    """A block without datum and a rig with a given baseline: scale the model to metres by the baseline of the
    thermal images oriented together with their partners (else the adjustment's rig constraint sets it)."""
    from ..geometry import Similarity
    from .georef import apply_similarity
    from .rig import _co_pairs, relative_from_poses

    if rig.R is None or np.linalg.norm(rig.t) <= 0:
        return []
    co = _co_pairs(rec, master, images)
    if not co:
        return ["rig: no datum and no thermal image oriented with its partner: the scale comes from the rig baseline "
                "in the adjustment alone"]
    _, t_m, _ = relative_from_poses(rec.R[[m for _, m in co]], rec.t[[m for _, m in co]], rec.R[[s for s, _ in co]],
                                    rec.t[[s for s, _ in co]])
    if not np.linalg.norm(t_m) > 0:
        return []
    k = float(np.linalg.norm(rig.t) / np.linalg.norm(t_m))
    apply_similarity(rec, images, Similarity(k, np.eye(3), np.zeros(3)))
    return [f"rig: no datum: the model is scaled by {k:.4g} so that {len(co)} co-oriented pair(s) match the rig baseline "
            f"{np.linalg.norm(rig.t):.3f} m"]
