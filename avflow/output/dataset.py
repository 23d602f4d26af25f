"""A run as one CF-1.11 ``xarray.Dataset`` (profiles and square grids).

The variables and their attributes come from :mod:`avflow.output.cf`; triangle meshes go to
:mod:`avflow.output.ugrid`; files are written by :mod:`avflow.output.netcdf`.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from avflow.output.cf import (FIELDS, SUMMARIES, global_attributes, link_coordinates,
                              per_width, time_coords)
from avflow.output.ugrid import to_ugrid_dataset
from avflow.simulation.runner import RunResult
from avflow.terrain.raster import cf_grid_mapping


def to_dataset(result: RunResult) -> xr.Dataset:
    """The CF Dataset of a run (profiles on (time, x), grids on (time, y, x))."""
    terrain, snaps = result.terrain, result.snapshots
    if terrain.kind == "triangles":  # fields on the nodes of a UGRID mesh
        return to_ugrid_dataset(result)
    profile = terrain.kind == "profile"
    space = ("x",) if profile else ("y", "x")

    def grid(values):
        """Per-cell values on the output grid; NaN outside the DEM."""
        return terrain.to_grid(np.asarray(values))

    h_cells = np.stack(snaps.h)
    with np.errstate(invalid="ignore", divide="ignore"):
        ua = np.where(h_cells > 0, np.stack(snaps.hu) / h_cells, 0.0)
        va = np.where(h_cells > 0, np.stack(snaps.hv) / h_cells, 0.0)
    if profile:
        velocity = {"u": grid(ua)}
    else:
        # Velocity along the bed, as the components of its horizontal projection.
        e1, e2 = terrain.tangent_basis[:, 0, :], terrain.tangent_basis[:, 1, :]
        velocity = {"u": grid(ua * e1[:, 0] + va * e2[:, 0]),
                    "v": grid(ua * e1[:, 1] + va * e2[:, 1])}
    h = grid(h_cells)

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

    data = {"h": (("time", *space), h, attrs("h"))}
    for name, values in velocity.items():
        data[name] = (("time", *space), values, attrs(name))
    flags = terrain.to_grid(np.stack(snaps.flag).astype(np.int8), fill=-1).astype(np.int8)
    data["flow_state"] = (("time", *space), flags, {**attrs("flow_state"), "_FillValue": -1})
    data["peak_thickness"] = (space, grid(result.state.peak_h), attrs("peak_thickness"))
    data["peak_speed"] = (space, grid(result.state.peak_speed), attrs("peak_speed"))
    data["deposit_thickness"] = (space, grid(result.state.h), attrs("deposit_thickness"))
    state = result.state
    density = result.scenario.physics.density
    data["peak_pressure"] = (space, grid(density * state.peak_speed**2), attrs("peak_pressure"))
    data["arrival_time"] = (space, grid(state.arrival), attrs("arrival_time"))
    at_rest = (state.h > 0.0) & (state.hu == 0.0) & (state.hv == 0.0)
    data["rest_time"] = (space, grid(np.where(at_rest, state.last_moved, np.nan)),
                         attrs("rest_time"))
    com = np.asarray(snaps.center_of_mass, dtype=float)
    for k, axis in enumerate("xyz"):
        data[f"center_of_mass_{axis}"] = ("time", com[:, k], attrs(f"center_of_mass_{axis}"))
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
    s = result.summary
    for name, (units, description) in SUMMARIES.items():
        data[name] = ((), float(s[name]), {"long_name": name.replace("_", " "),
                                            "units": per_width(units, profile),
                                            "comment": description})
    ds = xr.Dataset(data, coords=coords)
    link_coordinates(ds)
    ds.attrs = global_attributes(result)
    return ds
