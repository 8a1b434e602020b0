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

__all__ = ["FrameUnit", "Sensor", "OrientedImage", "OrientedCameras", "CAMERAS_FORMAT", "CAMERAS_VERSION", "check_crs",
           "check_plausible_camera", "MAX_COORDINATE_M"]

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


#: largest plausible coordinate of a projection centre (m): beyond any projected CRS's extent
MAX_COORDINATE_M = 1e8


def _bulk(values: list, n: int, where, *, allow_none: bool = False, ravel: bool = False) -> np.ndarray:
    """(len(values), n) float array of lists of ``n`` numbers, converted at once; when that fails (a ragged list,
    text, a non-finite number) the values are checked one by one and the first bad one is reported by :func:`_num_list`
    with ``where(k)``."""
    try:
        A = np.array(values, dtype=float).reshape(len(values), -1) if values else np.zeros((0, n))
        ok = A.shape[1] == n and all(isinstance(v, (list, tuple)) for v in values)
        if ok and not ravel:
            ok = all(len(v) == n for v in values)
    except (TypeError, ValueError):
        ok = False
    if ok and (allow_none or np.all(np.isfinite(A))):
        return A
    rows = []
    for k, v in enumerate(values):
        flat = np.asarray(v, dtype=object).ravel().tolist() if ravel and isinstance(v, list) else v
        rows.append(_num_list(flat, n, where(k), allow_none=allow_none))
    return np.array(rows, dtype=float).reshape(len(values), n)


def _check_frame_path(frame, where: str) -> None:
    """A frame path must be relative to the cameras.json folder and stay inside it (no absolute path, no '..')."""
    import posixpath

    if not isinstance(frame, str) or not frame.strip():
        raise ConfigError(f"{where} = {frame!r}: expected a path relative to the cameras.json folder, e.g. 'frames/<name>.tif'")
    norm = posixpath.normpath(frame.replace("\\", "/"))
    if frame.startswith(("/", "\\")) or (len(frame) > 1 and frame[1] == ":") \
            or norm == ".." or norm.startswith("../"):
        raise ConfigError(f"{where} = {frame!r} points outside the survey folder; expected a path relative to the "
                          "cameras.json folder that stays inside it (e.g. 'frames/<name>.tif')")


_CRS_OK: set[str] = set()


def check_crs(crs: str | None, where: str) -> None:
    """Refuse a CRS string pyproj cannot read (an unknown EPSG code, a typo) with ``where`` and the value."""
    if crs is None or crs in _CRS_OK:
        return
    try:
        from pyproj import CRS
        from pyproj.exceptions import CRSError
    except ImportError:  # pragma: no cover - pyproj is a dependency
        return
    try:
        CRS.from_user_input(crs)
    except CRSError as exc:
        raise ConfigError(f"{where} = {crs!r} is not a coordinate reference system pyproj knows ({exc}); "
                          "expected e.g. 'EPSG:32633' or null for a local frame") from None
    _CRS_OK.add(crs)


