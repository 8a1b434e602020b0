"""The camera table (thermogrammetry.camera.database), the survey's starting focal length from it, the focal-length
guard measured from the files' value, and the refusal of σ from an adjustment that did not converge."""

from types import SimpleNamespace

import numpy as np
import pytest

from thermogrammetry.camera import Camera
from thermogrammetry.camera.database import CAMERA_TABLE, LENS_FOCAL_SIGMA, find_camera, normalise_model, table_focal
from thermogrammetry.results import Termination


def test_lookup_is_case_and_spacing_insensitive_and_accepts_the_make_and_a_resolution():
    assert normalise_model("Zenmuse XT 2") == normalise_model("zenmuse-xt2") == "ZENMUSEXT2"
    assert find_camera("DJI", "XT").name == "DJI Zenmuse XT"
    assert find_camera("dji", "zenmuse xt2").name == "DJI Zenmuse XT2"
    assert find_camera("FLIR", "FLIR Vue Pro R 640").name == "FLIR Vue Pro"
    assert find_camera("DJI", "MAVIC2-ENTERPRISE-ADVANCED").name == "DJI Mavic 2 Enterprise Advanced"
    assert find_camera("DJI", "ZH20T").name == "DJI Zenmuse H20T"
    assert find_camera("thermogrammetry", "synthetic") is None and find_camera("DJI", "") is None
    # every alias finds its own entry (no alias shadowed by another camera's)
    for e in CAMERA_TABLE:
        for a in e.aliases:
            assert find_camera(e.make, a) is e, a


def test_focal_length_in_pixels_with_sigma():
    xt = table_focal("DJI", "XT", (640, 512), 13.0)
    assert xt.f_px == pytest.approx(13.0 / 0.017) and xt.sigma_px == pytest.approx(LENS_FOCAL_SIGMA * xt.f_px)
    # the lab calibration of the 13 mm XT (741 px) lies within 1 σ of the table's value
    assert abs(741.0 - xt.f_px) < xt.sigma_px
    # no focal length in the M2ED's files: its 57° ± 2° over the 640 px upscaled from the 160x120 core
    m2 = table_focal("DJI", "MAVIC2-ENTERPRISE-DUAL", (640, 480))
    assert m2.upscale == 4.0 and m2.native_size == (160, 120) and m2.pixel_pitch_um == pytest.approx(3.0)
    assert 580.0 < m2.f_px < 600.0 and 25.0 < m2.sigma_px < 50.0
    # an upscaled (high-resolution mode) image: the focal length on its own grid is twice the core's
    m4 = table_focal("DJI", "M4T", (1280, 1024), 12.0)
    assert m4.upscale == 2.0 and m4.f_px == pytest.approx(12.0 / 0.006)
    # without the file's focal length, the M4T's 45° diagonal field of view: within 2 % of the 12 mm lens
    assert table_focal("DJI", "M4T", (640, 512)).f_px == pytest.approx(1000.0, rel=0.02)
    # a camera with several lenses and a file without a focal length: no guess
    none = table_focal("DJI", "XT", (640, 512))
    assert none.f_px is None and "several lenses" in none.how
    # an image size the camera does not deliver: not this camera's frame
    assert table_focal("DJI", "XT", (320, 240), 13.0) is None


def test_survey_start_comes_from_the_table_and_counts_as_the_files_focal_length():
    from thermogrammetry.pipeline.survey.georef import _focal_from_exif, _focal_prior
    from thermogrammetry.pipeline.survey.inputs import _camera_guess

    def md(model, focal=None, pitch=None):
        return SimpleNamespace(make="DJI", model=model, focal_length_mm=focal, pixel_pitch_um=pitch, exif={})

    # the XT writes its 13 mm lens but no pixel pitch: before the table, "pitch assumed 17 µm", and the focal-length
    # guard was off for it (the flat-field block's 2,692 px against 765 px)
    xt = _camera_guess(640, 512, md("XT", 13.0))
    assert xt["focal_source"] == "camera_table:DJI Zenmuse XT" and xt["f_px"] == pytest.approx(764.7, abs=0.1)
    m2 = _camera_guess(640, 480, md("MAVIC2-ENTERPRISE-DUAL"))
    assert m2["focal_source"].startswith("camera_table:") and 580 < m2["f_px"] < 600
    exif = _camera_guess(640, 512, md("XT", 13.0, (17.0, 17.0)))
    assert exif["focal_source"] == "exif"
    unknown = _camera_guess(640, 512, md("Unknown cam", 13.0))
    assert unknown["focal_source"] == "assumed" and unknown["focal_sigma_px"] is None
    bare = _camera_guess(640, 512, md(""))
    assert bare["focal_source"] == "default" and bare["f_px"] == 640.0
    inputs = {"images": [{"camera_guess": g} for g in (xt, m2, exif, unknown, bare)]}
    rec = SimpleNamespace(image_camera=np.arange(5))
    assert [_focal_from_exif(inputs, rec, k) for k in range(5)] == [True, True, True, False, False]
    assert _focal_prior(inputs, rec, 0) == pytest.approx(764.7, abs=0.1) and _focal_prior(inputs, rec, 3) is None


def _fa(cam, termination=Termination.CONVERGED):
    return SimpleNamespace(result=SimpleNamespace(termination=termination, success=termination.success, reason="",
                                                  camera_std=[]), cameras_after={0: cam}, covariance_asked=False)


def _cam(**p):
    return Camera("opencv", (640, 512), dict(dict(fx=765.0, fy=765.0, cx=319.5, cy=255.5), **p))


