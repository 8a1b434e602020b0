"""A building facade with exact ground truth: triangle mesh (OBJ), temperature field, thermal + RGB rig.

Scene (world frame: x along the facade, y away from the street into the building, z up; metres):

* the wall is the plane y = 0, ``width_m`` × ``height_m``, with a grid of windows recessed by
  ``recess_m`` (reveals are separate triangles, the glass sits at y = recess) and a ground strip;
* materials: plaster (ε_n 0.93), glass (ε_n 0.84, strongly directional), ground (0.95); directional
  emissivity ε(θ) = ε_n F(θ)/F(0) with F the Fresnel emissivity of the material's index;
* true temperature T(x, z) on the wall: a smooth gradient, warm thermal bridges along the floor slabs
  and around the window reveals, a cool damp patch near the ground; glass a few kelvin warmer; ground
  separately;
* a rig of a thermal camera and an RGB camera (relative pose fixed: ``rig_baseline_m`` along the rig's
  x axis, a small rotation) at ``n_stations`` positions along the street ``distance_m`` from the wall.

Rendering: rays of the sub-pixel samples are intersected with the mesh (``trimesh``; Embree when
installed) to find the triangle, then the exact float64 intersection with that triangle's plane is
computed; radiometry as in :mod:`.survey` (sky as the reflected source over the upper hemisphere,
FLIR curve, atmosphere over the path). The RGB camera renders a brick/plaster albedo under diffuse
light (8-bit, for orientation and texturing workflows).

Files (:func:`write_facade`, prefix ``facade/``): ``mesh.obj``, ``cameras.json`` (both cameras with
intrinsics, per-station ``R``, ``t`` of each camera, and the rig's relative pose
``cam_thermal_from_cam_rgb``), ``thermal/<station>.tif`` (float32 K), ``rgb/<station>.png``,
``truth/temperature_grid.npy`` + ``truth/temperature_grid.json`` (T(x, z) on the wall plane with its
grid definition), ``truth/points.csv`` (window corners as natural check points).

References
----------
.. [1] Barazzetti, Erba, Previtali, Rosina, Scaioni (seed 002): facades mapped with thermal + RGB
   images, a bi-camera rig with a constant relative orientation (eq. 4–5).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from ._render import camera_key, sample_offsets, unproject_fast
from .radiance import FlirCurve, fresnel_emissivity
from .sensor import SensorEffects, apply_sensor_effects
from .._validate import config_keys

__all__ = ["FacadeConfig", "FacadeScene", "make_facade", "render_facade_thermal", "render_facade_rgb", "write_facade"]

_MATERIALS = {"plaster": (0.93, 1.5), "glass": (0.84, 1.5), "ground": (0.95, 1.6), "reveal": (0.93, 1.5)}


@dataclass(frozen=True)
class FacadeConfig:
    width_m: float = 20.0
    height_m: float = 9.0
    floors: int = 3
    windows_per_floor: int = 5
    window_w_m: float = 1.4
    window_h_m: float = 1.6
    recess_m: float = 0.2
    distance_m: float = 12.0
    n_stations: int = 4
    thermal_size: tuple[int, int] = (320, 240)
    thermal_focal_mm: float = 9.0
    thermal_pitch_um: float = 17.0
    rgb_size: tuple[int, int] = (960, 640)
    rgb_focal_px: float = 900.0
    rig_baseline_m: float = 0.08
    plaster_emissivity: float = 0.93  # normal emissivity of the wall; 0.9600 = pure Fresnel with n = 1.5
    sky_k: float = 250.0
    air_k: float = 278.15
    relative_humidity: float = 0.7
    supersample: int = 2
    sensor: SensorEffects = field(default_factory=lambda: SensorEffects(psf_sigma_px=0.5, netd_k=0.04, fpn_k=0.02, fpn_seed=5))
    seed: int = 0

    def __post_init__(self):
        for f in ("width_m", "height_m", "window_w_m", "window_h_m", "recess_m", "distance_m", "rig_baseline_m"):
            v = float(getattr(self, f))
            if not np.isfinite(v) or v <= 0:
                raise ConfigError(f"FacadeConfig.{f}={getattr(self, f)!r}: expected a positive number")
        if self.windows_per_floor * self.window_w_m >= self.width_m or self.floors * self.window_h_m >= self.height_m:
            raise ConfigError("FacadeConfig: the windows do not fit the wall (width/height too small)")

    @classmethod
    def from_dict(cls, d: dict) -> "FacadeConfig":
        return cls(**config_keys(cls, d))


@dataclass
class FacadeScene:
    config: FacadeConfig
    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    face_material: list  # (F,) names
    windows: list  # (x0, z0, x1, z1)
    thermal: object
    rgb: object
    stations: list  # [(name, pose_rgb, pose_thermal)]
    rig_relative: object  # Pose cam_thermal_from_cam_rgb
    _mesh: object = field(default=None, repr=False)

    def mesh(self):
        if self._mesh is None:
            import trimesh

            self._mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
        return self._mesh

    def wall_temperature(self, x, z) -> np.ndarray:
        """True wall temperature (K) at facade coordinates (x along, z up), any shape."""
        c = self.config
        x = np.asarray(x, float)
        z = np.asarray(z, float)
        t = 281.0 + 0.15 * z + 0.4 * np.sin(x / c.width_m * 2 * np.pi)
        for k in range(1, c.floors):  # floor slabs: thermal bridges
            zs = k * c.height_m / c.floors
            t = t + 1.6 * np.exp(-0.5 * ((z - zs) / 0.25) ** 2)
        for (x0, z0, x1, z1) in self.windows:  # warm rings around the windows
            dx = np.maximum(np.maximum(x0 - x, x - x1), 0.0)
            dz = np.maximum(np.maximum(z0 - z, z - z1), 0.0)
            t = t + 1.2 * np.exp(-np.hypot(dx, dz) / 0.3)
        damp = np.exp(-0.5 * (((x - 0.3 * c.width_m) / 1.5) ** 2 + ((z - 0.6) / 0.5) ** 2))
        return t - 2.0 * damp


def _quad(V, F, M, p00, p10, p11, p01, mat):
    i = len(V)
    V.extend([p00, p10, p11, p01])
    F.extend([[i, i + 1, i + 2], [i, i + 2, i + 3]])
    M.extend([mat, mat])


def make_facade(config: FacadeConfig | None = None) -> FacadeScene:
    """Build the mesh, the temperature field, the rig and the stations (deterministic)."""
    from ..camera import Camera
    from ..geometry import Pose
    from ..geometry.rotations import matrix_from_axis_angle

    c = config or FacadeConfig()
    rng = np.random.default_rng([c.seed, 0xFA])
    W, H, r = c.width_m, c.height_m, c.recess_m
    V: list = []
    F: list = []
    M: list = []
    # windows
    wins = []
    fh = H / c.floors
    for f in range(c.floors):
        for k in range(c.windows_per_floor):
            xc = (k + 0.5) * W / c.windows_per_floor
            zc = f * fh + 0.55 * fh
            wins.append((xc - c.window_w_m / 2, zc - c.window_h_m / 2, xc + c.window_w_m / 2, zc + c.window_h_m / 2))
    # wall: split into cells around the windows (a grid of x and z breaks)
    xs = sorted({0.0, W, *[w[0] for w in wins], *[w[2] for w in wins]})
    zs = sorted({0.0, H, *[w[1] for w in wins], *[w[3] for w in wins]})
    for i in range(len(xs) - 1):
        for j in range(len(zs) - 1):
            xm, zm = 0.5 * (xs[i] + xs[i + 1]), 0.5 * (zs[j] + zs[j + 1])
            if any(w[0] < xm < w[2] and w[1] < zm < w[3] for w in wins):
                continue
            _quad(V, F, M, (xs[i], 0, zs[j]), (xs[i + 1], 0, zs[j]), (xs[i + 1], 0, zs[j + 1]), (xs[i], 0, zs[j + 1]), "plaster")
    for (x0, z0, x1, z1) in wins:
        _quad(V, F, M, (x0, r, z0), (x1, r, z0), (x1, r, z1), (x0, r, z1), "glass")
        # reveals (normals point out of the recess, towards -y side openings)
        _quad(V, F, M, (x0, 0, z0), (x0, r, z0), (x0, r, z1), (x0, 0, z1), "reveal")
        _quad(V, F, M, (x1, r, z0), (x1, 0, z0), (x1, 0, z1), (x1, r, z1), "reveal")
        _quad(V, F, M, (x1, 0, z0), (x1, r, z0), (x0, r, z0), (x0, 0, z0), "reveal")
        _quad(V, F, M, (x0, 0, z1), (x0, r, z1), (x1, r, z1), (x1, 0, z1), "reveal")
    # ground strip in front of the wall
    _quad(V, F, M, (-5, -c.distance_m - 5, 0), (W + 5, -c.distance_m - 5, 0), (W + 5, 0, 0), (-5, 0, 0), "ground")
    verts = np.array(V, float)
    faces = np.array(F, int)
    tw, th = c.thermal_size
    ft = c.thermal_focal_mm / (c.thermal_pitch_um * 1e-3)
    thermal = Camera("opencv", (tw, th), dict(fx=ft, fy=ft, cx=(tw - 1) / 2 + 1.3, cy=(th - 1) / 2 - 0.8, k1=-0.09, k2=0.04),
                     pixel_pitch_um=c.thermal_pitch_um, name="facade-thermal")
    rw, rh = c.rgb_size
    rgb = Camera("opencv", (rw, rh), dict(fx=c.rgb_focal_px, fy=c.rgb_focal_px, cx=(rw - 1) / 2, cy=(rh - 1) / 2, k1=-0.05),
                 name="facade-rgb")
    rel_R = matrix_from_axis_angle(np.deg2rad([0.4, -0.6, 0.3]))
    rig = Pose(rel_R, np.array([-c.rig_baseline_m, 0.0, 0.0]))  # thermal sits to the right of the RGB camera
    stations = []
    for s in range(c.n_stations):
        x = W * (s + 0.5) / c.n_stations + rng.normal(0, 0.3)
        Cw = np.array([x, -c.distance_m + rng.normal(0, 0.2), 1.6 + rng.normal(0, 0.05)])
        target = np.array([x + rng.normal(0, 0.5), 0.0, H * 0.5])
        pose_rgb = Pose.look_at(Cw, target, up=(0, 0, 1))
        stations.append((f"S{s:02d}", pose_rgb, rig.compose(pose_rgb)))
    return FacadeScene(c, verts, faces, M, wins, thermal, rgb, stations, rig)


def _cast_mesh(scene: FacadeScene, C, d):
    """First hit: (tri (N,), t (N,), points (N, 3), normals (N, 3)); exact float64 plane intersection."""
    mesh = scene.mesh()
    o = np.broadcast_to(np.asarray(C, float), d.shape)
    tri = np.asarray(mesh.ray.intersects_first(ray_origins=o, ray_directions=d), int)
    hit = tri >= 0
    V, Fc = scene.vertices, scene.faces
    v0 = V[Fc[tri[hit], 0]]
    n = np.cross(V[Fc[tri[hit], 1]] - v0, V[Fc[tri[hit], 2]] - v0)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    den = np.einsum("ij,ij->i", d[hit], n)
    t = np.full(len(d), np.nan)
    t[hit] = np.einsum("ij,ij->i", v0 - C, n) / den
    pts = C + t[:, None] * d
    normals = np.full((len(d), 3), np.nan)
    normals[hit] = np.where((den > 0)[:, None], -n, n)  # facing the camera
    return tri, t, pts, normals


#: rays of the last few (camera, supersample) pairs: a scene's stations share one camera
_SAMPLE_RAYS: dict = {}


def _sample_rays(cam, ss):
    """(H·W·S², 3) camera-frame rays (z = 1) of the S×S sub-pixel samples of every pixel, row by row (read-only;
    computed once per camera and supersampling)."""
    key = (camera_key(cam), int(ss))
    hit = _SAMPLE_RAYS.get(key)
    if hit is None:
        if len(_SAMPLE_RAYS) >= 4:
            _SAMPLE_RAYS.clear()
        hit = _SAMPLE_RAYS[key] = _compute_sample_rays(cam, ss)
        hit.setflags(write=False)
    return hit


def _compute_sample_rays(cam, ss):
    w, h = cam.image_size
    off = sample_offsets(ss)
    oy, ox = np.meshgrid(off, off, indexing="ij")
    gy, gx = np.mgrid[0:h, 0:w].astype(float)
    x = (gx[:, :, None] + ox.ravel()).ravel()
    y = (gy[:, :, None] + oy.ravel()).ravel()
    return unproject_fast(cam, np.stack([x, y], axis=1))


def render_facade_thermal(scene: FacadeScene, station: int, *, sensor: bool = True, with_truth: bool = False) -> dict:
    """Thermal image (float32 K) of one station; ``with_truth``: per-pixel-centre truth rasters too."""
    from ..radiometry.atmosphere import atmospheric_transmission

    c = scene.config
    name, _, pose = scene.stations[station]
    cam = scene.thermal
    w, h = cam.image_size
    ss2 = c.supersample**2
    d = np.einsum("...i,ij->...j", _sample_rays(cam, c.supersample), pose.R)
    C = pose.center
    tri, t, pts, nrm = _cast_mesh(scene, C, d)
    hit = tri >= 0
    mats = np.array(scene.face_material, dtype=object)
    mat = np.where(hit, mats[np.clip(tri, 0, None)], "sky")
    temp = np.full(len(d), np.nan)
    wall = np.isin(mat, ("plaster", "reveal"))
    temp[wall] = scene.wall_temperature(pts[wall, 0], pts[wall, 2])
    glass = mat == "glass"
    temp[glass] = scene.wall_temperature(pts[glass, 0], pts[glass, 2]) + 3.0
    ground = mat == "ground"
    temp[ground] = 279.0 + 0.3 * np.sin(pts[ground, 0]) + 0.2 * np.cos(1.7 * pts[ground, 1])
    view = -d / np.linalg.norm(d, axis=1, keepdims=True)
    cos_t = np.clip(np.einsum("ij,ij->i", np.nan_to_num(nrm), view), 0.0, 1.0)
    theta = np.arccos(cos_t)
    eps = np.ones(len(d))
    for m, (en, n_idx) in _MATERIALS.items():
        if m in ("plaster", "reveal"):
            en = c.plaster_emissivity
        sel = mat == m
        if np.any(sel):
            f = fresnel_emissivity(theta[sel], n_idx)
            eps[sel] = en * f / float(fresnel_emissivity(0.0, n_idx))
    curve = FlirCurve()
    dist = t * np.linalg.norm(d, axis=1)
    tau = np.ones(len(d))
    tau[hit] = atmospheric_transmission(dist[hit] / 2.0, c.air_k, c.relative_humidity) ** 2
    s_sky = float(curve.signal(c.sky_k))
    sig = np.full(len(d), s_sky)
    sig[hit] = tau[hit] * (eps[hit] * curve.signal(temp[hit]) + (1 - eps[hit]) * s_sky) + (1 - tau[hit]) * float(curve.signal(c.air_k))
    img = sig.reshape(h, w, ss2).mean(axis=2)
    effects = c.sensor if sensor else SensorEffects()
    out = {"image_k": apply_sensor_effects(img, curve, effects, np.random.default_rng([c.seed, station, 0x7E]))}
    if with_truth:
        centre = np.arange(len(d)).reshape(h, w, ss2)[:, :, ss2 // 2]
        depth = (pts - C) @ pose.R.T
        out.update(surface_temperature_k=temp[centre], emissivity=np.where(hit, eps, np.nan)[centre],
                   angle_rad=np.where(hit, theta, np.nan)[centre], depth_m=depth[:, 2][centre],
                   material=mat[centre])
    return out


def render_facade_rgb(scene: FacadeScene, station: int) -> np.ndarray:
    """8-bit RGB image (H, W, 3) of one station: brick/plaster albedo, dark glass, diffuse light."""
    c = scene.config
    name, pose, _ = scene.stations[station]
    cam = scene.rgb
    w, h = cam.image_size
    d = np.einsum("...i,ij->...j", _sample_rays(cam, 1), pose.R)
    tri, t, pts, nrm = _cast_mesh(scene, pose.center, d)
    mats = np.array(scene.face_material, dtype=object)
    hit = tri >= 0
    mat = np.where(hit, mats[np.clip(tri, 0, None)], "sky")
    rgb = np.tile(np.array([150.0, 190.0, 230.0]), (len(d), 1))  # sky
    x, z = pts[:, 0], pts[:, 2]
    plaster = np.isin(mat, ("plaster", "reveal"))
    brick = (np.mod(z, 0.075) < 0.012) | (np.mod(x + 0.125 * (np.floor(z / 0.075) % 2), 0.25) < 0.012)
    base = np.array([205.0, 190.0, 165.0])
    mortar = np.array([170.0, 165.0, 150.0])
    rgb[plaster] = np.where(brick[plaster, None], mortar, base)
    rgb[mat == "glass"] = np.array([40.0, 55.0, 70.0])
    g = mat == "ground"
    rgb[g] = np.array([95.0, 95.0, 92.0]) + 15 * np.sin(3 * x[g])[:, None] * np.cos(2.3 * pts[g, 1])[:, None]
    shade = np.ones(len(d))
    shade[hit] = 0.65 + 0.35 * np.clip(nrm[hit] @ np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5]), 0, 1)
    img = np.clip(rgb * shade[:, None], 0, 255).astype(np.uint8).reshape(h, w, 3)
    return img


def write_facade(project, scene: FacadeScene, *, prefix: str = "facade") -> dict:
    """Render every station (thermal + RGB) and write mesh, cameras, images and truth through ``project``."""
    import io

    import cv2

    from ..io.tiff import encode_temperature_tiff

    p = prefix.rstrip("/") + "/"
    lines = ["# thermogrammetry synthetic facade; materials per face in facade/truth/face_material.json"]
    lines += [f"v {v[0]:.6f} {v[1]:.6f} {v[2]:.6f}" for v in scene.vertices]
    lines += [f"f {a + 1} {b + 1} {c_ + 1}" for a, b, c_ in scene.faces]
    project.write_text(f"{p}mesh.obj", "\n".join(lines) + "\n")
    project.write_json(f"{p}truth/face_material.json", scene.face_material)
    for k, (name, _, _) in enumerate(scene.stations):
        data, _ = encode_temperature_tiff(render_facade_thermal(scene, k)["image_k"])
        project.write_bytes(f"{p}thermal/{name}.tif", data)
        ok, png = cv2.imencode(".png", cv2.cvtColor(render_facade_rgb(scene, k), cv2.COLOR_RGB2BGR))
        project.write_bytes(f"{p}rgb/{name}.png", png.tobytes())
    project.write_json(f"{p}cameras.json", {
        "format": "thermogrammetry.synthetic.facade/1",
        "convention": "cam_from_world: X_cam = R X_world + t; world: x along the facade, y into the building, z up (m)",
        "cameras": {"thermal": scene.thermal.to_dict(), "rgb": scene.rgb.to_dict()},
        "rig": {"cam_thermal_from_cam_rgb": {"R": scene.rig_relative.R.tolist(), "t": scene.rig_relative.t.tolist()}},
        "stations": [{"name": n, "rgb": {"R": pr.R.tolist(), "t": pr.t.tolist()}, "thermal": {"R": pt.R.tolist(), "t": pt.t.tolist()}}
                     for n, pr, pt in scene.stations],
    })
    c = scene.config
    xs = np.arange(0.0, c.width_m + 1e-9, 0.02)
    zs = np.arange(0.0, c.height_m + 1e-9, 0.02)
    X, Z = np.meshgrid(xs, zs)
    project.write_array(f"{p}truth/temperature_grid.npy", scene.wall_temperature(X, Z).astype(np.float32))
    project.write_json(f"{p}truth/temperature_grid.json", {"x0_m": 0.0, "z0_m": 0.0, "step_m": 0.02, "shape": list(X.shape),
                                                           "plane": "y = 0 (wall); glass = wall + 3 K at y = recess_m",
                                                           "note": "row k is z = k * step (upwards), column j is x = j * step"})
    corners = [(f"W{i:02d}{tag}", x, c.recess_m, z) for i, (x0, z0, x1, z1) in enumerate(scene.windows)
               for tag, x, z in (("a", x0, z0), ("b", x1, z0), ("c", x1, z1), ("d", x0, z1))]
    project.write_text(f"{p}truth/points.csv", "name,X,Y,Z\n" + "".join(f"{n},{x:.4f},{y:.4f},{z:.4f}\n" for n, x, y, z in corners))
    _ = io
    return {"stations": len(scene.stations), "faces": int(len(scene.faces))}
