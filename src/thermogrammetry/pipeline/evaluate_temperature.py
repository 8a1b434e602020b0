"""The ``evaluate`` verb's temperature mode: an orthophoto against a second orthophoto, a reference temperature
raster or contact readings, with the standard deviations of ``ortho_sigma.tif``.

Reads and checks every input before writing anything (:func:`run_evaluate_temperature`), computes with
:mod:`thermogrammetry.products.compare` and writes OUT as one output set: ``difference.tif``,
``difference_sigma.tif``, ``significant.tif`` (with ``--against`` or ``--reference``), ``readings.csv`` (with
``--readings``) and ``evaluate.json``.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["run_evaluate_temperature", "sigma_path", "normalise_unit"]

_UNITS = {"k": "K", "kelvin": "K", "°c": "°C", "degc": "°C", "deg c": "°C", "c": "°C", "celsius": "°C",
          "counts": "counts", "dn": "dn"}


def normalise_unit(u: str | None) -> str | None:
    """``K``, ``°C``, ``counts``, ``dn`` from a raster's unit tag (``kelvin``, ``degC``, ``celsius`` accepted); other
    tags as given; None when there is none."""
    if u is None or not str(u).strip():
        return None
    return _UNITS.get(str(u).strip().lower(), str(u).strip())


def sigma_path(ortho) -> Path:
    """Where the σ raster of ``ortho`` is: ``<stem>_sigma.tif`` beside it (``ortho.tif`` → ``ortho_sigma.tif``)."""
    p = Path(ortho)
    return p.with_name(p.stem + "_sigma" + p.suffix)


@dataclass
class _Raster:
    path: Path
    values: np.ndarray
    grid: object
    crs: str | None
    unit: str | None
    tags: dict


def _read(path, what: str, max_cells) -> _Raster:
    """A raster's band 1 with its grid, CRS and unit, checked: exists, readable, north-up, under the cell cap, some value."""
    from ..errors import DataFileError
    from ..products.raster import read_raster

    p = Path(path)
    if not p.is_file():
        raise DataFileError(f"{what} {p}: no such file" + ("" if not p.is_dir() else " (a folder; expected a GeoTIFF)"))
    a, g, crs, tags = read_raster(p, max_cells=max_cells)
    if not np.isfinite(a).any():
        raise DataFileError(f"{p}: the {what} has no value (all {g.width * g.height} cells are nodata or NaN); "
                            "expected a raster of temperatures (or counts)")
    if np.isinf(a).any():
        raise DataFileError(f"{p}: the {what} holds {int(np.isinf(a).sum())} infinite value(s); expected finite values "
                            "(NaN or nodata where there is none)")
    return _Raster(p, a, g, crs, normalise_unit(tags.get("unit")), tags)


def _read_sigma(ortho: _Raster, what: str, max_cells) -> _Raster:
    from ..errors import DataFileError

    sp = sigma_path(ortho.path)
    if not sp.is_file():
        raise DataFileError(f"{ortho.path}: no {sp.name} beside the {what} ({sp}); expected the σ raster that "
                            f"'thermogrammetry ortho' writes beside ortho.tif (run ortho again to get it), or, for a "
                            "raster without one, compare it as --reference with a stated --reference-sigma")
    s = _read(sp, f"{what}'s σ raster", max_cells)
    if (s.grid.x0, s.grid.y0, s.grid.gsd, s.grid.width, s.grid.height) != (
            ortho.grid.x0, ortho.grid.y0, ortho.grid.gsd, ortho.grid.width, ortho.grid.height):
        raise DataFileError(f"{sp}: its grid ({s.grid.width} x {s.grid.height} cells of {s.grid.gsd:g} m from "
                            f"{s.grid.x0:.3f}, {s.grid.y0:.3f}) differs from {ortho.path}'s ({ortho.grid.width} x "
                            f"{ortho.grid.height} of {ortho.grid.gsd:g} m from {ortho.grid.x0:.3f}, {ortho.grid.y0:.3f}); "
                            "expected the pair written by one ortho run")
    if s.unit is not None and ortho.unit is not None and s.unit != ortho.unit:
        raise DataFileError(f"{sp}: σ in {s.unit!r}, {ortho.path} in {ortho.unit!r}; expected the pair written by one "
                            "ortho run (one unit)")
    if (s.values < 0).any():
        raise DataFileError(f"{sp}: {int((s.values < 0).sum())} negative standard deviation(s); expected σ >= 0")
    return s


