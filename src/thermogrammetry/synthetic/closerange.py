"""Synthetic replica of seed 000's close-range video-thermal set-up, with exact ground truth.

A box-shaped device (a computer monitor in the paper) about 2 m in front of two to four optical
cameras and one thermal camera; 6 control points and 11 pass points at the coordinates of seed 000
Table 1; hot planar faces picked by groups of marked points; image measurements with Gaussian noise;
a rendered thermal image whose apparent (black-body) temperature follows the cosine law — or any
chosen directional emissivity — in front of an ambient background.

Rendering model (per pixel centre, OpenCV origin): the pixel's ray is intersected with every hot
face's plane; inside the face's projected polygon (convex hull of its marked points' projections) the
nearest face wins. With θ the angle between the line of sight and the face normal, ε(θ) the
directional emissivity (``cos θ`` for the cosine law, seed 000 eq. 7) and ``Ta`` the ambient
temperature reflected by the face, the camera sees the total-radiation (Stefan–Boltzmann) balance

    T0⁴ = ε(θ) T⁴ + (1 − ε(θ)) Ta⁴,

which is exactly the inverse of seed 000 eq. 8 when ε = cos θ. Outside every face the pixel shows
``Ta``.

References
----------
Sawicki P., Stein R., Więcek B., *Directional emissivity correction by photogrammetric 3D object
reconstruction* (seed 000), Table 1 and eq. 5–8.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

from ..errors import InvalidInputError
from ..geometry import Pose

__all__ = [
    "TABLE1_CONTROL",
    "TABLE1_PASS",
    "DEFAULT_PLANES",
    "SceneCamera",
    "HotFace",
    "CloseRangeScene",
    "make_closerange_scene",
    "measure",
    "measurements_csv",
    "render_thermal",
    "fit_plane_exact",
    "convex_polygon_mask",
]

#: seed 000 Table 1, 3D control point coordinates (m)
TABLE1_CONTROL: dict[str, tuple[float, float, float]] = {
    "2": (1.7715, 2.8925, 1.1060),
    "3": (2.0655, 2.8910, 1.1065),
    "6": (1.7280, 3.2165, 1.1670),
    "8": (2.1120, 3.2140, 1.1670),
    "10": (1.7450, 2.9905, 0.7845),
    "11": (2.0955, 2.9835, 0.7845),
}
#: seed 000 Table 1, final computed 3D pass point coordinates (m) -- the truth of the replica
TABLE1_PASS: dict[str, tuple[float, float, float]] = {
    "1": (1.7705, 2.9070, 0.8485),
    "4": (2.0655, 2.9055, 0.8490),
    "5": (1.7260, 3.2310, 0.8620),
    "7": (1.9185, 3.1430, 1.1635),
    "9": (2.1160, 3.2290, 0.8625),
    "12": (1.7955, 2.8965, 1.0005),
    "13": (2.0410, 2.8940, 1.0010),
    "14": (1.8520, 2.8920, 0.9240),
    "15": (1.9900, 2.8900, 0.9245),
    "16": (1.7180, 3.2170, 1.1810),
    "17": (2.1220, 3.2140, 1.1820),
}
#: faces of the device picked by marked points (listed around the face)
DEFAULT_PLANES: dict[str, tuple[str, ...]] = {
    "front": ("1", "4", "3", "2"),
    "top": ("2", "3", "8", "6"),
    "right": ("4", "9", "17", "3"),
}


@dataclass(frozen=True)
class SceneCamera:
    """A true camera of the scene: ideal pinhole ``K`` (px), ``pose`` (cam_from_world), size (w, h)."""

    name: str
    K: np.ndarray
    pose: Pose
    image_size: tuple[int, int]
    kind: str  # "optical" | "thermal"
    model: object | None = None  # a thermogrammetry.Camera with distortion; None: ideal pinhole K

    @property
    def P(self) -> np.ndarray:
        """3×4 projection matrix ``K [R | t]`` (px)."""
        return self.K @ np.hstack([self.pose.R, self.pose.t[:, None]])

    def project(self, points_world) -> np.ndarray:
        """(N, 3) world points (m) → (N, 2) px (OpenCV origin)."""
        Xc = self.pose.transform(np.asarray(points_world, float))
        if self.model is not None:
            return np.asarray(self.model.project(Xc), float)
        uvw = Xc @ self.K.T
        return uvw[:, :2] / uvw[:, 2:3]

    def rays(self, xy_px) -> np.ndarray:
        """(N, 2) px → (N, 3) unit line-of-sight directions in the world frame."""
        xy = np.asarray(xy_px, float)
        if self.model is not None:
            d = np.asarray(self.model.unproject(xy), float) @ self.pose.R
        else:
            d = np.linalg.solve(self.K, np.column_stack([xy, np.ones(len(xy))]).T).T @ self.pose.R
        return d / np.linalg.norm(d, axis=1, keepdims=True)


@dataclass(frozen=True)
class HotFace:
    """A hot planar face: marked point ids, true temperature (K), plane ``n·X + d = 0`` (unit n)."""

    name: str
    ids: tuple[str, ...]
    temperature_k: float
    normal: np.ndarray
    d: float


@dataclass
class CloseRangeScene:
    """Ground truth of the replica.

    Attributes
    ----------
    control, passpoints : dict id → (3,) m
    cameras : list of SceneCamera (optical first, thermal last)
    thermal : name of the thermal camera
    faces : list of HotFace (the planes of ``planes.csv``)
    ambient_k : ambient (reflected) temperature, K
    """

    control: dict[str, np.ndarray]
    passpoints: dict[str, np.ndarray]
    cameras: list[SceneCamera]
    thermal: str
    faces: list[HotFace]
    ambient_k: float = 295.15
    extra: dict = field(default_factory=dict)

    def camera(self, name: str) -> SceneCamera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise InvalidInputError(f"camera {name!r} not in scene; expected one of {[c.name for c in self.cameras]}")

    @property
    def points(self) -> dict[str, np.ndarray]:
        return {**self.control, **self.passpoints}

    def control_csv(self) -> str:
        lines = ["id,X,Y,Z"] + [f"{k},{v[0]:.6f},{v[1]:.6f},{v[2]:.6f}" for k, v in self.control.items()]
        return "\n".join(lines) + "\n"

    def planes_csv(self) -> str:
        m = max(len(f.ids) for f in self.faces)
        head = "name," + ",".join(f"id{k + 1}" for k in range(m))
        return "\n".join([head] + [",".join([f.name, *f.ids]) for f in self.faces]) + "\n"


def fit_plane_exact(points) -> tuple[np.ndarray, float]:
    """Least-squares plane (unit normal n, d) with ``n·X + d = 0`` through (N ≥ 3, 3) points."""
    P = np.asarray(points, float)
    c = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - c)
    n = vt[-1]
    return n, float(-n @ c)


def make_closerange_scene(
    *,
    n_optical: int = 2,
    distance_m: float = 2.0,
    baseline_m: float = 1.2,
    control: Mapping[str, Sequence[float]] | None = None,
    passpoints: Mapping[str, Sequence[float]] | None = None,
    planes: Mapping[str, Sequence[str]] | None = None,
    face_temperatures_k: Mapping[str, float] | None = None,
    ambient_k: float = 295.15,
    optical_size: tuple[int, int] = (1600, 1200),
    optical_focal_px: float = 3000.0,
    thermal_size: tuple[int, int] = (640, 480),
    thermal_focal_px: float = 1400.0,
    thermal_center: Sequence[float] | None = None,
    thermal_distortion: Mapping[str, float] | None = None,
    optical_distortion: Mapping[str, float] | None = None,
) -> CloseRangeScene:
    """Build the replica of seed 000: Table 1 points, optical cameras ~2 m away, one thermal camera.

    Parameters
    ----------
    n_optical : int
        2–4 optical cameras, spread along a horizontal baseline of ``baseline_m`` in front of the
        device (the paper's system had four optical channels; its Table 1 used two images).
    distance_m : float
        Distance from the cameras to the device centre (m).
    control, passpoints : mapping id → (X, Y, Z) m, optional
        Default: seed 000 Table 1.
    planes : mapping name → ids, optional
        Hot faces (default :data:`DEFAULT_PLANES`).
    face_temperatures_k : mapping name → K, optional
        Default: 318.15 K, 313.15 K, 308.15 K, ... for the faces in order.
    thermal_center : (3,) m, optional
        Projection centre of the thermal camera; default an oblique station to the right so the
        faces are seen at 20°–60°.
    optical_distortion : mapping, optional
        OpenCV forward-form distortion of every optical camera (``k1``, ``p1``, ...), as for the thermal.
    thermal_distortion : mapping, optional
        OpenCV forward-form distortion of the thermal camera (``k1``, ``k2``, ``p1``, ``p2``, ...);
        the truth camera is then a ``thermogrammetry.Camera`` (model ``opencv``).
    """
    if not 2 <= n_optical <= 4:
        raise InvalidInputError(f"n_optical={n_optical}: expected 2 to 4 optical cameras")
    control = {str(k): np.asarray(v, float) for k, v in (control or TABLE1_CONTROL).items()}
    passpoints = {str(k): np.asarray(v, float) for k, v in (passpoints or TABLE1_PASS).items()}
    planes = dict(planes or DEFAULT_PLANES)
    allpts = {**control, **passpoints}
    centre = np.mean(list(allpts.values()), axis=0)
    # cameras in front of the device (−Y side), slightly above, looking at its centre
    view = np.array([0.0, -1.0, 0.35])
    view /= np.linalg.norm(view)
    xs = np.linspace(-baseline_m / 2, baseline_m / 2, n_optical)
    cams: list[SceneCamera] = []
    for i, dx in enumerate(xs):
        C = centre + distance_m * view + np.array([dx, 0.0, 0.08 * (i % 2)])
        pose = Pose.look_at(C, centre)
        K = np.array([[optical_focal_px, 0, (optical_size[0] - 1) / 2 + 3.0],
                      [0, optical_focal_px * 1.001, (optical_size[1] - 1) / 2 - 2.0], [0, 0, 1]])
        omodel = None
        if optical_distortion:
            from ..camera import Camera

            omodel = Camera("opencv", tuple(optical_size), {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2],
                                                             "cy": K[1, 2], **dict(optical_distortion)})
        cams.append(SceneCamera(f"opt{i + 1}", K, pose, tuple(optical_size), "optical", omodel))
    if thermal_center is None:
        Ct = centre + np.array([0.95, -1.65, 0.75])
    else:
        Ct = np.asarray(thermal_center, float)
    Kt = np.array([[thermal_focal_px, 0, (thermal_size[0] - 1) / 2], [0, thermal_focal_px, (thermal_size[1] - 1) / 2],
                   [0, 0, 1]])
    model = None
    if thermal_distortion:
        from ..camera import Camera

        model = Camera("opencv", tuple(thermal_size), {"fx": Kt[0, 0], "fy": Kt[1, 1], "cx": Kt[0, 2],
                                                        "cy": Kt[1, 2], **dict(thermal_distortion)})
    cams.append(SceneCamera("thermal", Kt, Pose.look_at(Ct, centre + np.array([0, -0.05, 0])), tuple(thermal_size),
                            "thermal", model))
    temps = dict(face_temperatures_k or {})
    faces = []
    for j, (name, ids) in enumerate(planes.items()):
        missing = [i for i in ids if i not in allpts]
        if missing:
            raise InvalidInputError(f"plane {name!r}: point ids {missing} are not in the scene")
        n, d = fit_plane_exact([allpts[i] for i in ids])
        if n @ (Ct - centre) < 0:  # normal towards the thermal camera side
            n, d = -n, -d
        faces.append(HotFace(name, tuple(ids), float(temps.get(name, 318.15 - 5.0 * j)), n, d))
    return CloseRangeScene(control, passpoints, cams, "thermal", faces, float(ambient_k))


def measure(scene: CloseRangeScene, sigma_px: float = 0.5, rng: np.random.Generator | None = None,
            *, thermal_ids: Sequence[str] | None = None) -> list[tuple[str, str, float, float]]:
    """Image measurements ``(image, id, x, y)`` with Gaussian noise of ``sigma_px`` per coordinate.

    Optical images measure every control and pass point; the thermal image only the pass points
    (seed 000: no control coordinates on the thermal image), or ``thermal_ids`` when given.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    rows = []
    for cam in scene.cameras:
        if cam.kind == "thermal":
            ids = list(thermal_ids) if thermal_ids is not None else list(scene.passpoints)
        else:
            ids = list(scene.points)
        X = np.array([scene.points[i] for i in ids])
        xy = cam.project(X) + sigma_px * rng.standard_normal((len(ids), 2))
        rows += [(cam.name, i, float(x), float(y)) for i, (x, y) in zip(ids, xy)]
    return rows


def measurements_csv(rows) -> str:
    return "image,id,x,y\n" + "".join(f"{a},{b},{x:.6f},{y:.6f}\n" for a, b, x, y in rows)


def convex_polygon_mask(polygon_xy, image_size: tuple[int, int]) -> np.ndarray:
    """Boolean (h, w) mask of pixel centres inside the convex hull of (N ≥ 3, 2) px vertices.

    A pixel whose centre lies exactly on an edge counts as inside.
    """
    from scipy.spatial import ConvexHull

    P = np.asarray(polygon_xy, float)
    w, h = image_size
    hull = ConvexHull(P)
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    inside = np.ones((h, w), bool)
    for a, b, c in hull.equations:  # a x + b y + c <= 0 inside
        inside &= a * u + b * v + c <= 1e-9
    return inside


def render_thermal(
    scene: CloseRangeScene,
    emissivity: Callable[[np.ndarray], np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """Render the thermal camera's apparent temperature image (K) and its truth rasters.

    Parameters
    ----------
    emissivity : callable θ (rad, array) → ε, optional
        Directional emissivity of the faces; default the cosine law ``cos θ`` (seed 000 eq. 7).

    Returns
    -------
    dict with float64 (h, w) arrays ``temperature_k`` (what the camera measures),
    ``true_temperature_k`` (face temperature, ambient outside), ``angle_rad`` (line of sight to
    normal, NaN outside), ``distance_m`` (NaN outside), int ``face`` (index into ``scene.faces``,
    −1 outside) and bool ``inside``.
    """
    emis = (lambda th: np.cos(th)) if emissivity is None else emissivity
    cam = scene.camera(scene.thermal)
    w, h = cam.image_size
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    rays = cam.rays(np.column_stack([u.ravel(), v.ravel()]))
    C = cam.pose.center
    best = np.full(w * h, np.inf)
    face_idx = np.full(w * h, -1)
    angle = np.full(w * h, np.nan)
    for j, f in enumerate(scene.faces):
        poly = cam.project(np.array([scene.points[i] for i in f.ids]))
        inside = convex_polygon_mask(poly, cam.image_size).ravel()
        denom = rays @ f.normal
        s = -(f.normal @ C + f.d) / np.where(np.abs(denom) > 1e-12, denom, np.nan)
        take = inside & (s > 0) & (s < best)
        best[take] = s[take]
        face_idx[take] = j
        angle[take] = np.arccos(np.clip(np.abs(denom[take]), 0.0, 1.0))
    Ta = scene.ambient_k
    T_true = np.full(w * h, Ta)
    T0 = np.full(w * h, Ta)
    sel = face_idx >= 0
    Tf = np.array([f.temperature_k for f in scene.faces])[face_idx[sel]]
    e = emis(angle[sel])
    T_true[sel] = Tf
    T0[sel] = (e * Tf**4 + (1.0 - e) * Ta**4) ** 0.25
    dist = np.where(sel, best, np.nan)
    return {
        "temperature_k": T0.reshape(h, w),
        "true_temperature_k": T_true.reshape(h, w),
        "angle_rad": angle.reshape(h, w),
        "distance_m": dist.reshape(h, w),
        "face": face_idx.reshape(h, w),
        "inside": sel.reshape(h, w),
    }
