"""The public extension API (``avflow.extend``), used from outside the package: a friction law
(a constant plus a term linear in speed), a mass source (snowfall: a rate in m/s over a
polygon, dry cells included) and an output map (peak momentum |h u|), defined here,
registered through the API, run on the profile, the square-grid and the face kernels (and on
the CUDA simulator where numba-cuda is installed), with nothing under ``avflow/`` edited.

Registration changes the process for good (every later run writes the map), so the cases
run in a child process: this file run as a script (``python tests/test_extension_api.py
CASE``), which registers the law and the map and prints what the test checks as JSON.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
MU = math.tan(math.radians(20.0))


# --- the extension, as a user writes it --------------------------------------------------------

def linear_speed(mu, k, h, speed, normal_accel, g):
    """Coulomb friction whose coefficient rises linearly with speed: mu + k |u|."""
    return (mu + k * speed) * h * normal_accel, 0.0


def peak_momentum(old, h, hu, hv, speed, t):
    """The largest momentum per unit width |h u| the cell has seen."""
    momentum = h * speed
    return momentum if momentum > old else old


def snowfall(rate, h, speed, t):
    """Snow falling at a constant rate (m/s of flow thickness), on snow and on bare ground."""
    return rate


def register():
    from avflow import extend

    extend.friction_law("linear_speed", parameters=("mu", "k"),
                        reference="a test law: mu + k |u|",
                        bounds={"mu": (0.0, 5.0), "k": (0.0, 1.0)})(linear_speed)
    extend.output_map("peak_momentum", units="m2 s-1",
                      long_name="maximum momentum per unit width |h u|")(peak_momentum)
    extend.source("snowfall", parameters=("rate",),
                  reference="a test source: snowfall at a constant rate")(snowfall)


# --- the scenes ---------------------------------------------------------------------------------

PROFILE = """
name: ext-profile
terrain: {kind: profile, length: 600.0, slope: {kind: constant, theta_deg: 30.0}}
grid: {dx: 10.0}
release: {kind: parabola, center: 150.0, half_length: 60.0, max_thickness: 8.0}
time: {end: 20.0, cfl: 0.5}
output: {every: 10.0}
"""
PLANE = """
name: ext-plane
terrain: {kind: plane, slope_deg: 30.0, azimuth_deg: 90.0,
          extent: {x: [0.0, 400.0], y: [0.0, 240.0]}}
