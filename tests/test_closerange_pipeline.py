"""The closerange workflow as pipeline steps and as the CLI verb (outputs, units, errors)."""

from __future__ import annotations

import csv
import io
import json

import numpy as np
import pytest

from thermogrammetry.closerange.pipeline import closerange_steps, write_inputs
from thermogrammetry.closerange.tables import parse_control, parse_measurements, parse_planes
from thermogrammetry.errors import DataFileError, InvalidInputError
from thermogrammetry.pipeline import MemoryProject, run_steps
from thermogrammetry.synthetic.closerange import make_closerange_scene, measure, measurements_csv, render_thermal


@pytest.fixture(scope="module")
def case():
    s = make_closerange_scene()
    rows = measure(s, 0.5, np.random.default_rng(5))
    return s, rows, render_thermal(s)


def test_pipeline_outputs_in_memory(case):
    s, rows, img = case
    p = MemoryProject()
    write_inputs(p, control_csv=s.control_csv(), measurements_csv=measurements_csv(rows), planes_csv=s.planes_csv(),
                 thermal="thermal", thermal_k=img["temperature_k"], thermal_unit="C")
    reps = run_steps(p, closerange_steps())
    assert [r.status for r in reps] == ["ok"] * 4, [r.error for r in reps]
    pts = list(csv.DictReader(io.StringIO(p.read_text("points.csv"))))
    assert list(pts[0])[:7] == ["id", "X", "Y", "Z", "sX", "sY", "sZ"]
    passp = {r["id"]: r for r in pts if r["kind"] == "pass"}
    assert set(passp) == set(s.passpoints)
    for pid, r in passp.items():  # within 4.5 sigma per coordinate (33 coordinates)
        for k, ax in enumerate("XYZ"):
            assert abs(float(r[ax]) - s.passpoints[pid][k]) < 4.5 * float(r["s" + ax])
    # cameras.json: the one oriented-cameras schema, consistent with the orientation report
    from thermogrammetry.io.oriented import OrientedCameras

    oc = OrientedCameras.from_dict(p.read_json("cameras.json"))
    rep = p.read_json("orientation.json")
    assert rep["format"] == "thermogrammetry.closerange.orientation/1" and rep["thermal"] == "thermal"
    assert sorted(oc.names()) == ["opt1", "opt2", "thermal"] and oc.crs is None
    th_im = oc.image("thermal")
    assert th_im.sensor.value == "thermal" and oc.image("opt1").sensor.value == "rgb"
    # the thermal camera gets the thermal image's size; optical ones a nominal one, said in the notes
    assert oc.camera_of("thermal").image_size == img["temperature_k"].shape[::-1]
    assert "nominal" in oc.image("opt1").notes and "nominal" not in th_im.notes
    for name in oc.names():
        r = rep["cameras"][name]
        np.testing.assert_allclose(oc.image(name).center, r["center_m"], rtol=0, atol=5e-14)  # measured 8.9e-16 m
        np.testing.assert_allclose(oc.image(name).center_std, [r["exterior_std"][k] for k in ("X0", "Y0", "Z0")],
                                   rtol=0, atol=0)
        # the camera + pose reproduce the DLT (P / P[2, 3] from dlt_L_world) on the pass points
        X = np.array([s.passpoints[k] for k in sorted(s.passpoints)])
        L = np.append(r["dlt_L_world"], 1.0).reshape(3, 4)
        xh = np.hstack([X, np.ones((len(X), 1))]) @ L.T
        xy_dlt = xh[:, :2] / xh[:, 2:]
        xy_cam = oc.camera_of(name).project(oc.image(name).pose.transform(X))
        assert np.abs(xy_cam - xy_dlt).max() < 1e-10, name  # measured 1.1e-12 px (worst camera)
    cams = rep["cameras"]
    assert set(cams) == {"opt1", "opt2", "thermal"}
    C = s.camera("thermal").pose.center
    th = cams["thermal"]
    for k, ax in enumerate(("X0", "Y0", "Z0")):
        assert abs(th["exterior"][ax] - C[k]) < 3 * th["exterior_std"][ax]
    # optical interior orientation recovered by the DLT decomposition (fx = 3000 px)
    assert abs(cams["opt1"]["interior"]["fx_px"] - 3000.0) < 4 * cams["opt1"]["interior_std"]["fx_px"]
    pl = list(csv.DictReader(io.StringIO(p.read_text("planes.csv"))))
    assert list(pl[0])[:6] == ["name", "normal_x", "normal_y", "normal_z", "angle_deg", "distance_m"]
    assert [r["name"] for r in pl] == ["front", "top", "right"]
    # corrected.tif: float32 in the input unit (°C here)
    import tifffile

    arr = tifffile.imread(io.BytesIO(p.read_bytes("corrected.tif")))
    assert arr.dtype == np.float32 and arr.shape == img["temperature_k"].shape
    outside = ~img["inside"]
    assert np.allclose(arr[outside], img["temperature_k"][outside] - 273.15, atol=1e-4)
    html = p.read_text("report.html")
    assert "Final Computed 3D Pass Points Coordinates" in html and "data:image/png;base64" in html