def _check_temperature_raster(r: _Raster, what: str, *, need_unit: bool) -> None:
    from ..errors import DataFileError

    if r.unit is None and need_unit:
        raise DataFileError(f"{r.path}: the {what} has no unit tag; expected an ortho.tif of 'thermogrammetry ortho' "
                            "(unit K, °C or counts)")
    if r.unit == "dn":
        raise DataFileError(f"{r.path}: the {what} holds display numbers (unit 'dn', an 8-bit rendering stretched per "
                            "frame), not temperatures or counts; expected an ortho of temperature (K, °C) or count frames")


def _same_crs(a: _Raster, b: _Raster, what_b: str) -> None:
    from ..errors import DataFileError
    from ..products.raster import same_horizontal_crs

    if (a.crs is None) != (b.crs is None) or not same_horizontal_crs(a.crs, b.crs):
        raise DataFileError(f"{b.path}: the {what_b} is in {b.crs or 'no CRS'}, the ortho {a.path} in "
                            f"{a.crs or 'no CRS'}; expected both in the same CRS")


def _extent(g) -> str:
    return f"X {g.x0:.2f}..{g.x0 + g.width * g.gsd:.2f}, Y {g.y0 - g.height * g.gsd:.2f}..{g.y0:.2f}"


def run_evaluate_temperature(ortho, out, *, against=None, reference=None, reference_sigma: float = 0.0,
                             readings=None, readings_unit: str | None = None, config=None,
                             max_cells: int | None = None) -> dict:
    """Compare the orthophoto ``ortho`` (GeoTIFF with its ``ortho_sigma.tif`` beside it) and write OUT.

    Parameters
    ----------
    ortho : A, the ortho compared (its grid is the grid of the outputs)
    against : B, a second ortho with its ``ortho_sigma.tif``: the difference is B − A
    reference : a reference temperature raster (σ ``reference_sigma``, in the ortho's unit): ortho − reference
    readings : CSV of contact readings ``[id,]X,Y[,Z],T[,sT]`` (:func:`~thermogrammetry.io.testfield_csv.parse_readings_csv`)
        in ``readings_unit`` (``K`` or ``C``; default the ortho's unit)
    config : :class:`~thermogrammetry.products.compare.CompareConfig` (level, FDR, offset removal)

    Returns the ``evaluate.json`` dict. Every input is checked before OUT is created (a refused comparison leaves
    nothing behind): units (a different unit on the two sides is refused, display numbers always), CRS, the σ
    rasters beside the orthos, the overlap, readings inside the ortho.
    """
    from .._atomic import OutputSet, check_output_apart, write_atomic_text
    from ..errors import ConfigError, DataFileError
    from ..products.compare import CompareConfig, compare_rasters, onto_grid, reading_residuals

    cfg = config or CompareConfig()
    if against is not None and reference is not None:
        raise ConfigError("--against and --reference: give one (a second ortho, or a reference temperature raster)")
    if against is None and reference is None and readings is None:
        raise ConfigError("nothing to compare the ortho with: give --against B/ortho.tif, --reference REF.tif and/or "
                          "--readings readings.csv")
    if not (np.isfinite(reference_sigma) and reference_sigma >= 0):
        raise ConfigError(f"--reference-sigma {reference_sigma!r}: expected a standard deviation >= 0 in the ortho's unit")
    check_output_apart(out, [(w, p) for w, p in (("ortho's folder", ortho), ("--against ortho's folder", against),
                                                  ("--reference's folder", reference), ("--readings' folder", readings))
                             if p is not None])
    a = _read(ortho, "ortho", max_cells)
    _check_temperature_raster(a, "ortho", need_unit=True)
    sa = _read_sigma(a, "ortho", max_cells)
    rep: dict = {"mode": "temperature", "ortho": str(a.path), "ortho_sigma": str(sa.path), "unit": a.unit,
                 "crs": a.crs, "comparison": None, "readings": None}
    cmp_ = None
    if against is not None or reference is not None:
        if against is not None:
            b = _read(against, "--against ortho", max_cells)
            _check_temperature_raster(b, "--against ortho", need_unit=True)
            sb = _read_sigma(b, "--against ortho", max_cells)
            kind, unit_note = "ortho", None
        else:
            b = _read(reference, "reference raster", max_cells)
            _check_temperature_raster(b, "reference raster", need_unit=False)
            sb = None
            kind = "reference"
            unit_note = None if b.unit is not None else f"the reference has no unit tag: taken as {a.unit}"
        if b.unit is not None and b.unit != a.unit:
            raise DataFileError(f"{b.path} is in {b.unit!r}, {a.path} in {a.unit!r}: values of different units are not "
                                "compared; expected both in one unit (ortho --unit K or --unit C for both flights; "
                                "counts only with counts)")
        _same_crs(a, b, "--against ortho" if kind == "ortho" else "reference raster")
        bx0, bx1 = b.grid.x0, b.grid.x0 + b.grid.width * b.grid.gsd
        by0, by1 = b.grid.y0 - b.grid.height * b.grid.gsd, b.grid.y0
        ax0, ax1 = a.grid.x0, a.grid.x0 + a.grid.width * a.grid.gsd
        ay0, ay1 = a.grid.y0 - a.grid.height * a.grid.gsd, a.grid.y0
        if bx0 >= ax1 or bx1 <= ax0 or by0 >= ay1 or by1 <= ay0:
            raise DataFileError(f"{b.path} ({_extent(b.grid)}) does not overlap {a.path} ({_extent(a.grid)}); expected "
                                "two rasters of the same area in one CRS")
        s_b = sb.values if sb is not None else np.where(np.isfinite(b.values), float(reference_sigma), np.nan)
        bv, bs, method = onto_grid(b.values, s_b, b.grid, a.grid)
        if kind == "ortho":
            cmp_ = compare_rasters(a.values, sa.values, bv, bs, a.grid, cfg)
        else:  # the ortho's error: ortho − reference
            cmp_ = compare_rasters(bv, bs, a.values, sa.values, a.grid, cfg)
        if not cmp_.summary["cells_compared"]:
            raise DataFileError(f"{b.path}: no cell of {a.path} has a value and a σ in both rasters (overlap of the "
                                f"grids: {_extent(a.grid)} and {_extent(b.grid)}); expected rasters with values over a "
                                "common area")
        rep["comparison"] = {
            "kind": kind, "against" if kind == "ortho" else "reference": str(b.path),
            "against_sigma" if kind == "ortho" else "reference_sigma": str(sb.path) if sb is not None else float(reference_sigma),
            "definition": "against − ortho (B − A)" if kind == "ortho" else "ortho − reference",
            "resampling": method, **({"unit_note": unit_note} if unit_note else {}), **cmp_.summary,
            "systematic": {"ortho": sa.tags.get("systematic", "unknown"),
                           "against" if kind == "ortho" else "reference":
                               sb.tags.get("systematic", "unknown") if sb is not None else "not stated",
                           "note": "the systematic parts (each flight's radiometric calibration, common to a frame or "
                                   "a flight) are not in difference_sigma; a common offset between the two is removed "
                                   "with --remove-offset median (see the offset entry)"}}
    rows = None
    if readings is not None:
        from ..io.testfield_csv import read_readings_csv

        if a.unit == "counts":
            raise DataFileError(f"{a.path}: the ortho holds raw sensor counts; contact readings ({readings}) are "
                                "temperatures; expected an ortho in K or °C")
        ru = a.unit if readings_unit is None else {"K": "K", "C": "°C"}.get(str(readings_unit).strip().upper().lstrip("°"))
        if ru is None or (ru != a.unit and a.unit not in ("K", "°C")):
            raise ConfigError(f"--readings-unit {readings_unit!r}: expected K or C (the ortho {a.path} is in {a.unit!r})")
        rd = read_readings_csv(readings)
        t = rd.value + (0.0 if ru == a.unit else (273.15 if a.unit == "K" else -273.15))
        r, c = a.grid.cell_of(rd.xy[:, 0], rd.xy[:, 1])
        out_pts = np.flatnonzero((r < 0) | (c < 0) | (r >= a.grid.height) | (c >= a.grid.width))
        if out_pts.size:
            k = int(out_pts[0])
            raise DataFileError(f"{rd.source}, row {rd.lines[k]}: point {rd.ids[k]!r} at X {rd.xy[k, 0]:.3f}, Y "
                                f"{rd.xy[k, 1]:.3f} lies outside the ortho {a.path} ({_extent(a.grid)})"
                                + (f" ({out_pts.size} of the {len(rd.ids)} points do)" if out_pts.size > 1 else "")
                                + "; expected readings inside the ortho, in its CRS")
        rows, summ = reading_residuals(a.values, sa.values, a.grid, rd.xy, t, rd.std)
        if not summ["n"]:
            raise DataFileError(f"{rd.source}: none of the {len(rd.ids)} reading(s) falls on an ortho cell with a value "
                                f"({a.path}); expected readings on the mapped surface")
        for k, row in enumerate(rows):
            row.update(id=rd.ids[k], x=float(rd.xy[k, 0]), y=float(rd.xy[k, 1]), reading=float(t[k]),
                       reading_sigma=float(rd.std[k]) if rd.std is not None else 0.0)
        rep["readings"] = {"file": str(rd.source), "readings_unit": ru, "converted_to": a.unit if ru != a.unit else None,
                           "points": len(rd.ids), **summ,
                           "note": "value = the ortho cell containing the point; z = (value − reading) / "
                                   "√(σ_ortho² + σ_reading²); Z is not used"}
    with OutputSet(out, "evaluate") as stage:
        if cmp_ is not None:
            _write_rasters(stage, a, cmp_, rep["comparison"])
        if rows is not None:
            write_atomic_text(stage.path("readings.csv"), _readings_csv(rows))
        write_atomic_text(stage.path("evaluate.json"), json.dumps(rep, indent=1) + "\n")
        stage.commit()
    return rep