grid: {dx: 20.0}
release: {kind: cylinder, center: [100.0, 120.0], radius: 50.0, thickness: 8.0}
time: {end: 12.0, cfl: 0.5}
output: {every: 6.0}
"""
SCENES = {"profile": (PROFILE, "auto"), "grid": (PLANE, "grid"), "faces": (PLANE, "faces")}


def _rheology(law: str, k: float = 0.0) -> str:
    if law == "coulomb":
        return "rheology: {law: coulomb, delta_deg: 20.0}\n"
    return f"rheology: {{law: linear_speed, mu: {MU!r}, k: {k!r}}}\n"


def _run(text: str, kernel: str, law: str, k: float = 0.0, backend: str = "cpu"):
    from avflow.scenario.schema import parse_scenario
    from avflow.simulation.runner import simulate

    # order 1: the GPU's (order 2 is the CPU's default on grids)
    numerics = f"numerics: {{kernel: {kernel}, backend: {backend}, threads: 1, order: 1}}\n"
    return simulate(parse_scenario(text + _rheology(law, k) + numerics))


def _same(a, b) -> bool:
    import numpy as np

    return bool(np.array_equal(a, b, equal_nan=True))


def case_kernels() -> dict:
    """The law at k = 0 against Coulomb, bit for bit, on each kernel; the law at k > 0
    stops shorter; the map against the states it was made from."""
    import numpy as np

    out = {}
    for kernel, (text, choice) in SCENES.items():
        ref = _run(text, choice, "coulomb")
        new = _run(text, choice, "linear_speed")
        slow = _run(text, choice, "linear_speed", k=0.05)
        names = ("h", "hu", "hv", "peak_h", "peak_speed", "arrival", "last_moved")
        snaps = new.snapshots
        # |h u| at every output time, never above the map (which saw every accepted step)
        seen = np.max([np.hypot(hu, hv) for hu, hv in zip(snaps.hu, snaps.hv)], axis=0)
        momentum = new.state.maps[0]
        out[kernel] = {
            "kernel_used": new.solver.kernel_used,
            "equal": {n: _same(getattr(ref.state, n), getattr(new.state, n)) for n in names},
            "steps": [ref.state.steps, new.state.steps],
            "runout": [ref.summary["runout"], new.summary["runout"], slow.summary["runout"]],
            "map_covers_snapshots": bool(np.all(momentum >= seen - 1e-12 * seen.max())),
            "map_max": float(momentum.max()),
            "map_bound": float(np.max(new.state.peak_h * new.state.peak_speed)),
            "map_rows": int(new.state.maps.shape[0]),
        }
    return out


def case_files(folder: str) -> dict:
    """The map in the NetCDF with its CF attributes, and in ``avflow export``."""
    import rasterio
    import xarray as xr

    from avflow.cli import main
    from avflow.output.dataset import to_dataset
    from avflow.output.netcdf import write_netcdf

    result = _run(PLANE, "grid", "linear_speed", k=0.02)
    path = Path(folder) / "run.nc"
    write_netcdf(to_dataset(result), path)
    with xr.open_dataset(path) as ds:
        var = ds["peak_momentum"]
        attrs = {k: str(v) for k, v in var.attrs.items()}
        dims = list(var.dims)
        references = ds.attrs["references"]
        values = var.values
    code = main(["export", str(path), "-o", str(Path(folder) / "maps")])
    tif = Path(folder) / "maps" / "run_peak_momentum.tif"
    with rasterio.open(tif) as src:
        band = src.read(1, masked=True)
    import numpy as np

    return {"attrs": attrs, "dims": dims, "references": references, "export_code": code,
            "tif_max": float(band.max()), "nc_max": float(np.nanmax(values))}


RATE = 2.0e-3  # m/s: 24 mm over the plane's 12 s


def _polygon(folder: Path) -> Path:
    """A GeoJSON square over x 240..340, y 60..180 of the plane (away from the release)."""
    ring = [[240.0, 60.0], [340.0, 60.0], [340.0, 180.0], [240.0, 60.0 + 120.0],
            [240.0, 60.0]]
    path = folder / "snow.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {},
         "geometry": {"type": "Polygon", "coordinates": [ring]}}]}))
    return path


def case_sources(folder: str) -> dict:
    """Snowfall alone and with entrainment, on each kernel: its volume against rate x area x
    time, the mass balance, snow on cells the flow never reached, the summary line."""
    import contextlib
    import io

    import numpy as np

    from avflow.cli import main
    from avflow.scenario.schema import parse_scenario
    from avflow.simulation.runner import simulate

    snow = _polygon(Path(folder))
    where = {"profile": "x: [300.0, 450.0]", "grid": f"polygon: {snow}",
             "faces": f"polygon: {snow}"}
    layer = {"profile": "{depth: 0.5, x: [0.0, 400.0]}",
             "grid": "{depth: 0.5, x: [0.0, 250.0]}", "faces": "{depth: 0.5, x: [0.0, 250.0]}"}
    out = {}
    for kernel, (text, choice) in SCENES.items():
        for with_entrainment in (False, True):
            extra = (_rheology("coulomb")
                     + f"numerics: {{kernel: {choice}, threads: 1}}\n"
                     + f"sources: [{{law: snowfall, rate: {RATE!r}, {where[kernel]}}}]\n")
            if with_entrainment:
                extra += ("entrainment: {law: exponential, growth_rate: 0.002, u_min: 0.0, "
                          f"layer: {layer[kernel]}}}\n")
            result = simulate(parse_scenario(text + extra, base_dir=folder))
            state, solver = result.state, result.solver
            covered = solver.sources[0].weight > 0.0
            area = math.fsum(solver.terrain.mesh.cell_area[covered])
            reached_by_flow = state.peak_h > 0.0
            s = result.summary
            out[f"{kernel}-{'both' if with_entrainment else 'snow'}"] = {
                "supplied": s["supplied_volume"], "expected": RATE * state.t * area,
                "entrained": s["entrained_volume"], "balance": s["mass_balance_error"],
                "stat": state.statistics.supplied_volume,
                "covered": int(covered.sum()),
                "dry_cells_snowed": int(np.count_nonzero(covered & (result.h0 == 0.0)
                                                         & (state.h > 0.0))),
                "covered_and_released": int(np.count_nonzero(covered & (result.h0 > 0.0))),
            }
    # the summary line of ``avflow run``
    yaml = Path(folder) / "snow.yaml"
    yaml.write_text(PLANE + _rheology("coulomb")
                    + f"sources: [{{law: snowfall, rate: {RATE!r}, polygon: {snow}}}]\n")
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        code = main(["run", str(yaml), "-o", str(Path(folder) / "snow.nc")])
    out["cli"] = {"code": code, "stdout": buffer.getvalue()}
    return out


def case_cuda() -> dict:
    """On the CUDA simulator: the law, the map and the source (with entrainment) against
    the CPU grid kernel."""
    snow = (f"sources: [{{law: snowfall, rate: {RATE!r}, x: [240.0, 340.0], "
            "y: [60.0, 180.0]}]\nentrainment: {law: exponential, growth_rate: 0.002, "
            "u_min: 0.0, layer: {depth: 0.5, x: [0.0, 250.0]}}\n")
    out = {}
    for name, law, k, text in (("law", "linear_speed", 0.0, PLANE),
                               ("law-speed", "linear_speed", 0.05, PLANE),
                               ("sources", "coulomb", 0.0, PLANE + snow)):
        cpu = _run(text, "grid", law, k)
        gpu = _run(text, "grid", law, k, backend="cuda")
        names = ("h", "hu", "hv", "peak_h", "peak_speed", "arrival", "last_moved", "maps",
                 "supplied", "erodible")
        out[name] = {n: _same(getattr(cpu.state, n), getattr(gpu.state, n)) for n in names}
        out[name]["steps"] = [cpu.state.steps, gpu.state.steps]
        out[name]["balance"] = gpu.summary["mass_balance_error"]
        out[name]["supplied_volume"] = [cpu.summary.get("supplied_volume", 0.0),
                                 gpu.summary.get("supplied_volume", 0.0)]
    return out


# --- the tests ----------------------------------------------------------------------------------


def _child(*args, simulate_cuda: bool = False) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT)] + sys.path))
    if simulate_cuda:
        env["NUMBA_ENABLE_CUDASIM"] = "1"
    else:
        env.pop("NUMBA_ENABLE_CUDASIM", None)
    done = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True,
                          env=env, timeout=1500)
    assert done.returncode == 0, done.stdout + done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def kernels():
    return _child("kernels")


@pytest.mark.parametrize("kernel", list(SCENES))
def test_the_law_without_its_speed_term_is_coulomb_bit_for_bit(kernels, kernel):
    report = kernels[kernel]
    assert report["kernel_used"] == ("faces" if kernel == "profile" else kernel)
    assert report["steps"][0] == report["steps"][1] > 0
    assert all(report["equal"].values()), report["equal"]


@pytest.mark.parametrize("kernel", list(SCENES))
def test_the_speed_term_brakes(kernels, kernel):
    coulomb, same, braked = kernels[kernel]["runout"]
    assert same == coulomb
    assert braked < coulomb


@pytest.mark.parametrize("kernel", list(SCENES))
def test_the_map_holds_the_largest_momentum_the_cells_saw(kernels, kernel):
    report = kernels[kernel]
    assert report["map_rows"] == 1
    assert report["map_covers_snapshots"]
    # |h u| <= max h * max |u| cell by cell; and the flow really moved
    assert 0.0 < report["map_max"] <= report["map_bound"] * (1 + 1e-12)


def test_the_map_is_in_the_file_with_cf_attributes_and_exported(tmp_path):
    report = _child("files", str(tmp_path))
    assert report["dims"] == ["y", "x"]
    attrs = report["attrs"]
    assert attrs["units"] == "m2 s-1"
    assert attrs["long_name"] == "maximum momentum per unit width |h u|"
    assert attrs["cell_methods"] == "duration: maximum"
    assert "grid_mapping" not in attrs or attrs["grid_mapping"] == "crs"
    assert "a test law: mu + k |u|" in report["references"]
    assert report["export_code"] == 0
    assert report["tif_max"] == pytest.approx(report["nc_max"], rel=1e-6)  # float32 GeoTIFF


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    return _child("sources", str(tmp_path_factory.mktemp("sources")))


@pytest.mark.parametrize("kernel", list(SCENES))
@pytest.mark.parametrize("together", ["snow", "both"])
def test_the_source_adds_its_rate_times_area_and_time_and_the_balance_holds(sources, kernel,
                                                                          together):
    """Snowfall alone, and with entrainment: what the sources added is rate x area x time
    (1e-12), the books close to 1e-12, and snow lies on cells the flow never reached."""
    report = sources[f"{kernel}-{together}"]
    assert report["covered"] > 0 and report["covered_and_released"] == 0
    assert report["supplied"] == pytest.approx(report["expected"], rel=1e-12)
    assert report["stat"] == pytest.approx(report["supplied"], rel=1e-12)
    assert report["balance"] <= 1e-12
    assert report["dry_cells_snowed"] == report["covered"]
    if together == "both":
        assert report["entrained"] > 0.0


def test_the_summary_line_counts_what_the_source_added(sources):
    report = sources["cli"]
    assert report["code"] == 0
    assert "+ supplied" in report["stdout"], report["stdout"]


@pytest.mark.skipif(importlib.util.find_spec("numba_cuda") is None,
                    reason="numba-cuda is not installed (pip install 'avflow[cuda]'); the "
                    "GPU backend's tests need its simulator")
def test_the_law_the_map_and_the_source_on_the_cuda_simulator():
    """The GPU backend against the CPU grid kernel, bit for bit on the simulator; the
    sources' volume to round-off (summed in another order), the balance closed."""
    report = _child("cuda", simulate_cuda=True)
    for name, equal in report.items():
        steps = equal.pop("steps")
        balance = equal.pop("balance")
        cpu, gpu = equal.pop("supplied_volume")
        assert steps[0] == steps[1] > 0, name
        assert all(equal.values()), (name, equal)
        assert balance <= 1e-12
        assert gpu == pytest.approx(cpu, rel=1e-12)


