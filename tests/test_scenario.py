"""Scenario files: the contract files load unchanged, bad input gives one clear error naming
file, line and field, YAML 1.1 traps are closed, hashes identify content, updates re-validate."""

import json
import os
import pickle
import re
from pathlib import Path

import pytest

from avflow.errors import AvflowError, ScenarioError
from avflow.scenario.schema import Scenario, load_scenario, parse_scenario

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("AVFLOW_SHARED", REPO.parent / "shared"))
CONTRACT = SHARED / "contract"
SCENARIOS = REPO / "scenarios"


def field(scenario, dotted):
    value = scenario
    for key in dotted.split("."):
        value = getattr(value, key)
    return value


@pytest.fixture(scope="module")
def contract():
    if not CONTRACT.is_dir():  # CI has it next to the checkout; a fresh clone does not
        pytest.skip(f"the external reference scenarios are not at {CONTRACT} (set "
                    "AVFLOW_SHARED): these tests check that they load unchanged")
    return CONTRACT


# --- the contract files --------------------------------------------------------------------

EXPECTED = {
    "seed_exponential_coulomb.yaml": {
        "name": "seed-exponential-coulomb-15", "terrain.kind": "profile",
        "terrain.length": 5500.0, "terrain.slope.kind": "exponential",
        "terrain.slope.theta0_deg": 35.0, "terrain.slope.a": 1750.0, "terrain.curvature": True,
        "grid.dx": 6.25, "grid.dy": None, "release.kind": "parabola", "release.center": 500.0,
        "release.half_length": 400.0, "release.max_thickness": 201.6,
        "release.volume_factor": 1.0, "rheology.law": "coulomb", "rheology.delta_deg": 15.0,
        "time.end": 300.0, "time.cfl": 0.5, "time.max_steps": 10_000_000,
        "output.every": 5.0, "output.stop_fraction": 1e-3, "output.runout_threshold": None,
        "boundary.x_min": "wall", "boundary.x_max": "wall", "physics.gravity": 9.81,
        "physics.dirac": True, "physics.density": 2000.0,
    },
    "seed_exponential_pouliquen.yaml": {
        "terrain.slope.theta0_deg": 35.0, "terrain.slope.a": 1750.0, "release.center": 500.0,
        "rheology.law": "pouliquen", "rheology.delta1_deg": 13.0, "rheology.delta2_deg": 20.0,
        "rheology.d": 1.5, "rheology.beta": 0.136, "output.every": 5.0,
    },
    "seed_dambreak_inclined.yaml": {
        "terrain.slope.kind": "constant", "terrain.slope.theta_deg": 5.0,
        "terrain.curvature": False, "grid.dx": 2.0, "release.kind": "dam",
        "release.position": 1000.0, "release.thickness": 1.0, "rheology.delta_deg": 1.0,
        "time.end": 35.0, "output.every": 35.0,
    },
    "plane_cylinder.yaml": {
        "terrain.kind": "plane", "terrain.slope_deg": 30.0, "terrain.azimuth_deg": 30.0,
        "terrain.extent.x": (0.0, 3000.0), "terrain.extent.y": (0.0, 3000.0),
        "terrain.elevation_at_center": 1000.0, "grid.dx": 10.0, "grid.dy": None,
        "release.kind": "cylinder", "release.center": (1000.0, 1800.0),
        "release.radius": 100.0, "release.thickness": 20.0, "rheology.delta_deg": 20.0,
        "time.end": 200.0, "output.every": 2.0,
    },
    "avakot_coulomb.yaml": {
        "terrain.kind": "dem", "terrain.nodata": "wall", "grid.dx": 5.0,
        "release.kind": "polygon", "release.thickness": None, "rheology.delta_deg": 20.0,
        "time.end": 400.0, "output.every": 5.0,
    },
}


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_contract_file_loads_unchanged_with_expected_values(contract, name):
    scenario = load_scenario(contract / name)
    for dotted, expected in EXPECTED[name].items():
        assert field(scenario, dotted) == expected, dotted
    assert scenario.source_path == str(contract / name)
    assert scenario.source_text == (contract / name).read_text()
    assert re.fullmatch(r"[0-9a-f]{16}", scenario.scenario_hash())
    again = parse_scenario(scenario.to_yaml())  # resolved YAML reads back to the same content
    assert again.model_dump() == scenario.model_dump()
    assert again.scenario_hash() == scenario.scenario_hash()


