"""The square-grid kernel against the face kernel, and 1 thread against N.

The structured kernel (avflow.numerics.square_grid) adds each cell's faces in the order of
their indices in the mesh, as the face kernel does, so the two agree bit for bit on the
state and the observers; only the grid-wide diagnostic sums (moving volume, film, kinetic
energy, outflow) are added per row, then over the rows, and differ by round-off.
"""

import math
from types import SimpleNamespace as NS

import numba
import numpy as np
import pytest

from avflow.errors import ScenarioError
from avflow.numerics.rheology import Law
from avflow.numerics.solver import Solver
from avflow.scenario.schema import load_scenario
from avflow.simulation.runner import simulate
from avflow.terrain.bed import plane_terrain, surface_terrain
from avflow.terrain.squaregrid import square_grid

from conftest import SCENARIOS, cylinder, faces_permuted, walls

STATE = ("h", "hu", "hv", "peak_h", "peak_speed", "arrival", "last_moved")
ROUND_OFF = ("moving", "film", "kinetic", "outflow")


def valley(nx=60, ny=40, dx=5.0, holes=True):
    """A curved valley DEM (x downslope, parabolic across, a bump), with NODATA holes."""
    x = np.arange(nx) * dx + 2.5
    y = np.arange(ny) * dx + 2.5
    xx, yy = np.meshgrid(x, y)
    z = (600.0 - 0.7 * xx + 0.004 * (yy - y.mean()) ** 2
         + 8.0 * np.exp(-((xx - 200.0) ** 2 + (yy - 90.0) ** 2) / 400.0))
    if holes:
        z[18:22, 30:34] = np.nan  # a hole in the path
        z[0:3, 0:5] = np.nan  # a notch on the edge
        z[ny - 1, 40:nx] = np.nan
    return z, x, y


def pair(terrain, law=Law.COULOMB, params=(math.tan(math.radians(20.0)),), **kw):
    """The same solver on both kernels."""
    faces = Solver(terrain, law, np.array(params, dtype=float), kernel="faces", **kw)
    grid = Solver(terrain, law, np.array(params, dtype=float), kernel="grid", threads=1, **kw)
    assert (faces.kernel_used, grid.kernel_used) == ("faces", "grid")
    return faces, grid


def run_both(terrain, h0, t_end, **kw):
    faces, grid = pair(terrain, **kw)
    states = []
    for solver in (faces, grid):
        state = solver.new_state(h0)
        statuses = [solver.advance(state, t) for t in np.linspace(t_end / 4, t_end, 4)]
        states.append((state, statuses))
    return states


def assert_same_state(a, b):
    for name in STATE:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.steps == b.steps
    assert a.t == b.t


def assert_round_off(a, b):
    from avflow.numerics import stepping

    for slot in (stepping.ST_MOVING, stepping.ST_FILM, stepping.ST_KINETIC, stepping.ST_OUTFLOW):
        assert a.stats[slot] == pytest.approx(b.stats[slot], rel=1e-12, abs=1e-9)


def test_layout_holds_every_face_once():
    z, x, y = valley()
    ter = surface_terrain(z, x, y, walls(x_max="outflow"), nodata="wall")
    grid = square_grid(ter)
    inner = ter.mesh.face_cells[:, 1] >= 0
    boundary = ~inner
    n_codes = np.count_nonzero(grid.x_code) + np.count_nonzero(grid.y_code)
    assert n_codes == ter.mesh.n_faces
    assert np.count_nonzero(grid.x_code == 1) + np.count_nonzero(grid.y_code == 1) == inner.sum()
    assert boundary.sum() > 0


