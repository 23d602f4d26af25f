"""The one time loop of every kernel (issue 27): step size (eq. 41, cut to land on an
output time), retry by halving, the mass sources, the stop rules and the statistics.

What differs between kernels is only how they find and walk the cells a step touches, their
*region*: the face kernel keeps lists of active faces and cells (:mod:`avflow.numerics.timeloop`),
the square-grid kernel the row spans of its swept band (:mod:`avflow.numerics.square_grid`).
A region is six hooks, named here as placeholders and replaced in each kernel's copies of
:func:`advance` (:func:`avflow.numerics.vectorize.specialize`; Numba's cache cannot keep a
loop that takes functions as arguments, measured: it compiles it again in every process):

- ``region_start(loop)`` -> ``(region, ctx)``: what the call works in; ``region`` is a named
  tuple of what changes from step to step (each hook returns it anew), ``ctx`` what does not;
- ``region_before(region, ctx, loop, cur, nxt, steps)`` -> ``region``: the cells the next
  step may touch, their state made ready;
- ``region_step(region, ctx, loop, cur, nxt, when, steps, attempt)`` -> ``(ok, outflow,
  dt_limit, moving, film, clamped, kinetic, fallbacks, region)``: one step (order 2: Heun's
  two stages and merge) from ``cur`` into ``nxt``; ``ok`` False where h < 0 would follow;
- ``region_source(region, ctx, loop, nxt, when)`` -> the largest inverse CFL limit of the
  cells the source changed: the mass source over the step's cells (only wet cells gain),
  its volume added to ``stats``;
- ``region_observe(region, ctx, loop, nxt, when)``: the running maps of the cells the step
  changed, from their accepted state (:mod:`avflow.numerics.observers`): once per accepted
  step, after the source, so that a step redone with half the time step writes no map;
- ``region_after(region, ctx, loop, nxt)`` -> ``region``: the wet cells after the step;
- ``region_end(region, ctx, loop, cur, t, steps)``: the newest state back in the fields
  where it sits in the work buffers, and the call's time and step count into ``stats``.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np

from avflow.numerics.cpu import SOURCE_NONE, dt_from_inverse
from avflow.numerics.sources import SRC_KIND
from avflow.numerics.stepping import (FAILED, MAX_RETRIES, REACHED_TARGET, ST_FALLBACK,
                                      ST_RETRIES, ST_SUPPLY, ST_TIME, Conserved, StepTime,
                                      record_step, step_size)
from avflow.numerics.supply import supply_cells

#: What a call of the loop runs on: the kernel's mesh, the fields (state, running maps,
#: ``stats``), its work buffers, the physics, the run's control, the kernel's own extra
#: (grid: the threads; faces: the order-1 sweep's geometry and work), and the registered
#: sources (:data:`avflow.numerics.supply.Supply`, in the kernel's numbering of cells)
Loop = namedtuple("Loop", "mesh fields work physics run extra supply")

#: Placeholders of a region's hooks (see the module's docstring)
region_start = region_before = region_step = region_source = region_after = None
region_observe = region_end = None


def advance(mesh, fields, work, physics, run, extra, supply):
    """Advance ``fields.h, hu, hv`` in place until ``run.t_target``, a stop, or
    ``run.max_steps``. Returns a status code: REACHED_TARGET, STOPPED, MAX_STEPS or FAILED.

    A template: each kernel compiles its copies with its region's hooks (module docstring).
    The arguments are named tuples (:mod:`avflow.numerics.stepping`); ``extra`` is the
    kernel's own, ``supply`` the registered sources (:mod:`avflow.numerics.supply`)."""
    loop = Loop(mesh, fields, work, physics, run, extra, supply)
    stats, source = fields.stats, physics.source
    cfl, t_target = run.cfl, run.t_target
    region, ctx = region_start(loop)
    cur = Conserved(fields.h, fields.hu, fields.hv)
    nxt = Conserved(work.h_work, work.hu_work, work.hv_work)
    t = stats[ST_TIME]
    status = REACHED_TARGET
    # an int64 from the start: a literal 0 had Numba compile a hook that is a function of
    # its own (the square grid's step) twice, once for the literal (1.4 s of a first run)
    steps = np.int64(0)
    while t < t_target:
        dt, dt_decide, last = step_size(stats, cfl, t, t_target)
        region = region_before(region, ctx, loop, cur, nxt, steps)
        ok = False
        for attempt in range(MAX_RETRIES):
            when = StepTime(dt, dt_decide, t_target if last else t + dt)
            ok, out, lim, moving, film, clamped, kinetic, fallbacks, region = region_step(
                region, ctx, loop, cur, nxt, when, steps, attempt)
            if ok:
                break
            dt *= 0.5  # eq. 41 is a sufficient condition: a step that would give h < 0 halves
            last = False
            stats[ST_RETRIES] += 1
        if not ok:
            status = FAILED
            break
        if source[SRC_KIND] != SOURCE_NONE:  # the source hook, once per accepted step
            lim = min(lim, dt_from_inverse(region_source(region, ctx, loop, nxt, when)))
        if supply.cells.size:  # registered sources: their cells are in every step's region
            added, inv = supply_cells(supply.cells, supply.weights, supply.params, nxt.h,
                                      nxt.hu, nxt.hv, fields.supplied, mesh.cell_area,
                                      mesh.cfl_factor, mesh.gamma_z, physics.g, when.dt,
                                      when.t_new)
            stats[ST_SUPPLY] += added
            lim = min(lim, dt_from_inverse(inv))
        region_observe(region, ctx, loop, nxt, when)  # the accepted state, sources included
        t = t_target if last else t + dt
        steps += 1
        region = region_after(region, ctx, loop, nxt)
        stats[ST_FALLBACK] += fallbacks
        cur, nxt = nxt, cur
        status = record_step(stats, dt, lim, moving, film, kinetic, clamped, out,
                             run.stop_volume, run.stop_kinetic, steps, run.max_steps)
        if status != REACHED_TARGET:
            break
    region_end(region, ctx, loop, cur, t, steps)
    return status
