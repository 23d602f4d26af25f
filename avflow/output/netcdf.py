"""Atomic NetCDF writes: a temporary file in the target folder, then a rename.

Fields are stored as float32 with zlib + shuffle, one chunk per snapshot; summaries and
coordinates stay float64. The temporary file is ``.{name}.XXXXXXXX.tmp`` (``mkstemp``) next
to the output: a write killed by SIGKILL leaves one, and :func:`remove_stale_temporaries`
(called by ``avflow run`` before it runs) removes those of that output name only.
:func:`write_netcdf` writes a whole Dataset; :mod:`avflow.output.stream` writes the same
file snapshot by snapshot while the run goes on, with the same temporary and rename.
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

import numpy as np
import xarray as xr

from avflow.errors import AvflowError


class OutputError(AvflowError):
    """An output path that cannot be used (found before the run: exit code 2)."""

    exit_code = 2


class OutputWriteError(OutputError):
    """A write that failed after the run (full disk, failing file system): exit code 1."""

    exit_code = 1


def _temporary_prefix(path: Path) -> str:
    return f".{path.name}."


def _stale_pattern(path: Path) -> re.Pattern:
    """The names ``mkstemp(prefix=".{name}.", suffix=".tmp")`` makes: 8 of [a-z0-9_]."""
    return re.compile(re.escape(_temporary_prefix(path)) + r"[a-z0-9_]{8}\.tmp")


def remove_stale_temporaries(path) -> list[Path]:
    """Remove the temporaries that killed writes of ``path`` left next to it; return them.

    Only names of avflow's own pattern for that output name are touched. A write of the same
    path still running in another process would lose its temporary: run one at a time.
    """
    path = Path(path)
    pattern = _stale_pattern(path)
    removed = []
    try:
        entries = list(os.scandir(path.parent))
    except OSError:
        return removed
    for entry in entries:
        if pattern.fullmatch(entry.name) and entry.is_file(follow_symlinks=False):
            try:
                os.unlink(entry.path)
            except FileNotFoundError:
                continue
            removed.append(Path(entry.path))
    return removed


def check_output_path(path, inputs=()) -> Path:
    """Refuse, before anything runs, an output ``path`` that cannot take the result.

    Not one of ``inputs`` (the scenario file, its DEM...: compared after resolving links and
    ``..``), not a folder, and its folder writable (or, when missing, creatable: the nearest
    existing folder above it writable). Raises :class:`OutputError` naming the path and why.
    Nothing is created (a probe file made to test the folder is removed at once).
    """
    path = Path(path)
    target = path.resolve()
    for item in inputs:
        if item is None:
            continue
        same = Path(item).resolve() == target
        if not same and target.exists() and Path(item).exists():
            same = os.path.samefile(item, target)
        if same:
            raise OutputError(f"output {path}: is an input of the run ({item}); "
                              "choose another file name")
    if path.is_dir():
        raise OutputError(f"output {path}: is a folder; give a file name, "
                          f"e.g. {path / 'out.nc'}")
    if path.exists() and not path.is_file():
        raise OutputError(f"output {path}: exists and is not a regular file")
    folder = path.parent
    missing = False
    while not folder.exists():
        if folder.is_symlink():  # a dangling link: mkdir would fail
            raise OutputError(f"output {path}: cannot create its folder: {folder} is a "
                              "broken link")
        folder, missing = folder.parent, True
    if not folder.is_dir():
        raise OutputError(f"output {path}: cannot create its folder: {folder} is not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=_temporary_prefix(path), suffix=".tmp", dir=folder)
    except OSError as err:
        what = "cannot create its folder in" if missing else "cannot write in"
        raise OutputError(f"output {path}: {what} {folder}: "
                          f"{err.strerror or err}") from None
    os.close(fd)
    os.unlink(probe)
    return path


#: Side of the square tiles (in cells) that hold a map field of one snapshot on
#: (time, y, x): 128 x 128 float32 = 64 KiB a chunk. A streamed record writes only the
#: tiles that hold the flow (:mod:`avflow.output.stream`), so its cost follows the flow, not
#: the map. Each chunk costs HDF5 and zlib some 40 us besides its bytes: 64-cell tiles made a
#: flow-sized map's record 30% dearer than one chunk a record, 128-cell ones 10%
#: (``workflows/benchmark_area.py``).
TILE = 128


def field_chunks(var) -> tuple:
    """The chunk shape of a float field: one tile of one snapshot on (time, y, x)
    (:data:`TILE`), one snapshot on (time, space), the whole variable otherwise."""
    if var.dims[0] != "time":
        return var.shape
    if var.ndim == 3:
        return (1, min(TILE, var.shape[1]), min(TILE, var.shape[2]))
    return (1, *var.shape[1:])


def encoding_for(ds: xr.Dataset) -> dict:
    """float32 + zlib for the big fields, chunks of :func:`field_chunks`; zlib for the
    integer fields on time (flow_state), one chunk a snapshot; no fill on coordinates."""
    enc = {}
    for name, var in ds.variables.items():
        if name in ds.coords:
            enc[name] = {"_FillValue": None}
        elif var.dtype.kind == "f" and var.ndim >= 1 and var.dims != ("time",):
            chunks = field_chunks(var)
            fill = np.float32(np.nan) if bool(np.isnan(var.values).any()) else None
            enc[name] = {"dtype": "float32", "zlib": True, "complevel": 2, "shuffle": True,
                         "chunksizes": chunks, "_FillValue": fill}
        elif var.dtype.kind == "f":
            enc[name] = {"_FillValue": None}
        elif var.dtype.kind == "i" and var.ndim >= 2 and var.dims[0] == "time":
            # flow_state: mostly 0 (dry), 1 byte a cell; deflated, one chunk a snapshot
            enc[name] = {"zlib": True, "complevel": 2, "chunksizes": (1, *var.shape[1:])}
    return enc


def _umask_mode() -> int:
    """rw for whoever the umask allows (mkstemp creates 0600 files)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def publish(tmp, path) -> None:
    """Give a finished temporary file the usual permissions, then rename it into place."""
    os.chmod(tmp, _umask_mode())
    os.replace(tmp, path)


