"""Shared test fixtures.

Real data lives in ``../shared/data`` beside the repository (see its INDEX.md);
tests that need it use the ``shared_data`` fixture and skip, with a clear reason,
when it is absent. Set ``THERMOGRAMMETRY_DATA`` to point elsewhere.

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


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Root of the shared real-data folder; skips the test when it is missing."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (set THERMOGRAMMETRY_DATA)")
    return SHARED_DATA


def data_path(*parts: str) -> Path:
    """Path under the shared data folder; skips the calling test when it does not exist."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real data file {p} is absent")
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
