"""Ensemble files: a base scenario and its variations, expanded into fully resolved members.

An ensemble file names a base scenario (relative to the ensemble file) and how to vary it::

    name: seed-exponential-ensemble
    base: seed_exponential_coulomb.yaml
    vary:                               # cartesian product, keys in file order
      rheology:                         # whole blocks: mixes laws
        - {law: coulomb, delta_deg: 14.0}
        - {law: pouliquen, delta1_deg: 13.0, delta2_deg: 20.0, d: 1.0}
      release.volume_factor: [0.5, 1.0, 2.0]   # any scenario field by dotted path
    sample:                             # seeded Latin hypercube (scipy.stats.qmc)
      n: 20
      seed: 1
      ranges:
        rheology.delta_deg: [12.0, 24.0]
    thresholds: [0.1, 1.0, 5.0]         # m, peak-thickness exceedance maps (grid scenes)
    # or per peak map:  thresholds: {peak_thickness: [0.1, 1.0], peak_speed: [1.0, 10.0],
    #                                peak_pressure: [1.0, 3.0, 30.0]}   # m, m/s, kPa

Members are the cartesian product of ``vary`` (first key slowest) crossed with the ``sample``
points (each vary combination gets every sample point; the sample is applied after the vary
updates, so a sampled ``rheology.delta_deg`` lands in a varied Coulomb block). Each member is
a fully resolved, validated :class:`~avflow.scenario.schema.Scenario` and is named on disk by its
:meth:`~avflow.scenario.schema.Scenario.scenario_hash`.

Everything is checked here, before any member runs: every problem is one
:class:`EnsembleError` naming the ensemble file, the line:column and the field.
"""

from __future__ import annotations

import itertools
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from avflow.errors import AvflowError, ScenarioError
from avflow.scenario.schema import Scenario, load_scenario
from avflow.scenario.yamlio import did_you_mean, position, read_text_file, read_yaml

__all__ = ["EnsembleError", "Ensemble", "Member", "load_ensemble", "parse_ensemble",
           "ensemble_from", "from_scenarios", "apply_overrides", "parse_overrides",
           "DEFAULT_THRESHOLDS"]

#: Peak-thickness thresholds (m) of the exceedance-probability maps, unless the file says.
DEFAULT_THRESHOLDS = (0.1, 1.0, 5.0)
#: Peak-speed thresholds (m/s) of the exceedance maps, unless the file says; peak-pressure
#: thresholds default to the base scenario's output.pressure_classes (kPa).
DEFAULT_SPEED_THRESHOLDS = (1.0, 5.0, 10.0)
#: The peak maps with exceedance probabilities, and the units of their thresholds.
THRESHOLD_UNITS = {"peak_thickness": "m", "peak_speed": "m s-1", "peak_pressure": "kPa"}

_TOP_KEYS = ("name", "description", "base", "vary", "sample", "thresholds")
_SAMPLE_KEYS = ("n", "seed", "ranges", "calibration", "use")

#: Most members an ensemble may have unless told otherwise (``--max-members``,
#: ``$AVFLOW_MAX_MEMBERS``): each is built and validated before any runs, and what that costs
#: bounds it (docs/performance.md, "Ensemble members before they run").
MAX_MEMBERS = 10_000
ENV_MAX_MEMBERS = "AVFLOW_MAX_MEMBERS"


def member_limit(max_members: int | None = None) -> int:
    """The bound on the members of an ensemble: given, else $AVFLOW_MAX_MEMBERS, else
    :data:`MAX_MEMBERS`."""
    if max_members is not None:
        return max_members
    text = os.environ.get(ENV_MAX_MEMBERS, "").strip()
    if not text:
        return MAX_MEMBERS
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise EnsembleError(f"${ENV_MAX_MEMBERS}: must be a positive integer, got {text!r}")
    return value

#: Summaries copied into every member row (and into ensemble.nc).
SUMMARY_FIELDS = ("runout", "time_to_stop", "deposit_max_thickness", "deposit_length",
                  "deposit_volume", "release_volume", "outflow_volume", "mass_balance_error",
                  "travel_angle", "wall_time", "entrained_volume", "moving_volume_end",
                  "runout_angle", "reach_from_release_centroid")
