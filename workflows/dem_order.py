"""Which order on DEMs: order 1 and order 2 on real paths against a finer reference.

    python workflows/dem_order.py                       # avaKot and avaWog, 10 / 5 / 2.5 m
    python workflows/dem_order.py --quick               # 20 m against 10 m (smoke test, ~1 min)
    python workflows/dem_order.py --paths avaKot --sizes 10,5,2.5 --reference-dx 1.25

For each path (``scenarios/avakot_coulomb.yaml``, ``scenarios/avawog_coulomb.yaml``, the
Coulomb scenario files as they are) every order at every cell size of ``--sizes`` is run
with ``avflow run --threads 1 --set grid.dx=DX --set numerics.order=N`` in a subprocess
that imports this checkout, and the reference with order ``--reference-order`` (2) at
``--reference-dx`` (2.5 m). A run with the reference's order and cell size is the reference
itself. Runs whose time loop took under ``REPEAT_BELOW_S`` are run again (3 in all) and the
fastest kept. Files go to ``--out`` (default ``out/dem_order``); a file that is there is
reused unless ``--force``.

Everything is measured from the NetCDF files (xarray), on the reference's cells: each
coarse field is sampled at the reference's cell centres (the coarse cell that holds each
reference centre; outside the coarse map or on its NODATA: 0). Measured per run:

- ``wall``: the summary ``wall_time`` (the time loop alone, one thread; Numba compiled
  beforehand, not counted), seconds;
- ``runout``: the summary's (horizontal distance from the release's centroid to the farthest
  cell of the final thickness above the file's ``runout_threshold_m``, 1 mm), and its
  difference from the reference's;
- footprint: cells whose peak thickness exceeds ``--threshold`` (0.1 m; the files' own
  threshold, ``runout_threshold_m``, is 1 mm: it draws the outline of ``avflow plot``):
  its area (horizontal, km^2, on the run's own cells), its excess over the reference's, the
  area it covers outside the reference's footprint and the reference's area it misses (both
  over the reference's area), and the intersection over union with the reference's;
- widths across the path: the path is the reference's centre-of-mass track
  (``avflow.output.path.com_path``, as ``avflow path`` draws it); every reference cell
  centre gets its distance ``s`` along it and ``l`` across it; in bins of 10 m along
  ``s``, a run's width is its footprint area in the bin over 10 m, and its spread the
  distance between its outermost footprint cells across the path (``l`` max - min).
  ``width`` is the mean width over the bins its footprint reaches (area / length
  covered along the path), ``spread`` the mean spread over the same bins: fingers and a
  fan of thin branches raise the spread much more than the width;
- ``L1 peak`` and ``L1 dep``: relative L1 differences of the peak thickness and of the
  final thickness, ``sum |h - h_ref| / sum h_ref`` over the reference's cells.

A second table gives the footprint's area, IoU and spread at 1 cm and 1 mm, and how each
run ended (its end time, what ended it, the share of the volume still moving). One PNG per path
(``PATH_footprints.png``): the peak thickness of every run, rows by cell size and columns by
order, over the hillshade, with the reference's footprint outline on each panel.
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"
PATHS = {"avaKot": "avakot_coulomb.yaml", "avaWog": "avawog_coulomb.yaml"}
REPEAT_BELOW_S = 5.0
BIN_M = 10.0


# =========================================================================================
# Runs
# =========================================================================================


def run_name(path: str, order: int, dx: float) -> str:
    return f"{path}_o{order}_dx{dx:g}"


def avflow_run(scenario: Path, order: int, dx: float, target: Path) -> None:
    """One ``avflow run`` of this checkout, one thread; raises on failure."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, "-m", "avflow.cli", "run", str(scenario), "-q", "--threads", "1",
           "--set", f"grid.dx={dx:g}", "--set", f"numerics.order={order}", "-o", str(target)]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if done.returncode != 0 or not target.exists():
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}): {done.stderr[-2000:]}")


