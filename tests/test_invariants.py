"""Invariants on many scenes: h >= 0, mass to round-off, exact rest, symmetry, no reversal.

Every test runs for both schemes: the seed's first order and the second-order kinetic
scheme (``numerics.order: 2``), which must keep everything the seed's scheme guarantees.
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from avflow.numerics.rheology import Law
from avflow.numerics.solver import Solver
from conftest import coulomb, slope_profile

pytestmark = pytest.mark.parametrize("order", [1, 2])


@settings(max_examples=25, deadline=None)
@given(theta=st.floats(0.0, 60.0), delta=st.floats(0.0, 45.0),
       thickness=st.floats(1e-3, 300.0), start=st.integers(1, 60), width=st.integers(1, 30),
       cfl=st.floats(0.05, 1.0), t_end=st.floats(0.5, 60.0))
def test_positivity_and_mass_conservation(order, theta, delta, thickness, start, width, cfl,
                                         t_end):
    """With walls, mass is kept to 1e-12 relative and h never turns negative."""
    terrain = slope_profile(100 * 5.0, 5.0, theta)
    solver = coulomb(terrain, delta, cfl=cfl, order=order)
    h0 = np.zeros(terrain.n_cells)
    h0[start:start + width] = thickness
    state = solver.new_state(h0)
    v0 = solver.volume(state)
    status = solver.advance(state, t_end)
    assert status == "running"
    assert np.all(state.h >= 0.0) and np.all(np.isfinite(state.hu))
    assert abs(solver.volume(state) - v0) <= 1e-12 * v0


def test_pile_under_its_friction_angle_stays_exactly_at_rest(order):
    """Slope 20 deg < delta 30 deg: h bit for bit unchanged after 5000 steps, q = 0."""
    terrain = slope_profile(1000.0, 5.0, 20.0)
    solver = coulomb(terrain, 30.0, order=order)
    x = terrain.x
    h0 = np.maximum(0.0, 10.0 * (1.0 - ((x - 500.0) / 100.0) ** 2))  # parabolic pile
    state = solver.new_state(h0)
    assert solver.advance(state, 1e9, max_steps=5000) == "max_steps"
    assert state.steps == 5000
    assert np.array_equal(state.h, h0)
    assert not state.hu.any()


REST_PROFILE = """
name: rest-profile
terrain: {kind: profile, length: 1000.0, slope: {kind: constant, theta_deg: 10.0}}
grid: {dx: 5.0}
release: {kind: parabola, center: 500.0, half_length: 100.0, max_thickness: 5.0}
rheology: {law: coulomb, delta_deg: 20.0}
time: {end: 60.0, cfl: 0.5}
output: {every: 10.0}
"""
REST_PLANE = """
name: rest-cylinder
terrain: {kind: plane, slope_deg: 10.0, azimuth_deg: 90.0,
          extent: {x: [0.0, 600.0], y: [0.0, 600.0]}}
