"""Mobility against volume: H/L of releases from 1e5 to 1e10 m^3 under Coulomb and under
velocity-weakening friction (Lucas, Mangeney and Ampuero 2014), over Scheidegger's line.

    python workflows/volume_mobility.py [-o OUTDIR] [--cells N] [--volumes 1e5,1e6,...]
        [--topography plane|hockey|exponential|exponential-similar] [--weakening MS,MW,UW]

Writes OUTDIR/volume_mobility.csv (one row per member: law, volume, H, L, H/L, dL, H/dL,
peak speed, steps, wall time) and OUTDIR/volume_mobility.png (H/L and H/dL against V,
log-log, both laws, with Scheidegger's (1973) fit ``log10(H/L) = -0.15666 log10(V) +
0.62419``), and prints the log-log slopes of H/L and of H/dL against V over 1e6-1e10 m^3
for each law (dL: the front's travel, below).

The scene is scenarios/ensembles/volume_mobility.yaml: one topography, a plane of 2 degrees
(a plane has no length scale, so it is the same topography at every volume), and a
cylinder of material as tall as it is wide (thickness = radius, normal to the bed) that
collapses and spreads on it. Each member's grid and window onto the plane scale with its
radius (``--cells`` cells per radius, 8 by default), so every volume costs the same. Under
Coulomb the depth-averaged equations have no length scale either: every volume is the
same flow, magnified, and H/L does not depend on V at all (measured: the slope is 0 to
round-off). The law's weakening speed ``U_w`` is the only scale: a larger mass falls its
own larger height, flows faster (sqrt(g h0)), and sees less friction. ``docs/guide/
volume-mobility.md`` says what this shows and where it stops being credible.

``--topography hockey`` runs the same laws on the issue's other scene, fixed at every
volume: a 40 degree slope 5 km high onto flat ground (:data:`HOCKEY`; DEMs written to
OUTDIR/dem; at 4 cells per radius it takes about 1 min per law, most of it the 1e5 m^3
member's 650,000 cells). ``exponential`` is the seed's exponential slope (section 6)
extruded to 2D with a cylindrical release at its top, fixed at every volume;
``exponential-similar`` magnifies that slope with the release, so that a larger mass
also falls from higher (:data:`EXPONENTIAL`). ``--weakening`` replaces the ensemble's
velocity-weakening parameters.

H and L follow the Fahrboschung: H is the drop from the highest point of the released mass
(the top of its upslope rim) to the farthest point of the deposit (downslope, where the
deposit is thicker than 1e-3 of the release), L the horizontal distance between them; dL
is the horizontal distance from the release's downslope rim to that tip. The
mass is symmetric about the plane's fall line: only the half y >= 0 is computed, with a
wall (a mirror) on y = 0, and volumes are those of the whole cylinder.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
ENSEMBLE = REPO / "scenarios" / "ensembles" / "volume_mobility.yaml"
VOLUMES = (1e5, 1e6, 1e7, 1e8, 1e9, 1e10)
#: Scheidegger (1973): log10(H/L) = A log10(V) + B, V in m^3
SCHEIDEGGER = (-0.15666, 0.62419)
FIT_RANGE = (1e6, 1e10)  # m^3: the volumes of the slope target
TIP_FRACTION = 1e-3  # deposit tip: the farthest cell thicker than this fraction of h0
BASE_CELLS = 8  # cells per radius in scenarios/volume_mobility_plane.yaml


def law_members():
    """The members of scenarios/ensembles/volume_mobility.yaml: one scenario per law."""
    from avflow.ensemble.spec import load_ensemble

    return [m.scenario for m in load_ensemble(ENSEMBLE).members]


def cylinder_volume(scenario) -> float:
    """m^3 of the whole cylinder (the run computes its half y >= 0)."""
    return math.pi * scenario.release.radius ** 2 * scenario.release.thickness


def magnified(scenario, volume: float, cells: int = BASE_CELLS):
    """The scene magnified to a cylinder of ``volume`` m^3: every length times k =
    (volume / base volume)^(1/3), times and speeds times sqrt(k) (the same flow under
    Coulomb), and ``cells`` cells per radius."""
    k = (volume / cylinder_volume(scenario)) ** (1.0 / 3.0)
    ter, rel = scenario.terrain, scenario.release
    ext = ter.extent
    return scenario.with_updates({
        "name": f"{scenario.name}-{scenario.rheology.law}-{volume:.0e}",
        "terrain.extent": {"x": [k * ext.x[0], k * ext.x[1]], "y": [k * ext.y[0], k * ext.y[1]]},
        "terrain.elevation_at_center": k * ter.elevation_at_center,
        "grid.dx": k * rel.radius / cells,
        "release.center": [k * rel.center[0], k * rel.center[1]],
        "release.radius": k * rel.radius,
        "release.thickness": k * rel.thickness,
        "time.end": math.sqrt(k) * scenario.time.end,
        "output.every": math.sqrt(k) * scenario.output.every,
        "physics.min_flow_thickness": k * scenario.physics.min_flow_thickness,
    })


#: The issue's other topography, fixed at every volume: a 40 degree slope 5 km high onto
#: flat ground (Valles Marineris' scale: it holds the 1e10 m^3 release), releases a quarter
#: as thick as wide with their crown at the top. Not similar across volumes: the window is
#: fixed (45 km of flat ground), the cells 1/cells of the radius, the DEM written per
#: member. The laws are the ensemble's; curvature off (the kink is one cell of the DEM).
HOCKEY = {"slope_deg": 40.0, "drop": 5000.0, "aspect": 0.25, "flat": 45000.0}

#: The seed's exponential slope (section 6, eq. 58: theta = theta0 exp(-s / a), s along the
#: bed; scenarios/seed_exponential_*.yaml) extruded across y, continued to 30 km (the
#: slope is below 0.1 degree from s = 11 km), 1.05 km high (a Si(theta0)) below s = 0 and
#: a plane at theta0 above (where the collapse spreads back). The release is a cylinder as
#: thick as half its radius (the seed's parabola: 201.6 m over a half length of 400 m),
#: crown at s = 0. The seed's own mass made round is 1.0e8 m^3 (radius 400 m).
#: "exponential" keeps the slope fixed at every volume; "exponential-similar" magnifies it
#: with the release (a = 1750 m at 1e8 m^3): the same scene at every volume under Coulomb,
#: as the plane.
EXPONENTIAL = {"theta0_deg": 35.0, "a": 1750.0, "aspect": 0.5, "length": 30000.0,
               "base_radius": 400.0}


def hockey_bed(x):
    """Bed elevation (m) of the plane-to-flat topography at x (m): the slope ends at x_t."""
    t = math.tan(math.radians(HOCKEY["slope_deg"]))
    return np.where(np.asarray(x) < HOCKEY["drop"] / t, HOCKEY["drop"] - t * np.asarray(x), 0.0)


def exponential_bed(scale: float = 1.0):
    """The seed's exponential slope times ``scale`` as a function of horizontal x (m; x = 0
    where s = 0 and theta = theta0): elevation 0 at its far end."""
    e = EXPONENTIAL
    theta0, a = math.radians(e["theta0_deg"]), e["a"] * scale
    s = np.linspace(-0.5 * a, e["length"] * scale, 200_001)  # 15 cm steps at scale 1
    theta = theta0 * np.exp(-np.maximum(s, 0.0) / a)  # above s = 0: a plane at theta0
    ds = s[1] - s[0]
    x = np.concatenate([[0.0], np.cumsum(0.5 * (np.cos(theta[1:]) + np.cos(theta[:-1])) * ds)])
    z = -np.concatenate([[0.0], np.cumsum(0.5 * (np.sin(theta[1:]) + np.sin(theta[:-1])) * ds)])
    x -= np.interp(0.0, s, x)
    z -= z[-1]
    return lambda xq: np.interp(np.asarray(xq, dtype=float), x, z)


def fixed_member(scenario, volume: float, cells: int, folder: Path, topography: str):
    """The ensemble member's law on a DEM topography (``hockey``, ``exponential`` or
    ``exponential-similar``), its DEM written to ``folder`` at the member's cell size.
    Returns the scenario, the bed function and the slope under the release's crown."""
    from avflow.scenario.schema import parse_scenario

    if topography == "hockey":
        a, bed, crown_slope = HOCKEY["aspect"], hockey_bed, HOCKEY["slope_deg"]
        radius = (volume / (math.pi * a)) ** (1.0 / 3.0)
        x_toe = HOCKEY["drop"] / math.tan(math.radians(HOCKEY["slope_deg"]))
        x0, x1 = -200.0, x_toe + HOCKEY["flat"]
        center = 200.0 + 1.05 * radius
        width = min(max(40.0 * radius, 1500.0), 15000.0)  # half width (m): the flow's sides
        t_end = 3000.0
    else:
        a, crown_slope = EXPONENTIAL["aspect"], EXPONENTIAL["theta0_deg"]
        radius = (volume / (math.pi * a)) ** (1.0 / 3.0)
        k = radius / EXPONENTIAL["base_radius"] if topography == "exponential-similar" else 1.0
        bed = exponential_bed(k)
        x0, x1 = -2.0 * radius, EXPONENTIAL["length"] * k  # the collapse spreads upslope
        center = radius  # crown at s = 0, where the slope is theta0
        width = min(max(30.0 * radius, 1500.0 * k), 15000.0 * k)
        t_end = 1500.0 * math.sqrt(k)
    dx = radius / cells
    x = x0 + dx * np.arange(int((x1 - x0) / dx) + 1)
    y = dx * np.arange(int(width / dx) + 1)
    folder.mkdir(parents=True, exist_ok=True)
    dem = folder / f"{topography}_{volume:.0e}_{cells}.asc"
    with open(dem, "w") as f:  # ESRI ASCII: rows from north to south
        f.write(f"ncols {x.size}\nnrows {y.size}\nxllcorner {x[0] - dx / 2}\n"
                f"yllcorner {y[0] - dx / 2}\ncellsize {dx}\nNODATA_value -9999\n")
        np.savetxt(f, np.repeat(bed(x)[None, :], y.size, axis=0), fmt="%.3f")
    h0 = a * radius
    doc = {"name": f"{topography}-{scenario.rheology.law}-{volume:.0e}",
           "terrain": {"kind": "dem", "path": str(dem), "curvature": False},
           "grid": {"dx": dx},
           "release": {"kind": "cylinder", "center": [center, 0.0],
                       "radius": radius, "thickness": h0},
           "rheology": scenario.rheology.model_dump(exclude_none=True),
           "time": {"end": t_end, "cfl": 0.5}, "output": {"every": t_end / 60.0},
           "boundary": {"x_min": "outflow", "x_max": "outflow", "y_min": "wall",
                        "y_max": "outflow"},
           "physics": {"min_flow_thickness": 1e-4 * h0}}
    return parse_scenario(yaml.safe_dump(doc, sort_keys=False)), bed, crown_slope


