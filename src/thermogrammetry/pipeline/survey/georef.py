"""The ``georef`` step: every block georeferenced, adjusted with a self-calibration it can carry, gated, extended
at GNSS positions; check points intersected; every output written (:mod:`.outputs`)."""

from __future__ import annotations

import time

import numpy as np

from ..._memory import release_free_heap
from ...sfm.block_gates import (BLOCK_RMS_GATE_PX, BLOCK_ROTATION_SIGMA_DEG, GNSS_FLAG_SIGMA, block_rejection,
                                block_rotation_sigma, check_gnss_offset, extend_with_gnss, gnss_far_share, precise_datum,
                                prune_gnss_contradicting, refuse_sigma, tie_rms, unconverged_sigma, unregister_images)
from ...sfm.reconstruction import restore_to, snapshot_of
from ...sfm.rig_block import rig_by_registration, rig_own_before, rig_refuse, rig_scale_local
from ...sfm.selfcal_ladder import FocalKnown, adjust_block, calibration_choice
from ...store import ProjectStore
from .controls import _gnss_xyz, _read_manual_ties, _read_markers
from .camera_start import _camera_start, _focal_from_exif, _focal_prior, _focal_prior_fov, _focal_prior_sigma  # noqa: F401
from .inputs import _attitudes
from .lowtexture import _low_texture_self_calibration, _low_texture_sequence_used
from .options import SurveyInput, SurveyOptions
from .outputs import _write_outputs
from .store import SurveyStore, _load_reconstruction, _read_frame, _tie_xy


