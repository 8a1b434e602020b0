"""A triangle mesh from a point cloud: the cloud's scale, the block lattice, and the mesh's finishing steps.

The surface of each block of space is :func:`thermogrammetry.products.mesh_surface.mesh_block` (outliers, oriented
normals, signed distance near the points, marching cubes, trimming). This module decides the scale those work at,
from the cloud itself (:func:`cloud_scale`), lays the lattice of blocks (:func:`make_lattice`) and, once the
blocks are meshed, stitches them and finishes the mesh (:func:`finish_mesh`): loose pieces smaller than
``min_piece_cells2`` cells² removed, holes up to ``fill_holes_m2`` filled and flagged
(:mod:`~thermogrammetry.products.mesh_repair`), decimation to ``edge_m`` or ``faces`` with its measured error
(:mod:`~thermogrammetry.products.mesh_decimate`). Nothing here reads or writes files; ``pipeline.mesh`` does.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from .mesh_surface import Lattice, SurfaceConfig, outlier_threshold, pca_normals, triangle_areas

__all__ = ["MeshConfig", "CloudScale", "cloud_scale", "make_lattice", "finish_mesh", "MIN_POINTS"]

#: fewer points than this are refused (a surface needs neighbourhoods of ``k_normal`` points in many places)
MIN_POINTS = 100


@dataclass(frozen=True)
class MeshConfig:
    """What ``mesh`` makes: the block surface (:class:`SurfaceConfig`), holes up to ``fill_holes_m2`` filled (0 =
    none), decimation to ``edge_m`` (m) or ``faces`` (at most one), loose pieces below ``min_piece_cells2`` lattice
    cells² removed."""

    surface: SurfaceConfig = field(default_factory=SurfaceConfig)
    fill_holes_m2: float = 1.0
    edge_m: float | None = None
    faces: int | None = None
    min_piece_cells2: float = 400.0

    def __post_init__(self):
        f = self.fill_holes_m2
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not np.isfinite(f) or f < 0:
            raise ConfigError(f"--fill-holes {f!r}: expected the largest hole to fill, in m² (>= 0; 0 = fill none)")
        if self.edge_m is not None and self.faces is not None:
            raise ConfigError(f"--edge {self.edge_m!r} and --faces {self.faces!r}: give one of them (a target edge "
                              "length or a face count)")
        if self.edge_m is not None and not (np.isfinite(self.edge_m) and self.edge_m > 0):
            raise ConfigError(f"--edge {self.edge_m!r}: expected a positive target edge length in metres")
        if self.faces is not None and (isinstance(self.faces, bool) or int(self.faces) != self.faces or self.faces < 4):
            raise ConfigError(f"--faces {self.faces!r}: expected a whole number of triangles >= 4")
        if not (np.isfinite(self.min_piece_cells2) and self.min_piece_cells2 >= 0):
            raise ConfigError(f"MeshConfig.min_piece_cells2={self.min_piece_cells2!r}: expected a number >= 0")


@dataclass(frozen=True)
class CloudScale:
    """The cloud's scale: median point spacing (m, nearest neighbour), noise (m, median RMS residual of local
    planes of ``k_normal`` points), the lattice cell (m) and the outlier threshold and search bound (m)."""

    spacing_m: float
    noise_m: float
    cell_m: float
    outlier_threshold_m: float
    outlier_bound_m: float
    neighbourhoods: int

    def as_dict(self) -> dict:
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def cloud_scale(neighbourhoods, cfg: SurfaceConfig) -> CloudScale:
    """The cloud's scale from a few complete neighbourhoods (every point of the cloud within a radius of a seed).

    Each item of ``neighbourhoods`` is ``(seed (3,), points (n, 3))``; the statistics are taken on the points within
    half the radius of the seed (their neighbours are all in the set), pooled, and their medians used:
    cell = ``cfg.cell_m`` or ``max(3 × spacing, 2.5 × noise)``; outlier threshold as
    :func:`~thermogrammetry.products.mesh_surface.outlier_threshold` of the mean distance to ``k_outlier`` neighbours,
    search bound twice that.
    """
    from scipy.spatial import cKDTree

    nn, res, stat = [], [], []
    used = 0
    for seed, P in neighbourhoods:
        if len(P) < cfg.k_normal + 2:
            continue
        r = np.linalg.norm(P - seed, axis=1)
        inner = r <= 0.5 * r.max()
        if inner.sum() < 3:
            continue
        used += 1
        tree = cKDTree(P)
        d, _ = tree.query(P[inner], k=cfg.k_outlier + 1)
        nn.append(d[:, 1])
        stat.append(d[:, 1:].mean(axis=1))
        n, ok = pca_normals(tree, P, P[inner], cfg.k_normal, np.inf)
        _, idx = tree.query(P[inner], k=cfg.k_normal)
        nb = P[idx]
        q = nb - nb.mean(axis=1, keepdims=True)
        res.append(np.sqrt(np.mean(np.einsum("mkj,mj->mk", q, n) ** 2, axis=1))[ok])
    if not nn:
        raise ConfigError("the cloud has no neighbourhood of enough points to measure its spacing")
    spacing = float(np.median(np.concatenate(nn)))
    noise = float(np.median(np.concatenate(res)))
    if spacing <= 0:  # duplicated points: the spacing of distinct ones
        d = np.concatenate(nn)
        spacing = float(np.median(d[d > 0])) if np.any(d > 0) else 0.0
    cell = float(cfg.cell_m) if cfg.cell_m is not None else max(3.0 * spacing, 2.5 * noise)
    if not (np.isfinite(cell) and cell > 0):
        raise ConfigError("the cloud's points coincide (no spacing between them); expected a surface of distinct points")
    thr = outlier_threshold(np.concatenate(stat), cfg.outlier_mads)
    thr = max(thr, 0.5 * cell)
    return CloudScale(spacing, noise, cell, float(thr), float(2.0 * thr), used)


def make_lattice(lo, hi, h: float, block: int) -> Lattice:
    """The lattice covering the box ``[lo, hi]`` (local m) with two cells to spare on every side."""
    lo = np.asarray(lo, float) - 2.0 * h
    hi = np.asarray(hi, float) + 2.0 * h
    shape = tuple(int(max(1, np.ceil((hi[k] - lo[k]) / (h * block)))) for k in range(3))
    return Lattice(tuple(float(x) for x in lo), float(h), int(block), shape)


def finish_mesh(blocks, lattice: Lattice, cfg: MeshConfig, *, on_step=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Stitch the block meshes and finish the mesh (see the module docstring).

    Returns ``(V (V, 3) local m, F (F, 3), filled (F,) bool, report)``; ``report`` has the counts and areas
    ``mesh.json`` records (``trimmed_area_m2``, ``pieces_removed``, ``holes``, ``decimation``).
    """
    from .mesh_decimate import decimate, target_faces
    from .mesh_repair import drop_small_components, fill_holes, weld

    step = on_step or (lambda name: None)
    step("stitching blocks")
    V, F = weld([b.vertices for b in blocks], [b.faces for b in blocks], lattice.h)
    trimmed = float(sum(b.trimmed_area_m2 for b in blocks))
    step("removing loose pieces")
    V, F, n_pieces, piece_area = drop_small_components(V, F, cfg.min_piece_cells2 * lattice.h ** 2)
    step("filling holes")
    if cfg.fill_holes_m2 > 0:
        V, F, filled, holes = fill_holes(V, F, cfg.fill_holes_m2)
    else:
        from .mesh_repair import HoleReport, boundary_loops

        filled, holes = np.zeros(len(F), bool), HoleReport()
        holes.left_open = len(boundary_loops(F))
    area_full = float(triangle_areas(V, F).sum()) if len(F) else 0.0
    n_target = target_faces(V, F, edge_m=cfg.edge_m, faces=cfg.faces) if len(F) else None
    dec = {"faces_before": int(len(F)), "faces_after": int(len(F)), "rms_m": 0.0, "max_m": 0.0, "decimated": False}
    if n_target is not None:
        step("decimating")
        V, F, filled, dec = decimate(V, F, filled, n_target)
    dec["target_faces"] = n_target
    dec["edge_m"] = cfg.edge_m
    dec["faces"] = cfg.faces
    areas = triangle_areas(V, F) if len(F) else np.zeros(0)
    report = {
        "trimmed_area_m2": trimmed,
        "pieces_removed": {"count": int(n_pieces), "area_m2": piece_area,
                           "below_m2": cfg.min_piece_cells2 * lattice.h ** 2},
        "holes": {"filled": holes.filled, "filled_faces_before_decimation": holes.filled_faces,
                  "filled_area_m2_before_decimation": holes.filled_area_m2,
                  "areas_filled_m2": holes.areas_filled_m2, "left_open": holes.left_open,
                  "left_open_area_m2": holes.left_open_area_m2, "largest_open_m2": holes.largest_open_m2,
                  "fill_holes_m2": cfg.fill_holes_m2},
        "decimation": dec,
        "area_m2": float(areas.sum()),
        "area_before_decimation_m2": area_full,
        "filled_area_m2": float(areas[filled].sum()) if len(F) else 0.0,
    }
    return V, F, np.asarray(filled, bool), report
