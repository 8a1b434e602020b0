"""The ``features`` step: tie-point features per frame (dask tasks), a burned-in display masked, the sensor's fixed
pattern, the starting cameras."""

from __future__ import annotations

import io

import numpy as np

from ...errors import ConfigError
from ...store import FolderProject, ProjectStore
from .cache import open_cache
from .options import SurveyOptions
from .store import LOW_TEXTURE_PATTERN_KEY, OVERLAY_MASK_KEY, SurveyStore, _load_npz_cached, _read_frame, _save_npz
from .tasks import _run_tasks


def feature_task(args) -> tuple[str, int, bool]:
    """Unit of work: features of one frame, written to ``<folder>/<name>.npz`` (``features/`` by default); read from
    the tie-point cache (:class:`~.cache.TieCache`, the task's last argument) when it holds them. Returns
    ``(name, number of features, read from the cache)``."""
    project, name, fopt, *rest = args
    folder = rest[0] if rest else "features"
    pattern_key = rest[1] if len(rest) > 1 else None
    overlay_key = rest[2] if len(rest) > 2 else None
    cache = rest[3] if len(rest) > 3 else None
    from ...sfm.features import extract_features
    from ...sfm.keypoints import to_pixel_centre_convention

    frame = _read_frame(project, name)
    if pattern_key and frame.ndim == 2:
        pat = _load_npz_cached(project, pattern_key)["pattern"]
        if pat.shape == frame.shape:  # the sensor's fixed pattern, estimated from the sequence
            frame = frame.astype(np.float32) - pat
    frame = _masked_overlay(project, frame, overlay_key)
    key = cache.features_key(frame, fopt) if cache is not None else None
    data = cache.get_features(key) if key is not None else None
    if data is not None:
        project.write_bytes(f"{folder}/{name}.npz", data)
        with np.load(io.BytesIO(data)) as z:
            return name, len(z["xy"]), True
    # (0, 0) = centre of the top-left pixel, like the camera model, GCP and manual-tie measurements
    f = to_pixel_centre_convention(extract_features(frame, fopt), fopt)
    _save_npz(project, f"{folder}/{name}.npz", **f.to_npz_dict())
    if key is not None:
        cache.put_features(key, project.read_bytes(f"{folder}/{name}.npz"))
    return name, len(f), False


def _masked_overlay(project: ProjectStore, frame: np.ndarray, overlay_key: str | None) -> np.ndarray:
    """``frame`` as float32 with the pixels of a burned-in display (``overlay_key``: :func:`_overlay_mask`) set to
    NaN (no tie point there); unchanged without a key or when the mask's size differs."""
    if not overlay_key or frame.ndim != 2:
        return frame
    mask = _load_npz_cached(project, overlay_key)["mask"]
    if mask.shape != frame.shape:
        return frame
    out = frame.astype(np.float32)
    out[mask] = np.nan
    return out


def _overlay_mask(project: ProjectStore, inputs: dict) -> dict | None:
    """A display burned into the 8-bit thermal renderings (``unit`` dn), found from the frames of the most common
    size (:func:`~thermogrammetry.sfm.features.static_overlay`); writes ``features/overlay.npz`` and returns
    ``{"key", "share", "frames", "images", "size"}`` (share of the frame masked, frames it was found from, images of
    that size it applies to, [width, height]), or None."""
    from ...sfm.features import OVERLAY_MIN_FRAMES, static_overlay

    members = _largest_size_group(inputs, _is_thermal_rendering)
    if len(members) < OVERLAY_MIN_FRAMES:
        return None
    # the frames static_overlay uses (it takes at most 60, fewer when they are large)
    frames = [f for f in (_read_frame(project, nm) for nm in _evenly_spaced(members, 60)) if f.ndim == 2]
    mask = static_overlay(frames)
    if mask is None:
        return None
    key = OVERLAY_MASK_KEY
    _save_npz(project, key, mask=mask)
    return {"key": key, "share": float(mask.mean()), "frames": len(frames), "images": len(members),
            "size": [int(mask.shape[1]), int(mask.shape[0])]}


def _is_thermal_rendering(im: dict) -> bool:
    """An input image (``work/inputs.json``) that is an 8-bit rendering of a thermal frame (unit dn)."""
    return im.get("sensor", "thermal") == "thermal" and im.get("unit") == "dn"


def _largest_size_group(inputs: dict, keep) -> list:
    """Names of the images that ``keep(image dict)`` accepts, those of the most common frame size (the first such
    size in input order on a tie); [] when none is accepted."""
    groups: dict = {}
    for im in inputs["images"]:
        if keep(im):
            groups.setdefault((int(im["height"]), int(im["width"])), []).append(im["name"])
    return max(groups.values(), key=len) if groups else []


