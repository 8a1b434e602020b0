"""``thermogrammetry run`` end to end on a small rendered block (6 frames in two lines, the user's GNSS CSV and
camera file): the project layout, the per-step hashes, a killed run resumed, a second run that skips every step
and changes no file, ``--rerun-from ortho``, the log, the report, the QGIS style, and refused arguments."""

from __future__ import annotations

import json
import logging
import os
import re
import time
from pathlib import Path
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from survey_truth import SMALL_BLOCK_FRAMES as FRAMES
from survey_truth import write_small_block
from thermogrammetry.cli.main import main



@pytest.fixture(scope="module")
def block(tmp_path_factory):
    root = tmp_path_factory.mktemp("runblock")
    _, opts = write_small_block(root)
    return root, [str(root / "images"), "--camera", str(root / "camera.json"), *opts]


def _snapshot(project):
    """Every file of PROJECT but run.log (which every run appends to): path -> (size, mtime ns, bytes digest)."""
    import hashlib

    out = {}
    for p in sorted(project.rglob("*")):
        if p.is_file() and p.name != "run.log":
            st = p.stat()
            out[p.relative_to(project).as_posix()] = (st.st_size, st.st_mtime_ns, hashlib.sha256(p.read_bytes()).hexdigest())
    return out


@pytest.fixture(scope="module")
def project(block, tmp_path_factory):
    """The first run killed during the ortho (survey and dense finished), then resumed: returns the timings."""
    import thermogrammetry.pipeline.ortho as ortho_mod

    root, args = block
    proj = tmp_path_factory.mktemp("proj") / "P"
    proj.mkdir()
    (proj / "notes.txt").write_text("the user's own notes\n")
    real = ortho_mod.run_ortho

    def killed(*a, on_tile=None, **kw):
        def boom(k, n):
            raise KeyboardInterrupt  # as if the run were killed in the middle of the mosaic
        return real(*a, on_tile=boom, **kw)

    ortho_mod.run_ortho = killed
    try:
        assert main(["run", *args, "-o", str(proj)]) in (1, 130)  # (click: "Aborted!", the status of an interrupt)
    finally:
        ortho_mod.run_ortho = real
    rec_killed = json.loads((proj / "run.json").read_text())
    ortho_after_kill = (proj / "ortho").exists()

    def noisy(*a, **kw):  # the libraries' own messages during the resumed run
        logging.getLogger("distributed.comm").warning("CommClosedError: a message the user must not see")
        os.write(2, b"a worker's traceback on stderr\n")
        return real(*a, **kw)

    ortho_mod.run_ortho = noisy
    try:
        code = main(["run", *args, "-o", str(proj)])
    finally:
        ortho_mod.run_ortho = real
    return {"root": root, "args": args, "proj": proj, "code": code,
            "rec_killed": rec_killed, "ortho_after_kill": ortho_after_kill}


def test_killed_run_resumes_from_the_last_finished_step(project, capfd):
    assert set(project["rec_killed"]["steps"]) == {"survey", "dense"}  # ortho was not finished: not recorded
    assert not project["ortho_after_kill"]  # its output set never appeared
    assert project["code"] == 0
    log = (project["proj"] / "run.log").read_text()
    resumed = log[log.rindex("steps survey, dense, ortho"):]
    assert "survey: skipped" in resumed and "dense: skipped" in resumed and "ortho: ran in" in resumed


def test_layout_hashes_report_and_log(project):
    proj = project["proj"]
    assert (proj / "notes.txt").read_text() == "the user's own notes\n"  # a user's file in PROJECT is kept
    for sub, files in (("survey", ["cameras.json", "survey.json", "report.html", "survey-manifest.json", "cameras.gpkg"]),
                       ("dense", ["dsm.tif", "cloud.las", "cloud.ply", "dense.json", "dense-manifest.json"]),
                       ("ortho", ["ortho.tif", "ortho.qml", "ortho.json", "ortho-manifest.json"])):
        for f in files:
            assert (proj / sub / f).is_file(), f"{sub}/{f}"
    rec = json.loads((proj / "run.json").read_text())
    assert rec["format"] == "thermogrammetry-run" and list(rec["steps"]) == ["survey", "dense", "ortho"]
    for name, r in rec["steps"].items():
        assert re.fullmatch("[0-9a-f]{64}", r["hash"]) and re.fullmatch("[0-9a-f]{64}", r["manifest_sha256"])
        assert r["seconds"] > 0
    assert len({r["hash"] for r in rec["steps"].values()}) == 3
    s = rec["steps"]["survey"]["summary"]
    assert s["images_oriented"] == s["images_total"] == len(FRAMES)
    o = rec["steps"]["ortho"]["summary"]
    assert 0.3 < o["coverage"] <= 1.0 and o["unit"] == "K"  # measured 0.56 (6 frames in two lines)
    html = (proj / "report.html").read_text()
    for link in ("survey/report.html", "dense/dsm.tif", "ortho/ortho.tif", "ortho/ortho.qml", "run.log"):
        assert f"href='{link}'" in html or f'href="{link}"' in html, link
    assert "images oriented: 6/6" in html and "ortho coverage of its box" in html
    # every report has the header: the version, the command as typed, the CRS, the inputs; dense and ortho write one
    import shlex

    import thermogrammetry
    from report_fields import header_fields

    root, args = project["root"], project["args"]
    cmd = shlex.join(["thermogrammetry", "run", *args, "-o", str(proj)])
    crs = json.loads((proj / "survey" / "cameras.json").read_text())["crs"]
    for page in ("report.html", "survey/report.html", "dense/report.html", "ortho/report.html"):
        f = header_fields((proj / page).read_text())
        assert f["software"] == f"thermogrammetry {thermogrammetry.__version__}", page
        assert f["command"] == cmd and f["crs"].startswith(f"{crs} ("), page
    for step in ("dense", "ortho"):
        assert "report.html" in json.loads((proj / step / f"{step}-manifest.json").read_text())["files"]
    f = header_fields((proj / "survey" / "report.html").read_text())
    assert f["inputs"] == f"6 thermal images in {(root / 'images').resolve()}"
    assert 40.0 < float(f["flying_height"].split()[0]) < 50.0  # the scene's 45 m above its ground
    assert "images covering each" in (proj / "survey" / "report.html").read_text().lower()
    log = (proj / "run.log").read_text()
    # progress with counts and elapsed time; the libraries' own messages are in the log
    assert re.search(r"dense reference images: 6/6 \(\d+\.\d s\)", log)
    assert re.search(r"ortho tiles: \d+/\d+ \(\d+\.\d s\)", log)
    assert "CommClosedError: a message the user must not see" in log and "a worker's traceback on stderr" in log


