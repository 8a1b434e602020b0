"""The synthetic building with facade detail (windows, frames, a door, spots) and texturing it with true poses.

Noise-free renderings (``sensor=False``) of black-body walls: a texel must equal the point truth up to the
sampling error (< 0.01 K on the smooth field, see test_texture.py) except where its source pixels straddle a
window, frame or door edge, where the truth jumps by kelvins. Those texels are excluded by their distance to the
edge in pixel footprints of the view they come from; everything else must hold the truth within 0.05 K.
"""

from __future__ import annotations

import numpy as np
import pytest

from cached_scenes import building_images
from thermogrammetry.errors import ConfigError
from thermogrammetry.products.texture import TextureConfig, TextureView, texture_mesh
from thermogrammetry.synthetic.building import (FRAME_M, GROUPS, BuildingConfig, apparent_temperature,
                                                discontinuity_distance, make_building,
                                                surface_temperature)

WALL = GROUPS.index("wall")


@pytest.fixture(scope="module")
def scene():
    return make_building(BuildingConfig(ground_margin_m=1.0, facade_detail=True))


def _on_south_wall(s, z):
    return np.array([[s, 0.0, z]])


def test_windows_door_and_spots_are_laid_out(scene):
    c = scene.config
    ops = scene.openings
    door = ops[0]
    assert door[2] == 0.0 and door[5] == 0.0  # the door stands on the ground, no frame
    wins = ops[1:]
    assert len(wins) >= 8 * c.floors  # every wall carries windows on every storey
    assert np.allclose(wins[:, 1] - wins[:, 0], c.window_width_m) and np.allclose(wins[:, 3] - wins[:, 2], c.window_height_m)
    assert np.ptp(wins[:, 4]) > 1.0  # glass temperatures differ from window to window
    area = 2 * (c.length_m + c.depth_m) * c.height_m
    assert len(scene.spots) == round(c.n_spots_per_m2 * area)
    # no detail unless asked for
    plain = make_building(BuildingConfig(ground_margin_m=1.0))
    assert len(plain.openings) == 0 and len(plain.spots) == 0
    assert np.isinf(discontinuity_distance(plain, _on_south_wall(3.0, 2.0), WALL)).all()


def test_glass_temperature_and_edge_distance(scene):
    # the first window on the south wall (s = x there)
    w = next(o for o in scene.openings[1:] if o[1] < scene.config.length_m)
    s0, s1, z0, z1, glass, dframe = w
    sc, zc = 0.5 * (s0 + s1), 0.5 * (z0 + z1)
    t = surface_temperature(scene, _on_south_wall(sc, zc), WALL)
    assert t[0] == pytest.approx(glass + 0.15 * (zc - z0), abs=1e-9)
    # distance to the nearest edge: the glass (inner) rectangle's nearer side
    d = discontinuity_distance(scene, _on_south_wall(sc, zc), WALL)[0]
    assert d == pytest.approx(min(0.5 * (s1 - s0), 0.5 * (z1 - z0)) - FRAME_M, abs=1e-9)
    # on the frame, 2 cm from its outer edge: the frame is warmer than the wall just outside by dframe
    d_out = discontinuity_distance(scene, _on_south_wall(s0 + 0.02, zc), WALL)[0]
    assert d_out == pytest.approx(0.02, abs=1e-9)
    jump = surface_temperature(scene, _on_south_wall(s0 + 1e-4, zc), WALL) - surface_temperature(scene, _on_south_wall(s0 - 1e-4, zc), WALL)
    assert jump[0] == pytest.approx(dframe, abs=0.01)  # the smooth field changes by < 0.01 K over 0.2 mm
    # off the walls: no discontinuity
    assert np.isinf(discontinuity_distance(scene, np.array([[3.0, 3.0, scene.config.height_m]]), GROUPS.index("roof"))).all()


def test_config_rejects_windows_that_do_not_fit():
    with pytest.raises(ConfigError, match="window_width_m"):
        BuildingConfig(facade_detail=True, window_width_m=2.8, window_spacing_m=3.0)
    with pytest.raises(ConfigError, match="window_height_m"):
        BuildingConfig(facade_detail=True, window_height_m=3.0)
    with pytest.raises(ConfigError, match="n_spots_per_m2"):
        BuildingConfig(n_spots_per_m2=-1)


