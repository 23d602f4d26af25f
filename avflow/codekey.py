"""A compiled function's key: a digest of everything its machine code is made from.

Numba keys its cache by the compiled function's own byte code and closure only, and checks
the stamp of the one file that defines it: a changed callee in another file, a helper's
constant, a user's ``@njit`` helper, left the old machine code in the cache, served silently.
As PyFR keys its cache by the rendered source of a kernel, :func:`code_key` hashes what
Numba freezes into the machine code, walked as Numba walks it:

- a function's module name (Numba imports it to load the code back), byte code, constants,
  defaults, closure cells and options (a compiled function's ``targetoptions`` and the
  no-alias flag), nested functions included;
- every global it reads (``LOAD_GLOBAL``) and every module attribute it reads through a
  global module (``np.pi``, ``physics.FLOWING``), by value: numbers, strings, tuples and
  arrays by their bytes, enum members by value;
- the functions it calls, compiled (a Numba dispatcher: its Python function) or plain,
  recursively, so a change anywhere below changes the key of every caller.

Functions of Python's own library and of installed packages (numpy, numba) count by their
name: their versions are part of the cache folder's name. A global of any other kind cannot
be frozen into machine code by value, so it cannot be hashed either: in a user's function
it is refused (:class:`UnhashableGlobal`, naming the file, the line and the name).
"""

from __future__ import annotations

import builtins
import dis
import enum
import hashlib
import sysconfig
import types
from pathlib import Path

import numpy as np

_PACKAGE = Path(__file__).resolve().parent
#: where installed libraries live (their functions count by name, not by code)
_LIBRARIES = tuple({str(Path(p).resolve()) for p in (
    sysconfig.get_paths()[k] for k in ("stdlib", "platstdlib", "purelib", "platlib"))})
_LOADS = {"LOAD_GLOBAL", "LOAD_NAME"}
_ATTRIBUTES = {"LOAD_ATTR", "LOAD_METHOD"}


class UnhashableGlobal(ValueError):
    """A global a compiled user function reads that has no value to hash (one line: the
    file, its line, the name and what it is)."""


def _in_library(code: types.CodeType) -> bool:
    """Whether ``code`` is Python's or an installed package's (avflow itself excepted, also
    where it is installed among them)."""
    path = code.co_filename
    if path.startswith("<"):  # made by exec: avflow's generated functions, a user's
        return False
    try:
        full = str(Path(path).resolve())
    except OSError:
        return False
    if full.startswith(str(_PACKAGE)):
        return False
    return full.startswith(_LIBRARIES)


def is_users(code: types.CodeType) -> bool:
    """Whether ``code`` is a user's: neither avflow's (its files, its generated functions)
    nor a library's."""
    if code.co_filename.startswith("<avflow"):
        return False
    try:
        if Path(code.co_filename).resolve().is_relative_to(_PACKAGE):
            return False
    except OSError:
        pass
    return not _in_library(code)


def _is_dispatcher(value) -> bool:
    return hasattr(value, "py_func") and hasattr(value, "targetoptions")