def step_georef(project: ProjectStore, inp: SurveyInput, opt: SurveyOptions, camera=None, progress=None) -> dict:
    """Georeference the largest block(s), adjust, intersect check points, write every output."""
    from ...results import Termination
    from ...sfm.georef import MIN_ATTITUDE_IMAGES, apply_similarity, attitude_images, similarity_start

    t0 = time.perf_counter()
    inputs = SurveyStore(project).load_inputs()
    names = [im["name"] for im in inputs["images"]]
    release_free_heap()  # (what the steps before left in the heap)
    rec, meta = _load_reconstruction(project)
    xy = [_tie_xy(project, n) for n in names]
    ctrl, crs, notes, c_ids, t_ids, t_obs = _controls(inp, opt, inputs, names)
    comps = rec.components()
    results = []
    oriented = np.zeros(len(names), bool)
    second_pass: list = []  # accepted GNSS blocks that may take images left over at the end (extend_with_gnss)
    rejected_at: dict = {}  # index in results of a rejected block -> its images (the second pass may move them)
    fa_all = []
    rig_master, rig_enabled, rig_out, tie_out = {}, {}, [], []
    rig_only: dict[int, str] = {}  # oriented rig views without observations of their own -> reason
    self_cal, focal_known, nts = _self_calibration(project, inp, opt, camera, inputs, rec, meta)
    notes += nts
    if inp.rig is not None:
        from ...sfm.rig import (RIG_MIN_OWN_OBSERVATIONS, attach_rig_images, own_observations, pair_rig_images,
                               plan_rig_blocks, rig_estimate_accepted, rig_estimation_evidence, rig_report, start_rig)

        rig_master, nts, rig_unpaired = pair_rig_images(inp.rig, inputs["images"])
        rig_used, rig_reg, nts_reg, self_cal = rig_by_registration(
            lambda nm: _read_frame(project, nm), rec, inp.rig, rig_master, names, comps, thermal_camera_given=camera is not None, xy=xy, ctrl=ctrl,
            self_cal=self_cal, adjust_kw=dict(focal_known=focal_known, tie_sigma_px=opt.tie_sigma_px,
                                              max_error_px=opt.reconstruction.max_error_px))
        nts += nts_reg
        comps, rig_enabled, nts2 = plan_rig_blocks(rec, rig_used, rig_master, comps)
        notes += nts + nts2 + [f"rig: {len(rig_master)} RGB/thermal pair(s) from {inp.rig.source}"]
    lt_seq = _low_texture_sequence_used(project)
    lt_verdict = SurveyStore(project).load_low_texture()
    if lt_verdict.get("why"):
        notes.append(f"{lt_verdict['why']}; " + ("its frames are not oriented" if lt_verdict.get("kept") else
                                                 "the primary matching's orientation is kept (what --low-texture off gives)"))
    queue = list(enumerate(comps))
    pruned_blocks: set[int] = set()  # blocks already adjusted again without their GNSS-contradicting images
    attitude_blocks: set[int] = set()  # blocks adjusted again with the camera attitudes (their GNSS left a rotation open)
    while queue:
        ci, images = queue.pop(0)
        if len(images) == 0:
            continue
        S, datum, nts = similarity_start(rec, images, ctrl, attitude_line=ci in attitude_blocks)
        notes += [f"block {ci + 1}: {x}" for x in nts]
        geo = S is not None
        # the block as the orientation left it (for :func:`prune_gnss_contradicting` and a second adjustment with the
        # camera attitudes): GNSS blocks only, not with a rig (similarity_start changes nothing in ``rec``)
        pre = snapshot_of(rec) if geo and datum.from_gnss and ci not in rig_enabled else None
        if not geo and ci > 0:
            # a second block without datum cannot be placed with the first: reported, not exported
            for i in images:
                rec.status[i].reason = f"in block {ci + 1} ({len(images)} images) that has no GNSS/GCP datum and no tie to block 1"
            continue
        rigv = None
        if ci in rig_enabled:
            rigv, nts = start_rig(rec, rig_used, rig_master, images, S.scale if geo else 1.0)
            notes += [f"block {ci + 1}: {x}" for x in nts]
        gnss_off = None
        if geo:
            apply_similarity(rec, images, S)
            if datum.from_gnss and ctrl.gcp_obs and inp.rig is None:
                gnss_off, nts = check_gnss_offset(rec, xy, images, ctrl, self_cal, focal_known=focal_known,
                                                  tie_sigma_px=opt.tie_sigma_px,
                                             max_error_px=opt.reconstruction.max_error_px, georeferenced=True)
                notes += [f"block {ci + 1}: {x}" for x in nts]
        elif rigv is not None:
            notes += [f"block {ci + 1}: {x}" for x in rig_scale_local(rec, images, inp.rig, rig_master, rigv)]
        block_images, snap, refused = images, None, ""
        if rigv is not None:
            snap = snapshot_of(rec)
            images, nts = attach_rig_images(rec, images, rigv, xy, max_error_px=opt.reconstruction.max_error_px,
                                            min_tri_angle_deg=opt.reconstruction.min_tri_angle_deg)
            notes += [f"block {ci + 1}: {x}" for x in nts]
            if not rigv.fixed:
                # R*, t estimated only from enough evidence (sfm.rig: >= 3 thermal frames with own observations,
                # spread over the block); a guess held at its start is not an orientation
                ok, why = rig_estimation_evidence(rec, rigv, images, rig_own_before(rec, rigv, images, t_obs))
                refused = "" if ok else why
        fa = None
        # the final adjustment's options for this block (the images and the rig may change below)
        adjust_kw = dict(focal_known=focal_known, attitude_priors=geo and datum.from_attitude, tie_sigma_px=opt.tie_sigma_px,
                         max_error_px=opt.reconstruction.max_error_px, georeferenced=geo, manual_ties=t_obs or None)
        # a block at its iteration limit whose centres contradict their GNSS is pruned below (wrong resections), not
        # adjusted on from where it stopped (the same test decides the pruning there)
        prunable = (lambda fa_: pre is not None and ci not in pruned_blocks  # noqa: B023 (called at once)
                    and (gnss_far_share(rec, images, ctrl) > 0 or bool(fa_.gnss_rejected))) if geo else None
        if rigv is not None and not refused:
            fa, cal_used, cal_steps = adjust_block(rec, xy, images, ctrl, self_cal, rigv=rigv, limit_handled=prunable,
                                                    compute_covariance=len(images) <= 2500, **adjust_kw)
            if not rigv.fixed:
                ok, why = rig_estimate_accepted(rigv, fa)
                refused = "" if ok else why
                if refused:
                    notes += [f"block {ci + 1}: {x}" for x in fa.notes]
        if refused:
            # estimation refused: the block is adjusted without the rig; thermal frames oriented on their own in
            # this block stay (as plain images), the others are not oriented
            images = rig_refuse(rec, snap, rigv, block_images, names, refused, ci, S if geo else None)
            notes.append(f"block {ci + 1}: rig: R*, t not estimated: {refused}; the thermal frames of this block are "
                         "oriented only where they have an orientation of their own")
            rig_out.append({"block": ci + 1, "estimated": False, "refused": refused, "start": rigv.start,
                            "pairs": len(rigv.master)})
            rigv = None
            fa = None
        if fa is None:
            fa, cal_used, cal_steps = adjust_block(rec, xy, images, ctrl, self_cal, rigv=rigv, limit_handled=prunable,
                                                    compute_covariance=len(images) <= 2500, **adjust_kw)
        release_free_heap()
        notes += [f"block {ci + 1}: {x}" for x in fa.notes]
        notes += [f"block {ci + 1}: {x}" for x in cal_steps]
        if cal_steps and cal_steps[-1].startswith("with the camera held fixed"):
            if pre is not None and ci not in pruned_blocks and rigv is None:
                # a few wrongly resected images (far from their GNSS after the orientation) can make the solve fail
                # (their points' normal blocks near-singular): the block without them is adjusted once more
                if _prune_requeue(rec, pre, images, ctrl, names, ci, f"the final adjustment failed ({cal_steps[-1]})",
                                  notes, pruned_blocks, queue):
                    fa = None
                    release_free_heap()
                    continue
            # not even the orientation alone is determined: not an orientation
            why = (f"in block {ci + 1} ({len(images)} images) rejected: its geometry does not determine the "
                   f"orientation ({cal_steps[-1]})")
            for i in images:
                rec.status[i].reason = why
            results.append({"block": ci + 1, "images": len(images), "datum": str(datum), "rejected": why,
                            "self_calibration_steps": cal_steps})
            continue
        if lt_seq and cal_steps and any(str(meta["camera_ids"][int(rec.image_camera[i])]).startswith("thermal") for i in images):
            # a tracked low-texture sequence self-calibrates only k1, k2 (+ fx, fy without an EXIF focal length); a
            # block that cannot carry even that is in conflict with a physical camera: the windowed synthetic facade's
            # wrong block (25 deg off) asked for fy/fx = 0.87 at every rung
            why = (f"in block {ci + 1} ({len(images)} images) rejected: a low-texture sequence's block whose limited "
                   f"self-calibration was refused ({cal_steps[0]})")
            for i in images:
                rec.status[i].reason = why
            notes.append(f"block {ci + 1}: {why.split(' rejected: ')[1]}")
            results.append({"block": ci + 1, "images": len(images), "datum": str(datum), "rejected": why,
                            "self_calibration_steps": cal_steps})
            continue
        if rigv is not None:
            own = own_observations(rigv, images, fa.tie_obs_image,
                                   [(mt_i,) for mt in fa.manual_ties for mt_i in mt["images"]])
            for s_, n_ in own.items():
                if n_ < RIG_MIN_OWN_OBSERVATIONS:
                    rig_only[s_] = ("pose from the rig only (no own tie points)" if n_ == 0 else
                                    f"pose from the rig only ({n_} own observation(s) < {RIG_MIN_OWN_OBSERVATIONS})")
            rig_out.append({"block": ci + 1, **rig_report(rigv, geo),
                            "own_observations": {names[s_]: n_ for s_, n_ in sorted(own.items())},
                            **({"evidence": rig_estimation_evidence(rec, rigv, images, own)[1]} if not rigv.fixed else {})})
        for mt in fa.manual_ties:
            v_ = mt["residuals_px"]
            tie_out.append({"id": t_ids[mt["tie"]], "block": ci + 1, "xyz": mt["xyz"].tolist(),
                            "images": [names[i] for i in mt["images"]],
                            "sensors": sorted({inputs["images"][i]["sensor"] for i in mt["images"]}),
                            "rms_px": tie_rms(v_)})
        v = fa.tie_residuals
        rms = tie_rms(v)
        far = gnss_far_share(rec, images, ctrl) if geo else 0.0
        # at its iteration limit, also if a second adjustment from there converged (selfcal_ladder.adjust_block)
        at_limit = fa.result.termination is Termination.MAX_ITERATIONS or bool(getattr(fa, "first_termination", None))
        if at_limit and prunable is not None and prunable(fa):
            # the adjustment found no minimum and some centres contradict their GNSS: a few wrongly resected images
            # can be the cause. The block as the orientation left it, without the images that no similarity puts
            # near their GNSS (sfm.georef.gnss_consensus), is adjusted once more
            if _prune_requeue(rec, pre, images, ctrl, names, ci,
                              f"the final adjustment did not converge ({fa.result.reason}) with {100 * far:.0f} % of "
                              f"the centres > {GNSS_FLAG_SIGMA:g} σ from their GNSS and {len(fa.gnss_rejected)} GNSS "
                              "position(s) rejected", notes, pruned_blocks, queue):
                fa = None
                release_free_heap()
                continue
        rot_sigma = block_rotation_sigma(fa, images) if geo and precise_datum(datum, ctrl, images) else 0.0
        if (rot_sigma > BLOCK_ROTATION_SIGMA_DEG and pre is not None and ci not in attitude_blocks
                and rms <= BLOCK_RMS_GATE_PX and len(attitude_images(ctrl, images)) >= MIN_ATTITUDE_IMAGES):
            # its GNSS does not fix its rotation, the frames' gimbal attitudes can: adjusted again from the orientation
            # with them (sfm.georef.similarity_start(attitude_line=True)) instead of being rejected
            notes.append(f"block {ci + 1}: its camera rotations have σ {rot_sigma:.1f}° on its GNSS alone (> "
                         f"{BLOCK_ROTATION_SIGMA_DEG:g}°): adjusted again with the camera attitudes of the files")
            restore_to(rec, pre)
            fa = None
            release_free_heap()
            attitude_blocks.add(ci)
            queue.insert(0, (ci, images))
            continue
        why = block_rejection(rms, far, rot_sigma, fa.result, pruned=ci in pruned_blocks, stopped_at_limit=at_limit)
        if why:
            for i in images:
                rec.status[i].reason = f"in block {ci + 1} ({len(images)} images) rejected: {why}"
            notes.append(f"block {ci + 1}: {why}")
            results.append({"block": ci + 1, "images": len(images), "datum": str(datum),
                            "rejected": f"in block {ci + 1} ({len(images)} images) rejected: {why}"})
            rejected_at[len(results) - 1] = set(int(i) for i in images)
            continue
        n_own = len(images)
        extendable = geo and datum.from_gnss and rigv is None and not np.any(ctrl.lever_arm_m)
        if extendable:
            images, fa, cal_used, cal_steps, nts = extend_with_gnss(rec, xy, images, ctrl, names, ci, self_cal, adjust_kw,
                                                                      opt.reconstruction, (fa, cal_used, cal_steps), rms, far)
            notes += nts
        no_sigma = unconverged_sigma(fa)
        if no_sigma:
            # never reported with σ as if it had converged: the orientation is kept, its σ refused
            refuse_sigma(fa, no_sigma)
            for c_ in {int(c) for c in rec.image_camera[np.asarray(images)]}:
                rec.cameras[c_] = rec.cameras[c_].replace(param_std=np.full(len(rec.cameras[c_].param_names), np.nan))
            if rig_out and rig_out[-1].get("block") == ci + 1 and "std" in rig_out[-1]:
                rig_out[-1].update({"std": None, "sigma_refused": no_sigma})
            notes.append(f"block {ci + 1}: {no_sigma}")
        oriented[images] = True
        fa_all.append((ci, images, fa, datum, geo))
        results.append({"block": ci + 1, "images": len(images), "datum": str(datum),
                        "sigma0": None if no_sigma else float(fa.result.sigma0),
                        "termination": fa.result.termination.value, "reason": fa.result.reason,
                        "converged": not no_sigma, **({"sigma_refused": no_sigma} if no_sigma else {}),
                        **({"first_termination": list(fa.first_termination)} if getattr(fa, "first_termination", None) else {}),
                        "self_calibration": sorted({n for v in cal_used.values() for n in v}),
                        "calibration": calibration_choice(self_cal, cal_used, fa, cal_steps, meta["camera_ids"]),
                        **({"focal_prior": {str(meta["camera_ids"][c]): {"f_px": f, "sigma_px": sg} for c, (f, sg)
                                            in fa.focal_priors_used.items()}} if getattr(fa, "focal_priors_used", None) else {}),
                        "self_calibration_steps": cal_steps, **({"gnss_offset": gnss_off} if gnss_off else {}),
                        **({"marker_sigma": fa.marker_sigma} if fa.marker_sigma else {}),
                        "determinability": {} if no_sigma else _determinability(rec, fa, images, meta),
                        **({"added_at_gnss": [names[i] for i in images[n_own:]]} if len(images) > n_own else {})})
        if extendable:
            second_pass.append((len(fa_all) - 1, len(results) - 1, adjust_kw, cal_used, cal_steps))
    notes += _second_pass(rec, xy, ctrl, names, self_cal, opt, oriented, fa_all, results, second_pass, rejected_at, meta)
    if not fa_all:
        crs = None
    georeferenced = any(g for *_, g in fa_all)
    if not georeferenced:
        crs = None
    checks, gcp_errors, gcp_rejected = _check_points(rec, fa_all, ctrl, names, c_ids)
    extra = _survey_extra(project, inp, rec, names, oriented, meta, lt_verdict, notes, t_ids, tie_out,
                          rig=(rig_used, rig_reg, rig_master, rig_unpaired, rig_out, rig_only) if inp.rig is not None else None)
    extra["camera_start"] = _camera_start(inputs, rec, meta, camera)
    extra["camera_file"] = inp.camera_file  # --camera's file, format and conversion residual (or None)
    from ...sfm.georef_checks import gcp_measurement_report

    extra.update(gcp_measurement_report(rec, fa_all, ctrl, names))
    out = _write_outputs(project, inputs, rec, fa_all, names, crs, ctrl, checks, gcp_errors, gcp_rejected, notes, results,
                         extra=extra, rig_only={k: w for k, w in rig_only.items() if oriented[k]})
    out["seconds_georef"] = time.perf_counter() - t0
    return out


