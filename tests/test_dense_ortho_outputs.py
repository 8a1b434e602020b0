"""dense and ortho against killed and concurrent runs: the spills and temporaries of a run are its own.

A run killed outright (SIGKILL, power loss) leaves its staging folder beside OUT, its spill inside it and its
GeoTIFF temporaries; the next run removes those whose process is gone, and its cloud has exactly the points of
a clean run (an older version appended to a fixed-name spill in OUT: a rerun had twice the points). Two runs into
one OUT at once: each builds its own set, the one that publishes last is what OUT holds, complete. The survey is
3 frames with TRUE poses (tests/survey_truth.py): ~1.5 s per dense run.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from survey_truth import write_true_dsm, write_true_survey  # noqa: E402

from thermogrammetry.cli.main import main  # noqa: E402

FRAMES = [18, 19, 20]


def _dead_pid() -> int:
    """The id of a process that has ended (a killed run's)."""
    p = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True, check=True)
    return int(p.stdout)


def _las_points(p: Path) -> int:
    import laspy

    with laspy.open(p) as f:
        return int(f.header.point_count)


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    root = tmp_path_factory.mktemp("killed")
    sc, sv = write_true_survey(root / "survey", frames=FRAMES)
    write_true_dsm(root / "dsm.tif", sc, 0.3)
    assert main(["dense", str(sv), "-o", str(root / "clean"), "--workers", "0"]) == 0
    n = json.loads((root / "clean" / "dense.json").read_text())["points"]
    assert n > 10_000 and _las_points(root / "clean" / "cloud.las") == n
    return root, sv, n


def _stale(folder: Path, pid: int, name: str) -> list[Path]:
    """What a run of process ``pid`` killed while writing into ``folder/name`` leaves behind."""
    stage = folder / f".{name}.partial-{pid}-k1ll3d"
    spill = stage / f".dense.spill-{pid}-k1ll3d"
    spill.mkdir(parents=True)
    (spill / "tile_0_0.bin").write_bytes(b"\0" * 4096)
    (folder / name).mkdir(exist_ok=True)
    legacy = folder / name / ".dense_tiles"  # the fixed-name spill of an older version, in OUT itself
    legacy.mkdir()
    (legacy / "tile_0_0.bin").write_bytes(b"\0" * 4096)
    tmp = folder / name / f".dsm.tif.{pid}.abcd1234.tmp.tif"
    tmp.write_bytes(b"II*\0")
    cog = folder / name / f".ortho.tif.{pid}.abcd1234.cog.tif"
    cog.write_bytes(b"II*\0")
    return [stage, legacy, tmp, cog]


def test_dense_rerun_after_a_killed_run_has_the_clean_point_count(clean):
    base, sv, n = clean
    root = base / "rerun"  # a folder this process has not written into yet (stale files are looked for once)
    root.mkdir()
    left = _stale(root, _dead_pid(), "OUT")
    live = root / f".OUT.partial-{os.getpid()}-running"  # a staging folder of a run still going: kept
    live.mkdir()
    assert main(["dense", str(sv), "-o", str(root / "OUT"), "--workers", "0"]) == 0
    assert json.loads((root / "OUT" / "dense.json").read_text())["points"] == n
    assert _las_points(root / "OUT" / "cloud.las") == n
    assert [p for p in left if p.exists()] == [] and live.is_dir()
    man = json.loads((root / "OUT" / "dense-manifest.json").read_text())
    assert not [f for f in man["files"] if "tile_" in f or "spill" in f]
    live.rmdir()


def test_two_dense_runs_into_one_out_give_one_clean_cloud(clean):
    """Run B starts and completes while run A is between its reference images; A then publishes its own set."""
    from thermogrammetry.pipeline.dense import run_dense

    root, sv, n = clean
    out = root / "BOTH"
    started = []

    def a_progress(done, total):
        if not started:
            started.append(True)
            rb = run_dense(sv, out, workers=0)
            assert rb["points"] == n
    ra = run_dense(sv, out, workers=0, on_image=a_progress)
    assert ra["points"] == n and started
    assert _las_points(out / "cloud.las") == n
    assert json.loads((out / "dense-manifest.json").read_text())["complete"] is True
    assert not [p for p in root.iterdir() if p.name.startswith(".BOTH.")]


def test_ortho_rerun_removes_a_killed_runs_temporaries(clean):
    base, sv, _ = clean
    root = base / "ortho"
    root.mkdir()
    left = _stale(root, _dead_pid(), "ORTHO")
    assert main(["ortho", str(sv), "--dsm", str(base / "dsm.tif"), "-o", str(root / "ORTHO"),
                 "--workers", "0"]) == 0
    assert (root / "ORTHO" / "ortho.tif").is_file()
    assert [p for p in left if p.exists() and p.name != ".dense_tiles"] == []


