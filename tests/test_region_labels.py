"""Region outputs that say what they hold: a release polygon partly outside the DEM is
clipped to it and releases.csv gives the released area (and the part outside); a flow that
runs away from the map's uphill edge is not flagged as reaching the edge; each release's
file has its window's x, y and the DEM's CRS.

test_region's tiny region: a 30 degree slope onto a flat floor, 20 m cells, Coulomb 24."""

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from test_region import REGION, X0, Y0, _dem, _releases


@pytest.fixture(scope="module")
def clipped(tmp_path_factory):
    from avflow.region import load_region
    from avflow.region.orchestrate import run_region

    root = tmp_path_factory.mktemp("clip")
    _dem(root)
    # 1: 100 m x 100 m, 40 m of it north of the DEM's north edge (40% outside); 2: inside
    _releases(root / "rel.gpkg", [(X0 + 200, Y0 - 60, X0 + 300, Y0 + 40),
                                  (X0 + 200, Y0 - 400, X0 + 300, Y0 - 300)])
    (root / "r.yaml").write_text(REGION.format(releases="rel.gpkg", buffer=40.0))
    return run_region(load_region(root / "r.yaml"), root / "out", workers=0, quiet=False), root


def test_polygon_outside_the_dem_is_clipped_and_said(clipped, capfd):
    outcome, root = clipped
    table = pd.read_csv(root / "out" / "releases.csv").set_index("id")
    assert table.loc[1, "area"] == pytest.approx(6000.0)  # 100 x 60 m on the DEM
    assert table.loc[1, "area_outside_dem"] == pytest.approx(4000.0)
    assert table.loc[2, "area"] == pytest.approx(10000.0)
    assert table.loc[2, "area_outside_dem"] == 0.0
    # the released volume is the clipped polygon's: 3 x 5 cells of 2 m on the DEM
    assert table.loc[1, "volume"] == pytest.approx(table.loc[2, "volume"] * 0.6, rel=0.2)


def test_clip_is_said_on_stderr(tmp_path, capfd):
    from avflow.region import load_region
    from avflow.region.orchestrate import run_region

    _dem(tmp_path)
    _releases(tmp_path / "rel.gpkg", [(X0 + 200, Y0 - 60, X0 + 300, Y0 + 40)])
    (tmp_path / "r.yaml").write_text(REGION.format(releases="rel.gpkg", buffer=40.0))
    capfd.readouterr()
    run_region(load_region(tmp_path / "r.yaml"), tmp_path / "out", workers=0, quiet=False)
    err = capfd.readouterr().err
    assert ("release 1: 40% of its polygon lies outside the DEM: clipped to it (released "
            "area 6000 of 10000 m2, area in releases.csv)") in err, err


def test_release_files_have_coordinates_and_crs(clipped):
    outcome, root = clipped
    row = outcome.table.set_index("id").loc[2]
    with xr.open_dataset(root / "out" / "releases" / "2.nc") as ds:
        x0 = X0 + 20.0 * (int(row.col0) + 0.5)
        y0 = Y0 - 20.0 * (int(row.row0) + 0.5)
        assert float(ds.x[0]) == x0 and float(ds.y[0]) == y0  # north first
        assert ds.x.attrs["standard_name"] == "projection_x_coordinate"
        assert ds.peak_thickness.attrs["grid_mapping"] == "crs"
        assert "CH1903+" in ds["crs"].attrs["crs_wkt"]
        # the window's maps sit where the whole region's store has them
        store = xr.open_zarr(outcome.store)
        part = store.peak_thickness.sel(x=ds.x, y=ds.y).values
        mine = ds.peak_thickness.values
        both = np.isfinite(mine) & np.isfinite(part)  # the store keeps what reaches
        assert both.sum() > 10 and (part[both] >= mine[both] - 1e-6).all()


def test_flow_running_away_from_an_uphill_edge_is_not_flagged(tmp_path):
    """A strip released along the west (uphill) edge of a 30 degree slope that also falls
    gently north to south (0.1): the edge cells south of the strip are lower than its
    lowest cell and the flow wets them, but the bed there falls into the map at 30 degrees:
    it runs away from that edge, which does not cut its runout. The flow reaches no other
    edge."""
    import avflow
    from avflow.terrain.raster import write_asc

    x = np.arange(0, 1000 + 10, 20.0)
    y = np.arange(0, 1000 + 10, 20.0)
    X, Y = np.meshgrid(x, y)
    z = np.tan(np.radians(30)) * np.clip(700 - X, 0, None) + 0.1 * (1000 - Y)
    write_asc(tmp_path / "dem.asc", z, x, y, None)
    body = ("terrain: {kind: dem, path: dem.asc}\ngrid: {dx: 20.0}\n"
            "rheology: {law: coulomb, delta_deg: 24.0}\ntime: {end: 200.0, cfl: 0.5}\n"
            "output: {every: 10.0}\n")
    (tmp_path / "edge.yaml").write_text(
        "name: uphill\n" + body
        + "release: {kind: box, x: [0.0, 10.0], y: [200.0, 600.0], thickness: 4.0}\n")
    ds = avflow.run(tmp_path / "edge.yaml")
    peak = np.nan_to_num(ds.peak_thickness.values)
    zmin = float(np.min(z[(X <= 10) & (Y >= 200) & (Y <= 600)]))
    lower_wet = (peak[:, 0] > 0.01) & (z[:, 0] < zmin)
    assert lower_wet.any()  # the old rule's trigger: wet edge cells below the release
    assert not (peak[:, -1] > 0.01).any() and not (peak[0] > 0.01).any() \
        and not (peak[-1] > 0.01).any()
    assert int(ds.attrs["runout_truncated"]) == 0
    # the same DEM cut at x = 600 m, on the slope: the flow reaches that edge, flagged
    keep = x <= 600
    write_asc(tmp_path / "short.asc", z[:, keep], x[keep], y, None)
    (tmp_path / "short.yaml").write_text(
        "name: downhill\n" + body.replace("dem.asc", "short.asc")
        + "release: {kind: box, x: [0.0, 10.0], y: [200.0, 600.0], thickness: 4.0}\n")
    assert int(avflow.run(tmp_path / "short.yaml").attrs["runout_truncated"]) == 1
