"""The self-calibration ladder of the final adjustment: the requested intrinsics first, fewer while the block
cannot carry them (rank deficient, σ not finite, implausible estimates; :func:`adjust_block`). Pure functions over a
:class:`~thermogrammetry.sfm.reconstruction.Reconstruction` and the controls (no store, no paths)."""

from __future__ import annotations

import numpy as np

from ..results import Termination
from .reconstruction import restore_to, snapshot_of

__all__ = ["FocalKnown", "FOCAL_PRIOR_K", "MAX_ITERATIONS_RETRY", "SELF_CALIBRATION_LADDER", "FIXED_INTERIOR_LADDER", "INTRINSICS_PLAUSIBLE", "intrinsics_problem",
           "intrinsics_check", "ladder_sets", "fixed_interior_rungs", "adjust_block", "fov_focal_priors", "FOV_PRIOR_ITERATIONS",
           "calibration_choice"]


#: self-calibration steps down this ladder (each rung intersected with the parameters asked for) while the
#: block cannot carry it: the adjustment stops rank deficient, a free parameter's σ is not finite, or the
#: estimate is implausible (below)
SELF_CALIBRATION_LADDER = (("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"), ("fx", "fy", "k1", "k2"), ("fx", "fy", "k1"),
                           ("fx", "fy"), ())


#: ... and the rungs a camera takes instead once its focal length was refused as implausible (more than
#: INTRINSICS_PLAUSIBLE["focal"] from the file's EXIF value): the block does not determine its interior orientation
#: (a single strip or a facade pass over flat ground without GCPs: focal length and ground distance trade freely),
#: so focal length and principal point stay at their start and only the distortion, which the ties determine in
#: the image, is self-calibrated. Measured on the M3T flight's frames 0008-0023 alone (one E-W strip on RTK, no
#: camera file): the focal length ran to 2007-2577 px on the first three rungs, and the (fx, fy) rung was accepted
#: at 738.6/714.9 px (the full flight's 783.2/781.0) with the orientation's distortion held: rotations 2.33 deg
#: RMS from the full flight's block, the full flight's tie points re-intersected through the strip's cameras
#: 0.59/3.03/6.16 m RMS off in X/Y/Z; on (k1, k2, p1, p2) with the EXIF focal length 758.3 px: 0.28 deg,
#: 1.06/0.25/2.28 m (Z: the EXIF focal length is 3 % short; with the full flight's camera file 0.03/0.57/0.16 m)
FIXED_INTERIOR_LADDER = (("k1", "k2", "p1", "p2"), ("k1", "k2"), ("k1",), ())


#: plausibility of self-calibrated intrinsics against their start (EXIF focal length and pixel pitch, or the
#: image centre): focal length within ±30 % (only when the start is the file's EXIF focal length), fy/fx within ±5 % (thermal and RGB sensors have square pixels to
#: well under 1 %), principal point within 15 % of the frame, radial distortion at the frame corner below 20 %
#: of the radius. Measured on the Thermitage fresco walls (thermal only, 6 frames tied by wrong matches): fy/fx
#: 1.26 and a rank-deficient solve, reported as an oriented block before this check.
INTRINSICS_PLAUSIBLE = {"focal": 0.30, "aspect": 0.05, "principal_point": 0.15, "corner_distortion": 0.20}


class FocalKnown(dict):
    """Camera index -> whether its starting focal length is the files' (EXIF, or EXIF/field of view with the camera
    table's pixel pitch), the ``focal_known`` of :func:`intrinsics_check`; ``prior``: camera index -> that focal
    length (px) or None. With a prior, the focal band of :data:`INTRINSICS_PLAUSIBLE` is measured from it, not
    from the camera the adjustment started from: an adjustment that starts from an earlier adjustment's camera (the
    block adjusted again with images added at their GNSS positions) cannot walk the focal length away 30 % at a
    time. ``sigma``: camera index -> σ (px) of that focal length or None; with both, an adjustment that frees fx
    and fy also weights them towards the prior (:func:`~thermogrammetry.sfm.georef.final_adjustment`
    ``focal_priors``): a block that cannot determine its focal length (a flat field flown at one height: focal
    length and heights are a twin) keeps the lens's value within its σ instead of running away."""

    def __init__(self, known=(), prior=None, sigma=None, fov=None):
        super().__init__(known)
        self.prior = dict(prior or {})
        self.sigma = dict(sigma or {})
        # camera index -> half extent (px) of the field of view the prior came from (None: a focal length)
        self.fov = {c: v for c, v in dict(fov or {}).items() if v}

    def priors(self) -> dict:
        """Camera index -> (focal length px, σ px) for the cameras with both."""
        return {c: (float(f), float(self.sigma[c])) for c, f in self.prior.items()
                if f and self.sigma.get(c) and np.isfinite(self.sigma[c]) and self.sigma[c] > 0}


