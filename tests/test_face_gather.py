"""The face kernel's order-2 stage in gather form (avflow.numerics.face_gather), on threads.

Each pass writes only its own face or its own cell, and each cell sums its faces in index
order, the order in which kernels.step_faces (the reference: a scatter, each face added to
both its cells) meets them: so the two give the same bits, stage by stage, and the time
loop gives the same bits on 1 thread (step_faces) and on 2 (the gather form).
"""

import math

import numba
import numpy as np
import pytest

from avflow.numerics import face_gather as FG
from avflow.numerics import kernels as K
from avflow.numerics import physics, stepping
from avflow.numerics.reconstruction import Predictor, predict_cells, reconstruct_cells
from avflow.numerics.rheology import Law
from avflow.numerics.solver import Solver
from conftest import assert_same_runs, bump_on_a_slope, cylinder

def bits(a):
    """The bit patterns of a float array: -0.0 and +0.0 differ, NaN equals NaN."""
    return np.ascontiguousarray(a).view(np.int64)


def solver_for(terrain, law, params, **kw):
    """The face kernel at order 2 (on a square grid too, where auto takes the grid kernel)."""
    return Solver(terrain, law, np.array(params, dtype=float), order=2,
                  **{"kernel": "faces", **kw})


LAWS = [(Law.COULOMB, (math.tan(math.radians(20.0)),)),
        (Law.VOELLMY, (0.2, 500.0)),
        (Law.POULIQUEN, (math.tan(math.radians(20.0)), math.tan(math.radians(32.0)), 1.0,
                         0.136))]


@pytest.mark.parametrize("scheme", ["heun", "hancock"])
@pytest.mark.parametrize("mesh_kind", ["triangles", "grid"])
@pytest.mark.parametrize("law, params", LAWS, ids=["coulomb", "voellmy", "pouliquen"])
def test_a_stage_in_gather_form_is_step_faces(mesh_kind, law, params, scheme):
    """step_cells (serial, and on 2 threads) against step_faces on the same reconstructed
    stage (Heun's, or MUSCL-Hancock's: the sides predicted half a step on, gravity and
    friction at the midpoint), and heun_cells against heun_faces, at six times of an
    order-2 run with fronts, dry neighbours, Dirac faces, an open side and the film rule:
    state, flags, transport, fluxes of the active faces and every returned sum, bit for
    bit."""
    hancock = scheme == "hancock"
    terrain = bump_on_a_slope(mesh_kind)
    solver = solver_for(terrain, law, params, h_zero=1e-6, h_dry=0.01, time_scheme=scheme)
    state = solver.new_state(cylinder(terrain, (60.0, 100.0), radius=40.0, thickness=6.0))
    m = terrain.mesh
    n, n_faces = m.n_cells, m.n_faces
    active = np.empty(n_faces, dtype=np.int64)
    touched = np.empty(n, dtype=np.int64)
    stamps = (np.full(n_faces, -1, dtype=np.int64), np.full(n, -1, dtype=np.int64))
    flags_seen = set()
    outflow = 0.0
    threads = numba.get_num_threads()
    for k, t in enumerate((0.0, 1.0, 4.0, 9.0, 16.0, 24.0)):
        solver.advance(state, t)
        h, hu, hv = state.h, state.hu, state.hv
        wet = np.flatnonzero(h > solver.h_zero)
        n_active, n_touched = K.activate(wet, wet.size, solver._cell_face_ptr,
                                         solver._cell_face_idx, m.face_cells, *stamps, k,
                                         active, touched)
        face_state = np.full((n_faces, 2, 7 if hancock else 3), np.nan)
        limit = K.dt_limit(solver._cfl_factor, terrain.gamma_z, h, hu, hv, solver.gravity)
        dt = 0.5 * limit
        fm = solver._face_mesh
        predictor = Predictor(0.5 * dt, fm.gamma_x, fm.gamma_y, fm.gamma_z, fm.curvature,
                              int(law), solver._rows, solver.gravity, fm.density)
        (predict_cells if hancock else reconstruct_cells)(
            m.face_cells, m.face_frame, m.face_length, solver._face_offset, m.cell_area, h, hu,
            hv, solver.h_zero, solver._cell_face_ptr, solver._cell_face_idx, touched,
            n_touched, np.zeros((n, 2)), face_state, predictor)
        timing = physics.MIDPOINT if hancock else True
        state_n = stepping.Conserved(h, hu, hv)
        when = stepping.StepTime(dt, dt, t + dt)
        lists = stepping.Lists(active, n_active, touched, n_touched, False, stamps[0], k)
        outs = []
        for kind in ("step_faces", "serial", "parallel"):
            new = [np.full(n, np.nan) for _ in range(3)]
            flux = np.full((n_faces, 5), np.nan)
            transport = np.full(n, np.nan)
            flag = state.flag.copy()
            phys = stepping.Physics(int(law), solver._rows, solver.gravity, True,
                                    solver.h_dry, solver.h_zero, solver._source)
            if kind == "step_faces":
                r = K.step_faces(solver._face_mesh, phys, state_n, stepping.Conserved(*new),
                                 flux, transport, flag, when, lists, timing, face_state,
                                 np.zeros((0, 7)))
            else:
                step = FG.step_cells_serial if kind == "serial" else FG.step_cells_parallel
                numba.set_num_threads(2 if kind == "parallel" else threads)
                try:
                    r = step(solver._face_mesh, phys, state_n, stepping.Conserved(*new), flux,
                             transport, flag, when, lists, face_state,
                             np.full((n, FG.N_SUMS), np.nan), timing)
                finally:
                    numba.set_num_threads(threads)
            # Heun's average of this stage with the state (as the second stage's merge)
            avg = [np.full(n, np.nan) for _ in range(3)]
            cells = touched[:n_touched]
            args = (cells, n_touched, solver._face_mesh, phys, state_n,
                    stepping.Conserved(*new), state.flag, transport, stepping.Conserved(*avg))
            if kind == "step_faces":
                rh = K.heun_faces(*args)
            else:
                heun = FG.heun_cells_serial if kind == "serial" else FG.heun_cells_parallel
                numba.set_num_threads(2 if kind == "parallel" else threads)
                try:
                    rh = heun(*args, np.full((n, FG.N_SUMS), np.nan))
                finally:
                    numba.set_num_threads(threads)
            outs.append((r, rh, new, flag, transport, flux[active[:n_active]], avg))
        ref = outs[0]
        assert ref[0][0], f"t = {t}: the stage failed"
        for kind, out in zip(("serial", "parallel"), outs[1:]):
            where = f"{kind}, t = {t}"
            assert out[0] == ref[0], where
            assert out[1] == ref[1], where
            for name, a, b in zip(("h", "hu", "hv"), ref[2], out[2]):
                np.testing.assert_array_equal(bits(a[cells]), bits(b[cells]),
                                              err_msg=f"{name}, {where}")
            np.testing.assert_array_equal(ref[3], out[3], err_msg=f"flags, {where}")
            np.testing.assert_array_equal(bits(ref[4][cells]), bits(out[4][cells]),
                                          err_msg=f"transport, {where}")
            np.testing.assert_array_equal(bits(ref[5]), bits(out[5]), err_msg=f"flux, {where}")
            for name, a, b in zip(("h", "hu", "hv"), ref[6], out[6]):
                np.testing.assert_array_equal(bits(a[cells]), bits(b[cells]),
                                              err_msg=f"Heun's {name}, {where}")
        flags_seen.update(np.unique(ref[3][cells]).tolist())
        outflow += ref[0][1]
    assert {physics.FLOWING, physics.UNDER_THRESHOLD, physics.DRY} <= flags_seen or law != Law.COULOMB
    if mesh_kind == "grid" and law != Law.POULIQUEN:  # (Pouliquen's mass is still on its way)
        assert outflow > 0.0


