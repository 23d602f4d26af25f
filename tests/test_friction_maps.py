"""Friction maps and forest from scenario files (issue 30): terrain that resists.

- every form of a map (a raster, polygons with an attribute or one value, a default) is
  sampled at the cell centres, and reaches the solver's rows in the kernels' units;
- a map equal to the number gives that number's run, bit for bit (h, hu, hv and every
  snapshot), for a raster and for polygons, on Coulomb and Voellmy;
- a two-zone map (two lanes of a plane, two Coulomb friction angles above the slope)
  stops each lane's front where a point mass starting at the block's speed stops;
- forest drag lowers the terminal speed of a uniform Voellmy layer to the force balance's;
- bad maps (another CRS, a raster short of the terrain, NODATA, values out of the law's
  range, a missing attribute, cells outside every polygon, Pouliquen's angles crossing)
  are one line naming the file, exit code 2, before any run.

The numerics of maps and forest are tested on the solver in tests/test_entrainment.py; these
tests go through the scenario, the loading and the runner.
"""

import math
import subprocess
import sys

import numpy as np
import pytest
import shapely
from pyogrio.raw import write as write_vector
from pyproj import CRS

from avflow.cli import main
from avflow.scenario.schema import load_scenario, parse_scenario
from avflow.simulation.runner import prepare, simulate
from avflow.terrain.build import build_terrain
from avflow.terrain.maps import friction_maps
from avflow.terrain.raster import write_asc

G = 9.81
LAMBERT = CRS.from_epsg(31287).to_wkt()  # MGI / Austria Lambert, the AvaFrame paths' CRS
UTM33 = CRS.from_epsg(32633).to_wkt()


def polygons(path, boxes, values=None, field="value", crs=None):
    """A vector file of rectangles ``(x0, y0, x1, y1)``, each with its ``field`` value."""
    geoms = np.array([shapely.to_wkb(shapely.box(*b)) for b in boxes], dtype=object)
    data = [] if values is None else [np.asarray(values, dtype=float)]
    write_vector(str(path), geoms, geometry_type="Polygon", field_data=data,
                 fields=[] if values is None else [field], crs=crs)
    return path


def plane(folder, rheology, extra="", slope=20.0, extent="{x: [0, 300], y: [0, 100]}",
          dx=10.0, release="{kind: box, x: [40, 100], y: [20, 80], thickness: 2.0}",
          end=6.0, name="s.yaml"):
    """A plane scenario file in ``folder`` (facing +x: x is downslope)."""
    path = folder / name
    path.write_text(f"""name: plane
terrain: {{kind: plane, slope_deg: {slope}, azimuth_deg: 90, extent: {extent}}}
grid: {{dx: {dx}}}
release: {release}
rheology: {rheology}
time: {{end: {end}}}
output: {{every: {end / 3}}}
{extra}""")
    return path


def centres(x0, x1, y0, y1, dx):
    """Cell centres covering [x0, x1] x [y0, y1]."""
    return np.arange(x0 + dx / 2, x1, dx), np.arange(y0 + dx / 2, y1, dx)


