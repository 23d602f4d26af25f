"""Entrainment from scenario files (issue 30): mass that grows on its way.

- every form of the erodible layer (a depth over the map or a range, a raster, polygons
  with their thickness attribute, one thickness or another attribute) and each law's
  parameters reach the solver's MassSource in the kernels' units;
- a file written by ``avflow run`` holds the entrained volume over time and at the end, the
  layer left and the bed's change, and the balance released + entrained = on the map +
  outflow to 1e-12 from its own variables; the summary line says it;
- ensembles vary ``entrainment.e_b`` by its dotted path and report what was entrained;
- bad layers (negative depths, NODATA, another CRS, a missing attribute) are one line,
  exit code 2, before any run; AvaFrame's Kontertal entrainment example loads.

The laws themselves are tested against their formulas on the solver in
tests/test_entrainment.py.
"""

import math

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from avflow.cli import main
from avflow.ensemble.orchestrate import run_ensemble
from avflow.ensemble.report import write_report
from avflow.ensemble.spec import load_ensemble
from avflow.numerics.physics import (SOURCE_EROSION_ENERGY, SOURCE_EXPONENTIAL,
                                     SOURCE_SHEAR_THRESHOLD)
from avflow.scenario.schema import load_scenario
from avflow.simulation.runner import mass_source, prepare
from avflow.terrain.build import build_terrain
from avflow.terrain.raster import write_asc
from conftest import REPO, SCENARIOS
from test_friction_maps import LAMBERT, UTM33, centres, one_line, plane, polygons


def layer_of(path, **updates):
    """The MassSource of the scenario at ``path`` with ``updates`` and its terrain."""
    sc = load_scenario(path)
    if updates:
        sc = sc.with_updates(updates)
    terrain = build_terrain(sc)
    return mass_source(sc, terrain), terrain, sc


ENTRAINMENT = "entrainment: {law: erosion_energy, layer: {depth: 0.5}}\n"


# ---------------------------------------------------------------------------- the forms
def test_every_form_of_the_layer_is_sampled_at_the_cell_centres(tmp_path):
    xr_, yr = centres(0, 300, 0, 100, 10.0)
    xx, yy = np.meshgrid(xr_, yr)
    write_asc(tmp_path / "depth.asc", np.where(xx > 150, np.nan, 0.1 * (yy > 50)), xr_, yr)
    polygons(tmp_path / "ent.gpkg", [(100, 0, 200, 100), (150, 50, 250, 100)], [0.3, 0.6],
             field="thickness")
    polygons(tmp_path / "snow.geojson", [(100, 0, 200, 100)], [0.8], field="hs")
    # a 'thickness' of 0 that one thickness for all replaces: not read, not refused
    polygons(tmp_path / "zero.gpkg", [(100, 0, 200, 100)], [0.0], field="thickness")
    path = plane(tmp_path, "{law: voellmy, mu: 0.2, xi: 1000}", ENTRAINMENT)
    source, terrain, _ = layer_of(path)
    cx, cy = terrain.cell_xy()
    in_ent = (cx > 100) & (cx < 200)
    in_second = (cx > 150) & (cx < 250) & (cy > 50)
    cases = [
        ({"depth": 0.5}, np.full(cx.size, 0.5)),
        ({"depth": 0.5, "x": [100, 200], "y": [0, 50]},
         np.where((cx >= 100) & (cx <= 200) & (cy <= 50), 0.5, 0.0)),
        ({"raster": "depth.asc", "default": 0.0}, np.where(cx > 150, 0.0, 0.1 * (cy > 50))),
        ({"polygon": "ent.gpkg"}, np.where(in_second, 0.6, np.where(in_ent, 0.3, 0.0))),
        ({"polygon": "ent.gpkg", "thickness": 0.2}, np.where(in_ent | in_second, 0.2, 0.0)),
        ({"polygon": "zero.gpkg", "thickness": 0.2}, np.where(in_ent, 0.2, 0.0)),
        ({"polygon": "snow.geojson", "attribute": "hs"}, np.where(in_ent, 0.8, 0.0)),
    ]
    for layer, want in cases:
        source, _, _ = layer_of(path, **{"entrainment.layer": layer})
        np.testing.assert_array_equal(source.erodible, want, err_msg=str(layer))
    # on a profile: a depth over a range along the bed
    profile = tmp_path / "p.yaml"
    profile.write_text("name: p\nterrain: {kind: profile, length: 300, slope: {kind: constant, "
                       "theta_deg: 30}}\ngrid: {dx: 5}\nrelease: {kind: box, x: [10, 40], "
                       "thickness: 2}\nrheology: {law: voellmy, mu: 0.2, xi: 1000}\n"
                       "time: {end: 5}\nentrainment: {law: exponential, growth_rate: 0.01, "
                       "layer: {depth: 0.4, x: [100, 200]}}\n")
    source, terrain, _ = layer_of(profile)
    np.testing.assert_array_equal(source.erodible, np.where(
        (terrain.x >= 100) & (terrain.x <= 200), 0.4, 0.0))


