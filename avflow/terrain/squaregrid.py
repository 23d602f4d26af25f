"""A square grid's faces laid out by row and column: what the structured kernel sweeps.

The face kernel (:func:`avflow.numerics.kernels.step_faces`) reads any mesh through per-face
index arrays. On a square grid (a plane or a DEM, :mod:`avflow.terrain.bed`) the same faces
have a place in the grid: the x face ``(r, k)`` lies between cells ``(r, k - 1)`` and
``(r, k)`` (``k = 0 .. nx``), the y face ``(k, c)`` between cells ``(k - 1, c)`` and ``(k, c)``
(``k = 0 .. ny``). :class:`SquareGrid` holds, for each of those places, what the face kernel
holds for the face (its frame as seen from each side and its length) and a code saying which
cell owns it, so the structured kernel (:mod:`avflow.numerics.square_grid`) computes every
face with the same arithmetic and needs no index array.

It also holds, per cell, the order in which the face kernel adds its four faces (the order of
their indices in the mesh): floating-point sums depend on the order, and with it the two
kernels agree bit for bit. Cells outside the DEM (NODATA) are part of the layout, never wet,
with no face of their own (their neighbours see walls or open sides, as in the mesh).

Built once per solver, outside the time loop, from :class:`~avflow.terrain.bed.Terrain`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from avflow.terrain.mesh import EAST, NORTH, OUTFLOW, SOUTH, WEST

# Face codes: who owns the face (the first cell of the face kernel, "i") and what is beyond.
NO_FACE = 0  #: between two cells outside the DEM
INNER = 1  #: i is the west (south) cell, j the east (north) one
LOW_WALL = 2  #: i is the west (south) cell; beyond it a wall
LOW_OPEN = 3  #: i is the west (south) cell; beyond it an open side
HIGH_WALL = 4  #: i is the east (north) cell, the face its west (south) side; a wall
HIGH_OPEN = 5  #: as HIGH_WALL, open
KIND = 7  #: the bits of a face code that hold the kinds above
#: A face code's sign bits: each side's frame is a rotation, rows ``n`` and ``t = s (-n_y,
#: n_x)``; the bit is set where s = -1 (side 0: the face's first cell, side 1: the second)
SIGN0 = 8
SIGN1 = 16

#: Per-cell order code of the four faces when they come West, East, South, North: two bits
#: per term, first term in the lowest bits (see :func:`order_code`).
CANONICAL_ORDER = 0 | (1 << 2) | (2 << 4) | (3 << 6)


def order_code(sides) -> int:
    """The code of an order of the four sides (0 W, 1 E, 2 S, 3 N), first side first."""
    return sum(int(s) << (2 * k) for k, s in enumerate(sides))


@dataclass(frozen=True)
class SquareGrid:
    """Faces of a square grid by place, and per-cell data on the full ``ny x nx`` grid."""

    ny: int
    nx: int
    #: (n_cells,) int64: each mesh cell's place ``r * nx + c`` on the full grid
    place: np.ndarray
    #: (ny * nx,) uint8: 1 where the grid has a cell (0: outside the DEM)
    valid: np.ndarray
    #: (ny * nx,) uint8: the order code of each cell's faces (:data:`CANONICAL_ORDER` mostly)
    face_order: np.ndarray
    x_code: np.ndarray  #: (ny, nx + 1) int8 face codes
    #: (ny, 4, nx + 1): the face normal seen from each side ``(n0x, n0y, n1x, n1y)`` (the
    #: face kernel's frame rows 0; rows 1, the tangents, follow from n and the sign bits),
    #: one contiguous line per component and row: the kernel's face loops vectorise on it
    x_frame: np.ndarray
    x_length: np.ndarray  #: (ny, nx + 1) m
    y_code: np.ndarray  #: (ny + 1, nx) int8
    y_frame: np.ndarray  #: (ny + 1, 4, nx)
    y_length: np.ndarray  #: (ny + 1, nx) m

    @property
    def n_places(self) -> int:
        return self.ny * self.nx

    @property
    def compact(self) -> bool:
        """True when every place holds a cell in mesh order (no NODATA): per-cell arrays of
        the mesh are the grid's arrays as they are, no copy needed."""
        return self.place.size == self.n_places

    def full(self, values: np.ndarray, fill=0.0) -> np.ndarray:
        """Per-cell values (n_cells, ...) on the full grid (ny * nx, ...), ``fill`` outside."""
        values = np.asarray(values)
        if self.compact:
            return np.ascontiguousarray(values)
        out = np.full((self.n_places,) + values.shape[1:], fill, dtype=values.dtype)
        out[self.place] = values
        return out


