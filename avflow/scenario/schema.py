"""Scenario files: YAML in, one validated, frozen, fully resolved :class:`Scenario` out.

Validation happens once, here, at the edge; the numerical code trusts what it gets. Every
problem becomes one :class:`~avflow.errors.ScenarioError` naming the file, the line:column
where the value was written and the dotted field::

    scenarios/foo.yaml:14:3: rheology.delta_deg: must be in [0, 90) degrees, got 95.0
    scenarios/foo.yaml:5:3: terrain.slop: unknown field (did you mean 'slope'?)

Conventions: SI units (m, s, kg/m^3), angles in degrees; thicknesses are measured normal to
the bed, as in the seed (Mangeney-Castelnau et al. 2003). Data files (DEM, release polygons)
are given relative to the YAML file and stored as absolute paths.

The format, for editors, is the JSON Schema in ``scenarios/schema.json``, written by
:func:`write_json_schema`.
"""

from __future__ import annotations

import copy
import functools
import hashlib
import json
import math
import os
import re
import types
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Mapping, Union, get_args, get_origin

import yaml
from pydantic import (BaseModel, ConfigDict, Discriminator, Field, PrivateAttr,
                      StringConstraints, Tag, ValidationError, ValidationInfo, WrapValidator,
                      field_validator, model_validator)
from pydantic.fields import FieldInfo
from pydantic_core import PydanticCustomError

from avflow.errors import Problem, ScenarioError
from avflow.scenario.yamlio import (did_you_mean, dotted, dotted_parts, position, read_text_file,
                                    read_yaml, show)

__all__ = ["Scenario", "load_scenario", "parse_scenario", "write_json_schema"]

#: Suffixes accepted for data files, with the companion files that belong to their content
#: (a shapefile's attributes, such as the release thickness, live in its .dbf).
DEM_SUFFIXES = {".asc": (".prj",), ".tif": (".tfw", ".prj"), ".tiff": (".tfw", ".prj"),
                ".nc": ()}
POLYGON_SUFFIXES = {".shp": (".shx", ".dbf", ".prj", ".cpg"), ".gpkg": (), ".geojson": (),
                    ".json": (), ".fgb": ()}

# =========================================================================================
# Value types: each carries its own range and says the whole range when a value is outside.
# =========================================================================================


def _problem(message: str, field: str | None = None) -> PydanticCustomError:
    """A validation error with our own message; ``field`` (dotted, relative to the model
    raising it) names the culprit when a model validator compares several fields."""
    return PydanticCustomError("scenario", message, {"field": field} if field else None)


Number = Annotated[float, Field(strict=True, allow_inf_nan=False)]  # ints accepted, not "5"
_BOUND_ERRORS = {"greater_than", "greater_than_equal", "less_than", "less_than_equal"}


@dataclass(frozen=True)
class Bounds:
    """The range of a number field, carried by its type (:func:`_interval`): what a map of
    that field (:class:`ParameterMap`) must hold in every cell (checked when it is sampled,
    :mod:`avflow.terrain.maps`)."""

    lo: float | None
    hi: float | None
    lo_open: bool
    hi_open: bool
    wanted: str  #: "must be in [0, 90) degrees"

    def inside(self, values: Any) -> Any:
        """Element-wise: finite and within the range (numpy arrays or floats)."""
        import numpy as np

        v = np.asarray(values, dtype=float)
        ok = np.isfinite(v)
        if self.lo is not None:
            ok &= (v > self.lo) if self.lo_open else (v >= self.lo)
        if self.hi is not None:
            ok &= (v < self.hi) if self.hi_open else (v <= self.hi)
        return ok


def bounds_of(kind: Any) -> Bounds | None:
    """The :class:`Bounds` a number type of :func:`_interval` carries (None: unbounded)."""
    return next((m for m in get_args(kind)[1:] if isinstance(m, Bounds)), None)


def _interval(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
              hi_open: bool = False, unit: str = "", why: str = "") -> Any:
    """A finite float within bounds (ints accepted; strings and booleans are not).

    The bounds go into the JSON Schema; a value outside them gets one message stating the
    whole interval (pydantic would only name the bound that failed).
    """
    bounds: dict[str, float] = {}
    if lo is not None:
        bounds["gt" if lo_open else "ge"] = lo
    if hi is not None:
        bounds["lt" if hi_open else "le"] = hi
    if lo is not None and hi is not None:
        wanted = f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    elif lo is not None:
        wanted = f"{'>' if lo_open else '>='} {lo:g}"
    else:
        wanted = f"{'<' if hi_open else '<='} {hi:g}"
    wanted = f"must be {wanted}{unit}{why}"

    def explain(value: Any, handler: Any) -> float:
        try:
            return handler(value)
        except ValidationError as err:
            if err.errors()[0]["type"] in _BOUND_ERRORS:
                raise _problem(f"{wanted}, got {show(value)}") from None
            raise

    return Annotated[float, Field(strict=True, allow_inf_nan=False, **bounds),
                     WrapValidator(explain), Bounds(lo, hi, lo_open, hi_open, wanted)]


def _pair(what: str, increasing: bool) -> Any:
    """Two finite floats written as a YAML list, e.g. ``[xmin, xmax]`` or ``[x, y]``."""

    def check(value: Any, handler: Any) -> tuple[float, float]:
        try:
            pair = handler(value)
        except ValidationError as err:
            if err.errors()[0]["type"] in ("too_short", "too_long", "missing", "tuple_type"):
                raise _problem(f"must be a list of two numbers {what}, got {show(value)}"
                               ) from None
            raise
        if increasing and not pair[0] < pair[1]:
            raise _problem(f"must be {what} with min < max, got {show(list(pair))}")
        return pair

    return Annotated[tuple[Number, Number], WrapValidator(check)]


Positive = _interval(0.0, lo_open=True)
NonNegative = _interval(0.0)
Angle = _interval(0.0, 90.0, hi_open=True, unit=" degrees")
SignedAngle = _interval(-90.0, 90.0, lo_open=True, hi_open=True, unit=" degrees")
Fraction = _interval(0.0, 1.0, hi_open=True)
Courant = _interval(0.0, 1.0, lo_open=True, why=": positivity of h needs it")
Range = _pair("[min, max]", increasing=True)
Point = _pair("[x, y]", increasing=False)
Flag = Annotated[bool, Field(strict=True)]  # only true/false: not 1, not "yes"
Text = Annotated[str, Field(strict=True)]
Side = Literal["wall", "outflow"]
SIDES = ("x_min", "x_max", "y_min", "y_max")


class _Model(BaseModel):
    """Frozen, unknown keys rejected; attribute docstrings become JSON Schema descriptions."""

    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)


def _data_file(value: str, info: ValidationInfo, suffixes: Mapping[str, Any]) -> str:
    """Absolute path of a data file named relative to the scenario file; it must exist."""
    path = Path(value).expanduser()
    if path.suffix.lower() not in suffixes:
        raise _problem(f"must be a {', '.join(suffixes)} file, got {show(value)}")
    base_dir = (info.context or {}).get("base_dir") or os.getcwd()
    path = Path(os.path.normpath(Path(base_dir) / path))  # unchanged when already absolute
    if not path.is_file():
        raise _problem(f"file not found: {path} (relative paths start at the scenario's "
                       "folder)")
    return str(path)


# =========================================================================================
# Terrain
# =========================================================================================


class ConstantSlope(_Model):
    """A plane bed: constant slope angle."""

    kind: Literal["constant"]
    theta_deg: Angle
    """Slope angle (degrees)."""


class ExponentialSlope(_Model):
    """The seed's eq. 58: ``theta(x) = theta0 exp(-x / a)``, x along the bed."""

    kind: Literal["exponential"]
    theta0_deg: Angle
    """Slope angle at x = 0 (degrees)."""
    a: Positive
    """Decay length (m, along the bed)."""


class TableSlope(_Model):
    """Slope angle given at points along the bed, linear between them."""

    kind: Literal["table"]
    x: Annotated[tuple[Number, ...], Field(min_length=2)]
    """Positions along the bed (m), strictly increasing."""
    theta_deg: tuple[SignedAngle, ...]
    """Slope angle at each position (degrees, negative uphill)."""

    @model_validator(mode="after")
    def _check_table(self) -> TableSlope:
        if any(b <= a for a, b in zip(self.x, self.x[1:])):
            raise _problem(f"must be strictly increasing, got {show(list(self.x))}", "x")
        if len(self.theta_deg) != len(self.x):
            raise _problem(f"must have one angle per x ({len(self.x)}), "
                           f"got {len(self.theta_deg)}", "theta_deg")
        return self


Slope = Annotated[Union[ConstantSlope, ExponentialSlope, TableSlope],
                  Field(discriminator="kind")]


class ProfileTerrain(_Model):
    """A transversally uniform slope, solved in 1D along the bed (seed section 2)."""

    kind: Literal["profile"]
    length: Positive
    """Length of the profile (m, measured along the bed)."""
    slope: Slope
    """Slope angle as a function of the distance along the bed."""
    curvature: Flag = True
    """Include the curvature term of eqs. 61-62."""


class Extent(_Model):
    """Horizontal rectangle covered by the grid."""

    x: Range
    """[xmin, xmax] (m)."""
    y: Range
    """[ymin, ymax] (m)."""


class PlaneTerrain(_Model):
    """An inclined plane over a horizontal rectangle."""

    kind: Literal["plane"]
    slope_deg: Angle
    """Steepest slope angle (degrees)."""
    azimuth_deg: Number = 0.0
    """Direction the plane faces (downslope), clockwise from north (+y), degrees."""
    extent: Extent
    """Horizontal extent of the grid (m)."""
    elevation_at_center: Number = 0.0
    """Bed elevation at the centre of the extent (m)."""
    domain: Text | None = None
    """Optional polygon file (.shp, .gpkg, .geojson, .fgb): only cells whose centre is
    inside are meshed (walls around); relative to the scenario file; stored absolute."""

    @field_validator("domain")
    @classmethod
    def _existing_domain(cls, value: str | None, info: ValidationInfo) -> str | None:
        return None if value is None else _data_file(value, info, POLYGON_SUFFIXES)


