"""Nothing lost, nothing invented, round two: the files a run, an ensemble, a calibration or
a region records as its inputs are never written over; calibrate and region bounded, locked
and checked like run and ensemble; results that cannot be physical refused; one line, never
a traceback.

Each test here failed before its fix (the attack's case, rebuilt small). Scenes: the 1D dam
break (profile kernel) and a 120 x 40 DEM at 20 m (grid kernel, Coulomb, order 1), both
compiled by the other tests already.
"""

import errno
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from avflow.cli import main
from conftest import SCENARIOS
from test_cli_habits import run_cli as cli
from test_region import BOXES, REGION, X0, Y0, _dem, _releases
from test_reliability import digests, one_line, subprocess_cli, temporaries

DAMBREAK = SCENARIOS / "seed_dambreak_flat_dx20.yaml"

SLOPE = ("name: slope\nterrain: {kind: dem, path: dem.tif}\ngrid: {dx: 20.0}\n"
         f"release: {{kind: cylinder, center: [{X0 + 300}, {Y0 - 400}], radius: 60, "
         "thickness: 2}\nrheology: {law: coulomb, delta_deg: 24}\ntime: {end: 4.0}\n"
         "output: {every: 2.0}\n")


@pytest.fixture(scope="module")
def slope(tmp_path_factory):
    """A DEM, a scenario on it, its run file (and a copy without recorded inputs)."""
    folder = tmp_path_factory.mktemp("slope")
    _dem(folder)
    (folder / "s.yaml").write_text(SLOPE)
    (folder / "line.csv").write_text(f"x,y\n{X0 + 100},{Y0 - 400}\n{X0 + 2300},{Y0 - 400}\n")
    assert main(["run", str(folder / "s.yaml"), "-q", "-o", str(folder / "run.nc")]) == 0
    return folder


# --- 1. data loss: the inputs a file records are inputs ----------------------------------------


def test_plot_writes_png_only_and_never_over_the_runs_own_inputs(slope, capsys, tmp_path):
    before = digests(slope)
    for target in (slope / "dem.tif", slope / "s.yaml", tmp_path / "x.asc"):
        code, out, err = cli(["plot", slope / "run.nc", "-o", target], capsys)
        assert code == 2 and "ending in .png" in one_line(err) and "wrote" not in out
    (tmp_path / "dem.png").symlink_to(slope / "dem.tif")
    (tmp_path / "s.png").symlink_to(slope / "s.yaml")
    for target in (tmp_path / "dem.png", tmp_path / "s.png"):
        code, _, err = cli(["plot", slope / "run.nc", "-o", target], capsys)
        assert code == 2 and "is an input of this command" in one_line(err)
    assert digests(slope) == before and not temporaries(slope)
    assert cli(["plot", slope / "run.nc", "-o", tmp_path / "ok.PNG"], capsys)[0] == 0


def test_a_run_file_without_its_list_of_inputs_still_protects_them(slope, capsys, tmp_path):
    with xr.open_dataset(slope / "run.nc", decode_times=False) as ds:
        ds = ds.load()
    assert str(slope / "dem.tif") in ds.attrs["input_files"].splitlines()
    del ds.attrs["input_files"]  # as avflow wrote them before: the scenario's text only
    old = slope / "old.nc"
    ds.to_netcdf(old)
    (tmp_path / "d.png").symlink_to(slope / "dem.tif")
    before = digests(slope)
    code, _, err = cli(["plot", old, "-o", tmp_path / "d.png"], capsys)
    assert code == 2 and "dem.tif" in one_line(err) and "is an input" in err
    assert digests(slope) == before
    old.unlink()


def test_export_and_path_never_write_over_the_runs_inputs(slope, capsys, tmp_path):
    before = digests(slope)
    (tmp_path / "run_peak_speed.tif").symlink_to(slope / "dem.tif")
    code, out, err = cli(["export", slope / "run.nc", "-o", tmp_path, "--variables",
                          "peak_thickness,peak_speed"], capsys)
    assert code == 2 and "is an input" in one_line(err) and "wrote" not in out
    (tmp_path / "p.csv").symlink_to(slope / "s.yaml")
    code, _, err = cli(["path", slope / "run.nc", "--line", slope / "line.csv", "-o",
                        tmp_path / "p"], capsys)
    assert code == 2 and "s.yaml" in one_line(err) and "is an input" in err
    assert digests(slope) == before


def test_report_and_path_of_an_ensemble_never_write_over_its_base(tmp_path, capsys):
    base = tmp_path / "base.yaml"
    base.write_text(DAMBREAK.read_text().replace("end: 137.0", "end: 5.0"))
    (tmp_path / "e.yaml").write_text("base: base.yaml\nvary: {rheology.delta_deg: [0.0, 1.0]}\n")
    out = tmp_path / "ens"
    assert cli(["ensemble", tmp_path / "e.yaml", "-o", out, "--workers", "0", "-q"],
               capsys)[0] == 0
    (out / "path.csv").symlink_to(base)
    (out / "report.md").symlink_to(tmp_path / "e.yaml")
    before = digests(tmp_path)
    code, _, err = cli(["path", out], capsys)
    assert code == 2 and "base.yaml" in one_line(err) and "is an input" in err
    code, _, err = cli(["report", out], capsys)
    assert code == 2 and "e.yaml" in one_line(err) and "is an input" in err
    assert digests(tmp_path) == before


def _hold_while_calibrating(monkeypatch, capsys, calls):
    """_Runner.run replaced: while the first calibration 'runs', run the given commands
    and keep their exit codes and errors; then stop it."""
    import avflow.calibration.run as run

    def run_others(self, unit, stage):
        for argv in calls["argv"]:
            code = main([str(a) for a in argv])
            calls["done"].append((code, capsys.readouterr().err))
        raise KeyboardInterrupt

    monkeypatch.setattr(run._Runner, "run", run_others)