if __name__ == "__main__":
    register()
    case = sys.argv[1]
    if case == "kernels":
        report = case_kernels()
    elif case == "files":
        report = case_files(sys.argv[2])
    elif case == "sources":
        report = case_sources(sys.argv[2])
    else:
        report = case_cuda()
    print(json.dumps(report))


def test_no_map_takes_a_name_the_run_file_uses():
    """The names a registered map may not take cover every variable the run file writes
    (the fields, the summaries, the geometry); a name that slipped through is still refused
    when the file is made, never written over."""
    import numpy as np

    from avflow.output import cf
    from avflow.scenario.extensions import BUILT_IN_FIELDS, ExtensionError, register_map

    missing = (set(cf.FIELDS) | set(cf.SUMMARIES) | {"cell_area", "crs", "duration_bounds",
                                                      "structure_height"}) - set(BUILT_IN_FIELDS)
    assert not missing, missing
    with pytest.raises(ExtensionError, match="another name"):
        register_map("peak_thickness", lambda old, h, hu, hv, speed, t: h, "m", "x")
    data = {"bed_elevation": (("y", "x"), np.zeros((2, 2)), {})}
    with pytest.raises(ValueError, match="bed_elevation"):
        cf.add_registered(data, {}, "bed_elevation", (("y", "x"), np.ones((2, 2)), {}))
    assert not data["bed_elevation"][1].any()
