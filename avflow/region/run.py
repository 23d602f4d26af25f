"""One release of a region, on a worker: its window of the DEM, its run, re-run in grown
windows while its flow reaches the window's edge, and its result file.

The result file ``OUTDIR/releases/<id>.nc`` (``<id>-<scenario>.nc`` when the region has
scenarios) holds the release's peak maps on its last
window (float32, north first) and its row of ``releases.csv`` as attributes; it is written
atomically and its sha256 kept in ``OUTDIR/checksums/<id>.sha256`` (as ensemble members
are), so that a rerun reuses it only when every byte is as written and its ``key`` (the
region's scenario block, window rules and DEM, and the release's polygon and thickness) is
the release's.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import tempfile
import time
from pathlib import Path

import numpy as np

from avflow.ensemble.orchestrate import checksum_path, file_sha256, write_checksum
from avflow.files import atomic_write

#: Status of a release merged into the maps, and of one merged although its flow reached
#: the DEM's own border (no larger window exists: the map is then a lower bound there).
MERGED = ("ok", "dem_edge")
#: Columns of releases.csv, in order.
COLUMNS = ("id", "scenario", "return_period", "thickness", "status", "volume",
           "entrained_volume", "runout", "runout_angle", "reach_from_release_centroid",
           "travel_angle", "area", "area_outside_dem",
           "retries",
           "wall_time", "run_time", "buffer", "row0", "row1", "col0", "col1", "cells",
           "steps", "mass_balance_error", "reach_threshold", "reused", "error")


def release_key(region_key: str, wkb: bytes, thickness, scenario_key: str = "") -> str:
    """16 hex chars: the region's key, the polygon, its thickness and the scenario's key
    ("" without scenarios: the keys of a region without them stay as they were)."""
    extra = f"{scenario_key}|" if scenario_key else ""
    digest = hashlib.sha256(f"{region_key}|{thickness!r}|{extra}".encode() + wkb)
    return digest.hexdigest()[:16]


def result_path(outdir, rid: int, scenario: int | None = None) -> Path:
    """``releases/<id>.nc``, or ``releases/<id>-<scenario>.nc`` in a region with
    scenarios (``scenario`` given)."""
    name = f"{rid}.nc" if scenario is None else f"{rid}-{scenario}.nc"
    return Path(outdir) / "releases" / name


def read_result(path, key: str | None = None, arrays: bool = True):
    """``(row, maps, "")`` of a result file a rerun can trust, else ``(None, None, why)``;
    ``maps``: field name -> float32 array on the row's window (None unless ``arrays``)."""
    path = Path(path)
    if not path.is_file():
        return None, None, ""
    try:
        expected = checksum_path(path).read_text(errors="replace").split()[0]
    except (OSError, IndexError):  # a damaged checksum file is one that does not match
        return None, None, "it has no checksum (never finished)"
    if file_sha256(path) != expected:
        return None, None, "its checksum does not match (changed or damaged)"
    try:
        import netCDF4

        with netCDF4.Dataset(path) as nc:
            row = json.loads(nc.getncattr("row"))
            maps = None
            if arrays:
                maps = {name: np.asarray(var[...].filled(np.nan) if np.ma.isMaskedArray(
                    var[...]) else var[...], dtype=np.float32)
                    for name, var in nc.variables.items() if name.startswith("peak_")}
    except Exception as err:  # noqa: BLE001 - a foreign file: run the release again
        return None, None, f"it cannot be read ({type(err).__name__})"
    if key is not None and row.get("key") != key:
        return None, None, "it holds another release's or another region's result"
    return row, maps, ""


def _write_result(path: Path, row: dict, maps: dict, dem=None, window=None) -> None:
    """The release's maps on its window, with the window's x, y (cell centres, m) and the
    DEM's CRS when ``dem`` and ``window`` are given (a GIS opens the file in place)."""
    import netCDF4

    from avflow.terrain.raster import cf_grid_mapping

    def write(tmp: Path) -> None:
        with netCDF4.Dataset(tmp, "w") as nc:
            ny, nx = next(iter(maps.values())).shape
            nc.createDimension("y", ny)
            nc.createDimension("x", nx)
            mapping = None
            if dem is not None and window is not None:
                r0, r1, c0, c1 = window
                for axis, values in (("x", dem.x(c0, c1)), ("y", dem.y(r0, r1))):
                    var = nc.createVariable(axis, "f8", (axis,))
                    var.setncatts({"standard_name": f"projection_{axis}_coordinate",
                                   "long_name": f"{axis} of the cell centres", "units": "m",
                                   "axis": axis.upper()})
                    var[...] = values
                mapping = cf_grid_mapping(dem.crs_wkt)
                if mapping is not None:
                    crs = nc.createVariable("crs", "i4")
                    crs.setncatts(mapping)
            for name, values in maps.items():
                var = nc.createVariable(name, "f4", ("y", "x"), zlib=True, complevel=1,
                                        fill_value=np.float32(np.nan))
                var.set_auto_maskandscale(False)
                if mapping is not None:
                    var.setncattr("grid_mapping", "crs")
                var[...] = values
            nc.setncattr("row", json.dumps(row, allow_nan=True))

    checksum_path(path).unlink(missing_ok=True)  # stale: the file is replaced
    atomic_write(path, write)
    write_checksum(path)


