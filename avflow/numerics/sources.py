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

from avflow.numerics.cpu import basal_shear, observe_cell, source_rate, take_erodible
from avflow.numerics.rheology import COULOMB, VOELLMY
from avflow.numerics.vectorize import ANY_LAW, by_law, cell_law, friction_law, law_label

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
def _gain(i, h, hu, hv, erodible, law, params, law_row, src, dt, cell_area, cfl_factor,
          gamma_z):
    """Cell i takes from its layer: ``(volume added, its new inverse CFL limit)``.
    ``law_row``: the run's own parameters (``p0..p7``), ``src``: the source's scalars
    ``(kind, ratio, u_min, s0..s3, h_zero, g)``, both loaded once per span. The running
    maps see the added mass in the time loop's observer pass, after this one.

    Without jumps (every value computed, the one that applies selected, every array
    written, with what it holds where nothing is taken), so that LLVM may vectorise a
    row's loop in the law-constant copies (:data:`SPAN`; what it gained:
    docs/performance.md)."""
    kind, ratio, u_min, s0, s1, s2, s3, h_zero, g = src
    p0, p1, p2, p3, p4, p5, p6, p7 = law_row
    hi = h[i]
    e = erodible[i]
    q_norm = math.sqrt(hu[i] * hu[i] + hv[i] * hv[i])
    wet = hi > h_zero  # a dry cell: nothing flows over its bed
    speed = q_norm / hi if wet else 0.0
    p0, p1, p2, p3, p4, p5, p6, p7 = cell_law(law, params, i, p0, p1, p2, p3, p4, p5, p6, p7)
    # the shear at time n + 1 on g cos(theta) (the curvature term left out: a small part of
    # an uncertain erosion law, and it would need the cell's curvature here)
    shear = basal_shear(law, p0, p1, p2, p3, p4, p5, p6, p7, hi, speed, g * gamma_z[i], g)
    rate = source_rate(kind, s0, s1, s2, s3, ratio, u_min, hi, speed, shear)
    take = take_erodible(rate, dt, e)
    take = take if wet & (take > 0.0) else 0.0
    erodible[i] = e - take if take > 0.0 else e  # exactly 0 where the layer is used up
    hn = hi + ratio * take if take > 0.0 else hi
    h[i] = hn
    _, inv = observe_cell(hn, q_norm, cfl_factor[i], gamma_z[i], g)
    return ratio * take * cell_area[i], (inv if take > 0.0 else 0.0)


@njit(error_model="numpy", cache=True, inline="always")
def _scalars(physics):
    """What every cell of a span reads: the law's own row and the source's scalars."""
    source, params = physics.source, physics.params
    law_row = (params[0, 0], params[0, 1], params[0, 2], params[0, 3], params[0, 4],
               params[0, 5], params[0, 6], params[0, 7])
    src = (int(source[SRC_KIND]), source[SRC_RATIO], source[SRC_UMIN], source[SRC_PARAMS],
           source[SRC_PARAMS + 1], source[SRC_PARAMS + 2], source[SRC_PARAMS + 3],
           physics.h_zero, physics.g)
    return law_row, src


def _add_span(a, b, h, hu, hv, erodible, physics, dt, cell_area, cfl_factor, gamma_z):
    """The source over cells ``a .. b - 1`` (a profile, a square grid's row): the volume
    added and the largest inverse CFL limit of the cells it changed."""
    law_row, src = _scalars(physics)
    law, params = friction_law(physics.law), physics.params  # a constant in SPAN's copies
    added = 0.0
    inv_lim = 0.0
    for i in range(a, b):
        v, inv = _gain(i, h, hu, hv, erodible, law, params, law_row, src, dt, cell_area,
                       cfl_factor, gamma_z)
        added += v
        inv_lim = inv if inv > inv_lim else inv_lim
    return added, inv_lim


#: :func:`_add_span` per law kind (:func:`~avflow.numerics.vectorize.by_law`): the
#: square-grid loop of each law calls its own, whose row loop vectorises for Coulomb and
#: Voellmy; :data:`add_span` reads the law (the profile kernel's loop calls it)
SPAN = {kind: by_law(_add_span, None if kind == ANY_LAW else kind, law_label(kind), nrt=False)
        for kind in (COULOMB, VOELLMY, ANY_LAW)}
add_span = SPAN[ANY_LAW]


@njit(error_model="numpy", cache=True, _nrt=False)
def add_listed(cells, n, h, hu, hv, erodible, physics, dt, cell_area, cfl_factor, gamma_z):
    """The source over the ``n`` listed ``cells`` (the face kernel's touched cells, a
    superset of the wet ones): as :func:`add_span`."""
    law_row, src = _scalars(physics)
    law, params = physics.law, physics.params
    added = 0.0
    inv_lim = 0.0
    for c in range(n):
        v, inv = _gain(cells[c], h, hu, hv, erodible, law, params, law_row, src, dt,
                       cell_area, cfl_factor, gamma_z)
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
