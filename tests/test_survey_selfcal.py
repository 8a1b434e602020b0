"""Self-calibration that the block can carry (``pipeline.survey._adjust_block``).

A weak block (few frames, little baseline, wrong matches) can "self-calibrate" into nonsense: on the real
Thermitage fresco walls, thermal only, 6 frames tied by wrong matches came out with fy/fx = 1.26 and a
rank-deficient solve and were reported as an oriented block. The survey now steps down a ladder of fewer
parameters while the solve is rank deficient, a free σ is not finite or the intrinsics are implausible, and
rejects the block when even the fixed camera leaves the orientation undetermined.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import thermogrammetry.pipeline.survey as sv
from thermogrammetry.camera import Camera
from thermogrammetry.results import Termination

W, H = 640, 512


def _cam(**kw):
    p = {"fx": 765.0, "fy": 765.0, "cx": 320.0, "cy": 256.0}
    p.update(kw)
    return Camera("opencv", (W, H), p, name="thermal")


def _fa(cam, termination=Termination.CONVERGED, std=None, reason=""):
    res = SimpleNamespace(termination=termination, success=termination.success, reason=reason,
                          camera_std=[np.asarray(std, float)] if std is not None else [])
    return SimpleNamespace(result=res, cameras_after={0: cam}, covariance_asked=True)


def _block(n, cameras=None, image_camera=None):
    """A stand-in for a Reconstruction of n registered images (what _adjust_block touches)."""
    return SimpleNamespace(R=np.repeat(np.eye(3)[None], n, 0), t=np.zeros((n, 3)), registered=np.ones(n, bool),
                           component=np.zeros(n, int), points=np.zeros((4, 3)), obs_valid=np.ones(8, bool),
                           cameras=cameras or [_cam()],
                           image_camera=np.zeros(n, int) if image_camera is None else np.asarray(image_camera),
                           status=[SimpleNamespace(registered=True, component=0, reason="") for _ in range(n)])


def test_ladder_rungs_follow_the_request():
    rungs = sv._ladder_sets(sv.SELF_CALIBRATION, [0])[0]
    assert [set(r) for r in rungs] == [set(sv.SELF_CALIBRATION), {"fx", "fy", "k1", "k2"}, {"fx", "fy", "k1"},
                                       {"fx", "fy"}, set()]
    # a camera held fixed stays fixed; a smaller request starts lower and never repeats a rung
    lad = sv._ladder_sets({0: (), 1: ("fx", "fy", "k1")}, [0, 1])
    assert lad[1] == [("fx", "fy", "k1"), ("fx", "fy"), ()] and lad[0] == [()]


@pytest.mark.parametrize("est, words", [
    (dict(fy=963.0), "fy/fx = 1.259"),
    (dict(fx=1100.0, fy=1100.0), "focal length"),
    (dict(cy=454.0), "principal point"),
    (dict(k1=-0.9), "radial distortion"),
])
def test_implausible_intrinsics_are_named(est, words):
    free = {0: sv.SELF_CALIBRATION}
    cam, why = sv._intrinsics_problem(_fa(_cam(**est)), {0: _cam()}, free)
    assert cam == 0 and words in why and why.startswith("camera thermal:")


def test_plausible_intrinsics_pass_at_the_edges_of_the_bands():
    # 4 % aspect, fx +23 % and fy +28 %, 14 % of the frame for the principal point, 9.5 % corner distortion
    ok = _cam(fx=940.0, fy=940.0 * 1.04, cx=320 + 0.14 * W, cy=256 - 0.14 * H, k1=-0.5)
    start = _cam(fx=765.0, fy=765.0)
    assert sv._intrinsics_problem(_fa(ok), {0: start}, {0: sv.SELF_CALIBRATION}) == (None, "")
    # the same camera held fixed is not judged
    assert sv._intrinsics_problem(_fa(_cam(fy=963.0)), {0: _cam()}, {0: ()}) == (None, "")


def test_rank_deficient_solve_and_undetermined_sigma_are_refused():
    cam = _cam()
    c, why = sv._intrinsics_problem(_fa(cam, Termination.RANK_DEFICIENT, reason="free network: rank defect"),
                                    {0: cam}, {0: sv.SELF_CALIBRATION})
    assert c is None and "rank defect" in why
    std = np.full(len(cam.param_names), 0.5)
    std[cam.param_names.index("cy")] = np.nan
    c, why = sv._intrinsics_problem(_fa(cam, std=std), {0: cam}, {0: sv.SELF_CALIBRATION})
    assert c == 0 and "σ of cy not finite" in why
    # NaN σ of a parameter held fixed is expected, not a problem
    assert sv._intrinsics_problem(_fa(cam, std=std), {0: cam}, {0: ("fx", "fy")}) == (None, "")


def test_adjust_block_steps_down_and_restores_the_block(monkeypatch):
    """Each rung starts from the same block: the state the refused solve left is undone."""
    import thermogrammetry.sfm.georef as georef

    n = 3
    rec = _block(n)
    calls = []

    def fake_final(rec_, xy, images, ctrl, *, self_calibrate, rig=None, **kw):
        calls.append((dict(self_calibrate), rec_.t.copy(), rec_.cameras[0]))
        rec_.t += 1.0  # what a solve does to the block
        free = set(self_calibrate[0])
        rec_.cameras[0] = _cam(fy=963.0) if "cy" in free else _cam(fx=770.0, fy=771.0)
        return SimpleNamespace(result=SimpleNamespace(termination=Termination.CONVERGED, success=True, reason="",
                                                      camera_std=[]), notes=[])

    monkeypatch.setattr(georef, "final_adjustment", fake_final)
    fa, used, steps = sv._adjust_block(rec, None, np.arange(n), None, sv.SELF_CALIBRATION, compute_covariance=True)
    assert len(calls) == 2 and set(used[0]) == {"fx", "fy", "k1", "k2"}
    assert np.all(calls[1][1] == 0.0)  # the second solve started from the block as it was
    assert calls[1][2].param_dict["fy"] == 765.0  # ... and from the starting camera
    assert len(steps) == 1 and "fy/fx = 1.259" in steps[0] and "adjusted again with thermal: fx, fy, k1, k2" in steps[0]
    assert rec.cameras[0].param_dict["fx"] == 770.0 and np.all(rec.t == 1.0)

    # nothing determines the block, not even with the camera fixed: every rung tried, the last step says so
    calls.clear()

    def never(rec_, xy, images, ctrl, *, self_calibrate, rig=None, **kw):
        calls.append(dict(self_calibrate))
        return SimpleNamespace(result=SimpleNamespace(termination=Termination.RANK_DEFICIENT, success=False,
                                                      reason="free network: rank defect larger than the 7 datum "
                                                             "parameters", camera_std=[]), notes=[])

    monkeypatch.setattr(georef, "final_adjustment", never)
    fa, used, steps = sv._adjust_block(rec, None, np.arange(n), None, sv.SELF_CALIBRATION)
    assert [set(c[0]) for c in calls][-1] == set() and len(calls) == 5
    assert steps[-1].startswith("with the camera held fixed") and "rank defect" in steps[-1]


def test_only_the_camera_that_cannot_be_calibrated_steps_down(monkeypatch):
    """RGB + thermal: the thermal camera with two frames of its own runs away, the RGB camera is determined.
    Only the thermal camera steps down (measured on the frescoes through a rig: one ladder for both cameras
    held the well-determined RGB camera fixed too)."""
    import thermogrammetry.sfm.georef as georef

    n = 4
    rgb = Camera("opencv", (1920, 1080), {"fx": 1700.0, "fy": 1700.0, "cx": 960.0, "cy": 540.0}, name="rgb")
    rec = _block(n, [_cam(), rgb], [0, 0, 1, 1])
    calls = []

    def fake_final(rec_, xy, images, ctrl, *, self_calibrate, rig=None, **kw):
        calls.append({c: tuple(v) for c, v in self_calibrate.items()})
        # the thermal camera runs away while its focal length is free with more than fx, fy
        free = set(self_calibrate[0])
        rec_.cameras[0] = _cam(fy=316.0) if "fy" in free and len(free) > 2 else _cam(k1=-0.2) if "fy" not in free else \
            _cam(fx=770.0, fy=772.0)
        rec_.cameras[1] = Camera("opencv", (1920, 1080), {"fx": 1694.0, "fy": 1701.0, "cx": 965.0, "cy": 545.0}, name="rgb")
        return SimpleNamespace(result=SimpleNamespace(termination=Termination.CONVERGED, success=True, reason="",
                                                      camera_std=[]), notes=[])

    monkeypatch.setattr(georef, "final_adjustment", fake_final)
    fa, used, steps = sv._adjust_block(rec, None, np.arange(n), None, sv.SELF_CALIBRATION)
    assert [set(c[1]) for c in calls] == [set(sv.SELF_CALIBRATION)] * 2  # the RGB camera keeps every parameter
    # the thermal camera's focal length ran away: it holds its interior orientation and calibrates distortion
    assert [set(c[0]) for c in calls] == [set(sv.SELF_CALIBRATION), {"k1", "k2", "p1", "p2"}]
    assert set(used[1]) == set(sv.SELF_CALIBRATION) and set(used[0]) == {"k1", "k2", "p1", "p2"}
    assert len(steps) == 1 and steps[0].startswith("self-calibration of thermal:")
    # a refusal that is not the focal length (fy/fx) steps down the usual ladder, still only for that camera
    calls.clear()
    monkeypatch.setattr(georef, "final_adjustment", lambda rec_, *a, self_calibrate, **kw: (
        calls.append({c: tuple(v) for c, v in self_calibrate.items()}),
        rec_.cameras.__setitem__(0, _cam(fy=840.0) if len(self_calibrate[0]) > 2 else _cam(fx=770.0, fy=772.0)),
        SimpleNamespace(result=SimpleNamespace(termination=Termination.CONVERGED, success=True, reason="",
                                               camera_std=[]), notes=[]))[-1])
    fa, used, steps = sv._adjust_block(rec, None, np.arange(n), None, sv.SELF_CALIBRATION)
    assert [len(c[0]) for c in calls] == [8, 4, 3, 2] and set(used[0]) == {"fx", "fy"}
    assert all(set(c[1]) == set(sv.SELF_CALIBRATION) for c in calls) and len(steps) == 3


def test_focal_band_only_when_the_start_is_the_files_focal_length():
    """A video or an image without EXIF starts from a guess (1 x the width) that self-calibration must be free
    to correct (2.3x on the synthetic video of tests/test_io_video.py); the ±30 % band applies to EXIF starts."""
    est = _fa(_cam(fx=765.0 * 2.3, fy=765.0 * 2.3))
    assert sv._intrinsics_problem(est, {0: _cam()}, {0: sv.SELF_CALIBRATION}, {0: True})[0] == 0
    assert sv._intrinsics_problem(est, {0: _cam()}, {0: sv.SELF_CALIBRATION}, {0: False}) == (None, "")
    # the aspect ratio is checked whatever the start
    assert "fy/fx" in sv._intrinsics_problem(_fa(_cam(fx=1700.0, fy=1900.0)), {0: _cam()}, {0: sv.SELF_CALIBRATION}, {0: False})[1]
    inputs = {"images": [{"camera_guess": {"source": "EXIF focal 13 mm / pitch 17 µm"}},
                         {"camera_guess": {"source": "EXIF focal 9 mm, pixel pitch assumed 17 µm"}},
                         {"camera_guess": {"source": "no focal length in the file: 1.0 x image width assumed (self-calibrated)"}},
                         {"camera_guess": {"source": "EXIF 35 mm-equivalent focal 40 mm"}}]}
    rec = SimpleNamespace(image_camera=np.array([0, 1, 2, 3]))
    assert [sv._focal_from_exif(inputs, rec, k) for k in range(4)] == [True, False, False, True]


def test_an_implausible_focal_length_holds_the_interior_orientation_and_calibrates_distortion(monkeypatch):
    """A block that does not determine its focal length (one strip over flat ground, no GCPs) runs it away on every
    rung that frees it. Once refused for that, the camera keeps focal length and principal point at their start and
    self-calibrates distortion only (FIXED_INTERIOR_LADDER) instead of freeing the focal length with the distortion
    held: on the real M3T strip 0008-0023 the old ladder accepted fx/fy 738.6/714.9 px (truth ~783/781) and the
    rotations were 2.33 deg off; now 0.28 deg. Other refusals step down the usual ladder (test above)."""
    import thermogrammetry.sfm.georef as georef

    n = 3
    rec = _block(n)
    calls = []

    def fake_final(rec_, xy, images, ctrl, *, self_calibrate, rig=None, **kw):
        free = set(self_calibrate[0])
        calls.append(free)
        # the focal length runs away whenever it is free; distortion alone is fine unless p1/p2 are free
        rec_.cameras[0] = (_cam(fx=2000.0, fy=1990.0) if "fx" in free else
                           _cam(k1=-0.9) if "p1" in free else _cam(k1=-0.3, k2=0.08))
        return SimpleNamespace(result=SimpleNamespace(termination=Termination.CONVERGED, success=True, reason="",
                                                      camera_std=[]), notes=[])

    monkeypatch.setattr(georef, "final_adjustment", fake_final)
    fa, used, steps = sv._adjust_block(rec, None, np.arange(n), None, sv.SELF_CALIBRATION, focal_known={0: True})
    assert calls == [set(sv.SELF_CALIBRATION), {"k1", "k2", "p1", "p2"}, {"k1", "k2"}]
    assert set(used[0]) == {"k1", "k2"} and rec.cameras[0].param_dict["fx"] == 765.0
    assert "focal length 2000.0/1990.0" in steps[0] and "held at their start" in steps[0]
    assert "radial distortion" in steps[1] and "adjusted again with thermal: k1, k2" in steps[1]
    # without the file's focal length (a guess) the focal band does not apply: the usual ladder, focal kept free
    calls.clear()
    fa, used, steps = sv._adjust_block(rec, None, np.arange(n), None, sv.SELF_CALIBRATION, focal_known={0: False})
    assert calls == [set(sv.SELF_CALIBRATION)] and set(used[0]) == set(sv.SELF_CALIBRATION)
    assert sv._fixed_interior_rungs(("fx", "fy", "k1"), [("fx", "fy", "k1")]) == [("k1",), ()]


def test_calibration_choice_says_how_each_focal_length_was_treated_and_why():
    """``blocks[].calibration``: per camera the treatment of its focal length (self-calibrate / prior / hold), the
    parameters estimated and the reason, from what the ladder did."""
    from types import SimpleNamespace

    from thermogrammetry.sfm.selfcal_ladder import calibration_choice

    ids = ["thermal", "rgb"]
    fa = SimpleNamespace(focal_priors_used={0: (741.2, 37.1)})
    steps = ["self-calibration of thermal: fx, fy refused: focal length 2692 px is more than 3 σ from 741 px; "
             "adjusted again with thermal: k1, k2, p1, p2"]
    got = calibration_choice(("fx", "fy", "k1"), {0: ("fx", "fy", "k1"), 1: ("fx", "fy")}, fa, [], ids)
    assert got["thermal"]["choice"] == "prior" and "741.2 ± 37.1 px" in got["thermal"]["reason"]
    assert got["thermal"]["estimated"] == ["fx", "fy", "k1"]
    assert got["rgb"]["choice"] == "self-calibrate"
    held = calibration_choice({0: ("fx", "fy", "k1", "k2")}, {0: ("k1", "k2", "p1", "p2")}, SimpleNamespace(), steps, ids)
    assert held["thermal"]["choice"] == "hold" and "2692 px" in held["thermal"]["reason"]
    given = calibration_choice({0: ()}, {0: ()}, SimpleNamespace(focal_priors_used=None), [], ids)
    assert given == {"thermal": {"choice": "hold", "estimated": [], "reason": given["thermal"]["reason"]}}
    assert "--camera" in given["thermal"]["reason"]
