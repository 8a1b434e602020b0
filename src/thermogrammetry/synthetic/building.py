"""A box building with an occluder in front of one facade: mesh, temperature field, thermal stations.

Scene (world frame: x east, y north, z up; metres). A rectangular building ``length_m`` (x) ×
``depth_m`` (y) × ``height_m`` (z) stands on a ground plane; its four walls and the flat roof are
triangulated on a regular grid of ``cell_m`` (so a facade has many faces and a face can be partly
occluded). In front of the south facade (y = 0, facing −y) stands a free-standing **occluder** (a
square column, ``occluder_size_m``, its centre ``occluder_distance_m`` in front of the wall), which
hides a different part of the facade from every station. Thermal stations stand on a ring around the
building at ``standoff_m`` from the walls, ``camera_height_m`` above ground, looking at the building.

True surface temperatures (K), continuous across the building's vertical edges (walls use the arc
length ``s`` around the perimeter, counter-clockwise from the south-west corner):

* walls: a vertical gradient, warm floor slabs (thermal bridges every ``height_m / floors``), a cool
  damp patch near the ground on the south facade and a fixed random sum of smooth plane waves
  (wavelengths 0.7–3 m, a few tenths of a kelvin; gives texture for tie points);
* roof 276 K + waves; ground 279 K + waves; occluder 286 K + a vertical gradient (warm, so that a
  texel taken through the occluder would stand out by several kelvin);
* with ``facade_detail=True`` (off by default, so that the field stays smooth at the pixel scale and every
  texel is comparable with the truth): windows on every storey (cold glass, a different temperature per
  window, warm 8 cm frames), a door on the south wall and small Gaussian warm/cool spots (fixings, vents,
  damp; 0.35 per m²). Real facades carry this structure, and so do their tie points: the smooth walls alone
  give a few dozen SIFT matches per pair, too few to orient a ring of views. The true temperature jumps at the
  window, frame and door edges; :func:`discontinuity_distance` tells how far a point is from them (pixels
  straddling an edge mix both sides and are not comparable with the point truth).

Radiometry: by default the surfaces are black bodies seen through no atmosphere
(``emissivity = 1``, ``atmosphere = False``), so that the noise-free apparent temperature of a surface
point equals its true temperature whatever the view; with ``emissivity < 1`` the walls' directional
emissivity is ε_n F(θ)/F(0) (Fresnel, n = 1.5) reflecting a sky at ``sky_k``, and with ``atmosphere``
the FLIR transmission over the path. :func:`apparent_temperature` gives the noise-free value a camera
at a centre sees at any surface point (the truth texels are compared with).

Rendering (:func:`render_building_thermal`): ``supersample``² sub-pixel rays per pixel are cast against
the mesh (trimesh with Embree), the exact intersection with the hit triangle's plane is taken, the
band signal (FLIR curve) is averaged over the pixel and the sensor effects (PSF, NETD, FPN) applied
unless ``sensor=False``. :func:`write_building_survey` writes a survey folder (``cameras.json`` in the
:class:`~thermogrammetry.io.oriented.OrientedCameras` schema with the TRUE poses, ``frames/<name>.tif``
float32 K, ``mesh.obj``) through a project store.

References
----------
.. [1] Barazzetti, Erba, Previtali, Rosina, Scaioni (seed 002): thermal textures of building models,
   occlusions and the choice of the image per triangle.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from .facade import _cast_mesh, _sample_rays
from .radiance import FlirCurve, fresnel_emissivity
from .sensor import SensorEffects, apply_sensor_effects
from .._validate import config_keys

__all__ = ["BuildingConfig", "BuildingScene", "make_building", "render_building_thermal", "apparent_temperature",
           "write_building_survey", "write_building_user_files", "surface_temperature", "discontinuity_distance",
           "clean_wall_texel_errors"]

GROUPS = ("wall", "roof", "ground", "occluder")


@dataclass(frozen=True)
class BuildingConfig:
    length_m: float = 12.0
    depth_m: float = 8.0
    height_m: float = 7.0
    floors: int = 2
    cell_m: float = 1.0
    occluder_size_m: tuple[float, float, float] = (1.2, 1.2, 5.0)  # x, y, z extent
    occluder_x_m: float = 4.5  # centre along the south facade
    occluder_distance_m: float = 2.5  # centre in front of the south wall
    ground_margin_m: float = 6.0
    standoff_m: float = 9.0
    camera_height_m: float = 1.7
    n_stations: int = 14
    thermal_size: tuple[int, int] = (320, 240)
    thermal_focal_px: float = 285.0
    emissivity: float = 1.0
    atmosphere: bool = False
    sky_k: float = 250.0
    air_k: float = 280.15
    relative_humidity: float = 0.6
    supersample: int = 2
    sensor: SensorEffects = field(default_factory=lambda: SensorEffects(psf_sigma_px=0.5, netd_k=0.04, fpn_k=0.02, fpn_seed=7))
    seed: int = 0
    facade_detail: bool = False
    window_width_m: float = 1.2
    window_height_m: float = 1.4
    window_spacing_m: float = 3.0
    n_spots_per_m2: float = 0.35

    def __post_init__(self):
        for f in ("length_m", "depth_m", "height_m", "cell_m", "standoff_m", "thermal_focal_px", "occluder_distance_m"):
            v = float(getattr(self, f))
            if not np.isfinite(v) or v <= 0:
                raise ConfigError(f"BuildingConfig.{f}={getattr(self, f)!r}: expected a positive number")
        if not 0 < self.emissivity <= 1:
            raise ConfigError(f"BuildingConfig.emissivity={self.emissivity!r}: expected a number in (0, 1]")
        if self.occluder_distance_m - self.occluder_size_m[1] / 2 <= 0:
            raise ConfigError("BuildingConfig: the occluder must stand in front of the south wall "
                              f"(occluder_distance_m={self.occluder_distance_m} <= half its depth)")
        if self.n_stations < 2:
            raise ConfigError(f"BuildingConfig.n_stations={self.n_stations!r}: expected at least 2")
        for f in ("window_width_m", "window_height_m", "window_spacing_m"):
            v = float(getattr(self, f))
            if not np.isfinite(v) or v <= 0:
                raise ConfigError(f"BuildingConfig.{f}={getattr(self, f)!r}: expected a positive number")
        if self.window_width_m + 0.4 > self.window_spacing_m:
            raise ConfigError(f"BuildingConfig: window_width_m={self.window_width_m} leaves no wall between windows "
                              f"at window_spacing_m={self.window_spacing_m}; expected width + 0.4 m <= spacing")
        if self.window_height_m + 1.1 > self.height_m / max(self.floors, 1):
            raise ConfigError(f"BuildingConfig: window_height_m={self.window_height_m} does not fit a storey of "
                              f"{self.height_m / max(self.floors, 1):.2f} m (sill 0.9 m, lintel 0.2 m)")
        if not (np.isfinite(self.n_spots_per_m2) and self.n_spots_per_m2 >= 0):
            raise ConfigError(f"BuildingConfig.n_spots_per_m2={self.n_spots_per_m2!r}: expected a number >= 0")

    @classmethod
    def from_dict(cls, d: dict) -> "BuildingConfig":
        return cls(**config_keys(cls, d))


@dataclass
class BuildingScene:
    config: BuildingConfig
    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3), counter-clockwise seen from outside (normals point out)
    face_group: np.ndarray  # (F,) index into GROUPS
    thermal: object  # Camera
    stations: list  # [(name, Pose cam_from_world)]
    waves: np.ndarray  # (K, 4): kx, ky, phase, amplitude of the texture waves
    openings: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))  # (K, 6): s0, s1, z0, z1, glass K, frame dK
    spots: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # (K, 4): s, z, sigma m, amplitude K
    _mesh: object = field(default=None, repr=False)

    def mesh(self):
        if self._mesh is None:
            import trimesh

            self._mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
        return self._mesh

    @property
    def face_normals(self) -> np.ndarray:
        V, F = self.vertices, self.faces
        n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        return n / np.linalg.norm(n, axis=1, keepdims=True)


def _grid_quad(V, F, G, origin, u, v, nu, nv, group):
    """Triangulate the parallelogram origin + a u + b v (a, b in [0, 1]) on an nu × nv grid; normal u × v."""
    base = len(V)
    a = np.linspace(0, 1, nu + 1)
    b = np.linspace(0, 1, nv + 1)
    for bj in b:
        for ai in a:
            V.append(np.asarray(origin, float) + ai * np.asarray(u, float) + bj * np.asarray(v, float))
    for j in range(nv):
        for i in range(nu):
            p00 = base + j * (nu + 1) + i
            p10, p01, p11 = p00 + 1, p00 + nu + 1, p00 + nu + 2
            F.extend([[p00, p10, p11], [p00, p11, p01]])
            G.extend([group, group])


def _box(V, F, G, lo, hi, cell, group, *, bottom: bool = False, walls_only: bool = False):
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    lx, ly, lz = x1 - x0, y1 - y0, z1 - z0
    n = lambda L: max(1, int(round(L / cell)))  # noqa: E731
    _grid_quad(V, F, G, (x0, y0, z0), (lx, 0, 0), (0, 0, lz), n(lx), n(lz), group)  # south, normal -y
    _grid_quad(V, F, G, (x1, y0, z0), (0, ly, 0), (0, 0, lz), n(ly), n(lz), group)  # east, +x
    _grid_quad(V, F, G, (x1, y1, z0), (-lx, 0, 0), (0, 0, lz), n(lx), n(lz), group)  # north, +y
    _grid_quad(V, F, G, (x0, y1, z0), (0, -ly, 0), (0, 0, lz), n(ly), n(lz), group)  # west, -x
    if not walls_only:
        _grid_quad(V, F, G, (x0, y0, z1), (lx, 0, 0), (0, ly, 0), n(lx), n(ly), "roof" if group == "wall" else group)
    if bottom:
        _grid_quad(V, F, G, (x0, y1, z0), (lx, 0, 0), (0, -ly, 0), n(lx), n(ly), group)


def make_building(config: BuildingConfig | None = None) -> BuildingScene:
    """Build the mesh, the temperature field's waves and the station ring (deterministic)."""
    from ..camera import Camera
    from ..geometry import Pose

    c = config or BuildingConfig()
    rng = np.random.default_rng([c.seed, 0xB1D])
    V: list = []
    F: list = []
    G: list = []
    L, D, H = c.length_m, c.depth_m, c.height_m
    _box(V, F, G, (0, 0, 0), (L, D, H), c.cell_m, "wall")
    ox, oy, oz = c.occluder_size_m
    xc, yc = c.occluder_x_m, -c.occluder_distance_m
    _box(V, F, G, (xc - ox / 2, yc - oy / 2, 0), (xc + ox / 2, yc + oy / 2, oz), 0.5 * c.cell_m, "occluder")
    # ground: a frame around the building (the footprint itself is not part of the mesh)
    m = c.ground_margin_m + c.standoff_m
    gc = 2.0 * c.cell_m
    _grid_quad(V, F, G, (-m, -m, 0), (L + 2 * m, 0, 0), (0, m, 0), int(round((L + 2 * m) / gc)), int(round(m / gc)), "ground")
    _grid_quad(V, F, G, (-m, D, 0), (L + 2 * m, 0, 0), (0, m, 0), int(round((L + 2 * m) / gc)), int(round(m / gc)), "ground")
    _grid_quad(V, F, G, (-m, 0, 0), (m, 0, 0), (0, D, 0), int(round(m / gc)), max(1, int(round(D / gc))), "ground")
    _grid_quad(V, F, G, (L, 0, 0), (m, 0, 0), (0, D, 0), int(round(m / gc)), max(1, int(round(D / gc))), "ground")
    verts = np.array(V, float)
    faces = np.array(F, np.int64)
    group = np.array([GROUPS.index(g) for g in G], np.int8)
    # texture waves: wavelengths 0.7-3 m, amplitudes 0.15-0.3 K
    k = 12
    lam = rng.uniform(0.7, 3.0, k)
    ang = rng.uniform(0, np.pi, k)
    waves = np.stack([2 * np.pi / lam * np.cos(ang), 2 * np.pi / lam * np.sin(ang), rng.uniform(0, 2 * np.pi, k),
                      rng.uniform(0.15, 0.3, k) / np.sqrt(k / 4)], axis=1)
    w, h = c.thermal_size
    f = c.thermal_focal_px
    thermal = Camera("opencv", (w, h), dict(fx=f, fy=f, cx=(w - 1) / 2 + 0.9, cy=(h - 1) / 2 - 0.6, k1=-0.12, k2=0.05),
                     pixel_pitch_um=17.0, name="building-thermal")
    # stations on a rounded rectangle at standoff_m from the walls, looking at the nearest wall point
    stations = []
    per = 2 * (L + D) + 2 * np.pi * c.standoff_m
    for s in range(c.n_stations):
        u = (s + 0.5 + rng.normal(0, 0.08)) / c.n_stations * per
        C, target = _ring_point(u, L, D, H, c.standoff_m)
        C = C + np.array([0.0, 0.0, c.camera_height_m + rng.normal(0, 0.05)])
        target = target + rng.normal(0, 0.3, 3) * np.array([1, 1, 0.5])
        stations.append((f"T{s:02d}", Pose.look_at(C, target, up=(0, 0, 1))))
    openings, spots = _facade_detail(c, np.random.default_rng([c.seed, 0xFAC]))
    return BuildingScene(c, verts, faces, group, thermal, stations, waves, openings, spots)