#: a self-calibrated focal length more than this many σ of the lens's value (:class:`FocalKnown` ``sigma``) from it
#: is refused (held at the lens's value; only the distortion self-calibrated). On the shared M3T flight's single
#: strip (16 frames on one line over flat ground) the weighted prior alone let fx run to 886 px against 758 ± 38 px
#: (3.4 σ; rotations 0.93° RMS from the whole flight's) where holding it gives 0.28°
FOCAL_PRIOR_K = 3.0


#: a focal prior from a field of view (:class:`FocalKnown` ``fov``) is expressed through the distortion the block
#: self-calibrates (:func:`~thermogrammetry.camera.database.focal_through_distortion`) and the block adjusted again,
#: at most this many times, until the prior moves by less than FOV_PRIOR_TOL of its σ
FOV_PRIOR_ITERATIONS = 4
FOV_PRIOR_TOL = 0.1


def fov_focal_priors(fa, sets: dict, focal_known, used: dict) -> dict:
    """Camera index -> (focal px, σ px): the field-of-view priors of :class:`FocalKnown` through each camera's
    self-calibrated radial distortion (``fa.cameras_after``), for the cameras whose fx, fy and k1 are free and whose
    prior moves by more than :data:`FOV_PRIOR_TOL` σ from ``used`` (the priors of the adjustment ``fa``)."""
    from ..camera.database import focal_through_distortion

    out = {}
    for c, ext in (getattr(focal_known, "fov", None) or {}).items():
        free = {n.lower() for n in sets.get(c, ())}
        cam = (getattr(fa, "cameras_after", None) or {}).get(c)
        f0, s0 = focal_known.prior.get(c), focal_known.sigma.get(c)
        if cam is None or not f0 or not s0 or not {"fx", "fy", "k1"} <= free or c not in used:
            continue
        p = cam.param_dict
        f = focal_through_distortion(f0, ext, p.get("k1", 0.0), p.get("k2", 0.0), p.get("k3", 0.0))
        if np.isfinite(f) and abs(f - used[c][0]) > FOV_PRIOR_TOL * used[c][1]:
            out[c] = (f, s0 * f / f0)
    return out


#: an adjustment of the ladder that stops at its iteration limit (with an accepted self-calibration) is adjusted
#: again once from where it stopped, with this many iterations (the final adjustment's default is 50)
MAX_ITERATIONS_RETRY = 200


def intrinsics_problem(fa, start_cams: dict, free_sets: dict, focal_known: dict | None = None) -> tuple[int | None, str]:
    """Why a final adjustment's self-calibration cannot be accepted: ``(camera index, reason)`` for one camera's
    implausible or undetermined intrinsics, ``(None, reason)`` when the solve itself failed, ``(None, "")`` when
    it can be accepted (:func:`intrinsics_check` also says which check refused it).

    ``start_cams``: camera index -> Camera before the adjustment; ``free_sets``: camera index -> free names;
    ``focal_known``: camera index -> whether the starting focal length is the file's (only then is the focal
    band of :data:`INTRINSICS_PLAUSIBLE` applied; default: for every camera).
    """
    cam, why, _ = intrinsics_check(fa, start_cams, free_sets, focal_known)
    return cam, why


