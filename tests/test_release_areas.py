"""Potential release areas from a DEM (avflow/terrain/release_areas.py, avflow release-areas).

Hand-checkable DEMs: a slope of three planes (20, 40 and 65 degrees) whose 40-degree part
alone is a release area away from the kinks; a rough copy of it that the roughness removes;
a ridge whose lee side a west wind shelters; the Swiss thickness rule at 28 degrees and at
the area's own mean slope and elevation.
"""

import math

import numpy as np
import pytest

from avflow.cli import main
from avflow.terrain.release_areas import (PRAError, PRASettings, potential_release_areas,
                                          swiss_thickness, write_release_areas)
from avflow.terrain.raster import write_tif

DX = 5.0


def _steps(tmp_path, noise=0.0, name="dem.tif"):
    """z(x): 20 degrees for x < 200, 40 degrees to 400, 65 degrees to 600 m (falling east),
    uniform in y over 300 m."""
    x = np.arange(DX / 2, 600.0, DX)
    y = np.arange(DX / 2, 300.0, DX)
    t = [math.tan(math.radians(a)) for a in (20.0, 40.0, 65.0)]
    drop = np.where(x < 200, t[0] * x, np.where(x < 400, t[0] * 200 + t[1] * (x - 200),
                                                t[0] * 200 + t[1] * 200 + t[2] * (x - 400)))
    z = 3000.0 - np.tile(drop, (y.size, 1))
    if noise:
        z = z + noise * np.random.default_rng(1).standard_normal(z.shape)
    write_tif(tmp_path / name, z, x, y, None)
    return tmp_path / name, x, y


def test_only_the_slope_band_is_released_and_the_thickness_follows_the_swiss_rule(tmp_path):
    dem, x, y = _steps(tmp_path)
    r = potential_release_areas(dem, PRASettings(d0=1.0))
    far = 4 * DX  # the windows of the coarsest roughness scale (3 cells) and the 3 x 3 sum
    inner = (x > 200 + far) & (x < 400 - far)
    rows = slice(5, -5)
    assert r.cells[rows][:, inner].all()
    assert not r.cells[:, (x < 200 - far) | (x > 400 + far)].any()
    # the 40-degree face, and a strip one cell wide at the 40/65 kink, where the fitted
    # plane's slope (58 degrees) is in the band and the kink's roughness left a gap
    area = max(r.areas, key=lambda a: a["area_m2"])
    assert area["mean_slope_deg"] == pytest.approx(40.0, abs=1.0)
    for other in r.areas:
        if other is not area:
            bx0, _, bx1, _ = other["geometry"].bounds
            assert bx0 >= 400 - DX and bx1 <= 400 + 2 * DX
    # the Swiss rule: d0 at 2000 m, +5 cm per 100 m, times 0.291 / (sin psi - 0.202 cos psi)
    psi, zm = math.radians(area["mean_slope_deg"]), area["mean_elevation_m"]
    expected = (1.0 + 0.05 * (zm - 2000.0) / 100.0) * 0.291 / (math.sin(psi)
                                                              - 0.202 * math.cos(psi))
    assert area["thickness"] == pytest.approx(expected, rel=1e-12)


def test_swiss_factor_by_hand():
    # sin 28 - 0.202 cos 28 = 0.469472 - 0.178355 = 0.291116: f = 0.99960
    assert swiss_thickness(1.0, 28.0, 2000.0) == pytest.approx(0.99960, abs=1e-5)
    # 40 degrees: 0.642788 - 0.154737 = 0.488051, f = 0.59625; at 2400 m d0 + 0.2 m
    assert swiss_thickness(1.0, 40.0, 2400.0) == pytest.approx(1.2 * 0.59625, abs=1e-5)
    assert swiss_thickness(1.0, 40.0, 2400.0, slope_correction=False) == pytest.approx(1.2)


def test_rough_terrain_is_left_out_and_small_areas_dropped(tmp_path):
    dem, x, y = _steps(tmp_path, noise=6.0, name="rough.tif")
    inner = (x > 220) & (x < 380)
    rough = potential_release_areas(dem, PRASettings())
    no_rough = potential_release_areas(dem, PRASettings(roughness=False))
    # on the rough face (6 m noise on 5 m cells) the roughness takes a fifth of the cells
    # the slope band keeps; on the smooth face none
    kept, band = rough.cells[:, inner].sum(), no_rough.cells[:, inner].sum()
    assert kept < 0.85 * band
    smooth_dem = _steps(tmp_path)[0]
    smooth = potential_release_areas(smooth_dem, PRASettings())
    plain = potential_release_areas(smooth_dem, PRASettings(roughness=False))
    assert smooth.cells[:, inner].sum() == plain.cells[:, inner].sum() > 0
    big = potential_release_areas(_steps(tmp_path)[0], PRASettings(min_area=1e6))
    assert big.areas == [] and not big.cells.any()
    with pytest.raises(PRAError, match="no potential release area"):
        write_release_areas(big, tmp_path / "none.gpkg")


def test_forest_polygons_are_excluded(tmp_path):
    import json

    dem, x, y = _steps(tmp_path)
    (tmp_path / "forest.geojson").write_text(json.dumps({
        "type": "FeatureCollection", "features": [{"type": "Feature", "properties": {},
        "geometry": {"type": "Polygon", "coordinates": [[[250, 0], [350, 0], [350, 300],
                                                         [250, 300], [250, 0]]]}}]}))
    r = potential_release_areas(dem, PRASettings(), forest=tmp_path / "forest.geojson")
    assert not r.cells[:, (x > 250) & (x < 350)].any()
    assert r.cells[:, (x > 220) & (x < 240)].any()
    faces = [a for a in r.areas if a["mean_slope_deg"] < 45.0]
    assert len(faces) == 2  # the forest strip splits the 40-degree face in two


