"""Secondary release areas: an area releases when the flow reaches it and not before, its
volume counts in the mass balance (to round-off), an area never reached releases nothing."""

import math

import numpy as np
import pytest

from avflow.cli import main
from avflow.scenario.schema import load_scenario
from avflow.simulation.runner import simulate
from conftest import SCENARIOS

# the block of plane_box_runout_2d stops some 400 m below its release (x 150-250 m): an area
# at x 500-600 m is reached, one at x 1800-1900 m never is
REACHED = {"kind": "box", "x": [500.0, 600.0], "y": [350.0, 450.0], "thickness": 2.0}
NEVER = {"kind": "box", "x": [1800.0, 1900.0], "y": [350.0, 450.0], "thickness": 3.0}


def _scenario(areas, **more):
    base = load_scenario(SCENARIOS / "plane_box_runout_2d.yaml")
    return base.with_updates({"secondary_release": {"areas": areas, "check_every": 1.0},
                              **more})


@pytest.fixture(scope="module")
def run():
    return simulate(_scenario([REACHED, NEVER]))


def _volume(run, h):
    return math.fsum(h * run.terrain.mesh.cell_area)


def _area_cells(run, spec):
    x, y = run.terrain.cell_xy()
    return np.flatnonzero((x >= spec["x"][0]) & (x <= spec["x"][1])
                          & (y >= spec["y"][0]) & (y <= spec["y"][1]))


def test_the_reached_area_releases_and_the_other_does_not(run):
    sec = run.secondary
    assert sec.names == ["secondary_release.areas.0", "secondary_release.areas.1"]
    assert 0.0 < sec.time[0] < run.state.t
    assert math.isnan(sec.time[1]) and sec.volume[1] == 0.0
    cells = _area_cells(run, REACHED)
    want = math.fsum(2.0 * run.terrain.mesh.cell_area[cells])
    assert sec.volume[0] == pytest.approx(want, rel=1e-14)
    assert run.summary["secondary_release_volume"] == sec.volume[0]


def test_mass_is_primary_plus_secondary_to_round_off(run):
    v0 = run.summary["release_volume"]
    v_sec = run.secondary.volume[0]
    t_sec = run.secondary.time[0]
    assert run.summary["mass_balance_error"] < 1e-13
    for t, h in zip(run.snapshots.time, run.snapshots.h):
        want = v0 + (v_sec if t >= t_sec else 0.0)
        assert _volume(run, h) == pytest.approx(want, rel=1e-13), t
    assert run.summary["deposit_volume"] == pytest.approx(v0 + v_sec, rel=1e-13)


def test_it_releases_when_the_flow_reaches_it_and_not_before(run):
    # the same run without the areas, a snapshot at every check: the first snapshot with
    # flow (h above the dry threshold) on the area is the area's release time
    alone = simulate(_scenario([NEVER], **{"output.every": 1.0}))
    cells = _area_cells(alone, REACHED)
    dry = alone.thresholds["dry"]
    reached = [t for t, h in zip(alone.snapshots.time, alone.snapshots.h)
               if np.any(h[cells] > dry)]
    assert reached, "the flow should reach the area"
    assert run.secondary.time[0] == pytest.approx(reached[0], abs=1e-9)
    # before then the released mass was not on the map
    before = [h for t, h in zip(run.snapshots.time, run.snapshots.h) if t < reached[0]]
    assert before and all(_volume(run, h) == pytest.approx(run.summary["release_volume"],
                                                           rel=1e-13) for h in before)


def test_an_area_never_reached_releases_nothing():
    run = simulate(_scenario([NEVER]))
    assert math.isnan(run.secondary.time[0])
    assert run.summary["secondary_release_volume"] == 0.0
    assert run.summary["deposit_volume"] == pytest.approx(run.summary["release_volume"],
                                                          rel=1e-13)
    assert np.all(run.state.h[_area_cells(run, NEVER)] == 0.0)


def test_a_polygon_file_releases_polygon_by_polygon(tmp_path):
    import pyogrio
    import shapely

    boxes = [shapely.box(500.0, 350.0, 600.0, 450.0), shapely.box(1800.0, 350.0, 1900.0, 450.0)]
    path = tmp_path / "secrel.gpkg"
    pyogrio.raw.write(path, shapely.to_wkb(boxes), [np.array([2.0, 3.0])], ["thickness"],
                      geometry_type="Polygon", driver="GPKG")
    run = simulate(_scenario([{"kind": "polygon", "path": str(path)}]))
    assert run.secondary.names == ["secondary_release.areas.0.0", "secondary_release.areas.0.1"]
    assert run.secondary.time[0] > 0 and math.isnan(run.secondary.time[1])
    assert run.summary["mass_balance_error"] < 1e-13


def test_cli_summary_and_file_say_the_volume(tmp_path, capsys):
    import xarray as xr

    scenario = tmp_path / "s.yaml"
    scenario.write_text((SCENARIOS / "plane_box_runout_2d.yaml").read_text() + (
        "secondary_release:\n  areas:\n    - {kind: box, x: [500, 600], y: [350, 450], "
        "thickness: 2.0}\n"))
    out = tmp_path / "run.nc"
    assert main(["run", str(scenario), "-o", str(out)]) == 0
    assert "+ secondary 2.128e+04" in capsys.readouterr().out
    ds = xr.open_dataset(out, decode_times=False)
    assert float(ds["secondary_release_volume"]) == pytest.approx(2.128e4, rel=1e-3)
    assert float(ds["mass_balance_error"]) < 1e-13


def test_an_area_off_the_map_is_refused(tmp_path, capsys):
    scenario = tmp_path / "s.yaml"
    scenario.write_text((SCENARIOS / "plane_box_runout_2d.yaml").read_text() + (
        "secondary_release:\n  areas:\n    - {kind: box, x: [5000, 6000], y: [350, 450], "
        "thickness: 2.0}\n"))
    assert main(["run", str(scenario), "-o", str(tmp_path / "run.nc")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "secondary_release.areas.0" in err[0]
    assert list(tmp_path.iterdir()) == [scenario]


@pytest.mark.parametrize("areas, field, words", [
    ([], "secondary_release.areas", "give at least one area"),
    ([{"kind": "parabola", "center": 1.0, "half_length": 2.0, "max_thickness": 1.0}],
     "secondary_release.areas.0", "'box', 'cylinder', 'polygon', 'raster'"),
    ([{"kind": "box", "x": [1.0, 2.0], "thickness": 1.0}], "secondary_release.areas.0.y",
     "required on a 2D terrain"),
])
def test_bad_areas_are_one_message(areas, field, words):
    from avflow.errors import ScenarioError

    with pytest.raises(ScenarioError) as caught:
        _scenario(areas)
    text = str(caught.value)
    assert len(text.splitlines()) == 1 and f"{field}: " in text and words in text, text
