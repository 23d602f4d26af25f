"""The pointwise physics of the seed's scheme, written once (issue 27): plain functions of
scalars, with no decorator of their own. Every traversal (profile, square grid, faces, on
one thread or many) calls these, compiled for the CPU by :mod:`avflow.numerics.cpu`; another
target compiles the same functions the same way.

- the threshold test of eq. 49 on the trial momentum of eq. 47 (:func:`trial_momentum`);
- the projection of eq. 50 with the law's drag (:func:`project`, :func:`final_momentum`),
  in a cell's update (:func:`cell_update`);
- the flux through a face, with the ghost of a wall or an open side (:func:`face_flux`);
- the Dirac face of eqs. 51-53 (:func:`dirac_face`), what a dry side takes back through one
  (:func:`take_back`), the open side (:func:`open_mass`) and what leaves through it
  (:func:`outflow_volume`);
- the curvature term of eqs. 61-62 (:func:`centripetal_accel`, :func:`normal_accel`);
- what a cell emits and how fast it moves (:func:`emitted_state`, :func:`observe_cell`,
  :func:`cell_moves` with :func:`carries`: the moving rule);

The kinetic half fluxes are in :mod:`avflow.numerics.kinetic`, the friction laws in
:mod:`avflow.numerics.rheology`.
"""

from __future__ import annotations

import math

from avflow.numerics.kinetic import SQRT3, half_flux_in, half_flux_out, half_fluxes, sound_speed
from avflow.numerics.rheology import friction

# Per-cell flag of sweep 1 (kept for output): which density the cell takes in sweep 2.
FLOWING = 0  #: above the Coulomb threshold: rectangular density
UNDER_THRESHOLD = 1  #: wet and under the threshold: Dirac density, q = 0 (eqs. 51, 56)
DRY = 2  #: dry at time n: zero temperature as well, momentum from the projection

#: A cell counts as moving when u != 0 and one of its faces carries a mass flux above this
#: fraction of h |u|. A kinetic scheme can hold a cell at a steady u != 0 whose face fluxes
#: balance to round-off (the "fluid-like zone" pinned behind a deposit, seed section 6.4):
#: such a cell transports nothing and must not keep a run alive.
TRANSPORT_EPS = 1e-9


#: ``explicit`` of :func:`trial_momentum` and :func:`final_momentum` for MUSCL-Hancock's
#: single stage: gravity and friction take the thickness at the step's midpoint (False: the
#: seed's h^{n+1}; True: a Runge-Kutta stage's own h^n)
MIDPOINT = 2


def normal_accel(g_normal, centripetal):
    """Bed-normal acceleration ``g cos(theta) + u.K.u`` (eqs. 61-62: ``u^2 / R`` on a profile),
    clamped at 0 where a convex bed would lift the material off (counted: returns 1)."""
    n = g_normal + centripetal
    if n < 0.0:
        return 0.0, 1
    return n, 0


def centripetal_accel(curvature, i, h, hu, hv):
    """``u.K.u`` (m/s^2) of cell i at time n: ``curvature[i] = (K11, K12, K22)`` in its basis."""
    if h <= 0.0:
        return 0.0
    u1 = hu / h
    u2 = hv / h
    return curvature[i, 0] * u1 * u1 + 2.0 * curvature[i, 1] * u1 * u2 + curvature[i, 2] * u2 * u2


def project(qx, qy, tau, drag, dt):
    """Projection of the trial discharge on the admissible Coulomb set, eq. 50, then drag."""
    if qy == 0.0:  # along a line: no norm to take, no division without drag
        excess = abs(qx) - tau * dt
        if excess <= 0.0:
            return 0.0, 0.0
        if drag > 0.0:
            excess /= 1.0 + drag * dt
        return math.copysign(excess, qx), 0.0
    norm = math.sqrt(qx * qx + qy * qy)
    excess = norm - tau * dt
    if excess <= 0.0 or norm <= 0.0:
        return 0.0, 0.0
    scale = excess / (norm * (1.0 + drag * dt))
    return qx * scale, qy * scale


def dt_from_inverse(inv_lim):
    """The CFL limit (s) from the largest inverse limit of the cells; inf when all is still."""
    return 1.0 / inv_lim if inv_lim > 0.0 else math.inf

