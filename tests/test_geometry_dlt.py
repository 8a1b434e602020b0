"""DLT: exact 3×4 cameras, additional parameters (seed 000 eq. 2–4), precision, bad input."""

import numpy as np
import pytest

from thermogrammetry.errors import DegenerateInputError, InvalidInputError, NonFiniteError, ShapeError, TooFewPointsError
from thermogrammetry.geometry import Pose, decompose_projection, dlt, dlt_linear, project_points, triangulate
from thermogrammetry.geometry import rotations as rot
from thermogrammetry.results import Termination

# Middlebury "temple" style camera: K from templeR_par.txt-like values, object ~0.15 m at ~0.6 m
K_MB = np.array([[1520.4, 0.0, 302.32], [0.0, 1525.9, 246.87], [0.0, 0.0, 1.0]])


def _points(rng, n, half=0.08, center=(0.0, 0.0, 0.0)):
    return np.asarray(center) + rng.uniform(-half, half, (n, 3))


@pytest.mark.parametrize("additional", [(), ("K1", "K2", "P1", "P2")])
def test_exact_3x4_cameras_reproduce_projections(rng, additional):
    worst = 0.0
    for k in range(3):
        pose = Pose.look_at(rng.normal(size=3) * 0.2 + [0.0, -0.6, 0.1], rng.normal(size=3) * 0.01)
        P = 7.3 * (K_MB @ pose.matrix())  # a raw 3×4 camera, arbitrary scale
        X = _points(rng, 25)
        xh = np.hstack([X, np.ones((25, 1))]) @ P.T
        xy = xh[:, :2] / xh[:, 2:]
        r = dlt(X, xy, additional=additional)
        assert r.termination is Termination.CONVERGED
        # the decomposed camera (K, R, X0) reproduces the projections to rounding; bounds ~50-100x the
        # figures measured (worst over the cases) in the comments
        err = np.abs(project_points(r.K, r.pose, X) - xy).max()
        worst = max(worst, err)
        assert err < 5e-11  # measured 5.1e-13 px
        assert np.abs(r.project(X) - xy).max() < 1e-11  # measured 1.7e-13 px
        assert np.allclose(r.K, K_MB, rtol=0, atol=1e-10)  # measured 1.9e-12 px
        assert np.abs(r.center - pose.center).max() < 1e-13  # measured 1.6e-15 m
        assert np.abs(r.R - pose.R).max() < 5e-13  # measured 7.7e-15
        assert np.allclose(r.L, (P / P[2, 3]).ravel()[:11], rtol=5e-12, atol=5e-16)  # measured 1.8e-12 abs
        for v in r.additional.values():
            assert abs(v) < 1e-16  # measured 1.3e-18
    print(f"max reprojection error of decomposed cameras: {worst:.2e} px")


def _apply_correction_form(ideal, x0, y0, K1, K2, P1, P2):
    """Measured coordinates x with x + Δx(x) = ideal (Brown 1971, correction form), Newton by hand."""
    x = ideal.copy()
    for _ in range(50):
        xb, yb = x[:, 0] - x0, x[:, 1] - y0
        r2 = xb**2 + yb**2
        rad = K1 * r2 + K2 * r2**2
        f = np.stack([xb * rad + P1 * (r2 + 2 * xb**2) + 2 * P2 * xb * yb,
                      yb * rad + 2 * P1 * xb * yb + P2 * (r2 + 2 * yb**2)], 1) + x - ideal
        h = 1e-4  # numerical 2×2 Jacobian is plenty for this generator
        J = np.empty((len(x), 2, 2))
        for j in range(2):
            e = np.zeros(2)
            e[j] = h
            xp = x + e
            xb, yb = xp[:, 0] - x0, xp[:, 1] - y0
            r2 = xb**2 + yb**2
            rad = K1 * r2 + K2 * r2**2
            fp = np.stack([xb * rad + P1 * (r2 + 2 * xb**2) + 2 * P2 * xb * yb,
                           yb * rad + 2 * P1 * xb * yb + P2 * (r2 + 2 * yb**2)], 1) + xp - ideal
            J[:, :, j] = (fp - f) / h
        x = x - np.linalg.solve(J, f[..., None])[..., 0]
    return x


