"""Atomic NetCDF writes: a temporary file in the target folder, then a rename.

Fields are stored as float32 with zlib + shuffle, one chunk per snapshot; summaries and
coordinates stay float64. The temporary file is ``.{name}.XXXXXXXX.tmp`` (``mkstemp``) next
to the output: a write killed by SIGKILL leaves one, and :func:`remove_stale_temporaries`
(called by ``avflow run`` with the output's lock held) removes those of that output name.
:func:`write_netcdf` writes a whole Dataset; :mod:`avflow.output.stream` writes the same
file snapshot by snapshot while the run goes on, with the same temporary and rename.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import xarray as xr

from avflow.files import (OutputError, OutputWriteError, atomic_write, check_target,
                          make_temporary, publish, remove_stale_temporaries,
                          write_error)
from avflow.output.xarray_dask import defer_dask_array

defer_dask_array()  # a run's file is made without importing dask.array

__all__ = ["OutputError", "OutputWriteError", "check_output_path", "make_temporary",
           "publish", "remove_stale_temporaries", "write_error", "write_netcdf"]


def check_output_path(path, inputs=()) -> Path:
    """Refuse, before anything runs, an output ``path`` that cannot take the result: one of
    ``inputs`` or their sidecars (:func:`avflow.files.protected`), a folder, not a regular
    file, or in a folder that cannot take it (:func:`avflow.files.check_target`)."""
    return check_target(path, inputs)


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
        elif (var.dtype.kind == "f" and var.ndim >= 1
              and var.dims not in (("time",), ("structure",))):  # volumes stay float64
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


def write_netcdf(ds: xr.Dataset, path) -> Path:
    """Write ``ds`` to ``path`` atomically: a temporary file in the same folder, then rename."""
    return atomic_write(path, lambda tmp: ds.to_netcdf(tmp, encoding=encoding_for(ds),
                                                       engine="netcdf4"))
