"""Add a friction law, a mass source or an output map to avflow without editing it.

Each is a plain Python function of scalars, registered by name before the first run that uses
it, in the same process. avflow compiles it into the kernels a run needs (the profile, the
square grid, the face lists and the GPU's), once per machine: the compiled kernels are kept in
the per-user kernel cache, keyed by what they are compiled from (the function's code, its
helpers' and the constants they read), so a change to any of them is compiled afresh.
Before anything compiles, each function the run uses is called once with typical numbers and
compiled alone: a wrong shape, a negative or non-finite friction, an exception is one line
naming the file and line. From the command line, ``--extensions FILE.py`` (or ``$AVFLOW_EXTENSIONS``)
runs a file of such registrations before the scenario is read, and the dask workers of an
ensemble, a region or a calibration run it before their members.

A friction law::

    from avflow import extend

    @extend.friction_law("linear_speed", parameters=("mu", "k"),
                         reference="Coulomb friction rising linearly with speed")
    def linear_speed(mu, k, h, speed, normal_accel, g):
        return (mu + k * speed) * h * normal_accel, 0.0

returns ``(tau, drag)``: ``tau`` the Coulomb-type threshold of the basal shear stress over
the density (m^2/s^2: ``mu h N`` for Coulomb, with N the normal acceleration, gravity plus
the curvature term), which the scheme compares with the trial momentum and removes by
projection (eqs. 47-50 of Mangeney-Castelnau et al. 2003), and ``drag`` a rate (1/s) that
divides the projected discharge implicitly (Voellmy's turbulent term is
``g |u| / (xi h)``). Friction is evaluated with the speed at the start of the step, as the
built-in laws are. A scenario then writes ``rheology: {law: linear_speed, mu: 0.4, k:
0.01}``; the file's ``references`` attribute carries ``reference``.

An output map::

    @extend.output_map("peak_momentum", units="m2 s-1",
                       long_name="maximum momentum per unit width |h u|")
    def peak_momentum(old, h, hu, hv, speed, t):
        return max(old, h * speed)

is updated on every cell the flow reaches, once per accepted step, and written to every
run's file with its CF attributes (``cell_methods: duration: maximum``), and by
``avflow export`` with the built-in maps.

A mass source::

    @extend.source("snowfall", parameters=("rate",), reference="snowfall at a constant rate")
    def snowfall(rate, h, speed, t):
        return rate

returns the rate (m/s of flow thickness) it adds to each cell of its area, wet or dry, once
per accepted step after the seed's step (a rate below 0 adds nothing); what lands comes with
no momentum along the bed. A scenario lists it under ``sources``, with where it falls:
``sources: [{law: snowfall, rate: 1.0e-4, polygon: area.geojson}]`` (or ``raster:`` a mask,
or ``x: [xmin, xmax]`` and ``y: [ymin, ymax]``). Several sources may run at once, and with
entrainment; the mass balance and the summary count what they added (``supplied_volume``).

Limits: at most 10 friction laws, of at most 7 parameters each, and sources of at most 4
(numbers, not maps); the functions are compiled by Numba (nopython mode: numbers, ``math``,
no Python objects).
"""

from __future__ import annotations

from avflow.scenario.extensions import (ExtensionError, register_friction_law, register_map,
                                        register_source)

__all__ = ["ExtensionError", "friction_law", "output_map", "source"]


def friction_law(name: str, *, parameters=(), reference: str, bounds: dict | None = None):
    """Register the decorated function as the friction law ``name`` (see the module's
    docstring); ``parameters``: the names of its first arguments, as a scenario writes them;
    ``bounds``: ``{parameter: (lo, hi)}`` checked when a scenario is read (None: any finite
    number)."""

    def register(function):
        register_friction_law(name, function, parameters, reference, bounds)
        return function

    return register


def source(name: str, *, parameters=(), reference: str):
    """Register the decorated function as the mass source ``name`` (see the module's
    docstring): ``function(*parameters, h, speed, t)`` returns a rate in m/s of flow
    thickness (below 0: nothing)."""

    def register(function):
        register_source(name, function, parameters, reference)
        return function

    return register


def output_map(name: str, *, units: str, long_name: str, cell_methods: str = "maximum",
               initial: float = 0.0):
    """Register the decorated function as the running map ``name`` (see the module's
    docstring): ``function(old, h, hu, hv, speed, t)`` returns the cell's new value;
    ``initial`` its value before the first step."""

    def register(function):
        register_map(name, function, units, long_name, cell_methods, initial)
        return function

    return register
