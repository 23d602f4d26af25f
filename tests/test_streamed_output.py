"""Issue 11, item 3: snapshots streamed to the NetCDF file as they are taken.

``avflow run`` and ensemble members append each snapshot to a temporary file next to the
output and rename it over the output at the end (avflow.output.stream). The finished file
equals the in-memory one (``write_netcdf(to_dataset(result))``) variable by variable; a run
that fails or is interrupted leaves no file, no temporary, and an older output untouched.
"""

import re

import netCDF4
import numpy as np
import pytest
import xarray as xr

import avflow
from avflow.cli import main
from avflow.errors import RunFailed
from avflow.output.dataset import to_dataset
from avflow.output.netcdf import write_netcdf
from avflow.output.stream import SnapshotStream
from avflow.simulation.resources import BYTES_PER_CELL_SNAPSHOT, check_resources, estimate
from avflow.simulation.runner import cell_flags, simulate
from conftest import SCENARIOS
from test_cli_output import strict_messages, ugrid_order
from test_limits import DAMBREAK, poison
from test_xarray_file import dem_scenario

FAST = SCENARIOS / "seed_dambreak_flat_dx20.yaml"  # 100 cells, 138 snapshots

#: Only the storage of these differs in a streamed file: ``time`` is unlimited, so the
#: variables on time alone are chunked, and flow_state is one chunk per snapshot.
STORAGE = ("chunksizes", "contiguous", "preferred_chunks")


class Both(SnapshotStream):
    """A stream that also keeps every snapshot in memory: one run gives both files (the
    same wall_time), the streamed one and ``write_netcdf(to_dataset(result))``."""

    def record(self, state, moving, terrain):
        super().record(state, moving, terrain)
        self.h.append(state.h.copy())
        self.hu.append(state.hu.copy())
        self.hv.append(state.hv.copy())
        self.flag.append(cell_flags(state))


def scenarios(tmp_path):
    return {
        "profile": avflow.load_scenario(FAST).with_updates({"time.end": 20.0}),
        "grid": avflow.load_scenario(SCENARIOS / "plane_box_2d.yaml").with_updates(
            {"time.end": 10.0, "output.every": 2.0,
             "output.release_time": "2024-02-03T11:15:00+01:00"}),
        "dem": dem_scenario(tmp_path),  # GeoTIFF with a CRS and a NODATA hole
        "triangles": avflow.load_scenario(
            SCENARIOS / "plane_cylinder_triangles.yaml").with_updates({"time.end": 4.0}),
    }


def both_files(scenario, tmp_path):
    with Both(tmp_path / "streamed.nc") as stream:
        result = simulate(scenario, snapshots=stream)
        stream.finish(result)
    old = write_netcdf(to_dataset(result), tmp_path / "in_memory.nc")
    return old, tmp_path / "streamed.nc"


def assert_same_file(old, new):
    """Variable by variable: names and order, dims, dtypes, values, attributes and their
    order, encodings (compression, _FillValue, dtype, coordinates), global attributes."""
    with xr.open_dataset(old, decode_cf=False) as a, xr.open_dataset(new, decode_cf=False) as b:
        xr.testing.assert_identical(a, b)
        assert list(a.variables) == list(b.variables)
        assert list(a.dims) == list(b.dims)
        assert list(a.attrs) == list(b.attrs)
        assert a.encoding["unlimited_dims"] == set() and b.encoding["unlimited_dims"] == {"time"}
        for name in a.variables:
            ea, eb = ({k: v for k, v in d.encoding.items() if k != "source"}
                      for d in (a[name], b[name]))
            if a[name].dims[:1] == ("time",) and (a[name].ndim == 1 or name == "flow_state"):
                assert ea["contiguous"] and not eb["contiguous"], name
                assert eb["chunksizes"] == (1, *a[name].shape[1:]) if a[name].ndim > 1 \
                    else eb["chunksizes"] == a[name].shape, name
                ea, eb = ({k: v for k, v in e.items() if k not in STORAGE} for e in (ea, eb))
            assert ea == eb, name
    with xr.open_dataset(old) as a, xr.open_dataset(new) as b:  # CF decoding (dates, masks)
        xr.testing.assert_identical(a, b)
    xr.testing.assert_identical(avflow.open_run(old), avflow.open_run(new))
    with netCDF4.Dataset(old) as a, netCDF4.Dataset(new) as b:
        assert a.ncattrs() == b.ncattrs() and a.data_model == b.data_model
        for name, var in a.variables.items():
            assert var.ncattrs() == b[name].ncattrs(), name  # the order of ncdump too
            assert var.filters() == b[name].filters(), name


