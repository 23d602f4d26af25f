"""Basal friction laws, all behind one pointwise signature.

Every law answers the same question for one cell: given the thickness ``h`` (m, normal to
the bed), the speed ``speed`` (m/s, at time n: the seed linearises the friction at time n,
section 3.3 after eq. 50) and the normal acceleration ``normal_accel`` (m/s^2: g cos(theta)
plus the curvature term u^2/R of eqs. 61-62), what is

- ``tau``: the Coulomb-type part of the basal shear stress divided by the density (m^2/s^2),
  ``mu(h, |u|) * h * normal_accel`` (eqs. 12, 44), the threshold of the projection (eq. 49);
- ``drag``: a velocity-proportional rate (1/s) treated implicitly after the projection,
  zero for Coulomb, Pouliquen and velocity weakening, ``g |u| / (xi h)`` for Voellmy's
  turbulent term,
  ``|u| / (D(h)^2 h)`` for samosAT's (:func:`samosat_drag_factor`).

The law is chosen by name once, outside the time loop (:class:`Law`), and enters the Numba
kernels as an integer with a float64 parameter vector; there is no config object in a kernel.
Adding a law touches this file (one enum member, one branch, one parameter packer) and one test.
"""

from __future__ import annotations

import math
from enum import IntEnum

import numpy as np
from numba import njit

from avflow.scenario.extensions import FRICTION_LAWS, law_by_code

__all__ = [
    "Law",
    "friction",
    "friction_parameters",
    "PARAMETER_SLOTS",
    "law_reference",
    "pouliquen_mu",
    "h_stop",
    "pouliquen_steady_froude",
    "samosat_drag_factor",
    "velocity_weakening_mu",
    "velocity_weakening_threshold",
]


class Law(IntEnum):
    """Friction laws known to the kernels."""

    COULOMB = 1  #: constant friction angle delta, eq. 11-14
    POULIQUEN = 2  #: flow-dependent angle of Pouliquen (1999), eq. 15, static branch below Fr = beta
    VOELLMY = 3  #: Coulomb plus turbulent drag g u^2 / xi (Voellmy 1955; Salm 1993)
    SAMOSAT = 4  #: AvaFrame's snow law: Coulomb reduced with speed, plus drag depending on h
    #: Lucas, Mangeney and Ampuero (2014): mu_w + (mu_s - mu_w) / (1 + |u| / U_w)
    VELOCITY_WEAKENING = 5


# Plain ints for the kernels: Numba freezes module globals as compile-time constants.
COULOMB = int(Law.COULOMB)
POULIQUEN = int(Law.POULIQUEN)
VOELLMY = int(Law.VOELLMY)
SAMOSAT = int(Law.SAMOSAT)
VELOCITY_WEAKENING = int(Law.VELOCITY_WEAKENING)

N_PARAMS = 8  # length of the parameter vector every law is packed into (zeros where unused)

#: Pa: AvaFrame's regularisation of the normal stress in samosAT's Rs (SamosATfric).
SAMOSAT_P_EPS = 0.001

_REFERENCES = {
    Law.COULOMB: "Mangeney-Castelnau et al. (2003), J. Geophys. Res. 108(B11), 2527, eqs. 11-14",
    Law.POULIQUEN: (
        "Pouliquen (1999), Phys. Fluids 11, 542; Pouliquen and Forterre (2002), J. Fluid Mech. 453, "
        "133 (static branch below Fr = beta); as used by Mangeney-Castelnau et al. (2003), eq. 15"
    ),
    Law.VOELLMY: "Voellmy (1955), Schweiz. Bauzeitung 73; Salm (1993), Ann. Glaciol. 18, 221",
    Law.SAMOSAT: (
        "samosAT: Sampl and Zwinger (2004), Ann. Glaciol. 38, 393-398, as implemented in "
        "AvaFrame com1DFA (DFAToolsCython.SamosATfric; Tonnel et al. (2023), Geosci. Model "
        "Dev. 16, 7013-7035; https://docs.avaframe.org, com1DFA theory, friction models)"
    ),
    Law.VELOCITY_WEAKENING: (
        "Lucas, Mangeney and Ampuero (2014), Frictional velocity-weakening in landslides on "
        "Earth and on other planetary bodies, Nat. Commun. 5, 3417, doi:10.1038/ncomms4417: "
        "mu(|u|) = mu_w + (mu_s - mu_w) / (1 + |u| / U_w)"
    ),
}


def law_reference(law: int) -> str:
    """Bibliographic reference of a friction law (built in or registered), for the NetCDF
    ``references`` attribute."""
    registered = law_by_code(int(law))
    if registered is not None:
        return registered.reference
    return _REFERENCES[Law(law)]


