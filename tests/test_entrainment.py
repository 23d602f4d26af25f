"""Entrainment, friction maps and forest in the numerics (issue 30), on the source seam of
issue 27 and the law's parameters per cell.

- the exponential law grows a sliding block as Hungr and McDougall's ``V = V0 exp(E_s s)``
  (s the distance its mass travelled), at both orders;
- released + entrained = on the map + outflow to round-off on random scenes, the layer and
  h never below 0;
- a pile under its friction threshold on an erodible bed stays at rest, bit for bit;
- each law's rate against its formula written out by hand;
- a friction map equal to the scalar gives the scalar's bits on every kernel, and forest
  drag gives the terminal speed of uniform flow that the force balance says.
"""

import math

import numpy as np
import pytest
from conftest import assert_same_runs, coulomb, slope_profile, walls
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from avflow.numerics.physics import (SOURCE_EROSION_ENERGY, SOURCE_EXPONENTIAL,
                                     SOURCE_SHEAR_THRESHOLD, basal_shear, source_rate)
from avflow.numerics.rheology import COULOMB, PER_CELL, VOELLMY, Law
from avflow.numerics.solver import Solver
from avflow.numerics.sources import MassSource

G = 9.81
LAWS = {"exponential": (SOURCE_EXPONENTIAL, (0.01,)),
        "erosion_energy": (SOURCE_EROSION_ENERGY, (5000.0,)),
        "shear_threshold": (SOURCE_SHEAR_THRESHOLD, (2e-5, 1000.0, 2000.0))}


# ------------------------------------------------------------------ the laws, pointwise
def test_each_law_is_its_formula():
    h, u, shear, ratio = 2.0, 8.0, 15.0, 0.5
    # Hungr and McDougall: dh/dt = E_s h |u| of flow, so the layer gives that over ratio
    assert source_rate(SOURCE_EXPONENTIAL, 0.01, 0, 0, 0, ratio, 0.0, h, u, shear) == \
        pytest.approx(0.01 * h * u / ratio, rel=1e-15)
    # AvaFrame: dm = A tau_b |u| dt / e_b, tau_b = rho_f shear; depth = dm / (A rho_e)
    rho_f = 1000.0
    dm_per_area = rho_f * shear * u / 5000.0
    assert source_rate(SOURCE_EROSION_ENERGY, 5000.0, 0, 0, 0, ratio, 0.0, h, u, shear) == \
        pytest.approx(dm_per_area / (ratio * rho_f), rel=1e-15)
    # shear threshold: k (rho_f shear - tau_c) above tau_c, nothing below
    assert source_rate(SOURCE_SHEAR_THRESHOLD, 2e-5, 1000.0, rho_f, 0, ratio, 0.0, h, u,
                       shear) == pytest.approx(2e-5 * (rho_f * shear - 1000.0), rel=1e-15)
    assert source_rate(SOURCE_SHEAR_THRESHOLD, 2e-5, 1000.0, rho_f, 0, ratio, 0.0, h, u,
                       0.5) == 0.0
    # nothing at or below u_min, for every entrainment law
    for kind, params in LAWS.values():
        assert source_rate(kind, *params, *(0,) * (4 - len(params)), ratio, u, h, u,
                           shear) == 0.0
        assert source_rate(kind, *params, *(0,) * (4 - len(params)), ratio, 0.0, h, 0.0,
                           shear) == 0.0


def test_basal_shear_is_the_law_stress():
    mu, xi, h, u, n = 0.2, 1500.0, 1.5, 12.0, G * math.cos(math.radians(30.0))
    p = (mu, xi, 0, 0, 0, 0, 0, 0)
    assert basal_shear(VOELLMY, *p, h, u, n, G) == pytest.approx(mu * h * n + G * u * u / xi,
                                                                  rel=1e-14)
    assert basal_shear(COULOMB, 0.4, *(0,) * 7, h, u, n, G) == 0.4 * h * n
    # forest's c_f |u|^2 adds to it where the parameters are per cell
    p_forest = (mu, xi, 0, 0, 0, 0, 0, 0.01)
    assert basal_shear(VOELLMY + PER_CELL, *p_forest, h, u, n, G) == pytest.approx(
        mu * h * n + G * u * u / xi + 0.01 * u * u, rel=1e-14)