#: Summaries a member file from before them may lack, and what they were then (no
#: entrainment existed: nothing was entrained; the moving volume: unknown).
SUMMARY_DEFAULTS = {"entrained_volume": 0.0, "moving_volume_end": float("nan"),
                    "runout_angle": float("nan"), "reach_from_release_centroid": float("nan")}
OK_STATUSES = ("at_rest", "ended_by_rule", "completed", "stopped")  # runner.SUCCESS_STATUSES


class EnsembleError(ScenarioError):
    """A bad ensemble file (same form as scenario errors: ``file:line:col: field: message``)."""


@dataclass(frozen=True)
class Member:
    """One member: its index, its resolved scenario and the values it was given."""

    index: int
    scenario: Scenario
    updates: dict  #: dotted path -> value, as applied to the base scenario
    scenario_hash: str

    @property
    def label(self) -> str:
        parts = []
        for key, value in self.updates.items():
            if isinstance(value, dict):
                inner = ", ".join(f"{k}={_fmt(v)}" for k, v in value.items())
                parts.append(f"{key}={{{inner}}}")
            else:
                parts.append(f"{key}={_fmt(value)}")
        return " ".join(parts)


def _fmt(value: Any) -> str:
    return f"{value:.6g}" if isinstance(value, float) else str(value)


@dataclass
class Ensemble:
    """A validated ensemble: base scenario, members and the settings of the outputs."""

    name: str
    path: str | None
    text: str
    base: Scenario
    members: list[Member]
    varied: list[str]  #: dotted paths as written under vary/sample (blocks included)
    thresholds: tuple[float, ...] = DEFAULT_THRESHOLDS
    description: str = ""
    sample: dict = field(default_factory=dict)
    #: thresholds of peak_speed (m/s) and peak_pressure (kPa) given in the file
    map_thresholds: dict = field(default_factory=dict)

    def exceedance_thresholds(self) -> dict[str, tuple[float, ...]]:
        """Thresholds of the exceedance-probability maps per peak map (units in
        :data:`THRESHOLD_UNITS`): the file's, else the defaults."""
        return {"peak_thickness": tuple(self.thresholds),
                "peak_speed": tuple(self.map_thresholds.get("peak_speed",
                                                            DEFAULT_SPEED_THRESHOLDS)),
                "peak_pressure": tuple(self.map_thresholds.get(
                    "peak_pressure", self.base.output.pressure_classes))}

    def parameters(self) -> dict[str, list]:
        """Member parameters as columns: every leaf under each varied path, resolved.

        A varied block (``rheology``) gives one column per field found in any member
        (``rheology.law``, ``rheology.delta_deg``, ...), None where a member's block has no
        such field. Values are read from the resolved member scenarios (defaults filled in).
        """
        dumps = [m.scenario.model_dump(mode="json") for m in self.members]
        columns: dict[str, list] = {}
        for path in self.varied:
            leaves: list[str] = []
            for d in dumps:
                for leaf in _leaves(_get(d, path), path):
                    if leaf not in leaves:
                        leaves.append(leaf)
            for leaf in leaves:
                columns[leaf] = [_get(d, leaf) for d in dumps]
        law = "rheology.law"
        if law not in columns:
            columns = {law: [d["rheology"]["law"] for d in dumps], **columns}
        else:  # the law first: it is the main grouping of every table and figure
            columns = {law: columns.pop(law), **columns}
        return columns


def _get(data: Any, dotted: str) -> Any:
    for key in dotted.split("."):
        if not isinstance(data, dict) or key not in data:
            return None
        data = data[key]
    return data


def _leaves(value: Any, prefix: str) -> list[str]:
    if isinstance(value, dict):
        return [leaf for k, v in value.items() for leaf in _leaves(v, f"{prefix}.{k}")]
    return [prefix] if value is not None else []


# =========================================================================================
# Parsing
# =========================================================================================


