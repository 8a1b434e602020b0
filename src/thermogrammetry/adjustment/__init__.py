"""The least-squares adjustment engine (placeholder docstring, replaced below)."""

from __future__ import annotations

_LAZY = {
    "solve_bal": ".bal",
    "BALResult": ".bal",
    "BALSolverOptions": ".bal",
    "bal_cost": ".bal",
}


def __getattr__(name):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'thermogrammetry.adjustment' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(mod, __name__), name)
