"""Issue 14: damaged sequence frames, output sets, file permissions, stale temporaries, size cap, workers."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from test_bad_inputs import counts_img, fff_frame, tiff_bytes, write
from thermogrammetry._atomic import OutputSet, clean_stale_temporaries, write_atomic
from thermogrammetry.cli.main import main
from thermogrammetry.errors import ImageTooLargeError
from thermogrammetry.io import read_thermal


def _seq(n=5, damaged=(), destroy_header=()):
    frames = []
    for i in range(n):
        f = bytearray(fff_frame(counts_img(level=15000 + 100 * i)))
        if i in damaged:  # RawData declares an impossible size: the frame does not decode
            raw_off = 0x40 + 2 * 0x20
            f[raw_off + 2: raw_off + 6] = b"\0\0\0\0"
        if i in destroy_header:
            f[0:4] = b"XXXX"
        frames.append(bytes(f))
    return b"".join(frames)


@pytest.mark.parametrize("how", ["records", "header"])
def test_damaged_sequence_frame_is_reported_and_others_keep_their_names(tmp_path, capsys, how):
    kw = {"damaged": (2,)} if how == "records" else {"destroy_header": (2,)}
    seq = write(tmp_path / "rec.seq", _seq(5, **kw))
    code = main(["convert", str(seq), "-o", str(tmp_path / "OUT")])
    text = " ".join(capsys.readouterr().out.split())
    assert code == 2
    assert "frame 2" in text and "damaged" in text
    names = sorted(p.name for p in (tmp_path / "OUT").glob("*.tif"))
    assert names == ["rec_f00000.tif", "rec_f00001.tif", "rec_f00003.tif", "rec_f00004.tif"]
    # frame 3 holds frame 3's counts (level 15300), not frame 4's
    f3 = read_thermal(tmp_path / "OUT" / "rec_f00003.tif")
    assert f3.metadata.extra["gdal_metadata"]["THERMOGRAMMETRY_FRAME"] == "3"
    ref = read_thermal(write(tmp_path / "one.fff", fff_frame(counts_img(level=15300))))
    np.testing.assert_allclose(f3.temperature_k, ref.temperature_k, atol=1e-4)
    man = json.loads((tmp_path / "OUT" / "convert-manifest.json").read_text())
    assert man["inputs"][0]["ok"] is False and len(man["files"]) == 4


def test_files_get_the_umask_permissions(tmp_path):
    old = os.umask(0o022)
    try:
        import thermogrammetry._atomic as a

        a._MODE = None  # re-read
        p = write_atomic(tmp_path / "x.bin", b"1")
        assert (p.stat().st_mode & 0o777) == 0o644
        with OutputSet(tmp_path / "set", "t") as s:
            s.path("a.txt").write_text("a")
            s.commit()
        assert ((tmp_path / "set").stat().st_mode & 0o777) == 0o755
        assert ((tmp_path / "set" / "t-manifest.json").stat().st_mode & 0o777) == 0o644
    finally:
        os.umask(old)
        a._MODE = None


def test_stale_temporaries_of_dead_processes_are_removed(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)
    stale = write(tmp_path / f".a.tif.{pid}.abc123.tmp", b"x")
    live = write(tmp_path / f".b.tif.{os.getpid()}.abc123.tmp", b"x")
    other = write(tmp_path / ".notes.tmp", b"x")  # not ours: no pid
    (tmp_path / f".OUT.partial-{pid}-xyz").mkdir()
    removed = clean_stale_temporaries(tmp_path, force=True)
    assert not stale.exists() and live.exists() and other.exists()
    assert not (tmp_path / f".OUT.partial-{pid}-xyz").exists() and len(removed) == 2


def test_output_set_is_absent_or_complete(tmp_path):
    out = tmp_path / "OUT"
    with pytest.raises(RuntimeError):
        with OutputSet(out, "t") as s:
            s.path("a.txt").write_text("a")
            raise RuntimeError("interrupted")
    assert not out.exists() and not list(tmp_path.iterdir())
    # replacing an existing set: old manifest removed first, new manifest last
    out.mkdir()
    (out / "keep.txt").write_text("user file")
    with OutputSet(out, "t") as s:
        s.path("a.txt").write_text("a")
        s.commit({"n": 1})
    assert sorted(p.name for p in out.iterdir()) == ["a.txt", "keep.txt", "t-manifest.json"]
    assert json.loads((out / "t-manifest.json").read_text())["files"] == ["a.txt"]


def test_size_cap_is_configurable(tmp_path, monkeypatch):
    p = write(tmp_path / "m.tif", tiff_bytes(np.full((40, 50), 30000, np.uint16)))
    monkeypatch.setenv("THERMOGRAMMETRY_MAX_PIXELS", "1999")
    with pytest.raises(ImageTooLargeError, match=r"m.tif: declares a 50x40 image"):
        read_thermal(p)
    monkeypatch.setenv("THERMOGRAMMETRY_MAX_PIXELS", "2000")
    assert read_thermal(p).shape == (40, 50)


def test_broken_exif_is_noted_not_fatal(tmp_path, monkeypatch):
    import struct

    import thermogrammetry.io.exif as exif

    def broken(data, out):
        out["make"] = "Partly read"
        raise struct.error("unpack requires a buffer of 12 bytes")

    monkeypatch.setattr(exif, "_read_exif", broken)
    data = tiff_bytes(np.full((4, 5), 300.0, np.float32),
                      [(42112, "s", 0, '<GDALMetadata><Item name="UNITTYPE" sample="0" role="unittype">K</Item></GDALMetadata>', True)])
    img = read_thermal(write(tmp_path / "e.tif", data))
    assert np.allclose(img.temperature_k, 300.0)  # the pixels are fine
    assert any("EXIF unreadable" in n and "unpack requires" in n for n in img.metadata.notes)


def test_workers_die_with_their_parent(tmp_path):
    """A parent SIGKILLed while its pool workers run: the workers are gone within seconds."""
    code = (
        "import os, sys, time\n"
        "from concurrent.futures import ProcessPoolExecutor\n"
        "import multiprocessing as mp\n"
        "from thermogrammetry._procs import die_with_parent\n"
        "def init(pp):\n    die_with_parent(pp)\n"
        "def work(_):\n    time.sleep(60); return os.getpid()\n"
        "ex = ProcessPoolExecutor(2, mp_context=mp.get_context('fork'), initializer=init, initargs=(os.getpid(),))\n"
        "fs = [ex.submit(work, i) for i in range(2)]\n"
        "time.sleep(1.5)\n"
        "print(' '.join(str(p) for p in ex._processes), flush=True)\n"
        "time.sleep(60)\n"
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, env=env)
    kids = [int(x) for x in proc.stdout.readline().split()]
    assert len(kids) == 2
    proc.kill()
    proc.wait()
    deadline = time.monotonic() + 10
    alive = kids
    while alive and time.monotonic() < deadline:
        time.sleep(0.1)
        alive = [k for k in kids if _alive(k)]
    assert not alive, f"workers {alive} outlived their parent"


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split()[2] != "Z"
    except OSError:
        return False


def test_replacing_a_set_is_one_atomic_swap(tmp_path, monkeypatch):
    """OUT existed: it is unchanged up to the folder exchange, complete after it; user files survive as the same file."""
    import thermogrammetry._atomic as atomic

    if not atomic._HAS_EXCHANGE:
        pytest.skip("renameat2(RENAME_EXCHANGE) not available here")
    out = tmp_path / "OUT"
    with OutputSet(out, "t") as s:
        s.path("a.txt").write_text("old a")
        s.path("sub/b.txt").write_text("old b")
        s.commit()
    (out / "user.txt").write_text("user file")
    (out / "sub" / "user2.txt").write_text("user file 2")
    inode = (out / "user.txt").stat().st_ino
    before = {p.relative_to(out).as_posix(): p.read_bytes() for p in out.rglob("*") if p.is_file()}

    def dies(a, b):  # the process dies just before the exchange
        raise KeyboardInterrupt

    monkeypatch.setattr(atomic, "_exchange", dies)
    with pytest.raises(KeyboardInterrupt):
        with OutputSet(out, "t") as s:
            s.path("a.txt").write_text("new a")
            s.commit()
    assert {p.relative_to(out).as_posix(): p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    monkeypatch.undo()
    with OutputSet(out, "t") as s:
        s.path("a.txt").write_text("new a")
        s.commit({"n": 2})
    assert (out / "a.txt").read_text() == "new a"
    assert (out / "sub" / "b.txt").read_text() == "old b"  # older outputs the new set does not replace stay
    assert (out / "user.txt").stat().st_ino == inode and (out / "sub" / "user2.txt").read_text() == "user file 2"
    assert json.loads((out / "t-manifest.json").read_text())["files"] == ["a.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["OUT"]  # no staging folder left


def test_a_set_published_while_another_run_created_out_goes_over_it(tmp_path, monkeypatch):
    """OUT absent when the run looked, created by another run before this one's rename: the rename fails (the
    folder is not empty) and the set is published over the other run's OUT instead -- both complete, OUT whole."""
    out = tmp_path / "OUT"
    a = OutputSet(out, "t")
    a.path("a.txt").write_text("from A")
    with OutputSet(out, "t") as b:  # the other run publishes first
        b.path("a.txt").write_text("from B")
        b.path("b_only.txt").write_text("B")
        b.commit()
    real_exists = type(out).exists
    monkeypatch.setattr(type(out), "exists", lambda p: False if p == out else real_exists(p))  # A looked before B
    a.commit({"run": "A"})
    monkeypatch.undo()
    assert (out / "a.txt").read_text() == "from A" and (out / "b_only.txt").read_text() == "B"
    assert json.loads((out / "t-manifest.json").read_text())["run"] == "A"
    assert [p.name for p in tmp_path.iterdir()] == ["OUT"]


