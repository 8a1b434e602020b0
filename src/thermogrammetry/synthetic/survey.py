"""A UAV thermal survey with exact ground truth: flight plan, rendered frames / video, GNSS, GCPs.

:func:`make_survey` builds a :class:`SurveyScene` (terrain, thermal camera, flight plan, ground control)
without rendering; :func:`render_frame` renders one frame; :func:`write_survey` renders every frame and
writes images and truth through a project store (:mod:`thermogrammetry.pipeline`).

Radiometry per sub-pixel sample: the ray hits the DSM surface (:mod:`.terrain`) at distance ``d`` and
viewing angle θ from the bilinear surface's normal; the material gives ε(θ) = ε_n · F(θ)/F(0) (Fresnel
shape, scaled to the material's normal emissivity); the sensor signal is
``τ(d) [ε S(T) + (1 − ε) S(T_sky)] + (1 − τ(d)) S(T_air)`` with ``τ`` the FLIR two-band transmission
over the path (``τ(d/2)²``, as :mod:`thermogrammetry.radiometry.measurement` splits it) and ``S`` the
FLIR calibration curve (:class:`~.radiance.FlirCurve`); rays that miss see the sky. Frames are
``float32`` apparent temperature (the camera's reading with ε = 1, τ = 1) after the sensor effects.

Flight plan: parallel lines along +x (east), serpentine, at ``flight_height_m`` above the mean ground;
the image's long side across track and the image top pointing forward; consecutive exposures
``(1 − overlap)`` of the along-track footprint apart (or ``speed_mps / video_fps`` in video mode);
lines ``(1 − sidelap)`` of the across-track footprint apart. Each exposure gets a small random attitude
(roll/pitch/yaw ~ ``attitude_sigma_deg``) as a real gimbal/airframe has.

Files written by :func:`write_survey` under ``prefix`` (default ``survey``):

================================  ================================================================
``images/<name>.tif``             float32 apparent temperature, K (GPS EXIF = noisy GNSS position)
``images_8bit/<name>.jpg``        optional palette JPEG (inferno, survey-wide fixed range)
``cameras.json``                  true camera (``Camera.to_dict()``) + per-image ``R``, ``t`` (cam_from_world, CRS coordinates), centre, time
``gnss.csv``                      name, easting, northing, height, sigma_h_m, sigma_v_m, time_s (noisy)
``gcp.csv`` / ``check.csv``       name, easting, northing, height (true)
``gcp_observations.csv``          image, name, x_px, y_px (exact projections, visible and unoccluded)
``truth/dsm.tif``                 DSM GeoTIFF (float32 m, EPSG, pixel-corner transform)
``truth/temperature.tif``         true surface temperature (float32 K), texture grid
``truth/emissivity.tif``          normal emissivity (float32), texture grid
``truth/points.csv``              all markers with type (gcp/check)
``truth/tie_points.csv``          optional: random surface points + ``truth/tie_observations.csv`` (exact)
``scene.json``                    configuration, CRS, origin, materials, counts, frame list
================================  ================================================================

References
----------
.. [1] Khodaei, Samadzadegan, Dadras Javan, Hasani (seed 003): thermal video from a UAV at 100 m,
   640×480, 25 mm, 17 µm, 80 % overlap, 60 % sidelap, GCPs for absolute orientation.
.. [2] M. Vollmer, K.-P. Möllmann, *Infrared Thermal Imaging*, 2nd ed., Wiley-VCH 2018, §2.3.
"""

from __future__ import annotations

import os

import csv
import io
import json
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

import numpy as np

from ..errors import ConfigError
from ._render import unproject_fast
from .radiance import FlirCurve, fresnel_emissivity
from .sensor import SensorEffects, apply_sensor_effects
from .terrain import HeightfieldCaster, Terrain, TerrainConfig, add_square_markers, make_terrain
from .._validate import config_keys

__all__ = [
    "SurveyConfig", "SurveyScene", "FramePlan", "make_survey", "render_frame", "render_frames", "write_survey",
    "marker_observations", "tie_points", "render_rgb_frame",
]


