"""What the figures show: map axes in plain metres (no matplotlib offset such as 1e6 or
+1.2e6 on UTM or LV95 coordinates) on the path and calibration maps, the one-parameter
posterior with its best-run star and its whole title, the Sobol legend off the bars, the
calibration footprint's legend naming only what was observed, a profile ensemble's deposit
curves labelled by member.

The scene: a 2 km trough at 20 m cells in LV95 coordinates (x near 2.6e6 m, y near 1.2e6 m),
Voellmy at order 1 (the calibration tests' kernel); a few runs of milliseconds each.
"""

from __future__ import annotations

import numpy as np
import pytest

from avflow.cli import main

X0, Y0, DX = 2600000.0, 1200000.0, 20.0


@pytest.fixture
def figures(monkeypatch):
    """Every figure saved, kept to look at its artists after the command."""
    from matplotlib.figure import Figure

    kept = []
    save = Figure.savefig

    def keep(self, *args, **kwargs):
        kept.append(self)
        return save(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", keep)
    return kept


def _plain(ax) -> None:
    ax.figure.canvas.draw()
    assert ax.xaxis.get_offset_text().get_text() == "", ax.get_title()
    assert ax.yaxis.get_offset_text().get_text() == "", ax.get_title()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from pyproj import CRS

    from avflow.terrain.raster import write_asc

    root = tmp_path_factory.mktemp("lv95")
    x = np.arange(0, 2000 + DX / 2, DX)
    y = np.arange(0, 400 + DX / 2, DX)
    s = np.tan(np.radians(32)) * 0.5 * (1 + np.cos(np.pi * np.clip((x - 600) / 400, 0, 1)))
    z = -np.concatenate([[0], np.cumsum(0.5 * (s[1:] + s[:-1]) * DX)])
    X, Y = np.meshgrid(x, y)
    write_asc(root / "dem.asc", np.broadcast_to(z - z.min(), X.shape)
              + 0.02 * (Y - 200) ** 2 / 200, x + X0, y + Y0, CRS.from_epsg(2056).to_wkt())
    (root / "base.yaml").write_text(f"""name: trough
terrain: {{kind: dem, path: dem.asc}}
grid: {{dx: 20.0}}
release: {{kind: box, x: [{X0 + 100}, {X0 + 200}], y: [{Y0 + 150}, {Y0 + 250}], thickness: 4.0}}
rheology: {{law: voellmy, mu: 0.25, xi: 1500.0}}
time: {{end: 200.0, cfl: 0.5}}
output: {{every: 10.0, stop_rule: kinetic_energy}}
""")
    (root / "line.csv").write_text(f"x,y\n{X0},{Y0 + 200}\n{X0 + 2000},{Y0 + 200}\n")
    assert main(["run", str(root / "base.yaml"), "-o", str(root / "base.nc"), "-q"]) == 0
    return root


def test_path_map_in_plain_metres(scene, figures):
    assert main(["path", str(scene / "base.nc"), "--line", str(scene / "line.csv"),
                 "-q"]) == 0
    fig = figures[-1]
    ax_map = next(ax for ax in fig.axes if ax.get_title() == "peak field and path")
    _plain(ax_map)


@pytest.fixture(scope="module")
def one_parameter(scene):
    from avflow.calibration import calibrate
    from avflow.output.path import analyse_run, read_line
    import xarray as xr

    with xr.open_dataset(scene / "base.nc", decode_times=False) as ds:
        _, res = analyse_run(ds.load(), line=read_line(scene / "line.csv"))
    (scene / "c1.yaml").write_text(f"""base: base.yaml
parameters:
  rheology.mu: [0.1, 0.5]
observations:
  - {{kind: runout, name: runout, point: [{res.scalars['runout_x']}, {Y0 + 200}],
     line: line.csv, error: 20.0}}
method: posterior
budget: 8
seed: 1
posterior: {{walkers: 8, steps: 300, burn: 100, checks: 0}}
sensitivity: {{n: 64}}
""")
    return calibrate(scene / "c1.yaml", scene / "cal", workers=0, quiet=True, report=False)


def test_one_parameter_posterior_star_and_title(one_parameter):
    from avflow.calibration.outputs import _corner

    fig = _corner(one_parameter)
    fig.canvas.draw()
    (ax,) = fig.axes
    best = one_parameter.best["rheology.mu"]
    stars = [line for line in ax.get_lines() if line.get_marker() == "*"]
    assert len(stars) == 1 and stars[0].get_xdata()[0] == pytest.approx(best)
    title = fig._suptitle.get_window_extent()
    assert title.x0 >= 0 and title.x1 <= fig.bbox.x1 and title.y1 <= fig.bbox.y1  # not clipped


def test_sobol_legend_off_the_bars(one_parameter):
    from avflow.calibration.outputs import _sobol_bars

    fig = _sobol_bars(one_parameter)
    fig.canvas.draw()
    (ax,) = fig.axes
    legend = ax.get_legend().get_window_extent()
    assert legend.x0 >= ax.get_window_extent().x1  # beside the axes, over no bar
    assert legend.x1 <= fig.bbox.x1


def test_footprint_legend_only_what_was_observed_and_plain_metres(one_parameter):
    from avflow.calibration.outputs import _footprint

    fig = _footprint(one_parameter)
    (ax,) = fig.axes
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "observed area" not in labels  # only a runout point was observed
    assert labels.count("observed runout") == 1 and any("simulated" in t for t in labels)
    _plain(ax)


def test_profile_ensemble_deposit_curves_are_labelled(tmp_path, figures):
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    (tmp_path / "e.yaml").write_text(
        f"name: profile-small\nbase: {root / 'scenarios' / 'seed_exponential_coulomb15.yaml'}\n"
        "vary:\n  grid.dx: [50.0]\n  rheology.delta_deg: [16.0, 20.0]\n")
    assert main(["ensemble", str(tmp_path / "e.yaml"), "-o", str(tmp_path / "out"),
                 "--workers", "0", "--report", "-q"]) == 0
    fig = next(f for f in figures if f.axes and "deposit profiles" in f.axes[0].get_title())
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels == ["rheology.delta_deg = 16", "rheology.delta_deg = 20"]


SQUARE = """name: square
terrain: {kind: plane, slope_deg: 25.0, azimuth_deg: 90.0,
          extent: {x: [0.0, 600.0], y: [0.0, 600.0]}}
grid: {dx: 20.0}
release: {kind: box, x: [100.0, 200.0], y: [250.0, 350.0], thickness: 5.0}
rheology: {law: coulomb, delta_deg: 20.0}
time: {end: 20.0, cfl: 0.5}
output: {every: 5.0}
"""


def _class_legend(fig, panel):
    legends = [*fig.legends, *(a for a in panel.artists if a.__class__.__name__ == "Legend")]
    if panel.get_legend() is not None:
        legends.append(panel.get_legend())
    return next(g for g in legends if g.get_title().get_text().startswith("peak pressure"))


@pytest.mark.parametrize("wide", [True, False], ids=["wide map", "square map"])
def test_pressure_class_legend_by_its_map_and_plain_metres(scene, tmp_path, figures, wide):
    if wide:  # the trough, 2000 m x 400 m: maps one under the other
        run = scene / "base.nc"
    else:
        (tmp_path / "square.yaml").write_text(SQUARE)
        run = tmp_path / "square.nc"
        assert main(["run", str(tmp_path / "square.yaml"), "-o", str(run), "-q"]) == 0
    assert main(["plot", str(run), "-o", str(tmp_path / "map.png"), "-q"]) == 0
    fig = figures[-1]
    classes = next(ax for ax in fig.axes if ax.get_title() == "peak pressure classes")
    fig.canvas.draw()
    legend = _class_legend(fig, classes)
    box, panel = legend.get_window_extent(), classes.get_window_extent()
    if wide:  # under its map, the lower one
        assert box.y1 <= panel.y0 and panel.x0 <= box.x0 and box.x1 <= panel.x1 + 1
    else:  # just right of its map, from the map's top down
        assert panel.x1 <= box.x0 <= panel.x1 + 0.05 * fig.bbox.width
        assert panel.y0 <= box.y1 <= panel.y1 + 2
        assert classes.get_legend() is legend  # the outlines' legend kept on the map too
        assert any(a.__class__.__name__ == "Legend" for a in classes.artists)
    for ax in fig.axes:
        if ax.get_title() in ("peak flow thickness", "peak pressure classes"):
            _plain(ax)
