"""Ensembles: expansion, dask runs equal to single runs, CF output, resume, failures, bad files,
a real scheduler losing a worker; and Voellmy's steady uniform flow (issue 3)."""

import math
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pandas as pd
import pytest
import xarray as xr
import yaml

from avflow.cli import main
from avflow.ensemble.spec import DEFAULT_THRESHOLDS, EnsembleError, load_ensemble, parse_ensemble
from avflow.ensemble.orchestrate import cluster_scenario, run_ensemble
from avflow.output.dataset import to_dataset
from avflow.ensemble.report import write_report
from avflow.simulation.runner import simulate
from avflow.scenario.schema import load_scenario, parse_scenario
from conftest import REPO, SCENARIOS
from test_cli_output import compliance_errors

SECTION6 = SCENARIOS / "seed_exponential_coulomb15.yaml"
ENSEMBLE = SCENARIOS / "ensembles" / "seed_exponential_ensemble.yaml"  # the contract's, here
SUMMARIES = ("runout", "time_to_stop", "deposit_max_thickness", "deposit_length",
             "deposit_volume", "mass_balance_error")


def coarse_base(tmp_path, dx=25.0):
    """The section-6 scene (scenarios/) on a coarser grid, next to the ensemble file."""
    text = SECTION6.read_text()
    path = tmp_path / "base.yaml"
    path.write_text(text.replace("dx: 6.25", f"dx: {dx}"))
    return path