def test_refinement_recovers_additional_parameters(rng):
    # thermal-camera-like: 320×240, 25 µm pitch, strong barrel distortion (≈ 6 px at the corners)
    K = np.array([[720.0, 0.0, 162.0], [0.0, 720.0, 118.5], [0.0, 0.0, 1.0]])
    pose = Pose.look_at([0.3, -3.0, 0.5], [0.0, 0.0, 0.0])
    X = rng.uniform(-0.6, 0.6, (60, 3))
    ideal = project_points(K, pose, X)
    truth = dict(K1=-4e-7, K2=2e-12, P1=3e-6, P2=-2e-6)
    xy = _apply_correction_form(ideal, K[0, 2], K[1, 2], **truth)
    assert np.abs(xy - ideal).max() > 3.0  # distortion is not negligible
    lin = dlt(X, xy, refine=True)
    assert lin.rms_px > 0.1  # plain DLT cannot absorb it
    r = dlt(X, xy, additional=("K1", "K2", "P1", "P2"), image_size=(320, 240), pixel_pitch_um=25.0)
    assert r.termination is Termination.CONVERGED, r.reason
    assert r.rms_px < 1e-12  # measured 1.9e-14 px
    for k, v in truth.items():
        assert abs(r.additional[k] / v - 1) < 5e-11, (k, r.additional[k], v)  # measured 6.1e-13
    assert np.abs(r.project(X) - xy).max() < 5e-12  # measured 5.7e-14 px
    assert np.allclose(r.K, K, rtol=0, atol=1e-10)  # measured 1.2e-12 px
    # published units (mm, y up): K1_mm = K1_px / pitch², P2 flips sign with the y axis
    a = 0.025
    # measured relative errors 1.9e-14 (K1) and 6.1e-13 (P2); c, x0, y0: 3.6e-15, 2.8e-15, 3.0e-14 mm
    assert abs(r.additional_mm["K1"] - truth["K1"] / a**2) < 1e-12 * abs(truth["K1"] / a**2) + 1e-18
    assert abs(r.additional_mm["P2"] + truth["P2"] / a) < 5e-11 * abs(truth["P2"] / a)
    assert abs(r.values["c_mm"] - 720 * a) < 2e-13
    assert abs(r.values["x0_mm"] - (162.0 - 159.5) * a) < 2e-13
    assert abs(r.values["y0_mm"] + (118.5 - 119.5) * a) < 2e-12


def test_dlt_monte_carlo_centre_and_focal_std():
    # 200 seeded runs, σ = 0.3 px; reported a-priori σ of X0, Y0, Z0 and c vs scatter
    rng = np.random.default_rng(2024)
    pose = Pose.look_at([0.5, -4.0, 1.0], [0.0, 0.0, 0.0])
    K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
    X = rng.uniform(-1, 1, (15, 3))
    xy = project_points(K, pose, X)
    sig = 0.3
    est, rep = [], []
    for _ in range(200):
        r = dlt(X, xy + rng.normal(0, sig, xy.shape), sigma_px=sig)
        assert r.success
        est.append([r.values[k] for k in ("X0", "Y0", "Z0", "c_px")])
        rep.append([r.std_prior[k] for k in ("X0", "Y0", "Z0", "c_px")])
    ratio = np.std(est, axis=0, ddof=1) / np.mean(rep, axis=0)
    # 200 runs: sampling error of a std ≈ 1/√398 = 5 %; ±20 % is 4σ
    assert np.all(np.abs(ratio - 1) < 0.2), ratio
    print("DLT MC scatter / reported σ (X0, Y0, Z0, c):", np.round(ratio, 3))


