"""``avflow plot`` and ``avflow report`` of a region's store (``OUTDIR/region.zarr``).

One PNG of two maps over the DEM's hillshade, with every release outlined and numbered:
the merged peak map (peak-pressure classes, or the peak thickness where the region merged
no pressure) and the release that set each maximum. Large regions are drawn from a
decimated view (the peaks by block maximum, so no hazard is hidden; the ids and the
hillshade by nearest cell). The report is ``OUTDIR/report.md``: the figure, the releases'
status counts and the longest runouts (from ``releases.csv``).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from avflow.region.export import RegionExportError, find_store

#: Most cells drawn along a side of the map (decimated above, by block maximum).
MOST_CELLS = 1200


def _open_store(path):
    import xarray as xr

    store = find_store(path)
    if store is None:
        raise RegionExportError(f"{path}: not a region store (region.zarr of avflow region)")
    try:
        return store, xr.open_zarr(store, consolidated=True)
    except Exception as err:  # noqa: BLE001 - one line naming the store
        raise RegionExportError(f"{store}: cannot be read as Zarr ({type(err).__name__}: "
                                f"{' '.join(str(err).split())[:120]})") from None


def _decimated(var, step: int, how: str) -> np.ndarray:
    if step > 1:
        var = (var.coarsen(y=step, x=step, boundary="pad").max() if how == "max"
               else var[::step, ::step])
    return np.asarray(var.values)


def _bed(ds, step: int, shape) -> np.ndarray | None:
    """The DEM under the maps (the store's ``dem`` attribute), on the drawn cells; None when
    the DEM is gone (the maps are drawn without a hillshade)."""
    dem = ds.attrs.get("dem")
    if not dem or not Path(dem).is_file():
        return None
    import rasterio
    from rasterio.enums import Resampling

    try:
        with rasterio.open(dem) as src:
            z = src.read(1, out_shape=shape, resampling=Resampling.nearest,
                         masked=True).astype(float).filled(np.nan)
    except Exception:  # noqa: BLE001 - a hillshade is a backdrop: drawn without it
        return None
    return z


def _outlines(ds):
    """(id, shapely geometry) of each release of the region file (the store's
    ``region_file`` attribute); empty when that file is gone or unreadable."""
    path = ds.attrs.get("region_file")
    if not path or not Path(path).is_file():
        return []
    try:
        import shapely

        from avflow.region.spec import load_region
        from avflow.region.windows import dem_info, read_releases

        region = load_region(path)
        return [(r.id, shapely.from_wkb(r.wkb)) for r in read_releases(region,
                                                                        dem_info(region.dem))
                if r.wkb is not None]
    except Exception:  # noqa: BLE001 - outlines are a help: the maps are drawn without them
        return []


def _draw_outlines(ax, outlines, label: bool) -> None:
    import shapely

    for rid, geom in outlines:
        for part in getattr(geom, "geoms", [geom]):
            if part.is_empty or not hasattr(part, "exterior"):
                continue
            xs, ys = part.exterior.xy
            ax.plot(xs, ys, color="black", lw=1.0, ls="--")
        if label and not geom.is_empty:
            p = shapely.point_on_surface(geom)
            ax.annotate(str(rid), (p.x, p.y), fontsize=7, ha="center", va="center",
                        bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.8))


def plot_region(path, output=None) -> Path:
    """Draw the region store ``path`` (the store, or the region's output folder) to a PNG
    (default: ``OUTDIR/region.png``); returns its path."""
    from avflow.files import check_target
    from avflow.output.maps import (_class_style, _layout, _plain_ticks, _plt, _save,
                                    _thickness_style, crs_name, hillshade,
                                    pressure_class_colors, pressure_class_labels)

    store, ds = _open_store(path)
    target = store.parent / "region.png" if output is None else Path(output)
    check_target(target, [], what="plot")
    with ds:
        pressure = "peak_pressure" in ds
        peak_name = "peak_pressure" if pressure else "peak_thickness"
        if peak_name not in ds:
            peak_name = next(n for n in ds.data_vars if n.startswith("peak_")
                             and not n.endswith("_release") and ds[n].dims == ("y", "x"))
        ny, nx = ds.sizes["y"], ds.sizes["x"]
        step = max(1, math.ceil(max(ny, nx) / MOST_CELLS))
        peak = _decimated(ds[peak_name], step, "max").astype(float)
        ids = _decimated(ds[f"{peak_name}_release"], step, "nearest") \
            if f"{peak_name}_release" in ds else None
        x = np.asarray(ds["x"].values, float)
        y = np.asarray(ds["y"].values, float)
        dx, dy = abs(float(x[1] - x[0])) if nx > 1 else 1.0, abs(float(y[1] - y[0])) \
            if ny > 1 else 1.0
        extent = (x.min() - dx / 2, x.max() + dx / 2, y.min() - dy / 2, y.max() + dy / 2)
        bed = _bed(ds, step, peak.shape)
        outlines = _outlines(ds)
        crs = crs_name(ds)
        classes = tuple(float(v) for v in np.atleast_1d(ds.attrs.get("pressure_classes_kPa",
                                                                      (1.0, 3.0, 30.0))))
        title = ds.attrs.get("title", "avflow region").removeprefix("avflow region ")
    plt = _plt()
    import matplotlib.colors as mcolors
    from matplotlib.patches import Patch

    figsize, where = _layout(extent, 2)
    shape = (2, 1) if where == "bottom" else (1, 2)
    fig, axes = plt.subplots(*shape, figsize=figsize, layout="constrained", squeeze=False,
                             sharex=True, sharey=True)
    axes = list(axes.ravel())
    # rows of the store go north first: imshow's "upper" origin puts them so
    show = dict(extent=extent, origin="upper", interpolation="nearest")
    for ax in axes:
        if bed is not None:
            shade = hillshade(bed[::-1], dx * step, dy * step)[::-1]
            ax.imshow(np.ma.masked_invalid(shade), cmap="gray", vmin=-0.5, vmax=1.15, **show)
    reached = np.isfinite(peak)
    if pressure:
        k = np.digitize(np.where(reached, peak / 1000.0, -1.0), classes)
        cmap, norm = _class_style(len(classes))
        axes[0].imshow(np.ma.masked_where(k == 0, k), cmap=cmap, norm=norm, alpha=0.9,
                       **show)
        handles = [Patch(facecolor=c, edgecolor="0.3", alpha=0.9, label=lab) for c, lab in
                   reversed(list(zip(pressure_class_colors(len(classes)),
                                     pressure_class_labels(classes))))]
        axes[0].legend(handles=handles, title=f"peak pressure\n(blank: < {classes[0]:g} kPa)",
                       fontsize=7, title_fontsize=7, loc="best", framealpha=0.85)
        axes[0].set_title("merged peak pressure classes", fontsize=9)
    else:
        levels, cmap, norm = _thickness_style(peak, ds)
        im = axes[0].imshow(np.ma.masked_invalid(peak), cmap=cmap, norm=norm, alpha=0.85,
                            **show)
        fig.colorbar(im, ax=axes[0], shrink=0.8, location=where,
                     label=f"{peak_name.replace('_', ' ')} (m)")
        axes[0].set_title(f"merged {peak_name.replace('_', ' ')}", fontsize=9)
    if ids is not None:
        present = np.unique(ids[ids > 0])
        if present.size:
            colours = [mcolors.to_hex(c) for c in plt.get_cmap("tab10")(
                np.arange(present.size) % 10)]
            index = np.searchsorted(present, np.where(ids > 0, ids, present[0]))
            axes[1].imshow(np.ma.masked_where(ids <= 0, index),
                           cmap=mcolors.ListedColormap(colours),
                           norm=mcolors.BoundaryNorm(np.arange(-0.5, present.size), present.size),
                           alpha=0.75, **show)
            if present.size <= 20:
                axes[1].legend(handles=[Patch(facecolor=c, alpha=0.75, label=f"release {r}")
                                        for c, r in zip(colours, present)],
                               fontsize=7, loc="best", framealpha=0.85)
    axes[1].set_title(f"release that set the {peak_name.replace('_', ' ')}", fontsize=9)
    for i, ax in enumerate(axes):
        _draw_outlines(ax, outlines, label=i == 1)
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_aspect("equal")
        _plain_ticks(ax)
        ax.set_xlabel("x (m)" + (f", {crs}" if crs else ""))
        ax.set_ylabel("y (m)")
        ax.tick_params(labelsize=8)
        plt.setp(ax.get_xticklabels(), rotation=20, ha="right")
    n = len(outlines)
    fig.suptitle(f"{title}: merged maps" + (f", {n} releases (dashed)" if n else "")
                 + (f" (drawn every {step} cells)" if step > 1 else ""), fontsize=10)
    try:
        return _save(fig, target)
    finally:
        plt.close(fig)


def write_region_report(path) -> Path:
    """``OUTDIR/report.md`` of a region: its figure (``region.png``), the releases' status
    counts and the longest runouts; returns the report's path."""
    import pandas as pd

    from avflow.files import atomic_write

    store, _ = _open_store(path)
    outdir = store.parent
    figure = plot_region(store, outdir / "region.png")
    lines = [f"# Region {outdir.name}", "", f"![merged maps]({figure.name})", ""]
    table_path = outdir / "releases.csv"
    if table_path.is_file():
        table = pd.read_csv(table_path)
        counts = table["status"].value_counts()
        lines += ["| status | runs |", "| --- | --- |"]
        lines += [f"| {status} | {count} |" for status, count in counts.items()]
        ok = table[table["status"].isin(("ok", "dem_edge"))].dropna(subset=["runout"])
        if len(ok):
            lines += ["", "Longest runouts (along the path, peak pressure >= 1 kPa; "
                      "alpha from the top of the release to that point):", "",
                      "| release | scenario | runout (m) | "
                      "alpha (deg) | volume (m3) | status |",
                      "| --- | --- | --- | --- | --- | --- |"]
            for _, r in ok.sort_values("runout", ascending=False).head(10).iterrows():
                lines.append(f"| {int(r['id'])} | {int(r['scenario'])} | {r['runout']:.0f} | "
                             f"{r.get('runout_angle', r['travel_angle']):.1f} | "
                             f"{r['volume']:.4g} | {r['status']} |")
        problems = table[~table["status"].isin(("ok",))]
        if len(problems):
            lines += ["", "Releases that did not run cleanly:", ""]
            lines += [f"- release {int(r['id'])}: {r['status']}"
                      + (f": {r['error']}" if isinstance(r["error"], str) and r["error"]
                         else " (its flow reaches the DEM's border: a lower bound there)"
                         if r["status"] == "dem_edge" else "")
                      for _, r in problems.iterrows()]
    report = outdir / "report.md"
    atomic_write(report, lambda tmp: Path(tmp).write_text("\n".join(lines) + "\n"))
    return report
