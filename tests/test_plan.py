"""Flight planning (Khodaei et al. 2015 §2.2): GSD ↔ height, overlaps, line spacing, video extraction, waypoints."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from thermogrammetry.cli.main import main
from thermogrammetry.errors import ConfigError
from thermogrammetry.sfm.plan import plan_flight


def _rect(cx, cy, a, b, ang_deg):
    t = np.deg2rad(ang_deg)
    u, v = np.array([np.cos(t), np.sin(t)]), np.array([-np.sin(t), np.cos(t)])
    return np.array([[cx, cy] + su * a / 2 * u + sv * b / 2 * v for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1))])


def test_plan_numbers_and_coverage():
    poly = _rect(2_540_000.0, 1_150_000.0, 400.0, 200.0, 30.0)  # long side 30 deg north of east
    p = plan_flight(1000.0, (640, 512), poly, gsd_m=0.1, forward_overlap=0.8, sidelap=0.6, speed_mps=5.0, video_fps=30.0)
    assert p.height_m == pytest.approx(100.0, rel=1e-12)
    assert (p.footprint_along_m, p.footprint_across_m) == pytest.approx((51.2, 64.0), rel=1e-12)
    assert p.trigger_distance_m == pytest.approx(10.24, rel=1e-12)
    assert p.line_spacing_m == pytest.approx(25.6, rel=1e-12)
    assert p.heading_deg == pytest.approx(60.0, abs=1e-6)  # 30 deg from east = 60 deg from north
    assert p.extract_every_n_frames == 61 and p.extraction_rate_hz == pytest.approx(30 / 61)
    assert p.n_lines == 9  # edges inside 2 strips: ceil((200 - 2 * (32 - 25.6)) / 25.6) + 1
    assert p.flight_time_s == pytest.approx(p.flight_length_m / 5.0)
    # every ground point of the area is inside >= 4 (along) x 2 (across) footprints
    photos = [w for w in p.waypoints if w.kind == "photo"]
    assert len(photos) == p.n_photos
    t = np.deg2rad(30.0)
    du, dv = np.array([np.cos(t), np.sin(t)]), np.array([-np.sin(t), np.cos(t)])
    c = np.array([[w.x, w.y] for w in photos])
    rng = np.random.default_rng(1)
    s = rng.uniform(-0.5, 0.5, (2000, 2)) * [400, 200]
    g = np.array([2_540_000.0, 1_150_000.0]) + s[:, :1] * du + s[:, 1:] * dv
    d = g[:, None, :] - c[None]
    inside = (np.abs(d @ du) <= 51.2 / 2) & (np.abs(d @ dv) <= 64.0 / 2)
    cover = inside.sum(axis=1)
    assert cover.min() >= 8
    # neighbouring triggers on a line are exactly the trigger distance apart
    line0 = c[[i for i, w in enumerate(photos) if w.line == 0]]
    assert np.allclose(np.linalg.norm(np.diff(line0, axis=0), axis=1), 10.24)


def test_plan_from_height_and_bad_arguments():
    poly = [[0, 0], [100, 0], [100, 50], [0, 50]]
    p = plan_flight(379.17, (320, 256), poly, height_m=50.0)
    assert p.gsd_m == pytest.approx(50.0 / 379.17)
    with pytest.raises(ConfigError, match="exactly one of gsd_m"):
        plan_flight(379.17, (320, 256), poly, height_m=50.0, gsd_m=0.1)
    with pytest.raises(ConfigError, match="forward_overlap=1.0"):
        plan_flight(379.17, (320, 256), poly, height_m=50.0, forward_overlap=1.0)
    with pytest.raises(ConfigError, match="zero area"):
        plan_flight(379.17, (320, 256), [[0, 0], [1, 1], [2, 2]], height_m=50.0)
    with pytest.raises(ConfigError, match="needs speed_mps"):
        plan_flight(379.17, (320, 256), poly, height_m=50.0, video_fps=30.0)


def test_plan_cli_geojson_to_swiss_crs(tmp_path, capsys):
    area = {"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [[
        [6.5600, 46.5200], [6.5650, 46.5200], [6.5650, 46.5230], [6.5600, 46.5230], [6.5600, 46.5200]]]}}
    (tmp_path / "area.geojson").write_text(json.dumps(area))
    rc = main(["plan", "--focal-px", "379.17", "--image-size", "320x256", "--gsd", "0.13", "--area",
               str(tmp_path / "area.geojson"), "--crs", "EPSG:2056", "--speed", "6", "--fps", "30", "-o", str(tmp_path / "p")])
    assert rc == 0, capsys.readouterr().err
    js = json.loads((tmp_path / "p/plan.json").read_text())
    assert js["crs"] == "EPSG:2056" and js["height_m"] == pytest.approx(0.13 * 379.17)
    rows = (tmp_path / "p/waypoints.csv").read_text().splitlines()
    assert rows[0] == "id,line,kind,X,Y,Z,lon,lat"
    x, y, lon, lat = (np.array([float(r.split(",")[k]) for r in rows[1:]]) for k in (3, 4, 6, 7))
    assert 2_530_000 < x.min() < x.max() < 2_540_000 and 1_150_000 < y.min() < y.max() < 1_155_000  # LV95 near Lausanne
    assert 6.555 < lon.min() and lon.max() < 6.570 and 46.515 < lat.min() and lat.max() < 46.528
    kml = ET.parse(tmp_path / "p/waypoints.kml")
    assert kml.getroot().tag.endswith("kml")


@pytest.mark.parametrize("args, msg", [
    (["--gsd", "0.1", "--height", "50"], "exactly one of gsd_m"),
    (["--gsd", "0.1", "--crs", "EPSG:4326"], "geographic CRS"),
    (["--gsd", "0.1", "--corners", "0,0 10,0 x"], "--corners"),
])
def test_plan_cli_bad_input_exit_2(tmp_path, capsys, args, msg):
    base = ["plan", "--focal-px", "1000", "--image-size", "640x512", "-o", str(tmp_path / "p")]
    if "--corners" not in args:
        base += ["--corners", "0,0 100,0 100,50 0,50"]
    assert main(base + args) == 2
    assert msg in " ".join(capsys.readouterr().err.split())
    assert not (tmp_path / "p").exists()


def test_an_area_needing_too_many_photos_is_refused_at_once_and_the_cap_can_be_raised(tmp_path):
    """A 1-degree square (~111 x 111 km) at 5 cm GSD would need ~10^9 photos: refused before any waypoint, naming
    the area, the estimate and the cap; a small area passes a lowered cap only when it fits under it."""
    square = [[0, 0], [111_000, 0], [111_000, 111_000], [0, 111_000]]
    with pytest.raises(ConfigError, match=r"area of 1\.23e\+04 km\^2 at a GSD of 5 cm: about 1\.88e\+08 photos "
                                          r"\(\d+ lines\), above the cap of 200000 photos.*--max-photos"):
        plan_flight(1000.0, (640, 512), square, gsd_m=0.05)
    small = [[0, 0], [200, 0], [200, 100], [0, 100]]
    p = plan_flight(1000.0, (640, 512), small, gsd_m=0.05)
    with pytest.raises(ConfigError, match="above the cap of 10 photos"):
        plan_flight(1000.0, (640, 512), small, gsd_m=0.05, max_photos=10)
    assert plan_flight(1000.0, (640, 512), small, gsd_m=0.05, max_photos=p.n_photos + 50).n_photos == p.n_photos
    assert main(["plan", "--focal-px", "1000", "--image-size", "640x512", "--gsd", "0.05", "--corners",
                 "0,0 111000,0 111000,111000 0,111000", "-o", str(tmp_path / "OUT")]) == 2
    assert not (tmp_path / "OUT").exists()
