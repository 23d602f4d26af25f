"""A plain Numba 2D kinetic kernel: the yardstick of the square-grid kernel's speed.

Issue 11 put the square-grid kernel's target beside "a plain Numba 2D kinetic kernel with
a flat bed, no frames and no Dirac faces" (about 5e7 cell-updates/s on the machine it was
measured on, against a target of 4e7). Machines of this project's class differ by 2x and
more (AVX-512 or not, Zen 3 or Zen 4, a busy neighbour), so a rate alone says little; the
same two kernels timed in one run give a ratio that holds from one machine to the next.

This is that plain kernel, written as one would write it first: 2D arrays, one flux array
per face direction, the rectangular half-fluxes with their branches
(:func:`avflow.numerics.kinetic.half_fluxes`), the Coulomb projection of eq. 50 with its
threshold (eq. 49), walls on the four sides, the time step of eq. 41 from the last update.
The bed is a plane (constant gravity components, one tangent frame for every cell, so the
equations in the bed's frame need no face frames), with no Dirac faces, no curvature, no
observers, no active region: what the square-grid kernel does beyond it is the price of its
physics and of following the flow, which the ratio of the two shows.

    python workflows/plain_kernel.py          # both kernels on the benchmark's plane
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from avflow.numerics.cpu import SQRT3, half_fluxes


@njit(error_model="numpy", cache=True, inline="always")
def _inner_face(hi, qni, qti, hj, qnj, qtj, g_normal, kf):
    """``(mass, normal momentum, tangential momentum)`` fluxes per unit length through a face
    from cell i to cell j, from their thickness and discharge along the face's normal and
    tangent."""
    ui = qni / hi if hi > 0.0 else 0.0
    vi = qti / hi if hi > 0.0 else 0.0
    uj = qnj / hj if hj > 0.0 else 0.0
    vj = qtj / hj if hj > 0.0 else 0.0
    ci = math.sqrt(0.5 * g_normal * hi) if hi > 0.0 else 0.0
    cj = math.sqrt(0.5 * g_normal * hj) if hj > 0.0 else 0.0
    fp_h, fp_q, _, _ = half_fluxes(hi, ui, ci, ci * kf)
    _, _, fm_h, fm_q = half_fluxes(hj, uj, cj, cj * kf)
    return fp_h + fm_h, fp_q + fm_q, vi * fp_h + vj * fm_h


@njit(error_model="numpy", cache=True, inline="always")
def _wall_face(hm, qn, g_normal, kf):
    """The normal momentum flux through a wall (a mirror ghost: no mass, twice the pressure
    of what leaves the cell towards the wall; ``qn``: its discharge towards the wall), along
    the face's normal on the east and north sides, against it on the west and south."""
    cm = math.sqrt(0.5 * g_normal * hm) if hm > 0.0 else 0.0
    _, fp_q, _, _ = half_fluxes(hm, qn / hm if hm > 0.0 else 0.0, cm, cm * kf)
    return 2.0 * fp_q


@njit(error_model="numpy", cache=True)
def _faces(h, hu, hv, g_normal, kf, fx, fy):
    """Mass and momentum fluxes per unit length through every x face (``fx[:, r, k]``:
    between cells k - 1 and k of row r) and y face (``fy[:, r, c]``: between rows r - 1 and
    r), walls on the sides: ``[mass, momentum along the face's normal, along its tangent]``
    (x faces: x, y; y faces: y, x)."""
    ny, nx = h.shape
    for r in range(ny):
        for k in range(nx + 1):
            if 0 < k < nx:
                fx[0, r, k], fx[1, r, k], fx[2, r, k] = _inner_face(
                    h[r, k - 1], hu[r, k - 1], hv[r, k - 1], h[r, k], hu[r, k], hv[r, k],
                    g_normal, kf)
            else:  # the west (k = 0) or east side
                m = k - 1 if k == nx else k
                toward = hu[r, m] if k == nx else -hu[r, m]
                fx[0, r, k], fx[1, r, k], fx[2, r, k] = 0.0, _wall_face(h[r, m], toward,
                                                                         g_normal, kf), 0.0
    for r in range(ny + 1):
        for c in range(nx):
            if 0 < r < ny:
                fy[0, r, c], fy[1, r, c], fy[2, r, c] = _inner_face(
                    h[r - 1, c], hv[r - 1, c], hu[r - 1, c], h[r, c], hv[r, c], hu[r, c],
                    g_normal, kf)
            else:  # the south (r = 0) or north side
                m = r - 1 if r == ny else r
                toward = hv[m, c] if r == ny else -hv[m, c]
                fy[0, r, c], fy[1, r, c], fy[2, r, c] = 0.0, _wall_face(h[m, c], toward,
                                                                         g_normal, kf), 0.0


