"""The face kernel's order-1 step with vectorised cell passes (avflow.numerics.face_sweep)
against its reference, kernels.step_faces, step after step on triangles and on a DEM: the
same bits everywhere (state, flags, and every value the step returns). So is its
step on threads (face_sweep._step_threads: each thread scatters into the cells of its own
piece of the faces, the cells shared by two pieces sum their faces afterwards), run
serially and on 2 threads, its lists cut into pieces of a few cells (pieces_of) so that
every case spans several pieces, runs are cut mid-way, and most cells are shared (32 pieces
of the faces) or a few (2 pieces).

Each step lists the active faces and touched cells as the time loop does, runs both kernels
on copies of the same state, compares, and goes on from the new kernel's state: a flow
that sets off, spreads over dry cells, leaves through an open side, and stops in part
(Dirac faces between cells under the Coulomb threshold).
"""

import math
from types import SimpleNamespace as NS

import numba
import numpy as np
import pytest

from avflow.numerics import face_sweep
from avflow.numerics import kernels as K
from avflow.numerics import physics, stepping
from avflow.numerics.rheology import Law
from avflow.numerics.solver import Solver
from avflow.numerics.vectorize import law_kind
from avflow.terrain.bed import surface_terrain
from avflow.terrain.trimesh import plane_triangle_terrain, triangle_terrain

from conftest import assert_same_runs, bump_on_a_slope, cylinder, walls

G = 9.81
OBSERVERS = ("peak_h", "peak_speed", "arrival", "last_moved")
#: The kernels compare_steps runs at every step: step_faces, face_sweep._step, and its step
#: on threads compiled serially and with threads (32 pieces of the faces), and with 2
#: step_faces, face_sweep._step (the Dirac pass swept over the faces, or gathered by each
#: cell at zero temperature), the step on threads compiled serially and on 2 threads
THREAD_KERNELS = ("pieces serially", "2 threads", "2 threads, 2 pieces")
KERNELS = ("reference", "vectorised", "vectorised, cold cells gathered") + THREAD_KERNELS
#: the kernels whose Dirac pass is gathered by the cells at zero temperature (the others
#: sweep the faces whenever a cell is cold)
GATHERED = ("vectorised, cold cells gathered", "2 threads")


def bits(a):
    """The bit patterns of a float array: -0.0 and +0.0 differ, NaN equals NaN."""
    return np.ascontiguousarray(a).view(np.int64)


