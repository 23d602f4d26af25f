"""Nothing lost, nothing invented: outputs never replace an input or a file that belongs to
one (a DEM's .prj, an extension file), a full disk is one line and leaves nothing, every
number a command takes is checked, and results the data cannot give are refused.

Hand-made DEMs (a slope of three planes, as in test_release_areas) keep each case quick.
"""

from __future__ import annotations

import math
import os
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from avflow.cli import main

ROOT = Path(__file__).resolve().parents[1]
DX = 5.0


def one_line(err: str) -> str:
    assert "Traceback" not in err, err
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert len(lines) == 1, err
    return lines[0]


def cli(argv, capsys):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def child(*argv, cwd=None, limit=None, env=None, timeout=300):
    """``python -m avflow ARGS`` in a child; ``limit``: files larger than that many bytes
    cannot be written (EFBIG, as on a full disk)."""
    pre = (lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))) if limit else None
    full_env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT),
                                                            os.environ.get("PYTHONPATH", "")])}
    full_env.pop("AVFLOW_EXTENSIONS", None)
    full_env.update(env or {})
    return subprocess.run([sys.executable, "-m", "avflow", *map(str, argv)], cwd=cwd,
                          env=full_env, capture_output=True, text=True, timeout=timeout,
                          preexec_fn=pre)


def steps_dem(folder: Path, name: str = "d3.asc", crs: str | None = "EPSG:2056") -> Path:
    """Three planes (20, 40, 65 degrees) falling east, 600 x 300 m at 5 m; an ASCII grid
    has its CRS in a .prj beside it."""
    import rasterio
    from rasterio.transform import from_origin

    x = np.arange(DX / 2, 600.0, DX)
    y = np.arange(DX / 2, 300.0, DX)
    t = [math.tan(math.radians(a)) for a in (20.0, 40.0, 65.0)]
    drop = np.where(x < 200, t[0] * x, np.where(x < 400, t[0] * 200 + t[1] * (x - 200),
                                                t[0] * 200 + t[1] * 200 + t[2] * (x - 400)))
    z = 3000.0 - np.tile(drop, (y.size, 1))
    path = folder / name
    driver = "AAIGrid" if name.endswith(".asc") else "GTiff"
    with rasterio.open(path, "w", driver=driver, width=x.size, height=y.size, count=1,
                       dtype="float64", crs=crs, transform=from_origin(0, 300, DX, DX)) as ds:
        ds.write(z[::-1], 1)
    return path


def digests(folder: Path) -> dict:
    import hashlib

    return {p.name: (p.stat().st_ino, hashlib.sha256(p.read_bytes()).hexdigest())
            for p in sorted(folder.iterdir()) if p.is_file()}


# --- 1. no output replaces an input, nor a file that belongs to one --------------------------


def test_a_shapefile_never_replaces_the_dems_projection(tmp_path, capsys):
    dem = steps_dem(tmp_path)
    assert (tmp_path / "d3.prj").exists()
    before = digests(tmp_path)
    code, out, err = cli(["release-areas", dem, "-o", tmp_path / "d3.shp"], capsys)
    assert code == 2 and "wrote" not in out
    line = one_line(err)
    assert "d3.prj" in line and "input" in line
    assert digests(tmp_path) == before  # the .prj is the DEM's own, same file, same bytes


