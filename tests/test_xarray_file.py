"""A run file that xarray users read without surprises (issue 12 item 3, issue 31): time in
seconds since the release with xarray's defaults too (the release instant settable, an
attribute), ``avflow.open_run`` equal to ``avflow.run``, the CRS found by rioxarray, no
``crs = 0`` in plot titles."""

from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import avflow
from avflow.output.netcdf import write_netcdf
from avflow.scenario.schema import parse_scenario
from avflow.terrain.raster import write_tif
from conftest import SCENARIOS
from test_cli_output import known_messages, strict_messages
from test_dem import lambert_wkt, tilted

PLANE = SCENARIOS / "plane_box_2d.yaml"


def dem_scenario(tmp_path: Path, extra: str = ""):
    """A 4 s run on the tilted DEM of test_dem, as a GeoTIFF in the avaKot Lambert CRS."""
    write_tif(tmp_path / "dem.tif", *tilted(), lambert_wkt())
    return parse_scenario(f"""
name: tilted
terrain: {{kind: dem, path: dem.tif}}
grid: {{dx: 5.0}}
release: {{kind: cylinder, center: [1050, 2070], radius: 20, thickness: 2}}
rheology: {{law: coulomb, delta_deg: 10.0}}
time: {{end: 4.0}}
output: {{every: 1.0{extra}}}
""", source_path=tmp_path / "s.yaml")


@pytest.fixture(scope="module")
def plane_run(tmp_path_factory):
    """plane_box_2d for 40 s with its release on 3 February 2024, 10:15 UTC (11:15 CET)."""
    sc = avflow.load_scenario(PLANE).with_updates(
        {"time.end": 40.0, "output.release_time": "2024-02-03T11:15:00+01:00"})
    ds = avflow.run(sc)
    path = write_netcdf(ds, tmp_path_factory.mktemp("plane") / "run.nc")
    return ds, path


def test_time_is_seconds_since_the_release_and_the_release_is_its_reference(plane_run):
    ds, path = plane_run
    # in memory, through open_run and with xarray's defaults: seconds since the release,
    # selectable as numbers (issue 31: xarray decoded "seconds since" units to 1970 dates)
    with xr.open_dataset(path) as plain:
        plain.load()
    for d in (ds, avflow.open_run(path), plain):
        assert d["time"].dtype == np.float64 and float(d["time"][0]) == 0.0
        assert d["time"].attrs["units"] == "s"
        assert d["time"].attrs["release_time"] == "2024-02-03T10:15:00Z"
        assert float(d["h"].sel(time=40, method="nearest")["time"]) == 40.0
        assert float(d["h"].sel(time=23.0, method="nearest")["time"]) == 25.0
        assert d.attrs["release_time"] == "2024-02-03T10:15:00Z"
        # the run maxima cover the scalar coordinate `duration`: the whole run
        assert float(d["duration"]) == 40.0
        np.testing.assert_array_equal(d["duration_bounds"].values, [0.0, 40.0])
    np.testing.assert_array_equal(plain["time"].values, ds["time"].values)


def test_the_epoch_stays_the_default_release_time(tmp_path):
    ds = avflow.run(avflow.load_scenario(PLANE).with_updates({"time.end": 5.0}))
    assert ds["time"].attrs["units"] == "s"
    assert ds["time"].attrs["release_time"] == "1970-01-01T00:00:00Z"
    assert ds.attrs["release_time"] == "1970-01-01T00:00:00Z"


def test_release_time_must_be_iso_8601():
    with pytest.raises(avflow.ScenarioError, match="ISO 8601") as err:
        avflow.load_scenario(PLANE).with_updates({"output.release_time": "yesterday noon"})
    assert err.value.field == "output.release_time"


def test_open_run_returns_what_run_returned(plane_run):
    ds, path = plane_run
    back = avflow.open_run(path)
    assert set(back.variables) == set(ds.variables)
    assert set(back.coords) == set(ds.coords)
    assert back.attrs.keys() == ds.attrs.keys()
    for name, var in ds.variables.items():
        assert back[name].dims == var.dims and back[name].dtype == var.dtype, name
        assert back[name].attrs.keys() == var.attrs.keys(), name
    xr.testing.assert_allclose(back, ds, rtol=1e-6, atol=1e-6)  # fields stored as float32
    np.testing.assert_array_equal(back["flow_state"].values, ds["flow_state"].values)


def test_only_the_run_period_is_a_scalar_coordinate(plane_run):
    """The run maxima name the scalar coordinate ``duration`` (bounds: the whole run) in
    their cell_methods; it is the only 0-d coordinate, so titles say when, not ``crs = 0``."""
    _, path = plane_run
    with xr.open_dataset(path) as plain:
        assert [n for n, c in plain.coords.items() if c.ndim == 0] == ["duration"]
        assert plain["h"].isel(time=2)._title_for_slice() == "time = 10.0 [s], duration = 40.0 [s]"
        assert plain["peak_thickness"]._title_for_slice() == "duration = 40.0 [s]"
        assert plain["peak_thickness"].attrs["cell_methods"] == "duration: maximum"
        assert plain["deposit_thickness"].attrs["cell_methods"] == "duration: point"
        assert plain["peak_thickness"].encoding["coordinates"] == "duration"
        assert "coordinates" not in plain["h"].encoding


def test_rioxarray_finds_the_crs_and_titles_show_no_crs(tmp_path):
    """``crs`` is the CF grid-mapping variable named by the maps' ``grid_mapping``, not a
    coordinate: xarray put a 0-d coordinate in every plot title (``crs = 0``, issue 31).
    rioxarray finds it as it documents, with ``decode_coords="all"``."""
    import rioxarray  # noqa: F401  (registers .rio)
    from pyproj import CRS

    expected = CRS.from_wkt(lambert_wkt())
    ds = avflow.run(dem_scenario(tmp_path))
    path = write_netcdf(ds, tmp_path / "run.nc")
    with xr.open_dataset(path) as plain:
        for d in (ds, plain, avflow.open_run(path)):
            assert "crs" in d.data_vars and "crs" not in d.coords
            assert "crs" not in d["peak_thickness"]._title_for_slice()
            assert "crs" not in d["h"].isel(time=1)._title_for_slice()
            for name in ("peak_thickness", "h", "bed_elevation"):
                assert d[name].attrs["grid_mapping"] == "crs"
        assert "coordinates" not in plain["moving_volume"].encoding
        assert "coordinates" not in plain["runout"].encoding
        assert {"crs_wkt", "spatial_ref"} <= set(plain["crs"].attrs)
    with xr.open_dataset(path, decode_coords="all") as d:
        assert CRS.from_user_input(d.rio.crs).equals(expected, ignore_axis_order=True)
        for name in ("peak_thickness", "h", "bed_elevation"):
            assert CRS.from_user_input(d[name].rio.crs).equals(expected, ignore_axis_order=True)
    assert strict_messages(path) == sorted(known_messages("grid"))
