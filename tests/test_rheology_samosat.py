"""samosAT, AvaFrame com1DFA's standard snow friction law (issue 9, item 5).

The law against AvaFrame's own formula (SamosATfric), the steady uniform flow it predicts on
an inclined plane, its parameter checks, that it never reverses a velocity, and a run of the
project's AvaFrame-path scenario.
"""

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import brentq

from avflow.errors import ScenarioError
from avflow.numerics.cpu import project as _project
from avflow.numerics.rheology import Law, friction, friction_parameters, law_reference
from avflow.output.dataset import to_dataset
from avflow.scenario.schema import load_scenario, parse_scenario
from avflow.simulation.runner import simulate

REPO = Path(__file__).resolve().parents[1]
G = 9.81
#: AvaFrame 2.1 com1DFACfg.ini, samosAT (standard)
DEFAULTS = dict(mu=0.155, tau0=0.0, Rs0=0.222, kappa=0.43, R=0.05, B=4.13)


def avaframe_tau(rho, v, sigma, h, mu, tau0, Rs0, kappa, R, B):
    """AvaFrame's DFAToolsCython.SamosATfric, line for line (Pa)."""
    rs = rho * v * v / (sigma + 0.001)
    div = h / R
    if div < 1.0:
        div = 1.0
    div = math.log(div) / kappa + B
    return tau0 + sigma * mu * (1.0 + Rs0 / (Rs0 + rs)) + rho * v * v / (div * div)


def packed(rho=200.0, **kw):
    rheology = parse_scenario(_scenario("{law: samosat%s}" % "".join(
        f", {k}: {v}" for k, v in kw.items()), rho)).rheology
    return friction_parameters(rheology, rho)


def _scenario(rheology, rho=200.0, theta=20.0, length=1000.0, thickness=1.0, end=10.0):
    return f"""
name: samosat
terrain: {{kind: profile, length: {length}, slope: {{kind: constant, theta_deg: {theta}}},
          curvature: false}}
grid: {{dx: 10.0}}
release: {{kind: box, x: [0.0, {length}], thickness: {thickness}}}
rheology: {rheology}
time: {{end: {end}, cfl: 0.5}}
output: {{every: 10.0, stop_fraction: 0.0}}
boundary: {{x_min: wall, x_max: outflow}}
physics: {{density: {rho}}}
"""


# --- the law is AvaFrame's ------------------------------------------------------------------


def test_defaults_are_avaframes_standard_samosat():
    rheology = parse_scenario(_scenario("{law: samosat}")).rheology
    assert {k: getattr(rheology, k) for k in DEFAULTS} == DEFAULTS
    law, params = friction_parameters(rheology, 200.0)
    assert law is Law.SAMOSAT and "Sampl and Zwinger (2004)" in law_reference(law)
    np.testing.assert_array_equal(params, [0.155, 0.0, 0.222, 0.001 / 200.0, 0.43, 0.05, 4.13, 0.0])
    with pytest.raises(ValueError, match="density"):
        friction_parameters(rheology)


@pytest.mark.parametrize("rho, kw", [(200.0, {}), (300.0, dict(mu=0.22, tau0=70.0)),
                                     (150.0, dict(Rs0=0.5, kappa=0.4, R=0.2, B=3.0))])
def test_tau_plus_drag_is_avaframes_stress_over_rho(rho, kw):
    """rho (tau + drag h |u|) equals SamosATfric's stress to round-off, across both branches
    of D (h below and above R), rest, films and a zero normal stress."""
    law, p = packed(rho, **kw)
    par = {**DEFAULTS, **kw}
    for h in (1e-9, 0.01, 0.05, 0.3, 2.0, 40.0):
        for v in (0.0, 0.3, 5.0, 60.0):
            for n in (0.0, 4.0, 9.81):
                tau, drag = friction(int(law), *p, h, v, n, G)
                expected = avaframe_tau(rho, v, rho * h * n, h, **par)
                assert rho * (tau + drag * h * v) == pytest.approx(expected, rel=1e-13, abs=1e-12)


# --- steady uniform flow on an inclined plane ----------------------------------------------


def steady_speed(theta_deg, h, rho, mu, tau0, Rs0, kappa, R, B, turbulent=True, rs=True):
    """Root of rho g sin(theta) h = tau_b(h, v) (Pa), N = g cos(theta) on a plane."""
    th = math.radians(theta_deg)
    sigma = rho * h * G * math.cos(th)
    d = math.log(max(h / R, 1.0)) / kappa + B

    def excess(v):
        factor = 1.0 + (Rs0 / (Rs0 + rho * v * v / (sigma + 0.001)) if rs else 0.0)
        return (rho * G * math.sin(th) * h - tau0 - mu * sigma * factor
                - (rho * v * v / d**2 if turbulent else 0.0))

    return brentq(excess, 0.0, 1e3, xtol=1e-14, rtol=4 * np.finfo(float).eps)


