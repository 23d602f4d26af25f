"""Values that vary in space, per cell: friction maps, the erodible layer, forest (issue 30).

A map is read from a raster (:mod:`avflow.terrain.raster`) or from polygons
(:mod:`avflow.terrain.polygons`) and sampled at the cell centres:

- a raster: each cell takes the value of the raster cell its centre lies in, with no
  interpolation (a zone map keeps its zones, a mask stays 0 or 1, a map of one value gives
  that value's bits); a centre outside the raster or on a NODATA cell takes the map's
  ``default``, and without one is an error;
- polygons: a cell whose centre is inside takes the polygon's value (its attribute, or one
  value for all; where polygons overlap the larger value wins, as for releases), the
  others the ``default`` (0 for a layer or a forest: where none stands); a friction map
  without a default must cover every cell.

Rasters and polygons must share the DEM's CRS when both carry one (as releases,
:func:`avflow.terrain.release._check_crs`). Every value must be finite and within the
range of the field it gives (the bounds of the number it replaces, from the schema), and
the cross-field rules of the law hold cell by cell (Pouliquen's delta1 < delta2, velocity
weakening's mu_w <= mu_s). Any problem is one :class:`MapError` naming the file, the
field and the first cell concerned, before any run.
"""

from __future__ import annotations

import numpy as np

from avflow.scenario.schema import NonNegative, bounds_of, field_bounds, map_fields
from avflow.terrain.bed import Terrain
from avflow.terrain.polygons import PolygonError, rasterize, read_polygons
from avflow.terrain.raster import RasterError, read_raster
from avflow.terrain.release import ReleaseError, _check_crs

__all__ = ["MapError", "erodible_depth", "forest_coefficient", "friction_maps",
           "raster_values", "polygon_values"]


class MapError(ValueError):
    """A map that cannot be used: ``field`` (dotted, in the scenario) and the problem, one
    line naming the file."""

    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field = field


def _points(terrain: Terrain) -> tuple[np.ndarray, np.ndarray | None]:
    """The cell centres: (x, y) on 2D terrains, (x along the bed, None) on profiles."""
    if terrain.kind == "profile":
        return terrain.x, None
    return terrain.cell_xy()


def _where(terrain: Terrain, cells: np.ndarray) -> str:
    """``x = .., y = ..`` of the first of ``cells`` (a boolean mask), for messages."""
    x, y = _points(terrain)
    k = int(np.flatnonzero(cells)[0])
    return f"x = {x[k]:.6g}" + ("" if y is None else f", y = {y[k]:.6g}")


def _need_2d(terrain: Terrain, path: str, field: str) -> None:
    if terrain.kind == "profile":
        raise MapError(field, f"{path}: a file map needs a 2D terrain ('plane' or 'dem')")


def raster_values(path: str, terrain: Terrain, default: float | None,
                  field: str) -> np.ndarray:
    """Per cell, the value of the raster cell its centre lies in; ``default`` outside the
    raster and on NODATA (None: an error naming the file)."""
    _need_2d(terrain, path, field)
    try:
        raster = read_raster(path)
        _check_crs(path, raster.crs_wkt, terrain)
    except (RasterError, ReleaseError) as err:
        raise MapError(field, str(err)) from None
    x, y = _points(terrain)
    values = np.full(x.size, np.nan)
    ix = np.floor((x - raster.x[0]) / raster.dx + 0.5).astype(np.int64)
    iy = np.floor((y - raster.y[0]) / raster.dy + 0.5).astype(np.int64)
    ny, nx = raster.values.shape
    inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    values[inside] = raster.values[iy[inside], ix[inside]]
    if default is None:
        if not inside.all():
            raise MapError(field, f"{path}: does not cover the terrain: "
                                  f"{int((~inside).sum())} of the terrain's {x.size} cells lie "
                                  f"outside the raster (the first at {_where(terrain, ~inside)}); "
                                  "give a raster that covers it, or a default")
        nodata = np.isnan(values)
        if nodata.any():
            raise MapError(field, f"{path}: NODATA in {int(nodata.sum())} of the terrain's "
                                  f"{x.size} cells (the first at {_where(terrain, nodata)}); "
                                  "fill them, or give a default")
    return np.where(np.isnan(values), np.nan if default is None else default, values)


def polygon_values(path: str, terrain: Terrain, field: str, attribute: str | None,
                   value: float | None, default: float | None) -> np.ndarray:
    """Per cell, the value of the polygon its centre lies in (``attribute`` of each, or
    ``value`` for all; the larger where they overlap), ``default`` outside every polygon
    (None: such a cell is an error naming the file)."""
    _need_2d(terrain, path, field)
    try:
        areas, wkt = read_polygons(path, attribute=attribute if value is None else False)
        _check_crs(path, wkt, terrain)
    except (PolygonError, ReleaseError) as err:
        raise MapError(field, str(err)) from None
    x, y = _points(terrain)
    values = np.full(x.size, -np.inf)
    for k, area in enumerate(areas):
        v = value if value is not None else area.thickness
        if v is None:
            raise MapError(field, f"{path}: polygon {k} has no value of {attribute!r}")
        try:
            inside = rasterize([area], x, y, 1.0, source=path) > 0.0
        except PolygonError as err:
            raise MapError(field, str(err)) from None
        values = np.where(inside, np.maximum(values, v), values)
    outside = np.isneginf(values)
    if default is None and outside.any():
        raise MapError(field, f"{path}: {int(outside.sum())} of the terrain's {x.size} cells "
                              f"lie outside every polygon (the first at "
                              f"{_where(terrain, outside)}); cover the terrain, or give a "
                              "default")
    return np.where(outside, np.nan if default is None else default, values)


