"""Agisoft Metashape (PhotoScan >= 1.3) camera calibration XML: read and write.

File layout (``Tools > Camera Calibration > Export``, format "Agisoft Camera Calibration")::

    <?xml version="1.0" encoding="UTF-8"?>
    <calibration>
      <projection>frame</projection>
      <width>640</width> <height>512</height>
      <f>1123.4</f> <cx>-3.2</cx> <cy>4.1</cy> <b1>0.2</b1> <b2>-0.1</b2>
      <k1>..</k1> <k2>..</k2> <k3>..</k3> <k4>..</k4> <p1>..</p1> <p2>..</p2>
      <covariance><params>f cx cy k1 ...</params><coeffs>row-major n x n</coeffs></covariance>  (optional)
      <date>2024-01-01T00:00:00Z</date>
    </calibration>

Metashape's frame-camera model (Metashape Professional manual, Appendix C "Camera models";
f, cx, cy, b1, b2 in pixels, the rest unitless)::

    x = X/Z, y = Y/Z, r2 = x^2 + y^2
    x' = x (1 + K1 r2 + K2 r2^2 + K3 r2^3 + K4 r2^4) + P1 (r2 + 2 x^2) + 2 P2 x y
    y' = y (1 + K1 r2 + K2 r2^2 + K3 r2^3 + K4 r2^4) + P2 (r2 + 2 y^2) + 2 P1 x y
    u = w/2 + cx + x' (f + B1) + y' B2,      v = h/2 + cy + y' f

with (u, v) in a frame whose top-left pixel centre is (0.5, 0.5). Compared with OpenCV
(``xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2)``) **Metashape's P1 and P2 are swapped**:
``p1_opencv = P2_metashape`` and ``p2_opencv = P1_metashape`` (confirmed against the Appendix C
formula and Agisoft's forum answer "F = Fy, B1 = Fx - Fy, B2 = skew"). So, exactly::

    fx = f + B1, fy = f, skew = B2, cx = w/2 + cx_ms - 0.5, cy = h/2 + cy_ms - 0.5,
    k1..k3 = K1..K3, p1 = P2_ms, p2 = P1_ms

The ``K4 r^8`` term has no OpenCV equivalent: a calibration with K4 != 0 is converted by a
least-squares fit of the OpenCV model (k1..k6 rational) over the whole image, and the fit's
maximum residual in pixels is reported. Writing works the other way: an OpenCV camera without
k4..k6 maps exactly; anything else (rational terms, the correction-form photogrammetric model) is
fitted with Metashape's model and the residual is reported.

The legacy PhotoScan < 1.3 layout (``<fx> <fy> <cx> <cy> <skew>``, absolute principal point) is
read as well; its P1/P2 follow the old Agisoft Lens formula ``x' = ... + P2 (r2 + 2 x^2) + 2 P1 x y``,
i.e. OpenCV's order, and its principal point is taken in the same corner-origin frame (``- 0.5``).

References
----------
Agisoft Metashape Professional Edition User Manual, Appendix C: Camera models.
Brown, D. C. (1971). Close-range camera calibration. Photogrammetric Engineering 37(8), 855-866.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from .._atomic import write_atomic_text
from ..camera.camera import Camera
from ..camera.models import CameraModel
from ..errors import (
    CorruptFileError,
    DataFileError,
    InvalidInputError,
    UnknownModelError,
    UnsupportedFormatError,
)
from ..results import Outcome, Termination

__all__ = [
    "MetashapeCalibration",
    "MetashapeExport",
    "read_metashape_xml",
    "write_metashape_xml",
    "read_metashape_calibration",
    "write_metashape_calibration",
]

_PARAMS = ("f", "cx", "cy", "b1", "b2", "k1", "k2", "k3", "k4", "p1", "p2")
_OTHER_NUMERIC = ("p3", "p4")  # higher-order tangential terms: must be zero
_IGNORED = ("date", "covariance", "residuals")


@dataclass(frozen=True)
class MetashapeCalibration:
    """A Metashape frame-camera calibration, in Metashape's own parameters and conventions.

    ``std`` maps parameter names to standard deviations (from ``<covariance>``), ``cov`` is the
    full covariance with ``cov_params`` naming its rows, when the file carried one.
    """

    width: int
    height: int
    f: float
    cx: float = 0.0
    cy: float = 0.0
    b1: float = 0.0
    b2: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    cov_params: tuple[str, ...] = ()
    cov: np.ndarray | None = field(default=None, compare=False)

    # -- model ---------------------------------------------------------------------------------
    def _distort(self, xn):
        x, y = xn[:, 0], xn[:, 1]
        r2 = x * x + y * y
        rad = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * (self.k3 + r2 * self.k4)))
        xd = x * rad + self.p1 * (r2 + 2 * x * x) + 2 * self.p2 * x * y
        yd = y * rad + self.p2 * (r2 + 2 * y * y) + 2 * self.p1 * x * y
        drad = self.k1 + r2 * (2 * self.k2 + r2 * (3 * self.k3 + 4 * self.k4 * r2))
        J = np.empty((len(x), 2, 2))
        J[:, 0, 0] = rad + 2 * x * x * drad + 6 * self.p1 * x + 2 * self.p2 * y
        J[:, 0, 1] = 2 * x * y * drad + 2 * self.p1 * y + 2 * self.p2 * x
        J[:, 1, 0] = 2 * x * y * drad + 2 * self.p2 * x + 2 * self.p1 * y
        J[:, 1, 1] = rad + 2 * y * y * drad + 6 * self.p2 * y + 2 * self.p1 * x
        return np.stack([xd, yd], axis=-1), J

    def project(self, points_cam) -> np.ndarray:
        """Pixels (N, 2) in thermogrammetry's convention ((0, 0) = centre of the top-left pixel)."""
        P = np.asarray(points_cam, dtype=np.float64)
        xd, _ = self._distort(P[:, :2] / P[:, 2:3])
        u = 0.5 * self.width + self.cx + xd[:, 0] * (self.f + self.b1) + xd[:, 1] * self.b2 - 0.5
        v = 0.5 * self.height + self.cy + xd[:, 1] * self.f - 0.5
        return np.stack([u, v], axis=-1)

    def unproject(self, xy_px) -> np.ndarray:
        """Rays (N, 3), z = 1, by Newton inversion of the distortion; NaN where it fails."""
        xy = np.asarray(xy_px, dtype=np.float64)
        yd = (xy[:, 1] + 0.5 - 0.5 * self.height - self.cy) / self.f
        xd = (xy[:, 0] + 0.5 - 0.5 * self.width - self.cx - yd * self.b2) / (self.f + self.b1)
        target = np.stack([xd, yd], axis=-1)
        xn = target.copy()
        for _ in range(60):
            F, J = self._distort(xn)
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            r = F - target
            step = np.stack([(J[:, 1, 1] * r[:, 0] - J[:, 0, 1] * r[:, 1]) / det,
                             (J[:, 0, 0] * r[:, 1] - J[:, 1, 0] * r[:, 0]) / det], axis=-1)
            xn = xn - step
            if np.all(~np.isfinite(step) | (np.abs(step) <= 1e-16 * (1 + np.abs(xn)))):
                break
        F, J = self._distort(xn)
        ok = np.max(np.abs(F - target), axis=1) <= 1e-12 * (1 + np.max(np.abs(target), axis=1))
        ok &= (J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]) > 0
        xn[~ok] = np.nan
        return np.column_stack([xn, np.ones(len(xn))])

    # -- conversion ----------------------------------------------------------------------------
    @property
    def exact_opencv(self) -> bool:
        """True when the calibration maps exactly onto the OpenCV model (K4 = 0)."""
        return self.k4 == 0.0

    def _opencv_params(self) -> dict[str, float]:
        return {"fx": self.f + self.b1, "fy": self.f, "skew": self.b2,
                "cx": 0.5 * self.width + self.cx - 0.5, "cy": 0.5 * self.height + self.cy - 0.5,
                "k1": self.k1, "k2": self.k2, "k3": self.k3,
                "p1": self.p2, "p2": self.p1}  # Metashape's P1/P2 are swapped relative to OpenCV

    def _opencv_std(self) -> dict[str, float] | None:
        """Standard deviations of the OpenCV parameters by linear propagation of ``cov``."""
        if self.cov is None or not self.cov_params:
            return None
        out_names = ("fx", "fy", "skew", "cx", "cy", "k1", "k2", "k3", "p1", "p2")
        # rows: opencv parameter as linear combination of metashape parameters
        combos = {"fx": {"f": 1.0, "b1": 1.0}, "fy": {"f": 1.0}, "skew": {"b2": 1.0}, "cx": {"cx": 1.0},
                  "cy": {"cy": 1.0}, "k1": {"k1": 1.0}, "k2": {"k2": 1.0}, "k3": {"k3": 1.0},
                  "p1": {"p2": 1.0}, "p2": {"p1": 1.0}}
        idx = {n: i for i, n in enumerate(self.cov_params)}
        std = {}
        for name in out_names:
            terms = combos[name]
            if not all(k in idx for k in terms):
                continue  # that Metashape parameter was fixed: no standard deviation
            a = np.zeros(len(self.cov_params))
            for k, c in terms.items():
                a[idx[k]] = c
            var = float(a @ self.cov @ a)
            std[name] = math.sqrt(max(var, 0.0))
        return std

    def to_camera(self, *, pixel_pitch_um=None, name: str = "", grid_step_px: float | None = None):
        """Convert to an ``opencv`` :class:`Camera`; returns a :class:`~thermogrammetry.camera.CameraConversion`.

        Exact (residual 0) when K4 = 0; otherwise fitted (k1..k6 rational, p1, p2, fx, fy, cx, cy,
        skew if B2 != 0) over the whole image, with the residual reported.
        """
        from ..camera.convert import CameraConversion, fit_camera, image_grid

        init = self._opencv_params()
        if self.exact_opencv:
            cam = Camera(CameraModel.OPENCV, (self.width, self.height), init, pixel_pitch_um=pixel_pitch_um,
                         param_std=self._opencv_std(), name=name)
            return CameraConversion(cam, 0.0, 0.0, 0, Outcome(Termination.CONVERGED, "exact mapping (K4 = 0)"),
                                    tuple(cam.param_names))
        grid = image_grid((self.width, self.height), grid_step_px)
        rays = self.unproject(grid)
        ok = np.all(np.isfinite(rays), axis=1)
        free = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"]
        if self.b2 != 0.0:
            free.append("skew")
        res = fit_camera(CameraModel.OPENCV, (self.width, self.height), rays[ok], grid[ok], init=init, free=free,
                         pixel_pitch_um=pixel_pitch_um, name=name)
        note = (f"K4 = {self.k4!r} has no OpenCV equivalent: fitted over {int(ok.sum())} grid points "
                f"(max residual {res.max_residual_px:.3g} px); standard deviations not transferred")
        return replace(res, outcome=Outcome(res.outcome.termination, f"{note}; {res.outcome.reason}"))

    @classmethod
    def from_camera(cls, camera: Camera, *, grid_step_px: float | None = None, area_px=None,
                    covariance: np.ndarray | None = None) -> "MetashapeExport":
        """Metashape calibration of ``camera``: exact for pinhole and OpenCV cameras without k4..k6,
        otherwise a least-squares fit of Metashape's forward model (f, cx, cy, b1, b2, k1-k4, p1, p2)
        over the whole image.

        ``area_px`` (M, 2): pixels the data covered; the residual over their convex hull is reported
        too. ``covariance`` (P, P) of ``camera.params``: propagated linearly to Metashape's parameters
        and carried in ``calibration.cov`` (written as ``<covariance>``)."""
        exp = cls._from_camera(camera, grid_step_px)
        if not exp.outcome.success:
            return exp
        from ..camera.convert import conversion_covariance, image_grid, inside_area

        if area_px is not None:
            grid = image_grid(camera.image_size, grid_step_px)
            rays = camera.unproject(grid)
            ok = np.all(np.isfinite(rays), axis=1) & inside_area(grid, area_px)
            if ok.any():
                d = np.linalg.norm(exp.calibration.project(rays[ok]) - grid[ok], axis=1)
                exp = replace(exp, area_max_residual_px=float(d.max()), area_rms_residual_px=float(np.sqrt(np.mean(d * d))))
        if covariance is not None:
            names = ["f", "cx", "cy", "b1", "k1", "k2", "k3", "k4", "p1", "p2"]
            if exp.calibration.b2 != 0.0:
                names.append("b2")
            theta = np.array([getattr(exp.calibration, n) for n in names])

            def proj(t, rays):
                return replace(exp.calibration, **{n: float(v) for n, v in zip(names, t)}).project(rays)

            try:
                C = conversion_covariance(camera, covariance, proj, theta, grid_step_px=grid_step_px)
                exp = replace(exp, calibration=replace(exp.calibration, cov_params=tuple(names), cov=C))
            except (np.linalg.LinAlgError, ValueError) as exc:  # reported, not fatal
                exp = replace(exp, outcome=Outcome(exp.outcome.termination,
                                                   f"{exp.outcome.reason}; covariance not propagated: {exc}"))
        return exp

    @classmethod
    def _from_camera(cls, camera: Camera, grid_step_px) -> "MetashapeExport":
        if not isinstance(camera, Camera):
            raise InvalidInputError(f"expected a Camera, got {type(camera).__name__}")
        w, h = camera.image_size
        p = camera.param_dict
        if camera.model is not CameraModel.PHOTOGRAMMETRIC:
            fx, fy, cx, cy = p["fx"], p["fy"], p["cx"], p["cy"]
            base = cls(w, h, f=fy, cx=cx + 0.5 - 0.5 * w, cy=cy + 0.5 - 0.5 * h, b1=fx - fy, b2=p.get("skew", 0.0),
                       k1=p.get("k1", 0.0), k2=p.get("k2", 0.0), k3=p.get("k3", 0.0),
                       p1=p.get("p2", 0.0), p2=p.get("p1", 0.0))
            if camera.model is CameraModel.PINHOLE or all(p[k] == 0.0 for k in ("k4", "k5", "k6")):
                return MetashapeExport(base, 0.0, 0.0, Outcome(Termination.CONVERGED, "exact mapping"))
        else:
            K = camera.K
            base = cls(w, h, f=K[1, 1], cx=K[0, 2] + 0.5 - 0.5 * w, cy=K[1, 2] + 0.5 - 0.5 * h,
                       b1=K[0, 0] - K[1, 1])
        return _fit_metashape(camera, base, grid_step_px)