def fahrboschung(result, bed=None, crown_slope_deg=None) -> tuple[float, float, float]:
    """(H, L, dL) in m of a finished run (module docstring): dL is the horizontal distance
    from the release's downslope rim to the deposit's tip (the front's travel), L the one
    from its upslope rim. ``bed(x)``: the bed's elevation (default: the plane of the scene,
    falling by tan(theta) per m along +x); ``crown_slope_deg``: the slope under the crown."""
    sc = result.scenario
    h0, radius = sc.release.thickness, sc.release.radius
    xx, _ = result.terrain.cell_xy()
    deposit = result.state.h > TIP_FRACTION * h0
    x_tip = float(xx[deposit].max())
    x_crown = sc.release.center[0] - radius  # the upslope rim of the cylinder
    d_front = x_tip - (sc.release.center[0] + radius)
    if bed is None:
        theta = math.radians(sc.terrain.slope_deg)
        return ((x_tip - x_crown) * math.tan(theta) + h0 / math.cos(theta), x_tip - x_crown,
                d_front)
    # the crown is h0 / cos(theta) above the bed, theta the slope under it
    theta = math.radians(crown_slope_deg)
    drop = float(bed(x_crown)) + h0 / math.cos(theta) - float(bed(x_tip))
    return drop, x_tip - x_crown, d_front


