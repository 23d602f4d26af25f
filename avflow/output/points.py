"""The points of interest of a run: a CF ``timeSeries`` (discrete sampling geometry), a CSV
table and a figure.

The time series go into the run's NetCDF as the group ``points`` (CF 1.8+ groups; its
``featureType`` applies to that group: ``xr.open_dataset(run, group="points")``), in the
orthogonal multidimensional form of CF 9.3.1: ``(station, time)`` variables, a
``station_name`` with ``cf_role: timeseries_id`` and x, y per station. Beside the run:
``OUT_points.csv`` (one row per point and time) and ``OUT_points.png``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import xarray as xr

#: Name of the NetCDF group of the points of interest.
GROUP = "points"

#: The CSV's columns after the point's name, x and y.
CSV_COLUMNS = ("time_s", "thickness_m", "speed_m_s", "pressure_kPa")


def points_dataset(result) -> xr.Dataset | None:
    """The points of interest of a run as a CF timeSeries Dataset (None: no points)."""
    series = result.points
    if series is None:
        return None
    from avflow.output.cf import grid_mapping, release_stamp

    a = series.arrays()
    dry = result.thresholds["dry"]
    arrival = np.array([_first(a["time"], h > dry) for h in a["thickness"]])
    stamp = release_stamp(result.scenario.output.release_time)
    crs = grid_mapping(result.terrain.crs_wkt)
    where = {"grid_mapping": "crs"} if crs else {}
    coords = {
        "time": ("time", a["time"], {"standard_name": "time", "long_name": "time since release",
                                     "units": f"seconds since {stamp}", "calendar": "standard",
                                     "axis": "T"}),
        "station_name": ("station", np.array(series.names, dtype=object),
                         {"long_name": "point of interest", "cf_role": "timeseries_id"}),
        "x": ("station", series.x, {"standard_name": "projection_x_coordinate",
                                    "long_name": "x of the point", "units": "m"}),
        "y": ("station", series.y, {"standard_name": "projection_y_coordinate",
                                    "long_name": "y of the point", "units": "m"}),
    }
    link = {"coordinates": "time x y station_name", **where}
    data = {
        "thickness": (("station", "time"), a["thickness"], {
            "long_name": "flow thickness normal to the bed at the point", "units": "m",
            **link}),
        "speed": (("station", "time"), a["speed"], {
            "long_name": "flow speed along the bed at the point", "units": "m s-1", **link}),
        "pressure": (("station", "time"), a["pressure"], {
            "long_name": "flow pressure rho u^2 at the point", "units": "kPa",
            "comment": f"density {series.density:g} kg m-3 (physics.density)",
            "classes": np.asarray(result.scenario.output.pressure_classes, dtype=float),
            **link}),
        "arrival_time": ("station", arrival, {
            "long_name": "first sampled time the thickness at the point exceeds the dry "
                         "threshold", "units": "s", "comment": "NaN: the flow never came",
            "coordinates": "x y station_name", **where}),
    }
    for name in ("thickness", "speed", "pressure"):
        peak = a[name].max(axis=1) if a[name].size else np.full(len(series.names), np.nan)
        data[f"peak_{name}"] = ("station", peak, {
            "long_name": f"largest sampled {name} at the point",
            "units": data[name][2]["units"], "coordinates": "x y station_name", **where})
    if crs:
        data["crs"] = ((), np.int32(0), {"long_name": "coordinate reference system", **crs})
    ds = xr.Dataset(data, coords=coords)
    ds.attrs = {"Conventions": "CF-1.11", "featureType": "timeSeries",
                "title": f"{result.scenario.name}: flow at the points of interest",
                "comment": "sampled every "
                           f"{float(np.diff(a['time']).min()) if a['time'].size > 1 else 0:g} "
                           "s or at the end of the run; thickness, speed and pressure of "
                           "the cell each point lies in"}
    return ds


def _first(times, mask) -> float:
    k = np.flatnonzero(mask)
    return float(times[k[0]]) if k.size else np.nan


def points_encoding(ds: xr.Dataset) -> dict:
    return {name: {"_FillValue": None} for name in ds.variables
            if ds[name].dtype.kind == "f" and name not in ("arrival_time",)}


def append_group(ds: xr.Dataset, path) -> None:
    """Add ``ds`` as the group :data:`GROUP` of the NetCDF file ``path`` (a temporary that
    is renamed afterwards: the caller's atomic write)."""
    ds.to_netcdf(path, mode="a", group=GROUP, engine="netcdf4", encoding=points_encoding(ds))


def write_points_csv(ds: xr.Dataset, path) -> Path:
    """One row per point and time: name, x, y, time (s), thickness (m), speed (m/s),
    pressure (kPa); written atomically."""
    import csv

    from avflow.files import atomic_write

    def write(tmp):
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(("point", "x_m", "y_m", *CSV_COLUMNS))
            t = ds["time"].values
            for k, name in enumerate(ds["station_name"].values):
                x, y = float(ds["x"][k]), float(ds["y"][k])
                for j in range(t.size):
                    w.writerow((name, f"{x:.3f}", f"{y:.3f}", f"{t[j]:.6g}",
                                f"{float(ds['thickness'][k, j]):.6g}",
                                f"{float(ds['speed'][k, j]):.6g}",
                                f"{float(ds['pressure'][k, j]):.6g}"))

    return atomic_write(path, write)


def plot_points(ds: xr.Dataset, path, title: str = "") -> Path:
    """Thickness, speed and pressure against time, a line per point, the pressure's 1, 3
    and 30 kPa limits dashed; written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from avflow.files import atomic_write

    t = ds["time"].values
    fig, axes = plt.subplots(3, 1, figsize=(7, 7), sharex=True, constrained_layout=True)
    for k, name in enumerate(ds["station_name"].values):
        for ax, var in zip(axes, ("thickness", "speed", "pressure")):
            ax.plot(t, ds[var].values[k], label=str(name), lw=1.4)
    for ax, label in zip(axes, ("flow thickness (m)", "speed (m/s)", "pressure (kPa)")):
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    limits = [float(v) for v in np.atleast_1d(ds["pressure"].attrs.get("classes", ()))]
    shown = [v for v in limits if float(ds["pressure"].max()) >= 0.5 * v]
    lines = [axes[2].axhline(limit, color="0.4", ls="--", lw=0.8) for limit in shown]
    if lines:  # the pressure classes' limits (output.pressure_classes)
        axes[2].legend(lines[:1], [", ".join(f"{v:g}" for v in shown) + " kPa"], fontsize=8,
                       loc="upper right")
    axes[-1].set_xlabel("time since release (s)")
    axes[0].legend(title="point", fontsize=8, loc="upper right")
    axes[0].set_title(title or "flow at the points of interest")

    def write(tmp):
        fig.savefig(tmp, dpi=110, format="png")

    try:
        return atomic_write(path, write)
    finally:
        plt.close(fig)


def sidecar_paths(out) -> tuple[Path, Path]:
    """The CSV and PNG of the points beside a run's file ``OUT.nc``."""
    out = Path(out)
    return out.with_name(out.stem + "_points.csv"), out.with_name(out.stem + "_points.png")