def test_texture_of_a_facade_with_windows_true_poses(scene, scene_cache):
    images = building_images(scene_cache, scene)  # render_building_thermal(sensor=False), once per test run
    views = [TextureView(n, scene.thermal, p, images[k]) for k, (n, p) in enumerate(scene.stations)]
    res = texture_mesh(scene.vertices, scene.faces, views, TextureConfig(texel_size_m=0.04))
    sel, tx = res.texel_selection, res.texels
    ok = sel.source >= 0
    C = np.array([v.pose.center for v in views])[sel.source[ok]]
    P, F = tx.points[ok], tx.face[ok]
    err = sel.temperature_k[ok] - apparent_temperature(scene, P, F, C)
    # pixel footprint of the source view at each texel (distance / f / cos incidence)
    v = C - P
    dist = np.linalg.norm(v, axis=1)
    cos_t = np.abs(np.einsum("ij,ij->i", scene.face_normals[F], v / dist[:, None]))
    foot = dist / scene.thermal.K[0, 0] / np.maximum(cos_t, 0.2)
    clean = discontinuity_distance(scene, P, scene.face_group[F]) > 2.0 * foot
    wall = scene.face_group[F] == WALL
    assert ok.sum() > 100_000 and 0.8 < clean[wall].mean() < 0.99  # windows take a real share of the walls
    assert np.max(np.abs(err[clean])) < 0.05
    assert np.max(np.abs(err[~clean])) > 1.0  # the excluded texels do mix both sides of an edge


def test_user_files_hold_noisy_gnss_and_the_camera():
    """gnss.csv: the true centres + N(0, 3 cm) per axis (seeded), σ columns as given; camera.json: the true camera."""
    from thermogrammetry.camera import Camera
    from thermogrammetry.pipeline.project import MemoryProject
    from thermogrammetry.synthetic.building import write_building_user_files

    sc = make_building(BuildingConfig(n_stations=40))
    proj = MemoryProject()
    write_building_user_files(proj, sc)
    lines = proj.read_text("gnss.csv").splitlines()
    assert lines[0] == "image,X,Y,Z,sX,sY,sZ" and len(lines) == 41
    rows = [ln.split(",") for ln in lines[1:]]
    assert [r[0] for r in rows] == [n for n, _ in sc.stations]
    d = np.array([[float(v) for v in r[1:4]] for r in rows]) - np.array([p.center for _, p in sc.stations])
    rms = np.sqrt(np.mean(d**2))
    assert 0.02 < rms < 0.04  # 120 draws of N(0, 0.03²): the RMS lies within ±20 % with > 99 % probability
    assert all(r[4:] == ["0.03", "0.03", "0.05"] for r in rows)
    cam = Camera.from_dict(proj.read_json("camera.json"))
    assert cam.image_size == sc.thermal.image_size and cam["fx"] == sc.thermal["fx"]


def _detail_everywhere(scene, s, z, t):
    """The facade detail by its definition: every spot and every opening evaluated at every point."""
    per = 2 * (scene.config.length_m + scene.config.depth_m)
    for s0, z0, sig, amp in scene.spots:
        ds = (s - s0 + per / 2) % per - per / 2
        t = t + amp * np.exp(-0.5 * (ds**2 + (z - z0) ** 2) / sig**2)
    for s0, s1, z0, z1, glass, dframe in scene.openings:
        inside = (s >= s0) & (s <= s1) & (z >= z0) & (z <= z1)
        if dframe > 0:
            frame = inside & ~((s >= s0 + FRAME_M) & (s <= s1 - FRAME_M) & (z >= z0 + FRAME_M) & (z <= z1 - FRAME_M))
            t = np.where(frame, t + dframe, t)
            inside = inside & ~frame
        t = np.where(inside, glass + 0.15 * (z - z0), t)
    return t


@pytest.mark.parametrize("seed", [0, 5])
def test_detail_evaluated_near_each_spot_equals_the_definition_bit_for_bit(seed):
    """The renderer applies each spot only within the distance beyond which its term rounds away, and each opening
    only to the points inside it (``_detail``): the same floats as the definition, including across the wall's
    seam at s = 0 and at window edges; and not the same when a spot is moved (the comparison can fail)."""
    from thermogrammetry.synthetic.building import _detail

    sc = make_building(BuildingConfig(facade_detail=True, seed=seed))
    c = sc.config
    per = 2 * (c.length_m + c.depth_m)
    rng = np.random.default_rng(seed)
    s = rng.uniform(0, per, 200_000)
    z = rng.uniform(0, c.height_m, s.size)
    s[:2000] = rng.choice(np.r_[sc.openings[:, :2].ravel(), 0.0, per], 2000)  # on edges and on the seam
    s[2000:4000] = rng.uniform(-0.3, 0.3, 2000) % per  # the spots near the seam wrap around it
    t = 281.0 + 0.25 * z + 0.6 * np.sin(2 * np.pi * s / per)
    want = _detail_everywhere(sc, s, z, t)
    assert np.array_equal(_detail(sc, s, z, t), want)
    moved = sc.spots.copy()
    moved[0, 0] += 0.01
    from dataclasses import replace

    assert not np.array_equal(_detail(replace(sc, spots=moved), s, z, t), want)
