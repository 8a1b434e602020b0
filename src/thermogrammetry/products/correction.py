"""Per-pixel directional correction of thermal temperatures: the one implementation (seed 000 eq. 7–8, extended).

``closerange`` (seed 000's workflow), ``correct`` and ``ortho`` all call this module: the per-pixel
kernel is :func:`apply_correction` (angle and distance rasters → emissivity, transmission, corrected
temperature, valid mask); :func:`correct_oriented_image` is the general case for any oriented camera
over planes, a mesh or a DSM.

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

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..enums import StrChoice
from ..errors import ConfigError, InvalidInputError
from .._validate import config_keys

__all__ = [
    "AngleMode",
    "EmissivityModelName",
    "CorrectionConfig",
    "CorrectionResult",
    "apply_correction",
    "camera_rays",
    "correct_oriented_image",
    "eq8_correction",
    "correct_temperature",
    "dT_deps",
    "cosine_emissivity",
    "pixel_rays_from_projection",
    "convex_mask",
    "convex_inset",
    "PlaneRaster",
    "plane_rasters",
    "as_correction_config",
    "emissivity_slope",
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


class AngleMode(StrChoice):
    LOS = "los"  # per-pixel line of sight (default)
    AXIS = "axis"  # seed 000: the camera axis (eq. 6) for the whole plane


class EmissivityModelName(StrChoice):
    COSINE = "cosine"  # seed 000 eq. 7-8
    FRESNEL = "fresnel"  # dielectric, refractive index n


@dataclass(frozen=True)
class CorrectionConfig:
    """Options of the per-pixel correction (unknown keys are errors, see :meth:`from_dict`).

    Attributes
    ----------
    ambient_c : reflected ambient temperature Ta (°C)
    angle_mode : "los" (per-pixel line of sight) or "axis" (seed 000's camera-axis angle)
    emissivity : "cosine" (seed 000) or "fresnel"
    refractive_index : for "fresnel"
    transmission : apply the atmospheric transmission over the real distance
    relative_humidity : fraction in [0, 1], for the transmission
    air_c : air temperature (°C) for the transmission; default ``ambient_c``
    max_angle_deg : corrections beyond this line-of-sight angle are marked invalid
    edge_margin_px : pixels closer than this to a plane polygon's edge are marked invalid
    """

    ambient_c: float = 22.0
    angle_mode: AngleMode = AngleMode.LOS
    emissivity: EmissivityModelName = EmissivityModelName.COSINE
    refractive_index: float = 1.5
    transmission: bool = False
    relative_humidity: float = 0.5
    air_c: float | None = None
    max_angle_deg: float = 75.0  # radiometry.DEFAULT_MAX_ANGLE_DEG: the models' documented valid range
    edge_margin_px: float = 1.5

    def __post_init__(self):
        object.__setattr__(self, "angle_mode", AngleMode(self.angle_mode))
        object.__setattr__(self, "emissivity", EmissivityModelName(self.emissivity))
        if not 0 < self.max_angle_deg < 90:
            raise ConfigError(f"max_angle_deg={self.max_angle_deg!r}: expected a value in (0, 90)")
        if not 0 <= self.relative_humidity <= 1:
            raise ConfigError(f"relative_humidity={self.relative_humidity!r}: expected a fraction in [0, 1]")
        if not self.refractive_index > 1:
            raise ConfigError(f"refractive_index={self.refractive_index!r}: expected a number > 1")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "CorrectionConfig":
        return cls(**config_keys(cls, d))

    @property
    def ambient_k(self) -> float:
        return self.ambient_c + 273.15

    @property
    def air_k(self) -> float:
        return (self.ambient_c if self.air_c is None else self.air_c) + 273.15

    def emissivity_function(self) -> Callable[[np.ndarray], np.ndarray]:
        if self.emissivity == EmissivityModelName.COSINE:
            return cosine_emissivity
        from ..radiometry import fresnel_emissivity

        n = self.refractive_index
        return lambda th: fresnel_emissivity(np.clip(th, 0.0, np.pi / 2), n)


def as_correction_config(config) -> CorrectionConfig:
    """A :class:`CorrectionConfig` from itself, None (defaults) or any config with a ``correction`` property
    (``closerange.CloseRangeConfig``)."""
    if config is None:
        return CorrectionConfig()
    if isinstance(config, CorrectionConfig):
        return config
    corr = getattr(config, "correction", None)
    if isinstance(corr, CorrectionConfig):
        return corr
    raise ConfigError(f"expected a CorrectionConfig, got {type(config).__name__}")


@dataclass
class CorrectionResult:
    """Per-pixel rasters of the thermal image (h, w).

    corrected_k : corrected temperature where valid, the measured one elsewhere (K)
    valid : bool mask where the correction applies
    sigma_k : 1-σ uncertainty of the correction from the propagated angle precision (K; NaN off mask)
    angle_rad : angle used (line of sight or axis), NaN off the planes
    sigma_angle_rad : its σ
    distance_m : line-of-sight distance to the surface (NaN off the planes)
    plane : index into the plane list (−1 none)
    emissivity, transmission : values used
    """

    corrected_k: np.ndarray
    valid: np.ndarray
    sigma_k: np.ndarray
    angle_rad: np.ndarray
    sigma_angle_rad: np.ndarray
    distance_m: np.ndarray
    plane: np.ndarray
    emissivity: np.ndarray
    transmission: np.ndarray
    notes: list[str] = field(default_factory=list)


def _transmission(distance_m, air_k, rh):
    from ..radiometry import atmospheric_transmission

    return atmospheric_transmission(distance_m, air_k, rh)


def apply_correction(t0_k, angle_rad, distance_m, on, config=None):
    """The per-pixel kernel: emissivity ε(θ), transmission τ(d) and the corrected temperature.

    Parameters
    ----------
    t0_k : (...) apparent temperature, K
    angle_rad : (...) viewing angle to the surface normal (rad; ignored where not ``on``)
    distance_m : (...) line-of-sight distance (m; ignored where not ``on``)
    on : (...) bool, where a surface was hit
    config : :class:`CorrectionConfig` (or one with a ``correction`` property)

    Returns
    -------
    corrected_k : (...) K, NaN where no real solution (where ``on`` is False: the inversion with ε, τ = 1
        pass-through is not applied; callers keep ``t0_k`` there)
    emissivity, transmission : (...) NaN where not ``on``
    valid : (...) bool: on the surface, finite input and output, angle below ``max_angle_deg``

    References
    ----------
    Sawicki, Stein, Więcek (seed 000) eq. 7–8; Vollmer & Möllmann (2018) §1.4, §2.5.
    """
    cfg = as_correction_config(config)
    T0 = np.asarray(t0_k, float)
    on = np.asarray(on, bool)
    angle = np.asarray(angle_rad, float)
    emis_f = cfg.emissivity_function()
    eps = np.where(on, emis_f(np.where(on, angle, 0.0)), np.nan)
    if cfg.transmission:
        tau = np.where(on, _transmission(np.where(on, distance_m, 0.0), cfg.air_k, cfg.relative_humidity), np.nan)
    else:
        tau = np.where(on, 1.0, np.nan)
    Tc = correct_temperature(T0, eps, cfg.ambient_k, transmission=np.where(on, tau, 1.0), atmosphere_k=cfg.air_k)
    with np.errstate(invalid="ignore"):
        valid = on & np.isfinite(T0) & np.isfinite(Tc) & (angle < np.radians(cfg.max_angle_deg))
    return Tc, eps, tau, valid


def emissivity_slope(config, angle_rad, valid) -> np.ndarray:
    """dε/dθ of the configured model by central difference (analytic −sin θ for the cosine law)."""
    emis_f = as_correction_config(config).emissivity_function()
    hth = 1e-6
    a0 = np.where(valid, angle_rad, 0.5)
    return (emis_f(a0 + hth) - emis_f(np.maximum(a0 - hth, 0))) / (a0 + hth - np.maximum(a0 - hth, 0))


def camera_rays(camera, R, t, image_size=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projection centre, viewing axis and unit world rays (h, w, 3) of every pixel of an oriented camera.

    Parameters
    ----------
    camera : ``thermogrammetry.Camera`` (distortion honoured through ``unproject``) or a (3, 3) ``K``
    R, t : pose ``cam_from_world``
    image_size : (w, h); default ``camera.image_size``
    """
    R = np.asarray(R, float)
    t = np.asarray(t, float).reshape(3)
    if hasattr(camera, "unproject"):
        w, h = image_size or camera.image_size
        unproject = camera.unproject
    else:
        K = np.asarray(camera, float)
        if image_size is None:
            raise InvalidInputError("image_size: required when the camera is given as a K matrix")
        w, h = image_size

        def unproject(xy):
            return np.column_stack([xy, np.ones(len(xy))]) @ np.linalg.inv(K).T

    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    d_cam = np.asarray(unproject(np.column_stack([u.ravel(), v.ravel()])), float)
    d = d_cam @ R  # R^T d_cam for every row
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return -R.T @ t, R[2].copy(), d.reshape(h, w, 3)


def correct_oriented_image(
    temperature_k,
    camera,
    R,
    t,
    planes: Sequence[tuple[Sequence[float], float]] | None,
    config=None,
    *,
    polygons_world: Sequence[np.ndarray] | None = None,
    mesh: tuple[np.ndarray, np.ndarray] | None = None,
    sigma_angle_rad=None,
) -> CorrectionResult:
    """General case: correct a thermal image of an oriented camera over planes or a triangle mesh.

    Parameters
    ----------
    temperature_k : (h, w) apparent temperatures, K
    camera, R, t : see :func:`camera_rays`
    planes : sequence of (normal (3,), d) with ``normal · X + d = 0`` (m), or None with ``mesh``
    config : :class:`CorrectionConfig` (or ``closerange.CloseRangeConfig``)
    polygons_world : optional (N_i ≥ 3, 3) outlines of each plane (m); default: the whole image
    mesh : optional (vertices (V, 3) m, faces (F, 3)) instead of planes (a DSM: :func:`.surfaces.dsm_to_mesh`);
        ``plane`` in the result then holds the face index
    sigma_angle_rad : optional per-pixel or scalar angle σ for the uncertainty map
    """
    cfg = as_correction_config(config)
    T0 = np.asarray(temperature_k, float)
    if T0.ndim != 2:
        raise InvalidInputError(f"temperature_k: expected a 2D image, got shape {T0.shape}")
    h, w = T0.shape
    C, axis, rays = camera_rays(camera, R, t, (w, h))
    if (planes is None) == (mesh is None):
        raise InvalidInputError("give either planes or a mesh as the surface")
    if mesh is not None:
        from .surfaces import mesh_rasters

        pr = mesh_rasters(C, rays, axis, *mesh)
        polygons_world = None
    elif polygons_world is None:
        big = np.array([[-1e6, -1e6], [1e6 + w, -1e6], [1e6 + w, 1e6 + h], [-1e6, 1e6 + h]])
        polys = [big] * len(planes)
    else:
        Rm = np.asarray(R, float)
        tv = np.asarray(t, float).reshape(3)
        polys = []
        for Pw in polygons_world:
            Xc = np.asarray(Pw, float) @ Rm.T + tv
            if hasattr(camera, "project"):
                polys.append(np.asarray(camera.project(Xc), float))
            else:
                uvw = Xc @ np.asarray(camera, float).T
                polys.append(uvw[:, :2] / uvw[:, 2:3])
    if mesh is None:
        planes = [(np.asarray(n, float) / np.linalg.norm(n), float(d) / np.linalg.norm(n)) for n, d in planes]
        pr = plane_rasters(C, rays, axis, planes, polys, margin_px=cfg.edge_margin_px)
    on = pr.plane >= 0
    angle = pr.angle_rad if cfg.angle_mode == AngleMode.LOS else pr.axis_angle_rad
    Tc, eps, tau, valid = apply_correction(T0, angle, pr.distance_m, on, cfg)
    margin_ok = pr.inset_px >= (cfg.edge_margin_px if polygons_world is not None else -np.inf)
    with np.errstate(invalid="ignore"):
        valid &= margin_ok
        if polygons_world is not None:
            valid &= pr.cover == 1
    sig_a = np.full((h, w), np.nan) if sigma_angle_rad is None else np.broadcast_to(
        np.asarray(sigma_angle_rad, float), (h, w)).copy()
    deps = emissivity_slope(cfg, angle, valid)
    sigma_k = np.where(valid, np.abs(dT_deps(np.where(valid, Tc, 300.0), np.where(valid, eps, 1.0),
                                             cfg.ambient_k) * deps) * sig_a, np.nan)
    return CorrectionResult(
        corrected_k=np.where(valid, Tc, T0), valid=valid, sigma_k=sigma_k, angle_rad=angle,
        sigma_angle_rad=np.where(valid, sig_a, np.nan), distance_m=pr.distance_m, plane=pr.plane, emissivity=eps,
        transmission=tau, notes=[],
    )
