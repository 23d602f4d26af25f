"""Calibration files: a base scenario, parameter ranges, observations, a method, a budget.

::

    name: kot-back-analysis
    base: avakot_voellmy.yaml            # relative to this file
    parameters:                          # dotted path -> [min, max], as ensembles sample
      rheology.mu: [0.1, 0.5]
      rheology.xi: [500.0, 4000.0]
    observations:
      - kind: runout                     # runout point along a path line
        point: [1234.0, 5678.0]          # or station: 1520.0 (m along the line)
        line: path.shp                   # a profile is its own path (no line)
        error: 10.0                      # m, sigma of the likelihood
      - kind: area                       # impact area: polygon, raster, or interval
        polygon: impact.shp              # (profiles: interval: [x0, x1])
        field: pressure                  # peak field that marks the simulated area
        threshold: 1.0                   # kPa (pressure) or m (thickness)
        score: tversky                   # csi | f1 | tversky | auroc
        alpha: 0.5
        beta: 0.5
      - kind: deposit                    # deposit: thickness raster (RMSE) or polygon
        raster: deposit.tif
    method: bayes-opt                    # grid | lhs | bayes-opt | posterior
    budget: 40                           # model runs of the design

Everything is checked before any run; every problem is one :class:`CalibrationError`
(``file:line:col: field: message``, exit 2).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from avflow.errors import ScenarioError
from avflow.scenario.schema import Scenario, load_scenario
from avflow.scenario.yamlio import position, read_text_file, read_yaml

__all__ = ["CalibrationError", "CalibrationFile", "Calibration", "load_calibration",
           "parse_calibration", "METHODS"]

METHODS = ("grid", "lhs", "bayes-opt", "posterior")
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Finite = Annotated[float, Field(allow_inf_nan=False)]


class CalibrationError(ScenarioError):
    """A bad calibration file (``file:line:col: field: message``, exit 2)."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class _Observation(_Model):
    name: str | None = None
    """Label in tables and figures (default: kind and position in the list)."""
    weight: Positive = 1.0
    """w_i of the misfit sum_i w_i (d_i / sigma_i)^2."""
    error: Positive | None = None
    """sigma_i, in the units of the discrepancy d_i (defaults: see each kind)."""


class RunoutObservation(_Observation):
    """The runout point along a path: d = s_sim - s_obs (m). Default error: one cell."""

    kind: Literal["runout"]
    point: tuple[Finite, Finite] | None = None
    """x, y of the observed runout point (projected on the line)."""
    station: Finite | None = None
    """Distance along the line of the observed runout point (m); on a profile, its
    horizontal x (m)."""
    line: str | None = None
    """Path line file (.shp, .geojson, .json, .csv); a profile is its own path."""
    field: Literal["pressure", "thickness"] = "pressure"
    """Peak field whose threshold marks the simulated runout point (avflow path)."""
    threshold: Positive | None = None
    """kPa (pressure, default 1) or m (thickness, default the run's runout threshold)."""

    @model_validator(mode="after")
    def _one_position(self):
        if (self.point is None) == (self.station is None):
            raise ValueError("give exactly one of point: [x, y] and station: s (m along "
                             "the line)")
        return self


