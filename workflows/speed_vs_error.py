"""Speed against error: what an answer costs at the accuracy it needs.

    python workflows/speed_vs_error.py                     # everything, order 1 and 2
    python workflows/speed_vs_error.py --quick             # 2-3 sizes per problem (smoke test)
    python workflows/speed_vs_error.py --problems avalanche_dry,ritter_t137
    python workflows/speed_vs_error.py --anuga-python /path/to/venv/bin/python

For every problem, every scheme (avflow order 1 and order 2; on the 2D case each on the
square grid and on triangles; ANUGA where it can be run) and every cell size from coarse to
fine, one run is timed and its error measured. Wall time is the summary ``wall_time`` (the
time loop, one core; Numba compiled beforehand by an untimed run of the coarsest size; runs
under 0.5 s are repeated and the fastest kept); beside it the CPU time of the same loop (the
thread's CPU seconds in ``Solver.advance``), which other work on the machine inflates much
less. Written to ``--out`` (default ``out/speed_vs_error``): ``PROBLEM.csv`` and
``PROBLEM.png`` (error against seconds, ``--clock wall`` (default) or ``cpu``, log-log, one
line per scheme, one point per cell size, the targets dotted) per problem, and ``report.md``
(the tables and the cheapest measured run reaching each target).

Order 2 is the scenario field ``numerics.order``; where this avflow does not know it (a
``ScenarioError``), the workflow says so and measures order 1 only. References (section 6, the
2D case) are run with the highest order there is, on the square grid.

The problems with an exact solution run with ``physics.min_flow_thickness: 0``, the equations
that solution solves (``--keep-film-rule``: as the scenario files have it, 1 mm): the film
rule holds the front's thin tip still and stalls dh at about 2e-3 on 5 degrees.

Problems and errors:

- ``ritter_t37``, ``ritter_t137``: the seed's 1 m dam break on a flat frictionless bed
  (Ritter), eq. 57's ``dh`` at 37 s and 137 s (``scenarios/seed_dambreak_flat_dx2.yaml``).
- ``dambreak5_delta0/1/4``: the seed's dam breaks on 5 degrees, Coulomb 0, 1, 4 degrees,
  ``dh`` at 35 s against Mangeney et al. (2000) (``seed_dambreak_inclined_delta*_dx2.yaml``).
- ``avalanche_dry``: ANUGA's validation case (``scenarios/anuga_avalanche_dry.yaml``): 20 m
  reservoir, bed slope 0.1, friction slope 0.05; relative L1 errors of the thickness ``h``
  and of the discharge ``q = h u`` at 1 s and 3 s over the dam +- 100 m (ANUGA's domain),
  ANUGA's tolerances 1% (h) and 2.5% (q).
- ``section6_coulomb15``, ``section6_pouliquen1.5``: the seed's section 6 (exponential slope,
  Coulomb 15 degrees; Pouliquen 13/20 degrees, d = 1.5 m): runout, time to stop and deposit
  maximum against a fine-grid reference (dx = 6.25 / 8 m, order 2 when there is one, else
  order 1; ``--fine-reference``: 6.25 / 16 m), cell sizes 25 to 3.125 m.
- ``plane_cylinder``: the contract's cylinder on a 30 degree plane facing 30 degrees off the
  grid axes (``scenarios/plane_cylinder.yaml``, a copy of ``shared/contract``), Coulomb 20
  degrees, at t = 20 s (at the contract's 200 s the mass has left the map), on a map cropped
  around the flow (the answer does not depend on the map; checked: no material reaches the
  crop's edge); cell sizes 20, 10, 5 m, reference 2.5 m (so the 5 m point's error is
  understated, about halved at first order; ``--fine-reference``: 1.25 m, minutes more),
  square grid and triangles against the same reference. The centre of mass against the
  reference's and against the point mass ``a t^2 / 2``, ``a = g (sin theta - cos theta tan
  delta)``, and the footprint (h > 1 cm) against the reference's: area of the symmetric
  difference over the reference's area, on the reference's cells. ``a t^2 / 2`` is exact
  only while every velocity points straight downslope; a cylinder spreads sideways, the
  friction's downslope part is then smaller and it runs ahead of it, so that column is an
  offset, not a numerical error.
- ``similarity``, ``similarity_rot45``: the similarity solution of Hutter et al. (1993)
  (``avflow.numerics.analytic.similarity``; the case of ``tests/test_similarity.py`` and
  ``workflows/similarity.py``, AvaFrame's ana1Tests): a parabolic cap, 80 m in radius and
  4 m thick, released on a 35 degree plane, Coulomb 25 degrees, at t = 5 s, the slope along
  the grid's axes and turned by 45 degrees on the grid, square grid and triangles; each cell
  size gets its release raster (the exact cap at its cell centres: the square cells' and
  the triangles' vertices), on a 400 m map around the flow; in the CSV ``volume0``, the
  released volume against the cap's (relative), and ``release``, the largest difference of
  the released thickness from the cap (m). Relative L2 (weighted by the cells' areas) of
  the thickness against the exact cap at the cells' centres; the front (farthest point
  downslope with h > 1% of the release thickness) against the exact contour there (m); the
  lateral spread and the area above that thickness against the exact ellipse's (relative);
  the signed values in the CSV. The exact solution's own approximation (its lateral
  friction linearised at the centre's speed) sets a floor under L2 that grows with time:
  at 5 s about 6e-3 (order 2's L2 at 1.25 m), at 20 s about 0.03 (order 2's at 2.5 m
  already).

ANUGA (not a dependency of avflow) is run in a subprocess by the Python given with
``--anuga-python`` (default: this one), when that Python can ``import anuga``: on the dam
breaks and ``avalanche_dry``, each in ANUGA's own equations (vertical depth, horizontal x,
``c0 = sqrt(g H0)``, acceleration ``g tan(theta) - g cos^2(theta) tan(delta)``, as in ANUGA's
avalanche_dry) against that model's exact solution, on ANUGA's 1D set-up (a strip 3 cells
wide, ``rectangular_cross``: 12 triangles per cell length), one OpenMP thread, with its
flow algorithms DE0 (Euler in time) and DE1 (Heun). Not on section 6 and the cylinder:
ANUGA has no Coulomb law with a threshold that lets a mass stop. PyClaw is not measured.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"
G = 9.81
REPEAT_BELOW_S = 0.5  # runs faster than this are repeated (3 in all) and the fastest kept


# =========================================================================================
# Exact solutions in ANUGA's equations (numpy only: the ANUGA worker imports no avflow)
# =========================================================================================


def ritter_accelerated(x, t, x0, h0, g_normal, accel):
    """Dam break on a plane with constant acceleration ``accel`` along +x (Mangeney et al.
    2000): Ritter's rarefaction with gravity ``g_normal`` in the frame moving at ``accel``.
    Reservoir of depth ``h0`` at x < x0 at t = 0. Returns ``(h, u)``. The formula of
    :func:`avflow.numerics.analytic.dam_break`, with ANUGA's gravity and acceleration: it is
    written again because the ANUGA worker runs in ANUGA's venv, where avflow is absent
    (tests/test_speed_vs_error.py checks the two against ANUGA's own solution)."""
    x = np.asarray(x, dtype=float)
    c0 = math.sqrt(g_normal * h0)
    xi = (x - x0 - 0.5 * accel * t * t) / t
    h = np.where(xi <= -c0, h0, np.where(xi >= 2 * c0, 0.0, (2 * c0 - xi) ** 2 / (9 * g_normal)))
    u = np.where(xi <= -c0, accel * t,
                 np.where(xi >= 2 * c0, 0.0, 2.0 * (c0 + xi) / 3.0 + accel * t))
    return h, u


def anuga_acceleration(tan_theta, tan_delta, g=G):
    """Acceleration of the reservoir in ANUGA's avalanche_dry: ``g tan(theta) - F`` with
    ``F = g cos^2(theta) tan(delta)`` (ANUGA's ``-m``; the seed's model has
    ``g (sin(theta) - cos(theta) tan(delta))`` and ``g cos(theta)`` across the bed)."""
    cos_t = math.cos(math.atan(tan_theta))
    return g * tan_theta - g * cos_t * cos_t * tan_delta


def eq57(h, h_exact, h0):
    """The seed's eq. 57 (as avflow.numerics.analytic.relative_error)."""
    m = (h_exact > 0.0) & (h_exact < h0)
    return float(np.sum((h[m] - h_exact[m]) ** 2) / np.sum(h_exact[m] ** 2))


def l1(value, exact, mask):
    """Relative L1 error over ``mask``: ``sum |v - v_a| / sum |v_a|``."""
    return float(np.sum(np.abs(value[mask] - exact[mask])) / np.sum(np.abs(exact[mask])))


# =========================================================================================
# ANUGA worker (runs in the ANUGA Python: python speed_vs_error.py --anuga-worker JSON)
# =========================================================================================


def anuga_worker(spec: dict) -> dict:
    """Runs one problem at the given cell sizes with one flow algorithm; returns rows."""
    import anuga

    try:
        anuga.set_omp_num_threads(1, verbose=False)
    except (AttributeError, TypeError):
        pass
    p = spec["problem"]
    s, tan_d, h0, x0 = p["tan_theta"], p["tan_delta"], p["h0"], p["x0"]
    xmin, xmax = p["xmin"], p["xmax"]
    cos_t = math.cos(math.atan(s))
    friction = G * cos_t * cos_t * tan_d  # ANUGA's F
    accel = G * s - friction
    rows = []
    for dx in spec["sizes"]:
        length, width = xmax - xmin, 3 * dx
        points, vertices, boundary = anuga.rectangular_cross(
            int(round(length / dx)), 3, length, width, (xmin, -width / 2))
        domain = anuga.Domain(points, vertices, boundary)
        domain.set_flow_algorithm(spec["algorithm"])
        domain.set_store(False)
        domain.set_quantity("friction", 0.0)
        domain.set_quantity("elevation", lambda x, y: -s * x)
        domain.set_quantity("stage", lambda x, y: -s * x + np.where(x < x0, h0, 0.0))
        if friction > 0.0:
            def coulomb(dom, f=friction):  # constant Coulomb forcing against +x (ANUGA's)
                h = (dom.quantities["stage"].centroid_values
                     - dom.quantities["elevation"].centroid_values)
                dom.quantities["xmomentum"].explicit_update[:] -= f * h
            domain.forcing_terms.append(coulomb)
        wall = anuga.Reflective_boundary(domain)
        left = wall
        if p.get("inflow"):  # ANUGA's avalanche_dry: the rest of the reservoir flows in
            left = anuga.Time_boundary(
                domain, function=lambda t: [-s * xmin + h0, accel * t * h0, 0.0])
        right = anuga.Transmissive_boundary(domain) if p.get("inflow") else wall
        domain.set_boundary({"left": left, "right": right, "top": wall, "bottom": wall})
        x = domain.centroid_coordinates[:, 0]
        times = sorted(p["times"])
        errors, spent, spent_cpu = {}, 0.0, 0.0
        start, start_cpu = time.perf_counter(), time.process_time()
        for t in domain.evolve(yieldstep=times[0] if len(times) == 1 else 1.0,
                               finaltime=times[-1]):
            if not any(abs(t - tt) < 1e-9 for tt in times):
                continue
            t0, t0_cpu = time.perf_counter(), time.process_time()
            q = domain.quantities
            h = q["stage"].centroid_values - q["elevation"].centroid_values
            he, ue = ritter_accelerated(x, t, x0, h0, G, accel)
            if p["measure"] == "dh":
                errors["dh"] = eq57(h, he, h0)
            else:
                window = np.abs(x - x0) <= p["window"]
                tag = f"t{t:g}"
                errors[f"h_L1_{tag}"] = l1(h, he, window)
                errors[f"q_L1_{tag}"] = l1(q["xmomentum"].centroid_values, he * ue, window)
            spent += time.perf_counter() - t0
            spent_cpu += time.process_time() - t0_cpu
        rows.append({"dx": dx, "cells": int(x.size), "wall": time.perf_counter() - start - spent,
                     "cpu": time.process_time() - start_cpu - spent_cpu, "steps": None,
                     "errors": errors})
    return {"rows": rows, "version": getattr(anuga, "__version__", "?")}


def run_anuga(python: str, problem: dict, algorithm: str, sizes, timeout: float):
    """Rows of one ANUGA algorithm on one problem, or (None, why)."""
    spec = json.dumps({"problem": problem, "algorithm": algorithm, "sizes": list(sizes)})
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    try:
        done = subprocess.run([python, str(Path(__file__).resolve()), "--anuga-worker", spec],
                              capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return None, f"ANUGA {algorithm}: over {timeout:.0f} s, stopped"
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("{")]
    if done.returncode != 0 or not lines:
        tail = (done.stderr.strip().splitlines() or ["no output"])[-1]
        return None, f"ANUGA {algorithm} failed: {tail}"
    return json.loads(lines[-1]), None


def anuga_importable(python: str) -> tuple[bool, str]:
    try:
        done = subprocess.run([python, "-c", "import anuga; print(anuga.__version__)"],
                              capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as err:
        return False, str(err)
    if done.returncode != 0:
        return False, (done.stderr.strip().splitlines() or ["import failed"])[-1]
    return True, done.stdout.strip().splitlines()[-1]


# =========================================================================================
# Problems
# =========================================================================================


@dataclass
class Measure:
    key: str
    label: str  #: for tables and plots
    unit: str = ""  #: "" for relative errors


@dataclass
class Problem:
    name: str
    title: str
    scenario: str  #: file in scenarios/
    updates: dict
    sizes: tuple  #: cell sizes, coarse to fine (m)
    quick: tuple
    measures: list
    observe: Callable  #: RunResult -> observations (dict)
    errors: Callable  #: (observations, reference observations or None) -> {measure: error}
    targets: list  #: [(label, {measure: bound})]
    reference_dx: float | None = None
    quick_reference_dx: float | None = None
    meshes: tuple = ("square",)
    anuga: dict | None = None  #: ANUGA's set-up of the same case
    anuga_sizes: tuple = ()
    anuga_quick: tuple = ()
    note: str = ""
    values: list = field(default_factory=list)  #: observation keys also written to the CSV
    #: updates that make the scenario the equations of the exact solution (see EXACT_MODEL)
    exact_model: bool = False
    #: the scenario file at a cell size (m), where one is written for each (a release raster
    #: at its cell centres); None: ``scenarios/<scenario>``
    scenario_file: Callable[[float], Path] | None = None


#: The exact solutions have no film rule: material thinner than physics.min_flow_thickness
#: (default 1 mm) holds still in avflow, which keeps the thin tip of a dam break's front
#: back and stalls eq. 57's dh (about 2e-3 on 5 degrees, delta 0, growing as dx falls).
#: Applied to the problems with an exact solution unless --keep-film-rule.
EXACT_MODEL = {"physics.min_flow_thickness": 0.0}


def _dam_break_problem(name, title, scenario, t, theta, delta, anuga_times):
    from avflow.numerics.analytic import dam_break, relative_error

    def observe(r):
        sc = r.scenario
        h_exact, _ = dam_break(r.terrain.x, r.state.t, x0=sc.release.position,
                               h0=sc.release.thickness, theta_deg=theta, delta_deg=delta,
                               g=sc.physics.gravity)
        assert abs(r.state.t - t) < 1e-9, (r.state.t, t)
        return {"dh": relative_error(r.state.h, h_exact, sc.release.thickness)}

    return Problem(
        name, title, scenario, {"time.end": t, "output.every": t},
        sizes=(20.0, 10.0, 5.0, 2.0, 1.0, 0.5), quick=(20.0, 5.0),
        measures=[Measure("dh", "dh (eq. 57)")], observe=observe,
        errors=lambda obs, ref: {"dh": obs["dh"]},
        targets=[(f"dh <= {b:g}", {"dh": b}) for b in (1e-3, 3e-4, 1e-4)],
        anuga={"xmin": 0.0, "xmax": 2000.0, "x0": 1000.0, "h0": 1.0,
               "tan_theta": math.tan(math.radians(theta)),
               "tan_delta": math.tan(math.radians(delta)), "times": anuga_times,
               "measure": "dh"},
        anuga_sizes=(20.0, 10.0, 5.0, 2.0), anuga_quick=(20.0,), exact_model=True)


def _avalanche_dry_problem():
    from avflow.numerics.analytic import dam_break

    window = 100.0

    def observe(r):
        sc = r.scenario
        x, x0, h0 = r.terrain.x, sc.release.position, sc.release.thickness
        mask = np.abs(x - x0) <= window
        out = {}
        for t in (1.0, 3.0):
            k = int(np.argmin(np.abs(np.asarray(r.snapshots.time) - t)))
            assert abs(r.snapshots.time[k] - t) < 1e-9, r.snapshots.time
            he, ue = dam_break(x, t, x0=x0, h0=h0, theta_deg=sc.terrain.slope.theta_deg,
                               delta_deg=sc.rheology.delta_deg, g=sc.physics.gravity)
            out[f"h_L1_t{t:g}"] = l1(r.snapshots.h[k], he, mask)
            out[f"q_L1_t{t:g}"] = l1(r.snapshots.hu[k], he * ue, mask)
        return out

    keys = ("h_L1_t1", "q_L1_t1", "h_L1_t3", "q_L1_t3")
    return Problem(
        "avalanche_dry", "ANUGA's avalanche_dry (h0 20 m, bed slope 0.1, friction slope 0.05)",
        "anuga_avalanche_dry.yaml", {}, sizes=(4.0, 2.0, 1.0, 0.5, 0.25, 0.125),
        quick=(2.0, 0.5),
        measures=[Measure("h_L1_t1", "L1 of h, 1 s"), Measure("q_L1_t1", "L1 of hu, 1 s"),
                  Measure("h_L1_t3", "L1 of h, 3 s"), Measure("q_L1_t3", "L1 of hu, 3 s")],
        observe=observe, errors=lambda obs, ref: {k: obs[k] for k in keys},
        targets=[(f"{f:g} x ANUGA's tolerances (h {f:g}%, hu {2.5 * f:g}%)",
                  {"h_L1_t1": 0.01 * f, "h_L1_t3": 0.01 * f,
                   "q_L1_t1": 0.025 * f, "q_L1_t3": 0.025 * f}) for f in (1.0, 0.5, 0.25)],
        anuga={"xmin": -window, "xmax": window, "x0": 0.0, "h0": 20.0, "tan_theta": 0.1,
               "tan_delta": 0.05, "times": [1.0, 3.0], "measure": "l1", "window": window,
               "inflow": True},
        anuga_sizes=(4.0, 2.0, 1.0, 0.5), anuga_quick=(2.0,),
        note="avflow: thickness normal to the bed, x along the bed, against Mangeney et al. "
             "(2000) in the seed's equations; ANUGA: vertical depth, horizontal x, against "
             "its own exact solution (ANUGA's set-up: 200 m, inflow boundary upslope)",
        exact_model=True)


def _section6_problem(name, title, scenario):
    keys = {"runout": "runout", "time_to_stop": "time_to_stop",
            "deposit_max": "deposit_max_thickness"}

    def observe(r):
        return {k: float(r.summary[v]) for k, v in keys.items()}

    def errors(obs, ref):
        return {k: abs(obs[k] - ref[k]) for k in keys}

    return Problem(
        name, title, scenario, {}, sizes=(25.0, 12.5, 6.25, 3.125),
        quick=(25.0, 12.5), reference_dx=0.78125, quick_reference_dx=3.125,
        measures=[Measure("runout", "runout", "m"), Measure("time_to_stop", "time to stop", "s"),
                  Measure("deposit_max", "deposit max", "m")],
        observe=observe, errors=errors,
        targets=[(f"runout {a:g} m, stop {b:g} s, deposit {c:g} m",
                  {"runout": a, "time_to_stop": b, "deposit_max": c})
                 for a, b, c in ((50.0, 2.0, 2.0), (20.0, 1.0, 1.0), (10.0, 0.5, 0.5))],
        values=list(keys))


#: The 2D case: cropped map (the contract's is 3000 m square; the flow stays inside this).
CYLINDER_EXTENT = {"x": [400.0, 1800.0], "y": [1200.0, 2900.0]}
CYLINDER_TIME = 20.0
FOOTPRINT_H = 0.01  # m


def _touches_edge(terrain, peak_h, above: float = 0.0) -> bool:
    """Whether the flow (thicker than ``above``, m) reached the cells along a cropped map's
    edge (it must not)."""
    xx, yy = terrain.cell_xy()
    edge = ((xx - xx.min() < 1.5 * terrain.dx) | (xx.max() - xx < 1.5 * terrain.dx)
            | (yy - yy.min() < 1.5 * terrain.dx) | (yy.max() - yy < 1.5 * terrain.dx))
    return bool(np.any(peak_h[edge] > above))


def _plane_cylinder_problem():
    def observe(r):
        sc, terrain = r.scenario, r.terrain
        xx, yy = terrain.cell_xy()
        theta = math.radians(sc.terrain.slope_deg)
        az = math.radians(sc.terrain.azimuth_deg)
        down = np.array([math.sin(az), math.cos(az)])
        delta = math.radians(sc.rheology.delta_deg)
        accel = sc.physics.gravity * (math.sin(theta) - math.cos(theta) * math.tan(delta))
        travel = 0.5 * accel * r.state.t ** 2 * math.cos(theta)  # horizontal
        c0 = np.array(r.snapshots.center_of_mass[0][:2])
        c = np.array(r.snapshots.center_of_mass[-1][:2])
        foot = r.state.h > FOOTPRINT_H
        return {"c0": c0, "c": c, "exact_travel": travel,
                "com_exact": float(np.hypot(*(c - (c0 + travel * down))) / travel),
                "travel_ratio": float((c - c0) @ down / travel),
                "xy": (xx[foot], yy[foot]), "all_xy": (xx, yy), "foot": foot,
                "area": float(np.sum(terrain.mesh.cell_area[foot]) * math.cos(theta)),
                "dx": terrain.dx, "edge_touched": _touches_edge(terrain, r.state.peak_h)}

    def errors(obs, ref):
        from scipy.spatial import cKDTree

        travel_ref = float(np.hypot(*(ref["c"] - ref["c0"])))
        com_ref = float(np.hypot(*((obs["c"] - obs["c0"]) - (ref["c"] - ref["c0"])))) / travel_ref
        # footprint on the reference's cells: nearest cell centre of this run
        rx, ry = ref["all_xy"]
        tree = cKDTree(np.column_stack(obs["all_xy"]))
        _, idx = tree.query(np.column_stack([rx, ry]))
        mine = obs["foot"][idx]
        sym = np.count_nonzero(mine ^ ref["foot"]) / max(np.count_nonzero(ref["foot"]), 1)
        return {"com_ref": com_ref, "footprint": float(sym), "com_exact": obs["com_exact"]}

    return Problem(
        "plane_cylinder", "contract plane_cylinder scene (30 deg plane, azimuth 30, Coulomb 20, "
        f"r 100 m, 20 m), t = {CYLINDER_TIME:g} s", "plane_cylinder.yaml",
        {"time.end": CYLINDER_TIME, "output.every": CYLINDER_TIME,
         "terrain.extent": CYLINDER_EXTENT},
        sizes=(20.0, 10.0, 5.0), quick=(20.0,), reference_dx=2.5, quick_reference_dx=10.0,
        meshes=("square", "triangles"),
        measures=[Measure("com_ref", "centre of mass vs reference"),
                  Measure("footprint", "footprint (h > 1 cm) vs reference"),
                  Measure("com_exact", "centre of mass vs a t^2/2 (offset, not an error)")],
        observe=observe, errors=errors,
        targets=[(f"centre of mass {a:g}, footprint {b:g}", {"com_ref": a, "footprint": b})
                 for a, b in ((1e-2, 0.1), (5e-3, 0.05), (2e-3, 0.02))],
        values=["travel_ratio", "area"],
        note="centre of mass: distance to the reference's (horizontal, relative to its "
             "travel); footprint: symmetric difference with the reference's (cells with "
             "h > 1 cm, on the reference's cells) over its area; 'vs a t^2/2': offset from the "
             "point mass, not an error (the spreading cylinder runs ahead of it)")


#: The similarity solution's case (tests/test_similarity.py's): slope, Coulomb angle (deg),
#: the cap's thickness and radius (m), the time compared (s); the thickness (m) that draws
#: the front, spread and area
SIMILARITY = {"theta": 35.0, "delta": 25.0, "h0": 4.0, "radius": 80.0, "time": 5.0}
SIMILARITY_EDGE = 0.01 * SIMILARITY["h0"]


def _similarity_frame(turn_deg: float):
    """On the plane facing ``90 + turn_deg`` degrees (east, turned clockwise): the cap's
    centre at t = 0, 250 m up the plane from (400, 400) m as in tests/test_similarity.py (so
    that the cells are its cells), and the map, 400 m square around the flow's path to 5 s,
    its sides on multiples of 10 m."""
    az = math.radians(90.0 + turn_deg)
    down = np.array([math.sin(az), math.cos(az)])  # horizontal
    start = np.array([400.0, 400.0]) - 250.0 * down
    mid = start + 15.0 * down  # the cap reaches 94 m down, 67 m up, 83 m across (horizontal)
    extent = {k: [10.0 * math.floor((c - 200.0) / 10.0), 10.0 * math.ceil((c + 200.0) / 10.0)]
              for k, c in zip("xy", mid)}
    return start, extent


def _bed_coordinates(x, y, turn_deg, start):
    """(along the slope from the cap's start, across it), both on the bed (m)."""
    from avflow.numerics.analytic import bed_coordinates

    return bed_coordinates(x, y, start, 90.0 + turn_deg, SIMILARITY["theta"])


def _release_cap(xi, eta):
    """The exact cap at t = 0 (m) at bed coordinates from its centre."""
    sim = SIMILARITY
    return sim["h0"] * np.clip(1.0 - (xi / sim["radius"]) ** 2 - (eta / sim["radius"]) ** 2,
                               0.0, None)


def _similarity_problem(name: str, turn_deg: float):
    start, extent = _similarity_frame(turn_deg)
    sim = SIMILARITY
    folder: list = []  # a temporary folder for the scenarios and rasters, made once

    def scenario_file(dx: float) -> Path:
        """A scenario and its release raster: the exact cap at t = 0 every half cell, so that
        its nodes hold the square grid's cell centres (odd nodes) and the triangles' vertices,
        their cells' centres (even nodes), where its bilinear sampling returns them."""
        import atexit
        import shutil
        import tempfile

        from avflow.terrain.raster import write_tif

        if not folder:
            folder.append(Path(tempfile.mkdtemp(prefix="avflow-similarity-")))
            atexit.register(shutil.rmtree, folder[0], True)
        path = folder[0] / f"{name}_dx{dx:g}.yaml"
        if path.exists():
            return path
        (x0, x1), (y0, y1) = extent["x"], extent["y"]
        # cell centres x0 + (k + 1/2) dx (plane_terrain), vertices x0 + k dx (triangles)
        x = x0 + np.arange(2 * int(round((x1 - x0) / dx)) + 1) * (0.5 * dx)
        y = y0 + np.arange(2 * int(round((y1 - y0) / dx)) + 1) * (0.5 * dx)
        xi, eta = _bed_coordinates(*np.meshgrid(x, y), turn_deg, start)
        raster = write_tif(folder[0] / f"{name}_dx{dx:g}.tif", _release_cap(xi, eta), x, y,
                           dtype="float64", description="release thickness", units="m")
        path.write_text(
            f"name: {name.replace('_', '-')}\n"
            f"terrain: {{kind: plane, slope_deg: {sim['theta']}, azimuth_deg: "
            f"{90.0 + turn_deg}, extent: {{x: {extent['x']}, y: {extent['y']}}}, "
            "elevation_at_center: 1000.0}\n"
            f"grid: {{dx: {dx}}}\n"
            f"release: {{kind: raster, path: {raster.name}}}\n"
            f"rheology: {{law: coulomb, delta_deg: {sim['delta']}}}\n"
            f"time: {{end: {sim['time']}}}\n"
            f"output: {{every: {sim['time']}}}\n")
        return path

    def observe(r):
        from avflow.numerics.analytic import similarity, similarity_errors

        terrain = r.terrain
        xi, eta = _bed_coordinates(*terrain.cell_xy(), turn_deg, start)
        cap = similarity(r.state.t, sim["theta"], sim["delta"], sim["h0"], sim["radius"],
                         sim["radius"])
        area = terrain.mesh.cell_area  # triangles' dual cells: 2/3 and 4/3 of dx^2 (bed)
        volume = math.pi * sim["radius"] ** 2 * sim["h0"] / 2.0  # the cap's, on the bed
        return {**similarity_errors(cap, r.state.h, xi, eta, area, SIMILARITY_EDGE),
                "volume0": float(np.sum(area * r.h0) / volume - 1.0),
                "release": float(np.max(np.abs(r.h0 - _release_cap(xi, eta)))),
                # no film rule: the scheme moves some mass a cell a step, 3e-9 m reaches
                # the edge at first order and 10 m; a micron would count
                "edge_touched": _touches_edge(terrain, r.state.peak_h, 1e-6)}

    where = "along the grid's axes" if turn_deg == 0.0 else f"turned {turn_deg:g} deg on the grid"
    return Problem(
        name, f"similarity solution (Hutter et al. 1993): cap 80 m, 4 m, {sim['theta']:g} deg "
        f"plane, Coulomb {sim['delta']:g} deg, t = {sim['time']:g} s, the slope {where}",
        "written for each cell size", {}, sizes=(10.0, 5.0, 2.5, 1.25), quick=(10.0, 5.0),
        meshes=("square", "triangles"),
        measures=[Measure("l2", "relative L2 of h"), Measure("front", "front", "m"),
                  Measure("spread", "lateral spread"), Measure("area", "area (h > 1% h0)")],
        observe=observe,
        errors=lambda obs, ref: {k: abs(obs[k]) for k in ("l2", "front", "spread", "area")},
        # the exact solution's own approximation holds L2 above about 6e-3 (1.25 m: 6.2e-3)
        targets=[(f"L2 {a:g}, front {b:g} m, spread {c:.0%}", {"l2": a, "front": b, "spread": c})
                 for a, b, c in ((3e-2, 5.0, 0.03), (1.5e-2, 2.5, 0.02), (8e-3, 1.25, 0.01))],
        values=["front", "spread", "area", "volume0", "release"],
        note="front: the farthest cell downslope with h > 1% of the release thickness against "
             "the exact contour there (m, on the bed; negative: behind); spread (across the "
             "slope) and area at that thickness, relative to the exact ellipse's (front and "
             "spread: to within a cell); the errors are their magnitudes, the values their "
             "signs",
        exact_model=True, scenario_file=scenario_file)


def problems() -> dict[str, Problem]:
    out = [
        _dam_break_problem("ritter_t37", "Ritter's dam break (flat, frictionless), t = 37 s",
                           "seed_dambreak_flat_dx2.yaml", 37.0, 0.0, 0.0, [37.0]),
        _dam_break_problem("ritter_t137", "Ritter's dam break (flat, frictionless), t = 137 s",
                           "seed_dambreak_flat_dx2.yaml", 137.0, 0.0, 0.0, [137.0]),
    ]
    for d in (0, 1, 4):
        out.append(_dam_break_problem(
            f"dambreak5_delta{d}", f"dam break on 5 deg, Coulomb delta = {d} deg, t = 35 s",
            f"seed_dambreak_inclined_delta{d}_dx2.yaml", 35.0, 5.0, float(d), [35.0]))
    out.append(_avalanche_dry_problem())
    out.append(_section6_problem("section6_coulomb15", "seed section 6, Coulomb 15 deg",
                                 "seed_exponential_coulomb15.yaml"))
    out.append(_section6_problem("section6_pouliquen1.5", "seed section 6, Pouliquen d = 1.5 m",
                                 "seed_exponential_pouliquen_d1.5.yaml"))
    out.append(_plane_cylinder_problem())
    out += [_similarity_problem("similarity", 0.0), _similarity_problem("similarity_rot45", 45.0)]
    return {p.name: p for p in out}


GROUPS = {"dambreaks": ["ritter_t37", "ritter_t137", "dambreak5_delta0", "dambreak5_delta1",
                        "dambreak5_delta4"],
          "section6": ["section6_coulomb15", "section6_pouliquen1.5"]}


# =========================================================================================
# avflow runs
# =========================================================================================


def order_support() -> tuple[bool, str]:
    """Whether this avflow knows ``numerics.order`` (order 2), and what it said if not."""
    from avflow.errors import ScenarioError
    from avflow.scenario.schema import load_scenario

    probe = load_scenario(SCENARIOS / "seed_dambreak_flat_dx2.yaml")
    try:
        probe.with_updates({"numerics.order": 2})
    except ScenarioError as err:
        return False, str(err).splitlines()[0]
    return True, ""


@dataclass
class Scheme:
    label: str
    order: int
    mesh: str = "square"
    limiter: str | None = None


def scheme_label(scheme: Scheme, problem: Problem) -> str:
    """'avflow o2', 'avflow o2 triangles'; 'avflow o2 square' where the problem has both."""
    square = len(problem.meshes) > 1 and scheme.mesh == "square"
    return scheme.label + (" square" if square else "")


def scheme_scenario(problem: Problem, scheme: Scheme, dx: float, order_field: bool,
                    film_rule: bool = False):
    from avflow.scenario.schema import load_scenario

    updates = dict(problem.updates)
    if problem.exact_model and not film_rule:
        updates.update(EXACT_MODEL)
    updates["grid.dx"] = dx
    if scheme.mesh != "square":
        updates["grid.mesh"] = scheme.mesh
    if order_field:
        updates["numerics.order"] = scheme.order
        if scheme.limiter:
            updates["numerics.limiter"] = scheme.limiter
    path = (SCENARIOS / problem.scenario if problem.scenario_file is None
            else problem.scenario_file(dx))
    return load_scenario(path).with_updates(updates)


@contextmanager
def loop_cpu_time():
    """Sums the thread's CPU seconds spent in ``Solver.advance`` (the time loop) meanwhile."""
    from avflow.numerics.solver import Solver

    original, spent = Solver.advance, [0.0]

    def advance(self, *args, **kwargs):
        t0 = time.thread_time()
        try:
            return original(self, *args, **kwargs)
        finally:
            spent[0] += time.thread_time() - t0

    Solver.advance = advance
    try:
        yield spent
    finally:
        Solver.advance = original


def timed_run(scenario, repeat: bool = True):
    """(RunResult, wall seconds, CPU seconds of the time loop): the fastest of up to 3 runs
    for short ones."""
    from avflow.simulation.runner import simulate

    walls, cpus = [], []
    result = None
    for _ in range(3):
        with loop_cpu_time() as cpu:
            run = simulate(scenario)
        result = result or run
        walls.append(run.summary["wall_time"])
        cpus.append(cpu[0] if cpu[0] > 0.0 else math.nan)
        if not repeat or walls[0] >= REPEAT_BELOW_S:
            break
    return result, min(walls), min(cpus)


def order2_notes(scheme: Scheme, scenario, summary: dict) -> dict:
    """Order 2's limiter and its counters of local fall-backs to order 1 (summary keys with
    'fallback'), for the CSV; nothing for order 1."""
    if scheme.order < 2:
        return {"limiter": None, "note": ""}
    numerics = getattr(scenario, "numerics", None)
    return {"limiter": getattr(numerics, "limiter", None),
            "note": "; ".join(f"{k} {v}" for k, v in summary.items() if "fallback" in k.lower())}


# =========================================================================================
# Driver
# =========================================================================================


def log(*args):
    print(*args, flush=True)


def measure_problem(problem: Problem, schemes: list, order_field: bool, quick: bool,
                    anuga_python: str | None, anuga_timeout: float, film_rule: bool = False,
                    fine_reference: bool = False):
    """All rows of one problem: dicts with scheme, dx, cells, steps, wall, errors, values."""
    sizes = problem.quick if quick else problem.sizes
    rows, notes, failures = [], [], []
    reference = None
    ref_dx = problem.quick_reference_dx if quick else problem.reference_dx
    if ref_dx is not None and fine_reference:
        ref_dx /= 2.0
    if problem.exact_model:
        notes.append("physics.min_flow_thickness " + ("as written (default 1 mm)" if film_rule
                     else "0: the exact solution has no film rule (--keep-film-rule: as "
                     "written)"))
    if ref_dx is not None:
        ref_scheme = max((s for s in schemes if s.mesh == "square"), key=lambda s: s.order)
        try:
            simulate_only(scheme_scenario(problem, ref_scheme, sizes[0], order_field, film_rule))
            sc = scheme_scenario(problem, ref_scheme, ref_dx, order_field, film_rule)
            r, wall, cpu = timed_run(sc, repeat=False)
            reference = problem.observe(r)
            ref_label = scheme_label(ref_scheme, problem)
            ref_text = f"{ref_label} at dx = {ref_dx:g} m"
            rows.append({"scheme": ref_label + " (reference)", "dx": ref_dx,
                         "cells": r.terrain.n_cells, "steps": r.summary["steps"], "wall": wall,
                         "cpu": cpu, "errors": {},
                         "values": {k: reference.get(k) for k in problem.values},
                         "reference": True, **order2_notes(ref_scheme, sc, r.summary)})
            notes.append(f"reference: {ref_text} ({wall:.2f} s)")
            if reference.get("edge_touched"):
                notes.append("WARNING: the reference run reached the cropped map's edge")
        except Exception as err:  # noqa: BLE001 - one failed run must not end the report
            failures.append(f"{problem.name} reference {ref_scheme.label} dx {ref_dx:g}: {err}")
            return rows, notes, failures
    for scheme in schemes:
        if scheme.mesh not in problem.meshes:
            continue
        label = scheme_label(scheme, problem)
        try:  # untimed warm-up (Numba compilation, caches) at the coarsest size
            simulate_only(scheme_scenario(problem, scheme, sizes[0], order_field, film_rule))
        except Exception as err:  # noqa: BLE001
            failures.append(f"{problem.name} {label}: {type(err).__name__}: {err}")
            continue
        for dx in sizes:
            try:
                sc = scheme_scenario(problem, scheme, dx, order_field, film_rule)
                r, wall, cpu = timed_run(sc)
                obs = problem.observe(r)
                errs = problem.errors(obs, reference)
            except Exception as err:  # noqa: BLE001
                failures.append(f"{problem.name} {label} dx {dx:g}: "
                                f"{type(err).__name__}: {err}")
                break
            if obs.get("edge_touched"):
                notes.append(f"WARNING: {label} dx {dx:g} reached the cropped map's edge")
            rows.append({"scheme": label, "dx": dx, "cells": r.terrain.n_cells,
                         "steps": r.summary["steps"], "wall": wall, "cpu": cpu, "errors": errs,
                         "values": {k: obs.get(k) for k in problem.values},
                         **order2_notes(scheme, sc, r.summary)})
            log(f"  {problem.name:22s} {label:24s} dx {dx:<8g} wall {wall:8.4f} s, "
                f"CPU {cpu:8.4f} s  "
                + "  ".join(f"{k} {v:.3g}" for k, v in errs.items()))
    if problem.anuga is not None and anuga_python:
        a_sizes = problem.anuga_quick if quick else problem.anuga_sizes
        for algorithm in ("DE0", "DE1"):
            out, why = run_anuga(anuga_python, problem.anuga, algorithm, a_sizes, anuga_timeout)
            if out is None:
                notes.append(why)
                continue
            for row in out["rows"]:
                rows.append({"scheme": f"ANUGA {out['version']} {algorithm}", "dx": row["dx"],
                             "cells": row["cells"], "steps": row["steps"], "wall": row["wall"],
                             "cpu": row.get("cpu", math.nan),
                             "errors": row["errors"], "values": {}, "note": "",
                             "anuga": True})
                log(f"  {problem.name:22s} ANUGA {algorithm:18s} dx {row['dx']:<8g} wall "
                    f"{row['wall']:8.4f} s, CPU {row.get('cpu', math.nan):8.4f} s  "
                    + "  ".join(f"{k} {v:.3g}" for k, v in row["errors"].items()))
    return rows, notes, failures


def simulate_only(scenario):
    from avflow.simulation.runner import simulate

    simulate(scenario)


def cheapest(problem: Problem, rows: list, clock: str = "wall") -> list[str]:
    """For each target, the measured run that reaches it in the least time (``clock``)."""
    lines = []
    for label, bounds in problem.targets:
        ok = [r for r in rows if not r.get("reference")
              and all(k in r["errors"] and r["errors"][k] <= b for k, b in bounds.items())]
        if ok:
            best = min(ok, key=lambda r: r[clock])
            lines.append(f"{label}: {best['scheme']} at dx = {best['dx']:g} m, "
                         f"{best[clock]:.3g} s ({clock})")
        else:
            lines.append(f"{label}: not reached by any measured run")
    return lines


def fmt(v, unit=""):
    """Errors: relative ones as 1.23e-04, absolute ones (with a unit) to 3 digits; values
    (unit "v") to 6 digits."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if unit == "v":
        return f"{v:.6g}"
    if unit:
        return f"{v:.3g}"
    return f"{v:.2e}"


def table(problem: Problem, rows: list) -> list[str]:
    head = ["scheme", "dx (m)", "cells", "steps", "wall (s)", "CPU (s)"]
    head += [m.label + (f" ({m.unit})" if m.unit else "") for m in problem.measures]
    head += [f"value: {k}" for k in problem.values]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r["scheme"], f"{r['dx']:g}", str(r["cells"]),
                 "-" if r["steps"] is None else str(r["steps"]), f"{r['wall']:.4f}",
                 f"{r['cpu']:.4f}"]
        cells += [fmt(r["errors"].get(m.key), m.unit) for m in problem.measures]
        cells += [fmt(r["values"].get(k), "v") for k in problem.values]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def write_csv(path: Path, problem: Problem, rows: list, reference: str) -> None:
    keys = [m.key for m in problem.measures]
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["problem", "scheme", "dx_m", "cells", "steps", "wall_s", "cpu_s"]
                   + [f"error_{k}" for k in keys] + problem.values
                   + ["limiter", "reference", "note"])
        for r in rows:
            w.writerow([problem.name, r["scheme"], r["dx"], r["cells"],
                        "" if r["steps"] is None else r["steps"], f"{r['wall']:.6g}",
                        f"{r['cpu']:.6g}"]
                       + [("" if r["errors"].get(k) is None else f"{r['errors'][k]:.6g}")
                          for k in keys]
                       + [("" if r["values"].get(k) is None else f"{r['values'][k]:.6g}")
                          for k in problem.values]
                       + [r.get("limiter") or "", reference, r.get("note", "")])


def plot(path: Path, problem: Problem, rows: list, reference: str, clock: str = "wall") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(problem.measures)
    ncol = 2 if n > 1 else 1
    nrow = math.ceil(n / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(6.2 * ncol, 4.4 * nrow), squeeze=False)
    schemes = list(dict.fromkeys(r["scheme"] for r in rows if not r.get("reference")))
    for ax, m in zip(axes.flat, problem.measures):
        for s in schemes:
            pts = sorted(((r[clock], r["errors"].get(m.key), r["dx"]) for r in rows
                          if r["scheme"] == s and r["errors"].get(m.key) is not None),
                         key=lambda p: -p[2])
            pts = [p for p in pts if p[1] > 0 and p[0] > 0]  # NaN fails both
            if not pts:
                continue
            style = "s--" if "ANUGA" in s else ("o-" if "square" in s or "tri" not in s else "^-")
            line, = ax.loglog([p[0] for p in pts], [p[1] for p in pts], style, label=s)
            for wall, err, dx in pts:
                ax.annotate(f"{dx:g}", (wall, err), textcoords="offset points", xytext=(4, 3),
                            fontsize=7, color=line.get_color())
        bounds = sorted({b[m.key] for _, b in problem.targets if m.key in b})
        for b in bounds:
            ax.axhline(b, color="0.6", lw=0.8, ls=":")
        ax.set_xlabel(f"{'wall' if clock == 'wall' else 'CPU'} time of the time loop "
                      "(s, one core)")
        ax.set_ylabel(m.label + (f" ({m.unit}, absolute)" if m.unit else " (relative)"))
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    title = problem.title + (f"\nreference: {reference}" if reference else "")
    fig.suptitle(title + "   (labels: dx in m; dotted: targets)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "out" / "speed_vs_error"))
    ap.add_argument("--quick", action="store_true", help="2-3 cell sizes per problem")
    ap.add_argument("--problems", default="all",
                    help="comma-separated: " + ", ".join(list(problems()) + list(GROUPS))
                    + " or all")
    ap.add_argument("--orders", default="1,2", help="avflow orders to measure (2 only where "
                    "this avflow has numerics.order)")
    ap.add_argument("--limiter", default=None, help="numerics.limiter for order 2 "
                    "(default: avflow's default)")
    ap.add_argument("--anuga-python", default=None,
                    help="a Python that can import anuga (default: this one, if it can)")
    ap.add_argument("--no-anuga", action="store_true", help="do not look for ANUGA")
    ap.add_argument("--keep-film-rule", action="store_true",
                    help="problems with an exact solution: keep physics.min_flow_thickness as "
                    "written (default: 0, the equations of the exact solution)")
    ap.add_argument("--fine-reference", action="store_true",
                    help="references at half the cell size (section 6: 0.39 m, the 2D case: "
                    "1.25 m; several minutes more)")
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                    help="time on the plots and for the cheapest run: the summary wall_time "
                    "(default) or the CPU time of the time loop (steadier on a busy machine)")
    ap.add_argument("--anuga-timeout", type=float, default=300.0,
                    help="seconds per ANUGA algorithm and problem")
    return ap.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    catalogue = problems()
    names = []
    for item in args.problems.split(","):
        item = item.strip()
        if item == "all":
            names += list(catalogue)
        elif item in GROUPS:
            names += GROUPS[item]
        elif item in catalogue:
            names.append(item)
        else:
            print(f"speed_vs_error: unknown problem {item!r}", file=sys.stderr)
            return 2
    names = list(dict.fromkeys(names))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    header = []
    has_order, why = order_support()
    orders = sorted({int(o) for o in args.orders.split(",")})
    if 2 in orders and not has_order:
        orders.remove(2)
        header.append(f"order 2: not available in this avflow ({why}); order 1 only")
    elif has_order:
        header.append(f"order 2: available (numerics.order); orders measured: {orders}")
    schemes = []
    for mesh in ("square", "triangles"):
        for o in orders:
            label = f"avflow o{o}" + ("" if mesh == "square" else " triangles")
            schemes.append(Scheme(label, o, mesh, args.limiter if o == 2 else None))

    anuga_python = None
    if not args.no_anuga:
        candidate = args.anuga_python or sys.executable
        ok, what = anuga_importable(candidate)
        if ok:
            anuga_python = candidate
            header.append(f"ANUGA {what} ({candidate}): measured on the dam breaks and "
                          "avalanche_dry, DE0 and DE1, one OpenMP thread")
        else:
            header.append(f"ANUGA: not importable by {candidate} ({what}); its rows are "
                          "skipped (give --anuga-python)")
    else:
        header.append("ANUGA: not looked for (--no-anuga)")
    header.append("PyClaw: not measured (no Fortran build here)")
    header.append(f"machine: {os.cpu_count()} cores, load average at the start "
                  f"{os.getloadavg()[0]:.1f} (wall times grow with other work on the machine)")
    for line in header:
        log(line)

    report = ["# Speed against error", "", f"`python workflows/speed_vs_error.py "
              f"{' '.join(argv if argv is not None else sys.argv[1:])}`", ""]
    report += [f"- {line}" for line in header] + [""]
    all_failures = []
    started = time.perf_counter()
    for name in names:
        problem = catalogue[name]
        log(f"{name}: {problem.title}")
        rows, notes, failures = measure_problem(problem, schemes, has_order, args.quick,
                                                anuga_python, args.anuga_timeout,
                                                args.keep_film_rule, args.fine_reference)
        all_failures += failures
        reference = next((n[len("reference: "):] for n in notes if n.startswith("reference: ")),
                         "")
        if rows:
            write_csv(out / f"{name}.csv", problem, rows, reference)
            plot(out / f"{name}.png", problem, rows, reference, args.clock)
        lines = table(problem, rows)
        targets = cheapest(problem, rows, args.clock)
        block = [f"## {name}: {problem.title}", ""]
        block += [f"- {n}" for n in notes + ([problem.note] if problem.note else [])]
        block += [f"- FAILED: {f}" for f in failures]
        block += [""] + lines + ["", "Cheapest measured run reaching each target:", ""]
        block += [f"- {t}" for t in targets] + [""]
        report += block
        log("\n".join(block))
    report.append(f"Total {time.perf_counter() - started:.0f} s; load average at the end "
                  f"{os.getloadavg()[0]:.1f}.")
    (out / "report.md").write_text("\n".join(report) + "\n")
    log(f"written: {out}/<problem>.csv, .png, report.md ({time.perf_counter() - started:.0f} s)")
    if all_failures:
        log("FAILED runs:\n  " + "\n  ".join(all_failures))
        return 1
    return 0


if __name__ == "__main__":
    if len(sys.argv) >= 3 and sys.argv[1] == "--anuga-worker":
        print(json.dumps(anuga_worker(json.loads(sys.argv[2]))))
        sys.exit(0)
    sys.exit(main())