def test_data_paths_are_resolved_next_to_the_scenario_file():
    scenario = load_scenario(str(SCENARIOS / "avakot_coulomb.yaml"))  # str accepted too
    data = (REPO / "data/avaframe/avaKot").resolve()
    # compare resolved paths: the checkout may sit behind a symbolic link
    assert Path(scenario.terrain.path).resolve() == data / "avaKot.asc"
    assert Path(scenario.release.path).resolve() == data / "relKot.shp"


def test_ensemble_file_is_not_a_scenario():
    """base + vary belongs to the ensemble reader; as a scenario it fails clearly."""
    with pytest.raises(ScenarioError, match=r"seed_exponential_ensemble\.yaml:3:1: base: "
                                            r"unknown field"):
        load_scenario(SCENARIOS / "ensembles" / "seed_exponential_ensemble.yaml")


# --- one clear error per bad input ---------------------------------------------------------

BASE = """\
name: bad-cases
terrain:
  kind: profile
  length: 1000.0
  slope: {kind: constant, theta_deg: 20.0}
grid:
  dx: 5.0
release:
  kind: dam
  position: 200.0
  thickness: 10.0
rheology:
  law: coulomb
  delta_deg: 15.0
time:
  end: 100.0
  cfl: 0.5
"""

BAD = [  # id, text replaced in BASE, replacement, dotted field named, line, words in message
    ("typo", "  dx: 5.0", "  dxx: 5.0", "grid.dxx", 7, "did you mean 'dx'"),
    ("typo-flow", "  slope: {", "  slop: {", "terrain.slop", 5, "did you mean 'slope'"),
    ("wrong-type", "dx: 5.0", "dx: abc", "grid.dx", 7, "must be a number, got 'abc'"),
    ("yes-is-no-number", "dx: 5.0", "dx: yes", "grid.dx", 7, "must be a number"),
    ("bool-is-no-number", "dx: 5.0", "dx: true", "grid.dx", 7, "must be a number"),
    ("not-finite", "dx: 5.0", "dx: .inf", "grid.dx", 7, "finite"),
    ("negative-thickness", "thickness: 10.0", "thickness: -10.0", "release.thickness", 11,
     "must be > 0, got -10.0"),
    ("zero-thickness", "thickness: 10.0", "thickness: 0", "release.thickness", 11, "> 0"),
    ("angle-range", "delta_deg: 15.0", "delta_deg: 95.0", "rheology.delta_deg", 14,
     "must be in [0, 90) degrees, got 95.0"),
    ("unknown-law", "law: coulomb", "law: mohr", "rheology.law", 13,
     "known: coulomb, pouliquen, voellmy"),
    ("cfl", "cfl: 0.5", "cfl: 1.5", "time.cfl", 17, "(0, 1]: positivity of h needs it"),
    ("missing-block", "time:\n  end: 100.0\n  cfl: 0.5\n", "", "time", 1, "missing"),
    ("missing-field", "  end: 100.0\n", "", "time.end", 15, "missing"),
    ("pouliquen-order", "  law: coulomb\n  delta_deg: 15.0",
     "  law: pouliquen\n  delta1_deg: 25.0\n  delta2_deg: 20.0\n  d: 1.0",
     "rheology.delta1_deg", 14, "smaller than delta2_deg"),
    ("box-order", "  kind: dam\n  position: 200.0", "  kind: box\n  x: [300.0, 100.0]",
     "release.x", 10, "min < max"),
    ("box-y-on-profile", "  kind: dam\n  position: 200.0",
     "  kind: box\n  x: [100.0, 300.0]\n  y: [0.0, 10.0]", "release.y", 11, "profile"),
    ("cylinder-on-profile", "  kind: dam\n  position: 200.0",
     "  kind: cylinder\n  center: [0.0, 0.0]\n  radius: 5.0", "release.kind", 9, "2D terrain"),
    ("dy-on-profile", "  dx: 5.0", "  dx: 5.0\n  dy: 5.0", "grid.dy", 8, "profile"),
    ("missing-dem", "  kind: profile\n  length: 1000.0\n  slope: {kind: constant, theta_deg: 20.0}",
     "  kind: dem\n  path: nowhere.asc", "terrain.path", 4, "file not found"),
    ("dem-suffix", "  kind: profile\n  length: 1000.0\n  slope: {kind: constant, theta_deg: 20.0}",
     "  kind: dem\n  path: dem.png", "terrain.path", 4, ".asc"),
    ("duplicate-key", "  dx: 5.0", "  dx: 5.0\n  dx: 6.0", "grid.dx", 8,
     "duplicate key (first written at line 7)"),
    ("bool-flag", "name: bad-cases", "name: bad-cases\nphysics: {dirac: no}", "physics.dirac", 2,
     "true or false"),
    ("boundary", "name: bad-cases", "name: bad-cases\nboundary: walls", "boundary", 2,
     "'wall', 'outflow'"),
    ("voellmy-both", "  law: coulomb\n  delta_deg: 15.0",
     "  law: voellmy\n  delta_deg: 15.0\n  mu: 0.3\n  xi: 500.0", "rheology.mu", 15, "not both"),
    ("table-slope", "{kind: constant, theta_deg: 20.0}",
     "{kind: table, x: [0.0, 10.0, 5.0], theta_deg: [30.0, 20.0, 10.0]}", "terrain.slope.x", 5,
     "strictly increasing"),
    ("empty-name", "name: bad-cases", "name: ''", "name", 1, "empty"),
]


