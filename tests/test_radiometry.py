"""Radiometry physics: Planck round trips, FLIR atmosphere, measurement equation, seed 000 eq. 7-8,
Fresnel emissivity, 16-bit encoding.  No real data needed."""

from __future__ import annotations

from decimal import Decimal, getcontext

import numpy as np
import pytest

from thermogrammetry.errors import ConfigError, InvalidInputError
from thermogrammetry.radiometry import (
    AtmosphericCoefficients,
    FresnelEmissivity,
    MeasurementParams,
    PlanckConstants,
    TabulatedEmissivity,
    atmospheric_transmission,
    choose_uint16_mapping,
    corrected_temperature,
    decode_uint16,
    encode_uint16,
    flux_correction_eq7,
    fresnel_emissivity,
    measurement_weights,
    object_temperature_from_raw,
    raw_for_directional,
    raw_from_object_temperature,
    raw_from_temperature,
    temperature_correction_eq8,
    temperature_from_raw,
)

# IR_2412.jpg / SampleSEQ.seq constants (flir_thermimage/SOURCE.md)
SC660 = PlanckConstants(r1=21106.77, r2=0.012545258, b=1501.0, f=1.0, o=-7340.0)
# FLIR Duo Pro R (flir_fff_tiff/SOURCE.md): R2 = 1 style constants
DUO = PlanckConstants(r1=364058.0, r2=1.0, b=1428.0, f=1.0, o=-228.0)


@pytest.mark.parametrize("planck", [SC660, DUO])
def test_planck_round_trip_below_1mk(planck, rng):
    t = rng.uniform(233.15, 473.15, size=100_000)  # -40 .. 200 degC
    raw = raw_from_temperature(t, planck)
    back = temperature_from_raw(raw, planck)
    # exact inverse in float64: the error is rounding only (~1e-12 K), far below the 1e-3 K requirement
    assert np.max(np.abs(back - t)) < 1e-3
    assert np.max(np.abs(back - t)) < 1e-11  # measured 1.1e-13 K
    # and through integer counts the error is bounded by half a count times dT/draw (not 0)
    back_int = temperature_from_raw(np.rint(raw), planck)
    dtdraw = 1.0 / np.gradient(raw_from_temperature(t + np.array([[-1e-3], [0], [1e-3]]), planck), 1e-3, axis=0)[1]
    assert np.all(np.abs(back_int - t) <= 0.5 * np.abs(dtdraw) * 1.001 + 1e-9)


def test_measurement_round_trip_per_pixel_maps(rng):
    h, w = 40, 50
    t_obj = rng.uniform(260, 380, size=(h, w))
    params = MeasurementParams(
        emissivity=rng.uniform(0.6, 1.0, size=(h, w)),
        reflected_temperature_k=290.0,
        atmospheric_temperature_k=300.0,
        relative_humidity=0.7,
        distance_m=rng.uniform(0, 80, size=(h, w)),
        window_temperature_k=295.0,
        window_transmission=0.9,
        window_reflectance=0.02,
    )
    raw = raw_from_object_temperature(t_obj, SC660, params)
    back = object_temperature_from_raw(raw, SC660, params)
    assert np.max(np.abs(back - t_obj)) < 5e-12  # measured 5.7e-14 K
    wts = measurement_weights(params)
    total = wts["object"] + wts["reflected"] + wts["atmosphere"] + wts["window"]
    np.testing.assert_allclose(total, 1.0, atol=2e-14, rtol=0)  # weights sum to one: Planck O cancels (measured 2.2e-16)


def test_thermimage_readme_worked_values():
    # Thermimage README (flir_thermimage/SOURCE.md): raw 17994.06 -> 23.31223 C with E=0.95, OD=1,
    # RTemp=ATemp=IRWTemp=20 C, IRT=0.96, RH=50 %, SC660 constants.  The README prints 5 decimals and its
    # constants are the exiftool-rounded ones we use here, so agreement to 1e-4 K is expected.
    p = MeasurementParams(emissivity=0.95, reflected_temperature_k=293.15, atmospheric_temperature_k=293.15,
                          relative_humidity=0.5, distance_m=1.0, window_temperature_k=293.15, window_transmission=0.96)
    t = float(object_temperature_from_raw(17994.06, SC660, p)) - 273.15
    assert t == pytest.approx(23.31223, abs=1e-4)


def test_transmission_is_one_at_zero_distance_and_falls():
    c = AtmosphericCoefficients()
    t_air = np.array([253.15, 273.15, 293.15, 313.15])[:, None, None]
    rh = np.linspace(0, 1, 11)[None, :, None]
    d = np.concatenate([[0.0], np.geomspace(0.01, 300, 60)])[None, None, :]
    tau = atmospheric_transmission(d, t_air, rh, c)
    np.testing.assert_allclose(tau[..., 0], 1.0, atol=1e-15)
    assert np.all(np.diff(tau, axis=2) < 0)  # strictly falling with distance (every T, RH)
    assert np.all(np.diff(tau[:, :, 1:], axis=1) < 0)  # strictly falling with humidity (d > 0)
    assert np.all(tau > 0)
    # physical magnitude: 20 C, 50 %, 100 m -> a few percent absorbed (FLIR model)
    assert 0.9 < float(atmospheric_transmission(100, 293.15, 0.5)) < 0.97


