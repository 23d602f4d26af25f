"""A validated scenario's terrain: the stage that reads rasters and polygons and meshes them.

:mod:`avflow.terrain.bed` builds profiles, planes and DEM grids from arrays,
:mod:`avflow.terrain.trimesh` the triangular dual mesh; this module chooses between them and
reads the files a scenario names (:mod:`avflow.terrain.raster`, :mod:`avflow.terrain.polygons`).
"""

from __future__ import annotations

import numpy as np

from avflow.terrain.bed import Terrain, plane_terrain, profile_terrain, surface_terrain
from avflow.terrain.polygons import PolygonError, rasterize, read_polygons
from avflow.terrain.raster import read_raster, resample
from avflow.terrain.trimesh import plane_triangle_terrain, triangle_terrain


def terrain_raster(scenario):
    """The bed of a 2D scenario as a horizontal raster ``(z, x, y, crs_wkt)``.

    A DEM is read (:mod:`avflow.terrain.raster`) and resampled to ``grid.dx`` (``dy``) unless its own
    spacing is within 1% of it; NODATA cells are NaN. A plane is sampled at its cell centres.
    The scenario's structures are built in (:mod:`avflow.terrain.structures`; a wall's
    cells NaN).
    """
    z, x, y, wkt, _ = structured_raster(scenario)
    return z, x, y, wkt


def structured_raster(scenario):
    """:func:`terrain_raster` and what its structures built (None without any)."""
    z, x, y, wkt = _bare_raster(scenario)
    built = None
    if getattr(scenario, "structures", ()):
        from avflow.terrain.structures import apply_structures

        z, built = apply_structures(z, x, y, wkt, scenario.structures)
    return z, x, y, wkt, built


def _bare_raster(scenario):
    t = scenario.terrain
    if t.kind == "dem":
        raster = resample(read_raster(t.path, "DEM"), scenario.grid.dx, scenario.grid.dy)
        z, x, y, wkt = raster.values, raster.x, raster.y, raster.crs_wkt
    elif t.kind == "plane":
        p = plane_terrain(t, scenario.grid.dx, scenario.grid.dy, scenario.boundary)
        z, x, y, wkt = p.bed_elevation.reshape(p.grid_shape), p.x, p.y, None
    else:
        raise ValueError(f"terrain kind {t.kind!r} has no raster")
    if getattr(t, "domain", None):
        z = _clip_to_domain(z, x, y, t.domain)
    return z, x, y, wkt


def _clip_to_domain(z, x, y, path):
    """NaN (outside the mesh) wherever a cell centre lies outside the domain polygons."""
    try:
        areas, _ = read_polygons(path)
    except PolygonError as err:
        raise ValueError(str(err)) from None
    xx, yy = np.meshgrid(x, y)
    inside = rasterize(areas, xx, yy, thickness=1.0) > 0.0
    if not inside.any():
        raise ValueError(f"{path}: the domain polygon covers no cell of the terrain")
    return np.where(inside, z, np.nan)


def build_terrain(scenario, max_cells: float | None = None) -> Terrain:
    """The terrain of a validated scenario; a triangle mesh refined past ``max_cells``
    nodes is refused (``trimesh.MeshTooLarge``) before it is built."""
    t = scenario.terrain
    if getattr(scenario.grid, "mesh", "square") == "triangles":  # median dual cells
        return scenario_triangle_terrain(scenario, max_cells)
    if t.kind == "profile":
        return profile_terrain(t, scenario.grid.dx, scenario.boundary)
    built_in = bool(getattr(scenario, "structures", ()))
    if t.kind == "plane" and not getattr(t, "domain", None) and not built_in:
        return plane_terrain(t, scenario.grid.dx, scenario.grid.dy, scenario.boundary)
    if t.kind in ("dem", "plane"):  # a DEM, or a plane cut to a domain polygon or built on
        z, x, y, wkt, built = structured_raster(scenario)
        terrain = surface_terrain(z, x, y, scenario.boundary,
                                  nodata=getattr(t, "nodata", "wall"), crs_wkt=wkt,
                                  curvature=_curved(t),
                                  walls=None if built is None else built.walls)
        if built is not None:
            terrain.extras["structures"] = built
        return terrain
    raise ValueError(f"terrain kind {t.kind!r} is not available")


def scenario_triangle_terrain(scenario, max_cells: float | None = None) -> Terrain:
    """The triangle terrain of a validated scenario with ``grid.mesh: triangles``."""
    t, g = scenario.terrain, scenario.grid
    ref = getattr(g, "refine", None)
    options = {"pattern": getattr(g, "pattern", None) or "alternate", "max_nodes": max_cells}
    if ref is not None:
        options.update(refine_angle_deg=ref.angle_deg, refine_slope_deg=ref.slope_deg,
                       refine_levels=ref.levels)
    if t.kind == "plane" and not getattr(t, "domain", None) and not scenario.structures:
        return plane_triangle_terrain(t, g.dx, g.dy, scenario.boundary, **options)
    # DEMs (and planes cut to a domain): the raster the square-grid builder would use
    z, x, y, crs_wkt, built = structured_raster(scenario)
    if built is not None and built.walls.any():
        raise ValueError("a wall needs the square grid (grid.mesh: square); on triangles "
                         "give the structure as a dam")
    terrain = triangle_terrain(z, x, y, scenario.boundary,
                               getattr(t, "nodata", "wall") or "wall", crs_wkt,
                               curvature=_curved(t), **options)
    if built is not None:
        terrain.extras["structures"] = built
    return terrain


def _curved(terrain) -> bool:
    """Whether the bed-curvature term applies: DEMs unless switched off (a plane has none)."""
    return terrain.kind == "dem" and terrain.curvature
