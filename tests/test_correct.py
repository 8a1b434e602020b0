"""Per-pixel directional correction (seed 000 eq. 7–8, emissivity, transmission) with a known geometry."""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry.products.correction import correct_temperature, dT_deps, eq8_correction
from thermogrammetry.closerange.workflow import CloseRangeConfig, correct_oriented_image
from thermogrammetry.synthetic.closerange import make_closerange_scene, render_thermal


@pytest.fixture(scope="module")
def scene_img():
    s = make_closerange_scene()
    return s, render_thermal(s)


def _true(s, img, cfg, **kw):
    cam = s.camera("thermal")
    return correct_oriented_image(img["temperature_k"], cam.K, cam.pose.R, cam.pose.t,
                                  [(f.normal, f.d) for f in s.faces], cfg,
                                  polygons_world=[np.array([s.points[i] for i in f.ids]) for f in s.faces], **kw)


def test_per_pixel_correction_equals_eq8_at_true_angle(scene_img):
    s, img = scene_img
    cr = _true(s, img, CloseRangeConfig(ambient_c=s.ambient_k - 273.15, edge_margin_px=0.0))
    v = cr.valid & img["inside"]
    assert v.sum() > 0.95 * img["inside"].sum()
    # the per-pixel angle found by ray casting is the true one
    assert np.nanmax(np.abs(cr.angle_rad[v] - img["angle_rad"][v])) < 1e-9
    e8 = eq8_correction(img["temperature_k"], img["angle_rad"], s.ambient_k)
    assert np.abs(cr.corrected_k[v] - e8[v]).max() < 1e-6
    # and the radiometry module's eq. 8 agrees
    from thermogrammetry.radiometry import temperature_correction_eq8

    e8r = temperature_correction_eq8(img["temperature_k"][v], s.ambient_k, img["angle_rad"][v])
    assert np.abs(cr.corrected_k[v] - e8r).max() < 1e-6
    # distance: line-of-sight length to the surface
    assert np.nanmax(np.abs(cr.distance_m[v] - img["distance_m"][v])) < 1e-9


def test_axis_mode_is_seed000_eq6_angle(scene_img):
    s, img = scene_img
    cr = _true(s, img, CloseRangeConfig(ambient_c=22.0, angle_mode="axis", edge_margin_px=0.0))
    ax = s.camera("thermal").pose.axis
    for j, f in enumerate(s.faces):
        sel = cr.valid & (cr.plane == j)
        assert np.allclose(cr.angle_rad[sel], np.arccos(abs(f.normal @ ax)), atol=1e-12)


def test_fresnel_emissivity_rendering_inverted(scene_img):
    from thermogrammetry.radiometry import fresnel_emissivity

    s, _ = scene_img
    img = render_thermal(s, emissivity=lambda th: fresnel_emissivity(th, 1.5))
    cr = _true(s, img, CloseRangeConfig(ambient_c=s.ambient_k - 273.15, emissivity="fresnel", refractive_index=1.5,
                                        edge_margin_px=0.0))
    v = cr.valid & img["inside"]
    assert np.abs(cr.corrected_k[v] - img["true_temperature_k"][v]).max() < 1e-4


def test_transmission_inversion_roundtrip():
    rng = np.random.default_rng(3)
    T = rng.uniform(290, 400, 100)
    eps = rng.uniform(0.3, 1.0, 100)
    tau = rng.uniform(0.8, 1.0, 100)
    Ta, Tatm = 293.0, 288.0
    T0 = (tau * (eps * T**4 + (1 - eps) * Ta**4) + (1 - tau) * Tatm**4) ** 0.25
    assert np.abs(correct_temperature(T0, eps, Ta, transmission=tau, atmosphere_k=Tatm) - T).max() < 1e-9
    # tau = 1, eps = cos: eq. 8
    th = rng.uniform(0, 1.2, 100)
    assert np.allclose(correct_temperature(T0, np.cos(th), Ta), eq8_correction(T0, th, Ta), atol=1e-9, rtol=0)


def test_transmission_over_distance_increases_correction(scene_img):
    s, img = scene_img
    a = _true(s, img, CloseRangeConfig(ambient_c=22.0, air_c=10.0, edge_margin_px=0.0))
    b = _true(s, img, CloseRangeConfig(ambient_c=22.0, air_c=10.0, transmission=True, relative_humidity=0.9,
                                       edge_margin_px=0.0))
    v = a.valid & b.valid
    assert np.all(b.transmission[v] < 1.0) and np.all(b.transmission[v] > 0.9)
    # a colder atmosphere in the path lowers the apparent temperature: correcting for it raises T
    assert np.all(b.corrected_k[v] > a.corrected_k[v])