def square_grid(terrain) -> SquareGrid | None:
    """The layout of a square-grid terrain (a plane or a DEM); None for any other mesh."""
    mesh = terrain.mesh
    if terrain.kind != "grid" or mesh.face_direction is None:
        return None
    ny, nx = terrain.grid_shape
    n = mesh.n_cells
    place = (np.arange(n, dtype=np.int64) if terrain.cell_index is None
             else np.asarray(terrain.cell_index, dtype=np.int64))
    row, col = place // nx, place % nx
    fc, step = mesh.face_cells, mesh.face_direction
    i, j = fc[:, 0], fc[:, 1]
    ri, ci = row[i], col[i]
    x_code = np.zeros((ny, nx + 1), dtype=np.int8)
    y_code = np.zeros((ny + 1, nx), dtype=np.int8)
    x_frame = np.zeros((ny, 4, nx + 1))
    y_frame = np.zeros((ny + 1, 4, nx))
    x_length = np.zeros((ny, nx + 1))
    y_length = np.zeros((ny + 1, nx))
    # face index of each cell's W, E, S, N side (every cell has four faces)
    sides = np.full((n, 4), -1, dtype=np.int64)
    # each side's frame as its normal and the sign of its tangent, t = s (-n_y, n_x), exactly
    frame = mesh.face_frame
    normals = np.ascontiguousarray(frame[:, :, 0, :].reshape(-1, 4))
    sign = np.where(frame[:, :, 1, 1] * frame[:, :, 0, 0] - frame[:, :, 1, 0] * frame[:, :, 0, 1]
                    >= 0.0, 1.0, -1.0)  # (n_faces, 2)
    rebuilt = sign[:, :, None] * np.stack([-frame[:, :, 0, 1], frame[:, :, 0, 0]], axis=-1)
    if not np.array_equal(rebuilt, frame[:, :, 1, :]):
        return None  # frames that are not rotations: the face kernel runs this mesh
    sign_bits = (np.where(sign[:, 0] < 0, SIGN0, 0) | np.where(sign[:, 1] < 0, SIGN1, 0))
    inner = j >= 0
    open_side = j == OUTFLOW
    if np.any(inner & ((step == WEST) | (step == SOUTH))):
        raise ValueError("a face between two cells must point east or north")
    for direction, codes, frames, lengths, (dr, dc), own, other in (
            (EAST, x_code, x_frame, x_length, (0, 1), 1, 0),
            (WEST, x_code, x_frame, x_length, (0, 0), 0, None),
            (NORTH, y_code, y_frame, y_length, (1, 0), 3, 2),
            (SOUTH, y_code, y_frame, y_length, (0, 0), 2, None)):
        f = np.flatnonzero(step == direction)
        r, c = ri[f] + dr, ci[f] + dc
        low = direction in (EAST, NORTH)
        code = np.where(inner[f], INNER,
                        np.where(open_side[f], LOW_OPEN if low else HIGH_OPEN,
                                 LOW_WALL if low else HIGH_WALL))
        if np.any(codes[r, c] != NO_FACE):
            raise ValueError("two faces share one place of the grid")
        codes[r, c] = code | sign_bits[f]
        frames[r, :, c] = normals[f]  # (len(f), 4): the advanced indices come first
        lengths[r, c] = mesh.face_length[f]
        sides[i[f], own] = f
        if other is not None:
            sides[j[f[inner[f]]], other] = f[inner[f]]
    if np.any(sides < 0):
        raise ValueError("a cell of the grid does not have four faces")
    ranked = np.argsort(sides, axis=1, kind="stable")
    face_order = np.zeros(ny * nx, dtype=np.uint8)
    face_order[place] = (ranked[:, 0] | (ranked[:, 1] << 2) | (ranked[:, 2] << 4)
                         | (ranked[:, 3] << 6)).astype(np.uint8)
    valid = np.zeros(ny * nx, dtype=np.uint8)
    valid[place] = 1
    return SquareGrid(ny=ny, nx=nx, place=place, valid=valid, face_order=face_order,
                      x_code=x_code, x_frame=x_frame, x_length=x_length,
                      y_code=y_code, y_frame=y_frame, y_length=y_length)
