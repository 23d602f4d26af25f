"""The cuda backend on a GPU: throughput, avaKot end to end, an ensemble.

    python workflows/benchmark_gpu.py [-o benchmark_gpu.csv] [--sizes 1024,4096,8192]
                                      [--steps 50] [--members 20] [--orders 1,2]
                                      [--cpu-1m] [--tiny]

Writes one CSV, a row per measurement (``part``, ``case``, ``backend``, ``order``,
``cells``, ``steps``, ``wall_s``, ``cell_updates_per_s``, ``status``, then the run
summaries that CPU and GPU runs are compared by). Parts 1 and 2 run at each of
``--orders`` (default: 1 and 2; a step of order 2 is Heun's two stages and merge, so its
cell-updates/s counts each cell once a step); the ensemble at the first of them:

1. ``throughput``: an all-wet tilted plane of N x N cells (1 m of material on a 30 degree
   plane, Coulomb 20 degrees: every cell moves), ``--steps`` steps timed after a warm-up
   call that compiles the kernels and takes one step; cell-updates/s = cells x steps / wall.
2. ``avakot``: scenarios/avakot_coulomb.yaml end to end (``simulate``: output times,
   summaries) at 5 m on cuda and cpu, and at 1 m (the DEM resampled: ``grid.dx``) on cuda
   (``--cpu-1m``: on cpu too). The summary columns should agree (the sums to round-off).
3. ``ensemble``: ``avflow ensemble`` of ``--members`` avaKot members (Coulomb angle from
   16 to 26 degrees, 5 m) with ``--backend cuda --workers 0`` (one GPU, this process),
   timed as a command.

``--tiny``: the same parts on toy sizes (8 and 16 cells a side, avaKot at 100 m and 70 m
for its first 6 s, 2 members at 100 m), which run under numba-cuda's simulator in about two
minutes with both orders (``NUMBA_ENABLE_CUDASIM=1``, no GPU): a check that the script runs end to end, not a
measurement.

Meant for a GPU machine, under 10 minutes with the default sizes at order 1, longer with
order 2 (``--orders 1`` for order 1 alone; an H200's 141 GB hold an 8192 x 8192 grid at
either order, an H100's 80 GB at order 2 only just; the host builds its terrain first, some 20 GB of memory and a minute or
two). Nothing of this was measured yet: no GPU machine was available when it was written.
"""

from __future__ import annotations

import argparse
import csv
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace as NS

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
AVAKOT = ROOT / "scenarios" / "avakot_coulomb.yaml"
SUMMARY = ("runout", "travel_length", "travel_angle", "deposit_volume", "outflow_volume",
           "deposit_max_thickness", "time_to_stop", "kinetic_energy_peak", "ended_by")
COLUMNS = ("part", "case", "backend", "order", "cells", "steps", "wall_s",
           "cell_updates_per_s", "status") + SUMMARY


def throughput(n: int, steps: int, backend: str, order: int = 1) -> dict:
    """Cell-updates/s of ``steps`` steps on an all-wet N x N tilted plane at ``order``."""
    from avflow.numerics.rheology import Law
    from avflow.numerics.solver import Solver
    from avflow.terrain.bed import plane_terrain

    size = 10.0 * n
    plane = NS(slope_deg=30.0, azimuth_deg=90.0, extent=NS(x=[0.0, size], y=[0.0, size]),
               elevation_at_center=0.0)
    walls = NS(x_min="wall", x_max="outflow", y_min="wall", y_max="wall")
    ter = plane_terrain(plane, 10.0, None, walls)
    solver = Solver(ter, Law.COULOMB, np.array([math.tan(math.radians(20.0))]),
                    backend=backend, kernel="grid", order=order)
    state = solver.new_state(np.ones(ter.n_cells))
    solver.advance(state, 1e6, max_steps=1)  # compiles; the flow under way
    n0, t0 = state.steps, time.perf_counter()
    status = solver.advance(state, 1e6, max_steps=n0 + steps)
    wall = time.perf_counter() - t0
    done = state.steps - n0
    return {"part": "throughput", "case": f"plane {n}x{n}", "backend": backend,
            "order": order, "cells": ter.n_cells, "steps": done, "wall_s": wall,
            "cell_updates_per_s": done * ter.n_cells / wall, "status": status}


