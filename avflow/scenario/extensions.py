"""What a user adds to avflow without editing it: friction laws, mass sources and output maps,
each a plain Python function of scalars registered by name (the public API is
:mod:`avflow.extend`).

This module only keeps the registry (it sits below every stage, so the scenario schema, the
numerics and the output all read it). The numerics compile what is registered into the
kernels a run needs (:mod:`avflow.numerics.variants`); the scenario schema accepts a
registered law by its name (:func:`avflow.scenario.schema.add_law`); the output writes a
registered map with its CF attributes.

Registration must come before the first run that uses it, in the same process; a name is
registered once (a second registration of the same name is refused, so two plug-ins cannot
silently replace each other). The command line registers from files (:func:`load_file`:
``--extensions``, ``$AVFLOW_EXTENSIONS``), and the workers of an ensemble, a region or a
calibration load the same files before their members (:func:`loaded_files` travels with
the tasks).
"""

from __future__ import annotations

import hashlib
import os
import sys
import types
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from avflow.errors import AvflowError

#: Codes of registered friction laws: after the built-in ones, below the flag the kernels add
#: for parameters per cell (numerics.rheology.PER_CELL = 16)
FIRST_LAW_CODE = 6
LAST_LAW_CODE = 15
#: Parameter slots a registered law may use (the last of the kernels' 8 is the forest's)
MAX_LAW_PARAMETERS = 7
#: Parameters a registered source may take
MAX_SOURCE_PARAMETERS = 4


class ExtensionError(ValueError):
    """A registration that cannot be accepted (one line: what and why)."""


class ExtensionFileError(AvflowError):
    """An extension file that cannot be loaded (one line: the file, its line where known,
    and why; the command line exits with code 2)."""


@dataclass(frozen=True)
class FrictionLaw:
    """A registered friction law: ``function(*parameters, h, speed, normal_accel, g)`` returns
    ``(tau, drag)`` as the built-in laws do (numerics.rheology: ``tau`` the Coulomb-type
    threshold over the density, m^2/s^2; ``drag`` an implicit rate, 1/s)."""

    name: str
    function: Callable
    parameters: tuple[str, ...]
    bounds: dict
    reference: str
    code: int


@dataclass(frozen=True)
class OutputMap:
    """A registered running map: ``function(old, h, hu, hv, speed, t)`` returns the cell's
    new value after each accepted step (``old``: its value so far, ``initial`` at the start)."""

    name: str
    function: Callable
    units: str
    long_name: str
    cell_methods: str
    initial: float


@dataclass(frozen=True)
class Source:
    """A registered mass source: ``function(*parameters, h, speed, t)`` returns the rate
    (m/s of flow thickness) it adds to a cell with ``weight > 0`` (dry cells included),
    times that cell's weight (0..1: the share of the cell inside the source's area)."""

    name: str
    function: Callable
    parameters: tuple[str, ...]
    reference: str
    index: int


#: The attribute that marks a registered map in a run's file (export takes such maps too)
REGISTERED_MAP = "avflow_registered_map"

FRICTION_LAWS: dict[str, FrictionLaw] = {}
MAPS: dict[str, OutputMap] = {}
SOURCES: dict[str, Source] = {}

BUILT_IN_LAWS = ("coulomb", "pouliquen", "voellmy", "samosat", "velocity_weakening")
#: Names the output already uses (a map may not take one of them): the state's, and every
#: variable a run's file holds (avflow.output.cf's fields and summaries, the geometry, the
#: structures' and the run's bounds; tests/test_extension_api.py holds the list to them)
BUILT_IN_FIELDS = (
    "h", "hu", "hv", "u", "v", "speed", "flag", "peak_h", "peak_speed", "peak_pressure",
    "arrival_time", "rest_time", "deposit", "erodible", "forest", "entrained", "x", "y",
    "time", "mask", "dem", "flow_thickness",
    # the run file's variables
    "peak_thickness", "deposit_thickness", "flow_state", "bed_elevation", "slope_angle",
    "bed_change", "erodible_depth", "entrained_volume_series", "moving_volume",
    "center_of_mass_x", "center_of_mass_y", "center_of_mass_z", "cell_area", "crs",
    "duration", "duration_bounds", "structure_height", "structure_kind", "structure_name",
    "structure_overtopped_volume", "structure_retained_volume",
    # its summaries
    "compile_time", "deposit_length", "deposit_max_thickness", "deposit_volume",
    "drop_height", "entrained_volume", "film_volume", "kinetic_energy_end",
    "kinetic_energy_peak", "mass_balance_error", "moving_volume_end", "outflow_volume",
    "release_volume", "runout", "runout_angle", "reach_from_release_centroid",
    "secondary_release_volume", "supplied_volume",
    "time_to_stop", "travel_angle", "travel_length", "wall_time")


