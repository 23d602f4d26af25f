"""Nothing lost, nothing invented (issue 33): every command that writes refuses its own
inputs (and their sidecars), devices and folders, writes through a temporary and a rename,
says when an output is held by another command, and never reports a non-finite result or a
full disk as a success; bounded inputs and resources; one line, never a traceback.

Each test here failed before its fix (the audit's case, rebuilt small)."""

import contextlib
import hashlib
import http.server
import json
import os
import resource
import shutil
import signal
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from avflow.cli import main, summary_line
from conftest import REPO, SCENARIOS
from test_cli_habits import run_cli as cli

KOT = REPO / "data" / "avaframe" / "avaKot"
DAMBREAK = SCENARIOS / "seed_dambreak_flat_dx20.yaml"
PLANE = SCENARIOS / "plane_box_2d.yaml"


def one_line(err: str) -> str:
    """The error output is one line, not a traceback."""
    assert "Traceback" not in err, err
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert len(lines) == 1, err
    return lines[0]


def subprocess_cli(*argv, timeout=120, **kw):
    return subprocess.run([sys.executable, "-m", "avflow.cli", *map(str, argv)],
                          capture_output=True, text=True, timeout=timeout, **kw)


def digests(folder: Path) -> dict:
    """Every file under ``folder``: its bytes' sha256 (what a failed command must not
    change)."""
    return {p.relative_to(folder): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def temporaries(folder: Path) -> list:
    return [p for p in folder.rglob("*") if p.name.endswith(".tmp") or p.name.endswith(".lock")]


@pytest.fixture
def kot(tmp_path):
    """A scenario on the avaKot DEM (40 m: quick) with its release shapefile and a DEM .prj
    beside it, in a folder of its own."""
    folder = tmp_path / "kot"
    shutil.copytree(KOT, folder)
    (folder / "avaKot.prj").write_text((folder / "relKot.prj").read_text())
    (folder / "ok.yaml").write_text(
        "name: kot\nterrain: {kind: dem, path: avaKot.asc}\ngrid: {dx: 40.0}\n"
        "release: {kind: polygon, path: relKot.shp}\nrheology: {law: coulomb, delta_deg: 25}\n"
        "time: {end: 20.0}\n")
    return folder


@pytest.fixture(scope="module")
def box_run(tmp_path_factory):
    """A small grid run file (the 2D box on a plane, 10 s)."""
    folder = tmp_path_factory.mktemp("box")
    out = folder / "box.nc"
    assert main(["run", str(PLANE), "--set", "time.end=10", "-q", "-o", str(out)]) == 0
    return out


# --- 1. inputs overwritten --------------------------------------------------------------------


@pytest.mark.parametrize("name", ["relKot.dbf", "relKot.shx", "relKot.prj", "relKot.cpg",
                                  "avaKot.prj", "RELKOT.SHP.xml", "ok.yaml", "avaKot.asc"])
def test_run_refuses_every_file_the_scenario_reads(kot, capsys, name):
    if name == "RELKOT.SHP.xml":  # a GIS program's metadata beside the shapefile, any case
        (kot / name).write_text("<metadata/>")
    before = digests(kot)
    code, out, err = cli(["run", kot / "ok.yaml", "-o", kot / name], capsys)
    assert code == 2
    assert "is an input of this command" in one_line(err)
    assert "wrote" not in out
    assert digests(kot) == before and not temporaries(kot)


def test_run_refuses_an_input_through_a_link_or_a_hard_link(kot, capsys, tmp_path):
    before = digests(kot)
    (tmp_path / "soft.dbf").symlink_to(kot / "relKot.dbf")
    os.link(kot / "relKot.shx", tmp_path / "hard.shx")
    for target in (tmp_path / "soft.dbf", tmp_path / "hard.shx",
                   kot / "sub" / ".." / "relKot.dbf"):
        code, _, err = cli(["run", kot / "ok.yaml", "-o", target], capsys)
        assert code == 2 and "is an input" in one_line(err)
    assert digests(kot) == before


def test_run_refuses_to_write_its_path_analysis_over_an_input(kot, capsys):
    (kot / "x_path.csv").write_text("x,y\n1e5,2e5\n1.01e5,2e5\n")  # the path line
    (kot / "ok.yaml").write_text((kot / "ok.yaml").read_text()
                                 + "output: {path: {line: x_path.csv}}\n")
    before = digests(kot)
    code, _, err = cli(["run", kot / "ok.yaml", "-o", kot / "x.nc"], capsys)  # -> x_path.*
    assert code == 2 and "x_path.csv: is an input" in one_line(err)
    assert digests(kot) == before


# --- 2. every command: not its inputs, not a device, not a folder; temporary and rename --------


def test_plot_refuses_its_run_file_a_device_and_a_folder(box_run, capsys, tmp_path):
    before = box_run.read_bytes()
    for target, why in [(box_run, "is an input"), ("/dev/null", "not a regular file"),
                        (tmp_path, "is a folder")]:
        code, _, err = cli(["plot", box_run, "-o", target], capsys)
        assert code == 2 and why in one_line(err)
    assert box_run.read_bytes() == before
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


def test_export_and_path_refuse_their_inputs(box_run, capsys, tmp_path):
    before = box_run.read_bytes()
    # export names its rasters <stem>_<map>.tif: one of them is made the input here
    copy = tmp_path / "box.nc"
    shutil.copy(box_run, copy)
    (tmp_path / "box_peak_speed.tif").symlink_to(copy)
    code, out, err = cli(["export", copy, "-o", tmp_path, "--variables",
                          "peak_thickness,peak_speed"], capsys)
    assert code == 2 and "is an input" in one_line(err) and "wrote" not in out
    assert not (tmp_path / "box_peak_thickness.tif").exists()  # checked before the first
    code, _, err = cli(["export", box_run, "-o", box_run], capsys)
    assert code == 2 and "not a folder" in one_line(err)
    line = tmp_path / "line.csv"
    line.write_text("x,y\n0,100\n1000,100\n")
    code, _, err = cli(["path", box_run, "--line", line, "-o", tmp_path / "line"], capsys)
    assert code == 2 and "line.csv: is an input" in one_line(err)
    assert box_run.read_bytes() == before and line.read_text() == "x,y\n0,100\n1000,100\n"


def test_ensemble_refuses_a_folder_whose_files_are_its_inputs(tmp_path, capsys):
    base = tmp_path / "ensemble.nc"  # a base scenario named like the ensemble's output
    base.write_text(DAMBREAK.read_text())
    spec = tmp_path / "e.yaml"
    spec.write_text(f"base: {base.name}\nvary: {{rheology.delta_deg: [0.0, 1.0]}}\n")
    before = digests(tmp_path)
    code, _, err = cli(["ensemble", spec, "-o", tmp_path, "--workers", "0"], capsys)
    assert code == 2 and "is an input" in one_line(err)
    assert digests(tmp_path) == before
    file = tmp_path / "afile"
    file.write_text("mine")
    code, _, err = cli(["ensemble", spec, "-o", file, "--workers", "0"], capsys)
    assert code == 2 and "not a folder" in one_line(err) and file.read_text() == "mine"


# --- 3. a full disk ----------------------------------------------------------------------------


def _limited(nbytes):
    """preexec_fn: files larger than ``nbytes`` cannot be written (EFBIG, as a full disk;
    Python ignores SIGXFSZ)."""
    return lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, nbytes))


