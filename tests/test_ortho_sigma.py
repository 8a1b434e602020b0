"""ortho_sigma.tif: the public contract (bands, units, nodata, tags, ortho.json) and an honesty check of the σ
model by a small Monte Carlo (true poses perturbed by their stated σ, white sensor noise of known NETD)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio

from sigma_mc import mc_table, monte_carlo

FRAMES = [18, 19, 20, 33, 34]  # 2 lines of a few frames: small and fast


@pytest.fixture(scope="module")
def mc(tmp_path_factory):
    root = tmp_path_factory.mktemp("sigma_mc")
    return root, monte_carlo(root, 8, frames=FRAMES, seed=1, dsm_gsd=0.2)


def test_ortho_sigma_scatter_matches_prediction_in_a_monte_carlo(mc):
    # 8 runs: per cell the RMS over 8 draws has a chi distribution with 8 degrees of freedom, whose median is
    # ~0.96 of the true σ (its relative spread ~1/sqrt(16) = 0.25 per cell; the median over ~10^4 cells is
    # tight). A correct model gives ~0.95 (the NETD estimate runs ~5-10 % high); 0.75-1.15 refuses a σ off by 25 %.
    _, m = mc
    tab = mc_table(m)
    assert tab["cells"] > 5000
    assert 0.75 < tab["median_ratio"] < 1.15, tab
    assert 0.9 < tab["within_2sigma"] < 0.995, tab
    assert 0.04 < np.median(m["netd"]) < 0.065  # the NETD estimated from the frames (true 0.05 K)


def test_ortho_sigma_tif_contract(mc):
    root, m = mc
    out = root / "truth"
    from thermogrammetry.pipeline.ortho import run_ortho

    rep = run_ortho(root / "base", root / "dsm.tif", root / "o", workers=0)
    with rasterio.open(root / "o" / "ortho_sigma.tif") as s, rasterio.open(root / "o" / "ortho.tif") as o:
        a, v = s.read(), o.read(1)
        assert s.count == 4 and s.dtypes[0] == "float32" and s.transform == o.transform and s.crs == o.crs
        assert s.units[0] == "K" and s.descriptions[0].startswith("total random")
        tags = s.tags()
        assert tags["systematic"] == "unknown" and float(tags["netd"]) >= 0
    assert np.array_equal(np.isfinite(a[0]), np.isfinite(v))
    ok = np.isfinite(v)
    assert np.allclose(a[0][ok] ** 2, (a[1:][:, ok] ** 2).sum(axis=0), rtol=1e-4)
    assert np.all(a[3][ok] == 0)  # no --correct
    # noise-free frames, no pose sigma in cameras.json: the estimated NETD is the estimator's floor (interpolation on the flattest tenth), the DSM σ (one cell, 0.2 m) remains
    assert rep["sigma"]["netd"] < 0.035 and rep["sigma"]["dsm_sigma_m"] == pytest.approx(0.2)
    man = json.loads((root / "o" / "ortho-manifest.json").read_text())
    assert "ortho_sigma.tif" in man["files"]
    j = json.loads((root / "o" / "ortho.json").read_text())["sigma"]
    assert set(j["share_below"]) == {"0.1", "0.5", "1.0"} and 0 <= j["total"]["median"] <= j["total"]["p95"]
    del out


def test_ortho_sigma_correction_band_with_correct(mc, tmp_path):
    root, _ = mc
    from thermogrammetry.pipeline.ortho import run_ortho

    run_ortho(root / "base", root / "dsm.tif", tmp_path / "o", workers=0, correct=True, gsd=0.4)
    with rasterio.open(tmp_path / "o" / "ortho_sigma.tif") as s:
        a = s.read()
    ok = np.isfinite(a[0])
    # the reflected temperature's 1 K and the emissivity's 0.01: tenths of a kelvin at ~300 K
    assert 0.05 < np.median(a[3][ok]) < 2.0
