"""avflow beside AvaFrame com1DFA on AvaFrame's own paths.

    python workflows/compare_avaframe.py --avaframe-python /work/avaframe_venv/bin/python
    python workflows/compare_avaframe.py --avaframe-results /work/avaframe_ref   # stored runs
    python workflows/compare_avaframe.py --quick                                 # 10 m smoke test

For avaKot and avaHit (``--paths``), for Coulomb 20 deg, Voellmy (mu 0.155, xi 4000) and
samosAT (``--laws``), at ``--dx`` (5 m), with the same DEM and release polygon (those of
``scenarios/avakot_coulomb.yaml`` / ``avahit_coulomb.yaml``), density 200 kg/m^3 and
tEnd 400 s on both sides, runs AvaFrame com1DFA then avflow, one after the other, and writes
into ``--out`` (default ``out/compare_avaframe``):

- ``compare.csv`` and ``compare.md``: one row per model and case (printed too);
- ``<path>_<law>.png``: AvaFrame's and avflow's peak thickness side by side (log colour
  scale over a hillshade with 100 m contours, same extent), and where their footprints
  (peak thickness > 0.01 m) overlap.

AvaFrame is not a dependency of avflow. It is run in this process when ``import avaframe``
works, else by the Python interpreter given with ``--avaframe-python`` or ``$AVAFRAME_PYTHON``
(a venv where ``pip install avaframe`` was done) through a small script written to
``OUT/avaframe/run_com1dfa.py``; else, with ``--avaframe-results DIR``, from stored runs
(``DIR/<path>_<law>/<path>_<law>_pft.asc``, ``..._pfv.asc``, ``<path>_DEM5m_remeshed.asc`` and
``DIR/results.csv``, as written by /work/avaframe_ref/analyze.py); else only avflow's rows.
AvaFrame's settings are its defaults (dt 0.1 s, SPH, curvature in the friction, stop when the
kinetic energy is 1% of its peak) except: meshCellSize = dx, rho 200, the release thickness
from the shapefile, the friction law. samosAT uses AvaFrame's standard ("large") parameters;
the row is skipped with a note when avflow has no ``law: samosat``.

Definitions, the same for both models, each on its own output grid (AvaFrame's rasters are
read as written; avflow's from :func:`avflow.output.dataset.to_dataset`):

- footprint(thr): cells whose peak thickness exceeds thr (0.01 or 0.1 m); its area is the
  number of such cells times the planimetric cell area (dx dy);
- runout: the largest horizontal distance from the release polygon (the shapefile, 0 inside)
  to the centre of a footprint(0.01) cell;
- travel angle: atan(drop / length) from the highest bed point inside the release polygon
  to the footprint(0.01) cell farthest from it horizontally;
- overlap: intersection over union of the footprints on avflow's grid, AvaFrame's peak
  thickness taken at each avflow cell centre from the nearest AvaFrame cell;
- max peak thickness and speed: the largest values of the two peak maps (AvaFrame's pfv is
  the particle speed, avflow's the speed along the bed);
- released and final volume: AvaFrame's initial and final mass / rho; avflow's release and
  final volume on the map;
- wall time: AvaFrame's own computation time (com1DFACore: initialisation and time loop);
  avflow's simulate() call (terrain, release, time loop), with Numba already compiled.

``--no-curvature`` runs both models without the bed-curvature term in the friction
(AvaFrame ``curvAccInFriction = 0``, avflow ``terrain.curvature: false``; rows and files
named ``<law>_nocurv``): a study that separates the curvature estimate from the rest.
``--avaframe-set KEY=VALUE`` changes one com1DFA [GENERAL] key of the live AvaFrame runs
(e.g. ``viscOption=0``: no artificial viscosity), for studies.

avflow is run with its default stop rule (``output.stop_rule: moving_volume``, the reported
row) and again with ``kinetic_energy`` (AvaFrame's rule; wall time, steps, end time and
footprint overlap in the CSV's ``ke_*`` columns and in the markdown's last column).
"""

from __future__ import annotations

import argparse
import csv
import importlib.util
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
PATHS = {"avakot": ("avaKot", "scenarios/avakot_coulomb.yaml"),
         "avahit": ("avaHit", "scenarios/avahit_coulomb.yaml")}
LAWS = {
    "coulomb": {"law": "coulomb", "delta_deg": 20.0},
    "voellmy": {"law": "voellmy", "mu": 0.155, "xi": 4000.0},
    "samosat": {"law": "samosat"},  # avflow's defaults: AvaFrame's standard parameters
}
RHO = 200.0  # kg/m^3, AvaFrame's snow density, on both sides
T_END = 400.0  # s, AvaFrame's tEnd, on both sides
THRESHOLDS = (0.01, 0.1)  # m of peak thickness
LOG_FLOOR = 0.01  # m: lower end of the colour scale (the footprint threshold)