def run_release(task: dict) -> dict:
    """Run one release (a task of :func:`avflow.region.orchestrate.run_region`); never
    raises for a model error: the row's status says ``invalid`` or ``failed`` and why.

    ``task``: id, wkb, thickness (m, or a :class:`~avflow.region.spec.ThicknessRule`),
    area, key, region (the :class:`Region`), dem (:class:`DemInfo`), outdir, one_thread;
    scenario (index), file_scenario (its index in file names, None without scenarios),
    updates, return_period; extensions (the extension files to load first, once per
    process; absent: none). Idempotent: a trusted result file is returned as it is (a task
    run twice after a lost worker)."""
    started = time.perf_counter()
    rid, outdir = task["id"], Path(task["outdir"])
    path = result_path(outdir, rid, task.get("file_scenario"))
    row, _, _ = read_result(path, task["key"], arrays=False)
    if row is not None:
        row.update(reused=True)
        return row
    region, dem = task["region"], task["dem"]
    row = {c: math.nan for c in COLUMNS}
    row.update(id=rid, scenario=task.get("scenario", 0), status="failed", area=task["area"],
               retries=0, reused=False, error="", key=task["key"],
               return_period=task.get("return_period") or math.nan)
    maps = None
    try:
        if task.get("extensions"):
            from avflow.scenario.extensions import load_files

            load_files(task["extensions"], worker=True)
        if isinstance(task["thickness"], (int, float)) or task["thickness"] is None:
            row["thickness"] = task["thickness"] if task["thickness"] else (
                task["patch"].mean if task.get("patch") is not None else math.nan)
        else:  # a rule: from the DEM under the polygon
            from avflow.region.windows import rule_thickness

            try:
                thickness, _, _ = rule_thickness(dem, task["wkb"], task["thickness"])
            except ValueError as err:
                from avflow.errors import ScenarioError

                raise ScenarioError(f"scenarios.return_periods.{task.get('return_period')}: "
                                    f"{err}") from None
            task = {**task, "thickness": thickness}
            row["thickness"] = thickness
        maps = _run_growing(task, region, dem, row, outdir)
    except Exception as err:  # noqa: BLE001 - recorded; the other releases go on
        from avflow.errors import RunFailed, ScenarioError

        problems = getattr(err, "problems", None)
        message = (" | ".join(f"{p.field + ': ' if p.field else ''}{p.message}"
                              for p in problems) if problems else " ".join(str(err).split()))
        row["status"] = ("invalid" if isinstance(err, ScenarioError)
                         else "failed" if isinstance(err, RunFailed) else "failed")
        # the release's files in the (removed) work folder: named as what they hold
        message = re.sub(r"\S*[/\\]work[/\\]release-\S*?[/\\](release)\.\w+", r"the \1 polygon",
                         message)
        row["error"] = f"{type(err).__name__}: {message}"
        maps = None
    row["wall_time"] = time.perf_counter() - started
    if maps is not None:
        _write_result(path, row, maps, dem, (row["row0"], row["row1"], row["col0"],
                                             row["col1"]))
    elif row["status"] == "invalid":  # kept without maps: resume does not retry the polygon
        _write_result(path, row, {"peak_thickness": np.full((1, 1), np.nan, np.float32)})
    return row  # a failed run keeps no file: a rerun tries it again


