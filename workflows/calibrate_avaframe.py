"""Calibrate avflow's friction to AvaFrame com1DFA's peak fields (issue 28, "against another
model").

    python workflows/calibrate_avaframe.py --avaframe-python /path/to/avaframe_venv/bin/python \
        [--paths avakot avahit] [--laws coulomb voellmy] [--dx 10] [--budget 40]

For each path and law: AvaFrame com1DFA runs once from its own venv with its parameters
(Coulomb 20 deg; Voellmy mu 0.155, xi 4000; rho 200, tEnd 400 s; as
``workflows/compare_avaframe.py`` runs it: AvaFrame is never a dependency). Its area above
1 kPa (its ``ppr`` raster) and its runout station along avflow's centre-of-mass path become
the observation; ``avflow calibrate`` (bayes-opt, ``--budget`` runs) calibrates avflow's
delta (Coulomb) or mu and xi (Voellmy). Written to ``OUT/result.md``: AvaFrame's parameters
beside avflow's calibrated ones, and the area scores before (avflow at AvaFrame's
parameters) and after.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "workflows"))

RANGES = {"coulomb": {"rheology.delta_deg": (12.0, 30.0)},
          "voellmy": {"rheology.mu": (0.05, 0.5), "rheology.xi": (500.0, 6000.0)}}


def main(argv=None) -> int:
    import compare_avaframe as ca

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--avaframe-python", required=True)
    p.add_argument("--paths", nargs="+", default=["avakot"], choices=sorted(ca.PATHS))
    p.add_argument("--laws", nargs="+", default=["coulomb", "voellmy"],
                   choices=["coulomb", "voellmy"])
    p.add_argument("--dx", type=float, default=10.0)
    p.add_argument("--budget", type=int, default=40)
    p.add_argument("--out", default="out/calibrate_avaframe")
    args = p.parse_args(argv)

    import avflow
    from avflow.calibration import calibrate, load_calibration
    from avflow.calibration.observe import member_cells, observe, score_member
    from avflow.output.path import path_for, run_points
    from avflow.scenario.schema import load_scenario
    from avflow.terrain.raster import read_raster

    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for key in args.paths:
        path, scenario_file = ca.PATHS[key]
        base = load_scenario(REPO / scenario_file)
        for law in args.laws:
            case = out / f"{path}_{law}"
            case.mkdir(exist_ok=True)
            clock = time.perf_counter()
            af = ca.run_avaframe("subprocess", args.avaframe_python, path, law, base,
                                 args.dx, out)
            t_af = time.perf_counter() - clock
            ppr = Path(af["pft"].replace("_pft.asc", "_ppr.asc"))
            scenario = ca.avflow_scenario(base, law, args.dx, stop_rule="kinetic_energy")
            (case / "base.yaml").write_text(scenario.to_yaml())
            before = avflow.run(case / "base.yaml")
            line = path_for(run_points(before), None)
            (case / "path.csv").write_text("x,y\n" + "".join(
                f"{x:.3f},{y:.3f}\n" for x, y in zip(line.x, line.y)))
            r = read_raster(ppr)
            X, Y = np.meshgrid(r.x, r.y)
            hit = np.nan_to_num(r.values) >= 1.0  # kPa
            s_obs = float(line.project(X[hit], Y[hit])[0].max())
            ranges = "\n".join(f"  {k}: [{lo}, {hi}]" for k, (lo, hi) in RANGES[law].items())
            calib = case / "calibrate.yaml"
            calib.write_text(f"""name: {path}-{law}-to-avaframe
base: base.yaml
parameters:
{ranges}
observations:
  - {{kind: area, name: impact, raster: {ppr}, raster_threshold: 0.999999, score: tversky,
     error: 0.02}}
  - {{kind: runout, name: runout, station: {s_obs:.3f}, line: path.csv, error: {args.dx:g}}}
method: bayes-opt
budget: {args.budget}
""")
            cal = load_calibration(calib)
            cells = member_cells(before)
            score0 = score_member(cal, observe(cal, cells), cells)
            result = calibrate(cal, case / "run", workers=0)
            best = result.table.loc[result.table["misfit"].idxmin()]
            af_params = ca.LAWS[law]
            rows.append({
                "case": f"{path} {law} {args.dx:g} m",
                "avaframe": ", ".join(f"{k}={v:g}" for k, v in af_params.items()
                                      if k != "law"),
                "calibrated": ", ".join(f"{n.split('.')[-1]}={best[n]:.4g}"
                                        for n in cal.names),
                "before": score0, "after": best.to_dict(), "af_wall": t_af,
                "runs": len(result.table), "wall": result.timings["total"]})
            print(rows[-1]["case"], rows[-1]["calibrated"], flush=True)
    lines = [f"# avflow calibrated to AvaFrame com1DFA ({time.strftime('%Y-%m-%d')})", "",
             "Observation: AvaFrame's area above 1 kPa (its ppr raster) and its runout station "
             "along avflow's centre-of-mass path; bayes-opt; scores of avflow at AvaFrame's "
             "parameters (before) and at the calibrated ones (after).", "",
             "| case | AvaFrame | avflow calibrated | Tversky before | after | CSI before | "
             "after | runout d before (m) | after (m) | runs |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        b, a = r["before"], r["after"]
        lines.append(f"| {r['case']} | {r['avaframe']} | {r['calibrated']} | "
                     f"{b['impact_tversky']:.3f} | {a['impact_tversky']:.3f} | "
                     f"{b['impact_csi']:.3f} | {a['impact_csi']:.3f} | {b['runout_d']:+.0f} | "
                     f"{a['runout_d']:+.0f} | {r['runs']} |")
    lines += ["", "Wall time: " + "; ".join(
        f"{r['case']}: AvaFrame {r['af_wall']:.0f} s, calibration {r['wall']:.0f} s"
        for r in rows), ""]
    (out / "result.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0 if all(math.isfinite(r["after"]["misfit"]) for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