# The AvaFrame side: one com1DFA run per call, in whatever Python has avaframe. This is
# /work/avaframe_ref/run_ref.py's setup (default configuration, a few keys overridden); no
# AvaFrame code is copied. ``run(job)`` writes ``job["json_out"]`` and returns the same dict.
AVAFRAME_SCRIPT = r'''
"""One AvaFrame com1DFA run for avflow's workflows/compare_avaframe.py.

    python run_com1dfa.py JOB.json
"""
import json
import pathlib
import shutil
import sys
import time


def run(job):
    from importlib.metadata import version
    from avaframe.in3Utils import cfgUtils, logUtils
    import avaframe.in3Utils.initializeProject as initProj
    from avaframe.com1DFA import com1DFA

    ava = pathlib.Path(job["ava_dir"])
    if ava.exists():
        shutil.rmtree(ava)
    initProj.initializeFolderStruct(str(ava))
    dem = pathlib.Path(job["dem"])
    shutil.copy(dem, ava / "Inputs" / dem.name)
    rel = pathlib.Path(job["release"])
    for f in rel.parent.glob(rel.stem + ".*"):  # .shp with its .shx, .dbf, .prj, .cpg
        shutil.copy(f, ava / "Inputs" / "REL" / f.name)
    if job.get("entrainment"):  # an entrainment area (thickness attribute) and its runs
        ent = pathlib.Path(job["entrainment"])
        for f in ent.parent.glob(ent.stem + ".*"):
            shutil.copy(f, ava / "Inputs" / "ENT" / f.name)

    cfgMain = cfgUtils.getGeneralConfig()
    cfgMain["MAIN"]["avalancheDir"] = str(ava)
    cfgMain["MAIN"]["nCPU"] = "1"
    cfgMain["FLAGS"]["createReport"] = "False"
    cfgMain["FLAGS"]["savePlot"] = "False"
    logUtils.initiateLogger(str(ava), "compare")
    cfg = cfgUtils.getModuleConfig(com1DFA, str(ava), toPrint=False)
    g = cfg["GENERAL"]
    g["meshCellSize"] = repr(float(job["dx"]))
    g["rho"] = repr(float(job["rho"]))
    g["tEnd"] = repr(float(job["t_end"]))
    g["relThFromFile"] = "True"            # the shapefile's thickness attribute
    g["resType"] = "ppr|pft|pfv"
    if not job.get("curvature", True):
        g["curvAccInFriction"] = "0"          # no bed curvature in the friction
    for key, value in job.get("extra", {}).items():  # --avaframe-set, for studies
        g[key] = value
    cfg["EXPORTS"]["exportRasters"] = "True"
    if job.get("entrainment"):
        g["simTypeList"] = "ent"
        g["entThFromFile"] = "True"
        g["rhoEnt"] = repr(float(job.get("rho_ent", 100.0)))
        g["entEroEnergy"] = repr(float(job.get("e_b", 5000.0)))
    law = job["law"]
    if law == "coulomb":
        g["frictModel"] = "Coulomb"
        g["mucoulomb"] = repr(float(job["mu"]))
    elif law == "voellmy":
        g["frictModel"] = "Voellmy"
        g["muvoellmy"] = repr(float(job["mu"]))
        g["xsivoellmy"] = repr(float(job["xi"]))
    elif law == "samosat":
        g["frictModel"] = "samosAT"            # the standard ("large") parameter set
    else:
        raise SystemExit(f"unknown law {law!r}")

    t0 = time.perf_counter()
    _, _, reports, simDF = com1DFA.com1DFAMain(cfgMain, cfgInfo=cfg)
    wall_main = time.perf_counter() - t0
    rd = reports[0]
    sp = rd["Simulation Parameters"]
    name = rd["simName"]["name"]
    row = simDF.reset_index().to_dict(orient="records")[0]
    peak = ava / "Outputs" / "com1DFA" / "peakFiles"
    out = {
        "avaframe_version": version("avaframe"),
        "sim_name": name,
        "friction_model": sp["Friction model"],
        "friction_parameters": {str(k): str(v) for k, v in rd["Friction model"].items()
                                if k != "type"},
        "wall_s": float(sp["Computation time [s]"]),
        "wall_loop_s": float(row["timeLoop"]),
        "wall_com1DFAMain_s": wall_main,
        "steps": int(row["nIter"]) - 1,
        "dt_s": float(row["dt"]),
        "t_end_s": float(sp["Process run time [s]"]),
        "ended_by": sp["Stop criterion"],
        "n_particles": int(row["nPart"]),
        "released_volume_m3": float(sp["Initial mass [kg]"]) / float(job["rho"]),
        "final_volume_m3": float(sp["Final mass [kg]"]) / float(job["rho"]),
        # .asc or .tif, as the DEM was given
        "pft": str(next(peak.glob(f"{name}_pft.*"), peak / f"{name}_pft.asc")),
        "pfv": str(next(peak.glob(f"{name}_pfv.*"), peak / f"{name}_pfv.asc")),
        "dem": str(next((ava / "Inputs" / "remeshedRasters").glob("*.asc"), dem)),
        # time, current mass, entrained in the step (kg): com1DFA's mass log
        "mass_log": str(next((ava / "Outputs" / "com1DFA").glob("mass_*.txt"), "")),
        "entrained_volume_m3": (float(rd["Simulation Parameters"].get("Entrained volume [m3]",
                                                                       "nan"))
                                if "Simulation Parameters" in rd else float("nan")),
    }
    pathlib.Path(job["json_out"]).write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    run(json.loads(pathlib.Path(sys.argv[1]).read_text()))
'''