def trial_momentum(h_old, h_zero, speed_n, hu_old, hv_old, rate_h, rate_x, rate_y, dt,
                    dt_decide, gx, gy, gz, centripetal, law, p0, p1, p2, p3, p4, p5, p6, p7, g,
                    explicit):
    """Sweep-1 closure of one cell: q~ of eq. 47 and the threshold test of eq. 49.

    Gravity acts on ``h*``, the thickness after the fluxes (eq. 47), or with ``explicit``
    (a Runge-Kutta stage of order 2) on the stage's own ``h`` when it is wet: Heun's average
    of two stages is second order only when each stage is an explicit Euler step; with
    ``explicit == MIDPOINT`` (MUSCL-Hancock's single stage) on the thickness half way
    through the step, which keeps the source second order in time. (A cell dry at the
    stage's start keeps ``h*``, as friction does: a front is first order.)

    ``rate_*``: the flux divergences (mass m/s, momentum m^2/s^2). The trial discharge q~
    (returned for the projection) uses the step ``dt``; the threshold is tested with
    ``dt_decide``, the CFL step of the state, so that the decision depends on the state alone
    and a deposit at rest stays at rest when a step is shortened to land on an output time.
    Returns ``(q~x, q~y, flag)``.
    """
    if explicit == MIDPOINT:
        h_star = h_old + 0.5 * dt * rate_h if h_old > h_zero else h_old + dt * rate_h
    else:
        h_star = h_old if explicit and h_old > h_zero else h_old + dt * rate_h
    qx = hu_old + dt * (rate_x + g * h_star * gx)
    qy = hv_old + dt * (rate_y + g * h_star * gy)
    if h_old <= h_zero:
        return qx, qy, DRY
    if dt_decide == dt and not explicit:  # the same numbers: not computed twice
        hd, qdx, qdy = h_star, qx, qy
    else:
        hd = h_old + dt_decide * rate_h
        qdx = hu_old + dt_decide * (rate_x + g * hd * gx)
        qdy = hv_old + dt_decide * (rate_y + g * hd * gy)
    accel, _ = normal_accel(g * gz, centripetal)
    tau, _ = friction(law, p0, p1, p2, p3, p4, p5, p6, p7, hd, speed_n, accel, g)
    limit = tau * dt_decide
    if qdx * qdx + qdy * qdy < limit * limit:
        return qx, qy, UNDER_THRESHOLD
    return qx, qy, FLOWING


def final_momentum(flag, speed_n, h_new, h_zero, qx, qy, dt, gz, centripetal, law, p0, p1, p2, p3,
                    p4, p5, p6, p7, g, h_old, explicit):
    """Sweep-2 momentum of one cell: q = 0 under the threshold (eq. 56), else eq. 50.

    The friction is linearised at time n (speed of ``U^n``), with the new thickness (with
    ``explicit``, a Runge-Kutta stage, with the stage's own thickness when wet, as gravity
    in :func:`trial_momentum`). A cell
    left with ``h <= h_zero`` holds a round-off residue of fluxes that nearly emptied it (on
    real DEMs 1e-28 m at 2 km/s): its momentum is as uncertain as its mass is negligible,
    so it is set to zero; the mass stays (conservation is untouched).
    Returns ``(qx, qy, clamped)``; clamped is 1 when the normal acceleration hit 0.
    """
    if flag == UNDER_THRESHOLD or h_new <= h_zero:
        return 0.0, 0.0, 0
    accel, clamped = normal_accel(g * gz, centripetal)
    if explicit == MIDPOINT:
        h_fric = 0.5 * (h_old + h_new) if h_old > h_zero else h_new
    else:
        h_fric = h_old if explicit and h_old > h_zero else h_new
    tau, drag = friction(law, p0, p1, p2, p3, p4, p5, p6, p7, h_fric, speed_n, accel, g)
    qx, qy = project(qx, qy, tau, drag, dt)
    return qx, qy, clamped