@dataclass(frozen=True)
class MetashapeExport:
    """A Metashape calibration derived from a :class:`Camera`, with the fit residual (0 when exact)."""

    calibration: MetashapeCalibration
    max_residual_px: float
    rms_residual_px: float
    outcome: Outcome
    area_max_residual_px: float = float("nan")
    area_rms_residual_px: float = float("nan")

    def summary(self) -> dict:
        """Max/RMS residual over the whole frame and over the data area (None when unknown), outcome."""
        def f(v):
            v = float(v)
            return v if np.isfinite(v) else None

        return {"max_residual_px": f(self.max_residual_px), "rms_residual_px": f(self.rms_residual_px),
                "area_max_residual_px": f(self.area_max_residual_px), "area_rms_residual_px": f(self.area_rms_residual_px),
                "covariance": self.calibration.cov is not None,
                "termination": self.outcome.termination.value, "reason": self.outcome.reason}


def _fit_metashape(camera: Camera, base: MetashapeCalibration, grid_step_px) -> MetashapeExport:
    from scipy.optimize import least_squares

    from ..camera.convert import image_grid

    grid = image_grid(camera.image_size, grid_step_px)
    rays = camera.unproject(grid)
    ok = np.all(np.isfinite(rays), axis=1)
    rays, grid = rays[ok], grid[ok]
    names = ["f", "cx", "cy", "b1", "k1", "k2", "k3", "k4", "p1", "p2"]
    if camera.param_dict.get("skew", 0.0) != 0.0 or camera.param_dict.get("B2", 0.0) != 0.0:
        names.append("b2")

    def make(theta):
        return replace(base, **{n: float(v) for n, v in zip(names, theta)})

    def res(theta):
        return np.nan_to_num(make(theta).project(rays) - grid, nan=1e6).ravel()

    x0 = np.array([getattr(base, n) for n in names])
    sol = least_squares(res, x0, method="lm", x_scale="jac", ftol=1e-14, xtol=1e-14, gtol=1e-14,
                        max_nfev=200 * (len(names) + 1))
    calib = make(sol.x)
    d = np.linalg.norm(calib.project(rays) - grid, axis=1)
    term = Termination.CONVERGED if sol.status > 0 else Termination.MAX_ITERATIONS
    reason = (f"{camera.model.value} camera has no exact Metashape equivalent: Metashape's model fitted over "
              f"{len(grid)} grid points; {sol.message}")
    return MetashapeExport(calib, float(d.max()), float(np.sqrt(np.mean(d * d))), Outcome(term, reason))


