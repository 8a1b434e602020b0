"""The ``evaluate`` verb's driver: a DSM against a reference DSM and/or check points → ``evaluate.json`` (+ histogram).

The statistics are computed by :mod:`thermogrammetry.products.evaluate` on arrays; this module reads the files and
writes OUT as one output set (:class:`~thermogrammetry._atomic.OutputSet`).
"""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["run_evaluate"]


def run_evaluate(dsm, out, *, reference=None, checkpoints=None, ortho=None, max_cells: int | None = None) -> dict:
    """Evaluate ``dsm`` (GeoTIFF path) and write ``out/evaluate.json`` (and ``evaluate_histogram.png`` with a
    reference DSM); returns the ``evaluate.json`` dict.

    The DSM and the reference are checked before they are read (:func:`~thermogrammetry.products.raster.inspect_raster`:
    north-up, at most ``max_cells`` cells, finite heights, no infinite one); a comparison without any common cell or
    check point is refused with its reason (OUT not created)."""
    from .._atomic import OutputSet, write_atomic, write_atomic_text
    from ..errors import ConfigError, DataFileError
    from ..products.evaluate import checkpoint_errors, difference_stats, dsm_difference, read_checkpoints
    from ..io.testfield_csv import read_text
    from ..products.raster import read_raster

    checkpoints = None if checkpoints is None else Path(checkpoints)
    png = None
    if reference is None and checkpoints is None:
        raise ConfigError("nothing to evaluate against: give --reference REF.tif and/or --checkpoints cp.csv")
    from ..products.raster import inspect_raster, same_horizontal_crs

    info = inspect_raster(dsm, "DSM", max_cells=max_cells)
    info_r = inspect_raster(reference, "reference DSM", max_cells=max_cells) if reference is not None else None
    if info_r is not None and (info.crs is None) != (info_r.crs is None):
        raise DataFileError(f"{reference}: the reference DSM is in {info_r.crs or 'no CRS'}, the DSM {dsm} in "
                            f"{info.crs or 'no CRS'}; expected both in the same CRS")
    if info_r is not None and not same_horizontal_crs(info.crs, info_r.crs):
        raise DataFileError(f"{reference}: CRS {info_r.crs} differs from the DSM's {info.crs}; expected the same CRS")
    if ortho is not None:
        inspect_raster(ortho, "ortho", max_cells=max_cells)
    if checkpoints is not None:  # the one reader of the user's CSV files: UTF-8 (a BOM allowed), the file named
        text, source = read_text(checkpoints)
        pts = read_checkpoints(text, source)
    z, g, crs, _ = read_raster(dsm, max_cells=max_cells)
    rep: dict = {"dsm": str(dsm), "crs": crs, "dsm_vs_reference": None, "checkpoints": None}
    if reference is not None:
        zr, gr, crs_r, _ = read_raster(reference, max_cells=max_cells)
        diff = dsm_difference(z, g, zr, gr)
        rep["dsm_vs_reference"] = difference_stats(diff)
        rep["dsm_vs_reference"]["unit"] = "m"
        if not rep["dsm_vs_reference"]["n"]:
            raise DataFileError(f"{reference}: no cell of the DSM {dsm} has a height in both rasters (the reference "
                                f"covers X {gr.x0:.2f}..{gr.x0 + gr.width * gr.gsd:.2f}, the DSM X {g.x0:.2f}.."
                                f"{g.x0 + g.width * g.gsd:.2f} m); expected overlapping rasters of the same area")
    if checkpoints is not None:
        o = og = None
        if ortho is not None:
            o, og, _, _ = read_raster(ortho)
        rep["checkpoints"] = checkpoint_errors(pts, z, g, o, og)
        if not rep["checkpoints"]["n"]:
            raise DataFileError(f"{checkpoints}: none of the {len(pts)} check point(s) falls on a DSM cell with a height "
                                f"({dsm}); expected check points inside the DSM, in its CRS")
    h = (rep["dsm_vs_reference"] or {}).get("histogram")
    if h:
        import matplotlib

        matplotlib.use("Agg")
        import io

        import matplotlib.pyplot as plt

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
        png = buf.getvalue()
    with OutputSet(out, "evaluate") as stage:
        write_atomic_text(stage.path("evaluate.json"), json.dumps(rep, indent=1) + "\n")
        if png is not None:
            write_atomic(stage.path("evaluate_histogram.png"), png)
        stage.commit()
    return rep
