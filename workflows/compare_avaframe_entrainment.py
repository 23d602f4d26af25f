"""avflow's erosion-energy entrainment beside AvaFrame com1DFA's, on AvaFrame's avaAlr.

    python workflows/compare_avaframe_entrainment.py --avaframe-python /work/avaframe_venv/bin/python

AvaFrame's own test path with an entrainment area: avaAlr (its DEM, release and ENT
polygon ``entAlr.shp``, 0.3 m, from ``data/avaframe/avaAlr``: AvaFrame's
``avaframe/data/avaAlr/Inputs``; ``--ent`` for another). The same parameters on both sides:
samosAT with AvaFrame's standard parameters, snow 200 kg/m^3, entrained snow
``rhoEnt`` = 100 kg/m^3 (AvaFrame's default), erosion energy ``e_b`` = 5000 J/kg
(``entEroEnergy``), cells of 5 m, tEnd 400 s. AvaFrame runs as in
``compare_avaframe.py`` (its defaults otherwise: SPH, dt 0.1 s, stop at 1% of the peak
kinetic energy); avflow runs the scenario ``scenarios/avaalr_samosat.yaml`` with an
``entrainment:`` block of the same law and layer, to the time AvaFrame stopped.

Prints and writes (``--out``, default ``out/compare_avaframe_entrainment``) the entrained
volume over time on both sides (m^3 of flowing snow at 200 kg/m^3: AvaFrame's mass log
over rho), the volume of the layer each eroded, the footprints (peak thickness > 0.1 m
and > 0.01 m, intersection over union on avflow's cells) and a figure
``entrainment_avaAlr.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

import compare_avaframe as ca  # noqa: E402

RHO_ENT = 100.0  # kg/m^3, AvaFrame's rhoEnt
E_B = 5000.0  # J/kg, AvaFrame's entEroEnergy
TIMES = (10, 25, 45, 65, 85, 105, 145, 185)


def avflow_run(scenario, ent_path, t_end):
    """avflow with AvaFrame's erosion energy over the ENT polygon's thickness, the
    scenario's ``entrainment:`` block, to ``t_end``: the series ``(t, entrained)`` at the
    snapshots (every 5 s), the peak thickness, the layer at the start, the cells'
    centres (and the grid's x, y) and areas, and the balance's terms."""
    from avflow.output.dataset import to_dataset
    from avflow.simulation.runner import simulate

    run = scenario.with_updates({
        "entrainment": {"law": "erosion_energy", "e_b": E_B, "density": RHO_ENT,
                        "layer": {"polygon": str(ent_path)}},
        "time.end": float(t_end), "output.every": 5.0, "numerics.threads": 1})
    simulate(run.with_updates({"time.end": 1.0, "output.every": 1.0}))  # compile first
    result = simulate(run)
    ds = to_dataset(result)
    s = result.summary
    xx, yy = np.meshgrid(ds["x"].values, ds["y"].values)
    dx = abs(float(ds["x"][1] - ds["x"][0])) * abs(float(ds["y"][1] - ds["y"][0]))
    peak = np.nan_to_num(ds["peak_thickness"].values)
    left = np.nan_to_num(ds["erodible_depth"].values)
    layer = left - np.nan_to_num(ds["bed_change"].values)
    # the bed's area per map cell (the layer is a depth normal to the bed: its volume is
    # what entrained_volume counts)
    area = dx / np.cos(np.radians(np.nan_to_num(ds["slope_angle"].values)))
    series = np.stack([ds["time"].values, ds["entrained_volume_series"].values], axis=1)
    return {"series": series, "peak_h": peak.ravel(), "layer": layer.ravel(),
            "x": xx.ravel(), "y": yy.ravel(), "xs": ds["x"].values, "ys": ds["y"].values,
            "area": area.ravel(),
            "wall_s": float(s["wall_time"]), "released": float(s["release_volume"]),
            "on_map": float(s["deposit_volume"]), "outflow": float(s["outflow_volume"]),
            "entrained": float(ds["entrained_volume"])}


def figure(png, af_t, af_v, fl, af_on_fl, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 7), gridspec_kw={"width_ratios": [1.6, 1]})
    a.plot(af_t, af_v, label="AvaFrame com1DFA (mass log / rho)")
    a.plot(fl["series"][:, 0], fl["series"][:, 1], label="avflow (the layer's books)")
    a.set_xlabel("time (s)")
    a.set_ylabel("entrained volume (m$^3$ of flowing snow)")
    a.legend()
    a.grid(alpha=0.3)
    x, y = fl["x"], fl["y"]
    f_af, f_fl = af_on_fl > 0.1, fl["peak_h"] > 0.1
    ent = fl["layer"] > 0
    b.scatter(x[ent], y[ent], s=1, c="0.85", label="entrainment area")
    b.scatter(x[f_af & ~f_fl], y[f_af & ~f_fl], s=1, c="tab:blue", label="AvaFrame only")
    b.scatter(x[f_fl & ~f_af], y[f_fl & ~f_af], s=1, c="tab:orange", label="avflow only")
    b.scatter(x[f_af & f_fl], y[f_af & f_fl], s=1, c="tab:green", label="both")
    b.set_aspect("equal")
    b.set_title("peak thickness > 0.1 m")
    b.legend(markerscale=8, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8)
    b.tick_params(labelsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ent", default=str(ROOT / "data" / "avaframe" / "avaAlr" / "entAlr.shp"),
                    help="AvaFrame's avaAlr ENT shapefile (default: the copy in data/)")
    ap.add_argument("--avaframe-python", default=None)
    ap.add_argument("--avaframe-results", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--dx", type=float, default=5.0)
    ap.add_argument("--out", default="out/compare_avaframe_entrainment")
    args = ap.parse_args(argv)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    from avflow.scenario import load_scenario

    base = load_scenario(ROOT / "scenarios" / "avaalr_samosat.yaml")
    scenario = base.with_updates({"grid.dx": args.dx, "physics.density": ca.RHO,
                                  "time.end": ca.T_END})
    how, where, note = ca.avaframe_runner(args)
    if how in (None, "stored"):
        raise SystemExit(f"compare_avaframe_entrainment: {note}: AvaFrame must run here")
    print(f"compare_avaframe_entrainment: {note}; cells {args.dx:g} m; output {out}",
          flush=True)
    af = ca.run_avaframe(how, where, "avaAlr", "samosat", scenario, args.dx, out,
                         entrainment={"path": args.ent, "rho_ent": RHO_ENT, "e_b": E_B})
    log = np.loadtxt(af["mass_log"], delimiter=",", skiprows=1, ndmin=2)
    af_t, af_v = log[:, 0], (log[:, 1] - log[0, 1]) / ca.RHO
    t_stop = float(af["t_end_s"])
    fl = avflow_run(scenario, Path(args.ent), t_stop)
    pft, ax_, ay_ = ca.read_asc(af["pft"])
    af_on_fl = ca.nearest_on(pft, ax_, ay_, fl["xs"], fl["ys"]).ravel()
    area = fl["area"]
    lines = [f"# AvaFrame com1DFA and avflow, erosion-energy entrainment on avaAlr "
             f"({args.dx:g} m cells)", "",
             f"- {note}; AvaFrame {af['avaframe_version']}, {af['ended_by']} at "
             f"{t_stop:.1f} s, {af['wall_s']:.1f} s; avflow to the same time, time loop "
             f"{fl['wall_s']:.1f} s (one thread)",
             f"- samosAT (AvaFrame's standard parameters), rho 200 kg/m^3, rhoEnt "
             f"{RHO_ENT:g} kg/m^3, e_b {E_B:g} J/kg; ENT {Path(args.ent).name}, "
             f"{float((fl['layer'] * area).sum()):.0f} m^3 of layer on avflow's cells",
             "", "| t (s) | AvaFrame entrained (m^3 of flow) | avflow | avflow / AvaFrame |",
             "|---|---|---|---|"]
    for t in TIMES:
        if t > t_stop:
            continue
        a = float(np.interp(t, af_t, af_v))
        f = float(np.interp(t, fl["series"][:, 0], fl["series"][:, 1]))
        lines.append(f"| {t} | {a:.0f} | {f:.0f} | {f / a if a else float('nan'):.2f} |")
    a_end, f_end = float(af_v[-1]), fl["entrained"]
    lines.append(f"| {t_stop:.1f} (end) | {a_end:.0f} | {f_end:.0f} | {f_end / a_end:.2f} |")
    eroded_af = a_end * ca.RHO / RHO_ENT
    eroded_fl = f_end * ca.RHO / RHO_ENT
    layer = float((fl["layer"] * area).sum())
    lines += ["", f"- layer eroded: AvaFrame {eroded_af:.0f} m^3 ({eroded_af / layer:.0%} "
              f"of it), avflow {eroded_fl:.0f} m^3 ({eroded_fl / layer:.0%})",
              f"- avflow's balance: released + entrained - on the map - outflow = "
              f"{fl['released'] + f_end - fl['on_map'] - fl['outflow']:.2e} m^3"]
    for thr in (0.1, 0.01):
        a, b = af_on_fl > thr, fl["peak_h"] > thr
        iou = (a & b).sum() / max((a | b).sum(), 1)
        lines.append(f"- footprint > {thr:g} m: AvaFrame {float(area[a].sum()) / 1e6:.3f} "
                     f"km^2, avflow {float(area[b].sum()) / 1e6:.3f} km^2, IoU {iou:.2f}")
    text = "\n".join(lines) + "\n"
    print(text)
    (out / "report.md").write_text(text)
    figure(out / "entrainment_avaAlr.png", af_t, af_v, fl, af_on_fl,
           f"avaAlr, erosion energy e_b = {E_B:g} J/kg, {args.dx:g} m")
    (out / "series.json").write_text(json.dumps(
        {"avaframe": {"t": af_t.tolist(), "entrained_m3": af_v.tolist()},
         "avflow": fl["series"].tolist()}))


if __name__ == "__main__":
    main()
