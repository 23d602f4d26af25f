"""The similarity solution of an avalanche on an inclined plane (Hutter et al. 1993, the
analytic test of AvaFrame's ana1Tests): a parabolic cap, 80 m in radius and 4 m thick,
released on a 35 degree plane with Coulomb friction 25 degrees, compared at t = 20 s (the
cap has slid 376 m, its semi-axes are 187 and 111 m) on the square grid at both orders,
with the slope turned by 0, 22.5 and 45 degrees on the grid.

Measures, on the bed: the relative L2 error of the thickness over the map; the front (the
farthest point downslope with h > 1% of the release thickness) against the analytic cap's
contour at that thickness; the lateral spread (across the slope at the same threshold) and
the area above it, both against the analytic ellipse's. The reference's lateral friction is
linearised at the centre's speed (``v / u_c`` for ``v / |u|``): avflow's acts along the
velocity itself, which is faster than u_c at the front and slower at the rear by up to
21% at 20 s. That model difference, not the grid, bounds how close order 2 comes (0.033 at
2.5 m against 0.042 at 5 m).
"""

import math
from types import SimpleNamespace as NS

import numpy as np
import pytest

from avflow.numerics.analytic import bed_coordinates, similarity, similarity_errors
from avflow.terrain.bed import plane_terrain
from conftest import coulomb, walls

THETA, DELTA, H0, RADIUS, T = 35.0, 25.0, 4.0, 80.0, 20.0
SIDE = 800.0  # m, the map (horizontal): the cap ends 611 m down the slope from its start
EDGE = 0.01 * H0  # thickness that draws the footprint


def run(dx, order, turn_deg, time_scheme="auto", t=T):
    """avflow on the plane facing ``90 + turn_deg`` degrees (east, turned clockwise), to
    ``t`` (s):
    ``(relative L2, front error (m), spread error, area error, the run's state, terrain,
    (xi, eta))``."""
    azimuth = 90.0 + turn_deg
    plane = NS(slope_deg=THETA, azimuth_deg=azimuth, extent=NS(x=[0.0, SIDE], y=[0.0, SIDE]),
               elevation_at_center=1000.0)
    terrain = plane_terrain(plane, dx, None, walls())
    solver = coulomb(terrain, DELTA, order=order, threads=1, h_zero=1e-9,
                     time_scheme=time_scheme)
    assert solver.kernel_used == "grid"
    az = math.radians(azimuth)
    start = (SIDE / 2 - 250.0 * math.sin(az), SIDE / 2 - 250.0 * math.cos(az))  # t = 0
    xi, eta = bed_coordinates(*terrain.cell_xy(), start, azimuth, THETA)
    state = solver.new_state(H0 * np.clip(1.0 - (xi / RADIUS) ** 2 - (eta / RADIUS) ** 2,
                                          0.0, None))
    solver.advance(state, t)
    e = similarity_errors(similarity(t, THETA, DELTA, H0, RADIUS, RADIUS), state.h, xi, eta,
                          terrain.mesh.cell_area, EDGE)
    return e["l2"], e["front"], e["spread"], e["area"], state, terrain, (xi, eta)


@pytest.fixture(scope="module")
def turned():
    """Both orders at 5 m, the slope turned by 0, 22.5 and 45 degrees on the grid."""
    return {(order, turn): run(5.0, order, turn)[:4] for order in (1, 2)
            for turn in (0.0, 22.5, 45.0)}


def test_order_2_is_close_to_the_similarity_solution_at_any_rotation(turned):
    """Measured 2026-12-05 at 5 m, t = 20 s (turn 0 / 22.5 / 45): L2 0.042 / 0.033 / 0.029,
    front -7.3 / -3.5 / -4.1 m, spread -1.2 / +1.1 / +0.7%, area -1.2 / +0.2 / +1.0%.
    Asserted: L2 under 0.05, the front within two cells, spread and area within 3%."""
    for turn in (0.0, 22.5, 45.0):
        l2, front, spread, area = turned[2, turn]
        assert l2 < 0.05 and abs(front) < 10.0, (turn, l2, front)
        assert abs(spread) < 0.03 and abs(area) < 0.03, (turn, spread, area)


def test_order_1_is_too_wide_and_depends_on_the_grid(turned):
    """Order 1 at 5 m (turn 0 / 22.5 / 45): L2 0.10 / 0.15 / 0.18, area +25 / +38 / +44%,
    spread +3 / +23 / +30%: its footprint is too large, the more so off the grid's axes
    (asserted: area at least +15% at every turn, the spread at 45 degrees at least 15
    points above that at 0), where order 2's moves by 2 points."""
    for turn in (0.0, 22.5, 45.0):
        l2, _, _, area = turned[1, turn]
        assert l2 > 2.0 * turned[2, turn][0] and area > 0.15, (turn, l2, area)
    assert turned[1, 45.0][2] - turned[1, 0.0][2] > 0.15
    assert abs(turned[2, 45.0][2] - turned[2, 0.0][2]) < 0.03


def test_order_2_converges_while_the_reference_holds():
    """Early (t = 5 s, the lateral speeds still small beside u_c) order 2 converges:
    measured L2 0.0257 / 0.0123 / 0.0073 at 10 / 5 / 2.5 m (0.0062 at 1.25 m: the
    reference's linearised lateral friction sets a floor that grows with time, 0.017 at
    10 s and 0.033 at 20 s). Asserted: each halving of the cells at least a third off."""
    errors = [run(dx, 2, 0.0, t=5.0)[0] for dx in (10.0, 5.0, 2.5)]
    assert errors[1] < 0.67 * errors[0] and errors[2] < 0.67 * errors[1], errors
    assert errors[1] < 0.015, errors


def test_the_front_converges_at_first_order():
    """Order 2's front trails the analytic contour by about a cell at 10 s (measured -6.1,
    -3.0, -1.5, -0.7 m at 10, 5, 2.5, 1.25 m): first order, as at every wet/dry front of a
    limited scheme (no slope towards a dry cell), not a lag that stays. Asserted: halved,
    within 35%, with each halving of the cells."""
    fronts = [run(dx, 2, 0.0, t=10.0)[1] for dx in (10.0, 5.0, 2.5)]
    assert all(f < 0.0 for f in fronts), fronts
    assert 0.35 < fronts[1] / fronts[0] < 0.65 and 0.35 < fronts[2] / fronts[1] < 0.65, fronts


def test_muscl_hancock_matches_heun_at_half_the_sweeps():
    """The two time schemes of order 2 at 5 m, t = 20 s: L2 0.0421 and 0.0418, the same
    front, spread and area to 0.2% (MUSCL-Hancock one flux sweep a step, Heun two)."""
    hancock, heun = run(5.0, 2, 22.5)[:4], run(5.0, 2, 22.5, "heun")[:4]
    assert hancock[0] == pytest.approx(heun[0], rel=0.1)
    assert abs(hancock[2] - heun[2]) < 0.005 and abs(hancock[3] - heun[3]) < 0.005
