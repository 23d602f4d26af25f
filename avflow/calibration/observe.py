"""Observations on the cells of a run, the checks made before any run, and one member's
scores.

The observed area, deposit and runout station are put on the cells of the run once (the
members of a calibration share their grid, which is not a calibrated parameter) and each
member's peak fields are scored against them (:mod:`avflow.calibration.scores`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from avflow.calibration import scores as S

__all__ = ["check_observations", "Observed", "observe", "member_cells", "score_member",
           "SUMMARIES"]

#: Per-member summaries emulated and analysed for sensitivity besides the discrepancies.
SUMMARIES = ("runout", "impact_area", "deposit_max_thickness")
#: Area and runout fields: (variable of the run file, factor to the threshold's units).
_FIELDS = {"pressure": ("peak_pressure", 1e-3), "thickness": ("peak_thickness", 1.0),
           "speed": ("peak_speed", 1.0)}


def map_frame(base):
    """``(xmin, xmax, ymin, ymax, crs_wkt)`` of a 2D base scenario's map (cell edges), or
    None for a profile."""
    if base.terrain.kind == "profile":
        return None
    from avflow.terrain.build import terrain_raster

    _, x, y, wkt = terrain_raster(base)
    hx = 0.5 * abs(float(x[1] - x[0])) if x.size > 1 else 0.0
    hy = 0.5 * abs(float(y[1] - y[0])) if y.size > 1 else 0.0
    return (float(x.min()) - hx, float(x.max()) + hx, float(y.min()) - hy,
            float(y.max()) + hy, wkt)


def check_observations(cal, fail) -> None:
    """Refuse, before anything runs, an observation outside the map or in another CRS.
    ``fail(keys, message)`` makes the error naming the file's line and field."""
    from avflow.terrain.raster import same_crs

    frame = map_frame(cal.base)
    _check_values(cal, frame, fail)
    if frame is None:
        length = float(cal.base.terrain.length)
        for k, obs in enumerate(cal.spec.observations):
            for i, pt in enumerate(getattr(obs, "points", None) or ()):
                if not 0 <= pt[0] <= length:
                    raise fail(("observations", k, "points", i), f"x = {pt[0]:g} m lies "
                               f"outside the profile (0 to {length:g} m)")
            if getattr(obs, "interval", None) is not None:
                a, b = obs.interval
                if b < 0 or a > length:
                    raise fail(("observations", k, "interval"), f"[{a:g}, {b:g}] lies outside "
                               f"the profile (0 to {length:g} m)")
            if getattr(obs, "station", None) is not None and not 0 <= obs.station <= length:
                raise fail(("observations", k, "station"), f"{obs.station:g} m lies outside "
                           f"the profile (0 to {length:g} m)")
        return
    xmin, xmax, ymin, ymax, wkt = frame
    where = f"the map (x {xmin:g} to {xmax:g}, y {ymin:g} to {ymax:g})"

    def inside(px, py) -> np.ndarray:
        px, py = np.asarray(px, float), np.asarray(py, float)
        return (px >= xmin) & (px <= xmax) & (py >= ymin) & (py <= ymax)

    for k, obs in enumerate(cal.spec.observations):
        if obs.kind == "points":
            for i, pt in enumerate(obs.points):
                if not inside(*pt):
                    raise fail(("observations", k, "points", i), f"{list(pt)} lies outside "
                               f"{where}")
            continue
        if obs.kind == "runout":
            from avflow.output.path import PathError, read_line

            try:
                line = read_line(cal.files[(k, "line")])
            except PathError as err:
                raise fail(("observations", k, "line"), str(err)) from None
            if not inside(line.x, line.y).any():
                raise fail(("observations", k, "line"), f"the path line lies outside {where}")
            if obs.point is not None and not inside(*obs.point):
                raise fail(("observations", k, "point"), f"{list(obs.point)} lies outside "
                           f"{where}")
            continue
        if obs.raster is not None:
            from avflow.terrain.raster import RasterError, read_raster

            try:
                r = read_raster(cal.files[(k, "raster")])
            except RasterError as err:
                raise fail(("observations", k, "raster"), str(err)) from None
            crs, bx, by = r.crs_wkt, r.x, r.y
            key = "raster"
            if obs.kind == "deposit":
                _check_deposit(r.values, frame, lambda m: fail(("observations", k, key), m))
        else:
            from avflow.terrain.polygons import PolygonError, read_polygons

            try:
                areas, crs = read_polygons(cal.files[(k, "polygon")])
            except PolygonError as err:
                raise fail(("observations", k, "polygon"), str(err)) from None
            pts = np.concatenate([np.asarray(ring, float).reshape(-1, 2)
                                  for a in areas for ring in a.rings])
            bx, by = pts[:, 0], pts[:, 1]
            key = "polygon"
        if crs and wkt and not same_crs(crs, wkt):
            raise fail(("observations", k, key), "is in another CRS than the base scenario's "
                       "map and avflow does not reproject it: reproject it (gdalwarp, "
                       "ogr2ogr) to the DEM's CRS")
        if (float(np.max(bx)) < xmin or float(np.min(bx)) > xmax or float(np.max(by)) < ymin
                or float(np.min(by)) > ymax):
            raise fail(("observations", k, key), f"lies outside {where} (x {np.min(bx):g} to "
                       f"{np.max(bx):g}, y {np.min(by):g} to {np.max(by):g})")


