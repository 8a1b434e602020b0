"""Temperature comparisons with their standard deviations: two orthophotos of one surface, an orthophoto against a
reference temperature raster, an orthophoto against contact readings.

Two rasters (:func:`compare_rasters`)
    ``d = b − a`` on ``a``'s grid (``b`` moved there by :func:`onto_grid`), its standard deviation
    ``σ_d = √(σ_a² + σ_b²)`` (the two rasters' random errors independent: two flights, two sets of sensor noise and
    pose errors), the normalised difference ``z = d / σ_d`` and the two-sided test of "no change" in every cell:
    ``p = 2 Φ(−|z|)``, significant where ``p < α``. Optionally a common offset is removed first (the median of
    ``d`` over the whole overlap or over a box of ground known to be unchanged): the systematic parts of the two
    rasters (each flight's radiometric calibration) are not in ``σ_d``, and a common offset would otherwise flag
    the whole overlap.
Multiple testing
    At a per-cell level α, a share α of the unchanged cells is flagged when the σ are right (a map of 10⁵
    cells: ~5 000 false cells at 5 %, scattered). With ``fdr=True`` the Benjamini–Hochberg step-up procedure is
    used instead: the cells with ``p ≤ p₍ₖ₎``, ``k`` the largest rank with ``p₍ₖ₎ ≤ k α / m`` (``m`` cells
    tested), so that the expected share of unchanged cells among the flagged ones is at most α — proven for
    independent tests and for positively regression-dependent ones (Benjamini & Yekutieli 2001); neighbouring
    cells here share frame pixels and poses (positively correlated errors), which two-sided tests do not fully
    fit in that proof.
Readings (:func:`reading_residuals`)
    per point, the value of the cell containing it and that cell's σ, the residual ``value − reading`` and
    its normalised form ``(value − reading) / √(σ² + σ_reading²)``.

References
----------
.. [1] Y. Benjamini, Y. Hochberg, "Controlling the false discovery rate: a practical and powerful approach to
   multiple testing", J. R. Stat. Soc. B 57 (1995) 289–300.
.. [2] Y. Benjamini, D. Yekutieli, "The control of the false discovery rate in multiple testing under
   dependency", Ann. Stat. 29 (2001) 1165–1188.
.. [3] JCGM 100:2008 (GUM), §5.1: the variance of a difference of uncorrelated quantities is the sum of their
   variances.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from .raster import Grid

__all__ = ["CompareConfig", "Comparison", "onto_grid", "compare_rasters", "z_test", "benjamini_hochberg",
           "reading_residuals", "NOT_COMPARED"]

#: ``significant.tif`` code of a cell without a difference (nodata)
NOT_COMPARED = 255


@dataclass(frozen=True)
class CompareConfig:
    """Options of a comparison of two rasters.

    Attributes
    ----------
    alpha : two-sided level of the per-cell test (0 < α < 1)
    fdr : Benjamini–Hochberg false-discovery control at level α instead of the per-cell level
    remove_offset : ``"none"`` or ``"median"`` (the median difference is removed before the test)
    offset_box : (xmin, ymin, xmax, ymax) in the rasters' CRS: the median over the cells whose centres lie in it
        (ground known to be unchanged); None = the whole overlap
    """

    alpha: float = 0.05
    fdr: bool = False
    remove_offset: str = "none"
    offset_box: tuple[float, float, float, float] | None = None

    def __post_init__(self):
        if not (np.isfinite(self.alpha) and 0.0 < float(self.alpha) < 1.0):
            raise ConfigError(f"--alpha {self.alpha!r}: expected a level between 0 and 1 (e.g. 0.05)")
        if self.remove_offset not in ("none", "median"):
            raise ConfigError(f"--remove-offset {self.remove_offset!r}: expected none or median")
        if self.offset_box is not None:
            b = tuple(float(v) for v in self.offset_box)
            if len(b) != 4 or not all(np.isfinite(b)) or not (b[0] < b[2] and b[1] < b[3]):
                raise ConfigError(f"--offset-box {self.offset_box!r}: expected XMIN,YMIN,XMAX,YMAX with XMIN < XMAX "
                                  "and YMIN < YMAX (m, in the rasters' CRS)")
            if self.remove_offset != "median":
                raise ConfigError("--offset-box: the box is where the median difference is taken; it needs "
                                  "--remove-offset median")


@dataclass
class Comparison:
    """Result of :func:`compare_rasters` on ``a``'s grid (H, W).

    Attributes
    ----------
    difference : (H, W) float64, ``b − a − offset`` in the rasters' unit, NaN where not compared
    sigma : (H, W) float64, ``√(σ_a² + σ_b²)``, NaN where not compared
    significant : (H, W) uint8, 1 significant, 0 not, :data:`NOT_COMPARED` elsewhere
    summary : the figures of ``evaluate.json`` ``comparison`` (see docs/formats/evaluate_json.md)
    """

    difference: np.ndarray
    sigma: np.ndarray
    significant: np.ndarray
    summary: dict = field(default_factory=dict)


def onto_grid(values, sigma, src: Grid, dst: Grid) -> tuple[np.ndarray, np.ndarray, str]:
    """``values`` and their σ (both (h, w) on ``src``) on the grid ``dst``: (H, W) arrays and the method used.

    Grids of one cell size whose origins differ by whole cells (orthos made at the same ``--gsd`` on DSMs of the
    same cell size): the cells are copied (``"same grid"`` or ``"cell copy"``), values and σ unchanged. Otherwise
    ``"bilinear"``: the value bilinear at ``dst``'s cell centres (NaN next to no data), and its σ the same
    bilinear weights applied to the σ (Σ wᵢ σᵢ: the upper bound, reached when the neighbours' errors are fully
    correlated; independent ones would give √Σ wᵢ² σᵢ², down to half at a cell corner). The interpolation's own
    error on a curved temperature field is not in the σ.
    """
    from .evaluate import sample_bilinear

    values, sigma = np.asarray(values, float), np.asarray(sigma, float)
    g = src.gsd
    dc, dr = (src.x0 - dst.x0) / g, (dst.y0 - src.y0) / g
    if abs(src.gsd - dst.gsd) <= 1e-9 * g and abs(dc - round(dc)) < 1e-6 and abs(dr - round(dr)) < 1e-6:
        dc, dr = int(round(dc)), int(round(dr))
        out_v = np.full((dst.height, dst.width), np.nan)
        out_s = np.full((dst.height, dst.width), np.nan)
        r0, r1 = max(dr, 0), min(dr + src.height, dst.height)
        c0, c1 = max(dc, 0), min(dc + src.width, dst.width)
        if r0 < r1 and c0 < c1:
            out_v[r0:r1, c0:c1] = values[r0 - dr:r1 - dr, c0 - dc:c1 - dc]
            out_s[r0:r1, c0:c1] = sigma[r0 - dr:r1 - dr, c0 - dc:c1 - dc]
        same = dc == 0 and dr == 0 and (src.width, src.height) == (dst.width, dst.height)
        return out_v, out_s, "same grid" if same else f"cell copy (aligned grids, offset {dr} rows, {dc} columns)"
    X, Y = dst.cell_centres(0, 0, dst.height, dst.width)
    return (sample_bilinear(values, src, X, Y), sample_bilinear(sigma, src, X, Y),
            "bilinear (value; σ interpolated with the same weights, an upper bound)")


def z_test(d, s) -> tuple[np.ndarray, np.ndarray]:
    """Normalised differences ``z = d / s`` and two-sided p-values ``2 Φ(−|z|)`` (NaN where ``s`` is not > 0)."""
    from scipy.special import ndtr

    d, s = np.asarray(d, float), np.asarray(s, float)
    ok = np.isfinite(d) & np.isfinite(s) & (s > 0)
    z = np.full(d.shape, np.nan)
    z[ok] = d[ok] / s[ok]
    p = np.full(d.shape, np.nan)
    p[ok] = 2.0 * ndtr(-np.abs(z[ok]))
    return z, p


def benjamini_hochberg(p, alpha: float) -> tuple[np.ndarray, float | None]:
    """Benjamini–Hochberg step-up at level ``alpha`` on the finite p-values (any shape; NaN = not tested).

    Returns the boolean rejections (same shape) and the p-value threshold (None: nothing rejected)."""
    p = np.asarray(p, float)
    ok = np.isfinite(p)
    v = np.sort(p[ok])
    m = v.size
    if not m:
        return np.zeros(p.shape, bool), None
    below = np.flatnonzero(v <= alpha * np.arange(1, m + 1) / m)
    if not below.size:
        return np.zeros(p.shape, bool), None
    thr = float(v[below[-1]])
    return ok & (np.where(ok, p, np.inf) <= thr), thr


def _box_mask(grid: Grid, box) -> np.ndarray:
    X, Y = grid.cell_centres(0, 0, grid.height, grid.width)
    return (X >= box[0]) & (X <= box[2]) & (Y >= box[1]) & (Y <= box[3])


def compare_rasters(a, sigma_a, b, sigma_b, grid: Grid, config: CompareConfig | None = None) -> Comparison:
    """``b − a`` with its σ and the significance of every cell, all on ``grid`` (``a``'s; ``b`` already moved there).

    Parameters
    ----------
    a, b : (H, W) values in one unit (NaN = no value)
    sigma_a, sigma_b : (H, W) random standard deviations of ``a`` and ``b`` (same unit), or scalars
    grid : the common grid (for ``config.offset_box``)
    config : :class:`CompareConfig`

    Raises
    ------
    ConfigError
        ``--offset-box`` covering no compared cell.
    """
    cfg = config or CompareConfig()
    a, b = np.asarray(a, float), np.asarray(b, float)
    sa = np.broadcast_to(np.asarray(sigma_a, float), a.shape)
    sb = np.broadcast_to(np.asarray(sigma_b, float), a.shape)
    d = b - a
    s = np.sqrt(sa**2 + sb**2)
    have = np.isfinite(d)
    tested = have & np.isfinite(s) & (s > 0)
    offset = {"removed": False, "method": "none", "value": 0.0, "cells": 0}
    if cfg.remove_offset == "median":
        area = tested if cfg.offset_box is None else tested & _box_mask(grid, cfg.offset_box)
        if not area.any():
            raise ConfigError(f"--offset-box {','.join(f'{v:.10g}' for v in cfg.offset_box)}: no compared cell has its "
                              f"centre in the box (the rasters cover X {grid.x0:.2f}..{grid.x0 + grid.width * grid.gsd:.2f}, "
                              f"Y {grid.y0 - grid.height * grid.gsd:.2f}..{grid.y0:.2f}); expected a box over unchanged "
                              "ground inside the overlap")
        off = float(np.median(d[area]))
        d = d - off
        offset = {"removed": True, "value": off, "cells": int(area.sum()),
                  "method": "median over the whole overlap" if cfg.offset_box is None else
                  f"median over the box {','.join(f'{v:.3f}' for v in cfg.offset_box)}"}
    z, p = z_test(np.where(tested, d, np.nan), np.where(tested, s, np.nan))
    thr = None
    if cfg.fdr:
        sig, thr = benjamini_hochberg(p, cfg.alpha)
    else:
        sig = tested & (np.where(tested, p, 1.0) < cfg.alpha)
    code = np.full(a.shape, NOT_COMPARED, np.uint8)
    code[tested] = sig[tested].astype(np.uint8)
    d_out, s_out = np.where(tested, d, np.nan), np.where(tested, s, np.nan)
    n = int(tested.sum())
    from scipy.special import ndtri

    summary = {
        "cells_compared": n, "cells_without_sigma": int((have & ~tested).sum()),
        "alpha": float(cfg.alpha), "two_sided": True, "z_critical": float(ndtri(1.0 - cfg.alpha / 2.0)),
        "fdr": bool(cfg.fdr), "fdr_p_threshold": thr,
        "significant_cells": int(sig.sum()),
        "share_significant": float(sig.sum() / n) if n else None,
        "share_significant_warmer": float((sig & (d_out > 0)).sum() / n) if n else None,
        "share_significant_colder": float((sig & (d_out < 0)).sum() / n) if n else None,
        "median_abs_z": float(np.median(np.abs(z[tested]))) if n else None,
        "offset": offset,
    }
    if n:
        dv, sv = d_out[tested], s_out[tested]
        summary.update(median=float(np.median(dv)), mean=float(dv.mean()), rmse=float(np.sqrt(np.mean(dv**2))),
                       p95_abs=float(np.percentile(np.abs(dv), 95)), sigma_median=float(np.median(sv)),
                       sigma_p95=float(np.percentile(sv, 95)))
    return Comparison(d_out, s_out, code, summary)


def reading_residuals(values, sigma, grid: Grid, xy, readings, reading_sigma=None) -> tuple[list[dict], dict]:
    """Contact readings against a raster: per point the value and σ of the cell containing it.

    Parameters
    ----------
    values, sigma : (H, W) raster and its random σ (same unit as the readings)
    grid : their grid
    xy : (M, 2) point positions (m, the raster's CRS); every point must lie on the grid (checked by the caller)
    readings : (M,) readings; ``reading_sigma`` (M,) their σ or None (0: taken as exact)

    Returns
    -------
    rows : per point ``value``, ``sigma``, ``residual`` (value − reading), ``sigma_total``, ``z`` (the normalised
        residual); None where the cell has no value (or no σ > 0 for ``z``)
    summary : ``n`` (points compared), ``rms``, ``median``, ``mean`` (of the residuals, unit), ``rms_z``,
        ``median_abs_z``, ``share_within_2sigma`` (|z| ≤ 2)
    """
    xy = np.asarray(xy, float).reshape(-1, 2)
    t = np.asarray(readings, float)
    sr = np.zeros(len(t)) if reading_sigma is None else np.asarray(reading_sigma, float)
    r, c = grid.cell_of(xy[:, 0], xy[:, 1])
    rows, res, zs = [], [], []
    for k in range(len(t)):
        v, s = float(values[r[k], c[k]]), float(sigma[r[k], c[k]])
        if not np.isfinite(v):
            rows.append({"value": None, "sigma": None, "residual": None, "sigma_total": None, "z": None})
            continue
        st = float(np.hypot(s, sr[k])) if np.isfinite(s) else None
        e = v - float(t[k])
        z = e / st if st is not None and st > 0 else None
        rows.append({"value": v, "sigma": s if np.isfinite(s) else None, "residual": e, "sigma_total": st, "z": z})
        res.append(e)
        if z is not None:
            zs.append(z)
    e, z = np.array(res), np.array(zs)
    summary = {"n": int(e.size), "not_on_a_value": int(len(t) - e.size),
               "rms": float(np.sqrt(np.mean(e**2))) if e.size else None,
               "median": float(np.median(e)) if e.size else None, "mean": float(e.mean()) if e.size else None,
               "rms_z": float(np.sqrt(np.mean(z**2))) if z.size else None,
               "median_abs_z": float(np.median(np.abs(z))) if z.size else None,
               "share_within_2sigma": float(np.mean(np.abs(z) <= 2.0)) if z.size else None}
    return rows, summary