@pytest.mark.parametrize("old, new, dotted, line, words",
                         [case[1:] for case in BAD], ids=[case[0] for case in BAD])
def test_bad_input_gives_one_clear_error(tmp_path, old, new, dotted, line, words):
    assert old in BASE
    path = tmp_path / "bad.yaml"
    path.write_text(BASE.replace(old, new))
    with pytest.raises(ScenarioError) as caught:
        load_scenario(path)
    err = caught.value
    first = str(err).splitlines()[0]
    assert first.startswith(f"{path}:{line}:"), first
    assert f": {dotted}: " in first and words in first, first
    assert (err.field, err.line, err.path) == (dotted, line, str(path))
    assert len(str(err).splitlines()) == 1, str(err)  # one problem, not a cascade


@pytest.mark.parametrize("text, line, words", [
    ("name: x\ngrid: {dx: [5.0}\n", 2, "YAML syntax error"),
    ("name: x\n  grid: 1\n", 2, "YAML syntax error"),
    ("", 1, "empty"),
    ("# only a comment\n", 1, "empty"),
    ("- a\n- b\n", 1, "expected a mapping"),
], ids=["flow", "indent", "empty", "comment-only", "list"])
def test_unreadable_yaml_names_file_and_line(tmp_path, text, line, words):
    path = tmp_path / "broken.yaml"
    path.write_text(text)
    with pytest.raises(ScenarioError, match=rf"^{re.escape(str(path))}:{line}:\d+: .*{words}"):
        load_scenario(path)


def test_missing_scenario_file_names_the_path(tmp_path):
    with pytest.raises(ScenarioError, match="nowhere.yaml: scenario file not found") as caught:
        load_scenario(tmp_path / "nowhere.yaml")
    assert isinstance(caught.value, AvflowError)


def test_several_problems_are_reported_one_per_line_in_file_order():
    text = BASE.replace("dx: 5.0", "dx: -1.0").replace("cfl: 0.5", "cfl: 2.0")
    with pytest.raises(ScenarioError) as caught:
        parse_scenario(text, source_path="many.yaml")
    lines = str(caught.value).splitlines()
    assert [p.field for p in caught.value.problems] == ["grid.dx", "time.cfl"]
    assert lines[0].endswith("many.yaml:7:3: grid.dx: must be > 0, got -1.0")
    assert ":17:3: time.cfl: " in lines[1]


