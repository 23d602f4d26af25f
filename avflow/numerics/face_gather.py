"""The face kernel's order-2 step in gather form: each cell sums its own faces, on threads.

The same step as :func:`avflow.numerics.kernels.step_faces` at order 2 (seed eqs. 26-56 on
the reconstructed face states: rectangular fluxes, trial momentum and Coulomb threshold,
Dirac faces, projection, curvature and film rules, walls, open sides), bit for bit:
thickness, discharge, flags, ``transport`` and the step's sums. ``step_faces`` adds each
face's flux to its two cells as it meets the face (a scatter: two faces of one cell met by
two threads would write the same place); here each pass writes only its own face or its
own cell, so the passes run on Numba's threads with no races, and the answer is the same on
any number of threads:

1. per active face: its fluxes (mass, and the momentum brought to each side) into
   ``flux[f]``, as step_faces computes them;
2. per touched cell: the sum of its active faces' fluxes, in index order
   (:func:`avflow.numerics.kernels.cell_faces` lists a cell's faces that way; step_faces
   meets them in that order, so every sum is the same), then its trial momentum (eq. 47)
   and Coulomb flag (eq. 49);
3. per touched cell: the mass through its faces that are not Dirac (eqs. 51-53, from both
   sides' flags) and what a dry cell takes back through a Dirac face, again in index order;
4. per touched cell: the new thickness and the projection of eq. 50; its terms of the
   step's sums into ``cell_sums``, added afterwards cell after cell in the list's order
   (step_faces' order), as is the volume that left through open faces (face order).

A face is active (listed by :func:`~avflow.numerics.kernels.activate`) when a side is wet,
``h > h_zero``: a cell reads that from the state rather than from the lists' stamps, which
the second stage of a step overwrites.

Written apart from step_faces on purpose, as :mod:`avflow.numerics.face_sweep` is: a helper
they shared would hide its faults from the test that holds one to the other
(``tests/test_face_gather.py``).
"""

from __future__ import annotations

import math

from numba import njit, prange

from avflow.numerics.cpu import (DRY, carries, cell_moves, cell_update, centripetal_accel,
                                 dirac_face, dt_from_inverse, heun_average, observe_cell,
                                 outflow_volume, speed_of, step_terms, take_back,
                                 trial_momentum)
from avflow.numerics.kernels import listed_flux, reconstructed_sides
from avflow.numerics.physics import MIDPOINT
from avflow.terrain.mesh import OUTFLOW
from avflow.numerics.vectorize import cell_law, specialize

#: A stage (or Heun's merge) that sweeps fewer cells than this runs serially, on step_faces
#: and heun_faces (the measured break-even: docs/performance.md, Order 2 on every core)
MIN_PARALLEL_CELLS = 1024

# Columns of the per-cell work array ``cell_sums`` (n, N_SUMS): a cell's terms of the sums
S_FAIL, S_INV, S_MOVING, S_FILM, S_KINETIC, S_COUNT = range(6)
N_SUMS = 6


@njit(error_model="numpy", cache=True, inline="always")
def _gather_fluxes(mesh, physics, cur, flux, when, lists, face_state, timing):
    """Pass 1 of :func:`step_cells`: each active face's fluxes into ``flux[f]``, each side
    in its own cell's basis. (Each pass is a function of its own, inlined by Numba into
    step_cells' copies: one compiled body, its loops on threads in the parallel copy.)"""
    face_cells, face_frame, face_length = mesh.face_cells, mesh.face_frame, mesh.face_length
    density, gamma_z, h = mesh.density, mesh.gamma_z, cur.h
    g, h_zero, active_faces = physics.g, physics.h_zero, lists.active_faces
    n_active = lists.n_active
    # --- 1: each active face's fluxes, each side in its own cell's basis
    for a in prange(n_active):
        f = active_faces[a]
        i = face_cells[f, 0]
        j = face_cells[f, 1]
        (hi, ui1, ui2, ci, si, khi, k3i, hj, uj1, uj2, cj, sj, khj,
         k3j) = reconstructed_sides(f, i, j, h, h_zero, face_state, g, gamma_z, density,
                                    timing == MIDPOINT)
        fh, qix, qiy, qjx, qjy = listed_flux(f, i, j, face_frame, face_length, hi, ui1, ui2, ci,
                                             si, khi, k3i, hj, uj1, uj2, cj, sj, khj, k3j)
        flux[f, 0] = fh
        flux[f, 1] = qix
        flux[f, 2] = qiy
        if j >= 0:
            flux[f, 3] = qjx
            flux[f, 4] = qjy


