"""Staged self-calibration of one or more cameras from targets with known coordinates.

Strategy of Yastikli & Guler (2013, §3), extended to several cameras, rigs and further parameters:

1. **Stage 1** — nominal principal distance, principal point at the image centre, no distortion;
   only the exterior orientations are estimated (initialised per image by resection,
   ``cv2.solvePnP``). Gross blunders are eliminated here. Because uncorrected distortion inflates the
   residuals at this stage (the camera of Yastikli & Guler 2013 has up to ~20 px of distortion in the
   corners), the test uses the a-posteriori σ0 and a conservative critical value (``stage1_critical``,
   default 5), so that only gross errors go. After stage 2 has converged, every stage-1 reject within 10 σ of
   the full model is re-admitted and re-tested by the stage-2 data snooping (otherwise valid
   corner points, the most informative on distortion, would stay out).
2. **Stage 2** — x0, y0, c, K1–K3, P1, P2 free (K4, K5 as in Khodaei et al. 2015, and B1, B2 on request); in
   the OpenCV model (``options.model = "opencv"``) fx, fy, cx, cy, k1, k2, p1, p2, k3 free, what
   ``cv2.calibrateCamera`` estimates by default (k3 can be held, ``fixed=("k3",)``; k4–k6 on request). Data
   snooping (Baarda 1968) with the a-priori σ of the measurements when every measurement carries
   one, otherwise Pope's τ test with the a-posteriori σ0; critical value 3.29 (α0 = 0.1 %,
   two-sided); at most one observation (image point) is removed per image and round.
3. **Tests** — Student-t significance test of every additional parameter (H0: value = 0, α = 5 %,
   two-sided, degrees of freedom = redundancy) and warnings for |ρ| > 0.9 between intrinsic
   parameters.

Several cameras are calibrated together (each has its own intrinsics; images are tied together by
the common object points). When images of different cameras share a ``frame`` key and ``rig=True``,
the second camera's poses are the first camera's pose composed with a constant relative orientation
``cam2_from_cam1`` (estimated, with precision): the relative orientation of a thermal + RGB pair.

The solve is one call, :func:`thermogrammetry.calibration.bundle.solve_bundle`: by default the
project's adjustment engine (:mod:`thermogrammetry.adjustment`), or the dense kernel
:func:`thermogrammetry.adjustment.dense.solve_dense` on the same problem, kept as a cross-check.

References
----------
Yastikli, N., Guler, E., 2013. Performance evaluation of thermographic cameras for photogrammetric
measurements. ISPRS Arch. XL-1/W1.
Khodaei, B. et al., 2015. 3D surface generation from aerial thermal imagery (K4, K5).
Fraser, C.S., 1997. Digital camera self-calibration. ISPRS J. Photogramm. Remote Sens. 52, 149–159.
Baarda, W., 1968. A testing procedure for use in geodetic networks.
Pope, A.J., 1976. The statistics of residuals and the detection of outliers. NOAA TR NOS 65 NGS 1.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from ..errors import InvalidInputError, TooFewPointsError
from ..geometry.rotations import mean_rotation
from ..results import Termination
from .bundle import BundleProblem, BundleSolution, CameraBlock, residuals, solve_bundle
from .selfcal_initial import init_focal_planar, is_planar, nominal_vector, pinhole_K, resect
from .selfcal_inputs import STAGE2_PARAMS, STAGE2_PARAMS_OPENCV, CameraSetup, ImageMeasurements, SelfCalibrationOptions
from .selfcal_results import (  # (ADDITIONAL and the result types: importable from here as before)
    ADDITIONAL,
    CalibrationResult,
    CameraCalibration,
    ImageVerdict,
    ParameterTest,
    RelativeOrientation,
    assemble,
    empty_result,
)

__all__ = [
    "SelfCalibrationOptions",
    "CameraSetup",
    "ImageMeasurements",
    "ParameterTest",
    "CameraCalibration",
    "ImageVerdict",
    "RelativeOrientation",
    "CalibrationResult",
    "calibrate",
    "STAGE2_PARAMS",
    "STAGE2_PARAMS_OPENCV",
]


def calibrate(
    cameras: Sequence[CameraSetup],
    points: np.ndarray,
    images: Sequence[ImageMeasurements],
    *,
    point_std: np.ndarray | None = None,
    options: SelfCalibrationOptions | None = None,
    rig: bool = False,
    progress=None,
    initial: Mapping[int, np.ndarray] | None = None,
    initial_poses: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
) -> CalibrationResult:
    """Self-calibrate ``cameras`` from measured images of known object ``points``.

    Parameters
    ----------
    cameras : setups (image size, pixel pitch, nominal values; ``nominal['c_mm']`` required unless
        every image of that camera sees a planar target).
    points : (M, 3) object coordinates, metres.
    images : per-image measurements (indices into ``points``, pixels in the OpenCV convention).
    point_std : (M, 3) a-priori standard deviations of the object coordinates (m); points with
        finite positive values are adjusted as weighted unknowns, others are fixed.
    options : :class:`SelfCalibrationOptions` (``options.model``: the camera model estimated, for every camera).
    rig : model images of different cameras sharing a ``frame`` as a rigid rig (first camera in
        each frame is the reference) and estimate the relative orientation. The cameras are then
        also solved with independent poses, and ``warnings`` says when a rig camera's RMS is more
        than ``options.rig_rms_warning_factor`` times its independent RMS.
    progress : optional callable ``progress(stage: str, done: int, total: int)``.
    initial : optional {camera index: (P,) parameters of ``options.model``} to start stage 2 from (skips
        stage 1's nominal model for that camera; used by Monte-Carlo studies started at the truth).
    initial_poses : optional per-image (R, t) to skip resection.

    Returns
    -------
    CalibrationResult. Bad input raises (``InvalidInputError`` family); a failed solve is returned
    with ``outcome.success == False`` and the reason. ``warnings`` lists undetermined precision
    (standard deviations NaN, never 0) and a rig that does not fit.

    References
    ----------
    Fraser, C. S. (1997). Digital camera self-calibration. ISPRS J. Photogramm. Remote Sens. 52, 149-159.
    """
    opt = options or SelfCalibrationOptions()
    kw = dict(point_std=point_std, options=opt, progress=progress, initial=initial, initial_poses=initial_poses)
    res = _calibrate_once(cameras, points, images, rig=rig, **kw)
    if rig and res.relative and res.outcome.success and opt.rig_rms_warning_factor > 0:
        indep = _calibrate_once(cameras, points, images, rig=False, **kw)
        if indep.outcome.success:
            for ci, (cr, cs) in enumerate(zip(res.cameras, indep.cameras)):
                if np.isfinite(cr.rms_px) and np.isfinite(cs.rms_px) and cr.rms_px > opt.rig_rms_warning_factor * cs.rms_px:
                    fx_r = cr.parameters_px()["fx"][0]
                    fx_s = cs.parameters_px()["fx"][0]
                    res.warnings.append(
                        f"rig does not fit camera {cr.name!r}: RMS {cr.rms_px:.3f} px with the rig constraint against "
                        f"{cs.rms_px:.3f} px with independent poses (> {opt.rig_rms_warning_factor:g}x; fx {fx_r:.1f} "
                        f"against {fx_s:.1f} px); check frame synchronisation and pairing")
            lost = sorted(set(indep.images_used) - set(res.images_used))
            if lost:
                res.warnings.append(
                    f"rig does not fit {len(lost)} image(s) that independent poses use ({', '.join(lost[:5])}"
                    f"{' ...' if len(lost) > 5 else ''}): rejected under the rig constraint; check frame "
                    "synchronisation and pairing")
    return res


def _calibrate_once(
    cameras: Sequence[CameraSetup],
    points: np.ndarray,
    images: Sequence[ImageMeasurements],
    *,
    point_std: np.ndarray | None = None,
    options: SelfCalibrationOptions | None = None,
    rig: bool = False,
    progress=None,
    initial: Mapping[int, np.ndarray] | None = None,
    initial_poses: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
) -> CalibrationResult:
    """One solve of :func:`calibrate` (rig or independent poses); see there."""
    opt = options or SelfCalibrationOptions()
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidInputError(f"points: expected shape (M, 3) in metres, got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise InvalidInputError("points: non-finite object coordinates")
    if not cameras:
        raise InvalidInputError("cameras: expected at least one CameraSetup")
    if not images:
        raise TooFewPointsError("images: no image measurements given")
    M = points.shape[0]
    verdicts: list[ImageVerdict] = []
    usable: list[int] = []
    for k, im in enumerate(images):
        if not (0 <= im.camera < len(cameras)):
            raise InvalidInputError(f"image {im.name!r}: camera index {im.camera} out of range 0..{len(cameras) - 1}")
        pi = np.asarray(im.point_index, dtype=int)
        xy = np.asarray(im.xy_px, dtype=float)
        if xy.shape != (pi.size, 2):
            raise InvalidInputError(f"image {im.name!r}: xy_px shape {xy.shape} does not match {pi.size} point indices")
        if pi.size and (pi.min() < 0 or pi.max() >= M):
            raise InvalidInputError(f"image {im.name!r}: point index out of range 0..{M - 1}")
        v = ImageVerdict(im.name, im.camera, False, n_points=int(pi.size))
        finite = np.all(np.isfinite(xy), axis=1)
        if np.count_nonzero(finite) < opt.min_points_per_image:
            v.reason = f"only {int(np.count_nonzero(finite))} measured points (need >= {opt.min_points_per_image})"
        else:
            usable.append(k)
        verdicts.append(v)

    # nominal principal distance per camera
    model = opt.model
    n_par = len(opt.param_names)
    cam_p: list[np.ndarray] = []
    c_nominal: list[float] = []
    for ci, cs in enumerate(cameras):
        if initial is not None and ci in initial:
            p0 = np.asarray(initial[ci], float).copy()
            if p0.shape != (n_par,):
                raise InvalidInputError(f"initial[{ci}]: shape {p0.shape}; expected ({n_par},) parameters of the "
                                        f"{model.value} model ({' '.join(opt.param_names)})")
            cam_p.append(p0)
            c_nominal.append(float("nan"))
            continue
        c = cs.nominal.get("c_mm")
        if c is None:
            ks = [k for k in usable if images[k].camera == ci]
            c = init_focal_planar(cs, [points[np.asarray(images[k].point_index)] for k in ks],
                                  [np.asarray(images[k].xy_px, float) for k in ks])
            if c is None:
                for k in ks:
                    verdicts[k].reason = "camera has no nominal focal length and too few planar views to initialise it"
                usable = [k for k in usable if images[k].camera != ci]
                c = 1.0
        cam_p.append(nominal_vector(cs, float(c), model))
        c_nominal.append(float(c))

    # resection of every usable image
    poses: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for n_done, k in enumerate(list(usable)):
        im = images[k]
        if initial_poses is not None:
            poses[k] = (np.asarray(initial_poses[k][0], float), np.asarray(initial_poses[k][1], float))
            continue
        pi = np.asarray(im.point_index, int)
        xy = np.asarray(im.xy_px, float)
        fin = np.all(np.isfinite(xy), axis=1)
        xyz = points[pi[fin]]
        planar = is_planar(xyz)
        if not planar and xyz.shape[0] < 6:
            verdicts[k].reason = f"only {xyz.shape[0]} non-coplanar points (need >= 6 for resection)"
            usable.remove(k)
            continue
        K = pinhole_K(cam_p[im.camera], cameras[im.camera], model)
        Rt, why = resect(xyz, xy[fin], K, planar)
        if Rt is None:
            verdicts[k].reason = why
            usable.remove(k)
            continue
        poses[k] = Rt
        if progress is not None:
            progress("resection", n_done + 1, len(images))
    if not usable:
        return empty_result(verdicts, Termination.TOO_FEW_OBSERVATIONS, "no usable image: " +
                            "; ".join(f"{v.name}: {v.reason}" for v in verdicts[:5]))

    # observation table
    obs_img, obs_pt, obs_xy, obs_sig = [], [], [], []
    have_sigma = all(images[k].sigma_px is not None for k in usable)
    for k in usable:
        im = images[k]
        pi = np.asarray(im.point_index, int)
        xy = np.asarray(im.xy_px, float)
        sg = np.asarray(im.sigma_px, float) if im.sigma_px is not None else np.full(xy.shape, opt.default_sigma_px)
        fin = np.all(np.isfinite(xy), axis=1) & np.all(np.isfinite(sg) & (sg > 0), axis=1)
        obs_img.append(np.full(np.count_nonzero(fin), k))
        obs_pt.append(pi[fin])
        obs_xy.append(xy[fin])
        obs_sig.append(sg[fin])
    obs_img = np.concatenate(obs_img)
    obs_pt = np.concatenate(obs_pt)
    obs_xy = np.concatenate(obs_xy)
    obs_sig = np.concatenate(obs_sig)
    active = np.ones(obs_img.size, dtype=bool)
    blunders: list[dict] = []

    # rig structure
    frames_of = {k: images[k].frame for k in usable}
    rig_members: dict[int, int] = {}  # camera -> rig index
    ref_cam: int | None = None
    if rig:
        ref_cam = min(images[k].camera for k in usable)
        others = sorted({images[k].camera for k in usable} - {ref_cam})
        for ci in others:
            both = [f for f in {frames_of[k] for k in usable if images[k].camera == ci}
                    if f is not None and any(frames_of[j] == f and images[j].camera == ref_cam for j in usable)]
            if both:
                rig_members[ci] = len(rig_members)

    def build(cam_params, free_masks, active_mask):
        sel = np.nonzero(active_mask)[0]
        used_imgs = sorted(set(obs_img[sel].tolist()))
        # pose table
        pose_keys: list = []
        pose_of_img: dict[int, int] = {}
        rig_of_img: dict[int, int] = {}
        if rig and rig_members:
            frame_pose: dict[str, int] = {}
            for k in used_imgs:
                im = images[k]
                f = frames_of[k]
                if im.camera in rig_members and f is not None and any(
                        frames_of[j] == f and images[j].camera == ref_cam for j in used_imgs):
                    continue
                if im.camera == ref_cam and f is not None:
                    frame_pose[f] = len(pose_keys)
                pose_of_img[k] = len(pose_keys)
                pose_keys.append(k)
            for k in used_imgs:
                if k not in pose_of_img:
                    pose_of_img[k] = frame_pose[frames_of[k]]
                    rig_of_img[k] = rig_members[images[k].camera]
        else:
            for k in used_imgs:
                pose_of_img[k] = len(pose_keys)
                pose_keys.append(k)
        R = np.array([poses[k][0] for k in pose_keys])
        t = np.array([poses[k][1] for k in pose_keys])
        blocks = [CameraBlock(cam_params[ci], free_masks[ci], cameras[ci].image_size, cameras[ci].pitch_mm, cameras[ci].name,
                              model) for ci in range(len(cameras))]
        oc = np.array([images[k].camera for k in obs_img[sel]], dtype=int)
        op = np.array([pose_of_img[k] for k in obs_img[sel]], dtype=int)
        orig = np.array([rig_of_img.get(k, -1) for k in obs_img[sel]], dtype=int)
        G = len(rig_members)
        rigR = np.array([rig_init[g][0] for g in range(G)]) if G else None
        rigt = np.array([rig_init[g][1] for g in range(G)]) if G else None
        prob = BundleProblem(blocks, R, t, points, oc, op, obs_pt[sel], obs_xy[sel], obs_sig[sel], obs_rig=orig,
                             rig_R=rigR, rig_t=rigt, point_prior_std=point_std)
        return prob, sel, pose_keys

    rig_init: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def init_rig():
        for ci, g in rig_members.items():
            rels = []
            for k in usable:
                if images[k].camera != ci or frames_of[k] is None:
                    continue
                refs = [j for j in usable if images[j].camera == ref_cam and frames_of[j] == frames_of[k]]
                if refs:
                    R1, t1 = poses[refs[0]]
                    R2, t2 = poses[k]
                    Rr = R2 @ R1.T
                    rels.append((Rr, t2 - Rr @ t1))
            Rm = mean_rotation(np.array([r[0] for r in rels]))
            tm = np.median(np.array([r[1] for r in rels]), axis=0)
            rig_init[g] = (Rm, tm)

    def store(sol: BundleSolution, pose_keys):
        for j, k in enumerate(pose_keys):
            poses[k] = (sol.R[j], sol.t[j])
        for g in range(sol.rig_R.shape[0]):
            rig_init[g] = (sol.rig_R[g], sol.rig_t[g])

    def snoop(cam_params, free_masks, critical, use_apriori, stage_name):
        nonlocal active
        sol = None
        for rnd in range(opt.max_snooping_rounds + 1):
            prob, sel, pose_keys = build(cam_params, free_masks, active)
            sol = solve_bundle(prob, engine=opt.solver)
            if not sol.outcome.success:
                return sol, sel, pose_keys
            store(sol, pose_keys)
            cam_params = [cb.params for cb in sol.cameras]
            if not opt.snooping or rnd == opt.max_snooping_rounds:
                break
            w = sol.normalized_residuals
            if not use_apriori:
                w = w / sol.sigma0
            wmax = np.nanmax(np.abs(w), axis=1)
            wmax = np.where(np.isfinite(wmax), wmax, 0.0)
            bad = wmax > critical
            if not np.any(bad):
                break
            # the worst observation of each image
            removed = 0
            for k in set(obs_img[sel][bad].tolist()):
                cand = np.nonzero(bad & (obs_img[sel] == k))[0]
                j = cand[np.argmax(wmax[cand])]
                gi = sel[j]
                # keep at least the minimum per image
                if np.count_nonzero(active & (obs_img == k)) <= opt.min_points_per_image:
                    continue
                active[gi] = False
                removed += 1
                blunders.append({"stage": stage_name, "image": images[k].name, "point": int(obs_pt[gi]),
                                 "w": float(wmax[j]), "residual_px": [float(v) for v in sol.residuals_px[j]]})
            if removed == 0:
                break
        return sol, sel, pose_keys

    # ---- stage 1: nominal interior orientation, poses only --------------------------------
    fixed_masks = [np.zeros(n_par, dtype=bool) for _ in cameras]
    if rig_members:
        init_rig()
    stage1 = {}
    if initial is None:
        sol1, sel1, pk1 = snoop(cam_p, fixed_masks, opt.stage1_critical, False, "stage1")
        if progress is not None:
            progress("stage 1", 1, 1)
        if not sol1.outcome.success:
            return empty_result(verdicts, sol1.outcome.termination, "stage 1: " + sol1.outcome.reason)
        rms1 = float(np.sqrt(np.mean(np.sum(sol1.residuals_px**2, axis=1))))
        stage1 = {"sigma0": sol1.sigma0, "rms_px": rms1, "n_observations": int(sel1.size),
                  "n_blunders": sum(1 for b in blunders if b["stage"] == "stage1"),
                  "c_mm": c_nominal}

    # ---- stage 2: additional parameters free, data snooping --------------------------------
    free2 = opt.stage2_free()
    free_masks = [free2.copy() for _ in cameras]
    use_apriori = have_sigma
    crit = opt.critical_value
    for attempt in range(5):
        sol, sel, pose_keys = snoop(cam_p, free_masks, crit, use_apriori, "stage2")
        if progress is not None:
            progress("stage 2", 1, 1)
        if not sol.outcome.success:
            break
        cam_p = [cb.params for cb in sol.cameras]
        # per-image RMS; reject inconsistent images and repeat
        rms_img = {}
        for k in set(obs_img[sel].tolist()):
            m = obs_img[sel] == k
            rms_img[k] = float(np.sqrt(np.mean(np.sum(sol.residuals_px[m] ** 2, axis=1))))
        med = float(np.median(list(rms_img.values())))
        worst = [k for k, r in rms_img.items() if r > max(opt.max_image_rms_factor * med, 1.0)]
        if not worst or len(rms_img) - len(worst) < 2:
            break
        for k in worst:
            verdicts[k].reason = f"inconsistent: RMS {rms_img[k]:.2f} px after stage 2 (median of images {med:.2f} px)"
            active[obs_img == k] = False
    if sol.outcome.success and opt.snooping:
        # re-admit observations rejected in stage 1 that fit the full model (they were flagged
        # because the nominal model could not explain distortion, not because they are wrong)
        s1 = [i for i, b in enumerate(blunders) if b["stage"] == "stage1"]
        if s1:
            cam_p = [cb.params for cb in sol.cameras]
            inact = ~active & np.isin(obs_img, list({k for k in obs_img[sel]}))
            prob, isel, _ = build(cam_p, free_masks, active | inact)
            res_all, ok_all = residuals(prob)
            # re-admit everything that is not grossly wrong under the full model (|v| < 10 σ); the
            # stage-2 data snooping below then tests them properly (w with redundancy numbers).
            # A threshold at the critical value itself would keep out valid corner points whose
            # raw |v| exceeds it only because their redundancy is low.
            w = np.abs(res_all) / (obs_sig[isel] * (sol.sigma0 if not use_apriori else 1.0))
            back = isel[(np.max(w, axis=1) < 10.0) & ok_all & inact[isel]]
            if back.size:
                active[back] = True
                readm = {(images[obs_img[g]].name, int(obs_pt[g])) for g in back}
                blunders[:] = [b for b in blunders if (b["image"], b["point"]) not in readm]
                sol, sel, pose_keys = snoop(cam_p, free_masks, crit, use_apriori, "stage2")
    if not sol.outcome.success:
        return empty_result(verdicts, sol.outcome.termination, "stage 2: " + sol.outcome.reason, stage1=stage1)
    return assemble(sol, sel, pose_keys, cameras, images, verdicts, obs_img, obs_pt, obs_xy, active, blunders, stage1,
                    opt, rig_members, ref_cam, use_apriori)
