"""The low-texture fallback of the ``orient`` step and its guard (plane parallax, planar share)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np

from ...store import ProjectStore
from .matching import step_matching
from .options import (LOW_TEXTURE_BA_GROWTH, LOW_TEXTURE_MAX_PLANE_PARALLAX, LOW_TEXTURE_MIN_PLANAR_SHARE,
                      LOW_TEXTURE_SELF_CALIBRATION, LOW_TEXTURE_SHARE, SurveyOptions)
from .orient import step_orient
from .store import (FEATURE_COUNTS_KEY, PAIRS_KEY, RECONSTRUCTION_JSON_KEY, RECONSTRUCTION_NPZ_KEY, SurveyStore,
                    _load_reconstruction, _tie_xy, features_key, matches_key, primary_key, tie_xy_key)


def _largest_thermal_block(project: ProjectStore) -> tuple[int, int]:
    """(thermal images, thermal images in the largest oriented block) of the last orientation."""
    inputs = SurveyStore(project).load_inputs()["images"]
    status = SurveyStore(project).load_reconstruction_meta()["status"]
    th = [k for k, im in enumerate(inputs) if im.get("sensor", "thermal") == "thermal"]
    count: dict = {}
    for k in th:
        if status[k]["registered"]:
            count[status[k]["component"]] = count.get(status[k]["component"], 0) + 1
    return len(th), max(count.values(), default=0)


def _low_texture_sequence_used(project: ProjectStore) -> bool:
    """Whether the thermal ties are the low-texture fallback's tracked sequence (``work/pairs.json``)."""
    info = SurveyStore(project).load_pairs().get("features", {}) if SurveyStore(project).has_pairs() else {}
    return "used" in info and bool(info.get("low_texture", {}).get("sequence"))


def _low_texture_orient_options(project: ProjectStore, opt: SurveyOptions) -> SurveyOptions:
    """Orientation options for a tracked low-texture sequence: a bundle adjustment after every added image.

    A walk along a plain wall is a long strip of frames whose tracks span 3-5 frames; registered one after the other
    with an adjustment only every 25 % of growth, the strip drifts and its ends flip (the planar-pose ambiguity):
    synthetic low-texture facade, 30 frames, true camera given -- rotations 4.9 deg RMS (max 22) off and the block
    split; with an adjustment after every image 30/30, 0.82 deg RMS (centres 0.3 % of the block's length)."""
    if not _low_texture_sequence_used(project):
        return opt
    return replace(opt, reconstruction=replace(opt.reconstruction, ba_growth=LOW_TEXTURE_BA_GROWTH))


def _low_texture_self_calibration(project: ProjectStore, camera_ids: list, self_cal, focal_known: dict):
    """Self-calibration of the thermal cameras of a tracked low-texture sequence: radial distortion only (and the
    focal length when it is a guess, not the file's EXIF value). Returns ``(self_cal, note or "")``.

    A strip of frames along a plane cannot carry the focal length and the principal point: they trade against the
    block's bending. Synthetic low-texture facade (30 frames, EXIF focal): incremental block 0.64-0.89 deg RMS off
    in rotation; the final adjustment with the 8 parameters bent it to 3.6-5.9 deg (fx +10 %, cy +29 px), with
    k1, k2 only it stays at 0.60-0.92 deg (k1 -0.051 for a true -0.05)."""
    if not _low_texture_sequence_used(project):
        return self_cal, ""
    out, limited, guessed = {}, [], []
    for k, cid in enumerate(camera_ids):
        req = tuple(self_cal.get(k, ())) if isinstance(self_cal, dict) else tuple(self_cal)
        if str(cid).startswith("thermal"):
            allow = LOW_TEXTURE_SELF_CALIBRATION if focal_known.get(k) else ("fx", "fy") + LOW_TEXTURE_SELF_CALIBRATION
            kept = tuple(p for p in req if p in allow)
            if kept != req:
                limited.append(f"{cid}: {', '.join(kept) or 'none'}")
            if "fx" in kept:
                guessed.append(str(cid))
            req = kept
        out[k] = req
    note = ("low-texture sequence: self-calibration limited to " + "; ".join(limited) +
            " (a strip of frames along a wall cannot carry the focal length and principal point)") if limited else ""
    if guessed:
        # synthetic facade walk filmed at 25 fps, 28 frames extracted (benchmarks/survey_lowtexture.py --synthetic
        # --video): fx 933 px for a true 765, rotations 9.6 deg RMS; with the camera file 1.3 deg
        note += ("; " if note else "low-texture sequence: ") + (
            f"the focal length of {', '.join(guessed)} is not known (no EXIF focal length, no camera file, the "
            "files' camera not in the camera table; a video carries none) and a walk along a wall determines it only weakly: expect rotations several degrees off "
            "(give --camera camera.json from `thermogrammetry calibrate`)")
    return out, note


