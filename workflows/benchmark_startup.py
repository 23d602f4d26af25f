"""The whole ``avflow run`` command against its own time loop: start-up, terrain, files, exit.

    python workflows/benchmark_startup.py [--before OTHER_CHECKOUT] [--rounds 3] [--dx 5]

Runs ``python -m avflow run scenarios/avakot_coulomb.yaml --set grid.dx=DX`` as a user
does, a new process each time, with the kernel cache warm (one run of each code first, not
counted), and reads the time loop and the compiling (or cache loading) from the summary
line. The rest is everything else the command does: imports, reading the DEM and the
release, the mesh, the solver's set-up, the NetCDF written as the run goes and finished,
the summary, the exit. With ``--before``, the same command with that checkout's code (its
folder first on ``PYTHONPATH``) runs in turn with this one, round by round, so both see
the same load of a shared machine; the two files must hold the same variables, values and
attributes but the timings. Prints the medians of the rounds and their ratios.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENARIO = REPO / "scenarios" / "avakot_coulomb.yaml"
SUMMARY = re.compile(r" in ([0-9.]+) s \(\+ ([0-9.]+) s compiling\)")
#: summaries that are the run's own timings, not its result
TIMINGS = ("wall_time", "compile_time", "cell_updates_per_second")


def run_once(code: Path, out: Path, dx: float) -> dict:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(code), *filter(None, [os.environ.get("PYTHONPATH")])])}
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "avflow", "run", str(SCENARIO), "--set",
                           f"grid.dx={dx:g}", "-o", str(out)], capture_output=True,
                          text=True, env=env, cwd=out.parent)
    wall = time.perf_counter() - started
    if done.returncode != 0:
        sys.exit(f"{code}: avflow run failed:\n{done.stderr}")
    found = SUMMARY.search(done.stdout)
    loop, compiling = float(found.group(1)), float(found.group(2))
    return {"whole": wall, "loop": loop, "compiling": compiling,
            "rest": wall - loop - compiling, "load": os.getloadavg()[0]}


def same_attrs(a: dict, b: dict) -> bool:
    """Attributes equal, arrays among them compared as their text."""
    return a.keys() == b.keys() and all(str(a[k]) == str(b[k]) for k in a)


def same_file(a: Path, b: Path) -> None:
    import numpy as np
    import xarray as xr

    with xr.open_dataset(a, decode_times=False) as x, xr.open_dataset(b, decode_times=False) as y:
        assert list(x.variables) == list(y.variables), "not the same variables"
        assert same_attrs(x.attrs, y.attrs), "not the same global attributes"
        for name in x.variables:
            u, v = x[name].variable, y[name].variable
            assert u.dims == v.dims and u.dtype == v.dtype and same_attrs(u.attrs, v.attrs), name
            if name not in TIMINGS:
                assert np.array_equal(u.values, v.values, equal_nan=u.dtype.kind == "f"), name


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, help="another checkout to compare with")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--dx", type=float, default=5.0)
    args = parser.parse_args()
    codes = {"this": REPO} if args.before is None else {"before": args.before.resolve(),
                                                        "this": REPO}
    with tempfile.TemporaryDirectory() as tmp:
        outs = {name: Path(tmp) / name / "run.nc" for name in codes}
        for name, code in codes.items():
            outs[name].parent.mkdir()
            run_once(code, outs[name], args.dx)  # the kernel cache warm, not counted
        rows = {name: [] for name in codes}
        for _ in range(args.rounds):
            for name, code in codes.items():
                rows[name].append(run_once(code, outs[name], args.dx))
        if args.before is not None:
            same_file(outs["before"], outs["this"])
    keys = ("whole", "loop", "compiling", "rest")
    med = {name: {k: statistics.median(r[k] for r in rs) for k in (*keys, "load")}
           for name, rs in rows.items()}
    print(f"avflow run {SCENARIO.name} --set grid.dx={args.dx:g}: medians of {args.rounds} "
          f"runs (s), load average {min(r['load'] for rs in rows.values() for r in rs):.2f}"
          f" to {max(r['load'] for rs in rows.values() for r in rs):.2f}")
    print(f"| code | {' | '.join(keys)} |")
    print("|---|" + "---:|" * len(keys))
    for name in codes:
        print(f"| {name} | " + " | ".join(f"{med[name][k]:.2f}" for k in keys) + " |")
    if args.before is not None:
        print("| this / before | " + " | ".join(
            f"{med['this'][k] / med['before'][k]:.2f}" for k in keys) + " |")
        print("the two files: the same variables, values and attributes but the timings")


if __name__ == "__main__":
    main()
