"""Release and domain polygons from vector files, and their rasterisation onto a grid.

Any polygon layer GDAL reads (through pyogrio): a shapefile (with its ``.dbf``), a
GeoPackage, GeoJSON, FlatGeobuf. A feature is one area: its rings (outer boundaries and
holes of a polygon or of every part of a multi-polygon, even-odd rule) and its ``thickness``
attribute (m, normal to the bed, AvaFrame's convention, as in the seed). Several features
are several areas; where two overlap the larger thickness wins. A cell is released when its
centre lies inside (cell-centre rasterisation by ``rasterio.features.rasterize``, GDAL's
scanline fill, as for every other release shape), so the released volume is ``sum h_i A_i``
and is reported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

THICKNESS_FIELD = "thickness"

#: Vector formats accepted for releases and domains (GDAL drivers through pyogrio).
VECTOR_SUFFIXES = (".shp", ".gpkg", ".geojson", ".json", ".fgb")

#: Most lattice cells :func:`rasterize` allocates for points on a regular lattice.
_MAX_LATTICE = 50_000_000


class PolygonError(ValueError):
    """A vector file that cannot be used as a release or domain; the message names it."""


@dataclass(frozen=True)
class Area:
    """One release area: rings of (x, y) vertices and its thickness (None if unset)."""

    rings: tuple
    thickness: float | None
    name: str = ""


def read_polygons(path, attribute: str | bool | None = None) -> tuple[list[Area], str | None]:
    """The polygon areas of a vector file and its CRS (WKT, or None when it has none).

    Each area's ``thickness`` is its ``thickness`` attribute (a positive number of metres),
    or with ``attribute`` the value of that attribute (any finite number; a file without
    it is an error, naming the attributes it has): a map's values
    (:mod:`avflow.terrain.maps`); ``attribute=False``: no attribute is read (None). A NULL
    value is None."""
    path = Path(path)
    if not path.is_file():
        raise PolygonError(f"{path}: no such file")
    if path.suffix.lower() == ".shp":
        # A shapefile is three files: without its .dbf (the attribute table: each polygon's
        # thickness) GDAL reads the shapes with no attributes; without its .shx, nothing.
        for part, what in ((".dbf", "attribute table"), (".shx", "shape index")):
            if not any(path.with_suffix(s).is_file() for s in (part, part.upper())):
                raise PolygonError(f"{path.with_suffix(part)}: not found; a shapefile needs "
                                   f"its {part} ({what}) beside the .shp")
    try:
        import pyogrio
        import shapely

        layer = _polygon_layer(pyogrio.list_layers(path), path)
        meta, _, wkb, columns = pyogrio.raw.read(path, layer=layer)
        geometries = shapely.from_wkb(wkb)
    except PolygonError:
        raise
    except Exception as err:  # GDAL's own error: say which file
        raise PolygonError(f"{path}: cannot be read as a vector file "
                           f"({type(err).__name__}: {str(err).strip()})") from None
    fields = {str(n).lower(): c for n, c in zip(meta["fields"], columns)}
    names = next((fields[k] for k in ("name", "name_ezg", "id") if k in fields), None)
    if isinstance(attribute, str) and attribute.lower() not in fields:
        have = ", ".join(str(n) for n in meta["fields"]) or "none"
        raise PolygonError(f"{path}: has no attribute {attribute!r} (its attributes: {have})")
    thicknesses = (None if attribute is False else
                   fields.get(THICKNESS_FIELD if attribute is None else attribute.lower()))
    areas = []
    for k, geom in enumerate(geometries):
        if geom is None or geom.is_empty:
            continue
        if geom.geom_type not in ("Polygon", "MultiPolygon"):
            raise PolygonError(f"{path}: feature {k} is a {geom.geom_type}, not a polygon")
        parts = geom.geoms if geom.geom_type == "MultiPolygon" else [geom]
        rings = tuple(np.asarray(ring.coords, dtype=float)[:, :2] for part in parts
                      for ring in (part.exterior, *part.interiors) if len(ring.coords) >= 3)
        if not rings:
            continue
        thickness = None
        if thicknesses is not None:
            thickness = (_thickness(thicknesses[k], k, path) if attribute is None
                         else _number(thicknesses[k], k, path, attribute))
        name = "" if names is None or names[k] is None else str(names[k])
        areas.append(Area(rings, thickness, name))
    if not areas:
        raise PolygonError(f"{path}: holds no polygon")
    return areas, _crs_wkt(meta.get("crs"), path, areas)


def _polygon_layer(layers, path: Path):
    """The one polygon layer of the file (a GeoPackage may hold several layers)."""
    if len(layers) == 0:
        raise PolygonError(f"{path}: holds no layer")
    polygons = [str(name) for name, kind in layers
                if "polygon" in str(kind).lower() or str(kind).lower() in ("unknown", "none")]
    if len(layers) == 1:
        if not polygons:
            raise PolygonError(f"{path}: holds {layers[0][1]} shapes, not polygons")
        return polygons[0]
    if len(polygons) != 1:
        raise PolygonError(f"{path}: holds {len(polygons)} polygon layers "
                           f"({', '.join(map(str, layers[:, 0]))}); keep the one to use in a "
                           "file of its own")
    return polygons[0]


def _as_number(value) -> float | None:
    """An attribute's value as a float: None for a NULL (or blank text), NaN for what is
    no number."""
    if value is None or (isinstance(value, str) and not value.strip()):
        return None
    if isinstance(value, float) and math.isnan(value):  # a NULL in a numeric column
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _thickness(value, k: int, path: Path) -> float | None:
    thickness = _as_number(value)
    if thickness is not None and not (math.isfinite(thickness) and thickness > 0.0):
        raise PolygonError(f"{path}: polygon {k} has thickness {value!r}; "
                           "it must be a positive number of metres")
    return thickness


def _number(value, k: int, path: Path, attribute: str) -> float | None:
    """A polygon's value of a map's attribute: a finite number, or None (NULL)."""
    number = _as_number(value)
    if number is not None and not math.isfinite(number):
        raise PolygonError(f"{path}: polygon {k} has {attribute} {value!r}; it must be a "
                           "finite number")
    return number


#: Files already warned about (one line per file and process, not one per ensemble member).
_WARNED_NO_CRS: set[str] = set()


def warn_no_crs(path, wkt: str | None, target_wkt: str | None, what: str = "the DEM's",
                stream=None) -> bool:
    """One line on stderr when a polygon file names no CRS but the DEM does: its coordinates
    are then taken as being in the DEM's CRS (a shapefile without .prj, a GeoJSON whose
    coordinates cannot be degrees). Returns whether it warned."""
    import sys

    if wkt or not target_wkt or str(path) in _WARNED_NO_CRS:
        return False
    _WARNED_NO_CRS.add(str(path))
    try:
        from pyproj import CRS

        name = CRS.from_user_input(target_wkt).name
    except Exception:
        name = "as written"
    print(f"avflow: warning: {path}: no CRS; its coordinates are taken as {what} CRS "
          f"({name})", file=stream or sys.stderr)
    return True


def _crs_wkt(crs, path: Path, areas) -> str | None:
    """The layer's CRS as WKT. GDAL gives a GeoJSON without a ``crs`` member WGS 84
    (RFC 7946); coordinates that cannot be degrees show the file is in a projected CRS it
    does not name: the CRS is then unknown (None), as for a shapefile without ``.prj``."""
    if not crs:
        return None
    from pyproj import CRS

    try:
        crs = CRS.from_user_input(crs)
    except Exception:
        return str(crs)
    if crs.is_geographic and path.suffix.lower() in (".geojson", ".json"):
        pts = np.concatenate([r for a in areas for r in a.rings])
        if np.abs(pts[:, 0]).max() > 360.0 or np.abs(pts[:, 1]).max() > 90.0:
            return None
    return crs.to_wkt()


def rasterize(areas: list[Area], x: np.ndarray, y: np.ndarray, thickness: float | None = None,
              source: str = "") -> np.ndarray:
    """Thickness at the points (x, y): inside an area, its thickness (or ``thickness``).

    Points on a regular lattice (grid cell centres, a subset of them, the nodes of a
    triangle mesh on the raster) are burnt by ``rasterio.features.rasterize`` on that
    lattice: a point is inside when GDAL's scanline fill covers its cell, the rule of
    the grids; other points are tested ring by ring (even-odd) with shapely, boundary
    included.
    """
    values = []
    for k, area in enumerate(areas):
        value = thickness if thickness is not None else area.thickness
        if value is None:
            raise PolygonError(f"{source}: polygon {k} has no '{THICKNESS_FIELD}' attribute; "
                               "give release.thickness in the scenario")
        values.append(float(value))
    px = np.asarray(x, dtype=float).ravel()
    py = np.asarray(y, dtype=float).ravel()
    out = np.zeros(px.size)
    lattice = _lattice(px, py)
    for area, value in zip(areas, values):
        inside = (_burn(area, *lattice) if lattice is not None
                  else _even_odd(area, px, py))
        out = np.where(inside, np.maximum(out, value), out)
    return out.reshape(np.shape(x))


def _lattice(px: np.ndarray, py: np.ndarray):
    """``(transform, shape, rows, cols)`` when every point is the centre of a cell of one
    north-up grid, else None."""
    if px.size < 2:
        return None
    steps = []
    for c in (px, py):
        u = np.unique(c)
        if u.size < 2:
            return None
        d = float(np.diff(u).min())
        idx = (c - u[0]) / d
        if d <= 0 or not np.allclose(idx, np.round(idx), rtol=0.0, atol=1e-6):
            return None
        steps.append((u[0], u[-1], d, np.round(idx).astype(np.int64)))
    (x0, _, dx, ix), (y0, y1, dy, iy) = steps
    shape = (int(iy.max()) + 1, int(ix.max()) + 1)
    if shape[0] * shape[1] > _MAX_LATTICE:
        return None
    from rasterio.transform import from_origin

    transform = from_origin(x0 - 0.5 * dx, y0 + (shape[0] - 0.5) * dy, dx, dy)
    return transform, shape, shape[0] - 1 - iy, ix


def _closed(ring: np.ndarray) -> list:
    ring = [tuple(p) for p in np.asarray(ring, dtype=float)[:, :2]]
    return ring if ring[0] == ring[-1] else ring + [ring[0]]


def _burn(area: Area, transform, shape, rows, cols) -> np.ndarray:
    """GDAL's fill of every ring of the area at once: even-odd over all its rings."""
    from rasterio.features import rasterize as gdal_rasterize

    geometry = {"type": "Polygon", "coordinates": [_closed(r) for r in area.rings]}
    mask = gdal_rasterize([(geometry, 1)], out_shape=shape, transform=transform, fill=0,
                          dtype="uint8", all_touched=False)
    return mask[rows, cols].astype(bool)


def _even_odd(area: Area, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    import shapely

    inside = np.zeros(px.size, dtype=bool)
    for ring in area.rings:  # a hole flips what its outer ring covered
        inside ^= shapely.intersects_xy(shapely.Polygon(_closed(ring)), px, py)
    return inside


__all__ = ["Area", "PolygonError", "VECTOR_SUFFIXES", "read_polygons", "rasterize"]
