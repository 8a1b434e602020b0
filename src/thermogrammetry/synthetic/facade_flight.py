"""A close-range UAV thermal facade flight with exact ground truth, written as a small drone's palette JPEGs.

The case users report as "could not reconstruct any model": a consumer thermal drone (the DJI Mavic 2 Enterprise Dual:
a 160x120 microbolometer delivered upscaled to 640x480, ~57° horizontal field of view, a wide lens with strong barrel
distortion) flown a few metres in front of an old brick facade with rows of identical windows; the frames are 8-bit
JPEGs rendered through a colour palette with a per-frame automatic range (AGC), with no radiometric data and no focal
length in EXIF, and the positions of a consumer GNSS (metres) in the EXIF GPS tags.

Scene (world frame: x along the facade, y into the building, z up; metres):

* the wall is the plane y = 0, brick in running bond: bricks ``brick_m`` (0.25 x 0.065 m) with ``joint_m`` mortar
  joints; every brick has its own temperature offset (σ ``brick_k``), the joints are ``mortar_k`` warmer (or colder,
  negative), and a smooth field (moisture, thermal bridges; σ ``field_k`` at 0.3-1.5 m scales) lies over all of it;
* a grid of identical windows (``window_size_m``, ``window_period_m`` apart, ``window_rows`` x as many columns as the
  wall needs): a frame ``frame_m`` wide ``frame_k`` warmer than the wall around glass recessed ``recess_m`` into
  the wall, the glass reflecting the cold sky (``glass_k``, with a gentle vertical gradient) and a mullion;
* downpipes: vertical strips ``pipe_k`` colder at ``pipe_x_m`` (not periodic: they break the windows' repetition
  for a human, as on a real facade);
* black bodies through no atmosphere (the radiometry is not what this scene tests).

Camera: an OpenCV model at the output size (640x480), focal length such that the horizontal field of view *with*
the distortion is ``hfov_deg``, radial ``k1``, ``k2``, principal point 2 px right / 1.5 px up of the centre. The frame
is integrated at the native resolution (each native pixel is the average of its ``upscale`` x ``upscale`` output
pixels, each of them ``supersample``² rays), the native sensor adds its PSF, fixed pattern and temporal noise, and the
native frame is upscaled bilinearly to the output size (the blur of an upscaled core). Native pixel i covers output
pixels ``upscale·i .. upscale·i + upscale − 1``: the upscaling is centre-aligned, the geometry is the output camera's.

Flight: horizontal strips (a lawnmower pattern: alternate strips flown in opposite directions) at ``distance_m`` from
the wall (each strip's distance drawn from ``distance_jitter_m``), the camera looking at the wall, spaced for
``overlap`` forward and ``sidelap`` between strips; the UAV's position jitter (σ 5 cm) and attitude jitter (σ
``jitter_deg``). GNSS (EXIF GPS): the true centre + a constant bias (σ ``gnss_bias_m`` per horizontal axis, 1.5x
vertically) + a slowly wandering error (AR(1), σ ``gnss_wander_m``, correlation 0.9 from one frame to the next),
in geographic coordinates around ``origin_latlon`` with the facade facing ``facade_azimuth_deg``.

Files (:func:`write_facade_flight`, through a project store): ``<prefix>frames/DJI_0001_T.jpg`` ... (8-bit RGB
JPEG through the ``iron`` palette, per-frame 1-99 % AGC, EXIF Make ``DJI``, Model ``model``, GPS, date; no focal
length, no radiometric block), ``<prefix>truth/camera.json`` and ``<prefix>truth/poses.json`` (the camera and every
frame's true ``cam_from_world``, the wall distance). Score an oriented block with
:func:`thermogrammetry.synthetic.lowtexture_facade.pose_errors`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from .._validate import config_keys

__all__ = ["FacadeFlightConfig", "FacadeFlight", "make_facade_flight", "render_facade_flight_frame",
           "facade_flight_frame_8bit", "write_facade_flight", "wall_temperature", "IRON_PALETTE"]


def _iron_lut() -> np.ndarray:
    """(256, 3) uint8: an 'iron' (ironbow) palette, black -> indigo -> magenta -> orange -> yellow -> white."""
    keys = np.array([0.0, 0.12, 0.3, 0.5, 0.7, 0.87, 1.0])
    cols = np.array([[0, 0, 0], [28, 0, 100], [120, 10, 150], [210, 50, 80], [245, 130, 10], [255, 210, 40],
                     [255, 255, 235]], float)
    g = np.linspace(0.0, 1.0, 256)
    return np.round(np.stack([np.interp(g, keys, cols[:, c]) for c in range(3)], axis=1)).astype(np.uint8)


#: the iron palette of the JPEGs (index = display number after the AGC)
IRON_PALETTE = _iron_lut()


@dataclass(frozen=True)
class FacadeFlightConfig:
    """Wall, windows, camera, flight and GNSS of the facade flight (lengths in m, temperatures in K, angles in deg).

    Attributes
    ----------
    n_strips, n_per_strip : int
        Horizontal strips and frames per strip.
    overlap, sidelap : float
        Forward overlap of consecutive frames and overlap of neighbouring strips on the wall (fractions).
    distance_m, distance_jitter_m : float
        Nominal distance to the wall; each strip's distance is drawn uniformly within ± the jitter.
    bottom_m : float
        Height of the lowest frame's bottom edge on the wall.
    jitter_deg : float
        Attitude jitter (σ of yaw, pitch and roll).
    image_size, native_size : (w, h)
        Output (upscaled) and native sensor sizes; their ratio must be an integer.
    hfov_deg, k1, k2 : float
        Horizontal field of view including the distortion, radial distortion of the OpenCV model.
    wall_k, brick_k, mortar_k, field_k : float
    brick_m, joint_m : (length, height) and joint width
    window_size_m, window_period_m : (w, h)
    window_rows, window_z0_m, window_x0_m : int, float, float
        Rows of windows, sill height of the first row, left edge of the first column.
    frame_m, frame_k, recess_m, glass_k : float
    pipe_x_m : tuple of float ; pipe_k, pipe_width_m : float
    fpn_k, netd_k, psf_sigma_px : float
        Native sensor: fixed pattern, temporal noise, optics blur (native px).
    supersample : int
        Rays per output pixel per axis.
    gnss_bias_m, gnss_wander_m : float
    origin_latlon : (lat, lon) ; origin_alt_m, facade_azimuth_deg : float
    make, model : str
        EXIF Make and Model (the files' camera names).
    jpeg_quality : int
    seed : int
    """

    n_strips: int = 5
    n_per_strip: int = 10
    overlap: float = 0.75
    sidelap: float = 0.7
    distance_m: float = 3.0
    distance_jitter_m: float = 0.5
    bottom_m: float = 0.8
    jitter_deg: float = 1.5
    image_size: tuple = (640, 480)
    native_size: tuple = (160, 120)
    hfov_deg: float = 57.0
    k1: float = -0.35
    k2: float = 0.06
    wall_k: float = 281.0
    brick_k: float = 0.35
    mortar_k: float = 0.5
    field_k: float = 0.6
    brick_m: tuple = (0.25, 0.065)
    joint_m: float = 0.012
    window_size_m: tuple = (1.0, 1.45)
    window_period_m: tuple = (2.2, 3.0)
    window_rows: int = 3
    window_z0_m: float = 1.0
    window_x0_m: float = 0.9
    frame_m: float = 0.07
    frame_k: float = 1.5
    recess_m: float = 0.15
    glass_k: float = -9.0
    pipe_x_m: tuple = (4.45, 11.1)
    pipe_k: float = -1.2
    pipe_width_m: float = 0.1
    fpn_k: float = 0.05
    netd_k: float = 0.05
    psf_sigma_px: float = 0.5
    supersample: int = 1
    gnss_bias_m: float = 2.5
    gnss_wander_m: float = 1.0
    origin_latlon: tuple = (47.3769, 8.5417)
    origin_alt_m: float = 420.0
    facade_azimuth_deg: float = 30.0
    make: str = "DJI"
    model: str = "M2ED"
    jpeg_quality: int = 90
    seed: int = 0

    def __post_init__(self):
        for f in ("n_strips", "n_per_strip", "window_rows", "supersample", "seed"):
            v = getattr(self, f)
            if not (isinstance(v, (int, np.integer)) and v >= (0 if f == "seed" else 1)):
                raise ConfigError(f"FacadeFlightConfig.{f}={v!r}: expected a positive integer")
        if self.n_strips * self.n_per_strip < 2:
            raise ConfigError("FacadeFlightConfig: expected at least 2 frames (n_strips x n_per_strip)")
        for f in ("overlap", "sidelap"):
            if not 0 <= getattr(self, f) < 1:
                raise ConfigError(f"FacadeFlightConfig.{f}={getattr(self, f)!r}: expected a fraction in [0, 1)")
        if not 0 <= self.distance_jitter_m < self.distance_m:
            raise ConfigError(f"FacadeFlightConfig.distance_jitter_m={self.distance_jitter_m!r}: expected 0 <= "
                              f"jitter < distance_m={self.distance_m!r}")
        if not 10.0 < self.hfov_deg < 150.0:
            raise ConfigError(f"FacadeFlightConfig.hfov_deg={self.hfov_deg!r}: expected 10..150 degrees")
        (w, h), (nw, nh) = self.image_size, self.native_size
        if w % nw or h % nh or w // nw != h // nh:
            raise ConfigError(f"FacadeFlightConfig: image_size {self.image_size!r} must be one integer multiple of "
                              f"native_size {self.native_size!r}")
        if not 1 <= int(self.jpeg_quality) <= 100:
            raise ConfigError(f"FacadeFlightConfig.jpeg_quality={self.jpeg_quality!r}: expected 1..100")

    @property
    def upscale(self) -> int:
        return int(self.image_size[0] // self.native_size[0])

    @classmethod
    def from_dict(cls, d: dict) -> "FacadeFlightConfig":
        return cls(**config_keys(cls, d))


@dataclass
class FacadeFlight:
    """The flight: configuration, camera, true poses, names, per-frame wall distance, GNSS (lat, lon, alt),
    the brick table and the smooth field raster."""

    config: FacadeFlightConfig
    camera: object
    poses: list
    names: list
    distances: np.ndarray
    gnss: np.ndarray
    bricks: np.ndarray
    field: np.ndarray
    field_step: float


def _focal_for_hfov(hfov_deg: float, k1: float, k2: float, half_width_px: float) -> float:
    """Focal length (px) that puts a ray ``hfov/2`` off-axis (horizontally) at the image edge through the radial
    distortion: f = (w/2) / (x (1 + k1 x² + k2 x⁴)), x = tan(hfov/2)."""
    x = np.tan(np.radians(hfov_deg) / 2.0)
    xd = x * (1.0 + k1 * x * x + k2 * x ** 4)
    if not xd > 0:
        raise ConfigError(f"FacadeFlightConfig: k1={k1!r}, k2={k2!r} fold the image edge of a {hfov_deg}° lens")
    return half_width_px / xd


def make_facade_flight(config: FacadeFlightConfig | None = None) -> FacadeFlight:
    """Build the camera, the flight, the GNSS and the wall's random tables (deterministic for a configuration)."""
    from ..camera import Camera
    from ..geometry import Pose
    from ..geometry.rotations import matrix_from_axis_angle
    from .lowtexture_facade import _field

    c = config or FacadeFlightConfig()
    rng = np.random.default_rng([int(c.seed), 0xFAC4])
    w, h = (int(v) for v in c.image_size)
    f = _focal_for_hfov(c.hfov_deg, c.k1, c.k2, w / 2.0)
    cam = Camera("opencv", (w, h), dict(fx=f, fy=f, cx=(w - 1) / 2 + 2.0, cy=(h - 1) / 2 - 1.5, k1=c.k1, k2=c.k2),
                 pixel_pitch_um=12.0 * c.native_size[0] / w, name="facade-flight-thermal")
    # footprint on the wall at the nominal distance (the undistorted field: tan of the half angles)
    fw = 2.0 * c.distance_m * np.tan(np.radians(c.hfov_deg) / 2.0)
    fh = fw * h / w
    step_x, step_z = (1.0 - c.overlap) * fw, (1.0 - c.sidelap) * fh
    x_start = 0.5 + fw / 2.0
    poses, names, dist = [], [], []
    jit = np.radians(c.jitter_deg)
    for s in range(c.n_strips):
        d_strip = c.distance_m + rng.uniform(-c.distance_jitter_m, c.distance_jitter_m)
        z = c.bottom_m + fh / 2.0 + s * step_z
        order = range(c.n_per_strip) if s % 2 == 0 else range(c.n_per_strip - 1, -1, -1)
        for k in order:
            C = np.array([x_start + k * step_x, -d_strip, z]) + rng.normal(0.0, 0.05, 3)
            yaw, pitch, roll = rng.normal(0.0, jit, 3)
            fwd = np.array([np.sin(yaw) * np.cos(pitch), np.cos(yaw) * np.cos(pitch), np.sin(pitch)])
            p = Pose.look_at(C, C + fwd, up=(0.0, 0.0, 1.0))
            Rr = matrix_from_axis_angle(np.array([0.0, 0.0, roll]))
            poses.append(Pose(Rr @ p.R, Rr @ p.t))
            names.append(f"DJI_{len(names) + 1:04d}_T")
            dist.append(-C[1])
    # wall tables: one temperature offset per brick, a smooth field on a 5 cm raster (periodic, 0.3-1.5 m)
    length = x_start * 2 + step_x * (c.n_per_strip - 1) + fw + 2.0
    top = c.bottom_m + fh + step_z * (c.n_strips - 1) + fh + 2.0
    pitch_x, pitch_z = c.brick_m[0] + c.joint_m, c.brick_m[1] + c.joint_m
    bricks = rng.normal(0.0, 1.0, (int(top / pitch_z) + 4, int(length / pitch_x) + 4))
    fs = 0.05
    field = _field(rng, (int(top / fs) + 2, int(length / fs) + 2), fs, (0.3, 0.7, 1.5), (0.3, 0.6, 0.8))
    # GNSS: bias + AR(1) wander (ENU in the facade frame, then geographic)
    n = len(poses)
    bias = rng.normal(0.0, c.gnss_bias_m, 3) * [1.0, 1.0, 1.5]
    wander = np.zeros((n, 3))
    rho = 0.9
    e = rng.normal(0.0, c.gnss_wander_m, (n, 3)) * [1.0, 1.0, 1.5]
    wander[0] = e[0]
    for k in range(1, n):
        wander[k] = rho * wander[k - 1] + np.sqrt(1 - rho * rho) * e[k]
    centres = np.array([p.center for p in poses])
    gnss = _to_latlon(c, centres + bias + wander)
    return FacadeFlight(c, cam, poses, names, np.array(dist), gnss, bricks, field.astype(np.float32), fs)


def _to_latlon(c: FacadeFlightConfig, P) -> np.ndarray:
    """(N, 3) facade-frame points -> (N, 3) latitude, longitude (deg), ellipsoidal height (m): the facade's x axis
    points to ``facade_azimuth_deg`` − 90° (the facade faces its azimuth: the camera looks along −azimuth), small-area
    spherical approximation (R = 6,378,137 m)."""
    a = np.radians(c.facade_azimuth_deg)
    # y (into the building) points opposite to the facade's outward normal (azimuth a): east/north of the axes
    ex = np.array([np.sin(a - np.pi / 2), np.cos(a - np.pi / 2)])
    ey = -np.array([np.sin(a), np.cos(a)])
    P = np.asarray(P, float)
    en = P[:, :1] * ex + P[:, 1:2] * ey
    R = 6378137.0
    lat0, lon0 = np.radians(c.origin_latlon[0]), np.radians(c.origin_latlon[1])
    lat = np.degrees(lat0 + en[:, 1] / R)
    lon = np.degrees(lon0 + en[:, 0] / (R * np.cos(lat0)))
    return np.stack([lat, lon, c.origin_alt_m + P[:, 2]], axis=1)


def wall_temperature(scene: FacadeFlight, x, z) -> np.ndarray:
    """True temperature (K) of the wall plane y = 0 at (x, z), any shape: bricks, joints, field, window frames and
    downpipes (the window openings themselves are handled by the renderer: glass and reveals lie behind the plane)."""
    from scipy.ndimage import map_coordinates

    c = scene.config
    x = np.asarray(x, float)
    z = np.asarray(z, float)
    px, pz = c.brick_m[0] + c.joint_m, c.brick_m[1] + c.joint_m
    course = np.floor(z / pz).astype(int)
    xs = x + 0.5 * px * (course % 2)
    col = np.floor(xs / px).astype(int)
    joint = ((xs - col * px) > c.brick_m[0]) | ((z - course * pz) > c.brick_m[1])
    nb = scene.bricks.shape
    T = c.wall_k + c.brick_k * scene.bricks[np.clip(course, 0, nb[0] - 1), np.clip(col, 0, nb[1] - 1)]
    T = np.where(joint, c.wall_k + c.mortar_k, T)
    cc = np.stack([np.clip(z, 0, None).ravel() / scene.field_step, np.clip(x, 0, None).ravel() / scene.field_step])
    T = T + c.field_k * map_coordinates(scene.field, cc, order=1, mode="nearest").reshape(x.shape)
    # window frames: a band frame_m wide around each opening, in the wall plane
    u, v, inside, _ = _window_coords(c, x, z, c.frame_m)
    T = np.where(inside, c.wall_k + c.frame_k, T)
    for xp in c.pipe_x_m:
        T = np.where(np.abs(x - xp) < c.pipe_width_m / 2, c.wall_k + c.pipe_k + 0.2 * np.sin(z * 3.0), T)
    return T


def _window_coords(c: FacadeFlightConfig, x, z, grow: float):
    """Local coordinates (u, v) in the nearest window of the grid, whether (x, z) lies in the opening grown by
    ``grow`` on every side, and the window's (column, row)."""
    ww, wh = c.window_size_m
    pxw, pzw = c.window_period_m
    col = np.floor((x - c.window_x0_m + (pxw - ww) / 2) / pxw)
    row = np.floor((z - c.window_z0_m + (pzw - wh) / 2) / pzw)
    u = x - (c.window_x0_m + col * pxw)
    v = z - (c.window_z0_m + row * pzw)
    inside = (u > -grow) & (u < ww + grow) & (v > -grow) & (v < wh + grow) & (row >= 0) & (row < c.window_rows)
    return u, v, inside, (col, row)


def _scene_temperature(scene: FacadeFlight, C, d) -> np.ndarray:
    """Apparent temperature along rays from ``C`` with world directions ``d`` (..., 3): the wall plane; inside a
    window opening, the recessed glass (mullion and transom frames) or the reveal (frame temperature)."""
    c = scene.config
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = np.where(d[..., 1] > 0, -C[1] / d[..., 1], np.nan)
    if not np.all(np.isfinite(t0)):
        raise ConfigError("FacadeFlightConfig: a ray misses the wall (attitude jitter too large)")
    x0, z0 = C[0] + t0 * d[..., 0], C[2] + t0 * d[..., 2]
    T = wall_temperature(scene, x0, z0)
    _, _, opening, cr0 = _window_coords(c, x0, z0, 0.0)
    if opening.any():
        t1 = (c.recess_m - C[1]) / d[..., 1]
        x1, z1 = C[0] + t1 * d[..., 0], C[2] + t1 * d[..., 2]
        u1, v1, in1, cr1 = _window_coords(c, x1, z1, 0.0)
        same = in1 & (cr1[0] == cr0[0]) & (cr1[1] == cr0[1])
        ww, wh = c.window_size_m
        bar = c.frame_m * 0.6
        mull = (np.abs(u1 - ww / 2) < bar / 2) | (np.abs(v1 - 0.62 * wh) < bar / 2) | (u1 < bar) | (u1 > ww - bar) \
            | (v1 < bar) | (v1 > wh - bar)
        glass = c.wall_k + c.glass_k + 0.8 * (v1 / wh)
        inner = np.where(mull, c.wall_k + 0.7 * c.frame_k, glass)
        T = np.where(opening, np.where(same, inner, c.wall_k + 0.5 * c.frame_k), T)
    return T


def render_facade_flight_frame(scene: FacadeFlight, k: int, *, sensor: bool = True) -> np.ndarray:
    """Apparent temperature (float32 K, output size (h, w)) of frame ``k``: integrated on the native grid, sensor
    effects on the native grid, upscaled bilinearly. ``sensor=False``: no PSF, pattern or noise."""
    import cv2

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
        d = np.einsum("...i,ij->...j", rays, pose.R)
        sig[rows] = np.asarray(curve.signal(_scene_temperature(scene, C, d))).mean(axis=-1)
    u = c.upscale
    nw, nh = c.native_size
    native = sig.reshape(nh, u, nw, u).mean(axis=(1, 3))
    eff = SensorEffects(psf_sigma_px=c.psf_sigma_px, netd_k=c.netd_k, fpn_k=c.fpn_k, fpn_seed=int(c.seed) + 17) \
        if sensor else SensorEffects()
    t = apply_sensor_effects(native, curve, eff, np.random.default_rng([int(c.seed), int(k), 0xF1]))
    return cv2.resize(t, (w, h), interpolation=cv2.INTER_LINEAR)


def facade_flight_frame_8bit(frame_k, percentiles=(1.0, 99.0)) -> np.ndarray:
    """(H, W, 3) uint8: the frame through :data:`IRON_PALETTE` after a per-frame stretch between its percentiles."""
    a = np.asarray(frame_k, float)
    lo, hi = np.percentile(a, percentiles)
    g = np.clip((a - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    return IRON_PALETTE[np.round(g * 255).astype(np.uint8)]


def _exif_bytes(c: FacadeFlightConfig, k: int, latlonalt) -> bytes:
    """EXIF of a palette JPEG as a small DJI drone writes it: Make, Model, DateTimeOriginal and a GPS IFD; no focal
    length, no focal-plane resolution."""
    from fractions import Fraction

    from PIL import Image

    def dms(v):
        v = abs(float(v))
        d = int(v)
        m = int((v - d) * 60)
        s = Fraction((v - d - m / 60.0) * 3600).limit_denominator(10000)
        return (Fraction(d), Fraction(m), s)

    ex = Image.Exif()
    ex[0x010F] = c.make
    ex[0x0110] = c.model
    sec = 10 + 2 * k
    ex[0x0132] = f"2026:11:20 14:{sec // 60:02d}:{sec % 60:02d}"
    exif_ifd = ex.get_ifd(0x8769)
    exif_ifd[0x9003] = ex[0x0132]
    lat, lon, alt = latlonalt
    gps = ex.get_ifd(0x8825)
    gps[0] = b"\x02\x03\x00\x00"
    gps[1] = "N" if lat >= 0 else "S"
    gps[2] = dms(lat)
    gps[3] = "E" if lon >= 0 else "W"
    gps[4] = dms(lon)
    gps[5] = 0 if alt >= 0 else 1
    gps[6] = Fraction(abs(float(alt))).limit_denominator(1000)
    return ex.tobytes()


def write_facade_flight(project, scene: FacadeFlight, *, prefix: str = "") -> dict:
    """Render every frame and write ``<prefix>frames/<name>.jpg`` and ``<prefix>truth/{camera,poses}.json``."""
    import io

    from PIL import Image

    c = scene.config
    p = prefix.rstrip("/") + "/" if prefix else ""
    for k, name in enumerate(scene.names):
        img = facade_flight_frame_8bit(render_facade_flight_frame(scene, k))
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, format="JPEG", quality=int(c.jpeg_quality), exif=_exif_bytes(c, k, scene.gnss[k]))
        project.write_bytes(f"{p}frames/{name}.jpg", buf.getvalue())
    project.write_json(f"{p}truth/camera.json", scene.camera.to_dict())
    project.write_json(f"{p}truth/poses.json", {
        "format": "thermogrammetry.synthetic.facade_flight/1",
        "convention": "cam_from_world: X_cam = R X_world + t; world: x along the wall, y into the building, z up (m)",
        "camera": scene.camera.to_dict(),
        "images": [{"name": n, "R": q.R.tolist(), "t": q.t.tolist(), "center": q.center.tolist(), "wall_distance_m": float(d),
                    "gnss_lat_lon_alt": g.tolist()}
                   for n, q, d, g in zip(scene.names, scene.poses, scene.distances, scene.gnss)],
    })
    return {"frames": len(scene.names)}