def parse_overrides(items) -> dict[str, tuple[Any, str]]:
    """``["grid.dx=5", ...]`` (``--set KEY=VALUE``, VALUE in YAML) -> ``{key: (value, text)}``.

    A malformed item is one :class:`~avflow.errors.AvflowError` naming it (exit code 2).
    """
    overrides: dict[str, tuple[Any, str]] = {}
    for item in items or ():
        key, sep, text = str(item).partition("=")
        key = key.strip()
        if not sep or not key or any(not part for part in key.split(".")):
            raise AvflowError(f"--set {item}: expected KEY=VALUE with KEY a dotted field, "
                              "e.g. --set grid.dx=5 or --set rheology.delta_deg=18")
        try:
            value = read_yaml(f"value: {text}\n", None)[0]["value"]
        except ScenarioError as err:  # a few characters of the value, and why
            shown = repr(text) if len(text) <= 40 else repr(text[:37] + "...")
            raise AvflowError(f"--set {key}: the value {shown} is not a YAML value "
                              f"({err.message})") from None
        except (TypeError, KeyError):
            raise AvflowError(f"--set {key}: the value {text!r} is not a YAML value") from None
        overrides[key] = (value, text)
    return overrides


def apply_overrides(scenario: Scenario, overrides: Mapping[str, Any]) -> Scenario:
    """``scenario.with_updates`` for ``--set`` (values, or ``(value, text)`` pairs from
    :func:`parse_overrides`): relative data paths still start at the scenario file's folder;
    a problem is one line naming the scenario file and the ``--set`` it comes from."""
    if not overrides:
        return scenario
    values = {k: (v[0] if isinstance(v, tuple) else v) for k, v in overrides.items()}
    texts = {k: (v[1] if isinstance(v, tuple) else str(v)) for k, v in overrides.items()}
    try:
        return scenario.with_updates(values)
    except ScenarioError as err:
        first = err.problems[0]
        field = first.field or ""
        key = next((k for k in values if field == k or field.startswith(k + ".")
                    or k.startswith(field + ".")), None)
        given = (f"--set {key}={texts[key]}" if key is not None
                 else " ".join(f"--set {k}={texts[k]}" for k in values))
        detail = f"{field}: " if field and field != key else ""
        raise ScenarioError(f"{given}: {detail}{first.message}",
                            scenario.source_path or scenario.name) from None


def load_ensemble(path: str | os.PathLike, overrides: Mapping[str, Any] | None = None,
                  max_members: int | None = None) -> Ensemble:
    """Read, validate and expand an ensemble file; any problem is one :class:`EnsembleError`.

    ``overrides`` (``--set``: dotted field -> value) change the base scenario before the
    variations apply (:func:`apply_overrides`); a field the ensemble varies cannot be set.
    """
    text = read_text_file(path, "ensemble", EnsembleError)
    return parse_ensemble(text, source_path=path, overrides=overrides,
                          max_members=max_members)


