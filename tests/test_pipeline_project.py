import json
import os

import numpy as np
import pytest

from thermogrammetry.errors import DataFileError, InvalidInputError
from thermogrammetry.pipeline import FolderProject, MemoryProject, Step, run_steps, write_atomic


@pytest.mark.parametrize("kind", ["folder", "memory"])
def test_store_round_trip(kind, tmp_path):
    store = FolderProject(tmp_path / "proj") if kind == "folder" else MemoryProject()
    store.write_json("calibration/camera.json", {"a": np.float64(1.5), "b": np.arange(3)})
    assert store.read_json("calibration/camera.json") == {"a": 1.5, "b": [0, 1, 2]}
    arr = np.linspace(0, 1, 7, dtype=np.float32).reshape(7, 1)
    store.write_array("x/arr.npy", arr)
    np.testing.assert_array_equal(store.read_array("x/arr.npy"), arr)
    assert store.keys("calibration/") == ["calibration/camera.json"]
    assert store.exists("x/arr.npy") and not store.exists("x/none.npy")
    with pytest.raises(DataFileError, match="none.npy"):
        store.read_bytes("x/none.npy")
    with pytest.raises(InvalidInputError, match=r"'\.\./escape': expected a relative POSIX path"):
        store.write_text("../escape", "x")


def test_write_atomic_keeps_old_content_on_failure(tmp_path):
    target = tmp_path / "out.bin"
    write_atomic(target, b"old")

    with pytest.raises(TypeError):
        write_atomic(target, object())  # not bytes: the write fails mid-way
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.bin"]  # no temp file left behind


def test_run_steps_times_and_stops_at_failure():
    store = MemoryProject()

    def ok(p):
        p.write_text("a.txt", "a")
        return {"n": 1}

    def bad(p):
        raise ValueError("bad thing")

    reps = run_steps(store, [Step("first", ok), Step("second", bad), Step("third", ok)])
    assert [r.status for r in reps] == ["ok", "failed"]
    assert reps[1].error == "ValueError: bad thing"
    rep = json.loads(store.read_text("reports/first.json"))
    assert rep["summary"] == {"n": 1} and rep["seconds"] >= 0.0
    assert store.exists("reports/second.json") and not store.exists("reports/third.json")


def test_staging_folder_writes_skip_fsync_and_are_flushed_once(tmp_path, monkeypatch):
    """A non-durable FolderProject (the survey's staging folder) writes atomically without one fsync per file;
    sync_folder flushes the folder once; a missing folder is an error naming it."""
    import os

    from thermogrammetry._atomic import sync_folder
    from thermogrammetry.errors import DataFileError

    calls = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (calls.append(fd), real(fd))[1])
    stage = FolderProject(tmp_path / "stage", durable=False)
    for k in range(5):
        stage.write_bytes(f"matches/{k}.npz", bytes([k]) * 10)
    assert calls == []
    assert [stage.read_bytes(f"matches/{k}.npz") for k in range(5)] == [bytes([k]) * 10 for k in range(5)]
    assert not [p for p in (tmp_path / "stage").rglob("*.tmp")]
    FolderProject(tmp_path / "out").write_bytes("a.json", b"{}")
    assert len(calls) == 1  # the default store stays durable: one fsync per file
    sync_folder(tmp_path / "stage")
    with pytest.raises(DataFileError, match="missing"):
        sync_folder(tmp_path / "missing")
