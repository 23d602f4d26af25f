"""What a run will need, checked before anything large is allocated.

:func:`check_resources` counts the cells a scenario's mesh will have (from the extent and
``grid.dx``; a DEM's extent from the DEM at its own spacing, before any resampling) and the
snapshots it stores, estimates the bytes, and refuses a run that would not fit the memory
limit with a :class:`~avflow.errors.ScenarioError` naming the field (``grid.dx`` or
``output.every``), the estimate and the limit, instead of growing until the system kills it.

The limit is ``--max-memory`` (``avflow run``), else the environment variable
``AVFLOW_MAX_MEMORY``, else half of the machine's physical memory. Sizes are written as
bytes or with a binary suffix: ``512M``, ``8G``, ``1.5GiB``; ``none`` switches the check off.

The bytes per cell were measured (peak resident memory, ``workflows``-sized runs on planes,
profiles and triangle meshes, through the NetCDF write) and rounded up: about 560-750 B per
grid cell, 1800 per profile cell, 2100 per triangle-mesh vertex while the mesh is built, and
60-70 B per cell and snapshot (``h``, ``hu``, ``hv``, flags, then the Dataset's copies).

A run that writes a file (``avflow run``, ensemble members) streams its snapshots to it as
they are taken (:mod:`avflow.output.stream`): one snapshot is in memory at a time, whatever
their number (``streamed=True``); :func:`avflow.run`, which returns them all as a Dataset,
holds every one. The file's size on disk grows with the snapshots: :attr:`Estimate.file_bytes`
bounds it (uncompressed; zlib shrinks the dry cells to almost nothing).
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from dataclasses import dataclass

from avflow.errors import AvflowError, ScenarioError

ENV_MAX_MEMORY = "AVFLOW_MAX_MEMORY"

#: Bytes per cell for the mesh, the terrain, the solver and the state, by mesh kind.
BYTES_PER_CELL = {"profile": 2000, "grid": 1000, "triangles": 2500}
#: Bytes per cell added by parameters per cell (friction maps, forest): a row of 8 float64
#: per cell, its copy on the square-grid kernel's layout, the sampled values (counted from
#: the arrays, not measured)
BYTES_PER_CELL_MAPS = 160
#: Bytes per cell added by entrainment: the layer at the start, in the state, on the
#: square-grid kernel's layout, the layer and bed-change maps of the output (counted)
BYTES_PER_CELL_ENTRAINMENT = 48
#: Bytes per cell and stored snapshot (the snapshot lists, then the output Dataset).
BYTES_PER_CELL_SNAPSHOT = 80
#: Bytes per cell and snapshot in the file before compression: h, u, v as float32, flow_state.
FILE_BYTES_PER_CELL_SNAPSHOT = 13

_UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40, "P": 2**50}


def parse_bytes(text: str | int | float) -> int | None:
    """``"8G"`` -> 8 GiB in bytes; plain numbers are bytes; ``"none"`` -> None (no limit)."""
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        value, unit = float(text), ""
    else:
        word = str(text).strip()
        if word.lower() in ("none", "off", "unlimited"):
            return None
        m = re.fullmatch(r"([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([kKmMgGtTpP]?)(?:i?[bB])?",
                         word)
        if not m:
            raise AvflowError(f"memory size {text!r}: expected bytes or a number with K, M, "
                              "G or T (binary units, e.g. 8G, 512M), or 'none'")
        value, unit = float(m.group(1)), m.group(2).upper()
    size = value * _UNITS[unit]
    if not (math.isfinite(size) and size > 0):
        raise AvflowError(f"memory size {text!r}: must be a positive size")
    return int(size)


def physical_memory() -> int | None:
    """Bytes of physical memory of this machine (None when the system does not say)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        pass
    try:
        import psutil  # a dependency of dask.distributed; Windows has no sysconf

        return int(psutil.virtual_memory().total)
    except Exception:  # noqa: BLE001
        return None


def default_max_memory() -> tuple[int | None, str]:
    """The limit when none is given, and where it comes from (for messages)."""
    env = os.environ.get(ENV_MAX_MEMORY)
    if env:
        try:
            return parse_bytes(env), f"{ENV_MAX_MEMORY}={env}"
        except AvflowError as err:
            raise AvflowError(f"{ENV_MAX_MEMORY}: {err}") from None
    total = physical_memory()
    if total is None:
        return None, "no limit: the machine's memory is unknown"
    return total // 2, f"half of this machine's {human(total)}"


