"""The structured square-grid kernel: the face kernel's step, swept by rows, on every core.

Same scheme as :func:`avflow.numerics.kernels.step_faces` (seed eqs. 26-56: rectangular
fluxes, trial momentum and Coulomb threshold, Dirac faces, projection, curvature and film
rules, walls, NODATA holes, open sides), on the layout of
:class:`avflow.terrain.squaregrid.SquareGrid`: x faces and y faces are found by their place
in the grid, with no face lists and no per-face index arrays, and each cell's thickness,
discharge and sound speed are read once per face sweep of its row.

One step is three parallel passes over the rows of the *swept region* (the rows and columns
the flow covers, one cell around, see :func:`advance_grid`), each a gather: a face is
computed by one row and written once; a cell sums its own four faces. No two threads write
the same place and every sum runs in the same order whatever the number of threads, so the
answer is bit for bit the same on 1 or N threads. Diagnostics summed over the whole grid
(moving volume, film, kinetic energy, outflow) are summed per row, then over the rows in
order: the same for any number of threads, but not in the face kernel's order (which adds
cell after cell), so those four differ from the face kernel's by round-off. Everything else
(thickness, discharge, observers, time steps) is the face kernel's, bit for bit: each cell
adds its faces in the order of their indices in the mesh (``face_order``), as the face
kernel does.

1. faces: the kinetic flux of every x face of a row and every y face below it;
2. cells: the trial momentum of eq. 47 and the threshold flag of eq. 49;
3. cells: mass through the faces that are not Dirac, momentum by projection (eq. 50),
   observers, the row's sums and the extent of the wet cells for the next step.

``prange`` runs serially when the functions are compiled without ``parallel``: the module
compiles each pass twice (``*_serial`` and ``*_parallel``), and one thread takes the serial
one, which never touches Numba's thread pool (safe inside dask workers and any thread).
"""

from __future__ import annotations

import math
import types

import numpy as np
from numba import njit, prange

from avflow.numerics.kernels import (DRY, FAILED, FLOWING, MAX_RETRIES, MAX_STEPS,
                                     REACHED_TARGET, STOPPED, ST_CLAMPED, ST_DT_LIMIT,
                                     ST_DT_MAX, ST_DT_MIN, ST_FILM, ST_KINETIC, ST_KINETIC_PEAK,
                                     ST_MOVING, ST_OUTFLOW, ST_RETRIES, ST_STEPS, ST_TIME,
                                     UNDER_THRESHOLD, _centripetal, _dirac_face, _final_momentum,
                                     _limit, _moves, _observe, _open_mass, _speed,
                                     _trial_momentum)
from avflow.numerics.kinetic import half_fluxes, sound_speed
from avflow.terrain.squaregrid import (CANONICAL_ORDER, HIGH_OPEN, HIGH_WALL, INNER, LOW_OPEN,
                                       LOW_WALL, NO_FACE)

# Columns of the per-row results of pass 3
R_OK = 0  #: 1 when every cell of the row kept h >= 0
R_OUT = 1  #: volume out through the row's open faces
R_INV = 2  #: largest inverse CFL limit
R_MOVING = 3
R_FILM = 4
R_KINETIC = 5
R_CLAMPED = 6
N_ROW = 7


@njit(error_model="numpy", cache=True, inline="always")
def _emitting_state(h, hu, hv, h_zero, g_normal, dens):
    """What a cell emits through its faces: ``(h, q1, q2, c, k)``, zero at or below h_zero."""
    if h <= h_zero:
        return 0.0, 0.0, 0.0, 0.0, 0.0
    c = sound_speed(h, g_normal)
    return h, hu, hv, c, c * dens


