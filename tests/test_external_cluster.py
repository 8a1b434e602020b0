"""``--scheduler ADDRESS``: a verb's tasks on a dask cluster the user started (``dask scheduler`` and two ``dask worker``
processes, as on several machines sharing a path), with the same outputs as the run in this process, also when a
worker is killed mid-run (its tasks are rerun on the other).

The verb is ``dense`` on a 6-frame survey with TRUE poses (tests/survey_truth.py): the cloud, the DSMs and dense.json
(without its timings and the worker fields) must be byte for byte those of ``--workers 0``.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from survey_truth import write_true_survey  # noqa: E402
from verb_process import VerbProcess  # noqa: E402

pytest.importorskip("distributed")
DASK = Path(sys.executable).with_name("dask")
FILES = ("cloud.las", "cloud.ply", "dsm.tif", "dsm_filled.tif")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A scheduler and two single-threaded workers, each its own process (session), closed at the end."""
    if not DASK.is_file():
        pytest.skip(f"no dask command beside {sys.executable}")
    root = tmp_path_factory.mktemp("cluster")
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    procs = [subprocess.Popen([str(DASK), "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                              stdout=subprocess.DEVNULL, stderr=open(root / "scheduler.log", "w"), start_new_session=True)]
    for w in ("w1", "w2"):
        procs.append(subprocess.Popen([str(DASK), "worker", addr, "--nthreads", "1", "--no-dashboard", "--no-nanny",
                                       "--name", w], stdout=subprocess.DEVNULL, stderr=open(root / f"{w}.log", "w"),
                                      start_new_session=True))
    from distributed import Client

    with Client(addr, timeout=60) as c:
        c.wait_for_workers(2, timeout=60)
    yield addr, {"w1": procs[1], "w2": procs[2]}
    for p in procs[::-1]:  # (SIGKILL: a SIGTERMed dask worker takes up to 30 s to close; nothing of theirs is kept)
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    for p in procs:
        p.wait(timeout=30)


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    root = tmp_path_factory.mktemp("cluster-survey")
    _, sv = write_true_survey(root / "survey", frames=[16, 17, 18, 19, 20, 21])
    out = root / "local"
    r = subprocess.run([sys.executable, "-m", "thermogrammetry", "dense", str(sv), "-o", str(out), "--workers", "0"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return root, sv, out


def _report(path: Path) -> dict:
    """A verb's JSON report without what says how and how fast it ran."""
    d = json.loads(path.read_text())
    for k in ("seconds", "workers", "scheduler", "timing", "steps"):
        d.pop(k, None)
    return d


def _same_outputs(a: Path, b: Path) -> None:
    for f in FILES:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    assert _report(a / "dense.json") == _report(b / "dense.json")


def test_dense_on_an_existing_cluster_equals_the_local_run(cluster, survey):
    addr, _ = cluster
    root, sv, local = survey
    out = root / "on-cluster"
    r = subprocess.run([sys.executable, "-m", "thermogrammetry", "dense", str(sv), "-o", str(out), "--scheduler", addr],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    _same_outputs(local, out)


def test_a_worker_killed_mid_run_costs_its_tasks_not_the_run(cluster, survey):
    addr, workers = cluster
    root, sv, local = survey
    out = root / "worker-killed"
    v = VerbProcess(["dense", sv, "-o", out, "--scheduler", addr])
    killed = v.wait_for_line("reference images 1/", 300)
    os.killpg(workers["w1"].pid, signal.SIGKILL)  # as a machine that goes away
    workers["w1"].wait(timeout=30)
    err = v.finish(600)
    assert v.p.returncode == 0, err
    _same_outputs(local, out)
    if not killed:
        pytest.skip("dense ended before the worker could be killed (outputs checked); the kill was not exercised")


def test_ortho_on_an_existing_cluster_equals_the_local_run(cluster, survey):
    """The ortho of the local run's DSM, its tiles on the cluster: every raster and ortho.json (timings aside) as in
    this process."""
    addr, workers = cluster
    if workers["w1"].poll() is not None and workers["w2"].poll() is not None:
        pytest.skip("no worker left")
    root, sv, local = survey
    outs = {}
    for name, flags in (("ortho-local", ["--workers", "0"]), ("ortho-cluster", ["--scheduler", addr])):
        outs[name] = root / name
        r = subprocess.run([sys.executable, "-m", "thermogrammetry", "ortho", str(sv), "--dsm", str(local / "dsm.tif"),
                            "-o", str(outs[name]), *flags], capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr
    a, b = outs["ortho-local"], outs["ortho-cluster"]
    tifs = sorted(p.name for p in a.glob("*.tif"))
    assert tifs and tifs == sorted(p.name for p in b.glob("*.tif"))
    for f in tifs:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    assert _report(a / "ortho.json") == _report(b / "ortho.json")
