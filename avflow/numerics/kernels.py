"""The traversals of one time step on profiles and face lists (seed section 3, eqs. 26-56).

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

from avflow.numerics.cpu import DRY, FACE_INNER, FACE_OPEN, FACE_WALL, INLINED
from avflow.numerics.physics import MIDPOINT
from avflow.numerics.vectorize import cell_law
from avflow.terrain.mesh import OUTFLOW, WALL

(carries, cell_moves, centripetal_accel, dirac_face, dt_from_inverse, emitted_state, emitting,
 face_flux, cell_update, half_fluxes, heun_average, observe_cell, open_mass, outflow_volume,
 side_fluxes, sound_speed, speed_of, step_terms, take_back, trial_momentum) = (
    INLINED[name] for name in (
        "carries", "cell_moves", "centripetal_accel", "dirac_face", "dt_from_inverse",
        "emitted_state", "emitting", "face_flux", "cell_update", "half_fluxes", "heun_average",
        "observe_cell", "open_mass", "outflow_volume", "side_fluxes", "sound_speed",
        "speed_of", "step_terms", "take_back", "trial_momentum"))


@njit(error_model="numpy", cache=True)
def dt_limit(cfl_factor, gamma_z, h, hu, hv, g):
    """Largest stable time step (cfl = 1) of a state: min 2 A / (P (|u| + sqrt(3) c)), eq. 41."""
    inv_lim = 0.0
    for i in range(h.size):
        speed, inv_i = observe_cell(h[i], math.sqrt(hu[i] * hu[i] + hv[i] * hv[i]), cfl_factor[i],
                                gamma_z[i], g)
        inv_lim = max(inv_lim, inv_i)
    return dt_from_inverse(inv_lim)


@njit(error_model="numpy", cache=True)
def _profile_fluxes2(recon, h, h_zero, density, gamma_z, g, left, right, flux):
    """Face fluxes of a profile from the reconstructed states (order 2); boundaries as in
    :func:`step_profile` (mirror walls; open ends closed to what would enter)."""
    n = h.size
    _, _, fm_h, fm_q = side_fluxes(recon[0, 0], recon[0, 1], h[0] > h_zero, density[0],
                                    g * gamma_z[0])
    if left == WALL:
        flux[0, 0] = 0.0
        flux[0, 1] = 2.0 * fm_q
    else:
        gp_h, gp_q, _, _ = side_fluxes(recon[0, 0], min(recon[0, 1], 0.0), h[0] > h_zero,
                                        density[0], g * gamma_z[0])
        flux[0, 0] = -open_mass(-(gp_h + fm_h))
        flux[0, 1] = gp_q + fm_q
    for i in range(1, n):
        k = i - 1
        fp_h, fp_q, _, _ = side_fluxes(recon[k, 2], recon[k, 3], h[k] > h_zero, density[k],
                                        g * gamma_z[k])
        _, _, fm_h, fm_q = side_fluxes(recon[i, 0], recon[i, 1], h[i] > h_zero, density[i],
                                        g * gamma_z[i])
        flux[i, 0] = fp_h + fm_h
        flux[i, 1] = fp_q + fm_q
    k = n - 1
    fp_h, fp_q, _, _ = side_fluxes(recon[k, 2], recon[k, 3], h[k] > h_zero, density[k],
                                    g * gamma_z[k])
    if right == WALL:
        flux[n, 0] = 0.0
        flux[n, 1] = 2.0 * fp_q
    else:
        _, _, gm_h, gm_q = side_fluxes(recon[k, 2], max(recon[k, 3], 0.0), h[k] > h_zero,
                                        density[k], g * gamma_z[k])
        flux[n, 0] = open_mass(fp_h + gm_h)
        flux[n, 1] = fp_q + gm_q


@njit(error_model="numpy", cache=True)
def step_profile(mesh, physics, cur, nxt, flux, flag, when, order2, recon):
    """One step on a profile (faces in line order, uniform dx), the face loop fused into the
    cell loops: the time loop runs it at order 2; at order 1 it runs the vectorised
    :func:`avflow.numerics.profile.step`, and this fused sweep is the reference that one is
    tested against, bit for bit (``tests/test_profile_sweep.py``).

    Same arithmetic as :func:`step_faces`.
    With ``order2`` the faces see the reconstructed states ``recon`` (h_L, u_L, h_R, u_R per
    cell, :func:`avflow.numerics.reconstruction.reconstruct_profile`) instead of the averages.
    The running maps are not written here: the time loop observes each accepted step
    (:mod:`avflow.numerics.observers`).
    ``flux[k, 0]`` is the mass flux (m^2/s) through face k towards +x, ``flux[k, 1]`` its
    momentum flux. Returns
    ``(ok, outflow, dt_limit, moving, film, clamped, kinetic)`` (see :func:`step_faces`).
    """
    face_cells, cell_area, cfl_factor = mesh.face_cells, mesh.cell_area, mesh.cfl_factor
    density, gamma_x, gamma_z = mesh.density, mesh.gamma_x, mesh.gamma_z
    curvature, h, hu, h_new = mesh.curvature, cur.h, cur.hu, nxt.h
    hu_new, hv_new, law, params, g = nxt.hu, nxt.hv, physics.law, physics.params, physics.g
    dirac, h_dry, h_zero, dt = physics.dirac, physics.h_dry, physics.h_zero, when.dt
    dt_decide = when.dt_decide
    n = h.size
    dx = cell_area[0]
    left = face_cells[0, 1]
    right = face_cells[n, 1]
    p0, p1, p2, p3 = params[0, 0], params[0, 1], params[0, 2], params[0, 3]
    p4, p5, p6, p7 = params[0, 4], params[0, 5], params[0, 6], params[0, 7]

    # --- sweep 1: fluxes (every normal along +x), trial state, threshold flags
    if order2:
        _profile_fluxes2(recon, h, h_zero, density, gamma_z, g, left, right, flux)
        for k in range(n):
            hk = emitting(h[k], h_zero)
            uk = abs(hu[k] / hk) if hk > 0.0 else 0.0
            pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(law, params, k, p0, p1, p2, p3,
                                                              p4, p5, p6, p7)
            qx, _, fk = trial_momentum(h[k], h_zero, uk, hu[k], 0.0,
                                        (flux[k, 0] - flux[k + 1, 0]) / dx,
                                        (flux[k, 1] - flux[k + 1, 1]) / dx, 0.0, dt, dt_decide,
                                        gamma_x[k], 0.0, gamma_z[k],
                                        curvature[k, 0] * (uk * uk),
                                        law, pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7, g, order2)
            hu_new[k] = qx
            hv_new[k] = uk  # scratch: |u^n| for sweep 2
            flag[k] = fk
    else:
        h0 = emitting(h[0], h_zero)
        c0 = sound_speed(h0, g * gamma_z[0])
        u0 = hu[0] / h0 if h0 > 0.0 else 0.0
        fp_h, fp_q, fm_h, fm_q = half_fluxes(h0, u0, c0, c0 * density[0])
        if left == WALL:  # mirror ghost (h, -u): no mass, twice the pressure
            fl_h = 0.0
            fl_q = 2.0 * fm_q
        else:  # open: transmissive for what leaves, closed to what would enter
            gp_h, gp_q, _, _ = half_fluxes(h0, min(u0, 0.0), c0, c0 * density[0])
            fl_h = open_mass(-(gp_h + fm_h)) * -1.0
            fl_q = gp_q + fm_q
        flux[0, 0] = fl_h
        flux[0, 1] = fl_q
        u_prev = u0
        for i in range(1, n + 1):
            if i < n:
                hi = emitting(h[i], h_zero)
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
                    hm = emitting(h[n - 1], h_zero)
                    um = hu[n - 1] / hm if hm > 0.0 else 0.0
                    cm = sound_speed(hm, g * gamma_z[n - 1])
                    _, _, gm_h, gm_q = half_fluxes(hm, max(um, 0.0), cm, cm * density[n - 1])
                    fr_h = open_mass(fp_h + gm_h)
                    fr_q = fp_q + gm_q
            flux[i, 0] = fr_h
            flux[i, 1] = fr_q
            k = i - 1  # cell k is complete: faces k (left) and k + 1 (right)
            pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(law, params, k, p0, p1, p2, p3,
                                                              p4, p5, p6, p7)
            qx, _, fk = trial_momentum(h[k], h_zero, abs(u_prev), hu[k], 0.0, (fl_h - fr_h) / dx,
                                        (fl_q - fr_q) / dx, 0.0, dt, dt_decide, gamma_x[k], 0.0,
                                        gamma_z[k], curvature[k, 0] * (u_prev * u_prev),
                                        law, pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7, g, order2)
            hu_new[k] = qx
            hv_new[k] = abs(u_prev)  # scratch: |u^n| for sweep 2 (hv is identically 0 on a line)
            flag[k] = fk
            u_prev = ui
            fl_h = fr_h
            fl_q = fr_q
            fp_h, fp_q = np_h, np_q

    # --- sweep 2: mass with the Dirac switch, projection
    outflow = 0.0
    inv_lim = 0.0
    moving = 0.0
    film = 0.0
    clamped = 0
    kinetic = 0.0
    for k in range(n):
        fk = flag[k]
        dirac_l = dirac_face(dirac, fk, flag[k - 1] if k > 0 else fk)
        dirac_r = dirac_face(dirac, fk, flag[k + 1] if k < n - 1 else fk)
        fl = 0.0 if dirac_l else flux[k, 0]
        fr = 0.0 if dirac_r else flux[k + 1, 0]
        # A dry cell takes momentum only with mass: a Dirac face (a resting neighbour)
        # carries neither, not even its pressure (zero temperature, eq. 53).
        form_dry = fk == DRY and (dirac_l or dirac_r)
        q = hu_new[k]
        if form_dry:
            q = (0.0 if dirac_l else flux[k, 1]) - (0.0 if dirac_r else flux[k + 1, 1])
        speed_n = hv_new[k]
        pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(law, params, k, p0, p1, p2, p3,
                                                          p4, p5, p6, p7)
        hn, qx, _, cl = cell_update(form_dry, fk, h[k], fl - fr, q, 0.0, dx, dt, gamma_x[k], 0.0,
                                    gamma_z[k], curvature[k, 0] * (speed_n * speed_n), speed_n,
                                    law, pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7, g, h_zero,
                                    order2, True)
        if hn < 0.0:
            return False, 0.0, 0.0, 0.0, 0.0, 0, 0.0
        if k == 0 and left == OUTFLOW:
            outflow += outflow_volume(-fl, dt)
        if k == n - 1 and right == OUTFLOW:
            outflow += outflow_volume(fr, dt)
        h_new[k] = hn
        hu_new[k] = qx
        hv_new[k] = 0.0
        clamped += cl
        speed, inv_k = observe_cell(hn, abs(qx), cfl_factor[k], gamma_z[k], g)
        inv_lim = max(inv_lim, inv_k)
        moves = cell_moves(speed, speed_n, carries(max(abs(fl), abs(fr)), hn, speed_n, 1.0))
        kin, mov, fil = step_terms(hn, dx, speed, moves, h_dry)
        kinetic += kin
        moving += mov
        film += fil
    return True, outflow, dt_from_inverse(inv_lim), moving, film, clamped, kinetic


@njit(error_model="numpy", cache=True, inline="always")
def reconstructed_sides(f, i, j, h, h_zero, face_state, g, gamma_z, density, direct):
    """What the two sides of listed face f emit at order 2 (:func:`emitted_state` of each
    side's reconstructed state at the face, ``face_state[f, side, 0:3] = (h, q1, q2)``, or
    with ``direct`` (MUSCL-Hancock's) the seven values the reconstruction wrote; nothing from
    a cell at or below ``h_zero``): i's seven values, then j's (beyond a boundary, ``j < 0``:
    values the flux does not read)."""
    k = j if j >= 0 else i
    if direct:  # the seven values as the reconstruction wrote them
        wi = h[i] > h_zero
        wj = j >= 0 and h[k] > h_zero
        return ((face_state[f, 0, 0] if wi else 0.0), (face_state[f, 0, 1] if wi else 0.0),
                (face_state[f, 0, 2] if wi else 0.0), (face_state[f, 0, 3] if wi else 0.0),
                (face_state[f, 0, 4] if wi else 0.0), (face_state[f, 0, 5] if wi else 0.0),
                (face_state[f, 0, 6] if wi else 0.0), (face_state[f, 1, 0] if wj else 0.0),
                (face_state[f, 1, 1] if wj else 0.0), (face_state[f, 1, 2] if wj else 0.0),
                (face_state[f, 1, 3] if wj else 0.0), (face_state[f, 1, 4] if wj else 0.0),
                (face_state[f, 1, 5] if wj else 0.0), (face_state[f, 1, 6] if wj else 0.0))
    hi = qi1 = qi2 = 0.0
    if h[i] > h_zero:
        hi, qi1, qi2 = face_state[f, 0, 0], face_state[f, 0, 1], face_state[f, 0, 2]
    hi, ui1, ui2, ci, si, khi, k3i = emitted_state(hi, qi1, qi2, 0.0, g * gamma_z[i],
                                                   density[i])
    hj = qj1 = qj2 = 0.0
    if j >= 0 and h[k] > h_zero:
        hj, qj1, qj2 = face_state[f, 1, 0], face_state[f, 1, 1], face_state[f, 1, 2]
    hj, uj1, uj2, cj, sj, khj, k3j = emitted_state(hj, qj1, qj2, 0.0, g * gamma_z[k],
                                                   density[k])
    return hi, ui1, ui2, ci, si, khi, k3i, hj, uj1, uj2, cj, sj, khj, k3j


@njit(error_model="numpy", cache=True, inline="always")
def listed_flux(f, i, j, face_frame, face_length, hi, ui1, ui2, ci, si, khi, k3i, hj, uj1, uj2,
                cj, sj, khj, k3j):
    """:func:`~avflow.numerics.physics.face_flux` of listed face f between cells i and j (a
    wall or an open side when ``j < 0``, :data:`~avflow.terrain.mesh.WALL` or OUTFLOW), its
    frames from the mesh's ``face_frame``: ``(L F_h, momentum to i (x, y), to j (x, y))``."""
    return face_flux(FACE_INNER if j >= 0 else (FACE_WALL if j == WALL else FACE_OPEN), hi,
                     ui1, ui2, ci, si, khi, k3i, hj, uj1, uj2, cj, sj, khj, k3j,
                     face_frame[f, 0, 0, 0], face_frame[f, 0, 0, 1], face_frame[f, 0, 1, 0],
                     face_frame[f, 0, 1, 1], face_frame[f, 1, 0, 0], face_frame[f, 1, 0, 1],
                     face_frame[f, 1, 1, 0], face_frame[f, 1, 1, 1], face_length[f])


@njit(error_model="numpy", cache=True, inline="always")
def _face_fluxes(mesh, physics, cur, nxt, flux, when, lists, order2, face_state, emit):
    """Sweeps 0 and 1a of :func:`step_faces`: what each cell emits (order 1; order 2 reads
    the reconstructed face states) and the rectangular fluxes of the active faces, each
    side read and written in its own cell's basis, into ``flux`` and the sums of ``nxt``.
    (Each sweep of step_faces is a function of its own, inlined into it by Numba: one
    compiled body, as before the split.)"""
    face_cells, face_frame, face_length = mesh.face_cells, mesh.face_frame, mesh.face_length
    density, gamma_z, h = mesh.density, mesh.gamma_z, cur.h
    hu, hv, h_new = cur.hu, cur.hv, nxt.h
    hu_new, hv_new, g = nxt.hu, nxt.hv, physics.g
    h_zero, active_faces, n_active = physics.h_zero, lists.active_faces, lists.n_active
    touched, n_touched = lists.touched, lists.n_touched
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
             emit[i, 6]) = emitted_state(h[i], hu[i], hv[i], h_zero, g * gamma_z[i], density[i])

    # --- sweep 1a: rectangular fluxes, each side read and written in its own cell's basis
    for a in range(n_active):
        f = active_faces[a]
        i = face_cells[f, 0]
        j = face_cells[f, 1]
        if order2:  # the reconstructed states at the face
            (hi, ui1, ui2, ci, si, khi, k3i, hj, uj1, uj2, cj, sj, khj,
             k3j) = reconstructed_sides(f, i, j, h, h_zero, face_state, g, gamma_z, density,
                                        order2 == MIDPOINT)
        else:
            k = j if j >= 0 else i  # beyond a boundary: values the flux does not read
            hi, ui1, ui2, ci = emit[i, 0], emit[i, 1], emit[i, 2], emit[i, 3]
            si, khi, k3i = emit[i, 4], emit[i, 5], emit[i, 6]
            hj, uj1, uj2, cj = emit[k, 0], emit[k, 1], emit[k, 2], emit[k, 3]
            sj, khj, k3j = emit[k, 4], emit[k, 5], emit[k, 6]
        fh, qix, qiy, qjx, qjy = listed_flux(f, i, j, face_frame, face_length, hi, ui1, ui2, ci,
                                             si, khi, k3i, hj, uj1, uj2, cj, sj, khj, k3j)
        flux[f, 0] = fh
        flux[f, 1] = qix
        flux[f, 2] = qiy
        h_new[i] -= fh
        hu_new[i] -= qix
        hv_new[i] -= qiy
        if j >= 0:
            flux[f, 3] = qjx
            flux[f, 4] = qjy
            h_new[j] += fh
            hu_new[j] += qjx
            hv_new[j] += qjy


