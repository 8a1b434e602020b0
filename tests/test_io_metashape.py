"""Agisoft Metashape calibration XML: exact mapping (P1/P2 swap, centre offsets), K4 fit, errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from thermogrammetry import Camera
from thermogrammetry.errors import CorruptFileError, UnknownModelError, UnsupportedFormatError
from thermogrammetry.io.metashape import (
    MetashapeCalibration,
    read_metashape_calibration,
    read_metashape_xml,
    write_metashape_calibration,
)

XML = """<?xml version="1.0" encoding="UTF-8"?>
<calibration>
  <projection>frame</projection>
  <width>640</width>
  <height>512</height>
  <f>1123.5</f>
  <cx>-3.25</cx>
  <cy>4.5</cy>
  <b1>0.75</b1>
  <b2>{b2}</b2>
  <k1>-0.11</k1>
  <k2>0.07</k2>
  <k3>-0.02</k3>
  <k4>{k4}</k4>
  <p1>0.0012</p1>
  <p2>-0.0007</p2>
  <date>2024-05-01T10:00:00Z</date>
</calibration>
"""


def metashape_formula(points, w=640, h=512, f=1123.5, cx=-3.25, cy=4.5, b1=0.75, b2=0.0, k1=-0.11, k2=0.07,
                      k3=-0.02, k4=0.0, p1=0.0012, p2=-0.0007):
    """Metashape manual Appendix C, written out literally; (u, v) with the top-left pixel centre at (0.5, 0.5)."""
    x = points[:, 0] / points[:, 2]
    y = points[:, 1] / points[:, 2]
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3 + k4 * r2**4
    xp = x * rad + p1 * (r2 + 2 * x * x) + 2 * p2 * x * y
    yp = y * rad + p2 * (r2 + 2 * y * y) + 2 * p1 * x * y
    return np.column_stack([w * 0.5 + cx + xp * f + xp * b1 + yp * b2, h * 0.5 + cy + yp * f])


def pts_in_view(n=300, seed=1):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-0.28, 0.28, n), rng.uniform(-0.22, 0.22, n), rng.uniform(1, 30, n)])


def test_exact_mapping_p1_p2_swap_and_centre(tmp_path):
    p = tmp_path / "calib.xml"
    p.write_text(XML.format(b2=0.0, k4=0.0))
    conv = read_metashape_calibration(p)
    cam = conv.camera
    assert conv.max_residual_px == 0.0 and conv.success
    assert cam["p1"] == -0.0007 and cam["p2"] == 0.0012  # Metashape P1/P2 swapped relative to OpenCV
    assert cam["fx"] == 1123.5 + 0.75 and cam["fy"] == 1123.5
    assert cam["cx"] == 320 - 3.25 - 0.5 and cam["cy"] == 256 + 4.5 - 0.5
    pts = pts_in_view()
    ref = metashape_formula(pts) - 0.5  # to our pixel convention
    np.testing.assert_allclose(cam.project(pts), ref, atol=5e-12, rtol=0)  # measured 5.7e-14 px
    # and OpenCV itself agrees with the mapped coefficients
    K, dist = cam.to_opencv()
    ocv = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    np.testing.assert_allclose(ocv, ref, atol=5e-12, rtol=0)  # measured 5.7e-14 px


def test_skew_b2(tmp_path):
    p = tmp_path / "calib.xml"
    p.write_text(XML.format(b2=-1.5, k4=0.0))
    cam = read_metashape_calibration(p).camera
    assert cam["skew"] == -1.5
    pts = pts_in_view()
    np.testing.assert_allclose(cam.project(pts), metashape_formula(pts, b2=-1.5) - 0.5, atol=5e-12, rtol=0)  # measured 5.7e-14 px


def test_k4_is_fitted_and_residual_reported(tmp_path):
    p = tmp_path / "calib.xml"
    k4 = 4.0
    p.write_text(XML.format(b2=0.0, k4=k4))
    calib = read_metashape_xml(p)
    # the Metashape model itself: project/unproject round trip over the whole image
    u, v = np.meshgrid(np.linspace(-0.5, 639.5, 81), np.linspace(-0.5, 511.5, 65))
    xy = np.column_stack([u.ravel(), v.ravel()])
    rays = calib.unproject(xy)
    np.testing.assert_allclose(calib.project(rays), xy, atol=5e-12, rtol=0)  # measured 5.7e-14 px
    np.testing.assert_allclose(calib.project(rays), metashape_formula(rays, k4=k4) - 0.5, atol=1e-11, rtol=0)  # measured 1.1e-13 px
    conv = calib.to_camera()
    assert conv.success and "K4" in conv.outcome.reason
    # K4 r^8 moves the corners by ~0.5 px (r^2 ~ 0.13 there); the rational OpenCV fit absorbs most of it
    k4_effect = np.abs(metashape_formula(rays, k4=k4) - metashape_formula(rays, k4=0.0)).max()
    assert 0.05 < k4_effect < 2.0
    assert 0.0 < conv.max_residual_px < 0.5 * k4_effect
    # the reported maximum is what an independent, denser check finds (corners are on both grids)
    d = np.linalg.norm(conv.camera.project(rays) - xy, axis=1)
    assert d.max() == pytest.approx(conv.max_residual_px, rel=0.1, abs=1e-6)


def test_write_exact_and_read_back(tmp_path):
    cam = Camera("opencv", (640, 512), dict(fx=1124.25, fy=1123.5, cx=316.25, cy=260.0, skew=0.5, k1=-0.11,
                                            k2=0.07, k3=-0.02, p1=-7e-4, p2=1.2e-3))
    out = write_metashape_calibration(tmp_path / "out.xml", cam)
    assert out.max_residual_px == 0.0
    assert out.calibration.p1 == 1.2e-3 and out.calibration.p2 == -7e-4  # swapped on the way out
    text = (tmp_path / "out.xml").read_text()
    assert "<f>1123.5</f>" in text and "<b1>0.75</b1>" in text and "<cx>-3.25</cx>" in text
    back = read_metashape_calibration(tmp_path / "out.xml").camera
    np.testing.assert_allclose(back.params, cam.params, rtol=1e-15, atol=1e-15)


def test_write_photogrammetric_camera_by_fit(tmp_path):
    # seed 001 Table 2 FLIR A320 in the correction form: Metashape's forward model is fitted
    flir = Camera("photogrammetric", (320, 240), dict(c_mm=17.2262, x0_mm=0.2883, y0_mm=-0.1995, K1=-30.6381e-4,
                                                      K2=2599.4545e-7, K3=-98791.5437e-10, P1=-22.6353e-5,
                                                      P2=28.1114e-5), pixel_pitch_um=25.0)
    out = write_metashape_calibration(tmp_path / "flir.xml", flir)
    assert out.outcome.success and "no exact Metashape equivalent" in out.outcome.reason
    # forward polynomial K1..K4 cannot equal the correction polynomial exactly: a few px at the corners,
    # consistent with convert_camera's k1..k3 result (5.6 px) and better thanks to K4
    assert 0.1 < out.max_residual_px < 6.0
    back = read_metashape_xml(tmp_path / "flir.xml")
    u, v = np.meshgrid(np.linspace(-0.5, 319.5, 33), np.linspace(-0.5, 239.5, 25))
    xy = np.column_stack([u.ravel(), v.ravel()])
    d = np.linalg.norm(back.project(flir.unproject(xy)) - xy, axis=1)
    assert d.max() <= out.max_residual_px * 1.05 + 1e-9


def test_covariance_gives_standard_deviations(tmp_path):
    names = "f cx cy b1 k1 p1 p2"
    C = np.diag([4.0, 1.0, 2.25, 0.25, 1e-6, 1e-8, 4e-8])
    C[0, 3] = C[3, 0] = -0.5  # cov(f, b1)
    cov = f"<covariance><params>{names}</params><coeffs>{' '.join(map(repr, C.ravel().tolist()))}</coeffs></covariance>"
    p = tmp_path / "c.xml"
    p.write_text(XML.format(b2=0.0, k4=0.0).replace("<date>", cov + "<date>"))
    cam = read_metashape_calibration(p).camera
    std = dict(zip(cam.param_names, cam.param_std))
    assert std["fy"] == pytest.approx(2.0, rel=1e-12)
    assert std["fx"] == pytest.approx(np.sqrt(4.0 + 0.25 - 1.0), rel=1e-12)  # var(f + b1)
    assert std["p1"] == pytest.approx(2e-4, rel=1e-12) and std["p2"] == pytest.approx(1e-4, rel=1e-12)  # swapped
    assert np.isnan(std["k2"]) and np.isnan(std["skew"])  # fixed in Metashape: unknown


def test_legacy_photoscan_layout(tmp_path):
    p = tmp_path / "old.xml"
    p.write_text("<calibration><projection>frame</projection><width>100</width><height>80</height>"
                 "<fx>90.5</fx><fy>90</fy><cx>50.5</cx><cy>40</cy><skew>0.1</skew><k1>-0.1</k1>"
                 "<p1>1e-3</p1><p2>2e-3</p2></calibration>")
    cam = read_metashape_calibration(p).camera
    assert cam["fx"] == 90.5 and cam["fy"] == 90.0 and cam["skew"] == 0.1
    assert cam["cx"] == 50.0 and cam["cy"] == 39.5
    assert cam["p1"] == 1e-3 and cam["p2"] == 2e-3  # old Agisoft Lens formula uses OpenCV's order


@pytest.mark.parametrize(
    "body, error, message",
    [
        ("<f>1000</f><focal>3</focal>", UnsupportedFormatError, r"c.xml: unknown element <focal>; expected projection"),
        ("<f>abc</f>", CorruptFileError, r"c.xml: element <f> is 'abc'; expected a number"),
        ("<f>1000</f><p3>0.1</p3>", UnsupportedFormatError, r"element <p3> = 0.1: higher-order tangential"),
        ("<cx>0</cx>", CorruptFileError, r"c.xml: missing element <f> \(focal length in pixels\)"),
        ("<f>-5</f>", CorruptFileError, r"element <f> is -5.0; expected a positive focal length"),
    ],
)
def test_bad_files(tmp_path, body, error, message):
    p = tmp_path / "c.xml"
    p.write_text(f"<calibration><projection>frame</projection><width>64</width><height>48</height>{body}</calibration>")
    with pytest.raises(error, match=message):
        read_metashape_xml(p)


def test_bad_projection_and_xml(tmp_path):
    p = tmp_path / "c.xml"
    p.write_text("<calibration><projection>fisheye</projection><width>64</width><height>48</height><f>50</f></calibration>")
    with pytest.raises(UnknownModelError, match=r"c.xml: <projection> is 'fisheye'; only 'frame' cameras are supported"):
        read_metashape_xml(p)
    p.write_text("<calibration><f>50</calibration>")
    with pytest.raises(CorruptFileError, match=r"c.xml: not well-formed XML"):
        read_metashape_xml(p)
    p.write_text("<document><chunk/></document>")
    with pytest.raises(UnsupportedFormatError, match=r"root element is <document>; expected <calibration>"):
        read_metashape_xml(p)


def test_metashape_round_trip_of_own_model():
    calib = MetashapeCalibration(640, 512, f=1000.0, cx=2.0, cy=-1.0, k1=-0.1, k4=0.05, p1=1e-3)
    u, v = np.meshgrid(np.linspace(-0.5, 639.5, 41), np.linspace(-0.5, 511.5, 33))
    xy = np.column_stack([u.ravel(), v.ravel()])
    np.testing.assert_allclose(calib.project(calib.unproject(xy)), xy, atol=5e-12, rtol=0)  # measured 5.7e-14 px
