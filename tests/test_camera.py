"""Camera models: round trips, agreement with OpenCV, analytic Jacobians, bad input."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from thermogrammetry import Camera
from thermogrammetry.camera import CameraModel
from thermogrammetry.camera import models as M
from thermogrammetry.errors import ConfigError, InvalidInputError, NonFiniteError, ShapeError, UnknownModelError

# Seed 001 (Yastikli & Guler 2013), Table 2: FLIR A320, 320x240 px, 25 um pitch. Table values with
# their printed powers of ten; units per conventions.md (K1 mm^-2, K2 mm^-4, K3 mm^-6, P mm^-1).
FLIR_A320 = dict(
    c_mm=17.2262, x0_mm=0.2883, y0_mm=-0.1995,
    K1=-30.6381e-4, K2=2599.4545e-7, K3=-98791.5437e-10,
    P1=-22.6353e-5, P2=28.1114e-5,
)


def flir_a320() -> Camera:
    return Camera("photogrammetric", (320, 240), FLIR_A320, pixel_pitch_um=25.0, name="FLIR A320 (seed 001)")


def full_grid(w: int, h: int, step: float = 0.5) -> np.ndarray:
    """Every half pixel over the whole image, borders of the outer pixels included."""
    u, v = np.meshgrid(np.arange(-0.5, w - 0.5 + 1e-9, step), np.arange(-0.5, h - 0.5 + 1e-9, step))
    return np.column_stack([u.ravel(), v.ravel()])


def random_opencv_camera(rng: np.random.Generator, w=640, h=480) -> Camera:
    """A random but physically plausible OpenCV camera with all of k1..k6, p1, p2 non-zero.

    Draws are repeated until the distortion is one-to-one over the whole image (a real lens's is;
    random coefficients can fold the image corners back, where no inverse exists).
    """
    while True:
        cam = _draw_opencv_camera(rng, w, h)
        if np.all(np.isfinite(cam.unproject(full_grid(w, h, step=8.0)))):
            return cam


def _draw_opencv_camera(rng, w, h):
    f = rng.uniform(400, 900)
    params = dict(
        fx=f, fy=f * rng.uniform(0.97, 1.03), cx=w / 2 + rng.uniform(-20, 20), cy=h / 2 + rng.uniform(-20, 20),
        k1=rng.uniform(-0.3, 0.1), k2=rng.uniform(-0.05, 0.1), p1=rng.uniform(-2e-3, 2e-3), p2=rng.uniform(-2e-3, 2e-3),
        k3=rng.uniform(-0.02, 0.02), k4=rng.uniform(-0.05, 0.05), k5=rng.uniform(-0.02, 0.02), k6=rng.uniform(-0.01, 0.01),
    )
    return Camera("opencv", (w, h), params)


def points_in_view(cam: Camera, rng: np.random.Generator, n: int) -> np.ndarray:
    """Camera-frame points that image inside the frame, at depths 0.5 .. 20."""
    w, h = cam.image_size
    xy = np.column_stack([rng.uniform(-0.5, w - 0.5, n), rng.uniform(-0.5, h - 0.5, n)])
    return cam.unproject(xy) * rng.uniform(0.5, 20.0, n)[:, None]


# --------------------------------------------------------------------------- round trips
def test_flir_a320_distortion_is_strong():
    # guard: the round-trip test below is meaningful only if distortion is pixels, not a rounding error
    cam = flir_a320()
    xy = full_grid(*cam.image_size, step=1.0)
    shift = np.linalg.norm(cam.undistort(xy) - xy, axis=1)
    assert 10.0 < shift.max() < 30.0  # about 17.4 px at the corners for Table 2's values


def test_flir_a320_round_trip_whole_image_below_1e11_px():
    cam = flir_a320()
    xy = full_grid(*cam.image_size)  # 641 x 481 points, corners included
    rays = cam.unproject(xy)
    np.testing.assert_allclose(rays[:, 2], 1.0)
    depth = np.random.default_rng(1).uniform(0.3, 50.0, len(xy))[:, None]
    back = cam.project(rays * depth)
    err = np.abs(back - xy).max()
    assert np.all(np.isfinite(back))
    assert err < 1e-11, err  # measured 1.4e-13 px


def test_flir_a320_project_then_unproject():
    cam = flir_a320()
    rng = np.random.default_rng(2)
    pts = points_in_view(cam, rng, 5000)
    xy = cam.project(pts)
    rays = cam.unproject(xy)
    # normalised-ray error scaled to pixels by the focal length in px (689 px)
    err_px = np.abs(rays[:, :2] - pts[:, :2] / pts[:, 2:3]).max() * cam.K[0, 0]
    assert err_px < 5e-12, err_px  # measured 9.6e-14 px


def test_photogrammetric_with_all_terms_round_trip():
    cam = flir_a320().replace(K4=2e-7, K5=-3e-9, B1=1.5e-3, B2=-8e-4)
    xy = full_grid(*cam.image_size)
    back = cam.project(cam.unproject(xy) * 7.0)
    assert np.abs(back - xy).max() < 1e-11  # measured 1.1e-13 px


def test_opencv_round_trip_whole_image(rng):
    for _ in range(5):
        cam = random_opencv_camera(rng)
        xy = full_grid(*cam.image_size, step=2.0)
        rays = cam.unproject(xy)
        assert np.all(np.isfinite(rays))
        back = cam.project(rays * 3.0)
        assert np.abs(back - xy).max() < 1e-11  # measured 2.3e-13 px (worst of 5)


def test_distort_undistort_inverse():
    for cam in (flir_a320(), random_opencv_camera(np.random.default_rng(5))):
        xy = full_grid(*cam.image_size, step=4.0)
        ideal = cam.undistort(xy)
        np.testing.assert_allclose(cam.distort(ideal), xy, atol=1e-11, rtol=0)  # measured 2.3e-13 px


def test_photogrammetric_unproject_matches_hand_computation():
    # one pixel computed by hand from the correction-form formula in conventions.md
    p = FLIR_A320
    cam = flir_a320()
    u, v = 300.0, 20.0
    x = (u - 159.5) * 0.025 - p["x0_mm"]
    y = -(v - 119.5) * 0.025 - p["y0_mm"]
    r2 = x * x + y * y
    dr = p["K1"] * r2 + p["K2"] * r2**2 + p["K3"] * r2**3
    dx = x * dr + p["P1"] * (r2 + 2 * x * x) + 2 * p["P2"] * x * y
    dy = y * dr + 2 * p["P1"] * x * y + p["P2"] * (r2 + 2 * y * y)
    expect = [(x + dx) / p["c_mm"], -(y + dy) / p["c_mm"], 1.0]
    np.testing.assert_allclose(cam.unproject([[u, v]])[0], expect, rtol=1e-14, atol=1e-15)


def test_ideal_K_of_photogrammetric_camera():
    K = flir_a320().K
    np.testing.assert_allclose(K[0, 0], 17.2262 / 0.025, rtol=1e-14)
    np.testing.assert_allclose(K[0, 2], 159.5 + 0.2883 / 0.025, rtol=1e-14)
    np.testing.assert_allclose(K[1, 2], 119.5 + 0.1995 / 0.025, rtol=1e-14)  # y up in mm -> +rows


# --------------------------------------------------------------------------- OpenCV agreement
def test_project_agrees_with_cv2_projectPoints():
    rng = np.random.default_rng(20261122)
    worst = 0.0
    for _ in range(25):
        cam = random_opencv_camera(rng)
        pts = points_in_view(cam, rng, 400)
        K, dist = cam.to_opencv()
        assert dist.shape == (8,)
        ref = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
        worst = max(worst, np.abs(cam.project(pts) - ref).max())
    assert worst < 1e-11, worst  # measured 2.3e-13 px


def test_unproject_agrees_with_cv2_undistortPoints():
    # cv2.undistortPoints iterates a fixed number of times; with a tight criterion it agrees to rounding
    # (measured 2.2e-16 in normalised coordinates, i.e. ~1e-13 px)
    rng = np.random.default_rng(7)
    cam = random_opencv_camera(rng)
    xy = full_grid(*cam.image_size, step=16.0)
    K, dist = cam.to_opencv()
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    ref = cv2.undistortPoints(xy.reshape(-1, 1, 2), K, dist, R=np.eye(3), P=np.eye(3), criteria=crit).reshape(-1, 2)
    np.testing.assert_allclose(cam.unproject(xy)[:, :2], ref, atol=2e-14, rtol=0)


def test_from_opencv_to_opencv_round_trip():
    K = np.array([[500.0, 0.0, 320.0], [0.0, 505.0, 240.0], [0.0, 0.0, 1.0]])
    for dist in ([0.1, -0.2, 1e-3, 2e-3], [0.1, -0.2, 1e-3, 2e-3, 0.05],
                 [0.1, -0.2, 1e-3, 2e-3, 0.05, 0.01, 0.02, 0.03],
                 [0.1, -0.2, 1e-3, 2e-3, 0.05, 0.01, 0.02, 0.03, 0, 0, 0, 0],
                 [0.1, -0.2, 1e-3, 2e-3, 0.05, 0.01, 0.02, 0.03, 0, 0, 0, 0, 0, 0]):
        cam = Camera.from_opencv(K, np.array(dist).reshape(1, -1), (640, 480))
        K2, d2 = cam.to_opencv()
        np.testing.assert_array_equal(K2, K)
        want = np.zeros(8)
        want[: min(len(dist), 8)] = dist[:8]
        np.testing.assert_array_equal(np.pad(d2, (0, 8 - len(d2))), want)
        assert len(d2) == (8 if np.any(want[5:]) else 5)


def test_from_opencv_rejects_thin_prism_and_tilt():
    K = np.eye(3)
    K[0, 0] = K[1, 1] = 500
    with pytest.raises(InvalidInputError, match=r"thin-prism/tilt terms .* must be 0, got s2=0\.001"):
        Camera.from_opencv(K, [0, 0, 0, 0, 0, 0, 0, 0, 0, 1e-3, 0, 0], (640, 480))
    with pytest.raises(InvalidInputError, match=r"got tauY=0\.01"):
        Camera.from_opencv(K, [0] * 13 + [0.01], (640, 480))
    with pytest.raises(ShapeError, match=r"dist: expected 4, 5, 8, 12 or 14 coefficients .* got 6"):
        Camera.from_opencv(K, [0] * 6, (640, 480))
    with pytest.raises(InvalidInputError, match=r"K: expected \[\[fx, s, cx\], \[0, fy, cy\], \[0, 0, 1\]\]"):
        Camera.from_opencv(np.ones((3, 3)), [0] * 5, (640, 480))


def test_to_opencv_refuses_photogrammetric_and_skew():
    with pytest.raises(UnknownModelError, match="convert_camera"):
        flir_a320().to_opencv()
    cam = random_opencv_camera(np.random.default_rng(3)).replace(skew=0.5)
    with pytest.raises(InvalidInputError, match=r"skew=0\.5 px is non-zero"):
        cam.to_opencv()


# --------------------------------------------------------------------------- Jacobians
def _check_jacobians(cam: Camera, pts: np.ndarray) -> None:
    """Analytic Jacobians vs central differences, relative 1e-7 (parameters) / 1e-8 (points) per column.

    Steps are chosen so that each perturbation moves the image by about 1e-3 px: truncation error
    (~h^2) and rounding error (~1e-13 px / 1e-3 px = 1e-10) stay below the bounds; measured worst cases over
    the cameras tested: 7.3e-9 (parameters) and 1.7e-10 (point coordinates).
    """
    xy, Jp, Jt = cam.project_jacobian(pts)
    np.testing.assert_allclose(xy, cam.project(pts), atol=1e-12, rtol=0)
    assert Jp.shape == (len(pts), 2, 3) and Jt.shape == (len(pts), 2, len(cam.param_names))
    # point-only path (triangulation/resection): same projection and point Jacobian, no J_params;
    # both are the same arithmetic, so they agree to rounding (1e-12 relative)
    xy1, Jp1, none = cam.project_jacobian(pts, params=False)
    assert none is None
    xy2, Jp2 = cam.project_point_jacobian(pts)
    scale_p = np.abs(Jp).max()
    for a, b in ((xy1, xy), (xy2, xy)):
        np.testing.assert_allclose(a, b, atol=1e-12, rtol=0)
    for J in (Jp1, Jp2):
        assert J.shape == Jp.shape and np.abs(J - Jp).max() <= 1e-12 * scale_p
    p = cam.params
    for i, name in enumerate(cam.param_names):
        scale = np.abs(Jt[:, :, i]).max()
        assert scale > 0, f"{name}: Jacobian column is zero at the test points"
        h = 1e-3 / scale
        plus, minus = p.copy(), p.copy()
        plus[i] += h
        minus[i] -= h
        num = (cam.with_params(plus).project(pts) - cam.with_params(minus).project(pts)) / (2 * h)
        rel = np.abs(num - Jt[:, :, i]).max() / scale
        assert rel < 1e-7, (cam.model, name, rel)
    for k in range(3):
        scale = np.abs(Jp[:, :, k]).max()
        h = 1e-3 / scale
        d = np.zeros(3)
        d[k] = h
        num = (cam.project(pts + d) - cam.project(pts - d)) / (2 * h)
        rel = np.abs(num - Jp[:, :, k]).max() / scale
        assert rel < 1e-8, (cam.model, "XYZ"[k], rel)


def test_jacobians_pinhole(rng):
    cam = Camera("pinhole", (640, 480), dict(fx=512.0, fy=498.0, cx=321.3, cy=236.9))
    _check_jacobians(cam, points_in_view(cam, rng, 50))


def test_jacobians_opencv_all_parameters(rng):
    for _ in range(3):
        cam = random_opencv_camera(rng).replace(skew=rng.uniform(-2, 2))
        _check_jacobians(cam, points_in_view(cam, rng, 50))


def test_jacobians_photogrammetric_all_parameters(rng):
    # every parameter non-zero (K4, K5 as in seed 003's model; magnitudes keep the image single-valued)
    cam = flir_a320().replace(K4=2e-7, K5=-3e-9, B1=1.5e-3, B2=-8e-4)
    _check_jacobians(cam, points_in_view(cam, rng, 50))
    # anisotropic pixels
    cam2 = cam.replace(pixel_pitch_um=(25.0, 24.0))
    _check_jacobians(cam2, points_in_view(cam2, rng, 50))


# --------------------------------------------------------------------------- bad input
def test_unknown_model():
    with pytest.raises(UnknownModelError, match=r"unknown camera model 'fisheye'; expected one of 'pinhole', 'opencv', 'photogrammetric'"):
        Camera("fisheye", (640, 480), dict(fx=1, fy=1, cx=0, cy=0))
    assert CameraModel("OpenCV") is CameraModel.OPENCV


def test_nan_and_shapes():
    cam = Camera("pinhole", (640, 480), dict(fx=500.0, fy=500.0, cx=320.0, cy=240.0))
    with pytest.raises(NonFiniteError, match=r"points_cam: 1 non-finite value\(s\), first at index \(1, 2\)"):
        cam.project([[0, 0, 1], [0, 0, np.nan]])
    with pytest.raises(ShapeError, match=r"points_cam: expected shape \(N, 3\), got \(4, 2\)"):
        cam.project(np.zeros((4, 2)))
    with pytest.raises(ShapeError, match=r"xy_px: expected shape \(N, 2\), got \(5, 3\)"):
        cam.unproject(np.zeros((5, 3)))
    with pytest.raises(NonFiniteError, match=r"xy_px: .*inf"):
        cam.unproject([[np.inf, 0.0]])
    with pytest.raises(NonFiniteError, match=r"params\['fx'\]: expected a finite number, got nan"):
        Camera("pinhole", (640, 480), dict(fx=np.nan, fy=500.0, cx=320.0, cy=240.0))
    with pytest.raises(ShapeError, match=r"params: expected shape \(13,\) for model 'opencv'"):
        Camera("opencv", (640, 480), np.ones(12))


def test_bad_params():
    with pytest.raises(ConfigError, match=r"unknown parameter\(s\) 'k7' for model 'opencv'"):
        Camera("opencv", (640, 480), dict(fx=500.0, fy=500.0, cx=320.0, cy=240.0, k7=0.1))
    with pytest.raises(ConfigError, match=r"missing parameter\(s\) 'cy' for model 'pinhole'"):
        Camera("pinhole", (640, 480), dict(fx=500.0, fy=500.0, cx=320.0))
    with pytest.raises(InvalidInputError, match=r"pixel_pitch_um is required for the photogrammetric model"):
        Camera("photogrammetric", (320, 240), FLIR_A320)
    with pytest.raises(InvalidInputError, match=r"image_size: height must be a positive integer \(pixels\), got 0"):
        Camera("pinhole", (640, 0), dict(fx=500.0, fy=500.0, cx=320.0, cy=240.0))
    with pytest.raises(InvalidInputError, match=r"params\['c_mm'\]: must be positive, got -17\.0"):
        Camera("photogrammetric", (320, 240), {**FLIR_A320, "c_mm": -17.0}, pixel_pitch_um=25)


def test_newton_failure_is_nan_not_exception():
    # far outside the image the correction polynomial folds over: NaN marks the failed solve
    cam = flir_a320()
    xy, ok = M.photogrammetric_project_solve(cam.params, np.array([[0.0, 0.0, 1.0], [5.0, 5.0, 1.0]]),
                                             cam.image_size, cam.pixel_pitch_um)
    assert ok.tolist() == [True, False]
    assert np.all(np.isfinite(xy[0])) and np.all(np.isnan(xy[1]))


def test_params_layout_and_repr():
    cam = flir_a320().replace(param_std=dict(c_mm=0.1288, K1=4.6329e-4))
    assert cam.param_names == M.PARAM_NAMES[CameraModel.PHOTOGRAMMETRIC]
    assert cam["K1"] == pytest.approx(-30.6381e-4, rel=1e-15)
    assert np.isnan(cam.param_std[1]) and cam.param_std[0] == pytest.approx(0.1288, rel=1e-15)
    r = repr(cam)
    assert "model='photogrammetric'" in r and "c_mm=17.2262±0.13" in r and "K4" not in r
    assert not cam.params.flags.writeable
    import pickle

    back = pickle.loads(pickle.dumps(cam))
    assert back == cam and not back.params.flags.writeable