def test_cross_block_checks():
    plane = BASE.replace(
        "  kind: profile\n  length: 1000.0\n  slope: {kind: constant, theta_deg: 20.0}",
        "  kind: plane\n  slope_deg: 20.0\n  extent: {x: [0.0, 1000.0], y: [0.0, 100.0]}")
    with pytest.raises(ScenarioError, match=r":9:3: release.kind: a 'dam' release needs a "
                                            r"'profile' terrain"):
        parse_scenario(plane)
    box = plane.replace("  kind: dam\n  position: 200.0", "  kind: box\n  x: [0.0, 100.0]")
    with pytest.raises(ScenarioError, match=r":8:1: release.y: required on a 2D terrain"):
        parse_scenario(box)
    scenario = parse_scenario(box.replace("x: [0.0, 100.0]", "x: [0.0, 100.0]\n  y: [0, 50]"))
    assert scenario.release.y == (0.0, 50.0)


def test_voellmy_needs_exactly_one_friction():
    text = BASE.replace("  law: coulomb\n  delta_deg: 15.0", "  law: voellmy\n  xi: 500.0")
    with pytest.raises(ScenarioError, match=r":12:1: rheology: needs a friction"):
        parse_scenario(text)
    assert parse_scenario(text.replace("xi: 500.0", "xi: 500.0\n  mu: 0.2")).rheology.mu == 0.2


def test_error_after_validation_points_at_the_field(tmp_path):
    path = tmp_path / "ok.yaml"
    path.write_text(BASE)
    scenario = load_scenario(path)
    err = ScenarioError.at(scenario, "release.thickness", "no mass on the domain")
    assert str(err) == f"{path}:11:3: release.thickness: no mass on the domain"
    err = ScenarioError.at(scenario, "physics.gravity", "not written: closest parent")
    assert (err.line, err.column) == (1, 1)
    copy = pickle.loads(pickle.dumps(err))  # dask ships errors between processes
    assert str(copy) == str(err) and copy.field == "physics.gravity"


# --- YAML 1.1 traps ------------------------------------------------------------------------

def test_yaml_scalars_follow_the_core_schema():
    text = BASE.replace("dx: 5.0", "dx: 1e-3").replace("end: 100.0", "end: 2E5") \
        .replace("cfl: 0.5", "cfl: .5").replace("thickness: 10.0", "thickness: 010") \
        .replace("name: bad-cases", "name: no\ndescription: on 2024-01-01 at 1:30")
    scenario = parse_scenario(text)
    assert scenario.grid.dx == 1e-3 and isinstance(scenario.grid.dx, float)
    assert scenario.time.end == 2e5 and scenario.time.cfl == 0.5
    assert scenario.release.thickness == 10.0  # decimal, not octal 8
    assert scenario.name == "no"  # not False
    assert scenario.description == "on 2024-01-01 at 1:30"
    with pytest.raises(ScenarioError, match="name: must be a string, got true"):
        parse_scenario(BASE.replace("name: bad-cases", "name: true"))


# --- identity ------------------------------------------------------------------------------

def test_hash_is_stable_and_follows_content(tmp_path):
    path = tmp_path / "a.yaml"
    path.write_text(BASE)
    reference = load_scenario(path).scenario_hash()
    assert load_scenario(path).scenario_hash() == reference
    assert parse_scenario(BASE.replace("delta_deg: 15.0", "delta_deg: 16.0")).scenario_hash() \
        != reference
    reformatted = ("# the same scene, written differently\n"
                   "time: {cfl: 0.5, end: 100}\n"
                   "rheology: {delta_deg: 15, law: coulomb}   # friction\n"
                   "release: {kind: dam, thickness: 10, position: 200}\n"
                   "grid: {dx: 5}\n"
                   "terrain:\n  kind: profile\n  slope:\n    kind: constant\n"
                   "    theta_deg: 20\n  length: 1000\n"
                   "name: bad-cases\n"
                   "output: {every: 5.0}   # the default, written out\n")
    assert parse_scenario(reformatted).scenario_hash() == reference


