"""A compiled kernel is what its code says: keys from the code itself (avflow.codekey), a
user's function tried before anything compiles (avflow.numerics.trial), and each copy named
after the registrations it reads (avflow.numerics.variants).

The stale cases each ran the old machine code before: a helper's constant, a helper's body,
a law's parameter default, a built-in source file edited in a checkout.
"""

from __future__ import annotations

import importlib.util
import math
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from avflow import codekey

ROOT = Path(__file__).resolve().parents[1]


def _module(tmp_path, name: str, text: str):
    """A user's module written to ``tmp_path`` and imported (its functions are a user's)."""
    path = tmp_path / f"{name}.py"
    path.write_text(textwrap.dedent(text))
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


HELPERS = """
from numba import njit
FACTOR = 1.0

@njit
def scaled(x):
    return FACTOR * x

def plain(x):
    return 2.0 * x

def law(mu, h, speed, normal_accel, g, k=0.5):
    return (mu + k * 0.0) * scaled(h) * plain(normal_accel), 0.0
"""


def test_a_helpers_constant_is_in_the_key(tmp_path):
    """The issue's stale kernel: an @njit helper reading a module constant."""
    m = _module(tmp_path, "helpers_a", HELPERS)
    first = codekey.code_key(m.law)
    m.FACTOR = 2.0
    codekey.forget()
    assert codekey.code_key(m.law) != first
    m.FACTOR = 1.0
    codekey.forget()
    assert codekey.code_key(m.law) == first  # the value, not the moment


def test_a_helpers_body_and_a_default_are_in_the_key(tmp_path):
    base = codekey.code_key(_module(tmp_path, "h0", HELPERS).law)
    body = _module(tmp_path, "h1", HELPERS.replace("return 2.0 * x", "return 3.0 * x"))
    default = _module(tmp_path, "h2", HELPERS.replace("k=0.5", "k=0.7"))
    compiled = _module(tmp_path, "h3", HELPERS.replace("return FACTOR * x", "return x * FACTOR + 0.0"))
    keys = {codekey.code_key(m.law) for m in (body, default, compiled)}
    assert base not in keys and len(keys) == 3


def test_arrays_and_tuples_by_their_bytes_and_options_count(tmp_path):
    text = """
    import numpy as np
    from numba import njit
    TABLE = np.array([1.0, 2.0])
    PAIR = (1, 2.5)
    def f(x):
        return TABLE[0] * x + PAIR[1]
    """
    m = _module(tmp_path, "arrays", text)
    first = codekey.code_key(m.f)
    m.TABLE[1] = 3.0
    codekey.forget()
    assert codekey.code_key(m.f) != first
    m.PAIR = (1, 2.5000001)
    codekey.forget()
    assert codekey.code_key(m.f) != codekey.code_key(_module(tmp_path, "arrays2", text).f)
    from numba import njit

    assert codekey.code_key(njit(m.f)) != codekey.code_key(njit(fastmath=True)(m.f))


def test_a_kernels_own_options_are_in_its_cache_key():
    """The same kernel under other options of its own decorator (``_nrt``, ``fastmath``)
    has another key in the kernel cache: Numba keys by the code alone, and a step_faces
    made without reference counts loaded the machine code that counted them (twice as
    slow) until its options were added."""
    from numba import njit

    from avflow.numerics import kernels

    keys = []
    for options in ({}, {"_nrt": False}, {"fastmath": True}):
        d = njit(error_model="numpy", cache=True, **options)(kernels.dt_limit.py_func)
        assert type(d._cache._impl.locator).__name__ == "SharedLocator"
        keys.append(d._cache._index_key(("float64",), d.targetctx.codegen()))
    assert len(set(keys)) == 3
    assert len({k[:-1] for k in keys}) == 1  # what Numba's own key holds: the same


