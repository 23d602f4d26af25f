"""avflow plot and avflow report of a region: the merged peak map over the hillshade, the
release outlines, the release that set each maximum; ensemble hints never shown for a region.

Reuses the tiny region of test_region.py (20 m cells, order 1 Coulomb: kernels the region
tests compile already).
"""

from __future__ import annotations

import numpy as np
import pytest

from avflow.cli import main
from avflow.region import load_region
from avflow.region.orchestrate import run_region

from test_region import BOXES, REGION, _dem, _releases


@pytest.fixture(scope="module")
def region_out(tmp_path_factory):
    folder = tmp_path_factory.mktemp("region_plot")
    _dem(folder)
    _releases(folder / "releases.gpkg", BOXES[:2])
    (folder / "r.yaml").write_text(REGION.format(releases="releases.gpkg", buffer=40.0)
                                   + "  thresholds: {peak_pressure: [1.0]}\n")
    run_region(load_region(folder / "r.yaml"), folder / "out", workers=0, quiet=True)
    return folder / "out"


def _drawn(monkeypatch):
    """The figure avflow plot saves, kept open to look at its axes."""
    import avflow.output.maps as maps

    figures = []
    save = maps._save

    def keep(fig, target):
        figures.append(fig)
        return save(fig, target)

    monkeypatch.setattr(maps, "_save", keep)
    return figures


def test_plot_draws_the_merged_maps_outlines_and_release_ids(region_out, monkeypatch, capsys):
    from avflow.output.maps import _plt

    figures = _drawn(monkeypatch)
    monkeypatch.setattr(_plt(), "close", lambda fig=None: None)
    assert main(["plot", str(region_out)]) == 0
    png = region_out / "region.png"
    assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert f"wrote {png}" in capsys.readouterr().out
    fig = figures[-1]
    left, right = fig.axes[:2]
    assert "peak pressure" in left.get_title() and "release that set" in right.get_title()
    for ax in (left, right):
        images = ax.get_images()
        assert len(images) == 2  # the hillshade, then the map over it
        # the release outlines: one dashed line a polygon
        assert sum(line.get_linestyle() == "--" for line in ax.get_lines()) == 2
        fig.canvas.draw()
        assert ax.xaxis.get_offset_text().get_text() == ""  # plain map coordinates
        assert ax.yaxis.get_offset_text().get_text() == ""
    ids = np.ma.filled(right.get_images()[1].get_array(), -1)
    assert set(np.unique(ids[ids >= 0])) == {0, 1}  # both releases set some maximum
    assert {t.get_text() for t in right.texts} == {"1", "2"}
    legend = [t.get_text() for t in right.get_legend().get_texts()]
    assert legend == ["release 1", "release 2"]


def test_plot_of_the_store_itself_and_report(region_out, capsys):
    out = region_out.parent / "store.png"
    assert main(["plot", str(region_out / "region.zarr"), "-o", str(out), "-q"]) == 0
    assert out.is_file()
    assert main(["report", str(region_out)]) == 0
    report = (region_out / "report.md").read_text()
    assert "![merged maps](region.png)" in report and "| ok |" in report
    assert "members" not in capsys.readouterr().err
    assert main(["path", str(region_out)]) == 2  # not a run: says what draws a region
    err = capsys.readouterr().err
    assert "a region's maps" in err and f"avflow plot {region_out}" in err


def test_a_folder_that_is_no_region_nor_ensemble_names_neither_members(tmp_path, capsys):
    assert main(["plot", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "members" not in err and "a folder" in err


def test_probability_cogs_carry_unit_1_and_the_thresholds_unit_apart(region_out, tmp_path):
    import rasterio

    assert main(["export", str(region_out), "-o", str(tmp_path), "-q", "--variables",
                 "peak_pressure_exceedance_probability"]) == 0
    with rasterio.open(tmp_path / "region_peak_pressure_exceedance_probability_1kPa.tif") as src:
        assert src.units == ("1",)
        assert src.tags(1)["threshold_units"] == "kPa" and "units" not in src.tags(1)


def test_exceedance_maps_asked_of_a_region_without_them_say_why(tmp_path, capsys):
    from test_region import _dem as dem

    dem(tmp_path)
    _releases(tmp_path / "releases.gpkg", BOXES[:1])
    (tmp_path / "r.yaml").write_text(REGION.format(releases="releases.gpkg", buffer=40.0))
    run_region(load_region(tmp_path / "r.yaml"), tmp_path / "out", workers=0, quiet=True)
    assert main(["export", str(tmp_path / "out"), "-o", str(tmp_path / "cogs"), "--variables",
                 "peak_pressure,peak_pressure_exceedance_count"]) == 2
    err = capsys.readouterr().err
    assert "peak_pressure_exceedance_count" in err and "scenarios:" in err
    assert not (tmp_path / "cogs" / "region_peak_pressure.tif").exists()


def test_region_summary_names_its_files_one_way_and_no_parquet_line(tmp_path, monkeypatch,
                                                                    capsys):
    from test_region import _dem as dem

    dem(tmp_path)
    _releases(tmp_path / "releases.gpkg", BOXES[:1])
    (tmp_path / "r.yaml").write_text(REGION.format(releases="releases.gpkg", buffer=40.0))
    monkeypatch.chdir(tmp_path)
    assert main(["region", "r.yaml", "-o", "maps", "--workers", "0"]) == 0
    out, err = capsys.readouterr()
    assert "wrote maps/region.zarr and maps/releases.csv" in out, out
    assert "parquet" not in err
