"""Protective structures built into the bed before the frame is built: dams and walls.

A structure is a line (any vector file GDAL reads, in the DEM's CRS) and a cross-section:

- **dam**: at a cell whose centre lies ``d`` from the line, the bed is raised to
  ``z_line + height - max(0, d - crest_width / 2) tan(side_slope)``, with ``z_line`` the
  original ground under the line at the nearest point (bilinear), wherever that is above
  the ground; the cells the line crosses carry the full crest height, so a crest narrower
  than a cell stays continuous. The bed, its slopes, the cells' frames and curvature are
  then built from this edited bed: every kernel sees the dam, and the run file's
  ``bed_elevation`` is the edited bed.
- **wall**: the cells the line crosses (and those within ``crest_width / 2``) leave the
  mesh; their faces are walls (reflecting) whatever ``terrain.nodata`` says. A wall is
  never overtopped.

:func:`structure_volumes` splits a run's final volume by the side of each line: on the
release's side (retained upstream) and beyond it (overtopped or gone round its ends), each
line continued straight beyond its ends. Errors are one line naming the scenario field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["BuiltStructures", "StructureError", "apply_structures", "read_line_file",
           "release_across", "release_under_dams", "structure_volumes"]


class StructureError(ValueError):
    """A structure that cannot be built; ``field`` names the scenario field."""

    def __init__(self, message: str, field: str = "structures"):
        super().__init__(message)
        self.field = field


@dataclass
class BuiltStructures:
    """What the structures did to the raster: the names, lines and kinds, the height added
    to the bed (m, on the grid; a wall's cells carry its height), the walls' cells."""

    names: list
    kinds: list
    lines: list                       #: shapely geometries (LineString or MultiLineString)
    added: np.ndarray                 #: (ny, nx) height added to the bed, m
    walls: np.ndarray                 #: (ny, nx) bool: cells turned into walls
    x: np.ndarray = field(repr=False, default=None)
    y: np.ndarray = field(repr=False, default=None)


def read_line_file(path, where: str):
    """The lines of a vector file as one shapely geometry, and its CRS (WKT or None)."""
    path = Path(path)
    try:
        import pyogrio
        import shapely

        meta, _, wkb, _ = pyogrio.raw.read(path)
        geometries = [g for g in shapely.from_wkb(wkb) if g is not None and not g.is_empty]
    except Exception as err:  # GDAL's own error: say which file
        raise StructureError(f"{path}: cannot be read as a vector file "
                             f"({type(err).__name__}: {' '.join(str(err).split())})",
                             where) from None
    parts = []
    for k, g in enumerate(geometries):
        if g.geom_type == "LineString":
            parts.append(g)
        elif g.geom_type == "MultiLineString":
            parts.extend(g.geoms)
        else:
            raise StructureError(f"{path}: feature {k} is a {g.geom_type}, not a line", where)
    if not parts:
        raise StructureError(f"{path}: holds no line", where)
    parts = [shapely.force_2d(p) for p in parts]
    line = parts[0] if len(parts) == 1 else shapely.MultiLineString(parts)
    crs = meta.get("crs")
    wkt = None
    if crs:
        from pyproj import CRS

        try:
            parsed = CRS.from_user_input(crs)
            wkt = parsed.to_wkt()
            pts = shapely.get_coordinates(line)
            if (parsed.is_geographic and path.suffix.lower() in (".geojson", ".json")
                    and (np.abs(pts[:, 0]).max() > 360.0 or np.abs(pts[:, 1]).max() > 90.0)):
                wkt = None  # GDAL's default WGS 84 of a GeoJSON in metres: no CRS given
        except Exception:  # noqa: BLE001 - an odd CRS text: compared as written
            wkt = str(crs)
    return line, wkt


def _check_crs(path, line_wkt, dem_wkt, where: str) -> None:
    from avflow.terrain.raster import same_crs

    if line_wkt and dem_wkt and not same_crs(line_wkt, dem_wkt):
        from pyproj import CRS

        def name(w):
            try:
                return CRS.from_user_input(w).name
            except Exception:  # noqa: BLE001
                return "another"
        raise StructureError(f"{path}: the line is in {name(line_wkt)}, the DEM in "
                             f"{name(dem_wkt)}; reproject the line to the DEM's CRS", where)


def _inside(line, x, y, path, where: str) -> None:
    """Every vertex within the grid (half a cell of margin): a line off the map is in
    another CRS or mistyped."""
    import shapely

    dx, dy = abs(x[1] - x[0]), abs(y[1] - y[0])
    x0, x1 = min(x[0], x[-1]) - dx / 2, max(x[0], x[-1]) + dx / 2
    y0, y1 = min(y[0], y[-1]) - dy / 2, max(y[0], y[-1]) + dy / 2
    pts = shapely.get_coordinates(line)
    off = ((pts[:, 0] < x0) | (pts[:, 0] > x1) | (pts[:, 1] < y0) | (pts[:, 1] > y1))
    if off.any():
        lx0, ly0, lx1, ly1 = line.bounds
        raise StructureError(f"{path}: the line (x {lx0:.6g} to {lx1:.6g}, y {ly0:.6g} to "
                             f"{ly1:.6g}) reaches outside the DEM (x {x0:.6g} to {x1:.6g}, "
                             f"y {y0:.6g} to {y1:.6g}); is it in the DEM's CRS?", where)


#: The highest crest allowed on a map of smaller relief (m).
MIN_HEIGHT_LIMIT = 100.0
#: The gentlest side slope of a dam (degrees): its sides reach height / tan(slope) away.
MIN_SIDE_SLOPE_DEG = 1.0


def _check_shape(line, path, where: str) -> None:
    """A line of zero length has no sides, one that crosses itself no single upstream side:
    the retained and beyond volumes would be invented."""
    if not line.length > 0:
        raise StructureError(f"{path}: the line has zero length (all its points coincide)",
                             where)
    if not line.is_simple:
        raise StructureError(f"{path}: the line crosses itself; the sides of the structure "
                             "(retained, beyond) are then not defined: draw it without "
                             "loops", where)


#: The share of the release allowed on the far side of a line (round-off of cells the line
#: grazes).
ACROSS_SHARE = 0.01


def release_across(built: BuiltStructures, cell_x, cell_y, volume0) -> tuple | None:
    """``(field, message)`` for the first structure whose line runs through the release
    (more than :data:`ACROSS_SHARE` of its volume on either side: which side is upstream is
    then not defined), else None."""
    volume0 = np.asarray(volume0, float)
    wet = volume0 > 0
    total = volume0.sum()
    if not total > 0:
        return None
    for k, (name, line) in enumerate(zip(built.names, built.lines)):
        side = _side(line, np.asarray(cell_x)[wet], np.asarray(cell_y)[wet])
        left = float(volume0[wet][side > 0].sum()) / total
        if min(left, 1.0 - left) > ACROSS_SHARE:
            return (f"structures[{k}].line",
                    f"{name}: the line runs through the release ({100 * left:.0f}% of its "
                    f"volume on one side, {100 * (1 - left):.0f}% on the other); which side "
                    "is upstream is not defined: move the line out of the release")
    return None


#: The share of the release on a dam's body above which a run says so (cells the toe grazes
#: aside).
UNDER_SHARE = 0.001


def release_under_dams(built: BuiltStructures, cell_x, cell_y, volume0) -> list[str]:
    """One message per dam whose body (the cells it raises) holds part of the release, the
    line itself clear of it: the snow then starts on the dam's slope, in a bed the
    practitioner did not mean. Each release cell on a raised cell goes to the nearest dam."""
    volume0 = np.asarray(volume0, float)
    total = volume0.sum()
    dams = [k for k, kind in enumerate(built.kinds) if kind == "dam"]
    if not dams or not total > 0 or built.x is None or built.x.size < 2 or built.y.size < 2:
        return []
    wet = volume0 > 0
    px, py = np.asarray(cell_x, float)[wet], np.asarray(cell_y, float)[wet]
    dx, dy = built.x[1] - built.x[0], built.y[1] - built.y[0]
    i = np.clip(np.rint((py - built.y[0]) / dy).astype(int), 0, built.y.size - 1)
    j = np.clip(np.rint((px - built.x[0]) / dx).astype(int), 0, built.x.size - 1)
    raised = np.nan_to_num(built.added[i, j]) * ~built.walls[i, j]
    on = raised > 1e-6 * max(float(np.nanmax(built.added)), 1e-12)
    if not on.any():
        return []
    import shapely

    points = shapely.points(px[on], py[on])
    distance = np.stack([shapely.distance(built.lines[k], points) for k in dams])
    nearest = np.asarray(dams)[np.argmin(distance, axis=0)]
    out = []
    for k in dams:
        mine = nearest == k
        share = float(volume0[wet][on][mine].sum()) / total
        if share > UNDER_SHARE:
            out.append(f"{built.names[k]}: the dam's body lies under {100 * share:.1f}% of the "
                       "release (the bed there raised by up to "
                       f"{float(raised[on][mine].max()):.1f} m): that part of the release "
                       "starts on the dam's slope; move the dam or redraw the release")
    return out


def _nearest_on(line, px, py):
    """Nearest point on ``line`` of every point, and the unit tangent there."""
    import shapely

    parts = list(line.geoms) if line.geom_type == "MultiLineString" else [line]
    pts = shapely.points(px, py)
    best = np.full(px.size, np.inf)
    qx, qy = np.empty(px.size), np.empty(px.size)
    tx, ty = np.empty(px.size), np.empty(px.size)
    for part in parts:
        d = shapely.distance(part, pts)
        t = shapely.line_locate_point(part, pts)
        q = shapely.get_coordinates(shapely.line_interpolate_point(part, t))
        eps = max(1e-6 * part.length, 1e-9)
        a = shapely.get_coordinates(shapely.line_interpolate_point(part, np.clip(
            t - eps, 0.0, part.length)))
        b = shapely.get_coordinates(shapely.line_interpolate_point(part, np.clip(
            t + eps, 0.0, part.length)))
        ux, uy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
        norm = np.hypot(ux, uy)
        norm[norm == 0] = 1.0
        closer = d < best
        best = np.where(closer, d, best)
        qx, qy = np.where(closer, q[:, 0], qx), np.where(closer, q[:, 1], qy)
        tx, ty = np.where(closer, ux / norm, tx), np.where(closer, uy / norm, ty)
    return best, qx, qy, tx, ty


def _touched(line, X, Y, dx, dy, near):
    """Cells (among ``near``) whose square the line crosses."""
    import shapely

    boxes = shapely.box(X[near] - dx / 2, Y[near] - dy / 2, X[near] + dx / 2, Y[near] + dy / 2)
    out = np.zeros(X.shape, bool)
    out[near] = shapely.intersects(boxes, line)
    return out


def _ground(z, x, y, qx, qy):
    """The original ground at points: bilinear on the grid, the nearest valid cell where a
    neighbour is NaN."""
    from scipy.interpolate import RegularGridInterpolator

    xs, ys, zz = x, y, z
    if xs[0] > xs[-1]:
        xs, zz = xs[::-1], zz[:, ::-1]
    if ys[0] > ys[-1]:
        ys, zz = ys[::-1], zz[::-1]
    pts = np.column_stack([qy, qx])
    out = RegularGridInterpolator((ys, xs), zz, bounds_error=False, fill_value=np.nan)(pts)
    bad = ~np.isfinite(out)
    if bad.any():
        from scipy.spatial import cKDTree

        X, Y = np.meshgrid(x, y)
        ok = np.isfinite(z)
        _, k = cKDTree(np.column_stack([X[ok], Y[ok]])).query(np.column_stack([qx[bad],
                                                                             qy[bad]]))
        out[bad] = z[ok][k]
    return out


def _near(line, X, Y, valid, reach):
    """Valid cells within the line's bounding box grown by ``reach``."""
    lx0, ly0, lx1, ly1 = line.bounds
    return (valid & (X >= lx0 - reach) & (X <= lx1 + reach) & (Y >= ly0 - reach)
            & (Y <= ly1 + reach))


def _build_dam(s, line, z, new, x, y, X, Y, valid, where):
    """``new`` with the dam raised: the band around the line grows until the dam's sides
    have met the ground (on a slope the downhill side reaches far)."""
    dx, dy = abs(x[1] - x[0]), abs(y[1] - y[0])
    tan = math.tan(math.radians(s.side_slope_deg))
    reach = 0.5 * s.crest_width + s.height / tan + math.hypot(dx, dy)
    span = math.hypot(x.max() - x.min(), y.max() - y.min()) + reach
    while True:
        near = _near(line, X, Y, valid, reach)
        d, qx, qy, _, _ = _nearest_on(line, X[near], Y[near])
        crest = _ground(z, x, y, qx, qy) + s.height
        top = crest - np.maximum(0.0, d - 0.5 * s.crest_width) * tan
        top = np.where(_touched(line, X, Y, dx, dy, near)[near], crest, top)
        raised = top > z[near]
        edge = d > reach - 1.5 * max(dx, dy)
        if not (raised & edge).any():
            break
        if reach > span:
            raise StructureError(f"{s.line}: the dam's side never meets the ground: its "
                                 f"side slope ({s.side_slope_deg:g} degrees) is not steeper "
                                 "than the ground below it", where.replace("line",
                                                                           "side_slope_deg"))
        reach *= 2.0
    out = new.copy()
    out[near] = np.maximum(new[near], np.where(d <= reach, top, -np.inf))
    return out


def apply_structures(z, x, y, dem_wkt, structures) -> tuple[np.ndarray, BuiltStructures]:
    """The bed ``z`` (ny, nx; NaN outside) with the scenario's ``structures`` built in
    (walls' cells NaN) and what was built."""
    z = np.asarray(z, dtype=float)
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    dx, dy = abs(x[1] - x[0]), abs(y[1] - y[0])
    X, Y = np.meshgrid(x, y)
    valid = np.isfinite(z)
    new = z.copy()
    walls = np.zeros(z.shape, bool)
    names, kinds, lines = [], [], []
    # a crest higher than the map's relief (or 100 m on flatter maps) is a typo: 1e15 m
    # rounds the float32 bed to one value, 1e300 makes it infinite
    relief = float(np.nanmax(z) - np.nanmin(z)) if valid.any() else 0.0
    highest = max(relief, MIN_HEIGHT_LIMIT)
    for k, s in enumerate(structures):
        where = f"structures[{k}].line"
        if not (math.isfinite(s.height) and s.height <= highest):
            raise StructureError(f"{s.height:g} m is higher than the map's relief "
                                 f"({relief:.4g} m; at most {highest:.4g} m)",
                                 f"structures[{k}].height")
        if s.kind == "dam" and not s.side_slope_deg >= MIN_SIDE_SLOPE_DEG:
            # tan 0 (or 5e-324, whose tangent underflows): sides that never meet the ground
            raise StructureError(f"a dam's sides must slope: give an angle of "
                                 f"{MIN_SIDE_SLOPE_DEG:g} degree or more, got "
                                 f"{s.side_slope_deg:g}", f"structures[{k}].side_slope_deg")
        line, wkt = read_line_file(s.line, where)
        _check_crs(s.line, wkt, dem_wkt, where)
        _inside(line, x, y, s.line, where)
        _check_shape(line, s.line, where)
        if dem_wkt and not wkt:
            from avflow.terrain.polygons import warn_no_crs

            warn_no_crs(s.line, wkt, dem_wkt)
        if s.kind == "dam":
            new = _build_dam(s, line, z, new, x, y, X, Y, valid, where)
        else:
            reach = 0.5 * s.crest_width + math.hypot(dx, dy)
            near = _near(line, X, Y, valid, reach)
            d, *_ = _nearest_on(line, X[near], Y[near])
            cells = _touched(line, X, Y, dx, dy, near)
            cells[near] |= d <= 0.5 * s.crest_width
            walls |= cells & valid
        names.append(s.name or Path(s.line).stem)
        kinds.append(s.kind)
        lines.append(line)
    if not np.isfinite(new[valid & ~walls]).any():
        raise StructureError("the walls cover every cell of the terrain")
    added = np.where(valid, new - z, np.nan)
    if walls.any():
        added[walls] = max((s.height for s in structures if s.kind == "wall"), default=0.0)
        new[walls] = np.nan
    return new, BuiltStructures(names, kinds, lines, added, walls, x, y)


def structure_volumes(built: BuiltStructures, cell_x, cell_y, volume, volume0) -> list[dict]:
    """For each structure: the final ``volume`` (per cell, m^3) on the release's side of its
    line (``volume0``'s centroid: retained upstream) and beyond it (overtopped, or gone round
    its ends); the line continued straight beyond its ends decides the side."""
    volume, volume0 = np.asarray(volume, float), np.asarray(volume0, float)
    total0 = volume0.sum()  # the release's centroid, the same for every structure
    cx = float((volume0 * cell_x).sum() / total0)
    cy = float((volume0 * cell_y).sum() / total0)
    out = []
    for name, kind, line in zip(built.names, built.kinds, built.lines):
        side = _side(line, np.append(cell_x, cx), np.append(cell_y, cy))
        release_side = side[-1]
        upstream = side[:-1] == release_side
        out.append({"name": name, "kind": kind,
                    "retained_volume": float(volume[upstream].sum()),
                    "overtopped_volume": float(volume[~upstream].sum())})
    return out


def _side(line, px, py) -> np.ndarray:
    """+1 left of the line (looking along it), -1 right; beyond its ends, of its straight
    continuation."""
    _, qx, qy, tx, ty = _nearest_on(line, np.asarray(px, float), np.asarray(py, float))
    cross = tx * (py - qy) - ty * (px - qx)
    return np.where(cross >= 0.0, 1, -1)