FRAME_M = 0.08  # width of a window's frame (a warm thermal bridge around the glass)


def _facade_detail(c: BuildingConfig, rng) -> tuple[np.ndarray, np.ndarray]:
    """Windows (cold glass that reflects the sky, warm frames), one door and small warm/cool spots (fixings,
    vents, damp) on the walls, in perimeter coordinates (arc length ``s``, height ``z``).

    Glass temperatures differ per window (curtains, blinds, an open window): real facades repeat their windows,
    but not their temperatures. Spots are Gaussian (σ 0.12–0.25 m, ±0.4–1.0 K): smooth at the pixel scale, so
    sampling a frame anywhere but on a window's edge gives the surface temperature.
    """
    if not c.facade_detail:
        return np.zeros((0, 6)), np.zeros((0, 4))
    L, D, H = c.length_m, c.depth_m, c.height_m
    starts = np.cumsum([0.0, L, D, L])
    lengths = [L, D, L, D]
    storey = H / max(c.floors, 1)
    door = (0.25 * L - 0.5, 0.25 * L + 0.5, 0.0, min(2.1, storey - 0.3), 283.5, 0.0)
    ops = [door]
    for a, wl in zip(starts, lengths):
        n = int(np.floor((wl - 1.0) / c.window_spacing_m))
        if n < 1:
            continue
        centres = a + wl / 2 + (np.arange(n) - (n - 1) / 2) * c.window_spacing_m
        for f in range(max(c.floors, 1)):
            z0 = f * storey + 0.9
            for sc in centres:
                s0, s1 = sc - c.window_width_m / 2, sc + c.window_width_m / 2
                if f == 0 and s0 < door[1] + 0.3 and s1 > door[0] - 0.3:
                    continue  # no window over the door
                ops.append((s0, s1, z0, z0 + c.window_height_m, 276.5 + rng.uniform(-1.2, 1.2), rng.uniform(0.8, 1.6)))
    area = 2 * (L + D) * H
    n_sp = int(round(c.n_spots_per_m2 * area))
    sp = np.stack([rng.uniform(0, 2 * (L + D), n_sp), rng.uniform(0.2, H - 0.2, n_sp), rng.uniform(0.12, 0.25, n_sp),
                   rng.choice([-1.0, 1.0], n_sp) * rng.uniform(0.4, 1.0, n_sp)], axis=1) if n_sp else np.zeros((0, 4))
    return np.array(ops, float), sp


