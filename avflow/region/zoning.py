"""Hazard zones of a region with return periods (``scenarios.return_periods``): each
release's run of each scenario zoned by its return period (:mod:`avflow.output.zoning`),
the most severe zone kept per pixel of the DEM."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from avflow.output.zoning import ZoningError, ZoningRule


def region_zoning(outdir, rule: ZoningRule = ZoningRule()) -> tuple[dict, list]:
    """The zones of the region in ``outdir`` (its folder, or its region.zarr) on the DEM's
    grid, and the return periods used: from every merged run's result file."""
    import pandas as pd
    import xarray as xr

    from avflow.region.export import find_store
    from avflow.region.orchestrate import TABLE
    from avflow.region.run import MERGED, read_result, result_path

    store = find_store(outdir)
    if store is None:
        raise ZoningError(f"{outdir}: not a region's output folder (no region.zarr)")
    folder = store.parent
    table_path = folder / TABLE
    try:
        table = pd.read_csv(table_path)
    except (OSError, ValueError) as err:
        raise ZoningError(f"{table_path}: cannot be read ({type(err).__name__})") from None
    periods = table["return_period"] if "return_period" in table else pd.Series(dtype=float)
    if not periods.notna().any():
        raise ZoningError(f"{folder}: the region has no return periods: give its scenarios "
                          "as scenarios.return_periods (years and release thickness)")
    with xr.open_zarr(store) as ds:
        x, y = ds["x"].values, ds["y"].values  # y north first, as the DEM's rows
        wkt = ds["crs"].attrs.get("crs_wkt") if "crs" in ds else None
    zones = np.zeros((y.size, x.size), dtype=np.uint8)
    multi = table["scenario"].nunique() > 1 if "scenario" in table else False
    used = set()
    for _, row in table.iterrows():
        years = row.get("return_period")
        if row["status"] not in MERGED or years is None or math.isnan(float(years)):
            continue
        scenario = int(row["scenario"]) if multi else None
        got, maps, why = read_result(result_path(folder, int(row["id"]), scenario))
        if maps is None:
            raise ZoningError(f"release {int(row['id'])}: its result file cannot be read "
                              f"back ({why or 'missing'}); run the region again")
        reached = np.nan_to_num(maps["peak_thickness"]) > float(got["reach_threshold"])
        z = rule.zone(maps["peak_pressure"].astype(float) / 1000.0, reached, float(years))
        r0, r1, c0, c1 = (int(got[k]) for k in ("row0", "row1", "col0", "col1"))
        np.maximum(zones[r0:r1, c0:c1], z, out=zones[r0:r1, c0:c1])
        used.add(float(years))
    # south first (ascending y), as the run files and write_tif take them
    order = np.argsort(y)
    return ({"zones": zones[order], "x": x, "y": y[order], "crs_wkt": wkt,
             "inside": np.ones(zones.shape, bool)}, sorted(used))


def default_output(outdir) -> Path:
    """``OUTDIR/zoning.tif`` of a region folder (or of the folder of its region.zarr)."""
    path = Path(outdir)
    return (path.parent if path.suffix == ".zarr" else path) / "zoning.tif"