@njit(error_model="numpy", cache=True, inline="always")
def _face_trials(mesh, physics, cur, nxt, flag, when, lists, order2):
    """Sweep 1b of :func:`step_faces`: the trial momentum and the threshold flag of each
    touched cell (eqs. 47, 49)."""
    cell_area, gamma_x, gamma_y = mesh.cell_area, mesh.gamma_x, mesh.gamma_y
    gamma_z, curvature, h = mesh.gamma_z, mesh.curvature, cur.h
    hu, hv, h_new = cur.hu, cur.hv, nxt.h
    hu_new, hv_new, law = nxt.hu, nxt.hv, physics.law
    params, g, h_zero = physics.params, physics.g, physics.h_zero
    dt, dt_decide = when.dt, when.dt_decide
    touched, n_touched = lists.touched, lists.n_touched
    p0, p1, p2, p3 = params[0, 0], params[0, 1], params[0, 2], params[0, 3]
    p4, p5, p6, p7 = params[0, 4], params[0, 5], params[0, 6], params[0, 7]
    # --- sweep 1b: trial state and threshold flags
    for c in range(n_touched):
        i = touched[c]
        if h[i] <= h_zero:  # dry: keep the momentum rate, formed in sweep 2b with its mass
            flag[i] = DRY
            h_new[i] = 0.0
            continue
        inv_area = 1.0 / cell_area[i]
        pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(law, params, i, p0, p1, p2, p3,
                                                          p4, p5, p6, p7)
        qx, qy, fi = trial_momentum(h[i], h_zero, speed_of(h[i], hu[i], hv[i]), hu[i], hv[i],
                                     h_new[i] * inv_area, hu_new[i] * inv_area,
                                     hv_new[i] * inv_area, dt, dt_decide, gamma_x[i],
                                     gamma_y[i], gamma_z[i],
                                     centripetal_accel(curvature, i, h[i], hu[i], hv[i]),
                                     law, pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7, g, order2)
        hu_new[i] = qx
        hv_new[i] = qy
        flag[i] = fi
        h_new[i] = 0.0


