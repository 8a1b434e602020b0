"""The ``inputs`` step: files/folders -> decoded frames (``frames/<name>.tif``) and ``work/inputs.json``."""

from __future__ import annotations

import io
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ...errors import DataFileError, ThermogrammetryError, UnsupportedFormatError
from ...store import ProjectStore
from .options import IMAGE_SUFFIXES, SurveyInput, SurveyOptions, VIDEO_SUFFIXES
from .store import SurveyStore, frame_key


# thermal cores whose pixel pitch the files do not state (µm): kept for callers; the camera table
# (:mod:`thermogrammetry.camera.database`) is what the survey reads
_PITCH_UM = {"M3T": 12.0, "M30T": 12.0, "H20T": 12.0, "H20N": 12.0, "H30T": 12.0, "M4T": 12.0, "M3TD": 12.0,
             "XT2": 17.0, "ZH20T": 12.0, "MAVIC2-ENTERPRISE-ADVANCED": 12.0, "M2EA": 12.0}


def _name_list(names: Sequence[str], k: int = 3) -> str:
    """The first ``k`` names, comma-separated, with " ..." when there are more (for notes)."""
    return ", ".join(names[:k]) + (" ..." if len(names) > k else "")


def expand_inputs(items: Sequence, *, kind: str = "thermal") -> tuple[list[Path], list[str]]:
    """Files from files/folders (folders: their image and video files, sorted; subfolders not entered; a CSV
    that is no temperature matrix — GCPs, GNSS, measurements kept next to the images — is skipped with a note,
    :func:`thermogrammetry.io.matrix.looks_like_matrix`).

    Returns (files, notes): notes say what was skipped and why.
    """
    from ...io.matrix import looks_like_matrix

    files, notes = [], []
    for it in items:
        p = Path(it)
        if p.is_dir():
            entries = sorted(p.iterdir())  # listed once (a flight folder may hold thousands of frames)
            inside, side, other = [], [], []
            for q in (q for q in entries if q.is_file()):
                sfx = q.suffix.lower()
                if sfx in IMAGE_SUFFIXES | VIDEO_SUFFIXES and (sfx != ".csv" or looks_like_matrix(q)):
                    inside.append(q)
                elif not q.name.startswith("."):
                    (side if sfx == ".csv" else other).append(q.name)
            subs = [q.name for q in entries if q.is_dir()]
            if side:
                notes.append(f"{p}: {len(side)} CSV file(s) that are not temperature matrices skipped "
                             f"({_name_list(side)}; GCPs, GNSS and measurements go to their own options)")
            if other:
                notes.append(f"{p}: {len(other)} file(s) that are not images or videos skipped ({_name_list(other)})")
            if subs:
                notes.append(f"{p}: subfolder(s) not entered: {_name_list(subs)} (name them to include them)")
            files += inside
        elif p.exists():
            files.append(p)
        else:
            files.append(p)  # reported as failed by the decode step, with the reason
    return files, notes


def _geotag_dict(gt) -> dict:
    if gt is None or gt.latitude_deg is None or gt.longitude_deg is None:
        return {}
    return {"lat": gt.latitude_deg, "lon": gt.longitude_deg, "alt": gt.altitude_m, "rtk_flag": gt.rtk_flag,
            "rtk_std_m": list(gt.rtk_std_m) if gt.rtk_std_m else None,
            "gimbal_yaw_deg": gt.gimbal_yaw_deg, "gimbal_pitch_deg": gt.gimbal_pitch_deg,
            "gimbal_roll_deg": gt.gimbal_roll_deg}


def _attitudes(inputs: dict, crs: str | None) -> np.ndarray | None:
    """(n, 3, 3) cam_from_world rotations in ``crs`` from the files' gimbal angles (NaN where an image has none;
    :mod:`thermogrammetry.sfm.attitude`), or None when no image has all three angles or there is no CRS."""
    from ...sfm.attitude import cam_from_world_from_gimbal, meridian_convergence_deg

    keys = ("gimbal_yaw_deg", "gimbal_pitch_deg", "gimbal_roll_deg", "lon", "lat")
    a = np.array([[(im.get("geotag") or {}).get(k) for k in keys] for im in inputs["images"]], dtype=float)
    have = np.all(np.isfinite(a), axis=1)
    if crs is None or not have.any():
        return None
    out = np.full((len(a), 3, 3), np.nan)
    gam = meridian_convergence_deg(crs, a[have, 3], a[have, 4])
    out[have] = cam_from_world_from_gimbal(a[have, 0], a[have, 1], a[have, 2], gam)
    return out