# ------------------------------------------------------------------------ every form
def test_every_form_of_a_map_is_sampled_at_the_cell_centres(tmp_path):
    """A raster: each centre takes the value of the raster cell it lies in (here a finer
    raster, 5 m, whose value changes along x: no interpolation); polygons: an attribute,
    or one value, with a default outside; the rows reach the solver transformed."""
    xr, yr = centres(0, 300, 0, 100, 5.0)
    xx, _ = np.meshgrid(xr, yr)
    write_asc(tmp_path / "delta.asc", 20.0 + np.floor(xx / 50.0), xr, yr)
    polygons(tmp_path / "zones.gpkg", [(0, 0, 150, 100), (150, 0, 300, 50)], [0.3, 0.4],
             field="mu")
    path = plane(tmp_path, "{law: coulomb, delta_deg: {raster: delta.asc}}")
    sc = load_scenario(path)
    terrain = build_terrain(sc)
    cx, cy = terrain.cell_xy()
    delta = friction_maps(sc.rheology, terrain)["delta_deg"]
    np.testing.assert_array_equal(delta, 20.0 + np.floor(cx / 50.0))
    _, _, solver, _ = prepare(sc)
    np.testing.assert_array_equal(solver.params[:, 0],
                                  [math.tan(math.radians(d)) for d in delta])
    for mu, want in (({"polygon": "zones.gpkg", "attribute": "mu", "default": 0.1},
                      np.where(cx < 150, 0.3, np.where(cy < 50, 0.4, 0.1))),
                     ({"polygon": "zones.gpkg", "value": 0.25, "default": 0.1},
                      np.where((cx < 150) | (cy < 50), 0.25, 0.1))):
        sc2 = sc.with_updates({"rheology": {"law": "voellmy", "mu": mu,
                                            "xi": {"raster": "delta.asc"}}})
        maps = friction_maps(sc2.rheology, terrain)
        np.testing.assert_array_equal(maps["mu"], want)
        _, _, solver, _ = prepare(sc2)
        np.testing.assert_array_equal(solver.params[:, :2], np.stack([want, delta], axis=1))


def test_maps_are_inputs_and_their_content_counts_in_the_hash(tmp_path, capsys):
    xr, yr = centres(0, 300, 0, 100, 10.0)
    write_asc(tmp_path / "mu.asc", np.full((yr.size, xr.size), 0.3), xr, yr, LAMBERT)
    path = plane(tmp_path, "{law: voellmy, xi: 1000, mu: {raster: mu.asc}}")
    sc = load_scenario(path)
    assert str(tmp_path / "mu.asc") in sc.input_files()
    for name in ("mu.asc", "mu.prj"):  # no run writes over a map or its sidecar
        assert main(["run", str(path), "-o", str(tmp_path / name)]) == 2
        assert "is an input of this command" in one_line(capsys.readouterr().err)
    before = sc.scenario_hash()
    write_asc(tmp_path / "mu.asc", np.full((yr.size, xr.size), 0.35), xr, yr)
    assert load_scenario(path).scenario_hash() != before
    # the number form of a field and an ensemble's dotted path into a map
    assert sc.with_updates({"rheology.mu.default": 0.2}).rheology.mu.default == 0.2
    assert sc.with_updates({"rheology.mu": 0.2}).rheology.mu == 0.2


# ------------------------------------------------------------------- a map = a number
def _run(path):
    r = simulate(load_scenario(path))
    return r.state, [np.stack(s) for s in (r.snapshots.h, r.snapshots.hu, r.snapshots.hv)]


def _same_bits(a, b):
    (sa, snaps_a), (sb, snaps_b) = a, b
    for name in ("h", "hu", "hv", "peak_h", "peak_speed"):
        assert getattr(sa, name).tobytes() == getattr(sb, name).tobytes(), name
    for x, y in zip(snaps_a, snaps_b):
        assert x.tobytes() == y.tobytes()


@pytest.mark.parametrize("law,number,as_maps", [
    ("coulomb", {"delta_deg": 22.0}, [{"delta_deg": "raster"}, {"delta_deg": "polygon"}]),
    ("voellmy", {"mu": 0.2, "xi": 1200.0}, [{"mu": "raster", "xi": "polygon"}]),
])
def test_a_map_equal_to_the_number_gives_its_bits(tmp_path, law, number, as_maps):
    """The scalar runs on its law's own copy of the kernel, the map on the copy that
    reads a row per cell: the same arithmetic on the same values, so the same bits."""
    xr, yr = centres(0, 300, 0, 100, 10.0)
    fields = ", ".join(f"{k}: {v}" for k, v in number.items())
    reference = _run(plane(tmp_path, f"{{law: {law}, {fields}}}", name="number.yaml"))
    assert reference[0].hu.any()  # it moved
    for k, form in enumerate(as_maps):
        parts = []
        for name, value in number.items():
            if form.get(name) == "raster":
                write_asc(tmp_path / f"{name}.asc", np.full((yr.size, xr.size), value), xr, yr)
                parts.append(f"{name}: {{raster: {name}.asc}}")
            elif form.get(name) == "polygon":
                polygons(tmp_path / f"{name}.geojson", [(-5, -5, 305, 105)], [value])
                parts.append(f"{name}: {{polygon: {name}.geojson, attribute: value}}")
            else:
                parts.append(f"{name}: {value}")
        mapped = plane(tmp_path, f"{{law: {law}, {', '.join(parts)}}}", name=f"map{k}.yaml")
        _, _, solver, _ = prepare(load_scenario(mapped))
        assert solver.params.ndim == 2  # the map ran on the per-cell copy
        _same_bits(reference, _run(mapped))


