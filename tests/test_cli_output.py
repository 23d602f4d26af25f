"""End to end: contract files through the CLI, CF compliance, round trip, bad input."""

import shutil
import subprocess
import sys

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
    from compliance_checker.runner import CheckSuite, ComplianceChecker

    CheckSuite.load_all_available_checkers()
    report = path.with_suffix(".json")
    ComplianceChecker.run_checker(str(path), ["cf:1.11"], 0, "strict",
                                  output_filename=str(report), output_format="json")
    import json

    results = json.loads(report.read_text())["cf:1.11"]
    return [m for k in ("high_priorities",) for item in results.get(k, [])
            for m in item["msgs"]]


@pytest.mark.parametrize("scenario", ["seed_exponential_coulomb15.yaml", "plane_box_2d.yaml"])
def test_cf_compliance_has_no_errors(scenario, tmp_path):
    path = write_netcdf(to_dataset(simulate(load_scenario(SCENARIOS / scenario))),
                        tmp_path / "run.nc")
    assert compliance_errors(path) == []


def test_round_trip_and_summary_from_file(tmp_path):
    result = simulate(load_scenario(SCENARIOS / "seed_exponential_coulomb15.yaml"))
    ds = to_dataset(result)
    back = xr.open_dataset(write_netcdf(ds, tmp_path / "r.nc"), decode_times=False)
    for name in ("runout", "time_to_stop", "deposit_max_thickness", "mass_balance_error"):
        assert float(back[name]) == float(ds[name])
    np.testing.assert_allclose(back["h"].values, ds["h"].values, rtol=1e-6, atol=1e-5)
    np.testing.assert_array_equal(back["time"].values, ds["time"].values)
    assert back["deposit_thickness"].attrs["cell_methods"] == "time_span: point"


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
