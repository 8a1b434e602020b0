"""Initial values of the self-calibration: the nominal parameter vector, the pinhole matrix of a camera, Zhang's
focal length from views of a plane, and the resection of an image by PnP."""

from __future__ import annotations

import cv2
import numpy as np

from ..camera.models import CameraModel, ideal_K
from ..errors import ConfigError
from .bundle import param_names
from .selfcal_inputs import CameraSetup

__all__ = ["nominal_vector", "is_planar", "pinhole_K", "init_focal_planar", "resect"]


def nominal_vector(setup: CameraSetup, c_mm: float, model=CameraModel.PHOTOGRAMMETRIC) -> np.ndarray:
    """The stage-1 camera of ``setup`` in ``model``'s layout: principal distance ``c_mm`` (mm), the setup's
    nominal values, everything else 0.

    opencv model: ``fx = c_mm / pitch_x``, ``fy = c_mm / pitch_y`` (px), the principal point at the image
    centre ``((w - 1)/2, (h - 1)/2)``, no distortion; nominal values given by opencv names override these.
    A nominal value of the other model (other than ``c_mm``) raises ConfigError: it is not silently dropped.
    """
    model = CameraModel(model)
    names = param_names(model)
    if model is CameraModel.PHOTOGRAMMETRIC:
        p = np.zeros(len(names))
        for k, v in setup.nominal.items():
            if v is not None:
                if k not in names:
                    raise ConfigError(f"camera {setup.name!r}: nominal {k!r} is not a parameter of the photogrammetric "
                                      f"model; expected names from {list(names)}")
                p[names.index(k)] = float(v)
        p[0] = c_mm
        return p
    w, h = setup.image_size
    px, py = setup.pitch_mm
    p = np.zeros(len(names))
    p[:4] = (c_mm / px, c_mm / py, 0.5 * (w - 1), 0.5 * (h - 1))
    for k, v in setup.nominal.items():
        if v is None or k == "c_mm":
            continue
        if k not in names:
            raise ConfigError(f"camera {setup.name!r}: nominal {k!r} is a parameter of the photogrammetric model, not "
                              f"of the opencv model being calibrated; expected names from {list(names)} (or c_mm)")
        p[names.index(k)] = float(v)
    return p


def is_planar(xyz: np.ndarray) -> bool:
    if xyz.shape[0] < 4:
        return True
    c = xyz - xyz.mean(0)
    s = np.linalg.svd(c, compute_uv=False)
    return s[2] < 1e-6 * max(s[0], 1e-12)


def pinhole_K(p: np.ndarray, setup: CameraSetup, model=CameraModel.PHOTOGRAMMETRIC) -> np.ndarray:
    """(3, 3) ideal camera matrix in px of the parameter vector ``p`` of ``model``."""
    if CameraModel(model) is CameraModel.PHOTOGRAMMETRIC:
        px, py = setup.pitch_mm
        w, h = setup.image_size
        return np.array([[p[0] / px, 0, (w - 1) / 2 + p[1] / px], [0, p[0] / py, (h - 1) / 2 - p[2] / py], [0, 0, 1.0]])
    return ideal_K(model, p)


def init_focal_planar(setup: CameraSetup, obj: list[np.ndarray], img: list[np.ndarray]) -> float | None:
    """Zhang initialisation of the focal length from views of a plane (cv2.initCameraMatrix2D)."""
    op = [o.astype(np.float32) for o in obj if o.shape[0] >= 4]
    ip = [i.astype(np.float32).reshape(-1, 1, 2) for o, i in zip(obj, img) if o.shape[0] >= 4]
    if len(op) < 2:
        return None
    # initCameraMatrix2D expects the plane as Z=0 in the object points' own frame
    op2 = []
    for o in op:
        c = o.mean(0)
        _, _, Vt = np.linalg.svd(o - c)
        op2.append(((o - c) @ Vt.T * np.array([1, 1, 0])).astype(np.float32))
    K = cv2.initCameraMatrix2D(op2, ip, setup.image_size, 1.0)
    f = 0.5 * (K[0, 0] + K[1, 1])
    if not np.isfinite(f) or f <= 0:
        return None
    return float(f * setup.pitch_mm[0])


def resect(xyz: np.ndarray, xy: np.ndarray, K: np.ndarray, planar: bool):
    """Initial cam_from_world by PnP; returns (R, t) or None with reason."""
    obj = np.ascontiguousarray(xyz, dtype=np.float64)
    im = np.ascontiguousarray(xy, dtype=np.float64).reshape(-1, 1, 2)
    try:
        if planar:
            ok, rvec, tvec = cv2.solvePnP(obj, im, K, None, flags=cv2.SOLVEPNP_IPPE)
        else:
            ok, rvec, tvec = cv2.solvePnP(obj, im, K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return None, "resection (solvePnP) failed"
        rvec, tvec = cv2.solvePnPRefineLM(obj, im, K, None, rvec, tvec)
    except cv2.error as exc:
        return None, f"resection (solvePnP) failed: {str(exc).strip().splitlines()[-1]}"
    R, _ = cv2.Rodrigues(rvec)
    t = tvec.ravel()
    z = obj @ R.T + t
    if np.any(z[:, 2] <= 0):
        return None, "resection put target points behind the camera"
    return (R, t), ""
