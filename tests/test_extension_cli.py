"""A registered friction law and map from the command line: ``--extensions FILE.py`` and
``$AVFLOW_EXTENSIONS`` load a file of ``avflow.extend`` registrations before the scenario is
read, and the workers of an ensemble load it before their members; a file that cannot be
loaded, or a scenario naming a law no file registered, is one line and exit 2.

Every case runs ``python -m avflow`` in a child process (registration changes a process for
good), all with one kernel cache: the first run compiles the law into the profile's kernels
(20-30 s), the others load them.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

LAW = '''"""A friction law and a map of one's own, as a user writes them."""
from avflow import extend


@extend.friction_law("linear_speed", parameters=("mu", "k"),
                     reference="a test law: mu + k |u|")
def linear_speed(mu, k, h, speed, normal_accel, g):
    return (mu + k * speed) * h * normal_accel, 0.0


@extend.output_map("peak_momentum", units="m2 s-1",
                   long_name="maximum momentum per unit width |h u|")
def peak_momentum(old, h, hu, hv, speed, t):
    momentum = h * speed
    return momentum if momentum > old else old
'''

SCENE = """name: ext-cli
terrain: {kind: profile, length: 600.0, slope: {kind: constant, theta_deg: 30.0}}
grid: {dx: 10.0}
release: {kind: parabola, center: 150.0, half_length: 60.0, max_thickness: 8.0}
rheology: {law: linear_speed, mu: 0.364, k: 0.0}
time: {end: 20.0, cfl: 0.5}
output: {every: 10.0}
"""


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """The extension file, a scenario and an ensemble using it, and broken files."""
    here = tmp_path_factory.mktemp("extension-cli")
    (here / "law.py").write_text(LAW)
    (here / "scene.yaml").write_text(SCENE)
    (here / "ens.yaml").write_text("base: scene.yaml\nvary:\n  rheology.k: [0.0, 0.05]\n")
    (here / "syntax.py").write_text("from avflow import extend\n\ndef law(:\n    pass\n")
    (here / "raises.py").write_text("from avflow import extend\n\nratio = 1 / 0\n")
    (here / "again.py").write_text(LAW)  # the same names as law.py, from another file
    return here


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    """The children's environment: one kernel cache for the module, no extension files."""
    cache = tmp_path_factory.mktemp("kernel-cache")
    out = {**os.environ, "AVFLOW_CACHE_DIR": str(cache),
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    out.pop("AVFLOW_EXTENSIONS", None)
    return out


def avflow(folder: Path, env: dict, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "avflow", *args], cwd=folder, env=env,
                          capture_output=True, text=True, timeout=600)


def _registered_map(path: Path):
    import xarray as xr

    with xr.open_dataset(path) as ds:
        var = ds["peak_momentum"]
        return dict(var.attrs), float(var.max()), ds.attrs["references"]


def test_run_with_extensions_writes_the_registered_map(folder, env):
    done = avflow(folder, env, "run", "--extensions", "law.py", "scene.yaml", "-o", "a.nc")
    assert done.returncode == 0, done.stderr
    attrs, peak, references = _registered_map(folder / "a.nc")
    assert attrs["units"] == "m2 s-1" and attrs["cell_methods"] == "duration: maximum"
    assert peak > 0.0
    assert "a test law: mu + k |u|" in references


def test_the_environment_variable_loads_the_same(folder, env):
    listed = {**env, "AVFLOW_EXTENSIONS": os.pathsep.join(["", str(folder / "law.py")])}
    done = avflow(folder, listed, "run", "scene.yaml", "-o", "b.nc", "-q")
    assert done.returncode == 0, done.stderr
    assert _registered_map(folder / "b.nc")[1] > 0.0


def test_without_the_file_the_law_is_unknown_in_one_line(folder, env):
    done = avflow(folder, env, "run", "scene.yaml", "-o", "c.nc")
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("avflow: error: scene.yaml:5:")
    assert "unknown law 'linear_speed'" in lines[0] and "--extensions FILE.py" in lines[0]
    assert not (folder / "c.nc").exists()


@pytest.mark.parametrize("given, says", [
    (["--extensions", "nothere.py"], "--extensions: nothere.py: no such file"),
    (["--extensions", "syntax.py"], "--extensions: syntax.py:3:9: syntax error"),
    (["--extensions", "raises.py"],
     "--extensions: raises.py:3: ZeroDivisionError: division by zero"),
    (["--extensions", "law.py", "--extensions", "again.py"],
     "--extensions: again.py:5: a friction law named 'linear_speed' exists already"),
    (["$", "nothere.py"], "$AVFLOW_EXTENSIONS: nothere.py: no such file"),
], ids=["missing", "syntax", "raises", "duplicate", "variable"])
def test_a_file_that_cannot_be_loaded_is_one_line_and_exit_2(folder, env, given, says):
    if given[0] == "$":
        env, given = {**env, "AVFLOW_EXTENSIONS": given[1]}, []
    done = avflow(folder, env, "ensemble", *given, "ens.yaml", "-o", "never")
    assert done.returncode == 2
    assert "Traceback" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"avflow: error: {says}"), done.stderr
    assert not (folder / "never").exists()  # refused before the ensemble started


def test_an_ensemble_on_a_dask_worker_runs_the_registered_law(folder, env):
    """Two members, one task each, on a local cluster of one worker process: the worker
    loads law.py before its first member and not again before its second."""
    import pandas as pd

    done = avflow(folder, env, "ensemble", "--extensions", "law.py", "ens.yaml", "-o", "ens",
                  "--workers", "1", "--batch", "1")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "local cluster" in done.stdout, done.stdout
    table = pd.read_csv(folder / "ens" / "summary.csv")
    assert list(table["status"].isin(["at_rest", "completed"])) == [True, True], table.error
    assert table["runout"].iloc[1] < table["runout"].iloc[0]  # k = 0.05 brakes
    for name in table["file"]:
        assert _registered_map(folder / "ens" / name)[1] > 0.0
