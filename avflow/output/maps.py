"""Maps out of a run file: ``avflow export`` (GeoTIFF / ESRI ASCII rasters) and ``avflow plot``.

Both read one ``avflow run`` NetCDF (:func:`avflow.output.dataset.to_dataset`).

- :func:`export_maps` writes the (y, x) maps of a grid scene (terrain ``plane`` or ``dem``)
  as north-up rasters named ``<stem>_<variable>.tif|.asc``, georeferenced with the CRS of
  the file's ``crs`` grid-mapping variable (``crs_wkt``). ESRI ASCII grids get a ``.prj`` in
  ESRI WKT1, the only form GDAL's AAIGrid driver reads. NaN (outside the DEM, never reached)
  is the rasters' NODATA.
- :func:`plot_run` draws one PNG (matplotlib Agg): on grids the peak thickness over a
  hillshade of the bed with the release and deposit outlines; on profiles the bed with the
  thickness at a few snapshots and the deposit; on triangle meshes (UGRID) the peak
  thickness on the mesh nodes.

Problems with the input file are :class:`MapsError` (one line naming the file).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from avflow.errors import AvflowError

__all__ = ["DEFAULT_EXPORT", "MapsError", "export_maps", "plot_run", "scene_kind"]

#: Maps exported when no ``--variables`` are given.
DEFAULT_EXPORT = ("peak_thickness", "peak_speed", "peak_pressure", "deposit_thickness",
                  "arrival_time", "rest_time")

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
        ds.close()
        raise MapsError(f"{path}: not an avflow run file (written by `avflow run`)")
    return ds


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
    gm = ds["peak_thickness"].attrs.get("grid_mapping") or ds["peak_thickness"].encoding.get(
        "grid_mapping")
    gm = gm or ("crs" if "crs" in ds.variables else None)
    if not gm or gm not in ds.variables:
        return None
    attrs = ds[gm].attrs
    return attrs.get("crs_wkt") or attrs.get("spatial_ref") or None


def _map_names(ds) -> list[str]:
    return [n for n, v in ds.data_vars.items() if v.dims == ("y", "x")]


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
    ``variables`` defaults to :data:`DEFAULT_EXPORT`. ``warn(message)`` is told when the
    file has no CRS (the rasters are then written without one).
    """
    from avflow.terrain.raster import RasterError, write_asc, write_tif

    path = Path(path)
    if fmt not in FORMATS:
        raise MapsError(f"unknown format {fmt!r} (use one of {', '.join(FORMATS)})")
    with open_run(path) as ds:
        kind = scene_kind(ds)
        if kind != "grid":
            what = {"profile": "a profile run (maps on x only)",
                    "triangles": "a triangle-mesh run (UGRID, maps on mesh nodes)"}.get(
                kind, f"peak_thickness on {ds['peak_thickness'].dims}")
            raise MapsError(f"{path}: export needs a grid scene (terrain plane or dem, "
                            f"square cells); this is {what}")
        available = _map_names(ds)
        names = list(DEFAULT_EXPORT if not variables else variables)
        unknown = [n for n in names if n not in available]
        if unknown:
            raise MapsError(f"{path}: no map named {', '.join(map(repr, unknown))}; "
                            f"available: {', '.join(available)}")
        wkt = crs_wkt(ds)
        if wkt is None and warn is not None:
            warn(f"{path}: no CRS in the file; rasters written without one")
        x = np.asarray(ds["x"].values, dtype=float)
        y = np.asarray(ds["y"].values, dtype=float)
        maps = {n: np.asarray(ds[n].values, dtype=float) for n in names}
    if x.size < 2 or y.size < 2:
        raise MapsError(f"{path}: the grid needs at least 2 x 2 cells to be exported")
    outdir = path.parent if outdir is None else Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    written = []
    for name, values in maps.items():
        target = outdir / f"{path.stem}_{name}.{fmt}"
        try:
            if fmt == "tif":
                write_tif(target, values, x, y, wkt)
            else:
                write_asc(target, values, x, y, _esri_wkt(wkt) if wkt else None)
        except RasterError as err:
            hint = "; use --format tif" if fmt == "asc" else ""
            raise MapsError(f"{err}{hint}") from None
        except OSError as err:
            raise MapsError(f"{target}: cannot write ({err.strerror or err})") from None
        written.append(target)
    return written


