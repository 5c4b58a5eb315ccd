"""The suites beyond the base evaluation, as pure functions over condition cells
(`conditions`) and scored records: controlled transfer and long-horizon composition.

- Controlled transfer (paper, tab:generalization-summary, tab:single-arm-generalization): a
  held-out task (suite "transfer") is paired with its base family under the same protocol and
  the same summary mode (falling back to "own"). Per run: the macro-average over the families
  with both sides scored in that run, leaving out a pair whose episodes on one side were all
  skipped (the model stopped before its first step: nothing was attempted, so Δ would measure
  that, not the transfer; such a family is listed with its counts and no Δ); across runs: mean
  and sample SD of the base, held-out and Δ = held-out − base macro-averages. Per family:
  counts pooled over those runs.
- Long-horizon composition: per (model, track, task) of suite "long_horizon" and run, objects
  placed = the sum of `progress` (k checkpoints = k objects) out of the sum of
  `n_checkpoints`, and strict success = successes / episodes.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from fractions import Fraction

from vabench.report.conditions import OWN, CondCell, TaskMeta
from vabench.report.stats import Spread, average, mean_sd, mean_sd_or_none, skipped_side
from vabench.run_records import Record, ReportError

# -- controlled transfer -------------------------------------------------------------------------


@dataclass(frozen=True)
class TransferFamily:
    heldout: str
    base: str
    base_mode: str
    base_successes: int
    base_total: int
    heldout_successes: int
    heldout_total: int
    base_skipped: int = 0
    heldout_skipped: int = 0

    @property
    def base_rate(self) -> Fraction:
        return Fraction(self.base_successes, self.base_total)

    @property
    def heldout_rate(self) -> Fraction:
        return Fraction(self.heldout_successes, self.heldout_total)

    @property
    def skipped_side(self) -> str | None:
        """ "base", "held-out" or "both" when every episode of that side was skipped (the
        model stopped before its first step): then Δ compares nothing."""
        return skipped_side(
            self.base_skipped == self.base_total,
            self.heldout_skipped == self.heldout_total,
            ("base", "held-out"),
        )

    @property
    def delta(self) -> Fraction | None:
        """Held-out minus base success rate; None when one side was all skipped."""
        return None if self.skipped_side else self.heldout_rate - self.base_rate


@dataclass(frozen=True)
class TransferComparison:
    """One model, protocol and summary mode: held-out variants against their base families."""

    model: str
    protocol: str
    mode: str
    runs: tuple[int, ...]
    families: tuple[TransferFamily, ...]
    base: Spread | None
    heldout: Spread | None
    delta: Spread | None
    """Run-level macro-averages across runs; delta's values are per-run held-out − base."""
    unmatched: tuple[str, ...]
    """Held-out tasks without a scored base-family run under the same protocol and run."""
    skipped: tuple[str, ...] = ()
    """Held-out tasks left out of the macro-averages in some run because every episode of
    one side (base or held-out) was skipped there."""


def transfer_comparisons(cells: Sequence[CondCell], meta: TaskMeta) -> list[TransferComparison]:
    by = {(c.model, c.protocol, c.mode, c.task, c.run): c for c in cells}
    conditions = sorted(
        {(c.model, c.protocol, c.mode) for c in cells if meta.suite.get(c.task) == "transfer"}
    )
    out = []
    for model, protocol, mode in conditions:
        held = [
            c
            for c in cells
            if (c.model, c.protocol, c.mode) == (model, protocol, mode)
            and meta.suite.get(c.task) == "transfer"
        ]
        per_run: dict[int, list[tuple[Fraction, Fraction]]] = defaultdict(list)
        pooled: dict[tuple[str, str, str], list[int]] = {}
        skipped: set[str] = set()
        for h in held:
            base = meta.base_family.get(h.task)
            if base is None:
                raise ReportError(
                    f"task {h.task!r}: suite 'transfer' but field 'base_family' is not set"
                )
            b = next(
                (
                    by[k]
                    for m in dict.fromkeys((mode, OWN))
                    if (k := (model, protocol, m, base, h.run)) in by
                ),
                None,
            )
            if b is None:
                continue
            if b.all_skipped or h.all_skipped:
                skipped.add(h.task)  # nothing attempted on one side: no pair for the macros
            else:
                per_run[h.run].append((b.rate, h.rate))
            p = pooled.setdefault((h.task, base, b.mode), [0, 0, 0, 0, 0, 0])
            p[0], p[1] = p[0] + b.successes, p[1] + b.total
            p[2], p[3] = p[2] + h.successes, p[3] + h.total
            p[4], p[5] = p[4] + b.skipped, p[5] + h.skipped
        runs = tuple(sorted(per_run))
        base_m = [average([b for b, _ in per_run[r]]) for r in runs]
        held_m = [average([h for _, h in per_run[r]]) for r in runs]
        matched = {task for task, _, _ in pooled}
        out.append(
            TransferComparison(
                model=model,
                protocol=protocol,
                mode=mode,
                runs=runs,
                families=tuple(
                    TransferFamily(t, b, m, *p) for (t, b, m), p in sorted(pooled.items())
                ),
                base=mean_sd_or_none(base_m),
                heldout=mean_sd_or_none(held_m),
                delta=mean_sd_or_none([h - b for b, h in zip(base_m, held_m, strict=True)]),
                unmatched=tuple(sorted({h.task for h in held} - matched)),
                skipped=tuple(sorted(skipped)),
            )
        )
    return out


# -- long-horizon composition --------------------------------------------------------------------


@dataclass(frozen=True)
class LongHorizonRun:
    run: int
    episodes: int
    placed: int
    possible: int
    successes: int

    @property
    def placed_rate(self) -> Fraction:
        return Fraction(self.placed, self.possible) if self.possible else Fraction(0)

    @property
    def success_rate(self) -> Fraction:
        return Fraction(self.successes, self.episodes)


@dataclass(frozen=True)
class LongHorizon:
    model: str
    track: str
    task: str
    runs: tuple[LongHorizonRun, ...]
    placed: Spread
    success: Spread


def long_horizon(records: Iterable[Record], meta: TaskMeta) -> list[LongHorizon]:
    sums: dict[tuple[str, str, str], dict[int, list[int]]] = defaultdict(dict)
    for rec in records:
        r = rec.result
        if not r.scored or meta.suite.get(r.task) != "long_horizon":
            continue
        s = sums[(r.model, rec.track, r.task)].setdefault(r.run, [0, 0, 0, 0])
        s[0] += 1
        s[1] += r.progress
        s[2] += r.n_checkpoints
        s[3] += int(r.success)
    out = []
    for (model, track, task), per_run in sorted(sums.items()):
        runs = tuple(LongHorizonRun(run, *per_run[run]) for run in sorted(per_run))
        out.append(
            LongHorizon(
                model,
                track,
                task,
                runs,
                mean_sd([r.placed_rate for r in runs]),
                mean_sd([r.success_rate for r in runs]),
            )
        )
    return out