def test_transmission_refuses_bad_input():
    # the empirical FLIR fit turns negative far outside its range (here 2 km at 40 C, saturated air)
    assert float(atmospheric_transmission(2000.0, 313.15, 1.0)) < 0
    with pytest.raises(InvalidInputError, match="outside the valid range of FLIR's empirical"):
        object_temperature_from_raw(18000.0, SC660, MeasurementParams(distance_m=2000.0, atmospheric_temperature_k=313.15,
                                                                      relative_humidity=1.0))
    with pytest.raises(InvalidInputError, match="distance_m"):
        atmospheric_transmission(-1.0, 293.15, 0.5)
    with pytest.raises(InvalidInputError, match="fraction"):
        atmospheric_transmission(10.0, 293.15, 50.0)


def _eq8_decimal(t0, ta, phi_deg):
    getcontext().prec = 50
    import math

    c = Decimal(repr(math.cos(math.radians(phi_deg))))
    inner = (Decimal(t0) ** 4 - Decimal(ta) ** 4) / c + Decimal(ta) ** 4
    return float(inner.sqrt().sqrt())


@pytest.mark.parametrize("t0,ta", [(300.0, 290.0), (350.0, 293.15), (280.0, 295.0), (400.0, 250.0)])
def test_eq8_matches_seed000_to_10pk(t0, ta):
    angles = np.array([0.0, 10.0, 30.0, 45.0, 60.0, 70.0, 75.0])
    got = temperature_correction_eq8(t0, ta, np.deg2rad(angles))
    ref = np.array([_eq8_decimal(t0, ta, a) for a in angles])
    assert np.max(np.abs(got - ref)) < 1e-11  # measured 0 (ulp at 400 K: 5.7e-14 K)
    assert got[0] == pytest.approx(t0, abs=1e-11)  # no correction at normal view
    # hotter than ambient -> corrected upwards, growing with the angle; colder -> downwards
    assert np.all(np.sign(np.diff(got)) == np.sign(t0 - ta))


def test_eq7_and_grazing_refusal():
    assert float(flux_correction_eq7(2.0, np.deg2rad(60))) == pytest.approx(4.0, rel=2e-14)  # measured 8.9e-16 abs
    with pytest.raises(InvalidInputError, match=r"beyond 75° .*largest 80\.00°"):
        temperature_correction_eq8(300.0, 290.0, np.deg2rad([10.0, 80.0]))
    # deliberately widened range is accepted, up to 89°
    assert np.isfinite(temperature_correction_eq8(300.0, 290.0, np.deg2rad(80.0), max_angle_deg=85))
    with pytest.raises(InvalidInputError, match="max_angle_deg"):
        temperature_correction_eq8(300.0, 290.0, 0.1, max_angle_deg=90)
    with pytest.raises(InvalidInputError, match="negative"):
        flux_correction_eq7(1.0, -0.1)


def test_fresnel_emissivity_known_values():
    n = 1.5
    th = np.deg2rad(np.linspace(0, 90, 181))
    eps = fresnel_emissivity(th, n)
    assert eps[0] == pytest.approx(1 - ((n - 1) / (n + 1)) ** 2, abs=1e-12)  # 0.96
    assert eps[-1] == pytest.approx(0.0, abs=2e-14)  # grazing: total reflection (measured 3.3e-16)
    assert np.all(np.diff(eps[20:]) < 0)  # falls monotonically beyond 10° (tiny rise near Brewster excluded)
    # at Brewster's angle R_p = 0, so eps = 1 - R_s/2
    tb = np.arctan(n)
    cs, ct = np.cos(tb), np.sqrt(1 - np.sin(tb) ** 2 / n**2)
    rs = ((cs - n * ct) / (cs + n * ct)) ** 2
    assert float(fresnel_emissivity(tb, n)) == pytest.approx(1 - rs / 2, abs=1e-12)
    scaled = FresnelEmissivity(1.5, normal_emissivity=0.9)
    assert float(scaled(0.0)) == pytest.approx(0.9, abs=1e-12)


def test_tabulated_emissivity_interpolates_and_refuses_outside():
    tab = TabulatedEmissivity((0.0, 40.0, 60.0, 80.0), (0.95, 0.94, 0.90, 0.70))
    np.testing.assert_allclose(tab(np.deg2rad([0, 20, 50, 70])), [0.95, 0.945, 0.92, 0.80], atol=1e-14, rtol=0)  # measured 1.1e-16
    with pytest.raises(InvalidInputError, match="outside the emissivity table"):
        tab(np.deg2rad(85.0))
    with pytest.raises(InvalidInputError, match="increase"):
        TabulatedEmissivity((0.0, 0.0), (0.9, 0.9))


