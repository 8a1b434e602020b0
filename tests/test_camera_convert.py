"""Conversion between the forward and correction forms by a least-squares fit over the whole image."""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry import Camera
from thermogrammetry.camera import CameraConversion, convert_camera
from thermogrammetry.errors import ConfigError, InvalidInputError

FLIR_A320 = dict(  # seed 001 Table 2 (see tests/test_camera.py)
    c_mm=17.2262, x0_mm=0.2883, y0_mm=-0.1995,
    K1=-30.6381e-4, K2=2599.4545e-7, K3=-98791.5437e-10,
    P1=-22.6353e-5, P2=28.1114e-5,
)


def flir() -> Camera:
    return Camera("photogrammetric", (320, 240), FLIR_A320, pixel_pitch_um=25.0)


def dense_residual(src: Camera, dst: Camera, step: float = 0.5):
    """Independent check of a conversion on a denser grid than the fit used."""
    w, h = src.image_size
    u, v = np.meshgrid(np.arange(-0.5, w - 0.5 + 1e-9, step), np.arange(-0.5, h - 0.5 + 1e-9, step))
    xy = np.column_stack([u.ravel(), v.ravel()])
    d = np.linalg.norm(dst.project(src.unproject(xy)) - xy, axis=1)
    return d.max(), np.sqrt(np.mean(d * d))


def test_identity_conversions_are_exact():
    cam = flir().replace(K4=2e-7, B1=1e-3, B2=-5e-4)
    res = convert_camera(cam, "photogrammetric")
    assert isinstance(res, CameraConversion) and res.success
    assert res.max_residual_px < 5e-12  # measured 8.6e-14 px
    np.testing.assert_allclose(res.camera.params, cam.params, rtol=1e-13, atol=1e-16)  # measured 2.8e-17 abs
    ocv = Camera("opencv", (640, 480), dict(fx=600.0, fy=602.0, cx=318.0, cy=241.0, k1=-0.12, k2=0.03, p1=3e-4,
                                            p2=-2e-4, k3=-0.004, k4=0.02, k5=-0.003, k6=1e-3))
    res = convert_camera(ocv, "opencv")
    assert res.max_residual_px < 1e-11  # measured 1.3e-13 px


def test_flir_a320_to_opencv_reports_its_residual():
    src = flir()
    res = convert_camera(src, "opencv", rational=False)
    assert res.success and res.n_points == 65 * 49
    # The correction polynomial of Table 2 has no exact forward k1..k3 equivalent: the best fit
    # leaves ~5.6 px at the extreme corners (0.21 px RMS). The report must say so, and the
    # independent dense check must find the same maximum (the worst point is a corner, on both grids).
    assert 3.0 < res.max_residual_px < 8.0
    assert 0.1 < res.rms_residual_px < 0.4
    dmax, drms = dense_residual(src, res.camera)
    assert dmax == pytest.approx(res.max_residual_px, rel=0.05)
    assert drms == pytest.approx(res.rms_residual_px, rel=0.25)
    # principal point and focal length are those of the source to a few tenths of a pixel
    np.testing.assert_allclose(res.camera.K[:2, 2], src.K[:2, 2], atol=0.5)
    np.testing.assert_allclose(np.diag(res.camera.K)[:2], np.diag(src.K)[:2], rtol=0.01)
    # by default the rational terms are tried: unbounded they reach ~1.2 px, but only with cancelling
    # coefficients (k2 ~ 2000, k3 ~ -19000: |k_i r_max^2i| ~ 12); bounded (regularised, denominator
    # > 0.5) they do not beat k1..k3, so the well-conditioned k1..k3 fit is kept and its residual reported
    auto = convert_camera(src, "opencv")
    assert "ill-conditioned" in auto.outcome.reason
    assert all(abs(v) <= 1.0 for v in auto.kappa.values()), auto.kappa
    assert auto.max_residual_px == pytest.approx(res.max_residual_px, rel=0.05)
    dmax, _ = dense_residual(src, auto.camera)
    assert dmax == pytest.approx(auto.max_residual_px, rel=0.05)


