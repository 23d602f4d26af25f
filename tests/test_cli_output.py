"""End to end: contract files through the CLI, CF compliance, round trip, bad input."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from avflow.cli import main
from avflow.output.dataset import to_dataset
from avflow.output.netcdf import write_netcdf
from avflow.simulation.runner import simulate
from avflow.scenario.schema import load_scenario
from conftest import SCENARIOS

PROFILE_CONTRACTS = ["seed_exponential_coulomb.yaml", "seed_exponential_pouliquen.yaml",
                     "seed_dambreak_inclined.yaml"]


@pytest.mark.parametrize("name", PROFILE_CONTRACTS)
def test_contract_files_run_unchanged(name, contract_dir, tmp_path, capsys):
    out = tmp_path / "out.nc"
    assert main(["run", str(contract_dir / name), "-o", str(out)]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    assert "mass error" in line and "runout" in line
    ds = xr.open_dataset(out, decode_times=False)
    assert ds.attrs["Conventions"] == "CF-1.11"
    assert float(ds["mass_balance_error"]) < 1e-12
    assert (ds["h"] >= 0).all()
    assert ds.attrs["scenario"] == (contract_dir / name).read_text()
    assert [n for n in tmp_path.iterdir()] == [out]  # no temporary file left behind


def compliance_errors(path):
    pytest.importorskip("compliance_checker", reason="compliance-checker (the test extra) "
                        "is not installed")
    from compliance_checker.runner import CheckSuite, ComplianceChecker

    CheckSuite.load_all_available_checkers()
    report = path.with_suffix(".json")
    ComplianceChecker.run_checker(str(path), ["cf:1.11"], 0, "strict",
                                  output_filename=str(report), output_format="json")
    import json

    results = json.loads(report.read_text())["cf:1.11"]
    return [m for k in ("high_priorities",) for item in results.get(k, [])
            for m in item["msgs"] if m != TIME_BY_NAME]


# The checker's guess, not a CF rule: a dimension *named* time must be a CF time coordinate
# (standard_name time, units "<unit> since <datetime>"). CF identifies a time coordinate by
# its units (4.4) and standardizes no names; avflow's `time` is seconds since the release in
# plain "s", so that xarray's default decoding keeps numbers (`ds.h.sel(time=40)`, issue 31),
# the release instant being its `release_time` attribute.
TIME_BY_NAME = "Coordinate variable 'time' should have standard_name='time', found: 'None'"


@pytest.mark.parametrize("scenario", ["seed_exponential_coulomb15.yaml", "plane_box_2d.yaml"])
def test_cf_compliance_has_no_errors(scenario, tmp_path):
    path = write_netcdf(to_dataset(simulate(load_scenario(SCENARIOS / scenario))),
                        tmp_path / "run.nc")
    assert compliance_errors(path) == []


def strict_messages(path):
    """Every message of ``compliance-checker --test cf:1.11 --criteria strict`` (all levels)."""
    import json

    pytest.importorskip("compliance_checker", reason="compliance-checker (the test extra) "
                        "is not installed")
    from compliance_checker.runner import CheckSuite, ComplianceChecker

    CheckSuite.load_all_available_checkers()
    report = path.with_suffix(".strict.json")
    ComplianceChecker.run_checker(str(path), ["cf:1.11"], 0, "strict",
                                  output_filename=str(report), output_format="json")
    results = json.loads(report.read_text())["cf:1.11"]
    return sorted(m for k in ("high_priorities", "medium_priorities", "low_priorities")
                  for item in results.get(k, []) for m in item["msgs"])


# The checker's mistake: CF 7.1 gives a boundary variable one more dimension than its
# coordinate, so the bounds of the scalar coordinate `duration` (the whole run, named by
# the run maxima's cell_methods) have one; the checker wants at least two.
SCALAR_BOUNDS = ("Boundary variable duration_bounds specified by duration should have at least "
                 "two dimensions to enclose the base case of a one dimensionsal variable")
# TIME_BY_NAME once per variable on time that the checker takes for geophysical: the fields
# and the series (flow_state, a flag, is not one)
ON_TIME = {"profile": ("h", "u", "moving_volume", "center_of_mass_x", "center_of_mass_y",
                       "center_of_mass_z"),
           "grid": ("h", "u", "v", "moving_volume", "center_of_mass_x", "center_of_mass_y",
                    "center_of_mass_z")}
ON_TIME["triangles"] = ON_TIME["grid"]


def known_messages(kind):
    """The strict messages a run file of this kind still gets (all the checker's own)."""
    if kind == "ensemble":
        return []
    return [SCALAR_BOUNDS] + [TIME_BY_NAME] * len(ON_TIME[kind])


# On UGRID files only, the checker does not know UGRID, which CF-1.11 includes by reference
# (see tests/test_trimesh.py::ugrid_errors): it takes the mesh's cf_role for a wrong
# discrete-geometry role, and the node dimension (spatial, the mesh's location) for a
# non-spatial one that should sit left of time.
UGRID_ROLE = ("mesh_topology is not a valid cf_role value. It must be one of timeseries_id, "
              "profile_id, trajectory_id")


def ugrid_order(name):
    return (f"{name}'s spatio-temporal dimensions are not in the recommended order T, Z, Y, X "
            "and/or further dimensions are not located left of T, Z, Y, X. The dimensions "
            "(and their guessed types) are time (T), node (A) (with U: other/unknown; L: "
            "unlimited).")


def _ensemble_file(tmp_path):
    from avflow.ensemble.orchestrate import run_ensemble
    from avflow.ensemble.spec import load_ensemble

    text = (SCENARIOS / "seed_exponential_coulomb15.yaml").read_text()
    (tmp_path / "base.yaml").write_text(text.replace("dx: 6.25", "dx: 50.0"))
    (tmp_path / "ens.yaml").write_text("base: base.yaml\nvary:\n"
                                       "  rheology.delta_deg: [15.0, 20.0]\n")
    assert run_ensemble(load_ensemble(tmp_path / "ens.yaml"), tmp_path / "ens", workers=0).ok
    return tmp_path / "ens" / "ensemble.nc"


@pytest.mark.parametrize("kind", ["profile", "grid", "triangles", "ensemble"])
def test_strict_cf_leaves_only_the_checkers_own_mistakes(kind, tmp_path):
    scenario = {"profile": "seed_dambreak_flat_dx20.yaml", "grid": "plane_box_2d.yaml",
                "triangles": "plane_cylinder_triangles.yaml"}.get(kind)
    if scenario is None:
        path = _ensemble_file(tmp_path)  # ensemble.nc has no run maxima
    else:
        path = write_netcdf(to_dataset(simulate(load_scenario(SCENARIOS / scenario))),
                            tmp_path / "run.nc")
    allowed = known_messages(kind)
    if kind == "triangles":
        allowed += [UGRID_ROLE]
    assert strict_messages(path) == sorted(allowed)


def test_round_trip_and_summary_from_file(tmp_path):
    result = simulate(load_scenario(SCENARIOS / "seed_exponential_coulomb15.yaml"))
    ds = to_dataset(result)
    back = xr.open_dataset(write_netcdf(ds, tmp_path / "r.nc"), decode_times=False)
    for name in ("runout", "time_to_stop", "deposit_max_thickness", "mass_balance_error"):
        assert float(back[name]) == float(ds[name])
    np.testing.assert_allclose(back["h"].values, ds["h"].values, rtol=1e-6, atol=1e-5)
    np.testing.assert_array_equal(back["time"].values, ds["time"].values)
    assert back["deposit_thickness"].attrs["cell_methods"] == "duration: point"


def test_bad_scenario_exits_2_with_one_line_and_no_output(tmp_path):
    bad = tmp_path / "bad.yaml"
    text = (SCENARIOS / "seed_exponential_coulomb15.yaml").read_text()
    bad.write_text(text.replace("delta_deg: 15.0", "delta_deg: -15.0"))
    out = tmp_path / "out.nc"
    proc = subprocess.run([sys.executable, "-m", "avflow.cli", "run", str(bad), "-o", str(out)],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "bad.yaml" in proc.stderr and "rheology.delta_deg" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not out.exists() and list(tmp_path.iterdir()) == [bad]


def test_missing_scenario_file_exits_2(tmp_path, capsys):
    assert main(["run", str(tmp_path / "nope.yaml")]) == 2
    assert "nope.yaml" in capsys.readouterr().err


def test_output_file_gets_the_usual_permissions(tmp_path):
    """The atomic write (a private temporary file, then rename) must not leave a 0600 file."""
    import os
    import stat

    from avflow.cli import main

    out = tmp_path / "run.nc"
    assert main(["run", str(SCENARIOS / "seed_dambreak_flat_dx20.yaml"), "-o", str(out)]) == 0
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(out.stat().st_mode) == 0o666 & ~mask


# --- output paths: checked before the run; a full disk is one line; stale temporaries -------

FAST = SCENARIOS / "seed_dambreak_flat_dx20.yaml"


@pytest.fixture
def no_run(monkeypatch):
    """Fail the test if the simulation starts."""
    import avflow.simulation.runner as runner

    def refuse(*args, **kwargs):
        raise AssertionError("the run started")

    monkeypatch.setattr(runner, "simulate", refuse)


def refused(capsys, args, *words):
    """`avflow run ARGS` exits 2 with one line on stderr that holds every word."""
    assert main(["run", *map(str, args)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for word in words:
        assert word in err, err
    return err


def test_output_equal_to_the_scenario_file_is_refused(tmp_path, capsys, no_run):
    scenario = tmp_path / "sc.yaml"
    shutil.copy(FAST, scenario)
    text = scenario.read_text()
    refused(capsys, [scenario, "-o", scenario], "sc.yaml", "input")
    refused(capsys, [scenario, "-o", tmp_path / "sub" / ".." / "sc.yaml"], "input")
    (tmp_path / "link.nc").symlink_to(scenario)
    refused(capsys, [scenario, "-o", tmp_path / "link.nc"], "input")
    assert scenario.read_text() == text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.nc", "sc.yaml"]


def test_output_that_is_a_folder_is_refused(tmp_path, capsys, no_run):
    refused(capsys, [FAST, "-o", tmp_path], str(tmp_path), "folder")
    assert list(tmp_path.iterdir()) == []


def unwritable_folder(tmp_path):
    """A read-only folder; root ignores mode bits, so then /sys (no one creates files there)."""
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    for candidate in (folder, Path("/sys")):
        try:
            (candidate / ".avflow-probe").touch()
        except OSError:
            return candidate
        (candidate / ".avflow-probe").unlink()
    pytest.skip("no folder that this user cannot write")


def test_output_in_a_read_only_folder_is_refused(tmp_path, capsys, no_run):
    folder = unwritable_folder(tmp_path)
    try:
        refused(capsys, [FAST, "-o", folder / "out.nc"], str(folder / "out.nc"), "cannot write")
        assert not (folder / "out.nc").exists()
        refused(capsys, [FAST, "-o", folder / "new" / "out.nc"], "cannot create")
    finally:
        (tmp_path / "ro").chmod(0o755)


def test_output_whose_folder_cannot_be_created_is_refused(tmp_path, capsys, no_run):
    (tmp_path / "afile").write_text("x")
    refused(capsys, [FAST, "-o", tmp_path / "afile" / "sub" / "out.nc"], "afile", "not a folder")
    assert [p.name for p in tmp_path.iterdir()] == ["afile"]


@pytest.mark.parametrize("error", [OSError(28, "No space left on device"),
                                   RuntimeError("NetCDF: HDF error")])
@pytest.mark.parametrize("when", ["during the run", "at the end"])
def test_full_disk_is_one_line_exit_1_no_temporary_and_the_old_file_intact(
        error, when, tmp_path, capsys, monkeypatch):
    """The snapshots are written as the run goes (avflow.output.stream): the disk may fill
    up at a snapshot, or with the maps and summaries written at the end."""
    from avflow.output.stream import SnapshotStream

    out = tmp_path / "out.nc"
    out.write_bytes(b"old result")
    append, dump = SnapshotStream._append, xr.Dataset.dump_to_store

    def full_at_snapshot_10(self, *args):
        if self.records == 10:
            raise error
        append(self, *args)

    def full_at_the_end(self, store, **kwargs):
        dump(self, store, **kwargs)
        if "peak_thickness" in self:  # the rest of the run, after the last snapshot
            raise error

    if when == "during the run":
        monkeypatch.setattr(SnapshotStream, "_append", full_at_snapshot_10)
    else:
        monkeypatch.setattr(xr.Dataset, "dump_to_store", full_at_the_end)
    assert main(["run", str(FAST), "-o", str(out)]) == 1
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert len(err.splitlines()) == 1 and str(out) in err, err
    assert ("No space left on device" in err) if isinstance(error, OSError) else "HDF" in err
    assert "wrote" not in captured.out
    assert [p.name for p in tmp_path.iterdir()] == ["out.nc"]  # no temporary left
    assert out.read_bytes() == b"old result"


def test_stale_temporaries_of_a_killed_write_are_removed_by_the_next_run(tmp_path):
    out = tmp_path / "out.nc"
    stale = [tmp_path / ".out.nc.k3_9zq0a.tmp", tmp_path / ".out.nc.abcdefgh.tmp"]
    kept = [tmp_path / ".out.nc.short.tmp", tmp_path / ".other.nc.abcdefgh.tmp",
            tmp_path / ".out.nc.ABCDEFGH.tmp", tmp_path / "out.nc.abcdefgh.tmp",
            tmp_path / ".out.nc.abcdefgh.tmp.keep"]
    for p in stale + kept:
        p.write_bytes(b"half a file")
    assert main(["run", str(FAST), "-o", str(out)]) == 0
    assert sorted(tmp_path.iterdir()) == sorted(kept + [out])