def avakot(dx: float, backend: str, updates: dict, order: int = 1) -> dict:
    """scenarios/avakot_coulomb.yaml at ``dx`` m on ``backend`` at ``order``, end to end."""
    from avflow.scenario.schema import load_scenario
    from avflow.simulation.runner import simulate

    scenario = load_scenario(AVAKOT).with_updates(
        {"grid.dx": dx, "numerics.backend": backend, "numerics.order": order, **updates})
    started = time.perf_counter()
    result = simulate(scenario)
    wall = time.perf_counter() - started
    s = result.summary
    row = {"part": "avakot", "case": f"avakot {dx:g} m", "backend": backend, "order": order,
           "cells": result.terrain.n_cells,
           "steps": s["steps"], "wall_s": wall,
           "cell_updates_per_s": s["cell_updates_per_second"], "status": s["status"]}
    row.update({k: s.get(k) for k in SUMMARY})
    return row


def ensemble(members: int, dx: float, sets: list[str], order: int = 1) -> dict:
    """``avflow ensemble --backend cuda --workers 0`` of avaKot members at ``order``, timed."""
    with tempfile.TemporaryDirectory() as tmp:
        spec = Path(tmp) / "avakot_gpu.yaml"
        deltas = ", ".join(f"{d:.4g}" for d in np.linspace(16.0, 26.0, members))
        spec.write_text(f"name: avakot-gpu\nbase: {AVAKOT}\nvary:\n"
                        f"  grid.dx: [{dx}]\n  rheology.delta_deg: [{deltas}]\n")
        command = [sys.executable, "-m", "avflow", "ensemble", str(spec), "-o",
                   str(Path(tmp) / "out"), "--backend", "cuda", "--workers", "0", "-q",
                   "--set", f"numerics.order={order}"]
        for s in sets:
            command += ["--set", s]
        started = time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True)
        wall = time.perf_counter() - started
        status = "ok" if done.returncode == 0 else f"exit {done.returncode}: " + (
            done.stderr.strip().splitlines() or [""])[-1]
    return {"part": "ensemble", "case": f"avakot {members} members {dx:g} m",
            "backend": "cuda", "order": order, "cells": "", "steps": "", "wall_s": wall,
            "cell_updates_per_s": "", "status": status}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default="benchmark_gpu.csv")
    parser.add_argument("--sizes", default="1024,4096,8192")
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--members", type=int, default=20)
    parser.add_argument("--orders", default="1,2", help="the scheme's orders of the "
                        "throughput and avaKot parts (the ensemble: the first)")
    parser.add_argument("--cpu-1m", action="store_true", help="run avaKot at 1 m on the "
                        "CPU too (minutes)")
    parser.add_argument("--tiny", action="store_true", help="toy sizes, for numba-cuda's "
                        "simulator (NUMBA_ENABLE_CUDASIM=1)")
    args = parser.parse_args(argv)
    orders = [int(o) for o in args.orders.split(",")]
    if not orders or any(o not in (1, 2) for o in orders):
        parser.error(f"--orders: 1, 2 or 1,2, got {args.orders!r}")
    if args.tiny:
        sizes, steps, members = [8, 16], 2, 2
        fine, coarse, ens_dx = 70.0, 100.0, 100.0
        short = {"time.end": 6.0, "output.every": 3.0}
        sets = ["time.end=6", "output.every=3"]
    else:
        sizes, steps, members = [int(s) for s in args.sizes.split(",")], args.steps, \
            args.members
        fine, coarse, ens_dx = 1.0, 5.0, 5.0
        short, sets = {}, []
    from avflow.numerics.cuda_grid import unavailable

    why = unavailable()
    if why is not None:
        print(f"benchmark_gpu: {why}", file=sys.stderr)
        return 2
    rows = []

    def keep(row):
        rows.append(row)
        print(", ".join(f"{k}={row.get(k)}" for k in COLUMNS[:9]), file=sys.stderr,
              flush=True)

    for order in orders:
        for n in sizes:
            try:
                keep(throughput(n, steps, "cuda", order))
            except Exception as err:  # too large for this GPU or host (CudaAPIError,
                # MemoryError)
                keep({"part": "throughput", "case": f"plane {n}x{n}", "backend": "cuda",
                      "order": order,
                      "status": f"{type(err).__name__}: {str(err).splitlines()[0][:200]}"})
        # the CPU kernel on the smallest, for scale
        keep(throughput(sizes[0], steps, "cpu", order))
    for order in orders:
        for dx, backends in ((coarse, ("cuda", "cpu")),
                             (fine, ("cuda", "cpu") if args.cpu_1m else ("cuda",))):
            for backend in backends:
                keep(avakot(dx, backend, short, order))
    keep(ensemble(members, ens_dx, sets, orders[0]))
    with open(args.output, "w", newline="") as f:
        writer = csv.DictWriter(f, COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {args.output}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
