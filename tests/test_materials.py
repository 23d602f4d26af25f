"""physics.material: snow, debris and rock set the density and the stop rule; the snow laws
without a density take snow's, and say so; a run never at rest says by when, not NaN."""

from __future__ import annotations

import warnings

import pytest

from avflow.errors import AvflowWarning
from avflow.scenario.schema import MATERIALS, parse_scenario

BASE = """
name: materials
terrain: {kind: plane, slope_deg: 30.0, azimuth_deg: 90.0,
          extent: {x: [0.0, 400.0], y: [0.0, 240.0]}}
rheology: RHEOLOGY
grid: {dx: 20.0}
release: {kind: cylinder, center: [100.0, 120.0], radius: 50.0, thickness: 2.0}
time: {end: 12.0, cfl: 0.5}
EXTRA
"""
VOELLMY = "{law: voellmy, mu: 0.2, xi: 1000}"
COULOMB = "{law: coulomb, delta_deg: 20.0}"


def _scenario(rheology=COULOMB, extra=""):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = parse_scenario(BASE.replace("RHEOLOGY", rheology).replace("EXTRA", extra))
    return s, [str(w.message) for w in caught if issubclass(w.category, AvflowWarning)]


@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_a_material_sets_the_density_and_the_stop_rule(material):
    s, said = _scenario(extra=f"physics: {{material: {material}}}")
    assert s.physics.density == MATERIALS[material]["density"]
    assert s.output.stop_rule == MATERIALS[material]["stop_rule"]
    assert said == []


def test_what_is_given_wins_over_the_material():
    s, _ = _scenario(extra="physics: {material: snow, density: 300.0}\n"
                           "output: {stop_rule: moving_volume}")
    assert s.physics.density == 300.0 and s.output.stop_rule == "moving_volume"


@pytest.mark.parametrize("law", ["voellmy", "samosat"])
def test_a_snow_law_without_density_takes_snows_and_says_so_when_it_runs(law):
    rheology = VOELLMY if law == "voellmy" else "{law: samosat, mu: 0.155}"
    s, said = _scenario(rheology)
    assert s.physics.density == 200.0
    assert said == []  # reading says nothing: a bad file gets its one error line alone
    note = s.density_note()
    assert note.startswith("physics.density not given: 200 kg/m^3") and law in note
    given, _ = _scenario(rheology, "physics: {density: 250.0}")
    assert given.density_note() is None and given.physics.density == 250.0
    snow, _ = _scenario(rheology, "physics: {material: snow}")
    assert snow.density_note() is None


def test_the_command_line_says_the_density_once(tmp_path):
    import subprocess
    import sys

    (tmp_path / "s.yaml").write_text(BASE.replace("RHEOLOGY", VOELLMY).replace("EXTRA", ""))
    done = subprocess.run([sys.executable, "-m", "avflow", "run", "s.yaml", "-o", "s.nc"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    lines = [x for x in done.stderr.splitlines() if "physics.density" in x]
    assert lines == ["avflow: warning: physics.density not given: 200 kg/m^3, snow's, for "
                     "the snow law voellmy (set physics.material or physics.density for "
                     "another material)"]


def test_debris_laws_keep_debris_density_without_a_word():
    s, said = _scenario()
    assert s.physics.density == 2000.0 and s.output.stop_rule == "moving_volume"
    assert said == []


def test_the_material_hashes_by_what_it_sets():
    given, _ = _scenario(extra="physics: {density: 200.0}\noutput: {stop_rule: kinetic_energy}")
    preset, _ = _scenario(extra="physics: {material: snow}")
    plain, _ = _scenario()
    assert given.scenario_hash() == preset.scenario_hash() != plain.scenario_hash()


def test_an_unknown_material_is_one_line():
    from avflow.errors import ScenarioError

    with pytest.raises(ScenarioError, match="physics.material"):
        parse_scenario(BASE.replace("RHEOLOGY", COULOMB).replace("EXTRA",
                                                                 "physics: {material: lava}"))


def test_a_run_not_at_rest_says_by_when_not_nan(tmp_path):
    from avflow.cli import main

    path = tmp_path / "s.yaml"
    path.write_text(BASE.replace("RHEOLOGY", COULOMB).replace("EXTRA", ""))
    import contextlib
    import io

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["run", str(path), "-o", str(tmp_path / "s.nc")]) == 0
    line = out.getvalue().splitlines()[0]
    assert "NaN" not in line and ", not at rest by 12 s," in line, line