@njit(error_model="numpy", cache=True)
def _update(h, hu, hv, fx, fy, dt, dx, dy, gx, gy, g_normal, tan_delta):
    """The new state in place from the face fluxes: mass, the trial momentum with gravity
    (eq. 47), Coulomb's threshold and projection (eqs. 49-50). Returns the largest
    ``(|u| + sqrt(3) c) P / 2A`` of the new state (eq. 41's inverse limit on a rectangle)."""
    ny, nx = h.shape
    r_dx = dt / dx
    r_dy = dt / dy
    perimeter = (dx + dy) / (dx * dy)  # P / 2A
    inv = 0.0
    for r in range(ny):
        for c in range(nx):
            h_new = h[r, c] - (r_dx * (fx[0, r, c + 1] - fx[0, r, c])
                               + r_dy * (fy[0, r + 1, c] - fy[0, r, c]))
            qx = hu[r, c] - (r_dx * (fx[1, r, c + 1] - fx[1, r, c])
                             + r_dy * (fy[2, r + 1, c] - fy[2, r, c])) + dt * gx * h_new
            qy = hv[r, c] - (r_dx * (fx[2, r, c + 1] - fx[2, r, c])
                             + r_dy * (fy[1, r + 1, c] - fy[1, r, c])) + dt * gy * h_new
            tau = dt * tan_delta * g_normal * h_new
            q = math.sqrt(qx * qx + qy * qy)
            if q <= tau or h_new <= 0.0:
                qx = 0.0
                qy = 0.0
            else:
                qx *= 1.0 - tau / q
                qy *= 1.0 - tau / q
            h[r, c] = h_new
            hu[r, c] = qx
            hv[r, c] = qy
            if h_new > 0.0:
                speed = math.sqrt(qx * qx + qy * qy) / h_new
                inv = max(inv, (speed + SQRT3 * math.sqrt(0.5 * g_normal * h_new)) * perimeter)
    return inv


@njit(error_model="numpy", cache=True)
def advance(h, hu, hv, dx, slope_deg, tan_delta, g, cfl, t_end):
    """Run the state ``(h, hu, hv)`` (``(ny, nx)`` arrays, in place) on a plane falling along
    +x from t = 0 to ``t_end``, on cells of ``dx`` by ``dx`` seen from above (so ``dx /
    cos(theta)`` along the bed, as avflow's grids on a plane); returns the steps taken."""
    theta = math.radians(slope_deg)
    dy = dx
    dx = dx / math.cos(theta)
    perimeter = (dx + dy) / (dx * dy)
    g_normal = g * math.cos(theta)
    gx = g * math.sin(theta)
    kf = 1.0 / (SQRT3 * g_normal)
    ny, nx = h.shape
    fx = np.zeros((3, ny, nx + 1))
    fy = np.zeros((3, ny + 1, nx))
    inv = 0.0
    for r in range(ny):
        for c in range(nx):
            if h[r, c] > 0.0:
                speed = math.sqrt(hu[r, c] ** 2 + hv[r, c] ** 2) / h[r, c]
                inv = max(inv, (speed + SQRT3 * math.sqrt(0.5 * g_normal * h[r, c])) * perimeter)
    t = 0.0
    steps = 0
    while t < t_end:
        dt = min(cfl / inv, t_end - t)
        _faces(h, hu, hv, g_normal, kf, fx, fy)
        inv = _update(h, hu, hv, fx, fy, dt, dx, dy, gx, 0.0, g_normal, tan_delta)
        t += dt
        steps += 1
    return steps


def cylinder_on_layer(n, dx=10.0):
    """The benchmark's all-wet case on an ``n x n`` plane: a cylinder of 20 m (radius
    300 m, a quarter of the way down) on a 1 m layer, at rest (row-major, y then x)."""
    x = (np.arange(n) + 0.5) * dx
    xx, yy = np.meshgrid(x, x)
    centre = (0.25 * dx * n, 0.5 * dx * n)
    return np.where((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 < 300.0**2, 20.0, 0.0) + 1.0


def rate(n=400, t_warm=0.5, t_end=3.0, min_wall=0.5, windows=3, slope_deg=30.0,
         delta_deg=20.0, g=9.81, cfl=0.5):
    """Cell-updates per second of the plain kernel on the benchmark's all-wet plane: the
    fastest of ``windows`` windows, each from the state at ``t_warm`` (compiled, under way)
    on to ``t_end`` and by as much again until it lasted ``min_wall`` (as the benchmark's
    ``_rate``). Returns ``(rate, wall, steps, h)`` with h the state at the end of the last
    window."""
    import time

    best = None
    tan_delta = math.tan(math.radians(delta_deg))
    for _ in range(windows):
        h = cylinder_on_layer(n)
        hu = np.zeros_like(h)
        hv = np.zeros_like(h)
        advance(h, hu, hv, 10.0, slope_deg, tan_delta, g, cfl, t_warm)
        t0 = time.perf_counter()
        steps = 0
        span = t_end - t_warm
        while True:
            steps += advance(h, hu, hv, 10.0, slope_deg, tan_delta, g, cfl, span)
            wall = time.perf_counter() - t0
            if wall >= min_wall:
                break
        r = (steps * h.size / wall, wall, steps, h)
        if best is None or r[0] > best[0]:
            best = r
    return best


if __name__ == "__main__":
    r = rate()
    print(f"plain kernel, 400 x 400, all wet, one core: {r[0]:.3g} cell-updates/s "
          f"({r[2]} steps in {r[1]:.2f} s); mass {r[3].sum() * 100.0:.6e} m^3")
