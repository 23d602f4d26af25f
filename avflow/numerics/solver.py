"""Solver and state (the Clawpack split: the Riemann part is :mod:`avflow.numerics.kinetic`).

- :class:`State` holds ``h`` and the discharge ``(hu, hv)`` in the bed's tangent basis, the
  time and the running observers (peak thickness, peak speed) of one run.
- :class:`Solver` binds a :class:`~avflow.terrain.bed.Terrain` and a friction law to the Numba
  kernels of :mod:`avflow.numerics.kernels`; :meth:`Solver.advance` runs the whole time loop inside
  Numba up to a target time, so no Python runs per step and no array is allocated per step.

Nothing here reads files or knows of scenarios: :mod:`avflow.simulation.runner` wires those.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from avflow.numerics import face_gather, face_sweep, kernels, registry, stepping, supply
from avflow.numerics.sources import MassSource, no_source
from avflow.numerics.physics import DRY, UNDER_THRESHOLD
from avflow.numerics.stepping import (ST_DT_LIMIT, ST_DT_MIN, ST_STEPS, ST_TIME, FaceMesh,
                                      FaceWork, GridMesh, GridWork, Statistics)
from avflow.numerics.rheology import FOREST_SLOT, N_PARAMS, PER_CELL, Law, law_name
from avflow.numerics.kinetic import density_factor
from avflow.numerics.reconstruction import LIMITERS
from avflow.terrain.bed import Terrain
from avflow.terrain.mesh import EAST, NORTH, WEST
from avflow.terrain.squaregrid import SquareGrid, square_grid

STATUS_NAMES = {
    stepping.REACHED_TARGET: "running",
    stepping.STOPPED: "stopped",
    stepping.MAX_STEPS: "max_steps",
    stepping.FAILED: "failed",
}


@dataclass
class State:
    """Conserved variables per cell and the observers of a run (float64 everywhere)."""

    h: np.ndarray  #: thickness normal to the bed, m
    hu: np.ndarray  #: discharge along the first tangent axis, m^2/s
    hv: np.ndarray  #: discharge along the second tangent axis, m^2/s
    flag: np.ndarray  #: uint8 per cell from the last step: physics.FLOWING / UNDER_THRESHOLD / DRY
    peak_h: np.ndarray  #: running maximum of h, m
    peak_speed: np.ndarray  #: running maximum of |u|, m/s
    arrival: np.ndarray  #: first time h exceeded the dry threshold, s (NaN: never)
    last_moved: np.ndarray  #: end of the last step in which u != 0, s (NaN: never moved)
    #: what is left of the erodible layer, m per cell (empty: the run has no mass source)
    erodible: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: the registered maps (avflow.extend), a row each (none: no rows)
    maps: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    #: what the registered sources added, m of flow thickness per cell (empty: none)
    supplied: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stats: np.ndarray = field(default_factory=lambda: np.zeros(stepping.N_STATS))

    @property
    def statistics(self) -> Statistics:
        """The time loop's statistics, by name."""
        return Statistics(self.stats)

    @property
    def t(self) -> float:
        return float(self.stats[ST_TIME])

    @property
    def steps(self) -> int:
        return int(self.stats[ST_STEPS])

    def copy(self) -> "State":
        """A copy of every array (a call on it leaves this state as it is)."""
        import dataclasses

        return State(**{f.name: getattr(self, f.name).copy() for f in dataclasses.fields(State)})

    def speed(self) -> np.ndarray:
        """|u| per cell (m/s), 0 where dry."""
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.hypot(self.hu, self.hv) / self.h
        return np.where(self.h > 0.0, s, 0.0)


def registered_maps(n: int) -> np.ndarray:
    """The registered maps' storage for ``n`` cells: a row per map (avflow.extend), at its
    initial value."""
    from avflow.scenario.extensions import MAPS

    maps = np.empty((len(MAPS), n))
    for k, entry in enumerate(MAPS.values()):
        maps[k] = entry.initial
    return maps


def face_offsets(terrain: Terrain) -> np.ndarray:
    """(n_faces, 2, 2): from each side's cell centre half the way to the other's, in that
    cell's tangent basis (zero on boundary faces): where order 2 evaluates its slopes.

    On a grid the point is the face's midpoint; on the triangles' median dual cells the
    midpoint of the edge between the two vertices, which the dual face crosses.
    """
    xx, yy = terrain.cell_xy()
    centre = np.stack([xx, yy, terrain.bed_elevation], axis=1)
    basis = terrain.tangent_basis
    fc = terrain.mesh.face_cells
    inner = fc[:, 1] >= 0
    i, j = fc[inner, 0], fc[inner, 1]
    half = 0.5 * (centre[j] - centre[i])
    out = np.zeros((fc.shape[0], 2, 2))
    out[inner, 0] = np.einsum("kc,kbc->kb", half, basis[i])
    out[inner, 1] = np.einsum("kc,kbc->kb", -half, basis[j])
    return np.ascontiguousarray(out)