@pytest.mark.parametrize("kind", ["plane", "dem"])
def test_faces_in_grid_order(kind):
    """Every cell's faces, walls and open sides at the map's edges and at NODATA holes
    included, have indices W < E < S < N (the order the face kernel adds them, which the
    square-grid kernel follows); a mesh with its faces in another order is not laid out,
    and the face kernel runs it, with the same answer to round-off."""
    if kind == "dem":
        z, x, y = valley()
        ter = surface_terrain(z, x, y, walls(x_max="outflow"), nodata="wall")
    else:
        plane = NS(slope_deg=30.0, azimuth_deg=100.0,
                   extent=NS(x=[0.0, 300.0], y=[0.0, 200.0]), elevation_at_center=0.0)
        ter = plane_terrain(plane, 10.0, None, walls(x_max="outflow", y_min="outflow"))
    m = ter.mesh
    ny, nx = ter.grid_shape
    place = np.arange(m.n_cells) if ter.cell_index is None else ter.cell_index
    side = np.full((m.n_cells, 4), -1)
    for f, ((i, j), d) in enumerate(zip(m.face_cells, m.face_direction)):
        side[i, d] = f  # EAST 0, WEST 1, NORTH 2, SOUTH 3: the owner's side
        if j >= 0:
            side[j, {0: 1, 2: 3}[int(d)]] = f
    w, e, n, s = side[:, 1], side[:, 0], side[:, 2], side[:, 3]
    assert (side >= 0).all()
    assert ((w < e) & (e < s) & (s < n)).all()
    edge = (place % nx == 0) | (place % nx == nx - 1) | (place // nx == 0) | (place // nx == ny - 1)
    assert edge.any() and (m.face_cells[:, 1] < 0).sum() > edge.sum()  # holes too (DEM)
    assert square_grid(ter) is not None
    # the same faces, those on the map's west side last (as the mesh had them before grid
    # order): no layout, the face kernel runs it
    west = np.flatnonzero(m.face_direction == 1)  # WEST: the owner's west side
    perm = np.concatenate([np.setdiff1d(np.arange(m.n_faces), west), west])
    other = faces_permuted(ter, perm)
    assert square_grid(other) is None
    if kind == "plane":  # a pile against the west wall, whose cells add their faces in
        # another order on the shuffled mesh: the same flow, to round-off
        h0 = cylinder(ter, (20.0, 100.0), radius=40.0, thickness=5.0)
        params = np.array([math.tan(math.radians(20.0))])
        a, b = Solver(ter, Law.COULOMB, params), Solver(other, Law.COULOMB, params)
        assert a.kernel_used == "grid" and b.kernel_used == "faces"
        sa, sb = a.new_state(h0), b.new_state(h0)
        a.advance(sa, 5.0)
        b.advance(sb, 5.0)
        assert sa.steps == sb.steps > 10
        np.testing.assert_allclose(sa.h, sb.h, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("bounds", [walls(), walls(x_max="outflow", y_min="outflow")])
def test_plane_agrees_bit_for_bit(bounds):
    plane = NS(slope_deg=30.0, azimuth_deg=100.0, extent=NS(x=[0.0, 600.0], y=[0.0, 300.0]),
               elevation_at_center=0.0)
    ter = plane_terrain(plane, 10.0, 7.5, bounds)
    h0 = cylinder(ter, (420.0, 150.0), radius=60.0, thickness=8.0)
    (a, sa), (b, sb) = run_both(ter, h0, 30.0, h_zero=1e-3, h_dry=1e-3)
    assert sa == sb
    assert_same_state(a, b)
    assert_round_off(a, b)
    if bounds.x_max == "outflow":
        from avflow.numerics import stepping

        assert a.stats[stepping.ST_OUTFLOW] > 0.0  # material left: the open sides are exercised


def valley_agrees(nodata, law, params, t_end):
    """A 5 m cylinder down the valley with holes (open lower side) on both kernels: the
    statuses, the state and the observers agree bit for bit, the sums to round-off.
    Returns the face kernel's state and the terrain."""
    z, x, y = valley()
    ter = surface_terrain(z, x, y, walls(x_max="outflow"), nodata=nodata)
    xx, yy = ter.cell_xy()
    h0 = np.where((xx - 60.0) ** 2 + (yy - 100.0) ** 2 < 30.0**2, 5.0, 0.0)
    (a, sa), (b, sb) = run_both(ter, h0, t_end, law=law, params=params, h_zero=1e-3,
                                h_dry=1e-3)
    assert sa == sb
    assert_same_state(a, b)
    assert_round_off(a, b)
    return a, ter


@pytest.mark.parametrize("nodata", ["wall", "outflow"])
@pytest.mark.parametrize("law,params", [(Law.COULOMB, (math.tan(math.radians(18.0)),)),
                                        (Law.VOELLMY, (0.15, 500.0))])
def test_dem_with_holes_agrees_bit_for_bit(nodata, law, params):
    """A curved DEM (bed-linked frames, curvature term) with NODATA holes in the path and on
    the edge, open lower side: state and observers are the face kernel's, bit for bit."""
    a, ter = valley_agrees(nodata, law, params, 40.0)
    assert a.t == 40.0 and a.h.shape == (ter.n_cells,)


@pytest.mark.parametrize("law,params", [
    (Law.POULIQUEN, (math.tan(math.radians(20.0)), math.tan(math.radians(32.0)), 1.0, 0.136)),
    (Law.SAMOSAT, (0.155, 0.0, 0.222, 0.001 / 200.0, 0.43, 0.05, 4.13))])
def test_laws_with_transcendental_functions_agree_bit_for_bit(law, params):
    """Pouliquen (exp) and samosAT (log) run the grid kernel's cell loops that read the law
    at run time (Coulomb and Voellmy have their own, vectorised, copies): the same bits."""
    a, _ = valley_agrees("wall", law, params, 30.0)
    assert np.count_nonzero(a.h) > 100  # it flowed


def test_film_rule_off_agrees_bit_for_bit():
    """h_zero = 0: every film flows (the seed's dam-break setting)."""
    z, x, y = valley(holes=False)
    ter = surface_terrain(z, x, y, walls())
    xx, yy = ter.cell_xy()
    h0 = np.where((xx - 60.0) ** 2 + (yy - 100.0) ** 2 < 30.0**2, 5.0, 0.0)
    (a, _), (b, _) = run_both(ter, h0, 20.0)
    assert_same_state(a, b)


def test_bowl_at_rest_stays_at_rest_bit_for_bit():
    """A pile in a bowl under its friction threshold: neither kernel moves a grain."""
    x = np.arange(40) * 5.0 + 2.5
    xx, yy = np.meshgrid(x, x)
    z = 0.002 * ((xx - 100.0) ** 2 + (yy - 100.0) ** 2)
    ter = surface_terrain(z, x, x, walls())
    cx, cy = ter.cell_xy()
    h0 = np.where((cx - 100.0) ** 2 + (cy - 100.0) ** 2 < 40.0**2, 2.0, 0.0)
    for solver in pair(ter, params=(math.tan(math.radians(30.0)),), h_zero=1e-3):
        state = solver.new_state(h0)
        assert solver.advance(state, 50.0, stop_volume=-1.0) == "running"
        assert np.array_equal(state.h, h0)
        assert not state.hu.any() and not state.hv.any()


def test_contract_plane_cylinder_agrees(contract_dir):
    """The shared contract's plane_cylinder on both kernels: the same run, bit for bit."""
    base = load_scenario(contract_dir / "plane_cylinder.yaml")
    # order 1 on both (the grid's default is order 2, MUSCL-Hancock, which the face kernel has
    # not: tests/test_grid_order2.py compares their Heun)
    a = simulate(base.with_updates({"numerics.kernel": "faces", "numerics.order": 1}))
    b = simulate(base.with_updates({"numerics.kernel": "grid", "numerics.threads": 1,
                                    "numerics.order": 1}))
    assert b.solver.kernel_used == "grid"
    assert_same_state(a.state, b.state)
    assert a.summary["runout"] == b.summary["runout"]
    assert a.summary["mass_balance_error"] < 1e-12 and b.summary["mass_balance_error"] < 1e-12


def test_grid_is_the_default_on_square_grids_at_both_orders():
    plane = load_scenario(SCENARIOS / "plane_box_2d.yaml")
    ter_solver = simulate(plane.with_updates({"time.end": 1.0})).solver
    assert ter_solver.kernel_used == "grid"
    assert simulate(plane.with_updates({"time.end": 1.0, "numerics.order": 2})
                    ).solver.kernel_used == "grid"
    tri = load_scenario(SCENARIOS / "plane_cylinder_triangles.yaml")
    with pytest.raises(ScenarioError, match="numerics.kernel.*square grids"):
        simulate(tri.with_updates({"time.end": 1.0, "numerics.kernel": "grid"}))


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2,
                    reason="Numba has one thread on this machine (NUMBA_NUM_THREADS=1)")
@pytest.mark.parametrize("holes", [False, True])
def test_threads_give_the_same_answer_bit_for_bit(holes):
    """The serial passes (1 thread) and the parallel ones on 2 threads: the same bits,
    diagnostics included (rows are summed in order whatever the threads)."""
    z, x, y = valley(holes=holes)
    ter = surface_terrain(z, x, y, walls(x_max="outflow"))
    xx, yy = ter.cell_xy()
    h0 = np.where((xx - 60.0) ** 2 + (yy - 100.0) ** 2 < 30.0**2, 5.0, 0.0)
    params = np.array([math.tan(math.radians(18.0))])
    results = []
    for threads in (1, 2):
        solver = Solver(ter, Law.COULOMB, params, kernel="grid", threads=threads, h_zero=1e-3)
        solver._parallel_from = (0, 2)  # every step on threads, in blocks of 2 rows and more
        state = solver.new_state(h0)
        solver.advance(state, 30.0)
        results.append(state)
    a, b = results
    assert_same_state(a, b)
    assert np.array_equal(a.stats, b.stats)


def test_threads_field_and_cli(tmp_path):
    from avflow.cli import main

    sc = load_scenario(SCENARIOS / "plane_box_2d.yaml").with_updates(
        {"time.end": 2.0, "numerics.threads": 1})
    assert sc.numerics.threads == 1
    # threads never change the answer: they are not part of the scenario's identity
    assert sc.scenario_hash() == sc.with_updates({"numerics.threads": 2}).scenario_hash()
    out = tmp_path / "p.nc"
    assert main(["run", str(SCENARIOS / "plane_box_2d.yaml"), "--set", "time.end=2",
                 "--threads", "1", "-q", "-o", str(out)]) == 0


def test_released_buffers_are_rebuilt_and_the_run_goes_on_bit_for_bit():
    """simulate frees the kernel's work arrays after the loop; a later advance builds them
    again and continues exactly as a solver that never let them go."""
    z, x, y = valley()
    ter = surface_terrain(z, x, y, walls())
    xx, yy = ter.cell_xy()
    h0 = np.where((xx - 60.0) ** 2 + (yy - 100.0) ** 2 < 30.0**2, 5.0, 0.0)
    a_solver, b_solver = pair(ter, h_zero=1e-3)[1], pair(ter, h_zero=1e-3)[1]
    a, b = a_solver.new_state(h0), b_solver.new_state(h0)
    a_solver.advance(a, 10.0)
    b_solver.advance(b, 10.0)
    b_solver.release_buffers()
    assert b_solver._grid is None and b_solver.kernel_used == "grid"
    a_solver.advance(a, 20.0)
    b_solver.advance(b, 20.0)
    assert_same_state(a, b)


@pytest.mark.parametrize("holes", [False, True])
def test_work_buffers_are_copied_only_near_the_flow(holes):
    """Both kernels copy the state into their work buffers only where the flow comes near
    (the grid kernel per row a hull that grows, the face kernel each cell a step first
    touches), not the whole map at each call. Work buffers full of NaN between calls, with
    two flows in the same rows (hulls with gaps between them) and a second state on the
    same solvers (the face kernel's stamps kept from the first), change no bit: the two
    kernels agree, and the face kernel agrees with a fresh one; and the second state's
    flags are those of a fresh grid solver (a flag buffer kept by the solver once gave it
    the first state's flags where it never swept)."""
    z, x, y = valley(nx=80, holes=holes)
    ter = surface_terrain(z, x, y, walls(x_max="outflow"), nodata="wall")
    h0 = cylinder(ter, (60.0, 40.0), radius=20.0, thickness=4.0) \
        + cylinder(ter, (60.0, 160.0), radius=20.0, thickness=4.0) \
        + cylinder(ter, (250.0, 100.0), radius=15.0, thickness=3.0)
    faces, grid = pair(ter)
    for solver in (faces, grid):  # another flow, left in the buffers and the stamps
        first = solver.new_state(h0[::-1].copy())
        solver.advance(first, 30.0)
    reference, state = faces.new_state(h0), grid.new_state(h0)
    for t in np.linspace(2.0, 40.0, 12):
        for work in (grid._h_work, grid._hu_work, grid._hv_work,
                     faces._h_work, faces._hu_work, faces._hv_work):
            work.fill(np.nan)
        assert grid.advance(state, t) == faces.advance(reference, t)
        assert_same_state(reference, state)
    fresh_faces = pair(ter)[0]  # and the face kernel as a fresh solver runs it
    again = fresh_faces.new_state(h0)
    for t in np.linspace(2.0, 40.0, 12):
        fresh_faces.advance(again, t)
    assert_same_state(again, reference)
    fresh = Solver(ter, Law.COULOMB, np.array([math.tan(math.radians(20.0))]), kernel="grid",
                   threads=1)
    again = fresh.new_state(h0)
    for t in np.linspace(2.0, 40.0, 12):
        fresh.advance(again, t)
    np.testing.assert_array_equal(state.flag, again.flag)


def test_work_hull_holds_the_state_with_no_gap():
    """The hull of each row (:func:`_sync_work`) holds the state in every cell it covers,
    when the flow comes back to a row far from where it was (the gap copied too), and
    covers the swept cells of the rows around, one more column each side."""
    from avflow.numerics.square_grid import _sync_work

    nx, ny = 20, 4
    state = [np.arange(nx * ny, dtype=float) + k * 1000.0 for k in range(3)]
    work = [np.full(nx * ny, np.nan) for _ in range(3)]
    sync_lo, sync_hi = np.full(ny, nx), np.full(ny, -1)
    lo, hi = np.full(ny, nx), np.full(ny, -1)
    for r, (a, b) in ((1, (12, 14)), (1, (2, 3)), (2, (17, 19))):  # right, then far left
        lo[:], hi[:] = nx, -1
        lo[r], hi[r] = a, b
        _sync_work(nx, ny, r, r, lo, hi, sync_lo, sync_hi, *state, *work)
    assert list(zip(sync_lo, sync_hi)) == [(1, 15), (1, 19), (1, 19), (16, 19)]
    for q in range(ny):
        held = slice(q * nx + sync_lo[q], q * nx + sync_hi[q] + 1)
        for s, w in zip(state, work):
            np.testing.assert_array_equal(w[held], s[held])
        outside = np.r_[q * nx:held.start, held.stop:(q + 1) * nx]
        assert np.isnan(work[0][outside]).all()  # nothing copied beyond the hull


@pytest.mark.parametrize("threads", [1, 2])
def test_ring_buffers_kept_from_call_to_call_change_no_bit(threads):
    """The kernel's ring buffers are made once per solver (a set per thread) and reused by
    every block of every step: filled with NaN, and with FLOWING flags, between calls, they
    change no bit against the face kernel, on one thread and on two (every step in blocks of
    2 rows and more)."""
    if threads > numba.config.NUMBA_NUM_THREADS:
        pytest.skip("Numba has one thread on this machine (NUMBA_NUM_THREADS=1)")
    from avflow.numerics.physics import FLOWING

    z, x, y = valley(nx=80)
    ter = surface_terrain(z, x, y, walls(x_max="outflow"), nodata="wall")
    h0 = cylinder(ter, (60.0, 40.0), radius=20.0, thickness=4.0) \
        + cylinder(ter, (60.0, 160.0), radius=20.0, thickness=4.0)
    faces, _ = pair(ter)
    grid = Solver(ter, Law.COULOMB, np.array([math.tan(math.radians(20.0))]), kernel="grid",
                  threads=threads)
    grid._parallel_from = (0, 2)
    reference, state = faces.new_state(h0), grid.new_state(h0)
    for t in np.linspace(2.0, 40.0, 12):
        assert grid.advance(state, t) == faces.advance(reference, t)
        assert_same_state(reference, state)
        rings = grid._g_rings
        assert rings.emit.shape[0] == threads
        for ring in rings:
            if ring.dtype == np.uint8:
                ring.fill(FLOWING if ring.ndim == 3 else 255)  # flags; the marks
            else:
                ring.fill(np.nan)
