"""The outputs of a calibration: calibration.csv, calibration.nc (CF), report.md and PNGs.

Every file is written to a temporary name in OUTDIR and renamed into place.
"""

from __future__ import annotations

import itertools
import math
import os
from pathlib import Path

import numpy as np

from avflow.calibration.observe import SUMMARIES

__all__ = ["write_outputs"]

GRID_POINTS = 41  #: per axis of the emulated misfit maps
_UNITS = {"pressure": "kPa", "thickness": "m", "speed": "m/s"}


def _atomic(path: Path, write) -> Path:
    from avflow.files import atomic_write

    return atomic_write(path, write)


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    plt = _plt()
    _atomic(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    plt.close(fig)
    return path


def write_outputs(result, report: bool = True) -> list[Path]:
    out = Path(result.outdir)
    written = [_atomic(out / "calibration.csv",
                       lambda tmp: result.table.to_csv(tmp, index=False))]
    ds = calibration_dataset(result)
    # float64 kept (write_netcdf stores maps as float32): draws and design read back exact
    encoding = {name: ({"_FillValue": None} if name in ds.coords
                       else {"zlib": True, "complevel": 2} if var.dtype.kind == "f" else {})
                for name, var in ds.variables.items()}
    written.append(_atomic(out / "calibration.nc", lambda tmp: ds.to_netcdf(
        tmp, engine="netcdf4", encoding=encoding)))
    if report:
        written.append(write_report(result, ds))
    return written


# =========================================================================================
# calibration.nc
# =========================================================================================


def _sha256(path) -> str:
    from avflow.ensemble.orchestrate import file_sha256

    return file_sha256(path)


def _emulated_grids(result) -> dict:
    """Per pair of parameters, the emulated misfit on a grid, the others at the best fit."""
    cal = result.calibration
    gp = result.emulators.get("sqrt_misfit")
    if gp is None:
        return {}
    lo = np.array([b[0] for b in cal.bounds])
    hi = np.array([b[1] for b in cal.bounds])
    best_u = (np.array([result.best[n] for n in cal.names]) - lo) / (hi - lo)
    axis = np.linspace(0.0, 1.0, GRID_POINTS)
    grids = {}
    pairs = list(itertools.combinations(range(len(cal.names)), 2)) or [(0,)]
    for pair in pairs:
        if len(pair) == 1:
            U = np.tile(best_u, (GRID_POINTS, 1))
            U[:, 0] = axis
            grids[pair] = np.maximum(gp.predict(U), 0.0) ** 2
            continue
        i, j = pair
        A, B = np.meshgrid(axis, axis, indexing="ij")
        U = np.tile(best_u, (A.size, 1))
        U[:, i], U[:, j] = A.ravel(), B.ravel()
        grids[pair] = (np.maximum(gp.predict(U), 0.0) ** 2).reshape(A.shape)
    return grids


def calibration_dataset(result):
    import xarray as xr

    cal = result.calibration
    table = result.table
    names = cal.names
    lo = np.array([b[0] for b in cal.bounds])
    hi = np.array([b[1] for b in cal.bounds])
    run = np.arange(len(table))
    data = {}
    data["design"] = (("run", "parameter"), table[names].to_numpy(float),
                      {"long_name": "parameter values of each model run"})
    data["misfit"] = ("run", table["misfit"].to_numpy(float),
                      {"long_name": "sum_i w_i (d_i / sigma_i)^2; NaN: the run failed "
                                    "(missing, not zero)", "units": "1"})
    data["log_likelihood"] = ("run", table["log_likelihood"].to_numpy(float)
                              if "log_likelihood" in table else np.full(len(run), np.nan),
                              {"long_name": "Gaussian log-likelihood of the stated errors",
                               "units": "1"})
    data["stage"] = ("run", table["stage"].astype(str).to_numpy())
    data["status"] = ("run", table["status"].astype(str).to_numpy())
    data["scenario_hash"] = ("run", table["scenario_hash"].astype(str).to_numpy())
    for k, obs in enumerate(cal.spec.observations):
        label = cal.label(k)
        col = f"{label}_d"
        units = ("m" if obs.kind == "runout" or (obs.kind == "deposit" and obs.raster)
                 else {"speed": "m s-1", "arrival_time": "s", "thickness": "m",
                       "pressure": "kPa", "deposit": "m"}[obs.field] if obs.kind == "points" else "1")
        data[col] = ("run", table[col].to_numpy(float) if col in table
                     else np.full(len(run), np.nan),
                     {"long_name": f"discrepancy of observation {label} ({obs.kind})",
                      "units": units, "error_sigma": cal.error(k), "weight": obs.weight})
        if f"{col}_z" in table:
            data[f"{col}_check_z"] = ("run", table[f"{col}_z"].to_numpy(float), {
                "long_name": f"check runs: model minus emulator of {col}, in emulator "
                             "standard deviations (NaN: not a check run)", "units": "1"})
        for extra in ("csi", "f1", "tversky", "auroc", "tp", "fp", "fn", "tn",
                      "s_sim", "s_obs", "rmse"):
            c = f"{label}_{extra}"
            if c in table:
                data[c] = ("run", table[c].to_numpy(float))
    for s in SUMMARIES:
        if s in table:
            data[s] = ("run", table[s].to_numpy(float))
    coords = {"run": run, "parameter": np.array(names, dtype=object),
              "parameter_min": ("parameter", lo), "parameter_max": ("parameter", hi)}
    data["best_fit"] = ("parameter", np.array([result.best[n] for n in names], float),
                        {"long_name": "parameters of the run of least misfit"})
    for pair, grid in _emulated_grids(result).items():
        if len(pair) == 1:
            a = f"{names[0]}_grid"
            coords[a] = np.linspace(lo[0], hi[0], GRID_POINTS)
            data["emulated_misfit"] = ((a,), grid, {"long_name": "GP emulator of the misfit (squared GP of sqrt(misfit))"})
            continue
        i, j = pair
        a, b = f"{names[i]}_grid", f"{names[j]}_grid"
        coords[a] = np.linspace(lo[i], hi[i], GRID_POINTS)
        coords[b] = np.linspace(lo[j], hi[j], GRID_POINTS)
        data[f"emulated_misfit_{i}_{j}"] = (
            (a, b), grid, {"long_name": f"GP emulator of the misfit over {names[i]} and "
                                        f"{names[j]}, the other parameters at the best fit"})
    if result.posterior is not None:
        p = result.posterior
        data["posterior"] = (("draw", "parameter"), p.draws,
                             {"long_name": "MCMC draws (emcee) of the emulator posterior",
                              "walkers": p.walkers, "steps": p.steps, "burn": p.burn,
                              "thin": 5, "acceptance_fraction": p.acceptance})
        q = np.quantile(p.draws, [0.05, 0.5, 0.95], axis=0)
        coords["quantile"] = [0.05, 0.5, 0.95]
        data["posterior_quantiles"] = (("quantile", "parameter"), q)
    if result.sobol:
        quantities = list(result.sobol)
        coords["quantity"] = np.array(quantities, dtype=object)
        for key in ("S1", "S1_conf", "ST", "ST_conf"):
            data[f"sobol_{key}"] = (("quantity", "parameter"),
                                    np.array([result.sobol[q][key] for q in quantities]),
                                    {"long_name": f"Sobol {key} on the GP emulator (SALib)"})
    if result.cv:
        coords.setdefault("quantity_cv", np.array(list(result.cv), dtype=object))
        data["emulator_cv_rmse"] = ("quantity_cv", [result.cv[q]["rmse"] for q in result.cv],
                                    {"long_name": "5-fold cross-validated RMSE of the GP "
                                                  "emulator (sqrt_misfit: the GP of sqrt(misfit))"})
        data["emulator_cv_coverage90"] = ("quantity_cv",
                                          [result.cv[q]["coverage90"] for q in result.cv])
    fit = result.fit
    if fit is not None:
        data["best_chi_square"] = ((), fit["chi2"], {
            "long_name": "misfit of the best run, a chi-square if the model reproduces the "
                         "observations within their errors", "units": "1",
            "degrees_of_freedom": fit["dof"], "limit": fit["limit"],
            "limit_quantile": fit["level"], "p_value": fit["p_value"]})
    ds = xr.Dataset({k: xr.Variable(*v) for k, v in data.items()}, coords=coords)
    observations = []
    for (k, key), path in sorted(cal.files.items()):
        observations.append(f"{cal.label(k)}.{key}: {path} sha256:{_sha256(path)}")
    base = cal.base.source_path
    ds.attrs = {
        "Conventions": "CF-1.11",
        "title": f"avflow calibration {cal.name}",
        "source": "avflow calibrate",
        "method": cal.spec.method,
        "calibration_file": cal.path or "",
        "calibration_sha256": _sha256(cal.path) if cal.path else "",
        "calibration_yaml": cal.text,
        "base_scenario": base or "",
        "base_scenario_sha256": _sha256(base) if base and os.path.isfile(base) else "",
        "observation_files": "\n".join(observations),
        "parameters": " ".join(names),
        "best_fit": " ".join(f"{n}={result.best[n]:.6g}" for n in names),
    }
    if fit is not None:
        ds.attrs["goodness_of_fit"] = (
            f"fits: best misfit {fit['chi2']:.4g} <= {fit['limit']:.4g}" if fit["fits"] else
            f"failed: the model cannot reproduce the observations within their errors "
            f"(best misfit {fit['chi2']:.4g} > {fit['limit']:.4g}, the {fit['level']:.0%} "
            f"quantile of chi-square with {fit['dof']} degrees of freedom)")
    if result.checks is not None:
        v = result.checks
        ds.attrs["posterior_check"] = (
            f"flagged: check runs' median misfit {v['median']:.4g} > best {v['best']:.4g} "
            f"+ {v['allowed_rise']:.3g}" if v["flagged"] else
            f"confirmed: check runs' median misfit {v['median']:.4g} <= best "
            f"{v['best']:.4g} + {v['allowed_rise']:.3g}")
    ident = result.identifiability
    if ident is not None:
        ds.attrs["constrained_parameters"] = " ".join(
            n for n, ok in ident["constrained"].items() if ok)
        if ident.get("withheld"):
            ds.attrs["constrained_parameters_withheld"] = ident["withheld"]
    return ds


# =========================================================================================
# report.md and its figures
# =========================================================================================


def _fmt(v) -> str:
    if isinstance(v, (float, np.floating)):
        return "NaN" if not math.isfinite(v) else f"{v:.4g}"
    return str(v)


def _table(header, rows) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(_fmt(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def identifiability_lines(result) -> list[str]:
    """The sentences of the report on what the data constrain (tested)."""
    ident = result.identifiability
    if ident is None:
        return ["No posterior was sampled (method is not `posterior`): identifiability is "
                "not assessed."]
    if ident.get("withheld"):
        return [f"**Not assessed: {ident['withheld']}.** The posterior above describes the "
                "emulator over the range, not what the observations allow: no parameter is "
                "constrained by the data, whatever the width of its interval."] + [
            f"- {n}: 90% interval {ident['width'][n]:.0%} of its prior range: not assessed."
            for n in ident["constrained"]]
    lines = []
    for a, b, r in ident["ridges"]:
        lines.append(f"**The data do not separate {a} and {b}**: the posterior lies along a "
                     f"ridge (correlation {r:+.2f}) and neither 90% interval is narrower "
                     f"than {ident['width_limit']:.0%} of its range; the observations fix a "
                     "combination of the two, not each.")
    for n, ok in ident["constrained"].items():
        w = ident["width"][n]
        lines.append(f"- {n}: 90% interval {w:.0%} of its prior range: "
                     + ("constrained by the data." if ok else "NOT constrained by the data."))
    return lines


#: Past this many emulator standard deviations a check run contradicts the emulator.
Z_WARN = 3.0


def fit_lines(result) -> list[str]:
    """The report's goodness-of-fit verdict on the best run (tested)."""
    fit = result.fit
    if fit is None:
        return []
    n = fit["dof"]
    head = (f"Goodness of fit: the best run's misfit {fit['chi2']:.4g} is a chi-square of "
            f"{n} observation(s) if the model reproduces them within their errors; "
            f"{fit['limit']:.3g} is its {fit['level']:.0%} quantile (p = {fit['p_value']:.2g}).")
    if fit["fits"]:
        return [head + " The fit is within the errors.", ""]
    return [f"**The model cannot reproduce the observations within their errors**: the best "
            f"of the runs misses them by a misfit of {fit['chi2']:.4g} where at most "
            f"{fit['limit']:.3g} is expected. A wrong friction law, a wrong release or DEM, "
            "or errors stated too small; no parameter value below is a calibrated one.", "",
            head, ""]


def check_lines(result) -> list[str]:
    """Warnings on the posterior's check runs: emulator contradicted, posterior worse than
    the best design run (tested)."""
    cal = result.calibration
    table = result.table
    lines = []
    checks = table[table["stage"] == "check"]
    for _, r in checks.iterrows():
        for k in range(len(cal.spec.observations)):
            c = f"{cal.label(k)}_d"
            z = r.get(c + "_z", math.nan)
            if isinstance(z, float) and math.isfinite(z) and abs(z) > Z_WARN:
                where = ", ".join(f"{n}={r[n]:.4g}" for n in cal.names)
                lines.append(f"**Emulator off at a check run** ({where}): {c} is "
                             f"{r[c]:.4g} by the model, {r[c + '_emulated']:.4g} +- "
                             f"{r[c + '_emulated_sd']:.2g} by the emulator, {z:+.1f} standard "
                             "deviations: the posterior there rests on a wrong emulator.")
    v = result.checks
    if v is not None:
        if v["flagged"]:
            lines.append(f"**The posterior is not confirmed by the model**: its check runs "
                         f"fit worse (median misfit {v['median']:.4g}) than the best design "
                         f"run ({v['best']:.4g}) by more than the {v['allowed_rise']:.3g} a "
                         "posterior that fits would allow; it is not reported as "
                         "constraining anything.")
        else:
            lines.append(f"Check runs: median misfit {v['median']:.4g} against the best "
                         f"design run's {v['best']:.4g} (within {v['allowed_rise']:.3g}).")
    return [*[ln + "\n" for ln in lines]] if lines else []


def write_report(result, ds) -> Path:
    out = Path(result.outdir)
    figdir = out / "report"
    figdir.mkdir(exist_ok=True)
    cal = result.calibration
    table = result.table
    names = cal.names
    md = [f"# Calibration {cal.name}", ""]
    if cal.spec.description:
        md += [cal.spec.description, ""]
    ok = table[np.isfinite(table["misfit"].to_numpy(float))]
    md += [f"Method **{cal.spec.method}**, {len(table)} model runs ({len(table) - len(ok)} "
           "failed or unscored: counted as missing, not zero). Base scenario: "
           f"`{cal.base.source_path}`.", ""]
    md += ["## Observations", "",
           _table(["observation", "kind", "source", "discrepancy d", "error sigma", "weight"],
                  [[cal.label(k), o.kind, _source(cal, k), _dname(o), cal.error(k), o.weight]
                   for k, o in enumerate(cal.spec.observations)]), "",
           "misfit = sum_i w_i (d_i / sigma_i)^2; log-likelihood = -misfit/2 - "
           "sum_i w_i log(sigma_i sqrt(2 pi)).", ""]
    best_row = table.iloc[int(np.nanargmin(table["misfit"].to_numpy(float)))]
    md += ["## Best fit", "", _table(["parameter", "range", "best run"],
                                     [[n, f"[{b[0]:g}, {b[1]:g}]", best_row[n]]
                                      for n, b in zip(names, cal.bounds)]), "",
           f"Misfit {best_row['misfit']:.4g}; " + "; ".join(
               f"{cal.label(k)} d = {best_row.get(cal.label(k) + '_d', math.nan):.4g}"
               for k in range(len(cal.spec.observations))), ""]
    md += fit_lines(result)
    edges = [n for n, (lo, hi) in zip(names, cal.bounds)
             if min(best_row[n] - lo, hi - best_row[n]) <= 0.02 * (hi - lo)]
    for n in edges:
        md += [f"**The best fit lies at the edge of the range of {n}** (within 2% of it): the "
               "optimum may lie outside the range; widen it, or read this as a bound.", ""]
    figures = []
    fig = _misfit_pairs(result, ds)
    if fig is not None:
        figures.append(("Misfit over each pair of parameters (GP emulator, the others at "
                        "the best fit) with the design points", _save(fig, figdir /
                                                                     "misfit_pairs.png")))
    fig = _footprint(result)
    if fig is not None:
        figures.append(("Best-fit footprint over the observation",
                        _save(fig, figdir / "footprint.png")))
    if result.posterior is not None:
        figures.append(("Posterior (corner plot of the MCMC draws)",
                        _save(_corner(result), figdir / "posterior_corner.png")))
    if result.sobol:
        figures.append(("Sobol indices on the emulator (bars: 95% confidence)",
                        _save(_sobol_bars(result), figdir / "sobol.png")))
    if result.posterior is not None:
        p = result.posterior
        q = np.quantile(p.draws, [0.05, 0.5, 0.95], axis=0)
        md += ["## Posterior", "",
               "Priors: uniform on each range. Likelihood: Gaussian on the emulated "
               "discrepancies, the emulator's predictive variance added to sigma_i^2. "
               f"emcee: {p.walkers} walkers, {p.steps} steps, {p.burn} burnt, thinned by 5 "
               f"({len(p.draws)} draws), acceptance {p.acceptance:.2f}, autocorrelation "
               "time " + ", ".join(f"{t:.0f}" for t in p.autocorr) + " steps.", "",
               _table(["parameter", "5%", "median", "95%"],
                      [[n, *q[:, i]] for i, n in enumerate(names)]), "",
               "### Identifiability", "", *identifiability_lines(result), ""]
        checks = table[table["stage"] == "check"]
        if len(checks):
            md += ["### Emulator checked by model runs at posterior draws", ""]
            rows = []
            for _, r in checks.iterrows():
                for k in range(len(cal.spec.observations)):
                    c = f"{cal.label(k)}_d"
                    rows.append([", ".join(f"{n}={r[n]:.4g}" for n in names), c, r.get(c),
                                 r.get(c + "_emulated"), r.get(c + "_emulated_sd"),
                                 r.get(c + "_z")])
            md += [_table(["draw", "discrepancy", "model", "emulator", "emulator sd",
                           "model - emulator (sd)"], rows), ""]
            md += check_lines(result)
    if result.cv:
        md += ["## Emulators", "", "GP (scikit-learn, constant x Matern 2.5 + white noise) of "
               "each quantity over the design; 5-fold cross-validation:", "",
               _table(["quantity", "CV RMSE", "held-out inside 90% interval"],
                      [[q, v["rmse"], v["coverage90"]] for q, v in result.cv.items()]), ""]
    if result.sobol:
        md += ["## Sensitivity", "", _table(
            ["quantity", *[f"S1 {n}" for n in names], *[f"ST {n}" for n in names]],
            [[q, *[f"{a:.2f} ± {c:.2f}" for a, c in zip(v["S1"], v["S1_conf"])],
              *[f"{a:.2f} ± {c:.2f}" for a, c in zip(v["ST"], v["ST_conf"])]]
             for q, v in result.sobol.items()]), ""]
    t = result.timings
    if t:
        md += ["## Time", "", f"Model runs {t.get('model_runs', 0):.1f} s; calibration "
               f"overhead {t.get('overhead', 0):.1f} s (bayes-opt surrogate and acquisition "
               f"{t.get('acquisition', 0):.1f} s, emulators with their cross-validation "
               f"{t.get('emulators', 0):.1f} s, MCMC {t.get('posterior', 0):.1f} s, Sobol "
               f"{t.get('sobol', 0):.1f} s); scoring {t.get('scoring', 0):.1f} s; total "
               f"{t.get('total', 0):.1f} s.", ""]
    failed = table[table["status"] == "failed"]
    if len(failed):
        md += ["## Failed runs (missing)", "", _table(["run", *names, "error"], [
            [r["run"], *[r[n] for n in names], r["error"]] for _, r in failed.iterrows()]), ""]
    for caption, path in figures:
        md += [f"![{caption}](report/{path.name})", "", f"*{caption}*", ""]
    text = "\n".join(md) + "\n"
    return _atomic(out / "report.md", lambda tmp: Path(tmp).write_text(text))


def _source(cal, k) -> str:
    o = cal.spec.observations[k]
    if o.kind == "points":
        return f"{len(o.points)} point(s)"
    if o.kind == "runout":
        return (f"station {o.station:g} m" if o.station is not None
                else f"point {list(o.point)}") + (f" on {os.path.basename(o.line)}"
                                                   if o.line else "")
    for a in ("raster", "polygon"):
        if getattr(o, a) is not None:
            return f"{a} {os.path.basename(getattr(o, a))}"
    return f"interval {list(o.interval)}"


def _dname(o) -> str:
    if o.kind == "points":
        what = {"thickness": "peak flow thickness", "deposit": "deposit thickness (end)",
                "speed": "peak speed", "pressure": "peak pressure",
                "arrival_time": "arrival time"}[o.field]
        return f"RMSE of the {what} at the points"
    if o.kind == "runout":
        return f"s_sim - s_obs (m), {o.field} >= threshold"
    if o.kind == "deposit" and o.raster is not None:
        return f"RMSE over the union (m), >= {o.threshold:g} m"
    what = f"deposit >= {o.threshold:g} m" if o.kind == "deposit" else \
        f"peak {o.field} >= {o.threshold:g} {_UNITS[o.field]}"
    return f"1 - {o.score} ({what})"


def _misfit_pairs(result, ds):
    cal = result.calibration
    names = cal.names
    plt = _plt()
    table = result.table
    X = table[names].to_numpy(float)
    m = table["misfit"].to_numpy(float)
    ib = int(np.nanargmin(m))
    if len(names) == 1:
        fig, ax = plt.subplots(figsize=(6, 4))
        if "emulated_misfit" in ds:
            ax.plot(ds[f"{names[0]}_grid"], ds["emulated_misfit"], label="emulator")
        ax.plot(X[:, 0], m, "o", label="runs")
        ax.set_xlabel(names[0])
        ax.set_ylabel("misfit")
        ax.set_yscale("symlog")
        ax.legend()
        return fig
    pairs = list(itertools.combinations(range(len(names)), 2))
    fig, axes = plt.subplots(1, len(pairs), figsize=(5.5 * len(pairs), 4.5), squeeze=False)
    for ax, (i, j) in zip(axes[0], pairs):
        key = f"emulated_misfit_{i}_{j}"
        if key in ds:
            g = np.log10(1.0 + np.maximum(ds[key].values, 0.0))
            cs = ax.contourf(ds[f"{names[i]}_grid"], ds[f"{names[j]}_grid"], g.T, 20,
                             cmap="viridis_r")
            fig.colorbar(cs, ax=ax, label="log10(1 + misfit), emulated")
        ok = np.isfinite(m)
        ax.scatter(X[ok, i], X[ok, j], c=np.arange(len(m))[ok], cmap="autumn", s=18,
                   edgecolor="k", linewidth=0.4, label="runs (colour: order)")
        if (~ok).any():
            ax.scatter(X[~ok, i], X[~ok, j], marker="x", c="k", label="failed (missing)")
        ax.plot(X[ib, i], X[ib, j], "*", ms=16, mfc="white", mec="k", label="best run")
        ax.set_xlabel(names[i])
        ax.set_ylabel(names[j])
        ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    return fig


def _corner(result):
    plt = _plt()
    names = result.calibration.names
    draws = result.posterior.draws
    d = len(names)
    side = max(2.8 * d + 1, 5.0)  # one parameter: room for the title
    fig, axes = plt.subplots(d, d, figsize=(side, side), squeeze=False, layout="constrained")
    for i in range(d):
        for j in range(d):
            ax = axes[i, j]
            if j > i:
                ax.axis("off")
                continue
            if i == j:
                ax.hist(draws[:, i], bins=40, color="tab:blue", alpha=0.8)
                for q in np.quantile(draws[:, i], [0.05, 0.5, 0.95]):
                    ax.axvline(q, color="k", ls="--", lw=0.8)
                ax.set_yticks([])
                # the best run on its parameter's axis, as on the pair panels
                ax.plot(result.best[names[i]], 0.0, "*", color="tab:red", ms=12,
                        clip_on=False, zorder=5)
                if d == 1:
                    ax.set_xlabel(names[i])
            else:
                ax.hist2d(draws[:, j], draws[:, i], bins=40, cmap="Blues")
            if i == d - 1:
                ax.set_xlabel(names[j])
            if j == 0 and i > 0:
                ax.set_ylabel(names[i])
            if i != j:
                ax.plot(result.best[names[j]], result.best[names[i]], "*", color="tab:red",
                        ms=10)
    fig.suptitle("posterior (dashed: 5%, 50%, 95%; star: best run)", fontsize=10)
    return fig


def _sobol_bars(result):
    plt = _plt()
    names = result.calibration.names
    quantities = list(result.sobol)
    fig, ax = plt.subplots(figsize=(min(13.5, max(7.5, 0.8 * len(quantities) * len(names)
                                                  + 1.5)), 4), layout="constrained")
    width = 0.8 / (2 * len(names))
    x = np.arange(len(quantities))
    for k, n in enumerate(names):
        for m, key in enumerate(("S1", "ST")):
            vals = [result.sobol[q][key][k] for q in quantities]
            conf = [result.sobol[q][key + "_conf"][k] for q in quantities]
            ax.bar(x + (2 * k + m - len(names)) * width + width / 2, vals, width, yerr=conf,
                   capsize=2, label=f"{key} {n}", alpha=0.9 if key == "ST" else 0.6)
    ax.set_xticks(x)
    ax.set_xticklabels(quantities, rotation=20, fontsize=8)
    ax.set_ylabel("Sobol index")
    ax.set_ylim(0, 1.1)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # off the bars
    return fig


def _footprint(result):
    """The best run's area (the first area-like observation's field and threshold) over
    the observed area, on the hillshade (maps) or along the profile."""
    import xarray as xr

    from avflow.calibration.observe import _FIELDS, member_cells, observe

    cal = result.calibration
    table = result.table
    ib = int(np.nanargmin(table["misfit"].to_numpy(float)))
    path = Path(result.outdir) / table.iloc[ib]["file"]
    try:
        with xr.open_dataset(path, decode_times=False, engine="netcdf4") as ds:
            ds = ds.load()
    except Exception:  # noqa: BLE001 - no figure
        return None
    cells = member_cells(ds)
    observed = observe(cal, cells)
    plt = _plt()
    k = next((k for k in observed.masks), None)
    p = cells.points
    if k is not None:
        o = cal.spec.observations[k]
        if o.kind == "deposit":
            sim = np.nan_to_num(cells.deposit) >= o.threshold
            what = f"deposit >= {o.threshold:g} m"
        else:
            name, factor = _FIELDS[o.field]
            sim = np.nan_to_num(np.asarray(p.fields[name], float)) * factor >= o.threshold
            what = f"peak {o.field} >= {o.threshold:g} {_UNITS[o.field]}"
        obs = observed.masks[k]
    else:
        name, factor = _FIELDS["pressure"]
        sim = np.nan_to_num(np.asarray(p.fields[name], float)) * factor >= 1.0
        obs = None
        what = "peak pressure >= 1 kPa"
    title = ("best run " + ", ".join(f"{n}={result.best[n]:.4g}" for n in cal.names))
    if p.kind == "profile":
        fig, ax = plt.subplots(figsize=(8, 3.5))
        ax.plot(p.x, p.z, color="0.4", label="bed")
        top = np.nanmax(p.z)
        ax.fill_between(p.x, np.nanmin(p.z), top, where=sim, color="tab:red", alpha=0.3,
                        label=f"simulated: {what}")
        if obs is not None:
            ax.fill_between(p.x, np.nanmin(p.z), top, where=obs, color="none",
                            hatch="//", edgecolor="k", label="observed")
        for j, s in observed.stations.items():
            ax.axvline(float(observed.lines[j].at(np.array([s]))[0][0]), color="k", ls="--",
                       label="observed runout")
        ax.set_xlabel("x (m, horizontal)")
        ax.set_ylabel("z (m)")
        ax.legend(fontsize=7)
        ax.set_title(title)
        return fig
    if p.grid is None:
        return None
    from avflow.output.maps import hillshade

    xg, yg, bed = p.grid
    dx, dy = abs(xg[1] - xg[0]), abs(yg[1] - yg[0])
    shade = hillshade(bed, dx, dy)
    on = np.isfinite(bed)

    def grid_of(v):
        g = np.zeros(bed.shape)
        g[on] = v
        return g

    fig, ax = plt.subplots(figsize=(8, 8 * bed.shape[0] / bed.shape[1] + 1.2))
    extent = (xg[0] - dx / 2, xg[-1] + dx / 2, yg[0] - dy / 2, yg[-1] + dy / 2)
    ax.imshow(shade, origin="lower", extent=extent, cmap="gray", vmin=0, vmax=1)
    from matplotlib.colors import ListedColormap

    ax.imshow(np.where(grid_of(sim) > 0, 1.0, np.nan), origin="lower", extent=extent,
              cmap=ListedColormap(["orange"]), alpha=0.5, vmin=0, vmax=1)
    if obs is not None:
        ax.contour(xg, yg, grid_of(obs), levels=[0.5], colors="tab:blue", linewidths=1.5)
    for j, line in observed.lines.items():
        ax.plot(line.x, line.y, "k--", lw=0.8)
        o = cal.spec.observations[j]
        if o.point is not None:
            ax.plot(*o.point, "o", mfc="white", mec="k", label="observed runout")
    if obs is not None:  # only what was observed
        ax.plot([], [], color="tab:blue", label="observed area")
    ax.fill([], [], color="orange", alpha=0.5, label=f"simulated: {what}")
    handles, labels = ax.get_legend_handles_labels()
    unique = dict(zip(labels, handles))  # one entry per kind (several runout points)
    ax.legend(unique.values(), unique.keys(), fontsize=7, loc="upper right")
    ax.set_title(title)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.ticklabel_format(useOffset=False, style="plain")  # UTM, LV95: whole metres
    ax.set_aspect("equal")
    fig.tight_layout()
    return fig
