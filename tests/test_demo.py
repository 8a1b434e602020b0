"""The demo: registry, rows and bounds, exit status, report; one real section end to end."""

from __future__ import annotations

import json

import pytest

from thermogrammetry.pipeline import MemoryProject
from thermogrammetry.pipeline.demo import (
    DEMO_SECTIONS,
    DemoOptions,
    DemoRow,
    DemoSection,
    PrefixedProject,
    register_section,
    run_demo,
)


@pytest.fixture
def fake_sections():
    """Temporarily register sections with known outcomes; restore the registry afterwards."""
    from thermogrammetry.pipeline.demo import all_sections

    saved = all_sections()  # imports SECTION_MODULES first, so restoring keeps their sections

    def good(project, opt):
        project.write_text("good/out.txt", "x")
        return [DemoRow("good", "error", 0.5, 1.0, "mm"), DemoRow("good", "count", 12, 10, "", kind="min"),
                DemoRow("good", "context", 1e9, None, "s", kind="info")]

    def bad(project, opt):
        return [DemoRow("bad", "error", 1.5, 1.0, "mm")]

    def boom(project, opt):
        raise RuntimeError("scene exploded")

    for s in (DemoSection("good", "Good", good), DemoSection("bad", "Bad", bad), DemoSection("boom", "Boom", boom)):
        register_section(s)
    yield
    DEMO_SECTIONS[:] = saved


def test_row_semantics():
    assert DemoRow("s", "c", 1.0, 1.0).passed
    assert not DemoRow("s", "c", 1.0000001, 1.0).passed
    assert DemoRow("s", "c", 10, 10, kind="min").passed and not DemoRow("s", "c", 9, 10, kind="min").passed
    assert DemoRow("s", "c", float("inf"), None, kind="info").passed
    assert not DemoRow("s", "c", float("nan"), 1.0).passed  # a missing figure is a failure


def test_failed_bound_and_failed_section_give_nonzero_exit(fake_sections, tmp_path, capsys):
    from thermogrammetry.cli.main import main

    assert main(["demo", str(tmp_path / "a"), "--sections", "good"]) == 0
    assert (tmp_path / "a" / "report.html").is_file() and (tmp_path / "a" / "good" / "out.txt").is_file()
    assert main(["demo", str(tmp_path / "b"), "--sections", "good,bad"]) == 1
    out = capsys.readouterr().out
    assert "FAIL" in out and "1 check(s) failed" in out
    assert main(["demo", str(tmp_path / "c"), "--sections", "boom,good"]) == 1
    rows = json.loads((tmp_path / "c" / "demo" / "rows.json").read_text())
    assert not rows["ok"]
    assert rows["rows"][0]["check"].startswith("section failed: RuntimeError: scene exploded")
    assert [r["section"] for r in rows["rows"]][1:] == ["good"] * 3  # a failed section does not stop the others
    html = (tmp_path / "c" / "report.html").read_text()
    assert "SOME CHECKS FAILED" in html and "scene exploded" in html
    assert main(["demo", str(tmp_path / "d"), "--sections", "nope"]) == 2


def test_prefixed_project_maps_keys():
    p = MemoryProject()
    sub = PrefixedProject(p, "closerange/")
    sub.write_json("inputs/settings.json", {"a": 1})
    assert p.keys() == ["closerange/inputs/settings.json"]
    assert sub.keys("inputs") == ["inputs/settings.json"] and sub.read_json("inputs/settings.json") == {"a": 1}
    assert sub.exists("inputs/settings.json") and not sub.exists("x")


def test_closerange_and_testfield_sections_end_to_end():
    """Two real sections through their workflows, in memory; every built-in bound holds."""
    p = MemoryProject()
    res = run_demo(p, DemoOptions(sections=("calibration-testfield", "closerange")))
    assert res.ok, [(r.check, r.value, r.bound) for r in res.rows if not r.passed]
    assert {r.section for r in res.rows} == {"calibration-testfield", "closerange"}
    assert len(res.rows) == 8
    for k in ("closerange/points.csv", "closerange/report.html", "calibration-testfield/control.csv", "report.html",
              "demo/closerange.json", "reports/closerange.json"):
        assert p.exists(k), k


def test_list_names_every_section_that_a_run_would_run(capsys):
    """``demo --list`` shows the sections registered by SECTION_MODULES too (survey-sfm was missing)."""
    from thermogrammetry.cli.main import main
    from thermogrammetry.pipeline.demo import all_sections

    assert main(["demo", "--list"]) == 0
    listed = [line.split()[0] for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert listed == [s.name for s in all_sections()]
    assert "survey-sfm" in listed
