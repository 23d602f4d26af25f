"""Which kernel runs a scene: a table of (traversal, backend) -> kernel, each with the orders
and meshes it supports, in the manner of xarray's backends. :class:`~avflow.numerics.solver.Solver`
asks :func:`select`; a combination no kernel runs fails there, at load time, with one line
naming what is available.

A backend registers its kernels here (the GPU's: ``backend="cuda"``,
:mod:`avflow.numerics.cuda_grid`); a new traversal registers its mesh kind. Nothing else
chooses a kernel.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

#: the values of ``numerics.kernel``: auto picks the fastest kernel that supports the scene
CHOICES = ("auto", "grid", "faces")


class KernelUnavailable(ValueError):
    """No registered kernel runs this combination (one line, naming what is available)."""


class SchemeUnavailable(KernelUnavailable):
    """The kernel does not run order 2 with the time scheme asked for."""


@dataclass(frozen=True)
class Kernel:
    """One traversal on one backend."""

    name: str  #: "profile", "grid" or "faces"
    backend: str  #: "cpu" or "cuda"
    orders: tuple[int, ...]
    description: str  #: for messages: what it walks
    #: None when it runs ``(terrain, order)``, else why not (a phrase)
    refuses: Callable[[object, int], str | None]
    #: the compiled time loop for ``(structured, order, law, parallel)``
    loop: Callable[..., object]
    #: None when this machine can run it, else what it lacks (a phrase: a package, a GPU)
    unavailable: Callable[[], str | None] = lambda: None
    #: the time schemes of its order 2, its default first: "hancock" (MUSCL-Hancock, one
    #: flux sweep of predicted sides) or "heun" (Heun's two stages and their mean)
    schemes: tuple[str, ...] = ("heun",)

    def label(self) -> str:
        orders = " and ".join(str(o) for o in self.orders)
        return f"{self.name} ({self.description}; order{'s' if len(self.orders) > 1 else ''} {orders}; {self.backend})"


def _profile_refuses(terrain, order):
    return None if terrain.mesh.structured_1d else "the mesh is not a profile"


def _grid_refuses(terrain, order):
    if terrain.kind != "grid" or terrain.mesh.face_direction is None:
        return "the mesh is not a square grid"
    return None


def _faces_refuses(terrain, order):
    return None


def _face_loop(structured, order, law, parallel, scheme="heun"):
    from avflow.numerics.timeloop import time_loop

    return time_loop(structured, order, law, parallel, scheme)


def _grid_loop(structured, order, law, parallel, scheme="hancock"):
    from avflow.numerics.square_grid import grid_loop

    return grid_loop(law, parallel, order, scheme)


def _cuda_unavailable():
    from avflow.numerics.cuda_grid import unavailable

    return unavailable()


def _cuda_grid_loop(structured, order, law, parallel, scheme="heun"):
    from avflow.numerics.cuda_grid import loop

    return loop(structured, order, law, parallel)


KERNELS: dict[tuple[str, str], Kernel] = {
    ("profile", "cpu"): Kernel("profile", "cpu", (1, 2), "a profile's cells in line order",
                               _profile_refuses, _face_loop),
    ("grid", "cpu"): Kernel("grid", "cpu", (1, 2), "square grids (planes, DEMs) by rows, on threads",
                            _grid_refuses, _grid_loop, schemes=("hancock", "heun")),
    ("faces", "cpu"): Kernel("faces", "cpu", (1, 2), "any mesh by face lists, on threads",
                             _faces_refuses, _face_loop, schemes=("hancock", "heun")),
    # numerics.cuda_grid: the square-grid kernel's step at orders 1 and 2
    ("grid", "cuda"): Kernel("grid", "cuda", (1, 2), "square grids (planes, DEMs), a GPU "
                             "thread per cell", _grid_refuses, _cuda_grid_loop,
                             _cuda_unavailable),
}


#: the values of ``numerics.backend``: the backends some kernel runs on (the scenario schema
#: and the command line offer these; tests/test_registry.py holds them to it)
BACKENDS = tuple(dict.fromkeys(k.backend for k in KERNELS.values()))


def available(backend: str | None = None) -> str:
    """The registered kernels, for messages."""
    return "; ".join(k.label() for k in KERNELS.values() if backend in (None, k.backend))


def select(terrain, order: int, kernel: str = "auto", backend: str = "cpu") -> Kernel:
    """The kernel that runs ``terrain`` at ``order`` on ``backend``: with ``auto``, the
    square-grid kernel where it applies, the profile sweep on profiles, the face kernel
    elsewhere; ``grid`` or ``faces``: that one, or :class:`KernelUnavailable`.
    (The square-grid kernel can still turn a grid down once laid out: a rotated DEM; the
    solver then takes the face kernel, which runs any mesh.)"""
    if kernel not in CHOICES:
        raise KernelUnavailable(f"kernel must be one of {', '.join(CHOICES)}, got {kernel!r}")
    if not any(k.backend == backend for k in KERNELS.values()):
        backends = sorted({k.backend for k in KERNELS.values()})
        raise KernelUnavailable(f"no kernel runs on the backend {backend!r}; available: "
                                f"{', '.join(backends)}")
    wanted = {"auto": ("grid", "profile", "faces"), "grid": ("grid",),
              "faces": ("profile", "faces")}[kernel]
    why = []
    for name in wanted:
        entry = KERNELS.get((name, backend))
        if entry is None:
            why.append(f"{name}: none on {backend}")
            continue
        reason = entry.refuses(terrain, order)
        if reason is None and order not in entry.orders:
            orders = " and ".join(str(o) for o in entry.orders)
            reason = f"it runs order {orders} only, not order {order}"
        if reason is None:
            # the scene is served; what this machine lacks is said alone, with what to do
            lacks = entry.unavailable()
            if lacks is not None:
                raise KernelUnavailable(f"the {backend} backend cannot run on this machine: "
                                        f"{lacks}; run with numerics.backend: cpu (--backend "
                                        "cpu), or on a machine that has it")
            return entry
        why.append(f"{name}: {reason}")
    raise KernelUnavailable(f"no {backend} kernel runs this scene at order {order} "
                            f"({'; '.join(why)}); available: {available(backend)}")