#: Largest observed value taken at a point, by field (beyond: not a measurement of an
#: avalanche; 1e308 overflowed the misfit of every run): m/s, s, m (the map's extent), kPa.
POINT_BOUNDS = {"speed": (1e3, "m/s"), "arrival_time": (1e7, "s"), "pressure": (1e6, "kPa")}


def _extent(cal, frame) -> float:
    if frame is None:
        return float(cal.base.terrain.length)
    xmin, xmax, ymin, ymax, _ = frame
    return max(xmax - xmin, ymax - ymin)


def _check_values(cal, frame, fail) -> None:
    """Observed values that no avalanche has: negative speeds, times, thicknesses or
    pressures, and values past :data:`POINT_BOUNDS` (a thickness: past the map's extent)."""
    for k, obs in enumerate(cal.spec.observations):
        if obs.kind != "points":
            continue
        bound, unit = POINT_BOUNDS.get(obs.field, (_extent(cal, frame), "m"))
        for i, value in enumerate(obs.values):
            if not 0.0 <= value <= bound:
                raise fail(("observations", k, "values", i), f"an observed {obs.field} of "
                           f"{value:g} {unit} is not physical (0 to {bound:g} {unit})")


def _check_deposit(values: np.ndarray, frame, fail) -> None:
    """An observed deposit: no negative thickness, none deeper than the map is long."""
    seen = values[np.isfinite(values)]
    if seen.size and float(seen.min()) < 0.0:
        raise fail(f"holds negative deposit thicknesses (down to {float(seen.min()):g} m): "
                   "a thickness is >= 0 (write NODATA where nothing was observed)")
    xmin, xmax, ymin, ymax, _ = frame
    extent = max(xmax - xmin, ymax - ymin)
    if seen.size and float(seen.max()) > extent:
        raise fail(f"holds a deposit {float(seen.max()):g} m thick, more than the map's "
                   f"{extent:g} m extent: not physical (check the raster and its units)")
    if values.size and np.isinf(values).any():
        raise fail("holds infinite values: not physical")


# =========================================================================================
# On the cells of a run
# =========================================================================================


@dataclass
class Cells:
    """A member's cells: RunPoints (peak fields, x, y) plus its deposit thickness."""

    points: object
    deposit: np.ndarray
    summary: dict
    arrival: np.ndarray | None = None  #: s, NaN where never reached
    end: float = math.nan              #: s, the run's last output time


def member_cells(ds) -> Cells:
    """The cells of a member Dataset (grid, profile or triangles), as the path analysis
    sees them, with ``deposit_thickness`` on the same cells."""
    from avflow.output.maps import scene_kind
    from avflow.output.path import run_points

    points = run_points(ds)
    dep = np.asarray(ds["deposit_thickness"].values, dtype=float)
    arrival = (np.asarray(ds["arrival_time"].values, dtype=float) if "arrival_time" in ds
               else None)
    if scene_kind(ds) == "grid":
        on = np.isfinite(ds["bed_elevation"].values)
        dep = dep[on]
        arrival = arrival[on] if arrival is not None else None
    pressure = np.nan_to_num(np.asarray(points.fields["peak_pressure"], float), nan=0.0)
    cell = points.spacing ** 2 if points.kind != "profile" else points.spacing
    summary = {"runout": float(ds["runout"]),
               "impact_area": float(np.count_nonzero(pressure >= 1e3) * cell),
               "deposit_max_thickness": float(ds["deposit_max_thickness"])}
    end = float(ds["time"].values[-1]) if "time" in ds.coords else math.nan
    return Cells(points, dep, summary, arrival, end)


@dataclass
class Observed:
    """The observations on the cells of the calibration's grid."""

    masks: dict       #: observation index -> bool mask (areas, deposit polygons/intervals)
    nearest: dict     #: observation index -> cell index nearest each observed point
    thickness: dict   #: observation index -> observed deposit thickness (rasters)
    lines: dict       #: observation index -> PathLine
    stations: dict    #: observation index -> s_obs (m along the line)
    n_cells: int


def _nearest(raster, px, py) -> np.ndarray:
    """Raster values at the cells nearest the points (NaN outside it)."""
    i = np.rint((np.asarray(px, float) - raster.x[0]) / raster.dx).astype(np.int64)
    j = np.rint((np.asarray(py, float) - raster.y[0]) / raster.dy).astype(np.int64)
    ny, nx = raster.values.shape
    ok = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
    out = np.full(i.shape, np.nan)
    out[ok] = raster.values[j[ok], i[ok]]
    return out


