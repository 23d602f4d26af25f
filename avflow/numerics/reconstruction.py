"""Limited linear reconstruction for the second-order kinetic scheme (``numerics.order: 2``).

The seed's scheme is first order: every face sees the cell averages. Its second-order form
(Perthame's and Audusse-Bristeau's kinetic schemes, cited in the seed's section 3) applies
the same kinetic flux (eqs. 38-40) to the thickness and velocity *reconstructed* at each face
from limited slopes, with a two-stage strong-stability-preserving Runge-Kutta (Heun) in time
(:func:`avflow.numerics.timeloop.time_loop`). Pure numerics: arrays and scalars only.

Limiters (``numerics.limiter``):

- ``minmod`` (default): on profiles the smaller of the two one-sided differences when they
  agree in sign, else 0; on grids and triangles the Barth-Jespersen limiter of a Green-Gauss
  gradient, its multidimensional counterpart (face values stay within the cell's and its
  neighbours' range). Robust at wet/dry fronts: a face thickness is never negative, never
  above the largest neighbouring thickness, and never above twice the cell's own (on a
  profile ``(h_L + h_R) / 2 = h`` gives that; on grids and triangles, whose face offsets are
  not exactly opposite on a curved bed and have none on the map's edge, it is enforced), so
  that with ``time.cfl <= 0.5`` no face sends more than the cell holds.
- ``mc`` (monotonized central) on profiles: ``minmod(2 a, 2 b, (a + b) / 2)``, sharper at
  smooth extrema, still monotone; on grids and triangles the same Barth-Jespersen limiter.

At a wet/dry front (a neighbour at or below the minimum flowing thickness) the velocity is
not reconstructed (slope 0): a dry neighbour's zero velocity says nothing about the flow.
Faces on the map's edge take the cell values (first order there).
"""

from __future__ import annotations

import math
from collections import namedtuple

from numba import njit, prange

from avflow.numerics.cpu import centripetal_accel, emitted_side, half_step
from avflow.numerics.vectorize import cell_law, specialize

MINMOD = 0
MC = 1
LIMITERS = {"minmod": MINMOD, "mc": MC}


@njit(error_model="numpy", cache=True, inline="always")
def limited_slope(a, b, limiter):
    """Slope from the one-sided differences a (backward) and b (forward) of one cell."""
    if a * b <= 0.0:
        return 0.0
    if limiter == MC:
        c = 0.5 * (a + b)
        m = min(abs(2.0 * a), abs(2.0 * b), abs(c))
        return math.copysign(m, a)
    return a if abs(a) < abs(b) else b


@njit(error_model="numpy", cache=True)
def reconstruct_profile(h, hu, h_zero, limiter, recon):
    """Face states of every cell of a profile: ``recon[k] = (h_L, u_L, h_R, u_R)``.

    Slopes of h and u = hu / h from the neighbours' differences (``limited_slope``); the two
    end cells and dry cells keep their averages. ``(h_L + h_R) / 2 = h``: the reconstruction
    moves no mass.
    """
    n = h.size
    for k in range(n):
        hk = h[k]
        uk = hu[k] / hk if hk > h_zero else 0.0
        sh = 0.0
        su = 0.0
        if hk > h_zero and 0 < k < n - 1:
            sh = limited_slope(hk - h[k - 1], h[k + 1] - hk, limiter)
            if h[k - 1] > h_zero and h[k + 1] > h_zero:
                su = limited_slope(uk - hu[k - 1] / h[k - 1], hu[k + 1] / h[k + 1] - uk,
                                   limiter)
        recon[k, 0] = hk - 0.5 * sh
        recon[k, 1] = uk - 0.5 * su
        recon[k, 2] = hk + 0.5 * sh
        recon[k, 3] = uk + 0.5 * su


# Columns of the per-cell work array of the face reconstruction.
_U1, _U2 = 0, 1  #: the cell's velocity in its basis
_GRAD = 2  #: 2..7: Green-Gauss gradients of h, u1, u2 (each x, y in the cell's basis)
_LO = 8  #: 8..10: smallest of h, u1, u2 over the cell and its neighbours
_HI = 11  #: 11..13: largest
_ALPHA = 14  #: 14..16: Barth-Jespersen factors of h, u1, u2
_FRONT = 17  #: 1 when a neighbour is at or below h_zero (no velocity slope)
N_WORK = 18

