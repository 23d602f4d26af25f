"""Snapshots appended to the NetCDF file as the run takes them (``avflow run``, ensembles).

A :class:`SnapshotStream` is the ``snapshots`` of
:func:`~avflow.simulation.runner.simulate`. At the first output time it makes the temporary
file ``.NAME.XXXXXXXX.tmp`` next to the output (:func:`~avflow.output.netcdf.make_temporary`,
as :func:`~avflow.output.netcdf.write_netcdf` does) and writes there, through xarray, the
fields on (time, space) of that snapshot (:func:`~avflow.output.dataset.to_dataset`,
``part="fields"``: ``h``, ``u``, ``v``, ``flow_state``; the mesh variables before them on
triangles) with ``time`` an unlimited dimension; every later output time appends one record
to each field (netCDF4). :meth:`SnapshotStream.finish` then writes what only the end knows
(``part="rest"``: the times and series, the maps of the final state, the static maps, the
summaries, the global attributes) and renames the file over the output. A run that fails
(:class:`~avflow.errors.RunFailed`), an interrupt (the progress callback, Ctrl-C) or a write
that fails leaves no file: the temporary, and any folder made for it, is removed, and a
file already at the output is untouched.

Cost follows the flow: a record holds the whole map, but only the window of cells where
the flow is or was at the previous output time is computed again
(:class:`~avflow.output.dataset.WindowedFields`; the centre of mass likewise,
:func:`~avflow.simulation.runner.center_of_mass`). What still grows with the map is one
pass over h to find the flow, and compressing and writing the record: the dry part of the
map is deflated too (about 1 ms per field and 180k dry cells), which the file's format
(zlib with shuffle, one chunk per record) asks for.

Memory: the state, the terrain and one snapshot, whatever the number of snapshots (the
times and series, a few numbers per snapshot, are kept for the end); HDF5's chunk cache
holds one record per field (its default, up to 64 MiB a variable, kept every record of a
run until the file was closed and compressed them all then).

The file equals ``write_netcdf(to_dataset(result), path)`` variable by variable (names,
order, dimensions, dtypes, values, attributes, compression, ``_FillValue``, the CF time
units, the global attributes; ``tests/test_streamed_output.py``). Only the storage differs:
``time`` is unlimited, so the variables on ``time`` alone are chunked rather than
contiguous and ``flow_state`` is stored one chunk per snapshot (uncompressed as before). The
float fields take NaN as ``_FillValue`` when the first snapshot has a NaN, as
:func:`~avflow.output.netcdf.encoding_for` does looking at every snapshot: NaN there is the
cells outside a DEM, the same in every snapshot (a non-finite state fails the run).
"""

from __future__ import annotations

import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import xarray as xr

from avflow.output.dataset import TIME_FIELDS, WindowedFields, to_dataset
from avflow.output.netcdf import encoding_for, make_temporary, publish, write_error
from avflow.simulation.runner import RunResult, Snapshots, cell_flags, wet_cells

try:  # the lock xarray takes around netCDF-C calls: HDF5 is not thread-safe, and two
    # members may run in the threads of one dask worker (xarray's own calls take it too)
    from xarray.backends.netCDF4_ import NETCDF4_PYTHON_LOCK as _NETCDF_LOCK
except ImportError:  # pragma: no cover - another xarray layout
    _NETCDF_LOCK = threading.Lock()


