"""Seed 000 close-range workflow on its synthetic replica (Table 1 coordinates, 0.5 px noise).

Tolerance bands: with R Monte-Carlo runs the relative standard error of an empirical standard
deviation is 1/sqrt(2R) (5 % for R = 200), so ±20 % is a 4-sigma band per coordinate.
"""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry import Camera
from thermogrammetry.closerange.solve import Observations, solve_network
from thermogrammetry.closerange.workflow import CloseRangeConfig, correct_thermal_image, estimate_planes
from thermogrammetry.errors import DegenerateInputError, TooFewPointsError
from thermogrammetry.synthetic.closerange import make_closerange_scene, measure, render_thermal

SIGMA = 0.5


@pytest.fixture(scope="module")
def scene():
    return make_closerange_scene()


def _thermal_camera(scene):
    c = scene.camera(scene.thermal)
    K = c.K
    return Camera("pinhole", c.image_size, {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]})


def _solve(scene, rng, known=None, sigma=SIGMA):
    rows = measure(scene, sigma, rng)
    return solve_network(scene.control, Observations.from_rows(rows, SIGMA), scene.thermal, known=known)


def test_replica_geometry(scene):
    # Table 1 and the set-up of seed 000: 6 control + 11 pass points, two optical cameras ~2 m away
    assert len(scene.control) == 6 and len(scene.passpoints) == 11
    centre = np.mean(list(scene.points.values()), axis=0)
    for cam in scene.cameras:
        assert 1.8 < np.linalg.norm(cam.pose.center - centre) < 2.3
        xy = cam.project(np.array(list(scene.points.values())))
        w, h = cam.image_size
        assert np.all((xy > 0) & (xy < [w - 1, h - 1]))


def test_noise_free_network_is_exact(scene):
    net = _solve(scene, np.random.default_rng(0), sigma=0.0)
    truth = np.array([scene.passpoints[i] for i in net.pass_ids])
    assert np.abs(net.points_world - truth).max() < 1e-9
    C, _ = net.thermal_center()
    assert np.abs(C - scene.camera("thermal").pose.center).max() < 1e-8


def test_monte_carlo_pass_points_and_thermal_centre(scene):
    rng = np.random.default_rng(2024)
    R = 200
    X, sig, Cs, sigC = [], [], [], []
    for _ in range(R):
        net = _solve(scene, rng)
        X.append(net.points_world)
        sig.append(net.point_sigmas)
        C, Cc = net.thermal_center()
        Cs.append(C)
        sigC.append(np.sqrt(np.diag(Cc)))
    X, sig, Cs, sigC = map(np.array, (X, sig, Cs, sigC))
    ratio = X.std(axis=0, ddof=1) / sig.mean(axis=0)
    # every coordinate of every pass point: empirical scatter within ±20 % of the reported sigma
    assert ratio.min() > 0.8 and ratio.max() < 1.2, ratio
    # unbiased: mean error below 4 standard errors of the mean
    truth = np.array([scene.passpoints[i] for i in net.pass_ids])
    assert np.all(np.abs(X.mean(axis=0) - truth) < 4 * sig.mean(axis=0) / np.sqrt(R))
    rC = Cs.std(axis=0, ddof=1) / sigC.mean(axis=0)
    assert rC.min() > 0.8 and rC.max() < 1.2, rC
    # thermal camera centre within 3 sigma of the truth in (nearly) every run: expect 99.7 % per axis
    z = np.abs(Cs - scene.camera("thermal").pose.center) / sigC
    assert np.mean(np.all(z < 3, axis=1)) > 0.97


def test_thermal_centre_single_run_within_3_sigma(scene):
    net = _solve(scene, np.random.default_rng(7))
    C, Cc = net.thermal_center()
    err = C - scene.camera("thermal").pose.center
    assert np.all(np.abs(err) < 3 * np.sqrt(np.diag(Cc)))
    assert float(err @ np.linalg.solve(Cc, err)) < 14.2  # chi2(3) 99.7 %


def test_plane_angles_within_half_degree_with_known_thermal_interior(scene):
    # the calibrated thermal camera (known interior orientation) is resected from the pass points
    Ct = scene.camera("thermal").pose
    net = _solve(scene, np.random.default_rng(11), known={"thermal": _thermal_camera(scene)})
    planes = estimate_planes(net, {f.name: f.ids for f in scene.faces})
    for p, f in zip(planes, scene.faces):
        true_eta = np.arccos(abs(f.normal @ Ct.axis))
        err = np.degrees(abs(p.angle_rad - true_eta))
        assert err < 0.5, (p.name, err)
        assert err < 3 * np.degrees(p.sigma_angle_rad) + 1e-6
        assert np.degrees(np.arccos(min(1.0, abs(p.normal @ f.normal)))) < 0.5
        assert p.distance_m == pytest.approx(np.linalg.norm(Ct.center - np.mean([scene.points[i] for i in f.ids], 0)),
                                             abs=3 * p.sigma_distance_m)