#: What MUSCL-Hancock's predictor reads (:data:`predict_cells`): half the step ``k``, the
#: mesh's gravity components and curvature, the friction law and its parameters, g, and the
#: cells' density of particles (what a side emits)
Predictor = namedtuple("Predictor", "k gamma_x gamma_y gamma_z curvature law params g density")
#: Whether a copy of :func:`reconstruct_cells` predicts (a constant in each copy)
PREDICT = False


@njit(error_model="numpy", cache=True)
def reconstruct_faces(face_cells, face_frame, face_length, face_offset, cell_area, h, hu, hv,
                      h_zero, active_faces, n_active, touched, n_touched, work, face_state):
    """Face states ``face_state[f, side] = (h, h u1, h u2)`` (side's basis) of the active faces.

    A sweep over the faces, each added to both cells' rows of ``work`` (n, N_WORK): the
    reference :func:`reconstruct_cells` (which the time loop runs) is held to, bit for bit.

    Green-Gauss gradients of h and of the velocity components in each cell's tangent basis
    (a neighbour's velocity turned through the face frame), limited by Barth-Jespersen, then
    evaluated at ``face_offset[f, side]``: half the way to the neighbour's centre, in that
    cell's basis (the midpoint of the dual edge on triangles). Only wet cells (h > h_zero)
    get slopes; every face of a wet cell is active, so its sums are complete.
    """
    for c in range(n_touched):
        i = touched[c]
        hi = h[i]
        for k in range(N_WORK):
            work[i, k] = 0.0
        if hi > h_zero:
            work[i, _U1] = hu[i] / hi
            work[i, _U2] = hv[i] / hi
        work[i, _LO] = work[i, _HI] = hi
        work[i, _LO + 1] = work[i, _HI + 1] = work[i, _U1]
        work[i, _LO + 2] = work[i, _HI + 2] = work[i, _U2]
        work[i, _ALPHA] = 1.0
        work[i, _ALPHA + 1] = 1.0
        work[i, _ALPHA + 2] = 1.0
    # pass 1: gradients, neighbour ranges, fronts
    for a in range(n_active):
        f = active_faces[a]
        i = face_cells[f, 0]
        j = face_cells[f, 1]
        length = face_length[f]
        for side in range(2 if j >= 0 else 1):
            c = i if side == 0 else j
            if h[c] <= h_zero:
                continue
            other = j if side == 0 else i
            nx = face_frame[f, side, 0, 0]
            ny = face_frame[f, side, 0, 1]
            if side == 1:  # the frame's normal points from i to j: outward for i only
                nx = -nx
                ny = -ny
            w = length / cell_area[c]
            hc = h[c]
            uc1 = work[c, _U1]
            uc2 = work[c, _U2]
            if other >= 0:
                ho = h[other]
                if ho > h_zero:  # its velocity, turned through the face into c's basis
                    o = 1 - side
                    v1 = hu[other] / ho
                    v2 = hv[other] / ho
                    un = v1 * face_frame[f, o, 0, 0] + v2 * face_frame[f, o, 0, 1]
                    ut = v1 * face_frame[f, o, 1, 0] + v2 * face_frame[f, o, 1, 1]
                    uo1 = un * face_frame[f, side, 0, 0] + ut * face_frame[f, side, 1, 0]
                    uo2 = un * face_frame[f, side, 0, 1] + ut * face_frame[f, side, 1, 1]
                else:
                    uo1 = uc1
                    uo2 = uc2
                    work[c, _FRONT] = 1.0
            else:  # the map's edge: zero normal gradient
                ho = hc
                uo1 = uc1
                uo2 = uc2
            # Green-Gauss sums (face value: the mean of the two sides) and the neighbours'
            # range, written out: helpers taking arrays slowed these sweeps (docs/performance.md)
            wx = w * nx
            wy = w * ny
            mid = 0.5 * (hc + ho)
            work[c, _GRAD + 0] += wx * mid
            work[c, _GRAD + 1] += wy * mid
            if ho < work[c, _LO + 0]:
                work[c, _LO + 0] = ho
            if ho > work[c, _HI + 0]:
                work[c, _HI + 0] = ho
            mid = 0.5 * (uc1 + uo1)
            work[c, _GRAD + 2] += wx * mid
            work[c, _GRAD + 3] += wy * mid
            if uo1 < work[c, _LO + 1]:
                work[c, _LO + 1] = uo1
            if uo1 > work[c, _HI + 1]:
                work[c, _HI + 1] = uo1
            mid = 0.5 * (uc2 + uo2)
            work[c, _GRAD + 4] += wx * mid
            work[c, _GRAD + 5] += wy * mid
            if uo2 < work[c, _LO + 2]:
                work[c, _LO + 2] = uo2
            if uo2 > work[c, _HI + 2]:
                work[c, _HI + 2] = uo2
    # pass 2: Barth-Jespersen factors over each cell's faces
    for a in range(n_active):
        f = active_faces[a]
        i = face_cells[f, 0]
        j = face_cells[f, 1]
        for side in range(2 if j >= 0 else 1):
            c = i if side == 0 else j
            if h[c] <= h_zero:
                continue
            rx = face_offset[f, side, 0]
            ry = face_offset[f, side, 1]
            for v in range(3):
                d = work[c, _GRAD + 2 * v] * rx + work[c, _GRAD + 2 * v + 1] * ry
                centre = h[c] if v == 0 else work[c, v - 1]  # _U1, _U2
                if d > 0.0:
                    ratio = (work[c, _HI + v] - centre) / d
                    if v == 0:  # a face thickness at most 2 h: no more than the cell holds
                        ratio = min(ratio, centre / d)
                elif d < 0.0:
                    ratio = (work[c, _LO + v] - centre) / d
                else:
                    continue
                if ratio < work[c, _ALPHA + v]:
                    work[c, _ALPHA + v] = ratio
    # pass 3: the face states
    for a in range(n_active):
        f = active_faces[a]
        i = face_cells[f, 0]
        j = face_cells[f, 1]
        for side in range(2):
            c = i if side == 0 else j
            if c < 0:
                continue
            hc = h[c]
            if hc <= h_zero:
                face_state[f, side, 0] = hc
                face_state[f, side, 1] = 0.0
                face_state[f, side, 2] = 0.0
                continue
            rx = face_offset[f, side, 0]
            ry = face_offset[f, side, 1]
            hf = hc + work[c, _ALPHA] * (work[c, _GRAD] * rx + work[c, _GRAD + 1] * ry)
            hf = max(hf, 0.0)
            u1 = work[c, _U1]
            u2 = work[c, _U2]
            if work[c, _FRONT] == 0.0:  # no velocity slope towards a dry neighbour
                u1 += work[c, _ALPHA + 1] * (work[c, _GRAD + 2] * rx + work[c, _GRAD + 3] * ry)
                u2 += work[c, _ALPHA + 2] * (work[c, _GRAD + 4] * rx + work[c, _GRAD + 5] * ry)
            face_state[f, side, 0] = hf
            face_state[f, side, 1] = hf * u1
            face_state[f, side, 2] = hf * u2