def compare_steps(terrain, law, params, h0, n_steps, *, h_zero=0.0, h_dry=0.0, dirac=True,
                  same_lists=0, all_flowing=0):
    """Run ``n_steps`` order-1 steps with every kernel; returns the last state's h, the
    flags seen (to check that the case reached what it is meant to test) and the volume
    out. Checks that at least ``same_lists`` steps ran on the last step's lists, and
    ``all_flowing`` steps with every touched cell flowing (those skip the Dirac pass)."""
    solver = Solver(terrain, law, np.array(params, dtype=float), kernel="faces", h_zero=h_zero,
                    h_dry=h_dry, dirac=dirac)
    state = solver.new_state(h0)
    mesh = terrain.mesh
    n, n_faces = mesh.n_cells, mesh.n_faces
    kind = law_kind(int(law))
    step_new = face_sweep.STEP[kind]
    # the step on threads: its geometry and work arrays (one a kernel: each keeps what it
    # made of the last step's lists), its lists cut into pieces of 8 or more, the faces into
    # 32 pieces (most cells shared) or 2 (a band at one cut)
    geo = face_sweep.geometry(terrain.mesh, 1.0 / terrain.mesh.cell_area, terrain.curvature,
                              solver._cell_face_ptr, solver._cell_face_idx, True)
    never = 1 << 40
    works = {kernel: face_sweep.work(n, n_faces, 2, min_piece=8, max_pieces=32,
                                     face_pieces=2 if kernel.endswith("2 pieces") else 32,
                                     cold_gather=0 if kernel in GATHERED else never)
             for kernel in THREAD_KERNELS}
    works["vectorised"] = face_sweep.work(n, n_faces, cold_gather=never)
    works["vectorised, cold cells gathered"] = face_sweep.work(n, n_faces, cold_gather=0)
    steps_with_cold = 0
    last_wet = None
    steps_on_the_same_lists = 0
    steps_all_flowing = 0
    out_all_flowing = 0.0  # what left in those steps (the face pass sums it)
    wet_changes_seen = False
    shares = set()  # (kernel, some cell shared, some not)
    threads = numba.get_num_threads()
    pieces_seen = 0
    active = np.empty(n_faces, dtype=np.int64)
    touched = np.empty(n, dtype=np.int64)
    face_stamp = np.full(n_faces, -1, dtype=np.int64)
    cell_stamp = np.full(n, -1, dtype=np.int64)
    emit = np.zeros((n, 7))
    h, hu, hv, flag = state.h.copy(), state.hu.copy(), state.hv.copy(), state.flag.copy()
    t = 0.0
    flags_seen = set()
    outflow = 0.0
    for k in range(n_steps):
        wet = np.flatnonzero(h > h_zero).astype(np.int64)
        # the lists are the last step's (activate lists the same wet cells alike): the
        # kernels run on what they kept of them, as in the time loop
        same = last_wet is not None and np.array_equal(wet, last_wet)
        steps_on_the_same_lists += same
        last_wet = wet
        n_active, n_touched = K.activate(wet, wet.size, solver._cell_face_ptr,
                                         solver._cell_face_idx, mesh.face_cells, face_stamp,
                                         cell_stamp, k, active, touched)
        limit = K.dt_limit(solver._cfl_factor, terrain.gamma_z, h, hu, hv, G)
        dt = 0.5 * limit if np.isfinite(limit) else 0.1
        t_new = t + dt
        # a face not listed holds no flux of this step: its mass in the kernels' work
        # arrays made NaN, so a kernel that reads it fails (the time loop's buffers hold
        # what earlier steps and calls left there)
        unlisted = face_stamp != k
        for wk in works.values():
            wk.mass[unlisted] = np.nan
        results, outputs = [], []
        for kernel in KERNELS:
            new = [h.copy(), hu.copy(), hv.copy()]  # the buffers agree where nothing is touched
            fl = flag.copy()
            flux = np.zeros((n_faces, 5))
            transport = np.zeros(n)
            phys = stepping.Physics(int(law), solver._rows, G, dirac, h_dry, h_zero,
                                    solver._source)
            cur, nxt = stepping.Conserved(h, hu, hv), stepping.Conserved(*new)
            when = stepping.StepTime(dt, dt, t_new)
            lists = stepping.Lists(active, n_active, touched, n_touched, same, face_stamp, k)
            if kernel == "reference":
                r = K.step_faces(solver._face_mesh, phys, cur, nxt, flux, transport, fl, when,
                                 lists, False, np.zeros((0, 2, 3)), emit)
            else:
                step, sweep = step_new, (solver._sweep.geometry, works[kernel])
                if kernel in THREAD_KERNELS:
                    step = (face_sweep.STEP_PIECES_SERIAL[kind] if kernel == "pieces serially"
                            else face_sweep.STEP_THREADS[kind])
                    sweep = (geo, works[kernel])
                    numba.set_num_threads(1 if kernel == "pieces serially" else 2)
                try:
                    r = step(solver._face_mesh, phys, cur, nxt, transport, fl, when, lists,
                             *sweep)
                finally:
                    numba.set_num_threads(threads)
            results.append(r)
            outputs.append((new, fl))
            if kernel in THREAD_KERNELS:
                wk = sweep[1]  # a cell shared in this step carries its number
                shared = wk.shared_mark[touched[:n_touched]] == wk.cut[face_sweep.CUT_MARK]
                shares.add((kernel, bool(shared.any()), not shared.all()))
        (ref_new, ref_fl) = outputs[0]
        if np.all(ref_fl[touched[:n_touched]] == physics.FLOWING):
            steps_all_flowing += 1
            out_all_flowing += results[0][1]
        else:
            steps_with_cold += 1
        assert results[0][0], f"step {k} failed"
        for kernel, r, (vec_new, vec_fl) in zip(KERNELS[1:], results[1:], outputs[1:]):
            where = f"{kernel}, step {k}"
            assert results[0] == r[:7], f"{where}: {results[0]} != {r}"
            # and the touched cells that became wet or dry
            was, now = h[touched[:n_touched]] > h_zero, vec_new[0][touched[:n_touched]] > h_zero
            assert r[7] == np.count_nonzero(was != now), where
            wet_changes_seen |= r[7] > 0
            for name, a, b in zip(("h", "hu", "hv"), ref_new, vec_new):
                np.testing.assert_array_equal(bits(a), bits(b), err_msg=f"{name}, {where}")
            np.testing.assert_array_equal(ref_fl, vec_fl, err_msg=f"flags, {where}")
        runs = np.empty(2 * (n + n_faces) + 4, dtype=np.int64)
        pieces_seen = max(pieces_seen, face_sweep.pieces_of(
            runs, face_sweep.runs_of(touched, n_touched, runs), n_touched, 8, 32,
            np.empty(2 * (n_touched + 32), dtype=np.int64), np.empty(33, dtype=np.int64)))
        h, hu, hv = vec_new
        flag, t = vec_fl, t_new
        outflow += results[1][1]
        flags_seen.update(np.unique(flag[touched[:n_touched]]).tolist())
    assert pieces_seen >= 4  # the cell passes on threads ran on several pieces
    # every cell shared at times with 32 pieces of the faces, some and not all with 2
    assert {k for k, some, _ in shares if some} == set(THREAD_KERNELS), shares
    assert ("2 threads, 2 pieces", True, True) in shares, shares
    assert steps_on_the_same_lists >= same_lists
    assert steps_all_flowing >= all_flowing, steps_all_flowing
    assert steps_with_cold > 0  # (the Dirac pass, swept and gathered, ran)
    assert out_all_flowing > 0.0 or all_flowing == 0
    assert wet_changes_seen or same_lists == n_steps - 1
    return h, flags_seen, outflow


