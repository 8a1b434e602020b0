"""``cameras.json``: the one file format of oriented images, read and written by every verb.

``thermogrammetry survey`` writes it; ``dense``, ``ortho``, ``texture``, ``correct`` and ``closerange``
read it (``closerange`` writes it too). One documented, versioned schema (version 1)::

    {
      "format": "thermogrammetry/cameras",
      "version": 1,
      "crs": "EPSG:32631" | null,            # object frame of every pose/centre; null = local frame
      "cameras": {"<camera_id>": <camera JSON>, ...},   # intrinsics shared by images (Camera.to_dict())
      "images": [
        {
          "name": "DJI_0008_T",               # unique image name (file stem or frame name)
          "camera_id": "thermal",             # key into "cameras"
          "camera": <camera JSON>,            # the same intrinsics, inline (self-contained per image)
          "sensor": "thermal" | "rgb",
          "cam_from_world": {"R": [[3x3]], "t": [3]},   # X_cam = R X_world + t (metres)
          "center": [X, Y, Z],                # projection centre C = -R^T t, in "crs" (metres)
          "center_std": [sX, sY, sZ] | null,  # a-posteriori sigma of the centre (m)
          "rotation_std_deg": [s_wx, s_wy, s_wz] | null,  # sigma of the left increment about camera axes
          "frame": "frames/DJI_0008_T.tif" | null,   # decoded frame, relative to the file's folder
          "source": "/abs/path/DJI_0008_T.JPG" | null,  # what the user gave
          "unit": "K" | "counts" | "dn"       # what the frame's values are: kelvin, raw sensor counts,
                                              # or display numbers of an 8-bit rendering (no temperature)
        }, ...
      ]
    }

Conventions (docs/conventions.md): camera frame x right, y down, z forward; pixels in OpenCV's
convention; poses ``cam_from_world``. Centres are stored redundantly with ``t`` for people and GIS
tools; the reader checks that they agree (to 1 mm).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Mapping

import numpy as np

from .._atomic import write_atomic_text
from ..camera import Camera
from ..enums import StrChoice
from ..errors import ConfigError, CorruptFileError, DataFileError, UnsupportedFormatError

__all__ = ["FrameUnit", "Sensor", "OrientedImage", "OrientedCameras", "CAMERAS_FORMAT", "CAMERAS_VERSION"]

CAMERAS_FORMAT = "thermogrammetry/cameras"
CAMERAS_VERSION = 1
_TOP_KEYS = ("format", "version", "crs", "cameras", "images", "notes")
_IMAGE_KEYS = ("name", "camera_id", "camera", "sensor", "cam_from_world", "center", "center_std",
               "rotation_std_deg", "frame", "source", "unit", "notes")


class FrameUnit(StrChoice):
    """What the values of a decoded frame are."""

    KELVIN = "K"
    COUNTS = "counts"
    DN = "dn"  # display numbers of a palette/greyscale rendering: geometry only, no temperature


class Sensor(StrChoice):
    THERMAL = "thermal"
    RGB = "rgb"


@dataclass
class OrientedImage:
    """One oriented image: intrinsics id, ``cam_from_world`` pose and its precision.

    Attributes
    ----------
    name : str
    camera_id : str
    R : (3, 3) array, world -> camera rotation
    t : (3,) array, metres
    center_std : (3,) array or None, metres
    rotation_std_deg : (3,) array or None
    frame : str or None, decoded frame path relative to the cameras.json folder
    source : str or None, original input path
    unit : FrameUnit
    sensor : Sensor
    """

    name: str
    camera_id: str
    R: np.ndarray
    t: np.ndarray
    center_std: np.ndarray | None = None
    rotation_std_deg: np.ndarray | None = None
    frame: str | None = None
    source: str | None = None
    unit: FrameUnit = FrameUnit.KELVIN
    sensor: Sensor = Sensor.THERMAL
    notes: str = ""

    def __post_init__(self):
        self.R = np.asarray(self.R, dtype=float).reshape(3, 3)
        self.t = np.asarray(self.t, dtype=float).reshape(3)
        self.unit = FrameUnit(self.unit)
        self.sensor = Sensor(self.sensor)
        if self.center_std is not None:
            self.center_std = np.asarray(self.center_std, dtype=float).reshape(3)
        if self.rotation_std_deg is not None:
            self.rotation_std_deg = np.asarray(self.rotation_std_deg, dtype=float).reshape(3)

    @property
    def center(self) -> np.ndarray:
        """Projection centre ``C = -R^T t`` (m, in the file's CRS)."""
        return -self.R.T @ self.t

    @property
    def pose(self):
        from ..geometry import Pose

        return Pose(self.R, self.t)


def _num_list(v, n, where, allow_none=False):
    if v is None and allow_none:
        return None
    try:
        a = np.asarray(v, dtype=float) if isinstance(v, (list, tuple)) else None
    except (TypeError, ValueError):  # ragged lists, strings, objects (found by fuzzing)
        a = None
    if a is None or a.size != n:
        raise ConfigError(f"{where}: expected a list of {n} numbers, got {v!r}")
    if allow_none and not np.all(np.isfinite(a)):
        return a  # NaN sigma = not determined; kept as NaN
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"{where}: expected finite numbers, got {v!r}")
    return a