# =========================================================================================
# Rasters, polygons, metrics
# =========================================================================================


def read_asc(path):
    """``(values, x, y)`` of an ESRI ASCII grid (or a GeoTIFF: AvaFrame writes its peak maps
    in the DEM's format): rows from south to north, cell centres."""
    if str(path).lower().endswith((".tif", ".tiff")):
        import rasterio

        with rasterio.open(path) as src:
            values = src.read(1, masked=True).filled(np.nan).astype(float)
            t = src.transform
            x = t.c + t.a * (np.arange(src.width) + 0.5)
            y = t.f + t.e * (np.arange(src.height) + 0.5)
        if y[0] > y[-1]:
            values, y = np.flipud(values), y[::-1]
        return values, x, y
    header = {}
    with open(path) as f:
        for _ in range(6):
            key, value = f.readline().split()
            header[key.lower()] = value
    values = np.loadtxt(path, skiprows=6, ndmin=2)
    nodata = header.get("nodata_value", "nan")
    if nodata.lower() != "nan":
        values[values == float(nodata)] = np.nan
    c = float(header["cellsize"])
    x0 = (float(header["xllcenter"]) if "xllcenter" in header
          else float(header["xllcorner"]) + 0.5 * c)
    y0 = (float(header["yllcenter"]) if "yllcenter" in header
          else float(header["yllcorner"]) + 0.5 * c)
    ny, nx = values.shape
    return np.flipud(values), x0 + c * np.arange(nx), y0 + c * np.arange(ny)


def release_geometry(path):
    """The release polygon's rings (list of (n, 2) arrays) and areas, read by avflow."""
    from avflow.terrain.polygons import read_polygons

    areas, _ = read_polygons(path)
    return areas, [ring for area in areas for ring in area.rings]


def inside_release(areas, xx, yy):
    from avflow.terrain.polygons import rasterize

    return rasterize(areas, xx, yy, thickness=1.0) > 0.0


def distance_to_rings(rings, px, py, chunk=20000):
    """Horizontal distance of points to the polygon boundary (to be zeroed inside)."""
    seg_a = np.concatenate([r for r in rings])
    seg_b = np.concatenate([np.roll(r, -1, axis=0) for r in rings])
    d = seg_b - seg_a
    len2 = np.maximum((d**2).sum(axis=1), 1e-300)
    out = np.empty(px.size)
    for s in range(0, px.size, chunk):
        qx, qy = px[s:s + chunk, None], py[s:s + chunk, None]
        t = np.clip(((qx - seg_a[:, 0]) * d[:, 0] + (qy - seg_a[:, 1]) * d[:, 1]) / len2, 0, 1)
        ex = seg_a[:, 0] + t * d[:, 0] - qx
        ey = seg_a[:, 1] + t * d[:, 1] - qy
        out[s:s + chunk] = np.sqrt(ex**2 + ey**2).min(axis=1)
    return out


def footprint_metrics(x, y, z, pft, pfv, areas, rings):
    """The table's geometric metrics of one model's peak maps on its own grid."""
    xx, yy = np.meshgrid(x, y)
    dx, dy = abs(x[1] - x[0]), abs(y[1] - y[0])
    thick = np.nan_to_num(pft, nan=0.0)
    m = {"max_peak_thickness_m": float(np.nanmax(pft)),
         "max_peak_speed_ms": float(np.nanmax(pfv)),
         "cell_m": 0.5 * (dx + dy)}
    for thr in THRESHOLDS:
        m[f"area_gt_{thr:g}_km2"] = float((thick > thr).sum() * dx * dy / 1e6)
    foot = thick > THRESHOLDS[0]
    if not foot.any():
        m.update(runout_m=math.nan, travel_angle_deg=math.nan, travel_length_m=math.nan)
        return m
    inside = inside_release(areas, xx, yy)
    fx, fy = xx[foot], yy[foot]
    dist = distance_to_rings(rings, fx, fy)
    dist[inside[foot]] = 0.0
    m["runout_m"] = float(dist.max())
    zr = np.where(inside & np.isfinite(z), z, -np.inf)
    top = np.unravel_index(np.argmax(zr), zr.shape)
    length = np.hypot(fx - xx[top], fy - yy[top])
    far = np.argmax(length)
    m["travel_length_m"] = float(length[far])
    m["travel_angle_deg"] = float(math.degrees(math.atan2(z[top] - z[foot][far], length[far])))
    return m


