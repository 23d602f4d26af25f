"""The time loop of the profile and face kernels (the square-grid kernel's is
:func:`avflow.numerics.square_grid.grid_loop`): step size, retry by halving, stop rules,
observers, Heun's two stages and merge at order 2, and the active lists of the faces.

:func:`_advance` is a template compiled per mesh kind, order, law kind and threads by
:func:`_advance_for` (:func:`avflow.numerics.vectorize.specialize`): Numba drops the
branches of the other kinds before it types a copy, so a run compiles only what it uses.
"""

from __future__ import annotations

import numpy as np

from avflow.numerics.cpu import DRY, SOURCE_NONE, dt_from_inverse
from avflow.numerics.face_gather import N_SUMS
from avflow.numerics.face_gather import heun_cells_parallel as _heun_parallel
from avflow.numerics.face_gather import step_cells_parallel as _step_parallel
from avflow.numerics.face_sweep import STEP as _FACES_STEP
from avflow.numerics.face_sweep import STEP_THREADS as _FACES_THREADS
from avflow.numerics.kernels import (RELIST_SHARE, _agree, activate, heun_faces, merge_lists,
                                     profile_transport, relist, step_faces, step_profile)
from avflow.numerics.profile import N_WORK as _PROFILE_WORK
from avflow.numerics.profile import STEP as _PROFILE_STEP
from avflow.numerics.reconstruction import (reconstruct_cells, reconstruct_profile,
                                            reconstruct_cells_parallel as _recon_par)
from avflow.numerics.sources import SRC_KIND, add_listed, add_span
from avflow.numerics.stepping import (FAILED, MAX_RETRIES, REACHED_TARGET, STAMPS_PER_STEP,
                                      ST_FALLBACK, ST_RETRIES, ST_SOURCE, ST_TIME, end_loop,
                                      record_end, record_step, step_size)
from avflow.numerics.vectorize import law_kind, law_label, specialize


