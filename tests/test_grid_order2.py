"""Order 2 on the square-grid kernel (issue 27) against the face kernel at order 2.

Each of Heun's stages is the grid's order-1 row sweep fed the reconstructed face sides of
each row (square_grid._recon_row: the face kernel's reconstruct_cells, cell by cell, and
step_faces' emitted states), so the state, the discharge, the observers and the time steps
are the face kernel's bit for bit; the grid-wide sums (moving volume, film, kinetic energy,
outflow) are added per row, then over the rows, and may differ by round-off. The flags may
differ where the grid sweeps a dry cell the face kernel's lists leave out (its own flag is
DRY there, the face kernel keeps an older one).

Those comparisons run the grid with Heun's stages (``time_scheme="heun"``); the grid's
default, MUSCL-Hancock (one sweep of sides predicted half a step on), has no face-kernel
twin: it keeps mass, h >= 0, rest and threads here, and its accuracy is tested in
tests/test_second_order.py and tests/test_similarity.py.
"""

import math
from types import SimpleNamespace as NS

import numba
import numpy as np
import pytest

from avflow.numerics import stepping
from avflow.numerics.rheology import Law
from avflow.numerics.solver import Solver
from avflow.terrain.bed import plane_terrain, surface_terrain

from conftest import bump_on_a_slope, cylinder, walls

STATE = ("h", "hu", "hv", "peak_h", "peak_speed", "arrival", "last_moved")
COULOMB20 = (Law.COULOMB, (math.tan(math.radians(20.0)),))
VOELLMY = (Law.VOELLMY, (0.2, 500.0))


def bits(a):
    """-0.0 and +0.0 differ, NaN equals NaN."""
    return np.ascontiguousarray(a).view(np.int64)


def runs(terrain, h0, times, law, params, kernels=("faces", "grid"), threads=1, **kw):
    """The same order-2 run on each kernel: ``{kernel: (state, statuses)}``."""
    out = {}
    for kernel in kernels:
        solver = Solver(terrain, law, np.array(params, dtype=float), order=2, kernel=kernel,
                        threads=threads, time_scheme="heun", **kw)
        assert solver.kernel_used == kernel
        state = solver.new_state(h0)
        out[kernel] = (state, [solver.advance(state, t) for t in times])
    return out


def assert_same_as_faces(out):
    (a, sa), (b, sb) = out["faces"], out["grid"]
    assert sa == sb
    for name in STATE:
        np.testing.assert_array_equal(bits(getattr(a, name)), bits(getattr(b, name)),
                                      err_msg=name)
    assert a.steps == b.steps and a.t == b.t
    for slot in (stepping.ST_DT_LIMIT, stepping.ST_DT_MIN, stepping.ST_DT_MAX,
                 stepping.ST_CLAMPED, stepping.ST_RETRIES, stepping.ST_FALLBACK):
        assert a.stats[slot] == b.stats[slot], slot
    for slot in (stepping.ST_MOVING, stepping.ST_FILM, stepping.ST_KINETIC,
                 stepping.ST_KINETIC_PEAK, stepping.ST_OUTFLOW):
        assert a.stats[slot] == pytest.approx(b.stats[slot], rel=1e-12, abs=1e-9), slot


def tilted_plane(**bounds):
    plane = NS(slope_deg=30.0, azimuth_deg=100.0, extent=NS(x=[0.0, 600.0], y=[0.0, 300.0]),
               elevation_at_center=0.0)
    return plane_terrain(plane, 10.0, 7.5, walls(**bounds))


@pytest.mark.parametrize("bounds", [{}, {"x_max": "outflow", "y_min": "outflow"}],
                         ids=["walls", "open"])
def test_plane_cylinder_is_the_face_kernel_bit_for_bit(bounds):
    ter = tilted_plane(**bounds)
    h0 = cylinder(ter, (420.0, 150.0), radius=60.0, thickness=8.0)
    out = runs(ter, h0, (5.0, 10.0, 20.0), *COULOMB20, h_zero=1e-3, h_dry=1e-3)
    assert_same_as_faces(out)
    a = out["grid"][0]
    assert a.stats[stepping.ST_FALLBACK] > 0  # cells stopped: Heun's fallback ran
    if bounds:
        assert a.stats[stepping.ST_OUTFLOW] > 0.0  # the open sides are exercised