def _run_growing(task, region, dem, row, outdir: Path) -> dict:
    """Runs in windows grown by ``window.growth`` while the flow reaches their edge."""
    from avflow.region.windows import estimate_buffer, window_for, write_window
    from avflow.simulation.runner import simulate

    rules = region.window
    buffer = estimate_buffer(dem, task["bbox"], rules)
    work = outdir / "work"
    work.mkdir(parents=True, exist_ok=True)
    run_time = 0.0
    with tempfile.TemporaryDirectory(prefix=f"release-{task['id']}-", dir=work) as folder:
        polygon = Path(folder) / "release.gpkg"
        patch = task.get("patch")
        if patch is None:
            _write_polygon(polygon, task["wkb"], task["thickness"], dem.crs_wkt)
        retries = 0
        while True:
            # after max_retries grown windows, the whole DEM
            window = window_for(dem, task["bbox"], buffer) if retries <= rules.max_retries \
                else dem.whole
            dem_file = Path(folder) / f"dem-{retries}.tif"
            write_window(dem, window, dem_file)
            name = f"{region.name}-{task['id']}" + (
                f"-{task['file_scenario']}" if task.get("file_scenario") is not None else "")
            release = polygon
            if patch is not None:  # the patch's thickness on this window, as the DEM's cells
                release = Path(folder) / f"release-{retries}.tif"
                _write_patch(release, dem, window, patch, task["thickness"])
            scenario = region.scenario_for(str(dem_file), dem.dx, dem.dy, str(release),
                                           task["thickness"], name, task.get("updates"),
                                           raster=patch is not None)
            if task.get("one_thread") and scenario.numerics.threads is None:
                scenario = scenario.with_updates({"numerics.threads": 1})
            clock = time.perf_counter()
            result = simulate(scenario)
            run_time += time.perf_counter() - clock
            truncated = bool(result.summary["runout_truncated"])
            dem_file.unlink(missing_ok=True)
            if patch is not None:
                release.unlink(missing_ok=True)
            if not truncated or window == dem.whole or not _inner_edge_reached(
                    result, window, dem):
                break  # a flow at the DEM's own border (or NODATA): no window is larger
            buffer *= rules.growth
            retries += 1
    from avflow.output.path import headline_runout

    s = headline_runout(result)  # runout along the path at the pressure limit
    r0, r1, c0, c1 = window
    row.update(status="dem_edge" if truncated else "ok", retries=retries,
               volume=s["release_volume"], entrained_volume=s.get("entrained_volume", 0.0),
               runout=s["runout"], runout_angle=s["runout_angle"],
               reach_from_release_centroid=s["reach_from_release_centroid"],
               travel_angle=s["travel_angle"],
               steps=int(s["steps"]), mass_balance_error=s["mass_balance_error"],
               run_time=run_time, buffer=buffer, row0=r0, row1=r1, col0=c0, col1=c1,
               cells=int(result.terrain.n_cells),
               reach_threshold=float(result.thresholds["runout"]))
    terrain, state = result.terrain, result.state
    rho = scenario.physics.density

    def grid(values):  # south first on the run's grid -> north first, as the DEM's rows
        return terrain.to_grid(np.asarray(values, dtype=float))[::-1].astype(np.float32)

    return {"peak_thickness": grid(state.peak_h), "peak_speed": grid(state.peak_speed),
            "peak_pressure": grid(rho * state.peak_speed ** 2)}


def _inner_edge_reached(result, window, dem) -> bool:
    """Whether the flow reached a side of its window that is not the DEM's own border, below
    the lowest released cell (where ``runout_truncated`` looks): only then can a grown
    window change the run. A flow truncated by the DEM's border or its NODATA alone is as
    it would be on the whole DEM, which it would otherwise grow to for nothing
    (docs/performance.md, "Regional maps")."""
    terrain = result.terrain

    def grid(values):  # north first, as the window's rows
        return terrain.to_grid(np.asarray(values, dtype=float))[::-1]

    peak, z, h0 = grid(result.state.peak_h), grid(terrain.bed_elevation), grid(result.h0)
    r0, r1, c0, c1 = window
    side = np.zeros(peak.shape, dtype=bool)
    side[0, :] |= r0 > 0
    side[-1, :] |= r1 < dem.height
    side[:, 0] |= c0 > 0
    side[:, -1] |= c1 < dem.width
    released = np.nan_to_num(h0) > 0.0
    low = np.nanmin(z[released]) if released.any() else np.inf
    with np.errstate(invalid="ignore"):
        below = np.nan_to_num(z, nan=np.inf) < low
    return bool(np.any(side & below & (np.nan_to_num(peak) > result.thresholds["runout"])))


def _write_polygon(path: Path, wkb: bytes, thickness, crs_wkt) -> None:
    """The release polygon as a GeoPackage of one feature, in the DEM's CRS, with its
    thickness as the attribute the run reads."""
    import pyogrio.raw

    def write(tmp: Path) -> None:
        import warnings

        tmp.unlink()  # GDAL makes the GeoPackage itself
        with warnings.catch_warnings():  # the temporary's .tmp extension
            warnings.simplefilter("ignore", RuntimeWarning)
            pyogrio.raw.write(str(tmp), np.array([wkb], dtype=object),
                              [np.array([thickness if thickness else 0.0])], ["thickness"],
                              layer="release", driver="GPKG", crs=crs_wkt,
                              geometry_type="Unknown")

    atomic_write(path, write)


def _write_patch(path: Path, dem, window, patch, thickness) -> None:
    """A raster patch's thickness on a DEM window, as a GeoTIFF on the window's own cells
    (so that the run samples each cell's value exactly); ``thickness`` (m), when given,
    replaces its values (the raster then only marks the patch)."""
    from avflow.terrain.raster import write_tif

    r0, r1, c0, c1 = window
    values = patch.values(dem, window)
    if isinstance(thickness, (int, float)) and thickness:
        values = np.where(values > 0, float(thickness), 0.0)
    write_tif(path, values[::-1], dem.x(c0, c1), dem.y(r0, r1)[::-1], dem.crs_wkt,
              dtype="float64")