def parse_ensemble(text: str, source_path: str | os.PathLike | None = None,
                   overrides: Mapping[str, Any] | None = None,
                   base: Scenario | None = None, max_members: int | None = None) -> Ensemble:
    """Validate ensemble YAML given as text; ``base`` is relative to ``source_path``'s folder
    (the working folder without one), or given as a loaded :class:`Scenario`."""
    path = os.path.abspath(source_path) if source_path is not None else None
    try:
        data, positions = read_yaml(text, path)
    except ScenarioError as err:
        raise EnsembleError(problems=err.problems) from None

    def fail(keys: tuple, message: str) -> EnsembleError:
        line_col = position(positions, keys) or ()
        return EnsembleError(message, path, ".".join(map(str, keys)) or None, *line_col)

    for key in data:
        if key not in _TOP_KEYS:
            hint = did_you_mean(key, _TOP_KEYS) or f"; expected one of: {', '.join(_TOP_KEYS)}"
            raise fail((key,), "unknown field" + hint)

    # --- base scenario --------------------------------------------------------------------
    base_ref = data.get("base")
    if base is None:
        if base_ref is None:
            raise fail(("base",), "required, but missing: the base scenario file (relative "
                                  "to this file)")
        if not isinstance(base_ref, str) or not base_ref.strip():
            raise fail(("base",), f"must be the path of a scenario file, got {base_ref!r}")
        folder = os.path.dirname(path) if path else os.getcwd()
        base_path = Path(os.path.normpath(Path(folder) / Path(base_ref).expanduser()))
        if not base_path.is_file():
            raise fail(("base",), f"scenario file not found: {base_path} (relative paths "
                                  "start at the ensemble file's folder)")
        base = load_scenario(base_path)  # its own errors name its own file
    base = apply_overrides(base, overrides or {})

    name = data.get("name", base.name)
    if not isinstance(name, str) or not name.strip():
        raise fail(("name",), f"must be a non-empty string, got {name!r}")
    description = data.get("description", "")
    if not isinstance(description, str):
        raise fail(("description",), f"must be a string, got {description!r}")

    # --- thresholds -----------------------------------------------------------------------
    map_thresholds = _thresholds(data.get("thresholds", list(DEFAULT_THRESHOLDS)), fail)
    thresholds = map_thresholds.pop("peak_thickness", DEFAULT_THRESHOLDS)

    # --- vary -----------------------------------------------------------------------------
    vary = data.get("vary", {})
    if not isinstance(vary, dict):
        raise fail(("vary",), "must be a mapping of dotted field -> list of values, got "
                              f"{vary!r}")
    for key, values in vary.items():
        if not isinstance(values, list):
            raise fail(("vary", key), f"must be a list of values, got {values!r}")
        if not values:
            raise fail(("vary", key), "must be a non-empty list of values")
        if not _shadowed(key, vary):
            _check_path(base, key, values[0], fail, ("vary", key))

    # --- how many: counted before any member is built ---------------------------------------
    sample = data.get("sample")
    n = sample.get("n") if isinstance(sample, dict) else None
    n = n if isinstance(n, int) and not isinstance(n, bool) and n > 0 else 1
    count = math.prod(len(v) for v in vary.values()) * n
    limit = member_limit(max_members)
    if count > limit:
        where = ("sample", "n") if n > 1 else ("vary",)
        raise fail(where, f"{count:,} members, more than the limit of {limit:,} (each is "
                          "built and validated before any runs); give fewer, or raise the "
                          f"limit with --max-members or ${ENV_MAX_MEMBERS}")

    # --- sample ---------------------------------------------------------------------------
    points: list[dict] = [{}]
    sample_info: dict = {}
    if sample is not None:
        points, sample_info = _sample_points(sample, base, vary, fail,
                                             os.path.dirname(path) if path else os.getcwd())

    if not vary and sample is None:
        raise fail((), "an ensemble needs 'vary:' (cartesian product) or 'sample:' (Latin "
                       "hypercube), or both")

    # --- members --------------------------------------------------------------------------
    combos = [dict(zip(vary, values)) for values in itertools.product(*vary.values())]
    members: list[Member] = []
    seen: dict[str, int] = {}
    for combo in combos:
        for point in points:
            updates = {**combo, **point}
            index = len(members)
            try:
                scenario = base.with_updates(updates)
            except ScenarioError as err:
                raise _member_error(err, index, updates, vary, sample_info, fail) from None
            digest = scenario.scenario_hash()
            if digest in seen:
                first = seen[digest]
                raise fail(("vary",) if vary else ("sample",),
                           f"members {first} and {index} are the same scenario "
                           f"({members[first].label} / {Member(index, scenario, updates, digest).label}):"
                           " remove the repeated value")
            seen[digest] = index
            members.append(Member(index, scenario, updates, digest))

    varied = list(vary) + [k for k in sample_info.get("ranges", {}) if k not in vary]
    for key in overrides or {}:
        for v in varied:
            if key == v or key.startswith(v + ".") or v.startswith(key + "."):
                where = ("vary", v) if v in vary else ("sample", "ranges", v)
                raise fail(where, f"--set {key}: this ensemble varies {v}, which would "
                                  "override it in every member; set it in the vary list "
                                  "instead")
    return Ensemble(name=name.strip(), path=path, text=text, base=base, members=members,
                    varied=varied, thresholds=thresholds, description=description,
                    sample=sample_info, map_thresholds=map_thresholds)