def _write_rasters(stage, a: _Raster, cmp_, summary: dict) -> None:
    from ..products.compare import NOT_COMPARED
    from ..products.raster import RasterSpec, write_cogs

    g = a.grid
    tags = {"product": "thermogrammetry evaluate", "definition": summary["definition"],
            "offset_removed": summary["offset"]["value"], "alpha": summary["alpha"], "fdr": summary["fdr"]}
    specs = {"d": RasterSpec(stage.path("difference.tif"), np.float32, nodata=float("nan"), unit=a.unit,
                             description=f"difference {summary['definition']}", tags={**tags, "unit": a.unit}),
             "s": RasterSpec(stage.path("difference_sigma.tif"), np.float32, nodata=float("nan"), unit=a.unit,
                             description="random standard deviation of the difference",
                             tags={**tags, "unit": a.unit, "systematic": "not included"}),
             "m": RasterSpec(stage.path("significant.tif"), np.uint8, nodata=NOT_COMPARED,
                             description=f"difference significant at {summary['alpha']:g}"
                                         + (" (Benjamini-Hochberg FDR)" if summary["fdr"] else " (per cell, two-sided)"),
                             tags=tags, resampling="nearest")}

    def tile(r0, c0, rows, cols):
        w = (slice(r0, r0 + rows), slice(c0, c0 + cols))
        return {"d": cmp_.difference[w], "s": cmp_.sigma[w], "m": cmp_.significant[w]}

    write_cogs(g, specs, tile, crs=a.crs)


def _readings_csv(rows) -> str:
    """``readings.csv``: coordinates to the millimetre, values and residuals to 4 decimals, σ and z to 6 digits."""
    fmt = {"x": "{:.3f}", "y": "{:.3f}", "reading": "{:.4f}", "value": "{:.4f}", "residual": "{:.4f}",
           "reading_sigma": "{:.6g}", "sigma": "{:.6g}", "sigma_total": "{:.6g}", "z": "{:.6g}"}
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    keys = ["id", "x", "y", "reading", "reading_sigma", "value", "sigma", "residual", "sigma_total", "z"]
    w.writerow(keys)
    for r in rows:
        w.writerow(["" if r[k] is None else fmt[k].format(r[k]) if k in fmt else r[k] for k in keys])
    return buf.getvalue()
