"""``avflow report OUTDIR``: a Markdown report of an ensemble, with PNG figures (matplotlib Agg).

Reads ``OUTDIR/ensemble.nc`` only (the stacked maps are there; member files are read for
deposit profiles when the members do not share a grid). Writes ``OUTDIR/report.md`` and
``OUTDIR/report/*.png``:

- runout and time to stop against each varied numeric parameter, coloured by friction law;
- runout and time to stop per law;
- profile scenes: the deposit profiles of all members overlaid;
- grid scenes: the exceedance-probability maps of peak thickness, speed and pressure at
  every threshold, over the hillshade of the bed with the CRS, the release outlined (read
  from the member files), a scale bar and a north arrow (as ``avflow plot``);
- a table of the failed members with their errors.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from avflow.ensemble.spec import OK_STATUSES
from avflow.files import atomic_text, atomic_write

__all__ = ["write_report"]

_COLORS = ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown"]


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _law_colors(laws) -> dict:
    return {law: _COLORS[i % len(_COLORS)] for i, law in enumerate(dict.fromkeys(laws))}


def _md_table(header: list[str], rows: list[list]) -> str:
    def cell(v):
        if isinstance(v, float):
            return "NaN" if math.isnan(v) else f"{v:.4g}"
        return str(v).replace("|", "\\|").replace("\n", " ")

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def write_report(outdir: str | os.PathLike) -> Path:
    """Write ``OUTDIR/report.md`` and its figures; returns the path of the report."""
    import xarray as xr

    from avflow.errors import AvflowError
    from avflow.files import check_folder, check_target, inputs_of
    from avflow.output.maps import moving_percent

    outdir = Path(outdir)
    if outdir.name == "ensemble.nc" and outdir.is_file():  # the file named, not its folder
        outdir = outdir.parent
    path = outdir / "ensemble.nc"
    if not path.is_file():
        raise AvflowError(f"{path}: not found (give the folder of `avflow ensemble ... -o "
                          "OUTDIR`, or of `avflow region ... -o OUTDIR`)")
    try:
        with xr.open_dataset(path, decode_times=False) as ds:
            ds = ds.load()
        ds["realization"], ds["status"], ds["law"]  # noqa: B018 - what the report reads
    except Exception as err:  # noqa: BLE001 - truncated, foreign
        raise AvflowError(f"{path}: cannot be read as an avflow ensemble file "
                          f"({type(err).__name__}); run the ensemble again to write it"
                          ) from None
    figdir = check_folder(outdir / "report", "report folder")
    check_target(outdir / "report.md", inputs_of(path, ds.attrs), what="report")
    plt = _plt()

    n = ds.sizes["realization"]
    status = ds["status"].values.astype(str)
    ok = np.isin(status, OK_STATUSES)
    laws = ds["law"].values.astype(str)
    colors = _law_colors(laws)
    profile = ds.attrs.get("scene") == "profile"
    params = [name for name, c in ds.coords.items()
              if c.dims == ("realization",) and c.dtype.kind == "f"
              and np.isfinite(c.values).any() and np.unique(c.values[np.isfinite(c.values)]).size > 1]
    x_units = {"runout": "m", "time_to_stop": "s"}
    runout_label = "runout along the bed" if profile else "runout along the path"

    md = [f"# Ensemble report: {ds.attrs.get('ensemble_name', '')}", ""]
    md += [f"- members: {n}, succeeded: {int(ok.sum())}, failed: {int((~ok).sum())}",
           f"- scene: {ds.attrs.get('scene')}; varied: {ds.attrs.get('varied', '')}",
           f"- base scenario hash: {ds.attrs.get('base_scenario_hash', '')}",
           f"- source: {ds.attrs.get('source', '')}"]
    if "runout_truncated" in ds:
        cut = np.flatnonzero(ds["runout_truncated"].values == 1)
        named = "; ".join(f"{i} (" + ", ".join(f"{_dotted(ds, p)}={float(ds[p].values[i]):g}"
                                               for p in params) + ")" if params else f"{i}"
                          for i in cut)
        md += [f"- deposit reaching the domain's edge (runout is a lower bound): {cut.size} "
               "member(s)" + (f": {named}; enlarge the domain" if cut.size else "")]
    # A member ended by its rule with mass still moving has no deposit at rest; its
    # time_to_stop is when the rule ended it. A panel of time_to_stop needs a finite one.
    rest = np.isin(status, ("at_rest", "stopped"))
    if ok.any() and not rest.any():
        md += ["- **no member came to rest**: every final thickness is a snapshot of a flow "
               "still moving (statuses: " + ", ".join(sorted(set(status[ok]))) + "); peak "
               "maps and exceedance probabilities are unaffected"]
    md += ["- runout: " + ("the downslope end of the deposit along the bed" if profile else
                           "the distance along the path (the scenario's path line, else each "
                           "member's centre-of-mass track) of the farthest cell whose peak "
                           "pressure reaches 1 kPa (or the limit of output.path), as AIMEC; "
                           "summary.csv's reach_from_release_centroid is the horizontal "
                           "distance from the release centroid to the farthest deposit cell")]
    panels = ["runout"]
    if np.isfinite(ds["time_to_stop"].values[ok]).any():
        panels.append("time_to_stop")
    x_units["time_to_stop"] = "s" if rest.any() else "s, when the stop rule ended the run"
    what = "runout and time to stop" if len(panels) == 2 else "runout"
    md += [""]
    figures: list[tuple[str, str]] = []

    # --- runout and time to stop against each varied parameter ---------------------------
    for param in params:
        values = ds[param].values
        fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4),
                                 constrained_layout=True, squeeze=False)
        axes = axes[0]
        others = [p for p in params if p != param]
        for ax, name in zip(axes, panels):
            y = ds[name].values
            sel = ok & np.isfinite(values)
            # Members that differ only by this parameter are joined by a line, labelled by
            # the values of the other parameters (and the law when there are several).
            keys = [tuple([laws[i]] + [_key(ds[p].values[i]) for p in others]) for i in range(n)]
            for j, key in enumerate(dict.fromkeys(k for k, s in zip(keys, sel) if s)):
                idx = [i for i in range(n) if sel[i] and keys[i] == key]
                idx.sort(key=lambda i: values[i])
                label = _line_label(ds, key, others, len(colors) > 1)
                ax.plot(values[idx], y[idx], "-", marker=_MARKERS[j % len(_MARKERS)],
                        color=colors[key[0]], alpha=0.7, ms=4,
                        label=label if ax is axes[0] and label else None)
            ax.set_xlabel(f"{ds[param].attrs.get('long_name', param)}"
                          f" ({ds[param].attrs.get('units', '')})")
            ax.set_ylabel(f"{runout_label if name == 'runout' else name.replace('_', ' ')} "
                          f"({x_units[name]})")
            ax.grid(alpha=0.3)
        if others:  # one entry per line: what the other parameters are on it
            axes[0].legend(fontsize=7)
        else:
            for law, c in colors.items():
                axes[0].plot([], [], "-o", color=c, label=law)
            axes[0].legend(title="law")
        fname = f"vs_{param}.png"
        fig.suptitle(f"{what} against {param}")
        _savefig(fig, figdir / fname)
        plt.close(fig)
        figures.append((f"{what.capitalize()} against {param}", fname))

    # --- per law (one law: nothing to compare) ---------------------------------------------
    if len(colors) > 1:
        fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4),
                                 constrained_layout=True, squeeze=False)
        axes = axes[0]
        rng = np.random.default_rng(0)
        for ax, name in zip(axes, panels):
            y = ds[name].values
            for k, law in enumerate(colors):
                sel = ok & (laws == law)
                ax.scatter(k + rng.uniform(-0.15, 0.15, sel.sum()), y[sel], color=colors[law],
                           alpha=0.8, s=18)
            ax.set_xticks(range(len(colors)), list(colors))
            ax.set_ylabel(f"{runout_label if name == 'runout' else name.replace('_', ' ')} "
                          f"({x_units[name]})")
            ax.grid(alpha=0.3)
        fig.suptitle(f"{what} per friction law")
        _savefig(fig, figdir / "by_law.png")
        plt.close(fig)
        figures.append((f"{what.capitalize()} per friction law", "by_law.png"))
    else:
        (figdir / "by_law.png").unlink(missing_ok=True)  # of an earlier report

    # --- deposits ---------------------------------------------------------------------------
    if profile:
        fig, ax = plt.subplots(figsize=(10, 4), constrained_layout=True)
        members = np.flatnonzero(ok)
        named = len(members) <= 12  # each curve labelled by its member's values
        palette = plt.get_cmap("tab10" if len(members) <= 10 else "tab20")
        for k, i in enumerate(members):
            x, h = _deposit_profile(ds, outdir, i)
            if x is None:
                continue
            if named:
                label = ", ".join(
                    [f"{_dotted(ds, q)} = {ds[q].values[i]:g}" for q in params]
                    + ([laws[i]] if len(colors) > 1 else [])) or f"member {i}"
                ax.plot(x, h, color=palette(k % palette.N), alpha=0.8, lw=1.2, label=label)
            else:
                ax.plot(x, h, color=colors[laws[i]], alpha=0.6, lw=1)
        if named:
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        else:
            for law, c in colors.items():
                ax.plot([], [], color=c, label=law)
            ax.legend(title="law")
        ax.set_xlabel("distance along the bed (m)")
        ax.set_ylabel("deposit thickness (m, normal to the bed)")
        ax.grid(alpha=0.3)
        ax.set_title(f"deposit profiles of the {int(ok.sum())} successful members")
        _savefig(fig, figdir / "deposit_profiles.png")
        plt.close(fig)
        figures.append(("Deposit profiles, all members overlaid", "deposit_profiles.png"))
    else:
        figures += _exceedance_figures(ds, figdir, plt, outdir)

    for title, fname in figures:
        md += [f"## {title}", "", f"![{title}](report/{fname})", ""]

    # --- tables ----------------------------------------------------------------------------
    md += ["## Summary per law", ""]
    rows = []
    for law in colors:
        sel = ok & (laws == law)
        if not sel.any():
            rows.append([law, 0] + [math.nan] * 6)
            continue
        r, t = ds["runout"].values[sel], ds["time_to_stop"].values[sel]
        rows.append([law, int(sel.sum()), float(np.min(r)), float(np.median(r)),
                     float(np.max(r)), float(np.nanmin(t)) if np.isfinite(t).any() else math.nan,
                     float(np.nanmedian(t)) if np.isfinite(t).any() else math.nan,
                     float(np.nanmax(t)) if np.isfinite(t).any() else math.nan])
    md += [_md_table(["law", "members", "runout min (m)", "median", "max",
                      "time to stop min (s)", "median", "max"], rows), ""]
    entrained = ds["entrained_volume"].values if "entrained_volume" in ds else None
    if entrained is not None and np.any(entrained[ok] > 0.0):
        units = ds["entrained_volume"].attrs.get("units", "m3")
        md += ["## Entrainment", "", "Volume the flow took from the erodible layer, and the "
               "growth it made (released + entrained over released), per law:", ""]
        rows = []
        for law in colors:
            sel = ok & (laws == law)
            if not sel.any():
                continue
            e = entrained[sel]
            growth = (ds["release_volume"].values[sel] + e) / ds["release_volume"].values[sel]
            rows.append([law, int(sel.sum()), float(np.min(e)), float(np.median(e)),
                         float(np.max(e)), float(np.min(growth)), float(np.median(growth)),
                         float(np.max(growth))])
        md += [_md_table(["law", "members", f"entrained min ({units})", "median", "max",
                          "growth min", "median", "max"], rows), ""]

    md += ["## Failed members", ""]
    failed = np.flatnonzero(~ok)
    varied = _varied_coordinates(ds)  # numbers and text (release.path...) alike
    if failed.size:
        md += [_md_table(["realization", "hash", "law", *[_dotted(ds, c) for c in varied],
                          "status", "error"],
                         [[int(i), str(ds["scenario_hash"].values[i]), laws[i],
                           *[_value(ds[c].values[i]) for c in varied], status[i],
                           str(ds["error"].values[i])] for i in failed]), ""]
    else:
        md += ["None: every member succeeded.", ""]

    if n <= 250:
        md += ["## All members", ""]
        names = ["runout", "time_to_stop", "deposit_max_thickness", "deposit_length",
                 "mass_balance_error", "wall_time"]
        if entrained is not None and np.any(entrained[ok] > 0.0):
            names.insert(4, "entrained_volume")
        # the share of the volume still moving at the end, whatever the status
        moving = (moving_percent(ds) if "moving_volume_end" in ds else np.full(n, np.nan))
        md += [_md_table(["realization", "law", *params, "status",
                          "still moving at the end (% of the volume)", *names],
                         [[int(i), laws[i], *[float(ds[p].values[i]) for p in params],
                           status[i], float(moving[i]), *[float(ds[m].values[i])
                                                          for m in names]]
                          for i in range(n)]), ""]
    return atomic_text(outdir / "report.md", "\n".join(md))


def _savefig(fig, target: Path) -> None:
    atomic_write(target, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))


#: Probability maps of ensemble.nc: figure file, title and how a threshold is written.
_EXCEEDANCE = (("peak_thickness", "exceedance.png", "Peak-thickness exceedance probability",
                "peak thickness > {:g} m"),
               ("peak_speed", "exceedance_speed.png", "Peak-speed exceedance probability",
                "peak speed > {:g} m/s"),
               ("peak_pressure", "exceedance_pressure.png",
                "Peak-pressure exceedance probability", "peak pressure > {:g} kPa"))


def probability_style(n: int):
    """Colormap, norm and tick values of an exceedance map over ``n`` members: the map can
    only hold k / n, so one colour per value (k >= 1; 0 is left blank)."""
    import matplotlib
    import matplotlib.colors as mcolors

    levels = np.arange(1, n + 1) / n
    cmap = matplotlib.colormaps["viridis"].resampled(n)
    norm = mcolors.BoundaryNorm(np.concatenate([[0.5 / n], levels + 0.5 / n]), n)
    return cmap, norm, levels


def _released(ds, outdir: Path, ok) -> np.ndarray | None:
    """Where the members released (y, x), from their run files' first snapshot: the first
    successful member's when no release field is varied, else every successful member's
    (their union). None where no member file is readable on the ensemble's grid."""
    import xarray as xr

    hashes = ds["scenario_hash"].values.astype(str)[ok]
    if "release" not in str(ds.attrs.get("varied", "")):
        hashes = hashes[:1]
    xs, ys = ds["x"].values, ds["y"].values
    union = None
    for h in hashes:
        try:
            with xr.open_dataset(outdir / "members" / f"{h}.nc", decode_times=False) as run:
                if run["x"].size != xs.size or run["y"].size != ys.size or not (
                        np.allclose(run["x"].values, xs) and np.allclose(run["y"].values, ys)):
                    continue
                h0 = np.nan_to_num(np.asarray(run["h"].isel(time=0).values, dtype=float)) > 0
        except Exception:  # noqa: BLE001 - a member file gone or foreign: no outline from it
            continue
        union = h0 if union is None else union | h0
    return union if union is not None and union.any() else None