# ------------------------------------------------------------------------------------------ XML
def _float(text, path, tag):
    try:
        v = float((text or "").strip())
    except ValueError:
        raise CorruptFileError(f"{path}: element <{tag}> is {text!r}; expected a number") from None
    if not math.isfinite(v):
        raise CorruptFileError(f"{path}: element <{tag}> is {text!r}; expected a finite number")
    return v


def read_metashape_xml(path) -> MetashapeCalibration:
    """Parse a Metashape calibration XML file into a :class:`MetashapeCalibration`.

    Unknown elements, non-numbers, a projection other than ``frame``, non-zero ``p3``/``p4`` and a
    malformed ``<covariance>`` are errors naming the file and the element.
    """
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except OSError as exc:
        raise DataFileError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    except ET.ParseError as exc:
        raise CorruptFileError(f"{path}: not well-formed XML ({exc})") from None
    if root.tag != "calibration":
        raise UnsupportedFormatError(f"{path}: root element is <{root.tag}>; expected <calibration> (Metashape calibration XML)")
    vals: dict[str, float] = {}
    legacy: dict[str, float] = {}
    projection = "frame"
    cov_params: tuple[str, ...] = ()
    cov = None
    for el in root:
        tag = el.tag
        if tag == "projection":
            projection = (el.text or "").strip()
        elif tag in ("width", "height"):
            v = _float(el.text, path, tag)
            if v != int(v) or v <= 0:
                raise CorruptFileError(f"{path}: element <{tag}> is {el.text!r}; expected a positive integer")
            vals[tag] = int(v)
        elif tag in _PARAMS:
            vals[tag] = _float(el.text, path, tag)
        elif tag in ("fx", "fy", "skew"):
            legacy[tag] = _float(el.text, path, tag)
        elif tag in _OTHER_NUMERIC:
            v = _float(el.text, path, tag)
            if v != 0.0:
                raise UnsupportedFormatError(
                    f"{path}: element <{tag}> = {v!r}: higher-order tangential terms are not supported; expected 0"
                )
        elif tag == "covariance":
            cov_params, cov = _read_covariance(el, path)
        elif tag in _IGNORED:
            continue
        else:
            raise UnsupportedFormatError(
                f"{path}: unknown element <{tag}>; expected projection, width, height, "
                f"{', '.join(_PARAMS)}, p3, p4, covariance, date (or legacy fx, fy, skew)"
            )
    if projection.lower() != "frame":
        raise UnknownModelError(f"{path}: <projection> is {projection!r}; only 'frame' cameras are supported")
    for tag in ("width", "height"):
        if tag not in vals:
            raise CorruptFileError(f"{path}: missing element <{tag}>")
    w, h = vals.pop("width"), vals.pop("height")
    if legacy:
        # PhotoScan < 1.3: fx, fy, absolute cx, cy, skew; P1/P2 in OpenCV's order (Agisoft Lens manual)
        for tag in ("fx", "fy", "cx", "cy"):
            if tag not in legacy and tag not in vals:
                raise CorruptFileError(f"{path}: legacy layout (with <fx>) is missing element <{tag}>")
        if "f" in vals:
            raise CorruptFileError(f"{path}: has both <f> and legacy <fx>/<fy>; expected one layout")
        fx, fy = legacy["fx"], legacy["fy"]
        return MetashapeCalibration(
            w, h, f=fy, cx=vals["cx"] - 0.5 * w, cy=vals["cy"] - 0.5 * h, b1=fx - fy, b2=legacy.get("skew", 0.0),
            k1=vals.get("k1", 0.0), k2=vals.get("k2", 0.0), k3=vals.get("k3", 0.0), k4=vals.get("k4", 0.0),
            p1=vals.get("p2", 0.0), p2=vals.get("p1", 0.0),
        )
    if "f" not in vals:
        raise CorruptFileError(f"{path}: missing element <f> (focal length in pixels)")
    if vals["f"] <= 0:
        raise CorruptFileError(f"{path}: element <f> is {vals['f']!r}; expected a positive focal length in pixels")
    return MetashapeCalibration(w, h, **vals, cov_params=cov_params, cov=cov)


