"""Empirical raw-count -> temperature mapping from in-scene references (for cameras without a documented one).

DJI publishes no conversion of its R-JPEG raw counts to temperature.  When the scene holds surfaces of known
temperature (a contact-probed roof, a water body with a logged temperature, a blackbody panel), their mean
raw counts and temperatures fix a linear mapping ``T_K = a * counts + b`` over the imaged range -- the usual
"in-scene calibration" of thermal surveys.  It is *empirical*: valid near the references' temperatures,
for the same camera, gain mode and atmospheric path; files written with it say so in their metadata.

Fit: weighted least squares with ``σ_i² = σ_ref,i² + (a · SEM_i)²`` (stated reference uncertainty and the
standard error of the region's mean count; two passes so ``a`` is known).  The covariance of ``(a, b)`` is
``(AᵀWA)⁻¹``; with redundancy (n >= 3 references) it is scaled by the a-posteriori variance factor
``s0² = rᵀWr / (n - 2)``, which also checks the linear model against the references.  With exactly two
references there is no check; the σ is the propagated a-priori one, or undetermined (NaN) when the
references carry no uncertainty and are single pixels.

References file (CSV, ``--references``): one row per reference, columns
``image`` (file name as given to convert), either ``x,y`` (pixel, column/row from the top-left pixel's
centre, optional ``radius_px``: disc of pixels) or ``polygon`` (``"x1 y1; x2 y2; x3 y3; ..."``; the pixels
whose centres are inside are used, left/top edges inclusive, right/bottom exclusive), ``temperature_c`` or ``temperature_k``, optional ``sigma_k``.

References
----------
.. [1] Kelly, J., Kljun, N., Olsson, P.-O., et al. (2019). Challenges and best practices for deriving
   temperature data from an uncalibrated UAV thermal infrared camera. Remote Sensing 11(5), 567 (in-scene
   reference targets and a linear empirical line).
.. [2] Smith, G. M., Milton, E. J. (1999). The use of the empirical line method to calibrate remotely sensed
   data to reflectance. Int. J. Remote Sensing 20(13), 2653-2662.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import CorruptFileError, DataFileError, InvalidInputError, TooFewPointsError

__all__ = ["Reference", "EmpiricalMapping", "read_references_csv", "region_mask", "fit_empirical_mapping"]


@dataclass(frozen=True)
class Reference:
    """One in-scene reference: ``image`` name, pixel region, known temperature (K) and its σ (K)."""

    image: str
    temperature_k: float
    sigma_k: float = 0.0
    xy: tuple[float, float] | None = None
    radius_px: float = 0.0
    polygon: tuple[tuple[float, float], ...] | None = None
    row: int = 0  # line in the CSV, for messages


@dataclass
class EmpiricalMapping:
    """``T_K = a * counts + b`` fitted to references (see module docstring).

    Attributes
    ----------
    a, b : float
        Slope (K per count) and intercept (K).
    cov : ndarray (2, 2)
        Covariance of (a, b).
    n, dof : int
        Number of references, redundancy (n - 2).
    s0 : float or None
        A-posteriori σ of unit weight (None without redundancy).
    residuals_k : ndarray (n,)
        Reference temperature minus fitted temperature (K).
    counts_range : (float, float)
        Smallest and largest reference mean count: the mapping is an interpolation inside it.
    """

    a: float
    b: float
    cov: np.ndarray
    n: int
    dof: int
    s0: float | None
    residuals_k: np.ndarray
    counts_range: tuple[float, float]
    source: str = ""
    notes: list[str] = field(default_factory=list)

    def temperature_k(self, counts) -> np.ndarray:
        """Temperatures (K, float64) of ``counts``."""
        return self.a * np.asarray(counts, dtype=np.float64) + self.b

    def sigma_k(self, counts) -> np.ndarray:
        """σ (K) of the mapped temperature at ``counts``: sqrt([c 1] Σ [c 1]ᵀ)."""
        c = np.asarray(counts, dtype=np.float64)
        v = self.cov[0, 0] * c * c + 2 * self.cov[0, 1] * c + self.cov[1, 1]
        return np.sqrt(np.maximum(v, 0.0))

    def metadata(self) -> dict[str, str]:
        """Items for the output files' GDAL metadata (stating that the temperatures are empirical)."""
        mid = 0.5 * (self.counts_range[0] + self.counts_range[1])
        sig = float(self.sigma_k(mid))
        return {
            "THERMOGRAMMETRY_TEMPERATURE_SOURCE": "empirical: in-scene reference calibration (linear T_K = a*counts + b), "
                                                  "not a manufacturer calibration",
            "THERMOGRAMMETRY_EMPIRICAL_A_K_PER_COUNT": f"{self.a:.9g}",
            "THERMOGRAMMETRY_EMPIRICAL_B_K": f"{self.b:.9g}",
            "THERMOGRAMMETRY_EMPIRICAL_COV_AB": " ".join(f"{v:.6g}" for v in self.cov.ravel()),
            "THERMOGRAMMETRY_EMPIRICAL_SIGMA_K": "undetermined" if not math.isfinite(sig) else f"{sig:.4g}",
            "THERMOGRAMMETRY_EMPIRICAL_REFERENCES": f"{self.n} (redundancy {self.dof})",
            "THERMOGRAMMETRY_EMPIRICAL_VALID_COUNTS": f"{self.counts_range[0]:.1f}..{self.counts_range[1]:.1f}",
            "THERMOGRAMMETRY_EMPIRICAL_SOURCE": self.source,
        }

    def describe(self) -> str:
        mid = 0.5 * (self.counts_range[0] + self.counts_range[1])
        sig = float(self.sigma_k(mid))
        s = "σ undetermined" if not math.isfinite(sig) else f"σ {sig:.3g} K at mid-range"
        res = "" if self.dof == 0 else f", RMS residual {float(np.sqrt(np.mean(self.residuals_k ** 2))):.3g} K"
        return (f"empirical mapping T = {self.a:.6g} K/count * counts + {self.b:.6g} K from {self.n} references "
                f"(redundancy {self.dof}{res}), {s}")


