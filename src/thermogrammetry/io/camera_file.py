"""A camera calibration from the files users have: thermogrammetry's ``camera.json``, a Metashape calibration XML, an
OpenCV ``FileStorage`` file (YAML or XML: ``camera_matrix``, ``distortion_coefficients``, ``image_width``,
``image_height``) or a COLMAP ``cameras.txt`` (:func:`read_camera_file`).

The format is recognised from the file's content, not its name: a JSON object is ``camera.json``; an XML root
``<calibration>`` is Metashape's, ``<opencv_storage>`` OpenCV's; a text starting ``%YAML`` is OpenCV's; otherwise a
COLMAP camera list. Pixel conventions are converted as each reader documents (COLMAP's pixel centre at 0.5; OpenCV's
and Metashape's as in :mod:`thermogrammetry.io.metashape` and :meth:`~thermogrammetry.camera.Camera.from_opencv`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import CorruptFileError, DataFileError, InvalidInputError

__all__ = ["CAMERA_FILE_FORMATS", "CameraFile", "camera_file_format", "read_camera_file", "open_camera_file", "describe_camera_file"]

#: the formats :func:`read_camera_file` reads
CAMERA_FILE_FORMATS = ("camera.json", "Metashape XML", "OpenCV YAML/XML", "COLMAP cameras.txt")


def camera_file_format(path) -> str:
    """Which of :data:`CAMERA_FILE_FORMATS` the file at ``path`` holds, from its first bytes; raises
    :class:`~thermogrammetry.errors.DataFileError` when it cannot be read."""
    path = Path(path)
    try:
        head = path.read_bytes()[:4096].decode("utf-8", errors="replace").lstrip("\ufeff \t\r\n")
    except OSError as exc:
        raise DataFileError(f"{path}: cannot read camera file ({exc.strerror or exc})") from exc
    if head.startswith("{"):
        return "camera.json"
    if head.startswith("%YAML"):
        return "OpenCV YAML/XML"
    if head.startswith("<"):
        body = head.split("?>", 1)[-1] if head.startswith("<?xml") else head
        if "<opencv_storage" in body:
            return "OpenCV YAML/XML"
        if "<calibration" in body:
            return "Metashape XML"
        raise CorruptFileError(f"{path}: an XML file, but neither a Metashape calibration (<calibration>) nor an "
                               "OpenCV FileStorage file (<opencv_storage>)")
    return "COLMAP cameras.txt"


def _read_opencv(path: Path) -> Camera:
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise CorruptFileError(f"{path}: not a readable OpenCV FileStorage file ({str(exc).strip()})") from None
    try:
        if not fs.isOpened():
            raise CorruptFileError(f"{path}: not a readable OpenCV FileStorage file")
        K = fs.getNode("camera_matrix").mat()
        dist = fs.getNode("distortion_coefficients").mat()
        w, h = fs.getNode("image_width"), fs.getNode("image_height")
        size = (int(w.real()), int(h.real())) if not (w.empty() or h.empty()) else None
    finally:
        fs.release()
    if K is None:
        raise CorruptFileError(f"{path}: no 'camera_matrix' (3x3) in this OpenCV file")
    if size is None or min(size) <= 0:
        raise CorruptFileError(f"{path}: no positive 'image_width'/'image_height' in this OpenCV file (the image size "
                               "the calibration belongs to is needed)")
    try:
        return Camera.from_opencv(np.asarray(K, float), None if dist is None else np.asarray(dist, float).ravel(),
                                  size, name=path.stem)
    except InvalidInputError as exc:
        raise CorruptFileError(f"{path}: {exc}") from None


@dataclass(frozen=True)
class CameraFile:
    """A camera read from a user's file (:func:`open_camera_file`): the camera, the file's format and the
    conversion's residual (px, max over the frame: 0 where the file's model is the camera's, as for OpenCV, COLMAP
    and camera.json; a Metashape calibration with K4 is converted by a fit)."""

    camera: Camera
    path: str
    format: str
    conversion_max_residual_px: float

    def to_dict(self) -> dict:
        return {"file": self.path, "format": self.format, "conversion_max_residual_px": self.conversion_max_residual_px}

    def describe(self) -> str:
        """One line for a user: the file, its format and what the conversion lost."""
        return describe_camera_file(self.to_dict())


def describe_camera_file(info: dict) -> str:
    """One line for a user from :meth:`CameraFile.to_dict`: the file, its format and what the conversion lost."""
    res = info["conversion_max_residual_px"]
    conv = "read exactly" if res == 0 else f"converted, max residual {res:.3g} px over the frame"
    return f"camera {info['file']} ({info['format']}; {conv})"


def read_camera_file(path) -> Camera:
    """Read one camera calibration from any of :data:`CAMERA_FILE_FORMATS` (:func:`camera_file_format`).

    Parameters
    ----------
    path : path-like
        The file. A COLMAP ``cameras.txt`` must hold exactly one camera; a Metashape calibration whose model has no
        exact OpenCV equivalent (K4 ≠ 0) is converted by a fit and refused when that fit is worse than 0.1 px.

    Returns
    -------
    Camera
        In thermogrammetry's conventions (``opencv`` or ``pinhole`` model, pixel centres at integer coordinates).

    Raises
    ------
    DataFileError, CorruptFileError
        The file cannot be read, or is none of the formats, or holds no single usable camera; the message names
        the file and what was expected.
    """
    return open_camera_file(path).camera


def open_camera_file(path) -> CameraFile:
    """:func:`read_camera_file` with the file's format and the conversion's residual (:class:`CameraFile`); the file
    is read once."""
    path = Path(path)
    fmt = camera_file_format(path)
    if fmt == "camera.json":
        return CameraFile(Camera.load(path), str(path), fmt, 0.0)
    if fmt == "OpenCV YAML/XML":
        return CameraFile(_read_opencv(path), str(path), fmt, 0.0)
    if fmt == "Metashape XML":
        from .metashape import read_metashape_calibration

        conv = read_metashape_calibration(path)
        res = float(getattr(conv, "max_residual_px", 0.0) or 0.0)
        if res > 0.1:
            raise CorruptFileError(f"{path}: this Metashape calibration has no exact OpenCV equivalent (K4 ≠ 0) and "
                                   f"its conversion is {res:.2f} px off at worst (> 0.1 px): export it from Metashape without K4, or "
                                   "convert it with thermogrammetry.io.read_metashape_calibration and save the camera "
                                   "if that residual is acceptable")
        return CameraFile(conv.camera, str(path), fmt, res)
    from .colmap import read_colmap_cameras

    cams = read_colmap_cameras(path)
    if len(cams) != 1:
        raise CorruptFileError(f"{path}: a COLMAP camera list with {len(cams)} cameras; expected exactly one "
                               "(or give a camera.json, a Metashape XML or an OpenCV YAML)")
    return CameraFile(next(iter(cams.values())), str(path), fmt, 0.0)
