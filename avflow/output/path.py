"""Runout along the avalanche path: AvaFrame's AIMEC view of a run or of an ensemble.

Engineers compare runs along the avalanche path, not by the farthest cell from the release
(Fischer 2013, Nat. Hazards Earth Syst. Sci. 13, 1655; AvaFrame's ``ana3AIMEC``):

- a **path line**: a polyline read from a line file (shapefile, GeoJSON or CSV of x, y), or,
  when none is given, the flow's own centre-of-mass track (``center_of_mass_x/y`` of every
  run file), thinned to one vertex per two cells and extended upslope to the top of the
  release, so that ``s = 0`` there;
- **path-following coordinates** of every cell: ``s``, the horizontal distance along the
  line to the cell's nearest point on it, and ``l``, the signed horizontal distance from the
  line (positive on the left looking downslope). Points beyond either end of the line are
  measured on the straight continuation of its first or last segment;
- AIMEC's **cross-section maxima** of ``peak_pressure``, ``peak_speed`` and
  ``peak_thickness`` in bins of one cell size along ``s`` (the maximum over ``l``, within
  ``width / 2`` of the line when a width is given);
- the **runout point**: of the cells whose peak pressure (``field: pressure``, threshold in
  kPa, AIMEC's default 1 kPa) or peak thickness (``field: thickness``, threshold in m,
  default the run's ``runout_threshold``) reaches the threshold, the one farthest along the
  path; its ``s``, ``l``, x, y and bed elevation;
- the **runout angle** ``alpha = atan(drop / length)`` from the highest released cell to
  the runout point, with ``length`` its distance along the path (``s_runout - s_top``) and
  ``drop`` the difference of their bed elevations.

Pure functions work on arrays (:class:`PathLine`, :func:`analyse`); :func:`run_points`
reads a run file, :func:`analyse_target` is ``avflow path``, :func:`ensemble_path` adds the
per-member columns to an ensemble's table and ``ensemble.nc``. Errors are one-line
:class:`PathError` (exit code 2).
"""

from __future__ import annotations

import csv
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from avflow.errors import AvflowError
from avflow.files import atomic_write, inputs_of, protected

__all__ = ["FIELDS", "LINE_SUFFIXES", "PathError", "PathLine", "PathResult", "PathSettings",
           "RunPoints", "analyse", "analyse_run", "analyse_target", "com_path",
           "ensemble_path", "read_line", "run_points"]

#: ``field`` -> (variable of the run file, factor from its units to the threshold's, units)
FIELDS = {"pressure": ("peak_pressure", 1e-3, "kPa"),
          "thickness": ("peak_thickness", 1.0, "m")}
#: ``--line com``: the centre-of-mass track even where the scenario names a line.
COM = "com"
#: AIMEC's default pressure limit (kPa).
DEFAULT_PRESSURE_KPA = 1.0
#: The summary of the horizontal distance from the release centroid to the farthest deposit.
_REACH = "reach_from_release_centroid"
LINE_SUFFIXES = (".shp", ".geojson", ".json", ".csv")
#: The fields projected along the path (run-file variables) and their short names.
PROFILE_FIELDS = {"peak_pressure": "pressure", "peak_speed": "speed",
                  "peak_thickness": "thickness"}


class PathError(AvflowError):
    """A path line or a run that cannot be analysed along the path; one line, exit 2."""


# =========================================================================================
# The path line and the projection onto (s, l)
# =========================================================================================


