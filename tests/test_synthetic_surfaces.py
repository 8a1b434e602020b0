"""Radiometric exactness of the flat-surface renderer against the radiometry forward model."""

from __future__ import annotations

import numpy as np
import pytest

import thermogrammetry as tg
from thermogrammetry import radiometry as rad
from thermogrammetry.geometry import Pose
from thermogrammetry.synthetic.radiance import BandPlanckCurve, FlirCurve, fresnel_emissivity
from thermogrammetry.synthetic.surfaces import FlatSurface, render_flat_surface


@pytest.fixture(scope="module")
def scene():
    cam = tg.Camera("opencv", (160, 120), dict(fx=180, fy=180, cx=80.2, cy=59.1, k1=-0.15, k2=0.02))
    # plane z = 0 seen obliquely from 2 m: viewing angles ~35..75 deg across the image
    pose = Pose.look_at(np.array([0.0, -3.0, 2.0]), np.array([0.0, 0.0, 0.0]), up=(0, 0, 1))
    pc = rad.PlanckConstants(17096.453, 0.046642166, 1428.0, 1.0, -7340.0)
    return cam, pose, pc


def test_flat_surface_matches_radiometry_forward_model(scene):
    """Must-show: per pixel, rendered apparent temperature = radiometry forward model within 0.01 K.

    Directional (Fresnel, n = 1.6, scaled to eps(0) = 0.93) emissivity, reflected 280 K, atmosphere
    with the FLIR transmission over the real per-pixel distance. Noise off. With S = 1 the sample is the
    pixel centre, so only float32 storage (3e-5 K) separates the two; with S = 4 the model is evaluated
    at the centre while the render averages 16 samples: the angle changes < 0.5 deg across a pixel, a
    second-order effect of < 1e-3 K here.
    """
    cam, pose, pc = scene
    eps_model = rad.FresnelEmissivity(1.6, normal_emissivity=0.93)
    params = rad.MeasurementParams(reflected_temperature_k=280.0, atmospheric_temperature_k=290.0, relative_humidity=0.6)

    def tau(d):
        t = rad.atmospheric_transmission(np.asarray(d) / 2.0, 290.0, 0.6, params.coefficients)
        return t * t  # FLIR splits the path at the (absent) window: tau1 * tau2

    surf = FlatSurface([0, 0, 0], [0, 0, 1], 318.15, eps_model)
    for ss, bound in ((1, 1e-4), (4, 0.01)):
        r = render_flat_surface(cam, pose, surf, reflected_k=280.0, atmosphere_k=290.0, transmission=tau,
                                background_k=250.0, supersample=ss, curve=FlirCurve.from_planck_constants(pc))
        on = np.isfinite(r.angle_rad) & (r.angle_rad < np.deg2rad(85))
        assert on.mean() > 0.8
        assert np.rad2deg(r.angle_rad[on]).min() < 40 and np.rad2deg(r.angle_rad[on]).max() > 70
        raw = rad.raw_for_directional(318.15, pc, params, r.angle_rad[on], eps_model, distance_m=r.distance_m[on], max_angle_deg=89.0)
        t_model = rad.temperature_from_raw(raw, pc)
        err = np.abs(r.image_k[on].astype(float) - t_model)
        print(f"flat surface S={ss}: max |rendered - forward model| = {err.max():.2e} K")
        assert err.max() < bound, (ss, err.max())
        # the effect being modelled is large: apparent temperature spans several kelvin across the image
        assert t_model.max() - t_model.min() > 3.0


def test_band_planck_curve_against_independent_quadrature():
    from scipy.integrate import quad

    h, c, k = 6.62607015e-34, 299792458.0, 1.380649e-23
    curve = BandPlanckCurve((8.0, 14.0))
    for t in (250.0, 300.0, 400.0):
        ref, _ = quad(lambda lam: 2 * h * c**2 / lam**5 / np.expm1(h * c / (k * lam * t)), 8e-6, 14e-6, epsabs=0, epsrel=1e-12)
        assert float(curve.signal(t)) == pytest.approx(ref, rel=1e-10)
        assert float(curve.temperature(ref)) == pytest.approx(t, abs=1e-7)


def test_local_fresnel_matches_radiometry_and_blackbody_plane_is_exact(scene):
    th = np.deg2rad(np.linspace(0, 89, 30))
    np.testing.assert_allclose(fresnel_emissivity(th, 1.6 + 0.05j), rad.fresnel_emissivity(th, 1.6, 0.05), atol=1e-12)
    cam, pose, _ = scene
    r = render_flat_surface(cam, pose, FlatSurface([0, 0, 0], [0, 0, 1], 305.0, 1.0), supersample=2)
    on = np.isfinite(r.angle_rad)
    np.testing.assert_allclose(r.image_k[on], 305.0, atol=1e-4)  # blackbody: no angle dependence at all
