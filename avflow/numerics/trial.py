"""A user's friction law, source or map tried before anything compiles.

Each registered function a run uses (:mod:`avflow.extend`) is called once in Python with
typical numbers (the run's own parameters, a few thicknesses and speeds, dry-to-deep and
rest-to-fast), and compiled alone: a wrong arity, a wrong return shape, a non-finite or
negative friction, an exception or a construct Numba cannot compile is one line naming the
user's file and line (exit 2), before the kernels compile for a minute and fail with
Numba's traceback. After a run failed on a non-finite state, :func:`suspect` looks wider
for the value that made it.
"""

from __future__ import annotations

import dis
import itertools
import math
import re
import traceback
import types

import numpy as np
from numba import njit

from avflow.codekey import is_users
from avflow.scenario.extensions import ExtensionFileError

G = 9.81
#: the trial's thicknesses (m) and speeds (m/s): a film to a deep flow, rest to fast
THICKNESSES = (1e-3, 0.1, 1.0, 10.0)
SPEEDS = (0.0, 0.5, 5.0, 50.0)
#: the normal acceleration on a 35-degree slope (m/s^2)
NORMAL = G * math.cos(math.radians(35.0))
#: where :func:`suspect` looks after a failure
WIDE_THICKNESSES = tuple(np.geomspace(1e-6, 1e3, 19))
WIDE_SPEEDS = (0.0, *np.geomspace(1e-6, 500.0, 17))
WIDE_NORMALS = (0.0, NORMAL, 3.0 * G)


def _where(fn, err: BaseException | None = None) -> str:
    """``file:line`` of ``fn``: the last of its file's lines ``err``'s traceback passed, else
    the line the function starts on."""
    code = fn.__code__
    line = code.co_firstlineno
    if err is not None:
        lines = [f.lineno for f in traceback.extract_tb(err.__traceback__)
                 if f.filename == code.co_filename and f.lineno]
        line = lines[-1] if lines else line
    return f"{code.co_filename}:{line}"


def _text(err: BaseException) -> str:
    """``err``'s message on one line, without Numba's colours; a Numba error's first line
    that says what is wrong."""
    lines = [re.sub(r"\x1b\[[0-9;]*m", "", line).strip() for line in str(err).splitlines()]
    lines = [line for line in lines if line]
    from numba.core.errors import NumbaError

    if isinstance(err, NumbaError):  # its first line that says what, not where or how
        said = [line for line in lines if not line.startswith(
            ("Failed in", "During:", "File", ">>>", "^", "Resolution", "There are", "- Of",
             "raised from", "Overload", "With argument", "Rejected", "<source", "[", "def "))]
        lines = said[:1] or lines[:1]
    return " ".join(" ".join(lines).split()).rstrip(":")


def _numba_line(err: BaseException, fn) -> str:
    """``file:line`` in ``fn``'s file where Numba's message points (the last mention), else
    :func:`_where`."""
    name = fn.__code__.co_filename
    base = re.escape(name.rsplit("/", 1)[-1])
    found = re.findall(rf'(?:{base}\"?, line (\d+)|{base} \((\d+)\))', str(err))
    lines = [a or b for a, b in found]
    return f"{name}:{lines[-1]}" if lines else _where(fn)


