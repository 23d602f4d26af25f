"""Points of interest (output.points): the time series against the stored snapshots and the
arrival-time map, CF compliance of the timeSeries, the CSV and figure beside the run, and
bad points refused in one line."""

import csv

import numpy as np
import pytest
import xarray as xr

from avflow.cli import main
from avflow.output.points import points_dataset, points_encoding
from avflow.scenario.schema import load_scenario
from avflow.simulation.runner import simulate
from conftest import SCENARIOS

# a block sliding and stopping on a 20 degree plane; outputs every 10 s (too sparse to see a
# front pass), the points sampled every second
POINTS = {"at": [{"name": "barn", "x": 400.0, "y": 400.0},
                 {"name": "road", "x": 455.0, "y": 395.0},
                 {"name": "far", "x": 1900.0, "y": 400.0}]}


def _scenario(points=POINTS, **more):
    base = load_scenario(SCENARIOS / "plane_box_runout_2d.yaml")
    return base.with_updates({"output.points": points, **more})


@pytest.fixture(scope="module")
def run():
    return simulate(_scenario())


def test_series_match_the_snapshots_at_output_times(run):
    series = run.points.arrays()
    t = series["time"]
    assert np.all(np.diff(t) > 0)
    assert np.max(np.diff(t)) <= 1.0 + 1e-9  # sampled every second, not every 10 s
    cells = run.points.cells
    for k, ts in enumerate(run.snapshots.time):
        j = np.flatnonzero(np.abs(t - ts) <= 1e-9 * max(ts, 1.0))
        assert j.size == 1, f"output time {ts} not sampled"
        assert np.array_equal(series["thickness"][:, j[0]], run.snapshots.h[k][cells])
        h, hu, hv = (getattr(run.snapshots, n)[k][cells] for n in ("h", "hu", "hv"))
        with np.errstate(invalid="ignore", divide="ignore"):
            u = np.where(h > 0, np.hypot(hu, hv) / h, 0.0)
        np.testing.assert_allclose(series["speed"][:, j[0]], u, rtol=1e-15)
    rho = run.scenario.physics.density
    np.testing.assert_allclose(series["pressure"], rho * series["speed"] ** 2 / 1000.0)


def test_arrival_agrees_with_the_arrival_map(run):
    ds = points_dataset(run)
    every = 1.0
    arrival_map = run.state.arrival[run.points.cells]
    reached = np.isfinite(arrival_map)
    assert list(reached) == [True, True, False]  # the far point: never reached
    got = ds["arrival_time"].values
    assert np.isnan(got[2])
    # the map holds the step the thickness first passed the dry threshold; the series the
    # first sample after it
    assert np.all(arrival_map[:2] <= got[:2] + 1e-9)
    assert np.all(got[:2] < arrival_map[:2] + every + 1e-9)
    assert got[1] > got[0]  # the road lies downslope of the barn
    assert np.all(ds["peak_thickness"].values[:2] > 0.1)


def test_points_are_a_cf_timeseries(run, tmp_path):
    from test_cli_output import compliance_errors

    ds = points_dataset(run)
    assert ds.attrs["featureType"] == "timeSeries"
    assert ds["station_name"].attrs["cf_role"] == "timeseries_id"
    assert list(ds["station_name"].values) == ["barn", "road", "far"]
    assert ds["thickness"].dims == ("station", "time")
    path = tmp_path / "points.nc"
    ds.to_netcdf(path, encoding=points_encoding(ds))
    assert compliance_errors(path) == []


