"""Mass sources registered through :mod:`avflow.extend`: mass that falls or flows onto an area
(snowfall, rain on a debris fan, a feeding hydrograph), dry cells included, once per accepted
step, after the seed's step and the entrainment source.

Each source is a plain function ``rate(*parameters, h, speed, t)`` (m/s of flow thickness),
times the cell's weight (0..1, the share of the cell in the source's area); rates below 0
add nothing. What a cell receives comes with no momentum along the bed (``q`` is kept, the
speed falls: the material arrives at rest, as entrained material does). Every kernel runs the
same pass (:func:`supply_cells`) over the source's cells, and keeps those cells in the region
its steps sweep, wet or dry (the square grid's rows, the face kernel's lists), so that mass
landing on a dry cell is swept from the next step on.

``supplied`` (m per cell) is the run's book of what the sources added: the mass balance reads
it, and a test holds it to the rate times the area and the time.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

from avflow.numerics.cpu import observe_cell, speed_of

#: What the kernels read of the registered sources (in ``Physics.supply``): the cells they
#: cover (each kernel's own numbering), each source's weight on them ``(k, cells)``, each
#: source's parameters ``(k, 4)``, per cell whether a source covers it (faces: kept in the
#: lists), and per row of a square grid the columns they cover (``row_lo > row_hi``: none)
Supply = namedtuple("Supply", "cells weights params mask row_lo row_hi")

#: Parameters a source takes (extensions.MAX_SOURCE_PARAMETERS)
N_SUPPLY_PARAMS = 4


def no_supply() -> Supply:
    """The ``Supply`` of a run without registered sources (every array empty)."""
    return Supply(np.zeros(0, dtype=np.int64), np.zeros((0, 0)), np.zeros((0, N_SUPPLY_PARAMS)),
                  np.zeros(0, dtype=np.uint8), np.zeros(0, dtype=np.int64),
                  np.zeros(0, dtype=np.int64))


@njit(error_model="numpy", cache=True, inline="always")
def supply_rate(weights, params, c, h, speed, t):
    """The rate (m/s) the run's sources add to their ``c``-th cell: none here, a placeholder
    that the kernels of a run with registered sources replace (numerics.variants)."""
    return 0.0


@njit(error_model="numpy", cache=True, inline="always")
def supply_at(c, cells, weights, params, h, hu, hv, supplied, cell_area, cfl_factor, gamma_z,
              g, dt, t_new):
    """The sources on their ``c``-th cell: it takes ``rate * dt``, into ``h`` and into its
    book ``supplied``. Returns ``(volume added, its new inverse CFL limit)`` (0, 0 where
    nothing falls). Every kernel's pass calls this, the GPU's too."""
    i = cells[c]
    hi = h[i]
    rate = supply_rate(weights, params, c, hi, speed_of(hi, hu[i], hv[i]), t_new)
    if not rate > 0.0:
        return 0.0, 0.0
    take = rate * dt
    hn = hi + take
    h[i] = hn
    supplied[i] += take
    _, inv = observe_cell(hn, math.sqrt(hu[i] * hu[i] + hv[i] * hv[i]), cfl_factor[i],
                          gamma_z[i], g)
    return take * cell_area[i], inv


@njit(error_model="numpy", cache=True, _nrt=False)
def supply_cells(cells, weights, params, h, hu, hv, supplied, cell_area, cfl_factor, gamma_z,
                 g, dt, t_new):
    """The sources over their ``cells`` (:func:`supply_at`). Returns ``(volume added, the
    largest new inverse CFL limit)``."""
    added = 0.0
    inv_lim = 0.0
    for c in range(cells.size):
        v, inv = supply_at(c, cells, weights, params, h, hu, hv, supplied, cell_area,
                           cfl_factor, gamma_z, g, dt, t_new)
        added += v
        inv_lim = max(inv_lim, inv)
    return added, inv_lim


class AreaSource:
    """A registered source (:mod:`avflow.extend`) on a solver's cells: its ``name``, its
    parameters (in the order it was registered with) and its ``weight`` per cell (0..1)."""

    def __init__(self, name: str, params, weight):
        from avflow.scenario.extensions import SOURCES

        if name not in SOURCES:
            raise ValueError(f"no source is registered as {name!r}; registered: "
                             f"{', '.join(SOURCES) or 'none'}")
        entry = SOURCES[name]
        params = tuple(float(p) for p in params)
        if len(params) != len(entry.parameters):
            raise ValueError(f"the source {name} takes {len(entry.parameters)} parameters "
                             f"({', '.join(entry.parameters)}), got {len(params)}")
        if not all(math.isfinite(p) for p in params):
            raise ValueError(f"the parameters of the source {name} must be finite")
        weight = np.ascontiguousarray(weight, dtype=float)
        if not np.all(np.isfinite(weight)) or np.any(weight < 0.0) or np.any(weight > 1.0):
            raise ValueError(f"the weights of the source {name} must lie in [0, 1]")
        self.entry, self.params, self.weight = entry, params, weight


def pack(sources, n_cells: int, place=None, nx: int = 0, n_places: int = 0) -> Supply:
    """The :data:`Supply` of ``sources`` on ``n_cells`` cells; on a square grid's full
    layout (``place``: each cell's place, ``nx`` its width, ``n_places`` its size), with the
    cells numbered by place and the rows' covered columns."""
    if not sources:
        return no_supply()
    weights = np.stack([s.weight for s in sources])
    if weights.shape[1] != n_cells:
        raise ValueError(f"a source's weights hold {weights.shape[1]} values, not one per "
                         f"cell ({n_cells})")
    cells = np.flatnonzero(weights.max(axis=0) > 0.0)
    params = np.zeros((len(sources), N_SUPPLY_PARAMS))
    for k, s in enumerate(sources):
        params[k, :len(s.params)] = s.params
    on = cells if place is None else np.asarray(place)[cells]
    order = np.argsort(on, kind="stable")  # in index order, as the kernels' lists are
    cells, on = cells[order], on[order]
    mask = np.zeros(n_cells if place is None else n_places, dtype=np.uint8)
    mask[on] = 1
    row_lo = row_hi = np.zeros(0, dtype=np.int64)
    if place is not None:
        ny = n_places // nx
        row_lo = np.full(ny, nx, dtype=np.int64)
        row_hi = np.full(ny, -1, dtype=np.int64)
        rows, cols = np.divmod(on, nx)
        np.minimum.at(row_lo, rows, cols)
        np.maximum.at(row_hi, rows, cols)
    return Supply(on.astype(np.int64), np.ascontiguousarray(weights[:, cells]), params, mask,
                  row_lo, row_hi)
