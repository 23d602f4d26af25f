"""The bed-curvature term of eqs. 61-62 in 1D and 2D: exact motion on a circular arc, and a
DEM extruded from the seed's exponential profile that lands where the profile does.

On a curved bed the material is pressed into the bed by the centripetal acceleration
``u.K.u`` on top of ``g cos(theta)``; Coulomb friction grows with it. The profile carries
``1/R = -d theta / ds`` exactly; a DEM carries the curvature tensor estimated from the
raster (:func:`avflow.terrain.bed.bed_hessian`).
"""

import math
from types import SimpleNamespace as NS

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from avflow.numerics import kernels as K
from avflow.numerics import stepping
from avflow.terrain.bed import bed_hessian, curvature_tensor, plane_basis, profile_terrain, \
    surface_terrain
from conftest import coulomb, walls

G = 9.81


# --- the tensor itself ------------------------------------------------------------------------


def test_tensor_of_a_paraboloid_matches_the_second_fundamental_form():
    """z = x^2 / (2 Rx) + y^2 / (2 Ry) at its vertex: K = diag(1/Rx, 1/Ry); on its flank the
    along-slope curvature of a cylinder z = x^2 / (2R) is b'' cos^3(theta) = 1/R_local."""
    x = np.arange(-200.0, 200.1, 5.0)
    y = np.arange(-100.0, 100.1, 5.0)
    xx, yy = np.meshgrid(x, y)
    z = xx**2 / (2 * 400.0) + yy**2 / (2 * 900.0)
    t = surface_terrain(z, x, y, walls())
    at = np.argmin(np.hypot(*t.cell_xy()))
    np.testing.assert_allclose(t.curvature[at], [1 / 400.0, 0.0, 1 / 900.0], atol=1e-9)
    # a cylinder: at x, the bed's radius of curvature is R (1 + b'^2)^(3/2)
    z = xx**2 / (2 * 400.0)
    t = surface_terrain(z, x, y, walls())
    cx, cy = t.cell_xy()
    inner = (np.abs(cx) < 150) & (np.abs(cy) < 50)
    slope = cx[inner] / 400.0
    expected = 1.0 / (400.0 * (1 + slope**2) ** 1.5)
    np.testing.assert_allclose(t.curvature[inner, 0], expected, rtol=1e-3)
    np.testing.assert_allclose(t.curvature[inner, 1:], 0.0, atol=1e-9)


def test_tensor_is_rotation_invariant():
    """u.K.u is a property of the bed, not of the grid: a bowl turned by 30 degrees gives
    the same K in the principal directions."""
    basis = plane_basis(0.0, 0.0)[None]
    a = math.radians(30.0)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    hess = rot @ np.diag([1 / 300.0, -1 / 700.0]) @ rot.T
    k = curvature_tensor(basis, np.ones(1), hess[0, 0], hess[0, 1], hess[1, 1])[0]
    tensor = np.array([[k[0], k[1]], [k[1], k[2]]])
    # horizontal bed: e1 = x, e2 = y, so K is the Hessian itself
    np.testing.assert_allclose(np.linalg.eigvalsh(tensor), [-1 / 700.0, 1 / 300.0], atol=1e-15)


def test_hessian_ignores_nodata():
    x = np.arange(0.0, 100.0, 5.0)
    xx, yy = np.meshgrid(x, x)
    z = 0.5 * xx
    z[8:12, 8:12] = np.nan
    for part in bed_hessian(z, 5.0, 5.0):
        assert np.all(np.isnan(part[8:12, 8:12]))
        np.testing.assert_allclose(part[np.isfinite(z)], 0.0, atol=1e-12)


# --- a mass on a circular arc -----------------------------------------------------------------

R, THETA0, DELTA = 500.0, 40.0, 15.0


def arc_block(length=1200.0, dx=2.0):
    """Circular arc theta = theta0 - s / R down to flat ground (a table slope)."""
    s_flat = R * math.radians(THETA0)
    slope = NS(kind="table", x=[0.0, s_flat], theta_deg=[THETA0, 0.0])
    return profile_terrain(NS(length=length, slope=slope, curvature=True), dx, walls())


def sliding_block(s0, curvature, t_end):
    """Point mass on the arc with Coulomb friction mu (g cos theta + v^2 / R)."""
    mu = math.tan(math.radians(DELTA))
    s_flat = R * math.radians(THETA0)

    def rhs(_, y):
        s, v = y
        theta = max(math.radians(THETA0) - s / R, 0.0)
        kappa = 1.0 / R if s < s_flat and curvature else 0.0
        return [v, G * math.sin(theta) - mu * (G * math.cos(theta) + kappa * v * v)]

    sol = solve_ivp(rhs, (0.0, t_end), [s0, 0.0], rtol=1e-10, atol=1e-10, dense_output=True)
    return sol.sol


@pytest.mark.parametrize("dx", [2.0])
def test_block_on_a_circular_arc_feels_v2_over_r(dx):
    """A 2 m x 30 m block slides down a concave arc (R = 500 m, 40 -> 0 degrees, Coulomb
    15 degrees). Its centre of mass follows the point-mass motion with the u^2/R friction
    within 0.6% of the distance travelled at 10, 15 and 20 s (measured: 0.41, 0.13, 0.16%;
    the block's spreading is the difference); without that term the point mass is 4.2% and
    5.4% ahead at 15 and 20 s, so the check tells them apart."""
    terrain = arc_block(dx=dx)
    solver = coulomb(terrain, DELTA, h_zero=1e-12)
    s = terrain.x
    s0 = 60.0
    h0 = np.where(np.abs(s - s0) <= 15.0, 2.0, 0.0)
    state = solver.new_state(h0)
    with_r = sliding_block(s0, True, 30.0)
    without = sliding_block(s0, False, 30.0)
    for t in (10.0, 15.0, 20.0):
        solver.advance(state, t)
        centre = np.sum(state.h * s) / np.sum(state.h)
        travel = with_r(t)[0] - s0
        assert abs(centre - with_r(t)[0]) < 0.006 * travel, (t, centre, with_r(t)[0])
    for t in (15.0, 20.0):
        assert without(t)[0] - with_r(t)[0] > 0.04 * (with_r(t)[0] - s0)


