"""COLMAP text files: pixel-centre conversion, models, round trips, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry import Camera
from thermogrammetry.errors import CorruptFileError, InvalidInputError, UnknownModelError
from thermogrammetry.io.colmap import (
    ColmapImage,
    ColmapPoints3D,
    read_colmap_cameras,
    read_colmap_images,
    read_colmap_points3d,
    write_colmap_cameras,
    write_colmap_images,
    write_colmap_points3d,
)

CAMERAS_TXT = """# Camera list with one line of data per camera:
#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]
# Number of cameras: 6
1 SIMPLE_PINHOLE 640 480 500 320 240
2 PINHOLE 640 480 500 505 320.5 240.25
3 SIMPLE_RADIAL 640 512 800 320 256 -0.05
4 RADIAL 640 512 800 320 256 -0.05 0.01
5 OPENCV 640 512 810 805 321 255 -0.1 0.02 0.001 -0.0005
6 FULL_OPENCV 640 512 810 805 321 255 -0.1 0.02 0.001 -0.0005 0.003 0.01 0.002 -0.001
"""


def _points(n=200, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-0.35, 0.35, (n, 2)), rng.uniform(1.0, 10.0, n)])


def test_read_all_models_with_pixel_centre_shift(tmp_path):
    p = tmp_path / "cameras.txt"
    p.write_text(CAMERAS_TXT)
    cams = read_colmap_cameras(p)
    assert sorted(cams) == [1, 2, 3, 4, 5, 6]
    assert cams[1].model == "pinhole" and cams[1].param_dict == {"fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 239.5}
    assert cams[2].param_dict["cx"] == 320.0 and cams[2].param_dict["cy"] == 239.75
    assert cams[3].model == "opencv" and cams[3]["k1"] == -0.05 and cams[3]["k2"] == 0.0
    assert cams[4]["k2"] == 0.01 and cams[4].image_size == (640, 512)
    assert cams[5]["p2"] == -0.0005 and cams[5]["k3"] == 0.0
    assert cams[6]["k6"] == -0.001 and cams[6]["cx"] == 320.5
    # hand computation for SIMPLE_RADIAL (COLMAP: u = f x (1 + k r^2) + cx, centre at 0.5)
    x, y = 0.2, -0.1
    r2 = x * x + y * y
    u = 800 * x * (1 - 0.05 * r2) + 320 - 0.5
    v = 800 * y * (1 - 0.05 * r2) + 256 - 0.5
    np.testing.assert_allclose(cams[3].project([[x, y, 1.0]])[0], [u, v], atol=1e-12, rtol=0)  # measured 0


def test_projection_matches_pycolmap(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    p = tmp_path / "cameras.txt"
    p.write_text(CAMERAS_TXT)
    cams = read_colmap_cameras(p)
    pts = _points()
    for line in CAMERAS_TXT.splitlines():
        if line.startswith("#"):
            continue
        tok = line.split()
        ref = pycolmap.Camera(model=tok[1], width=int(tok[2]), height=int(tok[3]), params=[float(t) for t in tok[4:]])
        # COLMAP's pixel centre is at (0.5, 0.5): ours = COLMAP - 0.5, to rounding error
        np.testing.assert_allclose(cams[int(tok[0])].project(pts), ref.img_from_cam(pts) - 0.5, atol=5e-12, rtol=0)  # measured 5.7e-14 px


def test_write_read_round_trip_and_model_choice(tmp_path):
    cams = {
        3: Camera("pinhole", (320, 240), dict(fx=400.0, fy=401.0, cx=159.5, cy=119.5)),
        7: Camera("opencv", (640, 512), dict(fx=810.0, fy=805.0, cx=320.3, cy=255.7, k1=-0.1, k2=0.02, p1=1e-3, p2=-5e-4)),
        9: Camera("opencv", (640, 512), dict(fx=810.0, fy=805.0, cx=320.3, cy=255.7, k1=-0.1, k6=1e-3)),
    }
    path = write_colmap_cameras(tmp_path / "cameras.txt", cams)
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    assert [ln.split()[1] for ln in lines] == ["PINHOLE", "OPENCV", "FULL_OPENCV"]
    assert lines[0].split()[4:] == ["400.0", "401.0", "160.0", "120.0"]  # +0.5 on the way out
    back = read_colmap_cameras(path)
    for cid, cam in cams.items():
        np.testing.assert_array_equal(back[cid].params, cam.params)
        assert back[cid].model == cam.model and back[cid].image_size == cam.image_size


def test_write_refuses_photogrammetric_and_skew(tmp_path):
    photo = Camera("photogrammetric", (320, 240), dict(c_mm=17.0, x0_mm=0.1, y0_mm=0.0, K1=-3e-3), pixel_pitch_um=25)
    with pytest.raises(UnknownModelError, match=r"camera 1: the photogrammetric .* no COLMAP equivalent; convert it with"):
        write_colmap_cameras(tmp_path / "c.txt", [photo])
    skewed = Camera("opencv", (64, 48), dict(fx=50.0, fy=50.0, cx=31.5, cy=23.5, skew=0.25))
    with pytest.raises(InvalidInputError, match=r"camera 4: skew=0\.25 px is non-zero but COLMAP models have no skew"):
        write_colmap_cameras(tmp_path / "c.txt", {4: skewed})
    assert not (tmp_path / "c.txt").exists()  # nothing half-written


def test_bad_cameras_files(tmp_path):
    p = tmp_path / "cameras.txt"
    p.write_text("# header\n1 OPENCV_FISHEYE 640 480 500 500 320 240 0 0 0 0\n")
    with pytest.raises(UnknownModelError, match=r"cameras.txt:2: camera model 'OPENCV_FISHEYE' is a COLMAP model "
                                                 r"thermogrammetry does not support; expected one of SIMPLE_PINHOLE"):
        read_colmap_cameras(p)
    p.write_text("1 WEIRD 640 480 1 2 3\n")
    with pytest.raises(UnknownModelError, match=r"cameras.txt:1: camera model 'WEIRD' is an unknown COLMAP model"):
        read_colmap_cameras(p)
    p.write_text("1 OPENCV 640 480 500 500 320 240 0 0 0\n")
    with pytest.raises(CorruptFileError, match=r"cameras.txt:1: OPENCV needs 8 parameters \(fx fy cx cy k1 k2 p1 p2\), got 7"):
        read_colmap_cameras(p)
    p.write_text("1 PINHOLE 640 480 500 abc 320 240\n")
    with pytest.raises(CorruptFileError, match=r"cameras.txt:1: fy is 'abc'; expected a number"):
        read_colmap_cameras(p)
    p.write_text("1 PINHOLE 640 480 500 nan 320 240\n")
    with pytest.raises(CorruptFileError, match=r"cameras.txt:1: fy is 'nan'; expected a finite number"):
        read_colmap_cameras(p)
    p.write_text("1 PINHOLE 640.5 480 500 500 320 240\n")
    with pytest.raises(CorruptFileError, match=r"cameras.txt:1: WIDTH is '640.5'; expected an integer"):
        read_colmap_cameras(p)


def test_images_and_points_round_trip_and_pycolmap(tmp_path):
    rng = np.random.default_rng(3)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    xy = rng.uniform(0, 600, (5, 2))
    images = [ColmapImage(1, q, np.array([0.1, -0.2, 3.0]), 1, "IR_0001.jpg", xy, np.array([0, 1, -1, 2, 3])),
              ColmapImage(2, np.array([1.0, 0, 0, 0]), np.zeros(3), 1, "IR_0002.jpg")]
    pts = ColmapPoints3D(np.array([0, 1, 2, 3]), rng.normal(size=(4, 3)), np.array([[255, 0, 0]] * 4, dtype=np.uint8),
                         np.array([0.1, 0.2, 0.3, 0.4]), [np.array([[1, 0]]), np.array([[1, 1]]), np.array([[1, 3]]),
                                                           np.array([[1, 4]])])
    cam = Camera("opencv", (640, 512), dict(fx=810.0, fy=805.0, cx=320.3, cy=255.7, k1=-0.1))
    write_colmap_cameras(tmp_path / "cameras.txt", {1: cam})
    write_colmap_images(tmp_path / "images.txt", images)
    write_colmap_points3d(tmp_path / "points3D.txt", pts)
    ims = read_colmap_images(tmp_path / "images.txt")
    assert sorted(ims) == [1, 2] and ims[2].xy_px.shape == (0, 2)
    np.testing.assert_array_equal(ims[1].xy_px, xy)
    np.testing.assert_array_equal(ims[1].point3d_ids, [0, 1, -1, 2, 3])
    assert ims[1].name == "IR_0001.jpg"
    R = ims[1].R
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)
    back = read_colmap_points3d(tmp_path / "points3D.txt")
    np.testing.assert_array_equal(back.xyz, pts.xyz)
    assert [t.tolist() for t in back.tracks] == [[[1, 0]], [[1, 1]], [[1, 3]], [[1, 4]]]

    pycolmap = pytest.importorskip("pycolmap")
    rec = pycolmap.Reconstruction()
    rec.read_text(str(tmp_path))
    im = rec.images[1]
    # COLMAP holds 2D points with its +0.5 convention and the same cam_from_world rotation
    np.testing.assert_allclose(np.array([p.xy for p in im.points2D]), xy + 0.5, atol=1e-12, rtol=0)  # measured 0
    np.testing.assert_allclose(im.cam_from_world().rotation.matrix(), R, atol=1e-12, rtol=0)  # measured 0
    np.testing.assert_allclose(rec.cameras[1].params[2:4], [320.8, 256.2], atol=1e-12, rtol=0)  # measured 0