def test_a_damaged_frame_is_skipped_by_name_and_the_cloud_is_the_others(clean, capsys):
    """A fourth image whose frame is cut after 60 bytes: dense and ortho skip it by name, list it, exit 0; the cloud is
    the clean run's (the same three images)."""
    import shutil

    from thermogrammetry.io.oriented import OrientedCameras

    base, sv, n = clean
    s2 = Path(shutil.copytree(sv, base / "damaged_survey"))
    oc = OrientedCameras.load(s2)
    bad = oc.images[0]
    d = oc.to_dict()
    extra = dict(d["images"][0], name="cut", frame="frames/cut.tif")
    d["images"].append(extra)
    (s2 / "frames" / "cut.tif").write_bytes((s2 / bad.frame).read_bytes()[:60])
    (s2 / "cameras.json").write_text(json.dumps(d))
    capsys.readouterr()
    assert main(["dense", str(s2), "-o", str(base / "dense_cut"), "--workers", "0"]) == 0
    rep = json.loads((base / "dense_cut" / "dense.json").read_text())
    assert rep["points"] == n and [s["name"] for s in rep["skipped_frames"]] == ["cut"]
    assert "cut.tif" in rep["skipped_frames"][0]["reason"]
    err = " ".join(capsys.readouterr().err.split())
    assert "1 frame(s) skipped" in err and "cut:" in err
    assert main(["ortho", str(s2), "--dsm", str(base / "dsm.tif"), "-o", str(base / "ortho_cut"), "--workers", "0"]) == 0
    rep = json.loads((base / "ortho_cut" / "ortho.json").read_text())
    assert [s["name"] for s in rep["skipped_frames"]] == ["cut"] and "cut" not in rep["images"].values()
    assert rep["cells"] > 1000


def test_messages_print_bracketed_values_literally():
    import io

    from rich.console import Console

    from thermogrammetry.cli.app import print_error, print_plain

    buf = io.StringIO()
    con = Console(file=buf, width=200, color_system=None)
    print_error(con, "t: expected finite numbers, got [nan, 1] and [red]x[/red]")
    print_plain(con, "note: frame [bold]a[/bold].tif skipped")
    text = buf.getvalue()
    assert "error: t: expected finite numbers, got [nan, 1] and [red]x[/red]" in text
    assert "note: frame [bold]a[/bold].tif skipped" in text


def test_cameras_json_loads_in_linear_time():
    """The checks of every image are one pass (the duplicate-name check was quadratic: 100,000 images never loaded).
    Counted, not timed (a timing depends on the machine's load): the Python-level calls of ``from_dict`` and one
    lookup by name, plus every comparison of two image names (the names are a ``str`` subclass that counts its
    ``==``, which C-level loops such as ``list.count`` also call), grow in proportion to the images -- 4x the
    images, 3.6-4.4x the count (a check that compares every image with every other: 16x). The count is
    deterministic; the band leaves room only for the constant part."""
    import sys

    from thermogrammetry.camera import Camera
    from thermogrammetry.io.oriented import OrientedCameras, OrientedImage

    count = [0]

    class Name(str):
        def __eq__(self, other):
            count[0] += 1
            return str.__eq__(self, other)

        __hash__ = str.__hash__

        def __str__(self):
            return self

    cam = Camera("pinhole", (40, 30), {"fx": 40.0, "fy": 40.0, "cx": 19.5, "cy": 14.5})
    d = OrientedCameras({"c": cam}, [OrientedImage(f"i{k}", "c", np.eye(3), [0.1 * k, 0, 50], frame=f"frames/i{k}.tif",
                                                   center_std=[0.1, 0.1, 0.2]) for k in range(8_000)]).to_dict()
    for e in d["images"]:
        e["name"] = Name(e["name"])

    def calls(n):
        dd = dict(d, images=d["images"][:n])

        def prof(frame, event, arg):
            if event in ("call", "c_call"):
                count[0] += 1

        count[0] = 0
        sys.setprofile(prof)
        try:
            oc = OrientedCameras.from_dict(dd)
            last = oc.image(f"i{n - 1}")
        finally:
            sys.setprofile(None)
        assert len(oc) == n and last.name == f"i{n - 1}" and type(oc.images[0].name) is Name
        return count[0]

    calls(200)  # imports (pyproj is not needed here: no CRS)
    small, large = calls(2_000), calls(8_000)
    assert 3.6 * small < large < 4.4 * small, (small, large)


