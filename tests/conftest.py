"""Shared helpers: small scenes built directly on the solver API, the project's paths and
the optional ../shared/contract folder (contract tests skip without it)."""

import math
import os
from pathlib import Path
from types import SimpleNamespace as NS

import numpy as np
import pytest

from avflow.numerics.rheology import Law
from avflow.numerics.solver import Solver
from avflow.terrain.bed import profile_terrain

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = REPO / "scenarios"
SHARED = Path(os.environ.get("AVFLOW_SHARED", REPO.parent / "shared"))
CONTRACT = SHARED / "contract"


def walls(x_min="wall", x_max="wall", y_min="wall", y_max="wall"):
    return NS(x_min=x_min, x_max=x_max, y_min=y_min, y_max=y_max)


def slope_profile(length, dx, theta_deg, curvature=False, **bounds):
    """A constant-slope profile terrain."""
    block = NS(length=length, slope=NS(kind="constant", theta_deg=theta_deg),
               curvature=curvature)
    return profile_terrain(block, dx, walls(**bounds))


def coulomb(terrain, delta_deg, **kw):
    params = np.array([math.tan(math.radians(delta_deg)), 0.0, 0.0, 0.0])
    return Solver(terrain, Law.COULOMB, params, **kw)


def cylinder(terrain, centre, radius=80.0, thickness=10.0):
    """Thickness of a cylinder release (horizontal radius) at the cell centres of a 2D mesh."""
    xx, yy = terrain.cell_xy()
    return np.where((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 <= radius**2, thickness, 0.0)


def faces_permuted(terrain, perm):
    """The terrain with its mesh's faces taken in the order ``perm`` (indices of the faces):
    the same cells and faces, numbered otherwise."""
    import dataclasses

    m = terrain.mesh
    mesh = dataclasses.replace(m, face_cells=m.face_cells[perm], face_normal=m.face_normal[perm],
                               face_length=m.face_length[perm], face_frame=m.face_frame[perm],
                               face_direction=m.face_direction[perm])
    return dataclasses.replace(terrain, mesh=mesh)


def centroid(terrain, h):
    """Horizontal centre of mass (x, y) of the thickness h."""
    xx, yy = terrain.cell_xy()
    w = h * terrain.mesh.cell_area
    return np.array([np.sum(w * xx), np.sum(w * yy)]) / np.sum(w)


@pytest.fixture(scope="session")
def contract_dir():
    """../shared/contract (or $AVFLOW_SHARED/contract): only for the tests whose point is that
    the shared contract files run unchanged; they skip where it is absent (a fresh clone)."""
    if not CONTRACT.is_dir():
        pytest.skip(f"contract files not found at {CONTRACT} (set AVFLOW_SHARED): this test "
                    "checks that the shared contract files run unchanged")
    return CONTRACT
