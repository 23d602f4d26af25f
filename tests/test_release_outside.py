"""A release polygon that covers no cell of the map (another file, another CRS's numbers):
one line naming the file and where it lies against the map, exit 2, nothing written."""

from __future__ import annotations

from pathlib import Path

from avflow.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_release_outside_the_dem_names_the_file_and_the_bounds(tmp_path, capsys):
    (tmp_path / "far.geojson").write_text(
        '{"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {}, '
        '"geometry": {"type": "Polygon", "coordinates": '
        '[[[1000, 2000], [1100, 2000], [1100, 2100], [1000, 2100], [1000, 2000]]]}}]}')
    (tmp_path / "s.yaml").write_text(f"""name: far
terrain: {{kind: dem, path: {ROOT / 'data/avaframe/avaKot/avaKot.asc'}}}
grid: {{dx: 20.0}}
release: {{kind: polygon, path: far.geojson, thickness: 1.0}}
rheology: {{law: coulomb, delta_deg: 20.0}}
time: {{end: 10.0}}
""")
    assert main(["run", str(tmp_path / "s.yaml"), "-o", str(tmp_path / "o.nc")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "far.geojson" in err and "x 1000-1100 m, y 2000-2100 m" in err
    assert "of the map (x 1769" in err  # avaKot's cell centres, EPSG:31287
    assert not (tmp_path / "o.nc").exists()


def test_a_region_release_on_no_cell_names_no_removed_work_file(tmp_path):
    from test_region import BOXES, REGION, _dem, _releases

    from avflow.region import load_region
    from avflow.region.orchestrate import run_region

    _dem(tmp_path)
    _releases(tmp_path / "releases.gpkg", [BOXES[4]])  # 6 m x 6 m between cell centres
    (tmp_path / "r.yaml").write_text(REGION.format(releases="releases.gpkg", buffer=40.0))
    outcome = run_region(load_region(tmp_path / "r.yaml"), tmp_path / "out", workers=0,
                         quiet=True)
    error = outcome.table.loc[0, "error"]
    assert "no mass on any cell" in error and "x 1022-1028 m" in error
    assert "work" not in error and "release.gpkg" not in error