def law_name(law: int) -> str:
    """The name of a friction law's code, as a scenario writes it (``coulomb``, or the name
    a law was registered under)."""
    registered = law_by_code(int(law))
    return registered.name if registered is not None else Law(law).name.lower()


def law_code(name: str) -> int:
    """The kernels' code of the law ``name`` (built in or registered)."""
    registered = FRICTION_LAWS.get(name)
    return registered.code if registered is not None else int(Law[name.upper()])


def _tan_deg(angle: float) -> float:
    return math.tan(math.radians(angle))


#: The parameter vector's slots, per law: which field of the scenario's rheology block fills
#: each slot, and the transform from its units to the kernels' (None: as written; "tan": an
#: angle in degrees to its tangent; "per_density": a stress in Pa over the density). What
#: :func:`friction_parameters` packs for a number, and cell by cell for a map. Voellmy's
#: slot 0 is mu, or tan(delta_deg) when delta_deg is given instead. samosAT's slot 3 is
#: fixed (``SAMOSAT_P_EPS / density``), no field's.
PARAMETER_SLOTS = {
    Law.COULOMB: {"delta_deg": (0, "tan")},
    Law.POULIQUEN: {"delta1_deg": (0, "tan"), "delta2_deg": (1, "tan"), "d": (2, None),
                    "beta": (3, None)},
    Law.VOELLMY: {"mu": (0, None), "delta_deg": (0, "tan"), "xi": (1, None)},
    Law.SAMOSAT: {"mu": (0, None), "tau0": (1, "per_density"), "Rs0": (2, None),
                  "kappa": (4, None), "R": (5, None), "B": (6, None)},
    Law.VELOCITY_WEAKENING: {"mu_s": (0, None), "mu_w": (1, None), "U_w": (2, None)},
}


def _transform(how: str | None, value: float, density: float | None) -> float:
    """One value from the scenario's units to the kernels' (:data:`PARAMETER_SLOTS`)."""
    if how == "tan":
        return _tan_deg(value)
    if how == "per_density":
        return value / density
    return float(value)


def _transform_map(how: str | None, values: np.ndarray, density: float | None) -> np.ndarray:
    """:func:`_transform` of every cell's value, with the same scalar arithmetic (math's
    tan, not numpy's), once per distinct value: a map equal to a number packs that
    number's bits in every cell."""
    distinct, where = np.unique(np.asarray(values, dtype=float), return_inverse=True)
    packed = np.array([_transform(how, float(v), density) for v in distinct])
    return packed[where.reshape(-1)]


def friction_parameters(rheology, density: float | None = None,
                        maps: dict | None = None) -> tuple[int, np.ndarray]:
    """Map a validated rheology block (``scenario.rheology``) to ``(law, params)``: a
    :class:`Law`, or the code of a law registered through :mod:`avflow.extend` (its
    parameters in its slots, in the order it was registered with).

    ``density`` (kg/m^3, ``scenario.physics.density``) is needed by samosAT only, whose
    stresses (Pa) are divided by it. Parameter vectors (float64, length N_PARAMS = 8, zeros
    after the last slot shown):
    - Coulomb: ``[tan(delta)]``
    - Pouliquen: ``[tan(delta1), tan(delta2), d (m), beta]``
    - Voellmy: ``[mu, xi (m/s^2)]``
    - samosAT: ``[mu, tau0 / rho (m^2/s^2), Rs0, 0.001 Pa / rho (m^2/s^2), kappa, R (m), B]``
    - velocity weakening: ``[mu_s, mu_w, U_w (m/s)]``

    ``maps``: fields of the block that vary in space, ``{field: values per cell}`` in the
    field's own units (degrees, Pa, ...; sampled by :mod:`avflow.terrain.maps`, their range
    checked there). ``params`` is then a map of shape ``(n_cells, N_PARAMS)``, a row per
    cell (:class:`~avflow.numerics.solver.Solver` takes it as it is); each mapped field's
    slot holds its transformed values (:data:`PARAMETER_SLOTS`), every other slot the
    number's, the same bits in every row.
    """
    registered = FRICTION_LAWS.get(rheology.law)
    law = Law[rheology.law.upper()] if registered is None else registered.code
    maps = dict(maps or {})
    slots = (PARAMETER_SLOTS[law] if registered is None
             else {p: (slot, None) for slot, p in enumerate(registered.parameters)})
    unknown = sorted(set(maps) - set(slots))
    if unknown:
        raise ValueError(f"{law_name(law)} has no parameter {unknown[0]!r} to map; its "
                         f"parameters: {', '.join(slots)}")
    if law is Law.SAMOSAT and (density is None or not density > 0.0):
        raise ValueError("samosAT needs the density (kg/m^3, physics.density), "
                         f"got {density!r}")
    params = np.zeros(N_PARAMS)
    for name, (slot, how) in slots.items():
        value = getattr(rheology, name)
        if value is None or name in maps:  # Voellmy's friction not given this way; a map
            continue
        if not isinstance(value, (int, float)):
            raise ValueError(f"{name} is a map: give its values per cell in maps")
        params[slot] = _transform(how, value, density)
    if law is Law.SAMOSAT:
        params[3] = SAMOSAT_P_EPS / density
    if not maps:
        return law, params
    sizes = {np.size(v) for v in maps.values()}
    if len(sizes) != 1:
        raise ValueError(f"the maps hold different numbers of cells: {sorted(sizes)}")
    rows = np.tile(params, (sizes.pop(), 1))
    for name, values in maps.items():
        slot, how = slots[name]
        rows[:, slot] = _transform_map(how, values, density)
    return law, rows


