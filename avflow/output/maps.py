"""Maps out of a run file: ``avflow export`` (GeoTIFF / ESRI ASCII rasters) and ``avflow plot``.

Both read one ``avflow run`` NetCDF (:func:`avflow.output.dataset.to_dataset`); ``export``
also reads an ensemble's ``ensemble.nc`` (:mod:`avflow.ensemble.dataset`).

- :func:`export_maps` writes the (y, x) maps of a grid scene (terrain ``plane`` or ``dem``)
  as north-up rasters named ``<stem>_<variable>.tif|.asc``, georeferenced with the CRS of
  the file's ``crs`` grid-mapping variable (``crs_wkt``). ESRI ASCII grids get a ``.prj`` in
  ESRI WKT1, the only form GDAL's AAIGrid driver reads. NaN (outside the DEM, never reached)
  is the rasters' NODATA. ``peak_pressure_class`` is the class of the peak pressure among
  the scenario's ``output.pressure_classes`` (kPa; 0 below the first threshold), a paletted
  byte GeoTIFF. Of an ``ensemble.nc`` it writes every exceedance-probability map, one
  raster per threshold: ``ensemble_<variable>_<threshold><unit>.tif``.
- :func:`plot_run` draws one PNG (matplotlib Agg): on grids the peak thickness over a
  hillshade of the bed (``matplotlib.colors.LightSource``) with the release and deposit
  outlines, and beside it the peak-pressure classes; on profiles the bed with the thickness
  at a few snapshots and the deposit; on triangle meshes (UGRID) the same two maps on the
  mesh.

Problems with the input file are :class:`MapsError` (one line naming the file).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from avflow.errors import AvflowError
from avflow.scenario.extensions import REGISTERED_MAP

__all__ = ["DEFAULT_EXPORT", "MapsError", "export_maps", "plot_run", "scene_kind",
           "pressure_classes", "pressure_class_map", "pressure_class_labels"]

#: Maps exported when no ``--variables`` are given (and every registered map of the file).
DEFAULT_EXPORT = ("peak_thickness", "peak_speed", "peak_pressure", "peak_pressure_class",
                  "deposit_thickness", "arrival_time", "rest_time")
#: Maps exported as well when the run has them (entrainment: the bed's change, the layer).
EXPORT_IF_PRESENT = ("bed_change", "erodible_depth")

#: The class map derived from ``peak_pressure`` (not a variable of the file).
PRESSURE_CLASS = "peak_pressure_class"
#: Byte value of cells outside the mesh in the class GeoTIFF.
CLASS_NODATA = 255
#: Colours of three pressure classes: the yellow, blue and red of hazard zoning.
_ZONE_COLORS = ("#f2d21b", "#2b6fce", "#d7191c")

FORMATS = ("tif", "asc")


class MapsError(AvflowError):
    """A run file that cannot be exported or plotted; the message names the file."""


# --- reading --------------------------------------------------------------------------------


def open_run(path) -> "xarray.Dataset":  # noqa: F821
    """The run file as an (open, lazy) Dataset; a :class:`MapsError` if it is not one."""
    import xarray as xr

    path = Path(path)
    if not path.is_file():
        raise MapsError(f"{path}: no such file")
    try:
        ds = xr.open_dataset(path, decode_times=False)
    except Exception as err:  # not NetCDF, truncated...
        raise MapsError(f"{path}: cannot be read as NetCDF ({type(err).__name__})") from None
    if "scenario_name" not in ds.attrs or "peak_thickness" not in ds.variables:
        ensemble = "ensemble_name" in ds.attrs
        ds.close()
        if ensemble:
            raise MapsError(f"{path}: an ensemble file; `avflow export` writes its "
                            "probability maps, `avflow report OUTDIR` draws them")
        raise MapsError(f"{path}: not an avflow run file (written by `avflow run`)")
    try:
        for name, var in ds.data_vars.items():  # the maps and summaries, not the snapshots
            if "time" not in var.dims and var.dtype.kind == "f":
                _refuse_infinite(path, name, var.values)
    except MapsError:
        ds.close()
        raise
    except Exception as err:  # noqa: BLE001 - truncated inside: HDF5 errors on reading
        ds.close()
        raise MapsError(f"{path}: cannot be read ({type(err).__name__}: truncated?)") from None
    return ds


def _open_any(path):
    """A run file or an ensemble's ensemble.nc (by its ``ensemble_name`` attribute)."""
    import xarray as xr

    path = Path(path)
    if path.is_file():
        try:
            with xr.open_dataset(path, decode_times=False) as ds:
                ensemble = "ensemble_name" in ds.attrs
        except Exception:
            ensemble = False
        if ensemble:
            return xr.open_dataset(path, decode_times=False), True
    return open_run(path), False


def scene_kind(ds) -> str:
    """``"grid"`` (maps on (y, x)), ``"profile"`` (on (x,)) or ``"triangles"`` (UGRID nodes)."""
    dims = ds["peak_thickness"].dims
    if dims == ("y", "x"):
        return "grid"
    if dims == ("x",):
        return "profile"
    if "mesh" in ds.variables and ds["mesh"].attrs.get("cf_role") == "mesh_topology":
        return "triangles"
    return "unknown"


def crs_wkt(ds) -> str | None:
    """WKT of the CRS the maps name in ``grid_mapping`` (None without one)."""
    gm = None
    for var in ds.variables.values():
        gm = var.attrs.get("grid_mapping") or var.encoding.get("grid_mapping")
        if gm:
            break
    gm = gm or ("crs" if "crs" in ds.variables else None)
    if not gm or gm not in ds.variables:
        return None
    attrs = ds[gm].attrs
    return attrs.get("crs_wkt") or attrs.get("spatial_ref") or None


