"""The time loop of the profile and face kernels (the square-grid kernel's is
:func:`avflow.numerics.square_grid.grid_loop`): step size, retry by halving, stop rules,
observers, Heun's two stages and merge at order 2, and the active lists of the faces.

:func:`_advance` is a template compiled per mesh kind, order, law kind and threads by
:func:`_advance_for` (:func:`avflow.numerics.vectorize.specialize`): Numba drops the
branches of the other kinds before it types a copy, so a run compiles only what it uses.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from avflow.numerics.cpu import DRY, SOURCE_NONE, dt_from_inverse
from avflow.numerics.face_gather import N_SUMS
from avflow.numerics.face_gather import heun_cells_parallel as _heun_parallel
from avflow.numerics.face_gather import step_cells_parallel as _step_parallel
from avflow.numerics.face_sweep import STEP as _FACES_STEP
from avflow.numerics.face_sweep import STEP_THREADS as _FACES_THREADS
from avflow.numerics.kernels import (RELIST_SHARE, _agree, activate, heun_faces, merge_lists,
                                     profile_transport, relist, step_faces, step_profile)
from avflow.numerics.profile import N_WORK as _PROFILE_WORK
from avflow.numerics.profile import ProfileLine
from avflow.numerics.profile import STEP as _PROFILE_STEP
from avflow.numerics.reconstruction import (reconstruct_cells, reconstruct_profile,
                                            reconstruct_cells_parallel as _recon_par)
from avflow.numerics.sources import SRC_KIND, add_listed, add_span
from avflow.numerics.stepping import (FAILED, MAX_RETRIES, REACHED_TARGET, STAMPS_PER_STEP,
                                      ST_FALLBACK, ST_RETRIES, ST_SOURCE, ST_TIME, Conserved,
                                      Lists, Observers, StepTime, end_loop, record_end,
                                      record_step, step_size)
from avflow.numerics.vectorize import law_kind, law_label, specialize


#: The face kernel's lists and what :func:`relist` works in (:func:`list_work`): the wet
#: cells now and after the last step, the touched cells and active faces, the cells that
#: became wet or dry, relist's new lists (they swap with the last ones) and its work
ListWork = namedtuple("ListWork", "wet wet_last touched active_faces gained lost new_faces "
                      "new_cells fresh_faces gone_faces added dropped")


@njit(error_model="numpy", cache=True)
def list_work(n, nf, mended):
    """:data:`ListWork` for ``n`` cells and ``nf`` faces (0 and 0: no lists, a profile),
    relist's arrays empty unless the lists are ``mended`` (order 1 on faces)."""
    m_re = n if mended else 0
    f_re = nf if mended else 0
    return ListWork(np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64),
                    np.empty(n, dtype=np.int64), np.empty(nf, dtype=np.int64),
                    np.empty(m_re, dtype=np.int64), np.empty(m_re, dtype=np.int64),
                    np.empty(f_re, dtype=np.int64), np.empty(m_re, dtype=np.int64),
                    np.empty(f_re, dtype=np.int64), np.empty(f_re, dtype=np.int64),
                    np.empty(m_re, dtype=np.int64), np.empty(2 * f_re, dtype=np.int64))


@njit(error_model="numpy", cache=True)
def sync_fresh(fresh, n_fresh, call, cell_sync, synced, n_synced, fields, work):
    """Order 1 on faces: a cell touched for the first time in this ``call`` gets its state
    into the work buffers (never written yet in this call, so ``fields`` holds it), and is
    listed in ``synced`` (to go back at the end). Returns how many are listed."""
    for c in range(n_fresh):
        i = fresh[c]
        if cell_sync[i] != call:
            cell_sync[i] = call
            work.h_work[i] = fields.h[i]
            work.hu_work[i] = fields.hu[i]
            work.hv_work[i] = fields.hv[i]
            synced[n_synced] = i
            n_synced += 1
    return n_synced


