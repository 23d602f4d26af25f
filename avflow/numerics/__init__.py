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

Numba's cache of compiled kernels (``cache=True``) checks only the file that defines a
function, not the functions it inlines from other files: after a change to ``kinetic.py``
alone, the time loops of ``kernels.py`` came back from the cache with the old half fluxes.
So the cache goes to a folder named after a digest of every file the kernels are compiled
from (:func:`kernel_cache_dir`), unless ``NUMBA_CACHE_DIR`` is set: a changed file, a new
version, is a new folder, compiled afresh, and the folders of other versions are removed.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

#: What the kernels are compiled from: these modules, and the constants Numba freezes into
#: them from the terrain (boundary and face codes).
_KERNEL_SOURCES = ("numerics/kinetic.py", "numerics/physics.py", "numerics/cpu.py",
                   "numerics/stepping.py", "numerics/loop.py", "numerics/timeloop.py",
                   "numerics/rheology.py", "numerics/kernels.py",
                   "numerics/reconstruction.py", "numerics/square_grid.py", "numerics/vectorize.py",
                   "numerics/profile.py", "numerics/face_sweep.py", "numerics/face_gather.py",
                   "numerics/sources.py",
                   "terrain/mesh.py", "terrain/squaregrid.py")


def kernel_cache_dir() -> Path:
    """``avflow/numerics/__pycache__/kernels-<digest>``: the digest of the kernels' sources."""
    package = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for name in _KERNEL_SOURCES:
        digest.update(name.encode())
        digest.update((package / name).read_bytes())
    return Path(__file__).resolve().parent / "__pycache__" / f"kernels-{digest.hexdigest()[:16]}"


def _prune(current: Path) -> None:
    """Remove the cache folders of other versions of the sources (``kernels-<digest>``
    beside ``current``): each edit or upgrade made one, some 5 MB, and none was ever read
    again. Best effort: a folder that cannot be removed stays."""
    import shutil

    for folder in current.parent.glob("kernels-*"):
        if folder.name != current.name and folder.is_dir():
            shutil.rmtree(folder, ignore_errors=True)


def _import_kernels() -> None:
    """Import the kernel modules with Numba's cache folder set to :func:`kernel_cache_dir`
    (where their dispatchers look is fixed when they are decorated), then put the setting
    back: other packages' cached functions in the same process keep their own folders."""
    from numba.core import config

    saved = config.CACHE_DIR
    if not os.environ.get("NUMBA_CACHE_DIR"):  # else the user's choice stands
        try:
            folder = kernel_cache_dir()
            config.CACHE_DIR = str(folder)
            _prune(folder)
        except OSError:  # sources unreadable (a zipped install): Numba's own locations
            pass
    try:
        from avflow.numerics import (cpu, kernels, reconstruction,  # noqa: F401
                                     rheology, square_grid, timeloop)
    finally:
        config.CACHE_DIR = saved


_import_kernels()