def cell_update(form_dry, flag, h_old, mass, qx, qy, area, dt, gx, gy, gz, centripetal, speed_n,
                law, p0, p1, p2, p3, p4, p5, p6, p7, g, h_zero, explicit, line):
    """The second half of a cell's step (sweep 2 of the seed's scheme): its new thickness and
    momentum. ``mass``: the sum of the mass fluxes through its faces that are not Dirac
    (eqs. 51-53, inward positive, each ``L F_h``), so ``h^{n+1} = h^n + dt / A mass``;
    ``qx, qy``: the trial discharge of :func:`trial_momentum` (eq. 47), or with
    ``form_dry`` (a cell dry at time n, which had no trial) its momentum sum, from which
    q~ of eq. 47 is formed here with ``q^n = 0`` and ``h* = h^{n+1}``. Then q = 0 under the
    threshold (eq. 56) or the projection of eq. 50 (:func:`final_momentum`).
    ``line`` (a constant where it is called): a profile, whose q_y is 0, a constant the
    projection's test then folds away (with q_y formed at run time, a vectorised profile
    paid a square root and a division per cell).
    Returns ``(h^{n+1}, qx, qy, clamped)``; the traversal decides what a negative
    thickness does (the step is redone)."""
    hn = h_old + dt / area * mass
    qx = dt * (qx / area + g * hn * gx) if form_dry else qx
    qy = 0.0 if line else (dt * (qy / area + g * hn * gy) if form_dry else qy)
    qx, qy, clamped = final_momentum(flag, speed_n, hn, h_zero, qx, qy, dt, gz, centripetal,
                                     law, p0, p1, p2, p3, p4, p5, p6, p7, g, h_old, explicit)
    return hn, qx, qy, clamped


def half_step(h, u1, u2, hx, hy, u1x, u1y, u2x, u2y, k, gx, gy, gz, centripetal, law, p0, p1,
              p2, p3, p4, p5, p6, p7, g):
    """MUSCL-Hancock's predictor: a wet cell's state ``(h, u1, u2)`` after ``k`` (half the
    step) of the depth-averaged equations in their primitive form, with the cell's limited
    slopes (``hx`` = dh/dx in its basis, ...): transport and the hydrostatic pressure
    gradient of eqs. 14-15, gravity along the bed, then friction as the seed's projection
    (eq. 50) over ``k``, so it never reverses the velocity. Its sides evaluated at this state
    make one flux sweep second order in time. Returns ``(h, u1, u2)``."""
    g_normal = g * gz
    ph = h - k * (u1 * hx + u2 * hy + h * (u1x + u2y))
    v1 = u1 - k * (u1 * u1x + u2 * u1y + g_normal * hx - g * gx)
    v2 = u2 - k * (u1 * u2x + u2 * u2y + g_normal * hy - g * gy)
    accel, _ = normal_accel(g_normal, centripetal)
    tau, drag = friction(law, p0, p1, p2, p3, p4, p5, p6, p7, h, math.sqrt(u1 * u1 + u2 * u2),
                         accel, g)
    v1, v2 = project(v1, v2, tau / h, drag, k)
    return ph, v1, v2


def heun_average(h0, hu0, hv0, h2, hu2, hv2, flag1, h_zero):
    """Order 2: Heun's average ``U^{n+1} = (U^n + U**) / 2`` of a cell's state at the step's
    start and after its second stage. A cell that the first stage (a step of the seed's
    scheme from ``U^n``) put under the Coulomb threshold (``flag1``) takes the first-order
    answer q = 0 (eq. 56): the average would give it q^n / 2, and a mass that stops would
    never quite stop. Mass is always averaged (each stage conserves it, so their average
    does). Returns ``(h, qx, qy, fallback)``, fallback 1 where q = 0 replaced a nonzero
    average."""
    hn = 0.5 * (h0 + h2)
    qx = 0.5 * (hu0 + hu2)
    qy = 0.5 * (hv0 + hv2)
    stopped = flag1 == UNDER_THRESHOLD
    fallback = 0
    if hn <= h_zero or stopped:
        if stopped and (qx != 0.0 or qy != 0.0):
            fallback = 1
        qx = 0.0
        qy = 0.0
    return hn, qx, qy, fallback


def emitting(h, h_zero):
    """Thickness that emits particles: a cell at or below ``h_zero`` is dry for the scheme.

    It keeps its mass and receives, but sends nothing (and holds no momentum, see
    :func:`final_momentum`). Without this a film of 1e-30 m spread one cell per step in every
    direction, whatever the physics, and soon covered the whole DEM.
    """
    return h if h > h_zero else 0.0