def intrinsics_check(fa, start_cams: dict, free_sets: dict, focal_known: dict | None = None) -> tuple[int | None, str, str]:
    """:func:`intrinsics_problem` and the check that refused: ``"solve"``, ``"sigma"``, ``"focal"``, ``"aspect"``,
    ``"principal_point"``, ``"distortion"`` or ``""``."""
    res = fa.result
    if not res.success or res.termination.value == "rank_deficient":
        return None, f"the adjustment stopped: {res.reason or res.termination.value}", "solve"
    lim = INTRINSICS_PLAUSIBLE
    order = sorted(start_cams)
    for c in order:
        free = {n.lower() for n in free_sets.get(c, ())}
        if not free:
            continue
        cam0, cam = start_cams[c], fa.cameras_after[c]
        p0, p = cam0.param_dict, cam.param_dict
        w, h = cam.image_size
        if res.camera_std and order.index(c) < len(res.camera_std):
            std = dict(zip(cam.param_names, np.asarray(res.camera_std[order.index(c)], float)))
            bad = sorted(n for n in free if n in std and not np.isfinite(std[n]))
            if bad and fa.covariance_asked:
                return c, f"camera {cam.name or c}: σ of {', '.join(bad)} not finite (the block does not determine them)", "sigma"
        if "fx" in p and "fy" in p:
            known = True if focal_known is None else bool(focal_known.get(c, False))
            ref = getattr(focal_known, "prior", {}).get(c) if focal_known is not None else None
            fx0, fy0, what = (ref, ref, "the files' (or the camera table's)") if ref else (p0["fx"], p0["fy"], "a start of")
            sg = getattr(focal_known, "sigma", {}).get(c) if (focal_known is not None and ref) else None
            # with the lens's σ: FOCAL_PRIOR_K σ of it (a block that pulls its focal length that far from the lens's
            # value against the weighted prior is a twin of its heights, not a measurement of the lens)
            band = min(lim["focal"], FOCAL_PRIOR_K * sg / ref) if sg else lim["focal"]
            if known and (abs(p["fx"] / fx0 - 1) > band or abs(p["fy"] / fy0 - 1) > band):
                return c, (f"camera {cam.name or c}: focal length {p['fx']:.1f}/{p['fy']:.1f} px from {what} {fx0:.1f} px "
                           + (f"± {sg:.1f} px (more than {FOCAL_PRIOR_K:g} σ, {band:.0%}, apart)" if sg and band < lim["focal"]
                              else f"(more than {band:.0%} apart)")), "focal"
            if abs(p["fy"] / p["fx"] - 1) > lim["aspect"]:
                return c, f"camera {cam.name or c}: fy/fx = {p['fy'] / p['fx']:.3f} (pixels are square to within {lim['aspect']:.0%})", "aspect"
        if "cx" in p and (abs(p["cx"] - p0["cx"]) > lim["principal_point"] * w or abs(p["cy"] - p0["cy"]) > lim["principal_point"] * h):
            return c, (f"camera {cam.name or c}: principal point ({p['cx']:.1f}, {p['cy']:.1f}) px, more than "
                    f"{lim['principal_point']:.0%} of the frame from its start ({p0['cx']:.1f}, {p0['cy']:.1f})"), "principal_point"
        if "k1" in p and "fx" in p:
            r2 = ((w / 2) ** 2 + (h / 2) ** 2) / p["fx"] ** 2
            d = abs(p.get("k1", 0.0) * r2 + p.get("k2", 0.0) * r2**2 + p.get("k3", 0.0) * r2**3)
            if d > lim["corner_distortion"]:
                return c, f"camera {cam.name or c}: radial distortion {d:.0%} of the radius at the frame corner", "distortion"
    return None, "", ""


def ladder_sets(self_cal, cam_indices) -> dict:
    """Rungs of :data:`SELF_CALIBRATION_LADDER` for the requested self-calibration, per camera index: a list of
    tuples of free names, from the request down to none (no rung repeated)."""
    out = {}
    for c in cam_indices:
        want = tuple(self_cal.get(int(c), ()) if isinstance(self_cal, dict) else self_cal)
        rungs: list = []
        for rung in (None,) + SELF_CALIBRATION_LADDER:
            sets = want if rung is None else tuple(n for n in want if n.lower() in rung)
            if sets not in rungs:
                rungs.append(sets)
        out[int(c)] = rungs
    return out


def fixed_interior_rungs(want, tried) -> list:
    """:data:`FIXED_INTERIOR_LADDER` intersected with the requested parameters ``want``, without the rungs already
    ``tried``; ends with the camera held fixed."""
    out: list = []
    for rung in FIXED_INTERIOR_LADDER:
        sets = tuple(n for n in want if n.lower() in rung)
        if sets not in out and sets not in tried:
            out.append(sets)
    return out if out and out[-1] == () else out + [()]


