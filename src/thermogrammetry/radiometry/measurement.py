"""The thermographic measurement equation (object, reflected, atmosphere, IR window) and its inversion.

All mixing happens in the radiance-proportional signal ``S = raw + O`` (see
:mod:`~thermogrammetry.radiometry.planck`).  With the path split at the IR window (FLIR's convention: the
window sits midway, each half of the object distance has transmission ``tau1 = tau2 = tau(d/2)``), window
transmission ``W``, window reflectance ``r_w`` (emissivity ``1 - W - r_w``) and object emissivity ``E``:

.. math::

    S_\\mathrm{meas} = E\\,\\tau_1 W \\tau_2\\, S(T_\\mathrm{obj})
      + (1-E)\\,\\tau_1 W \\tau_2\\, S(T_\\mathrm{refl})
      + (1-\\tau_1)\\, W \\tau_2\\, S(T_\\mathrm{atm})
      + (1-W-r_w)\\,\\tau_2\\, S(T_\\mathrm{win})
      + r_w\\,\\tau_2\\, S(T_\\mathrm{refl})
      + (1-\\tau_2)\\, S(T_\\mathrm{atm})

The weights sum to one, so the Planck offset ``O`` cancels whether one mixes raw counts or signals.  With
``W = 1`` (no window) this reduces to the textbook ``S = E tau S_obj + (1-E) tau S_refl + (1-tau) S_atm``
with ``tau = tau1 tau2``.  Every parameter may be a scalar (per image) or an array broadcastable to the image
(per pixel: emissivity map, distance map, ...).

References
----------
.. [1] ExifTool FLIR tags documentation, raw-to-temperature formula, https://exiftool.org/TagNames/FLIR.html
.. [2] G. J. Tattersall, Thermimage R package v4.1.3, ``raw2temp``.
.. [3] M. Vollmer, K.-P. Möllmann, *Infrared Thermal Imaging*, 2nd ed., Wiley-VCH 2018, sec. 2.3.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from ..errors import ConfigError, InvalidInputError
from .atmosphere import AtmosphericCoefficients, atmospheric_transmission
from .planck import PlanckConstants, signal_from_temperature, temperature_from_signal

__all__ = [
    "MeasurementParams",
    "measurement_weights",
    "raw_from_object_temperature",
    "object_temperature_from_raw",
]

ArrayLike = Any


@dataclass(frozen=True)
class MeasurementParams:
    """Parameters of the measurement equation; each may be a scalar or a per-pixel array.

    Attributes
    ----------
    emissivity : float or array
        Object emissivity in (0, 1].
    reflected_temperature_k : float or array
        Reflected apparent temperature (kelvin).
    atmospheric_temperature_k : float or array
        Air temperature along the path (kelvin).
    relative_humidity : float or array
        Fraction in [0, 1].
    distance_m : float or array
        Object distance in metres (>= 0).
    window_temperature_k : float or array
        IR window temperature (kelvin); irrelevant when ``window_transmission`` is 1.
    window_transmission : float
        IR window transmission in (0, 1].
    window_reflectance : float
        IR window reflectance in [0, 1 - window_transmission].
    coefficients : AtmosphericCoefficients
        alpha1, alpha2, beta1, beta2, X.
    """

    emissivity: ArrayLike = 1.0
    reflected_temperature_k: ArrayLike = 293.15
    atmospheric_temperature_k: ArrayLike = 293.15
    relative_humidity: ArrayLike = 0.5
    distance_m: ArrayLike = 1.0
    window_temperature_k: ArrayLike = 293.15
    window_transmission: float = 1.0
    window_reflectance: float = 0.0
    coefficients: AtmosphericCoefficients = AtmosphericCoefficients()

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))

    def override(self, **changes) -> "MeasurementParams":
        """Return a copy with the named parameters replaced; ``None`` values are ignored, unknown names refused."""
        names = set(self.field_names())
        unknown = sorted(k for k in changes if k not in names)
        if unknown:
            raise ConfigError(f"unknown measurement parameter(s) {unknown}; valid: {sorted(names)}")
        return replace(self, **{k: v for k, v in changes.items() if v is not None})

    def validate(self) -> None:
        """Raise :class:`InvalidInputError` naming the first out-of-range parameter."""
        def arr(x):
            return np.asarray(x, dtype=np.float64)

        # NaN in a per-pixel map means "no data here" and propagates to a NaN temperature
        e = arr(self.emissivity)
        with np.errstate(invalid="ignore"):
            if np.any((e <= 0) | (e > 1) | np.isinf(e)):
                raise InvalidInputError(f"emissivity: values must be in (0, 1], got min {np.nanmin(e)!r} max {np.nanmax(e)!r}")
            for name in ("reflected_temperature_k", "atmospheric_temperature_k", "window_temperature_k"):
                a = arr(getattr(self, name))
                if np.any((a <= 0) | np.isinf(a)):
                    raise InvalidInputError(f"{name}: expected kelvin > 0, got min {np.nanmin(a)!r}")
            w = float(self.window_transmission)
            r = float(self.window_reflectance)
            if not (0 < w <= 1) or not (0 <= r <= 1 - w + 1e-12):
                raise InvalidInputError(
                    f"window_transmission={w!r}, window_reflectance={r!r}: expected 0 < W <= 1 and 0 <= r <= 1 - W"
                )


def measurement_weights(params: MeasurementParams) -> dict[str, np.ndarray]:
    """Weights of each source in the measured signal (they sum to 1).

    Returns
    -------
    dict with keys ``object``, ``reflected``, ``atmosphere``, ``window`` and ``tau1``, ``tau2``
    (arrays broadcast from the parameters).
    """
    params.validate()
    d = np.asarray(params.distance_m, dtype=np.float64)
    tau = atmospheric_transmission(d / 2.0, params.atmospheric_temperature_k, params.relative_humidity, params.coefficients)
    if np.any(tau <= 0):  # NaN (pixels without a distance) propagates instead
        dmax = float(np.nanmax(d))
        raise InvalidInputError(
            f"atmospheric transmission <= 0 (min {float(np.nanmin(tau)):.3g}) for distance up to {dmax:g} m at "
            f"{float(np.nanmax(np.asarray(params.atmospheric_temperature_k))) - 273.15:.1f} °C and humidity "
            f"{float(np.nanmax(np.asarray(params.relative_humidity))):.2f}: outside the valid range of FLIR's empirical "
            "atmosphere model (a few hundred metres); shorten the distance or use a radiative-transfer model"
        )
    tau1 = tau2 = tau
    e = np.asarray(params.emissivity, dtype=np.float64)
    w = float(params.window_transmission)
    r = float(params.window_reflectance)
    return {
        "object": e * tau1 * w * tau2,
        "reflected": (1 - e) * tau1 * w * tau2 + r * tau2,
        "atmosphere": (1 - tau1) * w * tau2 + (1 - tau2),
        "window": (1 - w - r) * tau2,
        "tau1": tau1,
        "tau2": tau2,
    }


def _background_signal(params: MeasurementParams, planck: PlanckConstants, wts: dict) -> np.ndarray:
    s_refl = signal_from_temperature(params.reflected_temperature_k, planck)
    s_atm = signal_from_temperature(params.atmospheric_temperature_k, planck)
    bg = wts["reflected"] * s_refl + wts["atmosphere"] * s_atm
    if float(params.window_transmission) < 1.0 or float(params.window_reflectance) > 0.0:
        bg = bg + wts["window"] * signal_from_temperature(params.window_temperature_k, planck)
    return bg


def raw_from_object_temperature(object_temperature_k, planck: PlanckConstants, params: MeasurementParams) -> np.ndarray:
    """Forward model: raw counts the camera records for an object at ``object_temperature_k``.

    Parameters
    ----------
    object_temperature_k : array_like (H, W) or any shape
        True object surface temperature in kelvin.
    planck : PlanckConstants
    params : MeasurementParams
        Scalars or arrays broadcastable to ``object_temperature_k``.

    Returns
    -------
    ndarray, float64 raw counts (not rounded to integers).
    """
    wts = measurement_weights(params)
    s = wts["object"] * signal_from_temperature(object_temperature_k, planck) + _background_signal(params, planck, wts)
    return s - planck.o


def object_temperature_from_raw(raw_counts, planck: PlanckConstants, params: MeasurementParams) -> np.ndarray:
    """Invert the measurement equation: object temperature (kelvin) from raw counts.

    Parameters
    ----------
    raw_counts : array_like (H, W) or any shape
        Raw sensor counts.
    planck : PlanckConstants
    params : MeasurementParams
        Scalars or per-pixel arrays (emissivity map, distance map, ...) broadcastable to ``raw_counts``.

    Returns
    -------
    ndarray, float64, kelvin.  Pixels whose object signal comes out <= 0 (the background model exceeds the
    measurement: very low emissivity with a hot reflected temperature) are NaN.
    """
    wts = measurement_weights(params)
    s_meas = np.asarray(raw_counts, dtype=np.float64) + planck.o
    s_obj = (s_meas - _background_signal(params, planck, wts)) / wts["object"]
    return temperature_from_signal(s_obj, planck)
