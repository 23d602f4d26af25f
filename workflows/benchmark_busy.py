"""Threads on a busy machine: the time loop on 1 thread and on the default, with and without
one CPU-bound process beside it, for each threading layer and wait policy (issue 27).

    python workflows/benchmark_busy.py              # the table (a few minutes)
    python workflows/benchmark_busy.py --repeats 5

Cases: a 400 x 400 all-wet grid (Coulomb, 30 degree plane, the square-grid kernel) and the
README walk-through's step 1 (``avakot_coulomb.yaml`` at 10 m, order 1 on the square-grid
kernel and order 2 on the face kernel), 1 s to 40 s of its flow. Every cell is a fresh
process (a layer and a wait policy are fixed when Numba starts its threads); the number is
the fastest of ``--repeats`` time loops, kernels compiled before. Ratios are to the 1-thread
time measured in the same process.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

CONFIGS = {  # label: environment of the child
    "omp (default)": {},
    "omp, passive wait": {"OMP_WAIT_POLICY": "PASSIVE"},
    "workqueue": {"NUMBA_THREADING_LAYER": "workqueue"},
}


def child(case: str, repeats: int) -> dict:
    import math

    import numpy as np

    from avflow.numerics.rheology import Law
    from avflow.numerics.solver import Solver

    out = {}
    if case == "grid400":
        from types import SimpleNamespace as NS

        from avflow.terrain.bed import plane_terrain

        walls = NS(x_min="wall", x_max="wall", y_min="wall", y_max="wall")
        plane = NS(slope_deg=30.0, azimuth_deg=90.0, extent=NS(x=[0.0, 4000.0], y=[0.0, 4000.0]),
                   elevation_at_center=0.0)
        ter = plane_terrain(plane, 10.0, None, walls)
        xx, yy = ter.cell_xy()
        h0 = np.where((xx - 1000) ** 2 + (yy - 2000) ** 2 < 300**2, 20.0, 0.0) + 1.0
        law, params, t0, t1 = Law.COULOMB, np.array([math.tan(math.radians(20))]), 0.3, 3.0
        solvers = {k: Solver(ter, law, params, threads=k) for k in (1, None)}
    else:
        from avflow.scenario.schema import load_scenario
        from avflow.simulation.runner import prepare

        sc = load_scenario(REPO / "scenarios" / "avakot_coulomb.yaml").with_updates(
            {"grid.dx": 10, "numerics.order": 2 if case.endswith("order2") else 1})
        solvers = {}
        for k in (1, None):
            ter, h0, solvers[k], _ = prepare(sc.with_updates({"numerics.threads": k}))
        t0, t1 = 1.0, 40.0
    for _ in range(repeats):
        for k, s in solvers.items():
            st = s.new_state(h0)
            s.advance(st, t0)
            started = time.perf_counter()
            s.advance(st, t1)
            wall = time.perf_counter() - started
            key = "1" if k == 1 else "default"
            out[key] = min(out.get(key, math.inf), wall)
            out[key + "_threads"] = s.threads_used()
    import numba

    out["layer"] = numba.threading_layer()
    return out


def run(case, env, repeats, busy):
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if busy else None
    try:
        res = subprocess.run([sys.executable, __file__, "--child", case, "--repeats",
                              str(repeats)], env={**os.environ, **env}, capture_output=True,
                             text=True, timeout=1200)
    finally:
        if hog is not None:
            hog.kill()
    if res.returncode != 0:
        raise SystemExit(res.stderr)
    return json.loads(res.stdout.strip().splitlines()[-1])


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--case", action="append", choices=("grid400", "walkthrough", "walkthrough-order2"))
    p.add_argument("--config", action="append", choices=list(CONFIGS))
    p.add_argument("--child", help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.child:
        print(json.dumps(child(a.child, a.repeats)))
        return
    print(f"{time.strftime('%Y-%m-%d %H:%M')}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}")
    print(f"| case | layer, wait | busy | 1 thread (s) | default (s) | threads | default / 1 |")
    print("|---|---|---|---|---|---|---|")
    for case in a.case or ("grid400", "walkthrough", "walkthrough-order2"):
        for label in a.config or list(CONFIGS):
            for busy in (False, True):
                r = run(case, CONFIGS[label], a.repeats, busy)
                print(f"| {case} | {label} ({r['layer']}) | {'yes' if busy else 'no'} | "
                      f"{r['1']:.3f} | {r['default']:.3f} | {r['default_threads']} | "
                      f"{r['default'] / r['1']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
