"""Active vs passive camera protocol (paper, "Active evidence acquisition"), as pure functions
over the base evaluation's cells (`stats.task_cells`).

- Per family, success counts of both tracks and Δ = passive − active; the two-sided exact sign
  test over the non-tied families:
  p = min(1, 2 · P[X ≤ min(k, n − k)]), X ~ Bin(n, 1/2), n non-tied families, k of them worse
  under passive. Ties and the sign compare rates, which equal counts when totals match.
- A family whose episodes under one of the two tracks are all skipped (`stats.is_skipped`: the
  model stopped before its first step, which says nothing about the protocol) is left out of
  the sign test and gets no Δ (`FamilyPair.skipped_side` names the side); its counts are still
  shown, and the macro-averages still count those episodes as failures. With no family left to
  compare there is no sign test at all (`p_value` None).
- A passive run is paired with the active run of the same number; several common runs are
  also compared pooled.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction

from vabench.report.stats import Cell, skipped_side


@dataclass(frozen=True)
class FamilyPair:
    """One family under both tracks: counts and Δ = passive − active."""

    task: str
    active: int
    active_total: int
    passive: int
    passive_total: int
    active_skipped: int = 0
    passive_skipped: int = 0

    @property
    def delta(self) -> Fraction:
        """Passive minus active success rate."""
        return Fraction(self.passive, self.passive_total) - Fraction(self.active, self.active_total)

    @property
    def skipped_side(self) -> str | None:
        """The track(s) under which every episode of this family was skipped: then the pair
        compares nothing and stays out of the sign test."""
        return skipped_side(
            self.active_skipped == self.active_total, self.passive_skipped == self.passive_total
        )


@dataclass(frozen=True)
class TrackComparison:
    """Active vs passive for one model over the given runs (one run, or several pooled)."""

    model: str
    runs: tuple[int, ...]
    families: tuple[FamilyPair, ...]
    passive_worse: int
    passive_better: int
    ties: int
    p_value: Fraction | None
    """None when every family was left out (`skipped`): no test was made."""
    only_one_track: tuple[str, ...]
    """Families run under one of the two tracks only: left out of the comparison."""
    skipped: tuple[str, ...] = ()
    """Families whose episodes were all skipped under one track (or both): left out of the
    sign test, shown without a Δ."""

    @property
    def non_tied(self) -> int:
        return self.passive_worse + self.passive_better

    @property
    def compared(self) -> int:
        """Families in the sign test (non-tied and tied)."""
        return len(self.families) - len(self.skipped)


def sign_test(k: int, n: int) -> Fraction:
    """Two-sided exact sign test: min(1, 2 P[X <= min(k, n-k)]), X ~ Bin(n, 1/2); 1 if n = 0."""
    if not 0 <= k <= n:
        raise ValueError(f"sign_test needs 0 <= k <= n, got k={k}, n={n}")
    if n == 0:
        return Fraction(1)
    tail = sum(math.comb(n, i) for i in range(min(k, n - k) + 1))
    return min(Fraction(1), Fraction(2 * tail, 2**n))


def compare_tracks(
    cells: Sequence[Cell],
    model: str,
    runs: Sequence[int],
    active: str = "active",
    passive: str = "passive",
) -> TrackComparison:
    """Active vs passive for `model`, counts summed over `runs`, families in both tracks."""
    sums: dict[str, dict[str, list[int]]] = {active: {}, passive: {}}
    for c in cells:
        if c.model == model and c.run in runs and c.track in sums:
            s = sums[c.track].setdefault(c.task, [0, 0, 0])
            s[0] += c.successes
            s[1] += c.total
            s[2] += c.skipped
    both = sorted(set(sums[active]) & set(sums[passive]))
    one = sorted(set(sums[active]) ^ set(sums[passive]))
    pairs = []
    for t in both:
        (a, a_total, a_skipped), (p, p_total, p_skipped) = sums[active][t], sums[passive][t]
        pairs.append(FamilyPair(t, a, a_total, p, p_total, a_skipped, p_skipped))
    tested = [p for p in pairs if p.skipped_side is None]
    worse = sum(1 for p in tested if p.delta < 0)
    better = sum(1 for p in tested if p.delta > 0)
    return TrackComparison(
        model=model,
        runs=tuple(sorted(runs)),
        families=tuple(pairs),
        passive_worse=worse,
        passive_better=better,
        ties=len(tested) - worse - better,
        p_value=sign_test(worse, worse + better) if tested else None,
        only_one_track=tuple(one),
        skipped=tuple(p.task for p in pairs if p.skipped_side is not None),
    )


def track_comparisons(
    cells: Sequence[Cell], active: str = "active", passive: str = "passive"
) -> list[TrackComparison]:
    """For each model run under both tracks: one comparison per run present in both (matched
    run numbers, as the paper pairs a passive run with its active run), plus one over all those
    runs pooled when there are several."""
    runs: dict[tuple[str, str], set[int]] = defaultdict(set)
    for c in cells:
        runs[(c.model, c.track)].add(c.run)
    out = []
    for model in sorted({c.model for c in cells}):
        common = sorted(runs.get((model, active), set()) & runs.get((model, passive), set()))
        for run in common:
            out.append(compare_tracks(cells, model, [run], active, passive))
        if len(common) > 1:
            out.append(compare_tracks(cells, model, common, active, passive))
    return out


def in_order(pairs: Sequence[FamilyPair], order: Sequence[str]) -> list[FamilyPair]:
    """Families in `order` (the registry's: the paper's), unknown ones last by name."""
    rank = {t: i for i, t in enumerate(order)}
    return sorted(pairs, key=lambda p: (rank.get(p.task, len(rank)), p.task))