@pytest.mark.parametrize("theta, h, rho, kw, end", [
    (30.0, 2.0, 200.0, {}, 120.0),              # D on its logarithmic branch (h = 40 R)
    (20.0, 0.04, 200.0, {}, 100.0),             # h < R: D = B; Rs ~ 3.5, the Rs0 term is 6%
    (25.0, 0.5, 300.0, dict(tau0=20.0), 100.0),  # a yield stress and another density
], ids=["thick", "under-R", "tau0-rho300"])
def test_steady_uniform_flow_on_an_inclined_plane_reaches_the_predicted_speed(theta, h, rho, kw,
                                                                              end):
    """A long slope uniformly covered (at rest, h) accelerates to the speed where gravity
    balances samosAT: rho g sin(theta) h = tau_b(h, v), solved here with brentq.

    As in Voellmy's test (test_ensemble): the wall at the top sends a rarefaction down at
    most at u + sqrt(3) c (41 m/s for the thick case: 4.9 km in 120 s), the outflow at the
    bottom cannot be felt upstream once Fr > sqrt(3) (Fr = 8.3, 1.8, 5.2 here), so the
    middle of the slope stays uniform: the fluxes cancel exactly and each step solves the
    ODE of one cell with tau at |u^n| and the implicit drag. Its fixed point is the root
    above for every dt (at v_s: q (1 + v_s dt / (D^2 h)) = q + dt (g h sin - tau(v_s))), and
    the states are stable (tau_b grows with v: (Rs0 + Rs)^2 > mu Rs0 D^2), so what is left
    is the transient, below 1e-10 at these end times (measured). Tolerance 1e-8 relative;
    dropping the turbulent term or the Rs0 term moves the prediction by far more (checked).
    """
    par = {**DEFAULTS, **kw}
    v_s = steady_speed(theta, h, rho, **par)
    length = 12000.0 if h > 1.0 else 4000.0
    rheology = "{law: samosat%s}" % "".join(f", {k}: {v}" for k, v in kw.items())
    ds = to_dataset(simulate(parse_scenario(_scenario(rheology, rho, theta, length, h, end))))
    x = ds["x"].values
    middle = (x > 0.6 * length) & (x < 0.9 * length)
    u_end = ds["u"].values[-1, middle]
    assert float(ds["time"][-1]) == end
    np.testing.assert_array_equal(ds["h"].values[-1, middle], h)  # still uniform
    assert np.abs(u_end / v_s - 1.0).max() < 1e-8, (u_end.min(), u_end.max(), v_s)
    # each part of the law matters at this tolerance
    for off in (dict(turbulent=False), dict(rs=False)):
        try:
            other = steady_speed(theta, h, rho, **par, **off)
        except ValueError:  # no root: without drag the layer never stops accelerating
            continue
        assert abs(other / v_s - 1.0) > 1e-5  # thick: the Rs0 term is 6e-4 of v_s


def test_static_friction_is_twice_mu():
    """At rest Rs = 0: the Coulomb part is 2 mu sigma (AvaFrame's note: static friction
    0.31, 17.2 degrees). A layer on 16 degrees never moves; on 18 degrees it flows."""
    for theta, moves in ((16.0, False), (18.0, True)):
        ds = to_dataset(simulate(parse_scenario(_scenario("{law: samosat}", theta=theta))))
        assert bool(np.abs(ds["u"].values).max() > 0.0) is moves, theta
        assert float(ds["mass_balance_error"]) < 1e-12


# --- parameter checks -----------------------------------------------------------------------


@pytest.mark.parametrize("extra, dotted, words", [
    (", R: -0.05", "rheology.R", "must be > 0, got -0.05"),
    (", kappa: 0", "rheology.kappa", "must be > 0, got 0"),
    (", B: 0.0", "rheology.B", "must be > 0"),
    (", Rs0: -1", "rheology.Rs0", "must be > 0"),
    (", mu: -0.1", "rheology.mu", "must be >= 0"),
    (", tau0: -70", "rheology.tau0", "must be >= 0"),
    (", R: .nan", "rheology.R", "finite"),
    (", xi: 4000", "rheology.xi", "unknown field"),
    (", delta_deg: 20", "rheology.delta_deg", "unknown field"),
], ids=["R", "kappa", "B", "Rs0", "mu", "tau0", "nan", "xi", "delta"])
def test_bad_samosat_parameters_give_one_line_errors(tmp_path, extra, dotted, words):
    path = tmp_path / "bad.yaml"
    path.write_text(_scenario("{law: samosat%s}" % extra))
    with pytest.raises(ScenarioError) as caught:
        load_scenario(path)
    text = str(caught.value)
    assert len(text.splitlines()) == 1, text
    assert text.startswith(f"{path}:7:") and f": {dotted}: " in text and words in text, text


