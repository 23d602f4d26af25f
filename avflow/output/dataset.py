"""A run as one CF-1.11 ``xarray.Dataset`` (profiles and square grids).

The variables and their attributes come from :mod:`avflow.output.cf`; triangle meshes go to
:mod:`avflow.output.ugrid`; files are written by :mod:`avflow.output.netcdf`, or, as the run
goes, by :mod:`avflow.output.stream` (which builds the same variables in two ``part`` s).
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from avflow.output.cf import (FIELDS, SUMMARIES, global_attributes, link_coordinates,
                              per_width, time_coords)
from avflow.output.ugrid import to_ugrid_dataset
from avflow.simulation.runner import RunResult
from avflow.terrain.raster import cf_grid_mapping

#: The variables on (time, space), one value per cell and snapshot (``v`` not on profiles).
TIME_FIELDS = ("h", "u", "v", "flow_state")

#: ``part`` of :func:`to_dataset`: everything; the fields on (time, space) of the snapshots
#: given; everything but those fields (the snapshots' h, hu, hv and flags are not read).
PARTS = ("all", "fields", "rest")


def snapshot_fields(terrain, h, hu, hv, flag) -> dict:
    """h, u (v) and flow_state of snapshots: per-cell arrays ``(..., cells)`` -> arrays on the
    output grid ``(..., [y,] x)`` (NaN outside a DEM, flow_state -1), or on the nodes of a
    triangle mesh. One snapshot ``(cells,)`` or a stack ``(time, cells)`` give the same values.
    """
    h = np.asarray(h)
    with np.errstate(invalid="ignore", divide="ignore"):
        ua = np.where(h > 0, np.asarray(hu) / h, 0.0)
        va = np.where(h > 0, np.asarray(hv) / h, 0.0)
    flags = np.asarray(flag).astype(np.int8)
    if terrain.kind == "triangles":  # fields on the nodes of a UGRID mesh, no grid
        e1, e2 = terrain.tangent_basis[:, 0, :], terrain.tangent_basis[:, 1, :]
        return {"h": h, "u": ua * e1[:, 0] + va * e2[:, 0], "v": ua * e1[:, 1] + va * e2[:, 1],
                "flow_state": flags}
    if terrain.kind == "profile":
        velocity = {"u": terrain.to_grid(ua)}
    else:
        # Velocity along the bed, as the components of its horizontal projection.
        e1, e2 = terrain.tangent_basis[:, 0, :], terrain.tangent_basis[:, 1, :]
        velocity = {"u": terrain.to_grid(ua * e1[:, 0] + va * e2[:, 0]),
                    "v": terrain.to_grid(ua * e1[:, 1] + va * e2[:, 1])}
    return {"h": terrain.to_grid(h), **velocity,
            "flow_state": terrain.to_grid(flags, fill=-1).astype(np.int8)}


def to_dataset(result: RunResult, part: str = "all") -> xr.Dataset:
    """The CF Dataset of a run (profiles on (time, x), grids on (time, y, x)).

    ``part`` (see :data:`PARTS`): ``"all"``; ``"fields"``: only the fields on (time, space)
    of ``result.snapshots`` (:data:`TIME_FIELDS`; and on triangle meshes the mesh variables
    before them), with the space coordinates but no time coordinate (``result`` needs only
    ``terrain`` and ``snapshots``); ``"rest"``: every other variable, from the snapshots'
    times and series and the final state. A streamed file (:mod:`avflow.output.stream`)
    writes the first at every output time and the second at the end.
    """
    if part not in PARTS:
        raise ValueError(f"part must be one of {PARTS}, got {part!r}")
    terrain, snaps = result.terrain, result.snapshots
    if terrain.kind == "triangles":  # fields on the nodes of a UGRID mesh
        return to_ugrid_dataset(result, part)
    profile = terrain.kind == "profile"
    space = ("x",) if profile else ("y", "x")

    def grid(values):
        """Per-cell values on the output grid; NaN outside the DEM."""
        return terrain.to_grid(np.asarray(values))

    coords = {}
    if part != "fields":
        times = np.asarray(snaps.time, dtype=float)
        coords = time_coords(times, result.scenario.output.release_time)
    if profile:
        # The profile unrolled along the bed is the X axis of its own frame: CF names a
        # metric X axis that is not a longitude projection_x_coordinate (as on grids).
        coords["x"] = ("x", terrain.x, {
            "standard_name": "projection_x_coordinate",
            "long_name": "distance along the bed from the top of the profile", "units": "m",
            "axis": "X"})
        coords["x_horizontal"] = ("x", terrain.x_horizontal, {
            "long_name": "horizontal distance from the top of the profile", "units": "m"})
    else:
        coords["x"] = ("x", terrain.x, {"standard_name": "projection_x_coordinate",
                                        "long_name": "x coordinate of cell centre",
                                        "units": "m", "axis": "X"})
        coords["y"] = ("y", terrain.y, {"standard_name": "projection_y_coordinate",
                                        "long_name": "y coordinate of cell centre",
                                        "units": "m", "axis": "Y"})

    def attrs(name):
        return {k: v for k, v in FIELDS[name].items() if k not in ("kind", "grid_only")}

    data = {}
    if part != "rest":
        fields = snapshot_fields(terrain, np.stack(snaps.h), np.stack(snaps.hu),
                                 np.stack(snaps.hv), np.stack(snaps.flag))
        for name in TIME_FIELDS:
            if name in fields:
                data[name] = (("time", *space), fields[name], attrs(name))
        data["flow_state"][2]["_FillValue"] = -1
    if part != "fields":
        state = result.state
        data["peak_thickness"] = (space, grid(state.peak_h), attrs("peak_thickness"))
        data["peak_speed"] = (space, grid(state.peak_speed), attrs("peak_speed"))
        data["deposit_thickness"] = (space, grid(state.h), attrs("deposit_thickness"))
        density = result.scenario.physics.density
        data["peak_pressure"] = (space, grid(density * state.peak_speed**2),
                                 attrs("peak_pressure"))
        data["arrival_time"] = (space, grid(state.arrival), attrs("arrival_time"))
        at_rest = (state.h > 0.0) & (state.hu == 0.0) & (state.hv == 0.0)
        data["rest_time"] = (space, grid(np.where(at_rest, state.last_moved, np.nan)),
                             attrs("rest_time"))
        com = np.asarray(snaps.center_of_mass, dtype=float)
        for k, axis in enumerate("xyz"):
            data[f"center_of_mass_{axis}"] = ("time", com[:, k],
                                              attrs(f"center_of_mass_{axis}"))
        data["bed_elevation"] = (space, grid(terrain.bed_elevation), attrs("bed_elevation"))
        data["slope_angle"] = (space, grid(terrain.slope_deg), attrs("slope_angle"))
        data["moving_volume"] = ("time", np.asarray(snaps.moving_volume),
                                 {**attrs("moving_volume"),
                                  "units": per_width("m3", profile)})
    crs_attrs = None if profile else cf_grid_mapping(terrain.crs_wkt)
    if crs_attrs:  # CF 5.6: every map names the CRS; GDAL reads crs_wkt / spatial_ref
        coords["crs"] = ((), np.int32(0), {"long_name": "coordinate reference system",
                                            **crs_attrs})  # a coordinate: link_coordinates
        for name, (dims, _, attributes) in list(data.items()):
            if dims[-2:] == ("y", "x"):
                attributes["grid_mapping"] = "crs"
    if part != "fields":
        s = result.summary
        for name, (units, description) in SUMMARIES.items():
            data[name] = ((), float(s[name]), {"long_name": name.replace("_", " "),
                                                "units": per_width(units, profile),
                                                "comment": description})
    ds = xr.Dataset(data, coords=coords)
    link_coordinates(ds)
    if part != "fields":
        ds.attrs = global_attributes(result)
    return ds