@njit(error_model="numpy", cache=True, inline="always")
def _gather_trials(mesh, physics, cur, nxt, flux, flag, when, lists, timing):
    """Pass 2 of :func:`step_cells`: each cell's sum of its active faces (index order), its
    trial momentum (eq. 47) and flag (eq. 49)."""
    face_cells, cell_area, gamma_x = mesh.face_cells, mesh.cell_area, mesh.gamma_x
    gamma_y, gamma_z, curvature = mesh.gamma_y, mesh.gamma_z, mesh.curvature
    h, hu, hv = cur.h, cur.hu, cur.hv
    hu_new, hv_new, law = nxt.hu, nxt.hv, physics.law
    params, g, h_zero = physics.params, physics.g, physics.h_zero
    dt, dt_decide, touched = when.dt, when.dt_decide, lists.touched
    n_touched, cell_face_ptr, cell_face_idx = lists.n_touched, mesh.cell_face_ptr, mesh.cell_face_idx
    p0, p1, p2, p3 = params[0, 0], params[0, 1], params[0, 2], params[0, 3]
    p4, p5, p6, p7 = params[0, 4], params[0, 5], params[0, 6], params[0, 7]
    # --- 2: each cell's sum of its active faces (index order), trial state and flag
    for c in prange(n_touched):
        i = touched[c]
        wet = h[i] > h_zero
        rate_h = 0.0
        rate_x = 0.0
        rate_y = 0.0
        for p in range(cell_face_ptr[i], cell_face_ptr[i + 1]):
            f = cell_face_idx[p]
            if face_cells[f, 0] == i:
                j = face_cells[f, 1]
                if wet or (j >= 0 and h[j] > h_zero):
                    rate_h -= flux[f, 0]
                    rate_x -= flux[f, 1]
                    rate_y -= flux[f, 2]
            elif wet or h[face_cells[f, 0]] > h_zero:
                rate_h += flux[f, 0]
                rate_x += flux[f, 3]
                rate_y += flux[f, 4]
        if not wet:  # dry: keep the momentum rate, formed in pass 4 with its mass
            flag[i] = DRY
            hu_new[i] = rate_x
            hv_new[i] = rate_y
            continue
        inv_area = 1.0 / cell_area[i]
        pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(law, params, i, p0, p1, p2, p3,
                                                          p4, p5, p6, p7)
        qx, qy, fi = trial_momentum(h[i], h_zero, speed_of(h[i], hu[i], hv[i]), hu[i], hv[i],
                                     rate_h * inv_area, rate_x * inv_area, rate_y * inv_area,
                                     dt, dt_decide, gamma_x[i], gamma_y[i], gamma_z[i],
                                     centripetal_accel(curvature, i, h[i], hu[i], hv[i]),
                                     law, pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7, g, timing)
        hu_new[i] = qx
        hv_new[i] = qy
        flag[i] = fi


@njit(error_model="numpy", cache=True, inline="always")
def _gather_mass(mesh, physics, cur, nxt, flux, transport, flag, lists):
    """Pass 3 of :func:`step_cells`: the mass through each cell's faces that are not Dirac
    (eqs. 51-53), what a dry cell takes back through a Dirac face, its ``transport``."""
    face_cells, face_length, h = mesh.face_cells, mesh.face_length, cur.h
    h_new, hu_new, hv_new = nxt.h, nxt.hu, nxt.hv
    dirac, h_zero, touched = physics.dirac, physics.h_zero, lists.touched
    n_touched, cell_face_ptr, cell_face_idx = lists.n_touched, mesh.cell_face_ptr, mesh.cell_face_idx
    # --- 3: mass through the faces that keep the rectangular density (index order)
    for c in prange(n_touched):
        i = touched[c]
        wet = h[i] > h_zero
        dry = flag[i] == DRY
        mass = 0.0
        qx = hu_new[i]
        qy = hv_new[i]
        unit_max = 0.0
        for p in range(cell_face_ptr[i], cell_face_ptr[i + 1]):
            f = cell_face_idx[p]
            k = face_cells[f, 0]
            j = face_cells[f, 1]
            first = k == i
            if first:
                if not (wet or (j >= 0 and h[j] > h_zero)):
                    continue
            elif not (wet or h[k] > h_zero):
                continue
            d = dirac_face(dirac, flag[k], flag[j] if j >= 0 else flag[k])
            if d:  # a dry side takes back what the face brought to its trial's sum
                if dry:
                    if first:
                        qx = take_back(qx, -flux[f, 1], d)
                        qy = take_back(qy, -flux[f, 2], d)
                    else:
                        qx = take_back(qx, flux[f, 3], d)
                        qy = take_back(qy, flux[f, 4], d)
                continue
            fh = flux[f, 0]
            if first:
                mass -= fh
            else:
                mass += fh
            unit_max = max(unit_max, abs(fh) / face_length[f])
        h_new[i] = mass
        hu_new[i] = qx
        hv_new[i] = qy
        transport[i] = unit_max