def _evenly_spaced(items: list, n: int) -> list:
    """At most ``n`` of ``items``, evenly spaced from the first to the last: the frames that
    :func:`~thermogrammetry.sfm.features.fixed_pattern` and ``static_overlay`` would pick themselves (only those
    are read)."""
    return [items[k] for k in np.unique(np.linspace(0, len(items) - 1, min(len(items), n)).round().astype(int))]


def _overlay_keys(project: ProjectStore, inputs: dict) -> dict:
    """image name -> key of the burned-in display's mask that the features step found for it (``work/overlay.json``)."""
    ov = SurveyStore(project).load_overlay()
    if not ov.get("found"):
        return {}
    w, h = ov["size"]
    return {im["name"]: ov["key"] for im in inputs["images"]
            if _is_thermal_rendering(im) and int(im["width"]) == w and int(im["height"]) == h}


def _initial_cameras(inputs: dict, camera=None, rgb_camera=None) -> tuple[dict, list]:
    """Camera id -> starting Camera, and the camera id of each image (``rgb_camera``: the rig file's)."""
    from ...camera import Camera

    groups: dict[tuple, str] = {}
    cams, ids = {}, []
    for im in inputs["images"]:
        key = (im["sensor"], im["width"], im["height"], round(im["camera_guess"]["f_px"], 1))
        if key not in groups:
            cid = im["sensor"] if not any(k[0] == im["sensor"] for k in groups) else f"{im['sensor']}{len(groups) + 1}"
            groups[key] = cid
            if camera is not None and im["sensor"] == "thermal":
                if tuple(camera.image_size) != (im["width"], im["height"]):
                    raise ConfigError(f"camera file: image size {camera.image_size} differs from the frames' "
                                      f"{im['width']}x{im['height']} ({im['name']})")
                cams[cid] = camera
            elif rgb_camera is not None and im["sensor"] == "rgb" and tuple(rgb_camera.image_size) == (im["width"], im["height"]):
                cams[cid] = rgb_camera
            else:
                w, h, f = im["width"], im["height"], im["camera_guess"]["f_px"]
                pitch = im["camera_guess"].get("pitch_um")
                # a restart from a first orientation's self-calibration (workflow._restart_from_self_calibration):
                # its focal length and radial distortion
                st = im["camera_guess"].get("start") or {}
                f = float(st.get("fx", f))
                cams[cid] = Camera("opencv", (w, h), dict(fx=f, fy=f, cx=(w - 1) / 2, cy=(h - 1) / 2,
                                                          **{k: float(st[k]) for k in ("k1", "k2") if k in st}),
                                   pixel_pitch_um=pitch, name=cid)
        ids.append(groups[key])
    return cams, ids


def step_features(project: ProjectStore, opt: SurveyOptions, progress=None) -> dict:
    inputs = SurveyStore(project).load_inputs()
    store = project if not isinstance(project, FolderProject) else FolderProject(project.root, durable=project.durable)
    ov = _overlay_mask(project, inputs)
    SurveyStore(project).save_overlay({"found": False} if ov is None else {"found": True, **ov})
    keys = _overlay_keys(project, inputs)
    cache = open_cache(opt.cache)
    res = _run_tasks(feature_task, [(store, im["name"], opt.features, "features", None, keys.get(im["name"]), cache)
                                    for im in inputs["images"]], opt, progress, "features")
    counts = {name: n for name, n, _ in res}
    SurveyStore(project).save_feature_counts(counts)
    out = {"images": len(counts), "median_features": float(np.median(list(counts.values()))) if counts else 0.0}
    if cache is not None:
        out["from_cache"] = sum(hit for _, _, hit in res)
    if ov is not None:
        out["overlay_share"] = ov["share"]
    return out


def _fixed_pattern(project: ProjectStore, inputs: dict, names: list, *, highpass_sigma_px: float = 0.0,
                   key: str = LOW_TEXTURE_PATTERN_KEY) -> str | None:
    """Estimate the thermal sensor's fixed pattern from its frames (the most common frame size); its key or None."""
    from ...sfm.features import fixed_pattern

    names = set(names)
    members = _largest_size_group(inputs, lambda im: im.get("sensor", "thermal") == "thermal" and im["name"] in names)
    if not members:
        return None
    frames = [f for f in (_read_frame(project, nm) for nm in _evenly_spaced(members, 60)) if f.ndim == 2]
    pat = fixed_pattern(frames, highpass_sigma_px=highpass_sigma_px)
    if pat is None:
        return None
    _save_npz(project, key, pattern=pat)
    return key
