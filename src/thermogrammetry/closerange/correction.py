"""Per-pixel directional correction of a thermal image over planar surfaces (seed 000 eq. 7–8, extended).

For every pixel whose centre falls inside a plane's projected polygon (the convex hull of its
marked points' projections; the nearest plane wins where polygons overlap) the line of sight is
intersected with the plane. That gives the angle θ between the line of sight and the normal and the
real distance. The camera's apparent (black-body) temperature ``T0`` is then inverted with the
total-radiation balance

    T0⁴ = τ(d) [ ε(θ) T⁴ + (1 − ε(θ)) Ta⁴ ] + (1 − τ(d)) Tatm⁴

for the surface temperature ``T``, where ``Ta`` is the reflected ambient temperature, ``τ(d)`` the
atmospheric transmission over the pixel's distance and ``Tatm`` the air temperature. With
``ε = cos θ`` and ``τ = 1`` this is exactly seed 000 eq. 8,

    T = ⁴√( (T0⁴ − Ta⁴) / cos θ + Ta⁴ ),

which follows from eq. 7 (Φ = Φ0 / cos η) applied to the flux above ambient. The paper uses the angle
η of the camera *axis* (eq. 6); we use the actual line of sight of every pixel (``angle_mode="los"``)
or, on request, the axis angle as in the paper (``angle_mode="axis"``).

A pixel's correction is *valid* where it lies on a plane, in front of the camera, at θ below
``max_angle_deg`` (the cosine law and Fresnel emissivity are unreliable at grazing angles) and the
input temperature is finite. The uncertainty map is σ_T = |∂T/∂θ| σ_θ with σ_θ propagated from the
network (plane normal and thermal camera orientation, with their correlation).

References
----------
Sawicki, Stein, Więcek (seed 000) eq. 7–8; Vollmer & Möllmann, *Infrared Thermal Imaging* (2018) §1.4
(directional emissivity) and §2.5 (atmospheric transmission).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import InvalidInputError

__all__ = [
    "eq8_correction",
    "correct_temperature",
    "dT_deps",
    "cosine_emissivity",
    "pixel_rays_from_projection",
    "convex_mask",
    "convex_inset",
    "PlaneRaster",
    "plane_rasters",
]


def cosine_emissivity(theta) -> np.ndarray:
    """The cosine law ε(θ) = cos θ implied by seed 000 eq. 7."""
    return np.cos(np.asarray(theta, float))


def eq8_correction(t0_k, angle_rad, ambient_k) -> np.ndarray:
    """Seed 000 eq. 8 verbatim: ``T = ((T0⁴ − Ta⁴)/cos φ + Ta⁴)^¼`` (K).

    NaN where the bracket is negative (a measured temperature far below ambient at a large angle).
    """
    t0 = np.asarray(t0_k, float)
    ta = np.asarray(ambient_k, float)
    q = (t0**4 - ta**4) / np.cos(np.asarray(angle_rad, float)) + ta**4
    with np.errstate(invalid="ignore"):
        return np.where(q >= 0, np.abs(q) ** 0.25, np.nan)


def correct_temperature(
    t0_k,
    emissivity,
    ambient_k,
    *,
    transmission=1.0,
    atmosphere_k=None,
) -> np.ndarray:
    """Invert ``T0⁴ = τ[εT⁴ + (1−ε)Ta⁴] + (1−τ)Tatm⁴`` for ``T`` (K), element-wise.

    Parameters
    ----------
    t0_k : array_like
        Apparent (black-body equivalent) temperature measured by the camera, K.
    emissivity : array_like
        Directional emissivity ε(θ) per pixel, in (0, 1].
    ambient_k : float or array_like
        Reflected ambient temperature Ta, K.
    transmission : float or array_like
        Atmospheric transmission τ over the pixel's distance, in (0, 1].
    atmosphere_k : float or array_like, optional
        Air temperature (K) emitting the path radiance; default ``ambient_k``.

    Returns
    -------
    ndarray, K; NaN where ε ≤ 0 or the inversion has no real solution.
    """
    t0 = np.asarray(t0_k, float)
    eps = np.asarray(emissivity, float)
    ta = np.asarray(ambient_k, float)
    tau = np.asarray(transmission, float)
    tatm = ta if atmosphere_k is None else np.asarray(atmosphere_k, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = (t0**4 - (1.0 - tau) * tatm**4) / tau  # what the surface sends, unattenuated
        t4 = (q - ta**4) / eps + ta**4
        ok = (eps > 0) & (tau > 0) & (t4 >= 0)
        return np.where(ok, np.abs(t4) ** 0.25, np.nan)


def dT_deps(t_k, emissivity, ambient_k) -> np.ndarray:
    """∂T/∂ε of :func:`correct_temperature` (K per unit emissivity), at the corrected ``T``.

    From ``T⁴ = (Q − Ta⁴)/ε + Ta⁴``: ∂T⁴/∂ε = −(T⁴ − Ta⁴)/ε, so ∂T/∂ε = −(T⁴ − Ta⁴)/(4 ε T³).
    """
    t = np.asarray(t_k, float)
    ta = np.asarray(ambient_k, float)
    eps = np.asarray(emissivity, float)
    return -(t**4 - ta**4) / (4.0 * eps * t**3)


def pixel_rays_from_projection(P, image_size) -> tuple[np.ndarray, np.ndarray]:
    """Projection centre and unit world rays of every pixel centre of a 3×4 pinhole/DLT camera.

    Returns
    -------
    C : (3,) m
    rays : (h, w, 3) unit directions (pointing away from the camera)
    """
    P = np.asarray(P, float)
    if np.linalg.det(P[:, :3]) < 0:
        P = -P
    M = P[:, :3]
    C = -np.linalg.solve(M, P[:, 3])
    w, h = (int(image_size[0]), int(image_size[1]))
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    x = np.stack([u, v, np.ones_like(u)], axis=-1)
    d = x @ np.linalg.inv(M).T
    return C, d / np.linalg.norm(d, axis=-1, keepdims=True)


def convex_inset(polygon_xy, image_size) -> np.ndarray:
    """(h, w) signed distance (px) of every pixel centre inside the convex hull of (N ≥ 3, 2) px
    vertices: positive inside (distance to the nearest edge), negative outside; −inf for a
    degenerate hull."""
    from scipy.spatial import ConvexHull, QhullError

    P = np.asarray(polygon_xy, float)
    w, h = (int(image_size[0]), int(image_size[1]))
    try:
        hull = ConvexHull(P)
    except (QhullError, ValueError):
        return np.full((h, w), -np.inf)
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    dist = np.full((h, w), np.inf)
    for a, b, c in hull.equations:  # unit outward normals: a u + b v + c <= 0 inside
        dist = np.minimum(dist, -(a * u + b * v + c))
    return dist


def convex_mask(polygon_xy, image_size) -> np.ndarray:
    """(h, w) bool: pixel centres inside (or on) the convex hull of (N ≥ 3, 2) px vertices."""
    return convex_inset(polygon_xy, image_size) >= -1e-9


@dataclass
class PlaneRaster:
    """Per-pixel geometry of planes seen by one camera.

    Attributes
    ----------
    plane : (h, w) int index of the plane hit (−1: none)
    angle_rad : (h, w) angle between the line of sight and the normal (NaN off the planes)
    axis_angle_rad : (h, w) angle between the camera axis and the normal (seed 000 eq. 6)
    distance_m : (h, w) camera centre → surface along the line of sight (NaN off the planes)
    inset_px : (h, w) distance of the pixel centre from its polygon's edge (px; NaN off the planes)
    cover : (h, w) int, how many polygons (grown by ``margin_px``) contain the pixel centre
    """

    plane: np.ndarray
    angle_rad: np.ndarray
    axis_angle_rad: np.ndarray
    distance_m: np.ndarray
    inset_px: np.ndarray
    cover: np.ndarray


def plane_rasters(C, rays, axis, planes, polygons_xy, *, margin_px: float = 0.0) -> PlaneRaster:
    """Intersect every pixel's line of sight with the planes inside their projected polygons.

    Parameters
    ----------
    C : (3,) projection centre (m); rays : (h, w, 3) unit world rays; axis : (3,) unit viewing axis
    planes : sequence of (normal (3,), d) with ``normal · X + d = 0``
    polygons_xy : sequence of (N_i, 2) px vertices (projected marked points), one per plane
    """
    rays = np.asarray(rays, float)
    C = np.asarray(C, float)
    h, w, _ = rays.shape
    best = np.full((h, w), np.inf)
    idx = np.full((h, w), -1)
    angle = np.full((h, w), np.nan)
    axang = np.full((h, w), np.nan)
    inset = np.full((h, w), np.nan)
    cover = np.zeros((h, w), int)
    if len(planes) != len(polygons_xy):
        raise InvalidInputError(f"{len(planes)} planes but {len(polygons_xy)} polygons; expected one per plane")
    for j, ((n, d), poly) in enumerate(zip(planes, polygons_xy)):
        n = np.asarray(n, float)
        ins = convex_inset(poly, (w, h))
        inside = ins >= -1e-9
        cover += ins > -margin_px
        den = rays @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -(n @ C + d) / den
        take = inside & np.isfinite(s) & (s > 0) & (s < best)
        best[take] = s[take]
        idx[take] = j
        angle[take] = np.arccos(np.clip(np.abs(den[take]) / np.linalg.norm(n), 0.0, 1.0))
        axang[take] = np.arccos(np.clip(abs(n @ axis) / np.linalg.norm(n), 0.0, 1.0))
        inset[take] = ins[take]
    return PlaneRaster(idx, angle, axang, np.where(idx >= 0, best, np.nan), inset, cover)


EmissivityModel = Callable[[np.ndarray], np.ndarray]