@njit(error_model="numpy", cache=True, inline="always")
def _face_flux(code, hi, qi1, qi2, ci, ki, hj, qj1, qj2, cj, kj, n0x, n0y, t0x, t0y, n1x, n1y,
               t1x, t1y, length):
    """One face, the arithmetic of :func:`~avflow.numerics.kernels.step_faces` sweep 1a:
    ``(fh, qix, qiy, qjx, qjy)`` with i the face's first cell (frame side 0) and j the second
    (frame side 1) or the wall / open side beyond a boundary face."""
    uni = 0.0
    uti = 0.0
    if hi > 0.0:
        uni = (qi1 * n0x + qi2 * n0y) / hi
        uti = (qi1 * t0x + qi2 * t0y) / hi
    fp_h, fp_q, _, _ = half_fluxes(hi, uni, ci, ki)
    if code == INNER:
        unj = 0.0
        utj = 0.0
        if hj > 0.0:
            unj = (qj1 * n1x + qj2 * n1y) / hj
            utj = (qj1 * t1x + qj2 * t1y) / hj
        _, _, gm_h, gm_q = half_fluxes(hj, unj, cj, kj)
    elif code == LOW_WALL or code == HIGH_WALL:  # mirror ghost: no mass, twice the pressure
        gm_h = -fp_h
        gm_q = fp_q
        utj = uti
    else:  # open: transmissive for what leaves, closed to what would enter
        _, _, gm_h, gm_q = half_fluxes(hi, max(uni, 0.0), ci, ki)
        gm_h = _open_mass(fp_h + gm_h) - fp_h
        utj = uti
    f_n = (fp_q + gm_q) * length
    f_t = (uti * fp_h + utj * gm_h) * length
    fh = (fp_h + gm_h) * length
    return (fh, f_n * n0x + f_t * t0x, f_n * n0y + f_t * t0y,
            f_n * n1x + f_t * t1x, f_n * n1y + f_t * t1y)


@njit(error_model="numpy", cache=True, inline="always")
def _ordered(order, start, a_w, a_e, a_s, a_n):
    """``start`` plus the four side terms (W, E, S, N) in the cell's face order (the order of
    the face indices in the mesh: the face kernel's order of summation, bit for bit)."""
    if order == CANONICAL_ORDER:
        return (((start + a_w) + a_e) + a_s) + a_n
    s = start
    for k in range(4):
        d = (order >> (2 * k)) & 3
        if d == 0:
            s += a_w
        elif d == 1:
            s += a_e
        elif d == 2:
            s += a_s
        else:
            s += a_n
    return s


