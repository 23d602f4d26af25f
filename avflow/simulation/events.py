"""What the runner does between two output times: points of interest sampled, secondary
release areas checked and released.

The time loop (:meth:`avflow.numerics.solver.Solver.advance`) runs between two times the
runner chooses; the state is then on the host as numpy arrays. Where a run has points of
interest or secondary release areas, the runner advances between output times in shorter
intervals (``output.points.every``, ``secondary_release.check_every``; by default a tenth
of ``output.every``, at most 1 s) and, after each, samples the points and checks the areas.
A time step is shortened to land on each of these times, so such a run differs from one
without them by the size of a time step's truncation error, not more.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from avflow.errors import ScenarioError

#: Default interval of the samples and checks: this fraction of output.every ...
SAMPLE_FRACTION = 0.1
#: ... and at most this many seconds (a front at 50 m/s crosses 50 m).
SAMPLE_MAX = 1.0


def sample_interval(scenario) -> float | None:
    """Seconds between the samples of the points and the checks of the secondary areas
    (the shorter where both are given); None when the run has neither."""
    every = []
    default = min(SAMPLE_FRACTION * scenario.output.every, SAMPLE_MAX)
    if scenario.output.points is not None:
        every.append(scenario.output.points.every or default)
    if scenario.secondary_release is not None:
        every.append(scenario.secondary_release.check_every or default)
    return min(every) if every else None


# --- points of interest -------------------------------------------------------------------


@dataclass
class PointSeries:
    """Thickness, speed and pressure against time at the points of interest."""

    names: list
    x: np.ndarray  #: m, the points as given (in the terrain's CRS)
    y: np.ndarray
    cells: np.ndarray  #: the cell each point lies in
    density: float  #: kg/m^3, for the pressure rho u^2
    time: list = field(default_factory=list)
    h: list = field(default_factory=list)  #: m per point, per sample
    speed: list = field(default_factory=list)  #: m/s per point, per sample

    def sample(self, state) -> None:
        c = self.cells
        h = state.h[c]
        with np.errstate(invalid="ignore", divide="ignore"):
            u = np.where(h > 0.0, np.hypot(state.hu[c], state.hv[c]) / h, 0.0)
        self.time.append(state.t)
        self.h.append(h.copy())
        self.speed.append(u)

    def arrays(self) -> dict:
        """(points, samples) arrays: thickness (m), speed (m/s), pressure (kPa)."""
        h = np.asarray(self.h, dtype=float).T.reshape(len(self.names), -1)
        u = np.asarray(self.speed, dtype=float).T.reshape(len(self.names), -1)
        return {"time": np.asarray(self.time, dtype=float), "thickness": h, "speed": u,
                "pressure": self.density * u**2 / 1000.0}


def read_points(spec, terrain_wkt: str | None, scenario) -> tuple[list, np.ndarray, np.ndarray]:
    """The names and x, y of ``output.points``: those written in ``at``, then those of its
    point layer, reprojected to the terrain's CRS where both carry one."""
    names = [p.name for p in spec.at]
    xs = [p.x for p in spec.at]
    ys = [p.y for p in spec.at]
    if spec.file is not None:
        n, x, y = _read_layer(spec.file, spec.name_field, terrain_wkt, scenario)
        names += n
        xs += list(x)
        ys += list(y)
    if len(set(names)) != len(names):
        raise ScenarioError.at(scenario, "output.points",
                               f"the points' names must differ, got {sorted(names)}")
    return names, np.asarray(xs, dtype=float), np.asarray(ys, dtype=float)


def _read_layer(path, name_field, terrain_wkt, scenario):
    def fail(message):
        return ScenarioError.at(scenario, "output.points.file", f"{path}: {message}")

    try:
        import pyogrio
        import shapely

        meta, _, wkb, columns = pyogrio.raw.read(path)
        geometries = shapely.from_wkb(wkb)
    except Exception as err:  # GDAL's own error: say which file
        raise fail(f"cannot be read as a point layer ({' '.join(str(err).split())})") from None
    kinds = set(shapely.get_type_id(geometries).tolist())
    if not kinds or kinds - {0}:  # 0: Point
        raise fail("holds no points or other geometries than points (give one point per "
                   "feature)")
    x, y = shapely.get_x(geometries), shapely.get_y(geometries)
    fields = list(meta["fields"])
    if name_field in fields:
        names = [str(v) for v in columns[fields.index(name_field)]]
    else:
        names = [f"point_{k + 1}" for k in range(x.size)]
    wkt = meta.get("crs")
    if wkt and terrain_wkt:
        from avflow.terrain.raster import same_crs

        if not same_crs(wkt, terrain_wkt):  # reprojected (rasterio's PROJ)
            from rasterio.crs import CRS
            from rasterio.warp import transform

            try:
                x, y = (np.asarray(v) for v in transform(CRS.from_user_input(wkt),
                                                         CRS.from_wkt(terrain_wkt), x, y))
            except Exception as err:  # noqa: BLE001 - PROJ's words, one line
                raise fail(f"cannot be reprojected to the DEM's CRS ({err})") from None
    elif wkt and not terrain_wkt:
        raise fail("carries a CRS, the terrain none: the points cannot be placed (give "
                   "them in 'at' in the terrain's coordinates)")
    if not np.all(np.isfinite(x) & np.isfinite(y)):
        raise fail("holds empty or non-finite points")
    return names, x, y


