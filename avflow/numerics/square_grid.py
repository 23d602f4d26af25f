"""The structured square-grid kernel: the face kernel's step, swept by rows, on every core.

Same scheme as :func:`avflow.numerics.kernels.step_faces` (seed eqs. 26-56: rectangular
fluxes, trial momentum and Coulomb threshold, Dirac faces, projection, curvature and film
rules, walls, NODATA holes, open sides), on the layout of
:class:`avflow.terrain.squaregrid.SquareGrid`: x faces and y faces are found by their place
in the grid, with no face lists and no per-face index arrays, and each cell's thickness,
discharge and sound speed are read once per face sweep of its row.

One step is a wavefront over the rows of the *swept region* (the rows and columns the flow
covers, one cell around, see :func:`_advance_grid`): at stage k, the faces of row k (its x
faces and the y faces below it, from what each cell emits, computed once per cell), the
trial momentum and Coulomb flag of row k - 1 (eqs. 47, 49), the final update of row k - 2
(Dirac faces, projection of eq. 50). A row's fluxes and flags live in a ring of
four rows, still in cache when they are used: there is no flux array of the whole grid.

The band of rows is cut into blocks, one task each (Numba's threads): a block also computes
the faces and flags of the row on each side of it, never written out, so it needs nothing
from its neighbours and no two threads write the same place. Every value is computed with
the same arithmetic whoever computes it, and the sums over the grid are made per row, then
over the rows in order: the answer is bit for bit the same on 1 or N threads. Those grid-wide
diagnostics (moving volume, film, kinetic energy, outflow) differ from the face kernel's
(which adds cell after cell) by round-off; everything else (thickness, discharge, flags,
time steps) is the face kernel's, bit for bit: each cell adds its faces in the order of their
indices in the mesh, W, E, S, N on a square grid (:mod:`avflow.terrain.mesh`), as the face
kernel does.

Each pass over a row (what cells emit, x faces, y faces, trial, final update) is one loop
that LLVM vectorises, 8 cells at a time with AVX-512 (:mod:`avflow.numerics.vectorize`
says how): selects instead of jumps, one contiguous line per quantity (emitted values, face
fluxes, frames, curvature), boundary faces in a second, scalar pass, and a copy of the
sweep per friction law. The same arithmetic written with branches ran about twice as
long a cell (docs/performance.md).

Order 2 (Heun's two stages, :func:`_order2_step`) runs the same sweep twice, its faces fed
each row's reconstructed sides (:func:`_recon_row`, the face kernel's limited linear
reconstruction cell by cell) instead of the cells' emitted values, then merges the stages per
row (:func:`_heun_rows`): the face kernel's answers at order 2, bit for bit, the grid-wide
sums to round-off.

``prange`` runs serially when a function is compiled without ``parallel``: the sweep is
compiled twice (serial and parallel), and one thread takes the serial one, which never
touches Numba's thread pool (safe inside dask workers and any thread). The time loop is
compiled per friction law and with or without the parallel sweep (:func:`grid_loop`), so a
run compiles only what it runs.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numba
import numpy as np
from numba import njit, prange

from avflow.numerics.cpu import (DRY, FACE_INNER, FACE_OPEN, FACE_WALL, carries, cell_moves,
                                 cell_update, dirac_face, dt_from_inverse, emitted_side,
                                 face_flux, half_step, heun_average, observe_cell, outflow_volume, speed_of,
                                 step_terms, take_back, trial_momentum, vector_face_flux)
from avflow.numerics.loop import advance
from avflow.numerics.observers import observe_span
from avflow.numerics.sources import SPAN, add_span  # noqa: F401 (each copy's own)
from avflow.numerics.stepping import ST_SOURCE, Conserved, record_end
from avflow.numerics.cpu import SQRT3
from avflow.numerics.physics import MIDPOINT
from avflow.numerics.rheology import COULOMB, VOELLMY
from avflow.numerics.vectorize import (ANY_LAW, by_law, cell_law, friction_law, law_kind,
                                       law_label, line_max, line_sum, noalias, shared_names,
                                       specialize)
from avflow.terrain.squaregrid import (HIGH_OPEN, HIGH_WALL, INNER, KIND,
                                       LOW_OPEN, LOW_WALL, NO_FACE, SIGN0, SIGN1)

# Columns of the per-row results of pass 3
R_OK = 0  #: 1 when every cell of the row kept h >= 0
R_OUT = 1  #: volume out through the row's open faces
R_INV = 2  #: largest inverse CFL limit
R_MOVING = 3
R_FILM = 4
R_KINETIC = 5
R_CLAMPED = 6
R_FALLBACK = 7  #: order 2: cells of the row where Heun's merge fell back to q = 0
N_ROW = 8

#: Whether a copy of the row passes runs a stage of order 2 (a constant in each copy,
#: :func:`_block_for`): gravity and friction explicit in the stage (physics.trial_momentum),
#: each cell's transport kept for Heun's merge
ORDER2 = False
#: Whether a copy of the sweep feeds its faces each cell's reconstructed sides (order 2:
#: each of Heun's stages, or the single stage of MUSCL-Hancock), and whether those sides
#: are of the state half a step on (MUSCL-Hancock's predictor, physics.half_step)
SIDES = False
PREDICT = False
#: When in the step gravity and friction take the thickness (physics.trial_momentum's
#: ``explicit``): False at order 1, True in Heun's stages, MIDPOINT in MUSCL-Hancock's
TIMING = False


#: Per-cell values of an emitted row (:func:`_emit_row`)
E_H, E_U1, E_U2, E_C, E_S, E_KH, E_K3, E_SPEED = range(8)
N_EMIT = 8


@noalias
@njit(error_model="numpy", cache=True, _nrt=False)  # no reference counts: see _block_for
def _emit_row(base, c0, c1, h, hu, hv, gamma_z, density, h_zero, g, out):
    """Per cell ``c0..c1`` of a row, once per step, what its faces and its own update read
    (``out[E_*, c]``, one contiguous line per quantity): thickness and velocity it emits
    (zero at or below h_zero), sound speed c, ``sqrt(3) c``, ``k / 2`` and ``k / 3`` with
    ``k = c / (sqrt(3) g cos)`` (the factors of the half fluxes,
    :func:`avflow.numerics.kinetic.half_fluxes`, computed there per face side), and the speed
    ``|q| / h`` at time n.

    The face kernel's :func:`~avflow.numerics.physics.emitted_state` and
    :func:`~avflow.numerics.physics.speed_of`, the same operations on every value kept, so the
    same bits, written without branches so that LLVM vectorises the loop: a dry
    cell divides by 1 and its results are replaced by zeros (selects, not jumps); the loop
    counts from 0 and its first index is clamped at 0, which lets LLVM drop Numba's
    wraparound of negative indices (with it the loop stays scalar).
    """
    o_h, o_u1, o_u2, o_c = out[E_H], out[E_U1], out[E_U2], out[E_C]
    o_s, o_kh, o_k3, o_speed = out[E_S], out[E_KH], out[E_K3], out[E_SPEED]
    h_wet = max(h_zero, 0.0)  # wet: h > h_zero and h > 0, as emitted_state
    c0 = max(c0, 0)
    i0 = max(base + c0, 0)
    for j in range(c1 + 1 - c0):
        i = i0 + j
        c = c0 + j
        (o_h[c], o_u1[c], o_u2[c], o_c[c], o_s[c], o_kh[c], o_k3[c],
         o_speed[c]) = emitted_cell(h[i], hu[i], hv[i], g * gamma_z[i], density[i], h_wet)


@njit(error_model="numpy", cache=True, inline="always")
def emitted_cell(hc, q1, q2, g_normal, dens, h_wet):
    """One cell of :func:`_emit_row`: ``(h, u1, u2, c, sqrt(3) c, k / 2, k / 3, |q| / h)``,
    every case computed and the one that applies selected (a dry cell divides by 1)."""
    wet = hc > h_wet
    hs = hc if wet else 1.0
    sound = math.sqrt(0.5 * g_normal * hs)  # sound_speed(): 0 on a vertical bed
    sound = sound if g_normal > 0.0 else 0.0
    k = sound * dens
    positive = hc > 0.0  # speed_of(): |q| / h wherever h > 0, film included
    hp = hc if positive else 1.0
    speed = math.sqrt(q1 * q1 + q2 * q2) / hp
    return ((hc if wet else 0.0), (q1 / hs if wet else 0.0), (q2 / hs if wet else 0.0),
            (sound if wet else 0.0), (SQRT3 * sound if wet else 0.0),
            (0.5 * k if wet else 0.0), (k / 3.0 if wet else 0.0),
            (speed if positive else 0.0))


@njit(error_model="numpy", cache=True, inline="always")
def _kind_of(code):
    """What lies beyond a face of a given code (physics.face_flux's ``kind``)."""
    kind = code & KIND
    if kind == INNER:
        return FACE_INNER
    if kind == LOW_WALL or kind == HIGH_WALL:
        return FACE_WALL
    return FACE_OPEN


@njit(error_model="numpy", cache=True, inline="always")
def _coded_flux(kind, code, hi, ui1, ui2, ci, si, khi, k3i, hj, uj1, uj2, cj, sj, khj, k3j,
                n0x, n0y, n1x, n1y, length):
    """:func:`~avflow.numerics.physics.face_flux` of a grid face: i the face's first cell
    (frame side 0), j the second (frame side 1), or, beyond a boundary face, its owner.
    Each side's frame is a rotation: the tangent ``t = s (-n_y, n_x)``, its sign s in the
    code's bits. (:data:`_vector_coded_flux`: its copy for a line of inner faces.)"""
    s0 = -1.0 if code & SIGN0 else 1.0
    s1 = -1.0 if code & SIGN1 else 1.0
    return face_flux(kind, hi, ui1, ui2, ci, si, khi, k3i, hj, uj1, uj2, cj, sj, khj, k3j,
                     n0x, n0y, s0 * -n0y, s0 * n0x, n1x, n1y, s1 * -n1y, s1 * n1x, length)


#: :func:`_coded_flux` with the half fluxes' branch-free form (physics' copy
#: ``cpu.vector_face_flux``): the loops over a line of inner faces, which vectorise
_vector_coded_flux = specialize(_coded_flux.py_func, "_vector", inline="always",
                                face_flux=vector_face_flux)


@noalias
@njit(error_model="numpy", cache=True, _nrt=False)  # no reference counts: see _block_for
def _x_faces(k0, k1, codes, frames, lengths, west, east, out):
    """x faces ``k0..k1`` of a row (face k between cells k - 1 and k) into ``out[:, k]``
    (``frames``: the row's ``(4, nx + 1)`` normals; ``west``: what the west cell k - 1
    emits through its east side, ``east``: what cell k emits through its west side, both
    the row's emitted values at order 1, the reconstructed sides at order 2).

    Two passes: every face inside the map (``1 <= k < nx``) as an inner face, in one
    loop that LLVM vectorises (the face flux's kind a constant there: no branch is left),
    then the few others (walls, open sides, the map's two sides) again with their kind,
    which overwrites them (a NO_FACE keeps values nobody reads)."""
    nx = east.shape[1]
    w_h, w_u1, w_u2, w_c = west[E_H], west[E_U1], west[E_U2], west[E_C]
    w_s, w_kh, w_k3 = west[E_S], west[E_KH], west[E_K3]
    e_h, e_u1, e_u2, e_c = east[E_H], east[E_U1], east[E_U2], east[E_C]
    e_s, e_kh, e_k3 = east[E_S], east[E_KH], east[E_K3]
    n0x, n0y, n1x, n1y = frames[0], frames[1], frames[2], frames[3]
    o0, o1, o2, o3, o4 = out[0], out[1], out[2], out[3], out[4]
    a = max(k0, 1)
    b = min(k1, nx - 1)
    for j in range(b + 1 - a):
        k = a + j  # >= 1: the west cell k - 1 >= 0, no wraparound
        f0, f1, f2, f3, f4 = _vector_coded_flux(
            FACE_INNER, codes[k], w_h[k - 1], w_u1[k - 1], w_u2[k - 1], w_c[k - 1], w_s[k - 1],
            w_kh[k - 1], w_k3[k - 1], e_h[k], e_u1[k], e_u2[k], e_c[k], e_s[k], e_kh[k],
            e_k3[k], n0x[k], n0y[k], n1x[k], n1y[k], lengths[k])
        o0[k] = f0
        o1[k] = f1
        o2[k] = f2
        o3[k] = f3
        o4[k] = f4
    for k in range(max(k0, 0), k1 + 1):
        code = codes[k]
        kind = code & KIND
        if kind == INNER or kind == NO_FACE:
            continue
        if kind >= HIGH_WALL:  # the owner: the east cell for HIGH_*, else the west one
            f0, f1, f2, f3, f4 = _coded_flux(
                _kind_of(code), code, e_h[k], e_u1[k], e_u2[k], e_c[k], e_s[k], e_kh[k], e_k3[k],
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, n0x[k], n0y[k], n1x[k], n1y[k], lengths[k])
        else:
            m = k - 1
            f0, f1, f2, f3, f4 = _coded_flux(
                _kind_of(code), code, w_h[m], w_u1[m], w_u2[m], w_c[m], w_s[m], w_kh[m], w_k3[m],
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, n0x[k], n0y[k], n1x[k], n1y[k], lengths[k])
        o0[k] = f0
        o1[k] = f1
        o2[k] = f2
        o3[k] = f3
        o4[k] = f4


@noalias
@njit(error_model="numpy", cache=True, _nrt=False)  # no reference counts: see _block_for
def _y_faces(c0, c1, codes, frames, lengths, below, above, out):
    """y faces ``c0..c1`` between two rows (``below``: the emitted states of the lower row,
    ``above``: of the upper one) into ``out[:, c]``, in two passes as :func:`_x_faces` (at
    the map's south and north sides every face is a boundary face: the missing row's
    values, whatever the ring holds, are overwritten by the second pass).

    The twin of :func:`_x_faces` with the west cell at k - 1 there and the row below at c
    here: in one function taking that shift as an argument the loop stayed scalar, so the
    two are written apart."""
    b_h, b_u1, b_u2, b_c = below[E_H], below[E_U1], below[E_U2], below[E_C]
    b_s, b_kh, b_k3 = below[E_S], below[E_KH], below[E_K3]
    a_h, a_u1, a_u2, a_c = above[E_H], above[E_U1], above[E_U2], above[E_C]
    a_s, a_kh, a_k3 = above[E_S], above[E_KH], above[E_K3]
    n0x, n0y, n1x, n1y = frames[0], frames[1], frames[2], frames[3]
    o0, o1, o2, o3, o4 = out[0], out[1], out[2], out[3], out[4]
    c0 = max(c0, 0)
    for j in range(c1 + 1 - c0):
        c = c0 + j
        f0, f1, f2, f3, f4 = _vector_coded_flux(
            FACE_INNER, codes[c], b_h[c], b_u1[c], b_u2[c], b_c[c], b_s[c], b_kh[c], b_k3[c],
            a_h[c], a_u1[c], a_u2[c], a_c[c], a_s[c], a_kh[c], a_k3[c],
            n0x[c], n0y[c], n1x[c], n1y[c], lengths[c])
        o0[c] = f0
        o1[c] = f1
        o2[c] = f2
        o3[c] = f3
        o4[c] = f4
    for c in range(c0, c1 + 1):
        code = codes[c]
        kind = code & KIND
        if kind == INNER or kind == NO_FACE:
            continue
        if kind >= HIGH_WALL:  # the north cell owns it
            f0, f1, f2, f3, f4 = _coded_flux(
                _kind_of(code), code, a_h[c], a_u1[c], a_u2[c], a_c[c], a_s[c], a_kh[c], a_k3[c],
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, n0x[c], n0y[c], n1x[c], n1y[c], lengths[c])
        else:
            f0, f1, f2, f3, f4 = _coded_flux(
                _kind_of(code), code, b_h[c], b_u1[c], b_u2[c], b_c[c], b_s[c], b_kh[c], b_k3[c],
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, n0x[c], n0y[c], n1x[c], n1y[c], lengths[c])
        o0[c] = f0
        o1[c] = f1
        o2[c] = f2
        o3[c] = f3
        o4[c] = f4


#: The sides of a cell in the reconstruction's lines (:func:`_recon_row`): W, E, S, N
SIDE_W, SIDE_E, SIDE_S, SIDE_N = range(4)


@njit(error_model="numpy", cache=True, inline="always")
def _gg_face(hc, uc1, uc2, inner, second, code, n_0x, n_0y, n_1x, n_1y, w, ho_raw, huo, hvo,
             h_zero):
    """One face of a cell in the Green-Gauss sums of
    :func:`~avflow.numerics.reconstruction.reconstruct_cells`, without branches (the same
    operations on every value kept, so the same bits): ``second``, the cell is the face's
    second side (an inner W or S face); ``n_0``, ``n_1`` the frame normals of the face's two
    sides (tangents ``t = s (-n_y, n_x)``, the signs in the code's bits). Returns ``(wx, wy,
    ho, uo1, uo2, front)``: the weights of the face's mean values, the neighbour's thickness
    and velocity in this cell's basis (the cell's own beyond a boundary face: zero normal
    gradient), whether the neighbour is dry."""
    n_sx = n_1x if second else n_0x
    n_sy = n_1y if second else n_0y
    n_ox = n_0x if second else n_1x
    n_oy = n_0y if second else n_1y
    s_s = -1.0 if (code & (SIGN1 if second else SIGN0)) != 0 else 1.0
    s_o = -1.0 if (code & (SIGN0 if second else SIGN1)) != 0 else 1.0
    nx = -n_sx if second else n_sx  # the frame's normal points from the first side
    ny = -n_sy if second else n_sy
    wet = ho_raw > h_zero
    hs = ho_raw if wet else 1.0
    v1 = huo / hs
    v2 = hvo / hs
    un = v1 * n_ox + v2 * n_oy  # its velocity, turned through the face into this basis
    ut = v1 * (s_o * -n_oy) + v2 * (s_o * n_ox)
    t1 = un * n_sx + ut * (s_s * -n_sy)
    t2 = un * n_sy + ut * (s_s * n_sx)
    return (w * nx, w * ny, (ho_raw if inner else hc), (t1 if inner & wet else uc1),
            (t2 if inner & wet else uc2), inner & (not wet))


@njit(error_model="numpy", cache=True, inline="always")
def _range(centre, a, b, c, d):
    """The least and largest of a cell's value and its four neighbours', each kept unless a
    value is strictly beyond it (as reconstruct_cells, in face order)."""
    lo = centre
    hi = centre
    lo = a if a < lo else lo
    hi = a if a > hi else hi
    lo = b if b < lo else lo
    hi = b if b > hi else hi
    lo = c if c < lo else lo
    hi = c if c > hi else hi
    lo = d if d < lo else lo
    hi = d if d > hi else hi
    return lo, hi


@njit(error_model="numpy", cache=True, inline="always")
def _bj_select(alpha, d, centre, lo, hi, thickness):
    """:func:`~avflow.numerics.reconstruction._bj_factor` without branches, with one
    division (the vector loop is bound by its divisions): the numerator chosen first, and
    for a thickness ``min(a / d, c / d) == min(a, c) / d`` exactly, d > 0 (a rounded
    division is monotone)."""
    up = hi - centre
    up = min(up, centre) if thickness else up
    ratio = (up if d > 0.0 else (lo - centre)) / d
    return ratio if (d != 0.0) & (ratio < alpha) else alpha


@njit(error_model="numpy", cache=True, inline="always")
def _side_state(hc, uc1, uc2, a0, a1, a2, g0, g1, g2, g3, g4, g5, rx, ry, front):
    """A wet cell's limited linear state ``(h, u1, u2)`` at the offset ``(rx, ry)`` of one
    of its sides (in its basis), as
    :func:`~avflow.numerics.reconstruction.reconstruct_cells` makes it."""
    hf = hc + a0 * (g0 * rx + g1 * ry)
    hf = max(hf, 0.0)
    u1 = uc1 + a1 * (g2 * rx + g3 * ry)
    u2 = uc2 + a2 * (g4 * rx + g5 * ry)
    u1 = uc1 if front else u1  # no velocity slope towards a dry neighbour
    u2 = uc2 if front else u2
    return hf, u1, u2


@njit(error_model="numpy", cache=True, inline="always")
def _side(hc, uc1, uc2, a0, a1, a2, g0, g1, g2, g3, g4, g5, rx, ry, front, g_normal, dens):
    """A wet cell's reconstructed state on one side (:func:`_side_state`) and what it emits
    there as step_faces at order 2 (:func:`emitted_cell`, emitted_state without branches):
    ``(h, u1, u2, c, sqrt(3) c, k / 2, k / 3)``."""
    hf, u1, u2 = _side_state(hc, uc1, uc2, a0, a1, a2, g0, g1, g2, g3, g4, g5, rx, ry, front)
    e_h, e_u1, e_u2, e_c, e_s, e_kh, e_k3, _ = emitted_cell(hf, hf * u1, hf * u2, g_normal,
                                                             dens, 0.0)
    return e_h, e_u1, e_u2, e_c, e_s, e_kh, e_k3


@njit(error_model="numpy", cache=True, inline="always")
def _side_direct(hc, uc1, uc2, a0, a1, a2, g0, g1, g2, g3, g4, g5, rx, ry, front, g_normal,
                 dens):
    """:func:`_side` without forming q = h u and dividing it back, nor dividing k by 3: the
    same values to round-off, 12 divisions a cell fewer (MUSCL-Hancock's copy, which has no
    face-kernel twin to match bit for bit)."""
    hf, u1, u2 = _side_state(hc, uc1, uc2, a0, a1, a2, g0, g1, g2, g3, g4, g5, rx, ry, front)
    return emitted_side(hf, u1, u2, g_normal, dens)


@noalias
@njit(error_model="numpy", cache=True, _nrt=False)  # no reference counts: see _block_for
def _recon_cells(base, base_s, base_n, c0, c1, x_code, ys_code, yn_code, x_frame, ys_frame,
                 yn_frame, x_len, ys_len, yn_len, x_off, ys_off, yn_off, cell_area, density,
                 gamma_z, h, hu, hv, h_zero, g, dt_half, gamma_x, gamma_y, law, params,
                 w_h, w_u1, w_u2, w_c, w_s, w_kh, w_k3, e_h, e_u1, e_u2, e_c, e_s, e_kh, e_k3,
                 s_h, s_u1, s_u2, s_c, s_s, s_kh, s_k3, n_h, n_u1, n_u2, n_c, n_s, n_kh, n_k3):
    """:func:`_recon_row`'s loop over the cells ``c0..c1`` of a row (``base``: its first
    place, ``base_s`` / ``base_n``: the rows below and above, clamped to the map), each
    output line its own argument, without branches so that LLVM vectorises it (the
    neighbours' values loaded whatever the faces are, in the map: indices clamped)."""
    xf0, xf1, xf2, xf3 = x_frame[0], x_frame[1], x_frame[2], x_frame[3]
    sf0, sf1, sf2, sf3 = ys_frame[0], ys_frame[1], ys_frame[2], ys_frame[3]
    nf0, nf1, nf2, nf3 = yn_frame[0], yn_frame[1], yn_frame[2], yn_frame[3]
    xo0, xo1, xo2, xo3 = x_off[0], x_off[1], x_off[2], x_off[3]
    so0, so1, so2, so3 = ys_off[0], ys_off[1], ys_off[2], ys_off[3]
    no0, no1 = yn_off[0], yn_off[1]
    lw = friction_law(law)  # a constant in the copies of by_law
    p0, p1, p2, p3 = params[0, 0], params[0, 1], params[0, 2], params[0, 3]
    p4, p5, p6, p7 = params[0, 4], params[0, 5], params[0, 6], params[0, 7]
    last = max(h.size - 1, 0)
    c0 = max(c0, 0)
    i0 = max(base + c0, 0)
    is0 = max(base_s + c0, 0)  # (starts clamped at 0: no wraparound of negative indices)
    in0 = max(base_n + c0, 0)
    for j in range(c1 + 1 - c0):
        c = c0 + j
        i = i0 + j
        hc = h[i]
        wet = hc > h_zero
        hs = hc if wet else 1.0
        uc1 = hu[i] / hs
        uc2 = hv[i] / hs
        area = cell_area[i]
        # the faces' weights L / A: one division a cell in MUSCL-Hancock's copy, four in
        # Heun's (the face kernel's bits)
        inv = 1.0 / area
        l_w = x_len[c] * inv if PREDICT else x_len[c] / area
        l_e = x_len[c + 1] * inv if PREDICT else x_len[c + 1] / area
        l_s = ys_len[c] * inv if PREDICT else ys_len[c] / area
        l_n = yn_len[c] * inv if PREDICT else yn_len[c] / area
        cw, ce, cs, cn = x_code[c], x_code[c + 1], ys_code[c], yn_code[c]
        w_in = (cw & KIND) == INNER
        e_in = (ce & KIND) == INNER
        s_in = (cs & KIND) == INNER
        n_in = (cn & KIND) == INNER
        iw = max(i - 1, 0)
        ie = min(i + 1, last)
        i_s = is0 + j
        i_n = in0 + j
        # W (x face c: the cell its second side when inner), E (x face c + 1: its first),
        # S (y face below: second when inner), N (y face above: first)
        wx0, wy0, ho0, uo10, uo20, fr0 = _gg_face(
            hc, uc1, uc2, w_in, w_in, cw, xf0[c], xf1[c], xf2[c], xf3[c], l_w,
            h[iw], hu[iw], hv[iw], h_zero)
        wx1, wy1, ho1, uo11, uo21, fr1 = _gg_face(
            hc, uc1, uc2, e_in, False, ce, xf0[c + 1], xf1[c + 1], xf2[c + 1], xf3[c + 1],
            l_e, h[ie], hu[ie], hv[ie], h_zero)
        wx2, wy2, ho2, uo12, uo22, fr2 = _gg_face(
            hc, uc1, uc2, s_in, s_in, cs, sf0[c], sf1[c], sf2[c], sf3[c], l_s,
            h[i_s], hu[i_s], hv[i_s], h_zero)
        wx3, wy3, ho3, uo13, uo23, fr3 = _gg_face(
            hc, uc1, uc2, n_in, False, cn, nf0[c], nf1[c], nf2[c], nf3[c], l_n,
            h[i_n], hu[i_n], hv[i_n], h_zero)
        front = (fr0 | fr1) | (fr2 | fr3)
        # Green-Gauss sums (the mean of both sides on each face), in face order
        m0, m1, m2, m3 = 0.5 * (hc + ho0), 0.5 * (hc + ho1), 0.5 * (hc + ho2), 0.5 * (hc + ho3)
        g0 = _in_face_order(0.0, wx0 * m0, wx1 * m1, wx2 * m2, wx3 * m3)
        g1 = _in_face_order(0.0, wy0 * m0, wy1 * m1, wy2 * m2, wy3 * m3)
        m0, m1, m2, m3 = (0.5 * (uc1 + uo10), 0.5 * (uc1 + uo11), 0.5 * (uc1 + uo12),
                          0.5 * (uc1 + uo13))
        g2 = _in_face_order(0.0, wx0 * m0, wx1 * m1, wx2 * m2, wx3 * m3)
        g3 = _in_face_order(0.0, wy0 * m0, wy1 * m1, wy2 * m2, wy3 * m3)
        m0, m1, m2, m3 = (0.5 * (uc2 + uo20), 0.5 * (uc2 + uo21), 0.5 * (uc2 + uo22),
                          0.5 * (uc2 + uo23))
        g4 = _in_face_order(0.0, wx0 * m0, wx1 * m1, wx2 * m2, wx3 * m3)
        g5 = _in_face_order(0.0, wy0 * m0, wy1 * m1, wy2 * m2, wy3 * m3)
        # the neighbours' range, as reconstruct_cells keeps it (the same zero's sign)
        lo0, hi0 = _range(hc, ho0, ho1, ho2, ho3)
        lo1, hi1 = _range(uc1, uo10, uo11, uo12, uo13)
        lo2, hi2 = _range(uc2, uo20, uo21, uo22, uo23)
        # the offsets of the cell's side of each face (zero on boundary faces)
        rwx = xo2[c] if w_in else xo0[c]
        rwy = xo3[c] if w_in else xo1[c]
        rex, rey = xo0[c + 1], xo1[c + 1]
        rsx = so2[c] if s_in else so0[c]
        rsy = so3[c] if s_in else so1[c]
        rnx, rny = no0[c], no1[c]
        # Barth-Jespersen factors over the faces
        a0 = a1 = a2 = 1.0
        a0 = _bj_select(a0, g0 * rwx + g1 * rwy, hc, lo0, hi0, True)
        a1 = _bj_select(a1, g2 * rwx + g3 * rwy, uc1, lo1, hi1, False)
        a2 = _bj_select(a2, g4 * rwx + g5 * rwy, uc2, lo2, hi2, False)
        a0 = _bj_select(a0, g0 * rex + g1 * rey, hc, lo0, hi0, True)
        a1 = _bj_select(a1, g2 * rex + g3 * rey, uc1, lo1, hi1, False)
        a2 = _bj_select(a2, g4 * rex + g5 * rey, uc2, lo2, hi2, False)
        a0 = _bj_select(a0, g0 * rsx + g1 * rsy, hc, lo0, hi0, True)
        a1 = _bj_select(a1, g2 * rsx + g3 * rsy, uc1, lo1, hi1, False)
        a2 = _bj_select(a2, g4 * rsx + g5 * rsy, uc2, lo2, hi2, False)
        a0 = _bj_select(a0, g0 * rnx + g1 * rny, hc, lo0, hi0, True)
        a1 = _bj_select(a1, g2 * rnx + g3 * rny, uc1, lo1, hi1, False)
        a2 = _bj_select(a2, g4 * rnx + g5 * rny, uc2, lo2, hi2, False)
        gn = g * gamma_z[i]
        dens = density[i]
        if PREDICT:  # single-stage order 2: the sides of the state half a step on
            pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(lw, params, i, p0, p1, p2, p3,
                                                              p4, p5, p6, p7)
            ph, pu1, pu2 = half_step(hs, uc1, uc2, a0 * g0, a0 * g1, a1 * g2, a1 * g3,
                                     a2 * g4, a2 * g5, 0.0 if front else dt_half,
                                     gamma_x[i], gamma_y[i], gamma_z[i], 0.0, lw, pc0, pc1,
                                     pc2, pc3, pc4, pc5, pc6, pc7, g)
            hc, uc1, uc2 = ph, pu1, pu2
        # each side, zero where the cell is dry (it emits nothing)
        side = _side_direct if PREDICT else _side
        v0, v1, v2, v3, v4, v5, v6 = side(hc, uc1, uc2, a0, a1, a2, g0, g1, g2, g3, g4, g5,
                                          rwx, rwy, front, gn, dens)
        w_h[c], w_u1[c], w_u2[c] = (v0 if wet else 0.0), (v1 if wet else 0.0), (v2 if wet else 0.0)
        w_c[c], w_s[c] = (v3 if wet else 0.0), (v4 if wet else 0.0)
        w_kh[c], w_k3[c] = (v5 if wet else 0.0), (v6 if wet else 0.0)
        v0, v1, v2, v3, v4, v5, v6 = side(hc, uc1, uc2, a0, a1, a2, g0, g1, g2, g3, g4, g5,
                                          rex, rey, front, gn, dens)
        e_h[c], e_u1[c], e_u2[c] = (v0 if wet else 0.0), (v1 if wet else 0.0), (v2 if wet else 0.0)
        e_c[c], e_s[c] = (v3 if wet else 0.0), (v4 if wet else 0.0)
        e_kh[c], e_k3[c] = (v5 if wet else 0.0), (v6 if wet else 0.0)
        v0, v1, v2, v3, v4, v5, v6 = side(hc, uc1, uc2, a0, a1, a2, g0, g1, g2, g3, g4, g5,
                                          rsx, rsy, front, gn, dens)
        s_h[c], s_u1[c], s_u2[c] = (v0 if wet else 0.0), (v1 if wet else 0.0), (v2 if wet else 0.0)
        s_c[c], s_s[c] = (v3 if wet else 0.0), (v4 if wet else 0.0)
        s_kh[c], s_k3[c] = (v5 if wet else 0.0), (v6 if wet else 0.0)
        v0, v1, v2, v3, v4, v5, v6 = side(hc, uc1, uc2, a0, a1, a2, g0, g1, g2, g3, g4, g5,
                                          rnx, rny, front, gn, dens)
        n_h[c], n_u1[c], n_u2[c] = (v0 if wet else 0.0), (v1 if wet else 0.0), (v2 if wet else 0.0)
        n_c[c], n_s[c] = (v3 if wet else 0.0), (v4 if wet else 0.0)
        n_kh[c], n_k3[c] = (v5 if wet else 0.0), (v6 if wet else 0.0)


@njit(error_model="numpy", cache=True, _nrt=False)  # no reference counts: see _block_for
def _recon_row(r, c0, c1, nx, ny, x_code, ys_code, yn_code, x_frame, ys_frame, yn_frame,
               x_len, ys_len, yn_len, x_off, ys_off, yn_off, cell_area, density, gamma_z, h,
               hu, hv, h_zero, g, dt_half, gamma_x, gamma_y, law, params, out):
    """Order 2: what each cell ``c0..c1`` of row r emits through each of its sides
    (``out[SIDE_*, E_*, c]``) from its limited linear reconstruction: Green-Gauss gradients
    of h and of the velocity in the cell's basis over its faces W, E, S, N (their order of
    index in the mesh), Barth-Jespersen factors, the state at each face's offset
    (``x_off``, ``ys_off``, ``yn_off``: the row's offsets ``(rx0, ry0, rx1, ry1)`` of each
    face's two sides, :func:`avflow.numerics.solver.grid_offsets`). The face kernel's
    :func:`~avflow.numerics.reconstruction.reconstruct_cells` and step_faces' emitted states
    at order 2, the same operations, so the same bits. A cell at or below h_zero emits
    nothing (what it read of its neighbours is dropped: only a wet cell's neighbours lie
    where the work buffers hold the state, :func:`_sync_work`)."""
    w, e, s, n = out[SIDE_W], out[SIDE_E], out[SIDE_S], out[SIDE_N]
    _recon_cells(r * nx, max(r - 1, 0) * nx, min(r + 1, ny - 1) * nx, c0, c1, x_code, ys_code,
                 yn_code, x_frame, ys_frame, yn_frame, x_len, ys_len, yn_len, x_off, ys_off,
                 yn_off, cell_area, density, gamma_z, h, hu, hv, h_zero, g, dt_half, gamma_x,
                 gamma_y, law, params,
                 w[E_H], w[E_U1], w[E_U2], w[E_C], w[E_S], w[E_KH], w[E_K3],
                 e[E_H], e[E_U1], e[E_U2], e[E_C], e[E_S], e[E_KH], e[E_K3],
                 s[E_H], s[E_U1], s[E_U2], s[E_C], s[E_S], s[E_KH], s[E_K3],
                 n[E_H], n[E_U1], n[E_U2], n[E_C], n[E_S], n[E_KH], n[E_K3])


@njit(error_model="numpy", cache=True, inline="always")
def _in_face_order(start, a_w, a_e, a_s, a_n):
    """``start`` plus a cell's four side terms in the order of its faces' indices in the
    mesh, W, E, S, N for every cell of a square grid (its faces are numbered in grid order,
    :mod:`avflow.terrain.mesh`): the face kernel's order of summation, so the same bits."""
    return (((start + a_w) + a_e) + a_s) + a_n


@njit(error_model="numpy", cache=True, inline="always")
def _side_terms(c, x_code, y_south, xf0, xf1, xf2, xf3, xf4, ys0, ys1, ys2, ys3, ys4, yn0, yn1,
                yn2):
    """A cell's four side terms (mass, x, y) from the row's face fluxes (one line per
    component: 2D indexing keeps LLVM from vectorising): a face brings +F_j to its second
    cell and -F_i to its first; W and S are the cell's own faces only when they are
    boundary faces (codes other than INNER)."""
    w_in = (x_code[c] & KIND) == INNER
    s_in = (y_south[c] & KIND) == INNER
    # every value loaded whichever is kept: a load under a condition becomes a masked
    # load or a gather in the vector loop, slower than the scalar loop (docs/performance.md)
    w0, w1, w2, w3, w4 = xf0[c], xf1[c], xf2[c], xf3[c], xf4[c]
    s0, s1, s2, s3, s4 = ys0[c], ys1[c], ys2[c], ys3[c], ys4[c]
    return ((w0 if w_in else -w0), (w3 if w_in else -w1), (w4 if w_in else -w2),
            -xf0[c + 1], -xf1[c + 1], -xf2[c + 1],
            (s0 if s_in else -s0), (s3 if s_in else -s1), (s4 if s_in else -s2),
            -yn0[c], -yn1[c], -yn2[c])


def _trial_cells(base, c0, c1, valid, x_code, y_south, y_north, xf, ys, yn, em,
                 inv_area, gamma_x, gamma_y, gamma_z, curvature, h, hu, hv, law, params, g,
                 h_zero, dt, dt_decide, flags, qx_out, qy_out):
    """Per cell of a row: the flux divergence, the trial momentum of eq. 47 and the flag of
    eq. 49 (``flags[c + 1]``: the flag lines carry one column of padding on each side;
    ``qx_out[c]``, ``qy_out[c]``); a dry cell keeps its momentum sum for
    :func:`_final_cells` (as the face kernel's sweep 1b).

    One loop without jumps (selects), which LLVM vectorises for
    the laws without transcendental functions (Coulomb, Voellmy): the face kernel's
    operations on every value kept, so the same bits."""
    lw = friction_law(law)  # a constant in the copies of by_law
    p0, p1, p2, p3 = params[0, 0], params[0, 1], params[0, 2], params[0, 3]
    p4, p5, p6, p7 = params[0, 4], params[0, 5], params[0, 6], params[0, 7]
    e_u1, e_u2, e_speed = em[E_U1], em[E_U2], em[E_SPEED]
    xf0, xf1, xf2, xf3, xf4 = xf[0], xf[1], xf[2], xf[3], xf[4]
    ys0, ys1, ys2, ys3, ys4 = ys[0], ys[1], ys[2], ys[3], ys[4]
    yn0, yn1, yn2 = yn[0], yn[1], yn[2]
    k11, k12, k22 = curvature[0], curvature[1], curvature[2]
    c0 = max(c0, 0)
    i0 = max(base + c0, 0)
    for j in range(c1 + 1 - c0):
        c = c0 + j
        i = i0 + j
        wm, wx, wy, e_m, ex, ey, sm, sx, sy, nm, nx_, ny_ = _side_terms(
            c, x_code, y_south, xf0, xf1, xf2, xf3, xf4, ys0, ys1, ys2, ys3, ys4, yn0, yn1, yn2)
        mx = _in_face_order(0.0, wx, ex, sx, nx_)
        my = _in_face_order(0.0, wy, ey, sy, ny_)
        mh = _in_face_order(0.0, wm, e_m, sm, nm)
        ia = inv_area[i]
        u1 = e_u1[c]
        u2 = e_u2[c]
        centripetal = k11[i] * u1 * u1 + 2.0 * k12[i] * u1 * u2 + k22[i] * u2 * u2  # u.K.u, as physics.centripetal_accel
        pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(lw, params, i, p0, p1, p2, p3,
                                                          p4, p5, p6, p7)
        qx, qy, fi = trial_momentum(h[i], h_zero, e_speed[c], hu[i], hv[i],
                                     mh * ia, mx * ia, my * ia, dt,
                                     dt_decide, gamma_x[i], gamma_y[i], gamma_z[i],
                                     centripetal, lw, pc0, pc1, pc2, pc3,
                                     pc4, pc5, pc6, pc7, g, TIMING)
        dry = h[i] <= h_zero  # no trial: the momentum sum itself
        qx_out[c] = mx if dry else qx
        qy_out[c] = my if dry else qy
        flags[c + 1] = DRY if (valid[i] == 0 or dry) else fi


#: Per-cell lines of a row kept by :func:`_final_cells` for its sums: inverse CFL limit,
#: kinetic energy, moving volume, film volume, outflow
N_SCRATCH = 5

#: Bits of a cell's byte in the line the first loop of :func:`_final_cells` leaves for the
#: second: its W, E, S, N faces are Dirac faces; its update was kept (inside the DEM, h >= 0)
M_W, M_E, M_S, M_N, M_GOOD = 1, 2, 4, 8, 16


def _final_cells(r, base, c0, c1, valid, x_code, y_south, y_north, x_len, ys_len,
                 yn_len, xf, ys, yn, em, fl_s, fl, fl_n, qx_in, qy_in, cell_area, cfl_factor,
                 gamma_x, gamma_y, gamma_z, curvature, h, h_new, hu_new, hv_new, flag, law,
                 params, g, dirac, h_dry, h_zero, dt, rows, wet_lo, wet_hi, marks, t_inv, t_kin,
                 t_mov, t_film, t_out, em_s, em_n, transport):
    """Final update of row r, in two loops: (1) mass through the faces that keep the
    rectangular density, the projection; h, q and the flag of each cell, and ``marks[c]``
    (its Dirac faces and whether its update was kept, ``M_*``); (2) from what (1) wrote, the
    row's sums (``rows[r]``) and the columns of its wet cells. ``fl_s, fl,
    fl_n``: the flags of the rows below, of this one and above (cell c at ``c + 1``).

    Each loop is without jumps, so that LLVM vectorises it: every write is a select (a cell
    outside the DEM keeps h = 0 and q = 0; a cell that went below 0 makes the step be
    redone, whatever it wrote), and what the row's sums need is kept per cell in ``t_*``
    (separate arrays: lines of one array might overlap for LLVM, and the checks kept the
    loop scalar), then added line by line (:func:`~avflow.numerics.vectorize.line_sum`: the
    grid-wide diagnostics differ from the face kernel's cell-by-cell sums by round-off).

    Two loops, because one loop over the forty-odd lines of both kept most of their base
    pointers on the stack; in one function, because a call per loop cost every row a
    fixed overhead (both measured: docs/performance.md).

    In a stage of order 2 (``ORDER2``, a constant of the copy): friction with the stage's
    own thickness (physics.final_momentum's ``explicit``), and ``transport[i]``, the
    largest mass flux per metre through the cell's faces that are not Dirac, written where
    the face kernel's stage would touch the cell (it or a neighbour across an inner face
    wet: ``em_s``, ``em``, ``em_n``, the emitted thickness of the rows below, of this one
    and above) for Heun's merge."""
    lw = friction_law(law)  # a constant in the copies of by_law
    p0, p1, p2, p3 = params[0, 0], params[0, 1], params[0, 2], params[0, 3]
    p4, p5, p6, p7 = params[0, 4], params[0, 5], params[0, 6], params[0, 7]
    e_u1, e_u2, e_speed = em[E_U1], em[E_U2], em[E_SPEED]
    xf0, xf1, xf2, xf3, xf4 = xf[0], xf[1], xf[2], xf[3], xf[4]
    ys0, ys1, ys2, ys3, ys4 = ys[0], ys[1], ys[2], ys[3], ys[4]
    yn0, yn1, yn2 = yn[0], yn[1], yn[2]
    k11, k12, k22 = curvature[0], curvature[1], curvature[2]
    c0 = max(c0, 0)
    i0 = max(base + c0, 0)
    n_bad = 0
    clamped = 0
    # 1. the state: h, q, flags, and the marks the second loop reads
    for j in range(c1 + 1 - c0):
        c = c0 + j
        i = i0 + j
        # every value loaded whichever is kept, and & | instead of and / or: a load under a
        # condition becomes a masked load or a gather, or keeps the loop scalar
        inside = valid[i] != 0
        fi = fl[c + 1]
        f_w, f_e, f_s, f_n = fl[c], fl[c + 2], fl_s[c + 1], fl_n[c + 1]
        w_in = (x_code[c] & KIND) == INNER
        e_in = (x_code[c + 1] & KIND) == INNER
        s_in = (y_south[c] & KIND) == INNER
        n_in = (y_north[c] & KIND) == INNER
        wm, wx, wy, e_m, ex, ey, sm, sx, sy, nm, nx_, ny_ = _side_terms(
            c, x_code, y_south, xf0, xf1, xf2, xf3, xf4, ys0, ys1, ys2, ys3, ys4, yn0, yn1, yn2)
        area = cell_area[i]
        h_old = h[i]
        qx = qx_in[c]
        qy = qy_in[c]
        gx, gy, gz = gamma_x[i], gamma_y[i], gamma_z[i]
        speed_n = e_speed[c]
        u1 = e_u1[c]
        u2 = e_u2[c]
        kappa11, kappa12, kappa22 = k11[i], k12[i], k22[i]
        old_flag = flag[i]
        # Dirac faces (eqs. 51-53): both sides at zero temperature; a boundary ghost shares
        # its cell's flag
        d_w = dirac_face(dirac, fi, f_w if w_in else fi)  # a boundary's ghost: the cell's flag
        d_e = dirac_face(dirac, fi, f_e if e_in else fi)
        d_s = dirac_face(dirac, fi, f_s if s_in else fi)
        d_n = dirac_face(dirac, fi, f_n if n_in else fi)
        acc = _in_face_order(0.0, 0.0 if d_w else wm, 0.0 if d_e else e_m,
                             0.0 if d_s else sm, 0.0 if d_n else nm)
        # a dry side takes no momentum through a Dirac face: what those faces brought to the
        # sum of the trial, taken back in face order (W, E, S, N), kept where one is Dirac
        any_dirac = d_w | d_e | d_s | d_n
        bx = take_back(take_back(take_back(take_back(qx, wx, d_w), ex, d_e), sx, d_s), nx_, d_n)
        by = take_back(take_back(take_back(take_back(qy, wy, d_w), ey, d_e), sy, d_s), ny_, d_n)
        dry = fi == DRY
        centripetal = kappa11 * u1 * u1 + 2.0 * kappa12 * u1 * u2 + kappa22 * u2 * u2
        pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(lw, params, i, p0, p1, p2, p3,
                                                          p4, p5, p6, p7)
        hn, qx, qy, cl = cell_update(dry, fi, h_old, acc, bx if dry & any_dirac else qx,
                                     by if dry & any_dirac else qy, area, dt, gx, gy, gz,
                                     centripetal, speed_n, lw, pc0, pc1, pc2, pc3, pc4, pc5,
                                     pc6, pc7, g, h_zero, TIMING, False)
        good = inside & (hn >= 0.0)
        n_bad += 1 if inside & (hn < 0.0) else 0
        # writes: the new value where the cell is updated, else what is there
        flag[i] = fi if inside else old_flag
        # (a cell outside the DEM keeps h = 0, q = 0; one that went below 0 writes what it
        # had: its step is redone)
        h_new[i] = hn if good else h_old
        hu_new[i] = qx if good else 0.0
        hv_new[i] = qy if good else 0.0
        clamped += cl if good else 0
        marks[c] = (((M_W if d_w else 0) | (M_E if d_e else 0)) | ((M_S if d_s else 0)
                    | (M_N if d_n else 0))) | (M_GOOD if good else 0)
    # 2. the row's sums, from what the first loop wrote
    w_lo = x_len.size
    w_hi = -1
    for j in range(c1 + 1 - c0):
        c = c0 + j
        i = i0 + j
        m = marks[c]
        good = (m & M_GOOD) != 0
        d_w = (m & M_W) != 0
        d_e = (m & M_E) != 0
        d_s = (m & M_S) != 0
        d_n = (m & M_N) != 0
        w_code, e_code, s_code, n_code = x_code[c], x_code[c + 1], y_south[c], y_north[c]
        # the mass side terms (the momentum ones, unused, LLVM drops with their loads)
        wm, _, _, e_m, _, _, sm, _, _, nm, _, _ = _side_terms(
            c, x_code, y_south, xf0, xf1, xf2, xf3, xf4, ys0, ys1, ys2, ys3, ys4, yn0, yn1, yn2)
        area = cell_area[i]
        hn = h_new[i]  # the update where it was kept (good); nothing below reads it else
        qx = hu_new[i]
        qy = hv_new[i]
        speed_n = e_speed[c]
        len_w, len_e, len_s, len_n = x_len[c], x_len[c + 1], ys_len[c], yn_len[c]
        speed, inv_i = observe_cell(hn, math.sqrt(qx * qx + qy * qy), cfl_factor[i], gamma_z[i],
                                    g)
        # the moving rule (physics.cell_moves) through the faces that are not Dirac
        carried = (((not d_w) & carries(wm, hn, speed_n, len_w))
                   | ((not d_e) & carries(e_m, hn, speed_n, len_e))
                   | ((not d_s) & carries(sm, hn, speed_n, len_s))
                   | ((not d_n) & carries(nm, hn, speed_n, len_n)))
        moves = good & cell_moves(speed, speed_n, carried)
        t_inv[c] = inv_i if good else 0.0
        kin, t_mov[c], t_film[c] = step_terms(hn, area, speed, moves, h_dry)
        t_kin[c] = kin if good else 0.0
        # what left through open sides (a face's flux is outward from its owner: -term for
        # the cell's own faces), through the faces that are not Dirac
        open_w = ((w_code & KIND) == HIGH_OPEN) & (not d_w) & (wm < 0.0)
        open_e = ((e_code & KIND) == LOW_OPEN) & (not d_e) & (e_m < 0.0)
        open_s = ((s_code & KIND) == HIGH_OPEN) & (not d_s) & (sm < 0.0)
        open_n = ((n_code & KIND) == LOW_OPEN) & (not d_n) & (nm < 0.0)
        out_w = outflow_volume(-wm, dt) if open_w else 0.0
        out_e = outflow_volume(-e_m, dt) if open_e else 0.0
        out_s = outflow_volume(-sm, dt) if open_s else 0.0
        out_n = outflow_volume(-nm, dt) if open_n else 0.0
        t_out[c] = ((out_w + out_e) + out_s) + out_n if good else 0.0
        if ORDER2:  # step_faces' transport: only faces that are not Dirac (eq. 53)
            unit = max(max(max(0.0 if d_w else abs(wm) / len_w, 0.0 if d_e else abs(e_m) / len_e),
                           0.0 if d_s else abs(sm) / len_s), 0.0 if d_n else abs(nm) / len_n)
            e_h = em[E_H]
            touched = ((e_h[c] > 0.0) | (((w_code & KIND) == INNER) & (e_h[max(c - 1, 0)] > 0.0))
                       | (((e_code & KIND) == INNER) & (e_h[min(c + 1, e_h.size - 1)] > 0.0))
                       | (((s_code & KIND) == INNER) & (em_s[E_H, c] > 0.0))
                       | (((n_code & KIND) == INNER) & (em_n[E_H, c] > 0.0)))
            transport[i] = unit if touched else transport[i]
        wet = good & (hn > h_zero)
        w_lo = min(w_lo, c) if wet else w_lo
        w_hi = max(w_hi, c) if wet else w_hi
    # the row's sums (in an order of their own: the face kernel's sums differ by round-off)
    inv_lim = line_max(t_inv, c0, c1)
    outflow = line_sum(t_out, c0, c1)
    moving = line_sum(t_mov, c0, c1)
    film = line_sum(t_film, c0, c1)
    kinetic = line_sum(t_kin, c0, c1)
    rows[r, R_OK] = 1.0 if n_bad == 0 else 0.0
    rows[r, R_OUT] = outflow
    rows[r, R_INV] = inv_lim
    rows[r, R_MOVING] = moving
    rows[r, R_FILM] = film
    rows[r, R_KINETIC] = kinetic
    rows[r, R_CLAMPED] = clamped
    wet_lo[r] = w_lo
    wet_hi[r] = w_hi




@njit(error_model="numpy", cache=True, inline="always")
def _span(r, r0, r1, lo, hi, nx):
    """Columns swept in row r; empty, as ``(nx, -1)``, outside the band of rows r0..r1 (so
    that min / max of spans ignore it)."""
    if r < r0 or r > r1:
        return nx, -1
    return lo[r], hi[r]


def _sweep_block(a, b, nx, ny, valid, x_code, x_frame, x_length, y_code, y_frame,
                 y_length, cell_area, inv_area, cfl_factor, density, gamma_x, gamma_y,
                 gamma_z, curvature, h, hu, hv, h_new, hu_new, hv_new, flag, law, params, g, dirac,
                 h_dry, h_zero, dt, dt_decide, r0, r1, lo, hi, rows, wet_lo, wet_hi, emit, xf,
                 yf, fl, scratch, qx, qy, marks, x_off, y_off, transport, recon):
    """One step on the rows ``a..b`` of the swept band ``r0..r1``, as a wavefront: at stage
    k the faces of row k (its x faces, the y faces below it), the trial of row k - 1, the
    final update of row k - 2, so that a row's fluxes and flags are still in cache when they
    are used, and no face or flag array of the whole grid is needed. The rows a - 1 and
    b + 1 are computed here too (their faces and flags, never written out): the block needs
    nothing from its neighbours, and what it writes (rows a..b) no other block writes.

    Compiled once per friction law with that law's copies of the cell loops
    (:func:`~avflow.numerics.vectorize.by_law`): one call per block, rather than a layer
    of dispatch per row (docs/performance.md).

    A stage of order 2 (``ORDER2``) is the same sweep, its faces fed the reconstructed
    sides of each row (:func:`_recon_row`, into the ring ``recon``; ``x_off``, ``y_off``:
    the faces' offsets) instead of the cells' emitted values, which the cell passes still
    read for u^n and |u^n|."""
    ring = RING
    for k in range(a - 1, b + 3):
        # --- faces of row k: what rows k - 1 and k emit, computed once per cell
        s0, s1 = _span(k, r0, r1, lo, hi, nx)
        p0_, p1_ = _span(k - 1, r0, r1, lo, hi, nx)
        if k - 1 >= 0 and k - 1 < ny and k == a - 1:  # the block's first row below
            q0, q1 = _span(k - 2, r0, r1, lo, hi, nx)
            n0 = min(min(p0_, s0), q0) - 1
            n1 = max(max(p1_, s1), q1) + 1
            _emit_row((k - 1) * nx, max(n0, 0), min(n1, nx - 1), h, hu, hv, gamma_z,
                      density, h_zero, g, emit[(k - 1) % ring])
            if SIDES:
                _recon_row(k - 1, max(n0, 0), min(n1, nx - 1), nx, ny, x_code[k - 1],
                           y_code[k - 1], y_code[k], x_frame[k - 1], y_frame[k - 1],
                           y_frame[k], x_length[k - 1], y_length[k - 1], y_length[k],
                           x_off[k - 1], y_off[k - 1], y_off[k], cell_area, density, gamma_z,
                           h, hu, hv, h_zero, g, 0.5 * dt, gamma_x, gamma_y, law, params,
                           recon[(k - 1) % ring])
        if 0 <= k < ny:
            n_0, n_1 = _span(k + 1, r0, r1, lo, hi, nx)
            e0 = min(min(p0_, s0), n_0) - 1
            e1 = max(max(p1_, s1), n_1) + 1
            _emit_row(k * nx, max(e0, 0), min(e1, nx - 1), h, hu, hv, gamma_z, density,
                      h_zero, g, emit[k % ring])
            if SIDES:
                _recon_row(k, max(e0, 0), min(e1, nx - 1), nx, ny, x_code[k], y_code[k],
                           y_code[k + 1], x_frame[k], y_frame[k], y_frame[k + 1],
                           x_length[k], y_length[k], y_length[k + 1], x_off[k], y_off[k],
                           y_off[k + 1], cell_area, density, gamma_z, h, hu, hv, h_zero, g,
                           0.5 * dt, gamma_x, gamma_y, law, params, recon[k % ring])
            if s0 <= s1 and k <= b + 1:
                if SIDES:  # a face: the west cell's east side, the east cell's west side
                    _x_faces(s0, s1 + 1, x_code[k], x_frame[k], x_length[k],
                             recon[k % ring][SIDE_E], recon[k % ring][SIDE_W], xf[k % ring])
                else:
                    _x_faces(s0, s1 + 1, x_code[k], x_frame[k], x_length[k], emit[k % ring],
                             emit[k % ring], xf[k % ring])
        if 0 <= k <= ny:
            c0 = min(s0, p0_)
            c1 = max(s1, p1_)
            if c0 <= c1:
                if SIDES:  # the lower row's north sides, the upper row's south sides
                    _y_faces(c0, c1, y_code[k], y_frame[k], y_length[k],
                             recon[(k - 1) % ring][SIDE_N], recon[k % ring][SIDE_S],
                             yf[k % ring])
                else:
                    _y_faces(c0, c1, y_code[k], y_frame[k], y_length[k], emit[(k - 1) % ring],
                             emit[k % ring], yf[k % ring])
        # --- trial of row k - 1
        t = k - 1
        if a - 1 <= t <= b + 1 and 0 <= t < ny:
            t0, t1 = _span(t, r0, r1, lo, hi, nx)
            if t0 <= t1:
                _trial_cells(t * nx, t0, t1, valid, x_code[t], y_code[t],
                           y_code[t + 1], xf[t % ring], yf[t % ring], yf[(t + 1) % ring],
                           emit[t % ring], inv_area, gamma_x, gamma_y, gamma_z, curvature, h, hu, hv, law,
                           params, g, h_zero, dt, dt_decide, fl[t % ring], qx[t % ring],
                           qy[t % ring])
        # --- final update of row k - 2
        f = k - 2
        if a <= f <= b:
            f0, f1 = _span(f, r0, r1, lo, hi, nx)
            if f0 <= f1:
                _final_cells(f, f * nx, f0, f1, valid, x_code[f], y_code[f],
                             y_code[f + 1], x_length[f], y_length[f], y_length[f + 1],
                             xf[f % ring], yf[f % ring], yf[(f + 1) % ring], emit[f % ring],
                             fl[(f - 1) % ring], fl[f % ring], fl[(f + 1) % ring],
                             qx[f % ring], qy[f % ring], cell_area, cfl_factor, gamma_x,
                             gamma_y, gamma_z, curvature, h, h_new, hu_new, hv_new, flag, law,
                             params, g, dirac, h_dry, h_zero, dt, rows, wet_lo, wet_hi, marks,
                             scratch[0],
                             scratch[1], scratch[2], scratch[3], scratch[4],
                             emit[(f - 1) % ring], emit[(f + 1) % ring], transport)
            else:
                rows[f, R_OK] = 1.0
                rows[f, R_OUT] = 0.0
                rows[f, R_INV] = 0.0
                rows[f, R_MOVING] = 0.0
                rows[f, R_FILM] = 0.0
                rows[f, R_KINETIC] = 0.0
                rows[f, R_CLAMPED] = 0.0
                rows[f, R_FALLBACK] = 0.0
                wet_lo[f] = nx
                wet_hi[f] = -1


#: Rows of the ring buffers of a block (:func:`_rings`)
RING = 4


#: A set of ring buffers per thread (:func:`_rings`): rows' emitted values, their x faces
#: and the y faces below them, flags, scratch lines, trial momenta, a row's marks, and
#: at order 2 the reconstructed sides of each face of a row
Rings = namedtuple("Rings", "emit x_faces y_faces flags scratch qx qy marks sides")


@njit(error_model="numpy", cache=True)
def _rings(n, nx, order2):
    """``n`` sets of a block's ring buffers (:func:`_sweep_block`), one per thread: what rows
    emit, their x faces and the y faces below them, flags (cell c at c + 1), trial momenta,
    and lines of one row.

    Made once per solver (:meth:`~avflow.numerics.solver.Solver.advance` keeps them), not
    per step: a set spans the map's width, and fresh pages at every step would have to be
    faulted in and zeroed (docs/performance.md).
    What a set holds from the blocks before it (of this step or the last: the ring was
    always reused from row to row) changes nothing: the passes over a row read the emitted
    values and face fluxes that the passes before them wrote in the same stage; a flag read
    one column beyond a row's trial is that of a cell next to cells that emit nothing, whose
    face carries nothing whatever the flag says; the flags' padding columns (beyond the
    map's sides) decide nothing, a boundary face's ghost taking its cell's flag
    (tests/test_square_grid.py fills the sets with NaN and FLOWING flags between calls: the
    same bits). ``order2``: with the ring of the reconstructed sides (:func:`_recon_row`),
    empty at order 1."""
    return Rings(np.zeros((n, RING, N_EMIT, nx)), np.zeros((n, RING, 5, nx + 1)),
                 np.zeros((n, RING, 5, nx)), np.full((n, RING, nx + 2), DRY, dtype=np.uint8),
                 np.zeros((n, N_SCRATCH, nx)), np.zeros((n, RING, nx)),
                 np.zeros((n, RING, nx)), np.zeros((n, nx), dtype=np.uint8),
                 np.zeros((n, RING, 4, N_EMIT, nx if order2 else 0)))


def _block_for(law, label, order2=False, hancock=False):
    """:func:`_sweep_block` for one law (None: read at run time), calling that law's copies
    of the cell loops, for a step of order 1 or a stage of order 2 (``order2``); the block
    and the row passes it calls are compiled without reference counting
    (:func:`~avflow.numerics.vectorize.by_law`'s ``nrt``), as they allocate nothing: the
    buffers come from :func:`_rings`."""
    if order2:
        label += "_order2"
    names = {}
    timing = MIDPOINT if hancock else order2
    if hancock:  # one stage, its sides predicted: each law its copy of the reconstruction
        label += "_hancock"
        cells = by_law(_recon_cells.py_func, law, label, nrt=False, PREDICT=True)
        names["_recon_row"] = by_law(_recon_row.py_func, law, label, nrt=False,
                                     _recon_cells=cells)
    return by_law(_sweep_block, law, label, nrt=False, SIDES=order2 or hancock, **names,
                  _trial_cells=by_law(_trial_cells, law, label, nrt=False, TIMING=timing),
                  _final_cells=by_law(_final_cells, law, label, nrt=False, ORDER2=order2,
                                      TIMING=timing))


#: :func:`_sweep_block` per (law kind, order 2)
_BLOCKS = {(kind, scheme): _block_for(None if kind == ANY_LAW else kind, law_label(kind),
                                      scheme == "heun", scheme == "hancock")
           for kind in (COULOMB, VOELLMY, ANY_LAW) for scheme in ("order1", "heun", "hancock")}


#: The rows a step sweeps: ``r0..r1``, each row's columns ``lo..hi``, the rows' sums
#: (``R_*`` slots), and each row's wet extent (kept from step to step)
Band = namedtuple("Band", "r0 r1 lo hi rows wet_lo wet_hi")


def _sweep(n_blocks, grid, physics, cur, nxt, flag, dt, dt_decide, band, rings, transport):
    """One step on the band ``r0..r1`` (``band``: :data:`Band`), from ``cur`` into ``nxt``
    (:data:`~avflow.numerics.stepping.Conserved`), cut in ``n_blocks`` blocks of rows, one
    per task; ``rings``: the ring buffers (:func:`_rings`), a set per thread; ``transport``:
    each cell's transport, kept by a stage of order 2 (empty at order 1). The block
    sweep takes its arrays one by one: LLVM knows only arguments not to overlap
    (:func:`~avflow.numerics.vectorize.noalias`)."""
    r0, r1 = band.r0, band.r1
    n_rows = r1 - r0 + 1
    for blk in prange(n_blocks):
        a = r0 + (n_rows * blk) // n_blocks
        b = r0 + (n_rows * (blk + 1)) // n_blocks - 1
        if a <= b:
            slot = thread_slot()  # the ring buffers of the thread running this block
            sweep_block(
                a, b, grid.nx, grid.ny, grid.valid, grid.x_code, grid.x_frame, grid.x_length,
                grid.y_code, grid.y_frame, grid.y_length, grid.cell_area, grid.inv_area,
                grid.cfl_factor, grid.density, grid.gamma_x, grid.gamma_y, grid.gamma_z,
                grid.curvature, cur.h, cur.hu, cur.hv, nxt.h, nxt.hu, nxt.hv, flag,
                physics.law, physics.params, physics.g, physics.dirac, physics.h_dry,
                physics.h_zero, dt, dt_decide, r0, r1, band.lo, band.hi, band.rows,
                band.wet_lo, band.wet_hi, rings.emit[slot], rings.x_faces[slot],
                rings.y_faces[slot], rings.flags[slot], rings.scratch[slot], rings.qx[slot],
                rings.qy[slot], rings.marks[slot], grid.x_offset, grid.y_offset, transport,
                rings.sides[slot])


@noalias
@njit(error_model="numpy", cache=True, _nrt=False)  # no reference counts: see _block_for
def _heun_cells(r, base, c0, c1, lo1, hi1, valid, h0, hu0, hv0, h2, hu2, hv2, flag1,
                transport, cell_area, cfl_factor, gamma_z, g, h_dry, h_zero, h_new, hu_new,
                hv_new, rows, wet_lo, wet_hi, t_inv, t_kin, t_mov, t_film, t_fb):
    """Heun's merge of the cells ``c0..c1`` of row r (:func:`_heun_rows`), one loop without
    jumps (every value loaded whichever is kept), each cell's terms of the row's sums kept
    in ``t_*`` and added line by line, as :func:`_final_cells` does."""
    c0 = max(c0, 0)
    i0 = max(base + c0, 0)
    w_lo = h_new.size
    w_hi = -1
    for j in range(c1 + 1 - c0):
        c = c0 + j
        i = i0 + j
        f = flag1[i]
        f1 = f if (lo1 <= c) & (c <= hi1) else DRY  # stage 1's flag where it swept
        a = h0[i]
        qa, qb = hu0[i], hv0[i]
        hn, qx, qy, fell_back = heun_average(a, qa, qb, h2[i], hu2[i], hv2[i], f1, h_zero)
        h_new[i] = hn
        hu_new[i] = qx
        hv_new[i] = qy
        inside = valid[i] != 0
        speed, inv_i = observe_cell(hn, math.sqrt(qx * qx + qy * qy), cfl_factor[i],
                                    gamma_z[i], g)
        speed_n = speed_of(a, qa, qb)
        moves = cell_moves(speed, speed_n, carries(transport[i], hn, speed_n, 1.0))
        t_kin[c], t_mov[c], t_film[c] = step_terms(hn, cell_area[i], speed, moves, h_dry)
        t_inv[c] = inv_i
        t_fb[c] = fell_back
        wet = inside & (hn > h_zero)
        w_lo = min(w_lo, c) if wet else w_lo
        w_hi = max(w_hi, c) if wet else w_hi
    rows[r, R_INV] = line_max(t_inv, c0, c1)
    rows[r, R_KINETIC] = line_sum(t_kin, c0, c1)
    rows[r, R_MOVING] = line_sum(t_mov, c0, c1)
    rows[r, R_FILM] = line_sum(t_film, c0, c1)
    rows[r, R_FALLBACK] = line_sum(t_fb, c0, c1)
    wet_lo[r] = w_lo  # (none wet: lo > hi)
    wet_hi[r] = w_hi


@njit(error_model="numpy", cache=True, _nrt=False)
def _heun_rows(r0, r1, lo, hi, lo1, hi1, nx, valid, cell_area, cfl_factor, gamma_z, physics,
               start, stage2, flag1, transport, new, rows, wet_lo, wet_hi, scratch):
    """Order 2: Heun's merge (:func:`~avflow.numerics.physics.heun_average`) of the swept
    rows ``r0..r1`` (columns ``lo..hi``) from ``start`` and ``stage2`` into ``new``, with
    each row's sums (``rows``: R_INV, R_MOVING, R_FILM,
    R_KINETIC, R_FALLBACK) and wet columns, as :func:`~avflow.numerics.kernels.heun_faces`
    per cell (the same bits; the sums added per row, then over the rows: round-off).
    ``flag1``: the first stage's flags, read where it swept (``lo1..hi1``), DRY beyond
    (the face kernel's stage-1 flags outside its lists). ``scratch``: five lines of a row."""
    for r in range(r0, r1 + 1):
        if lo[r] > hi[r]:
            rows[r, R_INV] = rows[r, R_KINETIC] = rows[r, R_MOVING] = 0.0
            rows[r, R_FILM] = rows[r, R_FALLBACK] = 0.0
            wet_lo[r] = nx
            wet_hi[r] = -1
            continue
        _heun_cells(r, r * nx, lo[r], hi[r], lo1[r], hi1[r], valid, start.h, start.hu,
                    start.hv, stage2.h, stage2.hu, stage2.hv, flag1, transport, cell_area,
                    cfl_factor, gamma_z, physics.g, physics.h_dry, physics.h_zero, new.h,
                    new.hu, new.hv, rows, wet_lo, wet_hi, scratch[0], scratch[1], scratch[2],
                    scratch[3], scratch[4])


@njit(error_model="numpy", cache=True, inline="always")
def _row_sums(rows, r0, r1):
    """The step's sums from the rows' (in row order): ``(ok, outflow, inverse CFL limit,
    moving, film, kinetic, clamped, fallbacks)``."""
    ok = True
    outflow = 0.0
    inv_lim = 0.0
    moving = 0.0
    film = 0.0
    kinetic = 0.0
    clamped = 0
    fallbacks = 0
    for r in range(r0, r1 + 1):
        if rows[r, R_OK] == 0.0:
            ok = False
        outflow += rows[r, R_OUT]
        inv_lim = max(inv_lim, rows[r, R_INV])
        moving += rows[r, R_MOVING]
        film += rows[r, R_FILM]
        kinetic += rows[r, R_KINETIC]
        clamped += int(rows[r, R_CLAMPED])
        fallbacks += int(rows[r, R_FALLBACK])
    return ok, outflow, inv_lim, moving, film, kinetic, clamped, fallbacks


#: The order-2 step's regions (:func:`_order2_step`): the second stage's spans (``lo2``,
#: ``hi2``), what it needs (``need2_*``), and the first stage's spans on its rows (``prev2_*``)
Region2 = namedtuple("Region2", "lo2 hi2 need2_lo need2_hi prev2_lo prev2_hi")


def _order2_step(threads, grid, fields, work, physics, run, cur, nxt, when, band, reg,
                 sync_lo, sync_hi):
    """One step of order 2 on the grid: stage 1 (``cur`` -> ``nxt``, flags into the work's
    ``flag1``) on the swept band ``band``; stage 2 (``nxt`` -> the work's ``s_*``) on that
    band joined with what the first stage's wet cells need (:func:`_swept_columns`, so every
    cell stage 1 changed is swept again: the face kernel's stage 2 keeps stage 1's state on
    the cells it does not touch, which are dry and unchanged here); Heun's merge of ``cur``
    and stage 2 into ``nxt`` over the second band (:func:`_heun_rows`). Each stage is the
    order-1 sweep with reconstructed sides (:func:`_sweep_block`'s ``ORDER2`` copy).
    Returns ``(ok, outflow, inverse CFL limit, moving, film, kinetic, clamped, fallbacks,
    r0, r1)`` (the second band's rows)."""
    nx, ny = grid.nx, grid.ny
    s = Conserved(work.s_h, work.s_hu, work.s_hv)
    r0, r1, lo, hi = band.r0, band.r1, band.lo, band.hi
    rows, wet_lo, wet_hi = band.rows, band.wet_lo, band.wet_hi
    fail = (False, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0, r0, r1)
    if r1 < r0:  # nothing wet: nothing moves
        return (True, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0, r0, r1)
    _stage(threads, grid, physics, cur, nxt, work.flag1, when, band, work.rings,
           work.transport, run)
    ok, out1, _, _, _, _, clamped1, _ = _row_sums(rows, r0, r1)
    if not ok:
        return fail
    for r in range(max(r0 - 1, 0), min(r1 + 2, ny)):  # stage 1's spans, none off its band
        inside = r0 <= r <= r1
        reg.prev2_lo[r] = lo[r] if inside else nx
        reg.prev2_hi[r] = hi[r] if inside else -1
    q0, q1, _ = _swept_columns(nx, ny, wet_lo, wet_hi, reg.need2_lo, reg.need2_hi,
                               reg.prev2_lo, reg.prev2_hi, reg.lo2, reg.hi2, r0, r1)
    _sync_work(nx, ny, q0, q1, reg.lo2, reg.hi2, sync_lo, sync_hi, fields.h, fields.hu,
               fields.hv, work.h_work, work.hu_work, work.hv_work)
    band2 = Band(q0, q1, reg.lo2, reg.hi2, rows, wet_lo, wet_hi)
    _stage(threads, grid, physics, nxt, s, fields.flag, when, band2, work.rings,
           work.transport, run)
    ok, out2, _, _, _, _, clamped2, _ = _row_sums(rows, q0, q1)
    if not ok:
        return fail
    _heun_rows(q0, q1, reg.lo2, reg.hi2, lo, hi, nx, grid.valid, grid.cell_area,
               grid.cfl_factor, grid.gamma_z, physics, cur, s, work.flag1, work.transport,
               nxt, rows, wet_lo, wet_hi, work.rings.scratch[0])
    _, _, inv_lim, moving, film, kinetic, _, fallbacks = _row_sums(rows, q0, q1)
    return (True, 0.5 * (out1 + out2), inv_lim, moving, film, kinetic, clamped1 + clamped2,
            fallbacks, q0, q1)


def _stage(threads, grid, physics, cur, nxt, flag, when, band, rings, transport, run):
    """A step of the seed's scheme (a stage at order 2) on ``band``: on Numba's threads
    where it sweeps at least ``min_parallel_cells`` cells and two blocks of
    ``min_block_rows`` rows (in the copies with threads), else on the serial sweep."""
    n_cells = 0
    for r in range(band.r0, band.r1 + 1):
        n_cells += max(band.hi[r] - band.lo[r] + 1, 0)
    n_blocks = min(8 * threads, (band.r1 - band.r0 + 1) // run.min_block_rows)
    if threads == 1 or n_cells < run.min_parallel_cells:
        n_blocks = 1
    if band.r1 < band.r0:
        return
    if PARALLEL and n_blocks > 1:
        sweep_parallel(n_blocks, grid, physics, cur, nxt, flag, when.dt, when.dt_decide, band,
                       rings, transport)
    else:
        sweep_serial(1, grid, physics, cur, nxt, flag, when.dt, when.dt_decide, band, rings,
                     transport)


#: Placeholder of the constant of the copies of :func:`_advance_grid` (whether it has the
#: parallel sweep): see :func:`grid_loop`
PARALLEL = True
#: Placeholders of the sweeps the copies of :func:`_stage` call, of the block sweep (its
#: law's copy) a copy of :func:`_sweep` calls, and of the order-2 step (:func:`_order2_step`)
#: of the copies of :func:`_advance_grid` at order 2
sweep_serial = sweep_parallel = sweep_block = order2_step = None


@njit(error_model="numpy", cache=True, inline="always")
def _first_slot():
    """The ring buffers of a serial sweep: the first set (the thread pool untouched)."""
    return 0


#: Placeholder of the set of ring buffers a block of :func:`_sweep` takes: the thread's
#: (``numba.get_thread_id``, ``0 .. get_num_threads() - 1``) in the parallel copies
thread_slot = _first_slot


def _sweep_for(kind: int, parallel: bool, scheme: str):
    """:func:`_sweep` for one law kind and scheme, compiled serial or parallel (``prange``
    runs serially without Numba's ``parallel``), each under its own name."""
    return specialize(_sweep, f"_{law_label(kind)}_{'parallel' if parallel else 'serial'}"
                      + ("" if scheme == "order1" else "_order2")
                      + ("_hancock" if scheme == "hancock" else ""),
                      parallel=parallel, sweep_block=_BLOCKS[kind, scheme],
                      thread_slot=numba.get_thread_id if parallel else _first_slot)


def _loops() -> dict:
    """:func:`avflow.numerics.loop.advance` with the grid's region per (law kind, with the
    parallel sweep, order 2): the serial copy never compiles the parallel sweep, each its
    law's cell loops alone, and the order-1 copies never the order-2 passes."""
    loops = {}
    for kind in (COULOMB, VOELLMY, ANY_LAW):
        for scheme in ("order1", "heun", "hancock"):
            order2 = scheme != "order1"
            serial = _sweep_for(kind, False, scheme)
            for parallel in (False, True):
                suffix = (f"_grid_{law_label(kind)}_{'parallel' if parallel else 'serial'}"
                          + ("_order2" if order2 else "")
                          + ("_hancock" if scheme == "hancock" else ""))
                stage = specialize(_stage, suffix, PARALLEL=parallel, sweep_serial=serial,
                                   sweep_parallel=(_sweep_for(kind, True, scheme) if parallel
                                                   else serial))
                heun = (specialize(_order2_step, suffix, _stage=stage) if scheme == "heun"
                        else None)
                names = dict(ORDER2=scheme == "heun", _stage=stage, order2_step=heun,
                             add_span=SPAN[kind])
                # inlined into the loop (compiled once there), but for the step: inlined,
                # order 2 ran 8% slower (measured, docs/performance.md)
                fns = {"start": _grid_start, "before": _grid_before, "step": _grid_step,
                       "source": _grid_source, "observe": _grid_observe,
                       "after": _grid_after, "end": _grid_end}
                given = shared_names(fns, **names)
                hooks = {f"region_{hook}": specialize(fn, suffix, **given[hook],
                                                      inline="never" if hook == "step"
                                                      else "always")
                         for hook, fn in fns.items()}
                loops[kind, parallel, scheme] = specialize(advance, suffix, **hooks)
    return loops


def grid_loop(law: int, parallel: bool, order: int = 1, scheme: str = "hancock"):
    """The time loop (:func:`_advance_grid`: its arguments, its status codes) for one
    friction law and order, with the parallel sweep (``threads`` > 1) or without: each copy
    compiles only its law's cell loops, and the serial one never the parallel sweep
    (compiling every law's, serial and parallel, made the first run slow:
    docs/performance.md)."""
    return _LOOPS[law_kind(law), bool(parallel), "order1" if order == 1 else scheme]


#: Cells a vector iteration of the row passes takes (8 doubles, AVX-512), and the shortest
#: scalar remainder worth replacing by one more vector iteration over cells added to the row
LANES = 8
MIN_REMAINDER = 3


@njit(error_model="numpy", cache=True)
def _swept_columns(nx, ny, wet_lo, wet_hi, need_lo, need_hi, prev_lo, prev_hi, lo, hi, band0,
                   band1):
    """Columns to sweep per row: the wet cells of each row and of the rows above and below,
    one column more on each side (every face of a wet cell and the cells beyond), joined with
    what the last step needed (a cell it changed is written once more, so both buffers agree
    again wherever the sweep no longer goes), widened by up to 5 columns of cells that are
    not wet where that makes the row's length a multiple of :data:`LANES`. Only the rows
    ``band0 - 1 .. band1 + 1`` around the last step's band are looked at (no wet cell lies
    beyond them). Returns the band of rows ``(r0, r1)`` and the number of cells swept."""
    r0 = ny
    r1 = -1
    cells = 0
    for r in range(max(band0 - 1, 0), min(band1 + 2, ny)):
        a = nx
        b = -1
        for q in range(max(r - 1, 0), min(r + 2, ny)):
            if wet_lo[q] <= wet_hi[q]:
                a = min(a, wet_lo[q] - 1)
                b = max(b, wet_hi[q] + 1)
        if b >= 0:
            a = max(a, 0)
            b = min(b, nx - 1)
        need_lo[r] = a
        need_hi[r] = b
        lo[r] = min(a, prev_lo[r])
        hi[r] = max(b, prev_hi[r])
        n = hi[r] - lo[r] + 1
        short = (LANES - n % LANES) % LANES
        if n > 0 and 0 < short <= LANES - MIN_REMAINDER:
            # a whole vector iteration more instead of a scalar remainder of 3 cells or
            # more (it costs a row less: docs/performance.md): the cells added are not wet
            # and touch no wet cell, so the sweep leaves them as they are
            up = min(short, nx - 1 - hi[r])
            hi[r] += up
            lo[r] = max(lo[r] - (short - up), 0)
        if lo[r] <= hi[r]:
            r0 = min(r0, r)
            r1 = max(r1, r)
            cells += hi[r] - lo[r] + 1
    return r0, r1, cells


#: Fewer cells than this in a step, or fewer than 2 blocks of MIN_BLOCK_ROWS rows: the step
#: runs on the serial sweep (waking the thread pool costs more than it saves)
MIN_PARALLEL_CELLS = 32768
MIN_BLOCK_ROWS = 16


#: The square-grid kernel's region (:mod:`avflow.numerics.loop`): what changes from step to
#: step: the rows the step sweeps (``r0 .. r1``), those it swept last (``q0 .. q1``; order 2:
#: its second stage's), and the band of rows the next step looks at
GridRegion = namedtuple("GridRegion", "r0 r1 q0 q1 band0 band1")
#: ... and what does not: the threads, the per-row results, the wet extents per row, the
#: columns the next step needs, those the last one swept (``prev``), those swept now, the
#: columns the work buffers hold, order 2's second band
GridContext = namedtuple("GridContext", "threads rows wet_lo wet_hi need_lo need_hi prev_lo "
                         "prev_hi lo hi sync_lo sync_hi reg")


@njit(error_model="numpy", cache=True)
def _columns(n, fill):
    """Per row a column index, ``fill`` at first."""
    return np.full(n, fill, dtype=np.int64)


def _grid_start(loop):
    """The region at the start of a call: the wet extents of every row. ``extra``: the
    threads; steps that sweep at least ``min_parallel_cells`` cells and two blocks of
    ``min_block_rows`` rows run on Numba's thread pool (its size set by the caller; with
    fewer sets of ring buffers than threads, every step serial), the others serially.
    (``numba.get_num_threads`` here would keep the loop out of Numba's cache: its compiled
    form calls a ctypes pointer.)"""
    grid, h, h_zero = loop.mesh, loop.fields.h, loop.physics.h_zero
    nx, ny = grid.nx, grid.ny
    threads = loop.extra if loop.extra <= loop.work.rings.emit.shape[0] else 1
    wet_lo, wet_hi = _columns(ny, nx), _columns(ny, -1)
    for r in range(ny):
        for c in range(nx):
            if h[r * nx + c] > h_zero:
                wet_lo[r] = min(wet_lo[r], c)
                wet_hi[r] = max(wet_hi[r], c)
    _with_supply(loop.supply, wet_lo, wet_hi, 0, ny - 1)
    m2 = ny if ORDER2 else 0  # order 2's second band
    reg = Region2(_columns(m2, nx), _columns(m2, -1), _columns(m2, nx), _columns(m2, -1),
                  _columns(m2, nx), _columns(m2, -1))
    # the work buffers hold h, hu, hv wherever a step may read them: per row the columns
    # sync_lo .. sync_hi, copied from (h, hu, hv) as the flow first comes near them (a copy
    # of the whole map at each call was the one cost left that grew with the map)
    ctx = GridContext(threads, np.zeros((ny, N_ROW)), wet_lo, wet_hi, _columns(ny, nx),
                      _columns(ny, -1), _columns(ny, nx), _columns(ny, -1), _columns(ny, nx),
                      _columns(ny, -1), _columns(ny, nx), _columns(ny, -1), reg)
    return GridRegion(0, -1, 0, -1, 0, ny - 1), ctx  # the first step looks at every row


def _grid_before(region, ctx, loop, cur, nxt, steps):
    """Only the swept region is computed (:func:`_swept_columns`), so a step costs the area
    the flow covers; its rows are found from the extents of the wet cells kept per row."""
    nx, ny, f, w, c = loop.mesh.nx, loop.mesh.ny, loop.fields, loop.work, ctx
    r0, r1, _ = _swept_columns(nx, ny, c.wet_lo, c.wet_hi, c.need_lo, c.need_hi, c.prev_lo,
                               c.prev_hi, c.lo, c.hi, region.band0, region.band1)
    _sync_work(nx, ny, r0, r1, c.lo, c.hi, c.sync_lo, c.sync_hi, f.h, f.hu, f.hv, w.h_work,
               w.hu_work, w.hv_work)
    return GridRegion(r0, r1, r0, r1, region.band0, region.band1)


def _grid_step(region, ctx, loop, cur, nxt, when, steps, attempt):
    """A step on the band's rows: the sweep (on threads where it pays), or order 2's two
    stages and merge."""
    r0, r1, c = region.r0, region.r1, ctx
    band = Band(r0, r1, c.lo, c.hi, c.rows, c.wet_lo, c.wet_hi)
    fallbacks = 0
    q0, q1 = r0, r1
    if ORDER2:  # Heun's two stages and merge
        (ok, outflow, inv_lim, moving, film, kinetic, clamped, fallbacks, q0,
         q1) = order2_step(c.threads, loop.mesh, loop.fields, loop.work, loop.physics,
                           loop.run, cur, nxt, when, band, c.reg, c.sync_lo, c.sync_hi)
    else:
        _stage(c.threads, loop.mesh, loop.physics, cur, nxt, loop.fields.flag, when, band,
               loop.work.rings, loop.work.transport, loop.run)
        ok, outflow, inv_lim, moving, film, kinetic, clamped, _ = _row_sums(c.rows, r0, r1)
    return (ok, outflow, dt_from_inverse(inv_lim), moving, film, clamped, kinetic, fallbacks,
            GridRegion(r0, r1, q0, q1, region.band0, region.band1))


def _grid_source(region, ctx, loop, nxt, when):
    """The source over the cells swept last (they hold every wet one), row by row."""
    g, f = loop.mesh, loop.fields
    nx = g.nx
    s_lo = ctx.reg.lo2 if ORDER2 else ctx.lo  # the columns swept last
    s_hi = ctx.reg.hi2 if ORDER2 else ctx.hi
    inv_lim = 0.0
    for r in range(region.q0, region.q1 + 1):
        gained, inv = add_span(r * nx + s_lo[r], r * nx + s_hi[r] + 1, nxt.h, nxt.hu, nxt.hv,
                               f.erodible, loop.physics, when.dt, g.cell_area, g.cfl_factor,
                               g.gamma_z)
        f.stats[ST_SOURCE] += gained
        inv_lim = max(inv_lim, inv)
    return inv_lim


def _grid_observe(region, ctx, loop, nxt, when):
    """The running maps of the cells swept last (every cell the step changed), row by row,
    from their accepted state (:mod:`avflow.numerics.observers`)."""
    nx, f, h_dry = loop.mesh.nx, loop.fields, loop.physics.h_dry
    s_lo = ctx.reg.lo2 if ORDER2 else ctx.lo
    s_hi = ctx.reg.hi2 if ORDER2 else ctx.hi
    for r in range(region.q0, region.q1 + 1):
        observe_span(r * nx + s_lo[r], r * nx + s_hi[r] + 1, nxt.h, nxt.hu, nxt.hv, f.peak_h,
                     f.peak_speed, f.arrival, f.last_moved, f.maps, when.t_new, h_dry)


@njit(error_model="numpy", cache=True)
def _with_supply(supply, wet_lo, wet_hi, band0, band1):
    """The registered sources' cells counted as wet, whether they are or not (so that every
    step sweeps them: mass lands there, numerics.supply). Returns the band of rows
    ``band0 .. band1`` widened to their rows."""
    for r in range(supply.row_lo.size):
        if supply.row_lo[r] <= supply.row_hi[r]:
            wet_lo[r] = min(wet_lo[r], supply.row_lo[r])
            wet_hi[r] = max(wet_hi[r], supply.row_hi[r])
            band0 = min(band0, r)
            band1 = max(band1, r)
    return band0, band1


def _grid_after(region, ctx, loop, nxt):
    """What the step needed is what the next one compares against (order 2: both stages'),
    and the rows it swept last are the next step's band."""
    ny, c = loop.mesh.ny, ctx
    band0, band1, r0, r1 = region.band0, region.band1, region.r0, region.r1
    for r in range(max(band0 - 1, 0), min(band1 + 2, ny)):
        c.prev_lo[r] = c.need_lo[r]
        c.prev_hi[r] = c.need_hi[r]
    if ORDER2 and r1 >= r0:  # the cells stage 2 needed changed too
        for r in range(max(r0 - 1, 0), min(r1 + 2, ny)):
            known = band0 - 1 <= r <= band1 + 1
            c.prev_lo[r] = min(c.prev_lo[r], c.reg.need2_lo[r]) if known else c.reg.need2_lo[r]
            c.prev_hi[r] = max(c.prev_hi[r], c.reg.need2_hi[r]) if known else c.reg.need2_hi[r]
    band0, band1 = _with_supply(loop.supply, c.wet_lo, c.wet_hi, region.q0,
                                region.q1)
    return GridRegion(r0, r1, region.q0, region.q1, band0, band1)


def _grid_end(region, ctx, loop, cur, t, steps):
    """The newest state back where it changed when it is in the work buffers."""
    nx, ny, f = loop.mesh.nx, loop.mesh.ny, loop.fields
    if steps % 2 == 1:
        for r in range(ny):
            # element by element: a slice assignment compiles Numba's shape check and its
            # message's formatting into the loop (1.6 s of a first run)
            for i in range(r * nx + ctx.sync_lo[r], r * nx + ctx.sync_hi[r] + 1):
                f.h[i] = cur.h[i]
                f.hu[i] = cur.hu[i]
                f.hv[i] = cur.hv[i]
    record_end(f.stats, t, steps)


@njit(error_model="numpy", cache=True)
def _sync_work(nx, ny, r0, r1, lo, hi, sync_lo, sync_hi, h, hu, hv, h_work, hu_work, hv_work):
    """Before a step that sweeps columns ``lo[r] .. hi[r]`` of rows ``r0 .. r1``: the work
    buffers take (h, hu, hv) in every cell the step may read that they do not hold yet, per
    row a hull ``sync_lo .. sync_hi`` that only grows. The step reads a row's swept cells,
    one more on each side, and the swept cells of the rows above and below (their y faces);
    the hull of row q covers the swept columns of rows q - 1 .. q + 1, one more each side.
    A cell outside every hull so far was never written, in either buffer, so ``h`` (the
    caller's) still holds its value; inside, both buffers hold the state, as the sweep
    writes each cell it leaves once more (:func:`_swept_columns`)."""
    for q in range(max(r0 - 1, 0), min(r1 + 2, ny)):
        a = nx
        b = -1
        for r in range(max(q - 1, r0), min(q + 2, r1 + 1)):
            if lo[r] <= hi[r]:
                a = min(a, lo[r] - 1)
                b = max(b, hi[r] + 1)
        if b < 0:
            continue
        a = max(a, 0)
        b = min(b, nx - 1)
        s0, s1 = sync_lo[q], sync_hi[q]
        if s0 > s1:  # nothing held yet in this row
            s0, s1 = b + 1, b
        base = q * nx
        for c in range(a, s0):  # gaps between the hull and the cells read included
            h_work[base + c] = h[base + c]
            hu_work[base + c] = hu[base + c]
            hv_work[base + c] = hv[base + c]
        for c in range(s1 + 1, b + 1):
            h_work[base + c] = h[base + c]
            hu_work[base + c] = hu[base + c]
            hv_work[base + c] = hv[base + c]
        sync_lo[q] = min(a, s0)
        sync_hi[q] = max(b, s1)


_LOOPS = _loops()  # made at import: Numba fixes a dispatcher's cache folder then
