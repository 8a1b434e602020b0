"""``thermogrammetry facade``: thermal orthoimage of a flat facade from an oriented survey (seed 002).

The wall of ``tests/test_texture_counts.py``: plane y = 0 (4 m × 3 m), three pinhole cameras 5 m in front
(160 × 120 px, f = 150 px: 3.3 cm pixels), exact poses, frames = one world field sampled at the pixel
centres' rays. With exact poses a facade cell must equal the bilinear sample of its source frame at the
projection of the cell centre: recomputed here independently (float64 from the frame) and compared within
float32 rounding (1e-3 K at ~200 K; 0.004 count at 2e4).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_texture_counts import FOCAL, H, W, _bilinear64, _gdal_md, _poses, _write  # noqa: E402

from thermogrammetry.cli.main import main  # noqa: E402


def _expected(out, survey, scale=1.0):
    """Independent recomputation of every filled cell from its source frame."""
    import tifffile

    d = json.loads((out / "facade.json").read_text())
    vals = tifffile.imread(out / "facade_temperature.tif")
    src = tifffile.imread(out / "facade_source.tif")
    g, pl = d["grid"], d["plane"]
    h, w = g["shape"]
    A = g["a0"] + (np.arange(w) + 0.5) * g["cell"]
    B = g["b1"] - (np.arange(h) + 0.5) * g["cell"]
    AA, BB = np.meshgrid(A, B)
    P = np.asarray(pl["origin"]) + AA[..., None] * np.asarray(pl["u"]) + BB[..., None] * np.asarray(pl["v"])
    poses = _poses()
    names = {int(k): v for k, v in d["index"].items()}
    exp = np.full(vals.shape, np.nan)
    for k, name in names.items():
        m = src == k
        if not m.any():
            continue
        pose = poses[int(name[1:])]
        Xc = P[m] @ pose.R.T + pose.t
        xy = np.column_stack([FOCAL * Xc[:, 0] / Xc[:, 2] + (W - 1) / 2, FOCAL * Xc[:, 1] / Xc[:, 2] + (H - 1) / 2])
        frame = tifffile.imread(survey / "frames" / f"{name}.tif")
        exp[m] = _bilinear64(frame, xy)[0] * scale
    return d, vals, src, exp


@pytest.fixture(scope="module")
def kelvin(tmp_path_factory):
    root = tmp_path_factory.mktemp("facade_k")
    survey = _write(root / "s", unit="K")
    out = root / "out"
    code = main(["facade", str(survey), "-o", str(out), "--plane", "0,0,0,0,-1,0", "--cell", "0.05"])
    return survey, out, code


def test_cells_are_their_source_frame_values(kelvin):
    survey, out, code = kelvin
    assert code == 0
    d, vals, src, exp = _expected(out, survey)
    assert d["unit"] == "K" and d["quantity"] == "temperature"
    # the plane frame: normal towards the cameras (-y), u along +x, v up (+z: the cameras' up)
    np.testing.assert_allclose(d["plane"]["normal"], [0, -1, 0], atol=1e-9)
    np.testing.assert_allclose(d["plane"]["u"], [1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(d["plane"]["v"], [0, 0, 1], atol=1e-9)
    ok = src >= 0
    assert ok.sum() == d["cells_filled"] and d["cells_filled"] > 0.9 * d["cells_total"]
    assert np.all(np.isnan(vals[~ok]))
    assert np.max(np.abs(vals[ok] - exp[ok])) < 1e-3  # measured 7.6e-6 K (float32)
    # against the truth: cells 3 pixels inside the constant patch (x 1.5-2.5 m, z 1-2 m: 234.56 K) hold it exactly
    g = d["grid"]
    a = g["a0"] + (np.arange(vals.shape[1]) + 0.5) * g["cell"]
    b = g["b1"] - (np.arange(vals.shape[0]) + 0.5) * g["cell"]
    AA, BB = np.meshgrid(a, b)
    inner = (AA > 1.6) & (AA < 2.4) & (BB > 1.1) & (BB < 1.9)
    assert inner.sum() > 150 and np.all(np.abs(vals[inner] - 234.56) < 1e-4)
    assert d["images_used"] == 3 and "K" in _gdal_md(out / "facade_temperature.tif")
    for f in ("facade_angle.tif", "facade_resolution.tif", "facade.png"):
        assert (out / f).stat().st_size > 100
    # resolution on the facade: f cos(angle) / distance, 150 / 5 = 30 px/m at the foot of each camera
    import tifffile

    res = tifffile.imread(out / "facade_resolution.tif")
    assert 20 < np.nanmin(res) and np.nanmax(res) <= 30.0 + 1e-3


def test_plane_fitted_to_the_sparse_cloud(tmp_path):
    """``--plane auto``: 300 points on the wall (2 mm noise) and 60 on a pole 1 m in front: the wall is found."""
    from plyfile import PlyData, PlyElement

    survey = _write(tmp_path / "s", unit="K")
    rng = np.random.default_rng(0)
    wall = np.column_stack([rng.uniform(0.2, 3.8, 300), rng.normal(0, 0.002, 300), rng.uniform(0.2, 2.8, 300)])
    pole = np.column_stack([np.full(60, 2.0), np.full(60, -1.0), np.linspace(0, 2.5, 60)])
    X = np.concatenate([wall, pole])
    v = np.zeros(len(X), dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    v["x"], v["y"], v["z"] = X.T
    PlyData([PlyElement.describe(v, "vertex")]).write(str(survey / "sparse.ply"))
    out = tmp_path / "out"
    assert main(["facade", str(survey), "-o", str(out), "--cell", "0.05"]) == 0
    d = json.loads((out / "facade.json").read_text())
    n = np.asarray(d["plane"]["normal"])
    assert np.degrees(np.arccos(np.clip(-n[1], -1, 1))) < 0.5  # 300 points, 2 mm over 3.6 m: ~0.05 deg
    assert abs(d["plane"]["origin"][1]) < 0.002 and "fitted to" in d["plane"]["how"]
    # the extent is the wall points' 1-99 percentiles
    assert 3.2 < d["grid"]["a1"] - d["grid"]["a0"] < 3.6 and 2.3 < d["grid"]["b1"] - d["grid"]["b0"] < 2.6
    d2, vals, src, exp = _expected(out, survey)
    ok = src >= 0
    assert np.max(np.abs(vals[ok] - exp[ok])) < 1e-3


def test_counts_are_kept_and_labelled(tmp_path, capsys):
    survey = _write(tmp_path / "s", unit="counts")
    out = tmp_path / "out"
    assert main(["facade", str(survey), "-o", str(out), "--plane", "0,0,0,0,-1,0", "--cell", "0.05"]) == 0
    d, vals, src, exp = _expected(out, survey)
    assert d["unit"] == "counts" and d["quantity"] == "raw_counts"
    ok = src >= 0
    assert np.max(np.abs(vals[ok] - exp[ok])) < 0.004  # float32 of ~2e4 counts
    md = _gdal_md(out / "facade_temperature.tif")
    assert "counts" in md and "°C" not in md
    # a temperature unit cannot be applied to counts
    assert main(["facade", str(survey), "-o", str(tmp_path / "o2"), "--plane", "0,0,0,0,-1,0", "--unit", "C"]) == 2
    assert "raw counts" in capsys.readouterr().err


@pytest.mark.parametrize("args, words", [
    (["--plane", "1,2,3"], "six numbers"),
    (["--plane", "0,0,0,0,0,0"], "six numbers"),
    (["--cell", "-1"], "--cell"),
    (["--unit", "F"], "expected K or C"),
    ([], "sparse.ply"),  # --plane auto without a sparse cloud
])
def test_bad_arguments_exit_2_with_the_value(tmp_path, capsys, args, words):
    survey = _write(tmp_path / "s", unit="K")
    assert main(["facade", str(survey), "-o", str(tmp_path / "out"), *args]) == 2
    assert words in capsys.readouterr().err
    assert not (tmp_path / "out" / "facade.json").exists()
