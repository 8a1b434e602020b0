"""Partial circle grids: part of the grid outside the frame, cut by its border or hidden.

The ellipse candidates of a consistent size are put on an integer lattice by growing it from neighbour
to neighbour (:func:`_grow_lattice`; the basis that maps the seed's ellipse back to the roundest shape,
:func:`_anisotropy`), the patch is placed on the target by a rotation of the lattice and an integer
translation (:func:`_place_on_target`) and checked with a second-order map and the polarity test
(:func:`partial_grid`).

References
----------
Vidas, S., Lakemond, R., Denman, S., Fookes, C., Sridharan, S., Wark, T. (2012). A mask-based
approach for the geometric calibration of thermal-infrared cameras. IEEE TIM 61(6), 1625-1635.
"""

from __future__ import annotations

import numpy as np

from .circle_candidates import one_per_disc, size_group
from .circle_order import polarity_ok, quad_fit_rms
from .detect_common import CircleGridSpec

__all__ = ["partial_grid"]


def _ellipse_cov(c: np.ndarray) -> np.ndarray:
    """(2, 2) shape matrix ``R diag(major², minor²) Rᵀ`` of an :func:`ellipse_candidates` row."""
    ca, sa = np.cos(c[6]), np.sin(c[6])
    R = np.array([[ca, -sa], [sa, ca]])
    return R @ np.diag([c[2] ** 2, c[3] ** 2]) @ R.T


