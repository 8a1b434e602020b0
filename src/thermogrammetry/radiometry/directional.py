"""Viewing-angle corrections: seed 000 eq. 7-8 and directional emissivity (Fresnel, user table).

Seed 000 (Sawicki, Stein, Więcek) corrects the flux a camera sees from a surface viewed at angle ``eta``
between the surface normal and the camera axis (eq. 7), and for a blackbody the temperature (eq. 8):

.. math::

    \\Phi = \\frac{\\Phi_0}{\\cos\\eta} \\qquad (7)
    \\qquad\\qquad
    T = \\left(\\frac{T_0^4 - T_a^4}{\\cos\\varphi} + T_a^4\\right)^{1/4} \\qquad (8)

with ``T0`` the temperature measured by the camera and ``Ta`` the ambient temperature (kelvin).

A physically based alternative is the directional emissivity of a smooth dielectric from Fresnel's
equations, ``eps(theta) = 1 - (R_s + R_p) / 2``, which is nearly constant up to ~40-50° and falls towards
0 at grazing incidence; the corrected temperature then comes from the measurement equation with
``emissivity = eps(theta)`` per pixel (:func:`corrected_temperature`).

Valid range.  Both corrections diverge or become meaningless at grazing angles: ``1 / cos`` amplifies
noise by 2 at 60°, 3.9 at 75° and 5.8 at 80°, and within a pixel footprint at grazing view roughness and
curvature dominate the Fresnel model.  Functions here refuse angles above ``max_angle_deg`` (default
:data:`DEFAULT_MAX_ANGLE_DEG` = 75°, adjustable up to 89°) with an :class:`InvalidInputError` that names the
number of offending pixels and the largest angle.

References
----------
.. [1] P. Sawicki, R. Stein, B. Więcek, "Directional emissivity correction by photogrammetric 3D object
   reconstruction", seed 000, eqs. 6-8.
.. [2] M. Born, E. Wolf, *Principles of Optics*, 7th ed., sec. 1.5 (Fresnel formulae).
.. [3] M. Vollmer, K.-P. Möllmann, *Infrared Thermal Imaging*, 2nd ed., sec. 1.4.5 (directional emissivity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError, ShapeError
from .measurement import MeasurementParams, object_temperature_from_raw
from .planck import PlanckConstants, SignalModel, signal_from_temperature

__all__ = [
    "DEFAULT_MAX_ANGLE_DEG",
    "check_angles",
    "flux_correction_eq7",
    "temperature_correction_eq8",
    "fresnel_emissivity",
    "TabulatedEmissivity",
    "FresnelEmissivity",
    "CosineEmissivity",
    "corrected_temperature_from_apparent",
    "corrected_temperature",
    "raw_for_directional",
]

#: default largest viewing angle (degrees from the surface normal) the corrections accept
DEFAULT_MAX_ANGLE_DEG = 75.0
_ABS_MAX_ANGLE_DEG = 89.0


def check_angles(angle_rad, max_angle_deg: float = DEFAULT_MAX_ANGLE_DEG, name: str = "angle_rad") -> np.ndarray:
    """Validate viewing angles (radians, from the surface normal): NaN allowed (no surface), in
    [0, max_angle_deg].  Returns the float64 array."""
    if not (0.0 < float(max_angle_deg) <= _ABS_MAX_ANGLE_DEG):
        raise InvalidInputError(f"max_angle_deg={max_angle_deg!r}: expected a value in (0, {_ABS_MAX_ANGLE_DEG}] degrees")
    a = np.asarray(angle_rad, dtype=np.float64)
    lim = np.deg2rad(max_angle_deg)
    with np.errstate(invalid="ignore"):
        neg = a < 0
        over = a > lim
    if np.any(neg):
        raise InvalidInputError(f"{name}: {int(neg.sum())} negative angle(s) (min {np.nanmin(a)!r} rad); expected angles from the normal in [0, pi/2)")
    if np.any(over):
        worst = float(np.rad2deg(np.nanmax(a)))
        raise InvalidInputError(
            f"{name}: {int(over.sum())} pixel(s) viewed beyond {max_angle_deg:g}° from the surface normal "
            f"(largest {worst:.2f}°); the angle correction is not valid at grazing angles "
            f"(1/cos amplifies errors {1/np.cos(np.deg2rad(min(worst, 89.99))):.1f}x). Mask those pixels "
            "(NaN) or raise max_angle_deg deliberately"
        )
    return a


def flux_correction_eq7(flux, angle_rad, *, max_angle_deg: float = DEFAULT_MAX_ANGLE_DEG) -> np.ndarray:
    """Seed 000 eq. 7: flux normal to the surface ``Phi = Phi0 / cos(eta)``.

    Parameters
    ----------
    flux : array_like
        Measured flux ``Phi0`` (any radiometric unit; the result has the same).
    angle_rad : array_like, broadcastable
        Angle ``eta`` between surface normal and viewing direction (radians).

    Returns
    -------
    ndarray, broadcast shape, float64.
    """
    a = check_angles(angle_rad, max_angle_deg)
    return np.asarray(flux, dtype=np.float64) / np.cos(a)


def temperature_correction_eq8(measured_k, ambient_k, angle_rad, *, max_angle_deg: float = DEFAULT_MAX_ANGLE_DEG) -> np.ndarray:
    """Seed 000 eq. 8: ``T = ((T0^4 - Ta^4) / cos(phi) + Ta^4)^(1/4)`` (blackbody, total radiation).

    Parameters
    ----------
    measured_k : array_like
        Temperature ``T0`` measured by the camera (kelvin).
    ambient_k : array_like
        Ambient temperature ``Ta`` (kelvin).
    angle_rad : array_like
        Viewing angle ``phi`` from the surface normal (radians), per pixel or scalar.

    Returns
    -------
    ndarray, broadcast shape, float64 kelvin.  NaN where the bracket is negative (object much colder than
    ambient at a large angle: no real solution).
    """
    a = check_angles(angle_rad, max_angle_deg)
    t0 = np.asarray(measured_k, dtype=np.float64)
    ta = np.asarray(ambient_k, dtype=np.float64)
    if np.any(t0 <= 0) or np.any(ta <= 0):
        raise InvalidInputError("measured_k and ambient_k must be kelvin > 0")
    inner = (t0**4 - ta**4) / np.cos(a) + ta**4
    with np.errstate(invalid="ignore"):
        return np.where(inner > 0, np.abs(inner) ** 0.25, np.nan)


def fresnel_emissivity(angle_rad, refractive_index, extinction: float = 0.0) -> np.ndarray:
    """Directional emissivity ``1 - (R_s + R_p)/2`` of a smooth, opaque surface (Kirchhoff).

    Parameters
    ----------
    angle_rad : array_like
        Emission angle from the surface normal (radians, [0, pi/2]).
    refractive_index : float
        Real part ``n`` of the complex index (e.g. ~1.5 for glass/paint binders in 8-14 um; see literature).
    extinction : float
        Imaginary part ``k`` (0 for a dielectric).

    Returns
    -------
    ndarray, float64 in [0, 1].
    """
    n = complex(float(refractive_index), float(extinction))
    if n.real <= 0:
        raise InvalidInputError(f"refractive_index={refractive_index!r}: expected > 0")
    th = np.asarray(angle_rad, dtype=np.float64)
    if np.any(th < 0) or np.any(th > np.pi / 2 + 1e-12):
        raise InvalidInputError("angle_rad: expected angles in [0, pi/2]")
    c = np.cos(th).astype(np.complex128)
    s2 = np.sin(th) ** 2
    ct = np.sqrt(1.0 - s2 / n**2)
    rs = (c - n * ct) / (c + n * ct)
    rp = (n * c - ct) / (n * c + ct)
    return 1.0 - 0.5 * (np.abs(rs) ** 2 + np.abs(rp) ** 2)


@dataclass(frozen=True)
class FresnelEmissivity:
    """Directional emissivity model of a dielectric: ``eps(theta)`` from Fresnel, optionally rescaled so
    that ``eps(0) = normal_emissivity`` (rough real surfaces have lower normal emissivity than the ideal
    smooth value; the angular shape is kept)."""

    refractive_index: float
    extinction: float = 0.0
    normal_emissivity: float | None = None

    def __call__(self, angle_rad) -> np.ndarray:
        eps = fresnel_emissivity(angle_rad, self.refractive_index, self.extinction)
        if self.normal_emissivity is not None:
            eps = eps * (float(self.normal_emissivity) / float(fresnel_emissivity(0.0, self.refractive_index, self.extinction)))
        return eps


@dataclass(frozen=True)
class CosineEmissivity:
    """``eps(theta) = normal_emissivity * cos(theta)`` -- the Lambertian law implicit in seed 000 eq. 8.

    With this law, a reflected/ambient temperature ``Ta``, no atmosphere and the Stefan-Boltzmann signal,
    the measurement equation ``S0 = eps S(T) + (1 - eps) S(Ta)`` inverts to exactly eq. 8; the tests check it.
    """

    normal_emissivity: float = 1.0

    def __call__(self, angle_rad) -> np.ndarray:
        return float(self.normal_emissivity) * np.cos(np.asarray(angle_rad, dtype=np.float64))


@dataclass(frozen=True)
class TabulatedEmissivity:
    """User table of directional emissivity: angles (degrees, increasing) and emissivities; linear
    interpolation; angles outside the table are refused (no extrapolation)."""

    angles_deg: tuple[float, ...]
    emissivities: tuple[float, ...]

    def __post_init__(self) -> None:
        a = np.asarray(self.angles_deg, dtype=np.float64)
        e = np.asarray(self.emissivities, dtype=np.float64)
        if a.ndim != 1 or a.shape != e.shape or a.size < 2:
            raise ShapeError(f"emissivity table: need two 1-D sequences of equal length >= 2, got {a.shape} and {e.shape}")
        if np.any(np.diff(a) <= 0):
            raise InvalidInputError(f"emissivity table angles {a.tolist()}: must increase strictly")
        if np.any(~((e > 0) & (e <= 1))):
            raise InvalidInputError(f"emissivity table values {e.tolist()}: must be in (0, 1]")

    def __call__(self, angle_rad) -> np.ndarray:
        deg = np.rad2deg(np.asarray(angle_rad, dtype=np.float64))
        lo, hi = self.angles_deg[0], self.angles_deg[-1]
        with np.errstate(invalid="ignore"):
            out = (deg < lo - 1e-9) | (deg > hi + 1e-9)
        if np.any(out):
            raise InvalidInputError(
                f"angles {np.nanmin(deg):.2f}..{np.nanmax(deg):.2f}° outside the emissivity table's range {lo:g}..{hi:g}°"
            )
        return np.interp(deg, self.angles_deg, self.emissivities)


def corrected_temperature(
    raw_counts,
    planck: PlanckConstants,
    params: MeasurementParams,
    angle_rad,
    emissivity_model,
    *,
    distance_m=None,
    max_angle_deg: float = DEFAULT_MAX_ANGLE_DEG,
) -> np.ndarray:
    """Object temperature (K) per pixel with directional emissivity and per-pixel path length.

    Inverts the measurement equation (:func:`~.measurement.object_temperature_from_raw`) with
    ``emissivity = emissivity_model(angle)`` and ``distance_m`` (a per-pixel distance map) replacing the
    image's scalars.

    Parameters
    ----------
    raw_counts : array_like (H, W)
    planck : PlanckConstants
    params : MeasurementParams
        Reflected/atmospheric temperatures, humidity, window; its emissivity and distance are replaced.
    angle_rad : array_like (H, W) or scalar
        Viewing angle from the surface normal; NaN where no surface is known (result NaN).
    emissivity_model : callable
        ``eps(angle_rad) -> array``, e.g. :class:`FresnelEmissivity` or :class:`TabulatedEmissivity`.
    distance_m : array_like (H, W) or scalar, optional
        Camera-to-surface distance; defaults to ``params.distance_m``.

    Returns
    -------
    ndarray (H, W) float64 kelvin.
    """
    a = check_angles(angle_rad, max_angle_deg)
    nan = np.isnan(a)
    eps = emissivity_model(np.where(nan, 0.0, a))
    eps = np.where(nan, 1.0, eps)
    p = params.override(emissivity=eps, distance_m=params.distance_m if distance_m is None else distance_m)
    t = object_temperature_from_raw(raw_counts, planck, p)
    return np.where(nan, np.nan, t)


def raw_for_directional(temperature_k, planck, params, angle_rad, emissivity_model, *, distance_m=None,
                        max_angle_deg: float = DEFAULT_MAX_ANGLE_DEG) -> np.ndarray:
    """Forward model matching :func:`corrected_temperature` (for synthetic images): raw counts of a surface
    at ``temperature_k`` seen at ``angle_rad`` over ``distance_m``."""
    from .measurement import raw_from_object_temperature

    a = check_angles(angle_rad, max_angle_deg)
    p = params.override(emissivity=emissivity_model(a), distance_m=params.distance_m if distance_m is None else distance_m)
    return raw_from_object_temperature(temperature_k, planck, p)



def corrected_temperature_from_apparent(
    apparent_temperature_k,
    angle_rad,
    emissivity_model,
    *,
    signal_model: SignalModel,
    params: MeasurementParams,
    distance_m=None,
    max_angle_deg: float = DEFAULT_MAX_ANGLE_DEG,
) -> np.ndarray:
    """Like :func:`corrected_temperature`, from *apparent* (blackbody-equivalent) temperatures.

    Use this when only a temperature image is available (a camera set to emissivity 1 and no atmosphere,
    a converted TIFF): the apparent temperature is mapped back to the signal with ``signal_model`` (the
    camera's :class:`~.planck.PlanckConstants`, or :class:`~.planck.StefanBoltzmann` for total radiation)
    and the measurement equation is inverted with ``emissivity_model(angle)`` and ``distance_m``.

    Parameters
    ----------
    apparent_temperature_k : array_like (H, W)
    angle_rad : array_like (H, W) or scalar
        Viewing angle from the surface normal (NaN: no surface -> NaN).
    emissivity_model : callable ``eps(angle_rad)``
    signal_model : PlanckConstants or StefanBoltzmann
    params : MeasurementParams
        Reflected/atmospheric temperature, humidity, window; emissivity and distance are replaced.
    distance_m : array_like, optional

    Returns
    -------
    ndarray (H, W) float64 kelvin.
    """
    raw = signal_from_temperature(apparent_temperature_k, signal_model) - signal_model.o
    return corrected_temperature(raw, signal_model, params, angle_rad, emissivity_model,
                                 distance_m=distance_m, max_angle_deg=max_angle_deg)
