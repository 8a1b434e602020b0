"""The fuzz harnesses (fuzz/fuzz_targets.py) run on their generated seeds without atheris: every target
ACCEPTS its unmodified seeds (parsed without any error, into something non-empty), and on mutated seeds its
one-input function lets only the project's own exceptions through."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "fuzz"))
import fuzz_targets as ft  # noqa: E402


@pytest.mark.parametrize("target", ft.TARGETS)
def test_harness_accepts_seeds_and_refuses_mutations_cleanly(target):
    parse = ft.make_target(target)  # no exception swallowed: a valid seed refused is a failure here
    one = ft.one_input_factory(target)  # swallows only ThermogrammetryError (a clean refusal)
    seeds = ft.seeds(target)
    assert seeds
    for k, s in enumerate(seeds):
        parsed = parse(s)  # a seed is a small VALID file: it must be read, not refused
        assert parsed is not None, f"{target} seed {k}: parsed to nothing"
        if hasattr(parsed, "__len__"):
            assert len(parsed) > 0, f"{target} seed {k}: parsed to an empty {type(parsed).__name__}"
        for cut in (0, 1, len(s) // 2, len(s) - 1):  # truncations: refused cleanly, never another exception
            one(s[:cut])
        one(bytes(b ^ 0x5A for b in s[:64]) + s[64:])
