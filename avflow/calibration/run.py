"""``avflow calibrate``: the design on the ensemble machinery, the surrogate, the posterior,
the sensitivity, and the outputs.

Every model run is an ensemble member run by :func:`avflow.ensemble.orchestrate.run_ensemble`
into ``OUTDIR/members/<scenario_hash>.nc`` (checksums in ``OUTDIR/checksums/``): a rerun of
the same command finds its members there and runs only the others (bayes-opt is
deterministic given the file and its seed, so it proposes the same points again). A member
that fails is scored as missing (NaN), never as zero, and left out of every fit.
"""

from __future__ import annotations

import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from avflow.calibration import methods as M
from avflow.calibration.observe import SUMMARIES, member_cells, observe, score_member
from avflow.calibration.spec import Calibration, _levels, load_calibration, parse_calibration
from avflow.errors import AvflowError

__all__ = ["calibrate", "CalibrationResult"]


@dataclass
class CalibrationResult:
    """What :func:`calibrate` did; ``table`` has one row per model run."""

    calibration: Calibration
    table: object                   #: pandas.DataFrame
    best: dict                      #: parameter -> value of the run of least misfit
    outdir: Path
    posterior: object = None        #: methods.Posterior, or None
    identifiability: dict | None = None
    sobol: dict = field(default_factory=dict)
    cv: dict = field(default_factory=dict)
    emulators: dict = field(default_factory=dict)  #: quantity -> fitted GP (unit cube)
    timings: dict = field(default_factory=dict)
    written: list = field(default_factory=list)
    fit: dict | None = None         #: methods.goodness_of_fit of the best run
    checks: dict | None = None      #: methods.check_verdict of the posterior's check runs