@njit(error_model="numpy", cache=True)
def wet_after(changed, n_changed, h, h_zero, wet, wet_last, n_wet, gained, lost, order2):
    """The wet cells after a step into ``wet``, in index order: only the ``changed`` cells
    (sorted) can be wet. At order 1 (not ``order2``) also those that became wet
    (``gained``) or dry (``lost``) against the last step's ``n_wet`` cells (``wet_last``,
    sorted), merged from both lists. Returns ``(n_wet, n_gained, n_lost)``."""
    n_new = 0
    n_gained = 0
    n_lost = 0
    p = 0
    for c in range(n_changed):
        i = changed[c]
        if h[i] > h_zero:
            if not order2:
                while p < n_wet and wet_last[p] < i:
                    lost[n_lost] = wet_last[p]
                    n_lost += 1
                    p += 1
                if p < n_wet and wet_last[p] == i:
                    p += 1
                else:
                    gained[n_gained] = i
                    n_gained += 1
            wet[n_new] = i
            n_new += 1
    if not order2:
        while p < n_wet:
            lost[n_lost] = wet_last[p]
            n_lost += 1
            p += 1
    return n_new, n_gained, n_lost


def _advance(mesh, fields, work, physics, run, sweep_geo, sweep_work):
    """Advance ``(h, hu, hv)`` in place until ``t_target``, a stop, or ``max_steps``.

    ``stats`` (see the ``ST_*`` slots) carries the time, the CFL limit and the counters from
    one call to the next. Observers updated every step: ``peak_h``, ``peak_speed``,
    ``arrival`` (first time h > h_dry, NaN before) and ``last_moved`` (end of the last step
    with u != 0: the time a cell came to rest for good once it stays at rest). The run is
    *stopped* once the moving volume (cells with u != 0 and h > h_dry) falls below
    ``stop_volume``, or once the kinetic energy is at most ``stop_kinetic`` times its peak so
    far (AvaFrame's rule); a negative value switches that rule off.
    ``order`` 2: limited reconstruction (``limiter``, :mod:`avflow.numerics.reconstruction`;
    ``face_offset[f, side]``: from each cell's centre half the way to its neighbour's, in its
    basis) and Heun's two stages, each a full step of the seed's scheme (threshold, Dirac
    faces, projection), averaged by :func:`heun_faces`. ``flux`` (n_faces, 5): the face
    fluxes of order 2 (empty at order 1); ``transport`` (per cell): the largest mass flux
    per metre through its faces in the last step. ``sweep_geo, sweep_work``: what the face
    kernel's order-1 step reads and works in
    (:func:`avflow.numerics.face_sweep.geometry`, :func:`~avflow.numerics.face_sweep.work`;
    empty elsewhere, :func:`~avflow.numerics.face_sweep.unused`). ``min_parallel_cells``:
    in the copy with threads, an order-1 step, an order-2 stage or Heun's merge that sweeps
    at least that many cells runs on Numba's threads (order 1:
    :func:`avflow.numerics.face_sweep._step_threads`, each thread scattering into the cells
    of its own piece of the faces, from twice as many where its lists changed; order 2:
    :mod:`avflow.numerics.face_gather`, in gather form; the same bits as the serial
    sweeps). ``erodible, source``: the mass source and its layer
    (:mod:`avflow.numerics.sources`), applied once per accepted step to the new state.
    Returns a status code: REACHED_TARGET, STOPPED, MAX_STEPS or FAILED.

    The arguments are named tuples: ``mesh``
    (:data:`~avflow.numerics.stepping.FaceMesh`), ``fields``
    (:data:`~avflow.numerics.stepping.Fields`: the state, observers, erodible layer and
    ``stats``), ``work`` (:data:`~avflow.numerics.stepping.FaceWork`), ``physics``
    (:data:`~avflow.numerics.stepping.Physics`), ``run``
    (:data:`~avflow.numerics.stepping.Control`); their fields are named as here.

    Kept by the caller from one call to the next (face kernel): ``face_stamp`` (per face),
    ``cell_stamp`` and ``cell_sync`` (per cell, -1 at first), ``synced`` (per cell, any) and
    ``clock`` (int64[2]: the steps stamped so far, the calls). The stamps then never repeat,
    and nothing per call costs the map: at order 1 the work buffers take the state of a cell
    when a step first touches it in the call, and only those cells go back at the end. At
    order 1 a step whose wet cells are the last step's keeps that step's active lists (a
    flow covering its mesh, a deposit at rest: nothing is listed again), and one where a few
    changed mends them (:func:`relist`: a spreading flow lists its front, not its area).

    A template: :func:`time_loop` gives its copy for the mesh kind and the order, where
    ``STRUCTURED``, ``ORDER2`` and ``PARALLEL`` are constants:
    Numba drops the branches of the other kinds before it types the function, so a run
    compiles only the sweeps it uses (a fraction of the compile time: docs/performance.md).
    """
    face_cells, cell_area, cfl_factor = mesh.face_cells, mesh.cell_area, mesh.cfl_factor
    density, gamma_x, gamma_z, curvature = (mesh.density, mesh.gamma_x, mesh.gamma_z,
                                            mesh.curvature)
    cell_face_ptr, cell_face_idx = mesh.cell_face_ptr, mesh.cell_face_idx
    h, hu, hv, flag, stats = fields.h, fields.hu, fields.hv, fields.flag, fields.stats
    peak_h, peak_speed, arrival, last_moved = (fields.peak_h, fields.peak_speed,
                                               fields.arrival, fields.last_moved)
    erodible = fields.erodible
    h_work, hu_work, hv_work = work.h_work, work.hu_work, work.hv_work
    flux, transport, face_stamp, cell_stamp = (work.flux, work.transport, work.face_stamp,
                                               work.cell_stamp)
    cell_sync, synced, clock = work.cell_sync, work.synced, work.clock
    h_zero, source = physics.h_zero, physics.source
    cfl, t_target, max_steps = run.cfl, run.t_target, run.max_steps
    stop_volume, stop_kinetic, limiter = run.stop_volume, run.stop_kinetic, run.limiter
    min_parallel_cells = run.min_parallel_cells
    t = stats[ST_TIME]
    # order-2 work arrays: one allocation per call, none per step
    o2 = order2_work(h.size if ORDER2 else 0, face_cells.shape[0] if ORDER2 else 0,
                     STRUCTURED, PARALLEL)
    union = o2.union
    obs = Observers(peak_h, peak_speed, arrival, last_moved)
    # order-1 profile sweep (avflow.numerics.profile): its work lines, once per call
    m1 = h.size if STRUCTURED and not ORDER2 else 0
    p_kappa = np.empty(m1)
    for i in range(m1):
        p_kappa[i] = curvature[i, 0]
    line = ProfileLine(face_cells[0, 1], face_cells[face_cells.shape[0] - 1, 1], cell_area[0],
                       cfl_factor, density, gamma_x, gamma_z, p_kappa,
                       np.zeros((_PROFILE_WORK, m1 + 2 if m1 else 0)),
                       np.full(m1 + 2 if m1 else 0, DRY, dtype=flag.dtype))
    cur_h, cur_hu, cur_hv = h, hu, hv
    nxt_h, nxt_hu, nxt_hv = h_work, hu_work, hv_work
    status = REACHED_TARGET
    steps = 0
    # Active lists (face kernel): both buffers agree outside the cells touched by the last
    # step, so a cell left untouched needs no copy; those touched last time are copied.
    n = h.size
    nf = face_cells.shape[0]
    if STRUCTURED or ORDER2:  # the whole state into the work buffers (faces, order 1: lazily)
        h_work[:] = h
        hu_work[:] = hu
        hv_work[:] = hv
    clock[1] += 1
    call = clock[1]
    n_synced = 0
    lw = list_work(0 if STRUCTURED else n, 0 if STRUCTURED else nf,
                   not (STRUCTURED or ORDER2))
    wet, wet_last, touched, active_faces = lw.wet, lw.wet_last, lw.touched, lw.active_faces
    gained, lost, new_faces, new_cells = lw.gained, lw.lost, lw.new_faces, lw.new_cells
    n_wet = 0
    for i in range(wet_last.size):
        if h[i] > h_zero:
            wet[n_wet] = i
            n_wet += 1
    n_previous = 0
    n_active = 0
    n_touched = 0
    n_gained = 0
    n_lost = 0
    listed = False  # this call has active lists (made by activate, with list_stamp)
    list_stamp = 0
    same_wet = False  # wet cells as in the last step: its active lists still hold
    while t < t_target:
        dt, dt_decide, last = step_size(stats, cfl, t, t_target)
        ok = False
        if not STRUCTURED and not same_wet:
            # (skipped while the wet cells are the last step's: its lists hold, the step
            # rewrites all their cells in the work buffers, and they are synced already)
            if ORDER2 or not listed or n_gained + n_lost > RELIST_SHARE * n_wet:
                # listed from the wet cells (order 2, a call's first step, or where much
                # changed); the buffers first made to agree on the last step's cells (still
                # in its list: order 2's union is written again only once this step's
                # stages ran, order 1's touched list by activate below)
                _agree(union if ORDER2 else touched, n_previous, cur_h, cur_hu, cur_hv, nxt_h,
                       nxt_hu, nxt_hv)
                list_stamp = (STAMPS_PER_STEP if ORDER2 else 1) * (clock[0] + steps)
                n_active, n_touched = activate(wet, n_wet, cell_face_ptr, cell_face_idx,
                                               face_cells, face_stamp, cell_stamp, list_stamp,
                                               active_faces, touched)
                listed = True
                n_fresh = n_touched
                fresh = touched
            else:
                # order 1, a few cells changed: the last lists mended (relist); a cell that
                # leaves them gets its new state in both buffers (the step does not write
                # it), and the cells that join are synced below
                n_active, n_touched, n_fresh, n_dropped = relist(
                    gained, n_gained, lost, n_lost, cur_h, h_zero, cell_face_ptr,
                    cell_face_idx, face_cells, face_stamp, cell_stamp, list_stamp,
                    active_faces, n_active, touched, n_touched, new_faces, new_cells,
                    lw.fresh_faces, lw.gone_faces, lw.added, lw.dropped)
                active_faces, new_faces = new_faces, active_faces
                touched, new_cells = new_cells, touched
                _agree(lw.dropped, n_dropped, cur_h, cur_hu, cur_hv, nxt_h, nxt_hu, nxt_hv)
                fresh = lw.added
            if not ORDER2:
                # a cell touched for the first time in this call: its state into the work
                # buffers (never written yet in this call, so h holds it); both buffers then
                # agree on it, as the copies of the cells that leave the lists keep them
                n_synced = sync_fresh(fresh, n_fresh, call, cell_sync, synced, n_synced,
                                      fields, work)
        n_changed = n_touched if not STRUCTURED else 0
        for attempt in range(MAX_RETRIES):
            t_new = t_target if last else t + dt
            # the lists are the last step's (or this step's last attempt's): the order-1
            # face step keeps what it made of them (their runs and pieces)
            same_lists = same_wet or attempt > 0
            wet_changes = -1  # (the order-1 face steps count the cells wet or dry anew)
            fallbacks = 0
            cur = Conserved(cur_h, cur_hu, cur_hv)
            nxt = Conserved(nxt_h, nxt_hu, nxt_hv)
            when = StepTime(dt, dt_decide, t_new)
            lists = Lists(active_faces, n_active, touched, n_touched, same_lists, face_stamp,
                          list_stamp)
            if STRUCTURED and not ORDER2:
                ok, out, lim, moving, film, clamped, kinetic = profile_step(
                    line, physics, cur, nxt, flag, obs, when, True)
            elif (not ORDER2 and PARALLEL and n_touched >= min_parallel_cells
                  and (same_lists or n_touched // 2 >= min_parallel_cells)):
                # the same on threads, each on its piece of the faces (the same bits); on
                # lists that changed, from twice as many cells (it cuts them and finds the
                # cells its pieces share again, a cost the threads must win back:
                # docs/performance.md)
                ok, out, lim, moving, film, clamped, kinetic, wet_changes = faces_step_threads(
                    mesh, physics, cur, nxt, transport, flag, obs, when, lists, sweep_geo,
                    sweep_work)
            elif not ORDER2:  # step_faces with its cell passes vectorised, its law's copy
                ok, out, lim, moving, film, clamped, kinetic, wet_changes = faces_step(
                    mesh, physics, cur, nxt, transport, flag, obs, when, lists, sweep_geo,
                    sweep_work)
            elif STRUCTURED:  # order 2, profile: stage 1 (cur -> nxt), stage 2 (nxt -> s)
                ok, out, lim, moving, film, clamped, kinetic, fallbacks = heun_profile(
                    mesh, physics, cur, nxt, flux, transport, flag, obs, o2, limiter, when)
            else:  # order 2 on faces, each stage on its own active lists
                stamp = STAMPS_PER_STEP * (clock[0] + steps) + 2 * attempt
                ok, out, lim, moving, film, clamped, kinetic, fallbacks, n_changed = (
                    order2_faces(mesh, physics, cur, nxt, flux, transport, flag, obs, work, o2,
                                 lists, stamp, when, min_parallel_cells))
            if ok:
                break
            dt *= 0.5
            last = False
            stats[ST_RETRIES] += 1
        if not ok:
            status = FAILED
            break
        if source[SRC_KIND] != SOURCE_NONE:  # only wet cells gain: the wet lists still hold
            if STRUCTURED:
                src_volume, inv = add_span(0, n, nxt_h, nxt_hu, nxt_hv, erodible, physics,
                                           dt, t_new, cell_area, cfl_factor, gamma_z, peak_h,
                                           arrival)
            else:  # the cells the step touched (order 2: either stage), every wet one
                src_volume, inv = add_listed(union if ORDER2 else touched, n_changed, nxt_h,
                                             nxt_hu, nxt_hv, erodible, physics, dt, t_new,
                                             cell_area, cfl_factor, gamma_z, peak_h, arrival)
            stats[ST_SOURCE] += src_volume
            lim = min(lim, dt_from_inverse(inv))
        t = t_target if last else t + dt
        steps += 1
        if not STRUCTURED:
            changed = union if ORDER2 else touched
            # the new wet cells (only the changed ones can be). At order 1 those that became
            # wet or dry, from both sorted lists: a next step on the same wet cells keeps this
            # step's active lists (a flow at rest or covering its whole mesh lists nothing
            # again), and on a few changes they are mended (order 2 lists with stamps of its
            # own in each stage). An order-1 face step counts the touched cells that became
            # wet or dry: with none, the wet cells are the last step's, and are not looked
            # for again (a scan of every touched cell saved)
            n_gained = 0
            n_lost = 0
            if wet_changes != 0:  # (none: the wet cells are the last step's, so is wet)
                wet, wet_last = wet_last, wet
                n_wet, n_gained, n_lost = wet_after(changed, n_changed, nxt_h, h_zero, wet,
                                                    wet_last, n_wet, gained, lost, ORDER2)
            same_wet = not ORDER2 and n_gained == 0 and n_lost == 0
            n_previous = n_changed
        stats[ST_FALLBACK] += fallbacks
        cur_h, nxt_h = nxt_h, cur_h
        cur_hu, nxt_hu = nxt_hu, cur_hu
        cur_hv, nxt_hv = nxt_hv, cur_hv
        status = record_step(stats, dt, lim, moving, film, kinetic, clamped, out, stop_volume,
                             stop_kinetic, steps, max_steps)
        if status != REACHED_TARGET:
            break
    clock[0] += steps + 1  # the next call's stamps follow this one's
    if STRUCTURED or ORDER2:
        end_loop(stats, t, steps, h, hu, hv, cur_h, cur_hu, cur_hv)
    else:  # the newest state back only where a step touched, if it is in the work buffers
        if steps % 2 == 1:
            for c in range(n_synced):
                i = synced[c]
                h[i] = cur_h[i]
                hu[i] = cur_hu[i]
                hv[i] = cur_hv[i]
        record_end(stats, t, steps)
    return status


#: Placeholders of the order-1 sweeps :func:`_advance`'s copies call (their law's copy):
#: the profile's and the faces' (:mod:`avflow.numerics.face_sweep`; on threads, in the
#: copy with threads, its step on threads)
profile_step = None
faces_step = None
faces_step_threads = None


#: Order 2's work arrays (:func:`order2_work`): the profile's reconstruction, the faces'
#: reconstructed states and cell velocities, the gather form's per-cell sums, stage 2's
#: state and stage 1's flags (DRY outside a step), stage 2's lists and both stages' union,
#: and every cell of a profile
Order2Work = namedtuple("Order2Work", "recon velocity face_state no_emit cell_sums s_h s_hu "
                        "s_hv flag1 wet2 touched2 union active2 all_cells")


@njit(error_model="numpy", cache=True)
def order2_work(m2, f2, structured, parallel):
    """:data:`Order2Work` for ``m2`` cells and ``f2`` faces (0 and 0 at order 1), once a call
    (none per step)."""
    return Order2Work(np.zeros((m2 if structured else 0, 4)),
                      np.zeros((0 if structured else m2, 2)),
                      np.zeros((0 if structured else f2, 2, 3)),
                      np.zeros((0, 7)),  # step_faces' emitted values: read at order 1 only
                      np.empty((m2 if parallel else 0, N_SUMS)),
                      np.zeros(m2), np.zeros(m2), np.zeros(m2),
                      np.full(m2, DRY, dtype=np.uint8),
                      np.empty(0 if structured else m2, dtype=np.int64),
                      np.empty(0 if structured else m2, dtype=np.int64),
                      np.empty(0 if structured else m2, dtype=np.int64),
                      np.empty(0 if structured else f2, dtype=np.int64),
                      np.arange(m2 if structured else 0))


@njit(error_model="numpy", cache=True)
def heun_profile(mesh, physics, cur, nxt, flux, transport, flag, obs, o2, limiter, when):
    """An order-2 step on a profile: stage 1 (``cur`` -> ``nxt``), stage 2 (``nxt`` -> o2's
    ``s_*``), each a full step of the seed's scheme on its reconstruction, and Heun's average
    into ``nxt``. Returns ``(ok, outflow, dt_limit, moving, film, clamped, kinetic,
    fallbacks)``."""
    s = Conserved(o2.s_h, o2.s_hu, o2.s_hv)
    reconstruct_profile(cur.h, cur.hu, physics.h_zero, limiter, o2.recon)
    ok, out, lim, moving, film, clamped, kinetic = step_profile(
        mesh, physics, cur, nxt, flux, flag, obs, when, True, o2.recon, False)
    if not ok:
        return ok, out, lim, moving, film, clamped, kinetic, 0
    o2.flag1[:] = flag
    reconstruct_profile(nxt.h, nxt.hu, physics.h_zero, limiter, o2.recon)
    ok, out2, lim, moving, film, clamped2, kinetic = step_profile(
        mesh, physics, nxt, s, flux, flag, obs, when, True, o2.recon, False)
    if not ok:
        return ok, out, lim, moving, film, clamped, kinetic, 0
    profile_transport(flag, flux, physics.dirac, transport)
    lim, moving, film, kinetic, fallbacks = heun_faces(
        o2.all_cells, cur.h.size, mesh, physics, cur, s, o2.flag1, transport, obs, when.t_new,
        nxt)
    return (ok, 0.5 * (out + out2), lim, moving, film, clamped + clamped2, kinetic,
            fallbacks)


def _order2_faces(mesh, physics, cur, nxt, flux, transport, flag, obs, work, o2, lists,
                  stamp, when, min_parallel_cells):
    """An order-2 step on faces: stage 1 on the step's ``lists``, stage 2 on lists of its
    own (stamped ``stamp + 1``), Heun's average over the cells either touched (their union
    in o2's ``union``, stamped ``stamp + 2``). A template: compiled with and without threads
    (``PARALLEL``, :data:`ORDER2_FACES`). Returns ``(ok, outflow, dt_limit, moving, film,
    clamped, kinetic, fallbacks, cells changed)``."""
    m = mesh
    s = Conserved(o2.s_h, o2.s_hu, o2.s_hv)
    flag1, touched, n_touched = o2.flag1, lists.touched, lists.n_touched
    ok, out, lim, moving, film, clamped, kinetic = order2_stage(
        mesh, physics, cur, nxt, flux, transport, flag, obs, when, lists, o2,
        min_parallel_cells)
    if not ok:
        return ok, out, lim, moving, film, clamped, kinetic, 0, n_touched
    n_wet2 = 0
    for c in range(n_touched):
        i = touched[c]
        flag1[i] = flag[i]
        s.h[i] = nxt.h[i]  # stage 2 rewrites only its own touched cells
        s.hu[i] = nxt.hu[i]
        s.hv[i] = nxt.hv[i]
        if nxt.h[i] > physics.h_zero:
            o2.wet2[n_wet2] = i
            n_wet2 += 1
    n_active2, n_touched2 = activate(o2.wet2, n_wet2, m.cell_face_ptr, m.cell_face_idx,
                                     m.face_cells, work.face_stamp, work.cell_stamp,
                                     stamp + 1, o2.active2, o2.touched2)
    lists2 = Lists(o2.active2, n_active2, o2.touched2, n_touched2, False, work.face_stamp,
                   stamp + 1)
    ok, out2, lim, moving, film, clamped2, kinetic = order2_stage(
        mesh, physics, nxt, s, flux, transport, flag, obs, when, lists2, o2,
        min_parallel_cells)
    if not ok:
        return ok, out, lim, moving, film, clamped, kinetic, 0, n_touched
    union = o2.union
    n_changed = merge_lists(touched, n_touched, o2.touched2, n_touched2, work.cell_stamp,
                            stamp + 2, union)
    if PARALLEL and n_changed >= min_parallel_cells:
        lim, moving, film, kinetic, fallbacks = heun_cells_parallel(
            union, n_changed, mesh, physics, cur, s, flag1, transport, obs, when.t_new, nxt,
            o2.cell_sums)
    else:
        lim, moving, film, kinetic, fallbacks = heun_faces(
            union, n_changed, mesh, physics, cur, s, flag1, transport, obs, when.t_new, nxt)
    for c in range(n_changed):
        flag1[union[c]] = DRY
    return (ok, 0.5 * (out + out2), lim, moving, film, clamped + clamped2, kinetic,
            fallbacks, n_changed)


def _stage_faces(mesh, physics, cur, nxt, flux, transport, flag, obs, when, lists, o2,
                 min_parallel_cells):
    """One stage of order 2 on faces, from ``cur`` into ``nxt`` on the listed faces and
    cells: the reconstruction (o2's ``face_state``), then the step.
    In the copy with threads (``PARALLEL``) a stage of at least ``min_parallel_cells``
    cells runs both in gather form on Numba's threads (:mod:`avflow.numerics.face_gather`,
    the same bits), any other on :func:`reconstruct_cells` and :func:`step_faces`.
    Returns step_faces' ``(ok, outflow, dt_limit, moving, film, clamped, kinetic)``."""
    m = mesh
    if PARALLEL and lists.n_touched >= min_parallel_cells:
        reconstruct_cells_parallel(m.face_cells, m.face_frame, m.face_length, m.face_offset,
                                   m.cell_area, cur.h, cur.hu, cur.hv, physics.h_zero,
                                   m.cell_face_ptr, m.cell_face_idx, lists.touched,
                                   lists.n_touched, o2.velocity, o2.face_state)
        return step_cells_parallel(mesh, physics, cur, nxt, flux, transport, flag, when,
                                   lists, o2.face_state, o2.cell_sums)
    reconstruct_cells(m.face_cells, m.face_frame, m.face_length, m.face_offset, m.cell_area,
                      cur.h, cur.hu, cur.hv, physics.h_zero, m.cell_face_ptr, m.cell_face_idx,
                      lists.touched, lists.n_touched, o2.velocity, o2.face_state)
    return step_faces(mesh, physics, cur, nxt, flux, transport, flag, obs, when, lists, True,
                      o2.face_state, False, o2.no_emit)


#: Placeholders of the constants of the copies of :func:`_advance`, :func:`_order2_faces`
#: and :func:`_stage_faces` (see :func:`time_loop`), and of what their copies call (the
#: functions on threads only in the copies with threads)
STRUCTURED = ORDER2 = PARALLEL = False
reconstruct_cells_parallel = step_cells_parallel = heun_cells_parallel = None
order2_stage = order2_faces = None

#: :func:`_stage_faces` and :func:`_order2_faces` serial and with threads, each under its
#: own name
ORDER2_STAGE = {
    False: specialize(_stage_faces, "_serial", PARALLEL=False),
    True: specialize(_stage_faces, "_parallel", PARALLEL=True,
                     reconstruct_cells_parallel=_recon_par, step_cells_parallel=_step_parallel)}
ORDER2_FACES = {
    parallel: specialize(_order2_faces, "_parallel" if parallel else "_serial",
                         PARALLEL=parallel, order2_stage=ORDER2_STAGE[parallel],
                         heun_cells_parallel=_heun_parallel if parallel else None)
    for parallel in (False, True)}


def _advance_for(structured: bool, order2: bool, kind: int | None = None,
                 parallel: bool = False):
    """:func:`_advance` compiled with the mesh kind and the order constants (and, at order
    1, calling the sweep of the friction law ``kind``; ``parallel``: the face kernel with
    its passes on threads, whose functions the other copies never compile)."""
    suffix = f"_{'profile' if structured else 'faces'}_order{2 if order2 else 1}"
    names = {}
    if kind is not None:
        suffix += "_" + law_label(kind)
        if structured:
            names["profile_step"] = _PROFILE_STEP[kind]
        else:
            names["faces_step"] = _FACES_STEP[kind]
            if parallel:
                names["faces_step_threads"] = _FACES_THREADS[kind]
    if parallel:
        suffix += "_parallel"
    return specialize(_advance, suffix, STRUCTURED=structured, ORDER2=order2,
                      PARALLEL=parallel, order2_faces=ORDER2_FACES[parallel], **names)


#: The time loop per (structured, order 2, law kind, threads): the law only at order 1,
#: whose sweeps have a copy per law (:data:`avflow.numerics.profile.STEP`,
#: :data:`avflow.numerics.face_sweep.STEP`), None at order 2; threads only on faces
ADVANCE = {(s, o, k, p): _advance_for(s, o, k, p)
           for s, o, kinds, threads in (
               (True, False, tuple(_PROFILE_STEP), (False,)), (True, True, (None,), (False,)),
               (False, False, tuple(_FACES_STEP), (False, True)),
               (False, True, (None,), (False, True)))
           for k in kinds for p in threads}


def time_loop(structured: bool, order: int, law: int, parallel: bool = False):
    """The time loop (:func:`_advance`: its arguments, its status codes) compiled for this
    mesh kind (``structured``: a profile) and ``order`` alone (and, at order 1, for the
    friction ``law``); ``parallel``: with the passes on threads (on faces only;
    profiles run the serial copy)."""
    structured, order2 = bool(structured), order == 2
    parallel = bool(parallel) and not structured
    return ADVANCE[structured, order2, None if order2 else law_kind(law), parallel]