@njit(error_model="numpy", cache=True, inline="always")
def pouliquen_mu(h, speed, g, tan1, tan2, d, beta):
    """Friction coefficient of Pouliquen's law, eq. 15, extended below Fr = beta.

    Above Fr = |u| / sqrt(g h) = beta: ``mu = tan d1 + (tan d2 - tan d1) exp(-beta h / (d Fr))``.
    Below it the seed needs ``h = h_stop(theta)`` when u = 0 (section 5): we use the static
    branch ``mu_stop(h) = tan d1 + (tan d2 - tan d1) exp(-h / d)`` (Pouliquen and Forterre
    2002), which is the value of eq. 15 at Fr = beta, so mu is continuous, between tan d1 and
    tan d2, and a layer at rest on a slope theta stays exactly when h <= h_stop(theta).
    """
    if h <= 0.0:
        return tan2
    froude = speed / math.sqrt(g * h)
    if froude >= beta:
        return tan1 + (tan2 - tan1) * math.exp(-beta * h / (d * froude))
    return tan1 + (tan2 - tan1) * math.exp(-h / d)


@njit(error_model="numpy", cache=True, inline="always")
def velocity_weakening_mu(speed, mu_s, mu_w, u_w):
    """Friction coefficient of Lucas, Mangeney and Ampuero (2014):
    ``mu_w + (mu_s - mu_w) / (1 + |u| / U_w)``.

    ``mu_s`` at rest, half way to ``mu_w`` at ``|u| = U_w``, tending to ``mu_w`` in fast
    flow. Always in [mu_w, mu_s], so the law never pushes a cell (the projection of eq. 50
    only brakes). Written ``mu_s - (mu_s - mu_w) s / (1 + s)``, s = |u| / U_w, the same
    number, so that at rest it is mu_s to the bit (``mu_w + (mu_s - mu_w)`` can round off
    mu_s): the threshold of a cell at rest is Coulomb's with mu_s exactly.
    """
    s = speed / u_w
    return mu_s - (mu_s - mu_w) * (s / (1.0 + s))


def velocity_weakening_threshold(theta_deg, mu_s, mu_w, u_w):
    """Speed (m/s) above which a block on a plane of slope theta accelerates.

    On the plane ``du/dt = g cos(theta) (tan(theta) - mu(u))``; mu falls with u, so the
    block speeds up iff ``mu(u) < tan(theta)``, i.e. ``u > U_w (mu_s - tan) / (tan - mu_w)``.
    0 at or above atan(mu_s) (it moves from rest), infinite at or below atan(mu_w) (it
    always brakes).
    """
    t = math.tan(math.radians(theta_deg))
    if t >= mu_s:
        return 0.0
    if t <= mu_w:
        return math.inf
    return u_w * (mu_s - t) / (t - mu_w)


@njit(error_model="numpy", cache=True, inline="always")
def samosat_drag_factor(h, kappa, r, b):
    """samosAT's turbulent factor ``1 / D(h)^2``, ``D = ln(max(h / R, 1)) / kappa + B``.

    The turbulent stress is ``rho |u|^2 / D^2``: a logarithmic (rough-wall) velocity profile
    over a roughness length R, floored at ``B`` for layers thinner than R. No g in it.
    """
    d = b
    if h > r:
        d += math.log(h / r) / kappa
    return 1.0 / (d * d)


#: Added to a law's code when its parameters are per cell (friction maps, forest: issue 30):
#: the kernels then read a row of parameters per cell, and the forest's resistance
#: coefficient in the slot :data:`FOREST_SLOT` (no law uses it; 0 outside forest). Such a
#: run takes the kernels' copy that reads the law at run time; the law-constant copies
#: (Coulomb, Voellmy) never compile either
PER_CELL = 16
#: the parameter slot of the forest's resistance coefficient ``c_f`` (dimensionless)
FOREST_SLOT = 7


