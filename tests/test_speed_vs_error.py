"""workflows/speed_vs_error.py: ANUGA's avalanche_dry exact solution, and a --quick run of
the workflow on that case (order 1, and order 2 where avflow has numerics.order): order 1
misses ANUGA's discharge tolerance at 0.5 m, order 2 meets ANUGA's tolerances there."""

import csv
import importlib.util
import math
import sys

import numpy as np
import pytest

from avflow.numerics.analytic import dam_break
from avflow.scenario.schema import load_scenario
from conftest import REPO, SCENARIOS

spec = importlib.util.spec_from_file_location("speed_vs_error",
                                              REPO / "workflows" / "speed_vs_error.py")
sve = importlib.util.module_from_spec(spec)
sys.modules.setdefault("speed_vs_error", sve)  # dataclasses look their module up there
spec.loader.exec_module(sve)

G = 9.81


def anuga_analytical_sol(x, t, h_0=20.0, bed_slope=0.1, friction_slope=0.05):
    """ANUGA's validation_tests/analytical_exact/avalanche_dry/analytical_avalanche_dry.py,
    transcribed: bed z = bed_slope x rising with x, reservoir at x > 0 flowing to -x."""
    thet = math.atan(bed_slope)
    m = -G * bed_slope + G * math.cos(thet) ** 2 * friction_slope
    c0 = math.sqrt(G * h_0)
    h, u = np.zeros(len(x)), np.zeros(len(x))
    for i, xi in enumerate(x):
        if xi <= -2.0 * c0 * t + 0.5 * m * t**2:
            pass
        elif xi <= c0 * t + 0.5 * m * t**2:
            u[i] = 2.0 / 3.0 * (xi / t - c0 + m * t)
            h[i] = 1.0 / (9.0 * G) * (xi / t + 2.0 * c0 - 0.5 * m * t) ** 2
        else:
            u[i], h[i] = m * t, h_0
    return h, u


def test_anuga_avalanche_dry_exact_solution():
    """The workflow's exact solution for ANUGA's runs is ANUGA's, mirrored (flow to +x)."""
    x = np.linspace(-100.0, 100.0, 2001)
    accel = sve.anuga_acceleration(0.1, 0.05)
    assert accel == pytest.approx(0.4953564356, rel=1e-9)  # ANUGA's -m
    for t in (1.0, 2.0, 3.0):
        h_a, u_a = anuga_analytical_sol(x, t)
        h, u = sve.ritter_accelerated(-x, t, 0.0, 20.0, G, accel)
        assert np.allclose(h, h_a, rtol=1e-12, atol=1e-12)
        assert np.allclose(u, -u_a, rtol=1e-12, atol=1e-12)
    # a value worked by hand: t = 2 s, 10 m downslope of the dam (ANUGA's x = -10 m)
    h, u = sve.ritter_accelerated(np.array([10.0]), 2.0, 0.0, 20.0, G, accel)
    assert h[0] == pytest.approx(6.2600872, rel=1e-7)
    assert u[0] == pytest.approx(13.3319026, rel=1e-7)


def test_seed_model_avalanche_dry_is_anugas_case_up_to_theta_squared():
    """avflow's scenario: the same case in the seed's equations (thickness normal to the bed,
    g cos(theta) across it, a = g (sin - cos tan delta)): its exact solution (Mangeney et al.
    2000) differs from ANUGA's only by O(theta^2) = 1% terms: c0 by 0.25%, a by 1.5%."""
    sc = load_scenario(SCENARIOS / "anuga_avalanche_dry.yaml")
    assert math.tan(math.radians(sc.terrain.slope.theta_deg)) == pytest.approx(0.1, rel=1e-12)
    assert math.tan(math.radians(sc.rheology.delta_deg)) == pytest.approx(0.05, rel=1e-12)
    x0, h0 = sc.release.position, sc.release.thickness
    s = np.linspace(x0 - 100.0, x0 + 100.0, 4001)
    for t in (1.0, 3.0):
        h, u = dam_break(s, t, x0=x0, h0=h0, theta_deg=sc.terrain.slope.theta_deg,
                         delta_deg=sc.rheology.delta_deg)
        h_a, u_a = anuga_analytical_sol(x0 - s, t)
        assert np.sum(np.abs(h - h_a)) / np.sum(h_a) < 5e-3
        assert np.sum(np.abs(h * u + h_a * u_a)) / np.sum(np.abs(h_a * u_a)) < 2e-2


