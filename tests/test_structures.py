"""Protective structures in the bed (avflow/terrain/structures.py, avflow/output/structures.py).

On a 25-degree plane (10 m cells, Coulomb, order 1: the kernels the other plane tests use):
a dam taller than the flow's run-up keeps every cubic metre on the release's side (the
balance closes to round-off and nothing lies beyond); a low dam is overtopped and the
volume beyond it is reported; an oblique wall turns the flow towards its lower end; a dam
line in another CRS or off the map is one line and exit 2. The dam's cross-section is
checked against its formula on the plane.
"""

import json
import math

import numpy as np
import pytest
import xarray as xr

import avflow
from avflow.cli import main
from avflow.scenario import parse_scenario

PLANE = """
name: dam-{tag}
terrain:
  kind: plane
  slope_deg: 25.0
  azimuth_deg: 180.0
  extent: {{x: [0.0, {width}], y: [0.0, 400.0]}}
grid: {{dx: 10.0}}
release: {{kind: cylinder, center: [100.0, 310.0], radius: 30.0, thickness: 3.0}}
rheology: {{law: coulomb, delta_deg: 20.0}}
{structures}
time: {{end: 40.0, cfl: 0.5}}
output: {{every: 5.0}}
numerics: {{order: 1}}
"""
# (order 1, the default when these figures and the hash below were recorded: the resolved
# scenario, and so its hash, are those of then)


def _line(folder, name, xy, crs=None):
    data = {"type": "FeatureCollection", "features": [{
        "type": "Feature", "properties": {},
        "geometry": {"type": "LineString", "coordinates": [list(p) for p in xy]}}]}
    if crs:
        data["crs"] = {"type": "name", "properties": {"name": crs}}
    path = folder / f"{name}.geojson"
    path.write_text(json.dumps(data))
    return path


def _scenario(tmp_path, tag, structures="", width=200.0):
    text = PLANE.format(tag=tag, width=width, structures=structures)
    return parse_scenario(text, base_dir=tmp_path)


def _ground(y):
    return (y - 200.0) * math.tan(math.radians(25.0))


def test_the_dam_is_built_into_the_bed_as_its_cross_section_says(tmp_path):
    _line(tmp_path, "dam", [(0, 250), (200, 250)])
    sc = _scenario(tmp_path, "tall", "structures: [{line: dam.geojson, height: 25.0, "
                                     "crest_width: 20.0, side_slope_deg: 40.0}]")
    from avflow.terrain.build import build_terrain

    terrain = build_terrain(sc)
    bed = terrain.to_grid(terrain.bed_elevation)
    y = terrain.y
    crest = _ground(250.0) + 25.0
    tan40 = math.tan(math.radians(40.0))
    for j, yj in enumerate(y):
        d = abs(yj - 250.0)
        expected = max(_ground(yj), crest - max(0.0, d - 10.0) * tan40)
        np.testing.assert_allclose(bed[j], expected, atol=1e-9, err_msg=f"y = {yj}")
    # the downhill side meets the ground where (d - 10) tan 40 - d tan 25 = 25: d = (25 +
    # 10 tan 40) / (tan 40 - tan 25) = 89.5 m below the line; rows down to y = 160.5 are
    # raised (y = 165 by 1.7 m), the next (155) is the plane: the band grew past its first
    # guess (10 + 25 / tan 40 = 39.8 m)
    assert bed[np.searchsorted(y, 165.0), 0] > _ground(165.0) + 1.5
    assert bed[np.searchsorted(y, 155.0), 0] == pytest.approx(_ground(155.0), abs=1e-9)
    assert terrain.extras["structures"].names == ["dam"]


