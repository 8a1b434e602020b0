"""INTERIM stand-ins for radiometry functions that had not landed when this package was written.

Replace with ``thermogrammetry.radiometry`` equivalents when they exist (listed in the close-range
engineer's report): :func:`fresnel_emissivity` (directional emissivity of a dielectric) and
:func:`atmospheric_transmission` (FLIR two-term model, same formula as radiometry.atmosphere).
"""

from __future__ import annotations

import numpy as np

__all__ = ["fresnel_emissivity", "atmospheric_transmission"]


def fresnel_emissivity(theta, n: float) -> np.ndarray:
    """Directional emissivity of a smooth non-absorbing dielectric of refractive index ``n``.

    ε(θ) = 1 − (R_s + R_p)/2 with the Fresnel reflectances (Vollmer & Möllmann 2018, eq. 1.38–1.41).
    """
    th = np.asarray(theta, float)
    ci = np.cos(th)
    st = np.sin(th) / n
    ct = np.sqrt(np.clip(1 - st**2, 0, None))
    rs = ((ci - n * ct) / (ci + n * ct)) ** 2
    rp = ((ct - n * ci) / (ct + n * ci)) ** 2
    return 1.0 - 0.5 * (rs + rp)


def atmospheric_transmission(distance_m, air_temperature_k, relative_humidity):
    """FLIR's empirical two-term transmission (default coefficients); 1 at zero distance."""
    a1, a2, b1, b2, x = 0.006569, 0.012620, -0.002276, -0.006670, 1.9
    t = np.asarray(air_temperature_k, float) - 273.15
    hh = np.asarray(relative_humidity, float) * np.exp(1.5587 + 0.06939 * t - 0.00027816 * t**2 + 0.00000068455 * t**3)
    sd = np.sqrt(np.asarray(distance_m, float))
    sh = np.sqrt(hh)
    return x * np.exp(-sd * (a1 + b1 * sh)) + (1 - x) * np.exp(-sd * (a2 + b2 * sh))
