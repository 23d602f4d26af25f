"""Issue 11, item 3: snapshots streamed to the NetCDF file as they are taken.

``avflow run`` and ensemble members append each snapshot to a temporary file next to the
output and rename it over the output at the end (avflow.output.stream). The finished file
equals the in-memory one (``write_netcdf(to_dataset(result))``) variable by variable; a run
that fails or is interrupted leaves no file, no temporary, and an older output untouched.
"""

import dataclasses
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
#: variables on time alone are chunked.
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
            if a[name].dims[:1] == ("time",) and a[name].ndim == 1:
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
            assert ds["time"].attrs["release_time"] == "2024-02-03T10:15:00Z"
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix == ".nc") == [
        "in_memory.nc", "streamed.nc"]
    assert not list(tmp_path.glob(".*.tmp"))


@pytest.mark.parametrize("kind, tile, share", [("grid", 4, 0.8), ("dem", 2, 1.0)])
def test_a_record_writes_only_the_tiles_of_the_flow(kind, tile, share, tmp_path, monkeypatch):
    """Small tiles: the streamed file still equals the in-memory one, every value (the dry
    tiles never written read as 0 on the plane, the tiles all in the DEM's 3 x 3 hole as
    NaN), and the stream writes fewer tiles than the records hold: on the plane less than
    80% of them; on the DEM (NaN fill: its dry tiles are written) all but the hole's. Fails
    if a skipped tile reads anything else (a fill value lost reads 9.97e36), or if every
    tile is written."""
    import avflow.output.netcdf as nc
    import avflow.output.stream as st

    monkeypatch.setattr(nc, "TILE", tile)
    written = []
    blocks = st._Tiles.blocks

    def counted(self, wet):
        out = blocks(self, wet)
        written.append(sum(-(-(r.stop - r.start) // tile) * -(-(c.stop - c.start) // tile)
                           for r, c in out))
        return out

    monkeypatch.setattr(st._Tiles, "blocks", counted)
    scenario = scenarios(tmp_path)[kind]
    if kind == "dem":  # the release down the slope of the hole: the flow leaves it aside
        scenario = scenario.with_updates({"release.center": [1150.0, 2030.0]})
    old, new = both_files(scenario, tmp_path)
    assert_same_file(old, new)
    with xr.open_dataset(new, decode_cf=False) as ds:
        assert ds["h"].encoding["chunksizes"] == (1, tile, tile)
        assert ("_FillValue" not in ds["h"].attrs) if kind == "grid" \
            else np.isnan(ds["h"].attrs["_FillValue"])
        records, ny, nx = ds["h"].shape
    fields = 3  # h, u, v
    assert len(written) == fields * records
    assert sum(written) < share * fields * records * -(-ny // tile) * -(-nx // tile)


def test_a_lost_fill_value_falls_back_to_whole_records(tmp_path, monkeypatch):
    """Where the netCDF library would not keep HDF5's fill value at 0 (here: none given,
    so the unwritten tiles read netCDF's default fill, 9.97e36), the stream sees it on the
    first record and writes every tile from then on: the file still equals the in-memory
    one. Fails if the check or the fallback is taken out."""
    import avflow.output.netcdf as nc
    import avflow.output.stream as st

    monkeypatch.setattr(nc, "TILE", 4)
    monkeypatch.setattr(st, "_dry_fill", lambda dtype: None)
    old, new = both_files(scenarios(tmp_path)["grid"], tmp_path)
    assert_same_file(old, new)


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
        # the run read its scenario file, the member its text: only the first names a file
        assert a.attrs.pop("input_files") == str(FAST) and b.attrs.pop("input_files") == ""
        xr.testing.assert_identical(a.drop_vars(clocks), b.drop_vars(clocks))


# --- the fields refreshed only where the flow is or was (issue 11 item 4) -------------------


def full_center_of_mass(terrain, h):
    """The centre of mass as it was computed before the windowed sums: over every cell."""
    w = h * terrain.mesh.cell_area
    total = w.sum()
    if total <= 0.0:
        return (np.nan, np.nan, np.nan)
    if terrain.kind == "profile":
        x, y = terrain.x, np.zeros_like(terrain.x)
    else:
        x, y = terrain.cell_xy()
    return (float(np.sum(w * x) / total), float(np.sum(w * y) / total),
            float(np.sum(w * terrain.bed_elevation) / total))


def sliding(terrain, records=12):
    """States of a blob that slides across the map, end to end, and leaves the cells behind
    it dry (h exactly 0), with what a window must not miss: discharges in dry cells, cells at
    rest, h = -0.0 far from the flow, a map dry for two records and then wet elsewhere."""
    from avflow.numerics import stepping
    from avflow.numerics.solver import State

    if terrain.kind == "profile":
        xs, ys = terrain.x, np.zeros_like(terrain.x)
    else:
        xs, ys = terrain.cell_xy()
    radius = max(np.ptp(xs), np.ptp(ys)) / 8.0
    rng = np.random.default_rng(4)
    for k in range(records):
        cx = xs.min() + np.ptp(xs) * k / (records - 1)
        cy = ys.min() + np.ptp(ys) * (0.3 + 0.4 * k / (records - 1))
        d = np.hypot(xs - cx, ys - cy)
        h = np.where(d < radius, 1.0 + rng.random(d.size), 0.0)
        hu, hv = h * 3.0, -h * rng.random(d.size)
        hu[d < radius / 3], hv[d < radius / 3] = 0.0, 0.0  # at rest in the middle
        hu[np.argmax(d)] = 2.0  # a discharge in a dry cell: no velocity, dry
        if k in (4, 5):  # nothing on the map, twice
            h[:] = 0.0
        if k == 7:
            h[np.argmax(d)] = -0.0  # not +0.0: refreshed (h -0.0, dry)
        stats = np.zeros(stepping.N_STATS)
        stats[stepping.ST_TIME] = float(k)
        yield State(h=h, hu=hu, hv=hv, flag=np.zeros(h.size, np.uint8), peak_h=h.copy(),
                    peak_speed=np.zeros(h.size), arrival=np.full(h.size, np.nan),
                    last_moved=np.full(h.size, np.nan), stats=stats)


class Windows(Both):
    """Both, keeping the windows its fields were refreshed in."""

    def finish(self, result):
        self.windows = list(self._fields.windows)
        return super().finish(result)


@pytest.mark.parametrize("pieces", [False, True])
@pytest.mark.parametrize("kind", ["profile", "grid", "dem", "triangles"])
def test_windowed_fields_equal_the_whole_map_as_the_flow_slides_and_dries(kind, pieces,
                                                                         tmp_path,
                                                                         monkeypatch):
    """A flow that crosses the map and leaves it dry behind: every record's fields, refreshed
    in the window where the flow is or was, equal those of the whole map (snapshot_fields,
    cast to the file's dtypes) bit for bit, and so does the centre of mass; the streamed file
    equals the in-memory one."""
    if pieces:  # a window refreshed in pieces of 7 cells (rows of it on grids)
        monkeypatch.setattr("avflow.output.dataset.REFRESH_CELLS", 7)
    from avflow.output.dataset import WindowedFields, snapshot_fields
    from avflow.simulation.runner import center_of_mass

    result = simulate(scenarios(tmp_path)[kind])
    terrain = result.terrain
    states = list(sliding(terrain))
    dtypes = {"h": np.float32, "u": np.float32, "v": np.float32, "flow_state": np.int8}

    def whole(state):
        fields = snapshot_fields(terrain, state.h, state.hu, state.hv, cell_flags(state))
        return {name: np.asarray(v).astype(dtypes[name]) for name, v in fields.items()}

    first = whole(states[0])
    fields = WindowedFields(terrain, states[0].h, first, {n: dtypes[n] for n in first})
    for state in states[1:]:
        got, want = fields.update(state.h, state.hu, state.hv), whole(state)
        assert list(got) == list(want)
        for name in want:
            assert got[name].dtype == want[name].dtype, name
            assert got[name].tobytes() == want[name].tobytes(), (state.t, name)
        assert (np.array(center_of_mass(terrain, state.h)).tobytes()
                == np.array(full_center_of_mass(terrain, state.h)).tobytes()), state.t
    size = int(np.prod(first["h"].shape))
    assert () in fields.windows  # dry twice: nothing refreshed
    assert all(np.prod(w) < size for w in fields.windows)  # never the whole map
    if kind != "triangles":  # (the nodes of a mesh are in no order of space)
        assert min(np.prod(w) for w in fields.windows if w) < size / 4

    with Windows(tmp_path / "streamed.nc") as stream:
        for state in states:
            stream.record(state, 0.0, terrain)
        run = dataclasses.replace(result, snapshots=stream)
        stream.finish(run)
    assert stream.windows == fields.windows
    old = write_netcdf(to_dataset(run), tmp_path / "in_memory.nc")
    assert_same_file(old, tmp_path / "streamed.nc")
    with xr.open_dataset(old) as ds:
        assert int(ds["flow_state"][-1].max()) == 2 and float(ds["h"][4].max()) == 0.0


def test_windowed_file_of_a_flow_moving_down_a_plane(tmp_path):
    """A real run: a cylinder sliding down a plane, 13 snapshots refreshed in windows that
    are a small part of the map; the file equals the in-memory one."""
    scenario = avflow.load_scenario(SCENARIOS / "plane_cylinder.yaml").with_updates(
        {"grid.dx": 25.0, "time.end": 24.0, "output.every": 2.0})
    with Windows(tmp_path / "streamed.nc") as stream:
        result = simulate(scenario, snapshots=stream)
        stream.finish(result)
    ny, nx = result.terrain.grid_shape
    areas = [np.prod(w) for w in stream.windows]
    assert len(areas) == 12 and max(areas) < ny * nx / 4 and areas[-1] > areas[0]
    old = write_netcdf(to_dataset(result), tmp_path / "in_memory.nc")
    assert_same_file(old, tmp_path / "streamed.nc")


def test_window_sums_are_numpys_sums_bit_for_bit():
    from avflow.simulation.runner import window_sums

    rng = np.random.default_rng(7)
    for _ in range(300):
        n = int(rng.choice([rng.integers(1, 300), rng.integers(300, 200_000)]))
        lo = int(rng.integers(0, n))
        hi = int(rng.integers(lo + 1, n + 1))
        a = np.zeros((2, n))
        a[:, lo:hi] = rng.standard_normal((2, hi - lo)) * 10.0 ** rng.uniform(-5, 5, hi - lo)
        a[1, :lo] = -0.0  # the zeros outside may be negative ones
        got = window_sums(a[:, lo:hi], lo, n)
        assert list(got) == [np.sum(a[0]), np.sum(a[1])]
    # a zero sum: its sign is the zeros' outside the window, which it does not see
    assert window_sums(np.array([1.0, -1.0]), 3, 10) == 0.0


def test_window_sums_leave_no_reference_cycle():
    """A snapshot's centre of mass leaves nothing for Python's cycle collector: a recursive
    closure once kept every snapshot's window lines alive until the collector ran (half a
    GiB over a 1 m avaKot run). The lines must be freed by reference counting alone, the
    moment the caller lets go of them; counting what ``gc.collect`` finds instead made the
    test flaky (other tests' threads leave their own garbage in the window)."""
    import gc
    import weakref

    from avflow.simulation.runner import window_sums

    window_sums(np.ones((4, 200)), 10, 1000)  # the once-per-process check, outside the window
    rows = np.ones((4, 50_000))
    alive = weakref.ref(rows)
    gc.disable()
    try:
        window_sums(rows, 1000, 80_000)
        del rows
        assert alive() is None
    finally:
        gc.enable()
