"""Region files: one DEM, a layer of release polygons, a base scenario block, window and
merge rules; validated once, here, into a frozen :class:`Region`.

::

    name: valley
    dem: dem.tif                       # any GDAL raster; read by windows, never whole
    releases:
      path: releases.gpkg              # any polygon layer GDAL reads (pyogrio)
      thickness: 1.0                   # m, for every polygon; or
      # thickness_field: d0            #   a numeric attribute (default: 'thickness')
      id_field: id                     # positive integer attribute (default: feature order)
      # from_dem: {min_area: 2500}     # instead of path: avflow release-areas' areas
    scenario:                          # a scenario without terrain, grid and release
      rheology: {law: coulomb, delta_deg: 20.0}
      time: {end: 120.0}
    window:
      buffer: null                     # m around the release's box; null: estimated
      runout_angle_deg: 20.0           # buffer = drop / tan(angle), in [min_buffer, search]
    merge:
      fields: [pressure, thickness, speed]
      chunk: 256
      thresholds: {peak_pressure: [1.0, 3.0, 30.0]}   # kPa: exceedance maps (as ensembles)
    scenarios:                         # optional: every release runs once per scenario
      return_periods:                  # one scenario each, with its release thickness:
        - {years: 30, thickness: d30}  #   a polygon attribute (m), or
        - {years: 100, thickness: 1.2} #   m for every polygon, or
        - {years: 300, thickness: {d0: 1.5}}  # the Swiss rule (d0 at 2000 m, +5 cm/100 m, f(slope))
      vary: {rheology.delta_deg: [20.0, 24.0]}   # as in ensembles (cartesian product)
      sample: {n: 8, seed: 1, ranges: {rheology.mu: [0.15, 0.25]}}   # as in ensembles

Every problem is one :class:`RegionError` line naming the file, line:column and field, as
scenario and ensemble files do. The scenario block is validated as a scenario would be
(its errors name ``scenario.<field>``); terrain, grid and release are the region's own.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from avflow.errors import Problem, ScenarioError
from avflow.scenario.schema import parse_scenario
from avflow.scenario.yamlio import did_you_mean, position, read_text_file, read_yaml, show

__all__ = ["RegionError", "Region", "RegionScenario", "ThicknessRule", "load_region",
           "parse_region", "FIELD_NAMES"]

#: The merged maps a region can keep, and the per-run map each comes from.
FIELD_NAMES = {"pressure": "peak_pressure", "thickness": "peak_thickness",
               "speed": "peak_speed"}
#: Scenario blocks a region sets itself for each release.
REGION_BLOCKS = ("name", "terrain", "grid", "release")
#: Keys of ``scenarios:`` handed to the ensembles' parser (vary: cartesian product, sample:
#: Latin hypercube or a calibration's posterior), and the region's own.
ENSEMBLE_KEYS = ("vary", "sample")


class RegionError(ScenarioError):
    """A bad region file (``file:line:col: field: message``); exit code 2."""


Positive = Annotated[float, Field(strict=True, gt=0, allow_inf_nan=False)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Releases(_Model):
    path: Annotated[str, Field(strict=True, min_length=1)] | None = None
    """Polygon layer (.shp, .gpkg, .geojson, .fgb...), relative to the region file."""
    raster: Annotated[str, Field(strict=True, min_length=1)] | None = None
    """Instead of ``path``: a release-thickness raster (m; any GDAL raster) on the DEM's
    grid (same cell size, aligned, any part of it); each connected patch of cells above 0
    is one release (ids in scan order, from the north-west), its cells' values its
    thickness."""
    from_dem: dict[str, Any] | None = None
    """Instead of ``path`` or ``raster``: the potential release areas of the region's DEM,
    found as ``avflow release-areas`` finds them; a mapping of its options (``slope_min``,
    ``slope_max``, ``snow_depth``, ``roughness``, ``wind_direction``, ``wind_tolerance``,
    ``threshold``, ``max_curvature``, ``min_area``, ``split_aspect_deg``, ``d0``,
    ``reference_elevation``, ``gradient``, ``slope_correction``, ``forest``: a file relative
    to the region file), ``{}`` for the defaults; with ``d0`` each area's thickness. The
    DEM is read whole for it."""
    connectivity: Literal[4, 8] = 8
    """Cells of a raster patch touch by their sides (4) or their sides and corners (8)."""
    thickness: Positive | None = None
    """m, normal to the bed, for every polygon; null: the ``thickness_field`` attribute."""
    thickness_field: Annotated[str, Field(strict=True, min_length=1)] | None = None
    """Attribute holding each polygon's thickness (m); default 'thickness'."""
    id_field: Annotated[str, Field(strict=True, min_length=1)] | None = None
    """Positive integer attribute naming each release; default: feature order from 1."""


