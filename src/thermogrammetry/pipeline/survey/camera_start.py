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
