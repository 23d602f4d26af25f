"""The mass-source seam (issue 27; entrainment, issue 30, is built on it): a source adds
mass in one place, after each accepted step, for every kernel and both orders, and the
mass balance reads what it added from the erodible layer itself.

- a constant source on a lake at rest adds exactly ``rate * dt * area`` per step, and the
  layer, the steps' count and the balance all say so;
- on flows over every kernel the balance ``released + entrained = on the map + outflow``
  holds to round-off, h and the layer never go below 0, and a layer used up ends at 0;
- the balance can fail: mass put on the map that the layer did not give is seen;
- 1 and 2 threads give the same bits with a source.
"""

import math

import numpy as np
import pytest
from conftest import bump_on_a_slope, coulomb, slope_profile

from avflow.numerics.physics import SOURCE_CONSTANT, source_rate, take_erodible
from avflow.numerics.sources import MassSource


def _lake(order):
    """A lake 1 m deep at rest on a flat walled profile, 100 cells of 2 m."""
    ter = slope_profile(200.0, 2.0, 0.0)
    return ter, np.ones(ter.n_cells)


def test_pointwise_rate_and_cap():
    assert source_rate(SOURCE_CONSTANT, 0.02, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 5.0, 0.0) == 0.02
    assert source_rate(SOURCE_CONSTANT, 0.02, 0.0, 0.0, 0.0, 1.0, 9.0, 1.0, 0.0, 0.0) == 0.02
    assert source_rate(0, 0.02, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 5.0, 0.0) == 0.0
    assert take_erodible(0.02, 0.5, 1.0) == 0.02 * 0.5
    assert take_erodible(0.02, 0.5, 0.004) == 0.004  # never more than the layer holds
    assert take_erodible(0.02, 0.5, 0.0) == 0.0
    assert take_erodible(-1.0, 0.5, 1.0) == 0.0


@pytest.mark.parametrize("order", [1, 2])
def test_a_constant_source_adds_rate_dt_area_every_step(order):
    rate, ratio = 0.01, 0.8
    ter, h0 = _lake(order)
    area = ter.mesh.cell_area.sum()
    src = MassSource(SOURCE_CONSTANT, np.full(ter.n_cells, 5.0), (rate,), density_ratio=ratio)
    solver = coulomb(ter, 20.0, order=order, source=src)
    state = solver.new_state(h0)
    v0 = solver.volume(state)
    for _ in range(12):
        t, v, counted = state.t, solver.volume(state), state.statistics.source_volume
        assert solver.advance(state, 10.0, max_steps=state.steps + 1) == "max_steps"
        dt = state.t - t
        want = ratio * rate * dt * area
        assert solver.volume(state) - v == pytest.approx(want, rel=1e-12)
        assert state.statistics.source_volume - counted == pytest.approx(want, rel=1e-12)
    # the layer's books: each cell gave rate * t, and the balance reads them
    np.testing.assert_allclose(state.erodible, 5.0 - rate * state.t, rtol=0, atol=1e-14)
    entrained = solver.entrained_volume(state)
    assert entrained == pytest.approx(ratio * rate * state.t * area, rel=1e-12)
    assert abs(solver.volume(state) - v0 - entrained) <= 1e-13 * solver.volume(state)
    assert not np.any(state.hu)  # the lake stays at rest: the mass came with no momentum


