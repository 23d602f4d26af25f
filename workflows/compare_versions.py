"""Two versions of avflow side by side, in one run: time-loop speed and first-run compile time.

    python workflows/compare_versions.py OLD_REV [NEW_REV] [--cases grid,grid-order2,...]
        [--repeat 3] [--compile]

Each version is checked out into a temporary git worktree (NEW_REV: the working tree as it
is), and every measurement runs in a fresh process with that version first on the Python
path, old and new interleaved, ``--repeat`` rounds: a busy machine moves both alike, and the
ratio new / old is what the table gives (best of the rounds for speed, each version's best and
worst for compile time).

- speed: ``workflows/benchmark.py --case NAME`` of the version itself (cell-updates/s of the
  time loop, compilation excluded);
- ``--compile``: ``avflow run`` of a scene with an empty kernel cache (``AVFLOW_CACHE_DIR`` a
  new folder), wall time of the whole command: what a first run on a fresh machine waits.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: benchmark.py cases: the grid at both orders on 1 thread, the face kernel, the profile
SPEED_CASES = ("grid", "grid-order2", "grid-faces", "tri", "1d-wet", "section6")
#: first-run scenes: (label, scenario, extra arguments of ``avflow run``)
COMPILE_SCENES = (
    ("seed profile, order 1", "scenarios/seed_exponential_coulomb15.yaml", []),
    ("avaKot 10 m, order 1 (grid)", "scenarios/avakot_coulomb.yaml",
     ["--set", "grid.dx=10", "--threads", "1"]),
    ("avaKot 10 m, order 2 (grid)", "scenarios/avakot_coulomb.yaml",
     ["--set", "grid.dx=10", "--set", "numerics.order=2", "--threads", "1"]),
)


def _tree(rev: str | None, base: Path) -> Path:
    if rev is None:
        return ROOT
    path = base / rev.replace("/", "_")
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(path),
                    rev], check=True)
    return path


def _env(tree: Path, cache: Path | None = None) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    if cache is not None:
        env["AVFLOW_CACHE_DIR"] = str(cache)
    return env


def _speed(tree: Path, case: str) -> float:
    done = subprocess.run([sys.executable, str(tree / "workflows" / "benchmark.py"), "--case",
                           case, "--threads", "1"], capture_output=True, text=True,
                          env=_env(tree), cwd=tree, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])["rate"]


def _first_run(tree: Path, scenario: str, extra: list, scratch: Path) -> float:
    cache = Path(tempfile.mkdtemp(dir=scratch))
    out = Path(tempfile.mkdtemp(dir=scratch)) / "run.nc"
    started = time.perf_counter()
    subprocess.run([sys.executable, "-m", "avflow", "run", str(tree / scenario), "-o", str(out),
                    *extra], capture_output=True, text=True, env=_env(tree, cache), cwd=tree,
                   check=True)
    seconds = time.perf_counter() - started
    shutil.rmtree(cache, ignore_errors=True)
    return seconds


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("old")
    p.add_argument("new", nargs="?", default=None)
    p.add_argument("--cases", default=",".join(SPEED_CASES))
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--compile", action="store_true", help="first runs with an empty cache")
    args = p.parse_args()
    base = Path(tempfile.mkdtemp(prefix="avflow-versions-"))
    trees = {"old": _tree(args.old, base), "new": _tree(args.new, base)}
    try:
        for name, tree in trees.items():  # warm: each version's kernels in its own cache
            print(f"{name}: {tree} ({args.old if name == 'old' else args.new or 'working tree'})",
                  flush=True)
        cases = [c for c in args.cases.split(",") if c]
        if cases:
            print(f"\n{'case (1 thread)':20s} {'old cell-upd/s':>15s} {'new cell-upd/s':>15s} "
                  f"{'new/old':>8s}")
        for case in cases:
            best = {"old": 0.0, "new": 0.0}
            for _ in range(args.repeat):
                for name, tree in trees.items():
                    best[name] = max(best[name], _speed(tree, case))
            print(f"{case:20s} {best['old']:15.4g} {best['new']:15.4g} "
                  f"{best['new'] / best['old']:8.3f}", flush=True)
        if args.compile:
            print(f"\n{'first run, empty kernel cache':32s} {'old (s)':>13s} {'new (s)':>13s}")
            for label, scenario, extra in COMPILE_SCENES:
                times = {"old": [], "new": []}
                for _ in range(args.repeat):
                    for name, tree in trees.items():
                        times[name].append(_first_run(tree, scenario, extra, base))
                show = {k: f"{min(v):.1f}-{max(v):.1f}" for k, v in times.items()}
                print(f"{label:32s} {show['old']:>13s} {show['new']:>13s}", flush=True)
    finally:
        for name, tree in trees.items():
            if tree != ROOT:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force",
                                str(tree)], check=False)
        shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