@njit(error_model="numpy", cache=True, inline="always")
def _face_mass(mesh, physics, nxt, flux, transport, flag, when, lists):
    """Sweep 2a of :func:`step_faces`: the mass through the faces that keep the rectangular
    density (the Dirac faces of eq. 53 carry none), each cell's ``transport``. Returns the
    volume that left through open faces."""
    face_cells, face_length = mesh.face_cells, mesh.face_length
    h_new, hu_new, hv_new = nxt.h, nxt.hu, nxt.hv
    dirac, dt, active_faces = physics.dirac, when.dt, lists.active_faces
    n_active, touched, n_touched = lists.n_active, lists.touched, lists.n_touched
    # --- sweep 2a: mass through the faces that keep the rectangular density
    outflow = 0.0
    for c in range(n_touched):
        transport[touched[c]] = 0.0
    for a in range(n_active):
        f = active_faces[a]
        i = face_cells[f, 0]
        j = face_cells[f, 1]
        d = dirac_face(dirac, flag[i], flag[j] if j >= 0 else flag[i])
        if d:  # a dry side takes back what the face brought to its trial's sum
            if flag[i] == DRY:
                hu_new[i] = take_back(hu_new[i], -flux[f, 1], d)
                hv_new[i] = take_back(hv_new[i], -flux[f, 2], d)
            if j >= 0 and flag[j] == DRY:
                hu_new[j] = take_back(hu_new[j], flux[f, 3], d)
                hv_new[j] = take_back(hv_new[j], flux[f, 4], d)
            continue
        fh = flux[f, 0]
        h_new[i] -= fh
        unit = abs(fh) / face_length[f]
        transport[i] = max(transport[i], unit)
        if j >= 0:
            h_new[j] += fh
            transport[j] = max(transport[j], unit)
        elif j == OUTFLOW:
            outflow += outflow_volume(fh, dt)
    return outflow