def test_an_extension_file_is_an_input(tmp_path):
    (tmp_path / "law.py").write_text("from avflow import extend\n")
    (tmp_path / "s.yaml").write_text((ROOT / "scenarios" / "seed_dambreak_flat_dx20.yaml")
                                     .read_text())
    before = (tmp_path / "law.py").read_text()
    done = child("run", "--extensions", "law.py", "s.yaml", "-o", "law.py", cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert "law.py" in one_line(done.stderr) and "input" in done.stderr
    done = child("run", "s.yaml", "-o", "law.py", cwd=tmp_path,
                 env={"AVFLOW_EXTENSIONS": str(tmp_path / "law.py")})
    assert done.returncode == 2 and "input" in one_line(done.stderr)
    assert (tmp_path / "law.py").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["law.py", "s.yaml"]


@pytest.mark.parametrize("target", ["X.shp", "X.gpkg"])
def test_release_areas_on_a_full_disk_is_one_line_and_leaves_nothing(tmp_path, target):
    dem = steps_dem(tmp_path)
    out = tmp_path / "out"
    done = child("release-areas", dem, "-o", out / target, limit=100)
    assert done.returncode == 1, done.stderr
    line = one_line(done.stderr)
    assert f"cannot write {out / target}" in line and len(line) < 300
    assert "wrote" not in done.stdout
    assert not out.exists() or list(out.iterdir()) == []


def test_a_full_disk_keeps_the_previous_shapefile_whole(tmp_path):
    dem = steps_dem(tmp_path)
    target = tmp_path / "out" / "X.shp"
    assert child("release-areas", dem, "-o", target).returncode == 0
    before = digests(target.parent)
    assert set(before) == {"X.shp", "X.shx", "X.dbf", "X.prj", "X.cpg"}
    done = child("release-areas", dem, "--slope-min", "35", "-o", target, limit=100)
    assert done.returncode == 1 and "cannot write" in one_line(done.stderr)
    assert digests(target.parent) == before


@pytest.mark.parametrize("kind", ["device", "fifo", "huge"])
def test_an_extension_file_that_is_no_file_is_refused_at_once(tmp_path, kind):
    if kind == "device":
        path = Path("/dev/zero")
    elif kind == "fifo":
        path = tmp_path / "law.py"
        os.mkfifo(path)
    else:
        path = tmp_path / "law.py"
        with open(path, "wb") as f:
            f.truncate(64 << 20)  # sparse: nothing written
    done = child("run", "--extensions", path, "nothere.yaml", timeout=60)
    assert done.returncode == 2
    assert str(path) in one_line(done.stderr)


# --- 2. every number a command takes is checked -----------------------------------------------


@pytest.mark.parametrize("option, value", [
    ("--gradient", "nan"), ("--gradient", "1e308"), ("--reference-elevation", "inf"),
    ("--wind-direction", "nan"), ("--wind-direction", "inf"), ("--wind-direction", "1e308"),
    ("--wind-direction", "360"), ("--snow-depth", "1e6"), ("--snow-depth", "inf"),
    ("--d0", "1e308"), ("--d0", "nan"), ("--split-aspect", "nan")])
def test_release_areas_refuses_numbers_no_snow_cover_has(tmp_path, capsys, option, value):
    dem = steps_dem(tmp_path)
    code, out, err = cli(["release-areas", dem, "-o", tmp_path / "r.gpkg", option, value],
                         capsys)
    assert code == 2 and "wrote" not in out
    assert one_line(err).startswith(f"avflow: error: {option} must be")
    assert not (tmp_path / "r.gpkg").exists()


def test_a_slope_band_below_the_thickness_rules_reach_is_refused_with_d0(tmp_path, capsys):
    """0.291 / (sin psi - 0.202 cos psi) is negative below 11.42 degrees: -0.33 m before."""
    dem = steps_dem(tmp_path)
    code, _, err = cli(["release-areas", dem, "-o", tmp_path / "r.gpkg", "--d0", "1",
                        "--slope-min", "5"], capsys)
    assert code == 2 and "--slope-min must be above 11.42 degrees" in one_line(err)
    code, out, _ = cli(["release-areas", dem, "-o", tmp_path / "r.gpkg", "--d0", "1"], capsys)
    assert code == 0
    import pyogrio.raw

    meta, *_, fields = pyogrio.raw.read(tmp_path / "r.gpkg")
    thickness = fields[list(meta["fields"]).index("thickness")]
    assert (thickness > 0).all() and np.isfinite(thickness).all()


def test_a_dem_smaller_than_the_roughness_window_says_so(tmp_path, capsys):
    from avflow.terrain.raster import write_tif

    x = y = np.arange(2.5, 25.0, 5.0)
    write_tif(tmp_path / "small.tif", np.add.outer(y, x) * 0.8, x, y, None)
    code, _, err = cli(["release-areas", tmp_path / "small.tif", "-o", tmp_path / "r.gpkg"],
                       capsys)
    assert code == 2
    line = one_line(err)
    assert "smaller than the slope and roughness window (7 x 7 cells" in line
    assert "no cell meets" not in line


@pytest.mark.parametrize("options, field", [
    ({"wind_direction": float("nan")}, "wind_direction"),
    ({"snow_depth": float("inf")}, "snow_depth"),
    ({"min_area": "big"}, "min_area"),
    ({"roughness": "yes"}, "roughness")])
def test_from_dem_options_are_typed_and_named(options, field):
    from avflow.terrain.release_areas import PRAError, PRASettings

    with pytest.raises(PRAError) as err:
        PRASettings(**options)
    assert str(err.value).startswith(f"{field} must be")


PLANE = """
name: dam-{tag}
terrain:
  kind: plane
  slope_deg: 25.0
  azimuth_deg: 180.0
  extent: {{x: [0.0, 200.0], y: [0.0, 400.0]}}
grid: {{dx: 10.0}}
release: {{kind: cylinder, center: [100.0, 310.0], radius: 30.0, thickness: 3.0}}
rheology: {{law: coulomb, delta_deg: 20.0}}
structures: [{structure}]
time: {{end: 40.0, cfl: 0.5}}
output: {{every: 5.0}}
"""


def _line(folder, xy):
    import json

    path = folder / "line.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": [{
        "type": "Feature", "properties": {},
        "geometry": {"type": "LineString", "coordinates": [list(p) for p in xy]}}]}))
    return path


