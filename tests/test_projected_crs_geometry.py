"""Meshes in projected-CRS coordinates (EPSG:2056 eastings ~2.6e6 m, UTM northings ~5.5e6 m).

Embree (ray casting) and xatlas (charts) compute in float32, whose spacing at 2.6e6 is 0.25 m and at 5.5e6 is
0.5 m: cast against such a mesh, rays hit the wrong triangle and the occlusion tests (2 cm) fail. Before the
texture, facade and correction code moved to a local frame, the synthetic building textured at an EPSG:2056
offset had 0.8 % of its clean texels more than 0.05 K off (max 23.6 K; at the origin max 0.032 K), and its GLB
positions were rounded to 0.25 m. Every geometric result must be the same at the origin and at the offset:
the offset is a translation of the whole scene, poses included.
"""

from __future__ import annotations

import io

import numpy as np
import pytest

from thermogrammetry.geometry import Pose
from thermogrammetry.products.texture import TextureConfig, TextureView, texture_mesh
from thermogrammetry.synthetic.building import (BuildingConfig, apparent_temperature, discontinuity_distance,
                                                make_building, render_building_thermal)

LV95 = np.array([2_600_123.0, 1_200_456.0, 452.0])  # EPSG:2056 (Bern), orthometric height
UTM = np.array([500_321.0, 5_500_654.0, 300.0])  # a UTM zone's northing: float32 spacing 0.5 m


def _shifted(views, off):
    return [TextureView(v.name, v.camera, Pose(v.pose.R, v.pose.t - v.pose.R @ off), v.image_k) for v in views]


@pytest.fixture(scope="module")
def scene():
    sc = make_building(BuildingConfig(n_stations=8, facade_detail=True, ground_margin_m=1.0))
    views = [TextureView(n, sc.thermal, p, render_building_thermal(sc, k, sensor=False)["image_k"])
             for k, (n, p) in enumerate(sc.stations)]
    return sc, views


@pytest.fixture(scope="module")
def textured(scene):
    sc, views = scene
    cfg = TextureConfig(texel_size_m=0.04)
    return {name: texture_mesh(sc.vertices + off, sc.faces, _shifted(views, off), cfg)
            for name, off in (("origin", np.zeros(3)), ("lv95", LV95), ("utm", UTM))}


def _clean_errors(sc, res, off):
    """|texel - noise-free truth| of texels >= 2 pixel footprints from a temperature discontinuity."""
    sel, tx = res.texel_selection, res.texels
    ok = sel.source >= 0
    P, F = tx.points[ok] - off, tx.face[ok]
    C = np.array([p.center for _, p in sc.stations])[sel.source[ok]]
    err = np.abs(sel.temperature_k[ok] - apparent_temperature(sc, P, F, C))
    v = C - P
    dist = np.linalg.norm(v, axis=1)
    cos_t = np.abs(np.einsum("ij,ij->i", sc.face_normals[F], v / dist[:, None]))
    foot = dist / sc.thermal.K[0, 0] / np.maximum(cos_t, 0.2)
    return err[discontinuity_distance(sc, P, sc.face_group[F]) > 2.0 * foot]


@pytest.mark.parametrize("name,off", [("lv95", LV95), ("utm", UTM)])
def test_texture_at_projected_coordinates_equals_the_texture_at_the_origin(scene, textured, name, off):
    sc, _ = scene
    a, b = textured["origin"], textured[name]
    assert a.atlas.size == b.atlas.size and np.array_equal(a.texels.rc, b.texels.rc)  # same charts
    np.testing.assert_allclose(b.texels.points - off, a.texels.points, atol=1e-6)  # texel points in the input's frame
    sa, sb = a.texel_selection, b.texel_selection
    # the same image for every texel and the same value to float rounding of the projections (the frames
    # vary by < 0.5 K per pixel: 1e-4 K is a 2e-4 px shift)
    assert np.array_equal(sa.source, sb.source)
    both = sa.source >= 0
    assert both.sum() > 50_000
    assert np.max(np.abs(sa.temperature_k[both] - sb.temperature_k[both])) < 1e-4
    e = _clean_errors(sc, b, off)
    assert len(e) > 40_000 and e.max() < 0.05  # truth: the 0.05 K (max 0.032 K at the origin)


def test_glb_positions_keep_millimetres_at_projected_coordinates(textured):
    import trimesh

    from thermogrammetry.products.texture_export import glb_bytes, preview_rgb

    res = textured["lv95"]
    glb = glb_bytes(res, preview_rgb(res.temperature_k))
    mesh = trimesh.load(io.BytesIO(glb), file_type="glb", force="scene").to_geometry()
    want = res.vertices[res.atlas.vmapping]
    assert mesh.vertices.shape == want.shape
    # Y-up float32 positions about the offset in the asset's extras: ~1e-6 m for a 30 m building (0.25 m in
    # world float32)
    n = int.from_bytes(glb[12:16], "little")
    ox, oy, oz = __import__("json").loads(glb[20:20 + n])["asset"]["extras"]["thermogrammetry"]["offset"]
    P = np.asarray(mesh.vertices, float)
    back = np.column_stack([P[:, 0] + ox, -P[:, 2] + oy, P[:, 1] + oz])
    assert np.max(np.abs(back - want)) < 1e-3


def test_mesh_rasters_at_projected_coordinates(scene):
    from thermogrammetry.products.surfaces import mesh_rasters

    sc, views = scene
    v = views[0]
    w, h = v.camera.image_size
    gy, gx = np.mgrid[0:h, 0:w].astype(float)
    rays = v.camera.unproject(np.stack([gx.ravel(), gy.ravel()], 1)) @ v.pose.R
    rays = (rays / np.linalg.norm(rays, axis=1, keepdims=True)).reshape(h, w, 3)
    C = v.pose.center
    a = mesh_rasters(C, rays, (0, 0, 1), sc.vertices, sc.faces)
    b = mesh_rasters(C + LV95, rays, (0, 0, 1), sc.vertices + LV95, sc.faces)
    hit = a.plane >= 0
    assert hit.mean() > 0.5
    assert np.array_equal(a.plane, b.plane)
    assert np.nanmax(np.abs(a.distance_m - b.distance_m)) < 1e-6
    assert np.nanmax(np.abs(a.angle_rad - b.angle_rad)) < 1e-9
