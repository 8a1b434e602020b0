"""Shared test fixtures.

Real data lives in ``../shared/data`` beside the repository (see its INDEX.md);
tests that need it use the ``shared_data`` fixture (or ``data_path``, or call ``data_missing``) and skip, with a
clear reason, when it is absent. Set ``THERMOGRAMMETRY_DATA`` to point elsewhere. With
``THERMOGRAMMETRY_REQUIRE_DATA=1`` (CI, which has the data) a missing folder or file FAILS every test that needs it
instead: a CI that lost ``../shared/data`` cannot pass by skipping every real-data test.

Synthetic scenes that several tests render and survey are built once per test run through the ``scene_cache``
fixture (``_cache.py``, ``cached_scenes.py``), shared by the pytest-xdist workers.

Under pytest-xdist each worker's BLAS and OpenCV thread pools are limited to its share of the cores (2 workers on
2 cores: one thread each): two workers whose libraries each start a thread per core only contend for the cores.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("THERMOGRAMMETRY_DATA", REPO_ROOT.parent / "shared" / "data"))


_THREAD_LIMITS = None  # the threadpoolctl limiter of this worker (kept for the whole session)


def pytest_configure(config):
    """Under pytest-xdist: BLAS and OpenCV threads of this worker limited to its share of the cores."""
    global _THREAD_LIMITS
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if workers < 2:
        return
    share = max(1, (os.cpu_count() or 1) // workers)
    from threadpoolctl import threadpool_limits

    _THREAD_LIMITS = threadpool_limits(limits=share)
    import cv2

    cv2.setNumThreads(share)


def data_required() -> bool:
    """``THERMOGRAMMETRY_REQUIRE_DATA`` is set to anything but empty / ``0``: missing real data is a failure."""
    return os.environ.get("THERMOGRAMMETRY_REQUIRE_DATA", "").strip() not in ("", "0")


def data_missing(reason: str):
    """The one place a test meets missing real data: skips it with ``reason``, or fails it when
    ``THERMOGRAMMETRY_REQUIRE_DATA=1``."""
    if data_required():
        pytest.fail(f"{reason}; THERMOGRAMMETRY_REQUIRE_DATA is set, so missing real data is a failure", pytrace=False)
    pytest.skip(reason)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Root of the shared real-data folder; skips the test when it is missing (fails with the variable set)."""
    if not SHARED_DATA.is_dir():
        data_missing(f"real data folder {SHARED_DATA} is absent (set THERMOGRAMMETRY_DATA)")
    return SHARED_DATA


def data_path(*parts: str) -> Path:
    """Path under the shared data folder; skips the calling test when it does not exist (fails with
    ``THERMOGRAMMETRY_REQUIRE_DATA=1``)."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        data_missing(f"real data file {p} is absent")
    return p


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded generator; tests are deterministic."""
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def scene_cache(tmp_path_factory):
    """The session-wide cache of rendered / surveyed synthetic scenes (``_cache.SceneCache``)."""
    from _cache import SceneCache

    return SceneCache.for_session(tmp_path_factory)


# ------------------------------------------------------------------------------------ scheduling under pytest-xdist
#: the test files that take longest (worker-seconds of `pytest -n 2 --durations=0` on 2026-12-02), started first so
#: that the two workers finish together; files not listed follow in collection order
HEAVY_FIRST = (
    "test_survey.py", "test_survey_rig.py", "test_survey_building_rings.py", "test_texture_meshfit_ring.py",
    "test_circle_coded_marks.py", "test_lowtexture_sequence.py", "test_texture_survey_poses.py",
    "test_calibration_circle_grid.py", "test_survey_strip.py", "test_detect.py", "test_detect_circles_lowcontrast.py",
    "test_lowtexture_guard.py", "test_outputs_keep_user_files.py", "test_maskgrid_replica.py", "test_texture.py",
    "test_rigreg.py", "test_calibration_selfcal.py", "test_photofit.py", "test_calibration_circle_partial.py",
    "test_adjustment_chunked.py", "test_io_video.py", "test_projected_crs_geometry.py", "test_detect_realdata.py",
    "test_calibration_circle_cli.py", "test_detect_lowcontrast.py",
)


def _module_fixture_groups(items) -> dict:
    """``{item: group name}``: the tests of one file that share a module-scoped fixture (directly or through another
    fixture) form one group (union-find over the fixtures), so that ``--dist loadgroup`` runs them on one worker and
    the fixture is built once; a test without module-scoped fixtures gets no group (it goes wherever a worker is
    free)."""
    parent: dict = {}

    def find(x):
        while parent.setdefault(x, x) != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    fixtures_of = {}
    for item in items:
        info = getattr(item, "_fixtureinfo", None)
        if info is None:
            continue
        mods = []
        for name in info.names_closure:
            defs = info.name2fixturedefs.get(name) or ()
            if defs and defs[-1].scope == "module":
                mods.append((item.module.__name__, name))
        if mods:
            fixtures_of[item] = mods
            for m in mods[1:]:
                parent[find(m)] = find(mods[0])
    return {item: "%s:%s" % find(mods[0]) for item, mods in fixtures_of.items()}


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(session, config, items):
    """Heaviest files first (files stay contiguous, tests keep their order within a file) and, with
    ``--dist loadgroup``, the tests sharing a module-scoped fixture grouped on one worker."""
    rank = {name: k for k, name in enumerate(HEAVY_FIRST)}
    order = {item: k for k, item in enumerate(items)}
    first_of_file: dict = {}
    for item in items:
        first_of_file.setdefault(item.path.name, order[item])
    items.sort(key=lambda it: (rank.get(it.path.name, len(rank)), first_of_file[it.path.name], order[it]))
    # (on the xdist workers "dist" is "no" and "loadgroup" is set: the controller passes the scheduling on)
    if config.getoption("dist", "no") == "loadgroup" or config.getoption("loadgroup", False):
        for item, group in _module_fixture_groups(items).items():
            item.add_marker(pytest.mark.xdist_group(group))
            # xdist's worker gives the scheduler a test's group as a suffix of its node id ("<id>@<group>"), but
            # pytest-xdist 3.8 sets ``item._nodeid``, which pytest 9 no longer reads (the id is ``item._id``): the
            # suffix is set here the way pytest 9 keeps it
            if "@" not in item.nodeid.rsplit("]", 1)[-1]:
                from _pytest.nodeid import coerce_node_id

                item._id = coerce_node_id(f"{item.nodeid}@{group}")