def test_tables_errors():
    with pytest.raises(DataFileError, match=r"c.csv, row 1: missing column\(s\) Z in header 'id,X,Y'"):
        parse_control("id,X,Y\n1,2,3\n", "c.csv")
    with pytest.raises(DataFileError, match=r"c.csv, row 2: Y = 'abc' is not a number"):
        parse_control("id,X,Y,Z\n1,2,abc,3\n", "c.csv")
    with pytest.raises(DataFileError, match=r"row 3: point '1' measured twice in image 'a' \(first on row 2\)"):
        parse_measurements("image,id,x,y\na,1,2,3\na,1,4,5\n")
    assert parse_control("id,X,Y,Z\nA,1,2,3\n") == {"A": (1.0, 2.0, 3.0)}
    assert parse_measurements("image,id,x,y\nimg,A,1.5,2.5\n") == [("img", "A", 1.5, 2.5)]
    with pytest.raises(InvalidInputError, match="plane 'p' has 2 point id"):
        parse_planes("name,id1,id2,id3\np,1,2,\n")
    assert parse_planes("name,id1,id2,id3,id4\np,1,2,3,\nq,4,5,6,7\n") == {"p": ("1", "2", "3"), "q": ("4", "5", "6", "7")}


def test_cli_closerange_and_correct(case, tmp_path):
    from thermogrammetry.cli.main import main
    from thermogrammetry.io.tiff import write_temperature_tiff

    s, rows, img = case
    (tmp_path / "control.csv").write_text(s.control_csv())
    (tmp_path / "measurements.csv").write_text(measurements_csv(rows))
    (tmp_path / "planes.csv").write_text(s.planes_csv())
    write_temperature_tiff(tmp_path / "thermal.tif", img["temperature_k"], unit="K")
    out = tmp_path / "OUT"
    rc = main(["closerange", "--control", str(tmp_path / "control.csv"), "--measurements",
               str(tmp_path / "measurements.csv"), "--thermal", "thermal", "--thermal-image",
               str(tmp_path / "thermal.tif"), "--planes", str(tmp_path / "planes.csv"), "--ambient-c", "22",
               "-o", str(out)])
    assert rc == 0
    for f in ("points.csv", "cameras.json", "orientation.json", "planes.csv", "corrected.tif", "report.html"):
        assert (out / f).is_file()
    import shlex

    from report_fields import header_fields

    f = header_fields((out / "report.html").read_text())  # the report's header: the command as typed, the counts
    assert f["command"].startswith(shlex.join(["thermogrammetry", "closerange", "--control", str(tmp_path / "control.csv")]))
    n_img, n_ctl = len({r[0] for r in rows}), len(s.control_csv().strip().splitlines()) - 1
    assert f["inputs"] == (f"{n_img} images measured\n{n_ctl} control points\n{len(rows)} image measurements\n"
                           "3 planes")
    from thermogrammetry.io import read_thermal

    corr = read_thermal(out / "corrected.tif").temperature_k
    assert np.nanmax(corr) > np.nanmax(img["temperature_k"]) + 2  # corrected upwards on the hot faces
    # general case with the oriented thermal camera and the fitted planes
    rc = main(["correct", "--thermal-image", str(tmp_path / "thermal.tif"), "--cameras", str(out / "cameras.json"),
               "--thermal", "thermal", "--planes", str(out / "planes.csv"), "--ambient-c", "22", "-o",
               str(tmp_path / "OUT2")])
    assert rc == 0
    ang = read_thermal(tmp_path / "OUT2" / "corrected.tif").temperature_k
    assert ang.shape == corr.shape
    # with the points, only inside the planes' outlines: the same result as closerange's own correction
    rc = main(["correct", "--thermal-image", str(tmp_path / "thermal.tif"), "--cameras", str(out / "cameras.json"),
               "--thermal", "thermal", "--planes", str(out / "planes.csv"), "--points", str(out / "points.csv"),
               "--ambient-c", "22", "-o", str(tmp_path / "OUT3")])
    assert rc == 0
    c3 = read_thermal(tmp_path / "OUT3" / "corrected.tif").temperature_k
    import tifffile

    v = tifffile.imread(out / "valid.tif").astype(bool) & tifffile.imread(tmp_path / "OUT3" / "valid.tif").astype(bool)
    assert v.sum() > 0.95 * tifffile.imread(out / "valid.tif").sum()
    assert np.abs(c3[v] - corr[v]).max() < 1e-3  # float32 files; same geometry through cameras.json
    assert json.loads((out / "orientation.json").read_text())["thermal"] == "thermal"
    assert json.loads((out / "cameras.json").read_text())["format"] == "thermogrammetry/cameras"
    # a cameras.json in closerange's former format is still read by correct: same result
    old = json.loads((out / "orientation.json").read_text())
    old["format"] = "thermogrammetry.closerange.cameras/1"
    (tmp_path / "old.json").write_text(json.dumps(old))
    rc = main(["correct", "--thermal-image", str(tmp_path / "thermal.tif"), "--cameras", str(tmp_path / "old.json"),
               "--thermal", "thermal", "--planes", str(out / "planes.csv"), "--points", str(out / "points.csv"),
               "--ambient-c", "22", "-o", str(tmp_path / "OUT4")])
    assert rc == 0
    c4 = read_thermal(tmp_path / "OUT4" / "corrected.tif").temperature_k
    assert np.array_equal(np.isnan(c4), np.isnan(c3)) and np.nanmax(np.abs(c4 - c3)) < 1e-3


