"""Workflow benchmark of ``avflow region``: a synthetic region, end to end, for 1 and more
workers; prints a table (not a timed test).

    python workflows/region_benchmark.py [--size 2000] [--dx 10] [--releases 15]
                                         [--release-side 60] [--workers 0,1,2] [--keep DIR]

The region is made by workflows/make_region.py (ridge and valley, releases on 28-45 degree
slopes). Each entry of ``--workers`` (0: in this process, no dask; N: a local cluster of N
single-threaded workers) runs in a fresh Python process into a fresh folder (Numba's
kernels cached by a first warm-up run of two of the releases, as after any first use).
Columns:

- ``wall``: ``run_region`` from call to return (cluster start, runs, merge, tables);
- ``rel/min``: releases per minute of wall;
- ``runs %``: the releases' time in the solver (sum of ``run_time``) over workers x wall;
- ``io %``: the rest of the release tasks (DEM windows read and written, the buffer's
  estimate, result files) over workers x wall;
- ``merge %``: merging the results into the Zarr store, in the main process, over wall;
- ``sched %``: the rest: cluster start, dispatch, results travelling, the idle tail;
- ``rss main`` / ``rss worker``: peak resident memory (MB) of the main process and of the
  largest worker (psutil, sampled every 0.1 s).

Timings mean something only on an otherwise idle machine: the load average is printed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _child(region: str, outdir: str, workers: int) -> None:
    """One measured run (in its own process); prints one JSON line."""
    import psutil

    from avflow.region import load_region
    from avflow.region.orchestrate import run_region

    me = psutil.Process()
    peak = {"main": 0, "worker": 0}
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            try:
                peak["main"] = max(peak["main"], me.memory_info().rss)
                for child in me.children(recursive=True):
                    try:
                        peak["worker"] = max(peak["worker"], child.memory_info().rss)
                    except psutil.Error:
                        pass
            except psutil.Error:
                pass
            time.sleep(0.1)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    clock = time.perf_counter()
    out = run_region(load_region(region), outdir, workers=workers, quiet=True)
    wall = time.perf_counter() - clock
    done.set()
    sampler.join()
    t = out.table
    print(json.dumps({"workers": workers, "n": len(t), "ok": int((t.status == "ok").sum()),
                      "wall": wall, "run": float(t.run_time.sum()),
                      "task": float(t.wall_time.sum()), "merge": out.timings.get("merge", 0.0),
                      "retries": int(t.retries.sum()), "cells": float(t.cells.mean()),
                      "rss_main": peak["main"] / 1e6, "rss_worker": peak["worker"] / 1e6}))


def _subset(region: Path, n: int) -> Path:
    """A copy of the region file whose layer holds its first ``n`` releases."""
    import pyogrio.raw

    meta, _, wkb, columns = pyogrio.raw.read(region.parent / "releases.gpkg")
    target = region.parent / "warm.gpkg"
    target.unlink(missing_ok=True)
    pyogrio.raw.write(str(target), wkb[:n], [c[:n] for c in columns], list(meta["fields"]),
                      driver="GPKG", crs=meta["crs"], geometry_type="Polygon")
    warm = region.with_name("warm.yaml")
    warm.write_text(region.read_text().replace("releases.gpkg", "warm.gpkg"))
    return warm


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=float, default=2000.0)
    p.add_argument("--dx", type=float, default=10.0)
    p.add_argument("--releases", type=int, default=15)
    p.add_argument("--release-side", type=float, default=60.0, help="m, of each square "
                                                                    "release")
    p.add_argument("--workers", default="0,1,2")
    p.add_argument("--keep", help="make the region (and the outputs) here instead of a "
                                  "temporary folder")
    p.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        _child(args.child[0], args.child[1], int(args.child[2]))
        return
    sys.path.insert(0, str(HERE))
    from make_region import make_region

    folder = Path(args.keep or tempfile.mkdtemp(prefix="avflow-region-bench-"))
    region = make_region(folder, args.size, args.dx, args.releases, args.release_side)
    print(f"region: {args.size:g} m x {args.size:g} m at {args.dx:g} m "
          f"({int(args.size / args.dx) ** 2:,} cells), {args.releases} releases of "
          f"{args.release_side:g} m x {args.release_side:g} m; "
          f"load average {os.getloadavg()[0]:.2f}, {os.cpu_count()} cores, "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    # a first run fills Numba's cache (not measured): two of the releases suffice
    warm = _subset(region, 2)
    subprocess.run([sys.executable, __file__, "--child", str(warm), str(folder / "warm"),
                    "0"], check=True, stdout=subprocess.DEVNULL)
    rows = []
    for w in [int(v) for v in args.workers.split(",")]:
        res = subprocess.run([sys.executable, __file__, "--child", str(region),
                              str(folder / f"out-{w}"), str(w)], check=True,
                             capture_output=True, text=True)
        rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
    head = ("workers", "releases", "ok", "retries", "cells/win", "wall s", "rel/min", "runs %",
            "io %", "merge %", "sched %", "rss main MB", "rss worker MB")
    print(" | ".join(head))
    print(" | ".join("---" for _ in head))
    for r in rows:
        n = max(r["workers"], 1)
        runs = r["run"] / n / r["wall"]
        io = (r["task"] - r["run"]) / n / r["wall"]
        merge = r["merge"] / r["wall"]
        sched = max(0.0, 1.0 - runs - io - merge)
        print(" | ".join([str(r["workers"]), str(r["n"]), str(r["ok"]), str(r["retries"]),
                          f"{r['cells']:.0f}", f"{r['wall']:.1f}",
                          f"{60 * r['n'] / r['wall']:.1f}", f"{100 * runs:.0f}",
                          f"{100 * io:.0f}", f"{100 * merge:.0f}", f"{100 * sched:.0f}",
                          f"{r['rss_main']:.0f}",
                          f"{r['rss_worker']:.0f}" if r["workers"] else "-"]))
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
