"""avflow: debris-avalanche runs from scenario files (run, ensemble, report, export, plot, path,
region, calibrate, compare, release-areas, zoning).

Exit codes: 0 success, 1 the run failed numerically, 2 bad input (scenario or command line).
Errors in the input are one line naming the file and the field; no output file is left
behind (the NetCDF is written to a temporary name and renamed only when complete).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

from avflow import __version__
from avflow.errors import AvflowError

#: Extension files (paths separated by os.pathsep) that every command reading a scenario
#: loads, before those of --extensions
ENV_EXTENSIONS = "AVFLOW_EXTENSIONS"


class Progress:
    """Simulated time against end time on one terminal line (silent when not a terminal)."""

    def __init__(self, stream=sys.stderr, quiet: bool = False):
        self.stream = stream
        self.live = stream.isatty() and not quiet
        self.started = time.perf_counter()

    def __call__(self, t: float, t_end: float) -> None:
        if not self.live:
            return
        width = 30
        done = int(width * min(t / t_end, 1.0))
        wall = time.perf_counter() - self.started
        self.stream.write(f"\r  [{'#' * done}{'.' * (width - done)}] t = {t:8.2f} / {t_end:g} s"
                          f"  ({wall:5.1f} s wall)")
        self.stream.flush()

    def close(self) -> None:
        if self.live:
            self.stream.write("\n")


def _compiling(what: str) -> None:
    from avflow.numerics.compiling import notify_compiling

    notify_compiling(what)


def _announce_compiles(args) -> None:
    """Ensembles, regions and calibrations: one line on stderr when this process compiles
    kernels, and how long it took (quiet with -q)."""
    if not args.quiet:
        from avflow.numerics.compiling import announce

        announce()


def _compiled(seconds: float) -> None:
    from avflow.numerics.compiling import notify_compiled

    notify_compiled(seconds)


def summary_line(ds) -> str:
    """One line: what the run did and where the mass ended."""
    def f(name, fmt):
        v = float(ds[name])
        return "NaN" if math.isnan(v) else format(v, fmt)

    status = ds.attrs["status"]
    ended_by = ds.attrs.get("ended_by", "")
    moving = moving_share(ds)
    if status == "ended_by_rule":
        status += (f" (kinetic-energy rule, {moving} of the volume still moving: "
                   "not a deposit at rest)")
    elif status not in ("at_rest", "stopped") and ended_by:
        status += (f" ({ended_by.replace(', still moving', '')}, {moving} of the volume "
                   "still moving: not a deposit at rest)")
    elif status != "failed":  # at rest by the rule: a few thin cells may still move
        status += f" ({moving} of the volume still moving)"
    if int(ds.attrs.get("runout_truncated", 0)):
        status += ", RUNOUT TRUNCATED by the map's edge (a lower bound: enlarge the map)"
    profile = ds["peak_thickness"].dims == ("x",)
    from avflow.output.maps import runout_text

    runout = runout_text(ds, 1) or "runout: none"
    if math.isnan(float(ds["runout"])):  # no cell above the runout threshold: say why
        left = float(ds["outflow_volume"]) if "outflow_volume" in ds else 0.0
        released = max(float(ds["release_volume"]), 1e-300)
        runout = ("runout: none on the map (all the mass flowed out over its edge)"
                  if left >= 0.999 * released else
                  "runout: none (no cell above the runout threshold)"
                  if profile or not ds.attrs.get("runout_path") else
                  f"runout: none (no cell reaches {ds.attrs.get('runout_limit', '')} "
                  f"along the {ds.attrs['runout_path']})")
    stop = float(ds["time_to_stop"])
    if math.isnan(stop):  # never at rest: say by when, not NaN
        end = float(ds["time"][-1]) if "time" in ds.coords and ds["time"].size else math.nan
        stop_note = (f", not at rest by {end:.4g} s"
                     if math.isfinite(end) else ", not at rest")
    else:
        stop_note = f", time_to_stop {stop:.2f} s"
    return (f"{ds.attrs['scenario_name']}: {status}"
            f"{stop_note}"
            f", {runout}"
            f", deposit max {f('deposit_max_thickness', '.2f')} m"
            f", length {f('deposit_length', '.1f')} m"
            f", mass error {f('mass_balance_error', '.1e')}"
            + _entrained_note(ds)
            + _structure_note(ds)
            + f", {ds.attrs['steps']} steps{_order_note(ds)} in {f('wall_time', '.2f')} s"
            + _compile_note(ds))


def moving_share(ds) -> str:
    """The volume still moving at the end over the volume there was (released plus
    entrained), as a percentage with enough digits to be nonzero when it is."""
    from avflow.output.maps import moving_percent

    share = float(moving_percent(ds))
    return "0%" if share == 0 else f"{share:.2g}%" if share < 10 else f"{share:.0f}%"


def _entrained_note(ds) -> str:
    """`` (released 1.2e+04 + entrained 3.4e+03 = on the map 1.5e+04 + out 0 m3)``: the
    balance of a run with entrainment or registered sources (``+ supplied ...``); nothing
    for the others."""
    supplied = "supplied_volume" in ds
    secondary = "secondary_release_volume" in ds
    if not (supplied or secondary) and ("entrainment_law" not in ds.attrs
                                        or "entrained_volume" not in ds):
        return ""
    units = ds["release_volume"].attrs.get("units", "m3")
    v = {name: float(ds[name]) for name in ("release_volume", "entrained_volume",
                                            "deposit_volume", "outflow_volume")}
    added = (f" + entrained {v['entrained_volume']:.4g}" if "entrainment_law" in ds.attrs
             else "") + (f" + supplied {float(ds['supplied_volume']):.4g}" if supplied else "")
    if secondary:  # the secondary release areas the flow reached
        added += f" + secondary {float(ds['secondary_release_volume']):.4g}"
    return (f" (released {v['release_volume']:.4g}{added}"
            f" = on the map {v['deposit_volume']:.4g} + out {v['outflow_volume']:.4g} "
            f"{units})")


def _structure_note(ds) -> str:
    from avflow.output.structures import structure_note

    return structure_note(ds) if "structure_retained_volume" in ds else ""


def _order_note(ds) -> str:
    """`` at order 2``: the scheme's order (the default differs by terrain: 2 on square
    grids, 1 on profiles and triangles)."""
    order = ds.attrs.get("numerics_order")
    return "" if order is None else f" at order {int(order)}"


def _compile_note(ds) -> str:
    """`` (+ 9.81 s compiling)``: Numba's compilation, apart from the time loop (shown from
    0.05 s: loading the kernels from Numba's cache takes a few hundredths)."""
    if "compile_time" not in ds:
        return ""
    seconds = float(ds["compile_time"])
    return f" (+ {seconds:.2f} s compiling)" if seconds >= 0.05 else ""


