"""Files written without losing any: every command that writes goes through here.

- :func:`check_target`: before anything runs, refuse a target that is one of the command's
  inputs (by device and inode, so links and ``..`` do not hide it; a shapefile's or a
  raster's sidecars count, :func:`protected`), that is a folder or not a regular file (a
  device, a pipe: replacing ``/dev/null`` as root would be a disaster), or whose folder
  cannot take a file.
- :func:`atomic_write`: the file is written to ``.NAME.XXXXXXXX.tmp`` next to the target
  (``mkstemp``: unique per process), flushed to disk, checked (``verify``: GDAL reports a
  full disk as a log message, not an error), and only then renamed over the target. A
  failure leaves the previous file as it was and no temporary.
- :func:`output_lock`: an advisory lock (``flock``, released by the kernel when the holder
  dies) on an output file or folder, so a second command on the same output says who
  holds it instead of deleting the first one's temporary.

It sits beside :mod:`avflow.errors`, below every stage: terrain, output and ensemble write
through it.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import socket
import stat
import tempfile
from pathlib import Path
from typing import Callable, Iterable

from avflow.errors import AvflowError


class OutputError(AvflowError):
    """An output path that cannot be used (found before the run: exit code 2)."""

    exit_code = 2


class OutputWriteError(OutputError):
    """A write that failed after the work was done (full disk, failing file system): 1."""

    exit_code = 1


#: Files GIS programs keep beside a data file ``NAME.EXT``: ``NAME`` + one of these (a
#: shapefile's index, attributes, projection, code page; a raster's world file, overviews,
#: GDAL's statistics), or ``NAME.EXT`` + one of :data:`SIDECARS_OF_NAME`.
SIDECARS_OF_STEM = (".shp", ".shx", ".dbf", ".prj", ".cpg", ".qix", ".sbn", ".sbx", ".fbn",
                    ".fbx", ".ain", ".aih", ".atx", ".ixs", ".mxs", ".qmd", ".qpj", ".xml",
                    ".tfw", ".tifw", ".tiffw", ".wld", ".hdr", ".aux", ".aux.xml", ".ovr",
                    ".msk", ".rrd", ".stx")
SIDECARS_OF_NAME = (".aux.xml", ".ovr", ".msk", ".xml", ".aux", ".rrd")


#: Files a writer creates beside its target ``NAME.EXT``, by ``EXT``: ``NAME`` + one of these
#: (a shapefile's index, attributes, projection and code page; an ASCII grid's projection),
#: replaced along with the target, so checked with it.
CREATED_BESIDE = {".shp": (".shx", ".dbf", ".prj", ".cpg"), ".asc": (".prj",)}
#: ... and ``NAME.EXT`` + one of these (GDAL's statistics beside a raster).
CREATED_AFTER_NAME = {".tif": (".aux.xml",), ".tiff": (".aux.xml",), ".asc": (".aux.xml",)}

#: Files this command reads besides those its checks are given (extension files): no
#: output may replace them or their sidecars. :func:`read_input` adds one; :func:`forget_inputs`
#: starts afresh (a new command in the same process).
_READ: list[Path] = []


def read_input(path) -> None:
    """Count ``path`` among the inputs of the command that runs (an extension file)."""
    _READ.append(Path(path))


def forget_inputs() -> None:
    _READ.clear()


def created_with(path) -> list[Path]:
    """The files a writer of ``path`` creates or replaces beside it (:data:`CREATED_BESIDE`)."""
    path = Path(path)
    ext = path.suffix.lower()
    return ([path.with_suffix(s) for s in CREATED_BESIDE.get(ext, ())]
            + [path.with_name(path.name + s) for s in CREATED_AFTER_NAME.get(ext, ())])


def _why(err: OSError) -> str:
    if err.errno == errno.ENAMETOOLONG:
        return "the name is too long for the file system"
    return err.strerror or str(err)


def sidecars(path) -> list[Path]:
    """The files beside ``path`` that belong to it (:data:`SIDECARS_OF_STEM`), any case."""
    path = Path(path)
    stem, name = path.stem.lower(), path.name.lower()
    wanted = {stem + s for s in SIDECARS_OF_STEM} | {name + s for s in SIDECARS_OF_NAME}
    try:
        entries = list(os.scandir(path.parent))
    except OSError:
        return []
    return [Path(e.path) for e in entries if e.name.lower() in wanted and e.name != path.name]


def protected(paths: Iterable, with_sidecars: bool = True) -> dict[tuple[int, int], Path]:
    """(device, inode) -> path of every existing file among ``paths`` (and their sidecars),
    following links: what a command must never write over."""
    found: dict[tuple[int, int], Path] = {}
    for item in paths:
        if item is None:
            continue
        item = Path(item)
        for f in [item] + (sidecars(item) if with_sidecars else []):
            try:
                st = os.stat(f)
            except OSError:
                continue
            found.setdefault((st.st_dev, st.st_ino), f)
    return found


def _stat(path) -> os.stat_result | None:
    try:
        return os.stat(path)
    except FileNotFoundError:
        return None


def check_target(path, inputs: dict | Iterable = (), what: str = "output") -> Path:
    """Refuse, before anything runs, a target ``path`` that cannot take a result.

    ``inputs`` is :func:`protected` of the command's inputs (or paths to protect). Raises
    :class:`OutputError` naming the path and why. Nothing is created (a probe file made to
    test the folder is removed at once).
    """
    path = Path(path)
    inputs = dict(inputs) if isinstance(inputs, dict) else protected(inputs)
    for key, value in protected(_READ).items():  # extension files, and their sidecars
        inputs.setdefault(key, value)
    try:
        real = _stat(path)  # and lexically: a/missing/../b is b once a/missing is made
        lexical = _stat(Path(os.path.abspath(path)))
    except NotADirectoryError:  # a/file/x: said below, naming the file
        real = lexical = None
    except OSError as err:  # ENAMETOOLONG, ELOOP, EACCES
        raise OutputError(f"{what} {path}: {_why(err)}") from None
    for found in (real, lexical):
        same = found is not None and inputs.get((found.st_dev, found.st_ino))
        if same:
            raise OutputError(f"{what} {path}: is an input of this command ({same}); "
                              "choose another name")
    for beside in created_with(path):  # a shapefile's .prj must not replace the DEM's
        try:
            found = _stat(beside)
        except OSError:
            continue
        same = found is not None and inputs.get((found.st_dev, found.st_ino))
        if same:
            raise OutputError(f"{what} {path}: would replace {beside}, which belongs to "
                              f"an input of this command ({same}); choose another name")
    st = real or lexical
    if st is not None:
        if stat.S_ISDIR(st.st_mode):
            raise OutputError(f"{what} {path}: is a folder; give a file name, "
                              f"e.g. {path / 'out'}")
        if not stat.S_ISREG(st.st_mode):
            raise OutputError(f"{what} {path}: exists and is not a regular file (a device, "
                              "pipe or socket); refusing to replace it")
    folder, missing = path.parent, False
    while not folder.exists():
        if folder.is_symlink():  # a dangling link: mkdir would fail
            raise OutputError(f"{what} {path}: cannot create its folder: {folder} is a "
                              "broken link")
        folder, missing = folder.parent, True
    if not folder.is_dir():
        raise OutputError(f"{what} {path}: cannot create its folder: {folder} is not a "
                          "folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=temporary_prefix(path), suffix=".tmp", dir=folder)
    except OSError as err:
        how = "cannot create its folder in" if missing else "cannot write in"
        raise OutputError(f"{what} {path}: {how} {folder}: {_why(err)}") from None
    os.close(fd)
    os.unlink(probe)
    return path


def check_folder(path, what: str = "output folder") -> Path:
    """An output folder: refused when it is a file or cannot be created or written."""
    path = Path(path)
    try:
        if path.exists() and not path.is_dir():
            raise OutputError(f"{what} {path}: exists and is not a folder")
    except OSError as err:
        raise OutputError(f"{what} {path}: {_why(err)}") from None
    probe = path / ".avflow-probe"
    try:
        check_target(probe, what=what)
    except OutputError as err:  # said of the folder, not of the probe's name
        raise OutputError(str(err).replace(str(probe), str(path))) from None
    return path


def temporary_prefix(path: Path) -> str:
    return f".{Path(path).name}."


def stale_pattern(path: Path) -> re.Pattern:
    """The names ``mkstemp(prefix=".{name}.", suffix=".tmp")`` makes: 8 of [a-z0-9_]."""
    return re.compile(re.escape(temporary_prefix(path)) + r"[a-z0-9_]{8}\.tmp")


def _umask_mode() -> int:
    """rw for whoever the umask allows (mkstemp creates 0600 files)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def publish(tmp, path) -> None:
    """Give a finished temporary file the usual permissions, then rename it into place."""
    os.chmod(tmp, _umask_mode())
    os.replace(tmp, path)


