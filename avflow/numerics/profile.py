"""The 1D profile sweep at order 1, in loops that LLVM vectorises.

The same step as :func:`avflow.numerics.kernels.step_profile` (seed eqs. 26-56 on a line:
rectangular fluxes, trial momentum and Coulomb threshold of eqs. 47-49, Dirac faces of
eqs. 51-53, projection of eq. 50, curvature and film rules, walls and open ends), cut in
four passes over contiguous lines, each free of jumps (:mod:`avflow.numerics.vectorize`):

1. per cell, what it emits: ``|u|`` and its outward (+x) and inward (-x) half fluxes;
2. per face, the flux: the half flux of the cell on its left plus that of the cell on its
   right (the two ends: wall or open side, apart);
3. per cell, the trial momentum and the flag of eq. 49;
4. per cell, mass through the faces that keep the rectangular density and the projection;
   the step's sums per cell, added line by line afterwards.

``step_profile`` fused passes 1-3 in one loop carrying the left face from one cell to the
next, which LLVM cannot vectorise. Every value kept is computed with the operations of
``step_profile``: the state and the flags are its bits (tested); the sums
over the line (moving volume, film, kinetic energy) are added in another order and differ
by round-off.
"""

from __future__ import annotations

import math
from collections import namedtuple

from numba import njit

from avflow.numerics.cpu import (DRY, carries, cell_moves, cell_update, dirac_face,
                                 dt_from_inverse, observe_cell, open_mass,
                                 outflow_volume, step_terms, trial_momentum)
from avflow.numerics.cpu import SQRT3, half_fluxes, select_flux_in, select_flux_out, sound_speed
from avflow.numerics.vectorize import (cell_law, friction_law, law_copies, law_kind, law_label,
                                       line_sum, noalias, specialize)
from avflow.terrain.mesh import OUTFLOW, WALL

#: Lines of :func:`step`'s work array, ``(N_WORK, n + 2)``: per cell the half fluxes up
#: (+x) and down, |u|, the face fluxes (n + 1), the trial discharge, and what the sums need
W_UP_H, W_UP_Q, W_DOWN_H, W_DOWN_Q, W_SPEED, W_FLUX_H, W_FLUX_Q = range(7)
W_QX, W_INV, W_KIN, W_MOV, W_FILM = range(7, 12)
N_WORK = 12


@noalias
@njit(error_model="numpy", cache=True)
def _emit(n, h, hu, gamma_z, density, h_zero, g, up_h, up_q, down_h, down_q, speed):
    """Pass 1: per cell, ``|u|`` and the half fluxes of :func:`half_fluxes` towards +x
    (``up``) and -x (``down``), from the thickness it emits (0 at or below h_zero)."""
    h_wet = max(h_zero, 0.0)
    for k in range(n):
        hk = h[k]
        wet = hk > h_wet  # emitting(): h if h > h_zero else 0
        he = hk if wet else 0.0
        hs = hk if wet else 1.0
        g_normal = g * gamma_z[k]
        c = math.sqrt(0.5 * g_normal * hs)  # sound_speed(he, g_normal)
        c = c if wet & (g_normal > 0.0) else 0.0
        u = hu[k] / hs if wet else 0.0
        kk = c * density[k]
        s = SQRT3 * c
        fp_h, fp_q = select_flux_out(he, u, c, s, 0.5 * kk, kk / 3.0)
        fm_h, fm_q = select_flux_in(he, u, c, s, 0.5 * kk, kk / 3.0)
        up_h[k] = fp_h
        up_q[k] = fp_q
        down_h[k] = fm_h
        down_q[k] = fm_q
        speed[k] = abs(u)


@noalias
@njit(error_model="numpy", cache=True)
def _faces(n, up_h, up_q, down_h, down_q, flux_h, flux_q):
    """Pass 2: the inner faces 1..n-1, each the sum of its two half fluxes."""
    for j in range(n - 1):
        i = j + 1
        flux_h[i] = up_h[i - 1] + down_h[i]
        flux_q[i] = up_q[i - 1] + down_q[i]


@njit(error_model="numpy", cache=True)
def _ends(n, h, hu, gamma_z, density, h_zero, g, left, right, up_h, up_q, down_h, down_q,
          flux_h, flux_q):
    """The two end faces, as :func:`step_profile`: a wall mirrors the cell (no mass, twice
    the pressure); an open side lets out what leaves and nothing in."""
    if left == WALL:
        flux_h[0] = 0.0
        flux_q[0] = 2.0 * down_q[0]
    else:
        h0 = h[0] if h[0] > h_zero else 0.0
        c0 = sound_speed(h0, g * gamma_z[0])
        u0 = hu[0] / h0 if h0 > 0.0 else 0.0
        gp_h, gp_q, _, _ = half_fluxes(h0, min(u0, 0.0), c0, c0 * density[0])
        flux_h[0] = open_mass(-(gp_h + down_h[0])) * -1.0
        flux_q[0] = gp_q + down_q[0]
    m = n - 1
    if right == WALL:
        flux_h[n] = 0.0
        flux_q[n] = 2.0 * up_q[m]
    else:
        hm = h[m] if h[m] > h_zero else 0.0
        um = hu[m] / hm if hm > 0.0 else 0.0
        cm = sound_speed(hm, g * gamma_z[m])
        _, _, gm_h, gm_q = half_fluxes(hm, max(um, 0.0), cm, cm * density[m])
        flux_h[n] = open_mass(up_h[m] + gm_h)
        flux_q[n] = up_q[m] + gm_q



