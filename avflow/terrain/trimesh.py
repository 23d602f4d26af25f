"""Triangular finite-element mesh and its median dual cells (seed section 3.1, Fig. 2).

The seed discretises on "general triangular grids with a finite element data structure using
a particular control volume which is the median based dual cell": one finite-volume cell per
vertex ``P_i``, bounded by the segments that join the midpoints of the edges at ``P_i`` to
the centres of mass of the triangles around it (Fig. 2a); on the boundary, the cell is closed
by the two half-edges at the vertex (Fig. 2b). This module builds that mesh as the arrays of
:class:`~avflow.terrain.mesh.Mesh`, so the face kernel of :mod:`avflow.numerics.kernels` runs on it unchanged.

- :func:`raster_triangles`: triangles over the nodes of a horizontal raster (NaN = outside),
  each quad split along alternating diagonals ("union jack", pattern ``alternate``, so no
  direction is preferred) or into four triangles around its centre (``criss-cross``).
- :func:`refine`: conforming red-green-blue refinement of marked triangles (all edges of a
  marked triangle are bisected; a triangle with a bisected edge always bisects its longest
  edge too, so no hanging vertex remains and angles stay bounded). New vertices take the
  elevation of the bilinear interpolation of the raster. :func:`curvature_marks` marks the
  triangles whose normal turns by more than an angle from a neighbour's (slope change) or
  that are steeper than a slope.
- :func:`dual_mesh`: the median dual on the bed. Each triangle is a flat piece of the bed;
  the piece of cell i inside triangle T is the quadrilateral (P_i, edge midpoint, barycentre,
  edge midpoint) of 3D area ``area(T) / 3``, so the cell areas sum to the bed area of the mesh.
  The face between the two vertices of an edge is made of the two segments midpoint ->
  barycentre (one per adjacent triangle); its ``L n`` is the sum of the segments' ``L n``
  (each normal lying in its triangle's plane), which is exact for the flux of a constant
  state, and makes every interior cell closed (``sum_j L_ij n_ij = 0``) on a plane. Each
  boundary edge also gives its two vertices one wall/open face each: the half-edge.
  Every vertex has its own tangent basis, as :func:`avflow.terrain.bed.surface_terrain` builds
  it: z along the vertex normal (area-weighted normals of the triangles around it), x the
  projection of the horizontal x axis, y = z ^ x; a face's normal is projected onto each
  side's tangent plane and read in that side's basis (the mesh's face frames).
- :func:`triangle_terrain` (a raster) and :func:`plane_triangle_terrain` (a scenario's plane)
  return a :class:`~avflow.terrain.bed.Terrain` of kind ``"triangles"``: cells are the vertices
  (``x``, ``y`` hold the vertex coordinates), ``extras["triangles"]`` the (nt, 3) vertex
  indices (counter-clockwise seen from above), ``extras["boundary_node"]`` the vertices on
  the domain's boundary.
"""

from __future__ import annotations

import math

import numpy as np

from avflow.terrain.mesh import BOUNDARY_CODES, Mesh, _perimeters
from avflow.terrain.bed import Terrain, _side_frame, _unit, bed_coefficients, bed_hessian

PATTERNS = ("alternate", "criss-cross")
_LOCAL_EDGES = ((0, 1), (1, 2), (2, 0))


# --------------------------------------------------------------------------------------------
# The raster and its bilinear interpolation
# --------------------------------------------------------------------------------------------


def _increasing(z, x, y):
    """The raster with both axes increasing (a north-up DEM has y decreasing)."""
    z, x, y = np.asarray(z, dtype=float), np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if z.shape != (y.size, x.size) or x.size < 2 or y.size < 2:
        raise ValueError("the elevation must be a (ny, nx) array over x (nx) and y (ny), >= 2x2")
    if x[1] < x[0]:
        x, z = x[::-1], z[:, ::-1]
    if y[1] < y[0]:
        y, z = y[::-1], z[::-1, :]
    return np.ascontiguousarray(z), x, y


