"""Exports of a calibration to other tools' camera files (OpenCV, COLMAP, Metashape, the other model), with the residual
of every file.

What a file loses depends on the model the calibration was estimated in:

* **photogrammetric** (correction form, Brown 1971; Fraser 1997): OpenCV, COLMAP and Metashape use the forward
  form, so their files are least-squares conversions over the whole image
  (:func:`thermogrammetry.camera.convert_camera`); the residual is the conversion's.
* **opencv** (the forward form of ``cv2.calibrateCamera``, Bradski 2000): OpenCV YAML/JSON and COLMAP
  (``OPENCV`` / ``FULL_OPENCV``) hold the estimated parameters themselves, and so does Metashape's XML (its frame
  model is the same forward form with P1/P2 swapped and B1 = fx - fy, exact without k4..k6); the photogrammetric
  camera (``photogrammetric.json``, a camera.json) is a conversion. The residual of an exact file is not asserted:
  every written file is read back with the project's readers (:func:`thermogrammetry.io.camera_file.read_camera_file`)
  and its camera compared with ``camera.json``'s on the rays through a grid over the whole image and over the area
  the data covered (rounding of the written numbers: ~1e-12 px).

Above :data:`WARN_RESIDUAL_PX` (0.1 px, max over the frame) a warning is given; above :data:`BAD_RESIDUAL_PX` (1 px)
the files are written as ``<name>_INACCURATE.<ext>`` with the warning inside.

References
----------
Brown, D. C. (1971). Close-range camera calibration. Photogrammetric Engineering 37(8), 855-866.
Fraser, C. S. (1997). Digital camera self-calibration. ISPRS J. Photogramm. Remote Sens. 52, 149-159.
Bradski, G. (2000). The OpenCV library. Dr. Dobb's Journal of Software Tools (``calib3d`` camera model).
Agisoft Metashape Professional Edition User Manual, Appendix C: Camera models.
"""

from __future__ import annotations

import html
import json
import tempfile
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..camera.models import CameraModel
from .selfcal import CameraCalibration

__all__ = ["camera_from_calibration", "export_files", "readback_residual", "WARN_RESIDUAL_PX", "BAD_RESIDUAL_PX"]

#: conversion residual (px, max over the whole frame) above which an export is flagged
WARN_RESIDUAL_PX = 0.1
#: above this the file is written under a name that says so (``<name>_INACCURATE.<ext>``)
BAD_RESIDUAL_PX = 1.0

_COLMAP_HEADER = "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: 1\n"


def camera_from_calibration(cc: CameraCalibration):
    """The calibrated camera as a :class:`thermogrammetry.Camera` in the model that was estimated (with std)."""
    from ..camera import Camera

    std = {n: float(s) for n, s in zip(cc.param_names, cc.std) if np.isfinite(s)}
    return Camera(cc.model, cc.image_size, cc.param_dict, pixel_pitch_um=cc.pixel_pitch_um, param_std=std, name=cc.name)


def _f(v):
    v = float(v)
    return v if np.isfinite(v) else None