def test_plane_angles_dlt_thermal_within_3_sigma(scene):
    # paper's set-up (thermal camera by DLT from 11 pass points): consistent with its larger sigma
    Ct = scene.camera("thermal").pose
    net = _solve(scene, np.random.default_rng(12))
    for p, f in zip(estimate_planes(net, {f.name: f.ids for f in scene.faces}), scene.faces):
        err = abs(p.angle_rad - np.arccos(abs(f.normal @ Ct.axis)))
        assert err < 3 * p.sigma_angle_rad
        assert 0.2 < np.degrees(p.sigma_angle_rad) < 5.0  # a real, not vanishing, uncertainty


def test_hot_plate_corrected_within_0p1_k(scene):
    # hot faces at 35/32/29 °C, ambient 22 °C, cosine-law radiance, 0.5 px image noise everywhere
    s = make_closerange_scene(face_temperatures_k={"front": 308.15, "top": 305.15, "right": 302.15})
    img = render_thermal(s)
    net = _solve(s, np.random.default_rng(21), known={"thermal": _thermal_camera(s)})
    planes = estimate_planes(net, {f.name: f.ids for f in s.faces})
    cr = correct_thermal_image(net, planes, img["temperature_k"], CloseRangeConfig(ambient_c=s.ambient_k - 273.15))
    v = cr.valid
    assert v.sum() > 0.9 * img["inside"].sum()  # edges and overlaps only are excluded
    assert np.all(img["inside"][v])
    err = cr.corrected_k[v] - img["true_temperature_k"][v]
    assert np.abs(err).max() < 0.1
    # the correction itself is several kelvin: the test is not passed by doing nothing
    assert np.abs(img["temperature_k"][v] - img["true_temperature_k"][v]).max() > 2.0
    # errors consistent with the propagated uncertainty map
    assert np.abs(err).max() < 4 * np.nanmax(cr.sigma_k)
    # off the planes the image is unchanged
    assert np.array_equal(cr.corrected_k[~v], img["temperature_k"][~v])


def test_hot_plate_noise_free_exact(scene):
    img = render_thermal(scene)
    net = _solve(scene, np.random.default_rng(0), sigma=0.0)
    planes = estimate_planes(net, {f.name: f.ids for f in scene.faces})
    cr = correct_thermal_image(net, planes, img["temperature_k"], CloseRangeConfig(ambient_c=scene.ambient_k - 273.15))
    v = cr.valid
    assert np.abs(cr.corrected_k[v] - img["true_temperature_k"][v]).max() < 1e-6


# -- bad input ---------------------------------------------------------------------------------------

def test_coplanar_control_points_error_suggests_known_interior(scene):
    control = {k: (v[0], v[1], 1.0) for k, v in scene.control.items()}
    s = make_closerange_scene(control=control)
    rows = measure(s, SIGMA, np.random.default_rng(1))
    with pytest.raises(DegenerateInputError) as ei:
        solve_network(s.control, Observations.from_rows(rows), s.thermal)
    msg = str(ei.value)
    assert "coplanar" in msg and "DLT is singular" in msg and "interior orientation" in msg and "opt1" in msg


def test_coplanar_control_with_known_interior_works(scene):
    control = {k: (v[0], v[1], 1.0) for k, v in scene.control.items()}
    s = make_closerange_scene(control=control)
    known = {}
    for c in s.cameras:
        known[c.name] = Camera("pinhole", c.image_size,
                               {"fx": c.K[0, 0], "fy": c.K[1, 1], "cx": c.K[0, 2], "cy": c.K[1, 2]})
    rows = measure(s, 0.0, np.random.default_rng(1))
    net = solve_network(s.control, Observations.from_rows(rows), s.thermal, known=known)
    truth = np.array([s.passpoints[i] for i in net.pass_ids])
    assert np.abs(net.points_world - truth).max() < 1e-7


def test_too_few_pass_points_on_thermal_names_them(scene):
    seen = ["1", "4", "7", "12", "13"]
    rows = measure(scene, SIGMA, np.random.default_rng(1), thermal_ids=seen)
    with pytest.raises(TooFewPointsError) as ei:
        solve_network(scene.control, Observations.from_rows(rows), scene.thermal)
    msg = str(ei.value)
    assert "thermal" in msg and "at least 6" in msg
    for i in seen:
        assert i in msg
    assert "1, 4, 7, 12, 13" in msg