def bilinear(z, x, y, px, py):
    """Bilinear interpolation of the raster ``z`` (nodes x, y increasing) at points (px, py)."""
    dx, dy = x[1] - x[0], y[1] - y[0]
    fx, fy = (np.asarray(px) - x[0]) / dx, (np.asarray(py) - y[0]) / dy
    c = np.clip(np.floor(fx).astype(np.int64), 0, x.size - 2)
    r = np.clip(np.floor(fy).astype(np.int64), 0, y.size - 2)
    tx, ty = fx - c, fy - r
    return ((1 - tx) * (1 - ty) * z[r, c] + tx * (1 - ty) * z[r, c + 1]
            + (1 - tx) * ty * z[r + 1, c] + tx * ty * z[r + 1, c + 1])


# --------------------------------------------------------------------------------------------
# Triangles over a raster, refinement
# --------------------------------------------------------------------------------------------


def raster_triangles(z, x, y, pattern: str = "alternate"):
    """``(xy (nv, 2), z (nv,), triangles (nt, 3))`` over the valid nodes of a raster.

    Vertices are the raster nodes with a finite elevation (plus, for ``criss-cross``, the
    centre of every quad, at the mean of its corners: the bilinear value there). A quad
    whose four corners are valid is split into triangles; ``alternate`` picks the diagonal
    by the parity of (row + column). Triangles are counter-clockwise seen from above.
    """
    if pattern not in PATTERNS:
        raise ValueError(f"unknown triangulation pattern {pattern!r}: use one of {PATTERNS}")
    z, x, y = _increasing(z, x, y)
    ny, nx = z.shape
    valid = np.isfinite(z)
    xx, yy = np.meshgrid(x, y)
    index = -np.ones((ny, nx), dtype=np.int64)
    index[valid] = np.arange(valid.sum())
    xy = np.stack([xx[valid], yy[valid]], axis=1)
    zv = z[valid]
    quad = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]
    rr, cc = np.nonzero(quad)
    a, b = index[rr, cc], index[rr, cc + 1]  # a: lower left, b: lower right
    d, c = index[rr + 1, cc], index[rr + 1, cc + 1]  # d: upper left, c: upper right
    if pattern == "alternate":
        even = (rr + cc) % 2 == 0
        t1 = np.where(even[:, None], np.stack([a, b, c], 1), np.stack([a, b, d], 1))
        t2 = np.where(even[:, None], np.stack([a, c, d], 1), np.stack([b, c, d], 1))
        tris = np.concatenate([t1, t2])
    else:
        m = len(zv) + np.arange(rr.size)
        centre = 0.25 * (xy[a] + xy[b] + xy[c] + xy[d])
        zc = 0.25 * (zv[a] + zv[b] + zv[c] + zv[d])
        xy, zv = np.concatenate([xy, centre]), np.concatenate([zv, zc])
        tris = np.concatenate([np.stack(t, 1) for t in ((a, b, m), (b, c, m), (c, d, m),
                                                         (d, a, m))])
    if tris.size == 0:
        raise ValueError("the raster has no 2x2 block of valid nodes to triangulate")
    used = np.zeros(len(zv), dtype=bool)
    used[tris.ravel()] = True
    if not used.all():  # isolated valid nodes carry no triangle: drop them
        renum = -np.ones(len(zv), dtype=np.int64)
        renum[used] = np.arange(used.sum())
        xy, zv, tris = xy[used], zv[used], renum[tris]
    return xy, zv, np.ascontiguousarray(tris, dtype=np.int64)


def mesh_edges(tris):
    """``(edges (ne, 2) sorted vertex pairs, tri_edge (nt, 3))``; local edge k joins
    vertices k and k+1 of the triangle."""
    pairs = np.stack([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]], axis=1)
    keys = np.sort(pairs.reshape(-1, 2), axis=1)
    edges, inverse = np.unique(keys, axis=0, return_inverse=True)
    return edges, inverse.reshape(-1, 3)


def triangle_normals(xyz, tris):
    """Unscaled normals (twice the 3D area times the unit normal), (nt, 3)."""
    p0, p1, p2 = xyz[tris[:, 0]], xyz[tris[:, 1]], xyz[tris[:, 2]]
    return np.cross(p1 - p0, p2 - p0)


