"""Property-based fuzzing of the command line: mutated scenario, ensemble, calibration and
region files and ``--set`` values generated from the pydantic schema (with nesting thousands
of levels deep and sizes past every bound: budgets, counts, depths), hostile output paths,
and truncated or foreign NetCDF, GeoTIFF and Zarr inputs to ``export``, ``plot``, ``path``,
``report``, ``region`` (its own release files and store) and ``ensemble`` (a calibration's
calibration.nc).

Four invariants, whatever the input:
- never a Python traceback (``main`` returns 0, 1, 2 or 130; nothing escapes it);
- never a non-finite number (inf) in a file reported as a success;
- never a file left at a temporary name (``*.tmp``, ``*.lock``);
- never an existing file changed by a failed command.

Profiles (``AVFLOW_FUZZ``): ``ci`` (default: derandomized, the same few hundred examples
every time, a few minutes here) and ``long`` (thousands, random:
``AVFLOW_FUZZ=long pytest tests/test_fuzz.py``); what the long profile finds becomes a test
of its own in tests/test_reliability*.py.
Scenes stay on the 1D profile kernel at order 1 with Coulomb friction (structural choices
such as the terrain kind or the law are fuzzed with wrong values, not with other valid
ones, whose first compilation would take a minute each), ``time.max_steps`` is capped and
``--max-memory`` is small, so that an example costs a fraction of a second.
"""

import hashlib
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import yaml
from hypothesis import HealthCheck, example, given, seed, settings
from hypothesis import strategies as st

from avflow.cli import main
from avflow.scenario.schema import Scenario
from conftest import SCENARIOS

settings.register_profile("ci", max_examples=80, deadline=None, derandomize=True,
                          suppress_health_check=list(HealthCheck))
#: The newer commands run members (calibrate, region): fewer examples in CI.
settings.register_profile("ci-slow", max_examples=25, deadline=None, derandomize=True,
                          suppress_health_check=list(HealthCheck))
settings.register_profile("long-slow", max_examples=400, deadline=None, print_blob=True,
                          suppress_health_check=list(HealthCheck))
# print_blob: a failing example's reproduction line is printed, so it is never lost
settings.register_profile("long", max_examples=1500, deadline=None, print_blob=True,
                          suppress_health_check=list(HealthCheck))
PROFILE = os.environ.get("AVFLOW_FUZZ", "ci")
FUZZ = settings.get_profile(PROFILE)
SLOW = settings.get_profile("long-slow" if PROFILE == "long" else "ci-slow")

BASE = yaml.safe_load((SCENARIOS / "seed_dambreak_flat_dx20.yaml").read_text())
BASE["time"] = {"end": 4.0, "cfl": 0.5}
BASE["output"] = {"every": 1.0}
#: Always added: a run stays short whatever the mutation.
BOUNDS = ["--set", "time.max_steps=400", "--max-memory", "64M", "-q"]
#: Fields whose other valid values would switch kernels (a minute of compiling each).
STRUCTURAL = {"terrain.kind", "release.kind", "rheology.law", "grid.mesh", "numerics.order",
              "numerics.kernel", "terrain.slope.kind", "physics.dirac"}


def _leaves(schema: dict, defs: dict, prefix: str = "") -> dict[str, dict]:
    """Dotted path -> JSON Schema of every leaf field reachable from the profile scene's
    blocks (the discriminated unions: every branch's fields, as a mutation may name any)."""
    out = {}
    if "$ref" in schema:
        schema = defs[schema["$ref"].split("/")[-1]]
    branches = schema.get("anyOf") or schema.get("oneOf")
    if branches:
        for b in branches:
            out.update(_leaves(b, defs, prefix))
        return out
    if schema.get("type") == "object" and "properties" in schema:
        for name, sub in schema["properties"].items():
            out.update(_leaves(sub, defs, f"{prefix}.{name}" if prefix else name))
        return out
    if prefix:
        out[prefix] = schema
    return out


SCHEMA = Scenario.model_json_schema()
LEAVES = {k: v for k, v in _leaves(SCHEMA, SCHEMA["$defs"]).items()
          if not k.startswith("output.path")}

HOSTILE_NUMBERS = st.sampled_from([0, -1, 1e-300, 1e-200, 5e-324, 1e300, 1e308, -1e308,
                                   float("nan"), float("inf"), float("-inf"), 2**63, -2**63,
                                   10**400, 0.0, -0.0, 1e-9, 1e9, 3.5, 100])
