"""Agreement statistics and vote rules, on plain arrays.

A rating table has one row per item and one column per category; a cell counts the raters who
put that item in that category (for the diagnostics: columns 0 and 1, rows of three).

- Fleiss' kappa comes from statsmodels (`statsmodels.stats.inter_rater.fleiss_kappa`); it needs
  the same number of raters on every item and is undefined (None here) when every judgment
  falls in one category, where its chance term is 1.
- Gwet's AC1 (Gwet 2008, "Computing inter-rater reliability and its variance in the presence
  of high agreement") is written out below, in the general form that allows a different number
  of raters per item: percent agreement over the items with at least two ratings, chance
  agreement sum_k pi_k (1 - pi_k) / (q - 1) with pi_k the mean share of category k. Prevalence
  does not inflate its chance term, so near-ceiling criteria keep a high AC1 where kappa drops
  (the paper's TL row).

statsmodels and scipy are imported when first used, with a message naming the extra to
install: the report and the viewer work without them on runs that hold no annotations.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

VOTE_RULES: tuple[str, ...] = ("strict", "majority", "permissive")
"""strict: every judgment positive; majority: more than half (the paper's rule); permissive:
at least one."""


class MissingDependency(ImportError):
    pass


def _require(module: str, what: str) -> Any:
    try:
        return __import__(module, fromlist=["_"])
    except ImportError:
        raise MissingDependency(
            f"{what} needs {module.split('.')[0]}: pip install 'vabench[diagnostics]'"
        ) from None


def vote(values: Sequence[int], rule: str = "majority") -> int:
    """The episode label of one criterion from its judgments under a vote rule."""
    if not values:
        raise ValueError("no judgments to vote on")
    positives = sum(values)
    if rule == "majority":
        return int(2 * positives > len(values))
    if rule == "strict":
        return int(positives == len(values))
    if rule == "permissive":
        return int(positives > 0)
    raise ValueError(f"unknown vote rule {rule!r}; valid: {list(VOTE_RULES)}")


def binary_table(items: Sequence[Sequence[int]]) -> np.ndarray:
    """Rows [n0, n1] from each item's 0/1 judgments."""
    return np.array([[len(v) - sum(v), sum(v)] for v in items], dtype=float).reshape(-1, 2)


def percent_agreement(table: np.ndarray) -> float:
    """Mean pairwise agreement over the items rated at least twice (Gwet's p_a)."""
    table = np.asarray(table, float)
    r = table.sum(1)
    rated = r >= 2
    if not rated.any():
        raise ValueError("no item has two ratings")
    t, r = table[rated], r[rated]
    return float(np.mean((t * (t - 1)).sum(1) / (r * (r - 1))))


def gwet_ac1(table: np.ndarray) -> float:
    """Gwet's AC1 of a rating table (items x categories; rows may have different totals)."""
    table = np.asarray(table, float)
    q = table.shape[1]
    if q < 2:
        raise ValueError("AC1 needs at least two categories")
    r = table.sum(1)
    rated = table[r > 0] / r[r > 0, None]
    pi = rated.mean(0)
    pe = float((pi * (1 - pi)).sum() / (q - 1))
    pa = percent_agreement(table)
    return (pa - pe) / (1 - pe)


def fleiss_kappa(table: np.ndarray) -> float | None:
    """Fleiss' kappa (statsmodels); None when undefined (all judgments in one category)."""
    inter_rater = _require("statsmodels.stats.inter_rater", "Fleiss' kappa")
    table = np.asarray(table, float)
    totals = table.sum(1)
    if len(table) == 0 or totals.min() != totals.max() or totals[0] < 2:
        raise ValueError("Fleiss' kappa needs the same number (>= 2) of ratings on every item")
    marginal = table.sum(0) / table.sum()
    if math.isclose(float((marginal**2).sum()), 1.0):
        return None
    return float(inter_rater.fleiss_kappa(table, method="fleiss"))


def unanimity(items: Sequence[Sequence[int]]) -> float:
    return sum(len(set(v)) == 1 for v in items) / len(items)


def rank_correlations(a: Sequence[float], b: Sequence[float]) -> tuple[float | None, float | None]:
    """(Spearman rho, Kendall tau-b) of two score vectors; None where undefined (fewer than
    two conditions, or a constant vector)."""
    if len(a) != len(b):
        raise ValueError("score vectors differ in length")
    if len(a) < 2 or len(set(a)) < 2 or len(set(b)) < 2:
        return None, None
    scipy_stats = _require("scipy.stats", "rank correlations")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rho = scipy_stats.spearmanr(a, b).statistic
        tau = scipy_stats.kendalltau(a, b).statistic
    return (None if math.isnan(rho) else float(rho)), (None if math.isnan(tau) else float(tau))


def ranking(scores: dict[str, float]) -> list[str]:
    """Names from best to worst (ties by name, so the order is stable)."""
    return sorted(scores, key=lambda k: (-scores[k], k))
