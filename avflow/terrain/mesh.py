"""Finite-volume layout: cells and the faces between them (seed eqs. 24-27).

A :class:`Mesh` is the seed's notation as arrays, built once outside the time loop:

- cells ``i``: area ``A_i`` (m^2, measured on the bed; m per unit width for a profile) and
  perimeter ``sum_j L_ij`` (used by the CFL condition, eq. 41);
- faces ``Gamma_ij``: the two cells ``(i, j)``, the unit normal ``n_ij`` pointing from i to j,
  expressed in the bed's tangent basis, and the length ``L_ij`` (m; 1 for a profile);
- per face and side, the *frame* of the face seen from that cell: a 2x2 matrix whose rows
  are the face normal and the face tangent in the cell's own tangent basis. On a plane both
  sides hold the same rotation; on real terrain every cell has its own bed-linked basis
  (seed Fig. 1) and the frame carries a velocity from one basis to the other through the face.

A boundary face has ``j < 0``: :data:`WALL` (solid wall, the seed's default) or
:data:`OUTFLOW` (open: material leaves and is counted). The same arrays describe a 1D profile,
a 2D grid and a triangular dual mesh, so the kernels need nothing else. Profiles keep their
faces in order (face k between cells k-1 and k), which lets a structured sweep read them fast.

Square grids (planes and DEMs) keep theirs in *grid order*: the x faces row by row from west
to east (a face to the map's side or to a NODATA cell at its place in the row), then the y
faces row by row from south to north. Every cell then has its faces' indices in the order
W < E < S < N, the order in which the face kernel adds them to the cell; the square-grid
kernel adds them in that same order without a per-cell table, and gives the face kernel's
answer bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

WALL = -1
OUTFLOW = -2

# Grid steps of Mesh.face_direction, in index space (rows are the grid's y index)
EAST, WEST, NORTH, SOUTH = 0, 1, 2, 3

BOUNDARY_CODES = {"wall": WALL, "outflow": OUTFLOW}


@dataclass(frozen=True)
class Mesh:
    """Cells and faces of a finite-volume mesh. All arrays are C-contiguous."""

    cell_area: np.ndarray  #: (n_cells,) float64, m^2 on the bed
    cell_perimeter: np.ndarray  #: (n_cells,) float64, m
    face_cells: np.ndarray  #: (n_faces, 2) int64; second entry WALL/OUTFLOW on the boundary
    face_normal: np.ndarray  #: (n_faces, 2) float64 unit normal from the first cell to the second
    face_length: np.ndarray  #: (n_faces,) float64, m
    shape: tuple  #: logical shape of the cell array: (nx,) profile, (ny, nx) grid, (n,) triangles
    structured_1d: bool = False  #: faces ordered along a line: the fast 1D sweep applies
    #: (n_faces, 2, 2, 2) float64: [face, side (0: first cell, 1: second), row (0: normal,
    #: 1: tangent), component in that cell's tangent basis]. Derived from face_normal when
    #: all cells share one basis.
    face_frame: np.ndarray | None = None
    #: square grids only: (n_faces,) int8, the grid step from the first cell to the second
    #: (or to the outside): :data:`EAST` (column + 1), :data:`WEST`, :data:`NORTH` (row + 1),
    #: :data:`SOUTH`. What the structured square-grid kernel needs to lay the faces out.
    face_direction: np.ndarray | None = None

    @property
    def n_cells(self) -> int:
        return self.cell_area.shape[0]

    @property
    def n_faces(self) -> int:
        return self.face_length.shape[0]

    def __post_init__(self):
        n, nf = self.n_cells, self.n_faces
        if self.face_cells.shape != (nf, 2) or self.face_normal.shape != (nf, 2):
            raise ValueError("face arrays have inconsistent shapes")
        if self.cell_perimeter.shape != (n,):
            raise ValueError("cell arrays have inconsistent shapes")
        if np.any(self.cell_area <= 0.0):
            raise ValueError("cell areas must be positive")
        if int(np.prod(self.shape)) != n:
            raise ValueError(f"shape {self.shape} does not hold {n} cells")
        if self.face_frame is None:
            object.__setattr__(self, "face_frame", shared_basis_frames(self.face_normal))
        if self.face_frame.shape != (nf, 2, 2, 2):
            raise ValueError("face_frame must have shape (n_faces, 2, 2, 2)")
        if self.face_direction is not None and self.face_direction.shape != (nf,):
            raise ValueError("face_direction must have shape (n_faces,)")


def shared_basis_frames(face_normal: np.ndarray) -> np.ndarray:
    """Face frames when both cells share one tangent basis: rows n = (nx, ny), t = (-ny, nx)."""
    nx, ny = face_normal[:, 0], face_normal[:, 1]
    side = np.stack([np.stack([nx, ny], axis=1), np.stack([-ny, nx], axis=1)], axis=1)
    return np.ascontiguousarray(np.stack([side, side], axis=1))


def _perimeters(n_cells, face_cells, face_length):
    perimeter = np.zeros(n_cells)
    np.add.at(perimeter, face_cells[:, 0], face_length)
    inner = face_cells[:, 1] >= 0
    np.add.at(perimeter, face_cells[inner, 1], face_length[inner])
    return perimeter


def profile_mesh(n: int, dx: float, left: int = WALL, right: int = WALL) -> Mesh:
    """A line of ``n`` cells of length ``dx`` along the bed, per unit width.

    Face k (k = 1..n-1) lies between cells k-1 and k; face 0 is the upslope boundary of cell 0
    and face n the downslope boundary of cell n-1. All normals point downslope (+x) except the
    boundary face 0, whose normal points out of cell 0 (-x), as every boundary normal does.
    """
    if n < 2:
        raise ValueError("a profile needs at least 2 cells")
    face_cells = np.empty((n + 1, 2), dtype=np.int64)
    face_normal = np.zeros((n + 1, 2))
    face_cells[1:n, 0] = np.arange(n - 1)
    face_cells[1:n, 1] = np.arange(1, n)
    face_normal[1:n, 0] = 1.0
    face_cells[0] = (0, left)
    face_normal[0, 0] = -1.0
    face_cells[n] = (n - 1, right)
    face_normal[n, 0] = 1.0
    face_length = np.ones(n + 1)
    area = np.full(n, float(dx))
    return Mesh(
        cell_area=area,
        cell_perimeter=_perimeters(n, face_cells, face_length),
        face_cells=face_cells,
        face_normal=face_normal,
        face_length=face_length,
        shape=(n,),
        structured_1d=True,
    )


def grid_mesh(
    nx: int,
    ny: int,
    corner_vectors,
    cell_area: float,
    boundary: dict,
) -> Mesh:
    """A structured grid of ``ny x nx`` cells on a surface with one tangent basis (a plane).

    ``corner_vectors = (ex, ey)``: the cell's edge vectors along the grid's x and y axes,
    expressed in the bed's tangent basis (2-vectors, m). ``cell_area`` is the bed area of a
    cell (m^2). ``boundary`` maps ``x_min, x_max, y_min, y_max`` to WALL or OUTFLOW.
    Cells are numbered ``row * nx + col`` (row along y).
    """
    ex = np.asarray(corner_vectors[0], dtype=float)
    ey = np.asarray(corner_vectors[1], dtype=float)
    idx = np.arange(nx * ny).reshape(ny, nx)

    def normal_between(edge, toward):
        """Unit normal of an edge vector, oriented along ``toward``."""
        nrm = np.array([edge[1], -edge[0]]) / np.hypot(edge[0], edge[1])
        return nrm if nrm @ toward > 0 else -nrm

    n_x = normal_between(ey, ex)  # faces between column neighbours: along the edge ey
    n_y = normal_between(ex, ey)  # faces between row neighbours: along the edge ex
    len_x = float(np.hypot(*ey))
    len_y = float(np.hypot(*ex))

    # faces in grid order (see Mesh): the x faces row by row, west to east, the map's west
    # and east sides included, then the y faces row by row, south to north
    # x face k of a row lies between cells k - 1 and k: (ny, nx + 1), its first cell the
    # west one but on the map's west side
    x_first = np.concatenate([idx[:, :1], idx], axis=1)
    x_second = np.concatenate([np.full((ny, 1), boundary["x_min"]), idx[:, 1:],
                               np.full((ny, 1), boundary["x_max"])], axis=1)
    x_step = np.full((ny, nx + 1), EAST, dtype=np.int8)
    x_step[:, 0] = WEST
    y_first = np.concatenate([idx[:1, :], idx], axis=0)  # (ny + 1, nx), as the x faces
    y_second = np.concatenate([np.full((1, nx), boundary["y_min"]), idx[1:, :],
                               np.full((1, nx), boundary["y_max"])], axis=0)
    y_step = np.full((ny + 1, nx), NORTH, dtype=np.int8)
    y_step[0, :] = SOUTH
    face_cells = np.ascontiguousarray(np.concatenate([
        np.stack([x_first.ravel(), x_second.ravel()], axis=1),
        np.stack([y_first.ravel(), y_second.ravel()], axis=1)]), dtype=np.int64)
    steps = np.concatenate([x_step.ravel(), y_step.ravel()])
    # a face's normal points from its first cell to its second: -n on the west and south sides
    face_normal = np.ascontiguousarray(np.concatenate([
        np.where((x_step.ravel() == WEST)[:, None], -n_x, n_x),
        np.where((y_step.ravel() == SOUTH)[:, None], -n_y, n_y)]))
    face_length = np.concatenate([np.full(x_step.size, len_x), np.full(y_step.size, len_y)])
    n = nx * ny
    return Mesh(
        cell_area=np.full(n, float(cell_area)),
        cell_perimeter=_perimeters(n, face_cells, face_length),
        face_cells=face_cells,
        face_normal=face_normal,
        face_length=face_length,
        shape=(ny, nx),
        face_direction=steps,
    )