@dataclass(frozen=True)
class SurveyConfig:
    """Typed survey configuration (:meth:`from_dict` refuses unknown keys).

    Camera: ``image_size`` (w, h), ``focal_mm``, ``pixel_pitch_um``, OpenCV-form ``distortion``
    (k1 k2 p1 p2 k3), principal-point offset ``pp_offset_px``. Flight: ``flight_height_m`` above the
    mean ground, ``overlap``/``sidelap`` fractions, ``speed_mps``; ``video_fps`` switches to video mode
    (exposures every ``speed_mps / video_fps`` metres). ``max_frames`` caps the plan (None = all).
    GNSS noise ``gnss_sigma_h_m``/``gnss_sigma_v_m``. The attitude written in each frame's XMP as DJI gimbal angles
    (:mod:`thermogrammetry.sfm.attitude`): the true one turned by a common tilt ``gimbal_tilt_deg`` (about east, north)
    and per-frame noise ``gimbal_sigma_deg`` per axis (the DJI M3T flight: 1.3° tilt, ~0.5° scatter). Radiometry:
    sky, air, humidity. Sensor: see :class:`SensorEffects`. ``supersample``: S×S samples per pixel.
    """

    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    image_size: tuple[int, int] = (640, 512)
    focal_mm: float = 25.0
    pixel_pitch_um: float = 17.0
    distortion: dict = field(default_factory=lambda: {"k1": -0.08, "k2": 0.05, "p1": 2e-4, "p2": -1e-4})
    pp_offset_px: tuple[float, float] = (3.2, -2.1)
    flight_height_m: float = 100.0
    overlap: float = 0.8
    sidelap: float = 0.6
    speed_mps: float = 6.0
    video_fps: float | None = None
    max_frames: int | None = None
    attitude_sigma_deg: float = 1.0
    gimbal_sigma_deg: float = 0.5
    gimbal_tilt_deg: tuple[float, float] = (1.0, 0.5)
    gnss_sigma_h_m: float = 0.03
    gnss_sigma_v_m: float = 0.05
    n_gcp: int = 5
    n_check: int = 4
    marker_size_m: float = 1.0
    sky_k: float = 235.0
    air_k: float = 293.15
    relative_humidity: float = 0.5
    sensor: SensorEffects = field(default_factory=lambda: SensorEffects(psf_sigma_px=0.6, netd_k=0.05, fpn_k=0.03, vignetting=0.02, fpn_seed=11))
    supersample: int = 1
    seed: int = 0

    def __post_init__(self):
        for name in ("overlap", "sidelap"):
            v = float(getattr(self, name))
            if not 0 <= v < 1:
                raise ConfigError(f"SurveyConfig.{name}={v!r}: expected a fraction in [0, 1)")
        for name in ("focal_mm", "pixel_pitch_um", "flight_height_m", "speed_mps", "marker_size_m", "sky_k", "air_k"):
            v = float(getattr(self, name))
            if not np.isfinite(v) or v <= 0:
                raise ConfigError(f"SurveyConfig.{name}={getattr(self, name)!r}: expected a positive number")
        if self.video_fps is not None and not float(self.video_fps) > 0:
            raise ConfigError(f"SurveyConfig.video_fps={self.video_fps!r}: expected a positive frame rate or None")
        if not isinstance(self.supersample, (int, np.integer)) or self.supersample < 1:
            raise ConfigError(f"SurveyConfig.supersample={self.supersample!r}: expected an integer >= 1")
        unknown = sorted(set(self.distortion) - {"k1", "k2", "p1", "p2", "k3"})
        if unknown:
            raise ConfigError(f"SurveyConfig.distortion: unknown coefficient(s) {unknown}; valid: k1 k2 p1 p2 k3")

    @classmethod
    def from_dict(cls, d: dict) -> "SurveyConfig":
        d = config_keys(cls, d)
        if isinstance(d.get("terrain"), dict):
            d["terrain"] = TerrainConfig.from_dict(d["terrain"])
        if isinstance(d.get("sensor"), dict):
            d["sensor"] = SensorEffects.from_dict(d["sensor"])
        for k in ("image_size", "pp_offset_px", "gimbal_tilt_deg"):
            if k in d:
                d[k] = tuple(d[k])
        return cls(**d)

    def to_dict(self) -> dict:
        d = asdict(self)
        return d

    def camera(self):
        """The true thermal camera (OpenCV forward model, px)."""
        from ..camera import Camera

        w, h = self.image_size
        f = self.focal_mm / (self.pixel_pitch_um * 1e-3)
        params = dict(fx=f, fy=f, cx=(w - 1) / 2 + self.pp_offset_px[0], cy=(h - 1) / 2 + self.pp_offset_px[1])
        params.update({k: float(v) for k, v in self.distortion.items()})
        return Camera("opencv", (w, h), params, pixel_pitch_um=self.pixel_pitch_um, name="synthetic-thermal")


@dataclass(eq=False)
class FramePlan:
    """One exposure: name, flight line, time, true pose (cam_from_world, world = CRS coordinates)."""

    name: str
    line: int
    index: int
    time_s: float
    pose: Any
    gnss_enh: np.ndarray


@dataclass
class SurveyScene:
    config: SurveyConfig
    terrain: Terrain
    camera: Any
    frames: list[FramePlan]
    gcps: dict[str, np.ndarray]
    checks: dict[str, np.ndarray]
    caster: HeightfieldCaster = field(repr=False, default=None)
    curve: FlirCurve = field(default_factory=FlirCurve)
    _rays: np.ndarray | None = field(default=None, repr=False)

    @property
    def ground_height_m(self) -> float:
        return float(np.median(self.terrain.dsm))

    def rays_cam(self) -> np.ndarray:
        """(H·W·S², 3) camera-frame rays of all sub-pixel samples (cached)."""
        if self._rays is None:
            from ._render import sample_offsets

            w, h = self.camera.image_size
            off = sample_offsets(self.config.supersample)
            oy, ox = np.meshgrid(off, off, indexing="ij")
            gy, gx = np.mgrid[0:h, 0:w].astype(np.float64)
            x = (gx[:, :, None] + ox.ravel()[None, None, :]).ravel()
            y = (gy[:, :, None] + oy.ravel()[None, None, :]).ravel()
            self._rays = unproject_fast(self.camera, np.stack([x, y], axis=1))
        return self._rays