def loop_wall(target: Path) -> float:
    import xarray as xr

    with xr.open_dataset(target) as ds:
        return float(ds["wall_time"])


def ensure_run(out: Path, path: str, order: int, dx: float, force: bool) -> dict:
    """The run's file (made if absent or ``force``) and its best loop wall time."""
    target = out / f"{run_name(path, order, dx)}.nc"
    walls_file = target.with_suffix(".walls")
    if force or not target.exists():
        target.unlink(missing_ok=True)
        walls_file.unlink(missing_ok=True)
        t0 = time.perf_counter()
        avflow_run(SCENARIOS / PATHS[path], order, dx, target)
        walls = [loop_wall(target)]
        while walls[0] < REPEAT_BELOW_S and len(walls) < 3:  # short runs: best of 3
            again = target.with_name(target.stem + ".again.nc")
            avflow_run(SCENARIOS / PATHS[path], order, dx, again)
            walls.append(loop_wall(again))
            again.unlink()
        walls_file.write_text(" ".join(f"{w:.6g}" for w in walls) + "\n")
        print(f"  {target.name}: loop {min(walls):.3g} s (of {len(walls)}), "
              f"{time.perf_counter() - t0:.1f} s in all", flush=True)
    walls = [float(w) for w in walls_file.read_text().split()] if walls_file.exists() \
        else [loop_wall(target)]
    return {"path": path, "order": order, "dx": dx, "file": target, "wall": min(walls),
            "walls": walls}


# =========================================================================================
# Measures
# =========================================================================================


class Grid:
    """A run's grid fields (float64, NaN -> 0 for thicknesses)."""

    def __init__(self, file: Path):
        import xarray as xr

        with xr.open_dataset(file) as ds:
            self.x = ds["x"].values.astype(float)
            self.y = ds["y"].values.astype(float)
            self.bed = ds["bed_elevation"].values.astype(float)
            self.peak = np.nan_to_num(ds["peak_thickness"].values.astype(float))
            self.deposit = np.nan_to_num(ds["deposit_thickness"].values.astype(float))
            self.summary = {k: float(ds[k]) for k in ("runout", "wall_time", "time_to_stop",
                                                       "moving_volume_end", "release_volume",
                                                       "deposit_max_thickness")}
            self.attrs = dict(ds.attrs)
            self.steps = int(ds.attrs.get("steps", 0))
            self.com = (ds["center_of_mass_x"].values.astype(float),
                        ds["center_of_mass_y"].values.astype(float))
            self.h0 = np.nan_to_num(ds["h"].isel(time=0).values.astype(float))
            self.end = float(ds["time"].values[-1])
        self.dx = float(self.x[1] - self.x[0])
        self.dy = float(self.y[1] - self.y[0])

    @property
    def cell_area(self) -> float:
        return self.dx * self.dy

    def sample(self, field: np.ndarray, xr_: np.ndarray, yr_: np.ndarray) -> np.ndarray:
        """``field`` at the points ``(yr_[:, None], xr_[None, :])``: the value of the cell that
        holds each point, 0 outside the map."""
        ix = np.rint((xr_ - self.x[0]) / self.dx).astype(int)
        iy = np.rint((yr_ - self.y[0]) / self.dy).astype(int)
        okx = (ix >= 0) & (ix < self.x.size)
        oky = (iy >= 0) & (iy < self.y.size)
        out = field[np.clip(iy, 0, self.y.size - 1)[:, None],
                    np.clip(ix, 0, self.x.size - 1)[None, :]]
        return np.where(oky[:, None] & okx[None, :], out, 0.0)