@njit(error_model="numpy", cache=True, inline="always")
def _gather_finals(mesh, physics, cur, nxt, transport, flag, when, lists, cell_sums,
                   timing):
    """Pass 4 of :func:`step_cells`: the new thickness, the projection of eq. 50, each cell's
    terms of the step's sums into ``cell_sums``."""
    cell_area, cfl_factor, gamma_x = mesh.cell_area, mesh.cfl_factor, mesh.gamma_x
    gamma_y, gamma_z, curvature = mesh.gamma_y, mesh.gamma_z, mesh.curvature
    h, hu, hv = cur.h, cur.hu, cur.hv
    h_new, hu_new, hv_new = nxt.h, nxt.hu, nxt.hv
    law, params, g = physics.law, physics.params, physics.g
    h_zero, h_dry, dt = physics.h_zero, physics.h_dry, when.dt
    touched, n_touched = lists.touched, lists.n_touched
    p0, p1, p2, p3 = params[0, 0], params[0, 1], params[0, 2], params[0, 3]
    p4, p5, p6, p7 = params[0, 4], params[0, 5], params[0, 6], params[0, 7]
    # --- 4: new thickness, projection; each cell's terms of the sums
    for c in prange(n_touched):
        i = touched[c]
        area = cell_area[i]
        speed_n = speed_of(h[i], hu[i], hv[i])
        pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(law, params, i, p0, p1, p2, p3,
                                                          p4, p5, p6, p7)
        hn, qx, qy, cl = cell_update(flag[i] == DRY, flag[i], h[i], h_new[i], hu_new[i],
                                     hv_new[i], area, dt, gamma_x[i], gamma_y[i], gamma_z[i],
                                     centripetal_accel(curvature, i, h[i], hu[i], hv[i]),
                                     speed_n, law, pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7, g,
                                     h_zero, timing, False)
        h_new[i] = hn
        hu_new[i] = qx
        hv_new[i] = qy
        speed, inv_i = observe_cell(hn, math.sqrt(qx * qx + qy * qy), cfl_factor[i], gamma_z[i], g)
        _keep_terms(cell_sums, i, hn < 0.0, inv_i, hn, area, speed,
                    cell_moves(speed, speed_n, carries(transport[i], hn, speed_n, 1.0)), h_dry,
                    cl)


def step_cells(mesh, physics, cur, nxt, flux, transport, flag, when, lists, face_state,
               cell_sums, timing):
    """One order-2 stage on the listed faces and cells (step_faces' arguments at order 2;
    ``cell_face_ptr, cell_face_idx``: the cells' faces in index order; ``cell_sums``: work,
    (n, :data:`N_SUMS`); ``timing``: step_faces' ``order2``, True in Heun's stages,
    :data:`~avflow.numerics.physics.MIDPOINT` in MUSCL-Hancock's). Returns ``(ok, outflow,
    dt_limit, moving, film, clamped, kinetic)`` as step_faces does."""
    _gather_fluxes(mesh, physics, cur, flux, when, lists, face_state, timing)
    _gather_trials(mesh, physics, cur, nxt, flux, flag, when, lists, timing)
    _gather_mass(mesh, physics, cur, nxt, flux, transport, flag, lists)
    _gather_finals(mesh, physics, cur, nxt, transport, flag, when, lists, cell_sums, timing)
    face_cells, dirac, dt = mesh.face_cells, physics.dirac, when.dt
    active_faces, n_active, touched = lists.active_faces, lists.n_active, lists.touched
    n_touched = lists.n_touched
    # the sums, cell after cell in the list's order; the outflow face after face
    failed, lim, moving, film, kinetic, clamped = _add_terms(touched, n_touched, cell_sums)
    if failed:
        return False, 0.0, 0.0, 0.0, 0.0, 0, 0.0
    outflow = 0.0
    for a in range(n_active):
        f = active_faces[a]
        if face_cells[f, 1] == OUTFLOW:
            i = face_cells[f, 0]
            if not dirac_face(dirac, flag[i], flag[i]):
                outflow += outflow_volume(flux[f, 0], dt)
    return True, outflow, lim, moving, film, clamped, kinetic