def test_a_west_wind_shelters_the_lee_side_of_a_ridge(tmp_path):
    x = np.arange(DX / 2, 600.0, DX)
    y = np.arange(DX / 2, 300.0, DX)
    z = 2000.0 - math.tan(math.radians(38.0)) * np.abs(x - 300.0)  # ridge along y
    write_tif(tmp_path / "ridge.tif", np.tile(z, (y.size, 1)), x, y, None)
    r = potential_release_areas(tmp_path / "ridge.tif", PRASettings(wind_direction=270.0))
    mid = slice(20, -20)
    west = r.index[mid][:, (x > 150) & (x < 250)].mean()
    east = r.index[mid][:, (x > 350) & (x < 450)].mean()
    assert east > west + 0.2  # lee (east) slope sheltered, windward slope exposed
    plain = potential_release_areas(tmp_path / "ridge.tif", PRASettings())
    np.testing.assert_allclose(plain.index[mid][:, (x > 150) & (x < 250)].mean(),
                               plain.index[mid][:, (x > 350) & (x < 450)].mean(), rtol=1e-9)


def test_cli_writes_polygons_with_thickness_and_refuses_bad_input(tmp_path, capsys):
    import pyogrio

    dem, _, _ = _steps(tmp_path)
    out = tmp_path / "pra.gpkg"
    assert main(["release-areas", str(dem), "-o", str(out), "--d0", "1.2"]) == 0
    said = capsys.readouterr()
    assert "potential release areas" in said.out and "thickness" in said.out
    meta, _, wkb, cols = pyogrio.raw.read(out)
    names = list(meta["fields"])
    assert {"id", "area_m2", "mean_slope_deg", "thickness"} <= set(names)
    assert cols[names.index("thickness")][0] > 0
    assert main(["release-areas", str(dem), "-o", str(tmp_path / "x.gpkg"),
                 "--slope-min", "70"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--slope-min" in err  # the option, as typed
    assert not (tmp_path / "x.gpkg").exists()
    assert main(["release-areas", str(dem), "-o", str(dem)]) == 2  # never over the DEM
    assert dem.stat().st_size > 0


def test_a_region_runs_the_release_areas_of_its_dem(tmp_path, capsys):
    """releases: {from_dem: ...}: the region runs exactly the areas avflow release-areas
    finds (a 30-degree slope onto a flat floor, 20 m cells, the region tests' kernels)."""
    import pandas as pd
    import rasterio
    from rasterio.transform import from_origin

    dx, nx, ny = 20.0, 80, 30
    x = 1000.0 + dx * (np.arange(nx) + 0.5)
    y = 5000.0 - dx * (np.arange(ny) + 0.5)
    z = np.clip(1000.0 + 600.0 - x, 0.0, None) * math.tan(math.radians(33.0))
    z = z[None, :] + 0.05 * np.abs(y - y.mean())[:, None]
    with rasterio.open(tmp_path / "dem.tif", "w", driver="GTiff", width=nx, height=ny,
                       count=1, dtype="float32", crs="EPSG:2056",
                       transform=from_origin(1000.0, 5000.0, dx, dx)) as dst:
        dst.write(z.astype(np.float32), 1)
    region = """\
name: from-dem
dem: dem.tif
releases:
  from_dem: {{min_area: 20000, d0: 1.0{extra}}}
scenario:
  rheology: {{law: coulomb, delta_deg: 24.0}}
  time: {{end: 60.0}}
  numerics: {{order: 1}}
merge:
  chunk: 16
"""
    (tmp_path / "r.yaml").write_text(region.format(extra=""))
    found = potential_release_areas(tmp_path / "dem.tif", PRASettings(min_area=20000, d0=1.0))
    assert main(["region", str(tmp_path / "r.yaml"), "-o", str(tmp_path / "out"),
                 "--workers", "0", "-q"]) == 0
    table = pd.read_csv(tmp_path / "out" / "releases.csv")
    assert len(table) == len(found.areas) >= 1
    assert set(table["status"]) == {"ok"}
    np.testing.assert_allclose(sorted(table["thickness"]),
                               sorted(a["thickness"] for a in found.areas), rtol=1e-9)
    capsys.readouterr()
    (tmp_path / "bad.yaml").write_text(region.format(extra=", slope_mix: 30"))
    assert main(["region", str(tmp_path / "bad.yaml"), "-o", str(tmp_path / "bad"),
                 "--workers", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "releases.from_dem.slope_mix" in err


def test_split_by_aspect_separates_two_faces(tmp_path):
    """z = 3000 - tan 40 max(x, y): an east-facing face (x > y) and a north-facing one
    (y > x) meeting on the diagonal; connected they are one area, split by 90-degree
    sectors two, each on its own side of the diagonal (the fold's cells, whose fitted
    planes face north-east, join the face they border most)."""
    x = np.arange(DX / 2, 400.0, DX)
    X, Y = np.meshgrid(x, x)
    write_tif(tmp_path / "two.tif", 3000.0 - math.tan(math.radians(40.0)) * np.maximum(X, Y),
              x, x, None)
    # without the roughness, which leaves out the fold itself and so splits them already
    smooth = PRASettings(roughness=False)
    assert len(potential_release_areas(tmp_path / "two.tif", smooth).areas) == 1
    r = potential_release_areas(tmp_path / "two.tif",
                                PRASettings(roughness=False, split_aspect_deg=90.0))
    assert len(r.areas) == 2
    for a in r.areas:
        cells = r.labels == a["id"]
        east = (X > Y)[cells].mean()
        assert east > 0.95 or east < 0.05