def locate_points(terrain, x, y, names, scenario) -> np.ndarray:
    """The cell each point lies in (nearest cell centre, within half a cell along each axis
    on grids, a cell's size on triangles); a point off the map is an error naming it."""
    cx, cy = terrain.cell_xy()
    cells = np.empty(x.size, dtype=np.int64)
    half_x, half_y = terrain.dx / 2.0, terrain.dy / 2.0
    for k in range(x.size):
        d = (cx - x[k]) ** 2 + (cy - y[k]) ** 2
        i = int(np.argmin(d))
        if terrain.kind == "triangles":
            inside = math.sqrt(d[i]) <= max(terrain.dx, terrain.dy)
        else:
            inside = (abs(cx[i] - x[k]) <= half_x * (1 + 1e-9)
                      and abs(cy[i] - y[k]) <= half_y * (1 + 1e-9))
        if not inside:
            raise ScenarioError.at(
                scenario, "output.points", f"point {names[k]!r} at ({x[k]:.6g}, {y[k]:.6g}) is outside the domain "
                f"(x {cx.min() - half_x:.6g} to {cx.max() + half_x:.6g}, y "
                f"{cy.min() - half_y:.6g} to {cy.max() + half_y:.6g} m)")
        cells[k] = i
    return cells


def point_series(scenario, terrain) -> PointSeries | None:
    """The points of interest of a scenario, located on the terrain (None: none)."""
    spec = scenario.output.points
    if spec is None:
        return None
    names, x, y = read_points(spec, terrain.crs_wkt, scenario)
    cells = locate_points(terrain, x, y, names, scenario)
    return PointSeries(names, x, y, cells, scenario.physics.density)


# --- secondary release areas --------------------------------------------------------------


@dataclass
class SecondaryAreas:
    """The secondary release areas of a run: each one's thickness per cell, and when it
    released (NaN: not yet) and what volume."""

    names: list
    thickness: list  #: per area, (cells, thickness) of the cells it covers
    h_dry: float
    time: list = field(default_factory=list)
    volume: list = field(default_factory=list)

    def __post_init__(self):
        self.time = [math.nan] * len(self.names)
        self.volume = [0.0] * len(self.names)

    @property
    def released_volume(self) -> float:
        return math.fsum(self.volume)

    def check(self, state, cell_area) -> bool:
        """Release every area not yet released that the flow has reached (h above the dry
        threshold on one of its cells, as AvaFrame's com1DFA: flow thickness > 0 on one of
        its cells); True when one did (the caller then refreshes the solver's limits)."""
        released = False
        for k, (cells, h_add) in enumerate(self.thickness):
            if not math.isnan(self.time[k]) or not np.any(state.h[cells] > self.h_dry):
                continue
            state.h[cells] += h_add  # at rest: momentum unchanged, its speed falls
            from avflow.numerics.physics import DRY, UNDER_THRESHOLD

            state.flag[cells] = np.where(state.flag[cells] == DRY, UNDER_THRESHOLD,
                                         state.flag[cells])
            state.peak_h[cells] = np.maximum(state.peak_h[cells], state.h[cells])
            first = np.isnan(state.arrival[cells]) & (state.h[cells] > self.h_dry)
            state.arrival[cells[first]] = state.t
            self.time[k] = state.t
            self.volume[k] = math.fsum(h_add * cell_area[cells])
            released = True
        return released


def secondary_areas(scenario, terrain, h_dry: float) -> SecondaryAreas | None:
    """The scenario's secondary release areas on the terrain (a polygon file: one area per
    polygon); an area that covers no cell is an error naming it."""
    spec = scenario.secondary_release
    if spec is None:
        return None
    from avflow.terrain.polygons import PolygonError, rasterize, read_polygons
    from avflow.terrain.release import ReleaseError, _check_crs, initial_thickness

    names, parts = [], []
    x, y = terrain.cell_xy()
    for k, area in enumerate(spec.areas):
        name = f"secondary_release.areas.{k}"
        try:
            if area.kind == "polygon":  # each polygon its own area, as AvaFrame's
                polygons, wkt = read_polygons(area.path)
                _check_crs(area.path, wkt, terrain)
                hs = [rasterize([p], x, y, area.thickness, source=area.path)
                      * area.volume_factor for p in polygons]
                labels = [f"{name}.{j}" for j in range(len(hs))]
                if len(hs) == 1:
                    labels = [name]
            else:
                hs, labels = [initial_thickness(area, terrain)], [name]
        except (ReleaseError, PolygonError) as err:
            raise ScenarioError.at(scenario, name, str(err)) from None
        for h, label in zip(hs, labels):
            cells = np.flatnonzero(h > 0.0)
            if not cells.size:
                raise ScenarioError.at(scenario, name, f"{label}: the area covers no cell "
                                       "centre of the map")
            names.append(label)
            parts.append((cells, np.ascontiguousarray(h[cells], dtype=float)))
    return SecondaryAreas(names, parts, h_dry)


def advance_sampling(solver, state, target: float, every: float | None, points, areas,
                     **run) -> str:
    """:meth:`Solver.advance` to ``target``, through the times ``k * every`` before it: after
    each, the points sampled and the secondary areas checked. The status of the last call
    (``"running"`` where ``target`` was reached)."""
    if every is None:
        return solver.advance(state, target, **run)
    while True:
        k = math.floor(state.t / every * (1 + 1e-12)) + 1
        stop = min(k * every, target)
        status = solver.advance(state, stop, **run)
        if points is not None:
            points.sample(state)
        if areas is not None and status in ("running", "stopped") \
                and areas.check(state, solver.terrain.mesh.cell_area):
            solver.reset_limits(state)
            # the GPU keeps the state on the device between calls: uploaded again
            cuda = getattr(solver, "_cuda", None)
            if cuda is not None:
                cuda.held = None
            status = "running"  # new mass at rest on the map: not stopped yet
        if status != "running" or stop >= target:
            return status