def curvature_marks(xyz, tris, angle_deg=None, slope_deg=None):
    """Triangles to refine: the normal turns by more than ``angle_deg`` from a neighbour's
    across an edge (slope change, a discrete curvature), or the slope exceeds ``slope_deg``."""
    unit = _unit(triangle_normals(xyz, tris))
    marks = np.zeros(len(tris), dtype=bool)
    if slope_deg is not None:
        marks |= unit[:, 2] < math.cos(math.radians(slope_deg))
    if angle_deg is not None:
        _, tri_edge = mesh_edges(tris)
        flat = tri_edge.ravel()
        owner = np.repeat(np.arange(len(tris)), 3)
        order = np.argsort(flat, kind="stable")
        fe, fo = flat[order], owner[order]
        pair = np.flatnonzero(fe[1:] == fe[:-1])  # interior edges: two consecutive owners
        t1, t2 = fo[pair], fo[pair + 1]
        cos_turn = np.einsum("kc,kc->k", unit[t1], unit[t2])
        steep = cos_turn < math.cos(math.radians(angle_deg))
        marks[t1[steep]] = True
        marks[t2[steep]] = True
    return marks


def refine(xy, z, tris, marked, elevation):
    """One conforming red-green-blue refinement of the ``marked`` triangles.

    Every edge of a marked triangle is bisected; then, until nothing changes, a triangle with
    a bisected edge gets its longest (horizontal) edge bisected as well. A triangle is then
    split in 4 (three edges: red), 3 (longest and one more: blue) or 2 (longest only: green).
    ``elevation(px, py)`` gives the elevation of the new vertices (edge midpoints).
    Returns ``(xy, z, tris)``.
    """
    marked = np.asarray(marked, dtype=bool)
    if not marked.any():
        return xy, z, tris
    edges, tri_edge = mesh_edges(tris)
    length = np.linalg.norm(xy[edges[:, 0]] - xy[edges[:, 1]], axis=1)
    # the longest edge, ties broken by the lower edge number (the same for both neighbours)
    key = length[tri_edge] - 1e-9 * length.max() * tri_edge / max(len(edges), 1)
    longest = np.argmax(key, axis=1)
    longest_edge = tri_edge[np.arange(len(tris)), longest]
    split = np.zeros(len(edges), dtype=bool)
    split[tri_edge[marked].ravel()] = True
    while True:
        need = split[tri_edge].any(axis=1) & ~split[longest_edge]
        if not need.any():
            break
        split[longest_edge[need]] = True
    new = -np.ones(len(edges), dtype=np.int64)
    new[split] = len(xy) + np.arange(split.sum())
    mid = 0.5 * (xy[edges[split, 0]] + xy[edges[split, 1]])
    xy = np.concatenate([xy, mid])
    z = np.concatenate([z, elevation(mid[:, 0], mid[:, 1])])
    # rotate each triangle so that its longest edge is local edge 0 (vertices a, b; c opposite)
    rot = (np.arange(3)[None, :] + longest[:, None]) % 3
    rows = np.arange(len(tris))[:, None]
    v = tris[rows, rot]
    m = new[tri_edge[rows, rot]]  # midpoints of edges ab, bc, ca (-1: not split)
    a, b, c = v[:, 0], v[:, 1], v[:, 2]
    mab, mbc, mca = m[:, 0], m[:, 1], m[:, 2]
    keep = mab < 0
    red = ~keep & (mbc >= 0) & (mca >= 0)
    blue_bc = ~keep & (mbc >= 0) & (mca < 0)
    blue_ca = ~keep & (mbc < 0) & (mca >= 0)
    green = ~keep & (mbc < 0) & (mca < 0)
    out = [v[keep]]

    def tri(mask, *cols):
        out.append(np.stack([col[mask] for col in cols], axis=1))

    tri(red, a, mab, mca)
    tri(red, mab, b, mbc)
    tri(red, mca, mbc, c)
    tri(red, mab, mbc, mca)
    tri(green, a, mab, c)
    tri(green, mab, b, c)
    tri(blue_bc, a, mab, c)
    tri(blue_bc, mab, b, mbc)
    tri(blue_bc, mab, mbc, c)
    tri(blue_ca, mab, b, c)
    tri(blue_ca, a, mab, mca)
    tri(blue_ca, mca, mab, c)
    return xy, z, np.ascontiguousarray(np.concatenate(out), dtype=np.int64)