@njit(error_model="numpy", cache=True, inline="always")
def _face_finals(mesh, physics, cur, nxt, transport, flag, when, lists, order2):
    """Sweep 2b of :func:`step_faces`: the new thickness, the projection of eq. 50 and the
    step's sums. Returns ``(ok, dt_limit, moving, film, clamped,
    kinetic)``."""
    cell_area, cfl_factor, gamma_x = mesh.cell_area, mesh.cfl_factor, mesh.gamma_x
    gamma_y, gamma_z, curvature = mesh.gamma_y, mesh.gamma_z, mesh.curvature
    h, hu, hv = cur.h, cur.hu, cur.hv
    h_new, hu_new, hv_new = nxt.h, nxt.hu, nxt.hv
    law, params, g = physics.law, physics.params, physics.g
    h_dry, h_zero, dt = physics.h_dry, physics.h_zero, when.dt
    touched, n_touched = lists.touched, lists.n_touched
    p0, p1, p2, p3 = params[0, 0], params[0, 1], params[0, 2], params[0, 3]
    p4, p5, p6, p7 = params[0, 4], params[0, 5], params[0, 6], params[0, 7]
    # --- sweep 2b: new thickness, projection
    inv_lim = 0.0
    moving = 0.0
    film = 0.0
    clamped = 0
    kinetic = 0.0
    for c in range(n_touched):
        i = touched[c]
        area = cell_area[i]
        speed_n = speed_of(h[i], hu[i], hv[i])
        pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(law, params, i, p0, p1, p2, p3,
                                                          p4, p5, p6, p7)
        hn, qx, qy, cl = cell_update(flag[i] == DRY, flag[i], h[i], h_new[i], hu_new[i],
                                     hv_new[i], area, dt, gamma_x[i], gamma_y[i], gamma_z[i],
                                     centripetal_accel(curvature, i, h[i], hu[i], hv[i]),
                                     speed_n, law, pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7, g,
                                     h_zero, order2, False)
        if hn < 0.0:
            return False, 0.0, 0.0, 0.0, 0, 0.0
        h_new[i] = hn
        hu_new[i] = qx
        hv_new[i] = qy
        clamped += cl
        speed, inv_i = observe_cell(hn, math.sqrt(qx * qx + qy * qy), cfl_factor[i], gamma_z[i], g)
        inv_lim = max(inv_lim, inv_i)
        moves = cell_moves(speed, speed_n, carries(transport[i], hn, speed_n, 1.0))
        kin, mov, fil = step_terms(hn, area, speed, moves, h_dry)
        kinetic += kin
        moving += mov
        film += fil
    return True, dt_from_inverse(inv_lim), moving, film, clamped, kinetic