@njit(error_model="numpy", cache=True, inline="always")
def friction(law, p0, p1, p2, p3, p4, p5, p6, p7, h, speed, normal_accel, g):
    """Basal friction of one cell, :func:`law_friction`, plus the forest's drag where the
    law's code carries :data:`PER_CELL`: a resistance ``c_f |u|^2`` per unit area and
    density (AvaFrame com1DFA's resistance areas, ``computeResForce``; ``c_f = p7``, 0
    outside forest, where it adds exactly 0), implicit on ``q = h u`` like Voellmy's
    turbulent term: ``drag += c_f |u| / h``."""
    if law >= PER_CELL:  # never true in the law-constant copies: folded away there
        tau, drag = law_friction(law - PER_CELL, p0, p1, p2, p3, p4, p5, p6, p7, h, speed,
                                 normal_accel, g)
        if h > 0.0:
            drag += p7 * speed / h
        return tau, drag
    return law_friction(law, p0, p1, p2, p3, p4, p5, p6, p7, h, speed, normal_accel, g)


@njit(error_model="numpy", cache=True, inline="always")
def law_friction(law, p0, p1, p2, p3, p4, p5, p6, p7, h, speed, normal_accel, g):
    """Basal friction of one cell: ``(tau, drag)`` as described in the module docstring.

    ``tau`` (m^2/s^2) is compared with ``|q~| / dt`` in the threshold test of eq. 49 and
    removed in the projection of eq. 50; ``drag`` (1/s) divides the projected discharge
    implicitly, ``q <- q / (1 + drag dt)``, so it can slow a cell but never reverse it.
    ``p0..p7`` is the parameter vector of :func:`friction_parameters`, passed as scalars
    (array arguments cost reference counting at every call in Numba).

    samosAT (AvaFrame com1DFA's ``SamosATfric``, Sampl and Zwinger 2004), in Pa::

        tau_b = tau0 + mu sigma (1 + Rs0 / (Rs0 + Rs)) + rho |u|^2 / D(h)^2,
        Rs = rho |u|^2 / (sigma + 0.001 Pa),  D(h) = ln(max(h / R, 1)) / kappa + B,

    with ``sigma = rho h N`` the basal normal stress. Divided by rho (avflow's kinematic
    units, N = ``normal_accel``)::

        tau  = tau0/rho + mu h N (1 + Rs0 / (Rs0 + Rs)),  Rs = |u|^2 / (h N + 0.001/rho)
        drag = |u| / (D(h)^2 h)          (|u|^2 / D^2 on q = h u, implicit like Voellmy's)

    The speed-dependent Coulomb part, between ``2 mu h N`` at rest and ``mu h N`` when
    Rs >> Rs0, is linearised at time n like Pouliquen's law (seed section 3.3).
    """
    if law == COULOMB:
        return p0 * h * normal_accel, 0.0
    if law == POULIQUEN:
        mu = pouliquen_mu(h, speed, g, p0, p1, p2, p3)
        return mu * h * normal_accel, 0.0
    if law == VELOCITY_WEAKENING:
        # p0, p1, p2 = mu_s, mu_w, U_w; speed at time n like Pouliquen's (seed section 3.3)
        return velocity_weakening_mu(speed, p0, p1, p2) * h * normal_accel, 0.0
    if law == SAMOSAT:
        # p0..p6 = mu, tau0/rho, Rs0, 0.001 Pa/rho, kappa, R, B (friction_parameters)
        hn = h * normal_accel
        rs = speed * speed / (hn + p3)
        tau = p1 + p0 * hn * (1.0 + p2 / (p2 + rs))
        drag = 0.0
        if h > 0.0:
            drag = speed * samosat_drag_factor(h, p4, p5, p6) / h
        return tau, drag
    # VOELLMY: tau_b / rho = mu h N + g |u|^2 / xi; the turbulent part as an implicit drag
    # on q = h u: g |u| u / xi = (g |u| / (xi h)) q.
    drag = 0.0
    if h > 0.0:
        drag = g * speed / (p1 * h)
    return p0 * h * normal_accel, drag


def h_stop(theta_deg, delta1_deg, delta2_deg, d):
    """Thickness (m) of the deposit Pouliquen's law leaves on a slope theta (section 5).

    From ``tan(theta) = tan d1 + (tan d2 - tan d1) exp(-h_stop / d)``. Infinite at or below
    delta1 (the layer never flows), zero at or above delta2 (it never stops).
    """
    t, t1, t2 = (math.tan(math.radians(a)) for a in (theta_deg, delta1_deg, delta2_deg))
    if t <= t1:
        return math.inf
    if t >= t2:
        return 0.0
    return d * math.log((t2 - t1) / (t - t1))


def pouliquen_steady_froude(h, theta_deg, delta1_deg, delta2_deg, d, beta):
    """Froude number of a steady uniform flow of thickness h on slope theta: beta h / h_stop."""
    return beta * h / h_stop(theta_deg, delta1_deg, delta2_deg, d)
