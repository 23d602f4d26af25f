"""How a run ends and what it says about it: stop rules, films that stop, flows still
moving at time.end, runouts cut by the map's edge."""

import hashlib

import numpy as np
import pytest

from avflow.cli import main
from avflow.numerics import stepping
from avflow.output.dataset import to_dataset
from avflow.scenario import load_scenario, parse_scenario
from avflow.simulation.runner import simulate
from avflow.terrain.raster import write_asc
from conftest import SCENARIOS, faces_permuted

SECTION6 = SCENARIOS / "seed_exponential_coulomb15.yaml"
PLANE = SCENARIOS / "plane_box_2d.yaml"


# --- stop rules --------------------------------------------------------------------------------


def test_kinetic_energy_rule_ends_earlier_with_mass_still_moving():
    """AvaFrame's rule (kinetic energy at 1% of its peak) ends section 6 before the
    moving-volume rule, with part of the mass still moving; the output says which rule."""
    by_volume = simulate(load_scenario(SECTION6))
    by_energy = simulate(load_scenario(SECTION6).with_updates(
        {"output.stop_rule": "kinetic_energy"}))
    sv, se = by_volume.summary, by_energy.summary
    assert by_energy.scenario.output.stop_fraction == 0.01
    # the kinetic-energy rule ends it with mass still moving: not called at rest
    assert by_volume.status == "at_rest" and by_energy.status == "ended_by_rule"
    assert sv["ended_by"] == "moving_volume" and se["ended_by"] == "kinetic_energy"
    assert se["kinetic_energy_end"] <= 0.01 * se["kinetic_energy_peak"]
    assert se["time_to_stop"] < sv["time_to_stop"] - 5.0
    assert se["moving_volume_end"] > 10 * sv["moving_volume_end"]
    assert sv["moving_volume_end"] < 1e-3 * sv["release_volume"]
    assert sv["kinetic_energy_peak"] == pytest.approx(se["kinetic_energy_peak"], rel=1e-9)
    ds = to_dataset(by_energy)
    assert ds.attrs["stop_rule"] == "kinetic_energy" and ds.attrs["ended_by"] == "kinetic_energy"
    assert ds.attrs["status"] == "ended_by_rule" and to_dataset(by_volume).attrs["status"] == "at_rest"
    assert ds["kinetic_energy_peak"].attrs["units"] == "J m-1"  # per metre of width


def test_kinetic_energy_is_half_rho_h_u2_summed():
    result = simulate(load_scenario(PLANE).with_updates({"time.end": 5.0}))
    s, st = result.summary, result.state
    speed2 = (st.hu**2 + st.hv**2) / np.where(st.h > 0, st.h, 1.0) ** 2
    expected = 0.5 * 2000.0 * np.sum(st.h * result.terrain.mesh.cell_area * speed2)
    assert s["kinetic_energy_end"] == pytest.approx(expected, rel=1e-12)


def test_still_moving_at_time_end_says_so(tmp_path, capsys):
    """A flow cut by time.end: no deposit claimed, on the summary line and in the file."""
    out = tmp_path / "short.nc"
    path = tmp_path / "short.yaml"
    path.write_text(PLANE.read_text().replace("time: {end: 60.0, cfl: 0.5}",
                                              "time: {end: 10.0, cfl: 0.5}"))
    assert main(["run", str(path), "-o", str(out)]) == 0
    line = capsys.readouterr().out
    assert "still moving" in line and "not a deposit at rest" in line
    import xarray as xr
    with xr.open_dataset(out, decode_times=False) as ds:
        assert ds.attrs["ended_by"] == "time.end, still moving"
        assert np.isnan(float(ds["time_to_stop"]))


# --- films that stop ---------------------------------------------------------------------------


def film_scenario(min_flow):
    """A 0.5 mm film over a 30 degree plane, Coulomb 20 degrees: it would slide forever."""
    written = "" if min_flow == "default" else f"physics: {{min_flow_thickness: {min_flow}}}\n"
    return parse_scenario(f"""
name: film
terrain: {{kind: plane, slope_deg: 30.0, azimuth_deg: 90.0,
          extent: {{x: [0.0, 2000.0], y: [0.0, 100.0]}}}}
grid: {{dx: 10.0}}
release: {{kind: box, x: [0.0, 1000.0], y: [0.0, 100.0], thickness: 0.0005}}
rheology: {{law: coulomb, delta_deg: 20.0}}
time: {{end: 60.0}}
output: {{every: 10.0, stop_fraction: 0.0, dry_threshold: 1.0e-5}}
{written}""")


def test_a_film_thinner_than_the_minimum_flowing_thickness_stays():
    """With the rule (1 mm) the film keeps its mass where it lies, takes no momentum and no
    longer sets the time step; without it (0) it slides and costs a step per 2 cm/s."""
    held = simulate(film_scenario(0.001))
    free = simulate(film_scenario(0))
    assert held.state.h.tobytes() == held.h0.tobytes()
    assert not held.state.hu.any() and not held.state.hv.any()
    assert held.state.steps <= 10  # the CFL limit of material at rest: inf, one step per output
    assert free.state.steps > 100 * held.state.steps
    assert free.summary["moving_volume_end"] > 0.5 * free.summary["release_volume"]
    for r in (held, free):
        assert r.summary["mass_balance_error"] < 1e-14