def _low_texture_check(project: ProjectStore) -> dict:
    """The checks of every block of a tracked low-texture sequence: plane parallax of image-coplanar points
    (:data:`LOW_TEXTURE_MAX_PLANE_PARALLAX`) and planar share (:data:`LOW_TEXTURE_MIN_PLANAR_SHARE`).

    Returns ``{"blocks": [{"images", "thermal", "pairs", "median_plane_parallax_px", "residual_rms_px", "ratio",
    "planar_share", "refused"}], "refused_images": [...], "why": {image index: reason}}``; the reconstruction is not
    changed.
    """
    from ...sfm.lowtexture import plane_parallax

    rec, meta = _load_reconstruction(project)
    inputs = SurveyStore(project).load_inputs()["images"]
    is_th = np.array([im.get("sensor", "thermal") == "thermal" for im in inputs])
    xy = None
    blocks, refused, why = [], [], {}
    for comp in rec.components():
        th = [int(i) for i in comp if is_th[i]]
        if len(th) < 2:
            continue
        if xy is None:
            xy = [_tie_xy(project, im["name"]) for im in inputs]
        r = plane_parallax(rec.cameras, rec.image_camera, rec.R, rec.t, rec.points, rec.tracks.track, rec.tracks.image,
                           rec.tracks.feature, rec.obs_valid, xy, th)
        bad_par = not (r.ratio <= LOW_TEXTURE_MAX_PLANE_PARALLAX)
        bad_flat = not (r.planar_share >= LOW_TEXTURE_MIN_PLANAR_SHARE)
        bad = bad_par or bad_flat
        fin = lambda v: float(v) if np.isfinite(v) else None  # noqa: E731
        blocks.append({"images": len(comp), "thermal": len(th), "pairs": len(r.pairs),
                       "median_plane_parallax_px": fin(r.median_parallax_px), "residual_rms_px": fin(r.residual_rms_px),
                       "ratio": fin(r.ratio), "planar_share": fin(r.planar_share), "refused": bad})
        if bad:
            head = f"low-texture fallback: its block of {len(th)} thermal frames refused: "
            if not np.isfinite(r.ratio):
                reason = head + "no consecutive pair with enough common points to check its geometry"
            elif bad_par:
                reason = head + (f"the points its consecutive frames show coplanar lie off their plane by "
                                 f"{r.median_parallax_px:.2f} px (median plane parallax), {r.ratio:.2f} x the block's "
                                 f"{r.residual_rms_px:.2f} px RMS (> {LOW_TEXTURE_MAX_PLANE_PARALLAX:g}): a bent or wrong "
                                 "block (e.g. reflections on glass, a focal length far from the guess)")
            else:
                reason = head + (f"only {r.planar_share:.0%} of the points of consecutive frames lie within 1 % of their "
                                 f"depth of one plane (< {LOW_TEXTURE_MIN_PLANAR_SHARE:.0%}): the block does not "
                                 "reconstruct a wall (a walk explained as a turn, or depths too uncertain to check)")
            refused += th
            why.update({i: reason for i in th})
    return {"blocks": blocks, "refused_images": refused, "why": why}


def _low_texture_unregister(project: ProjectStore, why: dict) -> None:
    """Mark images of ``why`` (index -> reason) as not oriented in the saved reconstruction."""
    z = dict(SurveyStore(project).load_reconstruction_arrays())
    meta = SurveyStore(project).load_reconstruction_meta()
    reg = np.asarray(z["registered"]).astype(bool).copy()
    comp = np.asarray(z["component"]).copy()
    for i, reason in why.items():
        reg[i] = False
        comp[i] = -1
        meta["status"][i] = {**meta["status"][i], "registered": False, "component": -1, "reason": reason}
    z["registered"], z["component"] = reg, comp
    SurveyStore(project).save_reconstruction_arrays(**z)
    SurveyStore(project).save_reconstruction_meta(meta)


