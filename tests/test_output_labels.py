"""Outputs that say what they hold: u and v are the horizontal projection of the velocity
along the bed (and the file says how to get the bed speed back), the summary line gives the
share of the volume still moving whatever the status, the ensemble command names the
members that reached the map's edge, and a single-law ensemble has no by_law.png."""

import math

import numpy as np
import pytest
import xarray as xr

from avflow.cli import main, summary_line
from avflow.output.dataset import to_dataset
from avflow.scenario.schema import load_scenario, parse_scenario
from avflow.simulation.runner import simulate
from conftest import SCENARIOS


@pytest.fixture(scope="module")
def plane_run():
    """plane_box_2d (25 degree plane facing east, Coulomb 20 degrees) stopped at 10 s, in
    full flow."""
    text = (SCENARIOS / "plane_box_2d.yaml").read_text().replace("end: 60.0", "end: 10.0")
    result = simulate(parse_scenario(text))
    return result, to_dataset(result)


def test_u_v_are_the_horizontal_projection_and_say_so(plane_run):
    result, ds = plane_run
    for name in ("u", "v"):
        assert "horizontal projection" in ds[name].attrs["long_name"]
        assert "sqrt(u^2 + v^2 + w^2)" in ds[name].attrs["comment"]
    assert float(ds.time[-1]) == 10.0 and result.status == "completed"
    # the bed speed by the formula of the comment, from the file's u, v and bed ...
    u, v = ds.u.isel(time=-1).values, ds.v.isel(time=-1).values
    dx = float(ds.x[1] - ds.x[0])
    dy = float(ds.y[1] - ds.y[0])
    zy, zx = np.gradient(ds.bed_elevation.values, dy, dx)
    bed_speed = np.sqrt(u ** 2 + v ** 2 + (u * zx + v * zy) ** 2)
    # ... is the solver's speed along the bed, |(hu, hv)| / h in the bed's frame
    s = result.state
    with np.errstate(invalid="ignore", divide="ignore"):
        solver = np.where(s.h > 0, np.hypot(s.hu, s.hv) / s.h, 0.0)
    solver = result.terrain.to_grid(solver)
    wet = np.nan_to_num(ds.h.isel(time=-1).values) > 0.01
    assert wet.sum() > 50
    np.testing.assert_allclose(bed_speed[wet], solver[wet], rtol=1e-9)
    # and hypot(u, v) is short of it by cos(25 degrees) where the flow runs down the x axis
    moving = wet & (bed_speed > 1.0)
    ratio = np.hypot(u, v)[moving] / bed_speed[moving]
    assert np.median(ratio) == pytest.approx(math.cos(math.radians(25.0)), rel=1e-6)


def test_summary_line_says_how_much_still_moves(plane_run):
    _, ds = plane_run
    share = 100 * float(ds["moving_volume_end"]) / float(ds["release_volume"])
    assert share > 50  # a run ended by time.end in full flow
    line = summary_line(ds)
    assert f"{share:.0f}% of the volume still moving" in line, line
    rest = ds.copy()
    rest.attrs.update(status="at_rest", ended_by="")
    rest["moving_volume_end"] = rest["release_volume"] * 3e-4
    assert "at_rest (0.03% of the volume still moving)" in summary_line(rest)
    rest["moving_volume_end"] = rest["release_volume"] * 0.0
    assert "at_rest (0% of the volume still moving)" in summary_line(rest)


SHORT_DEM_ENSEMBLE = """name: short-trough
base: base.yaml
vary:
  rheology.delta_deg: [14.0, 30.0]
"""


def test_ensemble_names_edge_members_and_draws_no_by_law_for_one_law(tmp_path, capsys):
    """test_calibration's trough cut at x = 1000 m (32 degrees, easing to flat from 600 m),
    Coulomb 14 and 30 degrees: at 14 degrees the deposit reaches the lower edge, at 30 it
    stops well before it."""
    from avflow.terrain.raster import write_asc

    x = np.arange(0, 1000 + 10, 20.0)
    y = np.arange(0, 400 + 10, 20.0)
    slope = np.tan(np.radians(32)) * 0.5 * (1 + np.cos(np.pi * np.clip((x - 600) / 400, 0, 1)))
    z = -np.concatenate([[0], np.cumsum(0.5 * (slope[1:] + slope[:-1]) * 20.0)])
    X, Y = np.meshgrid(x, y)
    write_asc(tmp_path / "dem.asc", np.broadcast_to(z - z.min(), X.shape)
              + 0.02 * (Y - 200) ** 2 / 200, x, y, None)
    (tmp_path / "base.yaml").write_text(
        "name: short\nterrain: {kind: dem, path: dem.asc}\ngrid: {dx: 20.0}\n"
        "release: {kind: box, x: [100.0, 200.0], y: [150.0, 250.0], thickness: 4.0}\n"
        "rheology: {law: coulomb, delta_deg: 20.0}\ntime: {end: 200.0, cfl: 0.5}\n"
        "output: {every: 10.0}\n")
    (tmp_path / "ens.yaml").write_text(SHORT_DEM_ENSEMBLE)
    out = tmp_path / "out"
    code = main(["ensemble", str(tmp_path / "ens.yaml"), "-o", str(out), "--workers", "0"])
    stdout = capsys.readouterr().out
    table = __import__("pandas").read_csv(out / "summary.csv")
    cut = table[table["runout_truncated"] == 1]
    assert code == 0 and list(cut["realization"]) == [0], table
    assert ("1 member(s) reached the map's edge (runout a lower bound: enlarge the map): "
            "0 (rheology.delta_deg=14)") in stdout, stdout
    assert main(["report", str(out)]) == 0
    text = (out / "report.md").read_text()
    assert "1 member(s): 0 (rheology.delta_deg=14)" in text, text
    assert "by_law" not in text and not (out / "report" / "by_law.png").exists()
    # the moving share of every member, in the table and the report
    share = 100 * table["moving_volume_end"] / table["release_volume"]
    assert np.isfinite(share).all()
    assert "still moving at the end (% of the volume)" in text


def test_runouts_and_angles_are_named_by_what_they_measure(plane_run):
    """The runout is along the path at the pressure limit, with its alpha, in the summary
    line, the title and the path analysis alike; the distance from the release centroid
    keeps its own name."""
    from avflow.output.maps import _title

    _, ds = plane_run
    line = summary_line(ds)
    where = f"along the {ds.attrs['runout_path']} ({ds.attrs['runout_limit']})"
    assert f"runout {float(ds.runout):.1f} m {where}" in line
    title = _title(ds)
    assert f"runout {float(ds.runout):.0f} m {where}" in title
    assert f"alpha {float(ds.runout_angle):.1f}°" in title
    # the path analysis gives the same runout, and the distance from the release centroid
    from avflow.output.path import analyse_run, summary_line as path_line

    _, res = analyse_run(ds)
    assert res.scalars["runout_s"] == float(ds.runout)
    reach = float(ds.reach_from_release_centroid)
    text = path_line(res, reach)
    assert "m from the top of the release, alpha" in text, text
    assert (f"(reach_from_release_centroid, the farthest deposit cell from the release "
            f"centroid: {reach:.1f} m)") in text, text
