"""The running maps (peak thickness and speed, arrival, last motion) are observed once per
accepted step, from the state the run goes on from (avflow.numerics.observers): a step that
would turn a thickness negative and is redone with half the time step writes none of them,
and the mass a source adds is seen. On the profile, square-grid and face kernels, both
orders.

A step is made to be redone by hand: the state's CFL limit (``stats[ST_DT_LIMIT]``) set far
above its own before a call, so that the first attempt of its next step empties a cell."""

import math
from types import SimpleNamespace as NS

import numpy as np
import pytest

from avflow.numerics.physics import SOURCE_EROSION_ENERGY
from avflow.numerics.rheology import Law
from avflow.numerics.solver import Solver
from avflow.numerics.sources import MassSource
from avflow.numerics.stepping import ST_DT_LIMIT, ST_RETRIES
from avflow.terrain.bed import plane_terrain

from conftest import cylinder, slope_profile, walls

MAPS = ("peak_h", "peak_speed", "arrival", "last_moved")
KERNELS = [("profile", 1), ("profile", 2), ("grid", 1), ("grid", 2), ("faces", 1),
           ("faces", 2)]
IDS = [f"{kernel}-order{order}" for kernel, order in KERNELS]


def bits(a):
    """The bit patterns of a float array: -0.0 and +0.0 differ, NaN equals NaN."""
    return np.ascontiguousarray(a, dtype=float).view(np.int64)


def scene(kernel, order, delta_deg, source=False):
    """A solver and a release: a dam break on a 30 degree profile, or a cylinder on a 30
    degree plane (10 m cells) with an open lower side, on the grid or the face kernel."""
    params = np.array([math.tan(math.radians(delta_deg))])
    if kernel == "profile":
        terrain = slope_profile(400.0, 2.0, 30.0, x_max="outflow")
        h0 = np.where(np.abs(terrain.x - 100.0) < 30.0, 5.0, 0.0)
    else:
        plane = NS(slope_deg=30.0, azimuth_deg=100.0, elevation_at_center=0.0,
                   extent=NS(x=[0.0, 200.0], y=[0.0, 120.0]))
        terrain = plane_terrain(plane, 10.0, 10.0, walls(x_max="outflow"))
        h0 = cylinder(terrain, (150.0, 60.0), radius=30.0, thickness=4.0)
    layer = (MassSource(SOURCE_EROSION_ENERGY, np.full(terrain.n_cells, 0.5), (2000.0,),
                        density_ratio=0.5) if source else None)
    solver = Solver(terrain, Law.COULOMB, params, order=order, threads=1, h_zero=1e-6,
                    h_dry=1e-2, source=layer,
                    kernel="auto" if kernel == "profile" else kernel)
    return solver, h0


def one_step(solver, state, limit):
    """One step from ``state`` (changed in place) with its CFL limit set to ``limit``:
    the step is ``cfl * limit`` and each retry halves it. Returns the retries it took."""
    state.stats[ST_DT_LIMIT] = limit
    retries = state.stats[ST_RETRIES]
    assert solver.advance(state, 1e6, max_steps=state.steps + 1) == "max_steps"
    return int(state.stats[ST_RETRIES] - retries)


@pytest.mark.parametrize("kernel, order", KERNELS, ids=IDS)
def test_a_step_redone_leaves_the_maps_of_one_accepted_first_time(kernel, order):
    """From a flow under way, a step whose first attempts empty a cell (its CFL limit set 64
    times its own) leaves every map as a step accepted first time with the step it took
    (no friction: the threshold of eq. 49, tested with the uncut step, decides nothing).
    The rejected attempts went further in time and space: had they written the maps,
    arrival and last motion would hold their times."""
    solver, h0 = scene(kernel, order, 0.0)
    state = solver.new_state(h0)
    solver.advance(state, 3.0)
    limit = 64.0 * state.stats[ST_DT_LIMIT]
    redone, first = state.copy(), state.copy()
    retries = one_step(solver, redone, limit)
    assert retries > 0
    # the step it took, exactly: each retry halves cfl * limit (a power of 2 commutes with
    # rounding), and cfl * (limit / 2^k) is that same number
    assert one_step(solver, first, limit * 0.5**retries) == 0
    assert redone.t == first.t
    for name in ("h", "hu", "hv", "flag", *MAPS):
        np.testing.assert_array_equal(bits(getattr(redone, name)),
                                      bits(getattr(first, name)), err_msg=name)


@pytest.mark.parametrize("source", [False, True], ids=["plain", "entrainment"])
@pytest.mark.parametrize("kernel, order", KERNELS, ids=IDS)
def test_the_maps_are_those_of_the_accepted_states(kernel, order, source):
    """Step after step, with friction, every fifth step redone a few times (its CFL limit
    set 32 times its own) and, with an erosion law, mass entrained after each step: the
    maps are the running maxima and times of the states the steps left, computed here from
    those states (physics.observe's rule): a peak speed is the discharge over the thickness
    the source left."""
    solver, h0 = scene(kernel, order, 18.0, source)
    state = solver.new_state(h0)
    expected = {name: getattr(state, name).copy() for name in MAPS}
    retries = 0
    for k in range(40):
        limit = state.stats[ST_DT_LIMIT] * (32.0 if k % 5 == 2 else 1.0)
        retries += one_step(solver, state, limit)
        h, t = state.h, state.t
        speed = np.where(h > 0.0, np.sqrt(state.hu * state.hu + state.hv * state.hv)
                         / np.where(h > 0.0, h, 1.0), 0.0)
        expected["peak_h"] = np.maximum(expected["peak_h"], h)
        expected["peak_speed"] = np.maximum(expected["peak_speed"], speed)
        arrives = (h > solver.h_dry) & np.isnan(expected["arrival"])
        expected["arrival"] = np.where(arrives, t, expected["arrival"])
        expected["last_moved"] = np.where(speed > 0.0, t, expected["last_moved"])
        for name in MAPS:
            np.testing.assert_array_equal(bits(getattr(state, name)), bits(expected[name]),
                                          err_msg=f"{name} after step {k + 1}")
    assert retries > 0
    assert np.count_nonzero(~np.isnan(state.last_moved)) > 5  # the flow went somewhere
    if source:
        assert solver.entrained_volume(state) > 0.0
