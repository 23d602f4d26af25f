"""The regional maps: a chunked Zarr store (through xarray), merged release by release.

For each kept field ``peak_<f>`` the store holds the per-pixel maximum over the releases
that reached the pixel (peak thickness above the release's runout threshold) and
``peak_<f>_release``, the id of the release that set it, ties going to the smaller id;
``release_count`` counts the releases reaching each pixel. A maximum with that tie rule and a
count are associative and commutative: the maps do not depend on the order in which
releases finish, nor on how many workers ran them. Each release touches only the chunks of
its window (read, combined, written back), so the regional map is never held whole in
memory. Pixels no release reached are NaN (ids 0, count 0).

With exceedance thresholds (a region with ``scenarios:``, or ``merge.thresholds``), each
release is merged once all its scenarios are in: for every peak map and threshold the store
counts, per pixel, the runs (release and scenario) exceeding it
(``<map>_exceedance_count``, int32), ``scenario_count`` the scenarios of the releases
reaching the pixel, and ``<map>_exceedance_probability`` keeps the largest over the
releases of the fraction of a release's scenarios exceeding it (float32): sums and a
maximum, associative too. Exceedance is counted as the ensembles count it
(:func:`avflow.ensemble.dataset.exceedances`), and only where the run reached the pixel.

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

    def __init__(self, path, dem, fields, chunk: int, attrs: dict | None = None,
                 thresholds: dict | None = None, scenarios: int | None = None):
        import dask.array as da

        from avflow.ensemble.dataset import THRESHOLD_DIMS
        from avflow.ensemble.spec import THRESHOLD_UNITS
        import xarray as xr

        from avflow.output.cf import grid_mapping

        self.path, self.dem, self.chunk = Path(path), dem, chunk
        self.fields = [FIELD_NAMES[f] for f in fields]
        self.thresholds = {k: tuple(v) for k, v in (thresholds or {}).items()}
        self.counting = scenarios is not None or bool(self.thresholds)
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
        if self.counting:
            data["scenario_count"] = (
                ("y", "x"), da.zeros(shape, dtype=np.int32, chunks=chunks),
                {"long_name": "number of scenarios of the releases reaching the cell (those "
                              "that ran; a release counts where any of its scenarios "
                              "reached)", **({"grid_mapping": "crs"} if gm else {})})
        tcoords = {}
        for name, values in self.thresholds.items():
            dim, _ = THRESHOLD_DIMS[name]
            what = name.replace("_", " ")
            tcoords[dim] = (dim, np.asarray(values, dtype=float),
                            {"long_name": f"{what} threshold",
                             "units": THRESHOLD_UNITS[name]})
            tshape, tchunks = (len(values), *shape), (1, *chunks)
            gm_attr = {"grid_mapping": "crs"} if gm else {}
            data[f"{name}_exceedance_count"] = (
                (dim, "y", "x"), da.zeros(tshape, dtype=np.int32, chunks=tchunks),
                {"long_name": f"number of runs (release and scenario) whose {what} exceeds "
                              "the threshold", "comment": "where the run reached the cell; "
                              "divided by scenario_count: the fraction over the releases "
                              "reaching the cell", **gm_attr})
            data[f"{name}_exceedance_probability"] = (
                (dim, "y", "x"), da.full(tshape, np.nan, dtype=np.float32, chunks=tchunks),
                {"long_name": f"probability that the {what} exceeds the threshold",
                 "units": "1", "cell_methods": "area: maximum",
                 "comment": "largest over the releases reaching the cell of the fraction "
                            "of a release's scenarios whose run exceeds the threshold "
                            "there; NaN where no release reaches", **gm_attr})
            encoding[f"{name}_exceedance_probability"] = {"_FillValue": np.float32(np.nan)}
        coords = {**tcoords, "x": ("x", dem.x(), {"standard_name": "projection_x_coordinate",
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

    def add(self, rid: int, parts) -> None:
        """Merge one release into the store: ``parts`` holds ``(window, maps, threshold)``
        of each of its scenarios that ran (its peak maps, north first, on its window, and
        its runout threshold). The release's own maximum over its scenarios is merged as
        one release is; its exceedance counts and fractions as sums and a maximum."""
        r0 = min(w[0] for w, _, _ in parts)
        r1 = max(w[1] for w, _, _ in parts)
        c0 = min(w[2] for w, _, _ in parts)
        c1 = max(w[3] for w, _, _ in parts)
        ch = self.chunk
        # the chunks the windows touch: whole chunks read and written, none shared
        R0, C0 = r0 // ch * ch, c0 // ch * ch
        R1, C1 = min(-(-r1 // ch) * ch, self.dem.height), min(-(-c1 // ch) * ch, self.dem.width)
        slab = (slice(R0, R1), slice(C0, C1))
        shape = (R1 - R0, C1 - C0)
        reached = np.zeros(shape, dtype=bool)
        best = {name: np.full(shape, np.nan, dtype=np.float32) for name in self.fields}
        counts = {name: np.zeros((len(t), *shape), dtype=np.int32)
                  for name, t in self.thresholds.items()}
        for (w0, w1, v0, v1), maps, threshold in parts:
            inner = (slice(w0 - R0, w1 - R0), slice(v0 - C0, v1 - C0))
            here = np.zeros(shape, dtype=bool)
            here[inner] = np.nan_to_num(maps["peak_thickness"], nan=0.0) > threshold
            reached |= here
            for name in self.fields:
                new = np.full(shape, np.nan, dtype=np.float32)
                new[inner] = maps[name]
                new = np.where(here, new, np.nan)
                best[name] = np.where(np.isnan(best[name]) | (new > best[name]), new,
                                      best[name])
            for name, thresholds in self.thresholds.items():
                from avflow.ensemble.dataset import exceedances

                peak = np.full(shape, np.nan, dtype=np.float32)
                peak[inner] = maps[name]
                for k, over in enumerate(exceedances(name, peak, thresholds, here)):
                    counts[name][k] += over & here
        if not reached.any():
            return
        count = self.group["release_count"]
        count[slab] = count[slab] + reached
        for name in self.fields:
            new = best[name]
            cur, ids = self.group[name][slab], self.group[f"{name}_release"][slab]
            better = reached & (np.isnan(cur) | (new > cur) | ((new == cur) & (rid < ids)))
            self.group[name][slab] = np.where(better, new, cur)
            self.group[f"{name}_release"][slab] = np.where(better, rid, ids).astype(np.int32)
        if not self.counting:
            return
        n = len(parts)  # the release's scenarios that ran: its fractions' denominator
        scen = self.group["scenario_count"]
        scen[slab] = scen[slab] + reached.astype(np.int32) * np.int32(n)
        for name, c in counts.items():
            total = self.group[f"{name}_exceedance_count"]
            total[:, slab[0], slab[1]] = total[:, slab[0], slab[1]] + c
            prob = self.group[f"{name}_exceedance_probability"]
            cur = prob[:, slab[0], slab[1]]
            mine = np.where(reached, (c / np.float64(n)).astype(np.float32), np.nan)
            prob[:, slab[0], slab[1]] = np.where(np.isnan(cur) | (mine > cur), mine, cur)
