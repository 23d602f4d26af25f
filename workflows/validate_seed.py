"""Run the seed's cases and print the seed's figure beside avflow's, with speed.

    python workflows/validate_seed.py

Dam breaks (section 4): error dh of eq. 57 at dx = 20 m and 2 m. Section 5: Pouliquen's
deposit on the plane against h_stop. Section 6: stop time, deposit maximum, front, extents.
Wall time and cell-updates per second are those of the time loop, one core.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from avflow.numerics.analytic import dam_break, relative_error
from avflow.numerics.rheology import h_stop
from avflow.simulation.runner import simulate
from avflow.scenario.schema import load_scenario

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
ROWS = []


def run(name):
    r = simulate(load_scenario(SCENARIOS / f"{name}.yaml"))
    return r, r.summary


def row(case, quantity, seed, ours, s):
    ROWS.append((case, quantity, seed, ours, s["wall_time"], s["cell_updates_per_second"]))


def main() -> int:
    for delta in (0, 1, 4):
        errs = []
        for dx in (20, 2):
            r, s = run(f"seed_dambreak_inclined_delta{delta}_dx{dx}")
            ha, _ = dam_break(r.terrain.x, r.state.t, theta_deg=5.0, delta_deg=delta)
            errs.append(relative_error(r.state.h, ha))
            row(f"dam break 5 deg, delta {delta}, dx {dx}", "dh (eq. 57) at 35 s", "Fig. 8",
                f"{errs[-1]:.2e}", s)
        ROWS.append((f"dam break 5 deg, delta {delta}", "dh(20 m) / dh(2 m)", "about 4",
                     f"{errs[0] / errs[1]:.1f}", np.nan, np.nan))
    for dx in (20, 2):
        r, s = run(f"seed_dambreak_flat_dx{dx}")
        ha, _ = dam_break(r.terrain.x, r.state.t)
        row(f"Ritter dx {dx}", "dh at 137 s", "Fig. 8", f"{relative_error(r.state.h, ha):.2e}", s)
    r, s = run("pouliquen_plane")
    h = r.state.h[len(r.state.h) // 4: 3 * len(r.state.h) // 4]
    row("Pouliquen plane 25 deg", "deposit / h_stop", "1 (Fig. 9b)",
        f"{h.mean() / h_stop(25.0, 20.7, 32.8, 0.98e-3):.3f}", s)
    c = {d: run(f"seed_exponential_coulomb{d}")[1] for d in (14, 15, 16, 20, 24)}
    nocurv = run("seed_exponential_coulomb15_nocurv")[1]
    s15 = c[15]
    row("Coulomb 15", "stops at (s)", "86", f"{s15['time_to_stop']:.2f}", s15)
    row("Coulomb 15", "deposit max (m)", "68", f"{s15['deposit_max_thickness']:.2f}", s15)
    row("Coulomb 15", "front (m)", "near 4500", f"{s15['runout']:.1f}", s15)
    row("Coulomb 15, no curvature", "stops at (s)", "86.4", f"{nocurv['time_to_stop']:.2f}",
        nocurv)
    row("Coulomb 15, no curvature", "deposit max (m)", "67.8",
        f"{nocurv['deposit_max_thickness']:.2f}", nocurv)
    row("Coulomb 15", "front without - with curvature (m)", "156",
        f"{nocurv['runout'] - s15['runout']:.1f}", nocurv)
    row("Coulomb 14", "deposit length / max (m)", "2900 / 65",
        f"{c[14]['deposit_length']:.0f} / {c[14]['deposit_max_thickness']:.1f}", c[14])
    row("Coulomb 20", "deposit length / max (m)", "2290 / 75",
        f"{c[20]['deposit_length']:.0f} / {c[20]['deposit_max_thickness']:.1f}", c[20])
    row("Coulomb 14 vs 16", "fronts apart (m)", "about 740",
        f"{c[14]['runout'] - c[16]['runout']:.1f}", c[16])
    row("Coulomb 16 vs 20", "fronts apart (m)", "about 1060",
        f"{c[16]['runout'] - c[20]['runout']:.1f}", c[20])
    row("Coulomb 24", "stops at (s)", "front stopped by 70 s", f"{c[24]['time_to_stop']:.2f}",
        c[24])
    for d in ("1.0", "1.5", "2.0"):
        _, s = run(f"seed_exponential_pouliquen_d{d}")
        seed = "97.6 / near 4500" if d == "1.5" else "-"
        row(f"Pouliquen 13/20, d = {d}", "stops at (s) / front (m)", seed,
            f"{s['time_to_stop']:.2f} / {s['runout']:.0f}", s)

    header = ("case", "quantity", "seed", "avflow", "wall (s)", "cell-upd/s")
    widths = [max(len(str(x)) for x in col) for col in zip(header, *[r[:4] for r in ROWS])]
    print("  ".join(h.ljust(w) for h, w in zip(header[:4], widths)) + "  wall (s)  cell-upd/s")
    for case, quantity, seed, ours, wall, rate in ROWS:
        speed = "" if np.isnan(wall) else f"{wall:8.3f}  {rate:10.3g}"
        print("  ".join(str(v).ljust(w) for v, w in zip((case, quantity, seed, ours), widths))
              + "  " + speed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
