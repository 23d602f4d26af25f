"""Command line and Python habits (issue 12 item 4): ``--set``, ``--quiet``, ``--version``;
compile time apart from the time loop; where an ensemble runs, its final time, member times
kept on resume; ``avflow.run_ensemble`` from a file, a mapping or scenarios; the report's
failed-members table and line labels; the 2D demo ensemble's spread."""

import io
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import xarray as xr

import avflow
from avflow.cli import main
from avflow.ensemble.orchestrate import ProgressLine, run_ensemble
from avflow.ensemble.spec import EnsembleError, load_ensemble
from avflow.terrain.raster import write_asc
from conftest import REPO, SCENARIOS
from test_dem import tilted

SECTION6 = SCENARIOS / "seed_exponential_coulomb15.yaml"
PLANE = SCENARIOS / "plane_box_2d.yaml"


def run_cli(argv, capsys):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def dem_folder(tmp_path: Path) -> Path:
    """A scenario next to its DEM, named relative to it (the tilted plane of test_dem)."""
    folder = tmp_path / "scene"
    folder.mkdir()
    write_asc(folder / "dem.asc", *tilted())
    (folder / "s.yaml").write_text("""name: tilted
terrain: {kind: dem, path: dem.asc}
grid: {dx: 5.0}
release: {kind: cylinder, center: [1050, 2070], radius: 20, thickness: 2}
rheology: {law: coulomb, delta_deg: 10.0}
time: {end: 2.0}
output: {every: 1.0}
""")
    return folder / "s.yaml"


def coarse_ensemble(tmp_path: Path, vary: str, dx: float = 50.0) -> Path:
    """The section-6 scene at a coarse dx (members of a few hundredths of a second)."""
    (tmp_path / "base.yaml").write_text(SECTION6.read_text().replace("dx: 6.25", f"dx: {dx}"))
    path = tmp_path / "ens.yaml"
    path.write_text(f"base: base.yaml\nvary:\n{vary}")
    return path


# --- --set, --quiet, --version -------------------------------------------------------------


def test_set_changes_fields_and_data_paths_still_resolve_next_to_the_scenario(
        tmp_path, monkeypatch, capsys):
    scenario = dem_folder(tmp_path)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # dem.asc is not here: it is found next to s.yaml
    code, out, err = run_cli(["run", "../scene/s.yaml", "-o", "out.nc", "--set", "grid.dx=10",
                              "--set", "rheology.delta_deg=15", "--set",
                              "output.release_time=2024-01-01T06:00:00Z", "--quiet"], capsys)
    assert code == 0, err
    assert out == ""  # --quiet: no summary line, no "wrote"
    ds = avflow.open_run(elsewhere / "out.nc")
    assert float(ds["x"][1] - ds["x"][0]) == 10.0
    written = avflow.load_scenario(scenario).with_updates(
        {"grid.dx": 10.0, "rheology.delta_deg": 15.0,
         "output.release_time": "2024-01-01T06:00:00Z"})
    assert ds.attrs["scenario_hash"] == written.scenario_hash()
    assert ds["time"].attrs["release_time"] == "2024-01-01T06:00:00Z"


@pytest.mark.parametrize("item, words", [
    ("grid.dxx=3", "--set grid.dxx=3: unknown field (did you mean 'dx'?)"),
    ("grid.dx=abc", "--set grid.dx=abc: must be a number, got 'abc'"),
    ("grid.dx", "--set grid.dx: expected KEY=VALUE"),
    ("rheology.delta_deg=[1", "--set rheology.delta_deg: the value '[1' is not a YAML value"),
])
def test_set_errors_are_one_line_naming_the_key(tmp_path, capsys, item, words):
    scenario = dem_folder(tmp_path)
    code, out, err = run_cli(["run", scenario, "-o", tmp_path / "o.nc", "--set", item], capsys)
    assert code == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and words in err, err
    assert not (tmp_path / "o.nc").exists()


