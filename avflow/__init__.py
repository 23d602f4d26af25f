"""avflow: debris-avalanche scenarios with the kinetic Saint-Venant scheme of
Mangeney-Castelnau et al. (2003), with Dirac stopping under the Coulomb threshold.

Public API:

- :func:`load_scenario` reads and validates a scenario YAML file (``Scenario.with_updates``
  derives variants by dotted path);
- :func:`run` runs a scenario (a path or a loaded scenario) and returns a CF ``xarray.Dataset``;
- :func:`open_run` reads a file written by ``avflow run`` as the same Dataset;
- :func:`run_ensemble` runs an ensemble (a file, a mapping or a list of scenarios);
- :func:`run_region` runs every release area of a region into merged Zarr maps.
"""

__version__ = "0.1.0"

from avflow.errors import AvflowError, ScenarioError  # noqa: E402
from avflow.scenario import load_scenario  # noqa: E402


def run(scenario, progress=None, max_memory=None, *, overrides=None):
    """Run a scenario and return its results as a CF ``xarray.Dataset``.

    Parameters
    ----------
    scenario : str, path or Scenario
        A scenario YAML file, or a :class:`~avflow.scenario.schema.Scenario` from
        :func:`load_scenario` (``load_scenario(f).with_updates({"grid.dx": 5.0})`` gives a
        variant; relative data paths keep starting at the file's folder).
    progress : callable, optional
        ``progress(t, t_end)`` is called after every output time with the simulated time
        and the end time (s), e.g. ``lambda t, end: print(f"{t:.0f}/{end:g} s")``; None
        (default): nothing is reported while the run goes on.
    max_memory : int or str, optional
        Refuse, before anything is allocated, a run estimated to need more (bytes, or a size
        such as ``"8G"``; ``"none"`` switches the check off); default ``$AVFLOW_MAX_MEMORY``,
        else half the machine's memory.
    overrides : dict, optional
        Dotted field -> value changes, as ``avflow run --set KEY=VALUE`` does.

    Returns
    -------
    xarray.Dataset
        Fields ``h``, ``u`` (``v``), ``flow_state`` on ``(time, x)`` or ``(time, y, x)``,
        maps (``peak_thickness``, ``deposit_thickness``...), 0-d summaries (``runout``,
        ``time_to_stop``, ``wall_time`` for the time loop, ``compile_time`` for Numba) and
        the scenario in the attributes. ``time`` holds seconds since the release (units
        ``s``; its ``release_time`` attribute is ``output.release_time``), so
        ``ds.h.sel(time=40, method="nearest")`` works; :func:`open_run` and plain
        ``xr.open_dataset`` read a written file back the same way.

    Raises
    ------
    avflow.errors.ScenarioError
        The scenario is invalid (one line per problem: file:line:col: field: message).
    avflow.errors.RunFailed
        The run blew up (non-finite state): never a result; ``.result`` holds the run up to
        the failure.
    """
    from avflow.output.dataset import to_dataset
    from avflow.simulation.runner import simulate

    if not hasattr(scenario, "terrain"):
        scenario = load_scenario(scenario)
    if overrides:
        from avflow.ensemble.spec import apply_overrides

        scenario = apply_overrides(scenario, overrides)
    return to_dataset(simulate(scenario, progress=progress, max_memory=max_memory))


def open_run(path):
    """A file written by ``avflow run`` (or an ensemble member) as :func:`run` returned it.

    ``time`` in seconds since the release, the CRS as the grid-mapping variable ``crs``
    (``ds.set_coords("crs").rio.crs`` with rioxarray), the fields as float64 and
    ``flow_state`` as int8 with -1 outside the mesh, all loaded in memory (the file is
    closed). Values are those of the file: the fields were stored as float32.
    """
    import numpy as np
    import xarray as xr

    with xr.open_dataset(path, decode_times=False, decode_timedelta=False) as ds:
        ds = ds.load()
    for name, var in ds.variables.items():
        if var.dtype == np.float32:
            ds[name] = var.astype(np.float64)
    if "flow_state" in ds and ds["flow_state"].dtype.kind == "f":  # -1 was masked to NaN
        attrs = dict(ds["flow_state"].attrs)
        ds["flow_state"] = ds["flow_state"].fillna(-1).astype(np.int8)
        ds["flow_state"].attrs = {**attrs, "_FillValue": np.int8(-1)}
    for var in ds.variables.values():
        var.encoding = {k: v for k, v in var.encoding.items() if k == "coordinates"}
    return ds


