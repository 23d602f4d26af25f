"""The fields of a snapshot on the output's grid or mesh nodes: h, u (v) in the map's axes
and flow_state, from the state per cell (what every output builds its fields from)."""

from __future__ import annotations

import numpy as np


def snapshot_fields(terrain, h, hu, hv, flag) -> dict:
    """h, u (v) and flow_state of snapshots: per-cell arrays ``(..., cells)`` -> arrays on the
    output grid ``(..., [y,] x)`` (NaN outside a DEM, flow_state -1), or on the nodes of a
    triangle mesh. One snapshot ``(cells,)`` or a stack ``(time, cells)`` give the same values.
    """
    values = cell_values(np.asarray(h), hu, hv, flag, horizontal_basis(terrain))
    if terrain.kind == "triangles":  # fields on the nodes of a UGRID mesh, no grid
        return values
    return {name: terrain.to_grid(v, fill=-1).astype(np.int8) if name == "flow_state"
            else terrain.to_grid(v) for name, v in values.items()}


def horizontal_basis(terrain):
    """(e1_x, e2_x, e1_y, e2_y) per cell: the horizontal components of the cells' tangent
    basis, which turn (u, v) along the bed into the output's u and v; None on profiles."""
    if terrain.kind == "profile":
        return None
    e1, e2 = terrain.tangent_basis[:, 0, :], terrain.tangent_basis[:, 1, :]
    return e1[:, 0], e2[:, 0], e1[:, 1], e2[:, 1]


def cell_values(h, hu, hv, flag, basis) -> dict:
    """h, u (v) and flow_state per cell, before any grid: the arithmetic of
    :func:`snapshot_fields` and :class:`WindowedFields` (one, so both give the same bits).
    ``basis``: :func:`horizontal_basis` of those cells, or None on profiles (u along the bed)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        ua = np.where(h > 0, np.asarray(hu) / h, 0.0)
        va = np.where(h > 0, np.asarray(hv) / h, 0.0)
    flags = np.asarray(flag).astype(np.int8)
    if basis is None:
        return {"h": h, "u": ua, "flow_state": flags}
    # Velocity along the bed, as the components of its horizontal projection.
    e1x, e2x, e1y, e2y = basis
    return {"h": h, "u": ua * e1x + va * e2x, "v": ua * e1y + va * e2y, "flow_state": flags}


def entrainment_variables(result) -> dict:
    """``{name: (values per cell or per snapshot, is_map)}`` of a run with entrainment
    (empty without): the layer left at the end, the bed's change (final minus initial
    layer, <= 0) and the volume entrained at each snapshot."""
    source = getattr(result.solver, "source", None)
    if source is None:
        return {}
    state = result.state
    return {"erodible_depth": (state.erodible, True),
            "bed_change": (state.erodible - source.erodible, True),
            "entrained_volume_series": (np.asarray(result.snapshots.entrained_volume,
                                                   dtype=float), False)}
