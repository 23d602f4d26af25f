"""The pointwise physics compiled for the CPU: :mod:`avflow.numerics.kinetic` and
:mod:`avflow.numerics.physics`, each function compiled once on its own (and cached), and
inlined into the traversals that call it by LLVM rather than by Numba: Numba's inlining
copies and types a function's IR again at every call site, which made a third of a first
run's compile time, and LLVM's gives the same loops, vectorised as before
(docs/performance.md).

The source modules stay plain Python (callable as they are, and compilable for another target
by the same :func:`compile_pointwise`); the traversals import the compiled functions from
here, under the same names.
"""

from __future__ import annotations

import types

from numba import njit

from avflow.numerics import kinetic, physics


def compile_pointwise(modules, decorate, replace=None, suffix: str = "") -> dict:
    """Every public function of ``modules`` compiled by ``decorate``, in one namespace: a
    compiled function calls the compiled versions of its siblings (``trial_momentum`` the
    compiled ``normal_accel``), and the modules themselves are left as they are.
    ``replace(compiled)``: names bound anew in that namespace once the functions are
    compiled (a registered law's ``law_friction`` calling the compiled built-in one)."""
    namespace: dict = {}
    for module in modules:
        namespace.update({k: v for k, v in vars(module).items() if not k.startswith("__")})
    compiled = {}
    for module in modules:
        for name, fn in vars(module).items():
            if (isinstance(fn, types.FunctionType) and fn.__module__ == module.__name__
                    and not name.startswith("_")):
                copy = types.FunctionType(fn.__code__, namespace, fn.__name__ + suffix,
                                          fn.__defaults__, fn.__closure__)
                copy.__qualname__, copy.__module__, copy.__doc__ = (
                    fn.__qualname__ + suffix, fn.__module__, fn.__doc__)
                compiled[name] = decorate(copy)
    namespace.update(compiled)  # looked up when a caller is typed, so the order is free
    if replace is not None:
        changed = replace(dict(compiled))
        namespace.update(changed)
        compiled.update(changed)
    return compiled


_POINTWISE = compile_pointwise(
    (kinetic, physics), njit(error_model="numpy", cache=True, inline="never"))
_POINTWISE.pop("density_factor")  # numpy on whole arrays, once per solver: not pointwise
#: the same functions with the half fluxes' branch-free form, for the loops that vectorise
_VECTOR = compile_pointwise(
    (kinetic, physics), njit(error_model="numpy", cache=True, inline="never"),
    lambda c: {"half_flux_out": c["select_flux_out"], "half_flux_in": c["select_flux_in"]},
    suffix="_select")

#: the same functions inlined by Numba where called, for the big scalar bodies of
#: :mod:`avflow.numerics.kernels` (``step_faces``, ``step_profile``): LLVM left them as calls
#: there, and triangles at order 2 ran at 0.83 of their speed
INLINED = compile_pointwise(
    (kinetic, physics), njit(error_model="numpy", cache=True, inline="always"),
    suffix="_inlined")

sound_speed = _POINTWISE["sound_speed"]
half_fluxes = _POINTWISE["half_fluxes"]
half_flux_out = _POINTWISE["half_flux_out"]
half_flux_in = _POINTWISE["half_flux_in"]
select_flux_out = _POINTWISE["select_flux_out"]
select_flux_in = _POINTWISE["select_flux_in"]
normal_accel = _POINTWISE["normal_accel"]
centripetal_accel = _POINTWISE["centripetal_accel"]
project = _POINTWISE["project"]
dt_from_inverse = _POINTWISE["dt_from_inverse"]
trial_momentum = _POINTWISE["trial_momentum"]
final_momentum = _POINTWISE["final_momentum"]
cell_update = _POINTWISE["cell_update"]
emitting = _POINTWISE["emitting"]
speed_of = _POINTWISE["speed_of"]
cell_moves = _POINTWISE["cell_moves"]
carries = _POINTWISE["carries"]
observe_cell = _POINTWISE["observe_cell"]
observe = _POINTWISE["observe"]
step_terms = _POINTWISE["step_terms"]
open_mass = _POINTWISE["open_mass"]
dirac_face = _POINTWISE["dirac_face"]
take_back = _POINTWISE["take_back"]
outflow_volume = _POINTWISE["outflow_volume"]
face_flux = _POINTWISE["face_flux"]
vector_face_flux = _VECTOR["face_flux"]
emitted_state = _POINTWISE["emitted_state"]
emitted_side = _POINTWISE["emitted_side"]
heun_average = _POINTWISE["heun_average"]
half_step = _POINTWISE["half_step"]
side_fluxes = _POINTWISE["side_fluxes"]
source_rate = _POINTWISE["source_rate"]
take_erodible = _POINTWISE["take_erodible"]
basal_shear = _POINTWISE["basal_shear"]

#: the constants the traversals share with the pointwise functions
SQRT3 = kinetic.SQRT3
FLOWING, UNDER_THRESHOLD, DRY = physics.FLOWING, physics.UNDER_THRESHOLD, physics.DRY
FACE_INNER, FACE_WALL, FACE_OPEN = physics.FACE_INNER, physics.FACE_WALL, physics.FACE_OPEN
TRANSPORT_EPS = physics.TRANSPORT_EPS
SOURCE_NONE, SOURCE_CONSTANT = physics.SOURCE_NONE, physics.SOURCE_CONSTANT