def _trial(n, h, hu, gamma_x, gamma_z, kappa, speed, flux_h, flux_q, law, params, g, h_zero,
           dx, dt, dt_decide, qx_out, flag_out):
    """Pass 3: per cell, the trial momentum of eq. 47 and the flag of eq. 49
    (``flag_out[k + 1]``: the flag line is padded by one cell at each end)."""
    lw = friction_law(law)  # a constant in the copies of by_law
    p0, p1, p2, p3 = params[0, 0], params[0, 1], params[0, 2], params[0, 3]
    p4, p5, p6, p7 = params[0, 4], params[0, 5], params[0, 6], params[0, 7]
    for k in range(n):
        u = speed[k]
        fl_h, fr_h, fl_q, fr_q = flux_h[k], flux_h[k + 1], flux_q[k], flux_q[k + 1]
        pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(lw, params, k, p0, p1, p2, p3,
                                                          p4, p5, p6, p7)
        qx, _, fk = trial_momentum(h[k], h_zero, u, hu[k], 0.0, (fl_h - fr_h) / dx,
                                    (fl_q - fr_q) / dx, 0.0, dt, dt_decide, gamma_x[k], 0.0,
                                    gamma_z[k], kappa[k] * (u * u), lw, pc0, pc1, pc2, pc3,
                                    pc4, pc5, pc6, pc7, g, False)
        qx_out[k] = qx
        flag_out[k + 1] = fk


def _final(n, h, gamma_x, gamma_z, kappa, cfl_factor, speed, flux_h, flux_q, q_trial, pflag,
           law, params, g, dirac, h_dry, h_zero, dx, dt, h_new, hu_new, hv_new, flag, t_inv,
           t_kin, t_mov, t_film):
    """Pass 4: per cell, the new thickness (Dirac faces carry nothing), the momentum of
    eq. 50, what the sums need.
    Returns ``(cells below 0, clamped)``; a cell below 0 makes the step be redone,
    whatever it wrote."""
    lw = friction_law(law)
    p0, p1, p2, p3 = params[0, 0], params[0, 1], params[0, 2], params[0, 3]
    p4, p5, p6, p7 = params[0, 4], params[0, 5], params[0, 6], params[0, 7]
    n_bad = 0
    clamped = 0
    for k in range(n):
        fk = pflag[k + 1]
        f_l = pflag[k]
        f_r = pflag[k + 2]
        h_old = h[k]
        gx, gz = gamma_x[k], gamma_z[k]
        speed_n = speed[k]
        fl, fr, ql, qr = flux_h[k], flux_h[k + 1], flux_q[k], flux_q[k + 1]
        q = q_trial[k]
        kap = kappa[k]
        cfl_k = cfl_factor[k]
        dirac_l = dirac_face(dirac, fk, f_l)  # the ends' ghosts share the flag
        dirac_r = dirac_face(dirac, fk, f_r)
        fl = 0.0 if dirac_l else fl
        fr = 0.0 if dirac_r else fr
        # a dry cell takes momentum only with mass: a Dirac face carries neither, not even
        # its pressure (zero temperature, eq. 53); beside one, its q~ is formed anew
        ql = 0.0 if dirac_l else ql
        qr = 0.0 if dirac_r else qr
        form_dry = (fk == DRY) & (dirac_l | dirac_r)
        pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(lw, params, k, p0, p1, p2, p3,
                                                          p4, p5, p6, p7)
        hn, qx, _, cl = cell_update(form_dry, fk, h_old, fl - fr, (ql - qr) if form_dry else q,
                                    0.0, dx, dt, gx, 0.0, gz, kap * (speed_n * speed_n), speed_n,
                                    lw, pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7, g, h_zero, False,
                                    True)
        n_bad += 1 if hn < 0.0 else 0
        h_new[k] = hn
        hu_new[k] = qx
        hv_new[k] = 0.0
        flag[k] = fk
        clamped += cl
        speed_k, inv_k = observe_cell(hn, abs(qx), cfl_k, gz, g)
        # the moving rule with the transport max(|fl|, |fr|)
        moves = cell_moves(speed_k, speed_n, carries(max(abs(fl), abs(fr)), hn, speed_n, 1.0))
        t_inv[k] = inv_k
        t_kin[k], t_mov[k], t_film[k] = step_terms(hn, dx, speed_k, moves, h_dry)
    return n_bad, clamped


