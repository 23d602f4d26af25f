"""The vectorised profile sweep (avflow.numerics.profile) against the fused one it replaces
at order 1 (kernels.step_profile): one step from the same state gives the same bits for the
state and the flags, on states taken along real runs (flowing, stopping,
at rest, dry; walls and open ends; curvature; all four friction laws; a step shortened
below the CFL one). Only the sums over the line (moving volume, film, kinetic energy) are
added in another order: round-off."""

import math
from types import SimpleNamespace as NS

import numpy as np
import pytest

from avflow.numerics import kernels as K
from avflow.numerics import physics, stepping
from avflow.numerics import profile as P
from avflow.numerics.rheology import Law
from avflow.numerics.solver import Solver
from avflow.scenario.schema import load_scenario
from avflow.simulation.runner import prepare
from avflow.terrain.bed import profile_terrain

from conftest import SCENARIOS, walls


def one_step_both(solver, state, dt, dt_decide):
    """The step from ``state`` by both sweeps: ``[(result, h, hu, hv, flag)]``."""
    m, t = solver.terrain.mesh, solver.terrain
    n = state.h.size
    t_new = state.t + dt
    out = []
    for sweep in ("fused", "vectorised"):
        new = [np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)]
        flag = np.full(n, 7, dtype=np.uint8)
        cur, nxt = stepping.Conserved(state.h, state.hu, state.hv), stepping.Conserved(*new)
        when = stepping.StepTime(dt, dt_decide, t_new)
        if sweep == "fused":
            res = K.step_profile(solver._face_mesh, solver._physics(), cur, nxt,
                                 np.zeros((n + 1, 2)), flag, when, False, np.zeros((0, 4)))
        else:
            line = P.ProfileLine(m.face_cells[0, 1], m.face_cells[n, 1], m.cell_area[0],
                                 solver._cfl_factor, solver._density, t.gamma_x, t.gamma_z,
                                 np.ascontiguousarray(t.curvature[:, 0]),
                                 np.zeros((P.N_WORK, n + 2)),
                                 np.full(n + 2, physics.DRY, dtype=np.uint8))
            res = P.step(line, solver._physics(), cur, nxt, flag, when)
        out.append((res, *new, flag))
    return out


def assert_same_step(a, b):
    (ra, *arrays_a), (rb, *arrays_b) = a, b
    assert ra[0] == rb[0]  # ok
    if not ra[0]:
        return
    assert ra[1] == rb[1]  # outflow: the two end faces, same terms
    assert ra[2] == rb[2]  # CFL limit: a max, exact in any order
    assert ra[5] == rb[5]  # clamped count
    for slot in (3, 4, 6):  # moving, film, kinetic: sums in another order
        assert ra[slot] == pytest.approx(rb[slot], rel=1e-12, abs=1e-300)
    for x, y in zip(arrays_a, arrays_b):
        np.testing.assert_array_equal(x, y)


def check_along_run(solver, h0, times, hu0=None):
    """Steps compared from states taken along the run at ``times``; returns the flags seen."""
    state = solver.new_state(h0)
    if hu0 is not None:
        state.hu[:] = hu0
    seen = set()
    for t in times:
        solver.advance(state, t)
        dt = 0.5 / max(solver.terrain.mesh.n_cells, 1)  # replaced below by the CFL step
        lim = K.dt_limit(solver._cfl_factor, solver.terrain.gamma_z, state.h, state.hu,
                         state.hv, float(solver.gravity))
        dt = solver.cfl * lim if np.isfinite(lim) else 0.1
        for step, decide in ((dt, dt), (0.3 * dt, dt)):  # the CFL step, and one shortened
            a, b = one_step_both(solver, state, step, decide)
            assert_same_step(a, b)
            seen.update(np.unique(a[4]).tolist())
    return seen


@pytest.mark.parametrize("bounds", [{}, {"x_min": "outflow", "x_max": "outflow"}])
def test_dam_break_same_bits(bounds):
    """Frictionless dam break, half of it dry, walls or open ends."""
    ter = profile_terrain(NS(length=2000.0, slope=NS(kind="constant", theta_deg=0.0),
                             curvature=False), 1.0, walls(**bounds))
    solver = Solver(ter, Law.COULOMB, np.zeros(4), h_zero=0.0)
    h0 = np.where(ter.x < 600.0, 1.0, 0.0)
    check_along_run(solver, h0, [0.0, 5.0, 40.0, 120.0])


def test_seed_section6_same_bits():
    """The seed's exponential slope with its curvature term: flowing, stopping, at rest."""
    sc = load_scenario(SCENARIOS / "seed_exponential_coulomb15.yaml")
    _, h0, solver, _ = prepare(sc)
    seen = check_along_run(solver, h0, [0.0, 20.0, 60.0, 95.0])
    assert {physics.FLOWING, physics.UNDER_THRESHOLD, physics.DRY} <= seen  # every branch was exercised


@pytest.mark.parametrize("law,params", [
    (Law.VOELLMY, (0.2, 800.0)),
    (Law.POULIQUEN, (math.tan(math.radians(21.0)), math.tan(math.radians(33.0)), 0.8, 0.136)),
    (Law.SAMOSAT, (0.155, 0.0, 0.222, 0.001 / 200.0, 0.43, 0.05, 4.13))])
def test_other_laws_same_bits(law, params):
    """The copies of the cell loops for each law (Voellmy vectorised, Pouliquen and samosAT
    reading the law at run time), on a curved slope with an open lower end."""
    ter = profile_terrain(NS(length=3000.0, slope=NS(kind="exponential", theta0_deg=35.0,
                                                     a=1000.0), curvature=True),
                          5.0, walls(x_max="outflow"))
    solver = Solver(ter, law, np.array(params + (0.0,) * (8 - len(params))), h_zero=1e-6,
                    h_dry=1e-3)
    h0 = np.where(np.abs(ter.x - 300.0) < 150.0, 20.0, 0.0)
    check_along_run(solver, h0, [0.0, 10.0, 40.0])


def test_a_step_that_would_empty_a_cell_fails_in_both():
    """A step far beyond the CFL limit drives a cell below 0: both report it (the time loop
    then halves the step)."""
    ter = profile_terrain(NS(length=200.0, slope=NS(kind="constant", theta_deg=0.0),
                             curvature=False), 1.0, walls())
    solver = Solver(ter, Law.COULOMB, np.zeros(4), h_zero=0.0)
    state = solver.new_state(np.where(ter.x < 100.0, 1.0, 0.0))
    state.hu[:] = np.where(ter.x < 100.0, 50.0, 0.0)
    a, b = one_step_both(solver, state, 5.0, 5.0)
    assert a[0][0] is False and b[0][0] is False
