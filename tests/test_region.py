"""avflow region: windows grown while the flow reaches their edge, maps that do not depend on
the workers, releases that cannot run recorded, region files checked (one line, exit 2).

A tiny region: a 30-degree slope running out onto a flat floor, 20 m cells (120 x 40), order 1
Coulomb; the runs take milliseconds once Numba's kernels are cached.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from avflow.cli import main
from avflow.region import RegionError, load_region
from avflow.region.orchestrate import run_region

DX = 20.0
NX, NY = 120, 40
X0, Y0 = 1000.0, 5000.0  # west and north edges
CRS = "EPSG:2056"


def _dem(folder):
    import rasterio
    from rasterio.transform import from_origin

    x = X0 + DX * (np.arange(NX) + 0.5)
    y = Y0 - DX * (np.arange(NY) + 0.5)
    # 30 degrees down to x = X0 + 800 m, then flat; a shallow trough along y keeps the flow
    # near the middle rows
    s = np.clip(X0 + 800.0 - x, 0.0, None) * math.tan(math.radians(30.0))
    z = s[None, :] + 0.05 * np.abs(y - y.mean())[:, None] + np.zeros((NY, 1))
    with rasterio.open(folder / "dem.tif", "w", driver="GTiff", width=NX, height=NY, count=1,
                       dtype="float32", crs=CRS, transform=from_origin(X0, Y0, DX, DX)) as dst:
        dst.write(z.astype(np.float32), 1)


def _releases(path, boxes, crs=CRS, thickness=None):
    import pyogrio.raw
    import shapely

    geoms = [shapely.Polygon(b) if len(b) != 4 or not np.isscalar(b[0]) else shapely.box(*b)
             for b in boxes]
    thickness = thickness or [2.0] * len(geoms)
    pyogrio.raw.write(str(path), np.array([shapely.to_wkb(g) for g in geoms], dtype=object),
                      [np.arange(1, len(geoms) + 1, dtype=np.int32), np.array(thickness)],
                      ["id", "thickness"], driver="GPKG", crs=crs, geometry_type="Polygon")


REGION = """\
name: test-region
dem: dem.tif
releases:
  path: {releases}
  id_field: id
scenario:
  rheology: {{law: coulomb, delta_deg: 24.0}}
  time: {{end: 120.0}}
  numerics: {{order: 1}}
window:
  buffer: {buffer}
merge:
  chunk: 16
