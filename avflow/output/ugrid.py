"""A run on a triangle mesh as a UGRID-1.0 + CF-1.11 ``xarray.Dataset``.

The cells of a median dual mesh (:mod:`avflow.terrain.trimesh`) are the vertices of the triangles,
so every per-cell value lives on the UGRID *nodes*: a mesh topology variable ``mesh``
(``cf_role: mesh_topology``, ``topology_dimension: 2``) names the node coordinates
``mesh_node_x, mesh_node_y`` and the triangles ``mesh_face_nodes`` (0-based), and each field
carries ``mesh: mesh`` and ``location: node``. Names, units and other attributes of the
fields and summaries are those of the grid outputs (:data:`avflow.output.cf.FIELDS`,
:data:`avflow.output.cf.SUMMARIES`); the volumes are m^3, the velocity is the horizontal
projection of the velocity along the bed, as on grids. With a DEM's CRS, the fields name
the grid-mapping variable ``crs`` (:func:`avflow.output.cf.grid_mapping`).
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from avflow.output.cf import (FIELDS, SUMMARIES, global_attributes, grid_mapping,
                              link_coordinates, registered_maps, run_bounds, time_coords,
                              add_registered)

MESH = "mesh"
NODE, FACE = "node", "face"


def to_ugrid_dataset(result, part: str = "all") -> xr.Dataset:
    """The UGRID/CF Dataset of a run on a ``"triangles"`` terrain (fields on (time, node)).

    ``part`` as in :func:`avflow.output.dataset.to_dataset`: ``"fields"`` holds the mesh
    variables and the fields on (time, node), ``"rest"`` every other variable.
    """
    from avflow.output.fields import snapshot_fields

    terrain, snaps = result.terrain, result.snapshots
    tris = np.asarray(terrain.extras["triangles"], dtype=np.int32)

    coords = {} if part == "fields" else time_coords(
        np.asarray(snaps.time, dtype=float), result.scenario.output.release_time)
    coords = {
        **coords,
        "mesh_node_x": (NODE, terrain.x, {"standard_name": "projection_x_coordinate",
                                          "long_name": "x coordinate of mesh node (cell centre)",
                                          "units": "m"}),
        "mesh_node_y": (NODE, terrain.y, {"standard_name": "projection_y_coordinate",
                                          "long_name": "y coordinate of mesh node (cell centre)",
                                          "units": "m"}),
    }
    on_node = {"mesh": MESH, "location": "node"}
    crs_attrs = grid_mapping(terrain.crs_wkt)  # None without a CRS
    named_crs = {"grid_mapping": "crs"} if crs_attrs else {}

    def attrs(name, **extra):
        base = {k: v for k, v in FIELDS[name].items() if k not in ("kind", "grid_only")}
        return {**base, **on_node, **named_crs, **extra}

    space = (NODE,)
    data = {} if part == "rest" else {
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
    }
    if part != "rest":
        fields = snapshot_fields(terrain, np.stack(snaps.h), np.stack(snaps.hu),
                                 np.stack(snaps.hv), np.stack(snaps.flag))
        data["h"] = (("time", *space), fields["h"], attrs("h"))
        data["u"] = (("time", *space), fields["u"], attrs("u"))
        data["v"] = (("time", *space), fields["v"], attrs("v"))
        data["flow_state"] = (("time", *space), fields["flow_state"],
                              attrs("flow_state", _FillValue=np.int8(-1)))
    if part != "fields":
        _add_rest(data, result, space, attrs, on_node, named_crs)
    if crs_attrs and part != "fields":  # named by the fields' grid_mapping, no coordinate
        data["crs"] = ((), np.int32(0), {"long_name": "coordinate reference system",
                                          **crs_attrs})
    if part != "fields":
        data.update(run_bounds(np.asarray(snaps.time, dtype=float)))
        for name, (values, attributes) in registered_maps(result.state).items():
            add_registered(data, coords, name, (space, values, attributes))
    ds = xr.Dataset(data, coords=coords)
    link_coordinates(ds)
    if part != "fields":
        ds.attrs = global_attributes(result)
        ds.attrs["Conventions"] = "CF-1.11 UGRID-1.0"
        ds.attrs["comment"] = ("h is measured normal to the bed; fields live on the nodes of "
                               "a triangular mesh (UGRID), each node the centre of its median "
                               "dual cell")
    return ds


def _add_rest(data, result, space, attrs, on_node, named_crs) -> None:
    """The maps of the final state, the series, the static maps and the summaries."""
    terrain, snaps, state = result.terrain, result.snapshots, result.state
    data["peak_thickness"] = (space, state.peak_h, attrs("peak_thickness"))
    data["peak_speed"] = (space, state.peak_speed, attrs("peak_speed"))
    data["deposit_thickness"] = (space, state.h, attrs("deposit_thickness"))
    data["peak_pressure"] = (space, result.scenario.physics.density * state.peak_speed**2,
                             attrs("peak_pressure"))
    data["arrival_time"] = (space, state.arrival, attrs("arrival_time"))
    at_rest = (state.h > 0.0) & (state.hu == 0.0) & (state.hv == 0.0)
    data["rest_time"] = (space, np.where(at_rest, state.last_moved, np.nan), attrs("rest_time"))
    data["bed_elevation"] = (space, terrain.bed_elevation, attrs("bed_elevation"))
    data["slope_angle"] = (space, terrain.slope_deg, attrs("slope_angle"))
    data["cell_area"] = (space, terrain.mesh.cell_area, {
        **on_node, **named_crs, "standard_name": "cell_area", "units": "m2",
        "comment": "area of the median dual cell, measured on the bed"})
    com = np.asarray(snaps.center_of_mass, dtype=float)
    for k, axis in enumerate("xyz"):
        name = f"center_of_mass_{axis}"
        data[name] = ("time", com[:, k],
                      {k2: v for k2, v in FIELDS[name].items() if k2 != "kind"})
    data["moving_volume"] = ("time", np.asarray(snaps.moving_volume),
                             {k: v for k, v in FIELDS["moving_volume"].items() if k != "kind"})
    from avflow.output.fields import entrainment_variables

    for name, (values, is_map) in entrainment_variables(result).items():
        data[name] = ((space, values, attrs(name)) if is_map else
                      ("time", values, {k: v for k, v in FIELDS[name].items() if k != "kind"}))
    s = result.summary
    for name, (units, description) in SUMMARIES.items():
        if name not in s:  # (a summary of some runs only: supplied_volume)
            continue
        data[name] = ((), float(s[name]), {"long_name": name.replace("_", " "),
                                            "units": units, "comment": description})