def _determinability(rec, fa, images, meta) -> dict:
    """:func:`~thermogrammetry.sfm.determinability.block_determinability` of a block's final adjustment."""
    from ...sfm.determinability import block_determinability

    cams = {f"camera{c}": (meta["camera_ids"][int(c)], rec.cameras[int(c)]) for c in np.unique(rec.image_camera[images])}
    return block_determinability(fa.covariance, fa.param_names, cams)


def _prune_requeue(rec, pre, images, ctrl, names, ci, why, notes, pruned_blocks, queue) -> bool:
    """Block ``ci`` without its wrongly resected images (:func:`~thermogrammetry.sfm.block_gates.prune_gnss_contradicting`
    from the orientation's state ``pre``) put first in ``queue`` to be adjusted again, once per block; False (nothing
    changed) when no such images are found."""
    kept, nts = prune_gnss_contradicting(rec, pre, images, ctrl, names, ci, why)
    if kept is None:
        return False
    notes += nts
    pruned_blocks.add(ci)
    queue.insert(0, (ci, kept))
    return True


def _controls(inp: SurveyInput, opt: SurveyOptions, inputs: dict, names: list):
    """The control inputs of the final adjustment (:class:`~thermogrammetry.sfm.georef.ControlInputs`): GNSS, GCPs,
    check points and manual tie points. Returns ``(ctrl, crs, notes, check-point ids, tie ids, tie observations)``."""
    from ...sfm.georef import ControlInputs

    gnss, gsig, crs, notes = _gnss_xyz(inputs, opt, opt.crs)
    g_ids, g_xyz, g_sig, g_obs, n1 = _read_markers(inp.gcps, inp.gcp_measurements, names, opt.gcp_sigma_m, opt.marker_sigma_px, "GCPs")
    c_ids, c_xyz, _, c_obs, n2 = _read_markers(inp.checkpoints, inp.check_measurements, names, opt.gcp_sigma_m,
                                               opt.marker_sigma_px, "check points")
    notes += n1 + n2
    # ids of the GCP measurement file in neither gcps.csv nor cp.csv: manual tie points (RGB <-> thermal)
    t_ids, t_obs, n3 = _read_manual_ties(inp.gcp_measurements, names, set(g_ids) | set(c_ids), opt.marker_sigma_px)
    notes += n3
    ctrl = ControlInputs(gnss, np.where(np.isfinite(gsig), gsig, 1.0), np.asarray(opt.lever_arm_m, float),
                         g_ids, g_xyz, g_sig, g_obs, c_ids, c_xyz, c_obs,
                         attitude=_attitudes(inputs, crs) if str(opt.gnss).lower() != "none" else None)
    return ctrl, crs, notes, c_ids, t_ids, t_obs


