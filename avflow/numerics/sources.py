"""Mass sources, the seam through which entrainment adds mass (issues 27 and 30): once per
accepted step, after the seed's step (and after Heun's merge at order 2), every wet cell
takes from its erodible layer what the source law gives (:func:`physics.source_rate`,
capped by :func:`physics.take_erodible`), the same for every kernel and both orders.

The added mass comes with no momentum along the bed: the material at rest in the bed is
set moving by the flow, so ``q`` is kept and the speed falls (momentum is conserved, as in
Hungr and McDougall's and AvaFrame's entrainment). A first-order (Lie) splitting of the
source from the fluxes: its error is of the order of ``dt * rate / h``, far below the
scheme's own at the CFL step.

The erodible layer is a state array (m, normal to the bed) changed in place, one array for
both time-loop buffers; ``source`` packs the law: ``(kind, density ratio, s0 .. s3)``, the
ratio being the layer's density over the flow's (a depth ``e`` taken adds ``ratio * e`` of
flow thickness). With the kind :data:`~avflow.numerics.physics.SOURCE_NONE` no pass runs.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from avflow.numerics.cpu import basal_shear, observe_cell, source_rate, speed_of, take_erodible
from avflow.numerics.vectorize import cell_law

#: slots of the ``source`` vector: the law, the layer's density over the flow's, the speed
#: at or below which the entrainment laws take nothing, then the law's parameters
SRC_KIND = 0
SRC_RATIO = 1
SRC_UMIN = 2
SRC_PARAMS = 3
N_SOURCE = 7


def no_source() -> tuple[np.ndarray, np.ndarray]:
    """``(erodible, source)`` of a run without a source: no layer, the kind SOURCE_NONE."""
    return np.zeros(0), np.zeros(N_SOURCE)


@njit(error_model="numpy", cache=True, inline="always")
def _gain(i, h, hu, hv, erodible, physics, dt, t_new, cell_area, cfl_factor, gamma_z, peak_h,
          arrival):
    """Cell i takes from its layer: ``(volume added, its new inverse CFL limit)``."""
    hi = h[i]
    source, g = physics.source, physics.g
    if hi <= physics.h_zero:  # a dry cell: nothing flows over its bed
        return 0.0, 0.0
    speed = speed_of(hi, hu[i], hv[i])
    params = physics.params
    p0, p1, p2, p3, p4, p5, p6, p7 = cell_law(physics.law, params, i, params[0, 0],
                                              params[0, 1], params[0, 2], params[0, 3],
                                              params[0, 4], params[0, 5], params[0, 6],
                                              params[0, 7])
    # the shear at time n + 1 on g cos(theta) (the curvature term left out: a small part of
    # an uncertain erosion law, and it would need the cell's curvature here)
    shear = basal_shear(physics.law, p0, p1, p2, p3, p4, p5, p6, p7, hi, speed,
                        g * gamma_z[i], g)
    ratio = source[SRC_RATIO]
    rate = source_rate(int(source[SRC_KIND]), source[SRC_PARAMS], source[SRC_PARAMS + 1],
                       source[SRC_PARAMS + 2], source[SRC_PARAMS + 3], ratio,
                       source[SRC_UMIN], hi, speed, shear)
    take = take_erodible(rate, dt, erodible[i])
    if take <= 0.0:
        return 0.0, 0.0
    erodible[i] -= take  # exactly 0 where the layer is used up (take == erodible)
    hn = hi + ratio * take
    h[i] = hn
    if hn > peak_h[i]:
        peak_h[i] = hn
    if hn > physics.h_dry and math.isnan(arrival[i]):
        arrival[i] = t_new
    _, inv = observe_cell(hn, math.sqrt(hu[i] * hu[i] + hv[i] * hv[i]), cfl_factor[i],
                          gamma_z[i], g)
    return ratio * take * cell_area[i], inv


@njit(error_model="numpy", cache=True)
def add_span(a, b, h, hu, hv, erodible, physics, dt, t_new, cell_area, cfl_factor, gamma_z,
             peak_h, arrival):
    """The source over cells ``a .. b - 1`` (a profile, a square grid's row): the volume
    added and the largest inverse CFL limit of the cells it changed."""
    added = 0.0
    inv_lim = 0.0
    for i in range(a, b):
        v, inv = _gain(i, h, hu, hv, erodible, physics, dt, t_new, cell_area, cfl_factor,
                       gamma_z, peak_h, arrival)
        added += v
        inv_lim = max(inv_lim, inv)
    return added, inv_lim


@njit(error_model="numpy", cache=True)
def add_listed(cells, n, h, hu, hv, erodible, physics, dt, t_new, cell_area, cfl_factor,
               gamma_z, peak_h, arrival):
    """The source over the ``n`` listed ``cells`` (the face kernel's touched cells, a
    superset of the wet ones): as :func:`add_span`."""
    added = 0.0
    inv_lim = 0.0
    for c in range(n):
        v, inv = _gain(cells[c], h, hu, hv, erodible, physics, dt, t_new, cell_area,
                       cfl_factor, gamma_z, peak_h, arrival)
        added += v
        inv_lim = max(inv_lim, inv)
    return added, inv_lim


class MassSource:
    """A mass source for :class:`~avflow.numerics.solver.Solver`: its law ``kind``
    (``physics.SOURCE_*``), the law's parameters (at most 4), the erodible depth per cell
    at the start (m, normal to the bed, >= 0), the layer's density over the flow's, and
    the speed (m/s) at or below which the entrainment laws take nothing."""

    def __init__(self, kind: int, erodible, params=(), density_ratio: float = 1.0,
                 u_min: float = 0.0):
        erodible = np.ascontiguousarray(erodible, dtype=float).copy()
        if not np.all(np.isfinite(erodible)) or np.any(erodible < 0.0):
            raise ValueError("the erodible depth must be finite and >= 0")
        params = tuple(float(p) for p in params)
        if len(params) > N_SOURCE - SRC_PARAMS:
            raise ValueError(f"a source law takes at most {N_SOURCE - SRC_PARAMS} parameters")
        if not (math.isfinite(density_ratio) and density_ratio > 0.0):
            raise ValueError("the density ratio must be finite and > 0")
        self.kind = int(kind)
        self.erodible = erodible
        self.params = params
        self.density_ratio = float(density_ratio)
        if not (math.isfinite(u_min) and u_min >= 0.0):
            raise ValueError("the speed threshold u_min must be finite and >= 0")
        self.u_min = float(u_min)

    def vector(self) -> np.ndarray:
        """The ``source`` vector the time loops read (``SRC_*`` slots)."""
        out = np.zeros(N_SOURCE)
        out[SRC_KIND] = self.kind
        out[SRC_RATIO] = self.density_ratio
        out[SRC_UMIN] = self.u_min
        out[SRC_PARAMS:SRC_PARAMS + len(self.params)] = self.params
        return out