def check_plausible_camera(cam: Camera, where: str) -> None:
    """Refuse intrinsics no real camera has (bounds documented in docs/formats/cameras.md):

    focal lengths between 0.04 and 200 image widths/heights (fields of view of ~170° to ~0.3°), the principal
    point within one image size of the image, and a distortion that moves no image corner or edge midpoint by
    more than the image's larger side (k1 = 1e6 moves a corner by millions of pixels).
    """
    w, h = cam.image_size
    K = np.asarray(cam.K, float)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for name, f, n in (("fx", fx, w), ("fy", fy, h)):
        if not (np.isfinite(f) and 0.04 * n <= f <= 200.0 * n):
            raise ConfigError(f"{where}: focal length {name} = {f:.6g} px for a {w}x{h} image; expected "
                              f"{0.04 * n:.4g}..{200.0 * n:.4g} px (0.04 to 200 times the image size)")
    if not (-w <= cx <= 2 * w and -h <= cy <= 2 * h):
        raise ConfigError(f"{where}: principal point ({cx:.6g}, {cy:.6g}) px lies more than one image size outside "
                          f"the {w}x{h} image; expected it near the image centre")
    pts = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1], [(w - 1) / 2, 0], [0, (h - 1) / 2],
                    [w - 1, (h - 1) / 2], [(w - 1) / 2, h - 1]], float)
    with np.errstate(all="ignore"):
        try:
            moved = np.linalg.norm(np.asarray(cam.distort(pts), float) - pts, axis=1)
        except (ValueError, FloatingPointError, ArithmeticError):
            moved = np.array([np.inf])
    worst = float(np.max(np.where(np.isfinite(moved), moved, np.inf)))
    if worst > max(w, h):
        dist = {k: v for k, v in cam.param_dict.items() if k not in ("fx", "fy", "cx", "cy", "c_mm", "x0_mm", "y0_mm") and v}
        raise ConfigError(f"{where}: the distortion ({', '.join(f'{k}={v:.6g}' for k, v in dist.items()) or 'none'}) "
                          f"moves an image corner by {worst:.4g} px, more than the image size ({max(w, h)} px); "
                          "expected plausible lens distortion coefficients")