def _gsd_footprint(cfg: SurveyConfig) -> tuple[float, float]:
    w, h = cfg.image_size
    k = cfg.pixel_pitch_um * 1e-6 / (cfg.focal_mm * 1e-3) * cfg.flight_height_m
    return w * k, h * k  # across, along


def _nadir_R(forward_xy: np.ndarray) -> np.ndarray:
    fwd = np.array([forward_xy[0], forward_xy[1], 0.0])
    fwd /= np.linalg.norm(fwd)
    y_cam = -fwd  # image down = backwards: image top points forward
    z_cam = np.array([0.0, 0.0, -1.0])
    x_cam = np.cross(y_cam, z_cam)
    return np.stack([x_cam, y_cam, z_cam])


def _small_rotation(rng, sigma_rad) -> np.ndarray:
    from ..geometry.rotations import matrix_from_axis_angle

    return matrix_from_axis_angle(rng.normal(0.0, sigma_rad, 3))


def _pick_markers(terrain: Terrain, n: int, rng, margin_m: float, taken: list) -> list[np.ndarray]:
    """Open, flat ground spots (grass/concrete/asphalt, slope < 5 %), spread out, away from the border."""
    names = [m.name for m in terrain.materials]
    ok_mat = {names.index(k) for k in ("grass", "concrete", "asphalt") if k in names}
    out = []
    for _ in range(4000):
        if len(out) >= n:
            break
        x = rng.uniform(margin_m, terrain.width_m - margin_m)
        y = rng.uniform(margin_m, terrain.height_m - margin_m)
        r, c = terrain.texture_index(np.array([x]), np.array([y]))
        rr = slice(max(r[0] - 25, 0), r[0] + 26)
        cc = slice(max(c[0] - 25, 0), c[0] + 26)
        if not set(np.unique(terrain.material[rr, cc]).tolist()) <= ok_mat:
            continue
        hs = terrain.height_at(np.array([x - 1.5, x + 1.5, x, x]), np.array([y, y, y - 1.5, y + 1.5]))
        if abs(hs[1] - hs[0]) > 0.15 or abs(hs[3] - hs[2]) > 0.15:
            continue
        min_sep = 0.35 * np.sqrt(terrain.width_m * terrain.height_m / max(n + len(taken), 1))
        if any(np.hypot(x - p[0], y - p[1]) < min_sep for p in out + taken):
            continue
        out.append(np.array([x, y]))
    return out


def make_survey(config: SurveyConfig | None = None) -> SurveyScene:
    """Build the scene and the flight plan (nothing rendered yet). Deterministic in ``config.seed``."""
    cfg = config or SurveyConfig()
    rng = np.random.default_rng([cfg.seed, 0x5E])
    terrain = make_terrain(cfg.terrain, seed=cfg.seed)
    cam = cfg.camera()
    across, along = _gsd_footprint(cfg)
    z_fly = float(np.median(terrain.dsm)) + cfg.flight_height_m
    W, H = terrain.width_m, terrain.height_m
    # footprints stay inside the DSM by a margin covering the attitude noise (3 sigma) + 1 m
    margin = cfg.flight_height_m * np.tan(3 * np.deg2rad(cfg.attitude_sigma_deg)) + 1.0
    if W - along - 2 * margin <= 0 or H - across - 2 * margin <= 0:
        raise ConfigError(
            f"terrain {W:g} x {H:g} m is too small for a {across:.1f} x {along:.1f} m footprint at "
            f"{cfg.flight_height_m:g} m (margin {margin:.1f} m); enlarge the terrain or fly lower"
        )
    # lines along x, spaced across (y), fitted inside [margin + across/2, H - margin - across/2]
    span_y = H - across - 2 * margin
    spacing_y = across * (1 - cfg.sidelap)
    n_lines = max(1, int(np.ceil(span_y / spacing_y)) + 1)
    spacing_y = span_y / (n_lines - 1) if n_lines > 1 else 0.0
    y0 = margin + across / 2 if n_lines > 1 else H / 2
    step = cfg.speed_mps / cfg.video_fps if cfg.video_fps else along * (1 - cfg.overlap)
    x_start, x_end = margin + along / 2, W - margin - along / 2
    n_along = max(1, int(np.floor((x_end - x_start) / step + 1e-9)) + 1)
    x_start = W / 2 - (n_along - 1) * step / 2  # centre the exposures on the line
    frames = []
    t = 0.0
    sig = np.deg2rad(cfg.attitude_sigma_deg)
    for li in range(n_lines):
        y = y0 + li * spacing_y
        forward = np.array([1.0, 0.0]) if li % 2 == 0 else np.array([-1.0, 0.0])
        xs = x_start + step * np.arange(n_along)
        if li % 2:
            xs = xs[::-1]
        R0 = _nadir_R(forward)
        for k, x in enumerate(xs):
            R = _small_rotation(rng, sig) @ R0
            C_local = np.array([x, y, z_fly + rng.normal(0, 0.3)])
            C = terrain.to_world(C_local)
            from ..geometry import Pose

            pose = Pose.from_center(R, C)
            gnss = C + rng.normal(0, 1, 3) * np.array([cfg.gnss_sigma_h_m, cfg.gnss_sigma_h_m, cfg.gnss_sigma_v_m])
            frames.append(FramePlan(f"T{len(frames):04d}", li, k, t, pose, gnss))
            t += step / cfg.speed_mps
        t += 20.0  # turn
        if cfg.max_frames is not None and len(frames) >= cfg.max_frames:
            break
    if cfg.max_frames is not None:
        frames = frames[: cfg.max_frames]
    # ground control: painted foil squares on open flat ground
    margin = max(across, along) * 0.3
    g_xy = _pick_markers(terrain, cfg.n_gcp, rng, margin, [])
    c_xy = _pick_markers(terrain, cfg.n_check, rng, margin, g_xy)
    if g_xy or c_xy:
        snapped = add_square_markers(terrain, np.array(g_xy + c_xy), cfg.marker_size_m)
        g_xy, c_xy = list(snapped[: len(g_xy)]), list(snapped[len(g_xy):])

    def to3d(xy):
        z = terrain.height_at(np.array([xy[0]]), np.array([xy[1]]))[0]
        return terrain.to_world(np.array([xy[0], xy[1], z]))

    gcps = {f"GCP{i + 1:02d}": to3d(p) for i, p in enumerate(g_xy)}
    checks = {f"CHK{i + 1:02d}": to3d(p) for i, p in enumerate(c_xy)}
    caster = HeightfieldCaster(terrain.dsm, terrain.dsm_cell_m, terrain.height_m)
    return SurveyScene(cfg, terrain, cam, frames, gcps, checks, caster)