@pytest.mark.parametrize("xy, structure, field, words", [
    ([(0, 250), (200, 250)], "height: 1.0e300, side_slope_deg: 40", "structures[0].height",
     "higher than the map's relief"),
    ([(0, 250), (200, 250)], "height: 1.0e15, side_slope_deg: 40", "structures[0].height",
     "higher than the map's relief"),
    ([(0, 250), (200, 250)], "height: 5, side_slope_deg: 0", "structures[0].side_slope_deg",
     "must slope"),
    ([(0, 250), (200, 250)], "height: 5, side_slope_deg: 5.0e-324",
     "structures[0].side_slope_deg", "must slope"),
    ([(100, 250), (100, 250)], "height: 5, side_slope_deg: 40", "structures[0].line",
     "zero length"),
    ([(100, 250), (100, 250)], "kind: wall, height: 5", "structures[0].line", "zero length"),
    ([(0, 250), (200, 250), (150, 200), (150, 300)], "height: 5, side_slope_deg: 40",
     "structures[0].line", "crosses itself"),
    ([(100, 10), (100, 390)], "height: 5, side_slope_deg: 40", "structures[0].line",
     "runs through the release"),
    ([(0, 310), (200, 310)], "kind: wall, height: 5", "structures", "a wall covers"),
])
def test_structures_the_flow_cannot_give_volumes_for_are_refused(tmp_path, capsys, xy,
                                                                  structure, field, words):
    _line(tmp_path, xy)
    scene = tmp_path / "s.yaml"
    scene.write_text(PLANE.format(tag="x", structure="{line: line.geojson, "
                                  + structure + "}"))
    code, out, err = cli(["run", scene, "-o", tmp_path / "s.nc"], capsys)
    line = one_line(err)
    assert code == 2, line
    assert field in line and words in line
    assert not (tmp_path / "s.nc").exists()


# --- alpha-beta: coefficients read as written, angles of a path that descends --------------


@pytest.mark.parametrize("spec", ["1_0,0,0,-3,1", "1e308,0,0,0,1", "1,0,0,-1e308,1",
                                  "0,0,0,-5,1", "2,0,0,0,1", "1,0,0,0,1e300",
                                  "infinity,0,0,0,1", "0x1,0,0,0,1"])
def test_alpha_beta_coefficients_must_give_an_angle(spec):
    from avflow.output.alphabeta import AlphaBetaError, regression

    with pytest.raises(AlphaBetaError):
        regression(spec)