def path_coordinates(ref: Grid, cells: np.ndarray):
    """``(s, l)`` of the reference's cell centres ``cells`` (a mask) along the reference's
    centre-of-mass track, extended to the top of its release."""
    from avflow.output.path import com_path

    X, Y = np.meshgrid(ref.x, ref.y)
    rel = ref.h0 > 0.0
    bed = np.where(rel, ref.bed, -np.inf)
    top = np.unravel_index(np.argmax(bed), bed.shape)
    line = com_path(ref.com[0], ref.com[1], float(X[top]), float(Y[top]),
                    2.0 * max(ref.dx, 5.0))
    s, l = line.project(X[cells], Y[cells])
    return s, l, line


def widths(foot: np.ndarray, s: np.ndarray, l: np.ndarray, cell_area: float, cell: float):
    """Mean width (area / length along the path covered) and mean spread across the path of
    a footprint (mask over the projected cells), in bins of ``BIN_M`` along ``s``."""
    if not foot.any():
        return math.nan, math.nan
    b = np.floor(s[foot] / BIN_M).astype(int)
    b -= b.min()
    counts = np.bincount(b)
    lo = np.full(counts.size, np.inf)
    hi = np.full(counts.size, -np.inf)
    np.minimum.at(lo, b, l[foot])
    np.maximum.at(hi, b, l[foot])
    covered = counts > 0
    width = counts[covered].sum() * cell_area / (covered.sum() * BIN_M)
    spread = float(np.mean(hi[covered] - lo[covered] + cell))
    return float(width), spread


def measure(runs: list[dict], reference: dict, threshold: float, extra_thresholds=()):
    """Every run's measures against the reference (rows, in the order of ``runs``)."""
    ref = Grid(reference["file"])
    grids = {id(r): (ref if r is reference else Grid(r["file"])) for r in runs}
    sampled = {}
    for r in runs:
        g = grids[id(r)]
        if r is reference:
            sampled[id(r)] = (ref.peak, ref.deposit)
        else:
            sampled[id(r)] = (g.sample(g.peak, ref.x, ref.y), g.sample(g.deposit, ref.x, ref.y))
    # project once every reference cell that any run's footprint (lowest threshold) covers
    lowest = min((threshold,) + tuple(extra_thresholds))
    cells = np.zeros(ref.peak.shape, bool)
    for peak, _ in sampled.values():
        cells |= peak > lowest
    s, l, line = path_coordinates(ref, cells)
    ref_foot = ref.peak > threshold
    ref_area = ref_foot.sum() * ref.cell_area
    rows = []
    for r in runs:
        g = grids[id(r)]
        peak, dep = sampled[id(r)]
        foot = peak > threshold
        inter = np.count_nonzero(foot & ref_foot)
        union = np.count_nonzero(foot | ref_foot)
        own_area = np.count_nonzero(g.peak > threshold) * g.cell_area
        width, spread = widths(foot[cells], s, l, ref.cell_area, ref.dx)
        row = {
            "path": r["path"], "order": r["order"], "dx": r["dx"], "reference": r is reference,
            "wall": r["wall"], "walls": r["walls"], "steps": g.steps,
            "end": g.end, "ended_by": g.attrs.get("ended_by", g.attrs.get("status", "")),
            "moving_end": g.summary["moving_volume_end"] / g.summary["release_volume"],
            "truncated": bool(int(g.attrs.get("runout_truncated", 0))),
            "runout": g.summary["runout"],
            "runout_diff": g.summary["runout"] - ref.summary["runout"],
            "area": own_area / 1e6,
            "area_excess": own_area / ref_area - 1.0,
            "outside": np.count_nonzero(foot & ~ref_foot) * ref.cell_area / ref_area,
            "missed": np.count_nonzero(~foot & ref_foot) * ref.cell_area / ref_area,
            "iou": inter / union if union else math.nan,
            "width": width, "spread": spread,
            "l1_peak": float(np.abs(peak - ref.peak).sum() / ref.peak.sum()),
            "l1_dep": float(np.abs(dep - ref.deposit).sum() / ref.deposit.sum()),
            "deposit_max": g.summary["deposit_max_thickness"],
        }
        for t in extra_thresholds:
            f, rf = peak > t, ref.peak > t
            u = np.count_nonzero(f | rf)
            row[f"area@{t:g}"] = np.count_nonzero(g.peak > t) * g.cell_area / 1e6
            row[f"iou@{t:g}"] = np.count_nonzero(f & rf) / u if u else math.nan
            row[f"spread@{t:g}"] = widths(f[cells], s, l, ref.cell_area, ref.dx)[1]
        rows.append(row)
    return rows, line