def _thresholds(value: Any, fail) -> dict[str, tuple[float, ...]]:
    """``thresholds:`` as a list (peak thickness, m) or a mapping per peak map."""
    if isinstance(value, dict):
        if not value:
            raise fail(("thresholds",), "must name at least one of "
                                        f"{', '.join(THRESHOLD_UNITS)}")
        items = [(("thresholds", k), k, v) for k, v in value.items()]
    else:
        items = [(("thresholds",), "peak_thickness", value)]
    out = {}
    for keys, name, values in items:
        if name not in THRESHOLD_UNITS:
            hint = (did_you_mean(name, tuple(THRESHOLD_UNITS))
                    or f"; expected one of: {', '.join(THRESHOLD_UNITS)}")
            raise fail(keys, "unknown peak map" + hint)
        unit = THRESHOLD_UNITS[name]
        if not isinstance(values, list) or not values:
            raise fail(keys, f"must be a non-empty list of {name} thresholds ({unit}), got "
                             f"{values!r}")
        for i, t in enumerate(values):
            if not _is_number(t) or not t > 0:
                raise fail((*keys, i), f"must be a positive number ({unit}), got {t!r}")
        if len(set(values)) != len(values):
            raise fail(keys, "must not repeat a value")
        out[name] = tuple(float(t) for t in sorted(values))
    return out


def _is_number(value: Any) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value))


def _check_path(base: Scenario, key: str, value: Any, fail, keys: tuple) -> None:
    """An unknown dotted path is reported on the ensemble file, before members are built."""
    if not isinstance(key, str) or not key or any(not part for part in key.split(".")):
        raise fail(keys, f"must be a dotted field path such as 'rheology.delta_deg', got "
                         f"{key!r}")
    try:
        base.with_updates({key: value})
    except ScenarioError as err:
        if err.message.startswith("unknown field"):
            raise fail(keys, f"{err.field}: {err.message} (in the base scenario "
                             f"{os.path.basename(base.source_path or '')})") from None
        # Other problems are about the value: reported with the member that carries it.


def _shadowed(key: Any, vary: dict) -> bool:
    """A field inside a block that is itself varied (``rheology.d`` with ``rheology`` blocks):
    it exists in some members only, so it is checked member by member."""
    return isinstance(key, str) and any(key.startswith(f"{k}.") for k in vary)


def _sample_points(sample: Any, base: Scenario, vary: dict, fail, folder: str = ""
                   ) -> tuple[list[dict], dict]:
    """Latin hypercube points over the ranges, scaled to [min, max] (same seed, same points),
    or draws of a calibration's posterior (``calibration:``)."""
    from scipy.stats import qmc

    if not isinstance(sample, dict):
        raise fail(("sample",), f"must be a mapping with n, seed and ranges, got {sample!r}")
    for key in sample:
        if key not in _SAMPLE_KEYS:
            hint = (did_you_mean(key, _SAMPLE_KEYS)
                    or f"; expected one of: {', '.join(_SAMPLE_KEYS)}")
            raise fail(("sample", key), "unknown field" + hint)
    if "calibration" in sample:
        return _calibration_points(sample, base, vary, fail, folder)
    if "use" in sample:
        raise fail(("sample", "use"), "applies with calibration: (a calibration.nc) only")
    n = sample.get("n")
    if n is None:
        raise fail(("sample", "n"), "required, but missing: the number of members to draw")
    if not isinstance(n, int) or isinstance(n, bool) or n <= 0:
        raise fail(("sample", "n"), f"must be a positive integer, got {n!r}")
    seed = sample.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise fail(("sample", "seed"), f"must be a non-negative integer, got {seed!r}")
    ranges = sample.get("ranges")
    if not isinstance(ranges, dict) or not ranges:
        raise fail(("sample", "ranges"), "must be a non-empty mapping of dotted field -> "
                                         f"[min, max], got {ranges!r}")
    bounds = []
    for key, pair in ranges.items():
        keys = ("sample", "ranges", key)
        if (not isinstance(pair, list) or len(pair) != 2
                or not all(_is_number(v) for v in pair)):
            raise fail(keys, f"must be [min, max] (two numbers), got {pair!r}")
        if not pair[0] < pair[1]:
            raise fail(keys, f"must be [min, max] with min < max, got {pair!r}")
        if not _shadowed(key, vary):
            _check_path(base, key, pair[0], fail, keys)
        bounds.append((float(pair[0]), float(pair[1])))
    unit = qmc.LatinHypercube(d=len(bounds), rng=seed).random(n)
    lo, hi = [b[0] for b in bounds], [b[1] for b in bounds]
    scaled = qmc.scale(unit, lo, hi)
    points = [{key: float(v) for key, v in zip(ranges, row)} for row in scaled]
    return points, {"n": n, "seed": seed, "ranges": dict(ranges)}


