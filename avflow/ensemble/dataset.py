"""``OUTDIR/ensemble.nc``: the members of an ensemble as one CF-1.11 Dataset.

Dimensions: ``realization`` (standard_name ``realization``, one per member, in member order),
and for the maps the member grid (``x`` on profiles, ``y, x`` on 2D grids) and ``threshold``.

- the varied parameters are auxiliary coordinates along ``realization`` (``law`` is a string
  coordinate; a field that a member's law does not have is NaN);
- ``status`` and ``error`` (strings) and the summaries (float64, with units) per member;
- when every member that produced a file has the same grid: ``peak_thickness`` and
  ``deposit_thickness`` stacked along ``realization`` (NaN for failed members), and the
  exceedance probabilities over the successful members for every threshold of the
  ensemble file: ``peak_thickness_exceedance_probability(threshold, ...)`` (default 0.1,
  1 and 5 m), ``peak_speed_exceedance_probability(speed_threshold, ...)`` (1, 5, 10 m/s)
  and ``peak_pressure_exceedance_probability(pressure_threshold, ...)`` (the base
  scenario's pressure classes, kPa; default 1, 3 and 30);
- on a DEM with a CRS, the members' grid-mapping variable ``crs``, named by every map's
  ``grid_mapping`` (as in a run file): GDAL, QGIS and ``avflow export`` read it.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import xarray as xr

from avflow import __version__
from avflow.ensemble.spec import Ensemble
from avflow.output.cf import SEED_REFERENCE, SUMMARIES, per_width
from avflow.files import atomic_write
from avflow.ensemble.spec import OK_STATUSES, SUMMARY_FIELDS, THRESHOLD_UNITS

#: Units of scenario fields by their last name (varied-parameter coordinates).
FIELD_UNITS = {
    "delta_deg": "degree", "delta1_deg": "degree", "delta2_deg": "degree",
    "theta_deg": "degree", "theta0_deg": "degree", "slope_deg": "degree",
    "azimuth_deg": "degree", "d": "m", "a": "m", "length": "m", "dx": "m", "dy": "m",
    "center": "m", "half_length": "m", "max_thickness": "m", "thickness": "m",
    "position": "m", "radius": "m", "runout_threshold": "m", "dry_threshold": "m",
    "elevation_at_center": "m", "xi": "m s-2", "gravity": "m s-2", "density": "kg m-3",
    "mu": "1", "beta": "1", "volume_factor": "1", "cfl": "1", "stop_fraction": "1",
    "end": "s", "every": "s", "tau0": "Pa", "Rs0": "1", "kappa": "1", "R": "m", "B": "1",
}

MAPS = ("peak_thickness", "deposit_thickness")
#: Maps read from the members for their exceedance probabilities only (not stacked).
PROBABILITY_ONLY = ("peak_speed", "peak_pressure")
#: Dimension of each map's thresholds, and the factor from threshold units to map units.
THRESHOLD_DIMS = {"peak_thickness": ("threshold", 1.0), "peak_speed": ("speed_threshold", 1.0),
                  "peak_pressure": ("pressure_threshold", 1000.0)}


def coordinate_name(dotted: str) -> str:
    """``rheology.delta_deg`` -> ``rheology_delta_deg``; the law is just ``law``."""
    return "law" if dotted == "rheology.law" else dotted.replace(".", "_")


def ensemble_dataset(ensemble: Ensemble, table, outdir: str | os.PathLike,
                     maps: MemberMaps | None = None) -> xr.Dataset:
    """The ensemble Dataset from the member table (:func:`avflow.ensemble.orchestrate.member_table`).

    ``maps``: the member maps read so far (:class:`MemberMaps`, filled as members finish);
    the member files it has not read yet are read here.
    """
    outdir = Path(outdir)
    n = len(ensemble.members)
    profile = ensemble.base.terrain.kind == "profile"
    coords: dict = {
        "realization": ("realization", np.arange(n, dtype=np.int32), {
            "standard_name": "realization", "long_name": "ensemble member number",
            "units": "1"}),
        "scenario_hash": ("realization", table["scenario_hash"].astype(str).to_numpy(object), {
            "long_name": "scenario hash of the member (name of its file in members/)"}),
    }
    for dotted, values in ensemble.parameters().items():
        name = coordinate_name(dotted)
        attrs = {"long_name": f"scenario field {dotted}"}
        if all(v is None or isinstance(v, str) for v in values):
            coords[name] = ("realization", np.array(["" if v is None else v for v in values],
                                                    dtype=object), attrs)
        elif all(v is None or (isinstance(v, (int, float)) and not isinstance(v, bool))
                 for v in values):
            units = FIELD_UNITS.get(dotted.rsplit(".", 1)[-1])
            if units:
                attrs["units"] = units
            coords[name] = ("realization",
                            np.array([math.nan if v is None else float(v) for v in values]),
                            attrs)
        else:  # lists, booleans: as JSON text
            coords[name] = ("realization", np.array([json.dumps(v) for v in values],
                                                    dtype=object), attrs)
    coords["law"][2]["long_name"] = "basal friction law (rheology.law)"

    data: dict = {
        "status": ("realization", table["status"].astype(str).to_numpy(object), {
            "long_name": "end state of the member run",
            "comment": "at_rest, ended_by_rule (stop rule, mass still moving) or completed "
                       "(time.end, still moving): success; failed: raised (see error); "
                       "max_steps: step bound reached"}),
        "error": ("realization", table["error"].fillna("").astype(str).to_numpy(object), {
            "long_name": "error message of a failed member (empty when it succeeded)"}),
    }
    for name in SUMMARY_FIELDS:
        units, description = SUMMARIES[name]
        data[name] = ("realization", table[name].to_numpy(float), {
            "long_name": name.replace("_", " "), "units": per_width(units, profile),
            "comment": description})
    if "runout_truncated" in table:
        data["runout_truncated"] = ("realization",
                                    table["runout_truncated"].fillna(-1).to_numpy(np.int8), {
            "long_name": "deposit reaches the edge of the domain (runout is a lower bound)",
            "flag_values": np.array([0, 1], np.int8), "flag_meanings": "inside truncated",
            "_FillValue": np.int8(-1)})
    data["member_time"] = ("realization", table["member_time"].to_numpy(float), {
        "long_name": "wall-clock time of the member task (read, run, write)", "units": "s",
        "comment": "reused members keep the time of the run that made them (from the "
                   "summary.csv of that run; NaN where it is gone)"})

    ok = table["status"].isin(OK_STATUSES).to_numpy()
    maps, grid_coords, note, crs = _stacked_maps(ensemble, table, outdir, profile, maps)
    if maps is not None:
        coords.update(grid_coords)
        space = ("x",) if profile else ("y", "x")
        data["peak_thickness"] = (("realization", *space), maps["peak_thickness"], {
            "long_name": "maximum flow thickness over the member run", "units": "m",
            "comment": "measured normal to the bed; NaN for failed members"})
        data["deposit_thickness"] = (("realization", *space), maps["deposit_thickness"], {
            "long_name": "thickness at the end of the member run", "units": "m",
            "comment": "measured normal to the bed; NaN for failed members"})
        _probabilities(ensemble, maps, ok, space, coords, data)
        if crs is not None:  # a data variable, as in a run file (no crs = 0 in plot titles)
            for name, (dims, _, attributes) in data.items():
                if tuple(dims[-2:]) == ("y", "x"):
                    attributes["grid_mapping"] = "crs"
            data["crs"] = ((), np.int32(0), crs)
    ds = xr.Dataset(data, coords=coords)
    failed = int((~ok).sum())
    ds.attrs = {
        "Conventions": "CF-1.11",
        "title": f"avflow ensemble {ensemble.name}",
        "source": f"avflow {__version__}: kinetic scheme with Dirac stopping, one run per member",
        "references": SEED_REFERENCE,
        "history": "created by avflow " + __version__,
        "ensemble_name": ensemble.name,
        "ensemble": ensemble.text,
        "ensemble_file": ensemble.path or "",
        "input_files": "\n".join(str(p) for p in _input_files(ensemble)),
        "base_scenario": ensemble.base.source_text,
        "base_scenario_hash": ensemble.base.scenario_hash(),
        "varied": " ".join(ensemble.varied),
        "members": n,
        "failed_members": failed,
        "scene": "profile" if profile else "grid",
        "maps": note,
        "avflow_version": __version__,
        "comment": ("one member per realization; each member's full output is "
                    "members/<scenario_hash>.nc next to this file"),
    }
    if ensemble.sample.get("calibration"):  # a forecast: the calibration it samples
        ds.attrs.update(calibration_file=ensemble.sample["calibration"],
                        calibration_sha256=ensemble.sample["calibration_sha256"],
                        calibration_use=ensemble.sample["use"])
    return ds


def _input_files(ensemble) -> list:
    """Every file the ensemble read (report, export and path refuse to write over them)."""
    paths = {ensemble.path, *ensemble.base.input_files()}
    for member in ensemble.members:
        paths.update(member.scenario.input_files())
    if ensemble.sample.get("calibration"):
        paths.add(ensemble.sample["calibration"])
    return sorted(p for p in paths if p)


def _stacked_maps(ensemble: Ensemble, table, outdir: Path, profile: bool,
                  read: MemberMaps | None = None):
    """Maps of all members when they share one grid: ``(maps, grid coordinates, note,
    grid-mapping attributes or None)``; else ``(None, {}, why, None)``. ``maps`` holds the
    stacked :data:`MAPS` and :data:`PROBABILITY_ONLY` (None when a member file lacks it),
    and ``reached``: where each member's peak thickness passed its runout threshold."""
    files = [(int(i), outdir / f) for i, f in zip(table["realization"], table["file"]) if f]
    if not files:
        return None, {}, "no member produced a file", None
    if read is None or read.n != len(table) or read.profile != profile:
        read = MemberMaps(len(table), profile)
    for i, path in files:
        read.add(i, path)
    return read.result({i for i, _ in files})