def _anisotropy(cov: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> float:
    """Axis ratio (>= 1) of an image ellipse mapped back through the local lattice basis ``[e1 e2]``:
    1 for the image of a circle when ``e1, e2`` are the images of two orthogonal, equally long
    target steps (grid axes of a symmetric grid, the diagonals of an asymmetric one)."""
    J = np.column_stack([e1, e2])
    if abs(np.linalg.det(J)) < 1e-9:
        return np.inf
    Ji = np.linalg.inv(J)
    w = np.linalg.eigvalsh(Ji @ cov @ Ji.T)
    return float(np.sqrt(max(w[1], 1e-300) / max(w[0], 1e-300)))


def _grow_lattice(p: np.ndarray, cand: np.ndarray | None = None):
    """Integer lattice coordinates of points that form (part of) a distorted 2-D grid.

    A seed (the candidate with the most neighbours within 1.5 x the typical nearest-neighbour
    distance, nearest the middle) and two basis steps to its neighbours start a breadth-first growth:
    the position of a neighbour is predicted by extrapolating along the row or column (``p[k] +
    (p[k] - p[back])``, exact to first order under smooth distortion) or, without a point behind, by
    the local step carried along; the nearest candidate within 30 % of the step is taken, else one
    two steps on (a hidden circle between). A candidate claimed by two lattice positions makes the
    structure ambiguous (returns None).

    The basis: any two independent lattice vectors generate the same point lattice (a diagonal is
    as good as an axis to the points alone, and under strong perspective a diagonal can be the
    shorter step), so the points cannot tell the grid's axes. The circles can: with ``cand`` (the
    :func:`ellipse_candidates` rows of ``p``) the pair of steps that maps the seed's ellipse back to
    the roundest shape (:func:`_anisotropy`) is taken; without it, the nearest neighbour and the
    shortest step at more than 60 degrees to it.

    Returns
    -------
    (idx (K,), ab (K, 2) int) or None -- indices into ``p`` and their lattice coordinates (basis
    right-handed in the image).
    """
    m = len(p)
    if m < 3:
        return None
    d = np.linalg.norm(p[:, None] - p[None], axis=2)
    np.fill_diagonal(d, np.inf)
    nn = float(np.median(d.min(axis=1)))
    cnt = (d < 1.5 * nn).sum(axis=1)
    mid = np.median(p, axis=0)
    seed = int(np.lexsort((np.linalg.norm(p - mid, axis=1), -cnt))[0])
    nb = np.flatnonzero(d[seed] < 1.5 * nn)
    if len(nb) < 2:
        return None
    v = p[nb] - p[seed]
    ln = np.linalg.norm(v, axis=1)
    if cand is not None and cand.shape[1] >= 8:
        cov = _ellipse_cov(cand[seed])
        pairs = []
        for i in range(len(v)):
            for j in range(len(v)):
                cr = v[i, 0] * v[j, 1] - v[i, 1] * v[j, 0]
                if cr <= 0.2 * ln[i] * ln[j]:  # independent (> ~12 degrees apart), right-handed
                    continue
                pairs.append((_anisotropy(cov, v[i], v[j]), cr, i, j))
        if not pairs:
            return None
        # the roundest pairs; among them the smallest cell: the diagonals of a square cell are
        # orthogonal and equally long too, but span a cell twice as large (they skip every other disc)
        lo = min(q[0] for q in pairs)
        _, _, i, j = min((q for q in pairs if q[0] <= lo + 0.15 * lo), key=lambda q: q[1])
        e1, e2 = v[i], v[j]
    else:
        e1 = v[np.argmin(ln)]
        cosang = np.abs(v @ e1) / (ln * np.linalg.norm(e1))
        perp = np.flatnonzero(cosang < 0.5)
        if not len(perp):
            return None
        e2 = v[perp[np.argmin(ln[perp])]]
        if e1[0] * e2[1] - e1[1] * e2[0] < 0:
            e2 = -e2
    coords = {seed: (0, 0)}
    pos = {(0, 0): seed}
    basis = {seed: (e1, e2)}
    queue = [seed]
    while queue:
        k = queue.pop(0)
        a, b = coords[k]
        for axis, sgn in ((0, 1), (0, -1), (1, 1), (1, -1)):
            e = np.array([sgn, 0]) if axis == 0 else np.array([0, sgn])
            backkey = (a - e[0], b - e[1])
            step = p[k] - p[pos[backkey]] if backkey in pos else sgn * basis[k][axis]
            for mult in (1, 2):
                key = (a + mult * e[0], b + mult * e[1])
                if key in pos:
                    break
                pred = p[k] + mult * step
                dist = np.linalg.norm(p - pred, axis=1)
                j = int(np.argmin(dist))
                if dist[j] > 0.3 * np.linalg.norm(step):
                    continue
                if j in coords:
                    if coords[j] != key:
                        return None  # one disc at two lattice positions: not a grid
                    break
                coords[j] = key
                pos[key] = j
                b_new = list(basis[k])
                b_new[axis] = sgn * (p[j] - p[k]) / mult
                basis[j] = tuple(b_new)
                queue.append(j)
                break
    idx = np.array(sorted(coords), dtype=int)
    ab = np.array([coords[i] for i in idx], dtype=int)
    return idx, ab


def _place_on_target(ab: np.ndarray, spec: CircleGridSpec):
    """Object ids for lattice coordinates ``ab`` (right-handed in the image): every placement of the
    observed lattice patch on the target by a rotation of the lattice (multiples of 90 degrees) and an
    integer translation that puts every point on a circle of the target.

    Symmetric grid: lattice steps are the spacing s along x and y. Asymmetric grid: the nearest
    neighbours are the diagonals ``(±s, ±s)``, so lattice ``(a, b)`` is at ``(a - b, a + b) s``.
    A rotation or translation of the whole patch is a rigid motion of the target plane, which the
    view's own pose absorbs: any valid placement gives the same calibration.

    Returns
    -------
    list of ndarray (K,) int -- object ids of each valid placement (empty: the patch fits nowhere).
    """
    obj = spec.object_points()[:, :2] / spec.spacing_mm
    lut = {(int(round(x)), int(round(y))): i for i, (x, y) in enumerate(obj)}
    if spec.asymmetric:
        uv = np.column_stack([ab[:, 0] - ab[:, 1], ab[:, 0] + ab[:, 1]])
    else:
        uv = ab.copy()
    tx = np.array([k[0] for k in lut])
    ty = np.array([k[1] for k in lut])
    out = []
    for rot in range(4):
        r = uv.copy()
        for _ in range(rot):
            r = np.column_stack([-r[:, 1], r[:, 0]])
        for du in range(tx.min() - r[:, 0].min(), tx.max() - r[:, 0].max() + 1):
            for dv in range(ty.min() - r[:, 1].min(), ty.max() - r[:, 1].max() + 1):
                ids = [lut.get((int(x + du), int(y + dv))) for x, y in r]
                if all(i is not None for i in ids):
                    out.append(np.array(ids, dtype=np.int64))
    return out


def partial_grid(gray, spec, bright, cand, min_points: int):
    """A partial grid from ellipse candidates (:func:`_grow_lattice`, :func:`_place_on_target`),
    checked with a second-order map and the polarity test. Returns (points (K, 2), ids (K,),
    n_placements, why)."""
    n = spec.n_points
    if len(cand) < min_points:
        return None, None, 0, f"{len(cand)} ellipse candidates < {min_points}"
    # whole discs only: a disc cut by an occluder's edge or the frame border has a straight piece of
    # outline (relative departure from its fitted ellipse 0.15-0.3, against 0.02-0.05 for whole
    # blurred discs); its centroid would be off by pixels
    cand = cand[cand[:, 7] <= 0.1]
    cand = one_per_disc(cand)
    if len(cand) < min_points:
        return None, None, 0, f"{len(cand)} whole-disc ellipse candidates < {min_points}"
    grp = size_group(cand, n)
    c = cand[grp]
    if len(c) < min_points:
        return None, None, 0, f"only {len(c)} ellipses of a consistent size"
    grown = _grow_lattice(c[:, :2], c)
    if grown is None:
        return None, None, 0, "ellipses do not form a lattice"
    idx, ab = grown
    if len(idx) < min_points or len(np.unique(ab[:, 0])) < 2 or len(np.unique(ab[:, 1])) < 2:
        return None, None, 0, f"{len(idx)} ellipses on a lattice (< {min_points}, or on one line)"
    if len(idx) > n:
        return None, None, 0, f"{len(idx)} ellipses on a lattice: more than the {n} circles of the grid"
    pts = c[idx, :2]
    placements = _place_on_target(ab, spec)
    if not placements:
        span = ab.max(axis=0) - ab.min(axis=0) + 1
        return None, None, 0, (f"{len(idx)} ellipses on a {span[0]}x{span[1]} lattice that does not fit the "
                               f"{spec.columns}x{spec.rows} grid")
    ids = placements[0]
    obj = spec.object_points()[ids, :2]
    rms, mx = quad_fit_rms(obj, pts)
    nn_px = float(np.median(np.sort(np.linalg.norm(pts[:, None] - pts[None], axis=2), axis=1)[:, 1]))
    if mx > 0.15 * nn_px + 0.5:
        return None, None, 0, f"partial lattice of {len(idx)} ellipses does not fit a smooth map ({mx:.1f} px)"
    if not polarity_ok(gray, pts, c, bright):
        return None, None, 0, "partial lattice fails the polarity check"
    return pts, ids, len(placements), ""