def nearest_on(values, x, y, to_x, to_y):
    """``values`` on (y, x) cell centres sampled at the centres (to_y, to_x), nearest cell;
    0 outside."""
    cx, cy = x[1] - x[0], y[1] - y[0]
    ix = np.rint((to_x - x[0]) / cx).astype(int)
    iy = np.rint((to_y - y[0]) / cy).astype(int)
    okx = (ix >= 0) & (ix < x.size)
    oky = (iy >= 0) & (iy < y.size)
    out = np.zeros((to_y.size, to_x.size))
    sub = np.nan_to_num(values, nan=0.0)[np.ix_(iy[oky], ix[okx])]
    out[np.ix_(np.flatnonzero(oky), np.flatnonzero(okx))] = sub
    return out


def overlap(a, b):
    """Intersection over union of two footprints, and the areas (cells) only in each."""
    inter, union = np.count_nonzero(a & b), np.count_nonzero(a | b)
    return (inter / union if union else math.nan,
            int(np.count_nonzero(a & ~b)), int(np.count_nonzero(b & ~a)))


# =========================================================================================
# The two models
# =========================================================================================


def avaframe_runner(args):
    """``(how, python_or_dir, note)``: how AvaFrame results are obtained this time."""
    if importlib.util.find_spec("avaframe") is not None:
        try:
            importlib.import_module("avaframe.com1DFA.com1DFA")
            return "inprocess", None, "AvaFrame run in this process (import avaframe works)"
        except Exception as err:  # e.g. compiled against another numpy
            print(f"compare_avaframe: avaframe is installed here but does not import "
                  f"({type(err).__name__}: {err})", file=sys.stderr)
    python = args.avaframe_python or os.environ.get("AVAFRAME_PYTHON")
    if python:
        probe = subprocess.run([python, "-c", "import avaframe"], capture_output=True, text=True)
        if probe.returncode == 0:
            return "subprocess", python, f"AvaFrame run by {python} (subprocess)"
        why = (probe.stderr.strip().splitlines() or ["fails"])[-1]
        print(f"compare_avaframe: {python} cannot import avaframe ({why})", file=sys.stderr)
    if args.avaframe_results:
        return ("stored", Path(args.avaframe_results),
                f"AvaFrame not available here: stored results from {args.avaframe_results}")
    return None, None, ("AvaFrame not available (no import avaframe, no --avaframe-python / "
                        "$AVAFRAME_PYTHON, no --avaframe-results): avflow rows only")


def run_avaframe(how, where, path, law, scenario, dx, out_dir, curvature=True, extra=None,
                 entrainment=None):
    """AvaFrame's run of one case: its info dict, with ``pft``, ``pfv``, ``dem`` raster paths.
    ``entrainment``: a dict ``{"path": ENT shapefile, "rho_ent": kg/m^3, "e_b": J/kg}``
    (com1DFA's ``ent`` run, its mass log in ``mass_log``)."""
    case = (law if curvature else f"{law}_nocurv") + ("_ent" if entrainment else "")
    if how == "stored":
        return stored_avaframe(where, path, case, dx)
    work = out_dir / "avaframe"
    work.mkdir(parents=True, exist_ok=True)
    params = LAWS[law]
    job = {"ava_dir": str(work / f"{path}_{case}_{dx:g}m"), "dem": scenario.terrain.path,
           "release": scenario.release.path, "dx": dx, "rho": RHO, "t_end": T_END, "law": law,
           "mu": (math.tan(math.radians(params["delta_deg"])) if law == "coulomb"
                  else params.get("mu")),
           "xi": params.get("xi"), "curvature": curvature, "extra": dict(extra or {}),
           "json_out": str(work / f"{path}_{case}_{dx:g}m.json")}
    if entrainment:
        job.update(entrainment=str(entrainment["path"]), rho_ent=entrainment["rho_ent"],
                   e_b=entrainment["e_b"])
    if how == "inprocess":
        namespace = {"__name__": "compare_avaframe_com1dfa"}
        exec(compile(AVAFRAME_SCRIPT, "run_com1dfa.py", "exec"), namespace)
        return namespace["run"](job)
    script = work / "run_com1dfa.py"
    script.write_text(AVAFRAME_SCRIPT.lstrip())
    job_file = work / f"{path}_{case}_{dx:g}m_job.json"
    job_file.write_text(json.dumps(job, indent=1))
    log = work / f"{path}_{case}_{dx:g}m.log"
    with open(log, "w") as f:
        done = subprocess.run([where, str(script), str(job_file)], stdout=f,
                              stderr=subprocess.STDOUT, cwd=work)
    if done.returncode != 0:
        tail = log.read_text().strip().splitlines()[-3:]
        raise RuntimeError(f"AvaFrame failed (exit {done.returncode}, log {log}): "
                           + " | ".join(tail))
    return json.loads(Path(job["json_out"]).read_text())


