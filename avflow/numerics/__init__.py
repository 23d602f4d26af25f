"""Stage 3, the numerics: pure arrays and scalars, nothing of YAML, xarray or dask.

- :mod:`avflow.numerics.kinetic`: rectangular-Maxwellian half fluxes (seed eqs. 28-41);
- :mod:`avflow.numerics.rheology`: friction laws behind one signature (eqs. 15, 42-50);
- :mod:`avflow.numerics.kernels`: the Numba sweeps of one step and the time loop (eqs. 26-56);
- :mod:`avflow.numerics.solver`: :class:`~avflow.numerics.solver.Solver` and its state;
- :mod:`avflow.numerics.analytic`: exact dam-break solutions to test against.
"""