def test_cli_writes_group_csv_and_figure(tmp_path, capsys):
    scenario = tmp_path / "s.yaml"
    text = (SCENARIOS / "plane_box_runout_2d.yaml").read_text().replace(
        "output: {every: 10.0}",
        "output:\n  every: 10.0\n  points:\n    at: [{name: barn, x: 400, y: 400}]\n")
    scenario.write_text(text)
    out = tmp_path / "run.nc"
    assert main(["run", str(scenario), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "points: barn at" in printed
    group = xr.open_dataset(out, group="points", decode_times=False)
    main_file = xr.open_dataset(out, decode_times=False)
    assert "h" in main_file and "thickness" in group
    with open(tmp_path / "run_points.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == group.sizes["time"]
    assert [float(r["thickness_m"]) for r in rows] == pytest.approx(
        group["thickness"].values[0], rel=1e-5)
    png = tmp_path / "run_points.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size < 200_000
    from test_cli_output import compliance_errors

    assert compliance_errors(out) == []  # the run file with its group still passes


def test_point_outside_the_domain_is_one_line_exit_2(tmp_path, capsys):
    scenario = tmp_path / "s.yaml"
    text = (SCENARIOS / "plane_box_runout_2d.yaml").read_text().replace(
        "output: {every: 10.0}",
        "output:\n  every: 10.0\n  points:\n    at: [{name: hut, x: 2500, y: 400}]\n")
    scenario.write_text(text)
    out = tmp_path / "run.nc"
    assert main(["run", str(scenario), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "s.yaml" in err[0] and "output.points" in err[0] and "'hut'" in err[0]
    assert "outside the domain" in err[0]
    assert list(tmp_path.iterdir()) == [scenario]  # nothing written


def _write_points(path, xy, crs=None, names=("a", "b")):
    import pyogrio
    import shapely

    geoms = shapely.to_wkb(shapely.points(np.asarray(xy, dtype=float)))
    pyogrio.raw.write(path, geoms, [np.array(names, dtype=object)], ["name"],
                      geometry_type="Point", crs=crs, driver="GPKG")


def test_point_layer_read_and_reprojected(tmp_path):
    from avflow.simulation.events import read_points

    layer = tmp_path / "pois.gpkg"
    _write_points(layer, [[400.0, 400.0], [455.0, 395.0]])
    scenario = _scenario({"file": str(layer)})
    names, x, y = read_points(scenario.output.points, None, scenario)
    assert names == ["a", "b"] and list(x) == [400.0, 455.0] and list(y) == [400.0, 395.0]
    run = simulate(scenario.with_updates({"time.end": 20.0}))
    assert run.points.arrays()["thickness"].shape[0] == 2
    # a layer in geographic coordinates, a terrain in the Swiss grid: reprojected
    wgs = tmp_path / "wgs.gpkg"
    _write_points(wgs, [[7.4474, 46.9480]], crs="EPSG:4326", names=("bern",))
    from rasterio.crs import CRS

    lv95 = CRS.from_epsg(2056).to_wkt()
    names, x, y = read_points(_scenario({"file": str(wgs)}).output.points, lv95,
                              _scenario({"file": str(wgs)}))
    assert names == ["bern"]
    assert x[0] == pytest.approx(2600670, abs=200) and y[0] == pytest.approx(1199655, abs=200)


def test_point_layer_with_a_crs_on_a_terrain_without_one_is_refused(tmp_path):
    from avflow.errors import ScenarioError
    from avflow.simulation.events import read_points

    layer = tmp_path / "pois.gpkg"
    _write_points(layer, [[400.0, 400.0], [455.0, 395.0]], crs="EPSG:2056")
    scenario = _scenario({"file": str(layer)})
    with pytest.raises(ScenarioError, match="output.points.file.*carries a CRS"):
        read_points(scenario.output.points, None, scenario)


def test_points_on_a_profile_are_refused():
    from avflow.errors import ScenarioError

    base = load_scenario(SCENARIOS / "seed_exponential_coulomb15.yaml")
    with pytest.raises(ScenarioError, match="output.points"):
        base.with_updates({"output.points": POINTS})


def test_points_on_a_triangle_mesh_take_their_vertex():
    base = load_scenario(SCENARIOS / "plane_cylinder_triangles.yaml")
    cx, cy = base.release.center
    run = simulate(base.with_updates({"time.end": 6.0, "output.points": {"at": [
        {"name": "centre", "x": cx, "y": cy}, {"name": "below", "x": cx + 120.0, "y": cy}]}}))
    x, y = run.terrain.cell_xy()
    cells = run.points.cells
    assert np.hypot(x[cells] - [cx, cx + 120.0], y[cells] - cy).max() <= 10.0
    series = run.points.arrays()
    for k, ts in enumerate(run.snapshots.time):
        j = np.flatnonzero(np.abs(series["time"] - ts) <= 1e-9 * max(ts, 1.0))[0]
        assert np.array_equal(series["thickness"][:, j], run.snapshots.h[k][cells])
    assert series["thickness"][0, 0] == 10.0 and series["thickness"][1, 0] == 0.0
