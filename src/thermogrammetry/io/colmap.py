"""COLMAP text model files: ``cameras.txt``, ``images.txt``, ``points3D.txt``.

Pixel convention: COLMAP puts the centre of the top-left pixel at (0.5, 0.5); thermogrammetry
(OpenCV) at (0, 0). Readers subtract 0.5 from ``cx``, ``cy`` and from 2D point coordinates;
writers add it (``x_colmap = x + 0.5``, docs/conventions.md).

Camera models read: ``SIMPLE_PINHOLE`` (f cx cy), ``PINHOLE`` (fx fy cx cy), ``SIMPLE_RADIAL``
(f cx cy k), ``RADIAL`` (f cx cy k1 k2), ``OPENCV`` (fx fy cx cy k1 k2 p1 p2), ``FULL_OPENCV``
(fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6). COLMAP's radial/OpenCV distortion is OpenCV's forward model
(COLMAP ``src/colmap/sensor/models.h``), so all map exactly onto our ``pinhole``/``opencv`` models.
Written: ``PINHOLE`` (pinhole), ``OPENCV`` (opencv without k3..k6) or ``FULL_OPENCV``. The
photogrammetric (correction-form) model has no COLMAP equivalent: convert it first with
:func:`thermogrammetry.camera.convert_camera` and check ``max_residual_px``.

Poses in ``images.txt`` are ``cam_from_world`` (quaternion QW QX QY QZ, Hamilton, and T), which is
our convention.

References
----------
Schönberger, J. L., Frahm, J.-M. (2016). Structure-from-Motion Revisited. CVPR. COLMAP documentation,
"Output format" (text model files).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._atomic import write_atomic_text
from ..camera.camera import Camera
from ..camera.models import CameraModel
from ..errors import CorruptFileError, DataFileError, InvalidInputError, UnknownModelError

__all__ = [
    "COLMAP_READ_MODELS",
    "ColmapImage",
    "ColmapPoints3D",
    "read_colmap_cameras",
    "write_colmap_cameras",
    "colmap_camera_line",
    "read_colmap_images",
    "write_colmap_images",
    "read_colmap_points3d",
    "write_colmap_points3d",
]

_OFFSET = 0.5  # COLMAP pixel centre of the top-left pixel

# model -> parameter names in COLMAP order
COLMAP_READ_MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}
_OTHER_COLMAP = ("SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "OPENCV_FISHEYE", "FOV", "THIN_PRISM_FISHEYE",
                 "RAD_TAN_THIN_PRISM_FISHEYE", "SIMPLE_DIVISION", "DIVISION")


def _read_lines(path) -> list[tuple[int, str]]:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise DataFileError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    out = []
    for i, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            out.append((i, s))
    return out


def _num(tok: str, path, lineno: int, what: str, kind=float):
    try:
        v = kind(tok)
    except ValueError:
        raise CorruptFileError(f"{path}:{lineno}: {what} is {tok!r}; expected {'an integer' if kind is int else 'a number'}") from None
    if kind is float and not np.isfinite(v):
        raise CorruptFileError(f"{path}:{lineno}: {what} is {tok!r}; expected a finite number")
    return v


# ------------------------------------------------------------------------------------------ cameras
def read_colmap_cameras(path) -> dict[int, Camera]:
    """Read ``cameras.txt``; returns ``{camera_id: Camera}`` in thermogrammetry's pixel convention.

    Errors name the file, the line and the expected form (unknown model -> :class:`UnknownModelError`,
    wrong parameter count or non-numbers -> :class:`CorruptFileError`).
    """
    path = Path(path)
    cams: dict[int, Camera] = {}
    for lineno, line in _read_lines(path):
        tok = line.split()
        if len(tok) < 4:
            raise CorruptFileError(f"{path}:{lineno}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', got {line!r}")
        cid = _num(tok[0], path, lineno, "CAMERA_ID", int)
        model = tok[1].upper()
        if model not in COLMAP_READ_MODELS:
            what = "a COLMAP model thermogrammetry does not support" if model in _OTHER_COLMAP else "an unknown COLMAP model"
            raise UnknownModelError(
                f"{path}:{lineno}: camera model {tok[1]!r} is {what}; expected one of {', '.join(COLMAP_READ_MODELS)}"
            )
        w = _num(tok[2], path, lineno, "WIDTH", int)
        h = _num(tok[3], path, lineno, "HEIGHT", int)
        names = COLMAP_READ_MODELS[model]
        vals = tok[4:]
        if len(vals) != len(names):
            raise CorruptFileError(
                f"{path}:{lineno}: {model} needs {len(names)} parameters ({' '.join(names)}), got {len(vals)}"
            )
        p = {n: _num(v, path, lineno, n) for n, v in zip(names, vals)}
        if "f" in p:
            p["fx"] = p["fy"] = p.pop("f")
        p["cx"] -= _OFFSET
        p["cy"] -= _OFFSET
        if cid in cams:
            raise CorruptFileError(f"{path}:{lineno}: duplicate CAMERA_ID {cid}")
        try:
            if model in ("SIMPLE_PINHOLE", "PINHOLE"):
                cams[cid] = Camera(CameraModel.PINHOLE, (w, h), p, name=f"colmap camera {cid}")
            else:
                cams[cid] = Camera(CameraModel.OPENCV, (w, h), p, name=f"colmap camera {cid}")
        except InvalidInputError as exc:
            raise CorruptFileError(f"{path}:{lineno}: {exc}") from None
    return cams


def colmap_camera_line(camera_id: int, camera: Camera) -> str:
    """One ``cameras.txt`` line: ``PINHOLE`` / ``OPENCV`` / ``FULL_OPENCV`` (17 significant digits)."""
    if not isinstance(camera, Camera):
        raise InvalidInputError(f"camera {camera_id}: expected a Camera, got {type(camera).__name__}")
    w, h = camera.image_size
    p = camera.param_dict
    if camera.model is CameraModel.PHOTOGRAMMETRIC:
        raise UnknownModelError(
            f"camera {camera_id}: the photogrammetric (correction-form) model has no COLMAP equivalent; "
            "convert it with thermogrammetry.camera.convert_camera(camera, 'opencv') and check max_residual_px"
        )
    if camera.model is CameraModel.PINHOLE:
        model, vals = "PINHOLE", [p["fx"], p["fy"], p["cx"] + _OFFSET, p["cy"] + _OFFSET]
    else:
        if p["skew"] != 0.0:
            raise InvalidInputError(
                f"camera {camera_id}: skew={p['skew']!r} px is non-zero but COLMAP models have no skew; "
                "convert to a zero-skew camera first"
            )
        vals = [p["fx"], p["fy"], p["cx"] + _OFFSET, p["cy"] + _OFFSET, p["k1"], p["k2"], p["p1"], p["p2"]]
        if all(p[k] == 0.0 for k in ("k3", "k4", "k5", "k6")):
            model = "OPENCV"
        else:
            model = "FULL_OPENCV"
            vals += [p["k3"], p["k4"], p["k5"], p["k6"]]
    return f"{int(camera_id)} {model} {w} {h} " + " ".join(repr(float(v)) for v in vals)


def write_colmap_cameras(path, cameras: Mapping[int, Camera] | Sequence[Camera]) -> Path:
    """Write ``cameras.txt`` atomically; a sequence is numbered from 1."""
    items = cameras.items() if isinstance(cameras, Mapping) else enumerate(cameras, start=1)
    lines = [colmap_camera_line(cid, cam) for cid, cam in items]
    header = ("# Camera list with one line of data per camera:\n"
              "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
              f"# Number of cameras: {len(lines)}\n")
    path = Path(path)
    write_atomic_text(path, header + "".join(line + "\n" for line in lines))
    return path


# ------------------------------------------------------------------------------------------ images
@dataclass
class ColmapImage:
    """One entry of ``images.txt`` (pixel coordinates already in thermogrammetry's convention).

    Attributes
    ----------
    image_id : int
    qvec : (4,) float
        Quaternion ``(qw, qx, qy, qz)`` of ``R_cam_from_world`` (Hamilton).
    tvec : (3,) float
        Translation of ``cam_from_world``.
    camera_id : int
    name : str
    xy_px : (N, 2) float
        2D points, (0, 0) = centre of the top-left pixel.
    point3d_ids : (N,) int64
        Id of the 3D point each 2D point observes, -1 for none.
    """

    image_id: int
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str
    xy_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    point3d_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def R(self) -> np.ndarray:
        """(3, 3) ``R_cam_from_world`` from :attr:`qvec`."""
        w, x, y, z = np.asarray(self.qvec, dtype=np.float64) / np.linalg.norm(self.qvec)
        return np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ])

    @property
    def center(self) -> np.ndarray:
        """Projection centre ``C = -R^T t`` in world coordinates."""
        return -self.R.T @ np.asarray(self.tvec, dtype=np.float64)


def read_colmap_images(path) -> dict[int, ColmapImage]:
    """Read ``images.txt`` (two lines per image) into ``{image_id: ColmapImage}``."""
    path = Path(path)
    text_lines = []
    try:
        raw = path.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise DataFileError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    for i, line in enumerate(raw, start=1):
        if line.startswith("#"):
            continue
        text_lines.append((i, line.strip()))
    # the points line of an image without observations is empty: keep empty lines between headers
    while text_lines and not text_lines[-1][1]:
        text_lines.pop()
    images: dict[int, ColmapImage] = {}
    k = 0
    while k < len(text_lines):
        lineno, head = text_lines[k]
        if not head:
            k += 1
            continue
        tok = head.split()
        if len(tok) < 10:
            raise CorruptFileError(f"{path}:{lineno}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', got {head!r}")
        iid = _num(tok[0], path, lineno, "IMAGE_ID", int)
        q = np.array([_num(t, path, lineno, n) for t, n in zip(tok[1:5], ("QW", "QX", "QY", "QZ"))])
        t = np.array([_num(v, path, lineno, n) for v, n in zip(tok[5:8], ("TX", "TY", "TZ"))])
        cid = _num(tok[8], path, lineno, "CAMERA_ID", int)
        name = " ".join(tok[9:])
        pts_line = text_lines[k + 1][1] if k + 1 < len(text_lines) else ""
        pl = text_lines[k + 1][0] if k + 1 < len(text_lines) else lineno + 1
        ptok = pts_line.split()
        if len(ptok) % 3:
            raise CorruptFileError(f"{path}:{pl}: POINTS2D must be triples 'X Y POINT3D_ID', got {len(ptok)} values")
        try:
            arr = np.array(ptok, dtype=np.float64).reshape(-1, 3)
        except ValueError:
            raise CorruptFileError(f"{path}:{pl}: POINTS2D must be numbers") from None
        if iid in images:
            raise CorruptFileError(f"{path}:{lineno}: duplicate IMAGE_ID {iid}")
        images[iid] = ColmapImage(iid, q, t, cid, name, arr[:, :2] - _OFFSET, arr[:, 2].astype(np.int64))
        k += 2
    return images


def write_colmap_images(path, images: Mapping[int, ColmapImage] | Sequence[ColmapImage]) -> Path:
    """Write ``images.txt`` atomically (adds 0.5 to the 2D points)."""
    items = list(images.values()) if isinstance(images, Mapping) else list(images)
    out = ["# Image list with two lines of data per image:",
           "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
           "#   POINTS2D[] as (X, Y, POINT3D_ID)",
           f"# Number of images: {len(items)}"]
    for im in items:
        q = np.asarray(im.qvec, dtype=np.float64)
        t = np.asarray(im.tvec, dtype=np.float64)
        if not im.name or im.name != im.name.strip() or "\n" in im.name:
            raise InvalidInputError(f"image {im.image_id}: name {im.name!r} must be non-empty without surrounding whitespace")
        out.append(" ".join([str(int(im.image_id)), *(repr(float(v)) for v in q), *(repr(float(v)) for v in t),
                             str(int(im.camera_id)), im.name]))
        xy = np.asarray(im.xy_px, dtype=np.float64).reshape(-1, 2) + _OFFSET
        ids = np.asarray(im.point3d_ids, dtype=np.int64).reshape(-1)
        if len(ids) != len(xy):
            raise InvalidInputError(f"image {im.image_id}: {len(xy)} 2D points but {len(ids)} point3d_ids")
        out.append(" ".join(f"{x!r} {y!r} {int(i)}" for (x, y), i in zip(xy.tolist(), ids.tolist())))
    path = Path(path)
    write_atomic_text(path, "\n".join(out) + "\n")
    return path


# ------------------------------------------------------------------------------------------ points
@dataclass
class ColmapPoints3D:
    """Contents of ``points3D.txt``.

    Attributes
    ----------
    ids : (M,) int64
    xyz : (M, 3) float64, world coordinates
    rgb : (M, 3) uint8
    error : (M,) float64, mean reprojection error (px)
    tracks : list of (K, 2) int64 arrays of ``(IMAGE_ID, POINT2D_IDX)``
    """

    ids: np.ndarray
    xyz: np.ndarray
    rgb: np.ndarray
    error: np.ndarray
    tracks: list


def read_colmap_points3d(path) -> ColmapPoints3D:
    """Read ``points3D.txt``."""
    path = Path(path)
    ids, xyz, rgb, err, tracks = [], [], [], [], []
    for lineno, line in _read_lines(path):
        tok = line.split()
        if len(tok) < 8 or (len(tok) - 8) % 2:
            raise CorruptFileError(
                f"{path}:{lineno}: expected 'POINT3D_ID X Y Z R G B ERROR (IMAGE_ID POINT2D_IDX)...', got {len(tok)} values"
            )
        ids.append(_num(tok[0], path, lineno, "POINT3D_ID", int))
        xyz.append([_num(v, path, lineno, n) for v, n in zip(tok[1:4], "XYZ")])
        rgb.append([_num(v, path, lineno, n, int) for v, n in zip(tok[4:7], "RGB")])
        err.append(_num(tok[7], path, lineno, "ERROR"))
        try:
            tracks.append(np.array(tok[8:], dtype=np.int64).reshape(-1, 2))
        except ValueError:
            raise CorruptFileError(f"{path}:{lineno}: TRACK entries must be integers") from None
    return ColmapPoints3D(np.array(ids, dtype=np.int64), np.array(xyz, dtype=np.float64).reshape(-1, 3),
                          np.clip(np.array(rgb, dtype=np.int64).reshape(-1, 3), 0, 255).astype(np.uint8),
                          np.array(err, dtype=np.float64), tracks)


def write_colmap_points3d(path, points: ColmapPoints3D) -> Path:
    """Write ``points3D.txt`` atomically."""
    n = len(points.ids)
    out = ["# 3D point list with one line of data per point:",
           "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
           f"# Number of points: {n}"]
    for i in range(n):
        x, y, z = (repr(float(v)) for v in points.xyz[i])
        r, g, b = (str(int(v)) for v in points.rgb[i])
        tr = " ".join(f"{int(a)} {int(b_)}" for a, b_ in np.asarray(points.tracks[i]).reshape(-1, 2))
        out.append(f"{int(points.ids[i])} {x} {y} {z} {r} {g} {b} {float(points.error[i])!r} {tr}".rstrip())
    path = Path(path)
    write_atomic_text(path, "\n".join(out) + "\n")
    return path
