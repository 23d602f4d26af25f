"""What a protective structure did: its variables in the run file, and ``avflow compare``.

A run with ``structures`` carries, beside the edited ``bed_elevation``:

- ``structure_height`` (y, x): the height each structure added to the bed (m);
- along ``structure``: ``structure_retained_volume``, the final volume on the release's side
  of the line, and ``structure_overtopped_volume``, the final volume beyond it (overtopped,
  or gone round the line's ends); the material that left the map is in ``outflow_volume``.

``avflow compare RUN_A RUN_B`` sets two runs of the same map side by side (a scenario with
and without its structures): runout, travel angle, volumes, the peak-pressure maxima and the
areas above 1, 10 and 100 kPa, and the cells reached by one and not the other; a table (CSV,
Markdown) and a PNG: the peak pressure of both runs in their pressure classes and their
difference, over the hillshade with the release and the structures outlined, as ``avflow
plot`` draws a run.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from avflow.errors import AvflowError
from avflow.files import atomic_write

__all__ = ["CompareError", "compare_runs", "structure_variables"]

#: Peak-pressure classes (kPa) whose areas ``avflow compare`` reports.
PRESSURE_CLASSES = (1.0, 10.0, 100.0)


class CompareError(AvflowError):
    """Two runs that cannot be compared; one line, exit 2."""


def structure_variables(result, space) -> dict:
    """The run file's structure variables (see the module), or {} without structures."""
    from avflow.terrain.structures import structure_volumes

    terrain = result.terrain
    built = terrain.extras.get("structures")
    if built is None:
        return {}
    area = terrain.mesh.cell_area
    x, y = terrain.cell_xy()
    rows = structure_volumes(built, x, y, result.state.h * area, result.h0 * area)
    dim = "structure"
    data = {
        "structure_name": (dim, np.array([r["name"] for r in rows], dtype=object),
                           {"long_name": "name of the structure (its line file's stem "
                                         "unless named)"}),
        "structure_kind": (dim, np.array([r["kind"] for r in rows], dtype=object),
                           {"long_name": "dam (raised bed) or wall (vertical, reflecting)"}),
        "structure_retained_volume": (dim, np.array([r["retained_volume"] for r in rows]), {
            "long_name": "volume retained upstream of the structure", "units": "m3",
            "comment": "final volume on the release's side of the structure's line (the "
                       "line continued straight beyond its ends)"}),
        "structure_overtopped_volume": (dim, np.array([r["overtopped_volume"] for r in rows]), {
            "long_name": "volume beyond the structure", "units": "m3",
            "comment": "final volume on the far side of the structure's line from the "
                       "release: overtopped, or gone round its ends; what left the map is "
                       "in outflow_volume"}),
    }
    if terrain.kind == "grid":
        data["structure_height"] = (space, built.added, {
            "long_name": "height the structures added to the bed", "units": "m",
            "comment": "bed_elevation is the edited bed; a wall's cells (outside the mesh) "
                       "carry its height"})
    return data


def structure_note(ds) -> str:
    """`` (dam: retained 1.2e+04, overtopped 0 m3)`` for the summary line; nothing without
    structures."""
    if "structure_retained_volume" not in ds:
        return ""
    parts = []
    for k in range(ds.sizes.get("structure", 0)):
        name = str(ds["structure_name"].values[k])
        parts.append(f"{name}: retained {float(ds['structure_retained_volume'][k]):.4g}, "
                     f"beyond {float(ds['structure_overtopped_volume'][k]):.4g} m3")
    return " (" + "; ".join(parts) + ")"


# =========================================================================================
# avflow compare RUN_A RUN_B
# =========================================================================================


def _open(path):
    from avflow.output.maps import open_run

    try:
        return open_run(path)
    except AvflowError:
        raise
    except Exception as err:  # noqa: BLE001 - not a run file: say which
        raise CompareError(f"{path}: cannot be read as a run file ({type(err).__name__})") \
            from None


def _row(ds, label: str, cell_area: float) -> dict:
    p = ds["peak_pressure"].values.astype(float) * 1e-3
    row = {"run": label, "scenario": str(ds.attrs.get("scenario_name", ""))}
    for name in ("runout", "runout_angle", "reach_from_release_centroid", "travel_length",
                 "travel_angle", "release_volume",
                 "deposit_volume", "outflow_volume"):
        row[name] = float(ds[name]) if name in ds else math.nan
    row["peak_pressure_max_kPa"] = float(np.nanmax(p)) if np.isfinite(p).any() else math.nan
    for c in PRESSURE_CLASSES:
        row[f"area_above_{c:g}_kPa_m2"] = float((np.nan_to_num(p) >= c).sum() * cell_area)
    if "structure_retained_volume" in ds:
        row["structure_retained_volume"] = float(ds["structure_retained_volume"].sum())
        row["structure_overtopped_volume"] = float(ds["structure_overtopped_volume"].sum())
    return row