@dataclass(frozen=True, eq=False)
class PathLine:
    """A horizontal polyline (vertices ``x, y`` in the map's CRS, m) and where it came from."""

    x: np.ndarray
    y: np.ndarray
    source: str = "line"

    def __post_init__(self):
        x, y = np.asarray(self.x, dtype=float), np.asarray(self.y, dtype=float)
        if x.shape != y.shape or x.ndim != 1 or not (np.isfinite(x).all()
                                                     and np.isfinite(y).all()):
            raise PathError(f"{self.source}: a path needs finite x, y vertices")
        keep = np.ones(x.size, bool)
        with np.errstate(over="ignore", invalid="ignore"):  # huge coordinates: refused below
            keep[1:] = ~(np.hypot(np.diff(x), np.diff(y)) == 0.0)  # drop repeated vertices
        x, y = x[keep], y[keep]
        if x.size < 2:
            raise PathError(f"{self.source}: a path needs at least 2 distinct vertices")
        with np.errstate(over="ignore"):
            length = np.hypot(np.diff(x), np.diff(y)).sum()
        if not np.isfinite(length):
            raise PathError(f"{self.source}: vertices so far apart that their distance "
                            "overflows (coordinates near 1e308?)")
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "y", y)

    @property
    def s(self) -> np.ndarray:
        """Horizontal distance along the line at each vertex (0 at the first)."""
        return np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(self.x), np.diff(self.y)))])

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def project(self, px, py, chunk: int = 1 << 21) -> tuple[np.ndarray, np.ndarray]:
        """``(s, l)`` of points: distance along the line to the nearest point on it, and the
        signed distance from it (positive on the left of the direction of travel). The
        first and last segments continue straight beyond the line's ends."""
        px, py = np.asarray(px, dtype=float).ravel(), np.asarray(py, dtype=float).ravel()
        x0, y0 = self.x[:-1], self.y[:-1]
        dx, dy = np.diff(self.x), np.diff(self.y)
        seg = np.hypot(dx, dy)
        ux, uy = dx / seg, dy / seg
        s0 = self.s[:-1]
        lo = np.zeros(seg.size)
        hi = seg.copy()
        lo[0], hi[-1] = -np.inf, np.inf  # straight continuation beyond the ends
        s_out, l_out = np.empty(px.size), np.empty(px.size)
        step = max(1, chunk // seg.size)
        for a in range(0, px.size, step):
            qx = px[a:a + step, None] - x0
            qy = py[a:a + step, None] - y0
            along = np.clip(qx * ux + qy * uy, lo, hi)
            across = ux * qy - uy * qx
            dist2 = (qx - along * ux) ** 2 + (qy - along * uy) ** 2
            k = np.argmin(dist2, axis=1)
            rows = np.arange(k.size)
            t = along[rows, k]
            s_out[a:a + step] = s0[k] + t
            # nearest to a vertex (outside of a bend): l is the signed distance to it, on
            # the side given by the mean of the two segments' directions
            v = np.where(t <= 0.0, k, k + 1)
            corner = ((t <= 0.0) & (k > 0)) | ((t >= seg[k]) & (k < seg.size - 1))
            if corner.any():
                vc = v[corner]
                tx, ty = ux[vc - 1] + ux[vc], uy[vc - 1] + uy[vc]
                qx_, qy_ = px[a:a + step][corner] - self.x[vc], py[a:a + step][corner] - self.y[vc]
                side = np.sign(tx * qy_ - ty * qx_)
                across[rows[corner], k[corner]] = side * np.sqrt(dist2[rows[corner], k[corner]])
            l_out[a:a + step] = across[rows, k]
        return s_out, l_out

    def at(self, s) -> tuple[np.ndarray, np.ndarray]:
        """Map coordinates of the points at distances ``s`` along the line (extended
        straight beyond its ends)."""
        s = np.asarray(s, dtype=float)
        vs = self.s
        k = np.clip(np.searchsorted(vs, s, side="right") - 1, 0, vs.size - 2)
        t = (s - vs[k]) / (vs[k + 1] - vs[k])
        return (self.x[k] + t * (self.x[k + 1] - self.x[k]),
                self.y[k] + t * (self.y[k + 1] - self.y[k]))


def read_line(path) -> PathLine:
    """The path line of a file: a shapefile (.shp, one line), GeoJSON (.geojson/.json: a
    LineString, or a Feature / FeatureCollection holding one) or CSV (.csv: columns ``x``
    and ``y`` by header, else the first two columns)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in LINE_SUFFIXES:
        raise PathError(f"{path}: a path line must be a {', '.join(LINE_SUFFIXES)} file")
    if not path.is_file():
        raise PathError(f"{path}: no such file")
    try:
        points = {".shp": _shapefile_points, ".geojson": _geojson_points,
                  ".json": _geojson_points, ".csv": _csv_points}[suffix](path)
    except PathError:
        raise
    except Exception as err:  # noqa: BLE001 - a damaged file: say which
        raise PathError(f"{path}: cannot be read as a path line "
                        f"({type(err).__name__}: {' '.join(str(err).split())[:80]})") from None
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[0] < 2 or points.shape[1] < 2:
        raise PathError(f"{path}: a path line needs at least 2 vertices")
    return PathLine(points[:, 0], points[:, 1], source=str(path))


def _shapefile_points(path: Path):
    import shapefile  # pyshp

    with shapefile.Reader(str(path)) as reader:
        lines = [s for s in reader.shapes() if s.shapeType != shapefile.NULL]
    if not lines:
        raise PathError(f"{path}: holds no line")
    kinds = {shapefile.POLYLINE, shapefile.POLYLINEZ, shapefile.POLYLINEM}
    if lines[0].shapeType not in kinds:
        raise PathError(f"{path}: holds {lines[0].shapeTypeName} shapes, not a line")
    if len(lines) != 1 or len(lines[0].parts) != 1:
        raise PathError(f"{path}: holds {sum(len(s.parts) for s in lines)} lines; keep the "
                        "avalanche path alone in its file")
    return [p[:2] for p in lines[0].points]


def _geojson_points(path: Path):
    data = json.loads(path.read_text(encoding="utf-8-sig"))
    geometries = []

    def collect(obj):
        kind = obj.get("type") if isinstance(obj, dict) else None
        if kind == "FeatureCollection":
            for feature in obj.get("features") or []:
                collect(feature)
        elif kind == "Feature":
            if obj.get("geometry"):
                collect(obj["geometry"])
        elif kind == "LineString":
            geometries.append(obj["coordinates"])
        elif kind == "MultiLineString":
            geometries.extend(obj["coordinates"])
        elif kind is not None:
            raise PathError(f"{path}: holds a {kind}, not a line")
        else:
            raise PathError(f"{path}: not GeoJSON (no 'type')")

    collect(data)
    if len(geometries) != 1:
        raise PathError(f"{path}: holds {len(geometries)} lines; keep the avalanche path "
                        "alone in its file")
    return [p[:2] for p in geometries[0]]


def _csv_points(path: Path):
    with open(path, newline="", encoding="utf-8-sig") as f:
        rows = [r for r in csv.reader(f) if r and any(c.strip() for c in r)]
    if not rows:
        raise PathError(f"{path}: empty")
    header = [c.strip().lower() for c in rows[0]]
    try:
        [float(c) for c in rows[0][:2]]
        ix, iy, body = 0, 1, rows
    except ValueError:
        if "x" in header and "y" in header:
            ix, iy = header.index("x"), header.index("y")
        else:
            ix, iy = 0, 1
        body = rows[1:]
    points = []
    for n, r in enumerate(body, start=len(rows) - len(body) + 1):
        for name, i in (("x", ix), ("y", iy)):
            if i >= len(r):
                raise PathError(f"{path}:{n}: no {name} (column {i + 1}); each line needs "
                                "x, y") from None
            try:
                float(r[i])
            except ValueError:  # the field and a few characters, never the user's line
                raise PathError(f"{path}:{n}: {name} (column {i + 1}) is not a number: "
                                f"{_few(r[i])}") from None
        points.append((float(r[ix]), float(r[iy])))
    return points


def _few(text: str, n: int = 12) -> str:
    """At most ``n`` characters of a value from a user's file, quoted."""
    text = text.strip()
    return repr(text if len(text) <= n else text[:n] + "...")


def com_path(com_x, com_y, top_x: float, top_y: float, spacing: float) -> PathLine:
    """The centre-of-mass track as a path: one vertex per ``spacing`` of travel at least,
    extended straight upslope so that the top of the release (``top_x, top_y``) lies at
    ``s = 0``."""
    x, y = np.asarray(com_x, dtype=float), np.asarray(com_y, dtype=float)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size == 0:
        raise PathError("the run has no centre-of-mass track: give a path line")
    keep = [0]
    for k in range(1, x.size):
        if math.hypot(x[k] - x[keep[-1]], y[k] - y[keep[-1]]) >= spacing:
            keep.append(k)
    if len(keep) < 2:
        raise PathError("the centre of mass moved less than two cells: no path to follow; "
                        "give a path line")
    x, y = x[keep], y[keep]
    ux, uy = x[1] - x[0], y[1] - y[0]
    norm = math.hypot(ux, uy)
    back = ((top_x - x[0]) * ux + (top_y - y[0]) * uy) / norm  # < 0: the top lies upslope
    if back < 0.0:
        x = np.concatenate([[x[0] + back * ux / norm], x])
        y = np.concatenate([[y[0] + back * uy / norm], y])
    return PathLine(x, y, source="centre-of-mass track")


# =========================================================================================
# A run's cells, and the analysis along the path
# =========================================================================================


@dataclass(eq=False)
class RunPoints:
    """The cells (or mesh nodes) of a run: where they are and what the run left there."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray                     #: bed elevation
    fields: dict                      #: peak_pressure (Pa), peak_speed, peak_thickness
    released: np.ndarray              #: thickness > 0 at t = 0
    spacing: float                    #: cell size (m)
    com_x: np.ndarray | None = None
    com_y: np.ndarray | None = None
    kind: str = "grid"                #: grid, profile or triangles
    name: str = ""
    runout_threshold: float = math.nan  #: the run's, m (default of field: thickness)
    farthest_runout: float = math.nan   #: the run's ``runout`` summary
    grid: tuple | None = None         #: (x, y, bed(y, x)) of a grid, for maps
    truncated: bool = False           #: the run's runout_truncated: the flow left the map


@dataclass(frozen=True)
class PathSettings:
    """What to analyse: the line file (None: the centre-of-mass track), the field and its
    threshold (None: 1 kPa for pressure, the run's runout threshold for thickness) and the
    width of the band around the line (None: every cell)."""

    line: str | None = None
    field: str = "pressure"
    threshold: float | None = None
    width: float | None = None
    regression: str | None = None  #: alpha-beta regression (None: the Norwegian one)

    def __post_init__(self):
        if self.field not in FIELDS:
            raise PathError(f"field must be one of {', '.join(FIELDS)}, got {self.field!r}")
        for name in ("threshold", "width"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise PathError(f"{name} must be a number > 0, got {value:g}")
        if self.regression is not None:
            from avflow.output.alphabeta import regression

            regression(self.regression)  # a bad one: one line before anything is read

    @classmethod
    def from_scenario(cls, block) -> "PathSettings":
        """From a scenario's ``output.path`` block (or None: the defaults)."""
        if block is None:
            return cls()
        return cls(line=block.line, field=block.field, threshold=block.threshold,
                   width=block.width, regression=getattr(block, "alpha_beta", None))

    def threshold_for(self, points: RunPoints) -> float:
        if self.threshold is not None:
            return float(self.threshold)
        return DEFAULT_PRESSURE_KPA if self.field == "pressure" else points.runout_threshold


@dataclass(eq=False)
class PathResult:
    """The path, the settings and what was found along it (scalars NaN when no cell reaches
    the threshold)."""

    line: PathLine
    field: str
    threshold: float
    units: str
    width: float | None
    s: np.ndarray                 #: (n,) per cell
    l: np.ndarray                 #: (n,) per cell
    runout_index: int | None
    top_index: int | None
    scalars: dict
    profile: dict = field(default_factory=dict)  #: s, x, y, z and the cross-section maxima
    alpha_beta: object = None     #: :class:`avflow.output.alphabeta.ABResult` (a top found)

    def row(self) -> dict:
        """The per-run columns of a table (``path_*``)."""
        return {f"path_{k}": v for k, v in self.scalars.items()}


#: The scalars of a result: name -> (units, description), in table order.
SCALARS = {
    "runout_s": ("m", "distance along the path of the runout point"),
    "runout_length": ("m", "distance along the path from the top of the release to the "
                           "runout point (s_runout - s_top)"),
    "runout_angle": ("degree", "alpha = atan(drop / runout_length), top of the release to "
                               "the runout point"),
    "drop": ("m", "bed elevation of the top of the release minus that of the runout point"),
    "runout_x": ("m", "x of the runout point (the cell farthest along the path whose field "
                      "reaches the threshold)"),
    "runout_y": ("m", "y of the runout point"),
    "runout_l": ("m", "signed distance of the runout point from the path (left > 0)"),
    "runout_z": ("m", "bed elevation of the runout point"),
    "top_s": ("m", "distance along the path of the highest released cell"),
    "top_z": ("m", "bed elevation of the highest released cell"),
    "max_pressure": ("kPa", "largest peak pressure within the band around the path"),
    "max_speed": ("m s-1", "largest peak speed within the band around the path"),
    "max_thickness": ("m", "largest peak thickness within the band around the path"),
    "ab_beta": ("degree", "alpha-beta model: beta, the angle from the top of the release to "
                          "the first point where the path's slope falls to 10 degrees"),
    "ab_beta_s": ("m", "distance along the path of the beta (10 degree) point"),
    "ab_beta_z": ("m", "bed elevation of the beta point"),
    "ab_alpha": ("degree", "alpha-beta model: the regression's runout angle alpha"),
    "ab_alpha_s": ("m", "distance along the path where the alpha line meets the bed"),
    "ab_alpha_z": ("m", "bed elevation there"),
    "ab_alpha_m1sd": ("degree", "alpha minus one standard deviation of the regression"),
    "ab_alpha_m1sd_s": ("m", "distance along the path where that line meets the bed"),
    "ab_alpha_m1sd_z": ("m", "bed elevation there"),
    "ab_alpha_m2sd": ("degree", "alpha minus two standard deviations of the regression"),
    "ab_alpha_m2sd_s": ("m", "distance along the path where that line meets the bed"),
    "ab_alpha_m2sd_z": ("m", "bed elevation there"),
}


def analyse(points: RunPoints, line: PathLine, field: str = "pressure",
            threshold: float | None = None, width: float | None = None,
            bin_size: float | None = None, regression=None, profiles: bool = True
            ) -> PathResult:
    """The run ``points`` along ``line``: runout point, alpha, maxima, cross-section profiles,
    and the alpha-beta model's angles and points from the top of the release
    (``regression``: :func:`avflow.output.alphabeta.regression`); ``profiles=False``: the
    runout point, alpha and maxima only."""
    settings = PathSettings(None, field, threshold, width)
    threshold = settings.threshold_for(points)
    variable, factor, units = FIELDS[field]
    _near_the_map(points, line)
    s, l = line.project(points.x, points.y)
    inside = np.ones(s.size, bool) if width is None else np.abs(l) <= 0.5 * width
    values = np.asarray(points.fields[variable], dtype=float) * factor
    with np.errstate(invalid="ignore"):
        above = inside & (values >= threshold)
    nan = math.nan
    sc = dict.fromkeys(SCALARS, nan)
    top = None
    if points.released.any():
        rel = np.flatnonzero(points.released)
        top = int(rel[np.argmax(points.z[rel])])
        sc.update(top_s=float(s[top]), top_z=float(points.z[top]))
    run = None
    if above.any():
        cand = np.flatnonzero(above)
        run = int(cand[np.argmax(s[cand])])
        sc.update(runout_s=float(s[run]), runout_x=float(points.x[run]),
                  runout_y=float(points.y[run]), runout_l=float(l[run]),
                  runout_z=float(points.z[run]))
        if top is not None:
            length = sc["runout_s"] - sc["top_s"]
            drop = sc["top_z"] - sc["runout_z"]
            sc.update(runout_length=length, drop=drop,
                      runout_angle=math.degrees(math.atan2(drop, length)) if length > 0
                      else nan)
    for variable_name, short in PROFILE_FIELDS.items():
        v = np.asarray(points.fields[variable_name], dtype=float)[inside]
        v = v[np.isfinite(v)]
        scale = 1e-3 if short == "pressure" else 1.0
        sc[f"max_{short}"] = float(v.max() * scale) if v.size else nan
    result = PathResult(line, field, threshold, units, width, s, l, run, top, sc)
    if not profiles:  # the runout point alone (a run's headline): no sections, no alpha-beta
        return result
    result.profile = cross_sections(points, result, inside, bin_size or points.spacing)
    if top is not None:
        result.alpha_beta = path_alpha_beta(points, line, sc["top_s"], sc["top_z"],
                                            regression)
        sc.update(alpha_beta_scalars(result.alpha_beta))
    return result


def bed_along(points: RunPoints, line: PathLine, s) -> np.ndarray:
    """The bed elevation on the line at distances ``s`` (bilinear on a grid, linear on a
    profile or a triangle mesh; NaN off the map)."""
    s = np.asarray(s, dtype=float)
    x, y = line.at(s)
    if points.kind == "profile":
        return np.interp(x, points.x, points.z, left=np.nan, right=np.nan)
    if points.grid is not None:
        from scipy.interpolate import RegularGridInterpolator

        xg, yg, bed = points.grid
        if yg[0] > yg[-1]:
            yg, bed = yg[::-1], bed[::-1]
        if xg[0] > xg[-1]:
            xg, bed = xg[::-1], bed[:, ::-1]
        f = RegularGridInterpolator((yg, xg), bed, bounds_error=False, fill_value=np.nan)
        return f(np.column_stack([y, x]))
    from scipy.interpolate import LinearNDInterpolator

    return LinearNDInterpolator(np.column_stack([points.x, points.y]), points.z)(x, y)


def path_alpha_beta(points: RunPoints, line: PathLine, s_top: float, z_top: float,
                    regression=None):
    """The alpha-beta model from the top of the release (its highest cell, ``s_top``,
    ``z_top``: the dynamic runout angle's top too) along the bed on the line, sampled every
    half cell to the line's end or the map's edge (a stretch of the line off the map just
    below the top, as a centre-of-mass track's upslope extension can be, is skipped)."""
    from avflow.output.alphabeta import alpha_beta

    step = 0.5 * points.spacing
    s_end = max(line.length, float(np.nanmax(line.project(points.x, points.y)[0])))
    s = s_top + step * np.arange(1, max(int((s_end - s_top) / step) + 1, 1))
    z = bed_along(points, line, s)
    on = np.flatnonzero(np.isfinite(z))
    if on.size:
        s, z = s[on[0]:], z[on[0]:]
    return alpha_beta(np.concatenate([[s_top], s]), np.concatenate([[z_top], z]), regression)


def alpha_beta_scalars(ab) -> dict:
    """The ``ab_*`` scalars of an alpha-beta result (angles in degrees, s along the path)."""
    out = {"ab_beta": ab.beta, "ab_beta_s": ab.beta_s, "ab_beta_z": ab.beta_z}
    for label, a, s_, z_ in zip(ab.LABELS, ab.alphas, ab.points_s, ab.points_z):
        out[f"ab_{label}"] = a
        out[f"ab_{label}_s"] = s_
        out[f"ab_{label}_z"] = z_
    return out


def _near_the_map(points: RunPoints, line: PathLine) -> None:
    """A line that passes nowhere near the cells is in another CRS or mistyped: refused, not
    answered with "no cell reaches the threshold"."""
    x0, x1 = float(np.nanmin(points.x)), float(np.nanmax(points.x))
    y0, y1 = float(np.nanmin(points.y)), float(np.nanmax(points.y))
    pad = max(x1 - x0, y1 - y0, points.spacing)  # a line may start or end off the map
    if (line.x.max() < x0 - pad or line.x.min() > x1 + pad
            or line.y.max() < y0 - pad or line.y.min() > y1 + pad):
        raise PathError(f"{line.source}: the path line (x {line.x.min():.6g} to "
                        f"{line.x.max():.6g}, y {line.y.min():.6g} to {line.y.max():.6g}) lies "
                        f"outside the map (x {x0:.6g} to {x1:.6g}, y {y0:.6g} to {y1:.6g}); "
                        "is it in the DEM's CRS?")


def cross_sections(points: RunPoints, result: PathResult, inside: np.ndarray,
                   bin_size: float) -> dict:
    """AIMEC's ``A_cross^max(s)``: in bins of ``bin_size`` along the path (centred on
    multiples of it, so that runs on one grid share their bins), the maximum over the
    cross-section of each peak field, and the bed elevation of the cell nearest the line."""
    s, l = result.s[inside], result.l[inside]
    if s.size == 0:
        return {"s": np.zeros(0)}
    k = np.floor(s / bin_size + 0.5).astype(np.int64)
    k0 = int(k.min())
    k -= k0
    n = int(k.max()) + 1
    centres = (np.arange(n) + k0) * bin_size
    out = {"s": centres}
    x, y = result.line.at(centres)
    out["x"], out["y"] = x, y
    for variable_name, short in PROFILE_FIELDS.items():
        v = np.asarray(points.fields[variable_name], dtype=float)[inside]
        if short == "pressure":
            v = v * 1e-3
        m = np.full(n, -np.inf)
        ok = np.isfinite(v)
        np.maximum.at(m, k[ok], v[ok])
        out[short] = np.where(np.isfinite(m), m, np.nan)
    order = np.lexsort((np.abs(l), k))  # per bin, the cell nearest the line first
    first = order[np.r_[True, np.diff(k[order]) != 0]]
    z = np.full(n, np.nan)
    z[k[first]] = points.z[inside][first]
    out["z"] = z
    return out


def run_points(ds) -> RunPoints:
    """The cells of an ``avflow run`` Dataset (grid, profile or triangle mesh)."""
    from avflow.output.maps import scene_kind

    kind = scene_kind(ds)
    h0 = np.asarray(ds["h"].isel(time=0).values, dtype=float)
    names = ("peak_pressure", "peak_speed", "peak_thickness")
    if kind == "grid":
        xg, yg = ds["x"].values.astype(float), ds["y"].values.astype(float)
        bed = ds["bed_elevation"].values.astype(float)
        X, Y = np.meshgrid(xg, yg)
        on = np.isfinite(bed)
        x, y, z = X[on], Y[on], bed[on]
        fields = {n: ds[n].values.astype(float)[on] for n in names}
        released = np.nan_to_num(h0[on]) > 0.0
        spacing = float(min(abs(xg[1] - xg[0]), abs(yg[1] - yg[0])))
        grid = (xg, yg, bed)
    elif kind == "profile":
        xh = ds["x_horizontal"].values.astype(float)
        x, y, z = xh, np.zeros_like(xh), ds["bed_elevation"].values.astype(float)
        fields = {n: ds[n].values.astype(float) for n in names}
        released = np.nan_to_num(h0) > 0.0
        spacing = float(np.median(np.diff(xh)))
        grid = None
    elif kind == "triangles":
        x = ds["mesh_node_x"].values.astype(float)
        y = ds["mesh_node_y"].values.astype(float)
        z = ds["bed_elevation"].values.astype(float)
        fields = {n: ds[n].values.astype(float) for n in names}
        released = np.nan_to_num(h0) > 0.0
        area = ds["cell_area"].values if "cell_area" in ds else None
        spacing = float(math.sqrt(np.median(area))) if area is not None else 1.0
        grid = None
    else:
        raise PathError("unknown scene layout: cannot follow a path")
    com = [ds[f"center_of_mass_{a}"].values.astype(float) if f"center_of_mass_{a}" in ds
           else None for a in "xy"]
    if kind == "profile" and com[0] is not None:  # the profile's x is along the bed
        com[0] = np.interp(com[0], ds["x"].values.astype(float), xh)
        com[1] = np.zeros_like(com[0])
    return RunPoints(x, y, z, fields, released, spacing, com[0], com[1], kind,
                     str(ds.attrs.get("scenario_name", "")),
                     float(ds.attrs.get("runout_threshold_m", math.nan)),
                     float(ds[_REACH] if _REACH in ds else ds["runout"]) if "runout" in ds
                     else math.nan, grid,
                     bool(int(ds.attrs.get("runout_truncated", 0))))


def path_for(points: RunPoints, line_file: str | None) -> PathLine:
    """The line of a file, or the run's own path: the profile itself, or its centre-of-mass
    track on a map."""
    if points.kind == "profile":
        if line_file is not None:
            raise PathError(f"{line_file}: a profile is its own path; a line file applies to "
                            "maps only")
        return PathLine(points.x[[0, -1]], np.zeros(2), source="the profile")
    if line_file is not None:
        return read_line(line_file)
    if points.com_x is None:
        raise PathError("the run file has no centre-of-mass track: give a path line")
    top_x, top_y = _top(points)
    return com_path(points.com_x, points.com_y, top_x, top_y, 2.0 * points.spacing)


def _top(points: RunPoints) -> tuple[float, float]:
    if not points.released.any():
        return float(points.com_x[0]), float(points.com_y[0])
    rel = np.flatnonzero(points.released)
    top = rel[np.argmax(points.z[rel])]
    return float(points.x[top]), float(points.y[top])


def analyse_run(ds, settings: PathSettings | None = None, line: PathLine | None = None
                ) -> tuple[RunPoints, PathResult]:
    """A run Dataset along its path (``line``, else the settings' line file, else its own)."""
    settings = settings or PathSettings()
    points = run_points(ds)
    if line is None:
        line = path_for(points, settings.line)
    return points, analyse(points, line, settings.field, settings.threshold_for(points),
                           settings.width, regression=settings.regression)


# =========================================================================================
# Tables and figures
# =========================================================================================


def _fmt(v) -> str:
    if isinstance(v, float):
        return "NaN" if math.isnan(v) else f"{0.0 if abs(v) < 1e-9 else v:.6g}"
    return str(v)


def _settings_columns(result: PathResult) -> dict:
    ab = result.alpha_beta
    return {"path_source": result.line.source, "path_field": result.field,
            "path_threshold": result.threshold, "path_threshold_units": result.units,
            "path_width": math.nan if result.width is None else result.width,
            "path_ab_regression": "" if ab is None else ab.regression.name}


def _write_tables(rows: list[dict], stem: Path) -> list[Path]:
    import pandas as pd

    table = pd.DataFrame.from_records(rows)
    csv_path, md_path = stem.with_suffix(".csv"), stem.with_suffix(".md")
    atomic_write(csv_path, lambda tmp: table.to_csv(tmp, index=False))
    shown = [c for c in table.columns if c not in ("path_source", "path_threshold_units",
                                                   "path_width", "path_field",
                                                   "path_threshold", "file",
                                                   "path_ab_regression")
             and not (c.startswith("path_ab_") and c.endswith("_z"))]
    first = rows[0] if rows else {}
    width = first.get("path_width", math.nan)
    band = "every cell" if math.isnan(width) else f"{_fmt(width)} m wide"
    lines = [f"# Runout along the path ({len(rows)} run{'s' * (len(rows) != 1)})", "",
             f"- path: {first.get('path_source', '')}",
             f"- runout point: {first.get('path_field', '')} >= "
             f"{_fmt(first.get('path_threshold', math.nan))} "
             f"{first.get('path_threshold_units', '')}",
             f"- band around the path: {band}",
             "- lengths in m along the path (horizontal), angles in degrees, pressure in kPa",
             *_regression_lines(first.get("path_ab_regression", "")),
             "", "| " + " | ".join(c.removeprefix("path_") for c in shown) + " |",
             "|" + "---|" * len(shown)]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r.get(c, "")) for c in shown) + " |")
    atomic_write(md_path, lambda tmp: Path(tmp).write_text("\n".join(lines) + "\n"))
    return [csv_path, md_path]