grid: {dx: 20.0}
release: {kind: cylinder, center: [300.0, 300.0], radius: 100.0, thickness: 10.0}
rheology: {law: coulomb, delta_deg: 20.0}
time: {end: 60.0, cfl: 0.5}
output: {every: 10.0}
"""


def test_a_mass_that_never_moves_stops_at_time_zero(order):
    """Slope 10 deg under Coulomb 20 deg: nothing ever moves, so time_to_stop is 0 (not the
    end of the first step or the first output time)."""
    from avflow.scenario.schema import parse_scenario
    from avflow.simulation.runner import simulate

    for text in (REST_PROFILE, REST_PLANE):
        result = simulate(parse_scenario(text).with_updates({"numerics.order": order}))
        assert result.status == "at_rest"
        assert np.array_equal(result.state.h, result.h0)
        assert result.time_to_stop == 0.0 and result.summary["time_to_stop"] == 0.0


def test_without_dirac_the_pile_keeps_spreading(order):
    """The classical kinetic scheme (rectangular density everywhere) never stops (sec. 3.3)."""
    terrain = slope_profile(1000.0, 5.0, 20.0)
    x = terrain.x
    h0 = np.maximum(0.0, 10.0 * (1.0 - ((x - 500.0) / 100.0) ** 2))
    solver = coulomb(terrain, 30.0, dirac=False, order=order)
    state = solver.new_state(h0)
    solver.advance(state, 1e9, max_steps=5000)
    assert not np.array_equal(state.h, h0)
    assert np.count_nonzero(state.h) > np.count_nonzero(h0) + 10  # spread over > 10 more cells
    assert abs(solver.volume(state) - solver.volume(solver.new_state(h0))) < 1e-12 * h0.sum()


def test_moving_mass_stops_with_dirac(order):
    """A pile on a 10 deg slope with delta = 20 deg after a push: it stops and stays."""
    terrain = slope_profile(1000.0, 5.0, 10.0)
    solver = coulomb(terrain, 20.0, order=order)
    h0 = np.maximum(0.0, 10.0 * (1.0 - ((terrain.x - 300.0) / 100.0) ** 2))
    state = solver.new_state(h0)
    state.hu[:] = 5.0 * h0  # launched downslope at 5 m/s
    solver.reset_limits(state)
    assert solver.advance(state, 200.0, stop_volume=0.0) == "running"
    assert not state.hu.any()
    frozen = state.h.copy()
    solver.advance(state, 400.0)
    assert np.array_equal(state.h, frozen)


def test_symmetric_input_gives_a_symmetric_result(order):
    """Flat bed, frictionless and frictional piles: mirror symmetry to round-off."""
    for delta in (0.0, 10.0):
        terrain = slope_profile(1000.0, 5.0, 0.0)
        solver = coulomb(terrain, delta, order=order)
        h0 = np.maximum(0.0, 20.0 * (1.0 - ((terrain.x - 500.0) / 150.0) ** 2))
        state = solver.new_state(h0)
        solver.advance(state, 40.0)
        assert np.allclose(state.h, state.h[::-1], rtol=0, atol=1e-12 * h0.max())
        assert np.allclose(state.hu, -state.hu[::-1], rtol=0, atol=1e-12 * h0.max())


def test_friction_never_reverses_the_velocity(order):
    """A layer thrown uphill decelerates to rest without ever moving downhill first.

    Away from its ends the layer is uniform, so no pressure gradient acts there: only
    gravity and friction, and the projection (eq. 50) must bring u to 0, never below.
    """
    terrain = slope_profile(2000.0, 5.0, 5.0)
    solver = coulomb(terrain, 20.0, order=order)  # delta > theta: once stopped, it stays
    h0 = np.where((terrain.x > 200.0) & (terrain.x < 1800.0), 2.0, 0.0)
    state = solver.new_state(h0)
    state.hu[:] = -3.0 * h0  # uphill at 3 m/s: stops within about 1.4 s and 2 m
    solver.reset_limits(state)
    core = (terrain.x > 600.0) & (terrain.x < 1400.0)
    for k in range(1, 60):
        solver.advance(state, 0.05 * k)
        assert np.all(state.hu[core] <= 0.0)
    assert not state.hu[core].any()


def test_pouliquen_layer_under_h_stop_stays_at_rest(order):
    """A layer thinner than h_stop(theta) keeps h bit for bit (static branch of eq. 15)."""
    terrain = slope_profile(2.0, 0.01, 25.0)
    params = np.array([math.tan(math.radians(20.7)), math.tan(math.radians(32.8)), 0.98e-3,
                       0.136])
    solver = Solver(terrain, Law.POULIQUEN, params, order=order)
    h0 = np.full(terrain.n_cells, 0.9e-3)  # h_stop(25) = 1.081 mm
    state = solver.new_state(h0)
    solver.advance(state, 1e9, max_steps=2000)
    assert np.array_equal(state.h, h0)
