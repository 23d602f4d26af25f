"""Bed geometry in the frame linked to the topography (seed section 2, Fig. 1).

In each cell the bed defines a tangent basis (x along the bed, z normal to it, y = z ^ x) in
which the state lives. The gravity vector projects onto it as ``g (gamma_x, gamma_y, -gamma_z)``
(eqs. 7-8, 10): ``gamma_z = cos(theta)`` gives the bed-normal weight that sets the pressure and
the Coulomb threshold (eqs. 12, 19-20), ``(gamma_x, gamma_y)`` drive the flow. A profile also
carries the curvature ``1/R = -d theta / ds`` of eqs. 61-62 (positive where the slope flattens
downhill, which presses the mass onto the bed and adds friction).

Builders return a :class:`Terrain`: the finite-volume :class:`~avflow.terrain.mesh.Mesh` plus those
per-cell coefficients and the coordinates that outputs need. Everything is computed once.

- :func:`profile_terrain`: a transversally uniform slope solved in 1D along the bed (x is the
  curvilinear abscissa s), slope angle constant, exponential (eq. 58) or tabulated.
- :func:`plane_terrain`: an inclined plane of any slope and azimuth over a horizontal grid;
  the plane has one tangent basis, so cells are the grid cells lifted onto the bed.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from avflow.terrain.mesh import (BOUNDARY_CODES, EAST, NORTH, SOUTH, WEST, Mesh, _perimeters,
                                 grid_mesh, profile_mesh)


@dataclass(frozen=True)
class Terrain:
    """A mesh and its bed coefficients, one value per cell (1D arrays over the cells)."""

    kind: str  #: "profile", "grid" or "triangles" (median dual cells, avflow.terrain.trimesh)
    mesh: Mesh
    gamma_x: np.ndarray  #: gravity along the first tangent axis, / g (sin theta on a profile)
    gamma_y: np.ndarray  #: gravity along the second tangent axis, / g
    gamma_z: np.ndarray  #: bed-normal gravity, / g (cos theta)
    #: (n_cells, 3): (K11, K12, K22), the bed's curvature tensor (second fundamental form) in
    #: the cell's tangent basis, 1/m; u.K.u > 0 where the bed is concave along u (1/R of eqs.
    #: 61-62 on a profile, K11 = -d theta / ds); all 0 when the curvature term is off
    curvature: np.ndarray
    bed_elevation: np.ndarray  #: m
    slope_deg: np.ndarray  #: steepest slope angle theta, degrees
    x: np.ndarray  #: cell-centre coordinate along the grid's x axis (along the bed for profiles)
    y: np.ndarray | None = None  #: grid only: cell-centre y (m)
    x_horizontal: np.ndarray | None = None  #: profile only: horizontal distance of cell centres
    dx: float = 0.0  #: m, spacing along x (along the bed for a profile, horizontal for a grid)
    dy: float = 0.0
    #: grid only: (n_cells, 2, 3) unit vectors e1, e2 of each cell's tangent basis in (x, y, z)
    tangent_basis: np.ndarray | None = None
    #: grid only: flat index of each cell in the (ny, nx) grid (cells outside the DEM are absent)
    cell_index: np.ndarray | None = None
    crs_wkt: str | None = None
    extras: dict = field(default_factory=dict)

    @property
    def n_cells(self) -> int:
        return self.mesh.n_cells

    @property
    def grid_shape(self) -> tuple:
        """(nx,) for a profile, (ny, nx) for a grid, (n_vertices,) for triangles."""
        if self.kind == "triangles":
            return (self.x.size,)
        return (self.x.size,) if self.y is None else (self.y.size, self.x.size)

    def to_grid(self, values: np.ndarray, fill=np.nan) -> np.ndarray:
        """Per-cell values (..., n_cells) laid out on the grid (..., ny, nx), ``fill`` outside."""
        values = np.asarray(values)
        if self.cell_index is None:
            return values.reshape(values.shape[:-1] + self.grid_shape)
        out = np.full(values.shape[:-1] + (int(np.prod(self.grid_shape)),), fill,
                      dtype=np.result_type(values.dtype, type(fill)))
        out[..., self.cell_index] = values
        return out.reshape(values.shape[:-1] + self.grid_shape)

    def cell_xy(self):
        """Horizontal coordinates (x, y) of the cell centres, per cell (grids, triangles).

        Computed once per terrain (every snapshot's centre of mass reads them); read-only.
        """
        return self._cell_xy

    @functools.cached_property
    def _cell_xy(self):
        if self.kind == "triangles":  # cells are the vertices: x, y are per cell already
            return self.x, self.y
        xx, yy = np.meshgrid(self.x, self.y)
        xx, yy = xx.ravel(), yy.ravel()
        if self.cell_index is not None:
            xx, yy = xx[self.cell_index], yy[self.cell_index]
        xx.flags.writeable = False
        yy.flags.writeable = False
        return xx, yy


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
    curvature = np.zeros((n, 3))
    if terrain.curvature:
        curvature[:, 0] = -dtheta(s)
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
        curvature=np.zeros((n, 3)),
        bed_elevation=z.ravel(),
        slope_deg=np.full(n, terrain.slope_deg),
        x=x,
        y=y,
        dx=float(dx),
        dy=float(dy),
        tangent_basis=np.ascontiguousarray(np.broadcast_to(basis, (n, 2, 3))),
    )


def _gradient(z, d, axis):
    """dz/dx along ``axis`` with NaN-aware one-sided differences (0 where isolated)."""
    fwd = (np.roll(z, -1, axis) - z) / d
    bwd = (z - np.roll(z, 1, axis)) / d
    idx = [slice(None)] * 2
    idx[axis] = -1
    fwd[tuple(idx)] = np.nan
    idx[axis] = 0
    bwd[tuple(idx)] = np.nan
    with np.errstate(invalid="ignore"):
        both = 0.5 * (fwd + bwd)
    return np.where(np.isfinite(both), both,
                    np.where(np.isfinite(fwd), fwd, np.where(np.isfinite(bwd), bwd, 0.0)))


def _per_cell(fields, flat):
    """Raster fields at the cells (the valid raster nodes ``flat``)."""
    return tuple(np.ascontiguousarray(f.ravel()[flat]) for f in fields)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def bed_coefficients(basis, cos_theta, hessian=None) -> dict:
    """Terrain fields of per-cell bed frames ``basis`` (n, 2, 3) with bed-normal z component
    ``cos_theta``: gravity along e1, e2 and across the bed (``gamma = -(e1_z, e2_z)``,
    ``gamma_z = cos(theta)``), the slope angle, and the curvature tensor from the bed's
    ``hessian`` (per cell ``(b_xx, b_xy, b_yy)``, 1/m; None: no curvature term)."""
    cos_theta = np.ascontiguousarray(cos_theta)
    n = basis.shape[0]
    return {
        "gamma_x": np.ascontiguousarray(-basis[:, 0, 2]),
        "gamma_y": np.ascontiguousarray(-basis[:, 1, 2]),
        "gamma_z": cos_theta,
        "curvature": (np.zeros((n, 3)) if hessian is None
                      else curvature_tensor(basis, cos_theta, *hessian)),
        "slope_deg": np.degrees(np.arccos(np.clip(cos_theta, -1.0, 1.0))),
    }


def bed_hessian(z, dx, dy):
    """Second derivatives ``(b_xx, b_xy, b_yy)`` (1/m) of a raster bed, NaN where it is NaN.

    The derivative of the central gradient (:func:`_gradient`), so a stencil of 2 dx: the
    curvature is read over the same cells that give each cell its normal, and the noise of
    a 5 m DEM's three-point second difference is halved. NaN (NODATA) neighbours and the
    map's edges switch to one-sided differences; b_xy is symmetrised.
    """
    valid = np.isfinite(z)
    bx = np.where(valid, _gradient(z, dx, 1), np.nan)
    by = np.where(valid, _gradient(z, dy, 0), np.nan)
    bxx, byy = _gradient(bx, dx, 1), _gradient(by, dy, 0)
    bxy = 0.5 * (_gradient(bx, dy, 0) + _gradient(by, dx, 1))
    return tuple(np.where(valid, d, np.nan) for d in (bxx, bxy, byy))


def curvature_tensor(basis, cos_theta, bxx, bxy, byy):
    """(n, 3) curvature tensor ``(K11, K12, K22)`` of a bed ``z = b(x, y)`` in cell bases.

    The centripetal acceleration of material moving along the bed at velocity ``u`` (tangent)
    is ``u . K u`` along the bed normal: the second fundamental form
    ``II(u, u) = u_h^T H u_h / sqrt(1 + |grad b|^2)`` with ``u_h`` the horizontal projection
    of ``u`` and ``H`` the Hessian of ``b``. With ``u = u1 e1 + u2 e2``,
    ``K_ab = cos(theta) (e_a)_h^T H (e_b)_h``. On a transversally uniform bed it gives
    ``K11 = b'' cos^3(theta) = 1/R`` along the slope (eqs. 61-62).
    """
    hess = np.empty((cos_theta.size, 2, 2))
    hess[:, 0, 0], hess[:, 0, 1], hess[:, 1, 0], hess[:, 1, 1] = bxx, bxy, bxy, byy
    horiz = basis[:, :, :2]
    k = cos_theta[:, None, None] * np.einsum("nai,nij,nbj->nab", horiz, hess, horiz)
    return np.ascontiguousarray(np.stack([k[:, 0, 0], k[:, 0, 1], k[:, 1, 1]], axis=1))


def _side_frame(normal, tangent, basis):
    """(k, 2, 2) frames of faces with 3D normals and tangents as one side sees them, in
    that side's cell bases ``basis`` (k, 2, 3): rows the in-plane normal and tangent.

    Each side sees the face normal as its projection on that cell's tangent plane,
    *normalised*, and the tangent as that normal turned by +90 degrees in the plane (the
    orientation of ``tangent = bed x normal``). Each side's frame is then a rotation: a
    velocity keeps its norm when it is split into (u_n, u_t) and put back, so mass leaving
    a cell at its own velocity leaves that velocity unchanged, and a discharge crossing into
    a differently tilted cell keeps its magnitude (transported along the bed, not
    foreshortened). Projecting without normalising lost the out-of-plane part of the
    outgoing momentum while the mass left: on a 46 to 84 degree break of a real DEM a thin
    cell accelerated to 350 m/s.
    """
    n2 = np.einsum("kc,kbc->kb", normal, basis)
    t2 = np.einsum("kc,kbc->kb", tangent, basis)
    norm = np.hypot(n2[:, 0], n2[:, 1])
    n2 = n2 / norm[:, None]
    rot = np.stack([-n2[:, 1], n2[:, 0]], axis=1)
    # the 3D tangent fixes the orientation (it is +90 degrees of the normal in 3D)
    sign = np.where(np.einsum("kb,kb->k", rot, t2) >= 0.0, 1.0, -1.0)
    out = np.empty((normal.shape[0], 2, 2))
    out[:, 0, :] = n2
    out[:, 1, :] = rot * sign[:, None]
    return out


#: Cells whose faces :func:`surface_terrain` builds at once (bounds its temporaries)
FACE_CHUNK = 1 << 18


def surface_terrain(elevation, x, y, boundary, nodata: str = "wall", crs_wkt=None,
                    curvature: bool = True, walls=None) -> Terrain:
    """Any bed ``z = b(x, y)`` on a horizontal grid (a DEM); NaN cells lie outside the domain.

    Every cell is the lift of its grid cell onto the bed, with its own tangent basis (seed
    Fig. 1): z along the bed normal ``n = (-b_x, -b_y, 1) / |.|``, x the projection of the
    fixed horizontal x axis onto the tangent plane, y = z ^ x. Gravity gives
    ``gamma = (-e1_z, -e2_z)`` and ``gamma_z = n_z = cos(theta)``; the bed area of a cell is
    ``dx dy / cos(theta)``. A face between two cells lies on the bed plane of the averaged
    gradient (the difference across the face, the mean along it); its normal and tangent
    are read in each cell's basis (:class:`~avflow.terrain.mesh.Mesh` face frames), so a discharge
    crosses from one basis to the other through the face. Faces towards NODATA cells are
    walls or open (``nodata``). With ``curvature``, each cell carries the bed's curvature
    tensor (:func:`curvature_tensor` of :func:`bed_hessian`), the 2D form of eqs. 61-62.
    ``walls``: a (ny, nx) mask of NaN cells whose faces are walls whatever ``nodata`` says
    (a structure's vertical wall, :mod:`avflow.terrain.structures`).
    """
    z = np.asarray(elevation, dtype=float)
    ny, nx = z.shape
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    dx, dy = float(x[1] - x[0]), float(y[1] - y[0])
    valid = np.isfinite(z)
    if not valid.any():
        raise ValueError("the DEM has no valid cell")
    bx, by = _gradient(z, dx, 1), _gradient(z, dy, 0)
    normal = _unit(np.stack([-bx, -by, np.ones_like(z)], axis=-1))
    e1 = _unit(np.stack([1.0 - normal[..., 0] ** 2, -normal[..., 0] * normal[..., 1],
                         -normal[..., 0] * normal[..., 2]], axis=-1))
    e2 = np.cross(normal, e1)
    index = -np.ones((ny, nx), dtype=np.int64)
    index[valid] = np.arange(valid.sum())
    flat = np.flatnonzero(valid.ravel())
    basis = np.stack([e1, e2], axis=-2).reshape(-1, 2, 3)[flat]
    cells, frames, lengths, steps = [], [], [], []
    side_code = {k: BOUNDARY_CODES[getattr(boundary, k)] for k in ("x_min", "x_max", "y_min",
                                                                     "y_max")}
    hole = BOUNDARY_CODES[nodata]

    def add_faces(i_rc, j_rc, along_x):
        """Faces between cells at i_rc and j_rc (j = +1 in x or y); j may be off-grid/NaN."""
        (ri, ci), (rj, cj) = i_rc, j_rc
        inside = (rj >= 0) & (rj < ny) & (cj >= 0) & (cj < nx)
        rjc, cjc = np.clip(rj, 0, ny - 1), np.clip(cj, 0, nx - 1)
        j_valid = inside & valid[rjc, cjc]
        zi, zj = z[ri, ci], np.where(j_valid, z[rjc, cjc], np.nan)
        gi = np.stack([bx[ri, ci], by[ri, ci]], axis=-1)
        gj = np.where(j_valid[:, None], np.stack([bx[rjc, cjc], by[rjc, cjc]], axis=-1), gi)
        g = 0.5 * (gi + gj)
        step = (cj - ci) * dx if along_x else (rj - ri) * dy
        across = np.where(j_valid, (zj - zi) / step, g[:, 0 if along_x else 1])
        if along_x:
            g[:, 0] = across
            edge = np.stack([np.zeros_like(g[:, 0]), np.full_like(g[:, 0], dy), g[:, 1] * dy], 1)
        else:
            g[:, 1] = across
            edge = np.stack([np.full_like(g[:, 0], dx), np.zeros_like(g[:, 0]), g[:, 0] * dx], 1)
        direction = np.sign((cj - ci) if along_x else (rj - ri))[:, None]
        i_idx = index[ri, ci]
        if along_x:
            off = np.where(cj < 0, side_code["x_min"], side_code["x_max"])
        else:
            off = np.where(rj < 0, side_code["y_min"], side_code["y_max"])
        hole_j = (hole if walls is None else
                  np.where(inside & walls[rjc, cjc], BOUNDARY_CODES["wall"], hole))
        j_idx = np.where(j_valid, index[rjc, cjc], np.where(inside, hole_j, off))
        bj = np.where(j_valid[:, None, None], basis[np.maximum(index[rjc, cjc], 0)],
                      basis[i_idx])
        cells.append(np.stack([i_idx, j_idx], axis=1))
        steps.append(np.where(direction[:, 0] > 0, EAST if along_x else NORTH,
                              WEST if along_x else SOUTH).astype(np.int8))
        # Each side sees the face as the edge lifted onto its *own* tangent plane, with the
        # in-plane normal to it (towards j): always a proper direction of that cell. The
        # normal of the averaged bed plane, projected, can point nowhere near the neighbour
        # where the gradient turns sharply (78 degree cliffs of a 5 m DEM): a cell moving
        # downslope then had no face to empty through and gravity sped it up without end.
        # On a plane both constructions coincide.
        frame = np.empty((i_idx.size, 2, 2, 2))
        for side, (grad, b) in enumerate(((gi, basis[i_idx]), (gj, bj))):
            if along_x:
                e = np.stack([np.zeros_like(grad[:, 0]), np.ones_like(grad[:, 0]), grad[:, 1]], 1)
            else:
                e = np.stack([np.ones_like(grad[:, 0]), np.zeros_like(grad[:, 0]), grad[:, 0]], 1)
            plane = _unit(np.stack([-grad[:, 0], -grad[:, 1], np.ones_like(grad[:, 0])], 1))
            n_side = _unit(np.cross(e, plane) if along_x else np.cross(plane, e)) * direction
            t_side = np.cross(plane, n_side)
            frame[:, side] = _side_frame(n_side, t_side, b)
        frames.append(frame)
        lengths.append(np.linalg.norm(edge, axis=1))

    # The faces in grid order (:mod:`avflow.terrain.mesh`: every cell's W < E < S < N): the x
    # faces row by row from west to east, then the y faces from south to north. A face
    # between the places p - 1 and p along its axis belongs to the cell at p - 1 (towards
    # +x or +y) when that cell is valid, else to the cell at p (towards -x or -y, to the
    # side or to a NODATA cell beyond).
    padded = np.zeros((ny + 2, nx + 2), dtype=bool)
    padded[1:-1, 1:-1] = valid
    for along_x in (True, False):
        if along_x:  # places (r, k), k = 0..nx: between cells (r, k - 1) and (r, k)
            low, high = padded[1:-1, :-1], padded[1:-1, 1:]
        else:  # places (k, c), k = 0..ny: between cells (k - 1, c) and (k, c)
            low, high = padded[:-1, 1:-1], padded[1:, 1:-1]
        width = low.shape[1]
        faces = np.flatnonzero(low | high)
        # in chunks of faces, in order: a dozen temporaries per face at once made a 1 m
        # DEM's mesh peak at twice its size
        for lo in range(0, faces.size, FACE_CHUNK):
            f = faces[lo:lo + FACE_CHUNK]
            r, c = f // width, f % width  # the place: the high cell's row and column
            r_lo, c_lo = (r, c - 1) if along_x else (r - 1, c)
            owned = low.ravel()[f]  # the low cell is valid: it owns the face
            i_rc = (np.where(owned, r_lo, r), np.where(owned, c_lo, c))
            j_rc = (np.where(owned, r, r_lo), np.where(owned, c, c_lo))
            add_faces(i_rc, j_rc, along_x)
    face_cells = np.ascontiguousarray(np.concatenate(cells), dtype=np.int64)
    del cells
    face_frame = np.ascontiguousarray(np.concatenate(frames))
    del frames
    face_length = np.concatenate(lengths)
    # the first cell's normal (frame row 0 of side 0) in its basis, for Mesh.face_normal
    face_normal = np.ascontiguousarray(face_frame[:, 0, 0, :])
    n = flat.size
    cos_theta = normal.reshape(-1, 3)[flat, 2]
    mesh = Mesh(
        cell_area=np.full(n, dx * dy) / cos_theta,
        cell_perimeter=_perimeters(n, face_cells, face_length),
        face_cells=face_cells,
        face_normal=face_normal,
        face_length=face_length,
        shape=(n,),
        face_frame=face_frame,
        face_direction=np.concatenate(steps),
    )
    return Terrain(
        kind="grid",
        mesh=mesh,
        **bed_coefficients(basis, cos_theta, _per_cell(bed_hessian(z, dx, dy), flat)
                           if curvature else None),
        bed_elevation=z.ravel()[flat],
        x=x,
        y=y,
        dx=dx,
        dy=dy,
        tangent_basis=np.ascontiguousarray(basis),
        cell_index=None if valid.all() else flat,
        crs_wkt=crs_wkt,
    )
