"""The QGIS plugin (qgis/avflow_qgis) end to end in a real, headless QGIS: qgis_process runs
its algorithms on AvaFrame's Kontertal path at 20 m, and PyQGIS (the system Python, in a
subprocess: this venv cannot import qgis) checks the styles and Cancel. Skipped where QGIS
is not installed (apt-get install qgis python3-qgis qgis-providers)."""

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
KOT = ROOT / "data" / "avaframe" / "avaKot"
# Debian's qgis_process wrapper adds --noversioncheck, which the 3.22 executable rejects
QGIS_PROCESS = shutil.which("qgis_process.bin") or shutil.which("qgis_process")
SYSTEM_PYTHON = "/usr/bin/python3"


def _pyqgis() -> bool:
    if not os.path.exists(SYSTEM_PYTHON):
        return False
    return subprocess.run([SYSTEM_PYTHON, "-c", "import qgis.core"], capture_output=True,
                          env={"PATH": "/usr/bin:/bin"}).returncode == 0


pytestmark = pytest.mark.skipif(
    QGIS_PROCESS is None or not _pyqgis(),
    reason="QGIS is not installed (qgis_process and PyQGIS in /usr/bin/python3); CI installs "
           "it with apt-get install qgis python3-qgis qgis-providers")


@pytest.fixture(scope="module")
def qgis_env(tmp_path_factory):
    """A fresh QGIS profile, offscreen, with the plugin from the repository enabled, and
    avflow of this checkout as the provider's separate process."""
    base = tmp_path_factory.mktemp("qgis")
    runtime = base / "xdg"
    runtime.mkdir(mode=0o700)
    wrapper = base / "avflow"
    wrapper.write_text(f"#!/bin/sh\nPYTHONPATH={ROOT} exec {sys.executable} -m avflow \"$@\"\n")
    wrapper.chmod(0o755)
    cache = os.environ.get("AVFLOW_CACHE_DIR") or str(Path.home() / ".cache" / "avflow")
    env = {"PATH": "/usr/bin:/bin", "HOME": str(base / "home"), "XDG_RUNTIME_DIR": str(runtime),
           "QT_QPA_PLATFORM": "offscreen", "QGIS_PLUGINPATH": str(ROOT / "qgis"),
           "AVFLOW_EXECUTABLE": str(wrapper), "AVFLOW_CACHE_DIR": cache, "LANG": "C.UTF-8",
           # QGIS opening a raster writes its statistics beside it (.aux.xml): not into
           # the repository's data
           "GDAL_PAM_ENABLED": "NO"}
    (base / "home").mkdir()
    done = subprocess.run([QGIS_PROCESS, "plugins", "enable", "avflow_qgis"], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return {"env": env, "base": base}


def read_layer(path):
    """A vector file's fields (numpy arrays), its shapely geometries and CRS."""
    import pyogrio
    import shapely

    meta, _, geometry, values = pyogrio.raw.read(path)
    layer = dict(zip(meta["fields"], values))
    layer["geometry"] = list(shapely.from_wkb(geometry))
    layer["crs"] = meta["crs"]
    return layer


def qgis_process(qgis_env, algorithm, **params):
    args = [QGIS_PROCESS, "run", f"avflow:{algorithm}", "--json", "--"]
    args += [f"{k}={v}" for k, v in params.items()]
    done = subprocess.run(args, env=qgis_env["env"], capture_output=True, text=True,
                          timeout=900)
    try:
        out = json.loads(done.stdout)
    except json.JSONDecodeError:
        out = {}
    return done.returncode, out, done.stdout + done.stderr


def pyqgis(qgis_env, script):
    """Run a PyQGIS script (system Python) with the plugin importable; returns its JSON."""
    code = textwrap.dedent("""
        import json, sys
        sys.path.insert(0, {plugins!r})
        from qgis.core import QgsApplication
        app = QgsApplication([], False)
        app.initQgis()
        sys.path.insert(0, "/usr/share/qgis/python/plugins")
        from processing.core.Processing import Processing
        Processing.initialize()
        from avflow_qgis.provider import AvflowProvider
        provider = AvflowProvider()
        QgsApplication.processingRegistry().addProvider(provider)
        result = {{}}
    """).format(plugins=str(ROOT / "qgis")) + textwrap.dedent(script) + \
        (
        "\nprint('RESULT' + json.dumps(result), flush=True)\nimport os\nos._exit(0)\n")
    done = subprocess.run([SYSTEM_PYTHON, "-c", code], env=qgis_env["env"],
                          capture_output=True, text=True, timeout=900)
    line = [l for l in done.stdout.splitlines() if l.startswith("RESULT")]
    assert line, f"exit code {done.returncode}: " + done.stdout[-3000:] + done.stderr[-3000:]
    return json.loads(line[-1][len("RESULT"):])


@pytest.fixture(scope="module")
def kot_run(qgis_env):
    folder = qgis_env["base"] / "kot"
    rc, out, log = qgis_process(qgis_env, "run_scenario", DEM=KOT / "avaKot.asc",
                                RELEASE=KOT / "relKot.shp", THICKNESS_FIELD="thickness",
                                CELL_SIZE=20, NAME="kot", OUTPUT_FOLDER=folder)
    assert rc == 0, log[-3000:]
    return out["results"]


def test_the_provider_lists_every_algorithm(qgis_env):
    done = subprocess.run([QGIS_PROCESS, "list"], env=qgis_env["env"], capture_output=True,
                          text=True, timeout=300)
    for name in ("run_scenario", "load_run", "ensemble", "path_analysis", "release_areas",
                 "regional_map", "report_figure"):
        assert f"avflow:{name}" in done.stdout


def test_run_a_scenario_gives_the_maps_in_the_dem_crs(kot_run):
    import rasterio

    from avflow.output.maps import _ZONE_COLORS

    import re

    assert re.fullmatch(r"at rest|ended by rule, [0-9.]+% still moving", kot_run["STATUS"])
    tifs = {Path(p).stem.removeprefix("kot_"): p for p in kot_run["LAYERS"]}
    assert {"peak_pressure_class", "peak_thickness", "peak_speed", "peak_pressure",
            "deposit_thickness"} <= set(tifs)
    with rasterio.open(tifs["peak_pressure_class"]) as src:
        assert src.crs.to_epsg() == 31287  # MGI / Austria Lambert, from the release's .prj
        assert src.res == (20.0, 20.0)
        classes = src.read(1)
        palette = src.colormap(1)
    import numpy as np

    assert set(np.unique(classes)) <= {0, 1, 2, 3, 255}
    assert {1, 2, 3} <= set(np.unique(classes))  # every class reached on this path
    for k, color in enumerate(_ZONE_COLORS, start=1):  # the QML's colours are avflow plot's
        assert "#%02x%02x%02x" % palette[k][:3] == color
        assert color in Path(tifs["peak_pressure_class"]).with_suffix(".qml").read_text()
    # the scenario YAML beside the outputs repeats the run from the command line
    scenario = Path(kot_run["SCENARIO"])
    from avflow.scenario.schema import load_scenario

    sc = load_scenario(scenario)
    assert sc.grid.dx == 20.0 and sc.rheology.law == "samosat" and sc.physics.density == 200.0


def test_styles_load_in_qgis(qgis_env, kot_run):
    result = pyqgis(qgis_env, f"""
        from avflow_qgis import layers
        for path in {kot_run["LAYERS"]!r}:
            layer = layers.styled_raster(path, "x")
            r = layer.renderer()
            entry = {{"valid": layer.isValid(), "type": r.type(), "crs": layer.crs().authid()}}
            if r.type() == "paletted":
                entry["classes"] = [[c.value, c.color.name()] for c in r.classes()]
            elif r.type() == "singlebandpseudocolor":
                entry["items"] = [[i.value, i.color.name()] for i in
                                  r.shader().rasterShaderFunction().colorRampItemList()]
            result[path.rsplit("/", 1)[-1]] = entry
    """)
    assert all(e["valid"] and e["crs"] == "EPSG:31287" for e in result.values())
    classes = result["kot_peak_pressure_class.tif"]
    assert classes["type"] == "paletted"
    assert classes["classes"] == [[1, "#f2d21b"], [2, "#2b6fce"], [3, "#d7191c"]]
    pressure = result["kot_peak_pressure.tif"]
    assert [v for v, _ in pressure["items"]][:3] == [1.0, 3.0, 30.0]
    assert result["kot_peak_thickness.tif"]["type"] == "singlebandpseudocolor"
    assert result["kot_peak_speed.tif"]["type"] == "singlebandpseudocolor"


def test_load_a_run_names_its_status(qgis_env, kot_run):
    rc, out, log = qgis_process(qgis_env, "load_run", INPUT=kot_run["NETCDF"],
                                OUTPUT_FOLDER=qgis_env["base"] / "loaded")
    assert rc == 0, log[-3000:]
    assert out["results"]["STATUS"] == kot_run["STATUS"]
    assert len(out["results"]["LAYERS"]) >= 5


def test_report_figure_exports_pdf_and_png(qgis_env, kot_run):
    pdf, png = qgis_env["base"] / "fig" / "kot.pdf", qgis_env["base"] / "fig" / "kot.png"
    rc, out, log = qgis_process(qgis_env, "report_figure", INPUT=kot_run["NETCDF"], PDF=pdf,
                                PNG=png, DPI=60)
    assert rc == 0, log[-3000:]
    assert pdf.read_bytes()[:5] == b"%PDF-" and pdf.stat().st_size > 5000
    import numpy as np
    from PIL import Image

    with Image.open(png) as im:
        w, h = im.size  # A4 landscape at 60 dpi, give or take QGIS's rounding
        assert abs(w - 297 / 25.4 * 60) <= 1.5 and abs(h - 210 / 25.4 * 60) <= 1.5
        pixels = np.asarray(im.convert("RGB"), dtype=int)
    for color in ((0xf2, 0xd2, 0x1b), (0x2b, 0x6f, 0xce), (0xd7, 0x19, 0x1c)):
        # each class is drawn (in the map, at 90% over the hillshade, and in the legend)
        near = np.abs(pixels - np.array(color)).max(axis=-1) <= 30
        assert near.sum() > 50, color


def test_ensemble_gives_probabilities_between_0_and_1(qgis_env):
    import numpy as np
    import rasterio

    rc, out, log = qgis_process(
        qgis_env, "ensemble", DEM=KOT / "avaKot.asc", RELEASE=KOT / "relKot.shp",
        THICKNESS_FIELD="thickness", CELL_SIZE=20, NAME="kotens", LAW=2, PARAM_MIN=18,
        PARAM_MAX=24, FACTOR_MIN=1, FACTOR_MAX=1, MEMBERS=3, END_TIME=200,
        OUTPUT_FOLDER=qgis_env["base"] / "ens")
    assert rc == 0, log[-3000:]
    probabilities = [p for p in out["results"]["LAYERS"] if "exceedance_probability" in p]
    assert any("peak_pressure" in p for p in probabilities)
    for path in probabilities:
        with rasterio.open(path) as src:
            p = src.read(1, masked=True).compressed()
            assert src.crs.to_epsg() == 31287
        assert p.size and np.all((p >= 0) & (p <= 1))
        assert Path(path).with_suffix(".qml").read_text().count("colorrampshader") == 2


def test_an_avflow_error_fails_the_algorithm_with_its_line(qgis_env):
    rc, out, log = qgis_process(qgis_env, "run_scenario", DEM=KOT / "avaKot.asc",
                                RELEASE=KOT / "relKot.shp", THICKNESS_FIELD="thickness",
                                CELL_SIZE=20, LAW=3, DELTA=30, DELTA2=20, NAME="bad",
                                OUTPUT_FOLDER=qgis_env["base"] / "bad")
    assert rc != 0
    assert "avflow: error:" in log and "rheology.delta1_deg: must be smaller than delta2_deg" in log
    assert not (qgis_env["base"] / "bad" / "bad.nc").exists()


def test_cancel_stops_avflow_and_leaves_no_output(qgis_env):
    folder = qgis_env["base"] / "cancelled"
    result = pyqgis(qgis_env, f"""
        import threading, time
        from qgis.core import QgsProcessingContext, QgsProcessingFeedback, QgsProject
        import processing
        feedback = QgsProcessingFeedback()
        progress = []
        feedback.progressChanged.connect(lambda value: progress.append(value))
        def cancel_when_running():  # once avflow's progress bar has moved
            while not progress:
                time.sleep(0.05)
            result["progress_at_cancel"] = progress[-1]
            feedback.cancel()
        threading.Thread(target=cancel_when_running, daemon=True).start()
        started = time.time()
        try:
            processing.run("avflow:run_scenario", dict(
                DEM={str(KOT / "avaKot.asc")!r}, RELEASE={str(KOT / "relKot.shp")!r},
                THICKNESS_FIELD="thickness", CELL_SIZE=2.5, ORDER=1, END_TIME=400,
                NAME="cancelled", OUTPUT_FOLDER={str(folder)!r}), feedback=feedback)
            result["raised"] = False
        except Exception as err:
            result["raised"] = True
            result["message"] = str(err)
        result["seconds"] = time.time() - started
    """)
    assert result["raised"], result
    assert "Cancelled" in result["message"]
    assert 0 < result["progress_at_cancel"] < 100  # avflow's bar reached QGIS's, mid-run
    left = sorted(p.name for p in folder.iterdir())
    assert left == ["cancelled.yaml", "inputs"], left  # no NetCDF, no temporary file
    assert sorted(p.name for p in (folder / "inputs").iterdir()) == ["cancelled_release.gpkg"]


def test_path_analysis_gives_the_runout_and_alpha_beta_points(qgis_env, kot_run):
    rc, out, log = qgis_process(qgis_env, "path_analysis", INPUT=kot_run["NETCDF"],
                                LINE=KOT / "pathAB.shp", OUTPUT_FOLDER=qgis_env["base"] / "path")
    assert rc == 0, log[-3000:]
    res = out["results"]
    assert "runout (pressure >= 1 kPa)" in res["SUMMARY"] and "alpha-beta (norway)" in res["SUMMARY"]
    points = read_layer(res["POINTS"])
    assert list(points["point"]) == ["runout", "beta point", "alpha", "alpha - 1 SD",
                                     "alpha - 2 SD"]
    assert points["crs"] == "EPSG:31287"
    s = points["s"]
    assert (s[1:] > s[:-1]).all()  # beta, then alpha and its SDs farther down the path


def test_release_areas_from_the_dem(qgis_env):
    target = qgis_env["base"] / "pra" / "release_areas.gpkg"
    rc, out, log = qgis_process(qgis_env, "release_areas", DEM=KOT / "avaKot.asc",
                                OUTPUT=target)
    assert rc == 0, log[-3000:]
    areas = read_layer(target)
    assert len(areas["geometry"]) > 0 and all(g.area > 0 for g in areas["geometry"])


def test_regional_map_of_a_release_layer(qgis_env):
    import numpy as np
    import rasterio

    rc, out, log = qgis_process(qgis_env, "regional_map", DEM=KOT / "avaKot.asc",
                                RELEASE=KOT / "relKot.shp", THICKNESS_FIELD="thickness",
                                CELL_SIZE=20, OUTPUT_FOLDER=qgis_env["base"] / "region")
    assert rc == 0, log[-3000:]
    tifs = out["results"]["LAYERS"]
    pressure = next(p for p in tifs if p.endswith("region_peak_pressure.tif"))
    with rasterio.open(pressure) as src:
        assert src.res == (20.0, 20.0)
        kpa = src.read(1, masked=True)
    assert float(kpa.max()) > 30  # kPa, as the 1 / 3 / 30 kPa style expects
    assert Path(pressure).with_suffix(".qml").is_file()
    assert not Path(pressure.replace(".tif", "_release.qml")).exists()  # ids are not styled


def test_the_plugin_zip_installs_into_a_fresh_profile(qgis_env, tmp_path):
    import zipfile

    done = subprocess.run([sys.executable, str(ROOT / "qgis" / "build_plugin.py"), "-o",
                           str(tmp_path)], capture_output=True, text=True, check=True)
    archive = next(tmp_path.glob("avflow_qgis-*.zip"))
    assert str(archive) in done.stdout
    profile = tmp_path / "home"
    plugins = profile / ".local/share/QGIS/QGIS3/profiles/default/python/plugins"
    with zipfile.ZipFile(archive) as zf:
        names = zf.namelist()
        assert "avflow_qgis/metadata.txt" in names and "avflow_qgis/styles/peak_pressure_class.qml" in names
        assert not any("__pycache__" in n for n in names)
        zf.extractall(plugins)  # what Install from ZIP does
    env = dict(qgis_env["env"], HOME=str(profile))
    env.pop("QGIS_PLUGINPATH")
    for args in (["plugins", "enable", "avflow_qgis"], ["list"]):
        run = subprocess.run([QGIS_PROCESS] + args, env=env, capture_output=True, text=True,
                             timeout=300)
        assert run.returncode == 0, run.stderr[-2000:]
    assert "avflow:run_scenario" in run.stdout


def test_run_adds_named_styled_layers_to_the_project(qgis_env):
    """What the dialog does after a run: Processing loads the layers the algorithm queued,
    each named with what it holds and the run's status, each styled."""
    folder = qgis_env["base"] / "loaded_into_project"
    result = pyqgis(qgis_env, f"""
        from qgis.core import QgsProcessingContext, QgsProcessingFeedback, QgsProject
        from processing.gui.Postprocessing import handleAlgorithmResults
        alg = QgsApplication.processingRegistry().algorithmById("avflow:run_scenario").create()
        context = QgsProcessingContext()
        context.setProject(QgsProject.instance())
        feedback = QgsProcessingFeedback()
        out, ok = alg.run(dict(DEM={str(KOT / "avaKot.asc")!r},
                               RELEASE={str(KOT / "relKot.shp")!r}, THICKNESS_FIELD="thickness",
                               CELL_SIZE=20, NAME="kot", OUTPUT_FOLDER={str(folder)!r}),
                          context, feedback)
        handleAlgorithmResults(alg, context, feedback, False, out)
        result["layers"] = {{l.name(): l.renderer().type()
                            for l in QgsProject.instance().mapLayers().values()}}
    """)
    layers = result["layers"]
    import re

    classes = next(n for n in layers if n.startswith("kot: peak pressure class"))
    status = classes[len("kot: peak pressure class (1 / 3 / 30 kPa) "):]
    assert re.fullmatch(r"\[(at rest|ended by rule, [0-9.]+% still moving)\]", status), classes
    assert layers[classes] == "paletted"
    assert layers[f"kot: peak pressure (kPa) {status}"] == "singlebandpseudocolor"
    assert layers[f"kot: peak flow thickness (m) {status}"] == "singlebandpseudocolor"
    assert layers[f"kot: peak speed (m/s) {status}"] == "singlebandpseudocolor"
    assert layers["kot: release"] == "singleSymbol"


def test_forest_and_a_dam_go_into_the_scenario(qgis_env):
    import json

    from avflow.scenario.schema import load_scenario

    # a dam across the path below the release (the path line itself runs through the
    # release, which avflow refuses: which side is upstream is not defined)
    dam_line = qgis_env["base"] / "dam_across.geojson"
    dam_line.write_text(json.dumps({
        "type": "FeatureCollection",
        "crs": {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::31287"}},
        "features": [{"type": "Feature", "properties": {}, "geometry": {
            "type": "LineString", "coordinates": [[177700.0, 377300.0],
                                                  [178100.0, 377300.0]]}}]}))
    rc, out, log = qgis_process(qgis_env, "run_scenario", DEM=KOT / "avaKot.asc",
                                RELEASE=KOT / "relKot.shp", THICKNESS_FIELD="thickness",
                                CELL_SIZE=20, FOREST=KOT / "resistance.shp", FOREST_CF=0.02,
                                STRUCTURES=dam_line, STRUCTURE_HEIGHT=3,
                                STRUCTURE_SLOPE=35, END_TIME=60, NAME="protected",
                                OUTPUT_FOLDER=qgis_env["base"] / "protected")
    assert rc == 0, log[-3000:]
    sc = load_scenario(out["results"]["SCENARIO"])
    assert sc.forest.c_f == 0.02 and sc.forest.polygon.endswith("protected_forest.gpkg")
    (dam,) = sc.structures
    assert (dam.kind, dam.height, dam.side_slope_deg) == ("dam", 3.0, 35.0)
    assert Path(out["results"]["NETCDF"]).is_file()


def test_the_scenario_beside_the_outputs_repeats_the_run(kot_run, tmp_path):
    """avflow run NAME.yaml, from a terminal, gives the plugin's run again, bit for bit."""
    import xarray as xr

    folder = Path(kot_run["SCENARIO"]).parent
    done = subprocess.run([sys.executable, "-m", "avflow", "run", kot_run["SCENARIO"], "-o",
                           str(tmp_path / "again.nc")], cwd=folder, capture_output=True,
                          text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert done.returncode == 0, done.stderr
    with xr.open_dataset(kot_run["NETCDF"]) as a, xr.open_dataset(tmp_path / "again.nc") as b:
        assert a.attrs["scenario_hash"] == b.attrs["scenario_hash"]
        assert (a["peak_pressure"].fillna(-1) == b["peak_pressure"].fillna(-1)).all()


def test_a_missing_avflow_is_one_clear_line(qgis_env):
    env = dict(qgis_env["env"], AVFLOW_EXECUTABLE=str(qgis_env["base"] / "no-such-avflow"))
    done = subprocess.run([QGIS_PROCESS, "run", "avflow:load_run", "--",
                           f"INPUT={KOT / 'avaKot.asc'}",
                           f"OUTPUT_FOLDER={qgis_env['base'] / 'nothing'}"],
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode != 0
    assert "avflow executable not found or not executable" in done.stdout + done.stderr
    assert "Settings > Options > Processing > Providers > avflow" in done.stdout + done.stderr


def test_the_provider_setting_names_avflow(qgis_env):
    """Settings > Options > Processing > Providers > avflow: the executable set there is the
    one run, before $AVFLOW_EXECUTABLE and the PATH."""
    result = pyqgis(qgis_env, f"""
        import os
        from processing.core.ProcessingConfig import ProcessingConfig
        from avflow_qgis import process
        result["default"] = process.executable()
        ProcessingConfig.setSettingValue("AVFLOW_EXECUTABLE", {str(sys.executable)!r})
        result["set"] = process.executable()
        ProcessingConfig.setSettingValue("AVFLOW_EXECUTABLE", "")
        del os.environ["AVFLOW_EXECUTABLE"]
        os.environ["PATH"] = "/nowhere"
        try:
            process.executable()
        except Exception as err:
            result["none"] = str(err)
    """)
    assert result["default"] == qgis_env["env"]["AVFLOW_EXECUTABLE"]
    assert result["set"] == sys.executable
    assert result["none"].startswith("avflow not found on the PATH")