def _read_covariance(el, path):
    p = el.find("params")
    c = el.find("coeffs")
    if p is None or c is None:
        raise CorruptFileError(f"{path}: <covariance> needs <params> and <coeffs>")
    names = tuple((p.text or "").split())
    bad = [n for n in names if n not in _PARAMS and n not in _OTHER_NUMERIC]
    if bad:
        raise CorruptFileError(f"{path}: <covariance><params> names unknown parameter(s) {', '.join(bad)}")
    try:
        coeffs = np.array((c.text or "").split(), dtype=np.float64)
    except ValueError:
        raise CorruptFileError(f"{path}: <covariance><coeffs> must be numbers") from None
    n = len(names)
    if coeffs.size != n * n:
        raise CorruptFileError(f"{path}: <covariance><coeffs> has {coeffs.size} values; expected {n}x{n} = {n * n}")
    return names, coeffs.reshape(n, n)


def write_metashape_xml(path, calib: MetashapeCalibration) -> Path:
    """Write a calibration in Metashape's current XML layout, atomically."""
    root = ET.Element("calibration")
    ET.SubElement(root, "projection").text = "frame"
    ET.SubElement(root, "width").text = str(int(calib.width))
    ET.SubElement(root, "height").text = str(int(calib.height))
    for tag in _PARAMS:
        ET.SubElement(root, tag).text = repr(float(getattr(calib, tag)))
    if calib.cov is not None and calib.cov_params:
        cov = ET.SubElement(root, "covariance")
        ET.SubElement(cov, "params").text = " ".join(calib.cov_params)
        ET.SubElement(cov, "coeffs").text = " ".join(repr(float(v)) for v in np.asarray(calib.cov).ravel())
    ET.SubElement(root, "date").text = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    ET.indent(root, space="  ")
    text = '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
    path = Path(path)
    write_atomic_text(path, text)
    return path


