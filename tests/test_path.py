"""Runout along the avalanche path (avflow/output/path.py, `avflow path`, output.path).

Exact answers: on a plane with a straight path down the fall line, ``s`` of a cell is its
distance along the fall direction and the runout angle is the slope angle, whatever the
runout point. On a hairpin valley (a DEM built here around an analytic thalweg) the farthest
cell from the release, avflow's ``runout`` summary, is at the bend, far short of the
along-path runout, which must equal the analytic ``s`` of the farthest cell above the
threshold.
"""

import importlib.util
import json
import math

import numpy as np
import pytest
import xarray as xr

from avflow.cli import main
from avflow.output.path import (PathError, PathLine, PathSettings, RunPoints, analyse,
                                analyse_run, com_path, read_line)
from avflow.scenario import load_scenario, parse_scenario
import avflow
from conftest import REPO


# --- the line and the projection -----------------------------------------------------------


def test_projection_onto_a_line_is_exact_and_continues_beyond_its_ends():
    line = PathLine([0.0, 100.0, 100.0], [0.0, 0.0, 100.0])  # east, then north
    s, l = line.project([50.0, 120.0, 90.0, -30.0, 100.0, 130.0],
                        [10.0, 50.0, 150.0, -5.0, 200.0, 0.0])
    np.testing.assert_allclose(s, [50.0, 150.0, 250.0, -30.0, 300.0, 100.0])  # last: the corner
    # left of the direction of travel is positive
    np.testing.assert_allclose(l, [10.0, -20.0, 10.0, -5.0, 0.0, -30.0])
    x, y = line.at([50.0, 150.0, 250.0, -30.0])
    np.testing.assert_allclose(x, [50.0, 100.0, 100.0, -30.0])
    np.testing.assert_allclose(y, [0.0, 50.0, 150.0, 0.0])


def test_centre_of_mass_path_starts_at_the_top_of_the_release():
    cx = np.array([150.0, 150.0, 152.0, 200.0, 300.0, 301.0, 301.0])
    line = com_path(cx, np.full(cx.size, 100.0), top_x=105.0, top_y=40.0, spacing=20.0)
    np.testing.assert_allclose(line.x, [105.0, 150.0, 200.0, 300.0])
    s, l = line.project([105.0, 995.0], [40.0, 100.0])
    np.testing.assert_allclose(s, [0.0, 890.0])
    with pytest.raises(PathError, match="moved less than two cells"):
        com_path([1.0, 2.0], [0.0, 0.0], 0.0, 0.0, spacing=20.0)


def _plane_points(slope_deg, azimuth_deg, field):
    """A 10 m grid on a plane facing azimuth_deg, with a peak field given by a function of
    (x, y), a release disc at (150, 450)."""
    x = np.arange(5.0, 600.0, 10.0)
    X, Y = np.meshgrid(x, x)
    az = math.radians(azimuth_deg)
    d = np.array([math.sin(az), math.cos(az)])  # downslope, clockwise from north
    Z = 1000.0 - math.tan(math.radians(slope_deg)) * ((X - 300) * d[0] + (Y - 300) * d[1])
    released = (X - 150) ** 2 + (Y - 450) ** 2 <= 40.0**2
    f = field(X, Y)
    pts = RunPoints(X.ravel(), Y.ravel(), Z.ravel(),
                    {"peak_pressure": f.ravel(), "peak_speed": np.sqrt(f.ravel() / 2000.0),
                     "peak_thickness": f.ravel() / 1e3},
                    released.ravel(), 10.0, runout_threshold=0.01)
    return pts, d