def speed_of(h, hu, hv):
    """|u| = |q| / h (m/s), 0 where dry."""
    if h <= 0.0:
        return 0.0
    return math.sqrt(hu * hu + hv * hv) / h


def carries(flux, h, speed_n, length):
    """True when a face of ``length`` (1: ``flux`` is per metre) carried the cell's material
    in this step: a mass flux above TRANSPORT_EPS h |u^n| per metre of face (compared as
    ``|flux| > eps h |u^n| L``: no division)."""
    return abs(flux) > TRANSPORT_EPS * h * speed_n * length


def cell_moves(speed, speed_n, carried):
    """True when a cell moves material: u != 0 now, and either it just set off (u^n = 0)
    or one of its faces carried its material in this step (``carried``, :func:`carries`).
    Without jumps (``&``, ``|``), so that the cell loops that call it vectorise."""
    return (speed > 0.0) & ((speed_n == 0.0) | carried)


def observe_cell(h, q_norm, cfl_factor, gz, g):
    """Speed (m/s) of a cell of discharge norm q_norm and its inverse CFL limit (1/s).

    ``cfl_factor = P / (2 A)``: the limit of eq. 41 is ``1 / (cfl_factor (|u| + sqrt(3) c))``;
    the sweeps keep the largest inverse and divide once per step.
    """
    if h <= 0.0:
        return 0.0, 0.0
    speed = q_norm / h
    return speed, cfl_factor * (speed + SQRT3 * sound_speed(h, g * gz))


def observe(write, h, speed, t_new, h_dry, peak_h, peak_speed, arrival, last_moved):
    """The running observers of a cell after a step, each a select (no branch, so the cell
    loops vectorise): peak thickness and speed, arrival (first time above ``h_dry``) and
    the last time it moved, from its accepted state. ``write`` False keeps them as they
    were (the cuda backend: a cell outside the DEM). The observer pass calls this once per
    accepted step (:mod:`avflow.numerics.observers`, and the cuda backend's): a new running
    map is one more value here."""
    return (h if write & (h > peak_h) else peak_h,
            speed if write & (speed > peak_speed) else peak_speed,
            t_new if write & (h > h_dry) & math.isnan(arrival) else arrival,
            t_new if write & (speed > 0.0) else last_moved)


def step_terms(h, area, speed, moves, h_dry):
    """A cell's terms of the step's sums: kinetic energy / density ``h A |u|^2`` (halved
    once for the run), and its volume moving (``moves``, :func:`cell_moves`) above
    ``h_dry`` or as a film at most ``h_dry`` thick: what the stop rules read."""
    volume = h * area
    return (volume * speed * speed, volume if moves & (h > h_dry) else 0.0,
            volume if moves & (h <= h_dry) else 0.0)


def open_mass(f_out):
    """Mass flux (outward) through an open side: what leaves, never anything that enters.

    The ghost copies the cell with its outward normal velocity (``max(u_n, 0)``), so a state
    leaving the map passes through unchanged (the two half fluxes of one state add up to the
    exact flux ``h u_n``). A cell moving inward would still receive the ghost's particles,
    mass from outside the map: an open side lets material leave and nothing enter, so the
    net is cut at 0 (then the face holds the material like a wall, pressure included).
    """
    return f_out if f_out > 0.0 else 0.0


#: What lies beyond a face of cell i (:func:`face_flux`): another cell j, a wall, an open side
FACE_INNER, FACE_WALL, FACE_OPEN = 0, 1, 2