def _check_name(name: str, kind: str) -> None:
    if not (isinstance(name, str) and name.isidentifier() and name == name.lower()):
        raise ExtensionError(f"a {kind} name must be a lower-case identifier, got {name!r}")


def _check_function(function: Callable, kind: str, n_args: int) -> None:
    if not isinstance(function, types.FunctionType):
        raise ExtensionError(f"a {kind} is a plain Python function, got {function!r}")
    taken = function.__code__.co_argcount
    if taken != n_args:
        raise ExtensionError(f"the {kind} {function.__name__} takes {taken} arguments; it "
                             f"must take {n_args}")


def _check_parameters(parameters, most: int, kind: str, name: str, reserved) -> tuple:
    """``parameters`` as a tuple of at most ``most`` identifiers, none of them ``reserved``
    (the block's own keys)."""
    parameters = tuple(parameters)
    if len(parameters) > most:
        raise ExtensionError(f"a {kind} takes at most {most} parameters, {name} has "
                             f"{len(parameters)}")
    for p in parameters:
        _check_name(p, "parameter")
        if p in reserved:
            raise ExtensionError(f"a {kind}'s parameter may not be called {p!r}")
    return parameters


def register_friction_law(name: str, function: Callable, parameters, reference: str,
                          bounds: dict | None = None) -> FrictionLaw:
    """Register ``function`` as the friction law ``name`` (see :class:`FrictionLaw`);
    ``parameters``: its parameters' names, in the order the function takes them (at most
    7); ``bounds``: ``{parameter: (lo, hi)}``, checked when a scenario is read."""
    _check_name(name, "friction law")
    if name in BUILT_IN_LAWS or name in FRICTION_LAWS:
        raise ExtensionError(f"a friction law named {name!r} exists already")
    parameters = _check_parameters(parameters, MAX_LAW_PARAMETERS, "friction law", name,
                                   ("law",))
    _check_function(function, "friction law", len(parameters) + 4)
    code = FIRST_LAW_CODE + len(FRICTION_LAWS)
    if code > LAST_LAW_CODE:
        raise ExtensionError(f"at most {LAST_LAW_CODE - FIRST_LAW_CODE + 1} friction laws "
                             "can be registered")
    bounds = dict(bounds or {})
    unknown = sorted(set(bounds) - set(parameters))
    if unknown:
        raise ExtensionError(f"bounds given for {', '.join(unknown)}, not a parameter of {name}")
    law = FrictionLaw(name, function, parameters, bounds, str(reference), code)
    from avflow.scenario.schema import add_law

    add_law(name, parameters, bounds, function.__doc__ or "")
    FRICTION_LAWS[name] = law
    return law


def register_map(name: str, function: Callable, units: str, long_name: str,
                 cell_methods: str = "maximum", initial: float = 0.0) -> OutputMap:
    """Register ``function`` as the running map ``name`` (see :class:`OutputMap`), written to
    every run's file with these CF attributes and exported like the built-in maps;
    ``cell_methods``: how it sums up the run (CF 7.3: ``maximum``, ``minimum``, ``sum``,
    ``mean`` or ``point``)."""
    _check_name(name, "map")
    if name in BUILT_IN_FIELDS:
        raise ExtensionError(f"a map named {name!r} would replace the run file's own variable "
                             "of that name; give it another name")
    if name in MAPS:
        raise ExtensionError(f"a map named {name!r} exists already")
    _check_function(function, "map", 6)
    if cell_methods not in ("maximum", "minimum", "sum", "mean", "point"):
        raise ExtensionError(f"cell_methods of {name} must be maximum, minimum, sum, mean or "
                             f"point, got {cell_methods!r}")
    if not isinstance(initial, (int, float)) or isinstance(initial, bool):
        raise ExtensionError(f"the initial value of {name} must be a number, got {initial!r}")
    entry = OutputMap(name, function, str(units), str(long_name), str(cell_methods),
                      float(initial))
    MAPS[name] = entry
    return entry


def register_source(name: str, function: Callable, parameters, reference: str) -> Source:
    """Register ``function`` as the mass source ``name`` (see :class:`Source`)."""
    _check_name(name, "source")
    if name in SOURCES:
        raise ExtensionError(f"a source named {name!r} exists already")
    parameters = _check_parameters(parameters, MAX_SOURCE_PARAMETERS, "source", name,
                                   ("law", "raster", "polygon", "x", "y"))
    _check_function(function, "source", len(parameters) + 3)
    entry = Source(name, function, parameters, str(reference), len(SOURCES))
    from avflow.scenario.schema import add_source

    add_source(name, parameters, function.__doc__ or "")
    SOURCES[name] = entry
    return entry


