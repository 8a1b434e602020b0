"""Radiometrically exact rendering of a flat surface (temperature, directional emissivity, distance).

Each sub-pixel sample's ray is intersected with the plane; the viewing angle θ (between the surface
normal and the direction back to the camera) and the distance d give the signal at the sensor

    S = τ(d) · [ ε(θ) S(T) + (1 − ε(θ)) S(T_refl) ] + (1 − τ(d)) S(T_atm)

(the measurement equation without an IR window, Vollmer & Möllmann §2.3), averaged over the samples in
signal, then converted to apparent (blackbody-equivalent) temperature by the same curve. With
``curve = FlirCurve.from_planck_constants(pc)`` and ``transmission = lambda d: τ_FLIR(d/2)²`` this is
exactly :func:`thermogrammetry.radiometry.raw_for_directional` followed by
:func:`~thermogrammetry.radiometry.temperature_from_raw` (tested to 0.01 K).

References
----------
.. [1] M. Vollmer, K.-P. Möllmann, *Infrared Thermal Imaging*, 2nd ed., Wiley-VCH 2018, §2.3.
.. [2] Sawicki, Stein, Więcek (seed 000): viewing angle from the surface normal and the camera axis.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .._validate import as_array
from ..errors import ConfigError
from ._render import as_pose, camera_size, iter_sample_rays
from .radiance import BandPlanckCurve, SignalCurve
from .sensor import SensorEffects, apply_sensor_effects

__all__ = ["FlatSurface", "RenderedSurface", "render_flat_surface"]


@dataclass(frozen=True)
class FlatSurface:
    """An infinite plane through ``point`` with unit ``normal`` (world frame, metres).

    ``emissivity`` is a number in (0, 1] or a callable ``ε(θ_rad) -> array`` (directional, e.g.
    :class:`thermogrammetry.radiometry.FresnelEmissivity`). ``temperature_k`` is its true (kinetic)
    temperature. The side the normal points to is the emitting side; rays reaching the back see
    ``background_k`` of :func:`render_flat_surface`.
    """

    point: np.ndarray
    normal: np.ndarray
    temperature_k: float
    emissivity: float | Callable = 1.0

    def __post_init__(self):
        p = as_array(self.point, "FlatSurface.point", shape=(3,))
        n = as_array(self.normal, "FlatSurface.normal", shape=(3,))
        nn = np.linalg.norm(n)
        if nn < 1e-12:
            raise ConfigError(f"FlatSurface.normal={self.normal!r}: expected a non-zero vector")
        object.__setattr__(self, "point", p)
        object.__setattr__(self, "normal", n / nn)
        t = float(self.temperature_k)
        if not t > 0:
            raise ConfigError(f"FlatSurface.temperature_k={self.temperature_k!r}: expected kelvin > 0")
        object.__setattr__(self, "temperature_k", t)
        if not callable(self.emissivity):
            e = float(self.emissivity)
            if not 0 < e <= 1:
                raise ConfigError(f"FlatSurface.emissivity={self.emissivity!r}: expected a number in (0, 1] or a callable")
            object.__setattr__(self, "emissivity", e)

    def emissivity_at(self, theta_rad) -> np.ndarray:
        if callable(self.emissivity):
            return np.asarray(self.emissivity(theta_rad), dtype=np.float64)
        return np.full(np.shape(theta_rad), self.emissivity)


@dataclass
class RenderedSurface:
    """Rendered image with per-pixel geometry truth (at pixel centres).

    image_k (H, W) float32 apparent temperature; angle_rad, distance_m (H, W) float64 (NaN off the
    surface); signal (H, W) noise-free signal.
    """

    image_k: np.ndarray
    angle_rad: np.ndarray
    distance_m: np.ndarray
    signal: np.ndarray = field(repr=False)


def _hit(rays_cam, pose, surface):
    d = np.einsum("...i,ij->...j", rays_cam, pose.R)  # world directions (R^T d)
    C = pose.center
    n = surface.normal
    dn = d @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = ((surface.point - C) @ n) / dn
        ok = np.isfinite(lam) & (lam > 0) & (dn < 0)  # in front and seeing the emitting side
        norm_d = np.linalg.norm(d, axis=-1)
        dist = lam * norm_d
        cos_t = np.clip(-dn / norm_d, 0.0, 1.0)
    theta = np.arccos(cos_t)
    return ok, np.where(ok, theta, np.nan), np.where(ok, dist, np.nan)


def render_flat_surface(
    camera,
    pose,
    surface: FlatSurface,
    *,
    reflected_k: float = 293.15,
    transmission: float | Callable = 1.0,
    atmosphere_k: float = 293.15,
    background_k: float = 293.15,
    supersample: int = 4,
    effects: SensorEffects | None = None,
    seed: int = 0,
    curve: SignalCurve | None = None,
) -> RenderedSurface:
    """Render ``surface`` (see module docstring for the signal model).

    Parameters
    ----------
    camera : thermogrammetry.Camera
    pose : Pose or (R, t), ``cam_from_world``
    surface : FlatSurface
    reflected_k, atmosphere_k, background_k : float, kelvin
    transmission : float or callable ``τ(distance_m) -> array``
    supersample : int
    effects : SensorEffects, optional (default: ideal sensor)
    seed : int, temporal-noise seed
    curve : SignalCurve (default Planck 7.5–13.5 µm)

    Returns
    -------
    RenderedSurface
    """
    pose = as_pose(pose)
    curve = curve or BandPlanckCurve()
    effects = effects or SensorEffects()
    s_obj = float(curve.signal(surface.temperature_k))
    s_refl = float(curve.signal(reflected_k))
    s_atm = float(curve.signal(atmosphere_k))
    s_bg = float(curve.signal(background_k))
    w, h = camera_size(camera)
    signal = np.empty((h, w))
    for rows, rays in iter_sample_rays(camera, supersample):
        ok, theta, dist = _hit(rays, pose, surface)
        eps = surface.emissivity_at(np.where(ok, theta, 0.0))
        tau = np.asarray(transmission(np.where(ok, dist, 1.0)) if callable(transmission) else transmission, dtype=np.float64)
        s = tau * (eps * s_obj + (1.0 - eps) * s_refl) + (1.0 - tau) * s_atm
        signal[rows] = np.where(ok, s, s_bg).mean(axis=-1)
    angle = np.empty((h, w))
    dist_c = np.empty((h, w))
    for rows, rays in iter_sample_rays(camera, 1):
        _, th, d = _hit(rays[..., 0, :], pose, surface)
        angle[rows] = th
        dist_c[rows] = d
    image = apply_sensor_effects(signal, curve, effects, np.random.default_rng(seed))
    return RenderedSurface(image, angle, dist_c, signal)
