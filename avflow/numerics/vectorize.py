"""What lets LLVM vectorise the kernels' cell loops (8 cells at once with AVX-512).

Numba hands LLVM loops it can vectorise only when (found on the square-grid kernel;
figures in docs/performance.md):

- the loop is free of jumps: ``a if c else b`` between values already computed, every
  array element loaded whichever is kept (a load under a condition became a masked load,
  slower than the scalar loop), ``&`` and ``|`` rather than ``and`` / ``or``, no inner
  loop (the four terms of a face order written out), no early return;
- its index provably never negative (the loop counts from 0 from a start clamped at 0:
  Numba's wraparound of negative indices kept it scalar);
- arrays are 1D lines (2D indexing kept it scalar) and LLVM knows they do not overlap
  (:func:`noalias`), with lines of one array passed as separate arguments;
- the friction law is a constant (:func:`by_law`): Pouliquen's ``exp`` and samosAT's
  ``log`` have no vector form here, and their branches stay in a loop that reads the law.

What is written here keeps the scalar kernels' operations on every value kept, so the
vector loops give the same bits.
"""

from __future__ import annotations

import types

from numba import njit

from avflow.numerics.rheology import PER_CELL


def noalias(dispatcher):
    """Compile ``dispatcher`` telling LLVM that its array arguments never overlap (Numba's
    ``noalias`` flag, which its decorator does not expose): without it a loop that reads
    thirty arrays and writes ten needs hundreds of overlap checks, and LLVM leaves it
    scalar (the final update ran about twice as long: docs/performance.md). True of every caller
    here: the state is double-buffered, each ring row and output line is its own array.
    Where Numba's private hook is missing (another version), the loops stay scalar, with
    the same results."""
    compiler = getattr(dispatcher, "_compiler", None)
    if compiler is not None and hasattr(compiler, "_customize_flags"):
        def customize(flags):
            flags.noalias = True
            return flags

        compiler._customize_flags = customize
    return dispatcher


@njit(error_model="numpy", cache=True, fastmath={"reassoc"}, _nrt=False)
def line_sum(a, c0, c1):
    """``a[c0] + ... + a[c1]``, reassociated so that LLVM vectorises it (a chain of adds,
    one a cell, stays scalar). The order is fixed by the compiled code and the bounds: the
    same bits on 1 or N threads; against the face kernel's cell-by-cell sums, round-off."""
    s = 0.0
    c0 = max(c0, 0)
    for j in range(c1 + 1 - c0):
        s += a[c0 + j]
    return s


@njit(error_model="numpy", cache=True, fastmath={"nnan", "nsz", "reassoc"}, _nrt=False)
def line_max(a, c0, c1):
    """``max(0, a[c0], ..., a[c1])``, vectorised (rather than a scalar chain of maxima):
    a maximum is the same value in any order, so the same bits as
    the chain, for the values of the kernels (never NaN: a NaN thickness is refused before
    a run starts)."""
    m = 0.0
    c0 = max(c0, 0)
    for j in range(c1 + 1 - c0):
        v = a[c0 + j]
        m = v if v > m else m
    return m


@njit(error_model="numpy", cache=True, inline="always")
def friction_law(law):
    """The friction law of the cell loops: the argument itself here; a constant in the
    copies made by :func:`by_law`."""
    return law


@njit(error_model="numpy", cache=True, inline="always")
def cell_law(law, params, i, p0, p1, p2, p3, p4, p5, p6, p7):
    """The law's parameters at cell ``i``: its row of ``params`` where the law's code says
    they are per cell (:data:`~avflow.numerics.rheology.PER_CELL`: friction maps, forest),
    else the run's own ``p0..p7`` (row 0, loaded once per pass). Never per cell in the
    copies for one law (:func:`by_law`): the law is a constant there, the branch folds."""
    if law >= PER_CELL:
        return (params[i, 0], params[i, 1], params[i, 2], params[i, 3], params[i, 4],
                params[i, 5], params[i, 6], params[i, 7])
    return p0, p1, p2, p3, p4, p5, p6, p7


#: The law of a copy made by :func:`by_law` (each copy's globals hold its own)
LAW = -1


def _law_constant(law):
    """:func:`friction_law` of a copy: its ``LAW``, whatever the argument."""
    return LAW


#: The law kind of the copies that read the law at run time (Pouliquen, samosAT): their
#: ``exp`` and ``log`` keep a loop scalar anyway, so they share one copy
ANY_LAW = -1


