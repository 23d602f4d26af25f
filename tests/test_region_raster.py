"""avflow region with a release raster: each connected patch of cells above 0 one release,
run with its cells' thickness; equal to the same releases given as polygons, bit for bit.

The tiny region of tests/test_region.py (120 x 40 cells of 20 m, order 1 Coulomb).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import xarray as xr

from avflow.cli import main
from avflow.region import RegionError, load_region
from avflow.region.orchestrate import run_region
from test_region import BOXES, CRS, DX, NX, NY, REGION, X0, Y0, _dem, _releases

RASTER = REGION.replace("  path: {releases}\n  id_field: id\n", "  raster: {releases}\n")


def _raster(path, values, x0=X0, y0=Y0, dx=DX):
    import rasterio
    from rasterio.transform import from_origin

    ny, nx = values.shape
    with rasterio.open(path, "w", driver="GTiff", width=nx, height=ny, count=1,
                       dtype="float32", crs=CRS, transform=from_origin(x0, y0, dx, dx),
                       nodata=-9999.0) as dst:
        dst.write(values.astype(np.float32), 1)


def _cells(box, value=2.0):
    """The DEM cells whose centres lie in the box, at ``value`` (0 elsewhere)."""
    x = X0 + DX * (np.arange(NX) + 0.5)
    y = Y0 - DX * (np.arange(NY) + 0.5)
    inside = ((x[None, :] > box[0]) & (x[None, :] < box[2]) & (y[:, None] > box[1])
              & (y[:, None] < box[3]))
    return np.where(inside, value, 0.0)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("region-raster")
    _dem(folder)
    _releases(folder / "releases.gpkg", BOXES[:2])
    _raster(folder / "release.tif", _cells(BOXES[0]) + _cells(BOXES[1]))
    (folder / "poly.yaml").write_text(REGION.format(releases="releases.gpkg", buffer=40.0))
    (folder / "raster.yaml").write_text(RASTER.format(releases="release.tif", buffer=40.0))
    return folder


def test_raster_patches_equal_the_polygons(folder):
    poly = run_region(load_region(folder / "poly.yaml"), folder / "out-poly", workers=0,
                      quiet=True)
    rast = run_region(load_region(folder / "raster.yaml"), folder / "out-raster", workers=0,
                      quiet=True)
    a, b = poly.table.set_index("id"), rast.table.set_index("id")
    # patches numbered in scan order from the north-west: BOXES[1] is further north
    assert list(b.index) == [1, 2] and (b.status == "ok").all()
    for pid, rid in ((1, 2), (2, 1)):
        for column in ("volume", "runout", "retries", "area", "steps"):
            assert b.loc[rid, column] == a.loc[pid, column], column
        assert b.loc[rid, "thickness"] == 2.0
    ds_a = xr.open_zarr(poly.store).load()
    ds_b = xr.open_zarr(rast.store).load()
    for name in ("peak_pressure", "peak_thickness", "peak_speed", "release_count"):
        assert np.array_equal(ds_a[name].values, ds_b[name].values, equal_nan=True), name
    swap = np.array([0, 2, 1])  # the ids swapped
    np.testing.assert_array_equal(swap[ds_a.peak_pressure_release.values],
                                  ds_b.peak_pressure_release.values)


def test_raster_values_are_the_thickness_and_a_part_of_the_dem_will_do(folder):
    """A raster over part of the DEM (offset by whole cells), one patch of varying
    thickness: the run releases its values (volume: their mean times the uniform one's)."""
    values = _cells(BOXES[0], 1.0)
    ramp = values * (1.0 + 0.1 * np.arange(NX))[None, :]
    _raster(folder / "part.tif", ramp[5:30, 3:60], x0=X0 + 3 * DX, y0=Y0 - 5 * DX)
    _raster(folder / "one.tif", values[5:30, 3:60], x0=X0 + 3 * DX, y0=Y0 - 5 * DX)
    tables = {}
    for name in ("part", "one"):
        (folder / f"{name}.yaml").write_text(RASTER.format(releases=f"{name}.tif",
                                                           buffer=1.0e5))
        tables[name] = run_region(load_region(folder / f"{name}.yaml"), folder / f"out-{name}",
                                  workers=0, quiet=True).table
    ratio = tables["part"].volume.iloc[0] / tables["one"].volume.iloc[0]
    mean = ramp[ramp > 0].mean()
    assert tables["part"].thickness.iloc[0] == pytest.approx(mean, rel=1e-6)
    assert ratio == pytest.approx(mean, rel=2e-3)  # the trough's cross slope: 0.1 % a row
    # a uniform thickness given in the region file replaces the values: a mask then
    (folder / "mask.yaml").write_text(RASTER.format(releases="part.tif", buffer=1.0e5)
                                      .replace("  raster: part.tif\n",
                                               "  raster: part.tif\n  thickness: 1.0\n"))
    mask = run_region(load_region(folder / "mask.yaml"), folder / "out-mask", workers=0,
                      quiet=True).table
    assert mask.volume.iloc[0] == tables["one"].volume.iloc[0]


def test_connectivity(folder):
    """Two cells touching at a corner: one release with 8-connectivity, two with 4."""
    from avflow.region.windows import dem_info, read_releases

    values = np.zeros((NY, NX))
    values[10, 10] = values[11, 11] = 1.5
    _raster(folder / "diag.tif", values)
    counts = {}
    for conn in (8, 4):
        path = folder / f"diag{conn}.yaml"
        path.write_text(RASTER.format(releases="diag.tif", buffer=40).replace(
            "  raster: diag.tif\n", f"  raster: diag.tif\n  connectivity: {conn}\n"))
        region = load_region(path)
        rels = read_releases(region, dem_info(region.dem))
        counts[conn] = len(rels)
        assert all(r.area == pytest.approx(DX * DX * (2 if conn == 8 else 1)) for r in rels)
    assert counts == {8: 1, 4: 2}


@pytest.mark.parametrize("edit, field", [
    (("  raster: release.tif\n", "  raster: release.tif\n  path: releases.gpkg\n"),
     "releases.raster"),
    (("  raster: release.tif\n", "  raster: release.tif\n  thickness_field: d\n"),
     "releases.thickness_field"),
    (("  raster: release.tif\n", "  raster: release.tif\n  connectivity: 6\n"),
     "releases.connectivity"),
    (("  raster: release.tif\n", "  raster: half.tif\n"), "releases.raster"),
    (("  raster: release.tif\n", "  raster: nowhere.tif\n"), "releases.raster"),
    (("  raster: release.tif\n", "  path: releases.gpkg\n  connectivity: 4\n"),
     "releases.connectivity"),
])
def test_bad_release_raster_one_line_exit_2(folder, capsys, edit, field):
    _raster(folder / "half.tif", _cells(BOXES[0]), x0=X0 + DX / 2)  # not on the DEM's cells
    path = folder / "bad.yaml"
    path.write_text(RASTER.format(releases="release.tif", buffer=40).replace(*edit))
    with pytest.raises(RegionError):
        load_region(path)
    code = main(["region", str(path), "-o", str(folder / "out-bad")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith(f"avflow: error: {path}:") and f": {field}: " in err[0], err[0]
    assert not (folder / "out-bad").exists()


def test_empty_release_raster(folder, capsys):
    _raster(folder / "empty.tif", np.zeros((NY, NX)))
    (folder / "empty.yaml").write_text(RASTER.format(releases="empty.tif", buffer=40))
    code = main(["region", str(folder / "empty.yaml"), "-o", str(folder / "out-empty"),
                 "--workers", "0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "releases.raster: " in err[0]
    assert "holds no cell above 0" in err[0]
    assert math.isfinite(DX)


def test_raster_and_scenarios_on_two_dask_workers(folder):
    """Raster patches, return periods (one by the thickness rule) and a varied friction on
    a local cluster of 2 workers: the maps, counts and probabilities of the run here, bit
    for bit (tasks, patches and rules travel to the workers)."""
    text = RASTER.format(releases="release.tif", buffer=40.0) + """\
scenarios:
  return_periods:
    - {years: 30, thickness: 1.0}
    - {years: 300, thickness: {d0: 1.5, reference_elevation: 300.0}}
  vary: {rheology.delta_deg: [22.0, 26.0]}
"""
    (folder / "both.yaml").write_text(text)
    region = load_region(folder / "both.yaml")
    here = run_region(region, folder / "out-both-here", workers=0, quiet=True)
    dask = run_region(region, folder / "out-both-dask", workers=2, quiet=True)
    assert dask.where == "local cluster" and dask.workers == 2
    assert len(here.table) == 2 * 4 and (here.table.status == "ok").all()
    cols = ["id", "scenario", "thickness", "volume", "runout", "retries", "steps"]
    assert here.table[cols].equals(dask.table[cols])
    a = xr.open_zarr(here.store).load()
    b = xr.open_zarr(dask.store).load()
    assert "peak_pressure_exceedance_probability" in a and int(a.scenario_count.max()) == 8
    for name in a.data_vars:
        assert np.array_equal(a[name].values, b[name].values, equal_nan=True), name