def test_a_dam_taller_than_the_flow_holds_every_cubic_metre_upstream(tmp_path):
    _line(tmp_path, "dam", [(0, 250), (200, 250)])
    sc = _scenario(tmp_path, "tall", "structures: [{line: dam.geojson, height: 25.0, "
                                     "crest_width: 20.0, side_slope_deg: 40.0}]")
    ds = avflow.run(sc)
    released = float(ds["release_volume"])
    retained = float(ds["structure_retained_volume"][0])
    beyond = float(ds["structure_overtopped_volume"][0])
    assert beyond == 0.0
    assert float(ds["outflow_volume"]) == 0.0
    assert retained == pytest.approx(released, rel=1e-12)  # the balance, to round-off
    # nothing ever reached a cell past the crest
    peak = ds["peak_thickness"].values
    assert np.all(peak[ds["y"].values < 240.0] == 0.0)
    # the run file carries the edited bed and the height added
    ground = _ground(ds["y"].values)[:, None]
    np.testing.assert_allclose(ds["structure_height"].values,
                               ds["bed_elevation"].values - ground, atol=1e-9)
    assert float(ds["structure_height"].max()) > 25.0
    assert str(ds["structure_name"].values[0]) == "dam"


@pytest.mark.parametrize("y_line, warned", [(262.0, True), (200.0, False)])
def test_a_dam_whose_body_lies_under_the_release_is_said_once(tmp_path, capsys, y_line,
                                                                warned):
    """The line clear of the release (y 280 to 340), the body 10 + 20 / tan 30 = 44.6 m
    either side of it: from y = 262 it reaches the release's lower cells, from y = 200 it
    does not. One warning line naming the dam and the share of the release on it."""
    _line(tmp_path, "dam", [(0, y_line), (200, y_line)])
    (tmp_path / "s.yaml").write_text(PLANE.format(
        tag="under", width=200.0, structures="structures: [{name: upper dam, line: "
        "dam.geojson, height: 20.0, crest_width: 20.0, side_slope_deg: 30.0}]"))
    assert main(["run", str(tmp_path / "s.yaml"), "-o", str(tmp_path / "s.nc")]) == 0
    said = [line for line in capsys.readouterr().err.splitlines() if "dam's body" in line]
    if not warned:
        assert said == []
        return
    assert len(said) == 1, said
    assert "structures: upper dam: the dam's body lies under" in said[0]
    share = float(said[0].split("lies under ")[1].split("%")[0])
    with xr.open_dataset(tmp_path / "s.nc") as ds:
        # the volume of a cell: its thickness times its bed area, dx dy / cos(slope)
        v0 = ds["h"].isel(time=0).values / np.cos(np.radians(ds["slope_angle"].values))
        on = (v0 > 0) & (ds["structure_height"].values > 0)
        expected = 100 * float(v0[on].sum()) / float(v0.sum())
    assert 0.0 < share == pytest.approx(expected, abs=0.06)


