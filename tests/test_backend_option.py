"""``--backend`` reaches every member of an ensemble and every release of a region as
``numerics.backend`` (the runs themselves are stopped before they start: no GPU needed)."""

from __future__ import annotations

import pytest

from avflow.cli import main
from conftest import SCENARIOS


class Stop(Exception):
    """Raised in place of running: what would have run is kept."""


def test_ensemble_backend_reaches_every_member(monkeypatch, tmp_path):
    import avflow.ensemble.orchestrate as orchestrate

    seen = {}

    def capture(ensemble, *args, **kwargs):
        seen["backends"] = {m.scenario.numerics.backend for m in ensemble.members}
        raise Stop

    monkeypatch.setattr(orchestrate, "run_ensemble", capture)
    with pytest.raises(Stop):
        main(["ensemble", str(SCENARIOS / "ensembles" / "avakot_ensemble.yaml"), "-o",
              str(tmp_path / "out"), "--workers", "0", "--backend", "cuda", "-q"])
    assert seen["backends"] == {"cuda"}


def test_region_backend_reaches_the_scenario_block(monkeypatch, tmp_path):
    import avflow.region.orchestrate as orchestrate

    import test_region

    test_region._dem(tmp_path)
    test_region._releases(tmp_path / "releases.gpkg", test_region.BOXES[:1])
    (tmp_path / "r.yaml").write_text(test_region.REGION.format(releases="releases.gpkg",
                                                                buffer=40.0))
    seen = {}

    def capture(region, *args, **kwargs):
        seen["scenario"] = region.scenario_for(str(tmp_path / "dem.tif"), 20.0, 20.0,
                                               str(tmp_path / "releases.gpkg"), None, "x")
        seen["order"] = region.scenario["numerics"]["order"]
        raise Stop

    monkeypatch.setattr(orchestrate, "run_region", capture)
    with pytest.raises(Stop):
        main(["region", str(tmp_path / "r.yaml"), "-o", str(tmp_path / "out"), "--workers",
              "0", "--backend", "cuda", "-q"])
    assert seen["scenario"].numerics.backend == "cuda"
    assert seen["order"] == 1  # the block's own numerics kept