def test_hash_counts_data_files_by_content_not_location(tmp_path):
    text = BASE.replace(
        "  kind: profile\n  length: 1000.0\n  slope: {kind: constant, theta_deg: 20.0}",
        "  kind: dem\n  path: dem.asc").replace(
        "  kind: dam\n  position: 200.0", "  kind: cylinder\n  center: [10.0, 10.0]\n"
                                          "  radius: 5.0")
    hashes = []
    for checkout in ("one", "two"):
        folder = tmp_path / checkout
        folder.mkdir()
        (folder / "dem.asc").write_text("ncols 2\nnrows 2\n")
        (folder / "s.yaml").write_text(text)
        scenario = load_scenario(folder / "s.yaml")
        assert scenario.terrain.path == str(folder / "dem.asc")
        hashes.append(scenario.scenario_hash())
    assert hashes[0] == hashes[1]
    (tmp_path / "two" / "dem.asc").write_text("ncols 3\nnrows 2\n")
    assert load_scenario(tmp_path / "two" / "s.yaml").scenario_hash() != hashes[0]


# --- updates -------------------------------------------------------------------------------

def test_with_updates_on_dotted_paths():
    base = load_scenario(SCENARIOS / "seed_exponential_coulomb15.yaml")
    member = base.with_updates({"release.volume_factor": 2.0, "rheology.delta_deg": 14.0})
    assert member.release.volume_factor == 2.0 and member.rheology.delta_deg == 14.0
    assert member.release.center == base.release.center
    assert base.rheology.delta_deg == 15.0  # the base is untouched
    assert member.source_path == base.source_path
    assert member.scenario_hash() != base.scenario_hash()
    assert parse_scenario(member.source_text).scenario_hash() == member.scenario_hash()
    assert base.with_updates({}).scenario_hash() == base.scenario_hash()


def test_with_updates_replaces_a_whole_block():
    base = load_scenario(SCENARIOS / "seed_exponential_coulomb15.yaml")
    member = base.with_updates({"rheology": {"law": "pouliquen", "delta1_deg": 13.0,
                                             "delta2_deg": 20.0, "d": 1.0}})
    assert member.rheology.law == "pouliquen" and member.rheology.beta == 0.136
    assert member.with_updates({"rheology.d": 2.0}).rheology.d == 2.0


def test_with_updates_acts_as_editing_the_file():
    base = parse_scenario(BASE)
    assert base.output.every == 5.0  # default: time.end / 20
    assert base.with_updates({"time.end": 200.0}).output.every == 10.0
    outflow = parse_scenario(BASE + "boundary: outflow\n").with_updates({"boundary.x_min": "wall"})
    assert (outflow.boundary.x_min, outflow.boundary.x_max) == ("wall", "outflow")
    assert base.with_updates({"physics.gravity": 1.62}).physics.gravity == 1.62


@pytest.mark.parametrize("updates, dotted, words", [
    ({"rheology.delt_deg": 1.0}, "rheology.delt_deg", "did you mean 'delta_deg'"),
    ({"rheolgy.delta_deg": 1.0}, "rheolgy", "did you mean 'rheology'"),
    ({"grid.dx.value": 1.0}, "grid.dx.value", "unknown field"),
    ({"rheology.delta_deg": 95.0}, "rheology.delta_deg", "must be in [0, 90) degrees"),
    ({"release.thickness": -1.0}, "release.thickness", "must be > 0"),
])
def test_with_updates_errors_name_the_field(updates, dotted, words):
    base = parse_scenario(BASE, source_path="base.yaml")
    with pytest.raises(ScenarioError) as caught:
        base.with_updates(updates)
    assert caught.value.field == dotted and words in str(caught.value)
    assert f"base.yaml: {dotted}: " in str(caught.value)


# --- schema --------------------------------------------------------------------------------

def test_json_schema_file_is_up_to_date():
    written = json.loads((REPO / "scenarios" / "schema.json").read_text())
    assert written == Scenario.model_json_schema(), "run avflow.scenario.schema.write_json_schema"