# ----------------------------------------------------------- two zones, point-mass stop
def test_a_two_zone_map_stops_each_front_where_a_point_mass_stops(tmp_path):
    """A plane of 20 degrees in two lanes along the slope: Coulomb friction atan(0.5) in
    the lower lane (the map's default), atan(0.6) in the upper one (a polygon). A block
    0.5 m thick, 100 m long, set moving at u0 = 10 m/s in both: friction exceeds the slope,
    so each lane's material decelerates uniformly at ``g cos(theta) (mu - tan(theta))``
    and a point mass stops after ``s = u0^2 / (2 g cos(theta) (mu - tan(theta)))`` along
    the bed (39.9 m and 23.0 m).

    Measured: where the front's thickness crosses half the block's (between the cell
    centres, linearly), at the start and at rest, on the middle row of each lane. The
    box's step is smeared by the scheme, evenly about that point to first order, and its
    pressure gradient is soon far below mu - tan(theta), so the half-thickness point moves
    as the point mass; it is known to half a cell (its interpolation, and the last step to
    rest, at most u dt < dx): the tolerance, 2.7 m along the bed. The lanes (60 m wide)
    are wider than the lateral waves reach (c t = 2 m/s x 8 s) on the rows measured."""
    theta, mu1, mu2, u0, h, dx = 20.0, 0.5, 0.6, 10.0, 0.5, 5.0
    d1, d2 = (math.degrees(math.atan(m)) for m in (mu1, mu2))
    polygons(tmp_path / "upper.geojson", [(-10, 60, 1000, 130)], [d2], field="delta")
    path = plane(tmp_path, f"{{law: coulomb, delta_deg: {{polygon: upper.geojson, "
                           f"attribute: delta, default: {d1}}}}}",
                 slope=theta, extent="{x: [0, 400], y: [0, 120]}", dx=dx,
                 release=f"{{kind: box, x: [100, 200], y: [0, 120], thickness: {h}}}")
    terrain, h0, solver, _ = prepare(load_scenario(path))
    state = solver.new_state(h0)
    state.hu[:] = h0 * u0  # the first tangent axis is downslope (+x) on this plane
    assert solver.advance(state, 30.0, stop_volume=1e-12) == "stopped"
    assert not state.hu.any() and not state.hv.any()
    xx, yy = terrain.cell_xy()
    cos, tan = math.cos(math.radians(theta)), math.tan(math.radians(theta))

    def half_front(hrow, xrow):
        k = int(np.flatnonzero(hrow >= 0.5 * h).max())
        return xrow[k] + (hrow[k] - 0.5 * h) / (hrow[k] - hrow[k + 1]) * (xrow[k + 1] - xrow[k])

    reach = {}
    for mu, y in ((mu1, 32.5), (mu2, 92.5)):
        row = np.isclose(yy, y)
        moved = (half_front(state.h[row], xx[row]) - half_front(h0[row], xx[row])) / cos
        reach[mu] = moved
        s = u0**2 / (2 * G * cos * (mu - tan))
        assert moved == pytest.approx(s, abs=0.5 * dx / cos)
    assert reach[mu1] - reach[mu2] > 3 * dx  # the zones differ by three cells and more