class _MapObservation(_Observation):
    raster: str | None = None
    """Raster file (GeoTIFF, ESRI ASCII, NetCDF): values > raster_threshold are inside."""
    polygon: str | None = None
    """Vector file (shapefile, GeoPackage, GeoJSON...): cells inside its polygons."""
    interval: tuple[Finite, Finite] | None = None
    """On a profile: [x0, x1], horizontal metres."""
    raster_threshold: Finite = 0.0
    score: Literal["csi", "f1", "tversky", "auroc"] = "tversky"
    alpha: Annotated[float, Field(ge=0)] = 0.5
    beta: Annotated[float, Field(ge=0)] = 0.5

    @model_validator(mode="after")
    def _one_source(self):
        given = [k for k in ("raster", "polygon", "interval") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError("give exactly one of raster:, polygon: and interval: [x0, x1]"
                             + (f" (got {', '.join(given)})" if given else ""))
        if self.interval is not None and not self.interval[0] < self.interval[1]:
            raise ValueError(f"interval must be [x0, x1] with x0 < x1, got "
                             f"{list(self.interval)}")
        return self


class AreaObservation(_MapObservation):
    """An impact area: d = 1 - score (CSI, F1, Tversky or AUROC). Default error 0.05."""

    kind: Literal["area"]
    field: Literal["pressure", "thickness", "speed"] = "pressure"
    threshold: Positive = 1.0
    """kPa (pressure), m (thickness) or m/s (speed)."""


class DepositObservation(_MapObservation):
    """A deposit: a thickness raster (d = RMSE over the union, m, default error 0.5 m) or a
    polygon / interval (d = 1 - score on deposit_thickness >= threshold, default 0.05)."""

    kind: Literal["deposit"]
    threshold: Positive = 0.1
    """m: a cell is in the deposit from this thickness."""


class PointsObservation(_Observation):
    """Values measured at points (peak speed, arrival time, peak flow thickness, peak
    pressure, or deposit thickness at the end, as probes and pits give): d = RMSE over the
    points of the run's value at the nearest cell minus the observed one. Default errors:
    1 m/s, 5 s, 0.1 m, 1 kPa, 0.1 m."""

    kind: Literal["points"]
    points: Annotated[list[tuple[Finite, Finite]], Field(min_length=1)]
    """[[x, y], ...] (on a profile: [[x, 0], ...], x horizontal)."""
    field: Literal["speed", "arrival_time", "thickness", "pressure", "deposit"] = "speed"
    """thickness: the peak flow thickness over the run; deposit: the thickness at the end."""
    values: Annotated[list[Finite], Field(min_length=1)]
    """One observed value per point: m/s, s since release, m, kPa or m."""

    @model_validator(mode="after")
    def _one_value_each(self):
        if len(self.values) != len(self.points):
            raise ValueError(f"values must have one value per point ({len(self.points)}), "
                             f"got {len(self.values)}")
        return self


Observation = Annotated[Union[RunoutObservation, AreaObservation, DepositObservation,
                              PointsObservation], Field(discriminator="kind")]
POINT_ERRORS = {"speed": 1.0, "arrival_time": 5.0, "thickness": 0.1, "pressure": 1.0,
                "deposit": 0.1}


class PosteriorSettings(_Model):
    walkers: Annotated[int, Field(ge=4)] = 24
    steps: Annotated[int, Field(ge=100)] = 2000
    burn: Annotated[int, Field(ge=0)] = 500
    checks: Annotated[int, Field(ge=0)] = 4
    """Model runs at posterior draws, to check the emulator where it matters."""
    design: Literal["lhs", "bayes-opt"] = "bayes-opt"

    @model_validator(mode="after")
    def _burn(self):
        if self.burn >= self.steps:
            raise ValueError(f"burn ({self.burn}) must be less than steps ({self.steps})")
        return self


class SensitivitySettings(_Model):
    enabled: bool = True
    n: Annotated[int, Field(ge=16)] = 512
    """SALib's base sample size (N (d + 2) emulator evaluations)."""


class CalibrationFile(_Model):
    name: str | None = None
    description: str = ""
    base: str
    parameters: dict[str, tuple[Finite, Finite]]
    observations: Annotated[list[Observation], Field(min_length=1)]
    method: Literal["grid", "lhs", "bayes-opt", "posterior"] = "bayes-opt"
    budget: Annotated[int, Field(ge=2)] = 40
    initial: Annotated[int, Field(ge=2)] | None = None
    """Space-filling start of bayes-opt (default: max(5, 4 d), at most the budget)."""
    batch: Annotated[int, Field(ge=1)] | None = None
    """Runs per bayes-opt batch (default: the number of workers, 1 here)."""
    seed: Annotated[int, Field(ge=0)] = 0
    posterior: PosteriorSettings = PosteriorSettings()
    sensitivity: SensitivitySettings = SensitivitySettings()

    @model_validator(mode="after")
    def _ranges(self):
        if not self.parameters:
            raise ValueError("parameters: needs at least one dotted field -> [min, max]")
        return self


@dataclass
class Calibration:
    """A validated calibration: the file, its base scenario, resolved observation files."""

    spec: CalibrationFile
    path: str | None
    text: str
    base: Scenario
    names: list[str]  #: parameter dotted paths, in file order
    bounds: list[tuple[float, float]]
    files: dict = field(default_factory=dict)  #: (observation index, key) -> absolute path

    @property
    def name(self) -> str:
        return self.spec.name or f"{self.base.name}-calibration"

    def label(self, k: int) -> str:
        obs = self.spec.observations[k]
        return obs.name or f"{obs.kind}{k}"

    def error(self, k: int) -> float:
        """sigma_k: the file's, else the default of its kind (stated in the report)."""
        obs = self.spec.observations[k]
        if obs.error is not None:
            return float(obs.error)
        if obs.kind == "runout":
            return float(self.base.grid.dx)
        if obs.kind == "deposit" and obs.raster is not None:
            return 0.5
        if obs.kind == "points":
            return POINT_ERRORS[obs.field]
        return 0.05

    def initial(self) -> int:
        n = self.spec.initial or max(5, 4 * len(self.names))
        return min(n, self.spec.budget)


def load_calibration(path: str | os.PathLike) -> Calibration:
    # a regular file of at most 1 MiB, as scenario files (/dev/zero read without end)
    text = read_text_file(path, "calibration", CalibrationError)
    return parse_calibration(text, source_path=path)


_KINDS = ("runout", "area", "deposit", "points")


def parse_calibration(text: str, source_path: str | os.PathLike | None = None,
                      base: Scenario | None = None) -> Calibration:
    """Validate calibration YAML; relative paths start at ``source_path``'s folder."""
    path = os.path.abspath(source_path) if source_path is not None else None
    try:
        data, positions = read_yaml(text, path)
    except ScenarioError as err:
        raise CalibrationError(problems=err.problems) from None

    def fail(keys: tuple, message: str) -> CalibrationError:
        line_col = position(positions, keys) or ()
        return CalibrationError(message, path, ".".join(map(str, keys)) or None, *line_col)

    if base is not None and "base" not in data:
        data = {**data, "base": base.source_path or "<scenario>"}
    try:
        spec = CalibrationFile.model_validate(data)
    except ValidationError as err:
        first = err.errors()[0]
        keys = tuple(first["loc"])
        if len(keys) > 2 and keys[0] == "observations" and keys[2] in _KINDS:
            keys = keys[:2] + keys[3:]  # the tag pydantic inserts for the union
        message = first["msg"].removeprefix("Value error, ")
        if first["type"] == "extra_forbidden":
            message = "unknown field"
        elif first["type"] == "missing":
            message = "required, but missing"
        elif first["type"] == "union_tag_invalid":
            message = f"kind must be one of {', '.join(_KINDS)}"
        elif first["type"] == "union_tag_not_found":
            keys = keys + ("kind",)
            message = f"required, but missing: one of {', '.join(_KINDS)}"
        raise fail(keys, message) from None

    folder = os.path.dirname(path) if path else os.getcwd()
    if base is None:
        base_path = Path(os.path.normpath(Path(folder) / Path(spec.base).expanduser()))
        if not base_path.is_file():
            raise fail(("base",), f"scenario file not found: {base_path} (relative paths "
                                  "start at the calibration file's folder)")
        base = load_scenario(base_path)  # its own errors name its own file

    names, bounds = [], []
    for key, (lo, hi) in spec.parameters.items():
        keys = ("parameters", key)
        if not lo < hi:
            raise fail(keys, f"must be [min, max] with min < max, got {[lo, hi]}")
        if key.split(".")[0] in ("grid", "terrain"):
            # the observations are put on the cells once: every run must share them
            raise fail(keys, "the grid and the terrain cannot be calibrated (every run is "
                             "scored on the same cells); set them in the base scenario")
        for value in (lo, hi):
            try:
                base.with_updates({key: float(value)})
            except ScenarioError as err:
                detail = f"{err.field}: {err.message}" if err.field else err.message
                raise fail(keys, f"{detail} (in the base scenario "
                                 f"{os.path.basename(base.source_path or '')})") from None
        names.append(key)
        bounds.append((float(lo), float(hi)))

    files = {}
    profile = base.terrain.kind == "profile"
    for k, obs in enumerate(spec.observations):
        for attr in ("line", "raster", "polygon"):
            value = getattr(obs, attr, None)
            if value is None:
                continue
            full = Path(os.path.normpath(Path(folder) / Path(value).expanduser()))
            if not full.is_file():
                raise fail(("observations", k, attr), f"file not found: {full} (relative "
                                                      "paths start at the calibration "
                                                      "file's folder)")
            files[(k, attr)] = str(full)
        if profile and any(getattr(obs, a, None) is not None
                           for a in ("line", "raster", "polygon")):
            attr = next(a for a in ("line", "raster", "polygon")
                        if getattr(obs, a, None) is not None)
            raise fail(("observations", k, attr), "the base scenario is a profile: give "
                       "interval: [x0, x1] (areas) or station: s (runout) instead of files")
        if not profile and getattr(obs, "interval", None) is not None:
            raise fail(("observations", k, "interval"), "interval: [x0, x1] applies to "
                       "profiles; on a map give raster: or polygon:")
        if obs.kind == "runout" and not profile and obs.line is None:
            raise fail(("observations", k, "line"), "required on a map: the path line "
                       "along which the runout is measured (.shp, .geojson, .csv)")
        if obs.kind == "runout" and profile and obs.point is not None:
            raise fail(("observations", k, "point"), "on a profile give station: x "
                       "(horizontal m) instead")
    if spec.method == "grid":
        levels = _levels(spec.budget, len(names))
        if levels < 2:
            raise fail(("budget",), f"a grid over {len(names)} parameters needs at least "
                                    f"{2 ** len(names)} runs (2 per axis), got {spec.budget}")
    _check_sizes(spec, len(names), fail)
    cal = Calibration(spec, path, text, base, names, bounds, files)
    from avflow.calibration.observe import check_observations

    check_observations(cal, fail)
    return cal


#: Posterior draws kept (walkers x steps; 8 bytes per parameter each, and one emulator
#: evaluation each): 1e7 is some 30 s of emcee here and 80 MB per parameter.
MAX_POSTERIOR_DRAWS = 10_000_000
#: Emulator evaluations of the Sobol indices (SALib: n (d + 2) points).
MAX_SOBOL_POINTS = 10_000_000


def _check_sizes(spec: CalibrationFile, d: int, fail) -> None:
    """What the file asks for, counted before anything runs (a budget of 1e9 grew to
    20 GB before the system killed it, with nothing said): model runs against the
    ensembles' member limit, posterior draws and Sobol points against their bounds."""
    from avflow.ensemble.spec import ENV_MAX_MEMBERS, member_limit
    from avflow.simulation.resources import human

    try:
        limit = member_limit()
    except ScenarioError as err:
        raise fail((), err.message) from None
    checks = spec.posterior.checks if spec.method == "posterior" else 0
    for keys, runs in ((("budget",), spec.budget), (("posterior", "checks"), checks),
                       (("budget",), spec.budget + checks)):
        if runs > limit:
            raise fail(keys, f"{runs:,} model runs, more than the limit of {limit:,} (each "
                             "run is a member file of the calibration; a larger limit: "
                             f"${ENV_MAX_MEMBERS})")
    if spec.method == "posterior":
        post = spec.posterior
        walkers = max(post.walkers, 2 * d + 2)
        draws = walkers * post.steps
        if draws > MAX_POSTERIOR_DRAWS:
            raise fail(("posterior",), f"walkers x steps = {walkers:,} x {post.steps:,} = "
                                       f"{draws:,} draws (about {human(8 * d * draws)} in "
                                       f"memory), more than the limit of "
                                       f"{MAX_POSTERIOR_DRAWS:,}: use fewer steps or walkers")
    if spec.sensitivity.enabled:
        points = spec.sensitivity.n * (d + 2)
        if points > MAX_SOBOL_POINTS:
            raise fail(("sensitivity", "n"), f"n (d + 2) = {spec.sensitivity.n:,} x {d + 2} = "
                                             f"{points:,} emulator evaluations (about "
                                             f"{human(8 * (d + 1) * points)} in memory), "
                                             f"more than the limit of {MAX_SOBOL_POINTS:,}")


def _levels(budget: int, d: int) -> int:
    """Points per axis of a grid design within the budget."""
    n = int(math.floor(budget ** (1.0 / d) + 1e-9))
    return n