def test_a_low_dam_is_overtopped_and_the_volume_beyond_it_reported(tmp_path, capsys):
    _line(tmp_path, "dam", [(0, 250), (200, 250)])
    (tmp_path / "low.yaml").write_text(PLANE.format(
        tag="low", width=200.0, structures="structures: [{name: low dam, line: dam.geojson, "
        "height: 2.0, crest_width: 0.0, side_slope_deg: 30.0}]"))
    out = tmp_path / "low.nc"
    assert main(["run", str(tmp_path / "low.yaml"), "-o", str(out)]) == 0
    line = capsys.readouterr().out
    assert "low dam: retained" in line and "beyond" in line
    assert main(["run", str(tmp_path / "low.yaml"), "-o", str(tmp_path / "none.nc"),
                 "--without-structures"]) == 0
    with xr.open_dataset(out) as ds:
        released = float(ds["release_volume"])
        retained = float(ds["structure_retained_volume"][0])
        beyond = float(ds["structure_overtopped_volume"][0])
        out_of_map = float(ds["outflow_volume"])
    assert beyond > 0.2 * released  # overtopped
    assert retained + beyond + out_of_map == pytest.approx(released, rel=1e-12)
    with xr.open_dataset(tmp_path / "none.nc") as bare:
        assert "structure_retained_volume" not in bare
        bare_front = float(bare["y"][np.flatnonzero(bare["peak_thickness"].max("x").values
                                                    > 0.01)[0]])
    capsys.readouterr()
    assert main(["compare", str(tmp_path / "none.nc"), str(out), "-o",
                 str(tmp_path / "cmp")]) == 0
    said = capsys.readouterr().out
    assert "B's structures: retained" in said
    import pandas as pd

    table = pd.read_csv(tmp_path / "cmp.csv")
    assert list(table["run"]) == ["A", "B", "B - A"]
    assert table.loc[1, "structure_overtopped_volume"] == pytest.approx(beyond)
    assert (tmp_path / "cmp.png").stat().st_size > 0
    assert bare_front < 250.0  # without the dam the flow passed the line as well
    _compare_figure_is_a_map_figure(tmp_path / "none.nc", out)
    # a file that is not a run: one line, exit 2, nothing written
    capsys.readouterr()
    assert main(["compare", str(out), str(tmp_path / "low.yaml"), "-o",
                 str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "low.yaml" in err
    assert not (tmp_path / "bad.csv").exists()


def _compare_figure_is_a_map_figure(run_a, run_b):
    """The comparison's maps as `avflow plot` draws a run: axes labelled in metres with
    plain numbers (no offset), the release and B's dam outlined, a scale bar and a north
    arrow on each map, the pressure classes named."""
    import matplotlib.pyplot as plt
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    from avflow.output.structures import compare_figure

    with xr.open_dataset(run_a) as a, xr.open_dataset(run_b) as b:
        pa = np.nan_to_num(a["peak_pressure"].values) * 1e-3
        pb = np.nan_to_num(b["peak_pressure"].values) * 1e-3
        fig = compare_figure(a, b, pa, pb, "none.nc", "low.nc")
    try:
        fig.canvas.draw()
        maps = [ax for ax in fig.axes if ax.get_xlabel()]
        assert len(maps) == 3
        for ax in maps:
            assert ax.get_xlabel().startswith("x (m)") and ax.get_ylabel() == "y (m)"
            assert ax.xaxis.get_major_formatter().get_offset() == ""
            assert ax.yaxis.get_major_formatter().get_offset() == ""
            assert any(isinstance(c, AnchoredSizeBar) for c in ax.get_children())
            assert any(t.get_text() == "N" for t in ax.texts)  # the north arrow
        labels = [t.get_text() for ax in maps if ax.get_legend() for t in
                  ax.get_legend().get_texts()]
        assert "release" in labels and "structure (> 0.5 m)" in labels
        named = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
        assert any("kPa" in t for t in named)
    finally:
        plt.close(fig)


def test_an_oblique_wall_turns_the_flow_towards_its_lower_end(tmp_path):
    """A vertical wall from (40, 270) down to (260, 160) across the fall line (-y): the flow
    slides along it towards +x; without it the flow stays on x = 100 by symmetry."""
    _line(tmp_path, "wall", [(40, 270), (260, 160)])
    walled = avflow.run(_scenario(tmp_path, "wall", "structures: [{line: wall.geojson, "
                                  "kind: wall, height: 5.0}]", width=300.0))
    bare = avflow.run(_scenario(tmp_path, "bare", width=300.0))
    x_walled = float(walled["center_of_mass_x"][-1])
    x_bare = float(bare["center_of_mass_x"][-1])
    assert x_bare == pytest.approx(100.0, abs=0.5)
    assert x_walled > x_bare + 20.0
    assert float(walled["mass_balance_error"]) < 1e-12
    # the wall's cells are out of the mesh, so the flow never stood in them
    built = np.isnan(walled["bed_elevation"].values)
    assert built.any() and np.all(np.nan_to_num(walled["peak_thickness"].values)[built] == 0)


def _dem(tmp_path):
    from avflow.terrain.raster import write_tif

    x = np.arange(5.0, 200.0, 10.0) + 600000.0
    y = np.arange(5.0, 400.0, 10.0) + 200000.0
    z = np.tile(((y - y[0]) * 0.5)[:, None], (1, x.size))
    from pyproj import CRS

    write_tif(tmp_path / "dem.tif", z, x, y, CRS.from_epsg(31287).to_wkt())
    return x, y


@pytest.mark.parametrize("case", ["other_crs", "off_the_map"])
def test_a_dam_line_in_another_crs_or_off_the_map_is_one_line_exit_2(tmp_path, capsys, case):
    x, y = _dem(tmp_path)
    if case == "other_crs":  # degrees, WGS 84
        _line(tmp_path, "dam", [(13.0, 47.0), (13.01, 47.0)])
        expect = "reproject the line to the DEM's CRS"
    else:  # metres, but 5 km away
        _line(tmp_path, "dam", [(x[0] + 5000, y[10]), (x[-1] + 5000, y[10])])
        expect = "reaches outside the DEM"
    (tmp_path / "s.yaml").write_text(f"""
name: dem-dam
terrain: {{kind: dem, path: dem.tif}}
grid: {{dx: 10.0}}
release: {{kind: cylinder, center: [{x[10]}, {y[30]}], radius: 30.0, thickness: 2.0}}
rheology: {{law: coulomb, delta_deg: 20.0}}
structures: [{{line: dam.geojson, height: 5.0, side_slope_deg: 40.0}}]
time: {{end: 5.0}}
""")
    assert main(["run", str(tmp_path / "s.yaml"), "-o", str(tmp_path / "s.nc")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "structures[0].line" in err and expect in err
    assert not (tmp_path / "s.nc").exists()


def test_scenario_checks_of_a_structure(tmp_path):
    _line(tmp_path, "dam", [(0, 250), (200, 250)])
    with pytest.raises(Exception, match="side_slope_deg.*required for a dam"):
        _scenario(tmp_path, "x", "structures: [{line: dam.geojson, height: 5.0}]")
    with pytest.raises(Exception, match="a wall is vertical"):
        _scenario(tmp_path, "x", "structures: [{line: dam.geojson, kind: wall, height: 5.0, "
                                 "side_slope_deg: 40}]")
    with pytest.raises(Exception, match="file not found"):
        _scenario(tmp_path, "x", "structures: [{line: gone.geojson, height: 5.0, "
                                 "side_slope_deg: 40}]")


def test_a_region_scenario_block_refuses_structures(tmp_path):
    from avflow.region import RegionError, load_region

    x, y = _dem(tmp_path)
    _line(tmp_path, "dam", [(x[2], y[10]), (x[-3], y[10])])
    (tmp_path / "rel.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"thickness": 1.0}, "geometry": {
            "type": "Polygon", "coordinates": [[[x[5], y[30]], [x[9], y[30]], [x[9], y[34]],
                                                [x[5], y[34]], [x[5], y[30]]]]}}]}))
    (tmp_path / "r.yaml").write_text("""\
name: r
dem: dem.tif
releases: {path: rel.geojson}
scenario:
  rheology: {law: coulomb, delta_deg: 20.0}
  time: {end: 5.0}
  structures: [{line: dam.geojson, height: 5.0, side_slope_deg: 40.0}]
""")
    with pytest.raises(RegionError, match="scenario.structures: a structure belongs"):
        load_region(tmp_path / "r.yaml")