# ------------------------------------------------------------------------------- forest
def test_forest_lowers_the_terminal_speed_to_the_force_balance(tmp_path):
    """A uniform Voellmy layer 1 m thick over a 30 degree plane, open at its foot; forest
    everywhere (c_f 0.01, AvaFrame's cResH) or none. Uniform flow reaches the speed where
    ``g sin = mu g cos + g u^2 / (xi h) + c_f u^2 / h``: read 1735 m down after 40 s (the
    top's rarefaction has come 600 m; the speed is within 1e-6 of its limit after seven
    times the approach time u_t / (g (sin - mu cos)), 5.6 s), to 1e-4."""
    theta, mu, xi, h = 30.0, 0.2, 1000.0, 1.0
    s, c = math.sin(math.radians(theta)), math.cos(math.radians(theta))
    speeds = {}
    for c_f in (0.0, 0.01):
        path = plane(tmp_path, f"{{law: voellmy, mu: {mu}, xi: {xi}}}",
                     "boundary: {x_max: outflow}\n"
                     + (f"forest: {{x: [0, 3000], c_f: {c_f}}}\n" if c_f else ""),
                     slope=theta, extent="{x: [0, 2600], y: [0, 30]}", dx=10.0,
                     release=f"{{kind: box, x: [0, 2600], y: [0, 30], thickness: {h}}}",
                     end=40.0, name=f"f{c_f}.yaml")
        r = simulate(load_scenario(path))
        xx, yy = r.terrain.cell_xy()
        mid = int(np.flatnonzero(np.isclose(xx, 1735.0) & np.isclose(yy, 15.0))[0])
        assert r.state.h[mid] == pytest.approx(h, rel=1e-9)
        speeds[c_f] = r.state.hu[mid] / r.state.h[mid]
        u_t = math.sqrt(G * h * (s - mu * c) / (G / xi + c_f))
        assert speeds[c_f] == pytest.approx(u_t, rel=1e-4)
    assert speeds[0.01] < 0.75 * speeds[0.0]


def test_forest_forms_are_sampled_at_the_cell_centres(tmp_path):
    from avflow.terrain.maps import forest_coefficient

    xr, yr = centres(0, 300, 0, 100, 10.0)
    xx, yy = np.meshgrid(xr, yr)
    write_asc(tmp_path / "mask.asc", (xx > 150).astype(float), xr, yr)
    write_asc(tmp_path / "cres.asc", np.where(yy > 50, 0.02, 0.0), xr, yr)
    polygons(tmp_path / "forest.gpkg", [(100, 0, 200, 100)], [0.03], field="cres")
    path = plane(tmp_path, "{law: coulomb, delta_deg: 20}")
    sc = load_scenario(path)
    terrain = build_terrain(sc)
    cx, cy = terrain.cell_xy()
    for forest, want in (({"raster": "mask.asc"}, np.where(cx > 150, 0.01, 0.0)),
                         ({"raster": "cres.asc", "values": "coefficient"},
                          np.where(cy > 50, 0.02, 0.0)),
                         ({"polygon": "forest.gpkg"}, np.where((cx > 100) & (cx < 200),
                                                              0.01, 0.0)),
                         ({"polygon": "forest.gpkg", "attribute": "cres"},
                          np.where((cx > 100) & (cx < 200), 0.03, 0.0)),
                         ({"x": [100, 200], "y": [0, 50], "c_f": 0.05},
                          np.where((cx > 100) & (cx < 200) & (cy < 50), 0.05, 0.0))):
        block = sc.with_updates({"forest": forest}).forest
        np.testing.assert_array_equal(forest_coefficient(block, terrain), want)
    _, _, solver, _ = prepare(sc.with_updates({"forest": {"polygon": "forest.gpkg"}}))
    np.testing.assert_array_equal(solver.params[:, 7], np.where((cx > 100) & (cx < 200),
                                                                0.01, 0.0))