def human(n: float) -> str:
    """Bytes in binary units: ``12.3 GiB``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            if unit == "B":
                return f"{n:.0f} {unit}"
            return f"{n:.1f} {unit}" if abs(n) < 1e6 else f"{n:.2g} {unit}"
        n /= 1024
    return f"{n:.1f} EiB"


#: Cells along one axis counted at most (1e15: a 1000 km map at 1 nm cells). Beyond, the
#: count is this, which is refused by any memory limit, instead of an OverflowError.
MAX_AXIS_CELLS = 10**15


def _cells_along(span: float, d: float, floor: bool = False) -> int:
    n = span / d
    if not math.isfinite(n) or n > MAX_AXIS_CELLS:
        return MAX_AXIS_CELLS
    return int(math.floor(n + 1e-9)) + 1 if floor else max(int(round(n)), 1)


@dataclass(frozen=True)
class Estimate:
    """Cells, snapshots and bytes a scenario's run will hold (before the run)."""

    kind: str  #: "profile", "grid" or "triangles"
    shape: tuple  #: cells along x (and y); nodes for triangles
    cells: int
    snapshots: int
    mesh_bytes: float
    snapshot_bytes: float  #: those held in memory: all of them, or one when streamed
    what: str  #: the mesh in words, for messages
    streamed: bool = False  #: snapshots written to the file as they are taken
    max_cells: float | None = None  #: the most cells (nodes) the limit allows: refinement's

    @property
    def bytes(self) -> float:
        return self.mesh_bytes + self.snapshot_bytes

    @property
    def file_bytes(self) -> float:
        """Upper bound of the output file's size: every snapshot's fields, uncompressed."""
        return float(self.cells) * self.snapshots * FILE_BYTES_PER_CELL_SNAPSHOT


def snapshot_count(scenario) -> int:
    """Snapshots a run stores at most: t = 0, every ``output.every``, and ``time.end``."""
    end, every = scenario.time.end, scenario.output.every
    return int(math.ceil(end / every - 1e-9)) + 1


def estimate(scenario, streamed: bool = False) -> Estimate:
    """Cells and bytes of a validated scenario's run, from its extent and grid.dx only.

    A DEM is read at its own spacing (cached; nothing is resampled) for its extent. Triangle
    meshes count the grid's nodes before refinement (refinement adds where the bed bends).
    ``streamed``: the snapshots go to a file as they are taken, one is in memory at a time.
    """
    t, g = scenario.terrain, scenario.grid
    dx = g.dx
    dy = g.dy if getattr(g, "dy", None) is not None else dx
    if t.kind == "profile":
        n = _cells_along(t.length, dx)
        kind, shape, what = "profile", (n,), f"{t.length:g} m at dx = {dx:g} m"
    else:
        if t.kind == "dem":
            from avflow.terrain.raster import NATIVE_TOLERANCE, RasterError, read_raster

            try:
                raster = read_raster(t.path, "DEM")
            except RasterError as err:
                raise ScenarioError.at(scenario, "terrain.path", str(err)) from None
            span_x, span_y = raster.x[-1] - raster.x[0], raster.y[-1] - raster.y[0]
            if (abs(raster.dx - dx) <= NATIVE_TOLERANCE * dx
                    and abs(raster.dy - dy) <= NATIVE_TOLERANCE * dy):
                nx, ny = raster.x.size, raster.y.size
            else:  # as avflow.terrain.raster.resample will
                nx, ny = _cells_along(span_x, dx, True), _cells_along(span_y, dy, True)
            what = f"the DEM's {span_x:g} x {span_y:g} m"
        else:
            (x0, x1), (y0, y1) = t.extent.x, t.extent.y
            nx, ny = _cells_along(x1 - x0, dx), _cells_along(y1 - y0, dy)
            what = f"{x1 - x0:g} x {y1 - y0:g} m"
        what += f" at dx = {dx:g} m" + (f", dy = {dy:g} m" if dy != dx else "")
        if getattr(g, "mesh", "square") == "triangles":
            kind, shape = "triangles", (nx + 1, ny + 1)
            n = (nx + 1) * (ny + 1) * (2 if getattr(g, "pattern", "") == "criss-cross" else 1)
        else:
            kind, shape, n = "grid", (nx, ny), nx * ny
    snaps = snapshot_count(scenario)
    held = 1 if streamed else snaps
    per_cell = BYTES_PER_CELL[kind] + _extra_per_cell(scenario)
    return Estimate(kind, shape, n, snaps, float(n) * per_cell,
                    float(n) * held * BYTES_PER_CELL_SNAPSHOT, what, streamed)