def _self_calibration(project: ProjectStore, inp: SurveyInput, opt: SurveyOptions, camera, inputs: dict, rec, meta: dict):
    """What the final adjustment self-calibrates per camera, and whether each camera's start is the files' focal
    length. Returns ``(self_cal, focal_known, notes)``."""
    notes: list = []
    # intrinsics: a given thermal camera (--camera or the rig's) is held fixed, other sensors self-calibrated
    rgb_cam = getattr(inp.rig, "rgb_camera", None)
    self_cal = opt.self_calibrate if camera is None and rgb_cam is None else {
        k: (() if (camera is not None and str(cid).startswith("thermal")) or (rgb_cam is not None and str(cid).startswith("rgb"))
            else opt.self_calibrate) for k, cid in enumerate(meta["camera_ids"])}
    # the focal-length band of the plausibility test applies only where the start came from the file's EXIF focal
    # length and pixel pitch: a video or an image without them starts from a guess (1 x the width), which
    # self-calibration is there to correct (a factor 2.3 on the synthetic video of tests/test_io_video.py)
    focal_known = {k: _focal_from_exif(inputs, rec, k) for k in range(len(meta["camera_ids"]))}
    # the guard's reference: the files' (or the camera table's) focal length, not the last adjustment's
    ks = range(len(meta["camera_ids"]))
    focal_known = FocalKnown(dict(focal_known), {k: _focal_prior(inputs, rec, k) for k in ks},
                             {k: _focal_prior_sigma(inputs, rec, k) for k in ks}, fov={k: _focal_prior_fov(inputs, rec, k) for k in ks})
    self_cal, lt_note = _low_texture_self_calibration(project, meta["camera_ids"], self_cal, focal_known)
    notes += [lt_note] if lt_note else []
    return self_cal, focal_known, notes