def _wall_s(scene: BuildingScene, x, y) -> np.ndarray:
    c = scene.config
    L, D = c.length_m, c.depth_m
    return np.where(np.abs(y) < 1e-6, x,
                    np.where(np.abs(x - L) < 1e-6, L + y,
                             np.where(np.abs(y - D) < 1e-6, L + D + (L - x), 2 * L + D + (D - y))))


def _detail(scene: BuildingScene, s, z, t):
    """Add the spots to, and paint the openings over, the wall temperature ``t`` at (s, z).

    Each spot and each opening is evaluated only where it can change a value: the points are sorted by ``s`` once
    and a spot is applied to the points within ``R`` of its centre along the wall, where ``R`` is the distance beyond
    which its term ``amp exp(-d²/2σ²)`` is below a quarter of the spacing of the smallest ``|t|`` the loop can reach
    (so that adding it would round back to the same float); an opening to the points with ``s`` inside it. The result
    is the same, bit for bit, as evaluating every spot and opening at every point (the full evaluation is kept
    for ``t`` that are not finite or can come near zero), at a tenth of the time on a rendered wall.
    """
    per = 2 * (scene.config.length_m + scene.config.depth_m)
    s = np.asarray(s, float)
    z = np.asarray(z, float)
    t = np.array(np.broadcast_to(t, s.shape), dtype=np.result_type(t, s, z), copy=True)
    if s.size == 0:
        return t
    order = np.argsort(s, kind="stable")
    s_sorted = s[order]
    s_lo, s_hi = float(s_sorted[0]), float(s_sorted[-1])

    def within(a, b):
        """Indices of the points with a <= s <= b."""
        return order[np.searchsorted(s_sorted, a, side="left"):np.searchsorted(s_sorted, b, side="right")]

    everything = np.arange(s.size)
    # a lower bound of |t| over the whole loop (each spot moves t by at most |amp|)
    t_low = float(np.min(np.abs(t))) - float(np.sum(np.abs(scene.spots[:, 3]))) if len(scene.spots) else 0.0
    negligible = 0.25 * float(np.spacing(t_low)) if np.isfinite(t_low) and t_low > 0 else 0.0
    for s0, z0, sig, amp in scene.spots:
        idx = everything
        if negligible > 0 and abs(amp) > negligible:
            R = 1.01 * sig * np.sqrt(2.0 * np.log(abs(amp) / negligible))  # beyond R: |term| < negligible
            if 2 * R < per:
                k0, k1 = int(np.floor((s_lo - s0 - R) / per)), int(np.ceil((s_hi - s0 + R) / per))
                idx = np.concatenate([within(s0 + k * per - R, s0 + k * per + R) for k in range(k0, k1 + 1)])
        elif negligible > 0:
            continue  # |amp| itself rounds away
        ds = (s[idx] - s0 + per / 2) % per - per / 2  # continuous around the building
        t[idx] = t[idx] + amp * np.exp(-0.5 * (ds**2 + (z[idx] - z0) ** 2) / sig**2)
    for s0, s1, z0, z1, glass, dframe in scene.openings:
        idx = within(s0, s1)
        si, zi, ti = s[idx], z[idx], t[idx]
        inside = (si >= s0) & (si <= s1) & (zi >= z0) & (zi <= z1)
        if dframe > 0:
            frame = inside & ~((si >= s0 + FRAME_M) & (si <= s1 - FRAME_M) & (zi >= z0 + FRAME_M) & (zi <= z1 - FRAME_M))
            ti = np.where(frame, ti + dframe, ti)
            inside = inside & ~frame
        t[idx] = np.where(inside, glass + 0.15 * (zi - z0), ti)
    return t