def _emissivity_tables(terrain: Terrain, n_theta: int = 181) -> tuple[np.ndarray, np.ndarray]:
    th = np.linspace(0.0, np.pi / 2, n_theta)
    tab = np.empty((len(terrain.materials), n_theta))
    for i, m in enumerate(terrain.materials):
        f = fresnel_emissivity(th, m.refractive_index)
        tab[i] = m.emissivity * f / f[0]
    return th, tab


def _surface_normals(terrain: Terrain, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Unit normals (N, 3) of the bilinear DSM surface at local (x, y)."""
    dsm = terrain.dsm
    h, w = dsm.shape
    cell = terrain.dsm_cell_m
    u = np.clip(x / cell - 0.5, 0.0, w - 1.000001)
    v = np.clip((terrain.height_m - y) / cell - 0.5, 0.0, h - 1.000001)
    i = u.astype(np.intp)
    j = v.astype(np.intp)
    fu, fv = u - i, v - j
    a, b, c, d = dsm[j, i], dsm[j, i + 1], dsm[j + 1, i], dsm[j + 1, i + 1]
    dh_du = (b - a) + fv * (a - b - c + d)
    dh_dv = (c - a) + fu * (a - b - c + d)
    gx = dh_du / cell
    gy = -dh_dv / cell  # v grows southwards
    n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def render_frame(scene: SurveyScene, frame: FramePlan | int, *, with_truth: bool = False, sensor: bool = True) -> dict:
    """Render one frame.

    Returns
    -------
    dict with ``image_k`` (H, W) float32 apparent temperature; with ``with_truth``: ``signal`` (H, W),
    ``depth_m`` (H, W) camera-frame z of the surface at the pixel centre sample (NaN = sky),
    ``surface_temperature_k``, ``emissivity`` and ``angle_rad`` (H, W) at that sample.
    """
    fr = scene.frames[frame] if isinstance(frame, (int, np.integer)) else frame
    cfg, ter = scene.config, scene.terrain
    w, h = scene.camera.image_size
    ss2 = cfg.supersample**2
    rays = scene.rays_cam()
    R = fr.pose.R
    C = ter.to_local(fr.pose.center)
    d = np.einsum("...i,ij->...j", rays, R)  # R^T d per ray; einsum avoids BLAS threads for (N,3)@(3,3)
    pts, hit = _cast(scene, C, d)
    n = len(d)
    sig_sky = float(scene.curve.signal(cfg.sky_k))
    sig_air = float(scene.curve.signal(cfg.air_k))
    signal = np.full(n, sig_sky)
    ph = pts[hit]
    r_i, c_i = ter.texture_index(ph[:, 0], ph[:, 1])
    temp = ter.temperature_k[r_i, c_i].astype(np.float64)
    mat = ter.material[r_i, c_i]
    nrm = _surface_normals(ter, ph[:, 0], ph[:, 1])
    view = C[None, :] - ph
    dist = np.linalg.norm(view, axis=1)
    cos_t = np.clip(np.einsum("ij,ij->i", nrm, view) / dist, 0.0, 1.0)
    theta = np.arccos(cos_t)
    th_grid, tab = _emissivity_tables(ter)
    fi = theta / th_grid[-1] * (len(th_grid) - 1)
    i0 = np.minimum(fi.astype(np.intp), len(th_grid) - 2)
    fr_ = fi - i0
    eps = tab[mat, i0] * (1 - fr_) + tab[mat, i0 + 1] * fr_
    from ..radiometry.atmosphere import atmospheric_transmission

    tau = atmospheric_transmission(dist / 2.0, cfg.air_k, cfg.relative_humidity) ** 2
    signal[hit] = tau * (eps * scene.curve.signal(temp) + (1 - eps) * sig_sky) + (1 - tau) * sig_air
    sig_img = signal.reshape(h, w, ss2).mean(axis=2)
    k = next((i for i, f in enumerate(scene.frames) if f is fr), 0)
    rng = np.random.default_rng([cfg.seed, 0xF0, k])
    effects = cfg.sensor if sensor else SensorEffects()
    out = {"image_k": apply_sensor_effects(sig_img, scene.curve, effects, rng)}
    if with_truth:
        centre = np.arange(n).reshape(h, w, ss2)[:, :, ss2 // 2]
        full = lambda vals: _scatter(n, hit, vals)[centre]  # noqa: E731
        depth = (pts - C[None, :]) @ R.T
        out.update(
            signal=sig_img,
            depth_m=np.where(hit, depth[:, 2], np.nan)[centre],
            surface_temperature_k=full(temp),
            emissivity=full(eps),
            angle_rad=full(theta),
        )
    return out


def render_rgb_frame(scene: SurveyScene, pose, camera, *, noise_dn: float = 2.0, seed: int = 0,
                     sun=(0.35, -0.3, 0.89)) -> np.ndarray:
    """An RGB-like 8-bit image (H, W, 3) of the scene from ``pose`` with ``camera`` (one sample per pixel).

    Colour = an albedo per material, modulated by the fine structure of the temperature field (the same
    texture the thermal frames see, ±25 %), times Lambert shading by ``sun`` (world direction) plus 35 %
    ambient light; Gaussian noise of ``noise_dn`` (seeded). Sky: a flat blue. Not a radiometric model: a
    visible-band stand-in whose geometry is exact (the RGB camera of a rig, seed 002 §2.3).
    """
    ter = scene.terrain
    w, h = camera.image_size
    gy, gx = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = unproject_fast(camera, np.stack([gx.ravel(), gy.ravel()], axis=1))
    d = np.einsum("...i,ij->...j", rays, pose.R)
    C = ter.to_local(pose.center)
    pts, hit = _cast(scene, C, d)
    rgb = np.tile(np.array([150.0, 185.0, 225.0]), (len(d), 1))
    ph = pts[hit]
    r_i, c_i = ter.texture_index(ph[:, 0], ph[:, 1])
    mat = ter.material[r_i, c_i].astype(np.int64)
    temp = ter.temperature_k[r_i, c_i].astype(np.float64)
    rng_pal = np.random.default_rng(1234)
    palette = 60.0 + 150.0 * rng_pal.random((max(len(ter.materials), int(mat.max()) + 1), 3))
    base = np.array([m.base_temperature_k for m in ter.materials] + [300.0] * (len(palette) - len(ter.materials)))
    tex = np.clip((temp - base[mat]) / 4.0, -1.0, 1.0)
    nrm = _surface_normals(ter, ph[:, 0], ph[:, 1])
    sun = np.asarray(sun, float) / np.linalg.norm(sun)
    shade = 0.35 + 0.65 * np.clip(nrm @ sun, 0.0, 1.0)
    rgb[hit] = palette[mat] * (1.0 + 0.25 * tex)[:, None] * shade[:, None]
    rng = np.random.default_rng([scene.config.seed, 0x2B6, int(seed)])
    img = rgb.reshape(h, w, 3) + rng.normal(0.0, noise_dn, (h, w, 3))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _scatter(n, mask, vals):
    out = np.full(n, np.nan)
    out[mask] = vals
    return out


def _cast(scene, C_local, dirs):
    from .terrain import raycast_heightfield

    return raycast_heightfield(scene.terrain, C_local, dirs, caster=scene.caster)


_WORKER_SCENE = None


def _init_worker(scene, parent_pid=None):
    from .._procs import die_with_parent

    die_with_parent(parent_pid)  # a SIGKILLed demo must not leave rendering workers behind
    global _WORKER_SCENE
    _WORKER_SCENE = scene


def _render_in_worker(i):
    return render_frame(_WORKER_SCENE, i)["image_k"]


def render_frames(scene: SurveyScene, indices=None, *, threads: int = 2, on_frame: Callable | None = None,
                  mode: str = "process"):
    """Render frames (default all) in parallel; yields ``(index, image_k)`` in order.

    ``mode="process"`` (default): forked worker processes sharing the scene copy-on-write (POSIX; falls
    back to threads where ``fork`` is unavailable); ``mode="thread"``: a thread pool -- measured slower
    here (the ray caster's many medium-sized numpy operations contend for the GIL).
    """
    from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

    idx = list(range(len(scene.frames))) if indices is None else list(indices)
    scene.rays_cam()  # build the shared cache once, before the workers start
    if threads <= 1:
        for i in idx:
            img = render_frame(scene, i)["image_k"]
            if on_frame:
                on_frame(i)
            yield i, img
        return
    if mode not in ("thread", "process"):
        raise ConfigError(f"mode={mode!r}: expected 'thread' or 'process'")
    ex = None
    if mode == "process":
        import multiprocessing as mp

        if "fork" in mp.get_all_start_methods():
            ex = ProcessPoolExecutor(max_workers=int(threads), mp_context=mp.get_context("fork"),
                                     initializer=_init_worker, initargs=(scene, os.getpid()))
            submit = lambda k: ex.submit(_render_in_worker, k)  # noqa: E731
    if ex is None:
        ex = ThreadPoolExecutor(max_workers=int(threads))
        submit = lambda k: ex.submit(lambda j: render_frame(scene, j)["image_k"], k)  # noqa: E731
    with ex:
        futs = [(i, submit(i)) for i in idx]
        for i, f in futs:
            img = f.result()
            if on_frame:
                on_frame(i)
            yield i, img


def tie_points(scene: SurveyScene, n: int, *, seed: int = 0, min_views: int = 2) -> tuple[dict[str, np.ndarray], list]:
    """Random surface points (true 3D, CRS coordinates) and their exact, unoccluded image observations.

    Points are drawn uniformly over the terrain (away from the border by 2 m); those seen in fewer than
    ``min_views`` frames are dropped. Returns ``({name: (3,)}, [(image, name, x_px, y_px), ...])`` --
    the correspondences a feature matcher would ideally find, for testing orientation without matching.
    """
    ter = scene.terrain
    rng = np.random.default_rng([scene.config.seed, 0x71E, int(seed)])
    xy = np.c_[rng.uniform(2.0, ter.width_m - 2.0, n), rng.uniform(2.0, ter.height_m - 2.0, n)]
    P = ter.to_world(np.c_[xy, ter.height_at(xy[:, 0], xy[:, 1])])
    names = [f"TP{i:05d}" for i in range(n)]
    obs = _observations(scene, names, P)
    count: dict[str, int] = {}
    for _, nm, _, _ in obs:
        count[nm] = count.get(nm, 0) + 1
    keep = {nm for nm, c in count.items() if c >= min_views}
    pts = {nm: P[i] for i, nm in enumerate(names) if nm in keep}
    return pts, [o for o in obs if o[1] in keep]


def marker_observations(scene: SurveyScene) -> list[tuple[str, str, float, float]]:
    """(image, marker, x_px, y_px) for every marker visible (inside the image, not occluded) in every frame."""
    names = list(scene.gcps) + list(scene.checks)
    if not names:
        return []
    P = np.array([scene.gcps.get(k, scene.checks.get(k)) for k in names])
    return _observations(scene, names, P)


def _observations(scene: SurveyScene, names: list, P: np.ndarray) -> list[tuple[str, str, float, float]]:
    w, h = scene.camera.image_size
    K = scene.camera.K
    fov_x = 1.3 * (w / 2 + abs(K[0, 2] - (w - 1) / 2)) / K[0, 0]
    fov_y = 1.3 * (h / 2 + abs(K[1, 2] - (h - 1) / 2)) / K[1, 1]
    out = []
    for fr in scene.frames:
        pc = fr.pose.transform(P)
        with np.errstate(divide="ignore", invalid="ignore"):
            # inside 1.3x the field of view: a distortion polynomial can fold far-away points back in
            front = (pc[:, 2] > 0) & (np.abs(pc[:, 0] / pc[:, 2]) < fov_x) & (np.abs(pc[:, 1] / pc[:, 2]) < fov_y)
        if not front.any():
            continue
        xy = np.full((len(P), 2), np.nan)
        xy[front] = scene.camera.project(pc[front])
        ins = front & (xy[:, 0] >= 0) & (xy[:, 0] <= w - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= h - 1)
        if not ins.any():
            continue
        C = scene.terrain.to_local(fr.pose.center)
        Pl = scene.terrain.to_local(P[ins])
        pts, hit = _cast(scene, C, Pl - C[None, :])
        seen = hit & (np.linalg.norm(pts - Pl, axis=1) < 0.05)
        for k, s in zip(np.flatnonzero(ins), seen):
            if s:
                out.append((fr.name, names[k], float(xy[k, 0]), float(xy[k, 1])))
    return out


# ------------------------------------------------------------------------------------------- writing

def _csv_text(header, rows) -> str:
    buf = io.StringIO()
    wr = csv.writer(buf, lineterminator="\n")
    wr.writerow(header)
    wr.writerows(rows)
    return buf.getvalue()


def _geotiff_bytes(array: np.ndarray, transform, epsg: int, *, nodata=None, description: str = "") -> bytes:
    import rasterio
    from rasterio.io import MemoryFile

    arr = np.asarray(array)
    with MemoryFile() as mem:
        with mem.open(driver="GTiff", height=arr.shape[0], width=arr.shape[1], count=1, dtype=arr.dtype.name,
                      crs=rasterio.crs.CRS.from_epsg(int(epsg)), transform=transform, nodata=nodata, compress="deflate") as ds:
            ds.write(arr, 1)
            if description:
                ds.set_band_description(1, description)
        return mem.read()


class _VideoWriter:
    """Lossless 16-bit FFV1/Matroska in memory (PyAV)."""

    def __init__(self, fps: float):
        import av
        from fractions import Fraction

        self.buf = io.BytesIO()
        self.container = av.open(self.buf, mode="w", format="matroska")
        scale, offset = VIDEO_MAPPING
        self.container.metadata.update({"THERMOGRAMMETRY_SCALE": repr(scale), "THERMOGRAMMETRY_OFFSET": repr(offset),
                                        "THERMOGRAMMETRY_UNIT": "K", "THERMOGRAMMETRY_NODATA": "0"})
        self.rate = Fraction(float(fps)).limit_denominator(1000)
        self.stream = None
        self.pts: list[int] = []

    def add(self, image_k: np.ndarray, time_s: float) -> None:
        import av

        from ..radiometry.encoding import Uint16Mapping, encode_uint16

        h, w = image_k.shape
        if self.stream is None:
            self.stream = self.container.add_stream("ffv1", rate=self.rate)
            self.stream.width, self.stream.height, self.stream.pix_fmt = w, h, "gray16le"
        codes = encode_uint16(image_k, Uint16Mapping(*VIDEO_MAPPING))
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(codes), format="gray16le")
        pts = int(round(time_s * float(self.rate)))
        if self.pts and pts <= self.pts[-1]:
            pts = self.pts[-1] + 1
        frame.pts = pts
        self.pts.append(pts)
        for packet in self.stream.encode(frame):
            self.container.mux(packet)

    def finish(self) -> bytes:
        if self.stream is not None:
            for packet in self.stream.encode():
                self.container.mux(packet)
        self.container.close()
        return self.buf.getvalue()


def _latlon(epsg: int, enh: np.ndarray) -> tuple[float, float]:
    from pyproj import Transformer

    tr = Transformer.from_crs(int(epsg), 4326, always_xy=True)
    lon, lat = tr.transform(float(enh[0]), float(enh[1]))
    return lat, lon


VIDEO_MAPPING = (0.01, 150.0)  # (scale K/code, offset K): codes 1..65535 cover 150.01..805.35 K


def gimbal_angles(scene: SurveyScene) -> np.ndarray:
    """(N, 3) DJI gimbal yaw, pitch, roll (degrees) of the frames as :func:`write_survey` writes them: the true
    attitude turned by ``gimbal_tilt_deg`` and ``gimbal_sigma_deg`` noise (drawn from ``config.seed``, independent of
    every other draw of the scene)."""
    from ..geometry.rotations import matrix_from_axis_angle
    from ..geometry.attitude import gimbal_from_cam_from_world, meridian_convergence_deg

    from pyproj import Transformer

    cfg = scene.config
    rng = np.random.default_rng([cfg.seed, 0x61])
    n = len(scene.frames)
    # per frame: the common tilt + noise, one draw of 3 after the other (a world-frame turn of the camera)
    noise = np.array([rng.normal(0, cfg.gimbal_sigma_deg, 3) for _ in range(n)]).reshape(n, 3)
    e = np.r_[cfg.gimbal_tilt_deg, 0.0] + noise
    R = np.array([fr.pose.R for fr in scene.frames]).reshape(n, 3, 3) @ matrix_from_axis_angle(np.radians(e))
    C = np.array([fr.pose.center for fr in scene.frames]).reshape(n, 3)
    lon, lat = Transformer.from_crs(int(scene.terrain.epsg), 4326, always_xy=True).transform(C[:, 0], C[:, 1])
    g = meridian_convergence_deg(f"EPSG:{scene.terrain.epsg}", lon, lat)
    return np.column_stack(gimbal_from_cam_from_world(R, g))


def write_survey(project, scene: SurveyScene, *, prefix: str = "survey", threads: int = 2, write_jpeg: bool = False,
                 on_frame: Callable | None = None, mode: str = "process", write_video: bool | None = None,
                 n_tie_points: int = 0) -> dict:
    """Render all frames and write images + ground truth through ``project`` (see module docstring).

    ``write_video`` (default: when ``config.video_fps`` is set) also writes ``video/thermal.mkv``: the
    frames in flight order as lossless 16-bit FFV1 (``gray16le``), presentation time = exposure time,
    temperature = ``code * 0.01 + 150.0`` K (container metadata ``THERMOGRAMMETRY_SCALE``,
    ``THERMOGRAMMETRY_OFFSET``, ``THERMOGRAMMETRY_UNIT``; code 0 = no data), and ``video/frames.csv``
    (frame, pts, time_s, image). ``n_tie_points`` > 0 also writes ``truth/tie_points.csv`` and
    ``truth/tie_observations.csv`` (:func:`tie_points`: exact correspondences of random surface points).

    Returns a small summary dict (counts, seconds spent rendering).
    """
    import time

    from ..io.thermal import Geotag, ThermalMetadata
    from ..io.tiff import encode_temperature_tiff

    cfg, ter = scene.config, scene.terrain
    p = prefix.rstrip("/") + "/"
    t0 = time.perf_counter()
    lo, hi = None, None
    tr = ter.transform
    video = _VideoWriter(cfg.video_fps or 10.0) if (write_video if write_video is not None else cfg.video_fps) else None
    gimbal = gimbal_angles(scene)
    for i, img in render_frames(scene, threads=threads, on_frame=on_frame, mode=mode):
        if video is not None:
            video.add(img, scene.frames[i].time_s)
        fr = scene.frames[i]
        lat, lon = _latlon(ter.epsg, fr.gnss_enh)
        md = ThermalMetadata(make="thermogrammetry", model="synthetic", focal_length_mm=cfg.focal_mm,
                             pixel_pitch_um=(cfg.pixel_pitch_um, cfg.pixel_pitch_um),
                             geotag=Geotag(latitude_deg=lat, longitude_deg=lon, altitude_m=float(fr.gnss_enh[2]),
                                           gimbal_yaw_deg=float(gimbal[i, 0]), gimbal_pitch_deg=float(gimbal[i, 1]),
                                           gimbal_roll_deg=float(gimbal[i, 2])))
        data, _ = encode_temperature_tiff(img, metadata=md)
        project.write_bytes(f"{p}images/{fr.name}.tif", data)
        if write_jpeg:
            import cv2

            if lo is None:
                lo, hi = float(np.percentile(img, 0.5)) - 2.0, float(np.percentile(img, 99.5)) + 2.0
            u8 = np.clip((img - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)
            ok, jpg = cv2.imencode(".jpg", cv2.applyColorMap(u8, cv2.COLORMAP_INFERNO), [cv2.IMWRITE_JPEG_QUALITY, 92])
            project.write_bytes(f"{p}images_8bit/{fr.name}.jpg", jpg.tobytes())
    render_s = time.perf_counter() - t0
    if video is not None:
        project.write_bytes(f"{p}video/thermal.mkv", video.finish())
        project.write_text(f"{p}video/frames.csv", _csv_text(
            ["frame", "pts", "time_s", "image"],
            [[k, pts, f"{f.time_s:.4f}", f.name] for k, (pts, f) in enumerate(zip(video.pts, scene.frames))]))

    crs = f"EPSG:{ter.epsg}"
    project.write_json(f"{p}cameras.json", {
        "format": "thermogrammetry.synthetic.cameras/1",
        "crs": crs,
        "convention": "cam_from_world: X_cam = R X_world + t; world = CRS coordinates (m); pixel origin: OpenCV",
        "camera": scene.camera.to_dict(),
        "images": [{"name": f.name, "file": f"images/{f.name}.tif", "line": f.line, "time_s": f.time_s,
                    "R": f.pose.R.tolist(), "t": f.pose.t.tolist(), "center": f.pose.center.tolist()} for f in scene.frames],
    })
    project.write_text(f"{p}gnss.csv", _csv_text(
        ["name", "easting", "northing", "height", "sigma_h_m", "sigma_v_m", "time_s"],
        [[f.name, f"{f.gnss_enh[0]:.4f}", f"{f.gnss_enh[1]:.4f}", f"{f.gnss_enh[2]:.4f}", cfg.gnss_sigma_h_m, cfg.gnss_sigma_v_m, f"{f.time_s:.3f}"] for f in scene.frames]))
    for fname, pts in (("gcp.csv", scene.gcps), ("check.csv", scene.checks)):
        project.write_text(f"{p}{fname}", _csv_text(["name", "easting", "northing", "height"],
                                                    [[k, f"{v[0]:.4f}", f"{v[1]:.4f}", f"{v[2]:.4f}"] for k, v in pts.items()]))
    obs = marker_observations(scene)
    project.write_text(f"{p}gcp_observations.csv", _csv_text(["image", "name", "x_px", "y_px"],
                                                             [[a, b, f"{x:.4f}", f"{y:.4f}"] for a, b, x, y in obs]))
    if n_tie_points:
        tp, tobs = tie_points(scene, int(n_tie_points))
        project.write_text(f"{p}truth/tie_points.csv", _csv_text(["name", "easting", "northing", "height"],
                                                                 [[k, *(f"{c:.4f}" for c in v)] for k, v in tp.items()]))
        project.write_text(f"{p}truth/tie_observations.csv", _csv_text(["image", "name", "x_px", "y_px"],
                                                                       [[a, b, f"{x:.4f}", f"{y:.4f}"] for a, b, x, y in tobs]))
    project.write_text(f"{p}truth/points.csv", _csv_text(
        ["name", "type", "easting", "northing", "height"],
        [[k, "gcp", *(f"{c:.4f}" for c in v)] for k, v in scene.gcps.items()]
        + [[k, "check", *(f"{c:.4f}" for c in v)] for k, v in scene.checks.items()]))
    project.write_bytes(f"{p}truth/dsm.tif", _geotiff_bytes(ter.dsm.astype(np.float32), tr(ter.dsm_cell_m), ter.epsg, description="height (m)"))
    project.write_bytes(f"{p}truth/temperature.tif", _geotiff_bytes(ter.temperature_k, tr(ter.texture_cell_m), ter.epsg, description="surface temperature (K)"))
    project.write_bytes(f"{p}truth/emissivity.tif", _geotiff_bytes(ter.emissivity_table[ter.material].astype(np.float32), tr(ter.texture_cell_m), ter.epsg, description="normal emissivity"))
    scene_meta = {
        "format": "thermogrammetry.synthetic.survey/1",
        "crs": crs,
        "origin_en": list(ter.origin_en),
        "config": json.loads(json.dumps(cfg.to_dict(), default=lambda o: o.__dict__ if hasattr(o, "__dict__") else str(o))),
        "materials": [asdict(m) for m in ter.materials],
        "buildings": ter.buildings,
        "n_frames": len(scene.frames),
        "n_gcp": len(scene.gcps),
        "n_check": len(scene.checks),
        "n_marker_observations": len(obs),
        "signal_curve": asdict(scene.curve),
        "mode": "video" if cfg.video_fps else "frames",
    }
    project.write_json(f"{p}scene.json", scene_meta)
    return {"frames": len(scene.frames), "gcp": len(scene.gcps), "check": len(scene.checks),
            "marker_observations": len(obs), "render_seconds": round(render_s, 2)}
