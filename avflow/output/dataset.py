"""A run as one CF-1.11 ``xarray.Dataset`` (profiles and square grids).

The variables and their attributes come from :mod:`avflow.output.cf`; triangle meshes go to
:mod:`avflow.output.ugrid`; files are written by :mod:`avflow.output.netcdf`, or, as the run
goes, by :mod:`avflow.output.stream` (which builds the same variables in two ``part`` s).
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from avflow.output.cf import (FIELDS, SUMMARIES, global_attributes, grid_mapping,
                              link_coordinates, per_width, registered_maps, run_bounds,
                              add_registered,
                              time_coords)
from avflow.output.fields import (cell_values, entrainment_variables, horizontal_basis,
                                  snapshot_fields)
from avflow.output.ugrid import to_ugrid_dataset
from avflow.simulation.runner import RunResult, flags_of, wet_cells
from avflow.output.xarray_dask import defer_dask_array

defer_dask_array()  # a run's Dataset is made without importing dask.array

#: The variables on (time, space), one value per cell and snapshot (``v`` not on profiles).
TIME_FIELDS = ("h", "u", "v", "flow_state")

#: ``part`` of :func:`to_dataset`: everything; the fields on (time, space) of the snapshots
#: given; everything but those fields (the snapshots' h, hu, hv and flags are not read).
PARTS = ("all", "fields", "rest")


#: Cells refreshed at once by :meth:`WindowedFields.update` (its temporaries: about fifteen
#: arrays of this many values, 30 MB)
REFRESH_CELLS = 1 << 18


class WindowedFields:
    """The fields of successive snapshots (:func:`snapshot_fields` of one snapshot), kept in
    arrays of the file's dtypes that are refreshed only where the flow is or was.

    ``first``: the fields of the first snapshot, already on the output grid (or the nodes),
    whose thickness per cell is ``h``; ``dtypes``: the dtype of each field in the file. Each
    :meth:`update` refreshes the window of cells that hold material now or did at the
    previous snapshot: the rows x columns bounding them on grids, the range of cells holding
    them on profiles and meshes. A cell whose h is +0.0 (bit for bit) has the fields of a
    dry cell whatever its hu and hv (h 0, u = v = 0 turned by its basis, flow_state 0): a
    cell outside the window held +0.0 then and holds it now, so its fields are unchanged.
    The cost is one pass over h (its bits) and the work on the window, not on the map; the
    values are those of :func:`snapshot_fields` of the whole map, cast to ``dtypes``, bit for
    bit (``tests/test_streamed_output.py``).
    """

    def __init__(self, terrain, h, first: dict, dtypes: dict):
        self.values = {name: np.array(v, dtype=dtypes[name]) for name, v in first.items()}
        self.grid = terrain.kind == "grid"
        self.cell_index = terrain.cell_index if self.grid else None
        basis = horizontal_basis(terrain)
        self.basis = None if basis is None else tuple(np.ascontiguousarray(e) for e in basis)
        if self.grid:
            self.shape = terrain.grid_shape
            if self.cell_index is not None:  # cell of each place, -1 outside the DEM
                cellmap = np.full(int(np.prod(self.shape)), -1, dtype=np.int64)
                cellmap[self.cell_index] = np.arange(self.cell_index.size)
                self.cellmap = cellmap.reshape(self.shape)
        self.box = self.wet_box(h)
        #: the windows refreshed, (rows, columns) or (cells,) each (what the tests look at)
        self.windows: list[tuple] = []

    def wet_box(self, h, cells=None):
        """(row0, row1, col0, col1) on grids, (cell0, cell1) elsewhere (ends excluded)
        bounding the cells whose h is not +0.0 (``cells``, :func:`wet_cells` of h if
        known); None when there are none."""
        cells = wet_cells(h) if cells is None else cells
        if not cells.size:
            return None
        if not self.grid:
            return int(cells[0]), int(cells[-1]) + 1
        places = cells if self.cell_index is None else self.cell_index[cells]
        rows, cols = np.divmod(places, self.shape[1])
        return int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1

    def update(self, h, hu, hv, wet=None) -> dict:
        """The fields of the snapshot with these per-cell h, hu, hv (the arrays kept, on the
        output grid: valid until the next update); ``wet``: :func:`wet_cells` of h if known.

        The window is refreshed in pieces of about :data:`REFRESH_CELLS` cells (rows of it
        on grids): the temporaries of a piece (some fifteen arrays) then stay small, where a
        window covering a 1 m DEM's flow made them 0.5 GiB at once."""
        box = self.wet_box(h, wet)
        window = _union(self.box, box)
        self.box = box
        if window is None:  # dry then and now
            self.windows.append(())
            return self.values
        if not self.grid:  # a range of cells, the same range of the output
            self.windows.append((window[1] - window[0],))
            for a in range(window[0], window[1], REFRESH_CELLS):
                block = slice(a, min(a + REFRESH_CELLS, window[1]))
                self._refresh(block, block, block, h, hu, hv)
            return self.values
        r0, r1, c0, c1 = window
        self.windows.append((r1 - r0, c1 - c0))
        rows = max(1, REFRESH_CELLS // (c1 - c0))
        for a in range(r0, r1, rows):
            block = (slice(a, min(a + rows, r1)), slice(c0, c1))
            if self.cell_index is None:  # the places are the cells, row by row
                inside = cells = None
            else:  # the piece's places that hold a cell
                cm = self.cellmap[block]
                inside = cm >= 0
                cells = cm[inside]
            self._refresh(block, inside, cells, h, hu, hv)
        return self.values

    def _refresh(self, block, inside, cells, h, hu, hv) -> None:
        """The fields of one piece of the window: ``block`` of the output, whose ``inside``
        places hold the ``cells`` (None: the places are the cells; slices on profiles)."""

        def take(a):
            a = np.asarray(a)
            return a.reshape(self.shape)[block] if cells is None else a[cells]

        h, hu, hv = take(h), take(hu), take(hv)
        basis = None if self.basis is None else tuple(take(e) for e in self.basis)
        for name, v in cell_values(h, hu, hv, flags_of(h, hu, hv), basis).items():
            if inside is None or isinstance(inside, slice):
                self.values[name][block] = v
            else:
                self.values[name][block][inside] = v


def _union(a, b):
    """The box bounding boxes a and b (None: empty)."""
    if a is None or b is None:
        return b if a is None else a
    return tuple(min(x, y) if k % 2 == 0 else max(x, y) for k, (x, y) in enumerate(zip(a, b)))


def to_dataset(result: RunResult, part: str = "all") -> xr.Dataset:
    """The CF Dataset of a run (profiles on (time, x), grids on (time, y, x)).

    ``part`` (see :data:`PARTS`): ``"all"``; ``"fields"``: only the fields on (time, space)
    of ``result.snapshots`` (:data:`TIME_FIELDS`; and on triangle meshes the mesh variables
    before them), with the space coordinates but no time coordinate (``result`` needs only
    ``terrain`` and ``snapshots``); ``"rest"``: every other variable, from the snapshots'
    times and series and the final state. A streamed file (:mod:`avflow.output.stream`)
    writes the first at every output time and the second at the end.
    """
    if part not in PARTS:
        raise ValueError(f"part must be one of {PARTS}, got {part!r}")
    terrain, snaps = result.terrain, result.snapshots
    if part != "fields":  # the headline runout: along the path, at the pressure limit
        from avflow.output.path import headline_runout

        headline_runout(result)
    if terrain.kind == "triangles":  # fields on the nodes of a UGRID mesh
        return to_ugrid_dataset(result, part)
    profile = terrain.kind == "profile"
    space = ("x",) if profile else ("y", "x")

    def grid(values):
        """Per-cell values on the output grid; NaN outside the DEM."""
        return terrain.to_grid(np.asarray(values))

    coords = {}
    if part != "fields":
        times = np.asarray(snaps.time, dtype=float)
        coords = time_coords(times, result.scenario.output.release_time)
    if profile:
        # The profile unrolled along the bed is the X axis of its own frame: CF names a
        # metric X axis that is not a longitude projection_x_coordinate (as on grids).
        coords["x"] = ("x", terrain.x, {
            "standard_name": "projection_x_coordinate",
            "long_name": "distance along the bed from the top of the profile", "units": "m",
            "axis": "X"})
        coords["x_horizontal"] = ("x", terrain.x_horizontal, {
            "long_name": "horizontal distance from the top of the profile", "units": "m"})
    else:
        coords["x"] = ("x", terrain.x, {"standard_name": "projection_x_coordinate",
                                        "long_name": "x coordinate of cell centre",
                                        "units": "m", "axis": "X"})
        coords["y"] = ("y", terrain.y, {"standard_name": "projection_y_coordinate",
                                        "long_name": "y coordinate of cell centre",
                                        "units": "m", "axis": "Y"})

    def attrs(name):
        return {k: v for k, v in FIELDS[name].items() if k not in ("kind", "grid_only")}

    data = {}
    if part != "rest":
        fields = snapshot_fields(terrain, np.stack(snaps.h), np.stack(snaps.hu),
                                 np.stack(snaps.hv), np.stack(snaps.flag))
        for name in TIME_FIELDS:
            if name in fields:
                data[name] = (("time", *space), fields[name], attrs(name))
        data["flow_state"][2]["_FillValue"] = -1
    if part != "fields":
        state = result.state
        data["peak_thickness"] = (space, grid(state.peak_h), attrs("peak_thickness"))
        data["peak_speed"] = (space, grid(state.peak_speed), attrs("peak_speed"))
        data["deposit_thickness"] = (space, grid(state.h), attrs("deposit_thickness"))
        density = result.scenario.physics.density
        data["peak_pressure"] = (space, grid(density * state.peak_speed**2),
                                 attrs("peak_pressure"))
        data["arrival_time"] = (space, grid(state.arrival), attrs("arrival_time"))
        at_rest = (state.h > 0.0) & (state.hu == 0.0) & (state.hv == 0.0)
        data["rest_time"] = (space, grid(np.where(at_rest, state.last_moved, np.nan)),
                             attrs("rest_time"))
        com = np.asarray(snaps.center_of_mass, dtype=float)
        for k, axis in enumerate("xyz"):
            data[f"center_of_mass_{axis}"] = ("time", com[:, k],
                                              attrs(f"center_of_mass_{axis}"))
        data["bed_elevation"] = (space, grid(terrain.bed_elevation), attrs("bed_elevation"))
        data["slope_angle"] = (space, grid(terrain.slope_deg), attrs("slope_angle"))
        data["moving_volume"] = ("time", np.asarray(snaps.moving_volume),
                                 {**attrs("moving_volume"),
                                  "units": per_width("m3", profile)})
        if "structures" in terrain.extras:
            from avflow.output.structures import structure_variables

            data.update(structure_variables(result, space))
        for name, (values, is_map) in entrainment_variables(result).items():
            data[name] = ((space if is_map else "time"), grid(values) if is_map else values,
                          {**attrs(name), "units": attrs(name)["units"] if is_map
                           else per_width("m3", profile)})
    crs_attrs = None if profile else grid_mapping(terrain.crs_wkt)
    if crs_attrs:  # CF 5.6: every map names the CRS; GDAL reads crs_wkt / spatial_ref
        for name, (dims, _, attributes) in list(data.items()):
            if dims[-2:] == ("y", "x"):
                attributes["grid_mapping"] = "crs"
        if part != "fields":  # a data variable: see link_coordinates
            data["crs"] = ((), np.int32(0), {"long_name": "coordinate reference system",
                                              **crs_attrs})
    if part != "fields":
        data.update(run_bounds(times))
        s = result.summary
        for name, (units, description) in SUMMARIES.items():
            if name not in s:  # (a summary of some runs only: supplied_volume)
                continue
            data[name] = ((), float(s[name]), {"long_name": name.replace("_", " "),
                                                "units": per_width(units, profile),
                                                "comment": description})
    if part != "fields":  # last: a name the file uses already is refused, never written over
        for name, (values, attributes) in registered_maps(result.state).items():
            add_registered(data, coords, name, (space, grid(values), attributes))
    ds = xr.Dataset(data, coords=coords)
    link_coordinates(ds)
    if part != "fields":
        ds.attrs = global_attributes(result)
        # what commands reading this file (plot, export, path) must never write over
        ds.attrs["input_files"] = "\n".join(result.scenario.input_files())
    return ds