"""

#: Two releases on the slope; one outside the DEM; one of zero area (collinear vertices);
#: one of 6 m x 6 m between cell centres (no cell released: found when it runs).
BOXES = [(X0 + 200, Y0 - 400, X0 + 300, Y0 - 300),
         (X0 + 100, Y0 - 260, X0 + 180, Y0 - 180),
         (X0 + 5000, Y0 - 400, X0 + 5100, Y0 - 300),
         [(X0 + 400, Y0 - 200), (X0 + 450, Y0 - 200), (X0 + 500, Y0 - 200)],
         (X0 + 22, Y0 - 38, X0 + 28, Y0 - 32)]


@pytest.fixture(scope="module")
def region_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("region")
    _dem(folder)
    _releases(folder / "releases.gpkg", BOXES)
    for name, buffer in (("small", 40.0), ("whole", 1.0e5)):
        (folder / f"{name}.yaml").write_text(REGION.format(releases="releases.gpkg",
                                                           buffer=buffer))
    return folder


@pytest.fixture(scope="module")
def small(region_dir):
    """The releases in 40 m windows, run here (no dask)."""
    return run_region(load_region(region_dir / "small.yaml"), region_dir / "out-small",
                      workers=0, quiet=True)


def test_window_grows_and_equals_whole_dem(region_dir, small):
    whole = run_region(load_region(region_dir / "whole.yaml"), region_dir / "out-whole",
                       workers=0, quiet=True)
    t_small, t_whole = small.table.set_index("id"), whole.table.set_index("id")
    for rid in (1, 2):
        assert t_small.loc[rid, "status"] == "ok"
        assert t_small.loc[rid, "retries"] >= 1  # 40 m around the box: the flow leaves it
        assert t_whole.loc[rid, "retries"] == 0
        # the grown window is smaller than the DEM: the test is about a window, not the DEM
        cells = t_small.loc[rid, "cells"]
        assert 0 < cells < 0.75 * NX * NY
        assert t_small.loc[rid, "runout"] == pytest.approx(t_whole.loc[rid, "runout"],
                                                           abs=1e-9)
    a = xr.open_zarr(small.store).load()
    b = xr.open_zarr(whole.store).load()
    assert int(a.release_count.max()) == 2  # the two flows overlap on the floor
    for name in ("peak_thickness", "peak_speed", "peak_pressure"):
        both = np.isfinite(a[name].values) & np.isfinite(b[name].values)
        assert both.sum() > 100
        # the same cells reached, and the same values there: a window with no flow at its
        # edge computes what the whole DEM does (float32 maps: to 1e-5 of the largest)
        assert np.array_equal(np.isfinite(a[name].values), np.isfinite(b[name].values))
        scale = float(np.nanmax(b[name].values))
        assert np.nanmax(np.abs(a[name].values - b[name].values)) <= 1e-5 * scale
        np.testing.assert_array_equal(a[f"{name}_release"].values,
                                      b[f"{name}_release"].values)
    np.testing.assert_array_equal(a.release_count.values, b.release_count.values)


def test_invalid_releases_are_recorded_and_the_rest_go_on(region_dir, small, capfd):
    table = pd.read_csv(region_dir / "out-small" / "releases.csv")
    rows = table.set_index("id")
    assert rows.loc[3, "status"] == "invalid" and "outside the DEM" in rows.loc[3, "error"]
    assert rows.loc[4, "status"] == "invalid" and "zero area" in rows.loc[4, "error"]
    assert rows.loc[5, "status"] == "invalid" and "no mass on any cell" in rows.loc[5, "error"]
    assert set(rows.loc[[1, 2], "status"]) == {"ok"}
    for column in ("volume", "runout", "travel_angle", "area", "retries", "wall_time"):
        assert np.isfinite(rows.loc[[1, 2], column].astype(float)).all()
    # release 1: 5 x 5 cells of 2 m (the box's cell centres), 400 m^2 of map each, their
    # bed area 1/cos(30 deg) larger (the trough's 3-degree cross slope adds 0.1 %)
    assert rows.loc[1, "volume"] == pytest.approx(25 * DX * DX * 2.0 / math.cos(math.radians(30)),
                                                  rel=2e-3)
    assert 20.0 < rows.loc[1, "travel_angle"] < 30.0  # Coulomb 24 degrees
    assert small.failed == 3


def test_other_crs_is_recorded_on_stderr(region_dir, capsys):
    _releases(region_dir / "other_crs.gpkg", BOXES[:1], crs="EPSG:32632")
    (region_dir / "crs.yaml").write_text(REGION.format(releases="other_crs.gpkg", buffer=40))
    code = main(["region", str(region_dir / "crs.yaml"), "-o", str(region_dir / "out-crs"),
                 "--workers", "0", "-q"])
    err = capsys.readouterr().err
    assert code == 1
    assert "release 1: invalid: its CRS" in err and "differs from the DEM's" in err
    table = pd.read_csv(region_dir / "out-crs" / "releases.csv")
    assert list(table.status) == ["invalid"]
    ds = xr.open_zarr(region_dir / "out-crs" / "region.zarr")
    assert int(ds.release_count.max()) == 0  # nothing merged


def test_a_relative_output_folder_from_another_folder_gives_the_same_maps(region_dir, small,
                                                                          monkeypatch):
    """`avflow region REGION.yaml -o maps` from the folder above the region: the windows'
    files lie under OUTDIR, which must not be read from the region file's folder."""
    monkeypatch.chdir(region_dir.parent)
    code = main(["region", f"{region_dir.name}/small.yaml", "-o", "maps-relative",
                 "--workers", "0", "-q"])
    assert code == 1  # the three invalid releases of BOXES
    rows = pd.read_csv(region_dir.parent / "maps-relative" / "releases.csv").set_index("id")
    assert set(rows.loc[[1, 2], "status"]) == {"ok"}
    a = xr.open_zarr(region_dir.parent / "maps-relative" / "region.zarr").load()
    b = xr.open_zarr(small.store).load()
    np.testing.assert_array_equal(a.peak_thickness.values, b.peak_thickness.values)