def _number(value) -> float | None:
    """``value`` as a float when it is a real number (not a bool), else None."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        return None
    if isinstance(value, (complex, np.complexfloating)):
        return None
    return float(value)


def _call(entry, kind: str, args: tuple, names: tuple):
    """``entry.function(*args)``, an exception turned into one line."""
    try:
        return entry.function(*args)
    except Exception as err:  # noqa: BLE001 - the user's code: any exception, one line
        given = ", ".join(f"{n}={a:.6g}" for n, a in zip(names, args))
        text = _text(err)
        raise ExtensionFileError(
            f"{_where(entry.function, err)}: the {kind} {entry.name!r} raised "
            f"{type(err).__name__}{': ' + text if text else ''} (tried with {given})"
        ) from None


def _law_values(law, row, h, speed, normal):
    """The pair a law returns, or the reason it is not a pair of numbers."""
    names = (*law.parameters, "h", "speed", "normal_accel", "g")
    args = (*row, h, speed, normal, G)
    out = _call(law, "friction law", args, names)
    given = ", ".join(f"{n}={a:.6g}" for n, a in zip(names, args))
    if not isinstance(out, tuple) or len(out) != 2:
        shape = f"a tuple of {len(out)}" if isinstance(out, tuple) else type(out).__name__
        return None, (f"returns {shape}, not the pair (tau, drag) (tried with {given})")
    tau, drag = (_number(v) for v in out)
    if tau is None or drag is None:
        return None, f"returns {out!r}: tau and drag must be numbers (tried with {given})"
    return (tau, drag), given


def _rows(law, params) -> list[tuple]:
    """The parameter rows the run gives ``law`` (a few, where they vary per cell)."""
    rows = np.atleast_2d(np.asarray(params, dtype=float))[:, :len(law.parameters)]
    unique = np.unique(rows, axis=0)
    if len(unique) > 3:  # friction maps: the smallest, the median and the largest row
        order = np.argsort(unique.sum(axis=1))
        unique = unique[[order[0], order[len(order) // 2], order[-1]]]
    return [tuple(float(v) for v in row) for row in unique]


def with_helpers(fn, decorate, _seen=None):
    """``fn`` (a user's function) with the plain Python functions of the user's it calls
    compiled by ``decorate`` too, recursively (an undecorated helper works as an ``@njit``
    one does); ``fn`` itself where it calls none."""
    seen = {} if _seen is None else _seen
    if id(fn) in seen:
        return seen[id(fn)]
    seen[id(fn)] = fn
    scope = None
    codes = [fn.__code__]
    while codes:
        code = codes.pop()
        codes.extend(c for c in code.co_consts if isinstance(c, types.CodeType))
        for ins in dis.get_instructions(code):
            value = fn.__globals__.get(ins.argval) if ins.opname == "LOAD_GLOBAL" else None
            if isinstance(value, types.FunctionType) and is_users(value.__code__):
                scope = dict(fn.__globals__) if scope is None else scope
                scope[ins.argval] = decorate(with_helpers(value, decorate, seen))
    if scope is None:
        return fn
    made = types.FunctionType(fn.__code__, scope, fn.__name__, fn.__defaults__, fn.__closure__)
    made.__qualname__, made.__module__, made.__doc__ = fn.__qualname__, fn.__module__, fn.__doc__
    seen[id(fn)] = made
    return made


def compilable(fn, **options):
    """``fn`` compiled as the kernels compile a user's function (its plain helpers too);
    ``options``: Numba's, added."""
    def decorate(f):
        return njit(error_model="numpy", inline="always", **options)(f)

    return decorate(with_helpers(fn, decorate))


def check_law(law, params) -> None:
    """Try ``law`` (a registered :class:`~avflow.scenario.extensions.FrictionLaw`) with the
    run's ``params`` at the trial's thicknesses and speeds: a pair of finite numbers >= 0
    (friction never pushes), or one line naming the user's file."""
    where = _where(law.function)
    for row in _rows(law, params):
        for h, speed in itertools.product(THICKNESSES, SPEEDS):
            values, said = _law_values(law, row, h, speed, NORMAL)
            if values is None:
                raise ExtensionFileError(f"{where}: the friction law {law.name!r} {said}")
            for what, v in zip(("tau", "drag"), values):
                if not math.isfinite(v):
                    raise ExtensionFileError(f"{where}: the friction law {law.name!r} returns "
                                             f"{what} = {v} (tried with {said})")
                if v < 0.0:
                    raise ExtensionFileError(
                        f"{where}: the friction law {law.name!r} returns {what} = {v:.6g} "
                        f"< 0 (tried with {said}): friction never pushes the flow")


def check_source(entry, params) -> None:
    """Try a registered source with the run's ``params``: a finite number."""
    names = (*entry.parameters, "h", "speed", "t")
    for h, speed in itertools.product((0.0, *THICKNESSES), SPEEDS):
        args = (*params, h, speed, 1.0)
        out = _call(entry, "source", args, names)
        rate = _number(out)
        given = ", ".join(f"{n}={a:.6g}" for n, a in zip(names, args))
        if rate is None or not math.isfinite(rate):
            raise ExtensionFileError(f"{_where(entry.function)}: the source {entry.name!r} "
                                     f"returns {out!r}, not a finite rate (tried with {given})")


def check_map(entry) -> None:
    """Try a registered map: a finite number from its initial value on."""
    names = ("old", "h", "hu", "hv", "speed", "t")
    for h, speed in itertools.product((0.0, *THICKNESSES), SPEEDS):
        args = (entry.initial, h, h * speed, 0.0, speed, 1.0)
        out = _call(entry, "map", args, names)
        value = _number(out)
        given = ", ".join(f"{n}={a:.6g}" for n, a in zip(names, args))
        if value is None or not math.isfinite(value):
            raise ExtensionFileError(f"{_where(entry.function)}: the map {entry.name!r} "
                                     f"returns {out!r}, not a finite number (tried with "
                                     f"{given})")


def check_compiles(entry, kind: str, n_args: int, decorate) -> None:
    """Compile ``entry``'s function alone (``decorate``: as the kernels will, its plain
    helpers compiled with it) for float arguments: what Numba cannot compile is one line
    naming the user's file, not a traceback after the kernels' long compile."""
    from numba import float64
    from numba.core.errors import NumbaError

    try:  # (without Numba's reference counting, as the kernels are compiled)
        decorate(entry.function, _nrt=False).compile((float64,) * n_args)
    except NumbaError as err:
        said = _text(err) or type(err).__name__
        raise ExtensionFileError(f"{_numba_line(err, entry.function)}: the {kind} {entry.name!r} cannot "
                                 f"be compiled: {said}") from None


def check(laws, maps, sources, law_params) -> None:
    """Every check above for what a run uses of the registry (:func:`avflow.numerics
    .variants.registered`): its law with ``law_params``, every map, its sources
    (:class:`~avflow.numerics.supply.AreaSource`, with their parameters)."""
    for law in laws:
        check_law(law, law_params)
        check_compiles(law, "friction law", len(law.parameters) + 4, compilable)
    for entry in maps:
        check_map(entry)
        check_compiles(entry, "map", 6, compilable)
    for source in sources:
        check_source(source.entry, source.params)
        check_compiles(source.entry, "source", len(source.entry.parameters) + 3, compilable)


def suspect(laws, sources, law_params) -> str | None:
    """After a run failed on a non-finite state: the registered law or source that returns a
    non-finite value somewhere in a wide range of thicknesses and speeds, and where; None if
    none does."""
    for law in laws:
        for row in _rows(law, law_params):
            for h, speed, normal in itertools.product(WIDE_THICKNESSES, WIDE_SPEEDS,
                                                      WIDE_NORMALS):
                try:
                    values, said = _law_values(law, row, h, speed, normal)
                except ExtensionFileError as err:
                    return str(err)
                if values is not None and not all(math.isfinite(v) for v in values):
                    return (f"the friction law {law.name!r} ({_where(law.function)}) returns "
                            f"tau, drag = {values[0]}, {values[1]} with {said}")
    for source in sources:
        entry = source.entry
        for h, speed in itertools.product((0.0, *WIDE_THICKNESSES), WIDE_SPEEDS):
            try:
                rate = _number(entry.function(*source.params, h, speed, 1.0))
            except Exception as err:  # noqa: BLE001
                return (f"the source {entry.name!r} ({_where(entry.function, err)}) raised "
                        f"{type(err).__name__} with h={h:.6g}, speed={speed:.6g}")
            if rate is None or not math.isfinite(rate):
                return (f"the source {entry.name!r} ({_where(entry.function)}) returns "
                        f"{rate} with h={h:.6g}, speed={speed:.6g}")
    return None
