"""The alpha-beta model (avflow/output/alphabeta.py) and its place in `avflow path`.

Exact answers: on a piecewise-linear profile (30 degrees, then 5 degrees) the beta point is
the kink, beta is 30 degrees, and every alpha line meets the 5-degree segment where a line
equation says; on a parabola, whose slope falls linearly with s, the 10-degree point is
known in closed form and the sampled beta point lies within one sample of it.
"""

import math

import numpy as np
import pytest

from avflow.output.alphabeta import (REGRESSIONS, AlphaBetaError, alpha_beta, beta_index,
                                     regression)
from avflow.output.path import PathLine, RunPoints, analyse

T30, T5, T10 = (math.tan(math.radians(a)) for a in (30.0, 5.0, 10.0))


def _kinked(ds=10.0, s1=1000.0, end=6000.0):
    s = np.arange(0.0, end + ds / 2, ds)
    z = np.where(s <= s1, 1000.0 - T30 * s, 1000.0 - T30 * s1 - T5 * (s - s1))
    return s, z


def _meets(alpha_deg, s1=1000.0):
    """Where the line from (0, 1000) at alpha meets the 5-degree segment (hand algebra:
    1000 - tan(a) s = 1000 - tan30 s1 - tan5 (s - s1))."""
    return s1 * (T30 - T5) / (math.tan(math.radians(alpha_deg)) - T5)


def test_piecewise_linear_profile_beta_at_the_kink_and_alphas_where_the_algebra_says():
    s, z = _kinked()
    ab = alpha_beta(s, z)  # Norwegian: alpha = 0.96 beta - 1.4, SD 2.3
    assert ab.beta_s == 1000.0
    assert ab.beta == pytest.approx(30.0, abs=1e-12)
    expected = (0.96 * 30.0 - 1.4, 0.96 * 30.0 - 1.4 - 2.3, 0.96 * 30.0 - 1.4 - 4.6)
    np.testing.assert_allclose(ab.alphas, expected, atol=1e-12)
    np.testing.assert_allclose(ab.alphas, (27.4, 25.1, 22.8), atol=1e-12)
    for a, s_, z_ in zip(ab.alphas, ab.points_s, ab.points_z):
        assert s_ == pytest.approx(_meets(a), rel=1e-12)
        assert z_ == pytest.approx(1000.0 - math.tan(math.radians(a)) * _meets(a), abs=1e-9)
    # one of them by hand: alpha 27.4 deg meets the bed at s = 1000 (0.577350 - 0.087489)
    # / (0.518351 - 0.087489) = 1136.93 m
    assert ab.points_s[0] == pytest.approx(1136.93, abs=0.01)


def test_an_alpha_beyond_the_profile_is_nan_not_its_end():
    s, z = _kinked(end=1200.0)  # alpha meets the bed at 1137 m, alpha - 2 SD at 1472 m
    ab = alpha_beta(s, z)
    assert not math.isnan(ab.points_s[0]) and math.isnan(ab.points_s[2])


def test_parabola_ten_degree_point_within_one_sample_of_the_closed_form():
    """z = 1000 - b s + c s^2: slope b - 2 c s reaches tan 10 at s10 = (b - tan10) / 2c."""
    b = math.tan(math.radians(40.0))
    c = (b - T10) / 2000.0  # s10 = 1000 m
    ds = 2.0
    s = np.arange(0.0, 1500.0 + ds / 2, ds)
    z = 1000.0 - b * s + c * s**2
    ab = alpha_beta(s, z)
    assert abs(ab.beta_s - 1000.0) <= ds
    def beta_at(x):
        return math.degrees(math.atan((b * x - c * x * x) / x))
    assert beta_at(1000.0 + ds) <= ab.beta <= beta_at(1000.0 - ds)
    assert ab.beta == pytest.approx(beta_at(1000.0), abs=0.01)
    # the regression with the parabola's terms: z'' = 2c exactly, H0 = its drop on the profile
    small = alpha_beta(s, z, "austria_small")
    assert small.curvature == pytest.approx(2.0 * c, rel=1e-9)
    assert small.height == pytest.approx(z.max() - z.min(), rel=1e-9)
    assert small.alphas[0] == pytest.approx(0.933 * small.beta + 0.0088 * small.height - 5.02,
                                            abs=1e-9)
    austria = alpha_beta(s, z, "austria")
    assert austria.alphas[0] == pytest.approx(1.05 * austria.beta - 3130.0 * 2.0 * c - 2.38,
                                              abs=1e-9)
    assert austria.alphas[1] == pytest.approx(austria.alphas[0] - 1.25, abs=1e-12)


def test_a_bench_shorter_than_30_m_is_not_the_beta_point():
    s = np.arange(0.0, 2000.0, 5.0)
    slope = np.where((s >= 300) & (s < 320), math.tan(math.radians(5.0)), T30)  # 20 m bench
    slope = np.where(s >= 1000, T5, slope)
    z = 1000.0 - np.concatenate([[0.0], np.cumsum(slope[:-1] * np.diff(s))])
    assert s[beta_index(s, z)] == 1000.0
    assert s[beta_index(s, z, ds_min=10.0)] == 300.0  # a shorter guard takes the bench


def test_regressions_by_name_or_coefficients_and_bad_ones_refused():
    assert regression(None) is REGRESSIONS["norway"]
    custom = regression("1, 0, 0, -3, 1.5")
    assert (custom.k1, custom.k4, custom.sd) == (1.0, -3.0, 1.5)
    s, z = _kinked()
    assert alpha_beta(s, z, custom).alphas[0] == pytest.approx(27.0, abs=1e-12)
    for bad in ("sweden", "1,2,3", "1,0,0,-3,-1", "1,0,0,nan,1"):
        with pytest.raises(AlphaBetaError, match="k1,k2,k3,k4,sd"):
            regression(bad)