@pytest.fixture
def dam_calibration(tmp_path):
    (tmp_path / "base.yaml").write_text(DAMBREAK.read_text().replace("end: 137.0", "end: 5.0"))
    cal = tmp_path / "c.yaml"
    cal.write_text("base: base.yaml\nparameters:\n  rheology.delta_deg: [0.0, 10.0]\n"
                   "observations:\n  - {kind: runout, station: 1100.0, error: 20.0}\n"
                   "method: lhs\nbudget: 3\nsensitivity: {enabled: false}\n")
    return cal


def test_a_running_calibrations_folder_is_refused_to_a_second_calibrate_and_an_ensemble(
        dam_calibration, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    (tmp_path / "e.yaml").write_text("base: base.yaml\nvary: {rheology.delta_deg: [0.0]}\n")
    calls = {"argv": [["calibrate", dam_calibration, "-o", out, "--workers", "0"],
                      ["ensemble", tmp_path / "e.yaml", "-o", out, "--workers", "0"]],
             "done": []}
    _hold_while_calibrating(monkeypatch, capsys, calls)
    code, _, err = cli(["calibrate", dam_calibration, "-o", out, "--workers", "0"], capsys)
    assert code in (130, 143)
    (c1, e1), (c2, e2) = calls["done"]
    assert c1 == 2 and "in use by another avflow command" in one_line(e1)
    assert c2 == 2 and "in use by another avflow command" in one_line(e2)
    assert not list(out.glob("*.nc")) and not temporaries(tmp_path)


# --- 2. resources: what a calibration or region file may ask for -------------------------------


@pytest.mark.parametrize("edit, field, words", [
    ("budget: 1000000000", ":6:1: budget", "1,000,000,000 model runs, more than the limit "
                                             "of 10,000"),
    ("method: posterior\nbudget: 10\nposterior: {walkers: 24, steps: 1000000000}",
     ":8:1: posterior", "24 x 1,000,000,000 = 24,000,000,000 draws (about"),
    ("method: posterior\nbudget: 10\nposterior: {walkers: 100000000, steps: 1000}",
     ":8:1: posterior", "draws (about"),
    ("budget: 10\nsensitivity: {n: 1000000000}", ":7:15: sensitivity.n",
     "3,000,000,000 emulator evaluations (about"),
    ("method: posterior\nbudget: 10\nposterior: {checks: 100000}", ":8:",
     "100,000 model runs"),
])
def test_calibration_sizes_are_bounded_before_anything_runs(dam_calibration, tmp_path,
                                                            capsys, edit, field, words):
    text = dam_calibration.read_text().replace("method: lhs\nbudget: 3\n"
                                               "sensitivity: {enabled: false}\n", "")
    dam_calibration.write_text(text + edit + "\n")
    started = time.monotonic()
    code, _, err = cli(["calibrate", dam_calibration, "-o", tmp_path / "out"], capsys)
    assert code == 2 and words in one_line(err) and "c.yaml" + field in err, err
    assert time.monotonic() - started < 20 and not (tmp_path / "out").exists()


def test_calibration_files_are_bounded_and_regular(tmp_path, capsys):
    big = tmp_path / "big.yaml"
    big.write_bytes(b"a" * (2 << 20))
    (tmp_path / "zero.yaml").symlink_to("/dev/zero")
    for path, why in [("/dev/zero", "not a regular file"), (tmp_path / "zero.yaml",
                      "not a regular file"), (tmp_path, "a folder"), (big, "over 1 MiB")]:
        code, _, err = cli(["calibrate", path, "-o", tmp_path / "o"], capsys)
        assert code == 2 and why in one_line(err)
    assert not (tmp_path / "o").exists()


def test_out_of_memory_advice_fits_the_command(dam_calibration, tmp_path, capsys,
                                               monkeypatch):
    import avflow.calibration.run as run

    def no_memory(*args, **kw):
        raise MemoryError

    monkeypatch.setattr(run._Runner, "run", no_memory)
    code, _, err = cli(["calibrate", dam_calibration, "-o", tmp_path / "out"], capsys)
    assert code == 1 and "out of memory" in one_line(err)
    assert "--max-memory" not in err and "budget" in err


def _raster_region(folder: Path, width=120, height=40):
    import rasterio
    from rasterio.transform import from_origin

    _dem(folder)
    data = np.zeros((height, width), np.float32)
    data[10:14, 10:14] = 2.0
    with rasterio.open(folder / "rel.tif", "w", driver="GTiff", width=width, height=height,
                       count=1, dtype="float32", crs="EPSG:2056",
                       transform=from_origin(X0, Y0, 20.0, 20.0)) as dst:
        dst.write(data, 1)
    text = REGION.format(releases="x", buffer=40.0).replace(
        "  path: x\n  id_field: id\n", "  raster: rel.tif\n")
    (folder / "r.yaml").write_text(text)
    return folder / "r.yaml"


def test_a_release_raster_too_large_to_read_is_refused_with_advice_that_applies(
        tmp_path, capsys, monkeypatch):
    region = _raster_region(tmp_path)
    monkeypatch.setenv("AVFLOW_MAX_MEMORY", "64K")  # 120 x 40 cells need about 100 KiB
    code, _, err = cli(["region", region, "-o", tmp_path / "out", "--workers", "0"], capsys)
    assert code == 2 and "releases.raster" in one_line(err)
    assert "120 x 40 cells" in err and "crop the raster" in err and "--max-memory" not in err