def test_cli_bad_input_exit_code(case, tmp_path, capsys):
    from thermogrammetry.cli.main import main

    s, rows, _ = case
    (tmp_path / "control.csv").write_text(s.control_csv())
    few = [r for r in rows if r[0] != "thermal" or r[1] in ("1", "4", "5")]
    (tmp_path / "m.csv").write_text(measurements_csv(few))
    (tmp_path / "planes.csv").write_text(s.planes_csv())
    rc = main(["closerange", "--control", str(tmp_path / "control.csv"), "--measurements", str(tmp_path / "m.csv"),
               "--thermal", "thermal", "--planes", str(tmp_path / "planes.csv"), "-o", str(tmp_path / "O")])
    assert rc == 2
    text = capsys.readouterr().out
    assert "1, 4, 5" in text and "at least 6" in text


def test_cli_bundle_with_known_thermal_camera(case, tmp_path):
    from thermogrammetry import Camera
    from thermogrammetry.cli.main import main

    s, rows, _ = case
    (tmp_path / "control.csv").write_text(s.control_csv())
    (tmp_path / "m.csv").write_text(measurements_csv(rows))
    (tmp_path / "planes.csv").write_text(s.planes_csv())
    K = s.camera("thermal").K
    Camera("pinhole", (640, 480), {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}).save(tmp_path / "t.json")
    out = tmp_path / "O"
    rc = main(["closerange", "--control", str(tmp_path / "control.csv"), "--measurements", str(tmp_path / "m.csv"),
               "--thermal", "thermal", "--planes", str(tmp_path / "planes.csv"), "--camera",
               f"thermal={tmp_path / 't.json'}", "--bundle", "--additional", "k1", "--control-sigma-mm", "1",
               "-o", str(out)])
    assert rc == 0
    pts = {r["id"]: r for r in csv.DictReader(io.StringIO((out / "points.csv").read_text()))}
    # weighted control (1 mm) is adjusted: its sigma is positive and not above the given 1 mm
    for pid in s.control:
        sx = [float(pts[pid][k]) for k in ("sX", "sY", "sZ")]
        assert all(0 < v <= 0.001 + 1e-9 for v in sx), (pid, sx)
    from thermogrammetry.camera import Camera
    from thermogrammetry.io.oriented import OrientedCameras

    oc = OrientedCameras.load(out)
    assert oc.camera_of("thermal").to_dict() == Camera.load(tmp_path / "t.json").to_dict()  # calibrated model kept
    assert "additional parameters" in oc.image("opt1").notes
    cams = json.loads((out / "orientation.json").read_text())["cameras"]
    assert cams["thermal"]["method"].startswith("resection (known interior orientation)")
    assert cams["thermal"]["method"].endswith("joint adjustment")
    assert cams["thermal"]["interior"]["fx_px"] == pytest.approx(K[0, 0], rel=1e-9)
    assert "k1" in cams["opt1"]["additional_parameters"]
    # known interior orientation: the thermal centre is much better determined than by DLT (cm, not dm)
    C = s.camera("thermal").pose.center
    for k, ax in enumerate(("X0", "Y0", "Z0")):
        assert cams["thermal"]["exterior_std"][ax] < 0.02
        assert abs(cams["thermal"]["exterior"][ax] - C[k]) < 3 * cams["thermal"]["exterior_std"][ax]
    assert not (out / "corrected.tif").exists()  # no thermal image given: correction skipped