def stored_avaframe(folder, path, law, dx):
    """A stored AvaFrame run (/work/avaframe_ref layout), or None when it is not there."""
    case = folder / f"{path}_{law}"
    pft = case / f"{path}_{law}_pft.asc"
    if not pft.is_file():
        return None
    rows = {}
    if (folder / "results.csv").is_file():
        with open(folder / "results.csv", newline="") as f:
            rows = {r["run"]: r for r in csv.DictReader(f)}
    r = rows.get(f"{path}_{law}", {})
    _, xs, _ = read_asc(case / f"{path}_DEM5m_remeshed.asc")
    if abs((xs[1] - xs[0]) - dx) > 0.01 * dx:
        print(f"compare_avaframe: stored AvaFrame {path} {law} has {xs[1] - xs[0]:g} m cells, "
              f"avflow runs at {dx:g} m", file=sys.stderr)

    def num(key):
        return float(r[key]) if r.get(key) not in (None, "") else math.nan

    return {"avaframe_version": "stored", "friction_model": r.get("frictModel", ""),
            "friction_parameters": r.get("friction_params", ""),
            "wall_s": num("wall_sim_s"), "wall_loop_s": num("wall_timeloop_s"),
            "steps": int(num("n_time_steps")) if r else -1, "dt_s": num("dt_s"),
            "t_end_s": num("end_time_s"), "ended_by": r.get("stop_reason", ""),
            "released_volume_m3": num("released_volume_m3"),
            "final_volume_m3": num("final_volume_m3"),
            "pft": str(pft), "pfv": str(case / f"{path}_{law}_pfv.asc"),
            "dem": str(case / f"{path}_DEM5m_remeshed.asc")}


def avflow_scenario(base, law, dx, stop_rule=None, curvature=True):
    updates = {"grid.dx": dx, "physics.density": RHO, "rheology": LAWS[law],
               "time.end": T_END, "output.every": 20.0}  # peaks are tracked every step
    if not curvature:
        updates["terrain.curvature"] = False
    # the stop rule is set, not inherited from the YAML: avflow's default unless asked
    updates["output.stop_rule"] = stop_rule or "moving_volume"
    updates["output.stop_fraction"] = None  # the rule's own default
    return base.with_updates(updates)


def has_samosat(base):
    from avflow.errors import ScenarioError

    try:
        base.with_updates({"rheology": LAWS["samosat"]})
        return True
    except ScenarioError:
        return False


def run_avflow(scenario):
    """avflow's run: summary, timing and the peak maps on its grid."""
    from avflow.errors import RunFailed
    from avflow.output.dataset import to_dataset
    from avflow.simulation.runner import simulate

    t0 = time.perf_counter()
    try:
        result = simulate(scenario)
    except RunFailed as err:
        return {"failed": str(err), "wall_s": time.perf_counter() - t0}
    wall = time.perf_counter() - t0
    ds = to_dataset(result)
    s = result.summary
    out = {"wall_s": wall, "wall_loop_s": float(s["wall_time"]), "steps": int(s["steps"]),
           "t_end_s": float(result.state.t), "ended_by": str(s["ended_by"]),
           "released_volume_m3": float(s["release_volume"]),
           "final_volume_m3": float(s["deposit_volume"]),
           "outflow_volume_m3": float(s["outflow_volume"]),
           "runout_truncated": bool(s["runout_truncated"]),
           "moving_volume_end_m3": float(s["moving_volume_end"]),
           "clamped_normal_cells": int(s.get("clamped_normal_cells", -1)),
           "rheology": json.dumps(scenario.rheology.model_dump(mode="json")),
           "pft": np.asarray(ds["peak_thickness"].values, dtype=float),
           "pfv": np.asarray(ds["peak_speed"].values, dtype=float),
           "z": np.asarray(ds["bed_elevation"].values, dtype=float),
           "x": np.asarray(ds["x"].values, dtype=float),
           "y": np.asarray(ds["y"].values, dtype=float)}
    del ds, result
    return out


# =========================================================================================
# Figure
# =========================================================================================


def shade(z, dx, dy):
    dzdy, dzdx = np.gradient(z, dy, dx)
    az, alt = math.radians(315.0), math.radians(45.0)
    light = (math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt))
    s = (-dzdx * light[0] - dzdy * light[1] + light[2]) / np.sqrt(dzdx**2 + dzdy**2 + 1.0)
    return np.clip(s, 0.0, 1.0)


