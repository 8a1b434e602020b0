"""Accuracy of the products: DSM against a reference DSM and against check points; ortho against check points.

- :func:`dsm_difference` — DSM − reference at the DSM's cell centres (reference sampled bilinearly), with
  the statistics and histogram of seed 003's Fig. 9 (n, mean, std, RMSE, MAE, 95th percentile of |Δ|).
- :func:`checkpoint_errors` — per check point: ΔZ = DSM(X, Y) − Z; with an orthophoto, ΔX and ΔY = the
  centroid of the marker seen in the ortho around (X, Y) − (X, Y) (square targets that contrast with their
  surroundings, as GCP foil), hence per-axis RMSE.

References
----------
Khodaei et al. (seed 003): DSM vs reference DSM (difference histogram, Fig. 9) and check points.
"""

from __future__ import annotations

import csv
import io

import numpy as np

from ..errors import DataFileError
from .raster import Grid

__all__ = ["dsm_difference", "difference_stats", "sample_bilinear", "read_checkpoints", "checkpoint_errors",
           "marker_centroid"]


def sample_bilinear(a, grid: Grid, x, y) -> np.ndarray:
    """Bilinear value of raster ``a`` on ``grid`` at world (x, y); NaN outside or next to no data."""
    from .ortho import bilinear

    r = (grid.y0 - np.asarray(y, float)) / grid.gsd - 0.5
    c = (np.asarray(x, float) - grid.x0) / grid.gsd - 0.5
    return bilinear(np.asarray(a, float), r, c)


def difference_stats(diff, bins: int = 41, half_range: float | None = None) -> dict:
    """n, mean, std, rmse, mae, p95_abs of the finite values (m) and a histogram (edges, counts)."""
    d = np.asarray(diff, float)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return {"n": 0, "mean": None, "std": None, "rmse": None, "mae": None, "p95_abs": None, "histogram": None}
    hr = half_range if half_range is not None else max(float(np.percentile(np.abs(d), 99)), 1e-6)
    counts, edges = np.histogram(np.clip(d, -hr, hr), bins=bins, range=(-hr, hr))
    return {"n": int(d.size), "mean": float(d.mean()), "std": float(d.std(ddof=1)) if d.size > 1 else 0.0,
            "rmse": float(np.sqrt(np.mean(d**2))), "mae": float(np.mean(np.abs(d))),
            "p95_abs": float(np.percentile(np.abs(d), 95)),
            "histogram": {"edges": [float(e) for e in edges], "counts": [int(c) for c in counts],
                          "note": "values beyond the range are counted in the outer bins"}}


def dsm_difference(dsm, grid: Grid, reference, ref_grid: Grid) -> np.ndarray:
    """(H, W) DSM − reference (m) at the DSM's cell centres."""
    X, Y = grid.cell_centres(0, 0, grid.height, grid.width)
    return np.asarray(dsm, float) - sample_bilinear(reference, ref_grid, X, Y)


def read_checkpoints(text: str, source: str) -> list[tuple[str, float, float, float]]:
    """Check points from CSV ``id,X,Y,Z`` (also ``name``, ``E/N/H``, ``easting/northing/height``), metres."""
    rows = list(csv.reader(io.StringIO(text)))
    rows = [r for r in rows if r and not r[0].lstrip().startswith("#")]
    if not rows:
        raise DataFileError(f"{source}: empty; expected a CSV with columns id,X,Y,Z")
    head = [h.strip().lower() for h in rows[0]]
    alias = {"id": ("id", "name", "point"), "x": ("x", "e", "easting"), "y": ("y", "n", "northing"),
             "z": ("z", "h", "height", "elevation")}
    col = {}
    for k, names in alias.items():
        hit = [i for i, h in enumerate(head) if h in names]
        if not hit:
            raise DataFileError(f"{source}: header {rows[0]} has no {k!r} column; expected id,X,Y,Z "
                                f"(or name/E/N/H, easting/northing/height)")
        col[k] = hit[0]
    out = []
    for ln, r in enumerate(rows[1:], start=2):
        try:
            out.append((r[col["id"]].strip(), float(r[col["x"]]), float(r[col["y"]]), float(r[col["z"]])))
        except (ValueError, IndexError):
            raise DataFileError(f"{source}: line {ln}: {r!r}; expected id and three numbers X,Y,Z (m)") from None
        bad = [(k, r[col[k]].strip()) for k in ("x", "y", "z") if not np.isfinite(out[-1][1 + "xyz".index(k)])]
        if bad:
            raise DataFileError(f"{source}: line {ln}: {bad[0][0].upper()} = {bad[0][1]!r} is not finite; expected "
                                "finite coordinates X,Y,Z (m)")
    return out


def marker_centroid(ortho, grid: Grid, x, y, *, radius_m: float = 2.0) -> tuple[float, float] | None:
    """Centroid (m) of the contrasting blob nearest to (x, y) in the ortho, within ``radius_m``; None if unclear."""
    from scipy import ndimage

    r0, c0 = grid.cell_of(x, y)
    k = int(np.ceil(radius_m / grid.gsd))
    ra, rb, ca, cb = max(0, r0 - k), min(grid.height, r0 + k + 1), max(0, c0 - k), min(grid.width, c0 + k + 1)
    if ra >= rb or ca >= cb:
        return None
    win = np.asarray(ortho, float)[ra:rb, ca:cb]
    if np.isfinite(win).mean() < 0.8:
        return None
    med = np.nanmedian(win)
    dev = np.abs(win - med)
    thr = 0.5 * np.nanmax(dev)
    lab, n = ndimage.label(np.nan_to_num(dev) > thr)
    if n == 0:
        return None
    yy, xx = np.mgrid[ra:rb, ca:cb]
    cx = grid.x0 + (xx + 0.5) * grid.gsd
    cy = grid.y0 - (yy + 0.5) * grid.gsd
    best, bd = None, np.inf
    for i in range(1, n + 1):
        m = lab == i
        if m.sum() < 4:
            continue
        px, py = cx[m].mean(), cy[m].mean()
        d = np.hypot(px - x, py - y)
        if d < bd:
            best, bd = (float(px), float(py)), d
    return best


def checkpoint_errors(points, dsm, grid: Grid, ortho=None, ortho_grid: Grid | None = None) -> dict:
    """Per-point errors and per-axis RMSE (m). ``rmse_x``/``rmse_y`` need the ortho (else None)."""
    rows = []
    for name, x, y, z in points:
        dz = float(sample_bilinear(dsm, grid, np.array([x]), np.array([y]))[0]) - z
        dx = dy = None
        if ortho is not None:
            c = marker_centroid(ortho, ortho_grid or grid, x, y)
            if c is not None:
                dx, dy = c[0] - x, c[1] - y
        rows.append({"id": name, "dx": dx, "dy": dy, "dz": dz if np.isfinite(dz) else None})

    def rmse(key):
        v = np.array([r[key] for r in rows if r[key] is not None], float)
        return float(np.sqrt(np.mean(v**2))) if v.size else None

    n = sum(r["dz"] is not None for r in rows)
    return {"n": n, "rmse_x": rmse("dx"), "rmse_y": rmse("dy"), "rmse_z": rmse("dz"), "points": rows,
            "note": "dz = DSM(X, Y) - Z; dx, dy = marker centroid in the ortho - (X, Y) (only with an ortho)"}
