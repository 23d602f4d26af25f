"""Stage 6, ensembles: many scenarios, run on dask, summarised.

- :mod:`avflow.ensemble.spec`: ensemble files -> validated members;
- :mod:`avflow.ensemble.orchestrate`: members on dask (or in process), resume, failures;
- :mod:`avflow.ensemble.dataset`: ``ensemble.nc`` along ``realization``;
- :mod:`avflow.ensemble.report`: ``avflow report``.
"""
