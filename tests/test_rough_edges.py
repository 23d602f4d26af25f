"""What a newcomer met (issue 31): status words, warnings, help text, CF messages, plots.

Small scenes only: the seed's profile at 25 m cells, a 1.2 km x 0.6 km LV95 DEM at 20 m.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from avflow.cli import build_parser, main
from conftest import SCENARIOS

SECTION6 = SCENARIOS / "seed_exponential_coulomb15.yaml"


def _lv95_scene(tmp_path, release_crs: bool = True):
    """A 30 degree slope into a flat plain in Swiss LV95 (EPSG:2056), 20 m cells, with a
    GeoJSON release area (with or without its CRS member)."""
    import rasterio
    from rasterio.transform import from_origin

    dx, west, north = 20.0, 2_600_000.0, 1_200_000.0
    x = np.arange(0, 1200, dx) + dx / 2
    y = np.arange(0, 600, dx) + dx / 2
    X, Y = np.meshgrid(x, y)
    z = 1500 + np.tan(np.radians(30)) * np.clip(700 - X, 0, None) + 0.002 * (Y - 300) ** 2
    with rasterio.open(tmp_path / "dem.tif", "w", driver="GTiff", width=z.shape[1],
                       height=z.shape[0], count=1, dtype="float64", crs="EPSG:2056",
                       transform=from_origin(west, north, dx, dx)) as dst:
        dst.write(z, 1)
    x0, x1, y0, y1 = west + 100, west + 240, north - 370, north - 230
    feature = {"type": "Feature", "properties": {"thickness": 2.0},
               "geometry": {"type": "Polygon", "coordinates": [[[x0, y0], [x1, y0], [x1, y1],
                                                                [x0, y1], [x0, y0]]]}}
    collection = {"type": "FeatureCollection", "features": [feature]}
    if release_crs:
        collection["crs"] = {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::2056"}}
    (tmp_path / "release.geojson").write_text(json.dumps(collection))
    scenario = tmp_path / "lv95.yaml"
    scenario.write_text("""name: lv95
