"""The ortho in isolation: TRUE poses, the TRUE DSM and NOISE-FREE frames (``render_frame(sensor=False)``: no NETD,
fixed-pattern noise or PSF; one ray per pixel, so a pixel is the apparent temperature of the point its centre ray
hits).  Nothing is estimated, so the mosaic must be the frames themselves, sampled where the true geometry says:

- nearest: every cell is BITWISE the noise-free source pixel that the cell's true surface point projects to
  (rounded pixel coordinates), and ortho_source.tif names that pixel;
- bilinear: every cell is within 0.01 K of the noise-free frame interpolated (bilinear, computed here in float64)
  at the exact projection of the cell's true surface point.

The reference is computed from the scene, not from the product's inputs: heights from the terrain model
(``true_height``), not from the DSM file; projections with the scene's camera and frame poses, not cameras.json.
What may differ is only storage: the DSM file holds float32 heights (~100 m: ulp 7.6e-6 m, a projection shift
of ~1e-4 px at 45 m), the ortho float32 values (ulp 3e-5 K near 300 K).  With image steps of up to ~10 K per
pixel at roof edges that is a few 1e-4 K at worst.  Measured (4 frames, 62 337 cells): nearest bitwise in every
cell (25 cells within 1e-4 px of a rounding tie, left out of the check, agree too); bilinear max 4.0e-4 K, p99
1.6e-5 K, 100 % within 0.01 K.  The 0.01 K bound is the issue's (25x the measured worst).  A half-pixel
convention error shows far above it: neighbouring pixels differ by 0.05 K (median) to 1.7 K (p99) here.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
import tifffile

from survey_truth import true_height, write_true_dsm, write_true_survey
from thermogrammetry.cli.main import main

FRAMES = [18, 19, 33, 34]  # 2 frames on each of 2 lines: small and fast


@pytest.fixture(scope="module")
def iso(tmp_path_factory):
    root = tmp_path_factory.mktemp("ortho_iso")
    sc, sv = write_true_survey(root / "survey", frames=FRAMES, sensor=False)
    write_true_dsm(root / "dsm.tif", sc, 0.1, margin_m=8.0)
    for sampling in ("nearest", "bilinear"):
        assert main(["ortho", str(sv), "--dsm", str(root / "dsm.tif"), "-o", str(root / sampling), "--sampling",
                     sampling, "--workers", "0"]) == 0
    return sc, sv, root


def _cells(sc, sv, out):
    """Covered cells: (value, source index, source row, col, frame index in the scene, exact (u, v) of the cell's
    true surface point in that frame)."""
    with rasterio.open(out / "ortho.tif") as s:
        v = s.read(1)
        tr = s.transform
    with rasterio.open(out / "ortho_source.tif") as s:
        src = s.read()
    rep = json.loads((out / "ortho.json").read_text())
    rr, cc = np.nonzero(src[0] >= 0)
    x, y = tr.c + (cc + 0.5) * tr.a, tr.f + (rr + 0.5) * tr.e
    P = np.column_stack([x, y, true_height(sc, x, y)])
    index = {f.name: i for i, f in enumerate(sc.frames)}
    fi = np.array([index[rep["images"][str(k)]] for k in src[0, rr, cc]])
    uv = np.full((len(P), 2), np.nan)
    for i in np.unique(fi):
        m = fi == i
        uv[m] = sc.camera.project(sc.frames[i].pose.transform(P[m]))
    return v[rr, cc], src[1, rr, cc], src[2, rr, cc], fi, uv


def _frame(sv, sc, i):
    return tifffile.imread(sv / "frames" / f"{sc.frames[i].name}.tif")


def test_nearest_is_bitwise_the_noise_free_source_pixel_of_the_true_point(iso):
    sc, sv, root = iso
    val, row, col, fi, uv = _cells(sc, sv, root / "nearest")
    assert len(val) > 40_000 and np.all(np.isfinite(val))
    # a projection within 1e-4 px of a rounding tie may round either way under the float32 DSM: left out (counted)
    frac = np.abs(uv - np.floor(uv) - 0.5)
    clear = np.all(frac > 1e-4, axis=1)
    assert clear.mean() > 0.999
    ui, vi = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    assert np.array_equal(row[clear], vi[clear]) and np.array_equal(col[clear], ui[clear])
    truth = np.empty(len(val), np.float32)
    for i in np.unique(fi):
        m = fi == i
        truth[m] = _frame(sv, sc, i)[vi[m], ui[m]]
    assert np.array_equal(val[clear].view(np.uint32), truth[clear].view(np.uint32))


def test_bilinear_is_within_0_01_k_of_the_noise_free_frame_at_the_true_point(iso):
    sc, sv, root = iso
    val, _, _, fi, uv = _cells(sc, sv, root / "bilinear")
    ok = np.isfinite(val)
    assert ok.sum() > 40_000
    truth = np.full(len(val), np.nan)
    for i in np.unique(fi):
        m = ok & (fi == i)
        img = _frame(sv, sc, i).astype(float)
        H, W = img.shape
        # a frame covers its pixels' area, half a pixel beyond the outer pixel centres: there the edge pixel
        # holds (clamp to edge)
        u, v = uv[m, 0], uv[m, 1]
        assert u.min() >= -0.5 and v.min() >= -0.5 and u.max() <= W - 0.5 and v.max() <= H - 0.5
        u, v = np.clip(u, 0, W - 1), np.clip(v, 0, H - 1)
        u0, v0 = np.minimum(np.floor(u).astype(int), W - 2), np.minimum(np.floor(v).astype(int), H - 2)
        fu, fv = u - u0, v - v0
        truth[m] = ((img[v0, u0] * (1 - fu) + img[v0, u0 + 1] * fu) * (1 - fv)
                    + (img[v0 + 1, u0] * (1 - fu) + img[v0 + 1, u0 + 1] * fu) * fv)
    err = np.abs(val[ok] - truth[ok])
    assert np.max(err) < 0.01, np.max(err)
    assert np.mean(err < 0.05) == 1.0