def _faces(nx, ny, x_code, x_frame, x_length, y_code, y_frame, y_length, density, gamma_z,
           h, hu, hv, x_flux, y_flux, g, h_zero, r0, r1, lo, hi):
    """Pass 1: the faces of the swept rows ``r0..r1`` (x faces of row r, y faces below it)."""
    for r in prange(r0, r1 + 2):
        if r <= r1 and lo[r] <= hi[r]:  # x faces lo .. hi + 1 of row r
            base = r * nx
            p = base + lo[r] - 1
            if lo[r] > 0:
                hl, ql1, ql2, cl, kl = _emitting_state(h[p], hu[p], hv[p], h_zero,
                                                       g * gamma_z[p], density[p])
            else:
                hl = ql1 = ql2 = cl = kl = 0.0
            for k in range(lo[r], hi[r] + 2):
                p = base + k
                if k < nx:
                    hr, qr1, qr2, cr, kr = _emitting_state(h[p], hu[p], hv[p], h_zero,
                                                           g * gamma_z[p], density[p])
                else:
                    hr = qr1 = qr2 = cr = kr = 0.0
                code = x_code[r, k]
                if code != NO_FACE:
                    if code >= HIGH_WALL:  # the east cell owns it: i is the right cell
                        f0, f1, f2, f3, f4 = _face_flux(
                            code, hr, qr1, qr2, cr, kr, 0.0, 0.0, 0.0, 0.0, 0.0,
                            x_frame[r, k, 0], x_frame[r, k, 1], x_frame[r, k, 2],
                            x_frame[r, k, 3], x_frame[r, k, 4], x_frame[r, k, 5],
                            x_frame[r, k, 6], x_frame[r, k, 7], x_length[r, k])
                    else:
                        f0, f1, f2, f3, f4 = _face_flux(
                            code, hl, ql1, ql2, cl, kl, hr, qr1, qr2, cr, kr,
                            x_frame[r, k, 0], x_frame[r, k, 1], x_frame[r, k, 2],
                            x_frame[r, k, 3], x_frame[r, k, 4], x_frame[r, k, 5],
                            x_frame[r, k, 6], x_frame[r, k, 7], x_length[r, k])
                    x_flux[r, k, 0] = f0
                    x_flux[r, k, 1] = f1
                    x_flux[r, k, 2] = f2
                    x_flux[r, k, 3] = f3
                    x_flux[r, k, 4] = f4
                hl, ql1, ql2, cl, kl = hr, qr1, qr2, cr, kr
        # y faces (r, c) between rows r - 1 and r, over both rows' columns
        c0 = nx
        c1 = -1
        if r <= r1 and lo[r] <= hi[r]:
            c0 = min(c0, lo[r])
            c1 = max(c1, hi[r])
        if r - 1 >= r0 and lo[r - 1] <= hi[r - 1]:
            c0 = min(c0, lo[r - 1])
            c1 = max(c1, hi[r - 1])
        for c in range(c0, c1 + 1):
            code = y_code[r, c]
            if code == NO_FACE:
                continue
            if r > 0:
                p = (r - 1) * nx + c
                hl, ql1, ql2, cl, kl = _emitting_state(h[p], hu[p], hv[p], h_zero,
                                                       g * gamma_z[p], density[p])
            else:
                hl = ql1 = ql2 = cl = kl = 0.0
            if r < ny:
                p = r * nx + c
                hr, qr1, qr2, cr, kr = _emitting_state(h[p], hu[p], hv[p], h_zero,
                                                       g * gamma_z[p], density[p])
            else:
                hr = qr1 = qr2 = cr = kr = 0.0
            if code >= HIGH_WALL:
                f0, f1, f2, f3, f4 = _face_flux(
                    code, hr, qr1, qr2, cr, kr, 0.0, 0.0, 0.0, 0.0, 0.0,
                    y_frame[r, c, 0], y_frame[r, c, 1], y_frame[r, c, 2], y_frame[r, c, 3],
                    y_frame[r, c, 4], y_frame[r, c, 5], y_frame[r, c, 6], y_frame[r, c, 7],
                    y_length[r, c])
            else:
                f0, f1, f2, f3, f4 = _face_flux(
                    code, hl, ql1, ql2, cl, kl, hr, qr1, qr2, cr, kr,
                    y_frame[r, c, 0], y_frame[r, c, 1], y_frame[r, c, 2], y_frame[r, c, 3],
                    y_frame[r, c, 4], y_frame[r, c, 5], y_frame[r, c, 6], y_frame[r, c, 7],
                    y_length[r, c])
            y_flux[r, c, 0] = f0
            y_flux[r, c, 1] = f1
            y_flux[r, c, 2] = f2
            y_flux[r, c, 3] = f3
            y_flux[r, c, 4] = f4


def _trial(nx, valid, face_order, x_code, y_code, x_flux, y_flux, cell_area, gamma_x, gamma_y,
           gamma_z, curvature, h, hu, hv, hu_new, hv_new, flag, law, params, g, h_zero, dt,
           dt_decide, r0, r1, lo, hi):
    """Pass 2: per cell, the flux divergence, then the trial momentum and the flag (eq. 49);
    a dry cell keeps its momentum sum for pass 3 (as the face kernel's sweep 1b)."""
    p0, p1, p2, p3 = params[0], params[1], params[2], params[3]
    p4, p5, p6, p7 = params[4], params[5], params[6], params[7]
    for r in prange(r0, r1 + 1):
        for c in range(lo[r], hi[r] + 1):
            i = r * nx + c
            if valid[i] == 0:
                flag[i] = DRY
                continue
            cw, ce, cs, cn = x_code[r, c], x_code[r, c + 1], y_code[r, c], y_code[r + 1, c]
            # each side's terms (mass, x, y): a face brings +F_j to its second cell and
            # -F_i to its first (scalar loads: views of the flux arrays cost the sweep 2x)
            if cw == INNER:
                wm, wx, wy = x_flux[r, c, 0], x_flux[r, c, 3], x_flux[r, c, 4]
            else:
                wm, wx, wy = -x_flux[r, c, 0], -x_flux[r, c, 1], -x_flux[r, c, 2]
            em, ex, ey = -x_flux[r, c + 1, 0], -x_flux[r, c + 1, 1], -x_flux[r, c + 1, 2]
            if cs == INNER:
                sm, sx, sy = y_flux[r, c, 0], y_flux[r, c, 3], y_flux[r, c, 4]
            else:
                sm, sx, sy = -y_flux[r, c, 0], -y_flux[r, c, 1], -y_flux[r, c, 2]
            nm, nx_, ny_ = -y_flux[r + 1, c, 0], -y_flux[r + 1, c, 1], -y_flux[r + 1, c, 2]
            order = face_order[i]
            mx = _ordered(order, 0.0, wx, ex, sx, nx_)
            my = _ordered(order, 0.0, wy, ey, sy, ny_)
            if h[i] <= h_zero:
                flag[i] = DRY
                hu_new[i] = mx
                hv_new[i] = my
                continue
            mh = _ordered(order, 0.0, wm, em, sm, nm)
            inv_area = 1.0 / cell_area[i]
            qx, qy, fi = _trial_momentum(h[i], h_zero, _speed(h[i], hu[i], hv[i]), hu[i], hv[i],
                                         mh * inv_area, mx * inv_area, my * inv_area, dt,
                                         dt_decide, gamma_x[i], gamma_y[i], gamma_z[i],
                                         _centripetal(curvature, i, h[i], hu[i], hv[i]),
                                         law, p0, p1, p2, p3, p4, p5, p6, p7, g, False)
            hu_new[i] = qx
            hv_new[i] = qy
            flag[i] = fi


