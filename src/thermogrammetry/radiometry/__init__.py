"""Radiometry: raw counts <-> radiance <-> temperature, atmosphere, emissivity, angle corrections, encodings.

Pure, vectorised numpy functions; parameters may be scalars (per image) or arrays (per pixel).
Temperatures are kelvin; relative humidity is a fraction; distances are metres; angles radians.

Modules: :mod:`.planck` (FLIR calibration), :mod:`.atmosphere` (transmission), :mod:`.measurement`
(measurement equation and its inversion), :mod:`.directional` (seed 000 eq. 7-8, Fresnel emissivity),
:mod:`.encoding` (16-bit scale/offset, units).
"""

from __future__ import annotations

from .atmosphere import AtmosphericCoefficients, atmospheric_transmission, water_vapour_content
from .directional import (
    DEFAULT_MAX_ANGLE_DEG,
    CosineEmissivity,
    FresnelEmissivity,
    TabulatedEmissivity,
    check_angles,
    corrected_temperature,
    corrected_temperature_from_apparent,
    flux_correction_eq7,
    fresnel_emissivity,
    raw_for_directional,
    temperature_correction_eq8,
)
from .encoding import (
    Encoding,
    TemperatureUnit,
    Uint16Mapping,
    choose_uint16_mapping,
    decode_uint16,
    encode_uint16,
    from_kelvin,
    to_kelvin,
)
from .measurement import MeasurementParams, measurement_weights, object_temperature_from_raw, raw_from_object_temperature
from .planck import (
    PlanckConstants,
    SignalModel,
    StefanBoltzmann,
    raw_from_signal,
    raw_from_temperature,
    signal_from_raw,
    signal_from_temperature,
    temperature_from_raw,
    temperature_from_signal,
)

__all__ = [
    "AtmosphericCoefficients", "atmospheric_transmission", "water_vapour_content",
    "DEFAULT_MAX_ANGLE_DEG", "CosineEmissivity", "FresnelEmissivity", "corrected_temperature_from_apparent", "TabulatedEmissivity", "check_angles", "corrected_temperature",
    "flux_correction_eq7", "fresnel_emissivity", "raw_for_directional", "temperature_correction_eq8",
    "Encoding", "TemperatureUnit", "Uint16Mapping", "choose_uint16_mapping", "decode_uint16", "encode_uint16",
    "from_kelvin", "to_kelvin",
    "MeasurementParams", "measurement_weights", "object_temperature_from_raw", "raw_from_object_temperature",
    "PlanckConstants", "SignalModel", "StefanBoltzmann", "raw_from_signal", "raw_from_temperature", "signal_from_raw", "signal_from_temperature",
    "temperature_from_raw", "temperature_from_signal",
]
