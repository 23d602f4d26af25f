"""CF-1.11 vocabulary shared by every avflow file: variables, summaries, time, attributes.

One table, :data:`FIELDS`, declares every output variable (units, names, cell_methods);
the grid builder (:mod:`avflow.output.dataset`), the UGRID builder (:mod:`avflow.output.ugrid`)
and the tests read it. No CF standard name exists for a granular flow thickness or velocity,
so those carry a ``long_name`` and a ``comment`` (thickness is measured normal to the bed).
"""

from __future__ import annotations

from datetime import datetime, timezone

import numpy as np

from avflow import __version__
from avflow.terrain.raster import cf_grid_mapping
from avflow.numerics.rheology import law_reference
from avflow.scenario.extensions import REGISTERED_MAP
from avflow.simulation.runner import FLAG_DRY, FLAG_FLOWING, FLAG_STOPPED

SEED_REFERENCE = (
    "Mangeney-Castelnau, A., Vilotte, J.-P., Bristeau, M.-O., Perthame, B., Bouchut, F., "
    "Simeoni, C., Yerneni, S. (2003). Numerical modeling of avalanches based on Saint Venant "
    "equations using a kinetic scheme. J. Geophys. Res. 108(B11), 2527, doi:10.1029/2002JB002024"
)

#: Units of ``time``: seconds since the release, a number. Units "<unit> since <datetime>"
#: would make ``time`` a CF time coordinate, which xarray decodes to dates by default (1970
#: ones without ``output.release_time``), and ``ds.h.sel(time=40)`` would fail; the release
#: instant is the ``release_time`` attribute of ``time`` and of the file instead.
TIME_UNITS = "s"
EPOCH = datetime(1970, 1, 1)

H_COMMENT = "measured normal to the bed (topography-linked frame of the seed, Fig. 1)"
#: u and v on maps: the flow moves along the bed, so its speed there (what peak_speed and
#: peak_pressure use) is longer than hypot(u, v) by the bed's slope.
UV_COMMENT = ("on maps, the velocity along the bed projected on the horizontal plane; the "
              "speed along the bed is sqrt(u^2 + v^2 + w^2) with w = u dz/dx + v dz/dy, z "
              "the bed_elevation (on a slope of angle a in the flow direction, "
              "hypot(u, v) / cos(a)); on profiles, u is the velocity along the bed")

#: The run maxima and the deposit name, in ``cell_methods``, the scalar coordinate
#: :data:`RUN` whose bounds are the whole run (CF 7.3: a dimension or a scalar coordinate
#: of the variable).
RUN = "duration"
RUN_MAXIMUM = f"{RUN}: maximum"
OVER_THE_RUN = "over the whole run, every time step from the release to the last time"

#: name -> attributes. "kind": field (time, space), reduced (space), summary (0-d), coord.
FIELDS = {
    "h": dict(kind="field", long_name="flow thickness", units="m", comment=H_COMMENT),
    "u": dict(kind="field", long_name="depth-averaged velocity, x component of its "
                                      "horizontal projection", units="m s-1",
              comment=UV_COMMENT),
    "v": dict(kind="field", long_name="depth-averaged velocity, y component of its "
                                      "horizontal projection", units="m s-1",
              grid_only=True, comment=UV_COMMENT),
    "flow_state": dict(kind="flag", long_name="state of the cell after the step",
                       flag_values=np.array([FLAG_DRY, FLAG_FLOWING, FLAG_STOPPED], np.int8),
                       flag_meanings="dry flowing under_coulomb_threshold"),
    "peak_thickness": dict(kind="reduced", long_name="maximum flow thickness over the run",
                           units="m", cell_methods=RUN_MAXIMUM,
                           comment=f"{H_COMMENT}; {OVER_THE_RUN}"),
    "peak_speed": dict(kind="reduced", long_name="maximum speed over the run", units="m s-1",
                       cell_methods=RUN_MAXIMUM, comment=OVER_THE_RUN),
    "deposit_thickness": dict(kind="reduced", long_name="thickness at the end of the run",
                              units="m", cell_methods=f"{RUN}: point",
                              comment=f"{H_COMMENT}; at the last time of the run"),
    "bed_elevation": dict(kind="static", standard_name="ground_level_altitude", units="m"),
    "slope_angle": dict(kind="static", standard_name="ground_slope_angle", units="degree"),
    "peak_pressure": dict(kind="reduced", long_name="maximum dynamic pressure rho |u|^2",
                          units="Pa", cell_methods=RUN_MAXIMUM, comment=OVER_THE_RUN),
    "arrival_time": dict(kind="reduced", long_name="time of first arrival (h > dry threshold)",
                         units="s", comment="seconds since release; NaN where never reached"),
    "rest_time": dict(kind="reduced", long_name="time the cell came to rest for good",
                      units="s", comment=("end of the last step in which the material of the "
                                          "cell moved; NaN where dry or still moving at the end")),
    "moving_volume": dict(kind="series", long_name="volume of material still moving",
                          units="m3"),
    "center_of_mass_x": dict(kind="series", long_name="centre of mass, x", units="m"),
    "center_of_mass_y": dict(kind="series", long_name="centre of mass, y", units="m"),
    "center_of_mass_z": dict(kind="series", long_name="centre of mass, bed elevation",
                             units="m"),
    # entrainment (runs with an entrainment block only)
    "entrained_volume_series": dict(
        kind="series", long_name="volume entrained so far", units="m3",
        comment="flow volume the flow has taken from the erodible layer from the release to "
                "each snapshot (the layer's depth taken times its density over the "
                "flow's), from what the layer lost; entrainment runs only"),
    "erodible_depth": dict(
        kind="reduced", long_name="erodible layer left at the end of the run", units="m",
        cell_methods=f"{RUN}: point",
        comment="depth of the erodible layer still in place, measured normal to the bed, at "
                "the last time of the run; entrainment runs only"),
    "bed_change": dict(
        kind="reduced", long_name="change of the bed surface by erosion", units="m",
        cell_methods=f"{RUN}: sum",
        comment="final minus initial erodible depth, measured normal to the bed: negative "
                "where the bed was eroded (lowered), 0 elsewhere, never positive (no "
                "deposition onto the bed). The bed elevation the run used was not changed "
                "(bed_elevation is the initial bed); entrainment runs only"),
}

