"""What a thermal sensor does to the radiance field: optics blur, vignetting, noise, quantisation to K.

All effects act on a *signal* image (linear in radiance, see :mod:`.radiance`) except the noises, which
are specified the way data sheets state them — in kelvin (NETD for the temporal noise, a fixed-pattern
standard deviation) — and are added to the apparent-temperature image.

Order (as in a real camera): PSF blur (signal) → vignetting (signal) → signal-to-temperature →
fixed-pattern noise (K) → temporal noise (K).

References
----------
.. [1] M. Vollmer, K.-P. Möllmann, *Infrared Thermal Imaging*, 2nd ed., Wiley-VCH 2018, §2.4–2.5
   (NETD, fixed-pattern noise and non-uniformity correction of microbolometer arrays).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import lru_cache

import numpy as np

from ..errors import ConfigError, InvalidInputError
from .._validate import config_keys

__all__ = ["SensorEffects", "apply_sensor_effects", "vignetting_factor", "fixed_pattern"]


@dataclass(frozen=True)
class SensorEffects:
    """Sensor degradations; all zero means an ideal, noise-free, blur-free sensor.

    Attributes
    ----------
    psf_sigma_px : float
        Standard deviation of the Gaussian optics PSF in pixels (0 = none).
    netd_k : float
        Temporal noise, standard deviation in kelvin (NETD), drawn per image from its ``seed``.
    fpn_k : float
        Fixed-pattern noise, standard deviation in kelvin: half of its variance in column stripes, half per
        pixel; fixed for a sensor (drawn from ``fpn_seed``), the same in every image of that sensor.
    vignetting : float
        Relative signal fall-off at the image corner, quadratic in the radius from the image centre
        (0 = none, 0.05 = corners receive 5 % less signal).
    fpn_seed : int
        Seed of the fixed pattern (a property of the sensor, not of the image).
    """

    psf_sigma_px: float = 0.0
    netd_k: float = 0.0
    fpn_k: float = 0.0
    vignetting: float = 0.0
    fpn_seed: int = 0

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "fpn_seed":
                if not isinstance(v, (int, np.integer)) or v < 0:
                    raise ConfigError(f"SensorEffects.fpn_seed={v!r}: expected a non-negative integer")
                continue
            try:
                fv = float(v)
            except (TypeError, ValueError):
                raise ConfigError(f"SensorEffects.{f.name}={v!r}: expected a number") from None
            if not np.isfinite(fv) or fv < 0:
                raise ConfigError(f"SensorEffects.{f.name}={v!r}: expected a finite number >= 0")
            object.__setattr__(self, f.name, fv)
        if self.vignetting >= 1.0:
            raise ConfigError(f"SensorEffects.vignetting={self.vignetting!r}: expected a fraction in [0, 1)")

    @classmethod
    def from_dict(cls, d: dict) -> "SensorEffects":
        return cls(**config_keys(cls, d))


def vignetting_factor(image_size: tuple[int, int], vignetting: float) -> np.ndarray:
    """(H, W) multiplicative signal factor ``1 − v (r / r_corner)²`` about the image centre ((w−1)/2, (h−1)/2)."""
    w, h = (int(v) for v in image_size)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    r2 = ((x - cx) ** 2 + (y - cy) ** 2) / max(cx**2 + cy**2, 1e-12)
    return 1.0 - float(vignetting) * r2


def fixed_pattern(image_size: tuple[int, int], fpn_k: float, fpn_seed: int) -> np.ndarray:
    """(H, W) fixed-pattern offset in kelvin: column stripes + per-pixel offsets, total std ``fpn_k``."""
    return float(fpn_k) * _unit_pattern(tuple(int(v) for v in image_size), int(fpn_seed))


@lru_cache(maxsize=8)
def _unit_pattern(image_size: tuple[int, int], fpn_seed: int) -> np.ndarray:
    w, h = image_size
    rng = np.random.default_rng([int(fpn_seed), w, h, 0xF9])
    cols = rng.standard_normal(w)
    pix = rng.standard_normal((h, w))
    out = np.sqrt(0.5) * (cols[None, :] + pix)
    out.flags.writeable = False
    return out


def apply_sensor_effects(signal, curve, effects: SensorEffects, rng: np.random.Generator | None) -> np.ndarray:
    """Turn a per-pixel signal image into the apparent-temperature image a camera records.

    Parameters
    ----------
    signal : ndarray (H, W)
        Pixel-integrated, radiance-linear signal (units of ``curve``).
    curve : SignalCurve
        Converts signal to blackbody-equivalent temperature.
    effects : SensorEffects
    rng : numpy Generator or None
        Source of the temporal noise (required when ``effects.netd_k`` > 0).

    Returns
    -------
    ndarray (H, W) float32, apparent temperature in kelvin.
    """
    s = np.asarray(signal, dtype=np.float64)
    if s.ndim != 2:
        raise InvalidInputError(f"signal: expected an (H, W) image, got shape {s.shape}")
    if effects.psf_sigma_px > 0:
        from scipy.ndimage import gaussian_filter

        s = gaussian_filter(s, effects.psf_sigma_px, mode="nearest", truncate=4.0)
    h, w = s.shape
    if effects.vignetting > 0:
        s = s * vignetting_factor((w, h), effects.vignetting)
    t = np.asarray(curve.temperature(s), dtype=np.float64)
    if effects.fpn_k > 0:
        t = t + fixed_pattern((w, h), effects.fpn_k, effects.fpn_seed)
    if effects.netd_k > 0:
        if rng is None:
            raise InvalidInputError("rng: a seeded generator is required when netd_k > 0")
        t = t + effects.netd_k * rng.standard_normal(t.shape)
    return t.astype(np.float32)
