"""Cell-updates per second of the kernels, threads, memory bandwidth and peak memory.

    python workflows/benchmark.py            # the table (a few minutes)
    python workflows/benchmark.py --quick    # smaller cases, for a look

Every case runs in a fresh process (its peak resident memory is its own), after a warm-up
call (compilation excluded), and reports cell-updates per second (cells x steps / time loop),
the 1D and all-wet cases the fastest of three windows (``WINDOWS``):

- 1D: the structured profile sweep and the generic face sweep on the same profile (a
  frictionless dam break on 200 000 cells, half dry, and the same with every cell wet);
- square grid, 400 x 400 and 1000 x 1000 cells on a plane (cylinder release on a 1 m layer,
  every cell wet; Coulomb): the square-grid kernel on 1, 2 and all threads, and the face kernel;
- triangles: the face kernel on the median dual mesh of the same plane (401 x 401 nodes),
  on 1, 2 and all threads (its step in gather form on threads);
- order 2 on the all-wet 1D, grid and triangle cases (on grids the square-grid kernel, and
  the face kernel for comparison, on 1 and 2 threads);
- the cylinder alone (most of the map dry): map cells per second, what the active region buys;
- the all-wet grid with entrainment (AvaFrame's erosion energy over a layer everywhere),
  with its Coulomb friction as a map (a row of parameters per cell), and with forest;
- the seed's section 6 (880 cells), wall time of its time loop;
- the yardstick: a plain Numba 2D kinetic kernel (``plain_kernel.py``: flat bed, no frames,
  no Dirac faces, no observers) on the same all-wet 400 x 400 plane. Issue 11 set the
  square-grid kernel's target at 4e7 where that kernel did 5e7: machines of this class differ
  by 2x (AVX-512 or AVX2), so the ratio of the two, measured in one run, is the target that
  travels (0.8).

The machine's memory bandwidth is measured in the same run (a 512 MB numpy copy, read +
write), and each kernel's rate is put against it: ``bandwidth / bytes per cell-update`` is
the rate a kernel would reach if it only moved its arrays. The bytes per cell-update are a
model, counted from the arrays a step reads and writes per cell (``BYTES_PER_CELL``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace as NS

import numpy as np

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
WALLS = NS(x_min="wall", x_max="wall", y_min="wall", y_max="wall")

#: Bytes a cell-update reads and writes (a write counted twice: the line is read first).
#: Square-grid kernel: h, hu, hv (24), per-cell factors inv_area, area, cfl, density,
#: gamma x/y/z, curvature (80), codes and validity (3), two faces' normals and lengths (80),
#: observers read (32); written h, hu, hv (24), flag (1), observers (about 16), each twice.
#: Profile sweep: h, hu, gamma_x, gamma_z, density, cfl, curvature row (64), observers (32);
#: written h, hu, hv, two flux values, flag, observers (about 58), twice. Face kernel at
#: order 1 (numerics.face_sweep, five passes): per face (2 per grid cell, 3 per triangle
#: node) its cells (int32, 8, read twice), frame (64), length (8), mass flux written (16);
#: per cell, read over the passes: h, hu, hv, the factors, the emitted lines, the sums and
#: the observers (about 430); written: the emitted lines, the sums (twice), the flags, the
#: new state, the observers and the lines of the step's sums (about 225, twice).
BYTES_PER_CELL = {"profile": 212, "grid": 299, "faces-grid": 2 * 104 + 880,
                  "faces-tri": 3 * 104 + 880}


#: An all-wet case is timed over at least this many seconds: it runs on past its end time,
#: by as much again each time, until then (the 400 x 400 grid's 21 steps took 0.08 s, and
#: its rate moved by 10% from run to run)
MIN_WALL = 0.5


#: Windows an all-wet case is timed over; the fastest is kept (on a shared machine whose
#: speed moved by a third from minute to minute, one window measured the neighbours)
WINDOWS = 3


def _rate(solver, h0, t_warm, t_end, min_wall=0.0, windows=1):
    """``(cell-updates/s, wall, steps)`` of the fastest of ``windows`` windows, each from
    the state at ``t_warm`` (compiled and under way) to ``t_end``, and on by as much again
    until it lasted ``min_wall``."""
    best = None
    for _ in range(windows):
        state = solver.new_state(h0)
        solver.advance(state, t_warm)  # compiles, and the flow is under way
        n0, t0 = state.steps, time.perf_counter()
        target = t_end
        solver.advance(state, target)
        while time.perf_counter() - t0 < min_wall:
            target += t_end - t_warm
            solver.advance(state, target)
        wall = time.perf_counter() - t0
        r = ((state.steps - n0) * h0.size / wall, wall, state.steps - n0)
        if best is None or r[0] > best[0]:
            best = r
    return best


def _plane(n):
    from avflow.terrain.bed import plane_terrain

    size = 10.0 * n
    return NS(slope_deg=30.0, azimuth_deg=90.0, extent=NS(x=[0.0, size], y=[0.0, size]),
              elevation_at_center=0.0), plane_terrain


def case(name, threads):
    """One case in this process: ``(cell-updates/s, wall, steps, kernel used, threads
    used)``."""
    from avflow.numerics.rheology import Law
    from avflow.numerics.solver import Solver

    coulomb20 = np.array([math.tan(math.radians(20)), 0, 0, 0])
    if name.startswith("1d"):
        import dataclasses

        from avflow.terrain.bed import profile_terrain

        n = 200_000
        ter = profile_terrain(NS(length=float(n), slope=NS(kind="constant", theta_deg=0.0),
                                 curvature=False), 1.0, WALLS)
        wet = name.endswith("wet") or "order2" in name
        h0 = np.where(ter.x < n / 2, 1.0, 0.5 if wet else 0.0)
        if "generic" in name:
            ter = dataclasses.replace(ter, mesh=dataclasses.replace(ter.mesh,
                                                                    structured_1d=False))
        solver = Solver(ter, Law.COULOMB, np.zeros(4), order=2 if "order2" in name else 1)
        return (*_rate(solver, h0, 0.5, 30.0, windows=WINDOWS),
                "profile" if "generic" not in name else "faces", 1)
    if name.startswith("grid") or name.startswith("tri"):
        n = 1000 if "1000" in name else 400
        plane, build = _plane(n)
        if name.startswith("tri"):
            from avflow.terrain.trimesh import plane_triangle_terrain

            ter = plane_triangle_terrain(plane, 10.0, None, WALLS)
        else:
            ter = build(plane, 10.0, None, WALLS)
        xx, yy = ter.cell_xy()
        centre = (0.25 * 10.0 * n, 0.5 * 10.0 * n)
        cyl = np.where((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 < 300**2, 20.0, 0.0)
        kernel = "faces" if "faces" in name or name.startswith("tri") else "auto"
        order = 2 if "order2" in name else 1
        params, source, forest = coulomb20, None, None
        if "entrain" in name:  # AvaFrame's erosion energy over a layer everywhere
            from avflow.numerics.physics import SOURCE_EROSION_ENERGY
            from avflow.numerics.sources import MassSource

            source = MassSource(SOURCE_EROSION_ENERGY, np.full(ter.n_cells, 5.0), (5000.0,),
                                density_ratio=0.5)
        if "map" in name:  # the same friction, as a map (a row per cell)
            params = np.tile(coulomb20, (ter.n_cells, 1))
        if "forest" in name:
            forest = np.full(ter.n_cells, 0.01)
        solver = Solver(ter, Law.COULOMB, params, kernel=kernel, order=order,
                        threads=threads, source=source, forest=forest,
                        time_scheme="heun" if "heun" in name else "auto")
        if "cylinder" in name:
            return (*_rate(solver, cyl, 0.5, 10.0), solver.kernel_used, solver.threads_used())
        t_end = 1.5 if n == 1000 else 3.0
        return (*_rate(solver, cyl + 1.0, 0.5, t_end, MIN_WALL, WINDOWS), solver.kernel_used,
                solver.threads_used())
    if name == "plain":
        import plain_kernel

        rate, wall, steps, _ = plain_kernel.rate(400, 0.5, 3.0, MIN_WALL, WINDOWS)
        return rate, wall, steps, "plain", 1
    if name == "section6":
        from avflow.scenario.schema import load_scenario
        from avflow.simulation.runner import simulate

        sc = load_scenario(SCENARIOS / "seed_exponential_coulomb15.yaml")
        simulate(sc)
        s = simulate(sc).summary
        return s["cell_updates_per_second"], s["wall_time"], s["steps"], "profile", 1
    raise ValueError(name)


CASES = [
    # (label, case name, threads, traffic model)
    ("1D profile sweep, 200k, half dry", "1d-dry", 1, "profile"),
    ("1D profile sweep, 200k, all wet", "1d-wet", 1, "profile"),
    ("1D face kernel (generic), all wet", "1d-generic-wet", 1, None),
    ("1D profile sweep, all wet, order 2", "1d-order2", 1, None),
    ("grid 400x400, plain kernel (the yardstick)", "plain", 1, None),
    ("grid 400x400, square-grid kernel, 1 thread", "grid", 1, "grid"),
    ("grid 400x400, square-grid kernel, 2 threads", "grid", 2, "grid"),
    ("grid 400x400, square-grid kernel, all threads", "grid", None, "grid"),
    ("grid 400x400, face kernel", "grid-faces", 1, "faces-grid"),
    ("grid 400x400, order 2, square-grid kernel", "grid-order2", 1, None),
    ("grid 400x400, order 2, square-grid kernel, 2 threads", "grid-order2", 2, None),
    ("grid 400x400, order 2 (Heun), square-grid kernel", "grid-order2-heun", 1, None),
    ("grid 400x400, order 2, face kernel", "grid-faces-order2", 1, None),
    ("grid 400x400, order 2 (Heun), face kernel", "grid-faces-order2-heun", 1, None),
    ("grid 400x400, order 2, face kernel, 2 threads", "grid-faces-order2", 2, None),
    ("grid 400x400, cylinder only (map cells/s)", "grid-cylinder", 1, None),
    ("grid 400x400, entrainment (erosion energy)", "grid-entrain", 1, None),
    ("grid 400x400, Coulomb as a friction map", "grid-map", 1, None),
    ("grid 400x400, friction map and forest", "grid-map-forest", 1, None),
    ("grid 1000x1000, square-grid kernel, 1 thread", "grid-1000", 1, "grid"),
    ("grid 1000x1000, square-grid kernel, 2 threads", "grid-1000", 2, "grid"),
    ("grid 1000x1000, square-grid kernel, all threads", "grid-1000", None, "grid"),
    ("triangles 401x401 nodes, face kernel", "tri", 1, "faces-tri"),
    ("triangles 401x401 nodes, face kernel, 2 threads", "tri", 2, "faces-tri"),
    ("triangles 401x401 nodes, face kernel, all threads", "tri", None, "faces-tri"),
    ("triangles, order 2", "tri-order2", 1, None),
    ("triangles, order 2 (Heun)", "tri-order2-heun", 1, None),
    ("triangles, order 2, 2 threads", "tri-order2", 2, None),
    ("triangles, cylinder only (map cells/s)", "tri-cylinder", 1, None),
    ("triangles, cylinder only (map cells/s), 2 threads", "tri-cylinder", 2, None),
    ("section 6, Coulomb 15, 880 cells (loop)", "section6", 1, None),
]
QUICK = {"1d-wet", "plain", "grid", "grid-faces", "tri", "section6"}


def bandwidth(n_bytes=512 * 2**20, repeats=5) -> float:
    """Bytes per second of a large numpy copy, read + write (best of ``repeats``)."""
    a = np.ones(n_bytes // 8)
    b = np.empty_like(a)
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        np.copyto(b, a)
        best = min(best, time.perf_counter() - t0)
    return 2 * a.nbytes / best


def _peak_resident() -> int:
    """This process's peak resident memory (bytes): VmHWM (ru_maxrss keeps the parent's
    peak across exec on Linux, the bandwidth test's 1 GiB)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _child(name, threads):
    rate, wall, steps, kernel, used = case(name, threads)
    peak = _peak_resident()
    print(json.dumps({"rate": rate, "wall": wall, "steps": steps, "kernel": kernel,
                      "threads": used, "peak": peak}))


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--only", help="the cases of these names (comma-separated), e.g. "
                   "grid,grid-entrain,grid-map")
    p.add_argument("--repeat", type=int, default=1,
                   help="run the cases this many times, interleaved (ratios in one run)")
    p.add_argument("--case", help=argparse.SUPPRESS)
    p.add_argument("--threads", type=int, default=0, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.case:
        return _child(args.case, args.threads or None)
    import numba

    bw = bandwidth()
    cores = numba.config.NUMBA_NUM_THREADS
    print(f"machine: {_cpu_name()}, {os.cpu_count()} cores (Numba: {cores} threads), memory "
          f"bandwidth {bw / 1e9:.1f} GB/s (numpy copy, read + write)")
    print(f"{'case':50s} {'kernel':>8s} {'thr':>3s} {'cell-upd/s':>11s} {'of bw':>6s} "
          f"{'wall (s)':>9s} {'steps':>6s} {'peak MB':>8s}")
    rates = {}
    only = set(args.only.split(",")) if args.only else None
    for label, name, threads, traffic in CASES * args.repeat:
        if (args.quick and name not in QUICK) or (only and name not in only):
            continue
        if threads is None and cores <= 2 and any(c[1] == name and c[2] == cores
                                                  for c in CASES):
            continue  # "all" is 2 here: measured once
        cmd = [sys.executable, __file__, "--case", name, "--threads", str(threads or 0)]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
        r = json.loads(out.strip().splitlines()[-1])
        rates[(name, r["threads"])] = max(r["rate"], rates.get((name, r["threads"]), 0.0))
        frac = f"{r['rate'] * BYTES_PER_CELL[traffic] / bw:6.2f}" if traffic else "     -"
        print(f"{label:50s} {r['kernel']:>8s} {r['threads']:3d} {r['rate']:11.3g} {frac} "
              f"{r['wall']:9.3f} {r['steps']:6d} {r['peak'] / 2**20:8.0f}", flush=True)
    for n in ("grid", "grid-1000", "tri", "tri-cylinder"):
        one = rates.get((n, 1))
        many = max((k[1] for k in rates if k[0] == n), default=1)
        if one and many > 1:
            speedup = rates[(n, many)] / one
            print(f"{n}: {many} threads {speedup:.2f}x one thread, parallel efficiency "
                  f"{speedup / many:.2f}")
    if ("grid", 1) in rates and ("plain", 1) in rates:
        print(f"square-grid kernel / plain kernel, one thread: "
              f"{rates[('grid', 1)] / rates[('plain', 1)]:.2f} (issue 11's target: 4e7 against "
              f"5e7, 0.8)")
    for n in ("grid-entrain", "grid-map", "grid-map-forest"):
        if ("grid", 1) in rates and (n, 1) in rates:
            print(f"{n} / grid, one thread (fastest of {args.repeat}): "
                  f"{rates[(n, 1)] / rates[('grid', 1)]:.2f}")
    if ("grid", 1) in rates and ("grid-faces", 1) in rates:
        print(f"square-grid kernel / face kernel on the grid, one thread: "
              f"{rates[('grid', 1)] / rates[('grid-faces', 1)]:.2f}")


if __name__ == "__main__":
    main()
