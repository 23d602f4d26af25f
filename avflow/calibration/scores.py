"""Scores of a run against an observation, and how several combine into one misfit.

Pure functions on arrays of cells (the cells of the simulation domain, in any order): no
file, no model. Formulas (docs/calibration.md has them with their sources):

Areas, on the domain's cells, ``sim`` the cells whose peak field reaches the threshold and
``obs`` those inside the observed area::

    TP = |sim & obs|   FP = |sim & ~obs|   FN = |~sim & obs|   TN = |~sim & ~obs|

TN are the domain's cells outside both areas (not an invented multiple of the observed
area, as r.avaflow takes). Then ``CSI = TP / (TP + FP + FN)``, ``F1 = 2 TP / (2 TP + FP +
FN)``, ``Tversky(alpha, beta) = TP / (TP + alpha FP + beta FN)`` (alpha = beta = 1 is CSI,
alpha = beta = 1/2 is F1), and the AUROC of the peak field as a classifier of ``obs`` over
every threshold (scikit-learn's ``roc_auc_score``: the area under TPR = TP / (TP + FN)
against FPR = FP / (FP + TN)).

Runout: ``s_sim - s_obs`` along the path (m; > 0 the run went farther). Thickness:
``RMSE = sqrt(mean((h_sim - h_obs)^2))`` over the union of the cells where either reaches
the threshold.

Misfit: each observation gives a discrepancy ``d_i`` (area: ``1 - score``; runout: the
signed difference; thickness: the RMSE) and an error ``sigma_i`` (the file's ``error``);
``misfit = sum_i w_i (d_i / sigma_i)^2``, and the Gaussian log-likelihood is
``-misfit / 2`` up to a constant (weights other than 1 temper it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Confusion", "confusion", "csi", "f1", "tversky", "auroc", "area_scores",
           "runout_difference", "rmse_union", "misfit", "log_likelihood", "AREA_SCORES"]

#: The area scores a file can choose (each in [0, 1], 1 a perfect match).
AREA_SCORES = ("csi", "f1", "tversky", "auroc")


@dataclass(frozen=True)
class Confusion:
    """Confusion counts of a simulated against an observed area, on the domain's cells."""

    tp: int
    fp: int
    fn: int
    tn: int

    @property
    def n(self) -> int:
        return self.tp + self.fp + self.fn + self.tn


def confusion(sim, obs, domain=None) -> Confusion:
    """Counts of boolean arrays ``sim`` and ``obs`` (same shape) over ``domain`` (True:
    a cell of the simulation domain; None: every cell)."""
    sim = np.asarray(sim, dtype=bool)
    obs = np.asarray(obs, dtype=bool)
    if sim.shape != obs.shape:
        raise ValueError(f"sim and obs differ in shape: {sim.shape} and {obs.shape}")
    if domain is not None:
        domain = np.asarray(domain, dtype=bool)
        sim, obs = sim[domain], obs[domain]
    tp = int(np.count_nonzero(sim & obs))
    fp = int(np.count_nonzero(sim & ~obs))
    fn = int(np.count_nonzero(~sim & obs))
    tn = int(sim.size - tp - fp - fn)
    return Confusion(tp, fp, fn, tn)


def _ratio(num: float, den: float) -> float:
    return num / den if den > 0 else math.nan


def tversky(c: Confusion, alpha: float = 0.5, beta: float = 0.5) -> float:
    """``TP / (TP + alpha FP + beta FN)``; NaN when both areas are empty."""
    return _ratio(c.tp, c.tp + alpha * c.fp + beta * c.fn)


def csi(c: Confusion) -> float:
    """Critical success index (threat score, Jaccard): ``TP / (TP + FP + FN)``."""
    return _ratio(c.tp, c.tp + c.fp + c.fn)


def f1(c: Confusion) -> float:
    """F1 (Dice): ``2 TP / (2 TP + FP + FN)``."""
    return _ratio(2 * c.tp, 2 * c.tp + c.fp + c.fn)


def auroc(values, obs, domain=None) -> float:
    """Area under the ROC curve of ``values`` (the peak field) as a score of ``obs`` over
    every threshold, on the domain's cells; NaN when ``obs`` is all True or all False
    there. Non-finite values count as the lowest (no flow)."""
    from sklearn.metrics import roc_auc_score

    values = np.asarray(values, dtype=float)
    obs = np.asarray(obs, dtype=bool)
    if domain is not None:
        domain = np.asarray(domain, dtype=bool)
        values, obs = values[domain], obs[domain]
    if obs.all() or not obs.any():
        return math.nan
    finite = np.isfinite(values)
    floor = float(values[finite].min()) - 1.0 if finite.any() else 0.0
    values = np.where(finite, values, floor)  # below every finite value: no flow
    return float(roc_auc_score(obs, values))


def area_scores(values, threshold: float, obs, domain=None, alpha: float = 0.5,
                beta: float = 0.5) -> dict:
    """Every area score of a peak field ``values`` above ``threshold`` against ``obs``:
    ``tp, fp, fn, tn, csi, f1, tversky, auroc``."""
    values = np.asarray(values, dtype=float)
    with np.errstate(invalid="ignore"):
        sim = np.nan_to_num(values, nan=-np.inf) >= threshold
    c = confusion(sim, obs, domain)
    return {"tp": c.tp, "fp": c.fp, "fn": c.fn, "tn": c.tn, "csi": csi(c), "f1": f1(c),
            "tversky": tversky(c, alpha, beta), "auroc": auroc(values, obs, domain)}


def runout_difference(s_sim: float, s_obs: float) -> float:
    """Signed runout difference along the path (m): > 0 when the run went farther."""
    return float(s_sim) - float(s_obs)


def rmse_union(h_sim, h_obs, threshold: float, domain=None) -> float:
    """RMSE of thickness over the cells where either field reaches ``threshold`` (NaN
    counts as 0: no deposit); NaN when that union is empty."""
    h_sim = np.nan_to_num(np.asarray(h_sim, dtype=float), nan=0.0)
    h_obs = np.nan_to_num(np.asarray(h_obs, dtype=float), nan=0.0)
    if domain is not None:
        domain = np.asarray(domain, dtype=bool)
        h_sim, h_obs = h_sim[domain], h_obs[domain]
    union = (h_sim >= threshold) | (h_obs >= threshold)
    if not union.any():
        return math.nan
    return float(np.sqrt(np.mean((h_sim[union] - h_obs[union]) ** 2)))


def misfit(discrepancies, errors, weights=None) -> float:
    """``sum_i w_i (d_i / sigma_i)^2``; NaN when any ``d_i`` is NaN (a missing score is
    missing, never zero)."""
    d = np.asarray(discrepancies, dtype=float)
    s = np.asarray(errors, dtype=float)
    w = np.ones_like(d) if weights is None else np.asarray(weights, dtype=float)
    if not np.isfinite(d).all():
        return math.nan
    return float(np.sum(w * (d / s) ** 2))


def log_likelihood(discrepancies, errors, weights=None) -> float:
    """Gaussian log-likelihood of independent errors: ``-misfit / 2 - sum_i log(sigma_i
    sqrt(2 pi))`` (weights temper each term)."""
    m = misfit(discrepancies, errors, weights)
    s = np.asarray(errors, dtype=float)
    w = np.ones_like(s) if weights is None else np.asarray(weights, dtype=float)
    return float(-0.5 * m - np.sum(w * np.log(s * math.sqrt(2.0 * math.pi))))