def test_dT_deps_matches_finite_difference():
    T0, Ta = 310.0, 295.0
    eps = np.array([0.3, 0.6, 0.9])
    T = correct_temperature(T0, eps, Ta)
    h = 1e-6
    fd = (correct_temperature(T0, eps + h, Ta) - correct_temperature(T0, eps - h, Ta)) / (2 * h)
    assert np.allclose(dT_deps(T, eps, Ta), fd, rtol=1e-6)


def test_whole_image_plane_without_polygon():
    s = make_closerange_scene()
    cam = s.camera("thermal")
    T0 = np.full((480, 640), 305.0)
    f = s.faces[0]
    cr = correct_oriented_image(T0, cam.K, cam.pose.R, cam.pose.t, [(f.normal, f.d)],
                                CloseRangeConfig(ambient_c=22.0))
    assert cr.valid.mean() > 0.99  # the front plane fills the view
    assert np.all(cr.corrected_k[cr.valid] > 305.0)


def _on_plane(P, n, d):
    P = np.asarray(P, float)
    return P - (P @ n + d)[:, None] * n


def test_mesh_surface_matches_planes(scene_img):
    # the faces as a triangle mesh (corners projected onto the true planes) give the same per-pixel
    # angle and eq. 8 correction as the planes, away from the edges
    from thermogrammetry.products.correction import convex_inset

    s, img = scene_img
    cam = s.camera("thermal")
    V, F = [], []
    for f in s.faces:
        q = _on_plane([s.points[i] for i in f.ids], f.normal, f.d)
        k = len(V)
        V += list(q)
        F += [(k, k + 1, k + 2), (k, k + 2, k + 3)]
    cfg = CloseRangeConfig(ambient_c=s.ambient_k - 273.15)
    cr = correct_oriented_image(img["temperature_k"], cam.K, cam.pose.R, cam.pose.t, None, cfg,
                                mesh=(np.array(V), np.array(F)))
    inner = np.zeros(img["inside"].shape, bool)
    near = np.zeros(img["inside"].shape, int)  # faces whose outline is within 3 px (overlaps are ambiguous)
    for f in s.faces:
        ins = convex_inset(cam.project(np.array([s.points[i] for i in f.ids])), cam.image_size)
        inner |= ins > 3.0
        near += ins > -3.0
    v = cr.valid & inner & (near == 1) & img["inside"]
    assert v.sum() > 0.8 * img["inside"].sum()
    assert np.abs(cr.angle_rad[v] - img["angle_rad"][v]).max() < 1e-6  # Embree hits in float32; normals exact
    assert np.abs(cr.distance_m[v] - img["distance_m"][v]).max() < 1e-9
    e8 = eq8_correction(img["temperature_k"], img["angle_rad"], s.ambient_k)
    assert np.abs(cr.corrected_k[v] - e8[v]).max() < 1e-4


def test_dsm_surface_matches_analytic_plane():
    from thermogrammetry.products.surfaces import dsm_to_mesh
    from thermogrammetry.geometry import Pose

    # tilted planar DSM z = 0.1 x + 0.2 y + 1 on a 1 m grid (corner-addressed transform), camera 10 m above
    H, W = 40, 50
    transform = (1.0, 0.0, -25.0, 0.0, -1.0, 20.0)
    col, row = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    x, y = -25.0 + col, 20.0 - row
    z = 0.1 * x + 0.2 * y + 1.0
    V, F = dsm_to_mesh(z, transform)
    assert len(F) == 2 * (H - 1) * (W - 1)
    pose = Pose.look_at([2.0, -3.0, 12.0], [0.0, 0.0, 1.0], up=(0, 1, 0))
    K = np.array([[300.0, 0, 79.5], [0, 300.0, 59.5], [0, 0, 1]])
    T0 = np.full((120, 160), 300.0)
    n = np.array([-0.1, -0.2, 1.0])
    cfg = CloseRangeConfig(ambient_c=20.0)
    a = correct_oriented_image(T0, K, pose.R, pose.t, None, cfg, mesh=(V, F))
    b = correct_oriented_image(T0, K, pose.R, pose.t, [(n, -1.0)], cfg)
    v = a.valid & b.valid
    assert v.mean() > 0.9
    assert np.abs(a.angle_rad[v] - b.angle_rad[v]).max() < 1e-6
    assert np.abs(a.distance_m[v] - b.distance_m[v]).max() < 1e-9
    assert np.abs(a.corrected_k[v] - b.corrected_k[v]).max() < 1e-4
