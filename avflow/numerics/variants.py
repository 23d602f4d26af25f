"""Kernels with what a user registered built in (:mod:`avflow.extend`): one mechanism, made
on demand, checked.

A compiled time loop calls its passes, and they the pointwise physics, by global name. A
*variant* of a loop is a copy of it, and of every compiled function below it that reads one
of the names being replaced (directly or through what it calls), with those names bound to
new functions; everything that reads none of them is shared with the loop as it is.
Each copy is named after the registrations it reads (:func:`tag_of`), so Numba's cache keeps
it beside the built-in kernels, and a law's copies stay the same when a map is registered
beside it; what a copy is compiled from is in its cache key (:mod:`avflow.codekey`), so a
changed function, helper or constant is compiled afresh. Nothing is made at import: a variant
is made the first time a run asks for it, and compiled for that run alone.

Three names are replaced today, each a placeholder of the built-in kernels:

- ``law_friction`` (:func:`avflow.numerics.rheology.law_friction`): the registered laws'
  branches, then the built-in laws' (the loop that reads the law at run time is the root);
- ``more_maps`` (:func:`avflow.numerics.observers.more_maps`): the registered maps, each
  updated once per accepted step;
- ``supply_rate`` (:func:`avflow.numerics.supply.supply_rate`): the rate of the registered
  sources a run has, each with its weight per cell.

A name no function below the root reads is refused (:class:`UnknownPlaceholder`): a
misspelt name cannot leave the built-in one in place silently.
"""

from __future__ import annotations

import hashlib
import types

from numba import njit
from numba.core.caching import NullCache
from numba.core.registry import CPUDispatcher

from avflow.numerics.vectorize import UnknownPlaceholder, noalias
from avflow.codekey import code_key
from avflow.numerics.trial import with_helpers
from avflow.scenario.extensions import FRICTION_LAWS, MAPS

#: variants made so far in this process, by (root, tag): a second run takes the same
#: dispatchers (and their machine code), never new ones
_MADE: dict = {}


def _ours(value) -> bool:
    return (isinstance(value, CPUDispatcher)
            and (value.py_func.__module__ or "").startswith("avflow."))


def _copy(dispatcher, names: dict, tag: str):
    """``dispatcher``'s function with ``names`` over its globals, compiled with its options
    (threads, inlining, reference counting, no-alias) under the name ``<name>_<tag>``."""
    py = dispatcher.py_func
    scope = dict(py.__globals__)
    scope.update(names)
    fn = types.FunctionType(py.__code__, scope, f"{py.__name__}_{tag}", py.__defaults__,
                            py.__closure__)
    fn.__qualname__ = f"{py.__qualname__}_{tag}"
    fn.__module__, fn.__doc__ = py.__module__, py.__doc__
    options = {k: v for k, v in dispatcher.targetoptions.items() if k != "nopython"}
    copy = njit(cache=not isinstance(dispatcher._cache, NullCache), **options)(fn)
    if "_customize_flags" in vars(getattr(dispatcher, "_compiler", None) or object()):
        noalias(copy)
    return copy


def variant(root, tags: dict, **replace):
    """``root`` (a compiled function) with the globals ``replace`` bound anew in every
    function below it that reads them (see the module's docstring). ``tags``: for each
    replaced name, a tag of what replaces it; a copy is named after the tags of the names
    it reads, directly or below, and of no other: a law's sweeps keep their name (and their
    cache) when a map is registered beside it."""
    key = (id(root), tuple(sorted((name, tags[name]) for name in replace)))
    if key in _MADE:
        return _MADE[key][1]
    done: dict = {}
    read: set = set()

    def visit(dispatcher):
        if id(dispatcher) in done:
            return done[id(dispatcher)]
        done[id(dispatcher)] = (dispatcher, frozenset())  # (no cycles; guards anyway)
        py = dispatcher.py_func
        names, below = {}, set()
        for name in py.__code__.co_names:
            if name in replace and name in py.__globals__:
                names[name] = replace[name]
                below.add(name)
                continue
            value = py.__globals__.get(name)
            if _ours(value):
                made, reads = visit(value)
                if made is not value:
                    names[name] = made
                    below |= reads
        read.update(below)
        tag = "x" + hashlib.sha256(repr(sorted((n, tags[n]) for n in below)).encode()
                                   ).hexdigest()[:12]
        made = _copy(dispatcher, names, tag) if names else dispatcher
        done[id(dispatcher)] = (made, frozenset(below))
        return done[id(dispatcher)]

    made, _ = visit(root)
    unread = sorted(set(replace) - read)
    if unread:
        raise UnknownPlaceholder(f"no function below {root.py_func.__qualname__} reads a "
                                 f"global named {', '.join(unread)}: nothing to replace")
    _MADE[key] = (root, made)  # (the root kept alive: its id stays its own)
    return made


# --- what replaces the placeholders ----------------------------------------------------------

# a registered law's negative tau or drag counts as 0 (friction never pushes: the trial
# call refuses them at typical values, this holds everywhere); NaN stays NaN, a failure
_LAW_SOURCE = '''
def law_friction(law, p0, p1, p2, p3, p4, p5, p6, p7, h, speed, normal_accel, g):
{branches}    return built_in(law, p0, p1, p2, p3, p4, p5, p6, p7, h, speed, normal_accel, g)
'''

_MAPS_SOURCE = '''
def more_maps(maps, i, h, hu, hv, speed, t_new):
{lines}    return None
'''


def _generated(source: str, name: str, scope: dict, decorate):
    """The function ``name`` of ``source`` (a template filled in above), compiled by
    ``decorate`` with ``scope`` as its globals."""
    namespace = dict(scope)
    exec(compile(source, f"<avflow {name}>", "exec"), namespace)
    return decorate(namespace[name])


