"""One line on stderr while Numba compiles kernels, and how long it took.

Numba signals a compilation (``numba:compile``) only where the machine code is neither in
the process nor in the kernel cache (:func:`avflow.numerics.kernel_cache_dir`), so the
line appears on a first run of a kind on this machine and version, not on cache loads.
"""

from __future__ import annotations

import gc
import sys
import time
from typing import Callable

from numba.core import event


class _Watch(event.Listener):
    """Calls ``announce()`` at the first compilation and sums the seconds spent compiling
    (outermost compilations only: a kernel compiles its callees inside its own)."""

    def __init__(self, announce: Callable[[], None] | None):
        self.announce = announce
        self.depth = 0
        self.started = 0.0
        self.seconds = 0.0
        self.compiled = False

    def on_start(self, event):
        if self.depth == 0:
            self.started = time.perf_counter()
            if not self.compiled and self.announce is not None:
                self.announce()
            self.compiled = True
        self.depth += 1

    def on_end(self, event):
        self.depth -= 1
        if self.depth == 0:
            self.seconds += time.perf_counter() - self.started

    def __enter__(self):
        event.register("numba:compile", self)
        return self

    def __exit__(self, *exc):
        event.unregister("numba:compile", self)
        return False


class _FewerCollections(event.Listener):
    """Python's cyclic garbage collector runs less often while Numba compiles: the
    compiler makes millions of short-lived objects (copies of each inlined function's IR),
    and each full collection walks every object of the process, so in a process that holds
    many kernels' IR the collections took a quarter of the first run's compile time
    (docs/performance.md). The thresholds are restored when the outermost compilation ends."""

    #: Python's thresholds during a compilation (its defaults: 700, 10, 10)
    THRESHOLDS = (200_000, 50, 1000)

    def __init__(self):
        self.depth = 0
        self.saved = None

    def on_start(self, event):
        if self.depth == 0:
            self.saved = gc.get_threshold()
            gc.set_threshold(*self.THRESHOLDS)
        self.depth += 1

    def on_end(self, event):
        self.depth -= 1
        if self.depth == 0 and self.saved is not None:
            gc.set_threshold(*self.saved)


_COLLECTIONS = _FewerCollections()

#: Interrupts (exception classes) a signal handler asked for and that may not have arrived:
#: raised at Numba's next compiler pass (:class:`_StopCompiling`)
PENDING: list = []


class _StopCompiling(event.Listener):
    """A signal that arrives while LLVM runs is handled inside one of llvmlite's C callbacks,
    where Python prints the handler's exception and goes on: SIGTERM 8 s into a first
    compile let the run finish, 185 s later, with exit code 0. A handler that records its
    interrupt in :data:`PENDING` is heard at the next compiler pass or lock (every few
    hundred milliseconds, a long LLVM optimisation aside) and stops the compilation there."""

    def on_start(self, event):
        if PENDING:
            raise PENDING.pop()()

    def on_end(self, event):
        pass


_STOP = _StopCompiling()


def fewer_collections_while_compiling() -> None:
    """Install :class:`_FewerCollections` and :class:`_StopCompiling` for the whole process
    (once)."""
    if _COLLECTIONS not in event._registered.get("numba:compile", []):
        event.register("numba:compile", _COLLECTIONS)
    for kind in ("numba:compile", "numba:run_pass", "numba:llvm_lock"):
        if _STOP not in event._registered.get(kind, []):
            event.register(kind, _STOP)


def watch(on_compile: Callable[[str], None] | None, what: Callable[[], str]) -> _Watch:
    """A context manager: inside it, the first compilation calls ``on_compile(what())``;
    its ``seconds`` and ``compiled`` say how long Numba compiled and whether it did."""
    return _Watch(None if on_compile is None else (lambda: on_compile(what())))


def notify_compiling(what: str, stream=None) -> None:
    """One line on stderr: what is compiled, and that it happens once per machine and
    avflow version (the kernel cache's folder)."""
    from avflow.numerics import cache_root

    print(f"avflow: compiling {what} (once per machine and avflow version; kept in "
          f"{cache_root()}) ...", file=stream or sys.stderr, flush=True)


def notify_compiled(seconds: float, stream=None) -> None:
    """The line after :func:`notify_compiling`: how long it took."""
    print(f"avflow: compiled in {seconds:.0f} s", file=stream or sys.stderr, flush=True)


class _Announcer(_Watch):
    """For the whole process: the first compilation's line, and its duration once done."""

    def __init__(self, what: str, stream=None):
        super().__init__(lambda: notify_compiling(what, stream))
        self.stream, self.told = stream, False

    def on_end(self, event):
        super().on_end(event)
        if self.depth == 0 and not self.told:
            self.told = True
            notify_compiled(self.seconds, self.stream)


_ANNOUNCERS: list = []


def announce(what: str = "the kernels these scenes need", stream=None) -> None:
    """Until :func:`stop_announcing`, the first compilation in this process says so on
    stderr (ensembles, regions, calibrations: their runs in this process; their workers
    load the kernels this process compiled first)."""
    _ANNOUNCERS.append(_Announcer(what, stream))
    event.register("numba:compile", _ANNOUNCERS[-1])


def stop_announcing() -> None:
    """The end of a command: its :func:`announce` says nothing more."""
    while _ANNOUNCERS:
        event.unregister("numba:compile", _ANNOUNCERS.pop())
