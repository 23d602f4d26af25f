"""What every time loop shares: its status codes, the slots of the ``stats`` vector it keeps
between calls (named for readers outside the kernels by :class:`Statistics`), the step size of
eq. 41 cut to land on an output time, and the stop rules."""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

#: What every time loop takes by name (Numba types named tuples of arrays and scalars):
#: the state and running maps of a run, changed in place (``stats``: the ``ST_*`` slots;
#: ``maps``: the registered maps, a row each, :mod:`avflow.numerics.observers`;
#: ``supplied``: what the registered sources added per cell, :mod:`avflow.numerics.supply`)
Fields = namedtuple("Fields", "h hu hv flag peak_h peak_speed arrival last_moved erodible "
                    "maps supplied stats")
#: the physics: friction law and its parameters (numerics.rheology), gravity, the Dirac
#: flux on or off, the dry and zero thresholds, the mass source (numerics.sources); the
#: registered sources are an argument of their own (numerics.supply.Supply: a structure
#: of arrays inside this one would keep it from Numba's threads)
Physics = namedtuple("Physics", "law params g dirac h_dry h_zero source")
#: how far and how to run: CFL number, target time, step budget, stop rules, order 2's
#: limiter, and the least cells (and grid rows per block) of a step on threads
Control = namedtuple("Control", "cfl t_target max_steps stop_volume stop_kinetic limiter "
                     "min_parallel_cells min_block_rows")

#: What the face kernel's time loop reads of a mesh (:meth:`Solver` builds it once):
#: faces, frames, lengths, per-cell factors, each cell's faces (CSR), order 2's offsets
FaceMesh = namedtuple("FaceMesh", "face_cells face_frame face_length cell_area cfl_factor "
                      "density gamma_x gamma_y gamma_z curvature cell_face_ptr "
                      "cell_face_idx face_offset")
#: what it works in and keeps from one call to the next: the work buffers, order 2's face
#: fluxes, each cell's transport, and the active lists' stamps and clock
FaceWork = namedtuple("FaceWork", "h_work hu_work hv_work flux transport face_stamp "
                      "cell_stamp cell_sync synced clock")


#: What the square-grid kernel's time loop reads of its ``ny x nx`` grid
#: (:class:`~avflow.terrain.squaregrid.SquareGrid`: faces by row and column, per-cell factors
#: on the full grid; order 2's offsets of each face's two sides, ``(ny, 4, nx + 1)`` and
#: ``(ny + 1, 4, nx)``, empty at order 1)
GridMesh = namedtuple("GridMesh", "nx ny valid x_code x_frame x_length y_code y_frame "
                      "y_length cell_area inv_area cfl_factor density gamma_x gamma_y gamma_z "
                      "curvature x_offset y_offset")
#: its work buffers and the ring buffers of its blocks, a set per thread; order 2's second
#: stage (``s_*``), first stage's flags and each cell's transport (empty at order 1)
GridWork = namedtuple("GridWork", "h_work hu_work hv_work rings s_h s_hu s_hv flag1 transport")
#: one buffer of the conserved variables (the time loops swap two each step)
Conserved = namedtuple("Conserved", "h hu hv")

#: one step's times: the step, the CFL step the threshold is tested with (eq. 49: the
#: decision depends on the state alone), and the time the step lands on
StepTime = namedtuple("StepTime", "dt dt_decide t_new")
#: the face kernel's active lists: the listed faces and the cells they touch, whether they
#: are the last step's (``same``: a step keeps what it made of them), and the stamp that
#: marks a listed face (``face_stamp[f] == stamp``)
Lists = namedtuple("Lists", "active_faces n_active touched n_touched same face_stamp stamp")

# Status returned by the time loop (time_loop)
REACHED_TARGET = 0
STOPPED = 1
MAX_STEPS = 2
FAILED = 3

MAX_RETRIES = 12
#: Order 2 marks its lists with distinct stamps: stage 1, then stage 2 and the union of
#: both for every attempt of a step (a halved step lists again).
STAMPS_PER_STEP = 2 * MAX_RETRIES + 1

# Slots of the float64 ``stats`` vector shared between the time loop and its caller.
ST_TIME = 0
ST_DT_LIMIT = 1  #: dt allowed by the CFL condition with cfl = 1, for the next step
ST_STEPS = 2
ST_DT_MIN = 3
ST_DT_MAX = 4
ST_MOVING = 5  #: volume of cells with u != 0 and h > h_dry after the last step
ST_FILM = 6  #: volume of cells with u != 0 and 0 < h <= h_dry (a vanishing film)
ST_OUTFLOW = 7  #: cumulative volume that left through open boundaries
ST_CLAMPED = 8  #: cumulative count of cell-steps whose normal acceleration was clamped at 0
ST_RETRIES = 9  #: cumulative count of halved steps
ST_KINETIC = 10  #: kinetic energy / density, sum of h A |u|^2 / 2 (m^5 s^-2), after the last step
ST_KINETIC_PEAK = 11  #: its largest value so far
ST_FALLBACK = 12  #: cumulative count of cell-steps where order 2 fell back to order 1
ST_SOURCE = 13  #: cumulative volume the mass source added (numerics.sources)
ST_SUPPLY = 14  #: cumulative volume the registered sources added (numerics.supply)
N_STATS = 15


