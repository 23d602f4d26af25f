"""Bed geometry in the frame linked to the topography (seed section 2, Fig. 1).

In each cell the bed defines a tangent basis (x along the bed, z normal to it, y = z ^ x) in
which the state lives. The gravity vector projects onto it as ``g (gamma_x, gamma_y, -gamma_z)``
(eqs. 7-8, 10): ``gamma_z = cos(theta)`` gives the bed-normal weight that sets the pressure and
the Coulomb threshold (eqs. 12, 19-20), ``(gamma_x, gamma_y)`` drive the flow. A profile also
carries the curvature ``1/R = -d theta / ds`` of eqs. 61-62 (positive where the slope flattens
downhill, which presses the mass onto the bed and adds friction).

Builders return a :class:`Terrain`: the finite-volume :class:`~avflow.mesh.Mesh` plus those
per-cell coefficients and the coordinates that outputs need. Everything is computed once.

- :func:`profile_terrain`: a transversally uniform slope solved in 1D along the bed (x is the
  curvilinear abscissa s), slope angle constant, exponential (eq. 58) or tabulated.
- :func:`plane_terrain`: an inclined plane of any slope and azimuth over a horizontal grid;
  the plane has one tangent basis, so cells are the grid cells lifted onto the bed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .mesh import BOUNDARY_CODES, Mesh, grid_mesh, profile_mesh


@dataclass(frozen=True)
class Terrain:
    """A mesh and its bed coefficients, one value per cell (1D arrays over the cells)."""

    kind: str  #: "profile" or "grid"
    mesh: Mesh
    gamma_x: np.ndarray  #: gravity along the first tangent axis, / g (sin theta on a profile)
    gamma_y: np.ndarray  #: gravity along the second tangent axis, / g
    gamma_z: np.ndarray  #: bed-normal gravity, / g (cos theta)
    curvature: np.ndarray  #: 1/R (1/m), >0 where the bed is concave; 0 when curvature is off
    bed_elevation: np.ndarray  #: m
    slope_deg: np.ndarray  #: steepest slope angle theta, degrees
    x: np.ndarray  #: cell-centre coordinate along the grid's x axis (along the bed for profiles)
    y: np.ndarray | None = None  #: grid only: cell-centre y (m)
    x_horizontal: np.ndarray | None = None  #: profile only: horizontal distance of cell centres
    dx: float = 0.0  #: m, spacing along x (along the bed for a profile, horizontal for a grid)
    dy: float = 0.0
    tangent_basis: np.ndarray | None = None  #: grid only: (2, 3) unit vectors e1, e2 in (x, y, z)
    extras: dict = field(default_factory=dict)

    @property
    def n_cells(self) -> int:
        return self.mesh.n_cells


def slope_function(slope):
    """``theta(s)`` in radians and ``d theta / ds`` for a validated ``terrain.slope`` block."""
    if slope.kind == "constant":
        theta0 = math.radians(slope.theta_deg)
        return (lambda s: np.full_like(s, theta0)), (lambda s: np.zeros_like(s))
    if slope.kind == "exponential":  # eq. 58: theta = theta0 exp(-s / a)
        theta0, a = math.radians(slope.theta0_deg), slope.a
        return (lambda s: theta0 * np.exp(-s / a)), (lambda s: -theta0 / a * np.exp(-s / a))
    if slope.kind == "table":  # linear in s between the given points, constant beyond
        xs = np.asarray(slope.x, dtype=float)
        th = np.radians(np.asarray(slope.theta_deg, dtype=float))
        dth = np.diff(th) / np.diff(xs)

        def derivative(s):
            k = np.clip(np.searchsorted(xs, s, side="right") - 1, 0, len(dth) - 1)
            inside = (s > xs[0]) & (s < xs[-1])
            return np.where(inside, dth[k], 0.0)

        return (lambda s: np.interp(s, xs, th)), derivative
    raise ValueError(f"unknown slope kind {slope.kind!r}")


def _cumulative(fun, edges, sub=16):
    """Integral of fun from edges[0] to each edge (composite Simpson, ``sub`` panels a cell)."""
    a, b = edges[:-1], edges[1:]
    t = np.linspace(0.0, 1.0, 2 * sub + 1)
    pts = a[:, None] + (b - a)[:, None] * t[None, :]
    w = np.ones(2 * sub + 1)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    per_cell = (fun(pts) @ w) * (b - a) / (6.0 * sub)
    return np.concatenate([[0.0], np.cumsum(per_cell)])


def profile_terrain(terrain, dx: float, boundary) -> Terrain:
    """A transversally uniform slope, solved along the bed (seed section 6; ``terrain.kind = profile``).

    ``terrain.length`` and ``dx`` are measured along the bed. The bed elevation is 0 at the
    downslope end. The curvature term is kept only when ``terrain.curvature`` is true.
    """
    n = int(round(terrain.length / dx))
    if n < 2 or not math.isclose(n * dx, terrain.length, rel_tol=1e-9):
        raise ValueError(f"length {terrain.length} m is not a whole number (>= 2) of dx = {dx} m")
    theta, dtheta = slope_function(terrain.slope)
    s = (np.arange(n) + 0.5) * dx
    th = theta(s)
    mesh = profile_mesh(n, dx, BOUNDARY_CODES[boundary.x_min], BOUNDARY_CODES[boundary.x_max])
    # Horizontal position and elevation of cell centres: integrate cos and sin along the bed.
    nodes = np.sort(np.concatenate([np.arange(n + 1) * dx, s]))
    horiz = _cumulative(lambda v: np.cos(theta(v)), nodes)[1::2]
    drop = _cumulative(lambda v: np.sin(theta(v)), nodes)
    elevation = drop[-1] - drop[1::2]
    curvature = -dtheta(s) if terrain.curvature else np.zeros(n)
    return Terrain(
        kind="profile",
        mesh=mesh,
        gamma_x=np.sin(th),
        gamma_y=np.zeros(n),
        gamma_z=np.cos(th),
        curvature=np.ascontiguousarray(curvature, dtype=float),
        bed_elevation=elevation,
        slope_deg=np.degrees(th),
        x=s,
        x_horizontal=horiz,
        dx=float(dx),
    )


def plane_basis(slope_deg: float, azimuth_deg: float) -> np.ndarray:
    """Tangent basis (e1 downslope, e2 = e3 ^ e1) of a plane, as a (2, 3) array in (x, y, z).

    ``azimuth_deg`` is the direction the plane faces (downslope), clockwise from north (+y).
    """
    th, az = math.radians(slope_deg), math.radians(azimuth_deg)
    d = np.array([math.sin(az), math.cos(az)])
    e1 = np.array([d[0] * math.cos(th), d[1] * math.cos(th), -math.sin(th)])
    e3 = np.array([d[0] * math.sin(th), d[1] * math.sin(th), math.cos(th)])
    e2 = np.cross(e3, e1)
    return np.stack([e1, e2])


def plane_terrain(terrain, dx: float, dy: float | None, boundary) -> Terrain:
    """An inclined plane over the horizontal rectangle ``terrain.extent`` (``kind = plane``).

    The grid is horizontal (cells dx by dy); each cell is its lift onto the plane, of bed
    area ``dx dy / cos(theta)``, with faces whose normals and lengths are measured on the bed.
    """
    dy = dx if dy is None else dy
    (x0, x1), (y0, y1) = terrain.extent.x, terrain.extent.y
    nx, ny = int(round((x1 - x0) / dx)), int(round((y1 - y0) / dy))
    if nx < 2 or ny < 2:
        raise ValueError("the plane's extent holds fewer than 2 cells along an axis")
    th = math.radians(terrain.slope_deg)
    az = math.radians(terrain.azimuth_deg)
    basis = plane_basis(terrain.slope_deg, terrain.azimuth_deg)
    grad = -math.tan(th) * np.array([math.sin(az), math.cos(az)])  # dz/dx, dz/dy
    lift_x = np.array([dx, 0.0, grad[0] * dx])
    lift_y = np.array([0.0, dy, grad[1] * dy])
    ex, ey = basis @ lift_x, basis @ lift_y  # edge vectors in the tangent basis
    area = dx * dy / math.cos(th)
    bmap = {k: BOUNDARY_CODES[getattr(boundary, k)] for k in ("x_min", "x_max", "y_min", "y_max")}
    mesh = grid_mesh(nx, ny, (ex, ey), area, bmap)
    x = x0 + (np.arange(nx) + 0.5) * dx
    y = y0 + (np.arange(ny) + 0.5) * dy
    xc, yc = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    xx, yy = np.meshgrid(x, y)
    z = terrain.elevation_at_center + grad[0] * (xx - xc) + grad[1] * (yy - yc)
    n = nx * ny
    g_vec = np.array([0.0, 0.0, -1.0])
    return Terrain(
        kind="grid",
        mesh=mesh,
        gamma_x=np.full(n, basis[0] @ g_vec),
        gamma_y=np.full(n, basis[1] @ g_vec),
        gamma_z=np.full(n, math.cos(th)),
        curvature=np.zeros(n),
        bed_elevation=z.ravel(),
        slope_deg=np.full(n, terrain.slope_deg),
        x=x,
        y=y,
        dx=float(dx),
        dy=float(dy),
        tangent_basis=basis,
    )


def build_terrain(scenario) -> Terrain:
    """The terrain of a validated scenario."""
    t = scenario.terrain
    if t.kind == "profile":
        return profile_terrain(t, scenario.grid.dx, scenario.boundary)
    if t.kind == "plane":
        return plane_terrain(t, scenario.grid.dx, scenario.grid.dy, scenario.boundary)
    raise NotImplementedError(f"terrain kind {t.kind!r} is not available yet")