class SnapshotStream(Snapshots):
    """The snapshots of a run written to ``path`` as they are taken::

        with SnapshotStream(path) as stream:
            result = simulate(scenario, snapshots=stream)
            ds = stream.finish(result)  # the file is at path now

    Leaving the ``with`` block before :meth:`finish` (an exception, an interrupt) removes
    the temporary file. A failed write raises :class:`~avflow.output.netcdf.OutputWriteError`.
    """

    in_memory = False

    def __init__(self, path):
        super().__init__()
        self.path = Path(path)
        self.records = 0  #: snapshots written so far
        self.finished = False
        self._tmp: Path | None = None
        self._created: list[Path] = []  # folders made for the file
        self._nc = None  # netCDF4.Dataset, open from the first snapshot to finish()
        self._store = None  # xarray's store around it
        self._fields: WindowedFields | None = None  # the fields' last record, on the grid

    def __enter__(self) -> SnapshotStream:
        return self

    def __exit__(self, *exc) -> bool:
        if not self.finished:
            self.abort()
        return False

    def record(self, state, moving: float, terrain) -> None:
        """One output time: its time and series kept, its fields appended to the file."""
        if self.finished:
            raise RuntimeError(f"{self.path}: the stream is finished")
        wet = wet_cells(state.h)  # where the flow is: the centre of mass and the fields
        self.record_series(state, moving, terrain, wet)
        try:
            if self._nc is None:
                self._start(state, terrain)
            else:
                self._append(state, wet)
        except BaseException as err:
            self._fail(err)

    def _start(self, state, terrain) -> None:
        """The temporary file, its dimensions and the fields' variables (time unlimited),
        then the first snapshot. The file stays open until :meth:`finish`: every variable
        is made in one session, so the attributes keep their order."""
        import netCDF4
        from xarray.backends import NetCDF4DataStore

        self._tmp, self._created = make_temporary(self.path)
        first = Snapshots(time=[state.t], h=[state.h], hu=[state.hu], hv=[state.hv],
                          flag=[cell_flags(state)])
        ds = to_dataset(SimpleNamespace(terrain=terrain, snapshots=first), part="fields")
        ds = ds.drop_vars(list(ds.coords))  # written at the end, in to_dataset's order
        encoding = encoding_for(ds)  # NaN fill: the first snapshot has the DEM's holes
        for name in TIME_FIELDS:  # flow_state (int8, no encoding): one chunk per snapshot too
            if name in ds:
                encoding.setdefault(name, {}).setdefault("chunksizes",
                                                         (1, *ds[name].shape[1:]))
        with _NETCDF_LOCK:
            self._nc = netCDF4.Dataset(self._tmp, "w", format="NETCDF4")
            for var in ds.variables.values():  # in the order write_netcdf makes them
                for dim, size in var.sizes.items():
                    if dim not in self._nc.dimensions:
                        self._nc.createDimension(dim, None if dim == "time" else size)
        self._store = NetCDF4DataStore(self._nc)  # takes the lock itself
        ds.isel(time=slice(0, 0)).dump_to_store(self._store, encoding=encoding,
                                                unlimited_dims=["time"])
        names = [name for name in TIME_FIELDS if name in ds]
        with _NETCDF_LOCK:
            for name in names:
                # HDF5 keeps every chunk written in its cache, up to 64 MiB a variable, and
                # compresses them all on closing: a cache of one record writes each record
                # when the next comes (memory: one snapshot; the same file)
                var = self._nc.variables[name]
                var.set_var_chunk_cache(size=int(np.prod(var.chunking())) * var.dtype.itemsize,
                                        nelems=7, preemption=1.0)
        self._fields = WindowedFields(terrain, state.h, {n: ds[n].values[0] for n in names},
                                      {n: self._nc.variables[n].dtype for n in names})
        self._write(self._fields.values)

    def _append(self, state, wet) -> None:
        # the fields again only in the window where the flow is or was (the rest is dry)
        self._write(self._fields.update(state.h, state.hu, state.hv, wet))

    def _write(self, fields: dict) -> None:
        """One record of every field on (time, space)."""
        for name, values in fields.items():
            values = np.asarray(values)
            with _NETCDF_LOCK:
                var = self._nc.variables[name]
                var.set_auto_maskandscale(False)  # the values as given, NaN included
                var[self.records] = np.asarray(values, dtype=var.dtype)  # as xarray casts
        self.records += 1

    def finish(self, result: RunResult) -> xr.Dataset:
        """Write the rest of the run and rename the file over the output.

        Returns the Dataset of the run without its fields on (time, space) (``part="rest"``,
        in memory: the summaries, the maps, the attributes).
        """
        if self._nc is None:
            raise RuntimeError(f"{self.path}: no snapshot was recorded")
        try:
            rest = to_dataset(result, part="rest")
            if rest.sizes.get("time") != self.records:
                raise RuntimeError(f"{self.path}: {self.records} snapshots written, "
                                   f"{rest.sizes.get('time')} times")
            rest.dump_to_store(self._store, encoding=encoding_for(rest))
            with _NETCDF_LOCK:
                self._nc.close()
            self._nc = self._store = self._fields = None
            publish(self._tmp, self.path)
        except BaseException as err:
            self._fail(err)
        self.finished = True
        return rest

    def abort(self) -> None:
        """Close and remove the temporary file and the folders made for it (if empty)."""
        if self._nc is not None:
            try:
                with _NETCDF_LOCK:
                    self._nc.close()
            except Exception:  # noqa: BLE001 - removed anyway
                pass
            self._nc = self._store = self._fields = None
        if self._tmp is not None:
            self._tmp.unlink(missing_ok=True)
            self._tmp = None
        for folder in reversed(self._created):
            try:
                folder.rmdir()
            except OSError:  # not empty (someone else's files), or gone
                break
        self._created = []

    def _fail(self, err: BaseException):
        """Remove the temporary; raise a write error as one line, anything else as it is."""
        self.abort()
        error = write_error(self.path, err)
        if error is not None:
            raise error from err
        raise err