def test_a_global_with_no_value_to_hash_is_refused_naming_file_line_and_name(tmp_path):
    m = _module(tmp_path, "unhashable", """
    TABLE = {"a": 1.0}
    def f(x):
        return x * TABLE["a"]
    """)
    with pytest.raises(codekey.UnhashableGlobal) as err:
        codekey.code_key(m.f, strict=True)
    assert str(err.value).startswith(f"{tmp_path / 'unhashable.py'}:4: f reads 'TABLE', a dict")
    codekey.code_key(m.f)  # avflow's own count by their type: no refusal there


def _key_in(package_root: Path, cache: Path) -> str:
    code = ("import avflow.codekey as k; from avflow.numerics import square_grid, rheology; "
            "print(k.code_key(square_grid.grid_loop(rheology.COULOMB, False, 2)))")
    env = {**os.environ, "PYTHONPATH": str(package_root), "AVFLOW_CACHE_DIR": str(cache)}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, cwd=package_root, timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_a_kernel_source_edited_in_a_checkout_is_a_new_key_and_nothing_else_is(tmp_path):
    """The key of the order-2 grid loop, in fresh processes: the same twice (no address or
    set order in it), another after an edit of a function it calls in another file
    (kinetic.py's half fluxes), the same after an edit of a file it does not call."""
    copy = tmp_path / "checkout"
    shutil.copytree(ROOT / "avflow", copy / "avflow", ignore=shutil.ignore_patterns("__pycache__"))
    cache = tmp_path / "cache"
    first = _key_in(copy, cache)
    assert _key_in(copy, cache) == first
    cf = copy / "avflow" / "output" / "cf.py"
    cf.write_text(cf.read_text() + "\nUNRELATED = 1\n")
    assert _key_in(copy, cache) == first
    kinetic = copy / "avflow" / "numerics" / "kinetic.py"
    text = kinetic.read_text()
    assert "SQRT3 = math.sqrt(3.0)" in text
    kinetic.write_text(text.replace("SQRT3 = math.sqrt(3.0)", "SQRT3 = math.sqrt(3.0000001)"))
    assert _key_in(copy, cache) != first


def test_every_kernel_of_the_package_is_keyed_by_its_code():
    """Numba's key of a cached avflow kernel carries the code key (of the compiled
    function: its code and its options); another package's does not (Numba's own key, as
    Numba makes it)."""
    from numba import njit

    from avflow.numerics import cpu, square_grid, rheology

    loop = square_grid.grid_loop(rheology.COULOMB, False, 1)
    for dispatcher in (loop, cpu.face_flux):
        key = dispatcher._cache._index_key((), _Codegen())
        assert key[-1] == codekey.code_key(dispatcher), dispatcher
    assert loop._cache._impl.locator.get_source_stamp() == "avflow keyed by code"


class _Codegen:
    def magic_tuple(self):
        return ("target", "cpu", "features")


# --- a user's registrations, tried before anything compiles --------------------------------------

PLANE = """
name: keys-plane
terrain: {kind: plane, slope_deg: 30.0, azimuth_deg: 90.0,
          extent: {x: [0.0, 400.0], y: [0.0, 240.0]}}
rheology: {LAW}
grid: {dx: 20.0}
release: {kind: cylinder, center: [100.0, 120.0], radius: 50.0, thickness: 8.0}
time: {end: 12.0, cfl: 0.5}
output: {every: 6.0}
"""

LAWS = {
    "pair": ("return mu * h * normal_accel",
             "returns float, not the pair (tau, drag)"),
    "negative": ("return -mu * h * normal_accel, 0.0",
                 "returns tau = -0.00289292 < 0 (tried with mu=0.36, h=0.001, speed=0"),
    "raises": ("return mu * h * normal_accel, 1.0 / speed",
               "raised ZeroDivisionError: float division by zero (tried with mu=0.36, h=0.001, "
               "speed=0"),
    "nan": ("return mu * h * normal_accel, math.sqrt(-1.0) if speed > 1.0 else 0.0",
            "raised ValueError: math domain error (tried with mu=0.36, h=0.001, speed=5"),
    "uncompilable": ("return mu * h * normal_accel * len({1: 2}), 0.0",
                     "cannot be compiled"),
    "unhashable": ("return mu * h * normal_accel * TABLE['a'], 0.0",
                   "reads 'TABLE', a dict"),
}


