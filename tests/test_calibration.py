"""avflow calibrate (issue 28): scores on hand-computed numbers, bad calibration files, the
recovery of a known truth by bayes-opt and its posterior, identifiability of mu against xi
from the runout alone, failures scored as missing, resume.

The scene: a 2 km trough (32 degree slope easing to flat from x = 600 to 1000 m) at 20 m
cells, a 100 m x 100 m box 4 m thick, Voellmy mu = 0.25, xi = 1500 m/s^2; a run takes
0.03-0.05 s of time loop (2-core EPYC).
"""

import math
import os

import numpy as np
import pytest
import xarray as xr

from avflow.calibration import scores as S
from avflow.calibration.methods import identifiability
from avflow.calibration.spec import CalibrationError, load_calibration
from avflow.cli import main

TRUTH = {"rheology.mu": 0.25, "rheology.xi": 1500.0}
DX = 20.0

# =========================================================================================
# Scores on hand-computed numbers
# =========================================================================================


def test_confusion_and_area_scores_by_hand():
    # 10 domain cells (the 11th is outside the domain and must not count)
    sim = np.array([1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 1], bool)
    obs = np.array([1, 1, 0, 0, 1, 0, 0, 0, 0, 0, 1], bool)
    domain = np.array([1] * 10 + [0], bool)
    c = S.confusion(sim, obs, domain)
    assert (c.tp, c.fp, c.fn, c.tn) == (2, 2, 1, 5)  # TN: domain cells outside both
    assert S.csi(c) == pytest.approx(2 / 5)
    assert S.f1(c) == pytest.approx(4 / 7)
    assert S.tversky(c, 0.5, 0.5) == pytest.approx(S.f1(c))
    assert S.tversky(c, 1.0, 1.0) == pytest.approx(S.csi(c))
    assert S.tversky(c, 0.7, 0.3) == pytest.approx(2 / (2 + 1.4 + 0.3))
    assert math.isnan(S.csi(S.confusion(np.zeros(3, bool), np.zeros(3, bool))))


def test_auroc_by_hand():
    # obs: cells 0, 1; values rank them 1st and 3rd of 4: of the 2 x 2 (pos, neg) pairs,
    # 3 are ordered right -> AUROC = 3/4
    values = np.array([5.0, 2.0, 3.0, 1.0])
    obs = np.array([True, True, False, False])
    assert S.auroc(values, obs) == pytest.approx(0.75)
    # no flow (NaN) ranks below every value: cell 1 now below both negatives -> 2/4
    assert S.auroc(np.array([5.0, np.nan, 3.0, 1.0]), obs) == pytest.approx(0.5)
    assert math.isnan(S.auroc(values, np.ones(4, bool)))
    sc = S.area_scores(values, 2.5, obs)
    assert (sc["tp"], sc["fp"], sc["fn"], sc["tn"]) == (1, 1, 1, 1)


def test_runout_rmse_misfit_by_hand():
    assert S.runout_difference(950.0, 940.0) == 10.0
    assert S.runout_difference(900.0, 940.0) == -40.0
    h_sim = np.array([0.0, 1.0, 2.0, 0.05, np.nan])
    h_obs = np.array([0.0, 2.0, 2.0, 0.0, 0.5])
    # union of >= 0.1: cells 1, 2, 4 (sim NaN = 0): errors 1, 0, 0.5
    assert S.rmse_union(h_sim, h_obs, 0.1) == pytest.approx(math.sqrt((1 + 0 + 0.25) / 3))
    assert S.misfit([10.0, 0.1], [20.0, 0.05], [1.0, 2.0]) == pytest.approx(0.25 + 8.0)
    assert math.isnan(S.misfit([np.nan, 0.1], [20.0, 0.05]))  # missing, not zero
    ll = S.log_likelihood([10.0], [20.0])
    assert ll == pytest.approx(-0.125 - math.log(20.0 * math.sqrt(2 * math.pi)))