def _extra_per_cell(scenario) -> int:
    """Bytes per cell of friction maps, forest and entrainment (0 without them)."""
    from avflow.scenario.schema import map_fields

    maps = bool(map_fields(scenario.rheology)) or getattr(scenario, "forest", None) is not None
    return ((BYTES_PER_CELL_MAPS if maps else 0)
            + (BYTES_PER_CELL_ENTRAINMENT if getattr(scenario, "entrainment", None) else 0))


def check_resources(scenario, max_memory: int | str | None = None, *,
                    streamed: bool = False) -> Estimate:
    """The estimate of a scenario's run; a :class:`ScenarioError` when it exceeds the limit.

    ``max_memory``: bytes, or a size such as ``"8G"``; None: the default
    (:func:`default_max_memory`). ``streamed``: the run writes its snapshots to a file as
    they are taken (``avflow run``, ensemble members), one in memory at a time.
    """
    if max_memory is None:
        limit, source = default_max_memory()
    else:
        try:
            limit, source = parse_bytes(max_memory), "--max-memory"
        except AvflowError as err:
            raise AvflowError(f"--max-memory: {err}") from None
    est = estimate(scenario, streamed)
    if limit is not None:  # the bound a mesh that grows as it is built (refinement) must keep
        per_cell = est.bytes / max(est.cells, 1)
        est = dataclasses.replace(est, max_cells=limit / per_cell)
    if limit is None or est.bytes <= limit:
        return est
    unit = "nodes" if est.kind == "triangles" else "cells"
    count = f"{est.cells:.3g} {unit}"
    if len(est.shape) > 1:
        count = " x ".join(str(n) if n < 1e6 else f"{n:.3g}" for n in est.shape) + " = " + count
    held = "one snapshot, the others streamed to the file" if est.streamed else "snapshots"
    need = (f"{est.what} makes {count}; with {est.snapshots} "
            f"snapshots a run needs about {human(est.bytes)} ({human(est.mesh_bytes)} mesh "
            f"and state, {human(est.snapshot_bytes)} {held}), more than the memory limit "
            f"of {human(limit)} ({source})")
    if est.mesh_bytes > limit or est.streamed:  # the cells are too small (fewer snapshots
        field, fix = "grid.dx", "use a larger grid.dx"  # would not help a streamed run)
    else:  # the mesh fits, its snapshots do not
        field = "output.every"
        fix = "store fewer snapshots (a larger output.every) or use a larger grid.dx"
    # calibrate and region have no --max-memory: the variable is what applies everywhere
    raise_it = ("raise --max-memory" if source == "--max-memory" else
                f"raise the limit with ${ENV_MAX_MEMORY}")
    raise ScenarioError.at(scenario, field, f"{need}: {fix}, or {raise_it}")


def release_freed_memory() -> None:
    """Give the memory Python and numpy freed back to the system (glibc's ``malloc_trim``).

    Building a DEM's mesh frees about as much as it keeps: glibc raises its threshold for
    returning large blocks after the first ones are freed, so the freed temporaries stayed
    in the resident set (a 1 m avaKot mesh: 1.70 GiB resident, 1.17 GiB after the trim).
    Nothing happens where there is no glibc.
    """
    global _LIBC
    if _LIBC is None:
        try:
            import ctypes

            _LIBC = ctypes.CDLL("libc.so.6")
            _LIBC.malloc_trim.argtypes = [ctypes.c_size_t]
        except (OSError, AttributeError):
            _LIBC = False
    if _LIBC:
        _LIBC.malloc_trim(0)


_LIBC = None