terrain: {kind: dem, path: dem.tif}
grid: {dx: 20.0}
release: {kind: polygon, path: release.geojson}
rheology: {law: coulomb, delta_deg: 22.0}
time: {end: 120.0}
""")
    return scenario


# --- status words ---------------------------------------------------------------------------


def test_a_run_ended_by_the_kinetic_energy_rule_is_not_called_at_rest(tmp_path, capsys):
    import xarray as xr

    from avflow.output.maps import _title, at_rest

    out_rule, out_rest = tmp_path / "rule.nc", tmp_path / "rest.nc"
    assert main(["run", str(SECTION6), "--set", "grid.dx=25", "--set",
                 "output.stop_rule=kinetic_energy", "-o", str(out_rule)]) == 0
    assert main(["run", str(SECTION6), "--set", "grid.dx=25", "-o", str(out_rest)]) == 0
    rule_line, _, rest_line, _ = capsys.readouterr().out.splitlines()
    assert rule_line.split(": ")[1].startswith("ended_by_rule (kinetic-energy rule, ")
    assert "still moving: not a deposit at rest" in rule_line
    assert rest_line.split(": ")[1].startswith("at_rest (") and "stopped" not in rest_line
    assert "% of the volume still moving)" in rest_line
    with xr.open_dataset(out_rule, decode_times=False) as ds:
        moving = float(ds.moving_volume_end) / float(ds.release_volume)
        assert ds.attrs["status"] == "ended_by_rule" and moving > 1e-3  # it does still move
        assert not at_rest(ds) and "still moving" in _title(ds)
    with xr.open_dataset(out_rest, decode_times=False) as ds:
        assert ds.attrs["status"] == "at_rest" and at_rest(ds)
        assert float(ds.moving_volume_end) <= 1e-3 * float(ds.release_volume)
        assert "still moving" not in _title(ds)


def test_files_that_say_stopped_still_read_as_before():
    import xarray as xr

    from avflow.output.maps import at_rest

    old = xr.Dataset(attrs={"status": "stopped", "ended_by": "kinetic_energy"})
    assert not at_rest(old)
    assert at_rest(xr.Dataset(attrs={"status": "stopped", "ended_by": "moving_volume"}))


def test_report_warns_when_no_member_came_to_rest_and_drops_the_empty_panel(tmp_path):
    import avflow
    from avflow.ensemble.report import write_report

    base = avflow.load_scenario(SECTION6).with_updates({"grid.dx": 50.0, "time.end": 20.0})
    members = [base.with_updates({"rheology.delta_deg": d}) for d in (14.0, 16.0)]
    ds = avflow.run_ensemble(members, tmp_path / "ens", workers=0, quiet=True)
    assert set(ds["status"].values) == {"completed"}  # still moving at time.end
    assert np.isnan(ds["time_to_stop"].values).all()
    text = write_report(tmp_path / "ens").read_text()
    assert "no member came to rest" in text
    assert "Runout against" in text and "time to stop against" not in text
    assert "per friction law" not in text  # one law: nothing to compare

    import matplotlib.image as mpimg

    (vs,) = (tmp_path / "ens" / "report").glob("vs_*.png")
    img = mpimg.imread(vs)
    assert img.shape[1] < 1.5 * img.shape[0]  # one panel, not two with an empty one


# --- CRS -------------------------------------------------------------------------------------


def test_lv95_dem_prints_no_pyproj_warning(tmp_path, capfd):
    """pyproj warns that LV95's rectified-to-skew angle has no CF name: crs_wkt keeps it,
    so the warning is noise, and it used to be printed twice by every command."""
    scenario = _lv95_scene(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert main(["run", str(scenario), "-o", str(tmp_path / "lv95.nc"), "-q"]) == 0
    err = capfd.readouterr().err
    assert "UserWarning" not in err and "lost in conversion" not in err, err
    import rioxarray  # noqa: F401
    import xarray as xr

    with xr.open_dataset(tmp_path / "lv95.nc", decode_coords="all") as ds:
        assert ds.rio.crs.to_epsg() == 2056


def test_release_without_crs_on_a_dem_with_one_warns_on_one_line(tmp_path, capfd):
    scenario = _lv95_scene(tmp_path, release_crs=False)
    assert main(["run", str(scenario), "-o", str(tmp_path / "a.nc"), "-q"]) == 0
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("avflow: warning: ") and "release.geojson: no CRS" in err[0]
    assert "CH1903+ / LV95" in err[0]
    # with its CRS: nothing to say
    (tmp_path / "b").mkdir()
    scenario = _lv95_scene(tmp_path / "b", release_crs=True)
    assert main(["run", str(scenario), "-o", str(tmp_path / "b.nc"), "-q"]) == 0
    assert capfd.readouterr().err == ""


# --- help ------------------------------------------------------------------------------------


def test_help_shows_no_restructuredtext_markup():
    parser = build_parser()
    texts = [parser.format_help()]
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    texts += [command.format_help() for command in sub.choices.values()]
    for text in texts:
        assert "``" not in text and "`" not in text, text


# --- plots -----------------------------------------------------------------------------------


def test_path_plots_name_members_by_their_varied_values():
    import pandas as pd

    from avflow.output.path import member_labels

    table = pd.DataFrame({"realization": [0, 1, 2], "grid.dx": [20.0] * 3,
                          "rheology.delta_deg": [18.0, 20.0, 22.5], "runout": [1.0, 2.0, 3.0]})
    assert member_labels(table) == {0: "delta_deg 18", 1: "delta_deg 20", 2: "delta_deg 22.5"}
    same = pd.DataFrame({"realization": [0, 1], "grid.dx": [20.0, 20.0]})
    assert member_labels(same) == {0: "member 0", 1: "member 1"}


@pytest.mark.parametrize("n", [1, 4, 21])
def test_exceedance_colours_are_one_per_possible_probability(n):
    from avflow.ensemble.report import probability_style

    cmap, norm, levels = probability_style(n)
    values = np.arange(1, n + 1) / n
    assert cmap.N == n and np.allclose(levels, values)
    indices = norm(values)
    assert list(indices) == list(range(n))  # k / n -> colour k - 1, each its own
    between = norm((np.arange(1, n) + 0.49) / n) if n > 1 else np.array([], int)
    assert list(between) == list(range(n - 1))  # no value falls between two colours


def test_path_figure_keeps_the_map_label_clear_of_the_panel_below(tmp_path, monkeypatch):
    """The map's "x (m)" sat under the title of the path-coordinates panel (issue 31)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from avflow.output.path import analyse_target

    run = tmp_path / "box.nc"
    assert main(["run", str(SCENARIOS / "plane_box_2d.yaml"), "--set", "grid.dx=40",
                 "-o", str(run), "-q"]) == 0
    monkeypatch.setattr(plt, "close", lambda *a, **k: None)  # keep the figure to measure it
    analyse_target(run)
    fig = plt.gcf()
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    ax_map, ax_sl = fig.axes[0], fig.axes[1]
    label = ax_map.xaxis.label.get_window_extent(renderer)
    title = ax_sl.title.get_window_extent(renderer)
    assert ax_map.get_xlabel().startswith("x (m)")
    assert not label.overlaps(title), (label, title)
    plt.close("all")