# --------------------------------------------------------------------------- bad maps
def one_line(err: str) -> str:
    assert "Traceback" not in err, err
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture
def dem_folder(tmp_path):
    """A 400 x 200 m DEM in MGI / Austria Lambert and the bad maps of the tests."""
    x, y = centres(0, 400, 0, 200, 10.0)
    xx, yy = np.meshgrid(x, y)
    write_asc(tmp_path / "dem.asc", 1000.0 - 0.5 * xx, x, y, LAMBERT)
    write_asc(tmp_path / "mu_utm.asc", np.full_like(xx, 0.3), x, y, UTM33)
    write_asc(tmp_path / "mu_half.asc", np.full_like(xx[:, :20], 0.3), x[:20], y, LAMBERT)
    write_asc(tmp_path / "mu_holes.asc", np.where(xx > 300, np.nan, 0.3), x, y, LAMBERT)
    write_asc(tmp_path / "delta_95.asc", np.where(xx > 300, 95.0, 20.0), x, y, LAMBERT)
    write_asc(tmp_path / "delta1.asc", np.where(yy > 100, 25.0, 15.0), x, y, LAMBERT)
    write_asc(tmp_path / "mu_neg.asc", np.where(xx < 50, -0.1, 0.3), x, y, LAMBERT)
    polygons(tmp_path / "zones.gpkg", [(100, 0, 300, 200)], [0.4], field="mu_zone",
             crs="EPSG:31287")
    return tmp_path


BAD_MAPS = {
    "another CRS": ("{law: voellmy, xi: 1000, mu: {raster: mu_utm.asc}}",
                    "rheology.mu.raster", "mu_utm.asc", "CRS differs from the DEM's"),
    "short of the terrain": ("{law: voellmy, xi: 1000, mu: {raster: mu_half.asc}}",
                             "rheology.mu.raster", "mu_half.asc", "does not cover the terrain"),
    "NODATA inside": ("{law: voellmy, xi: 1000, mu: {raster: mu_holes.asc}}",
                      "rheology.mu.raster", "mu_holes.asc", "NODATA in 200 of the terrain's"),
    "out of range": ("{law: coulomb, delta_deg: {raster: delta_95.asc}}",
                     "rheology.delta_deg.raster", "delta_95.asc",
                     "delta_deg must be in [0, 90) degrees, got 95"),
    "a negative mu": ("{law: voellmy, xi: 1000, mu: {raster: mu_neg.asc}}",
                      "rheology.mu.raster", "mu_neg.asc", "mu must be >= 0, got -0.1"),
    "missing attribute": ("{law: voellmy, xi: 1000, mu: {polygon: zones.gpkg, attribute: mu, "
                          "default: 0.2}}", "rheology.mu.polygon", "zones.gpkg",
                          "has no attribute 'mu' (its attributes: mu_zone)"),
    "outside the polygons": ("{law: voellmy, xi: 1000, mu: {polygon: zones.gpkg, "
                             "attribute: mu_zone}}", "rheology.mu.polygon", "zones.gpkg",
                             "lie outside every polygon"),
    "angles crossing": ("{law: pouliquen, delta1_deg: {raster: delta1.asc}, delta2_deg: 20, "
                        "d: 1}", "rheology.delta1_deg", "delta1.asc",
                        "delta1_deg must be smaller than delta2_deg in every cell"),
}


@pytest.mark.parametrize("case", sorted(BAD_MAPS))
def test_a_bad_map_is_one_line_naming_the_file_exit_2(dem_folder, capsys, case):
    rheology, field, file, words = BAD_MAPS[case]
    path = dem_folder / "bad.yaml"
    path.write_text(f"""name: bad
terrain: {{kind: dem, path: dem.asc}}
grid: {{dx: 10.0}}
release: {{kind: box, x: [20, 80], y: [50, 150], thickness: 2}}
rheology: {rheology}
time: {{end: 5}}
""")
    code = main(["run", str(path), "-o", str(dem_folder / "out.nc")])
    line = one_line(capsys.readouterr().err)
    assert code == 2
    assert line.startswith("avflow: error: ") and "bad.yaml:5:" in line, line
    assert f"{field}: " in line and file in line and words in line, line
    assert not (dem_folder / "out.nc").exists()


