"""`survey --camera` reads the calibrations users have (thermogrammetry.io.camera_file.read_camera_file): camera.json,
Metashape XML, OpenCV YAML and XML, a one-camera COLMAP cameras.txt; each written from one camera and read back to
the same projection; files that are none of them, or hold no single camera, refused with the file's name."""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry.camera import Camera
from thermogrammetry.errors import CorruptFileError, DataFileError
from thermogrammetry.io.camera_file import camera_file_format, read_camera_file

# a wide thermal lens (the M2ED-like 57° over 640 px) with barrel distortion
CAM = Camera("opencv", (640, 512), dict(fx=590.3, fy=590.9, cx=322.4, cy=251.7, k1=-0.31, k2=0.12, p1=4e-4, p2=-3e-4,
                                       k3=-0.02), name="lab")


def _grid():
    u, v = np.meshgrid(np.linspace(0, 639, 9), np.linspace(0, 511, 7))
    return np.column_stack([u.ravel(), v.ravel()])


def _same_projection(cam: Camera, tol_px: float):
    # the pixels of rays through a grid over the whole frame, as the lab camera projects them
    rays = CAM.unproject(_grid())  # (N, 3), z = 1
    d = np.linalg.norm(cam.project(rays) - CAM.project(rays), axis=1)
    assert d.max() < tol_px, d.max()


def _opencv_file(path, K, dist, size):
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", int(size[0]))
    fs.write("image_height", int(size[1]))
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", dist.reshape(1, -1))
    fs.release()


def test_every_format_reads_back_the_same_camera(tmp_path):
    from thermogrammetry.io.colmap import write_colmap_cameras
    from thermogrammetry.io.metashape import write_metashape_calibration

    CAM.save(tmp_path / "camera.json")
    K, dist = CAM.to_opencv()
    _opencv_file(tmp_path / "opencv.yaml", K, dist, CAM.image_size)
    _opencv_file(tmp_path / "opencv.xml", K, dist, CAM.image_size)
    write_colmap_cameras(tmp_path / "cameras.txt", [CAM])
    write_metashape_calibration(tmp_path / "metashape.xml", CAM)
    expect = {"camera.json": "camera.json", "opencv.yaml": "OpenCV YAML/XML", "opencv.xml": "OpenCV YAML/XML",
              "cameras.txt": "COLMAP cameras.txt", "metashape.xml": "Metashape XML"}
    for name, fmt in expect.items():
        assert camera_file_format(tmp_path / name) == fmt, name
        cam = read_camera_file(tmp_path / name)
        assert tuple(cam.image_size) == (640, 512), name
        # written with 17 significant digits (JSON, COLMAP) or OpenCV's %.16e: the same projection to 1e-6 px;
        # Metashape's model (K1-K3, P1/P2 swapped, cx/cy from the centre) is the same for K4 = 0
        _same_projection(cam, 1e-6)


def test_files_that_are_no_single_camera_are_refused_with_their_name(tmp_path):
    from thermogrammetry.io.colmap import write_colmap_cameras

    (tmp_path / "other.xml").write_text("<?xml version='1.0'?><document><chunk/></document>")
    with pytest.raises(CorruptFileError, match="other.xml.*neither a Metashape"):
        read_camera_file(tmp_path / "other.xml")
    write_colmap_cameras(tmp_path / "two.txt", [CAM, CAM])
    with pytest.raises(CorruptFileError, match="two.txt.*2 cameras; expected exactly one"):
        read_camera_file(tmp_path / "two.txt")
    import cv2

    fs = cv2.FileStorage(str(tmp_path / "nosize.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", CAM.to_opencv()[0])
    fs.release()
    with pytest.raises(CorruptFileError, match="nosize.yaml.*image_width"):
        read_camera_file(tmp_path / "nosize.yaml")
    with pytest.raises(DataFileError, match="missing.json"):
        read_camera_file(tmp_path / "missing.json")


def test_the_file_format_and_conversion_residual_are_recorded(tmp_path):
    """open_camera_file: the format and the conversion residual (0 for files in the camera's own model)."""
    from thermogrammetry.io.camera_file import describe_camera_file, open_camera_file

    K, dist = CAM.to_opencv()
    _opencv_file(tmp_path / "opencv.yaml", K, dist, CAM.image_size)
    cf = open_camera_file(tmp_path / "opencv.yaml")
    assert cf.format == "OpenCV YAML/XML" and cf.conversion_max_residual_px == 0.0
    _same_projection(cf.camera, 1e-6)
    assert describe_camera_file(cf.to_dict()) == f"camera {tmp_path / 'opencv.yaml'} (OpenCV YAML/XML; read exactly)"


def test_correct_takes_an_opencv_camera_file(tmp_path, capsys):
    """`correct --camera` reads any of the formats, prints and records where the camera came from; the result is
    the same as from the camera.json of the same camera."""
    import json

    import tifffile

    from test_bad_inputs import correct_argv
    from thermogrammetry.cli.main import main

    a = tmp_path / "a"
    a.mkdir()
    argv = correct_argv(a)
    assert main(argv) == 0
    cam = Camera.load(a / "camera.json")
    K, dist = cam.to_opencv()
    _opencv_file(a / "opencv.yaml", K, dist, cam.image_size)
    argv_yaml = [str(a / "opencv.yaml") if v == str(a / "camera.json") else v for v in argv]
    argv_yaml[argv_yaml.index("-o") + 1] = str(tmp_path / "OUT_yaml")
    capsys.readouterr()
    assert main(argv_yaml) == 0
    assert "(OpenCV YAML/XML; read exactly)" in capsys.readouterr().out
    man = json.loads((tmp_path / "OUT_yaml" / "correct-manifest.json").read_text())
    assert man["camera_file"]["format"] == "OpenCV YAML/XML", man
    assert np.array_equal(tifffile.imread(a / "OUT" / "corrected.tif"), tifffile.imread(tmp_path / "OUT_yaml" / "corrected.tif"))