def test_each_law_reaches_the_solver_in_its_units(tmp_path):
    path = plane(tmp_path, "{law: voellmy, mu: 0.2, xi: 1000}", ENTRAINMENT)
    cases = [
        ({"law": "exponential", "growth_rate": 0.004}, SOURCE_EXPONENTIAL, (0.004,)),
        ({"law": "exponential", "growth_factor": 3.0, "path_length": 500.0},
         SOURCE_EXPONENTIAL, (math.log(3.0) / 500.0,)),
        ({"law": "erosion_energy"}, SOURCE_EROSION_ENERGY, (5000.0,)),  # AvaFrame's default
        ({"law": "erosion_energy", "e_b": 2500.0}, SOURCE_EROSION_ENERGY, (2500.0,)),
        # k in m/(s kPa) -> m/(s Pa); tau_c RAMMS's 1 kPa; the flow's density for tau_b
        ({"law": "shear_threshold", "k": 0.025}, SOURCE_SHEAR_THRESHOLD,
         (0.025 / 1000.0, 1000.0, 200.0)),  # Voellmy without a density: snow's
    ]
    for block, kind, params in cases:
        source, _, _ = layer_of(path, entrainment={**block, "layer": {"depth": 0.5}})
        assert (source.kind, source.params) == (kind, params)
        assert source.density_ratio == 1.0 and source.u_min == 0.0  # the flow's density
    source, _, _ = layer_of(path, entrainment={"law": "erosion_energy", "density": 100.0,
                                               "u_min": 0.5, "layer": {"depth": 0.5}},
                            **{"physics.density": 200.0})
    assert (source.density_ratio, source.u_min) == (0.5, 0.5)  # AvaFrame's snow: 100 / 200
    _, _, solver, _ = prepare(load_scenario(path))
    assert solver.source is not None
    np.testing.assert_array_equal(solver.source.erodible, 0.5)


# ------------------------------------------------------------- a run and its file
@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """``avflow run`` of a plane with an erodible strip (erosion energy, a layer of
    density 1000 under a flow of 2000), a forest below it and an open foot, and its file."""
    folder = tmp_path_factory.mktemp("ent")
    path = plane(folder, "{law: voellmy, mu: 0.25, xi: 1000}",
                 "entrainment: {law: erosion_energy, density: 1000, "
                 "layer: {depth: 0.5, x: [120, 250]}}\n"
                 "forest: {x: [250, 280], c_f: 0.05}\nboundary: {x_max: outflow}\n"
                 "physics: {material: debris}\n",  # a flow of 2000 (Voellmy's own: snow)
                 slope=30.0, extent="{x: [0, 300], y: [0, 100]}",
                 release="{kind: box, x: [20, 80], y: [30, 70], thickness: 3.0}", end=24.0)
    out = folder / "run.nc"
    return path, out, main(["run", str(path), "-o", str(out)])


