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
"""

from __future__ import annotations

import math

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
