"""A run as one CF-1.11 ``xarray.Dataset``, and its atomic NetCDF write.

One table, :data:`FIELDS`, declares every output variable (units, names, cell_methods);
the Dataset builder and the tests read it. Fields are computed in float64 and stored as
float32 with zlib + shuffle, one chunk per snapshot; summaries and coordinates stay float64.
No CF standard name exists for a granular flow thickness or velocity, so those carry a
``long_name`` and a ``comment`` (thickness is measured normal to the bed, as in the seed).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import xarray as xr

from . import __version__
from .dem import cf_grid_mapping
from .rheology import law_reference
from .runner import FLAG_DRY, FLAG_FLOWING, FLAG_STOPPED, RunResult

SEED_REFERENCE = (
    "Mangeney-Castelnau, A., Vilotte, J.-P., Bristeau, M.-O., Perthame, B., Bouchut, F., "
    "Simeoni, C., Yerneni, S. (2003). Numerical modeling of avalanches based on Saint Venant "
    "equations using a kinetic scheme. J. Geophys. Res. 108(B11), 2527, doi:10.1029/2002JB002024"
)

TIME_UNITS = "seconds since 1970-01-01 00:00:00"

H_COMMENT = "measured normal to the bed (topography-linked frame of the seed, Fig. 1)"

#: name -> attributes. "kind": field (time, space), reduced (space), summary (0-d), coord.
FIELDS = {
    "h": dict(kind="field", long_name="flow thickness", units="m", comment=H_COMMENT),
    "u": dict(kind="field", long_name="depth-averaged velocity along the bed, x component",
              units="m s-1"),
    "v": dict(kind="field", long_name="depth-averaged velocity along the bed, y component",
              units="m s-1", grid_only=True),
    "flow_state": dict(kind="flag", long_name="state of the cell after the step",
                       flag_values=np.array([FLAG_DRY, FLAG_FLOWING, FLAG_STOPPED], np.int8),
                       flag_meanings="dry flowing under_coulomb_threshold"),
    "peak_thickness": dict(kind="reduced", long_name="maximum flow thickness over the run",
                           units="m", cell_methods="time_span: maximum", comment=H_COMMENT),
    "peak_speed": dict(kind="reduced", long_name="maximum speed over the run", units="m s-1",
                       cell_methods="time_span: maximum"),
    "deposit_thickness": dict(kind="reduced", long_name="thickness at the end of the run",
                              units="m", cell_methods="time_span: point", comment=H_COMMENT),
    "bed_elevation": dict(kind="static", standard_name="ground_level_altitude", units="m"),
    "slope_angle": dict(kind="static", standard_name="ground_slope_angle", units="degree"),
    "peak_pressure": dict(kind="reduced", long_name="maximum dynamic pressure rho |u|^2",
                          units="Pa", cell_methods="time_span: maximum"),
    "arrival_time": dict(kind="reduced", long_name="time of first arrival (h > dry threshold)",
                         units="s", comment="seconds since release; NaN where never reached"),
    "rest_time": dict(kind="reduced", long_name="time the cell came to rest for good",
                      units="s", comment=("end of the last step in which the material of the "
                                          "cell moved; NaN where dry or still moving at the end")),
    "moving_volume": dict(kind="series", long_name="volume of material still moving",
                          units="m3"),
    "center_of_mass_x": dict(kind="series", long_name="centre of mass, x", units="m"),
    "center_of_mass_y": dict(kind="series", long_name="centre of mass, y", units="m"),
    "center_of_mass_z": dict(kind="series", long_name="centre of mass, bed elevation",
                             units="m"),
}

SUMMARIES = {
    "runout": ("m", "downslope end of the deposit (h > runout_threshold); along the bed "
                    "from the top on profiles, horizontal distance from the release centroid "
                    "on grids"),
    "time_to_stop": ("s", "first time the moving volume (u != 0, h > dry_threshold) is below "
                          "stop_fraction of the released volume; NaN if never"),
    "deposit_max_thickness": ("m", "largest final thickness"),
    "deposit_length": ("m", "extent of the deposit (h > runout_threshold) along the flow"),
    "deposit_volume": ("m3", "material on the mesh at the end, film included"),
    "release_volume": ("m3", "released volume"),
    "outflow_volume": ("m3", "volume that left through open boundaries"),
    "film_volume": ("m3", "volume still moving at the end with h <= dry_threshold"),
    "mass_balance_error": ("1", "|V_end + V_out - V_0| / V_0"),
    "wall_time": ("s", "wall-clock time of the time loop"),
    "travel_length": ("m", "horizontal distance from the highest released cell to the farthest "
                           "deposit cell"),
    "drop_height": ("m", "elevation drop over travel_length"),
    "travel_angle": ("degree", "atan(drop_height / travel_length), the Fahrboeschung"),
}


def _per_width(units: str, profile: bool) -> str:
    """Volumes on a profile are per metre of width."""
    return {"m3": "m2"}.get(units, units) if profile else units


def time_coords(times: np.ndarray) -> dict:
    """``time`` and the scalar ``time_span`` that the cell_methods of run maxima refer to.

    CF 4.4 wants "unit since reference" for time: the release happens at the epoch, so
    seconds since release are the stored values (decode_times=False reads them as such).
    """
    time_attrs = {"standard_name": "time", "units": TIME_UNITS, "calendar": "proleptic_gregorian",
                  "units_metadata": "leap_seconds: none"}
    return {
        "time": ("time", times, {**time_attrs, "long_name": "time since release",
                                 "comment": "the reference instant is the release"}),
        "time_span": ((), times[-1], {**time_attrs, "long_name": "end of the period reduced over",
                                      "bounds": "time_span_bounds"}),
    }


def to_dataset(result: RunResult) -> xr.Dataset:
    """The CF Dataset of a run (profiles on (time, x), grids on (time, y, x))."""
    terrain, snaps = result.terrain, result.snapshots
    if terrain.kind == "triangles":  # fields on the nodes of a UGRID mesh
        from .ugrid import to_ugrid_dataset

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
    coords = time_coords(times)
    if profile:
        coords["x"] = ("x", terrain.x, {
            "long_name": "distance along the bed from the top of the profile", "units": "m"})
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
                              "units": _per_width("m3", profile)})
    crs_attrs = None if profile else cf_grid_mapping(terrain.crs_wkt)
    if crs_attrs:  # CF 5.6: every map names the CRS; GDAL reads crs_wkt / spatial_ref
        data["crs"] = ((), np.int32(0), crs_attrs)
        for name, (dims, _, attributes) in list(data.items()):
            if dims[-2:] == ("y", "x"):
                attributes["grid_mapping"] = "crs"
    s = result.summary
    for name, (units, description) in SUMMARIES.items():
        data[name] = ((), float(s[name]), {"long_name": name.replace("_", " "),
                                            "units": _per_width(units, profile),
                                            "comment": description})
    data["time_span_bounds"] = (("nv",), np.array([times[0], times[-1]]), {})
    ds = xr.Dataset(data, coords=coords)
    ds.attrs = _global_attributes(result)
    return ds


def _global_attributes(result: RunResult) -> dict:
    sc, s = result.scenario, result.summary
    th = result.thresholds
    return {
        "Conventions": "CF-1.11",
        "title": f"avflow run of scenario {sc.name}",
        "source": f"avflow {__version__}: kinetic scheme with Dirac stopping (seed eqs. 26-56)",
        "references": f"{SEED_REFERENCE}; friction law: {law_reference(result.solver.law)}",
        "history": "created by avflow " + __version__,
        "scenario_name": sc.name,
        "scenario_hash": sc.scenario_hash(),
        "scenario": sc.source_text,
        "avflow_version": __version__,
        "status": s["status"],
        "runout_threshold_m": th["runout"],
        "dry_threshold_m": th["dry"],
        "stop_fraction": th["stop_fraction"],
        "steps": int(s["steps"]),
        "dt_min_s": s["dt_min"],
        "dt_max_s": s["dt_max"],
        "runout_truncated": int(s["runout_truncated"]),
        "clamped_normal_cells": s["clamped_normal_cells"],
        "halved_steps": s["halved_steps"],
        "comment": ("h is measured normal to the bed; on profiles x is the distance along the "
                    "bed and volumes are per metre of width"),
    }


def encoding_for(ds: xr.Dataset) -> dict:
    """float32 + zlib for the big fields, one chunk per snapshot; no fill on coordinates."""
    enc = {}
    for name, var in ds.variables.items():
        if name in ds.coords:
            enc[name] = {"_FillValue": None}
        elif var.dtype.kind == "f" and var.ndim >= 1 and var.dims != ("time",) and name not in (
                "time_span_bounds",):
            chunks = (1, *var.shape[1:]) if var.dims[0] == "time" else var.shape
            fill = np.float32(np.nan) if bool(np.isnan(var.values).any()) else None
            enc[name] = {"dtype": "float32", "zlib": True, "complevel": 2, "shuffle": True,
                         "chunksizes": chunks, "_FillValue": fill}
        elif var.dtype.kind == "f":
            enc[name] = {"_FillValue": None}
    return enc


def _umask_mode() -> int:
    """rw for whoever the umask allows (mkstemp creates 0600 files)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def publish(tmp, path) -> None:
    """Give a finished temporary file the usual permissions, then rename it into place."""
    os.chmod(tmp, _umask_mode())
    os.replace(tmp, path)


def write_netcdf(ds: xr.Dataset, path) -> Path:
    """Write ``ds`` to ``path`` atomically: a temporary file in the same folder, then rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        ds.to_netcdf(tmp, encoding=encoding_for(ds), engine="netcdf4")
        publish(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