def _second_pass(rec, xy, ctrl, names, self_cal, opt: SurveyOptions, oriented, fa_all, results, second_pass,
                 rejected_at, meta) -> list:
    """Images of rejected blocks and images still unregistered added at their GNSS positions to the accepted GNSS
    blocks (:func:`~thermogrammetry.sfm.block_gates.extend_with_gnss`); updates ``oriented``, ``fa_all`` and
    ``results`` in place. Returns the notes."""
    notes: list = []
    # images of blocks rejected after an accepted block was extended (short arcs, wrong blocks) and images still
    # unregistered: a second chance at their GNSS positions in the accepted blocks (their own orientation is dropped)
    left = np.nonzero(~oriented & np.all(np.isfinite(ctrl.gnss_xyz), axis=1))[0]
    freed = left[rec.registered[left]] if second_pass else left[:0]  # images of rejected blocks (the others were tried)
    unregister_images(rec, freed)
    for k_fa, k_res, kw_b, cal_b, steps_b in (second_pass if len(freed) else []):
        ci, images, fa, datum, geo = fa_all[k_fa]
        v = fa.tie_residuals
        rms = tie_rms(v)
        n_own = len(images)
        images2, fa2, cal2, steps2, nts = extend_with_gnss(rec, xy, images, ctrl, names, ci, self_cal, kw_b, opt.reconstruction,
                                                             (fa, cal_b, steps_b), rms, gnss_far_share(rec, images, ctrl))
        notes += nts
        if len(images2) > n_own:
            oriented[images2] = True
            fa_all[k_fa] = (ci, images2, fa2, datum, geo)
            r = results[k_res]
            r.update({"images": len(images2), "sigma0": float(fa2.result.sigma0), "termination": fa2.result.termination.value,
                      "reason": fa2.result.reason, "self_calibration": sorted({n for v in cal2.values() for n in v}),
                      "calibration": calibration_choice(self_cal, cal2, fa2, steps2, meta["camera_ids"]), "self_calibration_steps": steps2,
                      "added_at_gnss": r.get("added_at_gnss", []) + [names[i] for i in images2[n_own:]],
                      "converged": True, "determinability": _determinability(rec, fa2, images2, meta)})
            # (extend_with_gnss keeps only an adjustment that converged)
            r.pop("sigma_refused", None)
            for k_rej, members in rejected_at.items():
                # the rejected block's entry says where its images went (it still counts them as its own)
                moved = [names[i] for i in images2[n_own:] if int(i) in members]
                if moved:
                    results[k_rej].setdefault("moved_to_blocks", {})[str(ci + 1)] = moved
    return notes


