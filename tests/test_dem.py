"""Real terrain in: DEM readers (.asc, .tif, .nc), resampling, release polygons and rasters,
the AvaFrame paths run end to end with mass conserved (issue 4 items 1, 2, 6)."""

import math
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from avflow.terrain.raster import RasterError, read_raster, resample, write_asc, write_tif
from avflow.errors import ScenarioError
from avflow.terrain.polygons import Area, rasterize, read_polygons
from avflow.simulation.runner import prepare, simulate
from avflow.scenario.schema import load_scenario, parse_scenario

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "avaframe"
PATHS = {
    "avaKot": ("avaKot.asc", "relKot.shp"),
    "avaAlr": ("avaAlr.tif", "relAlr.shp"),
    "avaHit": ("avaHit.asc", "relHit.shp"),
    "avaWog": ("avaWog.asc", "relWog.shp"),
}
WKT = None


def lambert_wkt():
    return (DATA / "avaKot" / "relKot.prj").read_text()


def tilted(nx=40, ny=30, dx=5.0, x0=1000.0, y0=2000.0):
    """A plane z = 500 - 0.3 x + 0.1 y on cell centres, a NODATA hole in the middle."""
    x = x0 + dx * np.arange(nx)
    y = y0 + dx * np.arange(ny)
    z = 500.0 - 0.3 * (x[None, :] - x0) + 0.1 * (y[:, None] - y0)
    z[12:15, 20:23] = np.nan
    return z, x, y


def tilted_dem_scenario(tmp_path, release):
    """A scenario on the tilted DEM (written to tmp_path/dem.asc) with this release block."""
    write_asc(tmp_path / "dem.asc", *tilted())
    return parse_scenario(f"""
name: tilted
terrain: {{kind: dem, path: {tmp_path / 'dem.asc'}}}
grid: {{dx: 5.0}}
release: {release}
rheology: {{law: coulomb, delta_deg: 20.0}}
time: {{end: 1.0}}
""", source_path=tmp_path / "s.yaml")


@pytest.mark.parametrize("suffix", [".asc", ".tif", ".nc"])
def test_raster_round_trip(tmp_path, suffix):
    """Every reader gives ascending coordinates, NaN for NODATA and the CRS back."""
    z, x, y = tilted()
    path = tmp_path / f"dem{suffix}"
    if suffix == ".asc":
        write_asc(path, z, x, y, lambert_wkt())
    elif suffix == ".tif":
        write_tif(path, z, x, y, lambert_wkt())
    else:
        xr.Dataset({"elevation": (("y", "x"), z, {"grid_mapping": "crs"}),
                    "crs": ((), 0, {"crs_wkt": lambert_wkt()})},
                   coords={"x": x, "y": y[::-1] * 0 + y}).to_netcdf(path)
    r = read_raster(path)
    np.testing.assert_allclose(r.x, x, rtol=0, atol=1e-6)
    np.testing.assert_allclose(r.y, y, rtol=0, atol=1e-6)
    assert np.array_equal(np.isnan(r.values), np.isnan(z))
    np.testing.assert_allclose(r.values[np.isfinite(z)], z[np.isfinite(z)], rtol=1e-6)
    from pyproj import CRS

    assert CRS.from_wkt(r.crs_wkt).equals(CRS.from_wkt(lambert_wkt()), ignore_axis_order=True)


def test_resampling_a_plane_is_exact_and_keeps_nodata():
    """Bilinear interpolation reproduces a plane; a cell next to NODATA stays NODATA."""
    z, x, y = tilted()
    from avflow.terrain.raster import Raster

    coarse = resample(Raster(z, x, y), 10.0)
    assert coarse.dx == pytest.approx(10.0)
    expected = 500.0 - 0.3 * (coarse.x[None, :] - x[0]) + 0.1 * (coarse.y[:, None] - y[0])
    ok = np.isfinite(coarse.values)
    np.testing.assert_allclose(coarse.values[ok], expected[ok], atol=1e-9)
    assert (~ok).sum() >= 1  # the hole survives
    assert resample(Raster(z, x, y), 5.02) is not None  # within 1%: used as it is