def write(tmp_path, text, name="ens.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


# =========================================================================================
# The section-6 ensemble (scenarios/ensembles/) on a LocalCluster with two worker processes
# =========================================================================================


@pytest.fixture(scope="module")
def section6_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("section6") / "out"
    started = time.perf_counter()
    code = main(["ensemble", str(ENSEMBLE), "-o", str(out), "--workers", "2"])
    return code, out, time.perf_counter() - started


def test_section6_ensemble_runs_on_two_workers(section6_run):
    code, out, _ = section6_run
    assert code == 0
    ens = load_ensemble(ENSEMBLE)
    assert len(ens.members) == 21
    files = sorted(p.name for p in (out / "members").iterdir())
    assert files == sorted(f"{m.scenario_hash}.nc" for m in ens.members)
    table = pd.read_csv(out / "summary.csv")
    assert list(table["realization"]) == list(range(21))
    assert set(table["status"]) == {"at_rest"}
    assert not (out / "failures.csv").exists()
    with xr.open_dataset(out / "ensemble.nc", decode_times=False) as ds:
        assert ds["realization"].attrs["standard_name"] == "realization"
        assert list(ds["law"].values) == ["coulomb"] * 12 + ["pouliquen"] * 9
        assert list(ds["release_volume_factor"].values[:3]) == [0.5, 1.0, 2.0]
        np.testing.assert_array_equal(ds["rheology_d"].values[12:], np.repeat([1.0, 1.5, 2.0], 3))
        assert np.isnan(ds["rheology_d"].values[:12]).all()
        for name in SUMMARIES + ("wall_time",):
            assert ds[name].dims == ("realization",) and "units" in ds[name].attrs
            np.testing.assert_array_equal(ds[name].values, table[name].values)
        assert list(ds["status"].values) == ["at_rest"] * 21
        # Twice the volume goes farther, for every law.
        runout = ds["runout"].values.reshape(7, 3)
        assert (np.diff(runout, axis=1) > 0).all()


def test_ensemble_members_equal_single_runs_bit_for_bit(section6_run, tmp_path):
    _, out, _ = section6_run
    ens = load_ensemble(ENSEMBLE)
    ds = xr.open_dataset(out / "ensemble.nc", decode_times=False)
    # Member 4 (Coulomb 15 degrees, volume x1) is the base scenario itself: same hash,
    # and `avflow run` of that file gives the same numbers to the bit.
    base = load_scenario(SECTION6)
    assert ens.members[4].scenario_hash == base.scenario_hash()
    assert main(["run", str(SECTION6), "-o", str(tmp_path / "single.nc")]) == 0
    single = xr.open_dataset(tmp_path / "single.nc", decode_times=False)
    member = xr.open_dataset(out / "members" / f"{base.scenario_hash()}.nc", decode_times=False)
    for name in SUMMARIES:
        assert float(ds[name][4]) == float(single[name]) == float(member[name]), name
    np.testing.assert_array_equal(member["h"].values, single["h"].values)
    # A Pouliquen member with twice the volume, rerun here from its resolved scenario.
    m = ens.members[20]
    assert (m.scenario.rheology.law, m.scenario.rheology.d, m.scenario.release.volume_factor
            ) == ("pouliquen", 2.0, 2.0)
    result = simulate(parse_scenario(m.scenario.source_text))
    for name in SUMMARIES:
        assert float(ds[name][20]) == result.summary[name], name
    np.testing.assert_array_equal(ds["deposit_thickness"].values[20],
                                  result.state.h.astype(np.float32))


def test_ensemble_and_member_files_are_cf_compliant(section6_run, tmp_path):
    _, out, _ = section6_run
    shutil.copy(out / "ensemble.nc", tmp_path / "ensemble.nc")
    member = next((out / "members").iterdir())
    shutil.copy(member, tmp_path / "member.nc")
    assert compliance_errors(tmp_path / "ensemble.nc") == []
    assert compliance_errors(tmp_path / "member.nc") == []


def test_report_of_profile_ensemble(section6_run, tmp_path):
    _, out, _ = section6_run
    shutil.copytree(out, tmp_path / "out")
    assert main(["report", str(tmp_path / "out")]) == 0
    text = (tmp_path / "out" / "report.md").read_text()
    for fig in ("vs_release_volume_factor.png", "vs_rheology_delta_deg.png", "by_law.png",
                "deposit_profiles.png"):
        assert f"report/{fig}" in text
        assert (tmp_path / "out" / "report" / fig).stat().st_size > 10_000
    assert "None: every member succeeded." in text


def test_resume_skips_done_members(section6_run, tmp_path, capsys):
    _, out, _ = section6_run
    shutil.copytree(out, tmp_path / "out")
    ens = load_ensemble(ENSEMBLE)
    members = tmp_path / "out" / "members"
    removed = [ens.members[i].scenario_hash for i in (3, 17)]
    for h in removed:
        (members / f"{h}.nc").unlink()
    (members / f"{ens.members[5].scenario_hash}.nc").write_bytes(b"truncated")  # not complete
    kept = {p.name: p.stat().st_mtime_ns for p in members.iterdir()
            if p.name != f"{ens.members[5].scenario_hash}.nc"}
    outcome = run_ensemble(ens, tmp_path / "out", workers=0)
    assert (outcome.ran, outcome.reused, outcome.failed) == (3, 18, 0)
    for name, mtime in kept.items():
        assert (members / name).stat().st_mtime_ns == mtime  # not rewritten
    again = run_ensemble(ens, tmp_path / "out", workers=0)
    assert (again.ran, again.reused) == (0, 21)
    original = pd.read_csv(out / "summary.csv")
    for name in SUMMARIES:
        np.testing.assert_array_equal(again.table[name].values, original[name].values)


def test_contract_ensemble_runs_unchanged(contract_dir, section6_run, tmp_path):
    """../shared/contract/seed_exponential_ensemble.yaml, unchanged: the same 21 members as
    the project's copy (scenarios/ensembles/), and the same numbers to the bit."""
    contract = load_ensemble(contract_dir / "seed_exponential_ensemble.yaml")
    ours = load_ensemble(ENSEMBLE)
    assert [m.updates for m in contract.members] == [m.updates for m in ours.members]
    out = tmp_path / "out"
    assert main(["ensemble", str(contract_dir / "seed_exponential_ensemble.yaml"), "-o",
                 str(out), "--workers", "0"]) == 0
    table = pd.read_csv(out / "summary.csv")
    expected = pd.read_csv(section6_run[1] / "summary.csv")
    assert set(table["status"]) == {"at_rest"} and len(table) == 21
    for name in SUMMARIES:
        np.testing.assert_array_equal(table[name].values, expected[name].values)


# =========================================================================================
# Expansion
# =========================================================================================


def test_cartesian_expansion_mixes_whole_rheology_blocks():
    ens = load_ensemble(ENSEMBLE)
    assert ens.varied == ["rheology", "release.volume_factor"]
    laws = [m.scenario.rheology.law for m in ens.members]
    assert laws == ["coulomb"] * 12 + ["pouliquen"] * 9
    assert [m.scenario.release.volume_factor for m in ens.members[:6]] == [0.5, 1, 2] * 2
    assert ens.members[13].scenario.rheology.d == 1.0 and ens.members[13].updates == {
        "rheology": {"law": "pouliquen", "delta1_deg": 13.0, "delta2_deg": 20.0, "d": 1.0,
                     "beta": 0.136}, "release.volume_factor": 1.0}
    assert len({m.scenario_hash for m in ens.members}) == 21
    assert ens.thresholds == DEFAULT_THRESHOLDS
    # The release volume is the base volume times the factor.
    base_v = simulate(ens.members[1].scenario.with_updates({"time.end": 1e-3})).summary
    half_v = simulate(ens.members[0].scenario.with_updates({"time.end": 1e-3})).summary
    assert half_v["release_volume"] == pytest.approx(0.5 * base_v["release_volume"], rel=1e-14)


def test_latin_hypercube_sample_is_reproducible(tmp_path):
    base = coarse_base(tmp_path)
    text = f"""
base: {base.name}
vary:
  rheology.delta_deg: [14.0, 20.0]
sample:
  n: 8
  seed: 42
  ranges:
    release.volume_factor: [0.5, 2.0]
    terrain.slope.theta0_deg: [30.0, 40.0]
thresholds: [2.0, 0.5]
"""
    a = parse_ensemble(text, tmp_path / "a.yaml")
    b = load_ensemble(write(tmp_path, text))
    assert len(a.members) == 16 and a.thresholds == (0.5, 2.0)
    assert [m.updates for m in a.members] == [m.updates for m in b.members]
    assert [m.scenario_hash for m in a.members] == [m.scenario_hash for m in b.members]
    vf = np.array([m.updates["release.volume_factor"] for m in a.members[:8]])
    theta = np.array([m.updates["terrain.slope.theta0_deg"] for m in a.members[:8]])
    # Latin hypercube: one point in each of the n strata of every range.
    assert sorted(np.floor((vf - 0.5) / 1.5 * 8).astype(int)) == list(range(8))
    assert sorted(np.floor((theta - 30.0) / 10.0 * 8).astype(int)) == list(range(8))
    # The sample is crossed with every vary combination, applied after it.
    assert [m.updates["release.volume_factor"] for m in a.members[8:]] == list(vf)
    assert {m.scenario.rheology.delta_deg for m in a.members[8:]} == {20.0}
    other = parse_ensemble(text.replace("seed: 42", "seed: 43"), tmp_path / "a.yaml")
    assert [m.updates for m in other.members] != [m.updates for m in a.members]


# =========================================================================================
# Failures, bad files
# =========================================================================================


def test_failing_member_is_recorded_and_others_finish(tmp_path, capsys):
    base = coarse_base(tmp_path)
    # A release centred beyond the end of the profile passes validation but puts no mass
    # on the mesh: those members raise when they start.
    ens = write(tmp_path, f"""
base: {base.name}
vary:
  release.center: [500.0, 9000.0]
  rheology.delta_deg: [15.0, 20.0]
""")
    out = tmp_path / "out"
    code = main(["ensemble", str(ens), "-o", str(out), "--workers", "1"])
    assert code == 1
    err = capsys.readouterr().err
    failed_lines = [line for line in err.splitlines() if "failed:" in line]
    assert len(failed_lines) == 2 and all("release" in line for line in failed_lines)
    assert "member 2 " in err and "member 3 " in err
    table = pd.read_csv(out / "summary.csv")
    assert list(table["status"]) == ["at_rest", "at_rest", "failed", "failed"]
    assert table["error"].fillna("").str.contains("no mass").tolist() == [False, False, True,
                                                                          True]
    failures = pd.read_csv(out / "failures.csv")
    assert list(failures["realization"]) == [2, 3]
    assert len(list((out / "members").iterdir())) == 2
    with xr.open_dataset(out / "ensemble.nc", decode_times=False) as ds:
        assert list(ds["status"].values) == ["at_rest", "at_rest", "failed", "failed"]
        assert np.isnan(ds["runout"].values[2:]).all() and np.isfinite(ds["runout"][:2]).all()
        assert ds.attrs["failed_members"] == 2
    write_report(out)
    report = (out / "report.md").read_text()
    assert "## Failed members" in report and "no mass" in report


BAD = {
    "unknown dotted path": ("vary:\n  rheology.delta_dg: [14.0, 15.0]\n",
                            "vary.rheology.delta_dg", "unknown field"),
    "empty list": ("vary:\n  release.volume_factor: []\n", "vary.release.volume_factor",
                   "non-empty list"),
    "not a list": ("vary:\n  release.volume_factor: 2.0\n", "vary.release.volume_factor",
                   "must be a list"),
    "range min > max": ("sample:\n  n: 4\n  ranges:\n    rheology.delta_deg: [20.0, 12.0]\n",
                        "sample.ranges.rheology.delta_deg", "min < max"),
    "n <= 0": ("sample:\n  n: 0\n  ranges:\n    rheology.delta_deg: [12.0, 20.0]\n",
               "sample.n", "positive integer"),
    "member fails validation": ("vary:\n  rheology.delta_deg: [15.0, 95.0]\n",
                                "vary.rheology.delta_deg.1", "member 1"),
    "bad block in a list": ("vary:\n  rheology:\n    - {law: coulomb, delta_deg: 15.0}\n"
                            "    - {law: pouliquen, delta1_deg: 13.0}\n",
                            "vary.rheology.1", "rheology.delta2_deg: required"),
    "unknown top-level key": ("varry:\n  rheology.delta_deg: [15.0]\n", "varry",
                              "did you mean 'vary'"),
    "no variation": ("thresholds: [1.0]\n", None, "needs 'vary:'"),
    "bad threshold": ("vary:\n  rheology.delta_deg: [15.0]\nthresholds: [1.0, -1.0]\n",
                      "thresholds.1", "positive"),
    "repeated member": ("vary:\n  rheology.delta_deg: [15.0, 15.0]\n", "vary",
                        "same scenario"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_ensemble_file_one_clear_error_before_any_member(case, tmp_path, capsys):
    body, field, message = BAD[case]
    base = coarse_base(tmp_path)
    path = write(tmp_path, f"name: bad\nbase: {base.name}\n{body}", "bad_ensemble.yaml")
    out = tmp_path / "out"
    assert main(["ensemble", str(path), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("avflow: error: ") and "bad_ensemble.yaml:" in err, err
    assert message in err, err
    if field:
        assert f": {field}: " in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()  # nothing started
    with pytest.raises(EnsembleError):
        load_ensemble(path)


@pytest.mark.parametrize("port_8787", ["free", "taken"])
def test_bad_ensemble_file_with_workers_closes_the_cluster_started_meanwhile(tmp_path,
                                                                            capsys, port_8787):
    """--workers N starts the local cluster while the file is checked: a refused file is
    still one line, exit 2, and the cluster is gone. So too where another dask cluster on
    this machine holds port 8787, the default port of a scheduler's HTTP server, which it
    starts even without a dashboard (dask warned on stderr then: "Port 8787 is already in
    use")."""
    import multiprocessing
    import socket
    import warnings

    body, field, message = next(iter(BAD.values()))
    base = coarse_base(tmp_path)
    path = write(tmp_path, f"name: bad\nbase: {base.name}\n{body}", "bad_ensemble.yaml")
    out = tmp_path / "out"
    holder = socket.socket()
    try:
        if port_8787 == "taken":
            try:
                holder.bind(("", 8787))
                holder.listen()
            except OSError:  # held already (another cluster): the case itself
                pass
        with warnings.catch_warnings(record=True) as caught:  # (the CLI prints them)
            warnings.simplefilter("always")
            assert main(["ensemble", str(path), "-o", str(out), "--workers", "1"]) == 2
    finally:
        holder.close()
    assert not [str(w.message) for w in caught if "already in use" in str(w.message)]
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists() and not multiprocessing.active_children()


def test_missing_base_is_an_error_on_the_ensemble_file(tmp_path, capsys):
    path = write(tmp_path, "base: nope.yaml\nvary:\n  rheology.delta_deg: [15.0]\n")
    assert main(["ensemble", str(path), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "ens.yaml:1:1: base: scenario file not found" in err


# =========================================================================================
# Grid scene: stacked maps, exceedance probability
# =========================================================================================


def grid_ensemble(tmp_path, extra=""):
    """Four members (two friction angles, two volumes) of the plane box at 25 m cells."""
    text = (SCENARIOS / "plane_box_2d.yaml").read_text().replace("dx: 10.0", "dx: 25.0")
    (tmp_path / "plane.yaml").write_text(text)
    return load_ensemble(write(tmp_path, """
base: plane.yaml
vary:
  rheology.delta_deg: [18.0, 22.0]
  release.volume_factor: [0.5, 1.0]
""" + extra))


def test_grid_ensemble_maps_and_exceedance(tmp_path, monkeypatch):
    ens = grid_ensemble(tmp_path, "thresholds: [0.5, 2.0]")
    out = tmp_path / "out"
    outcome = run_ensemble(ens, out, workers=0)
    assert outcome.ok and outcome.ran == 4
    ds = xr.open_dataset(out / "ensemble.nc", decode_times=False)
    ny, nx = 8, 40
    assert ds["peak_thickness"].dims == ("realization", "y", "x")
    assert ds["peak_thickness"].shape == (4, ny, nx)
    assert ds["deposit_thickness"].shape == (4, ny, nx)
    prob = ds["peak_thickness_exceedance_probability"]
    assert prob.dims == ("threshold", "y", "x") and list(prob["threshold"].values) == [0.5, 2.0]
    peak = ds["peak_thickness"].values
    expected = (peak[None] > np.array([0.5, 2.0])[:, None, None, None]).mean(axis=1)
    np.testing.assert_array_equal(prob.values, expected.astype(np.float32))
    assert prob.values.max() == 1.0 and prob.values.min() == 0.0
    assert (prob.values[1] <= prob.values[0]).all()
    for i, m in enumerate(ens.members):
        with xr.open_dataset(out / "members" / f"{m.scenario_hash}.nc") as member:
            np.testing.assert_array_equal(member["peak_thickness"].values, peak[i])
    shutil.copy(out / "ensemble.nc", tmp_path / "grid_ensemble.nc")
    assert compliance_errors(tmp_path / "grid_ensemble.nc") == []
    import avflow.ensemble.report as report
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    drawn = {}
    saved = report._savefig

    def keep(fig, target):  # the figure as `avflow report` draws it, before it is closed
        fig.canvas.draw()
        drawn[target.name] = [(ax.get_legend() and [t.get_text() for t in
                                                    ax.get_legend().get_texts()],
                               any(isinstance(c, AnchoredSizeBar) for c in ax.get_children()),
                               [t.get_text() for t in ax.texts])
                              for ax in fig.axes if ax.get_xlabel().startswith("x (m)")]
        saved(fig, target)

    monkeypatch.setattr(report, "_savefig", keep)
    text = write_report(out).read_text()
    assert "report/exceedance.png" in text and (out / "report" / "exceedance.png").is_file()
    maps = drawn["exceedance.png"]
    assert len(maps) == 2  # one per threshold, each with a scale bar and a north arrow
    assert all(bar and "N" in texts for _, bar, texts in maps)
    assert "release" in maps[0][0]
    # the outline is where any member released: the release volume is varied here
    union = np.zeros((ny, nx), bool)
    for m in ens.members:
        with xr.open_dataset(out / "members" / f"{m.scenario_hash}.nc") as member:
            union |= member["h"].isel(time=0).values > 0
    ok = np.ones(ds.sizes["realization"], bool)
    np.testing.assert_array_equal(report._released(ds, out, ok), union)


def test_members_on_a_cluster_run_on_one_thread_and_equal_a_run_here(tmp_path):
    """Members on dask run their cluster_scenario: numerics.threads 1 unless their scenario
    sets a number (the hash does not change); here they keep the default (every core). The
    ensemble.nc and summary.csv of a cluster run are those of the run here, but for the
    timings."""
    ens = grid_ensemble(tmp_path)
    member = ens.members[0].scenario
    assert member.numerics.threads is None
    one = cluster_scenario(member)
    assert one.numerics.threads == 1 and one.scenario_hash() == member.scenario_hash()
    assert cluster_scenario(member.with_updates({"numerics.threads": 3})).numerics.threads == 3
    here = run_ensemble(ens, tmp_path / "here", workers=0)
    there = run_ensemble(ens, tmp_path / "there", workers=1)
    assert here.ok and there.ok and (here.where, there.where) == ("here", "local cluster")
    for out, threads in (("here", None), ("there", 1)):
        for m in ens.members:
            with xr.open_dataset(tmp_path / out / "members" / f"{m.scenario_hash}.nc") as ds:
                written = yaml.safe_load(ds.attrs["scenario"])
                assert written["numerics"].get("threads") == threads, out
    timings = {"wall_time", "member_time"}
    with xr.open_dataset(tmp_path / "here" / "ensemble.nc", decode_times=False) as a, \
            xr.open_dataset(tmp_path / "there" / "ensemble.nc", decode_times=False) as b:
        assert set(a.variables) == set(b.variables) and "path_runout_s" in a
        assert "peak_pressure_exceedance_probability" in a
        for name in set(a.variables) - timings:
            np.testing.assert_array_equal(a[name].values, b[name].values, err_msg=name)
        assert {k: str(v) for k, v in a.attrs.items()} == {k: str(v) for k, v in b.attrs.items()}
    a = pd.read_csv(tmp_path / "here" / "summary.csv")
    b = pd.read_csv(tmp_path / "there" / "summary.csv")
    assert list(a.columns) == list(b.columns)
    pd.testing.assert_frame_equal(a.drop(columns=list(timings)), b.drop(columns=list(timings)))


def _same_outputs(a_dir, b_dir):
    """ensemble.nc and summary.csv of two runs of one ensemble equal, but for the timings."""
    timings = {"wall_time", "member_time"}
    with xr.open_dataset(a_dir / "ensemble.nc", decode_times=False) as a, \
            xr.open_dataset(b_dir / "ensemble.nc", decode_times=False) as b:
        assert set(a.variables) == set(b.variables) and "path_runout_s" in a
        for name in set(a.variables) - timings:
            np.testing.assert_array_equal(a[name].values, b[name].values, err_msg=name)
        assert {k: str(v) for k, v in a.attrs.items()} == {k: str(v) for k, v in b.attrs.items()}
    a = pd.read_csv(a_dir / "summary.csv")
    b = pd.read_csv(b_dir / "summary.csv")
    assert list(a.columns) == list(b.columns)
    pd.testing.assert_frame_equal(a.drop(columns=list(timings)), b.drop(columns=list(timings)))


def test_the_end_reads_each_member_file_once(tmp_path, monkeypatch):
    """What ensemble.nc and the path analysis need of a member file (its maps, its cells) is
    read once, as the member finishes (on its worker on dask); the end opens no member file
    again. Where that read is missing (a part that could not be read), the end reads the
    file itself, and the outputs are the same."""
    from avflow.ensemble import orchestrate

    ens = grid_ensemble(tmp_path)
    opened = []
    real_open = xr.open_dataset

    def counting_open(path, *args, **kwargs):
        if "members" in str(path):
            opened.append(str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(xr, "open_dataset", counting_open)
    assert run_ensemble(ens, tmp_path / "once", workers=0).ok
    assert sorted(opened) == sorted(str(tmp_path / "once" / "members" / f"{m.scenario_hash}.nc")
                                    for m in ens.members)
    monkeypatch.setattr(orchestrate, "member_digest",
                        lambda path, profile: {"maps": None, "points": None})
    opened.clear()
    assert run_ensemble(ens, tmp_path / "again", workers=0).ok
    assert len(opened) == 2 * len(ens.members)  # the maps, then the cells, at the end
    _same_outputs(tmp_path / "once", tmp_path / "again")


def test_members_keep_their_own_threads_on_a_cluster(tmp_path):
    """A base scenario that sets numerics.threads keeps it on the cluster; a cluster started
    earlier for single-threaded members (NUMBA_NUM_THREADS=1) does not fit and is closed."""
    import multiprocessing

    from avflow.ensemble.orchestrate import start_local_cluster

    text = (SCENARIOS / "plane_box_2d.yaml").read_text().replace("dx: 10.0", "dx: 25.0")
    (tmp_path / "plane.yaml").write_text(text + "numerics: {threads: 2}\n")
    ens = load_ensemble(write(tmp_path, """
base: plane.yaml
vary:
  rheology.delta_deg: [18.0, 22.0]
"""))
    assert ens.members[0].scenario.numerics.threads == 2
    outcome = run_ensemble(ens, tmp_path / "out", workers=1, starting=start_local_cluster(1))
    assert outcome.ok and outcome.where == "local cluster"
    for m in ens.members:
        with xr.open_dataset(tmp_path / "out" / "members" / f"{m.scenario_hash}.nc") as ds:
            assert yaml.safe_load(ds.attrs["scenario"])["numerics"]["threads"] == 2
    assert not multiprocessing.active_children()


@pytest.mark.parametrize("start_s, where", [(1000.0, "here"), (0.0, "local cluster")])
def test_cluster_started_while_the_first_member_runs(start_s, where, tmp_path, monkeypatch):
    """On SPECULATE_MIN_CORES cores or more the local cluster starts while the first member
    runs here to choose where the others go: used if they go there, closed if they stay."""
    import multiprocessing

    from avflow.ensemble import orchestrate

    monkeypatch.setattr(orchestrate, "SPECULATE_MIN_CORES", 1)
    monkeypatch.setattr(orchestrate, "CLUSTER_START_S", start_s)
    ens = load_ensemble(write(tmp_path, f"""
base: {coarse_base(tmp_path, dx=50.0).name}
vary:
  rheology.delta_deg: [14.0, 16.0, 18.0, 20.0]
"""))
    outcome = run_ensemble(ens, tmp_path / "out")
    assert outcome.ok and outcome.ran == 4 and outcome.where == where
    assert ("cluster" in outcome.timings) == (where != "here")
    assert not multiprocessing.active_children()  # the cluster is closed either way
    table = pd.read_csv(tmp_path / "out" / "summary.csv")
    assert list(table["status"]) == ["at_rest"] * 4


# =========================================================================================
# Voellmy: steady uniform flow on an inclined plane
# =========================================================================================


def test_voellmy_steady_uniform_flow_on_an_inclined_plane():
    """u = sqrt(xi h (sin(theta) - mu cos(theta))), reached in the middle of a long slope.

    The whole slope starts uniformly covered (h = 2 m, at rest) and accelerates; the wall at
    the top sends a rarefaction down at u + c (< 20 m/s, under 1800 m in 90 s), the outflow
    at the bottom cannot be felt upstream (Fr ~ 3.7 > sqrt(3): the kinetic fluxes are fully
    upwind). In between the flow is uniform, the fluxes cancel exactly and each step solves
    the ODE du/dt = g (sin - mu cos) - g u^2 / (xi h) with the implicit drag of
    rheology.friction. Its fixed point is the exact steady speed (at u_s the update
    q (1 + g u_s dt / (xi h)) = q + dt g h (sin - mu cos) holds for every dt), so the error left
    is the transient: |u/u_s - 1| ~ exp(-2 a t / u_s), a = g (sin - mu cos), about 1e-10 at
    t = 90 s. Tolerance 1e-8. The transient itself follows u_s tanh(a t / u_s) to first order
    in dt (dt ~ 0.4 s here): checked at t = 10 s within 2e-3.
    """
    theta, delta, xi, h0 = 30.0, 20.0, 500.0, 2.0
    scenario = parse_scenario(f"""
name: voellmy-plane
terrain: {{kind: profile, length: 6000.0, slope: {{kind: constant, theta_deg: {theta}}},
          curvature: false}}
grid: {{dx: 10.0}}
release: {{kind: box, x: [0.0, 6000.0], thickness: {h0}}}
rheology: {{law: voellmy, delta_deg: {delta}, xi: {xi}}}
time: {{end: 90.0, cfl: 0.5}}
output: {{every: 10.0, stop_fraction: 0.0}}
boundary: {{x_min: wall, x_max: outflow}}
""")
    ds = to_dataset(simulate(scenario))
    th, mu = math.radians(theta), math.tan(math.radians(delta))
    a = 9.81 * (math.sin(th) - mu * math.cos(th))
    u_s = math.sqrt(xi * h0 * (math.sin(th) - mu * math.cos(th)))
    middle = ((ds["x"] > 3500) & (ds["x"] < 4500)).values
    u_end = ds["u"].values[-1, middle]
    assert float(ds["time"][-1]) == 90.0
    np.testing.assert_array_equal(ds["h"].values[-1, middle], h0)  # still uniform
    assert np.abs(u_end / u_s - 1.0).max() < 1e-8
    u_10 = ds["u"].sel(time=10.0).values[middle]
    assert np.abs(u_10 / (u_s * math.tanh(a * 10.0 / u_s)) - 1.0).max() < 2e-3
    # Same speed whatever the friction is written as: mu instead of delta_deg.
    via_mu = scenario.with_updates({"rheology": {"law": "voellmy", "mu": mu, "xi": xi}})
    assert float(simulate(via_mu).summary["deposit_volume"]) == pytest.approx(
        float(ds["deposit_volume"]), rel=1e-12)


# =========================================================================================
# A real scheduler and two workers on 127.0.0.1; one worker killed mid-ensemble
# =========================================================================================


def _spawn(args, log):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen([sys.executable, "-m", "dask", *args], cwd=REPO, env=env,
                            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def _stop(proc):
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


def test_killed_worker_every_member_done_exactly_once(tmp_path):
    from distributed import Client

    sched_file = tmp_path / "scheduler.json"
    log = open(tmp_path / "dask.log", "w")
    procs = [_spawn(["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                     "--scheduler-file", str(sched_file)], log)]
    try:
        deadline = time.monotonic() + 60
        while not sched_file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert sched_file.exists(), (tmp_path / "dask.log").read_text()
        workers = [_spawn(["worker", "--scheduler-file", str(sched_file), "--nthreads", "1",
                           "--no-nanny", "--no-dashboard", "--host", "127.0.0.1",
                           "--name", f"w{i}"], log) for i in range(2)]
        procs += workers
        with Client(scheduler_file=str(sched_file), timeout="60s") as client:
            client.wait_for_workers(2, timeout=90)
        # Section-6 scene at its seed resolution: 24 members of ~0.1 s, one per task.
        base = tmp_path / "base.yaml"
        shutil.copy(SECTION6, base)
        ens_path = write(tmp_path, """
base: base.yaml
vary:
  rheology.delta_deg: [14.0, 15.0, 16.0, 17.0, 18.0, 19.0, 20.0, 21.0]
  release.volume_factor: [0.5, 1.0, 2.0]
""")
        ens = load_ensemble(ens_path)
        out = tmp_path / "out"
        run = subprocess.Popen([sys.executable, "-m", "avflow.cli", "ensemble", str(ens_path),
                                "-o", str(out), "--scheduler", str(sched_file), "--batch", "1"],
                               cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, start_new_session=True)
        procs.append(run)  # (started in its own session too, see _stop)
        members = out / "members"
        deadline = time.monotonic() + 120
        done = 0
        while time.monotonic() < deadline and run.poll() is None:
            done = len(list(members.glob("*.nc"))) if members.is_dir() else 0
            if done >= 3:
                break
            time.sleep(0.01)
        assert 3 <= done < len(ens.members), f"killed too late ({done} members done)"
        workers[0].kill()  # SIGKILL: no goodbye to the scheduler, a task lost mid-way
        stdout, stderr = run.communicate(timeout=180)
        assert run.returncode == 0, stdout + stderr
        files = sorted(p.name for p in members.iterdir())
        assert files == sorted(f"{m.scenario_hash}.nc" for m in ens.members)  # once each
        table = pd.read_csv(out / "summary.csv")
        assert table["realization"].is_unique and table["scenario_hash"].is_unique
        assert len(table) == 24 and set(table["status"]) == {"at_rest"}
        assert workers[0].poll() is not None and workers[1].poll() is None
    finally:
        for p in reversed(procs):  # only the processes this test started
            _stop(p)
        log.close()


def test_warm_up_covers_every_kernel_the_members_run(tmp_path):
    """The time loop is compiled per mesh kind and order (per law on square grids): an
    ensemble varying numerics.order warms one tiny scenario of each order (workers
    compiling a kernel at once can crash, numba issue 4807), one varying the law one per
    law, one varying the friction angle only one."""
    from avflow.ensemble.orchestrate import tiny_scenario_yamls

    coarse_base(tmp_path)
    both = load_ensemble(write(tmp_path, """
name: orders
base: base.yaml
vary:
  numerics.order: [1, 2]
  rheology.delta_deg: [14.0, 16.0]
"""))
    tiny = tiny_scenario_yamls(both, one_thread=True)
    assert len(both.members) == 4 and len(tiny) == 2
    assert sorted(parse_scenario(t).numerics.order for t in tiny) == [1, 2]
    one = load_ensemble(write(tmp_path, """
name: angles
base: base.yaml
vary:
  rheology.delta_deg: [14.0, 16.0, 18.0]
""", name="angles.yaml"))
    assert len(tiny_scenario_yamls(one)) == 1
    laws = load_ensemble(write(tmp_path, """
name: laws
base: base.yaml
vary:
  rheology:
    - {law: coulomb, delta_deg: 14.0}
    - {law: coulomb, delta_deg: 16.0}
    - {law: voellmy, mu: 0.3, xi: 2000.0}
""", name="laws.yaml"))
    assert [parse_scenario(t).rheology.law for t in tiny_scenario_yamls(laws)] == [
        "coulomb", "voellmy"]
