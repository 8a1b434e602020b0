"""The ``orient`` step: tracks and the orientation (incremental, global or ``auto``) -> ``work/reconstruction.*``."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ..._memory import release_free_heap
from ...sfm.globalsfm import GlobalOptions, reconstruct_global
from ...store import ProjectStore
from .features import _initial_cameras
from .options import AUTO_GLOBAL_BELOW, SurveyOptions
from .store import SurveyStore, _read_frame


def step_orient(project: ProjectStore, opt: SurveyOptions, camera=None, progress=None, rgb_camera=None) -> dict:
    from ...sfm.reconstruction import reconstruct
    from ...sfm.tracks import build_tracks

    inputs = SurveyStore(project).load_inputs()
    counts = SurveyStore(project).load_feature_counts()
    names = [im["name"] for im in inputs["images"]]
    cams, cam_ids = _initial_cameras(inputs, camera, rgb_camera)
    cam_list = list(cams)
    image_camera = np.array([cam_list.index(c) for c in cam_ids])
    refine = opt.tie_refinement is not None
    xy, size, angle = [], [], []
    for n in names:  # one read per file; size and angle only for the refinement (descriptors are dropped)
        z = SurveyStore(project).load_features(n)
        xy.append(z["xy"])
        if refine:
            size.append(z["size"])
            angle.append(z["angle"])
    pairs = []
    pc = {}
    for i, j, npu, nv, reason in SurveyStore(project).load_pairs()["pairs"]:
        if reason:
            continue
        idx = SurveyStore(project).load_matches(i, j)
        pairs.append((i, j, idx))
        pc[(i, j)] = len(idx)
    tracks = build_tracks([int(counts[n]) for n in names], pairs)
    del pairs  # the matches (8 B per match) are in the tracks now: not held through the reconstruction
    release_free_heap()
    refinement = None
    if refine and len(tracks.track):
        from ...sfm.lsm import refine_tracks

        xy, tracks, refinement = refine_tracks(tracks, xy, lambda i: _read_frame(project, names[i]), size_by_image=size,
                                               angle_by_image=angle, options=opt.tie_refinement)
    del size, angle
    for n, a in zip(names, xy):  # what orient used, for georef and the exports (a rerun starts from the keypoints)
        SurveyStore(project).save_tie_xy(n, a)
    ropt = opt.reconstruction
    if camera is not None:
        ropt = replace(ropt, free_intrinsics=())
    cam_objs = [cams[c] for c in cam_list]
    mapper_auto = None
    if opt.mapper == "global":
        rec = reconstruct_global(cam_objs, image_camera, xy, tracks, pc, ropt, opt.global_orientation, on_progress=progress)
        used = "global"
    else:
        rec = reconstruct(cam_objs, image_camera, xy, tracks, pc, ropt, on_progress=progress)
        used = "incremental"
        if opt.mapper == "auto":
            rec, used, mapper_auto = _auto_global(rec, cam_objs, image_camera, xy, tracks, pc, ropt, progress,
                                                  opt.global_orientation)
    release_free_heap()
    SurveyStore(project).save_reconstruction_arrays(R=rec.R, t=rec.t, registered=rec.registered, component=rec.component,
              points=rec.points, track=tracks.track, image=tracks.image, feature=tracks.feature, obs_valid=rec.obs_valid,
              image_camera=image_camera)
    SurveyStore(project).save_reconstruction_meta({
        "cameras": {c: rec.cameras[k].to_dict() for k, c in enumerate(cam_list)}, "camera_ids": cam_list,
        "termination": rec.termination.value, "reason": rec.reason, "log": rec.log,
        "status": [{"registered": bool(s.registered), "component": int(s.component), "reason": s.reason} for s in rec.status],
        "tracks": int(tracks.n_tracks), "tracks_split": int(tracks.n_split), "seconds": rec.seconds,
        "tie_refinement": refinement, "mapper": used, "mapper_auto": mapper_auto})
    return {"oriented": int(rec.registered.sum()), "of": len(names), "components": [len(c) for c in rec.components()],
            "tracks": int(tracks.n_tracks), "reason": rec.reason, "tie_refinement": refinement, "mapper": used,
            "mapper_auto": mapper_auto}


def _auto_global(rec, cameras, image_camera, xy, tracks, pair_counts, ropt, progress, gopt: GlobalOptions | None = None):
    """``mapper="auto"``: the incremental reconstruction ``rec``, or the global one when the incremental one's largest
    block holds fewer than :data:`AUTO_GLOBAL_BELOW` of the images and the global one's largest block is larger while
    it orients at least as many images over all its blocks (the held-out 48-station ring of
    ``tests/test_survey_building_rings.py`` on RTK GNSS: the incremental orients 44 images in blocks of 26 and 18, both
    georeferenced, then 48/48 with the images added at their GNSS positions; keeping global's larger block gave 34/48).

    Returns (reconstruction, mapper used, summary dict or None when global was not tried). The summary has the
    largest block and the images oriented of each, which was kept and the global run's time; the kept
    reconstruction's log says why.
    """
    gopt = gopt or GlobalOptions()
    n = len(image_camera)
    inc = max((len(c) for c in rec.components()), default=0)
    if inc >= AUTO_GLOBAL_BELOW * n or n < gopt.min_part_images:
        return rec, "incremental", None
    t0 = time.perf_counter()
    glob = reconstruct_global(cameras, image_camera, xy, tracks, pair_counts, ropt, gopt, on_progress=progress)
    gl = max((len(c) for c in glob.components()), default=0)
    n_inc, n_gl = int(rec.registered.sum()), int(glob.registered.sum())
    # a larger largest block, and not fewer images oriented over all blocks (with GNSS every block is georeferenced
    # on its own, so blocks that are apart count too)
    keep = "global" if gl > inc and n_gl >= n_inc else "incremental"
    summary = {"incremental_largest_block": int(inc), "global_largest_block": int(gl), "incremental_oriented": n_inc,
               "global_oriented": n_gl, "images": int(n), "kept": keep,
               "global_seconds": round(time.perf_counter() - t0, 3), "global_reason": glob.reason}
    msg = (f"mapper auto: the incremental orientation's largest block holds {inc}/{n} images (< {AUTO_GLOBAL_BELOW:.0%}; "
           f"{n_inc} oriented in all); the global orientation's {gl}/{n} ({n_gl} in all): {keep} kept")
    if keep == "global":
        glob.log.insert(0, msg)
        return glob, "global", summary
    rec.log.append(msg)
    return rec, "incremental", summary
