"""Initial thickness of the released mass, per cell (thickness normal to the bed, m).

The velocity is zero at release (eq. 60). Shapes:

- ``parabola`` (eq. 59): ``h = K (l - (x - x0)^2)^+`` on a profile, with ``l = half_length^2``
  and ``K l = max_thickness``; the seed's section 6 mass is K = 1.26e-3 1/m, l = 1.6e5 m^2.
- ``dam``: a reservoir of uniform thickness upslope of ``position`` (seed section 4).
- ``box``: uniform thickness over an x range (and a y range on grids).
- ``cylinder``: uniform thickness within a horizontal radius of a centre (grids).
- ``polygon``: the areas of a shapefile, each with its ``thickness`` attribute or the
  scenario's thickness (grids; :mod:`avflow.terrain.polygons`).
- ``raster``: a thickness raster sampled bilinearly at the cell centres (grids).

Polygons and rasters must share the DEM's CRS when both carry one.

``volume_factor`` multiplies the thickness, hence the volume. Values are taken at cell
centres; the released volume is ``sum h_i A_i``.
"""

from __future__ import annotations

import numpy as np

from avflow.terrain.raster import RasterError, read_raster, same_crs
from avflow.terrain.polygons import PolygonError, rasterize, read_polygons, warn_no_crs
from avflow.terrain.bed import Terrain


class ReleaseError(ValueError):
    """The release leaves no mass on the mesh, or does not fit the terrain."""


def initial_thickness(release, terrain: Terrain) -> np.ndarray:
    """Thickness per cell (flattened like the mesh's cells) for a validated ``release`` block."""
    if terrain.kind == "profile":
        x, y = terrain.x, None
    else:
        x, y = terrain.cell_xy()
    kind = release.kind
    if kind == "parabola":
        l2 = release.half_length**2
        h = release.max_thickness / l2 * np.maximum(l2 - (x - release.center) ** 2, 0.0)
    elif kind == "dam":
        h = np.where(x < release.position, release.thickness, 0.0)
    elif kind == "box":
        inside = (x >= release.x[0]) & (x <= release.x[1])
        if y is not None and release.y is not None:
            inside &= (y >= release.y[0]) & (y <= release.y[1])
        h = np.where(inside, release.thickness, 0.0)
    elif kind == "cylinder":
        if y is None:
            raise ReleaseError("a cylinder release needs a 2D terrain")
        r2 = (x - release.center[0]) ** 2 + (y - release.center[1]) ** 2
        h = np.where(r2 <= release.radius**2, release.thickness, 0.0)
    elif kind == "polygon":
        try:
            areas, wkt = read_polygons(release.path)
            _check_crs(release.path, wkt, terrain)
            h = rasterize(areas, x, y, release.thickness, source=release.path)
        except PolygonError as err:
            raise ReleaseError(str(err)) from None
        if not np.any(h > 0.0):  # the file and where it lies against the map
            points = np.concatenate([np.asarray(r, float).reshape(-1, 2)
                                     for a in areas for r in a.rings])
            raise ReleaseError(f"{release.path}: the release puts no mass on any cell of the "
                               f"domain: its polygons (x {_span(points[:, 0])}, y "
                               f"{_span(points[:, 1])}) cover no cell centre of the map "
                               f"(x {_span(x)}, y {_span(y)})")
    elif kind == "raster":
        try:
            raster = read_raster(release.path)
        except RasterError as err:
            raise ReleaseError(str(err)) from None
        _check_crs(release.path, raster.crs_wkt, terrain)
        h = np.nan_to_num(raster.sample(x, y), nan=0.0)
        h = np.maximum(h, 0.0)
        if not np.any(h > 0.0):
            raise ReleaseError(f"{release.path}: the release puts no mass on any cell of the "
                               f"domain: no thickness above 0 on the map's cells (the raster: "
                               f"x {_span(raster.x)}, y {_span(raster.y)}; the map: "
                               f"x {_span(x)}, y {_span(y)})")
    else:
        raise ReleaseError(f"release kind {kind!r} is not available")
    h = np.ascontiguousarray(h * release.volume_factor, dtype=float)
    if not np.any(h > 0.0):
        raise ReleaseError("the release puts no mass on any cell of the domain")
    return h


def _span(values) -> str:
    """``177000-179000 m``: the range of coordinates, whole metres."""
    if values is None:
        return "none"
    v = np.ravel(np.asarray(values, dtype=float))
    v = v[np.isfinite(v)]
    return f"{v.min():.0f}-{v.max():.0f} m" if v.size else "none"


def _check_crs(path, wkt, terrain: Terrain) -> None:
    warn_no_crs(path, wkt, terrain.crs_wkt)
    if not same_crs(wkt, terrain.crs_wkt):
        raise ReleaseError(f"{path}: its CRS differs from the DEM's; reproject it first")


def release_crs(release) -> str | None:
    """The CRS (WKT) a polygon or raster release carries, None for the analytic shapes."""
    try:
        if release.kind == "polygon":
            return read_polygons(release.path)[1]
        if release.kind == "raster":
            return read_raster(release.path).crs_wkt
    except (PolygonError, RasterError):
        return None
    return None
