"""From judgments to the paper's numbers: episode labels, criterion and module percentages,
the agreement table and the vote-rule sensitivity.

Per annotated episode and criterion (appendix "Aggregation"):
- a gated criterion (ED, OC, PF by the error gate; AE by the ambiguity gate) is NA when the
  majority of the gate votes is 0, and is then left out of its denominator; judgments recorded
  for it anyway (an annotator who saw an error the majority did not) are counted as dropped;
- otherwise its judgments are the votes; the label is their vote under a rule (majority by
  default; strict and permissive for the sensitivity analysis). The gates themselves are
  always decided by majority, as the paper fixes them before stage two;
- an item nobody has judged yet is missing: neither NA nor in a denominator, and counted so a
  partial annotation is visible.

A criterion's score for a group (a condition = model x track, or a condition's task) is the
share of positive labels among its applicable episodes; a module's score is the equal-weight
mean of its criteria's scores. A criterion with no applicable episode is NA (None), never 0,
and a module mean over fewer than its three criteria says so (`Score.of`).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

from vabench.diagnostics import stats
from vabench.diagnostics.criteria import CRITERIA, CRITERION_CODES, GATE_CODES, MODULE_CRITERIA
from vabench.diagnostics.episodes import EpisodeRef, RunIndex
from vabench.diagnostics.store import Judgment, Key, majority

ItemStatus = Literal["scored", "na", "missing"]


@dataclass(frozen=True)
class EpisodeItem:
    episode: str
    criterion: str
    status: ItemStatus
    votes: tuple[int, ...] = ()
    annotators: tuple[str, ...] = ()

    def label(self, rule: str = "majority") -> int:
        return stats.vote(self.votes, rule)


@dataclass
class Collected:
    items: list[EpisodeItem] = field(default_factory=list)
    gates: dict[str, dict[str, int | None]] = field(default_factory=dict)
    """episode -> gate -> majority (None: nobody voted)."""
    annotators: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """episode -> who judged anything on it."""
    dropped: int = 0
    """Judgments of gated criteria on episodes whose majority gate is 0."""

    def scored(self, criterion: str | None = None) -> list[EpisodeItem]:
        return [
            i
            for i in self.items
            if i.status == "scored" and (criterion is None or i.criterion == criterion)
        ]

    def count(self, status: ItemStatus, criterion: str) -> int:
        return sum(i.status == status and i.criterion == criterion for i in self.items)


Votes = dict[str, dict[str, dict[str, int]]]
"""episode -> item -> annotator -> 0/1: the judgments in force, as `collect_votes` reads them."""


def votes_of(state: Mapping[Key, Judgment]) -> Votes:
    by_episode: Votes = {}
    for (episode, annotator, item), j in state.items():
        if j.value is not None:
            by_episode.setdefault(episode, {}).setdefault(item, {})[annotator] = j.value
    return by_episode


def collect(index: RunIndex, state: Mapping[Key, Judgment]) -> Collected:
    """Every annotated scored episode's gates and criterion items."""
    votes = {
        episode: judged
        for episode, judged in votes_of(state).items()
        if (ref := index.episodes.get(episode)) is not None and ref.result.scored
    }
    return collect_votes(votes)


def collect_votes(votes: Votes, gates_optional: bool = False) -> Collected:
    """Gates and criterion items of every episode of `votes`.

    A run's annotations always hold the gate before a gated criterion (the store refuses a
    criterion its gate does not activate), so there a gated criterion without gate votes is
    missing. A votes file from elsewhere may hold no gate rows at all (`gates_optional`): then
    a gated criterion judged on an episode with no vote on its gate counts as applicable, as
    the annotators who judged it found it so; where gate votes exist, their majority decides
    as always, and an NA criterion is one nobody judged."""
    out = Collected()
    for episode, judged in votes.items():
        out.annotators[episode] = tuple(sorted({a for v in judged.values() for a in v}))
        gates = {g: majority(judged.get(g, {}).values()) for g in GATE_CODES}
        out.gates[episode] = gates
        for code in CRITERION_CODES:
            votes_on = judged.get(code, {})
            gate = CRITERIA[code].gate
            decided = None if gate is None else gates[gate]
            if decided == 0:
                out.dropped += len(votes_on)
                out.items.append(EpisodeItem(episode, code, "na"))
            elif not votes_on or (gate is not None and decided is None and not gates_optional):
                out.items.append(EpisodeItem(episode, code, "missing"))
            else:
                names = tuple(sorted(votes_on))
                out.items.append(
                    EpisodeItem(episode, code, "scored", tuple(votes_on[a] for a in names), names)
                )
    return out


# -- scores -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Score:
    value: float | None
    """A share in [0, 1]; None: NA (no applicable episode)."""
    n: int = 0
    """Applicable episodes (criteria) or criteria with a score (modules)."""
    of: int = 0
    """Modules: how many criteria the module has."""


Group = tuple[str, ...]


def condition_of(ref: EpisodeRef) -> Group:
    return (ref.result.model, ref.track)


def task_group_of(ref: EpisodeRef) -> Group:
    return (ref.result.model, ref.track, ref.result.task)