@njit(error_model="numpy", cache=True)
def step_size(stats, cfl, t, t_target):
    """The next step of a time loop: ``cfl`` times the state's CFL limit (the whole interval
    when nothing moves), cut to land on ``t_target``. Returns ``(dt, dt_decide, last)``:
    ``dt_decide`` is the uncut step, with which the Coulomb threshold is always tested (the
    decision depends on the state alone), ``last`` whether the step lands on ``t_target``."""
    dt_max = stats[ST_DT_LIMIT]
    dt = cfl * dt_max if dt_max < np.inf else t_target - t
    if t + dt >= t_target:
        return t_target - t, dt, True
    return dt, dt, False


@njit(error_model="numpy", cache=True)
def record_step(stats, dt, dt_limit, moving, film, kinetic, clamped, outflow, stop_volume,
                stop_kinetic, steps, max_steps):
    """A finished step into ``stats`` (the ``ST_*`` slots; ``kinetic`` is the sum of
    h A |u|^2), then the stop rules: STOPPED (moving volume under ``stop_volume``, or kinetic
    energy at most ``stop_kinetic`` times its peak; negative: rule off), MAX_STEPS, or
    REACHED_TARGET to go on. ``steps``: taken in this call so far."""
    stats[ST_DT_LIMIT] = dt_limit
    stats[ST_MOVING] = moving
    stats[ST_FILM] = film
    stats[ST_KINETIC] = 0.5 * kinetic
    stats[ST_KINETIC_PEAK] = max(stats[ST_KINETIC_PEAK], 0.5 * kinetic)
    stats[ST_CLAMPED] += clamped
    stats[ST_OUTFLOW] += outflow
    stats[ST_DT_MIN] = min(stats[ST_DT_MIN], dt)
    stats[ST_DT_MAX] = max(stats[ST_DT_MAX], dt)
    if stop_volume >= 0.0 and moving < stop_volume:
        return STOPPED
    if stop_kinetic >= 0.0 and kinetic <= stop_kinetic * (2.0 * stats[ST_KINETIC_PEAK]):
        return STOPPED
    if stats[ST_STEPS] + steps >= max_steps:
        return MAX_STEPS
    return REACHED_TARGET


@njit(error_model="numpy", cache=True)
def end_loop(stats, t, steps, h, hu, hv, cur_h, cur_hu, cur_hv):
    """The end of a time loop that swaps two buffers each step: the newest state back in
    ``(h, hu, hv)`` when it sits in the work buffers (an odd number of steps), and
    :func:`record_end`. (Loops that know where the buffers differ copy only there.)"""
    if steps % 2 == 1:  # element by element: no shape check and message to compile
        for i in range(h.size):
            h[i] = cur_h[i]
            hu[i] = cur_hu[i]
            hv[i] = cur_hv[i]
    record_end(stats, t, steps)


@njit(error_model="numpy", cache=True)
def record_end(stats, t, steps):
    """The time and the step count of a time loop's call into ``stats``."""
    stats[ST_TIME] = t
    stats[ST_STEPS] += steps



def _slot(index: int, doc: str):
    return property(lambda self: float(self.array[index]), doc=doc)


class Statistics:
    """The ``stats`` vector of a run, by name: what :mod:`avflow.simulation` reads (the
    kernels write its ``ST_*`` slots)."""

    __slots__ = ("array",)

    def __init__(self, array: np.ndarray):
        self.array = array

    time = _slot(ST_TIME, "time reached, s")
    dt_limit = _slot(ST_DT_LIMIT, "CFL step (cfl = 1) of the current state, s")
    steps = _slot(ST_STEPS, "steps taken")
    dt_min = _slot(ST_DT_MIN, "shortest step taken, s")
    dt_max = _slot(ST_DT_MAX, "longest step taken, s")
    moving_volume = _slot(ST_MOVING, "volume of moving cells thicker than h_dry, m^3")
    film_volume = _slot(ST_FILM, "volume of moving cells at most h_dry thick, m^3")
    outflow_volume = _slot(ST_OUTFLOW, "volume that left through open sides, m^3")
    clamped_cells = _slot(ST_CLAMPED, "cell-steps whose normal acceleration was clamped at 0")
    halved_steps = _slot(ST_RETRIES, "steps redone with half the step")
    kinetic = _slot(ST_KINETIC, "kinetic energy / density after the last step, m^5 s^-2")
    kinetic_peak = _slot(ST_KINETIC_PEAK, "largest kinetic energy / density, m^5 s^-2")
    order2_fallbacks = _slot(ST_FALLBACK, "cell-steps where order 2 fell back to order 1")
    supplied_volume = _slot(ST_SUPPLY, "volume the registered sources added, m^3 (as counted "
                            "by the steps; the balance reads their book per cell)")
    source_volume = _slot(ST_SOURCE, "volume the mass source added, m^3 (as counted by the "
                          "steps; the balance reads the erodible layer itself)")