#: the order the study's figures were measured with (docs/guide/volume-mobility.md): the
#: seed's scheme, the default on every terrain then
STUDY_ORDER = 1


def run_member(scenario, volume: float, cells: int = BASE_CELLS, topography: str = "plane",
               folder: Path | None = None) -> dict:
    """One law at one volume: the Fahrboschung and what the run cost."""
    from avflow.simulation.runner import simulate

    if topography == "plane":
        member, bed, crown_slope = magnified(scenario, volume, cells), None, None
    else:
        member, bed, crown_slope = fixed_member(scenario, volume, cells, folder or Path("."),
                                                topography)
    member = member.with_updates({"numerics.order": STUDY_ORDER})
    started = time.perf_counter()
    result = simulate(member)
    elapsed = time.perf_counter() - started
    H, L, dL = fahrboschung(result, bed, crown_slope)
    v0 = result.solver.volume(result.solver.new_state(result.h0))
    return {"law": member.rheology.law, "volume_m3": volume, "H_m": H, "L_m": L,
            "H_over_L": H / L, "dL_m": dL, "H_over_dL": H / dL,
            "radius_m": member.release.radius,
            "thickness_m": member.release.thickness, "dx_m": member.grid.dx,
            "status": result.status,
            "peak_speed_m_s": float(np.max(result.state.peak_speed)),
            "steps": result.state.steps, "wall_s": round(elapsed, 3),
            # what left the window (must be 0: the window holds the deposit)
            "volume_lost": 1.0 - result.solver.volume(result.state) / v0,
            "parameters": " ".join(f"{k} {v:g}" for k, v in
                                   member.rheology.model_dump(exclude_none=True).items()
                                   if k != "law" and isinstance(v, float))}


