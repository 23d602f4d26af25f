"""The default threads (``threads`` None, issue 27): timed probes choose between all the
cores and one, and whatever they choose, the run is bit for bit the one on one thread."""

import math

import numpy as np
import pytest

from avflow.numerics.rheology import Law
from avflow.numerics.solver import Solver, ThreadChoice
from conftest import assert_same_runs, bump_on_a_slope, cylinder


def test_all_threads_are_kept_only_where_clearly_faster_and_probes_back_off():
    c = ThreadChoice(most=2)
    c.decide(one=1.0, many=0.95, steps=10)  # within the noise: one thread
    assert (c.choice, c.next_probe) == (1, 10 + ThreadChoice.FIRST_INTERVAL)
    c.decide(one=1.0, many=0.5, steps=300)
    assert c.choice == 2 and c.next_probe == 300 + ThreadChoice.FIRST_INTERVAL
    c.decide(one=1.0, many=0.5, steps=600)  # the same clear choice: probed twice as late
    assert c.choice == 2 and c.next_probe == 600 + 2 * ThreadChoice.FIRST_INTERVAL
    c.decide(one=1.0, many=27.0, steps=1200)  # a busy machine: back to one, probed soon
    assert c.choice == 1 and c.next_probe == 1200 + ThreadChoice.FIRST_INTERVAL


@pytest.mark.parametrize("from_cells", [1, 150], ids=["threads-from-the-start",
                                                     "threads-once-the-flow-spreads"])
@pytest.mark.parametrize("mesh_kind, order", [("grid", 1), ("triangles", 1),
                                              ("triangles", 2)])
def test_probes_and_switches_between_threads_leave_the_run_bit_for_bit(monkeypatch, mesh_kind,
                                                                       order, from_cells):
    """Every threaded path on (from 1 cell, or from 150 when the flow has spread: the
    threaded loop is then compiled and first called mid-run), the choice flipped at every
    probe and probes every 8 steps: the same states, observers and statistics as 1 thread."""
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one thread in this process (NUMBA_NUM_THREADS)")
    monkeypatch.setattr(ThreadChoice, "FIRST_INTERVAL", 8)
    flips = []

    def flip(self, one, many, steps):
        self.choice = 1 if self.choice == self.most else self.most
        self.next_probe = steps + 8
        flips.append(self.choice)

    monkeypatch.setattr(ThreadChoice, "decide", flip)
    monkeypatch.setattr(Solver, "threads_used", lambda self: 2)
    runs = []
    for threads in (1, None):
        terrain = bump_on_a_slope(mesh_kind)
        solver = Solver(terrain, Law.COULOMB, np.array([math.tan(math.radians(22.0))]),
                        order=order, threads=threads, h_zero=1e-6, h_dry=0.01)
        if threads is None:  # every step that may run on threads does
            if solver.kernel_used == "grid":
                solver._parallel_from = (from_cells, 2)
            else:
                from avflow.numerics import face_sweep

                solver._gather_from = from_cells
                if order == 1:  # pieces of a few cells, as tests/test_face_sweep.py
                    m = terrain.mesh
                    solver._sweep = solver._sweep._replace(work=face_sweep.work(
                        m.n_cells, m.n_faces, 2, min_piece=8, max_pieces=32, face_pieces=8))
        state = solver.new_state(cylinder(terrain, (60.0, 100.0), radius=40.0, thickness=6.0))
        snapshots = []
        for t in (2.0, 6.0, 12.0):
            solver.advance(state, t)
            snapshots.append(state.h.copy())
        runs.append((state, snapshots))
    assert_same_runs(runs)
    assert len(flips) >= 3 and set(flips) == {1, 2}  # both choices ran, more than once