def test_seed000_table1_control_and_pass_points():
    """Seed 000 Table 1: two video cameras at ≈ 2 m oriented by DLT on the 6 control points,
    pass points triangulated (synthetic exact image coordinates)."""
    ctrl = np.array([[1.7715, 2.8925, 1.1060], [2.0655, 2.8910, 1.1065], [1.7280, 3.2165, 1.1670],
                     [2.1120, 3.2140, 1.1670], [1.7450, 2.9905, 0.7845], [2.0955, 2.9835, 0.7845]])
    passp = np.array([[1.7705, 2.9070, 0.8485], [2.0655, 2.9055, 0.8490], [1.7260, 3.2310, 0.8620],
                      [1.9185, 3.1430, 1.1635], [2.1160, 3.2290, 0.8625], [1.7955, 2.8965, 1.0005],
                      [2.0410, 2.8940, 1.0010], [1.8520, 2.8920, 0.9240], [1.9900, 2.8900, 0.9245],
                      [1.7180, 3.2170, 1.1810], [2.1220, 3.2140, 1.1820]])
    K = np.array([[1000.0, 0.0, 383.5], [0.0, 1000.0, 287.5], [0.0, 0.0, 1.0]])  # 768×576 video
    target = ctrl.mean(0)
    poses = [Pose.look_at(target + [-0.5, -1.9, 0.4], target), Pose.look_at(target + [0.5, -1.9, 0.4], target)]
    res = [dlt(ctrl, project_points(K, p, ctrl)) for p in poses]
    assert all(r.termination is Termination.CONVERGED for r in res)
    for r, p in zip(res, poses):
        assert np.abs(r.center - p.center).max() < 2e-12  # measured 2.1e-14 m
    xy = np.stack([project_points(K, p, passp) for p in poses])
    tri = triangulate([r.K for r in res], [r.pose for r in res], xy)
    assert np.abs(tri.points - passp).max() < 2e-13  # measured 2.2e-15 m


def test_bad_input_errors(rng):
    X = rng.uniform(-1, 1, (8, 3))
    xy = rng.uniform(0, 100, (8, 2))
    with pytest.raises(TooFewPointsError, match=r"at least 6 control points.*got 5"):
        dlt(X[:5], xy[:5])
    Xp = X.copy()
    Xp[:, 2] = 0.3
    with pytest.raises(DegenerateInputError) as ei:
        dlt(Xp, xy)
    msg = str(ei.value)
    assert "coplanar" in msg and "singular" in msg and "resection" in msg and "interior orientation" in msg
    with pytest.raises(DegenerateInputError, match="coplanar"):
        dlt_linear(Xp, xy)
    bad = xy.copy()
    bad[3, 1] = np.nan
    with pytest.raises(NonFiniteError, match=r"xy_px.*\(3, 1\)"):
        dlt(X, bad)
    badX = X.copy()
    badX[0, 0] = np.inf
    with pytest.raises(NonFiniteError, match="points_world"):
        dlt(badX, xy)
    with pytest.raises(ShapeError, match=r"points_world: expected shape \(N, 3\)"):
        dlt(X[:, :2], xy)
    with pytest.raises(ShapeError, match="points_world has 8 rows but xy_px has 7"):
        dlt(X, xy[:7])
    with pytest.raises(InvalidInputError, match="K9"):
        dlt(X, xy, additional=("K1", "K9"))
    with pytest.raises(TooFewPointsError, match="12 equations for 13 unknowns"):
        dlt(X[:6], xy[:6], additional=("K1", "K2"))


def test_decompose_projection_signs(rng):
    R = rot.matrix_from_axis_angle(rng.normal(size=3))
    C = rng.normal(size=3)
    P = K_MB @ np.hstack([R, (-R @ C)[:, None]])
    for scale in (2.5, -0.01):  # negative scale must not flip the camera
        K, R2, C2 = decompose_projection(scale * P)
        assert np.allclose(K, K_MB, rtol=0, atol=5e-11)  # measured 5.5e-13 px (skew)
        assert np.allclose(R2, R, rtol=0, atol=2e-14)  # measured 3.9e-16
        assert np.allclose(C2, C, rtol=0, atol=2e-14)  # measured 2.9e-16 m