class WindowRules(_Model):
    buffer: Positive | None = None
    """m added on every side of the release's bounding box; null: estimated from the drop
    below the release top within ``search_radius`` and ``runout_angle_deg``."""
    runout_angle_deg: Annotated[float, Field(strict=True, gt=0, lt=90)] = 20.0
    """Travel angle (degrees) of the buffer's estimate: buffer = drop / tan(angle)."""
    min_buffer: Positive = 200.0
    """m, the smallest estimated buffer."""
    search_radius: Positive = 2500.0
    """m, where the drop is looked for, and the largest estimated buffer (AvaFrame's
    com7Regional clips its DEMs 2500 m around the releases)."""
    growth: Annotated[float, Field(strict=True, gt=1, le=100)] = 2.0
    """Factor on the buffer of a run whose flow reached the window's edge."""
    max_retries: Annotated[int, Field(strict=True, ge=0, le=20)] = 6
    """Re-runs in grown windows before a release is given up as truncated (the whole DEM
    is always tried last)."""


class MergeRules(_Model):
    fields: Annotated[tuple[Literal["pressure", "thickness", "speed"], ...],
                      Field(min_length=1)] = ("pressure", "thickness", "speed")
    """Peak maps merged by their per-pixel maximum (with the id of the release that set it)."""
    chunk: Annotated[int, Field(strict=True, ge=16, le=8192)] = 256
    """Zarr chunk side (cells)."""
    thresholds: Any = None
    """Exceedance maps, as in ensemble files: a list (peak thickness, m) or a mapping
    ``{peak_thickness: [m], peak_speed: [m/s], peak_pressure: [kPa]}``. Default with
    ``scenarios:``: the ensembles' defaults for each merged field (0.1, 1, 5 m; 1, 5,
    10 m/s; the scenario's ``output.pressure_classes``); without: none."""


class ThicknessRule(_Model):
    """Release thickness from the Swiss guidelines' rule (Salm, Burkard & Gubler 1990; as
    RAMMS uses it): ``d = (d0 + gradient * (z - reference_elevation) / 100) * f(psi)``,
    ``f(psi) = 0.291 / (sin psi - 0.202 cos psi)`` (1 at 28 degrees), with ``z`` and
    ``psi`` the release's mean DEM elevation and slope."""

    d0: Positive
    """m, the three-day snowfall increase of the return period at ``reference_elevation``."""
    reference_elevation: Annotated[float, Field(strict=False, allow_inf_nan=False)] = 2000.0
    """m."""
    gradient: Annotated[float, Field(strict=False, ge=0, allow_inf_nan=False)] = 0.05
    """m per 100 m of elevation above (less below) ``reference_elevation``."""
    slope_correction: Annotated[bool, Field(strict=True)] = True
    """Times ``f(psi)``; false: the thickness is ``d0`` with the elevation gradient only."""



