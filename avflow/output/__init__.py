"""Stage 5, the outputs: CF-1.11 NetCDF (grids and UGRID), GeoTIFF/ASCII maps, plots.

- :mod:`avflow.output.cf`: the variables, summaries and attributes every file shares;
- :mod:`avflow.output.dataset`, :mod:`avflow.output.ugrid`: a run as an ``xarray.Dataset``;
- :mod:`avflow.output.netcdf`: atomic writes (temporary name, then rename);
- :mod:`avflow.output.maps`: ``avflow export`` and ``avflow plot``.
"""