def add_registered(data: dict, coords: dict, name: str, variable) -> None:
    """A registered map into a run file's variables, refused where the file uses the name
    already (avflow.extend refuses the built-in names when a map is registered; this keeps
    a name the list missed from writing over a variable)."""
    if name in data or name in coords:
        raise ValueError(f"the registered map {name!r} has the name of a variable of the run "
                         "file: register it under another name")
    data[name] = variable


def registered_maps(state) -> dict:
    """The maps registered through :mod:`avflow.extend` that ``state`` kept, by name:
    ``(values per cell, CF attributes)``."""
    from avflow.scenario.extensions import MAPS

    if state.maps.shape[0] != len(MAPS):  # a state made before a map was registered
        return {}
    return {entry.name: (state.maps[k], {
        "long_name": entry.long_name, "units": entry.units,
        "cell_methods": f"{RUN}: {entry.cell_methods}", "comment": OVER_THE_RUN,
        REGISTERED_MAP: "yes"}) for k, entry in enumerate(MAPS.values())}


SUMMARIES = {
    "runout": ("m", "on maps: distance along the path (runout_path attribute: the scenario's "
                    "path line, else the centre-of-mass track) of the farthest cell whose "
                    "peak pressure reaches the limit (runout_limit attribute, 1 kPa by "
                    "default, as AIMEC); on profiles: downslope end of the deposit "
                    "(h > runout_threshold) along the bed from the top"),
    "runout_angle": ("degree", "alpha: atan(drop / distance along the path) from the top of "
                               "the release to the runout point (maps)"),
    "reach_from_release_centroid": ("m", "horizontal distance from the release centroid to "
                                         "the farthest deposit cell (h > runout_threshold); "
                                         "maps only (NaN on profiles)"),
    "time_to_stop": ("s", "time the stop rule ended the run (stop_rule attribute): the moving "
                          "volume (u != 0, h > dry_threshold) below stop_fraction of the "
                          "released volume, or the kinetic energy at most stop_fraction of its "
                          "peak; 0 if nothing ever moved, NaN if the run reached time.end"),
    "deposit_max_thickness": ("m", "largest final thickness"),
    "deposit_length": ("m", "extent of the deposit (h > runout_threshold) along the flow"),
    "deposit_volume": ("m3", "material on the mesh at the end, film included"),
    "release_volume": ("m3", "released volume"),
    "entrained_volume": ("m3", "flow volume taken from the erodible layer over the run (the "
                               "layer's depth taken times its density over the flow's), "
                               "from what the layer lost; 0 without entrainment"),
    "supplied_volume": ("m3", "volume the registered sources (avflow.extend) added over "
                              "the run, from their book per cell; runs with sources only"),
    "secondary_release_volume": ("m3", "volume the secondary release areas released when "
                                       "the flow reached them; runs with such areas only"),
    "outflow_volume": ("m3", "volume that left through open boundaries"),
    "film_volume": ("m3", "volume still moving at the end with h <= dry_threshold"),
    "mass_balance_error": ("1", "|V_end + V_out - V_0 - V_ent| / (V_0 + V_ent): released "
                                "plus entrained against on the map plus outflow"),
    "moving_volume_end": ("m3", "volume still moving (u != 0, h > dry_threshold) at the end"),
    "kinetic_energy_end": ("J", "kinetic energy sum rho h A |u|^2 / 2 at the end"),
    "kinetic_energy_peak": ("J", "largest kinetic energy of the run (after a step)"),
    "wall_time": ("s", "wall-clock time of the time loop (Numba's compilation not included)"),
    "compile_time": ("s", "wall-clock time to compile the Numba kernels, or load them from "
                          "their cache, before the time loop"),
    "travel_length": ("m", "horizontal distance from the highest released cell to the farthest "
                           "deposit cell"),
    "drop_height": ("m", "elevation drop over travel_length"),
    "travel_angle": ("degree", "atan(drop_height / travel_length), the Fahrboeschung"),
}