def make_temporary(path) -> tuple[Path, list[Path]]:
    """An empty temporary file ``.{name}.XXXXXXXX.tmp`` next to ``path``, its folder made if
    missing; returns it and the folders made (deepest last). :class:`OutputWriteError` if
    the file cannot be made."""
    path = Path(path)
    created = []
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        created.insert(0, folder)
        folder = folder.parent
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=_temporary_prefix(path), suffix=".tmp",
                                   dir=path.parent)
    except OSError as err:
        raise OutputWriteError(f"cannot write {path}: {err.strerror or err}") from err
    os.close(fd)
    return Path(tmp), created


def write_error(path, err: BaseException) -> OutputWriteError | None:
    """The one-line :class:`OutputWriteError` for an exception raised while writing ``path``,
    or None when it is no write error (an interrupt, a bug, an OutputWriteError already:
    raised as it is)."""
    if isinstance(err, OutputError):
        return None
    if isinstance(err, OSError):  # ENOSPC, EDQUOT, EIO...
        return OutputWriteError(f"cannot write {path}: {err.strerror or err}")
    if isinstance(err, RuntimeError) and str(err).startswith("NetCDF:"):
        # netCDF-C reports a full disk during an HDF5 write as "NetCDF: HDF error"
        return OutputWriteError(f"cannot write {path}: {err} (is the disk full?)")
    return None


def write_netcdf(ds: xr.Dataset, path) -> Path:
    """Write ``ds`` to ``path`` atomically: a temporary file in the same folder, then rename."""
    path = Path(path)
    tmp, _ = make_temporary(path)
    try:
        ds.to_netcdf(tmp, encoding=encoding_for(ds), engine="netcdf4")
        publish(tmp, path)
    except BaseException as err:
        Path(tmp).unlink(missing_ok=True)
        error = write_error(path, err)
        if error is not None:
            raise error from err
        raise
    return path