@pytest.mark.parametrize("scheme", ["heun", "hancock"])
@pytest.mark.parametrize("mesh_kind", ["triangles", "grid"])
def test_one_and_two_threads_give_the_same_run(mesh_kind, scheme):
    """The order-2 time loop on the face kernel, 1 thread (step_faces, heun_faces) against
    2 (every stage and merge in gather form: the threshold lowered to 1 cell), in calls of
    a few output times, with fronts, cells stopping, Heun's fallbacks (MUSCL-Hancock has
    none) and an open side: every state variable, flag, observer and statistic bit for bit;
    and the threads are those reported."""
    runs = []
    for threads in (1, 2):
        terrain = bump_on_a_slope(mesh_kind)
        solver = solver_for(terrain, *LAWS[0], h_zero=1e-6, h_dry=0.01, threads=threads,
                            kernel="faces", time_scheme=scheme)
        solver._gather_from = 1
        assert solver.threads_used() == min(threads, numba.config.NUMBA_NUM_THREADS)
        state = solver.new_state(cylinder(terrain, (60.0, 100.0), radius=40.0, thickness=6.0))
        stamps = []
        for t in (0.5, 3.0, 7.0, 12.0, 20.0, 26.0):
            solver.advance(state, t)
            stamps.append(state.h.copy())
        runs.append((state, stamps))
    assert_same_runs(runs)
    a = runs[0][0]
    assert a.stats[stepping.ST_STEPS] > 50
    assert (a.stats[stepping.ST_FALLBACK] > 0) == (scheme == "heun")
    assert physics.UNDER_THRESHOLD in a.flag
    if mesh_kind == "grid":
        assert a.stats[stepping.ST_OUTFLOW] > 0.0
