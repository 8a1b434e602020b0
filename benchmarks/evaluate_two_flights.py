"""Benchmark: ``evaluate --ortho A --against B`` on pairs of synthetic flights of one scene, a roof warmed by 0.5 K
between them (tests/two_flights.py): the share of the roof found significant and of the unchanged ground flagged,
per cell at the 5 % level and with the Benjamini–Hochberg control; the figure of one pair.

Each pair: two flights of 5 frames over the same scene (true poses drawn with their stated σ, 5 mm / 0.005°, and
white sensor noise of 0.05 K, independent per flight), building 0's roof 0.5 K warmer in the second flight's surface
temperature, ``ortho`` with ``ortho_sigma.tif`` on the true DSM for each, then the temperature mode of ``evaluate``.

Usage::

    python benchmarks/evaluate_two_flights.py [--pairs 10] [--figure docs/images/evaluate_two_flights.png] [--dir DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from two_flights import cell_classes, two_flights  # noqa: E402


def _read(p):
    import rasterio

    with rasterio.open(p) as s:
        return s.read(1)


def evaluate_pair(f: dict, pair: dict) -> dict:
    """Both modes (per cell at 5 %, Benjamini–Hochberg at 5 %) on one pair; the shares on the roof and the ground."""
    from thermogrammetry.pipeline.evaluate_temperature import run_evaluate_temperature
    from thermogrammetry.products.compare import CompareConfig

    roof, unch = cell_classes(f["scene"], pair["A"])
    row = {"netd_k": pair["netd"]}
    for name, cfg in (("per_cell", CompareConfig()), ("fdr", CompareConfig(fdr=True))):
        out = pair["dir"] / f"E_{name}"
        rep = run_evaluate_temperature(pair["A"], out, against=pair["B"], config=cfg)
        sig = _read(out / "significant.tif")
        d = _read(out / "difference.tif")
        s = _read(out / "difference_sigma.tif")
        ok = sig != 255
        flagged = sig == 1
        row[name] = {"roof_share": float(flagged[roof & ok].mean()), "unchanged_share": float(flagged[unch & ok].mean()),
                     "false_share_among_flagged": float((flagged & unch).sum() / max(flagged.sum(), 1)),
                     "roof_median_k": float(np.median(d[roof & ok])),
                     "unchanged_median_abs_z": float(np.median(np.abs(d[unch & ok] / s[unch & ok]))),
                     "cells": {"compared": int(ok.sum()), "roof": int((roof & ok).sum()), "unchanged": int((unch & ok).sum())},
                     "summary_share_significant": rep["comparison"]["share_significant"],
                     "unchanged_flagged": int(flagged[unch & ok].sum())}
    return row


def figure(root: Path, path: Path, scene) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.stats import norm

    a = _read(root / "oA" / "ortho.tif")
    d = _read(root / "E_per_cell" / "difference.tif")
    s = _read(root / "E_per_cell" / "difference_sigma.tif")
    sig = _read(root / "E_per_cell" / "significant.tif").astype(float)
    sig[sig == 255] = np.nan
    roof, unch = cell_classes(scene, root / "oA" / "ortho.tif")
    rr, cc = np.nonzero(np.isfinite(a))
    win = (slice(rr.min(), rr.max() + 1), slice(cc.min(), cc.max() + 1))
    a, d, s, sig, roof_w = a[win], d[win], s[win], sig[win], roof[win]
    fig, ax = plt.subplots(1, 5, figsize=(22, 4.2))
    for k, (img, title, kw) in enumerate([
            (a, "flight A ortho (K)", dict(cmap="inferno")),
            (d, "B − A (K)", dict(cmap="RdBu_r", vmin=-1, vmax=1)),
            (s, "σ of B − A (K)", dict(cmap="viridis", vmin=0, vmax=0.4)),
            (sig, "significant at 5 % per cell (yellow)", dict(cmap="cividis", vmin=0, vmax=1))]):
        im = ax[k].imshow(img, **kw)
        ax[k].contour(roof_w.astype(float), [0.5], colors="c" if k != 1 else "k", linewidths=0.6)
        ax[k].set_title(title)
        ax[k].set_xticks([])
        ax[k].set_yticks([])
        if k < 3:
            fig.colorbar(im, ax=ax[k], fraction=0.046)
    ok = np.isfinite(d) & np.isfinite(s)
    z = d[ok & unch[win]] / s[ok & unch[win]]
    zz = np.linspace(-5, 5, 201)
    ax[4].hist(np.clip(z, -5, 5), bins=80, range=(-5, 5), density=True, alpha=0.7, label="unchanged ground")
    ax[4].plot(zz, norm.pdf(zz), "k", lw=1, label="N(0, 1)")
    ax[4].axvline(-1.96, color="r", lw=0.8)
    ax[4].axvline(1.96, color="r", lw=0.8)
    ax[4].set_title(f"(B − A)/σ, unchanged ground: {100 * np.mean(np.abs(z) > 1.96):.1f} % beyond ±1.96", fontsize=10)
    ax[4].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=10)
    ap.add_argument("--figure", default=None, help="PNG of the first pair")
    ap.add_argument("--dir", default=None)
    a = ap.parse_args(argv)
    root = Path(a.dir or tempfile.mkdtemp(prefix="two_flights_"))
    f = two_flights(root, pairs=a.pairs)
    rows = [evaluate_pair(f, p) for p in f["pairs"]]
    if a.figure:
        figure(f["pairs"][0]["dir"], Path(a.figure), f["scene"])

    def stat(mode, key):
        v = np.array([r[mode][key] for r in rows])
        return {"median": float(np.median(v)), "min": float(v.min()), "max": float(v.max())}

    keys = ("roof_share", "unchanged_share", "false_share_among_flagged", "roof_median_k", "unchanged_median_abs_z")
    pooled = {m: sum(r[m]["unchanged_flagged"] for r in rows) / sum(r[m]["cells"]["unchanged"] for r in rows)
              for m in ("per_cell", "fdr")}
    print(json.dumps({"pairs": a.pairs, "apparent_warming_k": f["apparent_warming"],
                      "netd_estimated_k": stat_plain([x for r in rows for x in r["netd_k"]]),
                      "unchanged_share_pooled": pooled,
                      "unchanged_share_per_pair": [r["per_cell"]["unchanged_share"] for r in rows],
                      **{m: {k: stat(m, k) for k in keys} for m in ("per_cell", "fdr")},
                      "cells_first_pair": rows[0]["per_cell"]["cells"]}, indent=1))


def stat_plain(v):
    v = np.asarray(v, float)
    return {"median": float(np.median(v)), "min": float(v.min()), "max": float(v.max())}


if __name__ == "__main__":
    main()