class MemberMaps:
    """The maps of an ensemble's members, one member at a time: each member's worker reads
    them back from its file as the member finishes (:func:`read_member_maps`, kept here
    with :meth:`put`), so that ensemble.nc is assembled from memory at the end. The first
    grid kept is the reference; a member on another grid stops the stacking
    (:func:`_stacked_maps` says so). The coordinates, the bed and the grid mapping are those
    of the lowest-numbered member, as when the files were read in member order."""

    def __init__(self, n: int, profile: bool):
        self.n, self.profile = n, profile
        self.maps: dict = {}
        self.grid_coords: dict = {}
        self.crs = None
        self.reference = None  #: grid coordinates (arrays) of the first member read
        self.first = None  #: lowest member index read: its coordinates are the dataset's
        self.done: set[int] = set()
        self.different = False  #: a member on another grid: nothing stacked

    def add(self, index: int, path: str | os.PathLike) -> None:
        """Read one member's maps (once; nothing more after a member on another grid)."""
        if self.different or index in self.done:
            return
        with xr.open_dataset(path, decode_times=False) as ds:
            self.put(index, read_member_maps(ds, self.profile))

    def put(self, index: int, read: dict) -> None:
        """One member's maps as :func:`read_member_maps` read them (on a worker, as the
        member finished, or here); what :meth:`add` keeps of its file."""
        if self.different or index in self.done:
            return
        here = read["coords"]
        if self.reference is None:
            self.reference = here
            shape = (self.n, *read["shape"])
            for name in (*MAPS, *PROBABILITY_ONLY, "reached"):
                self.maps[name] = np.full(shape, np.nan)
        elif any(here[c].shape != self.reference[c].shape
                 or not np.array_equal(here[c], self.reference[c])
                 for c in self.reference):
            self.different = True
            self.maps = {}
            return
        if self.first is None or index < self.first:
            self.first = index
            self.grid_coords = read["grid_coords"]
            self.crs = read["crs"]
        for name in (*MAPS, *PROBABILITY_ONLY):
            if self.maps[name] is None:
                continue
            if read["maps"].get(name) is None:  # a member file written before the map existed
                self.maps[name] = None
                continue
            self.maps[name][index] = read["maps"][name]
        self.maps["reached"][index] = read["reached"]
        self.done.add(index)

    def result(self, members: set[int]):
        """What :func:`_stacked_maps` returns, over ``members`` (those with a file): a
        member read earlier but not among them (failed since) is left out (NaN)."""
        if self.different:
            return None, {}, "not stacked: the members have different grids", None
        if self.reference is None:
            return None, {}, "no member produced a file", None
        for index in self.done - members:
            for values in self.maps.values():
                if values is not None:
                    values[index] = np.nan
        return self.maps, self.grid_coords, "peak_thickness and deposit_thickness stacked", \
            self.crs


