"""xarray without importing dask.array until a dask array can exist.

xarray asks, for every variable it makes, whether the data is a dask array, and to know the
class it imports ``dask.array`` (and scipy's FFT with it) whenever dask is installed, even
where no dask array is ever made (``avflow run``; docs/performance.md, "Start-up and files
of a run").
No dask array can exist before ``dask.array`` is imported, so until then the answer is
"not a dask array" without the import; once ``dask.array`` is imported (an ensemble, a
user's chunked file) xarray's own record of dask takes over, and every later check is
xarray's as it was.

:func:`defer_dask_array` installs that record in xarray's cache of array modules; it does
nothing where the cache is not what this expects (another xarray layout) or dask was
already looked up.
"""

from __future__ import annotations

import sys


def defer_dask_array() -> bool:
    """Make xarray's dask-array check import nothing until ``dask.array`` is imported.

    Returns whether the deferred record is in place (False: xarray's own behaviour).
    """
    try:
        from xarray.namedarray import pycompat
    except ImportError:  # pragma: no cover - another xarray layout
        return False
    cache = getattr(pycompat, "_cached_duck_array_modules", None)
    base = getattr(pycompat, "DuckArrayModule", None)
    if not isinstance(cache, dict) or base is None:  # pragma: no cover - another layout
        return False
    if "dask" not in cache:
        cache["dask"] = _deferred_class(base)()
    return isinstance(cache["dask"], _Deferred)


class _Deferred:
    """Marks the deferred record (see :func:`_deferred_class`)."""


def _deferred_class(base):
    class DeferredDask(base, _Deferred):
        """xarray's record of dask (``DuckArrayModule("dask")``) that imports dask only
        when asked for more than the array class, or once ``dask.array`` is imported."""

        def __init__(self):  # noqa: D107 - no import here, unlike the base class
            pass

        def _real(self):
            """xarray's own record, made (importing dask) and cached in place of this."""
            from xarray.namedarray import pycompat

            real = base("dask")
            pycompat._cached_duck_array_modules["dask"] = real
            return real

        @property
        def type(self):
            module = sys.modules.get("dask.array")
            if getattr(module, "Array", None) is None:  # not (fully) imported: no dask array
                return ()
            return self._real().type

        @property
        def module(self):
            return self._real().module

        @property
        def version(self):
            return self._real().version

        @property
        def available(self):
            return self._real().available

    return DeferredDask