# --------------------------------------------------------------------------------------------
# The median dual
# --------------------------------------------------------------------------------------------


def vertex_bases(xyz, tris):
    """Per vertex: unit normal (area-weighted triangle normals) and the (2, 3) tangent basis
    (e1 = horizontal x projected on the tangent plane, e2 = n ^ e1), as surface_terrain."""
    acc = np.zeros_like(xyz)
    tn = triangle_normals(xyz, tris)
    for k in range(3):
        np.add.at(acc, tris[:, k], tn)
    normal = _unit(acc)
    e1 = _unit(np.stack([1.0 - normal[:, 0] ** 2, -normal[:, 0] * normal[:, 1],
                         -normal[:, 0] * normal[:, 2]], axis=1))
    e2 = np.cross(normal, e1)
    return normal, np.ascontiguousarray(np.stack([e1, e2], axis=1))


def _in_plane(vec, normal):
    """``vec`` projected onto the plane of unit ``normal``, normalised."""
    return _unit(vec - np.einsum("kc,kc->k", vec, normal)[:, None] * normal)


def dual_mesh(xyz, tris, boundary_code):
    """The median-dual :class:`~avflow.terrain.mesh.Mesh` of a triangulated bed.

    ``xyz`` (nv, 3) vertex positions, ``tris`` (nt, 3) counter-clockwise seen from above.
    ``boundary_code(edges, xy)`` gives the code (WALL / OUTFLOW) of each boundary edge
    (rows of sorted vertex pairs). Returns ``(mesh, vertex_normal, basis, boundary_node)``.
    Faces: one per edge (first cell the lower vertex number, normal from it to the other),
    then two per boundary edge (each end vertex's half-edge).
    """
    nv = len(xyz)
    tn = triangle_normals(xyz, tris)
    tarea = 0.5 * np.linalg.norm(tn, axis=1)
    if np.any(tn[:, 2] <= 0.0):
        raise ValueError("triangles must be counter-clockwise seen from above, not degenerate")
    tunit = tn / (2.0 * tarea)[:, None]
    area = np.zeros(nv)
    for k in range(3):
        np.add.at(area, tris[:, k], tarea / 3.0)
    normal, basis = vertex_bases(xyz, tris)
    edges, tri_edge = mesh_edges(tris)
    ne = len(edges)
    vec = np.zeros((ne, 3))  # sum over the adjacent triangles of L n (3D, from edge[0] to [1])
    count = np.zeros(ne, dtype=np.int64)
    bary = (xyz[tris[:, 0]] + xyz[tris[:, 1]] + xyz[tris[:, 2]]) / 3.0
    outward = np.zeros((ne, 3))  # boundary edges: L n of the whole edge, outward, in its plane
    for k, (p, q) in enumerate(_LOCAL_EDGES):
        va, vb = tris[:, p], tris[:, q]
        seg = bary - 0.5 * (xyz[va] + xyz[vb])
        ln = np.cross(seg, tunit)  # points from va to vb (the triangle is counter-clockwise)
        sign = np.where(va < vb, 1.0, -1.0)[:, None]
        e = tri_edge[:, k]
        np.add.at(vec, e, sign * ln)
        np.add.at(count, e, 1)
        np.add.at(outward, e, np.cross(xyz[vb] - xyz[va], tunit))
    if np.any(count > 2):
        raise ValueError("an edge is shared by more than two triangles: not a surface mesh")
    on_boundary = count == 1
    bedges = edges[on_boundary]
    codes = np.asarray(boundary_code(bedges, xyz[:, :2]), dtype=np.int64)
    half = 0.5 * outward[on_boundary]
    boundary_node = np.zeros(nv, dtype=bool)
    boundary_node[bedges.ravel()] = True

    face_cells = np.concatenate([
        edges,
        np.stack([bedges[:, 0], codes], axis=1),
        np.stack([bedges[:, 1], codes], axis=1),
    ]).astype(np.int64)
    fvec = np.concatenate([vec, half, half])
    face_length = np.linalg.norm(fvec, axis=1)
    if np.any(face_length <= 0.0):
        raise ValueError("a dual face has zero length (degenerate triangles)")
    i, j = face_cells[:, 0], face_cells[:, 1]
    jj = np.where(j >= 0, j, i)
    frames = np.zeros((len(face_cells), 2, 2, 2))
    for side, cell in enumerate((i, jj)):
        n_side = _in_plane(fvec, normal[cell])
        t_side = np.cross(normal[cell], n_side)
        frames[:, side] = _side_frame(n_side, t_side, basis[cell])
    face_frame = np.ascontiguousarray(frames)
    mesh = Mesh(
        cell_area=area,
        cell_perimeter=_perimeters(nv, face_cells, face_length),
        face_cells=np.ascontiguousarray(face_cells),
        face_normal=np.ascontiguousarray(face_frame[:, 0, 0, :]),
        face_length=face_length,
        shape=(nv,),
        face_frame=face_frame,
    )
    return mesh, normal, basis, boundary_node