def test_dask_messages_stay_off_the_terminal(block, tmp_path, capfd):
    """The same messages during a run: in run.log, not on the terminal (stderr)."""
    import thermogrammetry.pipeline.run as run_mod

    root, args = block
    real = run_mod._survey_hash

    def noisy(*a, **kw):
        logging.getLogger("distributed.worker").warning("a dask warning for the log only")
        os.write(2, b"raw stderr of a worker process\n")
        raise KeyboardInterrupt  # stop before any step runs

    run_mod._survey_hash = noisy
    try:
        assert main(["run", *args, "-o", str(tmp_path / "P")]) in (1, 130)
    finally:
        run_mod._survey_hash = real
    cap = capfd.readouterr()
    assert "a dask warning" not in cap.err + cap.out and "raw stderr" not in cap.err + cap.out
    log = (tmp_path / "P" / "run.log").read_text()
    assert "a dask warning for the log only" in log and "raw stderr of a worker process" in log


def test_second_run_skips_every_step_and_changes_no_file(project, monkeypatch):
    """Nothing is computed again: the step drivers are replaced by ones that fail when called (checked, not timed;
    measured: first run, killed and resumed, ~9 s, this one ~0.1 s)."""
    import thermogrammetry.pipeline.dense as dense_mod
    import thermogrammetry.pipeline.ortho as ortho_mod
    import thermogrammetry.pipeline.survey as survey_mod

    def called(*a, **kw):
        raise AssertionError("a step ran again in a run that had nothing to do")

    for mod, name in ((survey_mod, "survey_to_folder"), (dense_mod, "run_dense"), (ortho_mod, "run_ortho")):
        monkeypatch.setattr(mod, name, called)
    proj = project["proj"]
    before = _snapshot(proj)
    assert main(["run", *project["args"], "-o", str(proj)]) == 0
    assert _snapshot(proj) == before
    log = (proj / "run.log").read_text()
    last = log[log.rindex("steps survey, dense, ortho"):]
    assert last.count(": skipped (") == 3 and "running" not in last


def test_an_input_change_changes_the_survey_hash(project):
    from thermogrammetry.cli.survey import SURVEY_ARGS, survey_inputs
    from thermogrammetry.pipeline.run import _survey_hash
    from pathlib import Path

    root = project["root"]
    kw = dict.fromkeys(SURVEY_ARGS)
    kw.update(images=[root / "images"], out=project["proj"], input_unit="K", camera=root / "camera.json", rgb=[],
              gnss=str(root / "gnss.csv"), crs="EPSG:32633", workers=0, low_texture="auto", refine_ties="off",
              detector="sift", video_overlap=0.8, mapper="auto")
    inp, opt = survey_inputs(**kw)
    h = _survey_hash(inp, opt)
    assert _survey_hash(inp, opt) == h
    f = sorted(Path(root / "images").glob("*.tif"))[0]
    st = f.stat()
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    try:
        assert _survey_hash(inp, opt) != h
    finally:
        os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert _survey_hash(inp, opt) == h
    from dataclasses import replace

    assert _survey_hash(inp, replace(opt, workers=2)) == h  # how the work is spread is not an input
    assert _survey_hash(inp, replace(opt, low_texture="off")) != h


