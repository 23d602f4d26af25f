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
    scenario:                          # a scenario without terrain, grid and release
      rheology: {law: coulomb, delta_deg: 20.0}
      time: {end: 120.0}
    window:
      buffer: null                     # m around the release's box; null: estimated
      runout_angle_deg: 20.0           # buffer = drop / tan(angle), in [min_buffer, search]
    merge:
      fields: [pressure, thickness, speed]
      chunk: 256

Every problem is one :class:`RegionError` line naming the file, line:column and field, as
scenario and ensemble files do. The scenario block is validated as a scenario would be
(its errors name ``scenario.<field>``); terrain, grid and release are the region's own.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from avflow.errors import Problem, ScenarioError
from avflow.scenario.schema import parse_scenario
from avflow.scenario.yamlio import did_you_mean, position, read_text_file, read_yaml, show

__all__ = ["RegionError", "Region", "load_region", "parse_region", "FIELD_NAMES"]

#: The merged maps a region can keep, and the per-run map each comes from.
FIELD_NAMES = {"pressure": "peak_pressure", "thickness": "peak_thickness",
               "speed": "peak_speed"}
#: Scenario blocks a region sets itself for each release.
REGION_BLOCKS = ("name", "terrain", "grid", "release")


class RegionError(ScenarioError):
    """A bad region file (``file:line:col: field: message``); exit code 2."""


Positive = Annotated[float, Field(strict=True, gt=0, allow_inf_nan=False)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Releases(_Model):
    path: Annotated[str, Field(strict=True, min_length=1)]
    """Polygon layer (.shp, .gpkg, .geojson, .fgb...), relative to the region file."""
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

    def scenario_for(self, dem_path: str, dx: float, dy: float, release_path: str,
                     thickness: float | None, name: str):
        """The scenario of one release: its DEM window, the DEM's own spacing (so cells are
        the DEM's pixels) and its polygon; output.every = time.end (only peaks are kept)."""
        written = json.loads(json.dumps(self.scenario))  # a deep copy of plain data
        written.update(name=name, terrain={"kind": "dem", "path": dem_path},
                       grid={"dx": dx, **({"dy": dy} if dy != dx else {})},
                       release={"kind": "polygon", "path": release_path,
                                **({"thickness": thickness} if thickness else {})})
        output = dict(written.get("output") or {})
        output["every"] = written["time"]["end"]
        written["output"] = output
        return parse_scenario(yaml.safe_dump(written, sort_keys=False), base_dir=self.base_dir)

    def key(self) -> str:
        """16 hex chars over what every release's result depends on besides its polygon:
        the scenario block, the window rules and the DEM (path, size, modification time)."""
        st = os.stat(self.dem)
        data = {"scenario": self.scenario, "window": self.window.model_dump(mode="json"),
                "dem": [self.dem, st.st_size, st.st_mtime_ns]}
        text = json.dumps(data, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def input_files(self) -> list[str]:
        return [p for p in (self.path, self.dem, self.releases.path) if p]


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
    releases = spec.releases.model_copy(
        update={"path": _existing(spec.releases.path, base_dir, fail, ("releases", "path"))})
    if releases.thickness is not None and releases.thickness_field is not None:
        raise fail(("releases", "thickness_field"), "give either thickness (one for every "
                   "polygon) or thickness_field (an attribute), not both")
    for key in spec.scenario:
        if key in REGION_BLOCKS:
            raise fail(("scenario", key), f"set by the region for each release ({key} comes "
                       "from dem: and releases:); leave it out")
    _check_scenario_block(spec.scenario, path, positions, base_dir)
    return Region(name=spec.name.strip(), path=path, text=text, dem=dem, releases=releases,
                  scenario=spec.scenario, window=spec.window, merge=spec.merge,
                  base_dir=base_dir, description=spec.description)


def _first_error(err: ValidationError, fail) -> RegionError:
    e = err.errors()[0]
    keys = tuple(k for k in e["loc"] if not (isinstance(k, str) and k.startswith("function-")))
    if e["type"] == "extra_forbidden":
        choices = {(): _RegionFile, ("releases",): Releases, ("window",): WindowRules,
                   ("merge",): MergeRules}.get(keys[:-1])
        hint = did_you_mean(str(keys[-1]), list(choices.model_fields)) if choices else ""
        return fail(keys, "unknown field" + (hint or ""))
    if e["type"] == "missing":
        return fail(keys, "required, but missing")
    message = e["msg"].replace("Input should be", "must be").replace("Value error, ", "")
    return fail(keys, f"{message}, got {show(e.get('input'))}")


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
    except Exception as err:  # noqa: BLE001 - GDAL's own error, in one line
        raise fail(("dem",), f"{dem}: cannot be read as a raster ({type(err).__name__}: "
                             f"{' '.join(str(err).split())[:120]})") from None
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


def _check_scenario_block(block: dict, path: str | None, positions: dict,
                          base_dir: str) -> None:
    """The block validated as a scenario on a stand-in plane and release, so that its own
    errors are found now (with their place in the region file) rather than per release."""
    written = json.loads(json.dumps(block))
    written.update(name="region-check", grid={"dx": 10.0},
                   terrain={"kind": "plane", "slope_deg": 30.0,
                            "extent": {"x": [0.0, 1000.0], "y": [0.0, 1000.0]}},
                   release={"kind": "cylinder", "center": [500.0, 500.0], "radius": 50.0,
                            "thickness": 1.0})
    inner = {k[1:]: v for k, v in positions.items() if k[:1] == ("scenario",)}
    from avflow.scenario.schema import _validate  # the scenario's own validation, positions

    try:
        _validate(written, path=path, base_dir=base_dir, positions=inner)
    except ScenarioError as err:
        problems = [Problem(p.message, path, f"scenario.{p.field}" if p.field else "scenario",
                            p.line, p.column) for p in err.problems]
        raise RegionError(problems=problems[:1]) from None