# --- plot -----------------------------------------------------------------------------------


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def hillshade(z: np.ndarray, dx: float, dy: float, azimuth_deg: float = 315.0,
              altitude_deg: float = 45.0) -> np.ndarray:
    """Lambertian shade in [0, 1] of a surface on ascending (y, x); NaN stays NaN.

    The light comes from ``azimuth_deg`` (clockwise from north, +y) at ``altitude_deg``.
    """
    dzdy, dzdx = np.gradient(np.asarray(z, dtype=float), dy, dx)
    az, alt = math.radians(azimuth_deg), math.radians(altitude_deg)
    light = (math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt))
    norm = np.sqrt(dzdx**2 + dzdy**2 + 1.0)
    shade = (-dzdx * light[0] - dzdy * light[1] + light[2]) / norm
    return np.clip(shade, 0.0, 1.0)


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
    """Whether the run ended with its mass at rest (the moving-volume rule), so that its
    final thickness is a deposit. Files older than the stop rules: when it stopped."""
    ended_by = ds.attrs.get("ended_by", "moving_volume" if ds.attrs.get("status") == "stopped"
                            else "time.end")
    return ended_by == "moving_volume"


def _fmt(ds, name: str, fmt: str, unit: str) -> str | None:
    if name not in ds.variables:
        return None
    v = float(ds[name].values)
    return None if math.isnan(v) else f"{format(v, fmt)}{unit}"


def _title(ds) -> str:
    parts = [p for p in (
        _fmt(ds, "runout", ".0f", " m") and "runout " + _fmt(ds, "runout", ".0f", " m"),
        _fmt(ds, "travel_angle", ".1f", "°") and "travel angle "
        + _fmt(ds, "travel_angle", ".1f", "°"),
        _fmt(ds, "deposit_max_thickness", ".2g", " m") and "deposit max "
        + _fmt(ds, "deposit_max_thickness", ".3g", " m"),
        _fmt(ds, "time_to_stop", ".1f", " s") and "stops at "
        + _fmt(ds, "time_to_stop", ".1f", " s"),
    ) if p]
    name = ds.attrs.get("scenario_name", "?")
    status = ds.attrs.get("status")
    if status and not at_rest(ds):
        status += ", still moving"
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


def _save(fig, target: Path) -> Path:
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
    try:
        fig.savefig(tmp, dpi=120, format="png")
        os.replace(tmp, target)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise MapsError(f"{target}: cannot write ({err.strerror or err})") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return target


def plot_run(path, output=None) -> Path:
    """Draw the run file ``path`` to a PNG (default: next to it, same stem); returns its path."""
    path = Path(path)
    target = path.with_suffix(".png") if output is None else Path(output)
    plt = _plt()
    with open_run(path) as ds:
        kind = scene_kind(ds)
        draw = {"grid": _plot_grid, "profile": _plot_profile,
                "triangles": _plot_triangles}.get(kind)
        if draw is None:
            raise MapsError(f"{path}: unknown scene layout (peak_thickness on "
                            f"{ds['peak_thickness'].dims})")
        fig = draw(ds, plt)
    try:
        return _save(fig, target)
    finally:
        plt.close(fig)


def _crs_name(ds) -> str | None:
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