def compare_runs(run_a, run_b, output=None) -> tuple[str, list[Path]]:
    """``avflow compare``: the table ``STEM.csv``/``.md`` and ``STEM.png`` (peak pressure of
    B minus A); returns (summary line, written files)."""
    import pandas as pd

    from avflow.files import check_target, protected

    run_a, run_b = Path(run_a), Path(run_b)
    stem = Path(output) if output else run_b.with_name(f"{run_b.stem}_vs_{run_a.stem}")
    inputs = protected([run_a, run_b])
    for suffix in (".csv", ".md", ".png"):
        check_target(stem.with_suffix(suffix), inputs, what="comparison output")
    with _open(run_a) as a, _open(run_b) as b:
        if "y" not in a.dims or "y" not in b.dims:
            raise CompareError(f"{run_a}, {run_b}: avflow compare takes two runs on a grid")
        same = (a.sizes["x"] == b.sizes["x"] and a.sizes["y"] == b.sizes["y"]
                and np.allclose(a["x"].values, b["x"].values)
                and np.allclose(a["y"].values, b["y"].values))
        if not same:
            raise CompareError(f"{run_b}: its grid differs from {run_a}'s; compare two runs "
                               "of the same map")
        cell = abs(float(a["x"][1] - a["x"][0]) * float(a["y"][1] - a["y"][0]))
        rows = [_row(a, "A", cell), _row(b, "B", cell)]
        pa = np.nan_to_num(a["peak_pressure"].values.astype(float)) * 1e-3
        pb = np.nan_to_num(b["peak_pressure"].values.astype(float)) * 1e-3
        diff_row = {"run": "B - A", "scenario": ""}
        for k, v in rows[1].items():
            if isinstance(v, float) and k in rows[0]:
                diff_row[k] = v - rows[0][k]
        only_a = float(((pa >= 1.0) & (pb < 1.0)).sum() * cell)
        only_b = float(((pb >= 1.0) & (pa < 1.0)).sum() * cell)
        diff_row["area_above_1_kPa_only_in_A_m2"] = only_a
        diff_row["area_above_1_kPa_only_in_B_m2"] = only_b
        rows.append(diff_row)
        table = pd.DataFrame.from_records(rows)
        written = []
        csv = stem.with_suffix(".csv")
        atomic_write(csv, lambda tmp: table.to_csv(tmp, index=False))
        md = stem.with_suffix(".md")
        cols = list(table.columns)

        def fmt(v):
            if isinstance(v, float):
                return "NaN" if math.isnan(v) else f"{v:.6g}"
            return str(v)
        lines = [f"# {run_b.name} (B) against {run_a.name} (A)", "",
                 "Volumes in m3, lengths in m, angles in degrees, pressure in kPa, areas in m2.",
                 "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        lines += ["| " + " | ".join(fmt(r.get(c, "")) for c in cols) + " |" for r in rows]
        atomic_write(md, lambda tmp: Path(tmp).write_text("\n".join(lines) + "\n"))
        written += [csv, md]
        written.append(_plot(a, b, pa, pb, stem.with_suffix(".png"), run_a.name, run_b.name))
    ra, rb = rows[0], rows[1]
    text = (f"B ({run_b.name}) against A ({run_a.name}): runout {rb['runout']:.1f} m against "
            f"{ra['runout']:.1f} m, max peak pressure {rb['peak_pressure_max_kPa']:.3g} against "
            f"{ra['peak_pressure_max_kPa']:.3g} kPa, area above 1 kPa "
            f"{rb['area_above_1_kPa_m2']:.0f} against {ra['area_above_1_kPa_m2']:.0f} m2 "
            f"({only_b:.0f} m2 reached by B only, {only_a:.0f} m2 by A only)")
    if "structure_retained_volume" in rb:
        text += (f"; B's structures: retained {rb['structure_retained_volume']:.4g} m3, "
                 f"beyond {rb['structure_overtopped_volume']:.4g} m3")
    return text, written


def _ascending(ds, values):
    """``values`` on (y, x) with y ascending, as the map helpers of ``avflow plot`` take."""
    values = np.asarray(values, dtype=float)
    return values[::-1] if ds["y"].values[0] > ds["y"].values[-1] else values


def _plot(a, b, pa, pb, target: Path, name_a: str, name_b: str) -> Path:
    from avflow.output.maps import _plt, _save

    plt = _plt()
    fig = compare_figure(a, b, pa, pb, name_a, name_b)
    try:
        return _save(fig, target, dpi=100)
    finally:
        plt.close(fig)


def compare_figure(a, b, pa, pb, name_a: str, name_b: str):
    """The figure of ``avflow compare``: peak pressure (kPa: ``pa``, ``pb``) of A and of B in
    the runs' pressure classes, and B - A, in the style of ``avflow plot``: hillshade and
    contours, axes in the CRS, the release and the structures outlined, scale bar and north
    arrow."""
    from matplotlib.colors import TwoSlopeNorm
    from matplotlib.lines import Line2D

    from avflow.output.maps import (
        _class_legend, _class_style, _plain_ticks, _plt, _scale_and_north,
        crs_name, draw_terrain, pressure_classes, run_pressure_classes)

    plt = _plt()
    x = np.asarray(a["x"].values, dtype=float)
    y = np.sort(np.asarray(a["y"].values, dtype=float))
    dx, dy = abs(x[1] - x[0]), abs(y[1] - y[0])
    extent = (x[0] - dx / 2, x[-1] + dx / 2, y[0] - dy / 2, y[-1] + dy / 2)
    aspect = (extent[3] - extent[2]) / (extent[1] - extent[0])
    if aspect < 1.0:  # wider than tall: one map under the other, colourbars underneath
        aspect, where = max(aspect, 0.12), "bottom"
        fig, axes = plt.subplots(3, 1, figsize=(8.0, 3 * 7.2 * aspect + 3.2),
                                 layout="constrained", sharex=True, sharey=True)
    else:
        aspect, where = min(aspect, 2.0), "right"
        fig, axes = plt.subplots(1, 3, figsize=(15.0, 4.2 * aspect + 1.8),
                                 layout="constrained", sharex=True, sharey=True)
    axes = list(axes)
    classes = pressure_classes(b)
    cmap, norm = _class_style(len(classes))
    crs = crs_name(b)

    def raster(ax, values, **kw):
        return ax.imshow(np.ma.masked_invalid(values), extent=extent, origin="lower",
                         interpolation="nearest", **kw)

    def outlines(ax, ds):
        handles = []
        release = _ascending(ds, ds["h"].isel(time=0).values) if "h" in ds else None
        if release is not None and (np.nan_to_num(release) > 0).any():
            ax.contour(x, y, (np.nan_to_num(release) > 0).astype(float), levels=[0.5],
                       colors="tab:blue", linewidths=1.4, linestyles="--")
            handles.append(Line2D([], [], color="tab:blue", ls="--", lw=1.4, label="release"))
        if "structure_height" in ds:
            added = np.nan_to_num(_ascending(ds, ds["structure_height"].values))
            if (added > 0.5).any():
                ax.contour(x, y, (added > 0.5).astype(float), levels=[0.5], colors="black",
                           linewidths=1.2)
                handles.append(Line2D([], [], color="black", lw=1.2,
                                      label="structure (> 0.5 m)"))
        return handles

    handles = {}
    for ax, ds, title in ((axes[0], a, f"A: {name_a}"), (axes[1], b, f"B: {name_b}")):
        draw_terrain(ax, x, y, _ascending(ds, ds["bed_elevation"].values))
        k = _ascending(ds, run_pressure_classes(ds))
        raster(ax, np.where(k > 0, k, np.nan), cmap=cmap, norm=norm, alpha=0.9)
        for h in outlines(ax, ds):
            handles[h.get_label()] = h
        ax.set_title(f"{title}: peak pressure", fontsize=9)
    draw_terrain(axes[2], x, y, _ascending(b, b["bed_elevation"].values))
    d = _ascending(a, pb - pa)
    lim = max(float(np.abs(d).max()), 1e-9)
    reached = _ascending(a, (pa >= 1.0) | (pb >= 1.0))
    im = raster(axes[2], np.where(reached, d, np.nan), cmap="RdBu_r",
                norm=TwoSlopeNorm(0.0, -lim, lim), alpha=0.9)
    for h in outlines(axes[2], b):
        handles[h.get_label()] = h
    axes[2].set_title("peak pressure B \u2212 A (red: higher in B)", fontsize=9)
    bar = fig.colorbar(im, ax=axes[2], shrink=0.8, location=where,
                       aspect=20 if where == "right" else 40)
    bar.set_label("peak pressure B \u2212 A (kPa), where either is \u2265 1 kPa")
    for ax in axes:
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_aspect("equal")
        _plain_ticks(ax)
        ax.set_xlabel("x (m)" + (f", {crs}" if crs else ""), fontsize=8)
        ax.set_ylabel("y (m)", fontsize=8)
        ax.tick_params(labelsize=7)
        plt.setp(ax.get_xticklabels(), rotation=20, ha="right")
        _scale_and_north(ax)
    if handles:  # on B's map: A, without its structures, would name one it lacks
        axes[1].legend(handles=list(handles.values()), loc="lower right", fontsize=7,
                       framealpha=0.8)
    _class_legend(fig, classes, "bottom", None)
    fig.suptitle(f"B ({name_b}) against A ({name_a})", fontsize=10)
    return fig