def _num(text: str, what: str, where: str) -> float:
    try:
        v = float(str(text).strip())
    except ValueError:
        raise CorruptFileError(f"{where}: {what} {text!r} is not a number") from None
    if not math.isfinite(v):
        raise CorruptFileError(f"{where}: {what} {text!r} is not a finite number")
    return v


def read_references_csv(path: str | Path) -> list[Reference]:
    """Parse a references CSV (columns in the module docstring).

    Raises
    ------
    DataFileError / CorruptFileError
        Unreadable file, missing columns, non-numeric or non-finite values (naming file, line and value).
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise DataFileError(f"references file {p}: cannot be read ({exc.strerror or exc})") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise CorruptFileError(f"references file {p}: not UTF-8 text (byte {exc.start}); save it as UTF-8 CSV") from None
    try:
        rows = list(csv.reader(io.StringIO(text, newline="")))
    except csv.Error as exc:
        raise CorruptFileError(f"references file {p}: not a readable CSV ({exc})") from None
    rows = [r for r in rows if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")]
    if not rows:
        raise CorruptFileError(f"references file {p}: empty; expected a header image,x,y|polygon,temperature_c|temperature_k")
    head = [h.strip().lower() for h in rows[0]]
    col = {h: i for i, h in enumerate(head)}
    tcol = "temperature_c" if "temperature_c" in col else ("temperature_k" if "temperature_k" in col else None)
    if "image" not in col or tcol is None or not ({"x", "y"} <= set(col) or "polygon" in col):
        raise CorruptFileError(
            f"references file {p}: header {rows[0]} lacks columns; expected image, x and y (or polygon), and "
            "temperature_c or temperature_k (optional sigma_k, radius_px)")
    out = []
    for line, r in enumerate(rows[1:], start=2):
        where = f"references file {p}, line {line}"

        def cell(name):
            i = col.get(name)
            return r[i].strip() if i is not None and i < len(r) else ""

        img = cell("image")
        if not img:
            raise CorruptFileError(f"{where}: empty image name")
        t = _num(cell(tcol), tcol, where)
        tk = t + 273.15 if tcol == "temperature_c" else t
        if tk <= 0:
            raise CorruptFileError(f"{where}: {tcol} {cell(tcol)!r} is below absolute zero")
        sig = _num(cell("sigma_k"), "sigma_k", where) if cell("sigma_k") else 0.0
        if sig < 0:
            raise CorruptFileError(f"{where}: sigma_k {sig} is negative")
        if cell("polygon"):
            pts = []
            for pair in cell("polygon").replace(",", ";").split(";"):
                if not pair.strip():
                    continue
                xy = pair.split()
                if len(xy) != 2:
                    raise CorruptFileError(f"{where}: polygon vertex {pair.strip()!r}: expected 'x y'")
                pts.append((_num(xy[0], "polygon x", where), _num(xy[1], "polygon y", where)))
            if len(pts) < 3:
                raise CorruptFileError(f"{where}: polygon has {len(pts)} vertices, expected >= 3")
            out.append(Reference(img, tk, sig, polygon=tuple(pts), row=line))
        else:
            x, y = _num(cell("x"), "x", where), _num(cell("y"), "y", where)
            rad = _num(cell("radius_px"), "radius_px", where) if cell("radius_px") else 0.0
            if rad < 0:
                raise CorruptFileError(f"{where}: radius_px {rad} is negative")
            out.append(Reference(img, tk, sig, xy=(x, y), radius_px=rad, row=line))
    if not out:
        raise CorruptFileError(f"references file {p}: no reference rows after the header")
    return out


def region_mask(ref: Reference, shape: tuple[int, int]) -> np.ndarray:
    """Boolean (H, W) mask of the pixels a reference covers (pixel centres at integer x, y)."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    if ref.polygon is not None:
        poly = np.asarray(ref.polygon, dtype=np.float64)
        inside = np.zeros((h, w), dtype=bool)
        x0, y0 = poly[-1]
        for x1, y1 in poly:  # even-odd rule, crossing test on horizontal rays
            cond = (y1 > yy) != (y0 > yy)
            with np.errstate(divide="ignore", invalid="ignore"):
                xc = (x0 - x1) * (yy - y1) / (y0 - y1) + x1
            inside ^= cond & (xx < xc)
            x0, y0 = x1, y1
        return inside
    x, y = ref.xy  # type: ignore[misc]
    return (xx - x) ** 2 + (yy - y) ** 2 <= max(ref.radius_px, 0.5) ** 2