def discontinuity_distance(scene: BuildingScene, points, group) -> np.ndarray:
    """Distance (m, along the wall) from surface points (N, 3) to the nearest edge of a window, frame or door,
    where the true temperature jumps; ``inf`` off the walls or without facade detail. Pixels that straddle such an
    edge mix two temperatures: compare sampled values with the truth only away from them."""
    P = np.asarray(points, float).reshape(-1, 3)
    g = np.broadcast_to(np.asarray(group), (len(P),))
    out = np.full(len(P), np.inf)
    wall = g == GROUPS.index("wall")
    if not np.any(wall) or not len(scene.openings):
        return out
    s = _wall_s(scene, P[wall, 0], P[wall, 1])
    z = P[wall, 2]
    best = np.full(len(s), np.inf)
    for s0, s1, z0, z1, _, dframe in scene.openings:
        rects = [(s0, s1, z0, z1)] + ([(s0 + FRAME_M, s1 - FRAME_M, z0 + FRAME_M, z1 - FRAME_M)] if dframe > 0 else [])
        for a0, a1, b0, b1 in rects:
            # distance to the rectangle's boundary (inside or outside)
            ds = np.maximum(np.maximum(a0 - s, s - a1), 0.0)
            dz = np.maximum(np.maximum(b0 - z, z - b1), 0.0)
            outside = np.hypot(ds, dz)
            inside_d = np.minimum(np.minimum(s - a0, a1 - s), np.minimum(z - b0, b1 - z))
            best = np.minimum(best, np.where(outside > 0, outside, np.maximum(inside_d, 0.0)))
    out[wall] = best
    return out


