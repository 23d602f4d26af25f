"""Recovery of a known truth on a real path: avaKot at 10 m, Voellmy.

    python workflows/calibrate_avakot.py [--out out/calibrate_avakot] [--dx 10] [--budget 40]
                                         [--workers N] [--method bayes-opt|posterior]

1. The truth: ``scenarios/avakot_coulomb.yaml`` with ``rheology: {law: voellmy, mu: 0.25,
   xi: 1500}`` at ``--dx`` (10 m), run once.
2. Its observation: the area above 1 kPa (``impact.tif``) and its runout point along its
   own centre-of-mass path (``path.csv``, the line of ``avflow path``), as a field team
   would map them.
3. ``avflow calibrate`` of mu in [0.1, 0.5] and xi in [500, 4000] with ``--method``
   (default ``posterior``: bayes-opt within ``--budget`` runs, then the emulator posterior
   and 4 check runs).
4. Prints the best fit against the truth (target: mu within 0.02, runout within one cell),
   the posterior's 90% intervals (target: they cover the truth), and the cost: the model
   runs' wall time against the calibration's own (surrogate, acquisition, MCMC, Sobol;
   target < 10%). Writes ``OUT/result.md`` with those figures.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
TRUTH = {"rheology.mu": 0.25, "rheology.xi": 1500.0}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="out/calibrate_avakot")
    p.add_argument("--dx", type=float, default=10.0)
    p.add_argument("--budget", type=int, default=40)
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--method", default="posterior", choices=("bayes-opt", "posterior"))
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    import avflow
    from avflow.calibration import calibrate
    from avflow.output.path import analyse_run, path_for, run_points
    from avflow.terrain.raster import write_tif

    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    source = REPO / "scenarios" / "avakot_coulomb.yaml"
    text = source.read_text()
    text = text.replace("../data/", f"{REPO / 'data'}/")
    text = text.replace("rheology: {law: coulomb, delta_deg: 20.0}",
                        "rheology: {law: voellmy, mu: 0.25, xi: 1500.0}")
    text = text.replace("grid: {dx: 5.0}", f"grid: {{dx: {args.dx}}}")
    text = text.replace("name: avakot-coulomb-20", "name: avakot-voellmy-truth")
    base = out / "avakot_voellmy.yaml"
    base.write_text(text)

    clock = time.perf_counter()
    truth = avflow.run(base)
    t_truth = time.perf_counter() - clock
    points = run_points(truth)
    line = path_for(points, None)  # the truth's centre-of-mass track, as avflow path draws it
    (out / "path.csv").write_text("x,y\n" + "".join(f"{x:.3f},{y:.3f}\n"
                                                      for x, y in zip(line.x, line.y)))
    _, res = analyse_run(truth, line=line)
    rx, ry = res.scalars["runout_x"], res.scalars["runout_y"]
    from avflow.output.maps import crs_wkt

    crs = crs_wkt(truth)
    write_tif(out / "impact.tif", (truth.peak_pressure.values >= 1e3).astype(float),
              truth.x.values, truth.y.values, crs)
    print(f"truth: {t_truth:.1f} s, runout point ({rx:.1f}, {ry:.1f}) at s = "
          f"{res.scalars['runout_s']:.1f} m, impact area "
          f"{np.count_nonzero(truth.peak_pressure.values >= 1e3) * args.dx ** 2:.0f} m2")

    calib = out / "calibrate.yaml"
    calib.write_text(f"""name: avakot-recovery
description: avaKot at {args.dx:g} m, synthetic observation of Voellmy mu = 0.25, xi = 1500.
base: avakot_voellmy.yaml
parameters:
  rheology.mu: [0.1, 0.5]
  rheology.xi: [500.0, 4000.0]
observations:
  - {{kind: runout, name: runout, point: [{rx:.3f}, {ry:.3f}], line: path.csv,
     error: {args.dx:g}}}
  - {{kind: area, name: impact, raster: impact.tif, score: tversky, error: 0.02}}
method: {args.method}
budget: {args.budget}
seed: {args.seed}
""")
    result = calibrate(calib, out / "run", workers=args.workers)
    t = result.table
    design = t[t["stage"].isin(["initial", "bayes-opt"])]
    best = design.loc[design["misfit"].idxmin()]
    tim = result.timings
    lines = [f"# avaKot at {args.dx:g} m: recovery of Voellmy mu = 0.25, xi = 1500", "",
             f"Method {args.method}, {len(design)} design runs (+ {len(t) - len(design)} "
             "check runs).", "",
             "| | truth | best run | error |", "|---|---|---|---|"]
    for n in result.calibration.names:
        lines.append(f"| {n} | {TRUTH[n]:g} | {best[n]:.4g} | {best[n] - TRUTH[n]:+.4g} |")
    lines += ["", f"Runout difference of the best run along the path: "
              f"{best['runout_d']:+.1f} m (one cell: {args.dx:g} m); Tversky "
              f"{best['impact_tversky']:.3f}.", ""]
    if result.posterior is not None:
        q = np.quantile(result.posterior.draws, [0.05, 0.5, 0.95], axis=0)
        lines += ["| | 5% | median | 95% | covers the truth |", "|---|---|---|---|---|"]
        for i, n in enumerate(result.calibration.names):
            lines.append(f"| {n} | {q[0, i]:.4g} | {q[1, i]:.4g} | {q[2, i]:.4g} | "
                         f"{'yes' if q[0, i] <= TRUTH[n] <= q[2, i] else 'NO'} |")
        from avflow.calibration.outputs import identifiability_lines

        lines += ["", *identifiability_lines(result), ""]
    share = tim["overhead"] / tim["model_runs"] if tim["model_runs"] else float("nan")
    lines += [f"Cost: model runs {tim['model_runs']:.1f} s (truth run {t_truth:.1f} s), "
              f"calibration overhead (surrogate, acquisition, MCMC, Sobol) "
              f"{tim['overhead']:.1f} s = {100 * share:.1f}% of the model runs; scoring "
              f"{tim['scoring']:.1f} s; total {tim['total']:.1f} s.", ""]
    (out / "result.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
