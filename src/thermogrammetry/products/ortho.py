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

   θ: angle between the DSM normal and the direction to the camera; g = distance / f_px: the image's
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
from .raster import Grid
from .._validate import config_keys

__all__ = ["Sampling", "OrthoConfig", "ortho_tile", "gradient", "SCORE_DOC"]

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


def _project(cam, R, t, X):
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
    pixel for nearest), ``angle_deg``, ``distance_m``
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
    cos_max = np.cos(np.radians(cfg.max_angle_deg))
    for idx, cam, R, t in images:
        W, H = cam.image_size
        uv, z = _project(cam, R, t, P)
        with np.errstate(invalid="ignore"):
            inside = ok & (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < H - 0.5)
        if not inside.any():
            continue
        C = -R.T @ t
        d = C[None] - P
        dn = np.linalg.norm(d, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cth = np.einsum("ij,ij->i", n, d) / dn
        inside &= cth > cos_max
        # z-buffer of the occluders
        b = max(1, int(cfg.bin_px))
        uo, zo = _project(cam, R, t, dsm_pts)
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
            uv, _ = _project(cam, R, t, P[sel])
            x0 = np.clip(np.floor(uv[:, 0]).astype(int), 0, Ww - 2)
            y0 = np.clip(np.floor(uv[:, 1]).astype(int), 0, Hh - 2)
            fx = np.clip(uv[:, 0] - x0, 0, 1)
            fy = np.clip(uv[:, 1] - y0, 0, 1)
            a = fr.astype(np.float64)
            val[sel] = ((a[y0, x0] * (1 - fx) + a[y0, x0 + 1] * fx) * (1 - fy)
                        + (a[y0 + 1, x0] * (1 - fx) + a[y0 + 1, x0 + 1] * fx) * fy)
    return {"value": val.reshape(h, w), "source": src.reshape(h, w), "row": rowi.reshape(h, w),
            "col": coli.reshape(h, w), "angle_deg": ang.reshape(h, w), "distance_m": dist.reshape(h, w)}


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
def _bilinear(a, r, c):
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


def _survey(path):
    from ..dense.workflow import _survey as s

    return s(path)


def _ortho_task(survey_path: str, dsm_path: str, grid: Grid, window, cfg: OrthoConfig, margin_m: float,
                correction=None, unit_out: str = "K"):
    from .raster import read_raster, read_window

    sv = _survey(survey_path)
    r0, c0, rows, cols = window
    # ortho cells (with a one-cell pad for the normals) and their DSM heights
    X, Y = grid.cell_centres(r0 - 1, c0 - 1, rows + 2, cols + 2)
    dsm_meta = _dsm_meta(dsm_path)
    dg = dsm_meta["grid"]
    pad = int(np.ceil(margin_m / dg.gsd)) + 2
    xa, xb = X.min(), X.max()
    ya, yb = Y.min(), Y.max()
    dc0 = int(np.floor((xa - dg.x0) / dg.gsd)) - pad
    dr0 = int(np.floor((dg.y0 - yb) / dg.gsd)) - pad
    dc1 = int(np.ceil((xb - dg.x0) / dg.gsd)) + pad
    dr1 = int(np.ceil((dg.y0 - ya) / dg.gsd)) + pad
    D = read_window(dsm_path, dr0, dc0, dr1 - dr0, dc1 - dc0)
    Z = _bilinear(D, (dg.y0 - Y) / dg.gsd - 0.5 - dr0, (X - dg.x0) / dg.gsd - 0.5 - dc0)
    gx = np.full_like(Z, np.nan)
    gy = np.full_like(Z, np.nan)
    gx[:, 1:-1] = (Z[:, 2:] - Z[:, :-2]) / (2 * grid.gsd)
    gy[1:-1] = (Z[:-2] - Z[2:]) / (2 * grid.gsd)
    nrm = np.stack([-gx, -gy, np.ones_like(Z)], axis=-1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    X, Y, Z, nrm = X[1:-1, 1:-1], Y[1:-1, 1:-1], Z[1:-1, 1:-1], nrm[1:-1, 1:-1]
    nrm = np.where(np.isfinite(nrm), nrm, np.array([0.0, 0.0, 1.0]))  # border of the DSM: horizontal
    # candidate images: the tile's box (at the DSM's height range) projects into the frame
    images = []
    cell_px = 0.0  # largest projected DSM cell (px) among the candidates
    if np.isfinite(Z).any():
        zlo, zhi = np.nanmin(Z), np.nanmax(Z)
        corners = np.array([[x, y, z] for x in (xa, xb) for y in (ya, yb) for z in (zlo, zhi)])
        for k in range(len(sv)):
            cam, (R, t) = sv.cameras[k], sv.poses[k]
            uv, z = _project(cam, R, t, corners)
            if not (z > 0).all() or not np.isfinite(uv).all():
                continue
            W, H = cam.image_size
            if uv[:, 0].max() < -0.5 or uv[:, 0].min() > W - 0.5 or uv[:, 1].max() < -0.5 or uv[:, 1].min() > H - 0.5:
                continue
            images.append((k, cam, R, t))
            cell_px = max(cell_px, dg.gsd * max(cam.K[0, 0], cam.K[1, 1]) / float(z.min()))
    # between the centres only at height steps: a square spanning less than half the smallest visibility
    # tolerance is represented by its corners to within that (its points hide no cell its corners do not)
    tol_min = cfg.tolerance_m if cfg.tolerance_m is not None else 4 * grid.gsd
    occ = occluders(D, dg, dr0, dc0, occluder_subdivision(cell_px, cfg.bin_px), min_span_m=0.5 * tol_min)
    res = ortho_tile(X, Y, Z, nrm, occ, images, sv, cfg, gsd=grid.gsd, masks=sv.display_mask)
    v = res["value"]
    notes = 0
    if correction is not None:
        from .correction import apply_correction

        on = res["source"] >= 0
        Tc, eps, tau, valid = apply_correction(v, np.radians(res["angle_deg"]), res["distance_m"], on, correction)
        notes = int((on & ~valid).sum())
        v = np.where(valid, Tc, np.nan)
    if unit_out == "C":
        v = v - 273.15
    res["value"] = v.astype(np.float32)
    res["uncorrected"] = notes
    return res


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
    Z = _bilinear(D, fr, fc)  # the squares' four corners are finite: no NaN
    sub = np.column_stack([(dg.x0 + (dc0 + fc + 0.5) * dg.gsd).ravel(), (dg.y0 - (dr0 + fr + 0.5) * dg.gsd).ravel(),
                           Z.ravel()])
    return np.concatenate([occ, sub])


_DSM_META: dict = {}


def _dsm_meta(path):
    key = str(path)
    if key not in _DSM_META:
        import rasterio

        from .raster import read_raster  # noqa: F401

        with rasterio.open(path) as src:
            tr = src.transform
            g = Grid(tr.c, tr.f, tr.a, src.width, src.height)
            ov = src.read(1, out_shape=(max(1, src.height // 8), max(1, src.width // 8)), masked=True)
            crs = src.crs.to_string() if src.crs else None
        vals = np.asarray(ov.astype(float).filled(np.nan))
        _DSM_META.clear()
        _DSM_META[key] = {"grid": g, "crs": crs, "zmin": float(np.nanmin(vals)) if np.isfinite(vals).any() else 0.0,
                          "zmax": float(np.nanmax(vals)) if np.isfinite(vals).any() else 0.0}
    return _DSM_META[key]


def check_dsm_matches_survey(meta: dict, sv, dsm_path, survey_dir) -> None:
    """Raise :class:`~thermogrammetry.errors.ConfigError` when the DSM cannot belong to the survey: another
    horizontal CRS than ``cameras.json``'s, or an extent that no camera can see (the ground within
    ``max(200 m, 5 × flying height above the DSM)`` of a camera centre, i.e. up to ~79° off nadir)."""
    from ..errors import ConfigError
    from .raster import same_horizontal_crs

    a, b = meta.get("crs"), sv.crs
    if not same_horizontal_crs(a, b):
        raise ConfigError(f"{dsm_path}: the DSM is in {a}, the survey {survey_dir} in {b}; expected the DSM in the "
                          f"survey's CRS (reproject it first, e.g. gdalwarp -t_srs {b})")
    g = meta["grid"]
    dx0, dx1 = g.x0, g.x0 + g.width * g.gsd
    dy0, dy1 = g.y0 - g.height * g.gsd, g.y0
    C = np.array([im.center for im in sv.images])
    height = max(0.0, float(np.max(C[:, 2])) - float(meta["zmin"]))
    reach = max(200.0, 5.0 * height)
    cx0, cy0 = C[:, :2].min(axis=0) - reach
    cx1, cy1 = C[:, :2].max(axis=0) + reach
    if dx1 < cx0 or dx0 > cx1 or dy1 < cy0 or dy0 > cy1:
        raise ConfigError(f"{dsm_path}: the DSM covers X {dx0:.2f}..{dx1:.2f}, Y {dy0:.2f}..{dy1:.2f} m, which no camera of "
                          f"{survey_dir} sees (camera centres X {C[:, 0].min():.2f}..{C[:, 0].max():.2f}, Y "
                          f"{C[:, 1].min():.2f}..{C[:, 1].max():.2f} m, crs {b or 'local frame'}); expected a DSM of the "
                          "surveyed area in the survey's coordinates")


def run_ortho(survey_dir, dsm_path, out_dir, *, gsd: float | None = None, unit: str | None = None,
              sampling: str = "nearest", correct: bool = False, correction=None, workers: int = 1,
              scheduler: str | None = None, tile: int = 512, config: OrthoConfig | None = None) -> dict:
    """``thermogrammetry ortho``: the mosaic and its companion rasters in ``out_dir``; returns ``ortho.json``."""
    import json
    import time
    from pathlib import Path

    from .._atomic import write_atomic_text
    from ..dense.workflow import SurveyFrames, open_client, ordered_results
    from ..errors import ConfigError
    from ..radiometry.encoding import choose_uint16_mapping, encode_uint16
    from .correction import as_correction_config
    from .raster import RasterSpec, read_window, write_cogs

    t0 = time.perf_counter()
    out = Path(out_dir)
    sv = SurveyFrames(survey_dir)
    if not Path(dsm_path).exists():
        from ..errors import DataFileError

        raise DataFileError(f"{dsm_path}: no such DSM; expected the dsm.tif written by 'thermogrammetry dense'")
    meta = _dsm_meta(str(Path(dsm_path).resolve()))
    check_dsm_matches_survey(meta, sv, dsm_path, survey_dir)
    cfg = config or OrthoConfig(sampling=sampling)
    notes = []
    if sv.unit == "K":
        unit_out = (unit or "K").upper().lstrip("°")
        if unit_out not in ("K", "C"):
            raise ConfigError(f"--unit {unit!r}: expected K or C")
        label = "K" if unit_out == "K" else "°C"
        if unit_out == "C":
            notes.append("values converted to °C (value − 273.15 in float32): equal to the source within float32 "
                         "rounding, not bit-exact; use --unit K for bit-exact copies")
    else:
        if unit not in (None, sv.unit):
            raise ConfigError(f"--unit {unit}: the frames of {survey_dir} are {sv.unit!r} "
                              f"({'raw sensor counts' if sv.unit == 'counts' else 'display numbers'}), not temperatures; "
                              "omit --unit")
        unit_out = sv.unit
        label = "counts" if sv.unit == "counts" else "dn"
        notes.append("frames are raw sensor counts: the mosaic holds counts, not temperatures (labelled 'counts')"
                     if sv.unit == "counts" else
                     "frames are display numbers of an 8-bit rendering: geometry-only product, no temperature")
        if sv.display_mask(0) is not None:
            notes.append("a camera display burned into the frames (found by survey: work/overlay.json): its pixels "
                         "are never a source, the cells take their value from another image")
        if correct:
            raise ConfigError("--correct needs temperature frames (unit K); these frames are "
                              f"{sv.unit!r}")
    corr = as_correction_config(correction) if correct else None
    g = gsd if gsd is not None else meta["grid"].gsd
    if not (np.isfinite(g) and g > 0):
        raise ConfigError(f"--gsd {gsd!r}: expected a positive cell size in metres")
    dg = meta["grid"]
    grid = Grid(dg.x0, dg.y0, float(g), int(np.ceil(dg.width * dg.gsd / g)), int(np.ceil(dg.height * dg.gsd / g)), tile)
    margin_m = min(50.0, (meta["zmax"] - meta["zmin"]) * np.tan(np.radians(cfg.max_angle_deg)))
    out.mkdir(parents=True, exist_ok=True)
    client = open_client(workers, scheduler)
    spath = str(Path(survey_dir).resolve())
    dpath = str(Path(dsm_path).resolve())
    windows = list(grid.tiles())
    stats = {"lo": np.inf, "hi": -np.inf, "cells": 0, "uncorrected": 0}
    sources: set = set()

    def collect(res):
        v = res["value"]
        if np.isfinite(v).any():
            stats["lo"] = min(stats["lo"], float(np.nanmin(v)))
            stats["hi"] = max(stats["hi"], float(np.nanmax(v)))
        stats["cells"] += int(np.isfinite(v).sum())
        stats["uncorrected"] += res["uncorrected"]
        sources.update(int(s) for s in np.unique(res["source"]) if s >= 0)
        return {"value": v, "source": np.stack([res["source"], res["row"], res["col"]]), "angle": res["angle_deg"].astype(np.float32),
                "distance": res["distance_m"].astype(np.float32)}

    try:
        if client is not None:
            nt = len(windows)
            tiles = (collect(r) for r in ordered_results(client, _ortho_task, [spath] * nt, [dpath] * nt, [grid] * nt,
                                                         windows, [cfg] * nt, [margin_m] * nt, [corr] * nt,
                                                         [unit_out] * nt))
        else:
            tiles = (collect(_ortho_task(spath, dpath, grid, w, cfg, margin_m, corr, unit_out)) for w in windows)
        crs = sv.crs
        specs = {
            "value": RasterSpec(out / "ortho.tif", np.float32, nodata=float("nan"), unit=label,
                                description=("temperature" if sv.unit == "K" else
                                             "raw sensor counts (not a temperature)" if sv.unit == "counts" else
                                             "display numbers (not a temperature)") + f" [{label}]",
                                tags={"product": "thermogrammetry ortho", "unit": label}),
            "source": RasterSpec(out / "ortho_source.tif", np.int32, bands=3, nodata=-1, resampling="nearest",
                                 description=["source image index (lookup table in ortho.json; -1 = none)",
                                              "source pixel row (nearest sampling: the value is frame[row, col])",
                                              "source pixel column"]),
            "angle": RasterSpec(out / "ortho_angle.tif", np.float32, nodata=float("nan"), unit="deg",
                                description="viewing angle to the DSM normal (deg)"),
            "distance": RasterSpec(out / "ortho_distance.tif", np.float32, nodata=float("nan"), unit="m",
                                   description="camera-to-surface distance (m)"),
        }
        write_cogs(grid, specs, None, crs=crs, tiles=tiles)
    finally:
        if client is not None:
            client.close()
    # 16-bit encoding with one mapping for the whole mosaic (seed 002)
    if np.isfinite(stats["lo"]):
        if sv.unit == "K":
            lo_k = stats["lo"] + (273.15 if unit_out == "C" else 0.0)
            hi_k = stats["hi"] + (273.15 if unit_out == "C" else 0.0)
            mapping = choose_uint16_mapping(np.array([lo_k, hi_k]), unit_out)
            scale, offset = mapping.scale, mapping.offset

            def enc(v):
                return encode_uint16(v + (273.15 if unit_out == "C" else 0.0), mapping)
        else:
            scale, offset = 1.0, 0.0

            def enc(v):
                return np.where(np.isfinite(v), np.clip(v, 1, 65535), 0).astype(np.uint16)
    else:
        scale, offset = 1.0, 0.0

        def enc(v):
            return np.zeros(v.shape, np.uint16)

    def u16_tile(r0, c0, rows, cols):
        v = read_window(out / "ortho.tif", r0, c0, rows, cols)
        return {"u16": enc(v)}

    def grad_tile(r0, c0, rows, cols):
        v = read_window(out / "ortho.tif", r0 - 1, c0 - 1, rows + 2, cols + 2)
        mag, direc = gradient(v, grid.gsd)
        return {"grad": np.stack([mag[1:-1, 1:-1], direc[1:-1, 1:-1]]).astype(np.float32)}

    write_cogs(grid, {"u16": RasterSpec(out / "ortho_u16.tif", np.uint16, nodata=0, unit=label, scale=scale, offset=offset,
                                        description=f"{label} = code * {scale:g} + {offset:g}; 0 = no data",
                                        resampling="nearest")}, u16_tile, crs=sv.crs)
    write_cogs(grid, {"grad": RasterSpec(out / "ortho_gradient.tif", np.float32, bands=2, nodata=float("nan"),
                                         description=[f"gradient magnitude ({label}/m)",
                                                      "gradient direction (deg clockwise from grid north, uphill)"])},
               grad_tile, crs=sv.crs)
    if stats["uncorrected"]:
        notes.append(f"{stats['uncorrected']} cells left empty by --correct (no valid correction: angle ≥ "
                     f"{corr.max_angle_deg}° or no real solution)")
    if sv.crs is None:
        notes.append("cameras.json has no CRS: rasters are in the survey's local frame (no CRS written)")
    report = {
        "images": {str(k): sv.names[k] for k in range(len(sv))},
        "unit": label,
        "scale": scale,
        "offset": offset,
        "u16_nodata": 0,
        "sampling": str(cfg.sampling),
        "score": SCORE_DOC,
        "gsd_m": grid.gsd,
        "width": grid.width,
        "height": grid.height,
        "crs": sv.crs,
        "cells": stats["cells"],
        "images_used": len(sources),
        "corrected": bool(correct),
        "correction": None if corr is None else {k: str(getattr(corr, k)) for k in corr.__dataclass_fields__},
        "seconds": round(time.perf_counter() - t0, 2),
        "notes": notes,
    }
    write_atomic_text(out / "ortho.json", json.dumps(report, indent=1) + "\n")
    return report