class _Runner:
    """Runs batches of parameter points as ensembles into one OUTDIR, on one cluster."""

    def __init__(self, cal: Calibration, outdir: Path, workers, scheduler, quiet: bool):
        self.cal, self.outdir, self.quiet = cal, outdir, quiet
        self.workers, self.scheduler = workers, scheduler
        self.client = self.cluster = None
        self.n_workers = 1
        self.observed = None
        self.rows: list[dict] = []
        self.model_time = 0.0  #: s of wall time inside run_ensemble
        self.score_time = 0.0
        self.started = time.perf_counter()

    # -- where --------------------------------------------------------------------------
    def open(self) -> None:
        if self.scheduler:
            from avflow.ensemble.orchestrate import CONNECT_TIMEOUT, _connect

            self.client = _connect(self.scheduler, CONNECT_TIMEOUT)
        elif self.workers:
            self._local(self.workers)
        if self.client is not None:
            self.n_workers = max(1, len(self.client.scheduler_info(n_workers=-1)["workers"]))

    def _local(self, n: int) -> None:
        from distributed import Client

        from avflow.ensemble.orchestrate import start_local_cluster

        self.cluster = start_local_cluster(n).result()
        self.client = Client(self.cluster, set_as_default=False)
        self.n_workers = n

    def close(self) -> None:
        if self.client is not None and self.cluster is not None:
            self.client.close()
            self.cluster.close()
        elif self.client is not None:
            self.client.close()
        self.client = self.cluster = None

    def width(self) -> int:
        return self.cal.spec.batch or self.n_workers

    # -- runs ---------------------------------------------------------------------------
    def run(self, unit: np.ndarray, stage: str) -> list[dict]:
        """Run the unit-cube points ``unit`` (one member each) and score them."""
        from avflow.ensemble.orchestrate import ProgressLine, run_ensemble
        from avflow.ensemble.spec import Ensemble, Member

        cal = self.cal
        lo = np.array([b[0] for b in cal.bounds])
        hi = np.array([b[1] for b in cal.bounds])
        members, seen = [], {}
        for u in unit:
            values = lo + np.clip(u, 0.0, 1.0) * (hi - lo)
            # 9 significant digits: a hash that does not depend on the last bits of a float
            updates = {n: float(f"{v:.9g}") for n, v in zip(cal.names, values)}
            scenario = cal.base.with_updates(updates)
            digest = scenario.scenario_hash()
            if digest in seen:
                continue
            seen[digest] = True
            members.append(Member(len(members), scenario, updates, digest))
        ensemble = Ensemble(name=cal.name, path=None, text=cal.text, base=cal.base,
                            members=members, varied=list(cal.names))
        workers = 0 if self.client is None and (self.workers == 0 or self.rows) \
            else self.workers
        clock = time.perf_counter()
        # the runs' counter and time left on a terminal; the ensemble's notes left out
        line = ProgressLine(len(members), quiet=True, unit=f"{stage} runs")
        line.live = not self.quiet and sys.stderr.isatty()
        outcome = run_ensemble(ensemble, self.outdir, workers=workers, client=self.client,
                               progress=line, write_outputs=False, held_lock=True)
        self.model_time += time.perf_counter() - clock
        if self.client is None and self.workers is None and not self.rows \
                and outcome.where == "local cluster":
            # the machinery chose a cluster for the first design: keep one for the others
            self._local(os.cpu_count() or 1)
        clock = time.perf_counter()
        out = []
        for member, rec in zip(members, outcome.table.to_dict("records")):
            row = {"run": len(self.rows), "stage": stage, **member.updates,
                   "scenario_hash": member.scenario_hash, "status": rec["status"],
                   "error": rec.get("error", ""), "member_time": rec.get("member_time"),
                   "file": rec.get("file", "")}
            row.update(self._score(member, rec))
            self.rows.append(row)
            out.append(row)
        self.score_time += time.perf_counter() - clock
        self._progress()
        return out

    def _score(self, member, rec) -> dict:
        import xarray as xr

        if rec["status"] == "failed":  # missing, not zero
            return {"misfit": math.nan}
        path = self.outdir / rec["file"]
        try:
            with xr.open_dataset(path, decode_times=False, engine="netcdf4") as ds:
                cells = member_cells(ds)
        except Exception as err:  # noqa: BLE001 - scored as missing, said once
            print(f"avflow: warning: {path}: cannot be scored ({err}); counted as missing",
                  file=sys.stderr)
            return {"misfit": math.nan}
        if self.observed is None:
            self.observed = observe(self.cal, cells)
        return score_member(self.cal, self.observed, cells)

    def say(self, message: str) -> None:
        """A stage that takes a while without runs (emulators, posterior, report)."""
        if not self.quiet:
            print(f"calibration: {message} ({time.perf_counter() - self.started:.1f} s)",
                  file=sys.stderr, flush=True)

    def _progress(self) -> None:
        if self.quiet:
            return
        ok = [r for r in self.rows if math.isfinite(r.get("misfit", math.nan))]
        failed = len(self.rows) - len(ok)
        line = f"calibrate: {len(self.rows)} runs ({failed} missing)"
        if ok:
            best = min(ok, key=lambda r: r["misfit"])
            values = ", ".join(f"{n}={best[n]:.4g}" for n in self.cal.names)
            line += f", best misfit {best['misfit']:.4g} at {values}"
        line += f" ({time.perf_counter() - self.started:.1f} s)"
        print(line, file=sys.stderr, flush=True)

    # -- tables -------------------------------------------------------------------------
    def arrays(self, stages=None) -> tuple[np.ndarray, dict]:
        """Unit-cube design and columns (NaN where missing) of the runs of ``stages``."""
        rows = [r for r in self.rows if stages is None or r["stage"] in stages]
        lo = np.array([b[0] for b in self.cal.bounds])
        hi = np.array([b[1] for b in self.cal.bounds])
        X = np.array([[r[n] for n in self.cal.names] for r in rows], float)
        U = (X - lo) / (hi - lo)
        keys = {k for r in rows for k in r}
        cols = {k: np.array([_num(r.get(k)) for r in rows]) for k in keys
                if k not in ("stage", "scenario_hash", "status", "error", "file")}
        return U, cols