def heun_cells(cells, n_cells, mesh, physics, start, stage2, flag1, transport, new,
               cell_sums):
    """:func:`avflow.numerics.kernels.heun_faces` on threads: Heun's average of the two
    stages per cell, each cell's terms of the sums into ``cell_sums``,
    added afterwards in the list's order (the same bits). Returns ``(dt_limit, moving, film,
    kinetic, fallbacks)``."""
    h0, hu0, hv0, h2, hu2, hv2 = start.h, start.hu, start.hv, stage2.h, stage2.hu, stage2.hv
    cell_area, cfl_factor, gamma_z = mesh.cell_area, mesh.cfl_factor, mesh.gamma_z
    g, h_dry, h_zero = physics.g, physics.h_dry, physics.h_zero
    h_new, hu_new, hv_new = new.h, new.hu, new.hv
    for c in prange(n_cells):
        i = cells[c]
        # U^{n+1} = (U^n + U**) / 2, the first-order answer q = 0 where the first stage
        # put the cell under the Coulomb threshold (see heun_faces)
        hn, qx, qy, fell_back = heun_average(h0[i], hu0[i], hv0[i], h2[i], hu2[i], hv2[i],
                                             flag1[i], h_zero)
        h_new[i] = hn
        hu_new[i] = qx
        hv_new[i] = qy
        speed, inv_i = observe_cell(hn, math.sqrt(qx * qx + qy * qy), cfl_factor[i], gamma_z[i], g)
        speed_n = speed_of(h0[i], hu0[i], hv0[i])
        _keep_terms(cell_sums, i, False, inv_i, hn, cell_area[i], speed,
                    cell_moves(speed, speed_n, carries(transport[i], hn, speed_n, 1.0)), h_dry,
                    fell_back)
    _, lim, moving, film, kinetic, fallbacks = _add_terms(cells, n_cells, cell_sums)
    return lim, moving, film, kinetic, fallbacks


@njit(error_model="numpy", cache=True, inline="always")
def _keep_terms(cell_sums, i, failed, inv_lim, hn, area, speed, moves, h_dry, count):
    """Cell i's terms of a step's sums (as step_faces and heun_faces add them) into its
    row of ``cell_sums``: whether its thickness turned negative, its inverse CFL limit, its
    kinetic energy, its moving or film volume (``moves``: it carried mass), a count."""
    cell_sums[i, S_FAIL] = 1.0 if failed else 0.0
    cell_sums[i, S_INV] = inv_lim
    cell_sums[i, S_KINETIC], cell_sums[i, S_MOVING], cell_sums[i, S_FILM] = step_terms(
        hn, area, speed, moves, h_dry)
    cell_sums[i, S_COUNT] = count


@njit(error_model="numpy", cache=True, inline="always")
def _add_terms(cells, n_cells, cell_sums):
    """The sums of the listed cells' terms, cell after cell in the list's order (that of
    step_faces and heun_faces: the same bits; a volume that does not move adds 0.0, which
    changes no sum): ``(failed, dt_limit, moving, film, kinetic, count)``."""
    failed = False
    inv_lim = 0.0
    moving = 0.0
    film = 0.0
    kinetic = 0.0
    count = 0
    for c in range(n_cells):
        i = cells[c]
        failed = failed or cell_sums[i, S_FAIL] != 0.0
        inv_lim = max(inv_lim, cell_sums[i, S_INV])
        kinetic += cell_sums[i, S_KINETIC]
        moving += cell_sums[i, S_MOVING]
        film += cell_sums[i, S_FILM]
        count += int(cell_sums[i, S_COUNT])
    return failed, dt_from_inverse(inv_lim), moving, film, kinetic, count


#: Each compiled twice under its own name: on Numba's threads, and serial (``prange`` runs
#: as ``range`` without ``parallel``), which tests hold to step_faces on one thread
# (no reference counts: each inlined helper that takes an array counted it up and down in
# every cell's or face's iteration, half a stage's time: see kernels.step_faces)
step_cells_parallel = specialize(step_cells, "_parallel", parallel=True, nrt=False)
heun_cells_parallel = specialize(heun_cells, "_parallel", parallel=True, nrt=False)
step_cells_serial = specialize(step_cells, "_serial", nrt=False)
heun_cells_serial = specialize(heun_cells, "_serial", nrt=False)