def test_the_file_of_a_run_holds_what_was_entrained_and_the_balance(written, capsys):
    path, out, code = written
    assert code == 0
    with xr.open_dataset(out) as ds:
        ds = ds.load()
    series = ds["entrained_volume_series"]
    assert series.dims == ("time",) and series.attrs["units"] == "m3"
    assert series.values[0] == 0.0 and np.all(np.diff(series.values) >= 0.0)
    entrained = float(ds["entrained_volume"])
    assert entrained > 0.0 and series.values[-1] == entrained
    released, on_map, out_ = (float(ds[n]) for n in ("release_volume", "deposit_volume",
                                                     "outflow_volume"))
    assert out_ > 0.0  # some left over the open foot: the balance counts it
    assert abs(released + entrained - on_map - out_) <= 1e-12 * (released + entrained)
    assert float(ds["mass_balance_error"]) <= 1e-12
    assert ds.attrs["entrainment_law"] == "erosion_energy"
    assert ds.attrs["mass_balance"].startswith(f"released {released!r} + entrained "
                                               f"{entrained!r} = on the map {on_map!r}")
    assert "Hungr" not in ds.attrs["references"] and "entEroEnergy" in ds.attrs["references"]
    # the layer left and the bed's change: float32 maps, bed_change = left - initial <= 0
    layer, change = ds["erodible_depth"], ds["bed_change"]
    assert layer.dims == change.dims == ("y", "x")
    assert "negative where the bed was eroded" in change.attrs["comment"]
    x = ds["x"].values[None, :] + 0.0 * ds["y"].values[:, None]
    initial = np.where((x >= 120) & (x <= 250), 0.5, 0.0)
    np.testing.assert_allclose(layer.values - change.values, initial, atol=1e-6)
    assert change.values.max() <= 0.0 and change.values.min() < -0.01
    # what the layer lost, over the cells' bed area (dx^2 / cos 30), at half the density
    area = 10.0 * 10.0 / math.cos(math.radians(30.0))
    assert 0.5 * area * -change.values.sum() == pytest.approx(entrained, rel=1e-5)


def test_the_file_of_a_run_with_entrainment_is_cf_compliant(written):
    """The IOOS checker's strict messages are its known ones only (tests/test_cli_output.py),
    the new series on time counted with the other series."""
    from test_cli_output import SCALAR_BOUNDS, TIME_BY_NAME, compliance_errors, strict_messages

    _, out, _ = written
    assert compliance_errors(out) == []
    on_time = ("h", "u", "v", "moving_volume", "center_of_mass_x", "center_of_mass_y",
               "center_of_mass_z", "entrained_volume_series")
    assert strict_messages(out) == sorted([SCALAR_BOUNDS] + [TIME_BY_NAME] * len(on_time))


def test_the_summary_line_states_the_balance(written, capsys):
    path, out, _ = written
    code = main(["run", str(path), "-o", str(out.with_name("again.nc"))])
    line = capsys.readouterr().out.splitlines()[0]
    assert code == 0
    assert " (released " in line and " + entrained " in line and " = on the map " in line
    assert " + out " in line and "m3)" in line


def test_export_writes_the_bed_change_and_the_layer(written, tmp_path, capsys):
    import rasterio

    _, out, _ = written
    assert main(["export", str(out), "-o", str(tmp_path)]) == 0
    with rasterio.open(tmp_path / "run_bed_change.tif") as src:
        assert src.units == ("m",) and src.read(1).min() < -0.01
    assert (tmp_path / "run_erodible_depth.tif").is_file()


def test_a_run_without_entrainment_says_nothing_of_it(tmp_path, capsys):
    path = plane(tmp_path, "{law: coulomb, delta_deg: 20}")
    assert main(["run", str(path), "-o", str(tmp_path / "o.nc")]) == 0
    assert "entrained" not in capsys.readouterr().out
    with xr.open_dataset(tmp_path / "o.nc") as ds:
        assert float(ds["entrained_volume"]) == 0.0
        assert "erodible_depth" not in ds and "entrained_volume_series" not in ds
        assert "entrainment_law" not in ds.attrs