# =========================================================================================
# Report
# =========================================================================================


def pct(v: float) -> str:
    return f"{100 * v:+.0f}%" if math.isfinite(v) else "-"


def table(rows: list[dict], threshold: float) -> list[str]:
    head = ("| path | order | dx (m) | loop wall (s) | steps | runout (m) | vs ref (m) | "
            f"area > {threshold:g} m (km²) | excess | outside ref | ref missed | IoU | "
            "width (m) | spread (m) | L1 peak | L1 deposit |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        name = "**reference**, order" if r["reference"] else ""
        trunc = " (edge)" if r["truncated"] else ""
        lines.append(
            f"| {r['path']} | {name} {r['order']} | {r['dx']:g} | {r['wall']:.3g} | "
            f"{r['steps']} | {r['runout']:.0f}{trunc} | {r['runout_diff']:+.0f} | "
            f"{r['area']:.3f} | {pct(r['area_excess'])} | {100 * r['outside']:.0f}% | "
            f"{100 * r['missed']:.0f}% | {r['iou']:.2f} | {r['width']:.0f} | "
            f"{r['spread']:.0f} | {r['l1_peak']:.2f} | {r['l1_dep']:.2f} |")
    return lines


def threshold_table(rows: list[dict], thresholds) -> list[str]:
    cols = " | ".join(f"area > {t:g} m (km²) | IoU | spread (m)" for t in thresholds)
    head = f"| path | order | dx (m) | {cols} | end (s) | ended by | moving at end |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        vals = " | ".join(f"{r[f'area@{t:g}']:.3f} | {r[f'iou@{t:g}']:.2f} | "
                          f"{r[f'spread@{t:g}']:.0f}" for t in thresholds)
        name = "ref. " if r["reference"] else ""
        lines.append(f"| {r['path']} | {name}{r['order']} | {r['dx']:g} | {vals} | "
                     f"{r['end']:.1f} | {r['ended_by']} | {100 * r['moving_end']:.0f}% |")
    return lines


def equal_time(rows: list[dict]) -> list[str]:
    """Each order-2 run beside the order-1 run at half its cell size: about the same time."""
    lines = ["| path | order 2 at | loop (s) | IoU | L1 peak | order 1 at | loop (s) | IoU | "
             "L1 peak |", "|---|---|---|---|---|---|---|---|---|"]
    by = {(r["path"], r["order"], r["dx"]): r for r in rows}
    for r in rows:
        if r["order"] != 2 or r["reference"]:
            continue
        o1 = by.get((r["path"], 1, r["dx"] / 2))
        if o1 is None:
            continue
        lines.append(f"| {r['path']} | {r['dx']:g} m | {r['wall']:.3g} | {r['iou']:.2f} | "
                     f"{r['l1_peak']:.2f} | {o1['dx']:g} m | {o1['wall']:.3g} | "
                     f"{o1['iou']:.2f} | {o1['l1_peak']:.2f} |")
    return lines


def machine() -> str:
    load = os.getloadavg()
    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (f"{platform.node() or 'this machine'}: {os.cpu_count()} cores ({model or '?'}), "
            f"load average {load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f} (1 / 5 / 15 min)")


