"""Ensemble throughput: 200 members of the seed's section 6 scene, serially and on dask.

    python workflows/benchmark_ensemble.py [--batch N] [--members N]

Runs scenarios/ensembles/seed_exponential_benchmark.yaml three times into fresh folders:
in this process (no dask), then on an embedded LocalCluster with 1 and with 2 single-threaded
worker processes. For each: members/s, and the overhead

    overhead = (wall x workers) / (sum of member compute times)

where wall runs from the first task submitted to the last result (cluster start-up and the
ensemble.nc/summary.csv writing are reported apart), and a member's compute time is the
time of the member function on its worker: read the scenario, run it, write its NetCDF.
The loop-only column uses the time loops alone (the solver's wall_time) as the denominator.
Target: overhead < 1.15 at 2 workers. Timings are only meaningful on an otherwise idle machine
(the load average is printed).
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

from avflow.ensemble.spec import load_ensemble
from avflow.ensemble.orchestrate import auto_batch, run_ensemble

ENSEMBLE = Path(__file__).resolve().parents[1] / "scenarios" / "ensembles" / \
    "seed_exponential_benchmark.yaml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, help="members per task (default: automatic)")
    parser.add_argument("--members", type=int, default=200, help="first N members only")
    args = parser.parse_args()
    ensemble = load_ensemble(ENSEMBLE)
    ensemble.members = ensemble.members[:args.members]
    n = len(ensemble.members)
    rows = []
    root = Path(tempfile.mkdtemp(prefix="avflow-bench-"))
    try:
        for workers in (0, 1, 2):
            out = root / f"w{workers}"
            started = time.perf_counter()
            outcome = run_ensemble(ensemble, out, workers=workers, batch=args.batch)
            total = time.perf_counter() - started
            assert outcome.ok and outcome.ran == n, outcome
            compute = float(outcome.table["member_time"].sum())
            loops = float(outcome.table["wall_time"].sum())
            k = max(workers, 1)
            rows.append((("serial" if workers == 0 else f"{workers} worker(s)"),
                         "-" if workers == 0 else str(args.batch or auto_batch(n, workers)),
                         n / outcome.wall, outcome.wall, compute, outcome.wall * k / compute,
                         outcome.wall * k / loops, outcome.startup,
                         total - outcome.wall - outcome.startup))
    finally:
        shutil.rmtree(root, ignore_errors=True)
    load = os.getloadavg()
    print(f"{n} members of the section 6 scene (dx = 6.25 m); cores: {os.cpu_count()}, "
          f"load average before the last run: {load[0]:.2f}")
    print(f"{'run':<12} {'batch':>5} {'members/s':>9} {'wall s':>7} {'compute s':>9} "
          f"{'overhead':>8} {'loop-only':>9} {'startup s':>9} {'tables s':>8}")
    for name, batch, rate, wall, compute, over, over_loop, startup, tables in rows:
        print(f"{name:<12} {batch:>5} {rate:9.2f} {wall:7.2f} {compute:9.2f} {over:8.3f} "
              f"{over_loop:9.3f} {startup:9.2f} {tables:8.2f}")


if __name__ == "__main__":
    main()
