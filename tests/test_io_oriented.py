"""The one oriented-cameras schema (cameras.json): round trip and refusals with clear messages."""

import json

import numpy as np
import pytest

from thermogrammetry import Camera
from thermogrammetry.errors import ConfigError, UnsupportedFormatError
from thermogrammetry.geometry.rotations import matrix_from_axis_angle
from thermogrammetry.io.oriented import OrientedCameras, OrientedImage


def _block():
    cam = Camera("opencv", (640, 512), dict(fx=1470.0, fy=1470.0, cx=320.1, cy=255.4, k1=-0.08), pixel_pitch_um=17.0)
    ims = []
    for i in range(3):
        R = matrix_from_axis_angle(np.array([np.pi, 0.01 * i, 0.02]))
        C = np.array([2600000.0 + 10 * i, 1200000.0, 550.0])
        ims.append(OrientedImage(f"T{i}", "thermal", R, -R @ C, center_std=[0.01, 0.01, 0.02], frame=f"frames/T{i}.tif"))
    return OrientedCameras({"thermal": cam}, ims, crs="EPSG:2056")


def test_round_trip(tmp_path):
    oc = _block()
    p = oc.save(tmp_path / "cameras.json")
    back = OrientedCameras.load(tmp_path)
    assert back.crs == "EPSG:2056" and back.names() == ["T0", "T1", "T2"]
    for a, b in zip(oc, back):
        assert np.abs(a.center - b.center).max() < 1e-9  # metres; JSON floats round-trip exactly (measured 0; ulp at 5e6 m: 9e-10)
        assert np.abs(a.R - b.R).max() < 1e-15
    assert back.frame_path("T1") == tmp_path / "frames" / "T1.tif"
    d = json.loads(p.read_text())
    assert d["images"][0]["camera"]["model"] == "opencv" and len(d["images"][0]["center"]) == 3


def test_refuses_other_files_with_reason(tmp_path):
    (tmp_path / "cameras.json").write_text(json.dumps({"stations": []}))
    with pytest.raises(UnsupportedFormatError, match="older or different cameras file"):
        OrientedCameras.load(tmp_path / "cameras.json")
    d = _block().to_dict()
    d["images"][1]["center"][0] += 5.0
    with pytest.raises(ConfigError, match=r"images\[1\].*disagrees"):
        OrientedCameras.from_dict(d)
    d = _block().to_dict()
    d["images"][0]["cam_from_world"]["R"] = [[1, 0], [0, 1]]
    with pytest.raises(ConfigError, match=r"images\[0\].cam_from_world.R"):
        OrientedCameras.from_dict(d)
    d = _block().to_dict()
    d["images"][2]["camera_id"] = "rgb"
    with pytest.raises(ConfigError, match="'rgb'"):
        OrientedCameras.from_dict(d)
