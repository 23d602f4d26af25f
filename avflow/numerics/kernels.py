"""Numba kernels of one time step and of the time loop (seed section 3, eqs. 26-56).

Pure numerics: arrays and scalars in, arrays out; nothing here knows of YAML, xarray or dask.

One step from ``U^n`` to ``U^{n+1}`` (state ``h``, discharge ``(hu, hv)`` in the bed's tangent
basis) runs in two sweeps:

1. **Rectangular fluxes and trial momentum.** Every face gets the kinetic flux of eq. 38 with
   the rectangular density (eq. 54). Per cell the trial thickness ``h*`` (eq. 42) and the
   trial discharge without friction ``q~ = q^n - sum alpha F_q + g h* gamma_t dt`` (eq. 47)
   are formed, and the Coulomb threshold of eq. 49 is tested: a wet cell with
   ``|q~| < tau dt`` (``tau = mu h (g cos(theta) + u.K.u)``, the curvature term of eqs. 61-62) is
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

from avflow.numerics.kinetic import (SQRT3, half_flux_in, half_flux_out, half_fluxes,
                                     sound_speed)
from avflow.numerics.reconstruction import reconstruct_cells, reconstruct_profile
from avflow.terrain.mesh import OUTFLOW, WALL
from avflow.numerics.rheology import friction
from avflow.numerics.vectorize import law_kind, law_label, specialize

# Per-cell flag of sweep 1 (kept for output): which density the cell takes in sweep 2.
FLOWING = 0  #: above the Coulomb threshold: rectangular density
UNDER_THRESHOLD = 1  #: wet and under the threshold: Dirac density, q = 0 (eqs. 51, 56)
DRY = 2  #: dry at time n: zero temperature as well, momentum from the projection

# Status returned by the time loop (time_loop)
REACHED_TARGET = 0
STOPPED = 1
MAX_STEPS = 2
FAILED = 3

MAX_RETRIES = 12
#: Order 2 marks its lists with distinct stamps: stage 1, then stage 2 and the union of
#: both for every attempt of a step (a halved step lists again).
STAMPS_PER_STEP = 2 * MAX_RETRIES + 1

#: A cell counts as moving when u != 0 and one of its faces carries a mass flux above this
#: fraction of h |u|. A kinetic scheme can hold a cell at a steady u != 0 whose face fluxes
#: balance to round-off (the "fluid-like zone" pinned behind a deposit, seed section 6.4):
#: such a cell transports nothing and must not keep a run alive.
TRANSPORT_EPS = 1e-9

# Slots of the float64 ``stats`` vector shared between the time loop and its caller.
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
ST_KINETIC = 10  #: kinetic energy / density, sum of h A |u|^2 / 2 (m^5 s^-2), after the last step
ST_KINETIC_PEAK = 11  #: its largest value so far
ST_FALLBACK = 12  #: cumulative count of cell-steps where order 2 fell back to order 1
N_STATS = 13


@njit(error_model="numpy", cache=True, inline="always")
def _normal_accel(g_normal, centripetal):
    """Bed-normal acceleration ``g cos(theta) + u.K.u`` (eqs. 61-62: ``u^2 / R`` on a profile),
    clamped at 0 where a convex bed would lift the material off (counted: returns 1)."""
    n = g_normal + centripetal
    if n < 0.0:
        return 0.0, 1
    return n, 0


@njit(error_model="numpy", cache=True, inline="always")
def _centripetal(curvature, i, h, hu, hv):
    """``u.K.u`` (m/s^2) of cell i at time n: ``curvature[i] = (K11, K12, K22)`` in its basis."""
    if h <= 0.0:
        return 0.0
    u1 = hu / h
    u2 = hv / h
    return curvature[i, 0] * u1 * u1 + 2.0 * curvature[i, 1] * u1 * u2 + curvature[i, 2] * u2 * u2


@njit(error_model="numpy", cache=True, inline="always")
def _project(qx, qy, tau, drag, dt):
    """Projection of the trial discharge on the admissible Coulomb set, eq. 50, then drag."""
    if qy == 0.0:  # along a line: no norm to take, no division without drag
        excess = abs(qx) - tau * dt
        if excess <= 0.0:
            return 0.0, 0.0
        if drag > 0.0:
            excess /= 1.0 + drag * dt
        return math.copysign(excess, qx), 0.0
    norm = math.sqrt(qx * qx + qy * qy)
    excess = norm - tau * dt
    if excess <= 0.0 or norm <= 0.0:
        return 0.0, 0.0
    scale = excess / (norm * (1.0 + drag * dt))
    return qx * scale, qy * scale


@njit(error_model="numpy", cache=True, inline="always")
def _limit(inv_lim):
    """The CFL limit (s) from the largest inverse limit of the cells; inf when all is still."""
    return 1.0 / inv_lim if inv_lim > 0.0 else np.inf


@njit(error_model="numpy", cache=True)
def dt_limit(cfl_factor, gamma_z, h, hu, hv, g):
    """Largest stable time step (cfl = 1) of a state: min 2 A / (P (|u| + sqrt(3) c)), eq. 41."""
    inv_lim = 0.0
    for i in range(h.size):
        speed, inv_i = _observe(h[i], math.sqrt(hu[i] * hu[i] + hv[i] * hv[i]), cfl_factor[i],
                                gamma_z[i], g)
        inv_lim = max(inv_lim, inv_i)
    return _limit(inv_lim)


@njit(error_model="numpy", cache=True, inline="always")
def _trial_momentum(h_old, h_zero, speed_n, hu_old, hv_old, rate_h, rate_x, rate_y, dt,
                    dt_decide, gx, gy, gz, centripetal, law, p0, p1, p2, p3, p4, p5, p6, p7, g,
                    explicit):
    """Sweep-1 closure of one cell: q~ of eq. 47 and the threshold test of eq. 49.

    Gravity acts on ``h*``, the thickness after the fluxes (eq. 47), or with ``explicit``
    (a Runge-Kutta stage of order 2) on the stage's own ``h`` when it is wet: Heun's average
    of two stages is second order only when each stage is an explicit Euler step. (A cell
    dry at the stage's start keeps ``h*``, as friction does: a front is first order.)

    ``rate_*``: the flux divergences (mass m/s, momentum m^2/s^2). The trial discharge q~
    (returned for the projection) uses the step ``dt``; the threshold is tested with
    ``dt_decide``, the CFL step of the state, so that the decision depends on the state alone
    and a deposit at rest stays at rest when a step is shortened to land on an output time.
    Returns ``(q~x, q~y, flag)``.
    """
    h_star = h_old if explicit and h_old > h_zero else h_old + dt * rate_h
    qx = hu_old + dt * (rate_x + g * h_star * gx)
    qy = hv_old + dt * (rate_y + g * h_star * gy)
    if h_old <= h_zero:
        return qx, qy, DRY
    if dt_decide == dt and not explicit:  # the same numbers: not computed twice
        hd, qdx, qdy = h_star, qx, qy
    else:
        hd = h_old + dt_decide * rate_h
        qdx = hu_old + dt_decide * (rate_x + g * hd * gx)
        qdy = hv_old + dt_decide * (rate_y + g * hd * gy)
    accel, _ = _normal_accel(g * gz, centripetal)
    tau, _ = friction(law, p0, p1, p2, p3, p4, p5, p6, p7, hd, speed_n, accel, g)
    limit = tau * dt_decide
    if qdx * qdx + qdy * qdy < limit * limit:
        return qx, qy, UNDER_THRESHOLD
    return qx, qy, FLOWING


@njit(error_model="numpy", cache=True, inline="always")
def _final_momentum(flag, speed_n, h_new, h_zero, qx, qy, dt, gz, centripetal, law, p0, p1, p2, p3,
                    p4, p5, p6, p7, g, h_old, explicit):
    """Sweep-2 momentum of one cell: q = 0 under the threshold (eq. 56), else eq. 50.

    The friction is linearised at time n (speed of ``U^n``), with the new thickness (with
    ``explicit``, a Runge-Kutta stage, with the stage's own thickness when wet, as gravity
    in :func:`_trial_momentum`). A cell
    left with ``h <= h_zero`` holds a round-off residue of fluxes that nearly emptied it (on
    real DEMs 1e-28 m at 2 km/s): its momentum is as uncertain as its mass is negligible,
    so it is set to zero; the mass stays (conservation is untouched).
    Returns ``(qx, qy, clamped)``; clamped is 1 when the normal acceleration hit 0.
    """
    if flag == UNDER_THRESHOLD or h_new <= h_zero:
        return 0.0, 0.0, 0
    accel, clamped = _normal_accel(g * gz, centripetal)
    h_fric = h_old if explicit and h_old > h_zero else h_new
    tau, drag = friction(law, p0, p1, p2, p3, p4, p5, p6, p7, h_fric, speed_n, accel, g)
    qx, qy = _project(qx, qy, tau, drag, dt)
    return qx, qy, clamped


@njit(error_model="numpy", cache=True, inline="always")
def _emitting(h, h_zero):
    """Thickness that emits particles: a cell at or below ``h_zero`` is dry for the scheme.

    It keeps its mass and receives, but sends nothing (and holds no momentum, see
    :func:`_final_momentum`). Without this a film of 1e-30 m spread one cell per step in every
    direction, whatever the physics, and soon covered the whole DEM.
    """
    return h if h > h_zero else 0.0


@njit(error_model="numpy", cache=True, inline="always")
def _speed(h, hu, hv):
    """|u| = |q| / h (m/s), 0 where dry."""
    if h <= 0.0:
        return 0.0
    return math.sqrt(hu * hu + hv * hv) / h


@njit(error_model="numpy", cache=True, inline="always")
def _moves(speed, speed_n, transport, h):
    """True when a cell moves material: u != 0 now, and either it just set off (u^n = 0)
    or one of its faces carried a mass flux above TRANSPORT_EPS h |u^n| in this step."""
    return speed > 0.0 and (speed_n == 0.0 or transport > TRANSPORT_EPS * h * speed_n)


@njit(error_model="numpy", cache=True, inline="always")
def _observe(h, q_norm, cfl_factor, gz, g):
    """Speed (m/s) of a cell of discharge norm q_norm and its inverse CFL limit (1/s).

    ``cfl_factor = P / (2 A)``: the limit of eq. 41 is ``1 / (cfl_factor (|u| + sqrt(3) c))``;
    the sweeps keep the largest inverse and divide once per step.
    """
    if h <= 0.0:
        return 0.0, 0.0
    speed = q_norm / h
    return speed, cfl_factor * (speed + SQRT3 * sound_speed(h, g * gz))


@njit(error_model="numpy", cache=True, inline="always")
def _open_mass(f_out):
    """Mass flux (outward) through an open side: what leaves, never anything that enters.

    The ghost copies the cell with its outward normal velocity (``max(u_n, 0)``), so a state
    leaving the map passes through unchanged (the two half fluxes of one state add up to the
    exact flux ``h u_n``). A cell moving inward would still receive the ghost's particles,
    mass from outside the map: an open side lets material leave and nothing enter, so the
    net is cut at 0 (then the face holds the material like a wall, pressure included).
    """
    return f_out if f_out > 0.0 else 0.0


@njit(error_model="numpy", cache=True, inline="always")
def _dirac_face(dirac, flag_i, flag_j):
    """True when a face carries the Dirac (zero) mass flux: both cells at zero temperature.

    Eqs. 51-53 and section 3.3 (Figs. 4-5); a boundary ghost shares the flag of its cell.
    """
    return dirac and flag_i != FLOWING and flag_j != FLOWING


@njit(error_model="numpy", cache=True, inline="always")
def _emitted(h, q1, q2, h_zero, g_normal, dens):
    """What a cell emits through its faces, computed once per step (scalars only):
    ``(h, u1, u2, c, sqrt(3) c, k / 2, k / 3)`` with ``k = c * dens`` the particle density of
    :func:`~avflow.numerics.kinetic.half_fluxes`; all zero at or below ``h_zero``. The
    half fluxes then need no division (:func:`~avflow.numerics.kinetic.half_flux_out`)."""
    if h <= h_zero or h <= 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    c = sound_speed(h, g_normal)
    k = c * dens
    return h, q1 / h, q2 / h, c, SQRT3 * c, 0.5 * k, k / 3.0


@njit(error_model="numpy", cache=True, inline="always")
def _side_fluxes(hf, uf, wet, dens, g_normal):
    """Half fluxes of a cell's reconstructed state (hf, uf) at one of its faces; nothing from
    a cell at or below the minimum flowing thickness (``wet`` False). Scalars only: Numba's
    inlined helpers that take arrays slowed the sweeps threefold."""
    if not wet:
        return 0.0, 0.0, 0.0, 0.0
    c = sound_speed(hf, g_normal)
    return half_fluxes(hf, uf, c, c * dens)


@njit(error_model="numpy", cache=True)
def _profile_fluxes2(recon, h, h_zero, density, gamma_z, g, left, right, flux):
    """Face fluxes of a profile from the reconstructed states (order 2); boundaries as in
    :func:`step_profile` (mirror walls; open ends closed to what would enter)."""
    n = h.size
    _, _, fm_h, fm_q = _side_fluxes(recon[0, 0], recon[0, 1], h[0] > h_zero, density[0],
                                    g * gamma_z[0])
    if left == WALL:
        flux[0, 0] = 0.0
        flux[0, 1] = 2.0 * fm_q
    else:
        gp_h, gp_q, _, _ = _side_fluxes(recon[0, 0], min(recon[0, 1], 0.0), h[0] > h_zero,
                                        density[0], g * gamma_z[0])
        flux[0, 0] = -_open_mass(-(gp_h + fm_h))
        flux[0, 1] = gp_q + fm_q
    for i in range(1, n):
        k = i - 1
        fp_h, fp_q, _, _ = _side_fluxes(recon[k, 2], recon[k, 3], h[k] > h_zero, density[k],
                                        g * gamma_z[k])
        _, _, fm_h, fm_q = _side_fluxes(recon[i, 0], recon[i, 1], h[i] > h_zero, density[i],
                                        g * gamma_z[i])
        flux[i, 0] = fp_h + fm_h
        flux[i, 1] = fp_q + fm_q
    k = n - 1
    fp_h, fp_q, _, _ = _side_fluxes(recon[k, 2], recon[k, 3], h[k] > h_zero, density[k],
                                    g * gamma_z[k])
    if right == WALL:
        flux[n, 0] = 0.0
        flux[n, 1] = 2.0 * fp_q
    else:
        _, _, gm_h, gm_q = _side_fluxes(recon[k, 2], max(recon[k, 3], 0.0), h[k] > h_zero,
                                        density[k], g * gamma_z[k])
        flux[n, 0] = _open_mass(fp_h + gm_h)
        flux[n, 1] = fp_q + gm_q


@njit(error_model="numpy", cache=True)
def step_profile(face_cells, cell_area, cfl_factor, density, gamma_x, gamma_y, gamma_z, curvature,
                 h, hu, hv, h_new, hu_new, hv_new, flux, flag,
                 law, params, g, dirac, h_dry, h_zero, dt, dt_decide, t_new, peak_h, peak_speed,
                 arrival, last_moved, order2, recon, observe):
    """One step on a profile (faces in line order, uniform dx), the face loop fused into the
    cell loops: the time loop runs it at order 2; at order 1 it runs the vectorised
    :func:`avflow.numerics.profile.step`, and this fused sweep is the reference that one is
    tested against, bit for bit (``tests/test_profile_sweep.py``).

    Same arithmetic as :func:`step_faces`.
    With ``order2`` the faces see the reconstructed states ``recon`` (h_L, u_L, h_R, u_R per
    cell, :func:`avflow.numerics.reconstruction.reconstruct_profile`) instead of the averages.
    ``observe``: update the observers (peaks, arrival, last motion); False for a
    Runge-Kutta stage, whose state is not one of the run's.
    ``flux[k, 0]`` is the mass flux (m^2/s) through face k towards +x, ``flux[k, 1]`` its
    momentum flux. Returns
    ``(ok, outflow, dt_limit, moving, film, clamped, kinetic)`` (see :func:`step_faces`).
    """
    n = h.size
    dx = cell_area[0]
    r = dt / dx
    left = face_cells[0, 1]
    right = face_cells[n, 1]
    p0, p1, p2, p3 = params[0], params[1], params[2], params[3]
    p4, p5, p6, p7 = params[4], params[5], params[6], params[7]

    # --- sweep 1: fluxes (every normal along +x), trial state, threshold flags
    if order2:
        _profile_fluxes2(recon, h, h_zero, density, gamma_z, g, left, right, flux)
        for k in range(n):
            hk = _emitting(h[k], h_zero)
            uk = abs(hu[k] / hk) if hk > 0.0 else 0.0
            qx, _, fk = _trial_momentum(h[k], h_zero, uk, hu[k], 0.0,
                                        (flux[k, 0] - flux[k + 1, 0]) / dx,
                                        (flux[k, 1] - flux[k + 1, 1]) / dx, 0.0, dt, dt_decide,
                                        gamma_x[k], 0.0, gamma_z[k],
                                        curvature[k, 0] * (uk * uk),
                                        law, p0, p1, p2, p3, p4, p5, p6, p7, g, order2)
            hu_new[k] = qx
            hv_new[k] = uk  # scratch: |u^n| for sweep 2
            flag[k] = fk
    else:
        h0 = _emitting(h[0], h_zero)
        c0 = sound_speed(h0, g * gamma_z[0])
        u0 = hu[0] / h0 if h0 > 0.0 else 0.0
        fp_h, fp_q, fm_h, fm_q = half_fluxes(h0, u0, c0, c0 * density[0])
        if left == WALL:  # mirror ghost (h, -u): no mass, twice the pressure
            fl_h = 0.0
            fl_q = 2.0 * fm_q
        else:  # open: transmissive for what leaves, closed to what would enter
            gp_h, gp_q, _, _ = half_fluxes(h0, min(u0, 0.0), c0, c0 * density[0])
            fl_h = _open_mass(-(gp_h + fm_h)) * -1.0
            fl_q = gp_q + fm_q
        flux[0, 0] = fl_h
        flux[0, 1] = fl_q
        u_prev = u0
        for i in range(1, n + 1):
            if i < n:
                hi = _emitting(h[i], h_zero)
                ci = sound_speed(hi, g * gamma_z[i])
                ui = hu[i] / hi if hi > 0.0 else 0.0
                np_h, np_q, nm_h, nm_q = half_fluxes(hi, ui, ci, ci * density[i])
                fr_h = fp_h + nm_h
                fr_q = fp_q + nm_q
            else:
                ui = 0.0
                np_h = np_q = 0.0
                if right == WALL:
                    fr_h = 0.0
                    fr_q = 2.0 * fp_q
                else:
                    hm = _emitting(h[n - 1], h_zero)
                    um = hu[n - 1] / hm if hm > 0.0 else 0.0
                    cm = sound_speed(hm, g * gamma_z[n - 1])
                    _, _, gm_h, gm_q = half_fluxes(hm, max(um, 0.0), cm, cm * density[n - 1])
                    fr_h = _open_mass(fp_h + gm_h)
                    fr_q = fp_q + gm_q
            flux[i, 0] = fr_h
            flux[i, 1] = fr_q
            k = i - 1  # cell k is complete: faces k (left) and k + 1 (right)
            qx, _, fk = _trial_momentum(h[k], h_zero, abs(u_prev), hu[k], 0.0, (fl_h - fr_h) / dx,
                                        (fl_q - fr_q) / dx, 0.0, dt, dt_decide, gamma_x[k], 0.0,
                                        gamma_z[k], curvature[k, 0] * (u_prev * u_prev),
                                        law, p0, p1, p2, p3, p4, p5, p6, p7, g, order2)
            hu_new[k] = qx
            hv_new[k] = abs(u_prev)  # scratch: |u^n| for sweep 2 (hv is identically 0 on a line)
            flag[k] = fk
            u_prev = ui
            fl_h = fr_h
            fl_q = fr_q
            fp_h, fp_q = np_h, np_q

    # --- sweep 2: mass with the Dirac switch, projection, observers
    outflow = 0.0
    inv_lim = 0.0
    moving = 0.0
    film = 0.0
    clamped = 0
    kinetic = 0.0
    for k in range(n):
        fk = flag[k]
        dirac_l = _dirac_face(dirac, fk, flag[k - 1] if k > 0 else fk)
        dirac_r = _dirac_face(dirac, fk, flag[k + 1] if k < n - 1 else fk)
        fl = 0.0 if dirac_l else flux[k, 0]
        fr = 0.0 if dirac_r else flux[k + 1, 0]
        hn = h[k] + r * (fl - fr)
        if hn < 0.0:
            return False, 0.0, 0.0, 0.0, 0.0, 0, 0.0
        if fk == DRY and (dirac_l or dirac_r):
            # A dry cell takes momentum only with mass: a Dirac face (a resting neighbour)
            # carries neither, not even its pressure (zero temperature, eq. 53).
            ql = 0.0 if dirac_l else flux[k, 1]
            qr = 0.0 if dirac_r else flux[k + 1, 1]
            hu_new[k] = dt * ((ql - qr) / dx + g * hn * gamma_x[k])
        if k == 0 and left == OUTFLOW:
            outflow += max(-fl, 0.0) * dt
        if k == n - 1 and right == OUTFLOW:
            outflow += max(fr, 0.0) * dt
        speed_n = hv_new[k]
        qx, _, cl = _final_momentum(fk, speed_n, hn, h_zero, hu_new[k], 0.0, dt, gamma_z[k],
                                    curvature[k, 0] * (speed_n * speed_n),
                                    law, p0, p1, p2, p3, p4, p5, p6, p7, g, h[k], order2)
        h_new[k] = hn
        hu_new[k] = qx
        hv_new[k] = 0.0
        clamped += cl
        speed, inv_k = _observe(hn, abs(qx), cfl_factor[k], gamma_z[k], g)
        inv_lim = max(inv_lim, inv_k)
        if observe:
            # observers written out: as a helper (inlined or not) they cost the sweep 3x
            if hn > peak_h[k]:
                peak_h[k] = hn
            if speed > peak_speed[k]:
                peak_speed[k] = speed
            if hn > h_dry and math.isnan(arrival[k]):
                arrival[k] = t_new
            if speed > 0.0:
                last_moved[k] = t_new
        kinetic += hn * dx * speed * speed
        if _moves(speed, speed_n, max(abs(fl), abs(fr)), hn):
            if hn > h_dry:
                moving += hn * dx
            else:
                film += hn * dx
    return True, outflow, _limit(inv_lim), moving, film, clamped, kinetic


@njit(error_model="numpy", cache=True)
def step_faces(face_cells, face_frame, face_length, cell_area, cfl_factor, density,
               gamma_x, gamma_y, gamma_z, curvature,
               h, hu, hv, h_new, hu_new, hv_new, flux, transport, flag,
               law, params, g, dirac, h_dry, h_zero, dt, dt_decide, t_new, peak_h, peak_speed,
               arrival, last_moved, active_faces, n_active, touched, n_touched, order2,
               face_state, observe, emit):
    """One step on any mesh (grid, triangles, profile): loops over faces, then cells.

    Only the ``n_active`` faces of ``active_faces`` (those of the wet cells) and the
    ``n_touched`` cells of ``touched`` (their two sides) are swept: every other cell is dry,
    receives nothing and keeps its state, so the cost follows the area the mass covers.

    ``h_new`` first accumulates the trial mass rate, ``hu_new, hv_new`` the momentum rate.
    Normal and tangential components are taken in each face's frame (rotational invariance):
    the normal part uses the kinetic flux, the tangential velocity is carried upwind with the
    mass. ``face_frame`` (see :class:`avflow.terrain.mesh.Mesh`) maps each cell's discharge into the
    face frame and the flux back into the cell's own basis. ``flux[f, 0]`` is ``L_f`` times the mass flux through face f along its normal, ``flux[f, 1:5]`` the momentum it brings to side i (x, y) and side j (x, y).

    Returns ``(ok, outflow, dt_limit, moving, film, clamped, kinetic)``: ok is False when a thickness
    would turn negative; outflow the volume that left through open faces in this step;
    dt_limit the CFL limit of the new state; moving and film the volumes of the cells that
    transport mass (u != 0 and a face flux above TRANSPORT_EPS h |u|) above and below h_dry;
    ``transport`` is a per-cell work array; clamped the number of cells whose normal
    acceleration was clamped at 0; kinetic the sum of h A |u|^2 of the new state.
    """
    p0, p1, p2, p3 = params[0], params[1], params[2], params[3]
    p4, p5, p6, p7 = params[4], params[5], params[6], params[7]
    for c in range(n_touched):
        i = touched[c]
        h_new[i] = 0.0
        hu_new[i] = 0.0
        hv_new[i] = 0.0

    # --- sweep 0 (order 1): what each cell emits through its faces, once per cell
    if not order2:
        for c in range(n_touched):
            i = touched[c]
            (emit[i, 0], emit[i, 1], emit[i, 2], emit[i, 3], emit[i, 4], emit[i, 5],
             emit[i, 6]) = _emitted(h[i], hu[i], hv[i], h_zero, g * gamma_z[i], density[i])

    # --- sweep 1a: rectangular fluxes, each side read and written in its own cell's basis
    for a in range(n_active):
        f = active_faces[a]
        i = face_cells[f, 0]
        j = face_cells[f, 1]
        ni_x, ni_y = face_frame[f, 0, 0, 0], face_frame[f, 0, 0, 1]
        ti_x, ti_y = face_frame[f, 0, 1, 0], face_frame[f, 0, 1, 1]
        length = face_length[f]
        # both sides written out: through a helper taking the arrays the sweep ran 30% slower
        if order2:  # the reconstructed state at the face
            hi = qi1 = qi2 = 0.0
            if h[i] > h_zero:
                hi, qi1, qi2 = face_state[f, 0, 0], face_state[f, 0, 1], face_state[f, 0, 2]
            hi, ui1, ui2, ci, si, khi, k3i = _emitted(hi, qi1, qi2, 0.0, g * gamma_z[i],
                                                      density[i])
        else:
            hi, ui1, ui2, ci = emit[i, 0], emit[i, 1], emit[i, 2], emit[i, 3]
            si, khi, k3i = emit[i, 4], emit[i, 5], emit[i, 6]
        uni = ui1 * ni_x + ui2 * ni_y
        uti = ui1 * ti_x + ui2 * ti_y
        fp_h, fp_q = half_flux_out(hi, uni, ci, si, khi, k3i)
        if j >= 0:
            nj_x, nj_y = face_frame[f, 1, 0, 0], face_frame[f, 1, 0, 1]
            tj_x, tj_y = face_frame[f, 1, 1, 0], face_frame[f, 1, 1, 1]
            if order2:
                hj = qj1 = qj2 = 0.0
                if h[j] > h_zero:
                    hj, qj1, qj2 = face_state[f, 1, 0], face_state[f, 1, 1], face_state[f, 1, 2]
                hj, uj1, uj2, cj, sj, khj, k3j = _emitted(hj, qj1, qj2, 0.0, g * gamma_z[j],
                                                          density[j])
            else:
                hj, uj1, uj2, cj = emit[j, 0], emit[j, 1], emit[j, 2], emit[j, 3]
                sj, khj, k3j = emit[j, 4], emit[j, 5], emit[j, 6]
            unj = uj1 * nj_x + uj2 * nj_y
            utj = uj1 * tj_x + uj2 * tj_y
            gm_h, gm_q = half_flux_in(hj, unj, cj, sj, khj, k3j)
        elif j == WALL:  # mirror ghost (h, -u_n, u_t): no mass, twice the pressure
            gm_h = -fp_h
            gm_q = fp_q
            utj = uti
        else:  # open boundary: transmissive for what leaves, closed to what would enter
            gm_h, gm_q = half_flux_in(hi, max(uni, 0.0), ci, si, khi, k3i)
            gm_h = _open_mass(fp_h + gm_h) - fp_h
            utj = uti
        f_n = (fp_q + gm_q) * length  # normal momentum flux, face frame
        f_t = (uti * fp_h + utj * gm_h) * length  # tangential momentum, carried upwind
        fh = (fp_h + gm_h) * length
        qix = f_n * ni_x + f_t * ti_x
        qiy = f_n * ni_y + f_t * ti_y
        flux[f, 0] = fh
        flux[f, 1] = qix
        flux[f, 2] = qiy
        h_new[i] -= fh
        hu_new[i] -= qix
        hv_new[i] -= qiy
        if j >= 0:
            qjx = f_n * nj_x + f_t * tj_x
            qjy = f_n * nj_y + f_t * tj_y
            flux[f, 3] = qjx
            flux[f, 4] = qjy
            h_new[j] += fh
            hu_new[j] += qjx
            hv_new[j] += qjy

    # --- sweep 1b: trial state and threshold flags
    for c in range(n_touched):
        i = touched[c]
        if h[i] <= h_zero:  # dry: keep the momentum rate, formed in sweep 2b with its mass
            flag[i] = DRY
            h_new[i] = 0.0
            continue
        inv_area = 1.0 / cell_area[i]
        qx, qy, fi = _trial_momentum(h[i], h_zero, _speed(h[i], hu[i], hv[i]), hu[i], hv[i],
                                     h_new[i] * inv_area, hu_new[i] * inv_area,
                                     hv_new[i] * inv_area, dt, dt_decide, gamma_x[i],
                                     gamma_y[i], gamma_z[i],
                                     _centripetal(curvature, i, h[i], hu[i], hv[i]),
                                     law, p0, p1, p2, p3, p4, p5, p6, p7, g, order2)
        hu_new[i] = qx
        hv_new[i] = qy
        flag[i] = fi
        h_new[i] = 0.0

    # --- sweep 2a: mass through the faces that keep the rectangular density
    outflow = 0.0
    for c in range(n_touched):
        transport[touched[c]] = 0.0
    for a in range(n_active):
        f = active_faces[a]
        i = face_cells[f, 0]
        j = face_cells[f, 1]
        if _dirac_face(dirac, flag[i], flag[j] if j >= 0 else flag[i]):
            # A dry side takes momentum only with mass: the Dirac face (u = 0, eq. 53)
            # carries neither, not even the resting neighbour's pressure.
            if flag[i] == DRY:
                hu_new[i] += flux[f, 1]
                hv_new[i] += flux[f, 2]
            if j >= 0 and flag[j] == DRY:
                hu_new[j] -= flux[f, 3]
                hv_new[j] -= flux[f, 4]
            continue
        fh = flux[f, 0]
        h_new[i] -= fh
        unit = abs(fh) / face_length[f]
        transport[i] = max(transport[i], unit)
        if j >= 0:
            h_new[j] += fh
            transport[j] = max(transport[j], unit)
        elif j == OUTFLOW:
            outflow += max(fh, 0.0) * dt

    # --- sweep 2b: new thickness, projection, observers
    inv_lim = 0.0
    moving = 0.0
    film = 0.0
    clamped = 0
    kinetic = 0.0
    for c in range(n_touched):
        i = touched[c]
        area = cell_area[i]
        hn = h[i] + dt / area * h_new[i]
        if hn < 0.0:
            return False, 0.0, 0.0, 0.0, 0.0, 0, 0.0
        speed_n = _speed(h[i], hu[i], hv[i])
        qx = hu_new[i]
        qy = hv_new[i]
        if flag[i] == DRY:  # q~ of eq. 47 with q^n = 0 and h* = h^{n+1}
            qx = dt * (qx / area + g * hn * gamma_x[i])
            qy = dt * (qy / area + g * hn * gamma_y[i])
        qx, qy, cl = _final_momentum(flag[i], speed_n, hn, h_zero, qx, qy, dt, gamma_z[i],
                                     _centripetal(curvature, i, h[i], hu[i], hv[i]),
                                     law, p0, p1, p2, p3, p4, p5, p6, p7, g, h[i], order2)
        h_new[i] = hn
        hu_new[i] = qx
        hv_new[i] = qy
        clamped += cl
        speed, inv_i = _observe(hn, math.sqrt(qx * qx + qy * qy), cfl_factor[i], gamma_z[i], g)
        inv_lim = max(inv_lim, inv_i)
        if observe:
            # observers written out: as a helper (inlined or not) they cost the sweep 3x
            if hn > peak_h[i]:
                peak_h[i] = hn
            if speed > peak_speed[i]:
                peak_speed[i] = speed
            if hn > h_dry and math.isnan(arrival[i]):
                arrival[i] = t_new
            if speed > 0.0:
                last_moved[i] = t_new
        kinetic += hn * area * speed * speed
        if _moves(speed, speed_n, transport[i], hn):
            if hn > h_dry:
                moving += hn * area
            else:
                film += hn * area
    return True, outflow, _limit(inv_lim), moving, film, clamped, kinetic


@njit(error_model="numpy", cache=True)
def profile_transport(flag, flux, dirac, transport):
    """Per cell of a profile, the larger mass flux through its two faces in the step just
    taken (Dirac faces carry none): what :func:`heun_faces` reads as ``transport``."""
    n = flag.size
    for k in range(n):
        fk = flag[k]
        fl = 0.0 if _dirac_face(dirac, fk, flag[k - 1] if k > 0 else fk) else flux[k, 0]
        fr = 0.0 if _dirac_face(dirac, fk, flag[k + 1] if k < n - 1 else fk) else flux[k + 1, 0]
        transport[k] = max(abs(fl), abs(fr))


@njit(error_model="numpy", cache=True)
def heun_faces(cells, n_cells, h0, hu0, hv0, h2, hu2, hv2, flag1, transport, cell_area,
               cfl_factor, gamma_z, g, h_dry, h_zero, t_new, peak_h, peak_speed, arrival,
               last_moved, h_new, hu_new, hv_new):
    """Order 2: Heun's average of the two stages over the ``n_cells``
    listed ``cells`` (those either stage changed; all cells on a profile) and the step's
    observers. ``transport`` holds the face fluxes of the stage that last swept each cell.
    Returns ``(dt_limit, moving, film, kinetic, fallbacks)`` as the step kernels do (moving
    cells: u != 0 and a face that carried mass)."""
    inv_lim = 0.0
    moving = 0.0
    film = 0.0
    kinetic = 0.0
    fallbacks = 0
    for c in range(n_cells):
        i = cells[c]
        # U^{n+1} = (U^n + U**) / 2. A cell that the first stage (a first-order step from
        # U^n) put under the Coulomb threshold takes the first-order answer q = 0: the
        # average would give it q^n / 2, and a mass that stops would never quite stop.
        # Mass is always averaged (each stage conserves it, so their average does).
        hn = 0.5 * (h0[i] + h2[i])
        qx = 0.5 * (hu0[i] + hu2[i])
        qy = 0.5 * (hv0[i] + hv2[i])
        stopped = flag1[i] == UNDER_THRESHOLD
        if hn <= h_zero or stopped:
            if stopped and (qx != 0.0 or qy != 0.0):
                fallbacks += 1
            qx = 0.0
            qy = 0.0
        h_new[i] = hn
        hu_new[i] = qx
        hv_new[i] = qy
        speed, inv_i = _observe(hn, math.sqrt(qx * qx + qy * qy), cfl_factor[i], gamma_z[i], g)
        inv_lim = max(inv_lim, inv_i)
        # observers written out: as a helper (inlined or not) they cost the sweep 3x
        if hn > peak_h[i]:
            peak_h[i] = hn
        if speed > peak_speed[i]:
            peak_speed[i] = speed
        if hn > h_dry and math.isnan(arrival[i]):
            arrival[i] = t_new
        if speed > 0.0:
            last_moved[i] = t_new
        area = cell_area[i]
        kinetic += hn * area * speed * speed
        if _moves(speed, _speed(h0[i], hu0[i], hv0[i]), transport[i], hn):
            if hn > h_dry:
                moving += hn * area
            else:
                film += hn * area
    return _limit(inv_lim), moving, film, kinetic, fallbacks


@njit(error_model="numpy", cache=True)
def merge_lists(first, n_first, second, n_second, stamps, stamp, out):
    """``out``: the cells of both lists, each once (marked with ``stamp``); returns the count."""
    k = 0
    for c in range(n_first + n_second):
        i = first[c] if c < n_first else second[c - n_first]
        if stamps[i] != stamp:
            stamps[i] = stamp
            out[k] = i
            k += 1
    return k


@njit(error_model="numpy", cache=True)
def cell_faces(face_cells, n_cells):
    """The faces of every cell (CSR: ``idx[ptr[c]:ptr[c + 1]]``), in index order (the order
    in which the face sweeps add them to the cell: a sweep over a cell's own faces that
    sums them in this order gets the same bits). A counting sort, one pass over the faces
    (numpy's stable argsort of the owners took 11 ms on 179k cells)."""
    n_faces = face_cells.shape[0]
    ptr = np.zeros(n_cells + 1, dtype=np.int64)
    for f in range(n_faces):
        ptr[face_cells[f, 0] + 1] += 1
        if face_cells[f, 1] >= 0:
            ptr[face_cells[f, 1] + 1] += 1
    for c in range(n_cells):
        ptr[c + 1] += ptr[c]
    idx = np.empty(ptr[n_cells], dtype=np.int64)
    fill = ptr[:n_cells].copy()
    for f in range(n_faces):  # both sides of each face in turn: each cell's faces in order
        i = face_cells[f, 0]
        idx[fill[i]] = f
        fill[i] += 1
        j = face_cells[f, 1]
        if j >= 0:
            idx[fill[j]] = f
            fill[j] += 1
    return ptr, idx


@njit(error_model="numpy", cache=True)
def activate(wet, n_wet, cell_face_ptr, cell_face_idx, face_cells, face_stamp, cell_stamp,
             stamp, active_faces, touched):
    """Faces of the wet cells and the cells on both their sides, each listed once (sorted).

    ``stamp`` marks what this step has listed in ``face_stamp`` / ``cell_stamp``.
    Returns ``(n_active, n_touched)``.
    """
    m, k = _list_faces_of(wet, n_wet, cell_face_ptr, cell_face_idx, face_cells, face_stamp,
                          cell_stamp, stamp, active_faces, touched)
    return (_in_index_order(active_faces, m, face_stamp, stamp),
            _in_index_order(touched, k, cell_stamp, stamp))


@njit(error_model="numpy", cache=True, inline="always")
def _list_faces_of(cells, n_cells, cell_face_ptr, cell_face_idx, face_cells, face_stamp,
                   cell_stamp, stamp, faces, sides):
    """The faces of ``cells[:n_cells]`` not yet marked ``stamp`` into ``faces``, and the
    cells on their sides not yet marked into ``sides`` (both then marked), in the order
    met. Returns their counts."""
    m = 0
    k = 0
    for a in range(n_cells):
        c = cells[a]
        for p in range(cell_face_ptr[c], cell_face_ptr[c + 1]):
            f = cell_face_idx[p]
            if face_stamp[f] != stamp:
                face_stamp[f] = stamp
                faces[m] = f
                m += 1
                for side in range(2):
                    d = face_cells[f, side]
                    if d >= 0 and cell_stamp[d] != stamp:
                        cell_stamp[d] = stamp
                        sides[k] = d
                        k += 1
    return m, k


@njit(error_model="numpy", cache=True)
def relist(gained, n_gained, lost, n_lost, h, h_zero, cell_face_ptr, cell_face_idx, face_cells,
           face_stamp, cell_stamp, stamp, active_faces, n_active, touched, n_touched,
           new_faces, new_cells, fresh_faces, gone_faces, added, dropped):
    """The active lists after the wet cells changed, mended from the last ones: the lists
    :func:`activate` makes for the new wet cells, in the same order, at the cost of the
    cells that changed and of a block copy of each list, instead of all the wet cells' faces
    and a sort or a scan.

    ``gained`` / ``lost``: the cells that became wet / dry (``h > h_zero``, ``h`` the new
    state: it must hold every cell of the last lists); ``active_faces[:n_active]`` and
    ``touched[:n_touched]``: the last lists, which are marked with ``stamp`` in
    ``face_stamp`` / ``cell_stamp`` (those of a face or a cell leaving the lists are set to
    -1, a value no stamp takes). The new lists go to ``new_faces`` and ``new_cells``, sorted.
    ``fresh_faces``, ``gone_faces`` (per face), ``added`` (per cell), ``dropped`` (two per
    face): work. Returns ``(n_active, n_touched, n_joined, n_dropped)``: the cells that
    joined the touched list are ``added[:n_joined]``, those that left it
    ``dropped[:n_dropped]`` (both sorted).
    """
    # the faces of a cell that became wet are all active, and their sides touched
    n_fresh, n_add = _list_faces_of(gained, n_gained, cell_face_ptr, cell_face_idx, face_cells,
                                    face_stamp, cell_stamp, stamp, fresh_faces, added)
    # a face of a cell that became dry leaves with no wet side left; its sides may follow
    # (a face that gained a wet side above kept it: added and gone never meet)
    n_gone = 0
    n_cand = 0
    for a in range(n_lost):
        c = lost[a]
        for p in range(cell_face_ptr[c], cell_face_ptr[c + 1]):
            f = cell_face_idx[p]
            i = face_cells[f, 0]
            j = face_cells[f, 1]
            if face_stamp[f] == stamp and not (h[i] > h_zero or (j >= 0 and h[j] > h_zero)):
                face_stamp[f] = -1
                gone_faces[n_gone] = f
                n_gone += 1
                dropped[n_cand] = i
                n_cand += 1
                if j >= 0:
                    dropped[n_cand] = j
                    n_cand += 1
    n_dropped = 0
    for a in range(n_cand):  # a side leaves once none of its faces is active
        d = dropped[a]
        if cell_stamp[d] == stamp:
            kept = False
            for p in range(cell_face_ptr[d], cell_face_ptr[d + 1]):
                kept = kept or face_stamp[cell_face_idx[p]] == stamp
            if not kept:
                cell_stamp[d] = -1
                dropped[n_dropped] = d
                n_dropped += 1
    fresh_faces[:n_fresh].sort()
    gone_faces[:n_gone].sort()
    added[:n_add].sort()
    dropped[:n_dropped].sort()
    return (_mend(active_faces, n_active, fresh_faces, n_fresh, gone_faces, n_gone, new_faces),
            _mend(touched, n_touched, added, n_add, dropped, n_dropped, new_cells),
            n_add, n_dropped)


@njit(error_model="numpy", cache=True)
def _mend(old, n_old, fresh, n_fresh, gone, n_gone, out):
    """``out``: the sorted list ``old[:n_old]`` without ``gone[:n_gone]`` (items of it) and
    with ``fresh[:n_fresh]`` (none of it), both sorted; returns its length. The runs of
    ``old`` between two changes are block copies, each change's place a binary search."""
    k = 0
    p = 0  # the next item of old to copy
    a = 0
    b = 0
    while a < n_fresh or b < n_gone:
        take_fresh = b >= n_gone or (a < n_fresh and fresh[a] < gone[b])
        x = fresh[a] if take_fresh else gone[b]
        lo = p  # the first item of old[p:n_old] at least x
        hi = n_old
        while lo < hi:
            mid = (lo + hi) >> 1
            if old[mid] < x:
                lo = mid + 1
            else:
                hi = mid
        out[k:k + lo - p] = old[p:lo]
        k += lo - p
        if take_fresh:
            out[k] = x
            k += 1
            p = lo
            a += 1
        else:  # old[lo] is x: skipped
            p = lo + 1
            b += 1
    out[k:k + n_old - p] = old[p:n_old]
    return k + n_old - p


@njit(error_model="numpy", cache=True, inline="always")
def _agree(cells, count, h, hu, hv, h_to, hu_to, hv_to):
    """The state of the listed ``cells[:count]`` copied into the other buffers, so both
    buffers agree on them (the next step does not write them there)."""
    for c in range(count):
        i = cells[c]
        h_to[i] = h[i]
        hu_to[i] = hu[i]
        hv_to[i] = hv[i]


#: The face kernel's time loop (order 1) mends its active lists (:func:`relist`) while at
#: most this share of the wet cells became wet or dry in a step, and lists them again from
#: the wet cells (:func:`activate`) beyond it. Measured on 6,349 wet triangle nodes growing
#: by a ring: mending cost 0.3 of listing at a share of 0.02, 0.6 at 0.08, 1.0-1.6 at 0.19,
#: 3 at 0.35 (the new faces are sorted, and where the wet cells are mostly new, their
#: faces are all that are listed)
RELIST_SHARE = 0.15


#: Blocks of indices that :func:`_in_index_order` scans (2^SCAN_SHIFT): 64 stamps, 512 bytes
SCAN_SHIFT = 6
SCAN_BLOCK = 1 << SCAN_SHIFT


@njit(error_model="numpy", cache=True, inline="always")
def _in_index_order(items, count, stamps, stamp):
    """Put the ``count`` listed indices (those with ``stamps == stamp``) in increasing order.

    Faces and cells are swept in index order: memory order, and the same sums, bit for bit,
    as a sweep of the whole mesh. The list is rebuilt by a scan of the stamps over the
    blocks of :data:`SCAN_BLOCK` indices that hold one of its items, or sorted where that
    costs less (k log2 k against the blocks' indices). Only those blocks: on a grid the range
    a flow spans is the rows it covers times the map's width (its x faces and, far from
    them, its y faces), and scanning all of it made a step on a map 4x larger 20% dearer;
    weighing the sort against that whole range sorted the 12k faces of a flow on a 5 m DEM
    (0.5 ms) where a scan of their 400-odd blocks takes 30 us.
    """
    if count == 0:
        return 0
    lo = items[0]
    hi = items[0]
    for c in range(1, count):
        lo = min(lo, items[c])
        hi = max(hi, items[c])
    held = np.zeros(((hi - lo) >> SCAN_SHIFT) + 1, dtype=np.bool_)
    n_held = 0
    for c in range(count):
        b = (items[c] - lo) >> SCAN_SHIFT
        if not held[b]:
            held[b] = True
            n_held += 1
    if count * math.log2(count + 2.0) > n_held * SCAN_BLOCK:
        count = 0
        for b in range(held.size):
            if held[b]:
                for i in range(lo + (b << SCAN_SHIFT), min(lo + ((b + 1) << SCAN_SHIFT), hi + 1)):
                    if stamps[i] == stamp:
                        items[count] = i
                        count += 1
    else:
        items[:count].sort()
    return count


@njit(error_model="numpy", cache=True)
def step_size(stats, cfl, t, t_target):
    """The next step of a time loop: ``cfl`` times the state's CFL limit (the whole interval
    when nothing moves), cut to land on ``t_target``. Returns ``(dt, dt_decide, last)``:
    ``dt_decide`` is the uncut step, with which the Coulomb threshold is always tested (the
    decision depends on the state alone), ``last`` whether the step lands on ``t_target``."""
    dt_max = stats[ST_DT_LIMIT]
    dt = cfl * dt_max if dt_max < np.inf else t_target - t
    if t + dt >= t_target:
        return t_target - t, dt, True
    return dt, dt, False


@njit(error_model="numpy", cache=True)
def record_step(stats, dt, dt_limit, moving, film, kinetic, clamped, outflow, stop_volume,
                stop_kinetic, steps, max_steps):
    """A finished step into ``stats`` (the ``ST_*`` slots; ``kinetic`` is the sum of
    h A |u|^2), then the stop rules: STOPPED (moving volume under ``stop_volume``, or kinetic
    energy at most ``stop_kinetic`` times its peak; negative: rule off), MAX_STEPS, or
    REACHED_TARGET to go on. ``steps``: taken in this call so far."""
    stats[ST_DT_LIMIT] = dt_limit
    stats[ST_MOVING] = moving
    stats[ST_FILM] = film
    stats[ST_KINETIC] = 0.5 * kinetic
    stats[ST_KINETIC_PEAK] = max(stats[ST_KINETIC_PEAK], 0.5 * kinetic)
    stats[ST_CLAMPED] += clamped
    stats[ST_OUTFLOW] += outflow
    stats[ST_DT_MIN] = min(stats[ST_DT_MIN], dt)
    stats[ST_DT_MAX] = max(stats[ST_DT_MAX], dt)
    if stop_volume >= 0.0 and moving < stop_volume:
        return STOPPED
    if stop_kinetic >= 0.0 and kinetic <= stop_kinetic * (2.0 * stats[ST_KINETIC_PEAK]):
        return STOPPED
    if stats[ST_STEPS] + steps >= max_steps:
        return MAX_STEPS
    return REACHED_TARGET


@njit(error_model="numpy", cache=True)
def end_loop(stats, t, steps, h, hu, hv, cur_h, cur_hu, cur_hv):
    """The end of a time loop that swaps two buffers each step: the newest state back in
    ``(h, hu, hv)`` when it sits in the work buffers (an odd number of steps), and
    :func:`record_end`. (Loops that know where the buffers differ copy only there.)"""
    if steps % 2 == 1:
        h[:] = cur_h
        hu[:] = cur_hu
        hv[:] = cur_hv
    record_end(stats, t, steps)


@njit(error_model="numpy", cache=True)
def record_end(stats, t, steps):
    """The time and the step count of a time loop's call into ``stats``."""
    stats[ST_TIME] = t
    stats[ST_STEPS] += steps


def _advance(structured, face_cells, face_frame, face_length, cell_area, cfl_factor, density,
            gamma_x, gamma_y, gamma_z, curvature,
            h, hu, hv, h_work, hu_work, hv_work, flux, transport, flag,
            law, params, g, dirac, h_dry, h_zero, cfl, t_target, max_steps, stop_volume,
            stop_kinetic, peak_h, peak_speed, arrival, last_moved, cell_face_ptr, cell_face_idx,
            stats, order, limiter, face_offset, face_stamp, cell_stamp, cell_sync, synced, clock,
            sweep_geo, sweep_work, min_parallel_cells):
    """Advance ``(h, hu, hv)`` in place until ``t_target``, a stop, or ``max_steps``.

    ``stats`` (see the ``ST_*`` slots) carries the time, the CFL limit and the counters from
    one call to the next. Observers updated every step: ``peak_h``, ``peak_speed``,
    ``arrival`` (first time h > h_dry, NaN before) and ``last_moved`` (end of the last step
    with u != 0: the time a cell came to rest for good once it stays at rest). The run is
    *stopped* once the moving volume (cells with u != 0 and h > h_dry) falls below
    ``stop_volume``, or once the kinetic energy is at most ``stop_kinetic`` times its peak so
    far (AvaFrame's rule); a negative value switches that rule off.
    ``order`` 2: limited reconstruction (``limiter``, :mod:`avflow.numerics.reconstruction`;
    ``face_offset[f, side]``: from each cell's centre half the way to its neighbour's, in its
    basis) and Heun's two stages, each a full step of the seed's scheme (threshold, Dirac
    faces, projection), averaged by :func:`heun_faces`. ``flux`` (n_faces, 5): the face
    fluxes of order 2 (empty at order 1); ``transport`` (per cell): the largest mass flux
    per metre through its faces in the last step. ``sweep_geo, sweep_work``: what the face
    kernel's order-1 step reads and works in
    (:func:`avflow.numerics.face_sweep.geometry`, :func:`~avflow.numerics.face_sweep.work`;
    empty elsewhere, :func:`~avflow.numerics.face_sweep.unused`). ``min_parallel_cells``:
    in the copy with threads, an order-1 step, an order-2 stage or Heun's merge that sweeps
    at least that many cells runs on Numba's threads (order 1:
    :func:`avflow.numerics.face_sweep._step_threads`, each thread scattering into the cells
    of its own piece of the faces, from twice as many where its lists changed; order 2:
    :mod:`avflow.numerics.face_gather`, in gather form; the same bits as the serial
    sweeps).
    Returns a status code: REACHED_TARGET, STOPPED, MAX_STEPS or FAILED.

    Kept by the caller from one call to the next (face kernel): ``face_stamp`` (per face),
    ``cell_stamp`` and ``cell_sync`` (per cell, -1 at first), ``synced`` (per cell, any) and
    ``clock`` (int64[2]: the steps stamped so far, the calls). The stamps then never repeat,
    and nothing per call costs the map: at order 1 the work buffers take the state of a cell
    when a step first touches it in the call, and only those cells go back at the end. At
    order 1 a step whose wet cells are the last step's keeps that step's active lists (a
    flow covering its mesh, a deposit at rest: nothing is listed again), and one where a few
    changed mends them (:func:`relist`: a spreading flow lists its front, not its area).

    A template: :func:`time_loop` gives its copy for the mesh kind and the order, where
    ``STRUCTURED``, ``ORDER2`` and ``PARALLEL`` are constants (``structured`` and ``order``
    are not read):
    Numba drops the branches of the other kinds before it types the function, so a run
    compiles only the sweeps it uses (section 6 at order 1, Coulomb: 27 s -> 7 s cold, this
    machine).
    """
    t = stats[ST_TIME]
    # order-2 work arrays: one allocation per call, none per step
    m2 = h.size if ORDER2 else 0
    f2 = face_cells.shape[0] if ORDER2 else 0
    recon = np.zeros((m2 if STRUCTURED else 0, 4))
    velocity = np.zeros((0 if STRUCTURED else m2, 2))  # reconstruct_cells' work
    face_state = np.zeros((0 if STRUCTURED else f2, 2, 3))
    cell_sums = np.empty((m2 if PARALLEL else 0, N_SUMS))  # the gather form's per-cell sums
    no_emit = np.zeros((0, 7))  # step_faces' emitted values: read at order 1 only
    s_h = np.zeros(m2)
    s_hu = np.zeros(m2)
    s_hv = np.zeros(m2)
    flag1 = np.full(m2, DRY, dtype=flag.dtype)  # stage-1 flags; DRY outside a step
    wet2 = np.empty(0 if STRUCTURED else m2, dtype=np.int64)
    touched2 = np.empty(0 if STRUCTURED else m2, dtype=np.int64)
    union = np.empty(0 if STRUCTURED else m2, dtype=np.int64)
    active2 = np.empty(0 if STRUCTURED else f2, dtype=np.int64)
    all_cells = np.arange(m2 if STRUCTURED else 0)
    # order-1 profile sweep (avflow.numerics.profile): its work lines, once per call
    m1 = h.size if STRUCTURED and not ORDER2 else 0
    p_work = np.zeros((_PROFILE_WORK, m1 + 2 if m1 else 0))
    p_flag = np.full(m1 + 2 if m1 else 0, DRY, dtype=flag.dtype)
    p_kappa = np.empty(m1)
    for i in range(m1):
        p_kappa[i] = curvature[i, 0]
    cur_h, cur_hu, cur_hv = h, hu, hv
    nxt_h, nxt_hu, nxt_hv = h_work, hu_work, hv_work
    status = REACHED_TARGET
    steps = 0
    # Active lists (face kernel): both buffers agree outside the cells touched by the last
    # step, so a cell left untouched needs no copy; those touched last time are copied.
    n = h.size
    nf = face_cells.shape[0]
    if STRUCTURED or ORDER2:  # the whole state into the work buffers (faces, order 1: lazily)
        h_work[:] = h
        hu_work[:] = hu
        hv_work[:] = hv
    clock[1] += 1
    call = clock[1]
    n_synced = 0
    m_faces = 0 if STRUCTURED else n  # the face kernel's lists
    wet = np.empty(n, dtype=np.int64)
    touched = np.empty(n, dtype=np.int64)
    active_faces = np.empty(nf, dtype=np.int64)
    # order 1: the last step's wet cells, those that became wet / dry since, and what
    # relist() works in (its new lists swap with the last ones)
    m_re = 0 if STRUCTURED or ORDER2 else n
    f_re = 0 if STRUCTURED or ORDER2 else nf
    wet_last = np.empty(m_faces, dtype=np.int64)
    gained = np.empty(m_re, dtype=np.int64)
    lost = np.empty(m_re, dtype=np.int64)
    new_faces = np.empty(f_re, dtype=np.int64)
    new_cells = np.empty(m_re, dtype=np.int64)
    fresh_faces = np.empty(f_re, dtype=np.int64)
    gone_faces = np.empty(f_re, dtype=np.int64)
    added = np.empty(m_re, dtype=np.int64)
    dropped = np.empty(2 * f_re, dtype=np.int64)
    n_wet = 0
    for i in range(m_faces):
        if h[i] > h_zero:
            wet[n_wet] = i
            n_wet += 1
    n_previous = 0
    n_active = 0
    n_touched = 0
    n_gained = 0
    n_lost = 0
    listed = False  # this call has active lists (made by activate, with list_stamp)
    list_stamp = 0
    same_wet = False  # wet cells as in the last step: its active lists still hold
    while t < t_target:
        dt, dt_decide, last = step_size(stats, cfl, t, t_target)
        ok = False
        if not STRUCTURED and not same_wet:
            # (skipped while the wet cells are the last step's: its lists hold, the step
            # rewrites all their cells in the work buffers, and they are synced already)
            if ORDER2 or not listed or n_gained + n_lost > RELIST_SHARE * n_wet:
                # listed from the wet cells (order 2, a call's first step, or where much
                # changed); the buffers first made to agree on the last step's cells (still
                # in its list: order 2's union is written again only once this step's
                # stages ran, order 1's touched list by activate below)
                _agree(union if ORDER2 else touched, n_previous, cur_h, cur_hu, cur_hv, nxt_h,
                       nxt_hu, nxt_hv)
                list_stamp = (STAMPS_PER_STEP if ORDER2 else 1) * (clock[0] + steps)
                n_active, n_touched = activate(wet, n_wet, cell_face_ptr, cell_face_idx,
                                               face_cells, face_stamp, cell_stamp, list_stamp,
                                               active_faces, touched)
                listed = True
                n_fresh = n_touched
                fresh = touched
            else:
                # order 1, a few cells changed: the last lists mended (relist); a cell that
                # leaves them gets its new state in both buffers (the step does not write
                # it), and the cells that join are synced below
                n_active, n_touched, n_fresh, n_dropped = relist(
                    gained, n_gained, lost, n_lost, cur_h, h_zero, cell_face_ptr,
                    cell_face_idx, face_cells, face_stamp, cell_stamp, list_stamp,
                    active_faces, n_active, touched, n_touched, new_faces, new_cells,
                    fresh_faces, gone_faces, added, dropped)
                active_faces, new_faces = new_faces, active_faces
                touched, new_cells = new_cells, touched
                _agree(dropped, n_dropped, cur_h, cur_hu, cur_hv, nxt_h, nxt_hu, nxt_hv)
                fresh = added
            if not ORDER2:
                # a cell touched for the first time in this call: its state into the work
                # buffers (never written yet in this call, so h holds it); both buffers then
                # agree on it, as the copies of the cells that leave the lists keep them
                for c in range(n_fresh):
                    i = fresh[c]
                    if cell_sync[i] != call:
                        cell_sync[i] = call
                        h_work[i] = h[i]
                        hu_work[i] = hu[i]
                        hv_work[i] = hv[i]
                        synced[n_synced] = i
                        n_synced += 1
        n_changed = n_touched if not STRUCTURED else 0
        for attempt in range(MAX_RETRIES):
            t_new = t_target if last else t + dt
            # the lists are the last step's (or this step's last attempt's): the order-1
            # face step keeps what it made of them (their runs and pieces)
            same_lists = same_wet or attempt > 0
            wet_changes = -1  # (the order-1 face steps count the cells wet or dry anew)
            fallbacks = 0
            if STRUCTURED and not ORDER2:
                ok, out, lim, moving, film, clamped, kinetic = profile_step(
                    face_cells[0, 1], face_cells[n, 1], cell_area[0], cfl_factor, density,
                    gamma_x, gamma_z, p_kappa, cur_h, cur_hu, nxt_h, nxt_hu, nxt_hv, flag, law,
                    params, g, dirac, h_dry, h_zero, dt, dt_decide, t_new, peak_h, peak_speed,
                    arrival, last_moved, True, p_work, p_flag)
            elif (not ORDER2 and PARALLEL and n_touched >= min_parallel_cells
                  and (same_lists or n_touched // 2 >= min_parallel_cells)):
                # the same on threads, each on its piece of the faces (the same bits); on
                # lists that changed, from twice as many cells (it cuts them and finds the
                # cells its pieces share again: a pile spreading over 18k nodes ran 0.90x
                # on 2 threads from 8,192, 0.98x from 16,384; on kept lists, 10k nodes all
                # wet, 1.5x from 8,192)
                ok, out, lim, moving, film, clamped, kinetic, wet_changes = faces_step_threads(
                    face_cells, face_frame, face_length, cell_area, cfl_factor, density,
                    gamma_x, gamma_y, gamma_z, cur_h, cur_hu, cur_hv, nxt_h, nxt_hu, nxt_hv,
                    transport, flag, law, params, g, dirac, h_dry, h_zero, dt, dt_decide,
                    t_new, peak_h, peak_speed, arrival, last_moved, active_faces, n_active,
                    touched, n_touched, same_lists, face_stamp, list_stamp, sweep_geo,
                    sweep_work)
            elif not ORDER2:  # step_faces with its cell passes vectorised, its law's copy
                ok, out, lim, moving, film, clamped, kinetic, wet_changes = faces_step(
                    face_cells, face_frame, face_length, cell_area, cfl_factor, density,
                    gamma_x, gamma_y, gamma_z, cur_h, cur_hu, cur_hv, nxt_h, nxt_hu, nxt_hv,
                    transport, flag, law, params, g, dirac, h_dry, h_zero, dt, dt_decide,
                    t_new, peak_h, peak_speed, arrival, last_moved, active_faces, n_active,
                    touched, n_touched, same_lists, face_stamp, list_stamp, sweep_geo,
                    sweep_work)
            elif STRUCTURED:  # order 2, profile: stage 1 (cur -> nxt), stage 2 (nxt -> s)
                reconstruct_profile(cur_h, cur_hu, h_zero, limiter, recon)
                ok, out, lim, moving, film, clamped, kinetic = step_profile(
                    face_cells, cell_area, cfl_factor, density, gamma_x, gamma_y, gamma_z,
                    curvature,
                    cur_h, cur_hu, cur_hv, nxt_h, nxt_hu, nxt_hv, flux, flag,
                    law, params, g, dirac, h_dry, h_zero, dt, dt_decide, t_new, peak_h, peak_speed,
                    arrival, last_moved, True, recon, False)
                if ok:
                    flag1[:] = flag
                    reconstruct_profile(nxt_h, nxt_hu, h_zero, limiter, recon)
                    ok, out2, lim, moving, film, clamped2, kinetic = step_profile(
                        face_cells, cell_area, cfl_factor, density, gamma_x, gamma_y, gamma_z,
                        curvature,
                        nxt_h, nxt_hu, nxt_hv, s_h, s_hu, s_hv, flux, flag,
                        law, params, g, dirac, h_dry, h_zero, dt, dt_decide, t_new, peak_h,
                        peak_speed, arrival, last_moved, True, recon, False)
                if ok:
                    out = 0.5 * (out + out2)
                    clamped += clamped2
                    profile_transport(flag, flux, dirac, transport)
                    lim, moving, film, kinetic, fallbacks = heun_faces(
                        all_cells, h.size, cur_h, cur_hu, cur_hv, s_h, s_hu, s_hv, flag1,
                        transport, cell_area, cfl_factor, gamma_z, g, h_dry, h_zero, t_new,
                        peak_h, peak_speed, arrival, last_moved, nxt_h, nxt_hu, nxt_hv)
            else:  # order 2 on faces, each stage on its own active lists
                ok, out, lim, moving, film, clamped, kinetic = order2_stage(
                    face_cells, face_frame, face_length, face_offset, cell_area, cfl_factor,
                    density, gamma_x, gamma_y, gamma_z, curvature, cur_h, cur_hu, cur_hv,
                    nxt_h, nxt_hu, nxt_hv, flux, transport, flag, law, params, g, dirac,
                    h_dry, h_zero, dt, dt_decide, t_new, peak_h, peak_speed, arrival,
                    last_moved, active_faces, n_active, touched, n_touched, cell_face_ptr,
                    cell_face_idx, velocity, face_state, no_emit, cell_sums,
                    min_parallel_cells)
                if ok:
                    n_wet2 = 0
                    for c in range(n_touched):
                        i = touched[c]
                        flag1[i] = flag[i]
                        s_h[i] = nxt_h[i]  # stage 2 rewrites only its own touched cells
                        s_hu[i] = nxt_hu[i]
                        s_hv[i] = nxt_hv[i]
                        if nxt_h[i] > h_zero:
                            wet2[n_wet2] = i
                            n_wet2 += 1
                    # fresh stamps for each attempt: stage 1 listed with the step's first
                    stamp = STAMPS_PER_STEP * (clock[0] + steps) + 2 * attempt
                    n_active2, n_touched2 = activate(wet2, n_wet2, cell_face_ptr, cell_face_idx,
                                                     face_cells, face_stamp, cell_stamp,
                                                     stamp + 1, active2, touched2)
                    ok, out2, lim, moving, film, clamped2, kinetic = order2_stage(
                        face_cells, face_frame, face_length, face_offset, cell_area,
                        cfl_factor, density, gamma_x, gamma_y, gamma_z, curvature, nxt_h,
                        nxt_hu, nxt_hv, s_h, s_hu, s_hv, flux, transport, flag, law, params, g,
                        dirac, h_dry, h_zero, dt, dt_decide, t_new, peak_h, peak_speed,
                        arrival, last_moved, active2, n_active2, touched2, n_touched2,
                        cell_face_ptr, cell_face_idx, velocity, face_state, no_emit, cell_sums,
                        min_parallel_cells)
                if ok:
                    out = 0.5 * (out + out2)
                    clamped += clamped2
                    n_changed = merge_lists(touched, n_touched, touched2, n_touched2, cell_stamp,
                                            stamp + 2, union)
                    if PARALLEL and n_changed >= min_parallel_cells:
                        lim, moving, film, kinetic, fallbacks = heun_cells_parallel(
                            union, n_changed, cur_h, cur_hu, cur_hv, s_h, s_hu, s_hv, flag1,
                            transport, cell_area, cfl_factor, gamma_z, g, h_dry, h_zero,
                            t_new, peak_h, peak_speed, arrival, last_moved, nxt_h, nxt_hu,
                            nxt_hv, cell_sums)
                    else:
                        lim, moving, film, kinetic, fallbacks = heun_faces(
                            union, n_changed, cur_h, cur_hu, cur_hv, s_h, s_hu, s_hv, flag1,
                            transport, cell_area, cfl_factor, gamma_z, g, h_dry, h_zero,
                            t_new, peak_h, peak_speed, arrival, last_moved, nxt_h, nxt_hu,
                            nxt_hv)
                    for c in range(n_changed):
                        flag1[union[c]] = DRY
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
        if not STRUCTURED:
            changed = union if ORDER2 else touched
            # the new wet cells (only the changed ones can be). At order 1 those that became
            # wet or dry, from both sorted lists: a next step on the same wet cells keeps this
            # step's active lists (a flow at rest or covering its whole mesh lists nothing
            # again), and on a few changes they are mended (order 2 lists with stamps of its
            # own in each stage). An order-1 face step counts the touched cells that became
            # wet or dry: with none, the wet cells are the last step's, and are not looked
            # for again (a scan of every touched cell, 0.4 ms a step on 161k)
            n_gained = 0
            n_lost = 0
            if wet_changes != 0:  # (none: the wet cells are the last step's, so is wet)
                wet, wet_last = wet_last, wet
                n_new = 0
                p = 0
                for c in range(n_changed):
                    i = changed[c]
                    if nxt_h[i] > h_zero:
                        if not ORDER2:
                            while p < n_wet and wet_last[p] < i:
                                lost[n_lost] = wet_last[p]
                                n_lost += 1
                                p += 1
                            if p < n_wet and wet_last[p] == i:
                                p += 1
                            else:
                                gained[n_gained] = i
                                n_gained += 1
                        wet[n_new] = i
                        n_new += 1
                if not ORDER2:
                    while p < n_wet:
                        lost[n_lost] = wet_last[p]
                        n_lost += 1
                        p += 1
                n_wet = n_new
            same_wet = not ORDER2 and n_gained == 0 and n_lost == 0
            n_previous = n_changed
        stats[ST_FALLBACK] += fallbacks
        cur_h, nxt_h = nxt_h, cur_h
        cur_hu, nxt_hu = nxt_hu, cur_hu
        cur_hv, nxt_hv = nxt_hv, cur_hv
        status = record_step(stats, dt, lim, moving, film, kinetic, clamped, out, stop_volume,
                             stop_kinetic, steps, max_steps)
        if status != REACHED_TARGET:
            break
    clock[0] += steps + 1  # the next call's stamps follow this one's
    if STRUCTURED or ORDER2:
        end_loop(stats, t, steps, h, hu, hv, cur_h, cur_hu, cur_hv)
    else:  # the newest state back only where a step touched, if it is in the work buffers
        if steps % 2 == 1:
            for c in range(n_synced):
                i = synced[c]
                h[i] = cur_h[i]
                hu[i] = cur_hu[i]
                hv[i] = cur_hv[i]
        record_end(stats, t, steps)
    return status


# The order-1 profile sweep lives in its own module, which builds on this one's scalar
# functions: imported last, before the copies of _advance are made (each copy's globals are
# a snapshot of this module's, taken then).
from avflow.numerics.profile import N_WORK as _PROFILE_WORK  # noqa: E402
from avflow.numerics.profile import STEP as _PROFILE_STEP  # noqa: E402

from avflow.numerics.face_sweep import STEP as _FACES_STEP  # noqa: E402
from avflow.numerics.face_sweep import STEP_THREADS as _FACES_THREADS  # noqa: E402
from avflow.numerics.face_gather import N_SUMS  # noqa: E402
from avflow.numerics.face_gather import heun_cells_parallel as _heun_parallel  # noqa: E402
from avflow.numerics.face_gather import step_cells_parallel as _step_parallel  # noqa: E402
from avflow.numerics.reconstruction import reconstruct_cells_parallel as _recon_par  # noqa: E402

#: Placeholders of the order-1 sweeps :func:`_advance`'s copies call (their law's copy):
#: the profile's and the faces' (:mod:`avflow.numerics.face_sweep`; on threads, in the
#: copy with threads, its step on threads)
profile_step = None
faces_step = None
faces_step_threads = None


def _stage_faces(face_cells, face_frame, face_length, face_offset, cell_area, cfl_factor,
                 density, gamma_x, gamma_y, gamma_z, curvature, h, hu, hv, h_new, hu_new,
                 hv_new, flux, transport, flag, law, params, g, dirac, h_dry, h_zero, dt,
                 dt_decide, t_new, peak_h, peak_speed, arrival, last_moved, active_faces,
                 n_active, touched, n_touched, cell_face_ptr, cell_face_idx, velocity,
                 face_state, no_emit, cell_sums, min_parallel_cells):
    """One stage of order 2 on faces, from ``(h, hu, hv)`` into ``(h_new, hu_new, hv_new)``
    on the listed faces and cells: the reconstruction (``face_state``), then the step.
    In the copy with threads (``PARALLEL``) a stage of at least ``min_parallel_cells``
    cells runs both in gather form on Numba's threads (:mod:`avflow.numerics.face_gather`,
    the same bits), any other on :func:`reconstruct_cells` and :func:`step_faces`.
    Returns step_faces' ``(ok, outflow, dt_limit, moving, film, clamped, kinetic)``."""
    if PARALLEL and n_touched >= min_parallel_cells:
        reconstruct_cells_parallel(face_cells, face_frame, face_length, face_offset,
                                   cell_area, h, hu, hv, h_zero, cell_face_ptr, cell_face_idx,
                                   touched, n_touched, velocity, face_state)
        return step_cells_parallel(
            face_cells, face_frame, face_length, cell_area, cfl_factor, density, gamma_x,
            gamma_y, gamma_z, curvature, h, hu, hv, h_new, hu_new, hv_new, flux, transport,
            flag, law, params, g, dirac, h_zero, h_dry, dt, dt_decide, active_faces, n_active,
            touched, n_touched, cell_face_ptr, cell_face_idx, face_state, cell_sums)
    reconstruct_cells(face_cells, face_frame, face_length, face_offset, cell_area, h, hu, hv,
                      h_zero, cell_face_ptr, cell_face_idx, touched, n_touched, velocity,
                      face_state)
    return step_faces(face_cells, face_frame, face_length, cell_area, cfl_factor, density,
                      gamma_x, gamma_y, gamma_z, curvature, h, hu, hv, h_new, hu_new, hv_new,
                      flux, transport, flag, law, params, g, dirac, h_dry, h_zero, dt,
                      dt_decide, t_new, peak_h, peak_speed, arrival, last_moved, active_faces,
                      n_active, touched, n_touched, True, face_state, False, no_emit)


#: Placeholders of the constants of :func:`_advance`'s and :func:`_stage_faces`' copies (see
#: :func:`time_loop`), and of what their copies with threads call (none in the others)
STRUCTURED = ORDER2 = PARALLEL = False
reconstruct_cells_parallel = step_cells_parallel = heun_cells_parallel = order2_stage = None

#: :func:`_stage_faces` serial and with threads, each under its own name
ORDER2_STAGE = {
    False: specialize(_stage_faces, "_serial", PARALLEL=False),
    True: specialize(_stage_faces, "_parallel", PARALLEL=True,
                     reconstruct_cells_parallel=_recon_par, step_cells_parallel=_step_parallel)}


def _advance_for(structured: bool, order2: bool, kind: int | None = None,
                 parallel: bool = False):
    """:func:`_advance` compiled with the mesh kind and the order constants (and, at order
    1, calling the sweep of the friction law ``kind``; ``parallel``: the face kernel with
    its passes on threads, whose functions the other copies never compile)."""
    suffix = f"_{'profile' if structured else 'faces'}_order{2 if order2 else 1}"
    names = {}
    if kind is not None:
        suffix += "_" + law_label(kind)
        if structured:
            names["profile_step"] = _PROFILE_STEP[kind]
        else:
            names["faces_step"] = _FACES_STEP[kind]
            if parallel:
                names["faces_step_threads"] = _FACES_THREADS[kind]
    if parallel:
        suffix += "_parallel"
        names["heun_cells_parallel"] = _heun_parallel
    return specialize(_advance, suffix, STRUCTURED=structured, ORDER2=order2,
                      PARALLEL=parallel, order2_stage=ORDER2_STAGE[parallel], **names)


#: The time loop per (structured, order 2, law kind, threads): the law only at order 1,
#: whose sweeps have a copy per law (:data:`avflow.numerics.profile.STEP`,
#: :data:`avflow.numerics.face_sweep.STEP`), None at order 2; threads only on faces
ADVANCE = {(s, o, k, p): _advance_for(s, o, k, p)
           for s, o, kinds, threads in (
               (True, False, tuple(_PROFILE_STEP), (False,)), (True, True, (None,), (False,)),
               (False, False, tuple(_FACES_STEP), (False, True)),
               (False, True, (None,), (False, True)))
           for k in kinds for p in threads}


def time_loop(structured: bool, order: int, law: int, parallel: bool = False):
    """The time loop (:func:`_advance`: its arguments, its status codes) compiled for this
    mesh kind (``structured``: a profile) and ``order`` alone (and, at order 1, for the
    friction ``law``); ``parallel``: with the passes on threads (on faces only;
    profiles run the serial copy)."""
    structured, order2 = bool(structured), order == 2
    parallel = bool(parallel) and not structured
    return ADVANCE[structured, order2, None if order2 else law_kind(law), parallel]
