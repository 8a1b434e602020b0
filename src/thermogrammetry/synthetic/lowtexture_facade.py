"""A low-texture thermal facade walk with exact ground truth: a plain plastered wall, a hand-held camera.

The hard case users report ("thermal images could not reconstruct any model"): a wall with only weak, smooth
thermal contrast, filmed by a hand-held (or pole-mounted) thermal camera walking along it at a few metres with
high forward overlap, no GNSS. Most of the fine texture in such frames is the sensor's own: the fixed pattern
(column stripes, per-pixel offsets) and the temporal noise, of the same order as the scene's contrast.

Scene (world frame: x along the facade, y into the building, z up; metres):

* the wall is the plane y = 0; its true temperature is ``wall_k`` + a gentle vertical gradient (0.05 K/m) + a
  smooth random field of standard deviation ``contrast_k`` (plaster with moisture, insulation joints: a weighted
  sum of Gaussian-filtered white noises, by default at 4, 12, 35 and 100 cm, stored on a 1 cm raster and
  interpolated bicubically);
* the ground is the plane z = 0 in front of the wall (y < 0), ``ground_offset_k`` colder, with its own field
  of ``ground_contrast_k``; the camera pitched ``pitch_deg`` down sees a strip of it at the bottom of the frames
  (depth variation: the scene is not one plane);
* surfaces are black bodies seen through no atmosphere, so the noise-free apparent temperature equals the true
  temperature (the radiometry is not what this scene tests).

Camera walk: ``n_frames`` stations along the wall at ``distance_m``, ``camera_height_m`` above the ground, spaced
so that consecutive frames overlap by ``overlap`` on the wall; hand-held jitter of the position (σ 3/8/4 cm
along/across/up) and of the attitude (yaw σ ``jitter_deg``, pitch and roll 0.75 of it), all drawn from ``seed``.

Rendering: ``supersample``² sub-pixel rays per pixel through the camera model (distortion included), exact
ray-plane intersections, band signal (FLIR curve) averaged over the pixel, then the sensor
(:func:`~thermogrammetry.synthetic.sensor.apply_sensor_effects`): PSF, fixed-pattern noise ``fpn_k`` (half
column stripes, half per-pixel offsets, the same in every frame) and temporal noise ``netd_k``.

Files (:func:`write_lowtexture_facade`, through a project store): ``frames/F000.tif`` ... (float32 kelvin, or
uint16 counts = round(100 K) with ``unit="counts"``; EXIF focal length and pixel pitch as a real camera writes
them), ``truth/camera.json`` (the true camera, readable by ``survey --camera``) and ``truth/poses.json`` (the camera and
every frame's true ``cam_from_world``). :func:`pose_errors`
compares an oriented block with the truth after a similarity transform.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..geometry.rotations import mean_rotation
from .._validate import config_keys

__all__ = ["LowTextureFacadeConfig", "LowTextureFacade", "make_lowtexture_facade", "render_lowtexture_frame",
           "write_lowtexture_facade", "pose_errors"]


@dataclass(frozen=True)
class LowTextureFacadeConfig:
    """Scene, camera walk and sensor of the low-texture facade sequence (lengths in m, temperatures in K).

    Attributes
    ----------
    n_frames : int
    overlap : float
        Forward overlap of consecutive frames on the wall (fraction of the frame width).
    distance_m, camera_height_m, pitch_deg : float
        Nominal distance to the wall, height above the ground, downward pitch of the camera.
    jitter_deg : float
        Hand-held attitude jitter (σ of the yaw; pitch and roll 0.75 of it).
    image_size : (w, h) ; focal_mm, pixel_pitch_um : float ; k1 : float
        Thermal camera (pinhole + radial k1, principal point 1.5 px right / 1 px up of the centre).
    wall_k, contrast_k : float
        Mean wall temperature and the standard deviation of its smooth random field.
    texture_scales_m, texture_weights : tuple of float
        The field is the weighted sum of white noises smoothed by Gaussians of these σ (m), each of unit std.
    ground_offset_k, ground_contrast_k : float
    fpn_k, netd_k, psf_sigma_px : float
        Sensor: fixed-pattern σ (K), temporal noise σ (K), optics blur σ (px).
    supersample : int
    seed : int
        Scene field and walk; the temporal noise of frame k is drawn from ``(seed, k)``.
    """

    n_frames: int = 30
    overlap: float = 0.8
    distance_m: float = 4.0
    camera_height_m: float = 1.6
    pitch_deg: float = 8.0
    jitter_deg: float = 2.0
    image_size: tuple = (640, 512)
    focal_mm: float = 13.0
    pixel_pitch_um: float = 17.0
    k1: float = -0.05
    wall_k: float = 284.0
    contrast_k: float = 0.15
    texture_scales_m: tuple = (0.04, 0.12, 0.35, 1.0)
    texture_weights: tuple = (0.15, 0.35, 0.6, 0.8)
    ground_offset_k: float = -1.5
    ground_contrast_k: float = 0.3
    fpn_k: float = 0.08
    netd_k: float = 0.04
    psf_sigma_px: float = 0.5
    supersample: int = 2
    seed: int = 0

    def __post_init__(self):
        if not (isinstance(self.n_frames, (int, np.integer)) and self.n_frames >= 2):
            raise ConfigError(f"LowTextureFacadeConfig.n_frames={self.n_frames!r}: expected an integer >= 2")
        if not 0 <= self.overlap < 1:
            raise ConfigError(f"LowTextureFacadeConfig.overlap={self.overlap!r}: expected a fraction in [0, 1)")
        for f in ("distance_m", "camera_height_m", "focal_mm", "pixel_pitch_um"):
            v = float(getattr(self, f))
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"LowTextureFacadeConfig.{f}={getattr(self, f)!r}: expected a positive number")
        for f in ("contrast_k", "ground_contrast_k", "fpn_k", "netd_k", "psf_sigma_px", "jitter_deg"):
            v = float(getattr(self, f))
            if not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"LowTextureFacadeConfig.{f}={getattr(self, f)!r}: expected a number >= 0")
        if len(self.image_size) != 2 or min(self.image_size) < 32:
            raise ConfigError(f"LowTextureFacadeConfig.image_size={self.image_size!r}: expected (w, h), both >= 32")

    @classmethod
    def from_dict(cls, d: dict) -> "LowTextureFacadeConfig":
        return cls(**config_keys(cls, d))


@dataclass
class LowTextureFacade:
    """The scene: its configuration, the camera, the true poses and the temperature rasters.

    Attributes
    ----------
    config : LowTextureFacadeConfig
    camera : thermogrammetry.Camera
    poses : list of Pose, ``cam_from_world`` of every frame
    names : list of str, frame names (``F000`` ...)
    wall : (Hw, Ww) float32 K, wall raster (row k: z = wall_z0 + k·step, column j: x = wall_x0 + j·step)
    ground : (Hg, Wg) float32 K, ground raster (row k: y = ground_y0 + k·step, column j: x = wall_x0 + j·step)
    """

    config: LowTextureFacadeConfig
    camera: object
    poses: list
    names: list
    wall: np.ndarray
    ground: np.ndarray
    x0: float
    wall_step: float
    ground_y0: float
    ground_step: float

    def wall_temperature(self, x, z) -> np.ndarray:
        """True wall temperature (K) at facade coordinates (x along, z up), any shape."""
        from scipy.ndimage import map_coordinates

        x = np.asarray(x, float)
        z = np.asarray(z, float)
        c = np.stack([z.ravel() / self.wall_step, (x.ravel() - self.x0) / self.wall_step])
        v = map_coordinates(self.wall, c, order=3, mode="nearest")
        return (v + 0.05 * z.ravel()).reshape(x.shape)

    def ground_temperature(self, x, y) -> np.ndarray:
        """True ground temperature (K) at (x, y), y < 0 in front of the wall, any shape."""
        from scipy.ndimage import map_coordinates

        x = np.asarray(x, float)
        y = np.asarray(y, float)
        c = np.stack([(y.ravel() - self.ground_y0) / self.ground_step, (x.ravel() - self.x0) / self.ground_step])
        return map_coordinates(self.ground, c, order=3, mode="nearest").reshape(x.shape)


def _field(rng, shape, step_m, scales_m, weights) -> np.ndarray:
    """Zero-mean, unit-std smooth random field: a weighted sum of Gaussian-filtered white noises (one per scale,
    each of unit std; filtered in the Fourier domain, so the field is periodic over the raster)."""
    from scipy.ndimage import fourier_gaussian

    out = np.zeros(shape, np.float64)
    for s, w in zip(scales_m, weights):
        a = np.fft.irfft2(fourier_gaussian(np.fft.rfft2(rng.standard_normal(shape)), s / step_m, n=shape[1]), s=shape)
        out += w * a / max(a.std(), 1e-12)
    out -= out.mean()
    return out / max(out.std(), 1e-12)


def make_lowtexture_facade(config: LowTextureFacadeConfig | None = None) -> LowTextureFacade:
    """Build the camera, the walk and the temperature rasters (deterministic for a configuration)."""
    from ..camera import Camera
    from ..geometry import Pose
    from ..geometry.rotations import matrix_from_axis_angle

    c = config or LowTextureFacadeConfig()
    rng = np.random.default_rng([int(c.seed), 0x10E7])
    w, h = (int(v) for v in c.image_size)
    f = c.focal_mm / (c.pixel_pitch_um * 1e-3)
    cam = Camera("opencv", (w, h), dict(fx=f, fy=f, cx=(w - 1) / 2 + 1.5, cy=(h - 1) / 2 - 1.0, k1=c.k1),
                 pixel_pitch_um=c.pixel_pitch_um, name="lowtexture-thermal")
    foot = c.distance_m * w / f  # frame width on the wall (m)
    step = (1.0 - c.overlap) * foot
    length = 4.0 + foot + step * (c.n_frames - 1) + 4.0
    # rasters: the wall (1 cm) up to a height the frames cannot reach, the ground (2 cm) in front of it
    ws = 0.01
    top = c.camera_height_m + c.distance_m * 1.5 + 1.0
    wall = _field(rng, (int(np.ceil(top / ws)) + 1, int(np.ceil(length / ws)) + 1), ws, c.texture_scales_m, c.texture_weights)
    wall = (c.wall_k + c.contrast_k * wall).astype(np.float32)
    gs = 0.02
    gy0 = -(c.distance_m + 3.0)
    ground = _field(rng, (int(np.ceil(-gy0 / gs)) + 1, int(np.ceil(length / gs)) + 1), gs, (0.03, 0.1, 0.4), (0.3, 0.5, 0.8))
    ground = (c.wall_k + c.ground_offset_k + c.ground_contrast_k * ground).astype(np.float32)
    poses, names = [], []
    x_start = 4.0 + foot / 2
    jit = np.deg2rad(c.jitter_deg)
    for k in range(c.n_frames):
        C = np.array([x_start + k * step + rng.normal(0, 0.03), -c.distance_m + rng.normal(0, 0.08),
                      c.camera_height_m + rng.normal(0, 0.04)])
        yaw, pitch, roll = rng.normal(0, jit), -np.deg2rad(c.pitch_deg) + rng.normal(0, 0.75 * jit), rng.normal(0, 0.75 * jit)
        fwd = np.array([np.sin(yaw) * np.cos(pitch), np.cos(yaw) * np.cos(pitch), np.sin(pitch)])
        p = Pose.look_at(C, C + fwd, up=(0.0, 0.0, 1.0))
        Rr = matrix_from_axis_angle(np.array([0.0, 0.0, roll]))  # roll about the viewing axis (camera z)
        poses.append(Pose(Rr @ p.R, Rr @ p.t))
        names.append(f"F{k:03d}")
    return LowTextureFacade(c, cam, poses, names, wall, ground, 0.0, ws, gy0, gs)


def render_lowtexture_frame(scene: LowTextureFacade, k: int, *, sensor: bool = True) -> np.ndarray:
    """Apparent temperature (float32 K, (h, w)) of frame ``k``; ``sensor=False``: noise-free, no pattern, no blur."""
    from ._render import iter_sample_rays
    from .radiance import FlirCurve
    from .sensor import SensorEffects, apply_sensor_effects

    c = scene.config
    pose = scene.poses[k]
    C = pose.center
    w, h = scene.camera.image_size
    curve = FlirCurve()
    sig = np.empty((h, w))
    for rows, rays in iter_sample_rays(scene.camera, c.supersample):
        d = np.einsum("...i,ij->...j", rays, pose.R)  # world directions (rows, w, S, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            tw = np.where(d[..., 1] > 0, -C[1] / d[..., 1], np.inf)
            tg = np.where(d[..., 2] < 0, -C[2] / d[..., 2], np.inf)
        on_wall = tw <= tg
        t = np.minimum(tw, tg)
        if not np.all(np.isfinite(t)):
            raise ConfigError("LowTextureFacadeConfig: a ray sees neither the wall nor the ground (pitch the camera "
                              "towards the wall)")
        P = C + t[..., None] * d
        T = np.where(on_wall, scene.wall_temperature(P[..., 0], P[..., 2]), scene.ground_temperature(P[..., 0], P[..., 1]))
        sig[rows] = np.asarray(curve.signal(T)).mean(axis=-1)
    eff = SensorEffects(psf_sigma_px=c.psf_sigma_px, netd_k=c.netd_k, fpn_k=c.fpn_k, fpn_seed=int(c.seed) + 11) if sensor \
        else SensorEffects()
    return apply_sensor_effects(sig, curve, eff, np.random.default_rng([int(c.seed), int(k), 0x7E]))


def write_lowtexture_facade(project, scene: LowTextureFacade, *, unit: str = "K", prefix: str = "") -> dict:
    """Render every frame and write ``<prefix>frames/<name>.tif`` and ``<prefix>truth/poses.json`` through ``project``.

    ``unit="K"``: float32 kelvin TIFFs; ``"counts"``: uint16 TIFFs of round(100 · K) labelled as raw counts (a
    16-bit sensor's frames). Both carry the EXIF focal length and pixel pitch.
    """
    from ..io.thermal import ThermalMetadata
    from ..io.tiff import encode_counts_tiff, encode_temperature_tiff

    if unit not in ("K", "counts"):
        raise ConfigError(f"unit={unit!r}: expected 'K' or 'counts'")
    c = scene.config
    p = prefix.rstrip("/") + "/" if prefix else ""
    md = ThermalMetadata(make="synthetic", model="lowtexture-facade", focal_length_mm=float(c.focal_mm),
                         pixel_pitch_um=(float(c.pixel_pitch_um), float(c.pixel_pitch_um)))
    for k, name in enumerate(scene.names):
        img = render_lowtexture_frame(scene, k)
        if unit == "K":
            data, _ = encode_temperature_tiff(img, metadata=md)
        else:
            data = encode_counts_tiff(np.clip(np.round(img.astype(np.float64) * 100.0), 0, 65535).astype(np.uint16), metadata=md)
        project.write_bytes(f"{p}frames/{name}.tif", data)
    project.write_json(f"{p}truth/camera.json", scene.camera.to_dict())  # as `calibrate` writes it (for --camera)
    project.write_json(f"{p}truth/poses.json", {
        "format": "thermogrammetry.synthetic.lowtexture_facade/1",
        "convention": "cam_from_world: X_cam = R X_world + t; world: x along the wall, y into the building, z up (m)",
        "camera": scene.camera.to_dict(),
        "images": [{"name": n, "R": q.R.tolist(), "t": q.t.tolist(), "center": q.center.tolist()}
                   for n, q in zip(scene.names, scene.poses)],
    })
    return {"frames": len(scene.names), "unit": unit}


def pose_errors(truth: dict, estimate: dict) -> dict:
    """Oriented poses against the truth after the best similarity transform of the block.

    The rotation of the similarity is the chordal mean of ``R_trueᵀ R_est`` over the images (projected on SO(3)); scale
    and translation then fit the centres (least squares). A walk along a wall has its centres nearly on a line, which
    leaves the rotation about that line undetermined by the centres alone (Umeyama on the centres would report
    any roll of the whole block as a rotation error of every image).

    Parameters
    ----------
    truth, estimate : dict name -> (R (3, 3), t (3,)) ``cam_from_world``
        ``estimate`` holds the images of ONE oriented block (its own datum); names missing from the truth are
        ignored.

    Returns
    -------
    dict
        ``n``, ``names``; ``scale`` (estimate -> truth); ``center_err_m`` (n,) after the transform; ``extent_m``
        (largest distance between true centres of the block); ``center_rms_rel`` = RMS centre error / extent;
        ``rot_err_deg`` (n,) = angle of ``R_true · (R_est · Qᵀ)ᵀ``. ``n < 3``: errors empty, ratios NaN.
    """
    names = [n for n in estimate if n in truth]
    out = {"n": len(names), "names": names, "scale": float("nan"), "center_err_m": np.zeros(0), "rot_err_deg": np.zeros(0),
           "extent_m": float("nan"), "center_rms_rel": float("nan")}
    if len(names) < 3:
        return out

    def centre(R, t):
        return -np.asarray(R).T @ np.asarray(t)

    Rt = [np.asarray(truth[n][0], float) for n in names]
    Re = [np.asarray(estimate[n][0], float) for n in names]
    # X_true = s Q X_est + q  =>  R_est = R_true Q  (cam_from_world), so Q ~ mean of R_trueᵀ R_est
    Q = mean_rotation([a.T @ b for a, b in zip(Rt, Re)])
    Ct = np.array([centre(*truth[n]) for n in names])
    Ce = np.array([centre(*estimate[n]) for n in names])
    A, B = Ct - Ct.mean(0), (Ce - Ce.mean(0)) @ Q.T
    s = float(np.sum(A * B) / max(np.sum(B * B), 1e-300))
    err = np.linalg.norm(s * B - A, axis=1)
    rot = [np.degrees(np.arccos(np.clip((np.trace(a @ Q @ b.T) - 1) / 2, -1, 1))) for a, b in zip(Rt, Re)]
    ext = float(max(np.linalg.norm(Ct[a] - Ct[b]) for a in range(len(Ct)) for b in range(a + 1, len(Ct))))
    out.update(scale=s, center_err_m=err, rot_err_deg=np.array(rot), extent_m=ext,
               center_rms_rel=float(np.sqrt(np.mean(err ** 2)) / ext) if ext > 0 else float("nan"))
    return out
