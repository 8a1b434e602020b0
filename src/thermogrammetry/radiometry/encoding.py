"""Storing temperatures in files: 16-bit integer codes with an invertible linear mapping, or float32.

16-bit encoding: ``value = code * scale + offset`` (GDAL's convention for band scale/offset, so any GIS
that honours the GDAL metadata recovers kelvin or °C), code 0 reserved for no-data (NaN).  The mapping is
chosen from the data's range: the smallest step from :data:`NICE_STEPS` (0.001, 0.002, 0.005, 0.01 in the
output unit -- kelvin and °C steps are the same size) whose 65534 codes cover [min, max]; ranges wider
than 655 K at 0.01 K cannot keep the promised resolution and are refused (use float32).  The decoding error
is at most half a step (rounding), plus float32 representation error of the decoded value.

References
----------
.. [1] GDAL GTiff driver, "Metadata: Scale and offset" (``GDALMetadata`` TIFF tag 42112, items ``SCALE``,
   ``OFFSET`` with role ``scale``/``offset``), https://gdal.org/drivers/raster/gtiff.html
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..enums import StrChoice
from ..errors import InvalidInputError

__all__ = ["TemperatureUnit", "Encoding", "Uint16Mapping", "choose_uint16_mapping", "encode_uint16", "decode_uint16",
           "from_kelvin", "to_kelvin", "NICE_STEPS", "NODATA_CODE"]

NICE_STEPS = (0.001, 0.002, 0.005, 0.01)
NODATA_CODE = 0
_MAX_CODE = 65535


class TemperatureUnit(StrChoice):
    K = "K"
    C = "C"


class Encoding(StrChoice):
    FLOAT32 = "float32"
    UINT16 = "uint16"


def from_kelvin(temperature_k, unit) -> np.ndarray:
    """Kelvin -> the output unit (``"K"`` or ``"C"``), float64."""
    u = TemperatureUnit(unit)
    t = np.asarray(temperature_k, dtype=np.float64)
    return t - 273.15 if u is TemperatureUnit.C else t


def to_kelvin(values, unit) -> np.ndarray:
    """Values in ``unit`` -> kelvin, float64."""
    u = TemperatureUnit(unit)
    v = np.asarray(values, dtype=np.float64)
    return v + 273.15 if u is TemperatureUnit.C else v


@dataclass(frozen=True)
class Uint16Mapping:
    """``value = code * scale + offset`` in ``unit``; code :data:`NODATA_CODE` means no data."""

    scale: float
    offset: float
    unit: TemperatureUnit = TemperatureUnit.K

    @property
    def max_error(self) -> float:
        """Largest decoding error (half a step), in the unit (same in K and °C)."""
        return 0.5 * self.scale


def choose_uint16_mapping(temperature_k, unit="K", max_step: float = 0.01) -> Uint16Mapping:
    """Pick the finest step from :data:`NICE_STEPS` (<= ``max_step``) that covers the data's range.

    Parameters
    ----------
    temperature_k : array_like
        Temperatures in kelvin (NaN ignored).
    unit : "K" or "C"
        Unit the decoded values will be in.
    max_step : float
        Coarsest acceptable step (default 0.01).

    Raises
    ------
    InvalidInputError
        No finite value, or the range needs a step coarser than ``max_step``.
    """
    u = TemperatureUnit(unit)
    v = from_kelvin(temperature_k, u)
    finite = v[np.isfinite(v)]
    if finite.size == 0:
        raise InvalidInputError("cannot choose a 16-bit mapping: no finite temperature in the image")
    lo, hi = float(finite.min()), float(finite.max())
    for step in NICE_STEPS:
        if step > max_step + 1e-15:
            break
        offset = np.floor(lo / step) * step - step  # code 1 <= lo
        if (hi - offset) / step <= _MAX_CODE - 0.5:
            return Uint16Mapping(step, float(offset), u)
    raise InvalidInputError(
        f"temperature range {lo:.3f}..{hi:.3f} {u.value} ({hi - lo:.1f} wide) cannot be stored in 16 bits with a "
        f"step <= {max_step} {u.value}; use float32 encoding"
    )


def encode_uint16(temperature_k, mapping: Uint16Mapping) -> np.ndarray:
    """Kelvin -> uint16 codes (NaN -> :data:`NODATA_CODE`); values outside the mapping's range are refused."""
    v = from_kelvin(temperature_k, mapping.unit)
    code = np.rint((v - mapping.offset) / mapping.scale)
    fin = np.isfinite(code)
    with np.errstate(invalid="ignore"):
        bad = fin & ((code < 1) | (code > _MAX_CODE))
    if np.any(bad):
        raise InvalidInputError(
            f"{int(bad.sum())} temperature(s) outside the 16-bit mapping (scale {mapping.scale}, offset {mapping.offset} "
            f"{mapping.unit.value}); choose the mapping from these data"
        )
    out = np.full(code.shape, NODATA_CODE, dtype=np.uint16)
    out[fin] = code[fin].astype(np.uint16)
    return out


def decode_uint16(codes, mapping: Uint16Mapping) -> np.ndarray:
    """uint16 codes -> values in ``mapping.unit`` (float64; no-data -> NaN)."""
    c = np.asarray(codes)
    v = c.astype(np.float64) * mapping.scale + mapping.offset
    return np.where(c == NODATA_CODE, np.nan, v)