def figure(png, title, af, fl, rings, iou):
    """AvaFrame | avflow peak thickness (log scale) | footprint overlap, same extent."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap, LogNorm

    x, y, z = fl["x"], fl["y"], fl["z"]
    dx, dy = x[1] - x[0], y[1] - y[0]
    ext = (x[0] - dx / 2, x[-1] + dx / 2, y[0] - dy / 2, y[-1] + dy / 2)
    hs = np.ma.masked_invalid(shade(z, dx, dy))
    maps = []
    if af is not None:
        maps.append(("AvaFrame com1DFA", af["pft_grid"], af["x"], af["y"], af))
    maps.append(("avflow", fl["pft"], x, y, fl))
    # same extent: every footprint and the release, with a margin
    boxes = [np.concatenate(rings)]
    for _, p, px, py, _ in maps:
        foot = np.nan_to_num(p) > LOG_FLOOR
        if foot.any():
            pxx, pyy = np.meshgrid(px, py)
            boxes.append(np.column_stack([pxx[foot], pyy[foot]]))
    pts = np.concatenate(boxes)
    margin = 150.0
    lo, hi = pts.min(axis=0) - margin, pts.max(axis=0) + margin
    vmax = max(np.nanmax(p) for _, p, *_ in maps)
    norm = LogNorm(vmin=LOG_FLOOR, vmax=max(vmax, 10 * LOG_FLOOR))
    zf = z[np.isfinite(z)]
    levels = np.arange(math.ceil(zf.min() / 100) * 100, zf.max(), 100.0)

    n = len(maps) + (1 if af is not None else 0)
    aspect = (hi[1] - lo[1]) / (hi[0] - lo[0])
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n + 1.0, 4.2 * aspect + 0.8),
                             layout="constrained", squeeze=False)
    axes = axes[0]

    def background(ax):
        ax.imshow(hs, extent=ext, origin="lower", cmap="gray", vmin=-0.4, vmax=1.2,
                  interpolation="nearest")
        cs = ax.contour(x, y, z, levels=levels, colors="0.3", linewidths=0.4, alpha=0.6)
        ax.clabel(cs, fontsize=5, fmt="%g", inline_spacing=1)
        for r in rings:
            ax.plot(*np.vstack([r, r[:1]]).T, color="red", lw=0.9)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.tick_params(labelsize=6)
        ax.ticklabel_format(useOffset=False, style="plain")

    im = None
    for ax, (label, p, px, py, info) in zip(axes, maps):
        background(ax)
        pdx, pdy = px[1] - px[0], py[1] - py[0]
        pext = (px[0] - pdx / 2, px[-1] + pdx / 2, py[0] - pdy / 2, py[-1] + pdy / 2)
        im = ax.imshow(np.ma.masked_less_equal(np.nan_to_num(p), LOG_FLOOR), extent=pext,
                       origin="lower", cmap="viridis", norm=norm, interpolation="nearest")
        ax.set_title(f"{label}\nA(>0.01 m) {info['area_gt_0.01_km2']:.3f} km$^2$, "
                     f"max {info['max_peak_thickness_m']:.2f} m, "
                     f"{info['max_peak_speed_ms']:.0f} m/s", fontsize=8)
    if af is not None:
        ax = axes[-1]
        background(ax)
        a = af["pft_on_avflow"] > LOG_FLOOR
        b = np.nan_to_num(fl["pft"]) > LOG_FLOOR
        cls = np.where(a & b, 3, np.where(a, 1, np.where(b, 2, 0))).astype(float)
        cmap = ListedColormap(["#d95f02", "#1b9e77", "#7570b3"])
        ax.imshow(np.ma.masked_equal(cls, 0), extent=ext, origin="lower", cmap=cmap,
                  vmin=0.5, vmax=3.5, interpolation="nearest", alpha=0.85)
        ax.set_title(f"peak thickness > 0.01 m: IoU {iou:.2f}\norange AvaFrame only, green "
                     "avflow only, purple both", fontsize=8)
    fig.colorbar(im, ax=list(axes[:len(maps)]), shrink=0.8, label="peak thickness (m)")
    fig.suptitle(title, fontsize=9)
    fig.savefig(png, dpi=130)
    plt.close(fig)


# =========================================================================================
# Table
# =========================================================================================

COLUMNS = [  # (csv key, markdown header, format)
    ("path", "path", "{}"), ("law", "law", "{}"), ("model", "model", "{}"),
    ("wall_s", "wall [s]", "{:.1f}"), ("steps", "steps", "{}"),
    ("t_end_s", "t end [s]", "{:.1f}"), ("ended_by", "ended by", "{}"),
    ("runout_m", "runout from release [m]", "{:.0f}"),
    ("area_gt_0.01_km2", "A(>0.01 m) [km²]", "{:.3f}"),
    ("area_gt_0.1_km2", "A(>0.1 m) [km²]", "{:.3f}"),
    ("iou_0.01", "IoU >0.01", "{:.2f}"), ("iou_0.1", "IoU >0.1", "{:.2f}"),
    ("max_peak_thickness_m", "max pft [m]", "{:.2f}"),
    ("max_peak_speed_ms", "max pfv [m/s]", "{:.1f}"),
    ("travel_angle_deg", "travel angle [°]", "{:.1f}"),
    ("released_volume_m3", "V rel [m³]", "{:.0f}"),
    ("final_volume_m3", "V final [m³]", "{:.0f}"),
    ("ke_rule", "avflow, KE rule: wall / steps / t end / IoU>0.01", "{}"),
]
CSV_EXTRA = ["wall_loop_s", "cell_m", "travel_length_m", "only_avaframe_km2_0.01",
             "only_avflow_km2_0.01", "outflow_volume_m3", "runout_truncated",
             "moving_volume_end_m3", "clamped_normal_cells", "ke_wall_s", "ke_steps",
             "ke_t_end_s", "ke_ended_by", "ke_iou_0.01", "ke_area_gt_0.01_km2",
             "friction", "note", "load_average_1min"]


def fmt(value, spec):
    if value is None or value == "" or (isinstance(value, float) and math.isnan(value)):
        return "–"
    try:
        return spec.format(value)
    except (ValueError, TypeError):
        return str(value)


def markdown(rows):
    lines = ["| " + " | ".join(h for _, h, _ in COLUMNS) + " |",
             "|" + "---|" * len(COLUMNS)]
    for r in rows:
        lines.append("| " + " | ".join(fmt(r.get(k), f) for k, _, f in COLUMNS) + " |")
    return "\n".join(lines)


# =========================================================================================
# Main
# =========================================================================================


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--paths", nargs="+", default=["avaKot", "avaHit"],
                    help="AvaFrame paths: avaKot, avaHit")
    ap.add_argument("--laws", nargs="+", default=list(LAWS), choices=list(LAWS))
    ap.add_argument("--dx", type=float, default=5.0, help="cell size (m) of both models")
    ap.add_argument("--out", default="out/compare_avaframe", help="output folder")
    ap.add_argument("--quick", action="store_true", help="10 m cells (smoke test)")
    ap.add_argument("--avaframe-python", default=None,
                    help="Python with avaframe installed (else $AVAFRAME_PYTHON)")
    ap.add_argument("--avaframe-results", default=None,
                    help="folder of stored AvaFrame runs, used when AvaFrame cannot run")
    ap.add_argument("--no-curvature", action="store_true",
                    help="both models without the bed curvature in the friction (a study: "
                    "AvaFrame curvAccInFriction = 0, avflow terrain.curvature: false)")
    ap.add_argument("--avaframe-set", action="append", default=[], metavar="KEY=VALUE",
                    help="set a com1DFA [GENERAL] key for a study, e.g. viscOption=0 "
                    "(repeatable; live AvaFrame runs only)")
    ap.add_argument("--no-ke-rule", action="store_true",
                    help="skip avflow's second run with the kinetic-energy stop rule")
    args = ap.parse_args(argv)
    dx = 10.0 if args.quick else args.dx
    extra = dict(kv.split("=", 1) for kv in args.avaframe_set)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    from avflow.scenario import load_scenario
    from avflow.simulation.runner import simulate

    how, where, note = avaframe_runner(args)
    import avflow

    try:
        head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "avflow"],
                               capture_output=True, text=True).stdout.strip()
        state = f"avflow from {Path(avflow.__file__).parent}, checkout {head or '?'}" + (
            " with uncommitted changes in avflow/" if dirty else "")
    except OSError:
        state = f"avflow from {Path(avflow.__file__).parent}"
    print(f"compare_avaframe: {note}; cells {dx:g} m; output {out}", flush=True)

    rows, notes = [], [note, state]
    if extra:
        notes.append("AvaFrame with " + ", ".join(f"{k} = {v}" for k, v in extra.items()))
    warm = False
    for name in args.paths:
        key = name.lower()
        if key not in PATHS:
            raise SystemExit(f"compare_avaframe: unknown path {name!r} (avaKot, avaHit)")
        path, yaml = PATHS[key]
        base = load_scenario(ROOT / yaml)
        areas, rings = release_geometry(base.release.path)
        if not warm:  # compile avflow's kernels before anything is timed
            simulate(base.with_updates({"grid.dx": 50.0, "time.end": 2.0, "output.every": 1.0}))
            warm = True
        for law in args.laws:
            if law == "samosat" and not has_samosat(base):
                msg = (f"{path} samosat: skipped, this avflow has no 'law: samosat' "
                       "(the scenario does not parse)")
                print(f"compare_avaframe: {msg}", flush=True)
                notes.append(msg)
                rows.append({"path": path, "law": law, "model": "skipped", "note": msg})
                continue
            curv = not args.no_curvature
            case = law if curv else f"{law}_nocurv"
            scenario = avflow_scenario(base, law, dx, curvature=curv)
            print(f"== {path} {case} at {dx:g} m", flush=True)

            af = None
            if how is not None:
                try:
                    af = run_avaframe(how, where, path, law, scenario, dx, out, curv, extra)
                except Exception as err:  # one failed case does not end the comparison
                    msg = f"{path} {case}: AvaFrame failed: {err}"
                    print(f"compare_avaframe: {msg}", file=sys.stderr, flush=True)
                    notes.append(msg)
                if af is None and how == "stored":
                    notes.append(f"{path} {case}: no stored AvaFrame run in {where}")
            if af is not None:
                pft, ax_, ay_ = read_asc(af["pft"])
                pfv, _, _ = read_asc(af["pfv"])
                dem, _, _ = read_asc(af["dem"])
                af.update(footprint_metrics(ax_, ay_, dem, pft, pfv, areas, rings))
                af.update(pft_grid=pft, x=ax_, y=ay_)
                print(f"   AvaFrame: {af['wall_s']:.1f} s, {af['steps']} steps, "
                      f"{af['ended_by']}", flush=True)

            fl = run_avflow(scenario)
            load = os.getloadavg()[0]
            if "failed" in fl:
                msg = f"{path} {case}: avflow failed: {fl['failed']}"
                notes.append(msg)
                rows.append({"path": path, "law": case, "model": "avflow", "note": msg})
                continue
            fl.update(footprint_metrics(fl["x"], fl["y"], fl["z"], fl["pft"], fl["pfv"],
                                        areas, rings))
            print(f"   avflow: {fl['wall_s']:.1f} s, {fl['steps']} steps, {fl['ended_by']}",
                  flush=True)
            xx, yy = fl["x"], fl["y"]
            cell_km2 = abs((xx[1] - xx[0]) * (yy[1] - yy[0])) / 1e6
            iou = {}
            if af is not None:
                af["pft_on_avflow"] = nearest_on(af["pft_grid"], af["x"], af["y"], xx, yy)
                for thr in THRESHOLDS:
                    a = af["pft_on_avflow"] > thr
                    b = np.nan_to_num(fl["pft"]) > thr
                    iou[thr], only_a, only_b = overlap(a, b)
                    if thr == THRESHOLDS[0]:
                        fl["only_avaframe_km2_0.01"] = only_a * cell_km2
                        fl["only_avflow_km2_0.01"] = only_b * cell_km2

            ke = {}
            if not args.no_ke_rule:
                k = run_avflow(avflow_scenario(base, law, dx, "kinetic_energy", curv))
                if "failed" not in k:
                    kf = np.nan_to_num(k["pft"]) > THRESHOLDS[0]
                    ke = {"ke_wall_s": k["wall_s"], "ke_steps": k["steps"],
                          "ke_t_end_s": k["t_end_s"], "ke_ended_by": k["ended_by"],
                          "ke_area_gt_0.01_km2": kf.sum() * cell_km2}
                    if af is not None:
                        ke["ke_iou_0.01"] = overlap(af["pft_on_avflow"] > THRESHOLDS[0], kf)[0]
                    ke["ke_rule"] = (f"{k['wall_s']:.1f} s / {k['steps']} / "
                                     f"{k['t_end_s']:.1f} s / "
                                     + fmt(ke.get("ke_iou_0.01"), "{:.2f}"))
                    print(f"   avflow, KE rule: {k['wall_s']:.1f} s, {k['steps']} steps, "
                          f"{k['ended_by']} at {k['t_end_s']:.1f} s", flush=True)
                    del k

            common = {"path": path, "law": case, "load_average_1min": round(load, 2)}
            if af is not None:
                row = {**common, "model": f"AvaFrame {af['avaframe_version']}",
                       "friction": f"{af['friction_model']} {af['friction_parameters']}",
                       **{k: v for k, v in af.items() if not isinstance(v, np.ndarray)}}
                row["ended_by"] = ("KE < 1% of peak" if "PKE" in str(row.get("ended_by"))
                                   else row.get("ended_by"))
                rows.append(row)
            row = {**common, "model": "avflow", "friction": fl["rheology"],
                   **{k: v for k, v in fl.items() if not isinstance(v, np.ndarray)}, **ke}
            for thr in THRESHOLDS:
                row[f"iou_{thr:g}"] = iou.get(thr, math.nan)
            rows.append(row)

            png = out / f"{path}_{case}.png"
            figure(png, f"{path}, {case}, {dx:g} m cells: peak thickness (log scale), "
                   "release polygon in red, 100 m contours", af, fl, rings,
                   iou.get(THRESHOLDS[0], math.nan))
            print(f"   figure {png}", flush=True)
            del af, fl

    keys = [k for k, _, _ in COLUMNS] + CSV_EXTRA
    with open(out / "compare.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in keys})
    table = markdown([r for r in rows if r.get("model") != "skipped"])
    text = (f"Cells {dx:g} m. " + " ".join(f"{n}." for n in notes) + "\n\n" + table + "\n")
    (out / "compare.md").write_text(text)
    print()
    print(text)
    print(f"compare_avaframe: wrote {out / 'compare.csv'}, {out / 'compare.md'} and the PNGs")


if __name__ == "__main__":
    main()