def test_on_a_plane_the_runout_is_the_farthest_cell_down_the_fall_line_and_alpha_the_slope():
    """Exact: s = (x - x0) . d for a straight path down the fall line; alpha = the slope."""
    def pressure(X, Y):  # a tongue down the fall line, 2 kPa, fading to 0.5 kPa at its end
        along = ((X - 150) - (Y - 450)) / math.sqrt(2.0)
        across = ((X - 150) + (Y - 450)) / math.sqrt(2.0)
        return np.where((np.abs(across) < 40) & (along > -40) & (along < 400),
                        np.where(along < 300, 2000.0, 500.0), 0.0)

    pts, d = _plane_points(25.0, 135.0, pressure)
    start = np.array([150.0, 450.0]) - 100.0 * d
    line = PathLine([start[0], start[0] + 700 * d[0]], [start[1], start[1] + 700 * d[1]])
    r = analyse(pts, line)  # pressure >= 1 kPa
    proj = (pts.x - start[0]) * d[0] + (pts.y - start[1]) * d[1]
    above = pts.fields["peak_pressure"] >= 1000.0
    top = np.flatnonzero(pts.released)[np.argmax(pts.z[pts.released])]
    assert r.scalars["runout_s"] == pytest.approx(proj[above].max(), abs=1e-9)
    assert r.scalars["top_s"] == pytest.approx(proj[top], abs=1e-9)
    assert r.scalars["runout_length"] == pytest.approx(proj[above].max() - proj[top], abs=1e-9)
    assert r.scalars["runout_angle"] == pytest.approx(25.0, abs=1e-9)
    assert r.scalars["max_pressure"] == pytest.approx(2.0)
    # a lower threshold reaches the faded end of the tongue; thickness in m likewise
    low = analyse(pts, line, threshold=0.4)
    assert low.scalars["runout_s"] == pytest.approx(proj[pts.fields["peak_pressure"] >= 400].max())
    assert low.scalars["runout_s"] > r.scalars["runout_s"] + 50.0
    assert low.scalars["runout_angle"] == pytest.approx(25.0, abs=1e-9)
    thick = analyse(pts, line, field="thickness", threshold=1.5)
    assert thick.scalars["runout_s"] == pytest.approx(r.scalars["runout_s"])
    # a narrow band around the line keeps only the cells within width / 2 of it
    band = analyse(pts, line, width=20.0)
    assert np.all(np.abs(band.l[band.runout_index]) <= 10.0)
    # the cross-section maxima: 2 kPa along the tongue, nothing beyond its end
    prof = r.profile
    assert np.nanmax(prof["pressure"]) == pytest.approx(2.0)
    assert np.all(prof["pressure"][prof["s"] > proj[pts.fields["peak_pressure"] > 0].max()
                                    + 10] == 0.0)


# --- real runs -------------------------------------------------------------------------------

PLANE = """
name: plane-diagonal
terrain:
  kind: plane
  slope_deg: 25.0
  azimuth_deg: 135.0
  extent: {x: [0.0, 600.0], y: [0.0, 600.0]}
grid: {dx: 10.0}
release: {kind: cylinder, center: [150.0, 450.0], radius: 40.0, thickness: 5.0}
rheology: {law: coulomb, delta_deg: 20.0}
time: {end: 14.0, cfl: 0.5}
output: {every: 2.0}
"""


@pytest.fixture(scope="module")
def plane_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("plane")
    (folder / "plane.yaml").write_text(PLANE)
    out = folder / "plane.nc"
    assert main(["run", str(folder / "plane.yaml"), "-o", str(out)]) == 0
    return out


def _line_files(folder, xy):
    """The same line as CSV, GeoJSON and shapefile."""
    import shapefile

    (folder / "line.csv").write_text("id,x,y\n" + "".join(f"{k},{x},{y}\n"
                                                          for k, (x, y) in enumerate(xy)))
    (folder / "line.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {},
         "geometry": {"type": "LineString", "coordinates": [list(p) for p in xy]}}]}))
    with shapefile.Writer(str(folder / "line"), shapeType=shapefile.POLYLINE) as w:
        w.field("name", "C")
        w.line([[list(p) for p in xy]])
        w.record("path")
    return [folder / "line.csv", folder / "line.geojson", folder / "line.shp"]