def test_resume_reuses_finished_releases(region_dir, small):
    import avflow

    ds = avflow.run_region(region_dir / "small.yaml", region_dir / "out-small", workers=0,
                           quiet=True)  # the same folder again, through the Python API
    table = pd.read_csv(region_dir / "out-small" / "releases.csv").set_index("id")
    assert table.loc[[1, 2, 5], "reused"].all()  # release 5's row kept: not tried again
    assert int(ds.release_count.max()) == 2
    ref = small.table.set_index("id")
    assert (table.loc[[1, 2], "runout"] == ref.loc[[1, 2], "runout"]).all()


def test_interrupt_then_resume_gives_the_same_maps(region_dir, small, monkeypatch, capsys):
    """Ctrl-C after the first release: it is kept, nothing half-written is left; the rerun
    reuses it (checksum verified), runs again one whose file was damaged, and the maps are
    those of the uninterrupted run, bit for bit."""
    import avflow.region.orchestrate as orch

    out = region_dir / "out-interrupted"
    calls, run_release = [], orch.run_release

    def interrupted(task):
        if calls:
            raise KeyboardInterrupt
        calls.append(task["id"])
        return run_release(task)

    monkeypatch.setattr(orch, "run_release", interrupted)
    with pytest.raises(KeyboardInterrupt):
        orch.run_region(load_region(region_dir / "small.yaml"), out, workers=0, quiet=True)
    monkeypatch.undo()
    first = calls[0]
    assert sorted(p.name for p in (out / "releases").iterdir()) == [f"{first}.nc"]
    assert (out / "checksums" / f"{first}.sha256").is_file()
    assert not (out / "region.zarr").exists() and not (out / "work").exists()
    assert not list(out.glob(".*.tmp")) and not list(out.glob(".*lock"))
    resumed = orch.run_region(load_region(region_dir / "small.yaml"), out, workers=0,
                              quiet=True)
    assert resumed.reused == 1 and resumed.ran == 2
    ref = xr.open_zarr(small.store).load()
    ds = xr.open_zarr(resumed.store).load()
    for name in ref.data_vars:
        assert np.array_equal(ds[name].values, ref[name].values, equal_nan=True), name
    # a damaged file is run again, said on stderr
    damaged = out / "releases" / f"{first}.nc"
    data = bytearray(damaged.read_bytes())
    data[-10] ^= 0xFF
    damaged.write_bytes(bytes(data))
    again = orch.run_region(load_region(region_dir / "small.yaml"), out, workers=0)
    assert again.reused == 2 and again.ran == 1
    assert "checksum does not match" in capsys.readouterr().err
    ds = xr.open_zarr(again.store).load()
    for name in ref.data_vars:
        assert np.array_equal(ds[name].values, ref[name].values, equal_nan=True), name


def test_one_and_two_workers_same_maps(region_dir, small):
    """Local dask clusters of 1 and 2 workers (one thread each) against the run here."""
    ref = xr.open_zarr(small.store).load()
    for n in (1, 2):
        out = run_region(load_region(region_dir / "small.yaml"), region_dir / f"out-{n}w",
                         workers=n, quiet=True)
        assert out.where == "local cluster" and out.workers == n
        ds = xr.open_zarr(out.store).load()
        for name in ds.data_vars:
            assert np.array_equal(ds[name].values, ref[name].values, equal_nan=True), name
        assert (out.table.retries.values == small.table.retries.values).all()