# --- plot and report take what a user gives them --------------------------------------------


def test_plot_of_an_ensemble_folder_says_what_it_takes(tmp_path, capsys):
    (tmp_path / "ens").mkdir()
    (tmp_path / "ens" / "summary.csv").write_text("realization\n")
    assert main(["plot", str(tmp_path / "ens")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "an ensemble folder" in err
    assert "no such file" not in err and "avflow report" in err


def test_report_accepts_the_ensemble_file_as_well_as_its_folder(tmp_path):
    import avflow
    from avflow.ensemble.report import write_report

    base = avflow.load_scenario(SECTION6).with_updates({"grid.dx": 50.0})
    avflow.run_ensemble([base, base.with_updates({"rheology.delta_deg": 16.0})],
                        tmp_path / "ens", workers=0, quiet=True)
    by_folder = write_report(tmp_path / "ens")
    assert write_report(tmp_path / "ens" / "ensemble.nc") == by_folder
    assert "at_rest" in by_folder.read_text()


def test_lv95_triangles_ensemble_and_their_commands_print_no_pyproj_warning(tmp_path, capfd):
    """The warning came from every output that turns the CRS into CF attributes: grid files,
    UGRID files (avflow/output/ugrid.py) and the ensemble's members; run, plot, ensemble,
    report and export on an EPSG:2056 DEM print none of it."""
    import rioxarray  # noqa: F401
    import xarray as xr

    scenario = _lv95_scene(tmp_path)
    (tmp_path / "ens.yaml").write_text("base: lv95.yaml\nvary:\n  rheology.delta_deg: [20.0, 24.0]\n")
    short = ["--set", "time.end=20"]
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert main(["run", str(scenario), *short, "--set", "grid.mesh=triangles",
                     "-o", str(tmp_path / "tri.nc"), "-q"]) == 0
        assert main(["plot", str(tmp_path / "tri.nc"), "-q"]) == 0
        assert main(["ensemble", str(tmp_path / "ens.yaml"), *short, "-o", str(tmp_path / "ens"),
                     "--workers", "0", "-q"]) == 0
        assert main(["report", str(tmp_path / "ens"), "-q"]) == 0
        assert main(["export", str(tmp_path / "ens" / "ensemble.nc"), "-q"]) == 0
    err = capfd.readouterr().err
    assert "UserWarning" not in err and "lost in conversion" not in err, err
    for path in (tmp_path / "tri.nc", tmp_path / "ens" / "ensemble.nc"):
        with xr.open_dataset(path, decode_coords="all") as ds:
            assert ds.rio.crs.to_epsg() == 2056, path
        with xr.open_dataset(path) as ds:  # the grid mapping, no coordinate for titles
            assert "crs" in ds.data_vars and ds["crs"].attrs["crs_wkt"]
            assert "crs" not in ds["peak_thickness"]._title_for_slice()


# --- xarray's defaults ------------------------------------------------------------------------


def test_plain_xarray_reads_time_as_seconds_since_the_release(tmp_path):
    """``xr.open_dataset(run.nc)`` decoded time to 1970 dates, so ``sel(time=40)`` failed."""
    import xarray as xr

    out = tmp_path / "run.nc"
    assert main(["run", str(SECTION6), "--set", "grid.dx=50", "--set", "time.end=60",
                 "--set", "output.every=10", "-o", str(out), "-q"]) == 0
    with xr.open_dataset(out) as ds:
        assert ds["time"].dtype == np.float64 and ds["time"].attrs["units"] == "s"
        assert float(ds.h.sel(time=40, method="nearest").time) == 40.0
        assert float(ds.h.sel(time=44, method="nearest").time) == 40.0
        assert ds["time"].attrs["release_time"] == ds.attrs["release_time"]
        assert ds["peak_thickness"].attrs["cell_methods"] == "duration: maximum"
        assert float(ds["duration"]) == 60.0
        assert list(ds["duration_bounds"].values) == [0.0, 60.0]