def test_area_residual_and_well_conditioned_mild_camera():
    """Residuals over the data area are reported besides the whole frame; a normal camera's plain
    fit is not touched by the conditioning rule (exact round trip)."""
    ocv = Camera("opencv", (640, 512), dict(fx=440.0, fy=440.0, cx=320.0, cy=256.0, k1=-0.25, k2=0.05, k3=-0.002,
                                            p1=1e-4, p2=-2e-4))
    u, v = np.meshgrid(np.linspace(100, 540, 12), np.linspace(80, 430, 10))
    area = np.column_stack([u.ravel(), v.ravel()])
    res = convert_camera(ocv, "opencv", area_px=area)
    assert res.max_residual_px < 1e-11 and res.area_max_residual_px < 1e-11  # measured 9.7e-14 px
    np.testing.assert_allclose(res.camera.params, ocv.params, atol=1e-12, rtol=0)  # measured 0 (parameters unchanged)
    src = flir()
    c = convert_camera(src, "opencv", rational=False, area_px=np.array([[80.0, 60.0], [240.0, 60.0], [240.0, 180.0], [80.0, 180.0]]))
    # the central half of the frame converts far better than the corners
    assert c.area_max_residual_px < 0.2 * c.max_residual_px
    assert c.area_rms_residual_px < c.rms_residual_px
    s = c.summary()
    assert s["area_max_residual_px"] == pytest.approx(c.area_max_residual_px) and s["kappa"]["k1"] is not None


def test_mild_distortion_converts_both_ways_to_small_residual():
    # A mild, physically typical forward camera (~3 px at the corners): both forms represent it well.
    ocv = Camera("opencv", (640, 512), dict(fx=1000.0, fy=1000.0, cx=322.0, cy=250.0, k1=-0.08, k2=0.05,
                                            p1=2e-4, p2=-1e-4), pixel_pitch_um=17.0)
    to_photo = convert_camera(ocv, "photogrammetric")
    assert to_photo.success and to_photo.max_residual_px < 0.01
    dmax, _ = dense_residual(ocv, to_photo.camera, step=2.0)
    assert dmax < 0.01
    c = to_photo.camera
    # first-order inverse relation: K1 ~= -k1 / c^2 (in mm^-2); the higher orders move it by 0.02 % here
    # (measured relative difference 2.0e-4)
    assert c["K1"] == pytest.approx(-(-0.08) / c["c_mm"] ** 2, rel=2e-3)
    assert c["c_mm"] == pytest.approx(1000.0 * 0.017, rel=3e-6)  # measured 2.7e-7 relative (4.6e-6 mm)
    back = convert_camera(c, "opencv")
    assert back.max_residual_px < 0.01
    np.testing.assert_allclose(back.camera.params[:4], ocv.params[:4], atol=1e-4)  # measured 5.2e-6 px


def test_to_pinhole_residual_is_the_distortion():
    src = flir()
    res = convert_camera(src, "pinhole")
    assert 10.0 < res.max_residual_px < 25.0  # corners are displaced ~17 px by the distortion


def test_conversion_bad_input():
    ocv = Camera("pinhole", (64, 48), dict(fx=50.0, fy=50.0, cx=31.5, cy=23.5))
    with pytest.raises(InvalidInputError, match=r"photogrammetric target needs pixel_pitch_um"):
        convert_camera(ocv, "photogrammetric")
    with pytest.raises(ConfigError, match=r"free: unknown parameter\(s\) 'K1' for model 'opencv'"):
        convert_camera(ocv, "opencv", free=["fx", "K1"])
    with pytest.raises(InvalidInputError, match=r"grid_step_px: must be positive, got -1"):
        convert_camera(ocv, "opencv", grid_step_px=-1)