def tri_block(slope, azimuth, x=(0.0, 600.0), y=(0.0, 300.0)):
    return NS(slope_deg=slope, azimuth_deg=azimuth, extent=NS(x=list(x), y=list(y)),
              elevation_at_center=1000.0)


def test_triangles_on_a_plane_with_an_open_side():
    """Coulomb on a 30 degree plane facing 20 degrees off the axes: the flow spreads over
    dry nodes and part of it leaves through the open lower side."""
    ter = plane_triangle_terrain(tri_block(30.0, 70.0), 10.0, None, walls(x_max="outflow"))
    h0 = cylinder(ter, (500.0, 150.0), radius=60.0, thickness=10.0)
    h, flags, outflow = compare_steps(ter, Law.COULOMB, (math.tan(math.radians(20.0)),), h0,
                                      60)
    assert outflow > 0.0
    assert {physics.FLOWING, physics.DRY} <= flags


@pytest.mark.parametrize("law,params", [
    (Law.VOELLMY, (0.2, 500.0)),
    (Law.POULIQUEN, (math.tan(math.radians(20.0)), math.tan(math.radians(32.0)), 1.0, 0.136))])
def test_triangles_on_a_curved_bed(law, params):
    """A bump on a 20 degree slope, refined where it curves: every node has its own tangent
    basis (the frames carry velocities across faces) and the curvature term acts. Voellmy
    runs its own copy of the cell passes, Pouliquen the copy that reads the law."""
    x, y = np.arange(0.0, 401.0, 10.0), np.arange(0.0, 201.0, 10.0)
    xx, yy = np.meshgrid(x, y)
    z = -math.tan(math.radians(20.0)) * xx + 30.0 * np.exp(
        -((xx - 250.0) ** 2 + (yy - 100.0) ** 2) / 50.0**2)
    ter = triangle_terrain(z, x, y, walls(), pattern="alternate", refine_angle_deg=4.0,
                           refine_levels=1)
    h0 = cylinder(ter, (120.0, 100.0), radius=40.0, thickness=8.0)
    compare_steps(ter, law, params, h0, 50, h_zero=1e-6, h_dry=0.01)


def test_triangles_stopping_in_part():
    """A pile on a 22 degree plane with a 21 degree friction angle: its thin margins stay
    under the Coulomb threshold (Dirac faces between them), the core flows."""
    ter = plane_triangle_terrain(tri_block(22.0, 90.0), 10.0, None, walls())
    xx, yy = ter.cell_xy()
    r = np.hypot(xx - 300.0, yy - 150.0)
    h0 = np.clip(12.0 * (1.0 - r / 90.0), 0.0, None)
    h, flags, _ = compare_steps(ter, Law.COULOMB, (math.tan(math.radians(21.0)),), h0, 40)
    assert physics.UNDER_THRESHOLD in flags and physics.FLOWING in flags


