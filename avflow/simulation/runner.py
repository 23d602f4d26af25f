"""Run one scenario: terrain, release and law from the scenario, the solver, the snapshots.

The runner is the only place that decides output times; the time loop itself runs inside
:meth:`avflow.numerics.solver.Solver.advance` between two output times.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time as _time
import warnings
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from avflow.terrain.raster import RasterError
from avflow.errors import AvflowWarning, Problem, RunFailed, ScenarioError
from avflow.terrain.release import ReleaseError, initial_thickness, release_crs
from avflow.numerics.physics import (SOURCE_EROSION_ENERGY, SOURCE_EXPONENTIAL,
                                     SOURCE_SHEAR_THRESHOLD)
from avflow.numerics import compiling
from avflow.numerics.rheology import friction_parameters
from avflow.numerics.solver import Solver, State
from avflow.numerics.registry import SchemeUnavailable
from avflow.numerics.sources import MassSource
from avflow.numerics.stepping import MAX_RETRIES
from avflow.simulation.resources import check_resources, release_freed_memory
from avflow.simulation.summary import deposit_extent, runout_truncated, travel_angle
from avflow.terrain.bed import Terrain
from avflow.terrain.build import build_terrain
from avflow.terrain.structures import StructureError
from avflow.terrain.maps import (MapError, erodible_depth, forest_coefficient, friction_maps,
                                 source_weights)
from avflow.terrain.trimesh import MeshTooLarge

#: Default dry threshold and runout threshold, relative to the largest released thickness.
DEFAULT_THRESHOLD_FRACTION = 1e-3

#: Thickness below which a cell keeps its mass but no momentum, relative to the largest
#: released thickness: 1e-12 is 4 orders above the round-off of the flux sums (1e-16 of the
#: neighbours' thickness), so a real film keeps its speed and a residue cannot race ahead.
ZERO_THICKNESS_FRACTION = 1e-12

#: Default minimum flowing thickness (m), unless the dry threshold is smaller: GeoClaw's
#: dry tolerance. Thinner material holds its mass but does not flow (films that stop).
DEFAULT_MIN_FLOW = 1e-3

#: What ended a run that did not stop by its stop rule (summary ``ended_by``).
ENDED_BY = {"completed": "time.end, still moving", "max_steps": "time.max_steps, still moving"}

#: Statuses of a run ended by its stop rule: at rest (less than this fraction of the release
#: still moving, the moving-volume rule's default) or ended by the rule with mass still moving
#: (AvaFrame's kinetic-energy rule ends runs with a third of the volume sliding slowly).
AT_REST, ENDED_BY_RULE = "at_rest", "ended_by_rule"
REST_FRACTION = 1e-3
#: Statuses of a run that did not fail; files before avflow said "stopped" for both of the first.
SUCCESS_STATUSES = (AT_REST, ENDED_BY_RULE, "completed", "stopped")

# Cell states written to the output flag variable.
FLAG_DRY, FLAG_FLOWING, FLAG_STOPPED = 0, 1, 2


@dataclass
class Snapshots:
    """Fields stored at output times (lists of per-cell arrays, float64 / uint8).

    :func:`simulate` calls :meth:`record` at every output time. This class keeps every
    snapshot in memory (what :func:`avflow.run` returns as a Dataset); a subclass with
    ``in_memory = False`` (:class:`avflow.output.stream.SnapshotStream`) writes the fields
    to a file as they come and keeps only the times and the series.
    """

    #: False: the fields are not kept (one snapshot in memory at a time), see check_resources
    in_memory = True

    time: list = field(default_factory=list)
    h: list = field(default_factory=list)
    hu: list = field(default_factory=list)
    hv: list = field(default_factory=list)
    flag: list = field(default_factory=list)
    moving_volume: list = field(default_factory=list)
    center_of_mass: list = field(default_factory=list)  #: (x, y, z) per snapshot, m
    #: volume entrained so far per snapshot, m^3 (runs with entrainment; recorded by
    #: :func:`simulate`, from the erodible layer: :meth:`Solver.entrained_volume`)
    entrained_volume: list = field(default_factory=list)

    def record(self, state: State, moving: float, terrain: Terrain) -> None:
        self.record_series(state, moving, terrain)
        self.h.append(state.h.copy())
        self.hu.append(state.hu.copy())
        self.hv.append(state.hv.copy())
        self.flag.append(cell_flags(state))

    def record_series(self, state: State, moving: float, terrain: Terrain,
                      wet: np.ndarray | None = None) -> None:
        """The time and the scalars of one output time (every kind of snapshots keeps them);
        ``wet``: :func:`wet_cells` of ``state.h`` when the caller has them."""
        self.time.append(state.t)
        self.moving_volume.append(moving)
        self.center_of_mass.append(center_of_mass(terrain, state.h, wet))


def center_of_mass(terrain: Terrain, h: np.ndarray, wet: np.ndarray | None = None) -> tuple:
    """Volume-weighted centre (x, y, z) of the material, m (x along the bed on profiles).

    The sums run over the cells from the first to the last that hold material (elsewhere
    h is +0.0 and adds nothing) and equal numpy's sums over every cell bit for bit
    (:func:`window_sums`): the cost follows the flow, not the map; the values are unchanged.
    ``wet``: :func:`wet_cells` of ``h`` if known.
    """
    wet = wet_cells(h) if wet is None else wet
    if not wet.size:  # nothing on the map: every sum is 0
        return (np.nan, np.nan, np.nan)
    lo, hi = int(wet[0]), int(wet[-1]) + 1
    area = terrain.mesh.cell_area
    if terrain.kind == "profile":
        x, y = terrain.x, None  # y: 0 everywhere
    else:
        x, y = terrain.cell_xy()
    coords = (x, y, terrain.bed_elevation)
    # sums of products, not `w @ x`: BLAS's threaded dot took 22 ms a call on 179k cells
    # beside the kernel's threads (a third of a run's time went to snapshots' centres)
    rows = np.empty((4, hi - lo))
    w = np.multiply(h[lo:hi], area[lo:hi], out=rows[0])
    for k, c in enumerate(coords, start=1):
        np.multiply(w, 0.0 if c is None else c[lo:hi], out=rows[k])
    sums = window_sums(rows, lo, h.size)
    if sums is None or not sums.all():  # a zero sum (its sign), or a numpy that sums otherwise
        whole = h * area
        sums = [np.sum(whole)] + [np.sum(whole * (np.zeros_like(x) if c is None else c))
                                  for c in coords]
    total = sums[0]
    if total <= 0.0:
        return (np.nan, np.nan, np.nan)
    return tuple(float(s / total) for s in sums[1:])


#: numpy's pairwise summation (np.add.reduce of float64): blocks of this many values are
#: summed by 8 accumulators, longer runs are halved (the first half a multiple of 8).
_PAIRWISE_BLOCK = 128

#: Cells per block in :func:`wet_cells`' first pass.
_WET_BLOCK = 256


def wet_cells(h: np.ndarray) -> np.ndarray:
    """Ascending indices of the cells whose h is not +0.0 bit for bit (-0.0 and NaN count):
    every other cell holds nothing. One pass over h, then only the blocks of cells that
    hold some material (a flow on a large map costs about what it costs on a small one)."""
    wet = np.ascontiguousarray(h, dtype=np.float64).view(np.uint64) != 0
    n = wet.size
    k = n - n % _WET_BLOCK
    blocks = np.flatnonzero(wet[:k].reshape(-1, _WET_BLOCK).any(axis=1))
    tail = bool(wet[k:].any())
    if not blocks.size and not tail:
        return np.zeros(0, dtype=np.intp)
    start = int(blocks[0]) * _WET_BLOCK if blocks.size else k
    end = n if tail else (int(blocks[-1]) + 1) * _WET_BLOCK
    return start + np.flatnonzero(wet[start:end])


def window_sums(rows: np.ndarray, lo: int, n: int) -> np.ndarray | None:
    """``np.sum(a)`` of each of the arrays ``a`` of ``n`` values that are a row of ``rows``
    from index ``lo`` on and +-0 elsewhere, bit for bit (but the sign of a zero sum),
    summing only ``rows``; None where this numpy sums otherwise.

    numpy sums float64 pairwise, down to blocks of 128 (:data:`_PAIRWISE_BLOCK`); the same
    halving here, where a half outside the window is 0 and one inside is summed by numpy
    (a row of a 2-D reduce is summed as the 1-D array). A zero changes no sum but a zero
    one: there the sign comes from the zeros outside. Checked against ``np.sum`` once per
    process (:func:`_window_sums_work`).
    """
    if not _window_sums_work():
        return None
    return _pairwise_window(np.asarray(rows, dtype=np.float64), lo, n)


def _pairwise_window(rows, lo, n):
    return _pairwise(rows, lo, lo + rows.shape[-1], 0, n)


def _pairwise(rows, lo, hi, start, m):
    """numpy's pairwise sum of the values start .. start + m of the arrays that are ``rows``
    from ``lo`` to ``hi`` and 0 elsewhere. A module function, not a closure: a closure that
    calls itself is a reference cycle, which kept every snapshot's ``rows`` (4 lines of the
    window) alive until Python's cycle collector ran, rarely in a run: 3 MB a snapshot at
    5 m, half a GiB over a 1 m run."""
    end = start + m
    if end <= lo or start >= hi:
        return 0.0
    if lo <= start and end <= hi:
        return np.add.reduce(rows[..., start - lo:end - lo], axis=-1)
    if m <= _PAIRWISE_BLOCK:  # one of numpy's blocks: with its zeros around the window
        block = np.zeros(rows.shape[:-1] + (m,))
        a, b = max(start, lo), min(end, hi)
        block[..., a - start:b - start] = rows[..., a - lo:b - lo]
        return np.add.reduce(block, axis=-1)
    half = m // 2
    half -= half % 8
    return _pairwise(rows, lo, hi, start, half) + _pairwise(rows, lo, hi, start + half, m - half)


@functools.cache
def _window_sums_work() -> bool:
    """Whether this numpy sums as :func:`window_sums` assumes: random windows of arrays of
    a few lengths, one row and several, against ``np.sum`` of each."""
    rng = np.random.default_rng(11)
    for n, lo, hi in ((1000, 130, 771), (5003, 17, 4999), (70001, 9000, 52345),
                      (300, 0, 300), (129, 5, 6), (7, 2, 5)):
        a = np.zeros((3, n))
        a[:, lo:hi] = rng.standard_normal((3, hi - lo)) * 10.0 ** rng.uniform(-3, 3, hi - lo)
        want = [np.add.reduce(np.ascontiguousarray(row)) for row in a]
        if (list(_pairwise_window(a[:, lo:hi], lo, n)) != want
                or _pairwise_window(a[0, lo:hi], lo, n) != want[0]):
            return False
    return True


def cell_flags(state: State) -> np.ndarray:
    """0 dry, 1 flowing (above the Coulomb threshold), 2 at rest under the threshold."""
    return flags_of(state.h, state.hu, state.hv)


def flags_of(h: np.ndarray, hu: np.ndarray, hv: np.ndarray) -> np.ndarray:
    """:func:`cell_flags` of any cells' h, hu, hv (e.g. a window of the map's)."""
    flags = np.full(np.shape(h), FLAG_FLOWING, dtype=np.uint8)
    flags[(hu == 0.0) & (hv == 0.0)] = FLAG_STOPPED
    flags[h <= 0.0] = FLAG_DRY
    return flags


@dataclass
class RunResult:
    """Everything a run produced, before it becomes a Dataset (see :mod:`avflow.output.dataset`)."""

    scenario: object
    terrain: Terrain
    solver: Solver
    state: State
    h0: np.ndarray
    snapshots: Snapshots
    status: str  #: "at_rest", "ended_by_rule", "completed" (time.end), "max_steps" or "failed"
    time_to_stop: float
    wall_time: float  #: s, the time loop only
    thresholds: dict
    summary: dict
    #: s before the time loop compiling the Numba kernels (or loading them from the cache)
    compile_time: float = 0.0
    #: the points of interest's time series (avflow.simulation.events; None: no points)
    points: object = None
    #: the secondary release areas, when each released (None: none)
    secondary: object = None


def warm_up(solver: Solver, state: State, max_steps: int, **stop) -> float:
    """Seconds to compile the time loop's kernels (or load them from Numba's cache).

    The loop is called once with ``t_target`` at the present time on a copy of the state:
    it takes no step, so the run is unchanged, but Numba compiles for exactly the argument
    types of the run. ``wall_time`` then counts the time loop alone (a first run in a fresh
    environment spends seconds compiling; later ones load the cache in milliseconds).
    """
    copy = state.copy()
    started = _time.perf_counter()
    solver.advance(copy, copy.t, max_steps=max_steps, **stop)
    return _time.perf_counter() - started


def prepare(scenario, max_memory=None, *, streamed: bool = False):
    """Terrain, initial thickness and solver of a validated scenario (no time stepping).

    First the cells and snapshots are counted against the memory limit
    (:func:`~avflow.simulation.resources.check_resources`; ``max_memory`` bytes or "8G",
    None: ``AVFLOW_MAX_MEMORY`` or half the machine's memory), before anything is allocated;
    ``streamed``: the snapshots go to a file as they are taken (one in memory at a time).
    """
    try:
        estimate = check_resources(scenario, max_memory, streamed=streamed)
        terrain = build_terrain(scenario, estimate.max_cells)
        release_freed_memory()  # the mesh's temporaries, before the solver's arrays
    except RasterError as err:
        raise ScenarioError.at(scenario, "terrain.path", str(err)) from None
    except MeshTooLarge as err:
        raise ScenarioError.at(scenario, "grid.refine.levels", str(err)) from None
    except StructureError as err:
        raise ScenarioError.at(scenario, err.field, str(err)) from None
    except ValueError as err:
        raise ScenarioError.at(scenario, "grid.dx", str(err)) from None
    if terrain.crs_wkt is None and terrain.kind != "profile":
        # A DEM without a CRS (an .asc without .prj) takes that of its release polygon:
        # inputs of one scene share one CRS, and the outputs can then be georeferenced.
        wkt = release_crs(scenario.release)
        if wkt:
            terrain = dataclasses.replace(terrain, crs_wkt=wkt)
    try:
        h0 = initial_thickness(scenario.release, terrain)
    except ReleaseError as err:
        raise ScenarioError.at(scenario, "release", str(err)) from None
    _check_release_size(scenario, terrain, h0)
    _check_release_and_structures(scenario, terrain, h0)
    try:  # maps, layer and forest sampled at the cell centres, each checked
        maps = friction_maps(scenario.rheology, terrain)
        source = mass_source(scenario, terrain)
        sources = area_sources(scenario, terrain)
        forest = (forest_coefficient(scenario.forest, terrain)
                  if scenario.forest is not None else None)
    except MapError as err:
        raise ScenarioError.at(scenario, err.field, str(err)) from None
    _check_layer_depth(scenario, terrain, source)
    _warn_empty(scenario, source, forest)
    law, params = friction_parameters(scenario.rheology, scenario.physics.density, maps)
    h_max = float(h0.max())
    out = scenario.output
    thresholds = {
        "dry": out.dry_threshold if out.dry_threshold is not None
        else DEFAULT_THRESHOLD_FRACTION * h_max,
        "runout": out.runout_threshold if out.runout_threshold is not None
        else DEFAULT_THRESHOLD_FRACTION * h_max,
        "stop_rule": out.stop_rule,
        "stop_fraction": out.stop_fraction,
    }
    min_flow = scenario.physics.min_flow_thickness
    thresholds["min_flow"] = (min(DEFAULT_MIN_FLOW, thresholds["dry"]) if min_flow is None
                              else min_flow)
    try:
        solver = _solver(scenario, terrain, law, params, thresholds, h_max, source, forest,
                         sources)
    except ValueError as err:  # numerics.kernel: grid where it does not apply; the backend's
        field = ("numerics.time_scheme" if isinstance(err, SchemeUnavailable)
                 else "numerics.backend" if scenario.numerics.backend != "cpu"
                 else "numerics.kernel")
        raise ScenarioError.at(scenario, field, str(err)) from None
    return terrain, h0, solver, thresholds


def _solver(scenario, terrain, law, params, thresholds, h_max, source=None,
            forest=None, sources=()) -> Solver:
    return Solver(terrain, law, params, gravity=scenario.physics.gravity,
                    cfl=scenario.time.cfl, dirac=scenario.physics.dirac,
                    order=scenario.numerics.order, limiter=scenario.numerics.limiter,
                    time_scheme=scenario.numerics.time_scheme,
                    threads=scenario.numerics.threads, kernel=scenario.numerics.kernel,
                    backend=scenario.numerics.backend,
                    h_dry=thresholds["dry"],
                    h_zero=max(ZERO_THICKNESS_FRACTION * h_max, thresholds["min_flow"]),
                    source=source, forest=forest, sources=sources)


#: The source kind of each entrainment law (avflow.numerics.physics.source_rate).
ENTRAINMENT_KINDS = {"exponential": SOURCE_EXPONENTIAL, "erosion_energy": SOURCE_EROSION_ENERGY,
                     "shear_threshold": SOURCE_SHEAR_THRESHOLD}


def mass_source(scenario, terrain: Terrain) -> MassSource | None:
    """The scenario's entrainment as the solver's :class:`MassSource` (None without one):
    its law's parameters in the kernels' units, the erodible depth per cell, the layer's
    density over the flow's (the flow's own when the layer's is not given: exactly 1)."""
    e = scenario.entrainment
    if e is None:
        return None
    rho_flow = scenario.physics.density
    ratio = 1.0 if e.density is None else e.density / rho_flow
    if e.law == "exponential":
        params = (e.e_s,)  # 1/m
    elif e.law == "erosion_energy":
        params = (e.e_b,)  # J/kg
    else:  # k in m/(s kPa) -> m/(s Pa); tau_c in Pa; the flow's density turns tau/rho to Pa
        params = (e.k / 1000.0, e.tau_c, rho_flow)
    return MassSource(ENTRAINMENT_KINDS[e.law], erodible_depth(e.layer, terrain), params,
                      density_ratio=ratio, u_min=e.u_min)


def area_sources(scenario, terrain: Terrain) -> tuple:
    """The scenario's registered sources (``sources``, avflow.extend) as the solver's
    :class:`~avflow.numerics.supply.AreaSource`: each one's parameters and its area, 1 on
    the cells it covers; an area that covers no cell is one warning line."""
    from avflow.numerics.supply import AreaSource
    from avflow.scenario.extensions import SOURCES

    out = []
    for k, spec in enumerate(scenario.sources):
        weight = source_weights(spec, terrain, f"sources.{k}")
        if not weight.any():
            warnings.warn(f"{scenario.source_path or scenario.name}: sources.{k}: its area "
                          "covers no cell of the terrain: it adds nothing", AvflowWarning,
                          stacklevel=3)
        params = [getattr(spec, p) for p in SOURCES[spec.law].parameters]
        out.append(AreaSource(spec.law, params, weight))
    return tuple(out)


def _warn_empty(scenario, source, forest) -> None:
    """One warning line for a layer or a forest that lies on no cell (a file off the map,
    a range beside it): the run is then the run without it."""
    where = scenario.source_path or scenario.name
    if source is not None and not np.any(source.erodible > 0.0):
        warnings.warn(f"{where}: entrainment.layer: no cell of the terrain has an erodible "
                      "depth: nothing will be entrained", AvflowWarning, stacklevel=3)
    if forest is not None and not np.any(forest > 0.0):
        warnings.warn(f"{where}: forest: no cell of the terrain is in the forest",
                      AvflowWarning, stacklevel=3)


#: Bed area over map area of a release past which a warning says so: 2 is a mean slope of
#: 60 degrees, where a thickness normal to the bed makes twice the volume of one vertical.
RELEASE_AREA_RATIO = 2.0


def _check_release_and_structures(scenario, terrain, h0) -> None:
    """A release under a wall (its cells leave the mesh: the release would shrink unsaid) or
    across a structure's line (no upstream side): refused before the run. A dam's body under
    part of the release, its line clear of it: one warning line per dam."""
    built = getattr(terrain, "extras", {}).get("structures")
    if built is None:
        return
    import types

    from avflow.terrain.release import ReleaseError, initial_thickness
    from avflow.terrain.structures import release_across, release_under_dams

    volume0 = h0 * terrain.mesh.cell_area
    total = float(volume0.sum())
    if built.walls.any():
        X, Y = np.meshgrid(built.x, built.y)
        under_walls = types.SimpleNamespace(  # the walls' cells, as a terrain of their own
            kind="grid", crs_wkt=terrain.crs_wkt,
            cell_xy=lambda: (X[built.walls], Y[built.walls]))
        try:
            covered = initial_thickness(scenario.release, under_walls)
        except ReleaseError:  # none of the release under the walls
            covered = np.zeros(1)
        cell = abs(built.x[1] - built.x[0]) * abs(built.y[1] - built.y[0])
        under = float(np.sum(covered)) * cell
        if under > 1e-3 * (total + under):
            raise ScenarioError.at(scenario, "structures", f"a wall covers "
                                   f"{100 * under / (total + under):.0f}% of the release "
                                   "(its cells leave the mesh); move the wall or the release")
    problem = release_across(built, *terrain.cell_xy(), volume0)
    if problem is not None:
        raise ScenarioError.at(scenario, *problem)
    for line in release_under_dams(built, *terrain.cell_xy(), volume0):
        warnings.warn(f"{scenario.source_path or scenario.name}: structures: {line}",
                      AvflowWarning, stacklevel=3)


def _check_release_size(scenario, terrain: Terrain, h0: np.ndarray) -> None:
    """A release thicker than the map is wide is no shallow flow (DEMs, rasters, polygons:
    the YAML thicknesses on profiles and planes are checked when the scenario is loaded)."""
    h_max = float(h0.max()) if h0.size else 0.0
    released = h0 > 0.0
    if terrain.kind != "profile" and released.any():
        bed = terrain.mesh.cell_area[released]
        ratio = float(bed.sum() / (bed * terrain.gamma_z[released]).sum())
        if ratio > RELEASE_AREA_RATIO:  # a thickness normal to a near-vertical bed
            volume = float((h0 * terrain.mesh.cell_area).sum())
            warnings.warn(f"{scenario.source_path or scenario.name}: release: its bed area is "
                          f"{ratio:.1f} times its map area (slopes near vertical), so its "
                          f"{volume:.3g} m^3 are {ratio:.1f} times thickness x map area; "
                          "check the release area and the DEM", AvflowWarning, stacklevel=2)
    span = _span(terrain)
    if not h_max <= span:
        raise ScenarioError.at(
            scenario, "release", f"the release is {h_max:.6g} m thick, more than the map's "
            f"{span:.6g} m extent: the depth-averaged equations need a layer thin compared "
            "with the flow's length (check the thickness and its units)")


def _span(terrain: Terrain) -> float:
    """The map's extent (m): what no release or erodible layer may be thicker than."""
    xs = [terrain.x] if terrain.kind == "profile" else list(terrain.cell_xy())
    return max(float(np.ptp(v)) for v in xs) + max(terrain.dx, terrain.dy)


def _check_layer_depth(scenario, terrain: Terrain, source) -> None:
    """An erodible layer deeper than the map is long is refused, as such a release is
    (rasters, polygons: the YAML depths on profiles and planes are checked on loading)."""
    if source is None or not source.erodible.size:
        return
    deepest, span = float(source.erodible.max()), _span(terrain)
    if not deepest <= span:
        raise ScenarioError.at(
            scenario, "entrainment.layer", f"the erodible layer is {deepest:.6g} m deep, "
            f"more than the map's {span:.6g} m extent: the depth-averaged equations need a "
            "layer thin compared with the flow's length (check the depth and its units)")


#: Largest relative mass-balance error of a run reported as a result: the scheme closes its
#: balance to round-off (1e-12); beyond this the run made or lost mass and is no result.
MASS_BALANCE_TOLERANCE = 1e-6


def _non_finite(state: State, terrain: Terrain) -> str | None:
    """None when h, hu and hv are finite everywhere; else what is not, in a few words."""
    if all(np.isfinite(getattr(state, name)).all() for name in ("h", "hu", "hv")):
        return None  # (the usual case: no array of flags kept)
    bad = {name: ~np.isfinite(getattr(state, name)) for name in ("h", "hu", "hv")}
    cells = np.flatnonzero(bad["h"] | bad["hu"] | bad["hv"])
    which = ", ".join(name for name, b in bad.items() if b.any())
    x = terrain.x[cells[0]] if terrain.kind == "profile" else terrain.cell_xy()[0][cells[0]]
    return (f"{which} not finite in {cells.size} of {state.h.size} cells (first at x = "
            f"{float(x):.6g} m): the scheme blew up")


def _failure(scenario, t: float, reason: str) -> str:
    """One line: the scenario file (or name), the time and what went wrong."""
    return str(Problem(f"run failed at t = {t:.6g} s: {reason}",
                       scenario.source_path or scenario.name))


def simulate(scenario, progress: Callable[[float, float], None] | None = None, *,
             max_memory=None, snapshots: Snapshots | None = None,
             on_compile: Callable[[str], None] | None = None,
             on_compiled: Callable[[float], None] | None = None) -> RunResult:
    """Run a validated scenario to its end time or until the mass stops.

    ``progress(t, t_end)`` is called after every output time; ``on_compile(what)`` as
    Numba starts compiling kernels that are neither in this process nor in the kernel cache,
    ``on_compiled(seconds)`` once the first call of the time loop (the warm-up) has
    compiled them. A non-finite state (h, hu,
    hv, checked at every output time, or the mass balance) or a step that cannot keep
    h >= 0 raises :class:`~avflow.errors.RunFailed`: a blow-up is never a result.
    ``snapshots`` records the output times (default: a new :class:`Snapshots`, every field
    in memory; :class:`avflow.output.stream.SnapshotStream` appends them to a file instead);
    it becomes ``result.snapshots``.
    """
    snaps = Snapshots() if snapshots is None else snapshots
    terrain, h0, solver, thresholds = prepare(scenario, max_memory,
                                              streamed=not snaps.in_memory)
    note = scenario.density_note()
    if note:  # valid input only: a bad file gets its one error line, nothing else
        warnings.warn(note, AvflowWarning, stacklevel=2)
    from avflow.simulation.events import (advance_sampling, point_series, sample_interval,
                                          secondary_areas)

    points = point_series(scenario, terrain)  # points and areas off the map: exit 2 now
    areas = secondary_areas(scenario, terrain, thresholds["dry"])
    sampling = sample_interval(scenario)
    started = _time.perf_counter()
    state = solver.new_state(h0)  # Numba's first use in a process loads its registries
    first_use = _time.perf_counter() - started
    v0 = solver.volume(state)
    by_volume = thresholds["stop_rule"] == "moving_volume"
    stop = {"stop_volume": thresholds["stop_fraction"] * v0 if by_volume else -1.0,
            "stop_kinetic": -1.0 if by_volume else thresholds["stop_fraction"]}
    t_end, every = scenario.time.end, scenario.output.every
    snaps.record(state, 0.0, terrain)
    if points is not None:
        points.sample(state)
    entraining = solver.source is not None
    if entraining:
        snaps.entrained_volume.append(0.0)
    # Numba compiles here only what is neither loaded nor in the kernel cache: one line then
    with compiling.watch(on_compile, solver.describe_kernel) as compiled:
        compile_time = first_use + warm_up(solver, state, scenario.time.max_steps, **stop)
        if compiled.compiled and on_compiled is not None:
            on_compiled(compiled.seconds)
        started = _time.perf_counter()
        recording = 0.0  # s storing snapshots (copies, or writes to the file): not the loop's
        k = 1
        time_to_stop = np.nan
        while True:
            target = min(k * every, t_end)
            status = advance_sampling(solver, state, target, sampling, points, areas, **stop,
                                      max_steps=scenario.time.max_steps)
            before = _time.perf_counter()
            snaps.record(state, state.statistics.moving_volume, terrain)
            if entraining:
                snaps.entrained_volume.append(solver.entrained_volume(state))
            recording += _time.perf_counter() - before
            failure = _non_finite(state, terrain)
            if failure is not None:  # a user's law or source that returns NaN, named
                failure = solver.suspect() or failure
            if status == "failed" and failure is None:
                failure = (f"no time step kept h >= 0 after {MAX_RETRIES} halvings "
                           f"(time.cfl {scenario.time.cfl:g})")
            if failure is not None:
                status = "failed"
                break
            if progress is not None:
                progress(state.t, t_end)
            if status == "stopped":
                # A mass that never moved (no cell ever had a speed) was at rest from the release.
                time_to_stop = state.t if state.peak_speed.any() else 0.0
                still = state.statistics.moving_volume
                status = AT_REST if by_volume or still <= REST_FRACTION * v0 else ENDED_BY_RULE
                break
            if status != "running" or target >= t_end:
                status = "completed" if status == "running" else status
                break
            k += 1
    wall = _time.perf_counter() - started - recording
    solver.release_buffers()  # the kernel's work arrays, before the file is finished
    result = RunResult(scenario, terrain, solver, state, h0, snaps, status, time_to_stop,
                       wall, thresholds, {}, compile_time, points, areas)
    if failure is None:
        result.summary = summarize(result, v0)
        error = result.summary["mass_balance_error"]
        if not error <= MASS_BALANCE_TOLERANCE:  # NaN too
            what = "not finite" if not math.isfinite(error) else f"off by {error:.3g}"
            supplied = result.summary.get("supplied_volume")
            failure = (f"the mass balance is {what} (released {v0:.6g}, entrained "
                       f"{result.summary['entrained_volume']:.6g}, "
                       + (f"supplied {supplied:.6g}, " if supplied is not None else "")
                       + (f"secondary {areas.released_volume:.6g}, " if areas is not None
                          else "")
                       + "on the map "
                       f"{result.summary['deposit_volume']:.6g}, out "
                       f"{result.summary['outflow_volume']:.6g}): not a result")
    if failure is not None:
        result.status = "failed"
        raise RunFailed(_failure(scenario, state.t, failure), result)
    return result


def summarize(result: RunResult, v0: float) -> dict:
    """The scalar summaries of a run (see :mod:`avflow.simulation.summary` for the definitions)."""
    state, terrain = result.state, result.terrain
    v_end = result.solver.volume(state)
    v_out = state.statistics.outflow_volume
    v_src = result.solver.entrained_volume(state)
    supplying = bool(result.solver.sources)
    v_sup = result.solver.supplied_volume(state) if supplying else 0.0
    v_sec = result.secondary.released_volume if result.secondary is not None else 0.0
    rho = result.scenario.physics.density
    truncated = runout_truncated(terrain, state.peak_h, result.thresholds["runout"],
                                 result.scenario.terrain.kind == "dem", v_out, result.h0)
    runout, length = deposit_extent(terrain, state.h, result.thresholds["runout"], result.h0)
    travel, drop, angle = travel_angle(terrain, result.h0, state.h, result.thresholds["runout"])
    return {
        "travel_length": travel,
        "drop_height": drop,
        "travel_angle": angle,
        "runout": runout,
        "time_to_stop": result.time_to_stop,
        "deposit_max_thickness": float(state.h.max()),
        "deposit_length": length,
        "deposit_volume": v_end,
        "release_volume": v0,
        "entrained_volume": v_src,
        "outflow_volume": v_out,
        "film_volume": state.statistics.film_volume,
        "moving_volume": state.statistics.moving_volume,
        "moving_volume_end": state.statistics.moving_volume,
        "kinetic_energy_end": rho * state.statistics.kinetic,
        "kinetic_energy_peak": rho * state.statistics.kinetic_peak,
        "ended_by": result.thresholds["stop_rule"]
        if result.status in (AT_REST, ENDED_BY_RULE, "stopped")
        else ENDED_BY.get(result.status, result.status),
        # released + entrained (read from the erodible layer) + supplied (the registered
        # sources' book per cell) = on the map + out
        # (+ released by the secondary areas that the flow reached)
        "mass_balance_error": abs(v_end + v_out - v0 - v_src - v_sup - v_sec)
        / (v0 + v_src + v_sup + v_sec),
        **({"supplied_volume": v_sup} if supplying else {}),
        **({"secondary_release_volume": v_sec} if result.secondary is not None else {}),
        "runout_truncated": truncated,
        "status": result.status,
        "steps": state.steps,
        "dt_min": state.statistics.dt_min,
        "dt_max": state.statistics.dt_max,
        "clamped_normal_cells": int(state.statistics.clamped_cells),
        "halved_steps": int(state.statistics.halved_steps),
        "order2_fallbacks": int(state.statistics.order2_fallbacks),
        "wall_time": result.wall_time,
        "compile_time": result.compile_time,
        "cell_updates_per_second": state.steps * terrain.n_cells / max(result.wall_time, 1e-9),
    }