def _final(nx, ny, valid, face_order, x_code, y_code, x_flux, y_flux, x_length, y_length,
           cell_area, cfl_factor, gamma_x, gamma_y, gamma_z, curvature, h, hu, hv, h_new, hu_new,
           hv_new, flag, law, params, g, dirac, h_dry, h_zero, dt, t_new, peak_h, peak_speed,
           arrival, last_moved, r0, r1, lo, hi, rows, wet_lo, wet_hi):
    """Pass 3: mass through the faces that keep the rectangular density, the projection,
    the observers; per row its sums (``rows``) and the columns of its wet cells."""
    p0, p1, p2, p3 = params[0], params[1], params[2], params[3]
    p4, p5, p6, p7 = params[4], params[5], params[6], params[7]
    for r in prange(r0, r1 + 1):
        ok = 1.0
        outflow = 0.0
        inv_lim = 0.0
        moving = 0.0
        film = 0.0
        kinetic = 0.0
        clamped = 0
        w_lo = nx
        w_hi = -1
        for c in range(lo[r], hi[r] + 1):
            i = r * nx + c
            if valid[i] == 0:
                continue
            fi = flag[i]
            cw, ce, cs, cn = x_code[r, c], x_code[r, c + 1], y_code[r, c], y_code[r + 1, c]
            # each side's terms (mass, x, y): a face brings +F_j to its second cell and
            # -F_i to its first (scalar loads: views of the flux arrays cost the sweep 2x)
            if cw == INNER:
                wm, wx, wy = x_flux[r, c, 0], x_flux[r, c, 3], x_flux[r, c, 4]
            else:
                wm, wx, wy = -x_flux[r, c, 0], -x_flux[r, c, 1], -x_flux[r, c, 2]
            em, ex, ey = -x_flux[r, c + 1, 0], -x_flux[r, c + 1, 1], -x_flux[r, c + 1, 2]
            if cs == INNER:
                sm, sx, sy = y_flux[r, c, 0], y_flux[r, c, 3], y_flux[r, c, 4]
            else:
                sm, sx, sy = -y_flux[r, c, 0], -y_flux[r, c, 1], -y_flux[r, c, 2]
            nm, nx_, ny_ = -y_flux[r + 1, c, 0], -y_flux[r + 1, c, 1], -y_flux[r + 1, c, 2]
            # Dirac faces (eqs. 51-53): both sides at zero temperature; a boundary ghost
            # shares its cell's flag
            d_w = _dirac_face(dirac, fi, flag[i - 1] if cw == INNER else fi)
            d_e = _dirac_face(dirac, fi, flag[i + 1] if ce == INNER else fi)
            d_s = _dirac_face(dirac, fi, flag[i - nx] if cs == INNER else fi)
            d_n = _dirac_face(dirac, fi, flag[i + nx] if cn == INNER else fi)
            order = face_order[i]
            acc = _ordered(order, 0.0, 0.0 if d_w else wm, 0.0 if d_e else em,
                           0.0 if d_s else sm, 0.0 if d_n else nm)
            area = cell_area[i]
            hn = h[i] + dt / area * acc
            if hn < 0.0:
                ok = 0.0
                continue
            transport = 0.0
            # |fh| / L of the faces that carried mass; what left through open sides (a
            # face's flux is outward from its owner i: -term for the cell's own faces)
            if not d_w:
                transport = max(transport, abs(wm) / x_length[r, c])
                if cw == HIGH_OPEN:
                    outflow += max(-wm, 0.0) * dt
            if not d_e:
                transport = max(transport, abs(em) / x_length[r, c + 1])
                if ce == LOW_OPEN:
                    outflow += max(-em, 0.0) * dt
            if not d_s:
                transport = max(transport, abs(sm) / y_length[r, c])
                if cs == HIGH_OPEN:
                    outflow += max(-sm, 0.0) * dt
            if not d_n:
                transport = max(transport, abs(nm) / y_length[r + 1, c])
                if cn == LOW_OPEN:
                    outflow += max(-nm, 0.0) * dt
            qx = hu_new[i]
            qy = hv_new[i]
            if fi == DRY:
                # a dry side takes no momentum through a Dirac face: the face kernel takes
                # back, in face order, what those faces brought to the sum of pass 2
                if d_w or d_e or d_s or d_n:
                    qx = _ordered(order, qx, -wx if d_w else 0.0, -ex if d_e else 0.0,
                                  -sx if d_s else 0.0, -nx_ if d_n else 0.0)
                    qy = _ordered(order, qy, -wy if d_w else 0.0, -ey if d_e else 0.0,
                                  -sy if d_s else 0.0, -ny_ if d_n else 0.0)
                qx = dt * (qx / area + g * hn * gamma_x[i])
                qy = dt * (qy / area + g * hn * gamma_y[i])
            speed_n = _speed(h[i], hu[i], hv[i])
            qx, qy, cl = _final_momentum(fi, speed_n, hn, h_zero, qx, qy, dt, gamma_z[i],
                                         _centripetal(curvature, i, h[i], hu[i], hv[i]),
                                         law, p0, p1, p2, p3, p4, p5, p6, p7, g, h[i], False)
            h_new[i] = hn
            hu_new[i] = qx
            hv_new[i] = qy
            clamped += cl
            speed, inv_i = _observe(hn, math.sqrt(qx * qx + qy * qy), cfl_factor[i], gamma_z[i],
                                    g)
            inv_lim = max(inv_lim, inv_i)
            if hn > peak_h[i]:
                peak_h[i] = hn
            if speed > peak_speed[i]:
                peak_speed[i] = speed
            if hn > h_dry and math.isnan(arrival[i]):
                arrival[i] = t_new
            if speed > 0.0:
                last_moved[i] = t_new
            kinetic += hn * area * speed * speed
            if _moves(speed, speed_n, transport, hn):
                if hn > h_dry:
                    moving += hn * area
                else:
                    film += hn * area
            if hn > h_zero:
                w_lo = min(w_lo, c)
                w_hi = max(w_hi, c)
        rows[r, R_OK] = ok
        rows[r, R_OUT] = outflow
        rows[r, R_INV] = inv_lim
        rows[r, R_MOVING] = moving
        rows[r, R_FILM] = film
        rows[r, R_KINETIC] = kinetic
        rows[r, R_CLAMPED] = clamped
        wet_lo[r] = w_lo
        wet_hi[r] = w_hi


