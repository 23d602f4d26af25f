"""One runout, the one the field cites: the distance along the path of the farthest cell
whose peak pressure reaches 1 kPa (AvaFrame's AIMEC), the same number with the same name in
the summary line, summary.csv, the run file, the plot title, ``avflow path`` and the
ensemble report; and the automatic path (the centre-of-mass track) on a plane, where the
exact answer is known."""

import math
import re
import shutil

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from avflow.cli import main
from avflow.ensemble.report import write_report
from avflow.output.maps import _title
from conftest import SCENARIOS

SCENE = SCENARIOS / "plane_box_runout_2d.yaml"  # 20 degree plane facing east, a 100 m block


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("headline")
    shutil.copy(SCENE, folder / SCENE.name)
    out = folder / "run.nc"
    return folder, out


def test_one_runout_everywhere(run, capsys):
    folder, out = run
    assert main(["run", str(folder / SCENE.name), "-o", str(out)]) == 0
    line = capsys.readouterr().out
    with xr.open_dataset(out) as ds:
        runout = float(ds["runout"])
        alpha = float(ds["runout_angle"])
        reach = float(ds["reach_from_release_centroid"])
        title = _title(ds)
        assert ds.attrs["runout_path"] == "centre-of-mass track"
        assert ds.attrs["runout_limit"] == "pressure >= 1 kPa"
    assert math.isfinite(runout) and runout != pytest.approx(reach, abs=1.0)
    # the summary line
    assert (f"runout {runout:.1f} m along the centre-of-mass track (pressure >= 1 kPa), "
            f"alpha {alpha:.1f}°") in line
    # the plot title
    assert f"runout {runout:.0f} m along the centre-of-mass track" in title
    assert f"alpha {alpha:.1f}°" in title
    # avflow path
    assert main(["path", str(out)]) == 0
    path_line = capsys.readouterr().out
    assert f"at s = {runout:.1f} m" in path_line and f"alpha {alpha:.2f} deg" in path_line
    assert f"reach_from_release_centroid, the farthest deposit cell from the release " \
           f"centroid: {reach:.1f} m" in path_line
    table = pd.read_csv(out.with_name("run_path.csv"))
    assert table["path_runout_s"].iloc[0] == pytest.approx(runout, abs=1e-6)
    # summary.csv and the ensemble report of the same scene (one member)
    ens = folder / "one.yaml"
    ens.write_text(f"name: one\nbase: {SCENE.name}\nvary:\n  rheology.delta_deg: [24.0]\n")
    assert main(["ensemble", str(ens), "-o", str(folder / "ens"), "--workers", "0",
                 "--quiet"]) == 0
    summary = pd.read_csv(folder / "ens" / "summary.csv")
    assert summary["runout"].iloc[0] == pytest.approx(runout, abs=1e-9)
    assert summary["runout_angle"].iloc[0] == pytest.approx(alpha, abs=1e-9)
    assert summary["reach_from_release_centroid"].iloc[0] == pytest.approx(reach, abs=1e-9)
    report = write_report(folder / "ens").read_text()
    row = next(r for r in report.splitlines() if r.startswith("| coulomb"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert float(cells[2]) == pytest.approx(runout, rel=1e-3)  # runout min (m)
    assert "runout: the distance along the path" in report


def test_the_automatic_path_on_a_plane_gives_the_exact_runout_and_the_slope(run):
    folder, out = run
    if not out.exists():
        assert main(["run", str(folder / SCENE.name), "-o", str(out), "--quiet"]) == 0
    with xr.open_dataset(out) as ds:
        x = np.broadcast_to(ds["x"].values, ds["peak_pressure"].shape)
        h0 = ds["h"].isel(time=0).values
        above = ds["peak_pressure"].values >= 1e3
        # the fall line is +x: the centre-of-mass track runs along it from the top of the
        # release (its upslope edge cells, x = 155 m) to the farthest cell above 1 kPa
        exact = x[above].max() - x[h0 > 0].min()
        assert float(ds["runout"]) == pytest.approx(exact, abs=1e-6)
        # on a plane every chord falls at the slope: alpha is 20 degrees
        assert float(ds["runout_angle"]) == pytest.approx(20.0, abs=1e-6)