# --- never reverses a velocity -------------------------------------------------------------

finite = dict(allow_nan=False, allow_infinity=False)


@settings(max_examples=300, deadline=None)
@given(h=st.floats(0.0, 1e3, **finite), speed=st.floats(0.0, 1e3, **finite),
       accel=st.floats(0.0, 100.0, **finite), qx=st.floats(-1e5, 1e5, **finite),
       qy=st.floats(-1e5, 1e5, **finite), dt=st.floats(1e-6, 1e3, **finite),
       tau0=st.floats(0.0, 1e4, **finite), rho=st.floats(1.0, 3000.0, **finite))
def test_friction_never_reverses_the_velocity(h, speed, accel, qx, qy, dt, tau0, rho):
    """tau >= 0 finite and drag >= 0 (+inf only for a moving subnormal h, 5e-324 m: it
    stops the cell) for any state (dry, at rest, films, no normal stress); the projection
    then only shortens q~ along itself (eq. 50 and the implicit drag): the new discharge is
    q~ times a factor in [0, 1]."""
    law, p = packed(rho, tau0=tau0)
    tau, drag = friction(int(law), *p, h, speed, accel, G)
    assert math.isfinite(tau) and tau >= 0.0 and drag >= 0.0  # (NaN fails >= 0)
    assert math.isfinite(drag) or h < 1e-300
    nx, ny = _project(qx, qy, tau, drag, dt)
    assert nx * qx >= 0.0 and ny * qy >= 0.0
    assert abs(nx) <= abs(qx) and abs(ny) <= abs(qy)
    assert abs(nx * qy - ny * qx) <= 1e-12 * (qx * qx + qy * qy)  # parallel to q~


def test_a_mass_braking_on_flat_ground_never_turns_back():
    """A layer flows from a 30 degree slope onto flat ground (exponential profile) and
    comes to rest under samosAT (all but a creeping tail on the slope steeper than its static
    17.2 degrees): no cell ever moves upslope (u >= 0 at every snapshot)."""
    scenario = parse_scenario("""
name: samosat-runout
terrain: {kind: profile, length: 3000.0, slope: {kind: exponential, theta0_deg: 30.0, a: 400.0}}
grid: {dx: 5.0}
release: {kind: parabola, center: 200.0, half_length: 100.0, max_thickness: 5.0}
rheology: {law: samosat}
time: {end: 300.0, cfl: 0.5}
output: {every: 2.0}
physics: {density: 200.0}
""")
    ds = to_dataset(simulate(scenario))
    moving = ds["moving_volume"].values
    assert moving[-1] < 0.01 * float(ds["release_volume"]) < moving.max()  # it ran, it rests
    assert ds["u"].values.min() >= 0.0
    assert float(ds["mass_balance_error"]) < 1e-12


# --- the AvaFrame paths ---------------------------------------------------------------------


def test_avakot_samosat_scenario_runs_end_to_end():
    """scenarios/avakot_samosat.yaml (AvaFrame's standard setup) at 20 m for 20 s."""
    scenario = load_scenario(REPO / "scenarios" / "avakot_samosat.yaml")
    assert scenario.rheology.law == "samosat" and scenario.physics.density == 200.0
    ds = to_dataset(simulate(scenario.with_updates({"grid.dx": 20.0, "time.end": 20.0})))
    assert "samosAT" in ds.attrs["references"]
    assert float(ds["mass_balance_error"]) < 1e-12
    assert 10.0 < float(np.nanmax(ds["peak_speed"])) < 80.0
    assert np.isfinite(ds["h"].values[np.isfinite(ds["h"].values)]).all()


@pytest.mark.parametrize("name", ["avaalr", "avahit", "avakot", "avawog"])
def test_every_avaframe_path_has_snow_density_and_a_samosat_variant(name):
    law = {"avaalr": "voellmy"}.get(name, "coulomb")
    base = load_scenario(REPO / "scenarios" / f"{name}_{law}.yaml")
    variant = load_scenario(REPO / "scenarios" / f"{name}_samosat.yaml")
    assert base.physics.density == variant.physics.density == 200.0
    assert variant.rheology.law == "samosat"
    assert (variant.terrain, variant.grid, variant.release) == (base.terrain, base.grid,
                                                               base.release)