def test_alpha_beta_refuses_curvature_terms_that_leave_the_angles():
    from avflow.output.alphabeta import AlphaBetaError, alpha_beta, regression

    s = np.arange(0.0, 3000.0, 10.0)
    z = 1000.0 * np.exp(-s / 600.0)  # concave: z'' > 0
    with pytest.raises(AlphaBetaError, match="not an angle"):
        alpha_beta(s, z, regression("1,1e300,0,0,1"))
    assert 0 < alpha_beta(s, z, regression("austria")).alphas[0] < 90


def test_path_angles_need_a_path_that_descends_from_the_release():
    from avflow.output.alphabeta import AlphaBetaError, alpha_beta

    s = np.arange(0.0, 1500.0, 10.0)
    t30, t5 = math.tan(math.radians(30)), math.tan(math.radians(5))
    down = np.where(s <= 600, 1000.0 - t30 * s, 1000.0 - t30 * 600 - t5 * (s - 600))
    with pytest.raises(AlphaBetaError, match="does not descend from the release"):
        alpha_beta(s, down[::-1].copy())  # drawn uphill: beta was negative
    assert 20 < alpha_beta(s, down).beta < 30  # the same path drawn down the fall line
    # across the runout zone (nothing steeper than 10 degrees): no angles, not negative ones
    across = alpha_beta(s, 100.0 + 0.01 * np.sin(s / 50.0))
    assert math.isnan(across.beta) and all(math.isnan(a) for a in across.alphas)


# --- every layer in the DEM's CRS -----------------------------------------------------------


@pytest.mark.parametrize("kind", ["polygons", "raster"])
def test_a_forest_layer_in_another_crs_is_refused(tmp_path, capsys, kind):
    import json

    dem = steps_dem(tmp_path, "dem.tif")  # CH1903+ / LV95
    if kind == "polygons":
        forest = tmp_path / "forest.geojson"  # WGS 84 degrees: would match nothing
        forest.write_text(json.dumps({"type": "FeatureCollection", "features": [{
            "type": "Feature", "properties": {}, "geometry": {"type": "Polygon",
            "coordinates": [[[7.0, 46.0], [7.1, 46.0], [7.1, 46.1], [7.0, 46.0]]]}}]}))
    else:
        forest = steps_dem(tmp_path, "forest.tif", crs="EPSG:32632")  # > 0 everywhere
    code, out, err = cli(["release-areas", dem, "--forest", forest, "-o",
                          tmp_path / "r.gpkg"], capsys)
    assert code == 2 and "wrote" not in out
    line = one_line(err)
    assert str(forest) in line and "reproject it to the DEM's CRS" in line
    assert not (tmp_path / "r.gpkg").exists()


def test_an_extension_map_may_not_take_a_built_in_maps_name(tmp_path):
    (tmp_path / "maps.py").write_text('''from avflow import extend


@extend.output_map("peak_thickness", units="m", long_name="not the built-in one")
def peak_thickness(old, h, hu, hv, speed, t):
    return 0.0
''')
    done = child("run", "--extensions", "maps.py", "nothere.yaml", cwd=tmp_path, timeout=120)
    assert done.returncode == 2
    line = one_line(done.stderr)
    assert "maps.py" in line and "'peak_thickness'" in line and "another name" in line


# --- signals: a Ctrl-C is never lost ---------------------------------------------------------


def _swallowed_ctrl_c():
    """A Ctrl-C that code between the signal and the command eats (a finalizer, a library's
    bare except), as happened inside a release run here."""
    import signal

    try:
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(1000):  # the handler runs at the next bytecode boundary
            pass
    except KeyboardInterrupt:
        pass


def test_a_swallowed_ctrl_c_still_ends_the_command_as_interrupted(monkeypatch, capsys):
    import avflow.cli as cli_module

    def region(args):
        _swallowed_ctrl_c()
        return 0  # ran to the end as if nothing happened

    monkeypatch.setattr(cli_module, "_cmd_region", region)
    import signal

    # Python's own handler, as a command starts (a test runner's worker may have its own)
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        code, _, err = cli(["region", "any.yaml", "-o", "out"], capsys)
        assert code == 130 and one_line(err) == "avflow: interrupted"
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # put back
    finally:
        signal.signal(signal.SIGINT, old)