def _check_points(rec, fa_all, ctrl, names, c_ids):
    """Check points intersected in the georeferenced blocks (each in the block that sees it with most images), the
    GCP residuals and the rejected GCP measurements. Returns ``(checks, gcp_errors, gcp_rejected)``."""
    from ...sfm.georef import intersect_check_points

    # check points (in the block that sees them)
    checks = []
    gcp_errors = []
    gcp_rejected = []
    for ci, images, fa, datum, geo in fa_all:
        if not geo:
            continue
        cs = [c for c in intersect_check_points(rec, fa, ctrl) if c["xyz"] is not None or c["n_images"] > 0]
        if getattr(fa, "sigma_refused", ""):
            for c in cs:  # the error is measured; a σ from an unconverged adjustment is not reported
                c["std"], c["sigma_refused"] = None, fa.sigma_refused
        checks += cs
        gcp_errors += [fa.gcp_residuals_m[g] for g in np.nonzero(fa.gcp_used)[0]]
        gcp_rejected += [{"image": names[i], "id": gid, "residual_px": e} for i, gid, e in fa.gcp_rejected]
    # merge check points seen in several blocks: keep the one with most images
    best = {}
    for c in checks:
        if c["xyz"] is None:
            best.setdefault(c["id"], c)
        elif c["id"] not in best or best[c["id"]]["xyz"] is None or c["n_images"] > best[c["id"]]["n_images"]:
            best[c["id"]] = c
    checks = [best[k] for k in c_ids if k in best]
    return checks, gcp_errors, gcp_rejected