def face_flux(kind, hi, ui1, ui2, ci, si, khi, k3i, hj, uj1, uj2, cj, sj, khj, k3j, nix, niy,
              tix, tiy, njx, njy, tjx, tjy, length):
    """The rectangular flux through a face of ``length`` between cell i and what lies beyond
    it (``kind``): ``(L F_h, momentum to i (x, y), momentum to j (x, y))``, ``F_h`` along the
    normal out of i. Each side is given by what it emits (:func:`emitted_state`: h, u, c,
    sqrt(3) c, k / 2, k / 3) and its face frame (normal ``n`` and tangent ``t`` in its own
    basis, so a curved mesh turns the flux into each cell's basis). The normal part is the
    kinetic flux ``F+(U_i) + F-(U_j)`` (eq. 38), the tangential velocity is carried upwind with
    the mass. Beyond a wall the mirror ghost ``(h, -u_n, u_t)``: no mass, twice the pressure;
    beyond an open side the cell's own state leaving (``max(u_n, 0)``), closed to what would
    enter (:func:`open_mass`). The j side's values are not read there (pass zeros).

    Every traversal calls this one function; in the loops that vectorise, its copy with the
    branch-free half fluxes (``cpu.vector_face_flux``) with ``kind`` a constant, whose
    branch then folds away."""
    uni = ui1 * nix + ui2 * niy
    uti = ui1 * tix + ui2 * tiy
    fp_h, fp_q = half_flux_out(hi, uni, ci, si, khi, k3i)
    if kind == FACE_INNER:
        unj = uj1 * njx + uj2 * njy
        utj = uj1 * tjx + uj2 * tjy
        gm_h, gm_q = half_flux_in(hj, unj, cj, sj, khj, k3j)
    elif kind == FACE_WALL:  # mirror ghost (h, -u_n, u_t): no mass, twice the pressure
        gm_h = -fp_h
        gm_q = fp_q
        utj = uti
    else:  # open: transmissive for what leaves, closed to what would enter
        gm_h, gm_q = half_flux_in(hi, max(uni, 0.0), ci, si, khi, k3i)
        gm_h = open_mass(fp_h + gm_h) - fp_h
        utj = uti
    f_n = (fp_q + gm_q) * length  # normal momentum flux, face frame
    f_t = (uti * fp_h + utj * gm_h) * length  # tangential momentum, carried upwind
    return ((fp_h + gm_h) * length, f_n * nix + f_t * tix, f_n * niy + f_t * tiy,
            f_n * njx + f_t * tjx, f_n * njy + f_t * tjy)


def dirac_face(dirac, flag_i, flag_j):
    """True when a face carries the Dirac (zero) mass flux: both cells at zero temperature.

    Eqs. 51-53 and section 3.3 (Figs. 4-5); a boundary ghost shares the flag of its cell.
    """
    return dirac & (flag_i != FLOWING) & (flag_j != FLOWING)


def take_back(q, brought, dirac):
    """A dry cell's momentum sum ``q`` (one component) after one of its faces: what that face
    brought to the trial's sum (``brought``, inward positive) taken back where it is a Dirac
    face. A dry side takes momentum only with mass, and a Dirac face (u = 0, eq. 53) carries
    neither, not even the resting neighbour's pressure.

    ``q + (-brought)``, or ``q + 0.0`` on the other faces: a traversal that sums a cell's four
    faces in face order without a jump (the grid's rows) calls it on each, one that meets
    only the Dirac faces calls it there (``q - brought``, the same bits). Not the same bits as
    leaving q alone where q is -0.0: the caller decides which faces it passes."""
    return q + (-brought if dirac else 0.0)


def outflow_volume(f_out, dt):
    """The volume (m^3, or m^2 per metre of a profile) that leaves through an open side in a
    step ``dt``, from its outward mass flux ``f_out`` (``L F_h``, :func:`open_mass`): only
    what leaves, and nothing through a Dirac face (the caller passes those over). Summed,
    face after face, into the run's outflow: what the mass balance counts as gone."""
    return max(f_out, 0.0) * dt


def emitted_state(h, q1, q2, h_zero, g_normal, dens):
    """What a cell emits through its faces, computed once per step (scalars only):
    ``(h, u1, u2, c, sqrt(3) c, k / 2, k / 3)`` with ``k = c * dens`` the particle density of
    :func:`~avflow.numerics.kinetic.half_fluxes`; all zero at or below ``h_zero``. The
    half fluxes then need no division (:func:`~avflow.numerics.kinetic.half_flux_out`)."""
    if h <= h_zero or h <= 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    c = sound_speed(h, g_normal)
    k = c * dens
    return h, q1 / h, q2 / h, c, SQRT3 * c, 0.5 * k, k / 3.0


#: 1 / 3, for the sides of MUSCL-Hancock (:func:`emitted_side`)
THIRD = 1.0 / 3.0