def test_default_minimum_flowing_thickness():
    """1 mm, or the dry threshold when that is smaller (here 1e-5 m)."""
    assert simulate(film_scenario("default")).thresholds["min_flow"] == 1e-5
    section6 = load_scenario(SECTION6)
    from avflow.simulation.runner import prepare
    assert prepare(section6)[3]["min_flow"] == 1e-3


def before_grid_order(terrain):
    """A plane's terrain with its mesh's faces in the order grid_mesh made them before they
    were numbered in grid order: the x faces between cells, the y faces between cells, then
    the west, east, south and north sides."""
    ny, nx = terrain.grid_shape
    n_x = ny * (nx + 1)  # x faces first, at r * (nx + 1) + k; then y faces at n_x + k * nx + c
    r, k = np.meshgrid(np.arange(ny), np.arange(1, nx), indexing="ij")
    inner_x = (r * (nx + 1) + k).ravel()
    k, c = np.meshgrid(np.arange(1, ny), np.arange(nx), indexing="ij")
    inner_y = (n_x + k * nx + c).ravel()
    rows, cols = np.arange(ny), np.arange(nx)
    perm = np.concatenate([inner_x, inner_y, rows * (nx + 1), rows * (nx + 1) + nx,
                           n_x + cols, n_x + ny * nx + cols])
    assert np.array_equal(np.sort(perm), np.arange(terrain.mesh.n_faces))
    return faces_permuted(terrain, perm)


@pytest.mark.parametrize("order,expected", [
    # the faces as they were numbered then: the face kernel runs them (no grid layout)
    ("before", "07c7269c062e143dcaca8599e239b748a5a7c497da6bb056e1331cdf665a92ba"),
    # grid order: the cells along the walls add their faces in another order (round-off)
    ("grid", "e385f7e3cd181e1470f95287b0296dbbccd521d0f69748a2fb56111bd635ed72"),
])
def test_plane_without_the_film_rule_is_bit_for_bit_as_before(monkeypatch, order, expected):
    """plane_box_2d to 30 s with min_flow_thickness 0: the state (h, hu, hv) hashes as it did
    before curvature and films were added (commit a616345), with the faces numbered as they
    were then; numbered in grid order, as the hash of that change."""
    import avflow.simulation.runner as runner

    if order == "before":
        build = runner.build_terrain
        monkeypatch.setattr(runner, "build_terrain",
                            lambda sc, *limit: before_grid_order(build(sc, *limit)))
    result = simulate(load_scenario(PLANE).with_updates(
        {"time.end": 30.0, "physics.min_flow_thickness": 0.0, "numerics.order": 1}))
    st = result.state
    digest = hashlib.sha256(st.h.tobytes() + st.hu.tobytes() + st.hv.tobytes()).hexdigest()
    assert (digest, st.steps) == (expected, 323)


# --- runouts cut by the map's edge -------------------------------------------------------------


def slope_dem(tmp_path, length=300.0, boundary="wall"):
    """A 35 degree DEM 300 m long; Coulomb 20 degrees: the mass runs off its lower end."""
    x = np.arange(0.0, length, 5.0)
    y = np.arange(0.0, 100.0, 5.0)
    z = 1000.0 - np.tan(np.radians(35.0)) * x[None, :] + 0.0 * y[:, None]
    write_asc(tmp_path / "dem.asc", z, x, y)
    path = tmp_path / "s.yaml"
    path.write_text(f"""
name: edge
terrain: {{kind: dem, path: dem.asc}}
grid: {{dx: 5.0}}
boundary: {boundary}
release: {{kind: box, x: [20.0, 60.0], y: [30.0, 70.0], thickness: 2.0}}
rheology: {{law: coulomb, delta_deg: 20.0}}
time: {{end: 20.0}}
""")
    return path


@pytest.mark.parametrize("boundary", ["wall", "outflow"])
def test_flow_reaching_the_dem_edge_is_flagged_and_warned(tmp_path, capsys, boundary):
    path = slope_dem(tmp_path, boundary=boundary)
    assert main(["run", str(path), "-o", str(tmp_path / "edge.nc")]) == 0
    captured = capsys.readouterr()
    assert "runout is a lower bound" in captured.err
    assert "RUNOUT TRUNCATED" in captured.out
    result = simulate(load_scenario(path))
    assert result.summary["runout_truncated"]
    if boundary == "outflow":
        assert result.state.stats[stepping.ST_OUTFLOW] > 0.0


def test_flow_that_stays_inside_is_not_flagged(tmp_path):
    result = simulate(load_scenario(slope_dem(tmp_path)).with_updates({"time.end": 2.0}))
    assert not result.summary["runout_truncated"]


def test_plane_walls_are_geometry_not_a_truncation():
    """plane_box_2d's walls on its long sides touch the box from the start: they are the
    scene's channel, not the end of the data."""
    result = simulate(load_scenario(PLANE).with_updates({"time.end": 10.0}))
    assert not result.summary["runout_truncated"]


def test_a_release_drawn_up_to_the_dem_edge_has_not_travelled_there(tmp_path):
    """avaHit's release touches its DEM's NODATA edge: material spreading along the edge at
    the release's height has not reached the end of the map; a runout is not 'truncated'."""
    path = slope_dem(tmp_path)
    text = path.read_text().replace("x: [20.0, 60.0]", "x: [0.0, 40.0]")
    path.write_text(text)
    result = simulate(load_scenario(path).with_updates({"time.end": 2.0}))
    assert result.h0[result.terrain.cell_xy()[0] < 5.0].max() > 0.0  # released at the edge
    assert not result.summary["runout_truncated"]