def test_a_profile_with_entrainment_and_forest_balances_per_metre(tmp_path, capsys):
    path = tmp_path / "p.yaml"
    path.write_text("name: p\nterrain: {kind: profile, length: 600, slope: {kind: constant, "
                    "theta_deg: 32}}\ngrid: {dx: 4}\nrelease: {kind: box, x: [20, 60], "
                    "thickness: 2}\nrheology: {law: voellmy, mu: 0.2, xi: 1000}\n"
                    "time: {end: 20}\nentrainment: {law: exponential, growth_factor: 2, "
                    "path_length: 200, layer: {depth: 1.0, x: [100, 400]}}\n"
                    "forest: {x: [300, 600], c_f: 0.02}\n")
    assert main(["run", str(path), "-o", str(tmp_path / "p.nc")]) == 0
    with xr.open_dataset(tmp_path / "p.nc") as ds:
        assert ds["entrained_volume"].attrs["units"] == "m2"
        assert ds["erodible_depth"].dims == ("x",)
        r, e, d, o = (float(ds[n]) for n in ("release_volume", "entrained_volume",
                                             "deposit_volume", "outflow_volume"))
        assert e > 0.1 * r and abs(r + e - d - o) <= 1e-12 * (r + e)
        assert "per metre of width" in ds.attrs["mass_balance"]


def test_a_triangle_mesh_run_writes_the_layer_on_its_nodes(tmp_path):
    path = plane(tmp_path, "{law: voellmy, mu: 0.25, xi: 1000}",
                 "entrainment: {law: exponential, growth_rate: 0.005, "
                 "layer: {depth: 0.5, x: [100, 250]}}\nforest: {x: [250, 280], c_f: 0.05}\n"
                 "boundary: {x_max: outflow}\n", slope=30.0,
                 release="{kind: box, x: [20, 80], y: [30, 70], thickness: 3.0}", end=12.0)
    text = path.read_text().replace("grid: {dx: 10.0}", "grid: {dx: 10.0, mesh: triangles}")
    path.write_text(text)
    assert main(["run", str(path), "-q", "-o", str(tmp_path / "t.nc")]) == 0
    with xr.open_dataset(tmp_path / "t.nc") as ds:
        assert ds["bed_change"].dims == ("node",) and ds["bed_change"].attrs["mesh"] == "mesh"
        r, e, d, o = (float(ds[n]) for n in ("release_volume", "entrained_volume",
                                             "deposit_volume", "outflow_volume"))
        assert e > 0.0 and abs(r + e - d - o) <= 1e-12 * (r + e)


# ---------------------------------------------------------------------------- ensembles
def test_an_ensemble_varies_the_erosion_energy_and_reports_the_entrained(tmp_path):
    base = plane(tmp_path, "{law: voellmy, mu: 0.25, xi: 1000}",
                 "entrainment: {law: erosion_energy, layer: {depth: 1.0, x: [100, 300]}}\n",
                 slope=30.0, release="{kind: box, x: [20, 80], y: [30, 70], thickness: 3.0}",
                 end=12.0, name="base.yaml")
    spec = tmp_path / "ens.yaml"
    spec.write_text(f"name: eb\nbase: {base.name}\nvary:\n  entrainment.e_b: [2000.0, 8000.0]\n"
                    "thresholds: [0.1]\n")
    ens = load_ensemble(spec)
    assert [m.scenario.entrainment.e_b for m in ens.members] == [2000.0, 8000.0]
    outcome = run_ensemble(ens, tmp_path / "out", workers=0)
    assert outcome.failed == 0
    table = pd.read_csv(tmp_path / "out" / "summary.csv")
    entrained = table["entrained_volume"].to_numpy()
    assert entrained[0] > entrained[1] > 0.0  # less energy per kg eroded: more taken
    with xr.open_dataset(tmp_path / "out" / "ensemble.nc") as ds:
        np.testing.assert_array_equal(ds["entrained_volume"].values, entrained)
    report = write_report(tmp_path / "out").read_text()
    assert "## Entrainment" in report and "entrained_volume" in report


