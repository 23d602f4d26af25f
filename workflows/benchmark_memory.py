"""Peak memory of a run that writes its file: snapshots streamed, against all in memory.

    python workflows/benchmark_memory.py              # 2000 x 2000 DEM, 50 snapshots (~3-5 min)
    python workflows/benchmark_memory.py --size 500 --compare-size 250   # a quick look

Synthesizes, in a temporary folder, an inclined valley with some relief as a GeoTIFF DEM
(``--size`` cells a side, ``--dx`` m, a UTM CRS), a release polygon (GeoJSON, 2 m thick)
near its top and a scenario of ``--snapshots`` snapshots (t = 0 included) over ``--end``
seconds (Coulomb 20 degrees), then runs in a subprocess, each measured by ``os.wait4``
(the child's own peak resident memory, ``ru_maxrss``), with its wall time and file size:

- ``avflow run`` (streamed: one snapshot in memory whatever their number) on the full DEM,
  and with half the snapshots (the peak should not move);
- on a ``--compare-size`` DEM cut from the same valley, ``avflow run`` and the in-memory
  path of before (``write_netcdf(avflow.run(...))``: every snapshot in memory, then the
  Dataset, then the file) side by side. The in-memory path is run on the full DEM only with
  ``--in-memory-full`` (it needs the estimate's memory: ~16 GB at 2000 x 2000 x 50).

Beside each: avflow's estimate before the run (avflow.simulation.resources: the memory
check of ``--max-memory``), and the file's uncompressed bound. A first tiny run fills
Numba's cache so that no measured child compiles.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CRS_EPSG = 32632  # UTM 32N: metres
X0, Y0 = 600_000.0, 5_200_000.0

#: The in-memory path of before, in a child: every snapshot kept, then the Dataset, the file.
IN_MEMORY = ("import sys, avflow; from avflow.output.netcdf import write_netcdf; "
             "write_netcdf(avflow.run(sys.argv[1], max_memory='none'), sys.argv[2])")


def valley(n: int, dx: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Elevation (n x n) of a valley falling along +x, concave (35 to ~10 degrees over 4 km
    at 2 m), with a parabolic cross-section and a few metres of relief; cell centres."""
    x = X0 + dx * (np.arange(n) + 0.5)
    y = Y0 + dx * (np.arange(n) + 0.5)
    s = (x - X0)[None, :]
    across = (y - Y0)[:, None] - 0.5 * n * dx
    length = n * dx
    z = (2000.0 - 0.7 * s + 0.3 / length * s**2  # slope 0.7 at the top, 0.1 at the bottom
         + 250.0 * np.tanh((across / (0.15 * length + 1.0)) ** 2)
         + 3.0 * np.sin(2 * np.pi * s / 170.0) * np.sin(2 * np.pi * across / 230.0)
         + 2.0 * np.cos(2 * np.pi * s / 97.0 + 1.3))
    return z.astype(np.float64), x, y


def write_inputs(folder: Path, n: int, dx: float, snapshots: int, end: float) -> Path:
    """dem.tif, release.geojson and scenario.yaml of an n x n valley; the scenario's path."""
    from pyproj import CRS

    from avflow.terrain.raster import write_tif

    folder.mkdir(parents=True, exist_ok=True)
    z, x, y = valley(n, dx)
    write_tif(folder / "dem.tif", z, x, y, CRS.from_epsg(CRS_EPSG).to_wkt())
    # 120 m along the valley, 160 m across, centred 150 m below the top
    x0, x1 = X0 + 90.0, X0 + 210.0
    yc = Y0 + 0.5 * n * dx
    ring = [[x0, yc - 80.0], [x1, yc - 80.0], [x1, yc + 80.0], [x0, yc + 80.0], [x0, yc - 80.0]]
    (folder / "release.geojson").write_text(json.dumps({
        "type": "FeatureCollection",
        "crs": {"type": "name", "properties": {"name": f"urn:ogc:def:crs:EPSG::{CRS_EPSG}"}},
        "features": [{"type": "Feature", "properties": {"thickness": 2.0},
                      "geometry": {"type": "Polygon", "coordinates": [ring]}}]}))
    every = end / max(snapshots - 1, 1)
    path = folder / "scenario.yaml"
    path.write_text(f"""name: benchmark-memory-{n}
terrain: {{kind: dem, path: dem.tif}}
grid: {{dx: {dx}}}
release: {{kind: polygon, path: release.geojson}}
rheology: {{law: coulomb, delta_deg: 20.0}}
time: {{end: {end}}}
output: {{every: {every!r}}}
""")
    return path


def measure(argv: list[str]) -> tuple[float, float, int]:
    """Run ``argv``; (peak resident MiB of that child, wall s, exit status)."""
    started = time.perf_counter()
    child = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - started
    err = child.stderr.read().decode(errors="replace").strip()
    child.stderr.close()
    code = os.waitstatus_to_exitcode(status)
    if code != 0:
        print(f"  exit {code}: {err.splitlines()[-1] if err else ''}", file=sys.stderr)
    # ru_maxrss: KiB on Linux, bytes on macOS
    kib = usage.ru_maxrss / (1024.0 if sys.platform == "darwin" else 1.0)
    return kib / 1024.0, wall, code