@pytest.mark.parametrize("body, message", [
    ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\nNODATA_value -9999\n1 2 3\n4 5 6\n",
     "lacks 'cellsize'"),
    ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 5\n1 2 3\n4 5\n", "holds 5"),
    ("ncols 2\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 5\nNODATA_value -1\n-1 -1\n-1 -1\n",
     "every cell is NODATA"),
])
def test_bad_ascii_grids_name_the_file(tmp_path, body, message):
    path = tmp_path / "bad.asc"
    path.write_text(body)
    with pytest.raises(RasterError, match=message) as err:
        read_raster(path)
    assert "bad.asc" in str(err.value)


def test_polygon_rasterisation_with_a_hole_and_overlap():
    """Even-odd rings; where two areas overlap the larger thickness wins."""
    outer = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    hole = np.array([[4, 4], [6, 4], [6, 6], [4, 6]], float)
    other = np.array([[8, 8], [12, 8], [12, 12], [8, 12]], float)
    xx, yy = np.meshgrid(np.arange(0.5, 12), np.arange(0.5, 12))
    h = rasterize([Area((outer, hole), 2.0), Area((other,), 3.0)], xx, yy)
    assert h[5, 5] == 0.0 and h[1, 1] == 2.0 and h[9, 9] == 3.0 and h[11, 11] == 3.0
    assert np.count_nonzero(h == 2.0) == 100 - 4 - 4  # the hole and the overlap removed


@pytest.mark.parametrize("name", sorted(PATHS))
def test_release_polygons_of_the_real_paths(name):
    """The released area matches the polygon's area (cell-centre rasterisation, 5 m cells:
    within 6% for these 1-3 hectare areas) and the volume is sum h A on the bed."""
    dem, shp = PATHS[name]
    areas, wkt = read_polygons(DATA / name / shp)
    assert wkt and all(a.thickness == 1.0 for a in areas)
    sc = parse_scenario(f"""
name: {name}
terrain: {{kind: dem, path: {DATA / name / dem}}}
grid: {{dx: 5.0}}
release: {{kind: polygon, path: {DATA / name / shp}}}
rheology: {{law: coulomb, delta_deg: 20.0}}
time: {{end: 1.0}}
""")
    terrain, h0, solver, _ = prepare(sc)
    ring = areas[0].rings[0]
    shoelace = 0.5 * abs(np.dot(ring[:, 0], np.roll(ring[:, 1], 1))
                         - np.dot(ring[:, 1], np.roll(ring[:, 0], 1)))
    released = np.count_nonzero(h0) * terrain.dx * terrain.dy
    assert released == pytest.approx(shoelace, rel=0.06)
    volume = solver.volume(solver.new_state(h0))
    assert volume == pytest.approx(np.sum(h0 * terrain.mesh.cell_area))
    assert volume > released  # thickness normal to the bed: bed area > horizontal area
    assert np.all(np.isfinite(terrain.gamma_x)) and np.all(terrain.gamma_z > 0)


@pytest.mark.parametrize("name", sorted(PATHS))
def test_real_paths_conserve_mass_with_no_nan(name):
    """Every AvaFrame path at 20 m for 30 s: mass to round-off, h >= 0, nothing NaN, and
    speeds bounded by free fall along the path (sqrt(2 g drop))."""
    dem, shp = PATHS[name]
    sc = parse_scenario(f"""
name: {name}
terrain: {{kind: dem, path: {DATA / name / dem}}}
grid: {{dx: 20.0}}
release: {{kind: polygon, path: {DATA / name / shp}}}
rheology: {{law: coulomb, delta_deg: 20.0}}
time: {{end: 30.0}}
output: {{every: 10.0}}
""")
    r = simulate(sc)
    s = r.summary
    assert s["mass_balance_error"] < 1e-12, s["mass_balance_error"]
    assert np.all(r.state.h >= 0.0)
    assert np.all(np.isfinite(r.state.h)) and np.all(np.isfinite(r.state.hu))
    drop = np.nanmax(r.terrain.bed_elevation) - np.nanmin(r.terrain.bed_elevation)
    assert r.state.peak_speed.max() < math.sqrt(2 * 9.81 * drop)
    assert s["halved_steps"] == 0


def test_contract_dem_scenario_loads_unchanged():
    """../shared/contract/avakot_coulomb.yaml: DEM and polygon found relative to the file."""
    contract = ROOT.parent / "shared" / "contract" / "avakot_coulomb.yaml"
    if not contract.is_file():
        pytest.skip("the external reference scenarios ($AVFLOW_SHARED) are not here")
    sc = load_scenario(contract)
    terrain, h0, solver, _ = prepare(sc.with_updates({"grid.dx": 20.0}))
    assert terrain.crs_wkt and h0.max() == 1.0


