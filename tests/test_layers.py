"""The layer order of the package (``docs/architecture.md``): a module never imports one of a higher layer.

Every import of a ``thermogrammetry`` module is checked, at module level and inside functions alike (an import
inside a function is a dependency all the same; it only runs later). The one exception is the body of a
module-level ``__getattr__``: that is how a module that lost names to a higher layer keeps their old import
path working (``dense.workflow.run_dense`` is now ``pipeline.dense.run_dense``), and it is checked here that such a
function only re-exports names.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "thermogrammetry"

#: bottom to top; a module belongs to the layer of the longest prefix that names it
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("foundation", ("errors", "results", "enums", "_validate", "_atomic", "_libc", "_memory", "_procs", "_interrupt", "_sampling",
                    "reporting", "store", "tasks")),
    ("camera models, rotations, radiometry", ("camera", "geometry.rotations", "geometry.pose", "geometry._camera",
                                              "geometry._common", "geometry.attitude", "radiometry")),
    ("adjustment engine", ("adjustment",)),
    ("geometry on the engine (DLT, resection, triangulation, Helmert, planes)", ("geometry",)),
    ("io", ("io",)),
    ("calibration targets", ("targets",)),
    ("synthetic scenes", ("synthetic",)),
    ("calibration", ("calibration",)),
    ("sfm", ("sfm",)),
    ("dense", ("dense",)),
    ("products", ("products",)),
    ("closerange", ("closerange",)),
    ("pipeline (one driver per verb)", ("pipeline",)),
    ("cli", ("cli",)),
    ("package entry points", ("__main__", "__init__")),
]


def _layer(module: str) -> int:
    best, best_len = None, -1
    for k, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best_len:
                best, best_len = k, len(p)
    if best is None:
        raise AssertionError(f"module thermogrammetry.{module} is in no layer of tests/test_layers.py: add it")
    return best


def _module_name(path: Path) -> str:
    rel = path.relative_to(SRC).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__" and len(parts) > 1:
        parts = parts[:-1]
    return ".".join(parts)


def _is_module(dotted: str) -> bool:
    p = SRC.joinpath(*dotted.split("."))
    return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()


def _imports(path: Path):
    """(line, imported module, inside a module-level __getattr__) of every thermogrammetry import in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = list(path.relative_to(SRC).parent.parts)
    shim_nodes = set()
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and node.name == "__getattr__":
            shim_nodes.update(id(n) for n in ast.walk(node))
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level == 0:
                if not (node.module or "").startswith("thermogrammetry"):
                    continue
                base = node.module.split(".")[1:]
            else:
                base = package[: len(package) - (node.level - 1)] + (node.module.split(".") if node.module else [])
            for a in node.names:
                target = ".".join(base + [a.name]) if _is_module(".".join(base + [a.name])) else ".".join(base)
                if target:
                    yield node.lineno, target, id(node) in shim_nodes
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("thermogrammetry."):
                    yield node.lineno, a.name.split(".", 1)[1], id(node) in shim_nodes
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "import_module" and node.args \
                and isinstance(node.args[0], ast.Constant) and str(node.args[0].value).startswith("thermogrammetry."):
            yield node.lineno, node.args[0].value.split(".", 1)[1], id(node) in shim_nodes


def _all_modules():
    return sorted(p for p in SRC.rglob("*.py"))


def test_every_module_has_a_layer():
    for p in _all_modules():
        _layer(_module_name(p))


def test_no_module_imports_a_higher_layer():
    bad = []
    for p in _all_modules():
        me = _module_name(p)
        mine = _layer(me)
        for line, target, shim in _imports(p):
            if shim or target in ("", "__version__"):
                continue
            theirs = _layer(target)
            if theirs > mine:
                bad.append(f"{p.relative_to(SRC.parent)}:{line}: {me} ({LAYERS[mine][0]}) imports {target} "
                           f"({LAYERS[theirs][0]})")
    assert not bad, "imports from a higher layer:\n" + "\n".join(bad)


def test_the_checker_sees_function_level_imports(tmp_path, monkeypatch):
    """A planted upward import inside a function is found (the test can fail)."""
    pkg = tmp_path / "thermogrammetry"
    (pkg / "io").mkdir(parents=True)
    (pkg / "pipeline").mkdir()
    (pkg / "pipeline" / "__init__.py").write_text("")
    (pkg / "io" / "__init__.py").write_text("")
    (pkg / "io" / "bad.py").write_text("def f():\n    from ..pipeline import run\n    return run\n")
    monkeypatch.setattr(__import__(__name__), "SRC", pkg)
    with pytest.raises(AssertionError, match=r"io\.bad \(io\) imports pipeline"):
        test_no_module_imports_a_higher_layer()


def test_compatibility_getattr_only_reexports():
    """A module-level ``__getattr__`` that imports from a higher layer does nothing but look the name up there."""
    for p in _all_modules():
        tree = ast.parse(p.read_text(encoding="utf-8"))
        for node in tree.body:
            if isinstance(node, ast.FunctionDef) and node.name == "__getattr__":
                calls = {getattr(n.func, "attr", getattr(n.func, "id", "")) for n in ast.walk(node) if isinstance(n, ast.Call)}
                assert calls <= {"getattr", "import_module", "get", "AttributeError"}, (p, calls)


def test_modules_stay_small():
    """No module past 800 lines, the survey's steps (``pipeline/survey/``) at most 450: a module that grows past that
    is split along its seams (docs/architecture.md)."""
    too_long = []
    for p in _all_modules():
        n = len(p.read_text(encoding="utf-8").splitlines())
        limit = 450 if p.parent.name == "survey" and p.parent.parent.name == "pipeline" else 800
        if n > limit:
            too_long.append(f"{p.relative_to(SRC.parent)}: {n} lines > {limit}")
    assert not too_long, "\n".join(too_long)
