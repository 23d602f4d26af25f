"""Hazard zoning: the intensity-frequency rule cell by cell, the paletted GeoTIFF and its
legend from runs of given return periods and from a region with return periods, bad input
in one line."""

from __future__ import annotations

import numpy as np
import pytest

from avflow.cli import main
from avflow.output.zoning import BLUE, NONE, RED, YELLOW, ZoningRule, zone_map
from conftest import SCENARIOS
from test_region_scenarios import _on_dem, folder as region_folder  # noqa: F401 (a fixture)


@pytest.mark.parametrize("years, p, want", [
    (10, 0.5, RED), (30, 0.5, RED),  # frequent: any flow is red
    (100, 50.0, RED), (300, 30.0, RED),  # strong up to 300 years
    (100, 29.9, BLUE), (300, 3.0, BLUE),  # medium
    (100, 2.9, YELLOW), (31, 0.01, YELLOW),  # weak
    (1000, 500.0, YELLOW),  # rare: yellow whatever the pressure
])
def test_rule_cell_by_cell(years, p, want):
    z = ZoningRule().zone(np.array([p, p]), np.array([True, False]), years)
    assert list(z) == [want, NONE]


def test_the_most_severe_zone_wins():
    p100 = np.array([40.0, 10.0, 1.0, np.nan])
    p300 = np.array([60.0, 35.0, 2.0, 1.0])
    reached100 = np.isfinite(p100)
    z = zone_map([(100, p100, reached100), (300, p300, np.ones(4, bool))])
    assert list(z) == [RED, RED, YELLOW, YELLOW]
    # the limits are parameters
    z = zone_map([(100, p100, reached100)], ZoningRule(red_kpa=50.0, yellow_kpa=0.5))
    assert list(z) == [BLUE, BLUE, BLUE, NONE]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("zoning")
    paths = {}
    for years, delta in ((30, 27.0), (100, 24.0), (300, 22.0)):
        out = folder / f"run{years}.nc"
        assert main(["run", "-q", str(SCENARIOS / "plane_box_runout_2d.yaml"), "--set",
                     f"rheology.delta_deg={delta}", "--set", "physics.density=300",
                     "-o", str(out)]) == 0
        paths[years] = out
    return folder, paths


def test_zoning_of_runs_is_a_paletted_geotiff_with_a_legend(runs, capsys):
    import rasterio
    import xarray as xr

    folder, paths = runs
    out = folder / "zones.tif"
    assert main(["zoning", *(f"{t}={p}" for t, p in paths.items()), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "zones: red" in printed and "zones_legend.png" in printed
    with rasterio.open(out) as src:
        got = src.read(1)
        assert src.dtypes[0] == "uint8" and src.nodata == 255
        assert src.colormap(1)[RED][:3] == (230, 0, 0)
        assert src.colormap(1)[BLUE][:3] == (0, 112, 255)
        assert src.descriptions[0] == "hazard zone"
        assert "BFF/SLF (1984)" in src.tags(1)["reference"]
    # by hand from the run files (north first in the GeoTIFF)
    want = np.zeros(got.shape, np.uint8)
    for years, path in paths.items():
        with xr.open_dataset(path, decode_times=False) as ds:
            p = ds.peak_pressure.values / 1000.0
            reached = np.nan_to_num(ds.peak_thickness.values) > ds.attrs["runout_threshold_m"]
        if years <= 30:
            z = np.where(reached, RED, NONE)
        else:
            z = np.where(~reached, NONE, np.where(p >= 30, RED, np.where(p >= 3, BLUE, YELLOW)))
        want = np.maximum(want, z[::-1])
    np.testing.assert_array_equal(got, want)
    assert {RED, BLUE, YELLOW} <= set(np.unique(got))  # the three zones on this slope
    legend = folder / "zones_legend.png"
    assert legend.read_bytes()[:4] == b"\x89PNG" and legend.stat().st_size < 200_000


@pytest.mark.parametrize("args, words", [
    (["abc={run}"], "positive number of years"),
    (["100=nope.nc"], "file not found"),
    (["100={run}", "{folder}"], "either YEARS=RUN.nc pairs or one region folder"),
    (["{folder}"], "not a region's output folder"),
    (["100={run}", "--red-kpa", "2"], "--yellow-kpa must be below --red-kpa"),
])
def test_bad_input_is_one_line_exit_2(runs, args, words, capsys):
    folder, paths = runs
    args = [a.format(run=paths[30], folder=folder) for a in args]
    assert main(["zoning", *args, "-o", str(folder / "bad.tif")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err
    assert not (folder / "bad.tif").exists()


def test_runs_on_different_grids_are_refused(runs, tmp_path, capsys):
    folder, paths = runs
    other = tmp_path / "coarse.nc"
    assert main(["run", "-q", str(SCENARIOS / "plane_box_runout_2d.yaml"), "--set",
                 "grid.dx=20", "-o", str(other)]) == 0
    assert main(["zoning", f"100={paths[100]}", f"300={other}", "-o",
                 str(tmp_path / "z.tif")]) == 2
    assert "not the grid of" in capsys.readouterr().err


def test_zoning_of_a_region_with_return_periods(region_folder, capsys):
    import rasterio
    import xarray as xr

    from avflow.region import load_region
    from avflow.region.orchestrate import run_region
    from avflow.region.run import read_result, result_path

    folder = region_folder
    outcome = run_region(load_region(folder / "sc.yaml"), folder / "out-sc", workers=0,
                         quiet=True)
    assert main(["zoning", str(folder / "out-sc")]) == 0
    capsys.readouterr()
    with rasterio.open(folder / "out-sc" / "zoning.tif") as src:
        got = src.read(1)
    ds = xr.open_zarr(outcome.store)
    shape = (ds.sizes["y"], ds.sizes["x"])
    want = np.zeros(shape, np.uint8)
    rule = ZoningRule()
    for _, row in outcome.table.iterrows():
        info, maps, _ = read_result(result_path(folder / "out-sc", row.id, row.scenario))
        reached = _on_dem(maps["peak_thickness"], info, shape) > info["reach_threshold"]
        p = _on_dem(maps["peak_pressure"], info, shape) / 1000.0
        want = np.maximum(want, rule.zone(p, reached, float(row.return_period)))
    north_first = ds.y.values[0] > ds.y.values[-1]
    np.testing.assert_array_equal(got, want if north_first else want[::-1])
    assert (got == RED).any()
