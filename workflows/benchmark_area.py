"""Cost follows the area the flow covers, not the map (issue 4 item 7).

    python workflows/benchmark_area.py

The same cylinder release (r = 60 m, 8 m, Coulomb 24 degrees on a 28 degree plane, 40 s)
on a map just large enough for the flow and on one four times larger (twice the size in
x and in y, the release at the same place relative to the upslope corner). The face kernel
sweeps only wet cells and their neighbours, so the time loop should cost about the same.
Prints both wall times, their ratio (target < 1.3), and the largest difference of the final
thickness on the common part (the flow never reaches the small map's walls: checked).
"""

from __future__ import annotations

import math
import time
from types import SimpleNamespace as NS

import numpy as np

from avflow.numerics.rheology import Law
from avflow.numerics.solver import Solver
from avflow.terrain.bed import plane_terrain

WALLS = NS(x_min="wall", x_max="wall", y_min="wall", y_max="wall")


def run(size_x, size_y, dx=5.0, t_end=40.0):
    plane = NS(slope_deg=28.0, azimuth_deg=90.0, extent=NS(x=[0.0, size_x], y=[0.0, size_y]),
               elevation_at_center=0.0)
    ter = plane_terrain(plane, dx, None, WALLS)
    xx, yy = ter.cell_xy()
    h0 = np.where((xx - 150.0) ** 2 + (yy - 300.0) ** 2 <= 60.0**2, 8.0, 0.0)
    solver = Solver(ter, Law.COULOMB, np.array([math.tan(math.radians(24.0)), 0, 0, 0]),
                    h_zero=1e-12 * 8.0)
    warm = solver.new_state(h0)
    solver.advance(warm, 0.5)  # compile
    state = solver.new_state(h0)
    t0 = time.perf_counter()
    solver.advance(state, t_end)
    wall = time.perf_counter() - t0
    return ter, state, wall


def main():
    small, s_state, s_wall = run(1600.0, 700.0)
    large, l_state, l_wall = run(3200.0, 1400.0)
    hs = small.to_grid(s_state.h)
    hl = large.to_grid(l_state.h)[: hs.shape[0], : hs.shape[1]]
    edge = max(hs[0].max(), hs[-1].max(), hs[:, 0].max(), hs[:, -1].max())
    wet = int(np.count_nonzero(s_state.h > 1e-12 * 8.0))
    print(f"{'map':28s} {'cells':>8s} {'steps':>6s} {'wall (s)':>9s}")
    print(f"{'flow-sized, 1600 x 700 m':28s} {small.n_cells:8d} {s_state.steps:6d} {s_wall:9.3f}")
    print(f"{'4x larger, 3200 x 1400 m':28s} {large.n_cells:8d} {l_state.steps:6d} {l_wall:9.3f}")
    print(f"ratio large / small: {l_wall / s_wall:.2f} (target < 1.3); cells wet at the end: "
          f"{wet} of {small.n_cells}")
    print(f"max |h_large - h_small| on the common part: {np.abs(hl - hs).max():.3g} m; "
          f"thickness on the small map's edge: {edge:.3g} m")


if __name__ == "__main__":
    main()
