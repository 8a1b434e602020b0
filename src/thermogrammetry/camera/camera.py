"""The :class:`Camera` class: a thin, immutable wrapper over :mod:`thermogrammetry.camera.models`.

JSON file format (``Camera.save`` / ``Camera.load``), version 1::

    {
      "format": "thermogrammetry.camera",
      "version": 1,
      "name": "FLIR A320",                      # optional
      "model": "photogrammetric",               # pinhole | opencv | photogrammetric
      "image_size": [320, 240],                 # width, height in pixels
      "pixel_pitch_um": [25.0, 25.0],           # or a number, or null (required for photogrammetric)
      "params": {"c_mm": 17.2262, "x0_mm": 0.2883, ...},
      "units": {"c_mm": "mm", "K1": "mm^-2", ...},   # optional; checked when present
      "std": {"c_mm": 0.1288, ...},                  # optional standard deviations, same units
      "comment": "free text"                          # optional
    }

Unknown keys, unknown parameter names, units other than the documented ones, missing
required parameters (``fx fy cx cy`` / ``c_mm x0_mm y0_mm``) and unknown models are
errors naming the file and the key; missing distortion terms are 0.

References
----------
Brown, D. C. (1971). Close-range camera calibration. Photogrammetric Engineering 37(8), 855-866.
Fraser, C. S. (1997). Digital camera self-calibration. ISPRS J. Photogramm. Remote Sens. 52, 149-159.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from .._atomic import write_atomic_text
from .._validate import as_points
from ..errors import (
    ConfigError,
    CorruptFileError,
    DataFileError,
    InvalidInputError,
    NonFiniteError,
    ShapeError,
    UnknownModelError,
    UnsupportedFormatError,
)
from . import models as M
from .models import PARAM_NAMES, PARAM_UNITS, REQUIRED_PARAMS, CameraModel

__all__ = ["Camera", "FORMAT_NAME", "FORMAT_VERSION"]

FORMAT_NAME = "thermogrammetry.camera"
FORMAT_VERSION = 1
_TOP_KEYS = ("format", "version", "name", "model", "image_size", "pixel_pitch_um", "params", "units", "std", "comment")

_SUPERSCRIPT = str.maketrans({"⁻": "-", "¹": "1", "²": "2", "⁴": "4", "⁶": "6", "⁸": "8", "⁰": "0"})
_UNIT_ALIASES = {
    "px": "px", "pix": "px", "pixel": "px", "pixels": "px",
    "mm": "mm", "millimetre": "mm", "millimetres": "mm", "millimeter": "mm", "millimeters": "mm",
    "1": "1", "": "1", "-": "1", "unitless": "1", "dimensionless": "1", "none": "1",
}


def _normalise_unit(text: str) -> str:
    u = str(text).strip().lower().replace(" ", "").translate(_SUPERSCRIPT).replace("**", "^")
    if u in _UNIT_ALIASES:
        return _UNIT_ALIASES[u]
    if u.startswith("1/mm"):  # 1/mm^2, 1/mm2, 1/mm
        e = u[4:].lstrip("^") or "1"
        return f"mm^-{e}"
    if u.startswith("mm^-") or u.startswith("mm-"):
        return "mm^-" + u.split("-", 1)[1]
    return u


def _as_float(value, what: str, error=ConfigError) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise error(f"{what}: expected a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise NonFiniteError(f"{what}: expected a finite number, got {v!r}")
    return v


class Camera:
    """An intrinsic camera: model, image size, parameters (+ optional standard deviations).

    Parameters
    ----------
    model : {"pinhole", "opencv", "photogrammetric"} or CameraModel
        ``opencv`` is the forward Brown-Conrady form, ``photogrammetric`` the correction form
        (see :mod:`thermogrammetry.camera.models` for formulas and parameter layouts).
    image_size : (int, int)
        ``(width, height)`` in pixels.
    params : Mapping[str, float] or sequence of P floats
        Named parameters (see :data:`~thermogrammetry.camera.models.PARAM_NAMES`); distortion
        terms that are absent are 0. A sequence must have the full length P in layout order.
    pixel_pitch_um : float or (float, float), optional
        Pixel pitch (px, py) in micrometres; required for ``photogrammetric``.
    param_std : Mapping[str, float], optional
        Standard deviations of some or all parameters (same units); absent ones are NaN.
    name : str
        Free label.

    Notes
    -----
    Pixel coordinates: (0, 0) is the centre of the top-left pixel, x right, y down.
    Camera frame: x right, y down, z forward.

    References
    ----------
    Brown (1971); Fraser (1997); OpenCV calib3d camera model.
    """

    __slots__ = ("_model", "_size", "_params", "_pitch", "_std", "_name")

    def __init__(self, model, image_size, params, *, pixel_pitch_um=None, param_std=None, name: str = ""):
        self._model = CameraModel(model)
        self._size = self._check_size(image_size)
        names = PARAM_NAMES[self._model]
        self._params = self._read_params(params, names)
        self._pitch = self._check_pitch(pixel_pitch_um)
        if self._model is CameraModel.PHOTOGRAMMETRIC and self._pitch is None:
            raise InvalidInputError(
                "pixel_pitch_um is required for the photogrammetric model: give a number or (px, py) in micrometres"
            )
        self._check_values()
        self._std = None if param_std is None else self._read_std(param_std, names)
        self._name = str(name)

    # ---------------------------------------------------------------- validation
    @staticmethod
    def _check_size(image_size) -> tuple[int, int]:
        try:
            w, h = image_size
        except (TypeError, ValueError):
            raise ShapeError(f"image_size: expected (width, height), got {image_size!r}") from None
        out = []
        for v, label in ((w, "width"), (h, "height")):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer, float, np.floating)) or float(v) != int(v) or int(v) <= 0:
                raise InvalidInputError(f"image_size: {label} must be a positive integer (pixels), got {v!r}")
            out.append(int(v))
        return out[0], out[1]

    @staticmethod
    def _check_pitch(pitch):
        if pitch is None:
            return None
        arr = np.asarray(pitch, dtype=np.float64) if not isinstance(pitch, str) else None
        if arr is None or arr.shape not in ((), (1,), (2,)):
            raise ShapeError(f"pixel_pitch_um: expected a number or (px, py) in micrometres, got {pitch!r}")
        arr = np.broadcast_to(arr.reshape(-1), (2,)) if arr.size == 1 else arr
        if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
            raise InvalidInputError(f"pixel_pitch_um: expected positive finite micrometres, got {pitch!r}")
        return float(arr[0]), float(arr[1])

    def _read_params(self, params, names) -> np.ndarray:
        if isinstance(params, Mapping):
            unknown = [k for k in params if k not in names]
            if unknown:
                raise ConfigError(
                    f"unknown parameter(s) {', '.join(map(repr, unknown))} for model {self._model.value!r}; "
                    f"expected names from: {' '.join(names)}"
                )
            missing = [k for k in REQUIRED_PARAMS[self._model] if k not in params]
            if missing:
                raise ConfigError(
                    f"missing parameter(s) {', '.join(map(repr, missing))} for model {self._model.value!r} "
                    f"(required: {' '.join(REQUIRED_PARAMS[self._model])})"
                )
            arr = np.array([_as_float(params.get(k, 0.0), f"params[{k!r}]", ConfigError) for k in names])
        else:
            try:
                arr = np.asarray(params, dtype=np.float64)
            except (TypeError, ValueError):
                raise ShapeError(f"params: expected a mapping name -> value or {len(names)} numbers, got {params!r}") from None
            if arr.shape != (len(names),):
                raise ShapeError(
                    f"params: expected shape ({len(names)},) for model {self._model.value!r} "
                    f"({' '.join(names)}), got {arr.shape}"
                )
            arr = arr.copy()
            if not np.all(np.isfinite(arr)):
                i = int(np.flatnonzero(~np.isfinite(arr))[0])
                raise NonFiniteError(f"params[{names[i]!r}]: expected a finite number, got {float(arr[i])!r}")
        arr.flags.writeable = False
        return arr

    def _check_values(self) -> None:
        p = dict(zip(PARAM_NAMES[self._model], self._params))
        for k in ("fx", "fy", "c_mm"):
            if k in p and p[k] <= 0:
                raise InvalidInputError(f"params[{k!r}]: must be positive, got {float(p[k])!r}")

    def _read_std(self, std, names) -> np.ndarray:
        if isinstance(std, Mapping):
            unknown = [k for k in std if k not in names]
            if unknown:
                raise ConfigError(
                    f"param_std: unknown parameter(s) {', '.join(map(repr, unknown))} for model "
                    f"{self._model.value!r}; expected names from: {' '.join(names)}"
                )
            arr = np.full(len(names), np.nan)
            for i, k in enumerate(names):
                if k in std and std[k] is not None:
                    arr[i] = _as_float(std[k], f"param_std[{k!r}]")
                    if arr[i] < 0:
                        raise InvalidInputError(f"param_std[{k!r}]: must be >= 0, got {float(arr[i])!r}")
        else:
            arr = np.array(std, dtype=np.float64)
            if arr.shape != (len(names),):
                raise ShapeError(f"param_std: expected shape ({len(names)},), got {arr.shape}")
            if np.any(arr < 0):
                raise InvalidInputError(f"param_std: must be >= 0 (NaN = unknown), got {arr!r}")
        arr.flags.writeable = False
        return arr

    # ---------------------------------------------------------------- properties
    @property
    def model(self) -> CameraModel:
        return self._model

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self._size

    @property
    def width(self) -> int:
        return self._size[0]

    @property
    def height(self) -> int:
        return self._size[1]

    @property
    def name(self) -> str:
        return self._name

    @property
    def pixel_pitch_um(self) -> tuple[float, float] | None:
        """(px, py) in micrometres, or None."""
        return self._pitch

    @property
    def param_names(self) -> tuple[str, ...]:
        return PARAM_NAMES[self._model]

    @property
    def param_units(self) -> dict[str, str]:
        return dict(PARAM_UNITS[self._model])

    @property
    def params(self) -> np.ndarray:
        """(P,) float64 (read-only) in :attr:`param_names` order."""
        return self._params

    @property
    def param_std(self) -> np.ndarray | None:
        """(P,) standard deviations (NaN where unknown) or None."""
        return self._std

    @property
    def param_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in zip(self.param_names, self._params)}

    def __getitem__(self, name: str) -> float:
        try:
            return float(self._params[self.param_names.index(name)])
        except ValueError:
            raise ConfigError(
                f"unknown parameter {name!r} for model {self._model.value!r}; expected one of: {' '.join(self.param_names)}"
            ) from None

    @property
    def K(self) -> np.ndarray:
        """(3, 3) ideal pinhole matrix in px (see :func:`~thermogrammetry.camera.models.ideal_K`)."""
        return M.ideal_K(self._model, self._params, image_size=self._size, pixel_pitch_um=self._pitch)

    # ---------------------------------------------------------------- copies
    def replace(self, **named) -> "Camera":
        """A copy with some parameters (by name) or fields (``name``, ``image_size``,
        ``pixel_pitch_um``, ``param_std``) replaced. Standard deviations are kept."""
        fields = {"name": self._name, "image_size": self._size, "pixel_pitch_um": self._pitch,
                  "param_std": None if self._std is None else self._std}
        params = self.param_dict
        for k, v in named.items():
            if k in fields:
                fields[k] = v
            elif k in params:
                params[k] = v
            else:
                raise ConfigError(
                    f"replace: unknown name {k!r}; expected a parameter of model {self._model.value!r} "
                    f"({' '.join(self.param_names)}) or one of name, image_size, pixel_pitch_um, param_std"
                )
        std = fields.pop("param_std")
        return Camera(self._model, fields["image_size"], params, pixel_pitch_um=fields["pixel_pitch_um"],
                      param_std=std, name=fields["name"])

    def with_params(self, params, *, param_std=None) -> "Camera":
        """A copy with the full (P,) parameter vector replaced (standard deviations dropped unless given)."""
        return Camera(self._model, self._size, params, pixel_pitch_um=self._pitch, param_std=param_std, name=self._name)

    # ---------------------------------------------------------------- geometry
    def _kw(self):
        return {"image_size": self._size, "pixel_pitch_um": self._pitch}

    def project(self, points_cam) -> np.ndarray:
        """Project camera-frame points (N, 3) to pixels (N, 2).

        Points are projected mathematically (no visibility test); Z = 0 gives non-finite
        output and, for the photogrammetric model, NaN marks a failed Newton solve.
        """
        pts = as_points(points_cam, "points_cam", 3)
        return M.project(self._model, self._params, pts, **self._kw())

    def project_jacobian(self, points_cam, params: bool = True):
        """``(xy (N,2), J_point (N,2,3), J_params (N,2,P))``, analytic.

        ``params=False`` computes only the point Jacobian and returns ``J_params`` as None
        (cheaper: triangulation and resection with a fixed camera need no more).
        """
        pts = as_points(points_cam, "points_cam", 3)
        return M.project_jacobian(self._model, self._params, pts, wrt_params=bool(params), **self._kw())

    def project_point_jacobian(self, points_cam):
        """``(xy (N,2), J_point (N,2,3))``: projection and its Jacobian w.r.t. the point only."""
        xy, jp, _ = self.project_jacobian(points_cam, params=False)
        return xy, jp

    def unproject(self, xy_px) -> np.ndarray:
        """Undistorted rays (N, 3) with z = 1 through measured pixels (N, 2)."""
        xy = as_points(xy_px, "xy_px", 2)
        return M.unproject(self._model, self._params, xy, **self._kw())

    def distort(self, xy_ideal_px) -> np.ndarray:
        """Ideal pixels of the pinhole :attr:`K` (N, 2) -> measured (distorted) pixels (N, 2)."""
        xy = as_points(xy_ideal_px, "xy_ideal_px", 2)
        rays = np.linalg.solve(self.K, np.column_stack([xy, np.ones(len(xy))]).T).T
        return M.project(self._model, self._params, rays, **self._kw())

    def undistort(self, xy_px) -> np.ndarray:
        """Measured pixels (N, 2) -> ideal pixels of the pinhole :attr:`K` (N, 2)."""
        rays = self.unproject(xy_px)
        out = rays @ self.K.T
        return out[:, :2] / out[:, 2:3]

    # ---------------------------------------------------------------- OpenCV
    @classmethod
    def from_opencv(cls, K, dist, image_size, *, pixel_pitch_um=None, name: str = "") -> "Camera":
        """Camera from an OpenCV camera matrix and distortion vector.

        ``dist`` may have 0, 4, 5, 8, 12 or 14 entries (``k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]]``);
        the thin-prism ``s1..s4`` and tilt ``tauX tauY`` terms are not modelled and must be zero.
        ``K[0, 1]`` becomes ``skew``. Returns an ``opencv`` camera.
        """
        Km = np.asarray(K, dtype=np.float64)
        if Km.shape != (3, 3):
            raise ShapeError(f"K: expected shape (3, 3), got {Km.shape}")
        if not np.all(np.isfinite(Km)):
            raise NonFiniteError(f"K: expected finite numbers, got {Km.tolist()}")
        if abs(Km[1, 0]) > 0 or abs(Km[2, 0]) > 0 or abs(Km[2, 1]) > 0 or abs(Km[2, 2] - 1.0) > 1e-12:
            raise InvalidInputError(f"K: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {Km.tolist()}")
        d = np.asarray([] if dist is None else dist, dtype=np.float64).reshape(-1)
        if d.size not in (0, 4, 5, 8, 12, 14):
            raise ShapeError(
                f"dist: expected 4, 5, 8, 12 or 14 coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tauX tauY]]]]), "
                f"got {d.size}"
            )
        if not np.all(np.isfinite(d)):
            raise NonFiniteError(f"dist: expected finite numbers, got {d.tolist()}")
        extra_names = ("s1", "s2", "s3", "s4", "tauX", "tauY")
        bad = [f"{extra_names[i - 8]}={float(d[i])!r}" for i in range(8, d.size) if d[i] != 0.0]
        if bad:
            raise InvalidInputError(
                f"dist: thin-prism/tilt terms are not supported by thermogrammetry's camera models and must be 0, "
                f"got {', '.join(bad)}"
            )
        full = np.zeros(8)
        full[: min(d.size, 8)] = d[:8]
        params = {"fx": Km[0, 0], "fy": Km[1, 1], "cx": Km[0, 2], "cy": Km[1, 2], "skew": Km[0, 1]}
        params.update(zip(M.OPENCV_DIST_NAMES, full))
        return cls(CameraModel.OPENCV, image_size, params, pixel_pitch_um=pixel_pitch_um, name=name)

    def to_opencv(self) -> tuple[np.ndarray, np.ndarray]:
        """``(K (3,3), dist)`` for OpenCV: ``dist`` has 5 entries, or 8 when k4..k6 are non-zero.

        Raises for the photogrammetric model (convert it first with
        :func:`~thermogrammetry.camera.convert_camera`) and for non-zero skew (OpenCV's
        ``projectPoints``/``undistortPoints`` ignore ``K[0, 1]``).
        """
        if self._model is CameraModel.PHOTOGRAMMETRIC:
            raise UnknownModelError(
                "to_opencv: the photogrammetric (correction-form) model has no exact OpenCV equivalent; "
                "use thermogrammetry.camera.convert_camera(camera, 'opencv') and check its max_residual_px"
            )
        K = self.K
        if self._model is CameraModel.PINHOLE:
            return K, np.zeros(5)
        p = self.param_dict
        if p["skew"] != 0.0:
            raise InvalidInputError(
                f"to_opencv: skew={float(p['skew'])!r} px is non-zero but OpenCV's distortion functions ignore K[0, 1]; "
                "convert to a zero-skew camera first"
            )
        dist = np.array([p[k] for k in M.OPENCV_DIST_NAMES])
        if np.all(dist[5:] == 0.0):
            dist = dist[:5]
        return K, dist

    # ---------------------------------------------------------------- JSON
    def to_dict(self) -> dict:
        """JSON-ready dictionary in the versioned format (see module docstring)."""
        d = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "name": self._name,
            "model": self._model.value,
            "image_size": [self._size[0], self._size[1]],
            "pixel_pitch_um": None if self._pitch is None else [self._pitch[0], self._pitch[1]],
            "params": self.param_dict,
            "units": self.param_units,
        }
        if self._std is not None:
            d["std"] = {k: float(v) for k, v in zip(self.param_names, self._std) if np.isfinite(v)}
        return d

    @classmethod
    def from_dict(cls, d, *, source: str = "camera dict") -> "Camera":
        """Inverse of :meth:`to_dict`; errors name ``source`` (the file) and the key."""
        if not isinstance(d, Mapping):
            raise UnsupportedFormatError(f"{source}: expected a JSON object, got {type(d).__name__}")
        unknown = [k for k in d if k not in _TOP_KEYS]
        if unknown:
            raise ConfigError(f"{source}: unknown key(s) {', '.join(map(repr, unknown))}; expected keys: {', '.join(_TOP_KEYS)}")
        fmt = d.get("format")
        if fmt != FORMAT_NAME:
            raise UnsupportedFormatError(f"{source}: key 'format' is {fmt!r}; expected {FORMAT_NAME!r}")
        ver = d.get("version")
        if ver != FORMAT_VERSION or isinstance(ver, bool):
            raise UnsupportedFormatError(f"{source}: key 'version' is {ver!r}; this reader supports version {FORMAT_VERSION}")
        for key in ("model", "image_size", "params"):
            if key not in d:
                raise ConfigError(f"{source}: missing key {key!r}")
        try:
            model = CameraModel(d["model"]) if isinstance(d["model"], str) else None
        except UnknownModelError as exc:
            raise UnknownModelError(f"{source}: key 'model': {exc}") from None
        if model is None:
            raise UnknownModelError(f"{source}: key 'model' is {d['model']!r}; expected one of "
                                    + ", ".join(repr(m.value) for m in CameraModel))
        params = d["params"]
        if not isinstance(params, Mapping):
            raise ConfigError(f"{source}: key 'params' must be an object name -> number, got {params!r}")
        units = d.get("units")
        if units is not None:
            if not isinstance(units, Mapping):
                raise ConfigError(f"{source}: key 'units' must be an object name -> unit, got {units!r}")
            expected = PARAM_UNITS[model]
            for k, u in units.items():
                if k not in expected:
                    raise ConfigError(f"{source}: key 'units' names unknown parameter {k!r} for model {model.value!r}; "
                                      f"expected names from: {' '.join(expected)}")
                if _normalise_unit(u) != expected[k]:
                    raise ConfigError(f"{source}: key 'units.{k}' is {u!r}; expected {expected[k]!r}")
        std = d.get("std")
        if std is not None and not isinstance(std, Mapping):
            raise ConfigError(f"{source}: key 'std' must be an object name -> number, got {std!r}")
        name = d.get("name", "") or ""
        if not isinstance(name, str):
            raise ConfigError(f"{source}: key 'name' must be a string, got {name!r}")
        try:
            return cls(model, d["image_size"], params, pixel_pitch_um=d.get("pixel_pitch_um"), param_std=std, name=name)
        except (InvalidInputError,) as exc:
            raise type(exc)(f"{source}: {exc}") from None

    def save(self, path) -> Path:
        """Write the versioned JSON file atomically; returns the path."""
        path = Path(path)
        write_atomic_text(path, json.dumps(self.to_dict(), indent=2) + "\n")
        return path

    @classmethod
    def load(cls, path) -> "Camera":
        """Read a camera JSON file written by :meth:`save` (or by hand, same format)."""
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise DataFileError(f"{path}: cannot read camera file ({exc.strerror or exc})") from exc
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CorruptFileError(f"{path}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None
        return cls.from_dict(d, source=str(path))

    # ---------------------------------------------------------------- misc
    def __repr__(self) -> str:
        parts = [f"model={self._model.value!r}", f"image_size={self._size}"]
        if self._pitch is not None:
            parts.append(f"pixel_pitch_um={self._pitch}")
        names = self.param_names
        core = set(REQUIRED_PARAMS[self._model])
        for i, k in enumerate(names):
            v = float(self._params[i])
            if k not in core and v == 0.0:
                continue
            s = f"{k}={v:.6g}"
            if self._std is not None and np.isfinite(self._std[i]):
                s += f"±{self._std[i]:.2g}"
            parts.append(s)
        if self._name:
            parts.insert(0, f"name={self._name!r}")
        return "Camera(" + ", ".join(parts) + ")"

    def __eq__(self, other) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        same_std = (self._std is None) == (other._std is None) and (
            self._std is None or np.array_equal(self._std, other._std, equal_nan=True)
        )
        return (self._model is other._model and self._size == other._size and self._pitch == other._pitch
                and np.array_equal(self._params, other._params) and same_std and self._name == other._name)

    __hash__ = None  # mutable-looking numpy content; not hashable

    def __reduce__(self):  # pickling (dask workers) through the validated dict form keeps arrays read-only
        return (Camera.from_dict, (self.to_dict(),))
