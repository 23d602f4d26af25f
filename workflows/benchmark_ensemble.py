"""Ensemble throughput and where the time goes: the section 6 scene, serially and on dask.

    python workflows/benchmark_ensemble.py [--dx 1] [--members 48] [--workers 0,1,2]
                                           [--batch N] [--repeat 1] [--serial-members K]

Runs the first ``--members`` members of scenarios/ensembles/seed_exponential_benchmark.yaml
(a seeded Latin hypercube over the Coulomb angle and the release volume) at ``--dx`` m, once
per entry of ``--workers`` (0: in this process, no dask; N: an embedded LocalCluster of N
single-threaded worker processes), each into a fresh folder. ``--dx 1`` makes members of
about a second (0.6-1.1 s on a 2-core machine), ``--dx 3.125`` members of about 0.1 s.

For each run, one row:

- ``wall``: from the call of ``run_ensemble`` to its return, in a fresh Python process per
  run (as ``avflow ensemble`` starts: Numba's kernels in the cache, nothing loaded yet):
  cluster start, warming, the members, summary.csv and ensemble.nc all included (loading
  and checking the ensemble file is printed apart: the command line does it before);
- ``speed-up``: the serial row's wall over this one; ``eff``: speed-up / workers (with
  ``--serial-members K``, the serial row ran K members, the other N - K counted at the
  mean time of its members after the first);
- ``member``: mean time of one member task on its worker (read, run, write its NetCDF);
- the fixed costs, from ``Outcome.timings`` (``avflow.ensemble.orchestrate.TIMINGS``):
  ``here`` warming this process (imports, Numba kernels), ``cluster`` starting the local
  cluster until its first worker is up, ``workers`` warming every worker, ``first`` from the
  first task submitted to the first result, ``runs`` from the first task to the last result,
  ``idle`` = runs - (sum of member times) / workers (dispatch, results, the tail),
  ``write`` everything after the last result: the path analysis, summary.csv, ensemble.nc
  and waiting for the cluster to close. Stages that overlap (the cluster starting while
  this process warms or runs members) are each timed on their own clock.

Every run's row goes to stderr as it ends, with ``timings``: all of ``Outcome.timings`` (the
table keeps the fastest run of each worker count).

Timings mean something only on an otherwise idle machine: the load average is printed.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ENSEMBLE = Path(__file__).resolve().parents[1] / "scenarios" / "ensembles" / \
    "seed_exponential_benchmark.yaml"

COLUMNS = ("workers", "members", "member s", "wall s", "speed-up", "eff", "here s",
           "cluster s", "workers s", "first s", "runs s", "idle s", "write s")


def load(dx: float, members: int):
    from avflow.ensemble.spec import load_ensemble

    ensemble = load_ensemble(ENSEMBLE, overrides={"grid.dx": dx})
    ensemble.members = ensemble.members[:members]
    return ensemble


def measure_here(dx: float, members: int, workers: int, batch: int | None, out: Path) -> dict:
    """One run in this (fresh) process: the parent starts cold, as the command line does."""
    from avflow.ensemble.orchestrate import run_ensemble

    ensemble = load(dx, members)
    started = time.perf_counter()
    outcome = run_ensemble(ensemble, out, workers=workers, batch=batch)
    wall = time.perf_counter() - started
    n = len(ensemble.members)
    assert outcome.ok and outcome.ran == n, outcome
    t = getattr(outcome, "timings", None)
    if t is None:  # an avflow without Outcome.timings: what it does say
        t = {"cluster": outcome.startup, "runs": outcome.wall,
             "tables": wall - outcome.wall - outcome.startup}
    member = float(outcome.table["member_time"].sum())
    runs = t.get("runs", 0.0)
    k = max(workers, 1)
    later = outcome.table["member_time"].iloc[1:]  # the first member loads the kernels
    return {"workers": workers, "members": n, "member": member / n, "wall": wall,
            "member_later": float(later.mean()) if len(later) else member / n,
            "here": t.get("warm_here", t.get("probe", 0.0)), "cluster": t.get("cluster", 0.0),
            "warm": t.get("warm_workers", 0.0), "first": t.get("first_result", 0.0),
            "runs": runs, "idle": runs - member / k,
            "write": sum(t.get(k, 0.0) for k in ("path", "tables", "ensemble_nc", "close")),
            "timings": {k: round(v, 3) for k, v in t.items()}}


def measure(args, workers: int, out: Path) -> dict:
    """One run in a fresh Python process (cold imports, Numba kernels loaded from the
    cache, as ``avflow ensemble`` starts). The serial run on ``--serial-members`` K < N
    members stands for N: the N - K others at the mean time of its members after the first
    (which loads the kernels), its fixed costs as measured."""
    members = args.members
    if workers == 0 and args.serial_members and args.serial_members < members:
        members = args.serial_members
    command = [sys.executable, __file__, "--one", str(workers), "--out", str(out),
               "--dx", repr(args.dx), "--members", str(members)]
    if args.batch:
        command += ["--batch", str(args.batch)]
    done = subprocess.run(command, check=True, stdout=subprocess.PIPE, text=True)
    shutil.rmtree(out, ignore_errors=True)
    row = json.loads(done.stdout.strip().splitlines()[-1])
    if members < args.members:  # the other members take the mean time of the later ones
        more = row["member_later"] * (args.members - members)
        row["wall"] += more
        row["runs"] += more
        row["member"] = (row["member"] * members + more) / args.members
        row["members"] = f"{args.members} (from {members})"
    return row


def table(rows: list[dict]) -> str:
    serial = next((r["wall"] for r in rows if r["workers"] == 0), None)
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        speed = serial / r["wall"] if serial else float("nan")
        eff = speed / max(r["workers"], 1)
        lines.append(
            f"| {r['workers']} | {r['members']} | {r['member']:.3f} | {r['wall']:.2f} | "
            f"{speed:.2f} | {eff:.2f} | {r['here']:.2f} | {r['cluster']:.2f} | "
            f"{r['warm']:.2f} | {r['first']:.2f} | {r['runs']:.2f} | {r['idle']:.2f} | "
            f"{r['write']:.2f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dx", type=float, default=1.0, help="cell size, m (default 1)")
    parser.add_argument("--members", type=int, default=48, help="first N members (default 48)")
    parser.add_argument("--workers", default="0,1,2",
                        help="comma-separated worker counts, 0 = in this process (default 0,1,2)")
    parser.add_argument("--batch", type=int, help="members per task (default: automatic)")
    parser.add_argument("--repeat", type=int, default=1,
                        help="runs per worker count; the fastest is kept (default 1)")
    parser.add_argument("--serial-members", type=int, metavar="K",
                        help="run the serial baseline on the first K members only and scale "
                             "its member loop to all (a big machine's serial run is long)")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # a run in this process
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one is not None:
        print(json.dumps(measure_here(args.dx, args.members, args.one, args.batch, args.out)))
        return
    started = time.perf_counter()
    n = len(load(args.dx, args.members).members)
    loaded = time.perf_counter() - started
    from avflow.ensemble.orchestrate import warm, tiny_scenario_yaml

    first = load(args.dx, 1)  # Numba's cache filled before any timing (both variants)
    warm(tiny_scenario_yaml(first))
    if "one_thread" in tiny_scenario_yaml.__code__.co_varnames:
        warm(tiny_scenario_yaml(first, one_thread=True))
    rows = []
    root = Path(tempfile.mkdtemp(prefix="avflow-bench-"))
    try:
        for workers in (int(w) for w in args.workers.split(",")):
            runs = []
            for i in range(args.repeat):
                runs.append(measure(args, workers, root / f"w{workers}-{i}"))
                print(json.dumps(runs[-1]), file=sys.stderr, flush=True)  # kept if stopped
            rows.append(min(runs, key=lambda r: r["wall"]))
    finally:
        shutil.rmtree(root, ignore_errors=True)
    average = os.getloadavg()
    median = statistics.median(r["member"] for r in rows)
    print(f"{n} members of the section 6 scene at dx = {args.dx:g} m (median member "
          f"{median:.2f} s); loading and checking the ensemble file: {loaded:.2f} s; "
          f"cores: {os.cpu_count()}; load average after: {average[0]:.2f}")
    print(table(rows))


if __name__ == "__main__":
    main()