def _camera_guess(width, height, md) -> dict:
    """The starting focal length in px of a frame and where it came from.

    In this order: EXIF focal length and pixel pitch (FocalPlaneResolution); EXIF focal length and the camera
    table's pitch (:func:`thermogrammetry.camera.database.table_focal`, by the files' make and model; the pitch on
    the image's grid when the image is an upscaled core); EXIF 35 mm-equivalent focal length; the table's field of
    view (a file without a focal length, e.g. the Mavic 2 Enterprise Dual); EXIF focal length with 17 µm assumed;
    1.0 x the image width. Keys: ``f_px``, ``source`` (text), ``pitch_um``, ``focal_source`` (``"exif"``,
    ``"camera_table:<camera>"``, ``"assumed"`` or ``"default"``), ``focal_sigma_px`` (σ of the start, None when
    unknown) and, from the table, ``camera_table`` (camera name, native size, upscale, how)."""
    from ...camera.database import LENS_FOCAL_SIGMA, table_focal

    exif = getattr(md, "exif", {}) or {}
    raw = exif.get("raw_exif", {}) if isinstance(exif, dict) else {}
    f35 = raw.get(41989)
    model = getattr(md, "model", None) or ""
    make = getattr(md, "make", None) or (exif.get("make") if isinstance(exif, dict) else None) or ""
    xmp = (getattr(md, "extra", None) or {}).get("xmp") or {} if isinstance(getattr(md, "extra", None), dict) else {}
    focal = getattr(md, "focal_length_mm", None)
    pitch = getattr(md, "pixel_pitch_um", None)
    pitch = pitch[0] if isinstance(pitch, (tuple, list)) else pitch
    tab = None
    # the reader's model (a FLIR file's camera-info model first), then EXIF Model, then DJI's XMP model name
    for name in dict.fromkeys(m for m in (model, exif.get("model") if isinstance(exif, dict) else None,
                                          xmp.get("Model")) if m):
        tab = table_focal(make, name, (width, height), focal)
        if tab is not None:
            break
    table = ({"camera_table": {"camera": tab.camera, "native_size": list(tab.native_size), "upscale": tab.upscale,
                               "how": tab.how, "source": tab.source,
                               **({"fov_half_extent_px": tab.fov_half_extent_px} if tab.fov_half_extent_px else {})}}
             if tab is not None else {})

    def guess(f, source, pitch_um, focal_source, sigma_px):
        return {"f_px": f, "source": source, "pitch_um": pitch_um, "focal_source": focal_source,
                "focal_sigma_px": sigma_px, **table}

    def exif_pitch(pitch_um):
        f = focal / (pitch_um * 1e-3)
        return guess(f, f"EXIF focal {focal:g} mm / pitch {pitch_um:g} µm", pitch_um, "exif", LENS_FOCAL_SIGMA * f)

    if focal and pitch:
        return exif_pitch(pitch)
    if focal and tab is not None and tab.f_px and tab.pixel_pitch_um:
        return guess(tab.f_px, f"EXIF {tab.how}", tab.pixel_pitch_um, f"camera_table:{tab.camera}", tab.sigma_px)
    if pitch is None and str(model).upper() in _PITCH_UM:
        pitch = _PITCH_UM[model.upper()]
        if focal:
            return exif_pitch(pitch)
    if f35:
        try:
            f35 = float(f35)
        except (TypeError, ValueError):
            f35 = None
    if f35:
        f = f35 * np.hypot(width, height) / 43.2666
        return guess(f, f"EXIF 35 mm-equivalent focal {f35:g} mm", pitch, "exif", LENS_FOCAL_SIGMA * f)
    if tab is not None and tab.f_px:
        g = guess(tab.f_px, f"no focal length in the file: {tab.how}", tab.pixel_pitch_um, f"camera_table:{tab.camera}",
                  tab.sigma_px)
        if tab.fov_half_extent_px:  # the start is a field of view: its focal length follows the block's distortion
            g["fov_half_extent_px"] = float(tab.fov_half_extent_px)
        return g
    if focal:
        return guess(focal / 0.017, f"EXIF focal {focal:g} mm, pixel pitch assumed 17 µm", 17.0, "assumed", None)
    return guess(1.0 * max(width, height), "no focal length in the file: 1.0 x image width assumed (self-calibrated)",
                 None, "default", None)


