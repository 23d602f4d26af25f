"""What a protective structure did: its variables in the run file, and ``avflow compare``.

A run with ``structures`` carries, beside the edited ``bed_elevation``:

- ``structure_height`` (y, x): the height each structure added to the bed (m);
- along ``structure``: ``structure_retained_volume``, the final volume on the release's side
  of the line, and ``structure_overtopped_volume``, the final volume beyond it (overtopped,
  or gone round the line's ends); the material that left the map is in ``outflow_volume``.

``avflow compare RUN_A RUN_B`` sets two runs of the same map side by side (a scenario with
and without its structures): runout, travel angle, volumes, the peak-pressure maxima and the
areas above 1, 10 and 100 kPa, and the cells reached by one and not the other; a table (CSV,
Markdown) and a PNG of the peak-pressure difference.
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


def _plot(a, b, pa, pb, target: Path, name_a: str, name_b: str) -> Path:
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm

    from avflow.output.maps import hillshade

    x, y = a["x"].values, a["y"].values
    dx, dy = abs(x[1] - x[0]), abs(y[1] - y[0])
    extent = (x.min() - dx / 2, x.max() + dx / 2, y.min() - dy / 2, y.max() + dy / 2)
    origin = "lower" if y[0] < y[-1] else "upper"
    fig, axes = plt.subplots(1, 3, figsize=(15, 5), layout="constrained")
    for ax, ds, p, title in ((axes[0], a, pa, f"A: {name_a}"), (axes[1], b, pb, f"B: {name_b}")):
        bed = ds["bed_elevation"].values.astype(float)
        # hillshade takes rows south to north: light from the north-west either way
        shade = (hillshade(bed, dx, dy) if origin == "lower"
                 else hillshade(bed[::-1], dx, dy)[::-1])
        ax.imshow(shade, cmap="gray", extent=extent, origin=origin, vmin=0, vmax=1)
        im = ax.imshow(np.where(p >= 1.0, p, np.nan), cmap="viridis", extent=extent,
                       origin=origin, alpha=0.85)
        if "structure_height" in ds:
            added = ds["structure_height"].values
            ax.contour(x, y, np.nan_to_num(added), levels=[0.5], colors="red", linewidths=1)
        ax.set_title(title)
        ax.set_aspect("equal")
        fig.colorbar(im, ax=ax, shrink=0.8, label="peak pressure >= 1 kPa")
    d = pb - pa
    lim = max(float(np.abs(d).max()), 1e-9)
    im = axes[2].imshow(np.where((pa >= 1.0) | (pb >= 1.0), d, np.nan), cmap="RdBu_r",
                        norm=TwoSlopeNorm(0.0, -lim, lim), extent=extent, origin=origin)
    axes[2].set_title("peak pressure B - A (kPa)")
    axes[2].set_aspect("equal")
    fig.colorbar(im, ax=axes[2], shrink=0.8, label="kPa")
    try:
        atomic_write(target, lambda tmp: fig.savefig(tmp, dpi=100, format="png"))
    finally:
        plt.close(fig)
    return target