# ---------------------------------------------------- exponential growth, analytically
@pytest.mark.parametrize("order", [1, 2])
def test_a_sliding_block_grows_as_exp_of_its_travel(order):
    """Coulomb friction equal to the slope: the block slides with no net force, so its
    momentum stays (nearly: its ends spread) and the entrained mass, with no momentum,
    slows it. ``dV/dt = E_s sum(h |u| A)`` makes ``V = V0 exp(E_s s)`` with
    ``s = int Q/V dt`` the distance its centre of mass travels, whatever the speed does:
    checked to 1e-3 at a growth factor of 3 (the trapezoid rule on s over 0.5 s outputs
    is good to 1e-4 here). With Q constant V also grows linearly, ``V0 + E_s Q0 t``: to 1%
    (Q drifts by 1.4-1.6% by the end as the ends thin)."""
    theta, e_s, u0 = 30.0, 0.01, 10.0
    ter = slope_profile(600.0, 2.0, theta, x_max="outflow")
    h0 = np.where((ter.x > 20.0) & (ter.x < 60.0), 2.0, 0.0)
    solver = coulomb(ter, theta, order=order, h_zero=1e-9, h_dry=1e-3,
                     source=MassSource(SOURCE_EXPONENTIAL, np.full(ter.n_cells, 50.0),
                                       (e_s,)))
    state = solver.new_state(h0)
    state.hu[:] = h0 * u0
    area = ter.mesh.cell_area
    v0, q0 = solver.volume(state), float(np.sum(state.hu * area))
    t_prev, mean_prev, s = 0.0, q0 / v0, 0.0
    for t in np.arange(0.5, 20.01, 0.5):
        assert solver.advance(state, t) == "running"
        v = solver.volume(state)
        mean = float(np.sum(np.abs(state.hu) * area)) / v
        s += 0.5 * (mean_prev + mean) * (t - t_prev)
        t_prev, mean_prev = t, mean
    assert state.statistics.outflow_volume == 0.0
    assert v / v0 > 2.95  # a growth factor of 3
    assert v / v0 == pytest.approx(math.exp(e_s * s), rel=1e-3)
    assert v / v0 == pytest.approx(1.0 + e_s * q0 * 20.0 / v0, rel=1e-2)
    assert v == pytest.approx(v0 + solver.entrained_volume(state), rel=1e-13)


# ----------------------------------------------------------------- rest stays rest
def _plane_grid(theta=20.0, n=30, dx=10.0):
    from types import SimpleNamespace as NS

    from avflow.terrain.bed import plane_terrain

    plane = NS(slope_deg=theta, azimuth_deg=90.0, extent=NS(x=[0.0, n * dx], y=[0.0, n * dx]),
               elevation_at_center=0.0)
    return plane_terrain(plane, dx, None, walls())