def test_the_command_line_says_a_bad_map_in_one_line(dem_folder):
    """The same through ``python -m avflow`` in a process of its own."""
    path = dem_folder / "bad.yaml"
    path.write_text("name: bad\nterrain: {kind: dem, path: dem.asc}\ngrid: {dx: 10.0}\n"
                    "release: {kind: box, x: [20, 80], y: [50, 150], thickness: 2}\n"
                    "rheology: {law: voellmy, xi: 1000, mu: {raster: mu_utm.asc}}\n"
                    "time: {end: 5}\n")
    done = subprocess.run([sys.executable, "-m", "avflow", "run", str(path), "-o",
                           str(dem_folder / "o.nc")], capture_output=True, text=True,
                          timeout=120, cwd=dem_folder)
    assert done.returncode == 2
    assert one_line(done.stderr) == (
        "avflow: error: bad.yaml:5:41: rheology.mu.raster: "
        f"{dem_folder / 'mu_utm.asc'}: its CRS differs from the DEM's; reproject it first")


def test_maps_need_a_2d_terrain_and_their_values_their_range(tmp_path):
    base = ("name: p\nterrain: {kind: profile, length: 100, slope: {kind: constant, "
            "theta_deg: 30}}\ngrid: {dx: 5}\nrelease: {kind: box, x: [10, 20], thickness: 2}"
            "\ntime: {end: 5}\n")
    xr, yr = centres(0, 300, 0, 100, 10.0)
    write_asc(tmp_path / "mu.asc", np.full((yr.size, xr.size), 0.3), xr, yr)
    cases = {
        "rheology: {law: voellmy, xi: 1000, mu: {raster: mu.asc}}":
            "rheology.mu: a map needs a 2D terrain",
        "rheology: {law: voellmy, xi: 1000, mu: 0.2}\nforest: {raster: mu.asc}":
            "forest.raster: not on a 'profile' terrain",
        "rheology: {law: voellmy, xi: 1000, mu: {raster: mu.asc, default: -1}}":
            "rheology.mu.default: must be >= 0, got -1",
        "rheology: {law: voellmy, xi: 1000, mu: {polygon: mu.asc}}":
            "rheology.mu.polygon: must be a .shp",
        "rheology: {law: voellmy, xi: 1000, mu: {raster: mu.asc, attribute: a}}":
            "rheology.mu.attribute: applies to polygon maps only",
        "rheology: {law: voellmy, xi: 1000, mu: mu.asc}":
            "rheology.mu: must be a number, or a map such as {raster: FILE}",
    }
    for text, words in cases.items():
        with pytest.raises(Exception) as err:
            parse_scenario(base + text, source_path=tmp_path / "p.yaml")
        assert words in str(err.value), str(err.value)


def test_a_map_scaled_by_a_factor_for_ensembles_and_calibration(tmp_path):
    """``scale`` multiplies every cell's value (the default's too) before the range check:
    an ensemble or a calibration varies ``rheology.mu.scale`` like any number; 1 is the map
    itself to the bit, and a factor that pushes a cell out of the law's range is one line."""
    from avflow.errors import ScenarioError

    polygons(tmp_path / "zones.gpkg", [(0, 0, 150, 100)], [0.3], field="mu")
    path = plane(tmp_path, "{law: voellmy, mu: {polygon: zones.gpkg, attribute: mu, "
                           "default: 0.2}, xi: 2000}")
    sc = load_scenario(path)
    terrain = build_terrain(sc)
    cx, _ = terrain.cell_xy()
    base = friction_maps(sc.rheology, terrain)["mu"]
    np.testing.assert_array_equal(base, np.where(cx < 150, 0.3, 0.2))
    assert sc.rheology.mu.scale == 1.0
    scaled = sc.with_updates({"rheology.mu.scale": 1.5})
    np.testing.assert_array_equal(friction_maps(scaled.rheology, terrain)["mu"], base * 1.5)
    _, _, solver, _ = prepare(scaled)
    np.testing.assert_array_equal(solver.params[:, 0], base * 1.5)
    with pytest.raises(ScenarioError, match="scale"):
        sc.with_updates({"rheology.mu.scale": 0.0})