# ----------------------------------------------------------------------- bad layers
@pytest.fixture
def dem_folder(tmp_path):
    x, y = centres(0, 400, 0, 200, 10.0)
    xx, _ = np.meshgrid(x, y)
    write_asc(tmp_path / "dem.asc", 1000.0 - 0.5 * xx, x, y, LAMBERT)
    write_asc(tmp_path / "neg.asc", np.where(xx > 200, -0.5, 0.5), x, y, LAMBERT)
    write_asc(tmp_path / "holes.asc", np.where(xx > 300, np.nan, 0.5), x, y, LAMBERT)
    write_asc(tmp_path / "utm.asc", np.full_like(xx, 0.5), x, y, UTM33)
    write_asc(tmp_path / "short.asc", np.full_like(xx[:, :10], 1.0), x[:10], y, LAMBERT)
    polygons(tmp_path / "ent.gpkg", [(100, 0, 300, 200)], [0.4], field="depth",
             crs="EPSG:31287")
    return tmp_path


BAD_LAYERS = {
    "negative depths": ("entrainment: {law: erosion_energy, layer: {raster: neg.asc}}",
                        "entrainment.layer.raster", "neg.asc",
                        "the erodible depth (m) must be >= 0, got -0.5"),
    "NODATA inside": ("entrainment: {law: erosion_energy, layer: {raster: holes.asc}}",
                      "entrainment.layer.raster", "holes.asc", "NODATA in 200 of"),
    "another CRS": ("entrainment: {law: erosion_energy, layer: {raster: utm.asc}}",
                    "entrainment.layer.raster", "utm.asc", "its CRS differs from the DEM's"),
    "missing attribute": ("entrainment: {law: erosion_energy, layer: {polygon: ent.gpkg}}",
                          "entrainment.layer.polygon", "ent.gpkg",
                          "has no attribute 'thickness' (its attributes: depth)"),
    "forest short of the map": ("forest: {raster: short.asc}", "forest.raster", "short.asc",
                                "does not cover the terrain"),
    "negative forest": ("forest: {raster: neg.asc, values: coefficient}", "forest.raster",
                        "neg.asc", "c_f must be >= 0, got -0.5"),
}


@pytest.mark.parametrize("case", sorted(BAD_LAYERS))
def test_a_bad_layer_or_forest_is_one_line_exit_2(dem_folder, capsys, case):
    block, field, file, words = BAD_LAYERS[case]
    path = dem_folder / "bad.yaml"
    path.write_text(f"""name: bad
terrain: {{kind: dem, path: dem.asc}}
grid: {{dx: 10.0}}
release: {{kind: box, x: [20, 80], y: [50, 150], thickness: 2}}
rheology: {{law: voellmy, mu: 0.2, xi: 1000}}
time: {{end: 5}}
{block}
""")
    code = main(["run", str(path), "-o", str(dem_folder / "out.nc")])
    line = one_line(capsys.readouterr().err)
    assert code == 2 and line.startswith("avflow: error: ") and "bad.yaml:7:" in line, line
    assert f"{field}: " in line and file in line and words in line, line
    assert not (dem_folder / "out.nc").exists()


# ------------------------------------------------------------------ the real example
def test_avaframes_kontertal_entrainment_example_loads():
    """scenarios/avakot_entrainment.yaml: AvaFrame's own entrainment polygon (0.3 m) and
    resistance areas of avaKot (data/avaframe/avaKot), its erosion energy, snow densities
    and cResH; sampled on a 20 m grid."""
    sc = load_scenario(SCENARIOS / "avakot_entrainment.yaml").with_updates({"grid.dx": 20.0})
    assert str(REPO / "data" / "avaframe" / "avaKot" / "entKot.shp") in sc.input_files()
    terrain = build_terrain(sc)
    source = mass_source(sc, terrain)
    assert set(np.unique(source.erodible)) == {0.0, 0.3}
    assert source.kind == SOURCE_EROSION_ENERGY and source.params == (5000.0,)
    assert source.density_ratio == 0.5  # 100 kg/m^3 of snow cover under a flow of 200
    _, _, solver, _ = prepare(sc)
    assert set(np.unique(solver.params[:, 7])) == {0.0, 0.01}  # the resistance areas
