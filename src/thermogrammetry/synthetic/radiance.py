"""Radiometric building blocks for the renderers: detector signal curves and directional emissivity.

The renderers mix radiation in a *signal* that is linear in radiance (never in temperature) and
convert to an apparent (blackbody-equivalent) temperature only at the end, exactly as a radiometric
camera does. A :class:`SignalCurve` is any object with ``signal(temperature_k)`` and
``temperature(signal)``; two are provided:

* :class:`BandPlanckCurve` — the exact Planck spectral radiance integrated over a spectral band
  (default 7.5–13.5 µm, LWIR microbolometer) by Gauss–Legendre quadrature, inverted by Newton's method;
  a fine lookup table (:meth:`BandPlanckCurve.table`) is used where speed matters.
* :class:`FlirCurve` — the closed-form FLIR calibration curve ``S(T) = R1 / (R2 (exp(B/T) - F))``
  (the curve of :mod:`thermogrammetry.radiometry.planck`; this local copy keeps the renderers usable
  without importing the radiometry package and is checked against it in the tests).

Directional emissivity: :func:`fresnel_emissivity` for a smooth dielectric (complex refractive index),
``ε(θ) = 1 − (|r_s|² + |r_p|²)/2``.

References
----------
.. [1] M. Planck (1901); constants from CODATA 2018 (h, c, k exact in the SI).
.. [2] M. Born, E. Wolf, *Principles of Optics*, 7th ed., §1.5 (Fresnel formulae), §14.2 (absorbing media).
.. [3] M. Vollmer, K.-P. Möllmann, *Infrared Thermal Imaging*, 2nd ed., Wiley-VCH 2018, §1.3–1.4
   (band radiance, directional emissivity of non-metals).
.. [4] ExifTool FLIR tags documentation, raw-to-temperature formula, https://exiftool.org/TagNames/FLIR.html
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

import numpy as np

from ..errors import InvalidInputError

__all__ = [
    "SignalCurve",
    "BandPlanckCurve",
    "FlirCurve",
    "CurveTable",
    "band_radiance",
    "band_temperature",
    "fresnel_emissivity",
    "mix_signal",
]

H_PLANCK = 6.62607015e-34  # J s (exact)
C_LIGHT = 299792458.0  # m/s (exact)
K_BOLTZMANN = 1.380649e-23  # J/K (exact)
C1L = 2.0 * H_PLANCK * C_LIGHT**2  # W m^2 sr^-1 (first radiation constant for radiance)
C2 = H_PLANCK * C_LIGHT / K_BOLTZMANN  # m K (second radiation constant)


class SignalCurve(Protocol):
    """Monotone map between blackbody temperature (K) and a radiance-linear signal."""

    def signal(self, temperature_k) -> np.ndarray: ...

    def temperature(self, signal) -> np.ndarray: ...


def _check_positive_t(t: np.ndarray, name: str = "temperature_k") -> None:
    with np.errstate(invalid="ignore"):
        bad = ~(t > 0)
    if np.any(bad):
        raise InvalidInputError(f"{name}: {int(bad.sum())} value(s) not > 0 K (first {t[bad].ravel()[0]!r}); expected kelvin")


#: temperatures per chunk of :class:`BandPlanckCurve`'s quadrature (its (chunk, nodes) temporaries stay in cache: an
#: image's signal 5x faster than in one pass, the same floats, since each value's sum over the nodes is unchanged)
_CHUNK = 4096


def _by_chunks(band, t: np.ndarray, *more: np.ndarray) -> np.ndarray:
    """``band`` (a function of 1-D arrays of temperatures and of ``more`` arrays of ``t``'s shape, one value per
    temperature) applied to ``t`` of any shape in chunks of :data:`_CHUNK`."""
    flat = t.reshape(-1)
    others = [np.broadcast_to(m, t.shape).reshape(-1) for m in more]
    out = np.empty(flat.shape, dtype=np.float64)
    for i in range(0, flat.size, _CHUNK):
        out[i : i + _CHUNK] = band(flat[i : i + _CHUNK], *(m[i : i + _CHUNK] for m in others))
    return out.reshape(t.shape) if t.ndim else out[0]


@dataclass(frozen=True)
class BandPlanckCurve:
    """Planck radiance integrated over ``band_um`` (W m⁻² sr⁻¹), flat spectral response.

    Parameters
    ----------
    band_um : (float, float)
        Spectral band in micrometres, default (7.5, 13.5).
    nodes : int
        Gauss–Legendre nodes (48 make the integral exact to ~1e-14 relative for smooth Planck curves).
    """

    band_um: tuple[float, float] = (7.5, 13.5)
    nodes: int = 48

    def __post_init__(self):
        lo, hi = (float(v) for v in self.band_um)
        if not (0 < lo < hi):
            raise InvalidInputError(f"band_um={self.band_um!r}: expected (low, high) micrometres with 0 < low < high")
        object.__setattr__(self, "band_um", (lo, hi))

    @cached_property
    def _quadrature(self) -> tuple[np.ndarray, np.ndarray]:
        x, w = np.polynomial.legendre.leggauss(int(self.nodes))
        lo, hi = (v * 1e-6 for v in self.band_um)
        lam = 0.5 * (hi - lo) * x + 0.5 * (hi + lo)
        return lam, 0.5 * (hi - lo) * w

    @cached_property
    def _weights(self) -> np.ndarray:
        """The quadrature's weights times C1L / λ⁵ (the factor of :meth:`signal`, :meth:`derivative` and the Newton
        steps of :meth:`temperature`, evaluated left to right as they were written)."""
        lam, w = self._quadrature
        return w * C1L / lam**5

    def signal(self, temperature_k) -> np.ndarray:
        """Band radiance in W m⁻² sr⁻¹ of a blackbody at ``temperature_k`` (any shape)."""
        t = np.asarray(temperature_k, dtype=np.float64)
        _check_positive_t(t)
        lam, k = self._quadrature[0], self._weights

        def band(tc):
            x = C2 / (lam * tc[:, None])
            return np.sum(k / np.expm1(x), axis=-1)

        return _by_chunks(band, t)

    def derivative(self, temperature_k) -> np.ndarray:
        """d(band radiance)/dT in W m⁻² sr⁻¹ K⁻¹."""
        t = np.asarray(temperature_k, dtype=np.float64)
        lam, k = self._quadrature[0], self._weights

        def band(tc):
            x = C2 / (lam * tc[:, None])
            ex = np.exp(x)
            return np.sum(k * ex * x / (tc[:, None] * (ex - 1.0) ** 2), axis=-1)

        return _by_chunks(band, t)

    @cached_property
    def _inverse_table(self) -> tuple[np.ndarray, np.ndarray]:
        t = np.arange(150.0, 1000.0 + 0.025, 0.05)
        return self.signal(t), t

    def temperature(self, signal, *, iterations: int = 2) -> np.ndarray:
        """Inverse of :meth:`signal`: table start (0.05 K grid, 150–1000 K) + Newton steps (NaN for signal <= 0).

        Two Newton steps from the table start are exact to < 1e-9 K inside the table range; values
        outside it start from a one-wavelength Wien estimate and get six more steps.
        """
        s = np.asarray(signal, dtype=np.float64)
        sig_tab, t_tab = self._inverse_table
        t = np.interp(s, sig_tab, t_tab)
        outside = (s < sig_tab[0]) | (s > sig_tab[-1])
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            if np.any(outside):
                lam_c = 0.5e-6 * sum(self.band_um)
                dlam = (self.band_um[1] - self.band_um[0]) * 1e-6
                wien = C2 / (lam_c * np.log1p(C1L * dlam / (lam_c**5 * s)))
                t = np.where(outside & np.isfinite(wien) & (wien > 0), wien, t)
            n_iter = iterations + (6 if np.any(outside) else 0)
            lam, k = self._quadrature[0], self._weights

            def newton(tc, sc):  # one Newton step on a chunk: signal and derivative from one x (values as theirs)
                x = C2 / (lam * tc[:, None])
                ex = np.exp(x)
                f = np.sum(k / np.expm1(x), axis=-1)
                d = np.sum(k * ex * x / (tc[:, None] * (ex - 1.0) ** 2), axis=-1)
                return tc - (f - sc) / d

            for _ in range(n_iter):
                t = np.asarray(t, np.float64)
                _check_positive_t(t)
                t = np.clip(_by_chunks(newton, t, s), 1.0, None)
        return np.where(s > 0, t, np.nan)

    def table(self, t_min_k: float = 180.0, t_max_k: float = 500.0, step_k: float = 0.01) -> "CurveTable":
        """A lookup table of this curve (fast, interpolation error < 1e-5 K at the default step)."""
        return CurveTable.from_curve(self, t_min_k, t_max_k, step_k)


@dataclass(frozen=True)
class FlirCurve:
    """Closed-form FLIR calibration curve ``S(T) = R1 / (R2 (exp(B/T) − F))`` (signal = raw + O).

    Defaults are plausible LWIR microbolometer constants (the values are not from any one camera).
    """

    r1: float = 17096.453
    r2: float = 0.046642166
    b: float = 1428.0
    f: float = 1.0
    o: float = -7340.0

    def signal(self, temperature_k) -> np.ndarray:
        t = np.asarray(temperature_k, dtype=np.float64)
        _check_positive_t(t)
        return self.r1 / (self.r2 * (np.exp(self.b / t) - self.f))

    def temperature(self, signal) -> np.ndarray:
        s = np.asarray(signal, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            arg = self.r1 / (self.r2 * s) + self.f
            t = self.b / np.log(arg)
        return np.where((s > 0) & (arg > 1.0), t, np.nan)

    @classmethod
    def from_planck_constants(cls, pc) -> "FlirCurve":
        """From a :class:`thermogrammetry.radiometry.planck.PlanckConstants` (attributes r1 r2 b f o)."""
        return cls(float(pc.r1), float(pc.r2), float(pc.b), float(pc.f), float(pc.o))


@dataclass(frozen=True)
class CurveTable:
    """Tabulated signal curve: ``signal``/``temperature`` by linear interpolation on a fine grid."""

    temperature_k: np.ndarray
    signal_values: np.ndarray

    @classmethod
    def from_curve(cls, curve: SignalCurve, t_min_k: float, t_max_k: float, step_k: float) -> "CurveTable":
        t = np.arange(float(t_min_k), float(t_max_k) + step_k, float(step_k))
        return cls(t, np.asarray(curve.signal(t), dtype=np.float64))

    def signal(self, temperature_k) -> np.ndarray:
        return np.interp(temperature_k, self.temperature_k, self.signal_values)

    def temperature(self, signal) -> np.ndarray:
        return np.interp(signal, self.signal_values, self.temperature_k)


_DEFAULT_BAND = BandPlanckCurve()


def band_radiance(temperature_k, band_um: tuple[float, float] = (7.5, 13.5)) -> np.ndarray:
    """Planck radiance of a blackbody integrated over ``band_um`` (W m⁻² sr⁻¹); any shape."""
    curve = _DEFAULT_BAND if tuple(band_um) == _DEFAULT_BAND.band_um else BandPlanckCurve(tuple(band_um))
    return curve.signal(temperature_k)


def band_temperature(radiance, band_um: tuple[float, float] = (7.5, 13.5)) -> np.ndarray:
    """Inverse of :func:`band_radiance`: blackbody-equivalent temperature in kelvin (NaN for radiance <= 0)."""
    curve = _DEFAULT_BAND if tuple(band_um) == _DEFAULT_BAND.band_um else BandPlanckCurve(tuple(band_um))
    return curve.temperature(radiance)


def fresnel_emissivity(theta_rad, n: complex = 1.5 + 0.0j) -> np.ndarray:
    """Directional emissivity of a smooth, opaque surface from the Fresnel equations.

    ``ε(θ) = 1 − (|r_s|² + |r_p|²) / 2`` (unpolarised), with ``r_s`` and ``r_p`` the amplitude reflection
    coefficients from air (index 1) into a medium of complex index ``m = n + ik`` (Born & Wolf §1.5, §14.2).

    Parameters
    ----------
    theta_rad : array_like, any shape
        Angle between the surface normal and the viewing direction, radians, in [0, π/2].
    n : complex
        Complex refractive index of the surface material in the band (e.g. 1.5 for glass-like paint,
        ``2.0 + 0.1j``...).

    Returns
    -------
    ndarray, same shape, float64, emissivity in [0, 1].
    """
    th = np.asarray(theta_rad, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        bad = ~((th >= 0) & (th <= np.pi / 2 + 1e-12))
    if np.any(bad):
        raise InvalidInputError(f"theta_rad: {int(bad.sum())} value(s) outside [0, pi/2] (first {th[bad].ravel()[0]!r})")
    m = complex(n)
    if m.real <= 0:
        raise InvalidInputError(f"n={n!r}: expected a refractive index with positive real part")
    cos_i = np.cos(th).astype(np.complex128)
    sin2 = np.sin(th) ** 2
    root = np.sqrt(m * m - sin2)
    rs = (cos_i - root) / (cos_i + root)
    rp = (m * m * cos_i - root) / (m * m * cos_i + root)
    return 1.0 - 0.5 * (np.abs(rs) ** 2 + np.abs(rp) ** 2)


def mix_signal(
    curve: SignalCurve,
    temperature_k,
    emissivity,
    reflected_k,
    *,
    transmission=1.0,
    atmosphere_k=None,
):
    """Signal at the sensor: ``τ (ε S(T) + (1 − ε) S(T_refl)) + (1 − τ) S(T_atm)``.

    All arguments broadcast. ``atmosphere_k`` is only needed when ``transmission`` < 1.
    This is the textbook measurement equation (Vollmer & Möllmann §2.3) without an IR window.
    """
    e = np.asarray(emissivity, dtype=np.float64)
    tau = np.asarray(transmission, dtype=np.float64)
    s = tau * (e * curve.signal(temperature_k) + (1.0 - e) * curve.signal(reflected_k))
    if np.any(tau < 1.0):
        if atmosphere_k is None:
            raise InvalidInputError("atmosphere_k: required when transmission < 1")
        s = s + (1.0 - tau) * curve.signal(atmosphere_k)
    return s
