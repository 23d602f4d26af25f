"""The region of the profile and face kernels in the one time loop
(:func:`avflow.numerics.loop.advance`): the profile's line, or the active lists of the
faces, and what a step runs on them (the order-1 sweep of the law, or Heun's two stages and
merge at order 2). The square-grid kernel's region is in :mod:`avflow.numerics.square_grid`.

The hooks (:func:`_start` .. :func:`_end`) are templates compiled per mesh kind, order, law
kind and threads by :func:`_advance_for` (:func:`avflow.numerics.vectorize.specialize`):
Numba drops the branches of the other kinds before it types a copy, so a run compiles only
what it uses.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from avflow.numerics.cpu import DRY
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
from avflow.numerics.physics import MIDPOINT
from avflow.numerics.reconstruction import (Predictor, predict_cells, reconstruct_cells,
                                            reconstruct_profile)
from avflow.numerics.reconstruction import predict_cells_parallel as _predict_par
from avflow.numerics.reconstruction import reconstruct_cells_parallel as _recon_par
from avflow.numerics.loop import advance
from avflow.numerics.observers import observe_listed, observe_span
from avflow.numerics.sources import add_listed, add_span
from avflow.numerics.stepping import (STAMPS_PER_STEP, ST_SOURCE, Conserved, Lists, end_loop,
                                      record_end)
from avflow.numerics.vectorize import law_kind, law_label, shared_names, specialize


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
def wet_after(changed, n_changed, h, h_zero, wet, wet_last, n_wet, gained, lost, order2,
              supplied):
    """The wet cells after a step into ``wet``, in index order: only the ``changed`` cells
    (sorted) can be wet; a cell a registered source covers (``supplied``, a mask; empty
    without sources) counts as wet, so the lists keep it (mass lands there). At order 1 (not ``order2``) also those that became wet
    (``gained``) or dry (``lost``) against the last step's ``n_wet`` cells (``wet_last``,
    sorted), merged from both lists. Returns ``(n_wet, n_gained, n_lost)``."""
    n_new = 0
    n_gained = 0
    n_lost = 0
    p = 0
    for c in range(n_changed):
        i = changed[c]
        if h[i] > h_zero or (supplied.size > 0 and supplied[i] != 0):
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


#: The face kernel's region (:mod:`avflow.numerics.loop`): what changes from step to step.
#: Its lists (they swap with relist's new ones and with the last step's wet cells; ``fresh``:
#: the cells to sync) and their counts, the stamp of the listed faces, whether this call has
#: lists yet (``listed``), whether the wet cells are the last step's (``same_wet``: its lists
#: hold), and how many cells the last step found wet or dry anew (-1: not counted)
FaceRegion = namedtuple("FaceRegion", "wet wet_last touched active_faces new_faces new_cells "
                        "fresh n_wet n_previous n_active n_touched n_fresh n_changed n_gained "
                        "n_lost n_synced list_stamp listed same_wet wet_changes")
#: ... and what does not: order 2's work, the profile's line, the lists' work, and this
#: call's number (:func:`sync_fresh`)
FaceContext = namedtuple("FaceContext", "o2 line lw call")


@njit(error_model="numpy", cache=True)
def _lists(region, n_active, n_touched, n_fresh, active_faces=None, touched=None,
           new_faces=None, new_cells=None, fresh=None, listed=True, list_stamp=-1,
           n_synced=-1):
    """``region`` with new lists (the arrays left out stay as they are)."""
    r = region
    return FaceRegion(r.wet, r.wet_last, r.touched if touched is None else touched,
                      r.active_faces if active_faces is None else active_faces,
                      r.new_faces if new_faces is None else new_faces,
                      r.new_cells if new_cells is None else new_cells,
                      r.fresh if fresh is None else fresh, r.n_wet, r.n_previous, n_active,
                      n_touched, n_fresh, r.n_changed, r.n_gained, r.n_lost,
                      r.n_synced if n_synced < 0 else n_synced,
                      r.list_stamp if list_stamp < 0 else list_stamp, listed, r.same_wet,
                      r.wet_changes)


def _start(loop):
    """The face kernel's region at the start of a call: order 2's work arrays, the profile's
    line and the lists' work (one allocation per call, none per step), the wet cells."""
    mesh, fields, work = loop.mesh, loop.fields, loop.work
    face_cells, h = mesh.face_cells, fields.h
    o2 = order2_work(h.size if ORDER2 else 0, face_cells.shape[0] if ORDER2 else 0,
                     STRUCTURED, PARALLEL, 7 if HANCOCK else 3)
    # order-1 profile sweep (avflow.numerics.profile): its work lines, once per call
    m1 = h.size if STRUCTURED and not ORDER2 else 0
    p_kappa = np.empty(m1)
    for i in range(m1):
        p_kappa[i] = mesh.curvature[i, 0]
    line = ProfileLine(face_cells[0, 1], face_cells[face_cells.shape[0] - 1, 1],
                       mesh.cell_area[0], mesh.cfl_factor, mesh.density, mesh.gamma_x,
                       mesh.gamma_z, p_kappa, np.zeros((_PROFILE_WORK, m1 + 2 if m1 else 0)),
                       np.full(m1 + 2 if m1 else 0, DRY, dtype=fields.flag.dtype))
    if STRUCTURED or ORDER2:  # the whole state into the work buffers (faces, order 1: lazily)
        for i in range(h.size):  # (element by element: no shape check's message to compile)
            work.h_work[i] = h[i]
            work.hu_work[i] = fields.hu[i]
            work.hv_work[i] = fields.hv[i]
    work.clock[1] += 1
    n = h.size
    nf = face_cells.shape[0]
    lw = list_work(0 if STRUCTURED else n, 0 if STRUCTURED else nf,
                   not (STRUCTURED or ORDER2))
    n_wet = 0
    supplied = loop.supply.mask  # (registered sources' cells: wet for the lists)
    for i in range(lw.wet_last.size):
        if h[i] > loop.physics.h_zero or (supplied.size > 0 and supplied[i] != 0):
            lw.wet[n_wet] = i
            n_wet += 1
    region = FaceRegion(lw.wet, lw.wet_last, lw.touched, lw.active_faces, lw.new_faces,
                        lw.new_cells, lw.touched, n_wet, 0, 0, 0, 0, 0, 0, 0, 0, 0, False,
                        False, -1)
    return region, FaceContext(o2, line, lw, work.clock[1])


