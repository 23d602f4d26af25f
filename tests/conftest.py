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


def bump_on_a_slope(mesh_kind):
    """A 25 m bump on a 25 degree slope, 300 x 200 m: triangles refined where it curves (a
    tangent basis per node) with walls, or its DEM grid (10 m) with a NODATA hole and an
    open lower side (x_max). Order 2's tests of fronts, dry neighbours and the map's edge."""
    from avflow.terrain.bed import surface_terrain
    from avflow.terrain.trimesh import triangle_terrain

    x, y = np.arange(0.0, 301.0, 10.0), np.arange(0.0, 201.0, 10.0)
    xx, yy = np.meshgrid(x, y)
    z = -math.tan(math.radians(25.0)) * xx + 25.0 * np.exp(
        -((xx - 200.0) ** 2 + (yy - 100.0) ** 2) / 50.0**2)
    if mesh_kind == "triangles":
        return triangle_terrain(z, x, y, walls(), refine_angle_deg=4.0, refine_levels=1)
    z[8:11, 15:18] = np.nan
    return surface_terrain(z, x, y, walls(x_max="outflow"))


def assert_same_runs(runs):
    """Two runs ``[(state, snapshots of h), (state, snapshots)]`` are the same bit for bit:
    every snapshot, state variable, observer, statistic and flag (-0.0 and +0.0 differ,
    NaN equals NaN)."""
    def bits(a):
        return np.ascontiguousarray(a).view(np.int64)

    (a, sa), (b, sb) = runs
    for k, (x, y) in enumerate(zip(sa, sb)):
        np.testing.assert_array_equal(bits(x), bits(y), err_msg=f"h at output {k}")
    for name in ("h", "hu", "hv", "peak_h", "peak_speed", "arrival", "last_moved", "stats"):
        np.testing.assert_array_equal(bits(getattr(a, name)), bits(getattr(b, name)),
                                      err_msg=name)
    np.testing.assert_array_equal(a.flag, b.flag)


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
        pytest.skip(f"the external reference scenarios are not at {CONTRACT} (set "
                    "AVFLOW_SHARED): this test checks that they run unchanged")
    return CONTRACT