class DemTerrain(_Model):
    """A digital elevation model."""

    kind: Literal["dem"]
    path: Text
    """DEM file (.asc, .tif, .tiff or .nc), relative to the scenario file; stored absolute."""
    nodata: Side = "wall"
    """How the flow treats NODATA cells: as walls or as outflow."""
    domain: Text | None = None
    """Optional polygon file (.shp, .gpkg, .geojson, .fgb): only cells whose centre is
    inside are meshed (the rest is treated as NODATA); relative to the scenario file;
    stored absolute."""
    curvature: Flag = True
    """Include the bed-curvature term of eqs. 61-62 in 2D: the normal acceleration
    g cos(theta) + u.K.u, with K the curvature tensor of the DEM (README)."""

    @field_validator("domain")
    @classmethod
    def _existing_domain(cls, value: str | None, info: ValidationInfo) -> str | None:
        return None if value is None else _data_file(value, info, POLYGON_SUFFIXES)

    @field_validator("path")
    @classmethod
    def _existing_dem(cls, value: str, info: ValidationInfo) -> str:
        return _data_file(value, info, DEM_SUFFIXES)


Terrain = Annotated[Union[ProfileTerrain, PlaneTerrain, DemTerrain], Field(discriminator="kind")]

# =========================================================================================
# Release: the mass at rest at t = 0 (eq. 60); thicknesses are normal to the bed
# =========================================================================================


class _Release(_Model):
    kind: str  # narrowed to a Literal by each shape (declared here so that it dumps first)
    volume_factor: Positive = 1.0
    """Multiplies the thickness, hence the released volume."""


class ParabolaRelease(_Release):
    """The seed's eq. 59 on a profile: ``h = K (l - (x - x0)^2)``, zero outside."""

    kind: Literal["parabola"]
    center: Number
    """x0 (m, along the bed)."""
    half_length: Positive
    """sqrt(l): half the length of the mass (m, along the bed)."""
    max_thickness: Positive
    """K l: thickness at the centre (m, normal to the bed)."""


class DamRelease(_Release):
    """A reservoir of uniform thickness at x < position, dry beyond (profile)."""

    kind: Literal["dam"]
    position: Number
    """Position of the dam (m, along the bed)."""
    thickness: Positive
    """Thickness of the reservoir (m, normal to the bed)."""


class BoxRelease(_Release):
    """Uniform thickness over an x range (and a y range on a 2D terrain)."""

    kind: Literal["box"]
    x: Range
    """[xmin, xmax] (m)."""
    y: Range | None = None
    """[ymin, ymax] (m): required on 2D terrains, not allowed on a profile."""
    thickness: Positive
    """m, normal to the bed."""


class CylinderRelease(_Release):
    """Uniform thickness within a horizontal radius of a centre (2D terrains)."""

    kind: Literal["cylinder"]
    center: Point
    """[x, y] (m, horizontal)."""
    radius: Positive
    """m, horizontal."""
    thickness: Positive
    """m, normal to the bed."""


class PolygonRelease(_Release):
    """Release areas from a polygon file: shapefile, GeoPackage, GeoJSON (2D terrains)."""

    kind: Literal["polygon"]
    path: Text
    """Polygon file (.shp with its .dbf, .gpkg, .geojson, .fgb), relative to the scenario
    file; stored absolute."""
    thickness: Positive | None = None
    """m, normal to the bed; null: each polygon's 'thickness' attribute."""

    @field_validator("path")
    @classmethod
    def _existing_shapefile(cls, value: str, info: ValidationInfo) -> str:
        return _data_file(value, info, POLYGON_SUFFIXES)


class RasterRelease(_Release):
    """A raster of release thickness (2D terrains), sampled at the cell centres."""

    kind: Literal["raster"]
    path: Text
    """Thickness raster (.asc, .tif, .tiff or .nc; m, normal to the bed), relative to the
    scenario file; stored absolute. NODATA and negative cells release nothing."""

    @field_validator("path")
    @classmethod
    def _existing_raster(cls, value: str, info: ValidationInfo) -> str:
        return _data_file(value, info, DEM_SUFFIXES)


Release = Annotated[Union[ParabolaRelease, DamRelease, BoxRelease, CylinderRelease,
                          PolygonRelease, RasterRelease], Field(discriminator="kind")]
PROFILE_RELEASES = ("parabola", "dam")
GRID_RELEASES = ("cylinder", "polygon", "raster")


#: The release shapes of a secondary area (2D terrains).
SecondaryArea = Annotated[Union[BoxRelease, CylinderRelease, PolygonRelease, RasterRelease],
                          Field(discriminator="kind")]


class SecondaryRelease(_Model):
    """Release areas that release when the flow reaches them (AvaFrame's secondary release
    areas): each area (each polygon of a polygon file) releases its mass, at rest, the first
    time the flow stands above the dry threshold on one of its cells (2D terrains)."""

    areas: tuple[SecondaryArea, ...]
    """The areas, each as a release (box, cylinder, polygon or raster); at least one."""
    check_every: Positive | None = None
    """Time between checks whether the flow reached an area (s); null: output.every / 10,
    at most 1 s. An area releases at the first check after the flow reached it."""

    @field_validator("areas")
    @classmethod
    def _some_area(cls, value: tuple) -> tuple:
        if not value:  # (checked here, not by length: a bad area is then one message)
            raise _problem("give at least one area")
        return value

#: Largest map (m along a profile, or a side of a plane's extent): 10 000 km, a quarter of
#: the Earth's circumference, where a flat bed without the Earth's curvature means nothing.
MAX_EXTENT = 1e7
#: Most snapshots a run stores (time.end / output.every): one every 0.04 s (a film's frame)
#: for an hour is 90 000; each costs a copy of the state and a return to Python.
MAX_SNAPSHOTS = 100_000

# =========================================================================================
# Maps: values that vary in space, sampled at the cell centres (avflow.terrain.maps)
# =========================================================================================


class _Where(_Model):
    """Fields shared by the maps: a raster, or polygons, sampled at the cell centres."""

    raster: Text | None = None
    """Raster file (.asc, .tif, .tiff or .nc), relative to the scenario file; stored
    absolute. Each cell takes the value of the raster cell its centre lies in (no
    interpolation: zones stay zones, a mask stays 0 or 1). Same CRS as the DEM."""
    polygon: Text | None = None
    """Polygon file (.shp with its .dbf, .gpkg, .geojson, .fgb), relative to the scenario
    file; stored absolute. A cell is inside when its centre is (where polygons overlap,
    the larger value wins, as for releases). Same CRS as the DEM."""

    @field_validator("raster")
    @classmethod
    def _existing_raster(cls, value: str | None, info: ValidationInfo) -> str | None:
        return None if value is None else _data_file(value, info, DEM_SUFFIXES)

    @field_validator("polygon")
    @classmethod
    def _existing_polygons(cls, value: str | None, info: ValidationInfo) -> str | None:
        return None if value is None else _data_file(value, info, POLYGON_SUFFIXES)

    def files(self) -> list[str]:
        """The data files this map reads."""
        return [f for f in (self.raster, self.polygon) if f]


class ParameterMap(_Where):
    """A friction parameter that varies in space (2D terrains), in the parameter's own
    units, e.g. ``mu: {raster: mu.tif}`` or ``mu: {polygon: zones.gpkg, attribute: mu,
    default: 0.2}``. Every cell's value must lie in the parameter's range (the bounds of
    the number it replaces), checked before the run."""

    attribute: Text | None = None
    """Polygons: the attribute that holds each polygon's value (give this or value)."""
    value: Number | None = None
    """Polygons: one value inside every polygon (give this or attribute)."""
    default: Number | None = None
    """The value of the cells the map says nothing of: outside every polygon, outside the
    raster or on its NODATA cells; null: such a cell is an error."""
    scale: Positive = 1.0
    """A factor on every cell's value (the default's too), before the range check: an
    ensemble or a calibration moves the whole map up or down by varying it
    (``rheology.mu.scale``); 1 leaves the map's values as they are, to the bit."""

    @model_validator(mode="after")
    def _one_source(self) -> ParameterMap:
        if (self.raster is None) == (self.polygon is None):
            raise _problem("give raster or polygon, not both"
                           if self.raster else "needs raster (a file) or polygon (a file)")
        if self.raster is not None:
            for name in ("attribute", "value"):
                if getattr(self, name) is not None:
                    raise _problem("applies to polygon maps only (a raster holds its values)",
                                   name)
        elif (self.attribute is None) == (self.value is None):
            raise _problem("give attribute (each polygon's value) or value (one for all), "
                           "not both" if self.value is not None else
                           "needs attribute (the polygons' attribute holding the value) or "
                           "value (one value inside every polygon)", "attribute")
        return self


class _MapMarker:
    """Marks a field that takes a number or a :class:`ParameterMap` (:func:`_mappable`);
    ``bounds``: the number's range, what every cell of a map must hold."""

    def __init__(self, bounds: Bounds | None):
        self.bounds = bounds


def _number_or_map(value: Any) -> str:
    return "map" if isinstance(value, (dict, BaseModel)) else "number"


def _mappable(kind: Any) -> Any:
    """A number of type ``kind`` (:func:`_interval`), or a map of it (:class:`ParameterMap`):
    chosen by the value written (a mapping is a map), so a bad value gets one message."""

    def number(value: Any, handler: Any) -> float:
        try:
            return handler(value)
        except ValidationError as err:
            if err.errors()[0]["type"] in ("float_type", "float_parsing"):
                raise _problem(f"must be a number, or a map such as {{raster: FILE}} or "
                               f"{{polygon: FILE, attribute: NAME}}, got {show(value)}"
                               ) from None
            raise

    return Annotated[Union[Annotated[kind, WrapValidator(number), Tag("number")],
                           Annotated[ParameterMap, Tag("map")]],
                     Discriminator(_number_or_map), _MapMarker(bounds_of(kind))]


def map_fields(model: BaseModel) -> dict[str, ParameterMap]:
    """The fields of ``model`` given as maps, by name."""
    return {name: value for name in type(model).model_fields
            if isinstance(value := getattr(model, name), ParameterMap)}


def field_bounds(model: type[BaseModel] | BaseModel, name: str) -> Bounds | None:
    """The range of a field that may be a map (None: none known)."""
    cls = model if isinstance(model, type) else type(model)
    info = cls.model_fields[name]
    marker = next((m for m in info.metadata if isinstance(m, _MapMarker)), None)
    todo = [info.annotation]
    while marker is None and todo:  # an optional field: the marker is inside its union
        kind = todo.pop()
        args = get_args(kind)
        if get_origin(kind) is Annotated:
            marker = next((m for m in args[1:] if isinstance(m, _MapMarker)), None)
        todo += list(args)
    return None if marker is None else marker.bounds


class _MapsChecked(_Model):
    """A model whose map fields' ``value`` and ``default`` must lie in the field's range."""

    @model_validator(mode="after")
    def _map_values_in_range(self) -> _MapsChecked:
        for name, spec in map_fields(self).items():
            bounds = field_bounds(self, name)
            for key in ("value", "default"):
                v = getattr(spec, key)
                if v is not None and bounds is not None and not bounds.inside(v):
                    raise _problem(f"{bounds.wanted}, got {show(v)}", f"{name}.{key}")
        return self


