"""Stage 2, the terrain: bed geometry and the finite-volume layout, built once per run.

- :mod:`avflow.terrain.raster`, :mod:`avflow.terrain.polygons`: DEMs and release/domain
  polygons in and out (CRS, NODATA, resampling);
- :mod:`avflow.terrain.mesh`: cells, faces, normals, lengths and boundary codes;
- :mod:`avflow.terrain.bed`: the frame linked to the topography of every cell (seed Fig. 1)
  on profiles, planes and DEM grids;
- :mod:`avflow.terrain.trimesh`: the seed's triangular mesh with median dual cells;
- :mod:`avflow.terrain.build`: a scenario's terrain, choosing among those;
- :mod:`avflow.terrain.release`: the initial thickness.
"""