@pytest.mark.parametrize("edit, field", [
    (("delta_deg: 24.0", "delta_deg: 95.0"), "scenario.rheology.delta_deg"),
    (("buffer:", "bufer:"), "window.bufer"),
    (("dem: dem.tif", "dem: none.tif"), "dem"),
    (("  numerics: {order: 1}", "  grid: {dx: 5}"), "scenario.grid"),
    (("chunk: 16", "chunk: 3"), "merge.chunk"),
])
def test_bad_region_file_one_line_exit_2(region_dir, capsys, edit, field):
    path = region_dir / "bad.yaml"
    path.write_text(REGION.format(releases="releases.gpkg", buffer=40).replace(*edit))
    with pytest.raises(RegionError):
        load_region(path)
    code = main(["region", str(path), "-o", str(region_dir / "out-bad")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith(f"avflow: error: {path}:")
    assert f": {field}: " in err[0]
    assert not (region_dir / "out-bad").exists()


def test_external_scheduler_with_a_worker_killed(region_dir):
    """`dask scheduler` and two `dask worker` processes (no nanny) on 127.0.0.1; one worker
    is killed once the first release has finished; its tasks run on the other, and the maps
    are those of the run here, bit for bit. Every process started is stopped."""
    import os
    import signal
    import subprocess
    import sys
    import threading
    import time
    from pathlib import Path

    boxes = [(X0 + 100 + 70 * i, Y0 - y - 60, X0 + 160 + 70 * i, Y0 - y)
             for y in (140, 620) for i in range(5)]
    _releases(region_dir / "many.gpkg", boxes)
    (region_dir / "many.yaml").write_text(REGION.format(releases="many.gpkg", buffer=40))
    region = load_region(region_dir / "many.yaml")
    ref = run_region(region, region_dir / "out-many-here", workers=0, quiet=True)
    dask = str(Path(sys.executable).with_name("dask"))
    sched_file = region_dir / "scheduler.json"
    env = dict(os.environ, NUMBA_NUM_THREADS="1")
    procs = []
    try:
        procs.append(subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0",
                                       "--no-dashboard", "--scheduler-file", str(sched_file)],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                      env=env, start_new_session=True))
        for _ in range(2):
            procs.append(subprocess.Popen([dask, "worker", "--scheduler-file", str(sched_file),
                                           "--nthreads", "1", "--no-nanny",
                                           "--host", "127.0.0.1", "--no-dashboard"],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                          env=env, start_new_session=True))
        deadline = time.monotonic() + 60
        while not sched_file.is_file() and time.monotonic() < deadline:
            time.sleep(0.1)
        out = region_dir / "out-many-dask"
        killed = {}

        def kill_one() -> None:  # once the first release is done, not after the last
            folder = out / "releases"
            while time.monotonic() < deadline:
                done = list(folder.glob("*.nc")) if folder.is_dir() else []
                if done:
                    killed["done_then"] = len(done)
                    procs[1].send_signal(signal.SIGKILL)
                    return
                time.sleep(0.02)

        from distributed import Client

        with Client(scheduler_file=str(sched_file), timeout=30) as client:
            client.wait_for_workers(2, timeout=60)
            killer = threading.Thread(target=kill_one, daemon=True)
            killer.start()
            outcome = run_region(region, out, scheduler=str(sched_file), quiet=True)
            killer.join(5)
        assert procs[1].wait(10) == -signal.SIGKILL
        assert 0 < killed["done_then"] < len(boxes)  # killed in the middle
        assert outcome.where == "scheduler" and outcome.failed == 0
        assert (outcome.table.status == "ok").all() and len(outcome.table) == len(boxes)
        a = xr.open_zarr(ref.store).load()
        b = xr.open_zarr(outcome.store).load()
        for name in a.data_vars:
            assert np.array_equal(a[name].values, b[name].values, equal_nan=True), name
        assert int(b.release_count.max()) >= 2
    finally:
        for proc in procs[::-1]:  # the workers first: else they wait for the scheduler
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)