def _calibration_points(sample: dict, base: Scenario, vary: dict, fail, folder: str
                        ) -> tuple[list[dict], dict]:
    """Members from ``avflow calibrate``'s calibration.nc: ``use: posterior`` (default),
    ``n`` of its MCMC draws picked at random (``seed``), or ``use: best``, its best fit (one
    point). Read as a file (xarray): the ensemble stage does not import the calibration."""
    import hashlib

    import numpy as np
    import xarray as xr

    if "ranges" in sample:
        raise fail(("sample", "ranges"), "give either ranges (Latin hypercube) or "
                                         "calibration (its posterior), not both")
    ref = sample["calibration"]
    if not isinstance(ref, str) or not ref.strip():
        raise fail(("sample", "calibration"), f"must be the path of a calibration.nc, got "
                                              f"{ref!r}")
    nc = Path(os.path.normpath(Path(folder) / Path(ref).expanduser()))
    use = sample.get("use", "posterior")
    if use not in ("posterior", "best"):
        raise fail(("sample", "use"), f"must be posterior or best, got {use!r}")
    seed = sample.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise fail(("sample", "seed"), f"must be a non-negative integer, got {seed!r}")
    try:
        with xr.open_dataset(nc, decode_times=False) as ds:
            names = [str(v) for v in ds["parameter"].values]
            if use == "best":
                rows = ds["best_fit"].values[None, :].astype(float)
            elif "posterior" not in ds:
                raise fail(("sample", "use" if "use" in sample else "calibration"),
                           f"{nc} holds no posterior draws (method "
                           f"{ds.attrs.get('method', '?')}): use: best, or calibrate with "
                           "method: posterior")
            else:
                rows = ds["posterior"].values.astype(float)
            method = str(ds.attrs.get("method", ""))
    except FileNotFoundError:
        raise fail(("sample", "calibration"), f"file not found: {nc} (relative paths "
                                              "start at the ensemble file's folder)") from None
    except (OSError, KeyError, ValueError) as err:
        raise fail(("sample", "calibration"), f"{nc}: not a calibration.nc of avflow "
                   f"calibrate ({type(err).__name__}: {err})") from None
    n = sample.get("n", 1 if use == "best" else None)
    if n is None:
        raise fail(("sample", "n"), "required, but missing: the number of posterior draws")
    if not isinstance(n, int) or isinstance(n, bool) or n <= 0:
        raise fail(("sample", "n"), f"must be a positive integer, got {n!r}")
    if use == "best" and n != 1:
        raise fail(("sample", "n"), "use: best gives one point; n must be 1 (or left out)")
    if n > len(rows):
        raise fail(("sample", "n"), f"{nc} holds {len(rows)} draws, fewer than n = {n}")
    pick = np.random.default_rng(seed).choice(len(rows), size=n, replace=False) \
        if use == "posterior" else np.arange(1)
    for key in names:
        if not _shadowed(key, vary):
            _check_path(base, key, float(rows[0][names.index(key)]), fail,
                        ("sample", "calibration"))
    points = [{k: float(f"{v:.9g}") for k, v in zip(names, rows[i])} for i in pick]
    digest = hashlib.sha256(nc.read_bytes()).hexdigest()
    return points, {"n": n, "seed": seed, "ranges": {k: None for k in names},
                    "calibration": str(nc), "calibration_sha256": digest, "use": use,
                    "calibration_method": method}


def _member_error(err: ScenarioError, index: int, updates: dict, vary: dict, sample_info: dict,
                  fail) -> EnsembleError:
    """A member that fails validation: reported at the vary/sample entry that made it."""
    culprit = None
    for key in list(updates):
        if err.field and (err.field == key or err.field.startswith(key + ".")
                          or key.startswith(err.field + ".")):
            culprit = key
    culprit = culprit or next(iter(updates))
    where = ("vary", culprit) if culprit in vary else ("sample", "ranges", culprit)
    value = updates[culprit]
    if culprit in vary and value in vary[culprit]:
        where = ("vary", culprit, vary[culprit].index(value))
    elif culprit in (sample_info or {}).get("ranges", {}):  # drawn: where it was drawn from
        where = ("sample", "ranges", culprit)
    label = Member(index, None, updates, "").label  # type: ignore[arg-type]
    detail = "; ".join(f"{p.field + ': ' if p.field else ''}{p.message}" for p in err.problems)
    return fail(where, f"member {index} ({label}) is not a valid scenario: {detail}")