def emitted_side(hf, u1, u2, g_normal, dens):
    """:func:`emitted_state` of a reconstructed side given by its velocity, not its
    discharge (MUSCL-Hancock's sides): the same values to round-off without q = h u formed
    and divided back nor k divided by 3, and no branch (a loop with it vectorises); all zero
    where ``hf`` is 0."""
    wet = hf > 0.0
    sound = math.sqrt(0.5 * g_normal * hf)
    sound = sound if g_normal > 0.0 else 0.0
    k = sound * dens
    return ((hf if wet else 0.0), (u1 if wet else 0.0), (u2 if wet else 0.0),
            (sound if wet else 0.0), (SQRT3 * sound if wet else 0.0), (0.5 * k if wet else 0.0),
            (THIRD * k if wet else 0.0))


def side_fluxes(hf, uf, wet, dens, g_normal):
    """Half fluxes of a cell's reconstructed state (hf, uf) at one of its faces; nothing from
    a cell at or below the minimum flowing thickness (``wet`` False). Scalars only: Numba's
    inlined helpers that take arrays slowed the sweeps threefold."""
    if not wet:
        return 0.0, 0.0, 0.0, 0.0
    c = sound_speed(hf, g_normal)
    return half_fluxes(hf, uf, c, c * dens)



# Mass sources (issue 27's seam, entrainment of issue 30): what a law takes from the
# erodible layer, applied by numerics.sources once per step after the seed's step.
SOURCE_NONE = 0  #: no source: the pass is not run at all
SOURCE_CONSTANT = 1  #: a fixed rate s0 (m/s of erodible depth) wherever the flow lies
#: Hungr and McDougall (2009): the flow grows as ``dh/dt = E_s h |u|`` (s0 = E_s, 1/m), so a
#: volume travelling a distance s grows as ``exp(E_s s)``
SOURCE_EXPONENTIAL = 2
#: AvaFrame com1DFA's erosion energy: ``dm/dt = tau_b |u| / e_b`` per unit area (s0 = e_b,
#: J/kg; its default 5000), the basal shear tau_b of the cell's friction law
SOURCE_EROSION_ENERGY = 3
#: RAMMS::DEBRISFLOW's shear threshold in rate form: ``de/dt = k (tau_b - tau_c)`` above
#: tau_c (s0 = k, m/(s Pa); s1 = tau_c, Pa; s2 = the flow's density, kg/m^3)
SOURCE_SHEAR_THRESHOLD = 4


def source_rate(kind, s0, s1, s2, s3, ratio, u_min, h, speed, shear):
    """Rate (m/s) at which a wet cell of thickness ``h`` and speed ``speed`` takes from its
    erodible layer, for the source law ``kind`` with its parameters ``s0 .. s3``.

    ``shear``: the basal shear stress over the flow's density (m^2/s^2), ``ratio``: the
    layer's density over the flow's (a depth ``e`` taken adds ``ratio e`` of flow). The
    entrainment laws take nothing at or below the speed ``u_min``, so nothing at rest."""
    if kind == SOURCE_CONSTANT:
        return s0
    if speed <= u_min:
        return 0.0
    if kind == SOURCE_EXPONENTIAL:  # dh/dt = E_s h |u| of flow, ratio times the layer's
        return s0 * h * speed / ratio
    if kind == SOURCE_EROSION_ENERGY:  # rho_f shear |u| / (rho_e e_b)
        return shear * speed / (ratio * s0)
    if kind == SOURCE_SHEAR_THRESHOLD:
        excess = s2 * shear - s1  # Pa
        return s0 * excess if excess > 0.0 else 0.0
    return 0.0


def basal_shear(law, p0, p1, p2, p3, p4, p5, p6, p7, h, speed, normal_accel, g):
    """The basal shear stress over the density (m^2/s^2) of a cell moving at ``speed``:
    the law's threshold ``tau`` plus its drag ``drag h |u|`` (Voellmy's ``g |u|^2 / xi``,
    samosAT's turbulent term, the forest's), what the erosion laws read."""
    tau, drag = friction(law, p0, p1, p2, p3, p4, p5, p6, p7, h, speed, normal_accel, g)
    return tau + drag * h * speed


def take_erodible(rate, dt, erodible):
    """Erodible depth (m) a cell takes in a step ``dt``: ``rate * dt``, never more than the
    layer holds, so the layer never goes below zero and the budget stays exact."""
    if rate <= 0.0 or erodible <= 0.0:
        return 0.0
    take = rate * dt
    return take if take < erodible else erodible
