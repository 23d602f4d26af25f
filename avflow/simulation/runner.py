"""Run one scenario: terrain, release and law from the scenario, the solver, the snapshots.

The runner is the only place that decides output times; the time loop itself runs inside
:meth:`avflow.numerics.solver.Solver.advance` between two output times.
"""

from __future__ import annotations

import dataclasses
import time as _time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from avflow.numerics import kernels as K
from avflow.terrain.raster import RasterError
from avflow.errors import ScenarioError
from avflow.terrain.release import ReleaseError, initial_thickness, release_crs
from avflow.numerics.rheology import friction_parameters
from avflow.numerics.solver import Solver, State
from avflow.simulation.summary import deposit_extent, runout_truncated, travel_angle
from avflow.terrain.bed import Terrain
from avflow.terrain.build import build_terrain

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

# Cell states written to the output flag variable.
FLAG_DRY, FLAG_FLOWING, FLAG_STOPPED = 0, 1, 2


@dataclass
class Snapshots:
    """Fields stored at output times (lists of per-cell arrays, float64 / uint8)."""

    time: list = field(default_factory=list)
    h: list = field(default_factory=list)
    hu: list = field(default_factory=list)
    hv: list = field(default_factory=list)
    flag: list = field(default_factory=list)
    moving_volume: list = field(default_factory=list)
    center_of_mass: list = field(default_factory=list)  #: (x, y, z) per snapshot, m

    def record(self, state: State, moving: float, terrain: Terrain) -> None:
        self.time.append(state.t)
        self.h.append(state.h.copy())
        self.hu.append(state.hu.copy())
        self.hv.append(state.hv.copy())
        self.flag.append(cell_flags(state))
        self.moving_volume.append(moving)
        self.center_of_mass.append(center_of_mass(terrain, state.h))


def center_of_mass(terrain: Terrain, h: np.ndarray) -> tuple:
    """Volume-weighted centre (x, y, z) of the material, m (x along the bed on profiles)."""
    w = h * terrain.mesh.cell_area
    total = w.sum()
    if total <= 0.0:
        return (np.nan, np.nan, np.nan)
    if terrain.kind == "profile":
        x, y = terrain.x, np.zeros_like(terrain.x)
    else:
        x, y = terrain.cell_xy()
    return (float(w @ x / total), float(w @ y / total), float(w @ terrain.bed_elevation / total))


def cell_flags(state: State) -> np.ndarray:
    """0 dry, 1 flowing (above the Coulomb threshold), 2 at rest under the threshold."""
    flags = np.full(state.h.shape, FLAG_FLOWING, dtype=np.uint8)
    flags[(state.hu == 0.0) & (state.hv == 0.0)] = FLAG_STOPPED
    flags[state.h <= 0.0] = FLAG_DRY
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
    status: str  #: "stopped", "completed" (end time reached), "max_steps" or "failed"
    time_to_stop: float
    wall_time: float
    thresholds: dict
    summary: dict


def prepare(scenario):
    """Terrain, initial thickness and solver of a validated scenario (no time stepping)."""
    try:
        terrain = build_terrain(scenario)
    except RasterError as err:
        raise ScenarioError.at(scenario, "terrain.path", str(err)) from None
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
    law, params = friction_parameters(scenario.rheology)
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
    solver = Solver(terrain, law, params, gravity=scenario.physics.gravity,
                    cfl=scenario.time.cfl, dirac=scenario.physics.dirac,
                    h_dry=thresholds["dry"],
                    h_zero=max(ZERO_THICKNESS_FRACTION * h_max, thresholds["min_flow"]))
    return terrain, h0, solver, thresholds


def simulate(scenario, progress: Callable[[float, float], None] | None = None) -> RunResult:
    """Run a validated scenario to its end time or until the mass stops.

    ``progress(t, t_end)`` is called after every output time.
    """
    terrain, h0, solver, thresholds = prepare(scenario)
    state = solver.new_state(h0)
    v0 = solver.volume(state)
    by_volume = thresholds["stop_rule"] == "moving_volume"
    stop = {"stop_volume": thresholds["stop_fraction"] * v0 if by_volume else -1.0,
            "stop_kinetic": -1.0 if by_volume else thresholds["stop_fraction"]}
    t_end, every = scenario.time.end, scenario.output.every
    snaps = Snapshots()
    snaps.record(state, 0.0, terrain)
    started = _time.perf_counter()
    k = 1
    time_to_stop = np.nan
    while True:
        target = min(k * every, t_end)
        status = solver.advance(state, target, **stop, max_steps=scenario.time.max_steps)
        snaps.record(state, float(state.stats[K.ST_MOVING]), terrain)
        if progress is not None:
            progress(state.t, t_end)
        if status == "stopped":
            # A mass that never moved (no cell ever had a speed) was at rest from the release.
            time_to_stop = state.t if state.peak_speed.any() else 0.0
            break
        if status != "running" or target >= t_end:
            status = "completed" if status == "running" else status
            break
        k += 1
    wall = _time.perf_counter() - started
    result = RunResult(scenario, terrain, solver, state, h0, snaps, status, time_to_stop,
                       wall, thresholds, {})
    result.summary = summarize(result, v0)
    return result


def summarize(result: RunResult, v0: float) -> dict:
    """The scalar summaries of a run (see :mod:`avflow.simulation.summary` for the definitions)."""
    state, terrain = result.state, result.terrain
    v_end = result.solver.volume(state)
    v_out = float(state.stats[K.ST_OUTFLOW])
    rho = result.scenario.physics.density
    truncated = runout_truncated(terrain, state.peak_h, result.thresholds["runout"],
                                 result.scenario.terrain.kind == "dem", v_out)
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
        "outflow_volume": v_out,
        "film_volume": float(state.stats[K.ST_FILM]),
        "moving_volume": float(state.stats[K.ST_MOVING]),
        "moving_volume_end": float(state.stats[K.ST_MOVING]),
        "kinetic_energy_end": rho * float(state.stats[K.ST_KINETIC]),
        "kinetic_energy_peak": rho * float(state.stats[K.ST_KINETIC_PEAK]),
        "ended_by": ENDED_BY.get(result.status, result.status) if result.status != "stopped"
        else result.thresholds["stop_rule"],
        "mass_balance_error": abs(v_end + v_out - v0) / v0,
        "runout_truncated": truncated,
        "status": result.status,
        "steps": state.steps,
        "dt_min": float(state.stats[K.ST_DT_MIN]),
        "dt_max": float(state.stats[K.ST_DT_MAX]),
        "clamped_normal_cells": int(state.stats[K.ST_CLAMPED]),
        "halved_steps": int(state.stats[K.ST_RETRIES]),
        "wall_time": result.wall_time,
        "cell_updates_per_second": state.steps * terrain.n_cells / max(result.wall_time, 1e-9),
    }