def run_ensemble(ensemble, outdir, *, workers=None, scheduler=None, overrides=None,
                 name=None, quiet=False, report=False):
    """Run an ensemble into ``outdir`` and return its ``ensemble.nc`` as an ``xarray.Dataset``.

    Parameters
    ----------
    ensemble : path, dict or list of Scenario
        An ensemble YAML file; a dict with the keys of one (``base``: a scenario file
        relative to the working folder, or a Scenario; ``vary``, ``sample``,
        ``thresholds``); or a list of scenarios (Scenario objects or files), one member
        each, whose differing fields are the varied parameters.
    outdir : path
        Output folder (members/, summary.csv, ensemble.nc); a rerun resumes.
    workers : int, optional
        Local worker processes; 0 runs the members here, one after the other; None
        (default) chooses by the members' size and says so on stderr.
    scheduler : str, optional
        Address or scheduler file of a running dask scheduler.
    overrides : dict, optional
        Dotted field -> value changes of the base scenario (``--set``).
    name : str, optional
        Name of the ensemble (lists of scenarios: default ``<first name>-ensemble``).
    quiet : bool
        No progress line nor information on stderr (failed members are still reported).
    report : bool
        Also write ``outdir/report.md`` with its figures.

    Every member and file is as ``avflow ensemble`` makes it; ``summary.csv`` beside the
    Dataset has the same rows as a table. A failed member does not raise:
    its ``status`` is ``failed`` and ``error`` says why.
    """
    import xarray as xr

    from avflow.ensemble.orchestrate import ProgressLine
    from avflow.ensemble.orchestrate import run_ensemble as _run
    from avflow.ensemble.spec import ensemble_from

    spec = ensemble_from(ensemble, name=name, overrides=overrides)
    _run(spec, outdir, workers=workers, scheduler=scheduler,
         progress=ProgressLine(len(spec.members), quiet=quiet))
    if report:
        from avflow.ensemble.report import write_report

        write_report(outdir)
    from pathlib import Path

    with xr.open_dataset(Path(outdir) / "ensemble.nc", decode_times=False) as ds:
        return ds.load()


def calibrate(calibration, outdir, *, workers=None, scheduler=None, quiet=False):
    """Calibrate a scenario to an observed event (``avflow calibrate``): see
    :func:`avflow.calibration.calibrate`; returns its CalibrationResult."""
    from avflow.calibration import calibrate as _calibrate

    return _calibrate(calibration, outdir, workers=workers, scheduler=scheduler, quiet=quiet)


def run_region(region, outdir, *, workers=None, scheduler=None, quiet=False):
    """Run every release of a region file (``avflow region``) into ``outdir`` and return
    the merged maps, ``outdir/region.zarr``, as a lazy ``xarray.Dataset`` (``xr.open_zarr``).

    ``region``: a region YAML file or a :class:`avflow.region.Region`; ``workers``: local
    worker processes (0: here, no dask; None: one per core); ``scheduler``: address or
    scheduler file of a running dask scheduler. ``outdir/releases.csv`` has one row per
    release (status, volume, runout, travel angle, area, retries, wall time); a release
    that cannot run is a row with its error, never an exception. See docs/guide/region.md.
    """
    import xarray as xr

    from avflow.region import load_region
    from avflow.region.orchestrate import run_region as _run

    if not hasattr(region, "scenario_for"):
        region = load_region(region)
    outcome = _run(region, outdir, workers=workers, scheduler=scheduler, quiet=quiet)
    return xr.open_zarr(outcome.store)


__all__ = ["__version__", "AvflowError", "ScenarioError", "load_scenario", "run", "open_run",
           "run_ensemble", "calibrate", "run_region"]
