"""The ``matching`` step: candidate pairs, matching and verification (dask tasks), the low-texture fallback's ties."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...store import FolderProject, ProjectStore
from .controls import _gnss_xyz
from .features import _fixed_pattern, _initial_cameras, _masked_overlay, _overlay_keys, feature_task
from .cache import open_cache
from .options import LOW_TEXTURE_GUIDED_RADIUS_PX, LOW_TEXTURE_PATTERN_SIGMA_PX, LOW_TEXTURE_SHARE, SurveyOptions
from .store import (FEATURE_COUNTS_KEY, LOW_TEXTURE_PATTERN_FINE_KEY, LOW_TEXTURE_PREFIX, PAIRS_KEY, SurveyStore,
                    _load_npz, _load_npz_cached, _read_frame, features_key, matches_key, primary_key)
from .tasks import _run_tasks


def match_task(args) -> tuple[int, int, int, int, str, bool]:
    """Unit of work: match and verify one pair, written to ``matches/<i>_<j>.npz`` (or ``<prefix>matches/``); read
    from the tie-point cache (:class:`~.cache.TieCache`, the task's last argument) when it holds the pair. Returns
    ``(i, j, putative, verified, reason, read from the cache)``."""
    project, i, j, ni, nj, cam_i, cam_j, mopt, *rest = args
    pre = rest[0] if rest else ""
    cache = rest[1] if len(rest) > 1 else None
    fi = _load_npz_cached(project, features_key(ni, pre))
    fj = _load_npz_cached(project, features_key(nj, pre))
    key = cache.matches_key(fi, fj, cam_i, cam_j, mopt) if cache is not None else None
    hit = cache.get_matches(key) if key is not None else None
    if hit is not None:
        inl, n_putative, n_verified, reason = hit
        if not reason:
            SurveyStore(project).save_matches(i, j, inl, pre)
        return i, j, n_putative, n_verified, reason, True
    i, j, n_putative, n_verified, reason, inl = _match_pair(project, i, j, fi, fj, cam_i, cam_j, mopt, pre)
    if key is not None:
        cache.put_matches(key, inl, n_putative, n_verified, reason)
    return i, j, n_putative, n_verified, reason, False


def _match_pair(project, i, j, fi, fj, cam_i, cam_j, mopt, pre):
    """Match and verify one pair (its verified matches saved): ``(i, j, putative, verified, reason, inliers)``."""
    from ...sfm.matching import guided_matches, homography_prior, match_descriptors, verify_pair

    m = match_descriptors(fi["descriptors"], fj["descriptors"], ratio=mopt.ratio)
    if mopt.guided_radius_px > 0 and fi["descriptors"].dtype != np.uint8:
        H = homography_prior(fi["xy"], fj["xy"], m, seed=mopt.seed)
        if H is not None:
            g = guided_matches(fi["xy"], fi["descriptors"], fj["xy"], fj["descriptors"], H, radius_px=mopt.guided_radius_px)
            if len(g) > len(m):
                m = g
    if cam_i is not None and cam_j is not None and len(m) >= mopt.min_inliers:
        ri = cam_i.unproject(fi["xy"][m[:, 0]])[:, :2]
        rj = cam_j.unproject(fj["xy"][m[:, 1]])[:, :2]
        full_i = np.zeros((len(fi["xy"]), 2))
        full_j = np.zeros((len(fj["xy"]), 2))
        full_i[m[:, 0]] = ri
        full_j[m[:, 1]] = rj
        inl, model, reason = verify_pair(fi["xy"], fj["xy"], m, camera1=cam_i, camera2=cam_j, rays1=full_i, rays2=full_j, options=mopt)
    else:
        inl, model, reason = verify_pair(fi["xy"], fj["xy"], m, options=mopt)
    if not reason:
        SurveyStore(project).save_matches(i, j, inl, pre)
    return i, j, len(m), len(inl), reason, inl


#: the low-texture fallback tracks frames with positions as a sequence when the median distance between consecutive
#: frames is at most this multiple of the median nearest-neighbour distance (:func:`_sequence_order_ratio`)
SEQUENCE_ORDER_RATIO = 3.0


def _sequence_order_ratio(xyz) -> float | None:
    """Median distance between consecutive frames (acquisition order) over the median distance of each frame to its
    nearest neighbour; None with fewer than 3 positions or all positions equal.

    A walk along a wall or a flight line in serpentine order gives ~1 (consecutive frames are neighbours): with a
    30-frame walk (0.65 m apart) 1.05 with exact positions, 1.0-1.1 with RTK (3 cm), 1.3-1.7 with 0.3-1 m of GNSS
    noise, 1.8-2.6 with 3 m (positions that cannot order the frames: the acquisition order is the better guess);
    the same frames shuffled 7-11, a shuffled 5 x 10 grid 3.6."""
    from scipy.spatial import cKDTree

    X = np.asarray(xyz, float)
    fin = np.all(np.isfinite(X), axis=1)
    X = X[fin]
    if len(X) < 3:
        return None
    dc = np.linalg.norm(np.diff(X, axis=0), axis=1)
    dn = cKDTree(X).query(X, k=2)[0][:, 1]
    med_n = float(np.median(dn))
    if not med_n > 0:
        return None
    return float(np.median(dc) / med_n)


def _track_thermal_sequence(project: ProjectStore, inputs: dict, thermal: list, cams: dict, cam_ids: list,
                            pattern_key: str | None, cache=None, from_cache: dict | None = None) -> tuple[dict, list]:
    """Low-texture fallback for a sequence (no positions, or positions in walk order): the thermal frames tracked
    frame to frame (input order).

    Writes ``lowtexture/features/<name>.npz`` (the tracked points; no descriptors: zero rows) and
    ``lowtexture/matches/<i>_<j>.npz`` of the verified consecutive pairs. Returns (feature counts by name, match
    results ``(i, j, n_putative, n_verified, reason)`` of the consecutive pairs).
    """
    from ...sfm.lowtexture import TrackingOptions, track_sequence

    names = [inputs["images"][k]["name"] for k in thermal]
    pattern = _load_npz(project, pattern_key)["pattern"] if pattern_key else None
    overlay = _overlay_keys(project, inputs)
    shapes = [(int(inputs["images"][k]["height"]), int(inputs["images"][k]["width"])) for k in thermal]
    counts: dict = {}
    res: list = []
    # runs of consecutive frames of one size (a sequence of one sensor); the tracker sees one run at a time
    start = 0
    for end in range(1, len(thermal) + 1):
        if end < len(thermal) and shapes[end] == shapes[start]:
            continue
        run = thermal[start:end]
        pat = pattern if pattern is not None and pattern.shape == shapes[start] else None

        def load(a, run=run):
            nm = inputs["images"][run[a]]["name"]
            return _masked_overlay(project, _read_frame(project, nm), overlay.get(nm))

        run_cams = [cams[cam_ids[k]] for k in run]
        key = (cache.tracks_key((load(a) for a in range(len(run))), pat, run_cams, TrackingOptions())
               if cache is not None else None)
        st = cache.get_tracks(key) if key is not None else None
        if st is None:
            st = track_sequence(load, len(run), pattern=pat, cameras=run_cams)
            if key is not None:
                cache.put_tracks(key, st)
        elif from_cache is not None:
            from_cache["tracks"] = from_cache.get("tracks", 0) + 1
        for a, k in enumerate(run):
            nm = inputs["images"][k]["name"]
            xy = st.xy[a]
            SurveyStore(project).save_features(nm, LOW_TEXTURE_PREFIX, xy=xy, size=np.full(len(xy), 12.0, np.float32),
                      angle=np.zeros(len(xy), np.float32), descriptors=np.zeros((len(xy), 128), np.float32))
            counts[nm] = len(xy)
        for a in range(1, len(run)):
            i, j = run[a - 1], run[a]
            m = st.matches.get((a - 1, a))
            reason = st.reasons.get((a - 1, a), "")
            if m is not None and not reason:
                SurveyStore(project).save_matches(i, j, m, LOW_TEXTURE_PREFIX)
            res.append((i, j, int(st.n_putative.get((a - 1, a), 0)), 0 if m is None or reason else len(m), reason))
        if end < len(thermal):
            res.append((thermal[end - 1], thermal[end], 0, 0, f"frame size {shapes[end]} differs from the previous frame's"))
        start = end
    return counts, res


def step_matching(project: ProjectStore, opt: SurveyOptions, camera=None, progress=None, rig=None, *,
                  low_texture_only: bool = False) -> dict:
    """Pairs, matching and verification; with ``low_texture == "auto"`` the low-texture fallback when fewer than
    80 % of the thermal frames find a verified pair. ``low_texture_only``: the primary matching is already in
    ``work/pairs.json`` (its orientation left < 80 % of the thermal frames in one block): only the fallback runs,
    and its ties replace the thermal ones whenever it verifies any pair (the orientation judges them)."""
    from ...sfm.matching import select_pairs

    inputs = SurveyStore(project).load_inputs()
    cams, cam_ids = _initial_cameras(inputs, camera, getattr(rig, "rgb_camera", None))
    xyz, _, crs, _ = _gnss_xyz(inputs, opt, opt.crs)
    names = [im["name"] for im in inputs["images"]]
    pairs = select_pairs(len(names), xyz, options=opt.matching)
    rig_pairs: set = set()
    if rig is not None:  # rig mode: every thermal image is matched with its RGB partner (cross-modal ties)
        from ...sfm.rig import pair_rig_images

        master, _, _ = pair_rig_images(rig, inputs["images"])
        rig_pairs = {(min(a, b), max(a, b)) for a, b in master.items()}
        pairs = sorted(set(pairs) | rig_pairs)
    store = project if not isinstance(project, FolderProject) else FolderProject(project.root, durable=project.durable)

    cache = open_cache(opt.cache)
    from_cache = {"features": 0, "pairs": 0}

    def match(pre, mopt=None, pair_list=None):
        mopt = mopt or opt.matching
        tasks = [(store, i, j, names[i], names[j], cams[cam_ids[i]], cams[cam_ids[j]], mopt, pre, cache)
                 for i, j in (pairs if pair_list is None else pair_list)]
        res = _run_tasks(match_task, tasks, opt, progress, "matching")
        from_cache["pairs"] += sum(r[5] for r in res)
        return [r[:5] for r in res]

    def connected(res):
        return len({k for i, j, npu, nv, reason in res if not reason for k in (i, j)})

    if low_texture_only:
        prev = SurveyStore(project).load_pairs()
        res = [tuple(r) for r in prev["pairs"]]
        info = dict(prev.get("features", {}))
    else:
        res = match("")
        info = {"features": f"{opt.features.detector.value}/{opt.features.enhancement.value}", "connected": connected(res)}
    n = len(names)
    # the low-texture fallback concerns the thermal frames only: RGB images of a combined block keep their own
    # features and matches (their texture is fine; a sequence-window pair list and thermal preprocessing would
    # only lose their links -- measured on the frescoes, RGB + thermal: the RGB block fell from 40 to 27 images)
    thermal = [k for k, im in enumerate(inputs["images"]) if im.get("sensor", "thermal") == "thermal"]
    is_th = np.zeros(n, bool)
    is_th[thermal] = True
    nt = len(thermal)

    def connected_thermal(res):
        return len({k for i, j, npu, nv, reason in res if not reason for k in (i, j) if is_th[k]})

    if opt.low_texture == "auto" and nt >= 2 and "low_texture" not in info and (
            low_texture_only or connected_thermal(res) < LOW_TEXTURE_SHARE * nt):
        # low-texture frames (facades, walls, water, fields): the sensor's fixed pattern estimated from the
        # sequence and removed, more SIFT features (lower contrast threshold), and matches guided by a
        # homography from the few that pass the global ratio test
        th_names = [names[k] for k in thermal]
        mopt_lt = replace(opt.matching, guided_radius_px=LOW_TEXTURE_GUIDED_RADIUS_PX)
        pairs_lt = [(i, j) for i, j in pairs if is_th[i] and is_th[j]]
        have_pos = xyz is not None and int(np.all(np.isfinite(xyz[thermal]), axis=1).sum()) >= 2
        order_ratio = _sequence_order_ratio(xyz[thermal]) if have_pos else None
        as_sequence = not have_pos or (order_ratio is not None and order_ratio <= SEQUENCE_ORDER_RATIO)
        if not as_sequence:
            pattern_key = _fixed_pattern(project, inputs, th_names)
            lt = replace(opt.features, detector="sift", enhancement="clahe", contrast_threshold=0.005,
                         max_features=max(opt.features.max_features, 4000))
            overlay = _overlay_keys(project, inputs)
            res_f = _run_tasks(feature_task, [(store, nm, lt, "lowtexture/features", pattern_key, overlay.get(nm), cache)
                                              for nm in th_names], opt, None, "features")
            counts_lt = {nm: n for nm, n, _ in res_f}
            from_cache["features"] += sum(hit for _, _, hit in res_f)
            res_lt = match(LOW_TEXTURE_PREFIX, mopt_lt, pairs_lt)
            how = "sift/clahe on pattern-corrected thermal frames, guided matching"
        else:
            # no positions, or positions that say the acquisition order is a walk (consecutive frames are neighbours):
            # the frames are taken as a sequence (acquisition order) and tracked frame to frame
            pattern_key = _fixed_pattern(project, inputs, th_names, highpass_sigma_px=LOW_TEXTURE_PATTERN_SIGMA_PX,
                                         key=LOW_TEXTURE_PATTERN_FINE_KEY)
            counts_lt, res_lt = _track_thermal_sequence(project, inputs, thermal, cams, cam_ids, pattern_key, cache,
                                                        from_cache)
            how = "pattern-corrected thermal frames tracked frame to frame (KLT), consecutive pairs verified"
        info["low_texture"] = {"features": how, "sequence": as_sequence, "order_ratio": order_ratio,
                               "fixed_pattern": bool(pattern_key), "thermal_connected": connected_thermal(res_lt),
                               "thermal_connected_before": connected_thermal(res), "thermal_images": nt,
                               "trigger": ("orientation: < 80 % of the thermal frames in one block" if low_texture_only
                                           else "matching: < 80 % of the thermal frames with a verified pair")}
        if connected_thermal(res_lt) > (1 if low_texture_only else connected_thermal(res)):
            if not low_texture_only:
                # the primary matching, put aside: the orientation step puts it back when the fallback's blocks are
                # refused (_low_texture_check), so that ``auto`` is never worse than ``off`` there
                prim = [features_key(nm) for nm in th_names]
                prim += [matches_key(i, j) for i, j, npu, nv, reason in res if not reason]
                for k in prim:
                    if project.exists(k):
                        project.write_bytes(primary_key(k), project.read_bytes(k))
                project.write_json(primary_key(FEATURE_COUNTS_KEY), SurveyStore(project).load_feature_counts())
                project.write_json(primary_key(PAIRS_KEY),
                                   {"pairs": [[i, j, npu, nv, reason] for i, j, npu, nv, reason in res],
                                    "features": {k: v for k, v in info.items() if k != "low_texture"}})
                info["primary_kept"] = [k for k in prim if project.exists(k)]
            for nm in th_names:
                project.write_bytes(features_key(nm), project.read_bytes(features_key(nm, LOW_TEXTURE_PREFIX)))
            for i, j, npu, nv, reason in res_lt:
                if not reason:
                    project.write_bytes(matches_key(i, j), project.read_bytes(matches_key(i, j, LOW_TEXTURE_PREFIX)))
            SurveyStore(project).save_feature_counts({**SurveyStore(project).load_feature_counts(), **counts_lt})
            # pairs of a thermal frame with an RGB image are matched again: the thermal features changed
            cross = [(i, j) for i, j in pairs if is_th[i] != is_th[j]]
            res_cross = match("", None, cross) if cross else []
            res = sorted([r for r in res if not (is_th[r[0]] or is_th[r[1]])] + list(res_lt) + list(res_cross),
                         key=lambda r: (r[0], r[1]))
            info["used"] = ("low-texture fallback for the thermal frames (fixed pattern removed, SIFT with a low "
                            "contrast threshold, homography-guided matching)" if not as_sequence else
                            "low-texture fallback for the thermal frames (fixed pattern removed, frames tracked as a "
                            "sequence, consecutive pairs verified)")
    kept = [(i, j, nv) for i, j, npu, nv, reason in res if not reason]
    SurveyStore(project).save_pairs({"pairs": [[i, j, npu, nv, reason] for i, j, npu, nv, reason in res], "features": info})
    out = {"pairs_tried": len(pairs), "pairs_verified": len(kept), "images_connected": connected(res), "features": info,
           "median_verified_matches": float(np.median([k[2] for k in kept])) if kept else 0.0}
    if cache is not None:
        out["from_cache"] = from_cache
    return out