def _load_extensions(given: list[str]) -> None:
    """The extension files of $AVFLOW_EXTENSIONS, then those of ``--extensions``, each run
    once (:func:`avflow.scenario.extensions.load_file`): what they register is then known to
    the scenario, and the files travel with the members to the workers."""
    from avflow.files import read_input
    from avflow.scenario.extensions import MAPS, ExtensionFileError, load_file

    listed = [(f"${ENV_EXTENSIONS}", path) for path in
              os.environ.get(ENV_EXTENSIONS, "").split(os.pathsep) if path]
    for origin, path in listed + [("--extensions", path) for path in given]:
        read_input(path)  # an input of the command: no output may replace it
        try:
            _check_extension_file(path)
            before = set(MAPS)
            load_file(path)
            _check_map_names(path, [name for name in MAPS if name not in before])
        except ExtensionFileError as err:
            raise ExtensionFileError(f"{origin}: {err}") from None


#: An extension file is Python source of a few laws: larger is no extension file.
MAX_EXTENSION_BYTES = 16 << 20


def _check_extension_file(path) -> None:
    """Refuse, before Python reads it, an extension file that is a device or a pipe
    (``/dev/zero`` would be read without end, a FIFO waits for a writer) or too large."""
    import stat

    from avflow.scenario.extensions import ExtensionFileError

    try:
        st = os.stat(path)
    except OSError:
        return  # missing, a loop of links: said by load_file
    if stat.S_ISDIR(st.st_mode):
        return
    if not stat.S_ISREG(st.st_mode):
        raise ExtensionFileError(f"{path}: not a regular file (a device, a pipe or a "
                                 "socket); give a Python file")
    if st.st_size > MAX_EXTENSION_BYTES:
        raise ExtensionFileError(f"{path}: over {MAX_EXTENSION_BYTES >> 20} MiB: not an "
                                 "extension file")


def _check_map_names(path, names) -> None:
    """A registered map may not take the name of a variable every run file has (it would
    silently replace ``peak_thickness``...)."""
    if not names:
        return
    from avflow.output.cf import FIELDS, SUMMARIES
    from avflow.scenario.extensions import ExtensionFileError

    for name in names:
        if name in FIELDS or name in SUMMARIES:
            raise ExtensionFileError(f"{path}: a map named {name!r} would replace the run "
                                     "file's own variable of that name; give it another name")


def _extension_hint(err: AvflowError) -> str:
    """After a scenario's unknown law or source, where a law of one's own comes from (on
    the commands that take --extensions)."""
    import re

    if re.search(r"\b(rheology|sources\.\d+)(\.law: unknown law|: no source is registered)",
                 str(err)):
        return " (a law or source of your own: load its file with --extensions FILE.py)"
    return ""


def _load_with_sets(args):
    """The scenario of ``avflow run``, with the ``--set KEY=VALUE`` changes applied."""
    from avflow.ensemble.spec import apply_overrides, parse_overrides
    from avflow.scenario.schema import load_scenario

    sets = list(args.set)
    if getattr(args, "threads", None) is not None:
        sets.append(f"numerics.threads={args.threads}")
    if getattr(args, "backend", None) is not None:
        sets.append(f"numerics.backend={args.backend}")
    overrides = parse_overrides(sets)  # a malformed --set: exit 2 before reading
    scenario = apply_overrides(load_scenario(args.scenario), overrides)
    if getattr(args, "without_structures", False):  # the twin run without its structures
        scenario = scenario.with_updates({"structures": ()})
    return scenario


def _cmd_run(args) -> int:
    from avflow.files import output_lock, protected
    from avflow.output.netcdf import (OutputWriteError, check_output_path,
                                      remove_stale_temporaries)
    from avflow.output.stream import SnapshotStream
    from avflow.simulation.runner import SUCCESS_STATUSES, simulate

    scenario = _load_with_sets(args)
    out = Path(args.output) if args.output else Path(Path(args.scenario).stem + ".nc")
    # Checked before the run (exit 2): not an input nor one of their sidecars, not a folder
    # nor a device, writable; likewise the path analysis' files beside it.
    inputs = protected([args.scenario, *scenario.input_files()])
    check_output_path(out, inputs)
    if scenario.output.path is not None:
        from avflow.output.path import check_path_outputs, read_line

        check_path_outputs(out.with_name(out.stem + "_path"), inputs)
        if scenario.output.path.line:
            read_line(scenario.output.path.line)  # a bad path line: exit 2 before the run
    if scenario.output.points is not None:  # OUT_points.csv and .png, checked likewise
        from avflow.output.points import sidecar_paths

        for side in sidecar_paths(out):
            check_output_path(side, inputs)
    with output_lock(out):  # a second run to the same OUT says so, and leaves this one be
        remove_stale_temporaries(out)  # left by a write that was killed
        progress = Progress(quiet=args.quiet)
        try:
            # Each snapshot goes to .OUT.XXXXXXXX.tmp as it is taken; renamed to OUT at the
            # end. A failed or interrupted run, or a failed write, leaves no file (an old OUT
            # intact).
            with SnapshotStream(out) as stream:
                try:
                    result = simulate(scenario, progress=progress,
                                      max_memory=args.max_memory, snapshots=stream,
                                      on_compile=None if args.quiet else _compiling,
                                      on_compiled=None if args.quiet else _compiled)
                finally:
                    progress.close()
                if result.status not in SUCCESS_STATUSES:  # exit 1 writes nothing
                    state = result.state
                    print(f"avflow: error: {args.scenario}: time.max_steps "
                          f"({scenario.time.max_steps}) reached at t = {state.t:.6g} s of "
                          f"{scenario.time.end:g} s, the flow still moving; no file written "
                          "(raise time.max_steps, or use a larger grid.dx)", file=sys.stderr)
                    return 1
                rest = stream.finish(result)
        except OutputWriteError as err:  # full disk: exit 1, nothing left behind
            print(f"avflow: error: {err}", file=sys.stderr)
            return 1
        import xarray as xr

        # the engine named: guessing it loads every installed backend (rioxarray's, dask)
        with xr.open_dataset(out, decode_times=False, engine="netcdf4") as on_disk:
            # the run as avflow.run returns it: the fields on (time, space) read from the
            # file when asked for (the path analysis reads h at t = 0), the rest from memory
            ds = rest.assign({name: on_disk[name].variable for name in on_disk.data_vars
                              if name not in rest.variables})
            code = _after_run(args, scenario, out, ds, result.status, inputs)
        if result.points is not None:
            _write_points(args, result, out)
        return code