def _missing_folders(folder: Path) -> list[Path]:
    """The folders of ``folder`` a mkdir would make, outermost first."""
    missing = []
    while not folder.exists() and folder != folder.parent:
        missing.insert(0, folder)
        folder = folder.parent
    return missing


def make_temporary(path) -> tuple[Path, list[Path]]:
    """An empty temporary file ``.{name}.XXXXXXXX.tmp`` next to ``path``, its folder made if
    missing; returns it and the folders made (deepest last). :class:`OutputWriteError` if
    the file cannot be made."""
    path = Path(path)
    created = _missing_folders(path.parent)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=temporary_prefix(path), suffix=".tmp",
                                   dir=path.parent)
    except OSError as err:
        raise OutputWriteError(f"cannot write {path}: {_why(err)}") from err
    os.close(fd)
    return Path(tmp), created


def remove_folders(created: list[Path]) -> None:
    """The folders :func:`make_temporary` made, deepest first, where still empty."""
    for folder in reversed(created):
        try:
            folder.rmdir()
        except OSError:
            break


def _disk_full(folder: Path) -> bool:
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    return st.f_bavail == 0 or (st.f_favail == 0 and st.f_files > 0)


def write_error(path, err: BaseException) -> OutputWriteError | None:
    """The one-line :class:`OutputWriteError` for an exception raised while writing ``path``,
    or None when it is no write error (an interrupt, a bug, an OutputError already: raised
    as it is)."""
    if isinstance(err, OutputError):
        return None
    if isinstance(err, OSError):  # ENOSPC, EDQUOT, EIO, EFBIG...
        why = _why(err)
        if err.errno != errno.ENOSPC and _disk_full(Path(path).parent):
            why = "No space left on device"  # HDF5 says "Permission denied" on a full disk
        return OutputWriteError(f"cannot write {path}: {why}")
    if isinstance(err, RuntimeError) and str(err).startswith("NetCDF:"):
        # netCDF-C reports a full disk during an HDF5 write as "NetCDF: HDF error"
        return OutputWriteError(f"cannot write {path}: {err} (is the disk full?)")
    name = type(err).__module__ or ""
    if name.startswith(("rasterio", "pyogrio")):  # GDAL could not write (CPLE_*, DataSourceError)
        text = " ".join(str(err).split())
        if len(text) > 200:  # SQLite quotes its whole statement: the cause is at the end
            text = text.rsplit(") failed: ", 1)[-1][-200:]
        return OutputWriteError(f"cannot write {path}: {text}")
    return None