def test_hash_without_structures_is_unchanged_and_lines_count_by_content(tmp_path):
    # recorded before the structures block existed: a scenario without it hashes the same
    assert _scenario(tmp_path, "h").scenario_hash() == "99c37ce8e570da4d"
    _line(tmp_path, "dam", [(0, 250), (200, 250)])
    block = "structures: [{line: %s, height: 5.0, side_slope_deg: 40.0}]"
    with_dam = _scenario(tmp_path, "h", block % "dam.geojson").scenario_hash()
    assert with_dam != "99c37ce8e570da4d"
    (tmp_path / "elsewhere").mkdir()
    _line(tmp_path / "elsewhere", "dam", [(0, 250), (200, 250)])
    assert _scenario(tmp_path, "h", block % "elsewhere/dam.geojson").scenario_hash() == with_dam
    _line(tmp_path / "elsewhere", "dam", [(0, 240), (200, 240)])
    assert _scenario(tmp_path, "h", block % "elsewhere/dam.geojson").scenario_hash() != with_dam


def test_a_run_never_writes_over_its_structure_line(tmp_path, capsys):
    _line(tmp_path, "dam", [(0, 250), (200, 250)])
    (tmp_path / "s.yaml").write_text(PLANE.format(
        tag="x", width=200.0, structures="structures: [{line: dam.geojson, height: 5.0, "
        "side_slope_deg: 40.0}]"))
    before = (tmp_path / "dam.geojson").read_bytes()
    assert main(["run", str(tmp_path / "s.yaml"), "-o", str(tmp_path / "dam.geojson")]) == 2
    assert "dam.geojson" in capsys.readouterr().err
    assert (tmp_path / "dam.geojson").read_bytes() == before