def test_a_plane_run_along_its_fall_line(plane_run, tmp_path):
    """The run's runout point is the farthest cell down the fall line with peak pressure
    >= 1 kPa; alpha is the slope; the three line formats agree; the centre-of-mass track of
    a flow straight down the plane is that same line."""
    d = np.array([1.0, -1.0]) / math.sqrt(2.0)
    start = np.array([150.0, 450.0]) - 100.0 * d
    files = _line_files(tmp_path, [tuple(start), tuple(start + 800.0 * d)])
    with xr.open_dataset(plane_run, decode_times=False) as ds:
        X, Y = np.meshgrid(ds.x.values, ds.y.values)
        proj = (X - start[0]) * d[0] + (Y - start[1]) * d[1]
        expected = proj[ds.peak_pressure.values >= 1000.0].max()
        h0 = ds.h.isel(time=0).values
        bed = ds.bed_elevation.values
        top = np.argmax(np.where(h0 > 0, bed, -np.inf))
        results = [analyse_run(ds, PathSettings(line=str(f)))[1] for f in files]
        _, own = analyse_run(ds)
    for r in results:
        assert r.scalars["runout_s"] == pytest.approx(expected, abs=1e-6)
        assert r.scalars["runout_length"] == pytest.approx(expected - proj.ravel()[top], abs=1e-6)
        assert r.scalars["runout_angle"] == pytest.approx(25.0, abs=1e-6)
    assert own.line.source == "centre-of-mass track"
    assert own.scalars["runout_length"] == pytest.approx(results[0].scalars["runout_length"],
                                                         abs=0.5)
    assert own.scalars["runout_angle"] == pytest.approx(25.0, abs=0.01)


spec = importlib.util.spec_from_file_location("path_hairpin",
                                              REPO / "workflows" / "path_hairpin.py")
hairpin = importlib.util.module_from_spec(spec)
spec.loader.exec_module(hairpin)


def test_hairpin_valley_along_path_runout_against_the_farthest_cell(tmp_path):
    scenario = load_scenario(hairpin.write_case(tmp_path, end=70.0))
    ds = avflow.run(scenario)
    points, r = analyse_run(ds, PathSettings.from_scenario(scenario.output.path))
    s_exact, _ = hairpin.hairpin_sl(points.x, points.y)
    above = points.fields["peak_pressure"] >= 1000.0
    # the along-path runout: the analytic s of the farthest cell above 1 kPa (the line's
    # chords shorten the half circle by 0.1 m)
    assert r.scalars["runout_s"] == pytest.approx(s_exact[above].max(), abs=0.5)
    assert r.scalars["runout_x"] < 0 and r.scalars["runout_y"] > 0  # in the arm going west
    top = np.flatnonzero(points.released)[np.argmax(points.z[points.released])]
    length = s_exact[above].max() - s_exact[top]
    assert r.scalars["runout_length"] == pytest.approx(length, abs=0.5)
    drop = points.z[top] - points.z[r.runout_index]
    assert r.scalars["runout_angle"] == pytest.approx(math.degrees(math.atan2(drop, length)),
                                                      abs=0.05)
    # the run's headline runout is this one: along the scenario's path line
    assert float(ds["runout"]) == pytest.approx(r.scalars["runout_s"], abs=1e-9)
    assert ds.attrs["runout_path"] == "path line"
    # the farthest deposit cell from the release centroid lies near the bend: hundreds of
    # metres short of the path length, which it cannot see
    farthest = float(ds["reach_from_release_centroid"])
    assert farthest < 0.7 * length
    # ... and the straight-line distance from the top to the runout point is shorter still
    chord = math.hypot(r.scalars["runout_x"] - points.x[top], r.scalars["runout_y"] - points.y[top])
    assert chord < 0.5 * length


# --- command line, scenario block, ensembles -----------------------------------------------