def test_square_grid_dem_on_the_face_kernel():
    """The face kernel on a curved DEM's square grid (bed-linked frames, curvature), with
    the film rule and an open lower side."""
    x = np.arange(40) * 5.0 + 2.5
    y = np.arange(30) * 5.0 + 2.5
    xx, yy = np.meshgrid(x, y)
    z = 600.0 - 0.7 * xx + 0.004 * (yy - y.mean()) ** 2
    ter = surface_terrain(z, x, y, walls(x_max="outflow"))
    h0 = cylinder(ter, (150.0, 75.0), radius=25.0, thickness=6.0)
    _, _, outflow = compare_steps(ter, Law.COULOMB, (math.tan(math.radians(18.0)),), h0, 80,
                                  h_zero=1e-6, h_dry=0.01)
    assert outflow > 0.0


def test_triangles_covering_their_mesh():
    """A layer over the whole mesh, a pile on it, an open side: every step after the first
    runs on the last step's lists (the time loop's same wet cells), on what the kernels
    kept of them (their runs, pieces and shared cells). In 12 of its steps every node
    flows: those skip the Dirac pass, and take the outflow from the face pass."""
    ter = plane_triangle_terrain(tri_block(25.0, 70.0), 10.0, None, walls(x_max="outflow"))
    h0 = 0.5 + cylinder(ter, (300.0, 150.0), radius=60.0, thickness=6.0)
    _, flags, outflow = compare_steps(ter, Law.COULOMB, (math.tan(math.radians(20.0)),), h0,
                                      30, same_lists=29, all_flowing=10)
    assert outflow > 0.0 and physics.FLOWING in flags


def test_classical_scheme_without_dirac_faces():
    """dirac=False (the classical kinetic scheme): no face is ever Dirac."""
    ter = plane_triangle_terrain(tri_block(25.0, 90.0), 10.0, None, walls())
    h0 = cylinder(ter, (300.0, 150.0), radius=50.0, thickness=5.0)
    compare_steps(ter, Law.COULOMB, (math.tan(math.radians(24.0)),), h0, 30, dirac=False)


def list_terrain(mesh_kind):
    """A mesh for the tests of the active lists: triangles with an open side, or a DEM grid
    with an open side and a NODATA hole (walls inside the map)."""
    if mesh_kind == "triangles":
        return plane_triangle_terrain(tri_block(20.0, 70.0), 10.0, None, walls(x_max="outflow"))
    x = np.arange(50) * 5.0 + 2.5
    y = np.arange(37) * 5.0 + 2.5
    xx, yy = np.meshgrid(x, y)
    z = 600.0 - 0.5 * xx + 0.01 * (yy - 90.0) ** 2
    z[15:20, 30:34] = np.nan
    return surface_terrain(z, x, y, walls(y_min="outflow"))


def faces_of_wet_cells(fc, n, wet):
    """numpy's answer: the faces with a wet side, and the cells on the sides of those."""
    is_wet = np.zeros(n, dtype=bool)
    is_wet[wet] = True
    want = np.flatnonzero(is_wet[fc[:, 0]] | ((fc[:, 1] >= 0) & is_wet[np.maximum(fc[:, 1], 0)]))
    sides = np.concatenate([fc[want, 0], fc[want, 1]])
    return want, np.unique(sides[sides >= 0])