def side_codes(edges, xy, box, side_code, hole_code):
    """Boundary code per edge: the side of the bounding ``box = (x0, x1, y0, y1)`` it lies on,
    else (the edge of a NODATA hole) ``hole_code``."""
    x0, x1, y0, y1 = box
    tol = 1e-9 * max(x1 - x0, y1 - y0)
    pa, pb = xy[edges[:, 0]], xy[edges[:, 1]]
    codes = np.full(len(edges), hole_code, dtype=np.int64)
    for name, axis, value in (("x_min", 0, x0), ("x_max", 0, x1), ("y_min", 1, y0),
                              ("y_max", 1, y1)):
        on = (np.abs(pa[:, axis] - value) < tol) & (np.abs(pb[:, axis] - value) < tol)
        codes[on] = side_code[name]
    return codes


# --------------------------------------------------------------------------------------------
# Terrains
# --------------------------------------------------------------------------------------------


def _terrain(xy, z, tris, boundary_code, dx, dy, crs_wkt=None, extras=None,
             hessian=None) -> Terrain:
    """``hessian``: None (no curvature term) or a callable (x, y) -> (b_xx, b_xy, b_yy)."""
    xyz = np.column_stack([xy, z])
    mesh, normal, basis, boundary_node = dual_mesh(xyz, tris, boundary_code)
    cos_theta = normal[:, 2]
    at_cells = None if hessian is None else hessian(xy[:, 0], xy[:, 1])
    return Terrain(
        kind="triangles",
        mesh=mesh,
        **bed_coefficients(basis, cos_theta, at_cells),
        bed_elevation=np.ascontiguousarray(z, dtype=float),
        x=np.ascontiguousarray(xy[:, 0]),
        y=np.ascontiguousarray(xy[:, 1]),
        dx=float(dx),
        dy=float(dy),
        tangent_basis=basis,
        crs_wkt=crs_wkt,
        extras={"triangles": tris, "boundary_node": boundary_node, **(extras or {})},
    )


class MeshTooLarge(ValueError):
    """Refinement that would pass the memory limit's number of nodes."""


