"""Atomic NetCDF writes: a temporary file in the target folder, then a rename.

Fields are stored as float32 with zlib + shuffle, one chunk per snapshot; summaries and
coordinates stay float64.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import xarray as xr


def encoding_for(ds: xr.Dataset) -> dict:
    """float32 + zlib for the big fields, one chunk per snapshot; no fill on coordinates."""
    enc = {}
    for name, var in ds.variables.items():
        if name in ds.coords:
            enc[name] = {"_FillValue": None}
        elif var.dtype.kind == "f" and var.ndim >= 1 and var.dims != ("time",) and name not in (
                "time_span_bounds",):
            chunks = (1, *var.shape[1:]) if var.dims[0] == "time" else var.shape
            fill = np.float32(np.nan) if bool(np.isnan(var.values).any()) else None
            enc[name] = {"dtype": "float32", "zlib": True, "complevel": 2, "shuffle": True,
                         "chunksizes": chunks, "_FillValue": fill}
        elif var.dtype.kind == "f":
            enc[name] = {"_FillValue": None}
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


def write_netcdf(ds: xr.Dataset, path) -> Path:
    """Write ``ds`` to ``path`` atomically: a temporary file in the same folder, then rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        ds.to_netcdf(tmp, encoding=encoding_for(ds), engine="netcdf4")
        publish(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
