"""Issue 8, items 3 and 4: a blow-up is never a success; values outside physical sense and
runs that would not fit the memory are refused before anything large is allocated."""

import time

import numpy as np
import pytest

from avflow.cli import main
from avflow.errors import AvflowError, RunFailed, ScenarioError
from avflow.numerics import stepping
from avflow.numerics.solver import Solver
from avflow.scenario.schema import MAX_SNAPSHOTS, load_scenario, parse_scenario
from avflow.scenario.yamlio import MAX_ALIAS_VALUES
from avflow.simulation import runner
from avflow.simulation.resources import check_resources, estimate, parse_bytes
from conftest import REPO, SCENARIOS

DAMBREAK = (SCENARIOS / "seed_dambreak_flat_dx20.yaml").read_text()  # 100 cells, 138 snapshots


def write(tmp_path, text, name="s.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def run_cli(argv, capsys):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


# --- item 3: values outside physical sense, refused at load ----------------------------------


def test_release_thickness_1e200_is_refused_at_load(tmp_path, capsys):
    path = write(tmp_path, DAMBREAK.replace("thickness: 1.0}", "thickness: 1e200}"))
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    e = err.value
    assert (e.field, e.line) == ("release.thickness", 10)
    assert "1e+200 m thick" in e.message and "2000 m" in e.message
    code, out, err_text = run_cli(["run", path, "-o", tmp_path / "o.nc"], capsys)
    assert code == 2 and len(err_text.strip().splitlines()) == 1
    assert f"{path.name}:10:" in err_text and not (tmp_path / "o.nc").exists()


@pytest.mark.parametrize("old, new, field, words", [
    ("thickness: 1.0}", "thickness: 10.0, volume_factor: 300.0}", "release.thickness",
     "volume_factor 300"),
    ("length: 2000.0", "length: 2.0e7", "terrain.length", "1e+07 m"),
    ("dx: 20.0", "dx: 1500.0", "grid.dx", "at least 2 cells"),
    ("every: 1.0", "every: 1.0e-5", "output.every", f"{MAX_SNAPSHOTS} a run stores"),
])
def test_sizes_outside_physical_sense_name_the_field(old, new, field, words):
    with pytest.raises(ScenarioError) as err:
        parse_scenario(DAMBREAK.replace(old, new), "s.yaml")
    assert err.value.field == field and words in err.value.message
    assert str(err.value).startswith("s.yaml:") and len(str(err.value).splitlines()) == 1


def test_plane_release_thicker_than_its_extent_is_refused():
    text = (SCENARIOS / "plane_box_2d.yaml").read_text().replace("thickness: 10.0",
                                                                 "thickness: 5000.0")
    with pytest.raises(ScenarioError, match="thicker than the map is long") as err:
        parse_scenario(text, "p.yaml")
    assert err.value.field == "release.thickness"


# --- item 3: a non-finite state ends the run as failed ---------------------------------------


def poison(monkeypatch, where="h"):
    """Solver.advance as usual, then a NaN in the state (or an infinite outflow)."""
    advance = Solver.advance

    def advance_then_nan(self, state, t_target, **kw):
        status = advance(self, state, t_target, **kw)
        if state.t >= 5.0:
            if where == "outflow":
                state.stats[stepping.ST_OUTFLOW] = np.inf
            else:
                getattr(state, where)[3] = np.nan
        return status

    monkeypatch.setattr(Solver, "advance", advance_then_nan)


@pytest.mark.parametrize("where", ["h", "hu"])
def test_non_finite_state_is_a_failed_run(monkeypatch, where):
    poison(monkeypatch, where)
    with pytest.raises(RunFailed) as err:
        runner.simulate(parse_scenario(DAMBREAK, "s.yaml"))
    message = str(err.value)
    assert len(message.splitlines()) == 1
    assert f"{where} not finite in 1 of 100 cells" in message and "t = 5 s" in message
    assert err.value.result.status == "failed" and err.value.exit_code == 1


def test_non_finite_mass_balance_is_a_failed_run(monkeypatch):
    poison(monkeypatch, "outflow")
    with pytest.raises(RunFailed, match="mass balance is not finite"):
        runner.simulate(parse_scenario(DAMBREAK.replace("every: 1.0", "every: 137.0")))


def test_no_positive_step_is_a_failed_run(monkeypatch):
    monkeypatch.setattr(Solver, "advance", lambda self, state, t, **kw: "failed")
    with pytest.raises(RunFailed, match="no time step kept h >= 0"):
        runner.simulate(parse_scenario(DAMBREAK))


def test_blow_up_exits_1_with_one_line_and_no_file(tmp_path, monkeypatch, capsys):
    poison(monkeypatch)
    path = write(tmp_path, DAMBREAK)
    out = tmp_path / "o.nc"
    code, stdout, err = run_cli(["run", path, "-o", out], capsys)
    assert code == 1 and stdout == ""
    assert len(err.strip().splitlines()) == 1 and "run failed at t = 5 s" in err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["s.yaml"]


def test_blown_up_ensemble_member_is_recorded_failed_without_a_file(tmp_path, monkeypatch):
    from avflow.ensemble.orchestrate import run_member

    poison(monkeypatch)
    row = run_member(DAMBREAK, str(tmp_path / "m.nc"))
    assert row["status"] == "failed" and "h not finite" in row["error"]
    assert "\n" not in row["error"] and not (tmp_path / "m.nc").exists()


# --- item 4: YAML alias bombs --------------------------------------------------------------


def alias_bomb(levels=6, width=10):
    """A "billion laughs" file: ``width ** levels`` values from a few hundred bytes."""
    lines = ["a0: &a0 [" + ", ".join(['"lol"'] * width) + "]"]
    lines += [f"a{k}: &a{k} [" + ", ".join([f"*a{k - 1}"] * width) + "]"
              for k in range(1, levels)]
    return "name: bomb\n" + "\n".join(lines) + "\n"


def test_yaml_alias_bomb_is_refused_quickly(tmp_path, capsys):
    path = write(tmp_path, alias_bomb())  # 1e6 values from 400 bytes
    started = time.perf_counter()
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    assert time.perf_counter() - started < 2.0
    assert f"more than {MAX_ALIAS_VALUES} values" in err.value.message
    assert err.value.path == str(path) and err.value.line is not None
    code, _, err_text = run_cli(["run", path, "-o", tmp_path / "o.nc"], capsys)
    assert code == 2 and len(err_text.strip().splitlines()) == 1
    assert "aliases (*name) expand to more than" in err_text


def test_yaml_alias_bomb_in_an_ensemble_file_is_refused(tmp_path):
    from avflow.ensemble.spec import load_ensemble

    path = write(tmp_path, alias_bomb().replace("name: bomb", "name: bomb\nbase: x.yaml"),
                 "ens.yaml")
    with pytest.raises(ScenarioError, match=f"more than {MAX_ALIAS_VALUES} values") as err:
        load_ensemble(path)
    assert err.value.path == str(path)


def test_recursive_yaml_alias_is_one_error():
    with pytest.raises(ScenarioError, match="alias refers to a collection that contains it"):
        parse_scenario("name: x\na: &x [1, *x]\n", "r.yaml")


def test_a_few_aliases_still_work():
    text = DAMBREAK.replace("theta_deg: 0.0}", "theta_deg: &zero 0.0}").replace(
        "delta_deg: 0.0}", "delta_deg: *zero}")
    assert text != DAMBREAK and parse_scenario(text).rheology.delta_deg == 0.0


# --- item 4: memory estimated before anything is allocated ---------------------------------


def test_parse_bytes():
    assert parse_bytes("8G") == 8 * 2**30 and parse_bytes("512MiB") == 512 * 2**20
    assert parse_bytes("1.5k") == 1536 and parse_bytes(1000) == 1000
    assert parse_bytes("none") is None
    for bad in ("8X", "-1G", "0", "lots"):
        with pytest.raises(AvflowError):
            parse_bytes(bad)


def dem_scenario(tmp_path, dx):
    dem = REPO / "data" / "avaframe" / "avaKot" / "avaKot.asc"
    return write(tmp_path, name=f"dem_{dx}.yaml", text=f"""name: tiny-cells
terrain: {{kind: dem, path: {dem}}}
grid: {{dx: {dx}}}
release: {{kind: polygon, path: {dem.with_name('relKot.shp')}}}
rheology: {{law: coulomb, delta_deg: 20.0}}
time: {{end: 400.0}}
""")


def test_dem_resampled_to_1cm_is_refused_before_allocation(tmp_path, monkeypatch, capsys):
    def no_terrain(*args, **kw):
        raise AssertionError("the terrain was built")

    monkeypatch.setattr(runner, "build_terrain", no_terrain)
    path = dem_scenario(tmp_path, 0.01)
    code, _, err = run_cli(["run", path, "-o", tmp_path / "o.nc", "--max-memory", "4G"],
                           capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert f"{path.name}:3:" in err and "grid.dx:" in err
    assert "218899 x 257881 = 5.64e+10 cells" in err and "TiB" in err and "4.0 GiB" in err
    assert not (tmp_path / "o.nc").exists()


def test_default_limit_is_half_the_machine_or_the_environment(tmp_path, monkeypatch):
    path = dem_scenario(tmp_path, 0.01)
    with pytest.raises(ScenarioError, match="half of this machine's"):  # 51 TiB of mesh
        check_resources(load_scenario(path))
    monkeypatch.setenv("AVFLOW_MAX_MEMORY", "1M")
    scenario = load_scenario(dem_scenario(tmp_path, 50.0))
    with pytest.raises(ScenarioError, match=r"AVFLOW_MAX_MEMORY=1M"):
        check_resources(scenario)
    monkeypatch.setenv("AVFLOW_MAX_MEMORY", "none")
    assert check_resources(load_scenario(path)).cells == 218899 * 257881


def test_too_many_snapshots_for_the_memory_is_refused(tmp_path, capsys):
    """avflow.run holds every snapshot (it returns them as a Dataset); avflow run streams
    them to its file (tests/test_streamed_output.py): one in memory at a time."""
    path = write(tmp_path, DAMBREAK.replace("every: 1.0", "every: 0.01"))  # 13 701 snapshots
    with pytest.raises(ScenarioError) as err:
        runner.simulate(load_scenario(path), max_memory="10M")
    message = str(err.value)
    assert len(message.splitlines()) == 1 and err.value.field == "output.every"
    assert "13701 snapshots" in message and "10.0 MiB" in message
    assert check_resources(load_scenario(path), "10M", streamed=True).snapshots == 13701
    code, _, err = run_cli(["run", path, "-o", tmp_path / "o.nc", "--max-memory", "lots"],
                           capsys)
    assert code == 2 and err.startswith("avflow: error: --max-memory:")
    # with a streamed run too, the mesh alone can be too large: grid.dx, exit 2
    code, _, err = run_cli(["run", path, "-o", tmp_path / "o.nc", "--max-memory", "50K"],
                           capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "grid.dx:" in err and "one snapshot, the others streamed to the file" in err
    assert not (tmp_path / "o.nc").exists()


def test_estimates_follow_the_mesh(tmp_path):
    plane = parse_scenario((SCENARIOS / "plane_box_2d.yaml").read_text())
    est = estimate(plane)
    assert (est.kind, est.shape, est.cells, est.snapshots) == ("grid", (100, 20), 2000, 13)
    tri = parse_scenario((SCENARIOS / "plane_cylinder_triangles.yaml").read_text())
    assert estimate(tri).kind == "triangles"
    assert estimate(tri).cells == runner.prepare(tri)[0].n_cells  # no refinement there
    assert estimate(parse_scenario(DAMBREAK)).cells == 100


def test_ensemble_members_are_checked_before_any_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("AVFLOW_MAX_MEMORY", "none")  # restored after: the CLI sets it
    out = tmp_path / "ens"
    code, _, err = run_cli(["ensemble", SCENARIOS / "ensembles" / "plane_box_2d_ensemble.yaml",
                            "-o", out, "--workers", "0", "--max-memory", "100K"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "100.0 KiB" in err
    assert not out.exists()


def test_release_thicker_than_a_dem_is_refused_before_the_run(tmp_path):
    path = dem_scenario(tmp_path, 50.0)
    path.write_text(path.read_text().replace("relKot.shp}", "relKot.shp, thickness: 1.0e5}"))
    with pytest.raises(ScenarioError, match="100000 m thick, more than the map's") as err:
        runner.prepare(load_scenario(path))
    assert err.value.field == "release" and err.value.line == 4