def commit() -> str:
    try:
        done = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=True)
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "avflow"],
                               capture_output=True, text=True, check=True).stdout.strip()
        return done.stdout.strip() + (" (avflow/ modified)" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "?"


# =========================================================================================
# Figure
# =========================================================================================


def figure(path: str, runs: list[dict], reference: dict, threshold: float, line, target: Path,
           rows_dx=None):
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    from avflow.output.maps import hillshade

    ref = Grid(reference["file"])
    runs = [r for r in runs if rows_dx is None or r["dx"] in rows_dx]
    grids = [(r, ref if r is reference else Grid(r["file"])) for r in runs]
    sizes = sorted({r["dx"] for r in runs if rows_dx is None or r["dx"] in rows_dx},
                   reverse=True)
    orders = sorted({r["order"] for r in runs})
    # the view: every run's footprint above 1 cm, with a margin
    lo_x, hi_x, lo_y, hi_y = np.inf, -np.inf, np.inf, -np.inf
    for _, g in grids:
        jy, jx = np.nonzero(g.peak > 0.01)
        if jx.size:
            lo_x, hi_x = min(lo_x, g.x[jx].min()), max(hi_x, g.x[jx].max())
            lo_y, hi_y = min(lo_y, g.y[jy].min()), max(hi_y, g.y[jy].max())
    margin = 60.0
    view = (lo_x - margin, hi_x + margin, lo_y - margin, hi_y + margin)
    aspect = (view[3] - view[2]) / (view[1] - view[0])
    w = 3.6
    fig, axes = plt.subplots(len(sizes), len(orders), squeeze=False,
                             figsize=(w * len(orders) + 1.0, w * aspect * len(sizes) + 0.8),
                             layout="constrained")
    vmax = max(float(g.peak.max()) for _, g in grids)
    norm = LogNorm(vmin=0.01, vmax=vmax)
    image = None
    for i, dx in enumerate(sizes):
        for j, order in enumerate(orders):
            ax = axes[i][j]
            match = [(r, g) for r, g in grids if r["dx"] == dx and r["order"] == order]
            ax.set_xlim(view[0], view[1])
            ax.set_ylim(view[2], view[3])
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            if not match:
                ax.set_axis_off()
                continue
            r, g = match[0]
            ext = (g.x[0] - g.dx / 2, g.x[-1] + g.dx / 2, g.y[0] - g.dy / 2, g.y[-1] + g.dy / 2)
            ax.imshow(np.ma.masked_invalid(hillshade(g.bed, g.dx, g.dy)), extent=ext,
                      origin="lower", cmap="gray", vmin=-0.5, vmax=1.15, interpolation="nearest")
            image = ax.imshow(np.ma.masked_less_equal(g.peak, 0.01), extent=ext, origin="lower",
                              cmap="viridis", norm=norm, interpolation="nearest")
            ax.contour(ref.x, ref.y, (ref.peak > threshold).astype(float), levels=[0.5],
                       colors="red", linewidths=0.7)
            ax.plot(line.x, line.y, color="white", lw=0.6, ls="--")
            label = "reference, " if r is reference else ""
            ax.set_title(f"{label}order {order}, {dx:g} m (loop {r['wall']:.2g} s)", fontsize=8)
    if image is not None:
        bar = fig.colorbar(image, ax=axes, shrink=0.6)
        bar.set_label("peak thickness (m), above 1 cm")
    fig.suptitle(f"{path}, Coulomb 20°: peak thickness; red: reference's footprint "
                 f"(> {threshold:g} m); dashed: its centre-of-mass track", fontsize=9)
    fig.savefig(target, dpi=90)
    plt.close(fig)
    try:  # a 256-colour palette: a third of the bytes, for the docs
        from PIL import Image

        with Image.open(target) as im:
            im.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(
                target, optimize=True)
    except ImportError:
        pass
    return target


# =========================================================================================
# Driver
# =========================================================================================


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    p.add_argument("--paths", default="avaKot,avaWog", help="comma-separated: avaKot, avaWog")
    p.add_argument("--sizes", default="10,5,2.5", help="cell sizes (m), both orders at each")
    p.add_argument("--reference-dx", type=float, default=2.5)
    p.add_argument("--reference-order", type=int, default=2, choices=(1, 2))
    p.add_argument("--threshold", type=float, default=0.1, help="footprint: peak > this (m)")
    p.add_argument("--quick", action="store_true",
                   help="20 m against a 10 m reference: a smoke test of about a minute")
    p.add_argument("--out", type=Path, default=ROOT / "out" / "dem_order")
    p.add_argument("--report", type=Path, default=None,
                   help="markdown report (default OUT/report.md)")
    p.add_argument("--force", action="store_true", help="run again even where files exist")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--figure-sizes", default=None,
                   help="cell sizes (m) drawn as the figure's rows (default: all)")
    a = p.parse_args(argv)
    if a.quick:
        a.sizes, a.reference_dx = "20", 10.0
    return a