#: Sizes around and far past the bounds (members, budgets, walkers, chunks, depths).
SIZES = st.sampled_from([-1, 0, 1, 2, 3, 16, 10_000, 10_001, 10**6, 10**9, 10**18, 2**63,
                         1e16, 1e308])
#: Nesting depths of a value (a scenario needs 4; 64 is the bound; PyYAML recursed past 1000).
DEPTHS = st.sampled_from([1, 5, 63, 64, 65, 200, 3000])
#: Stands for a deeply nested value in a structure, replaced in its text by :func:`_dump`
#: (PyYAML's dumper recurses too: it cannot write them).
DEEP = "__avflow_fuzz_deep_{}__"


def _nested(depth: int, mapping: bool) -> str:
    """A flow-style YAML value nested ``depth`` levels deep."""
    return ("{a: " * depth + "1" + "}" * depth) if mapping else ("[" * depth + "]" * depth)


@st.composite
def deep_values(draw):
    """A placeholder :func:`_dump` turns into a value nested DEPTHS deep."""
    return DEEP.format(f"{draw(DEPTHS)}_{'m' if draw(st.booleans()) else 'l'}")
WRONG_TYPES = st.one_of(st.text(max_size=20), st.booleans(), st.none(),
                        st.lists(st.integers(), max_size=3),
                        st.dictionaries(st.text(max_size=5), st.integers(), max_size=2),
                        st.sampled_from(["\u00e9\u00e8\u2013\U0001f600", "1e3", ".inf", "",
                                         "null", "~", "[1, 2]", "{a: 1}"]))


def _value_for(schema: dict):
    """Values for a field: in-range ones from its schema, its edges, and hostile ones."""
    kinds = []
    if "enum" in schema or "const" in schema:
        kinds.append(st.text(max_size=8))
    lo = schema.get("minimum", schema.get("exclusiveMinimum"))
    hi = schema.get("maximum", schema.get("exclusiveMaximum"))
    if schema.get("type") in ("number", "integer") or lo is not None or hi is not None:
        a = float(lo) if lo is not None else -1e6
        b = float(hi) if hi is not None else 1e6
        kinds.append(st.floats(min_value=a, max_value=b, allow_nan=False))
        kinds.append(st.sampled_from([a, b, np.nextafter(a, -np.inf), np.nextafter(b, np.inf)]))
    kinds += [HOSTILE_NUMBERS, SIZES, WRONG_TYPES]
    return st.one_of(*kinds)


def _set(data: dict, dotted: str, value) -> None:
    keys = dotted.split(".")
    for k in keys[:-1]:
        if not isinstance(data.get(k), dict):
            data[k] = {}
        data = data[k]
    data[keys[-1]] = value


def _delete(data: dict, dotted: str) -> None:
    keys = dotted.split(".")
    for k in keys[:-1]:
        data = data.get(k)
        if not isinstance(data, dict):
            return
    data.pop(keys[-1], None)


@st.composite
def mutated_scenarios(draw):
    data = yaml.safe_load(yaml.safe_dump(BASE))
    for _ in range(draw(st.integers(1, 4))):
        what = draw(st.sampled_from(["value", "value", "value", "missing", "extra", "junk",
                                     "deep"]))
        key = draw(st.sampled_from(sorted(LEAVES)))
        if what == "deep":
            _set(data, key, draw(deep_values()))
        elif what == "value":
            if key in STRUCTURAL:
                _set(data, key, draw(WRONG_TYPES))
            else:
                _set(data, key, draw(_value_for(LEAVES[key])))
        elif what == "missing":
            _delete(data, key if draw(st.booleans()) else key.split(".")[0])
        elif what == "extra":
            _set(data, key.rsplit(".", 1)[0] + "." + draw(st.text(min_size=1, max_size=8)),
                 draw(HOSTILE_NUMBERS))
        else:
            _set(data, key.split(".")[0], draw(WRONG_TYPES))
    return data


def _dump(data) -> str:
    try:
        text = yaml.safe_dump(data, allow_unicode=True, width=10**6)
    except (yaml.YAMLError, ValueError):  # 10**400 and the like: as text
        text = str(data)
    return re.sub(r"'?__avflow_fuzz_deep_(\d+)_([ml])__'?",
                  lambda m: _nested(int(m.group(1)), m.group(2) == "m"), text)


# --- the invariants ---------------------------------------------------------------------------


def _digests(folder: Path, skip: Path | None = None) -> dict:
    return {p: hashlib.sha256(p.read_bytes()).hexdigest()
            for p in folder.rglob("*") if p.is_file()
            and (skip is None or skip not in p.parents)}


