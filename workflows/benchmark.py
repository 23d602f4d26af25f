"""Cell-updates per second of the kernels, single core, and the section 6 wall time.

    python workflows/benchmark.py

- 1D: the structured profile sweep and the generic face sweep on the same profile (a
  frictionless dam break on 200 000 cells, half dry, and the same with every cell wet), so
  their ratio is measured in one run;
- 2D: the face sweep on a 400 x 400 grid over a plane (cylinder release, Coulomb), and on
  the triangle mesh of the same plane (401 x 401 vertices, median dual cells, avflow.terrain.trimesh);
- the seed's section 6 run (880 cells) from its scenario, wall time of the time loop;
- order 2 (numerics.order: 2, reconstruction + Heun) on the all-wet 1D, grid and triangle
  cases, beside order 1 in the same run: what a step of order 2 costs.
Compilation is excluded (a warm-up call first).
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from types import SimpleNamespace as NS

import numpy as np

from avflow.numerics.rheology import Law
from avflow.simulation.runner import simulate
from avflow.scenario.schema import load_scenario
from avflow.numerics.solver import Solver
from avflow.terrain.bed import plane_terrain, profile_terrain
from avflow.terrain.trimesh import plane_triangle_terrain

WALLS = NS(x_min="wall", x_max="wall", y_min="wall", y_max="wall")
SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


def rate(solver, h0, t_warm, t_end):
    state = solver.new_state(h0)
    solver.advance(state, t_warm)
    n0, t0 = state.steps, time.perf_counter()
    solver.advance(state, t_end)
    wall = time.perf_counter() - t0
    return (state.steps - n0) * h0.size / wall, wall, state.steps - n0


def main():
    rows = []
    n = 200_000
    ter = profile_terrain(NS(length=float(n), slope=NS(kind="constant", theta_deg=0.0),
                             curvature=False), 1.0, WALLS)
    params = np.zeros(4)
    generic_ter = dataclasses.replace(ter, mesh=dataclasses.replace(ter.mesh, structured_1d=False))
    for label, h0 in (("dam break, half dry", np.where(ter.x < n / 2, 1.0, 0.0)),
                      ("all wet", np.where(ter.x < n / 2, 1.0, 0.5))):
        fast = rate(Solver(ter, Law.COULOMB, params), h0, 0.5, 30.0)
        slow = rate(Solver(generic_ter, Law.COULOMB, params), h0, 0.5, 30.0)
        rows.append((f"1D profile sweep, 200k, {label}", *fast))
        rows.append((f"1D generic face sweep, {label}", *slow))
    second_1d = rate(Solver(ter, Law.COULOMB, params, order=2), h0, 0.5, 30.0)
    rows.append(("1D profile sweep, all wet, order 2", *second_1d))
    plane = NS(slope_deg=30.0, azimuth_deg=90.0, extent=NS(x=[0.0, 4000.0], y=[0.0, 4000.0]),
               elevation_at_center=0.0)
    ter2 = plane_terrain(plane, 10.0, None, WALLS)
    xx, yy = np.meshgrid(ter2.x, ter2.y)
    h2 = np.where((xx - 1000) ** 2 + (yy - 2000) ** 2 < 300**2, 20.0, 0.0).ravel()
    coulomb20 = np.array([math.tan(math.radians(20)), 0, 0, 0])
    first_2d = rate(Solver(ter2, Law.COULOMB, coulomb20), h2 + 1.0, 0.5, 3.0)
    rows.append(("2D grid, 400x400, all wet (1 m + cylinder)", *first_2d))
    second_2d = rate(Solver(ter2, Law.COULOMB, coulomb20, order=2), h2 + 1.0, 0.5, 3.0)
    rows.append(("2D grid, 400x400, all wet, order 2", *second_2d))
    rows.append(("2D grid, 400x400, cylinder (map cells/s)",
                 *rate(Solver(ter2, Law.COULOMB, coulomb20), h2, 0.5, 10.0)))
    ter3 = plane_triangle_terrain(plane, 10.0, None, WALLS)
    x3, y3 = ter3.cell_xy()
    h3 = np.where((x3 - 1000) ** 2 + (y3 - 2000) ** 2 < 300**2, 20.0, 0.0)
    first_tri = rate(Solver(ter3, Law.COULOMB, coulomb20), h3 + 1.0, 0.5, 3.0)
    rows.append(("2D triangles, 401x401 nodes, all wet", *first_tri))
    second_tri = rate(Solver(ter3, Law.COULOMB, coulomb20, order=2), h3 + 1.0, 0.5, 3.0)
    rows.append(("2D triangles, all wet, order 2", *second_tri))
    rows.append(("2D triangles, cylinder (map cells/s)",
                 *rate(Solver(ter3, Law.COULOMB, coulomb20), h3, 0.5, 10.0)))
    print(f"{'kernel':44s} {'cell-upd/s':>11s} {'wall (s)':>9s} {'steps':>6s}")
    for name, r, wall, steps in rows:
        print(f"{name:44s} {r:11.3g} {wall:9.3f} {steps:6d}")
    print(f"structured / generic 1D speed ratio (all wet): {fast[0] / slow[0]:.2f}")
    print("order 1 / order 2 cell-updates per second (all wet): "
          f"1D {fast[0] / second_1d[0]:.2f}, grid {first_2d[0] / second_2d[0]:.2f}, "
          f"triangles {first_tri[0] / second_tri[0]:.2f}")
    sc = load_scenario(SCENARIOS / "seed_exponential_coulomb15.yaml")
    simulate(sc)
    s = simulate(sc).summary
    print(f"section 6 (Coulomb 15, 880 cells, {s['steps']} steps): time loop {s['wall_time']:.3f} s"
          f", {s['cell_updates_per_second']:.3g} cell-upd/s (with output every 5 s)")


if __name__ == "__main__":
    main()