def test_set_on_an_ensemble_changes_the_base_not_a_varied_field(tmp_path, capsys):
    path = coarse_ensemble(tmp_path, "  rheology.delta_deg: [15.0, 20.0]\n")
    ens = load_ensemble(path, overrides={"time.end": 50.0})
    assert [m.scenario.time.end for m in ens.members] == [50.0, 50.0]
    assert [m.scenario.rheology.delta_deg for m in ens.members] == [15.0, 20.0]
    with pytest.raises(EnsembleError, match="--set rheology.delta_deg: this ensemble varies"):
        load_ensemble(path, overrides={"rheology.delta_deg": 18.0})
    code, out, err = run_cli(["ensemble", path, "-o", tmp_path / "out", "--set",
                              "rheology={law: coulomb, delta_deg: 18}"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "--set rheology: this ensemble varies rheology.delta_deg" in err
    assert not (tmp_path / "out").exists()


def test_version(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out.strip() == f"avflow {avflow.__version__}"


# --- wall time and compile time --------------------------------------------------------------


def test_wall_time_leaves_out_the_first_compile(tmp_path):
    """A first run in a fresh Numba cache spends seconds compiling: that is compile_time,
    on the summary line apart from the time loop's wall_time."""
    env = {**os.environ, "AVFLOW_CACHE_DIR": str(tmp_path / "kernel-cache")}
    done = subprocess.run([sys.executable, "-m", "avflow.cli", "run", str(PLANE), "-o",
                           str(tmp_path / "p.nc"), "--set", "time.end=5"], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    line = done.stdout.splitlines()[0]
    loop, compiling = re.search(r"steps at order [12] in ([0-9.]+) s \(\+ ([0-9.]+) s compiling\)",
                                line).groups()
    ds = avflow.open_run(tmp_path / "p.nc")
    assert float(ds["compile_time"]) > 1.0  # compiled, not loaded from a cache
    assert float(ds["wall_time"]) < 0.25 * float(ds["compile_time"])
    assert (loop, compiling) == (f"{float(ds['wall_time']):.2f}",
                                 f"{float(ds['compile_time']):.2f}")
    # said while it happened: what, once per machine and version, where, how long
    said = [l for l in done.stderr.splitlines() if l.startswith("avflow: compil")]
    assert said[0].startswith("avflow: compiling the grid kernel at order 2 (MUSCL-Hancock) with Coulomb "
                              "friction (once per machine and avflow version; kept in "
                              f"{tmp_path / 'kernel-cache'}) ..."), done.stderr
    assert re.fullmatch(r"avflow: compiled in \d+ s", said[1]) and len(said) == 2, said


# --- where an ensemble runs; its times ------------------------------------------------------


def test_a_few_short_members_start_no_cluster_and_resume_keeps_member_times(tmp_path):
    path = coarse_ensemble(tmp_path, "  rheology.delta_deg: [14.0, 16.0, 18.0, 20.0]\n")
    ens = load_ensemble(path)
    stream = io.StringIO()
    progress = ProgressLine(len(ens.members), stream=stream, live=True)
    outcome = run_ensemble(ens, tmp_path / "out", progress=progress)
    assert outcome.ok and outcome.ran == 4
    assert (outcome.where, outcome.workers, outcome.startup) == ("here", 0, 0.0)
    text = stream.getvalue()
    assert "the first took" in text and "running the other 3 here too" in text
    # the final line's time is the progress line's last time
    shown = re.findall(r"members, 0 failed \(\s*([0-9.]+) s\)", text)[-1]
    assert shown == f"{outcome.elapsed:.1f}"
    first = pd.read_csv(tmp_path / "out" / "summary.csv")
    assert np.isfinite(first["member_time"]).all()
    again = run_ensemble(ens, tmp_path / "out", workers=0)
    assert (again.ran, again.reused) == (0, 4)
    resumed = pd.read_csv(tmp_path / "out" / "summary.csv")
    np.testing.assert_array_equal(resumed["member_time"].values, first["member_time"].values)


def test_ensemble_command_says_where_and_quiet_says_nothing(tmp_path, capsys):
    path = coarse_ensemble(tmp_path, "  rheology.delta_deg: [15.0, 20.0]\n")
    code, out, err = run_cli(["ensemble", path, "-o", tmp_path / "a"], capsys)
    assert code == 0
    assert "avflow: 2 members, the first took" in err and "here too" in err  # on stderr
    assert re.search(r"2 run, 0 reused, 0 failed \([0-9.]+ s, here\)", out)
    code, out, err = run_cli(["ensemble", path, "-o", tmp_path / "b", "--quiet"], capsys)
    assert (code, out, err) == (0, "", "")


# --- avflow.run_ensemble from Python ------------------------------------------------------


def test_run_ensemble_takes_a_file_a_mapping_or_scenarios(tmp_path):
    path = coarse_ensemble(tmp_path, "  rheology.delta_deg: [15.0, 20.0]\n")
    from_file = avflow.run_ensemble(path, tmp_path / "file", workers=0, quiet=True)
    assert from_file.sizes["realization"] == 2
    base = avflow.load_scenario(tmp_path / "base.yaml")
    from_dict = avflow.run_ensemble(
        {"base": base, "vary": {"rheology.delta_deg": [15.0, 20.0]}}, tmp_path / "dict",
        workers=0, quiet=True)
    assert list(from_dict["scenario_hash"].values) == list(from_file["scenario_hash"].values)
    np.testing.assert_array_equal(from_dict["runout"].values, from_file["runout"].values)
    scenarios = [base.with_updates({"rheology.delta_deg": d}) for d in (15.0, 20.0)]
    from_list = avflow.run_ensemble(scenarios, tmp_path / "list", workers=0, quiet=True)
    assert list(from_list["scenario_hash"].values) == list(from_file["scenario_hash"].values)
    np.testing.assert_array_equal(from_list["rheology_delta_deg"].values, [15.0, 20.0])
    assert from_list.attrs["varied"] == "rheology.delta_deg"


def test_help_of_run_explains_its_arguments():
    doc = avflow.run.__doc__
    for words in ("progress(t, t_end)", "max_memory", "with_updates", "RunFailed",
                  'sel(time=40, method="nearest")'):
        assert words in doc, words


# --- the report --------------------------------------------------------------------------


def test_failed_members_table_shows_the_varied_fields(tmp_path):
    """Members varying release.path (text): the table of failed members names the file."""
    import shapefile

    scenario = dem_folder(tmp_path)
    for name, thickness in (("good", 1.0), ("huge", 1e5)):
        w = shapefile.Writer(str(tmp_path / "scene" / name), shapeType=shapefile.POLYGON)
        w.field("thickness", "N", decimal=3)
        w.poly([[[1030, 2050], [1070, 2050], [1070, 2090], [1030, 2090], [1030, 2050]]])
        w.record(thickness)
        w.close()
    base = avflow.load_scenario(scenario)
    members = [base.with_updates({"release": {"kind": "polygon", "path": f"{n}.shp"}})
               for n in ("good", "huge")]
    ds = avflow.run_ensemble(members, tmp_path / "out", workers=0, quiet=True, report=True)
    assert list(ds["status"].values) == ["completed", "failed"]
    text = (tmp_path / "out" / "report.md").read_text()
    table = text.split("## Failed members", 1)[1].split("##", 1)[0]
    header, _, row = table.strip().splitlines()[:3]
    assert "release.path" in header
    assert str(tmp_path / "scene" / "huge.shp") in row and "more than the map" in row


def test_line_plots_over_two_parameters_are_labelled():
    from avflow.ensemble.report import _line_label

    ds = xr.Dataset(coords={"release_volume_factor": ("realization", [0.5, 2.0], {
        "long_name": "scenario field release.volume_factor"})})
    assert _line_label(ds, ("coulomb", 2.0), ["release_volume_factor"], False) == \
        "release.volume_factor = 2"
    assert _line_label(ds, ("pouliquen", None), ["release_volume_factor"], True) == \
        "pouliquen, release.volume_factor = NaN"


def test_the_2d_demo_ensemble_shows_a_real_spread(tmp_path):
    """scenarios/ensembles/plane_box_2d_ensemble.yaml: every member stops in the open, at a
    runout of its own (all 9 hit the wall at 850.3 m before), but for the cell size: at
    order 2 two members (22 degrees with half the volume, 24 with all of it) stop in the same
    farthest cell, 405.3 m out. (Measured by the farthest deposit cell: the runout along the
    path needs 1 kPa, which the two members whose friction is steepest against their volume
    never reach: NaN, said so.)"""
    ens = load_ensemble(SCENARIOS / "ensembles" / "plane_box_2d_ensemble.yaml")
    outcome = run_ensemble(ens, tmp_path / "out", workers=0,
                           progress=ProgressLine(len(ens.members), quiet=True))
    table = outcome.table
    assert set(table["status"]) == {"at_rest"} and (table["runout_truncated"] == 0).all()
    reach = table["reach_from_release_centroid"].to_numpy()
    assert len(np.unique(np.round(reach))) >= 8
    assert reach.max() > 2.5 * reach.min()
    assert np.isfinite(table["runout"].to_numpy()).sum() >= 7
    with xr.open_dataset(tmp_path / "out" / "ensemble.nc", decode_times=False) as ds:
        x_max = float(ds["x"].max())
        reach = ds["peak_thickness"].where(ds["peak_thickness"] > 1e-3)
        assert float(reach["x"].where(reach.notnull()).max()) < x_max - 200.0  # no wall hit