def _no_inf(out: Path) -> None:
    """No infinite number in an output reported as a success (NetCDF, Zarr, CSV)."""
    out = Path(out)
    if out.suffix == ".nc" and out.is_file():
        with xr.open_dataset(out, decode_times=False) as ds:
            for name, var in ds.variables.items():
                if var.dtype.kind == "f":
                    assert not np.isinf(var.values).any(), name
    elif out.suffix == ".zarr" and out.is_dir():
        with xr.open_zarr(out) as ds:
            for name, var in ds.variables.items():
                if var.dtype.kind == "f":
                    assert not np.isinf(var.values).any(), name
    elif out.suffix == ".csv" and out.is_file():
        import pandas as pd

        table = pd.read_csv(out)
        numbers = table.select_dtypes("number").to_numpy(dtype=float)
        assert not np.isinf(numbers).any(), out


def _check(argv, folder: Path, outputs=(), own: Path | None = None) -> int:
    """Run ``avflow argv``; assert the four invariants; return the exit code. ``own``: the
    command's output folder, whose files a run that ends in error may have written (a
    region's finished releases, a calibration's members); every other file must stay."""
    before = _digests(folder, own)
    code = main([str(a) for a in argv])  # any exception escaping main fails the example
    assert code in (0, 1, 2, 130)
    left = [p for p in folder.rglob("*") if p.name.endswith((".tmp", ".lock"))]
    assert not left, left
    if code != 0:
        after = _digests(folder, own)
        changed = [p for p, d in before.items() if after.get(p) != d]
        assert not changed, changed
    else:
        for out in outputs:
            _no_inf(out)
    return code


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A folder with a finished run file (the profile), its plot, and a grid run file."""
    folder = tmp_path_factory.mktemp("fuzz")
    (folder / "base.yaml").write_text(_dump(BASE))
    assert main(["run", str(folder / "base.yaml"), "-o", str(folder / "run.nc"), "-q"]) == 0
    assert main(["run", str(SCENARIOS / "plane_box_2d.yaml"), "--set", "time.end=5", "-q",
                 "-o", str(folder / "grid.nc")]) == 0
    return folder


def _fresh(tmp_path_factory, work) -> Path:
    case = tmp_path_factory.mktemp("case")
    shutil.copy(work / "run.nc", case / "old.nc")  # an existing file a failure must keep
    return case


@FUZZ
@given(data=mutated_scenarios())
def test_mutated_scenario_files(tmp_path_factory, work, capsys, data):
    case = _fresh(tmp_path_factory, work)
    (case / "s.yaml").write_text(_dump(data))
    _check(["run", case / "s.yaml", "-o", case / "old.nc", *BOUNDS], case, [case / "old.nc"])
    capsys.readouterr()


@FUZZ
@given(sets=st.lists(st.tuples(st.sampled_from(sorted(LEAVES) + ["grid", "x.y.z", "", "time."]),
                               st.one_of(st.text(max_size=12), HOSTILE_NUMBERS.map(repr),
                                         SIZES.map(repr),
                                         DEPTHS.map(lambda d: _nested(d, d % 2 == 0)))),
                     min_size=1, max_size=3))
def test_set_values(tmp_path_factory, work, capsys, sets):
    case = _fresh(tmp_path_factory, work)
    argv = ["run", work / "base.yaml", "-o", case / "old.nc"]
    for key, value in sets:
        if key in STRUCTURAL:
            value = "'" + value.replace("'", "") + "'"
        argv += ["--set", f"{key}={value}"]
    _check(argv + BOUNDS, case, [case / "old.nc"])
    capsys.readouterr()


@st.composite
def ensemble_files(draw):
    spec = {"base": "base.yaml"}
    if draw(st.booleans()):
        spec["vary"] = {draw(st.sampled_from(["rheology.delta_deg", "time.end", "grid.dx",
                                              "nope.field", "release.thickness"])):
                        draw(st.one_of(st.lists(HOSTILE_NUMBERS, max_size=3), WRONG_TYPES))}
    if draw(st.booleans()) or "vary" not in spec:
        spec["sample"] = {"n": draw(st.one_of(st.integers(-2, 4), st.just(10**12), SIZES,
                                              WRONG_TYPES, deep_values())),
                          "seed": draw(st.one_of(st.integers(-1, 5), WRONG_TYPES)),
                          "ranges": {"rheology.delta_deg": draw(st.one_of(
                              st.lists(HOSTILE_NUMBERS, min_size=2, max_size=2), WRONG_TYPES))}}
    for key in draw(st.lists(st.sampled_from(["name", "thresholds", "description", "extra"]),
                             max_size=2)):
        spec[key] = draw(st.one_of(WRONG_TYPES, HOSTILE_NUMBERS))
    return spec


@FUZZ
@given(spec=ensemble_files())
# found by the long profile: a sampled value of a varied field, outside the schema (the
# error's place was looked for among the varied values: a traceback)
@example(spec={"base": "base.yaml", "vary": {"rheology.delta_deg": [0]},
               "sample": {"n": 1, "seed": 0, "ranges": {"rheology.delta_deg": [-1, 0]}}})
def test_mutated_ensemble_files(tmp_path_factory, work, capsys, spec):
    case = _fresh(tmp_path_factory, work)
    shutil.copy(work / "base.yaml", case / "base.yaml")
    (case / "e.yaml").write_text(_dump(spec))
    _check(["ensemble", case / "e.yaml", "-o", case / "ens", "--workers", "0",
            "--max-members", "3", "-q", "--set", "time.max_steps=400", "--max-memory", "64M"],
           case, list((case / "ens").glob("*.nc")))
    capsys.readouterr()


def _hostile_targets(case: Path) -> list:
    (case / "dir").mkdir(exist_ok=True)
    link = case / "link.nc"
    if not link.exists():
        link.symlink_to(case / "old.nc")
    return [case / "old.nc", link, case / "base.yaml", case / "dir", "/dev/null",
            case / "missing" / ".." / "old.nc", case / ("n" * 300), case / "old.nc" / "x"]


@FUZZ
@given(command=st.sampled_from(["run", "plot", "export", "path"]), pick=st.integers(0, 7))
def test_hostile_output_paths(tmp_path_factory, work, capsys, command, pick):
    case = _fresh(tmp_path_factory, work)
    shutil.copy(work / "base.yaml", case / "base.yaml")
    target = _hostile_targets(case)[pick]
    source = {"run": case / "base.yaml"}.get(command, case / "old.nc")
    argv = [command, source, "-o", target] + (BOUNDS if command == "run" else [])
    code = _check(argv, case)
    refused = {"run": (2, 3, 4), "plot": (0, 1, 3, 4, 5)}  # an input (or a link to one,
    if pick in refused.get(command, ()):                 # or a/missing/../it), a folder, a
        assert code == 2                                 # device: refused
    capsys.readouterr()


@FUZZ
@seed(20261205)  # the same examples in every profile: one that failed once fails again
@given(source=st.sampled_from(["run.nc", "grid.nc"]), cut=st.floats(0.0, 1.0),
       flips=st.lists(st.integers(0, 10**6), max_size=4),
       command=st.sampled_from(["export", "plot", "path", "report", "tif"]))
def test_truncated_and_foreign_inputs(tmp_path_factory, work, capsys, source, cut, flips,
                                      command):
    case = tmp_path_factory.mktemp("bad")
    data = bytearray((work / source).read_bytes())
    if command == "tif":  # a damaged GeoTIFF given as the DEM
        assert main(["export", str(work / "grid.nc"), "-o", str(case), "--variables",
                     "peak_thickness", "-q"]) == 0
        data = bytearray((case / "grid_peak_thickness.tif").read_bytes())
    for f in flips:
        data[f % len(data)] ^= 0xFF
    data = bytes(data[:int(cut * len(data))])
    if command == "tif":
        (case / "dem.tif").write_bytes(data)
        (case / "s.yaml").write_text(
            "name: t\nterrain: {kind: dem, path: dem.tif}\ngrid: {dx: 10}\nrelease: {kind: "
            "cylinder, center: [100, 100], radius: 30, thickness: 2}\nrheology: {law: "
            "coulomb, delta_deg: 20}\ntime: {end: 1}\n")
        argv = ["run", case / "s.yaml", "-o", case / "x.nc", *BOUNDS]
    elif command == "report":
        (case / "ens").mkdir()
        (case / "ens" / "ensemble.nc").write_bytes(data)
        argv = ["report", case / "ens"]
    else:
        (case / "in.nc").write_bytes(data)
        argv = [command, case / "in.nc"]
    _check(argv, case)
    capsys.readouterr()


# --- calibration files -----------------------------------------------------------------------

#: The calibration's base: the fuzzed profile, capped in the file itself (calibrate has no
#: --set): 400 steps at most a run.
CAL_BASE = {**BASE, "time": {**BASE["time"], "max_steps": 400}}
METHODS = ["grid", "lhs", "bayes-opt", "posterior"]


@st.composite
def observations(draw):
    kind = draw(st.sampled_from(["runout", "area", "deposit", "points", "volume"]))
    obs = {"kind": kind}
    if kind == "runout":
        obs["station"] = draw(st.one_of(st.floats(0, 2000), HOSTILE_NUMBERS, WRONG_TYPES))
    elif kind in ("area", "deposit"):
        a = draw(st.one_of(st.floats(0, 2000), HOSTILE_NUMBERS))
        obs["interval"] = draw(st.one_of(st.just([a, 1100.0]), st.lists(HOSTILE_NUMBERS,
                                                                          max_size=3)))
    elif kind == "points":
        n = draw(st.integers(1, 3))
        obs["points"] = [[draw(st.one_of(st.floats(0, 2000), HOSTILE_NUMBERS)), 0.0]
                         for _ in range(n)]
        obs["values"] = draw(st.lists(st.one_of(st.floats(-10, 100), HOSTILE_NUMBERS),
                                      min_size=n, max_size=n + draw(st.integers(0, 1))))
        obs["field"] = draw(st.sampled_from(["speed", "arrival_time", "thickness",
                                             "pressure", "nope"]))
    for key in draw(st.lists(st.sampled_from(["error", "weight", "threshold", "score"]),
                             max_size=2)):
        obs[key] = draw(st.one_of(HOSTILE_NUMBERS, WRONG_TYPES))
    return obs


@st.composite
def calibration_files(draw):
    lo = draw(st.one_of(st.just(0.0), HOSTILE_NUMBERS))
    hi = draw(st.one_of(st.just(8.0), HOSTILE_NUMBERS))
    spec = {"base": "base.yaml",
            "parameters": {draw(st.sampled_from(["rheology.delta_deg", "time.end", "grid.dx",
                                                 "nope.x", "physics.density"])): [lo, hi]},
            "observations": draw(st.lists(observations(), min_size=0, max_size=2)),
            "method": draw(st.sampled_from(METHODS + ["annealing"])),
            "budget": draw(st.one_of(st.sampled_from([2, 3]), SIZES, WRONG_TYPES)),
            "sensitivity": {"enabled": draw(st.booleans()),
                            "n": draw(st.one_of(st.just(16), SIZES))}}
    if draw(st.booleans()):
        spec["posterior"] = {"walkers": draw(st.one_of(st.just(8), SIZES)),
                             "steps": draw(st.one_of(st.just(100), SIZES)),
                             "burn": draw(st.one_of(st.just(10), SIZES)),
                             "checks": draw(st.one_of(st.just(0), SIZES))}
    if draw(st.booleans()):
        key = draw(st.sampled_from(["initial", "batch", "seed", "name", "extra"]))
        spec[key] = draw(st.one_of(SIZES, WRONG_TYPES, deep_values()))
    if draw(st.integers(0, 4)) == 0:
        spec[draw(st.sampled_from(sorted(spec)))] = draw(deep_values())
    return spec


@SLOW
@given(spec=calibration_files())
def test_mutated_calibration_files(tmp_path_factory, work, capsys, spec):
    case = _fresh(tmp_path_factory, work)
    (case / "base.yaml").write_text(_dump(CAL_BASE))
    (case / "c.yaml").write_text(_dump(spec))
    out = case / "cal"
    _check(["calibrate", case / "c.yaml", "-o", out, "--workers", "0", "-q"], case,
           [out / "calibration.nc", out / "calibration.csv"], own=out)
    capsys.readouterr()


# --- region files and their outputs --------------------------------------------------------------

REGION_BASE = {"name": "fuzz", "dem": "dem.tif",
               "releases": {"path": "rel.gpkg", "id_field": "id"},
               "scenario": {"rheology": {"law": "coulomb", "delta_deg": 24.0},
                            "time": {"end": 20.0, "max_steps": 400},
                            "numerics": {"order": 1}},
               "window": {"buffer": 40.0}, "merge": {"chunk": 16}}
REGION_KEYS = ["name", "dem", "releases.path", "releases.id_field", "releases.thickness",
               "releases.thickness_field", "releases.raster", "scenario.rheology.delta_deg",
               "scenario.time.end", "scenario.time.max_steps", "scenario.grid.dx",
               "window.buffer", "window.growth", "window.max_retries", "window.min_buffer",
               "window.search_radius", "merge.chunk", "merge.fields", "merge.thresholds",
               "scenarios.vary", "scenarios.sample.n", "scenarios.return_periods",
               "scenario.entrainment.layer.depth", "extra"]


@st.composite
def region_files(draw):
    data = yaml.safe_load(yaml.safe_dump(REGION_BASE))
    for _ in range(draw(st.integers(1, 3))):
        key = draw(st.sampled_from(REGION_KEYS))
        what = draw(st.sampled_from(["value", "value", "size", "missing", "deep"]))
        if what == "missing":
            _delete(data, key)
        elif what == "deep":
            _set(data, key, draw(deep_values()))
        elif what == "size":
            _set(data, key, draw(SIZES))
        else:
            _set(data, key, draw(st.one_of(HOSTILE_NUMBERS, WRONG_TYPES)))
    if "scenarios" in data and isinstance(data["scenarios"], dict) \
            and isinstance(data["scenarios"].get("sample"), dict):
        data["scenarios"]["sample"].setdefault("ranges", {"rheology.delta_deg": [20, 26]})
    return data


@pytest.fixture(scope="module")
def region_work(tmp_path_factory):
    """A DEM, a release layer, and a finished region (store, tables, release files)."""
    from test_region import BOXES, _dem, _releases

    folder = tmp_path_factory.mktemp("fuzz-region")
    _dem(folder)
    _releases(folder / "rel.gpkg", BOXES[:1])
    (folder / "r.yaml").write_text(_dump(REGION_BASE))
    assert main(["region", str(folder / "r.yaml"), "-o", str(folder / "out"), "--workers", "0",
                 "-q"]) == 0
    return folder


def _region_case(tmp_path_factory, region_work, with_output=False) -> Path:
    case = tmp_path_factory.mktemp("rcase")
    for name in ("dem.tif", "rel.gpkg", "r.yaml"):
        shutil.copy(region_work / name, case / name)
    if with_output:
        shutil.copytree(region_work / "out", case / "out")
    return case


@SLOW
@given(data=region_files())
def test_mutated_region_files(tmp_path_factory, region_work, capsys, data):
    case = _region_case(tmp_path_factory, region_work)
    (case / "r.yaml").write_text(_dump(data))
    out = case / "out"
    _check(["region", case / "r.yaml", "-o", out, "--workers", "0", "-q"], case,
           [out / "region.zarr", out / "releases.csv"], own=out)
    capsys.readouterr()


@SLOW
@given(pick=st.integers(0, 10**6), how=st.sampled_from(["flip", "cut", "delete", "empty"]),
       where=st.sampled_from(["region.zarr", "releases", "checksums", "releases.csv"]),
       flips=st.lists(st.integers(0, 10**6), min_size=1, max_size=4), cut=st.floats(0, 1),
       command=st.sampled_from(["export", "region"]))
def test_damaged_region_outputs(tmp_path_factory, region_work, capsys, pick, how, where, flips,
                                cut, command):
    case = _region_case(tmp_path_factory, region_work, with_output=True)
    out = case / "out"
    files = sorted(p for p in (out / where).rglob("*") if p.is_file()) if (out / where).is_dir() \
        else [out / where]
    target = files[pick % len(files)]
    data = bytearray(target.read_bytes())
    if how == "delete":
        target.unlink()
    elif how == "empty":
        target.write_bytes(b"")
    elif how == "cut":
        target.write_bytes(bytes(data[:int(cut * len(data))]))
    elif data:
        for f in flips:
            data[f % len(data)] ^= 0xFF
        target.write_bytes(bytes(data))
    if command == "export":
        code = _check(["export", out, "-o", case / "gis", "-q"], case)
        if where == "region.zarr" and how == "delete" and not target.name.startswith("."):
            assert code == 2  # a chunk missing: the store is damaged, never an empty map
    else:  # the rerun: a damaged release file is run again, the store made anew
        _check(["region", case / "r.yaml", "-o", out, "--workers", "0", "-q"], case,
               [out / "region.zarr", out / "releases.csv"], own=out)
    capsys.readouterr()


# --- a calibration's output as the input of a forecast -----------------------------------------


@pytest.fixture(scope="module")
def calibration_work(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz-cal")
    (folder / "base.yaml").write_text(_dump(CAL_BASE))
    (folder / "c.yaml").write_text(
        "base: base.yaml\nparameters:\n  rheology.delta_deg: [0.0, 0.5]\nobservations:\n"
        "  - {kind: points, field: speed, points: [[1010.0, 0.0]], values: [3.0]}\n"
        "method: lhs\nbudget: 3\nsensitivity: {enabled: false}\n")
    assert main(["calibrate", str(folder / "c.yaml"), "-o", str(folder / "cal"), "--workers",
                 "0", "-q"]) == 0
    return folder


@SLOW
@given(cut=st.floats(0, 1), flips=st.lists(st.integers(0, 10**6), max_size=4),
       use=st.sampled_from(["best", "posterior", "junk"]))
def test_damaged_calibration_file_in_a_forecast(tmp_path_factory, calibration_work, capsys,
                                                cut, flips, use):
    case = tmp_path_factory.mktemp("ccase")
    shutil.copy(calibration_work / "base.yaml", case / "base.yaml")
    data = bytearray((calibration_work / "cal" / "calibration.nc").read_bytes())
    for f in flips:
        data[f % len(data)] ^= 0xFF
    (case / "calibration.nc").write_bytes(bytes(data[:max(1, int(cut * len(data)))]))
    (case / "e.yaml").write_text(f"base: base.yaml\nsample: {{calibration: calibration.nc, "
                                 f"use: {use}, n: 2}}\n")
    _check(["ensemble", case / "e.yaml", "-o", case / "ens", "--workers", "0", "-q",
            "--max-members", "3", "--set", "time.max_steps=400"], case,
           list((case / "ens").glob("*.nc")), own=case / "ens")
    capsys.readouterr()


# --- release areas, alpha-beta coefficients, structures, extension files ---------------------

#: The numbers of ``avflow release-areas`` (each alone may be hostile; the rest default).
RELEASE_OPTIONS = ["--slope-min", "--slope-max", "--snow-depth", "--wind-direction",
                   "--wind-tolerance", "--threshold", "--max-curvature", "--min-area",
                   "--split-aspect", "--d0", "--reference-elevation", "--gradient"]
#: As typed on a command line: numbers in Python's and other spellings, and words.
TYPED_NUMBERS = st.one_of(HOSTILE_NUMBERS.map(repr), st.sampled_from(
    ["1_0", "0x10", "1e999", "-0", "nan", "inf", "-inf", "Infinity", "", " ", "1,5", "30",
     "45", "359.9999", "360", "11.4", "11.5", "0.5", "2.3", "20.0001"]))


@pytest.fixture(scope="module")
def release_work(tmp_path_factory):
    """A DEM (a 25-to-45-degree slope, 60 x 40 cells of 5 m) with its .prj."""
    import rasterio
    from rasterio.transform import from_origin

    folder = tmp_path_factory.mktemp("fuzz-pra")
    x = np.arange(2.5, 300.0, 5.0)
    drop = np.where(x < 150, np.tan(np.radians(25)) * x,
                    np.tan(np.radians(25)) * 150 + np.tan(np.radians(45)) * (x - 150))
    z = 2500.0 - np.tile(drop, (40, 1))
    with rasterio.open(folder / "dem.asc", "w", driver="AAIGrid", width=60, height=40,
                       count=1, dtype="float64", crs="EPSG:2056",
                       transform=from_origin(0, 200, 5, 5)) as ds:
        ds.write(z, 1)
    return folder


@FUZZ
@given(options=st.lists(st.tuples(st.sampled_from(RELEASE_OPTIONS), TYPED_NUMBERS),
                        min_size=1, max_size=3),
       target=st.sampled_from(["r.gpkg", "r.shp", "dem.shp", "dem.prj", "r.geojson"]))
# found by the long profile: a d0 of 1e-300 m gave thicknesses the file stored as 0
@example(options=[("--d0", "1e-300"), ("--gradient", "0")], target="r.shp")
def test_release_areas_options(tmp_path_factory, release_work, capsys, options, target):
    import pyogrio.raw

    case = tmp_path_factory.mktemp("pra")
    for name in ("dem.asc", "dem.prj"):
        shutil.copy(release_work / name, case / name)
    argv = ["release-areas", case / "dem.asc", "-o", case / target]
    for option, value in options:
        argv.append(f"{option}={value}")  # "=": a value starting with "-" stays a value
    try:
        code = _check(argv, case)
    except SystemExit as err:  # argparse: a value that is no number at all
        assert err.code == 2
        capsys.readouterr()
        return
    if target.startswith("dem."):
        assert code == 2  # the DEM's own .prj, or its sidecar: never replaced
    if code == 0:
        meta, *_, fields = pyogrio.raw.read(case / target)
        for name, values in zip(meta["fields"], fields):
            if values.dtype.kind == "f":
                assert np.isfinite(values).all(), name
            if name == "thickness":
                assert (values > 0).all() and (values <= 10 * 1.6).all()
    capsys.readouterr()


@FUZZ
@given(coefficients=st.lists(TYPED_NUMBERS, min_size=4, max_size=6))
def test_alpha_beta_coefficients(coefficients):
    from avflow.output.alphabeta import AlphaBetaError, alpha_beta, regression

    spec = ",".join(coefficients)
    try:
        reg = regression(spec)
    except AlphaBetaError:
        return
    assert "_" not in spec and "x" not in spec.lower()
    s = np.arange(0.0, 2000.0, 10.0)
    z = 1000.0 * np.exp(-s / 500.0)
    try:
        ab = alpha_beta(s, z, reg)
    except AlphaBetaError:
        return
    for angle in ab.alphas:
        assert 0.0 < angle < 90.0


STRUCTURE_PLANE = """
name: fuzz-structure
terrain: {kind: plane, slope_deg: 25.0, azimuth_deg: 180.0,
          extent: {x: [0.0, 200.0], y: [0.0, 400.0]}}
