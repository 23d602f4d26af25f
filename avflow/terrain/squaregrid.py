"""A square grid's faces laid out by row and column: what the structured kernel sweeps.

The face kernel (:func:`avflow.numerics.kernels.step_faces`) reads any mesh through per-face
index arrays. On a square grid (a plane or a DEM, :mod:`avflow.terrain.bed`) the same faces
have a place in the grid: the x face ``(r, k)`` lies between cells ``(r, k - 1)`` and
``(r, k)`` (``k = 0 .. nx``), the y face ``(k, c)`` between cells ``(k - 1, c)`` and ``(k, c)``
(``k = 0 .. ny``). :class:`SquareGrid` holds, for each of those places, what the face kernel
holds for the face (its frame as seen from each side and its length) and a code saying which
cell owns it, so the structured kernel (:mod:`avflow.numerics.square_grid`) computes every
face with the same arithmetic and needs no index array.

Floating-point sums depend on their order: the face kernel adds a cell's faces in the order
of their indices, and a square grid's mesh numbers them in grid order (:mod:`avflow.terrain.mesh`),
so that every cell's come W, E, S, N; the structured kernel adds them in that order, and the
two kernels agree bit for bit. A mesh whose faces are in another order is not laid out (the
face kernel runs it). Cells outside the DEM (NODATA) are part of the layout, never wet,
with no face of their own (their neighbours see walls or open sides, as in the mesh).

Built once per solver, outside the time loop, from :class:`~avflow.terrain.bed.Terrain`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from avflow.terrain.mesh import EAST, NORTH, OUTFLOW, WEST

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

@dataclass(frozen=True)
class SquareGrid:
    """Faces of a square grid by place, and per-cell data on the full ``ny x nx`` grid."""

    ny: int
    nx: int
    #: (n_cells,) int64: each mesh cell's place ``r * nx + c`` on the full grid
    place: np.ndarray
    #: (ny * nx,) uint8: 1 where the grid has a cell (0: outside the DEM)
    valid: np.ndarray
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
    x_code = np.zeros((ny, nx + 1), dtype=np.int8)
    y_code = np.zeros((ny + 1, nx), dtype=np.int8)
    x_frame = np.zeros((ny, 4, nx + 1))
    y_frame = np.zeros((ny + 1, 4, nx))
    x_length = np.zeros((ny, nx + 1))
    y_length = np.zeros((ny + 1, nx))
    status = _lay_out(place, nx, mesh.face_cells, mesh.face_direction, mesh.face_frame,
                      mesh.face_length, x_code, y_code, x_frame, y_frame, x_length, y_length,
                      EAST, WEST, NORTH, OUTFLOW)
    if status == _NOT_ROTATIONS or status == _NOT_GRID_ORDER:
        return None  # the face kernel runs this mesh
    if status != _LAID_OUT:
        raise ValueError(_LAYOUT_ERRORS[status])
    valid = np.zeros(ny * nx, dtype=np.uint8)
    valid[place] = 1
    return SquareGrid(ny=ny, nx=nx, place=place, valid=valid,
                      x_code=x_code, x_frame=x_frame, x_length=x_length,
                      y_code=y_code, y_frame=y_frame, y_length=y_length)


# What _lay_out found (0: the layout is made)
_LAID_OUT, _NOT_ROTATIONS, _NOT_GRID_ORDER, _TWO_FACES, _INNER_BACKWARD, _MISSING_SIDE = range(6)
_LAYOUT_ERRORS = {
    _TWO_FACES: "two faces share one place of the grid",
    _INNER_BACKWARD: "a face between two cells must point east or north",
    _MISSING_SIDE: "a cell of the grid does not have four faces",
}


@numba.njit(cache=True, nogil=True)
def _lay_out(place, nx, face_cells, face_direction, face_frame, face_length,
             x_code, y_code, x_frame, y_frame, x_length, y_length, east, west, north, outflow):
    """Fill the layout's arrays from the mesh's faces, one pass over them; returns a status
    (:data:`_LAID_OUT` or what is wrong). One loop, not numpy passes over the face arrays:
    the layout of a 179k-cell map took 38 ms in numpy, as long as the run's time loop.

    A face ``f`` from cell ``i`` to ``j`` (or a wall, an open side) in direction ``d`` lies on
    the x face ``(r, c + 1)`` (east), ``(r, c)`` (west), or the y face ``(r + 1, c)`` (north),
    ``(r, c)`` (south) of ``i = (r, c)``. Its frame seen from each side is a rotation, rows
    ``n`` and ``t = s (-n_y, n_x)`` exactly (else the face kernel runs the mesh); the sign
    bits keep ``s``. Every cell's faces must have indices in the order W < E < S < N (grid
    order, :mod:`avflow.terrain.mesh`), the order in which the face kernel adds them:
    :data:`_NOT_GRID_ORDER` else.

    The mesh's codes (``east``, ``west``, ``north``, ``outflow``) come as arguments: Numba
    caches this function against this file alone, and would keep constants of mesh.py
    frozen after a change there (see :mod:`avflow.numerics`)."""
    n_cells = place.size
    sides = np.full((n_cells, 4), -1, dtype=np.int64)  # face of each cell's W, E, S, N side
    n_faces = face_cells.shape[0]
    sign_bits = np.zeros(n_faces, dtype=np.int8)
    for f in range(n_faces):  # all frames first: any that is not a rotation, no layout
        for side in range(2):
            n_x, n_y = face_frame[f, side, 0, 0], face_frame[f, side, 0, 1]
            t_x, t_y = face_frame[f, side, 1, 0], face_frame[f, side, 1, 1]
            s = 1.0 if t_y * n_x - t_x * n_y >= 0.0 else -1.0
            if not (s * -n_y == t_x and s * n_x == t_y):
                return _NOT_ROTATIONS
            if s < 0.0:
                sign_bits[f] |= SIGN0 if side == 0 else SIGN1
    for f in range(n_faces):
        bits = sign_bits[f]
        i, j = face_cells[f, 0], face_cells[f, 1]
        d = face_direction[f]
        r, c = place[i] // nx, place[i] % nx
        low = d == east or d == north
        if j >= 0:
            if not low:
                return _INNER_BACKWARD
            kind = INNER
        elif j == outflow:
            kind = LOW_OPEN if low else HIGH_OPEN
        else:
            kind = LOW_WALL if low else HIGH_WALL
        if d == east:
            c += 1
        elif d == north:
            r += 1
        x_side = d == east or d == west
        codes = x_code if x_side else y_code
        frames = x_frame if x_side else y_frame
        if codes[r, c] != NO_FACE:
            return _TWO_FACES
        codes[r, c] = kind | bits
        frames[r, 0, c] = face_frame[f, 0, 0, 0]
        frames[r, 1, c] = face_frame[f, 0, 0, 1]
        frames[r, 2, c] = face_frame[f, 1, 0, 0]
        frames[r, 3, c] = face_frame[f, 1, 0, 1]
        if x_side:
            x_length[r, c] = face_length[f]
        else:
            y_length[r, c] = face_length[f]
        own = 1 if d == east else 0 if d == west else 3 if d == north else 2
        sides[i, own] = f
        if j >= 0:
            sides[j, own - 1] = f  # the cell beyond sees it as its W (S) side
    for i in range(n_cells):
        for side in range(4):
            if sides[i, side] < 0:
                return _MISSING_SIDE
        if not sides[i, 0] < sides[i, 1] < sides[i, 2] < sides[i, 3]:
            return _NOT_GRID_ORDER
    return _LAID_OUT