@njit(error_model="numpy", cache=True, _nrt=False)  # no reference counts: see step_faces
def reconstruct_cells(face_cells, face_frame, face_length, face_offset, cell_area, h, hu, hv,
                      h_zero, cell_face_ptr, cell_face_idx, touched, n_touched, velocity,
                      face_state, predictor):
    """:func:`reconstruct_faces`' face states, cell after cell: the same bits (what the
    order-2 time loop runs), faster than the sweep over faces (docs/performance.md).

    Each touched cell sweeps its own faces (``cell_face_idx[cell_face_ptr[c]:
    cell_face_ptr[c + 1]]``, in index order, as :func:`avflow.numerics.kernels.cell_faces`
    lists them) three times: its Green-Gauss sums and neighbours' range, its
    Barth-Jespersen factors, its side of each face's state. Its sums stay in registers,
    where the sweep over faces added each face to two cells' rows of a work array in turn;
    each cell adds its faces in the same order, so every sum is the same. ``velocity``
    (n, 2): work, the touched cells' velocities (``hu / h``, 0 when dry). A dry cell writes
    ``(h, 0, 0)`` on its side of all its faces, active or not. Written apart from
    reconstruct_faces on purpose: a helper they shared would hide its faults from the test
    that holds one to the other.

    ``predictor`` (:data:`Predictor`) is read only by the copy :data:`predict_cells`
    (MUSCL-Hancock): each wet cell away from a front moves its centre state half a step on
    (:func:`~avflow.numerics.physics.half_step`, with its limited slopes) before its sides
    are formed, so that one flux sweep is second order in time; it writes what each side
    emits (``face_state[f, side, 0:7]``, :func:`~avflow.numerics.physics.emitted_side`),
    which the flux sweep then reads as it is.
    """
    for c in prange(n_touched):
        i = touched[c]
        hi = h[i]
        u1 = 0.0
        u2 = 0.0
        if hi > h_zero:
            u1 = hu[i] / hi
            u2 = hv[i] / hi
        velocity[i, 0] = u1
        velocity[i, 1] = u2
    for c in prange(n_touched):  # each cell writes its own side of its faces alone
        i = touched[c]
        hc = h[i]
        first = cell_face_ptr[i]
        last = cell_face_ptr[i + 1]
        if hc <= h_zero:
            for p in range(first, last):
                f = cell_face_idx[p]
                side = 0 if face_cells[f, 0] == i else 1
                face_state[f, side, 0] = hc
                face_state[f, side, 1] = 0.0
                face_state[f, side, 2] = 0.0
            continue
        uc1 = velocity[i, 0]
        uc2 = velocity[i, 1]
        w_area = cell_area[i]
        g0 = g1 = g2 = g3 = g4 = g5 = 0.0
        lo0 = hi0 = hc
        lo1 = hi1 = uc1
        lo2 = hi2 = uc2
        front = False
        # 1: gradients (the mean of both sides on each face), neighbours' range, fronts
        for p in range(first, last):
            f = cell_face_idx[p]
            side = 0 if face_cells[f, 0] == i else 1
            other = face_cells[f, 1 - side]
            nx = face_frame[f, side, 0, 0]
            ny = face_frame[f, side, 0, 1]
            if side == 1:  # the frame's normal points from i to j: outward for i only
                nx = -nx
                ny = -ny
            w = face_length[f] / w_area
            if other >= 0:
                ho = h[other]
                if ho > h_zero:  # its velocity, turned through the face into this basis
                    o = 1 - side
                    v1 = velocity[other, 0]
                    v2 = velocity[other, 1]
                    un = v1 * face_frame[f, o, 0, 0] + v2 * face_frame[f, o, 0, 1]
                    ut = v1 * face_frame[f, o, 1, 0] + v2 * face_frame[f, o, 1, 1]
                    uo1 = un * face_frame[f, side, 0, 0] + ut * face_frame[f, side, 1, 0]
                    uo2 = un * face_frame[f, side, 0, 1] + ut * face_frame[f, side, 1, 1]
                else:
                    uo1 = uc1
                    uo2 = uc2
                    front = True
            else:  # the map's edge: zero normal gradient
                ho = hc
                uo1 = uc1
                uo2 = uc2
            wx = w * nx
            wy = w * ny
            mid = 0.5 * (hc + ho)
            g0 += wx * mid
            g1 += wy * mid
            lo0 = ho if ho < lo0 else lo0
            hi0 = ho if ho > hi0 else hi0
            mid = 0.5 * (uc1 + uo1)
            g2 += wx * mid
            g3 += wy * mid
            lo1 = uo1 if uo1 < lo1 else lo1
            hi1 = uo1 if uo1 > hi1 else hi1
            mid = 0.5 * (uc2 + uo2)
            g4 += wx * mid
            g5 += wy * mid
            lo2 = uo2 if uo2 < lo2 else lo2
            hi2 = uo2 if uo2 > hi2 else hi2
        # 2: Barth-Jespersen factors over the faces
        a0 = a1 = a2 = 1.0
        for p in range(first, last):
            f = cell_face_idx[p]
            side = 0 if face_cells[f, 0] == i else 1
            rx = face_offset[f, side, 0]
            ry = face_offset[f, side, 1]
            a0 = _bj_factor(a0, g0 * rx + g1 * ry, hc, lo0, hi0, True)
            a1 = _bj_factor(a1, g2 * rx + g3 * ry, uc1, lo1, hi1, False)
            a2 = _bj_factor(a2, g4 * rx + g5 * ry, uc2, lo2, hi2, False)
        # what MUSCL-Hancock's sides emit reads these (Heun's copy loads nothing)
        g_normal = predictor.g * predictor.gamma_z[i] if PREDICT else 0.0
        dens = predictor.density[i] if PREDICT else 0.0
        if PREDICT and not front:  # MUSCL-Hancock: the sides of the state half a step on
            pr = predictor
            params = pr.params
            pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(
                pr.law, params, i, params[0, 0], params[0, 1], params[0, 2], params[0, 3],
                params[0, 4], params[0, 5], params[0, 6], params[0, 7])
            hc, uc1, uc2 = half_step(hc, uc1, uc2, a0 * g0, a0 * g1, a1 * g2, a1 * g3, a2 * g4,
                                     a2 * g5, pr.k, pr.gamma_x[i], pr.gamma_y[i],
                                     pr.gamma_z[i],
                                     centripetal_accel(pr.curvature, i, h[i], hu[i], hv[i]),
                                     pr.law, pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7, pr.g)
        # 3: this cell's side of each face
        for p in range(first, last):
            f = cell_face_idx[p]
            side = 0 if face_cells[f, 0] == i else 1
            rx = face_offset[f, side, 0]
            ry = face_offset[f, side, 1]
            hf = hc + a0 * (g0 * rx + g1 * ry)
            hf = max(hf, 0.0)
            u1 = uc1
            u2 = uc2
            if not front:  # no velocity slope towards a dry neighbour
                u1 += a1 * (g2 * rx + g3 * ry)
                u2 += a2 * (g4 * rx + g5 * ry)
            if PREDICT:  # what the side emits (kernels.reconstructed_sides' direct form)
                (face_state[f, side, 0], face_state[f, side, 1], face_state[f, side, 2],
                 face_state[f, side, 3], face_state[f, side, 4], face_state[f, side, 5],
                 face_state[f, side, 6]) = emitted_side(hf, u1, u2, g_normal, dens)
            else:
                face_state[f, side, 0] = hf
                face_state[f, side, 1] = hf * u1
                face_state[f, side, 2] = hf * u2


@njit(error_model="numpy", cache=True, inline="always")
def _bj_factor(alpha, d, centre, lo, hi, thickness):
    """Barth-Jespersen: ``alpha`` lowered so that ``centre + alpha d`` stays within
    ``[lo, hi]`` (and, for a thickness, at most twice ``centre``: no face sends more than
    the cell holds)."""
    if d > 0.0:
        ratio = (hi - centre) / d
        if thickness:
            ratio = min(ratio, centre / d)
    elif d < 0.0:
        ratio = (lo - centre) / d
    else:
        return alpha
    return ratio if ratio < alpha else alpha


#: :func:`reconstruct_cells` on Numba's threads (each cell writes its own sides of its faces
#: and reads only the state: no races, the same bits on any number of threads)
reconstruct_cells_parallel = specialize(reconstruct_cells.py_func, "_parallel", parallel=True,
                                        nrt=False)
#: ... and MUSCL-Hancock's copies, serial and on threads: the sides of the state predicted
#: half a step on (``predictor``)
predict_cells = specialize(reconstruct_cells.py_func, "_predicted", nrt=False, PREDICT=True)
predict_cells_parallel = specialize(reconstruct_cells.py_func, "_predicted_parallel",
                                    parallel=True, nrt=False, PREDICT=True)
