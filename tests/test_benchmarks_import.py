"""The benchmark scripts (run by hand, not installed) still match the package's API.

They are not imported here (some set thread variables at import); instead each project import
they make is resolved: a renamed or removed name fails this fast test, not a benchmark run.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

BENCHMARKS = sorted((Path(__file__).resolve().parents[1] / "benchmarks").glob("*.py"))
PROJECT = ("uavtrack_env", "baselines", "train")


def _project_imports(path: Path) -> list[tuple[str, str | None]]:
    """(module, name) for every ``from project... import name`` / ``import project...``."""
    out: list[tuple[str, str | None]] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.split(".")[0] in PROJECT:
                out += [(node.module, alias.name) for alias in node.names]
        elif isinstance(node, ast.Import):
            out += [(a.name, None) for a in node.names if a.name.split(".")[0] in PROJECT]
    return out


def test_there_are_benchmarks():
    assert len(BENCHMARKS) >= 5


@pytest.mark.parametrize("path", BENCHMARKS, ids=lambda p: p.stem)
def test_benchmark_compiles_and_its_project_imports_resolve(path: Path):
    compile(path.read_text(), str(path), "exec")
    imports = _project_imports(path)
    for module, name in imports:
        mod = importlib.import_module(module)
        if name is not None and not hasattr(mod, name):
            importlib.import_module(f"{module}.{name}")  # a submodule; raises if missing