def test_identifiability_rule():
    rng = np.random.default_rng(0)
    bounds = [(0.1, 0.5), (500.0, 4000.0)]
    t = rng.uniform(0, 1, 4000)
    ridge = np.column_stack([0.1 + 0.4 * t, 500 + 3500 * t + rng.normal(0, 100, t.size)])
    out = identifiability(ridge, ["mu", "xi"], bounds)
    assert out["ridges"] and out["ridges"][0][:2] == ("mu", "xi")
    point = np.column_stack([rng.normal(0.25, 0.005, 4000), rng.normal(1500, 50, 4000)])
    out = identifiability(point, ["mu", "xi"], bounds)
    assert not out["ridges"] and all(out["constrained"].values())


# =========================================================================================
# The scene and its synthetic observation
# =========================================================================================


def _dem(path, wkt=None):
    from avflow.terrain.raster import write_asc

    x = np.arange(0, 2000 + DX / 2, DX)
    y = np.arange(0, 400 + DX / 2, DX)
    s = np.tan(np.radians(32)) * 0.5 * (1 + np.cos(np.pi * np.clip((x - 600) / 400, 0, 1)))
    z = -np.concatenate([[0], np.cumsum(0.5 * (s[1:] + s[:-1]) * DX)])
    z = z - z.min()
    X, Y = np.meshgrid(x, y)
    write_asc(path, np.broadcast_to(z, X.shape) + 0.02 * (Y - 200) ** 2 / 200, x, y, wkt)


BASE = """name: trough-voellmy
terrain: {kind: dem, path: dem.asc}
grid: {dx: 20.0}
release: {kind: box, x: [100.0, 200.0], y: [150.0, 250.0], thickness: 4.0}
rheology: {law: voellmy, mu: 0.25, xi: 1500.0}
time: {end: 200.0, cfl: 0.5}
output: {every: 10.0, stop_rule: kinetic_energy}
"""


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """DEM, base scenario, and the truth run's area above 1 kPa, deposit and runout."""
    import avflow
    from avflow.output.path import analyse_run, read_line
    from avflow.terrain.raster import write_tif

    root = tmp_path_factory.mktemp("scene")
    _dem(root / "dem.asc")
    (root / "base.yaml").write_text(BASE)
    (root / "line.csv").write_text("x,y\n0,200\n2000,200\n")
    ds = avflow.run(root / "base.yaml")
    x, y = ds.x.values, ds.y.values
    write_tif(root / "impact.tif", (ds.peak_pressure.values >= 1e3).astype(float), x, y)
    write_tif(root / "deposit.tif", np.nan_to_num(ds.deposit_thickness.values), x, y)
    _, res = analyse_run(ds, line=read_line(root / "line.csv"))
    return root, res.scalars["runout_x"]


def _calib(root, body, name="calib.yaml"):
    path = root / name
    path.write_text("base: base.yaml\nparameters:\n  rheology.mu: [0.1, 0.5]\n"
                    "  rheology.xi: [500.0, 4000.0]\n" + body)
    return path


def _runout(x):
    return (f"  - {{kind: runout, name: runout, point: [{x}, 200.0], line: line.csv, "
            "error: 20.0}\n")


# =========================================================================================
# Bad files: one line, file:line:col and field, exit 2, nothing run
# =========================================================================================