def test_missing_dem_and_missing_thickness_are_clear_errors(tmp_path):
    with pytest.raises(ScenarioError, match="terrain.path") as err:
        parse_scenario("""
name: x
terrain: {kind: dem, path: nowhere.asc}
grid: {dx: 5.0}
release: {kind: cylinder, center: [0, 0], radius: 10, thickness: 1}
rheology: {law: coulomb, delta_deg: 20.0}
time: {end: 1.0}
""", source_path=tmp_path / "s.yaml")
    assert "nowhere.asc" in str(err.value)
    # a shapefile without a thickness attribute and no thickness in the scenario
    import shapefile

    w = shapefile.Writer(str(tmp_path / "area"), shapeType=shapefile.POLYGON)
    w.field("name", "C")
    w.poly([[[1010, 2010], [1080, 2010], [1080, 2080], [1010, 2080], [1010, 2010]]])
    w.record("a")
    w.close()
    sc = tilted_dem_scenario(tmp_path, f"{{kind: polygon, path: {tmp_path / 'area.shp'}}}")
    with pytest.raises(ScenarioError, match="thickness") as err:
        prepare(sc)
    assert "release" in str(err.value) and "area.shp" in str(err.value)


def test_raster_release_samples_the_thickness_grid(tmp_path):
    """A thickness raster on the DEM's grid gives exactly its values; NODATA releases 0."""
    z, x, y = tilted()
    thick = np.zeros_like(z)
    thick[5:10, 5:12] = 2.5
    thick[0, 0] = np.nan
    write_asc(tmp_path / "h0.asc", thick, x, y)
    sc = tilted_dem_scenario(tmp_path, f"{{kind: raster, path: {tmp_path / 'h0.asc'}}}")
    terrain, h0, solver, _ = prepare(sc)
    grid = terrain.to_grid(h0, fill=0.0)
    np.testing.assert_array_equal(grid, np.nan_to_num(thick) * np.isfinite(z))


def test_contract_plane_cylinder_runs_unchanged(tmp_path):
    """../shared/contract/plane_cylinder.yaml through the CLI (about 10 s): the flow slides
    down the 30 degree plane (Coulomb 20) until it piles against the downslope wall."""
    contract = ROOT.parent / "shared" / "contract" / "plane_cylinder.yaml"
    if not contract.is_file():
        pytest.skip("the external reference scenarios ($AVFLOW_SHARED) are not here")
    from avflow.cli import main

    out = tmp_path / "pc.nc"
    assert main(["run", str(contract), "-o", str(out)]) == 0
    with xr.open_dataset(out, decode_times=False) as ds:
        assert float(ds["mass_balance_error"]) < 1e-12
        assert float(ds["release_volume"]) == pytest.approx(
            float(ds["deposit_volume"]), rel=1e-12)
        assert ds.attrs["status"] == "completed"


def test_a_real_path_runs_from_yaml_to_png(tmp_path):
    """scenarios/avakot_coulomb.yaml at 20 m for 40 s: run, export, plot through the CLI."""
    from avflow.cli import main

    sc = load_scenario(ROOT / "scenarios" / "avakot_coulomb.yaml").with_updates(
        {"grid.dx": 20.0, "time.end": 40.0, "output.every": 10.0})
    path = tmp_path / "kot.yaml"
    path.write_text(sc.to_yaml())  # data paths are absolute once loaded
    out = tmp_path / "kot.nc"
    assert main(["run", str(path), "-o", str(out)]) == 0
    assert main(["export", str(out), "--format", "tif"]) == 0
    assert (tmp_path / "kot_peak_thickness.tif").stat().st_size > 0
    assert main(["plot", str(out), "-o", str(tmp_path / "kot.png")]) == 0
    assert (tmp_path / "kot.png").stat().st_size > 10_000
    with xr.open_dataset(out, decode_times=False) as ds:
        assert "crs" in ds and ds["peak_thickness"].attrs["grid_mapping"] == "crs"
        assert float(ds["mass_balance_error"]) < 1e-12