def _survey_extra(project: ProjectStore, inp: SurveyInput, rec, names, oriented, meta, lt_verdict, notes, t_ids, tie_out,
                  rig=None) -> dict:
    """survey.json's entries beyond the blocks: ``rig``, ``manual_ties``, ``mapper``, ``overlay``, ``low_texture``;
    the status reasons of rig partners and refused low-texture frames; notes appended to ``notes``. ``rig``:
    ``(rig_used, rig_reg, rig_master, rig_unpaired, rig_out, rig_only)`` in rig mode."""
    if rig is not None:
        rig_used, rig_reg, rig_master, rig_unpaired, rig_out, rig_only = rig
    extra = {}
    if inp.rig is not None:
        for s_, m_ in rig_master.items():
            if not oriented[s_] and not oriented[m_]:
                rec.status[s_].reason = f"RGB partner {names[m_]} not oriented; on its own: {rec.status[s_].reason or 'not oriented'}"
        for s_, why in rig_unpaired.items():
            if not oriented[s_]:
                rec.status[s_].reason = f"{why}; on its own: {rec.status[s_].reason or 'not oriented'}"
        r_only = sorted(k for k in rig_only if oriented[k])
        extra["rig"] = {"file": inp.rig.source, "pairs": len(rig_master), "fixed": not rig_used.estimate,
                        **({"registration": rig_reg} if rig_reg else {}),
                        "thermal_unpaired": [names[k] for k in sorted(rig_unpaired)], "blocks": rig_out,
                        "rig_only": [names[k] for k in r_only],
                        "rig_only_counted": (
                            "thermal images posed only through the rig (no or too few observations of their own) are "
                            "counted in images_oriented: R*, t is given by the rig file (calibrated), was estimated in "
                            "their block from >= 3 spread thermal frames with a converged adjustment and finite σ, or "
                            "was registered on the edges of >= 3 agreeing RGB/thermal pairs (rig.registration); "
                            "when that evidence is missing R*, t is not estimated and they are not oriented")}
        extra["images_rig_only"] = len(r_only)
    if t_ids:
        extra["manual_ties"] = {"ids": len(t_ids), "used": tie_out}
    extra["mapper"] = meta.get("mapper", "incremental")  # which orientation built the blocks (SurveyOptions.mapper)
    if meta.get("mapper_auto"):
        extra["mapper_auto"] = meta["mapper_auto"]
    ov = (SurveyStore(project).load_overlay() or {"found": False})
    extra["overlay"] = ({k: ov[k] for k in ("share", "frames", "images", "size")} if ov.get("found") else None)
    if ov.get("found"):
        notes.append(f"a display burned into the 8-bit frames (text, marks, colour bar at the same pixels in every "
                     f"frame) was found in {ov['frames']} frames: {100 * ov['share']:.1f} % of each "
                     f"{ov['size'][0]}x{ov['size'][1]} frame masked, no tie points there ({ov['images']} images)")
    if lt_verdict:
        extra["low_texture"] = lt_verdict
        for nm in lt_verdict.get("refused_images", []):  # frames the primary orientation left out: both reasons
            i = names.index(nm)
            if not oriented[i] and lt_verdict["why"] not in rec.status[i].reason:
                rec.status[i].reason = f"{rec.status[i].reason or 'not oriented'}; {lt_verdict['why']}"
    return extra