def _num(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def calibrate(calibration, outdir, *, workers: int | None = None,
              scheduler: str | None = None, quiet: bool = False,
              report: bool = True) -> CalibrationResult:
    """Calibrate the base scenario's parameters to the observations; write OUTDIR.

    ``calibration``: a calibration YAML file or a :class:`Calibration`. ``workers``: local
    dask worker processes (0: here, one run after the other; None: as ``avflow ensemble``
    chooses for the first design, kept for the rest); ``scheduler``: a running dask
    scheduler's address or file. Writes ``calibration.csv``, ``calibration.nc`` and (with
    ``report``) ``report.md`` and its PNGs, each atomically.
    """
    cal = calibration if isinstance(calibration, Calibration) else load_calibration(calibration)
    from avflow.files import check_folder, check_target, output_lock, protected

    outdir = check_folder(Path(outdir), "calibration folder")
    inputs = protected([cal.path, cal.base.source_path, *cal.files.values()])
    for name in ("calibration.nc", "calibration.csv", "report.md"):
        check_target(outdir / name, inputs, what="calibration output")
    from avflow.simulation.resources import check_resources

    check_resources(cal.base, streamed=True)  # every run's cells: the grid is not calibrated
    # the ensembles' lock: a second calibrate, or an ensemble, into this folder is refused
    with output_lock(outdir, folder=True, what="calibration folder"):
        return _calibrate(cal, outdir, workers, scheduler, quiet, report)


def _calibrate(cal: Calibration, outdir: Path, workers, scheduler, quiet: bool,
               report: bool) -> CalibrationResult:
    spec = cal.spec
    d = len(cal.names)
    runner = _Runner(cal, outdir, workers, scheduler, quiet)
    timings: dict = {}
    t_all = time.perf_counter()
    overhead = 0.0
    runner.open()
    limits = limit_blas_threads()
    try:
        method = spec.method
        design = spec.posterior.design if method == "posterior" else method
        if design == "grid":
            runner.run(M.grid_design(d, _levels(spec.budget, d)), "grid")
        elif design == "lhs":
            runner.run(M.lhs_design(d, spec.budget, spec.seed), "lhs")
        else:
            runner.run(M.lhs_design(d, cal.initial(), spec.seed), "initial")
            step, kernel = 0, None
            while len(runner.rows) < spec.budget:
                U, cols = runner.arrays()
                y = M.objective(cols["misfit"])
                if np.isfinite(y).sum() < 2:
                    raise AvflowError(f"{cal.path}: fewer than 2 runs of the initial design "
                                      "could be scored; see the failures above")
                clock = time.perf_counter()
                q = min(runner.width(), spec.budget - len(runner.rows))
                # hyper-parameters from the last batch's, searched afresh every 5th
                batch, kernel = M.propose_batch(U, y, q, spec.seed + 1 + step,
                                                None if step % 5 == 0 else kernel)
                overhead += time.perf_counter() - clock
                if not len(batch):
                    if not quiet:
                        print(f"calibrate: the range is covered at {M.MIN_SPACING:.0%} "
                              "spacing: stopping before the budget", file=sys.stderr)
                    break
                runner.run(batch, "bayes-opt")
                step += 1
        timings["acquisition"] = overhead
        result = _analyse(cal, runner, outdir, timings)
        overhead += timings.get("emulators", 0.0) + timings.get("posterior", 0.0) \
            + timings.get("sobol", 0.0)
    finally:
        limits.restore_original_limits()
        runner.close()
    timings.update(model_runs=runner.model_time, scoring=runner.score_time,
                   overhead=overhead, total=time.perf_counter() - t_all)
    result.timings = timings
    from avflow.calibration.outputs import write_outputs

    runner.say("writing the tables" + (" and the report" if report else ""))
    result.written = write_outputs(result, report=report)
    where = outdir / ("report.md" if report else "calibration.nc")
    if result.fit is not None and not result.fit["fits"]:
        print(f"avflow: warning: the model cannot reproduce the observations within their "
              f"errors (best misfit {result.fit['chi2']:.4g}, at most "
              f"{result.fit['limit']:.3g} expected): no parameter is calibrated; see "
              f"{where}", file=sys.stderr)
    elif result.checks is not None and result.checks["flagged"]:
        print("avflow: warning: the model runs at posterior draws fit worse than the best "
              f"design run: the posterior is not confirmed; see {where}", file=sys.stderr)
    zcols = [c for c in result.table.columns if c.endswith("_d_z")]
    far = int((result.table[zcols].abs() > 3.0).to_numpy().sum()) if zcols else 0
    if far:
        print(f"avflow: warning: {far} check-run discrepancies lie more than 3 emulator "
              f"standard deviations from the emulator; see {where}", file=sys.stderr)
    return result


def limit_blas_threads():
    """One thread for every BLAS the calibration uses, returned as a threadpoolctl limiter
    (``restore_original_limits()`` undoes it). threadpoolctl limits the libraries already
    loaded only, so numpy's and scipy's (each wheel brings its own OpenBLAS) are loaded
    first: the GP's small matrices gain nothing from more threads and lose up to 10x to
    idle pools on a busy machine."""
    import scipy.linalg  # noqa: F401 - loads scipy's OpenBLAS before the limit
    import sklearn.gaussian_process  # noqa: F401 - and what scikit-learn links
    from threadpoolctl import threadpool_limits

    return threadpool_limits(1, user_api="blas")


def _analyse(cal: Calibration, runner: _Runner, outdir: Path, timings: dict
             ) -> CalibrationResult:
    """Emulators, cross-validation, posterior with its check runs, Sobol indices."""
    import pandas as pd

    spec = cal.spec
    U, cols = runner.arrays()
    misfit = cols["misfit"]
    if not np.isfinite(misfit).any():
        raise AvflowError(f"{cal.path}: no run could be scored (every member failed); "
                          "see the failures above")
    scored = misfit[np.isfinite(misfit)]
    if scored.size > 1 and float(np.ptp(scored)) == 0.0:
        # no run is better than another: the first one would be called the best fit
        raise AvflowError(f"{cal.path}: every run has the same misfit ({scored[0]:.6g}): "
                          "the observations do not tell the parameters apart (an observed "
                          "area or point that no run reaches?); no best fit. Check the "
                          "observations against the base scenario's map")
    ib = int(np.nanargmin(misfit))
    best = {n: runner.rows[ib][n] for n in cal.names}
    result = CalibrationResult(cal, None, best, outdir)
    n_ok = int(np.isfinite(misfit).sum())
    quantities = [f"{cal.label(k)}_d" for k in range(len(spec.observations))]
    emulators = {}
    if n_ok >= 4:
        runner.say(f"fitting the emulators to {n_ok} runs")
        clock = time.perf_counter()
        for q in ["sqrt_misfit", *quantities, *SUMMARIES]:
            y = M.objective(cols["misfit"]) if q == "sqrt_misfit" else cols[q]
            if np.isfinite(y).sum() >= 4:
                emulators[q] = M.fit_gp(U, y, spec.seed)
                result.cv[q] = M.cross_validate(U, y, spec.seed,
                                                kernel=emulators[q].kernel_)
        timings["emulators"] = time.perf_counter() - clock
    result.emulators = emulators
    if spec.method == "posterior" and all(q in emulators for q in quantities):
        runner.say(f"sampling the posterior ({spec.posterior.walkers} walkers x "
                   f"{spec.posterior.steps} steps)")
        clock = time.perf_counter()
        errors = [cal.error(k) for k in range(len(spec.observations))]
        weights = [o.weight for o in spec.observations]
        post = M.sample_posterior([emulators[q] for q in quantities], errors, weights,
                                  cal.bounds, U[ib], spec.posterior.walkers,
                                  spec.posterior.steps, spec.posterior.burn, spec.seed)
        result.posterior = post
        result.identifiability = M.identifiability(post.draws, cal.names, cal.bounds)
        timings["posterior"] = time.perf_counter() - clock
        if spec.posterior.checks:
            rng = np.random.default_rng(spec.seed)
            pick = rng.choice(len(post.draws), size=min(spec.posterior.checks,
                                                        len(post.draws)), replace=False)
            lo = np.array([b[0] for b in cal.bounds])
            hi = np.array([b[1] for b in cal.bounds])
            uc = (post.draws[pick] - lo) / (hi - lo)
            rows = runner.run(uc, "check")
            for row, u in zip(rows, uc):
                for q in quantities:
                    m, s = emulators[q].predict(u[None, :], return_std=True)
                    row[f"{q}_emulated"], row[f"{q}_emulated_sd"] = float(m[0]), float(s[0])
                    # the model's value in emulator standard deviations from its mean
                    row[f"{q}_z"] = ((row.get(q, math.nan) - float(m[0]))
                                     / max(float(s[0]), 1e-300))
            result.checks = M.check_verdict([r["misfit"] for r in rows],
                                            float(misfit[ib]), len(cal.names))
    result.fit = M.goodness_of_fit(float(misfit[ib]), len(spec.observations))
    if result.identifiability is not None and (
            not result.fit["fits"] or (result.checks or {}).get("flagged")):
        # a posterior of a model that cannot fit, or that its own check runs contradict,
        # constrains nothing: the widths are kept, the verdicts withdrawn
        ident = result.identifiability
        ident["withheld"] = ("the model cannot reproduce the observations within their "
                             "errors" if not result.fit["fits"] else
                             "the model runs at posterior draws fit worse than the best "
                             "design run")
        ident["constrained"] = {n: False for n in ident["constrained"]}
    if spec.sensitivity.enabled and emulators:
        runner.say("Sobol indices of the emulators")
        clock = time.perf_counter()
        for q in ["sqrt_misfit", *quantities, *SUMMARIES]:
            if q in emulators:
                gp = emulators[q]
                result.sobol[q] = M.sobol_indices(gp.predict, cal.names, spec.sensitivity.n,
                                                  spec.seed)
        timings["sobol"] = time.perf_counter() - clock
    result.table = pd.DataFrame.from_records(runner.rows)
    return result
