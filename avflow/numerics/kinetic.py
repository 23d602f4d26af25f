"""Pointwise kinetic half-fluxes (seed section 3.2, eqs. 28-41, 53-55).

The kinetic scheme sees the thickness as a density of fictitious particles whose velocity is
spread around the mean ``u`` by a "temperature" ``c^2 = g cos(theta) h / 2`` (eq. 29, with the
bed-normal gravity of eq. 19). Through a face of unit normal ``n`` the particles of cell i that
move outward give ``F+`` (eq. 39) and those of cell j that move inward give ``F-`` (eq. 40):
the face flux is ``F+(U_i) + F-(U_j)`` (eq. 38).

With the rectangular density of eq. 32 projected on the normal (half-width ``sqrt(3) c``,
``omega_M = sqrt(3)``) the integrals are polynomials of the support bounds ``a = u_n - sqrt(3) c``
and ``b = u_n + sqrt(3) c``; eq. 54 is the special case ``a < 0 < b``. Their sum is the exact
physical flux ``(h u_n, h u_n^2 + g cos(theta) h^2 / 2)`` and each half-flux carries only the
mass of the cell it comes from, which is why h stays >= 0 under the CFL condition of eq. 41.

A zero temperature (``c = 0``) gives the Dirac density of eqs. 51, 53 and 55: particles move
with the fluid velocity and no pressure wave propagates.

These functions are plain scalar functions: :mod:`avflow.numerics.cpu` compiles them, with
:mod:`avflow.numerics.physics`, into the traversals.
"""

from __future__ import annotations

import math

SQRT3 = math.sqrt(3.0)  # omega_M of the rectangular density, eq. 32


def sound_speed(h, g_normal):
    """Kinetic 'temperature' c = sqrt(g cos(theta) h / 2) (eq. 29), m/s; 0 where dry."""
    if h <= 0.0 or g_normal <= 0.0:
        return 0.0
    return math.sqrt(0.5 * g_normal * h)


def density_factor(g_normal):
    """``1 / (sqrt(3) g cos(theta))`` (s/m), per cell: ``h / (2 sqrt(3) c) = c * factor``.

    Precomputed once with the geometry (``inf`` where the bed is vertical, where c = 0 and
    the Dirac branch applies instead).
    """
    import numpy as np

    with np.errstate(divide="ignore"):
        return 1.0 / (SQRT3 * np.asarray(g_normal, dtype=float))


def half_fluxes(h, un, c, k):
    """Outward and inward half-fluxes of one cell through a face, per unit face length.

    Parameters: thickness h (m), normal velocity un (m/s, positive along the face normal),
    temperature c (m/s), and the particle density per unit velocity ``k = h / (2 sqrt(3) c)``,
    which equals ``c * density_factor`` (see :func:`density_factor`): passing it saves a
    division per call. Returns ``(fp_h, fp_q, fm_h, fm_q)``:

    - ``fp_h = int_{xi>0} xi M dxi`` (m^2/s) and ``fp_q = int_{xi>0} xi^2 M dxi`` (m^3/s^2):
      the particles leaving through the face along +n (eq. 39);
    - ``fm_h``, ``fm_q``: the same over xi < 0 (eq. 40), ``fm_h <= 0``.

    ``c = 0`` is the Dirac density of eqs. 53 and 55.
    """
    if h <= 0.0:
        return 0.0, 0.0, 0.0, 0.0
    if c <= 0.0:
        if un > 0.0:
            return h * un, h * un * un, 0.0, 0.0
        return 0.0, 0.0, h * un, h * un * un
    s = SQRT3 * c
    a = un - s
    b = un + s
    ap = a if a > 0.0 else 0.0
    bp = b if b > 0.0 else 0.0
    am = a if a < 0.0 else 0.0
    bm = b if b < 0.0 else 0.0
    fp_h = 0.5 * k * (bp * bp - ap * ap)
    fp_q = (k / 3.0) * (bp * bp * bp - ap * ap * ap)
    fm_h = 0.5 * k * (bm * bm - am * am)
    fm_q = (k / 3.0) * (bm * bm * bm - am * am * am)
    return fp_h, fp_q, fm_h, fm_q


def half_flux_out(h, un, c, s, kh, k3):
    """``(fp_h, fp_q)`` of :func:`half_fluxes` from a cell's factors computed once per step
    (``s = sqrt(3) c``, ``kh = k / 2``, ``k3 = k / 3``): the same operations, none of its
    divisions. Nothing from a dry side; the Dirac density (``c = 0``, eq. 53) carries all of
    it or nothing. The scalar face loops' form: the case that applies alone."""
    if h <= 0.0:
        return 0.0, 0.0
    if c <= 0.0:
        return (h * un, h * un * un) if un > 0.0 else (0.0, 0.0)
    a = un - s  # the support of the rectangular density (eq. 39)
    b = un + s
    ap = a if a > 0.0 else 0.0
    bp = b if b > 0.0 else 0.0
    return kh * (bp * bp - ap * ap), k3 * (bp * bp * bp - ap * ap * ap)


def half_flux_in(h, un, c, s, kh, k3):
    """``(fm_h, fm_q)`` of :func:`half_fluxes`, as :func:`half_flux_out`."""
    if h <= 0.0:
        return 0.0, 0.0
    if c <= 0.0:
        return (0.0, 0.0) if un > 0.0 else (h * un, h * un * un)
    a = un - s
    b = un + s
    am = a if a < 0.0 else 0.0
    bm = b if b < 0.0 else 0.0
    return kh * (bm * bm - am * am), k3 * (bm * bm * bm - am * am * am)


def select_flux_out(h, un, c, s, kh, k3):
    """:func:`half_flux_out` with every case computed and the one that applies selected,
    without a branch: the same operations on the value kept, so the same bits, and a line
    of faces vectorises (the grid's rows, the profile), where the scalar face loops ran
    10-18% slower with it. The two forms differ only in how the case is chosen."""
    a = un - s
    b = un + s
    ap = a if a > 0.0 else 0.0
    bp = b if b > 0.0 else 0.0
    rect_h = kh * (bp * bp - ap * ap)
    rect_q = k3 * (bp * bp * bp - ap * ap * ap)
    leaving = un > 0.0
    dirac_h = h * un if leaving else 0.0
    dirac_q = h * un * un if leaving else 0.0
    f_h = rect_h if c > 0.0 else dirac_h
    f_q = rect_q if c > 0.0 else dirac_q
    return (f_h if h > 0.0 else 0.0), (f_q if h > 0.0 else 0.0)


def select_flux_in(h, un, c, s, kh, k3):
    """:func:`half_flux_in` without a branch, as :func:`select_flux_out`."""
    a = un - s
    b = un + s
    am = a if a < 0.0 else 0.0
    bm = b if b < 0.0 else 0.0
    rect_h = kh * (bm * bm - am * am)
    rect_q = k3 * (bm * bm * bm - am * am * am)
    leaving = un > 0.0
    dirac_h = 0.0 if leaving else h * un
    dirac_q = 0.0 if leaving else h * un * un
    f_h = rect_h if c > 0.0 else dirac_h
    f_q = rect_q if c > 0.0 else dirac_q
    return (f_h if h > 0.0 else 0.0), (f_q if h > 0.0 else 0.0)