def _map_names(ds) -> list[str]:
    names = [n for n, v in ds.data_vars.items() if v.dims == ("y", "x")]
    if "peak_pressure" in names:
        names.insert(names.index("peak_pressure") + 1, PRESSURE_CLASS)
    return names


# --- pressure classes -----------------------------------------------------------------------


def pressure_classes(ds) -> tuple[float, ...]:
    """The run's peak-pressure class thresholds (kPa): its ``output.pressure_classes``
    (attribute ``pressure_classes_kPa``); files written before it: 1, 3 and 30 kPa."""
    value = ds.attrs.get("pressure_classes_kPa")
    if value is None:
        from avflow.scenario.schema import Output

        return tuple(Output.model_fields["pressure_classes"].default)
    return tuple(float(v) for v in np.atleast_1d(value))


def pressure_class_map(peak_pressure_pa: np.ndarray, classes_kpa,
                       reached: np.ndarray | None = None) -> np.ndarray:
    """Class of each peak pressure (Pa): 0 below the first threshold, k from the k-th
    threshold (included) up to the next; NaN stays NaN. Where ``reached`` is False (the
    peak thickness never passed the runout threshold: a film) the class is 0."""
    p = np.asarray(peak_pressure_pa, dtype=float) / 1000.0
    k = np.digitize(np.nan_to_num(p, nan=-1.0), np.asarray(classes_kpa, dtype=float))
    if reached is not None:
        k = np.where(reached, k, 0)
    return np.where(np.isfinite(p), k, np.nan)


def run_pressure_classes(ds, peak_pressure=None, peak_thickness=None) -> np.ndarray:
    """The class map of a run file: its peak pressure in its classes, where its peak
    thickness passed the runout threshold (the outline of the thickness map)."""
    p = ds["peak_pressure"].values if peak_pressure is None else peak_pressure
    h = ds["peak_thickness"].values if peak_thickness is None else peak_thickness
    threshold = float(ds.attrs.get("runout_threshold_m", 0.0) or 0.0)
    with np.errstate(invalid="ignore"):
        reached = np.nan_to_num(np.asarray(h, dtype=float)) >= threshold
    return pressure_class_map(p, pressure_classes(ds), reached)


def pressure_class_labels(classes_kpa) -> list[str]:
    """Legend names of classes 1..n: ``1-3 kPa``, ..., ``>= 30 kPa``."""
    c = [f"{v:g}" for v in classes_kpa]
    return [f"{a}\u2013{b} kPa" for a, b in zip(c, c[1:])] + [f"\u2265 {c[-1]} kPa"]


def pressure_class_colors(n: int) -> list[str]:
    """Colours of classes 1..n: the zoning colours for three classes, else YlOrRd."""
    if n == len(_ZONE_COLORS):
        return list(_ZONE_COLORS)
    from matplotlib import colormaps
    import matplotlib.colors as mcolors

    return [mcolors.to_hex(c) for c in colormaps["YlOrRd"](np.linspace(0.3, 1.0, n))]


# --- export ---------------------------------------------------------------------------------


def _esri_wkt(wkt: str) -> str:
    """The CRS as ESRI WKT1 for a .prj (GDAL's AAIGrid driver reads no WKT2)."""
    try:
        from pyproj import CRS

        return CRS.from_user_input(wkt).to_wkt("WKT1_ESRI") or wkt
    except Exception:
        return wkt


def export_maps(path, fmt: str = "tif", outdir=None, variables=None, warn=None) -> list[Path]:
    """Write maps of the grid run file ``path`` as rasters; returns the paths written.

    ``fmt`` is ``"tif"`` or ``"asc"``; ``outdir`` defaults to the folder of ``path``;
    ``variables`` defaults to :data:`DEFAULT_EXPORT` (of an ``ensemble.nc``: every
    exceedance-probability map). ``warn(message)`` is told when the file has no CRS (the
    rasters are then written without one).
    """
    from avflow.terrain.raster import RasterError, write_asc, write_tif

    from avflow.files import check_folder, check_target, inputs_of

    path = Path(path)
    if fmt not in FORMATS:
        raise MapsError(f"unknown format {fmt!r} (use one of {', '.join(FORMATS)})")
    ds, ensemble = _open_any(path)
    with ds:
        inputs = inputs_of(path, ds.attrs)  # the file, and the files it was made from
        rasters = (_ensemble_rasters if ensemble else _run_rasters)(ds, path, variables)
        wkt = crs_wkt(ds)
        x = np.asarray(ds["x"].values, dtype=float)
        y = np.asarray(ds["y"].values, dtype=float)
    if x.size < 2 or y.size < 2:
        raise MapsError(f"{path}: the grid needs at least 2 x 2 cells to be exported")
    for name, values, _ in rasters:
        _refuse_infinite(path, name, values)
    outdir = check_folder(path.parent if outdir is None else Path(outdir))
    targets = [outdir / f"{path.stem}_{name}.{fmt}" for name, _, _ in rasters]
    for target in targets + ([t.with_suffix(".prj") for t in targets] if fmt == "asc" and wkt
                             else []):
        check_target(target, inputs, what="raster")  # every one before the first is written
    if wkt is None and warn is not None:
        warn(f"{path}: no CRS in the file; rasters written without one")
    written = []
    for target, (name, values, options) in zip(targets, rasters):
        try:
            if fmt == "tif":
                write_tif(target, values, x, y, wkt, **options)
            else:
                write_asc(target, values, x, y, _esri_wkt(wkt) if wkt else None)
        except RasterError as err:
            hint = "; use --format tif" if fmt == "asc" else ""
            raise MapsError(f"{err}{hint}") from None
        written.append(target)
    return written


