"""The benchmark's yardstick (workflows/plain_kernel.py) does the same work as avflow.

Its rate is only a yardstick if it solves the same problem: on the benchmark's all-wet plane
(a cylinder on a 1 m layer, 30 degrees, Coulomb 20 degrees), it keeps the mass to round-off,
takes about as many steps as avflow's square-grid kernel and moves the mass as far.
"""

import importlib.util
import math
import sys
from types import SimpleNamespace as NS

import numpy as np

from avflow.numerics.rheology import Law
from avflow.numerics.solver import Solver
from avflow.terrain.bed import plane_terrain
from conftest import REPO, walls

spec = importlib.util.spec_from_file_location("plain_kernel",
                                              REPO / "workflows" / "plain_kernel.py")
plain = importlib.util.module_from_spec(spec)
sys.modules["plain_kernel"] = plain
spec.loader.exec_module(plain)


def centre_x(h, dx=10.0):
    x = (np.arange(h.shape[1]) + 0.5) * dx
    return float((h * x).sum() / h.sum())


def test_plain_kernel_solves_the_benchmarks_plane_as_avflow_does():
    n = 120
    h = plain.cylinder_on_layer(n)
    h0 = h.copy()
    hu, hv = np.zeros_like(h), np.zeros_like(h)
    tan20 = math.tan(math.radians(20.0))
    steps = plain.advance(h, hu, hv, 10.0, 30.0, tan20, 9.81, 0.5, 3.0)
    assert h.min() >= 0.0
    assert abs(h.sum() - h0.sum()) <= 1e-12 * h0.sum()  # walls all round: nothing leaves
    plane = NS(slope_deg=30.0, azimuth_deg=90.0, extent=NS(x=[0.0, 10.0 * n], y=[0.0, 10.0 * n]),
               elevation_at_center=0.0)
    ter = plane_terrain(plane, 10.0, None, walls())
    solver = Solver(ter, Law.COULOMB, np.array([tan20]), h_zero=0.0, h_dry=0.0)
    state = solver.new_state(h0.ravel())
    solver.advance(state, 3.0)
    ours = state.h.reshape(h.shape)
    assert abs(steps - state.steps) <= 0.15 * state.steps
    moved, moved_ours = centre_x(h) - centre_x(h0), centre_x(ours) - centre_x(h0)
    assert moved > 1.0  # the mass slid
    assert abs(moved - moved_ours) <= 0.005 * moved_ours  # (0.1% here)
    # the same field but at the cylinder's rim, where a 20 m step meets the layer
    assert np.abs(h - ours).mean() < 1e-3 * h.mean()