def _map(spec, terrain: Terrain, field: str, *, attribute=None, value=None,
         default=None) -> tuple[np.ndarray, str]:
    """The values of a raster or polygon map and the file they came from."""
    if spec.raster is not None:
        return raster_values(spec.raster, terrain, default, f"{field}.raster"), spec.raster
    return (polygon_values(spec.polygon, terrain, f"{field}.polygon", attribute, value,
                           default), spec.polygon)


def _check(values, bounds, path, name, field, terrain) -> None:
    """Every cell finite and within ``bounds`` (schema.Bounds): else one line naming the
    file, the field's range and the first cell out of it."""
    bad = ~np.isfinite(values) if bounds is None else ~bounds.inside(values)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        wanted = "must be finite" if bounds is None else bounds.wanted
        raise MapError(field, f"{path}: {name} {wanted}, got {values[k]:.6g} at "
                              f"{_where(terrain, bad)} ({int(bad.sum())} cells out of range)")


def friction_maps(rheology, terrain: Terrain, prefix: str = "rheology") -> dict:
    """``{field: values per cell}`` of the rheology block's maps, in the field's units,
    each within the field's range, and the law's cross-field rules cell by cell."""
    out, files = {}, {}
    for name, spec in map_fields(rheology).items():
        field = f"{prefix}.{name}"
        values, path = _map(spec, terrain, field, attribute=spec.attribute, value=spec.value,
                            default=spec.default)
        if spec.scale != 1.0:  # (1: the values as read, to the bit)
            values = values * spec.scale
        _check(values, field_bounds(rheology, name), path, name, field + (
            ".raster" if spec.raster else ".polygon"), terrain)
        out[name], files[name] = values, path
    rules = {"pouliquen": ("delta1_deg", "delta2_deg", np.less, "smaller than"),
             "velocity_weakening": ("mu_w", "mu_s", np.less_equal, "at most")}
    if out and rheology.law in rules:
        a, b, ok, words = rules[rheology.law]
        va, vb = (out.get(n, getattr(rheology, n)) for n in (a, b))
        bad = ~ok(va, vb)
        if np.any(bad):
            bad = np.broadcast_to(bad, (terrain.n_cells,))
            name = a if a in out else b
            k = int(np.flatnonzero(bad)[0])
            got = [float(np.broadcast_to(v, bad.shape)[k]) for v in (va, vb)]
            raise MapError(f"{prefix}.{name}", f"{files[name]}: {a} must be {words} {b} in "
                                               f"every cell, got {got[0]:.6g} and {got[1]:.6g} "
                                               f"at {_where(terrain, bad)} "
                                               f"({int(bad.sum())} cells)")
    return out


def _box(terrain: Terrain, x_range, y_range) -> np.ndarray:
    """Cells whose centre lies within the ranges (bounds included; None: no limit)."""
    x, y = _points(terrain)
    inside = np.ones(x.size, dtype=bool)
    if x_range is not None:
        inside &= (x >= x_range[0]) & (x <= x_range[1])
    if y_range is not None and y is not None:
        inside &= (y >= y_range[0]) & (y <= y_range[1])
    return inside


def erodible_depth(layer, terrain: Terrain, field: str = "entrainment.layer") -> np.ndarray:
    """The erodible depth per cell (m, normal to the bed, >= 0) of an ``ErodibleLayer``."""
    if layer.depth is not None:
        return np.where(_box(terrain, layer.x, layer.y), float(layer.depth), 0.0)
    values, path = _map(layer, terrain, field, attribute=layer.attribute or "thickness",
                        value=layer.thickness, default=layer.default if layer.raster
                        else 0.0)
    where = f"{field}.{'raster' if layer.raster else 'polygon'}"
    _check(values, bounds_of(NonNegative), path, "the erodible depth (m)", where, terrain)
    return np.ascontiguousarray(values, dtype=float)


def source_weights(area, terrain: Terrain, field: str) -> np.ndarray:
    """Per cell, 1 where a registered source adds mass and 0 elsewhere: its x [and y]
    range, the cells inside its polygons, or its raster's cells > 0 (NODATA and cells
    outside the raster: 0)."""
    if area.x is not None:
        return np.where(_box(terrain, area.x, area.y), 1.0, 0.0)
    values, path = _map(area, terrain, field, value=None if area.raster else 1.0, default=0.0)
    where = f"{field}.{'raster' if area.raster else 'polygon'}"
    _check(values, None, path, "the source's area", where, terrain)
    return np.where(values > 0.0, 1.0, 0.0)


def forest_coefficient(forest, terrain: Terrain, field: str = "forest") -> np.ndarray:
    """The resistance coefficient c_f per cell (0 outside forest) of a ``Forest`` block."""
    if forest.x is not None:
        return np.where(_box(terrain, forest.x, forest.y), float(forest.c_f), 0.0)
    if forest.raster is not None:
        values, path = _map(forest, terrain, field, default=forest.default)
        if (forest.values or "mask") == "mask":
            _check(values, None, path, "the forest mask", f"{field}.raster", terrain)
            return np.where(values > 0.0, float(forest.c_f), 0.0)
    else:
        values, path = _map(forest, terrain, field, attribute=forest.attribute,
                            value=None if forest.attribute else forest.c_f, default=0.0)
    where = f"{field}.{'raster' if forest.raster else 'polygon'}"
    _check(values, bounds_of(NonNegative), path, "c_f", where, terrain)
    return np.ascontiguousarray(values, dtype=float)
