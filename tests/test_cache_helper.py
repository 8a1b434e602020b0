"""tests/_cache.py: an entry is built once per cache root (any number of SceneCache objects, as the xdist workers
have), a builder that failed is run again, and the key covers every parameter."""

from __future__ import annotations

import multiprocessing

import pytest

from _cache import SceneCache, copy_entry


def _build_in_child(root, log):
    def build(folder):
        with open(log, "a") as fh:
            fh.write("built\n")
        (folder / "a.txt").write_text("x")
        return 7

    return SceneCache(root).folder("s", {"seed": 1}, build)[1]


def test_entry_is_built_once_across_processes_and_instances(tmp_path):
    root, log = tmp_path / "cache", tmp_path / "log.txt"
    ctx = multiprocessing.get_context("fork")
    with ctx.Pool(2) as pool:
        values = pool.starmap(_build_in_child, [(root, log)] * 4)
    assert values == [7] * 4 and log.read_text() == "built\n"
    folder, value = SceneCache(root).folder("s", {"seed": 1}, lambda f: pytest.fail("built again"))
    assert value == 7 and (folder / "a.txt").read_text() == "x"
    own = copy_entry(folder, tmp_path / "own")
    assert sorted(p.name for p in own.iterdir()) == ["a.txt"]
    # another parameter, another entry
    assert SceneCache(root).value("s", {"seed": 2}, lambda: 8) == 8


def test_failed_builder_leaves_no_entry(tmp_path):
    cache = SceneCache(tmp_path)

    def broken(folder):
        (folder / "half.txt").write_text("")
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        cache.folder("s", {}, broken)
    folder, value = SceneCache(tmp_path).folder("s", {}, lambda f: "ok")
    assert value == "ok" and not (folder / "half.txt").exists()
