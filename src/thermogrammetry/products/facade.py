"""Facade mosaics without a mesh: thermal orthoimages of a flat facade, temperatures kept, source map.

Two ways to put images on a facade plane (plane coordinates ``(a, b)`` in metres: ``a`` along the facade,
``b`` up; the output raster's row 0 is the TOP, cell ``(row, col)`` centred at
``a = a0 + (col + 0.5)·cell_m``, ``b = b1 − (row + 0.5)·cell_m``):

1. **Homography** (:func:`fit_facade_homography`, :func:`homography_mosaic`): from ≥ 4 points with known
   plane coordinates measured in an image (no orientation needed). With a camera model the measured
   points are undistorted first and the lens distortion is re-applied when sampling, so the plane
   maps exactly through a 3×3 homography ``x_ideal ~ H (a, b, 1)``; the fit is the normalised DLT
   (Hartley & Zisserman 2003, alg. 4.2) refined by Gauss–Newton on the image residuals, reported in px.
2. **Ortho on a plane** (:func:`plane_mosaic`): from oriented images (``cameras.json``) and a plane;
   every cell is projected into every image.

Both choose the image of every cell with the rule of :mod:`thermogrammetry.products.texture`: the
resolution on the surface (pixels per metre along the steepest direction) times a border weight
``min(1, b/b0)``, evaluated per **tile** (``tile_m``, the analogue of a mesh face, so that an image
covers whole tiles and seams follow tile edges unless an image cannot serve a cell). For a homography the
resolution is the smallest singular value of the Jacobian of ``(a, b) -> x`` (equal to ``f cos θ / d`` of
a pinhole camera); with poses it is ``f cos θ / d`` directly. Ortho on a plane can take occluding
geometry (a mesh of what stands in front: the per-cell ray test and the mixed-pixel test of the texture
module then apply); without it nothing in front of the plane is known and the homography/ortho mosaic
cannot exclude occluders (stated in the result's ``notes``).

Values are sampled bilinearly from one image per cell; nothing is blended or filled (NaN, source −1).

Optional levelling (``levelling="offsets"``, both mosaics; it ALTERS the values): per-image additive offsets
``o_k`` with ``T_a(x) + o_a = T_b(x) + o_b`` over pairs of images that can both serve a cell ``x``, least squares
by :func:`thermogrammetry.products.texture.estimate_offsets`, the image supplying most cells held at 0
(:func:`level_offsets`). Memory stays bounded: the mosaics select cells in chunks/bands and keep every image's
value only at a deterministic sample of at most ``LEVELLING_SAMPLE_CELLS`` cells (and at most
``LEVELLING_MAX_PAIRS`` pairs), never an images × cells stack.

References
----------
.. [1] Barazzetti, Erba, Previtali, Rosina, Scaioni (2013), seed 002: thermal orthophotos of facades,
   rectification of planar facades and mosaics keeping the temperatures.
.. [2] Hartley R., Zisserman A. (2003), *Multiple View Geometry*, 2nd ed., §4.1–4.2 (normalised DLT).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .._sampling import bilinear
from ..errors import ConfigError, InvalidInputError, ShapeError, TooFewPointsError

__all__ = ["FacadeGrid", "FacadePlane", "FacadeMosaic", "FacadeLevelling", "HomographyFit", "fit_facade_homography",
           "homography_mosaic", "level_offsets", "plane_mosaic"]


@dataclass(frozen=True)
class FacadeGrid:
    """Output raster on the plane: extent ``a0 <= a <= a1``, ``b0 <= b <= b1`` (m) and ``cell_m``."""

    a0: float
    a1: float
    b0: float
    b1: float
    cell_m: float

    def __post_init__(self):
        if not (self.a1 > self.a0 and self.b1 > self.b0 and self.cell_m > 0):
            raise ConfigError(f"FacadeGrid({self.a0}, {self.a1}, {self.b0}, {self.b1}, cell_m={self.cell_m}): "
                              "expected a1 > a0, b1 > b0 and a positive cell size")

    @property
    def shape(self) -> tuple[int, int]:
        return int(np.ceil((self.b1 - self.b0) / self.cell_m - 1e-9)), int(np.ceil((self.a1 - self.a0) / self.cell_m - 1e-9))

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) arrays of plane coordinates a, b of the cell centres (row 0 at the top)."""
        h, w = self.shape
        a = self.a0 + (np.arange(w) + 0.5) * self.cell_m
        b = self.b1 - (np.arange(h) + 0.5) * self.cell_m
        return np.meshgrid(a, b)


