"""Kernel dispatch through the registry (issue 27): which kernel runs which scene, one line
naming what is available where none does, and the word to the user before a compile."""

import math

import numpy as np
import pytest
from numba import njit

from avflow.numerics import registry
from avflow.numerics.rheology import Law
from avflow.numerics.solver import Solver
from conftest import SCENARIOS, bump_on_a_slope, slope_profile

COULOMB = np.array([math.tan(math.radians(20.0))])


@pytest.mark.parametrize("scene, kernel, order, expected", [
    ("profile", "auto", 1, "profile"), ("profile", "auto", 2, "profile"),
    ("profile", "faces", 1, "profile"),
    ("grid", "auto", 1, "grid"), ("grid", "auto", 2, "grid"), ("grid", "faces", 1, "faces"),
    ("grid", "faces", 2, "faces"),
    ("grid", "grid", 1, "grid"),
    ("triangles", "auto", 1, "faces"), ("triangles", "auto", 2, "faces"),
])
def test_each_scene_gets_its_kernel(scene, kernel, order, expected):
    ter = slope_profile(100.0, 1.0, 30.0) if scene == "profile" else bump_on_a_slope(scene)
    assert registry.select(ter, order, kernel).name == expected
    solver = Solver(ter, Law.COULOMB, COULOMB, order=order, kernel=kernel)
    assert solver._kernel.name == expected
    assert solver.kernel_used == ("grid" if expected == "grid" else "faces")


@pytest.mark.parametrize("scene, order, backend, words", [
    ("triangles", 1, "cpu", ["grid: the mesh is not a square grid"]),
    ("grid", 1, "rocm", ["no kernel runs on the backend 'rocm'", "available: cpu, cuda"]),
    ("triangles", 1, "cuda", ["grid: the mesh is not a square grid",
                              "available: grid (square grids"]),
])
def test_a_combination_no_kernel_runs_fails_at_load_in_one_line_naming_what_is_there(
        scene, order, backend, words):
    ter = bump_on_a_slope(scene)
    with pytest.raises(registry.KernelUnavailable) as err:
        Solver(ter, Law.COULOMB, COULOMB, order=order, kernel="grid", backend=backend)
    message = str(err.value)
    assert "\n" not in message
    for w in words:
        assert w in message
    if backend == "cpu":
        assert "available: profile" in message and "faces (any mesh" in message


def test_a_scenario_asking_for_the_grid_kernel_on_a_profile_names_the_field_and_the_file():
    from avflow.errors import ScenarioError
    from avflow.scenario.schema import load_scenario
    from avflow.simulation.runner import simulate

    sc = load_scenario(SCENARIOS / "seed_exponential_coulomb15.yaml")
    with pytest.raises(ScenarioError, match=r"seed_exponential_coulomb15.yaml: numerics.kernel: "
                                            r"no cpu kernel runs this scene"):
        simulate(sc.with_updates({"numerics.kernel": "grid"}))


def test_the_user_is_told_while_numba_compiles_and_only_then(capsys):
    """The line comes from Numba's own compile event: a cache load or a kernel compiled
    earlier in the process says nothing."""
    from avflow.numerics import compiling
    from avflow.scenario.schema import load_scenario
    from avflow.simulation.runner import simulate

    @njit
    def thrice(x):
        return 3 * x

    said = []
    with compiling.watch(said.append, lambda: "a kernel") as first:
        thrice(1.0)
    assert said == ["a kernel"] and first.compiled and first.seconds > 0
    with compiling.watch(said.append, lambda: "a kernel") as again:
        thrice(2.0)
    assert said == ["a kernel"] and not again.compiled
    sc = load_scenario(SCENARIOS / "seed_exponential_coulomb15.yaml").with_updates(
        {"time.end": 1.0})
    simulate(sc)  # compiled (or loaded) now, if it was not
    said.clear()
    simulate(sc, on_compile=said.append, on_compiled=said.append)
    assert said == []  # in this process already: nothing to say
    compiling.notify_compiling("the profile kernel at order 1 with Coulomb friction")
    compiling.notify_compiled(12.3)
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("avflow: compiling the profile kernel at order 1 with Coulomb "
                             "friction (once per machine and avflow version; kept in ")
    assert err[1] == "avflow: compiled in 12 s" and len(err) == 2


def test_a_backend_this_machine_lacks_is_said_alone_with_what_to_do(monkeypatch):
    """A scene the backend serves, on a machine without its GPU: what is missing and what to
    do, not a list of kernels that ends by offering the one just refused."""
    import dataclasses

    cuda = registry.KERNELS["grid", "cuda"]
    monkeypatch.setitem(registry.KERNELS, ("grid", "cuda"), dataclasses.replace(
        cuda, unavailable=lambda: "no CUDA GPU or driver found"))
    with pytest.raises(registry.KernelUnavailable) as err:
        registry.select(bump_on_a_slope("grid"), 1, "auto", "cuda")
    message = str(err.value)
    assert message == ("the cuda backend cannot run on this machine: no CUDA GPU or driver "
                       "found; run with numerics.backend: cpu (--backend cpu), or on a "
                       "machine that has it")
    # what the backend does not serve is still said first, with what it does serve
    with pytest.raises(registry.KernelUnavailable, match="not a square grid.*available: grid"):
        registry.select(bump_on_a_slope("triangles"), 1, "auto", "cuda")


def test_the_gpu_backend_compiles_every_friction_function_there_is():
    """The device copies take every compiled function and constant of the friction laws'
    module: a law's new helper needs no list in the GPU backend to keep up with."""
    from avflow.numerics import cuda_grid, rheology

    plain = cuda_grid._plain_rheology()
    compiled = {name for name, v in vars(rheology).items()
                if getattr(getattr(v, "py_func", None), "__module__", "") == rheology.__name__}
    assert compiled >= {"friction", "law_friction", "pouliquen_mu", "samosat_drag_factor"}
    for name in compiled:
        assert getattr(plain, name) is getattr(rheology, name).py_func, name
    assert plain.COULOMB == rheology.COULOMB and plain.math is math


def test_a_command_run_in_process_stops_announcing_when_it_ends(capsys, tmp_path):
    """An ensemble, region or calibration called through ``main()`` in a process that goes
    on (a notebook, a test) leaves no compile notice behind it."""
    from types import SimpleNamespace

    from avflow.cli import _announce_compiles, main
    from avflow.numerics import compiling

    _announce_compiles(SimpleNamespace(quiet=False))  # as those commands do
    assert len(compiling._ANNOUNCERS) == 1
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [\n")
    assert main(["run", str(bad)]) == 2
    assert compiling._ANNOUNCERS == []

    @njit
    def four_times(x):
        return 4 * x

    capsys.readouterr()
    four_times(1.0)
    assert "avflow: compiling" not in capsys.readouterr().err


def test_the_schema_and_the_command_line_offer_the_registered_backends_and_kernels():
    """``numerics.backend`` / ``--backend`` and ``numerics.kernel`` list what the registry
    runs (the scenario schema sits below the numerics and the command line starts without
    Numba, so each keeps its list, held to the registry here)."""
    import argparse
    import typing

    from avflow.cli import build_parser
    from avflow.numerics import registry
    from avflow.scenario.schema import Numerics

    assert typing.get_args(Numerics.model_fields["backend"].annotation) == registry.BACKENDS
    assert typing.get_args(Numerics.model_fields["kernel"].annotation) == registry.CHOICES
    found = []
    for action in build_parser()._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found += [tuple(a.choices) for a in sub._actions
                          if "--backend" in a.option_strings]
    assert found and all(choices == registry.BACKENDS for choices in found)
