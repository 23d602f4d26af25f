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

Cost follows the flow: only the window of cells where the flow is or was at the previous
output time is computed again (:class:`~avflow.output.dataset.WindowedFields`; the centre of
mass likewise, :func:`~avflow.simulation.runner.center_of_mass`), and a record of a map
field on (time, y, x) writes only its tiles (the chunks, 128 x 128 cells) that hold a wet
cell (:class:`_Tiles`): a tile never written reads as the variable's fill value, which is
0, a dry cell, on a map without holes (HDF5's fill value, with no CF ``_FillValue``), and
NaN on a DEM with NODATA holes (there the tiles that hold a DEM cell are written every
time, those all in the holes never). What still grows with the map is one pass over h to
find the flow and flow_state, one deflated chunk a record (1 byte a cell).

Memory: the state, the terrain and one snapshot, whatever the number of snapshots (the
times and series, a few numbers per snapshot, are kept for the end); HDF5's chunk cache
holds one chunk per field (its default, up to 64 MiB a variable, kept every record of a
run until the file was closed and compressed them all then).

The file equals ``write_netcdf(to_dataset(result), path)`` variable by variable (names,
order, dimensions, dtypes, values, attributes, compression, ``_FillValue``, the CF time
units, the global attributes; ``tests/test_streamed_output.py``). Only the storage differs:
``time`` is unlimited, so the variables on ``time`` alone are chunked rather than
contiguous, and HDF5 keeps only the tiles written. The float fields take NaN as
``_FillValue`` when the first snapshot has a NaN, as
:func:`~avflow.output.netcdf.encoding_for` does looking at every snapshot: NaN there is the
cells outside a DEM, the same in every snapshot (a non-finite state fails the run).
"""

from __future__ import annotations

import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import xarray as xr

from avflow.errors import RunFailed
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
        self._tiles: dict[str, _Tiles] = {}  # the tiled fields and what each record writes

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
                self._start(state, terrain, wet)
            else:
                self._append(state, wet)
        except BaseException as err:
            self._fail(err)

    def _start(self, state, terrain, wet) -> None:
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
        for name in TIME_FIELDS:  # one chunk per snapshot where encoding_for sets none
            if name in ds:
                encoding.setdefault(name, {}).setdefault("chunksizes",
                                                         (1, *ds[name].shape[1:]))
        tiled = [name for name in TIME_FIELDS if name in ds and ds[name].ndim == 3
                 and encoding[name]["chunksizes"][1:] != ds[name].shape[1:]]
        # HDF5 gives a chunk never written the variable's fill value. With no CF fill (no
        # hole in the map), make it 0, the value of a dry cell, then drop the attribute
        # that setting it made (HDF5 keeps the value in the dataset's creation properties)
        zero_fill = [name for name in tiled if encoding[name].get("_FillValue") is None]
        for name in zero_fill:
            encoding[name]["_FillValue"] = _dry_fill(encoding[name]["dtype"])
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
            self._nc.sync()  # the HDF5 datasets made, their fill value with them
            for name in zero_fill:
                if "_FillValue" in self._nc.variables[name].ncattrs():
                    self._nc.variables[name].delncattr("_FillValue")
            for name in names:
                # HDF5 keeps every chunk written in its cache, up to 64 MiB a variable, and
                # compresses them all on closing: a cache of one chunk writes each chunk
                # when the next comes (memory: one tile, or one snapshot; the same file)
                var = self._nc.variables[name]
                var.set_var_chunk_cache(size=int(np.prod(var.chunking())) * var.dtype.itemsize,
                                        nelems=7, preemption=1.0)
        self._fields = WindowedFields(terrain, state.h, {n: ds[n].values[0] for n in names},
                                      {n: self._nc.variables[n].dtype for n in names})
        self._tiles = {name: _Tiles(ds[name].values[0], encoding[name]["chunksizes"][1:],
                                    0.0 if name in zero_fill else np.nan, terrain.cell_index)
                       for name in tiled}
        self._write(self._fields.values, wet)
        for name in zero_fill:  # the dry tiles left unwritten read as 0: check it once
            self._check_fill(name, wet)

    def _append(self, state, wet) -> None:
        # the fields again only in the window where the flow is or was (the rest is dry)
        self._write(self._fields.update(state.h, state.hu, state.hv, wet), wet)

    def _write(self, fields: dict, wet: np.ndarray) -> None:
        """One record of every field on (time, space); of a tiled field only the blocks of
        tiles that hold a ``wet`` cell (:func:`wet_cells`) or differ from the fill
        (:class:`_Tiles`)."""
        for name, values in fields.items():
            values = np.asarray(values)
            if values.dtype.kind == "f" and np.isinf(values).any():
                raise RunFailed(f"{self.path}: {name} is infinite in {int(np.isinf(values).sum())}"
                                " cells at a snapshot (parameters beyond the float range?); "
                                "no file written")
            tiles = self._tiles.get(name)
            with _NETCDF_LOCK:
                var = self._nc.variables[name]
                var.set_auto_maskandscale(False)  # the values as given, NaN included
                values = np.asarray(values, dtype=var.dtype)  # as xarray casts
                if tiles is None:
                    var[self.records] = values
                    continue
                for rows, cols in tiles.blocks(wet):
                    var[self.records, rows, cols] = values[rows, cols]
        self.records += 1

    def _check_fill(self, name, wet) -> None:
        """Read back one cell of the first record that no block wrote: 0 as a dry cell
        holds, else (a netCDF library that does not keep HDF5's fill value) every tile is
        written from now on, the first record again."""
        tiles = self._tiles[name]
        skipped = tiles.skipped(wet)
        if skipped is None:
            return
        with _NETCDF_LOCK:
            var = self._nc.variables[name]
            if var[0, skipped[0], skipped[1]] == 0:
                return
            del self._tiles[name]
            var[0] = np.asarray(self._fields.values[name], dtype=var.dtype)

    def finish(self, result: RunResult) -> xr.Dataset:
        """Write the rest of the run and rename the file over the output.

        Returns the Dataset of the run without its fields on (time, space) (``part="rest"``,
        in memory: the summaries, the maps, the attributes).
        """
        if self._nc is None:
            raise RuntimeError(f"{self.path}: no snapshot was recorded")
        try:
            rest = to_dataset(result, part="rest")
            refuse_infinite(rest, self.path)
            if rest.sizes.get("time") != self.records:
                raise RuntimeError(f"{self.path}: {self.records} snapshots written, "
                                   f"{rest.sizes.get('time')} times")
            rest.dump_to_store(self._store, encoding=encoding_for(rest))
            with _NETCDF_LOCK:
                self._nc.close()
            self._nc = self._store = self._fields = None
            from avflow.output.points import append_group, points_dataset

            points = points_dataset(result)  # the points of interest: a group of the file
            if points is not None:
                append_group(points, self._tmp)
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


def refuse_infinite(ds: xr.Dataset, path) -> None:
    """:class:`~avflow.errors.RunFailed` when a variable of ``ds`` holds an infinite value:
    never a result (NaN is a cell outside the mesh, a time never reached, a runout of no
    cell). Checked before the rename, so the file is never published."""
    for name, var in ds.variables.items():
        values = var.values
        if values.dtype.kind == "f" and np.isinf(values).any():
            raise RunFailed(f"{path}: {name} is infinite in {int(np.isinf(values).sum())} "
                            "values (parameters beyond the float range?); no file written")


def _dry_fill(dtype):
    """The fill value given to HDF5 for a tiled field on a map without holes: 0, a dry
    cell's value (a function, so that a test can take it away and see the fallback of
    :meth:`SnapshotStream._check_fill` at work)."""
    return np.zeros((), dtype=dtype)


class _Tiles:
    """Which tiles of a map field on (time, y, x) a record writes (the chunks,
    :func:`~avflow.output.netcdf.field_chunks`). HDF5 stores only the chunks written; one
    never written reads as the variable's fill value, ``fill``: NaN (the CF fill where the
    map has NODATA holes), or 0 (no hole: the HDF5 fill is made 0, the CF attribute
    dropped). A record writes the tiles that hold a wet cell, and the tiles whose dry
    values are not the fill: on a map with holes those that hold a DEM cell. So a record
    costs the flow's tiles, plus the DEM's where it has holes, not the map's.

    ``first``: the field's first record (its NaN are the holes); ``tile``: the chunk's
    (rows, columns); ``cell_index``: each cell's place on the map (None: the cells are
    the places)."""

    def __init__(self, first: np.ndarray, tile: tuple, fill: float, cell_index=None):
        self.shape = first.shape
        self.tile = tile
        self.cell_index = cell_index
        ty, tx = tile
        bands, cols = -(-self.shape[0] // ty), -(-self.shape[1] // tx)
        pad = np.zeros((bands * ty, cols * tx), dtype=bool)
        # dry values that differ from the fill: 0 where fill is NaN, NaN where fill is 0
        pad[:self.shape[0], :self.shape[1]] = ~np.isnan(first) if np.isnan(fill) \
            else np.isnan(first)
        #: (bands, columns of tiles): a tile written by every record
        self.static = pad.reshape(bands, ty, cols, tx).any(axis=(1, 3))

    def _needed(self, wet) -> np.ndarray:
        need = self.static.copy()
        if wet.size:
            places = wet if self.cell_index is None else self.cell_index[wet]
            rows, cols = np.divmod(places, self.shape[1])
            need[rows // self.tile[0], cols // self.tile[1]] = True
        if not need.any():  # every record writes something: it makes the record exist
            need[0, 0] = True
        return need

    def blocks(self, wet) -> list[tuple[slice, slice]]:
        """(rows, columns) of the map to write for a record whose ``wet`` cells are these
        (:func:`~avflow.simulation.runner.wet_cells`): per band of tiles each run of
        consecutive tiles needed, the same run in consecutive bands as one block. Each
        block covers whole chunks, so HDF5 never reads one back."""
        return self._cut(self._needed(wet))

    def _cut(self, need) -> list[tuple[slice, slice]]:
        ty, tx = self.tile
        ny, nx = self.shape
        edges = np.diff(need.astype(np.int8), axis=1, prepend=0, append=0)
        open_runs: dict[tuple[int, int], int] = {}  # run of tiles -> its first band
        blocks = []

        def close(run, first, end):
            blocks.append((slice(first * ty, min(end * ty, ny)),
                           slice(run[0] * tx, min(run[1] * tx, nx))))

        for band in range(need.shape[0]):
            runs = set(zip(np.flatnonzero(edges[band] == 1).tolist(),
                           np.flatnonzero(edges[band] == -1).tolist()))
            for run in [r for r in open_runs if r not in runs]:
                close(run, open_runs.pop(run), band)
            for run in runs:
                open_runs.setdefault(run, band)
        for run, first in open_runs.items():
            close(run, first, need.shape[0])
        return blocks

    def skipped(self, wet) -> tuple[int, int] | None:
        """(row, column) of a cell that a record with these ``wet`` cells does not write,
        or None."""
        written = np.zeros(self.shape, dtype=bool)
        for rows, cols in self._cut(self._needed(wet)):
            written[rows, cols] = True
        left = np.argwhere(~written)
        return None if not left.size else (int(left[0, 0]), int(left[0, 1]))