@pytest.mark.parametrize("law", sorted(LAWS))
@pytest.mark.parametrize("mesh", ["profile", "grid"])
def test_a_pile_at_rest_on_an_erodible_bed_stays_at_rest_bit_for_bit(law, mesh):
    """The piles of the invariant tests (a parabola on 20 degrees, a cylinder on 10, under
    Coulomb 30 and 20 degrees) never move: no law takes anything at u = 0 (the shear
    threshold's tau_b there would be the static threshold, far above tau_c), so the run is
    the run without a layer, bit for bit, and the layer is untouched."""
    if mesh == "profile":
        ter = slope_profile(1000.0, 5.0, 20.0)
        h0 = np.maximum(0.0, 10.0 * (1.0 - ((ter.x - 500.0) / 100.0) ** 2))
        delta = 30.0
    else:
        ter = _plane_grid(theta=10.0, n=30, dx=20.0)
        xx, yy = ter.cell_xy()
        h0 = np.where((xx - 300.0) ** 2 + (yy - 300.0) ** 2 <= 100.0**2, 10.0, 0.0)
        delta = 20.0
    kind, params = LAWS[law]
    runs = []
    for source in (None, MassSource(kind, np.full(ter.n_cells, 2.0), params)):
        solver = coulomb(ter, delta, source=source, h_zero=1e-9)
        state = solver.new_state(h0)
        snaps = []
        for t in (1.0, 2.0, 5.0):
            solver.advance(state, t)
            snaps.append(state.h.copy())
        runs.append((state, snaps))
    assert_same_runs(runs)
    assert not np.any(runs[0][0].hu)
    np.testing.assert_array_equal(runs[1][0].erodible, 2.0)


