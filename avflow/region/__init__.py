"""Regional hazard maps: every release area of a region in its own window of one DEM, run
on dask as ensembles are, merged into chunked Zarr maps (``avflow region``).

A stage above :mod:`avflow.ensemble` (whose dask client and checksums it uses); nothing
below imports it.
"""

from avflow.region.spec import Region, RegionError, load_region, parse_region

__all__ = ["Region", "RegionError", "load_region", "parse_region"]
