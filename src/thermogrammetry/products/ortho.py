"""True orthophoto mosaic whose values are the frames' own values (temperatures, or raw counts).

Per output cell (centre ``(x, y)``, height ``z`` from the DSM, bilinear):

1. **Visibility** per image by a z-buffer: the DSM surface of the tile and of a margin around it (wide enough
   for the tallest relief seen at ``max_angle_deg``) is projected into the image; each bin of ``bin_px`` ×
   ``bin_px`` pixels keeps the nearest depth. The surface is sampled at the DSM cell centres and, at height
   steps (four neighbouring centres spanning more than half the smallest tolerance, and the squares next
   to them), also between them on the bilinear surface the cells' heights come from: ``n`` × ``n`` samples
   per square of centres, ``n = min(4, ceil(√2 s / bin_px))``, ``s`` the largest projected DSM cell in
   pixels. (With the centres
   alone nothing stood between the last roof centre and the first ground centre, where the roof's edge is:
   ground cells that edge hides in a view were taken as visible and given the roof's value.) A cell is
   visible in the image when it projects inside the frame, in front of the camera, and its depth is within
   ``max(4 gsd, 1 % depth)`` of its bin's nearest depth.
2. **Image choice** among the visible images by the score (documented and reported in ``ortho.json``)::

       score = cos θ · (g_min / g) · (1 − 0.5 r)

   θ: angle between the DSM normal (Horn's 3 × 3 slope, :func:`surface_normals`) and the direction to the camera,
   at most ``max_angle_deg``; g = distance / f_px: the image's
   ground sampling distance at the cell, g_min the best among the visible images; r: distance of the
   projected point from the image centre divided by the half-diagonal. The highest score wins (ties:
   lowest image index). No blending: the value is the chosen frame's value at the projected position,
   **nearest** (bit-exact copy of the source pixel) or **bilinear**. (Feathering would average several images and alter values; it is
   not offered.)
3. Optional per-pixel **correction** for viewing angle, directional emissivity and atmospheric
   transmission over the real distance (:mod:`.correction`, seed 000) from the DSM normal and distance.

Rasters (tiled COGs with overviews, the survey's CRS): temperature float32 (NaN = none; K or °C; unit in
the band metadata), its 16-bit encoding with one scale/offset for the mosaic (seed 002), the source image
index (int32, −1 = none; bands 2–3: the source pixel's row and column), viewing angle (°), distance (m), and the temperature gradient (magnitude per
metre and direction, seed 002's GIS analysis).

References
----------
Seed 002 (thermal orthophoto mosaics for GIS, invertible 16-bit encoding, gradient analysis);
Sawicki, Stein, Więcek (seed 000) eq. 7–8 for the correction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..enums import StrChoice
from .._validate import config_keys

__all__ = ["Sampling", "OrthoConfig", "ortho_tile", "gradient", "surface_normals", "bilinear", "project_world", "occluders",
           "occluder_subdivision", "SCORE_DOC"]

SCORE_DOC = ("score = cos(theta) * (g_min / g) * (1 - 0.5 r); theta = angle between the DSM normal and the "
             "direction to the camera, g = distance / f_px (image GSD at the cell), g_min = best g among the "
             "visible images, r = distance from the image centre / half-diagonal; highest score wins, ties -> "
             "lowest index; no blending")


class Sampling(StrChoice):
    NEAREST = "nearest"
    BILINEAR = "bilinear"


@dataclass(frozen=True)
class OrthoConfig:
    """Options of the orthophoto (unknown keys are errors in :meth:`from_dict`)."""

    sampling: Sampling = Sampling.NEAREST
    max_angle_deg: float = 60.0
    bin_px: int = 2
    tolerance_m: float | None = None  # default max(4 gsd, 1 % depth)

    def __post_init__(self):
        object.__setattr__(self, "sampling", Sampling(self.sampling))

    @classmethod
    def from_dict(cls, d) -> "OrthoConfig":
        return cls(**config_keys(cls, d))


def project_world(cam, R, t, X):
    """Pixels (N, 2) (NaN behind the camera or for non-finite points) and camera depths (N,)."""
    Xc = np.einsum("ij,kj->ik", X, R) + t
    good = np.isfinite(Xc).all(axis=1) & (Xc[:, 2] > 1e-9)
    uv = np.full((len(X), 2), np.nan)
    if good.any():
        uv[good] = np.asarray(cam.project(Xc[good]), float)
    return uv, np.where(good, Xc[:, 2], np.nan)


def ortho_tile(X, Y, Z, normals, dsm_pts, images, frames, config: OrthoConfig | None = None, *, gsd: float,
               masks=None):
    """Mosaic one tile.

    Parameters
    ----------
    X, Y, Z : (h, w) cell centres and DSM heights (m; Z NaN = no surface)
    normals : (h, w, 3) unit DSM normals (up)
    dsm_pts : (M, 3) DSM surface points of the tile and its margin (the occluders for the z-buffer,
        see :func:`occluders`)
    images : list of (index, camera, R, t) candidate images
    frames : callable index -> frame array
    gsd : cell size (m)
    masks : callable index -> (H, W) bool or None, optional
        Pixels that are never a source (a camera display burned into 8-bit frames): a cell whose projection falls
        there takes its value from another image that sees it.

    Returns
    -------
    dict of (h, w) arrays: ``value`` float64 (NaN none), ``source`` int32 (−1), ``row``/``col`` int32 (source
    pixel for nearest), ``angle_deg``, ``distance_m``, ``in_frame`` bool (the cell's surface point projects into
    some candidate frame, in front of its camera: the images' footprint on the surface)
    """
    cfg = config or OrthoConfig()
    h, w = X.shape
    P = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    n = normals.reshape(-1, 3)
    ok = np.isfinite(P).all(axis=1)
    best = np.full(h * w, -np.inf)
    src = np.full(h * w, -1, np.int32)
    val = np.full(h * w, np.nan)
    rowi = np.full(h * w, -1, np.int32)
    coli = np.full(h * w, -1, np.int32)
    ang = np.full(h * w, np.nan)
    dist = np.full(h * w, np.nan)
    gmin = np.full(h * w, np.inf)
    per = []
    in_frame = np.zeros(h * w, bool)
    cos_max = np.cos(np.radians(cfg.max_angle_deg))
    for idx, cam, R, t in images:
        W, H = cam.image_size
        uv, z = project_world(cam, R, t, P)
        with np.errstate(invalid="ignore"):
            inside = ok & (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < H - 0.5)
        if not inside.any():
            continue
        in_frame |= inside
        C = -R.T @ t
        d = C[None] - P
        dn = np.linalg.norm(d, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cth = np.einsum("ij,ij->i", n, d) / dn
        inside &= cth > cos_max
        # z-buffer of the occluders
        b = max(1, int(cfg.bin_px))
        uo, zo = project_world(cam, R, t, dsm_pts)
        good = np.isfinite(uo).all(axis=1) & (zo > 0)
        bw, bh = W // b + 1, H // b + 1
        bu = np.floor((uo[good, 0] + 0.5) / b).astype(np.int64)
        bv = np.floor((uo[good, 1] + 0.5) / b).astype(np.int64)
        inb = (bu >= 0) & (bu < bw) & (bv >= 0) & (bv < bh)
        zbuf = np.full(bw * bh, np.inf)
        np.minimum.at(zbuf, (bv[inb] * bw + bu[inb]), zo[good][inb])
        ci = np.flatnonzero(inside)
        cb = (np.floor((uv[ci, 1] + 0.5) / b).astype(np.int64) * bw + np.floor((uv[ci, 0] + 0.5) / b).astype(np.int64))
        tol = cfg.tolerance_m if cfg.tolerance_m is not None else np.maximum(4 * gsd, 0.01 * z[ci])
        vis = z[ci] <= zbuf[cb] + tol
        ci = ci[vis]
        dm = masks(idx) if masks is not None else None
        if dm is not None and len(ci):
            rr = np.clip(np.rint(uv[ci, 1]).astype(np.int64), 0, H - 1)
            cc = np.clip(np.rint(uv[ci, 0]).astype(np.int64), 0, W - 1)
            ci = ci[~dm[rr, cc]]
        if len(ci) == 0:
            continue
        f_px = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
        g = dn[ci] / f_px
        gmin[ci] = np.minimum(gmin[ci], g)
        r = np.hypot(uv[ci, 0] - (W - 1) / 2, uv[ci, 1] - (H - 1) / 2) / np.hypot((W - 1) / 2, (H - 1) / 2)
        per.append((idx, ci, g, cth[ci], r, uv[ci], dn[ci]))
    for idx, ci, g, cth, r, uv, dn in per:
        score = cth * (gmin[ci] / g) * (1 - 0.5 * r)
        win = score > best[ci]
        ci, score = ci[win], score[win]
        best[ci] = score
        src[ci] = idx
        rowi[ci] = np.clip(np.rint(uv[win, 1]), 0, None).astype(np.int32)
        coli[ci] = np.clip(np.rint(uv[win, 0]), 0, None).astype(np.int32)
        ang[ci] = np.degrees(np.arccos(np.clip(cth[win], -1, 1)))
        dist[ci] = dn[win]
    # values: one pass per chosen image
    for idx in np.unique(src[src >= 0]):
        sel = np.flatnonzero(src == idx)
        fr = np.asarray(frames(int(idx)))
        if fr.ndim == 3:
            fr = fr[..., 0]
        Hh, Ww = fr.shape
        rr, cc = np.minimum(rowi[sel], Hh - 1), np.minimum(coli[sel], Ww - 1)
        if cfg.sampling == Sampling.NEAREST:
            val[sel] = fr[rr, cc]
        else:
            cam, R, t = next((c, Rm, tv) for k, c, Rm, tv in images if k == idx)
            uv, _ = project_world(cam, R, t, P[sel])
            x0 = np.clip(np.floor(uv[:, 0]).astype(int), 0, Ww - 2)
            y0 = np.clip(np.floor(uv[:, 1]).astype(int), 0, Hh - 2)
            fx = np.clip(uv[:, 0] - x0, 0, 1)
            fy = np.clip(uv[:, 1] - y0, 0, 1)
            a = fr.astype(np.float64)
            val[sel] = ((a[y0, x0] * (1 - fx) + a[y0, x0 + 1] * fx) * (1 - fy)
                        + (a[y0 + 1, x0] * (1 - fx) + a[y0 + 1, x0 + 1] * fx) * fy)
    return {"value": val.reshape(h, w), "source": src.reshape(h, w), "row": rowi.reshape(h, w),
            "col": coli.reshape(h, w), "angle_deg": ang.reshape(h, w), "distance_m": dist.reshape(h, w),
            "in_frame": in_frame.reshape(h, w)}


def surface_normals(Z, gsd: float) -> np.ndarray:
    """(h, w, 3) unit upward normals of a north-up height grid (row 0 north) by Horn's 3 × 3 slope estimator [H81]_:
    ``∂z/∂x = ((z_NE + 2 z_E + z_SE) − (z_NW + 2 z_W + z_SW)) / (8 gsd)`` and likewise north. It weighs the three
    rows (columns) of the neighbourhood, so that the slope's noise from independent height errors σ is 0.43 σ/gsd
    against 0.71 σ/gsd for the central difference of two cells: on a photogrammetric DSM, whose neighbouring cells
    differ by their noise, the viewing angle to the normal is less often the noise's. Cells without all 8
    neighbours (the grid's border, next to a hole) get the vertical normal.

    References
    ----------
    .. [H81] Horn, B. K. P. (1981). Hill shading and the reflectance map. Proceedings of the IEEE 69(1), 14-47.
    """
    a = np.asarray(Z, float)
    gx = np.full(a.shape, np.nan)
    gy = np.full(a.shape, np.nan)
    if min(a.shape) >= 3:
        gx[1:-1, 1:-1] = ((a[:-2, 2:] + 2 * a[1:-1, 2:] + a[2:, 2:]) - (a[:-2, :-2] + 2 * a[1:-1, :-2] + a[2:, :-2])) / (8 * gsd)
        gy[1:-1, 1:-1] = ((a[:-2, :-2] + 2 * a[:-2, 1:-1] + a[:-2, 2:]) - (a[2:, :-2] + 2 * a[2:, 1:-1] + a[2:, 2:])) / (8 * gsd)
    n = np.stack([-gx, -gy, np.ones_like(a)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where(np.isfinite(n), n, np.array([0.0, 0.0, 1.0]))


def gradient(values, gsd: float) -> tuple[np.ndarray, np.ndarray]:
    """Gradient magnitude (unit per metre) and direction (degrees clockwise from grid north, the direction of
    increase) of a north-up raster by central differences; NaN where a neighbour is missing.

    Parameters
    ----------
    values : (H, W) raster (rows southwards); gsd : cell size (m)
    """
    v = np.asarray(values, float)
    gx = np.full_like(v, np.nan)
    gy = np.full_like(v, np.nan)
    gx[:, 1:-1] = (v[:, 2:] - v[:, :-2]) / (2 * gsd)  # east
    gy[1:-1] = (v[:-2] - v[2:]) / (2 * gsd)  # north (row 0 is north)
    mag = np.hypot(gx, gy)
    direction = np.degrees(np.arctan2(gx, gy)) % 360.0
    return mag, np.where(np.isfinite(mag), direction, np.nan)


# --------------------------------------------------------------------------------------------- workflow
def bilinear(a, r, c):
    """Bilinear sample of ``a`` at fractional (row, col) of cell centres; NaN outside or next to NaN."""
    H, W = a.shape
    r0 = np.floor(r).astype(np.int64)
    c0 = np.floor(c).astype(np.int64)
    fr, fc = r - r0, c - c0
    ok = (r0 >= 0) & (c0 >= 0) & (r0 + 1 < H) & (c0 + 1 < W)
    r0c, c0c = np.clip(r0, 0, max(H - 2, 0)), np.clip(c0, 0, max(W - 2, 0))
    r1c, c1c = np.minimum(r0c + 1, H - 1), np.minimum(c0c + 1, W - 1)
    v = ((a[r0c, c0c] * (1 - fc) + a[r0c, c1c] * fc) * (1 - fr) + (a[r1c, c0c] * (1 - fc) + a[r1c, c1c] * fc) * fr)
    # exactly on a cell centre: take that cell (no NaN from an unused neighbour)
    exact = ok & (fr == 0) & (fc == 0)
    v = np.where(exact, a[r0c, c0c], v)
    return np.where(ok | exact, v, np.nan)


def occluder_subdivision(cell_px: float, bin_px: int) -> int:
    """Samples per DSM cell side for the z-buffer's surface between the cell centres:
    ``min(4, max(1, ceil(√2 cell_px / bin_px)))``, so that the samples project at most one bin apart even
    along the diagonal (a continuous edge in the z-buffer, whatever the image's rotation to the grid);
    ``cell_px`` is the largest projected DSM cell in pixels."""
    b = max(1, int(bin_px))
    if not np.isfinite(cell_px) or cell_px <= 0:
        return 1
    return int(min(4, max(1, np.ceil(np.sqrt(2.0) * cell_px / b))))


def occluders(D, dg, dr0: int, dc0: int, n: int, *, min_span_m: float = 0.0) -> np.ndarray:
    """(M, 3) occluder points of the DSM window ``D`` (rows from ``dr0``, columns from ``dc0`` of the DSM grid
    ``dg``): the cell centres and, for ``n`` > 1, the bilinear surface between them (the surface the ortho
    cells' heights come from, :func:`_bilinear`) at fractions ``k / n`` of the spacing, in each square of four
    centres whose heights span more than ``min_span_m`` (height steps; elsewhere every point of the square
    lies within ``min_span_m`` of its corners, which stand for it) and in the squares next to those.
    Squares with a missing corner are skipped."""
    rows, cols = D.shape
    dcol, drow = np.meshgrid(np.arange(dc0, dc0 + cols), np.arange(dr0, dr0 + rows))
    occ = np.column_stack([(dg.x0 + (dcol + 0.5) * dg.gsd).ravel(), (dg.y0 - (drow + 0.5) * dg.gsd).ravel(), D.ravel()])
    occ = occ[np.isfinite(occ[:, 2])]
    n = int(n)
    if n <= 1 or rows < 2 or cols < 2:
        return occ
    from scipy.ndimage import binary_dilation

    q = np.stack([D[:-1, :-1], D[:-1, 1:], D[1:, :-1], D[1:, 1:]])
    with np.errstate(invalid="ignore"):
        step = (q.max(axis=0) - q.min(axis=0)) > min_span_m  # NaN corner -> False
    # and the squares next to a step: a bin straddling the projected edge takes the roof only when a roof
    # sample falls in it
    step = binary_dilation(step, np.ones((3, 3), bool)) & np.isfinite(q).all(axis=0)
    i, j = np.nonzero(step)
    if len(i) == 0:
        return occ
    a, b = np.meshgrid(np.arange(n) / n, np.arange(n) / n, indexing="ij")
    a, b = a.ravel()[1:], b.ravel()[1:]  # (0, 0) is the centre itself
    fr, fc = i[:, None] + a, j[:, None] + b
    Z = bilinear(D, fr, fc)  # the squares' four corners are finite: no NaN
    sub = np.column_stack([(dg.x0 + (dc0 + fc + 0.5) * dg.gsd).ravel(), (dg.y0 - (dr0 + fr + 0.5) * dg.gsd).ravel(),
                           Z.ravel()])
    return np.concatenate([occ, sub])

#: the names these functions had before they became public (kept for code that imports them)
_project = project_world
_bilinear = bilinear


def __getattr__(name):
    """``run_ortho`` and ``check_dsm_matches_survey`` moved to :mod:`thermogrammetry.pipeline.ortho` (the verb's
    driver, which reads the survey folder and the DSM file); this keeps the old import path working."""
    if name in ("run_ortho", "check_dsm_matches_survey"):
        import importlib

        return getattr(importlib.import_module("thermogrammetry.pipeline.ortho"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