def test_no_ten_degree_point_gives_nan():
    s = np.arange(0.0, 500.0, 5.0)
    ab = alpha_beta(s, 1000.0 - T30 * s)
    assert math.isnan(ab.beta) and all(math.isnan(v) for v in ab.points_s)


def test_path_analysis_carries_the_alpha_beta_points_beside_the_dynamic_angle():
    """A profile run's cells (the kinked profile, 10 m cells): the ab_* scalars are the
    exact ones, and the dynamic runout angle stands beside them."""
    s, z = _kinked(ds=10.0, end=3000.0)
    released = s <= 100.0
    pressure = np.where(s <= 1200.0, 5000.0, 0.0)
    pts = RunPoints(s, np.zeros_like(s), z,
                    {"peak_pressure": pressure, "peak_speed": pressure / 1e3,
                     "peak_thickness": pressure / 1e3}, released, 10.0, kind="profile")
    r = analyse(pts, PathLine([0.0, 3000.0], [0.0, 0.0], source="the profile"))
    sc = r.scalars
    assert sc["top_s"] == 0.0 and sc["runout_s"] == 1200.0
    assert sc["ab_beta"] == pytest.approx(30.0, abs=1e-9)
    assert sc["ab_alpha"] == pytest.approx(27.4, abs=1e-9)
    assert sc["ab_alpha_s"] == pytest.approx(_meets(27.4), rel=1e-9)
    assert sc["ab_alpha_m2sd_s"] == pytest.approx(_meets(22.8), rel=1e-9)
    dynamic = math.degrees(math.atan2(1000.0 - z[120], 1200.0))
    assert sc["runout_angle"] == pytest.approx(dynamic, abs=1e-9)


def test_a_bench_near_the_top_is_not_the_alpha_point():
    """40 degrees for 20 m, a 15-degree bench to 100 m, 40 degrees to 1000 m, then 5: the
    alpha line from the top dips under the bench, but the runout lies beyond the beta
    point, where the algebra puts it."""
    t40, t15 = math.tan(math.radians(40.0)), math.tan(math.radians(15.0))
    s = np.arange(0.0, 4000.0, 5.0)
    slope = np.where(s < 20, t40, np.where(s < 100, t15, np.where(s < 1000, t40, T5)))
    z = 1000.0 - np.concatenate([[0.0], np.cumsum(slope[:-1] * np.diff(s))])
    ab = alpha_beta(s, z)
    drop = 20 * t40 + 80 * t15 + 900 * t40
    assert ab.beta_s == 1000.0
    assert ab.beta == pytest.approx(math.degrees(math.atan(drop / 1000.0)), abs=1e-9)
    a = math.radians(ab.alphas[0])
    # 1000 - tan(a) s = 1000 - drop - tan5 (s - 1000)
    assert ab.points_s[0] == pytest.approx((drop - 1000 * T5) / (math.tan(a) - T5), rel=1e-9)


def test_a_path_that_starts_off_the_map_still_gives_beta_from_the_release_top():
    """A 10 m grid of the kinked profile (x from 0 to 3000 m), the release's top cell at
    x = 5, the path line from x = -200 (off the map, as a centre-of-mass track's upslope
    extension can be): beta is taken from the top cell to the first sample from which the
    bed falls at 10 degrees or less, the cell centre x = 1005 (bilinear between the centres
    995 and 1005 the bed falls at 18 degrees)."""
    x = np.arange(5.0, 3000.0, 10.0)
    y = np.arange(5.0, 100.0, 10.0)
    zx = np.where(x <= 1000, 1000.0 - T30 * x, 1000.0 - T30 * 1000 - T5 * (x - 1000))
    X, Y = np.meshgrid(x, y)
    Z = np.tile(zx, (y.size, 1))
    released = (X < 50.0)
    pressure = np.where(X < 1200.0, 5000.0, 0.0)
    pts = RunPoints(X.ravel(), Y.ravel(), Z.ravel(),
                    {"peak_pressure": pressure.ravel(), "peak_speed": pressure.ravel() / 1e3,
                     "peak_thickness": pressure.ravel() / 1e3}, released.ravel(), 10.0,
                    grid=(x, y, Z))
    z_top, z_beta = 1000.0 - T30 * 5.0, 1000.0 - T30 * 1000.0 - T5 * 5.0
    r = analyse(pts, PathLine([-200.0, 3000.0], [45.0, 45.0]))
    assert r.scalars["ab_beta_s"] == pytest.approx(1205.0)  # s from the line's start
    assert r.scalars["ab_beta"] == pytest.approx(
        math.degrees(math.atan((z_top - z_beta) / 1000.0)), abs=1e-9)
    # a line whose first segment runs off the map (y > 100) where the top cell projects
    line = PathLine([-50.0, 300.0, 3000.0], [200.0, 45.0, 45.0])
    r = analyse(pts, line)
    sc = r.scalars
    assert math.isfinite(sc["ab_beta"])  # not lost to the stretch off the map
    # the beta point: the first half-cell sample past the kink's cells (samples 5 m apart
    # along the line, not on the cell centres here)
    assert 1000.0 <= float(line.at([sc["ab_beta_s"]])[0][0]) <= 1010.0
    assert sc["ab_beta"] == pytest.approx(math.degrees(math.atan(
        (z_top - sc["ab_beta_z"]) / (sc["ab_beta_s"] - sc["top_s"]))), abs=1e-9)