def _exceedance_figures(ds, figdir: Path, plt, outdir: Path) -> list[tuple[str, str]]:
    """One figure per peak map: its probability at each threshold over the hillshade of the
    bed, axes in the CRS, the release outlined, a scale bar and a north arrow (as `avflow
    plot`); P = 0 is left transparent."""
    from matplotlib.lines import Line2D

    from avflow.output.maps import _scale_and_north, crs_name, draw_terrain

    figures = []
    xs, ys = ds["x"].values, ds["y"].values
    bed = ds["bed_elevation"].values if "bed_elevation" in ds.variables else None
    crs = crs_name(ds)
    n_ok = max(int(np.isin(ds["status"].values.astype(str), OK_STATUSES).sum()), 1)
    cmap, norm, levels = probability_style(n_ok)
    released = _released(ds, outdir, np.isin(ds["status"].values.astype(str), OK_STATUSES))
    for name, fname, title, label in _EXCEEDANCE:
        var = f"{name}_exceedance_probability"
        if var not in ds:
            continue
        prob = ds[var]
        dim = prob.dims[0]
        k = prob.sizes[dim]
        aspect = (np.ptp(xs) + 1e-9) / (np.ptp(ys) + 1e-9)
        if aspect > 2.0:  # long domains: one map under the other
            fig, axes = plt.subplots(k, 1, figsize=(10, 1.2 + k * 10 / aspect),
                                     constrained_layout=True, squeeze=False, sharex=True)
            axes = axes[:, 0]
        else:
            fig, axes = plt.subplots(1, k, figsize=(3.9 * k + 1.3, 4.4), constrained_layout=True,
                                     squeeze=False, sharey=True)
            axes = axes[0]
        for ax, t in zip(axes, prob[dim].values):
            if bed is not None:
                draw_terrain(ax, xs, ys, np.asarray(bed, dtype=float))
            p = prob.sel({dim: t}).values
            im = ax.pcolormesh(xs, ys, np.ma.masked_where(~(p > 0), p), norm=norm,
                               cmap=cmap, shading="nearest", alpha=0.85)
            ax.set_aspect("equal")
            ax.ticklabel_format(useOffset=False, style="plain")
            ax.tick_params(labelsize=7)
            ax.xaxis.set_major_locator(plt.MaxNLocator(4))
            plt.setp(ax.get_xticklabels(), rotation=20, ha="right")
            ax.set_title(f"P({label.format(float(t))})", fontsize=10)
            ax.set_xlabel("x (m)" + (f"\n{crs}" if crs else ""), fontsize=8)
            ax.set_ylabel("y (m)", fontsize=8)
            if released is not None:
                ax.contour(xs, ys, released.astype(float), levels=[0.5], colors="tab:blue",
                           linewidths=1.6, linestyles="--", zorder=5)
            _scale_and_north(ax)
        if released is not None:
            axes[0].legend(handles=[Line2D([], [], color="tab:blue", ls="--", lw=1.6,
                                           label="release")], loc="lower right", fontsize=7,
                           framealpha=0.8)
        bar = fig.colorbar(im, ax=list(axes), shrink=0.9, ticks=levels,
                           label=f"probability over {n_ok} members (blank: 0)")
        bar.ax.set_yticklabels([f"{k}/{n_ok}" for k in range(1, n_ok + 1)] if n_ok <= 12
                               else [f"{v:.2f}" for v in levels])
        _savefig(fig, figdir / fname)
        plt.close(fig)
        figures.append((title, fname))
    return figures