def test_rerun_from_ortho_reruns_only_the_ortho(project):
    proj = project["proj"]
    before = _snapshot(proj)
    assert main(["run", *project["args"], "-o", str(proj), "--rerun-from", "ortho"]) == 0
    after = _snapshot(proj)
    for k, v in before.items():
        if k.startswith(("survey/", "dense/")) or k == "notes.txt":
            assert after[k] == v, k
    assert after["ortho/ortho.tif"][1] > before["ortho/ortho.tif"][1]  # written again
    assert after["ortho/ortho.tif"][2] == before["ortho/ortho.tif"][2]  # the same mosaic
    html = (proj / "report.html").read_text()
    assert len(re.findall("skipped \\(unchanged\\)", html)) == 2 and len(re.findall(">ran<", html)) == 1


def test_ortho_qml_is_a_qgis_style_in_the_orthos_unit(project, tmp_path):
    proj = project["proj"]
    q = ET.parse(proj / "ortho" / "ortho.qml").getroot()
    rr = q.find("pipe/rasterrenderer")
    assert q.tag == "qgis" and rr.get("type") == "singlebandpseudocolor" and rr.get("band") == "1"
    items = rr.findall("rastershader/colorrampshader/item")
    vals = [float(i.get("value")) for i in items]
    assert len(items) >= 5 and all(i.get("label").endswith(" K") for i in items) and vals == sorted(vals)
    # QGIS's continuous legend (a ramp with its end values): the unit as suffix, the entries' decimals as number format
    legend = rr.find("rastershader/colorrampshader/rampLegendSettings")
    assert legend.get("suffix") == " K" and legend.get("useContinuousLegend") == "1"
    fmt = {o.get("name"): o.get("value") for o in legend.findall("numericFormat/Option/Option")}
    assert legend.find("numericFormat").get("id") == "basic" and fmt["show_thousand_separator"] == "false"
    assert fmt["decimals"] == rr.find("rastershader/colorrampshader").get("labelPrecision")
    # the robust limits (2nd, 98th percentiles) lie inside the mosaic's range, not at its extremes
    rep = json.loads((proj / "ortho" / "ortho.json").read_text())
    import rasterio

    with rasterio.open(proj / "ortho" / "ortho.tif") as src:
        v = src.read(1)
    v = v[np.isfinite(v)]
    assert v.min() <= vals[0] < vals[-1] <= v.max() and rep["style"]["file"] == "ortho.qml"
    assert abs(vals[0] - np.percentile(v, 2)) < 0.5 and abs(vals[-1] - np.percentile(v, 98)) < 0.5
    # in °C when the ortho is in °C
    assert main(["ortho", str(proj / "survey"), "--dsm", str(proj / "dense" / "dsm.tif"), "-o", str(tmp_path / "c"),
                 "--unit", "C", "--workers", "0"]) == 0
    items = ET.parse(tmp_path / "c" / "ortho.qml").getroot().findall(".//colorrampshader/item")
    assert all(i.get("label").endswith(" °C") for i in items)
    assert abs(float(items[0].get("value")) - (vals[0] - 273.15)) < 0.5


def test_refused_arguments_exit_2_and_write_nothing(project, tmp_path, capsys):
    args = project["args"]
    new = tmp_path / "new"
    for extra, msg in ((["--rerun-from", "mosaic"], "unknown step"), (["--products", "ortho,mesh"], "no mesh verb"),
                       (["--products", "[bold]x"], "[bold]x"),  # a bracketed value printed literally, not as markup
                       (["--products", "texture"], "texture"), (["--products", "dsm", "--rerun-from", "ortho"], "not a step")):
        assert main(["run", *args, "-o", str(new), *extra]) == 2
        assert msg in " ".join(capsys.readouterr().err.split())
        assert not new.exists()
    (tmp_path / "empty").mkdir()  # no image: the survey's inputs step refuses it, the new project is not left behind
    assert main(["run", str(tmp_path / "empty"), "-o", str(new), "--workers", "0"]) == 2
    assert "no input images" in capsys.readouterr().err and not new.exists()
    before = _snapshot(project["proj"])
    assert main(["run", *args, "-o", str(project["proj"]), "--rerun-from", "mosaic"]) == 2
    assert _snapshot(project["proj"]) == before
    # PROJECT in or as the images' folder: refused before run.log or anything else is written there
    images = Path(args[0])
    listing = sorted(images.rglob("*"))
    for proj in (images, images / "P"):
        assert main(["run", *args, "-o", str(proj), "--workers", "0"]) == 2
        assert "input images' folder" in " ".join(capsys.readouterr().err.split())
        assert sorted(images.rglob("*")) == listing


def test_a_step_without_progress_reports_that_it_is_still_running(tmp_path):
    from thermogrammetry.pipeline.run import _Meter
    from thermogrammetry.pipeline.runlog import RunLog

    seen = []
    with RunLog(tmp_path / "run.log", echo=seen.append) as log:
        m = _Meter(log, "survey", None)
        m("orient", 32, 32)
        stop = m.heartbeat(every_s=0.2)
        time.sleep(0.7)
        stop.set()
    assert 2 <= sum("survey: still running (" in s for s in seen) <= 4  # every 0.2 s without a report
    assert "last: orient 32/32" in seen[0]
    assert "still running" in (tmp_path / "run.log").read_text()
