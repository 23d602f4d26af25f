"""Velocity-weakening friction of Lucas, Mangeney and Ampuero (2014) (issue 34).

``mu(|u|) = mu_w + (mu_s - mu_w) / (1 + |u| / U_w)``: the law against its formula, a pile at
rest under atan(mu_s) on every kernel at both orders, the block on a plane between atan(mu_w)
and atan(mu_s) (at rest it stays, above the analytic speed threshold it accelerates, below
it stops), its parameter checks, and an ensemble mixing it with the other laws.
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

from avflow.errors import ScenarioError
from avflow.numerics.rheology import (Law, friction, friction_parameters, law_reference,
                                      velocity_weakening_mu, velocity_weakening_threshold)
from avflow.numerics.solver import Solver
from avflow.scenario.schema import load_scenario, parse_scenario
from conftest import slope_profile

G = 9.81
MU_S, MU_W, U_W = 0.7, 0.1, 4.0  # test values (atan: 35.0 and 5.7 degrees)
PARAMS = np.array([MU_S, MU_W, U_W, 0.0, 0.0, 0.0, 0.0, 0.0])


def _scenario(rheology, theta=20.0):
    return f"""
name: velocity-weakening
terrain: {{kind: profile, length: 1000.0, slope: {{kind: constant, theta_deg: {theta}}},
          curvature: false}}