def law_by_code(code: int) -> FrictionLaw | None:
    """The registered law of a kernel code (None: a built-in code)."""
    return next((law for law in FRICTION_LAWS.values() if law.code == code), None)


# --- extension files -------------------------------------------------------------------------

#: The extension files loaded in this process, by absolute path (their modules)
LOADED_FILES: dict[str, types.ModuleType] = {}
#: Files that failed to load here, with their error: a second try would find what the file
#: registered before it failed taken already, and say so instead of the real cause
_FAILED: dict[str, ExtensionFileError] = {}


def load_file(path: str | os.PathLike) -> str:
    """Run the extension file ``path`` as a module, so that its ``@extend...`` decorators
    register what it defines; once per process (a file loaded already is not run again).
    Returns its absolute path. Raises :class:`ExtensionFileError`: no such file, a syntax
    error, an exception while it runs, a registration refused (each with the file's line)."""
    import importlib.machinery
    import importlib.util

    shown = os.fspath(path)
    try:
        full = Path(path).expanduser().resolve(strict=True)
    except FileNotFoundError:
        raise ExtensionFileError(f"{shown}: no such file") from None
    except (OSError, RuntimeError) as err:  # a loop of links, a folder that cannot be read
        raise ExtensionFileError(f"{shown}: {getattr(err, 'strerror', None) or err}") from None
    key = str(full)
    if key in LOADED_FILES:
        return key
    if key in _FAILED:
        raise _FAILED[key]
    if full.is_dir():
        raise ExtensionFileError(f"{shown}: a folder, not a Python file")
    # one module name per path: two files of the same name in different folders both load
    stem = "".join(c if c.isalnum() else "_" for c in full.stem)
    name = f"avflow_extension_{stem}_{hashlib.sha1(key.encode()).hexdigest()[:8]}"
    loader = importlib.machinery.SourceFileLoader(name, key)  # any suffix, not only .py
    module = importlib.util.module_from_spec(
        importlib.util.spec_from_file_location(name, key, loader=loader))
    sys.modules[name] = module  # as an import does: pickle and dataclasses look it up there
    try:
        loader.exec_module(module)
    except (Exception, SystemExit) as err:  # noqa: BLE001 - reported in one line
        del sys.modules[name]
        _FAILED[key] = ExtensionFileError(_load_error(shown, key, err))
        raise _FAILED[key] from None
    LOADED_FILES[key] = module
    return key


def _load_error(shown: str, key: str, err: BaseException) -> str:
    """One line: where ``err`` arose (the file's line: a syntax error's, else the last of
    its lines the traceback passed) and what it says."""
    import traceback

    if isinstance(err, SyntaxError):
        where = shown if err.filename in (None, key) else err.filename
        where += f":{err.lineno}" if err.lineno else ""
        where += f":{err.offset}" if err.lineno and err.offset else ""
        return f"{where}: syntax error: {err.msg}"
    lines = [f.lineno for f in traceback.extract_tb(err.__traceback__) if f.filename == key]
    where = f"{shown}:{lines[-1]}" if lines and lines[-1] else shown
    text = " ".join(str(err).split())
    if isinstance(err, ExtensionError):  # the registry's own words say what was refused
        return f"{where}: {text}"
    return f"{where}: {type(err).__name__}" + (f": {text}" if text else "")


def load_files(paths, worker: bool = False) -> tuple[str, ...]:
    """:func:`load_file` of each of ``paths``, in order; their absolute paths. ``worker``:
    in a worker of an ensemble, a region or a calibration (the error says so: the file is
    to be found on that machine, at the path it had where the command ran)."""
    try:
        return tuple(load_file(p) for p in paths)
    except ExtensionFileError as err:
        if not worker:
            raise
        raise ExtensionFileError(f"{err} (on a dask worker, which loads the extension files "
                                 "from the paths they had where the command ran)") from None


def loaded_files() -> tuple[str, ...]:
    """The absolute paths of the extension files loaded in this process, in the order they
    were: what a worker loads before running a member of this process's ensemble."""
    return tuple(LOADED_FILES)


__all__ = ["ExtensionError", "ExtensionFileError", "FrictionLaw", "OutputMap", "Source",
           "FRICTION_LAWS", "MAPS", "SOURCES", "register_friction_law", "register_map",
           "register_source", "law_by_code", "load_file", "load_files",
           "loaded_files"]