@pytest.mark.parametrize("mesh", ["square", "triangles"])
def test_a_domain_polygon_cuts_the_mesh(tmp_path, mesh):
    """terrain.domain keeps only the cells inside a polygon, on grids and triangle meshes:
    the domain is walled, mass is conserved and no cell outside ever gets material."""
    import shapefile

    w = shapefile.Writer(str(tmp_path / "domain"), shapeType=shapefile.POLYGON)
    w.field("name", "C")
    w.poly([[[100, 100], [100, 500], [700, 300], [100, 100]]])
    w.record("a")
    w.close()
    text = f"""
name: cut
terrain:
  kind: plane
  slope_deg: 30.0
  azimuth_deg: 90.0
  extent: {{x: [0.0, 800.0], y: [0.0, 600.0]}}
  domain: {tmp_path / 'domain.shp'}
grid: {{dx: 10.0, mesh: {mesh}}}
release: {{kind: cylinder, center: [200.0, 300.0], radius: 50.0, thickness: 5.0}}
rheology: {{law: coulomb, delta_deg: 20.0}}
time: {{end: 30.0}}
output: {{every: 10.0}}
"""
    r = simulate(parse_scenario(text, source_path=tmp_path / "s.yaml"))
    x, y = r.terrain.cell_xy()
    inside = rasterize(read_polygons(tmp_path / "domain.shp")[0], x, y, thickness=1.0) > 0
    assert inside.all()  # only cells inside are meshed (grid cells: centres; nodes: closed)
    assert r.terrain.n_cells < 0.45 * (81 * 61)
    assert r.summary["mass_balance_error"] < 1e-12
    assert r.state.peak_h.max() > 0 and np.all(r.state.h >= 0)


# =========================================================================================
# Libraries doing their part: ESRI ASCII through GDAL, vector releases through pyogrio
# =========================================================================================


def test_esri_ascii_reads_every_value_in_float64():
    """avaKot.asc through GDAL's AAIGrid driver: the values as written (float64, not GDAL's
    default float32 for decimal grids), NODATA as NaN, cell centres from the corner."""
    path = DATA / "avaKot" / "avaKot.asc"
    header = dict(line.split() for line in path.read_text().splitlines()[:6])
    raw = np.loadtxt(path, skiprows=6)[::-1]
    raw[raw == float(header["NODATA_value"])] = np.nan
    r = read_raster(path)
    np.testing.assert_array_equal(r.values, raw)
    assert r.dx == pytest.approx(float(header["cellsize"]), rel=1e-9)
    assert r.x[0] == pytest.approx(float(header["xllcorner"]) + 0.5 * r.dx, abs=1e-9)
    assert r.y[0] == pytest.approx(float(header["yllcorner"]) + 0.5 * r.dx, abs=1e-9)
    assert r.crs_wkt is None  # no .prj beside it


def _write_vector(path, geometries, thickness=None, crs="EPSG:31287", **kw):
    import pyogrio.raw
    import shapely

    fields, data = [], []
    if thickness is not None:
        fields, data = ["thickness"], [np.asarray(thickness, dtype=float)]
    fields.append("name")
    data.append(np.array([f"area {k}" for k in range(len(geometries))], dtype=object))
    pyogrio.raw.write(str(path), shapely.to_wkb(np.asarray(geometries, dtype=object)), data,
                      fields, crs=crs, geometry_type=kw.pop("geometry_type", "MultiPolygon"),
                      **kw)
    return path


@pytest.mark.parametrize("suffix", [".geojson", ".gpkg"])
def test_geojson_and_geopackage_releases_equal_the_shapefile(tmp_path, suffix):
    """relKot.shp rewritten as GeoJSON / GeoPackage (thickness attribute, CRS) releases the
    same cells with the same thickness on avaKot; its CRS is the shapefile's."""
    import shapely

    shp = DATA / "avaKot" / "relKot.shp"
    areas, wkt = read_polygons(shp)
    polygon = shapely.Polygon(areas[0].rings[0], areas[0].rings[1:])
    path = _write_vector(tmp_path / f"relKot{suffix}", [polygon], thickness=[1.5])
    areas2, wkt2 = read_polygons(path)
    assert [a.thickness for a in areas2] == [1.5] and areas2[0].name == "area 0"
    from avflow.terrain.raster import same_crs

    assert wkt2 and same_crs(wkt, wkt2)

    def release(p):
        sc = parse_scenario(f"""
name: kot
terrain: {{kind: dem, path: {DATA / 'avaKot' / 'avaKot.asc'}}}
grid: {{dx: 10.0}}
release: {{kind: polygon, path: {p}}}
rheology: {{law: coulomb, delta_deg: 20.0}}
time: {{end: 1.0}}
""")
        return prepare(sc)[1]

    h_shp, h_new = release(shp), release(path)
    assert np.count_nonzero(h_shp) > 50
    np.testing.assert_array_equal(h_new, 1.5 * h_shp)  # relKot's own thickness is 1 m


