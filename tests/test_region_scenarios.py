"""avflow region with scenarios: every release run once per scenario (return periods with
their release thickness, vary and sample as in ensembles), exceedance counts and
probabilities merged release by release; the thickness rule; bad scenario blocks.

The tiny region of tests/test_region.py (120 x 40 cells of 20 m, order 1 Coulomb).
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from avflow.cli import main
from avflow.region import RegionError, load_region
from avflow.region.orchestrate import run_region
from test_region import BOXES, CRS, DX, REGION, X0, Y0, _dem

SCENARIOS = """\
scenarios:
  return_periods:
    - {years: 30, thickness: 1.0}
    - {years: 100, thickness: d100}
  vary: {rheology.delta_deg: [22.0, 26.0]}
"""
#: One scenario's thickness from the Swiss rule instead of an attribute.
RULE = SCENARIOS.replace("{years: 100, thickness: d100}",
                         "{years: 300, thickness: {d0: 1.5, reference_elevation: 300.0}}")


def _region_text(buffer=1.0e5, scenarios=SCENARIOS, **edits) -> str:
    text = REGION.format(releases="releases.gpkg", buffer=buffer) + scenarios
    for old, new in edits.values():
        text = text.replace(old, new)
    return text


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    import pyogrio.raw
    import shapely

    folder = tmp_path_factory.mktemp("region-scenarios")
    _dem(folder)
    geoms = [shapely.box(*b) for b in BOXES[:2]]
    # a d100 attribute per polygon (m), beside the thickness the base region reads
    pyogrio.raw.write(str(folder / "releases.gpkg"),
                      np.array([shapely.to_wkb(g) for g in geoms], dtype=object),
                      [np.array([1, 2], dtype=np.int32), np.array([2.0, 2.0]),
                       np.array([1.5, 2.5])], ["id", "thickness", "d100"], driver="GPKG",
                      crs=CRS, geometry_type="Polygon")
    (folder / "sc.yaml").write_text(_region_text().replace("  id_field: id\n",
                                                           "  id_field: id\n"))
    return folder


@pytest.fixture(scope="module")
def scenario_run(folder):
    return run_region(load_region(folder / "sc.yaml"), folder / "out-sc", workers=0,
                      quiet=True)


def _on_dem(values, row, shape):
    out = np.full(shape, np.nan)
    out[int(row["row0"]):int(row["row1"]), int(row["col0"]):int(row["col1"])] = values
    return out


def test_exceedance_counts_and_probabilities(folder, scenario_run):
    """Counted again here, from the per-run result files, by hand: per pixel, the runs
    whose peak exceeds each threshold where they reached; the scenarios of the releases
    reaching; the largest per-release fraction."""
    from avflow.region.run import read_result, result_path

    table = scenario_run.table
    assert len(table) == 2 * 4 and (table.status == "ok").all()
    assert list(table.scenario) == [0, 1, 2, 3] * 2
    assert list(table.return_period) == [30, 30, 100, 100] * 2
    # release thickness: 1 m at 30 years; the d100 attribute at 100 years
    assert list(table.thickness) == [1.0, 1.0, 1.5, 1.5, 1.0, 1.0, 2.5, 2.5]
    scen = pd.read_csv(folder / "out-sc" / "scenarios.csv")
    assert list(scen.columns[:3]) == ["scenario", "return_period", "thickness"]
    assert list(scen["rheology.delta_deg"]) == [22.0, 26.0, 22.0, 26.0]
    ds = xr.open_zarr(scenario_run.store).load()
    region = load_region(folder / "sc.yaml")
    assert ds.attrs["scenarios"] == 4
    shape = ds.release_count.shape
    thresholds = region.thresholds
    assert thresholds["peak_pressure"] == (1.0, 3.0, 30.0)  # the ensembles' defaults
    counts = {n: np.zeros((len(t), *shape), int) for n, t in thresholds.items()}
    scenario_count = np.zeros(shape, int)
    fraction = {n: np.full((len(t), *shape), np.nan) for n, t in thresholds.items()}
    for rid in (1, 2):
        rows = table[table.id == rid]
        mine = {n: np.zeros((len(t), *shape), int) for n, t in thresholds.items()}
        any_reached = np.zeros(shape, bool)
        for _, row in rows.iterrows():
            got, maps, _ = read_result(result_path(folder / "out-sc", rid, row.scenario))
            reached = _on_dem(maps["peak_thickness"], got, shape) > got["reach_threshold"]
            any_reached |= reached
            for name, ts in thresholds.items():
                peak = _on_dem(maps[name], got, shape)
                unit = 1000.0 if name == "peak_pressure" else 1.0
                for k, t in enumerate(ts):
                    mine[name][k] += reached & (np.nan_to_num(peak, nan=-1) > t * unit)
        scenario_count += 4 * any_reached
        for name in thresholds:
            counts[name] += mine[name]
            f = np.where(any_reached, mine[name] / 4.0, np.nan)
            fraction[name] = np.fmax(fraction[name], f)
    np.testing.assert_array_equal(ds.scenario_count.values, scenario_count)
    for name in thresholds:
        np.testing.assert_array_equal(ds[f"{name}_exceedance_count"].values, counts[name])
        np.testing.assert_array_equal(ds[f"{name}_exceedance_probability"].values,
                                      fraction[name].astype(np.float32))
    p = ds.peak_pressure_exceedance_probability
    assert p.dims == ("pressure_threshold", "y", "x")
    assert set(np.unique(p.values[np.isfinite(p.values)])) <= {0.0, 0.25, 0.5, 0.75, 1.0}
    assert 0.0 < float(p.sel(pressure_threshold=30.0).mean()) < 1.0
    # the envelope is the maximum over the releases and their scenarios
    assert float(ds.peak_pressure.max()) == pytest.approx(
        max(float(np.nanmax(read_result(result_path(folder / "out-sc", r, s))[1]
                            ["peak_pressure"])) for r in (1, 2) for s in range(4)))


def test_merge_is_order_independent(tmp_path):
    """Releases merged in any order give the same store, bit for bit (ties included)."""
    from avflow.region.merge import RegionStore
    from avflow.region.windows import DemInfo

    dem = DemInfo("none.tif", 50, 40, 0.0, 400.0, 10.0, 10.0, None, "float32")
    rng = np.random.default_rng(3)
    releases = []
    for rid in range(1, 7):
        parts = []
        for _ in range(3):
            r0, c0 = rng.integers(0, 20), rng.integers(0, 30)
            w = (r0, r0 + 20, c0, c0 + 20)
            h = np.round(rng.random((20, 20)), 1).astype(np.float32)  # ties on purpose
            parts.append((w, {"peak_thickness": h, "peak_speed": 3 * h,
                              "peak_pressure": (h * 2000).astype(np.float32)}, 0.05))
        releases.append((rid, parts))
    thresholds = {"peak_pressure": (0.2, 1.0), "peak_thickness": (0.5,)}
    stores = []
    for k, order in enumerate((releases, releases[::-1], [releases[i] for i in
                                                          (3, 0, 5, 1, 4, 2)])):
        store = RegionStore(tmp_path / f"{k}.zarr", dem, ("pressure", "thickness", "speed"),
                            16, thresholds=thresholds, scenarios=3)
        for rid, parts in order:
            store.add(rid, parts)
        stores.append(xr.open_zarr(tmp_path / f"{k}.zarr").load())
    for ds in stores[1:]:
        for name in stores[0].data_vars:
            assert np.array_equal(ds[name].values, stores[0][name].values,
                                  equal_nan=True), name
    assert int(stores[0].scenario_count.max()) >= 6


def test_resume_with_scenarios(folder, scenario_run):
    again = run_region(load_region(folder / "sc.yaml"), folder / "out-sc", workers=0,
                       quiet=True)
    assert again.reused == 8 and again.ran == 0
    a = xr.open_zarr(scenario_run.store).load()  # the same path: read the new store
    assert set(f.name for f in (folder / "out-sc" / "releases").iterdir()) == {
        f"{r}-{s}.nc" for r in (1, 2) for s in range(4)}
    assert int(a.scenario_count.max()) == 8


def test_thickness_rule(folder):
    """The Swiss rule on the 30-degree slope: (d0 + 0.05 (z - z_ref) / 100) f(30 deg), z
    the mean DEM elevation of the released cells, f = 0.291 / (sin - 0.202 cos)."""
    from avflow.region.spec import ThicknessRule
    from avflow.region.windows import dem_info, read_window, rule_thickness

    import shapely

    dem = dem_info(str(folder / "dem.tif"))
    box = BOXES[0]
    d, z, psi = rule_thickness(dem, shapely.to_wkb(shapely.box(*box)),
                               ThicknessRule(d0=1.5, reference_elevation=300.0))
    # the box's cell centres: columns 10..14, rows 15..19 (5 x 5 of 20 m)
    zz = read_window(dem, (15, 20, 10, 15))
    assert z == pytest.approx(zz.mean(), rel=1e-12)
    assert psi == pytest.approx(30.0, abs=0.2)  # the trough's cross slope adds a little
    f = 0.291 / (math.sin(math.radians(psi)) - 0.202 * math.cos(math.radians(psi)))
    assert d == pytest.approx((1.5 + 0.05 * (z - 300.0) / 100.0) * f, rel=1e-12)
    flat = rule_thickness(dem, shapely.to_wkb(shapely.box(*box)),
                          ThicknessRule(d0=1.5, reference_elevation=300.0,
                                        slope_correction=False))[0]
    assert flat == pytest.approx(1.5 + 0.05 * (z - 300.0) / 100.0, rel=1e-12)
    # in a region: the row says the thickness it computed, and the run released it
    (folder / "rule.yaml").write_text(_region_text(scenarios=RULE))
    out = run_region(load_region(folder / "rule.yaml"), folder / "out-rule", workers=0,
                     quiet=True)
    rows = out.table[(out.table.id == 1) & (out.table.return_period == 300)]
    assert len(rows) == 2 and (rows.status == "ok").all()
    assert rows.thickness.iloc[0] == pytest.approx(d, rel=1e-12)
    ref = out.table[(out.table.id == 1) & (out.table.return_period == 30)]  # 1 m
    assert rows.volume.iloc[0] / ref.volume.iloc[0] == pytest.approx(d, rel=1e-9)


@pytest.mark.parametrize("edit, field", [
    (("rheology.delta_deg: [22.0, 26.0]", "release.thickness: [1.0, 2.0]"),
     "scenarios.vary.release.thickness"),
    (("vary: {rheology.delta_deg: [22.0, 26.0]}",
      "sample: {n: 4, ranges: {rheology.delta_deg: [26.0, 22.0]}}"),
     "scenarios.sample.ranges.rheology.delta_deg"),
    (("rheology.delta_deg: [22.0, 26.0]", "rheology.delta_deg: [22.0, 95.0]"),
     "scenarios.vary.rheology.delta_deg.1"),
    (("rheology.delta_deg: [22.0, 26.0]", "rheology.delta_dg: [22.0, 26.0]"),
     "scenarios.vary.rheology.delta_dg"),
    (("{years: 30, thickness: 1.0}", "{years: 30, thickness: -1.0}"),
     "scenarios.return_periods.0.thickness"),
    (("{years: 30, thickness: 1.0}", "{years: 100, thickness: 1.0}"),
     "scenarios.return_periods.1.years"),
    (("{years: 30, thickness: 1.0}", "{years: 30, thickness: {d0: 1.0, gradiant: 0.1}}"),
     "scenarios.return_periods.0.thickness.gradiant"),
    (("  id_field: id\n", "  id_field: id\n  thickness: 2.0\n"), "releases.thickness"),
    (("chunk: 16", "chunk: 16\n  thresholds: {peak_presure: [1.0]}"),
     "merge.thresholds.peak_presure"),
    (("chunk: 16", "chunk: 16\n  thresholds: [1.0, -2.0]"), "merge.thresholds.1"),
    (("scenarios:", "scenarioz:"), "scenarioz"),
])
def test_bad_scenarios_one_line_exit_2(folder, capsys, edit, field):
    path = folder / "bad.yaml"
    text = _region_text()
    assert edit[0] in text
    path.write_text(text.replace(*edit, 1))
    with pytest.raises(RegionError):
        load_region(path)
    code = main(["region", str(path), "-o", str(folder / "out-bad")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith(f"avflow: error: {path}:"), err
    assert f": {field}: " in err[0], err[0]
    assert not (folder / "out-bad").exists()


def test_missing_thickness_attribute_names_the_field(folder, capsys):
    path = folder / "noattr.yaml"
    path.write_text(_region_text().replace("thickness: d100", "thickness: d300"))
    code = main(["region", str(path), "-o", str(folder / "out-noattr"), "--workers", "0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "scenarios.return_periods: " in err[0] and "no attribute 'd300'" in err[0]
    assert "300 years" not in err[0] and "100 years" in err[0]


def test_thresholds_without_scenarios(folder):
    """merge.thresholds alone: the one scenario's exceedance (0 or 1 per release)."""
    (folder / "thr.yaml").write_text(
        REGION.format(releases="releases.gpkg", buffer=1.0e5).replace(
            "chunk: 16", "chunk: 16\n  thresholds: {peak_pressure: [3.0]}"))
    out = run_region(load_region(folder / "thr.yaml"), folder / "out-thr", workers=0,
                     quiet=True)
    ds = xr.open_zarr(out.store).load()
    assert "peak_thickness_exceedance_probability" not in ds
    p = ds.peak_pressure_exceedance_probability.sel(pressure_threshold=3.0).values
    pressure = ds.peak_pressure.values
    np.testing.assert_array_equal(np.isfinite(p), np.isfinite(pressure))
    np.testing.assert_array_equal(p[np.isfinite(p)] == 1.0, pressure[np.isfinite(p)] > 3000.0)
    np.testing.assert_array_equal(ds.scenario_count.values, ds.release_count.values)
    assert sorted(p.name for p in (folder / "out-thr" / "releases").iterdir()) == \
        ["1.nc", "2.nc"]
    assert not (folder / "out-thr" / "scenarios.csv").exists()
    assert {X0, Y0, DX}  # the module's geometry, shared with test_region