def _refuse_infinite(path: Path, name: str, values) -> None:
    """An infinite value in a map is an edited or broken file, never a result: refused
    (NaN is a cell outside the mesh or never reached)."""
    values = np.asarray(values)
    if values.dtype.kind == "f" and np.isinf(values).any():
        raise MapsError(f"{path}: {name} holds infinite values ({int(np.isinf(values).sum())} "
                        "cells); not an avflow result")


def _need_grid(ds, path: Path, what: str) -> None:
    kind = scene_kind(ds) if what == "run" else ("grid" if ("y" in ds.dims and "x" in ds.dims)
                                                   else "profile")
    if kind != "grid":
        this = {"profile": f"a profile {what} (maps on x only)",
                "triangles": "a triangle-mesh run (UGRID, maps on mesh nodes)"}.get(
            kind, f"peak_thickness on {ds['peak_thickness'].dims}")
        raise MapsError(f"{path}: export needs a grid scene (terrain plane or dem, "
                        f"square cells); this is {this}")


def _unknown(path: Path, unknown, available) -> MapsError:
    return MapsError(f"{path}: no map named {', '.join(map(repr, unknown))}; "
                     f"available: {', '.join(available)}")


def _run_rasters(ds, path: Path, variables):
    """``(name, values, write_tif options)`` of the maps of a run file to export."""
    _need_grid(ds, path, "run")
    available = _map_names(ds)
    # the maps a user registered (avflow.extend) go with the built-in ones
    registered = tuple(n for n in available
                       if n in ds.data_vars and ds[n].attrs.get(REGISTERED_MAP) == "yes")
    names = [n for n in (variables or DEFAULT_EXPORT + EXPORT_IF_PRESENT + registered)
             if variables or n in available]  # files before a map existed: skip it
    unknown = [n for n in names if n not in available]
    if unknown:
        raise _unknown(path, unknown, available)
    rasters = []
    for name in names:
        if name != PRESSURE_CLASS:
            attrs = ds[name].attrs  # the band says what it holds, and in which units
            values, units = np.asarray(ds[name].values, dtype=float), attrs.get("units")
            if name == "peak_pressure" and units == "Pa":  # kPa, as the classes, plots and
                values, units = values / 1000.0, "kPa"   # path tables say
            rasters.append((name, values, {"description": attrs.get("long_name", name),
                                           "units": units}))
            continue
        classes = pressure_classes(ds)
        labels = pressure_class_labels(classes)
        colors = pressure_class_colors(len(classes))
        values = run_pressure_classes(ds)
        rasters.append((name, values, {
            "dtype": "uint8", "nodata": CLASS_NODATA,
            "colormap": {0: (255, 255, 255, 255),  # a TIFF palette has no alpha
                         **{k + 1: _rgba(c) for k, c in enumerate(colors)}},
            "description": "peak pressure class",
            "units": "class",  # an index into the tags below, not a pressure
            "tags": {"pressure_classes_kPa": ", ".join(f"{v:g}" for v in classes),
                     "class_0": f"< {classes[0]:g} kPa, or the peak thickness stayed "
                                f"under the runout threshold",
                     **{f"class_{k + 1}": label.replace("\u2013", "-").replace("\u2265", ">=")
                        for k, label in enumerate(labels)}}}))
    return rasters


def _rgba(color: str) -> tuple:
    import matplotlib.colors as mcolors

    return tuple(int(round(255 * v)) for v in mcolors.to_rgba(color))


#: Short unit spellings for file names.
_UNIT_SUFFIX = {"m": "m", "m s-1": "m_s", "kPa": "kPa", "Pa": "Pa"}


def _ensemble_rasters(ds, path: Path, variables):
    """Every (selected) exceedance-probability map of an ensemble.nc, one per threshold."""
    _need_grid(ds, path, "ensemble")
    probabilities = [n for n, v in ds.data_vars.items()
                     if n.endswith("_exceedance_probability") and v.dims[-2:] == ("y", "x")]
    available = probabilities + [n for n, v in ds.data_vars.items() if v.dims == ("y", "x")]
    if not probabilities and not variables:
        raise MapsError(f"{path}: holds no exceedance-probability map (the members did not "
                        "share one grid)")
    names = list(variables or probabilities)
    unknown = [n for n in names if n not in available]
    if unknown:
        raise _unknown(path, unknown, available)
    members = ds.attrs.get("members", "?")
    rasters = []
    for name in names:
        var = ds[name]
        if var.dims == ("y", "x"):
            rasters.append((name, np.asarray(var.values, dtype=float), {}))
            continue
        coord = ds[var.dims[0]]
        units = coord.attrs.get("units", "")
        what = name.removesuffix("_exceedance_probability").replace("_", " ")
        for t in coord.values:
            label = f"{float(t):g}{_UNIT_SUFFIX.get(units, units.replace(' ', '_'))}"
            rasters.append((f"{name}_{label}", np.asarray(var.sel({coord.name: t}).values,
                                                          dtype=float), {
                "description": f"P({what} > {float(t):g} {units})",
                "units": "1",  # a probability: the threshold's units are a tag of their own
                "tags": {"variable": name, "threshold": f"{float(t):g}",
                         "threshold_units": units,
                         "members": str(members),
                         "comment": var.attrs.get("comment", "")}}))
    return rasters


# --- plot -----------------------------------------------------------------------------------


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def moving_percent(ds):
    """The volume still moving at the end (``moving_volume_end``) in percent of the volume
    there was, released plus entrained plus supplied: a number for a run file, one per member for an
    ``ensemble.nc``. What the summary line, the plot title and the report say."""
    total = np.asarray(ds["release_volume"].values, dtype=float)
    for added in ("entrained_volume", "supplied_volume"):
        if added in ds:
            total = total + np.nan_to_num(np.asarray(ds[added].values, dtype=float))
    return 100 * np.asarray(ds["moving_volume_end"].values, dtype=float) / np.maximum(total,
                                                                                      1e-300)