def read_member_maps(ds: xr.Dataset, profile: bool) -> dict:
    """What :class:`MemberMaps` keeps of one member's run Dataset (an open member file): its
    grid coordinates, bed and grid mapping, its :data:`MAPS` and :data:`PROBABILITY_ONLY`
    (None where the file lacks one) and ``reached``, where its peak thickness passed its
    runout threshold. Plain arrays and dicts: a worker reads it as the member finishes and
    returns it with the member's row."""
    names = ["x", "x_horizontal"] if profile else ["y", "x"]
    coords = {c: ds[c].values for c in names if c in ds.coords}
    grid_coords = {c: (ds[c].dims, coords[c], dict(ds[c].attrs)) for c in coords}
    if "bed_elevation" in ds:
        grid_coords["bed_elevation"] = (
            ds["bed_elevation"].dims, ds["bed_elevation"].values.astype(float),
            dict(ds["bed_elevation"].attrs))
    gm = ds["peak_thickness"].attrs.get("grid_mapping")
    crs = ({"long_name": "coordinate reference system", **ds[gm].attrs}
           if gm and gm in ds.variables else None)
    maps = {name: ds[name].values if name in ds else None for name in (*MAPS, *PROBABILITY_ONLY)}
    threshold = float(ds.attrs.get("runout_threshold_m", 0.0) or 0.0)
    reached = np.nan_to_num(maps["peak_thickness"]) >= threshold
    return {"coords": coords, "grid_coords": grid_coords, "crs": crs, "maps": maps,
            "reached": reached, "shape": maps["peak_thickness"].shape}