def test_cli_correct_with_dsm_and_pose(tmp_path):
    import rasterio
    from rasterio.transform import from_origin

    from thermogrammetry import Camera
    from thermogrammetry.cli.main import main
    from thermogrammetry.geometry import Pose
    from thermogrammetry.io import read_thermal
    from thermogrammetry.io.tiff import write_temperature_tiff

    # flat ground DSM at z = 1 m, camera 10 m above looking obliquely; °C input → °C output
    H, W = 30, 40
    with rasterio.open(tmp_path / "dsm.tif", "w", driver="GTiff", height=H, width=W, count=1, dtype="float32",
                       transform=from_origin(-20.0, 15.0, 1.0, 1.0)) as dst:
        dst.write(np.ones((1, H, W), np.float32))
    pose = Pose.look_at([0.0, -6.0, 11.0], [0.0, 0.0, 1.0], up=(0, 1, 0))
    (tmp_path / "pose.json").write_text(json.dumps({"R": pose.R.tolist(), "t": pose.t.tolist()}))
    Camera("pinhole", (80, 60), {"fx": 100.0, "fy": 100.0, "cx": 39.5, "cy": 29.5}).save(tmp_path / "cam.json")
    write_temperature_tiff(tmp_path / "t.tif", np.full((60, 80), 303.15), unit="C")
    rc = main(["correct", "--thermal-image", str(tmp_path / "t.tif"), "--camera", str(tmp_path / "cam.json"),
               "--pose", str(tmp_path / "pose.json"), "--dsm", str(tmp_path / "dsm.tif"), "--ambient-c", "20",
               "-o", str(tmp_path / "O")])
    assert rc == 0
    import tifffile

    ang = tifffile.imread(tmp_path / "O" / "angle_deg.tif")
    # the centre pixel looks at (0, 0, 1): angle to the vertical normal = atan(6 / 10)
    assert ang[30, 40] == pytest.approx(np.degrees(np.arctan2(6.0, 10.0)), abs=0.5)
    out = read_thermal(tmp_path / "O" / "corrected.tif")
    assert "in C" in " ".join(out.metadata.notes)
    assert np.all(out.temperature_k[30, 35:45] > 303.15)
