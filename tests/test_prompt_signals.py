"""Ctrl-C and SIGTERM stop a run within a second or two, in the compiled loop and while
Numba compiles, and a run cut into many calls of the compiled loop is the same bit for bit.

Before: the loop held the interpreter until the next output time (8.6-20.1 s on a 42 s
run), and SIGTERM 8 s into a first compile was lost inside LLVM (the run finished and
exited 0, 185 s later).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

PLANE = """
name: signals-plane
terrain: {kind: plane, slope_deg: 30.0, azimuth_deg: 90.0,
          extent: {x: [0.0, 400.0], y: [0.0, 240.0]}}
rheology: {law: coulomb, delta_deg: 20.0}
grid: {dx: 10.0}
numerics: {kernel: KERNEL, threads: 1, order: ORDER}
release: {kind: cylinder, center: [100.0, 120.0], radius: 50.0, thickness: 8.0}
time: {end: 12.0, cfl: 0.5}
output: {every: 6.0}
"""
PROFILE = """
name: signals-profile
terrain: {kind: profile, length: 600.0, slope: {kind: constant, theta_deg: 30.0}}
rheology: {law: coulomb, delta_deg: 20.0}
grid: {dx: 5.0}
numerics: {threads: 1, order: ORDER}
release: {kind: parabola, center: 150.0, half_length: 60.0, max_thickness: 8.0}
time: {end: 20.0, cfl: 0.5}
output: {every: 10.0}
"""
SCENES = {"grid": PLANE.replace("KERNEL", "grid"), "faces": PLANE.replace("KERNEL", "faces"),
          "profile": PROFILE}


@pytest.mark.parametrize("order", (1, 2))
@pytest.mark.parametrize("scene", sorted(SCENES))
def test_a_run_in_many_calls_is_the_same_bit_for_bit(scene, order, monkeypatch):
    """Calls of 8 steps (the shortest the solver makes) against calls to each output time."""
    from avflow.numerics.solver import Solver
    from avflow.scenario.schema import parse_scenario
    from avflow.simulation.runner import simulate

    text = SCENES[scene].replace("ORDER", str(order))
    runs = []
    for seconds in (1e9, 1e-12):
        monkeypatch.setattr(Solver, "CALL_SECONDS", seconds)
        result = simulate(parse_scenario(text))
        runs.append(result)
    whole, pieces = runs
    assert pieces.state.steps == whole.state.steps > 16
    for name in ("h", "hu", "hv", "peak_h", "peak_speed", "arrival", "flag"):
        a, b = getattr(whole.state, name), getattr(pieces.state, name)
        np.testing.assert_array_equal(a, b, err_msg=name)
    np.testing.assert_array_equal(whole.state.stats, pieces.state.stats)


LONG = """
name: signals-long
terrain: {kind: plane, slope_deg: 30.0, azimuth_deg: 90.0,
          extent: {x: [0.0, 2000.0], y: [0.0, 600.0]}}
rheology: {law: coulomb, delta_deg: 15.0}
grid: {dx: 2.0}
numerics: {threads: 1}
release: {kind: cylinder, center: [200.0, 300.0], radius: 100.0, thickness: 10.0}
time: {end: END, cfl: 0.5}
output: {every: END}
"""


def _start(folder: Path, env: dict, end: float, name: str):
    (folder / f"{name}.yaml").write_text(LONG.replace("END", str(end)))
    return subprocess.Popen([sys.executable, "-m", "avflow", "run", f"{name}.yaml", "-o",
                             f"{name}.nc"], cwd=folder, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


@pytest.mark.parametrize("sig, code, says", [(signal.SIGTERM, 143, "avflow: terminated"),
                                             (signal.SIGINT, 130, "avflow: interrupted")])
def test_a_signal_stops_the_compiled_loop_within_a_second_or_two(tmp_path, sig, code, says):
    """One output time at the end of a long run: the loop used to keep the signal until
    then. The kernels compiled first (a short run of the same scene)."""
    env = {**os.environ}
    warm = _start(tmp_path, env, 0.5, "warm")
    assert warm.wait(timeout=600) == 0, warm.stderr.read()
    run = _start(tmp_path, env, 600.0, "long")
    time.sleep(6.0)  # the interpreter, the scenario, the first calls of the loop
    assert run.poll() is None, run.stderr.read()
    sent = time.perf_counter()
    run.send_signal(sig)
    assert run.wait(timeout=60) == code
    waited = time.perf_counter() - sent
    assert waited < 3.0, waited  # CALL_SECONDS 0.5, and the file's removal
    assert says in run.stderr.read()
    assert not (tmp_path / "long.nc").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_sigterm_while_numba_compiles_stops_the_run(tmp_path):
    """An empty kernel cache: the first run compiles for tens of seconds; SIGTERM once it
    says so stops it within seconds, exit code 143, no file left."""
    env = {**os.environ, "AVFLOW_CACHE_DIR": str(tmp_path / "cache")}
    env.pop("NUMBA_CACHE_DIR", None)
    run = _start(tmp_path, env, 30.0, "cold")
    waited_for = time.perf_counter()
    line = run.stderr.readline()
    while line and "avflow: compiling" not in line:
        line = run.stderr.readline()
    assert "avflow: compiling" in line, line
    time.sleep(3.0)  # well inside the compilation (20 s and more here)
    assert run.poll() is None
    sent = time.perf_counter()
    run.send_signal(signal.SIGTERM)
    assert run.wait(timeout=120) == 143, run.stderr.read()
    waited = time.perf_counter() - sent
    assert waited < 8.0, (waited, time.perf_counter() - waited_for)
    assert "avflow: terminated" in run.stderr.read()
    assert not (tmp_path / "cold.nc").exists()


def test_an_interrupt_lost_inside_llvm_is_raised_at_the_next_compiler_pass():
    """Where a signal's handler ran inside one of llvmlite's C callbacks, Python printed its
    exception and went on compiling: the handler also records it (as the command line's
    do), and the next compiler pass raises it."""
    from numba import njit

    import avflow.numerics  # noqa: F401 - installs the listener
    from avflow.numerics import compiling

    compiling.PENDING[:] = [KeyboardInterrupt]
    with pytest.raises(KeyboardInterrupt):
        njit(lambda x: x + 1)(1)
    assert compiling.PENDING == []
    assert njit(lambda x: x + 2)(1) == 3  # nothing pending: compiles as ever


def test_a_worker_says_nothing_of_its_closed_scheduler():
    """A 2-worker ensemble stopped by SIGTERM printed a worker's heartbeat traceback
    (CommClosedError) in 1 of 6 tries: the scheduler had closed first. The workers' preload
    drops that one record, and nothing else."""
    import logging

    from avflow.ensemble import orchestrate

    logger = logging.getLogger("distributed.worker")
    orchestrate.dask_setup(None)
    try:
        def record(message):
            return logging.LogRecord("distributed.worker", logging.ERROR, __file__, 1,
                                     message, None, None)

        assert not logger.filter(record("Failed to communicate with scheduler during "
                                        "heartbeat."))
        assert logger.filter(record("Compute Failed"))
    finally:
        logger.removeFilter(orchestrate._closed_scheduler_filter)