def clean_wall_texel_errors(scene: BuildingScene, result, view_centers) -> np.ndarray:
    """|texel - truth| (K) of the textured wall texels of a texture of this scene that lie at least two pixel
    footprints from a temperature edge (window, frame, door: :func:`discontinuity_distance`).

    Parameters
    ----------
    scene : BuildingScene
    result : thermogrammetry.products.texture.TextureResult
    view_centers : (K, 3) array, the TRUE centre of each of the texture's views (the truth is the apparent
        temperature seen from there: :func:`apparent_temperature`; footprints use the scene's camera)
    """
    sel, tx = result.texel_selection, result.texels
    ok = sel.source >= 0
    P, F = tx.points[ok], tx.face[ok]
    C = np.asarray(view_centers, float)[sel.source[ok]]
    err = np.abs(sel.temperature_k[ok] - apparent_temperature(scene, P, F, C))
    v = C - P
    dist = np.linalg.norm(v, axis=1)
    cos_t = np.abs(np.einsum("ij,ij->i", scene.face_normals[F], v / dist[:, None]))
    foot = dist / scene.thermal.K[0, 0] / np.maximum(cos_t, 0.2)
    clean = (discontinuity_distance(scene, P, scene.face_group[F]) > 2.0 * foot) & (scene.face_group[F] == GROUPS.index("wall"))
    return err[clean]