@pytest.mark.parametrize("mesh_kind", ["triangles", "grid"])
def test_active_lists_are_the_faces_of_the_wet_cells_in_order(mesh_kind):
    """kernels.activate against numpy: the faces with a wet side and the cells on both
    sides of those, each once and sorted, for wet sets from one cell to all of them and
    scattered ones, stamp after stamp (the stamps of earlier lists never leak in)."""
    ter = list_terrain(mesh_kind)
    solver = Solver(ter, Law.COULOMB, np.array([0.3]), kernel="faces")
    mesh = ter.mesh
    fc = mesh.face_cells
    n, n_faces = mesh.n_cells, mesh.n_faces
    active = np.empty(n_faces, dtype=np.int64)
    touched = np.empty(n, dtype=np.int64)
    face_stamp = np.full(n_faces, -1, dtype=np.int64)
    cell_stamp = np.full(n, -1, dtype=np.int64)
    rng = np.random.default_rng(7)
    xx, yy = ter.cell_xy()
    sets = [np.array([0]), np.array([n - 1]), np.arange(n), np.array([], dtype=np.int64)]
    sets += [np.flatnonzero(rng.random(n) < p) for p in (0.001, 0.05, 0.5)]
    sets += [np.flatnonzero(np.hypot(xx - cx, yy - 100.0) < 40.0) for cx in (60.0, 200.0)]
    for stamp, wet in enumerate(sets):
        wet = wet.astype(np.int64)
        n_active, n_touched = K.activate(wet, wet.size, solver._cell_face_ptr,
                                         solver._cell_face_idx, fc, face_stamp, cell_stamp,
                                         stamp, active, touched)
        want, want_cells = faces_of_wet_cells(fc, n, wet)
        np.testing.assert_array_equal(active[:n_active], want)
        np.testing.assert_array_equal(touched[:n_touched], want_cells)
        assert np.all(face_stamp[want] == stamp)
        assert np.all(cell_stamp[touched[:n_touched]] == stamp)


