"""The running maps of a run (peak thickness and speed, arrival, last motion, and any map a
user registers), observed once per *accepted* step, after the mass source, on the cells the
step changed: a step redone with half the time step writes nothing here, and what is
observed is the state the run goes on from.

Every kernel's time loop calls one of the two passes below through its region's
``observe`` hook (:mod:`avflow.numerics.loop`): a span of cells (a profile, a square grid's
row) or a list of cells (the face kernel's touched cells). The rule of each map is the
pointwise :func:`~avflow.numerics.physics.observe`, written once.

``more_maps`` is where maps registered through :mod:`avflow.extend` come in: a
placeholder that reads and writes nothing here, replaced in the copies of a run with
registered maps (:func:`avflow.numerics.variants.variant`). ``maps`` is their storage,
``(number of maps, cells)`` (empty when there are none).
"""

from __future__ import annotations

from numba import njit

from avflow.numerics.cpu import observe, speed_of
from avflow.numerics.vectorize import noalias


@njit(error_model="numpy", cache=True, inline="always")
def more_maps(maps, i, h, hu, hv, speed, t_new):
    """The registered maps of cell ``i`` (none here: see the module's docstring)."""
    return None


@njit(error_model="numpy", cache=True, inline="always")
def observe_cell_at(i, h, hu, hv, peak_h, peak_speed, arrival, last_moved, maps, t_new, h_dry):
    """The maps of cell ``i`` from its accepted state ``(h, hu, hv)[i]``."""
    hi = h[i]
    qx = hu[i]
    qy = hv[i]
    speed = speed_of(hi, qx, qy)
    peak_h[i], peak_speed[i], arrival[i], last_moved[i] = observe(
        True, hi, speed, t_new, h_dry, peak_h[i], peak_speed[i], arrival[i], last_moved[i])
    more_maps(maps, i, hi, qx, qy, speed, t_new)


@njit(error_model="numpy", cache=True, inline="always")
def _observe_run(a, b, h, hu, hv, peak_h, peak_speed, arrival, last_moved, maps, t_new,
                 h_dry):
    """The maps of the cells ``a .. b - 1`` (counted from 0 from a start clamped at 0: an
    index that cannot be negative lets the loop vectorise, vectorize.py)."""
    a = max(a, 0)
    for j in range(b - a):
        observe_cell_at(a + j, h, hu, hv, peak_h, peak_speed, arrival, last_moved, maps,
                        t_new, h_dry)


def _observe_span(a, b, h, hu, hv, peak_h, peak_speed, arrival, last_moved, maps, t_new,
                  h_dry):
    """The maps of the cells ``a .. b - 1``."""
    _observe_run(a, b, h, hu, hv, peak_h, peak_speed, arrival, last_moved, maps, t_new, h_dry)


def _observe_listed(cells, n, h, hu, hv, peak_h, peak_speed, arrival, last_moved, maps,
                    t_new, h_dry):
    """The maps of the ``n`` listed ``cells``, a run of consecutive indices at a time (the
    face kernel's lists are sorted: mostly long runs, whose loop vectorises)."""
    c = 0
    while c < n:
        first = cells[c]
        e = c
        while e + 1 < n and cells[e + 1] == cells[e] + 1:
            e += 1
        _observe_run(first, cells[e] + 1, h, hu, hv, peak_h, peak_speed, arrival, last_moved,
                     maps, t_new, h_dry)
        c = e + 1


# no reference counting (called once per row), and the arrays known not to overlap, so a
# row's loop vectorises (vectorize.noalias)
observe_span = noalias(njit(error_model="numpy", cache=True, _nrt=False)(_observe_span))
observe_listed = noalias(njit(error_model="numpy", cache=True, _nrt=False)(_observe_listed))
