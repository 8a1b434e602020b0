"""``thermogrammetry evaluate --dsm DSM.tif [--reference REF.tif] [--checkpoints cp.csv] -o OUT``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from .app import app


@app.command("evaluate")
def evaluate(
    dsm: Path = typer.Option(..., "--dsm", help="DSM GeoTIFF to evaluate."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder: evaluate.json (+ evaluate_histogram.png)."),
    reference: Optional[Path] = typer.Option(None, "--reference", help="Reference DSM GeoTIFF in the same CRS."),
    checkpoints: Optional[Path] = typer.Option(None, "--checkpoints", help="cp.csv: id,X,Y,Z (m, the DSM's CRS)."),
    ortho: Optional[Path] = typer.Option(None, "--ortho", help="ortho.tif: check-point markers located in it give ΔX, ΔY."),
) -> None:
    """DSM against a reference DSM (difference statistics and histogram) and against check points (per axis)."""
    from rich.console import Console

    from .._atomic import write_atomic_text
    from ..errors import ConfigError, DataFileError, ThermogrammetryError
    from ..products.evaluate import checkpoint_errors, difference_stats, dsm_difference, read_checkpoints
    from ..products.raster import read_raster

    console = Console(stderr=True)
    try:
        if reference is None and checkpoints is None:
            raise ConfigError("nothing to evaluate against: give --reference REF.tif and/or --checkpoints cp.csv")
        from ..products.raster import same_horizontal_crs

        z, g, crs, _ = read_raster(dsm)
        rep: dict = {"dsm": str(dsm), "crs": crs, "dsm_vs_reference": None, "checkpoints": None}
        if reference is not None:
            zr, gr, crs_r, _ = read_raster(reference)
            if not same_horizontal_crs(crs, crs_r):
                raise DataFileError(f"{reference}: CRS {crs_r} differs from the DSM's {crs}; expected the same CRS")
            diff = dsm_difference(z, g, zr, gr)
            rep["dsm_vs_reference"] = difference_stats(diff)
            rep["dsm_vs_reference"]["unit"] = "m"
        if checkpoints is not None:
            try:
                text = checkpoints.read_text(encoding="utf-8")
            except OSError as exc:
                raise DataFileError(f"{checkpoints}: cannot read ({exc.strerror or exc})") from None
            pts = read_checkpoints(text, str(checkpoints))
            o = og = None
            if ortho is not None:
                o, og, _, _ = read_raster(ortho)
            rep["checkpoints"] = checkpoint_errors(pts, z, g, o, og)
        write_atomic_text(out / "evaluate.json", json.dumps(rep, indent=1) + "\n")
        h = (rep["dsm_vs_reference"] or {}).get("histogram")
        if h:
            import matplotlib

            matplotlib.use("Agg")
            import io

            import matplotlib.pyplot as plt

            from .._atomic import write_atomic

            fig, ax = plt.subplots(figsize=(6, 3.5))
            e = h["edges"]
            ax.bar(e[:-1], h["counts"], width=e[1] - e[0], align="edge")
            s = rep["dsm_vs_reference"]
            ax.set_xlabel("DSM − reference (m)")
            ax.set_ylabel("cells")
            ax.set_title(f"n={s['n']} mean={s['mean']:.3f} RMSE={s['rmse']:.3f} m")
            buf = io.BytesIO()
            fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
            plt.close(fig)
            write_atomic(out / "evaluate_histogram.png", buf.getvalue())
    except (ThermogrammetryError, OSError, ValueError) as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
        raise typer.Exit(2)
    if rep["dsm_vs_reference"] and rep["dsm_vs_reference"]["n"]:
        s = rep["dsm_vs_reference"]
        console.print(f"DSM − reference: n={s['n']} mean {s['mean']:+.3f} std {s['std']:.3f} RMSE {s['rmse']:.3f} "
                      f"MAE {s['mae']:.3f} p95|Δ| {s['p95_abs']:.3f} m", highlight=False)
    if rep["checkpoints"]:
        c = rep["checkpoints"]
        f = lambda v: "—" if v is None else f"{v:.3f}"  # noqa: E731
        console.print(f"check points: n={c['n']} RMSE X {f(c['rmse_x'])} Y {f(c['rmse_y'])} Z {f(c['rmse_z'])} m", highlight=False)
    console.print(f"outputs in {out}: evaluate.json", highlight=False)