def per_width(units: str, profile: bool) -> str:
    """Volumes on a profile are per metre of width."""
    return {"m3": "m2", "J": "J m-1"}.get(units, units) if profile else units


def release_instant(release_time: str | None) -> datetime:
    """The release as a naive UTC datetime (the epoch when the scenario gives none)."""
    if release_time is None:
        return EPOCH
    t = datetime.fromisoformat(release_time)
    if t.tzinfo is not None:
        t = t.astimezone(timezone.utc).replace(tzinfo=None)
    return t


def release_stamp(release_time: str | None) -> str:
    """The release instant as ISO 8601 UTC, ``2024-02-03T10:15:00Z`` (the epoch if unset)."""
    return release_instant(release_time).isoformat() + "Z"


def time_coords(times: np.ndarray, release_time: str | None = None) -> dict:
    """``time``, seconds since the release, and the scalar coordinate :data:`RUN` that the
    run maxima reduce over, with bounds ``[0, last time]``.

    ``time`` is a plain coordinate in s (no ``standard_name: time``, no ``axis: T``: CF
    4.4 gives those to time coordinates, whose units are "<unit> since <datetime>"), so
    ``xr.open_dataset(f).h.sel(time=40, method="nearest")`` works with xarray's defaults;
    its ``release_time`` attribute (ISO 8601, UTC) is the instant of its 0.
    """
    stamp = release_stamp(release_time)
    end = float(times[-1]) if len(times) else 0.0
    return {
        "time": ("time", times, {
            "long_name": "time since release", "units": TIME_UNITS, "release_time": stamp,
            "comment": f"seconds since the release at {stamp} (output.release_time)"}),
        RUN: ((), end, {
            "long_name": "time since release over the whole run", "units": TIME_UNITS,
            "bounds": f"{RUN}_bounds",
            "comment": "the run maxima and the deposit (cell_methods) cover these bounds: "
                       "from the release to the last time of the run"}),
    }


def run_bounds(times: np.ndarray) -> dict:
    """The bounds variable of :data:`RUN` (CF 7.1: one more dimension than its scalar
    coordinate), as a data variable of :func:`to_dataset`."""
    end = float(times[-1]) if len(times) else 0.0
    return {f"{RUN}_bounds": (("nv",), np.array([0.0, end]), {})}


def grid_mapping(wkt) -> dict | None:
    """CF grid-mapping attributes of a CRS (None without one), without pyproj's UserWarning
    that a parameter CF cannot name (Swiss LV95's rectified-to-skew angle) was dropped:
    ``crs_wkt`` and ``spatial_ref`` carry the whole CRS, which GDAL, rioxarray and pyproj
    read first. Every output (grids, UGRID meshes, ensembles) takes it from here."""
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*lost in conversion to CF",
                                category=UserWarning)
        return cf_grid_mapping(wkt)


def link_coordinates(ds) -> None:
    """Name in each variable's ``coordinates`` only the auxiliary coordinates that describe it.

    Those on its dimensions (``x_horizontal``, the UGRID node coordinates), and the scalar
    coordinate :data:`RUN` only on the maps whose ``cell_methods`` name it: xarray would list
    every 0-d coordinate on every variable. The grid-mapping variable ``crs`` is no
    coordinate (CF 5.6 names it by ``grid_mapping``): as one, xarray would show ``crs = 0``
    in every plot title.
    """
    aux = [name for name in ds.coords if name not in ds.dims]
    for name, var in ds.data_vars.items():
        methods = str(var.attrs.get("cell_methods", "")).split()
        linked = [c for c in aux
                  if (f"{c}:" in methods if ds[c].ndim == 0
                      else set(ds[c].dims) <= set(var.dims))]
        var.encoding["coordinates"] = " ".join(linked) if linked else None