def fsync(path) -> None:
    """Flush a written file to the disk: a full disk that the write did not report (delayed
    allocation) fails here, before the rename."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path, write: Callable[[Path], object],
                 verify: Callable[[Path], None] | None = None) -> Path:
    """``write(tmp)`` into a temporary next to ``path``, flushed, ``verify(tmp)`` (raises
    when the file is not what was meant), then renamed over ``path``. On any failure the
    temporary (and any folder made for it) is removed and ``path`` is as it was; a write
    error (a full disk...) is :class:`OutputWriteError`, one line."""
    path = Path(path)
    tmp, created = make_temporary(path)
    try:
        write(tmp)
        fsync(tmp)
        if verify is not None:
            verify(tmp)
        publish(tmp, path)
    except BaseException as err:
        tmp.unlink(missing_ok=True)
        remove_folders(created)
        error = write_error(path, err)
        if error is not None:
            raise error from None
        raise
    return path


def atomic_text(path, text: str) -> Path:
    """A text file written with :func:`atomic_write`, read back before the rename."""
    data = text.encode()

    def verify(tmp: Path) -> None:
        if tmp.read_bytes() != data:
            raise OutputWriteError(f"cannot write {path}: the file reads back different "
                                   "(is the disk full?)")

    return atomic_write(path, lambda tmp: tmp.write_bytes(data), verify)


# --- the lock of an output ------------------------------------------------------------------


def lock_path(path, folder: bool = False) -> Path:
    """``.NAME.lock`` beside an output file; ``.avflow.lock`` inside an output folder."""
    path = Path(path)
    return path / ".avflow.lock" if folder else path.with_name(f".{path.name}.lock")


@contextlib.contextmanager
def output_lock(path, folder: bool = False, what: str = "output"):
    """Hold the advisory lock of the output ``path`` (a file, or a ``folder``) while the
    block runs; :class:`OutputError` at once, naming the holder (pid and host), when another
    process holds it. The lock file is removed on release; one left by a killed process is
    taken over (the kernel released its lock)."""
    import fcntl

    path = Path(path)
    lock = lock_path(path, folder)
    created = _missing_folders(lock.parent)
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"{what} {path}: cannot create {lock.parent}: {_why(err)}") from None
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            remove_folders(created)
            raise OutputError(f"{what} {path}: cannot write in {lock.parent}: "
                              f"{_why(err)}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            holder = os.read(fd, 200).decode(errors="replace").strip() or "another process"
            os.close(fd)
            if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise OutputError(f"{what} {path}: in use by another avflow command "
                                  f"({holder}); wait for it to end or choose another "
                                  "output") from None
            raise OutputError(f"{what} {path}: cannot lock {lock}: {_why(err)}") from None
        try:  # the file we locked may have been removed by its last holder meanwhile
            same = os.fstat(fd).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode())
    except OSError:
        pass  # a full disk: the lock holds all the same, without its note
    try:
        yield lock
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)
        os.close(fd)
        remove_folders(created)


def remove_stale_temporaries(path) -> list[Path]:
    """Remove the temporaries that killed writes of ``path`` left next to it; return them.
    Only names of avflow's own pattern for that output name are touched; call it with the
    output's :func:`output_lock` held (a live write holds that lock)."""
    path = Path(path)
    pattern = stale_pattern(path)
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


