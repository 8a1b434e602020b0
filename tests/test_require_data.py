"""``THERMOGRAMMETRY_REQUIRE_DATA=1`` turns missing real data into a failure of every test that needs it (conftest:
``shared_data``, ``data_path``, ``data_missing``); without it such tests skip. Run in a child pytest on a probe
file, with ``THERMOGRAMMETRY_DATA`` pointing at a folder that does not exist."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent

PROBE = '''
from conftest import data_missing, data_path, shared_data  # the fixture is found through the import

def test_uses_the_fixture(shared_data):
    assert shared_data.is_dir()

def test_uses_data_path():
    assert data_path("bal", "problem-21-11315-pre.txt.bz2").is_file()

def test_calls_data_missing():
    data_missing("probe: a sub-folder is absent")
'''


def _run(tmp_path, require: str | None):
    (tmp_path / "test_probe.py").write_text(PROBE)
    env = {k: v for k, v in os.environ.items() if k not in ("THERMOGRAMMETRY_REQUIRE_DATA", "PYTEST_XDIST_WORKER_COUNT",
                                                           "PYTEST_ADDOPTS")}
    env["THERMOGRAMMETRY_DATA"] = str(tmp_path / "no-such-data")
    env["PYTHONPATH"] = os.pathsep.join([str(TESTS), env.get("PYTHONPATH", "")])
    if require is not None:
        env["THERMOGRAMMETRY_REQUIRE_DATA"] = require
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rsf", "-p", "no:cacheprovider", "-p", "no:xdist",
                        "--rootdir", str(tmp_path), "-c", os.devnull, str(tmp_path / "test_probe.py")],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    return r.returncode, r.stdout + r.stderr


@pytest.mark.parametrize("require", [None, "0", ""])
def test_missing_data_skips_without_the_variable(tmp_path, require):
    code, out = _run(tmp_path, require)
    assert code == 0 and "3 skipped" in out and "failed" not in out, out
    assert "no-such-data" in out and "absent" in out, out  # the reason names the missing folder


def test_missing_data_fails_with_the_variable(tmp_path):
    code, out = _run(tmp_path, "1")
    # the fixture's failure is reported as an error in the test's setup: a failed run either way
    assert code == 1 and "2 failed, 1 error" in out and "skipped" not in out, out
    assert out.count("THERMOGRAMMETRY_REQUIRE_DATA is set") >= 3 and "no-such-data" in out, out
