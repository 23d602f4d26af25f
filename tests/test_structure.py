"""The shape of the code (issue 27): imports run one way, down the stages, with no circle;
there is no import circle."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "avflow"
#: the stages, top to bottom: a module may import its own stage and those below it
STAGES = ["calibration", "ensemble", "output", "simulation", "numerics", "terrain", "scenario"]
BASE = {"avflow.errors", "avflow.files", "avflow.codekey", "avflow"}  # below every stage


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


# --- the physics written once ------------------------------------------------------------------

NUMERICS = PACKAGE / "numerics"
#: the running maps: written by the observer pass alone (the GPU's copy: cuda_grid._observe)
MAPS = {"peak_h", "peak_speed", "arrival", "last_moved"}


def _functions(path):
    """``(function name, node)`` of every function of a module, nested ones included."""
    tree = ast.parse(path.read_text())
    return [(n.name, n) for n in ast.walk(tree)
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]


def _names(node) -> set:
    return {n.id if isinstance(n, ast.Name) else n.attr for n in ast.walk(node)
            if isinstance(n, (ast.Name, ast.Attribute))}


def _where(predicate) -> list:
    """``module.function`` of the numerics' functions whose body holds a node matching
    ``predicate`` (in that function itself, not in a function nested in it)."""
    found = []
    for path in sorted(NUMERICS.glob("*.py")):
        for name, fn in _functions(path):
            inner = {id(n) for sub in ast.walk(fn) if sub is not fn
                     and isinstance(sub, (ast.FunctionDef, ast.AsyncFunctionDef))
                     for n in ast.walk(sub)}
            if any(predicate(n) for n in ast.walk(fn) if id(n) not in inner):
                found.append(f"{path.stem}.{name}")
    return sorted(set(found))


def test_the_dirac_rule_is_written_once():
    """A face carries the Dirac (zero) flux when both its sides are at zero temperature
    (eqs. 51-53): one expression, physics.dirac_face; every traversal calls it."""
    def rule(n):
        return (isinstance(n, (ast.BoolOp, ast.BinOp)) and "dirac" in _names(n)
                and "FLOWING" in _names(n))

    assert _where(rule) == ["physics.dirac_face"]
    callers = _where(lambda n: isinstance(n, ast.Call) and "dirac_face" in _names(n.func))
    assert len(callers) >= 6, callers  # profile, faces (3 forms), grid, GPU


def test_the_take_back_is_written_once():
    """A dry cell takes no momentum through a Dirac face (eq. 53): what the face brought to
    its trial's sum is taken back, physics.take_back, the one place that negates what a face
    brought under the Dirac test; every 2D traversal calls it (the grid's rows, the GPU, the
    face sweep's two forms, step_faces, the gather form). A profile has no take-back: its
    dry cell sums anew its two faces that are not Dirac."""
    def rule(n):
        return (isinstance(n, ast.IfExp) and isinstance(n.body, ast.UnaryOp)
                and isinstance(n.body.op, ast.USub) and isinstance(n.orelse, ast.Constant)
                and n.orelse.value == 0.0)

    assert _where(rule) == ["physics.take_back"]
    assert _callers("take_back") == [
        "cuda_grid._final", "face_gather._gather_mass", "face_sweep._add_masses",
        "face_sweep._cold_masses", "kernels._face_mass", "square_grid._final_cells"]


def test_the_outflow_is_written_once():
    """What leaves through an open side in a step, ``max(L F_h, 0) dt`` (nothing through a
    Dirac face): physics.outflow_volume, the one place that multiplies an outward flux by the
    step; every traversal calls it (the grid's rows, the GPU, the face sweep's three sums,
    step_faces, the gather form, both profiles)."""
    def rule(n):
        if not (isinstance(n, ast.BinOp) and isinstance(n.op, ast.Mult)):
            return False
        sides = (n.left, n.right)
        return (any(isinstance(s, ast.Name) and s.id == "dt" for s in sides)
                and any((isinstance(s, ast.Call) and "max" in _names(s.func))
                        or (isinstance(s, ast.UnaryOp) and isinstance(s.op, ast.USub))
                        for s in sides))

    assert _where(rule) == ["physics.outflow_volume"]
    assert _callers("outflow_volume") == [
        "cuda_grid._final", "face_gather.step_cells", "face_sweep._add_masses",
        "face_sweep._face_fluxes", "face_sweep._open_outflow", "kernels._face_mass",
        "kernels.step_profile", "profile._step", "square_grid._final_cells"]


def test_the_moving_rule_is_written_once():
    """A cell moves material when u != 0 and it just set off or a face carried its mass
    above TRANSPORT_EPS h |u^n| (what the stop rules count): physics.carries and
    physics.cell_moves; no traversal compares with TRANSPORT_EPS itself."""
    uses = _where(lambda n: isinstance(n, ast.Name) and n.id == "TRANSPORT_EPS")
    assert uses == ["physics.carries"]
    callers = _where(lambda n: isinstance(n, ast.Call) and "cell_moves" in _names(n.func))
    assert len(callers) >= 7, callers


def test_the_running_maps_are_written_by_the_observer_pass_alone():
    """peak thickness and speed, arrival and last motion: written once per accepted step by
    the observer pass (observers.observe_cell_at; the GPU's copy, cuda_grid._observe), from
    the rule physics.observe, never by a step that may be redone."""
    def writes_a_map(n):
        targets = n.targets if isinstance(n, ast.Assign) else (
            [n.target] if isinstance(n, ast.AugAssign) else [])
        for t in targets:
            for e in (t.elts if isinstance(t, ast.Tuple) else [t]):
                if isinstance(e, ast.Subscript) and _names(e.value) & MAPS:
                    return True
        return False

    assert _where(writes_a_map) == ["cuda_grid._observe", "observers.observe_cell_at"]
    callers = _where(lambda n: isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
                     and n.func.id == "observe")
    assert callers == ["cuda_grid._observe", "observers.observe_cell_at"]


def test_the_friction_laws_are_chosen_in_one_place():
    """A law's branch (``law == COULOMB`` ...) only in rheology.law_friction: the kernels
    call friction() and never test a law themselves (a registered law joins that chain,
    numerics.variants)."""
    laws = {"COULOMB", "POULIQUEN", "VOELLMY", "SAMOSAT", "VELOCITY_WEAKENING"}

    def branch(n):
        return (isinstance(n, ast.Compare) and any(isinstance(o, ast.Eq) for o in n.ops)
                and _names(n) & laws)

    assert _where(branch) == ["rheology.law_friction"]


def test_the_time_loop_is_written_once():
    """Step size, retry by halving, the sources, the stop rules: loop.advance, for every
    kernel and backend (the GPU's runs it as Python); nothing else halves a step."""
    halves = _where(lambda n: isinstance(n, ast.AugAssign) and isinstance(n.op, ast.Mult)
                    and isinstance(n.value, ast.Constant) and n.value.value == 0.5)
    assert halves == ["loop.advance"]
    steps = _where(lambda n: isinstance(n, ast.Call) and "step_size" in _names(n.func))
    assert steps == ["loop.advance"]


def _callers(name):
    return _where(lambda n: isinstance(n, ast.Call) and name in _names(n.func))


def test_the_face_flux_is_written_once():
    """The flux through a face with the ghost of a wall or an open side (eq. 38, the kinetic
    half fluxes of eqs. 39-40): physics.face_flux, called by every traversal of a 2D mesh
    (the grid's rows and the GPU's through square_grid._coded_flux, the face sweep, the
    gather form and step_faces through kernels.listed_flux). The half fluxes are called by it alone; their branch-free
    form (the same bits, for the loops that vectorise: ``cpu.vector_face_flux``, the face
    flux compiled with it) also by the profile's per-cell pass: on a line each cell's two
    half fluxes are computed once and summed per face, and the profile's two ends apply the
    same open rule (physics.open_mass)."""
    assert _callers("face_flux") == ["face_sweep._face_flux", "kernels.listed_flux",
                                     "square_grid._coded_flux"]
    assert _callers("listed_flux") == ["face_gather._gather_fluxes", "kernels._face_fluxes"]
    for half in ("half_flux_out", "half_flux_in"):
        assert _callers(half) == ["physics.face_flux"], half
    for half in ("select_flux_out", "select_flux_in"):
        assert _callers(half) == ["profile._emit"], half
    assert _callers("open_mass") == ["kernels._profile_fluxes2", "kernels.step_profile",
                                     "physics.face_flux", "profile._ends"]
    assert _callers("coded_flux") == ["cuda_grid._faces"]


def test_the_cell_update_is_written_once():
    """A cell's new thickness ``h^n + dt / A sum``, the q~ of a cell dry at time n and the
    projection of eq. 50: physics.cell_update, called by every traversal (profile, its
    reference, the grid's rows, the face sweep, step_faces, the gather form, the GPU);
    nothing else calls the projection."""
    assert _callers("final_momentum") == ["physics.cell_update"]
    assert _callers("cell_update") == [
        "cuda_grid._final", "face_gather._gather_finals", "face_sweep._final_cells",
        "kernels._face_finals", "kernels.step_profile", "profile._final",
        "square_grid._final_cells"]
