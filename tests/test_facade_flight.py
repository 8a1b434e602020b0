"""synthetic.facade_flight: the rendered frames agree with the true camera (distortion included), the EXIF is a
small DJI drone's (make, model, GPS; no focal length), the GNSS error is of consumer size."""

import io

import numpy as np
import pytest

from thermogrammetry.synthetic.facade_flight import (FacadeFlightConfig, facade_flight_frame_8bit, make_facade_flight,
                                                     render_facade_flight_frame, write_facade_flight)

CFG = FacadeFlightConfig(n_strips=2, n_per_strip=3, seed=3)


@pytest.fixture(scope="module")
def scene():
    return make_facade_flight(CFG)


def test_field_of_view_and_distortion_are_the_configured_ones(scene):
    cam = scene.camera
    # the horizontal half-field through the distortion: the ray of the image edge (on the principal row) is 28.5°
    # off-axis by construction; cx is 2 px right of the centre, so the edges are at cx ± 320 ± 2
    ray = cam.unproject(np.array([[cam["cx"] + 320.0, cam["cy"]], [cam["cx"] - 320.0, cam["cy"]]]))
    ang = np.degrees(np.arctan2(np.abs(ray[:, 0]), ray[:, 2]))
    np.testing.assert_allclose(ang, 28.5, atol=1e-6)
    # strong barrel: the pinhole corner (r² = 0.371) is pulled in by 1 - (1 + k1 r² + k2 r⁴) = 12.2 %: 38.7 px, 29.4 px
    xy = cam.project(np.array([[(639 - cam["cx"]) / cam["fx"], (479 - cam["cy"]) / cam["fy"], 1.0]]))[0]
    np.testing.assert_allclose([639 - xy[0], 479 - xy[1]], [38.7, 29.4], atol=0.1)


def test_glass_and_wall_render_where_the_true_camera_projects_them(scene):
    """Glass-pane centres (on the recessed plane) and wall points between windows, projected by the true camera
    model (the forward distortion, independent of the renderer's ray lattice), land on cold and on wall pixels."""
    c = scene.config
    ww, wh = c.window_size_m
    k = 0
    img = render_facade_flight_frame(scene, k, sensor=False)
    pose = scene.poses[k]
    glass, wall = [], []
    for col in range(8):
        for row in range(c.window_rows):
            x0, z0 = c.window_x0_m + col * c.window_period_m[0], c.window_z0_m + row * c.window_period_m[1]
            for fu, fv in ((0.25, 0.3), (0.75, 0.3), (0.25, 0.85), (0.75, 0.85)):
                glass.append([x0 + fu * ww, c.recess_m, z0 + fv * wh])
            wall.append([x0 + ww + (c.window_period_m[0] - ww) / 2, 0.0, z0 + wh / 2])
    n_seen = 0
    for pts, cold in ((np.array(glass), True), (np.array(wall), False)):
        xy = scene.camera.project(pts @ pose.R.T + pose.t)
        ok = (xy[:, 0] > 8) & (xy[:, 0] < 631) & (xy[:, 1] > 8) & (xy[:, 1] < 471)
        v = img[np.round(xy[ok, 1]).astype(int), np.round(xy[ok, 0]).astype(int)]
        n_seen += ok.sum()
        if cold:  # glass is 9 K colder (+ 0.8 K gradient); the wall within ±3 K of its mean
            assert ok.sum() >= 4 and np.all(v < c.wall_k - 6.0)
        else:
            assert ok.sum() >= 1 and np.all(np.abs(v - c.wall_k) < 3.0)
    assert n_seen >= 6