def hillshade(z: np.ndarray, dx: float, dy: float, azimuth_deg: float = 315.0,
              altitude_deg: float = 45.0) -> np.ndarray:
    """Shade in [0, 1] of a surface on ascending (y, x) by ``matplotlib.colors.LightSource``
    (Lambertian, contrast stretched over the map); NaN stays NaN.

    The light comes from ``azimuth_deg`` (clockwise from north, +y) at ``altitude_deg``.
    NODATA cells take their nearest value for the slopes of their neighbours.
    """
    from matplotlib.colors import LightSource

    z = np.asarray(z, dtype=float)
    bad = ~np.isfinite(z)
    if bad.all():
        return np.full(z.shape, np.nan)
    if bad.any():
        from scipy.ndimage import distance_transform_edt

        nearest = distance_transform_edt(bad, return_distances=False, return_indices=True)
        z = z[tuple(nearest)]
    # LightSource takes row 0 as the north (image order); these rows go south to north.
    shade = LightSource(azdeg=azimuth_deg, altdeg=altitude_deg).hillshade(
        z[::-1], dx=dx, dy=dy)[::-1]
    return np.where(bad, np.nan, shade)


def _nice_levels(lo: float, hi: float, most: int = 9) -> list[float]:
    """1-2-5 steps from the largest one <= ``lo`` to the first one >= ``hi``.

    At most ``most`` + 1 boundaries: steps of 2, then of 5 are dropped until they fit.
    """
    if not hi > 0:
        return [1e-3, 1.0]
    lo = min(lo, hi / 2) if lo > 0 else hi / 1000
    steps = [(m, m * 10.0**e) for e in range(math.floor(math.log10(lo)) - 1,
                                              math.ceil(math.log10(hi)) + 2) for m in (1, 2, 5)]
    first = max(i for i, (_, v) in enumerate(steps) if v <= lo * (1 + 1e-9))
    last = min(i for i, (_, v) in enumerate(steps) if v >= hi * (1 - 1e-9))
    steps = steps[first:last + 1]
    for drop in (2, 5):
        if len(steps) <= most + 1:
            break
        steps = [s for i, s in enumerate(steps) if s[0] != drop or i in (0, len(steps) - 1)]
    return [v for _, v in steps]


def at_rest(ds) -> bool:
    """Whether the run ended with its mass at rest, so that its final thickness is a deposit.
    Files that say "stopped" (before at_rest and ended_by_rule): by the moving-volume rule;
    files older than the stop rules: when it stopped."""
    status = ds.attrs.get("status")
    if status in ("at_rest", "ended_by_rule"):
        return status == "at_rest"
    ended_by = ds.attrs.get("ended_by", "moving_volume" if status == "stopped" else "time.end")
    return ended_by == "moving_volume"


def _fmt(ds, name: str, fmt: str, unit: str) -> str | None:
    if name not in ds.variables:
        return None
    v = float(ds[name].values)
    return None if math.isnan(v) else f"{format(v, fmt)}{unit}"


def runout_text(ds, digits: int = 0) -> str | None:
    """The headline runout as the summary line and the plot title show it: on maps the
    distance along the path at the pressure limit and its alpha, on profiles along the bed."""
    r = _fmt(ds, "runout", f".{digits}f", " m")
    if r is None:
        return None
    if scene_kind(ds) == "profile":
        return f"runout {r} along the bed from the top"
    if not ds.attrs.get("runout_path"):  # triangle meshes, files of earlier versions
        return f"runout {r} from the release centroid (horizontal)"
    text = (f"runout {r} along the {ds.attrs['runout_path']} "
            f"({ds.attrs.get('runout_limit', '')})")
    a = _fmt(ds, "runout_angle", ".1f", "°")
    return text + (f", alpha {a}" if a else "")


def _title(ds) -> str:
    # the headline runout and its alpha, named by what they measure (see runout_text)
    parts = [p for p in (
        runout_text(ds),
        _fmt(ds, "deposit_max_thickness", ".2g", " m") and "deposit max "
        + _fmt(ds, "deposit_max_thickness", ".3g", " m"),
        _fmt(ds, "time_to_stop", ".1f", " s") and ("stops at " if at_rest(ds) else
                                                    "the stop rule ended it at ")
        + _fmt(ds, "time_to_stop", ".1f", " s"),
    ) if p]
    name = ds.attrs.get("scenario_name", "?")
    status = ds.attrs.get("status")
    if status and not at_rest(ds) and status != "failed":
        moved = (float(moving_percent(ds))
                 if "moving_volume_end" in ds and "release_volume" in ds else math.nan)
        status += (f", {moved:.2g}% of the volume still moving" if math.isfinite(moved)
                   else ", still moving")
    if int(ds.attrs.get("runout_truncated", 0)):
        parts.append("runout truncated by the map's edge (a lower bound)")
    head = f"{name}" + (f" ({status})" if status else "")
    return head + ("\n" + ", ".join(parts) if parts else "")


def _thickness_style(peak: np.ndarray, ds):
    """Colormap and BoundaryNorm of stepped thickness levels; values below are transparent."""
    import matplotlib.colors as mcolors
    from matplotlib import colormaps

    finite = peak[np.isfinite(peak)]
    hi = float(finite.max()) if finite.size else 0.0
    # Coloured where the peak reaches the runout threshold: the deposit outline (same
    # threshold) then lies inside the coloured area.
    lo = float(ds.attrs.get("runout_threshold_m", 0.0) or 0.0)
    lo = lo or float(ds.attrs.get("dry_threshold_m", 0.0) or 0.0)
    levels = _nice_levels(lo if lo > 0 else 1e-3 * max(hi, 1.0), hi)
    cmap = colormaps["YlOrRd"].resampled(len(levels) - 1)
    colors = cmap(np.linspace(0.12, 1.0, len(levels) - 1))
    cmap = mcolors.ListedColormap(colors).with_extremes(under=(0, 0, 0, 0), bad=(0, 0, 0, 0),
                                                        over=colors[-1])
    return levels, cmap, mcolors.BoundaryNorm(levels, cmap.N)


