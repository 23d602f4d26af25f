"""Pointwise physics against hand-computed numbers (kinetic fluxes, projection, laws)."""

import math

import pytest

from avflow.numerics.cpu import project as _project
from avflow.numerics.kinetic import SQRT3, density_factor, half_fluxes, sound_speed
from avflow.numerics.rheology import h_stop, pouliquen_mu

G = 9.81


def fluxes(h, u, c=None):
    """half_fluxes with the temperature of a flat bed and its particle density."""
    c = sound_speed(h, G) if c is None else c
    return half_fluxes(h, u, c, c * density_factor(G))


@pytest.mark.parametrize("h,u", [(1.0, 0.0), (2.0, 1.5), (0.5, -2.0), (1.0, 10.0), (3.0, -9.0)])
def test_half_fluxes_sum_to_the_physical_flux(h, u):
    """F+ + F- = (h u, h u^2 + g h^2 / 2) for the rectangular density (eqs. 34, 38)."""
    fp_h, fp_q, fm_h, fm_q = fluxes(h, u)
    assert fp_h + fm_h == pytest.approx(h * u, rel=1e-13, abs=1e-13)
    assert fp_q + fm_q == pytest.approx(h * u * u + 0.5 * G * h * h, rel=1e-13)
    assert fp_h >= 0.0 and fm_h <= 0.0 and fp_q >= 0.0 and fm_q >= 0.0


def test_half_flux_matches_eq_54():
    """Subcritical outgoing mass flux, eq. 54: h u/2 + sqrt(3)/4 h c + h u^2 / (4 sqrt(3) c)."""
    h, u = 2.0, 0.7
    c = math.sqrt(G * h / 2)
    expected = 0.5 * h * u + SQRT3 / 4 * h * c + h * u * u / (4 * SQRT3 * c)
    assert fluxes(h, u, c)[0] == pytest.approx(expected, rel=1e-14)
    assert h / (2 * SQRT3 * c) == pytest.approx(c * density_factor(G), rel=1e-14)


def test_supercritical_flux_is_fully_upwind():
    h, u = 1.0, 20.0  # u > sqrt(3) c: every particle moves right
    fp_h, fp_q, fm_h, fm_q = fluxes(h, u)
    assert fm_h == 0.0 and fm_q == 0.0
    assert fp_h == pytest.approx(h * u, rel=1e-12)


def test_zero_temperature_is_the_dirac_flux():
    """c = 0: eqs. 53 and 55, particles move with the fluid velocity only."""
    assert half_fluxes(2.0, 3.0, 0.0, 0.0) == (6.0, 18.0, 0.0, 0.0)
    assert half_fluxes(2.0, -3.0, 0.0, 0.0) == (0.0, 0.0, -6.0, 18.0)
    assert half_fluxes(0.0, 3.0, 1.0, 1.0) == (0.0, 0.0, 0.0, 0.0)


def test_projection_eq_50_by_hand():
    qx, qy = 3.0, 4.0  # |q~| = 5
    assert _project(qx, qy, 1.0, 0.0, 2.0) == pytest.approx((1.8, 2.4))  # (5 - 2)/5
    assert _project(qx, qy, 2.5, 0.0, 2.0) == (0.0, 0.0)  # exactly at the threshold: stops
    assert _project(qx, qy, 10.0, 0.0, 1.0) == (0.0, 0.0)  # under it: stops, never reverses
    assert _project(qx, qy, 0.0, 1.0, 1.0) == pytest.approx((1.5, 2.0))  # drag: / (1 + 1)


def test_pouliquen_is_continuous_at_fr_beta_and_bounded():
    t1, t2, d, beta, h = math.tan(math.radians(13)), math.tan(math.radians(20)), 1.5, 0.136, 4.0
    u_beta = beta * math.sqrt(G * h)
    below = pouliquen_mu(h, u_beta * (1 - 1e-12), G, t1, t2, d, beta)
    above = pouliquen_mu(h, u_beta, G, t1, t2, d, beta)
    assert below == pytest.approx(above, rel=1e-10)
    assert below == pytest.approx(t1 + (t2 - t1) * math.exp(-h / d), rel=1e-14)  # mu_stop(h)
    for hh in (0.0, 1e-9, 0.1, 10.0, 1e4):
        for u in (0.0, 0.1, 10.0, 1e3):
            assert t1 <= pouliquen_mu(hh, u, G, t1, t2, d, beta) <= t2


def test_h_stop_inverts_the_static_branch():
    hs = h_stop(25.0, 20.7, 32.8, 0.98e-3)
    t1, t2 = math.tan(math.radians(20.7)), math.tan(math.radians(32.8))
    assert t1 + (t2 - t1) * math.exp(-hs / 0.98e-3) == pytest.approx(math.tan(math.radians(25)))
    assert h_stop(20.0, 20.7, 32.8, 1.0) == math.inf and h_stop(40.0, 20.7, 32.8, 1.0) == 0.0