@pytest.mark.parametrize("kind", ["profile", "grid", "dem", "triangles"])
def test_streamed_file_equals_the_in_memory_one(kind, tmp_path):
    scenario = scenarios(tmp_path)[kind]
    old, new = both_files(scenario, tmp_path)
    assert_same_file(old, new)
    with xr.open_dataset(new, decode_cf=False) as ds:
        assert ds["h"].encoding["zlib"] and ds["h"].dtype == np.float32
        assert ds["h"].encoding["chunksizes"][0] == 1
        if kind == "dem":  # the hole outside the DEM: NaN fill, -1 flags
            assert np.isnan(ds["h"].attrs["_FillValue"])
            assert (ds["flow_state"].values == -1).any()
        if kind == "grid":
            assert ds["time"].attrs["units"] == "seconds since 2024-02-03 10:15:00"
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix == ".nc") == [
        "in_memory.nc", "streamed.nc"]
    assert not list(tmp_path.glob(".*.tmp"))


def test_cli_file_equals_the_in_memory_one_but_for_the_clocks(tmp_path, capsys):
    """`avflow run` (streamed) against avflow.run + write_netcdf of the same scenario: two
    runs, so only wall_time and compile_time differ."""
    out = tmp_path / "cli.nc"
    assert main(["run", str(FAST), "-o", str(out), "--set", "time.end=30"]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    assert line.startswith("seed-dambreak-flat-dx20:") and "mass error" in line
    ds = avflow.run(FAST, overrides={"time.end": 30.0})
    old = write_netcdf(ds, tmp_path / "api.nc")
    clocks = ["wall_time", "compile_time"]
    with xr.open_dataset(old, decode_cf=False) as a, xr.open_dataset(out, decode_cf=False) as b:
        xr.testing.assert_identical(a.drop_vars(clocks), b.drop_vars(clocks))
        assert list(a.variables) == list(b.variables)


@pytest.mark.parametrize("kind", ["grid", "triangles"])
def test_strict_cf_says_the_same_of_both_files(kind, tmp_path):
    """The same, but for one mistake of the checker that the unlimited time avoids: it
    takes UGRID's node dimension for a non-spatial one that should sit left of time, unless
    time is the record dimension."""
    old, new = both_files(scenarios(tmp_path)[kind], tmp_path)
    expected = strict_messages(old)
    if kind == "triangles":
        expected = [m for m in expected
                    if m not in [ugrid_order(n) for n in ("flow_state", "h", "u", "v")]]
    assert strict_messages(new) == expected


# --- one snapshot in memory: the file grows while the run goes on ---------------------------


def temporaries(folder):
    return [p for p in folder.iterdir() if re.fullmatch(r"\.out\.nc\.[a-z0-9_]{8}\.tmp", p.name)]


def test_snapshots_go_to_the_temporary_file_as_they_are_taken(tmp_path):
    out = tmp_path / "out.nc"
    seen = []

    def progress(t, t_end):
        assert not out.exists()  # the output appears at the end only
        (tmp,) = temporaries(tmp_path)
        seen.append((t, stream.records, stream._nc.dimensions["time"].size))

    with SnapshotStream(out) as stream:
        result = simulate(avflow.load_scenario(FAST).with_updates({"time.end": 5.0}),
                          progress=progress, snapshots=stream)
        stream.finish(result)
    # t = 0, then one record in the file per output time
    assert seen == [(float(k), k + 1, k + 1) for k in range(1, 6)]
    assert stream.h == [] and stream.hu == [] and stream.flag == []  # no field kept
    assert stream.records == len(stream.time) == 6
    assert temporaries(tmp_path) == [] and out.is_file()


def test_a_streamed_run_counts_one_snapshot_against_the_memory_limit(tmp_path, capsys):
    """13701 snapshots of 100 cells: 105 MiB held in memory, 8 KiB streamed."""
    path = tmp_path / "s.yaml"
    path.write_text(DAMBREAK.replace("every: 1.0", "every: 0.01"))
    scenario = avflow.load_scenario(path)
    held, streamed = estimate(scenario), estimate(scenario, streamed=True)
    assert held.snapshots == streamed.snapshots == 13701
    assert held.snapshot_bytes == 100 * 13701 * BYTES_PER_CELL_SNAPSHOT
    assert streamed.snapshot_bytes == 100 * BYTES_PER_CELL_SNAPSHOT
    assert streamed.file_bytes == held.file_bytes == 100 * 13701 * 13
    assert check_resources(scenario, "10M", streamed=True).streamed
    with pytest.raises(avflow.ScenarioError, match="13701 snapshots") as err:
        avflow.run(scenario, max_memory="10M")  # avflow.run returns them all: refused
    assert err.value.field == "output.every"


# --- interrupted, failed: no file, no temporary, the old output untouched -------------------


@pytest.fixture
def old_output(tmp_path):
    out = tmp_path / "out.nc"
    out.write_bytes(b"an older result, not to be touched")
    return out


def half_way_raises(error):
    def progress(t, t_end):
        if t >= t_end / 2:
            raise error
    return progress


@pytest.mark.parametrize("error", [KeyboardInterrupt(), RuntimeError("callback bug")])
def test_run_interrupted_half_way_leaves_nothing(error, tmp_path, old_output):
    before = old_output.read_bytes()
    scenario = avflow.load_scenario(FAST).with_updates({"time.end": 20.0})
    with pytest.raises(type(error)):
        with SnapshotStream(old_output) as stream:
            stream.finish(simulate(scenario, progress=half_way_raises(error),
                                   snapshots=stream))
    assert stream.records == 11  # t = 0 .. 10 s were written before the interrupt
    assert old_output.read_bytes() == before
    assert sorted(tmp_path.iterdir()) == [old_output]


def test_cli_interrupted_half_way_exits_130_and_leaves_nothing(tmp_path, old_output,
                                                               monkeypatch, capsys):
    import avflow.cli as cli

    before = old_output.read_bytes()
    monkeypatch.setattr(cli.Progress, "__call__",
                        lambda self, t, t_end: half_way_raises(KeyboardInterrupt())(t, t_end))
    assert main(["run", str(FAST), "-o", str(old_output)]) == 130
    assert "interrupted" in capsys.readouterr().err
    assert old_output.read_bytes() == before
    assert sorted(tmp_path.iterdir()) == [old_output]
    # a new folder made for the output goes too
    new = tmp_path / "new" / "sub" / "out.nc"
    assert main(["run", str(FAST), "-o", str(new)]) == 130
    assert sorted(tmp_path.iterdir()) == [old_output]


def test_failed_run_leaves_nothing_and_the_old_output_untouched(tmp_path, old_output,
                                                                monkeypatch, capsys):
    poison(monkeypatch)  # NaN in h from t = 5 s: RunFailed
    before = old_output.read_bytes()
    with pytest.raises(RunFailed):
        with SnapshotStream(old_output) as stream:
            stream.finish(simulate(avflow.load_scenario(FAST), snapshots=stream))
    assert stream.records == 6  # t = 0 .. 5 s, the last one holding the NaN
    assert main(["run", str(FAST), "-o", str(old_output)]) == 1
    assert "run failed at t = 5 s" in capsys.readouterr().err
    assert old_output.read_bytes() == before
    assert sorted(tmp_path.iterdir()) == [old_output]


def test_failed_ensemble_member_leaves_no_temporary(tmp_path, monkeypatch):
    from avflow.ensemble.orchestrate import run_member

    poison(monkeypatch)
    row = run_member(DAMBREAK, str(tmp_path / "m.nc"))
    assert row["status"] == "failed" and "h not finite" in row["error"]
    assert list(tmp_path.iterdir()) == []


def test_ensemble_member_file_is_streamed_and_equals_the_in_memory_one(tmp_path):
    from avflow.ensemble.orchestrate import read_member_row, run_member

    scenario = avflow.load_scenario(FAST).with_updates({"time.end": 10.0})
    member = tmp_path / "members" / f"{scenario.scenario_hash()}.nc"
    row = run_member(scenario.source_text, str(member))
    assert row["status"] == "completed" and not row["reused"]
    assert read_member_row(member) is not None  # its checksum was written after it
    assert [p.name for p in member.parent.iterdir()] == [member.name]
    old = write_netcdf(avflow.run(scenario), tmp_path / "old.nc")
    clocks = ["wall_time", "compile_time"]
    with xr.open_dataset(old, decode_cf=False) as a, \
            xr.open_dataset(member, decode_cf=False) as b:
        xr.testing.assert_identical(a.drop_vars(clocks), b.drop_vars(clocks))
