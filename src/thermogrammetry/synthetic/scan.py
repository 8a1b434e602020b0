"""A laser-scan-like point cloud of a mesh: points sampled uniformly on its surface, Gaussian noise, a hole cut out.

:func:`scan_cloud` samples ``density`` points per m² on the triangles (area-weighted, seeded), removes the points
of a rectangular hole (``hole``: a patch of a plane, e.g. 1 m × 1 m of a wall, where the scanner saw nothing), and
adds isotropic Gaussian noise of ``noise_m`` per axis. No normals: a scan file has none. The truth kept beside the
cloud: each point's noise-free position and its triangle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError

__all__ = ["ScanHole", "ScanCloud", "scan_cloud", "building_wall_hole", "building_scan"]


@dataclass(frozen=True)
class ScanHole:
    """A rectangle of a plane with no points: centre (m), two orthogonal in-plane unit directions and half-sizes
    (m); points within ``depth_m`` of the plane and inside the rectangle are removed."""

    center: tuple[float, float, float]
    u: tuple[float, float, float]
    v: tuple[float, float, float]
    half_u_m: float
    half_v_m: float
    depth_m: float = 0.05

    @property
    def area_m2(self) -> float:
        return 4.0 * self.half_u_m * self.half_v_m

    def contains(self, X) -> np.ndarray:
        c, u, v = (np.asarray(a, float) for a in (self.center, self.u, self.v))
        w = np.cross(u, v)
        Q = np.asarray(X, float) - c
        return (np.abs(Q @ u) <= self.half_u_m) & (np.abs(Q @ v) <= self.half_v_m) & (np.abs(Q @ w) <= self.depth_m)


@dataclass
class ScanCloud:
    """Points (N, 3) with noise, their noise-free positions (N, 3) and triangle indices (N,)."""

    points: np.ndarray
    truth: np.ndarray
    face: np.ndarray


def building_wall_hole(scene, area_m2: float = 1.0) -> ScanHole:
    """A square hole of ``area_m2`` in the middle of the synthetic building's east wall (x = length, facing +x)."""
    c = scene.config
    s = 0.5 * np.sqrt(float(area_m2))
    return ScanHole((c.length_m, 0.5 * c.depth_m, 0.5 * c.height_m), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), s, s)


def scan_cloud(vertices, faces, *, density: float, noise_m: float, hole: ScanHole | None = None,
               seed: int = 0, offset=(0.0, 0.0, 0.0)) -> ScanCloud:
    """Sample the mesh ``(vertices, faces)`` like a scan (see the module docstring).

    ``density`` points per m² (expected), ``noise_m`` σ per axis (m), ``offset`` added to every coordinate (to put
    the cloud at a projected CRS's coordinates).
    """
    if not (np.isfinite(density) and density > 0):
        raise ConfigError(f"scan_cloud density={density!r}: expected points per m² > 0")
    if not (np.isfinite(noise_m) and noise_m >= 0):
        raise ConfigError(f"scan_cloud noise_m={noise_m!r}: expected a standard deviation >= 0 m")
    V = np.asarray(vertices, float)
    F = np.asarray(faces, np.int64)
    a = V[F[:, 1]] - V[F[:, 0]]
    b = V[F[:, 2]] - V[F[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(a, b), axis=1)
    rng = np.random.default_rng([seed, 0x5CA7])
    n = rng.poisson(area * density)
    face = np.repeat(np.arange(len(F)), n)
    r1, r2 = rng.random(len(face)), rng.random(len(face))
    flip = r1 + r2 > 1
    r1, r2 = np.where(flip, 1 - r1, r1), np.where(flip, 1 - r2, r2)
    X = V[F[face, 0]] + r1[:, None] * a[face] + r2[:, None] * b[face]
    if hole is not None:
        keep = ~hole.contains(X)
        X, face = X[keep], face[keep]
    P = X + rng.normal(0.0, noise_m, X.shape)
    off = np.asarray(offset, float)
    return ScanCloud(P + off, X + off, face)


def building_scan(scene, *, density: float, noise_m: float, hole_area_m2: float = 1.0, ground_m: float = 2.5,
                  seed: int = 0, offset=(0.0, 0.0, 0.0)) -> tuple[ScanCloud, ScanHole]:
    """A terrestrial scan of the synthetic building (:func:`~thermogrammetry.synthetic.building.make_building`):
    its walls, roof, occluder and the ground within ``ground_m`` of the walls (and around the occluder), without
    the ground under the occluder (a scanner does not see it), a square hole of ``hole_area_m2`` in the east wall
    (:func:`building_wall_hole`). Returns ``(cloud, hole)``."""
    c = scene.config
    hole = building_wall_hole(scene, hole_area_m2)
    cl = scan_cloud(scene.vertices, scene.faces, density=density, noise_m=0.0, hole=hole, seed=seed)
    X = cl.truth
    ox, oy, oz = c.occluder_size_m
    xc, yc = c.occluder_x_m, -c.occluder_distance_m
    inside = ((np.abs(X[:, 0] - xc) < ox / 2 - 1e-6) & (np.abs(X[:, 1] - yc) < oy / 2 - 1e-6) & (X[:, 2] < oz - 1e-6))
    y0 = min(-ground_m, yc - oy / 2 - 1.0)
    keep = ~inside & (X[:, 0] >= -ground_m) & (X[:, 0] <= c.length_m + ground_m) & (X[:, 1] >= y0) \
        & (X[:, 1] <= c.depth_m + ground_m)
    X, face = X[keep], cl.face[keep]
    rng = np.random.default_rng([seed, 0x5CA8])
    P = X + rng.normal(0.0, noise_m, X.shape)
    off = np.asarray(offset, float)
    return ScanCloud(P + off, X + off, face), hole