def _numbers(*values: Any) -> bool:
    """True when every value is a number (not a map): cross-field checks then apply here;
    with maps they apply cell by cell when the maps are sampled."""
    return all(isinstance(v, (int, float)) for v in values)


# =========================================================================================
# Rheology: basal friction laws (parameters are turned into numbers in avflow.numerics.rheology)
# =========================================================================================


class Coulomb(_MapsChecked):
    """Coulomb friction with a constant friction angle (seed eq. 12)."""

    law: Literal["coulomb"]
    delta_deg: _mappable(Angle)
    """Friction angle (degrees)."""


class Pouliquen(_MapsChecked):
    """Pouliquen's flow law (seed eq. 15): friction between tan(delta1) and tan(delta2)."""

    law: Literal["pouliquen"]
    delta1_deg: _mappable(Angle)
    """Friction angle of thick or fast layers (degrees), smaller than delta2_deg."""
    delta2_deg: _mappable(Angle)
    """Friction angle of thin or slow layers (degrees)."""
    d: _mappable(Positive)
    """Length scale of the law (m, a multiple of the grain size)."""
    beta: _mappable(Positive) = 0.136
    """Dimensionless constant of the law (Froude number scale)."""

    @model_validator(mode="after")
    def _ordered_angles(self) -> Pouliquen:
        if (_numbers(self.delta1_deg, self.delta2_deg)
                and not self.delta1_deg < self.delta2_deg):
            raise _problem(f"must be smaller than delta2_deg ({self.delta2_deg!r}), "
                           f"got {self.delta1_deg!r}", "delta1_deg")
        return self


class Voellmy(_MapsChecked):
    """Voellmy friction: Coulomb plus a turbulent drag ``g |u|^2 / xi``."""

    law: Literal["voellmy"]
    delta_deg: _mappable(Angle) | None = None
    """Friction angle (degrees); give this or mu."""
    mu: _mappable(NonNegative) | None = None
    """Friction coefficient tan(delta); give this or delta_deg."""
    xi: _mappable(Positive)
    """Turbulent coefficient (m/s^2)."""

    @model_validator(mode="after")
    def _one_friction(self) -> Voellmy:
        if self.delta_deg is not None and self.mu is not None:
            raise _problem("give delta_deg or mu, not both", "mu")
        if self.delta_deg is None and self.mu is None:
            raise _problem("needs a friction: delta_deg (degrees) or mu")
        return self


class SamosAT(_MapsChecked):
    """samosAT, AvaFrame com1DFA's standard snow friction law (Sampl and Zwinger 2004).

    Basal shear stress (Pa), with ``sigma = rho h N`` the basal normal stress (N the normal
    acceleration, g cos(theta) plus the curvature term; rho = physics.density)::

        tau_b = tau0 + mu sigma (1 + Rs0 / (Rs0 + Rs)) + rho |u|^2 / D^2
        Rs = rho |u|^2 / (sigma + 0.001 Pa),   D = ln(max(h / R, 1)) / kappa + B

    A Coulomb friction that falls from ``2 mu`` at rest to ``mu`` in fast flow (Rs >> Rs0),
    plus a turbulent drag of a logarithmic velocity profile over a roughness length R.
    Defaults: AvaFrame's standard ("samosAT", large avalanches). AvaFrame's default
    ``samosATAuto`` takes mu = 0.22 (samosATSmall) for releases under 25 000 m^3 and
    mu = 0.17 (samosATMedium) under 60 000 m^3, the other parameters unchanged.
    Set ``physics.density`` to AvaFrame's 200 kg/m^3 for snow (it enters tau0 / rho and Rs).
    """

    law: Literal["samosat"]
    mu: _mappable(NonNegative) = 0.155
    """Coulomb friction coefficient (-), the fast-flow limit; 0.22 samosATSmall, 0.17
    samosATMedium."""
    tau0: _mappable(NonNegative) = 0.0
    """Minimum shear stress, a yield stress (Pa)."""
    Rs0: _mappable(Positive) = 0.222
    """Scale of Rs = rho |u|^2 / sigma (-): the Coulomb factor 1 + Rs0 / (Rs0 + Rs) is 2 at
    rest, 1.5 at Rs = Rs0, tends to 1 in fast flow."""
    kappa: _mappable(Positive) = 0.43
    """Von Karman constant of the turbulent term (-)."""
    R: _mappable(Positive) = 0.05
    """Roughness length of the turbulent term (m): flows thinner than R have D = B."""
    B: _mappable(Positive) = 4.13
    """Offset of the turbulent term's logarithmic profile (-)."""


class VelocityWeakening(_MapsChecked):
    """Velocity-weakening friction of Lucas, Mangeney and Ampuero (2014, Nat. Commun. 5, 3417)::

        mu(|u|) = mu_w + (mu_s - mu_w) / (1 + |u| / U_w)

    Coulomb with ``mu_s`` at rest (a pile under atan(mu_s) stays at rest exactly), half way
    to ``mu_w`` at ``|u| = U_w``, tending to ``mu_w`` in fast flow. No defaults: see the
    model page (guide/model.md) for where the values of the examples come from.
    """

    law: Literal["velocity_weakening"]
    mu_s: _mappable(NonNegative)
    """Friction coefficient at rest (-), tan of the static friction angle."""
    mu_w: _mappable(NonNegative)
    """Weakened friction coefficient (-), the fast-flow limit; at most mu_s."""
    U_w: _mappable(Positive)
    """Weakening speed (m/s): mu is half way from mu_s to mu_w at |u| = U_w."""

    @model_validator(mode="after")
    def _weakens(self) -> VelocityWeakening:
        if _numbers(self.mu_w, self.mu_s) and not self.mu_w <= self.mu_s:
            raise _problem(f"must be at most mu_s ({self.mu_s!r}), got {self.mu_w!r}", "mu_w")
        return self


#: The built-in laws; a law registered through avflow.extend joins them (:func:`add_law`)
RHEOLOGY_MODELS: list[type[BaseModel]] = [Coulomb, Pouliquen, Voellmy, SamosAT,
                                          VelocityWeakening]
Rheology = Annotated[Union[tuple(RHEOLOGY_MODELS)], Field(discriminator="law")]


def add_law(name: str, parameters: tuple[str, ...], bounds: dict, doc: str) -> None:
    """A friction law registered through :mod:`avflow.extend` becomes a value of
    ``rheology.law``: a block of its parameters (numbers, within ``bounds``), checked like
    the built-in laws' (the scenario model is rebuilt with it)."""
    from pydantic import create_model

    fields: dict[str, Any] = {"law": (Literal[name], ...)}
    for p in parameters:
        lo, hi = bounds.get(p, (None, None))
        kind = (_interval(lo, hi) if lo is not None or hi is not None
                else Annotated[float, Field(strict=True, allow_inf_nan=False)])
        fields[p] = (kind, ...)
    model = create_model("".join(w.title() for w in name.split("_")), __base__=_Model,
                         __doc__=doc.strip() or f"The friction law {name}.", **fields)
    RHEOLOGY_MODELS.append(model)
    info = FieldInfo.from_annotation(
        Annotated[Union[tuple(RHEOLOGY_MODELS)], Field(discriminator="law")])
    info.description = Scenario.model_fields["rheology"].description
    Scenario.model_fields["rheology"] = info
    Scenario.model_rebuild(force=True)

# =========================================================================================
# Entrainment and forest (issue 30; the laws are avflow.numerics.physics.source_rate)
# =========================================================================================

#: Densest erodible layer or flow accepted (kg/m^3), as physics.density.
Density = _interval(0.0, 1e5, lo_open=True, unit=" kg/m^3", why=" (4x the densest element)")


class ErodibleLayer(_Where):
    """The erodible layer at the start (m, normal to the bed, like the flow's thickness):
    give one of ``depth`` (uniform: over the whole map, or over an x [and y] range),
    ``raster`` (a raster of depths) or ``polygon`` (each polygon's ``thickness`` attribute,
    or one ``thickness``). Cells outside the polygons or the range have no layer."""

    depth: NonNegative | None = None
    """Uniform depth (m): over the whole map, or the cells within x (and y) when given."""
    x: Range | None = None
    """With depth: [xmin, xmax] (m; along the bed on a profile) of the cells with a layer."""
    y: Range | None = None
    """With depth, 2D terrains: [ymin, ymax] (m) of the cells with a layer."""
    thickness: NonNegative | None = None
    """Polygons: one depth (m) inside every polygon; null: each polygon's attribute."""
    attribute: Text | None = None
    """Polygons: the attribute that holds each polygon's depth (m), when thickness is null;
    null: 'thickness' (as for releases)."""
    default: NonNegative | None = None
    """Raster: the depth (m) of cells outside the raster or on its NODATA; null: such a
    cell is an error (write 0 for no layer there)."""

    @model_validator(mode="after")
    def _one_form(self) -> ErodibleLayer:
        given = [k for k in ("depth", "raster", "polygon") if getattr(self, k) is not None]
        if len(given) != 1:
            raise _problem(f"give one of depth, raster or polygon, got {len(given)}"
                           + (f" ({', '.join(given)})" if given else ""))
        form = given[0]
        for name, owner in (("x", "depth"), ("y", "depth"), ("thickness", "polygon"),
                            ("attribute", "polygon"), ("default", "raster")):
            if getattr(self, name) is not None and form != owner:
                raise _problem(f"applies with {owner} only, not with {form}", name)
        if self.thickness is not None and self.attribute is not None:
            raise _problem("give thickness (one depth) or attribute, not both", "attribute")
        return self


class _Entrainment(_Model):
    law: str  # narrowed to a Literal by each law (declared here so that it dumps first)
    layer: ErodibleLayer
    """Where the erodible layer lies, and its depth (m, normal to the bed)."""
    density: Density | None = None
    """Density of the erodible layer (kg/m^3); null: the flow's (physics.density), a bed
    of the flow's own material (debris over debris): a depth e taken adds e of flow
    thickness. Set it for snow: AvaFrame's rhoEnt is 100 kg/m^3 (snow cover) against a
    flow of 200 (physics.density); a depth e then adds e * 100 / 200."""
    u_min: NonNegative = 0.0
    """Speed (m/s) at or below which nothing is entrained (0: only material at rest takes
    nothing)."""


