"""What every report.html shares (``thermogrammetry.reporting``): the header's fields, the command line recorded by
the CLI or the outermost driver, colour limits that exclude outliers, vectors and ellipses at their map positions.
All in-process and without files: milliseconds each."""

from __future__ import annotations

import re

import numpy as np
import pytest

import thermogrammetry
from report_fields import header_fields as _fields
from thermogrammetry import reporting as rp


def test_header_fields_and_omitted_values():
    h = rp.ReportHeader("dense", inputs=[(12, "oriented images", ["/data/survey"]), (None, "DSM", ["/data/dsm.tif"])],
                        crs="EPSG:32631", gsd_m=0.192, gsd_note="DSM cell", flying_height_m=75.04, area_m2=23456.0,
                        seconds=252.4, command="thermogrammetry dense s -o d")
    f = _fields(rp.header_html(h))
    assert f["software"] == f"thermogrammetry {thermogrammetry.__version__}"
    assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC", f["date"])
    assert f["command"] == "thermogrammetry dense s -o d"
    assert f["inputs"] == "12 oriented images in /data/survey\nDSM: /data/dsm.tif"
    assert f["crs"] == "EPSG:32631 (WGS 84 / UTM zone 31N)"
    assert f["gsd"] == "19.2 cm (DSM cell)" and f["flying_height"] == "75.0 m"
    assert f["area"].startswith("2.35 ha (23,456 m²)") and f["time"] == "4 min 12 s"
    # what the verb does not know is left out, not guessed; a local frame is said to be one
    f = _fields(rp.header_html(rp.ReportHeader("x", georeferenced=False, gsd_m=float("nan"))))
    assert set(f) == {"software", "date", "crs"} and f["crs"].startswith("none: a local frame")
    assert set(_fields(rp.header_html(rp.ReportHeader("x")))) == {"software", "date"}


def test_command_line_is_the_cli_s_else_the_outermost_driver_call():
    def outer(survey_dir, out_dir, *, gsd=None, workers=1, on_image=None):
        with rp.driver_call(outer, locals()):
            return inner(out_dir)

    def inner(out_dir, *, fill=False):
        with rp.driver_call(inner, locals()):
            return rp.command_line()

    from pathlib import Path

    got = outer(Path("/a/survey"), "/a/out", workers=0, on_image=print)
    assert got.endswith("outer('/a/survey', '/a/out', workers=0)")  # the outer call; defaults and callbacks left out
    assert rp.command_line() is None  # nothing recorded once the call returned
    with rp.cli_command(["dense", "/my survey", "-o", "out"]):
        assert outer("/a/survey", "/a/out") == "thermogrammetry dense '/my survey' -o out"
    assert rp.command_line() is None


def test_format_seconds():
    assert [rp.format_seconds(x) for x in (12.34, 59.96, 119.7, 252.4, 3599.6, 3725.0)] == [
        "12.3 s", "1 min 00 s", "2 min 00 s", "4 min 12 s", "1 h 00 min", "1 h 02 min"]


def test_insert_header_goes_after_the_title():
    page = "<html><body><h1>Camera calibration report</h1><p>Route</p></body></html>"
    out = rp.insert_header(page, rp.ReportHeader("calibrate", command="thermogrammetry calibrate x"))
    assert out.index("</h1>") < out.index("tg-header") < out.index("<p>Route")


def test_colour_limits_exclude_planted_outliers():
    """The demo's case: 14 tie points at −335 m among points on ~100 m ground (σ 2 m): the limits stay on the ground."""
    rng = np.random.default_rng(1)
    z = np.r_[100 + rng.normal(0, 2.0, 2000), np.full(14, -335.0), [np.nan, np.inf]]
    lim = rp.colour_limits(z, 1.0, 99.0)
    # 1st/99th percentile of N(100, 2): 100 ∓ 4.65 m; the 14 outliers (0.7 %) shift the lower one by < 0.7 m
    assert 94.0 < lim.lo < 96.5 and 103.5 < lim.hi < 106.0
    assert lim.below >= 14 and lim.above >= 1 and lim.n == 2014 and lim.extend == "both"
    assert "1st–99th percentile" in lim.caption("m") and "14" not in f"{lim.lo:.1f}"
    assert (np.nanmin(z[np.isfinite(z)]), np.nanmax(z[np.isfinite(z)]))[0] == -335.0  # what min/max would have drawn
    one = rp.colour_limits(np.full(5, 7.0))
    assert one.lo < 7.0 < one.hi and rp.colour_limits([np.nan]).n == 0


def test_vectors_are_drawn_at_their_map_positions():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xy = np.array([[512340.0, 5300120.0], [512100.0, 5300400.0], [512250.0, 5300010.0]])  # not in list order
    d = np.array([[0.02, -0.01], [-0.005, 0.03], [0.0, 0.01]])
    origin = rp.map_origin(xy[:, 0], xy[:, 1])
    assert origin == (512000.0, 5300000.0)
    fig, ax = plt.subplots()
    q, mag = rp.vectors_at(ax, xy, d, origin=origin)
    np.testing.assert_allclose(np.column_stack([q.X, q.Y]), xy - origin)  # at the points, not at 0, 1, 2
    np.testing.assert_allclose(np.column_stack([q.U, q.V]), d * mag)
    extent = max(np.ptp(xy[:, 0]), np.ptp(xy[:, 1]))  # 390 m; longest 3.04 cm → ×1000 (1 of 1, 2, 5 × 10^k)
    assert mag == 1000.0 and 0.05 * extent < np.hypot(*d.T).max() * mag <= 0.12 * extent
    plt.close(fig)