def _save(fig, target: Path, dpi: int = 120) -> Path:
    from avflow.files import atomic_write

    return atomic_write(target, lambda tmp: fig.savefig(tmp, dpi=dpi, format="png"))


#: What ``avflow plot --map`` draws on a map: both panels, or one of them
PLOT_MAPS = ("both", "thickness", "pressure", "speed")


def plot_run(path, output=None, *, map: str = "both", extent=None, dpi: int = 120) -> Path:
    """Draw the run file ``path`` to a PNG (default: next to it, same stem); returns its path.

    On a map (grid or triangles): ``map`` one of :data:`PLOT_MAPS`; ``extent`` ``(xmin,
    xmax, ymin, ymax)`` in the map's coordinates (default: the whole map); ``dpi`` of the
    image. Maps carry a scale bar and a north arrow."""
    if map not in PLOT_MAPS:
        raise MapsError(f"--map: one of {', '.join(PLOT_MAPS)}, got {map!r}")
    if not (isinstance(dpi, int) and 20 <= dpi <= 1200):
        raise MapsError(f"--dpi: a whole number from 20 to 1200, got {dpi!r}")
    if extent is not None:
        extent = tuple(float(v) for v in extent)
        if (len(extent) != 4 or not all(math.isfinite(v) for v in extent)
                or not (extent[0] < extent[1] and extent[2] < extent[3])):
            raise MapsError("--extent: XMIN XMAX YMIN YMAX, finite, with XMIN < XMAX and "
                            f"YMIN < YMAX, got {' '.join(f'{v:g}' for v in extent)}")
    from avflow.files import check_target, inputs_of

    path = Path(path)
    if path.is_dir():  # an ensemble's folder: say what plot and report each take
        if (path / "ensemble.nc").is_file() or (path / "summary.csv").is_file():
            raise MapsError(f"{path}: an ensemble folder; avflow plot draws one run file "
                            f"(e.g. {path / 'members'}/<hash>.nc), avflow report {path} "
                            "draws the ensemble")
        raise MapsError(f"{path}: a folder; avflow plot draws one run file (.nc) or a "
                        "region's output folder")
    target = path.with_suffix(".png") if output is None else Path(output)
    with open_run(path) as ds:
        # neither the run file nor the scenario, DEM, release, maps or path line it records
        check_target(target, inputs_of(path, ds.attrs), what="plot")
        if target.suffix.lower() != ".png":  # a PNG named dem.asc once replaced the DEM
            raise MapsError(f"plot {target}: avflow plot writes PNG images; give a name "
                            "ending in .png")
        plt = _plt()
        kind = scene_kind(ds)
        draw = {"grid": _plot_grid, "profile": _plot_profile,
                "triangles": _plot_triangles}.get(kind)
        if draw is None:
            raise MapsError(f"{path}: unknown scene layout (peak_thickness on "
                            f"{ds['peak_thickness'].dims})")
        if kind == "profile" and (map != "both" or extent is not None):
            raise MapsError(f"{path}: a 1D profile; --map and --extent are for maps")
        if kind == "grid" and map == "pressure" and "peak_pressure" not in ds.variables:
            raise MapsError(f"{path}: the file has no peak_pressure to draw")
        fig = draw(ds, plt) if kind == "profile" else draw(ds, plt, map=map, extent=extent)
    try:
        return _save(fig, target, dpi)
    finally:
        plt.close(fig)


def _scale_and_north(ax) -> None:
    """A scale bar (a round length near a fifth of the width shown) at the lower left and a
    north arrow at the upper right: the maps are drawn in their CRS, y to the north."""
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    x0, x1 = ax.get_xlim()
    width = abs(x1 - x0)
    if not width > 0:
        return
    target = width / 5.0
    step = 10.0 ** math.floor(math.log10(target))
    length = max((m * step for m in (1, 2, 5) if m * step <= target), default=step)
    label = f"{length / 1000:g} km" if length >= 1000 else f"{length:g} m"
    ax.add_artist(AnchoredSizeBar(ax.transData, length, label, "lower left", pad=0.4,
                                  borderpad=0.6, sep=3, frameon=True, size_vertical=0,
                                  fontproperties={"size": 8}))
    ax.annotate("N", xy=(0.95, 0.95), xytext=(0.95, 0.83), xycoords="axes fraction",
                ha="center", va="center", fontsize=9, fontweight="bold",
                arrowprops=dict(arrowstyle="-|>", color="black", lw=1.5),
                bbox=dict(boxstyle="circle,pad=0.15", fc="white", ec="none", alpha=0.7))


def crs_name(ds) -> str | None:
    wkt = crs_wkt(ds)
    if not wkt:
        return None
    try:
        from pyproj import CRS

        crs = CRS.from_user_input(wkt)
        epsg = crs.to_epsg()
        return crs.name + (f" (EPSG:{epsg})" if epsg else "")
    except Exception:
        return None


def _layout(extent, panels: int = 1) -> tuple[tuple[float, float], str]:
    """Inches for ``panels`` maps of ``extent`` at equal aspect, and where the colourbar of
    each goes: wide maps one under the other, colourbars underneath; others side by side."""
    width, height = extent[1] - extent[0], extent[3] - extent[2]
    aspect = height / width if width > 0 and height > 0 else 1.0
    if aspect < 0.6:  # wide: colourbar underneath
        aspect = max(aspect, 0.12)
        return (9.0, 8.4 * aspect + 2.0 + (panels - 1) * (8.4 * aspect + 1.0)), "bottom"
    aspect = min(aspect, 2.0)
    map_w = 7.0 if aspect <= 1.2 else 8.4 / aspect
    if panels > 1:
        map_w *= 0.8
    return (panels * (map_w + 1.9), map_w * aspect + 1.6), "right"