def criterion_scores(
    collected: Collected,
    index: RunIndex,
    group_of: Callable[[EpisodeRef], Group] = condition_of,
    rule: str = "majority",
) -> dict[Group, dict[str, Score]]:
    tallies: dict[Group, Counter] = {}
    for item in collected.scored():
        group = group_of(index.episodes[item.episode])
        tally = tallies.setdefault(group, Counter())
        tally[(item.criterion, "n")] += 1
        tally[(item.criterion, "pos")] += item.label(rule)
    for episode in collected.gates:  # groups whose episodes are all NA still get a row
        tallies.setdefault(group_of(index.episodes[episode]), Counter())
    out: dict[Group, dict[str, Score]] = {}
    for group in sorted(tallies):
        t = tallies[group]
        out[group] = {
            c: Score(t[(c, "pos")] / t[(c, "n")] if t[(c, "n")] else None, t[(c, "n")])
            for c in CRITERION_CODES
        }
    return out


def module_scores(scores: Mapping[str, Score]) -> dict[str, Score]:
    out = {}
    for module, codes in MODULE_CRITERIA.items():
        values = [v for c in codes if (v := scores[c].value) is not None]
        mean = sum(values) / len(values) if values else None
        out[module] = Score(mean, len(values), len(codes))
    return out


def mean_over_criteria(scores: Mapping[str, Score]) -> float | None:
    values = [s.value for s in scores.values() if s.value is not None]
    return sum(values) / len(values) if values else None


# -- agreement --------------------------------------------------------------------------------


@dataclass(frozen=True)
class AgreementRow:
    module: str
    label: str
    n: int
    unanimity: float | None
    positive_rate: float | None
    kappa: float | None
    ac1: float | None
    kappa_note: str = ""


def raters_of(collected: Collected) -> int | None:
    """The usual number of judgments per item (the paper's 3): the most common count."""
    counts = Counter(len(i.votes) for i in collected.scored())
    if not counts:
        return None
    return max(counts, key=lambda k: (counts[k], k))


def agreement_row(module: str, label: str, items: Sequence[EpisodeItem]) -> AgreementRow:
    if not items:
        return AgreementRow(module, label, 0, None, None, None, None)
    table = stats.binary_table([i.votes for i in items])
    kappa, note = None, ""
    try:
        kappa = stats.fleiss_kappa(table)
        if kappa is None:
            note = "undefined: every judgment in one category"
    except stats.MissingDependency as err:
        note = str(err)
    return AgreementRow(
        module,
        label,
        len(items),
        stats.unanimity([i.votes for i in items]),
        sum(i.label() for i in items) / len(items),
        kappa,
        stats.gwet_ac1(table),
        note,
    )


def agreement(collected: Collected, raters: int | None = None) -> tuple[list[AgreementRow], int]:
    """The paper's agreement table over the items judged by exactly `raters` annotators
    (default: the usual count), per criterion, then all criteria and all but FG; and how many
    scored items were left out for having another number of judgments."""
    raters = raters or raters_of(collected)
    items = [i for i in collected.scored() if len(i.votes) == raters and raters and raters >= 2]
    left_out = len(collected.scored()) - len(items)
    rows = [
        agreement_row(CRITERIA[c].module, c, [i for i in items if i.criterion == c])
        for c in CRITERION_CODES
    ]
    rows.append(agreement_row("", "All criteria", items))
    rows.append(agreement_row("", "All except FG", [i for i in items if i.criterion != "FG"]))
    return rows, left_out


# -- vote-rule sensitivity --------------------------------------------------------------------


@dataclass
class Sensitivity:
    means: dict[Group, dict[str, float | None]]
    """condition -> rule -> mean over the nine criteria (of those with a score)."""
    rankings: dict[str, list[Group]]
    correlations: list[tuple[str, str, float | None, float | None]]
    """(rule a, rule b, Spearman rho, Kendall tau) of the conditions' means."""
    note: str = ""
    """Why the correlations are missing, when a package is."""


def _by_mean(
    means: Mapping[Group, Mapping[str, float | None]], rule: str
) -> Callable[[Group], tuple[float, Group]]:
    """Sort key: best mean first, ties by name."""
    return lambda g: (-(means[g][rule] or 0.0), g)


def sensitivity(collected: Collected, index: RunIndex) -> Sensitivity:
    per_rule = {
        rule: criterion_scores(collected, index, condition_of, rule) for rule in stats.VOTE_RULES
    }
    groups = sorted(per_rule["majority"])
    means = {g: {r: mean_over_criteria(per_rule[r][g]) for r in stats.VOTE_RULES} for g in groups}
    ranked = [g for g in groups if all(means[g][r] is not None for r in stats.VOTE_RULES)]
    rankings = {r: sorted(ranked, key=_by_mean(means, r)) for r in stats.VOTE_RULES}
    correlations = []
    note = ""
    for a, b in (("strict", "majority"), ("majority", "permissive"), ("strict", "permissive")):
        try:
            rho, tau = stats.rank_correlations(
                [means[g][a] or 0.0 for g in ranked], [means[g][b] or 0.0 for g in ranked]
            )
        except stats.MissingDependency as err:  # the report still renders without scipy
            rho, tau, note = None, None, str(err)
        correlations.append((a, b, rho, tau))
    return Sensitivity(means, rankings, correlations, note)
