"""The fuzz harnesses (fuzz/fuzz_targets.py) run on their generated seeds without atheris: every target
accepts its seeds and its one-input function lets only the project's own exceptions through."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "fuzz"))
import fuzz_targets as ft  # noqa: E402


@pytest.mark.parametrize("target", ft.TARGETS)
def test_harness_runs_on_seeds_and_mutations(target):
    one = ft.one_input_factory(target)
    for s in ft.seeds(target):
        one(s)
        for cut in (0, 1, len(s) // 2, len(s) - 1):  # truncations: refused cleanly, never another exception
            one(s[:cut])
        one(bytes(b ^ 0x5A for b in s[:64]) + s[64:])