_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")


def _dotted(ds, name: str) -> str:
    """The scenario field of a parameter coordinate (``release_volume_factor`` ->
    ``release.volume_factor``), from its long_name."""
    long_name = str(ds[name].attrs.get("long_name", ""))
    prefix = "scenario field "
    return long_name[len(prefix):] if long_name.startswith(prefix) else name


def _line_label(ds, key: tuple, others: list[str], with_law: bool) -> str:
    """``release.volume_factor = 2`` for a line of members that differ by one parameter."""
    parts = [f"{_dotted(ds, p)} = {'NaN' if v is None else format(v, 'g')}"
             for p, v in zip(others, key[1:])]
    if with_law:
        parts.insert(0, str(key[0]))
    return ", ".join(parts)


def _varied_coordinates(ds) -> list[str]:
    """Parameter coordinates whose values differ between members (law aside)."""
    names = []
    for name, c in ds.coords.items():
        if (c.dims != ("realization",) or name in ("realization", "scenario_hash", "law")
                or c.dtype.kind not in "fiuOUS"):
            continue
        shown = {repr(_value(v)) for v in c.values}
        if len(shown) > 1:
            names.append(name)
    return names


def _value(v):
    """A table cell: numbers as float, text as is."""
    if isinstance(v, (str, bytes)):
        return v.decode() if isinstance(v, bytes) else v
    try:
        return float(v)
    except (TypeError, ValueError):
        return str(v)


def _key(value):
    """A hashable, NaN-safe grouping key (NaN != NaN would split every group)."""
    value = float(value)
    return None if math.isnan(value) else value


def _deposit_profile(ds, outdir: Path, i: int):
    """Deposit thickness along x of member ``i``: from ensemble.nc, else its member file."""
    if "deposit_thickness" in ds:
        return ds["x"].values, ds["deposit_thickness"].values[i]
    import xarray as xr

    path = outdir / "members" / f"{ds['scenario_hash'].values[i]}.nc"
    if not path.is_file():
        return None, None
    with xr.open_dataset(path, decode_times=False) as m:
        return m["x"].values, m["deposit_thickness"].values