def fit_empirical_mapping(refs: list[Reference], counts_by_image: dict[str, np.ndarray], source: str = "") -> EmpiricalMapping:
    """Fit ``T_K = a * counts + b`` to the references (module docstring).

    Parameters
    ----------
    refs : list of Reference
    counts_by_image : dict name -> (H, W) raw counts
        The referenced images' raw counts.

    Raises
    ------
    TooFewPointsError
        Fewer than two references, or all at the same mean count.
    InvalidInputError
        A reference names an image not given, or covers no pixel of it.
    """
    if len(refs) < 2:
        raise TooFewPointsError(f"{source}: {len(refs)} reference(s); an empirical mapping needs >= 2 at different temperatures")
    means, sems, temps, sig_ref = [], [], [], []
    for r in refs:
        where = f"{source}, line {r.row}" if source else f"reference line {r.row}"
        if r.image not in counts_by_image:
            raise InvalidInputError(f"{where}: image {r.image!r} is not among the inputs with raw counts "
                                    f"({', '.join(sorted(counts_by_image)) or 'none'})")
        c = counts_by_image[r.image]
        m = region_mask(r, c.shape)
        if not m.any():
            raise InvalidInputError(f"{where}: the region covers no pixel of {r.image} ({c.shape[1]}x{c.shape[0]})")
        v = c[m].astype(np.float64)
        means.append(float(v.mean()))
        sems.append(float(v.std(ddof=1) / math.sqrt(v.size)) if v.size > 1 else 0.0)
        temps.append(r.temperature_k)
        sig_ref.append(r.sigma_k)
    c, t = np.array(means), np.array(temps)
    if np.ptp(c) <= 0:
        raise TooFewPointsError(f"{source}: all references have the same mean count {c[0]:.1f}; need different temperatures")
    A = np.column_stack([c, np.ones_like(c)])
    a = float(np.polyfit(c, t, 1)[0])
    if a <= 0:
        order = np.argsort(t)
        raise InvalidInputError(
            f"{source}: the references give temperature falling with raw counts (slope {a:.4g} K/count; "
            + ", ".join(f"line {refs[i].row}: {t[i]:.2f} K at {c[i]:.1f} counts" for i in order)
            + "); a thermal sensor's counts rise with temperature -- check the image, pixel and temperature columns")
    var = np.array(sig_ref) ** 2 + (a * np.array(sems)) ** 2
    n, dof = len(refs), len(refs) - 2
    have_prior = bool(np.all(var > 0))
    wts = 1.0 / var if have_prior else np.ones_like(c)
    N = A.T @ (A * wts[:, None])
    ab = np.linalg.solve(N, A.T @ (wts * t))
    res = t - A @ ab
    Ninv = np.linalg.inv(N)
    notes = []
    s0 = None
    if dof >= 1:
        s0 = float(np.sqrt(res @ (wts * res) / dof))
        cov = Ninv * s0 ** 2 if not have_prior else Ninv * max(s0 ** 2, 1.0)
        notes.append(f"σ from the references' residuals (redundancy {dof})")
    elif have_prior:
        cov = Ninv
        notes.append("σ propagated from the references' stated σ and pixel noise; 2 references give no check of the fit")
    else:
        cov = np.full((2, 2), np.nan)
        notes.append("σ undetermined: 2 references without sigma_k and single pixels; add sigma_k or a third reference")
    return EmpiricalMapping(float(ab[0]), float(ab[1]), cov, n, dof, s0, res, (float(c.min()), float(c.max())),
                            source=str(source), notes=notes)