def law_kind(law: int) -> int:
    """The copy that runs ``law``: its own for Coulomb and Voellmy, :data:`ANY_LAW` else
    (Pouliquen, samosAT, velocity weakening, and every law with parameters per cell)."""
    from avflow.numerics.rheology import COULOMB, VOELLMY

    return law if law in (COULOMB, VOELLMY) else ANY_LAW


def law_label(kind: int) -> str:
    """The name of a law kind in the names of its copies."""
    from avflow.numerics.rheology import COULOMB, VOELLMY

    return {COULOMB: "coulomb", VOELLMY: "voellmy"}.get(kind, "any")


class UnknownPlaceholder(NameError):
    """A copy asked to replace a global its function never reads (a misspelt name)."""


#: Globals :func:`by_law` replaces in every copy, whether or not the function reads them
_OPTIONAL = frozenset({"friction_law"})


def shared_names(fns: dict, **names) -> dict:
    """``names`` shared out among the functions ``fns`` (key -> function): each gets those
    its code reads; a name that none of them reads is :class:`UnknownPlaceholder`."""
    read = {key: set(fn.__code__.co_names) for key, fn in fns.items()}
    unread = sorted(set(names) - set().union(*read.values()))
    if unread:
        raise UnknownPlaceholder(f"none of {', '.join(fn.__qualname__ for fn in fns.values())} "
                                 f"reads a global named {', '.join(unread)}: nothing to replace")
    return {key: {k: v for k, v in names.items() if k in read[key]} for key in fns}


def specialize(fn, suffix: str, parallel: bool = False, nrt: bool = True,
               inline: str = "never", **names):
    """``fn`` compiled as a copy named ``fn.__name__ + suffix`` whose globals ``names`` are
    replaced (constants Numba then folds, branches it drops before typing, or the copies of
    what it calls). Its own name: Numba's cache files are named after the function (name
    and line), not after its globals or flags, so two copies under one name would load each
    other's machine code (a "serial" sweep once ran on the thread pool that way). Its cache
    folder is the package's (:mod:`avflow.numerics`).

    Every name in ``names`` must be a global that ``fn``'s code reads: a misspelt name would
    otherwise leave the original in place, silently (:class:`UnknownPlaceholder`)."""
    unknown = sorted(set(names) - set(fn.__code__.co_names) - _OPTIONAL)
    if unknown:
        raise UnknownPlaceholder(f"{fn.__module__}.{fn.__qualname__} reads no global named "
                                 f"{', '.join(unknown)}: nothing to replace")
    namespace = dict(fn.__globals__)
    namespace.update(names)
    copy = types.FunctionType(fn.__code__, namespace, fn.__name__ + suffix,
                              fn.__defaults__, fn.__closure__)
    copy.__qualname__ = fn.__qualname__ + suffix
    copy.__module__ = fn.__module__
    copy.__doc__ = fn.__doc__
    # nrt=False: no reference counting (see :func:`by_law`)
    return njit(error_model="numpy", cache=True, parallel=parallel, _nrt=nrt,
                inline=inline)(copy)


def by_law(fn, law: int | None, label: str, nrt: bool = True, **names):
    """``fn`` compiled with the friction law a constant (``law``; None: read at run time),
    under its own name (Numba's cache files are named after the function); ``names``: other
    globals of ``fn`` replaced in the copy (the copies for the same law of what it calls).

    In a copy for one law, LLVM folds the law's branches in :func:`~avflow.numerics.rheology.friction` away, and the
    loop of a law without transcendental functions (Coulomb, Voellmy) vectorises (8 cells
    at once with AVX-512); with Pouliquen's ``exp`` or samosAT's ``log`` in it, a loop stays
    scalar, so those laws share the copy that reads the law at run time.

    ``nrt=False``: compiled without Numba's reference counting, for a function that
    allocates nothing and is called once per row: every view it takes of an array (a line
    of a 2D array) would otherwise cost an atomic increment and decrement of the array's
    count.
    """
    if law is not None:
        # inlined where it is called, never compiled (nor cached) on its own
        names.setdefault("friction_law", njit(error_model="numpy", inline="always")(
            types.FunctionType(_law_constant.__code__, {"LAW": law}, "friction_law_" + label)))
    return noalias(specialize(fn, "_" + label, nrt=nrt, **names))


def law_copies(fn):
    """:func:`by_law`'s copies of ``fn`` per law kind (:func:`law_kind`): Coulomb and
    Voellmy each their own, :data:`ANY_LAW` the one that reads the law at run time."""
    from avflow.numerics.rheology import COULOMB, VOELLMY

    return {kind: by_law(fn, None if kind == ANY_LAW else kind, law_label(kind))
            for kind in (COULOMB, VOELLMY, ANY_LAW)}


