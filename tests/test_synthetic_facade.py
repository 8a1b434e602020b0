"""Facade scene: mesh, rig, radiometric and geometric truth of the thermal render, files."""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry import radiometry as rad
from thermogrammetry.errors import ConfigError
from thermogrammetry.pipeline import MemoryProject
from thermogrammetry.synthetic.facade import FacadeConfig, make_facade, render_facade_rgb, render_facade_thermal, write_facade
from thermogrammetry.synthetic.radiance import FlirCurve

pytest.importorskip("trimesh")


@pytest.fixture(scope="module")
def scene():
    return make_facade(FacadeConfig(thermal_size=(160, 120), thermal_focal_mm=4.5, rgb_size=(320, 240), rgb_focal_px=300.0,
                                    n_stations=2, supersample=1))


def test_rig_relative_pose_is_constant(scene):
    for _, pr, pt in scene.stations:
        rel = pt.compose(pr.inverse())
        np.testing.assert_allclose(rel.R, scene.rig_relative.R, atol=1e-12)
        np.testing.assert_allclose(rel.t, scene.rig_relative.t, atol=1e-12)
    # the thermal camera is rig_baseline_m from the RGB camera
    d = np.linalg.norm(scene.stations[0][2].center - scene.stations[0][1].center)
    assert d == pytest.approx(scene.config.rig_baseline_m, abs=1e-12)


def test_thermal_render_matches_forward_model_and_mesh(scene):
    out = render_facade_thermal(scene, 0, sensor=False, with_truth=True)
    c = scene.config
    cam = scene.thermal
    w, h = cam.image_size
    gy, gx = np.mgrid[0:h, 0:w]
    rays = cam.unproject(np.c_[gx.ravel(), gy.ravel()].astype(float))
    depth = out["depth_m"].ravel()
    hit = np.isfinite(depth)
    assert hit.mean() > 0.99  # the facade (and the street) fill the view
    # geometry: points from the depth truth lie on the wall (y = 0) or on the glass (y = recess)
    _, _, pose = scene.stations[0]
    pw = (rays[hit] * depth[hit, None] - pose.t) @ pose.R
    mat = out["material"].ravel()[hit]
    assert np.abs(pw[mat == "plaster", 1]).max() < 1e-6
    assert np.abs(pw[mat == "glass", 1] - c.recess_m).max() < 1e-6
    # radiometry: the FLIR measurement equation with the truth's emissivity, sky, air and path
    curve = FlirCurve()
    pc = rad.PlanckConstants(curve.r1, curve.r2, curve.b, curve.f, curve.o)
    dist = depth[hit] * np.linalg.norm(rays[hit], axis=1)
    params = rad.MeasurementParams(emissivity=out["emissivity"].ravel()[hit], reflected_temperature_k=c.sky_k,
                                   atmospheric_temperature_k=c.air_k, relative_humidity=c.relative_humidity, distance_m=dist)
    t_app = rad.temperature_from_raw(rad.raw_from_object_temperature(out["surface_temperature_k"].ravel()[hit], pc, params), pc)
    assert np.abs(out["image_k"].ravel()[hit] - t_app).max() < 0.01
    # the thermal bridges are visible: slab rows are warmer than mid-floor rows by > 0.5 K in the truth
    T = scene.wall_temperature(np.full(2, 2.0), np.array([c.height_m / c.floors, 0.25 * c.height_m / c.floors]))
    assert T[0] - T[1] > 0.5


def test_write_facade_files(scene):
    proj = MemoryProject()
    s = write_facade(proj, scene)
    assert s["stations"] == 2
    obj = proj.read_text("facade/mesh.obj")
    assert obj.count("\nv ") == len(scene.vertices) and obj.count("\nf ") == len(scene.faces)
    cams = proj.read_json("facade/cameras.json")
    assert set(cams["cameras"]) == {"thermal", "rgb"} and len(cams["stations"]) == 2
    grid = proj.read_array("facade/truth/temperature_grid.npy")
    meta = proj.read_json("facade/truth/temperature_grid.json")
    assert list(grid.shape) == meta["shape"]
    assert grid[10, 20] == pytest.approx(float(scene.wall_temperature(20 * 0.02, 10 * 0.02)), abs=1e-4)
    rgb = render_facade_rgb(scene, 1)
    assert rgb.shape == (240, 320, 3) and rgb.dtype == np.uint8
    for k in ("facade/thermal/S00.tif", "facade/rgb/S01.png", "facade/truth/points.csv"):
        assert proj.exists(k)


def test_bad_facade_configuration():
    with pytest.raises(ConfigError, match="unknown"):
        FacadeConfig.from_dict({"widht_m": 3})
    with pytest.raises(ConfigError, match="do not fit"):
        FacadeConfig(width_m=5.0, windows_per_floor=5)
