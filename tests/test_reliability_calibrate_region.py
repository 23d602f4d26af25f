"""Nothing lost, nothing invented, round two: the files a run, an ensemble, a calibration or
a region records as its inputs are never written over; calibrate and region bounded, locked
and checked like run and ensemble; results that cannot be physical refused; one line, never
a traceback.

Each test here failed before its fix (the attack's case, rebuilt small), but one said so. Scenes: the 1D dam
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
    for target, why in ((slope / "dem.tif", "is an input"), (slope / "s.yaml", "is an input"),
                        (tmp_path / "x.asc", "ending in .png")):
        code, out, err = cli(["plot", slope / "run.nc", "-o", target], capsys)
        assert code == 2 and why in one_line(err) and "wrote" not in out
    assert not (tmp_path / "x.asc").exists()
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


# --- 3. invented results ---------------------------------------------------------------------


@pytest.mark.parametrize("depth", ["1000", "1e6", "1e16", "1e308"])
def test_an_erodible_layer_deeper_than_the_map_is_long_is_refused(tmp_path, capsys, depth):
    small = tmp_path / "small.yaml"  # a 600 m profile
    small.write_text(DAMBREAK.read_text().replace("length: 2000.0", "length: 600.0")
                     .replace("position: 1000.0", "position: 300.0"))
    code, out, err = cli(["run", small, "--set", "entrainment={law: erosion_energy, layer: "
                          f"{{depth: {depth}}}}}", "-o", tmp_path / "x.nc"], capsys)
    assert code == 2 and "entrainment.layer.depth" in one_line(err)
    assert "deeper than the map is long (600 m)" in err and not (tmp_path / "x.nc").exists()


def test_an_erodible_raster_deeper_than_the_map_is_refused_before_the_run(slope, tmp_path,
                                                                           capsys):
    from avflow.terrain.raster import read_raster, write_tif

    dem = read_raster(slope / "dem.tif")
    write_tif(tmp_path / "layer.tif", np.full(dem.values.shape, 1e16), dem.x, dem.y,
              dem.crs_wkt)
    shutil.copy(slope / "dem.tif", tmp_path / "dem.tif")
    (tmp_path / "s.yaml").write_text(SLOPE + "entrainment: {law: erosion_energy, layer: "
                                     "{raster: layer.tif}}\n")
    code, _, err = cli(["run", tmp_path / "s.yaml", "-o", tmp_path / "x.nc"], capsys)
    assert code == 2 and "entrainment.layer: the erodible layer is 1e+16 m deep" in one_line(err)


def test_a_run_whose_mass_balance_fails_is_no_success(tmp_path, capsys, monkeypatch):
    import avflow.simulation.runner as runner

    made = runner.summarize

    def unbalanced(result, v0):
        summary = made(result, v0)
        summary["mass_balance_error"] = 54.0  # 5.7e5 m3 of flow from nothing
        return summary

    monkeypatch.setattr(runner, "summarize", unbalanced)
    out = tmp_path / "x.nc"
    out.write_bytes(b"the previous good file")
    code, printed, err = cli(["run", DAMBREAK, "--set", "time.end=5", "-o", out], capsys)
    assert code == 1 and "the mass balance is off by 54" in one_line(err)
    assert "wrote" not in printed and "completed" not in printed
    assert out.read_bytes() == b"the previous good file"


def _dam_cal(tmp_path, observations, method="method: lhs\nbudget: 3\n"):
    (tmp_path / "base.yaml").write_text(DAMBREAK.read_text().replace("end: 137.0", "end: 5.0"))
    cal = tmp_path / "c.yaml"
    cal.write_text("base: base.yaml\nparameters:\n  rheology.delta_deg: [0.0, 10.0]\n"
                   "observations:\n" + observations + method
                   + "sensitivity: {enabled: false}\n")
    return cal


def test_an_observed_area_no_run_reaches_gives_no_best_fit(tmp_path, capsys):
    cal = _dam_cal(tmp_path, "  - {kind: area, interval: [1800.0, 1900.0], score: csi}\n")
    code, out, err = cli(["calibrate", cal, "-o", tmp_path / "out", "--workers", "0", "-q"],
                         capsys)
    assert code == 2 and "every run has the same misfit" in one_line(err)
    assert "best fit" not in out and not (tmp_path / "out" / "calibration.nc").exists()


@pytest.mark.parametrize("field, value, words", [
    ("thickness", "-1.0", "an observed thickness of -1 m is not physical"),
    ("speed", "1e308", "an observed speed of 1e+308 m/s is not physical"),
    ("arrival_time", "-5", "not physical"),
    ("pressure", "1e308", "not physical"),
])
def test_observed_values_no_avalanche_has_are_refused_at_load(tmp_path, capsys, field, value,
                                                              words):
    cal = _dam_cal(tmp_path, f"  - {{kind: points, field: {field}, points: [[1010.0, 0.0]], "
                             f"values: [{value}]}}\n")
    code, _, err = cli(["calibrate", cal, "-o", tmp_path / "out"], capsys)
    assert code == 2 and "observations.0.values.0" in one_line(err) and words in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("value, words", [(-0.5, "negative deposit thicknesses"),
                                          (1e30, "not physical")])
def test_an_observed_deposit_raster_that_cannot_be_is_refused_at_load(slope, tmp_path, capsys,
                                                                       value, words):
    from avflow.terrain.raster import read_raster, write_tif

    dem = read_raster(slope / "dem.tif")
    deposit = np.zeros(dem.values.shape)
    deposit[20, 20] = value
    write_tif(tmp_path / "dep.tif", deposit, dem.x, dem.y, dem.crs_wkt)
    shutil.copy(slope / "dem.tif", tmp_path / "dem.tif")
    (tmp_path / "s.yaml").write_text(SLOPE)
    (tmp_path / "c.yaml").write_text(
        "base: s.yaml\nparameters:\n  rheology.delta_deg: [20.0, 28.0]\nobservations:\n"
        "  - {kind: deposit, raster: dep.tif}\nmethod: lhs\nbudget: 3\n")
    code, _, err = cli(["calibrate", tmp_path / "c.yaml", "-o", tmp_path / "out"], capsys)
    assert code == 2 and "observations.0.raster" in one_line(err) and words in err


@pytest.fixture(scope="module")
def region_out(tmp_path_factory):
    """A region of one release (run here, no dask), its store exported once."""
    folder = tmp_path_factory.mktemp("region")
    _dem(folder)
    _releases(folder / "rel.gpkg", BOXES[:1])
    (folder / "r.yaml").write_text(REGION.format(releases="rel.gpkg", buffer=40.0))
    assert main(["region", str(folder / "r.yaml"), "-o", str(folder / "out"), "--workers",
                 "0", "-q"]) == 0
    return folder


def _copy_store(region_out, tmp_path) -> Path:
    shutil.copytree(region_out / "out" / "region.zarr", tmp_path / "region.zarr")
    return tmp_path / "region.zarr"


def test_a_region_store_with_a_chunk_missing_is_damaged_not_empty(region_out, tmp_path,
                                                                   capsys):
    store = _copy_store(region_out, tmp_path)
    chunk = sorted(p for p in (store / "peak_pressure").iterdir()
                   if not p.name.startswith("."))[0]
    chunk.unlink()
    code, out, err = cli(["export", store, "-o", tmp_path / "gis"], capsys)
    assert code == 2 and "the store is damaged" in one_line(err)
    assert f"chunk peak_pressure/{chunk.name} is missing" in err and "wrote" not in out
    assert not (tmp_path / "gis").exists() or not list((tmp_path / "gis").iterdir())


def test_region_export_never_writes_over_the_regions_inputs(region_out, tmp_path, capsys):
    store = _copy_store(region_out, tmp_path)
    (tmp_path / "region_peak_pressure.tif").symlink_to(region_out / "dem.tif")
    before = digests(region_out)
    code, _, err = cli(["export", store, "-o", tmp_path], capsys)
    assert code == 2 and "dem.tif" in one_line(err) and "is an input" in err
    assert digests(region_out) == before


# --- 4. tracebacks and misleading lines ---------------------------------------------------------


def test_a_garbled_or_truncated_store_is_one_line(region_out, tmp_path, capsys):
    store = _copy_store(region_out, tmp_path)
    chunk = sorted(p for p in (store / "peak_pressure").iterdir()
                   if not p.name.startswith("."))[0]
    chunk.write_bytes(b"\x02\x01garbage" * 4)  # a blosc header, then nothing that decodes
    code, _, err = cli(["export", store, "-o", tmp_path / "gis", "--variables",
                        "peak_pressure"], capsys)
    assert code == 2 and "the store is damaged" in one_line(err)
    meta = store / ".zmetadata"
    meta.write_bytes(meta.read_bytes()[:100])
    for target in (store, tmp_path):
        code, _, err = cli(["export", target, "-o", tmp_path / "gis"], capsys)
        assert code == 2 and "the store is damaged" in one_line(err)
        assert "no such file" not in err


def _full_disk(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_full_disk_under_export_is_one_line_and_leaves_nothing(region_out, slope, tmp_path,
                                                                 capsys, monkeypatch):
    # (passed before too: kept beside the region's case, which did not)
    import rasterio.shutil

    store = _copy_store(region_out, tmp_path)
    monkeypatch.setattr(rasterio.shutil, "copy", _full_disk)
    code, out, err = cli(["export", store, "-o", tmp_path / "gis"], capsys)
    assert code == 1 and "No space left on device" in one_line(err) and "wrote" not in out
    assert not (tmp_path / "gis").exists() or not list((tmp_path / "gis").iterdir())
    import avflow.files as files

    monkeypatch.setattr(files, "fsync", _full_disk)  # the disk found full as it is flushed
    code, out, err = cli(["export", slope / "run.nc", "-o", tmp_path / "gis2"], capsys)
    assert code == 1 and "No space left on device" in err.strip().splitlines()[-1]
    assert "Traceback" not in err
    assert not (tmp_path / "gis2").exists() or not list((tmp_path / "gis2").iterdir())


def test_a_full_disk_under_region_is_one_line_and_leaves_no_store(region_out, tmp_path,
                                                                  capsys, monkeypatch):
    import avflow.region.merge as merge

    monkeypatch.setattr(merge.RegionStore, "add", _full_disk)
    out = tmp_path / "out"
    code, _, err = cli(["region", region_out / "r.yaml", "-o", out, "--workers", "0"], capsys)
    assert code == 1 and "No space left on device" in one_line(err)
    assert not (out / "region.zarr").exists() and not list(out.glob(".region.zarr.*"))


@pytest.mark.parametrize("nested", ["[" * 5000 + "]" * 5000, "{a: " * 3000 + "1" + "}" * 3000])
def test_yaml_nested_thousands_of_levels_is_one_line_everywhere(tmp_path, capsys, nested):
    deep = tmp_path / "deep.yaml"
    deep.write_text("name: " + nested + "\n")
    for argv in (["run", deep], ["ensemble", deep, "-o", tmp_path / "o"],
                 ["calibrate", deep, "-o", tmp_path / "o"],
                 ["region", deep, "-o", tmp_path / "o"],
                 ["run", DAMBREAK, "--set", "rheology.delta_deg=" + nested],
                 ["ensemble", deep, "-o", tmp_path / "o", "--set", "x=" + nested]):
        code, _, err = cli(argv, capsys)
        assert code == 2 and "nested more than 64 levels deep" in one_line(err), argv
        assert len(err) < 400  # a few characters of the value, not 10 KB of it
    assert not (tmp_path / "o").exists()


def _until(path_glob, folder: Path, seconds=120):
    deadline = time.monotonic() + seconds
    while not list(folder.glob(path_glob)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert list(folder.glob(path_glob)), f"{path_glob} never appeared in {folder}"


LONG = ["--set", "time.end=1e6", "--set", "output.every=1e5", "--set", "grid.dx=1"]


def _terminated(argv, folder: Path, wait=0.0):
    process = subprocess.Popen([sys.executable, "-m", "avflow.cli", *map(str, argv)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _until("**/.*.tmp", folder)  # a member is being written
        time.sleep(wait)
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=120)
    finally:
        process.kill()
    return process.returncode, err


def _long_dambreak(folder) -> None:
    """``folder/long.yaml``: the dam break run for days on 1 m cells (a run to interrupt)."""
    (folder / "long.yaml").write_text(
        DAMBREAK.read_text().replace("end: 137.0", "end: 1.0e6")
        .replace("every: 1.0", "every: 1.0e5").replace("dx: 20.0", "dx: 1.0"))


def test_sigterm_of_ensemble_calibrate_and_region_exits_143(tmp_path):
    _long_dambreak(tmp_path)
    (tmp_path / "e.yaml").write_text("base: long.yaml\nvary: {rheology.delta_deg: [0.0, 1.0]}\n")
    code, err = _terminated(["ensemble", tmp_path / "e.yaml", "-o", tmp_path / "ens",
                             "--workers", "0", "-q"], tmp_path / "ens")
    assert code == 143 and "Traceback" not in err, err
    (tmp_path / "c.yaml").write_text(
        "base: long.yaml\nparameters:\n  rheology.delta_deg: [0.0, 10.0]\nobservations:\n"
        "  - {kind: runout, station: 1100.0}\nmethod: lhs\nbudget: 3\n")
    code, err = _terminated(["calibrate", tmp_path / "c.yaml", "-o", tmp_path / "cal",
                             "--workers", "0", "-q"], tmp_path / "cal")
    assert code == 143 and "Traceback" not in err, err
    assert not list((tmp_path / "cal").glob("**/*.tmp"))


def test_sigterm_of_a_region_exits_143(region_out, tmp_path):
    text = (region_out / "r.yaml").read_text().replace("time: {end: 120.0}", "time: {end: 1e5}")
    text = text.replace("delta_deg: 24.0", "delta_deg: 1.0").replace("buffer: 40.0",
                                                                      "buffer: 1000.0")
    shutil.copy(region_out / "dem.tif", tmp_path / "dem.tif")
    shutil.copy(region_out / "rel.gpkg", tmp_path / "rel.gpkg")
    (tmp_path / "r.yaml").write_text(text)
    code, err = _terminated(["region", tmp_path / "r.yaml", "-o", tmp_path / "out",
                             "--workers", "0", "-q"], tmp_path / "out")
    assert code == 143 and "Traceback" not in err, err


def test_sigterm_of_a_two_worker_ensemble_is_143_without_dask_tracebacks(tmp_path):
    _long_dambreak(tmp_path)
    (tmp_path / "e.yaml").write_text("base: long.yaml\nvary: {rheology.delta_deg: [0.0, 1.0]}\n")
    code, err = _terminated(["ensemble", tmp_path / "e.yaml", "-o", tmp_path / "ens",
                             "--workers", "2", "-q"], tmp_path / "ens", wait=1.0)
    assert code == 143, err
    assert "Traceback" not in err and "CommClosedError" not in err, err


def test_a_scenario_from_a_pipe_runs_and_a_device_that_never_ends_is_refused(tmp_path):
    text = DAMBREAK.read_text().replace("end: 137.0", "end: 2.0")
    done = subprocess.run([sys.executable, "-m", "avflow.cli", "run", "/dev/stdin", "-q", "-o",
                           str(tmp_path / "x.nc")], input=text, capture_output=True, text=True,
                          timeout=120, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "x.nc").is_file()
    started = time.monotonic()
    done = subprocess_cli("run", "/dev/zero", "-o", tmp_path / "y.nc")
    assert done.returncode == 2 and "not a regular file" in one_line(done.stderr)
    fifo = tmp_path / "named.yaml"  # a named pipe nobody writes to: would block for ever
    os.mkfifo(fifo)
    done = subprocess_cli("run", fifo, "-o", tmp_path / "y.nc")
    assert done.returncode == 2 and "not a regular file" in one_line(done.stderr)
    assert time.monotonic() - started < 60


def test_an_unparsable_csv_line_shows_the_field_and_a_few_characters(slope, tmp_path, capsys):
    secret = "confidential-survey-note-" * 40
    line = tmp_path / "line.csv"
    line.write_text(f"x,y\n{X0 + 100},{Y0 - 400}\n{X0 + 900},{secret}\n")
    code, _, err = cli(["path", slope / "run.nc", "--line", line, "-o", tmp_path / "p"], capsys)
    assert code == 2 and "line.csv:3: y (column 2) is not a number" in one_line(err)
    assert secret[:40] not in err and len(err) < 300
    line.write_text(f"x,y\n{X0 + 100},{Y0 - 400}\n{secret}\n")
    code, _, err = cli(["path", slope / "run.nc", "--line", line, "-o", tmp_path / "p"], capsys)
    assert code == 2 and "line.csv:3: x (column 1) is not a number" in one_line(err)
    assert secret[:40] not in err


# --- found by the fuzzer (tests/test_fuzz.py, long profile) ------------------------------------


def test_a_garbled_checksum_file_means_run_again_not_a_traceback(region_out, tmp_path, capsys):
    shutil.copytree(region_out / "out", tmp_path / "out")
    for name in ("dem.tif", "rel.gpkg", "r.yaml"):
        shutil.copy(region_out / name, tmp_path / name)
    checksum = next((tmp_path / "out" / "checksums").iterdir())
    data = bytearray(checksum.read_bytes())
    data[0] ^= 0xFF  # not UTF-8 any more: was a UnicodeDecodeError traceback
    checksum.write_bytes(bytes(data))
    code, _, err = cli(["region", tmp_path / "r.yaml", "-o", tmp_path / "out", "--workers", "0"],
                       capsys)
    assert code == 0 and "checksum does not match" in err and "Traceback" not in err


def test_a_garbled_member_checksum_means_run_again_not_a_traceback(tmp_path, capsys):
    (tmp_path / "base.yaml").write_text(DAMBREAK.read_text().replace("end: 137.0", "end: 5.0"))
    (tmp_path / "e.yaml").write_text("base: base.yaml\nvary: {rheology.delta_deg: [0.0]}\n")
    argv = ["ensemble", tmp_path / "e.yaml", "-o", tmp_path / "ens", "--workers", "0"]
    assert cli(argv + ["-q"], capsys)[0] == 0
    checksum = next((tmp_path / "ens" / "checksums").iterdir())
    checksum.write_bytes(b"\xc6" + checksum.read_bytes()[1:])
    code, _, err = cli(argv, capsys)
    assert code == 0 and "checksum" in err and "Traceback" not in err


def test_a_calibration_too_large_for_memory_is_refused_before_its_runs(dam_calibration,
                                                                       tmp_path, capsys):
    base = dam_calibration.parent / "base.yaml"
    base.write_text(base.read_text().replace("dx: 20.0", "dx: 1.0e-6"))
    code, _, err = cli(["calibrate", dam_calibration, "-o", tmp_path / "out"], capsys)
    assert code == 2 and "grid.dx" in one_line(err) and "$AVFLOW_MAX_MEMORY" in err
    assert "--max-memory" not in err and not (tmp_path / "out").exists()