def _plain_ticks(ax) -> None:
    ax.ticklabel_format(useOffset=False, style="plain")


def _map_axes(plt, extent, panels: int):
    figsize, where = _layout(extent, panels)
    shape = (panels, 1) if where == "bottom" else (1, panels)
    fig, axes = plt.subplots(*shape, figsize=figsize, layout="constrained", squeeze=False,
                             sharex=True, sharey=True)
    return fig, list(axes.ravel()), where


def _plot_grid(ds, plt, map: str = "both", extent=None):
    x = np.asarray(ds["x"].values, dtype=float)
    y = np.asarray(ds["y"].values, dtype=float)
    dx = float(x[1] - x[0]) if x.size > 1 else 1.0
    dy = float(y[1] - y[0]) if y.size > 1 else dx
    grid_extent = (x[0] - dx / 2, x[-1] + dx / 2, y[0] - dy / 2, y[-1] + dy / 2)
    shown_extent = grid_extent if extent is None else extent
    bed = np.asarray(ds["bed_elevation"].values, dtype=float)
    peak = np.asarray(ds["peak_thickness"].values, dtype=float)
    deposit = np.asarray(ds["deposit_thickness"].values, dtype=float)
    release = np.asarray(ds["h"].isel(time=0).values, dtype=float)
    threshold = float(ds.attrs.get("runout_threshold_m", 0.0) or 0.0)
    pressure = "peak_pressure" in ds.variables
    panels = (["thickness", "pressure"] if map == "both" and pressure else
              ["thickness"] if map == "both" else [map])

    fig, axes, where = _map_axes(plt, shown_extent, len(panels))
    for ax in axes:
        draw_terrain(ax, x, y, bed)

    def raster(ax, values, **kw):
        return ax.imshow(np.ma.masked_invalid(values), extent=grid_extent, origin="lower",
                         interpolation="nearest", **kw)

    outlines = (np.nan_to_num(release) > 0, np.nan_to_num(deposit) > threshold, threshold)
    for ax in axes:
        ax.set_xlim(shown_extent[0], shown_extent[1])
        ax.set_ylim(shown_extent[2], shown_extent[3])
        _finish_map(ds, fig, ax, lambda v, ax=ax, **kw: ax.contour(x, y, v, **kw),
                    *outlines, where)
    for ax, panel in zip(axes, panels):
        if panel == "thickness":
            levels, cmap, norm = _thickness_style(peak, ds)
            shown = np.where(np.isfinite(peak) & (peak >= levels[0]), peak, np.nan)
            im = raster(ax, shown, cmap=cmap, norm=norm, alpha=0.85)
            _thickness_colorbar(fig, ax, im, levels, where,
                                "peak flow thickness (m, normal to the bed)")
        elif panel == "pressure":
            classes = pressure_classes(ds)
            k = run_pressure_classes(ds)
            cmap, norm = _class_style(len(classes))
            raster(ax, np.where(k > 0, k, np.nan), cmap=cmap, norm=norm, alpha=0.9)
            _class_legend(fig, classes, where, ax)
        else:  # speed, coloured where the flow went
            speed = np.asarray(ds["peak_speed"].values, dtype=float)
            speed = np.where(np.isfinite(peak) & (peak >= threshold) & (speed > 0), speed,
                             np.nan)
            levels, cmap, norm = _speed_style(speed)
            im = raster(ax, speed, cmap=cmap, norm=norm, alpha=0.85)
            _thickness_colorbar(fig, ax, im, levels, where, "peak speed (m/s)")
        _scale_and_north(ax)
    _titles(fig, axes, ds, panels)
    for ax in axes:
        plt.setp(ax.get_xticklabels(), rotation=20, ha="right")
    return fig


def _speed_style(speed: np.ndarray):
    """Colormap and BoundaryNorm of stepped speed levels (m/s)."""
    import matplotlib.colors as mcolors
    from matplotlib import colormaps

    finite = speed[np.isfinite(speed)]
    hi = float(finite.max()) if finite.size else 1.0
    levels = _nice_levels(max(0.05 * hi, 0.1), max(hi, 0.2))
    colors = colormaps["viridis"](np.linspace(0.0, 1.0, len(levels) - 1))
    cmap = mcolors.ListedColormap(colors).with_extremes(under=colors[0], bad=(0, 0, 0, 0),
                                                        over=colors[-1])
    return levels, cmap, mcolors.BoundaryNorm(levels, cmap.N)


def draw_terrain(ax, x, y, bed) -> None:
    """Hillshade of the bed (grid on ascending x, y) with labelled contour lines."""
    dx = float(x[1] - x[0]) if x.size > 1 else 1.0
    dy = float(y[1] - y[0]) if y.size > 1 else dx
    extent = (x[0] - dx / 2, x[-1] + dx / 2, y[0] - dy / 2, y[-1] + dy / 2)
    shade = hillshade(bed, dx, dy)
    ax.imshow(np.ma.masked_invalid(shade), extent=extent, origin="lower", cmap="gray",
              vmin=-0.5, vmax=1.15, interpolation="nearest")
    finite_bed = bed[np.isfinite(bed)]
    if finite_bed.size and np.ptp(finite_bed) > 0:
        step = _nice_levels(np.ptp(finite_bed) / 12, np.ptp(finite_bed) / 6)[0]
        lv = np.arange(math.ceil(finite_bed.min() / step) * step, finite_bed.max(), step)
        if lv.size:
            cs = ax.contour(x, y, bed, levels=lv, colors="0.35", linewidths=0.4, alpha=0.7,
                            negative_linestyles="solid")
            ax.clabel(cs, fontsize=6, fmt="%g", inline_spacing=1)