def test_geopackage_multipolygon_with_a_hole_is_even_odd(tmp_path):
    """One feature of two parts, one with a hole: the hole is released nowhere, both parts
    are; a domain from the same GeoPackage meshes only them."""
    import shapely

    x0, y0 = 1002.5, 2002.5  # between the tilted DEM's cell centres (every 5 m from 1000)
    part1 = shapely.Polygon([(x0 + 20, y0 + 20), (x0 + 90, y0 + 20), (x0 + 90, y0 + 90),
                             (x0 + 20, y0 + 90)],
                            [[(x0 + 40, y0 + 40), (x0 + 70, y0 + 40), (x0 + 70, y0 + 70),
                              (x0 + 40, y0 + 70)]])
    part2 = shapely.box(x0 + 120, y0 + 20, x0 + 160, y0 + 60)
    path = _write_vector(tmp_path / "areas.gpkg", [shapely.MultiPolygon([part1, part2])],
                         thickness=[2.0])
    z, x, y = tilted()
    xx, yy = np.meshgrid(x, y)
    h = rasterize(read_polygons(path)[0], xx, yy)
    inside = lambda g: shapely.contains_xy(g, xx, yy)  # noqa: E731  (no centre on an edge)
    np.testing.assert_array_equal(h, np.where(inside(part1) | inside(part2), 2.0, 0.0))
    assert h[11, 11] == 0.0 and h[5, 5] == 2.0 and h[5, 28] == 2.0  # hole, part 1, part 2
    # the same answer for scattered points (triangle-mesh nodes off the lattice)
    jitter = 1e-3 * np.random.default_rng(0).random(xx.size)
    np.testing.assert_array_equal(
        rasterize(read_polygons(path)[0], xx.ravel() + jitter, yy.ravel()), h.ravel())


def test_geojson_without_crs_member_takes_the_dems(tmp_path):
    """GeoJSON's default CRS is WGS 84: coordinates in metres show it is not, so the file's
    CRS is unknown and it is used on the DEM's (as a shapefile without .prj)."""
    import shapely

    path = tmp_path / "area.geojson"
    path.write_text('{"type": "FeatureCollection", "features": [{"type": "Feature", '
                    '"properties": {"thickness": 3.0}, "geometry": '
                    + shapely.to_geojson(shapely.box(1012.5, 2012.5, 1082.5, 2082.5)) + "}]}")
    areas, wkt = read_polygons(path)
    assert wkt is None and areas[0].thickness == 3.0
    sc = tilted_dem_scenario(tmp_path, f"{{kind: polygon, path: {path}}}")
    h0 = prepare(sc)[1]
    assert h0.max() == 3.0 and np.count_nonzero(h0) == 14 * 14


def test_vector_files_that_cannot_be_releases_are_one_line(tmp_path):
    import shapely

    from avflow.terrain.polygons import PolygonError

    lines = _write_vector(tmp_path / "lines.geojson", [shapely.LineString([(0, 0), (1, 1)])],
                          geometry_type="LineString")
    with pytest.raises(PolygonError, match="lines.geojson: holds LineString shapes"):
        read_polygons(lines)
    source = DATA / "avaKot"
    for suffix in (".shp", ".dbf", ".prj"):  # no .shx
        (tmp_path / f"relKot{suffix}").write_bytes((source / f"relKot{suffix}").read_bytes())
    with pytest.raises(PolygonError, match=r"relKot\.shx: not found"):
        read_polygons(tmp_path / "relKot.shp")
    broken = tmp_path / "broken.gpkg"
    broken.write_text("not a GeoPackage\n")
    with pytest.raises(PolygonError, match="broken.gpkg: cannot be read as a vector file"):
        read_polygons(broken)
    assert "\n" not in str(pytest.raises(PolygonError, read_polygons, broken).value)
