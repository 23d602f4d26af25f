"""Cost follows the area the flow covers, not the map (issue 4 item 7, issue 11 item 4).

    python workflows/benchmark_area.py

The same cylinder release (r = 60 m, 8 m, Coulomb 24 degrees on a 28 degree plane, 40 s)
on a map just large enough for the flow and on one four times larger (twice the size in
x and in y, the release at the same place relative to the upslope corner). Both kernels
sweep only where the flow is (the face kernel wet cells and their neighbours, the
square-grid kernel the rows and columns they span), so the time loop should cost about the
same. Then the whole run as ``avflow run`` does it, with 41 snapshots streamed to a NetCDF
file: from the call to the renamed file, so terrain and solver set-up, the time loop, the
snapshots and the end of the file (the maps of the run, the static maps) all count.
Prints the wall times, their ratios (target < 1.3), and the largest difference of the final
thickness on the common part (the flow never reaches the small map's walls: checked). For
the whole run also where the time went: the loop; one snapshot (its fields refreshed where
the flow is or was, its centre of mass, the tiles of its record that hold the flow
compressed and written, flow_state whole); the end of the file (the maps of the run, the static maps);
and the rest, set-up (terrain, solver, the first use of the state) and summaries, which
grow with the map.

Every time is the best of 3 runs after one that compiles (before issue 11 item 4: one run
after the compiling one, the same quantities otherwise).

    python workflows/benchmark_area.py --widths

The square-grid kernel's time loop per step on ever wider maps (200 to 4000 columns of
5 m, 200 rows) around the same flow (a cylinder, r = 60 m, 8 m, Coulomb 24 degrees on a 28
degree plane, 20 s): what a step costs beyond the flow grows with the map's width, the one
dimension the kernel's per-row work lines span.
"""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace as NS

import numpy as np

from avflow.numerics.rheology import Law
from avflow.numerics.solver import Solver
from avflow.terrain.bed import plane_terrain

WALLS = NS(x_min="wall", x_max="wall", y_min="wall", y_max="wall")

#: timed runs of each case after the one that compiles: the best counts (a shared machine)
REPEATS = 3


def run(size_x, size_y, dx=5.0, t_end=40.0, kernel="auto"):
    plane = NS(slope_deg=28.0, azimuth_deg=90.0, extent=NS(x=[0.0, size_x], y=[0.0, size_y]),
               elevation_at_center=0.0)
    ter = plane_terrain(plane, dx, None, WALLS)
    xx, yy = ter.cell_xy()
    h0 = np.where((xx - 150.0) ** 2 + (yy - 300.0) ** 2 <= 60.0**2, 8.0, 0.0)
    solver = Solver(ter, Law.COULOMB, np.array([math.tan(math.radians(24.0)), 0, 0, 0]),
                    h_zero=1e-12 * 8.0, kernel=kernel, threads=1)
    warm = solver.new_state(h0)
    solver.advance(warm, 0.5)  # compile
    wall = math.inf
    for _ in range(REPEATS):
        state = solver.new_state(h0)
        t0 = time.perf_counter()
        solver.advance(state, t_end)
        wall = min(wall, time.perf_counter() - t0)
    return ter, state, wall


SCENARIO = """
name: area-{size_x:.0f}
terrain: {{kind: plane, slope_deg: 28.0, azimuth_deg: 90.0, elevation_at_center: 0.0,
          extent: {{x: [0.0, {size_x}], y: [0.0, {size_y}]}}}}
grid: {{dx: 5.0}}
release: {{kind: cylinder, center: [150.0, 300.0], radius: 60.0, thickness: 8.0}}
rheology: {{law: coulomb, delta_deg: 24.0}}
physics: {{min_flow_thickness: 0.0}}
numerics: {{kernel: {kernel}, threads: 1}}
time: {{end: 40.0}}
output: {{every: 1.0, stop_rule: kinetic_energy, stop_fraction: 0.0}}
"""


def run_written(size_x, size_y, kernel):
    """The run as `avflow run` makes it: 41 snapshots streamed to a file. Wall seconds from
    the call to the renamed file, best of REPEATS runs after one that compiles; with the
    seconds of that run's loop, snapshots (all of them) and end of the file."""
    from avflow.output.stream import SnapshotStream
    from avflow.scenario.schema import parse_scenario
    from avflow.simulation.runner import simulate

    class Timed(SnapshotStream):
        """Seconds in record() (the snapshots) and finish() (the end of the file)."""

        recording = finishing = 0.0

        def record(self, *args):
            t0 = time.perf_counter()
            super().record(*args)
            self.recording += time.perf_counter() - t0

        def finish(self, result):
            t0 = time.perf_counter()
            rest = super().finish(result)
            self.finishing += time.perf_counter() - t0
            return rest

    scenario = parse_scenario(SCENARIO.format(size_x=size_x, size_y=size_y, kernel=kernel))
    best = None
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(REPEATS + 1):
            out = Path(tmp) / "run.nc"
            t0 = time.perf_counter()
            with Timed(out) as stream:
                result = simulate(scenario, snapshots=stream)
                stream.finish(result)
            wall = time.perf_counter() - t0
            if k and (best is None or wall < best.wall):
                best = NS(wall=wall, loop=result.summary["wall_time"],
                          snaps=len(result.snapshots.time), size=out.stat().st_size,
                          recording=stream.recording, finishing=stream.finishing)
    best.setup = best.wall - best.loop - best.recording - best.finishing
    return best