def test_written_jpegs_carry_the_drones_exif_and_consumer_gnss(scene, tmp_path):
    from PIL import Image

    from thermogrammetry.io.exif import read_exif
    from thermogrammetry.pipeline.project import FolderProject

    write_facade_flight(FolderProject(tmp_path), scene)
    files = sorted((tmp_path / "frames").glob("*.jpg"))
    assert len(files) == 6
    ex = read_exif(files[0].read_bytes())
    assert ex["make"] == "DJI" and ex["model"] == "M2ED" and ex.get("focal_length_mm") is None
    im = np.asarray(Image.open(files[0]))
    assert im.shape == (480, 640, 3) and im.dtype == np.uint8
    # GNSS error: bias σ 2.5 m + wander σ 1 m per axis -> each horizontal error well under 15 m, not exact
    lat0 = np.radians(c_lat := scene.config.origin_latlon[0])
    errs = []
    for f, p in zip(files, scene.poses):
        e = read_exif(f.read_bytes())
        g = scene.gnss[scene.names.index(f.stem)]
        assert abs(e["latitude_deg"] - g[0]) < 1e-6 and abs(e["longitude_deg"] - g[1]) < 1e-6
        errs.append(e["altitude_m"] - (scene.config.origin_alt_m + p.center[2]))
    assert 0.01 < np.max(np.abs(errs)) < 20.0
    assert c_lat == 47.3769 and np.isfinite(lat0)


def test_palette_is_monotonic_in_luminance_and_the_agc_stretches_each_frame(scene):
    from thermogrammetry.synthetic.facade_flight import IRON_PALETTE

    lum = IRON_PALETTE @ np.array([0.299, 0.587, 0.114])
    assert np.all(np.diff(lum) > 0)
    rgb = facade_flight_frame_8bit(render_facade_flight_frame(scene, 1))
    assert rgb[..., 0].max() == 255 and rgb.reshape(-1, 3).sum(1).min() < 30


def test_the_field_of_view_focal_through_the_distortion_is_the_lens_focal(scene):
    """The camera table's pinhole focal length of a 57° HFOV (589.4 px on 640 px), expressed through the true radial
    distortion, is the synthetic lens's focal length (built from tan(28.5°) independently): 653.4 px."""
    from thermogrammetry.camera.database import focal_through_distortion, table_focal

    tab = table_focal("DJI", "M2ED", (640, 480))
    assert tab.fov_half_extent_px == 320.0
    np.testing.assert_allclose(tab.f_px, 320.0 / np.tan(np.radians(28.5)), rtol=1e-12)
    f = focal_through_distortion(tab.f_px, tab.fov_half_extent_px, CFG.k1, CFG.k2)
    np.testing.assert_allclose(f, scene.camera["fx"], rtol=1e-9)
    assert focal_through_distortion(tab.f_px, 320.0) == tab.f_px
    assert np.isnan(focal_through_distortion(tab.f_px, 320.0, -3.0))  # folds the edge back


def test_restart_camera_only_for_a_field_of_view_start_that_the_distortion_moves():
    from thermogrammetry.pipeline.survey.camera_start import restart_camera

    g = {"f_px": 589.37, "focal_sigma_px": 38.3, "fov_half_extent_px": 320.0, "focal_source": "camera_table:M2ED"}
    inputs = {"images": [{"sensor": "thermal", "camera_guess": dict(g)}]}
    survey = {"camera_start": {"thermal": {"focal_source": "camera_table:DJI Mavic 2 Enterprise Dual"}},
              "cameras": {"thermal": {"params": {"fx": 599.0, "k1": -0.259, "k2": 0.012}}},
              "blocks": [{"self_calibration": ["fx", "fy", "k1", "k2"]}]}
    st = restart_camera(inputs, survey)["thermal"]
    # 589.37 / (1 - 0.259 x 0.2948 + 0.012 x 0.0869) = 637.2 px
    np.testing.assert_allclose(st["fx"], 589.37 / (1 - 0.259 * (320 / 589.37) ** 2 + 0.012 * (320 / 589.37) ** 4))
    assert st["k1"] == -0.259
    small = {**survey, "cameras": {"thermal": {"params": {"fx": 590.0, "k1": -0.02}}}}
    assert restart_camera(inputs, small) == {}  # 3.5 px: within 0.5 σ
    inputs["images"][0]["camera_guess"]["start"] = st
    assert restart_camera(inputs, survey) == {}  # once
    exif = {"images": [{"sensor": "thermal", "camera_guess": {**g, "fov_half_extent_px": None}}]}
    assert restart_camera(exif, survey) == {}  # a focal length in mm: no field of view to express