def slope(rows: list[dict], law: str, lo: float = FIT_RANGE[0], hi: float = FIT_RANGE[1],
          measure: str = "H_over_L") -> float:
    """Least-squares slope of log10(measure) against log10(V) over [lo, hi] m^3
    (``measure``: "H_over_L", or "H_over_dL" with the front's travel dL)."""
    pts = [(math.log10(r["volume_m3"]), math.log10(r[measure])) for r in rows
           if r["law"] == law and lo * 0.999 <= r["volume_m3"] <= hi * 1.001]
    x, y = np.array(pts).T
    return float(np.polyfit(x, y, 1)[0])


def scheidegger(volume):
    return 10.0 ** (SCHEIDEGGER[0] * np.log10(volume) + SCHEIDEGGER[1])


TITLES = {"plane": "2 degree plane, magnified with the release",
          "hockey": "40 degree slope 5 km high onto flat",
          "exponential": "seed's exponential slope, fixed",
          "exponential-similar": "seed's exponential slope, magnified"}


def plot(rows: list[dict], path: Path, slopes: dict, topography: str = "plane",
         slopes_front: dict | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 6.0))
    v = np.logspace(4.5, 10.5, 50)
    ax.loglog(v, scheidegger(v), "k--", lw=1, label="Scheidegger (1973)")
    for law, colour, marker in zip(dict.fromkeys(r["law"] for r in rows), ("C0", "C1", "C2"),
                                   "os^"):
        sel = [r for r in rows if r["law"] == law]
        vol = [r["volume_m3"] for r in sel]
        ax.loglog(vol, [r["H_over_L"] for r in sel], "-", marker=marker, color=colour,
                  label=f"{law} ({sel[0]['parameters']}), H/L "
                        f"(slope {round(slopes[law], 3) + 0.0:+.3f})")
        if slopes_front is not None:  # open markers: H over the front's travel dL
            ax.loglog(vol, [r["H_over_dL"] for r in sel], ":", marker=marker, color=colour,
                      mfc="none", label=f"{law}, H/$\\Delta$L "
                                        f"(slope {round(slopes_front[law], 3) + 0.0:+.3f})")
    ax.set_xlabel("volume V (m$^3$)")
    ax.set_ylabel("H / L,  H / $\\Delta$L")
    ax.set_title("Mobility against volume: " + TITLES[topography], fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7.5, loc="upper center", bbox_to_anchor=(0.5, -0.14))  # off the data
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default="volume_mobility",
                        help="output folder (default: ./volume_mobility)")
    parser.add_argument("--cells", type=int, default=8, help="cells per release radius")
    parser.add_argument("--volumes", help="comma-separated volumes (m^3); default 1e5-1e10")
    parser.add_argument("--topography", choices=tuple(TITLES), default="plane",
                        help="plane: the ensemble's scene magnified (default); hockey: a "
                             "fixed 40 degree slope 5 km high onto flat ground; "
                             "exponential: the seed's exponential slope extruded, fixed; "
                             "exponential-similar: the same, magnified with the release")
    parser.add_argument("--weakening", metavar="MU_S,MU_W,U_W",
                        help="the velocity-weakening member's mu_s, mu_w, U_w (m/s) instead "
                             "of the ensemble's 0.7,0.1,5")
    args = parser.parse_args(argv)
    members = law_members()
    if args.weakening:
        try:
            mu_s, mu_w, u_w = (float(v) for v in args.weakening.split(","))
        except ValueError:
            print(f"volume_mobility: --weakening must be three numbers MU_S,MU_W,U_W, got "
                  f"{args.weakening!r}", file=sys.stderr)
            return 2
        if not (mu_s >= mu_w >= 0.0 and u_w > 0.0):
            print(f"volume_mobility: --weakening needs mu_s >= mu_w >= 0 and U_w > 0, got "
                  f"{args.weakening!r}", file=sys.stderr)
            return 2
        from avflow.errors import ScenarioError

        try:
            members = [m.with_updates({"rheology.mu_s": mu_s, "rheology.mu_w": mu_w,
                                       "rheology.U_w": u_w})
                       if m.rheology.law == "velocity_weakening" else m for m in members]
        except ScenarioError as err:
            print(f"volume_mobility: --weakening: {err}", file=sys.stderr)
            return 2
    if args.cells < 2:
        print("volume_mobility: --cells must be at least 2", file=sys.stderr)
        return 2
    try:
        volumes = (tuple(float(v) for v in args.volumes.split(",")) if args.volumes
                   else VOLUMES)
    except ValueError:
        print(f"volume_mobility: --volumes must be numbers, got {args.volumes!r}",
              file=sys.stderr)
        return 2
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for scenario in members:
        for volume in volumes:
            row = run_member(scenario, volume, args.cells, args.topography, out / "dem")
            rows.append(row)
            print(f"{row['law']:>20} V {volume:8.0e} m3  H/L {row['H_over_L']:.4f}  "
                  f"H/dL {row['H_over_dL']:.4f}  "
                  f"peak speed {row['peak_speed_m_s']:6.1f} m/s  {row['steps']:5d} steps  "
                  f"{row['wall_s']:6.1f} s  {row['status']}", flush=True)
            if row["volume_lost"] > 1e-9:
                print(f"volume_mobility: {row['volume_lost']:.1e} of the volume left the "
                      "window (plane: widen terrain.extent in the base scenario; others: "
                      "fixed_member's window)", file=sys.stderr)
    with open(out / "volume_mobility.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    laws = list(dict.fromkeys(r["law"] for r in rows))
    fits = [v for v in volumes if FIT_RANGE[0] * 0.999 <= v <= FIT_RANGE[1] * 1.001]
    slopes = {law: slope(rows, law) if len(fits) >= 2 else math.nan for law in laws}
    front = {law: slope(rows, law, measure="H_over_dL") if len(fits) >= 2 else math.nan
             for law in laws}
    plot(rows, out / "volume_mobility.png", slopes, args.topography, front)
    print(f"log-log slope against V over {FIT_RANGE[0]:.0e}-{FIT_RANGE[1]:.0e} m3 "
          f"(Scheidegger {SCHEIDEGGER[0]:+.3f}), of H/L and of H/dL (dL: the front's travel):")
    for law in laws:
        print(f"  {law}: {slopes[law]:+.4f}   H/dL {front[law]:+.4f}")
    print(f"wrote {out / 'volume_mobility.csv'} and {out / 'volume_mobility.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