def test_focal_guard_is_measured_from_the_files_value_not_from_the_last_start():
    from thermogrammetry.sfm.selfcal_ladder import FocalKnown, intrinsics_check

    est = _fa(_cam(fx=2692.0, fy=2692.0))
    drifted = {0: _cam(fx=2300.0, fy=2300.0)}  # a start an earlier adjustment left (within 30 % of 2,692 px)
    assert intrinsics_check(est, drifted, {0: ("fx", "fy")}, {0: True})[2] == ""
    cam, why, check = intrinsics_check(est, drifted, {0: ("fx", "fy")}, FocalKnown({0: True}, {0: 764.7}))
    assert check == "focal" and "764.7" in why
    # within the band of the files' value: accepted
    ok = _fa(_cam(fx=790.0, fy=790.0))
    assert intrinsics_check(ok, drifted, {0: ("fx", "fy")}, FocalKnown({0: True}, {0: 764.7}))[2] == ""


def test_an_adjustment_at_its_iteration_limit_is_adjusted_again_then_its_sigma_refused(monkeypatch):
    import thermogrammetry.sfm.georef as georef
    from thermogrammetry.sfm.block_gates import refuse_sigma, unconverged_sigma
    from thermogrammetry.sfm.selfcal_ladder import MAX_ITERATIONS_RETRY, adjust_block

    rec = SimpleNamespace(image_camera=np.zeros(4, int), cameras=[_cam()], R=np.zeros((4, 3, 3)), t=np.zeros((4, 3)),
                          points=np.zeros((0, 3)), obs_valid=np.zeros(0, bool), registered=np.ones(4, bool),
                          component=np.zeros(4, int), status=[SimpleNamespace(registered=True, component=0, reason="")] * 4)
    for outcome, expect in (([Termination.MAX_ITERATIONS, Termination.CONVERGED], Termination.CONVERGED),
                            ([Termination.MAX_ITERATIONS, Termination.MAX_ITERATIONS], Termination.MAX_ITERATIONS)):
        calls = []

        def fake(rec_, xy, images, ctrl, *, self_calibrate=(), rig=None, **kw):
            t = outcome[min(len(calls), 1)]
            calls.append(kw.get("max_iterations", 50))
            return SimpleNamespace(result=SimpleNamespace(termination=t, success=t.success, reason=f"{t.value}",
                                                          iterations=calls[-1], camera_std=[np.ones(4)], sigma0=1.0),
                                   notes=[], center_std=np.ones((4, 3)), rotation_std_deg=np.ones((4, 3)),
                                   covariance=np.eye(3))

        monkeypatch.setattr(georef, "final_adjustment", fake)
        fa, used, steps = adjust_block(rec, None, np.arange(4), None, ("fx", "fy"), compute_covariance=False)
        assert calls == [50, MAX_ITERATIONS_RETRY] and fa.result.termination is expect
        assert "adjusted again" in fa.notes[0] and fa.first_termination[0] == "max_iterations"
        why = unconverged_sigma(fa)
        assert bool(why) == (expect is not Termination.CONVERGED)
        if why:
            refuse_sigma(fa, why)
            assert np.isnan(fa.center_std).all() and np.isnan(fa.rotation_std_deg).all() and fa.covariance is None
            assert np.isnan(fa.result.camera_std[0]).all() and "not reported" in fa.sigma_refused
    # an adjustment that converged at once is not adjusted again
    calls = []
    outcome = [Termination.CONVERGED, Termination.CONVERGED]
    fa, used, steps = adjust_block(rec, None, np.arange(4), None, ("fx", "fy"), compute_covariance=False)
    assert calls == [50] and not getattr(fa, "first_termination", None)


def test_a_block_that_contradicts_its_gnss_after_stopping_at_its_limit_stays_rejected_when_adjusted_again():
    from thermogrammetry.sfm.block_gates import block_rejection

    conv = SimpleNamespace(termination=Termination.CONVERGED, reason="converged")
    assert block_rejection(1.0, 0.5, 0.0, conv) == ""
    assert "did not converge" in block_rejection(1.0, 0.5, 0.0, conv, stopped_at_limit=True)
    assert block_rejection(1.0, 0.1, 0.0, conv, stopped_at_limit=True) == ""  # its centres agree with their GNSS


def test_with_the_lens_sigma_the_focal_band_is_three_sigma_of_the_lens_value():
    from thermogrammetry.sfm.selfcal_ladder import FOCAL_PRIOR_K, FocalKnown, intrinsics_check

    start = {0: _cam(fx=758.3, fy=758.3)}
    fk = FocalKnown({0: True}, {0: 758.3}, {0: 37.9})
    assert fk.priors() == {0: (758.3, 37.9)}
    # the M3T strip over flat ground: 886 px against 758.3 ± 37.9 px is 3.4 σ -> refused (held)
    cam, why, check = intrinsics_check(_fa(_cam(fx=886.1, fy=886.1)), start, {0: ("fx", "fy")}, fk)
    assert check == "focal" and "3 σ" in why and FOCAL_PRIOR_K == 3.0
    # 2.5 σ: accepted; without a σ the 30 % band of the files' value applies (886 px is 17 % off: accepted)
    assert intrinsics_check(_fa(_cam(fx=853.0, fy=853.0)), start, {0: ("fx", "fy")}, fk)[2] == ""
    assert intrinsics_check(_fa(_cam(fx=886.1, fy=886.1)), start, {0: ("fx", "fy")}, FocalKnown({0: True}, {0: 758.3}))[2] == ""