grid: {dx: 10.0}
release: {kind: cylinder, center: [100.0, 310.0], radius: 30.0, thickness: 3.0}
rheology: {law: coulomb, delta_deg: 20.0}
time: {end: 0.5, cfl: 0.5}
output: {every: 0.5}
"""
COORDS = st.one_of(st.floats(-50.0, 450.0), HOSTILE_NUMBERS)


@SLOW
@given(points=st.lists(st.tuples(COORDS, COORDS), min_size=1, max_size=5),
       kind=st.sampled_from(["dam", "wall"]),
       height=st.one_of(st.floats(0.1, 30.0), HOSTILE_NUMBERS),
       slope=st.one_of(st.floats(0.0, 89.0), HOSTILE_NUMBERS))
def test_structures(tmp_path_factory, capsys, points, kind, height, slope):
    import json

    case = tmp_path_factory.mktemp("structure")
    line = {"type": "FeatureCollection", "features": [{
        "type": "Feature", "properties": {},
        "geometry": {"type": "LineString", "coordinates": [list(p) for p in points]}}]}
    try:
        (case / "line.geojson").write_text(json.dumps(line, allow_nan=True))
    except ValueError:  # 10**400 in a line: JSON cannot say it
        return
    scene = yaml.safe_load(STRUCTURE_PLANE)
    structure = {"line": "line.geojson", "kind": kind, "height": height}
    if kind == "dam":
        structure["side_slope_deg"] = slope
    scene["structures"] = [structure]
    (case / "s.yaml").write_text(_dump(scene))
    code = _check(["run", case / "s.yaml", "-o", case / "s.nc", "-q", "--set",
                   "time.max_steps=100"], case, [case / "s.nc"])
    if code == 0:
        with xr.open_dataset(case / "s.nc") as ds:
            retained = ds["structure_retained_volume"].values
            beyond = ds["structure_overtopped_volume"].values
            released = float(ds["release_volume"])
            assert np.isfinite(retained).all() and np.isfinite(beyond).all()
            assert (retained + beyond <= released * (1 + 1e-9)).all()
            assert np.isfinite(ds["bed_elevation"].values[~np.isnan(
                ds["bed_elevation"].values)]).all()
    capsys.readouterr()


@FUZZ
@given(kind=st.sampled_from(["fifo", "device", "folder", "empty", "text", "binary",
                             "syntax", "raises", "exits", "peak_thickness", "self"]))
def test_extension_files(tmp_path_factory, work, capsys, kind):
    case = _fresh(tmp_path_factory, work)
    path = case / "ext.py"
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "device":
        path = Path("/dev/zero")
    elif kind == "folder":
        path.mkdir()
    else:
        path.write_bytes({
            "empty": b"", "text": b"hello there\n", "binary": bytes(range(256)),
            "syntax": b"def f(:\n", "raises": b"1 / 0\n", "exits": b"raise SystemExit(0)\n",
            "peak_thickness": b"from avflow import extend\n\n\n"
                              b"@extend.output_map('peak_thickness', units='m')\n"
                              b"def f(old, h, hu, hv, speed, t):\n    return old\n",
            "self": b"from avflow import extend\n"}[kind])
    target = path if kind == "self" else case / "old.nc"
    code = _check(["run", "--extensions", path, work / "base.yaml", "-o", target, *BOUNDS],
                  case)
    if kind in ("fifo", "device", "peak_thickness", "self", "syntax", "raises", "exits",
                "binary", "folder"):
        assert code == 2
    capsys.readouterr()
