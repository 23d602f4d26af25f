"""Analytical solutions used for verification (seed section 4).

Dam break of a reservoir of thickness h0 at rest upslope of x0, on a plane of slope theta
with Coulomb friction delta < theta (Mangeney et al. 2000): in the frame that moves with the
uniform acceleration ``a = g (sin theta - cos theta tan delta)`` the flow is Ritter's
rarefaction with the bed-normal gravity ``g cos theta``. With ``c0 = sqrt(g cos theta h0)``
and ``xi = (x - x0 - a t^2 / 2) / t``:

- ``h = h0``, ``u = a t`` for ``xi <= -c0`` (the reservoir slides as a block);
- ``h = (2 c0 - xi)^2 / (9 g cos theta)``, ``u = 2 (c0 + xi) / 3 + a t`` for
  ``-c0 < xi < 2 c0``;
- ``h = 0`` beyond the front ``xi = 2 c0``.

theta = delta = 0 gives Ritter's solution. The domain must be long enough that the walls
are not reached (the seed's 0-2000 m with the dam at 1000 m is, up to t = 137 s and 35 s).

In 2D, the similarity solution of a cap on an inclined plane (:func:`similarity`, Hutter et
al. 1993): the analytic test of AvaFrame's ``ana1Tests``.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np


def dam_break(x, t, x0=1000.0, h0=1.0, theta_deg=0.0, delta_deg=0.0, g=9.81):
    """``(h, u)`` of the dam break at positions x (m, along the bed) and time t > 0 (s)."""
    x = np.asarray(x, dtype=float)
    th, de = math.radians(theta_deg), math.radians(delta_deg)
    gn = g * math.cos(th)
    accel = g * (math.sin(th) - math.cos(th) * math.tan(de))
    c0 = math.sqrt(gn * h0)
    xi = (x - x0 - 0.5 * accel * t * t) / t
    h = np.where(xi <= -c0, h0, np.where(xi >= 2 * c0, 0.0, (2 * c0 - xi) ** 2 / (9 * gn)))
    u = np.where(xi <= -c0, accel * t,
                 np.where(xi >= 2 * c0, 0.0, 2.0 * (c0 + xi) / 3.0 + accel * t))
    return h, u


def relative_error(h, h_exact, h0=1.0):
    """The seed's mean relative error of eq. 57, ``sum (h - h_a)^2 / sum h_a^2``.

    The sums run over the points where ``0 < h_a < h0`` (the rarefaction), as in the seed.
    """
    h, h_exact = np.asarray(h), np.asarray(h_exact)
    m = (h_exact > 0.0) & (h_exact < h0)
    return float(np.sum((h[m] - h_exact[m]) ** 2) / np.sum(h_exact[m] ** 2))


#: The parabolic cap of the similarity solution at time t (:func:`similarity`): its centre's
#: travel and speed along the slope, its semi-axes along and across the slope and their rates,
#: its thickness at the centre (m, m/s, s^-1 ... as named)
Cap = namedtuple("Cap", "travel speed a a_rate b b_rate h_centre")


def similarity(t, theta_deg=35.0, delta_deg=25.0, h0=4.0, a0=80.0, b0=80.0, g=9.81):
    """The similarity solution of a granular avalanche on an inclined plane (Hutter,
    Siegel, Savage and Nohguchi 1993, Acta Mechanica 100, 37-68): a cap released at rest
    as the elliptic paraboloid ``h = h0 (1 - xi^2 / a0^2 - eta^2 / b0^2)`` (xi along the
    slope, eta across it, both on the bed) stays one, ``h = H (1 - (xi - x_c)^2 / a^2 -
    eta^2 / b^2)`` with ``H = h0 a0 b0 / (a b)`` (its volume is kept), the velocity linear in
    space, ``u = x_c' + (xi - x_c) a' / a``, ``v = eta b' / b``. With isotropic hydrostatic
    pressure (earth-pressure coefficient 1, avflow's model) and Coulomb friction ``tan(delta)
    g cos(theta)``:

    - the centre slides at the constant acceleration ``g (sin theta - tan delta cos theta)``
      (the basal friction along the slope, u > 0 everywhere);
    - ``a'' = 2 g cos(theta) h0 a0 b0 / (a^2 b)`` (the pressure gradient along the slope);
    - ``b'' = 2 g cos(theta) h0 a0 b0 / (a b^2) - tan(delta) g cos(theta) b' / x_c'``: the
      pressure gradient across it, and the friction's lateral part linearised as ``tan(delta)
      g cos(theta) v / u_c`` (the paper's: the friction acts along the velocity, whose
      direction is taken at the centre's speed ``u_c``).

    The ODEs are integrated with scipy from a short early solution (Taylor's, past the
    ``1 / t`` of the lateral friction at the start). Returns :data:`Cap` at ``t`` (s, > 0).
    The solution needs u > 0 over the whole cap (checked: ``speed > a_rate``)."""
    from scipy.integrate import solve_ivp

    th, de = math.radians(theta_deg), math.radians(delta_deg)
    g_normal = g * math.cos(th)
    accel = g * math.sin(th) - math.tan(de) * g_normal
    if accel <= 0.0:
        raise ValueError("the cap does not slide: delta must be below the slope")
    c = math.tan(de) * g_normal
    volume = h0 * a0 * b0  # (times pi / 2)

    def rhs(s, y):
        a, da, b, db = y
        return [da, 2.0 * g_normal * volume / (a * a * b), db,
                2.0 * g_normal * volume / (a * b * b) - c * db / (accel * s)]

    t1 = min(1e-3, 0.5 * t)  # early solution: a'' and b'' constant (b' / u_c -> b'' / accel)
    a2 = 2.0 * g_normal * h0 / a0
    b2 = 2.0 * g_normal * h0 / b0 / (1.0 + c / accel)
    start = [a0 + 0.5 * a2 * t1**2, a2 * t1, b0 + 0.5 * b2 * t1**2, b2 * t1]
    sol = solve_ivp(rhs, (t1, t), start, method="DOP853", rtol=1e-11, atol=1e-11)
    a, da, b, db = sol.y[:, -1]
    cap = Cap(0.5 * accel * t * t, accel * t, a, da, b, db, volume / (a * b))
    if cap.speed <= cap.a_rate:
        raise ValueError("the cap's rear moves upslope at t: outside the solution's range")
    return cap


def similarity_thickness(cap, xi, eta):
    """The thickness (m) of :func:`similarity`'s cap at bed coordinates ``xi`` (along the
    slope, from the cap's start) and ``eta`` (across it)."""
    xi, eta = np.asarray(xi, dtype=float), np.asarray(eta, dtype=float)
    return cap.h_centre * np.clip(1.0 - ((xi - cap.travel) / cap.a) ** 2 - (eta / cap.b) ** 2,
                                  0.0, None)


def bed_coordinates(x, y, start, azimuth_deg, theta_deg):
    """Bed coordinates ``(xi, eta)`` (m) of map points ``(x, y)`` on a plane of slope
    ``theta_deg`` facing ``azimuth_deg`` (clockwise from north): ``xi`` along the slope from
    ``start`` (a map point), ``eta`` across it (horizontal, to the right looking downslope)."""
    az = math.radians(azimuth_deg)
    down_x, down_y = math.sin(az), math.cos(az)
    dx, dy = np.asarray(x, dtype=float) - start[0], np.asarray(y, dtype=float) - start[1]
    return ((dx * down_x + dy * down_y) / math.cos(math.radians(theta_deg)),
            -dx * down_y + dy * down_x)


def similarity_errors(cap, h, xi, eta, area, edge):
    """A thickness ``h`` (m, on cells of bed ``area`` m^2 at bed coordinates ``xi``, ``eta``)
    against :func:`similarity`'s ``cap``: the relative L2 of h (area-weighted), and with the
    footprint drawn at ``edge`` (m): the front (the farthest cell downslope against the exact
    contour there, m; negative: behind), the spread across the slope and the area, relative
    to the exact ellipse's. Returns a dict with ``l2``, ``front``, ``spread``, ``area``."""
    exact = similarity_thickness(cap, xi, eta)
    wet = h > edge
    inside = math.sqrt(1.0 - edge / cap.h_centre)  # the exact contour at edge
    return {"l2": math.sqrt(np.sum(area * (h - exact) ** 2) / np.sum(area * exact**2)),
            "front": float(xi[wet].max() - (cap.travel + cap.a * inside)),
            "spread": float((eta[wet].max() - eta[wet].min()) / (2.0 * cap.b * inside) - 1.0),
            "area": float(np.sum(area[wet]) / (math.pi * cap.a * cap.b * inside**2) - 1.0)}