class ExponentialEntrainment(_Entrainment):
    """Hungr and McDougall (2009, Comput. Geosci. 35, 978-992): the flow grows as
    ``dh/dt = E_s h |u|``, so a volume travelling a distance s over an erodible bed grows
    as ``V0 exp(E_s s)``. Give growth_rate (E_s), or growth_factor and path_length
    (``E_s = ln(growth_factor) / path_length``, Hungr and McDougall's growth rate: the
    volume multiplies by growth_factor over path_length of erodible path)."""

    law: Literal["exponential"]
    growth_rate: NonNegative | None = None
    """E_s (1/m): growth of the flow's thickness per metre travelled."""
    growth_factor: _interval(1.0) | None = None
    """Final over initial volume (-) over path_length of erodible path, >= 1."""
    path_length: Positive | None = None
    """Length (m) of erodible path over which the volume grows by growth_factor."""

    @model_validator(mode="after")
    def _one_rate(self) -> ExponentialEntrainment:
        factor = self.growth_factor is not None or self.path_length is not None
        if self.growth_rate is not None and factor:
            raise _problem("give growth_rate, or growth_factor and path_length, not both",
                           "growth_rate")
        if self.growth_rate is None and not factor:
            raise _problem("needs growth_rate (E_s, 1/m), or growth_factor and path_length")
        if factor and (self.growth_factor is None or self.path_length is None):
            missing = "growth_factor" if self.growth_factor is None else "path_length"
            raise _problem("required with " + ("path_length" if missing == "growth_factor"
                                               else "growth_factor"), missing)
        return self

    @property
    def e_s(self) -> float:
        """E_s (1/m)."""
        import math

        if self.growth_rate is not None:
            return self.growth_rate
        return math.log(self.growth_factor) / self.path_length


class ErosionEnergyEntrainment(_Entrainment):
    """AvaFrame com1DFA's entrainment by erosion energy (entEroEnergy; Tonnel et al. 2023,
    Geosci. Model Dev. 16, 7013-7035): ``dm/dt = tau_b |u| / e_b`` per unit area, with
    tau_b the basal shear stress of the friction law (its Coulomb part and its drag, and
    forest's): the work of the basal shear erodes the bed."""

    law: Literal["erosion_energy"]
    e_b: Positive = 5000.0
    """Specific erosion energy (J/kg); AvaFrame's default entEroEnergy, 5000."""


class ShearThresholdEntrainment(_Entrainment):
    """RAMMS::DEBRISFLOW's idea (Frank, McArdell et al. 2015, Nat. Hazards Earth Syst. Sci.
    15, 2569-2583; ramms.slf.ch, debris-flow module, erosion) in rate form: the bed erodes
    at ``de/dt = k (tau_b - tau_c)`` where the basal shear stress tau_b exceeds tau_c, not
    below. RAMMS itself caps the depth eroded at ``dz/dtau (tau_b - tau_c)`` (dz/dtau =
    0.1 m/kPa, tau_c = 1 kPa), eroded at 0.025 m/s; avflow's law is the rate, with no cap
    but the layer's depth."""

    law: Literal["shear_threshold"]
    k: NonNegative
    """Erosion rate per shear stress above tau_c, m/(s kPa): e.g. 0.025 erodes 2.5 cm/s
    under 1 kPa of excess shear."""
    tau_c: NonNegative = 1000.0
    """Critical shear stress (Pa) below which nothing erodes; RAMMS's 1 kPa."""


Entrainment = Annotated[Union[ExponentialEntrainment, ErosionEnergyEntrainment,
                              ShearThresholdEntrainment], Field(discriminator="law")]


class Forest(_Where):
    """Forest: a resistance ``c_f |u|^2`` per unit area and density on the flow where it
    stands (AvaFrame com1DFA's resistance areas, computeResForce; its cResH), added to the
    friction law's drag. Where: polygons, a raster, or an x [and y] range."""

    c_f: NonNegative = 0.01
    """Resistance coefficient (-); AvaFrame's default cResH, 0.01. With a raster of
    values 'coefficient' or polygons with an attribute, the file's values instead."""
    attribute: Text | None = None
    """Polygons: the attribute holding each polygon's c_f; null: c_f inside all."""
    values: Literal["mask", "coefficient"] | None = None
    """Raster: 'mask' (cells > 0 are forest, with c_f) or 'coefficient' (the raster's
    values are c_f); null: mask."""
    default: NonNegative | None = None
    """Raster: the value of cells outside the raster or on its NODATA (a mask's 0 or 1,
    or a c_f); null: such a cell is an error (write 0 for no forest there)."""
    x: Range | None = None
    """[xmin, xmax] (m; along the bed on a profile) of the forest, instead of a file."""
    y: Range | None = None
    """With x, 2D terrains: [ymin, ymax] (m) of the forest."""

    @model_validator(mode="after")
    def _one_form(self) -> Forest:
        form = _one_form_of(self, "where the forest stands")
        for name, owner in (("attribute", "polygon"), ("default", "raster"), ("y", "x"),
                            ("values", "raster")):
            if getattr(self, name) is not None and form != owner:
                raise _problem(f"applies with {owner} only, not with {form}", name)
        return self

def _one_form_of(block: BaseModel, what: str) -> str:
    """The one form a block's area is given in (raster, polygon or x), else one line."""
    given = [k for k in ("raster", "polygon", "x") if getattr(block, k) is not None]
    if len(given) != 1:
        raise _problem(f"give one of polygon, raster or x (and y): {what}, got {len(given)}"
                       + (f" ({', '.join(given)})" if given else ""))
    return given[0]


class _SourceArea(_Where):
    """Where a registered source adds mass: polygons, a raster mask (cells > 0), or an x
    [and y] range; dry cells included."""

    x: Range | None = None
    """[xmin, xmax] (m; along the bed on a profile) of the area, instead of a file."""
    y: Range | None = None
    """With x, 2D terrains: [ymin, ymax] (m) of the area."""

    @model_validator(mode="after")
    def _one_form(self) -> _SourceArea:
        form = _one_form_of(self, "where the source adds mass")
        if self.y is not None and form != "x":
            raise _problem(f"applies with x only, not with {form}", "y")
        return self


class NoSourceRegistered(_Model):
    """No source is registered in this process: ``sources`` stays empty. A source is a
    Python function registered through avflow.extend (user guide: your own friction law,
    source or map); each registered source then has its block here, chosen by ``law``."""

    @model_validator(mode="before")
    @classmethod
    def _none(cls, value: Any) -> Any:
        raise _problem("no source is registered in this process: a source is a function "
                       "registered through avflow.extend before the scenario is read")


#: The sources registered through avflow.extend (:func:`add_source`)
SOURCE_MODELS: list[type[BaseModel]] = []


def add_source(name: str, parameters: tuple[str, ...], doc: str) -> None:
    """A source registered through :mod:`avflow.extend` becomes a value of
    ``sources[].law``: its parameters (finite numbers) and where it adds mass
    (:class:`_SourceArea`); the scenario model is rebuilt with it."""
    from pydantic import create_model

    fields: dict[str, Any] = {"law": (Literal[name], ...)}
    for p in parameters:
        fields[p] = (Annotated[float, Field(strict=True, allow_inf_nan=False)], ...)
    model = create_model("".join(w.title() for w in name.split("_")), __base__=_SourceArea,
                         __doc__=doc.strip() or f"The source {name}.", **fields)
    SOURCE_MODELS.append(model)
    info = FieldInfo.from_annotation(
        tuple[Annotated[Union[tuple(SOURCE_MODELS)], Field(discriminator="law")], ...])
    info.default = ()
    info.description = Scenario.model_fields["sources"].description
    Scenario.model_fields["sources"] = info
    Scenario.model_rebuild(force=True)


# =========================================================================================
# Grid, time, output, boundaries, physics
# =========================================================================================


class Refinement(_Model):
    """Conforming refinement of a triangle mesh where the terrain bends or is steep."""

    levels: Annotated[int, Field(strict=True, ge=1, le=8)] = 2
    """Rounds of refinement (each bisects the edges of the marked triangles)."""
    angle_deg: Angle | None = 5.0
    """Refine triangles whose normal turns by more than this from a neighbour's (degrees)."""
    slope_deg: Angle | None = None
    """Refine triangles steeper than this (degrees); null: slope does not mark."""


class Grid(_Model):
    """Cell sizes."""

    dx: Positive
    """m: along the bed on a profile, horizontal on a 2D grid."""
    dy: Positive | None = None
    """m, horizontal (2D terrains only); null: dy = dx."""
    mesh: Literal["square", "triangles"] = "square"
    """2D terrains: square cells, or triangles on the grid nodes with median dual cells
    (seed section 3.1, Fig. 2; one cell per vertex)."""
    pattern: Literal["alternate", "criss-cross"] = "alternate"
    """Triangles only: each square split along alternating diagonals, or into four."""
    refine: Refinement | None = None
    """Triangles only: refinement where the terrain bends; null: none."""


class Time(_Model):
    """Time stepping."""

    end: Positive
    """End time (s); the run may stop earlier when the mass comes to rest."""
    cfl: Courant = 0.5
    """CFL number of the kinetic scheme, in (0, 1]."""
    max_steps: Annotated[int, Field(strict=True, gt=0)] = 10_000_000
    """Bound on the number of time steps."""


#: Default stop_fraction of each stop rule: 1e-3 of the release still moving, or 1% of the
#: peak kinetic energy (AvaFrame com1DFA's stopCrit).
STOP_FRACTIONS = {"moving_volume": 1e-3, "kinetic_energy": 0.01}


#: Path line files of output.path (a shapefile's companions count in its content).
LINE_SUFFIXES = {".shp": (".shx", ".dbf", ".prj"), ".geojson": (), ".json": (), ".csv": ()}


#: The alpha-beta regressions by name (avflow/output/alphabeta.py holds their coefficients).
AB_REGRESSIONS = ("norway", "austria", "austria_small")