def opencv_yaml(K: np.ndarray, dist: np.ndarray, size) -> str:
    """cv::FileStorage YAML text: ``image_width``, ``image_height``, ``camera_matrix``, ``distortion_coefficients``."""
    import cv2

    fs = cv2.FileStorage("calib.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.write("image_width", int(size[0]))
    fs.write("image_height", int(size[1]))
    fs.write("camera_matrix", np.asarray(K, float))
    fs.write("distortion_coefficients", np.asarray(dist, float).reshape(1, -1))
    return fs.releaseAndGetString()


def verdict(fmt: str, summary: dict) -> tuple[str, str]:
    """(file suffix, warning text) of an export from its residuals."""
    mx = summary.get("max_residual_px")
    if mx is None:
        return "_INACCURATE", f"{fmt} export: conversion residual unknown ({summary.get('reason', '')})"
    area = summary.get("area_max_residual_px")
    figs = (f"max {mx:.3g} px / RMS {summary['rms_residual_px']:.3g} px over the whole frame"
            + (f", max {area:.3g} px / RMS {summary['area_rms_residual_px']:.3g} px over the data area" if area is not None else ""))
    if mx > BAD_RESIDUAL_PX:
        return "_INACCURATE", (f"{fmt} export loses accuracy: {figs} (> {BAD_RESIDUAL_PX:g} px); written as "
                               f"*_INACCURATE.*; use camera.json (exact) where possible")
    if mx > WARN_RESIDUAL_PX:
        return "", f"{fmt} export: {figs} (> {WARN_RESIDUAL_PX:g} px)"
    return "", ""


def readback_residual(camera, exported, area_px: np.ndarray | None = None, *, grid_step_px: float | None = None) -> dict:
    """Pixel distance between ``camera`` and ``exported`` (a Camera, or any object with ``project(rays)``) on the
    rays of ``camera`` through a grid over the whole image (:func:`thermogrammetry.camera.convert.image_grid`,
    borders included) and over the convex hull of ``area_px``.

    Returns ``{"max_residual_px", "rms_residual_px", "area_max_residual_px", "area_rms_residual_px", "n_points"}``
    (None where undefined; a file whose camera cannot project a ray gets an infinite residual).
    """
    from ..camera.convert import image_grid, inside_area

    grid = image_grid(camera.image_size, grid_step_px)
    rays = camera.unproject(grid)
    ok = np.all(np.isfinite(rays), axis=1)
    d = np.linalg.norm(np.asarray(exported.project(rays[ok]), float) - camera.project(rays[ok]), axis=1)
    d = np.where(np.isfinite(d), d, np.inf)
    out = {"max_residual_px": float(d.max()) if d.size else None,
           "rms_residual_px": float(np.sqrt(np.mean(d * d))) if d.size else None,
           "area_max_residual_px": None, "area_rms_residual_px": None, "n_points": int(d.size)}
    if area_px is not None and d.size:
        inside = inside_area(grid[ok], area_px)
        if inside.any():
            out["area_max_residual_px"] = float(d[inside].max())
            out["area_rms_residual_px"] = float(np.sqrt(np.mean(d[inside] ** 2)))
    return out


def _read_back(name: str, data: bytes, reader: Callable[[Path], Any]):
    """``reader(path)`` on ``data`` written to a temporary file called ``name``."""
    with tempfile.TemporaryDirectory() as td:
        p = Path(td) / name
        p.write_bytes(data)
        return reader(p)


def export_files(cc: CameraCalibration, area_px: np.ndarray | None = None) -> tuple[dict[str, bytes], dict[str, Any]]:
    """Files (relative key -> bytes) and a summary per format with the residuals (whole frame and the area the
    data covered), conditioning, warnings; a file whose residual exceeds :data:`BAD_RESIDUAL_PX` is written under
    ``<name>_INACCURATE.<ext>``. See the module docstring for what each model's files are."""
    if cc.model is CameraModel.OPENCV:
        return _exports_opencv(cc, area_px)
    return _exports_photogrammetric(cc, area_px)


def _free_cov(cc: CameraCalibration) -> np.ndarray:
    return np.where(cc.free[:, None] & cc.free[None, :], cc.covariance, 0.0)


def _metashape(cam, cov, area_px, *, exact_readback: bool) -> tuple[dict[str, bytes], dict]:
    """The Metashape XML of ``cam`` and its summary; ``exact_readback``: the residual is that of the written file read
    back (an exact mapping), otherwise the fit's."""
    from ..io.camera_file import read_camera_file
    from ..io.metashape import MetashapeCalibration, write_metashape_xml

    files: dict[str, bytes] = {}
    try:
        ex = MetashapeCalibration.from_camera(cam, area_px=area_px, covariance=cov)
        ms = ex.summary()
        if ex.outcome.success:
            with tempfile.TemporaryDirectory() as td:
                p = Path(td) / "metashape.xml"
                write_metashape_xml(p, ex.calibration)
                text = p.read_text()
            if exact_readback and ex.max_residual_px == 0.0:
                back = _read_back("metashape.xml", text.encode(), read_camera_file)
                ms.update({k: v for k, v in readback_residual(cam, back, area_px).items() if k != "n_points"})
                ms["residual"] = "the written file read back and compared with camera.json"
        suffix, warn = verdict("Metashape", ms)
        ms["warning"] = warn
        if ex.outcome.success:
            if warn:
                text = text.replace("<calibration>", f"<!-- WARNING: {html.escape(warn)} -->\n<calibration>", 1)
            files[f"metashape{suffix}.xml"] = text.encode()
            ms["files"] = [f"metashape{suffix}.xml"]
        return files, ms
    except Exception as exc:  # noqa: BLE001 - an export that cannot be made is reported, not fatal
        return files, {"error": f"{type(exc).__name__}: {exc}", "warning": f"Metashape export failed: {exc}"}


def _exports_photogrammetric(cc: CameraCalibration, area_px):
    """A photogrammetric calibration: OpenCV, COLMAP and Metashape files converted by least squares."""
    from ..camera import convert_camera
    from ..camera import models as _M
    from ..camera.convert import conversion_covariance

    files: dict[str, bytes] = {}
    info: dict[str, Any] = {}
    cam = camera_from_calibration(cc)
    cov = _free_cov(cc)
    conv = convert_camera(cam, "opencv", area_px=area_px)
    summ = conv.summary()
    suffix, warn = verdict("OpenCV/COLMAP", summ)
    summ["warning"] = warn
    if conv.success:
        ocv = conv.camera
        K, dist = ocv.to_opencv()
        summ["files"] = [f"opencv{suffix}.yaml", f"opencv{suffix}.json", f"colmap_cameras{suffix}.txt"]
        files[f"opencv{suffix}.yaml"] = opencv_yaml(K, dist, cc.image_size).encode()
        ocv_cov = None
        try:
            free = list(conv.free)
            idx = [ocv.param_names.index(k) for k in free]

            def proj(t, rays):
                p = ocv.params.copy()
                p[idx] = t
                return _M.project("opencv", p, rays)

            C = conversion_covariance(cam, cov, proj, ocv.params[idx])
            ocv_cov = {"params": free, "matrix": C.tolist()}
        except (np.linalg.LinAlgError, ValueError):  # pragma: no cover - reported as absent
            ocv_cov = None
        files[f"opencv{suffix}.json"] = (json.dumps({
            "image_size": list(cc.image_size), "K": K.tolist(), "dist": np.asarray(dist).ravel().tolist(),
            "dist_order": "k1 k2 p1 p2 k3 [k4 k5 k6]",
            "converted_from": "photogrammetric (correction form)",
            "conversion_max_residual_px": _f(conv.max_residual_px),
            "conversion_rms_residual_px": _f(conv.rms_residual_px),
            "conversion_area_max_residual_px": summ["area_max_residual_px"],
            "conversion_area_rms_residual_px": summ["area_rms_residual_px"],
            "conversion_warning": warn,
            "covariance": ocv_cov,
        }, indent=2) + "\n").encode()
        try:
            from ..io.colmap import colmap_camera_line

            header = _COLMAP_HEADER + (f"# WARNING: {warn}\n" if warn else "")
            files[f"colmap_cameras{suffix}.txt"] = (header + colmap_camera_line(1, ocv) + "\n").encode()
        except Exception as exc:  # noqa: BLE001 - an export that cannot be made is reported, not fatal
            summ["colmap_error"] = f"{type(exc).__name__}: {exc}"
    info["opencv"] = summ
    info["colmap"] = {"max_residual_px": summ["max_residual_px"], "area_max_residual_px": summ["area_max_residual_px"],
                      "same_as": "opencv"}
    ms_files, info["metashape"] = _metashape(cam, cov, area_px, exact_readback=False)
    files.update(ms_files)
    return files, info


def _exports_opencv(cc: CameraCalibration, area_px):
    """An opencv-model calibration: OpenCV YAML/JSON, COLMAP and Metashape hold its parameters (residuals of the
    files read back); the photogrammetric camera is converted by least squares."""
    from ..camera import Camera, convert_camera
    from ..camera import models as _M
    from ..camera.convert import conversion_covariance
    from ..io.camera_file import read_camera_file
    from ..io.colmap import colmap_camera_line

    files: dict[str, bytes] = {}
    info: dict[str, Any] = {}
    cam = camera_from_calibration(cc)
    cov = _free_cov(cc)
    free = [n for n, f in zip(cc.param_names, cc.free) if f]
    idx = [cc.param_names.index(n) for n in free]
    summ: dict[str, Any] = {"method": "exact: the parameters estimated in the opencv model; residual of each file as "
                                      "written, read back and compared with camera.json"}
    backs: dict[str, dict] = {}
    try:
        K, dist = cam.to_opencv()
        yaml_text = opencv_yaml(K, dist, cc.image_size)
        backs["yaml"] = readback_residual(cam, _read_back("opencv.yaml", yaml_text.encode(), read_camera_file), area_px)
        json_doc = {"image_size": list(cc.image_size), "K": K.tolist(), "dist": np.asarray(dist).ravel().tolist(),
                    "dist_order": "k1 k2 p1 p2 k3 [k4 k5 k6]", "estimated_in": "opencv (forward form)",
                    "covariance": {"params": free, "matrix": cov[np.ix_(idx, idx)].tolist()}}
        back_json = json.loads(json.dumps(json_doc))
        backs["json"] = readback_residual(cam, Camera.from_opencv(np.array(back_json["K"]), np.array(back_json["dist"]),
                                                                  tuple(back_json["image_size"])), area_px)
    except Exception as exc:  # noqa: BLE001 - e.g. a nominal skew: reported, not fatal
        summ.update({"max_residual_px": None, "error": f"{type(exc).__name__}: {exc}"})
        yaml_text = json_doc = None
    colmap_text = None
    try:
        colmap_text = _COLMAP_HEADER + colmap_camera_line(1, cam) + "\n"
        backs["colmap"] = readback_residual(cam, _read_back("cameras.txt", colmap_text.encode(), read_camera_file), area_px)
    except Exception as exc:  # noqa: BLE001
        summ["colmap_error"] = f"{type(exc).__name__}: {exc}"
    ocv_backs = [backs[k] for k in ("yaml", "json") if k in backs]
    if ocv_backs:
        for key in ("max_residual_px", "rms_residual_px", "area_max_residual_px", "area_rms_residual_px"):
            vals = [b[key] for b in ocv_backs if b[key] is not None]
            summ[key] = max(vals) if vals else None
    suffix, warn = verdict("OpenCV", summ)
    summ["warning"] = warn
    if yaml_text is not None:
        json_doc.update({"residual_max_px": summ["max_residual_px"], "residual_rms_px": summ["rms_residual_px"],
                         "residual_area_max_px": summ["area_max_residual_px"],
                         "residual_area_rms_px": summ["area_rms_residual_px"], "warning": warn})
        files[f"opencv{suffix}.yaml"] = yaml_text.encode()
        files[f"opencv{suffix}.json"] = (json.dumps(json_doc, indent=2) + "\n").encode()
        summ["files"] = [f"opencv{suffix}.yaml", f"opencv{suffix}.json"]
    info["opencv"] = summ
    if "colmap" in backs:
        col = {k: v for k, v in backs["colmap"].items() if k != "n_points"}
        col["residual"] = "the written file read back and compared with camera.json"
        suffix, warn = verdict("COLMAP", col)
        col["warning"] = warn
        files[f"colmap_cameras{suffix}.txt"] = ((_COLMAP_HEADER + (f"# WARNING: {warn}\n" if warn else "")
                                                 + colmap_text[len(_COLMAP_HEADER):]).encode())
        col["files"] = [f"colmap_cameras{suffix}.txt"]
        info["colmap"] = col
    else:
        info["colmap"] = {"max_residual_px": None, "error": summ.get("colmap_error", ""),
                          "warning": f"COLMAP export failed: {summ.get('colmap_error', '')}"}
    ms_files, info["metashape"] = _metashape(cam, cov, area_px, exact_readback=True)
    files.update(ms_files)
    # the other model: the photogrammetric (correction-form) camera, converted
    try:
        conv = convert_camera(cam, "photogrammetric", area_px=area_px)
        ph = conv.summary()
        suffix, warn = verdict("photogrammetric", ph)
        ph["warning"] = warn
        if conv.success:
            pcam = conv.camera
            pfree = list(conv.free)
            pidx = [pcam.param_names.index(k) for k in pfree]
            std = None
            try:
                def proj(t, rays):
                    p = pcam.params.copy()
                    p[pidx] = t
                    return _M.project("photogrammetric", p, rays, image_size=pcam.image_size,
                                      pixel_pitch_um=pcam.pixel_pitch_um)

                C = conversion_covariance(cam, cov, proj, pcam.params[pidx])
                std = dict(zip(pfree, np.sqrt(np.maximum(np.diag(C), 0.0)).tolist()))
            except (np.linalg.LinAlgError, ValueError):  # pragma: no cover - reported as absent
                std = None
            ph["std_propagated"] = std is not None
            pcam = pcam.with_params(pcam.params, param_std=std)
            files[f"photogrammetric{suffix}.json"] = (json.dumps(pcam.to_dict(), indent=2) + "\n").encode()
            ph["files"] = [f"photogrammetric{suffix}.json"]
        info["photogrammetric"] = ph
    except Exception as exc:  # noqa: BLE001
        info["photogrammetric"] = {"error": f"{type(exc).__name__}: {exc}",
                                   "warning": f"photogrammetric export failed: {exc}"}
    return files, info