def _ring_point(u, L, D, H, r):
    """Point at arc length ``u`` on the ring at distance ``r`` around the footprint (counter-clockwise from
    the south-west corner along the south side) and the wall point it looks at."""
    segs = [("S", L), ("cSE", np.pi / 2 * r), ("E", D), ("cNE", np.pi / 2 * r), ("N", L), ("cNW", np.pi / 2 * r),
            ("W", D), ("cSW", np.pi / 2 * r)]
    for name, length in segs:
        if u <= length:
            break
        u -= length
    zt = 0.45 * H
    if name == "S":
        return np.array([u, -r, 0.0]), np.array([u, 0.0, zt])
    if name == "E":
        return np.array([L + r, u, 0.0]), np.array([L, u, zt])
    if name == "N":
        return np.array([L - u, D + r, 0.0]), np.array([L - u, D, zt])
    if name == "W":
        return np.array([-r, D - u, 0.0]), np.array([0.0, D - u, zt])
    a = u / r  # corner arcs
    corner, start = {"cSE": ((L, 0), -np.pi / 2), "cNE": ((L, D), 0.0), "cNW": ((0, D), np.pi / 2), "cSW": ((0, 0), np.pi)}[name]
    phi = start + a
    P = np.array([corner[0] + r * np.cos(phi), corner[1] + r * np.sin(phi), 0.0])
    return P, np.array([corner[0], corner[1], zt])


def _waves(scene: BuildingScene, a, b) -> np.ndarray:
    """The sum of the scene's plane waves at (a, b), evaluated in chunks of 8192 points (the (chunk, waves) temporaries
    stay in cache; each point's sum is the same as in one pass)."""
    w = scene.waves
    shape = np.broadcast_shapes(np.shape(a), np.shape(b))
    af = np.broadcast_to(np.asarray(a, float), shape).reshape(-1)
    bf = np.broadcast_to(np.asarray(b, float), shape).reshape(-1)
    out = np.empty(af.size)
    for i in range(0, af.size, 8192):
        ac, bc = af[i : i + 8192], bf[i : i + 8192]
        out[i : i + 8192] = np.sum(w[:, 3] * np.sin(np.multiply.outer(ac, w[:, 0]) + np.multiply.outer(bc, w[:, 1]) + w[:, 2]),
                                   axis=-1)
    return out.reshape(shape)


