"""The regional maps out of the Zarr store: Cloud-Optimized GeoTIFFs through
``avflow export`` (layout COG, tiles, overviews, CRS, NODATA, the store's values), and
releases.parquet beside releases.csv where pandas has a parquet engine."""

from __future__ import annotations

import importlib.util

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from avflow.cli import main

CRS = "EPSG:2056"


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A store of 1,100 x 1,300 cells (10 m, chunks of 256) filled with six made-up
    releases of three scenarios: large enough for overviews and several strips."""
    from pyproj import CRS as ProjCRS

    from avflow.region.merge import RegionStore
    from avflow.region.windows import DemInfo

    folder = tmp_path_factory.mktemp("region-export") / "out"
    folder.mkdir()
    dem = DemInfo("none.tif", 1300, 1100, 2_600_000.0, 1_200_000.0, 10.0, 10.0,
                  ProjCRS.from_user_input(CRS).to_wkt(), "float32")
    path = folder / "region.zarr"
    s = RegionStore(path, dem, ("pressure", "thickness", "speed"), 256,
                    {"title": "avflow region test", "source": "avflow region"},
                    thresholds={"peak_pressure": (1.0, 30.0)}, scenarios=3)
    rng = np.random.default_rng(7)
    for rid in range(1, 7):
        parts = []
        for _ in range(3):
            r0, c0 = int(rng.integers(0, 700)), int(rng.integers(0, 900))
            h = rng.random((400, 400)).astype(np.float32) * 3
            parts.append(((r0, r0 + 400, c0, c0 + 400),
                          {"peak_thickness": h, "peak_speed": 5 * h,
                           "peak_pressure": (h * 20000).astype(np.float32)}, 0.5))
        s.add(rid, parts)
    import zarr

    zarr.consolidate_metadata(str(path))
    return path


def test_cog_export_of_the_region_store(store, capsys):
    import rasterio

    out = store.parent / "cog"
    code = main(["export", str(store.parent), "-o", str(out)])  # the region's OUTDIR
    assert code == 0
    written = capsys.readouterr().out.split()
    ds = xr.open_zarr(store).load()
    names = {p.name for p in out.iterdir()}
    assert names == {f"region_{n}.tif" for n, v in ds.data_vars.items() if v.ndim == 2} | {
        f"region_peak_pressure_exceedance_probability_{t}kPa.tif" for t in ("1", "30")}
    assert len([w for w in written if w.endswith(".tif")]) == len(names)
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporaries
    for name in names:
        with rasterio.open(out / name) as src:
            assert src.driver == "GTiff"
            assert src.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG", name
            assert src.is_tiled and src.block_shapes[0] == (512, 512)
            assert src.overviews(1) == [2, 4], name  # 1,300 x 1,100 cells: two levels
            assert src.crs.to_epsg() == 2056
            assert src.transform.c == 2_600_000.0 and src.transform.f == 1_200_000.0
            assert src.res == (10.0, 10.0)
            assert src.tags(1)["overview_resampling"] in ("max", "nearest")
            values = src.read(1)
            profile = src.profile
        var = name.removeprefix("region_").removesuffix(".tif")
        if var.startswith("peak_pressure_exceedance_probability_"):
            t = float(var.rsplit("_", 1)[1].removesuffix("kPa"))
            ref = ds.peak_pressure_exceedance_probability.sel(pressure_threshold=t).values
        else:
            ref = ds[var].values
        if var == "peak_pressure":
            ref = ref * np.float32(1e-3)  # kPa, as every avflow export
        if ref.dtype.kind == "f":
            assert np.isnan(profile["nodata"])
            np.testing.assert_array_equal(values, ref.astype(np.float32))
            assert np.isnan(values).any() and np.isfinite(values).any()
        elif var.endswith("_release"):
            assert profile["nodata"] == 0 and profile["dtype"] == "int32"
            np.testing.assert_array_equal(values, ref)
        else:  # counts: 0 is a count, no NODATA
            assert profile["nodata"] is None
            np.testing.assert_array_equal(values, ref)
    with rasterio.open(out / "region_peak_pressure.tif") as src:
        assert src.units == ("kPa",)
    # a rerun writes over its own outputs (renamed into place), never into the store
    assert main(["export", str(store), "-o", str(out), "--variables",
                 "peak_pressure_exceedance_count", "-q"]) == 0
    assert (out / "region_peak_pressure_exceedance_count_30kPa.tif").is_file()


@pytest.mark.parametrize("args, says", [
    (["--format", "asc"], "Cloud-Optimized GeoTIFF only"),
    (["--variables", "peak_presure"], "no map named 'peak_presure'"),
])
def test_bad_export_one_line_exit_2(store, capsys, args, says):
    code = main(["export", str(store), "-o", str(store.parent / "bad"), *args])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and says in err[0], err
    assert not (store.parent / "bad").exists() or not list((store.parent / "bad").iterdir())


def test_releases_parquet(tmp_path, capsys):
    """releases.parquet holds releases.csv's table where pandas has a parquet engine;
    elsewhere it is not written, and no run says so (releases.csv has the same table)."""
    from test_region import BOXES, REGION, _dem, _releases

    from avflow.region import load_region
    from avflow.region.orchestrate import run_region

    _dem(tmp_path)
    _releases(tmp_path / "releases.gpkg", BOXES[:1])
    (tmp_path / "r.yaml").write_text(REGION.format(releases="releases.gpkg", buffer=1.0e5))
    run_region(load_region(tmp_path / "r.yaml"), tmp_path / "out", workers=0)
    err = capsys.readouterr().err
    engine = any(importlib.util.find_spec(m) for m in ("pyarrow", "fastparquet"))
    if not engine:
        assert not (tmp_path / "out" / "releases.parquet").exists()
        assert "pyarrow" not in err and "parquet" not in err  # not said on every run
        pytest.skip("no parquet engine (pyarrow, fastparquet) installed: only its absence "
                    "is tested")
    table = pd.read_parquet(tmp_path / "out" / "releases.parquet")
    csv = pd.read_csv(tmp_path / "out" / "releases.csv")
    assert list(table.columns) == list(csv.columns) and len(table) == len(csv) == 1
    assert table.runout.iloc[0] == pytest.approx(csv.runout.iloc[0], rel=1e-12)