def _cli(folder: Path, *args):
    env = {k: v for k, v in os.environ.items() if k != "AVFLOW_EXTENSIONS"}
    return subprocess.run([sys.executable, "-m", "avflow", *args], cwd=folder, env=env,
                          capture_output=True, text=True, timeout=600)


@pytest.mark.parametrize("case", sorted(LAWS))
def test_a_law_of_the_wrong_shape_is_one_line_naming_its_file_before_compiling(tmp_path, case):
    body, says = LAWS[case]
    (tmp_path / "law.py").write_text(
        "import math\nfrom avflow import extend\nTABLE = {'a': 1.0}\n\n"
        f"@extend.friction_law('trial_{case}', parameters=('mu',), reference='a test')\n"
        f"def trial_{case}(mu, h, speed, normal_accel, g):\n    {body}\n")
    (tmp_path / "s.yaml").write_text(PLANE.replace("LAW", f"law: trial_{case}, mu: 0.36"))
    done = _cli(tmp_path, "run", "--extensions", "law.py", "s.yaml", "-o", "out.nc")
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    assert lines[0].startswith(f"avflow: error: {tmp_path / 'law.py'}:"), lines[0]
    assert says in lines[0], lines[0]
    assert not (tmp_path / "out.nc").exists()


MAP = """
from numba import njit
from avflow import extend
FACTOR = 1.0

@njit
def scaled(x):
    return FACTOR * x

def plain(x):          # not decorated: compiled with the map
    return 1.0 * x

@extend.output_map("scaled_peak", units="m", long_name="scaled peak thickness")
def scaled_peak(old, h, hu, hv, speed, t):
    v = scaled(plain(h))
    return v if v > old else old
"""


def test_no_stale_map_after_a_helpers_constant_or_body_changes(tmp_path):
    """The issue's case end to end, with the same kernel cache: FACTOR 1 -> 2 doubles the
    map (it stayed the same: the old machine code), a helper's body x -> 3x triples it; an
    undecorated helper compiles with the map."""
    import xarray as xr

    (tmp_path / "s.yaml").write_text(PLANE.replace("LAW", "law: coulomb, delta_deg: 20.0"))
    peaks = []
    for k, text in enumerate((MAP, MAP.replace("FACTOR = 1.0", "FACTOR = 2.0"),
                              MAP.replace("return 1.0 * x", "return 3.0 * x"))):
        (tmp_path / "map.py").write_text(text)
        done = _cli(tmp_path, "run", "--extensions", "map.py", "s.yaml", "-o", f"{k}.nc", "-q")
        assert done.returncode == 0, done.stderr
        with xr.open_dataset(tmp_path / f"{k}.nc") as ds:
            peaks.append((float(ds["scaled_peak"].max()), float(ds["peak_thickness"].max())))
    (one, h), (two, _), (three, _) = peaks
    assert one == pytest.approx(h, rel=1e-12) and one > 0.0
    assert two == pytest.approx(2.0 * one, rel=1e-12)  # x2 commutes with float32 rounding
    # the file holds float32: float32(3 v) and 3 float32(v) differ by up to 2 half-ulps
    assert three == pytest.approx(3.0 * one, rel=2.5e-7) and three != pytest.approx(one)


# --- the kernels' side of a user's law ------------------------------------------------------------