def _class_style(n: int):
    """Colormap and norm of pressure classes 1..n."""
    import matplotlib.colors as mcolors

    cmap = mcolors.ListedColormap(pressure_class_colors(n))
    return cmap, mcolors.BoundaryNorm(np.arange(0.5, n + 1.0), cmap.N)


def _class_legend(fig, classes, where, ax=None) -> None:
    """The classes named in a legend beside their map ``ax`` (under the maps when wide)."""
    from matplotlib.patches import Patch

    handles = [Patch(facecolor=c, edgecolor="0.3", alpha=0.9, label=label) for c, label in
               reversed(list(zip(pressure_class_colors(len(classes)),
                                 pressure_class_labels(classes))))]
    title = f"peak pressure\n(blank: < {classes[0]:g} kPa)"
    if where == "bottom":
        fig.legend(handles=handles[::-1], title=title.replace("\n", " "), fontsize=8,
                   title_fontsize=8, loc="outside lower center", ncol=len(handles),
                   frameon=False)
    elif ax is not None:  # at the top right of its own map, the outlines' legend kept
        outlines = ax.get_legend()
        ax.legend(handles=handles, title=title, fontsize=8, title_fontsize=8,
                  loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0,
                  frameon=False)
        if outlines is not None:
            ax.add_artist(outlines)
    else:
        fig.legend(handles=handles, title=title, fontsize=8, title_fontsize=8,
                   loc="outside right upper", frameon=False)


def _thickness_colorbar(fig, ax, im, levels, where, label) -> None:
    cb = fig.colorbar(im, ax=ax, shrink=0.8, spacing="uniform", location=where,
                      aspect=20 if where == "right" else 40)
    cb.set_label(label)
    cb.set_ticks(levels)
    cb.set_ticklabels([f"{v:g}" for v in levels])


_PANEL_TITLES = {"thickness": "peak flow thickness", "pressure": "peak pressure classes",
                 "speed": "peak speed"}


def _titles(fig, axes, ds, panels=("thickness", "pressure")) -> None:
    """The run's title over the figure; each map named when there are two."""
    if len(axes) == 1:  # one map's width: the lines wrapped, not cut at the figure's edge
        import textwrap

        lines = [textwrap.fill(line, 95) for line in _title(ds).split("\n")]
        axes[0].set_title("\n".join(lines), fontsize=9)
        return
    fig.suptitle(_title(ds), fontsize=10)
    for ax, panel in zip(axes, panels):
        ax.set_title(_PANEL_TITLES[panel], fontsize=9)


def _erodible_at_start(ds):
    """Where an entrainment run's erodible layer lay at the start (``erodible_depth`` minus
    ``bed_change``), or None for a run without one."""
    if "erodible_depth" not in ds.variables or "bed_change" not in ds.variables:
        return None
    start = (np.nan_to_num(np.asarray(ds["erodible_depth"].values, dtype=float))
             - np.nan_to_num(np.asarray(ds["bed_change"].values, dtype=float)))
    return start > 0.0


def _finish_map(ds, fig, ax, contour, released, deposited, threshold, where):
    """Release and deposit outlines (and an entrainment run's erodible layer) with their
    legend, equal-aspect axes in m (with the CRS name); ``contour(values, **kw)`` draws on
    the scene's own geometry (grid or triangles)."""
    from matplotlib.lines import Line2D

    handles = []
    layer = _erodible_at_start(ds)
    if layer is not None and layer.any() and not layer.all():
        contour(layer.astype(float), levels=[0.5], colors="tab:green", linewidths=1.2,
                linestyles="-.")
        handles.append(Line2D([], [], color="tab:green", ls="-.", lw=1.2,
                              label="erodible layer"))
    if released.any():
        contour(released.astype(float), levels=[0.5], colors="tab:blue", linewidths=1.4,
                linestyles="--")
        handles.append(Line2D([], [], color="tab:blue", ls="--", lw=1.4, label="release"))
    if deposited.any():
        # a deposit only when the mass is at rest; a flow in motion gets its last outline
        style = dict(ls="-" if at_rest(ds) else ":", lw=1.2)
        contour(deposited.astype(float), levels=[0.5], colors="black",
                linewidths=style["lw"], linestyles=style["ls"])
        what = "deposit" if at_rest(ds) else "end of run, still moving"
        handles.append(Line2D([], [], color="black", **style,
                              label=f"{what} (> {threshold:.3g} m)"))
    if handles:
        ax.legend(handles=handles, loc="best", fontsize=8, framealpha=0.8)
    ax.set_aspect("equal")
    _plain_ticks(ax)
    crs = crs_name(ds)
    ax.set_xlabel("x (m)" + (f", {crs}" if crs else ""))
    ax.set_ylabel("y (m)")
    ax.tick_params(labelsize=8)