# -------------------------------------------------------- exact budget, random scenes
@settings(max_examples=12, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(law=st.sampled_from(sorted(LAWS)), order=st.sampled_from([1, 2]),
       mesh=st.sampled_from(["profile", "grid"]), theta=st.floats(25.0, 40.0),
       ratio=st.floats(0.3, 2.0), scale=st.floats(0.2, 5.0), u_min=st.floats(0.0, 2.0),
       seed=st.integers(0, 2**31 - 1))
def test_released_plus_entrained_is_on_the_map_plus_outflow(law, order, mesh, theta, ratio,
                                                             scale, u_min, seed):
    """Voellmy flows over a patchy layer (random depths, a third of the cells bare) with an
    open lower side: the balance from the state (the layer's books, the outflow count) holds
    to 1e-12, the layer never goes below 0 nor above its start, h never below 0."""
    rng = np.random.default_rng(seed)
    if mesh == "profile":
        ter = slope_profile(300.0, 2.0, theta, x_max="outflow")
        h0 = np.where((ter.x > 20.0) & (ter.x < 60.0), 4.0, 0.0)
    else:
        from types import SimpleNamespace as NS

        from avflow.terrain.bed import plane_terrain

        plane = NS(slope_deg=theta, azimuth_deg=90.0, extent=NS(x=[0.0, 300.0],
                                                                 y=[0.0, 150.0]),
                   elevation_at_center=0.0)
        ter = plane_terrain(plane, 10.0, None, walls(x_max="outflow"))
        xx, yy = ter.cell_xy()
        h0 = np.where((xx - 60.0) ** 2 + (yy - 75.0) ** 2 <= 40.0**2, 4.0, 0.0)
    layer = rng.uniform(0.0, 1.5, ter.n_cells) * (rng.uniform(size=ter.n_cells) > 0.33)
    kind, params = LAWS[law]
    params = (params[0] * scale,) + params[1:]
    solver = Solver(ter, Law.VOELLMY, np.array([0.25, 1000.0]), order=order, h_zero=1e-9,
                    h_dry=1e-3, source=MassSource(kind, layer, params, density_ratio=ratio,
                                                  u_min=u_min))
    state = solver.new_state(h0)
    v0 = solver.volume(state)
    for t in (2.0, 5.0, 9.0):
        solver.advance(state, t)
        assert state.h.min() >= 0.0
        assert state.erodible.min() >= 0.0 and np.all(state.erodible <= layer)
        gained = solver.entrained_volume(state)
        out = state.statistics.outflow_volume
        assert abs(solver.volume(state) + out - v0 - gained) <= 1e-12 * (v0 + gained)
    assert state.statistics.source_volume == pytest.approx(gained, rel=1e-9, abs=1e-12 * v0)


def test_the_erosion_energy_law_entrains_what_avaframe_would_in_one_step():
    """One step of a uniform Voellmy flow on a profile over a uniform layer: each cell's
    eroded depth is AvaFrame's ``dm = A tau_b |u| dt / e_b`` over ``A rho_e``, with tau_b
    at the state after the seed's step."""
    theta, h, u, ratio = 30.0, 1.0, 10.0, 0.4
    ter = slope_profile(400.0, 4.0, theta, x_min="outflow", x_max="outflow")
    solver = Solver(ter, Law.VOELLMY, np.array([0.2, 1500.0]), h_zero=1e-9,
                    source=MassSource(SOURCE_EROSION_ENERGY, np.full(ter.n_cells, 3.0),
                                      (5000.0,), density_ratio=ratio))
    state = solver.new_state(np.full(ter.n_cells, h))
    state.hu[:] = h * u
    solver.advance(state, 10.0, max_steps=1)
    mid = ter.n_cells // 2
    dt = state.t
    taken = 3.0 - state.erodible[mid]
    h_before = state.h[mid] - ratio * taken  # the seed's step left it there
    speed = abs(state.hu[mid]) / h_before
    n = G * math.cos(math.radians(theta))
    shear = 0.2 * h_before * n + G * speed * speed / 1500.0
    assert taken == pytest.approx(shear * speed * dt / (ratio * 5000.0), rel=1e-12)


# ------------------------------------------------------------- friction maps, forest
def _grid_run(law, params, order=1, kernel="auto", forest=None, t_end=6.0):
    from avflow.terrain.bed import plane_terrain
    from types import SimpleNamespace as NS

    plane = NS(slope_deg=30.0, azimuth_deg=90.0, extent=NS(x=[0.0, 400.0], y=[0.0, 200.0]),
               elevation_at_center=0.0)
    ter = plane_terrain(plane, 10.0, None, walls(x_max="outflow"))
    xx, yy = ter.cell_xy()
    h0 = np.where((xx - 80.0) ** 2 + (yy - 100.0) ** 2 <= 50.0**2, 5.0, 0.0)
    solver = Solver(ter, law, params, order=order, kernel=kernel, forest=forest,
                    h_zero=1e-9, h_dry=1e-3)
    state = solver.new_state(h0)
    snaps = []
    for t in np.linspace(t_end / 3, t_end, 3):
        solver.advance(state, t)
        snaps.append(state.h.copy())
    return ter, solver, state, snaps


@pytest.mark.parametrize("law,vector", [(Law.COULOMB, [math.tan(math.radians(22.0))]),
                                        (Law.VOELLMY, [0.2, 1200.0]),
                                        (Law.SAMOSAT, None)])
@pytest.mark.parametrize("order,kernel", [(1, "auto"), (2, "auto"), (1, "faces")])
def test_a_map_equal_to_the_scalar_gives_the_scalar_bits(law, vector, order, kernel):
    """A map whose rows are all the scalar's runs on the copy that reads the law (scalar
    loops), the scalar on its law's own copy (vector loops for Coulomb and Voellmy): the
    same operations on every value, so the same bits; a forest of c_f = 0 too."""
    if vector is None:
        from types import SimpleNamespace as NS

        from avflow.numerics.rheology import friction_parameters

        rh = NS(law="samosat", mu=0.155, tau0=0.0, Rs0=0.222, kappa=0.43, R=0.05, B=4.13)
        vector = friction_parameters(rh, 200.0)[1][:7]
    vector = np.asarray(vector, dtype=float)
    ter, solver, state, snaps = _grid_run(law, vector, order, kernel)
    n = ter.n_cells
    for params, forest in ((np.tile(vector, (n, 1)), None), (vector, np.zeros(n))):
        _, mapped, s2, snaps2 = _grid_run(law, params, order, kernel, forest)
        assert mapped._law_code == int(law) + PER_CELL
        assert_same_runs([(state, snaps), (s2, snaps2)])


def test_a_map_on_a_profile_gives_the_scalar_bits():
    ter = slope_profile(400.0, 2.0, 32.0, x_max="outflow")
    h0 = np.where((ter.x > 40.0) & (ter.x < 80.0), 6.0, 0.0)
    runs = []
    for params, order in ((np.array([0.2, 1200.0]), 1), (np.tile([0.2, 1200.0], (ter.n_cells, 1)), 1)):
        solver = Solver(ter, Law.VOELLMY, params, order=order, h_zero=1e-9)
        state = solver.new_state(h0)
        snaps = []
        for t in (3.0, 6.0):
            solver.advance(state, t)
            snaps.append(state.h.copy())
        runs.append((state, snaps))
    assert_same_runs(runs)


def test_a_two_zone_map_stops_the_flow_where_friction_rises():
    """Voellmy on a 30 degree profile: mu = 0.2 above x = 200 m, mu = 0.9 (above tan 30)
    below. The front stops in the rough zone where a point mass entering it at the speed
    the flow had at the boundary stops, ``u^2 / (2 g cos(theta) (mu - tan(theta)))``: to
    3 cells beyond (the front's smearing, and the pressure of the mass behind it pushes
    it on) and 20% short of it (the turbulent drag brakes it too). The thin tail left on
    the smooth part (mu < tan 30) keeps draining into the rough zone."""
    theta = 30.0
    ter = slope_profile(600.0, 2.0, theta)
    mu = np.where(ter.x < 200.0, 0.2, 0.9)
    params = np.stack([mu, np.full(ter.n_cells, 2000.0)], axis=1)
    solver = Solver(ter, Law.VOELLMY, params, h_zero=1e-9, h_dry=1e-3)
    state = solver.new_state(np.where((ter.x > 20.0) & (ter.x < 60.0), 3.0, 0.0))
    solver.advance(state, 200.0)
    edge = int(np.searchsorted(ter.x, 200.0))
    u_in = float(state.peak_speed[edge - 1])  # the last smooth cell's largest speed
    reach = u_in**2 / (2 * G * math.cos(math.radians(theta))
                       * (0.9 - math.tan(math.radians(theta))))
    front = int(np.flatnonzero(state.h > 1e-3).max())
    assert 200.0 + 0.8 * reach < ter.x[front] <= 200.0 + reach + 6.0
    assert not np.any(state.hu[ter.x > 200.0 + 0.8 * reach])  # the front is at rest
    assert not np.any(state.h[ter.x > 200.0 + reach + 6.0])
    volume = state.h * ter.mesh.cell_area
    assert volume[ter.x > 200.0].sum() > 0.98 * volume.sum()


@pytest.mark.parametrize("c_f", [0.0, 0.01])
def test_forest_drag_gives_the_terminal_speed_of_uniform_flow(c_f):
    """A uniform Voellmy layer 1 m thick on a 30 degree slope, forest everywhere: the force
    balance ``g sin = mu g cos + g u^2 / (xi h) + c_f u^2 / h`` gives the terminal speed.
    Read mid-slope after 40 s (the rarefaction from the top has not come so far), to 0.5%."""
    theta, mu, xi, h = 30.0, 0.2, 1000.0, 1.0
    ter = slope_profile(3000.0, 5.0, theta, x_max="outflow")
    n = ter.n_cells
    solver = Solver(ter, Law.VOELLMY, np.array([mu, xi]), forest=np.full(n, c_f),
                    h_zero=1e-9)
    state = solver.new_state(np.full(n, h))
    solver.advance(state, 40.0)
    s, c = math.sin(math.radians(theta)), math.cos(math.radians(theta))
    u_t = math.sqrt(G * h * (s - mu * c) / (G / xi + c_f))
    mid = int(np.searchsorted(ter.x, 2000.0))
    assert state.h[mid] == pytest.approx(h, rel=1e-9)
    assert state.hu[mid] / state.h[mid] == pytest.approx(u_t, rel=5e-3)