def _check_inline_camera(inline, cam: Camera | None, where: str, camera_id: str) -> None:
    """An image's inline camera must agree with ``cameras[camera_id]`` (it is a copy for self-contained images)."""
    if cam is None:
        return  # the unknown camera_id is reported by the constructor
    other = Camera.from_dict(inline, source=where)
    a, b = np.asarray(other.params, float), np.asarray(cam.params, float)
    if other.model != cam.model or other.image_size != cam.image_size or a.shape != b.shape \
            or not np.allclose(a, b, rtol=1e-9, atol=1e-12):
        diff = [k for k, x, y in zip(cam.param_names, b, a) if not np.isclose(x, y, rtol=1e-9, atol=1e-12)] \
            if a.shape == b.shape else ["model"]
        raise ConfigError(f"{where}: the image's inline camera disagrees with cameras.{camera_id} "
                          f"({', '.join(diff[:4]) or 'model/image size'} differ); expected the same intrinsics "
                          "(the inline copy is informative: remove it or make it equal)")


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
        self._by_name: dict[str, OrientedImage] = {}
        dup: set[str] = set()
        for im in self.images:  # one pass (a 100,000-image file loads in linear time)
            if im.name in self._by_name:
                dup.add(im.name)
            self._by_name[im.name] = im
        if dup:
            raise ConfigError(f"cameras.json: image names must be unique; repeated: {sorted(dup)[:5]}")
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
        im = self._by_name.get(name)
        if im is not None and im in self.images:
            return im
        for im in self.images:  # the list was changed after construction
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
    def from_dict(cls, d, *, source: str = "cameras.json", root: Path | None = None,
                  confine_frames: bool = True) -> "OrientedCameras":
        """The content of a parsed ``cameras.json`` after checking every value (errors name ``source``, the key and
        the value): finite poses and proper rotations, sigmas finite or NaN, plausible intrinsics
        (:func:`check_plausible_camera`), a CRS pyproj knows (:func:`check_crs`), inline cameras equal to ``cameras``,
        and (``confine_frames``) frame paths relative to the file's folder that stay inside it. Linear in the images.
        """
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
        check_crs(crs, f"{source}: key 'crs'")
        cams = {str(k): Camera.from_dict(v, source=f"{source}: cameras.{k}") for k, v in d["cameras"].items()}
        for k, cam in cams.items():
            check_plausible_camera(cam, f"{source}: cameras.{k}")
        if not isinstance(d.get("images"), list):
            raise ConfigError(f"{source}: key 'images' must be a list of oriented images")
        raw_cams = d["cameras"]
        rows = d["images"]
        Rs, ts, centers, cstd, rstd = [], [], [], [], []
        for i, e in enumerate(rows):  # structure, per image (cheap); the numbers are checked for all images at once
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
            Rs.append(cfw["R"])
            ts.append(cfw["t"])
            centers.append(e.get("center"))
            cstd.append(e.get("center_std"))
            rstd.append(e.get("rotation_std_deg"))
            frame = e.get("frame")
            if frame is not None and confine_frames:
                _check_frame_path(frame, f"{where}.frame")
            inline = e.get("camera")
            if inline is not None and inline != raw_cams.get(str(e["camera_id"])):
                _check_inline_camera(inline, cams.get(str(e["camera_id"])), f"{where}.camera", str(e["camera_id"]))
        n = len(rows)
        wh = lambda k: f"{source}: images[{k}]"  # noqa: E731
        R = _bulk(Rs, 9, lambda k: f"{wh(k)}.cam_from_world.R", ravel=True).reshape(n, 3, 3)
        t = _bulk(ts, 3, lambda k: f"{wh(k)}.cam_from_world.t")
        if n:
            err = np.abs(np.einsum("nij,nkj->nik", R, R) - np.eye(3)).reshape(n, 9).max(axis=1)
            bad = np.flatnonzero((err > 1e-6) | (np.linalg.det(R) < 0))
            if len(bad):
                raise ConfigError(f"{wh(int(bad[0]))}.cam_from_world.R: not a proper rotation (R R^T = I, det R = +1 expected)")
        C = -np.einsum("nji,nj->ni", R, t)
        far = np.flatnonzero(~np.all(np.abs(C) <= MAX_COORDINATE_M, axis=1))
        if len(far):
            raise ConfigError(f"{wh(int(far[0]))}: projection centre {C[far[0]].tolist()} m lies beyond {MAX_COORDINATE_M:g} m "
                              "of the CRS origin; expected coordinates in metres of a projected or local frame")
        given = [k for k, c in enumerate(centers) if c is not None]
        if given:
            Cg = _bulk([centers[k] for k in given], 3, lambda j: f"{wh(given[j])}.center")
            dev = np.linalg.norm(Cg - C[given], axis=1)
            off = np.flatnonzero(~(dev <= 1e-3))
            if len(off):
                k = given[int(off[0])]
                raise ConfigError(f"{wh(k)}: 'center' {Cg[off[0]].tolist()} disagrees with -R^T t = {C[k].tolist()} by "
                                  f"{dev[off[0]]:.4g} m; expected the same projection centre")
        stds = []
        for vals, key, unit in ((cstd, "center_std", "m"), (rstd, "rotation_std_deg", "deg")):
            got = [k for k, v in enumerate(vals) if v is not None]
            arr = [None] * n
            if got:
                A = _bulk([vals[k] for k in got], 3, lambda j: f"{wh(got[j])}.{key}", allow_none=True)
                badk = np.flatnonzero(np.isinf(A).any(axis=1) | (A < 0).any(axis=1))
                if len(badk):
                    j = int(badk[0])
                    c = int(np.flatnonzero(np.isinf(A[j]) | (A[j] < 0))[0])
                    raise ConfigError(f"{wh(got[j])}.{key}[{c}] = {float(A[j, c])!r}: expected a finite sigma >= 0 in {unit} "
                                      "(NaN or null = not determined)")
                for j, k in enumerate(got):
                    arr[k] = A[j]
            stds.append(arr)
        images = []
        for i, e in enumerate(rows):
            try:
                images.append(OrientedImage(str(e["name"]), str(e["camera_id"]), R[i], t[i], center_std=stds[0][i],
                                            rotation_std_deg=stds[1][i], frame=e.get("frame"), source=e.get("source"),
                                            unit=e.get("unit", "K"), sensor=e.get("sensor", "thermal"),
                                            notes=e.get("notes", "")))
            except ConfigError as exc:
                raise ConfigError(f"{wh(i)}: {exc}") from None
        try:
            return cls(cams, images, crs=crs, notes=str(d.get("notes", "")), root=root)
        except ConfigError as exc:
            msg = str(exc)
            raise ConfigError(f"{source}: {msg[len('cameras.json: '):] if msg.startswith('cameras.json: ') else msg}") from None

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