def test_collinear_plane_names_the_plane(scene):
    net = _solve(scene, np.random.default_rng(3), sigma=0.0)
    # 14, 15 and the midpoint-ish 12/13 lie on a line? use exact collinear control-like points instead:
    net.control["c1"] = np.array([1.0, 3.0, 1.0])
    net.control["c2"] = np.array([1.5, 3.0, 1.0])
    net.control["c3"] = np.array([2.0, 3.0, 1.0])
    with pytest.raises(DegenerateInputError) as ei:
        estimate_planes(net, {"front": ("1", "4", "3"), "ledge": ("c1", "c2", "c3")})
    assert "'ledge'" in str(ei.value) and "collinear" in str(ei.value)


def test_known_thermal_camera_with_distortion(scene):
    # a calibrated thermal camera with strong radial distortion: measurements are undistorted for the
    # resection and every pixel's ray goes through the undistorted position
    s = make_closerange_scene(thermal_distortion={"k1": -0.25, "k2": 0.1, "p1": 0.001})
    img = render_thermal(s)
    known = {"thermal": s.camera("thermal").model}
    net = _solve(s, np.random.default_rng(0), known=known, sigma=0.0)
    C, _ = net.thermal_center()
    assert np.abs(C - s.camera("thermal").pose.center).max() < 1e-6
    planes = estimate_planes(net, {f.name: f.ids for f in s.faces})
    cr = correct_thermal_image(net, planes, img["temperature_k"], CloseRangeConfig(ambient_c=s.ambient_k - 273.15))
    v = cr.valid
    assert v.sum() > 0.9 * img["inside"].sum()
    # polygons are straight in the object, curved in the image: pixels near the curved edges are
    # excluded by the 1.5 px margin; the remaining ones are exact up to the camera's undistort precision
    assert np.abs(cr.corrected_k[v] - img["true_temperature_k"][v]).max() < 1e-4
    assert np.nanmax(np.abs(cr.angle_rad[v] - img["angle_rad"][v])) < 1e-6


def test_optical_dlt_agrees_with_geometry_dlt(scene):
    # an independent implementation (thermogrammetry.geometry.dlt) gives the same camera and the same
    # a-priori standard deviations as our propagated Jacobians
    from thermogrammetry.closerange.pipeline import camera_report
    from thermogrammetry.geometry import dlt

    rows = measure(scene, SIGMA, np.random.default_rng(8))
    net = solve_network(scene.control, Observations.from_rows(rows, SIGMA), scene.thermal)
    sel = [r for r in rows if r[0] == "opt1" and r[1] in scene.control]
    g = dlt(np.array([scene.control[r[1]] for r in sel]), np.array([[r[2], r[3]] for r in sel]), sigma_px=SIGMA)
    rep = camera_report(net, "opt1")
    assert np.abs(np.asarray(rep["center_m"]) - g.center).max() < 1e-8
    for k in ("X0", "Y0", "Z0"):
        assert rep["exterior_std"][k] == pytest.approx(g.std_prior[k], rel=1e-4)
    assert rep["interior"]["fx_px"] == pytest.approx(g.values["fx"], rel=1e-9)
    assert rep["interior_std"]["fx_px"] == pytest.approx(g.std_prior["fx"], rel=1e-4)


def test_plane_with_unknown_point_and_missing_thermal_image(scene):
    from thermogrammetry.errors import InvalidInputError

    net = _solve(scene, np.random.default_rng(3))
    with pytest.raises(InvalidInputError, match=r"plane 'lid': point\(s\) 99 have no coordinates"):
        estimate_planes(net, {"lid": ("1", "4", "99")})
    rows = measure(scene, SIGMA, np.random.default_rng(1))
    with pytest.raises(InvalidInputError, match=r"thermal image 'IR_0001' has no measurements.*'opt1'"):
        solve_network(scene.control, Observations.from_rows(rows), "IR_0001")


def test_optical_image_with_five_control_points_is_refused(scene):
    rows = [r for r in measure(scene, SIGMA, np.random.default_rng(1)) if not (r[0] == "opt2" and r[1] == "11")]
    with pytest.raises(TooFewPointsError, match=r"5 control points on image 'opt2' \(2, 3, 6, 8, 10\).*at least 6"):
        solve_network(scene.control, Observations.from_rows(rows), scene.thermal)


def test_third_optical_image_without_control_is_left_out_with_warning():
    s = make_closerange_scene(n_optical=3)
    rows = [r for r in measure(s, SIGMA, np.random.default_rng(1)) if not (r[0] == "opt3" and r[1] in ("10", "11"))]
    net = solve_network(s.control, Observations.from_rows(rows), s.thermal)
    assert set(net.cameras) == {"opt1", "opt2", "thermal"}
    assert any("opt3" in w and "4 control points" in w for w in net.warnings)
