"""`survey` on terrestrial rings of thermal frames around a building (synthetic.building, 40 stations, 320 x 240
frames with ~200 SIFT features each, RTK-like GNSS σ 3/5 cm, the true camera file), default options.

Two rings where the old settings failed in opposite ways: seed 1 broke at one station whose resection had 10 PnP
inliers (12 were required: 19/40 oriented); seed 0 gave a 20-image block 5.6° RMS / 19° max off its true rotations
and reported it as oriented (its final adjustment stopped at the iteration limit with 40 % of the centres > 5 σ
from their GNSS), later rejected it whole; seed 2's second block was lost to another block's similarity."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cached_scenes import building_ring_survey
from thermogrammetry.synthetic.building import BuildingConfig, make_building


def _survey(scene_cache, extra=(), **kw):
    # the ring's frames, user files and survey are built once per test run (tests/cached_scenes.py): the ring of
    # seed 3 with default options is also the one tests/test_texture_meshfit_ring.py surveys
    config = BuildingConfig(**{"facade_detail": True, "n_stations": 40, **kw})
    sc = make_building(config)
    _, out, code = building_ring_survey(scene_cache, config, extra)
    truth = dict(sc.stations)
    errs = {}
    if (out / "cameras.json").exists():
        for c in json.loads((out / "cameras.json").read_text())["images"]:
            R = np.array(c["cam_from_world"]["R"])
            errs[c["name"]] = float(np.degrees(Rotation.from_matrix(R @ truth[c["name"]].R.T).magnitude()))
    return code, json.loads((out / "survey.json").read_text()), errs


@pytest.mark.slow
def test_ring_is_not_broken_by_one_weak_resection(scene_cache):
    code, s, errs = _survey(scene_cache, seed=1)
    assert code == 0
    # measured 33/40 in one block, 0.80 deg RMS / 1.58 max (OpenCV 5.0, NumPy 2.4; 38/40 at 0.57 deg with the
    # packages of 2026-11-26); 34/40, 0.70 / 1.41 deg since T35 is added at its GNSS position. The same code before
    # the block bookkeeping of this change: 7/40 at 29 deg in a local frame on these packages. The orientation's
    # second block (4 stations on a 27 deg arc) has rotation σ 7.8 deg: rejected, not reported
    assert s["images_oriented"] >= 31 and s["components"][0] == s["images_oriented"]
    e = np.array(list(errs.values()))
    # since the rejected 4-station arc (T36-T39) and T35 are added to the block at their RTK GNSS positions: 38/40,
    # 0.81 deg RMS, max 1.96 deg (T36, at the end of that chain; the others 0.95-1.52 deg)
    assert np.sqrt(np.mean(e**2)) < 1.0 and e.max() < 2.5


@pytest.mark.slow
def test_wrongly_resected_images_are_left_out_of_a_block_that_contradicts_its_gnss(scene_cache):
    code, s, errs = _survey(scene_cache, seed=0)
    # the orientation's largest block (T02-T21) holds three wrongly resected stations (T02-T04, 1.2-7 m from their
    # GNSS): its final adjustment stopped at the iteration limit and the whole block used to be rejected (0/40).
    # Without the images that no similarity puts near their GNSS it is adjusted again: 17 images, 0.89 deg RMS
    # (max 1.77) -- whatever is reported as oriented must be right (no rotation beyond 3 deg; the wrong ones 19 deg)
    assert code == 0
    assert all(e < 3.0 for e in errs.values()), errs
    assert s["images_oriented"] >= 15 and s["components"][0] == s["images_oriented"]
    assert np.sqrt(np.mean(np.square(list(errs.values())))) < 1.2  # measured 0.89 deg (17 images), 0.84 deg (28)
    # T02-T04 left out of the block as wrong resections (17 images), then placed at their RTK GNSS positions and turned
    # to the block's points. Whether the block adjusted with them alone converges depends on the CPU's floating-point
    # paths: it did not on the machines of 2026-11-29 (not kept then, said in a note; added with the arcs below), it did
    # on an AVX2-only AMD EPYC (2026-12-02: added in that first round). Either way a note names them ...
    assert any("T04, T02, T03" in n and (("placed at their GNSS positions" in n and "not kept" in n)
                                         or "added at their GNSS positions" in n) for n in s["notes"])
    # two short arcs (7 and 4 stations) whose GNSS positions do not fix their rotation (σ 1.5 and 5.3 deg; they were
    # 5-7 deg off) are rejected, not reported as oriented as blocks of their own
    weak = [b["rejected"] for b in s["blocks"] if "does not fix its rotation" in (b.get("rejected") or "")]
    assert len(weak) == 2
    # ... and after those blocks were rejected, their images and T02-T04 were placed at their GNSS positions in block
    # 1 together: 28/40 in one block, 0.84 deg RMS (max 1.38; the added 0.63-1.38 deg)
    added = s["blocks"][0].get("added_at_gnss", [])
    assert {"T02", "T03", "T04"} <= set(added) and s["images_oriented"] >= 25
    assert max(errs[k] for k in added) < 2.0
    # the rejected blocks' entries say where their images went: every moved image is one block 1 added, and the
    # moved ones are among the rejected blocks' images (the two arcs: 11 stations)
    moved = [nm for b in s["blocks"] if b.get("rejected") for nm in (b.get("moved_to_blocks") or {}).get("1", [])]
    assert moved and set(moved) <= set(added) and len(moved) == len(set(moved)) <= 11


@pytest.mark.slow
def test_second_block_is_adjusted_in_its_own_frame(scene_cache):
    # seed 2: the orientation gives two blocks (23 and 13 stations). Each block's similarity to the GNSS used to move
    # every point of the survey, so the second block's points reached its final adjustment in another frame than its
    # cameras: it diverged and was rejected (23/40). Now both are oriented
    code, s, errs = _survey(scene_cache, seed=2)
    assert code == 0
    assert s["images_oriented"] >= 34 and len(s["components"]) == 2  # measured 36: [23, 13]
    e = np.array(list(errs.values()))
    assert np.sqrt(np.mean(e**2)) < 1.0 and e.max() < 2.0  # measured 0.80 / 1.39 deg


@pytest.mark.slow
def test_one_far_point_does_not_make_a_block_singular(scene_cache):
    # a held-out ring (48 stations, seed 3, occluder 7 m along the south wall, 1 m of ground) with --refine-ties lsm:
    # its 29-image block's final adjustment stopped "datum or parameters undetermined (condition 4.77e+300)" and the
    # block was rejected (15/48 oriented). The cause was one tie point whose rays had become parallel: left out, the
    # block solves (44/48 in [29, 15], 0.78 deg RMS, max 1.27)
    code, s, errs = _survey(scene_cache, seed=3, n_stations=48, occluder_x_m=7.0, ground_margin_m=1.0,
                            extra=["--refine-ties", "lsm"])
    assert code == 0
    assert s["images_oriented"] >= 40 and s["components"][0] >= 25
    e = np.array(list(errs.values()))
    assert np.sqrt(np.mean(e**2)) < 1.1 and e.max() < 2.0
    # whether that point drifts far enough to make the solve singular depends on the CPU's floating-point paths: the
    # note was there on the machines of 2026-11-27 and is not on an AMD EPYC of 2026-11-28 (same packages, and main
    # 8d3d00d as well). Either way the block must solve, and a final adjustment that stopped must have been solved
    # again without the parallel-ray points (sfm.georef.MIN_FINAL_TRI_ANGLE_DEG; the selection: tests/test_tracks.py)
    stopped = [n for n in s["notes"] if "final adjustment (round" in n and "stopped" in n]
    assert all("solved again without the points whose rays meet at less than" in n for n in stopped), stopped


@pytest.mark.slow
def test_stations_with_few_ties_are_added_at_their_gnss_position(scene_cache):
    # the held-out ring with default options: T47-T02 share 20-30 verified matches with their neighbours but too few
    # oriented points for a resection (PnP needs 10): 44/48 in [26, 18]. With their RTK centres known, three
    # unknowns are left: each is turned to the block's points at its GNSS position (sfm.reconstruction.
    # register_with_known_centres), the next one uses the points the previous one triangulated, and the block is
    # adjusted again: 48/48 in [26, 22], 0.78 deg RMS (max 1.49; the added four 0.89-1.17 deg, as their neighbours)
    code, s, errs = _survey(scene_cache, seed=3, n_stations=48, occluder_x_m=7.0, ground_margin_m=1.0)
    assert code == 0 and s["images_oriented"] == 48
    assert any("added at their GNSS positions" in n and "T47, T00, T01, T02" in n for n in s["notes"])
    e = np.array(list(errs.values()))
    assert np.sqrt(np.mean(e**2)) < 1.0 and e.max() < 2.0
    assert max(errs[k] for k in ("T47", "T00", "T01", "T02")) < 1.6