def _write_points(args, result, out: Path) -> None:
    """OUT_points.csv and OUT_points.png of a run with points of interest, and one line."""
    from avflow.output.points import (plot_points, points_dataset, sidecar_paths,
                                      write_points_csv)

    ds = points_dataset(result)
    csv_path, png_path = sidecar_paths(out)
    write_points_csv(ds, csv_path)
    plot_points(ds, png_path, f"{result.scenario.name}: flow at the points of interest")
    if not args.quiet:
        arrivals = ", ".join(
            f"{n} {'not reached' if math.isnan(t) else f'at {t:.1f} s'} (peak {p:.3g} kPa)"
            for n, t, p in zip(ds["station_name"].values, ds["arrival_time"].values,
                               ds["peak_pressure"].values))
        print(f"points: {arrivals}")
        print(f"wrote {csv_path}, {png_path} (and the group 'points' of {out})")


def _after_run(args, scenario, out: Path, ds, status: str, inputs=None) -> int:
    """The warnings, the summary line and the path analysis of a written run."""
    if int(ds.attrs.get("runout_truncated", 0)):
        print(f"avflow: warning: {args.scenario}: material reached the edge of the map; the "
              "runout is a lower bound (enlarge the map or the DEM)", file=sys.stderr)
    if not args.quiet:
        print(summary_line(ds))
        print(f"wrote {out}")
    if scenario.output.path is not None:
        _run_path(ds, scenario.output.path, out, args.quiet, inputs)
    from avflow.simulation.runner import SUCCESS_STATUSES

    return 0 if status in SUCCESS_STATUSES else 1


def _run_path(ds, block, out: Path, quiet: bool = False, inputs=None) -> None:
    """output.path of a run: OUT_path.csv/.md/.png and one line; a warning if impossible."""
    from avflow.output.path import PathSettings, summary_line as path_line, write_run_path

    try:
        result, written = write_run_path(ds, PathSettings.from_scenario(block),
                                         out.with_name(out.stem + "_path"), inputs)
    except AvflowError as err:
        print(f"avflow: warning: path analysis: {err}", file=sys.stderr)
        return
    if quiet:
        return
    truncated = bool(int(ds.attrs.get("runout_truncated", 0)))
    reach = ds["reach_from_release_centroid"] if "reach_from_release_centroid" in ds \
        else ds["runout"]
    print(path_line(result, float(reach), truncated))
    print("wrote " + ", ".join(str(w) for w in written))


def _cmd_compare(args) -> int:
    from avflow.output.structures import compare_runs

    text, written = compare_runs(args.run_a, args.run_b, args.output)
    if not args.quiet:
        print(text)
        print("wrote " + ", ".join(str(w) for w in written))
    return 0


def _cmd_release_areas(args) -> int:
    from avflow.files import check_target, protected
    from avflow.terrain.release_areas import (PRASettings, potential_release_areas,
                                              write_release_areas)

    settings = _option_named(PRASettings,
        slope_min=args.slope_min, slope_max=args.slope_max, snow_depth=args.snow_depth,
        roughness=not args.no_roughness, wind_direction=args.wind_direction,
        wind_tolerance=args.wind_tolerance, threshold=args.threshold,
        max_curvature=args.max_curvature, min_area=args.min_area,
        split_aspect_deg=args.split_aspect, d0=args.d0,
        reference_elevation=args.reference_elevation, gradient=args.gradient,
        slope_correction=not args.no_slope_correction)
    inputs = protected([args.dem, args.forest])
    check_target(args.output, inputs, what="release areas")
    if args.index_raster:
        check_target(args.index_raster, inputs, what="release index raster")
    result = potential_release_areas(args.dem, settings, forest=args.forest)
    written = write_release_areas(result, args.output, args.index_raster)
    if result.crs_wkt is None:
        print(f"avflow: warning: {args.dem}: no CRS; the release areas are written without "
              "one (in the DEM's coordinates)", file=sys.stderr)
    if not args.quiet:
        total = sum(a["area_m2"] for a in result.areas)
        thick = [a["thickness"] for a in result.areas if "thickness" in a]
        line = (f"{len(result.areas)} potential release areas, {total / 1e4:.2f} ha in all "
                f"(slope {settings.slope_min:g}-{settings.slope_max:g} deg"
                f"{', roughness' if settings.roughness else ''}"
                f"{', wind from %g deg' % settings.wind_direction if settings.wind_direction is not None else ''})")
        if thick:
            line += f", thickness {min(thick):.2f} to {max(thick):.2f} m"
        print(line)
        print("wrote " + ", ".join(str(w) for w in written))
    return 0


#: The option of ``avflow release-areas`` that sets each field of its settings.
_RELEASE_OPTIONS = {"split_aspect_deg": "--split-aspect", "roughness": "--no-roughness",
                    "slope_correction": "--no-slope-correction"}


def _option_named(settings, **values):
    """``settings(**values)``; its error names the command-line option, not the field."""
    from avflow.terrain.release_areas import PRAError

    import re

    try:
        return settings(**values)
    except PRAError as err:
        def option(match):
            name = match.group(0)
            return _RELEASE_OPTIONS.get(name, "--" + name.replace("_", "-"))

        words = "|".join(sorted(map(re.escape, values), key=len, reverse=True))
        raise PRAError(re.sub(rf"\b({words})\b", option, str(err))) from None