def test_a_region_run_here_stops_before_the_next_release_after_a_ctrl_c(monkeypatch):
    import signal

    import avflow.cli as cli_module
    import avflow.region.orchestrate as orchestrate
    from avflow.errors import INTERRUPTS

    ran, merged = [], []

    def run_release(task):
        ran.append(task)
        _swallowed_ctrl_c()
        return {"task": task}

    monkeypatch.setattr(orchestrate, "run_release", run_release)
    INTERRUPTS.clear()
    old = signal.signal(signal.SIGINT, cli_module._interrupt)
    try:
        with pytest.raises(KeyboardInterrupt):
            orchestrate._run([1, 2, 3], 0, None, None, merged.append, {}, None)
    finally:
        signal.signal(signal.SIGINT, old)
        INTERRUPTS.clear()
    assert ran == [1] and merged == [{"task": 1}]


# --- misleading messages ----------------------------------------------------------------------


def _region_store(folder: Path) -> Path:
    import zarr
    from pyproj import CRS as ProjCRS

    from avflow.region.merge import RegionStore
    from avflow.region.windows import DemInfo

    dem = DemInfo("none.tif", 300, 200, 2_600_000.0, 1_200_000.0, 10.0, 10.0,
                  ProjCRS.from_user_input("EPSG:2056").to_wkt(), "float32")
    path = folder / "region.zarr"
    s = RegionStore(path, dem, ("pressure", "thickness", "speed"), 256,
                    {"title": "t", "source": "avflow region"})
    h = np.random.default_rng(1).random((100, 100)).astype(np.float32) * 3
    s.add(1, [((10, 110, 20, 120), {"peak_thickness": h, "peak_speed": 5 * h,
                                   "peak_pressure": (h * 20000).astype(np.float32)}, 0.5)])
    zarr.consolidate_metadata(str(path))
    return path


def test_a_failed_region_export_blames_the_output_not_the_store(tmp_path, capsys,
                                                                 monkeypatch):
    import rasterio.shutil

    store = _region_store(tmp_path)

    def full(*args, **kwargs):  # GDAL's COG driver on a full disk, as a foreign error
        raise RuntimeError("TIFFAppendToStrip: Write error at scanline 0")

    monkeypatch.setattr(rasterio.shutil, "copy", full)
    code, out, err = cli(["export", store, "-o", tmp_path / "gis"], capsys)
    line = one_line(err)
    assert code == 1, line
    assert f"cannot write {tmp_path / 'gis'}" in line and "damaged" not in line
    assert not (tmp_path / "gis").exists() or not any((tmp_path / "gis").iterdir())


def test_a_signal_noted_while_the_cluster_closes_is_not_lost():
    """Signals are only noted while dask runs (raised at safe points); one that came after
    the last safe point, while the cluster closed, is raised when the block ends."""
    import logging
    import signal

    from avflow.ensemble.orchestrate import _deferred_sigint

    level = logging.getLogger("distributed").level
    old = signal.signal(signal.SIGINT, signal.default_int_handler)  # as a command starts
    try:
        with pytest.raises(KeyboardInterrupt):
            with _deferred_sigint():
                os.kill(os.getpid(), signal.SIGINT)
                for _ in range(1000):
                    pass  # no check(): as in the cluster's closing
        # the cluster's own tracebacks of connections closed on purpose are not printed
        assert logging.getLogger("distributed").level > logging.CRITICAL
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        logging.getLogger("distributed").setLevel(level)
        signal.signal(signal.SIGINT, old)


def test_many_commands_in_one_process_do_not_stack_warning_handlers(capsys):
    """main() wrapped warnings.showwarning on every call: after a few thousand commands in
    one process (the fuzzer's), any warning hit Python's recursion limit."""
    import warnings

    for _ in range(3000):
        main(["release-areas", "nothere.tif", "-o", "x.gpkg", "--split-aspect", "nan"])
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.warn("a foreign warning", RuntimeWarning)  # RecursionError before
    assert "a foreign warning" in capsys.readouterr().err
