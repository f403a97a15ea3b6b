"""The package's import graph: batch and study import alone and not each other, and no
module of palpsim reaches itself through its imports (issue 27: no import cycle)."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

# the checkout's package folder, and the folder a fresh interpreter must import it from
PACKAGE = Path(__file__).resolve().parents[1] / "palpsim"
MODULES = sorted(p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__")


def palpsim_imports(module: str) -> set[str]:
    """The palpsim modules that `module` imports anywhere in its text (top level or inside a
    function), read from its import statements."""
    tree = ast.parse((PACKAGE / f"{module}.py").read_text(), filename=f"{module}.py")
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            names = [node.module or ""]
        elif isinstance(node, ast.ImportFrom) and node.level == 1:
            # `from .x import y` names module x; `from . import x, y` names modules x and y
            names = [f"palpsim.{node.module}"] if node.module else \
                [f"palpsim.{a.name}" for a in node.names]
        else:
            continue
        for name in names:
            parts = name.split(".")
            if parts[0] == "palpsim" and len(parts) > 1 and parts[1] in MODULES:
                found.add(parts[1])
    return found


@pytest.mark.parametrize("module", ["batch", "study"])
def test_imports_alone_in_a_fresh_interpreter(module):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(PACKAGE.parent)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])}
    r = subprocess.run([sys.executable, "-c", f"import palpsim.{module} as m; print(m.__file__)"],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    # the module came from this checkout, not from another installed palpsim
    assert Path(r.stdout.strip()).resolve() == PACKAGE / f"{module}.py"


def test_batch_and_study_do_not_import_each_other():
    assert "study" not in palpsim_imports("batch") or "batch" not in palpsim_imports("study"), \
        "palpsim.batch and palpsim.study import each other"


def test_no_import_cycle_in_the_package():
    graph = {m: palpsim_imports(m) for m in MODULES}
    # depth-first walk; a module met again while still on the path closes a cycle
    state: dict[str, int] = {}  # 1 on the path, 2 done
    path: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        path.append(m)
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                cycle = path[path.index(d):] + [d]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if d not in state:
                visit(d)
        path.pop()
        state[m] = 2

    for m in MODULES:
        if m not in state:
            visit(m)
