"""Numba's cache of the kernels: one folder per user and version, shared by every checkout
(what each kernel is compiled from is in its key: tests/test_kernel_keys.py)."""

import os
from pathlib import Path

import pytest

import avflow.numerics as numerics
from avflow.numerics import (cpu, face_sweep, kernels, reconstruction, rheology, sources,
                             square_grid, timeloop)


#: the hooks of a kernel's region in its copies of the one time loop (numerics/loop.py)
HOOKS = ("start", "before", "step", "source", "observe", "after", "end")


def _hook(loop, name):
    return loop.py_func.__globals__[f"region_{name}"]


def test_every_cached_kernel_uses_the_versioned_folder_and_nothing_else_does():
    from numba.core import config

    if os.environ.get("NUMBA_CACHE_DIR"):
        pytest.skip("NUMBA_CACHE_DIR is set: the kernels use the user's folder")
    folder = numerics.kernel_cache_dir()
    loops = [square_grid.grid_loop(law, parallel, order, scheme)
             for law in (rheology.COULOMB, -1) for parallel in (False, True)
             for order, scheme in ((1, "hancock"), (2, "heun"), (2, "hancock"))]
    hooks = [_hook(loop, name) for loop in (*loops, *timeloop.ADVANCE.values())
             for name in HOOKS]
    stages = [_hook(loop, "step").py_func.__globals__["_stage"] for loop in loops]
    sweeps = [stage.py_func.__globals__[name] for stage in stages
              for name in ("sweep_serial", "sweep_parallel")]
    heuns = [_hook(loop, "step").py_func.__globals__["order2_step"] for loop in loops[1::3]]
    for dispatcher in (*timeloop.ADVANCE.values(), *hooks, *face_sweep.STEP.values(),
                       *face_sweep.STEP_THREADS.values(), *face_sweep.STEP_PIECES_SERIAL.values(),
                       kernels.step_faces,
                       kernels.step_profile,
                       cpu.half_fluxes, cpu.trial_momentum, rheology.friction, reconstruction.reconstruct_faces,
                       reconstruction.reconstruct_cells,
                       *loops, *stages, *sweeps, *heuns, *sources.SPAN.values(),
                       sources.add_span, sources.add_listed):
        assert Path(dispatcher._cache._cache_path).is_relative_to(folder), dispatcher
    assert config.CACHE_DIR != str(folder)  # other packages' caches stay where Numba puts them


def test_the_square_grid_loops_can_be_cached():
    """A loop whose compiled form calls through a ctypes pointer (``numba.get_num_threads``
    in a jitted function does) is never cached: every process compiled the parallel loop
    again (10 s here). The serial and the parallel time loops of the square grid, as a
    2-thread run compiles or loads them, hold no such pointer."""
    import math

    import numpy as np

    from avflow.numerics.solver import Solver
    from avflow.terrain.bed import plane_terrain
    from conftest import cylinder, walls
    from types import SimpleNamespace as NS

    plane = NS(slope_deg=30.0, azimuth_deg=90.0, extent=NS(x=[0.0, 400.0], y=[0.0, 400.0]),
               elevation_at_center=0.0)
    ter = plane_terrain(plane, 10.0, None, walls())
    for threads in (1, 2):
        solver = Solver(ter, rheology.Law.COULOMB, np.array([math.tan(math.radians(20.0))]),
                        threads=threads)
        solver._parallel_from = (0, 2)
        solver.advance(solver.new_state(cylinder(ter, (100.0, 200.0), 60.0, 5.0)), 1.0)
    for parallel in (False, True):
        loop = square_grid.grid_loop(rheology.COULOMB, parallel)
        assert loop.overloads, parallel
        stage = _hook(loop, "step").py_func.__globals__["_stage"]
        for sweep in (stage.py_func.__globals__["sweep_serial"],
                      stage.py_func.__globals__["sweep_parallel"], stage, loop,
                      *(_hook(loop, name) for name in HOOKS)):
            for compiled in sweep.overloads.values():
                assert not compiled.library.has_dynamic_globals, (sweep, parallel)


def test_a_misspelt_placeholder_is_refused_not_ignored():
    """A copy's replacement for a global its function never reads would leave the original
    in place without a word: refused, for one function and for a group."""
    from avflow.numerics.vectorize import UnknownPlaceholder, shared_names, specialize

    def uses_order2():
        return ORDER2  # noqa: F821 - a placeholder, filled in the copy

    with pytest.raises(UnknownPlaceholder, match="reads no global named ORDR2"):
        specialize(uses_order2, "_x", ORDR2=True)
    assert specialize(uses_order2, "_y", ORDER2=True).py_func() is True
    with pytest.raises(UnknownPlaceholder, match="reads a global named PARALEL"):
        shared_names({"a": uses_order2}, ORDER2=True, PARALEL=True)
    assert shared_names({"a": uses_order2, "b": lambda: 0}, ORDER2=1) == {"a": {"ORDER2": 1},
                                                                        "b": {}}


def test_the_kernel_cache_is_shared_by_every_checkout(tmp_path):
    """Two copies of the package at different places put a kernel's compiled files in the
    same per-user folder (Numba's own locators name it after the path on disk: each clone
    compiled everything again)."""
    import shutil
    import subprocess
    import sys

    package = Path(numerics.__file__).resolve().parents[1]
    code = ("import avflow.numerics as n; from avflow.numerics import kinetic, kernels; "
            "print(kernels.step_faces._cache._cache_path); print(n.kernel_cache_dir()); "
            "print(n.__file__)")
    seen = []
    for place in ("a", "b"):
        root = tmp_path / place
        shutil.copytree(package, root / "avflow",
                        ignore=shutil.ignore_patterns("__pycache__"))
        env = {**os.environ, "PYTHONPATH": str(root), "AVFLOW_CACHE_DIR": str(tmp_path / "c")}
        env.pop("NUMBA_CACHE_DIR", None)
        done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                              text=True, cwd=root, timeout=300)
        assert done.returncode == 0, done.stderr
        path, folder, imported = done.stdout.split()
        assert Path(imported).is_relative_to(root), imported  # the copy, not this checkout
        assert Path(path) == Path(folder) / "numerics", (path, folder)
        assert Path(folder).parent == tmp_path / "c"
        seen.append(path)
    assert seen[0] == seen[1]