def test_same_arc_as_a_dem_matches_the_profile():
    """The arc extruded across y as a DEM (walls on the sides) gives the profile's motion:
    the tensor's K11 is the profile's 1/R."""
    fine = arc_block(dx=0.25)
    X = np.arange(0.0, 800.0, 2.0)
    z = np.interp(X, fine.x_horizontal, fine.bed_elevation)
    s_of_x = np.interp(X, fine.x_horizontal, fine.x)
    y = np.arange(0.0, 8.0, 2.0)
    dem = surface_terrain(np.tile(z, (y.size, 1)), X, y, walls())
    cx, _ = dem.cell_xy()
    s_cells = np.interp(cx, X, s_of_x)
    inner = (s_cells > 20.0) & (s_cells < R * math.radians(THETA0) - 20.0)
    np.testing.assert_allclose(dem.curvature[inner, 0], 1.0 / R, rtol=0.02)
    solver = coulomb(dem, DELTA, h_zero=1e-12)
    h0 = np.where(np.abs(s_cells - 60.0) <= 15.0, 2.0, 0.0)
    state = solver.new_state(h0)
    with_r = sliding_block(60.0, True, 30.0)
    for t in (10.0, 15.0):
        solver.advance(state, t)
        w = state.h * dem.mesh.cell_area
        centre = np.sum(w * s_cells) / np.sum(w)
        assert abs(centre - with_r(t)[0]) < 0.01 * (with_r(t)[0] - 60.0), (t, centre)


# --- the seed's section 6 on a DEM --------------------------------------------------------------


def section6_profile(dx, curvature=True):
    block = NS(length=5500.0, slope=NS(kind="exponential", theta0_deg=35.0, a=1750.0),
               curvature=curvature)
    return profile_terrain(block, dx, walls())


def parabola(s):
    return 201.6 / 400.0**2 * np.maximum(400.0**2 - (s - 500.0) ** 2, 0.0)


def stop_run(terrain, h0, x_cells, threshold):
    """Coulomb 15 degrees until the moving volume is below 1e-3 of the release."""
    solver = coulomb(terrain, 15.0, h_dry=1e-3 * h0.max(), h_zero=1e-12 * h0.max())
    state = solver.new_state(h0)
    v0 = solver.volume(state)
    status = solver.advance(state, 300.0, stop_volume=1e-3 * v0)
    assert status == "stopped"
    front = x_cells[state.h > threshold].max()
    return state.t, front, state.h.max()


@pytest.mark.slow
def test_section6_on_an_extruded_dem_lands_where_the_profile_does():
    """Seed section 6 (Coulomb 15 deg, 6.25 m) on a DEM extruded from the exponential
    profile: front within 60 m of the profile run with curvature (the curvature moves it by
    about 160 m), deposit maximum within 2 m, time to stop within 2 s."""
    profile = section6_profile(6.25)
    t_p, front_p, hmax_p = stop_run(profile, parabola(profile.x), profile.x_horizontal, 0.2016)
    fine = section6_profile(0.5)
    X = np.arange(0.0, fine.x_horizontal[-1], 6.25)
    z = np.interp(X, fine.x_horizontal, fine.bed_elevation)
    y = np.arange(0.0, 25.0, 6.25)
    dem = surface_terrain(np.tile(z, (y.size, 1)), X, y, walls())
    cx, _ = dem.cell_xy()
    h0 = parabola(np.interp(cx, fine.x_horizontal, fine.x))
    t_d, front_d, hmax_d = stop_run(dem, h0, cx, 0.2016)
    assert abs(front_d - front_p) < 60.0, (front_d, front_p)
    assert abs(hmax_d - hmax_p) < 2.0, (hmax_d, hmax_p)
    assert abs(t_d - t_p) < 2.0, (t_d, t_p)
    # and it is the curvature that brings it there: without it the DEM runs ~160 m further
    flat = surface_terrain(np.tile(z, (y.size, 1)), X, y, walls(), curvature=False)
    _, front_flat, _ = stop_run(flat, h0, cx, 0.2016)
    assert front_flat - front_d > 100.0


def test_flag_counts_clamped_cells_on_a_convex_crest():
    """A fast mass over a sharp convex crest would need a negative normal force: clamped at
    0 (the material flies over friction-free) and counted, on a DEM as on profiles."""
    x = np.arange(0.0, 600.0, 5.0)
    y = np.arange(0.0, 20.0, 5.0)
    z = np.where(x < 300.0, 200.0 - 0.2 * x, 140.0 - 0.7 * (x - 300.0))
    z = np.convolve(np.pad(z, 3, mode="edge"), np.ones(7) / 7, mode="valid")  # a rounded crest
    dem = surface_terrain(np.tile(z, (y.size, 1)), x, y, walls())
    solver = coulomb(dem, 5.0, h_zero=1e-12)
    cx, _ = dem.cell_xy()
    state = solver.new_state(np.where(np.abs(cx - 150.0) < 20.0, 2.0, 0.0))
    state.hu[:] = 40.0 * state.h  # launched downslope at 40 m/s
    solver.advance(state, 12.0)
    assert state.stats[stepping.ST_CLAMPED] > 0
