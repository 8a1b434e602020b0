"""Raw counts <-> radiance-proportional signal <-> temperature (the FLIR Planck calibration).

A radiometric thermal camera reports ``raw_counts`` that are an affine function of the in-band radiance
reaching the detector.  FLIR (and the FLIR cores inside DJI XT2/XTR) store the calibration as five
constants ``R1, R2, B, F, O``:

.. math::

    S(T) = \\frac{R_1}{R_2\\,(\\exp(B/T) - F)}, \\qquad \\mathrm{raw} = S(T) - O,
    \\qquad T = \\frac{B}{\\ln\\!\\left(\\frac{R_1}{R_2\\,(\\mathrm{raw} + O)} + F\\right)}

with ``T`` in kelvin.  ``S`` (called *signal* here) is proportional to the in-band blackbody radiance; all
radiative mixing (object, reflected, atmosphere, window) is linear in ``S`` -- see
:mod:`thermogrammetry.radiometry.measurement`.  Raw counts are never presented as temperatures: the
functions here are the only way between the two.

References
----------
.. [1] ExifTool FLIR tags documentation (P. Harvey), "FLIR tags -- raw to temperature conversion",
   https://exiftool.org/TagNames/FLIR.html
.. [2] G. J. Tattersall, "Thermimage: thermal image analysis", R package v4.1.3, function ``raw2temp``
   (2017--2023), https://github.com/gtatters/Thermimage
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError

__all__ = [
    "PlanckConstants",
    "StefanBoltzmann",
    "SignalModel",
    "signal_from_temperature",
    "temperature_from_signal",
    "raw_from_temperature",
    "temperature_from_raw",
    "signal_from_raw",
    "raw_from_signal",
]


@dataclass(frozen=True)
class PlanckConstants:
    """FLIR calibration constants of one camera/lens/range (from the file's CameraInfo record).

    Attributes
    ----------
    r1, r2, b, f, o : float
        ``PlanckR1`` (counts-like), ``PlanckR2`` (1/counts-like), ``PlanckB`` (kelvin), ``PlanckF``
        (unitless, usually 1), ``PlanckO`` (counts, the raw offset).
    """

    r1: float
    r2: float
    b: float
    f: float = 1.0
    o: float = 0.0

    def __post_init__(self) -> None:
        for name in ("r1", "r2", "b", "f", "o"):
            v = getattr(self, name)
            try:
                fv = float(v)
            except (TypeError, ValueError):
                raise InvalidInputError(f"PlanckConstants.{name}={v!r}: expected a number") from None
            if not np.isfinite(fv):
                raise InvalidInputError(f"PlanckConstants.{name}={v!r}: expected a finite number")
            object.__setattr__(self, name, fv)
        if self.r1 <= 0 or self.r2 <= 0 or self.b <= 0:
            raise InvalidInputError(
                f"PlanckConstants r1={self.r1}, r2={self.r2}, b={self.b}: all three must be > 0"
            )

    def as_dict(self) -> dict[str, float]:
        return {"r1": self.r1, "r2": self.r2, "b": self.b, "f": self.f, "o": self.o}


@dataclass(frozen=True)
class StefanBoltzmann:
    """Broadband (total radiation) signal model ``S(T) = sigma T^4`` in W m^-2, ``O = 0``.

    The model behind seed 000 eq. 8 (total exitance of a blackbody).  Usable wherever a
    :class:`PlanckConstants` is accepted, for cameras without a band calibration or for synthetic work;
    for a real long-wave camera the band-limited :class:`PlanckConstants` is the better model.
    """

    o: float = 0.0
    sigma: float = 5.670374419e-8  # W m^-2 K^-4 (CODATA 2018, exact by SI definition)


SignalModel = PlanckConstants | StefanBoltzmann


def _check_temperature(t: np.ndarray, name: str = "temperature_k") -> None:
    with np.errstate(invalid="ignore"):
        bad = np.asarray(t) <= 0  # NaN passes (no-data pixels stay NaN)
    if np.any(bad):
        first = np.asarray(t)[bad].ravel()[0]
        raise InvalidInputError(f"{name}: {int(np.sum(bad))} value(s) <= 0 K (first {first!r}); expected kelvin > 0")


def signal_from_temperature(temperature_k, planck: PlanckConstants) -> np.ndarray:
    """Radiance-proportional signal ``S(T) = R1 / (R2 (exp(B/T) - F))`` of a blackbody at ``T``.

    Parameters
    ----------
    temperature_k : array_like, any shape
        Blackbody temperature in kelvin (> 0).
    planck : PlanckConstants or StefanBoltzmann

    Returns
    -------
    ndarray, same shape, float64
        Signal in count units (``raw + O``), or W m^-2 for :class:`StefanBoltzmann`.
    """
    t = np.asarray(temperature_k, dtype=np.float64)
    _check_temperature(t)
    if isinstance(planck, StefanBoltzmann):
        return planck.sigma * t**4
    return planck.r1 / (planck.r2 * (np.exp(planck.b / t) - planck.f))


def temperature_from_signal(signal, planck: PlanckConstants) -> np.ndarray:
    """Inverse of :func:`signal_from_temperature`: ``T = B / ln(R1 / (R2 S) + F)`` in kelvin.

    Signals at or below zero (or so low that the logarithm's argument is <= 1) have no blackbody
    temperature; they map to NaN instead of raising, because they occur per pixel (dead pixels,
    over-corrected atmosphere) and the caller decides what to do with them.

    Parameters
    ----------
    signal : array_like, any shape
        Radiance-proportional signal in count units (``raw + O``).
    planck : PlanckConstants

    Returns
    -------
    ndarray, same shape, float64, kelvin (NaN where undefined).
    """
    s = np.asarray(signal, dtype=np.float64)
    if isinstance(planck, StefanBoltzmann):
        with np.errstate(invalid="ignore"):
            return np.where(s > 0, np.abs(s / planck.sigma) ** 0.25, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        arg = planck.r1 / (planck.r2 * s) + planck.f
        t = planck.b / np.log(arg)
    ok = (s > 0) & (arg > 1.0) & np.isfinite(t)
    return np.where(ok, t, np.nan)


def raw_from_temperature(temperature_k, planck: PlanckConstants) -> np.ndarray:
    """Raw counts a blackbody at ``temperature_k`` produces: ``S(T) - O`` (float64, not rounded)."""
    return signal_from_temperature(temperature_k, planck) - planck.o


def temperature_from_raw(raw_counts, planck: PlanckConstants) -> np.ndarray:
    """Blackbody (apparent, emissivity 1, no atmosphere) temperature in kelvin of raw counts."""
    return temperature_from_signal(signal_from_raw(raw_counts, planck), planck)


def signal_from_raw(raw_counts, planck: PlanckConstants) -> np.ndarray:
    """``S = raw + O`` (float64)."""
    return np.asarray(raw_counts, dtype=np.float64) + planck.o


def raw_from_signal(signal, planck: PlanckConstants) -> np.ndarray:
    """``raw = S - O`` (float64)."""
    return np.asarray(signal, dtype=np.float64) - planck.o
