"""A DEM in degrees (EPSG:4326, a common GIS export) is refused in one line that says so and
names the file, before anything runs: by avflow run and by avflow region."""

from __future__ import annotations

import numpy as np

from avflow.cli import main


def _dem_in_degrees(path):
    import rasterio
    from rasterio.transform import from_origin

    z = np.add.outer(np.linspace(2000.0, 1500.0, 40), np.zeros(40)).astype(np.float32)
    # 0.0005 degrees (about 50 m) cells near 47 N 11 E
    with rasterio.open(path, "w", driver="GTiff", width=40, height=40, count=1,
                       dtype="float32", crs="EPSG:4326",
                       transform=from_origin(11.0, 47.02, 0.0005, 0.0005)) as dst:
        dst.write(z, 1)


SCENARIO = """\
name: degrees
terrain: {kind: dem, path: dem.tif}
grid: {dx: 10.0}
release: {kind: box, x: [11.005, 11.006], y: [47.01, 47.011], thickness: 1.0}
rheology: {law: coulomb, delta_deg: 20.0}
time: {end: 10.0}
"""

REGION = """\
name: degrees
dem: dem.tif
releases: {path: releases.gpkg, thickness: 1.0}
scenario:
  rheology: {law: coulomb, delta_deg: 22.0}
  time: {end: 10.0}
"""


def test_run_says_the_dem_is_in_degrees(tmp_path, capsys):
    _dem_in_degrees(tmp_path / "dem.tif")
    (tmp_path / "s.yaml").write_text(SCENARIO)
    assert main(["run", str(tmp_path / "s.yaml"), "-o", str(tmp_path / "o.nc")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "dem.tif" in err and "this DEM is in degrees" in err and "EPSG:4326" in err
    assert "reproject it to a projected CRS in metres" in err
    assert not (tmp_path / "o.nc").exists()


def test_region_says_the_dem_is_in_degrees(tmp_path, capsys):
    _dem_in_degrees(tmp_path / "dem.tif")
    (tmp_path / "r.yaml").write_text(REGION)
    (tmp_path / "releases.gpkg").write_bytes(b"")  # never read: the DEM is refused first
    assert main(["region", str(tmp_path / "r.yaml"), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "dem.tif" in err and "this DEM is in degrees (EPSG:4326)" in err
    assert not (tmp_path / "out").exists()
