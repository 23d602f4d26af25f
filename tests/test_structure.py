"""The shape of the code (issue 27): imports run one way, down the stages, with no circle;
there is no import circle."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "avflow"
#: the stages, top to bottom: a module may import its own stage and those below it
STAGES = ["calibration", "ensemble", "output", "simulation", "numerics", "terrain", "scenario"]
BASE = {"avflow.errors", "avflow.files", "avflow"}  # below every stage


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        yield name, path


def _imports(name, path):
    """The avflow modules ``name`` imports, anywhere in its file (a function's import too)."""
    known = {n for n, _ in _modules()}
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.startswith("avflow"):
                for alias in node.names:
                    full = f"{node.module}.{alias.name}"
                    out.add(full if full in known else node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("avflow"))
    # a package imported by its own submodules is how Python loads them, not a dependency
    return {m for m in out if m != name and not name.startswith(m + ".")}


GRAPH = {name: _imports(name, path) for name, path in _modules()}


def _cycles(graph):
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_no_import_circle_in_avflow():
    assert _cycles(GRAPH) == []


def _stage(module):
    parts = module.split(".")
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in STAGES) else None


@pytest.mark.parametrize("stage", STAGES)
def test_a_stage_imports_only_itself_and_the_stages_below(stage):
    allowed = set(STAGES[STAGES.index(stage):])
    wrong = sorted(f"{m} imports {d}" for m, deps in GRAPH.items() if _stage(m) == stage
                   for d in deps if d not in BASE and _stage(d) not in allowed)
    assert wrong == []