def test_avflow_path_writes_the_table_and_the_figure(plane_run, tmp_path, capsys):
    assert main(["path", str(plane_run), "-o", str(tmp_path / "p")]) == 0
    out = capsys.readouterr().out
    assert "along the path (centre-of-mass track)" in out and "alpha 25.00 deg" in out
    for name in ("p.csv", "p.md", "p.png", "p_profile.csv"):
        assert (tmp_path / name).stat().st_size > 0
    import pandas as pd

    row = pd.read_csv(tmp_path / "p.csv").iloc[0]
    assert row["path_field"] == "pressure" and row["path_threshold"] == 1.0
    assert row["path_runout_angle"] == pytest.approx(25.0, abs=0.01)
    assert "| run | runout_s |" in (tmp_path / "p.md").read_text()
    # thickness, threshold in m
    assert main(["path", str(plane_run), "--field", "thickness", "--threshold", "0.5",
                 "-o", str(tmp_path / "t")]) == 0
    assert pd.read_csv(tmp_path / "t.csv").iloc[0]["path_threshold_units"] == "m"
    capsys.readouterr()
    assert main(["path", str(plane_run), "-q", "-o", str(tmp_path / "q")]) == 0
    assert capsys.readouterr().out == "" and (tmp_path / "q.csv").exists()  # --quiet
    # alpha-beta beside the dynamic angle: a plane never falls to 10 degrees
    assert main(["path", str(plane_run), "--alpha-beta", "austria", "-o",
                 str(tmp_path / "ab")]) == 0
    assert "alpha-beta (austria): no 10-degree point" in capsys.readouterr().out
    row = pd.read_csv(tmp_path / "ab.csv").iloc[0]
    assert row["path_ab_regression"] == "austria" and math.isnan(row["path_ab_beta"])
    assert "Austrian Alps" in (tmp_path / "ab.md").read_text()


@pytest.mark.parametrize("args, message", [
    (["--line", "nowhere.shp"], "nowhere.shp: no such file"),
    (["--threshold", "-1"], "threshold must be a number > 0"),
    (["--alpha-beta", "sweden"], "alpha-beta regression 'sweden'"),
])
def test_avflow_path_bad_input_is_one_line_exit_2(plane_run, tmp_path, capsys, args, message):
    args = [a if a != "nowhere.shp" else str(tmp_path / a) for a in args]
    assert main(["path", str(plane_run), *args, "-o", str(tmp_path / "p")]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "p.csv").exists()


def test_bad_line_files_are_one_line_errors(tmp_path):
    import shapefile

    (tmp_path / "two.geojson").write_text(json.dumps({"type": "MultiLineString", "coordinates": [
        [[0, 0], [1, 1]], [[2, 2], [3, 3]]]}))
    with pytest.raises(PathError, match="holds 2 lines"):
        read_line(tmp_path / "two.geojson")
    (tmp_path / "bad.csv").write_text("x,y\n0,0\n1,oops\n")
    with pytest.raises(PathError, match=r"bad.csv:3: y \(column 2\) is not a number: .oops."):
        read_line(tmp_path / "bad.csv")
    with shapefile.Writer(str(tmp_path / "pts"), shapeType=shapefile.POINT) as w:
        w.field("name", "C")
        w.point(1.0, 2.0)
        w.record("a")
    with pytest.raises(PathError, match="POINT shapes, not a line"):
        read_line(tmp_path / "pts.shp")
    with pytest.raises(PathError, match="must be a .shp, .geojson, .json, .csv file"):
        read_line(tmp_path / "line.kml")