@pytest.mark.parametrize("law, params", [COULOMB20, VOELLMY], ids=["coulomb", "voellmy"])
def test_bumpy_dem_with_a_hole_is_the_face_kernel_bit_for_bit(law, params):
    """A 25 m bump on a slope (bed-linked frames, curvature), a NODATA hole in the path, an
    open lower side: fronts, dry neighbours, walls and holes in the reconstruction."""
    ter = bump_on_a_slope("grid")
    h0 = cylinder(ter, (110.0, 100.0), radius=40.0, thickness=5.0)
    out = runs(ter, h0, (4.0, 12.0, 40.0), law, params, h_zero=1e-6, h_dry=0.01)
    assert_same_as_faces(out)
    assert out["grid"][0].stats[stepping.ST_OUTFLOW] > 0.0


def test_film_rule_off_is_the_face_kernel_bit_for_bit():
    """h_zero = 0: every film flows and is reconstructed."""
    ter = bump_on_a_slope("grid")
    h0 = cylinder(ter, (110.0, 100.0), radius=40.0, thickness=5.0)
    assert_same_as_faces(runs(ter, h0, (3.0, 9.0), *COULOMB20, h_zero=0.0, h_dry=0.01))


SCHEMES = ("hancock", "heun")


@pytest.mark.parametrize("scheme", SCHEMES)
def test_mass_is_conserved_and_h_stays_positive(scheme):
    ter = tilted_plane()
    h0 = cylinder(ter, (420.0, 150.0), radius=60.0, thickness=8.0)
    solver = Solver(ter, COULOMB20[0], np.array(COULOMB20[1]), order=2, kernel="grid",
                    threads=1, h_zero=1e-6, time_scheme=scheme)
    state = solver.new_state(h0)
    v0 = solver.volume(state)
    for t in (2.0, 6.0, 15.0, 30.0):
        solver.advance(state, t)
        assert state.h.min() >= 0.0
        assert abs(solver.volume(state) - v0) <= 1e-12 * v0
    assert state.steps > 50


@pytest.mark.parametrize("scheme", SCHEMES)
def test_a_pile_under_its_threshold_stays_at_rest_bit_for_bit(scheme):
    """A pile in a bowl under its friction threshold: not a grain moves at order 2 (every
    stage puts it under the threshold, and Heun's merge keeps q = 0; MUSCL-Hancock's one
    sweep puts it under the threshold and its faces are Dirac)."""
    x = np.arange(40) * 5.0 + 2.5
    xx, yy = np.meshgrid(x, x)
    z = 0.002 * ((xx - 100.0) ** 2 + (yy - 100.0) ** 2)
    ter = surface_terrain(z, x, x, walls())
    cx, cy = ter.cell_xy()
    h0 = np.where((cx - 100.0) ** 2 + (cy - 100.0) ** 2 < 40.0**2, 2.0, 0.0)
    solver = Solver(ter, Law.COULOMB, np.array([math.tan(math.radians(30.0))]), order=2,
                    kernel="grid", threads=1, h_zero=1e-3, time_scheme=scheme)
    state = solver.new_state(h0)
    assert solver.advance(state, 50.0, stop_volume=-1.0) == "running"
    assert np.array_equal(bits(state.h), bits(h0))
    assert not state.hu.any() and not state.hv.any()


def test_auto_runs_order_2_on_the_grid_kernel():
    ter = tilted_plane()
    solver = Solver(ter, COULOMB20[0], np.array(COULOMB20[1]), order=2)
    assert solver.kernel_used == "grid"


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2,
                    reason="Numba has one thread on this machine (NUMBA_NUM_THREADS=1)")
@pytest.mark.parametrize("scheme", SCHEMES)
def test_one_and_two_threads_give_the_same_run_bit_for_bit(scheme):
    """Every stage on threads, in blocks of 2 rows (each block recomputes the rows beside
    it, reconstruction included): the same bits as one thread."""
    ter = bump_on_a_slope("grid")
    h0 = cylinder(ter, (110.0, 100.0), radius=40.0, thickness=5.0)
    states = []
    for threads in (1, 2):
        solver = Solver(ter, COULOMB20[0], np.array(COULOMB20[1]), order=2, kernel="grid",
                        threads=threads, h_zero=1e-6, h_dry=0.01, time_scheme=scheme)
        solver._parallel_from = (0, 2)
        state = solver.new_state(h0)
        for t in (4.0, 12.0, 30.0):
            solver.advance(state, t)
        states.append(state)
    a, b = states
    for name in STATE + ("stats",):
        np.testing.assert_array_equal(bits(getattr(a, name)), bits(getattr(b, name)),
                                      err_msg=name)
    np.testing.assert_array_equal(a.flag, b.flag)