@dataclass(frozen=True)
class FacadePlane:
    """A plane in object space: ``X = origin + a·u + b·v`` with orthonormal ``u`` (along) and ``v`` (up);
    its normal ``u × v`` points towards the cameras."""

    origin: tuple
    u: tuple
    v: tuple

    def __post_init__(self):
        u, v = np.asarray(self.u, float), np.asarray(self.v, float)
        if u.shape != (3,) or v.shape != (3,) or np.asarray(self.origin, float).shape != (3,):
            raise ShapeError("FacadePlane: origin, u and v must be 3-vectors")
        if abs(np.linalg.norm(u) - 1) > 1e-6 or abs(np.linalg.norm(v) - 1) > 1e-6 or abs(u @ v) > 1e-6:
            raise ConfigError(f"FacadePlane: u={u.tolist()} and v={v.tolist()} must be orthonormal")

    def points(self, a, b) -> np.ndarray:
        return np.asarray(self.origin, float) + np.multiply.outer(a, self.u) + np.multiply.outer(b, self.v)

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.u, self.v)


@dataclass
class FacadeMosaic:
    """``temperature_k`` (H, W) float32, NaN = none; ``source`` (H, W) int32 image index, −1 = none;
    ``resolution_px_per_m`` (H, W) of the source image; ``names`` index -> image; ``grid``; ``notes``."""

    temperature_k: np.ndarray
    source: np.ndarray
    resolution_px_per_m: np.ndarray
    names: list
    grid: FacadeGrid
    notes: str = ""
    angle_deg: np.ndarray | None = None
    fits: list = field(default_factory=list)
    levelling: "FacadeLevelling | None" = None


# ------------------------------------------------------------------------------------------- levelling
#: cells sampled for the levelling (at most; a deterministic random subset of the grid)
LEVELLING_SAMPLE_CELLS = 200_000
#: image pairs (two images' values at one sampled cell) at most in the least squares
LEVELLING_MAX_PAIRS = 1_000_000


@dataclass
class FacadeLevelling:
    """Per-image additive offsets estimated from the overlaps (``levelling="offsets"``).

    ``offsets`` (K,) in the mosaic's value unit (kelvin, or counts for count frames), ADDED to every cell of
    their image; ``sigma`` (K,) their formal standard deviation (NaN: not estimated); ``fixed`` the image
    held at 0 (the one supplying most cells); ``pairs`` (K,) pair differences per image; ``connected`` (K,)
    bool: the image is tied to the held image through overlaps (the others are not levelled, offset 0);
    ``rms_before`` / ``rms_after`` RMS of the pair differences before and after; ``cells_sampled`` cells with
    >= 2 usable images that entered the estimate.
    """

    offsets: np.ndarray
    sigma: np.ndarray
    fixed: int
    pairs: np.ndarray
    connected: np.ndarray
    rms_before: float
    rms_after: float
    cells_sampled: int
    note: str = ""