def grid_offsets(layout: SquareGrid, mesh, face_offset: np.ndarray) -> tuple:
    """:func:`face_offsets` on a square grid's layout: ``(ny, 4, nx + 1)`` for its x faces
    and ``(ny + 1, 4, nx)`` for its y faces, ``(rx, ry)`` of side 0 then of side 1."""
    ny, nx = layout.ny, layout.nx
    x_off = np.zeros((ny, 4, nx + 1))
    y_off = np.zeros((ny + 1, 4, nx))
    d = mesh.face_direction
    r, c = np.divmod(layout.place[mesh.face_cells[:, 0]], nx)
    r = r + (d == NORTH)
    c = c + (d == EAST)
    on_x = (d == EAST) | (d == WEST)
    both = face_offset.reshape(-1, 4)
    x_off[r[on_x], :, c[on_x]] = both[on_x]
    y_off[r[~on_x], :, c[~on_x]] = both[~on_x]
    return x_off, y_off


@dataclass
class ThreadChoice:
    """Which threads the next steps of a solver with ``threads`` None run on: all of them
    (``most``) or one. :data:`PROBE_STEPS` steps are timed on each; all threads are kept
    only when at least :data:`GAIN` faster. Probed again after :data:`FIRST_INTERVAL`
    steps, then twice as late each time the same clear choice stands."""

    most: int
    choice: int = 1
    next_probe: int = 0
    #: whether the flow has been large enough for threads (and their loop compiled)
    ready: bool = False
    interval: int = 0
    PROBE_STEPS = 4
    FIRST_INTERVAL = 256
    GAIN = 0.9

    def decide(self, one: float, many: float, steps: int) -> None:
        """``one``, ``many``: seconds the probe's steps took on one thread and on all."""
        choice = self.most if many < self.GAIN * one else 1
        clear = many < self.GAIN * one or many > one / self.GAIN
        self.interval = (2 * self.interval if choice == self.choice and clear and self.interval
                         else self.FIRST_INTERVAL)
        self.choice, self.next_probe = choice, steps + self.interval