class _Walk:
    """One digest: each function's own digest memoised by the function object (kept alive,
    so its id stays its own), a cycle cut at the function met again."""

    _MEMO: dict = {}

    def __init__(self, strict: bool):
        self.strict = strict
        self.active: set = set()

    def function(self, fn: types.FunctionType) -> bytes:
        memo = self._MEMO.get((id(fn), self.strict))
        if memo is not None and memo[0] is fn:
            return memo[1]
        if id(fn) in self.active:  # recursion: its name only (its digest is being made)
            return f"recursive {fn.__qualname__}".encode()
        if _in_library(fn.__code__):
            return f"library {fn.__module__}.{fn.__qualname__}".encode()
        self.active.add(id(fn))
        try:
            h = hashlib.sha256(b"function")
            # the module Numba imports by name to load the machine code back
            h.update(f"module {fn.__globals__.get('__name__')}".encode())
            self.code(h, fn.__code__, fn)
            self.value(h, fn.__defaults__, fn, "defaults")
            self.value(h, tuple(sorted((fn.__kwdefaults__ or {}).items())), fn, "defaults")
            for name, cell in zip(fn.__code__.co_freevars, fn.__closure__ or ()):
                try:
                    contents = cell.cell_contents
                except ValueError:  # an empty cell
                    contents = None
                h.update(f"cell {name}=".encode())
                self.value(h, contents, fn, name)
            out = h.digest()
        finally:
            self.active.discard(id(fn))
        self._MEMO[(id(fn), self.strict)] = (fn, out)
        return out

    def code(self, h, code: types.CodeType, fn) -> None:
        """The byte code, names and constants of ``code`` (nested functions recursively),
        and the values of the globals and module attributes it reads."""
        h.update(code.co_code)
        h.update(repr((code.co_names, code.co_varnames, code.co_argcount)).encode())
        module = None
        for ins in dis.get_instructions(code):
            if ins.opname in _LOADS:
                name = ins.argval
                scope = fn.__globals__
                if name in scope:
                    value = scope[name]
                elif hasattr(builtins, name):
                    value = getattr(builtins, name)
                else:
                    module = None
                    continue  # unbound: the compiler says so
                h.update(f"global {name}=".encode())
                self.value(h, value, fn, name, ins.positions)
                module = value if isinstance(value, types.ModuleType) else None
            elif ins.opname in _ATTRIBUTES and module is not None:
                missing = object()
                value = getattr(module, ins.argval, missing)
                name = f"{module.__name__}.{ins.argval}"
                if value is not missing:
                    h.update(f"attribute {name}=".encode())
                    self.value(h, value, fn, name, ins.positions)
                module = value if isinstance(value, types.ModuleType) else None
            else:
                module = None
        for const in code.co_consts:
            if isinstance(const, types.CodeType):
                self.code(h, const, fn)
            else:
                h.update(repr((type(const).__name__, const)).encode())

    def value(self, h, value, fn, name: str, where=None) -> None:
        """``value`` into ``h``: what it is and its bytes (see the module's docstring)."""
        if value is None or isinstance(value, (bool, int, float, complex, str, bytes)):
            h.update(repr((type(value).__name__, value)).encode())
        elif isinstance(value, enum.Enum):
            h.update(repr((type(value).__qualname__, value.value)).encode())
        elif isinstance(value, np.generic):
            h.update(repr((value.dtype.str, value.tobytes())).encode())
        elif isinstance(value, np.ndarray):
            h.update(repr((value.dtype.str, value.shape)).encode())
            h.update(np.ascontiguousarray(value).tobytes())
        elif isinstance(value, tuple):
            h.update(f"tuple {len(value)}".encode())
            for item in value:
                self.value(h, item, fn, name, where)
        elif _is_dispatcher(value):
            options = sorted((k, _canonical(v)) for k, v in value.targetoptions.items())
            noalias = "_customize_flags" in vars(getattr(value, "_compiler", None) or object())
            h.update(repr(("compiled", options, noalias)).encode())
            h.update(self.function(value.py_func))
        elif isinstance(value, types.FunctionType):
            h.update(self.function(value))
        elif isinstance(value, types.ModuleType):
            h.update(f"module {value.__name__}".encode())
        elif isinstance(value, (types.BuiltinFunctionType, np.ufunc, type)) or _library_object(value):
            h.update(f"named {getattr(value, '__module__', '')}."
                     f"{getattr(value, '__qualname__', getattr(value, '__name__', repr(value)))}"
                     .encode())
        elif self.strict and is_users(fn.__code__):
            line = where.lineno if where is not None and where.lineno else \
                fn.__code__.co_firstlineno
            raise UnhashableGlobal(
                f"{fn.__code__.co_filename}:{line}: {fn.__name__} reads {name!r}, a "
                f"{type(value).__name__}: a compiled function can read numbers, strings, "
                "tuples, arrays, modules and functions")
        else:
            h.update(f"object {type(value).__module__}.{type(value).__qualname__}".encode())


def _canonical(option) -> str:
    """An option's text, the same in every process (a set's order is not)."""
    if isinstance(option, (set, frozenset)):
        return repr(sorted(_canonical(v) for v in option))
    if isinstance(option, dict):
        return repr(sorted((_canonical(k), _canonical(v)) for k, v in option.items()))
    return repr(option)


def _library_object(value) -> bool:
    """An object of the compiler's own packages (Numba's types and markers, numpy's): named,
    the package's version fixes it."""
    root = (type(value).__module__ or "").split(".")[0]
    return root in ("numba", "numpy", "llvmlite")


def code_key(*functions, strict: bool = False) -> str:
    """A hex digest of what ``functions`` (Python functions or Numba dispatchers) compile
    from (the module's docstring). ``strict``: a global with no value to hash, read by a
    user's function, raises :class:`UnhashableGlobal` (avflow's own count by their type)."""
    walk = _Walk(strict)
    h = hashlib.sha256()
    for fn in functions:
        if _is_dispatcher(fn):
            walk.value(h, fn, fn.py_func, fn.py_func.__name__)
        else:
            h.update(walk.function(fn))
    return h.hexdigest()


def forget() -> None:
    """Forget the digests made so far in this process (a test that changes a global)."""
    _Walk._MEMO.clear()
