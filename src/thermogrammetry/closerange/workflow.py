"""Seed 000's whole workflow on arrays: network → planes → per-pixel correction, with precision.

:func:`estimate_planes` and :func:`correct_thermal_image` are the array-level API; the pipeline
steps that read and write a project live in :mod:`.pipeline`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..enums import StrChoice
from ..errors import ConfigError, InvalidInputError
from ..products import correction as corr
from ..products.correction import (
    AngleMode,
    CorrectionConfig,
    CorrectionResult,
    EmissivityModelName,
    camera_rays,
    correct_oriented_image,
)
from . import network as nw
from .planes import PlaneEstimate, angle_to_axis, check_plane_points, fit_plane, plane_jacobian
from .solve import NetworkResult
from .._validate import config_keys

__all__ = [
    "AngleMode",
    "EmissivityModelName",
    "CloseRangeConfig",
    "estimate_planes",
    "CorrectionResult",
    "correct_thermal_image",
    "thermal_geometry",
    "camera_rays",
    "correct_oriented_image",
]


@dataclass(frozen=True)
class CloseRangeConfig:
    """Configuration of the close-range workflow (unknown keys are errors, see :meth:`from_dict`).

    Attributes
    ----------
    sigma_px : a-priori σ of an image measurement (px), used for the propagated precision
    ambient_c : reflected ambient temperature Ta (°C)
    angle_mode : "los" (per-pixel line of sight) or "axis" (seed 000's camera-axis angle)
    emissivity : "cosine" (seed 000) or "fresnel"
    refractive_index : for "fresnel"
    transmission : apply the atmospheric transmission over the real distance
    relative_humidity : fraction in [0, 1], for the transmission
    air_c : air temperature (°C) for the transmission; default ``ambient_c``
    max_angle_deg : corrections beyond this line-of-sight angle are marked invalid
    edge_margin_px : pixels closer than this to a plane polygon's edge are marked invalid (mixed
        pixels; the polygon's vertices are uncertain by the image precision)
    max_sigma_k : pixels whose propagated 1-σ exceeds this (K) are marked invalid; None: no limit
    control_sigma_m : σ of the control coordinates (m); None: errorless control. Propagated into every
        result; adjusted as weighted observations in the joint adjustment
    bundle : after the sequential chain, adjust all cameras and pass points jointly (:mod:`.adjust`)
    additional_parameters : distortion terms of the optical DLT cameras in the joint adjustment
        (names of :data:`.adjust.ADDITIONAL_PARAMETERS`, e.g. ``("k1", "p1", "p2")``)
    """

    sigma_px: float = 0.5
    ambient_c: float = 22.0
    angle_mode: AngleMode = AngleMode.LOS
    emissivity: EmissivityModelName = EmissivityModelName.COSINE
    refractive_index: float = 1.5
    transmission: bool = False
    relative_humidity: float = 0.5
    air_c: float | None = None
    max_angle_deg: float = 75.0  # radiometry.DEFAULT_MAX_ANGLE_DEG: the models' documented valid range
    edge_margin_px: float = 1.5
    max_sigma_k: float | None = None
    control_sigma_m: float | None = None
    bundle: bool = False
    additional_parameters: tuple[str, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "angle_mode", AngleMode(self.angle_mode))
        object.__setattr__(self, "emissivity", EmissivityModelName(self.emissivity))
        if not self.sigma_px > 0:
            raise ConfigError(f"sigma_px={self.sigma_px!r}: expected a positive number of pixels")
        if self.control_sigma_m is not None and not self.control_sigma_m > 0:
            raise ConfigError(f"control_sigma_m={self.control_sigma_m!r}: expected a positive number of metres or None")
        if not 0 < self.max_angle_deg < 90:
            raise ConfigError(f"max_angle_deg={self.max_angle_deg!r}: expected a value in (0, 90)")
        if not 0 <= self.relative_humidity <= 1:
            raise ConfigError(f"relative_humidity={self.relative_humidity!r}: expected a fraction in [0, 1]")
        if not self.refractive_index > 1:
            raise ConfigError(f"refractive_index={self.refractive_index!r}: expected a number > 1")
        from .adjust import ADDITIONAL_PARAMETERS

        add = tuple(str(a).strip().lower() for a in self.additional_parameters)
        bad = [a for a in add if a not in ADDITIONAL_PARAMETERS]
        if bad:
            raise ConfigError(f"additional_parameters {bad}: expected some of {list(ADDITIONAL_PARAMETERS)}")
        if add and not self.bundle:
            raise ConfigError("additional_parameters are estimated in the joint adjustment: set bundle=True (--bundle)")
        object.__setattr__(self, "additional_parameters", add)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "CloseRangeConfig":
        return cls(**config_keys(cls, d))

    def to_dict(self) -> dict[str, Any]:
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = str(v) if isinstance(v, StrChoice) else (list(v) if isinstance(v, tuple) else v)
        return out

    @property
    def correction(self) -> CorrectionConfig:
        """The per-pixel correction options (:class:`thermogrammetry.products.correction.CorrectionConfig`)."""
        return CorrectionConfig(ambient_c=self.ambient_c, angle_mode=self.angle_mode, emissivity=self.emissivity,
                                refractive_index=self.refractive_index, transmission=self.transmission,
                                relative_humidity=self.relative_humidity, air_c=self.air_c,
                                max_angle_deg=self.max_angle_deg, edge_margin_px=self.edge_margin_px)

    @property
    def ambient_k(self) -> float:
        return self.ambient_c + 273.15

    @property
    def air_k(self) -> float:
        return (self.ambient_c if self.air_c is None else self.air_c) + 273.15

    def emissivity_function(self) -> Callable[[np.ndarray], np.ndarray]:
        return self.correction.emissivity_function()


def thermal_geometry(net: NetworkResult) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World projection matrix, unit viewing axis and projection centre of the thermal camera."""
    P = net.cameras[net.thermal].P_world(net.frame)
    a, C = nw.camera_axis_center(P)
    return P, a, C


def _axis_from_L(L, frame: nw.Frame) -> np.ndarray:
    P = nw.dlt_matrix(L) @ frame.world_matrix()
    return nw.camera_axis_center(P)[0]


def estimate_planes(net: NetworkResult, planes: Mapping[str, Sequence[str]]) -> list[PlaneEstimate]:
    """Fit each plane to its marked points and relate it to the thermal camera (eq. 5–6).

    Raises
    ------
    InvalidInputError : a plane names a point with no coordinates
    DegenerateInputError : collinear points (the message names the plane)
    """
    _, axis, C = thermal_geometry(net)
    cam = net.cameras[net.thermal]
    out = []
    known = set(net.control) | set(net.pass_ids)
    for name, ids in planes.items():
        ids = tuple(str(i) for i in ids)
        missing = [i for i in ids if i not in known]
        if missing:
            raise InvalidInputError(
                f"plane {name!r}: point(s) {', '.join(missing)} have no coordinates (neither control points nor "
                "pass points intersected from ≥ 2 optical images)"
            )
        X = np.array([net.point(i) for i in ids])
        check_plane_points(X, name, ids)
        n, d, rms = fit_plane(X)
        if n @ C + d < 0:  # orient towards the thermal camera
            n, d = -n, -d
        Jpts = np.vstack([net.point_jacobian(i) for i in ids])
        J_nd = plane_jacobian(X, n) @ Jpts
        centroid = X.mean(axis=0)
        # angle η (eq. 6) and its σ: depends on the normal and on the thermal camera's axis
        eta = float(angle_to_axis(n, axis))
        g_n = np.zeros(3)
        g_L = np.zeros(11)
        h = 1e-7
        for k in range(3):
            e = np.zeros(3)
            e[k] = h
            g_n[k] = (angle_to_axis(n + e, axis) - angle_to_axis(n - e, axis)) / (2 * h)
        for k in range(11):
            hk = 1e-7 * max(1.0, abs(cam.L[k]))
            e = np.zeros(11)
            e[k] = hk
            g_L[k] = (angle_to_axis(n, _axis_from_L(cam.L + e, net.frame))
                      - angle_to_axis(n, _axis_from_L(cam.L - e, net.frame))) / (2 * hk)
        J_eta = g_n @ J_nd[:3] + g_L @ cam.J
        sig_eta = float(np.sqrt(net.cov(J_eta[None])[0, 0]))
        # distance thermal centre → centroid, with σ
        from .solve import _center_and_jacobian

        _, JC = _center_and_jacobian(cam, net.frame)
        Jcent = np.mean(Jpts.reshape(len(ids), 3, -1), axis=0)
        vec = centroid - C
        dist = float(np.linalg.norm(vec))
        J_dist = (vec / dist) @ (Jcent - JC)
        sig_d = float(np.sqrt(net.cov(J_dist[None])[0, 0]))
        los = vec / dist
        out.append(PlaneEstimate(
            name=str(name), ids=ids, normal=n, d=d, centroid=centroid, rms_m=rms,
            angle_rad=eta, sigma_angle_rad=sig_eta,
            los_angle_rad=float(np.arccos(np.clip(abs(n @ los), 0, 1))),
            distance_m=dist, sigma_distance_m=sig_d, perpendicular_m=float(abs(n @ C + d)),
            cov_normal=net.cov(J_nd[:3]), J_nd=J_nd,
        ))
    return out


def _rays_from_L(L, frame, image_size, pix):
    P = nw.dlt_matrix(L) @ frame.world_matrix()
    if np.linalg.det(P[:, :3]) < 0:
        P = -P
    d = pix @ np.linalg.inv(P[:, :3]).T
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def correct_thermal_image(
    net: NetworkResult,
    planes: Sequence[PlaneEstimate],
    temperature_k,
    config: CloseRangeConfig | None = None,
) -> CorrectionResult:
    """Correct the thermal image per pixel over the planes (module :mod:`.correction`).

    Parameters
    ----------
    net : the oriented network (thermal camera from DLT)
    planes : from :func:`estimate_planes`
    temperature_k : (h, w) apparent temperatures of the thermal image, K
    config : CloseRangeConfig
    """
    cfg = config or CloseRangeConfig()
    T0 = np.asarray(temperature_k, float)
    if T0.ndim != 2:
        raise InvalidInputError(f"temperature_k: expected a 2D image, got shape {T0.shape}")
    h, w = T0.shape
    P, axis, C = thermal_geometry(net)
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    grid = np.column_stack([u.ravel(), v.ravel()])
    known_cam = net.known.get(net.thermal)
    if known_cam is not None:  # known interior orientation: rays through the undistorted pixel positions
        grid_ideal = np.asarray(known_cam.undistort(grid), float)
    else:
        grid_ideal = grid
    pix_all = np.column_stack([grid_ideal, np.ones(len(grid))])
    rays = _rays_from_L(net.cameras[net.thermal].L, net.frame, (w, h), pix_all).reshape(h, w, 3)
    polys = []
    for p in planes:
        xy = nw.dlt_project(net.cameras[net.thermal].L, net.frame.to_norm(np.array([net.point(i) for i in p.ids])))
        polys.append(np.asarray(known_cam.distort(xy), float) if known_cam is not None else xy)
    pr = corr.plane_rasters(C, rays, axis, [(p.normal, p.d) for p in planes], polys, margin_px=cfg.edge_margin_px)
    on = pr.plane >= 0
    angle = pr.angle_rad if cfg.angle_mode == AngleMode.LOS else pr.axis_angle_rad
    # σ of the angle per pixel: gradient w.r.t. (normal, L_thermal), joint covariance of both
    sig_angle = np.full((h, w), np.nan)
    cam = net.cameras[net.thermal]
    for j, p in enumerate(planes):
        sel = pr.plane == j
        if not sel.any():
            continue
        if cfg.angle_mode == AngleMode.AXIS:
            sig_angle[sel] = p.sigma_angle_rad
            continue
        pix = pix_all[sel.ravel()]
        n0 = p.normal

        def theta(n, L):
            r = _rays_from_L(L, net.frame, (w, h), pix)
            return np.arccos(np.clip(np.abs(r @ n) / np.linalg.norm(n), 0, 1))

        G = np.zeros((sel.sum(), 14))
        for k in range(3):
            e = np.zeros(3)
            e[k] = 1e-7
            G[:, k] = (theta(n0 + e, cam.L) - theta(n0 - e, cam.L)) / 2e-7
        for k in range(11):
            hk = 1e-7 * max(1.0, abs(cam.L[k]))
            e = np.zeros(11)
            e[k] = hk
            G[:, 3 + k] = (theta(n0, cam.L + e) - theta(n0, cam.L - e)) / (2 * hk)
        Sp = net.cov(np.vstack([p.J_nd[:3], cam.J]))
        sig_angle[sel] = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", G, Sp, G), 0))
    Tc, eps, tau, valid = corr.apply_correction(T0, angle, pr.distance_m, on, cfg)
    with np.errstate(invalid="ignore"):
        valid &= (pr.inset_px >= cfg.edge_margin_px) & (pr.cover == 1)
    deps = corr.emissivity_slope(cfg, angle, valid)
    sigma_k = np.where(valid, np.abs(corr.dT_deps(np.where(valid, Tc, 300.0), np.where(valid, eps, 1.0),
                                                  cfg.ambient_k) * deps) * sig_angle, np.nan)
    if cfg.max_sigma_k is not None:
        with np.errstate(invalid="ignore"):
            valid &= sigma_k <= cfg.max_sigma_k
        sigma_k = np.where(valid, sigma_k, np.nan)
    notes = []
    n_out = int((on & ~valid).sum())
    if n_out:
        notes.append(f"{n_out} pixels on planes left uncorrected (within {cfg.edge_margin_px} px of an edge or of "
                     "another plane's polygon, "
                     f"angle ≥ {cfg.max_angle_deg}°, above max_sigma_k or no real solution)")
    return CorrectionResult(
        corrected_k=np.where(valid, Tc, T0), valid=valid, sigma_k=sigma_k, angle_rad=angle,
        sigma_angle_rad=sig_angle, distance_m=pr.distance_m, plane=pr.plane, emissivity=eps, transmission=tau,
        notes=notes,
    )