# no reference counts: each helper Numba inlines that takes an array (the face's sides,
# its flux, a cell's law) counted each array up and down in every face's and cell's
# iteration, atomically: half the step's time at order 2 (docs/performance.md)
@njit(error_model="numpy", cache=True, _nrt=False)
def step_faces(mesh, physics, cur, nxt, flux, transport, flag, when, lists, order2,
               face_state, emit):
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
    _face_fluxes(mesh, physics, cur, nxt, flux, when, lists, order2, face_state, emit)
    _face_trials(mesh, physics, cur, nxt, flag, when, lists, order2)
    outflow = _face_mass(mesh, physics, nxt, flux, transport, flag, when, lists)
    ok, lim, moving, film, clamped, kinetic = _face_finals(mesh, physics, cur, nxt, transport,
                                                          flag, when, lists, order2)
    return ok, outflow if ok else 0.0, lim, moving, film, clamped, kinetic


@njit(error_model="numpy", cache=True)
def profile_transport(flag, flux, dirac, transport):
    """Per cell of a profile, the larger mass flux through its two faces in the step just
    taken (Dirac faces carry none): what :func:`heun_faces` reads as ``transport``."""
    n = flag.size
    for k in range(n):
        fk = flag[k]
        fl = 0.0 if dirac_face(dirac, fk, flag[k - 1] if k > 0 else fk) else flux[k, 0]
        fr = 0.0 if dirac_face(dirac, fk, flag[k + 1] if k < n - 1 else fk) else flux[k + 1, 0]
        transport[k] = max(abs(fl), abs(fr))