def _plot_profile(ds, plt):
    xh = np.asarray(ds["x_horizontal"].values, dtype=float)
    bed = np.asarray(ds["bed_elevation"].values, dtype=float)
    slope = np.radians(np.asarray(ds["slope_angle"].values, dtype=float))
    vertical = 1.0 / np.cos(slope)  # a layer h thick normal to the bed is h / cos thick
    times = np.asarray(ds["time"].values, dtype=float)
    deposit = np.nan_to_num(np.asarray(ds["deposit_thickness"].values, dtype=float))
    h = ds["h"]
    picks = np.unique(np.linspace(0, times.size - 1, min(times.size, 5)).round().astype(int))

    fig, ax = plt.subplots(figsize=(10, 4.8), layout="constrained")
    ax.plot(xh, bed, color="0.2", lw=1.2, label="bed")
    lowest = np.nanmin(bed)
    ax.fill_between(xh, lowest - 0.05 * np.ptp(bed), bed, color="0.85", lw=0)
    what = "deposit" if at_rest(ds) else "end of run, still moving"
    ax.fill_between(xh, bed, bed + deposit * vertical, where=deposit > 0, color="tab:brown",
                    alpha=0.6 if at_rest(ds) else 0.25, lw=0,
                    label=f"{what} (t = {times[-1]:.1f} s)")
    colors = plt.get_cmap("viridis")(np.linspace(0.0, 0.85, picks.size))
    for c, i in zip(colors, picks):
        hi = np.nan_to_num(np.asarray(h.isel(time=int(i)).values, dtype=float))
        top = np.where(hi > 0, bed + hi * vertical, np.nan)
        ax.plot(xh, top, color=c, lw=1.1, label=f"t = {times[i]:.1f} s")
    if "peak_pressure" in ds.variables:  # a strip along the foot of the axes
        classes = pressure_classes(ds)
        k = np.nan_to_num(run_pressure_classes(ds))
        strip = ax.get_xaxis_transform()
        for cls, (color, label) in enumerate(zip(pressure_class_colors(len(classes)),
                                                 pressure_class_labels(classes)), start=1):
            if (k == cls).any():
                ax.fill_between(xh, 0.0, 0.035, where=k == cls, transform=strip, color=color,
                                lw=0, step="mid", label=f"peak pressure {label}")
    ax.set_xlabel("horizontal distance from the top of the profile (m)")
    ax.set_ylabel("elevation (m)")
    ax.set_xlim(xh[0], xh[-1])
    ax.set_ylim(lowest - 0.05 * np.ptp(bed), None)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper right")
    ax.set_title(_title(ds), fontsize=10)
    caption = fig.supxlabel("flow surface drawn at bed + h / cos(slope): h, measured normal to "
                            "the bed, drawn vertically", fontsize=7, color="0.3", x=0.01,
                            ha="left")
    fig.canvas.draw()  # the axes' size on the page gives the vertical exaggeration
    box = ax.get_window_extent()
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    if box.width > 0 and box.height > 0 and y1 > y0:
        exaggeration = ((x1 - x0) / box.width) / ((y1 - y0) / box.height)
        caption.set_text(caption.get_text() + f"; vertical exaggeration {exaggeration:.1f}x")
    return fig


def _plot_triangles(ds, plt, map: str = "both", extent=None):
    import matplotlib.tri as mtri

    if map != "both":
        raise MapsError("--map: a run on triangles draws both maps (its thickness and "
                        "pressure classes); --map thickness, pressure or speed is for grids")

    nx = np.asarray(ds["mesh_node_x"].values, dtype=float)
    ny = np.asarray(ds["mesh_node_y"].values, dtype=float)
    conn = ds["mesh"].attrs.get("face_node_connectivity", "mesh_face_nodes")
    faces = np.asarray(ds[conn].values)
    start = int(ds[conn].attrs.get("start_index", 0))
    faces = faces.astype(np.int64) - start
    tri = mtri.Triangulation(nx, ny, faces)
    peak = np.asarray(ds["peak_thickness"].values, dtype=float)
    bed = np.asarray(ds["bed_elevation"].values, dtype=float)
    deposit = np.nan_to_num(np.asarray(ds["deposit_thickness"].values, dtype=float))
    release = np.nan_to_num(np.asarray(ds["h"].isel(time=0).values, dtype=float))
    threshold = float(ds.attrs.get("runout_threshold_m", 0.0) or 0.0)
    pressure = "peak_pressure" in ds.variables

    shown_extent = (nx.min(), nx.max(), ny.min(), ny.max()) if extent is None else extent
    fig, axes, where = _map_axes(plt, shown_extent, 2 if pressure else 1)
    for ax in axes:
        if np.ptp(bed) > 0:
            cs = ax.tricontour(tri, bed, levels=12, colors="0.45", linewidths=0.4,
                               negative_linestyles="solid")
            ax.clabel(cs, fontsize=6, fmt="%g")
    levels, cmap, norm = _thickness_style(peak, ds)
    # Flat shading, each triangle the mean of its nodes (Gouraud blends in the transparent
    # "under" colour and draws dark fringes); triangles below the lowest level are masked.
    face_peak = np.nan_to_num(peak)[faces].mean(axis=1)
    tri_wet = mtri.Triangulation(nx, ny, faces)
    tri_wet.set_mask(face_peak < levels[0])
    im = axes[0].tripcolor(tri_wet, facecolors=face_peak, cmap=cmap, norm=norm, alpha=0.9,
                           edgecolors="face", linewidth=0.2)
    for ax in axes:
        _finish_map(ds, fig, ax, lambda v, ax=ax, **kw: ax.tricontour(tri, v, **kw),
                    release > 0, deposit > threshold, threshold, where)
    _thickness_colorbar(fig, axes[0], im, levels, where,
                        "peak flow thickness on mesh nodes (m, normal to the bed)")
    if pressure:
        classes = pressure_classes(ds)
        face_p = np.nan_to_num(np.asarray(ds["peak_pressure"].values, float))[faces].mean(1)
        k = run_pressure_classes(ds, face_p, face_peak)
        cmap, norm = _class_style(len(classes))
        tri_p = mtri.Triangulation(nx, ny, faces)
        tri_p.set_mask(k < 1)
        axes[1].tripcolor(tri_p, facecolors=np.maximum(k, 1), cmap=cmap, norm=norm,
                          alpha=0.9, edgecolors="face", linewidth=0.2)
        _class_legend(fig, classes, where, axes[1])
    for ax in axes:
        ax.set_xlim(shown_extent[0], shown_extent[1])
        ax.set_ylim(shown_extent[2], shown_extent[3])
        _scale_and_north(ax)
    _titles(fig, axes, ds)
    return fig