def mass_balance_text(summary: dict, units: str = "m3") -> str:
    """``released V0 + entrained Ve = on the map Vend + outflow Vout (m3)``, each volume to
    the digits that read back the float (repr): the balance a file states."""
    supplied = (f" + supplied {summary['supplied_volume']!r}" if "supplied_volume" in summary
                else "")
    if "secondary_release_volume" in summary:
        supplied += f" + secondary {summary['secondary_release_volume']!r}"
    return (f"released {summary['release_volume']!r} + entrained "
            f"{summary['entrained_volume']!r}{supplied} = on the map "
            f"{summary['deposit_volume']!r} + "
            f"outflow {summary['outflow_volume']!r} ({units}); relative error "
            f"{summary['mass_balance_error']:.3g}")


#: Reference of each entrainment law, for the files' ``references``.
ENTRAINMENT_REFERENCES = {
    "exponential": "Hungr and McDougall (2009), Two numerical models for landslide dynamic "
                   "analysis, Comput. Geosci. 35, 978-992 (exponential entrainment)",
    "erosion_energy": "AvaFrame com1DFA entrainment by erosion energy (entEroEnergy); Tonnel "
                      "et al. (2023), Geosci. Model Dev. 16, 7013-7035",
    "shear_threshold": "RAMMS::DEBRISFLOW erosion above a critical shear stress (Frank et al. "
                       "2015, Nat. Hazards Earth Syst. Sci. 15, 2569-2583), in rate form",
}
FOREST_REFERENCE = ("forest: AvaFrame com1DFA resistance areas (computeResForce, cResH); "
                    "Tonnel et al. (2023), Geosci. Model Dev. 16, 7013-7035")


def global_attributes(result) -> dict:
    sc, s = result.scenario, result.summary
    references = f"{SEED_REFERENCE}; friction law: {law_reference(result.solver.law)}"
    extra = {}
    if getattr(sc, "entrainment", None) is not None:
        references += f"; entrainment: {ENTRAINMENT_REFERENCES[sc.entrainment.law]}"
        extra["entrainment_law"] = sc.entrainment.law
    if getattr(sc, "forest", None) is not None:
        references += f"; {FOREST_REFERENCE}"
    for source in getattr(result.solver, "sources", ()):
        references += f"; source {source.entry.name}: {source.entry.reference}"
    if "entrained_volume" in s:
        units = "m2 per metre of width" if result.terrain.kind == "profile" else "m3"
        extra["mass_balance"] = mass_balance_text(s, units)
    return {**_attributes(result, references), **extra}


def _attributes(result, references: str) -> dict:
    sc, s = result.scenario, result.summary
    th = result.thresholds
    return {
        "Conventions": "CF-1.11",
        "title": f"avflow run of scenario {sc.name}",
        "source": f"avflow {__version__}: kinetic scheme with Dirac stopping (seed eqs. 26-56)",
        "references": references,
        "history": "created by avflow " + __version__,
        "scenario_name": sc.name,
        "scenario_hash": sc.scenario_hash(),
        "scenario": sc.source_text,
        "avflow_version": __version__,
        "release_time": release_stamp(sc.output.release_time),
        "status": s["status"],
        "runout_threshold_m": th["runout"],
        "runout_path": s.get("runout_path", ""),
        "runout_limit": s.get("runout_limit", ""),
        "dry_threshold_m": th["dry"],
        "stop_rule": th["stop_rule"],
        "stop_fraction": th["stop_fraction"],
        "ended_by": s["ended_by"],
        "min_flow_thickness_m": th["min_flow"],
        "pressure_classes_kPa": np.asarray(sc.output.pressure_classes, dtype=float),
        "steps": int(s["steps"]),
        "dt_min_s": s["dt_min"],
        "dt_max_s": s["dt_max"],
        "runout_truncated": int(s["runout_truncated"]),
        "clamped_normal_cells": s["clamped_normal_cells"],
        "halved_steps": s["halved_steps"],
        "numerics_order": sc.numerics.order,
        "limiter": sc.numerics.limiter,
        "time_scheme": (result.solver.time_scheme_used
                        if getattr(result, "solver", None) is not None
                        else sc.numerics.time_scheme),
        "order2_fallbacks": s["order2_fallbacks"],
        "comment": ("h is measured normal to the bed; on profiles x is the distance along the "
                    "bed and volumes are per metre of width"),
    }