#: Passes 3 and 4 per law kind (:func:`~avflow.numerics.vectorize.law_copies`)
TRIAL = law_copies(_trial)
FINAL = law_copies(_final)

#: Placeholders of :func:`_step`'s copies (:data:`STEP`): their law's passes 3 and 4
trial_pass = final_pass = None


#: What the order-1 profile step reads of its line: the end conditions, the uniform
#: ``dx``, the per-cell factors, the curvature line (``curvature[:, 0]``, contiguous) and
#: its work lines and flags (:data:`N_WORK` x ``n + 2``, ``n + 2``), made once a time loop
ProfileLine = namedtuple("ProfileLine", "left right dx cfl_factor density gamma_x gamma_z "
                         "kappa work pflag")


def _step(line, physics, cur, nxt, flag, when):
    """One order-1 step on a profile of uniform ``dx`` with end conditions ``left`` and
    ``right`` (WALL or OUTFLOW): :func:`~avflow.numerics.kernels.step_profile`'s numbers.
    ``kappa``: the curvature line (``curvature[:, 0]``, contiguous); ``work``: float lines
    ``(N_WORK, n + 2)``, ``pflag``: ``n + 2`` flags (uint8), allocated once per time loop.
    Returns ``(ok, outflow, dt_limit, moving, film, clamped, kinetic)``."""
    left, right, dx, cfl_factor = line.left, line.right, line.dx, line.cfl_factor
    density, gamma_x, gamma_z, kappa = line.density, line.gamma_x, line.gamma_z, line.kappa
    h, hu, h_new, hu_new, hv_new, law = cur.h, cur.hu, nxt.h, nxt.hu, nxt.hv, physics.law
    params, g, dirac, h_dry = physics.params, physics.g, physics.dirac, physics.h_dry
    h_zero, dt, dt_decide = physics.h_zero, when.dt, when.dt_decide
    work, pflag = line.work, line.pflag
    n = h.size
    up_h, up_q, down_h, down_q = work[W_UP_H], work[W_UP_Q], work[W_DOWN_H], work[W_DOWN_Q]
    speed, flux_h, flux_q = work[W_SPEED], work[W_FLUX_H], work[W_FLUX_Q]
    q_trial, t_inv, t_kin = work[W_QX], work[W_INV], work[W_KIN]
    t_mov, t_film = work[W_MOV], work[W_FILM]
    _emit(n, h, hu, gamma_z, density, h_zero, g, up_h, up_q, down_h, down_q, speed)
    _faces(n, up_h, up_q, down_h, down_q, flux_h, flux_q)
    _ends(n, h, hu, gamma_z, density, h_zero, g, left, right, up_h, up_q, down_h, down_q,
          flux_h, flux_q)
    # passes 3 and 4 of the law: globals of each copy of this function (STEP), so Numba
    # compiles only its law's (written as calls: functions held in variables are Numba's
    # experimental first-class functions)
    trial_pass(n, h, hu, gamma_x, gamma_z, kappa, speed, flux_h, flux_q, law, params, g, h_zero,
               dx, dt, dt_decide, q_trial, pflag)
    pflag[0] = pflag[1]  # the ends' ghosts share their cell's flag
    pflag[n + 1] = pflag[n]
    n_bad, clamped = final_pass(
        n, h, gamma_x, gamma_z, kappa, cfl_factor, speed, flux_h, flux_q, q_trial, pflag, law,
        params, g, dirac, h_dry, h_zero, dx, dt, h_new, hu_new, hv_new, flag, t_inv, t_kin,
        t_mov, t_film)
    if n_bad > 0:
        return False, 0.0, 0.0, 0.0, 0.0, 0, 0.0
    # what left through open ends (the fluxes of faces that are not Dirac)
    outflow = 0.0
    if left == OUTFLOW:
        fk = pflag[1]
        if not dirac_face(dirac, fk, fk):
            outflow += outflow_volume(-flux_h[0], dt)
    if right == OUTFLOW:
        fk = pflag[n]
        if not dirac_face(dirac, fk, fk):
            outflow += outflow_volume(flux_h[n], dt)
    inv_lim = 0.0
    for k in range(n):
        inv_lim = max(inv_lim, t_inv[k])
    return (True, outflow, dt_from_inverse(inv_lim), line_sum(t_mov, 0, n - 1),
            line_sum(t_film, 0, n - 1), clamped, line_sum(t_kin, 0, n - 1))


#: :func:`_step` per law kind (:func:`~avflow.numerics.vectorize.law_kind`), each calling
#: its law's passes 3 and 4
STEP = {kind: specialize(_step, "_" + law_label(kind), trial_pass=TRIAL[kind],
                         final_pass=FINAL[kind])
        for kind in TRIAL}


def step(line, physics, cur, nxt, flag, when):
    """:func:`_step` in the copy for the law (from Python; the time loop calls its law's
    copy itself)."""
    return STEP[law_kind(physics.law)](line, physics, cur, nxt, flag, when)