def _layout(extent) -> tuple[tuple[float, float], str]:
    """Inches for a map of ``extent`` at equal aspect, and where its colourbar goes."""
    width, height = extent[1] - extent[0], extent[3] - extent[2]
    aspect = height / width if width > 0 and height > 0 else 1.0
    if aspect < 0.6:  # wide: colourbar underneath
        aspect = max(aspect, 0.12)
        return (9.0, 8.4 * aspect + 2.0), "bottom"
    aspect = min(aspect, 2.0)
    map_w = 7.0 if aspect <= 1.2 else 8.4 / aspect
    return (map_w + 1.9, map_w * aspect + 1.6), "right"


def _plain_ticks(ax) -> None:
    ax.ticklabel_format(useOffset=False, style="plain")


def _plot_grid(ds, plt):
    x = np.asarray(ds["x"].values, dtype=float)
    y = np.asarray(ds["y"].values, dtype=float)
    dx = float(x[1] - x[0]) if x.size > 1 else 1.0
    dy = float(y[1] - y[0]) if y.size > 1 else dx
    extent = (x[0] - dx / 2, x[-1] + dx / 2, y[0] - dy / 2, y[-1] + dy / 2)
    bed = np.asarray(ds["bed_elevation"].values, dtype=float)
    peak = np.asarray(ds["peak_thickness"].values, dtype=float)
    deposit = np.asarray(ds["deposit_thickness"].values, dtype=float)
    release = np.asarray(ds["h"].isel(time=0).values, dtype=float)
    threshold = float(ds.attrs.get("runout_threshold_m", 0.0) or 0.0)

    figsize, where = _layout(extent)
    fig, ax = plt.subplots(figsize=figsize, layout="constrained")

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

    levels, cmap, norm = _thickness_style(peak, ds)
    shown = np.where(np.isfinite(peak) & (peak >= levels[0]), peak, np.nan)
    im = ax.imshow(np.ma.masked_invalid(shown), extent=extent, origin="lower", cmap=cmap,
                   norm=norm, alpha=0.85, interpolation="nearest")
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    _finish_map(ds, fig, ax, im, lambda v, **kw: ax.contour(x, y, v, **kw),
                np.nan_to_num(release) > 0, np.nan_to_num(deposit) > threshold, threshold,
                levels, where, "peak flow thickness (m, normal to the bed)")
    plt.setp(ax.get_xticklabels(), rotation=20, ha="right")
    return fig


def _finish_map(ds, fig, ax, im, contour, released, deposited, threshold, levels, where,
                label):
    """Release and deposit outlines with their legend, the thickness colourbar, equal-aspect
    axes in m (with the CRS name) and the title; ``contour(values, **kw)`` draws on the
    scene's own geometry (grid or triangles)."""
    from matplotlib.lines import Line2D

    handles = []
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
    cb = fig.colorbar(im, ax=ax, shrink=0.8, spacing="uniform", location=where,
                      aspect=20 if where == "right" else 40)
    cb.set_label(label)
    cb.set_ticks(levels)
    cb.set_ticklabels([f"{v:g}" for v in levels])
    ax.set_aspect("equal")
    _plain_ticks(ax)
    crs = _crs_name(ds)
    ax.set_xlabel("x (m)" + (f", {crs}" if crs else ""))
    ax.set_ylabel("y (m)")
    ax.tick_params(labelsize=8)
    ax.set_title(_title(ds), fontsize=10)


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


def _plot_triangles(ds, plt):
    import matplotlib.tri as mtri

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

    figsize, where = _layout((nx.min(), nx.max(), ny.min(), ny.max()))
    fig, ax = plt.subplots(figsize=figsize, layout="constrained")
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
    im = ax.tripcolor(tri_wet, facecolors=face_peak, cmap=cmap, norm=norm, alpha=0.9,
                      edgecolors="face", linewidth=0.2)
    _finish_map(ds, fig, ax, im, lambda v, **kw: ax.tricontour(tri, v, **kw), release > 0,
                deposit > threshold, threshold, levels, where,
                "peak flow thickness on mesh nodes (m, normal to the bed)")
    return fig

