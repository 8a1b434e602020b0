"""A surface from a point cloud, one block of space at a time: outliers, oriented normals, a signed distance on a
voxel lattice near the points, marching cubes, and the faces the data do not support trimmed.

Method
------
The cloud's space is divided into blocks of ``C`` × ``C`` × ``C`` cells of one global lattice (cell ``h``). A block
is given the points of its core and of a margin around it (:func:`block_margin`), and every decision it makes
depends only on points within that margin of the lattice nodes it owns, through neighbour searches bounded in
distance, with thresholds that are the same for every block. Neighbouring blocks therefore compute the same values
at the nodes they share, and the triangles they emit meet exactly on the shared faces of the lattice: the block
meshes are stitched by welding equal vertices, with no seam.

1. **Outliers** (Rusu et al. 2008): the mean distance of a point to its ``k`` nearest neighbours; a point whose mean
   distance is above a global threshold (``median + 3 × 1.4826 × max(MAD, 0.2 median)`` of it, estimated once for the
   cloud) is removed.
2. **Normals**: principal axes of the ``k_normal`` nearest neighbours (Hoppe et al. 1992), the sign taken from the
   cloud's own normal where it has one (a dense cloud's, a PLY's ``nx ny nz``), else from the most parallel of the
   four nearest coarse representative points, whose signs were propagated over the whole cloud along a minimum spanning tree of the
   representatives' neighbour graph (Hoppe et al. 1992, §3.3; :func:`orient_representatives`).
3. **Signed distance** at the lattice nodes within ``band`` cells of a point: the Gaussian-weighted mean over the
   ``k_sdf`` nearest points of the distance of the node to each point's tangent plane, ``n_i · (x - p_i)``
   (positive on the side the normals point to, i.e. the side the surface was seen from), over those neighbours
   whose normal is within 35° of the nearest point's (at an edge the two faces are not averaged into a chamfer:
   each node takes the face it is nearest to, as the tangent plane of the nearest point does in Hoppe et al.).
   Nodes further from the data have no value.
4. **Marching cubes** (Lorensen & Cline 1987; Lewiner et al. 2003, scikit-image) over the cubes whose eight
   corners have a value: the zero set, triangles wound so that their normals (right-hand rule) point to the
   positive side.
5. **Trimming**: a triangle whose centroid is farther than ``trim`` cells from every point (after the outliers)
   is not supported by the data and is removed; its area is counted.

References
----------
H. Hoppe, T. DeRose, T. Duchamp, J. McDonald, W. Stuetzle, "Surface reconstruction from unorganized points",
SIGGRAPH 1992.
W. E. Lorensen, H. E. Cline, "Marching cubes: a high resolution 3D surface construction algorithm", SIGGRAPH 1987.
T. Lewiner, H. Lopes, A. W. Vieira, G. Tavares, "Efficient implementation of marching cubes' cases with
topological guarantees", Journal of Graphics Tools 8(2), 2003.
R. B. Rusu, Z. C. Marton, N. Blodow, M. Dolha, M. Beetz, "Towards 3D point cloud based object maps for household
environments", Robotics and Autonomous Systems 56(11), 2008.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError

__all__ = ["SurfaceConfig", "Lattice", "BlockMesh", "block_margin", "pca_normals", "outlier_statistic",
           "outlier_threshold", "block_representatives", "orient_representatives", "mesh_block", "triangle_areas"]


@dataclass(frozen=True)
class SurfaceConfig:
    """Parameters of the block surface (lengths in lattice cells unless named ``_m``).

    ``cell_m`` lattice cell (m; None = 3 × the cloud's median point spacing, at least 2.5 × its noise);
    ``k_outlier``/``outlier_mads`` the outlier statistic; ``k_normal`` neighbours of a normal; ``k_sdf`` points
    averaged into a node's signed distance; ``band`` nodes farther than this from every point have no value;
    ``trim`` faces farther than this from every point are removed; ``block`` cells per block side;
    ``rep_cells`` the coarse representatives' voxel (cells).
    """

    cell_m: float | None = None
    k_outlier: int = 8
    outlier_mads: float = 3.0
    k_normal: int = 16
    k_sdf: int = 8
    band: float = 2.0
    trim: float = 1.5
    block: int = 160
    rep_cells: int = 4

    def __post_init__(self):
        if self.cell_m is not None and not (np.isfinite(self.cell_m) and self.cell_m > 0):
            raise ConfigError(f"--cell {self.cell_m!r}: expected a positive lattice cell size in metres")
        for f in ("k_outlier", "k_normal", "k_sdf", "block", "rep_cells"):
            if int(getattr(self, f)) < 1:
                raise ConfigError(f"SurfaceConfig.{f}={getattr(self, f)!r}: expected a positive integer")
        if self.block % self.rep_cells:
            raise ConfigError(f"SurfaceConfig.block={self.block} must be a multiple of rep_cells={self.rep_cells}")
        for f in ("band", "trim", "outlier_mads"):
            v = float(getattr(self, f))
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"SurfaceConfig.{f}={v!r}: expected a positive number")


@dataclass(frozen=True)
class Lattice:
    """The global lattice: node ``(i, j, k)`` is at ``origin + h · (i, j, k)`` (local coordinates, m); block
    ``(bi, bj, bk)`` owns the cubes ``[b·C, (b+1)·C)`` along each axis and the nodes ``[b·C, (b+1)·C]``."""

    origin: tuple[float, float, float]
    h: float
    block: int
    shape: tuple[int, int, int]  # blocks along x, y, z

    def block_box(self, b) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper corner (m, local) of block ``b``'s cubes."""
        lo = np.asarray(self.origin) + self.h * self.block * np.asarray(b, float)
        return lo, lo + self.h * self.block

    def block_of(self, xyz) -> np.ndarray:
        """(N, 3) block index of each point (clipped into the lattice)."""
        b = np.floor((np.asarray(xyz) - np.asarray(self.origin)) / (self.h * self.block)).astype(np.int64)
        return np.clip(b, 0, np.asarray(self.shape) - 1)


@dataclass
class BlockMesh:
    """One block's surface: vertices (V, 3) float64 local m, triangles (F, 3) int64, and what the block counted."""

    vertices: np.ndarray
    faces: np.ndarray
    points_core: int = 0
    outliers_core: int = 0
    trimmed_area_m2: float = 0.0


def block_margin(h: float, cfg: SurfaceConfig, outlier_bound_m: float) -> float:
    """Distance (m) around a block's cubes whose points the block needs: a node's signed-distance neighbours lie
    within ``band + 2`` cells (bounded search), their normals' neighbours within ``band + 6`` cells more and those
    neighbours' outlier test within ``outlier_bound_m``; one cell to spare."""
    return 2.0 * (cfg.band + 2.0) * h + 4.0 * h + outlier_bound_m + h


def triangle_areas(V, F) -> np.ndarray:
    """(F,) area (m²) of each triangle."""
    a = V[F[:, 1]] - V[F[:, 0]]
    b = V[F[:, 2]] - V[F[:, 0]]
    return 0.5 * np.linalg.norm(np.cross(a, b), axis=1)


def outlier_statistic(tree, pts, k: int, bound_m: float) -> np.ndarray:
    """(N,) mean distance (m) of each point to its ``k`` nearest other points, ``inf`` when fewer than ``k`` lie
    within ``bound_m``."""
    d, _ = tree.query(pts, k=k + 1, distance_upper_bound=bound_m)
    return d[:, 1:].mean(axis=1)


def outlier_threshold(stat: np.ndarray, mads: float) -> float:
    """``median + mads × 1.4826 × max(MAD, 0.2 × median)`` of the finite values of the outlier statistic."""
    s = stat[np.isfinite(stat)]
    if len(s) == 0:
        return float("inf")
    med = float(np.median(s))
    mad = float(np.median(np.abs(s - med)))
    return med + mads * 1.4826 * max(mad, 0.2 * med)  # a regular grid has MAD ~ 0: its border points are no outliers


def pca_normals(tree, pts, query, k: int, bound_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit normal (smallest principal axis of the ``k`` nearest points within ``bound_m``) at each query point,
    unsigned, and a validity flag (at least 5 neighbours). Returns ``(normals (M, 3), valid (M,))``."""
    d, idx = tree.query(query, k=k, distance_upper_bound=bound_m)
    ok = np.isfinite(d)
    cnt = ok.sum(axis=1)
    idx = np.where(ok, idx, 0)
    nb = pts[idx]  # (M, k, 3)
    w = ok[..., None].astype(float)
    mean = (nb * w).sum(axis=1) / np.maximum(cnt, 1)[:, None]
    q = (nb - mean[:, None, :]) * w
    cov = np.matmul(q.transpose(0, 2, 1), q)
    _, vec = np.linalg.eigh(cov)
    n = vec[:, :, 0]
    return n, cnt >= 5


def block_representatives(pts, file_normals, lattice: Lattice, cfg: SurfaceConfig):
    """Coarse representatives of the points of one block's core: the mean point of each occupied voxel of
    ``rep_cells`` cells, its point count and the sum of the cloud's own normals in it (zeros where the cloud has
    none). Returns ``(keys (R,) int64, means (R, 3), counts (R,), normal_sums (R, 3))``."""
    R = lattice.h * cfg.rep_cells
    v = np.floor((pts - np.asarray(lattice.origin)) / R).astype(np.int64)
    key = (v[:, 0] * 1_000_003 + v[:, 1]) * 1_000_003 + v[:, 2]
    uk, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    means = np.zeros((len(uk), 3))
    np.add.at(means, inv, pts)
    means /= cnt[:, None]
    ns = np.zeros((len(uk), 3))
    if file_normals is not None:
        np.add.at(ns, inv, file_normals.astype(float))
    return uk, means, cnt, ns


def orient_representatives(reps, normal_sums, k: int = 8) -> tuple[np.ndarray, dict]:
    """Oriented unit normals (R, 3) of the representatives, and how they were oriented.

    Normals: principal axes of the ``k + 4`` nearest representatives. Signs: a representative whose points carry
    the cloud's own normals takes their sign (``normal_sums``); the others get theirs along a minimum spanning
    tree of the ``k``-nearest-neighbour graph weighted ``1 - |n_i · n_j|`` (Hoppe et al. 1992), from those, or, in a
    connected part of the cloud that has none, from one seed: its highest representative whose normal is within
    45° of the vertical, taken to face up (a roof or the ground), else its representative farthest from the part's
    centroid, taken to face away from it.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
    from scipy.spatial import cKDTree

    n_r = len(reps)
    info = {"representatives": int(n_r), "from_cloud_normals": 0, "seeded_parts": 0}
    if n_r == 0:
        return np.zeros((0, 3)), info
    tree = cKDTree(reps)
    kk = min(k + 4, n_r)
    nrm, _ = pca_normals(tree, reps, reps, kk, np.inf)
    if n_r == 1:
        return nrm, info
    kq = min(k + 1, n_r)
    d, idx = tree.query(reps, k=kq)
    rows = np.repeat(np.arange(n_r), kq - 1)
    cols = idx[:, 1:].ravel()
    w = 1.0 - np.abs(np.einsum("ij,ij->i", nrm[rows], nrm[cols])) + 1e-6
    ncomp, label = connected_components(coo_matrix((w, (rows, cols)), shape=(n_r, n_r)), directed=False)
    proj = np.einsum("ij,ij->i", nrm, normal_sums)
    seeded = np.abs(proj) > 1e-6 * np.maximum(np.linalg.norm(normal_sums, axis=1), 1e-30)
    seeded &= np.linalg.norm(normal_sums, axis=1) > 0
    sign0 = np.where(proj < 0, -1.0, 1.0)
    info["from_cloud_normals"] = int(seeded.sum())
    seeds = list(np.flatnonzero(seeded))
    for c in range(ncomp):
        members = np.flatnonzero(label == c)
        if seeded[members].any():
            continue
        vert = members[np.abs(nrm[members, 2]) > np.cos(np.radians(45))]
        if len(vert):
            s = int(vert[np.argmax(reps[vert, 2])])
            sign0[s] = 1.0 if nrm[s, 2] > 0 else -1.0
        else:
            cen = reps[members].mean(axis=0)
            s = int(members[np.argmax(np.linalg.norm(reps[members] - cen, axis=1))])
            sign0[s] = 1.0 if nrm[s] @ (reps[s] - cen) > 0 else -1.0
        seeds.append(s)
        info["seeded_parts"] += 1
    # a virtual root joined to every seed with a negligible weight: one spanning tree, searched from the root
    root = n_r
    seeds = np.asarray(seeds, np.int64)
    rows2 = np.r_[rows, np.full(len(seeds), root)]
    cols2 = np.r_[cols, seeds]
    w2 = np.r_[w, np.full(len(seeds), 1e-9)]
    g = coo_matrix((w2, (rows2, cols2)), shape=(n_r + 1, n_r + 1)).tocsr()
    g = g.maximum(g.T)
    mst = minimum_spanning_tree(g)
    order, pred = breadth_first_order(mst, root, directed=False, return_predecessors=True)
    sign = np.ones(n_r)
    for v in order[1:]:
        p = pred[v]
        if p == root or seeded[v]:
            sign[v] = sign0[v]
        else:
            sign[v] = sign[p] * (1.0 if nrm[v] @ nrm[p] >= 0 else -1.0)
    return nrm * sign[:, None], info


def _edge_vertices(Vv, vol) -> np.ndarray:
    """The marching-cubes vertices (lattice units) again in float64: scikit-image returns float32 positions (1e-5
    cells at a block's far side, enough to keep two blocks' copies of a shared vertex apart); each vertex lies on a
    lattice edge, whose crossing ``t = f0 / (f0 - f1)`` is computed again from the node values."""
    v = np.asarray(Vv, np.float64)
    r = np.rint(v)
    frac = np.abs(v - r)
    ax = np.argmax(frac, axis=1)
    on_edge = frac[np.arange(len(v)), ax] > 1e-4
    out = r.copy()
    e = np.flatnonzero(on_edge)
    i0 = r[e].astype(np.int64)
    a = ax[e]
    i0[np.arange(len(e)), a] = np.floor(v[e, a]).astype(np.int64)
    i1 = i0.copy()
    i1[np.arange(len(e)), a] += 1
    f0 = vol[i0[:, 0], i0[:, 1], i0[:, 2]]
    f1 = vol[i1[:, 0], i1[:, 1], i1[:, 2]]
    t = f0 / (f0 - f1)
    out[e] = i0
    out[e, a] += t
    return out


def mesh_block(pts, file_normals, rep_pts, rep_normals, lattice: Lattice, b, cfg: SurfaceConfig,
               outlier_thr: float, outlier_bound_m: float) -> BlockMesh:
    """The surface of block ``b`` from the points of its core and margin (see the module docstring).

    Parameters
    ----------
    pts : (N, 3) float64
        Local coordinates (m) of the points within :func:`block_margin` of the block.
    file_normals : (N, 3) float32 or None
        The cloud's own normals (zeros where a point has none).
    rep_pts, rep_normals : (R, 3)
        Oriented coarse representatives near the block (:func:`orient_representatives`).
    outlier_thr, outlier_bound_m : float
        The global outlier threshold (m) and the bound of its neighbour search (m).
    """
    from scipy import ndimage
    from scipy.spatial import cKDTree

    h, C = lattice.h, lattice.block
    lo, hi = lattice.block_box(b)
    core = np.all((pts >= lo) & (pts < hi), axis=1)
    out = BlockMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), points_core=int(core.sum()))
    if len(pts) < cfg.k_normal:
        out.outliers_core = int(core.sum())
        return out
    tree = cKDTree(pts)
    stat = outlier_statistic(tree, pts, cfg.k_outlier, outlier_bound_m)
    keep = stat <= outlier_thr
    out.outliers_core = int((core & ~keep).sum())
    pts = pts[keep]
    fn = None if file_normals is None else file_normals[keep]
    if len(pts) < cfg.k_normal:
        return out
    tree = cKDTree(pts)
    # nodes within the band of a point, inside this block's node box
    nb = C + 1
    rel = (pts - lo) / h
    near = np.all((rel > -cfg.band - 1) & (rel < C + cfg.band + 1), axis=1)
    if not near.any():
        return out
    occ = np.zeros((nb, nb, nb), bool)
    ijk = np.clip(np.rint(rel[near]).astype(np.int64), 0, C)
    occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    cand = occ.view(np.uint8)
    r = int(np.ceil(cfg.band)) + 1
    for ax in range(3):  # a cube of 2r + 1 nodes about every occupied node (separable)
        cand = ndimage.maximum_filter1d(cand, 2 * r + 1, axis=ax)
    ci = np.argwhere(cand)
    X = lo + h * ci
    d1, _ = tree.query(X, k=1, distance_upper_bound=cfg.band * h)
    act = np.isfinite(d1)
    ci, X = ci[act], X[act]
    if len(ci) == 0:
        return out
    d, idx = tree.query(X, k=cfg.k_sdf, distance_upper_bound=(cfg.band + 2.0) * h)
    # oriented normals of the points the nodes use
    used = np.unique(idx[np.isfinite(d)])
    n_used, valid = pca_normals(tree, pts, pts[used], cfg.k_normal, 4.0 * h + (cfg.band + 2.0) * h)
    ref = None
    if fn is not None:
        ref = fn[used].astype(float)
    # the sign from the most parallel of the 4 nearest representatives (at an edge the nearest one may be the other
    # face's, at right angles: no sign at all)
    rtree = cKDTree(rep_pts)
    kr = min(4, len(rep_pts))
    _, ri = rtree.query(pts[used], k=kr)
    ri = np.asarray(ri).reshape(len(used), kr)
    dots = np.einsum("mkj,mj->mk", rep_normals[ri], n_used)
    best = np.argmax(np.abs(dots), axis=1)
    rep_ref = rep_normals[ri[np.arange(len(used)), best]]
    if ref is not None:
        has = np.linalg.norm(ref, axis=1) > 0
        rep_ref = np.where(has[:, None], ref, rep_ref)
    n_used = n_used * np.where(np.einsum("ij,ij->i", n_used, rep_ref) < 0, -1.0, 1.0)[:, None]
    normals = np.zeros((len(pts), 3))
    ok_n = np.zeros(len(pts), bool)
    normals[used] = n_used
    ok_n[used] = valid
    fin = np.isfinite(d)
    idx0 = np.where(fin, idx, 0)
    fin &= ok_n[idx0]
    # only neighbours whose normal agrees with the nearest one's: two faces of an edge are not averaged into a chamfer
    agree = np.einsum("mkj,mj->mk", normals[idx0], normals[idx0[:, 0]]) > np.cos(np.radians(35.0))
    fin &= agree
    w = np.where(fin, np.exp(-(np.where(fin, d, 0.0) / h) ** 2), 0.0)
    sd = np.einsum("mkj,mkj->mk", normals[idx0], X[:, None, :] - pts[idx0])
    wsum = w.sum(axis=1)
    good = wsum > 0
    vol = np.full((nb, nb, nb), np.nan)  # float64: marching cubes returns vertices of the volume's precision
    vol[ci[good, 0], ci[good, 1], ci[good, 2]] = np.einsum("mk,mk->m", w, sd)[good] / wsum[good]
    have = np.isfinite(vol)
    cube = (have[:-1, :-1, :-1] & have[1:, :-1, :-1] & have[:-1, 1:, :-1] & have[:-1, :-1, 1:]
            & have[1:, 1:, :-1] & have[1:, :-1, 1:] & have[:-1, 1:, 1:] & have[1:, 1:, 1:])
    if not cube.any():
        return out
    mask = np.zeros((nb, nb, nb), bool)
    mask[1:, 1:, 1:] = cube  # scikit-image processes cube (x, y, z) when mask[x + 1, y + 1, z + 1]
    from skimage.measure import marching_cubes

    try:
        Vv, F, _, _ = marching_cubes(np.nan_to_num(vol, nan=1.0), 0.0, mask=mask, allow_degenerate=False)
    except (ValueError, RuntimeError):  # no zero crossing in this block
        return out
    V = lo + h * _edge_vertices(Vv, vol)
    F = F.astype(np.int64)
    if len(F) == 0:
        return out
    cen = V[F].mean(axis=1)
    dc, _ = tree.query(cen, k=1, distance_upper_bound=cfg.trim * h)
    sup = np.isfinite(dc)
    out.trimmed_area_m2 = float(triangle_areas(V, F[~sup]).sum())
    F = F[sup]
    usedv = np.unique(F)
    remap = np.full(len(V), -1, np.int64)
    remap[usedv] = np.arange(len(usedv))
    out.vertices, out.faces = V[usedv], remap[F]
    return out