def _advance(structured, face_cells, face_frame, face_length, cell_area, cfl_factor, density,
            gamma_x, gamma_y, gamma_z, curvature,
            h, hu, hv, h_work, hu_work, hv_work, flux, transport, flag,
            law, params, g, dirac, h_dry, h_zero, cfl, t_target, max_steps, stop_volume,
            stop_kinetic, peak_h, peak_speed, arrival, last_moved, cell_face_ptr, cell_face_idx,
            stats, order, limiter, face_offset, face_stamp, cell_stamp, cell_sync, synced, clock,
            sweep_geo, sweep_work, min_parallel_cells, erodible, source):
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

    Kept by the caller from one call to the next (face kernel): ``face_stamp`` (per face),
    ``cell_stamp`` and ``cell_sync`` (per cell, -1 at first), ``synced`` (per cell, any) and
    ``clock`` (int64[2]: the steps stamped so far, the calls). The stamps then never repeat,
    and nothing per call costs the map: at order 1 the work buffers take the state of a cell
    when a step first touches it in the call, and only those cells go back at the end. At
    order 1 a step whose wet cells are the last step's keeps that step's active lists (a
    flow covering its mesh, a deposit at rest: nothing is listed again), and one where a few
    changed mends them (:func:`relist`: a spreading flow lists its front, not its area).

    A template: :func:`time_loop` gives its copy for the mesh kind and the order, where
    ``STRUCTURED``, ``ORDER2`` and ``PARALLEL`` are constants (``structured`` and ``order``
    are not read):
    Numba drops the branches of the other kinds before it types the function, so a run
    compiles only the sweeps it uses (a fraction of the compile time: docs/performance.md).
    """
    t = stats[ST_TIME]
    # order-2 work arrays: one allocation per call, none per step
    m2 = h.size if ORDER2 else 0
    f2 = face_cells.shape[0] if ORDER2 else 0
    recon = np.zeros((m2 if STRUCTURED else 0, 4))
    velocity = np.zeros((0 if STRUCTURED else m2, 2))  # reconstruct_cells' work
    face_state = np.zeros((0 if STRUCTURED else f2, 2, 3))
    cell_sums = np.empty((m2 if PARALLEL else 0, N_SUMS))  # the gather form's per-cell sums
    no_emit = np.zeros((0, 7))  # step_faces' emitted values: read at order 1 only
    s_h = np.zeros(m2)
    s_hu = np.zeros(m2)
    s_hv = np.zeros(m2)
    flag1 = np.full(m2, DRY, dtype=flag.dtype)  # stage-1 flags; DRY outside a step
    wet2 = np.empty(0 if STRUCTURED else m2, dtype=np.int64)
    touched2 = np.empty(0 if STRUCTURED else m2, dtype=np.int64)
    union = np.empty(0 if STRUCTURED else m2, dtype=np.int64)
    active2 = np.empty(0 if STRUCTURED else f2, dtype=np.int64)
    all_cells = np.arange(m2 if STRUCTURED else 0)
    # order-1 profile sweep (avflow.numerics.profile): its work lines, once per call
    m1 = h.size if STRUCTURED and not ORDER2 else 0
    p_work = np.zeros((_PROFILE_WORK, m1 + 2 if m1 else 0))
    p_flag = np.full(m1 + 2 if m1 else 0, DRY, dtype=flag.dtype)
    p_kappa = np.empty(m1)
    for i in range(m1):
        p_kappa[i] = curvature[i, 0]
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
    m_faces = 0 if STRUCTURED else n  # the face kernel's lists
    wet = np.empty(n, dtype=np.int64)
    touched = np.empty(n, dtype=np.int64)
    active_faces = np.empty(nf, dtype=np.int64)
    # order 1: the last step's wet cells, those that became wet / dry since, and what
    # relist() works in (its new lists swap with the last ones)
    m_re = 0 if STRUCTURED or ORDER2 else n
    f_re = 0 if STRUCTURED or ORDER2 else nf
    wet_last = np.empty(m_faces, dtype=np.int64)
    gained = np.empty(m_re, dtype=np.int64)
    lost = np.empty(m_re, dtype=np.int64)
    new_faces = np.empty(f_re, dtype=np.int64)
    new_cells = np.empty(m_re, dtype=np.int64)
    fresh_faces = np.empty(f_re, dtype=np.int64)
    gone_faces = np.empty(f_re, dtype=np.int64)
    added = np.empty(m_re, dtype=np.int64)
    dropped = np.empty(2 * f_re, dtype=np.int64)
    n_wet = 0
    for i in range(m_faces):
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
                    fresh_faces, gone_faces, added, dropped)
                active_faces, new_faces = new_faces, active_faces
                touched, new_cells = new_cells, touched
                _agree(dropped, n_dropped, cur_h, cur_hu, cur_hv, nxt_h, nxt_hu, nxt_hv)
                fresh = added
            if not ORDER2:
                # a cell touched for the first time in this call: its state into the work
                # buffers (never written yet in this call, so h holds it); both buffers then
                # agree on it, as the copies of the cells that leave the lists keep them
                for c in range(n_fresh):
                    i = fresh[c]
                    if cell_sync[i] != call:
                        cell_sync[i] = call
                        h_work[i] = h[i]
                        hu_work[i] = hu[i]
                        hv_work[i] = hv[i]
                        synced[n_synced] = i
                        n_synced += 1
        n_changed = n_touched if not STRUCTURED else 0
        for attempt in range(MAX_RETRIES):
            t_new = t_target if last else t + dt
            # the lists are the last step's (or this step's last attempt's): the order-1
            # face step keeps what it made of them (their runs and pieces)
            same_lists = same_wet or attempt > 0
            wet_changes = -1  # (the order-1 face steps count the cells wet or dry anew)
            fallbacks = 0
            if STRUCTURED and not ORDER2:
                ok, out, lim, moving, film, clamped, kinetic = profile_step(
                    face_cells[0, 1], face_cells[n, 1], cell_area[0], cfl_factor, density,
                    gamma_x, gamma_z, p_kappa, cur_h, cur_hu, nxt_h, nxt_hu, nxt_hv, flag, law,
                    params, g, dirac, h_dry, h_zero, dt, dt_decide, t_new, peak_h, peak_speed,
                    arrival, last_moved, True, p_work, p_flag)
            elif (not ORDER2 and PARALLEL and n_touched >= min_parallel_cells
                  and (same_lists or n_touched // 2 >= min_parallel_cells)):
                # the same on threads, each on its piece of the faces (the same bits); on
                # lists that changed, from twice as many cells (it cuts them and finds the
                # cells its pieces share again, a cost the threads must win back:
                # docs/performance.md)
                ok, out, lim, moving, film, clamped, kinetic, wet_changes = faces_step_threads(
                    face_cells, face_frame, face_length, cell_area, cfl_factor, density,
                    gamma_x, gamma_y, gamma_z, cur_h, cur_hu, cur_hv, nxt_h, nxt_hu, nxt_hv,
                    transport, flag, law, params, g, dirac, h_dry, h_zero, dt, dt_decide,
                    t_new, peak_h, peak_speed, arrival, last_moved, active_faces, n_active,
                    touched, n_touched, same_lists, face_stamp, list_stamp, sweep_geo,
                    sweep_work)
            elif not ORDER2:  # step_faces with its cell passes vectorised, its law's copy
                ok, out, lim, moving, film, clamped, kinetic, wet_changes = faces_step(
                    face_cells, face_frame, face_length, cell_area, cfl_factor, density,
                    gamma_x, gamma_y, gamma_z, cur_h, cur_hu, cur_hv, nxt_h, nxt_hu, nxt_hv,
                    transport, flag, law, params, g, dirac, h_dry, h_zero, dt, dt_decide,
                    t_new, peak_h, peak_speed, arrival, last_moved, active_faces, n_active,
                    touched, n_touched, same_lists, face_stamp, list_stamp, sweep_geo,
                    sweep_work)
            elif STRUCTURED:  # order 2, profile: stage 1 (cur -> nxt), stage 2 (nxt -> s)
                reconstruct_profile(cur_h, cur_hu, h_zero, limiter, recon)
                ok, out, lim, moving, film, clamped, kinetic = step_profile(
                    face_cells, cell_area, cfl_factor, density, gamma_x, gamma_y, gamma_z,
                    curvature,
                    cur_h, cur_hu, cur_hv, nxt_h, nxt_hu, nxt_hv, flux, flag,
                    law, params, g, dirac, h_dry, h_zero, dt, dt_decide, t_new, peak_h, peak_speed,
                    arrival, last_moved, True, recon, False)
                if ok:
                    flag1[:] = flag
                    reconstruct_profile(nxt_h, nxt_hu, h_zero, limiter, recon)
                    ok, out2, lim, moving, film, clamped2, kinetic = step_profile(
                        face_cells, cell_area, cfl_factor, density, gamma_x, gamma_y, gamma_z,
                        curvature,
                        nxt_h, nxt_hu, nxt_hv, s_h, s_hu, s_hv, flux, flag,
                        law, params, g, dirac, h_dry, h_zero, dt, dt_decide, t_new, peak_h,
                        peak_speed, arrival, last_moved, True, recon, False)
                if ok:
                    out = 0.5 * (out + out2)
                    clamped += clamped2
                    profile_transport(flag, flux, dirac, transport)
                    lim, moving, film, kinetic, fallbacks = heun_faces(
                        all_cells, h.size, cur_h, cur_hu, cur_hv, s_h, s_hu, s_hv, flag1,
                        transport, cell_area, cfl_factor, gamma_z, g, h_dry, h_zero, t_new,
                        peak_h, peak_speed, arrival, last_moved, nxt_h, nxt_hu, nxt_hv)
            else:  # order 2 on faces, each stage on its own active lists
                ok, out, lim, moving, film, clamped, kinetic = order2_stage(
                    face_cells, face_frame, face_length, face_offset, cell_area, cfl_factor,
                    density, gamma_x, gamma_y, gamma_z, curvature, cur_h, cur_hu, cur_hv,
                    nxt_h, nxt_hu, nxt_hv, flux, transport, flag, law, params, g, dirac,
                    h_dry, h_zero, dt, dt_decide, t_new, peak_h, peak_speed, arrival,
                    last_moved, active_faces, n_active, touched, n_touched, cell_face_ptr,
                    cell_face_idx, velocity, face_state, no_emit, cell_sums,
                    min_parallel_cells)
                if ok:
                    n_wet2 = 0
                    for c in range(n_touched):
                        i = touched[c]
                        flag1[i] = flag[i]
                        s_h[i] = nxt_h[i]  # stage 2 rewrites only its own touched cells
                        s_hu[i] = nxt_hu[i]
                        s_hv[i] = nxt_hv[i]
                        if nxt_h[i] > h_zero:
                            wet2[n_wet2] = i
                            n_wet2 += 1
                    # fresh stamps for each attempt: stage 1 listed with the step's first
                    stamp = STAMPS_PER_STEP * (clock[0] + steps) + 2 * attempt
                    n_active2, n_touched2 = activate(wet2, n_wet2, cell_face_ptr, cell_face_idx,
                                                     face_cells, face_stamp, cell_stamp,
                                                     stamp + 1, active2, touched2)
                    ok, out2, lim, moving, film, clamped2, kinetic = order2_stage(
                        face_cells, face_frame, face_length, face_offset, cell_area,
                        cfl_factor, density, gamma_x, gamma_y, gamma_z, curvature, nxt_h,
                        nxt_hu, nxt_hv, s_h, s_hu, s_hv, flux, transport, flag, law, params, g,
                        dirac, h_dry, h_zero, dt, dt_decide, t_new, peak_h, peak_speed,
                        arrival, last_moved, active2, n_active2, touched2, n_touched2,
                        cell_face_ptr, cell_face_idx, velocity, face_state, no_emit, cell_sums,
                        min_parallel_cells)
                if ok:
                    out = 0.5 * (out + out2)
                    clamped += clamped2
                    n_changed = merge_lists(touched, n_touched, touched2, n_touched2, cell_stamp,
                                            stamp + 2, union)
                    if PARALLEL and n_changed >= min_parallel_cells:
                        lim, moving, film, kinetic, fallbacks = heun_cells_parallel(
                            union, n_changed, cur_h, cur_hu, cur_hv, s_h, s_hu, s_hv, flag1,
                            transport, cell_area, cfl_factor, gamma_z, g, h_dry, h_zero,
                            t_new, peak_h, peak_speed, arrival, last_moved, nxt_h, nxt_hu,
                            nxt_hv, cell_sums)
                    else:
                        lim, moving, film, kinetic, fallbacks = heun_faces(
                            union, n_changed, cur_h, cur_hu, cur_hv, s_h, s_hu, s_hv, flag1,
                            transport, cell_area, cfl_factor, gamma_z, g, h_dry, h_zero,
                            t_new, peak_h, peak_speed, arrival, last_moved, nxt_h, nxt_hu,
                            nxt_hv)
                    for c in range(n_changed):
                        flag1[union[c]] = DRY
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
                src_volume, inv = add_span(0, n, nxt_h, nxt_hu, nxt_hv, erodible, source, dt,
                                           h_zero, h_dry, t_new, cell_area, cfl_factor,
                                           gamma_z, g, peak_h, arrival)
            else:  # the cells the step touched (order 2: either stage), every wet one
                src_volume, inv = add_listed(union if ORDER2 else touched, n_changed, nxt_h,
                                             nxt_hu, nxt_hv, erodible, source, dt, h_zero,
                                             h_dry, t_new, cell_area, cfl_factor, gamma_z, g,
                                             peak_h, arrival)
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
                n_new = 0
                p = 0
                for c in range(n_changed):
                    i = changed[c]
                    if nxt_h[i] > h_zero:
                        if not ORDER2:
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
                if not ORDER2:
                    while p < n_wet:
                        lost[n_lost] = wet_last[p]
                        n_lost += 1
                        p += 1
                n_wet = n_new
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


def _stage_faces(face_cells, face_frame, face_length, face_offset, cell_area, cfl_factor,
                 density, gamma_x, gamma_y, gamma_z, curvature, h, hu, hv, h_new, hu_new,
                 hv_new, flux, transport, flag, law, params, g, dirac, h_dry, h_zero, dt,
                 dt_decide, t_new, peak_h, peak_speed, arrival, last_moved, active_faces,
                 n_active, touched, n_touched, cell_face_ptr, cell_face_idx, velocity,
                 face_state, no_emit, cell_sums, min_parallel_cells):
    """One stage of order 2 on faces, from ``(h, hu, hv)`` into ``(h_new, hu_new, hv_new)``
    on the listed faces and cells: the reconstruction (``face_state``), then the step.
    In the copy with threads (``PARALLEL``) a stage of at least ``min_parallel_cells``
    cells runs both in gather form on Numba's threads (:mod:`avflow.numerics.face_gather`,
    the same bits), any other on :func:`reconstruct_cells` and :func:`step_faces`.
    Returns step_faces' ``(ok, outflow, dt_limit, moving, film, clamped, kinetic)``."""
    if PARALLEL and n_touched >= min_parallel_cells:
        reconstruct_cells_parallel(face_cells, face_frame, face_length, face_offset,
                                   cell_area, h, hu, hv, h_zero, cell_face_ptr, cell_face_idx,
                                   touched, n_touched, velocity, face_state)
        return step_cells_parallel(
            face_cells, face_frame, face_length, cell_area, cfl_factor, density, gamma_x,
            gamma_y, gamma_z, curvature, h, hu, hv, h_new, hu_new, hv_new, flux, transport,
            flag, law, params, g, dirac, h_zero, h_dry, dt, dt_decide, active_faces, n_active,
            touched, n_touched, cell_face_ptr, cell_face_idx, face_state, cell_sums)
    reconstruct_cells(face_cells, face_frame, face_length, face_offset, cell_area, h, hu, hv,
                      h_zero, cell_face_ptr, cell_face_idx, touched, n_touched, velocity,
                      face_state)
    return step_faces(face_cells, face_frame, face_length, cell_area, cfl_factor, density,
                      gamma_x, gamma_y, gamma_z, curvature, h, hu, hv, h_new, hu_new, hv_new,
                      flux, transport, flag, law, params, g, dirac, h_dry, h_zero, dt,
                      dt_decide, t_new, peak_h, peak_speed, arrival, last_moved, active_faces,
                      n_active, touched, n_touched, True, face_state, False, no_emit)


#: Placeholders of the constants of :func:`_advance`'s and :func:`_stage_faces`' copies (see
#: :func:`time_loop`), and of what their copies with threads call (none in the others)
STRUCTURED = ORDER2 = PARALLEL = False
reconstruct_cells_parallel = step_cells_parallel = heun_cells_parallel = order2_stage = None

#: :func:`_stage_faces` serial and with threads, each under its own name
ORDER2_STAGE = {
    False: specialize(_stage_faces, "_serial", PARALLEL=False),
    True: specialize(_stage_faces, "_parallel", PARALLEL=True,
                     reconstruct_cells_parallel=_recon_par, step_cells_parallel=_step_parallel)}


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
        names["heun_cells_parallel"] = _heun_parallel
    return specialize(_advance, suffix, STRUCTURED=structured, ORDER2=order2,
                      PARALLEL=parallel, order2_stage=ORDER2_STAGE[parallel], **names)


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
