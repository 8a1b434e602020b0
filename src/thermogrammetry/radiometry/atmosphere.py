"""Atmospheric transmission over a path: FLIR's empirical two-term model.

.. math::

    h = \\mathrm{RH}\\,\\exp(1.5587 + 0.06939\\,t - 0.00027816\\,t^2 + 0.00000068455\\,t^3)
    \\quad (t = T_\\mathrm{air} - 273.15\\ ^\\circ\\mathrm{C},\\ \\mathrm{RH}\\in[0, 1])

    \\tau(d) = X \\exp\\!\\big(-\\sqrt{d}\\,(\\alpha_1 + \\beta_1 \\sqrt{h})\\big)
             + (1 - X) \\exp\\!\\big(-\\sqrt{d}\\,(\\alpha_2 + \\beta_2 \\sqrt{h})\\big)

``h`` is FLIR's water-vapour content parameter (the cubic is a fit of saturation vapour content versus air
temperature); ``d`` is the path length in metres.  ``tau(0) = X + (1 - X) = 1`` exactly.

Valid range.  The coefficients are FLIR's fit for the 7.5--14 um band at ground level; FLIR documents the
model for distances up to a few hundred metres and air temperatures of about -40 to +60 degC.  Outside that
range the function still evaluates but the numbers are extrapolations; :func:`atmospheric_transmission`
refuses negative distances and humidities outside [0, 1].

References
----------
.. [1] ExifTool FLIR tags documentation, "AtmosphericTransAlpha1/2, Beta1/2, X" and the raw-to-temperature
   formula, https://exiftool.org/TagNames/FLIR.html
.. [2] G. J. Tattersall, Thermimage R package v4.1.3, ``raw2temp`` (atmospheric transmission block).
.. [3] M. Vollmer, K.-P. Möllmann, *Infrared Thermal Imaging*, 2nd ed., Wiley-VCH 2018, sec. 2.5 / 3.2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError

__all__ = ["AtmosphericCoefficients", "water_vapour_content", "atmospheric_transmission"]


@dataclass(frozen=True)
class AtmosphericCoefficients:
    """FLIR's atmospheric transmission coefficients (``AtmosphericTransAlpha1`` ... ``X``).

    Defaults are the values FLIR writes in most cameras' CameraInfo record (and Thermimage's defaults).
    """

    alpha1: float = 0.006569
    alpha2: float = 0.012620
    beta1: float = -0.002276
    beta2: float = -0.006670
    x: float = 1.9

    def __post_init__(self) -> None:
        for name in ("alpha1", "alpha2", "beta1", "beta2", "x"):
            v = float(getattr(self, name))
            if not np.isfinite(v):
                raise InvalidInputError(f"AtmosphericCoefficients.{name}={v!r}: expected a finite number")
            object.__setattr__(self, name, v)


def _nonneg(a, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        bad = (arr < 0) | np.isinf(arr)
    if np.any(bad):
        first = arr[bad].ravel()[0]
        raise InvalidInputError(f"{name}: {int(np.sum(bad))} value(s) negative or infinite (first {first!r}); expected >= 0 "
                                "(NaN marks pixels without a distance)")
    return arr


def water_vapour_content(air_temperature_k, relative_humidity) -> np.ndarray:
    """FLIR's water-vapour parameter ``h`` (dimensionless fit value, grows with humidity and temperature).

    Parameters
    ----------
    air_temperature_k : array_like
        Air temperature in kelvin.
    relative_humidity : array_like
        Relative humidity as a fraction in [0, 1] (50 % -> 0.5).

    Returns
    -------
    ndarray, broadcast shape, float64
    """
    rh = np.asarray(relative_humidity, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        bad = ~((rh >= 0) & (rh <= 1))
    if np.any(bad):
        first = rh[bad].ravel()[0]
        raise InvalidInputError(
            f"relative_humidity: {int(np.sum(bad))} value(s) outside [0, 1] (first {first!r}); "
            "give humidity as a fraction (50 % -> 0.5)"
        )
    t = np.asarray(air_temperature_k, dtype=np.float64) - 273.15
    return rh * np.exp(1.5587 + 0.06939 * t - 0.00027816 * t**2 + 0.00000068455 * t**3)


def atmospheric_transmission(
    distance_m,
    air_temperature_k,
    relative_humidity,
    coefficients: AtmosphericCoefficients | None = None,
) -> np.ndarray:
    """Transmission ``tau`` of an atmospheric path of length ``distance_m`` (FLIR model, module docstring).

    Parameters
    ----------
    distance_m : array_like
        Path length in metres (>= 0); a per-pixel distance map works (broadcasting); NaN (no surface) gives NaN.
    air_temperature_k : array_like
        Air temperature in kelvin.
    relative_humidity : array_like
        Fraction in [0, 1].
    coefficients : AtmosphericCoefficients, optional
        The camera's alpha1, alpha2, beta1, beta2, X; FLIR defaults when omitted.

    Returns
    -------
    ndarray, broadcast shape, float64
        Transmission, 1 at zero distance.
    """
    c = coefficients or AtmosphericCoefficients()
    d = _nonneg(distance_m, "distance_m")
    sqrt_h = np.sqrt(water_vapour_content(air_temperature_k, relative_humidity))
    sd = np.sqrt(d)
    return c.x * np.exp(-sd * (c.alpha1 + c.beta1 * sqrt_h)) + (1.0 - c.x) * np.exp(-sd * (c.alpha2 + c.beta2 * sqrt_h))