def test_quick_run_on_avalanche_dry(tmp_path, capsys):
    assert sve.main(["--quick", "--problems", "avalanche_dry", "--out", str(tmp_path),
                     "--no-anuga"]) == 0
    printed = capsys.readouterr().out
    has_order2, _ = sve.order_support()
    assert ("order 2: available" if has_order2 else "order 2: not available") in printed
    assert (tmp_path / "avalanche_dry.png").stat().st_size > 10_000
    assert "Cheapest measured run" in (tmp_path / "report.md").read_text()
    with open(tmp_path / "avalanche_dry.csv") as f:
        rows = list(csv.DictReader(f))
    o1 = {float(r["dx_m"]): r for r in rows if r["scheme"] == "avflow o1"}
    assert sorted(o1) == [0.5, 2.0]
    for key in ("h_L1_t1", "q_L1_t1", "h_L1_t3", "q_L1_t3"):
        assert float(o1[0.5][f"error_{key}"]) < float(o1[2.0][f"error_{key}"])
    # order 1 at 0.5 m (measured 0.57% / 4.2% at 1 s, 0.83% / 2.1% at 3 s): h within
    # ANUGA's 1%, the discharge not within its 2.5% at 1 s (issue 10: about 5%)
    assert float(o1[0.5]["error_h_L1_t1"]) < 0.01 and float(o1[0.5]["error_h_L1_t3"]) < 0.01
    assert 0.025 < float(o1[0.5]["error_q_L1_t1"]) < 0.06
    assert all(float(r["wall_s"]) > 0.0 and float(r["cpu_s"]) > 0.0 for r in rows)
    if has_order2:
        # issue 10: order 2 at 0.5 m within ANUGA's own tolerances at 1 s and 3 s (measured:
        # h 0.23% / 0.22%, discharge 2.1% / 0.71%)
        o2 = {float(r["dx_m"]): r for r in rows if r["scheme"] == "avflow o2"}
        assert sorted(o2) == [0.5, 2.0]
        for t in ("t1", "t3"):
            assert float(o2[0.5][f"error_h_L1_{t}"]) < 0.01
            assert float(o2[0.5][f"error_q_L1_{t}"]) < 0.025


def test_quick_run_on_the_similarity_solution(tmp_path, capsys):
    """The similarity problems at 10 and 5 m, on the square grid and on triangles: each cell
    size's release raster holds the exact cap at the square cells' centres and at the
    triangles' vertices (their dual cells' centres), so the release is the cap there and the
    errors on squares are tests/test_similarity.py's (its runs, on its cells: order 2 at 5 m
    and 5 s, L2 0.0123 along the grid's axes), and the map is cropped around the flow
    without its edge being reached."""
    assert sve.main(["--quick", "--problems", "similarity,similarity_rot45", "--out",
                     str(tmp_path), "--no-anuga"]) == 0
    assert "reached the cropped map's edge" not in capsys.readouterr().out
    schemes = [f"avflow o{o} {m}" for m in ("square", "triangles") for o in (1, 2)]
    for name in ("similarity", "similarity_rot45"):
        with open(tmp_path / f"{name}.csv") as f:
            rows = {(r["scheme"], float(r["dx_m"])): r for r in csv.DictReader(f)}
        assert sorted(rows) == sorted((s, dx) for s in schemes for dx in (5.0, 10.0))
        # the release: the exact cap at the cells' centres (the raster's nodes; sampled
        # between them, at the vertices, it was up to 0.23 m off), its volume the cap's
        # (measured within 0.13%)
        for r in rows.values():
            assert float(r["release"]) < 1e-9, r
            assert abs(float(r["volume0"])) < 0.01, r
        l2 = {k: float(r["error_l2"]) for k, r in rows.items()}
        # measured 2026-12-05 (along the axes / turned 45 degrees): at 5 m order 2 0.0122 /
        # 0.0116 on squares, 0.0145 / 0.0150 on triangles; order 1 0.0653 / 0.0630 and
        # 0.0710 / 0.0710; both halve or better from 10 m
        assert 0.010 < l2["avflow o2 square", 5.0] < 0.014, l2
        assert 0.012 < l2["avflow o2 triangles", 5.0] < 0.018, l2
        for mesh in ("square", "triangles"):
            o1, o2 = f"avflow o1 {mesh}", f"avflow o2 {mesh}"
            assert l2[o1, 5.0] > 4.0 * l2[o2, 5.0], l2
            for scheme in (o1, o2):
                assert l2[scheme, 5.0] < 0.65 * l2[scheme, 10.0], l2
        # the front (signed): order 2's within a cell of the exact one, order 1's ahead by
        # more than a cell (measured 11 to 28 m)
        for (scheme, dx), r in rows.items():
            front = float(r["front"])
            assert (abs(front) < dx if "o2" in scheme else front > dx), (scheme, dx, r)
            assert math.isfinite(float(r["spread"])) and math.isfinite(float(r["area"])), r