def level_offsets(values, cells_per_image, *, max_pairs: int = LEVELLING_MAX_PAIRS, seed: int = 0) -> FacadeLevelling:
    """Per-image offsets from sampled overlap cells, by :func:`thermogrammetry.products.texture.estimate_offsets`.

    Parameters
    ----------
    values : (S, K) float, each image's value at S sampled cells (NaN where the image cannot serve the cell);
        rows with fewer than 2 values are ignored
    cells_per_image : (K,) int, cells each image supplies to the whole mosaic: the largest is held at 0
    max_pairs : int, rows are subsampled (deterministically) until their pairs fit; all pairs of the kept rows
        are used, so the formal σ below counts them exactly

    Returns
    -------
    :class:`FacadeLevelling`. σ is the least-squares formal one, ``s² (MᵀM)⁻¹`` over the pair differences with
    ``s`` from their residuals: it treats the pairs as independent, which they are not quite (a cell seen by
    3+ images gives dependent pairs; cells finer than a pixel share pixels), so it is a lower bound.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from .texture import Selection, estimate_offsets

    V = np.asarray(values, np.float32)
    cnt = np.asarray(cells_per_image, np.int64)
    K = V.shape[1]
    fixed = int(np.argmax(cnt))
    fin = np.isfinite(V)
    m = fin.sum(axis=1)
    keep = m >= 2
    V, fin, m = V[keep], fin[keep], m[keep]
    per_row = m * (m - 1) // 2
    if per_row.sum() > max_pairs:  # fewer rows, every pair of each kept row
        order = np.random.default_rng(seed).permutation(len(V))
        take = np.sort(order[: int(np.searchsorted(np.cumsum(per_row[order]), max_pairs, side="right"))])
        V, fin, m = V[take], fin[take], m[take]
    nan = np.full(K, np.nan)
    Fm = fin.astype(np.float64)
    Nkj = Fm.T @ Fm  # (K, K) cells shared by images k and j
    np.fill_diagonal(Nkj, 0.0)
    _, comp = connected_components(coo_matrix(Nkj > 0), directed=False)
    connected = comp == comp[fixed]
    connected &= (Nkj.sum(axis=1) > 0) | (np.arange(K) == fixed)
    if not np.any(connected & (np.arange(K) != fixed)):
        return FacadeLevelling(np.zeros(K), nan, fixed, np.zeros(K, np.int64), connected, float("nan"), float("nan"),
                               int(len(V)), "no overlap with the held image: nothing levelled")
    V = np.where(connected[None, :], V, np.nan).astype(np.float32)  # images not tied to the held one stay out
    fin = np.isfinite(V)
    m = fin.sum(axis=1)
    use = m >= 2
    V, fin, m = V[use], fin[use], m[use]
    total = int((m * (m - 1) // 2).sum())
    sel = Selection(np.zeros(len(V), np.int64), np.zeros(len(V)), np.zeros(len(V)), np.zeros(len(V)), m,
                    np.zeros((len(V), 0), bool), V)
    off, fixed_, pairs, rb, ra = estimate_offsets(sel, K, max_pairs=max(total, 1), seed=seed, fixed=fixed)
    off = np.where(connected, off, 0.0)
    # formal sigma: cov = s^2 (M^T M)^-1, M^T M = the pair graph's Laplacian without the held image
    Fm = fin.astype(np.float64)
    Nkj = Fm.T @ Fm
    np.fill_diagonal(Nkj, 0.0)
    L = np.diag(Nkj.sum(axis=1)) - Nkj
    free = np.flatnonzero(connected & (np.arange(K) != fixed))
    sig = nan.copy()
    sig[fixed] = 0.0
    dof = total - len(free)
    if dof > 0:
        s2 = ra**2 * total / dof
        try:
            cov = s2 * np.linalg.inv(L[np.ix_(free, free)])
            sig[free] = np.sqrt(np.maximum(np.diag(cov), 0.0))
        except np.linalg.LinAlgError:
            pass
    note = "" if np.all(connected) else (f"{int((~connected).sum())} image(s) share no overlap chain with the held image: "
                                         "not levelled (offset 0, sigma null)")
    return FacadeLevelling(off, sig, fixed_, np.asarray(pairs, np.int64), connected, float(rb), float(ra), int(len(V)), note)


# ------------------------------------------------------------------------------------------- homography
@dataclass
class HomographyFit:
    """``H`` (3×3) maps plane (a, b, 1) to ideal (undistorted) pixels; ``residuals_px`` (N, 2); ``rms_px``."""

    H: np.ndarray
    residuals_px: np.ndarray
    rms_px: float
    camera: object = None

    def to_pixels(self, a, b) -> np.ndarray:
        """Pixel coordinates (..., 2) of plane points, lens distortion re-applied when a camera is known."""
        a = np.asarray(a, float)
        p = np.stack([a, np.asarray(b, float), np.ones_like(a)], -1) @ self.H.T
        xy = p[..., :2] / p[..., 2:3]
        if self.camera is not None:
            flat = xy.reshape(-1, 2)
            xy = self.camera.distort(flat).reshape(xy.shape)
        return xy

    def jacobian_min_sv(self, a, b) -> np.ndarray:
        """Smallest singular value of d(x)/d(a, b) (ideal pixels per metre, worst direction)."""
        H = self.H
        a = np.asarray(a, float)
        b = np.asarray(b, float)
        w = H[2, 0] * a + H[2, 1] * b + H[2, 2]
        x = (H[0, 0] * a + H[0, 1] * b + H[0, 2]) / w
        y = (H[1, 0] * a + H[1, 1] * b + H[1, 2]) / w
        J = np.stack([np.stack([(H[0, 0] - x * H[2, 0]) / w, (H[0, 1] - x * H[2, 1]) / w], -1),
                      np.stack([(H[1, 0] - y * H[2, 0]) / w, (H[1, 1] - y * H[2, 1]) / w], -1)], -2)
        return np.linalg.svd(J, compute_uv=False)[..., -1]


def _normalise(p):
    c = p.mean(axis=0)
    s = np.sqrt(2) / max(np.mean(np.linalg.norm(p - c, axis=1)), 1e-12)
    T = np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1]])
    return T, (p - c) * s


#: a homography needs 4 points with no 3 on a line: each of them at least this share of the points' span
#: away from the line through two others
GENERAL_POSITION_FRACTION = 0.05


def _general_position(P, frac: float = GENERAL_POSITION_FRACTION) -> bool:
    """Whether the plane points (N, 2) hold 4 points with no 3 nearly collinear (greedy: the farthest pair,
    the point farthest from their line, then the point farthest from all three lines)."""

    def dist_line(p, q, X):
        d = q - p
        return np.abs(d[0] * (X[:, 1] - p[1]) - d[1] * (X[:, 0] - p[0])) / max(np.hypot(*d), 1e-300)

    D = np.linalg.norm(P[:, None] - P[None], axis=2)
    i, j = np.unravel_index(np.argmax(D), D.shape)
    span = D[i, j]
    if not span > 0:
        return False
    d3 = dist_line(P[i], P[j], P)
    k = int(np.argmax(d3))
    if d3[k] < frac * span:
        return False
    d4 = np.minimum(np.minimum(d3, dist_line(P[i], P[k], P)), dist_line(P[j], P[k], P))
    return bool(np.max(d4) >= frac * span)


def fit_facade_homography(plane_ab, image_xy_px, *, camera=None, iterations: int = 10) -> HomographyFit:
    """Homography from ≥ 4 plane points (N, 2) m to their measured pixels (N, 2) (module docstring).

    Raises :class:`~thermogrammetry.errors.TooFewPointsError` below 4 points and
    :class:`~thermogrammetry.errors.DegenerateInputError` when no 4 points are in general position (3 of 4
    collinear, within ``GENERAL_POSITION_FRACTION`` of the points' span, or a rank-deficient DLT) or when the
    fitted plane's horizon line passes between the points (some would be behind the camera).
    The returned ``H`` is scaled so that ``w = H[2]·(a, b, 1) > 0`` at the points (in front of the camera).
    """
    from ..errors import DegenerateInputError

    P = np.asarray(plane_ab, float)
    X = np.asarray(image_xy_px, float)
    if P.ndim != 2 or P.shape[1] != 2 or X.shape != P.shape:
        raise ShapeError(f"plane points {P.shape} and image points {X.shape}: expected two (N, 2) arrays")
    if len(P) < 4:
        raise TooFewPointsError(f"facade homography: {len(P)} points given; expected at least 4 with known plane coordinates")
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(X))):
        raise InvalidInputError("facade homography: non-finite coordinates")
    if not _general_position(P):
        raise DegenerateInputError(f"facade homography: the {len(P)} plane points hold no 4 points with no 3 collinear "
                                   f"(within {GENERAL_POSITION_FRACTION:.0%} of their span); expected 4+ points spread "
                                   "over the facade")
    Xi = camera.undistort(X) if camera is not None else X
    Tp, p = _normalise(P)
    Tx, x = _normalise(Xi)
    A = []
    for (a, b), (u, v) in zip(p, x):
        A.append([a, b, 1, 0, 0, 0, -u * a, -u * b, -u])
        A.append([0, 0, 0, a, b, 1, -v * a, -v * b, -v])
    _, s, Vt = np.linalg.svd(np.asarray(A))
    if s[-2] < 1e-9 * s[0]:
        raise DegenerateInputError("facade homography: the points are degenerate (three or more collinear); "
                                   "expected 4+ points spread over the facade")
    Hn = Vt[-1].reshape(3, 3)
    H = np.linalg.inv(Tx) @ Hn @ Tp
    H /= H[2, 2]
    h = H.ravel()[:8].copy()
    for _ in range(iterations):  # Gauss-Newton on image residuals
        Hm = np.append(h, 1.0).reshape(3, 3)
        q = np.c_[P, np.ones(len(P))] @ Hm.T
        w = q[:, 2]
        pred = q[:, :2] / w[:, None]
        r = (Xi - pred).ravel()
        J = np.zeros((2 * len(P), 8))
        a, b = P[:, 0], P[:, 1]
        J[0::2, 0:3] = np.c_[a, b, np.ones_like(a)] / w[:, None]
        J[1::2, 3:6] = np.c_[a, b, np.ones_like(a)] / w[:, None]
        J[0::2, 6:8] = -pred[:, :1] * np.c_[a, b] / w[:, None]
        J[1::2, 6:8] = -pred[:, 1:2] * np.c_[a, b] / w[:, None]
        dh, *_ = np.linalg.lstsq(J, r, rcond=None)
        h += dh
        if np.linalg.norm(dh) < 1e-12 * max(1.0, np.linalg.norm(h)):
            break
    H = np.append(h, 1.0).reshape(3, 3)
    q = np.c_[P, np.ones(len(P))] @ H.T
    if not (np.all(q[:, 2] > 0) or np.all(q[:, 2] < 0)) or not np.all(np.isfinite(H)):
        raise DegenerateInputError("facade homography: the fit puts some points behind the camera (the horizon line "
                                   "passes between them); check the measurements and the point ids")
    if q[0, 2] < 0:
        H, q = -H, -q
    res = Xi - q[:, :2] / q[:, 2:3]
    return HomographyFit(H, res, float(np.sqrt(np.mean(np.sum(res**2, axis=1)))), camera)


def _choose(scores_cells, usable, tiles):
    """Per-tile score (mean over the tile's usable cells) then per cell the best usable image."""
    K = scores_cells.shape[0]
    tid = tiles.ravel()
    nt = tid.max() + 1
    tile_score = np.zeros((K, nt))
    for k in range(K):
        s = np.where(usable[k].ravel(), scores_cells[k].ravel(), 0.0)
        n = np.bincount(tid, weights=usable[k].ravel().astype(float), minlength=nt)
        with np.errstate(invalid="ignore", divide="ignore"):
            tile_score[k] = np.where(n > 0, np.bincount(tid, weights=s, minlength=nt) / n, 0.0)
    cell_score = np.where(usable.reshape(K, -1), tile_score[:, tid], -1.0)
    best = np.argmax(cell_score, axis=0)
    best = np.where(cell_score[best, np.arange(cell_score.shape[1])] > 0, best, -1)
    return best.reshape(tiles.shape)


def _apply_levelling(T, src, values_sample, cells_per_image):
    lev = level_offsets(values_sample, cells_per_image)
    ok = src >= 0
    T[ok] = (T[ok] + lev.offsets[src[ok]]).astype(T.dtype)
    return lev


def homography_mosaic(images: Sequence[np.ndarray], fits: Sequence[HomographyFit], grid: FacadeGrid, *, names=None,
                      tile_m: float = 1.0, border_px: float = 2.0, border_fraction: float = 0.1,
                      levelling: str = "none", band_values: int = 4_000_000) -> FacadeMosaic:
    """Mosaic of rectified images on the facade grid; image choice by the module's rule.

    Parameters
    ----------
    images : K (H_k, W_k) arrays, kelvin (or all raw counts: the mosaic then holds counts)
    fits : K :class:`HomographyFit`, plane (a, b) m -> pixels of each image
    grid : :class:`FacadeGrid`
    levelling : ``"none"`` or ``"offsets"`` (per-image offsets from the overlaps, :func:`level_offsets`; they
        alter the values and are returned in ``levelling``)
    band_values : the grid is processed in bands of whole tile rows holding about this many (cell, image)
        values, so memory does not grow with K x cells

    Returns
    -------
    :class:`FacadeMosaic` (``angle_deg`` None: no orientation, no viewing angle)
    """
    from .texture import Levelling, _levelling_sample

    lev_mode = Levelling(levelling)
    if len(images) != len(fits) or not len(images):
        raise InvalidInputError(f"homography_mosaic: {len(images)} images and {len(fits)} homographies; expected the same number >= 1")
    images = [np.asarray(im, np.float32) for im in images]
    h, w = grid.shape
    K = len(images)
    per = max(1, int(round(tile_m / grid.cell_m)))
    band = per * max(1, int(band_values // max(1, K * w * per)))
    T = np.full((h, w), np.nan, np.float32)
    res = np.full((h, w), np.nan, np.float32)
    src = np.full((h, w), -1, np.int32)
    sample = _levelling_sample(h * w, LEVELLING_SAMPLE_CELLS).reshape(h, w) if lev_mode is Levelling.OFFSETS else None
    samples = []
    A_all, B_all = grid.centres()
    for r0 in range(0, h, band):
        A, B = A_all[r0:r0 + band], B_all[r0:r0 + band]
        bh = A.shape[0]
        scores = np.zeros((K, bh, w))
        usable = np.zeros((K, bh, w), bool)
        xys = []
        for k, (img, fit) in enumerate(zip(images, fits)):
            H_, W_ = img.shape
            xy = fit.to_pixels(A, B)
            xys.append(xy)
            bd = np.minimum(np.minimum(xy[..., 0] + 0.5, W_ - 0.5 - xy[..., 0]), np.minimum(xy[..., 1] + 0.5, H_ - 0.5 - xy[..., 1]))
            q = np.stack([A, B, np.ones_like(A)], -1) @ fit.H.T
            front = q[..., 2] > 0
            ok = front & np.isfinite(bd) & (bd >= border_px + 0.5)
            usable[k] = ok
            b0 = border_fraction * min(W_, H_)
            scores[k] = np.where(ok, fit.jacobian_min_sv(A, B) * np.minimum(1.0, np.maximum(bd, 0) / b0), 0.0)
        r, c = np.mgrid[0:bh, 0:w]
        tiles = (r // per) * ((w + per - 1) // per) + (c // per)
        best = _choose(scores, usable, tiles)
        for k in range(K):
            m = best == k
            if np.any(m):
                T[r0:r0 + bh][m] = bilinear(images[k], xys[k][m])
                res[r0:r0 + bh][m] = fits[k].jacobian_min_sv(A[m], B[m])
        src[r0:r0 + bh] = best
        if sample is not None:
            sm = sample[r0:r0 + bh] & (usable.sum(axis=0) >= 2)
            vals = np.full((int(sm.sum()), K), np.nan, np.float32)
            for k in range(K):
                u = usable[k][sm]
                vals[u, k] = bilinear(images[k], xys[k][sm][u])
            samples.append(vals)
    lev = None
    if sample is not None:
        lev = _apply_levelling(T, src, np.concatenate(samples) if samples else np.zeros((0, K), np.float32),
                               np.bincount(src[src >= 0], minlength=K))
    return FacadeMosaic(T, src, res, list(names) if names is not None else [str(i) for i in range(K)], grid,
                        notes="homography rectification: nothing in front of the plane is known; occluders are not excluded",
                        fits=list(fits), levelling=lev)


def plane_mosaic(views, plane: FacadePlane, grid: FacadeGrid, *, occluders=None, tile_m: float = 1.0, config=None,
                 levelling: str = "none", chunk_cells: int = 250_000) -> FacadeMosaic:
    """Ortho on a plane from oriented images (``views``: :class:`~thermogrammetry.products.texture.TextureView`).

    ``occluders``: optional ``(vertices, faces)`` of geometry in front of the plane (e.g. a mesh of a
    balcony or a tree); with it every cell gets the texture module's occlusion and mixed-pixel tests.
    ``levelling``: ``"none"`` or ``"offsets"`` (per-image offsets from the overlaps, :func:`level_offsets`,
    estimated from a sample of at most ``LEVELLING_SAMPLE_CELLS`` cells; they alter the values).
    The cells are selected and sampled ``chunk_cells`` at a time (each image's value is held for one chunk only).
    """
    from .texture import (Levelling, TextureConfig, _intersector, _levelling_sample, local_origin, pixel_surfaces, plane_ids,
                          select_in_chunks, view_in_frame)

    lev_mode = Levelling(levelling)

    cfg = config or TextureConfig()
    A, B = grid.centres()
    h, w = A.shape
    # the plane as a tile mesh: two triangles per tile (the "faces" of the image-choice rule)
    per = max(1, int(round(tile_m / grid.cell_m)))
    nta, ntb = (w + per - 1) // per, (h + per - 1) // per
    ea = grid.a0 + np.arange(nta + 1) * per * grid.cell_m
    eb = grid.b1 - np.arange(ntb + 1) * per * grid.cell_m
    EA, EB = np.meshgrid(ea, eb)
    PV = plane.points(EA.ravel(), EB.ravel())
    idx = np.arange(len(PV)).reshape(ntb + 1, nta + 1)
    q00, q10, q01, q11 = idx[1:, :-1], idx[1:, 1:], idx[:-1, :-1], idx[:-1, 1:]  # row+1 is lower b
    F = np.concatenate([np.stack([q00, q10, q11], -1).reshape(-1, 3), np.stack([q00, q11, q01], -1).reshape(-1, 3)])
    nf_plane = len(F)
    V = PV
    if occluders is not None:
        OV, OF = (np.asarray(occluders[0], float), np.asarray(occluders[1], np.int64))
        F = np.concatenate([F, OF + len(V)])
        V = np.concatenate([V, OV])
    # which plane triangle holds each cell centre
    r, c = np.mgrid[0:h, 0:w]
    tr, tc = r // per, c // per
    fa = (A - ea[tc]) / (per * grid.cell_m)  # in [0, 1) along a within the tile
    fb = (eb[tr] - B) / (per * grid.cell_m)  # in [0, 1) downwards within the tile
    lower = (1 - fb) <= fa  # triangle (q00, q10, q11) holds points with (1 - fb) <= fa
    tile = tr * nta + tc
    face = np.where(lower, tile, tile + nta * ntb)
    P = plane.points(A.ravel(), B.ravel())
    from .texture import face_view_scores

    # a local frame for Embree's float32 ray casting (texture.local_origin); distances and angles do not change
    origin = local_origin(V)
    V, P = V - origin, P - origin
    views = [view_in_frame(v, origin) for v in views]

    scores = face_view_scores(V, F, views, max_angle_deg=cfg.max_angle_deg, border_fraction=cfg.border_fraction)
    inter = _intersector(V, F)
    planes = plane_ids(V, F)
    surfaces = [pixel_surfaces(inter, V, F, v, planes) for v in views]
    K = len(views)
    N = h * w
    fr = face.ravel()
    sample = _levelling_sample(N, LEVELLING_SAMPLE_CELLS) if lev_mode is Levelling.OFFSETS else None
    sel, _, sample_k = select_in_chunks(inter, V, F, views, surfaces, scores, P, fr, cfg, sample=sample,
                                        chunk_point_views=max(1, int(chunk_cells)) * max(K, 1))
    T, src = sel.temperature_k.astype(np.float32), sel.source.astype(np.int32)
    ang, dist = sel.angle_deg.astype(np.float32), sel.distance_m
    n_usable_sample = sel.n_usable[sample] if sample is not None else None
    del sel
    T, src, ang, dist = T.reshape(h, w), src.reshape(h, w), ang.reshape(h, w), dist.reshape(h, w)
    res = np.full((h, w), np.nan, np.float32)
    ok = src >= 0
    fpx = np.array([0.5 * (v.camera.K[0, 0] + v.camera.K[1, 1]) for v in views])
    res[ok] = (fpx[src[ok]] * np.cos(np.deg2rad(ang[ok])) / dist[ok]).astype(np.float32)
    lev = None
    if sample is not None:
        lev = _apply_levelling(T, src, sample_k[n_usable_sample >= 2], np.bincount(src[ok], minlength=K))
    _ = nf_plane
    notes = ("ortho on a plane with occluding geometry: occlusion and mixed-pixel tests applied" if occluders is not None else
             "ortho on a plane without occluding geometry: only the plane is known; objects in front are not excluded")
    return FacadeMosaic(T, src, res, [v.name for v in views], grid, notes=notes, angle_deg=ang, levelling=lev)
