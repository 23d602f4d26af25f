"""Ensembles trust what they check (issue 8, item 6): resume reruns a member whose file was
damaged or belongs to another member; an unreachable scheduler, Ctrl-C and a release shapefile
without its .dbf are one line each. Only the project's own scenarios and data."""

import os
import shutil
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from avflow.cli import main
from avflow.ensemble.orchestrate import run_ensemble
from avflow.ensemble.spec import load_ensemble
from conftest import REPO, SCENARIOS

SUMMARIES = ("runout", "time_to_stop", "deposit_max_thickness", "deposit_length",
             "deposit_volume", "mass_balance_error")


def small_ensemble(tmp_path, deltas=(15.0, 20.0), dx=25.0):
    """The seed's section 6 scene on a coarse grid, one member per friction angle."""
    text = (SCENARIOS / "seed_exponential_coulomb15.yaml").read_text()
    (tmp_path / "base.yaml").write_text(text.replace("dx: 6.25", f"dx: {dx}"))
    path = tmp_path / "ens.yaml"
    path.write_text(f"name: trust\nbase: base.yaml\nvary:\n"
                    f"  rheology.delta_deg: [{', '.join(str(d) for d in deltas)}]\n")
    return load_ensemble(path), path


def member_file(out, member):
    return out / "members" / f"{member.scenario_hash}.nc"


def flip_bytes_of(path, values):
    """Flip every bit of the first stored byte of ``values`` (float64, found once in the file)."""
    data = bytearray(path.read_bytes())
    needle = np.ascontiguousarray(values, dtype="<f8").tobytes()
    at = data.find(needle)
    assert at >= 0 and data.find(needle, at + 1) < 0, "stored bytes not found exactly once"
    data[at] ^= 0xFF
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("where", ["moving_volume", "runout"])
def test_resume_reruns_a_member_file_with_flipped_bytes(where, tmp_path, capsys):
    ens, _ = small_ensemble(tmp_path)
    out = tmp_path / "out"
    first = run_ensemble(ens, out, workers=0)
    assert first.ok and first.ran == 2
    damaged = member_file(out, ens.members[0])
    with xr.open_dataset(damaged, decode_times=False) as ds:
        good = ds[where].values.copy()
    flip_bytes_of(damaged, good)
    with xr.open_dataset(damaged, decode_times=False) as ds:  # still reads, silently wrong
        assert not np.array_equal(ds[where].values, good)
    capsys.readouterr()
    again = run_ensemble(ens, out, workers=0)
    assert (again.ran, again.reused, again.failed) == (1, 1, 0)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and "member 0 " in lines[0] and "checksum" in lines[0], lines
    with xr.open_dataset(damaged, decode_times=False) as ds:
        np.testing.assert_array_equal(ds[where].values, good)
    table = pd.read_csv(out / "summary.csv")
    for name in SUMMARIES:
        np.testing.assert_array_equal(table[name].values, first.table[name].values)


@pytest.mark.parametrize("with_checksum", [False, True])
def test_resume_reruns_another_members_file_in_its_slot(with_checksum, tmp_path, capsys):
    ens, _ = small_ensemble(tmp_path)
    out = tmp_path / "out"
    first = run_ensemble(ens, out, workers=0)
    assert first.ok
    deposits = first.table["deposit_max_thickness"].values
    assert deposits[0] != deposits[1]
    a, b = ens.members
    shutil.copy(member_file(out, b), member_file(out, a))
    if with_checksum:  # the whole record copied: the checksum matches, the scenario does not
        sums = out / "checksums"
        shutil.copy(sums / f"{b.scenario_hash}.sha256", sums / f"{a.scenario_hash}.sha256")
    capsys.readouterr()
    again = run_ensemble(ens, out, workers=0)
    assert (again.ran, again.reused) == (1, 1)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and "member 0 " in lines[0], lines
    if with_checksum:
        assert b.scenario_hash in lines[0], lines
    table = pd.read_csv(out / "summary.csv")
    np.testing.assert_array_equal(table["deposit_max_thickness"].values, deposits)
    with xr.open_dataset(member_file(out, a), decode_times=False) as ds:
        assert ds.attrs["scenario_hash"] == a.scenario_hash


