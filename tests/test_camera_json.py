"""Camera JSON files: versioned round trip and specific errors for bad files."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from thermogrammetry import Camera
from thermogrammetry.errors import (
    ConfigError,
    CorruptFileError,
    DataFileError,
    NonFiniteError,
    UnknownModelError,
    UnsupportedFormatError,
)

FLIR_A320 = dict(
    c_mm=17.2262, x0_mm=0.2883, y0_mm=-0.1995,
    K1=-30.6381e-4, K2=2599.4545e-7, K3=-98791.5437e-10,
    P1=-22.6353e-5, P2=28.1114e-5,
)
# seed 001 Table 2 standard deviations, in the table's units (the K/P columns carry the same power of ten)
FLIR_A320_STD = dict(c_mm=0.1288, x0_mm=0.0512, y0_mm=0.0656, K1=4.6329e-4, K2=493.9109e-7, K3=16416.952e-10,
                     P1=4.6768e-5, P2=4.8051e-5)


def flir() -> Camera:
    return Camera("photogrammetric", (320, 240), FLIR_A320, pixel_pitch_um=25.0, param_std=FLIR_A320_STD,
                  name="FLIR A320")


def write(tmp_path, d, name="cam.json"):
    p = tmp_path / name
    p.write_text(json.dumps(d))
    return p


def test_round_trip_all_models(tmp_path):
    cams = [
        flir(),
        Camera("opencv", (640, 512), dict(fx=800.5, fy=801.25, cx=319.7, cy=255.1, skew=0.3, k1=-0.1, k2=0.02,
                                          p1=1e-4, p2=-2e-4, k3=1e-3, k4=0.01, k5=-1e-3, k6=2e-4),
               pixel_pitch_um=(12.0, 12.0)),
        Camera("pinhole", (100, 80), dict(fx=90.0, fy=91.0, cx=49.5, cy=39.5)),
    ]
    for i, cam in enumerate(cams):
        path = cam.save(tmp_path / f"c{i}.json")
        back = Camera.load(path)
        assert back == cam  # bit-identical: JSON floats round-trip exactly (repr is shortest round-trip)
        d = json.loads(path.read_text())
        assert d["format"] == "thermogrammetry.camera" and d["version"] == 1
    d = json.loads((tmp_path / "c0.json").read_text())
    assert d["units"]["K1"] == "mm^-2" and d["std"]["c_mm"] == 0.1288
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]  # atomic write leaves no temp file


def test_std_round_trip(tmp_path):
    cam = flir()
    back = Camera.load(cam.save(tmp_path / "c.json"))
    np.testing.assert_array_equal(back.param_std[:10], cam.param_std[:10])
    assert np.isnan(back.param_std[-1])  # B2 had no standard deviation


def test_hand_written_file_with_unit_aliases(tmp_path):
    d = {"format": "thermogrammetry.camera", "version": 1, "model": "OpenCV", "image_size": [640, 480],
         "params": {"fx": 500, "fy": 500, "cx": 319.5, "cy": 239.5, "k1": -0.1},
         "units": {"fx": "pixels", "k1": "unitless"}}
    cam = Camera.load(write(tmp_path, d))
    assert cam["k1"] == pytest.approx(-0.1, rel=1e-15) and cam["k6"] == 0.0 and cam.param_std is None
    d2 = {"format": "thermogrammetry.camera", "version": 1, "model": "photogrammetric", "image_size": [320, 240],
          "pixel_pitch_um": 25, "params": FLIR_A320, "units": {"K1": "1/mm^2", "K2": "mm⁻⁴", "c_mm": "millimetres"}}
    assert Camera.load(write(tmp_path, d2, "p.json")).pixel_pitch_um == (25.0, 25.0)


def _base():
    return flir().to_dict()


def test_unknown_top_level_key(tmp_path):
    d = _base()
    d["focal"] = 17.0
    p = write(tmp_path, d)
    with pytest.raises(ConfigError, match=rf"{p.name}: unknown key\(s\) 'focal'; expected keys: format, version"):
        Camera.load(p)


def test_unknown_parameter_name(tmp_path):
    d = _base()
    d["params"]["k1"] = 0.1  # OpenCV name in a photogrammetric file
    p = write(tmp_path, d)
    with pytest.raises(ConfigError, match=rf"{p.name}: unknown parameter\(s\) 'k1' for model 'photogrammetric'"):
        Camera.load(p)


def test_wrong_unit(tmp_path):
    d = _base()
    d["units"]["K1"] = "px^-2"
    p = write(tmp_path, d)
    with pytest.raises(ConfigError, match=rf"{p.name}: key 'units.K1' is 'px\^-2'; expected 'mm\^-2'"):
        Camera.load(p)
    d = _base()
    d["units"]["c_mm"] = "px"
    with pytest.raises(ConfigError, match=r"key 'units.c_mm' is 'px'; expected 'mm'"):
        Camera.load(write(tmp_path, d))


def test_missing_parameter(tmp_path):
    d = _base()
    del d["params"]["c_mm"]
    p = write(tmp_path, d)
    with pytest.raises(ConfigError, match=rf"{p.name}: missing parameter\(s\) 'c_mm' for model 'photogrammetric' "
                                          r"\(required: c_mm x0_mm y0_mm\)"):
        Camera.load(p)
    d = _base()
    del d["image_size"]
    with pytest.raises(ConfigError, match=r"missing key 'image_size'"):
        Camera.load(write(tmp_path, d))


def test_unknown_model(tmp_path):
    d = _base()
    d["model"] = "fisheye"
    p = write(tmp_path, d)
    with pytest.raises(UnknownModelError, match=rf"{p.name}: key 'model': unknown camera model 'fisheye'; expected one of"):
        Camera.load(p)


def test_bad_format_version_and_json(tmp_path):
    d = _base()
    d["version"] = 2
    with pytest.raises(UnsupportedFormatError, match=r"key 'version' is 2; this reader supports version 1"):
        Camera.load(write(tmp_path, d))
    d = _base()
    d["format"] = "colmap"
    with pytest.raises(UnsupportedFormatError, match=r"key 'format' is 'colmap'; expected 'thermogrammetry.camera'"):
        Camera.load(write(tmp_path, d))
    p = tmp_path / "broken.json"
    p.write_text('{"format": "thermogrammetry.camera", "version": 1,')
    with pytest.raises(CorruptFileError, match=r"broken.json: not valid JSON \(line 1, column"):
        Camera.load(p)
    with pytest.raises(DataFileError, match=r"missing.json: cannot read camera file"):
        Camera.load(tmp_path / "missing.json")


def test_bad_values(tmp_path):
    d = _base()
    d["params"]["K2"] = "0.1"
    with pytest.raises(ConfigError, match=r"params\['K2'\]: expected a number, got '0.1'"):
        Camera.load(write(tmp_path, d))
    p = tmp_path / "nan.json"
    p.write_text(json.dumps(_base()).replace("17.2262", "NaN"))
    with pytest.raises(NonFiniteError, match=r"nan.json: params\['c_mm'\]: expected a finite number, got nan"):
        Camera.load(p)
    d = _base()
    d["std"] = {"K9": 1.0}
    with pytest.raises(ConfigError, match=r"param_std: unknown parameter\(s\) 'K9'"):
        Camera.load(write(tmp_path, d))


def test_json_round_trip_is_bit_exact_for_arbitrary_values(tmp_path):
    # property test: any finite parameter values (tiny, huge, negative zero) survive save/load unchanged
    from hypothesis import given, settings
    from hypothesis import strategies as st

    finite = st.floats(min_value=-1e12, max_value=1e12, allow_nan=False, allow_infinity=False)
    positive = st.floats(min_value=1e-6, max_value=1e6, allow_nan=False, allow_infinity=False)

    @settings(max_examples=60, deadline=None, database=None, derandomize=True)
    @given(c=positive, rest=st.lists(finite, min_size=11, max_size=11), pitch=positive,
           size=st.tuples(st.integers(1, 100000), st.integers(1, 100000)))
    def check(c, rest, pitch, size):
        cam = Camera("photogrammetric", size, [c, *rest], pixel_pitch_um=pitch)
        back = Camera.load(cam.save(tmp_path / "h.json"))
        assert back == cam
        np.testing.assert_array_equal(np.signbit(back.params), np.signbit(cam.params))

    check()
