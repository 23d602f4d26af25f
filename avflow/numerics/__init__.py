"""Stage 3, the numerics: pure arrays and scalars, nothing of YAML, xarray or dask.

- :mod:`avflow.numerics.kinetic`, :mod:`avflow.numerics.physics`: the pointwise physics,
  plain functions of scalars (half fluxes eqs. 28-41; threshold, projection, Dirac faces
  eqs. 47-56; curvature eqs. 61-62), compiled for the CPU by :mod:`avflow.numerics.cpu`;
- :mod:`avflow.numerics.rheology`: friction laws behind one signature (eqs. 15, 42-50);
- :mod:`avflow.numerics.kernels`, :mod:`~avflow.numerics.profile`,
  :mod:`~avflow.numerics.face_sweep`, :mod:`~avflow.numerics.face_gather`,
  :mod:`~avflow.numerics.square_grid`, :mod:`~avflow.numerics.reconstruction`: the
  traversals of one step (profiles, face lists, square-grid rows; order 2's reconstruction);
- :mod:`avflow.numerics.stepping`, :mod:`avflow.numerics.timeloop`: the time loops' shared
  rules (step size, stop rules, statistics) and the loop of profiles and faces;
- :mod:`avflow.numerics.cuda_grid`: the square-grid kernel on a CUDA GPU (the same
  pointwise physics compiled by numba-cuda; ``numerics.backend: cuda``);
- :mod:`avflow.numerics.registry`: which kernel runs which scene, on which backend;
- :mod:`avflow.numerics.solver`: :class:`~avflow.numerics.solver.Solver` and its state;
- :mod:`avflow.numerics.analytic`: exact dam-break solutions to test against.

Numba's cache of compiled kernels (``cache=True``) keys a function by its own byte code and
checks only the file that defines it, not the functions it calls from other files nor the
globals they read: after a change to ``kinetic.py`` alone, the time loops of ``kernels.py``
came back from the cache with the old half fluxes; a user's ``@njit`` helper reading a
changed constant came back with the old one. So every kernel of this package, and every copy
with a user's functions built in, is keyed by what it is compiled from
(:func:`avflow.codekey.code_key`: its code and the code and values of everything it reads,
through its callees), added to Numba's own key (:func:`_key_by_code`): a changed function
anywhere below a kernel, a changed constant, is a new key, compiled afresh. The cache lies
in one folder per user, avflow version, Numba, Python and processor
(:func:`kernel_cache_dir`: ``$AVFLOW_CACHE_DIR``, else ``$XDG_CACHE_HOME/avflow`` or
``~/.cache/avflow``), and a function's files inside it are named after its place in the
package, not on disk (:func:`_shared_locator`): every clone and virtual environment of one
version shares what the first one compiled. ``NUMBA_CACHE_DIR``, where set, is used as Numba
uses it.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parents[1]

#: Folders of other versions unused this long are removed (another clone may still use one)
_STALE_DAYS = 30


def cache_root() -> Path:
    """Where avflow keeps compiled kernels for this user: ``$AVFLOW_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/avflow``, else ``~/.cache/avflow``."""
    chosen = os.environ.get("AVFLOW_CACHE_DIR")
    if chosen:
        return Path(chosen).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "avflow"


def kernel_cache_dir() -> Path:
    """``<cache_root>/kernels-<digest>``: the digest of avflow's, Numba's and Python's
    versions and of the processor's architecture (what the kernels are compiled from is in
    each one's key: :func:`_key_by_code`)."""
    import platform
    import sys

    from numba import __version__ as numba_version

    from avflow import __version__

    digest = hashlib.sha256(
        f"{__version__} {numba_version} {sys.version} {platform.machine()}".encode())
    return cache_root() / f"kernels-{digest.hexdigest()[:16]}"