def run_row(label: str, scenario: Path, out: Path, in_memory: bool, extra: list[str]) -> dict:
    from avflow.scenario import load_scenario
    from avflow.simulation.resources import estimate

    sc = load_scenario(scenario)
    est = estimate(sc, streamed=not in_memory)
    argv = ([sys.executable, "-c", IN_MEMORY, str(scenario), str(out)] if in_memory else
            [sys.executable, "-m", "avflow.cli", "run", str(scenario), "-o", str(out), "-q",
             "--max-memory", "none", *extra])
    rss, wall, code = measure(argv)
    loop = float("nan")
    if code == 0:
        import xarray as xr

        with xr.open_dataset(out, decode_times=False) as ds:
            loop = float(ds["wall_time"])
            n_snap = ds.sizes["time"]
    else:
        n_snap = 0
    row = {"run": label, "cells": est.cells, "snapshots": n_snap,
           "path": "in memory" if in_memory else "streamed", "rss_mib": rss,
           "estimate_mib": est.bytes / 2**20, "wall_s": wall, "loop_s": loop,
           "file_mib": out.stat().st_size / 2**20 if code == 0 else float("nan"),
           "file_bound_mib": est.file_bytes / 2**20, "exit": code}
    print(f"  {label}: {rss:.0f} MiB peak, {wall:.1f} s", file=sys.stderr)
    if code == 0:
        out.unlink()
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=2000, help="cells a side (default 2000)")
    p.add_argument("--dx", type=float, default=2.0, help="cell size, m (default 2)")
    p.add_argument("--snapshots", type=int, default=50, help="snapshots, t = 0 included "
                   "(default 50)")
    p.add_argument("--end", type=float, default=20.0, help="simulated s (default 20)")
    p.add_argument("--compare-size", type=int, default=1000, help="cells a side of the "
                   "side-by-side comparison with the in-memory path (default 1000; 0: none)")
    p.add_argument("--in-memory-full", action="store_true", help="also run the in-memory "
                   "path on the full DEM (needs the estimate's memory)")
    p.add_argument("--threads", type=int, help="passed to avflow run --threads")
    p.add_argument("--keep", help="folder to write the inputs to (kept); default: a "
                   "temporary folder")
    args = p.parse_args(argv)
    extra = ["--threads", str(args.threads)] if args.threads else []
    folder = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="avflow-mem-"))
    rows = []
    try:
        print(f"inputs in {folder}", file=sys.stderr)
        warm = write_inputs(folder / "warm", 100, args.dx, 3, 1.0)
        measure([sys.executable, "-m", "avflow.cli", "run", str(warm), "-o",
                 str(folder / "warm" / "out.nc"), "-q"])  # fills Numba's cache
        full = write_inputs(folder / "full", args.size, args.dx, args.snapshots, args.end)
        half = write_inputs(folder / "half", args.size, args.dx,
                            max(args.snapshots // 2, 2), args.end)
        n = args.size
        rows.append(run_row(f"{n} x {n}", full, folder / "full.nc", False, extra))
        rows.append(run_row(f"{n} x {n}", half, folder / "half.nc", False, extra))
        if args.in_memory_full:
            rows.append(run_row(f"{n} x {n}", full, folder / "full_mem.nc", True, extra))
        if args.compare_size:
            m = args.compare_size
            small = write_inputs(folder / "small", m, args.dx, args.snapshots, args.end)
            rows.append(run_row(f"{m} x {m}", small, folder / "small.nc", False, extra))
            rows.append(run_row(f"{m} x {m}", small, folder / "small_mem.nc", True, extra))
    finally:
        if not args.keep:
            import shutil

            shutil.rmtree(folder, ignore_errors=True)
    print("| DEM | cells | snapshots | snapshots kept | peak RSS MiB | estimate MiB | "
          "wall s | time loop s | file MiB | file bound MiB |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['run']} | {r['cells']:,} | {r['snapshots']} | {r['path']} | "
              f"{r['rss_mib']:.0f} | {r['estimate_mib']:.0f} | {r['wall_s']:.1f} | "
              f"{r['loop_s']:.1f} | {r['file_mib']:.1f} | {r['file_bound_mib']:.0f} |")
    if not args.in_memory_full:
        from avflow.simulation.resources import BYTES_PER_CELL, BYTES_PER_CELL_SNAPSHOT

        cells = args.size**2
        need = cells * (BYTES_PER_CELL["grid"] + args.snapshots * BYTES_PER_CELL_SNAPSHOT)
        print(f"\nin memory on the full DEM (not run; --in-memory-full): estimated "
              f"{need / 2**30:.1f} GiB ({args.snapshots} snapshots of {cells:,} cells)")
    return 0 if all(r["exit"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
