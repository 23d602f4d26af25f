"""Seed section 4: dam breaks against Ritter and Mangeney et al. (2000), eq. 57 error.

Bounds: the errors measured with this scheme (dh at dx = 2 m: 1.0e-4 to 1.3e-3) with a
margin of about 1.5; the seed reports dh falling by a factor of about 4 when dx falls
tenfold (first order), so the ratio must be at least 4.
"""

import numpy as np
import pytest

from avflow.numerics.analytic import dam_break, relative_error
from conftest import coulomb, slope_profile

CASES = [  # theta, delta, t, dh bound at dx = 20, dh bound at dx = 2
    (0.0, 0.0, 37.0, 7e-3, 8e-4),
    (0.0, 0.0, 137.0, 2e-3, 1.6e-4),
    (5.0, 0.0, 35.0, 2.2e-2, 2e-3),
    (5.0, 1.0, 35.0, 2.5e-2, 1.6e-3),
    (5.0, 4.0, 35.0, 4e-3, 5e-4),
]


def dam_break_error(theta, delta, t, dx):
    terrain = slope_profile(2000.0, dx, theta)
    solver = coulomb(terrain, delta)
    state = solver.new_state(np.where(terrain.x < 1000.0, 1.0, 0.0))
    v0 = solver.volume(state)
    assert solver.advance(state, t) == "running"
    h_exact, _ = dam_break(terrain.x, t, theta_deg=theta, delta_deg=delta)
    assert abs(solver.volume(state) - v0) <= 1e-13 * v0
    assert state.h.min() >= 0.0
    return relative_error(state.h, h_exact)


@pytest.mark.parametrize("theta,delta,t,bound20,bound2", CASES)
def test_dam_break_error_and_convergence(theta, delta, t, bound20, bound2):
    coarse = dam_break_error(theta, delta, t, 20.0)
    fine = dam_break_error(theta, delta, t, 2.0)
    assert coarse < bound20
    assert fine < bound2
    assert coarse / fine > 4.0