def test_resume_reruns_a_file_without_checksum(tmp_path, capsys):
    ens, _ = small_ensemble(tmp_path)
    out = tmp_path / "out"
    run_ensemble(ens, out, workers=0)
    (out / "checksums" / f"{ens.members[1].scenario_hash}.sha256").unlink()
    capsys.readouterr()
    again = run_ensemble(ens, out, workers=0)
    assert (again.ran, again.reused) == (1, 1)
    err = capsys.readouterr().err
    assert "member 1 " in err and "no checksum" in err, err
    assert run_ensemble(ens, out, workers=0).reused == 2  # checked and trusted now


def _unused_local_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_scheduler_is_one_line_exit_2(tmp_path, capsys):
    _, path = small_ensemble(tmp_path)
    address = f"tcp://127.0.0.1:{_unused_local_port()}"
    started = time.perf_counter()
    code = main(["ensemble", str(path), "-o", str(tmp_path / "out"), "--scheduler", address,
                 "--connect-timeout", "2"])
    assert code == 2
    assert time.perf_counter() - started < 20
    err = capsys.readouterr().err
    assert err.startswith("avflow: error: ") and address in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err


def test_missing_scheduler_file_is_one_line_exit_2(tmp_path, capsys):
    _, path = small_ensemble(tmp_path)
    code = main(["ensemble", str(path), "-o", str(tmp_path / "out"), "--scheduler",
                 str(tmp_path / "sched.json")])
    assert code == 2
    err = capsys.readouterr().err
    assert "sched.json" in err and len(err.strip().splitlines()) == 1, err


def test_ctrl_c_is_one_line_exit_130_and_the_cluster_is_closed(tmp_path):
    """SIGINT to the whole process group, as a terminal's Ctrl-C sends it: the parent and
    its local dask workers all get it."""
    _, path = small_ensemble(tmp_path, deltas=tuple(14.0 + 0.5 * k for k in range(16)),
                             dx=12.5)
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    run = subprocess.Popen([sys.executable, "-m", "avflow.cli", "ensemble", str(path), "-o",
                            str(out), "--workers", "1", "--batch", "1"], cwd=REPO, env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and run.poll() is None:
            if len(list((out / "members").glob("*.nc"))) >= 2:
                break
            time.sleep(0.02)
        assert run.poll() is None, run.communicate()
        os.killpg(run.pid, signal.SIGINT)
        stdout, stderr = run.communicate(timeout=60)
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGKILL)
            run.wait(10)
    assert run.returncode == 130, stdout + stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    assert "interrupted" in lines[0] and "resume" in lines[0], lines
    # Nothing of the cluster is left: the process group is empty once the parent is gone.
    deadline = time.monotonic() + 10
    while True:
        try:
            os.killpg(run.pid, 0)
        except ProcessLookupError:
            break
        assert time.monotonic() < deadline, "worker processes outlived the ensemble"
        time.sleep(0.1)
    done = len(list((out / "checksums").glob("*.sha256")))  # written after each member file
    assert done >= 2 and f"{done} of 16" in lines[0], lines


def test_release_shapefile_without_dbf_is_one_line_exit_2(tmp_path, capsys):
    from avflow.terrain.polygons import PolygonError, read_polygons

    source = REPO / "data" / "avaframe" / "avaAlr"
    for suffix in (".shp", ".shx", ".prj"):
        shutil.copy(source / f"relAlr{suffix}", tmp_path / f"relAlr{suffix}")
    with pytest.raises(PolygonError, match="relAlr.dbf"):
        read_polygons(tmp_path / "relAlr.shp")
    scenario = tmp_path / "alr.yaml"
    scenario.write_text(f"""name: alr-no-dbf
terrain: {{kind: dem, path: {source / 'avaAlr.tif'}}}
grid: {{dx: 20.0}}
release: {{kind: polygon, path: relAlr.shp}}
rheology: {{law: voellmy, mu: 0.155, xi: 4000.0}}
time: {{end: 1.0}}
output: {{every: 1.0}}
""")
    assert main(["run", str(scenario), "-o", str(tmp_path / "alr.nc")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("avflow: error: ") and "relAlr.dbf" in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