def main(argv=None) -> int:
    a = parse_args(argv)
    args = sys.argv[1:] if argv is None else list(argv)
    paths = [p.strip() for p in a.paths.split(",") if p.strip()]
    unknown = [p for p in paths if p not in PATHS]
    if unknown:
        print(f"unknown path(s) {unknown}; known: {list(PATHS)}", file=sys.stderr)
        return 2
    sizes = [float(s) for s in a.sizes.split(",") if s.strip()]
    a.out.mkdir(parents=True, exist_ok=True)
    report = a.report or a.out / "report.md"
    extra = (0.01, 0.001)
    started = time.perf_counter()
    load_before = os.getloadavg()
    all_rows, figures = [], []
    for path in paths:
        print(f"{path}:", flush=True)
        reference = ensure_run(a.out, path, a.reference_order, a.reference_dx, a.force)
        runs = []
        for dx in sizes:
            for order in (1, 2):
                if (order, dx) == (a.reference_order, a.reference_dx):
                    runs.append(reference)
                else:
                    runs.append(ensure_run(a.out, path, order, dx, a.force))
        if not any(r is reference for r in runs):
            runs.append(reference)
        rows, line = measure(runs, reference, a.threshold, extra)
        all_rows += rows
        if not a.no_figures:
            rows_dx = None if a.figure_sizes is None else \
                {float(v) for v in a.figure_sizes.split(",") if v.strip()}
            figures.append(figure(path, runs, reference, a.threshold, line,
                                  a.out / f"{path}_footprints.png", rows_dx))
    lines = [
        "# Order 1 and order 2 on DEMs: `workflows/dem_order.py`",
        "",
        f"- date: {datetime.date.today().isoformat()}; commit {commit()}",
        f"- machine: {machine()}; load average at the start "
        f"{load_before[0]:.2f} / {load_before[1]:.2f} / {load_before[2]:.2f}",
        f"- command: `python workflows/dem_order.py {' '.join(args)}`"
        f" ({time.perf_counter() - started:.0f} s, runs found in {a.out} reused)",
        f"- reference: order {a.reference_order} at {a.reference_dx:g} m; every run sampled at "
        "the reference's cell centres; footprint: peak thickness > "
        f"{a.threshold:g} m (the files' runout_threshold_m: 1 mm); one thread; loop wall: the "
        f"summary wall_time, best of 3 below {REPEAT_BELOW_S:g} s",
        "",
        *table(all_rows, a.threshold),
        "",
        "At about equal time (order 2 beside order 1 at half its cell size):",
        "",
        *equal_time(all_rows),
        "",
        "Other footprint thresholds, and how each run ended:",
        "",
        *threshold_table(all_rows, extra),
        "",
        *[f"![{f.stem}]({f.name})" for f in figures],
    ]
    text = "\n".join(lines) + "\n"
    report.parent.mkdir(parents=True, exist_ok=True)
    report.write_text(text)
    print(text)
    print(f"wrote {report}" + "".join(f", {f}" for f in figures))
    return 0


if __name__ == "__main__":
    sys.exit(main())