@dataclass
class Solver:
    """The kinetic scheme of the seed on one terrain with one friction law.

    ``h_dry`` (m) only classifies: a moving cell thinner than it is a *film* (counted, never
    deleted) and does not keep a run alive. ``dirac=False`` switches the zero-temperature flux
    off (the classical kinetic scheme), for studies of what it changes.
    """

    terrain: Terrain
    law: Law
    params: np.ndarray
    gravity: float = 9.81
    cfl: float = 0.5
    dirac: bool = True
    h_dry: float = 0.0
    #: m: a cell thinner than this after a step keeps its mass but no momentum (a round-off
    #: residue of emptying fluxes, see physics.final_momentum); 0 disables it.
    h_zero: float = 0.0
    #: 1: the seed's first-order scheme; 2: limited linear reconstruction and Heun's two
    #: stages (:mod:`avflow.numerics.reconstruction`)
    order: int = 1
    limiter: str = "minmod"
    #: order 2's time scheme: "hancock" (MUSCL-Hancock: one flux sweep of the sides
    #: predicted half a step on, physics.half_step; the square-grid kernel), "heun" (Heun's
    #: two stages and their mean; every kernel), "auto": the kernel's first
    #: (registry.Kernel.schemes)
    time_scheme: str = "auto"
    #: CPU threads of the square-grid kernel and of the face kernel (None: every core, where
    #: timed probes show them faster than one thread, else one: ThreadChoice); the answer
    #: does not depend on it. 1 runs the serial passes, outside
    #: Numba's thread pool. Profiles run on one.
    threads: int | None = None
    #: "auto": the square-grid kernel (:mod:`avflow.numerics.square_grid`) on square grids
    #: (both orders), the face kernel elsewhere; "faces": the face kernel everywhere (the
    #: reference); "grid": the square-grid kernel, an error where it does not apply.
    kernel: str = "auto"
    #: where the kernels run: "cpu", or "cuda" (a GPU: square grids at orders 1 and 2 (Heun),
    #: :mod:`avflow.numerics.cuda_grid`); the kernels of
    #: :mod:`avflow.numerics.registry`
    backend: str = "cpu"
    #: a mass source and its erodible layer (:mod:`avflow.numerics.sources`); None: none
    source: MassSource | None = None
    #: forest: the resistance coefficient ``c_f`` per cell (drag ``c_f |u|^2``, AvaFrame's
    #: resistance areas; 0 outside forest), or None
    forest: np.ndarray | None = None
    #: sources registered through avflow.extend, over their areas
    #: (:class:`~avflow.numerics.supply.AreaSource`): mass added on wet and dry cells
    sources: tuple = ()

    def __post_init__(self):
        if self.order not in (1, 2):
            raise ValueError(f"order must be 1 or 2, got {self.order}")
        if self.limiter not in LIMITERS:
            raise ValueError(f"limiter must be one of {', '.join(LIMITERS)}, got {self.limiter!r}")
        if not 0.0 < self.cfl <= 1.0:
            raise ValueError("cfl must be in (0, 1]: positivity of h needs it (eq. 41)")
        self._set_params()
        if self.threads is not None and self.threads < 1:
            raise ValueError(f"threads must be at least 1, got {self.threads}")
        m = self.terrain.mesh
        n = m.n_cells
        if self.source is not None and self.source.erodible.shape != (n,):
            raise ValueError(f"the erodible layer has {self.source.erodible.size} cells, the "
                             f"mesh {n}")
        self._source = no_source()[1] if self.source is None else self.source.vector()
        self.sources = tuple(self.sources)
        from avflow.numerics.variants import check_registered

        check_registered(self._law_code, self.sources, self.params)  # before any compiling
        self._supply = supply.pack(self.sources, n)
        self._grid = None
        self._released = False
        self._call_steps = 64  # steps of the next call of the compiled loop (advance)
        self._auto = None  # ThreadChoice of threads None
        # Per-cell factors derived from the geometry once: P / (2 A) for the CFL limit
        # (eq. 41) and 1 / (sqrt(3) g cos(theta)) for the kinetic particle density.
        self._cfl_factor = m.cell_perimeter / (2.0 * m.cell_area)
        self._density = density_factor(self.gravity * self.terrain.gamma_z)
        self._kernel = registry.select(self.terrain, self.order, self.kernel, self.backend)
        self._scheme = self._time_scheme()
        self._cuda = None  # the cuda backend's grid on the device, made at the first call
        if self._kernel.name == "grid":
            layout = square_grid(self.terrain)
            if layout is not None:
                self._setup_grid(layout)
                return
            if self.backend == "cuda":  # no face kernel on the GPU to fall back on
                raise registry.KernelUnavailable(
                    "the cuda kernel does not run this grid (its faces are not axis-aligned "
                    f"rows); available: {registry.available(self.backend)}")
            if self.kernel == "grid":  # a grid whose faces are not in the kernel's order
                raise registry.KernelUnavailable(
                    "the square-grid kernel does not run this grid (its faces are not "
                    f"axis-aligned rows); available: {registry.available(self.backend)}")
            self._kernel = registry.KERNELS["faces", self.backend]
            self._scheme = self._time_scheme()
        # Work buffers, allocated once per solver and reused by every step.
        self._h_work = np.zeros(n)
        self._hu_work = np.zeros(n)
        self._hv_work = np.zeros(n)
        # Per face: mass flux, then the momentum it brings to each side (x, y of side i,
        # x, y of side j), so a Dirac face can take back what a dry side must not receive.
        # (order 2 only: the order-1 sweeps keep their fluxes in their own work lines)
        self._flux = np.zeros((m.n_faces if self.order == 2 else 0, 5))
        # Faces of every cell (CSR), for the active lists of the face kernel.
        self._cell_face_ptr, self._cell_face_idx = kernels.cell_faces(m.face_cells, n)
        # What the face kernel keeps from one call to the next (see timeloop._start)
        self._face_stamp = np.full(m.n_faces, -1, dtype=np.int64)
        self._cell_stamp = np.full(n, -1, dtype=np.int64)
        self._cell_sync = np.full(n, -1, dtype=np.int64)
        self._synced = np.empty(n, dtype=np.int64)
        self._clock = np.zeros(2, dtype=np.int64)
        self._transport = np.zeros(n)
        # the face kernel at order 1 (numerics.face_sweep): its geometry and work arrays
        # (with what its step on threads needs where it runs on threads); on a mesh whose
        # cells' faces lie far apart in index order (a square grid's) that step stays on
        # one thread (face_sweep.pieces_stay_local)
        on_threads = False
        if self.order == 1 and not m.structured_1d:
            threads = self.threads_used()
            geo = face_sweep.geometry(m, 1.0 / m.cell_area, self.terrain.curvature,
                                      self._cell_face_ptr, self._cell_face_idx, threads > 1)
            on_threads = threads > 1 and face_sweep.pieces_stay_local(geo, m.n_faces, threads)
            self._sweep = face_sweep.Sweep(geo, face_sweep.work(n, m.n_faces,
                                                                threads if on_threads else 1))
        else:
            self._sweep = face_sweep.unused()
        self._face_offset = (face_offsets(self.terrain) if self.order == 2 and not m.structured_1d
                             else np.zeros((0, 2, 2)))
        #: cells from which an order-1 step or an order-2 stage on faces runs on threads
        #: (tests lower it); an order-1 step on a mesh whose cells' faces lie far apart in
        #: index order (a square grid's) never does (face_sweep.pieces_stay_local)
        if self.order == 2:
            self._gather_from = face_gather.MIN_PARALLEL_CELLS
        else:
            self._gather_from = (face_sweep.MIN_PARALLEL_CELLS if on_threads
                                 else np.iinfo(np.int64).max)
        t = self.terrain
        self._face_mesh = FaceMesh(m.face_cells, m.face_frame, m.face_length, m.cell_area,
                                   self._cfl_factor, self._density, t.gamma_x, t.gamma_y,
                                   t.gamma_z, t.curvature, self._cell_face_ptr,
                                   self._cell_face_idx, self._face_offset)
        self._face_work = FaceWork(self._h_work, self._hu_work, self._hv_work, self._flux,
                                   self._transport, self._face_stamp, self._cell_stamp,
                                   self._cell_sync, self._synced, self._clock)

    def _set_params(self) -> None:
        """The law's parameters as the kernels read them: ``(1, N_PARAMS)``, or a row per
        cell where they vary in space (a map given as ``(n_cells, k)``, or forest), the
        forest's coefficient in :data:`~avflow.numerics.rheology.FOREST_SLOT`, and the
        law's code marked :data:`~avflow.numerics.rheology.PER_CELL` then."""
        # The kernels read N_PARAMS slots: a shorter vector (e.g. [tan(delta), 0, 0, 0]) is
        # padded with zeros, never read past its end.
        given = np.asarray(self.params, dtype=float)
        n = self.terrain.mesh.n_cells
        per_cell = given.ndim == 2 or self.forest is not None
        if given.ndim > 2 or (given.ndim == 2 and given.shape[0] != n):
            raise ValueError(f"a parameter map has a row per cell ({n}), got {given.shape}")
        width = given.shape[-1] if given.ndim else 1
        if width > N_PARAMS:
            raise ValueError(f"params holds at most {N_PARAMS} values, got {width}")
        if (self.forest is not None and width > FOREST_SLOT
                and np.any(given.reshape(-1, width)[:, FOREST_SLOT] != 0.0)):
            raise ValueError(f"with forest, the slot {FOREST_SLOT} of params is the forest's "
                             "coefficient: give the law's parameters only")
        rows = np.zeros((n if per_cell else 1, N_PARAMS))
        rows[:, :width] = given.reshape(-1, width) if given.ndim else given
        if self.forest is not None:
            forest = np.asarray(self.forest, dtype=float)
            if forest.shape != (n,) or not np.all(np.isfinite(forest)) or np.any(forest < 0):
                raise ValueError(f"the forest's coefficient is one finite value >= 0 per cell "
                                 f"({n}), got shape {forest.shape}")
            rows[:, FOREST_SLOT] = forest
        if not np.all(np.isfinite(rows)):
            raise ValueError("the friction parameters must be finite")
        self.params = rows if per_cell else rows[0].copy()
        self._rows = self._cell_rows = rows
        self._law_code = int(self.law) + (PER_CELL if per_cell else 0)

    def _setup_grid(self, layout: SquareGrid) -> None:
        """Arrays of the square-grid kernel: per-cell factors on the full grid, face fluxes
        by place, work buffers. The face kernel's face buffers are not allocated."""
        self._grid = layout
        # the registered sources' cells by place on the full grid, and their rows' columns
        self._supply = supply.pack(self.sources, self.terrain.mesh.n_cells, layout.place,
                                   layout.nx, layout.nx * layout.ny)
        from avflow.numerics.square_grid import MIN_BLOCK_ROWS, MIN_PARALLEL_CELLS

        #: (cells, rows per block) from which a step runs on threads (tests lower them)
        self._parallel_from = (MIN_PARALLEL_CELLS, MIN_BLOCK_ROWS)
        t, m = self.terrain, self.terrain.mesh
        full = layout.full
        self._g_cells = {
            "cell_area": full(m.cell_area, 1.0),
            "inv_area": full(1.0 / m.cell_area, 1.0),
            "cfl_factor": full(self._cfl_factor),
            "density": full(self._density),
            "gamma_x": full(t.gamma_x), "gamma_y": full(t.gamma_y), "gamma_z": full(t.gamma_z),
            # (3, places): one contiguous line per component, for the kernel's vector loops
            "curvature": np.ascontiguousarray(full(t.curvature).T),
        }
        if self._cell_rows.shape[0] > 1:  # the parameters per cell, on the grid's places
            self._rows = np.ascontiguousarray(layout.full(self._cell_rows))
        c = self._g_cells
        if self.order == 2:  # where order 2 evaluates its slopes, per face side
            x_offset, y_offset = grid_offsets(layout, m, face_offsets(t))
        else:
            x_offset, y_offset = np.zeros((0, 4, 0)), np.zeros((0, 4, 0))
        self._g_mesh = GridMesh(layout.nx, layout.ny, layout.valid, layout.x_code,
                                layout.x_frame, layout.x_length, layout.y_code,
                                layout.y_frame, layout.y_length, c["cell_area"],
                                c["inv_area"], c["cfl_factor"], c["density"], c["gamma_x"],
                                c["gamma_y"], c["gamma_z"], c["curvature"], x_offset,
                                y_offset)
        n = layout.n_places
        self._h_work, self._hu_work, self._hv_work = np.zeros(n), np.zeros(n), np.zeros(n)
        m2 = n if self.order == 2 else 0  # order 2: stage 2, stage 1's flags, transport
        self._g_order2 = (np.zeros(m2), np.zeros(m2), np.zeros(m2),
                          np.full(m2, DRY, dtype=np.uint8), np.zeros(m2))
        self._g_flag = np.zeros(n, dtype=np.uint8)
        self._g_rings = None  # the kernel's ring buffers, a set per thread (square_grid._grid_start)
        if not layout.compact:  # state and observers on the full grid, copied in and out
            self._g_state = {name: np.zeros(n) for name in self._grid_fields()}

    def _grid_fields(self) -> tuple:
        """The State arrays the square-grid kernel reads and writes."""
        return (("h", "hu", "hv", "peak_h", "peak_speed", "arrival", "last_moved")
                + (("erodible",) if self.source is not None else ())
                + (("supplied",) if self.sources else ()))

    @property
    def kernel_used(self) -> str:
        """``"grid"`` or ``"faces"``: the kernel this solver runs."""
        return "grid" if self._grid is not None or self._released else "faces"

    @property
    def time_scheme_used(self) -> str:
        """Order 2's time scheme this solver runs (``"hancock"`` or ``"heun"``), ``"none"``
        at order 1."""
        return self._scheme if self.order == 2 else "none"

    def release_buffers(self) -> None:
        """Free the square-grid kernel's layout and work arrays (a 1 m DEM: about 1.3 GiB)
        once a run is over, before its file is finished; the next :meth:`advance` builds
        them again. Nothing happens for the other kernels."""
        if self._grid is not None:
            self._grid = self._g_cells = self._g_state = self._g_flag = None
            self._g_rings = self._g_mesh = self._g_order2 = None
            self._h_work = self._hu_work = self._hv_work = None
            self._cuda = None  # the device's memory too
            self._released = True

    def threads_used(self) -> int:
        """CPU threads the time loop runs on: the square-grid kernel's, and the face
        kernel's (:mod:`avflow.numerics.face_sweep` at order 1,
        :mod:`avflow.numerics.face_gather` at order 2); 1 for profiles, which are serial.
        (The face kernel's order-1 step on a square grid, ``numerics.kernel: faces``,
        stays on one of them: :func:`~avflow.numerics.face_sweep.pieces_stay_local`.)"""
        if self.kernel_used != "grid" and self.terrain.mesh.structured_1d:
            return 1
        import os

        import numba

        # every core this process may run on (a batch job's or a container's share)
        try:
            cores = len(os.sched_getaffinity(0))
        except AttributeError:  # not on Linux
            cores = os.cpu_count() or 1
        return max(1, min(self.threads or cores, numba.config.NUMBA_NUM_THREADS))

    def _on_grid(self, state: State) -> stepping.Fields:
        """The state as the square-grid kernels (CPU and GPU) take it: its own arrays on a
        compact layout, else copied into the full-grid arrays (0 off the DEM, NaN for the
        times, DRY flags). The state's own flags: the kernel writes those of the cells it
        sweeps and keeps the others (a flag buffer kept by the solver gave a second state
        the flags the first had left where the second never swept)."""
        layout = self._grid
        if layout.compact:
            return self._fields(state, {"flag": state.flag})
        arrays = self._g_state
        for name in self._grid_fields():
            full = arrays[name]
            full.fill(np.nan if name in ("arrival", "last_moved") else 0.0)
            full[layout.place] = getattr(state, name)
        self._g_flag.fill(DRY)
        self._g_flag[layout.place] = state.flag
        maps = state.maps
        if maps.shape[0]:  # the registered maps, on the full grid too
            maps = np.zeros((maps.shape[0], layout.nx * layout.ny))
            maps[:, layout.place] = state.maps
        return self._fields(state, dict(arrays, flag=self._g_flag, maps=maps))

    def _off_grid(self, state: State, fields: stepping.Fields) -> None:
        """The kernel's answer back into ``state`` where it ran on the full-grid arrays."""
        layout = self._grid
        if not layout.compact:
            for name in self._grid_fields():
                getattr(state, name)[:] = getattr(fields, name)[layout.place]
            state.flag[:] = fields.flag[layout.place]
            if state.maps.shape[0]:
                state.maps[:] = fields.maps[:, layout.place]

    def _advance_grid(self, state: State, t_target, stop_volume, stop_kinetic, max_steps,
                      threads):
        """The time loop on the square-grid kernel, on ``threads`` (see :meth:`advance`)."""
        import numba

        from avflow.numerics.square_grid import _rings

        layout = self._grid
        chunk = None
        if threads > 1:
            numba.set_num_threads(threads)
            # blocks handed out one at a time, not split evenly up front: a thread that the
            # system deschedules (a busy machine) then holds up one block, not its share
            chunk = numba.set_parallel_chunksize(1)
        # ring buffers of the kernel's blocks, a set per thread, made once (each step made
        # its own before: 0.7-1 ms a step on a map 2000 cells wide)
        if self._g_rings is None or self._g_rings.emit.shape[0] < threads:
            self._g_rings = _rings(self.threads_used(), layout.nx, self.order == 2)
        fields = self._on_grid(state)
        run = self._control(t_target, max_steps, stop_volume, stop_kinetic,
                            *self._parallel_from)
        work = GridWork(self._h_work, self._hu_work, self._hv_work, self._g_rings,
                        *self._g_order2)
        status = self._loop(threads)(self._g_mesh, fields, work, self._physics(), run,
                                     threads, self._supply)
        if chunk is not None:
            numba.set_parallel_chunksize(chunk)
        self._off_grid(state, fields)
        return STATUS_NAMES[status]

    def _advance_cuda(self, state: State, t_target, stop_volume, stop_kinetic,
                      max_steps) -> str:
        """The time loop on the GPU (:class:`~avflow.numerics.cuda_grid.CudaGrid`, made at
        the first call and kept: the geometry and the state stay on the device), on the
        square-grid kernel's layout and full-grid arrays."""
        fields = self._on_grid(state)
        run = self._control(t_target, max_steps, stop_volume, stop_kinetic, 0, 0)
        if self._cuda is None:  # (what the run uses of avflow.extend built in, as on the CPU)
            self._cuda = self._loop(1)(self._g_mesh, self._rows, self._law_code, self.sources)
        status = self._cuda.advance(fields, self._physics(), run, owner=state,
                                    supply=self._supply)
        self._off_grid(state, fields)
        return STATUS_NAMES[status]

    def _loop(self, threads: int):
        """The compiled time loop of this solver's kernel, law and threads, with what was
        registered through avflow.extend built in where the run uses it."""
        from avflow.numerics.variants import with_registered

        loop = self._kernel.loop(self.terrain.mesh.structured_1d, self.order, self._law_code,
                                 threads > 1 and self._kernel.name != "profile",
                                 self._scheme)
        if self._kernel.backend != "cpu":
            return loop

        return with_registered(loop, self._law_code, self.sources)

    def _time_scheme(self) -> str:
        """Order 2's time scheme on this solver's kernel: ``time_scheme``, or the kernel's
        default; one the kernel does not run is refused."""
        schemes = self._kernel.schemes
        if self.time_scheme == "auto":
            return schemes[0]
        if self.time_scheme not in ("hancock", "heun"):
            raise ValueError(f"time_scheme must be auto, hancock or heun, got "
                             f"{self.time_scheme!r}")
        if self.order == 2 and self.time_scheme not in schemes:
            raise registry.SchemeUnavailable(
                f"the {self._kernel.name} kernel runs order 2 with {' or '.join(schemes)} "
                f"only, not {self.time_scheme}")
        return self.time_scheme

    def suspect(self) -> str | None:
        """After a non-finite state: the registered law or source of this run that returns a
        non-finite value in a wide range of thicknesses and speeds, in one line; else None."""
        from avflow.numerics import trial
        from avflow.numerics.variants import registered

        laws, _, _ = registered(self._law_code, self.sources)
        found = trial.suspect(laws, self.sources, self.params)
        return None if found is None else f"{found}: the state became non-finite"

    def describe_kernel(self) -> str:
        """What runs this solver, for the user: kernel, order, law, threads."""
        threads = 1 if self.threads is None else self.threads_used()
        name = law_name(self.law)
        law = {"samosat": "samosAT", "velocity_weakening": "velocity-weakening",
               "coulomb": "Coulomb", "pouliquen": "Pouliquen", "voellmy": "Voellmy"}.get(
            name, name)
        if self._kernel.backend == "cuda":
            return (f"the {self._kernel.name} kernel at order {self.order} with {law} "
                    "friction on the GPU")
        order = f"order {self.order}" + (
            " (MUSCL-Hancock)" if self.order == 2 and self._scheme == "hancock" else "")
        return (f"the {self._kernel.name} kernel at {order} with {law} friction"
                + (f" on {threads} threads" if threads > 1 else ""))

    def new_state(self, h0: np.ndarray) -> State:
        """A state at rest (eq. 60) with thickness ``h0`` (m) per cell."""
        h0 = np.ascontiguousarray(h0, dtype=float).copy()
        if h0.shape != (self.terrain.n_cells,):
            raise ValueError("initial thickness has the wrong shape")
        if not np.all(np.isfinite(h0)) or np.any(h0 < 0.0):
            raise ValueError("initial thickness must be finite and >= 0")
        n = h0.size
        state = State(
            h=h0,
            hu=np.zeros(n),
            hv=np.zeros(n),
            flag=np.where(h0 > 0.0, UNDER_THRESHOLD, DRY).astype(np.uint8),
            peak_h=h0.copy(),
            peak_speed=np.zeros(n),
            arrival=np.where(h0 > self.h_dry, 0.0, np.nan),
            last_moved=np.full(n, np.nan),
            erodible=(self.source.erodible.copy() if self.source is not None
                      else np.zeros(0)),
            maps=registered_maps(n),
            supplied=np.zeros(n if self.sources else 0),
        )
        self.reset_limits(state)
        state.stats[ST_DT_MIN] = np.inf
        return state

    def reset_limits(self, state: State) -> None:
        """Recompute the CFL limit of ``state`` (after editing its arrays by hand)."""
        state.stats[ST_DT_LIMIT] = kernels.dt_limit(
            self._cfl_factor, self.terrain.gamma_z, state.h, state.hu, state.hv, self.gravity)

    def volume(self, state: State) -> float:
        """Total volume on the mesh (m^3; m^2 per unit width on a profile), compensated sum.
        Over the cells that hold something: the dry ones add exact zeros, which change no
        exact sum, and the sum then costs the flow, not the map."""
        held = np.flatnonzero(state.h)
        return math.fsum(state.h[held] * self.terrain.mesh.cell_area[held])

    def supplied_volume(self, state: State) -> float:
        """Volume the registered sources have added so far (m^3; m^2 on a profile), from
        their book per cell."""
        held = np.flatnonzero(state.supplied)
        return math.fsum(state.supplied[held] * self.terrain.mesh.cell_area[held])

    def entrained_volume(self, state: State) -> float:
        """Volume the source has added to the flow so far (m^3; m^2 on a profile), read from
        what is left of the erodible layer, not from the steps' counts: the balance
        ``released + entrained = on the map + outflow`` then checks the source's own books."""
        if self.source is None:
            return 0.0
        taken = self.source.erodible - state.erodible
        held = np.flatnonzero(taken)
        return self.source.density_ratio * math.fsum(
            taken[held] * self.terrain.mesh.cell_area[held])

    def advance(self, state: State, t_target: float, *, stop_volume: float = -1.0,
                stop_kinetic: float = -1.0, max_steps: int = 10**9) -> str:
        """Run the time loop until ``t_target`` (s), a stop, or ``max_steps`` steps in all.

        The run counts as stopped once the volume still moving (u != 0 with mass crossing a
        face of the cell, h > h_dry) is below
        ``stop_volume`` (negative: never), or once the kinetic energy is at most
        ``stop_kinetic`` times its peak (negative: never). Returns ``"running"`` (target reached),
        ``"stopped"``, ``"max_steps"`` or ``"failed"``.
        """
        if self.source is not None and state.erodible.shape != self.source.erodible.shape:
            raise ValueError("the state has no erodible layer of this solver's source "
                             "(make it with new_state)")
        # The compiled loop holds the interpreter until it returns: it returns every
        # CALL_SECONDS of wall time or so (a step count learnt from the last call), so that
        # Ctrl-C and SIGTERM stop a run within a second. The steps are the same, bit for
        # bit: a call boundary changes no step (as the thread probes' calls show).
        import time

        while True:
            limit = min(max_steps, state.steps + self._call_steps)
            before, clock = state.steps, time.perf_counter()
            status = self._advance_call(state, t_target, stop_volume, stop_kinetic, limit)
            if status != "max_steps" or limit >= max_steps:
                return status
            spent, taken = time.perf_counter() - clock, state.steps - before
            if taken > 0:
                self._call_steps = int(min(max(taken * self.CALL_SECONDS / max(spent, 1e-6),
                                               8), 10**7))

    #: about how long one call of the compiled loop runs (s), at most: see :meth:`advance`
    CALL_SECONDS = 0.5

    def _advance_call(self, state: State, t_target, stop_volume, stop_kinetic,
                      max_steps) -> str:
        """One call of the compiled loop (:meth:`advance` without its return to Python)."""
        if self._released:
            self._setup_grid(square_grid(self.terrain))
            self._released = False
        if self._kernel.backend == "cuda":
            return self._advance_cuda(state, t_target, stop_volume, stop_kinetic, max_steps)
        most = self.threads_used()
        if self.threads is None and most > 1 and self._kernel.name != "profile":
            return self._advance_auto(state, t_target, stop_volume, stop_kinetic, max_steps)
        return self._advance_on(most, state, t_target, stop_volume, stop_kinetic, max_steps)

    def _advance_auto(self, state, t_target, stop_volume, stop_kinetic, max_steps) -> str:
        """:meth:`advance` on the threads that run fastest now (``threads`` None): every so
        often a few steps are timed on one thread, then on all of them one step at a time,
        stopping as soon as they are behind; all threads go on only where they were clearly
        faster. The answer does not depend on the threads, bit for bit; on a busy machine a
        step on two threads sharing a core with another process took 27x one on one thread
        (docs/performance.md), so a losing probe costs one step, not a call."""
        auto = self._auto
        if auto is None or auto.most != self.threads_used():
            auto = self._auto = ThreadChoice(self.threads_used())
        while True:
            if not auto.ready and state.steps >= auto.next_probe:
                # threads only once the flow is large enough to run on them at all: until
                # then the serial loop runs, and the threaded one is not even compiled
                if np.count_nonzero(state.h) >= self._parallel_cells():
                    self._warm(auto.most, state)
                    auto.ready = True
                else:
                    auto.next_probe = state.steps + ThreadChoice.FIRST_INTERVAL
            if auto.ready and state.steps >= auto.next_probe:
                status = self._probe(auto, state, t_target, stop_volume, stop_kinetic,
                                     max_steps)
                if status is not None:
                    return status  # the call ended within the probe
            limit = min(max_steps, auto.next_probe)
            status = self._advance_on(auto.choice, state, t_target, stop_volume, stop_kinetic,
                                      limit)
            if status != "max_steps" or limit == max_steps:
                return status

    def _parallel_cells(self) -> int:
        """Cells from which a step of this solver's kernel runs on threads at all."""
        if self._grid is not None:
            return int(self._parallel_from[0])
        return int(self._gather_from)

    def _warm(self, threads: int, state: State) -> None:
        """Compile (or load) the loop on ``threads`` with a call that takes no step, on a
        copy of ``state``, so that a probe does not time a compile."""
        copy = state.copy()
        self._advance_on(threads, copy, copy.t, -1.0, -1.0, 10**9)

    def _probe(self, auto, state, t_target, stop_volume, stop_kinetic, max_steps):
        """A few steps timed on one thread, then on all, one at a time; ``auto`` decides.
        Returns the loop's status where the call ended within the probe, else None."""
        import time

        spent = {1: 0.0, auto.most: 0.0}
        for k, steps, calls in ((1, ThreadChoice.PROBE_STEPS, 1),
                                (auto.most, 1, ThreadChoice.PROBE_STEPS)):
            for _ in range(calls):
                limit = min(max_steps, state.steps + steps)
                before, clock = state.steps, time.perf_counter()
                status = self._advance_on(k, state, t_target, stop_volume, stop_kinetic, limit)
                spent[k] += time.perf_counter() - clock
                if status != "max_steps" or limit == max_steps or state.steps == before:
                    return status
                if k > 1 and spent[k] >= spent[1]:
                    break  # behind one thread already
        auto.decide(spent[1], spent[auto.most], state.steps)
        return None

    def _fields(self, state: State, arrays=None) -> stepping.Fields:
        """The state's arrays as the time loops take them (``arrays``: the square-grid
        kernel's copies on its full grid, by name, where it does not run on the state's)."""
        def get(name):
            return arrays[name] if arrays and name in arrays else getattr(state, name)

        return stepping.Fields(*(get(name) for name in stepping.Fields._fields))

    def _physics(self) -> stepping.Physics:
        """The friction law, gravity, the Dirac flux, the thresholds and the source."""
        return stepping.Physics(self._law_code, self._rows, float(self.gravity),
                                bool(self.dirac), float(self.h_dry), float(self.h_zero),
                                self._source)

    def _control(self, t_target, max_steps, stop_volume, stop_kinetic, parallel_cells,
                 block_rows) -> stepping.Control:
        """How far a call runs, its stop rules, and from how many cells (grid: and rows a
        block) a step runs on threads."""
        return stepping.Control(float(self.cfl), float(t_target), int(max_steps),
                                float(stop_volume), float(stop_kinetic),
                                int(LIMITERS[self.limiter]), int(parallel_cells),
                                int(block_rows))

    def _advance_on(self, threads, state, t_target, stop_volume, stop_kinetic,
                    max_steps) -> str:
        """The time loop on ``threads`` threads (1: every step serial)."""
        if self._grid is not None:
            return self._advance_grid(state, t_target, stop_volume, stop_kinetic, max_steps,
                                      threads)
        if threads > 1:
            import numba

            numba.set_num_threads(threads)
        run = self._control(t_target, max_steps, stop_volume, stop_kinetic,
                            self._gather_from if threads > 1 else np.iinfo(np.int64).max, 0)
        status = self._loop(threads)(self._face_mesh, self._fields(state), self._face_work,
                                     self._physics(), run, self._sweep, self._supply)
        return STATUS_NAMES[status]
