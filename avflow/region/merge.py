"""The regional maps: a chunked Zarr store (through xarray), merged release by release.

For each kept field ``peak_<f>`` the store holds the per-pixel maximum over the releases
that reached the pixel (peak thickness above the release's runout threshold) and
``peak_<f>_release``, the id of the release that set it, ties going to the smaller id;
``release_count`` counts the releases reaching each pixel. A maximum with that tie rule and a
count are associative and commutative: the maps do not depend on the order in which
releases finish, nor on how many workers ran them. Each release touches only the chunks of
its window (read, combined, written back), so the regional map is never held whole in
memory. Pixels no release reached are NaN (ids 0, count 0).

The CRS is a CF grid mapping (variable ``crs``, with ``crs_wkt`` and ``spatial_ref``),
named by every map's ``grid_mapping``: ``xr.open_zarr`` and ``rioxarray`` read it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from avflow.region.spec import FIELD_NAMES


class RegionStore:
    """A Zarr store of the region's maps, created empty (lazily: no chunk written) over the
    whole DEM, then merged into with :meth:`add`."""

    def __init__(self, path, dem, fields, chunk: int, attrs: dict | None = None):
        import dask.array as da
        import xarray as xr

        from avflow.output.cf import grid_mapping

        self.path, self.dem, self.chunk = Path(path), dem, chunk
        self.fields = [FIELD_NAMES[f] for f in fields]
        shape, chunks = (dem.height, dem.width), (chunk, chunk)
        gm = grid_mapping(dem.crs_wkt)  # without pyproj's warning on LV95, as every output
        data, encoding = {}, {}
        units = {"peak_pressure": "Pa", "peak_thickness": "m", "peak_speed": "m s-1"}
        for name in self.fields:
            data[name] = (("y", "x"), da.full(shape, np.nan, dtype=np.float32, chunks=chunks),
                          {"long_name": f"maximum over the region's releases of {name}",
                           "units": units[name], "cell_methods": "area: maximum",
                           **({"grid_mapping": "crs"} if gm else {})})
            data[f"{name}_release"] = (
                ("y", "x"), da.zeros(shape, dtype=np.int32, chunks=chunks),
                {"long_name": f"id of the release that set {name} (smaller id on ties; 0: "
                              "none)", **({"grid_mapping": "crs"} if gm else {})})
            encoding[name] = {"_FillValue": np.float32(np.nan)}
        data["release_count"] = (("y", "x"), da.zeros(shape, dtype=np.int32, chunks=chunks),
                                 {"long_name": "number of releases reaching the cell (peak "
                                               "thickness above their runout threshold)",
                                  **({"grid_mapping": "crs"} if gm else {})})
        coords = {"x": ("x", dem.x(), {"standard_name": "projection_x_coordinate",
                                       "units": "m", "axis": "X"}),
                  "y": ("y", dem.y(), {"standard_name": "projection_y_coordinate",
                                       "units": "m", "axis": "Y"})}
        ds = xr.Dataset(data, coords=coords, attrs={"Conventions": "CF-1.11",
                                                    **(attrs or {})})
        if gm:  # a coordinate, so that each map carries it (rioxarray's .rio.crs)
            ds = ds.assign_coords(crs=((), np.int32(0), gm))
        # Zarr format 2, consolidated: what GDAL's Zarr driver and every xarray read
        ds.to_zarr(self.path, mode="w-", compute=False, encoding=encoding, consolidated=True,
                   zarr_format=2)
        import zarr

        self.group = zarr.open_group(str(self.path), mode="r+")

    def add(self, rid: int, window, maps: dict, threshold: float) -> None:
        """Merge one release's peak maps (north first, on its ``window``) into the store."""
        r0, r1, c0, c1 = window
        ch = self.chunk
        # the chunks the window touches: whole chunks read and written, none shared
        R0, C0 = r0 // ch * ch, c0 // ch * ch
        R1, C1 = min(-(-r1 // ch) * ch, self.dem.height), min(-(-c1 // ch) * ch, self.dem.width)
        slab = (slice(R0, R1), slice(C0, C1))
        inner = (slice(r0 - R0, r1 - R0), slice(c0 - C0, c1 - C0))
        thick = maps["peak_thickness"]
        reached = np.zeros((R1 - R0, C1 - C0), dtype=bool)
        reached[inner] = np.nan_to_num(thick, nan=0.0) > threshold
        if not reached.any():
            return
        count = self.group["release_count"]
        count[slab] = count[slab] + reached
        for name in self.fields:
            new = np.full(reached.shape, np.nan, dtype=np.float32)
            new[inner] = maps[name]
            new = np.where(reached, new, np.nan)
            cur, ids = self.group[name][slab], self.group[f"{name}_release"][slab]
            better = reached & (np.isnan(cur) | (new > cur) | ((new == cur) & (rid < ids)))
            self.group[name][slab] = np.where(better, new, cur)
            self.group[f"{name}_release"][slab] = np.where(better, rid, ids).astype(np.int32)