@pytest.mark.parametrize("mesh_kind", ["triangles", "grid"])
def test_mended_lists_are_those_listed_from_scratch(mesh_kind):
    """kernels.relist mends the last active lists after some cells became wet and others
    dry: the same lists as numpy's (and activate's), sorted, with the cells that joined
    and left the touched list, and only the listed faces and cells marked, along a chain
    of wet sets that grow, shrink, move, split and jump (a change as large as the set)."""
    ter = list_terrain(mesh_kind)
    solver = Solver(ter, Law.COULOMB, np.array([0.3]), kernel="faces")
    mesh = ter.mesh
    fc = mesh.face_cells
    n, n_faces = mesh.n_cells, mesh.n_faces
    bufs = [np.empty(n_faces, dtype=np.int64) for _ in range(2)]
    cells = [np.empty(n, dtype=np.int64) for _ in range(2)]
    fresh_faces, gone_faces = np.empty((2, n_faces), dtype=np.int64)
    added = np.empty(n, dtype=np.int64)
    dropped = np.empty(2 * n_faces, dtype=np.int64)
    face_stamp = np.full(n_faces, -1, dtype=np.int64)
    cell_stamp = np.full(n, -1, dtype=np.int64)
    xx, yy = ter.cell_xy()
    rng = np.random.default_rng(11)
    chain = [np.flatnonzero(np.hypot(xx - 150.0, yy - 100.0) < r) for r in (30.0, 45.0, 60.0)]
    chain += [np.flatnonzero(np.hypot(xx - cx, yy - 100.0) < 50.0) for cx in (160.0, 175.0)]
    ring = np.hypot(xx - 175.0, yy - 100.0)
    chain += [np.flatnonzero((ring < 50.0) & (ring > 20.0)),          # a hole opens
              np.flatnonzero((ring < 50.0) & (np.abs(xx - 175.0) > 8.0)),  # and splits
              np.flatnonzero(rng.random(n) < 0.02),                   # a jump
              np.flatnonzero(rng.random(n) < 0.02), np.arange(n), np.array([0, n - 1]),
              np.array([], dtype=np.int64), np.array([n // 2])]
    stamp = 5
    first = chain[0].astype(np.int64)
    n_active, n_touched = K.activate(first, first.size, solver._cell_face_ptr,
                                     solver._cell_face_idx, fc, face_stamp, cell_stamp, stamp,
                                     bufs[0], cells[0])
    last = first
    for k, wet in enumerate(chain[1:]):
        wet = wet.astype(np.int64)
        gained = np.setdiff1d(wet, last)
        lost = np.setdiff1d(last, wet)
        h = np.zeros(n)
        h[wet] = 1.0
        old_cells = cells[k % 2][:n_touched].copy()
        n_active, n_touched, n_joined, n_dropped = K.relist(
            gained, gained.size, lost, lost.size, h, 0.0, solver._cell_face_ptr,
            solver._cell_face_idx, fc, face_stamp, cell_stamp, stamp, bufs[k % 2], n_active,
            cells[k % 2], n_touched, bufs[(k + 1) % 2], cells[(k + 1) % 2], fresh_faces, gone_faces,
            added, dropped)
        want, want_cells = faces_of_wet_cells(fc, n, wet)
        np.testing.assert_array_equal(bufs[(k + 1) % 2][:n_active], want, err_msg=f"set {k + 1}")
        np.testing.assert_array_equal(cells[(k + 1) % 2][:n_touched], want_cells)
        np.testing.assert_array_equal(added[:n_joined], np.setdiff1d(want_cells, old_cells))
        np.testing.assert_array_equal(dropped[:n_dropped], np.setdiff1d(old_cells, want_cells))
        np.testing.assert_array_equal(np.flatnonzero(face_stamp == stamp), want)
        np.testing.assert_array_equal(np.flatnonzero(cell_stamp == stamp), want_cells)
        last = wet


def test_the_time_loop_lists_again_only_when_the_wet_cells_change():
    """The face kernel's time loop keeps the active lists of the last step while the wet
    cells stay the same, and mends them where a few changed: the same bits as a loop that
    lists them from scratch every step (one step a call), for a flow that covers the whole
    mesh, one that spreads and stops in part, and one that slides down a steep plane,
    leaving dry cells behind it (a film under h_zero). The stamps show which step listed
    from the wet cells last."""
    covered = plane_triangle_terrain(tri_block(20.0, 70.0), 10.0, None, walls())
    spreading = plane_triangle_terrain(tri_block(22.0, 90.0), 10.0, None, walls())
    steep = plane_triangle_terrain(tri_block(35.0, 90.0), 10.0, None, walls())
    xx, yy = spreading.cell_xy()
    pile = np.clip(12.0 * (1.0 - np.hypot(xx - 300.0, yy - 150.0) / 90.0), 0.0, None)
    for ter, h0, h_zero in ((covered, 1.0 + cylinder(covered, (300.0, 150.0), 60.0, 5.0), 0.0),
                            (spreading, pile, 0.0),
                            (steep, cylinder(steep, (150.0, 150.0), 50.0, 4.0), 1e-3)):
        runs = []
        dried = 0
        for one_step_a_call in (False, True):
            solver = Solver(ter, Law.COULOMB, np.array([math.tan(math.radians(21.0))]),
                            kernel="faces", h_zero=h_zero)
            state = solver.new_state(h0)
            if one_step_a_call:
                while state.steps < 60:
                    was_wet = state.h > h_zero
                    solver.advance(state, 1e9, max_steps=state.steps + 1)
                    dried += np.count_nonzero(was_wet & (state.h <= h_zero))
            else:
                solver.advance(state, 1e9, max_steps=60)
                # the stamp of the last step that listed from the wet cells: the covered
                # mesh's first; the flows that spread and slide change more than
                # K.RELIST_SHARE of their few wet cells in their first steps, then only mend
                assert solver._face_stamp.max() == (0 if ter is covered else 2)
            assert state.steps == 60
            runs.append(state)
        if ter is steep:  # what this case is for: cells leave the lists
            assert dried > 50
        for name in ("h", "hu", "hv", "flag", *OBSERVERS):
            np.testing.assert_array_equal(bits(getattr(runs[0], name).astype(float)),
                                          bits(getattr(runs[1], name).astype(float)),
                                          err_msg=name)
        np.testing.assert_array_equal(runs[0].stats, runs[1].stats)


@pytest.mark.parametrize("mesh_kind, law, params", [
    ("triangles", Law.COULOMB, (math.tan(math.radians(20.0)),)),
    ("grid", Law.COULOMB, (math.tan(math.radians(20.0)),)),
    ("triangles", Law.POULIQUEN, (math.tan(math.radians(20.0)), math.tan(math.radians(32.0)),
                                  1.0, 0.136))], ids=["triangles", "grid", "pouliquen"])
def test_one_and_two_threads_give_the_same_run(mesh_kind, law, params):
    """The order-1 time loop on the face kernel, 1 thread (face_sweep._step) against 2
    (every step on the threads: the threshold lowered to 1 cell, the lists cut into pieces
    of 8 cells or more, the faces into 8), in calls of a few output times, with fronts, cells
    stopping, the film rule and (grid) a NODATA hole and an open side: every state
    variable, flag, observer and statistic bit for bit; and the threads are those
    reported."""
    runs = []
    for threads in (1, 2):
        terrain = bump_on_a_slope(mesh_kind)
        solver = Solver(terrain, law, np.array(params, dtype=float), kernel="faces",
                        h_zero=1e-6, h_dry=0.01, threads=threads)
        assert solver.threads_used() == min(threads, numba.config.NUMBA_NUM_THREADS)
        if threads > 1:
            m = terrain.mesh
            solver._gather_from = 1
            solver._sweep = solver._sweep._replace(work=face_sweep.work(
                m.n_cells, m.n_faces, 2, min_piece=8, max_pieces=32, face_pieces=8))
        state = solver.new_state(cylinder(terrain, (60.0, 100.0), radius=40.0, thickness=6.0))
        snapshots = []
        for t in (0.5, 3.0, 7.0, 12.0, 20.0, 30.0):
            solver.advance(state, t)
            snapshots.append(state.h.copy())
        runs.append((state, snapshots))
    assert_same_runs(runs)
    a = runs[0][0]
    assert a.stats[stepping.ST_STEPS] > 50
    assert physics.UNDER_THRESHOLD in a.flag
    if mesh_kind == "grid":
        assert a.stats[stepping.ST_OUTFLOW] > 0.0


def test_a_solver_reused_for_another_release_on_threads_gives_its_own_run():
    """A solver's work buffers hold the cells of its last run where this one has not touched
    them yet (they take a cell's state when a step first touches it): the step on threads
    must not read them. A big release, then a small one on the same solver, on 2 threads
    (every step on the threads), against the small one on a fresh solver on 1 thread."""
    ter = plane_triangle_terrain(tri_block(25.0, 90.0, x=(0.0, 800.0), y=(0.0, 400.0)), 10.0,
                                 None, walls())
    big = cylinder(ter, (400.0, 200.0), radius=150.0, thickness=15.0)
    small = cylinder(ter, (500.0, 200.0), radius=60.0, thickness=8.0)
    params = np.array([math.tan(math.radians(22.0))])

    def run(solver, h0):
        state = solver.new_state(h0)
        for t in (1.0, 3.0, 6.0):
            solver.advance(state, t, max_steps=1000)  # (a run gone wrong takes 1e5 steps)
        return state

    reused = Solver(ter, Law.COULOMB, params, kernel="faces", threads=2)
    reused._gather_from = 1
    run(reused, big)
    a = run(reused, small)
    b = run(Solver(ter, Law.COULOMB, params, kernel="faces", threads=1), small)
    for name in ("h", "hu", "hv", *OBSERVERS, "stats"):
        np.testing.assert_array_equal(bits(getattr(a, name)), bits(getattr(b, name)),
                                      err_msg=name)


def test_the_step_on_threads_runs_where_its_pieces_stay_local():
    """On 2 threads, the order-1 face step runs on them from MIN_PARALLEL_CELLS touched
    cells on triangles over a raster, whose cells' faces span a few rows of faces; on a
    square grid, whose x faces come before its y faces (a cell's faces span half of them,
    so two pieces would share nearly every cell), and on a small refined mesh, whose new
    nodes come last, it stays on one thread, its work arrays without the lines for
    threads."""
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("Numba has one thread here")
    params = np.array([math.tan(math.radians(20.0))])
    raster = plane_triangle_terrain(tri_block(25.0, 70.0), 10.0, None, walls())
    for name, terrain, local in (("raster triangles", raster, True),
                                 ("grid", bump_on_a_slope("grid"), False),
                                 ("refined triangles", bump_on_a_slope("triangles"), False)):
        solver = Solver(terrain, Law.COULOMB, params, kernel="faces", threads=2)
        geo, wk = solver._sweep
        span, n_faces = int(geo.span[0]), terrain.mesh.n_faces
        assert face_sweep.pieces_stay_local(geo, n_faces, 2) is local, (name, span, n_faces)
        if local:
            assert 4 * span <= n_faces
            assert solver._gather_from == face_sweep.MIN_PARALLEL_CELLS
            assert wk.side.shape == (4, n_faces)
        else:
            assert 4 * span > n_faces
            assert solver._gather_from > terrain.mesh.n_cells
            assert wk.side.shape == (4, 0)