grid: {{dx: 10.0}}
release: {{kind: box, x: [0.0, 1000.0], thickness: 1.0}}
rheology: {rheology}
time: {{end: 10.0, cfl: 0.5}}
output: {{every: 10.0}}
"""


# --- the law ---------------------------------------------------------------------------------


def test_parameters_are_packed_and_the_reference_is_the_paper():
    rheology = parse_scenario(_scenario(
        "{law: velocity_weakening, mu_s: 0.7, mu_w: 0.1, U_w: 4.0}")).rheology
    law, params = friction_parameters(rheology)
    assert law is Law.VELOCITY_WEAKENING
    np.testing.assert_array_equal(params, PARAMS)
    assert "Lucas, Mangeney and Ampuero (2014)" in law_reference(law)
    assert "Nat. Commun. 5, 3417" in law_reference(law)


def test_tau_is_the_formula_times_the_normal_load_and_there_is_no_drag():
    """tau = mu(|u|) h N with mu by hand; mu_s at rest, the mid value at U_w, mu_w far out;
    mu_w = mu_s is Coulomb at every speed."""
    for h in (0.0, 1e-9, 0.3, 40.0):
        for v in (0.0, 0.5, 4.0, 60.0, 1e6):
            for n in (0.0, 4.0, 9.81):
                tau, drag = friction(int(Law.VELOCITY_WEAKENING), *PARAMS, h, v, n, G)
                by_hand = (MU_W + (MU_S - MU_W) / (1.0 + v / U_W)) * h * n
                # the paper's form by hand, the kernel's rearranged one: a few ulps apart
                assert tau == pytest.approx(by_hand, rel=1e-14, abs=0.0) and drag == 0.0
    # exactly Coulomb at rest, for any pair (mu_w + (mu_s - mu_w) rounds 0.9, 0.2 to
    # 0.8999999999999999)
    for mu_s, mu_w in ((MU_S, MU_W), (0.9, 0.2), (0.9391491627785106, 0.35800764067250507)):
        assert velocity_weakening_mu(0.0, mu_s, mu_w, U_W) == mu_s
    assert velocity_weakening_mu(U_W, MU_S, MU_W, U_W) == pytest.approx((MU_S + MU_W) / 2)
    assert velocity_weakening_mu(1e12, MU_S, MU_W, U_W) == pytest.approx(MU_W, rel=1e-10)
    tau, _ = friction(int(Law.VELOCITY_WEAKENING), 0.4, 0.4, 2.0, 0, 0, 0, 0, 0,
                      2.0, 33.0, 9.0, G)
    assert tau == friction(int(Law.COULOMB), 0.4, 0, 0, 0, 0, 0, 0, 0, 2.0, 33.0, 9.0, G)[0]


finite = dict(allow_nan=False, allow_infinity=False)


@settings(max_examples=200, deadline=None)
@given(speed=st.floats(0.0, 1e4, **finite), mu_s=st.floats(0.0, 3.0, **finite),
       frac=st.floats(0.0, 1.0, **finite), u_w=st.floats(1e-3, 1e3, **finite))
def test_mu_stays_between_mu_w_and_mu_s_and_falls_with_speed(speed, mu_s, frac, u_w):
    """The law only brakes, never more than Coulomb with mu_s nor less than with mu_w, and
    a faster cell never has more friction (velocity weakening)."""
    mu_w = frac * mu_s
    mu = velocity_weakening_mu(speed, mu_s, mu_w, u_w)
    assert mu_w * (1 - 1e-15) <= mu <= mu_s * (1 + 1e-15)
    assert velocity_weakening_mu(speed * 1.5 + 1.0, mu_s, mu_w, u_w) <= mu * (1 + 1e-15)


def test_speed_threshold_is_where_gravity_balances_the_weakened_friction():
    """u_c = U_w (mu_s - tan) / (tan - mu_w) solves mu(u_c) = tan(theta); 0 from
    atan(mu_s) up, infinite from atan(mu_w) down."""
    for theta in (10.0, 20.0, 30.0):
        u_c = velocity_weakening_threshold(theta, MU_S, MU_W, U_W)
        assert velocity_weakening_mu(u_c, MU_S, MU_W, U_W) == pytest.approx(
            math.tan(math.radians(theta)), rel=1e-14)
    assert velocity_weakening_threshold(36.0, MU_S, MU_W, U_W) == 0.0
    assert velocity_weakening_threshold(5.0, MU_S, MU_W, U_W) == math.inf


# --- rest: Coulomb with mu_s, bit for bit, every kernel --------------------------------------


def _plane(mesh_kind, theta_deg=20.0):
    from avflow.terrain.bed import surface_terrain
    from avflow.terrain.trimesh import triangle_terrain
    from conftest import walls

    x, y = np.arange(0.0, 401.0, 10.0), np.arange(0.0, 301.0, 10.0)
    xx, _ = np.meshgrid(x, y)
    z = -math.tan(math.radians(theta_deg)) * xx
    if mesh_kind == "triangles":
        return triangle_terrain(z, x, y, walls())
    return surface_terrain(z, x, y, walls())


@pytest.mark.parametrize("mesh_kind, kernel, order", [
    ("profile", "auto", 1), ("profile", "auto", 2),
    ("grid", "grid", 1), ("grid", "faces", 1), ("grid", "faces", 2),
    ("triangles", "faces", 1), ("triangles", "faces", 2)])
def test_pile_under_atan_mu_s_stays_exactly_at_rest(mesh_kind, kernel, order):
    """A parabolic pile (10 m high, 100 m in radius) on a 20 degree profile or a 15 degree
    plane under mu_s = tan 30 deg and mu_w = 0.1 (which alone lets it flow): at rest mu =
    mu_s exactly, so the threshold of eq. 49 holds it and the Dirac flux moves no mass. h
    bit for bit after 2000 steps, q = 0. (The plane is gentler: a 2D pile's rim on 10 m
    cells on 20 degrees is at tan 30 deg's limit and slumps under Coulomb 30 deg too.)"""
    params = np.array([math.tan(math.radians(30.0)), MU_W, U_W])
    if mesh_kind == "profile":
        terrain = slope_profile(1000.0, 5.0, 20.0)
        h0 = np.maximum(0.0, 10.0 * (1.0 - ((terrain.x - 500.0) / 100.0) ** 2))
    else:
        terrain = _plane(mesh_kind, 15.0)
        xx, yy = terrain.cell_xy()
        h0 = np.maximum(0.0, 10.0 * (1.0 - ((xx - 200.0) ** 2 + (yy - 150.0) ** 2) / 100.0**2))
    solver = Solver(terrain, Law.VELOCITY_WEAKENING, params, order=order, kernel=kernel,
                    threads=1)
    state = solver.new_state(h0)
    assert solver.advance(state, 1e9, max_steps=2000) == "max_steps"
    assert state.steps == 2000
    assert np.array_equal(state.h, h0)
    assert not state.hu.any() and not state.hv.any()
    # the same pile under mu_w alone (Coulomb 5.7 deg) does flow: the rest is mu_s's doing
    moving = Solver(terrain, Law.COULOMB, np.array([MU_W]), order=order, kernel=kernel,
                    threads=1)
    other = moving.new_state(h0)
    moving.advance(other, 1e9, max_steps=20)
    assert other.hu.any()


# --- a block on a plane between atan(mu_w) and atan(mu_s) ------------------------------------

THETA = 20.0  # deg: atan(0.1) = 5.7 < 20 < atan(0.7) = 35
LENGTH, H = 4000.0, 2.0
MIDDLE = (1500.0, 3500.0)


def _block(u0, order, dx=10.0, t_end=30.0):
    """A uniform layer (2 m) over a long slope, launched downslope at u0: away from the ends
    the fluxes cancel and each cell is the point mass ``du/dt = g cos(tan - mu(u))`` (seed
    eqs. 47-50 with mu at time n). The wall at the top sends a rarefaction down at most at
    u + sqrt(3) c (38 m/s here: 1.1 km in 30 s), the outflow at the bottom sends nothing
    further up than (sqrt(3) c - u) t < 230 m, so the middle 1500-3500 m stays uniform."""
    terrain = slope_profile(LENGTH, dx, THETA, x_max="outflow")
    solver = Solver(terrain, Law.VELOCITY_WEAKENING, PARAMS, order=order)
    state = solver.new_state(np.full(terrain.n_cells, H))
    state.hu[:] = u0 * H
    solver.advance(state, t_end)
    middle = (terrain.x > MIDDLE[0]) & (terrain.x < MIDDLE[1])
    assert np.array_equal(state.h[middle], np.full(middle.sum(), H))  # still uniform
    return state.hu[middle] / H


def point_mass_speed(u0, t_end):
    th = math.radians(THETA)

    def rhs(_, u):
        return [G * math.cos(th) * (math.tan(th) - velocity_weakening_mu(u[0], MU_S, MU_W, U_W))]

    return solve_ivp(rhs, (0.0, t_end), [u0], rtol=1e-12, atol=1e-12).y[0, -1]


@pytest.mark.parametrize("order", [1, 2])
def test_block_released_at_rest_stays_at_rest(order):
    """mu_s = 0.7 > tan 20 deg = 0.36: the layer never moves (q = 0 exactly), though mu_w
    alone would accelerate it at 2.4 m/s^2."""
    assert not _block(0.0, order).any()


@pytest.mark.parametrize("order", [1, 2])
def test_speed_threshold_of_the_block_is_the_analytic_one(order):
    """Released 0.1% above u_c = U_w (mu_s - tan) / (tan - mu_w) = 5.09 m/s it accelerates;
    0.1% below it brakes and stops. u_c is the unstable fixed point of du/dt = g cos (tan -
    mu(u)) (mu falls with u), and each explicit stage moves u away from it on its own side
    (u^{n+1} - u_c = u^n - u_c + dt f(u^n), f of the sign of u - u_c; Heun's average of two
    such stages too), so the scheme's threshold is the analytic one at any dt; 0.1% grows
    by exp(f'(u_c) t) = exp(0.27 t), out of round-off and into a stop or a run within 30 s."""
    u_c = velocity_weakening_threshold(THETA, MU_S, MU_W, U_W)
    assert u_c == pytest.approx(4.0 * (0.7 - math.tan(math.radians(20.0)))
                                / (math.tan(math.radians(20.0)) - 0.1), rel=1e-15)
    above = _block(u_c * 1.001, order)
    below = _block(u_c * 0.999, order)
    assert above.min() > 2.0 * u_c, above.min()   # ran away (point mass: 13 m/s)
    assert not below.any()                        # stopped: q = 0 exactly (eq. 49)


@pytest.mark.parametrize("order", [1, 2])
def test_block_launched_above_the_threshold_follows_the_point_mass(order):
    """Launched at 2 u_c the layer accelerates as the point mass (solve_ivp, 1e-12). Each
    stage's friction is explicit (mu at time n): order 1 is Euler's method, first order in
    dt, order 2 Heun's, second order; the error at 20 s is under 2% at dx = 10 m and falls
    by 2 (order 1) or 4 (order 2) when dx, hence dt, halves."""
    u0, t_end = 2.0 * velocity_weakening_threshold(THETA, MU_S, MU_W, U_W), 20.0
    exact = point_mass_speed(u0, t_end)
    errors = []
    for dx in (10.0, 5.0):
        u = _block(u0, order, dx=dx, t_end=t_end)
        assert np.ptp(u) <= 1e-12 * exact  # uniform: every middle cell the same point mass
        errors.append(abs(u[0] / exact - 1.0))
    assert exact > 2.5 * u0  # it accelerated: 10 -> 40 m/s
    assert errors[0] < 0.01, errors
    assert 0.8 / 2**order < errors[1] / errors[0] < 1.2 / 2**order, errors


@pytest.mark.parametrize("mesh_kind, kernel, order", [
    ("grid", "grid", 1), ("grid", "faces", 1), ("grid", "faces", 2), ("triangles", "faces", 1)])
def test_speed_threshold_on_the_2d_kernels(mesh_kind, kernel, order):
    """The same block on a 2D plane (a 4 km x 60 m strip of the 20 degree plane, walls on
    its sides, outflow at its foot) on the square-grid and face kernels: 0.1% above u_c the
    middle of the layer runs away, 0.1% below it stops, at rest it stays (q = 0 exactly).
    Side walls take nothing from a flow along them; the ends are as far as on the profile."""
    from avflow.terrain.bed import surface_terrain
    from avflow.terrain.trimesh import triangle_terrain
    from conftest import walls

    x, y = np.arange(0.0, LENGTH + 1.0, 20.0), np.arange(0.0, 61.0, 20.0)
    xx, _ = np.meshgrid(x, y)
    z = -math.tan(math.radians(THETA)) * xx
    bounds = walls(x_max="outflow")
    terrain = (triangle_terrain(z, x, y, bounds) if mesh_kind == "triangles"
               else surface_terrain(z, x, y, bounds))
    cx, _ = terrain.cell_xy()
    middle = (cx > MIDDLE[0]) & (cx < MIDDLE[1])
    u_c = velocity_weakening_threshold(THETA, MU_S, MU_W, U_W)
    speeds = {}
    for factor in (0.0, 0.999, 1.001):
        solver = Solver(terrain, Law.VELOCITY_WEAKENING, PARAMS, order=order, kernel=kernel,
                        threads=1)
        state = solver.new_state(np.full(terrain.n_cells, H))
        state.hu[:] = factor * u_c * H  # along the first tangent axis: downslope (+x)
        solver.advance(state, 30.0)
        # still uniform, to the round-off of 2D face geometry (measured 1.6e-12 after 30 s)
        assert np.abs(state.h[middle] / H - 1.0).max() < 1e-10
        speeds[factor] = np.hypot(state.hu, state.hv)[middle] / H
    assert not speeds[0.0].any() and not speeds[0.999].any()
    assert speeds[1.001].min() > 2.0 * u_c


# --- bad input -------------------------------------------------------------------------------


@pytest.mark.parametrize("rheology, dotted, words", [
    ("mu_s: 0.3, mu_w: 0.5, U_w: 4.0", "rheology.mu_w", "must be at most mu_s (0.3), got 0.5"),
    ("mu_s: 0.7, mu_w: 0.1, U_w: 0", "rheology.U_w", "must be > 0, got 0"),
    ("mu_s: 0.7, mu_w: 0.1, U_w: -4.0", "rheology.U_w", "must be > 0, got -4"),
    ("mu_s: .nan, mu_w: 0.1, U_w: 4.0", "rheology.mu_s", "finite"),
    ("mu_s: 0.7, mu_w: .nan, U_w: 4.0", "rheology.mu_w", "finite"),
    ("mu_s: 0.7, mu_w: 0.1, U_w: .nan", "rheology.U_w", "finite"),
    ("mu_s: 0.7, mu_w: -0.1, U_w: 4.0", "rheology.mu_w", "must be >= 0"),
    ("mu_s: 0.7, mu_w: 0.1", "rheology.U_w", "required"),
    ("mu_s: 0.7, mu_w: 0.1, U_w: 4.0, xi: 3", "rheology.xi", "unknown field"),
], ids=["mu_w>mu_s", "U_w=0", "U_w<0", "nan-mu_s", "nan-mu_w", "nan-U_w", "mu_w<0",
        "missing", "unknown"])
def test_bad_parameters_give_one_line_errors(tmp_path, rheology, dotted, words):
    path = tmp_path / "bad.yaml"
    path.write_text(_scenario("{law: velocity_weakening, %s}" % rheology))
    with pytest.raises(ScenarioError) as caught:
        load_scenario(path)
    text = str(caught.value)
    assert len(text.splitlines()) == 1, text
    assert text.startswith(f"{path}:7:") and f": {dotted}: " in text and words in text, text


def test_bad_parameters_exit_2_with_one_line_from_the_command_line(tmp_path):
    import subprocess
    import sys

    path = tmp_path / "bad.yaml"
    path.write_text(_scenario("{law: velocity_weakening, mu_s: 0.2, mu_w: 0.5, U_w: 4.0}"))
    done = subprocess.run([sys.executable, "-m", "avflow.cli", "run", str(path), "-o",
                           str(tmp_path / "out.nc")], capture_output=True, text=True)
    assert done.returncode == 2, done.stderr
    assert done.stdout == "" and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert f"{path}:7:" in done.stderr and "rheology.mu_w: must be at most mu_s" in done.stderr


# --- an ensemble mixing the laws -------------------------------------------------------------

LAWS_ENSEMBLE = """
name: four-laws
base: base.yaml
vary:
  rheology:
    - {law: coulomb, delta_deg: 24.0}
    - {law: voellmy, mu: 0.155, xi: 4000.0}
    - {law: samosat}
    - {law: velocity_weakening, mu_s: 0.4452, mu_w: 0.155, U_w: 4.0}
thresholds: [0.1, 1.0]
"""


def test_an_ensemble_mixing_four_laws_runs_and_its_report_keeps_them_apart(tmp_path):
    """scenarios/ensembles/avakot_friction_laws.yaml's mix on the cheap plane scene (20 m
    cells): one member per law, each named in ensemble.nc and in its own row of the
    report's per-law table. Velocity weakening from tan 24 deg = 0.4452 at rest never has
    more friction than Coulomb 24 deg, so it runs at least as far (farther: it speeds up)."""
    import xarray as xr

    from avflow.cli import main
    from conftest import SCENARIOS

    base = (SCENARIOS / "plane_box_runout_2d.yaml").read_text().replace("dx: 10.0", "dx: 20.0")
    (tmp_path / "base.yaml").write_text(base)
    (tmp_path / "ens.yaml").write_text(LAWS_ENSEMBLE)
    out = tmp_path / "out"
    assert main(["ensemble", str(tmp_path / "ens.yaml"), "-o", str(out)]) == 0
    assert main(["report", str(out)]) == 0
    laws = ["coulomb", "voellmy", "samosat", "velocity_weakening"]
    with xr.open_dataset(out / "ensemble.nc", decode_times=False) as ds:
        assert list(ds["law"].values) == laws
        runout = dict(zip(laws, ds["runout"].values))
        np.testing.assert_array_equal(ds["rheology_U_w"].values[:3], np.nan)
        assert float(ds["rheology_U_w"].values[3]) == 4.0
    assert runout["velocity_weakening"] > runout["coulomb"] > 0.0
    text = (out / "report.md").read_text()
    table = text.split("## Summary per law")[1].split("##")[0]
    rows = [line.split("|")[1].strip() for line in table.splitlines() if line.startswith("| ")]
    assert rows == ["law"] + laws


# --- volume mobility (workflows/volume_mobility.py, coarse) ------------------------------------


def _workflow():
    import importlib.util

    from conftest import REPO

    spec = importlib.util.spec_from_file_location("volume_mobility",
                                                  REPO / "workflows" / "volume_mobility.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_coulomb_mobility_does_not_depend_on_volume_on_a_plane():
    """A plane has no length scale and neither has Coulomb's law: the member of 1e6 m^3 is
    the member of 1e10 m^3 shrunk by 1e4^(1/3) in length and 1e4^(1/6) in time, so H/L is
    the same to round-off (1e-12; the grid, the window and the film threshold scale with
    the release, workflows/volume_mobility.py: magnified)."""
    vm = _workflow()
    coulomb = vm.law_members()[0]
    assert coulomb.rheology.law == "coulomb"
    rows = [vm.run_member(coulomb, v, cells=4) for v in (1e6, 1e10)]
    assert rows[0]["steps"] == rows[1]["steps"]
    assert rows[1]["H_over_L"] == pytest.approx(rows[0]["H_over_L"], rel=1e-12)
    assert rows[1]["L_m"] / rows[0]["L_m"] == pytest.approx(1e4 ** (1 / 3), rel=1e-12)
    assert all(r["status"] == "at_rest" and r["volume_lost"] < 1e-12 for r in rows)


def test_velocity_weakening_mobility_grows_with_volume_coarse():
    """The issue's benchmark at 4 cells per radius (1e6, 1e8, 1e10 m^3; the workflow's 8
    cells give -0.038, measured 2026-12-04): velocity weakening's log-log slope of H/L
    against V is negative but short of Scheidegger's -0.157 on this scene, which only lets
    a mass fall its own height (speed ~ sqrt(g h0) ~ V^(1/6), so mu ~ U_w / |u| falls at
    most as V^(-1/6), and mu_w = 0.1 stops it sooner). Pinned within 0.01 of the measured
    -0.037; Coulomb's slope is 0 (the test above), at most a third of it in magnitude.
    docs/guide/volume-mobility.md: the target is not met, and why."""
    vm = _workflow()
    weakening = vm.law_members()[1]
    assert weakening.rheology.law == "velocity_weakening"
    rows = [vm.run_member(weakening, v, cells=4) for v in (1e6, 1e8, 1e10)]
    assert all(r["status"] == "at_rest" and r["volume_lost"] < 1e-9 for r in rows)
    h_over_l = [r["H_over_L"] for r in rows]
    assert h_over_l[0] > h_over_l[1] > h_over_l[2]  # mobility grows with volume
    measured = vm.slope(rows, "velocity_weakening")
    assert measured == pytest.approx(-0.037, abs=0.01)
    # the same flows under Coulomb with mu_s go less far at every volume
    assert max(h_over_l) < vm.run_member(vm.law_members()[0], 1e6, cells=4)["H_over_L"]


def test_a_small_coulomb_mass_on_the_fixed_hockey_stick_is_the_sliding_block(tmp_path):
    """--topography hockey: 1e6 m^3 (a radius of 110 m) down the 5 km, 40 degree slope onto
    flat ground under Coulomb 35 deg. A sliding block loses g H in friction work mu g L
    (curvature off; the break turns the velocity without loss), so H/L = tan 35 deg; the
    mass is a block to 0.2% here (measured 0.7014 against 0.7002), checked within 1%."""
    vm = _workflow()
    row = vm.run_member(vm.law_members()[0], 1e6, cells=4, topography="hockey",
                        folder=tmp_path)
    assert row["status"] == "at_rest" and row["volume_lost"] < 1e-12
    assert row["H_over_L"] == pytest.approx(math.tan(math.radians(35.0)), rel=0.01)


def test_the_exponential_slope_magnified_with_the_release_is_one_scene_under_coulomb(tmp_path):
    """--topography exponential-similar: the seed's exponential slope magnified with the
    cylinder (a = 1750 m at 1e8 m^3), so under Coulomb the 1e10 m^3 member is the 1e6 m^3
    one magnified 1e4^(1/3) times: H/L and H/dL agree to round-off (1e-9) and nothing
    leaves the window."""
    vm = _workflow()
    rows = [vm.run_member(vm.law_members()[0], v, cells=4, topography="exponential-similar",
                          folder=tmp_path) for v in (1e6, 1e10)]
    assert rows[0]["steps"] == rows[1]["steps"]
    assert rows[1]["H_over_L"] == pytest.approx(rows[0]["H_over_L"], rel=1e-9)
    assert rows[1]["H_over_dL"] == pytest.approx(rows[0]["H_over_dL"], rel=1e-9)
    assert rows[1]["L_m"] / rows[0]["L_m"] == pytest.approx(1e4 ** (1 / 3), rel=1e-9)
    assert all(r["status"] == "at_rest" and r["volume_lost"] < 1e-12 for r in rows)


@pytest.mark.parametrize("mu_w, u_w, slope_l, slope_dl", [
    (0.1, 5.0, -0.0615, -0.0721),   # the ensemble's values
    (0.05, 10.0, -0.124, -0.151),   # chosen: the steepest with mu_w 0.05 in our scan
])
def test_mobility_against_volume_on_the_magnified_exponential_slope_coarse(
        tmp_path, mu_w, u_w, slope_l, slope_dl):
    """The issue's benchmark on the seed's exponential slope magnified with the release,
    at 4 cells per radius (1e6, 1e8, 1e10 m^3), velocity weakening with mu_s 0.7: slopes
    of H/L and of H/dL (dL: the front's travel beyond the release) against V pinned within
    0.01 of those measured 2026-12-04. With the ensemble's 0.1 / 5 m/s they fall short of
    Scheidegger's -0.157 +- 0.05; with mu_w 0.05 and U_w 10 m/s (our choice, not the
    paper's values) both are within it. Coulomb's slope is 0 (the test above)."""
    vm = _workflow()
    law = vm.law_members()[1].with_updates({"rheology.mu_w": mu_w, "rheology.U_w": u_w})
    rows = [vm.run_member(law, v, cells=4, topography="exponential-similar", folder=tmp_path)
            for v in (1e6, 1e8, 1e10)]
    assert all(r["status"] == "at_rest" and abs(r["volume_lost"]) < 1e-9 for r in rows)
    assert rows[0]["H_over_L"] > rows[1]["H_over_L"] > rows[2]["H_over_L"]
    assert all(r["H_over_dL"] > r["H_over_L"] for r in rows)  # dL = L - 2 radii
    assert vm.slope(rows, "velocity_weakening") == pytest.approx(slope_l, abs=0.01)
    assert vm.slope(rows, "velocity_weakening", measure="H_over_dL") == pytest.approx(
        slope_dl, abs=0.01)


def test_volume_mobility_workflow_writes_its_table_and_plot(tmp_path, capsys):
    vm = _workflow()
    assert vm.main(["-o", str(tmp_path), "--cells", "3", "--volumes", "1e6,1e10"]) == 0
    text = (tmp_path / "volume_mobility.csv").read_text().splitlines()
    assert text[0].startswith("law,volume_m3,H_m,L_m,H_over_L,dL_m,H_over_dL") and len(text) == 5
    assert (tmp_path / "volume_mobility.png").stat().st_size > 10_000
    out = capsys.readouterr().out
    assert "coulomb: " in out and "velocity_weakening: " in out and "Scheidegger -0.157" in out
    assert vm.main(["-o", str(tmp_path), "--volumes", "1e6,lots"]) == 2
    for bad in ("0.7,0.1", "0.1,0.7,5", "0.7,0.1,0", "inf,0.1,5"):
        assert vm.main(["-o", str(tmp_path), "--weakening", bad]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 5 and all(line.startswith("volume_mobility: ") for line in err)