def _low_texture_verdict(project: ProjectStore, out: dict, verdict: dict) -> dict:
    """Record the fallback's outcome for :func:`step_georef` (``work/low_texture.json`` -> survey.json) and the step."""
    SurveyStore(project).save_low_texture(verdict)
    out["low_texture"] = {**out.get("low_texture", {}), **verdict}
    return out


def step_orient_low_texture(project: ProjectStore, opt: SurveyOptions, camera=None, progress=None, rgb_camera=None,
                            rig=None, *, primary_rejected: bool = False) -> dict:
    """:func:`step_orient`, then, with ``low_texture == "auto"``, the low-texture fallback when the orientation left
    fewer than 80 % of the thermal frames in one block although the matching did not trigger it (descriptor matches
    on noise and the sensor's pattern verify pairs that no orientation can use: a plain wall's frames were all
    "connected" and none oriented). The fallback's ties replace the thermal ones and the orientation is run again;
    its result is kept only when its largest block holds more thermal frames, else everything is put back as it was.

    Every block of a tracked sequence (from either trigger) must pass :func:`_low_texture_check` (its coplanar points
    lie flat, most points of consecutive frames on one plane); a refused block's thermal frames are not oriented
    (their reason says why) and the primary matching's orientation is put back when its largest thermal block is at
    least as large as what is left of the fallback's: with a refused block ``auto`` gives what ``off`` gives. The
    outcome goes to ``work/low_texture.json`` and survey.json's ``low_texture``.

    ``primary_rejected``: the final adjustment rejected every block of the primary orientation although it held
    enough frames not to trigger the fallback (descriptor matches on noise can connect every frame into a block
    that no adjustment can determine): the fallback runs, and its result is kept when it has any block
    (:func:`run_survey` re-runs ``georef`` on it).
    """
    out = step_orient(project, _low_texture_orient_options(project, opt), camera, progress, rgb_camera)
    if opt.low_texture != "auto":
        return _low_texture_verdict(project, out, {"ran": False})
    feats = SurveyStore(project).load_pairs().get("features", {})  # (read once: the checks below do not write it)
    if "low_texture" in feats:
        if not _low_texture_sequence_used(project):
            lt_info = feats["low_texture"]
            return _low_texture_verdict(project, out, {"ran": True, "trigger": "matching", "kept": "used" in feats,
                                                       **({"why": lt_info["refused"]} if lt_info.get("refused") else {})})
        chk = _low_texture_check(project)
        if not chk["refused_images"]:
            return _low_texture_verdict(project, out, {"ran": True, "trigger": "matching", "kept": True, "check": chk["blocks"]})
        why = sorted(set(chk["why"].values()))[0]
        prim = feats.get("primary_kept")
        if prim is not None and project.exists(primary_key(PAIRS_KEY)):
            # a block refused: the primary matching is oriented instead (what ``off`` gives); the refused block's
            # frames are not oriented in the fallback's result, so the primary one is kept unless the fallback's
            # remaining blocks hold more thermal frames
            _low_texture_unregister(project, chk["why"])
            _, best_rest = _largest_thermal_block(project)
            saved = {k: project.read_bytes(k) for k in [PAIRS_KEY, FEATURE_COUNTS_KEY, RECONSTRUCTION_JSON_KEY,
                                                        RECONSTRUCTION_NPZ_KEY]}
            saved_ties = {k: project.read_bytes(k) for k in (tie_xy_key(im['name'])
                                                             for im in SurveyStore(project).load_inputs()["images"])
                          if project.exists(k)}
            lt_files = {k: project.read_bytes(k) for k in prim if project.exists(k)}
            for k in prim:
                project.write_bytes(k, project.read_bytes(primary_key(k)))
            SurveyStore(project).save_feature_counts(project.read_json(primary_key(FEATURE_COUNTS_KEY)))
            pp = project.read_json(primary_key(PAIRS_KEY))
            # what the fallback did stays on record (without "used": its ties are not the ones in use)
            pp["features"]["low_texture"] = {**json.loads(saved[PAIRS_KEY])["features"]["low_texture"], "refused": why}
            SurveyStore(project).save_pairs(pp)
            out_p = step_orient(project, opt, camera, progress, rgb_camera)
            _, best_p = _largest_thermal_block(project)
            if best_p >= best_rest:
                names = [im["name"] for im in SurveyStore(project).load_inputs()["images"]]
                return _low_texture_verdict(project, out_p, {"ran": True, "trigger": "matching", "kept": False,
                                                             "check": chk["blocks"], "why": why, "primary_block": best_p,
                                                             "refused_images": [names[i] for i in chk["refused_images"]]})
            for k, v in {**lt_files, **saved, **saved_ties}.items():  # the fallback's remaining blocks are larger
                project.write_bytes(k, v)
            out["oriented"] -= len(chk["refused_images"])
            return _low_texture_verdict(project, out, {"ran": True, "trigger": "matching", "kept": True, "check": chk["blocks"],
                                                       "why": why, "primary_block": best_p})
        _low_texture_unregister(project, chk["why"])
        out["oriented"] -= len(chk["refused_images"])
        return _low_texture_verdict(project, out, {"ran": True, "trigger": "matching", "kept": False,
                                                   "check": chk["blocks"], "why": why})
    nt, best = _largest_thermal_block(project)
    if nt < 2 or (best >= LOW_TEXTURE_SHARE * nt and not primary_rejected):
        return _low_texture_verdict(project, out, {"ran": False})
    trigger = "orientation"
    if primary_rejected:
        trigger, best = "adjustment", 1  # the primary blocks were all rejected: any block of two frames is more
    inputs = SurveyStore(project).load_inputs()["images"]
    keep = [PAIRS_KEY, FEATURE_COUNTS_KEY, RECONSTRUCTION_JSON_KEY, RECONSTRUCTION_NPZ_KEY]
    keep += [tie_xy_key(im['name']) for im in inputs]
    keep += [features_key(im['name']) for im in inputs if im.get("sensor", "thermal") == "thermal"]
    keep += [matches_key(i, j) for i, j, _, _, reason in SurveyStore(project).load_pairs()["pairs"] if not reason]
    keep = [k for k in keep if project.exists(k)]
    for k in keep:  # the primary result, put aside on disk (features can be large)
        project.write_bytes(primary_key(k), project.read_bytes(k))

    def restore():
        for k in keep:
            project.write_bytes(k, project.read_bytes(primary_key(k)))

    m = step_matching(project, opt, camera, None, rig, low_texture_only=True)
    if primary_rejected and "low_texture" in m["features"]:
        m["features"]["low_texture"]["trigger"] = "adjustment: the final adjustment rejected every primary block"
        pp = SurveyStore(project).load_pairs()
        pp["features"]["low_texture"]["trigger"] = m["features"]["low_texture"]["trigger"]
        SurveyStore(project).save_pairs(pp)
    lt = m["features"].get("low_texture", {})
    if m.get("from_cache"):  # what the fallback's matching read from the tie cache (the orient step's report says it)
        out["from_cache"] = m["from_cache"]
    if "used" not in m["features"]:
        restore()
        out["low_texture"] = lt
        return _low_texture_verdict(project, out, {"ran": True, "trigger": trigger, "kept": False,
                                                   "why": "the fallback verified no consecutive pair"})
    out2 = step_orient(project, _low_texture_orient_options(project, opt), camera, progress, rgb_camera)
    if m.get("from_cache"):
        out2["from_cache"] = m["from_cache"]
    chk = _low_texture_check(project) if _low_texture_sequence_used(project) else {"blocks": [], "refused_images": [], "why": {}}
    if chk["refused_images"]:
        _low_texture_unregister(project, chk["why"])
        out2["oriented"] -= len(chk["refused_images"])
    _, best2 = _largest_thermal_block(project)
    if best2 > best:
        out2["low_texture"] = {**lt, "largest_thermal_block_before": best, "largest_thermal_block": best2}
        return _low_texture_verdict(project, out2, {"ran": True, "trigger": trigger, "kept": True, "check": chk["blocks"],
                                                    **({"why": sorted(set(chk["why"].values()))[0]} if chk["why"] else {})})
    # the primary result stands (its frames keep their own reasons)
    restore()
    out["low_texture"] = lt
    why = (sorted(set(chk["why"].values()))[0] if chk["why"] else
           f"its largest block holds {best2} thermal frames" + (" (the primary's were rejected by the final adjustment)"
                                                                if primary_rejected else f", the primary's {best}"))
    return _low_texture_verdict(project, out, {"ran": True, "trigger": trigger, "kept": False, "check": chk["blocks"],
                                               "why": why})