def _before(region, ctx, loop, cur, nxt, steps):
    """The active lists of the next step (not on a profile). Kept while the wet cells are
    the last step's (the step rewrites all their cells in the work buffers, which are
    synced already); made from the wet cells at order 2, in a call's first step, or where
    much changed; else mended (:func:`relist`: a spreading flow lists its front, not its
    area). At order 1 a cell touched for the first time in this call is synced."""
    r = region
    if not STRUCTURED and not r.same_wet:
        mesh, work, lw, o2 = loop.mesh, loop.work, ctx.lw, ctx.o2
        if ORDER2 or not r.listed or r.n_gained + r.n_lost > RELIST_SHARE * r.n_wet:
            # the buffers first made to agree on the last step's cells (still in its list:
            # order 2's union is written again only once this step's stages ran, order 1's
            # touched list by activate below)
            _agree(o2.union if ORDER2 else r.touched, r.n_previous, cur.h, cur.hu, cur.hv,
                   nxt.h, nxt.hu, nxt.hv)
            list_stamp = (STAMPS_PER_STEP if ORDER2 else 1) * (work.clock[0] + steps)
            n_active, n_touched = activate(r.wet, r.n_wet, mesh.cell_face_ptr,
                                           mesh.cell_face_idx, mesh.face_cells,
                                           work.face_stamp, work.cell_stamp, list_stamp,
                                           r.active_faces, r.touched)
            r = _lists(r, n_active, n_touched, n_touched, fresh=r.touched,
                       list_stamp=list_stamp)
        else:
            # a cell that leaves the lists gets its new state in both buffers (the step does
            # not write it); the cells that join are synced below
            n_active, n_touched, n_fresh, n_dropped = relist(
                lw.gained, r.n_gained, lw.lost, r.n_lost, cur.h, loop.physics.h_zero,
                mesh.cell_face_ptr, mesh.cell_face_idx, mesh.face_cells, work.face_stamp,
                work.cell_stamp, r.list_stamp, r.active_faces, r.n_active, r.touched,
                r.n_touched, r.new_faces, r.new_cells, lw.fresh_faces, lw.gone_faces,
                lw.added, lw.dropped)
            _agree(lw.dropped, n_dropped, cur.h, cur.hu, cur.hv, nxt.h, nxt.hu, nxt.hv)
            r = _lists(r, n_active, n_touched, n_fresh, active_faces=r.new_faces,
                       new_faces=r.active_faces, touched=r.new_cells, new_cells=r.touched,
                       fresh=lw.added)
        if not ORDER2:
            # its state into the work buffers (never written yet in this call, so the
            # fields hold it); both buffers then agree on it
            n_synced = sync_fresh(r.fresh, r.n_fresh, ctx.call, work.cell_sync, work.synced,
                                  r.n_synced, loop.fields, work)
            r = _lists(r, r.n_active, r.n_touched, r.n_fresh, n_synced=n_synced)
    return _counted(r, r.n_touched if not STRUCTURED else 0, r.wet_changes)