def _cmd_path(args) -> int:
    from avflow.output.path import analyse_target

    text, written = analyse_target(args.target, line=args.line, field=args.field,
                                   threshold=args.threshold, width=args.width,
                                   output=args.output, regression=args.alpha_beta)
    if not args.quiet:
        print(text)
        print("wrote " + ", ".join(str(w) for w in written))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="avflow",
                                description=" ".join(__doc__.split("\n\n")[0].split()))
    p.add_argument("--version", action="version", version=f"avflow {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    quiet = argparse.ArgumentParser(add_help=False)
    quiet.add_argument("-q", "--quiet", action="store_true", help="print nothing but warnings "
                       "and errors (no progress, no summary line)")
    sets = argparse.ArgumentParser(add_help=False)
    sets.add_argument("--set", action="append", metavar="KEY=VALUE", default=[],
                      help="change one scenario field by its dotted path, the value in YAML "
                      "(e.g. --set grid.dx=5 --set rheology.delta_deg=18); repeatable; data "
                      "paths still start at the scenario file's folder")
    extensions = argparse.ArgumentParser(add_help=False)
    extensions.add_argument("--extensions", action="append", metavar="FILE.py", default=[],
                            help="a Python file of your own friction laws, sources or output "
                            "maps (avflow.extend), loaded before the scenario is read, and "
                            "by the workers that run it; repeatable; also "
                            f"${ENV_EXTENSIONS} (paths separated by {os.pathsep!r})")
    r = sub.add_parser("run", help="run one scenario and write a CF NetCDF file",
                       parents=[quiet, sets, extensions])
    r.add_argument("scenario", help="scenario YAML file")
    r.add_argument("-o", "--output", help="output NetCDF (default: the scenario file's name "
                   "with .nc, in the current folder)")
    r.add_argument("--max-memory", metavar="SIZE", help="refuse a run estimated to need more "
                   "(bytes, or 8G, 512M; 'none': no check; default: $AVFLOW_MAX_MEMORY, "
                   "else half of this machine's memory)")
    r.add_argument("--threads", type=int, metavar="N", help="CPU threads of the time loop "
                   "(numerics.threads; default: every core this process may use where a few "
                   "timed steps show them faster than one thread, else one); the answer does "
                   "not depend on it")
    r.add_argument("--backend", choices=("cpu", "cuda"), help="where the time loop runs "
                   "(numerics.backend; cuda: a GPU, square grids at orders 1 and 2, "
                   "docs/guide/gpu.md)")
    r.add_argument("--without-structures", action="store_true",
                   help="run the scenario with its structures left out (the twin run that "
                        "avflow compare sets beside the one with them)")
    r.set_defaults(func=_cmd_run)
    e = sub.add_parser("ensemble", help="run an ensemble file (here or on dask); exit 1 if "
                                        "a member failed",
                       parents=[quiet, sets, extensions])
    e.add_argument("ensemble", help="ensemble YAML file (base scenario + vary/sample)")
    e.add_argument("-o", "--output", required=True, help="output folder (resumable)")
    e.add_argument("--scheduler", help="address (tcp://host:port) or scheduler file of a "
                                       "running dask scheduler (default: a local cluster)")
    e.add_argument("--connect-timeout", type=float, default=10.0, metavar="S",
                   help="seconds to reach --scheduler before giving up (default: 10)")
    e.add_argument("--workers", type=int, help="local worker processes (0: run in this "
                   "process, no dask; default: chosen by the size of the members, said on "
                   "stderr: a few short members run here, others on one worker per core)")
    e.add_argument("--batch", type=int, help="members per dask task (default: automatic)")
    e.add_argument("--max-memory", metavar="SIZE", help="refuse a member estimated to need "
                   "more (as for avflow run; passed to local workers as $AVFLOW_MAX_MEMORY)")
    e.add_argument("--max-members", type=int, metavar="N", help="refuse an ensemble of more "
                   "members (default: $AVFLOW_MAX_MEMBERS, else 10000)")
    e.add_argument("--report", action="store_true", help="write OUTDIR/report.md at the end")
    e.add_argument("--backend", choices=("cpu", "cuda"), help="where every member's time "
                   "loop runs (numerics.backend; cuda: one GPU per worker, docs/guide/gpu.md)")
    e.set_defaults(func=_cmd_ensemble)
    rp = sub.add_parser("report", help="write OUTDIR/report.md (PNG figures) of an ensemble "
                        "or a region", parents=[quiet])
    rp.add_argument("outdir", help="output folder of avflow ensemble (or its ensemble.nc), "
                    "or of avflow region (or its region.zarr)")
    rp.set_defaults(func=_cmd_report)
    x = sub.add_parser("export", help="write the maps of a grid run, or the probability maps "
                                      "of an ensemble.nc, as GeoTIFF or ESRI ASCII rasters "
                                      "(<stem>_<variable>.<ext>); the maps of a region's "
                                      "region.zarr as Cloud-Optimized GeoTIFFs",
                       parents=[quiet])
    x.add_argument("run_file", help="NetCDF written by avflow run, OUTDIR/ensemble.nc, or "
                                    "a region's OUTDIR (or OUTDIR/region.zarr)")
    x.add_argument("--format", choices=("tif", "asc"), default="tif",
                   help="GeoTIFF (default) or ESRI ASCII grid + .prj")
    x.add_argument("-o", "--output", help="output folder (default: next to RUN_FILE)")
    x.add_argument("--variables", help="comma-separated maps (default: peak_thickness, "
                                       "peak_speed, peak_pressure, peak_pressure_class, "
                                       "deposit_thickness, arrival_time, rest_time; of an "
                                       "ensemble.nc: every *_exceedance_probability, one "
                                       "raster per threshold; of a region: every map, and "
                                       "every *_exceedance_probability per threshold)")
    x.set_defaults(func=_cmd_export)
    z = sub.add_parser("zoning", help="hazard zones (red, blue, yellow) from peak pressure "
                       "and return period: a paletted GeoTIFF and its legend (PNG)",
                       parents=[quiet])
    z.add_argument("sources", nargs="+", metavar="SOURCE", help="YEARS=RUN.nc (a run of that "
                   "return period, repeatable, one grid for all; several runs of one return "
                   "period: their largest pressure), or the output folder of an avflow "
                   "region with scenarios.return_periods")
    z.add_argument("-o", "--output", help="output GeoTIFF (default: zoning.tif, in a region's "
                   "folder for a region); the legend is OUT_legend.png")
    z.add_argument("--red-kpa", type=float, default=30.0, metavar="KPA",
                   help="pressure from which a scenario up to --rare-years is red (default 30)")
    z.add_argument("--yellow-kpa", type=float, default=3.0, metavar="KPA",
                   help="pressure under which a scenario beyond --frequent-years is yellow "
                        "(default 3)")
    z.add_argument("--frequent-years", type=float, default=30.0, metavar="T",
                   help="return period up to which any flow is red (default 30)")
    z.add_argument("--rare-years", type=float, default=300.0, metavar="T",
                   help="return period beyond which any flow is yellow (default 300)")
    z.set_defaults(func=_cmd_zoning)
    pl = sub.add_parser("plot", help="draw a run to a PNG (peak thickness and peak-pressure "
                                     "classes over a hillshade; bed and snapshots on "
                                     "profiles; a region's merged maps, release outlines "
                                     "and the release that set each maximum)",
                        parents=[quiet])
    pl.add_argument("run_file", help="NetCDF written by avflow run, or a region's OUTDIR "
                                     "(or OUTDIR/region.zarr)")
    pl.add_argument("-o", "--output", help="PNG file (default: RUN_FILE with .png; "
                                           "OUTDIR/region.png for a region)")
    pl.add_argument("--map", default="both", choices=("both", "thickness", "pressure", "speed"),
                    help="on a map: both panels (peak thickness and peak-pressure classes, "
                         "the default), or one of them, or the peak speed")
    pl.add_argument("--extent", nargs=4, type=float, metavar=("XMIN", "XMAX", "YMIN", "YMAX"),
                    help="on a map: the part to draw, in the map's coordinates (m)")
    pl.add_argument("--dpi", type=int, default=120,
                    help="the image's resolution in dots per inch (default 120; 300 for print)")
    pl.set_defaults(func=_cmd_plot)
    pa = sub.add_parser("path", help="runout along the avalanche path (AvaFrame's AIMEC): "
                                     "table and PNG of a run file or an ensemble folder",
                        parents=[quiet])
    pa.add_argument("target", help="NetCDF written by avflow run, or an avflow ensemble "
                                   "folder")
    pa.add_argument("--line", help="path line (.shp, .geojson, .json, .csv of x, y; 'com': "
                                   "the flow's centre-of-mass track; default: the "
                                   "scenario's output.path.line, else 'com')")
    pa.add_argument("--field", choices=("pressure", "thickness"),
                    help="peak field that marks the runout point (default: pressure)")
    pa.add_argument("--threshold", type=float, help="kPa for pressure (default 1), m for "
                    "thickness (default: the run's runout threshold)")
    pa.add_argument("--width", type=float, help="width (m) of the band around the line "
                                                "whose cells count (default: every cell)")
    pa.add_argument("-o", "--output", help="output stem (default: RUN_path next to the run "
                                           "file, OUTDIR/path for an ensemble)")
    pa.add_argument("--alpha-beta", metavar="REGRESSION",
                    help="alpha-beta regression: norway (Lied and Bakkehoi 1980, the "
                         "default), austria, austria_small (AvaFrame com2AB's sets), or "
                         "k1,k2,k3,k4,sd for alpha = k1 beta + k2 z'' + k3 H0 + k4")
    pa.set_defaults(func=_cmd_path)
    ra = sub.add_parser("release-areas", help="potential release areas of a DEM (slope band, "
                        "roughness, wind shelter, forest, minimum area) as polygons with a "
                        "release thickness, for avflow region", parents=[quiet])
    ra.add_argument("dem", help="DEM (GeoTIFF, ESRI ASCII, any GDAL raster)")
    ra.add_argument("-o", "--output", required=True, help="polygon file (.gpkg, .shp, "
                                                          ".geojson, .fgb)")
    ra.add_argument("--slope-min", type=float, default=28.0, help="degrees (default 28)")
    ra.add_argument("--slope-max", type=float, default=60.0, help="degrees (default 60)")
    ra.add_argument("--snow-depth", type=float, default=2.3, help="m, the snow depth that "
                    "sets the roughness scales (default 2.3)")
    ra.add_argument("--no-roughness", action="store_true", help="leave the roughness out")
    ra.add_argument("--wind-direction", type=float, help="degrees from north the wind comes "
                    "from: adds the wind-shelter index (default: none)")
    ra.add_argument("--wind-tolerance", type=float, default=30.0, help="degrees either side "
                    "of the wind direction (default 30)")
    ra.add_argument("--threshold", type=float, default=0.0, help="release index (0..1) a "
                    "cell must exceed (default 0: the slope band and the roughness limit)")
    ra.add_argument("--max-curvature", type=float, help="1/m: leave out terrain more convex "
                    "than this (default: no limit)")
    ra.add_argument("--forest", help="forest raster (> 0 is forest) or polygons: excluded")
    ra.add_argument("--min-area", type=float, help="m2, smallest release area (default: 4 "
                    "cells)")
    ra.add_argument("--split-aspect", type=float, metavar="DEG", help="split connected "
                    "areas where the slope's direction changes sector (sectors of DEG)")
    ra.add_argument("--d0", type=float, help="m, reference release depth d0*: adds each "
                    "area's thickness by the Swiss rule (elevation gradient, slope correction)")
    ra.add_argument("--reference-elevation", type=float, default=2000.0,
                    help="m, where d0 holds (default 2000)")
    ra.add_argument("--gradient", type=float, default=0.05, help="m of depth per 100 m of "
                    "elevation (default 0.05)")
    ra.add_argument("--no-slope-correction", action="store_true",
                    help="thickness without the slope factor f(psi)")
    ra.add_argument("--index-raster", help="also write the release index as a GeoTIFF")
    ra.set_defaults(func=_cmd_release_areas)
    cm = sub.add_parser("compare", help="two runs of one map side by side (a scenario with "
                                        "and without its structures): runout, volumes, "
                                        "peak-pressure areas; table and PNG",
                        parents=[quiet])
    cm.add_argument("run_a", help="NetCDF written by avflow run (A, e.g. without the dam)")
    cm.add_argument("run_b", help="NetCDF written by avflow run (B, e.g. with the dam)")
    cm.add_argument("-o", "--output", help="output stem (default: B_vs_A next to B)")
    cm.set_defaults(func=_cmd_compare)
    _add_region_parser(sub, [quiet, extensions])
    ca = sub.add_parser("calibrate", help="calibrate parameters to an observed event "
                                          "(grid, lhs, bayes-opt, posterior); resumable",
                        description="Calibrate friction parameters to an observed event "
                        "(runout, impact area, deposit, values at points). The file's method "
                        "says how: grid (a regular grid of the ranges), lhs (a Latin "
                        "hypercube), bayes-opt (Bayesian optimisation with a Gaussian-process "
                        "surrogate, the default) or posterior (an emulator's posterior sampled "
                        "by MCMC, with Sobol indices). Resumable: run it again on the same "
                        "output folder to go on.",
                        parents=[quiet, extensions])
    ca.add_argument("calibration", help="calibration YAML file (base scenario, parameter "
                                        "ranges, observations, method, budget)")
    ca.add_argument("-o", "--output", required=True, help="output folder (members/, "
                    "calibration.nc, calibration.csv, report.md)")
    ca.add_argument("--workers", type=int, help="local worker processes (0: here, no dask; "
                    "default: as avflow ensemble chooses)")
    ca.add_argument("--scheduler", help="address or scheduler file of a running dask "
                                        "scheduler")
    ca.set_defaults(func=_cmd_calibrate)
    return p


def _add_region_parser(sub, parents) -> None:
    g = sub.add_parser("region", help="run every release area of a region file, each in its "
                       "own window of the DEM, and merge them into Zarr maps; exit 1 if a "
                       "release failed", parents=parents)
    g.add_argument("region", help="region YAML file (DEM, release polygons, scenario block)")
    g.add_argument("-o", "--output", required=True, help="output folder (region.zarr, "
                   "releases.csv, releases/; resumable)")
    g.add_argument("--workers", type=int, help="local worker processes (0: run here, no "
                   "dask; default: one per core)")
    g.add_argument("--scheduler", help="address (tcp://host:port) or scheduler file of a "
                   "running dask scheduler (default: a local cluster)")
    g.add_argument("--backend", choices=("cpu", "cuda"), help="where every release's time "
                   "loop runs (the scenario block's numerics.backend; cuda: one GPU per "
                   "worker, docs/guide/gpu.md)")
    g.set_defaults(func=_cmd_region)


def _cmd_region(args) -> int:
    from avflow.ensemble.orchestrate import Interrupted
    from avflow.region import load_region
    from avflow.region.orchestrate import run_region

    if args.workers is not None and args.workers < 0:
        raise AvflowError(f"--workers must be >= 0, got {args.workers}")
    region = load_region(args.region)  # every check of the file before any release runs
    _announce_compiles(args)
    numerics = region.scenario.get("numerics") or {}
    if args.backend is not None and args.backend != numerics.get("backend", "cpu"):
        import dataclasses

        # the scenario block as if written so (its key too: results on another backend)
        region = dataclasses.replace(region, scenario={
            **region.scenario, "numerics": {**numerics, "backend": args.backend}})
    try:
        outcome = run_region(region, args.output, workers=args.workers,
                             scheduler=args.scheduler, quiet=args.quiet)
    except (Interrupted, KeyboardInterrupt):
        print("avflow: interrupted; the finished releases are kept in "
              f"{Path(args.output) / 'releases'}: run the same command again to resume",
              file=sys.stderr)
        return _interrupted()
    if not args.quiet:
        runs = (f"{outcome.table.id.nunique()} releases x {len(region.scenarios)} scenarios"
                if region.with_scenarios else f"{len(outcome.table)} releases")
        print(f"{region.name}: {runs}, {outcome.ran} run, "
              f"{outcome.reused} reused, {outcome.failed} not merged ({outcome.elapsed:.1f} s, "
              f"{outcome.where}); wrote {Path(args.output) / outcome.store.name} and "
              f"{Path(args.output) / 'releases.csv'}")
    return 0 if outcome.failed == 0 else 1


def _cmd_calibrate(args) -> int:
    from avflow.calibration import calibrate, load_calibration

    if args.workers is not None and args.workers < 0:
        raise AvflowError(f"--workers must be >= 0, got {args.workers}")
    calibration = load_calibration(args.calibration)  # every check before any run
    _announce_compiles(args)
    result = calibrate(calibration, args.output, workers=args.workers,
                       scheduler=args.scheduler, quiet=args.quiet)
    if not args.quiet:
        best = ", ".join(f"{k}={v:.6g}" for k, v in result.best.items())
        print(f"{calibration.name}: {len(result.table)} runs, best fit {best}; wrote "
              + ", ".join(str(p) for p in result.written))
    return 0


def _cmd_ensemble(args) -> int:
    from avflow.ensemble.spec import load_ensemble
    from avflow.ensemble.orchestrate import Interrupted, run_ensemble

    if args.workers is not None and args.workers < 0:
        raise AvflowError(f"--workers must be >= 0, got {args.workers}")
    if args.max_members is not None and args.max_members < 1:
        raise AvflowError(f"--max-members must be >= 1, got {args.max_members}")
    if args.batch is not None and args.batch < 1:
        raise AvflowError(f"--batch must be >= 1, got {args.batch}")
    if not args.connect_timeout > 0:
        raise AvflowError(f"--connect-timeout must be > 0, got {args.connect_timeout}")
    from avflow.ensemble.orchestrate import ProgressLine
    from avflow.ensemble.spec import parse_overrides

    overrides = parse_overrides(args.set + ([f"numerics.backend={args.backend}"]
                                            if args.backend else []))
    # --workers N: the local cluster starts now, while the ensemble file is checked (closed
    # again if the file is refused); run_ensemble uses it, or closes it if it does not fit
    from avflow.ensemble.orchestrate import close_started, start_local_cluster

    starting = start_local_cluster(args.workers) if args.workers and not args.scheduler \
        else None
    try:
        # every check before any member starts
        ensemble = load_ensemble(args.ensemble, overrides=overrides,
                                 max_members=args.max_members)
        _check_members_fit(ensemble, args.max_memory)
        from avflow.files import check_folder

        check_folder(Path(args.output), "ensemble folder")
    except BaseException:
        close_started(starting)
        raise
    out = Path(args.output)
    _announce_compiles(args)
    say = (lambda *a, **k: None) if args.quiet else print
    say(f"{ensemble.name}: {len(ensemble.members)} members -> {out}")
    progress = ProgressLine(len(ensemble.members), quiet=args.quiet)
    try:
        outcome = run_ensemble(ensemble, out, scheduler=args.scheduler, workers=args.workers,
                               batch=args.batch, connect_timeout=args.connect_timeout,
                               progress=progress, starting=starting)
    except Interrupted as err:  # the cluster is closed; say what finished
        print(f"avflow: {err}", file=sys.stderr)
        return _interrupted()
    finally:
        if starting is not None:
            close_started(starting)  # closed by now, unless run_ensemble failed early
    # The time of the progress line: from the start to the last member (tables not included)
    say(f"{outcome.ran} run, {outcome.reused} reused, {outcome.failed} failed "
        f"({outcome.elapsed:.1f} s, {outcome.where}); wrote {out / 'ensemble.nc'} and "
        f"{out / 'summary.csv'}")
    from avflow.ensemble.orchestrate import edge_members

    edge = edge_members(outcome.table, [n for n in ensemble.varied
                                        if n in outcome.table.columns])
    if edge:
        say(f"{len(edge)} member(s) reached the map's edge (runout a lower bound: enlarge "
            f"the map): " + "; ".join(edge))
    if args.report:
        from avflow.ensemble.report import write_report

        written = write_report(out)
        say(f"wrote {written}")
    return 0 if outcome.ok else 1


def _check_members_fit(ensemble, max_memory) -> None:
    """Every member's cells against the memory limit, before any runs (a member streams
    its snapshots to its file: one in memory); the limit then travels to the local workers
    through the environment."""
    import os

    from avflow.simulation.resources import ENV_MAX_MEMORY, check_resources, parse_bytes

    if max_memory is not None:
        try:
            parse_bytes(max_memory)
        except AvflowError as err:
            raise AvflowError(f"--max-memory: {err}") from None
        os.environ[ENV_MAX_MEMORY] = max_memory
    for member in ensemble.members:
        check_resources(member.scenario, streamed=True)


def _cmd_report(args) -> int:
    from avflow.region.export import find_store

    if find_store(args.outdir) is not None:  # a region's folder or its region.zarr
        from avflow.region.plot import write_region_report as write_report
    else:
        from avflow.ensemble.report import write_report

    written = write_report(args.outdir)
    if not args.quiet:
        print(f"wrote {written}")
    return 0


def _cmd_export(args) -> int:
    from avflow.output.maps import export_maps

    names = None
    if args.variables is not None:
        names = [n.strip() for n in args.variables.split(",") if n.strip()]
        if not names:
            raise AvflowError("--variables: give at least one map name")

    def warn(message):
        print(f"avflow: warning: {message}", file=sys.stderr)

    from avflow.region.export import export_region, find_store

    if find_store(args.run_file) is not None:  # a region's Zarr store, or its folder
        if args.format != "tif":
            raise AvflowError(f"{args.run_file}: a region's maps are exported as "
                              "Cloud-Optimized GeoTIFF only (--format tif)")
        written = export_region(args.run_file, args.output, names)
    else:
        written = export_maps(args.run_file, args.format, args.output, names, warn=warn)
    for path in written:
        if not args.quiet:
            print(f"wrote {path}")
    return 0


def _cmd_zoning(args) -> int:
    from avflow.files import protected
    from avflow.output.netcdf import check_output_path
    from avflow.output.zoning import (ZONE_NAMES, ZoningError, ZoningRule, write_zoning,
                                      zone_areas, zoning_from_runs)

    rule = ZoningRule(args.red_kpa, args.yellow_kpa, args.frequent_years, args.rare_years)
    if not (0 < rule.yellow_kpa < rule.red_kpa and 0 < rule.frequent_years < rule.rare_years):
        raise ZoningError("--yellow-kpa must be below --red-kpa and --frequent-years below "
                          "--rare-years, all positive")
    pairs = [s for s in args.sources if "=" in s]
    if pairs and len(pairs) != len(args.sources):
        raise ZoningError("give either YEARS=RUN.nc pairs or one region folder, not both")
    if pairs:
        runs = {}
        for item in pairs:
            years, _, path = item.partition("=")
            try:
                t = float(years)
            except ValueError:
                t = math.nan
            if not t > 0 or math.isinf(t):
                raise ZoningError(f"{item}: the return period before '=' must be a positive "
                                  "number of years")
            if not Path(path).is_file():
                raise ZoningError(f"{item}: file not found: {path}")
            runs.setdefault(t, []).append(path)
        out = Path(args.output or "zoning.tif")
        check_output_path(out, protected(pairs and [p.partition("=")[2] for p in pairs]))
        result = zoning_from_runs(runs, rule)
        periods = sorted(runs)
        title = "hazard zones from " + ", ".join(f"{t:g}" for t in periods) + "-year runs"
    else:
        from avflow.region.zoning import default_output, region_zoning

        if len(args.sources) != 1:
            raise ZoningError("give one region folder (or YEARS=RUN.nc pairs)")
        out = Path(args.output) if args.output else default_output(args.sources[0])
        check_output_path(out)
        result, periods = region_zoning(args.sources[0], rule)
        title = f"hazard zones of the region {Path(args.sources[0]).name}"
    written = write_zoning(result, out, rule, periods, title)
    if not args.quiet:
        areas = zone_areas(result)
        print("zones: " + ", ".join(f"{ZONE_NAMES[c]} {a / 1e4:.2f} ha"
                                     for c, a in areas.items()))
        print("wrote " + ", ".join(str(w) for w in written))
    return 0


def _cmd_plot(args) -> int:
    from avflow.region.export import find_store

    if find_store(args.run_file) is not None:  # a region's folder or its region.zarr
        from avflow.region.plot import plot_region

        if args.map != "both" or args.extent is not None or args.dpi != 120:
            raise AvflowError(f"{args.run_file}: a region's figure takes no --map, --extent "
                              "or --dpi; avflow export gives its maps to a GIS")
        written = plot_region(args.run_file, args.output)
    else:
        from avflow.output.maps import plot_run

        written = plot_run(args.run_file, args.output, map=args.map, extent=args.extent,
                           dpi=args.dpi)
    if not args.quiet:
        print(f"wrote {written}")
    return 0


def _one_line_warnings() -> None:
    """avflow's own warnings as ``avflow: warning: ...`` lines on stderr, once each."""
    import warnings

    from avflow.errors import AvflowWarning

    shown = warnings.showwarning
    # main() called again in one process wraps the original once, not its own wrapper:
    # thousands of commands stacked thousands of wrappers (a RecursionError at a warning)
    shown = getattr(shown, "avflow_wrapped", shown)

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, AvflowWarning):
            print(f"avflow: warning: {message}", file=sys.stderr)
        else:
            shown(message, category, filename, lineno, file, line)

    show.avflow_wrapped = shown
    warnings.showwarning = show
    warnings.simplefilter("default", AvflowWarning)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that every write in progress removes its temporary."""


#: Set by SIGTERM: the command's exit code is then 143, also where an ensemble, a region or
#: a calibration turned the interrupt into its own (saying what finished).
TERMINATED: list = []


def _terminate(signum, frame):
    from avflow.errors import INTERRUPTS

    TERMINATED.append(signum)
    INTERRUPTS.append(signum)
    _pending(Terminated)
    raise Terminated


def _interrupt(signum, frame):
    """Ctrl-C: noted, then raised as Python does (a swallowed one is raised again)."""
    from avflow.errors import INTERRUPTS

    INTERRUPTS.append(signum)
    _pending(KeyboardInterrupt)
    raise KeyboardInterrupt


def _pending(interrupt) -> None:
    """The interrupt raised again at Numba's next compiler pass, where the handler ran
    inside LLVM and its exception was lost (numerics.compiling.PENDING)."""
    compiling = sys.modules.get("avflow.numerics.compiling")
    if compiling is not None:
        compiling.PENDING[:] = [interrupt]


def _interrupted() -> int:
    """The exit code of an interrupted command: 143 after SIGTERM, 130 after Ctrl-C."""
    return 143 if TERMINATED else 130


#: What to do when memory ran out, by command (only advice that applies to it).
OUT_OF_MEMORY = {
    "run": "give the run fewer cells (a larger grid.dx), or leave --max-memory on to be "
           "told before it starts",
    "ensemble": "give the members fewer cells (a larger grid.dx), use fewer workers, or "
                "leave --max-memory on to be told before they start",
    "calibrate": "give the base scenario fewer cells (a larger grid.dx), or ask for less "
                 "(budget, posterior.walkers and steps, sensitivity.n), or use fewer "
                 "workers",
    "region": "crop or coarsen the DEM and the release raster, give smaller windows "
              "(window.buffer) or fewer workers",
    "export": "the maps are larger than this machine's memory; export fewer at a time "
              "(--variables) on a machine with more memory",
    "plot": "the run file is larger than this machine's memory can draw",
    "path": "the run file is larger than this machine's memory can analyse",
    "report": "the ensemble is larger than this machine's memory can draw",
}


#: The collector's first threshold while avflow runs as a command (Python's default: 700).
#: Importing numba, pandas and xarray makes some 200,000 objects that live as long as the
#: process, and the default had the collector walk them again and again (the figures:
#: docs/performance.md, "Start-up and files of a run").
PROGRAM_GC_THRESHOLD = 5000


def main(argv=None) -> int:
    import gc
    import logging
    import signal
    import threading

    program = argv is None  # the command itself, not main() called in a longer process
    if program:
        gc.set_threshold(PROGRAM_GC_THRESHOLD, *gc.get_threshold()[1:])
    # GDAL's messages reach Python's logging (rasterio); avflow reports the failure itself,
    # in one line, and a full disk would otherwise print each message of libtiff first
    logging.getLogger("rasterio").addHandler(logging.NullHandler())
    args = build_parser().parse_args(argv)
    _one_line_warnings()
    TERMINATED.clear()
    from avflow.files import forget_inputs

    forget_inputs()  # main() called again in one process: the last command's inputs
    from avflow.errors import INTERRUPTS

    INTERRUPTS.clear()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminate)
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            signal.signal(signal.SIGINT, _interrupt)
    reads_scenarios = hasattr(args, "extensions")
    try:
        if reads_scenarios:
            _load_extensions(args.extensions)  # before the scenario is read
        code = args.func(args)
        if INTERRUPTS and code in (0, 1):  # an interrupt swallowed on the way: never lost
            raise KeyboardInterrupt
        return code
    except AvflowError as err:  # bad input: 2; a run that failed numerically: 1
        hint = _extension_hint(err) if reads_scenarios else ""
        print(f"avflow: error: {err}{hint}", file=sys.stderr)
        return err.exit_code
    except MemoryError:  # past the estimate (--max-memory none, or a bigger need than it)
        advice = OUT_OF_MEMORY.get(args.command, OUT_OF_MEMORY["run"])
        print(f"avflow: error: out of memory; {advice}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as err:
        if isinstance(err, Terminated) or TERMINATED:
            print("avflow: terminated", file=sys.stderr)
            return 143
        print("avflow: interrupted", file=sys.stderr)
        return 130
    finally:
        if "avflow.numerics.compiling" in sys.modules:  # main() called in a longer process
            sys.modules["avflow.numerics.compiling"].stop_announcing()
            sys.modules["avflow.numerics.compiling"].PENDING.clear()
        if threading.current_thread() is threading.main_thread() \
                and signal.getsignal(signal.SIGINT) is _interrupt:
            signal.signal(signal.SIGINT, signal.default_int_handler)
        if program:  # the files are closed: the exit then skips a last walk over every
            gc.freeze()  # object, which would only find what the exit frees anyway


if __name__ == "__main__":
    sys.exit(main())