@pytest.mark.parametrize("body, where, words", [
    ("observations:\n  - {kind: area, raster: impact.tif, scor: csi}\n", ":6:", "scor"),
    ("observations:\n  - {kind: area, raster: nothere.tif}\n", ":6:",
     "observations.0.raster: file not found"),
    ("observations:\n  - {kind: volume, raster: impact.tif}\n", ":6:", "kind must be one of"),
    ("observations:\n  - {kind: runout, point: [5000.0, 200.0], line: line.csv}\n", ":6:",
     "observations.0.point: [5000.0, 200.0] lies outside the map"),
    ("observations:\n  - {kind: area, raster: impact.tif, threshold: -1}\n", ":6:",
     "observations.0.threshold"),
    ("observations:\n  - {kind: runout, point: [900.0, 200.0]}\n", ":6:",
     "observations.0.line: required on a map"),
    ("observations:\n  - {kind: area, raster: impact.tif}\nmethod: annealing\n", ":7:",
     "method"),
])
def test_bad_files_one_line_exit_2(scene, capsys, body, where, words):
    root, _ = scene
    path = _calib(root, body, "bad.yaml")
    out = root / "bad_out"
    code = main(["calibrate", str(path), "-o", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1, err
    assert "bad.yaml" + where in err and words in err, err
    assert not out.exists()  # nothing run, nothing written


def test_bad_range_and_unknown_parameter(scene):
    root, _ = scene
    path = root / "bad2.yaml"
    path.write_text("base: base.yaml\nparameters:\n  rheology.mu: [0.5, 0.1]\n"
                    "observations:\n  - {kind: area, raster: impact.tif}\n")
    with pytest.raises(CalibrationError, match=r"bad2.yaml:3:\d+: parameters.rheology.mu: "
                                               "must be \\[min, max\\] with min < max"):
        load_calibration(path)
    path.write_text("base: base.yaml\nparameters:\n  rheology.muu: [0.1, 0.5]\n"
                    "observations:\n  - {kind: area, raster: impact.tif}\n")
    with pytest.raises(CalibrationError, match=r"bad2.yaml:3:\d+: parameters.rheology.muu: "
                                               "rheology.muu: unknown field"):
        load_calibration(path)
    path.write_text("base: base.yaml\nparameters:\n  grid.dx: [10.0, 20.0]\n"
                    "observations:\n  - {kind: area, raster: impact.tif}\n")
    with pytest.raises(CalibrationError, match=r"bad2.yaml:3:\d+: parameters.grid.dx: the "
                                               "grid and the terrain cannot be calibrated"):
        load_calibration(path)


def test_observation_in_another_crs_is_refused(tmp_path):
    from pyproj import CRS

    from avflow.terrain.raster import write_tif

    _dem(tmp_path / "dem.asc", CRS.from_epsg(31287).to_wkt())
    (tmp_path / "base.yaml").write_text(BASE)
    x = np.arange(0, 2000 + DX / 2, DX)
    y = np.arange(0, 400 + DX / 2, DX)
    write_tif(tmp_path / "impact.tif", np.ones((y.size, x.size)), x, y,
              CRS.from_epsg(32632).to_wkt())
    path = _calib(tmp_path, "observations:\n  - {kind: area, raster: impact.tif}\n")
    with pytest.raises(CalibrationError, match="observations.0.raster: is in another CRS"):
        load_calibration(path)


# =========================================================================================
# Recovery of a known truth; the posterior covers it; outputs
# =========================================================================================


@pytest.fixture(scope="module")
def recovered(scene):
    from avflow.calibration import calibrate

    root, runout_x = scene
    path = _calib(root, "observations:\n" + _runout(runout_x)
                  + "  - {kind: area, name: impact, raster: impact.tif, error: 0.02}\n"
                  "  - {kind: deposit, name: deposit, raster: deposit.tif, error: 0.05}\n"
                  "method: posterior\nbudget: 40\nseed: 1\n"
                  "posterior: {walkers: 16, steps: 1500, burn: 500, checks: 3}\n"
                  "sensitivity: {n: 256}\n", "recover.yaml")
    return calibrate(path, root / "recover", workers=0, quiet=True), root / "recover"


def test_bayes_opt_recovers_the_truth_in_40_runs(recovered):
    result, _ = recovered
    t = result.table
    design = t[t["stage"].isin(["initial", "bayes-opt"])]
    assert len(design) <= 40
    best = design.loc[design["misfit"].idxmin()]
    assert abs(best["rheology.mu"] - TRUTH["rheology.mu"]) <= 0.02
    assert abs(best["runout_d"]) <= DX  # within one cell
    assert result.best["rheology.mu"] == best["rheology.mu"]


def test_posterior_covers_the_truth(recovered):
    result, _ = recovered
    q05, q95 = np.quantile(result.posterior.draws, [0.05, 0.95], axis=0)
    for k, name in enumerate(result.calibration.names):
        assert q05[k] <= TRUTH[name] <= q95[k], (name, q05[k], q95[k])
    assert len(result.table[result.table["stage"] == "check"]) == 3  # re-run at draws


def test_outputs_readable_with_provenance(recovered):
    result, out = recovered
    with xr.open_dataset(out / "calibration.nc") as ds:
        assert ds.attrs["Conventions"] == "CF-1.11"
        assert "impact.tif sha256:" in ds.attrs["observation_files"]
        from avflow.ensemble.orchestrate import file_sha256

        assert file_sha256(out.parent / "impact.tif") in ds.attrs["observation_files"]
        assert ds["design"].shape == (len(result.table), 2)
        assert ds["posterior"].shape[1] == 2
        assert np.isfinite(ds["sobol_ST"].values).all()
        assert ds["emulated_misfit_0_1"].shape == (41, 41)
    text = (out / "report.md").read_text()
    for png in ("misfit_pairs", "footprint", "posterior_corner", "sobol"):
        assert f"report/{png}.png" in text
        assert (out / "report" / f"{png}.png").stat().st_size > 10_000
    assert (out / "calibration.csv").read_text().count("\n") == len(result.table) + 1
    assert len(list((out / "members").glob("*.nc"))) == len(result.table)
    assert not list(out.glob(".*.tmp"))


def test_rerun_resumes_every_member(scene):
    """bayes-opt is deterministic given the file: a rerun proposes the same points and
    finds every member in members/ (none is run again)."""
    from avflow.calibration import calibrate

    root, runout_x = scene
    path = _calib(root, "observations:\n" + _runout(runout_x)
                  + "  - {kind: area, name: impact, raster: impact.tif, error: 0.02}\n"
                  "method: bayes-opt\nbudget: 10\ninitial: 6\nbatch: 2\nseed: 4\n"
                  "sensitivity: {enabled: false}\n", "resume.yaml")
    out = root / "resume"
    first = calibrate(path, out, workers=0, quiet=True)
    stamps = {p: p.stat().st_mtime_ns for p in (out / "members").glob("*.nc")}
    assert len(stamps) == 10
    again = calibrate(path, out, workers=0, quiet=True)
    assert list(again.table["scenario_hash"]) == list(first.table["scenario_hash"])
    assert {p: p.stat().st_mtime_ns for p in (out / "members").glob("*.nc")} == stamps


# =========================================================================================
# Identifiability: the runout alone does not separate mu and xi
# =========================================================================================


def test_runout_alone_does_not_separate_mu_and_xi(scene):
    from avflow.calibration import calibrate

    root, runout_x = scene
    path = _calib(root, "observations:\n" + _runout(runout_x)
                  + "method: posterior\nbudget: 20\nseed: 2\n"
                  "posterior: {walkers: 16, steps: 1500, burn: 500, checks: 0}\n"
                  "sensitivity: {enabled: false}\n", "runout_only.yaml")
    result = calibrate(path, root / "runout_only", workers=0, quiet=True)
    assert result.identifiability["ridges"], result.identifiability
    text = (root / "runout_only" / "report.md").read_text()
    assert "The data do not separate rheology.mu and rheology.xi" in text


# =========================================================================================
# A failed member is missing, not zero
# =========================================================================================


def test_failed_member_scored_as_missing(scene, monkeypatch):
    import avflow.ensemble.orchestrate as orchestrate
    from avflow.calibration import calibrate

    root, runout_x = scene
    real = orchestrate.run_member

    def flaky(text, out, *args, **kwargs):
        """The member's record when its run raises (as run_member makes it), for mu < 0.2."""
        import yaml

        if yaml.safe_load(text)["rheology"]["mu"] < 0.2:
            row = {n: math.nan for n in orchestrate.SUMMARY_FIELDS}
            row.update(status="failed", steps=0, error="RunFailed: injected",
                       reused=False, member_time=0.0)
            return row
        return real(text, out, *args, **kwargs)

    monkeypatch.setattr(orchestrate, "run_member", flaky)
    path = _calib(root, "observations:\n" + _runout(runout_x)
                  + "method: lhs\nbudget: 8\nseed: 3\nsensitivity: {enabled: false}\n",
                  "flaky.yaml")
    result = calibrate(path, root / "flaky", workers=0, quiet=True)
    t = result.table
    failed = t[t["rheology.mu"] < 0.2]
    assert len(failed) > 0 and (failed["status"] == "failed").all()
    assert failed["misfit"].isna().all()  # missing, not zero
    assert t[t["rheology.mu"] >= 0.2]["misfit"].notna().all()
    assert result.best["rheology.mu"] >= 0.2
    assert "Failed runs (missing)" in (root / "flaky" / "report.md").read_text()


# =========================================================================================
# Forecast: an ensemble sampling a calibration's posterior, with provenance
# =========================================================================================


def test_ensemble_samples_the_posterior_with_provenance(recovered):
    from avflow.ensemble.orchestrate import file_sha256

    result, out = recovered
    root = out.parent
    (root / "forecast.yaml").write_text(
        "name: trough-forecast\nbase: base.yaml\nvary:\n  release.volume_factor: [1.0, 1.5]\n"
        "sample:\n  calibration: recover/calibration.nc\n  n: 3\n  seed: 0\n")
    assert main(["ensemble", str(root / "forecast.yaml"), "-o", str(root / "fc"),
                 "--workers", "0", "-q"]) == 0
    with xr.open_dataset(root / "fc" / "ensemble.nc") as ds:
        assert ds.sizes["realization"] == 6
        assert ds.attrs["calibration_file"] == str(out / "calibration.nc")
        assert ds.attrs["calibration_sha256"] == file_sha256(out / "calibration.nc")
        assert ds.attrs["calibration_use"] == "posterior"
        draws = result.posterior.draws
        for mu, xi in zip(ds["rheology_mu"].values, ds["rheology_xi"].values):
            same = (np.isclose(draws[:, 0], mu, rtol=1e-8, atol=0)
                    & np.isclose(draws[:, 1], xi, rtol=1e-8, atol=0))
            assert same.any()  # a draw of the posterior (to 9 digits)


def test_forecast_from_a_calibration_without_posterior_is_refused(scene, capsys):
    root, runout_x = scene
    path = _calib(root, "observations:\n" + _runout(runout_x)
                  + "method: lhs\nbudget: 4\nsensitivity: {enabled: false}\n", "lhs.yaml")
    assert main(["calibrate", str(path), "-o", str(root / "lhs"), "--workers", "0",
                 "-q"]) == 0
    capsys.readouterr()
    (root / "fc2.yaml").write_text("base: base.yaml\nsample:\n  calibration: "
                                   "lhs/calibration.nc\n  n: 3\n")
    assert main(["ensemble", str(root / "fc2.yaml"), "-o", str(root / "fc2")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "fc2.yaml:3:" in err
    assert "holds no posterior draws (method lhs): use: best" in err
    (root / "fc2.yaml").write_text("base: base.yaml\nsample:\n  calibration: "
                                   "lhs/calibration.nc\n  use: best\n")
    assert main(["ensemble", str(root / "fc2.yaml"), "-o", str(root / "fc2"), "--workers",
                 "0", "-q"]) == 0


# =========================================================================================
# On dask: batches as wide as the workers; on a profile: station and interval
# =========================================================================================


def test_bayes_opt_batches_on_a_local_cluster(scene, capsys):
    root, runout_x = scene
    path = _calib(root, "observations:\n" + _runout(runout_x)
                  + "  - {kind: area, name: impact, raster: impact.tif, error: 0.02}\n"
                  "method: bayes-opt\nbudget: 8\ninitial: 4\nseed: 0\n"
                  "sensitivity: {enabled: false}\n", "dask.yaml")
    assert main(["calibrate", str(path), "-o", str(root / "dask"), "--workers", "2"]) == 0
    err = capsys.readouterr().err
    progress = [line for line in err.splitlines() if line.startswith("calibrate:")]
    # the initial design, then two batches of two (one run per worker)
    assert [line.split(" runs")[0] for line in progress] == [
        "calibrate: 4", "calibrate: 6", "calibrate: 8"]
    assert "best misfit" in progress[-1]
    import pandas as pd

    table = pd.read_csv(root / "dask" / "calibration.csv")
    assert list(table["stage"]) == ["initial"] * 4 + ["bayes-opt"] * 4
    assert table["misfit"].notna().all()


def test_profile_station_and_interval(tmp_path):
    """The seed's exponential slope at 25 m (Coulomb 20 deg): its runout x and its
    1 kPa interval as the observation; delta recovered within 0.5 degree in 10 runs."""
    import avflow
    from avflow.calibration import calibrate
    from conftest import SCENARIOS

    text = (SCENARIOS / "seed_exponential_coulomb20.yaml").read_text()
    (tmp_path / "prof.yaml").write_text(text.replace("dx: 6.25", "dx: 25.0"))
    ds = avflow.run(tmp_path / "prof.yaml")
    x = ds.x_horizontal.values[ds.peak_pressure.values >= 1e3]
    (tmp_path / "c.yaml").write_text(
        "base: prof.yaml\nparameters:\n  rheology.delta_deg: [15.0, 25.0]\nobservations:\n"
        f"  - {{kind: runout, station: {x.max()}, error: 25.0}}\n"
        f"  - {{kind: area, interval: [{x.min()}, {x.max()}], score: csi}}\n"
        "method: bayes-opt\nbudget: 10\ninitial: 5\nsensitivity: {enabled: false}\n")
    result = calibrate(tmp_path / "c.yaml", tmp_path / "out", workers=0, quiet=True)
    assert abs(result.best["rheology.delta_deg"] - 20.0) <= 0.5
    best = result.table.loc[result.table["misfit"].idxmin()]
    assert abs(best["runout0_d"]) <= 25.0 and best["area1_csi"] > 0.95
    assert "edge of the range" not in (tmp_path / "out" / "report.md").read_text()
    # a range that stops short of the truth: the best run is on its edge, and the report says
    text = (tmp_path / "c.yaml").read_text().replace("[15.0, 25.0]", "[15.0, 19.0]")
    (tmp_path / "c.yaml").write_text(text.replace("method: bayes-opt\nbudget: 10\ninitial: 5",
                                                  "method: grid\nbudget: 3"))
    result = calibrate(tmp_path / "c.yaml", tmp_path / "edge", workers=0, quiet=True)
    assert list(result.table["rheology.delta_deg"]) == [15.0, 17.0, 19.0]
    assert result.best["rheology.delta_deg"] == 19.0
    assert ("The best fit lies at the edge of the range of rheology.delta_deg"
            in (tmp_path / "edge" / "report.md").read_text())


def test_points_observation_scores_the_nearest_cells(scene):
    """Peak speed and arrival time at points: d = RMSE at the nearest cells; 0 for the truth
    run itself, and the offset when every observed value is off by it."""
    import avflow
    from avflow.calibration.observe import member_cells, observe, score_member

    root, _ = scene
    ds = avflow.run(root / "base.yaml")
    pts = [(300.0, 200.0), (514.0, 195.0)]  # the second nearest to the cell (520, 200)
    cells = [(300.0, 200.0), (520.0, 200.0)]
    speed = [float(ds.peak_speed.sel(x=x, y=y)) for x, y in cells]
    arrival = [float(ds.arrival_time.sel(x=x, y=y)) for x, y in cells]
    path = _calib(root, "observations:\n"
                  f"  - {{kind: points, name: v, points: {[list(p) for p in pts]}, "
                  f"values: {speed}}}\n"
                  f"  - {{kind: points, name: t, field: arrival_time, points: "
                  f"{[list(p) for p in pts]}, values: {[a + 3.0 for a in arrival]}}}\n",
                  "points.yaml")
    cal = load_calibration(path)
    assert cal.error(0) == 1.0 and cal.error(1) == 5.0  # the stated defaults
    c = member_cells(ds)
    row = score_member(cal, observe(cal, c), c)
    assert row["v_d"] == pytest.approx(0.0, abs=1e-12)
    assert row["t_d"] == pytest.approx(3.0, rel=1e-9)
    assert row["misfit"] == pytest.approx((3.0 / 5.0) ** 2, rel=1e-9)
    path.write_text(path.read_text().replace("values: [", "values: [1.0, ", 1))
    with pytest.raises(CalibrationError, match=r"observations.0: values must have one value "
                                               "per point"):
        load_calibration(path)


def test_fast_predictor_is_the_gp_itself():
    from avflow.calibration.methods import fast_predictor, fit_gp

    rng = np.random.default_rng(1)
    X = rng.uniform(size=(30, 2))
    gp = fit_gp(X, np.sin(4 * X[:, 0]) * 50 + 3 * X[:, 1] + 7.0)
    U = rng.uniform(size=(17, 2))
    m0, s0 = gp.predict(U, return_std=True)
    m1, s1 = fast_predictor(gp)(U)
    np.testing.assert_allclose(m1, m0, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(s1, s0, rtol=1e-9, atol=1e-12)
