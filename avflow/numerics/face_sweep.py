"""The face kernel's order-1 step with its cell passes vectorised: any mesh (triangles).

The same step as :func:`avflow.numerics.kernels.step_faces` at order 1 (seed eqs. 26-56:
rectangular fluxes, trial momentum and Coulomb threshold, Dirac faces, projection,
curvature and film rules, walls, open sides), bit for bit: thickness, discharge, flags
and the step's sums. ``step_faces`` stays as the reference (and runs order 2).

The active lists are sorted, so they are runs of consecutive indices (on an all-wet mesh,
one run). Each pass over cells is one loop without jumps over a run, which LLVM vectorises
(:mod:`avflow.numerics.vectorize` says what that takes), as the square-grid kernel's rows:

1. per touched cell, what it emits through its faces, in lines (the square-grid kernel's
   :func:`~avflow.numerics.square_grid.emitted_cell`); its sums start at 0;
2. per active face, the rectangular flux, added to both cells' sums in face order (scalar,
   :func:`_face_fluxes`); only the mass flux is kept;
3. per touched cell, the trial momentum (eq. 47) and the Coulomb flag (eq. 49);
4. per active face with a side at zero temperature, in face order, the mass of the faces
   that are not Dirac (eqs. 51-53) and what a dry side takes back through a Dirac face
   (:func:`_add_masses`; a flowing cell has no Dirac face, so its sum of pass 2 stands,
   and a step whose touched cells all flow skips this pass: pass 2 summed its outflow);
5. per touched cell, the new thickness, the projection of eq. 50 and the step's sums,
   added cell after cell in the lists' order (step_faces' order).

The vector cell passes cost less than step_faces' cell loops; the face pass, scalar and
bound by its arithmetic, is step_faces' own, and is most of the step (the figures:
docs/performance.md, "Measurements moved out of the code").

On threads (:func:`_step_threads`, below) the same passes run on pieces: the cell passes
on pieces of the runs, the two face passes on one piece of the active faces a thread, each
scattering into the cells of its own piece. The few cells whose faces lie in two pieces
(near a cut, or along a boundary, whose faces a mesh numbers last) take nothing from the
face passes and sum their listed faces afterwards, in index order: the order in which the
scatter meets them, so the same bits on any number of threads.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit, prange

from avflow.numerics.cpu import (DRY, FACE_INNER, FACE_OPEN, FACE_WALL, FLOWING, carries,
                                 cell_moves, cell_update, dirac_face, dt_from_inverse,
                                 face_flux, observe_cell, outflow_volume, step_terms,
                                 take_back, trial_momentum)
from avflow.terrain.mesh import OUTFLOW, WALL
from avflow.numerics.square_grid import (E_C, E_H, E_K3, E_KH, E_S, E_SPEED, E_U1, E_U2,
                                         N_EMIT, emitted_cell)
from avflow.numerics.vectorize import (cell_law, friction_law, law_copies, law_label, noalias,
                                       specialize)

# Lines of the per-cell work array (N_CELL_LINES, n): what the step's sums need
C_INV, C_KIN, C_MOV, C_FILM = range(4)
N_CELL_LINES = 4


#: What the sweep reads of a mesh besides its frames and lengths (:func:`geometry`)
SweepGeometry = namedtuple("SweepGeometry", "pairs inv_area curvature face_ptr face_idx "
                           "open_faces span near_edge edge_cells")
#: What a solver keeps of the sweep: its geometry and its work arrays
Sweep = namedtuple("Sweep", "geometry work")
#: The sweep's work arrays (:func:`work`)
SweepWork = namedtuple("SweepWork", "emit mass per_cell runs side pieces cut face_mark "
                       "shared_mark shared_cells cold")


def geometry(mesh, inv_area, curvature, cell_face_ptr, cell_face_idx, threads=False):
    """What the sweep reads of a mesh besides its frames and lengths, built once (a tuple,
    as the time loop takes it): the faces' cells as int32 (half the bytes a face reads),
    ``1 / A`` and the curvature as three lines, each cell's faces in index order
    (:func:`~avflow.numerics.kernels.cell_faces`, the solver's), the open faces in index
    order, for the step on threads (``threads``; empty otherwise) the largest span of the
    face indices of a cell without a boundary face (one number in an array: 3 rows of
    nodes on triangles made from a raster, half the faces on a square grid, whose x faces
    come before its y faces), per face whether it touches a cell with a boundary face, and
    those cells."""
    fc = mesh.face_cells
    open_faces = np.flatnonzero(fc[:, 1] == OUTFLOW).astype(np.int64)
    # the cells with a boundary face (a mesh numbers those faces last, far from the cell's
    # others), the faces that touch one, and the largest span of the face indices of the
    # other cells (a cell's faces are in index order)
    edge = np.zeros(mesh.n_cells, dtype=bool)
    edge[fc[fc[:, 1] < 0, 0]] = True
    inner = ~edge & (cell_face_ptr[1:] > cell_face_ptr[:-1])  # (a cell without faces: none)
    spans = (cell_face_idx[cell_face_ptr[1:][inner] - 1]
             - cell_face_idx[cell_face_ptr[:-1][inner]])
    span = int(np.max(spans, initial=0))
    near_edge = edge[fc[:, 0]] | (fc[:, 1] >= 0) & edge[np.maximum(fc[:, 1], 0)]
    if not threads:
        near_edge, edge = near_edge[:0], edge[:0]
    return SweepGeometry(fc.astype(np.int32), np.ascontiguousarray(inv_area),
                         np.ascontiguousarray(np.asarray(curvature).T), cell_face_ptr,
                         cell_face_idx, open_faces, np.array([span], dtype=np.int64),
                         near_edge.astype(np.uint8), np.flatnonzero(edge).astype(np.int64))


# How a step's lists are cut (the work arrays' ``cut``, :func:`work`): the pieces' least
# size and most number, the steps that listed anew so far (a listed face and a shared cell
# carry the last one's number), the pieces of the faces; then what the last step made of
# its lists, kept for a next step on the same lists (the time loop's ``same_wet``): the
# runs of cells and of faces, the pieces of each, the shared cells, and whether the pieces
# and the shared cells were made (by the step on threads) since the lists last changed
(CUT_MIN_PIECE, CUT_MAX_PIECES, CUT_MARK, CUT_FACE_PIECES, CUT_RUNS, CUT_FACE_RUNS,
 CUT_CELL_PIECES, CUT_FACE_PIECES_MADE, CUT_SHARED, CUT_PIECES_KEPT, CUT_COLD_GATHER,
 N_CUT) = range(12)

#: The Dirac pass gathers over the faces of each cell at zero temperature (under the
#: threshold or dry) while there are fewer than one such cell for this many active faces;
#: with more, it sweeps every active face (a cell's gather costs what sweeping a dozen-odd
#: faces does: docs/performance.md)
COLD_GATHER = 32


def work(n_cells: int, n_faces: int, threads: int = 1, min_piece: int | None = None,
         max_pieces: int | None = None, face_pieces: int | None = None,
         cold_gather: int | None = None):
    """The sweep's work arrays (a tuple), allocated once per solver: the emitted lines, the
    mass flux of each face, the per-cell lines, the runs of both lists; for the step on
    ``threads`` > 1 threads (empty otherwise), the momentum each face brings to its sides
    (four lines: x, y to its first cell, x, y to its second; written where a side is
    shared), the pieces of both lists (:func:`pieces_of`), how they are cut and what the
    last step made of its lists (:data:`CUT_MIN_PIECE` ... :data:`CUT_PIECES_KEPT`; by
    default pieces of :data:`MIN_PIECE` or more, at most :data:`MAX_PIECES`, and as many
    pieces of the faces as threads; tests cut small meshes finer), per face the step that
    listed it last, per cell the step that found it shared last, the list of the shared
    cells, and that of the cells at zero temperature (the Dirac pass in gather form, with
    ``cold_gather``, default :data:`COLD_GATHER`; 0: always, a huge number: never)."""
    on_threads = threads > 1
    m, f = (n_cells, n_faces) if on_threads else (0, 0)
    cut = np.zeros(N_CUT, dtype=np.int64)
    cut[CUT_MIN_PIECE] = min_piece or MIN_PIECE
    cut[CUT_MAX_PIECES] = max_pieces or MAX_PIECES
    cut[CUT_FACE_PIECES] = face_pieces or threads
    cut[CUT_COLD_GATHER] = COLD_GATHER if cold_gather is None else cold_gather
    n_pieces = int(cut[CUT_MAX_PIECES])
    return SweepWork(
        np.zeros((N_EMIT, n_cells)), np.zeros(n_faces), np.zeros((N_CELL_LINES, n_cells)),
        np.empty(2 * (n_cells + n_faces) + 4, dtype=np.int64), np.zeros((4, f)),
        np.empty(2 * (m + f) + 8 * n_pieces + 8 if on_threads else 0, dtype=np.int64),
        cut, np.full(f, -1, dtype=np.int64), np.full(m, -1, dtype=np.int64),
        np.empty(m, dtype=np.int64), np.empty(n_cells, dtype=np.int64))


def unused():
    """The same tuples, empty: for the time loops that do not run this sweep (same types,
    so one compiled loop serves both)."""
    return Sweep(
        SweepGeometry(np.empty((0, 2), dtype=np.int32), np.empty(0), np.empty((3, 0)),
                      np.zeros(1, dtype=np.int64), np.empty(0, dtype=np.int64),
                      np.empty(0, dtype=np.int64), np.zeros(1, dtype=np.int64),
                      np.empty(0, dtype=np.uint8), np.empty(0, dtype=np.int64)),
        SweepWork(np.empty((N_EMIT, 0)), np.empty(0), np.empty((N_CELL_LINES, 0)),
                  np.empty(0, dtype=np.int64), np.empty((4, 0)), np.empty(0, dtype=np.int64),
                  np.zeros(N_CUT, dtype=np.int64), np.empty(0, dtype=np.int64),
                  np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64),
                  np.empty(0, dtype=np.int64)))


@njit(error_model="numpy", cache=True)
def runs_of(items, count, runs):
    """The sorted list ``items[:count]`` as runs of consecutive indices: ``runs[2r]`` the
    first, ``runs[2r + 1]`` the last of run r. Returns the number of runs."""
    if count == 0:
        return 0
    r = 0
    runs[0] = items[0]
    for c in range(1, count):
        if items[c] != items[c - 1] + 1:
            runs[2 * r + 1] = items[c - 1]
            r += 1
            runs[2 * r] = items[c]
    runs[2 * r + 1] = items[count - 1]
    return r + 1


@njit(error_model="numpy", cache=True, inline="always")
def _face_flux(f, i, j, face_frame, face_length, e_h, e_u1, e_u2, e_c, e_s, e_kh, e_k3):
    """:func:`~avflow.numerics.physics.face_flux` of face f between cells i and j (a wall or
    an open side when ``j < 0``), from what the cells emit (the lines of
    :func:`_emit_cells`) and the face's frames: ``(L F_h, momentum to i (x, y), momentum to
    j (x, y))``."""
    if j >= 0:  # the kind a constant in each call: the inner faces' path has no branch on it
        return face_flux(FACE_INNER, e_h[i], e_u1[i], e_u2[i], e_c[i], e_s[i], e_kh[i],
                         e_k3[i], e_h[j], e_u1[j], e_u2[j], e_c[j], e_s[j], e_kh[j], e_k3[j],
                         face_frame[f, 0, 0, 0], face_frame[f, 0, 0, 1], face_frame[f, 0, 1, 0],
                         face_frame[f, 0, 1, 1], face_frame[f, 1, 0, 0], face_frame[f, 1, 0, 1],
                         face_frame[f, 1, 1, 0], face_frame[f, 1, 1, 1], face_length[f])
    return face_flux(FACE_WALL if j == WALL else FACE_OPEN, e_h[i], e_u1[i], e_u2[i], e_c[i],
                     e_s[i], e_kh[i], e_k3[i], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                     face_frame[f, 0, 0, 0], face_frame[f, 0, 0, 1], face_frame[f, 0, 1, 0],
                     face_frame[f, 0, 1, 1], 0.0, 0.0, 0.0, 0.0, face_length[f])


def _face_fluxes(runs, r0, n_runs, pairs, face_frame, face_length, emit, mass, h_sum, x_sum,
                 y_sum, transport, shared, mark, safe_lo, safe_hi, near_edge, side, marks, dt):
    """The faces of runs ``r0 .. r0 + n_runs - 1`` (:func:`runs_of`): the flux of each
    added to its cells' sums in face order (the scatter of step_faces sweep 1a: the same
    sums, bit for bit), and the largest ``|F_h| / L`` through each cell's faces. Only the
    mass flux is kept (``mass[f]``): the few Dirac faces with a dry side recompute their
    momentum in :func:`_add_masses`. Returns the volume that leaves through the open faces
    if every cell flows (:func:`_add_masses`' sum, in its order: a step whose cells all flow
    has no Dirac face, and skips that pass). Scalar, bound by its arithmetic: LLVM keeps a
    loop that gathers the cells' values itself scalar, and the vector forms tried (the
    cells' values copied into lines per block of faces; each face's fluxes written into
    lines, the sums then taken per cell) were no faster (docs/performance.md).

    On threads (:func:`_step_threads`, each thread on its own piece of the faces; the copy
    ``FACE_FLUXES[True]``): the cells whose faces lie in more than one piece have
    ``shared[i] == mark``, the step's number. Nothing is added to those here: a face with
    a shared side keeps the momentum it brings to each side in ``side`` (four lines: x, y
    to its first cell, x, y to its second) and gets ``marks[f] = mark`` (it is listed in
    this step), and :func:`_shared_sums` adds them
    up in face order afterwards. Only the faces outside ``safe_lo .. safe_hi`` (those
    within a cell's span of a cut) and those ``near_edge`` (touching a cell with a
    boundary face) can touch a shared cell: the others are not tested."""
    e_h, e_u1, e_u2, e_c = emit[E_H], emit[E_U1], emit[E_U2], emit[E_C]
    e_s, e_kh, e_k3 = emit[E_S], emit[E_KH], emit[E_K3]
    some = SHARED  # a constant in each copy (FACE_FLUXES): the serial one does not test
    outflow = 0.0
    for r in range(r0, r0 + n_runs):
        for f in range(runs[2 * r], runs[2 * r + 1] + 1):
            i = pairs[f, 0]
            j = pairs[f, 1]
            fh, qix, qiy, qjx, qjy = _face_flux(f, i, j, face_frame, face_length, e_h, e_u1, e_u2,
                                                e_c, e_s, e_kh, e_k3)
            mass[f] = fh
            unit = abs(fh) / face_length[f]
            own_i = True
            own_j = j >= 0
            if j == OUTFLOW:
                outflow += outflow_volume(fh, dt)
            if some:
                if f < safe_lo or f > safe_hi or near_edge[f] != 0:  # a side may be shared
                    own_i = shared[i] != mark
                    own_j = own_j and shared[j] != mark
                if not own_i or (j >= 0 and not own_j):
                    marks[f] = mark
                    side[0, f] = qix
                    side[1, f] = qiy
                    side[2, f] = qjx
                    side[3, f] = qjy
            if own_i:
                h_sum[i] -= fh
                x_sum[i] -= qix
                y_sum[i] -= qiy
                transport[i] = max(transport[i], unit)
            if own_j:
                h_sum[j] += fh
                x_sum[j] += qjx
                y_sum[j] += qjy
                transport[j] = max(transport[j], unit)
    return outflow


def _add_masses(runs, r0, n_runs, pairs, face_frame, face_length, emit, mass, flag, dirac, dt,
                h_sum, x_sum, y_sum, shared, mark, safe_lo, safe_hi, near_edge):
    """The faces of runs ``r0 ..`` once the flags are known, in face order (step_faces
    sweep 2a), for the cells at zero temperature (under the threshold or dry): the mass of
    the faces that keep the rectangular density; a Dirac face (both cells at zero
    temperature, eqs. 51-53) carries none, and a dry side takes back the momentum it had
    brought to the trial's sum (recomputed: the same operations on the same values, so the
    same bits). A flowing cell has no Dirac face: its sums from :func:`_face_fluxes` are
    already these (the same faces in the same order), and a face between two flowing cells
    is passed over. The transport is left as it is: it decides whether a cell that moves
    counts as moving, and a cell at zero temperature either ends at rest (q = 0 under the
    threshold, eq. 56) or just set off (dry at time n: it counts whatever its faces
    carried). Returns the volume that left through the open faces. ``shared``: as
    :func:`_face_fluxes` (``ADD_MASSES[True]``, on threads: nothing is added to those
    cells here, and the outflow returned is not the step's, which is summed in face order
    afterwards)."""
    e_h, e_u1, e_u2, e_c = emit[E_H], emit[E_U1], emit[E_U2], emit[E_C]
    e_s, e_kh, e_k3 = emit[E_S], emit[E_KH], emit[E_K3]
    some = SHARED
    outflow = 0.0
    for r in range(r0, r0 + n_runs):
        for f in range(runs[2 * r], runs[2 * r + 1] + 1):
            i = pairs[f, 0]
            j = pairs[f, 1]
            fl_i = flag[i]
            fl_j = flag[j] if j >= 0 else fl_i
            open_side = j == OUTFLOW
            if fl_i == FLOWING and fl_j == FLOWING and not open_side:
                continue
            own_i = True
            own_j = j >= 0
            if some and (f < safe_lo or f > safe_hi or near_edge[f] != 0):
                own_i = shared[i] != mark
                own_j = own_j and shared[j] != mark
            d = dirac_face(dirac, fl_i, fl_j)
            if d:
                if (fl_i == DRY and own_i) or (own_j and fl_j == DRY):
                    _, qix, qiy, qjx, qjy = _face_flux(f, i, j, face_frame, face_length, e_h,
                                                       e_u1, e_u2, e_c, e_s, e_kh, e_k3)
                    if fl_i == DRY and own_i:
                        x_sum[i] = take_back(x_sum[i], -qix, d)
                        y_sum[i] = take_back(y_sum[i], -qiy, d)
                    if own_j and fl_j == DRY:
                        x_sum[j] = take_back(x_sum[j], qjx, d)
                        y_sum[j] = take_back(y_sum[j], qjy, d)
                continue
            fh = mass[f]
            if fl_i != FLOWING and own_i:
                h_sum[i] -= fh
            if j >= 0:
                if fl_j != FLOWING and own_j:
                    h_sum[j] += fh
            elif open_side:
                outflow += outflow_volume(fh, dt)
    return outflow


@noalias
@njit(error_model="numpy", cache=True)
def _emit_cells(runs, n_runs, h, hu, hv, gamma_z, density, h_zero, g, o_h, o_u1, o_u2, o_c,
                o_s, o_kh, o_k3, o_speed, h_sum, x_sum, y_sum, transport):
    """The cells of the runs: what each emits through its faces (the square-grid kernel's
    :func:`~avflow.numerics.square_grid.emitted_cell`, one line per value); its sums and
    transport start at 0."""
    h_wet = max(h_zero, 0.0)  # wet: h > h_zero and h > 0, as physics.emitted_state
    for r in range(n_runs):
        a = max(runs[2 * r], 0)
        for k in range(runs[2 * r + 1] + 1 - a):
            i = a + k
            (o_h[i], o_u1[i], o_u2[i], o_c[i], o_s[i], o_kh[i], o_k3[i],
             o_speed[i]) = emitted_cell(h[i], hu[i], hv[i], g * gamma_z[i], density[i], h_wet)
            h_sum[i] = 0.0
            x_sum[i] = 0.0
            y_sum[i] = 0.0
            transport[i] = 0.0


#: Placeholder of the copies' constant: True in the copies for the step on threads
SHARED = False
#: :func:`_face_fluxes` and :func:`_add_masses` serially (False) and for the step on
#: threads (True, where cells are shared)
FACE_FLUXES = {shared: specialize(_face_fluxes, "_shared" if shared else "_serial",
                                  SHARED=shared) for shared in (False, True)}
ADD_MASSES = {shared: specialize(_add_masses, "_shared" if shared else "_serial",
                                 SHARED=shared) for shared in (False, True)}


def _trial_cells(runs, n_runs, inv_area, e_u1, e_u2, e_speed, k11, k12, k22, h, hu, hv,
                 gamma_x, gamma_y, gamma_z, law, params, g, h_zero, dt, dt_decide, flag,
                 h_sum, x_sum, y_sum):
    """The cells of the runs (:func:`runs_of`): the trial momentum of eq. 47 and the flag of
    eq. 49 from their sums (step_faces sweep 1b), into ``x_sum, y_sum`` (a dry cell keeps
    its momentum sum); the mass sum of a cell at zero temperature starts again at 0 for
    :func:`_add_masses`. Returns how many are at zero temperature (under the threshold or
    dry): with none, no face is Dirac and that pass has nothing to do."""
    lw = friction_law(law)  # a constant in the copies of by_law
    p0, p1, p2, p3 = params[0, 0], params[0, 1], params[0, 2], params[0, 3]
    p4, p5, p6, p7 = params[0, 4], params[0, 5], params[0, 6], params[0, 7]
    n_cold = 0
    for r in range(n_runs):
        a = max(runs[2 * r], 0)  # (no wraparound of a negative index: the loop vectorises)
        for k in range(runs[2 * r + 1] + 1 - a):
            i = a + k
            ia = inv_area[i]
            mh, mx, my = h_sum[i], x_sum[i], y_sum[i]
            u1 = e_u1[i]
            u2 = e_u2[i]
            centripetal = k11[i] * u1 * u1 + 2.0 * k12[i] * u1 * u2 + k22[i] * u2 * u2
            pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(lw, params, i, p0, p1, p2, p3,
                                                              p4, p5, p6, p7)
            qx, qy, fi = trial_momentum(h[i], h_zero, e_speed[i], hu[i], hv[i], mh * ia, mx * ia,
                                         my * ia, dt, dt_decide, gamma_x[i], gamma_y[i],
                                         gamma_z[i], centripetal, lw, pc0, pc1, pc2, pc3,
                                         pc4, pc5, pc6, pc7, g, False)
            dry = h[i] <= h_zero
            flowing = (fi == FLOWING) & (not dry)
            x_sum[i] = mx if dry else qx
            y_sum[i] = my if dry else qy
            flag[i] = DRY if dry else fi
            h_sum[i] = mh if flowing else 0.0  # summed again without its Dirac faces
            n_cold += 0 if flowing else 1
    return n_cold


def _final_cells(runs, n_runs, cell_area, cfl_factor, e_u1, e_u2, e_speed, k11, k12, k22, h,
                 gamma_x, gamma_y, gamma_z, flag, law, params, g, h_dry, h_zero, dt, h_new,
                 hu_new, hv_new, transport, t_inv, t_kin, t_mov, t_film):
    """The cells of the runs: the new thickness from the mass sum in ``h_new``, eq. 50's
    projection of the trial discharge in ``hu_new, hv_new`` and what the step's sums need
    (step_faces sweep 2b), every write a select. Returns ``(cells below 0, clamped, cells
    that became wet or dry)``: a cell below 0 makes the step be redone, whatever it wrote;
    with none wet or dry anew, the wet cells and the lists hold."""
    lw = friction_law(law)
    p0, p1, p2, p3 = params[0, 0], params[0, 1], params[0, 2], params[0, 3]
    p4, p5, p6, p7 = params[0, 4], params[0, 5], params[0, 6], params[0, 7]
    n_bad = 0
    clamped = 0
    flips = 0
    for r in range(n_runs):
        a = max(runs[2 * r], 0)  # (no wraparound of a negative index: the loop vectorises)
        for k in range(runs[2 * r + 1] + 1 - a):
            i = a + k
            area = cell_area[i]
            h_old = h[i]
            fi = flag[i]
            speed_n = e_speed[i]
            u1 = e_u1[i]
            u2 = e_u2[i]
            centripetal = k11[i] * u1 * u1 + 2.0 * k12[i] * u1 * u2 + k22[i] * u2 * u2
            gz = gamma_z[i]
            pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(lw, params, i, p0, p1, p2, p3,
                                                              p4, p5, p6, p7)
            hn, qx, qy, cl = cell_update(fi == DRY, fi, h_old, h_new[i], hu_new[i], hv_new[i],
                                         area, dt, gamma_x[i], gamma_y[i], gz, centripetal,
                                         speed_n, lw, pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7, g,
                                         h_zero, False, False)
            bad = hn < 0.0  # (as step_faces: a NaN goes on)
            n_bad += 1 if bad else 0
            flips += 1 if (h_old > h_zero) != (hn > h_zero) else 0
            speed, inv_i = observe_cell(hn, math.sqrt(qx * qx + qy * qy), cfl_factor[i], gz, g)
            h_new[i] = hn
            hu_new[i] = qx
            hv_new[i] = qy
            clamped += cl
            # the moving rule with the largest |F_h| / L of the faces that carried mass
            moves = cell_moves(speed, speed_n, carries(transport[i], hn, speed_n, 1.0))
            t_inv[i] = inv_i
            t_kin[i], t_mov[i], t_film[i] = step_terms(hn, area, speed, moves, h_dry)
    return n_bad, clamped, flips


@njit(error_model="numpy", cache=True, inline="always")
def _step_sums(runs, n_runs, per_cell):
    """The step's sums from the per-cell lines of the final update, cell after cell in the
    lists' order (step_faces' order): ``(dt_limit, moving, film, kinetic)``."""
    t_inv, t_kin = per_cell[C_INV], per_cell[C_KIN]
    t_mov, t_film = per_cell[C_MOV], per_cell[C_FILM]
    inv_lim = 0.0
    moving = 0.0
    film = 0.0
    kinetic = 0.0
    for r in range(n_runs):
        for i in range(runs[2 * r], runs[2 * r + 1] + 1):
            inv_lim = max(inv_lim, t_inv[i])
            kinetic += t_kin[i]
            moving += t_mov[i]
            film += t_film[i]
    return dt_from_inverse(inv_lim), moving, film, kinetic


#: The cell passes per law kind (:func:`~avflow.numerics.vectorize.law_copies`)
TRIAL = law_copies(_trial_cells)
FINAL = law_copies(_final_cells)

#: Placeholders of :func:`_step`'s copies (:data:`STEP`): their law's cell passes, and the
#: face passes (:data:`FACE_FLUXES`, :data:`ADD_MASSES`)
trial_cells = final_cells = face_fluxes = add_masses = None


@njit(error_model="numpy", cache=True)
def _runs(active_faces, n_active, touched, n_touched, same, wk):
    """The runs of both lists (:func:`runs_of`; cells, then faces, in ``wk``'s runs):
    those the last step left when the lists are its own (``same``), else made and kept.
    Returns how many of each."""
    runs, cut = wk.runs, wk.cut
    if same:
        return cut[CUT_RUNS], cut[CUT_FACE_RUNS]
    n_runs = runs_of(touched, n_touched, runs)
    cut[CUT_RUNS] = n_runs
    cut[CUT_FACE_RUNS] = runs_of(active_faces, n_active, runs[2 * n_runs:])
    cut[CUT_PIECES_KEPT] = 0  # the pieces are the last lists' now
    return n_runs, cut[CUT_FACE_RUNS]


@njit(error_model="numpy", cache=True)
def _cold_cells(runs, n_runs, flag, cold):
    """The cells of the runs at zero temperature (not flowing) into ``cold``; their count."""
    n = 0
    for r in range(n_runs):
        for i in range(runs[2 * r], runs[2 * r + 1] + 1):
            if flag[i] != FLOWING:
                cold[n] = i
                n += 1
    return n


@njit(error_model="numpy", cache=True, inline="always")
def _cold_masses(i, face_ptr, face_idx, face_stamp, stamp, pairs, face_frame, face_length,
                 emit, mass, flag, dirac, h_sum, x_sum, y_sum):
    """:func:`_add_masses` for one cell at zero temperature, over its listed faces
    (``face_stamp[f] == stamp``) in index order: the order in which that pass meets them,
    so the same sums, bit for bit (a - b is a + (-b)). What a dry cell takes back through a
    Dirac face is computed again, as there; only the cell's own sums are written."""
    e_h, e_u1, e_u2, e_c = emit[E_H], emit[E_U1], emit[E_U2], emit[E_C]
    e_s, e_kh, e_k3 = emit[E_S], emit[E_KH], emit[E_K3]
    fl = flag[i]
    mh = h_sum[i]  # 0.0 from the trial
    mx = x_sum[i]
    my = y_sum[i]
    for q in range(face_ptr[i], face_ptr[i + 1]):
        f = face_idx[q]
        if face_stamp[f] != stamp:
            continue
        k = pairs[f, 0]
        j = pairs[f, 1]
        first = k == i
        fl_k = flag[k]
        d = dirac_face(dirac, fl_k, flag[j] if j >= 0 else fl_k)
        if d:
            if fl == DRY:  # takes back the momentum the face brought to the trial
                _, qix, qiy, qjx, qjy = _face_flux(f, k, j, face_frame, face_length, e_h,
                                                   e_u1, e_u2, e_c, e_s, e_kh, e_k3)
                if first:
                    mx = take_back(mx, -qix, d)
                    my = take_back(my, -qiy, d)
                else:
                    mx = take_back(mx, qjx, d)
                    my = take_back(my, qjy, d)
            continue
        if first:
            mh -= mass[f]
        else:
            mh += mass[f]
    h_sum[i] = mh
    x_sum[i] = mx
    y_sum[i] = my


@njit(error_model="numpy", cache=True, inline="always")
def _open_outflow(open_faces, face_stamp, stamp, pairs, mass, flag, dirac, dt):
    """What left through the listed open faces that are not Dirac, face after face (the
    sum :func:`_add_masses` makes)."""
    outflow = 0.0
    for o in range(open_faces.size):
        f = open_faces[o]
        i = pairs[f, 0]
        if face_stamp[f] == stamp and not dirac_face(dirac, flag[i], flag[i]):
            outflow += outflow_volume(mass[f], dt)
    return outflow


def _step(mesh, physics, cur, nxt, transport, flag, when, lists, geo, wk):
    """One order-1 step over the active lists (sorted): the numbers of
    :func:`~avflow.numerics.kernels.step_faces`, with ``geo`` from :func:`geometry` and
    ``wk`` from :func:`work`; ``same``: the lists are those of the last step with ``wk``,
    whose runs it holds; a face is listed when ``face_stamp[f] == stamp``. ``h_new,
    hu_new, hv_new`` first hold the cells' sums; ``transport`` (per cell): the largest
    ``|F_h| / L`` through its faces. Each
    pass is one call over all the runs of its list (a call per run made a flow cut into
    many runs dearer: docs/performance.md). Returns
    ``(ok, outflow, dt_limit, moving, film, clamped, kinetic, wet_changes)``, the last the
    touched cells that became wet or dry (none: the next step's lists are these)."""
    face_frame, face_length, cell_area = mesh.face_frame, mesh.face_length, mesh.cell_area
    cfl_factor, density, gamma_x = mesh.cfl_factor, mesh.density, mesh.gamma_x
    gamma_y, gamma_z, h, hu, hv = mesh.gamma_y, mesh.gamma_z, cur.h, cur.hu, cur.hv
    h_new, hu_new, hv_new, law, params = nxt.h, nxt.hu, nxt.hv, physics.law, physics.params
    g, dirac, h_dry, h_zero = physics.g, physics.dirac, physics.h_dry, physics.h_zero
    dt, dt_decide = when.dt, when.dt_decide
    active_faces, n_active, touched = lists.active_faces, lists.n_active, lists.touched
    n_touched, same, face_stamp = lists.n_touched, lists.same, lists.face_stamp
    stamp = lists.stamp
    pairs, inv_area, curv = geo.pairs, geo.inv_area, geo.curvature
    emit, mass, per_cell, runs = wk.emit, wk.mass, wk.per_cell, wk.runs
    e_u1, e_u2, e_speed = emit[E_U1], emit[E_U2], emit[E_SPEED]
    t_inv, t_kin = per_cell[C_INV], per_cell[C_KIN]
    t_mov, t_film = per_cell[C_MOV], per_cell[C_FILM]
    k11, k12, k22 = curv[0], curv[1], curv[2]
    n_runs, n_face_runs = _runs(active_faces, n_active, touched, n_touched, same, wk)

    # 1. what each touched cell emits; its sums start at 0
    _emit_cells(runs, n_runs, h, hu, hv, gamma_z, density, h_zero, g, emit[E_H], e_u1, e_u2,
                emit[E_C], emit[E_S], emit[E_KH], emit[E_K3], e_speed, h_new, hu_new, hv_new,
                transport)
    # 2. the active faces' fluxes and the cells' sums, in face order
    none = wk.shared_mark[:0]  # no cell shared by threads here
    outflow = face_fluxes(runs, n_runs, n_face_runs, pairs, face_frame, face_length, emit,
                          mass, h_new, hu_new, hv_new, transport, none, 0, 0, 0, geo.near_edge,
                          wk.side, wk.face_mark, dt)
    # 3. the trial and the flags
    n_cold = trial_cells(runs, n_runs, inv_area, e_u1, e_u2, e_speed, k11, k12, k22, h, hu,
                         hv, gamma_x, gamma_y, gamma_z, law, params, g, h_zero, dt, dt_decide,
                         flag, h_new, hu_new, hv_new)
    # 4. the mass through the faces that are not Dirac, in face order; what left through
    # the open ones (where every touched cell flows, no face is Dirac and pass 2's sums
    # and outflow stand: a scan of every active face saved;
    # where a few are cold, each sums its own faces)
    if n_cold > 0 and n_cold * wk.cut[CUT_COLD_GATHER] < n_active:
        cold = wk.cold
        n_cold = _cold_cells(runs, n_runs, flag, cold)
        for c in range(n_cold):
            _cold_masses(cold[c], geo.face_ptr, geo.face_idx, face_stamp, stamp, pairs, face_frame,
                         face_length, emit, mass, flag, dirac, h_new, hu_new, hv_new)
        outflow = _open_outflow(geo.open_faces, face_stamp, stamp, pairs, mass, flag, dirac, dt)
    elif n_cold > 0:
        outflow = add_masses(runs, n_runs, n_face_runs, pairs, face_frame, face_length, emit,
                             mass, flag, dirac, dt, h_new, hu_new, hv_new, none, 0, 0, 0,
                             geo.near_edge)
    # 5. the new state
    n_bad, clamped, flips = final_cells(
        runs, n_runs, cell_area, cfl_factor, e_u1, e_u2, e_speed, k11, k12, k22, h, gamma_x,
        gamma_y, gamma_z, flag, law, params, g, h_dry, h_zero, dt, h_new, hu_new, hv_new,
        transport, t_inv, t_kin, t_mov, t_film)
    if n_bad > 0:
        return False, 0.0, 0.0, 0.0, 0.0, 0, 0.0, 0
    lim, moving, film, kinetic = _step_sums(runs, n_runs, per_cell)
    return True, outflow, lim, moving, film, clamped, kinetic, flips


#: :func:`_step` per law kind (:func:`~avflow.numerics.vectorize.law_kind`), each calling
#: its law's cell passes, so Numba compiles only those
STEP = {kind: specialize(_step, "_" + law_label(kind), trial_cells=TRIAL[kind],
                         final_cells=FINAL[kind], face_fluxes=FACE_FLUXES[False],
                         add_masses=ADD_MASSES[False])
        for kind in TRIAL}


# --- The same step on threads: each thread scatters into the cells of its own faces ------
#
# The face passes above add each face to both its cells as they meet it (a scatter: two
# threads meeting two faces of one cell would write the same place). On threads the active
# faces are cut into as many pieces as there are threads (consecutive indices), and each
# thread runs those passes over its piece. A cell whose faces all lie in one piece is
# written by that piece's thread only, in face order: the same sums. The few cells whose
# faces lie in two pieces ("shared": on 401 x 401 triangle nodes, a band of about two rows
# at each cut) get nothing from the face passes: the faces keep what they bring to each
# side in lines, and each shared cell then sums its listed faces in index order
# (kernels.cell_faces), the order in which the scatter meets them, so every sum is again
# the same. The cell passes are the vector loops above on pieces of the runs. The same bits
# as _step (and step_faces) on any number of threads, however the lists are cut.

#: The touched cells are cut into at most this many pieces for the cell passes ...
MAX_PIECES = 256
#: ... of at least this many cells or faces (a piece's vector loops have a scalar end);
#: the solver's work arrays carry both (:func:`work`), and the number of pieces of the
#: active faces (by default the threads: each cut between two pieces makes shared cells)
MIN_PIECE = 256
#: A step of fewer touched cells than this runs serially (:func:`_step`) in the copy of
#: the time loop with threads: below it, waking the pool for the step's passes costs what
#: the other cores save (measured on 2 threads: docs/performance.md, Kernels and threads);
#: a step whose lists changed, below twice this (cutting them again costs it)
MIN_PARALLEL_CELLS = 8192


def pieces_stay_local(geo, n_faces: int, threads: int) -> bool:
    """Whether the step on ``threads`` threads pays on this mesh (``geo`` from
    :func:`geometry`): its pieces of the faces must leave most cells within one piece,
    which a cell's faces do when they span few indices (``geo.span``: a small share of the
    faces on triangles, docs/performance.md). A square grid numbers its x faces before its
    y faces, so its cells' faces span half the faces, and nearly every cell would be shared
    by two pieces and summed again: slower on 2 threads than on one (docs/performance.md).
    Grids run on threads on the square-grid kernel."""
    return 4 * (threads - 1) * int(geo.span[0]) <= n_faces


@njit(error_model="numpy", cache=True)
def pieces_of(runs, n_runs, count, min_piece, max_pieces, segments, bounds):
    """The runs ``runs[:2 n_runs]`` of a list of ``count`` items (:func:`runs_of`) cut into
    segments of consecutive indices (``segments[2s], segments[2s + 1]``: first and last),
    grouped into pieces of about the same number of items: piece p is the segments
    ``bounds[p] .. bounds[p + 1] - 1``. At most ``max_pieces`` pieces of at least
    ``min_piece`` items (but the last), so at most ``n_runs + max_pieces`` segments.
    Returns the number of pieces."""
    size = max(min_piece, (count + max_pieces - 1) // max_pieces)
    n_seg = 0
    n_pieces = 0
    held = 0
    bounds[0] = 0
    for r in range(n_runs):
        a = runs[2 * r]
        b = runs[2 * r + 1]
        while a <= b:
            e = min(b, a + size - held - 1)
            segments[2 * n_seg] = a
            segments[2 * n_seg + 1] = e
            n_seg += 1
            held += e - a + 1
            a = e + 1
            if held >= size:
                n_pieces += 1
                bounds[n_pieces] = n_seg
                held = 0
    if held > 0:
        n_pieces += 1
        bounds[n_pieces] = n_seg
    return n_pieces


@njit(error_model="numpy", cache=True, inline="always")
def _last_at_most(a, stride, n, x):
    """The last k < n with ``a[stride * k] <= x`` in a sorted strided array (0 when there
    is none): a binary search."""
    lo = 0
    hi = n - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if a[stride * mid] <= x:
            lo = mid
        else:
            hi = mid - 1
    return lo


@njit(error_model="numpy", cache=True, inline="always")
def _piece_of(first_faces, n_pieces, f):
    """The piece of the faces that index ``f`` falls in: the last p with
    ``first_faces[p] <= f`` (0 below the first)."""
    return _last_at_most(first_faces, 1, n_pieces, f)


@njit(error_model="numpy", cache=True, inline="always")
def _in_runs(runs, n_runs, i):
    """Whether cell ``i`` is in the runs ``runs[:2 n_runs]`` (sorted: a binary search)."""
    r = _last_at_most(runs, 2, n_runs, i)
    return n_runs > 0 and runs[2 * r] <= i <= runs[2 * r + 1]


@njit(error_model="numpy", cache=True, inline="always")
def _share(i, runs, n_runs, face_ptr, face_idx, first_faces, n_pieces, shared, mark, cells, n):
    """Cell ``i`` (< 0: none) listed as shared if it is touched, not listed yet, and its
    first and last faces lie in different pieces; returns the cells listed."""
    if i < 0 or shared[i] == mark or not _in_runs(runs, n_runs, i):
        return n
    a = _piece_of(first_faces, n_pieces, face_idx[face_ptr[i]])
    b = _piece_of(first_faces, n_pieces, face_idx[face_ptr[i + 1] - 1])
    if a == b:
        return n
    shared[i] = mark
    cells[n] = i
    return n + 1


@njit(error_model="numpy", cache=True)
def _find_shared(runs, n_runs, n_touched, pairs, face_ptr, face_idx, span, edge_cells,
                 first_faces, n_pieces, shared, mark, cells):
    """The touched cells (in the runs) whose faces lie in more than one piece of the faces:
    ``shared[i] = mark`` and listed in ``cells``; returns how many. The faces of a cell are
    in index order and span at most ``span`` indices, but for the ``edge_cells`` (with a
    boundary face, numbered far away), so such a cell is one of those or has its first face
    within ``span`` below a cut, where only it is looked for (a few thousand faces a cut
    and the cells along the walls on triangles). Where that would visit
    more cells than are touched (a square grid, whose x faces come before its y faces: its
    span is half the faces), every touched cell is looked at instead (the same cells: a
    scan of every face within a span of each cut, at every step, cost a grid on faces many
    times its time on one thread: docs/performance.md)."""
    n = 0
    if 2 * (n_pieces - 1) * (span + 2) + edge_cells.size > n_touched:
        for r in range(n_runs):
            for i in range(runs[2 * r], runs[2 * r + 1] + 1):
                a = _piece_of(first_faces, n_pieces, face_idx[face_ptr[i]])
                b = _piece_of(first_faces, n_pieces, face_idx[face_ptr[i + 1] - 1])
                if a != b:
                    shared[i] = mark
                    cells[n] = i
                    n += 1
        return n
    for e in range(edge_cells.size):
        n = _share(edge_cells[e], runs, n_runs, face_ptr, face_idx, first_faces, n_pieces,
                   shared, mark, cells, n)
    for p in range(1, n_pieces):
        cut = first_faces[p]
        for f in range(max(cut - span - 1, 0), min(cut, pairs.shape[0] - 1) + 1):
            for k in range(2):
                n = _share(pairs[f, k], runs, n_runs, face_ptr, face_idx, first_faces,
                           n_pieces, shared, mark, cells, n)
    return n


@njit(error_model="numpy", cache=True, inline="always")
def _shared_sums(i, face_ptr, face_idx, pairs, face_length, mass, side, marks, mark, h_sum,
                 x_sum, y_sum, transport):
    """A shared cell: the sums of its listed faces (``marks[f] == mark``) in index order,
    the scatter's order, and the largest ``|F_h| / L``. A cell's side of a face is a
    select: a - b is a + (-b), bit for bit."""
    mh = 0.0
    mx = 0.0
    my = 0.0
    unit_max = 0.0
    for q in range(face_ptr[i], face_ptr[i + 1]):
        f = face_idx[q]
        if marks[f] != mark:
            continue
        first = pairs[f, 0] == i
        fh = mass[f]
        mh += -fh if first else fh
        mx += -side[0, f] if first else side[2, f]
        my += -side[1, f] if first else side[3, f]
        unit_max = max(unit_max, abs(fh) / face_length[f])
    h_sum[i] = mh
    x_sum[i] = mx
    y_sum[i] = my
    transport[i] = unit_max


@njit(error_model="numpy", cache=True, inline="always")
def _safe_faces(first_faces, n_pieces, last_face, span, p):
    """The faces of piece p that touch no shared cell: ``(lo, hi)``, those more than a
    cell's span from both its cuts (none below ``lo`` or above ``hi`` is sure)."""
    lo = first_faces[p] + span if p > 0 else -1
    hi = (first_faces[p + 1] - 1 - span) if p < n_pieces - 1 else last_face + 1
    return lo, hi


@njit(error_model="numpy", cache=True, inline="always")
def _piece_lines(pieces, n_touched, n_active, max_pieces):
    """The pieces of both lists in the work arrays' ``pieces`` (:func:`pieces_of`): the
    cells' segments and bounds, then the faces', then each face piece's first face."""
    m_seg = 2 * (n_touched + max_pieces)
    rest = pieces[m_seg + max_pieces + 1:]
    f_seg = 2 * (n_active + max_pieces)
    return (pieces[:m_seg], pieces[m_seg:m_seg + max_pieces + 1], rest[:f_seg],
            rest[f_seg:f_seg + max_pieces + 1],
            rest[f_seg + max_pieces + 1:f_seg + 2 * max_pieces + 1])


@njit(error_model="numpy", cache=True)
def _cut_lists(active_faces, n_active, touched, n_touched, same, pairs, face_ptr, face_idx,
               span, edge_cells, wk):
    """The lists of the step on threads cut into pieces (the layout of ``wk``'s pieces: the
    cells' segments and bounds, then the faces', then each face piece's first face), and
    the shared cells found (:func:`_find_shared`). On the lists of the last step
    (``same``) what it made is used again, if it was made on threads (a flow covering its
    whole mesh cuts nothing again). Returns the numbers of runs of cells and of
    faces, of pieces of each, and of shared cells."""
    runs, pieces, cut = wk.runs, wk.pieces, wk.cut
    shared, shared_cells = wk.shared_mark, wk.shared_cells
    if same and cut[CUT_PIECES_KEPT] == 1:
        return (cut[CUT_RUNS], cut[CUT_FACE_RUNS], cut[CUT_CELL_PIECES],
                cut[CUT_FACE_PIECES_MADE], cut[CUT_SHARED])
    n_runs, n_face_runs = _runs(active_faces, n_active, touched, n_touched, same, wk)
    # A new number for these lists: a face listed in them and a cell shared in them carry
    # it (the work buffers hold the state of a cell only once a step touched it in this
    # call of the time loop: whether a neighbour beyond a touched dry cell is wet cannot be
    # read there)
    cut[CUT_MARK] += 1
    min_piece, max_pieces = cut[CUT_MIN_PIECE], cut[CUT_MAX_PIECES]
    cell_seg, cell_bounds, face_seg, face_bounds, first_faces = _piece_lines(
        pieces, n_touched, n_active, max_pieces)
    n_cp = pieces_of(runs, n_runs, n_touched, min_piece, max_pieces, cell_seg, cell_bounds)
    n_fp = pieces_of(runs[2 * n_runs:], n_face_runs, n_active, min_piece,
                     max(1, min(max_pieces, cut[CUT_FACE_PIECES])), face_seg, face_bounds)
    for p in range(n_fp):
        first_faces[p] = face_seg[2 * face_bounds[p]]
    n_shared = _find_shared(runs, n_runs, n_touched, pairs, face_ptr, face_idx, span,
                            edge_cells, first_faces, n_fp, shared, cut[CUT_MARK],
                            shared_cells)
    cut[CUT_CELL_PIECES] = n_cp
    cut[CUT_FACE_PIECES_MADE] = n_fp
    cut[CUT_SHARED] = n_shared
    cut[CUT_PIECES_KEPT] = 1
    return n_runs, n_face_runs, n_cp, n_fp, n_shared


def _step_threads(mesh, physics, cur, nxt, transport, flag, when, lists, geo, wk):
    """:func:`_step` on Numba's threads (its arguments, its returns, its bits; ``geo`` and
    ``wk`` from :func:`geometry` and :func:`work` with ``threads``):

    1. the active faces cut into pieces (one a thread by default), the touched cells whose
       faces lie in two pieces found near the cuts (:func:`_cut_lists`; kept from the last
       step on the same lists, ``same``); per piece of the touched cells, what they emit
       (:func:`_emit_cells`);
    2. per piece of the faces, :func:`_face_fluxes` (a shared cell's sides into lines);
       per shared cell its sums (:func:`_shared_sums`); per piece of the cells, the trial
       and the flags;
    3. per piece of the faces, :func:`_add_masses`; per shared cell at zero temperature
       its own faces (:func:`_cold_masses`); where few cells are at zero temperature, each
       of those sums its own faces instead, and where none, nothing;
    4. per piece of the cells, the new state (:func:`_final_cells`);
       then, serially, the volume through the open faces (in face order) and the step's
       sums (in the lists' order).
    """
    face_frame, face_length, cell_area = mesh.face_frame, mesh.face_length, mesh.cell_area
    cfl_factor, density, gamma_x = mesh.cfl_factor, mesh.density, mesh.gamma_x
    gamma_y, gamma_z, h, hu, hv = mesh.gamma_y, mesh.gamma_z, cur.h, cur.hu, cur.hv
    h_new, hu_new, hv_new, law, params = nxt.h, nxt.hu, nxt.hv, physics.law, physics.params
    g, dirac, h_dry, h_zero = physics.g, physics.dirac, physics.h_dry, physics.h_zero
    dt, dt_decide = when.dt, when.dt_decide
    active_faces, n_active, touched = lists.active_faces, lists.n_active, lists.touched
    n_touched, same, face_stamp = lists.n_touched, lists.same, lists.face_stamp
    stamp = lists.stamp
    pairs, inv_area, curv = geo.pairs, geo.inv_area, geo.curvature
    face_ptr, face_idx, open_faces, span = geo.face_ptr, geo.face_idx, geo.open_faces, geo.span[0]
    near_edge, edge_cells = geo.near_edge, geo.edge_cells
    emit, mass, per_cell, runs, side = wk.emit, wk.mass, wk.per_cell, wk.runs, wk.side
    pieces, cut, marks = wk.pieces, wk.cut, wk.face_mark
    shared, shared_cells = wk.shared_mark, wk.shared_cells
    max_pieces = cut[CUT_MAX_PIECES]
    e_u1, e_u2, e_speed = emit[E_U1], emit[E_U2], emit[E_SPEED]
    t_inv, t_kin = per_cell[C_INV], per_cell[C_KIN]
    t_mov, t_film = per_cell[C_MOV], per_cell[C_FILM]
    k11, k12, k22 = curv[0], curv[1], curv[2]
    n_runs, _, n_cp, n_fp, n_shared = _cut_lists(
        active_faces, n_active, touched, n_touched, same, pairs, face_ptr, face_idx, span,
        edge_cells, wk)
    mark = cut[CUT_MARK]
    cell_seg, cell_bounds, face_seg, face_bounds, first_faces = _piece_lines(
        pieces, n_touched, n_active, max_pieces)
    last_face = active_faces[n_active - 1] if n_active > 0 else 0

    # 1. what each touched cell emits
    for p in prange(n_cp):
        s0 = cell_bounds[p]
        _emit_cells(cell_seg[2 * s0:], cell_bounds[p + 1] - s0, h, hu, hv, gamma_z, density,
                    h_zero, g, emit[E_H], e_u1, e_u2, emit[E_C], emit[E_S], emit[E_KH],
                    emit[E_K3], e_speed, h_new, hu_new, hv_new, transport)
    # 2. the faces' fluxes, each thread into the cells of its own piece; the shared cells'
    # sums; the trial and the flags
    for p in prange(n_fp):
        lo, hi = _safe_faces(first_faces, n_fp, last_face, span, p)
        face_fluxes(face_seg, face_bounds[p], face_bounds[p + 1] - face_bounds[p], pairs,
                    face_frame, face_length, emit, mass, h_new, hu_new, hv_new, transport,
                    shared, mark, lo, hi, near_edge, side, marks, dt)
    for c in prange(n_shared):
        _shared_sums(shared_cells[c], face_ptr, face_idx, pairs, face_length, mass, side,
                     marks, mark, h_new, hu_new, hv_new, transport)
    n_cold = 0
    for p in prange(n_cp):
        s0 = cell_bounds[p]
        n_cold += trial_cells(cell_seg[2 * s0:], cell_bounds[p + 1] - s0, inv_area, e_u1,
                              e_u2, e_speed, k11, k12, k22, h, hu, hv, gamma_x, gamma_y,
                              gamma_z, law, params, g, h_zero, dt, dt_decide, flag, h_new,
                              hu_new, hv_new)
    # 3. the cells at zero temperature: the mass of their faces that are not Dirac (none
    # where every touched cell flows: the sums of 2 stand; where a few are cold, each sums
    # its own faces, shared or not)
    if n_cold > 0 and n_cold * cut[CUT_COLD_GATHER] < n_active:
        cold = wk.cold
        n_cold = _cold_cells(runs, n_runs, flag, cold)
        for c in prange(n_cold):
            _cold_masses(cold[c], face_ptr, face_idx, face_stamp, stamp, pairs, face_frame,
                         face_length, emit, mass, flag, dirac, h_new, hu_new, hv_new)
    elif n_cold > 0:
        for p in prange(n_fp):
            lo, hi = _safe_faces(first_faces, n_fp, last_face, span, p)
            add_masses(face_seg, face_bounds[p], face_bounds[p + 1] - face_bounds[p], pairs,
                       face_frame, face_length, emit, mass, flag, dirac, dt, h_new, hu_new,
                       hv_new, shared, mark, lo, hi, near_edge)
        for c in prange(n_shared):  # (the faces of a shared cell at zero temperature)
            i = shared_cells[c]
            if flag[i] != FLOWING:
                _cold_masses(i, face_ptr, face_idx, face_stamp, stamp, pairs, face_frame,
                             face_length, emit, mass, flag, dirac, h_new, hu_new, hv_new)
    # 4. the new state
    n_bad = 0
    clamped = 0
    flips = 0
    for p in prange(n_cp):
        s0 = cell_bounds[p]
        bad, cl, fl = final_cells(
            cell_seg[2 * s0:], cell_bounds[p + 1] - s0, cell_area, cfl_factor, e_u1, e_u2,
            e_speed, k11, k12, k22, h, gamma_x, gamma_y, gamma_z, flag, law, params, g, h_dry,
            h_zero, dt, h_new, hu_new, hv_new, transport, t_inv, t_kin, t_mov, t_film)
        n_bad += bad
        clamped += cl
        flips += fl
    if n_bad > 0:
        return False, 0.0, 0.0, 0.0, 0.0, 0, 0.0, 0
    # what left through the open faces that are listed, face after face
    outflow = _open_outflow(open_faces, face_stamp, stamp, pairs, mass, flag, dirac, dt)
    lim, moving, film, kinetic = _step_sums(runs, n_runs, per_cell)
    return True, outflow, lim, moving, film, clamped, kinetic, flips


#: :func:`_step_threads` per law kind, compiled with threads, and serially (``prange``
#: runs as ``range``: what the tests hold to :func:`_step` on one thread)
_SHARED_PASSES = dict(face_fluxes=FACE_FLUXES[True], add_masses=ADD_MASSES[True])
STEP_THREADS = {kind: specialize(_step_threads, "_" + law_label(kind) + "_parallel",
                                 parallel=True, trial_cells=TRIAL[kind],
                                 final_cells=FINAL[kind], **_SHARED_PASSES)
                for kind in TRIAL}
STEP_PIECES_SERIAL = {kind: specialize(_step_threads, "_" + law_label(kind) + "_serial",
                                       trial_cells=TRIAL[kind], final_cells=FINAL[kind],
                                       **_SHARED_PASSES)
                      for kind in TRIAL}
