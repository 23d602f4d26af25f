"""``avflow export`` and ``avflow plot``: georeferencing of the run file and of the exported
rasters as GDAL (rasterio) and rioxarray read them, value round trips, PNGs, bad input."""

import numpy as np
import pytest
import rasterio
import xarray as xr
from pyproj import CRS
from rasterio.transform import Affine

from avflow.cli import main
from avflow.terrain.raster import read_raster, same_crs, write_asc
from avflow.output.maps import DEFAULT_EXPORT, _nice_levels, hillshade
from avflow.output.dataset import to_dataset
from avflow.output.netcdf import write_netcdf
from avflow.simulation.runner import simulate
from avflow.scenario.schema import load_scenario
from conftest import SCENARIOS

EPSG = 31287  # MGI / Austria Lambert
DX = 10.0
X0, Y0 = 400000.0, 350000.0  # lower-left corner of the DEM
NX, NY = 60, 50  # not square: a transposed or flipped map would not fit


@pytest.fixture(scope="module")
def grid_run(tmp_path_factory):
    """A cylinder on a slope that flattens into a shallow valley, on a DEM with a CRS and a
    NODATA corner; run through the CLI."""
    folder = tmp_path_factory.mktemp("grid")
    x = X0 + DX * (np.arange(NX) + 0.5)
    y = Y0 + DX * (np.arange(NY) + 0.5)
    xx, yy = np.meshgrid(x, y)
    z = 1000.0 + 150.0 * np.exp(-(xx - x[0]) / 150.0) + 5e-4 * (yy - y.mean())**2
    z[:5, -8:] = np.nan  # south-east corner outside the DEM
    write_asc(folder / "dem.asc", z, x, y, CRS.from_epsg(EPSG).to_wkt())
    (folder / "scene.yaml").write_text(f"""\
name: synthetic-valley
terrain: {{kind: dem, path: dem.asc}}
grid: {{dx: {DX}}}
release: {{kind: cylinder, center: [{X0 + 110.0}, {y.mean()}], radius: 40.0, thickness: 8.0}}
rheology: {{law: coulomb, delta_deg: 20.0}}
time: {{end: 12.0}}
output: {{every: 2.0}}
numerics: {{order: 1}}  # its wider front covers every pressure class on this small scene
""")
    out = folder / "run.nc"
    assert main(["run", str(folder / "scene.yaml"), "-o", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def profile_run(tmp_path_factory):
    scenario = load_scenario(SCENARIOS / "seed_exponential_coulomb15.yaml").with_updates(
        {"time.end": 20.0})
    return write_netcdf(to_dataset(simulate(scenario)),
                        tmp_path_factory.mktemp("profile") / "profile.nc")


@pytest.fixture(scope="module")
def triangles_run(tmp_path_factory):
    scenario = load_scenario(SCENARIOS / "plane_cylinder_triangles.yaml").with_updates(
        {"time.end": 4.0, "output.every": 1.0})
    return write_netcdf(to_dataset(simulate(scenario)),
                        tmp_path_factory.mktemp("triangles") / "tri.nc")


def _expected_transform():
    # North-up: the origin is the north-west corner of the north-west cell.
    return Affine(DX, 0.0, X0, 0.0, -DX, Y0 + NY * DX)


def _same_crs(crs) -> bool:
    return crs is not None and CRS.from_wkt(crs.to_wkt()).equals(CRS.from_epsg(EPSG),
                                                                  ignore_axis_order=True)


def test_netcdf_maps_are_georeferenced_for_gdal(grid_run):
    with rasterio.open(f"netcdf:{grid_run}:peak_thickness") as src:
        assert _same_crs(src.crs)
        assert src.transform.almost_equals(_expected_transform())
        assert (src.width, src.height) == (NX, NY)
        band = src.read(1, masked=True).filled(np.nan)
    ds = xr.open_dataset(grid_run, decode_times=False)
    np.testing.assert_array_equal(band, ds["peak_thickness"].values[::-1])  # north up
    assert np.isnan(band[-1, -1]) and np.isfinite(band[0, 0])  # NODATA corner is south-east


def test_netcdf_maps_are_georeferenced_for_rioxarray(grid_run):
    import rioxarray  # noqa: F401  (registers .rio)

    ds = xr.open_dataset(grid_run, decode_coords="all", decode_times=False)
    for name in ("peak_thickness", "deposit_thickness", "bed_elevation"):
        assert _same_crs(ds[name].rio.crs), name
    assert _same_crs(ds.rio.crs)
    t = ds["peak_thickness"].rio.transform()  # rioxarray keeps the file's ascending y
    assert t.almost_equals(Affine(DX, 0.0, X0, 0.0, DX, Y0))


@pytest.mark.parametrize("fmt", ["tif", "asc"])
def test_export_round_trip(grid_run, tmp_path, fmt, capsys):
    assert main(["export", str(grid_run), "--format", fmt, "-o", str(tmp_path)]) == 0
    printed = capsys.readouterr()
    assert printed.err == ""  # the file has a CRS: no warning
    ds = xr.open_dataset(grid_run, decode_times=False)
    written = sorted(p.name for p in tmp_path.glob(f"*.{fmt}"))
    assert written == sorted(f"run_{name}.{fmt}" for name in DEFAULT_EXPORT)
    for name in DEFAULT_EXPORT:
        with rasterio.open(tmp_path / f"run_{name}.{fmt}") as src:
            values = src.read(1, masked=True).astype(float).filled(np.nan)[::-1]
            assert src.transform.almost_equals(_expected_transform())
            if fmt == "tif":
                assert _same_crs(src.crs)
            else:  # the .prj is ESRI WKT1: GDAL recognises the CRS, names differ
                assert src.crs is not None and src.crs.to_epsg() == EPSG
        if name == "peak_pressure_class":  # derived: classes of 1, 3 and 30 kPa where the
            p = ds["peak_pressure"].values / 1000.0  # flow was thicker than the threshold
            reached = ds["peak_thickness"].values >= ds.attrs["runout_threshold_m"]
            k = sum((p >= t).astype(float) for t in (1, 3, 30)) * reached
            expected = np.where(np.isnan(p), np.nan, k)
            assert set(np.unique(k)) == {0, 1, 2, 3}
        else:
            expected = ds[name].values.astype(float)
        if name == "peak_pressure":  # in kPa, as the classes, plots and path tables
            expected = expected / 1000.0
        if fmt == "tif":  # each band names its units and what it holds
            with rasterio.open(tmp_path / f"run_{name}.{fmt}") as src:
                units = ("kPa" if name == "peak_pressure" else "class"
                         if name == "peak_pressure_class" else ds[name].attrs.get("units"))
                assert (src.units[0] or None) == units, name
                assert src.descriptions[0], name
        assert np.array_equal(np.isnan(values), np.isnan(expected)), name
        # GeoTIFF: float32 as stored (kPa: float32 of the Pa / 1000); ESRI ASCII: the 6
        # significant digits of dem.write_asc
        rtol = (1e-7 if name == "peak_pressure" else 0.0) if fmt == "tif" else 1e-5
        np.testing.assert_allclose(values, expected, rtol=rtol, atol=1e-6, equal_nan=True,
                                   err_msg=name)
    # avflow reads its own exports back as DEMs / thickness rasters
    back = read_raster(tmp_path / f"run_deposit_thickness.{fmt}")
    np.testing.assert_allclose(back.x, ds["x"].values)
    np.testing.assert_allclose(back.y, ds["y"].values)
    assert back.crs_wkt and same_crs(back.crs_wkt, CRS.from_epsg(EPSG).to_wkt())
    assert np.nanmax(ds["deposit_thickness"].values) > 1.0  # the scene did flow


def test_export_selected_variables_next_to_the_file(grid_run, capsys):
    names = ["bed_elevation", "deposit_thickness"]
    assert main(["export", str(grid_run), "--variables", ",".join(names)]) == 0
    out = capsys.readouterr().out
    for name in names:
        path = grid_run.parent / f"run_{name}.tif"
        assert path.is_file() and f"wrote {path}" in out
        path.unlink()
    assert not list(grid_run.parent.glob("*.tif"))  # only those asked for


def test_export_without_crs_warns(tmp_path, capsys):
    scenario = load_scenario(SCENARIOS / "plane_box_2d.yaml").with_updates({"time.end": 2.0})
    path = write_netcdf(to_dataset(simulate(scenario)), tmp_path / "plane.nc")
    assert main(["export", str(path), "--variables", "peak_thickness"]) == 0
    assert "no CRS" in capsys.readouterr().err
    with rasterio.open(tmp_path / "plane_peak_thickness.tif") as src:
        assert src.crs is None
        assert src.transform.a == 10.0 and src.transform.e == -10.0


def test_plot_grid(grid_run, tmp_path, capsys):
    png = tmp_path / "map.png"
    assert main(["plot", str(grid_run), "-o", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    assert main(["plot", str(grid_run)]) == 0  # default: next to the file
    assert grid_run.with_suffix(".png").is_file()


def test_plot_profile(profile_run):
    assert main(["plot", str(profile_run)]) == 0
    png = profile_run.with_suffix(".png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000


def test_plot_triangles_and_no_export(triangles_run, capsys):
    assert main(["plot", str(triangles_run)]) == 0
    assert triangles_run.with_suffix(".png").stat().st_size > 20_000
    capsys.readouterr()
    assert main(["export", str(triangles_run)]) == 2
    err = capsys.readouterr().err
    assert "export needs a grid scene" in err and str(triangles_run) in err


def test_errors_exit_2_naming_the_file(grid_run, profile_run, tmp_path, capsys):
    def fails(argv, *words):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("avflow: error: ") and err.count("\n") == 1, err
        for word in words:
            assert word in err, (word, err)

    missing = tmp_path / "missing.nc"
    fails(["export", str(missing)], str(missing), "no such file")
    fails(["plot", str(missing)], str(missing), "no such file")
    text = tmp_path / "notes.nc"
    text.write_text("not NetCDF\n")
    fails(["export", str(text)], str(text), "NetCDF")
    fails(["export", str(profile_run)], str(profile_run), "export needs a grid scene",
          "profile")
    fails(["export", str(grid_run), "--variables", "peak_thickness,bogus"], "'bogus'",
          "available:", "deposit_thickness", "slope_angle")
    fails(["export", str(grid_run), "--variables", " , "], "--variables")
    assert not list(tmp_path.glob("*.tif"))


def test_hillshade_lights_slopes_facing_north_west():
    x = np.arange(20.0)
    xx, yy = np.meshgrid(x, x)
    facing_nw = hillshade(xx - yy, 1.0, 1.0)  # rises to the south-east
    facing_se = hillshade(yy - xx, 1.0, 1.0)
    flat = hillshade(np.zeros_like(xx), 1.0, 1.0)
    assert facing_nw.min() > flat.max() > facing_se.max()
    z = np.zeros((5, 5))
    z[0, 0] = np.nan
    assert np.isnan(hillshade(z, 1.0, 1.0)[0, 0])


def test_nice_levels():
    assert _nice_levels(0.01, 0.3) == [0.01, 0.02, 0.05, 0.1, 0.2, 0.5]
    levels = _nice_levels(1e-4, 300.0)
    assert len(levels) <= 10 and levels[0] <= 1e-4 and levels[-1] >= 300.0


# =========================================================================================
# Ensembles on a DEM: the CRS in ensemble.nc, probability maps exported as GeoTIFFs
# =========================================================================================


@pytest.fixture(scope="module")
def dem_ensemble(grid_run):
    """Four members on the synthetic valley (a DEM with a CRS), run in this process."""
    folder = grid_run.parent
    (folder / "ens.yaml").write_text("""\
base: scene.yaml
vary:
  rheology.delta_deg: [16.0, 24.0]
  release.volume_factor: [0.5, 1.0]
thresholds:
  peak_thickness: [0.5, 2.0]
  peak_speed: [2.0, 5.0]
""")
    out = folder / "ens"
    assert main(["ensemble", str(folder / "ens.yaml"), "-o", str(out), "--workers", "0"]) == 0
    return out


def test_ensemble_nc_carries_the_crs_and_probabilities(dem_ensemble):
    ds = xr.open_dataset(dem_ensemble / "ensemble.nc", decode_times=False)
    assert "crs" in ds.data_vars and _same_crs(CRS.from_wkt(ds["crs"].attrs["crs_wkt"]))
    expected = {"peak_thickness": ("threshold", [0.5, 2.0]),
                "peak_speed": ("speed_threshold", [2.0, 5.0]),
                "peak_pressure": ("pressure_threshold", [1.0, 3.0, 30.0])}  # classes, kPa
    for name, (dim, values) in expected.items():
        prob = ds[f"{name}_exceedance_probability"]
        assert prob.dims == (dim, "y", "x") and list(ds[dim].values) == values, name
        assert prob.attrs["grid_mapping"] == "crs", name
        assert np.nanmax(prob.values) == 1.0 and np.nanmin(prob.values) == 0.0, name
        assert np.all(np.diff(prob.values, axis=0)[np.isfinite(prob.values[1:])] <= 0), name
        assert np.isnan(prob.values[:, 0, -1]).all()  # the NODATA corner (south-east)
    assert ds["pressure_threshold"].attrs["units"] == "kPa"
    # P(peak thickness > 0.5 m), recomputed from the members' own files
    peaks = []
    for h in ds["scenario_hash"].values:
        with xr.open_dataset(dem_ensemble / "members" / f"{h}.nc", decode_times=False) as m:
            peaks.append(m["peak_thickness"].values)
    np.testing.assert_array_equal(ds["peak_thickness_exceedance_probability"].values[0],
                                  np.where(np.isnan(peaks[0]), np.nan,
                                           np.mean(np.array(peaks) > 0.5, axis=0)))
    with rasterio.open(f"netcdf:{dem_ensemble / 'ensemble.nc'}:"
                       "peak_pressure_exceedance_probability") as src:
        assert _same_crs(src.crs) and src.count == 3  # GDAL reads the CRS and the bands
    assert "crs" not in ds["status"].encoding.get("coordinates", "")
    from test_cli_output import compliance_errors

    assert compliance_errors(dem_ensemble / "ensemble.nc") == []


def test_ensemble_probability_maps_exported_to_geotiff(dem_ensemble, tmp_path, capsys):
    """`avflow export OUTDIR/ensemble.nc --format tif`: one GeoTIFF per map and threshold,
    read back by rasterio with the DEM's CRS, transform and the file's values."""
    path = dem_ensemble / "ensemble.nc"
    assert main(["export", str(path), "--format", "tif", "-o", str(tmp_path)]) == 0
    assert capsys.readouterr().err == ""
    ds = xr.open_dataset(path, decode_times=False)
    expected = {f"ensemble_peak_thickness_exceedance_probability_{t}m.tif" for t in ("0.5", "2")}
    expected |= {f"ensemble_peak_speed_exceedance_probability_{t}m_s.tif" for t in ("2", "5")}
    expected |= {f"ensemble_peak_pressure_exceedance_probability_{t}kPa.tif"
                 for t in ("1", "3", "30")}
    assert {p.name for p in tmp_path.glob("*.tif")} == expected
    with rasterio.open(tmp_path / "ensemble_peak_pressure_exceedance_probability_3kPa.tif") as src:
        assert _same_crs(src.crs)
        assert src.transform.almost_equals(_expected_transform())
        assert src.descriptions[0] == "P(peak pressure > 3 kPa)"
        # a probability's pixels have no unit of pressure: the threshold's is a tag
        assert src.units[0] == "1" and src.tags(1)["threshold_units"] == "kPa"
        assert "units" not in src.tags(1)
        values = src.read(1, masked=True).filled(np.nan)[::-1]
    stored = ds["peak_pressure_exceedance_probability"].sel(pressure_threshold=3.0).values
    np.testing.assert_array_equal(values, stored)
    assert np.nanmax(values) > 0.0
    # the CRS survives the ESRI ASCII route too (.prj)
    assert main(["export", str(path), "--format", "asc", "-o", str(tmp_path),
                 "--variables", "peak_speed_exceedance_probability"]) == 0
    back = read_raster(tmp_path / "ensemble_peak_speed_exceedance_probability_5m_s.asc")
    assert same_crs(back.crs_wkt, CRS.from_epsg(EPSG).to_wkt())


def test_ensemble_report_maps_over_the_hillshade(dem_ensemble):
    from avflow.ensemble.report import write_report

    text = write_report(dem_ensemble).read_text()
    for fig in ("exceedance.png", "exceedance_speed.png", "exceedance_pressure.png"):
        assert f"report/{fig}" in text
        assert (dem_ensemble / "report" / fig).stat().st_size > 20_000


def test_plot_and_export_of_an_ensemble_file_say_what_it_is(dem_ensemble, capsys):
    assert main(["plot", str(dem_ensemble / "ensemble.nc")]) == 2
    assert "avflow report" in capsys.readouterr().err


def test_the_plot_outlines_where_an_entrainment_runs_layer_lay():
    """An entrainment run's file: the layer at the start is what is left minus the bed's
    change (negative where eroded); a run without entrainment has no such outline."""
    import xarray as xr

    from avflow.output.maps import _erodible_at_start

    left = np.array([[0.0, 0.1], [0.3, 0.0]])
    change = np.array([[0.0, -0.2], [0.0, -0.3]])  # the last cell eroded to nothing
    ds = xr.Dataset({"erodible_depth": (("y", "x"), left),
                     "bed_change": (("y", "x"), change)})
    np.testing.assert_array_equal(_erodible_at_start(ds), [[False, True], [True, True]])
    assert _erodible_at_start(xr.Dataset()) is None


def test_plot_options_for_a_report(grid_run, tmp_path, capsys):
    """--map, --extent and --dpi: one panel of the peak speed, a part of the map, at half
    the resolution (half the pixels each way); a scale bar and a north arrow on each map."""
    import matplotlib.image as mpimg

    full, part = tmp_path / "full.png", tmp_path / "part.png"
    assert main(["plot", str(grid_run), "-o", str(full)]) == 0
    ds = xr.open_dataset(grid_run)
    x0, x1 = float(ds.x.min()), float(ds.x.max())
    y0, y1 = float(ds.y.min()), float(ds.y.max())
    mid = (x0 + x1) / 2
    assert main(["plot", str(grid_run), "--map", "speed", "--extent", str(x0), str(mid),
                 str(y0), str(y1), "--dpi", "60", "-o", str(part)]) == 0
    half = tmp_path / "half.png"
    assert main(["plot", str(grid_run), "--dpi", "60", "-o", str(half)]) == 0
    assert abs(mpimg.imread(half).shape[0] / mpimg.imread(full).shape[0] - 0.5) < 0.01
    assert part.stat().st_size > 10_000
    capsys.readouterr()
    assert main(["plot", str(grid_run), "--extent", "1", "0", "0", "1",
                 "-o", str(tmp_path / "bad.png")]) == 2
    assert "--extent: XMIN XMAX YMIN YMAX" in capsys.readouterr().err
    assert not (tmp_path / "bad.png").exists()


def test_every_map_has_a_scale_bar_and_a_north_arrow(grid_run):
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    from avflow.output.maps import _plot_grid, _plt

    plt = _plt()
    with xr.open_dataset(grid_run) as ds:
        fig = _plot_grid(ds, plt)
    for ax in fig.axes:
        if ax.get_label() == "<colorbar>":
            continue
        assert any(isinstance(a, AnchoredSizeBar) for a in ax.artists), ax
        assert any(t.get_text() == "N" for t in ax.texts), ax
    plt.close(fig)