def test_dlt_recovers_flir_a320_correction_form_exactly(rng):
    """The DLT's additional parameters are the correction form of conventions.md: on projections of the
    seed 001 Table 2 FLIR A320 camera (Camera 'photogrammetric') the DLT returns c, x0, y0, K1..K3,
    P1, P2 in the published units, and to_camera() rebuilds a camera that reproduces the images."""
    from thermogrammetry import Camera

    a320 = dict(c_mm=17.2262, x0_mm=0.2883, y0_mm=-0.1995, K1=-30.6381e-4, K2=2599.4545e-7,
                K3=-98791.5437e-10, P1=-22.6353e-5, P2=28.1114e-5)
    cam = Camera("photogrammetric", (320, 240), a320, pixel_pitch_um=25.0)
    pose = Pose.look_at([0.4, -3.0, 0.6], [0.0, 0.0, 0.0])
    X = rng.uniform(-0.8, 0.8, (200, 3))
    xy = cam.project(pose.transform(X))
    inside = np.all((xy > 0) & (xy < [319, 239]), axis=1)
    X, xy = X[inside][:40], xy[inside][:40]
    r = dlt(X, xy, additional=("K1", "K2", "K3", "P1", "P2"), image_size=(320, 240), pixel_pitch_um=25.0)
    assert r.termination is Termination.CONVERGED and r.rms_px < 1e-12, r.rms_px  # measured 1.9e-14 px
    for k in ("c_mm", "x0_mm", "y0_mm"):
        assert abs(r.values[k] - a320[k]) < 5e-13, k  # measured 7.1e-15 mm
    for k in ("K1", "K2", "K3", "P1", "P2"):
        assert abs(r.additional_mm[k] / a320[k] - 1) < 5e-12, (k, r.additional_mm[k], a320[k])  # measured 1.1e-13
    back = r.to_camera()
    assert back.model.value == "photogrammetric"
    assert np.abs(back.project(r.pose.transform(X)) - xy).max() < 5e-11  # measured 5.1e-13 px
    with pytest.raises(InvalidInputError, match="correction form"):
        r.to_camera("opencv")


def test_to_camera_opencv_with_skew(rng):
    K = np.array([[800.0, 1.5, 330.0], [0.0, 790.0, 245.0], [0.0, 0.0, 1.0]])
    pose = Pose.look_at([1.0, -6.0, 2.5], [0.2, 0.3, 0.4])
    X = rng.uniform(-1, 1, (20, 3))
    xy = project_points(K, pose, X)
    r = dlt(X, xy, image_size=(640, 480))
    cam = r.to_camera()
    assert cam.model.value == "opencv"
    assert np.abs(cam.project(r.pose.transform(X)) - xy).max() < 5e-11  # measured 5.7e-13 px
    r = dlt(X, xy, image_size=(640, 480), pixel_pitch_um=17.0)  # aspect ≠ 1 and skew carried by B1, B2
    assert np.abs(r.to_camera().project(r.pose.transform(X)) - xy).max() < 5e-11  # measured 5.7e-13 px


def test_L_coefficients_and_their_precision(rng):
    # std of L1..L11 from the refinement equals the textbook linearised precision of the
    # 11-parameter model in the original (unnormalised) frame: Q_L = (AᵀA)⁻¹ σ²
    K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
    pose = Pose.look_at([0.5, -4.0, 1.0], [0.0, 0.0, 0.0])
    X = rng.uniform(-1, 1, (12, 3))
    xy = project_points(K, pose, X)
    r = dlt(X, xy, sigma_px=0.5)
    L = np.array([r.values[f"L{i}"] for i in range(1, 12)])
    assert np.allclose(L, r.L, rtol=1e-12, atol=0)  # measured: identical
    den = X @ L[8:11] + 1
    A = np.zeros((24, 11))
    Xh = np.hstack([X, np.ones((12, 1))]) / den[:, None]
    A[0::2, 0:4] = Xh
    A[1::2, 4:8] = Xh
    A[0::2, 8:11] = -(xy[:, :1] * Xh[:, :3])
    A[1::2, 8:11] = -(xy[:, 1:] * Xh[:, :3])
    std_ref = 0.5 * np.sqrt(np.diag(np.linalg.inv(A.T @ A)))
    std = np.array([r.std_prior[f"L{i}"] for i in range(1, 12)])
    assert np.allclose(std, std_ref, rtol=1e-7, atol=0), std / std_ref