def _compiled(fn, parallel: bool):
    """``fn`` compiled serial or parallel, under its own name: Numba's cache files are named
    after the function (name and line), not after its flags, so two dispatchers of one
    function would load each other's machine code (the "serial" pass then ran on the thread
    pool, 5x slower on a busy machine)."""
    suffix = "_parallel" if parallel else "_serial"
    copy = types.FunctionType(fn.__code__, fn.__globals__, fn.__name__ + suffix,
                              fn.__defaults__, fn.__closure__)
    copy.__qualname__ = fn.__qualname__ + suffix
    copy.__module__ = fn.__module__
    copy.__doc__ = fn.__doc__
    return njit(error_model="numpy", cache=True, parallel=parallel)(copy)


faces_serial, faces_parallel = _compiled(_faces, False), _compiled(_faces, True)
trial_serial, trial_parallel = _compiled(_trial, False), _compiled(_trial, True)
final_serial, final_parallel = _compiled(_final, False), _compiled(_final, True)


@njit(error_model="numpy", cache=True)
def _swept_columns(nx, ny, wet_lo, wet_hi, need_lo, need_hi, prev_lo, prev_hi, lo, hi):
    """Columns to sweep per row: the wet cells of each row and of the rows above and below,
    one column more on each side (every face of a wet cell and the cells beyond), joined with
    what the last step needed (a cell it changed is written once more, so both buffers agree
    again wherever the sweep no longer goes). Returns the band of rows ``(r0, r1)``."""
    r0 = ny
    r1 = -1
    for r in range(ny):
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
        if lo[r] <= hi[r]:
            r0 = min(r0, r)
            r1 = max(r1, r)
    return r0, r1