def _prune(current: Path) -> None:
    """Remove the folders of other versions (``kernels-<digest>`` beside ``current``) unused
    for :data:`_STALE_DAYS` days, and the ones older versions kept inside the package. Best
    effort: a folder that cannot be removed stays."""
    import shutil
    import time

    now = time.time()
    try:
        os.utime(current)  # in use: not stale for the other clones' pruning
    except OSError:
        pass
    for folder in current.parent.glob("kernels-*"):
        try:
            stale = now - folder.stat().st_mtime > _STALE_DAYS * 86400
        except OSError:
            continue
        if folder.name != current.name and folder.is_dir() and stale:
            shutil.rmtree(folder, ignore_errors=True)
    for folder in (Path(__file__).resolve().parent / "__pycache__").glob("kernels-*"):
        shutil.rmtree(folder, ignore_errors=True)


def _shared_locator(folder: Path):
    """A Numba cache locator that puts the compiled files of this package's functions in
    ``folder``, under their module's folder *in the package* (``numerics/``), wherever the
    checkout lies; Numba's own locators name the folder after the path on disk, so each
    clone compiled everything again. Numba checks each file's content hash, as before."""
    from numba.core import caching, config

    class SharedLocator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
        def __init__(self, py_func, py_file):
            self._py_file = py_file
            self._lineno = py_func.__code__.co_firstlineno
            inside = Path(py_file).resolve().parent.relative_to(_PACKAGE)
            self._cache_path = str(folder / inside)

        def get_cache_path(self):
            return self._cache_path

        def get_source_stamp(self):
            # the key holds what the function is compiled from (_key_by_code), so the
            # file's date and size need not match: clones and edits share one index
            return "avflow keyed by code"

        @classmethod
        def from_function(cls, py_func, py_file):
            if config.CACHE_DIR:  # NUMBA_CACHE_DIR: the user's choice stands
                return None
            try:
                Path(py_file).resolve().relative_to(_PACKAGE)
            except (ValueError, OSError):  # another package's function: Numba's locators
                return None
            # None where the folder cannot be written: Numba's own locators then
            return super().from_function(py_func, py_file)

    return SharedLocator


def _key_by_code() -> None:
    """Numba's key of a cached function (its signature, the processor, its own byte code)
    with :func:`avflow.codekey.code_key` added for the functions cached in avflow's
    folder (:func:`_shared_locator`): what they are compiled from, through their callees,
    and the function's own options (its dispatcher's: without them a kernel whose decorator
    changed, ``_nrt`` or ``fastmath``, loaded the machine code of the old options)."""
    import weakref

    from numba.core import caching
    from numba.core.dispatcher import Dispatcher

    if getattr(caching.Cache._index_key, "avflow", False):
        return
    numba_key = caching.Cache._index_key
    numba_enable = Dispatcher.enable_caching

    def enable_caching(self):
        numba_enable(self)
        self._cache._avflow_owner = weakref.ref(self)  # (its options are read when keyed)

    def index_key(self, sig, codegen):
        key = numba_key(self, sig, codegen)
        if type(self._impl.locator).__name__ != "SharedLocator":
            return key
        from avflow.codekey import code_key

        owner = getattr(self, "_avflow_owner", lambda: None)()
        return (*key, code_key(self._py_func if owner is None else owner))

    index_key.avflow = True
    caching.Cache._index_key = index_key
    Dispatcher.enable_caching = enable_caching


def _install_cache() -> None:
    """Put :func:`_shared_locator` first among Numba's cache locators. Where a dispatcher
    caches is fixed when it is decorated, and every kernel module lies in this package, so
    this runs before any of them is imported; nothing else is imported here (a command
    loads the kernels it runs, when it runs them)."""
    from numba.core import caching

    try:
        folder = kernel_cache_dir()
        folder.mkdir(parents=True, exist_ok=True)
        _prune(folder)
    except OSError:  # sources unreadable or no writable cache: Numba's own locations
        folder = None
    locators = caching.CacheImpl._locator_classes
    if folder is not None and not any(c.__name__ == "SharedLocator" for c in locators):
        locators.insert(0, _shared_locator(folder))
        _key_by_code()


_install_cache()


def _collect_less_while_compiling() -> None:
    """Python's garbage collector runs less often during compilations
    (:mod:`avflow.numerics.compiling`)."""
    from avflow.numerics.compiling import fewer_collections_while_compiling

    fewer_collections_while_compiling()


_collect_less_while_compiling()