def main():
    print(f"{'kernel':7s} {'map':26s} {'cells':>8s} {'steps':>6s} {'loop (s)':>9s}")
    for kernel in ("grid", "faces"):
        small, s_state, s_wall = run(1600.0, 700.0, kernel=kernel)
        large, l_state, l_wall = run(3200.0, 1400.0, kernel=kernel)
        hs = small.to_grid(s_state.h)
        hl = large.to_grid(l_state.h)[: hs.shape[0], : hs.shape[1]]
        edge = max(hs[0].max(), hs[-1].max(), hs[:, 0].max(), hs[:, -1].max())
        wet = int(np.count_nonzero(s_state.h > 1e-12 * 8.0))
        print(f"{kernel:7s} {'flow-sized, 1600 x 700 m':26s} {small.n_cells:8d} "
              f"{s_state.steps:6d} {s_wall:9.3f}")
        print(f"{kernel:7s} {'4x larger, 3200 x 1400 m':26s} {large.n_cells:8d} "
              f"{l_state.steps:6d} {l_wall:9.3f}")
        print(f"        time loop, ratio large / small: {l_wall / s_wall:.2f} (target < 1.3); "
              f"cells wet at the end: {wet} of {small.n_cells}; max |h_large - h_small| on "
              f"the common part: {np.abs(hl - hs).max():.3g} m; thickness on the small map's "
              f"edge: {edge:.3g} m")
    print()
    print(f"{'kernel':7s} {'map':26s} {'snapshots':>9s} {'file (MB)':>9s} {'loop (s)':>9s} "
          f"{'run (s)':>8s}   {'set-up (s)':>10s} {'1 snapshot (ms)':>15s} {'end (s)':>8s}")
    for kernel in ("grid", "faces"):
        walls = []
        for label, (sx, sy) in (("flow-sized, 1600 x 700 m", (1600.0, 700.0)),
                                ("4x larger, 3200 x 1400 m", (3200.0, 1400.0))):
            r = run_written(sx, sy, kernel)
            walls.append(r.wall)
            print(f"{kernel:7s} {label:26s} {r.snaps:9d} {r.size / 1e6:9.1f} {r.loop:9.3f} "
                  f"{r.wall:8.3f}   {r.setup:10.3f} {1e3 * r.recording / r.snaps:15.2f} "
                  f"{r.finishing:8.3f}")
        print(f"        whole run with snapshots, ratio large / small: {walls[1] / walls[0]:.2f} "
              "(target < 1.3)")


def widths(columns=(200, 1000, 2000, 4000)):
    """The time loop per step of the same flow on maps ``columns`` cells wide (one thread,
    best of 2 after one that compiles), and its ratio to the narrowest map's."""
    print(f"{'columns':>7s} {'steps':>6s} {'loop (ms)':>9s} {'per step (us)':>13s} "
          f"{'ratio':>6s}")
    first = None
    for nx in columns:
        plane = NS(slope_deg=28.0, azimuth_deg=90.0, extent=NS(x=[0.0, 5.0 * nx], y=[0.0, 1000.0]),
                   elevation_at_center=0.0)
        terrain = plane_terrain(plane, 5.0, None, WALLS)
        xx, yy = terrain.cell_xy()
        h0 = np.where((xx - 300.0) ** 2 + (yy - 500.0) ** 2 < 60.0**2, 8.0, 0.0)
        solver = Solver(terrain, Law.COULOMB, np.array([math.tan(math.radians(24.0))]),
                        threads=1)
        best = math.inf
        for rep in range(3):
            state = solver.new_state(h0)
            t0 = time.perf_counter()
            solver.advance(state, 20.0)
            if rep:
                best = min(best, time.perf_counter() - t0)
        per_step = best / state.steps
        first = first or per_step
        print(f"{nx:7d} {state.steps:6d} {1e3 * best:9.0f} {1e6 * per_step:13.0f} "
              f"{per_step / first:6.2f}", flush=True)


if __name__ == "__main__":
    import sys

    if "--widths" in sys.argv[1:]:
        widths()
    else:
        main()
