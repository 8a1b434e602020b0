"""``thermogrammetry convert``: keeps going past bad files, exits non-zero, other outputs complete."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import data_path
from thermogrammetry.cli.main import main
from thermogrammetry.io import read_thermal
from thermogrammetry.io.convert import ConvertOptions, convert_files

THERMIMAGE = ("flir_thermimage", "inst", "extdata")


def _bad_files(tmp_path: Path) -> tuple[Path, Path]:
    from PIL import Image

    good = data_path(*THERMIMAGE, "IR_2412.jpg").read_bytes()
    truncated = tmp_path / "in" / "truncated.jpg"
    truncated.parent.mkdir(exist_ok=True)
    truncated.write_bytes(good[:30_000])  # cut inside the FLIR APP1 segments
    plain = tmp_path / "in" / "visible.jpg"
    Image.new("RGB", (64, 48), (90, 120, 200)).save(plain)  # a JPEG without radiometric data
    return truncated, plain


def test_cli_convert_keeps_going_and_exits_nonzero(tmp_path, capsys):
    truncated, plain = _bad_files(tmp_path)
    ir = data_path(*THERMIMAGE, "IR_2412.jpg")
    seq = data_path(*THERMIMAGE, "SampleSEQ.seq")
    xt2 = data_path("rjpeg_samples", "images", "DJI_XT2.jpg")
    out = tmp_path / "out"
    code = main(["convert", str(truncated), str(ir), str(plain), str(seq), str(xt2), "-o", str(out),
                 "--unit", "C", "--encoding", "uint16"])
    text = capsys.readouterr().out
    assert code == 2
    # both bad files listed at the end with their reasons
    tail = text[text.index("failed:"):]
    assert "truncated.jpg" in tail and "truncated file" in tail
    assert "visible.jpg" in tail and "JPEG without radiometric data" in tail
    assert "3 of 5 file(s) converted, 4 TIFF(s) written" in " ".join(text.split())
    # the other outputs are complete and hold the right temperatures
    names = sorted(p.name for p in out.iterdir())
    assert names == ["DJI_XT2.tif", "IR_2412.tif", "SampleSEQ_f00000.tif", "SampleSEQ_f00001.tif", "convert-manifest.json"]
    ref = np.fromfile(data_path("flir_thermimage", "Uploads", "FLIRjpg_W640_H480_F1_I.raw"), "<f4").reshape(480, 640)
    back = read_thermal(out / "IR_2412.tif")
    # 16-bit: half a step (<= 0.005 K) + float32 of the reference + our 3e-5 K agreement with Thermimage
    assert np.max(np.abs(back.temperature_k - 273.15 - ref)) < 0.006
    step = float(back.metadata.extra["gdal_metadata"]["THERMOGRAMMETRY_MAX_QUANTISATION_ERROR"]) * 2
    assert step <= 0.01
    f1 = read_thermal(out / "SampleSEQ_f00001.tif")
    assert f1.metadata.extra["gdal_metadata"]["THERMOGRAMMETRY_FRAME"] == "1"
    assert read_thermal(out / "DJI_XT2.tif").metadata.geotag.has_position  # GPS kept
    assert not list(out.glob(".*"))  # no temporaries left


def test_cli_convert_overrides_and_float32(tmp_path, capsys):
    ir = data_path(*THERMIMAGE, "IR_2412.jpg")
    out = tmp_path / "o"
    code = main(["convert", str(ir), "-o", str(out), "--emissivity", "0.9", "--distance", "5", "--humidity", "80",
                 "--reflected", "15C", "--air-temperature", "298.15K"])
    assert code == 0
    got = read_thermal(out / "IR_2412.tif")
    want = read_thermal(ir, emissivity=0.9, distance_m=5.0, relative_humidity=0.8, reflected_temperature_k=288.15,
                        atmospheric_temperature_k=298.15)
    np.testing.assert_allclose(got.temperature_k, want.temperature_k, atol=1e-6)  # float32 stored exactly
    plain = read_thermal(ir)
    assert abs(float(np.mean(got.temperature_k - plain.temperature_k))) > 0.2  # the overrides did something
    md = got.metadata.extra["gdal_metadata"]
    assert md["EMISSIVITY"] == "0.9" and md["OBJECT_DISTANCE_M"] == "5" and md["RELATIVE_HUMIDITY"] == "0.8"
    assert main(["convert", str(ir), "-o", str(out), "--unit", "F"]) != 0  # bad unit refused


def test_library_convert_raw_counts_only_is_a_failure(tmp_path):
    m3t = data_path("rjpeg_samples", "images", "M3T", "DJI_0001_R.JPG")
    ir = data_path(*THERMIMAGE, "IR_2412.jpg")
    copy = tmp_path / "IR_2412.jpg"
    shutil.copy(ir, copy)
    rep = convert_files([m3t, copy, ir], tmp_path / "o", ConvertOptions(unit="K"), jobs=2)
    assert [r.ok for r in rep.results] == [False, True, True]
    assert "raw counts only" in rep.results[0].message
    # same stem twice -> distinct outputs
    assert sorted(Path(o).name for r in rep.results for o in r.outputs) == ["IR_2412.tif", "IR_2412_2.tif"]


def test_cli_convert_accepts_a_folder(tmp_path, capsys):
    src = tmp_path / "flight"
    src.mkdir()
    for name in ("DJI_XT2.jpg", "DJI_XTR.jpg"):
        shutil.copy(data_path("rjpeg_samples", "images", name), src / name)
    code = main(["convert", str(src), "-o", str(tmp_path / "out")])
    assert code == 0
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["DJI_XT2.tif", "DJI_XTR.tif", "convert-manifest.json"]


def test_cli_convert_matrix_needs_input_unit(tmp_path, capsys):
    m = tmp_path / "m.npy"
    np.save(m, np.full((4, 5), 21.5))
    assert main(["convert", str(m), "-o", str(tmp_path / "a")]) == 2
    assert "unit" in capsys.readouterr().out
    assert main(["convert", str(m), "-o", str(tmp_path / "b"), "--input-unit", "C"]) == 0
    np.testing.assert_allclose(read_thermal(tmp_path / "b" / "m.tif").temperature_k, 21.5 + 273.15, atol=1e-4)


def test_convert_options_refuse_unknown_override():
    from thermogrammetry.errors import ConfigError

    with pytest.raises(ConfigError, match="emisivity"):
        ConvertOptions(overrides={"emisivity": 0.9})