def exceedances(name: str, peak: np.ndarray, thresholds, reached: np.ndarray) -> list:
    """Where ``peak`` (a peak map, or a stack of them, in the map's units) exceeds each
    threshold (in :data:`THRESHOLD_UNITS`: kPa for pressure): one boolean array per
    threshold. Speed and pressure count only where ``reached`` (the peak thickness passed
    the runout threshold), so thin films do not. The ensembles' exceedance maps and the
    regions' (:mod:`avflow.region.merge`) count with it."""
    _, scale = THRESHOLD_DIMS[name]
    with np.errstate(invalid="ignore"):
        over = [peak > t * scale for t in thresholds]
    if name != "peak_thickness":
        over = [o & reached for o in over]
    return over


def _probabilities(ensemble: Ensemble, maps: dict, ok: np.ndarray, space: tuple, coords: dict,
                   data: dict) -> None:
    """Exceedance probability of each peak map at each of its thresholds, over the
    successful members; speed and pressure count where a member's peak thickness passed
    its runout threshold (as in its pressure-class map), so thin films do not."""
    n_ok = int(ok.sum())
    reached = maps["reached"][ok] > 0
    for name, thresholds in ensemble.exceedance_thresholds().items():
        if maps.get(name) is None:
            continue
        dim, _ = THRESHOLD_DIMS[name]
        what = name.replace("_", " ").replace("peak ", "peak flow " if name ==
                                              "peak_thickness" else "peak ")
        coords[dim] = (dim, np.asarray(thresholds, dtype=float), {
            "long_name": f"{what} threshold", "units": THRESHOLD_UNITS[name]})
        peak = maps[name][ok]
        with np.errstate(invalid="ignore"):
            if peak.shape[0]:
                over = exceedances(name, peak, thresholds, reached)
                prob = np.stack([o.mean(axis=0) for o in over])
                prob[:, np.isnan(peak).all(axis=0)] = np.nan
            else:
                prob = np.full((len(thresholds), *maps[name].shape[1:]), np.nan)
        film = ("" if name == "peak_thickness" else
                " and whose peak thickness passed its runout threshold")
        data[f"{name}_exceedance_probability"] = ((dim, *space), prob, {
            "long_name": f"probability that the {what} exceeds the threshold",
            "units": "1",
            "comment": f"fraction of the {n_ok} successful members whose {name} is above "
                       f"the threshold{film}; NaN outside the mesh"})


def write_ensemble_netcdf(ds: xr.Dataset, path: str | os.PathLike) -> Path:
    """Write atomically (temporary file, then rename); summaries stay float64."""
    path = Path(path)
    encoding = {}
    for name, var in ds.variables.items():
        if var.dtype == object:
            continue
        if name in ds.coords:
            encoding[name] = {"_FillValue": None}
        elif var.dtype.kind == "f" and var.ndim >= 2:
            chunks = (1, *var.shape[1:])
            encoding[name] = {"dtype": "float32", "zlib": True, "complevel": 2,
                              "shuffle": True, "chunksizes": chunks,
                              "_FillValue": np.float32(np.nan)}
        elif var.dtype.kind == "f":
            encoding[name] = {"_FillValue": np.nan}
    return atomic_write(path, lambda tmp: ds.to_netcdf(tmp, encoding=encoding,
                                                       engine="netcdf4"))