@njit(error_model="numpy", cache=True, _nrt=False)  # no reference counts: see step_faces
def heun_faces(cells, n_cells, mesh, physics, start, stage2, flag1, transport, new):
    """Order 2: Heun's average of the two stages over the ``n_cells``
    listed ``cells`` (those either stage changed; all cells on a profile) and the step's
    sums. ``transport`` holds the face fluxes of the stage that last swept each cell.
    Returns ``(dt_limit, moving, film, kinetic, fallbacks)`` as the step kernels do (moving
    cells: u != 0 and a face that carried mass)."""
    h0, hu0, hv0, h2, hu2, hv2 = start.h, start.hu, start.hv, stage2.h, stage2.hu, stage2.hv
    cell_area, cfl_factor, gamma_z = mesh.cell_area, mesh.cfl_factor, mesh.gamma_z
    g, h_dry, h_zero = physics.g, physics.h_dry, physics.h_zero
    h_new, hu_new, hv_new = new.h, new.hu, new.hv
    inv_lim = 0.0
    moving = 0.0
    film = 0.0
    kinetic = 0.0
    fallbacks = 0
    for c in range(n_cells):
        i = cells[c]
        hn, qx, qy, fell_back = heun_average(h0[i], hu0[i], hv0[i], h2[i], hu2[i], hv2[i],
                                             flag1[i], h_zero)
        fallbacks += fell_back
        h_new[i] = hn
        hu_new[i] = qx
        hv_new[i] = qy
        speed, inv_i = observe_cell(hn, math.sqrt(qx * qx + qy * qy), cfl_factor[i], gamma_z[i], g)
        inv_lim = max(inv_lim, inv_i)
        area = cell_area[i]
        speed_n = speed_of(h0[i], hu0[i], hv0[i])
        moves = cell_moves(speed, speed_n, carries(transport[i], hn, speed_n, 1.0))
        kin, mov, fil = step_terms(hn, area, speed, moves, h_dry)
        kinetic += kin
        moving += mov
        film += fil
    return dt_from_inverse(inv_lim), moving, film, kinetic, fallbacks


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
    (cheaper than numpy's stable argsort of the owners: docs/performance.md)."""
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
#: the wet cells (:func:`activate`) beyond it: about where mending stops costing less than
#: listing (measured: docs/performance.md; the new faces are sorted, and where the wet cells
#: are mostly new, their faces are all that are listed)
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
    them, its y faces), and scanning all of it made a step cost more on a larger map;
    weighing the sort against that whole range sorted the faces of a flow on a DEM where a
    scan of their blocks costs far less (docs/performance.md).
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


