"""Running a region: every release in its own window, on dask as ensembles run, merged.

Layout of OUTDIR::

    releases/<id>.nc        each release's peak maps on its last window and its row
    checksums/<id>.sha256   their sha256 (resume trusts a file only when it matches)
    releases.csv            id, status, volume, runout, travel angle, area, retries, times...
    region.zarr             the merged maps (:mod:`avflow.region.merge`)

Releases run largest first (by polygon area). A release that cannot run (outside the DEM,
zero area, another CRS, a run that fails) is a row with its status and error, and one line
on stderr; the others go on. A rerun reuses every release whose file it can trust and
merges the maps again from the files (the store is rebuilt next to the old one and
renamed into place at the end).
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

# the ensembles' dask client (local cluster, --scheduler, warming) and Ctrl-C handling
from avflow.ensemble.orchestrate import _client, _deferred_sigint
from avflow.files import atomic_write, check_folder, check_target, output_lock, protected
from avflow.region.run import COLUMNS, MERGED, read_result, release_key, result_path, \
    run_release
from avflow.region.windows import dem_info, read_releases

#: Names of the outputs in OUTDIR.
STORE, TABLE = "region.zarr", "releases.csv"
PARQUET, SCENARIOS = "releases.parquet", "scenarios.csv"


@dataclass
class RegionOutcome:
    """What :func:`run_region` did."""

    table: object  #: pandas.DataFrame, one row per release, in id order
    store: Path
    ran: int
    reused: int
    failed: int  #: releases not merged (invalid, failed)
    elapsed: float  #: s, from the start to the end of the merge
    where: str
    workers: int
    #: s, wall clock in this process: "check", "startup", "runs" (first submit to last
    #: result), "merge" (merging results into the store), "tables"
    timings: dict = field(default_factory=dict)


class RegionProgress:
    """``[####....] 12/40 releases, 1 failed, 3.2 km2 covered`` on one line; failures on
    their own lines (always, even when quiet)."""

    def __init__(self, total: int, pixel_area: float, stream=None, quiet: bool = False,
                 unit: str = "releases"):
        self.stream = stream if stream is not None else sys.stderr
        self.total, self.quiet, self.pixel_area, self.unit = total, quiet, pixel_area, unit
        self.said: set = set()  # (id, error) already on stderr: once per release
        self.live = self.stream.isatty() and not quiet
        self.done = self.failed = self.instant = 0
        self.covered = 0.0
        self.started = time.perf_counter()

    def update(self, row: dict) -> None:
        self.done += 1
        if row.get("reused") is True or row["status"] == "invalid":  # no run: not in the pace
            self.instant += 1
        if row["status"] not in MERGED:
            self.failed += 1
            if (row["id"], row["error"]) not in self.said:
                self.said.add((row["id"], row["error"]))
                if self.live:
                    self.stream.write("\r\033[K")
                self.stream.write(f"release {row['id']}: {row['status']}: {row['error']}\n")
        elif row["status"] == "dem_edge":
            self.note(f"release {row['id']}: its flow reaches the DEM's border (runout "
                      "truncated, merged as a lower bound): extend the DEM there")
        else:
            cells = (row["row1"] - row["row0"]) * (row["col1"] - row["col0"])
            self.covered += cells * self.pixel_area
        self.draw()

    def note(self, message: str) -> None:
        if self.quiet:
            return
        if self.live:
            self.stream.write("\r\033[K")
        self.stream.write(message + "\n")
        self.draw()

    def draw(self) -> None:
        if not self.live:
            return
        from avflow.ensemble.orchestrate import time_left

        filled = int(30 * self.done / max(self.total, 1))
        wall = time.perf_counter() - self.started
        left = time_left(wall, self.done - self.instant, self.total - self.instant)
        self.stream.write(f"\r  [{'#' * filled}{'.' * (30 - filled)}] {self.done}/{self.total}"
                          f" {self.unit}, {self.failed} failed, {self.covered / 1e6:.2f} km2 of "
                          f"windows ({wall:5.1f} s{left})\033[K")
        self.stream.flush()

    def close(self) -> None:
        if self.live:
            self.stream.write("\n")
            self.stream.flush()


def run_region(region, outdir, *, workers: int | None = None, scheduler: str | None = None,
               quiet: bool = False, client=None) -> RegionOutcome:
    """Run every release of ``region`` (a :class:`~avflow.region.spec.Region`) into
    ``outdir`` and merge them. ``workers``: local worker processes (0: here, no dask; None:
    one per core, or here when at most one release is left to run); ``scheduler``: address
    or scheduler file of a running dask scheduler; ``client``: a ``distributed.Client``."""
    # absolute: the members' scenario files name their windows from their own folder
    outdir = check_folder(Path(outdir).absolute(), "region folder")
    inputs = protected(region.input_files())
    check_target(outdir / TABLE, inputs, what="region output")
    store = outdir / STORE
    if store.exists() and not store.is_dir():
        from avflow.files import OutputError

        raise OutputError(f"region output {store}: exists and is not a folder (a Zarr store)")
    with output_lock(outdir, folder=True, what="region folder"):
        return _run_locked(region, outdir, workers, scheduler, quiet, client)


def _run_locked(region, outdir: Path, workers, scheduler, quiet, client) -> RegionOutcome:
    started = time.perf_counter()
    timings: dict[str, float] = {}
    dem = dem_info(region.dem)
    releases = read_releases(region, dem)
    key = region.key()
    scenarios = region.scenarios
    multi = region.with_scenarios  # file names <id>-<scenario>.nc
    progress = RegionProgress(len(releases) * len(scenarios), dem.dx * dem.dy, quiet=quiet,
                              unit="runs" if multi else "releases")
    rows: dict[tuple[int, int], dict] = {}
    todo, reuse = [], []
    for rel in sorted(releases, key=lambda r: (-r.area, r.id)):  # largest first
        if rel.area_outside > 0 and not rel.problem:
            whole = rel.area + rel.area_outside
            progress.note(f"release {rel.id}: {100 * rel.area_outside / whole:.0f}% of its "
                          f"polygon lies outside the DEM: clipped to it (released area "
                          f"{rel.area:.6g} of {whole:.6g} m2, area in {TABLE})")
        for rs in scenarios:
            thickness = _thickness(rel, rs)
            rkey = release_key(key, rel.wkb, thickness if not hasattr(thickness, "d0")
                               else None, rs.key() + rel.fingerprint)
            if rel.problem:
                rows[rel.id, rs.index] = _invalid_row(rel, rkey, rs)
                progress.update(rows[rel.id, rs.index])
                continue
            fs = rs.index if multi else None
            row, _, why = read_result(result_path(outdir, rel.id, fs), rkey, arrays=False)
            if row is not None:
                row["reused"] = True
                reuse.append(row)
                continue
            if why:
                progress.note(f"release {rel.id}{_of(rs, multi)}: not reusing "
                              f"{result_path(outdir, rel.id, fs).name}: {why}; running it "
                              "again")
            todo.append({"id": rel.id, "wkb": rel.wkb, "thickness": thickness,
                         "area": rel.area, "bbox": rel.bbox, "key": rkey, "region": region,
                         "dem": dem, "outdir": str(outdir), "scenario": rs.index,
                         "file_scenario": fs, "updates": rs.updates,
                         "return_period": rs.return_period, "patch": rel.patch})
    timings["check"] = time.perf_counter() - started

    tmp_store = _fresh_store_path(outdir)
    from avflow.region.merge import RegionStore

    merging = 0.0
    waiting: dict[int, dict[int, dict]] = {}  # release id -> its scenarios' rows so far
    try:
        merged = RegionStore(tmp_store, dem, region.merge.fields, region.merge.chunk,
                             {"title": f"avflow region {region.name}",
                              "source": "avflow region", "region_key": key,
                              # what avflow plot draws under and over the maps
                              "dem": str(Path(region.dem).absolute()),
                              **({"region_file": str(Path(region.path).absolute())}
                                 if region.path else {}),
                              "input_files": "\n".join(map(str, region.input_files())),
                              **_scenario_attrs(region)},
                             thresholds=region.thresholds, scenarios=len(scenarios)
                             if region.with_scenarios or region.thresholds else None)
        def merge(row: dict) -> None:
            """A row as it comes; a release is merged once all its scenarios are in (the
            exceedance fractions are per release: associative only release by release)."""
            nonlocal merging
            clock = time.perf_counter()
            rid, s = row["id"], int(row.get("scenario", 0) or 0)
            rows[rid, s] = row
            got = waiting.setdefault(rid, {})
            got[s] = row
            if len(got) == len(scenarios):
                parts = []
                for k in sorted(got):
                    r = got[k]
                    if r["status"] not in MERGED:
                        continue
                    path = result_path(outdir, rid, k if multi else None)
                    _, maps, why = read_result(path, r["key"])
                    if maps is None:
                        raise RuntimeError(f"release {rid}{_of(scenarios[k], multi)}: its "
                                           f"result file cannot be read back ({why})")
                    parts.append(((r["row0"], r["row1"], r["col0"], r["col1"]), maps,
                                  r["reach_threshold"]))
                if parts:
                    merged.add(rid, parts)
                del waiting[rid]
            merging += time.perf_counter() - clock
            progress.update(row)

        for row in reuse:
            merge(row)
        where, n_workers = _run(todo, workers, scheduler, client, merge, timings, progress)
        progress.close()
        clock = time.perf_counter()
        by_id = {rel.id: rel for rel in releases}
        for (rid, _), row in rows.items():  # the area on the DEM, reused rows included
            if rid in by_id:
                row.update(area=by_id[rid].area, area_outside_dem=by_id[rid].area_outside)
        table = _table(rows)
        atomic_write(outdir / TABLE, lambda tmp: table.to_csv(tmp, index=False))
        if multi:
            scen = _scenario_table(region)
            atomic_write(outdir / SCENARIOS, lambda tmp: scen.to_csv(tmp, index=False))
        _write_parquet(table, outdir / PARQUET, progress)
        _publish_store(tmp_store, outdir / STORE)
        timings["tables"] = time.perf_counter() - clock
    except BaseException as err:
        shutil.rmtree(tmp_store, ignore_errors=True)
        from avflow.files import write_error

        error = write_error(outdir / STORE, err)  # a full disk: one line, exit 1
        if error is not None:
            raise error from None
        raise
    finally:
        shutil.rmtree(outdir / "work", ignore_errors=True)
    timings["merge"] = merging
    failed = sum(r["status"] not in MERGED for r in rows.values())
    return RegionOutcome(table, outdir / STORE, len(todo), len(reuse), failed,
                         time.perf_counter() - started, where, n_workers, timings)


def _thickness(rel, rs):
    """The release thickness of ``rel`` in scenario ``rs``: m, or the rule (worked out on
    the worker, from the DEM under the polygon)."""
    if rs.thickness is None:
        return rel.thickness
    if isinstance(rs.thickness, str):
        return (rel.attributes or {}).get(rs.thickness)
    if isinstance(rs.thickness, (int, float)):
        return float(rs.thickness)
    return rs.thickness


def _of(rs, multi: bool) -> str:
    return f" scenario {rs.index}" if multi else ""


def _scenario_attrs(region) -> dict:
    if not region.with_scenarios:
        return {}
    import json

    return {"scenarios": len(region.scenarios),
            "scenario_labels": json.dumps([rs.label for rs in region.scenarios])}


def _scenario_table(region):
    """scenarios.csv: index, return period, the thickness rule, the varied values."""
    import json

    import pandas as pd

    out = []
    for rs in region.scenarios:
        thick = rs.thickness
        out.append({"scenario": rs.index, "return_period": rs.return_period,
                    "thickness": (json.dumps(thick.model_dump(mode="json"), sort_keys=True)
                                  if hasattr(thick, "d0") else thick),
                    **{k: (json.dumps(v, sort_keys=True) if isinstance(v, (dict, list))
                           else v) for k, v in rs.updates.items()},
                    "label": rs.label})
    table = pd.DataFrame(out)
    table["return_period"] = table["return_period"].astype("Int64")
    return table


def _write_parquet(table, path: Path, progress) -> None:
    """releases.parquet beside releases.csv, when pandas has a parquet engine (pyarrow or
    fastparquet: an optional extra, ``avflow[parquet]``); else said once, not an error."""
    import importlib.util

    if not any(importlib.util.find_spec(m) for m in ("pyarrow", "fastparquet")):
        # not said on every run: the guide says releases.csv holds the same table
        path.unlink(missing_ok=True)  # a stale one would disagree with releases.csv
        return
    atomic_write(path, lambda tmp: table.to_parquet(tmp, index=False))


def _invalid_row(rel, rkey: str, rs=None) -> dict:
    row = {c: math.nan for c in COLUMNS}
    row.update(id=rel.id, scenario=rs.index if rs is not None else 0, status="invalid",
               area=rel.area, retries=0, reused=False, error=rel.problem, key=rkey,
               wall_time=0.0)
    if rs is not None and rs.return_period:
        row["return_period"] = rs.return_period
    return row


def _run(todo, workers, scheduler, client, merge, timings, progress) -> tuple[str, int]:
    """Run the tasks here or on dask, merging each result as it comes."""
    if not todo:
        return "nothing to run", 0
    if workers is None and scheduler is None and client is None and len(todo) == 1:
        workers = 0
    if workers == 0 and scheduler is None and client is None:
        clock = time.perf_counter()
        from avflow.errors import check_interrupted

        for task in todo:
            check_interrupted()  # a Ctrl-C a library swallowed during the last release
            merge(run_release(task))
        timings["runs"] = time.perf_counter() - clock
        return "here", 0
    from distributed import as_completed

    from avflow.scenario.extensions import loaded_files

    clock = time.perf_counter()
    tiny = _tiny_scenarios(todo[0])
    with _deferred_sigint() as sigint, _client(
            scheduler, workers, client, tiny, check=sigint.check, timings=timings,
            env={"NUMBA_NUM_THREADS": "1"}) as cl:
        n_workers = len(cl.client.scheduler_info(n_workers=-1)["workers"])
        timings["startup"] = time.perf_counter() - clock
        clock = time.perf_counter()
        # the workers register what this process did from files, before the release runs
        extensions = loaded_files()
        futures = {cl.client.submit(run_release, {**task, "one_thread": True,
                                                  "extensions": extensions},
                                    key=f"avflow-region-release-{task['id']}-"
                                        f"{task['scenario']}-{task['key']}",
                                    priority=len(todo) - k, pure=False, retries=1): task
                   for k, task in enumerate(todo)}  # largest first: highest priority
        # polled, as the ensembles do: a Ctrl-C is acted on between two polls
        pending = as_completed(list(futures), loop=cl.client.loop, raise_errors=False)
        while not pending.is_empty():
            sigint.check()
            done = pending.next_batch(block=False)
            if not done:
                time.sleep(0.05)
                continue
            for future in done:
                task = futures.pop(future)
                try:
                    row = future.result()
                except Exception as err:  # noqa: BLE001 - a lost task (KilledWorker)
                    row = _invalid_row(_Lost(task), task["key"])
                    row.update(scenario=task.get("scenario", 0),
                               return_period=task.get("return_period") or math.nan,
                               status="failed", error=f"{type(err).__name__}: "
                                                      f"{' '.join(str(err).split())}")
                finally:
                    future.release()
                merge(row)
        timings["runs"] = time.perf_counter() - clock
    where = "scheduler" if scheduler else "client" if client else "local cluster"
    return where, n_workers


@dataclass
class _Lost:
    """A task's release, for the row of a task dask gave up on."""

    task: dict

    @property
    def id(self):
        return self.task["id"]

    @property
    def area(self):
        return self.task["area"]

    problem = ""


def _tiny_scenarios(task) -> list[str] | None:
    """Scenario YAMLs of the first release cut to two steps, on a small window: run here
    (:func:`avflow.ensemble.orchestrate.warm`) before any worker loads Numba's kernels."""
    from avflow.region.run import _write_polygon
    from avflow.region.windows import window_for, write_window

    region, dem = task["region"], task["dem"]
    folder = Path(task["outdir"]) / "work" / "warm"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        polygon = folder / "release.gpkg"
        # a polygon even for a raster's patch, a metre for a rule: two steps of the kernels
        thickness = task["thickness"] if isinstance(task["thickness"], (int, float)) else 1.0
        _write_polygon(polygon, task["wkb"], thickness, dem.crs_wkt)
        dem_file = folder / "dem.tif"
        write_window(dem, window_for(dem, task["bbox"], 2 * max(dem.dx, dem.dy)), dem_file)
        sc = region.scenario_for(str(dem_file), dem.dx, dem.dy, str(polygon), thickness,
                                 "warm", task.get("updates"))
        sc = sc.with_updates({"time.end": 1e-3, "time.max_steps": 2, "output.every": 1e-3})
        texts = [sc.source_text]
        if sc.numerics.threads is None:
            texts.append(sc.with_updates({"numerics.threads": 1}).source_text)
        return texts
    except Exception:  # noqa: BLE001 - best effort: the releases report their own problems
        return None


def _table(rows: dict):
    import pandas as pd

    table = pd.DataFrame([{c: rows[i].get(c) for c in COLUMNS} for i in sorted(rows)],
                         columns=list(COLUMNS))
    for c in ("scenario", "return_period", "retries", "row0", "row1", "col0", "col1",
              "cells", "steps"):
        table[c] = table[c].astype("Int64")
    return table


def _fresh_store_path(outdir: Path) -> Path:
    """A new temporary store name next to the final one (old ones of killed runs removed)."""
    import tempfile

    for old in outdir.glob(f".{STORE}.*.tmp"):
        shutil.rmtree(old, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{STORE}.", suffix=".tmp", dir=outdir))
    tmp.rmdir()  # to_zarr(mode="w-") makes it
    return tmp


def _publish_store(tmp: Path, target: Path) -> None:
    """The finished store renamed into place; an old one is moved aside first, then
    removed (two renames: a reader sees the old store or the new one, never a mix)."""
    from avflow.region.export import write_manifest

    write_manifest(tmp)  # the chunks written: one deleted later is found, not read as NaN
    old = None
    if target.exists():
        old = target.with_name(f".{target.name}.old-{os.getpid()}.tmp")
        os.replace(target, old)
    os.replace(tmp, target)
    if old is not None:
        with contextlib.suppress(OSError):
            shutil.rmtree(old)