def frame_values(im, path, counts_dtype=np.uint16) -> tuple[str, np.ndarray, str]:
    """One decoded frame (:func:`thermogrammetry.io.iter_thermal`) -> ``(name suffix, values, unit)``: float32 kelvin
    (``"K"``) when the reader gave temperatures, else the raw counts (``"counts"``, as ``counts_dtype``); the suffix is
    ``_fNNNNN`` for a frame of a sequence, else empty. A temperature frame without one finite value is an
    :class:`UnsupportedFormatError` naming ``path``."""
    if im.temperature_k is not None:
        arr, unit = np.asarray(im.temperature_k, np.float32), "K"
        if not np.isfinite(arr).any():
            raise UnsupportedFormatError(f"{path}: no finite temperature in the frame")
    else:
        arr, unit = np.asarray(im.raw_counts, counts_dtype), "counts"
    fi = im.metadata.frame_index
    return ("" if fi is None else f"_f{fi:05d}"), arr, unit


#: a video whose frame-to-frame motion cannot be measured in most frames is sampled at this interval (s) instead: a
#: walk at 1 m/s 4 m from a wall moves ~20 % of a 40-degree frame in 0.6 s, a UAV at 5 m/s and 60 m in ~1.7 s
VIDEO_FALLBACK_INTERVAL_S = 0.5


#: multi-frame thermal recordings (FLIR SEQ/CSQ): their frames are selected for a forward overlap like a video's
SEQUENCE_SUFFIXES = {".seq", ".csq"}


