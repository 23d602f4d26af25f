"""Scalar summaries of a run: how far, how thick, how long, how well mass was kept.

Definitions (documented in the NetCDF attributes too):

- ``runout`` (m): on a profile, the downslope end, measured along the bed from the top of
  the profile, of the last cell whose final thickness exceeds ``runout_threshold``; on a
  grid, the largest horizontal distance from the release's centroid to a deposit cell.
- ``deposit_length`` (m): on a profile, from the upslope end of the first such cell to the
  downslope end of the last; on a grid, the extent of the deposit along the horizontal
  downslope direction of the bed (x when the bed is flat).
- ``deposit_max_thickness`` (m), ``deposit_volume`` (m^3; m^2 per metre of width on a
  profile: all material left on the mesh, film included).
- ``time_to_stop`` (s): first time the volume still moving (cells with u != 0 and h above
  the dry threshold) falls below ``stop_fraction`` of the released volume; NaN when the run
  reaches its end time first.
- ``mass_balance_error``: ``|V_end + V_out - V_0| / V_0`` (V_out: left through open faces).
- ``runout_truncated``: material above ``runout_threshold`` reached, at any time, the edge
  of what is modelled (a DEM's border or NODATA hole, an open side) below the lowest
  released cell, or left the map: the runout is a lower bound, enlarge the map.
- ``travel_length`` (m, horizontal), ``drop_height`` (m) and ``travel_angle`` (degrees, the
  Fahrboeschung ``atan(drop / length)``): from the highest released cell to the deposit cell
  (h > runout_threshold) farthest from it horizontally.
"""

from __future__ import annotations

import math

import numpy as np

from avflow.terrain.bed import Terrain
from avflow.terrain.mesh import OUTFLOW


def deposit_extent(terrain: Terrain, h: np.ndarray, threshold: float, h0: np.ndarray):
    """``(runout, deposit_length)`` of a final thickness field."""
    mask = h > threshold
    if not mask.any():
        return math.nan, 0.0
    if terrain.kind == "profile":
        idx = np.nonzero(mask)[0]
        half = 0.5 * terrain.dx
        runout = float(terrain.x[idx[-1]] + half)
        length = float(terrain.x[idx[-1]] - terrain.x[idx[0]] + 2 * half)
        return runout, length
    xx, yy = terrain.cell_xy()
    weights = h0 * terrain.mesh.cell_area
    cx, cy = np.average(xx, weights=weights), np.average(yy, weights=weights)
    runout = float(np.max(np.hypot(xx[mask] - cx, yy[mask] - cy)))
    # the deposit's extent along the direction the mass travelled (release centroid to
    # deposit centroid), or along x when it did not move
    dweights = h * terrain.mesh.cell_area
    travel = np.array([np.average(xx, weights=dweights) - cx,
                       np.average(yy, weights=dweights) - cy])
    norm = np.hypot(*travel)
    direction = travel / norm if norm > 1e-9 * max(terrain.dx, 1.0) else np.array([1.0, 0.0])
    along = xx[mask] * direction[0] + yy[mask] * direction[1]
    length = float(along.max() - along.min() + abs(terrain.dx * direction[0])
                   + abs(terrain.dy * direction[1]))
    return runout, length


def edge_cells(terrain: Terrain, walls_are_edges: bool) -> np.ndarray:
    """Cells with a face on the edge of what is modelled: every open (outflow) side, and the
    walls too when ``walls_are_edges`` (a DEM: its border and its NODATA holes are where the
    data end, not a wall of the terrain). A profile's or a plane's walls are the scene's
    own geometry (a channel end, the seed's closed profiles) and are not counted."""
    faces = terrain.mesh.face_cells
    j = faces[:, 1]
    edge = (j < 0) if walls_are_edges else (j == OUTFLOW)
    return np.unique(faces[edge, 0])


def runout_truncated(terrain: Terrain, peak_h: np.ndarray, threshold: float,
                     walls_are_edges: bool, outflow_volume: float, h0: np.ndarray) -> bool:
    """True when material above the runout threshold reached the edge of the map at any
    time (:func:`edge_cells`) below the lowest released cell, or left the map: the runout is
    then a lower bound. Contact higher up cannot cut a runout: a release drawn up to a DEM's
    border (avaHit's touches its NODATA edge) spreads along it without travelling."""
    cells = edge_cells(terrain, walls_are_edges)
    z = terrain.bed_elevation
    released = h0 > 0.0
    if released.any():
        cells = cells[z[cells] < z[released].min()]
    cells = np.setdiff1d(cells, uphill_edge_cells(terrain, walls_are_edges))
    return bool(outflow_volume > 0.0 or np.any(peak_h[cells] > threshold))


#: Gravity along the bed pointing into the map across an edge by more than this (/ g, about
#: a 15 degree slope falling away from the edge): a flow there runs away from that edge.
AWAY_FROM_EDGE = 0.25


def uphill_edge_cells(terrain: Terrain, walls_are_edges: bool) -> np.ndarray:
    """Edge cells (:func:`edge_cells`, grids) whose every edge face has the bed falling into
    the map: the top of a slope cut by the map's border. A flow touching the border there
    moves away from it, so the border does not cut its runout (a release drawn up to an
    oblique uphill edge wets edge cells lower than its lowest cell)."""
    if terrain.tangent_basis is None:
        return np.empty(0, dtype=np.int64)
    mesh = terrain.mesh
    faces = mesh.face_cells
    j = faces[:, 1]
    on_edge = np.flatnonzero((j < 0) if walls_are_edges else (j == OUTFLOW))
    cell = faces[on_edge, 0]
    e1, e2 = terrain.tangent_basis[cell, 0, :], terrain.tangent_basis[cell, 1, :]
    n = mesh.face_normal[on_edge]  # outward, in the cell's tangent basis
    outward = n[:, :1] * e1 + n[:, 1:] * e2
    gravity = terrain.gamma_x[cell, None] * e1 + terrain.gamma_y[cell, None] * e2
    into_map = np.einsum("ij,ij->i", outward, gravity) < -AWAY_FROM_EDGE
    # a cell is uphill-only when none of its edge faces lets gravity point out of the map
    cutting = np.unique(cell[~into_map])
    return np.setdiff1d(np.unique(cell), cutting)


def travel_angle(terrain: Terrain, h0: np.ndarray, h: np.ndarray, threshold: float):
    """``(travel_length, drop_height, travel_angle_deg)`` from the release top to the far end."""
    released, deposit = h0 > 0.0, h > threshold
    if not deposit.any():
        return math.nan, math.nan, math.nan
    if terrain.kind == "profile":
        xs, ys = terrain.x_horizontal, np.zeros_like(terrain.x_horizontal)
    else:
        xs, ys = terrain.cell_xy()
    z = terrain.bed_elevation
    top = np.flatnonzero(released)[np.argmax(z[released])]
    far = np.flatnonzero(deposit)
    dist = np.hypot(xs[far] - xs[top], ys[far] - ys[top])
    end = far[np.argmax(dist)]
    length, drop = float(dist.max()), float(z[top] - z[end])
    angle = math.degrees(math.atan2(drop, length)) if length > 0.0 else math.nan
    return length, drop, angle