class PathAnalysis(_Model):
    """Runout along the avalanche path (AvaFrame's AIMEC; avflow/output/path.py): `avflow
    run` writes OUT_path.csv/.md/.png beside the NetCDF, ensembles add path_* columns to
    summary.csv and ensemble.nc. Post-processing only: not part of the scenario hash."""

    line: Text | None = None
    """Path line file (.shp, .geojson, .json, or .csv of x, y), relative to the scenario
    file; stored absolute; null: the flow's own centre-of-mass track."""
    field: Literal["pressure", "thickness"] = "pressure"
    """Peak field whose threshold marks the runout point."""
    threshold: Positive | None = None
    """kPa for pressure (null: 1 kPa, AIMEC's default), m for thickness (null: the run's
    runout threshold)."""
    width: Positive | None = None
    """Width (m) of the band around the line whose cells count; null: every cell."""
    alpha_beta: Text | None = None
    """Alpha-beta regression beside the dynamic runout: norway (Lied and Bakkehøi 1980,
    alpha = 0.96 beta - 1.4 deg, SD 2.3 deg; null means this one), austria or austria_small
    (AvaFrame com2AB's sets), or "k1,k2,k3,k4,sd" for alpha = k1 beta + k2 z'' + k3 H0 + k4."""

    @field_validator("alpha_beta")
    @classmethod
    def _known_regression(cls, value: str | None) -> str | None:
        if value is None or value.strip() in AB_REGRESSIONS:
            return value
        try:
            numbers = [float(p) for p in value.split(",")]
        except ValueError:
            numbers = []
        if len(numbers) != 5 or not all(math.isfinite(v) for v in numbers) or numbers[4] < 0:
            raise ValueError(f"give one of {', '.join(AB_REGRESSIONS)} or k1,k2,k3,k4,sd "
                             "(five numbers, sd >= 0)")
        return value

    @field_validator("line")
    @classmethod
    def _existing_line(cls, value: str | None, info: ValidationInfo) -> str | None:
        return None if value is None else _data_file(value, info, LINE_SUFFIXES)


class PointOfInterest(_Model):
    """A place where the flow is recorded against time (a building, a road)."""

    name: Annotated[str, StringConstraints(strict=True, strip_whitespace=True, min_length=1)]
    x: Number
    """m, in the terrain's coordinates."""
    y: Number
    """m, in the terrain's coordinates."""


class Points(_Model):
    """Points of interest (2D terrains): flow thickness, speed and pressure against time
    at each, written beside the run (OUT_points.csv, OUT_points.png) and in its NetCDF
    (group ``points``)."""

    at: tuple[PointOfInterest, ...] = ()
    """Points given by name and coordinates."""
    file: Text | None = None
    """A point layer (.shp with its .dbf, .gpkg, .geojson, .fgb), relative to the scenario
    file; stored absolute. Reprojected to the DEM's CRS where both carry one."""
    name_field: Text = "name"
    """The attribute of the point layer that names each point (missing: point_1, ...)."""
    every: Positive | None = None
    """Time between samples (s); null: output.every / 10, at most 1 s."""

    @field_validator("file")
    @classmethod
    def _existing_points(cls, value: str | None, info: ValidationInfo) -> str | None:
        return None if value is None else _data_file(value, info, POLYGON_SUFFIXES)

    @model_validator(mode="after")
    def _some_point(self) -> Points:
        if not self.at and self.file is None:
            raise _problem("give the points in 'at' or a point layer in 'file'")
        names = [p.name for p in self.at]
        if len(set(names)) != len(names):
            raise _problem(f"the points' names must differ, got {show(names)}", "at")
        return self


class Output(_Model):
    """What is stored, and when the run counts as stopped."""

    every: Positive | None = None
    """Time between stored snapshots (s); default time.end / 20."""
    runout_threshold: Positive | None = None
    """Thickness (m) above which a cell counts in the deposit and the runout; null: automatic."""
    release_time: Text | None = None
    """ISO 8601 date and time of the release (UTC unless it carries an offset, e.g.
    2024-02-03T10:15:00Z or 2024-02-03T11:15:00+01:00): the reference of the file's time
    axis, which stores seconds since the release; null: the epoch 1970-01-01T00:00:00Z."""

    @field_validator("release_time")
    @classmethod
    def _iso_release_time(cls, value: str | None) -> str | None:
        """Normalised to UTC, ``YYYY-MM-DDTHH:MM:SS[.ffffff]Z`` (one spelling, one hash)."""
        if value is None:
            return None
        import datetime as _dt

        try:
            t = _dt.datetime.fromisoformat(value.strip())
        except ValueError:
            raise _problem(f"must be an ISO 8601 date and time such as 2024-02-03T10:15:00Z, "
                           f"got {show(value)}") from None
        if t.tzinfo is not None:
            t = t.astimezone(_dt.timezone.utc).replace(tzinfo=None)
        return t.isoformat() + "Z"
    stop_rule: Literal["moving_volume", "kinetic_energy"] = "moving_volume"
    """When the run ends before time.end. moving_volume: the volume still moving (u != 0,
    h above the dry threshold, mass crossing a face) falls below stop_fraction of the
    release: what remains is a deposit at rest. kinetic_energy: the kinetic energy falls
    to stop_fraction of its peak (AvaFrame's rule): a third to a half of the mass may still
    be moving, slowly; the final thickness is then a snapshot, not a deposit at rest."""
    stop_fraction: Fraction | None = None
    """The fraction of the stop rule; null: 1e-3 (moving_volume) or 0.01 (kinetic_energy,
    AvaFrame's stopCrit); 0: never stop before time.end (kinetic_energy: only at rest)."""

    @model_validator(mode="before")
    @classmethod
    def _default_stop_fraction(cls, data: Any) -> Any:
        """stop_fraction follows the rule unless written (resolved, so a file says it)."""
        if isinstance(data, dict) and data.get("stop_fraction") is None:
            rule = data.get("stop_rule", "moving_volume")
            if isinstance(rule, str) and rule in STOP_FRACTIONS:  # else: its own error
                data = {**data, "stop_fraction": STOP_FRACTIONS[rule]}
        return data
    dry_threshold: Positive | None = None
    """Thickness (m) below which a cell counts as dry in decisions; null: automatic."""
    path: PathAnalysis | None = None
    """Runout along the avalanche path (line, field, threshold, width); null: not done by
    `avflow run` (ensembles use the centre-of-mass track)."""
    pressure_classes: Annotated[tuple[Positive, ...], Field(min_length=1)] = (1.0, 3.0, 30.0)
    """Peak-pressure thresholds (kPa, increasing) of the pressure classes drawn by avflow
    plot and written by avflow export (peak_pressure_class): the common zoning values 1, 3
    and 30 kPa by default."""

    @field_validator("pressure_classes")
    @classmethod
    def _increasing_classes(cls, value: tuple) -> tuple:
        if any(b <= a for a, b in zip(value, value[1:])):
            raise _problem(f"must be strictly increasing (kPa), got {show(list(value))}")
        return value
    points: Points | None = None
    """Points of interest: thickness, speed and pressure against time at each (2D
    terrains); null: none."""


class Boundaries(_Model):
    """Condition on each side of the domain. Also written as one word for all sides."""

    x_min: Side = "wall"
    x_max: Side = "wall"
    y_min: Side = "wall"
    y_max: Side = "wall"

    @model_validator(mode="before")
    @classmethod
    def _one_word_for_all_sides(cls, data: Any) -> Any:
        if not isinstance(data, str):
            return data
        if data not in get_args(Side):
            raise _problem(f"must be 'wall', 'outflow' or a mapping of sides, got {show(data)}")
        return dict.fromkeys(SIDES, data)

    @classmethod
    def __get_pydantic_json_schema__(cls, core_schema: Any, handler: Any) -> dict[str, Any]:
        sides = handler(core_schema)
        return {"anyOf": [{"type": "string", "enum": list(get_args(Side))}, sides],
                "title": sides.get("title", cls.__name__), "description": cls.__doc__}


class Numerics(_Model):
    """The scheme: the seed's first order, or its second-order kinetic form."""

    order: Literal[1, 2] = 1
    """1: the seed's scheme (its figures are reproduced with it); 2: limited linear
    reconstruction of thickness and velocity at the faces, in time MUSCL-Hancock or Heun's
    Runge-Kutta (``time_scheme``), keeping the threshold, Dirac faces and projection.
    Default: 2 on planes and DEMs (square grids and triangles) with the CPU kernels, 1
    elsewhere (profiles, the GPU)."""
    limiter: Literal["minmod", "mc"] = "minmod"
    """Limited slopes of order 2: minmod (robust at wet/dry fronts; Barth-Jespersen on grids
    and triangles) or mc (monotonized central, sharper at smooth extrema: profiles only, as
    grids and triangles have the one Barth-Jespersen limiter)."""
    time_scheme: Literal["auto", "hancock", "heun"] = "auto"
    """Order 2's time stepping. hancock: MUSCL-Hancock, the faces' sides predicted half a
    step on in each cell, then one step of the seed's scheme with them (threshold, Dirac
    faces and projection as at order 1): about half the cost of heun and no less accurate
    (docs/validation.md); planes and DEMs (square grids and triangles) on the CPU. heun:
    Heun's two-stage Runge-Kutta, each stage a step of the seed's scheme, then their mean;
    every mesh. auto: hancock on planes and DEMs with the CPU kernels, heun elsewhere."""
    threads: Annotated[int, Field(strict=True, ge=1, le=4096)] | None = None
    """CPU threads of the time loop (grids and triangles; profiles run on one; null: every
    core this process may use, where a few timed steps show them faster than one thread,
    else one: a machine busy with other work does not slow a run down). The answer is the
    same, bit for bit, whatever the number. Ensemble members run on one thread each unless this is set: members are the
    better parallelism there."""
    kernel: Literal["auto", "grid", "faces"] = "auto"
    """auto: the structured square-grid kernel on square grids (both orders), the face kernel
    elsewhere; faces: the general face kernel everywhere (the reference it is tested
    against); grid: the square-grid kernel, an error where it does not apply."""
    backend: Literal["cpu", "cuda"] = "cpu"
    """cpu: the kernels above, on this machine's cores; cuda: the square-grid kernel on a
    CUDA GPU (``pip install 'avflow[cuda]'``; square grids at orders 1 and 2;
    anything else is refused at load time, as is a machine without a GPU). Its fields
    agree with the CPU's to round-off (docs/guide/gpu.md)."""


#: What ``physics.material`` sets where not given: the bulk density (kg/m^3: AvaFrame's
#: snow; debris flows 1800-2300; rock avalanches about 2500) and the stop rule (snow runs
#: leave thin layers creeping on steep slopes long after the runout is reached: docs' run end)
MATERIALS = {"snow": {"density": 200.0, "stop_rule": "kinetic_energy"},
             "debris": {"density": 2000.0, "stop_rule": "moving_volume"},
             "rock": {"density": 2500.0, "stop_rule": "moving_volume"}}
#: The laws of snow avalanches: without a material or density, snow's density
SNOW_LAWS = ("samosat", "voellmy")


