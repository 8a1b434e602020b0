"""Every verb that writes a folder publishes it through the one output publisher (``_atomic.OutputSet``).

A file the user keeps in OUT (notes, a QGIS project) is still there, byte for byte, after ``survey``, ``dense``,
``ortho``, ``texture`` and ``facade`` wrote into that OUT; the verb's own files are there as well, listed in its
``<verb>-manifest.json``; no staging folder is left beside OUT. The inputs are small synthetic cases of the
verbs' own tests (true poses for dense/ortho/texture/facade; survey on a few rendered frames).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from survey_truth import write_true_dsm, write_true_survey  # noqa: E402
from test_texture_counts import _write  # noqa: E402

from thermogrammetry.cli.main import main  # noqa: E402

NOTE = "my notes: flight of 2026-11-30, wind 3 m/s\n"
FRAMES = [k for line in (1, 2) for k in range(14 * line + 4, 14 * line + 9)]  # 2 lines x 5 frames (as test_ortho)


def _out_with_user_file(parent: Path, name: str = "OUT") -> Path:
    out = parent / name
    (out / "sub").mkdir(parents=True)
    (out / "notes.txt").write_text(NOTE)
    (out / "sub" / "project.qgz").write_bytes(b"\x00user bytes\xff")
    return out


def _check(out: Path, verb: str, produced: list[str]) -> None:
    assert (out / "notes.txt").read_text() == NOTE
    assert (out / "sub" / "project.qgz").read_bytes() == b"\x00user bytes\xff"
    man = json.loads((out / f"{verb}-manifest.json").read_text())
    assert man["verb"] == verb and man["complete"] is True
    for f in produced:
        assert (out / f).is_file(), f
        assert f in man["files"], f
    assert "notes.txt" not in man["files"]
    assert not list(out.parent.glob(f".{out.name}.partial-*"))


@pytest.fixture(scope="module")
def true_survey(tmp_path_factory):
    root = tmp_path_factory.mktemp("keep")
    sc, sv = write_true_survey(root / "survey", frames=FRAMES)
    write_true_dsm(root / "dsm.tif", sc, 0.1)
    return root, sv


def test_dense_and_ortho_keep_a_users_file_in_out(true_survey):
    root, sv = true_survey
    out = _out_with_user_file(root, "dense")
    assert main(["dense", str(sv), "-o", str(out), "--workers", "0"]) == 0
    _check(out, "dense", ["cloud.las", "cloud.ply", "dsm.tif", "dense.json"])
    out = _out_with_user_file(root, "ortho")
    assert main(["ortho", str(sv), "--dsm", str(root / "dsm.tif"), "-o", str(out), "--workers", "0"]) == 0
    _check(out, "ortho", ["ortho.tif", "ortho_u16.tif", "ortho_source.tif", "ortho.json"])
    # a second run into the same OUT: still the user's file, the outputs replaced
    before = json.loads((out / "ortho.json").read_text())
    assert main(["ortho", str(sv), "--dsm", str(root / "dsm.tif"), "-o", str(out), "--workers", "1"]) == 0
    _check(out, "ortho", ["ortho.tif", "ortho.json"])
    assert json.loads((out / "ortho.json").read_text())["cells"] == before["cells"]


def test_texture_and_facade_keep_a_users_file_in_out(tmp_path):
    survey = _write(tmp_path / "wall")
    out = _out_with_user_file(tmp_path, "tex")
    assert main(["texture", str(survey), "--mesh", str(survey / "mesh.obj"), "-o", str(out), "--texel-size", "0.02"]) == 0
    _check(out, "texture", ["texture.json", "textured.glb", "temperature_texture.tif"])
    out = _out_with_user_file(tmp_path, "fac")
    assert main(["facade", str(survey), "-o", str(out), "--plane", "0,0,0,0,-1,0", "--cell", "0.05"]) == 0
    _check(out, "facade", ["facade.json", "facade_temperature.tif"])


def test_survey_keeps_a_users_file_in_out(true_survey, tmp_path):
    _, sv = true_survey
    out = _out_with_user_file(tmp_path)
    # three of the frames: what is asserted (the user's files kept, the survey's files published) does not depend on
    # how many frames are oriented, and three take seconds where ten took a minute and a half
    frames = sorted(p for p in (sv / "frames").iterdir() if p.is_file())[:3]
    rc = main(["survey", *map(str, frames), "-o", str(out), "--workers", "0", "--gnss", "none", "--low-texture", "off",
              "--input-unit", "K"])
    assert rc in (0, 1)  # 1: nothing oriented -- OUT still holds survey.json and the reasons
    _check(out, "survey", ["survey.json", "cameras.json", "report.html"])