def _jsonable(a):
    if a is None:
        return None
    return [None if not np.isfinite(x) else float(x) for x in np.asarray(a, dtype=float).ravel()]


@dataclass
class OrientedCameras:
    """The content of a ``cameras.json``: a CRS, intrinsics by id, oriented images.

    Use :meth:`load` / :meth:`save` for files, :meth:`from_dict` / :meth:`to_dict` in memory.
    """

    cameras: dict[str, Camera]
    images: list[OrientedImage]
    crs: str | None = None
    notes: str = ""
    root: Path | None = field(default=None, repr=False)  # folder of the file (for frame paths)

    def __post_init__(self):
        names = [im.name for im in self.images]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ConfigError(f"cameras.json: image names must be unique; repeated: {dup[:5]}")
        for im in self.images:
            if im.camera_id not in self.cameras:
                raise ConfigError(f"cameras.json: image {im.name!r} names camera_id {im.camera_id!r}; "
                                  f"expected one of {sorted(self.cameras)}")

    # ------------------------------------------------------------------ access
    def __iter__(self) -> Iterator[OrientedImage]:
        return iter(self.images)

    def __len__(self) -> int:
        return len(self.images)

    def names(self) -> list[str]:
        return [im.name for im in self.images]

    def image(self, name: str) -> OrientedImage:
        for im in self.images:
            if im.name == name:
                return im
        raise KeyError(f"no image {name!r} in cameras.json; images: {self.names()[:5]}...")

    def camera_of(self, image: OrientedImage | str) -> Camera:
        im = self.image(image) if isinstance(image, str) else image
        return self.cameras[im.camera_id]

    def frame_path(self, image: OrientedImage | str) -> Path | None:
        """Absolute path of the decoded frame (``frame`` relative to the file's folder)."""
        im = self.image(image) if isinstance(image, str) else image
        if im.frame is None:
            return None
        p = Path(im.frame)
        return p if p.is_absolute() or self.root is None else self.root / p

    def read_frame(self, image: OrientedImage | str) -> np.ndarray:
        """The decoded frame as a 2D array: float32 kelvin (unit ``K``), uint16 raw counts (``counts``)
        or uint8/uint16 display numbers (``dn``); (H, W, 3) for RGB images."""
        import tifffile

        p = self.frame_path(image)
        if p is None:
            name = image if isinstance(image, str) else image.name
            raise DataFileError(f"cameras.json: image {name!r} has no decoded 'frame'; expected frames/<name>.tif beside it")
        try:
            return tifffile.imread(p)
        except FileNotFoundError:
            raise DataFileError(f"{p}: frame file missing (named by cameras.json)") from None
        except Exception as exc:  # tifffile raises many kinds on damaged files
            raise CorruptFileError(f"{p}: cannot read frame TIFF ({exc})") from None

    # ------------------------------------------------------------------ dict form
    def to_dict(self) -> dict:
        cams = {k: c.to_dict() for k, c in self.cameras.items()}
        images = []
        for im in self.images:
            images.append({
                "name": im.name,
                "camera_id": im.camera_id,
                "camera": cams[im.camera_id],
                "sensor": im.sensor.value,
                "cam_from_world": {"R": im.R.tolist(), "t": im.t.tolist()},
                "center": im.center.tolist(),
                "center_std": _jsonable(im.center_std),
                "rotation_std_deg": _jsonable(im.rotation_std_deg),
                "frame": im.frame,
                "source": im.source,
                "unit": im.unit.value,
                **({"notes": im.notes} if im.notes else {}),
            })
        d = {"format": CAMERAS_FORMAT, "version": CAMERAS_VERSION, "crs": self.crs, "cameras": cams, "images": images}
        if self.notes:
            d["notes"] = self.notes
        return d

    @classmethod
    def from_dict(cls, d, *, source: str = "cameras.json", root: Path | None = None) -> "OrientedCameras":
        if not isinstance(d, Mapping):
            raise UnsupportedFormatError(f"{source}: expected a JSON object with 'format': {CAMERAS_FORMAT!r}, got {type(d).__name__}")
        if d.get("format") != CAMERAS_FORMAT:
            hint = ""
            if "format" not in d and ("stations" in d or "cameras" in d or "frames" in d):
                hint = " (this looks like an older or different cameras file; re-run the verb that wrote it)"
            raise UnsupportedFormatError(f"{source}: key 'format' is {d.get('format')!r}; expected {CAMERAS_FORMAT!r}{hint}")
        if d.get("version") != CAMERAS_VERSION or isinstance(d.get("version"), bool):
            raise UnsupportedFormatError(f"{source}: key 'version' is {d.get('version')!r}; this reader supports version {CAMERAS_VERSION}")
        unknown = [k for k in d if k not in _TOP_KEYS]
        if unknown:
            raise ConfigError(f"{source}: unknown key(s) {unknown}; expected keys: {', '.join(_TOP_KEYS)}")
        crs = d.get("crs")
        if crs is not None and not isinstance(crs, str):
            raise ConfigError(f"{source}: key 'crs' must be a string such as 'EPSG:2056' or null, got {crs!r}")
        if not isinstance(d.get("cameras"), Mapping) or not d["cameras"]:
            raise ConfigError(f"{source}: key 'cameras' must be a non-empty object id -> camera JSON")
        cams = {str(k): Camera.from_dict(v, source=f"{source}: cameras.{k}") for k, v in d["cameras"].items()}
        if not isinstance(d.get("images"), list):
            raise ConfigError(f"{source}: key 'images' must be a list of oriented images")
        images = []
        for i, e in enumerate(d["images"]):
            where = f"{source}: images[{i}]"
            if not isinstance(e, Mapping):
                raise ConfigError(f"{where}: expected an object, got {e!r}")
            bad = [k for k in e if k not in _IMAGE_KEYS]
            if bad:
                raise ConfigError(f"{where}: unknown key(s) {bad}; expected keys: {', '.join(_IMAGE_KEYS)}")
            for k in ("name", "camera_id", "cam_from_world"):
                if k not in e:
                    raise ConfigError(f"{where}: missing key {k!r}")
            cfw = e["cam_from_world"]
            if not isinstance(cfw, Mapping) or "R" not in cfw or "t" not in cfw:
                raise ConfigError(f"{where}.cam_from_world: expected an object with 'R' (3x3) and 't' (3)")
            R = _num_list(np.asarray(cfw["R"], dtype=object).ravel().tolist() if isinstance(cfw["R"], list) else cfw["R"],
                          9, f"{where}.cam_from_world.R").reshape(3, 3)
            if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
                raise ConfigError(f"{where}.cam_from_world.R: not a proper rotation (R R^T = I, det R = +1 expected)")
            t = _num_list(cfw["t"], 3, f"{where}.cam_from_world.t")
            try:
                im = OrientedImage(str(e["name"]), str(e["camera_id"]), R, t,
                                   center_std=_num_list(e.get("center_std"), 3, f"{where}.center_std", allow_none=True),
                                   rotation_std_deg=_num_list(e.get("rotation_std_deg"), 3, f"{where}.rotation_std_deg", allow_none=True),
                                   frame=e.get("frame"), source=e.get("source"), unit=e.get("unit", "K"),
                                   sensor=e.get("sensor", "thermal"), notes=e.get("notes", ""))
            except ConfigError as exc:
                raise ConfigError(f"{where}: {exc}") from None
            if e.get("center") is not None:
                C = _num_list(e["center"], 3, f"{where}.center")
                if np.linalg.norm(C - im.center) > 1e-3:
                    raise ConfigError(f"{where}: 'center' {C.tolist()} disagrees with -R^T t = {im.center.tolist()} by "
                                      f"{np.linalg.norm(C - im.center):.4g} m; expected the same projection centre")
            images.append(im)
        try:
            return cls(cams, images, crs=crs, notes=str(d.get("notes", "")), root=root)
        except ConfigError as exc:
            raise ConfigError(f"{source}: {exc}".replace("cameras.json: ", "")) from None

    # ------------------------------------------------------------------ files
    def save(self, path) -> Path:
        path = Path(path)
        write_atomic_text(path, json.dumps(self.to_dict(), indent=1) + "\n")
        return path

    @classmethod
    def load(cls, path) -> "OrientedCameras":
        """Read a ``cameras.json`` (a folder is taken as ``folder/cameras.json``)."""
        path = Path(path)
        if path.is_dir():
            path = path / "cameras.json"
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise DataFileError(f"{path}: no such file; expected a cameras.json written by 'thermogrammetry survey'") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise DataFileError(f"{path}: cannot read cameras file ({getattr(exc, 'strerror', None) or exc})") from None
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CorruptFileError(f"{path}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None
        return cls.from_dict(d, source=str(path), root=path.parent)
