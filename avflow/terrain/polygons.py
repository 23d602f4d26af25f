"""Release polygons from shapefiles, and their rasterisation onto the cells of a grid.

A shapefile record is one release area: its rings (outer boundary and holes, even-odd rule)
and its ``thickness`` attribute (m, normal to the bed, AvaFrame's convention, as in the
seed). Several records are several areas; where two overlap the larger thickness wins.
A cell is released when its centre lies inside (cell-centre rasterisation, as for every
other release shape), so the released volume is ``sum h_i A_i`` and is reported.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.path import Path as _MplPath

THICKNESS_FIELD = "thickness"


class PolygonError(ValueError):
    """A shapefile that cannot be used as a release; the message names the file."""


@dataclass(frozen=True)
class Area:
    """One release area: rings of (x, y) vertices and its thickness (None if unset)."""

    rings: tuple
    thickness: float | None
    name: str = ""


def read_polygons(path) -> tuple[list[Area], str | None]:
    """The areas of a polygon shapefile and its CRS (WKT of the .prj sidecar, or None)."""
    import shapefile  # pyshp

    path = Path(path)
    if not path.is_file():
        raise PolygonError(f"{path}: no such shapefile")
    # Without its .dbf (the attribute table: each polygon's thickness) pyshp fails late, deep
    # inside; a missing .shx it works around.
    if not any(path.with_suffix(s).is_file() for s in (".dbf", ".DBF")):
        raise PolygonError(f"{path.with_suffix('.dbf')}: not found; a shapefile needs its .dbf "
                           "(attribute table) beside the .shp")
    try:
        reader = shapefile.Reader(str(path))
    except Exception as err:
        raise PolygonError(f"{path}: cannot be read as a shapefile ({err})") from None
    try:
        return _read_areas(reader, path)
    except PolygonError:
        raise
    except Exception as err:  # a damaged .shp/.shx/.dbf: pyshp fails while iterating
        raise PolygonError(f"{path}: cannot be read as a shapefile "
                           f"({type(err).__name__}: {err})") from None


def _read_areas(reader, path: Path) -> tuple[list[Area], str | None]:
    import shapefile  # pyshp

    with reader:
        if reader.shapeType not in (shapefile.POLYGON, shapefile.POLYGONZ, shapefile.POLYGONM):
            raise PolygonError(f"{path}: holds {reader.shapeTypeName} shapes, not polygons")
        fields = [f[0] for f in reader.fields[1:]]
        lower = [f.lower() for f in fields]
        areas = []
        for k, sr in enumerate(reader.iterShapeRecords()):
            pts = np.asarray(sr.shape.points, dtype=float)[:, :2]
            if pts.shape[0] < 3:
                continue
            bounds = list(sr.shape.parts) + [pts.shape[0]]
            rings = tuple(pts[a:b] for a, b in zip(bounds[:-1], bounds[1:]) if b - a >= 3)
            thickness = None
            if THICKNESS_FIELD in lower:
                value = sr.record[lower.index(THICKNESS_FIELD)]
                if value is not None and value != "":
                    thickness = float(value)
                    if not np.isfinite(thickness) or thickness <= 0.0:
                        raise PolygonError(f"{path}: polygon {k} has thickness {value!r}; "
                                           "it must be a positive number of metres")
            name = ""
            for key in ("name", "name_ezg", "id"):
                if key in lower:
                    name = str(sr.record[lower.index(key)])
                    break
            areas.append(Area(rings, thickness, name))
    if not areas:
        raise PolygonError(f"{path}: holds no polygon")
    prj = path.with_suffix(".prj")
    return areas, (prj.read_text().strip() if prj.is_file() else None)


def rasterize(areas: list[Area], x: np.ndarray, y: np.ndarray, thickness: float | None = None,
              source: str = "") -> np.ndarray:
    """Thickness at the points (x, y): inside an area, its thickness (or ``thickness``)."""
    pts = np.column_stack([np.asarray(x, float).ravel(), np.asarray(y, float).ravel()])
    out = np.zeros(pts.shape[0])
    for k, area in enumerate(areas):
        value = thickness if thickness is not None else area.thickness
        if value is None:
            raise PolygonError(f"{source}: polygon {k} has no '{THICKNESS_FIELD}' attribute; "
                               "give release.thickness in the scenario")
        inside = np.zeros(pts.shape[0], dtype=bool)
        for ring in area.rings:  # even-odd: a hole flips what its outer ring covered
            inside ^= _MplPath(ring).contains_points(pts)
        out = np.where(inside, np.maximum(out, value), out)
    return out.reshape(np.shape(x))


__all__ = ["Area", "PolygonError", "read_polygons", "rasterize"]