def _flow(kind, order, threads=1, erodible=0.3, rate=0.05):
    """A release on the bump's slope (grid with an open side, triangles, faces on the grid)
    or the 32 degree profile, over an erodible layer downslope."""
    if kind == "profile":
        ter = slope_profile(400.0, 2.0, 32.0, x_max="outflow")
        h0 = np.where((ter.x > 40.0) & (ter.x < 80.0), 6.0, 0.0)
        layer = np.where(ter.x > 60.0, erodible, 0.0)
        kernel = "auto"
    else:
        ter = bump_on_a_slope("triangles" if kind == "triangles" else "grid")
        xx, yy = ter.cell_xy()
        h0 = np.where((xx - 80.0) ** 2 + (yy - 100.0) ** 2 <= 40.0**2, 5.0, 0.0)
        layer = np.where(xx > 100.0, erodible, 0.0)
        kernel = "faces" if kind == "faces" else "auto"
    src = MassSource(SOURCE_CONSTANT, layer, (rate,), density_ratio=0.9)
    solver = coulomb(ter, 24.0, order=order, kernel=kernel, threads=threads, source=src,
                     h_dry=1e-3, h_zero=1e-9)
    if threads > 1:  # every step on threads, however few its cells
        if solver.kernel_used == "grid":
            solver._parallel_from = (0, 2)
        else:
            solver._gather_from = 1 if order == 2 else solver._gather_from
    return ter, solver, solver.new_state(h0)


@pytest.mark.parametrize("kind,order", [("profile", 1), ("profile", 2), ("grid", 1),
                                        ("faces", 2), ("triangles", 1), ("triangles", 2)])
def test_balance_with_a_source_on_every_kernel(kind, order):
    ter, solver, state = _flow(kind, order)
    v0 = solver.volume(state)
    for t in (3.0, 6.0, 9.0):
        assert solver.advance(state, t) == "running"
        assert state.h.min() >= 0.0 and state.erodible.min() >= 0.0
        entrained = solver.entrained_volume(state)
        out = state.statistics.outflow_volume
        assert abs(solver.volume(state) + out - v0 - entrained) <= 1e-12 * (v0 + entrained)
    assert entrained > 0.05 * v0  # the source really acted
    # the steps' own count agrees with the layer's books
    assert state.statistics.source_volume == pytest.approx(entrained, rel=1e-10)
    # where the flow stayed long enough the layer is used up, exactly; where it never
    # came the layer is whole
    assert np.any(state.erodible == 0.0)
    never = state.peak_h == 0.0
    np.testing.assert_array_equal(state.erodible[never], solver.source.erodible[never])


def test_the_balance_sees_mass_the_layer_did_not_give():
    ter, solver, state = _flow("grid", 1)
    v0 = solver.volume(state)
    solver.advance(state, 4.0)
    entrained = solver.entrained_volume(state)
    state.erodible[:] = solver.source.erodible  # the layer's books lost: the mass stays
    out = state.statistics.outflow_volume
    err = abs(solver.volume(state) + out - v0 - solver.entrained_volume(state)) / v0
    assert err > 0.5 * entrained / v0 > 1e-3


@pytest.mark.parametrize("kind,order", [("grid", 1), ("triangles", 2)])
def test_threads_give_the_same_bits_with_a_source(kind, order):
    runs = []
    for threads in (1, 2):
        _, solver, state = _flow(kind, order, threads)
        solver.advance(state, 6.0)
        runs.append(state)
    for name in ("h", "hu", "hv", "erodible", "peak_h", "arrival", "stats"):
        a, b = (np.ascontiguousarray(getattr(s, name)) for s in runs)
        np.testing.assert_array_equal(a.view(np.int64), b.view(np.int64), err_msg=name)


def test_a_source_needs_the_solver_state_and_a_valid_layer():
    ter, h0 = _lake(1)
    with pytest.raises(ValueError, match="erodible"):
        MassSource(SOURCE_CONSTANT, np.full(ter.n_cells, -1.0), (0.1,))
    with pytest.raises(ValueError, match="cells"):
        coulomb(ter, 20.0, source=MassSource(SOURCE_CONSTANT, np.ones(3), (0.1,)))
    solver = coulomb(ter, 20.0, source=MassSource(SOURCE_CONSTANT, np.ones(ter.n_cells),
                                                  (0.1,)))
    plain = coulomb(ter, 20.0).new_state(h0)
    with pytest.raises(ValueError, match="erodible layer"):
        solver.advance(plain, 1.0)
    assert math.isclose(solver.entrained_volume(solver.new_state(h0)), 0.0)