def observe(cal, cells: Cells) -> Observed:
    """Put every observation on these cells (those of any member: they share the grid)."""
    from avflow.output.path import path_for, read_line
    from avflow.terrain.polygons import rasterize
    from avflow.terrain.raster import read_raster

    p = cells.points
    masks, thickness, lines, stations, nearest = {}, {}, {}, {}, {}
    for k, obs in enumerate(cal.spec.observations):
        if obs.kind == "points":
            pts = np.asarray(obs.points, float)
            nearest[k] = np.array([int(np.argmin((p.x - px) ** 2 + (p.y - py) ** 2))
                                   for px, py in pts])
            continue
        if obs.kind == "runout":
            line = read_line(cal.files[(k, "line")]) if obs.line else path_for(p, None)
            lines[k] = line
            if obs.station is not None and p.kind == "profile":
                # on a profile, station is the horizontal x of the runout point (the path
                # starts at the first cell, not at x = 0)
                stations[k] = float(line.project([obs.station], [0.0])[0][0])
            elif obs.station is not None:
                stations[k] = float(obs.station)
            else:
                stations[k] = float(line.project([obs.point[0]], [obs.point[1]])[0][0])
            continue
        if obs.interval is not None:
            a, b = obs.interval
            masks[k] = (p.x >= a) & (p.x <= b)
        elif obs.polygon is not None:
            from avflow.terrain.polygons import read_polygons

            areas, _ = read_polygons(cal.files[(k, "polygon")])
            masks[k] = rasterize(areas, p.x, p.y, thickness=1.0) > 0
        else:
            values = _nearest(read_raster(cal.files[(k, "raster")]), p.x, p.y)
            if obs.kind == "deposit":
                thickness[k] = np.nan_to_num(values, nan=0.0)
            else:
                masks[k] = np.nan_to_num(values, nan=-np.inf) > obs.raster_threshold
    return Observed(masks, nearest, thickness, lines, stations, int(p.x.size))


def score_member(cal, observed: Observed, cells: Cells) -> dict:
    """One member's scores: per observation ``<label>_d`` (its discrepancy) and its detail
    (confusion counts and area scores, runout stations), then ``misfit``."""
    from avflow.output.path import analyse

    p = cells.points
    row: dict = {}
    ds_, errs, weights = [], [], []
    for k, obs in enumerate(cal.spec.observations):
        label = cal.label(k)
        if obs.kind == "runout":
            threshold = obs.threshold
            result = analyse(p, observed.lines[k], obs.field, threshold)
            s_sim = result.scalars["runout_s"]
            d = S.runout_difference(s_sim, observed.stations[k])
            row.update({f"{label}_s_sim": s_sim, f"{label}_s_obs": observed.stations[k]})
        elif obs.kind == "points":
            cells_at = observed.nearest[k]
            if obs.field == "arrival_time":
                # never reached: arrival taken as the run's end (a late arrival, not none)
                sim = np.where(np.isfinite(cells.arrival[cells_at]), cells.arrival[cells_at],
                               cells.end)
            elif obs.field == "deposit":  # thickness at the end (NaN: none there)
                sim = np.nan_to_num(cells.deposit[cells_at])
            else:
                name, factor = {"speed": ("peak_speed", 1.0), "pressure": ("peak_pressure",
                                                                          1e-3),
                                "thickness": ("peak_thickness", 1.0)}[obs.field]
                sim = np.nan_to_num(np.asarray(p.fields[name], float)[cells_at]) * factor
            d = float(np.sqrt(np.mean((sim - np.asarray(obs.values, float)) ** 2)))
            row[f"{label}_rmse"] = d
        elif obs.kind == "deposit" and k in observed.thickness:
            d = S.rmse_union(cells.deposit, observed.thickness[k], obs.threshold)
            row[f"{label}_rmse"] = d
        else:
            if obs.kind == "deposit":
                values, threshold = cells.deposit, obs.threshold
            else:
                name, factor = _FIELDS[obs.field]
                values, threshold = np.asarray(p.fields[name], float) * factor, obs.threshold
            sc = S.area_scores(values, threshold, observed.masks[k], alpha=obs.alpha,
                               beta=obs.beta)
            row.update({f"{label}_{key}": v for key, v in sc.items()})
            d = 1.0 - sc[obs.score] if math.isfinite(sc[obs.score]) else math.nan
        row[f"{label}_d"] = float(d)
        ds_.append(d)
        errs.append(cal.error(k))
        weights.append(obs.weight)
    row["misfit"] = S.misfit(ds_, errs, weights)
    row["log_likelihood"] = (S.log_likelihood(ds_, errs, weights)
                             if math.isfinite(row["misfit"]) else math.nan)
    row.update(cells.summary)
    return row