def _dense_process(sv: Path, out: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path), OMP_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, "-m", "thermogrammetry", "dense", str(sv), "-o", str(out), "--workers", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def test_dense_sigkilled_mid_run_then_rerun_and_two_processes_at_once(clean):
    """Real processes: a dense run SIGKILLed after its first reference image leaves its staging folder (with the
    spill); the rerun removes it and has the clean point count. Two dense processes started together into one OUT:
    both complete (the one that publishes second swaps its set in over the first), OUT holds one clean cloud."""
    base, sv, n = clean
    root = base / "sigkill"
    root.mkdir()
    p = _dense_process(sv, root / "OUT")
    for line in p.stderr:
        if "reference images 1/" in line:
            break
    p.kill()
    p.wait(timeout=30)
    left = [q for q in root.iterdir() if ".partial-" in q.name]
    assert left and not (root / "OUT").exists()
    assert main(["dense", str(sv), "-o", str(root / "OUT"), "--workers", "0"]) == 0
    assert _las_points(root / "OUT" / "cloud.las") == n
    assert not [q for q in root.iterdir() if ".partial-" in q.name]

    both = base / "together"
    both.mkdir()
    procs = [_dense_process(sv, both / "OUT") for _ in range(2)]
    results = [(q.wait(timeout=120), q.stderr.read()) for q in procs]
    codes = sorted(c for c, _ in results)
    assert codes == [0, 0], results  # the second to publish publishes over the first (one atomic swap)
    assert all("Traceback" not in e for _, e in results), results
    assert _las_points(both / "OUT" / "cloud.las") == n
    assert json.loads((both / "OUT" / "dense.json").read_text())["points"] == n
    assert json.loads((both / "OUT" / "dense-manifest.json").read_text())["complete"] is True
    assert [q.name for q in both.iterdir()] == ["OUT"]


def test_dense_and_ortho_reports_are_outputs_with_the_header(clean, tmp_path):
    """report.html is in dense's and ortho's OUT and manifest; its header names the version, the command line as typed
    (the CLI) or the driver's Python call, the survey's CRS, the inputs; the ortho's figures include the σ map only
    when ortho_sigma.tif was written."""
    import shlex

    import thermogrammetry
    from report_fields import header_fields
    from thermogrammetry.pipeline.ortho import run_ortho

    root, sv, n = clean
    crs = json.loads((sv / "cameras.json").read_text())["crs"]
    dense = root / "clean"
    assert "report.html" in json.loads((dense / "dense-manifest.json").read_text())["files"]
    page = (dense / "report.html").read_text()
    f = header_fields(page)
    assert f["software"] == f"thermogrammetry {thermogrammetry.__version__}"
    assert f["command"] == shlex.join(["thermogrammetry", "dense", str(sv), "-o", str(dense), "--workers", "0"])
    assert f["crs"].startswith(f"{crs} (") and f["inputs"] == f"3 oriented images of the survey in {sv.resolve()}"
    rep = json.loads((dense / "dense.json").read_text())
    assert f["gsd"].startswith(f"{100 * rep['gsd_m']:.1f} cm") and 35.0 < float(f["flying_height"].split()[0]) < 50.0
    assert f"{n:,}" in page and f"{100 * rep['completeness']:.1f} %" in page and page.count("data:image/png") == 2

    out = tmp_path / "O"
    assert main(["ortho", str(sv), "--dsm", str(dense / "dsm.tif"), "-o", str(out), "--workers", "0"]) == 0
    assert "report.html" in json.loads((out / "ortho-manifest.json").read_text())["files"]
    page = (out / "report.html").read_text()
    f = header_fields(page)
    assert f["command"] == shlex.join(["thermogrammetry", "ortho", str(sv), "--dsm", str(dense / "dsm.tif"), "-o",
                                       str(out), "--workers", "0"])
    assert f["crs"].startswith(f"{crs} (") and f"DSM: {(dense / 'dsm.tif').resolve()}" in f["inputs"]
    rep = json.loads((out / "ortho.json").read_text())
    assert f"values in {rep['unit']} (temperature (K))" in page and f"{rep['cells']:,}" in page
    assert f"{rep['fill']['ortho_cells_on_filled']:,} mosaic cells" in page
    assert page.count("data:image/png") == 3 and "Precision of each cell" in page  # ortho, coverage, σ

    # from Python: the driver's call is the command line; no σ map without ortho_sigma.tif
    run_ortho(sv, dense / "dsm.tif", tmp_path / "P", workers=0, sigma=False)
    page = (tmp_path / "P" / "report.html").read_text()
    cmd = header_fields(page)["command"]
    assert cmd.startswith(f"thermogrammetry.pipeline.ortho.run_ortho({str(sv)!r}, ") and cmd.endswith("sigma=False)")
    assert "workers=0" in cmd and "Precision of each cell" not in page and page.count("data:image/png") == 2