def read_metashape_calibration(path, *, pixel_pitch_um=None, grid_step_px: float | None = None):
    """Read a Metashape calibration XML as an ``opencv`` :class:`Camera`.

    Returns a :class:`~thermogrammetry.camera.CameraConversion`: ``.camera`` and the conversion
    residual (0 for K4 = 0; otherwise the max/RMS pixel residual of the fit over the whole image).
    Standard deviations from ``<covariance>`` are propagated for the exact case.
    """
    calib = read_metashape_xml(path)
    return calib.to_camera(pixel_pitch_um=pixel_pitch_um, name=Path(path).stem, grid_step_px=grid_step_px)


def write_metashape_calibration(path, camera: Camera, *, grid_step_px: float | None = None, area_px=None,
                                covariance: np.ndarray | None = None) -> MetashapeExport:
    """Write ``camera`` as a Metashape calibration XML; returns the calibration and its fit residual
    (see :meth:`MetashapeCalibration.from_camera` for ``area_px`` and ``covariance``)."""
    export = MetashapeCalibration.from_camera(camera, grid_step_px=grid_step_px, area_px=area_px, covariance=covariance)
    if not export.outcome.success:
        raise InvalidInputError(f"{path}: cannot express the camera in Metashape's model: {export.outcome.reason}")
    write_metashape_xml(path, export.calibration)
    return export