class ReturnPeriod(_Model):
    years: Annotated[int, Field(strict=True, gt=0)]
    """The return period (years): a label of the scenario, in releases.csv and the store."""
    thickness: Any
    """The release thickness of its scenario: m for every polygon, the name of a polygon
    attribute (m), or a :class:`ThicknessRule` (``{d0: 1.2}``)."""


class ScenarioRules(_Model):
    return_periods: Annotated[list[ReturnPeriod], Field(min_length=1)] | None = None
    """One scenario per return period (crossed with vary and sample), each with its
    release thickness."""
    vary: dict[str, Any] | None = None
    """As in ensemble files: dotted scenario fields -> lists of values (cartesian)."""
    sample: dict[str, Any] | None = None
    """As in ensemble files: a seeded Latin hypercube (n, seed, ranges) or a
    calibration's posterior (calibration, n, seed, use)."""


class _RegionFile(_Model):
    name: Annotated[str, Field(strict=True, min_length=1)]
    description: Annotated[str, Field(strict=True)] = ""
    dem: Annotated[str, Field(strict=True, min_length=1)]
    """DEM (any GDAL raster: GeoTIFF, VRT, ESRI ASCII...), relative to the region file."""
    releases: Releases
    scenario: dict[str, Any]
    """A scenario without name, terrain, grid and release (they are the region's)."""
    window: WindowRules = WindowRules()
    merge: MergeRules = MergeRules()
    scenarios: ScenarioRules | None = None


@dataclass(frozen=True)
class RegionScenario:
    """One scenario every release runs: its index, the dotted updates applied to the
    scenario block (vary, sample), its return period and how its release thickness is
    found (None: the releases' own, ``releases.thickness`` or ``thickness_field``)."""

    index: int
    updates: dict
    return_period: int | None = None
    thickness: float | str | ThicknessRule | None = None

    @property
    def label(self) -> str:
        parts = [f"return_period={self.return_period}"] if self.return_period else []
        for key, value in self.updates.items():
            parts.append(f"{key}={value:.6g}" if isinstance(value, float)
                         else f"{key}={json.dumps(value, sort_keys=True)}")
        return " ".join(parts)

    def key(self) -> str:
        """What a release's result depends on in this scenario ("" for the one scenario of
        a region without ``scenarios:``, so that its keys are as before)."""
        if not self.updates and self.thickness is None:
            return ""
        thick = (self.thickness.model_dump(mode="json")
                 if isinstance(self.thickness, ThicknessRule) else self.thickness)
        return json.dumps({"updates": self.updates, "thickness": thick,
                           "return_period": self.return_period}, sort_keys=True)


#: The one scenario of a region without ``scenarios:``.
SINGLE = (RegionScenario(0, {}),)