def test_directional_correction_recovers_truth_per_pixel(rng):
    h, w = 30, 40
    truth = rng.uniform(280, 340, size=(h, w))
    angle = np.deg2rad(rng.uniform(0, 70, size=(h, w)))
    dist = rng.uniform(1, 50, size=(h, w))
    model = FresnelEmissivity(1.6, normal_emissivity=0.93)
    base = MeasurementParams(reflected_temperature_k=285.0, atmospheric_temperature_k=295.0, relative_humidity=0.6)
    raw = raw_for_directional(truth, SC660, base, angle, model, distance_m=dist)
    angle_nan = angle.copy()
    angle_nan[0, 0] = np.nan  # no surface there
    got = corrected_temperature(raw, SC660, base, angle_nan, model, distance_m=dist)
    assert np.isnan(got[0, 0])
    assert np.nanmax(np.abs(got - truth)) < 5e-12  # measured 5.7e-14 K
    # ignoring the angle (normal emissivity everywhere) is biased low at large angles for hot objects
    naive = object_temperature_from_raw(raw, SC660, base.override(emissivity=0.93, distance_m=dist))
    big = (np.rad2deg(angle) > 60) & (truth > 300)
    assert np.all(naive[big] < truth[big] - 0.5)


def test_uint16_round_trip_below_half_step(rng):
    for lo, hi in [(250.0, 330.0), (290.0, 291.0), (200.0, 850.0)]:
        t = rng.uniform(lo, hi, size=(64, 80))
        t[3, 4] = np.nan
        for unit in ("K", "C"):
            m = choose_uint16_mapping(t, unit)
            assert m.scale <= 0.01
            codes = encode_uint16(t, m)
            assert codes[3, 4] == 0
            back = decode_uint16(codes, m) + (273.15 if unit == "C" else 0.0)
            err = np.nanmax(np.abs(back - t))
            assert err <= 0.5 * m.scale * (1 + 1e-9) + 1e-12
            assert err > 0.3 * m.scale  # uniform data: the worst rounding error is close to half a step
            assert np.isnan(back[3, 4])
    assert choose_uint16_mapping(np.array([290.0, 291.0])).scale == pytest.approx(0.001)
    with pytest.raises(InvalidInputError, match="cannot be stored in 16 bits"):
        choose_uint16_mapping(np.array([100.0, 1000.0]))


def test_params_override_refuses_unknown_and_bad_values():
    p = MeasurementParams()
    with pytest.raises(ConfigError, match="emisivity"):
        p.override(emisivity=0.9)
    with pytest.raises(InvalidInputError, match="emissivity"):
        measurement_weights(p.override(emissivity=1.2))
    with pytest.raises(InvalidInputError, match="kelvin"):
        measurement_weights(p.override(reflected_temperature_k=-5.0))


def test_eq8_is_the_measurement_equation_with_cosine_emissivity(rng):
    # seed 000 eq. 8 == inverting S0 = eps S(T) + (1 - eps) S(Ta) with eps = cos(phi), S = sigma T^4, tau = 1
    from thermogrammetry.radiometry import CosineEmissivity, StefanBoltzmann, corrected_temperature_from_apparent

    t0 = rng.uniform(270, 400, size=500)
    ta = rng.uniform(260, 310, size=500)
    phi = np.deg2rad(rng.uniform(0, 75, size=500))
    got = corrected_temperature_from_apparent(
        t0, phi, CosineEmissivity(), signal_model=StefanBoltzmann(),
        params=MeasurementParams(reflected_temperature_k=ta, atmospheric_temperature_k=ta, distance_m=0.0),
    )
    ok = np.isfinite(got)
    assert ok.mean() > 0.95  # NaN only where no real solution exists (cold object, big angle)
    assert np.max(np.abs(got[ok] - temperature_correction_eq8(t0, ta, phi)[ok])) < 1e-11  # measured 1.1e-13 K
    np.testing.assert_array_equal(np.isnan(got), np.isnan(temperature_correction_eq8(t0, ta, phi)))


def test_nan_distance_marks_pixels_without_surface():
    d = np.array([[1.0, np.nan], [5.0, 10.0]])
    tau = atmospheric_transmission(d, 293.15, 0.5)
    assert np.isnan(tau[0, 1]) and np.all(np.isfinite(tau[[0, 1, 1], [0, 0, 1]]))
    t = object_temperature_from_raw(np.full((2, 2), 18500.0), SC660, MeasurementParams(distance_m=d, emissivity=0.9))
    assert np.isnan(t[0, 1]) and np.all(np.isfinite(t[[0, 1, 1], [0, 0, 1]]))
    e = np.array([[0.9, 0.9], [np.nan, 0.95]])  # an emissivity map with a no-data pixel
    t = object_temperature_from_raw(np.full((2, 2), 18500.0), SC660, MeasurementParams(emissivity=e))
    assert np.isnan(t[1, 0]) and np.isfinite(t[1, 1])