class Physics(_Model):
    """Physical constants."""

    gravity: _interval(0.0, 1000.0, lo_open=True, unit=" m/s^2",
                       why=" (100 g: a geotechnical centrifuge)") = 9.81
    """m/s^2."""
    dirac: Flag = True
    """The seed's zero-temperature (Dirac) flux; false only for studies."""
    material: Literal["snow", "debris", "rock"] | None = None
    """What flows, for its defaults (:data:`MATERIALS`): snow (density 200 kg/m^3, the
    kinetic-energy stop rule, as AvaFrame), debris (2000, the moving-volume rule) or rock
    (2500, the moving-volume rule). null: debris, except with the snow laws samosat and
    voellmy, which take snow's density (said on stderr). ``density`` and
    ``output.stop_rule``, where given, win."""
    density: _interval(0.0, 1e5, lo_open=True, unit=" kg/m^3",
                       why=" (4x the densest element)") = 2000.0
    """Bulk density of the flowing material (kg/m^3); default: the material's."""
    min_flow_thickness: NonNegative | None = None
    """Material thinner than this (m) does not flow: it keeps its mass where it lies (in the
    deposit), sends and takes no momentum and plays no part in the time step. null: 1 mm
    (GeoClaw's dry tolerance), or the dry threshold when that is smaller (a release under
    1 m thick: 1e-3 of its thickness); 0: no such rule (only round-off residues, 1e-12 of
    the largest release thickness, are held)."""


class Structure(_Model):
    """A protective structure built into the bed before the run (AvaFrame com1DFA's dam
    takes a crest line, a height and a side slope; RAMMS users edit the DEM): every feature
    of a line file (any vector format GDAL reads), in the DEM's CRS.

    - ``dam``: an earth dam or catching/deflecting dam: the bed is raised to a crest
      ``height`` above the ground under the line, ``crest_width`` wide, falling at
      ``side_slope_deg`` on both sides; a flow with enough energy overtops it.
    - ``wall``: a vertical wall, ``crest_width`` thick (at least the cells the line
      touches): its cells leave the mesh and reflect the flow (walls of the grid), so it is
      never overtopped, whatever its ``height``."""

    name: Text = ""
    """Label in the outputs; empty: the file's stem."""
    line: Text
    """Line file (.shp, .gpkg, .geojson, .json, .fgb), relative to the scenario file;
    stored absolute."""
    kind: Literal["dam", "wall"] = "dam"
    """dam (raised bed with side slopes, can be overtopped) or wall (vertical, reflecting)."""
    height: Positive
    """Crest height above the ground under the line (m)."""
    crest_width: NonNegative = 0.0
    """Width of the flat crest (m); a wall's thickness."""
    side_slope_deg: Angle | None = None
    """A dam's side slope (degrees from the horizontal), both sides; required for a dam."""

    @field_validator("line")
    @classmethod
    def _existing_line(cls, value: str, info: ValidationInfo) -> str:
        return _data_file(value, info, POLYGON_SUFFIXES)

    @model_validator(mode="after")
    def _slope_for_a_dam(self) -> Structure:
        if self.kind == "dam" and self.side_slope_deg is None:
            raise _problem("required for a dam (its sides' angle from the horizontal, "
                           "degrees)", "side_slope_deg")
        if self.kind == "wall" and self.side_slope_deg is not None:
            raise _problem("a wall is vertical: leave side_slope_deg out, or make it a dam",
                           "side_slope_deg")
        return self