def test_export_on_a_full_disk_fails_and_keeps_the_old_raster(box_run, tmp_path):
    out = tmp_path / "gis"
    assert subprocess_cli("export", box_run, "-o", out, "--variables",
                          "peak_thickness").returncode == 0
    old = (out / "box_peak_thickness.tif").read_bytes()
    assert len(old) > 600
    done = subprocess_cli("export", box_run, "-o", out, "--variables", "peak_thickness",
                          preexec_fn=_limited(600))
    assert done.returncode == 1, done.stderr
    assert "no CRS" in done.stderr  # the plane has none: one warning, then the error
    assert "cannot write" in one_line(done.stderr.split("\n", 1)[1]) and "wrote" not in done.stdout
    assert (out / "box_peak_thickness.tif").read_bytes() == old
    assert not temporaries(out)


@contextlib.contextmanager
def full_tmpfs(tmp_path):
    """A 64 KiB tmpfs filled to the last byte (root and mount needed: skipped without)."""
    mnt = tmp_path / "full"
    mnt.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs",
                                            str(mnt)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here (not root, or no mount)")
    try:
        with contextlib.suppress(OSError), open(mnt / "fill", "wb") as f:
            while True:
                f.write(b"\0" * 4096)
                f.flush()
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=False)


def test_a_full_disk_is_said_as_such_and_leaves_nothing(box_run, tmp_path):
    with full_tmpfs(tmp_path) as mnt:
        done = subprocess_cli("run", DAMBREAK, "-o", mnt / "x.nc")
        assert done.returncode == 1
        assert "No space left on device" in one_line(done.stderr)  # was "Permission denied"
        done = subprocess_cli("export", box_run, "-o", mnt)
        assert done.returncode == 1 and "wrote" not in done.stdout
        assert "cannot write" in done.stderr.strip().splitlines()[-1]
        assert sorted(p.name for p in mnt.iterdir()) == ["fill"]