@dataclass(frozen=True)
class Region:
    """A validated region: absolute paths, the scenario block as written, the rules."""

    name: str
    path: str | None
    text: str
    dem: str
    releases: Releases
    scenario: dict  #: the scenario block as written (validated)
    window: WindowRules
    merge: MergeRules
    base_dir: str
    description: str = ""
    #: the scenarios every release runs (one, without ``scenarios:``)
    scenarios: tuple = SINGLE
    #: peak map -> thresholds (units of :data:`avflow.ensemble.spec.THRESHOLD_UNITS`) of
    #: the exceedance maps; empty: none
    thresholds: dict = field(default_factory=dict)

    @property
    def with_scenarios(self) -> bool:
        """True when releases run more than one scenario, or the file asks for them."""
        return len(self.scenarios) > 1 or self.scenarios != SINGLE

    def scenario_for(self, dem_path: str, dx: float, dy: float, release_path: str,
                     thickness: float | None, name: str, updates: dict | None = None,
                     raster: bool = False):
        """The scenario of one release: its DEM window, the DEM's own spacing (so cells are
        the DEM's pixels) and its polygon (or, ``raster``, its thickness raster on the
        window), the scenario's ``updates`` (dotted fields, as an ensemble member's);
        output.every = time.end (only peaks are kept)."""
        written = json.loads(json.dumps(self.scenario))  # a deep copy of plain data
        for key, value in (updates or {}).items():
            _set_dotted(written, key, json.loads(json.dumps(value)))
        written.update(name=name, terrain={"kind": "dem", "path": dem_path},
                       grid={"dx": dx, **({"dy": dy} if dy != dx else {})},
                       release={"kind": "raster", "path": release_path} if raster else
                       {"kind": "polygon", "path": release_path,
                        **({"thickness": thickness} if thickness else {})})
        output = dict(written.get("output") or {})
        output["every"] = written["time"]["end"]
        written["output"] = output
        return parse_scenario(yaml.safe_dump(written, sort_keys=False), base_dir=self.base_dir)

    def key(self) -> str:
        """16 hex chars over what every release's result depends on besides its polygon:
        the scenario block, the window rules and the DEM (path, size, modification time),
        and the files of the scenario's maps (friction maps, the erodible layer, forest:
        the same for each of them and its companions), so that an edited map is run again."""
        st = os.stat(self.dem)
        data = {"scenario": self.scenario, "window": self.window.model_dump(mode="json"),
                "dem": [self.dem, st.st_size, st.st_mtime_ns]}
        maps = self._map_files()
        if maps:  # none: the keys of regions without maps stay as they were
            data["maps"] = maps
        text = json.dumps(data, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def _map_files(self) -> list:
        """``[path, size, mtime]`` of every file a ``raster:`` or ``polygon:`` of the
        scenario block names (relative to the region file's folder), with a shapefile's
        companions."""
        found = []

        def walk(node):
            if isinstance(node, dict):
                for k, v in node.items():
                    if k in ("raster", "polygon") and isinstance(v, str):
                        found.append(v)
                    else:
                        walk(v)
            elif isinstance(node, list):
                for v in node:
                    walk(v)

        walk(self.scenario)
        out = []
        for name in sorted(set(found)):
            path = Path(name) if Path(name).is_absolute() else Path(self.base_dir) / name
            for f in sorted(path.parent.glob(path.stem + ".*")) or [path]:
                try:
                    st = os.stat(f)
                    out.append([str(f), st.st_size, st.st_mtime_ns])
                except OSError:
                    out.append([str(f), None, None])
        return out

    def input_files(self) -> list[str]:
        forest = (self.releases.from_dem or {}).get("forest")
        return [p for p in (self.path, self.dem, self.releases.path, self.releases.raster,
                            forest) if p]


def _set_dotted(data: dict, dotted: str, value) -> None:
    keys = dotted.split(".")
    for key in keys[:-1]:
        if not isinstance(data.get(key), dict):
            data[key] = {}
        data = data[key]
    data[keys[-1]] = value


def load_region(path: str | os.PathLike) -> Region:
    """Read and validate a region file; any problem is one :class:`RegionError`."""
    text = read_text_file(path, "region", RegionError)
    return parse_region(text, source_path=path)


def parse_region(text: str, source_path: str | os.PathLike | None = None) -> Region:
    """Validate region YAML given as text; relative paths start at the file's folder."""
    path = os.path.abspath(source_path) if source_path is not None else None
    base_dir = os.path.dirname(path) if path else os.getcwd()
    try:
        data, positions = read_yaml(text, path)
    except ScenarioError as err:
        raise RegionError(problems=err.problems) from None

    def fail(keys: tuple, message: str) -> RegionError:
        line_col = position(positions, keys) or ()
        return RegionError(message, path, ".".join(map(str, keys)) or None, *line_col)

    if not isinstance(data, dict):
        raise fail((), f"a region file is a mapping (name, dem, releases, scenario...), got "
                       f"{show(data)}")
    try:
        spec = _RegionFile.model_validate(data)
    except ValidationError as err:
        raise _first_error(err, fail) from None
    dem = _existing(spec.dem, base_dir, fail, ("dem",))
    _check_dem(dem, fail)
    given = [k for k in ("path", "raster", "from_dem")
             if getattr(spec.releases, k) is not None]
    if len(given) != 1:
        raise fail(("releases", given[-1]) if given else ("releases",),
                   "give one of path (a polygon layer), raster (a release-thickness "
                   "raster) or from_dem (release areas found in the DEM)"
                   + (f", not {len(given)}" if given else ""))
    if given[0] == "from_dem":
        releases = spec.releases.model_copy(update={"from_dem": _from_dem(
            spec.releases.from_dem, base_dir, fail)})
    else:
        releases = spec.releases.model_copy(
            update={given[0]: _existing(getattr(spec.releases, given[0]), base_dir, fail,
                                        ("releases", given[0]))})
    if releases.raster is not None:
        for key in ("thickness_field", "id_field"):
            if getattr(releases, key) is not None:
                raise fail(("releases", key), "a release raster has no attributes: its "
                           "values are the thickness, its patches numbered in scan order")
        _check_release_raster(releases.raster, dem, fail)
    elif "connectivity" in (data.get("releases") or {}):
        raise fail(("releases", "connectivity"), "applies to a release raster only")
    if releases.thickness is not None and releases.thickness_field is not None:
        raise fail(("releases", "thickness_field"), "give either thickness (one for every "
                   "polygon) or thickness_field (an attribute), not both")
    for key in spec.scenario:
        if key in REGION_BLOCKS:
            raise fail(("scenario", key), f"set by the region for each release ({key} comes "
                       "from dem: and releases:); leave it out")
    if spec.scenario.get("structures"):
        raise fail(("scenario", "structures"), "a structure belongs to one scenario's DEM and "
                   "a release's window need not hold its line: run the releases that reach "
                   "it with avflow run (the structures in their scenario)")
    stand_in = _check_scenario_block(spec.scenario, path, positions, base_dir)
    scenarios = SINGLE
    if spec.scenarios is not None:
        scenarios = _scenarios(spec.scenarios, stand_in, path, positions, fail)
        if spec.scenarios.return_periods is not None and (
                releases.thickness is not None or releases.thickness_field is not None):
            which = "thickness" if releases.thickness is not None else "thickness_field"
            raise fail(("releases", which), "the release thickness comes from "
                       "scenarios.return_periods; leave releases." + which + " out")
    if releases.raster is not None or releases.from_dem is not None:
        for k, rs in enumerate(spec.scenarios.return_periods or () if spec.scenarios else ()):
            if isinstance(rs.thickness, str):
                raise fail(("scenarios", "return_periods", k, "thickness"), "a release "
                           + ("raster" if releases.raster is not None else "area found in "
                              "the DEM") + " has no attributes: give metres or a rule "
                           "({d0: ...})")
    thresholds = _region_thresholds(spec.merge, spec.scenarios is not None, stand_in, fail)
    return Region(name=spec.name.strip(), path=path, text=text, dem=dem, releases=releases,
                  scenario=spec.scenario, window=spec.window, merge=spec.merge,
                  base_dir=base_dir, description=spec.description, scenarios=scenarios,
                  thresholds=thresholds)


def _region_thresholds(merge: MergeRules, scenarios: bool, stand_in, fail) -> dict:
    """The exceedance maps' thresholds: parsed by the ensembles' own rules (a list: peak
    thickness; a mapping per peak map); by default, with scenarios, the ensembles' defaults
    for each merged field."""
    from avflow.ensemble.spec import DEFAULT_SPEED_THRESHOLDS, DEFAULT_THRESHOLDS
    from avflow.ensemble.spec import _thresholds as parse_thresholds

    if merge.thresholds is None:
        if not scenarios:
            return {}
        defaults = {"peak_thickness": DEFAULT_THRESHOLDS, "peak_speed": DEFAULT_SPEED_THRESHOLDS,
                    "peak_pressure": tuple(stand_in.output.pressure_classes)}
        return {FIELD_NAMES[f]: tuple(float(t) for t in defaults[FIELD_NAMES[f]])
                for f in FIELD_NAMES if f in merge.fields}
    value = merge.thresholds
    if isinstance(value, (list, dict)):
        value = json.loads(json.dumps(value))
    parsed = parse_thresholds(value, lambda keys, message: fail(("merge", *keys), message))
    return {name: parsed[name] for name in FIELD_NAMES.values() if name in parsed}


def _scenarios(rules: ScenarioRules, stand_in, path, positions, fail) -> tuple:
    """The region's scenarios: each return period crossed with the members the ensembles'
    parser makes of ``vary`` and ``sample`` (its own checks, with their place here)."""
    from avflow.ensemble.spec import EnsembleError, parse_ensemble

    members = [{}]
    if rules.vary is not None or rules.sample is not None:
        for block in ENSEMBLE_KEYS:
            where = getattr(rules, block)
            keys = (where or {}).get("ranges", {}) if block == "sample" else (where or {})
            for key in keys if isinstance(keys, dict) else ():
                head = str(key).split(".")[0]
                if head in REGION_BLOCKS:
                    at = ("scenarios", block, *(("ranges",) if block == "sample" else ()), key)
                    raise fail(at, f"{head} is set by the region for each release; vary the "
                                   "scenario block's own fields (rheology, physics, time...)")
        data = {"name": "region", **{k: getattr(rules, k) for k in ENSEMBLE_KEYS
                                     if getattr(rules, k) is not None}}
        try:
            ensemble = parse_ensemble(yaml.safe_dump(json.loads(json.dumps(data)),
                                                     sort_keys=False),
                                      source_path=path, base=stand_in)
        except EnsembleError as err:
            first = err.problems[0]
            keys = _keys_of(("scenarios",), first.field or "", positions)
            raise fail(keys, first.message) from None
        members = [m.updates for m in ensemble.members]
    periods = [(p.years, _thickness_spec(p.thickness, ("scenarios", "return_periods", k,
                                                      "thickness"), fail))
               for k, p in enumerate(rules.return_periods or ())] or [(None, None)]
    seen = set()
    for k, (years, _) in enumerate(periods):
        if years is not None and years in seen:
            raise fail(("scenarios", "return_periods", k, "years"), f"{years} years twice: "
                       "give each return period once")
        seen.add(years)
    from avflow.ensemble.spec import member_limit

    limit = member_limit()  # counted before they are made, as ensembles count members
    if len(periods) * len(members) > limit:
        raise fail(("scenarios",), f"{len(periods):,} return periods x {len(members):,} "
                                   f"members = {len(periods) * len(members):,} scenarios, more "
                                   f"than the limit of {limit:,} runs of each release")
    out = []
    for period, thickness in periods:
        for updates in members:
            out.append(RegionScenario(len(out), dict(updates), period, thickness))
    return tuple(out)


def _thickness_spec(value, keys: tuple, fail):
    """A return period's thickness: m (a positive number), a polygon attribute's name, or
    a :class:`ThicknessRule` mapping."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if not (math.isfinite(value) and value > 0):
            raise fail(keys, f"must be a positive number of metres, got {show(value)}")
        return float(value)
    if isinstance(value, str) and value.strip():
        return value.strip()
    if isinstance(value, dict):
        try:
            return ThicknessRule.model_validate(value)
        except ValidationError as err:
            e = err.errors()[0]
            inner = tuple(e["loc"])
            if e["type"] == "extra_forbidden":
                hint = did_you_mean(str(inner[-1]), list(ThicknessRule.model_fields))
                raise fail((*keys, *inner), "unknown field" + (hint or "")) from None
            if e["type"] == "missing":
                raise fail((*keys, *inner), "required, but missing") from None
            message = e["msg"].replace("Input should be", "must be")
            raise fail((*keys, *inner), f"{message}, got {show(e.get('input'))}") from None
    raise fail(keys, "must be metres (a positive number), a polygon attribute's name or a "
                     f"rule ({{d0: 1.2, ...}}), got {show(value)}")


def _keys_of(prefix: tuple, dotted: str, positions: dict) -> tuple:
    """The key path of a dotted field an inner parser named (its keys may hold dots
    themselves, as ``vary: {rheology.delta_deg: ...}``): the written one it spells."""
    want = ".".join(map(str, prefix)) + ("." + dotted if dotted else "")
    found = [k for k in positions if ".".join(map(str, k)) == want]
    if found:
        return max(found, key=len)
    return (*prefix, *[p for p in dotted.split(".") if p])


def _first_error(err: ValidationError, fail) -> RegionError:
    e = err.errors()[0]
    keys = tuple(k for k in e["loc"] if not (isinstance(k, str) and k.startswith("function-")))
    if e["type"] == "extra_forbidden":
        choices = {(): _RegionFile, ("releases",): Releases, ("window",): WindowRules,
                   ("merge",): MergeRules, ("scenarios",): ScenarioRules}.get(keys[:-1])
        if choices is None and keys[:2] == ("scenarios", "return_periods"):
            choices = ReturnPeriod if len(keys) == 4 else ThicknessRule
        hint = did_you_mean(str(keys[-1]), list(choices.model_fields)) if choices else ""
        return fail(keys, "unknown field" + (hint or ""))
    if e["type"] == "missing":
        return fail(keys, "required, but missing")
    message = e["msg"].replace("Input should be", "must be").replace("Value error, ", "")
    return fail(keys, f"{message}, got {show(e.get('input'))}")


def _from_dem(options: dict, base_dir: str, fail) -> dict:
    """``releases.from_dem`` checked as ``avflow release-areas`` checks its options; the
    forest file made absolute."""
    import dataclasses

    from avflow.terrain.release_areas import PRAError, PRASettings

    options = dict(options)
    known = {f.name for f in dataclasses.fields(PRASettings)} | {"forest"}
    for key in options:
        if key not in known:
            raise fail(("releases", "from_dem", key), f"unknown option; known: "
                       f"{', '.join(sorted(known))}")
    if options.get("forest") is not None:
        options["forest"] = _existing(str(options["forest"]), base_dir, fail,
                                      ("releases", "from_dem", "forest"))
    try:
        PRASettings(**{k: v for k, v in options.items() if k != "forest"})
    except PRAError as err:
        word = str(err).split()[0]
        raise fail(("releases", "from_dem", word if word in known else "from_dem"),
                   str(err)) from None
    except TypeError as err:
        raise fail(("releases", "from_dem"), str(err)) from None
    return options


def _existing(value: str, base_dir: str, fail, keys: tuple) -> str:
    p = Path(os.path.normpath(Path(base_dir) / Path(value).expanduser()))
    if not p.is_file():
        raise fail(keys, f"file not found: {p} (relative paths start at the region file's "
                         "folder)")
    return str(p)


def _check_dem(dem: str, fail) -> None:
    """Opened with GDAL (header only): a north-up raster with a cell size."""
    import rasterio

    try:
        with rasterio.open(dem) as src:
            t = src.transform
            rotated = t.b != 0.0 or t.d != 0.0
            shape = (src.height, src.width)
            wkt = src.crs.to_wkt() if src.crs is not None else None
    except Exception as err:  # noqa: BLE001 - GDAL's own error, in one line
        raise fail(("dem",), f"{dem}: cannot be read as a raster ({type(err).__name__}: "
                             f"{' '.join(str(err).split())[:120]})") from None
    from avflow.terrain.raster import geographic_crs

    degrees = geographic_crs(wkt)
    if degrees:
        raise fail(("dem",), f"{dem}: this DEM is in degrees ({degrees}): reproject it to a "
                             "projected CRS in metres (e.g. gdalwarp -t_srs EPSG:<UTM zone>)")
    if rotated:
        raise fail(("dem",), f"{dem}: rotated rasters are not supported; warp it north-up "
                             "first (gdalwarp)")
    if t.a < 0 or t.e > 0:
        raise fail(("dem",), f"{dem}: only north-up rasters with columns going east are "
                             "supported; warp it first (gdalwarp)")
    if min(shape) < 2:
        raise fail(("dem",), f"{dem}: {shape[1]} x {shape[0]} cells; a DEM needs at least "
                             "2 x 2")
    if not (math.isfinite(t.a) and math.isfinite(t.e) and t.a != 0 and t.e != 0):
        raise fail(("dem",), f"{dem}: no cell size in its georeferencing")


def _check_release_raster(raster: str, dem: str, fail) -> None:
    """A release raster on the DEM's grid: same CRS, cell size and alignment (header only)."""
    import rasterio

    from avflow.terrain.raster import same_crs

    keys = ("releases", "raster")
    try:
        with rasterio.open(raster) as src:
            t, crs = src.transform, src.crs
        with rasterio.open(dem) as src:
            d, dem_crs = src.transform, src.crs
    except Exception as err:  # noqa: BLE001 - GDAL's own error, in one line
        raise fail(keys, f"{raster}: cannot be read as a raster ({type(err).__name__}: "
                         f"{' '.join(str(err).split())[:120]})") from None
    if crs is not None and dem_crs is not None and not same_crs(crs.to_wkt(),
                                                                 dem_crs.to_wkt()):
        raise fail(keys, f"{raster}: its CRS differs from the DEM's; reproject it onto the "
                         "DEM's grid (gdalwarp -t_srs ... -tr ... -tap)")
    off_c, off_r = (t.c - d.c) / d.a, (t.f - d.f) / d.e
    if (t.b != 0 or t.d != 0 or not math.isclose(t.a, d.a, rel_tol=1e-9)
            or not math.isclose(t.e, d.e, rel_tol=1e-9)
            or abs(off_c - round(off_c)) > 1e-6 or abs(off_r - round(off_r)) > 1e-6):
        raise fail(keys, f"{raster}: its cells are not the DEM's (cell {t.a:g} x {-t.e:g} m "
                         f"at {t.c:.6g}, {t.f:.6g}; the DEM's {d.a:g} x {-d.e:g} m at "
                         f"{d.c:.6g}, {d.f:.6g}); warp it onto the DEM's grid first "
                         "(gdalwarp -tr -tap, or -te with the DEM's bounds)")


def _check_scenario_block(block: dict, path: str | None, positions: dict,
                          base_dir: str):
    """The block validated as a scenario on a stand-in plane and release, so that its own
    errors are found now (with their place in the region file) rather than per release;
    returns that stand-in scenario (the base the ensembles' parser varies)."""
    written = json.loads(json.dumps(block))
    written.update(name="region-check", grid={"dx": 10.0},
                   terrain={"kind": "plane", "slope_deg": 30.0,
                            "extent": {"x": [0.0, 1000.0], "y": [0.0, 1000.0]}},
                   release={"kind": "cylinder", "center": [500.0, 500.0], "radius": 50.0,
                            "thickness": 1.0})
    inner = {k[1:]: v for k, v in positions.items() if k[:1] == ("scenario",)}
    from avflow.scenario.schema import _validate  # the scenario's own validation, positions

    try:
        return _validate(written, path=path, base_dir=base_dir, positions=inner)
    except ScenarioError as err:
        problems = [Problem(p.message, path, f"scenario.{p.field}" if p.field else "scenario",
                            p.line, p.column) for p in err.problems]
        raise RegionError(problems=problems[:1]) from None