def adjust_block(rec, xy, images, ctrl, self_cal, *, rigv=None, focal_known: dict | None = None,
                 limit_handled=None, **kw):
    """:func:`~thermogrammetry.sfm.georef.final_adjustment` with a self-calibration the block can carry.

    The requested parameters first. When one camera's intrinsics are implausible (:data:`INTRINSICS_PLAUSIBLE`)
    or a free parameter's σ is not finite, that camera steps one rung down :data:`SELF_CALIBRATION_LADDER`
    (fewer parameters; after an implausible focal length the rungs of :data:`FIXED_INTERIOR_LADDER`, distortion
    only); when the solve itself stops (rank deficient), every camera with free parameters
    steps down. ``rec`` is restored and the block adjusted again, until the solve is accepted or every camera
    is held fixed. (On the frescoes, RGB + thermal through a rig, the thermal camera with 2 frames of its own
    ran to fy = 316 px while the RGB camera, 40 frames, was well determined: only the thermal one steps down.)
    An accepted adjustment that stopped at its iteration limit is adjusted again once from where it stopped
    (:data:`MAX_ITERATIONS_RETRY` iterations; ``fa.first_termination`` records the first pass) unless
    ``limit_handled(fa)`` is true (the caller has its own remedy for that block, e.g. leaving wrongly resected
    images out); when that second solve fails outright, the first adjustment is returned as it stopped.
    Returns the final adjustment, the free parameters used per camera index and the reasons of every step.
    """
    from .georef import final_adjustment

    cams_in = sorted({int(c) for c in rec.image_camera[np.asarray(images)]})
    start = {c: rec.cameras[c] for c in cams_in}
    fp = focal_known.priors() if isinstance(focal_known, FocalKnown) else {}
    if fp and "focal_priors" not in kw:
        kw = {**kw, "focal_priors": {c: v for c, v in fp.items() if c in cams_in}}
    ladder = ladder_sets(self_cal, cams_in)
    level = {c: 0 for c in cams_in}

    def keep():  # the block's state (and the rig's) to come back to
        return snapshot_of(rec), ((rigv.R.copy(), rigv.t.copy()) if rigv is not None else None)

    def back(state):
        restore_to(rec, state[0])
        if state[1] is not None:
            rigv.R, rigv.t = state[1][0].copy(), state[1][1].copy()

    start_state = keep()
    steps: list[str] = []
    first = True
    n_fov = 0
    names = lambda v: ", ".join(v) or "nothing"  # noqa: E731
    while True:
        sets = {c: ladder[c][level[c]] for c in cams_in}
        if not first:
            back(start_state)
        first = False
        fa = final_adjustment(rec, xy, images, ctrl, self_calibrate=sets, rig=rigv, **kw)
        fa.cameras_after = {c: rec.cameras[c] for c in cams_in}
        fa.covariance_asked = bool(kw.get("compute_covariance", True))
        cam, why, check = intrinsics_check(fa, start, sets, focal_known)
        if (not why and fa.result.termination is Termination.MAX_ITERATIONS
                and not (limit_handled is not None and limit_handled(fa))):
            # stopped at the iteration limit, not converged: adjusted again once from where it stopped (its
            # state is in ``rec``) with more iterations, and that adjustment checked like the first
            n0, r0 = fa.result.iterations, fa.result.reason
            at_limit = keep()
            kw2 = {**kw, "max_iterations": max(MAX_ITERATIONS_RETRY, 4 * int(kw.get("max_iterations", 50)))}
            fa2 = final_adjustment(rec, xy, images, ctrl, self_calibrate=sets, rig=rigv, **kw2)
            fa2.cameras_after = {c: rec.cameras[c] for c in cams_in}
            fa2.covariance_asked = fa.covariance_asked
            fa2.notes = fa.notes + [f"the final adjustment stopped without converging ({r0 or n0}); adjusted again from "
                                    f"there with up to {kw2['max_iterations']} iterations: "
                                    f"{fa2.result.termination.value}" + (f" ({fa2.result.reason})" if fa2.result.reason else "")
                                    ] + fa2.notes
            fa2.first_termination = (fa.result.termination.value, r0)
            cam2, why2, check2 = intrinsics_check(fa2, start, sets, focal_known)
            if why2 and cam2 is None:
                # the second solve failed outright (e.g. its precision step): the first adjustment, as it stopped
                back(at_limit)
                fa.notes = fa.notes + [f"the final adjustment stopped without converging ({r0 or n0}); adjusted again "
                                       f"from there with up to {kw2['max_iterations']} iterations: {why2}; the first "
                                       "adjustment kept as it stopped"]
            else:
                fa, cam, why, check = fa2, cam2, why2, check2
        if not why:
            fa.focal_priors_used = {c: kw["focal_priors"][c] for c in kw.get("focal_priors", {})
                                    if {"fx", "fy"} <= {n.lower() for n in sets.get(c, ())}}
            upd = fov_focal_priors(fa, sets, focal_known, fa.focal_priors_used) if n_fov < FOV_PRIOR_ITERATIONS else {}
            if upd:
                # the prior was a field of view: the focal length it implies through the distortion just estimated
                n_fov += 1
                kw = {**kw, "focal_priors": {**kw["focal_priors"], **upd}}
                steps.append("focal prior from the field of view expressed through the self-calibrated distortion: "
                             + ", ".join(f"{start[c].name or c}: {fa.focal_priors_used[c][0]:.1f} -> {f:.1f} ± {sg:.1f} px"
                                         for c, (f, sg) in upd.items()) + "; adjusted again")
                continue
            return fa, sets, steps
        held = ""
        if check == "focal" and cam is not None:
            # the block does not determine the interior orientation: the rest of this camera's ladder holds focal
            # length and principal point at their start (FIXED_INTERIOR_LADDER)
            ladder[cam] = ladder[cam][: level[cam] + 1] + fixed_interior_rungs(ladder[cam][0], ladder[cam][: level[cam] + 1])
            held = " (focal length and principal point held at their start from now on: the block does not determine them)"
        down = [c for c in ([cam] if cam is not None else cams_in) if level[c] + 1 < len(ladder[c])]
        if not down:
            steps.append(f"with the camera held fixed: {why}" if all(not v for v in sets.values()) else
                         f"with {', '.join(f'{start[c].name or c}: {names(sets[c])}' for c in cams_in)}: {why}")
            return fa, sets, steps
        for c in down:
            level[c] += 1
        steps.append(f"self-calibration of {', '.join(f'{start[c].name or c}: {names(sets[c])}' for c in down)} refused: {why}; "
                     f"adjusted again with {', '.join(f'{start[c].name or c}: ' + (', '.join(ladder[c][level[c]]) or 'held fixed') for c in down)}"
                     + held)