class Scenario(_Model):
    """A validated scenario. Build one with :func:`load_scenario` or :func:`parse_scenario`.

    Blocks ``output``, ``boundary`` and ``physics`` are optional; everything is resolved
    (defaults filled in, data-file paths absolute). ``source_path`` and ``source_text`` tell
    where it came from; they are not part of :meth:`scenario_hash`.
    """

    name: Annotated[str, StringConstraints(strict=True, strip_whitespace=True, min_length=1)]
    """Short identifier of the scenario."""
    description: Text = ""
    terrain: Terrain
    """The bed: a 1D profile, an inclined plane or a DEM."""
    grid: Grid
    release: Release
    """The mass at rest at t = 0 (thickness normal to the bed)."""
    rheology: Rheology
    """Basal friction law, chosen by ``law``. Any of its parameters may be a map."""
    entrainment: Entrainment | None = None
    """Mass the flow takes from an erodible layer on its way, by ``law``; null: none."""
    forest: Forest | None = None
    """Forest's resistance to the flow, where it stands; null: none."""
    sources: tuple[NoSourceRegistered, ...] = ()
    """Mass added over an area, dry cells included, by sources registered through
    avflow.extend (snowfall, a feeding flow), each chosen by ``law``; empty: none."""
    structures: tuple[Structure, ...] = ()
    """Dams and walls built into the bed before the run (2D terrains)."""
    secondary_release: SecondaryRelease | None = None
    """Areas that release when the flow reaches them (2D terrains); null: none."""
    time: Time
    output: Output = Output()
    boundary: Boundaries = Boundaries()
    physics: Physics = Physics()
    numerics: Numerics = Numerics()

    _source_path: str | None = PrivateAttr(None)
    _source_text: str | None = PrivateAttr(None)
    _positions: dict[tuple, tuple[int, int]] = PrivateAttr(default_factory=dict)
    _written: dict[str, Any] | None = PrivateAttr(None)  # the mapping as written, for updates
    _base_dir: str | None = PrivateAttr(None)

    @model_validator(mode="before")
    @classmethod
    def _material_defaults(cls, data: Any) -> Any:
        """physics.density and output.stop_rule from physics.material where they are not
        given; without a material, the snow laws (samosat, voellmy) take snow's density, and
        one line on stderr says so when it runs (:meth:`density_note`): debris density would
        make their pressures ten times too high. Filled in before validation (the model stays
        frozen)."""
        if not isinstance(data, dict):
            return data
        physics, output = data.get("physics", {}), data.get("output", {})
        if isinstance(physics, BaseModel):
            physics = physics.model_dump(exclude_unset=True)
        if isinstance(output, BaseModel):
            output = output.model_dump(exclude_unset=True)
        if not isinstance(physics, dict) or not isinstance(output, dict):
            return data  # their own errors are reported
        material = physics.get("material")
        rheology = data.get("rheology")
        law = getattr(rheology, "law", None) if isinstance(rheology, BaseModel) else (
            rheology.get("law") if isinstance(rheology, dict) else None)
        preset = MATERIALS.get(material) if isinstance(material, str) else None
        if physics.get("density") is None:
            if preset is not None:
                physics = {**physics, "density": preset["density"]}
            elif material is None and law in SNOW_LAWS:  # said when it runs: density_note
                physics = {**physics, "density": MATERIALS["snow"]["density"]}
        if preset is not None and output.get("stop_rule") is None:
            output = {**output, "stop_rule": preset["stop_rule"]}
        if physics or "physics" in data:
            data = {**data, "physics": physics}
        if output or "output" in data:
            data = {**data, "output": output}
        return data

    @model_validator(mode="before")
    @classmethod
    def _default_order(cls, data: Any) -> Any:
        """numerics.order where not given: 2 on planes and DEMs (square grids and
        triangles, the CPU kernels), where MUSCL-Hancock costs about two order-1 steps on a
        square grid and three on triangles and is far closer to analytic 2D solutions and
        to the grid's turned copy (docs/validation.md); 1 on profiles (the seed's scheme,
        which its figures are reproduced with) and on the GPU. Filled in before validation
        (the model stays frozen)."""
        if not isinstance(data, dict):
            return data
        numerics = data.get("numerics", {})
        if isinstance(numerics, BaseModel):
            numerics = numerics.model_dump(exclude_unset=True)
        if not isinstance(numerics, dict) or numerics.get("order") is not None:
            return data

        def field(block, key, default=None):
            value = data.get(block)
            if isinstance(value, BaseModel):
                return getattr(value, key, default)
            return value.get(key, default) if isinstance(value, dict) else default

        surface = (field("terrain", "kind") in ("plane", "dem")
                   and numerics.get("backend", "cpu") == "cpu")
        return {**data, "numerics": {**numerics, "order": 2 if surface else 1}}

    @model_validator(mode="before")
    @classmethod
    def _default_output_every(cls, data: Any) -> Any:
        """output.every defaults to time.end / 20: twenty snapshots whatever the duration.

        Filled in before validation so that the model stays frozen; left alone when time.end
        is not a valid number (its own error is reported then).
        """
        if not isinstance(data, dict):
            return data
        time, output = data.get("time"), data.get("output", {})
        if isinstance(time, Time):
            time = {"end": time.end}
        if isinstance(output, Output):
            output = output.model_dump(exclude_unset=True)
        end = time.get("end") if isinstance(time, dict) else None
        if (isinstance(output, dict) and output.get("every") is None
                and isinstance(end, (int, float)) and not isinstance(end, bool)
                and 0 < end < float("inf")):
            data = {**data, "output": {**output, "every": end / 20.0}}
        return data

    @model_validator(mode="after")
    def _blocks_fit_together(self) -> Scenario:
        terrain, release = self.terrain.kind, self.release.kind
        if release in PROFILE_RELEASES and terrain != "profile":
            raise _problem(f"a {release!r} release needs a 'profile' terrain, "
                           f"got {terrain!r}", "release.kind")
        if release in GRID_RELEASES and terrain == "profile":
            raise _problem(f"a {release!r} release needs a 2D terrain ('plane' or 'dem'), "
                           "got 'profile'", "release.kind")
        if release == "box" and terrain == "profile" and self.release.y is not None:
            raise _problem("not allowed on a 'profile' terrain (1D: x only)", "release.y")
        if release == "box" and terrain != "profile" and self.release.y is None:
            raise _problem(f"required on a 2D terrain ({terrain!r})", "release.y")
        if terrain == "profile" and self.grid.dy is not None:
            raise _problem("not allowed on a 'profile' terrain (1D: dx only)", "grid.dy")
        if terrain == "profile" and self.output.path is not None and self.output.path.line:
            raise _problem("not allowed on a 'profile' terrain (the profile is its own path)",
                           "output.path.line")
        if terrain == "profile" and self.structures:
            raise _problem("a structure needs a 2D terrain ('plane' or 'dem')", "structures")
        if terrain == "profile" and self.secondary_release is not None:
            raise _problem("needs a 2D terrain ('plane' or 'dem')", "secondary_release")
        if terrain == "profile" and self.output.points is not None:
            raise _problem("needs a 2D terrain ('plane' or 'dem'): on a profile every "
                           "place is in the file's fields on (time, x)", "output.points")
        for k, area in enumerate(self.secondary_release.areas
                                 if self.secondary_release is not None else ()):
            if area.kind == "box" and area.y is None:
                raise _problem(f"required on a 2D terrain ({terrain!r})",
                               f"secondary_release.areas.{k}.y")
        if terrain == "profile" and self.grid.mesh != "square":
            raise _problem("not allowed on a 'profile' terrain (1D)", "grid.mesh")
        self._maps_fit(terrain)
        if terrain != "profile" and self.numerics.limiter == "mc":
            # the 2D reconstruction has one limiter, Barth-Jespersen's: mc would be a no-op
            raise _problem("'mc' applies to profiles only; on grids and triangles order 2 "
                           "uses the Barth-Jespersen limiter (minmod's multidimensional "
                           "form): leave limiter out or write minmod", "numerics.limiter")
        return self

    def _maps_fit(self, terrain: str) -> None:
        """Maps, layers and forests from files need a 2D terrain; y ranges too."""
        if terrain != "profile":
            return
        mapped = list(map_fields(self.rheology))
        if mapped:
            raise _problem("a map needs a 2D terrain ('plane' or 'dem'); a profile takes a "
                           "number", f"rheology.{mapped[0]}")
        for block, what in (("entrainment", "layer"), ("forest", None)):
            where = getattr(self, block)
            where = getattr(where, what) if where is not None and what else where
            prefix = f"{block}.{what}" if what else block
            for name in ("raster", "polygon", "y"):
                if where is not None and getattr(where, name) is not None:
                    raise _problem(f"not on a 'profile' terrain (1D: give x, a range along "
                                   "the bed" + (", or a uniform depth" if what else "")
                                   + ")", f"{prefix}.{name}")

    def data_maps(self) -> dict[str, _Where]:
        """Every map of this scenario that may read a file, by its dotted field: the
        friction maps, the erodible layer, the forest, the registered sources' areas."""
        maps: dict[str, _Where] = {f"rheology.{name}": spec
                                   for name, spec in map_fields(self.rheology).items()}
        if self.entrainment is not None:
            maps["entrainment.layer"] = self.entrainment.layer
        if self.forest is not None:
            maps["forest"] = self.forest
        for k, source in enumerate(self.sources):  # registered sources' areas
            maps[f"sources.{k}"] = source
        return maps

    @model_validator(mode="after")
    def _physical_sense(self) -> Scenario:
        """Sizes that no shallow debris flow on Earth has, refused before any allocation.

        The map is at most MAX_EXTENT; it holds at least 2 cells along each axis; a release
        is not thicker than the map is long (the depth-averaged equations need a layer thin
        compared with its length: 1e200 m only overflows); at most MAX_SNAPSHOTS snapshots.
        DEM extents and thicknesses read from files are checked when the terrain is built.
        """
        t, g, r = self.terrain, self.grid, self.release
        if t.kind == "profile":
            spans = {"terrain.length": (t.length, g.dx, "grid.dx")}
        elif t.kind == "plane":
            (x0, x1), (y0, y1) = t.extent.x, t.extent.y
            spans = {"terrain.extent.x": (x1 - x0, g.dx, "grid.dx"),
                     "terrain.extent.y": (y1 - y0, g.dy or g.dx, "grid.dy" if g.dy else "grid.dx")}
        else:
            spans = {}
        for name, (span, d, d_name) in spans.items():
            if span > MAX_EXTENT:
                raise _problem(f"a map of {span:g} m is larger than the {MAX_EXTENT:g} m this "
                               "flat-bed model allows (a quarter of the Earth's circumference)",
                               name)
            if d > span / 2:
                raise _problem(f"must leave at least 2 cells along {name} ({span:g} m), "
                               f"got {d:g} m", d_name)
        field = "max_thickness" if r.kind == "parabola" else "thickness"
        thickness = getattr(r, field, None)
        if spans and thickness is not None:
            size = max(span for span, _, _ in spans.values())
            h = thickness * r.volume_factor
            if h > size:
                scaled = f" ({thickness:g} m x volume_factor {r.volume_factor:g})" if \
                    r.volume_factor != 1.0 else ""
                raise _problem(f"a release {h:g} m thick{scaled} is thicker than the map is "
                               f"long ({size:g} m): the depth-averaged equations need a layer "
                               "thin compared with the flow's length", f"release.{field}")
        layer = self.entrainment.layer if self.entrainment is not None else None
        for name in ("depth", "thickness", "default") if spans and layer is not None else ():
            size, depth = max(span for span, _, _ in spans.values()), getattr(layer, name)
            if depth is not None and depth > size:  # 1e16 m made a flow out of nothing
                raise _problem(f"an erodible layer {depth:g} m deep is deeper than the map "
                               f"is long ({size:g} m): the depth-averaged equations need a "
                               "layer thin compared with the flow's length",
                               f"entrainment.layer.{name}")
        n = self.time.end / self.output.every
        if n > MAX_SNAPSHOTS:
            raise _problem(f"time.end / output.every = {n:.4g} snapshots, more than the "
                           f"{MAX_SNAPSHOTS} a run stores: use output.every >= "
                           f"{self.time.end / MAX_SNAPSHOTS:.4g} s", "output.every")
        return self

    # --- provenance -------------------------------------------------------------------------

    def input_files(self) -> list[str]:
        """Every file a run of this scenario reads: the scenario file and its data files
        (DEM, domain, release, path line, friction maps, erodible layer, forest; their
        sidecars are found by :func:`avflow.files.protected`). What no command may write
        over."""
        files = [self._source_path]
        for block in (self.terrain, self.release):
            files += [getattr(block, name, None) for name in ("path", "domain")]
        for spec in self.data_maps().values():
            files += spec.files()
        if self.output.path is not None:
            files.append(self.output.path.line)
        files += [s.line for s in self.structures]
        if self.output.points is not None:
            files.append(self.output.points.file)
        for area in self.secondary_release.areas if self.secondary_release else ():
            files.append(getattr(area, "path", None))
        return [f for f in files if f]

    @property
    def source_path(self) -> str | None:
        """Absolute path of the scenario file (None for text or programmatic scenarios)."""
        return self._source_path

    @property
    def source_text(self) -> str:
        """The YAML text it was read from (the resolved YAML for derived scenarios)."""
        return self._source_text if self._source_text is not None else self.to_yaml()

    def locate(self, field: str) -> tuple[int, int] | None:
        """(line, column), 1-based, of a dotted field in the source text, or of its closest
        written parent; None when the scenario was not read from text."""
        return position(self._positions, dotted_parts(field))

    # --- identity and export ----------------------------------------------------------------

    def scenario_hash(self) -> str:
        """16 hex chars of sha256 over the resolved scenario, as canonical JSON.

        Comments, formatting and key order do not count, nor where the file lies: data
        files count by their content (with their companion files), not by their path (maps
        too: :meth:`data_maps`). A scenario without entrainment or forest hashes as it did
        before those blocks existed.
        """
        data = self.model_dump(mode="json")
        data["output"].pop("path", None)  # post-processing: the run does not depend on it
        if data["output"].get("pressure_classes") == [1.0, 3.0, 30.0]:  # the default: hashes
            data["output"].pop("pressure_classes")  # as before the field
        if data["output"].get("release_time") is None:  # unset: hashes as before the field
            data["output"].pop("release_time", None)
        # threads never change the answer (bit for bit); the automatic kernel hashes as before
        data["numerics"].pop("threads", None)
        if data["numerics"].get("kernel") == "auto":
            data["numerics"].pop("kernel")
        if data["numerics"].get("backend") == "cpu":  # hashes as before the field
            data["numerics"].pop("backend")
        if data["numerics"].get("time_scheme") == "auto":  # hashes as before the field
            data["numerics"].pop("time_scheme")
        for block in ("terrain", "release"):
            if "path" in data[block]:
                try:
                    data[block]["path"] = "sha256:" + _content_digest(data[block]["path"])
                except OSError as err:
                    raise ScenarioError.at(self, f"{block}.path", f"cannot read: {err}") from None
        for block in ("entrainment", "forest"):  # none: hashes as before the blocks
            if data.get(block) is None:
                data.pop(block, None)
        if not data.get("structures"):  # none: hashes as before the block
            data.pop("structures", None)
        if not data.get("sources"):  # none (no registered source): as before the field
            data.pop("sources", None)
        if data["output"].get("points") is None:  # none: hashes as before the field
            data["output"].pop("points", None)
        if data.get("secondary_release") is None:  # none: hashes as before the block
            data.pop("secondary_release", None)
        # the material counts by what it sets (density, stop rule), resolved above
        data["physics"].pop("material", None)
        files = [(("output", "points"), "file")] if data["output"].get("points") else []
        files += [(("secondary_release", "areas", k), "path") for k, a in enumerate(
            (data.get("secondary_release") or {}).get("areas", ())) if a.get("path")]
        for where, key in files:  # points and secondary areas count by their files' content
            node = data
            for part in where:
                node = node[part]
            if node.get(key):
                try:
                    node[key] = "sha256:" + _content_digest(node[key])
                except OSError as err:
                    raise ScenarioError.at(self, ".".join(map(str, where)) + f".{key}",
                                           f"cannot read: {err}") from None
        for k, structure in enumerate(data.get("structures") or ()):  # lines by content
            try:
                structure["line"] = "sha256:" + _content_digest(structure["line"])
            except OSError as err:
                raise ScenarioError.at(self, f"structures.{k}.line",
                                       f"cannot read: {err}") from None
        for field, spec in self.data_maps().items():  # maps count by their files' content
            node = data
            for key in field.split("."):
                node = node[int(key)] if isinstance(node, list) else node[key]
            for key in ("raster", "polygon"):
                if node.get(key):
                    try:
                        node[key] = "sha256:" + _content_digest(node[key])
                    except OSError as err:
                        raise ScenarioError.at(self, f"{field}.{key}",
                                               f"cannot read: {err}") from None
        canonical = json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=False)
        return hashlib.sha256(canonical.encode()).hexdigest()[:16]

    def to_yaml(self) -> str:
        """The resolved scenario as YAML (reads back to an equal scenario)."""
        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False,
                              default_flow_style=None, width=100)

    # --- variations -------------------------------------------------------------------------

    def density_note(self) -> str | None:
        """The line a run says where a snow law took snow's density because the scenario
        gives neither ``physics.density`` nor ``physics.material``; else None."""
        written = self._written if isinstance(self._written, dict) else {}
        physics = written.get("physics") if isinstance(written.get("physics"), dict) else {}
        if (self.rheology.law not in SNOW_LAWS or physics.get("density") is not None
                or physics.get("material") is not None):
            return None
        return (f"physics.density not given: {self.physics.density:g} kg/m^3, snow's, for "
                f"the snow law {self.rheology.law} (set physics.material or physics.density "
                "for another material)")

    def with_updates(self, updates: Mapping[str, Any]) -> Scenario:
        """A new scenario: this one as written, with dotted-path updates, validated again.

        ``{"release.volume_factor": 2.0, "rheology.delta_deg": 14.0}`` sets single fields;
        ``{"rheology": {"law": "pouliquen", ...}}`` replaces a whole block. Updates apply in
        order, as if the file had been edited: defaults are re-derived (output.every follows
        a new time.end) and relative data paths start at the original file's folder. The
        result keeps ``source_path``; its ``source_text`` is its own resolved YAML.
        """
        written = copy.deepcopy(self._written if self._written is not None
                                else self.model_dump(mode="json"))
        for key, value in updates.items():
            _set_dotted(written, key, _plain(value), self)
        scenario = _validate(written, path=self._source_path, base_dir=self._base_dir)
        scenario._source_text = scenario.to_yaml()
        return scenario