# =========================================================================================
# Ensembles from Python: a file, a mapping, or a list of scenarios
# =========================================================================================


def ensemble_from(spec: Any, *, name: str | None = None,
                  overrides: Mapping[str, Any] | None = None) -> Ensemble:
    """An :class:`Ensemble` from a file path, a mapping or a list of scenarios.

    - a path: an ensemble YAML file (:func:`load_ensemble`);
    - a mapping with the keys of an ensemble file (``base``: a scenario file, relative to
      the working folder, or a :class:`Scenario`; ``vary``, ``sample``, ``thresholds``...);
    - a list of :class:`Scenario` objects (or scenario files): one member each, the
      varied fields found by comparing them (:func:`from_scenarios`);
    - an :class:`Ensemble`, returned as is.

    ``overrides`` (dotted field -> value) change the base scenario (files and mappings) or
    every scenario (lists), as ``--set`` does.
    """
    if isinstance(spec, Ensemble):
        return spec
    if isinstance(spec, (str, os.PathLike)):
        ensemble = load_ensemble(spec, overrides=overrides)
    elif isinstance(spec, Mapping):
        import yaml

        data = dict(spec)
        base = data.get("base")
        if isinstance(base, Scenario):
            data.pop("base")
        else:
            base = None
        if isinstance(data.get("base"), os.PathLike):
            data["base"] = os.fspath(data["base"])
        try:
            text = yaml.safe_dump(data, sort_keys=False)
        except yaml.YAMLError as err:
            raise EnsembleError(f"cannot write the ensemble mapping as YAML: {err}") from None
        ensemble = parse_ensemble(text, overrides=overrides, base=base)
    elif isinstance(spec, (list, tuple)):
        scenarios = [s if isinstance(s, Scenario) else load_scenario(s) for s in spec]
        ensemble = from_scenarios([apply_overrides(s, overrides or {}) for s in scenarios],
                                  name=name)
    else:
        raise EnsembleError(f"an ensemble is a file, a mapping or a list of scenarios, got "
                            f"{type(spec).__name__}")
    if name is not None:
        ensemble.name = name
    return ensemble


def from_scenarios(scenarios: list[Scenario], name: str | None = None,
                   thresholds: tuple[float, ...] = DEFAULT_THRESHOLDS) -> Ensemble:
    """An ensemble whose members are these scenarios, in order.

    The varied fields are the leaves whose resolved values differ between them (e.g.
    ``rheology.delta_deg``, ``release.path``); the first scenario is the base.
    """
    import yaml

    scenarios = list(scenarios)
    if not scenarios:
        raise EnsembleError("an ensemble needs at least one scenario")
    for i, s in enumerate(scenarios):
        if not isinstance(s, Scenario):
            raise EnsembleError(f"member {i}: not a Scenario (got {type(s).__name__}); load "
                                "it with avflow.load_scenario")
    dumps = [s.model_dump(mode="json") for s in scenarios]
    leaves: list[str] = []
    for d in dumps:
        for leaf in _leaves(d, "")[:]:
            leaf = leaf.lstrip(".")
            if leaf not in leaves:
                leaves.append(leaf)
    varied = [leaf for leaf in leaves if leaf != "name"
              and len({repr(_get(d, leaf)) for d in dumps}) > 1]
    members: list[Member] = []
    seen: dict[str, int] = {}
    for i, (s, d) in enumerate(zip(scenarios, dumps)):
        digest = s.scenario_hash()
        if digest in seen:
            raise EnsembleError(f"scenarios {seen[digest]} and {i} are the same scenario: "
                                "remove one")
        seen[digest] = i
        members.append(Member(i, s, {k: _get(d, k) for k in varied}, digest))
    name = name or f"{scenarios[0].name}-ensemble"
    text = yaml.safe_dump({"name": name, "members": [s.name for s in scenarios],
                           "varied": varied}, sort_keys=False)
    return Ensemble(name=name, path=None, text=text, base=scenarios[0], members=members,
                    varied=varied, thresholds=tuple(thresholds))