def law_friction_with(laws, built_in, decorate):
    """:func:`~avflow.numerics.rheology.law_friction` with the registered ``laws``' branches
    before the built-in ones (``built_in``), each law's function compiled by ``decorate``."""
    branches = ""
    scope = {"built_in": built_in}
    for law in laws:
        args = ", ".join(f"p{k}" for k in range(len(law.parameters)))
        branches += (f"    if law == {law.code}:\n        tau, drag = law_{law.code}("
                     f"{args}{', ' if args else ''}h, speed, normal_accel, g)\n"
                     "        return (0.0 if tau < 0.0 else tau), (0.0 if drag < 0.0 else drag)\n")
        scope[f"law_{law.code}"] = decorate(with_helpers(law.function, decorate))
    return _generated(_LAW_SOURCE.format(branches=branches), "law_friction", scope, decorate)


def more_maps_with(maps, decorate):
    """:func:`~avflow.numerics.observers.more_maps` writing the registered ``maps`` (a row
    of ``maps`` each, in their order), each map's function compiled by ``decorate``."""
    lines = ""
    scope = {}
    for k, entry in enumerate(maps):
        lines += f"    maps[{k}, i] = map_{k}(maps[{k}, i], h, hu, hv, speed, t_new)\n"
        scope[f"map_{k}"] = decorate(with_helpers(entry.function, decorate))
    return _generated(_MAPS_SOURCE.format(lines=lines), "more_maps", scope, decorate)


_SUPPLY_SOURCE = '''
def supply_rate(weights, params, c, h, speed, t):
    rate = 0.0
{lines}    return rate
'''


def supply_rate_with(entries, decorate):
    """:func:`~avflow.numerics.supply.supply_rate` summing the run's registered sources
    (``entries``, in the order of the solver's sources: a row of ``weights`` and ``params``
    each), a rate below 0 counted as 0, each source's function compiled by ``decorate``."""
    lines = ""
    scope = {}
    for k, entry in enumerate(entries):
        args = "".join(f"params[{k}, {j}], " for j in range(len(entry.parameters)))
        lines += (f"    r = source_{k}({args}h, speed, t)\n"
                  f"    rate += weights[{k}, c] * (r if r > 0.0 else 0.0)\n")
        scope[f"source_{k}"] = decorate(with_helpers(entry.function, decorate))
    return _generated(_SUPPLY_SOURCE.format(lines=lines), "supply_rate", scope, decorate)


def _inline(fn):
    return njit(error_model="numpy", inline="always")(fn)


def registered(law: int, sources=()):
    """What of the registry a run compiles in: ``(laws, maps, sources)``, the registered law
    of its law code ``law`` (PER_CELL included; none for a built-in law), every registered
    map, and the registered sources it runs (``sources``: its
    :class:`~avflow.numerics.supply.AreaSource`, in order)."""
    from avflow.numerics.rheology import PER_CELL

    base = law - PER_CELL if law >= PER_CELL else law
    laws = tuple(entry for entry in FRICTION_LAWS.values() if entry.code == base)
    return laws, tuple(MAPS.values()), tuple(s.entry for s in sources)


def tag_of(*entries) -> str:
    """A tag of registered ``entries`` (laws, maps, sources): their kinds, names, codes and
    what their functions compile from (:func:`avflow.codekey.code_key`)."""
    names = repr([(type(e).__name__, e.name, getattr(e, "code", None)) for e in entries])
    functions = code_key(*(e.function for e in entries), strict=True)
    return hashlib.sha256((names + functions).encode()).hexdigest()[:12]


#: what :func:`check_registered` found sound in this process
_CHECKED: set = set()


def check_registered(law: int, sources=(), params=()) -> None:
    """Before anything compiles: what the run uses of the registry (:func:`registered`)
    tried in Python and compiled alone (:mod:`avflow.numerics.trial`), and keyed
    (a global no key can hold refused); ``params``: the law's parameters as the kernels
    read them. One line naming the user's file on failure
    (:class:`~avflow.scenario.extensions.ExtensionFileError`)."""
    import numpy as np

    from avflow.codekey import UnhashableGlobal
    from avflow.numerics import trial
    from avflow.scenario.extensions import ExtensionFileError

    laws, maps, entries = registered(law, sources)
    if not (laws or maps or entries):
        return
    try:  # (the parameters by a digest: a friction map holds a row per cell)
        given = np.ascontiguousarray(params, dtype=float)
        key = (tag_of(*laws, *maps, *entries), given.shape,
               hashlib.sha256(given.tobytes()).hexdigest(), tuple(s.params for s in sources))
    except UnhashableGlobal as err:
        raise ExtensionFileError(str(err)) from None
    if key in _CHECKED:
        return
    trial.check(laws, maps, sources, params)
    _CHECKED.add(key)


def with_registered(loop, law: int, sources=()):
    """The time loop ``loop`` (a compiled :func:`avflow.numerics.loop.advance` copy) with
    what the run uses of the registry built in (:func:`registered`); ``loop`` itself where
    it uses none of it."""
    laws, maps, entries = registered(law, sources)
    if not (laws or maps or entries):
        return loop
    from avflow.numerics import rheology

    replace, tags = {}, {}
    if laws:
        replace["law_friction"] = law_friction_with(laws, rheology.law_friction, _inline)
        tags["law_friction"] = tag_of(*laws)
    if maps:
        replace["more_maps"] = more_maps_with(maps, _inline)
        tags["more_maps"] = tag_of(*maps)
    if entries:
        replace["supply_rate"] = supply_rate_with(entries, _inline)
        tags["supply_rate"] = tag_of(*entries)
    return variant(loop, tags, **replace)