def _regression_lines(name: str) -> list[str]:
    """The alpha-beta regression the ``ab_*`` columns used, with its source."""
    if not name:
        return []
    from avflow.output.alphabeta import REGRESSIONS

    reg = REGRESSIONS.get(name)
    source = reg.source if reg is not None else "the user's coefficients"
    return [f"- alpha-beta (ab_*): regression {name}: {source}; beta point: the path's "
            "slope first at 10 degrees or less (for 30 m on); the ab_*_s columns are where "
            "each alpha line from the top of the release meets the bed"]


def _write_profiles(profiles: list[tuple[object, dict]], target: Path) -> Path:
    import pandas as pd

    frames = []
    for key, prof in profiles:
        frame = pd.DataFrame({k: prof[k] for k in ("s", "x", "y", "z", "pressure", "speed",
                                                     "thickness") if k in prof})
        frame = frame.rename(columns={"pressure": "pressure_max_kPa",
                                      "speed": "speed_max_m_s", "thickness": "thickness_max_m",
                                      "z": "bed_elevation"})
        if key is not None:
            frame.insert(0, "realization", key)
        frames.append(frame)
    table = pd.concat(frames, ignore_index=True)
    atomic_write(target, lambda tmp: table.to_csv(tmp, index=False))
    return target


def check_path_outputs(stem, inputs=()) -> None:
    """Refuse, before anything runs, files of the analysis (``stem``.csv, .md, .png,
    _profile.csv) that would replace one of ``inputs`` or are not regular files."""
    from avflow.files import check_target

    stem = Path(stem)
    for target in (stem.with_suffix(".csv"), stem.with_suffix(".md"), stem.with_suffix(".png"),
                   stem.with_name(stem.name + "_profile.csv")):
        check_target(target, inputs, what="path analysis output")


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def plot_path(points: RunPoints, results: list[tuple[str, PathResult]], target: Path,
              title: str) -> Path:
    """AIMEC's view: the map with the path and the runout points, the chosen field in (s, l)
    (first run), and the cross-section maxima of pressure, speed and thickness against ``s``
    with each run's runout point, over the bed profile with the runout angle."""
    plt = _plt()
    from matplotlib.gridspec import GridSpec

    label0, first = results[0]
    many = len(results) > 1
    # constrained layout keeps the map's x label clear of the panel below and its title
    fig = plt.figure(figsize=(13, 9.5), layout="constrained")
    gs = GridSpec(4, 2, figure=fig, width_ratios=[1, 1.35])
    ax_map = fig.add_subplot(gs[:2, 0])
    ax_sl = fig.add_subplot(gs[2:, 0])
    axes = [fig.add_subplot(gs[0, 1])]
    axes += [fig.add_subplot(gs[i, 1], sharex=axes[0]) for i in (1, 2, 3)]
    variable, factor, units = FIELDS[first.field]
    values = np.asarray(points.fields[variable], dtype=float) * factor
    wet = np.isfinite(values) & (values > 0)

    # map
    if points.kind == "profile":
        ax_map.plot(points.x, points.z, color="0.3", lw=1.5)
        sc = ax_map.scatter(points.x[wet], points.z[wet], c=values[wet], s=8, cmap="viridis",
                            zorder=3)
        fig.colorbar(sc, ax=ax_map, shrink=0.8, label=f"peak {first.field} ({units})")
    elif points.grid is not None:
        from avflow.output.maps import hillshade

        xg, yg, bed = points.grid
        dx, dy = abs(xg[1] - xg[0]), abs(yg[1] - yg[0])
        shade = hillshade(bed, dx, dy)  # rows south to north, as drawn (origin "lower")
        extent = (xg[0] - dx / 2, xg[-1] + dx / 2, yg[0] - dy / 2, yg[-1] + dy / 2)
        ax_map.imshow(shade, cmap="gray", origin="lower", extent=extent, vmin=0, vmax=1)
        full = np.full(bed.shape, np.nan)
        full[np.isfinite(bed)] = np.where(wet, values, np.nan)
        im = ax_map.imshow(full, origin="lower", extent=extent, cmap="viridis", alpha=0.8)
        fig.colorbar(im, ax=ax_map, shrink=0.8, label=f"peak {first.field} ({units})")
    else:
        sc = ax_map.scatter(points.x[wet], points.y[wet], c=values[wet], s=6, cmap="viridis")
        fig.colorbar(sc, ax=ax_map, shrink=0.8, label=f"peak {first.field} ({units})")
    line = first.line
    vertical = "runout_z" if points.kind == "profile" else "runout_y"
    reach = _reach(results, points.spacing)
    if points.kind != "profile":
        ax_map.plot(line.x, line.y, "-", color="tab:red", lw=1.5, label="path")
        ax_map.plot(line.x[0], line.y[0], "o", color="tab:red", ms=4)
        if reach is not None:  # the straight continuations beyond the line's ends
            for a, b in ((reach[0], 0.0), (line.length, reach[1])):
                if b > a:
                    ex, ey = line.at([a, b])
                    ax_map.plot(ex, ey, ":", color="tab:red", lw=1.2)
    for label, r in results:
        if r.runout_index is not None:
            ax_map.plot(r.scalars["runout_x"], r.scalars[vertical], "x", color="k",
                        ms=8 if not many else 5, mew=2 if not many else 1)
    if first.top_index is not None:
        top_v = points.z if points.kind == "profile" else points.y
        ax_map.plot(points.x[first.top_index], top_v[first.top_index], "^", color="w",
                    mec="k", ms=7, label="top of release")
    ax_map.plot([], [], "x", color="k", label="runout point" + "s" * many)
    if points.grid is not None:
        ax_map.set_xlim(extent[0], extent[1])
        ax_map.set_ylim(extent[2], extent[3])
    if points.kind != "profile":
        ax_map.set_aspect("equal")
    ax_map.set_xlabel("x (m)" if points.kind != "profile" else "horizontal distance (m)")
    ax_map.set_ylabel("y (m)" if points.kind != "profile" else "bed elevation (m)")
    ax_map.legend(loc="best", fontsize=8)
    ax_map.set_title("peak field and path")
    ax_map.ticklabel_format(useOffset=False, style="plain")  # UTM, LV95: whole metres

    # the chosen field in path coordinates, first run
    l = first.l
    keep = wet & (np.abs(l) <= (0.5 * first.width if first.width else np.inf))
    if keep.any() and points.kind != "profile":
        img, ext = sl_image(points, first, values, keep)
        im2 = ax_sl.imshow(img, origin="lower", extent=ext, cmap="viridis", aspect="auto")
        fig.colorbar(im2, ax=ax_sl, shrink=0.8, label=f"peak {first.field} ({units})")
        if first.runout_index is not None:
            ax_sl.axvline(first.scalars["runout_s"], color="k", ls="--", lw=1)
            ax_sl.plot(first.scalars["runout_s"], first.scalars["runout_l"], "x", color="k",
                       ms=8, mew=2)
    ax_sl.axhline(0.0, color="tab:red", lw=1)
    ax_sl.set_xlabel("s along the path (m)")
    ax_sl.set_ylabel("l across the path (m, left > 0)")
    ax_sl.set_title(f"in path coordinates{' (' + label0 + ')' if many else ''}")

    # cross-section maxima against s
    colors = plt.cm.viridis(np.linspace(0, 0.9, len(results))) if many else ["tab:blue"]
    rows = (("pressure", "max peak pressure (kPa)"), ("speed", "max peak speed (m/s)"),
            ("thickness", "max peak thickness (m)"))
    for ax, (short, ylabel) in zip(axes, rows):
        for (label, r), color in zip(results, colors):
            prof = r.profile
            if "s" not in prof or prof["s"].size == 0:
                continue
            ax.plot(prof["s"], prof[short], color=color, lw=1 if many else 1.5,
                    label=label if many and short == "pressure" else None)
            if r.runout_index is not None:
                ax.axvline(r.scalars["runout_s"], color=color, ls="--", lw=0.8)
        if short == first.field:
            top = np.nanmax([np.nanmax(r.profile.get(short, [np.nan]), initial=0.0)
                             for _, r in results])
            if top > 100.0 * first.threshold:  # a log scale shows where it crosses
                ax.set_yscale("log")
                ax.set_ylim(first.threshold / 10.0, top * 2.0)
            ax.axhline(first.threshold, color="tab:red", lw=1, ls=":",
                       label=f"threshold {first.threshold:g} {units}")
            ax.legend(fontsize=7, loc="upper right", ncol=2 if many else 1)
        ax.set_ylabel(ylabel, fontsize=9)
        ax.grid(alpha=0.3)
        plt.setp(ax.get_xticklabels(), visible=False)
    axes[0].set_title("maximum over the cross-section (AIMEC), runout point dashed")

    # bed along the path and the runout angle
    ax = axes[3]
    prof = first.profile
    if "z" in prof:
        ax.plot(prof["s"], prof["z"], color="0.3", lw=1.5, label="bed on the path")
    for (label, r), color in zip(results, colors):
        sc = r.scalars
        if not math.isnan(sc["runout_angle"]):
            ax.plot([sc["top_s"], sc["runout_s"]], [sc["top_z"], sc["runout_z"]], "--",
                    color=color, lw=1,
                    label=None if many else f"run: alpha = {sc['runout_angle']:.1f} deg")
            ax.plot(sc["runout_s"], sc["runout_z"], "x", color=color, ms=6, mew=1.5)
    if first.top_index is not None:
        ax.plot(first.scalars["top_s"], first.scalars["top_z"], "^", color="w", mec="k",
                ms=7, label="top of release")
    _plot_alpha_beta(ax, ax_map if points.kind != "profile" else None, first)
    if reach is not None:
        sc = first.scalars
        far = np.nanmax([reach[1], sc.get("ab_alpha_m2sd_s", np.nan) + 3 * points.spacing])
        reach = (reach[0], far)
        ax.set_xlim(*reach)
    ax.set_xlabel("s along the path (m, horizontal)")
    ax.set_ylabel("bed elevation (m)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper right")
    plt.setp(ax.get_xticklabels(), visible=True)
    fig.suptitle(title, fontsize=11)
    try:
        atomic_write(target, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    finally:
        plt.close(fig)
    return target


def _plot_alpha_beta(ax, ax_map, result: PathResult) -> None:
    """The beta point and the alpha, alpha - 1 SD and alpha - 2 SD lines from the top of the
    release on the bed panel, and their points on the map."""
    ab = result.alpha_beta
    if ab is None or math.isnan(ab.beta):
        return
    sc = result.scalars
    s0, z0 = ab.points_s, ab.points_z
    top_s = sc["top_s"]
    top_z = sc["ab_beta_z"] + math.tan(math.radians(ab.beta)) * (ab.beta_s - top_s)
    ax.plot([top_s, ab.beta_s], [top_z, ab.beta_z], ":", color="tab:purple", lw=1)
    ax.plot(ab.beta_s, ab.beta_z, "D", color="tab:purple", ms=5,
            label=f"beta = {ab.beta:.1f} deg (10 deg point)")
    styles = (("tab:orange", f"alpha-beta ({ab.regression.name}): alpha"),
              ("tab:red", "alpha-1SD"), ("darkred", "alpha-2SD"))
    for a, s_, z_, (color, name) in zip(ab.alphas, s0, z0, styles):
        if math.isnan(s_):
            continue
        ax.plot([top_s, s_], [top_z, z_], "-", color=color, lw=0.8, alpha=0.7)
        ax.plot(s_, z_, "o", color=color, ms=5, label=f"{name} = {a:.1f} deg")
        if ax_map is not None:
            x, y = result.line.at([s_])
            ax_map.plot(x, y, "o", color=color, mec="k", ms=5)
    if ax_map is not None:
        x, y = result.line.at([ab.beta_s])
        ax_map.plot(x, y, "D", color="tab:purple", mec="k", ms=5)


def _reach(results, spacing: float):
    """The range of s the flows covered (with a margin), or None."""
    lo, hi = math.inf, -math.inf
    for _, r in results:
        prof = r.profile
        if prof.get("s") is None or prof["s"].size == 0:
            continue
        wet = (np.nan_to_num(prof["thickness"]) > 0) | (np.nan_to_num(prof["speed"]) > 0)
        if wet.any():
            lo, hi = min(lo, prof["s"][wet].min()), max(hi, prof["s"][wet].max())
    if not math.isfinite(lo):
        return None
    margin = max(5.0 * spacing, 0.08 * (hi - lo))
    return lo - margin, hi + margin


def sl_image(points: RunPoints, result: PathResult, values: np.ndarray, keep: np.ndarray):
    """``values`` resampled on a regular (l, s) raster of one cell size (AIMEC's deskewed
    raster): each node takes the value of the cell nearest to ``line(s) + l n(s)``, with
    ``n`` the left normal of the line between ``s -+ one cell``. Returns (image, extent)."""
    bs = points.spacing
    s_nodes = bs * np.arange(np.floor(result.s[keep].min() / bs),
                             np.ceil(result.s[keep].max() / bs) + 1)
    half = np.abs(result.l[keep]).max() + bs
    l_nodes = bs * np.arange(-np.ceil(half / bs), np.ceil(half / bs) + 1)
    x0, y0 = result.line.at(s_nodes)
    xa, ya = result.line.at(s_nodes - bs)
    xb, yb = result.line.at(s_nodes + bs)
    tx, ty = xb - xa, yb - ya
    norm = np.hypot(tx, ty)
    nx, ny = -ty / norm, tx / norm
    gx = x0[None, :] + l_nodes[:, None] * nx[None, :]
    gy = y0[None, :] + l_nodes[:, None] * ny[None, :]
    shown = np.where(keep, values, np.nan)
    if points.grid is not None:
        xg, yg, bed = points.grid
        ix = np.rint((gx - xg[0]) / (xg[1] - xg[0])).astype(np.int64)
        iy = np.rint((gy - yg[0]) / (yg[1] - yg[0])).astype(np.int64)
        ok = (ix >= 0) & (ix < xg.size) & (iy >= 0) & (iy < yg.size)
        full = np.full(bed.shape, np.nan)
        full[np.isfinite(bed)] = shown
        img = np.full(gx.shape, np.nan)
        img[ok] = full[iy[ok], ix[ok]]
    else:
        from scipy.spatial import cKDTree

        dist, k = cKDTree(np.column_stack([points.x, points.y])).query(
            np.column_stack([gx.ravel(), gy.ravel()]))
        img = np.where(dist <= bs, shown[k], np.nan).reshape(gx.shape)
    ext = (s_nodes[0] - bs / 2, s_nodes[-1] + bs / 2, l_nodes[0] - bs / 2, l_nodes[-1] + bs / 2)
    return img, ext


def _title(result: PathResult, name: str) -> str:
    sc = result.scalars
    what = f"{result.field} >= {result.threshold:g} {result.units}"
    if math.isnan(sc["runout_s"]):
        return f"{name}: no cell reaches {what} along the path"
    return (f"{name}: runout ({what}) at s = {sc['runout_s']:.1f} m, "
            f"{sc['runout_length']:.1f} m from the top of the release, "
            f"alpha = {sc['runout_angle']:.2f} deg")


def alpha_beta_text(result: PathResult) -> str:
    """``; alpha-beta (norway): beta 28.1, alpha 25.6 at s = ...`` or nothing."""
    ab = result.alpha_beta
    if ab is None:
        return ""
    if math.isnan(ab.beta):
        return f"; alpha-beta ({ab.regression.name}): no 10-degree point on the path"

    def at(s_):
        return "beyond the path" if math.isnan(s_) else f"s = {s_:.0f} m"

    a, m1, m2 = ab.alphas
    return (f"; alpha-beta ({ab.regression.name}): beta {ab.beta:.1f} deg, alpha {a:.1f} deg "
            f"at {at(ab.points_s[0])}, alpha-1SD {m1:.1f} at {at(ab.points_s[1])}, "
            f"alpha-2SD {m2:.1f} at {at(ab.points_s[2])}")


def summary_line(result: PathResult, farthest: float = math.nan,
                 truncated: bool = False) -> str:
    """One line: where the runout point lies along the path."""
    sc = result.scalars
    what = f"{result.field} >= {result.threshold:g} {result.units}"
    if math.isnan(sc["runout_s"]):
        return (f"along the path ({result.line.source}): no cell reaches {what}"
                + alpha_beta_text(result))
    text = (f"along the path ({result.line.source}): runout ({what}) at s = "
            f"{sc['runout_s']:.1f} m, {sc['runout_length']:.1f} m from the top of the "
            f"release, alpha {sc['runout_angle']:.2f} deg, max pressure "
            f"{sc['max_pressure']:.3g} kPa, max speed {sc['max_speed']:.3g} m/s")
    if not math.isnan(farthest):
        text += (f" (reach_from_release_centroid, the farthest deposit cell from the "
                 f"release centroid: {farthest:.1f} m)")
    text += alpha_beta_text(result)
    if truncated:
        text += "; a lower bound: the flow reached the edge of the map"
    return text


# =========================================================================================
# avflow path OUT.nc | OUTDIR, avflow run with output.path, ensembles
# =========================================================================================


def write_run_path(ds, settings: PathSettings, stem, inputs=None
                   ) -> tuple[PathResult, list[Path]]:
    """The analysis of one run Dataset: ``stem``.csv, .md, .png and ``stem``_profile.csv;
    none of them may replace one of ``inputs`` (:func:`avflow.files.protected`)."""
    stem = Path(stem)
    check_path_outputs(stem, inputs if inputs is not None else {})
    points, result = analyse_run(ds, settings)
    row = {"run": points.name, **_settings_columns(result), **result.row(),
           "farthest_cell_runout": points.farthest_runout,
           "runout_truncated": int(points.truncated)}
    written = _write_tables([row], stem)
    written.append(_write_profiles([(None, result.profile)],
                                   stem.with_name(stem.name + "_profile.csv")))
    written.append(plot_path(points, [(points.name, result)], stem.with_suffix(".png"),
                             _title(result, points.name)))
    return result, written


def scenario_settings(text: str, near: Path, need_line: bool = True) -> PathSettings:
    """The ``output.path`` block of a scenario's text as stored in a file (defaults when it
    has none); a relative line file is looked for beside ``near``, then in the working
    folder."""
    import yaml

    try:
        data = yaml.safe_load(text or "") or {}
        block = (data.get("output") or {}).get("path")
    except Exception:  # noqa: BLE001 - an odd text: the defaults
        block = None
    if not isinstance(block, dict):
        return PathSettings()
    line = block.get("line") if need_line else None
    if line is not None:
        candidates = [Path(line)] if Path(line).is_absolute() else [near / line, Path(line)]
        found = next((c for c in candidates if c.is_file()), None)
        if found is None:
            raise PathError(f"the run's scenario names output.path.line {line}, not found "
                            "from here: give it with --line")
        line = str(found)
    return PathSettings(line, block.get("field") or "pressure", block.get("threshold"),
                        block.get("width"), block.get("alpha_beta"))


def merge_settings(base: PathSettings, line=None, field=None, threshold=None,
                   width=None, regression=None) -> PathSettings:
    """``base`` with the command line's options on top (another field drops the base's
    threshold: kPa and m do not mix)."""
    if field is not None and field != base.field:
        base = PathSettings(base.line, field, None, base.width, base.regression)
    if line == COM:
        base, line = PathSettings(None, base.field, base.threshold, base.width,
                                  base.regression), None
    return PathSettings(line if line is not None else base.line,
                        field if field is not None else base.field,
                        threshold if threshold is not None else base.threshold,
                        width if width is not None else base.width,
                        regression if regression is not None else base.regression)


def analyse_target(target, line=None, field=None, threshold=None, width=None, output=None,
                   regression=None) -> tuple[str, list[Path]]:
    """``avflow path``: a run file (-> ``OUT_path.*``) or an ensemble folder
    (-> ``OUTDIR/path.*``); returns (summary line, written files)."""
    target = Path(target)
    if line is not None and line != COM and not Path(line).is_file():
        raise PathError(f"{line}: no such file")
    if target.is_dir():
        return _analyse_folder(target, line, field, threshold, width, output, regression)
    from avflow.output.maps import open_run

    with open_run(target) as ds:
        base = PathSettings() if line not in (None, COM) else scenario_settings(
            ds.attrs.get("scenario", ""), target.parent, need_line=line is None)
        settings = merge_settings(base, line, field, threshold, width, regression)
        stem = Path(output) if output else target.with_name(target.stem + "_path")
        inputs = inputs_of(target, ds.attrs)  # the run file and the files it records
        inputs.update(protected([settings.line]))
        result, written = write_run_path(ds, settings, stem, inputs)
        farthest = float(ds[_REACH] if _REACH in ds else ds["runout"]) if "runout" in ds \
            else math.nan
        truncated = bool(int(ds.attrs.get("runout_truncated", 0)))
    return summary_line(result, farthest, truncated), written


def member_labels(table) -> dict[int, str]:
    """realization -> what sets the member apart: its varied parameters (``delta_deg 18``),
    from the dotted columns of summary.csv whose values differ; ``member k`` without any."""
    varied = [c for c in table.columns if "." in c and table[c].nunique(dropna=False) > 1]

    def short(value):
        return f"{value:g}" if isinstance(value, float) else str(value)

    return {int(k): ", ".join(f"{c.rsplit('.', 1)[-1]} {short(row[c])}" for c in varied)
            or f"member {int(k)}" for k, (_, row) in zip(table["realization"], table.iterrows())}


def _analyse_folder(outdir: Path, line, field, threshold, width, output, regression=None):
    import pandas as pd
    import xarray as xr

    summary = outdir / "summary.csv"
    if not summary.is_file():
        if (outdir / "region.zarr").is_dir() or outdir.name == "region.zarr":
            raise PathError(f"{outdir}: a region's maps; avflow path takes a run file or an "
                            f"ensemble folder (avflow plot {outdir} draws the region)")
        raise PathError(f"{outdir}: not a run file nor an ensemble folder (no summary.csv)")
    try:
        table = pd.read_csv(summary, keep_default_na=False, na_values=[""])
        table["realization"], table["file"]  # noqa: B018 - the columns the analysis needs
    except Exception as err:  # noqa: BLE001 - truncated, edited, not a table
        raise PathError(f"{summary}: cannot be read as an avflow summary table "
                        f"({type(err).__name__})") from None
    # The ensemble's own analysis (ensemble.nc) gives the defaults: its path and settings.
    recorded, base, made_from = None, PathSettings(), {}
    ens_nc = outdir / "ensemble.nc"
    if ens_nc.is_file():
        try:
            ens = xr.open_dataset(ens_nc)
        except Exception as err:  # noqa: BLE001 - truncated or foreign
            raise PathError(f"{ens_nc}: cannot be read as NetCDF ({type(err).__name__}); "
                            "run the ensemble again to write it") from None
        with ens:
            a = ens.attrs
            made_from = inputs_of(ens_nc, a)  # the ensemble's own inputs
            if "path_x" in ens and "path_field" in a:
                threshold_set = a.get("path_threshold_setting", "default")
                width_set = float(a.get("path_width_m", math.nan))
                base = PathSettings(None, str(a["path_field"]),
                                    None if threshold_set == "default" else float(threshold_set),
                                    None if math.isnan(width_set) else width_set)
                if line is None or line == COM and "centre-of-mass" in a.get("path_source", ""):
                    recorded = PathLine(ens["path_x"].values, ens["path_y"].values,
                                        source=str(a.get("path_source", "ensemble.nc")))
    settings = merge_settings(base, line, field, threshold, width, regression)
    stem = Path(output) if output else outdir / "path"
    members = [outdir / str(f) for f in table.get("file", ()) if isinstance(f, str) and f]
    check_path_outputs(stem, {**made_from,
                              **protected([summary, ens_nc, settings.line, *members])})
    _, results, rows, points = _ensemble_results(table, outdir, settings, recorded)
    written = _write_tables(rows, stem)
    written.append(_write_profiles([(k, r.profile) for k, r in results],
                                   stem.with_name(stem.name + "_profile.csv")))
    first = results[0][1]
    labels = member_labels(table)
    written.append(plot_path(points, [(labels.get(k, f"member {k}"), r) for k, r in results],
                             stem.with_suffix(".png"),
                             f"{outdir.name}: {len(results)} members along "
                             f"{first.line.source}, {first.field} >= {first.threshold:g} "
                             f"{first.units}"))
    s_run = [r.scalars["runout_s"] for _, r in results]
    alphas = [r.scalars["runout_angle"] for _, r in results]
    text = (f"{len(results)} members along the path ({first.line.source}): runout s "
            f"{np.nanmin(s_run):.1f} to {np.nanmax(s_run):.1f} m, alpha "
            f"{np.nanmin(alphas):.2f} to {np.nanmax(alphas):.2f} deg"
            if np.isfinite(s_run).any() else
            f"{len(results)} members along the path: none reaches the threshold")
    return text, written


def _ensemble_results(table, outdir: Path, settings: PathSettings, line: PathLine | None,
                      points: dict | None = None):
    """Every member with a file, along one path: the line, else the centre-of-mass track of
    the member whose centre of mass travelled farthest. ``points``: realization ->
    :class:`RunPoints` already read from the member files (by the workers, as each member
    finished); the member files not among them are read here."""
    files = [(int(k), outdir / str(f)) for k, f in zip(table["realization"], table["file"])
             if isinstance(f, str) and f]
    if not files:
        raise PathError(f"{outdir}: no member produced a file")
    points = points or {}
    members = {}
    for k, path in files:
        members[k] = points[k] if k in points else member_points(path)
    if line is None:
        if settings.line is not None:
            line = read_line(settings.line)
        else:
            def travel(p):
                if p.com_x is None or p.com_x.size == 0:
                    return -1.0
                return float(np.nanmax(np.hypot(p.com_x - p.com_x[0], p.com_y - p.com_y[0])))
            k_far = max(members, key=lambda k: travel(members[k]))
            line = path_for(members[k_far], None)
            label = member_labels(table).get(k_far, f"member {k_far}")  # its varied values
            named = "" if label == f"member {k_far}" else f", {label}"
            line = PathLine(line.x, line.y, source=f"{line.source} of member {k_far}{named}")
    spacing = min(p.spacing for p in members.values())
    results, rows = [], []
    for k, p in members.items():
        r = analyse(p, line, settings.field, settings.threshold_for(p), settings.width,
                    bin_size=spacing, regression=settings.regression)
        results.append((k, r))
        rows.append({"realization": k, **_settings_columns(r), **r.row(),
                     "farthest_cell_runout": p.farthest_runout})
    return line, results, rows, members[files[0][0]]


def member_points(path) -> RunPoints:
    """:func:`run_points` of a run file (what the ensemble path analysis needs of a member)."""
    import xarray as xr

    try:
        with xr.open_dataset(path, decode_times=False) as ds:
            return run_points(ds)
    except FileNotFoundError:
        raise PathError(f"{path}: member file missing (run the ensemble again to redo "
                        "it)") from None
    except (OSError, ValueError, KeyError, RuntimeError) as err:
        raise PathError(f"{path}: member file cannot be read ({type(err).__name__}: "
                        "truncated or not a run file?); run the ensemble again to redo "
                        "it") from None


def ensemble_path(table, outdir, settings: PathSettings, points: dict | None = None):
    """Add the ``path_*`` columns to an ensemble's member table (in place) and return the
    ``ensemble.nc`` variables: the scalars along ``realization``, the path line and the
    cross-section maxima on a common ``path_s`` axis; attributes record the settings.
    ``points``: realization -> :class:`RunPoints` of members read already (the others are
    read from their files; their peak fields may be float32 holding the same values:
    :func:`analyse` works in float64)."""
    import xarray as xr

    outdir = Path(outdir)
    if not any(isinstance(f, str) and f for f in table["file"]):
        return None  # every member failed: nothing to follow
    line, results, rows, _ = _ensemble_results(table, outdir, settings, None, points)
    n = len(table)
    index = {int(k): i for i, k in enumerate(table["realization"])}
    first = results[0][1]
    for name in SCALARS:
        column = np.full(n, np.nan)
        for k, r in results:
            column[index[k]] = r.scalars[name]
        table[f"path_{name}"] = column
    for name, value in _settings_columns(first).items():
        table[name] = value if name != "path_threshold" else np.nan
    for k, r in results:  # the thickness default is each member's runout threshold
        table.loc[table.index[index[k]], "path_threshold"] = r.threshold
    data = {}
    for name, (units, description) in SCALARS.items():
        data[f"path_{name}"] = ("realization", table[f"path_{name}"].to_numpy(float),
                                {"long_name": name.replace("_", " ") + " (along the path)",
                                 "units": units, "comment": description})
    lo = min(r.profile["s"][0] for _, r in results if r.profile["s"].size)
    hi = max(r.profile["s"][-1] for _, r in results if r.profile["s"].size)
    step = min(p for p in [np.median(np.diff(r.profile["s"])) for _, r in results
                           if r.profile["s"].size > 1] or [1.0])
    s_axis = lo + step * np.arange(int(round((hi - lo) / step)) + 1)
    units = {"pressure": "kPa", "speed": "m s-1", "thickness": "m"}
    for short in ("pressure", "speed", "thickness"):
        values = np.full((n, s_axis.size), np.nan)
        for k, r in results:
            prof = r.profile
            if prof["s"].size:
                j = np.round((prof["s"] - lo) / step).astype(int)
                values[index[k], j] = prof[short]
        data[f"path_peak_{short}"] = (("realization", "path_s"), values, {
            "long_name": f"maximum over the cross-section of peak {short}",
            "units": units[short],
            "comment": "AIMEC's A_cross^max(s): in bins of path_s (one cell) along the path"})
    data["path_x"] = ("path_vertex", line.x, {"long_name": "x of the path's vertices",
                                              "units": "m"})
    data["path_y"] = ("path_vertex", line.y, {"long_name": "y of the path's vertices",
                                              "units": "m"})
    coords = {"path_s": ("path_s", s_axis, {"long_name": "distance along the path "
                                                         "(horizontal)", "units": "m"})}
    data["path_threshold"] = ("realization", table["path_threshold"].to_numpy(float), {
        "long_name": f"threshold of peak {first.field} marking the runout point",
        "units": first.units})
    attrs = {"path_source": line.source, "path_field": first.field,
             "path_threshold_setting": ("default" if settings.threshold is None
                                        else float(settings.threshold)),
             "path_threshold_units": first.units,
             "path_width_m": math.nan if first.width is None else first.width}
    return xr.Dataset(data, coords=coords, attrs=attrs)


# =========================================================================================
# The headline runout of a run: s along the path at the pressure limit (as AIMEC)
# =========================================================================================


def result_points(result) -> RunPoints:
    """The cells of a run result on a grid (before it becomes a Dataset)."""
    terrain, state = result.terrain, result.state
    x, y = terrain.cell_xy()
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    density = result.scenario.physics.density
    fields = {"peak_pressure": density * np.asarray(state.peak_speed, dtype=float) ** 2,
              "peak_speed": np.asarray(state.peak_speed, dtype=float),
              "peak_thickness": np.asarray(state.peak_h, dtype=float)}
    com = np.asarray(result.snapshots.center_of_mass, dtype=float).reshape(-1, 3)
    spacing = float(min(abs(terrain.x[1] - terrain.x[0]), abs(terrain.y[1] - terrain.y[0])))
    released = np.nan_to_num(np.asarray(result.h0, dtype=float)) > 0.0
    # only the cells the flow reached can hold the runout point: the projection onto the
    # path then costs what the flow covers, not the map
    keep = released | (fields["peak_thickness"] > 0.0)
    return RunPoints(x[keep], y[keep], np.asarray(terrain.bed_elevation, dtype=float)[keep],
                     {k: v[keep] for k, v in fields.items()}, released[keep], spacing,
                     com[:, 0], com[:, 1], "grid", result.scenario.name,
                     float(result.thresholds["runout"]))


def headline_runout(result) -> dict:
    """Set the headline ``runout`` of a map run's summary: the distance along the path
    (``output.path.line`` when the scenario gives one, else the flow's centre-of-mass track)
    of the farthest cell whose peak pressure reaches the limit (``output.path``'s field and
    threshold, else 1 kPa, as AIMEC), with ``runout_angle`` (alpha, top of the release to
    that point). The horizontal distance from the release centroid to the farthest deposit
    cell stays as ``reach_from_release_centroid``. Profiles keep their runout along the bed.
    Returns the summary; a second call changes nothing."""
    s = result.summary
    if "reach_from_release_centroid" in s:
        return s
    # on a profile the runout is already the end of the deposit along the bed: no other
    s["reach_from_release_centroid"] = (math.nan if result.terrain.kind == "profile"
                                        else s["runout"])
    s["runout_angle"] = math.nan
    s["runout_path"] = ""
    if result.terrain.kind != "grid":
        return s
    block = result.scenario.output.path
    settings = PathSettings.from_scenario(block)
    s["runout_path"] = "path line" if settings.line else "centre-of-mass track"
    s["runout"] = math.nan
    try:
        points = result_points(result)
        line = path_for(points, settings.line)
        res = analyse(points, line, settings.field, settings.threshold_for(points),
                      settings.width, profiles=False)
    except (AvflowError, ValueError):
        return s  # no path to follow (nothing moved): no runout along a path
    s["runout"] = res.scalars["runout_s"]
    s["runout_angle"] = res.scalars["runout_angle"]
    s["runout_limit"] = f"{res.field} >= {res.threshold:g} {res.units}"
    return s
