"""Numba kernels of one time step and of the time loop (seed section 3, eqs. 26-56).

Pure numerics: arrays and scalars in, arrays out; nothing here knows of YAML, xarray or dask.

One step from ``U^n`` to ``U^{n+1}`` (state ``h``, discharge ``(hu, hv)`` in the bed's tangent
basis) runs in two sweeps:

1. **Rectangular fluxes and trial momentum.** Every face gets the kinetic flux of eq. 38 with
   the rectangular density (eq. 54). Per cell the trial thickness ``h*`` (eq. 42) and the
   trial discharge without friction ``q~ = q^n - sum alpha F_q + g h* gamma_t dt`` (eq. 47)
   are formed, and the Coulomb threshold of eq. 49 is tested: a wet cell with
   ``|q~| < tau dt`` (``tau = mu g cos(theta) h``, plus the curvature term of eqs. 61-62) is
   *under the threshold*. A cell dry at time n is also at zero temperature: it has no
   particles of its own.
2. **Mass with the Dirac switch, momentum by projection.** A face whose two cells are both
   under the threshold (or dry) carries the Dirac flux of eq. 53 with the implicit velocity
   ``u^{n+1} = 0``, i.e. no mass at all (section 3.3, Figs. 4-5); every other face keeps its
   rectangular flux. Mass is accumulated afresh from those face fluxes, so a cell whose faces
   are all Dirac gets exactly ``h^{n+1} = h^n`` (bit for bit) and mass is conserved to
   round-off (each face flux leaves one cell and enters the other). Cells under the threshold
   get ``q = 0`` (eq. 56); the others the projection of eq. 50
   ``q = (|q~| - tau dt)^+ q~/|q~|``, then the implicit drag of the law (Voellmy) divides it.
   Friction can stop a cell within a step and never reverses it.

The time step is ``dt = cfl * min_i 2 A_i / (P_i (|u_i| + sqrt(3) c_i))`` with ``P_i`` the
cell perimeter: eq. 41 with the factor 2 that makes it the classic ``dx / (|u| + sqrt(3) c)``
on a line. A step that would still give h < 0 (it cannot under this condition; the check
guards round-off at cfl = 1 on distorted cells) is redone with half the time step.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .kinetic import SQRT3, half_fluxes, sound_speed
from .mesh import OUTFLOW, WALL
from .rheology import friction

# Per-cell flag of sweep 1 (kept for output): which density the cell takes in sweep 2.
FLOWING = 0  #: above the Coulomb threshold: rectangular density
UNDER_THRESHOLD = 1  #: wet and under the threshold: Dirac density, q = 0 (eqs. 51, 56)
DRY = 2  #: dry at time n: zero temperature as well, momentum from the projection

# Status returned by advance()
REACHED_TARGET = 0
STOPPED = 1
MAX_STEPS = 2
FAILED = 3

MAX_RETRIES = 12

# Slots of the float64 ``stats`` vector shared between advance() and its caller.
ST_TIME = 0
ST_DT_LIMIT = 1  #: dt allowed by the CFL condition with cfl = 1, for the next step
ST_STEPS = 2
ST_DT_MIN = 3
ST_DT_MAX = 4
ST_MOVING = 5  #: volume of cells with u != 0 and h > h_dry after the last step
ST_FILM = 6  #: volume of cells with u != 0 and 0 < h <= h_dry (a vanishing film)
ST_OUTFLOW = 7  #: cumulative volume that left through open boundaries
ST_CLAMPED = 8  #: cumulative count of cell-steps whose normal acceleration was clamped at 0
ST_RETRIES = 9  #: cumulative count of halved steps
N_STATS = 10


@njit(cache=True, inline="always")
def _normal_accel(g_normal, curvature, speed2):
    """Bed-normal acceleration g cos(theta) + u^2 / R (eqs. 61-62), clamped at 0 on convex beds."""
    n = g_normal + curvature * speed2
    if n < 0.0:
        return 0.0, 1
    return n, 0


@njit(cache=True, inline="always")
def _project(qx, qy, tau, drag, dt):
    """Projection of the trial discharge on the admissible Coulomb set, eq. 50, then drag."""
    norm = math.sqrt(qx * qx + qy * qy)
    excess = norm - tau * dt
    if excess <= 0.0 or norm <= 0.0:
        return 0.0, 0.0
    scale = excess / (norm * (1.0 + drag * dt))
    return qx * scale, qy * scale


@njit(cache=True)
def dt_limit(cell_area, cell_perimeter, gamma_z, h, hu, hv, g):
    """Largest stable time step (cfl = 1) of a state: min 2 A / (P (|u| + sqrt(3) c)), eq. 41."""
    best = np.inf
    for i in range(h.size):
        if h[i] > 0.0:
            speed = math.sqrt(hu[i] * hu[i] + hv[i] * hv[i]) / h[i]
            wave = speed + SQRT3 * sound_speed(h[i], g * gamma_z[i])
            if wave > 0.0:
                lim = 2.0 * cell_area[i] / (cell_perimeter[i] * wave)
                if lim < best:
                    best = lim
    return best


@njit(cache=True)
def _finish_cell(i, h_new, hu_new, hv_new, flag, h, hu, hv, dt, area, perimeter,
                 gamma_z, curvature, law, params, g, h_dry, peak_h, peak_speed, acc):
    """Sweep-2 update of one cell once its new thickness is known; shared by both sweeps.

    ``acc`` accumulates [dt_limit, moving, film, clamped] over the cells of the step.
    """
    if flag[i] == UNDER_THRESHOLD or h_new[i] <= 0.0:
        hu_new[i] = 0.0  # eq. 56: q = 0 under the threshold
        hv_new[i] = 0.0
    else:
        speed_n = 0.0
        if h[i] > 0.0:
            speed_n = math.sqrt(hu[i] * hu[i] + hv[i] * hv[i]) / h[i]
        accel, clamped = _normal_accel(g * gamma_z[i], curvature[i], speed_n * speed_n)
        acc[3] += clamped
        tau, drag = friction(law, params, h_new[i], speed_n, accel, g)
        hu_new[i], hv_new[i] = _project(hu_new[i], hv_new[i], tau, drag, dt)
    hn = h_new[i]
    if hn > 0.0:
        speed = math.sqrt(hu_new[i] * hu_new[i] + hv_new[i] * hv_new[i]) / hn
        if hn > peak_h[i]:
            peak_h[i] = hn
        if speed > peak_speed[i]:
            peak_speed[i] = speed
        wave = speed + SQRT3 * sound_speed(hn, g * gamma_z[i])
        if wave > 0.0:
            lim = 2.0 * area[i] / (perimeter[i] * wave)
            if lim < acc[0]:
                acc[0] = lim
        if speed > 0.0:
            if hn > h_dry:
                acc[1] += hn * area[i]
            else:
                acc[2] += hn * area[i]


@njit(cache=True)
def _trial_cell(i, h_star, hu_t, hv_t, h, hu, hv, dt, gamma_x, gamma_y, gamma_z, curvature,
                law, params, g, flag):
    """Sweep-1 closure of one cell: add gravity to q~ (eq. 47) and test the threshold (eq. 49).

    ``hu_t, hv_t`` hold the discharge after the fluxes and receive q~.
    """
    hs = h_star
    qx = hu_t + g * hs * gamma_x[i] * dt
    qy = hv_t + g * hs * gamma_y[i] * dt
    if h[i] <= 0.0:
        f = DRY
    else:
        speed_n = math.sqrt(hu[i] * hu[i] + hv[i] * hv[i]) / h[i]
        accel, _ = _normal_accel(g * gamma_z[i], curvature[i], speed_n * speed_n)
        tau, _ = friction(law, params, hs, speed_n, accel, g)
        f = UNDER_THRESHOLD if math.sqrt(qx * qx + qy * qy) < tau * dt else FLOWING
    flag[i] = f
    return qx, qy


@njit(cache=True, inline="always")
def _dirac_face(flag, i, j, dirac):
    """True when the face between i and j carries the Dirac (zero) mass flux, eqs. 51-53."""
    if not dirac:
        return False
    if flag[i] == FLOWING:
        return False
    if j >= 0:
        return flag[j] != FLOWING
    return True  # a boundary ghost shares the state of its cell


@njit(cache=True)
def step_profile(face_cells, cell_area, cell_perimeter, gamma_x, gamma_y, gamma_z, curvature,
                 h, hu, hv, h_new, hu_new, hv_new, flux_h, flag,
                 law, params, g, dirac, h_dry, dt, peak_h, peak_speed, acc):
    """One step on a profile (faces in line order, uniform dx): the fast structured sweep.

    Same arithmetic as :func:`step_faces`, with the face loop fused into the cell loops.
    ``flux_h[k]`` is the mass flux (m^2/s) through face k towards +x. Returns
    ``(ok, outflow_volume)``; ok is False when a thickness would become negative.
    """
    n = h.size
    dx = cell_area[0]
    r = dt / dx
    left = face_cells[0, 1]
    right = face_cells[n, 1]

    # --- sweep 1: fluxes (every normal along +x), trial state, threshold flags
    c0 = sound_speed(h[0], g * gamma_z[0])
    u0 = hu[0] / h[0] if h[0] > 0.0 else 0.0
    fp_h, fp_q, fm_h, fm_q = half_fluxes(h[0], u0, c0)
    if left == WALL:
        fl_h = 0.0
        fl_q = 2.0 * fm_q
    else:  # open: ghost copies cell 0 but cannot push material in
        gp_h, gp_q, _, _ = half_fluxes(h[0], min(u0, 0.0), c0)
        fl_h = gp_h + fm_h
        fl_q = gp_q + fm_q
    flux_h[0] = fl_h
    for i in range(1, n + 1):
        if i < n:
            ci = sound_speed(h[i], g * gamma_z[i])
            ui = hu[i] / h[i] if h[i] > 0.0 else 0.0
            np_h, np_q, nm_h, nm_q = half_fluxes(h[i], ui, ci)
            fr_h = fp_h + nm_h
            fr_q = fp_q + nm_q
        else:
            um = hu[n - 1] / h[n - 1] if h[n - 1] > 0.0 else 0.0
            if right == WALL:
                fr_h = 0.0
                fr_q = 2.0 * fp_q
            else:
                cm = sound_speed(h[n - 1], g * gamma_z[n - 1])
                _, _, gm_h, gm_q = half_fluxes(h[n - 1], max(um, 0.0), cm)
                fr_h = fp_h + gm_h
                fr_q = fp_q + gm_q
            np_h = np_q = nm_h = nm_q = 0.0
        flux_h[i] = fr_h
        k = i - 1  # cell k is complete: faces k (left) and k + 1 (right)
        h_star = h[k] + r * (fl_h - fr_h)
        qx, qy = _trial_cell(k, h_star, hu[k] + r * (fl_q - fr_q), 0.0, h, hu, hv, dt,
                             gamma_x, gamma_y, gamma_z, curvature, law, params, g, flag)
        hu_new[k] = qx
        hv_new[k] = 0.0
        fl_h = fr_h
        fl_q = fr_q
        fp_h, fp_q = np_h, np_q

    # --- sweep 2: mass with the Dirac switch, projection
    outflow = 0.0
    for k in range(n):
        jl = k - 1 if k > 0 else left
        jr = k + 1 if k < n - 1 else right
        fl = 0.0 if _dirac_face(flag, k, jl, dirac) else flux_h[k]
        fr = 0.0 if _dirac_face(flag, k, jr, dirac) else flux_h[k + 1]
        if fl == 0.0 and fr == 0.0:
            hn = h[k]  # no face carries mass: the thickness is untouched, bit for bit
        else:
            hn = h[k] + r * (fl - fr)
        if hn < 0.0:
            return False, 0.0
        h_new[k] = hn
        if k == 0 and left == OUTFLOW:
            outflow -= fl * dt
        if k == n - 1 and right == OUTFLOW:
            outflow += fr * dt
        _finish_cell(k, h_new, hu_new, hv_new, flag, h, hu, hv, dt, cell_area, cell_perimeter,
                     gamma_z, curvature, law, params, g, h_dry, peak_h, peak_speed, acc)
    return True, outflow


@njit(cache=True)
def step_faces(face_cells, face_normal, face_length, cell_area, cell_perimeter,
               gamma_x, gamma_y, gamma_z, curvature,
               h, hu, hv, h_new, hu_new, hv_new, flux_h, flag,
               law, params, g, dirac, h_dry, dt, peak_h, peak_speed, acc):
    """One step on any mesh (grid, triangles, profile): loops over faces, then cells.

    ``h_new`` first accumulates the trial mass rate, ``hu_new, hv_new`` the momentum rate.
    Normal and tangential components are taken in each face's frame (rotational invariance):
    the normal part uses the kinetic flux, the tangential velocity is carried upwind with the
    mass. ``flux_h[f]`` is ``L_f`` times the mass flux through face f along its normal.
    """
    n = h.size
    for i in range(n):
        h_new[i] = 0.0
        hu_new[i] = 0.0
        hv_new[i] = 0.0

    # --- sweep 1a: rectangular fluxes
    for f in range(face_cells.shape[0]):
        i = face_cells[f, 0]
        j = face_cells[f, 1]
        nx = face_normal[f, 0]
        ny = face_normal[f, 1]
        length = face_length[f]
        hi = h[i]
        uni = 0.0
        uti = 0.0
        if hi > 0.0:
            uni = (hu[i] * nx + hv[i] * ny) / hi
            uti = (-hu[i] * ny + hv[i] * nx) / hi
        ci = sound_speed(hi, g * gamma_z[i])
        fp_h, fp_q, fm_h, fm_q = half_fluxes(hi, uni, ci)
        if j >= 0:
            hj = h[j]
            unj = 0.0
            utj = 0.0
            if hj > 0.0:
                unj = (hu[j] * nx + hv[j] * ny) / hj
                utj = (-hu[j] * ny + hv[j] * nx) / hj
            cj = sound_speed(hj, g * gamma_z[j])
            _, _, gm_h, gm_q = half_fluxes(hj, unj, cj)
        elif j == WALL:  # mirror ghost: (h, -u_n, u_t)
            gm_h = -fp_h
            gm_q = fp_q
            utj = uti
        else:  # open boundary: ghost copies the cell but cannot push material in
            _, _, gm_h, gm_q = half_fluxes(hi, max(uni, 0.0), ci)
            utj = uti
        f_h = fp_h + gm_h
        f_n = fp_q + gm_q
        f_t = uti * fp_h + utj * gm_h
        fx = (f_n * nx - f_t * ny) * length
        fy = (f_n * ny + f_t * nx) * length
        flux_h[f] = f_h * length
        h_new[i] -= flux_h[f]
        hu_new[i] -= fx
        hv_new[i] -= fy
        if j >= 0:
            h_new[j] += flux_h[f]
            hu_new[j] += fx
            hv_new[j] += fy

    # --- sweep 1b: trial state and threshold flags
    for i in range(n):
        r = dt / cell_area[i]
        h_star = h[i] + r * h_new[i]
        qx, qy = _trial_cell(i, h_star, hu[i] + r * hu_new[i], hv[i] + r * hv_new[i],
                             h, hu, hv, dt, gamma_x, gamma_y, gamma_z, curvature,
                             law, params, g, flag)
        hu_new[i] = qx
        hv_new[i] = qy
        h_new[i] = 0.0

    # --- sweep 2a: mass through the faces that keep the rectangular density
    outflow = 0.0
    for f in range(face_cells.shape[0]):
        i = face_cells[f, 0]
        j = face_cells[f, 1]
        if _dirac_face(flag, i, j, dirac):
            continue
        h_new[i] -= flux_h[f]
        if j >= 0:
            h_new[j] += flux_h[f]
        elif j == OUTFLOW:
            outflow += flux_h[f] * dt

    # --- sweep 2b: new thickness, projection, observers
    for i in range(n):
        rate = h_new[i]
        hn = h[i] if rate == 0.0 else h[i] + dt / cell_area[i] * rate
        if hn < 0.0:
            return False, 0.0
        h_new[i] = hn
        _finish_cell(i, h_new, hu_new, hv_new, flag, h, hu, hv, dt, cell_area, cell_perimeter,
                     gamma_z, curvature, law, params, g, h_dry, peak_h, peak_speed, acc)
    return True, outflow


@njit(cache=True)
def advance(structured, face_cells, face_normal, face_length, cell_area, cell_perimeter,
            gamma_x, gamma_y, gamma_z, curvature,
            h, hu, hv, h_work, hu_work, hv_work, flux_h, flag,
            law, params, g, dirac, h_dry, cfl, t_target, max_steps, stop_volume,
            peak_h, peak_speed, stats):
    """Advance ``(h, hu, hv)`` in place until ``t_target``, a stop, or ``max_steps``.

    ``stats`` (see the ``ST_*`` slots) carries the time, the CFL limit and the counters from
    one call to the next. The run is *stopped* once the moving volume (cells with u != 0 and
    h > h_dry) falls below ``stop_volume``; a negative ``stop_volume`` never stops.
    Returns a status code: REACHED_TARGET, STOPPED, MAX_STEPS or FAILED.
    """
    t = stats[ST_TIME]
    cur_h, cur_hu, cur_hv = h, hu, hv
    nxt_h, nxt_hu, nxt_hv = h_work, hu_work, hv_work
    acc = np.zeros(4)
    status = REACHED_TARGET
    steps = 0
    while t < t_target:
        dt_max = stats[ST_DT_LIMIT]
        dt = cfl * dt_max if dt_max < np.inf else t_target - t
        last = False
        if t + dt >= t_target:
            dt = t_target - t
            last = True
        ok = False
        for _ in range(MAX_RETRIES):
            acc[0] = np.inf
            acc[1] = 0.0
            acc[2] = 0.0
            acc[3] = 0.0
            if structured:
                ok, out = step_profile(face_cells, cell_area, cell_perimeter, gamma_x, gamma_y,
                                       gamma_z, curvature, cur_h, cur_hu, cur_hv, nxt_h, nxt_hu,
                                       nxt_hv, flux_h, flag, law, params, g, dirac, h_dry, dt,
                                       peak_h, peak_speed, acc)
            else:
                ok, out = step_faces(face_cells, face_normal, face_length, cell_area,
                                     cell_perimeter, gamma_x, gamma_y, gamma_z, curvature,
                                     cur_h, cur_hu, cur_hv, nxt_h, nxt_hu, nxt_hv, flux_h, flag,
                                     law, params, g, dirac, h_dry, dt, peak_h, peak_speed, acc)
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
        cur_h, nxt_h = nxt_h, cur_h
        cur_hu, nxt_hu = nxt_hu, cur_hu
        cur_hv, nxt_hv = nxt_hv, cur_hv
        stats[ST_DT_LIMIT] = acc[0]
        stats[ST_MOVING] = acc[1]
        stats[ST_FILM] = acc[2]
        stats[ST_CLAMPED] += acc[3]
        stats[ST_OUTFLOW] += out
        if dt < stats[ST_DT_MIN]:
            stats[ST_DT_MIN] = dt
        if dt > stats[ST_DT_MAX]:
            stats[ST_DT_MAX] = dt
        if stop_volume >= 0.0 and acc[1] < stop_volume:
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