def test_ellipses_are_centred_at_the_positions_with_their_axes():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.radians(30.0)
    R = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    cov = R @ np.diag([0.03**2, 0.01**2]) @ R.T  # σ 3 cm along 30°, 1 cm across
    xy = np.array([[10.0, 20.0], [60.0, 5.0]])
    fig, ax = plt.subplots()
    mag = rp.ellipses_at(ax, xy, np.stack([cov, np.full((2, 2), np.nan)]), extent=100.0)
    (e,) = ax.patches  # the one with a covariance
    assert e.center == pytest.approx((10.0, 20.0))
    assert e.width == pytest.approx(2 * 0.03 * mag) and e.height == pytest.approx(2 * 0.01 * mag)
    assert e.angle % 180 == pytest.approx(30.0)
    assert mag == 100.0  # 0.04 × 100 m / 3 cm = 133 → 100
    plt.close(fig)


def test_map_axes_show_few_short_ticks():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4, 3))
    x0, y0 = rp.map_origin([599450, 599650], [5695500, 5695580])
    ax.plot(np.array([599450, 599650]) - x0, np.array([5695500, 5695580]) - y0)
    rp.map_axes(ax, (x0, y0))
    fig.canvas.draw()
    labels = [t.get_text() for t in ax.get_xticklabels() if t.get_text()]
    assert ax.get_xlabel() == "E − 599000 (m)" and ax.get_ylabel() == "N − 5695000 (m)"
    assert len(labels) <= 7 and max(len(t) for t in labels) <= 4
    plt.close(fig)


def test_thin_labels_keeps_at_most_the_cap():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    rp.thin_labels(ax, [f"IMG_{k:04d}" for k in range(300)], max_labels=40)
    assert 30 <= len(ax.get_xticks()) <= 40 and ax.get_xticklabels()[1].get_text() == "IMG_0008"
    plt.close(fig)
    dji = ["DJI_20240806173449_0008_T", "DJI_20240806173450_0009_T", "DJI_20240806173451_0010_T"]
    assert rp.short_names(dji) == ["0008_T", "0009_T", "0010_T"]  # not "9_0008_T": the parts that tell them apart
    assert rp.short_names(["a_T", "b_T", "a_T"]) == ["a_T", "b_T", "a_T"]


def test_control_points_take_the_given_coordinates():
    from thermogrammetry.pipeline.survey.report_figures import control_points

    s = {"gcp_residuals": [{"id": "G2", "x": 512300.0, "y": 5300100.0, "z": 410.0, "dx": 0.01, "dy": -0.02, "dz": 0.03}],
         "checkpoint_errors": [{"id": "C9", "x": 512010.0, "y": 5300300.0, "z": 402.0, "dx": -0.04, "dy": 0.0, "dz": 0.1,
                                "n_images": 4},
                               {"id": "C1", "n_images": 1, "reason": "seen in fewer than 2 images"}]}
    pts = control_points(s)
    assert [(p["kind"], p["id"], p["xy"], p["dxy"]) for p in pts] == [
        ("GCP", "G2", (512300.0, 5300100.0), (0.01, -0.02)), ("check point", "C9", (512010.0, 5300300.0), (-0.04, 0.0))]


def test_overlap_counts_two_squares():
    from thermogrammetry.pipeline.survey.report_figures import overlap_counts

    a = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    counts, ext, cell = overlap_counts([a, a + [5.0, 0.0]], max_cells=150)
    assert ext[0] == 0.0 and ext[3] == 10.0 and cell == pytest.approx(0.1)
    area = (counts > 0).sum() * cell**2
    assert area == pytest.approx(150.0, rel=0.02) and (counts == 2).sum() * cell**2 == pytest.approx(50.0, rel=0.03)


def test_calibrate_report_has_the_header(tmp_path):
    """calibrate (test-field route): the header under the report's title, with the command as typed and the
    inputs' files; the report's own content after it."""
    import shlex

    from thermogrammetry.cli.main import main
    from thermogrammetry.synthetic.testfield import make_testfield

    field = make_testfield(np.random.default_rng(11), noise_px=0.4)
    (tmp_path / "control.csv").write_text(field.control_csv())
    (tmp_path / "measurements.csv").write_text(field.measurements_csv())
    args = ["calibrate", "--control", str(tmp_path / "control.csv"), "--measurements", str(tmp_path / "measurements.csv"),
            "--image-size", "320x240", "--pixel-pitch-um", "25", "--focal-mm", "18", "-o", str(tmp_path / "OUT")]
    assert main(args) == 0
    page = (tmp_path / "OUT" / "report.html").read_text()
    f = _fields(page)
    assert f["software"] == f"thermogrammetry {thermogrammetry.__version__}"
    assert f["command"] == shlex.join(["thermogrammetry", *args])
    assert f["inputs"] == (f"16 images measured\ncontrol points: {(tmp_path / 'control.csv').resolve()}\n"
                           f"image measurements: {(tmp_path / 'measurements.csv').resolve()}")
    assert float(f["time"].split()[0]) > 0 and "crs" not in f  # a calibration has no CRS: the row is left out
    assert page.index("</h1>") < page.index("tg-header") < page.index("Table 2")