@njit(error_model="numpy", cache=True)
def _counted(r, n_changed, wet_changes):
    """``r`` with the cells a step changed and how many it found wet or dry anew."""
    return FaceRegion(r.wet, r.wet_last, r.touched, r.active_faces, r.new_faces, r.new_cells,
                      r.fresh, r.n_wet, r.n_previous, r.n_active, r.n_touched, r.n_fresh,
                      n_changed, r.n_gained, r.n_lost, r.n_synced, r.list_stamp, r.listed,
                      r.same_wet, wet_changes)


def _step(region, ctx, loop, cur, nxt, when, steps, attempt):
    """One step on the profile's line or on the active lists: the order-1 sweep (its law's
    copy; on threads where at least ``min_parallel_cells`` cells are touched), or order 2's
    two stages and merge."""
    r = region
    mesh, work, physics, fields = loop.mesh, loop.work, loop.physics, loop.fields
    flag, o2 = fields.flag, ctx.o2
    min_parallel_cells = loop.run.min_parallel_cells
    # the lists are the last step's (or this step's last attempt's): the order-1 face step
    # keeps what it made of them (their runs and pieces)
    same_lists = r.same_wet or attempt > 0
    wet_changes = -1  # (the order-1 face steps count the cells wet or dry anew)
    fallbacks = 0
    n_changed = r.n_changed
    lists = Lists(r.active_faces, r.n_active, r.touched, r.n_touched, same_lists,
                  work.face_stamp, r.list_stamp)
    if STRUCTURED and not ORDER2:
        ok, out, lim, moving, film, clamped, kinetic = profile_step(
            ctx.line, physics, cur, nxt, flag, when)
    elif (not ORDER2 and PARALLEL and r.n_touched >= min_parallel_cells
          and (same_lists or r.n_touched // 2 >= min_parallel_cells)):
        # on threads, each on its piece of the faces (the same bits); on lists that changed,
        # from twice as many cells (it cuts them and finds the cells its pieces share again,
        # a cost the threads must win back: docs/performance.md)
        ok, out, lim, moving, film, clamped, kinetic, wet_changes = faces_step_threads(
            mesh, physics, cur, nxt, work.transport, flag, when, lists, loop.extra.geometry,
            loop.extra.work)
    elif not ORDER2:  # step_faces with its cell passes vectorised, its law's copy
        ok, out, lim, moving, film, clamped, kinetic, wet_changes = faces_step(
            mesh, physics, cur, nxt, work.transport, flag, when, lists, loop.extra.geometry,
            loop.extra.work)
    elif STRUCTURED:  # order 2, profile: stage 1 (cur -> nxt), stage 2 (nxt -> s)
        ok, out, lim, moving, film, clamped, kinetic, fallbacks = heun_profile(
            mesh, physics, cur, nxt, work.flux, work.transport, flag, o2, loop.run.limiter,
            when)
    else:  # order 2 on faces, each stage on its own active lists
        stamp = STAMPS_PER_STEP * (work.clock[0] + steps) + 2 * attempt
        ok, out, lim, moving, film, clamped, kinetic, fallbacks, n_changed = order2_faces(
            mesh, physics, cur, nxt, work.flux, work.transport, flag, work, o2, lists, stamp,
            when, min_parallel_cells)
    return (ok, out, lim, moving, film, clamped, kinetic, fallbacks,
            _counted(r, n_changed, wet_changes))


def _source(region, ctx, loop, nxt, when):
    """The source over the cells the step touched (order 2: either stage; a profile: all),
    which hold every wet one."""
    mesh, fields, physics = loop.mesh, loop.fields, loop.physics
    if STRUCTURED:
        volume, inv = add_span(0, nxt.h.size, nxt.h, nxt.hu, nxt.hv, fields.erodible, physics,
                               when.dt, mesh.cell_area, mesh.cfl_factor, mesh.gamma_z)
    else:
        volume, inv = add_listed(ctx.o2.union if ORDER2 else region.touched, region.n_changed,
                                 nxt.h, nxt.hu, nxt.hv, fields.erodible, physics, when.dt,
                                 mesh.cell_area, mesh.cfl_factor, mesh.gamma_z)
    fields.stats[ST_SOURCE] += volume
    return inv


def _observe(region, ctx, loop, nxt, when):
    """The running maps of the cells the step changed (a profile: all of them), from their
    accepted state (:mod:`avflow.numerics.observers`)."""
    f, h_dry = loop.fields, loop.physics.h_dry
    if STRUCTURED:
        observe_span(0, nxt.h.size, nxt.h, nxt.hu, nxt.hv, f.peak_h, f.peak_speed, f.arrival,
                     f.last_moved, f.maps, when.t_new, h_dry)
    else:
        observe_listed(ctx.o2.union if ORDER2 else region.touched, region.n_changed, nxt.h,
                       nxt.hu, nxt.hv, f.peak_h, f.peak_speed, f.arrival, f.last_moved, f.maps,
                       when.t_new, h_dry)


def _after(region, ctx, loop, nxt):
    """The wet cells after a step (only the changed ones can be). At order 1 also those that
    became wet or dry: a next step on the same wet cells keeps this step's active lists (a
    flow at rest or covering its whole mesh lists nothing again), and on a few changes they
    are mended. An order-1 face step counts the touched cells that became wet or dry: with
    none, the wet cells are the last step's, and are not looked for again."""
    r = region
    if STRUCTURED:
        return r
    changed = ctx.o2.union if ORDER2 else r.touched
    wet, wet_last, n_wet = r.wet, r.wet_last, r.n_wet
    n_gained = 0
    n_lost = 0
    if r.wet_changes != 0:
        wet, wet_last = wet_last, wet
        n_wet, n_gained, n_lost = wet_after(changed, r.n_changed, nxt.h, loop.physics.h_zero,
                                            wet, wet_last, n_wet, ctx.lw.gained, ctx.lw.lost,
                                            ORDER2, loop.supply.mask)
    same_wet = not ORDER2 and n_gained == 0 and n_lost == 0
    return FaceRegion(wet, wet_last, r.touched, r.active_faces, r.new_faces, r.new_cells,
                      r.fresh, n_wet, r.n_changed, r.n_active, r.n_touched, r.n_fresh,
                      r.n_changed, n_gained, n_lost, r.n_synced, r.list_stamp, r.listed,
                      same_wet, r.wet_changes)


def _end(region, ctx, loop, cur, t, steps):
    """The next call's stamps follow this one's; the newest state back where it is in the
    work buffers (faces, order 1: only where a step touched)."""
    fields, work = loop.fields, loop.work
    work.clock[0] += steps + 1
    if STRUCTURED or ORDER2:
        end_loop(fields.stats, t, steps, fields.h, fields.hu, fields.hv, cur.h, cur.hu,
                 cur.hv)
    else:
        if steps % 2 == 1:
            for c in range(region.n_synced):
                i = work.synced[c]
                fields.h[i] = cur.h[i]
                fields.hu[i] = cur.hu[i]
                fields.hv[i] = cur.hv[i]
        record_end(fields.stats, t, steps)


#: Placeholders of the order-1 sweeps :func:`_step`'s copies call (their law's copy):
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
def order2_work(m2, f2, structured, parallel, width):
    """:data:`Order2Work` for ``m2`` cells and ``f2`` faces (0 and 0 at order 1), once a call
    (none per step); ``width``: the values of a face's side (3, its state; MUSCL-Hancock's
    7, what it emits)."""
    return Order2Work(np.zeros((m2 if structured else 0, 4)),
                      np.zeros((0 if structured else m2, 2)),
                      np.zeros((0 if structured else f2, 2, width)),
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
def heun_profile(mesh, physics, cur, nxt, flux, transport, flag, o2, limiter, when):
    """An order-2 step on a profile: stage 1 (``cur`` -> ``nxt``), stage 2 (``nxt`` -> o2's
    ``s_*``), each a full step of the seed's scheme on its reconstruction, and Heun's average
    into ``nxt``. Returns ``(ok, outflow, dt_limit, moving, film, clamped, kinetic,
    fallbacks)``."""
    s = Conserved(o2.s_h, o2.s_hu, o2.s_hv)
    reconstruct_profile(cur.h, cur.hu, physics.h_zero, limiter, o2.recon)
    ok, out, lim, moving, film, clamped, kinetic = step_profile(
        mesh, physics, cur, nxt, flux, flag, when, True, o2.recon)
    if not ok:
        return ok, out, lim, moving, film, clamped, kinetic, 0
    for k in range(flag.size):
        o2.flag1[k] = flag[k]
    reconstruct_profile(nxt.h, nxt.hu, physics.h_zero, limiter, o2.recon)
    ok, out2, lim, moving, film, clamped2, kinetic = step_profile(
        mesh, physics, nxt, s, flux, flag, when, True, o2.recon)
    if not ok:
        return ok, out, lim, moving, film, clamped, kinetic, 0
    profile_transport(flag, flux, physics.dirac, transport)
    lim, moving, film, kinetic, fallbacks = heun_faces(
        o2.all_cells, cur.h.size, mesh, physics, cur, s, o2.flag1, transport, nxt)
    return (ok, 0.5 * (out + out2), lim, moving, film, clamped + clamped2, kinetic,
            fallbacks)


def _order2_faces(mesh, physics, cur, nxt, flux, transport, flag, work, o2, lists, stamp,
                  when, min_parallel_cells):
    """An order-2 step on faces: stage 1 on the step's ``lists``, stage 2 on lists of its
    own (stamped ``stamp + 1``), Heun's average over the cells either touched (their union
    in o2's ``union``, stamped ``stamp + 2``). A template: compiled with and without threads
    (``PARALLEL``, :data:`ORDER2_FACES`). Returns ``(ok, outflow, dt_limit, moving, film,
    clamped, kinetic, fallbacks, cells changed)``."""
    m = mesh
    s = Conserved(o2.s_h, o2.s_hu, o2.s_hv)
    flag1, touched, n_touched = o2.flag1, lists.touched, lists.n_touched
    ok, out, lim, moving, film, clamped, kinetic = order2_stage(
        mesh, physics, cur, nxt, flux, transport, flag, when, lists, o2, min_parallel_cells)
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
        mesh, physics, nxt, s, flux, transport, flag, when, lists2, o2, min_parallel_cells)
    if not ok:
        return ok, out, lim, moving, film, clamped, kinetic, 0, n_touched
    union = o2.union
    n_changed = merge_lists(touched, n_touched, o2.touched2, n_touched2, work.cell_stamp,
                            stamp + 2, union)
    if PARALLEL and n_changed >= min_parallel_cells:
        lim, moving, film, kinetic, fallbacks = heun_cells_parallel(
            union, n_changed, mesh, physics, cur, s, flag1, transport, nxt, o2.cell_sums)
    else:
        lim, moving, film, kinetic, fallbacks = heun_faces(
            union, n_changed, mesh, physics, cur, s, flag1, transport, nxt)
    for c in range(n_changed):
        flag1[union[c]] = DRY
    return (ok, 0.5 * (out + out2), lim, moving, film, clamped + clamped2, kinetic,
            fallbacks, n_changed)


def _hancock_faces(mesh, physics, cur, nxt, flux, transport, flag, work, o2, lists, stamp,
                   when, min_parallel_cells):
    """An order-2 step on faces by MUSCL-Hancock: one stage (:func:`_stage_faces` with the
    predictor) on the step's ``lists``; the cells it changed are its touched cells (into
    o2's ``union``, which the step's other hooks read). :func:`_order2_faces`' arguments
    and returns (no fallbacks: there is no average to fall back from)."""
    ok, out, lim, moving, film, clamped, kinetic = order2_stage(
        mesh, physics, cur, nxt, flux, transport, flag, when, lists, o2, min_parallel_cells)
    touched, n_touched, union = lists.touched, lists.n_touched, o2.union
    for c in range(n_touched):
        union[c] = touched[c]
    return ok, out, lim, moving, film, clamped, kinetic, 0, n_touched


def _stage_faces(mesh, physics, cur, nxt, flux, transport, flag, when, lists, o2,
                 min_parallel_cells):
    """One stage of order 2 on faces, from ``cur`` into ``nxt`` on the listed faces and
    cells: the reconstruction (o2's ``face_state``), then the step. In MUSCL-Hancock's
    copies (``HANCOCK``) the sides are of the state half a step on and gravity and friction
    take the step's midpoint (:data:`~avflow.numerics.physics.MIDPOINT`); in Heun's, a
    stage's own state.
    In the copy with threads (``PARALLEL``) a stage of at least ``min_parallel_cells``
    cells runs both in gather form on Numba's threads (:mod:`avflow.numerics.face_gather`,
    the same bits), any other on :func:`reconstruct_cells` and :func:`step_faces`.
    Returns step_faces' ``(ok, outflow, dt_limit, moving, film, clamped, kinetic)``."""
    m = mesh
    timing = MIDPOINT if HANCOCK else True
    predictor = Predictor(0.5 * when.dt, m.gamma_x, m.gamma_y, m.gamma_z, m.curvature,
                          physics.law, physics.params, physics.g, m.density)
    if PARALLEL and lists.n_touched >= min_parallel_cells:
        reconstruct_cells_parallel(m.face_cells, m.face_frame, m.face_length, m.face_offset,
                                   m.cell_area, cur.h, cur.hu, cur.hv, physics.h_zero,
                                   m.cell_face_ptr, m.cell_face_idx, lists.touched,
                                   lists.n_touched, o2.velocity, o2.face_state, predictor)
        return step_cells_parallel(mesh, physics, cur, nxt, flux, transport, flag, when,
                                   lists, o2.face_state, o2.cell_sums, timing)
    reconstruct_cells(m.face_cells, m.face_frame, m.face_length, m.face_offset, m.cell_area,
                      cur.h, cur.hu, cur.hv, physics.h_zero, m.cell_face_ptr, m.cell_face_idx,
                      lists.touched, lists.n_touched, o2.velocity, o2.face_state, predictor)
    return step_faces(mesh, physics, cur, nxt, flux, transport, flag, when, lists, timing,
                      o2.face_state, o2.no_emit)


#: Placeholders of the constants of the copies of :func:`_advance`, :func:`_order2_faces`
#: and :func:`_stage_faces` (see :func:`time_loop`), and of what their copies call (the
#: functions on threads only in the copies with threads)
STRUCTURED = ORDER2 = PARALLEL = HANCOCK = False
reconstruct_cells_parallel = step_cells_parallel = heun_cells_parallel = None
order2_stage = order2_faces = None

#: :func:`_stage_faces` serial and with threads, Heun's and MUSCL-Hancock's, and the steps
#: that run them (:func:`_order2_faces`, :func:`_hancock_faces`), each under its own name
ORDER2_STAGE = {
    (parallel, scheme): specialize(
        _stage_faces, ("_parallel" if parallel else "_serial")
        + ("_hancock" if scheme == "hancock" else ""), PARALLEL=parallel,
        HANCOCK=scheme == "hancock",
        reconstruct_cells=predict_cells if scheme == "hancock" else reconstruct_cells,
        reconstruct_cells_parallel=(None if not parallel else _predict_par
                                    if scheme == "hancock" else _recon_par),
        step_cells_parallel=_step_parallel if parallel else None)
    for parallel in (False, True) for scheme in ("heun", "hancock")}
ORDER2_FACES = {
    (parallel, "heun"): specialize(_order2_faces, "_parallel" if parallel else "_serial",
                                   PARALLEL=parallel, order2_stage=ORDER2_STAGE[parallel, "heun"],
                                   heun_cells_parallel=_heun_parallel if parallel else None)
    for parallel in (False, True)}
ORDER2_FACES.update({
    (parallel, "hancock"): specialize(_hancock_faces, "_parallel" if parallel else "_serial",
                                      order2_stage=ORDER2_STAGE[parallel, "hancock"])
    for parallel in (False, True)})


def _advance_for(structured: bool, order2: bool, kind: int | None = None,
                 parallel: bool = False, scheme: str = "heun"):
    """:func:`avflow.numerics.loop.advance` with the face kernel's region, its hooks
    compiled with the mesh kind and the order constants (and, at order 1, calling the sweep
    of the friction law ``kind``; ``parallel``: with its passes on threads, whose functions
    the other copies never compile; ``scheme``: order 2's time scheme on faces)."""
    suffix = f"_{'profile' if structured else 'faces'}_order{2 if order2 else 1}"
    if order2 and scheme == "hancock":
        suffix += "_hancock"
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
    fns = {"start": _start, "before": _before, "step": _step, "source": _source,
           "observe": _observe, "after": _after, "end": _end}
    given = shared_names(fns, STRUCTURED=structured, ORDER2=order2, PARALLEL=parallel,
                         HANCOCK=order2 and scheme == "hancock",
                         order2_faces=ORDER2_FACES[parallel, scheme], **names)
    hooks = {f"region_{hook}": specialize(fn, suffix, inline="always", **given[hook])
             for hook, fn in fns.items()}
    return specialize(advance, suffix, **hooks)


#: The time loop per (structured, order 2, law kind, threads, time scheme): the law only
#: at order 1, whose sweeps have a copy per law (:data:`avflow.numerics.profile.STEP`,
#: :data:`avflow.numerics.face_sweep.STEP`), None at order 2; threads only on faces; the
#: scheme "heun" except at order 2 on faces, which has "hancock" too
ADVANCE = {(s, o, k, p, sc): _advance_for(s, o, k, p, sc)
           for s, o, kinds, threads, schemes in (
               (True, False, tuple(_PROFILE_STEP), (False,), ("heun",)),
               (True, True, (None,), (False,), ("heun",)),
               (False, False, tuple(_FACES_STEP), (False, True), ("heun",)),
               (False, True, (None,), (False, True), ("heun", "hancock")))
           for k in kinds for p in threads for sc in schemes}


def time_loop(structured: bool, order: int, law: int, parallel: bool = False,
              scheme: str = "heun"):
    """The time loop (:func:`avflow.numerics.loop.advance`: its arguments, its status
    codes; ``extra``: ``(sweep_geo, sweep_work)``, what the face kernel's order-1 step reads
    and works in, :func:`avflow.numerics.face_sweep.geometry`,
    :func:`~avflow.numerics.face_sweep.work`; empty elsewhere,
    :func:`~avflow.numerics.face_sweep.unused`) compiled for this
    mesh kind (``structured``: a profile) and ``order`` alone (and, at order 1, for the
    friction ``law``); ``parallel``: with the passes on threads (on faces only;
    profiles run the serial copy); ``scheme``: order 2's time scheme on faces ("hancock" or
    "heun"; profiles run Heun's)."""
    structured, order2 = bool(structured), order == 2
    parallel = bool(parallel) and not structured
    scheme = scheme if order2 and not structured else "heun"
    return ADVANCE[structured, order2, None if order2 else law_kind(law), parallel, scheme]
