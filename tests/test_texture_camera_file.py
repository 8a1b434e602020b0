"""`texture --camera`: a calibration of the user's (any of the camera-file formats) in place of the survey's thermal
camera of the same image size; another size is refused with both sizes named."""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry.camera import Camera
from thermogrammetry.errors import ConfigError
from thermogrammetry.io.camera_file import open_camera_file
from thermogrammetry.io.oriented import OrientedCameras, OrientedImage
from thermogrammetry.pipeline.texture import with_camera_file


def _cameras():
    th = Camera("opencv", (320, 256), dict(fx=400.0, fy=400.0, cx=159.5, cy=127.5))
    rgb = Camera("opencv", (1280, 1024), dict(fx=1500.0, fy=1500.0, cx=639.5, cy=511.5))
    ims = [OrientedImage("t0", "thermal", np.eye(3), np.zeros(3)),
           OrientedImage("r0", "rgb", np.eye(3), np.zeros(3), sensor="rgb")]
    return OrientedCameras({"thermal": th, "rgb": rgb}, ims)


def test_the_thermal_camera_of_that_size_is_replaced(tmp_path):
    lab = Camera("opencv", (320, 256), dict(fx=405.2, fy=404.8, cx=161.0, cy=126.2, k1=-0.2), name="lab")
    K, dist = lab.to_opencv()
    import cv2

    fs = cv2.FileStorage(str(tmp_path / "lab.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 320)
    fs.write("image_height", 256)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", dist.reshape(1, -1))
    fs.release()
    given = _cameras()
    cams, rec = with_camera_file(given, open_camera_file(tmp_path / "lab.yaml"))
    assert rec["replaces"] == ["thermal"] and rec["format"] == "OpenCV YAML/XML" and rec["conversion_max_residual_px"] == 0
    assert np.allclose(cams.camera_of("t0").params, lab.params, rtol=0, atol=1e-9)
    assert cams.camera_of("r0") is given.cameras["rgb"]  # the RGB camera (another size) is kept
    assert given.camera_of("t0").params[0] == 400.0  # the survey's cameras are not modified


def test_a_camera_of_another_size_is_refused(tmp_path):
    Camera("opencv", (640, 512), dict(fx=800.0, fy=800.0, cx=319.5, cy=255.5)).save(tmp_path / "camera.json")
    with pytest.raises(ConfigError, match=r"image size 640x512; the survey's thermal cameras are 320x256"):
        with_camera_file(_cameras(), open_camera_file(tmp_path / "camera.json"))