# =========================================================================================
# Validation errors -> ScenarioError
# =========================================================================================


@dataclass(frozen=True)
class _Union:
    """A discriminated union in the schema: pydantic puts the tag into error locations."""

    discriminator: str
    members: dict[str, type[BaseModel]]


SchemaNode = Union[type[BaseModel], _Union, None]  # None: a value, not a block


def _schema_node(field: FieldInfo) -> SchemaNode:
    """What a field holds: a model, a discriminated union of models, or a plain value."""
    return _node_of(field.annotation, field.discriminator, tuple(field.metadata))


def _node_of(annotation: Any, discriminator: Any = None, metadata: tuple = ()) -> SchemaNode:
    """:func:`_schema_node` of a type: optional blocks (``X | None``) are their block; a
    number-or-map field (:func:`_mappable`) a union whose tags are "number" and "map"."""
    if any(isinstance(m, _MapMarker) for m in metadata):
        return _Union("", {"number": None, "map": ParameterMap})
    if get_origin(annotation) is Annotated:
        inner, *extra = get_args(annotation)
        found = next((m.discriminator for m in extra
                      if isinstance(m, FieldInfo) and m.discriminator), None)
        return _node_of(inner, found or discriminator, tuple(extra))
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    args = get_args(annotation)
    if get_origin(annotation) in (Union, types.UnionType):
        rest = [a for a in args if a is not type(None)]
        if len(rest) == 1:  # optional: the block it holds when written
            return _node_of(rest[0], discriminator)
        if isinstance(discriminator, str):
            members = [m for m in rest if isinstance(m, type) and issubclass(m, BaseModel)]
            return _Union(discriminator, {
                tag: m for m in members
                for tag in get_args(m.model_fields[discriminator].annotation)})
    return None


def _walk(loc: tuple) -> tuple[tuple, SchemaNode]:
    """The YAML keys of a pydantic error location (tags dropped) and the schema node there."""
    keys: list = []
    node: SchemaNode = Scenario
    for part in loc:
        if isinstance(node, _Union):  # this part is the tag pydantic inserted, not a key
            node = node.members.get(part)
            continue
        keys.append(part)
        field = node.model_fields.get(part) if isinstance(node, type) else None
        node = _schema_node(field) if field else None
    return tuple(keys), node


_TYPE_NAMES = {"float": "a number", "int": "an integer", "bool": "true or false",
               "string": "a string", "list": "a list", "tuple": "a list",
               "dict": "a mapping (key: value)", "model": "a mapping (key: value)",
               "model_attributes": "a mapping (key: value)"}


def _explain(error: Mapping[str, Any]) -> tuple[tuple, str]:
    """YAML keys and message of one pydantic error."""
    kind, loc, ctx = error["type"], error["loc"], error.get("ctx") or {}
    keys, node = _walk(loc)
    got = show(error.get("input"))
    if kind == "missing":
        return keys, "required, but missing"
    if kind == "extra_forbidden":
        _, parent = _walk(loc[:-1])
        allowed = parent.model_fields if isinstance(parent, type) else ()
        hint = did_you_mean(loc[-1], allowed) or f"; expected one of: {', '.join(allowed)}"
        return keys, "unknown field" + hint
    if kind in ("union_tag_invalid", "union_tag_not_found") and isinstance(node, _Union):
        known = ", ".join(node.members)
        if kind == "union_tag_not_found":
            return keys + (node.discriminator,), f"required, one of: {known}"
        tag = ctx.get("tag", "")
        return (keys + (node.discriminator,),
                f"unknown {node.discriminator} {tag!r}{did_you_mean(tag, node.members)}; "
                f"known: {known}")
    if kind == "scenario":  # ours, from _problem
        return keys + dotted_parts(ctx.get("field")), error["msg"]
    if kind == "finite_number":
        return keys, f"must be a finite number, got {got}"
    if kind == "string_too_short":
        return keys, "must not be empty"
    if kind == "literal_error":
        return keys, f"must be {ctx.get('expected')}, got {got}"
    if kind in ("too_short", "too_long"):
        need = ctx.get("min_length") if kind == "too_short" else ctx.get("max_length")
        return keys, (f"must have at {'least' if kind == 'too_short' else 'most'} {need} items,"
                      f" got {ctx.get('actual_length')}")
    for prefix, name in _TYPE_NAMES.items():
        if kind in (f"{prefix}_type", f"{prefix}_parsing", f"{prefix}_from_float"):
            return keys, f"must be {name}, got {got}"
    return keys, error["msg"].removeprefix("Value error, ")


def _scenario_error(err: ValidationError, path: str | None,
                    positions: Mapping[tuple, tuple[int, int]]) -> ScenarioError:
    """One ScenarioError listing every problem pydantic found, in file order."""
    explained = [_explain(e) for e in err.errors(include_url=False)]
    # A misspelt key also makes the right spelling "missing": the hint already says it.
    hinted = {keys[:-1] + (m.group(1),) for keys, message in explained
              if (m := re.search(r"did you mean '([^']+)'", message))}
    problems = [Problem(message, path, dotted(keys), *(position(positions, keys) or ()))
                for keys, message in explained
                if not (message == "required, but missing" and keys in hinted)]
    problems.sort(key=lambda p: (p.line is None, p.line or 0, p.column or 0))
    return ScenarioError(problems=problems)


def _validate(written: Any, *, path: str | None, base_dir: str | None,
              positions: Mapping[tuple, tuple[int, int]] | None = None) -> Scenario:
    """Validate the mapping as written; keep what is needed to update it later."""
    positions = positions or {}
    base_dir = base_dir or (os.path.dirname(path) if path else os.getcwd())
    try:
        scenario = Scenario.model_validate(written, context={"base_dir": base_dir})
    except ValidationError as err:
        raise _scenario_error(err, path, positions) from None
    # Private attributes may be set on a frozen model: they are provenance, not content.
    scenario._source_path = path
    scenario._positions = dict(positions)
    scenario._written = written
    scenario._base_dir = base_dir
    return scenario


# =========================================================================================
# Dotted updates
# =========================================================================================


def _plain(value: Any) -> Any:
    """Plain Python values (NumPy scalars, from samplers, become floats and ints)."""
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if type(value).__module__ == "numpy" and hasattr(value, "item"):
        return value.item()
    return value


def _set_dotted(written: dict[str, Any], path: str, value: Any, scenario: Scenario) -> None:
    """Set ``written[a][b][c] = value`` for ``path = "a.b.c"``, checking the path first."""
    keys = tuple(path.split("."))
    node: SchemaNode = Scenario
    block: Any = written
    for depth, key in enumerate(keys):
        # Which models could hold this key: a union is narrowed by the block's written tag.
        if isinstance(node, _Union):
            tag = block.get(node.discriminator) if isinstance(block, dict) else None
            models = [node.members[tag]] if tag in node.members else list(node.members.values())
            models = [m for m in models if m is not None]  # a number is no block
        else:
            models = [node] if isinstance(node, type) else []
        model = next((m for m in models if key in m.model_fields), None)
        if model is None:
            known = sorted({name for m in models for name in m.model_fields})
            where = dotted(keys[:depth + 1])
            raise ScenarioError(f"unknown field{did_you_mean(key, known)}",
                                scenario.source_path, where)
        if depth == len(keys) - 1:
            block[key] = value
            return
        node = _schema_node(model.model_fields[key])
        if not isinstance(block.get(key), dict):
            # Not written (defaults), or written in short form (boundary: wall): start from
            # its resolved value so that the other fields keep their meaning.
            resolved = getattr(scenario, key, None) if depth == 0 else None
            block[key] = (resolved.model_dump(mode="json", exclude_unset=True)
                          if isinstance(resolved, Boundaries) else {})
        block = block[key]


# =========================================================================================
# Data files
# =========================================================================================


def _content_digest(path: str) -> str:
    """16 hex chars of sha256 over a data file and its companion files (.dbf, .prj, ...)."""
    main = Path(path)
    companions = {**DEM_SUFFIXES, **POLYGON_SUFFIXES}.get(main.suffix.lower(), ())
    files = [main] + [f for s in companions if (f := main.with_suffix(s)).is_file()]
    stamp = tuple((str(f), f.stat().st_mtime_ns, f.stat().st_size) for f in files)
    return _digest_files(stamp)


@functools.lru_cache(maxsize=64)
def _digest_files(stamp: tuple[tuple[str, int, int], ...]) -> str:
    """Cached on (path, mtime, size): a DEM is read once per process, not once per hash."""
    digest = hashlib.sha256()
    for name, _, _ in stamp:
        digest.update(Path(name).suffix.lower().encode())
        with open(name, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                digest.update(chunk)
    return digest.hexdigest()[:16]


# =========================================================================================
# Entry points
# =========================================================================================


def parse_scenario(text: str, source_path: str | os.PathLike | None = None,
                   base_dir: str | os.PathLike | None = None) -> Scenario:
    """Validate scenario YAML given as text.

    ``source_path`` names the file in messages; relative data paths start at ``base_dir``
    (default: the folder of ``source_path``, else the working directory).
    """
    path = os.path.abspath(source_path) if source_path is not None else None
    written, positions = read_yaml(text, path)
    scenario = _validate(written, path=path, positions=positions,
                         base_dir=os.path.abspath(base_dir) if base_dir is not None else None)
    scenario._source_text = text
    return scenario


def load_scenario(path: str | os.PathLike) -> Scenario:
    """Read and validate a scenario YAML file; any problem is a :class:`ScenarioError`."""
    text = read_text_file(path, "scenario")
    from avflow.scenario.yamlio import is_stdin_pipe

    # from a pipe (/dev/stdin): relative data paths start at the working folder, not /dev
    return parse_scenario(text, source_path=path,
                          base_dir=os.getcwd() if is_stdin_pipe(path) else None)


def write_json_schema(path: str | os.PathLike) -> None:
    """Write the JSON Schema of the scenario format (``scenarios/schema.json``, for editors)."""
    Path(path).write_text(json.dumps(Scenario.model_json_schema(), indent=1) + "\n")