# --- 4. two commands on one output --------------------------------------------------------------


def test_a_held_output_is_refused_with_its_holder(tmp_path, capsys):
    from avflow.files import output_lock

    out = tmp_path / "x.nc"
    with output_lock(out):
        code, _, err = cli(["run", DAMBREAK, "-o", out], capsys)
    assert code == 2
    assert f"in use by another avflow command (pid {os.getpid()} on" in one_line(err)
    assert not out.exists() and not temporaries(tmp_path)
    spec = tmp_path / "e.yaml"
    spec.write_text(f"base: {DAMBREAK}\nvary: {{rheology.delta_deg: [0.0, 1.0]}}\n")
    with output_lock(tmp_path / "ens", folder=True):
        code, _, err = cli(["ensemble", spec, "-o", tmp_path / "ens", "--workers", "0"], capsys)
    assert code == 2 and "in use by another avflow command" in err


def test_a_second_run_leaves_the_first_alone_and_sigterm_cleans_up(tmp_path):
    out = tmp_path / "long.nc"
    first = subprocess.Popen([sys.executable, "-m", "avflow.cli", "run", str(DAMBREAK),
                              "--set", "time.end=1e6", "--set", "output.every=1e5",
                              "--set", "grid.dx=1", "-q", "-o", str(out)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 90
        while not list(tmp_path.glob(".long.nc.*.tmp")) and time.monotonic() < deadline:
            time.sleep(0.2)
        live = list(tmp_path.glob(".long.nc.*.tmp"))
        assert live, "the first run never wrote its temporary"
        second = subprocess_cli("run", DAMBREAK, "-o", out)
        assert second.returncode == 2
        assert f"pid {first.pid}" in one_line(second.stderr)
        assert all(p.exists() for p in live)  # the first run's temporary is still there
        first.send_signal(signal.SIGTERM)
        _, err = first.communicate(timeout=60)
    finally:
        first.kill()
    assert first.returncode == 143 and one_line(err) == "avflow: terminated"
    assert sorted(tmp_path.iterdir()) == []  # no temporary, no lock, no file


# --- 5-8. bounded resources and inputs ---------------------------------------------------------


def test_members_are_counted_before_they_are_built(tmp_path, capsys):
    spec = tmp_path / "big.yaml"
    spec.write_text(f"base: {DAMBREAK}\nsample: {{n: 1000000000, ranges: "
                    "{rheology.delta_deg: [0, 5]}}\n")
    code, _, err = cli(["ensemble", spec, "-o", tmp_path / "o"], capsys)
    assert code == 2
    assert "1,000,000,000 members, more than the limit of 10,000" in one_line(err)
    values = ", ".join(str(v) for v in range(20))
    spec.write_text(f"base: {DAMBREAK}\nvary:\n" + "".join(
        f"  {key}: [{values}]\n" for key in ("rheology.delta_deg", "time.end", "grid.dx",
                                              "release.thickness", "release.position")))
    code, _, err = cli(["ensemble", spec, "-o", tmp_path / "o"], capsys)
    assert code == 2 and "3,200,000 members" in one_line(err) and "big.yaml:2:1: vary" in err
    spec.write_text(f"base: {DAMBREAK}\nvary: {{rheology.delta_deg: [0, 1, 2]}}\n")
    code, _, err = cli(["ensemble", spec, "-o", tmp_path / "o", "--max-members", "2"], capsys)
    assert code == 2 and "3 members, more than the limit of 2" in err
    assert not (tmp_path / "o").exists()


def test_refinement_is_counted_before_it_is_built(kot, capsys):
    code, _, err = cli(["run", kot / "ok.yaml", "--set", "grid.mesh=triangles", "--set",
                        "grid.dx=20", "--set", "grid.refine={levels: 8, angle_deg: 0.5}",
                        "--max-memory", "300M", "-o", kot / "x.nc"], capsys)
    assert code == 2
    assert "grid.refine.levels: refinement round" in one_line(err)
    assert "the memory limit allows" in err


def test_scenario_files_are_bounded_and_regular(tmp_path, capsys):
    big = tmp_path / "big.yaml"
    big.write_bytes(b"a" * (2 << 20))
    fifo = tmp_path / "pipe.yaml"
    os.mkfifo(fifo)
    for path, why in [("/dev/zero", "not a regular file"), (fifo, "not a regular file"),
                      (tmp_path, "a folder"), (big, "over 1 MiB"),
                      (tmp_path / ("x" * 300 + ".yaml"), "too long")]:
        code, _, err = cli(["run", path], capsys)
        assert code == 2 and why in one_line(err)
        code, _, err = cli(["ensemble", path, "-o", tmp_path / "o"], capsys)
        assert code == 2 and why in one_line(err)


class _Http(http.server.BaseHTTPRequestHandler):
    def do_GET(self):  # noqa: N802 - http.server's name
        self.send_response(200)
        self.end_headers()

    def log_message(self, *args):
        pass


def test_scheduler_problems_are_one_line_within_the_timeout(tmp_path):
    server = http.server.HTTPServer(("127.0.0.1", 0), _Http)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    spec = tmp_path / "e.yaml"
    spec.write_text(f"base: {DAMBREAK}\nvary: {{rheology.delta_deg: [0.0, 1.0]}}\n")
    (tmp_path / "bad.json").write_text('{"address": 5')
    (tmp_path / "other.json").write_text('{"foo": 1}')
    cases = [(f"tcp://127.0.0.1:{server.server_port}", "cannot connect within 3 s"),
             (tmp_path / "bad.json", "not a dask scheduler file"),
             (tmp_path / "other.json", "not a dask scheduler file"),
             ("foo://127.0.0.1:1", "unknown address scheme 'foo'")]
    try:
        for address, why in cases:
            started = time.monotonic()
            done = subprocess_cli("ensemble", spec, "-o", tmp_path / "o", "--scheduler",
                                  address, "--connect-timeout", "3", timeout=60)
            assert time.monotonic() - started < 30  # it hung for 150 s and more
            assert done.returncode == 2
            assert why in done.stderr and "Traceback" not in done.stderr
            assert "Exception ignored" not in done.stderr
            assert len(done.stderr.strip().splitlines()) == 1, done.stderr
            assert not (tmp_path / "o" / "members").exists()  # no empty members/ left
    finally:
        server.shutdown()


# --- 9-10. non-finite numbers are never a success ------------------------------------------------


def test_physics_beyond_the_float_range_is_refused(capsys, tmp_path):
    for key, value in [("physics.density", "1e37"), ("physics.gravity", "1e200")]:
        code, _, err = cli(["run", PLANE, "--set", f"{key}={value}", "-o", tmp_path / "x.nc"],
                           capsys)
        assert code == 2 and f"--set {key}={value}: must be in" in one_line(err)


def test_an_infinite_field_fails_the_run_and_keeps_the_old_file(capsys, tmp_path, monkeypatch):
    import avflow.output.stream as stream

    out = tmp_path / "x.nc"
    out.write_bytes(b"the previous good file")
    made = stream.to_dataset

    def with_inf(result, part="all"):
        ds = made(result, part=part)
        if "peak_pressure" in ds:
            ds["peak_pressure"].values[..., 0] = np.inf
        return ds

    monkeypatch.setattr(stream, "to_dataset", with_inf)
    code, out_text, err = cli(["run", DAMBREAK, "-o", out], capsys)
    assert code == 1 and "peak_pressure is infinite" in one_line(err)
    assert "wrote" not in out_text
    assert out.read_bytes() == b"the previous good file" and not temporaries(tmp_path)


def test_export_plot_and_path_refuse_an_edited_file_with_inf(box_run, capsys, tmp_path):
    edited = tmp_path / "edited.nc"
    with xr.open_dataset(box_run, decode_times=False) as ds:
        ds = ds.load()
    ds["peak_pressure"].values[3, 3] = np.inf
    ds.to_netcdf(edited)
    for argv in (["export", edited], ["plot", edited], ["path", edited]):
        code, out, err = cli(argv, capsys)
        assert code == 2 and "peak_pressure holds infinite values" in one_line(err)
        assert "wrote" not in out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["edited.nc"]


def test_a_path_line_far_off_or_overflowing_is_refused(box_run, capsys, tmp_path):
    huge, far = tmp_path / "huge.csv", tmp_path / "far.csv"
    huge.write_text("x,y\n1e308,1e308\n-1e308,-1e308\n")
    far.write_text("x,y\n1e7,1e7\n1.1e7,1e7\n")  # another CRS's numbers
    code, _, err = cli(["path", box_run, "--line", huge, "-o", tmp_path / "p"], capsys)
    assert code == 2 and "overflows" in one_line(err)
    code, _, err = cli(["path", box_run, "--line", far, "-o", tmp_path / "p"], capsys)
    assert code == 2 and "lies outside the map" in one_line(err)  # was "no cell reaches"


# --- tracebacks where one line belongs --------------------------------------------------------


@pytest.mark.parametrize("scenario", [PLANE, DAMBREAK])
def test_tiny_cells_are_refused_not_overflowed(scenario, capsys, tmp_path):
    code, _, err = cli(["run", scenario, "--set", "grid.dx=1e-200", "-o", tmp_path / "x.nc"],
                       capsys)
    assert code == 2 and "grid.dx" in one_line(err) and "memory limit" in err


@pytest.mark.parametrize("ncols,nrows", [(1, 1), (5, 1), (1, 4)])
def test_a_dem_of_one_cell_or_one_row_is_one_line(tmp_path, capsys, ncols, nrows):
    rows = "\n".join(" ".join(["5"] * ncols) for _ in range(nrows))
    (tmp_path / "d.asc").write_text(f"ncols {ncols}\nnrows {nrows}\nxllcorner 0\nyllcorner 0\n"
                                    f"cellsize 10\nNODATA_value -9999\n{rows}\n")
    (tmp_path / "d.yaml").write_text(
        "name: d\nterrain: {kind: dem, path: d.asc}\ngrid: {dx: 10.0}\nrelease: {kind: "
        "cylinder, center: [5, 5], radius: 20, thickness: 1}\nrheology: {law: coulomb, "
        "delta_deg: 25}\ntime: {end: 5.0}\n")
    code, _, err = cli(["run", tmp_path / "d.yaml", "-o", tmp_path / "x.nc"], capsys)
    assert code == 2 and "needs at least 2 x 2" in one_line(err)


def test_path_and_report_on_damaged_ensemble_folders(tmp_path, capsys):
    spec = tmp_path / "e.yaml"
    spec.write_text(f"base: {DAMBREAK}\nvary: {{rheology.delta_deg: [0.0, 1.0]}}\n")
    out = tmp_path / "ens"
    assert cli(["ensemble", spec, "-o", out, "--workers", "0", "-q"], capsys)[0] == 0
    members = sorted((out / "members").glob("*.nc"))
    members[0].write_bytes(members[0].read_bytes()[:500])  # truncated
    code, _, err = cli(["path", out], capsys)
    assert code == 2 and "member file cannot be read" in one_line(err)
    members[0].unlink()
    code, _, err = cli(["path", out], capsys)
    assert code == 2 and "member file missing" in one_line(err)
    (out / "ensemble.nc").write_bytes((out / "ensemble.nc").read_bytes()[:300])
    for argv in (["report", out], ["report", out / "ensemble.nc"]):
        code, _, err = cli(argv, capsys)
        assert code == 2 and "cannot be read as an avflow ensemble file" in one_line(err)


def test_names_over_the_file_systems_limit_are_one_line(box_run, capsys, tmp_path):
    long = tmp_path / ("n" * 300 + ".png")
    code, _, err = cli(["plot", box_run, "-o", long], capsys)
    assert code == 2 and "too long" in one_line(err)
    code, _, err = cli(["run", DAMBREAK, "-o", tmp_path / ("n" * 300 + ".nc")], capsys)
    assert code == 2 and "too long" in one_line(err)


def test_out_of_memory_past_the_estimate_is_one_line(capsys, tmp_path, monkeypatch):
    import avflow.simulation.runner as runner

    def no_memory(*args, **kw):
        raise MemoryError

    monkeypatch.setattr(runner, "build_terrain", no_memory)
    code, _, err = cli(["run", DAMBREAK, "--max-memory", "none", "-o", tmp_path / "x.nc"],
                       capsys)
    assert code == 1 and "out of memory" in one_line(err)
    assert not list(tmp_path.iterdir())


# --- smaller -------------------------------------------------------------------------------------


def test_a_release_on_a_near_vertical_bed_is_warned_of(tmp_path, capsys):
    scenario = tmp_path / "steep.yaml"
    scenario.write_text(
        "name: steep\nterrain: {kind: plane, slope_deg: 80.0, extent: {x: [0, 400], y: [0, "
        "200]}}\ngrid: {dx: 10.0}\nrelease: {kind: cylinder, center: [100, 100], radius: 50, "
        "thickness: 5}\nrheology: {law: coulomb, delta_deg: 20.0}\ntime: {end: 1.0}\n")
    code, _, err = cli(["run", scenario, "-o", tmp_path / "x.nc", "-q"], capsys)
    assert code == 0
    assert "bed area is 5.8 times its map area" in one_line(err)  # 1 / cos 80 deg = 5.76


def test_a_run_whose_mass_all_left_says_so(box_run):
    with xr.open_dataset(box_run, decode_times=False) as ds:
        ds = ds.load()
    ds["runout"] = np.nan
    ds["outflow_volume"] = ds["release_volume"]
    assert "runout: none on the map (all the mass flowed out" in summary_line(ds)
    ds["outflow_volume"] = 0.0
    # a map's runout is found along its path at a pressure limit: the line names both
    assert ("runout: none (no cell reaches pressure >= 1 kPa along the centre-of-mass track)"
            in summary_line(ds))
    assert "NaN m" not in summary_line(ds)


def test_a_raster_error_does_not_echo_the_file(tmp_path, capsys):
    dem = tmp_path / "d.tif"
    dem.write_text("secret line of a text file posing as a GeoTIFF\n" * 20)
    (tmp_path / "d.yaml").write_text(
        "name: d\nterrain: {kind: dem, path: d.tif}\ngrid: {dx: 10.0}\nrelease: {kind: "
        "cylinder, center: [5, 5], radius: 20, thickness: 1}\nrheology: {law: coulomb, "
        "delta_deg: 25}\ntime: {end: 5.0}\n")
    code, _, err = cli(["run", tmp_path / "d.yaml", "-o", tmp_path / "x.nc"], capsys)
    assert code == 2 and "secret line" not in one_line(err)


# --- found by the fuzzer (tests/test_fuzz.py, long profile) ------------------------------------


def test_a_list_where_the_stop_rule_belongs_is_one_line(tmp_path, capsys):
    scenario = tmp_path / "s.yaml"
    scenario.write_text(DAMBREAK.read_text().replace("output: {every: 1.0, stop_fraction: 0.0}",
                                                     "output: {every: 1.0, stop_rule: []}"))
    code, _, err = cli(["run", scenario, "-o", tmp_path / "x.nc"], capsys)
    assert code == 2 and "output.stop_rule" in one_line(err)  # was a TypeError traceback


def test_a_run_ended_by_max_steps_keeps_the_old_file(tmp_path, capsys):
    out = tmp_path / "x.nc"
    out.write_bytes(b"the previous good file")
    code, printed, err = cli(["run", DAMBREAK, "--set", "time.cfl=1e-3", "--set",
                              "time.max_steps=400", "-o", out], capsys)
    assert code == 1 and "time.max_steps (400) reached" in one_line(err)
    assert "wrote" not in printed
    assert out.read_bytes() == b"the previous good file"  # exit 1 wrote over it before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.nc"]