def calibration_choice(requested, used: dict, adjustment, steps: list, camera_ids: list) -> dict:
    """What a block's final adjustment did with each camera's interior orientation, and why: camera id ->
    ``{"choice", "estimated", "reason"}``.

    ``choice`` says how the focal length -- the parameter a weak block trades against its heights (Kraus 2007
    §4.4) -- was treated: ``"self-calibrate"`` (estimated from the block alone), ``"prior"`` (estimated with a
    weighted prior at the files' or the camera table's value) or ``"hold"`` (kept at its start: a calibration given
    by the user, or a block that could not carry its estimation). ``estimated`` lists the parameters estimated.

    Parameters
    ----------
    requested : sequence of str, or dict camera index -> sequence of str
        The parameters asked for (``SurveyOptions.self_calibrate``; a camera given with ``--camera`` asks none).
    used : dict camera index -> sequence of str
        The parameters the accepted adjustment estimated (:func:`adjust_block`'s sets).
    adjustment : the accepted final adjustment
        Its ``focal_priors_used`` (camera index -> (focal px, σ px)) are the focal priors it applied.
    steps : list of str
        The ladder's steps (``self_calibration_steps``): the last one that names a camera gives a hold's reason.
    camera_ids : list of str
        Camera index -> id.
    """
    priors = getattr(adjustment, "focal_priors_used", None) or {}
    out = {}
    for c, names in sorted(used.items()):
        names = [str(n) for n in names]
        free = {n.lower() for n in names}
        req = requested.get(c, ()) if isinstance(requested, dict) else (requested or ())
        cid = str(camera_ids[c]) if c < len(camera_ids) else str(c)
        if {"fx", "fy"} & free and c in priors:
            f, sg = priors[c]
            choice = "prior"
            reason = (f"focal length estimated with a weighted prior at {float(f):.1f} ± {float(sg):.1f} px (the files' or "
                      "the camera table's value): a block that cannot tell its focal length from its heights keeps it "
                      "within that σ")
        elif {"fx", "fy"} & free:
            choice, reason = "self-calibrate", "focal length estimated from the block alone (no prior for this camera)"
        else:
            choice = "hold"
            if not req:
                reason = "no parameter asked to be estimated: the camera is held as given (--camera, a rig file or --self-calibrate)"
            else:
                why = next((st for st in reversed(steps) if "refused" in st or "held" in st), None)
                reason = ("focal length held at its start: " + why) if why else "focal length held at its start"
        out[cid] = {"choice": choice, "estimated": sorted(names), "reason": reason}
    return out
