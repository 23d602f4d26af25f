"""Running an ensemble on dask.distributed, resuming it, and writing its tables.

The numerical core knows nothing of this module. A member is run by :func:`run_member`, a
top-level function taking the member's resolved scenario YAML (plain text, so it pickles) and
the path of its NetCDF file; it writes the file atomically (temporary name, then rename) and
returns a small dict (the summary, the status, an error message). A member that raises
becomes a failure record; the others go on.

Layout of OUTDIR::

    members/<scenario_hash>.nc   one CF NetCDF per member (complete, or absent)
    checksums/<scenario_hash>.sha256   its sha256 (``sha256sum`` format), written after it
    summary.csv                  one row per member (and summary.parquet with pyarrow)
    failures.csv                 the failed members and their errors (only if any)
    ensemble.nc                  CF-1.11, realization dimension (see :mod:`avflow.ensemble.dataset`)

Re-running skips the members whose file it can trust: its sha256 equals the one written
right after the file was (so every byte reads back as written: data, summaries, attributes),
and its global attribute ``scenario_hash`` is the member's (not another member's file copied
into its slot). Any other file is run again, with one line on stderr saying why.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import os
import signal
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from avflow.ensemble.spec import (OK_STATUSES, SUMMARY_DEFAULTS, SUMMARY_FIELDS, Ensemble,
                                  Member)
from avflow.errors import AvflowError
from avflow.files import atomic_text, atomic_write

CONNECT_TIMEOUT = 10.0  #: s, to reach a given ``--scheduler``
WORKER_TIMEOUT = 120.0  #: s, for its first worker
#: s, what starting a local cluster costs before its first result: worker processes spawned
#: and importing avflow while this process loads the Numba kernels, then each worker's first
#: member loading them (5-10 s on a busy 2-core machine, about 5 s on 16 cores).
CLUSTER_START_S = 10.0
#: Members with more cells (estimated before anything runs) go to the cluster unprobed.
PROBE_MAX_CELLS = 100_000
#: With this many cores or more, the local cluster starts while the first member runs
#: here to choose where the others run (closed again if they stay here).
SPECULATE_MIN_CORES = 4


class ClusterError(AvflowError):
    """The dask scheduler given cannot be used: unreachable, no such file, no worker."""


class Interrupted(KeyboardInterrupt):
    """Ctrl-C during an ensemble; the message says what finished (the cluster is closed)."""


# =========================================================================================
# One member (runs on a worker)
# =========================================================================================


def checksum_path(path: str | os.PathLike) -> Path:
    """``OUTDIR/checksums/<hash>.sha256`` of the member file ``OUTDIR/members/<hash>.nc``."""
    path = Path(path)
    return path.parent.parent / "checksums" / f"{path.stem}.sha256"


def file_sha256(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_checksum(path: str | os.PathLike) -> Path:
    """The sha256 of a finished member file, atomically, in ``sha256sum`` format (check by
    hand with ``cd OUTDIR/members && sha256sum -c ../checksums/*.sha256``)."""
    path = Path(path)
    target = checksum_path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    line = f"{file_sha256(path)}  {path.name}\n"
    atomic_text(target, line)
    return target


def check_member_file(path: str | os.PathLike,
                      scenario_hash: str | None = None) -> tuple[dict | None, str]:
    """``(row, "")`` for a member file resume can trust, else ``(None, why)``.

    Trusted: its sha256 equals the one kept in ``checksums/`` (every byte as written), it
    reads, and its ``scenario_hash`` attribute is ``scenario_hash`` (default: the file's
    stem). ``why`` is "" when the file is simply absent.
    """
    path = Path(path)
    scenario_hash = scenario_hash or path.stem
    if not path.is_file():
        return None, ""
    try:
        expected = checksum_path(path).read_text(errors="replace").split()[0]
    except (OSError, IndexError):  # a damaged checksum file is one that does not match
        return None, "it has no checksum in checksums/ (never finished, or older than checksums)"
    try:
        if file_sha256(path) != expected:
            return None, "its checksum does not match (the file was changed or damaged)"
        import netCDF4

        with netCDF4.Dataset(path) as nc:
            row = {name: float(nc.variables[name][...]) if name in nc.variables
                   else SUMMARY_DEFAULTS[name] for name in SUMMARY_FIELDS}
            row["status"] = str(nc.getncattr("status"))
            row["scenario_hash"] = str(nc.getncattr("scenario_hash"))
            row["steps"] = int(nc.getncattr("steps"))
            row["runout_truncated"] = int(nc.getncattr("runout_truncated"))
    except Exception as err:  # noqa: BLE001 - a foreign file: run the member again
        return None, f"it cannot be read ({type(err).__name__}: {' '.join(str(err).split())})"
    if row["scenario_hash"] != scenario_hash:
        return None, (f"it holds the run of scenario {row['scenario_hash']}, not this member's "
                      "(another member's file)")
    row["error"] = "" if row["status"] in OK_STATUSES else f"run ended with status {row['status']}"
    return row, ""


def read_member_row(path: str | os.PathLike, scenario_hash: str | None = None) -> dict | None:
    """The summary row stored in a member file, or None unless resume can trust it
    (:func:`check_member_file`)."""
    return check_member_file(path, scenario_hash)[0]


def cluster_scenario(scenario):
    """A member's scenario as it runs on a dask worker: ``numerics.threads: 1`` unless it
    sets a number itself (the ensemble file's base scenario, or a varied field). The
    members are the better parallelism there: one worker per core, one thread each. The
    answer and the scenario hash do not depend on the number of threads."""
    if getattr(scenario.numerics, "threads", 1) is not None:
        return scenario
    return scenario.with_updates({"numerics.threads": 1})


def member_digest(path: str | os.PathLike, profile: bool) -> dict:
    """What the end of an ensemble needs of a member file, read in one opening: the maps of
    ``ensemble.nc`` (:func:`avflow.ensemble.dataset.read_member_maps`) and the cells of the
    path analysis (:func:`avflow.output.path.run_points`). A worker reads it as its member
    finishes (the file is still in the page cache) and returns it with the member's row, so
    that the end reads no member file again. A part that cannot be read is None: the file is
    read again at the end, which reports the error as before."""
    import xarray as xr

    from avflow.ensemble.dataset import read_member_maps
    from avflow.output.path import run_points

    digest = {"maps": None, "points": None}
    try:
        # engine named: the engine xarray picks for these files, without the search of every
        # installed backend (0.6 s at a process's first file: rioxarray imported)
        with xr.open_dataset(path, decode_times=False, engine="netcdf4") as ds:
            for key, read in (("maps", lambda: read_member_maps(ds, profile)),
                              ("points", lambda: _narrow_fields(run_points(ds)))):
                try:
                    digest[key] = read()
                except Exception:  # noqa: BLE001 - read (and reported) again at the end
                    pass
    except Exception:  # noqa: BLE001 - idem
        pass
    return digest


def _narrow_fields(points):
    """A member's RunPoints with its peak fields in float32 where that holds every value
    exactly (they are float32 in the file; run_points makes them float64): half the bytes
    to send and to keep. The path analysis works on them in float64 (``np.asarray(...,
    dtype=float)``), the same values to the bit."""
    import numpy as np

    for name, values in points.fields.items():
        narrow = values.astype(np.float32)
        if narrow.astype(values.dtype).tobytes() == values.tobytes():
            points.fields[name] = narrow
    return points


def run_member(scenario_yaml: str, out_path: str, one_thread: bool = False,
               digest: bool | None = None) -> dict:
    """Run one member and write its NetCDF atomically; never raises for a model error.

    Idempotent: if ``out_path`` is already complete (a previous run, or the same task run
    twice after a lost worker) its stored summary is returned and nothing is recomputed.
    ``one_thread``: a member on a dask worker runs its :func:`cluster_scenario`.
    ``digest``: None, or whether the ensemble is on a profile: the row then carries the
    file's :func:`member_digest` under ``"digest"`` (when a file was written).
    """
    started = time.perf_counter()
    row = read_member_row(out_path)
    if row is not None:
        if digest is not None:
            row["digest"] = member_digest(out_path, digest)
        row.update(reused=True, member_time=time.perf_counter() - started)
        return row
    from avflow.output.stream import SnapshotStream
    from avflow.simulation.runner import simulate
    from avflow.scenario.schema import parse_scenario

    try:
        # The snapshots go to the member's temporary file as they are taken (one in memory);
        # the file is renamed into place at the end, and a failed member leaves none. The
        # stream writes through its own netCDF4 handle: no distributed.Lock round trip to
        # the scheduler (~0.25 s) as xarray's to_netcdf would take inside a dask worker.
        with SnapshotStream(out_path) as stream:
            scenario = parse_scenario(scenario_yaml)
            if one_thread:
                scenario = cluster_scenario(scenario)
            result = simulate(scenario, snapshots=stream)
            checksum_path(out_path).unlink(missing_ok=True)  # stale: the file is replaced
            stream.finish(result)
        write_checksum(out_path)
        row = {name: float(result.summary[name]) for name in SUMMARY_FIELDS}
        row.update(status=result.status, steps=int(result.summary["steps"]),
                   runout_truncated=int(result.summary["runout_truncated"]),
                   error="" if result.status in OK_STATUSES
                   else f"run ended with status {result.status}")
    except Exception as err:  # noqa: BLE001 - recorded, the other members go on
        problems = getattr(err, "problems", None)  # ScenarioError: field and message
        message = (" | ".join(f"{p.field + ': ' if p.field else ''}{p.message}"
                              for p in problems) if problems
                   else " | ".join(str(err).splitlines()) or repr(err))
        row = {name: math.nan for name in SUMMARY_FIELDS}
        row.update(status="failed", steps=0, error=f"{type(err).__name__}: {message}")
    if digest is not None and row["status"] != "failed":
        row["digest"] = member_digest(out_path, digest)
    row.update(reused=False, member_time=time.perf_counter() - started)
    return row


def run_batch(items: list[tuple[int, str, str]], one_thread: bool = False,
              digest: bool | None = None, extensions: tuple[str, ...] = ()
              ) -> list[tuple[int, dict]]:
    """Several members in one task (``(index, yaml, out_path)`` each): fewer, longer tasks.
    ``extensions``: the extension files the members' scenarios need (absolute paths, those
    the submitting process loaded), loaded here first, once per worker process; a file that
    cannot be loaded fails the members with its error."""
    from avflow.scenario.extensions import ExtensionFileError, load_files

    try:
        load_files(extensions, worker=True)
    except ExtensionFileError as err:
        row = {name: math.nan for name in SUMMARY_FIELDS}
        row.update(status="failed", steps=0, error=f"ExtensionFileError: {err}",
                   reused=False, member_time=0.0)
        return [(index, dict(row)) for index, _, _ in items]
    return [(index, run_member(text, out, one_thread, digest)) for index, text, out in items]


def tiny_scenario_yaml(ensemble: Ensemble, one_thread: bool = False,
                       member: int = 0) -> str | None:
    """A member (the first) cut to a couple of steps: enough to compile every kernel it runs
    (those of its :func:`cluster_scenario` with ``one_thread``: a single thread runs other
    kernels)."""
    try:
        scenario = ensemble.members[member].scenario
        if one_thread:
            scenario = cluster_scenario(scenario)
        return scenario.with_updates(
            {"time.end": 1e-3, "time.max_steps": 2, "output.every": 1e-3}).source_text
    except Exception:  # noqa: BLE001
        return None


def tiny_scenario_yamls(ensemble: Ensemble, one_thread: bool = False) -> list[str]:
    """:func:`tiny_scenario_yaml` of the first member of each kind of kernel among the
    members: the time loop is compiled per mesh kind and order, and the square-grid one per
    friction law and thread count, so an ensemble that varies ``numerics.order`` or the law
    (or the terrain, the kernel, the threads) needs each warmed before its workers start
    (workers compiling one kernel at once can crash: numba issue 4807)."""
    seen, out = set(), []
    for k, member in enumerate(getattr(ensemble, "members", ())):
        try:
            sc = member.scenario
            key = (sc.terrain.kind, sc.grid.mesh, sc.numerics.order, sc.numerics.kernel,
                   sc.numerics.threads, sc.rheology.law)
        except AttributeError:
            key = None
        if key in seen:
            continue
        seen.add(key)
        text = tiny_scenario_yaml(ensemble, one_thread, member=k)
        if text is not None:
            out.append(text)
    return out


def _closed_scheduler_filter(record: logging.LogRecord) -> bool:
    """False for a worker's log of a heartbeat to a scheduler that has closed (its
    ``CommClosedError`` traceback), the one thing a worker logs when a command is stopped."""
    return not record.getMessage().startswith("Failed to communicate with scheduler")


def dask_setup(worker) -> None:
    """Preload of the local cluster's workers (dask's ``preload``, as the worker starts,
    before it takes a task): SIGINT ignored (see :func:`_ignore_sigint_plugin`) and the
    modules a member needs imported, while this process warms its own (in parallel, not in
    each worker's first member). Numba's kernels are loaded by the first member itself,
    after this process has filled the cache (numba issue 4807)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    # a worker whose scheduler closed first (the command interrupted) logged a traceback of
    # its heartbeat's closed connection (1 SIGTERM in 6 of a 2-worker ensemble): no news
    logging.getLogger("distributed.worker").addFilter(_closed_scheduler_filter)
    try:
        import avflow.ensemble.dataset  # noqa: F401 - member_digest
        import avflow.output.path  # noqa: F401
        import avflow.output.stream  # noqa: F401
        import avflow.scenario.schema  # noqa: F401
        import avflow.simulation.runner  # noqa: F401
    except Exception:  # noqa: BLE001 - best effort: the member imports (and reports) itself
        pass


def dask_teardown(worker) -> None:
    """Preload of the local cluster's workers, as one closes: every object frozen out of the
    garbage collector (``gc.freeze``), so that the process exits at once. The collections of
    Python's shutdown took 0.4 s in a worker that had run members (avflow, Numba, xarray
    loaded: 230 000 objects), and the end of an ensemble waits for its workers to exit."""
    import gc

    gc.freeze()


def warm(scenario_yaml: str | list[str] | None) -> bool:
    """Run a tiny scenario (each of a list) and write its file: imports, Numba kernels,
    NetCDF libraries.

    In the parent before any worker takes a member, it compiles (or loads) the cache=True
    kernels once: workers compiling the same cache at once can crash (numba issue 4807).
    The workers load them in their first member. Best effort: a failure here is reported by
    the member itself.
    """
    if scenario_yaml is None:
        return False
    if isinstance(scenario_yaml, list):
        return all([warm(text) for text in scenario_yaml]) and bool(scenario_yaml)
    from avflow.output.stream import SnapshotStream
    from avflow.simulation.runner import simulate
    from avflow.scenario.schema import parse_scenario

    try:
        with tempfile.TemporaryDirectory(prefix="avflow-warm-") as folder:
            with SnapshotStream(Path(folder) / "warm.nc") as stream:  # as run_member writes
                stream.finish(simulate(parse_scenario(scenario_yaml), snapshots=stream))
    except Exception:  # noqa: BLE001
        return False
    return True


# =========================================================================================
# The ensemble
# =========================================================================================


@dataclass
class Outcome:
    """What :func:`run_ensemble` did."""

    table: object  #: pandas.DataFrame, one row per member, in member order
    ran: int  #: members computed now
    reused: int  #: members whose file was already there
    failed: int
    wall: float  #: s, running the members (starting a cluster not included)
    startup: float  #: s, starting (or connecting to) the cluster, warming included
    workers: int
    #: s, from the start to the last result: the clock of the progress line
    elapsed: float = math.nan
    where: str = ""  #: "here" (this process, no dask), "local cluster", "scheduler", "client"
    #: s, where the time went (:data:`TIMINGS`); a stage that did not happen is absent
    timings: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.failed == 0


#: The stages of :attr:`Outcome.timings` (seconds, wall clock, in this process).
TIMINGS = {
    "check": "checking the member files already there (resume)",
    "probe": "the first member run here to choose where the others run (warming included)",
    "warm_here": "imports and Numba kernels loaded in this process before a cluster starts",
    "cluster": "starting the local cluster (or connecting) until its first worker is there",
    "warm_workers": "every worker warmed (imports, Numba kernels) before the first task",
    "first_result": "from the first task submitted to the first result back",
    "runs": "from the first task submitted (or the first member here) to the last result",
    "connect": "a client on the local cluster, once it is up (a worker plugin registered)",
    "path": "the member table and the path analysis, here, on the members' cells read back "
            "as each member finished (by its worker on dask; a file not read then is read now)",
    "close": "waiting at the end for the local cluster to close (it closes meanwhile)",
    "tables": "summary.csv (and summary.parquet, failures.csv)",
    "ensemble_nc": "building and writing ensemble.nc (from the maps read back as members "
                   "finished)",
}


def time_left(elapsed: float, done: int, total: int) -> str:
    """``, ~2 min 10 s left``: the time the ``total - done`` runs still to go take at the
    pace of the ``done`` ones so far; empty before the first."""
    if done <= 0 or total <= done:
        return ""
    left = elapsed / done * (total - done)
    if left < 1:
        return ", <1 s left"
    if left < 60:
        return f", ~{left:.0f} s left"
    minutes, seconds = divmod(int(round(left)), 60)
    if minutes < 60:
        return f", ~{minutes} min {seconds:02d} s left"
    return f", ~{minutes // 60} h {minutes % 60:02d} min left"


class ProgressLine:
    """``[#####.....] 12/21 members, 1 failed (40.2 s, ~30 s left)`` on one terminal line;
    failures on their own. The time left is from the members run since the line started
    (members reused from an earlier run are not counted in its pace)."""

    def __init__(self, total: int, stream=None, live: bool | None = None, quiet: bool = False,
                 unit: str = "members"):
        stream = stream if stream is not None else sys.stderr
        self.total, self.stream, self.quiet, self.unit = total, stream, quiet, unit
        self.live = (stream.isatty() if live is None else live) and not quiet
        self.done = self.failed = 0
        self.started = time.perf_counter()
        self.elapsed = math.nan  #: s, when closed: the last time the line showed
        self._base: tuple[int, float] | None = None  # (done, s) at the first update

    def info(self, message: str) -> None:
        """A line of information (where the members run), left out when quiet."""
        if not self.quiet:
            self.note(message)

    def update(self, done: int, failed: int) -> None:
        self.done, self.failed = done, failed
        wall = time.perf_counter() - self.started
        if self._base is None:
            self._base = (done, wall)
        if not self.live:
            return
        width = 30
        filled = int(width * done / max(self.total, 1))
        left = time_left(wall - self._base[1], done - self._base[0], self.total - self._base[0])
        self.stream.write(f"\r  [{'#' * filled}{'.' * (width - filled)}] {done}/{self.total} "
                          f"{self.unit}, {failed} failed ({wall:5.1f} s{left})\033[K")
        self.stream.flush()

    def failure(self, member: Member, error: str) -> None:
        if self.live:
            self.stream.write("\r\033[K")
        self.stream.write(f"member {member.index} ({member.scenario_hash}, {member.label}) "
                          f"failed: {error}\n")
        self.stream.flush()
        self.update(self.done, self.failed)

    def note(self, message: str) -> None:
        """One line of its own (the progress line is redrawn after it)."""
        if self.live:
            self.stream.write("\r\033[K")
        self.stream.write(message + "\n")
        self.stream.flush()
        self.update(self.done, self.failed)

    def close(self) -> None:
        if math.isfinite(self.elapsed):
            return  # closed already
        self.update(self.done, self.failed)  # the final time on the line
        self.elapsed = time.perf_counter() - self.started
        if self.live:
            self.stream.write("\n")
            self.stream.flush()


def member_path(outdir: Path, member: Member) -> Path:
    return Path(outdir) / "members" / f"{member.scenario_hash}.nc"


def _clean_temporaries(folder: Path) -> None:
    """Temporary files of members whose worker was killed while writing."""
    for tmp in folder.glob(".*.nc.*.tmp"):
        tmp.unlink(missing_ok=True)
    for tmp in (folder.parent / "checksums").glob(".*.sha256.*.tmp"):
        tmp.unlink(missing_ok=True)


def auto_batch(n_members: int, n_workers: int) -> int:
    """Members per task: about 16 tasks per worker, so the tail stays short."""
    return max(1, n_members // max(1, 16 * n_workers))


#: The files an ensemble writes in its folder besides members/ and checksums/.
FOLDER_FILES = ("summary.csv", "summary.parquet", "failures.csv", "ensemble.nc", "report.md")


def ensemble_inputs(ensemble: Ensemble) -> dict:
    """:func:`avflow.files.protected` of every file the ensemble reads: its file, and the
    scenario and data files of its base and of every member (a member may vary a DEM)."""
    from avflow.files import protected

    paths = {ensemble.path, *ensemble.base.input_files(), ensemble.sample.get("calibration")}
    for member in ensemble.members:
        paths.update(member.scenario.input_files())
    return protected(sorted(p for p in paths if p))


def run_ensemble(ensemble: Ensemble, outdir: str | os.PathLike, **options) -> Outcome:
    """Run every member not already done, then write summary.csv and ensemble.nc (the
    options: :func:`_run_locked`). The folder is checked first (a folder, writable; none of
    its files an input of the ensemble) and locked while the ensemble runs: a second
    ensemble on it is refused with one line naming the holder. A members/ folder made by a
    run that failed before any member (a scheduler that cannot be reached) is removed."""
    from avflow.files import check_folder, check_target, output_lock

    outdir = check_folder(Path(outdir), "ensemble folder")
    inputs = ensemble_inputs(ensemble)
    for name in FOLDER_FILES:
        check_target(outdir / name, inputs, what="ensemble output")
    members = outdir / "members"
    fresh = not members.exists()
    # held_lock: the caller (a calibration) holds the folder's lock already
    held = options.pop("held_lock", False)
    with (contextlib.nullcontext() if held
          else output_lock(outdir, folder=True, what="ensemble folder")):
        try:
            return _run_locked(ensemble, outdir, **options)
        except BaseException:
            if fresh:
                with contextlib.suppress(OSError):
                    members.rmdir()  # only when empty
            raise


def _run_locked(ensemble: Ensemble, outdir: Path, *, scheduler: str | None = None,
                workers: int | None = None, batch: int | None = None,
                progress: ProgressLine | None = None, write_outputs: bool = True,
                client=None, connect_timeout: float = CONNECT_TIMEOUT,
                starting: _ClusterStart | None = None) -> Outcome:
    """Run every member not already done, then write summary.csv and ensemble.nc.

    ``scheduler``: address (``tcp://host:port``) or scheduler file of a running cluster,
    reached within ``connect_timeout`` s or :class:`ClusterError`; None starts an embedded
    ``LocalCluster`` with ``workers`` single-threaded worker processes (default: one per
    core). ``workers=0`` runs the members in this process, one after the other (no dask).
    ``client``: an existing ``distributed.Client`` to use. Ctrl-C closes the cluster and
    raises :class:`Interrupted` saying how many members finished (a rerun resumes).

    By default (no ``workers``, ``scheduler`` or ``client``) the size of the members
    decides, and one line on stderr says what was chosen (:func:`_choose_where`): the first
    member runs here, timed, and the others follow it here unless a local cluster of one
    worker per core would finish them sooner, its start (:data:`CLUSTER_START_S`) included.
    A resumed run keeps in ``summary.csv`` the ``member_time`` of the members it reuses.
    ``starting``: a local cluster started earlier (:func:`start_local_cluster`, by the
    command line while it checks the ensemble file), used if it fits, closed in any case.
    """
    outdir = Path(outdir)
    folder = outdir / "members"
    folder.mkdir(parents=True, exist_ok=True)
    _clean_temporaries(folder)
    rows: dict[int, dict] = {}
    todo: list[Member] = []
    progress = progress or ProgressLine(len(ensemble.members))
    times = _previous_member_times(outdir)
    timings: dict[str, float] = {}
    clock = time.perf_counter()
    for member in ensemble.members:
        path = member_path(outdir, member)
        row, why = check_member_file(path, member.scenario_hash)
        if row is not None:
            row.update(reused=True, member_time=times.get(member.scenario_hash, math.nan))
            rows[member.index] = row
        else:
            if why:
                progress.note(f"member {member.index} ({member.scenario_hash}, {member.label}): "
                              f"not reusing {path.relative_to(outdir)}: {why}; running it "
                              "again")
            todo.append(member)
    n_failed = sum(r["status"] not in OK_STATUSES for r in rows.values())
    timings["check"] = time.perf_counter() - clock
    progress.update(len(rows), n_failed)

    # What the end needs of each member file (the maps of ensemble.nc, the cells of the
    # path analysis) is read once, by the worker as its member finishes (member_digest),
    # and kept here as the rows come in; the files of reused members are read here while
    # the others run (this process has nothing else to do then). The end reads no member
    # file again: the path analysis, summary.csv and ensemble.nc are made from memory.
    profile = ensemble.base.terrain.kind == "profile"
    maps = None  # MemberMaps, made when the first is kept (xarray imported then, not before)
    points: dict[int, object] = {}  # realization -> RunPoints, for the path analysis
    unread = [m for m in ensemble.members if m.index in rows
              and rows[m.index]["status"] != "failed"]  # reused members, read when idle

    def keep(index: int, digest: dict) -> None:
        """A member's :func:`member_digest`; a part missing is read at the end."""
        nonlocal maps
        if write_outputs and digest.get("maps") is not None:
            if maps is None:
                from avflow.ensemble.dataset import MemberMaps

                maps = MemberMaps(len(ensemble.members), profile)
            try:
                maps.put(index, digest["maps"])
            except Exception:  # noqa: BLE001 - read again, and reported, for ensemble.nc
                pass
        if digest.get("points") is not None:
            points[index] = _share_grid(digest["points"], points)

    def read_one() -> bool:
        """Read one reused member's file; False when none is left to read."""
        if not unread:
            return False
        member = unread.pop(0)
        keep(member.index, member_digest(member_path(outdir, member), profile))
        return True

    def record(member: Member, row: dict) -> None:
        nonlocal n_failed
        digest = row.pop("digest", None)
        rows[member.index] = row
        if row["status"] not in OK_STATUSES:
            n_failed += 1
            progress.failure(member, row["error"])
        if row["status"] != "failed":
            if digest is None:  # a worker of an older avflow: read here
                unread.append(member)
            else:
                keep(member.index, digest)
        progress.update(len(rows), n_failed)

    def finish() -> object:
        """The member table, the path analysis, summary.csv and ensemble.nc."""
        clock = time.perf_counter()
        table = member_table(ensemble, rows, outdir)
        path_ds = _path_analysis(ensemble, table, outdir, points)  # adds path_* columns
        timings["path"] = time.perf_counter() - clock
        clock = time.perf_counter()
        if write_outputs:
            write_tables(table, outdir)
            timings["tables"] = time.perf_counter() - clock
            clock = time.perf_counter()
            from avflow.ensemble.dataset import ensemble_dataset, write_ensemble_netcdf

            ds = ensemble_dataset(ensemble, table, outdir, maps)
            if path_ds is not None:
                ds = ds.merge(path_ds)
                ds.attrs.update(path_ds.attrs)
            write_ensemble_netcdf(ds, outdir / "ensemble.nc")
            timings["ensemble_nc"] = time.perf_counter() - clock
        else:
            timings["tables"] = time.perf_counter() - clock
        return table

    t0 = time.perf_counter()
    startup = 0.0
    n_workers = 0
    table = None
    where = "here" if workers == 0 else "scheduler" if scheduler else "client" if client \
        else "local cluster"
    # Members on one thread on dask: so is Numba in the local cluster's workers (no idle
    # thread pools); the nanny already sets OMP/MKL/OPENBLAS_NUM_THREADS=1 (dask's default).
    one_thread = {getattr(m.scenario.numerics, "threads", 1) or 1 for m in todo}
    env = {"NUMBA_NUM_THREADS": "1"} if one_thread == {1} else {}
    # a local cluster started earlier or while probing: used if it fits, else closed
    speculative: list[_ClusterStart] = [starting] if starting is not None else []

    def speculate() -> None:
        if not speculative:
            speculative.append(start_local_cluster(None, env))

    def started_fits(n: int | None) -> _ClusterStart | None:
        """The cluster started earlier if it has the workers wanted, else None (it closes
        meanwhile)."""
        if not speculative or not isinstance(speculative[-1], _ClusterStart):
            return None
        if speculative[-1].n == (n or os.cpu_count() or 1) and speculative[-1].env == env:
            return speculative.pop()
        speculative.append(_discard(speculative.pop()))
        return None

    try:
        started = time.perf_counter()
        if todo and workers is None and scheduler is None and client is None:
            todo, workers = _choose_where(ensemble, todo, outdir, record, progress,
                                          speculate, profile)
            timings["probe"] = time.perf_counter() - started
            where = "here" if workers == 0 else where
            if workers == 0 and speculative:  # not needed: it closes while they run here
                speculative.append(_discard(speculative.pop()))
        if todo and workers == 0 and scheduler is None and client is None:
            clock = time.perf_counter()
            for member in todo:
                record(member, run_member(member.scenario.source_text,
                                          str(member_path(outdir, member)), digest=profile))
            timings["runs"] = time.perf_counter() - clock
            wall = time.perf_counter() - started
        elif todo:
            t0 = time.perf_counter()
            with _deferred_sigint() as sigint, _client(
                    scheduler, workers, client, tiny_scenario_yamls(ensemble, one_thread=True),
                    connect_timeout, sigint.check, timings, env,
                    started_fits(workers) if scheduler is None and client is None
                    else None) as cl:
                n_workers = len(cl.client.scheduler_info(n_workers=-1)["workers"]) if hasattr(
                    cl.client, "scheduler_info") else 0
                startup = time.perf_counter() - t0
                _run_on_dask(cl.client, todo, outdir,
                             batch or auto_batch(len(todo), max(n_workers, 1)), record,
                             sigint.check, timings, idle=read_one, digest=profile)
                wall = time.perf_counter() - started - startup
                progress.close()
                _clean_temporaries(folder)
                # The cluster closes while the reused members left are read and the path
                # analysis, summary.csv and ensemble.nc are made here, from memory.
                cl.close_soon()
                while read_one():
                    sigint.check()
                table = finish()
                sigint.check()  # a Ctrl-C while writing them: said once they are written
        else:
            wall = time.perf_counter() - started
    except KeyboardInterrupt:  # the cluster is closed by now (_client.__exit__)
        _close_speculative(speculative)
        progress.close()
        _clean_temporaries(folder)
        kept = sum(checksum_path(member_path(outdir, m)).is_file() for m in ensemble.members)
        raise Interrupted(f"interrupted: {kept} of {len(ensemble.members)} members finished "
                          f"and kept in {folder}; run the same command again to resume "
                          "(the others run then)") from None
    except BaseException:
        _close_speculative(speculative)
        raise
    if table is None:
        progress.close()
        _clean_temporaries(folder)
        while read_one():  # reused members: each file opened once
            pass
        table = finish()
    _close_speculative(speculative)
    ran = sum(not r.get("reused") for r in rows.values())
    return Outcome(table, ran, len(rows) - ran, n_failed, wall, startup, n_workers,
                   progress.elapsed, where, timings)


def _choose_where(ensemble: Ensemble, todo: list[Member], outdir: Path, record,
                  progress: ProgressLine, speculate: Callable[[], None] = lambda: None,
                  digest: bool | None = None) -> tuple[list[Member], int | None]:
    """Where the members run when nothing says: ``(members left, workers)``, 0 for here.

    A local cluster costs :data:`CLUSTER_START_S` before its first result: a few short
    members are done sooner in this process. The first member runs here (after the kernels
    are loaded, so its time is the member's own), and its time ``t1`` decides: the others
    stay here unless ``start + t1 (n - 1) / cores < t1 (n - 1)``, ``start`` being what is
    left of :data:`CLUSTER_START_S`: on :data:`SPECULATE_MIN_CORES` cores or more the
    cluster starts (``speculate``) while the first member runs, its other cores being idle
    then. Members estimated at more than :data:`PROBE_MAX_CELLS` cells go to the cluster
    without a probe. One line on stderr says what was chosen. ``digest``: see
    :func:`run_member`.
    """
    cores = os.cpu_count() or 1
    n = len(todo)
    if cores < 2 or n == 1:
        why = "one core" if cores < 2 else "one member to run"
        progress.info(f"avflow: {n} member(s) to run, {why}: running here, in this process "
                      "(no dask cluster)")
        return todo, 0
    from avflow.simulation.resources import estimate

    try:
        cells = estimate(todo[0].scenario).cells
    except Exception:  # noqa: BLE001 - the member reports its own problem when it runs
        cells = 0
    if cells > PROBE_MAX_CELLS:
        progress.info(f"avflow: {n} members of ~{cells:,} cells: starting a local dask "
                      f"cluster of {cores} workers (--workers 0 runs them here)")
        return todo, None
    speculated = time.perf_counter()
    if cores >= SPECULATE_MIN_CORES:
        speculate()
    warm(tiny_scenario_yamls(ensemble))  # Numba's kernels loaded: t1 is the member's own
    started = time.perf_counter()
    first = todo[0]
    record(first, run_member(first.scenario.source_text, str(member_path(outdir, first)),
                             digest=digest))
    t1 = time.perf_counter() - started
    serial = t1 * (n - 1)
    start = CLUSTER_START_S
    if cores >= SPECULATE_MIN_CORES:  # started meanwhile
        start = max(0.0, start - (time.perf_counter() - speculated))
    cluster = start + serial / cores
    if cluster < serial:
        progress.info(f"avflow: {n} members, the first took {t1:.2f} s here: starting a "
                      f"local dask cluster of {cores} workers for the other {n - 1} (about "
                      f"{cluster:.0f} s against {serial:.0f} s here; --workers 0 runs them "
                      "here)")
        return todo[1:], None
    progress.info(f"avflow: {n} members, the first took {t1:.2f} s here: running the other "
                  f"{n - 1} here too (about {serial:.1f} s; a dask cluster takes about "
                  f"{CLUSTER_START_S:.0f} s to start; --workers N starts one anyway)")
    return todo[1:], 0


def _previous_member_times(outdir: Path) -> dict[str, float]:
    """``scenario_hash -> member_time`` from the summary.csv of an earlier run, if any."""
    path = Path(outdir) / "summary.csv"
    if not path.is_file():
        return {}
    try:
        import pandas as pd

        old = pd.read_csv(path, usecols=["scenario_hash", "member_time"],
                          dtype={"scenario_hash": str})
    except Exception:  # noqa: BLE001 - an old or foreign table: the times are unknown
        return {}
    return {h: float(t) for h, t in zip(old["scenario_hash"], old["member_time"])
            if isinstance(h, str) and math.isfinite(float(t))}


class _client:
    """Context manager: a Client on the given scheduler, or on a fresh LocalCluster.

    A local cluster starts in a thread while this process warms (imports, Numba's kernels
    into the cache): its workers import what a member needs meanwhile (:func:`dask_setup`)
    and load the kernels in their first member. ``env``: environment of its workers.
    :meth:`close_soon` starts closing it in the background (:meth:`__exit__` waits).
    """

    def __init__(self, scheduler, workers, client, tiny, connect_timeout=CONNECT_TIMEOUT,
                 check: Callable[[], None] = lambda: None, timings: dict | None = None,
                 env: dict | None = None, starting: _ClusterStart | None = None):
        self.scheduler, self.workers, self.given, self.tiny = scheduler, workers, client, tiny
        self.connect_timeout, self.check = connect_timeout, check
        self.timings = {} if timings is None else timings
        self.env = env or {}
        self.starting = starting  #: a local cluster already starting (see _choose_where)
        self.cluster = self.client = self.closing = None

    def __enter__(self):
        try:
            self._start()
        except BaseException:  # Ctrl-C or an error while starting: nothing left running
            self.__exit__()
            raise
        return self

    def _start(self) -> None:
        from distributed import Client

        clock = time.perf_counter()
        if self.given is not None:
            warm(self.tiny)
            self.timings["warm_here"] = time.perf_counter() - clock
            self.client = self.given
        elif self.scheduler:
            self.client = _connect(self.scheduler, self.connect_timeout)
            self.timings["cluster"] = time.perf_counter() - clock
            clock = time.perf_counter()
            warm(self.tiny)
            self.timings["warm_here"] = time.perf_counter() - clock
        else:
            self.check()
            if self.starting is None:
                # The worker processes inherit SIGINT ignored: a terminal's Ctrl-C, sent to
                # the whole process group, acts only in this process, which closes the
                # cluster (else each worker prints its own KeyboardInterrupt tracebacks).
                # Ignored here only until they are spawned: a Ctrl-C in that while is lost.
                self.starting = start_local_cluster(self.workers, self.env)
            warm(self.tiny)  # meanwhile, before any worker loads the kernels (see warm)
            self.timings["warm_here"] = time.perf_counter() - clock
            self.check()
            self.cluster = self.starting.result(self.check)
            self.timings["cluster"] = self.starting.elapsed
            clock = time.perf_counter()
            # not the process's default scheduler: this process's file I/O (member maps,
            # ensemble.nc) would then take a distributed.Lock through xarray, and fail with
            # "ConnectionPool is closed" once the cluster closes beside the writes
            self.client = Client(self.cluster, set_as_default=False)
            self.client.register_plugin(_ignore_sigint_plugin())  # restarted workers too
            self.timings["connect"] = time.perf_counter() - clock
        self.check()
        try:
            self.client.wait_for_workers(1, timeout=WORKER_TIMEOUT)
        except TimeoutError:
            where = f"the scheduler {self.scheduler}" if self.scheduler else "the cluster"
            raise ClusterError(f"no dask worker joined {where} within {WORKER_TIMEOUT:g} s; "
                               "start one with `dask worker ADDRESS`") from None
        self.check()

    def close_soon(self) -> None:
        """Start closing the local cluster in a thread (its workers exit meanwhile)."""
        if self.given is None and self.closing is None:
            self.closing = threading.Thread(target=self._close, name="avflow-close-cluster",
                                            daemon=True)
            self.closing.start()

    def _close(self) -> None:
        if self.client is not None:
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()

    def __exit__(self, *exc):
        if self.given is not None:
            return
        if self.closing is not None:
            clock = time.perf_counter()
            self.closing.join()
            self.timings["close"] = time.perf_counter() - clock
            return
        if self.starting is not None and self.cluster is None:
            self.cluster = self.starting.result()  # started meanwhile: closed below
        self._close()


class _ClusterStart(threading.Thread):
    """``LocalCluster(...)`` in a thread: one single-threaded worker process per core."""

    def __init__(self, n: int, env: dict):
        super().__init__(name="avflow-start-cluster", daemon=True)
        self.n, self.env = n, env
        self.cluster = self.error = None
        self.elapsed = math.nan
        import multiprocessing

        self._before = {p.pid for p in _children(multiprocessing)}

    def run(self) -> None:
        from distributed import LocalCluster

        started = time.perf_counter()
        try:
            # no dashboard; the scheduler's HTTP server (health, metrics), which it starts
            # anyway, on a free port: on its default, 8787, a second cluster on the machine
            # made dask warn on stderr that the port was taken
            self.cluster = LocalCluster(
                n_workers=self.n, threads_per_worker=1, processes=True,
                dashboard_address=None, scheduler_kwargs={"dashboard_address": ":0"},
                silence_logs=logging.ERROR, env=self.env,
                preload=["avflow.ensemble.orchestrate"])  # dask_setup, in each worker
        except BaseException as err:  # noqa: BLE001 - raised in the caller's thread
            self.error = err
        self.elapsed = time.perf_counter() - started

    def wait_spawned(self, timeout: float = 30.0) -> None:
        """Until the worker processes exist (or the start ended, or ``timeout`` s)."""
        import multiprocessing

        deadline = time.monotonic() + timeout
        while self.is_alive() and time.monotonic() < deadline:
            new = [p for p in _children(multiprocessing) if p.pid not in self._before]
            if len(new) >= self.n:
                return
            time.sleep(0.01)

    def result(self, check: Callable[[], None] = lambda: None):
        """The cluster, once started (``check`` every 50 ms meanwhile), or its error."""
        while self.is_alive():
            check()
            self.join(0.05)
        if self.error is not None:
            raise self.error
        return self.cluster


def start_local_cluster(workers: int | None = None, env: dict | None = None
                        ) -> _ClusterStart:
    """Start a local cluster of ``workers`` (default: one per core) single-threaded worker
    processes in a thread, for :func:`run_ensemble` (``starting=``); ``env``: of its
    workers (default: ``NUMBA_NUM_THREADS=1``, as members on one thread want). SIGINT is
    ignored here until the workers are spawned (they keep ignoring it, see _client)."""
    n = workers or os.cpu_count() or 1
    starting = _ClusterStart(n, {"NUMBA_NUM_THREADS": "1"} if env is None else env)
    with _sigint_ignored():
        starting.start()
        starting.wait_spawned()
    return starting


def close_started(starting: _ClusterStart | None) -> None:
    """Close a cluster from :func:`start_local_cluster` that no ensemble used."""
    if starting is not None:
        _discard(starting).join()


def _discard(starting: _ClusterStart) -> threading.Thread:
    """Close a local cluster that was started for nothing, in a thread (started)."""
    def close() -> None:
        try:
            cluster = starting.result()
        except BaseException:  # noqa: BLE001 - it did not start: nothing to close
            return
        cluster.close()

    closing = threading.Thread(target=close, name="avflow-discard-cluster", daemon=True)
    closing.start()
    return closing


def _close_speculative(speculative: list) -> None:
    """Close (or wait for the closing of) the cluster started while probing, if any."""
    while speculative:
        item = speculative.pop()
        (_discard(item) if isinstance(item, _ClusterStart) else item).join()


def _children(multiprocessing) -> list:
    """This process's multiprocessing children (started from any thread)."""
    for _ in range(100):
        try:
            return multiprocessing.active_children()
        except RuntimeError:  # the set changed size while another thread started one
            time.sleep(0.001)
    return []


def _scheduler_address(scheduler: str) -> str:
    """The address of ``--scheduler``: itself, or the ``address`` of a scheduler file; one
    line (:class:`ClusterError`) for a file that is no scheduler file or an unknown scheme."""
    import json

    from distributed.comm import parse_address, registry

    address = scheduler
    if os.path.isfile(scheduler):
        try:
            with open(scheduler, encoding="utf-8") as f:
                info = json.loads(f.read(1 << 20))
            address = info["address"]
            if not isinstance(address, str):
                raise TypeError
        except (OSError, ValueError, KeyError, TypeError):
            raise ClusterError(f"--scheduler {scheduler}: not a dask scheduler file (JSON with "
                               "the scheduler's 'address', as `dask scheduler "
                               "--scheduler-file` writes)") from None
    elif "://" not in scheduler and (scheduler.endswith(".json") or os.sep in scheduler):
        raise ClusterError(f"--scheduler {scheduler}: no such scheduler file")
    try:
        registry.get_backend(parse_address(address)[0])
    except ValueError as err:
        raise ClusterError(f"--scheduler {scheduler}: {err}") from None
    return address


def _probe(address: str, timeout: float) -> None:
    """Ask the scheduler at ``address`` who it is, all within ``timeout`` s: a port that
    answers in another protocol (HTTP) kept distributed's Client waiting past its own
    timeout (150 s and more), and a Client that failed to start logs tracebacks on its
    way out."""
    import asyncio

    from distributed.comm import connect

    async def ask() -> None:
        comm = await connect(address, timeout=timeout)
        try:
            await comm.write({"op": "identity", "reply": True})
            reply = await comm.read()
        finally:
            comm.abort()
        if not isinstance(reply, dict) or reply.get("type") != "Scheduler":
            raise OSError("it answers, but not as a dask scheduler")

    async def bounded() -> None:
        await asyncio.wait_for(ask(), timeout)

    asyncio.run(bounded())


def _connect(scheduler: str, timeout: float):
    """A Client on a scheduler address or scheduler file, or one line saying why not."""
    from distributed import Client

    address = _scheduler_address(scheduler)
    try:
        _probe(address, timeout)
        # not the default scheduler, as for the local cluster (see _client.__enter__)
        return Client(address, timeout=f"{timeout}s", set_as_default=False)
    except (OSError, TimeoutError, ValueError, EOFError) as err:
        detail = " ".join(str(err).split()) or type(err).__name__
        raise ClusterError(f"--scheduler {scheduler}: cannot connect within {timeout:g} s "
                           f"({detail}); is the dask scheduler running there?") from None


def _ignore_sigint_plugin():
    """A worker plugin: SIGINT ignored in the workers of the embedded cluster, including those
    a nanny restarts after the first ones (which inherited it ignored, see _sigint_ignored)."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class IgnoreSigint(WorkerPlugin):
        name = "avflow-ignore-sigint"

        def setup(self, worker):
            if threading.current_thread() is threading.main_thread():
                signal.signal(signal.SIGINT, signal.SIG_IGN)

    return IgnoreSigint()


class _deferred_sigint:
    """Ctrl-C only noted while dask is in use; ``check()`` raises KeyboardInterrupt at points
    where that is safe. (Raised inside distributed's blocking calls it trips their cleanup,
    which logs tracebacks from the event loop thread.) A second Ctrl-C raises at once.
    Main thread only (elsewhere: nothing)."""

    def __enter__(self):
        self.hit = False
        self.signum = signal.SIGINT
        self.active = threading.current_thread() is threading.main_thread()
        if self.active:
            self.old = signal.signal(signal.SIGINT, self._noted)
            # SIGTERM too: raised inside distributed's calls it printed CommClosedError
            # tracebacks; raised at check() by the handler it had (the command line's: 143)
            self.old_term = signal.signal(signal.SIGTERM, self._noted)
        return self

    def _noted(self, signum, frame):
        if self.hit:
            self._raise(frame)
        self.hit, self.signum = True, signum
        # the cluster is now closed on purpose: its broken connections (CommClosedError)
        # are no news, and their tracebacks are not printed
        for name in ("distributed", "tornado", "asyncio"):
            logging.getLogger(name).setLevel(logging.CRITICAL + 1)

    def _raise(self, frame=None):
        old = self.old_term if self.signum == signal.SIGTERM else None
        if callable(old):
            old(self.signum, frame)
        raise KeyboardInterrupt

    def check(self) -> None:
        if self.hit:
            self._raise()

    def __exit__(self, *exc):
        if self.active:
            signal.signal(signal.SIGINT, signal.default_int_handler if self.old is None
                          else self.old)
            signal.signal(signal.SIGTERM, signal.SIG_DFL if self.old_term is None
                          else self.old_term)
            if self.hit and exc[0] is None:  # noted while the cluster closed: not lost
                self._raise()


class _sigint_ignored:
    """SIGINT ignored for a while: the processes started meanwhile keep ignoring it (Python
    installs no KeyboardInterrupt handler where SIGINT is ignored at start). A Ctrl-C in
    that while is lost. Main thread only (elsewhere: nothing)."""

    def __enter__(self):
        self.active = threading.current_thread() is threading.main_thread()
        if self.active:
            self.old = signal.signal(signal.SIGINT, signal.SIG_IGN)

    def __exit__(self, *exc):
        if self.active:  # None: a handler set outside Python; the default is the closest
            signal.signal(signal.SIGINT, signal.default_int_handler if self.old is None
                          else self.old)


def _run_on_dask(client, todo: list[Member], outdir: Path, batch: int,
                 record: Callable[[Member, dict], None],
                 check: Callable[[], None] = lambda: None, timings: dict | None = None,
                 idle: Callable[[], bool] = lambda: False, digest: bool | None = None
                 ) -> None:
    """Submit the members in batches; results are recorded as they complete.

    A lost worker is the scheduler's business: its tasks are run again elsewhere (the member
    function is idempotent and writes atomically). A task that still errors (KilledWorker
    after repeated losses) marks its members failed. ``check`` is called every 50 ms while
    waiting (it raises on a Ctrl-C noted meanwhile, see :class:`_deferred_sigint`); ``idle``
    does a bit of work meanwhile (False: nothing left to do). Every member runs its
    :func:`cluster_scenario` (one thread unless it says otherwise); ``digest``: see
    :func:`run_member` (the worker reads back what the end needs of each member file).
    Each task carries the extension files this process loaded, for the worker to load.
    """
    from distributed import as_completed

    from avflow.scenario.extensions import loaded_files

    timings = {} if timings is None else timings
    clock = time.perf_counter()
    by_index = {m.index: m for m in todo}
    futures = {}
    extensions = loaded_files()  # the workers register what this process did from files
    for start in range(0, len(todo), batch):
        chunk = todo[start:start + batch]
        items = [(m.index, m.scenario.source_text, str(member_path(outdir, m))) for m in chunk]
        key = "avflow-member-" + "-".join(m.scenario_hash for m in chunk[:1]) + f"-{len(chunk)}"
        future = client.submit(run_batch, items, True, digest, extensions, key=key,
                                pure=False, retries=1)
        futures[future] = chunk
        check()
    pending = as_completed(list(futures), loop=client.loop, raise_errors=False)
    while not pending.is_empty():
        check()
        done = pending.next_batch(block=False)
        if not done:
            if not idle():
                time.sleep(0.05)
            continue
        if "first_result" not in timings:
            timings["first_result"] = time.perf_counter() - clock
        for future in done:
            _record_task(future, futures.pop(future), by_index, record)
    timings["runs"] = time.perf_counter() - clock


def _record_task(future, chunk: list[Member], by_index: dict, record) -> None:
    """The rows of one finished task, or its members failed with the task's error."""
    try:
        results = future.result()
    except Exception as err:  # noqa: BLE001 - infrastructure failure of the whole task
        for m in chunk:
            record(m, {**{n: math.nan for n in SUMMARY_FIELDS}, "status": "failed",
                       "steps": 0, "error": f"{type(err).__name__}: {err}",
                       "reused": False, "member_time": math.nan})
        return
    finally:
        future.release()
    for index, row in results:
        record(by_index[index], row)


# =========================================================================================
# Tables
# =========================================================================================


def _path_analysis(ensemble: Ensemble, table, outdir: Path, points: dict | None = None):
    """Runout along one path for every member (:mod:`avflow.output.path`; the base
    scenario's ``output.path``, else the farthest-travelling member's centre-of-mass track):
    ``path_*`` columns in ``table`` and the ``ensemble.nc`` variables, or None with a line
    on stderr when it cannot be done (the members' files are untouched). ``points``: the
    members' cells read already (realization -> RunPoints); the other files are read here."""
    from avflow.output.path import PathSettings, ensemble_path

    try:
        return ensemble_path(table, outdir, PathSettings.from_scenario(ensemble.base.output.path),
                             points)
    except Exception as err:  # noqa: BLE001 - the members are done; say why, go on
        print(f"avflow: warning: path analysis skipped: {' '.join(str(err).split())}",
              file=sys.stderr)
        return None


def _same_bits(a, b) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def _share_grid(points, kept: dict):
    """``points`` (a member's RunPoints) with the cell coordinates, bed and grid of a member
    kept before where they are the same to the bit: one copy of the grid for the members
    that share it, not one each."""
    other = next(iter(kept.values()), None)
    if other is None or other.kind != points.kind:
        return points
    for name in ("x", "y", "z"):
        if _same_bits(getattr(points, name), getattr(other, name)):
            setattr(points, name, getattr(other, name))
    if points.grid is not None and other.grid is not None and len(points.grid) == len(
            other.grid) and all(_same_bits(a, b) for a, b in zip(points.grid, other.grid)):
        points.grid = other.grid
    return points


def member_table(ensemble: Ensemble, rows: dict[int, dict], outdir: Path):
    """One row per member, in member order: parameters, status, summaries, file."""
    import pandas as pd

    params = ensemble.parameters()
    records = []
    for member in ensemble.members:
        row = rows[member.index]
        record = {"realization": member.index, "scenario_hash": member.scenario_hash,
                  "status": row["status"], "error": row.get("error", "")}
        for name, values in params.items():
            record[name] = values[member.index]
        for name in SUMMARY_FIELDS:
            record[name] = row.get(name, math.nan)
        record["runout_truncated"] = row.get("runout_truncated", -1)
        record["member_time"] = row.get("member_time", math.nan)
        record["steps"] = row.get("steps", 0)
        record["file"] = (os.path.relpath(member_path(outdir, member), outdir)
                          if row["status"] != "failed" else "")
        records.append(record)
    return pd.DataFrame.from_records(records)


def edge_members(table, varied) -> list[str]:
    """The members whose deposit reached the map's edge (runout a lower bound), each as
    ``realization (name=value, ...)`` with the varied parameters."""
    out = []
    for _, row in table.iterrows():
        if int(row.get("runout_truncated", 0)) == 1:
            values = ", ".join(f"{n}={row[n]:g}" if isinstance(row[n], float) else
                               f"{n}={row[n]}" for n in varied if n in row)
            out.append(f"{int(row['realization'])}" + (f" ({values})" if values else ""))
    return out


def write_tables(table, outdir: Path) -> None:
    """summary.csv (+ summary.parquet when pyarrow is importable) and failures.csv."""
    outdir = Path(outdir)
    atomic_write(outdir / "summary.csv", lambda tmp: table.to_csv(tmp, index=False))
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        pass
    else:
        atomic_write(outdir / "summary.parquet", lambda tmp: table.to_parquet(tmp, index=False))
    failed = table[~table["status"].isin(OK_STATUSES)]
    failures = outdir / "failures.csv"
    if len(failed):
        columns = [c for c in table.columns if c not in SUMMARY_FIELDS
                   and c not in ("member_time", "steps", "file") and not c.startswith("path_")]
        atomic_write(failures, lambda tmp: failed[columns].to_csv(tmp, index=False))
    else:
        failures.unlink(missing_ok=True)