# --- the inputs an output records -----------------------------------------------------------

#: Attributes of avflow's outputs that name one input file each (an ensemble's, a
#: calibration's, its base scenario's).
_PATH_ATTRIBUTES = ("ensemble_file", "calibration_file", "base_scenario", "region_file")


def recorded_inputs(attrs, beside=None) -> list[Path]:
    """The files an avflow output says it was made from: a run file's scenario and data
    files (DEM, release, maps, path line), an ensemble's, a calibration's (observations
    too), a region's. A command reading the output writes over none of them. Run files
    written before they recorded ``input_files``: the data paths of their scenario text,
    from the folder ``beside`` (the run file's)."""
    found: list = []
    listed = attrs.get("input_files")
    if isinstance(listed, str):
        found += listed.splitlines()
    elif isinstance(listed, (list, tuple)):
        found += [str(p) for p in listed]
    for key in _PATH_ATTRIBUTES:
        value = attrs.get(key)
        if isinstance(value, str) and value and "\n" not in value and len(value) < 4096:
            found.append(value)
    observed = attrs.get("observation_files")  # "label.key: PATH sha256:HEX" per line
    if isinstance(observed, str):
        for line in observed.splitlines():
            found.append(line.partition(": ")[2].rsplit(" sha256:", 1)[0])
    if listed is None and beside is not None and isinstance(attrs.get("scenario"), str):
        found += _paths_in_yaml(attrs["scenario"], Path(beside))
    return [Path(p) for p in found if str(p).strip()]


def _paths_in_yaml(text: str, folder: Path) -> list[Path]:
    """Every string of a scenario's YAML that names an existing file from ``folder``."""
    import yaml

    try:
        data = yaml.safe_load(text[:1 << 20])
    except (yaml.YAMLError, RecursionError, ValueError):
        return []
    out, stack = [], [data]
    while stack and len(out) < 1000:
        item = stack.pop()
        if isinstance(item, dict):
            stack += list(item.values())
        elif isinstance(item, list):
            stack += item
        elif isinstance(item, str) and 0 < len(item) < 4096 and "\n" not in item:
            path = folder / Path(item).expanduser()
            try:
                if path.is_file():
                    out.append(path)
            except OSError:  # a name too long for the file system
                continue
    return out


def inputs_of(path, attrs=None) -> dict[tuple[int, int], Path]:
    """:func:`protected` of an avflow output ``path`` that a command reads, and of the
    inputs it records (:func:`recorded_inputs` of its ``attrs``, with their sidecars)."""
    found = protected([path], with_sidecars=False)
    if attrs is not None:
        for key, value in protected(recorded_inputs(attrs, Path(path).parent)).items():
            found.setdefault(key, value)
    return found