def test_scenario_block_runs_with_avflow_run_and_leaves_the_hash_alone(tmp_path, capsys):
    _line_files(tmp_path, [(100.0, 500.0), (600.0, 0.0)])
    text = PLANE.replace("output: {every: 2.0}",
                         "output: {every: 2.0, path: {line: line.shp, field: thickness}}")
    (tmp_path / "s.yaml").write_text(text)
    plain = parse_scenario(PLANE)
    with_path = parse_scenario(text, base_dir=tmp_path)
    assert with_path.output.path.line == str(tmp_path / "line.shp")
    assert with_path.scenario_hash() == plain.scenario_hash()  # post-processing only
    assert main(["run", str(tmp_path / "s.yaml"), "-o", str(tmp_path / "s.nc")]) == 0
    out = capsys.readouterr().out
    assert "along the path (" in out and "thickness >=" in out
    assert (tmp_path / "s_path.png").is_file() and (tmp_path / "s_path.csv").is_file()
    # avflow path takes the file's scenario block (its line found beside the run file);
    # --line com forces the centre-of-mass track
    assert main(["path", str(tmp_path / "s.nc"), "-o", str(tmp_path / "again")]) == 0
    assert f"along the path ({tmp_path / 'line.shp'})" in capsys.readouterr().out
    assert main(["path", str(tmp_path / "s.nc"), "--line", "com", "-o", str(tmp_path / "c")]) == 0
    assert "along the path (centre-of-mass track): runout (thickness" in capsys.readouterr().out
    # a line file that is not there: refused at load, one line, exit 2, nothing run
    (tmp_path / "bad.yaml").write_text(text.replace("line.shp", "gone.shp"))
    assert main(["run", str(tmp_path / "bad.yaml"), "-o", str(tmp_path / "bad.nc")]) == 2
    err = capsys.readouterr().err
    assert "output.path.line" in err and "gone.shp" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "bad.nc").exists()


def test_a_profile_is_its_own_path(tmp_path):
    text = """
name: p
terrain: {kind: profile, length: 400.0, slope: {kind: constant, theta_deg: 30.0}}
grid: {dx: 5.0}
release: {kind: dam, position: 100.0, thickness: 10.0}
rheology: {law: coulomb, delta_deg: 20.0}
time: {end: 5.0}
"""
    (tmp_path / "x.csv").write_text("x,y\n0,0\n1,1\n")
    with pytest.raises(Exception, match="output.path.line: .*profile is its own path"):
        parse_scenario(text.replace("time: {end: 5.0}",
                                    "time: {end: 5.0}\noutput: {path: {line: x.csv}}"),
                       base_dir=tmp_path)
    ds = avflow.run(parse_scenario(text))
    _, r = analyse_run(ds)
    assert r.line.source == "the profile"
    assert r.scalars["runout_angle"] == pytest.approx(30.0, abs=1e-6)


def test_ensemble_records_the_path_per_member(tmp_path, capsys):
    from avflow.ensemble.orchestrate import run_ensemble
    from avflow.ensemble.spec import load_ensemble
    import pandas as pd

    (tmp_path / "base.yaml").write_text(PLANE.replace("end: 14.0", "end: 8.0"))
    (tmp_path / "ens.yaml").write_text(
        "name: e\nbase: base.yaml\nvary:\n  rheology.delta_deg: [18.0, 21.0, 24.0]\n")
    outdir = tmp_path / "ens"
    assert run_ensemble(load_ensemble(tmp_path / "ens.yaml"), outdir, workers=0).ok
    table = pd.read_csv(outdir / "summary.csv")
    assert table["path_runout_angle"].to_numpy() == pytest.approx([25.0] * 3, abs=0.01)
    assert table["path_runout_s"].is_monotonic_decreasing  # more friction, shorter
    assert set(table["path_source"]) == {"centre-of-mass track of member 0, delta_deg 18"}
    with xr.open_dataset(outdir / "ensemble.nc") as ens:
        assert ens["path_runout_s"].dims == ("realization",)
        assert ens["path_peak_pressure"].dims == ("realization", "path_s")
        assert ens.attrs["path_field"] == "pressure" and ens["path_x"].size >= 2
        np.testing.assert_allclose(ens["path_runout_s"], table["path_runout_s"])
        # alpha-beta beside each member's angle: a plane never falls to 10 degrees
        assert ens["path_ab_beta"].dims == ("realization",)
    assert table["path_ab_beta"].isna().all() and set(table["path_ab_regression"]) == {"norway"}
    assert main(["path", str(outdir)]) == 0
    assert "3 members along the path" in capsys.readouterr().out
    for name in ("path.csv", "path.md", "path.png", "path_profile.csv"):
        assert (outdir / name).is_file()
    again = pd.read_csv(outdir / "path.csv")  # the recorded path and settings: same answer
    np.testing.assert_allclose(again["path_runout_s"], table["path_runout_s"])