def surface_temperature(scene: BuildingScene, points, group) -> np.ndarray:
    """True surface temperature (K) of points (N, 3) on faces of the given group index (N,) or scalar."""
    c = scene.config
    P = np.asarray(points, float).reshape(-1, 3)
    g = np.broadcast_to(np.asarray(group), (len(P),))
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    L, D, H = c.length_m, c.depth_m, c.height_m
    out = np.full(len(P), np.nan)
    wall = g == GROUPS.index("wall")
    if np.any(wall):
        xw, yw, zw = x[wall], y[wall], z[wall]
        # arc length around the perimeter, counter-clockwise from (0, 0) along the south wall
        s = _wall_s(scene, xw, yw)
        t = 281.0 + 0.25 * zw + 0.6 * np.sin(2 * np.pi * s / (2 * (L + D)))
        for k in range(1, c.floors):
            t = t + 1.5 * np.exp(-0.5 * ((zw - k * H / c.floors) / 0.35) ** 2)
        t = t - 1.8 * np.exp(-0.5 * (((s - 0.7 * L) / 1.2) ** 2 + ((zw - 0.7) / 0.5) ** 2))
        out[wall] = _detail(scene, s, zw, t + _waves(scene, s, zw))
    roof = g == GROUPS.index("roof")
    out[roof] = 276.0 + _waves(scene, x[roof], y[roof])
    ground = g == GROUPS.index("ground")
    out[ground] = 279.0 + 0.7 * _waves(scene, x[ground], y[ground])
    occ = g == GROUPS.index("occluder")
    out[occ] = 286.0 + 0.3 * z[occ] + 0.5 * _waves(scene, x[occ] + y[occ], z[occ])
    return out


def _emissivity(scene: BuildingScene, theta, group) -> np.ndarray:
    c = scene.config
    if c.emissivity >= 1.0:
        return np.ones_like(np.asarray(theta, float))
    f = fresnel_emissivity(theta, 1.5) / float(fresnel_emissivity(0.0, 1.5))
    return np.where(np.asarray(group) == GROUPS.index("wall"), c.emissivity * f, 1.0)


def apparent_temperature(scene: BuildingScene, points, face_index, center, *, curve=None) -> np.ndarray:
    """Noise-free apparent (black-body equivalent) temperature (K) of surface points seen from ``center``.

    Parameters
    ----------
    points : (N, 3) points on the mesh, metres
    face_index : (N,) index of the face each point lies on
    center : (3,) or (N, 3) projection centre of the viewing camera

    With the default scene (``emissivity = 1``, no atmosphere) this is :func:`surface_temperature`.
    """
    from ..radiometry.atmosphere import atmospheric_transmission

    c = scene.config
    curve = curve or FlirCurve()
    P = np.asarray(points, float).reshape(-1, 3)
    fi = np.asarray(face_index, int).reshape(-1)
    g = scene.face_group[fi]
    T = surface_temperature(scene, P, g)
    if c.emissivity >= 1.0 and not c.atmosphere:
        return T
    v = np.asarray(center, float) - P
    dist = np.linalg.norm(v, axis=1)
    cos_t = np.clip(np.einsum("ij,ij->i", scene.face_normals[fi], v / dist[:, None]), 0.0, 1.0)
    eps = _emissivity(scene, np.arccos(cos_t), g)
    s_sky = float(curve.signal(c.sky_k))
    sig = eps * curve.signal(T) + (1 - eps) * s_sky
    if c.atmosphere:
        tau = atmospheric_transmission(dist, c.air_k, c.relative_humidity)
        sig = tau * sig + (1 - tau) * float(curve.signal(c.air_k))
    return curve.temperature(sig)


def render_building_thermal(scene: BuildingScene, station: int, *, sensor: bool = True, pose=None,
                            with_truth: bool = False) -> dict:
    """Thermal image (float32 K) of one station (``pose`` overrides the station's true pose).

    Returns ``{"image_k": (H, W) float32}``; with ``with_truth`` also ``face_index`` (H, W; -1 = sky),
    ``points`` (H, W, 3) and ``apparent_k`` (H, W) at the pixel centres.
    """
    c = scene.config
    name, true_pose = scene.stations[station]
    pose = pose or true_pose
    cam = scene.thermal
    w, h = cam.image_size
    ss2 = c.supersample**2
    d = np.einsum("...i,ij->...j", _sample_rays(cam, c.supersample), pose.R)
    C = pose.center
    tri, t, pts, _ = _cast_mesh(scene, C, d)
    hit = tri >= 0
    curve = FlirCurve()
    sig = np.full(len(d), float(curve.signal(c.sky_k)))
    sig[hit] = curve.signal(apparent_temperature(scene, pts[hit], tri[hit], C, curve=curve))
    img = sig.reshape(h, w, ss2).mean(axis=2)
    effects = c.sensor if sensor else SensorEffects()
    out = {"image_k": apply_sensor_effects(img, curve, effects, np.random.default_rng([c.seed, station, 0xB7])).astype(np.float32)}
    if with_truth:
        d1 = np.einsum("...i,ij->...j", _sample_rays(cam, 1), pose.R)
        tri1, _, pts1, _ = _cast_mesh(scene, C, d1)
        app = np.full(len(d1), np.nan)
        app[tri1 >= 0] = apparent_temperature(scene, pts1[tri1 >= 0], tri1[tri1 >= 0], C)
        out.update(face_index=tri1.reshape(h, w), points=pts1.reshape(h, w, 3), apparent_k=app.reshape(h, w))
    return out


