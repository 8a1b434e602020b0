"""``thermogrammetry evaluate --dsm DSM.tif [--reference REF.tif] [--checkpoints cp.csv] -o OUT`` (DSM mode) and
``thermogrammetry evaluate --ortho A/ortho.tif [--against B/ortho.tif | --reference REF.tif] [--readings r.csv] -o OUT``
(temperature mode)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .app import app, print_error, print_plain

_TEMPERATURE_ONLY = ("--against", "--reference-sigma", "--readings", "--readings-unit", "--alpha", "--fdr",
                     "--remove-offset", "--offset-box")


@app.command("evaluate")
def evaluate(
    out: Path = typer.Option(..., "-o", "--out", help="Output folder: evaluate.json (+ evaluate_histogram.png; in the "
                             "temperature mode difference.tif, difference_sigma.tif, significant.tif, readings.csv)."),
    dsm: Optional[Path] = typer.Option(None, "--dsm", help="DSM GeoTIFF to evaluate (DSM mode)."),
    reference: Optional[Path] = typer.Option(None, "--reference", help="With --dsm: reference DSM GeoTIFF in the same "
                                             "CRS. Without --dsm: a reference temperature raster, compared as "
                                             "ortho − reference (σ: --reference-sigma)."),
    checkpoints: Optional[Path] = typer.Option(None, "--checkpoints", help="cp.csv: id,X,Y,Z (m, the DSM's CRS)."),
    ortho: Optional[Path] = typer.Option(None, "--ortho", help="With --dsm: ortho.tif in which the check points' markers "
                                         "give ΔX, ΔY. Without --dsm: the ortho compared (temperature mode; its "
                                         "ortho_sigma.tif beside it)."),
    against: Optional[Path] = typer.Option(None, "--against", help="A second ortho.tif of the same surface (its "
                                           "ortho_sigma.tif beside it): difference = against − ortho on the ortho's grid."),
    reference_sigma: Optional[float] = typer.Option(None, "--reference-sigma", help="σ of the --reference temperature "
                                                    "raster, in the ortho's unit (default 0: taken as exact)."),
    readings: Optional[Path] = typer.Option(None, "--readings", help="Contact readings CSV, columns id (optional), X, Y "
                                            "(m, the ortho's CRS), Z (optional, not used), T and sT (optional) in "
                                            "--readings-unit."),
    readings_unit: Optional[str] = typer.Option(None, "--readings-unit", help="K or C: the unit of the readings "
                                                "(default: the ortho's)."),
    alpha: Optional[float] = typer.Option(None, "--alpha", help="Two-sided level of the per-cell test of the "
                                          "difference (default 0.05)."),
    fdr: bool = typer.Option(False, "--fdr", help="Benjamini–Hochberg false-discovery control at --alpha instead of "
                             "the per-cell level."),
    remove_offset: Optional[str] = typer.Option(None, "--remove-offset", help="none (default) or median: remove the "
                                                "median difference (over the overlap, or --offset-box) before the test."),
    offset_box: Optional[str] = typer.Option(None, "--offset-box", help="XMIN,YMIN,XMAX,YMAX (m, the CRS): unchanged "
                                             "ground where --remove-offset median takes its median."),
    max_cells: Optional[int] = typer.Option(None, "--max-cells", help="Cap on the cells of each raster read (default: "
                                            "sized for this machine's memory, or $THERMOGRAMMETRY_MAX_CELLS)."),
) -> None:
    """DSM against a reference DSM and check points (--dsm); or an ortho's temperatures against a second ortho, a
    reference raster or contact readings, with their σ and the significant differences (--ortho without --dsm)."""
    from rich.console import Console

    from ..errors import ConfigError, ThermogrammetryError

    console = Console(stderr=True)
    given = {"--against": against, "--reference-sigma": reference_sigma, "--readings": readings,
             "--readings-unit": readings_unit, "--alpha": alpha, "--fdr": fdr or None, "--remove-offset": remove_offset,
             "--offset-box": offset_box}
    try:
        if dsm is not None:
            extra = [k for k in _TEMPERATURE_ONLY if given[k] is not None]
            if extra:
                raise ConfigError(f"{', '.join(extra)}: options of the temperature mode (--ortho without --dsm); "
                                  "with --dsm evaluate compares a DSM")
            _dsm_mode(console, dsm, out, reference, checkpoints, ortho, max_cells)
            return
        if ortho is None:
            raise ConfigError("nothing to evaluate: give --dsm DSM.tif (a DSM against --reference/--checkpoints) or "
                              "--ortho ortho.tif (temperatures against --against/--reference/--readings)")
        if checkpoints is not None:
            raise ConfigError("--checkpoints: check points evaluate a DSM; give --dsm DSM.tif")
        _temperature_mode(console, ortho, out, against, reference, reference_sigma, readings, readings_unit, alpha,
                          fdr, remove_offset, offset_box, max_cells)
    except (ThermogrammetryError, OSError, ValueError) as exc:
        print_error(console, exc)
        raise typer.Exit(2)


def _dsm_mode(console, dsm, out, reference, checkpoints, ortho, max_cells) -> None:
    from ..pipeline.evaluate import run_evaluate

    rep = run_evaluate(dsm, out, reference=reference, checkpoints=checkpoints, ortho=ortho, max_cells=max_cells)
    if rep["dsm_vs_reference"] and rep["dsm_vs_reference"]["n"]:
        s = rep["dsm_vs_reference"]
        console.print(f"DSM − reference: n={s['n']} mean {s['mean']:+.3f} std {s['std']:.3f} RMSE {s['rmse']:.3f} "
                      f"MAE {s['mae']:.3f} p95|Δ| {s['p95_abs']:.3f} m", highlight=False)
    if rep["checkpoints"]:
        c = rep["checkpoints"]
        f = lambda v: "—" if v is None else f"{v:.3f}"  # noqa: E731
        console.print(f"check points: n={c['n']} RMSE X {f(c['rmse_x'])} Y {f(c['rmse_y'])} Z {f(c['rmse_z'])} m", highlight=False)
    print_plain(console, f"outputs in {out}: evaluate.json")


def _temperature_mode(console, ortho, out, against, reference, reference_sigma, readings, readings_unit, alpha, fdr,
                      remove_offset, offset_box, max_cells) -> None:
    from ..errors import ConfigError
    from ..pipeline.evaluate_temperature import run_evaluate_temperature
    from ..products.compare import CompareConfig

    box = None
    if offset_box is not None:
        try:
            box = tuple(float(v) for v in offset_box.split(","))
        except ValueError:
            raise ConfigError(f"--offset-box {offset_box!r}: expected four numbers XMIN,YMIN,XMAX,YMAX (m)") from None
        if len(box) != 4:
            raise ConfigError(f"--offset-box {offset_box!r}: {len(box)} number(s); expected XMIN,YMIN,XMAX,YMAX (m)")
    if reference_sigma is not None and reference is None:
        raise ConfigError("--reference-sigma: the σ of a --reference raster; give --reference REF.tif (the σ of an "
                          "--against ortho is its ortho_sigma.tif)")
    if readings_unit is not None and readings is None:
        raise ConfigError("--readings-unit: the unit of --readings; give --readings readings.csv")
    if (against is None and reference is None) and (alpha is not None or fdr or remove_offset or box):
        raise ConfigError("--alpha, --fdr, --remove-offset, --offset-box: options of a comparison of two rasters; "
                          "give --against or --reference")
    cfg = CompareConfig(alpha=0.05 if alpha is None else alpha, fdr=fdr, remove_offset=remove_offset or "none",
                        offset_box=box)
    rep = run_evaluate_temperature(ortho, out, against=against, reference=reference,
                                   reference_sigma=0.0 if reference_sigma is None else reference_sigma,
                                   readings=readings, readings_unit=readings_unit, config=cfg, max_cells=max_cells)
    u = rep["unit"]
    files = ["evaluate.json"]
    c = rep["comparison"]
    if c:
        files[:0] = ["difference.tif", "difference_sigma.tif", "significant.tif"]
        off = f", offset {c['offset']['value']:+.3f} {u} removed" if c["offset"]["removed"] else ""
        print_plain(console, f"{c['definition']}: {c['cells_compared']} cells, median {c['median']:+.3f} {u}, median "
                             f"σ {c['sigma_median']:.3f} {u}, median |d|/σ {c['median_abs_z']:.2f}; significant at "
                             f"{c['alpha']:g}{' (FDR)' if c['fdr'] else ''}: {100 * c['share_significant']:.1f} % of the "
                             f"cells{off}")
    r = rep["readings"]
    if r:
        files.insert(-1, "readings.csv")
        w2 = "—" if r["share_within_2sigma"] is None else f"{100 * r['share_within_2sigma']:.0f} %"
        print_plain(console, f"readings: {r['n']} of {r['points']} points, ortho − reading RMS {r['rms']:.3f} {u}, "
                             f"median {r['median']:+.3f} {u}, within 2σ {w2}")
    print_plain(console, f"outputs in {out}: {', '.join(files)}")