def test_a_registered_laws_negative_friction_counts_as_zero_and_nan_stays():
    """Friction never pushes (the guide's promise), where the trial did not look either; a
    NaN is not hidden as 0 (the run then fails, naming the law: test below)."""
    from types import SimpleNamespace as NS

    from numba import njit

    from avflow.numerics import variants

    def pushy(a, h, speed, normal_accel, g):
        return a * h, a * speed

    law = NS(code=7, parameters=("a",), function=pushy)

    @njit
    def built_in(law, p0, p1, p2, p3, p4, p5, p6, p7, h, speed, normal_accel, g):
        return 9.0, 9.0

    friction = variants.law_friction_with([law], built_in, njit)
    assert friction(7, -1.0, 0, 0, 0, 0, 0, 0, 0, 2.0, 3.0, 9.0, 9.81) == (0.0, 0.0)
    assert friction(7, 1.0, 0, 0, 0, 0, 0, 0, 0, 2.0, 3.0, 9.0, 9.81) == (2.0, 3.0)
    tau, drag = friction(7, math.nan, 0, 0, 0, 0, 0, 0, 0, 2.0, 3.0, 9.0, 9.81)
    assert math.isnan(tau) and math.isnan(drag)
    assert friction(3, 1.0, 0, 0, 0, 0, 0, 0, 0, 2.0, 3.0, 9.0, 9.81) == (9.0, 9.0)


def test_after_a_non_finite_state_the_law_that_returns_nan_is_named():
    from types import SimpleNamespace as NS

    from avflow.numerics import trial

    def steep(mu, h, speed, normal_accel, g):
        return mu * h * normal_accel, (math.nan if speed > 100.0 else 0.0)

    law = NS(name="steep", parameters=("mu",), function=steep)
    found = trial.suspect([law], (), np.array([0.3, 0, 0, 0, 0, 0, 0, 0]))
    assert found.startswith("the friction law 'steep' (") and "test_kernel_keys.py:" in found
    assert "tau, drag = " in found and "nan" in found
    assert trial.suspect([NS(name="fine", parameters=("mu",),
                             function=lambda mu, h, s, n, g: (mu * h * n, 0.0))], (),
                         np.zeros(8)) is None


# --- each copy named after the registrations it reads ---------------------------------------------

def _copies(root) -> dict:
    """qualname -> dispatcher of every avflow function below ``root`` (itself included)."""
    from avflow.numerics.variants import _ours

    seen, todo = {}, [root]
    while todo:
        d = todo.pop()
        if d.py_func.__qualname__ in seen:
            continue
        seen[d.py_func.__qualname__] = d
        todo.extend(v for name in d.py_func.__code__.co_names
                    if _ours(v := d.py_func.__globals__.get(name)))
    return seen


def test_a_laws_copies_keep_their_names_when_a_map_is_registered_beside_it():
    """A map beside a law renamed the law's sweeps, and a cached law compiled again (21 s):
    the copies that read only the law are the same with and without the map, the ones that
    read the map are new."""
    from avflow.numerics import rheology, square_grid, variants

    loop = square_grid.grid_loop(-1, False, 1)  # the loop that reads the law at run time

    @njit_inline
    def law(law, p0, p1, p2, p3, p4, p5, p6, p7, h, speed, normal_accel, g):
        return 0.0, 0.0

    @njit_inline
    def maps(maps, i, h, hu, hv, speed, t_new):
        return None

    alone = _copies(variants.variant(loop, {"law_friction": "L1"}, law_friction=law))
    both = _copies(variants.variant(loop, {"law_friction": "L1", "more_maps": "M1"},
                                    law_friction=law, more_maps=maps))
    other = _copies(variants.variant(loop, {"law_friction": "L1", "more_maps": "M2"},
                                     law_friction=law, more_maps=maps))
    law_copies = {n for n in alone if n not in _copies(loop)}
    kept = law_copies & set(both) & set(other)  # the sweeps, the stage: the law's alone
    assert any(n.startswith("_stage_") for n in kept), kept
    assert any(n.startswith("_final_cells") for n in kept), kept
    assert not any(n.startswith("advance") for n in kept)  # the root reads both
    map_copies = set(both) - set(alone)
    assert map_copies and not map_copies & set(other)  # another map: new names
    assert rheology.law_friction is not law


def njit_inline(fn):
    from numba import njit

    return njit(inline="always")(fn)
