"""The alpha-beta model (Lied and Bakkehøi 1980): a statistical runout angle from the
path's profile, the practitioner's first check beside a dynamic run.

- **beta** is the angle seen from the top of the release to the *beta point*, the first
  point of the profile from which its slope is 10 degrees or less (and stays so over the
  next ``ds_min`` metres, AvaFrame com2AB's guard against short benches, 30 m by default).
  The profile is taken as piecewise linear between its samples, so the beta point is a
  sample: the start of the first segment of 10 degrees or less.
- **alpha** follows a regression ``alpha = k1 beta + k2 z'' + k3 H0 + k4`` (degrees), with
  ``z''`` the second derivative and ``H0`` the height (max - min) of the least-squares
  parabola through the whole profile (as AvaFrame com2AB computes them); ``alpha - 1 SD``
  and ``alpha - 2 SD`` reach farther.
- each alpha's **point** is where the line from the top of the release, falling at that
  angle, first meets the profile beyond the beta point (from the top for an alpha above
  beta), linear between the samples: exact on a piecewise-linear profile.

The regressions (:data:`REGRESSIONS`) are published ones, quoted with their sources; a
user's own is ``k1,k2,k3,k4,sd``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from avflow.errors import AvflowError

__all__ = ["ABResult", "AlphaBetaError", "REGRESSIONS", "Regression", "alpha_beta",
           "regression"]

#: The slope (degrees) that marks the beta point.
BETA_SLOPE_DEG = 10.0
#: A path whose beta point lies this many degrees above its start is drawn uphill.
UPHILL_DEG = 1.0
#: AvaFrame com2AB's dsMin: the slope must stay at or under 10 degrees this far (m).
DS_MIN = 30.0


class AlphaBetaError(AvflowError):
    """A regression that cannot be read; one line, exit 2."""


@dataclass(frozen=True)
class Regression:
    """``alpha = k1 beta + k2 z'' + k3 H0 + k4`` (degrees; ``z''`` in 1/m, ``H0`` in m) and
    the standard deviation of its residuals (degrees)."""

    name: str
    k1: float
    k2: float
    k3: float
    k4: float
    sd: float
    source: str

    def alpha(self, beta: float, curvature: float = 0.0, height: float = 0.0) -> float:
        return self.k1 * beta + self.k2 * curvature + self.k3 * height + self.k4


#: Published regressions. The Norwegian one is Lied and Bakkehøi's; the Austrian sets are
#: those AvaFrame com2AB ships (its com2ABCfg.ini, standard and ``smallAva``).
REGRESSIONS = {
    "norway": Regression(
        "norway", 0.96, 0.0, 0.0, -1.4, 2.3,
        "Lied and Bakkehøi (1980), J. Glaciol. 26(94), 165-177: alpha = 0.96 beta - 1.4 deg, "
        "SD 2.3 deg (Norwegian paths)"),
    "austria": Regression(
        "austria", 1.05, -3130.0, 0.0, -2.38, 1.25,
        "AvaFrame com2AB default set (com2ABCfg.ini k1..k4, SD), calibrated on avalanches in "
        "the Austrian Alps (AvaFrame cites Lied and Bakkehøi 1980, Bakkehøi et al. 1983, "
        "Ann. Glaciol. 4, 24-29, Wagner 2016, MSc thesis BOKU)"),
    "austria_small": Regression(
        "austria_small", 0.933, 0.0, 0.0088, -5.02, 2.36,
        "AvaFrame com2AB small-avalanche set (com2ABCfg.ini k1_small..SD_small; Wagner 2016, "
        "MSc thesis BOKU: small and medium avalanches)"),
}
DEFAULT = "norway"


_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")


def regression(spec: str | Regression | None) -> Regression:
    """A regression by name (:data:`REGRESSIONS`) or as ``k1,k2,k3,k4,sd``."""
    if spec is None:
        return REGRESSIONS[DEFAULT]
    if isinstance(spec, Regression):
        return spec
    text = str(spec).strip()
    if text in REGRESSIONS:
        return REGRESSIONS[text]
    parts = [p.strip() for p in text.split(",")]
    # plain decimals only: Python's float() reads "1_0" as 10 and "infinity" as inf
    values = [float(p) for p in parts if _NUMBER.fullmatch(p)]
    if len(parts) != 5 or len(values) != 5 or not all(math.isfinite(v) for v in values) \
            or values[4] < 0:
        raise AlphaBetaError(f"alpha-beta regression {text!r}: give one of "
                             f"{', '.join(REGRESSIONS)} or k1,k2,k3,k4,sd (five numbers, "
                             "sd >= 0)")
    k1, k2, k3, k4, sd = values
    # alpha is an angle of a path: for a plain slope (z'' = 0, H0 = 0) with beta anywhere
    # from 10 to 60 degrees, and its SD, it must lie in (0, 90) degrees
    for beta in (BETA_SLOPE_DEG, 60.0):
        alpha = k1 * beta + k4
        if not (0.0 < alpha - 2.0 * sd and alpha < 90.0):
            raise AlphaBetaError(f"alpha-beta regression {text!r}: gives alpha = {alpha:.4g} "
                                 f"deg (minus 2 SD: {alpha - 2 * sd:.4g}) for beta = "
                                 f"{beta:g} deg; alpha must lie in (0, 90) degrees")
    return Regression("custom", k1, k2, k3, k4, sd,
                      f"user's coefficients: alpha = {k1:g} beta + {k2:g} z'' + {k3:g} H0 "
                      f"+ {k4:g} deg, SD {sd:g} deg")


@dataclass(frozen=True)
class ABResult:
    """beta, the alphas (alpha, alpha - 1 SD, alpha - 2 SD) and where each meets the
    profile (``s`` from the top of the release, ``z``); NaN where not found."""

    regression: Regression
    beta: float
    beta_s: float
    beta_z: float
    curvature: float
    height: float
    alphas: tuple          #: (alpha, alpha - SD, alpha - 2 SD), degrees
    points_s: tuple        #: their s (NaN: beyond the profile's end)
    points_z: tuple

    LABELS = ("alpha", "alpha_m1sd", "alpha_m2sd")


def _nan_result(reg: Regression) -> ABResult:
    nan = math.nan
    return ABResult(reg, nan, nan, nan, nan, nan, (nan,) * 3, (nan,) * 3, (nan,) * 3)


def beta_index(s: np.ndarray, z: np.ndarray, ds_min: float = DS_MIN) -> int | None:
    """The first sample from which the profile falls at 10 degrees or less over the next
    ``ds_min`` metres (every segment starting within them); None if there is none."""
    ds = np.diff(s)
    tan = (z[:-1] - z[1:]) / ds
    gentle = tan <= math.tan(math.radians(BETA_SLOPE_DEG)) * (1.0 + 1e-12)
    for j in np.flatnonzero(gentle):
        if j == 0:
            continue  # the top itself: no beta from a flat start
        ahead = (s[:-1] >= s[j]) & (s[:-1] < s[j] + ds_min)
        if gentle[ahead].all():
            return int(j)
    return None


def crossing(s: np.ndarray, z: np.ndarray, angle_deg: float, start: int = 0
             ) -> tuple[float, float]:
    """Where the line from ``(s[0], z[0])`` falling at ``angle_deg`` first meets the
    profile from above (linear between samples), from sample ``start`` on; NaN, NaN beyond
    its end."""
    line = z[0] - math.tan(math.radians(angle_deg)) * (s - s[0])
    d = line - z  # > 0: the line runs above the bed
    above = np.flatnonzero(d[1:] > 0.0) + 1
    above = above[above >= start]
    if above.size == 0:
        return math.nan, math.nan
    for j in range(int(above[0]), s.size - 1):
        if d[j] > 0.0 and d[j + 1] <= 0.0:
            t = d[j] / (d[j] - d[j + 1])
            sj = s[j] + t * (s[j + 1] - s[j])
            return float(sj), float(z[j] + t * (z[j + 1] - z[j]))
    return math.nan, math.nan


def alpha_beta(s, z, reg: str | Regression | None = None, ds_min: float = DS_MIN) -> ABResult:
    """The alpha-beta model on a profile ``z(s)`` whose first sample is the top of the
    release (``s`` horizontal, increasing; samples with a NaN bed are dropped from the end
    on: the profile stops at the first one)."""
    reg = regression(reg)
    s, z = np.asarray(s, dtype=float), np.asarray(z, dtype=float)
    bad = np.flatnonzero(~(np.isfinite(s) & np.isfinite(z)))
    if bad.size:
        s, z = s[:bad[0]], z[:bad[0]]
    if s.size < 3 or np.any(np.diff(s) <= 0):
        return _nan_result(reg)
    k = beta_index(s, z, ds_min)
    if k is None:
        return _nan_result(reg)
    beta = math.degrees(math.atan2(z[0] - z[k], s[k] - s[0]))
    if beta <= -UPHILL_DEG:  # drawn uphill: beta and alpha would be negative
        raise AlphaBetaError(f"the path does not descend from the release: it starts at "
                             f"{z[0]:.1f} m and rises to {z[k]:.1f} m at {s[k] - s[0]:.0f} m "
                             f"(beta {beta:.1f} deg); draw it from the top of the release "
                             "down the fall line")
    if not beta > BETA_SLOPE_DEG:  # no slope steeper than 10 degrees: no beta point
        return _nan_result(reg)
    curvature = height = 0.0
    if reg.k2 != 0.0 or reg.k3 != 0.0:
        poly = np.poly1d(np.polyfit(s - s[0], z, 2))
        curvature = float(poly.deriv(2)(0.0))
        fit = poly(s - s[0])
        height = float(fit.max() - fit.min())
    alpha = reg.alpha(beta, curvature, height)
    if not (math.isfinite(alpha) and 0.0 < alpha - 2.0 * reg.sd and alpha < 90.0):
        raise AlphaBetaError(f"the {reg.name} regression gives alpha = {alpha:.4g} deg on "
                             f"this path (beta {beta:.1f} deg, z'' {curvature:.3g} 1/m, H0 "
                             f"{height:.4g} m; minus 2 SD: {alpha - 2 * reg.sd:.4g}): not an "
                             "angle in (0, 90) degrees; check its coefficients")
    alphas = (alpha, alpha - reg.sd, alpha - 2.0 * reg.sd)
    # an angle under beta meets the bed beyond the beta point (AvaFrame's com2AB looks
    # beyond its split point): a gentle stretch near the top is not a runout
    points = [crossing(s, z, a, k if a <= beta else 0) if 0.0 < a < 90.0
              else (math.nan, math.nan) for a in alphas]
    return ABResult(reg, beta, float(s[k]), float(z[k]), curvature, height, alphas,
                    tuple(p[0] for p in points), tuple(p[1] for p in points))
