"""Where each camera's starting focal length came from (``work/inputs.json`` ``camera_guess``): whether it is the
files' (or the camera table's), the guard's reference value, and ``survey.json`` ``camera_start``."""

from __future__ import annotations

import numpy as np


def _focal_from_exif(inputs: dict, rec, cam_index: int) -> bool:
    """True when every image of this camera had its starting focal length from the files, not a guess: EXIF focal
    length and pixel pitch, a 35 mm-equivalent focal, or the EXIF focal length / field of view with the camera
    table's pitch (``camera_guess.focal_source`` "exif" or "camera_table:..."; inputs without that key: the
    ``source`` text "EXIF focal ... / pitch ..." or a 35 mm-equivalent focal)."""
    guesses = [im.get("camera_guess", {}) for im, c in zip(inputs["images"], rec.image_camera) if int(c) == cam_index]

    def known(g) -> bool:
        fs = g.get("focal_source")
        if fs is not None:
            return fs == "exif" or str(fs).startswith("camera_table:")
        s_ = str(g.get("source", ""))
        return s_.startswith("EXIF") and "assumed" not in s_

    return bool(guesses) and all(known(g) for g in guesses)


def _camera_start(inputs: dict, rec, meta: dict, camera=None) -> dict:
    """survey.json ``camera_start``: per camera id where its starting focal length came from (``focal_source``:
    ``"exif"``, ``"camera_table:<camera>"``, ``"camera_file"`` for a thermal camera given with ``--camera`` or the
    rig file, ``"assumed"``, ``"default"``), the start ``f_px`` with its σ (``focal_sigma_px``, None when unknown),
    the text ``source``, and the camera table's entry when it knows the camera."""
    out = {}
    for k, cid in enumerate(meta["camera_ids"]):
        g = next((im.get("camera_guess", {}) for im, c in zip(inputs["images"], rec.image_camera) if int(c) == k), {})
        given = camera is not None and str(cid).startswith("thermal")
        fs = "camera_file" if given else g.get("focal_source", "exif" if _focal_from_exif(inputs, rec, k) else "default")
        f = (float(camera.param_dict["fx"]) if "fx" in camera.param_dict else None) if given else g.get("f_px")
        out[str(cid)] = {"focal_source": fs, "f_px": f, "focal_sigma_px": None if given else g.get("focal_sigma_px"),
                         "source": "camera file" if given else g.get("source"),
                         **({"camera_table": g["camera_table"]} if g.get("camera_table") else {})}
    return out


def _focal_prior(inputs: dict, rec, cam_index: int) -> float | None:
    """The focal length (px) the camera's images started from when it came from the files or the camera table
    (:func:`_focal_from_exif`): the reference of the focal-length guard of the self-calibration, which every
    adjustment of the block (and every later one, e.g. with images added at their GNSS positions) is held to,
    not the value the previous adjustment left. None otherwise."""
    if not _focal_from_exif(inputs, rec, cam_index):
        return None
    f = [float(im["camera_guess"]["f_px"]) for im, c in zip(inputs["images"], rec.image_camera) if int(c) == cam_index]
    return float(np.median(f)) if f else None


def _focal_prior_sigma(inputs: dict, rec, cam_index: int) -> float | None:
    """σ (px) of :func:`_focal_prior`: the median ``camera_guess.focal_sigma_px`` of the camera's images (the lens's
    nominal focal length, 5 %; the camera table's field of view with its tolerance), None when unknown."""
    if not _focal_from_exif(inputs, rec, cam_index):
        return None
    s_ = [im["camera_guess"].get("focal_sigma_px") for im, c in zip(inputs["images"], rec.image_camera)
          if int(c) == cam_index]
    s_ = [float(v) for v in s_ if v is not None and np.isfinite(v) and v > 0]
    return float(np.median(s_)) if s_ else None


def _focal_prior_fov(inputs: dict, rec, cam_index: int) -> float | None:
    """The half extent (px) of the field of view the camera's starting focal length came from (the camera table's
    field of view, for a file without a focal length; ``camera_guess.fov_half_extent_px``), None when the start is a
    focal length (EXIF, a lens's mm) or the images disagree: the final adjustment then expresses the prior through
    the block's distortion (:func:`thermogrammetry.camera.database.focal_through_distortion`)."""
    if not _focal_from_exif(inputs, rec, cam_index):
        return None
    v = {im["camera_guess"].get("fov_half_extent_px") for im, c in zip(inputs["images"], rec.image_camera)
         if int(c) == cam_index}
    return float(v.pop()) if len(v) == 1 and None not in v else None


#: a thermal camera whose start was the camera table's field of view is oriented again from its self-calibration
#: (:func:`restart_camera`) when the focal length that field of view implies through the self-calibrated distortion
#: is more than this many σ of the table's value from the start. Measured on the synthetic M2ED-like facade flight,
#: seed 0 (``benchmarks/survey_facade_flight.py``): the orientation started from the pinhole 589 px (true 653 px
#: through k1 -0.35) self-calibrates 599 px / k1 -0.26 whatever the prior (the incremental orientation made with a
#: pinhole start fixes the block's shape); the field of view through k1 -0.26 says 637 px (1.2 σ), and the block
#: oriented again from 637 px, k1 -0.26 (same matches) self-calibrates 656 px / k1 -0.34 (true 653 / -0.35; rotations
#: 3.2° -> 1.3° RMS; seeds 1-3: focal length within 10 px of the truth, rotations 1.2-1.5°)
RESTART_FOCAL_SIGMA = 0.5


def restart_camera(inputs: dict, survey: dict) -> dict:
    """Camera id -> start ``{"fx", "k1", "k2"}`` for a second orientation, for the thermal cameras that started from
    the camera table's field of view (``camera_guess.fov_half_extent_px``), whose final adjustment self-calibrated
    k1, and whose field-of-view focal length through that distortion
    (:func:`~thermogrammetry.camera.database.focal_through_distortion`) is more than :data:`RESTART_FOCAL_SIGMA` σ
    from their start. Empty when none qualifies (or the inputs already started from a restart)."""
    from ...camera.database import focal_through_distortion

    out = {}
    cams = survey.get("cameras") or {}
    start = survey.get("camera_start") or {}
    for cid, st in start.items():
        g = next((im.get("camera_guess", {}) for im in inputs["images"] if im.get("sensor", "thermal") == "thermal"
                  and str(cid).startswith("thermal")), {})
        ext, f0, s0 = g.get("fov_half_extent_px"), g.get("f_px"), g.get("focal_sigma_px")
        p = (cams.get(cid) or {}).get("params") or {}
        if not (ext and f0 and s0) or g.get("start") or "k1" not in p or not str(st.get("focal_source", "")).startswith(
                "camera_table:"):
            continue
        if not any("k1" in (b.get("self_calibration") or []) for b in survey.get("blocks", []) if not b.get("rejected")):
            continue
        f = focal_through_distortion(f0, ext, p.get("k1", 0.0), p.get("k2", 0.0), p.get("k3", 0.0))
        if np.isfinite(f) and abs(f - f0) > RESTART_FOCAL_SIGMA * s0:
            out[str(cid)] = {"fx": float(f), "k1": float(p["k1"]), "k2": float(p.get("k2", 0.0))}
    return out