def test_output_apart_from_the_inputs(tmp_path):
    """An input folder refuses an OUT that is it, lies inside it or contains it (also through a symlink); an input
    file refuses only an OUT that is its own folder (an OUT beside a video or a frame is usual)."""
    from thermogrammetry._atomic import check_output_apart
    from thermogrammetry.errors import DataFileError

    sv = tmp_path / "survey"
    (sv / "frames").mkdir(parents=True)
    video = write(tmp_path / "flight.mp4", b"x")
    (tmp_path / "link").symlink_to(sv, target_is_directory=True)
    for out, how in ((sv, "is"), (sv / "frames", "lies inside"), (sv / "new" / "OUT", "lies inside"),
                     (tmp_path, "contains"), (tmp_path / "link", "is"), (tmp_path / "link" / "o", "lies inside")):
        with pytest.raises(DataFileError, match=f": {how} the survey folder {sv}; expected an output folder apart"):
            check_output_apart(out, [("survey folder", sv)])
    for out in (tmp_path / "OUT", tmp_path / "survey2", tmp_path / "surv"):
        check_output_apart(out, [("survey folder", sv)])  # beside it, or a name it begins with: accepted
    check_output_apart(tmp_path / "OUT", [("input images' folder", video)])
    check_output_apart(tmp_path.parent, [("input images' folder", video)])
    with pytest.raises(DataFileError, match=r"-o .*: is the input images' folder"):
        check_output_apart(tmp_path, [("input images' folder", video)])
