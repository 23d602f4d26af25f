"""What `avflow run` imports and how it ends: no dask.array where no dask array is made (xarray
would import it for every variable), dask arrays still recognised once dask is imported, and
the command's own process (the collector's settings) giving the same file."""

import importlib.util
import os
import subprocess
import sys

import pytest
import xarray as xr

from conftest import REPO, SCENARIOS

FAST = SCENARIOS / "seed_dambreak_flat_dx20.yaml"  # 100 cells

needs_dask = pytest.mark.skipif(importlib.util.find_spec("dask") is None,
                                reason="dask is not installed: nothing to defer")


def python(code: str, *args, cwd=None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])}
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True,
                          text=True, env=env, cwd=cwd, timeout=600)


@needs_dask
def test_a_file_is_written_and_read_without_dask_array(tmp_path):
    code = """
import sys
import numpy as np
import xarray as xr
from avflow.output.netcdf import write_netcdf

ds = xr.Dataset({"h": (("time", "x"), np.ones((2, 3)))}, coords={"x": [0.0, 1.0, 2.0]})
write_netcdf(ds, sys.argv[1])
with xr.open_dataset(sys.argv[1], engine="netcdf4") as back:
    assert float(back.h.sum()) == 6.0
print("dask.array" in sys.modules)
"""
    done = python(code, tmp_path / "a.nc")
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["False"]


@needs_dask
def test_dask_arrays_are_still_dask_arrays_once_dask_is_imported():
    code = """
import numpy as np
import xarray as xr
import avflow.output.dataset  # the deferred record of dask in place
from xarray.namedarray import pycompat

before = xr.DataArray(np.zeros(4), dims="x")  # no dask yet
assert before.chunks is None
import dask
import dask.array as da

lazy = xr.DataArray(da.zeros(4, chunks=2), dims="x")
assert isinstance(lazy.data, da.Array) and lazy.chunks == ((2, 2),)
assert float((lazy + before).sum().compute()) == 0.0
masked = xr.Variable("x", da.from_array(np.ma.masked_array([1.0, 2.0], [False, True]), 1))
assert np.isnan(masked.values[1])  # xarray's masked-dask branch: it saw the dask array
assert str(pycompat.mod_version("dask")) == dask.__version__
assert type(pycompat._cached_duck_array_modules["dask"]) is pycompat.DuckArrayModule
print("ok")
"""
    done = python(code)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["ok"]


def test_a_deferred_record_asks_dask_only_when_asked_for_more_than_the_class():
    from xarray.namedarray import pycompat

    from avflow.output.xarray_dask import _deferred_class

    record = _deferred_class(pycompat.DuckArrayModule)()
    if "dask.array" not in sys.modules:
        assert record.type == ()
    else:  # this process imported dask already: the record is xarray's own from here on
        import dask.array as da

        assert record.type == (da.Array,)


def test_the_command_imports_no_dask_array_and_writes_the_same_file(tmp_path):
    # main() with no arguments is the command itself (its collector settings); main([...])
    # is main() called in a longer process, as in the other tests
    code = """
import sys
from avflow.cli import main

sys.argv = ["avflow", "run", sys.argv[1], "-o", sys.argv[2], "-q"]
code = main()
print(code, "dask.array" in sys.modules)
"""
    done = python(code, FAST, tmp_path / "cmd.nc")
    assert done.returncode == 0, done.stderr
    code, imported = done.stdout.split()
    assert code == "0"
    if importlib.util.find_spec("dask") is not None:
        assert imported == "False"
    from avflow.cli import main

    assert main(["run", str(FAST), "-o", str(tmp_path / "lib.nc"), "-q"]) == 0
    a = xr.open_dataset(tmp_path / "cmd.nc", decode_times=False)
    b = xr.open_dataset(tmp_path / "lib.nc", decode_times=False)
    with a, b:
        run_times = ["wall_time", "compile_time", "cell_updates_per_second"]
        xr.testing.assert_identical(a.drop_vars(run_times, errors="ignore"),
                                    b.drop_vars(run_times, errors="ignore").assign_attrs(
                                        {k: a.attrs[k] for k in a.attrs
                                         if k in ("history", "date_created")}))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cmd.nc", "lib.nc"]