def _decode(path: Path, input_unit: str | None, overlap: float | None = None, dji_sdk: str | None = None):
    """One input file -> list of (name suffix, array, unit, geotag dict, camera guess dict, note).

    A FLIR SEQ/CSQ recording with several frames keeps only those that :class:`~thermogrammetry.io.video.OverlapSelector`
    picks for ``overlap`` (a recording at 30 Hz holds frames that overlap by > 99 %; all of them would be near-duplicate
    images and an unbounded memory), after a first pass that estimates the sensor's static pattern; ``overlap=None``
    keeps every frame. ``dji_sdk``: DJI's Thermal SDK library for DJI R-JPEGs (temperatures; else raw counts)."""
    from ...io import iter_thermal

    suffix = path.suffix.lower()
    if suffix in VIDEO_SUFFIXES:
        raise UnsupportedFormatError(f"{path}: video input is decoded by the inputs step (io.video)")
    try:
        select, n_frames = None, None
        if suffix in SEQUENCE_SUFFIXES and overlap is not None:
            from ...io.video import OverlapSelector, static_pattern_of

            count = [0]

            def values():
                for im in iter_thermal(path, unit=input_unit, dji_sdk=dji_sdk):
                    count[0] += 1
                    yield frame_values(im, path)[1]

            static = static_pattern_of(values())
            n_frames = count[0]
            if n_frames > 1:
                select = OverlapSelector(overlap, static)

        def decoded(select):
            out = []
            for im in iter_thermal(path, unit=input_unit, dji_sdk=dji_sdk):
                sfx, arr, unit = frame_values(im, path)
                if select is not None and not select(arr):
                    continue
                md = im.metadata
                h, w = arr.shape
                notes = ["raw counts (no documented conversion): geometry and products labelled as counts"] if unit == "counts" else []
                if select is not None:
                    notes.append(f"frame {md.frame_index} of {n_frames} in the recording (frames kept for "
                                 f"{overlap:.0%} forward overlap)")
                out.append((sfx, arr, unit, _geotag_dict(md.geotag), _camera_guess(w, h, md), "; ".join(notes)))
            return out

        out = decoded(select)
        if select is not None and not select.motion_measured:
            # most consecutive frames show no measurable motion: not a video-rate recording (an interval recording
            # whose frames do not overlap, or noise only), every frame is kept
            out = decoded(None)
        return out
    except UnsupportedFormatError as exc:
        not_radiometric = "radiometric" in str(exc) or "no reader" in str(exc).lower() or "not a" in str(exc).lower()
        if not not_radiometric or suffix not in (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff"):
            raise
    # plain image: 8-bit rendering (geometry only) or 16-bit grey without a unit
    import cv2

    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise UnsupportedFormatError(f"{path}: neither a radiometric thermal file nor an image OpenCV can decode")
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
    unit = "dn" if img.dtype == np.uint8 else "counts"
    if img.dtype not in (np.uint8, np.uint16):
        raise UnsupportedFormatError(f"{path}: {img.dtype} image without a unit; give --input-unit K|C for float temperature TIFFs")
    geo, md = {}, None
    try:
        from ...io.exif import read_exif

        ex = read_exif(bytes(data[: 1 << 20])) if suffix in (".jpg", ".jpeg") else {}
        if ex.get("latitude_deg") is not None:
            geo = {"lat": ex["latitude_deg"], "lon": ex["longitude_deg"], "alt": ex.get("altitude_m"), "rtk_flag": None, "rtk_std_m": None}

        class _Md:  # what _camera_guess reads
            exif = ex
            model = ex.get("model")
            make = ex.get("make")
            focal_length_mm = ex.get("focal_length_mm")
            pixel_pitch_um = ex.get("pixel_pitch_um")  # EXIF FocalPlane resolution, when written
        md = _Md
    except Exception:  # noqa: BLE001 - EXIF is optional for a plain image; its absence is noted below
        md = None
    h, w = img.shape
    note = "8-bit rendering: geometry only, these frames carry no temperatures" if unit == "dn" else \
        "16-bit image without a declared mapping: values kept as counts"
    return [("", img, unit, geo, _camera_guess(w, h, md) if md else _camera_guess(w, h, None), note)]


def _decode_video(path: Path, overlap: float):
    try:
        from ...io.video import read_video_frames
    except ImportError:
        raise UnsupportedFormatError(f"{path}: video input needs thermogrammetry.io.video, which this installation lacks") from None
    def decoded(note, **how):
        out = []
        for fr in read_video_frames(path, **how):
            h, w = fr.image.shape[:2]
            out.append((f"_f{fr.index:06d}", fr.image, fr.unit, {}, _camera_guess(w, h, None),
                        f"video frame at {fr.time_s:.2f} s" + (f" ({note})" if note else "")))
        return out

    stats: dict = {}
    out = decoded("", forward_overlap=overlap, stats=stats)
    sel = stats.get("selector")
    if sel is not None and not sel.motion_measured:
        # the motion between frames could not be measured in most of the video (too little texture left once the
        # static pattern is out): frames at a fixed interval instead of none after the first
        fps = stats["fps"] if np.isfinite(stats["fps"]) and stats["fps"] > 0 else 25.0
        every = max(1, int(round(fps * VIDEO_FALLBACK_INTERVAL_S)))
        out = decoded(f"the frame-to-frame motion was measurable in {sel.measured} of {sel.pairs} frames: frames "
                      f"taken every {every / fps:.2f} s instead of for {overlap:.0%} overlap", every=every)
    return out


#: readers of radiometric JPEGs (:func:`thermogrammetry.io.thermal.sniff_reader`): such a file is a thermal frame
RADIOMETRIC_JPEG_READERS = ("flir_rjpeg", "workswell_rjpeg", "dji_rjpeg")


def _radiometric_jpeg(path: Path) -> bool:
    """Whether ``path`` is a JPEG that one of the radiometric readers accepts (a DJI _T / FLIR R-JPEG)."""
    from ...io.thermal import sniff_reader

    if path.suffix.lower() not in (".jpg", ".jpeg"):
        return False
    try:
        return sniff_reader(path).name in RADIOMETRIC_JPEG_READERS
    except (ThermogrammetryError, OSError, ValueError):
        return False


def step_inputs(project: ProjectStore, inp: SurveyInput, opt: SurveyOptions, progress: Callable | None = None) -> dict:
    """Decode every input to ``frames/<name>.tif``; ``work/inputs.json``."""
    import tifffile

    t0 = time.perf_counter()
    items = []
    notes = []
    for kind, src in (("thermal", inp.images), ("rgb", inp.rgb)):
        files, nts = expand_inputs(src, kind=kind)
        notes += nts
        items += [(kind, f) for f in files]
    def skipped() -> str:  # what the inputs left out, for the errors below
        return f" ({'; '.join(notes)})" if notes else ""

    if not items:
        given = [str(x) for x in list(inp.images or []) + list(inp.rgb or [])]
        shown = ", ".join(given[:5]) + (f" (+{len(given) - 5} more)" if len(given) > 5 else "")
        raise DataFileError(f"no input images: {shown} hold(s) no image or video files (expected files ending "
                            f"in {' '.join(sorted(IMAGE_SUFFIXES | VIDEO_SUFFIXES))}){skipped()}")
    failed: list[dict] = []
    slots: list[list] = [[] for _ in items]  # the decoded frames of each input, in the inputs' order
    used_names: set[str] = set()
    plain: list[tuple] = []  # (k, path, sizes): 8-bit renderings among the thermal inputs, written at the end

    def emit(k, kind, path, decoded):
        for sfx, arr, unit, geo, guess, note in decoded:
            name = path.stem + sfx
            base, n = name, 1
            while name in used_names:
                n += 1
                name = f"{base}_{n}"
            used_names.add(name)
            buf = io.BytesIO()
            tifffile.imwrite(buf, arr, photometric="rgb" if arr.ndim == 3 else "minisblack",
                             metadata={"unit": unit, "source": str(path)})
            project.write_bytes(frame_key(name), buf.getvalue())
            slots[k].append({"name": name, "source": str(path.resolve()) if path.exists() else str(path), "sensor": kind,
                             "unit": unit, "width": int(arr.shape[1]), "height": int(arr.shape[0]), "geotag": geo,
                             "camera_guess": guess, "note": note})

    def fail(path, exc):
        reason = str(exc)
        if "pass unit='K' or unit='C'" in reason:
            reason = reason.replace("pass unit='K' or unit='C'", "give --input-unit K or C")
        failed.append({"file": str(path), "reason": reason})

    rgb_thermal = []  # radiometric thermal files given among the RGB images (a DJI folder given to --rgb)
    for k, (kind, path) in enumerate(items):
        if kind == "rgb" and _radiometric_jpeg(path):
            rgb_thermal.append(path.name)
            if progress:
                progress(k + 1, len(items))
            continue
        try:
            if not path.exists():
                raise DataFileError(f"{path}: no such file")
            if path.suffix.lower() in VIDEO_SUFFIXES:
                decoded = _decode_video(path, opt.video_overlap)
            elif kind == "rgb":
                import cv2

                img = cv2.imdecode(np.fromfile(str(path), dtype=np.uint8), cv2.IMREAD_COLOR)
                if img is None:
                    raise UnsupportedFormatError(f"{path}: not an image OpenCV can decode (RGB input)")
                from ...io.exif import read_exif

                ex = {}
                if path.suffix.lower() in (".jpg", ".jpeg"):
                    try:
                        ex = read_exif(path.read_bytes()[: 1 << 20])
                    except ThermogrammetryError:
                        ex = {}
                geo = {"lat": ex["latitude_deg"], "lon": ex["longitude_deg"], "alt": ex.get("altitude_m"), "rtk_flag": None,
                       "rtk_std_m": None} if ex.get("latitude_deg") is not None else {}

                class _Md:
                    exif = ex
                    model = ex.get("model")
                    make = ex.get("make")
                    focal_length_mm = ex.get("focal_length_mm")
                    pixel_pitch_um = ex.get("pixel_pitch_um")  # EXIF FocalPlane resolution, when written
                h, w = img.shape[:2]
                decoded = [("", img[..., ::-1].copy(), "dn", geo, _camera_guess(w, h, _Md), "RGB image")]
            else:
                decoded = _decode(path, opt.input_unit, opt.video_overlap, opt.dji_sdk)
        except (ThermogrammetryError, OSError, ValueError, MemoryError) as exc:
            fail(path, exc)
            if progress:
                progress(k + 1, len(items))
            continue
        if kind == "thermal" and path.suffix.lower() not in VIDEO_SUFFIXES and decoded \
                and all(d[2] == "dn" for d in decoded):
            # an 8-bit rendering: kept only if no radiometric frame says the thermal frames have another size (a
            # DJI folder holds the visible _V/_W/_Z photographs next to the _T thermal frames); decoded again then
            plain.append((k, path, {(int(d[1].shape[1]), int(d[1].shape[0])) for d in decoded}))
        else:
            emit(k, kind, path, decoded)
        if progress:
            progress(k + 1, len(items))
    if rgb_thermal:
        notes.append(f"{len(rgb_thermal)} radiometric thermal file(s) among the RGB images ({_name_list(rgb_thermal)}): "
                     "not used as RGB images")
    thermal_sizes = {(im["width"], im["height"]) for ims in slots for im in ims
                     if im["sensor"] == "thermal" and im["unit"] != "dn"}  # (not an 8-bit video's frames)
    others = {k for k, path, sizes in plain if thermal_sizes and not sizes & thermal_sizes}
    if others:
        names = [path.name for k, path, _ in plain if k in others]
        notes.append(f"{len(others)} ordinary 8-bit image(s) of another size than every radiometric or 16-bit thermal "
                     f"frame ({_name_list(names)}): visible photographs, not used as thermal frames (give them with --rgb "
                     "to use them)")
    for k, path, _ in plain:
        if k in others:
            continue
        try:
            emit(k, "thermal", path, _decode(path, opt.input_unit, opt.video_overlap, opt.dji_sdk))
        except (ThermogrammetryError, OSError, ValueError, MemoryError) as exc:
            fail(path, exc)
    images = [im for ims in slots for im in ims]
    if not images:
        raise DataFileError("no usable input image: " + "; ".join(f["reason"] for f in failed[:5])
                            + (f" (and {len(failed) - 5} more)" if len(failed) > 5 else "") + skipped())
    SurveyStore(project).save_inputs({"images": images, "failed": failed, "notes": notes})
    return {"images": len(images), "failed": len(failed), "seconds": time.perf_counter() - t0}