def test_a_flow_at_the_dem_border_is_not_grown_to_the_whole_dem(region_dir):
    """A release on the southern border: its flow runs along the DEM's edge. Windows grow
    while it reaches their inner sides, then stop (status dem_edge) without the whole DEM;
    the maps equal the whole-DEM run's."""
    _releases(region_dir / "border.gpkg", [(X0 + 200, Y0 - 800, X0 + 300, Y0 - 720)])
    for name, buffer in (("border-small", 40.0), ("border-whole", 1.0e5)):
        (region_dir / f"{name}.yaml").write_text(REGION.format(releases="border.gpkg",
                                                               buffer=buffer))
    small = run_region(load_region(region_dir / "border-small.yaml"),
                       region_dir / "out-border-small", workers=0, quiet=True)
    whole = run_region(load_region(region_dir / "border-whole.yaml"),
                       region_dir / "out-border-whole", workers=0, quiet=True)
    row = small.table.iloc[0]
    assert row.status == "dem_edge" and whole.table.status.iloc[0] == "dem_edge"
    assert 1 <= row.retries <= 6 and row.row1 == NY  # grown, to the border, not further
    assert row.cells < 0.75 * NX * NY
    a, b = xr.open_zarr(small.store).load(), xr.open_zarr(whole.store).load()
    for name in ("peak_thickness", "peak_speed", "peak_pressure"):
        assert np.array_equal(np.isfinite(a[name].values), np.isfinite(b[name].values))
        scale = float(np.nanmax(b[name].values))
        assert np.nanmax(np.abs(a[name].values - b[name].values)) <= 1e-5 * scale


def test_the_key_follows_the_files_of_the_scenarios_maps(tmp_path):
    """A release's result depends on the scenario's maps (a friction map, the erodible
    layer, forest): their files count in the region's key by size and time, so an edited
    map is run again; a region without maps keeps its key."""
    import os

    _dem(tmp_path)
    _releases(tmp_path / "releases.gpkg", BOXES[:1])
    plain = REGION.format(releases="releases.gpkg", buffer=40.0)
    (tmp_path / "plain.yaml").write_text(plain)
    _releases(tmp_path / "layer.gpkg", BOXES[:2], thickness=[0.3, 0.5])
    with_map = plain.replace(
        "  numerics: {order: 1}\n",
        "  numerics: {order: 1}\n  entrainment: {law: erosion_energy, layer: "
        "{polygon: layer.gpkg}}\n")
    (tmp_path / "maps.yaml").write_text(with_map)
    region = load_region(tmp_path / "maps.yaml")
    assert region._map_files() and region._map_files()[0][0].endswith("layer.gpkg")
    before = region.key()
    assert load_region(tmp_path / "plain.yaml")._map_files() == []
    _releases(tmp_path / "layer.gpkg", BOXES[:2], thickness=[0.3, 0.9])  # edited
    st = os.stat(tmp_path / "layer.gpkg")
    os.utime(tmp_path / "layer.gpkg", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert load_region(tmp_path / "maps.yaml").key() != before


def test_a_region_runs_with_entrainment(tmp_path):
    """The scenario block may carry an entrainment layer (a depth here): each release runs
    with it on its window, and its balance, entrained mass included, holds."""
    _dem(tmp_path)
    _releases(tmp_path / "releases.gpkg", BOXES[:1])
    text = REGION.format(releases="releases.gpkg", buffer=1.0e5).replace(
        "  numerics: {order: 1}\n",
        "  numerics: {order: 1}\n  entrainment: {law: erosion_energy, layer: {depth: 0.5}}\n")
    (tmp_path / "ent.yaml").write_text(text)
    result = run_region(load_region(tmp_path / "ent.yaml"), tmp_path / "out", workers=0,
                        quiet=True)
    row = result.table.set_index("id").loc[1]
    assert row["status"] == "ok"
    assert abs(row["mass_balance_error"]) < 1e-12
    assert row["entrained_volume"] > 0.0  # the layer was eroded, and the balance holds