def _refined(xy, z, tris, elevation, refine_angle_deg, refine_slope_deg, refine_levels,
             max_nodes=None):
    """Up to ``refine_levels`` rounds of :func:`refine`; before each, its nodes are counted
    against ``max_nodes`` (a marked triangle adds 1.5-1.7 nodes with the closure, its edge
    midpoints being shared: 2 is counted), so a mesh too large is refused before it is
    built, not by numpy's MemoryError a minute later; the mesh made is counted again."""
    for level in range(int(refine_levels)):
        marks = curvature_marks(np.column_stack([xy, z]), tris, refine_angle_deg,
                                refine_slope_deg)
        if not marks.any():
            break
        expected = len(xy) + 2 * int(marks.sum())
        if max_nodes is not None and expected > max_nodes:
            raise MeshTooLarge(f"refinement round {level + 1} of {int(refine_levels)} would "
                               f"make about {expected:,} nodes ({len(xy):,} now), more than "
                               f"the {int(max_nodes):,} the memory limit allows: fewer "
                               "levels, a larger angle_deg or grid.dx, or raise --max-memory")
        xy, z, tris = refine(xy, z, tris, marks, elevation)
        if max_nodes is not None and len(xy) > max_nodes:
            raise MeshTooLarge(f"refinement round {level + 1} of {int(refine_levels)} made "
                               f"{len(xy):,} nodes, more than the {int(max_nodes):,} the "
                               "memory limit allows: fewer levels, a larger angle_deg or "
                               "grid.dx, or raise --max-memory")
    return xy, z, tris


def triangle_terrain(elevation, x, y, boundary, nodata: str = "wall", crs_wkt=None, *,
                     pattern: str = "alternate", refine_angle_deg=None, refine_slope_deg=None,
                     refine_levels: int = 0, curvature: bool = True,
                     max_nodes: float | None = None) -> Terrain:
    """The median-dual terrain of a raster ``z = b(x, y)`` (the inputs of surface_terrain).

    Vertices on the raster nodes with a finite elevation; faces on the outer box are the
    ``boundary`` sides, faces around NODATA holes ``nodata``. With ``refine_levels > 0``,
    up to that many rounds of :func:`refine` on the triangles marked by
    :func:`curvature_marks`, new elevations by bilinear interpolation of the raster. With
    ``curvature``, the raster's Hessian (:func:`~avflow.terrain.bed.bed_hessian`) is
    interpolated bilinearly to the vertices for the curvature term.
    """
    z, x, y = _increasing(elevation, x, y)
    hessian = None
    if curvature:
        parts = bed_hessian(z, x[1] - x[0], y[1] - y[0])
        parts = [np.where(np.isfinite(p), p, 0.0) for p in parts]  # NODATA: the mesh's edge
        hessian = lambda px, py: tuple(bilinear(p, x, y, px, py) for p in parts)  # noqa: E731
    xy, zv, tris = raster_triangles(z, x, y, pattern)
    xy, zv, tris = _refined(xy, zv, tris, lambda px, py: bilinear(z, x, y, px, py),
                            refine_angle_deg, refine_slope_deg, refine_levels, max_nodes)
    sides = {k: BOUNDARY_CODES[getattr(boundary, k)] for k in ("x_min", "x_max", "y_min",
                                                                 "y_max")}
    box = (x[0], x[-1], y[0], y[-1])
    return _terrain(xy, zv, tris,
                    lambda e, p: side_codes(e, p, box, sides, BOUNDARY_CODES[nodata]),
                    x[1] - x[0], y[1] - y[0], crs_wkt, hessian=hessian)


def plane_triangle_terrain(terrain, dx: float, dy: float | None, boundary, **options) -> Terrain:
    """An inclined plane (a scenario's ``terrain`` block of kind plane) over its extent.

    Vertices at ``x0 + k dx``, ``y0 + l dy`` cover the extent exactly, so the bed area is
    that of the square grid with the same dx; ``options`` as :func:`triangle_terrain`.
    """
    dy = dx if dy is None else dy
    (x0, x1), (y0, y1) = terrain.extent.x, terrain.extent.y
    nx, ny = int(round((x1 - x0) / dx)), int(round((y1 - y0) / dy))
    if nx < 2 or ny < 2:
        raise ValueError("the plane's extent holds fewer than 2 cells along an axis")
    th, az = math.radians(terrain.slope_deg), math.radians(terrain.azimuth_deg)
    grad = -math.tan(th) * np.array([math.sin(az), math.cos(az)])
    x = x0 + np.arange(nx + 1) * dx
    y = y0 + np.arange(ny + 1) * dy
    xx, yy = np.meshgrid(x, y)
    xc, yc = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    z = terrain.elevation_at_center + grad[0] * (xx - xc) + grad[1] * (yy - yc)
    return triangle_terrain(z, x, y, boundary, **options)