def write_building_survey(project, scene: BuildingScene, *, sensor: bool = True, prefix: str = "") -> dict:
    """Render every station and write a survey folder with the TRUE poses through ``project``:

    ``cameras.json`` (:class:`~thermogrammetry.io.oriented.OrientedCameras`), ``frames/<name>.tif``
    (float32 K), ``mesh.obj`` (the whole scene, occluder and ground included) and
    ``truth/face_group.json`` (group name per face).
    """
    import io

    import tifffile

    from ..io.oriented import OrientedCameras, OrientedImage

    p = (prefix.rstrip("/") + "/") if prefix else ""
    images = []
    for k, (name, pose) in enumerate(scene.stations):
        img = render_building_thermal(scene, k, sensor=sensor)["image_k"]
        buf = io.BytesIO()
        tifffile.imwrite(buf, img.astype(np.float32))
        project.write_bytes(f"{p}frames/{name}.tif", buf.getvalue())
        images.append(OrientedImage(name, "thermal", pose.R, pose.t, frame=f"frames/{name}.tif",
                                    source=f"synthetic building station {k}", unit="K", sensor="thermal"))
    oc = OrientedCameras({"thermal": scene.thermal}, images, crs=None,
                         notes="synthetic building: TRUE poses (thermogrammetry.synthetic.building)")
    import json

    project.write_text(f"{p}cameras.json", json.dumps(oc.to_dict(), indent=1) + "\n")
    lines = ["# thermogrammetry synthetic building (groups per face in truth/face_group.json)"]
    lines += [f"v {v[0]:.6f} {v[1]:.6f} {v[2]:.6f}" for v in scene.vertices]
    lines += [f"f {a + 1} {b + 1} {c_ + 1}" for a, b, c_ in scene.faces]
    project.write_text(f"{p}mesh.obj", "\n".join(lines) + "\n")
    project.write_json(f"{p}truth/face_group.json", [GROUPS[g] for g in scene.face_group])
    return {"stations": len(scene.stations), "faces": int(len(scene.faces))}


def write_building_user_files(project, scene: BuildingScene, *, gnss_noise_m: float = 0.03,
                              gnss_sigma_m: tuple = (0.03, 0.03, 0.05), seed: int = 1, prefix: str = "") -> None:
    """What a user brings to ``survey`` besides the frames (:func:`write_building_survey` writes those), through
    ``project``: ``gnss.csv`` (``image,X,Y,Z,sX,sY,sZ``: the true centres plus a seeded N(0, ``gnss_noise_m``²) on
    every axis, σ columns ``gnss_sigma_m``, as an RTK rover on a pole gives them) and ``camera.json`` (the true
    camera, as ``calibrate`` would give it)."""
    import json

    p = (prefix.rstrip("/") + "/") if prefix else ""
    rng = np.random.default_rng(seed)
    sx, sy, sz = gnss_sigma_m
    rows = ["image,X,Y,Z,sX,sY,sZ"]
    for name, pose in scene.stations:
        C = pose.center + rng.normal(0, gnss_noise_m, 3)
        rows.append(f"{name},{C[0]:.4f},{C[1]:.4f},{C[2]:.4f},{sx:g},{sy:g},{sz:g}")
    project.write_text(f"{p}gnss.csv", "\n".join(rows) + "\n")
    project.write_text(f"{p}camera.json", json.dumps(scene.thermal.to_dict(), indent=2) + "\n")
