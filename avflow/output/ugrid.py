"""A run on a triangle mesh as a UGRID-1.0 + CF-1.11 ``xarray.Dataset``.

The cells of a median dual mesh (:mod:`avflow.terrain.trimesh`) are the vertices of the triangles,
so every per-cell value lives on the UGRID *nodes*: a mesh topology variable ``mesh``
(``cf_role: mesh_topology``, ``topology_dimension: 2``) names the node coordinates
``mesh_node_x, mesh_node_y`` and the triangles ``mesh_face_nodes`` (0-based), and each field
carries ``mesh: mesh`` and ``location: node``. Names, units and other attributes of the
fields and summaries are those of the grid outputs (:data:`avflow.output.cf.FIELDS`,
:data:`avflow.output.cf.SUMMARIES`); the volumes are m^3, the velocity is the horizontal
projection of the velocity along the bed, as on grids. With a DEM's CRS, the fields name
the grid-mapping variable ``crs`` (:func:`avflow.terrain.raster.cf_grid_mapping`).
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from avflow.terrain.raster import cf_grid_mapping
from avflow.output.cf import FIELDS, SUMMARIES, global_attributes, link_coordinates, time_coords

MESH = "mesh"
NODE, FACE = "node", "face"


def to_ugrid_dataset(result) -> xr.Dataset:
    """The UGRID/CF Dataset of a run on a ``"triangles"`` terrain (fields on (time, node))."""
    terrain, snaps, state = result.terrain, result.snapshots, result.state
    tris = np.asarray(terrain.extras["triangles"], dtype=np.int32)
    h = np.stack(snaps.h)
    with np.errstate(invalid="ignore", divide="ignore"):
        ua = np.where(h > 0, np.stack(snaps.hu) / h, 0.0)
        va = np.where(h > 0, np.stack(snaps.hv) / h, 0.0)
    e1, e2 = terrain.tangent_basis[:, 0, :], terrain.tangent_basis[:, 1, :]

    times = np.asarray(snaps.time, dtype=float)
    coords = {
        **time_coords(times, result.scenario.output.release_time),
        "mesh_node_x": (NODE, terrain.x, {"standard_name": "projection_x_coordinate",
                                          "long_name": "x coordinate of mesh node (cell centre)",
                                          "units": "m"}),
        "mesh_node_y": (NODE, terrain.y, {"standard_name": "projection_y_coordinate",
                                          "long_name": "y coordinate of mesh node (cell centre)",
                                          "units": "m"}),
    }
    on_node = {"mesh": MESH, "location": "node"}
    crs_attrs = cf_grid_mapping(terrain.crs_wkt)  # None without a CRS
    grid_mapping = {"grid_mapping": "crs"} if crs_attrs else {}

    def attrs(name, **extra):
        base = {k: v for k, v in FIELDS[name].items() if k not in ("kind", "grid_only")}
        return {**base, **on_node, **grid_mapping, **extra}

    space = (NODE,)
    data = {
        MESH: ((), np.int32(0), {
            "cf_role": "mesh_topology",
            "long_name": "triangular mesh; finite-volume cells are the median dual cells of "
                         "its nodes (seed section 3.1, Fig. 2)",
            "topology_dimension": np.int32(2),
            "node_coordinates": "mesh_node_x mesh_node_y",
            "face_node_connectivity": "mesh_face_nodes",
            "face_dimension": FACE,
        }),
        # UGRID's optional cf_role "face_node_connectivity" is left out: CF allows one
        # variable with a cf_role, and the mesh variable must carry its own.
        "mesh_face_nodes": ((FACE, "max_face_nodes"), tris, {
            "long_name": "nodes of each triangle, counter-clockwise seen from above",
            "start_index": np.int32(0),
        }),
        "h": (("time", *space), h, attrs("h")),
        "u": (("time", *space), ua * e1[:, 0] + va * e2[:, 0], attrs("u")),
        "v": (("time", *space), ua * e1[:, 1] + va * e2[:, 1], attrs("v")),
        "flow_state": (("time", *space), np.stack(snaps.flag).astype(np.int8),
                       attrs("flow_state", _FillValue=np.int8(-1))),
        "peak_thickness": (space, state.peak_h, attrs("peak_thickness")),
        "peak_speed": (space, state.peak_speed, attrs("peak_speed")),
        "deposit_thickness": (space, state.h, attrs("deposit_thickness")),
        "peak_pressure": (space, result.scenario.physics.density * state.peak_speed**2,
                          attrs("peak_pressure")),
        "arrival_time": (space, state.arrival, attrs("arrival_time")),
    }
    at_rest = (state.h > 0.0) & (state.hu == 0.0) & (state.hv == 0.0)
    data["rest_time"] = (space, np.where(at_rest, state.last_moved, np.nan), attrs("rest_time"))
    data["bed_elevation"] = (space, terrain.bed_elevation, attrs("bed_elevation"))
    data["slope_angle"] = (space, terrain.slope_deg, attrs("slope_angle"))
    data["cell_area"] = (space, terrain.mesh.cell_area, {
        **on_node, **grid_mapping, "standard_name": "cell_area", "units": "m2",
        "comment": "area of the median dual cell, measured on the bed"})
    com = np.asarray(snaps.center_of_mass, dtype=float)
    for k, axis in enumerate("xyz"):
        name = f"center_of_mass_{axis}"
        data[name] = ("time", com[:, k],
                      {k2: v for k2, v in FIELDS[name].items() if k2 != "kind"})
    data["moving_volume"] = ("time", np.asarray(snaps.moving_volume),
                             {k: v for k, v in FIELDS["moving_volume"].items() if k != "kind"})
    s = result.summary
    for name, (units, description) in SUMMARIES.items():
        data[name] = ((), float(s[name]), {"long_name": name.replace("_", " "),
                                            "units": units, "comment": description})
    if crs_attrs:  # a coordinate, named by the fields on the nodes (see link_coordinates)
        coords["crs"] = ((), np.int32(0), {"long_name": "coordinate reference system",
                                            **crs_attrs})
    ds = xr.Dataset(data, coords=coords)
    link_coordinates(ds)
    ds.attrs = global_attributes(result)
    ds.attrs["Conventions"] = "CF-1.11 UGRID-1.0"
    ds.attrs["comment"] = ("h is measured normal to the bed; fields live on the nodes of a "
                           "triangular mesh (UGRID), each node the centre of its median dual "
                           "cell")
    return ds