@njit(error_model="numpy", cache=True)
def advance_grid(parallel, nx, ny, valid, face_order, x_code, x_frame, x_length, y_code, y_frame,
                 y_length, cell_area, cfl_factor, density, gamma_x, gamma_y, gamma_z, curvature,
                 h, hu, hv, h_work, hu_work, hv_work, x_flux, y_flux, flag,
                 law, params, g, dirac, h_dry, h_zero, cfl, t_target, max_steps, stop_volume,
                 stop_kinetic, peak_h, peak_speed, arrival, last_moved, stats):
    """:func:`avflow.numerics.kernels.advance` for a square grid at order 1 (same arguments
    where they mean the same, same status codes and ``stats`` slots), on ``ny x nx`` arrays
    (:class:`~avflow.terrain.squaregrid.SquareGrid`). ``parallel`` picks the passes compiled
    for Numba's threads (their number is set by the caller) or the serial ones.

    Only the swept region is computed (:func:`_swept_columns`), so a step costs the area
    the flow covers; its rows are found from the extents of the wet cells kept per row.
    """
    t = stats[ST_TIME]
    status = REACHED_TARGET
    steps = 0
    h_work[:] = h
    hu_work[:] = hu
    hv_work[:] = hv
    rows = np.zeros((ny, N_ROW))
    wet_lo = np.full(ny, nx, dtype=np.int64)
    wet_hi = np.full(ny, -1, dtype=np.int64)
    need_lo = np.full(ny, nx, dtype=np.int64)
    need_hi = np.full(ny, -1, dtype=np.int64)
    prev_lo = np.full(ny, nx, dtype=np.int64)
    prev_hi = np.full(ny, -1, dtype=np.int64)
    lo = np.full(ny, nx, dtype=np.int64)
    hi = np.full(ny, -1, dtype=np.int64)
    for r in range(ny):
        for c in range(nx):
            if h[r * nx + c] > h_zero:
                wet_lo[r] = min(wet_lo[r], c)
                wet_hi[r] = max(wet_hi[r], c)
    cur_h, cur_hu, cur_hv = h, hu, hv
    nxt_h, nxt_hu, nxt_hv = h_work, hu_work, hv_work
    while t < t_target:
        dt_max = stats[ST_DT_LIMIT]
        dt = cfl * dt_max if dt_max < np.inf else t_target - t
        dt_decide = dt
        last = False
        if t + dt >= t_target:
            dt = t_target - t
            last = True
        r0, r1 = _swept_columns(nx, ny, wet_lo, wet_hi, need_lo, need_hi, prev_lo, prev_hi,
                                lo, hi)
        ok = False
        outflow = 0.0
        inv_lim = 0.0
        moving = 0.0
        film = 0.0
        kinetic = 0.0
        clamped = 0
        for attempt in range(MAX_RETRIES):
            t_new = t_target if last else t + dt
            if r1 >= r0:
                if parallel:
                    faces_parallel(nx, ny, x_code, x_frame, x_length, y_code, y_frame, y_length,
                                   density, gamma_z, cur_h, cur_hu, cur_hv, x_flux, y_flux, g,
                                   h_zero, r0, r1, lo, hi)
                    trial_parallel(nx, valid, face_order, x_code, y_code, x_flux, y_flux,
                                   cell_area, gamma_x, gamma_y, gamma_z, curvature, cur_h,
                                   cur_hu, cur_hv, nxt_hu, nxt_hv, flag, law, params, g, h_zero,
                                   dt, dt_decide, r0, r1, lo, hi)
                    final_parallel(nx, ny, valid, face_order, x_code, y_code, x_flux, y_flux,
                                   x_length, y_length, cell_area, cfl_factor, gamma_x, gamma_y,
                                   gamma_z, curvature, cur_h, cur_hu, cur_hv, nxt_h, nxt_hu,
                                   nxt_hv, flag, law, params, g, dirac, h_dry, h_zero, dt, t_new,
                                   peak_h, peak_speed, arrival, last_moved, r0, r1, lo, hi, rows,
                                   wet_lo, wet_hi)
                else:
                    faces_serial(nx, ny, x_code, x_frame, x_length, y_code, y_frame, y_length,
                                 density, gamma_z, cur_h, cur_hu, cur_hv, x_flux, y_flux, g,
                                 h_zero, r0, r1, lo, hi)
                    trial_serial(nx, valid, face_order, x_code, y_code, x_flux, y_flux,
                                 cell_area, gamma_x, gamma_y, gamma_z, curvature, cur_h,
                                 cur_hu, cur_hv, nxt_hu, nxt_hv, flag, law, params, g, h_zero,
                                 dt, dt_decide, r0, r1, lo, hi)
                    final_serial(nx, ny, valid, face_order, x_code, y_code, x_flux, y_flux,
                                 x_length, y_length, cell_area, cfl_factor, gamma_x, gamma_y,
                                 gamma_z, curvature, cur_h, cur_hu, cur_hv, nxt_h, nxt_hu,
                                 nxt_hv, flag, law, params, g, dirac, h_dry, h_zero, dt, t_new,
                                 peak_h, peak_speed, arrival, last_moved, r0, r1, lo, hi, rows,
                                 wet_lo, wet_hi)
            ok = True
            outflow = 0.0
            inv_lim = 0.0
            moving = 0.0
            film = 0.0
            kinetic = 0.0
            clamped = 0
            for r in range(r0, r1 + 1):  # the rows' sums, in row order
                if rows[r, R_OK] == 0.0:
                    ok = False
                outflow += rows[r, R_OUT]
                inv_lim = max(inv_lim, rows[r, R_INV])
                moving += rows[r, R_MOVING]
                film += rows[r, R_FILM]
                kinetic += rows[r, R_KINETIC]
                clamped += int(rows[r, R_CLAMPED])
            if ok:
                break
            dt *= 0.5
            last = False
            stats[ST_RETRIES] += 1
        if not ok:
            status = FAILED
            break
        t = t_target if last else t + dt
        steps += 1
        for r in range(ny):
            prev_lo[r] = need_lo[r]
            prev_hi[r] = need_hi[r]
        cur_h, nxt_h = nxt_h, cur_h
        cur_hu, nxt_hu = nxt_hu, cur_hu
        cur_hv, nxt_hv = nxt_hv, cur_hv
        stats[ST_DT_LIMIT] = _limit(inv_lim)
        stats[ST_MOVING] = moving
        stats[ST_FILM] = film
        stats[ST_KINETIC] = 0.5 * kinetic
        stats[ST_KINETIC_PEAK] = max(stats[ST_KINETIC_PEAK], 0.5 * kinetic)
        stats[ST_CLAMPED] += clamped
        stats[ST_OUTFLOW] += outflow
        stats[ST_DT_MIN] = min(stats[ST_DT_MIN], dt)
        stats[ST_DT_MAX] = max(stats[ST_DT_MAX], dt)
        if stop_volume >= 0.0 and moving < stop_volume:
            status = STOPPED
            break
        if stop_kinetic >= 0.0 and kinetic <= stop_kinetic * (2.0 * stats[ST_KINETIC_PEAK]):
            status = STOPPED
            break
        if stats[ST_STEPS] + steps >= max_steps:
            status = MAX_STEPS
            break
    if steps % 2 == 1:  # the newest state sits in the work buffers
        h[:] = cur_h
        hu[:] = cur_hu
        hv[:] = cur_hv
    stats[ST_TIME] = t
    stats[ST_STEPS] += steps
    return status
