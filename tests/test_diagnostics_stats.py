"""Agreement statistics and vote rules on hand-built rating sets with known answers: Gwet's
published worked example, the Fleiss (1971) example, the paper's own TL row, an all-unanimous
criterion, a skewed one where kappa and AC1 diverge, and NA gating through the aggregation."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from vabench.agent.records import EpisodeResult
from vabench.diagnostics import aggregate as agg
from vabench.diagnostics import stats
from vabench.diagnostics.episodes import EpisodeRef, RunIndex
from vabench.diagnostics.store import Judgment, current
from vabench.run_records import Record


def counts(rows, categories):
    """Items x categories counts from raw ratings (None = not rated)."""
    return np.array([[sum(r == c for r in row) for c in categories] for row in rows], float)


def test_gwet_ac1_matches_the_handbook_worked_example():
    # Gwet, Handbook of Inter-Rater Reliability (4th ed., 2014), p. 120: 4 raters, 12 units,
    # 5 categories, missing ratings; published p_a = 0.818, p_e = 0.190, AC1 = 0.775.
    ratings = [
        [1, 1, None, 1],
        [2, 2, 3, 2],
        [3, 3, 3, 3],
        [3, 3, 3, 3],
        [2, 2, 2, 2],
        [1, 2, 3, 4],
        [4, 4, 4, 4],
        [1, 1, 2, 1],
        [2, 2, 2, 2],
        [None, 5, 5, 5],
        [None, None, 1, 1],
        [None, None, 3, None],
    ]
    table = counts(ratings, [1, 2, 3, 4, 5])
    assert stats.percent_agreement(table) == pytest.approx(0.818, abs=5e-4)
    assert stats.gwet_ac1(table) == pytest.approx(0.7754, abs=5e-5)


def test_fleiss_kappa_matches_the_fleiss_1971_style_example():
    # The worked example of 10 subjects x 14 raters x 5 categories (kappa = 0.210).
    table = np.array(
        [
            [0, 0, 0, 0, 14],
            [0, 2, 6, 4, 2],
            [0, 0, 3, 5, 6],
            [0, 3, 9, 2, 0],
            [2, 2, 8, 1, 1],
            [7, 7, 0, 0, 0],
            [3, 2, 6, 3, 0],
            [2, 5, 3, 2, 2],
            [6, 5, 2, 1, 0],
            [0, 2, 2, 3, 7],
        ]
    )
    assert stats.fleiss_kappa(table) == pytest.approx(0.210, abs=5e-4)


def test_the_papers_tl_row_is_reproduced():
    # Table "annotation-agreement", TL: n = 3,360, unanimity 97.41 %, positive rate 0.974,
    # kappa 0.723, AC1 0.982. The only composition of 2-1 splits consistent with n, unanimity
    # and positive rate: 3,198 unanimous 1, 75 unanimous 0, 75 splits 2-1, 12 splits 1-2.
    votes = [(1, 1, 1)] * 3198 + [(0, 0, 0)] * 75 + [(1, 1, 0)] * 75 + [(1, 0, 0)] * 12
    table = stats.binary_table(votes)
    assert round(stats.unanimity(votes) * 100, 2) == 97.41
    assert round(sum(stats.vote(v) for v in votes) / len(votes), 3) == 0.974
    assert round(stats.fleiss_kappa(table), 3) == 0.723
    assert round(stats.gwet_ac1(table), 3) == 0.982


def test_all_unanimous():
    one_category = stats.binary_table([(1, 1, 1)] * 8)
    assert stats.unanimity([(1, 1, 1)] * 8) == 1.0
    assert stats.fleiss_kappa(one_category) is None  # chance agreement 1: undefined
    assert stats.gwet_ac1(one_category) == pytest.approx(1.0)
    both = stats.binary_table([(1, 1, 1)] * 6 + [(0, 0, 0)] * 2)
    assert stats.fleiss_kappa(both) == pytest.approx(1.0)
    assert stats.gwet_ac1(both) == pytest.approx(1.0)


def test_skewed_criterion_kappa_and_ac1_diverge():
    # 18 unanimous positives and two 2-1 splits: 90 % unanimity, yet kappa is below zero
    # while AC1 stays high. Exact values from the definitions, in fractions:
    votes = [(1, 1, 1)] * 18 + [(1, 1, 0)] * 2
    pa = (18 + 2 * Fraction(1, 3)) / 20
    pi1 = (18 + 2 * Fraction(2, 3)) / 20
    pi0 = 1 - pi1
    kappa = (pa - (pi0**2 + pi1**2)) / (1 - (pi0**2 + pi1**2))
    ac1 = (pa - 2 * pi0 * pi1) / (1 - 2 * pi0 * pi1)
    table = stats.binary_table(votes)
    assert stats.fleiss_kappa(table) == pytest.approx(float(kappa), abs=1e-12)
    assert stats.gwet_ac1(table) == pytest.approx(float(ac1), abs=1e-12)
    assert stats.fleiss_kappa(table) < 0 < 0.9 < stats.gwet_ac1(table)


def test_vote_rules():
    assert [stats.vote((1, 1, 0), r) for r in stats.VOTE_RULES] == [0, 1, 1]
    assert [stats.vote((1, 0, 0), r) for r in stats.VOTE_RULES] == [0, 0, 1]
    assert [stats.vote((1, 1, 1), r) for r in stats.VOTE_RULES] == [1, 1, 1]
    assert stats.vote((1, 0), "majority") == 0  # a tie is not a majority
    with pytest.raises(ValueError, match="unknown vote rule"):
        stats.vote((1,), "loose")


def test_rank_correlations():
    assert stats.rank_correlations([0.1, 0.5, 0.9], [0.2, 0.4, 0.8]) == (1.0, 1.0)
    rho, tau = stats.rank_correlations([0.1, 0.5, 0.9], [0.9, 0.5, 0.1])
    assert (rho, tau) == (-1.0, -1.0)
    assert stats.rank_correlations([0.5], [0.5]) == (None, None)
    assert stats.rank_correlations([0.5, 0.5], [0.1, 0.2]) == (None, None)


# -- aggregation over a hand-built run --------------------------------------------------------


def fake_index(episodes):
    """A RunIndex over (id, model, track, task) without a run directory."""
    refs = {}
    for i, (eid, model, track, task) in enumerate(episodes):
        result = EpisodeResult(
            task=task,
            seed=1000 + i,
            model=model,
            protocol="active",
            run=1,
            status="failure",
            success=False,
            stop_reason="budget_exhausted",
            step_budget=5,
            n_checkpoints=2,
        )
        refs[eid] = EpisodeRef(eid, track, Record(track, result, i + 1))
    return RunIndex(None, refs)  # type: ignore[arg-type]


def judgments(table):
    """{(episode, annotator): {item: value}} -> judgments in force."""
    out, t = [], 0.0
    for (episode, annotator), items in table.items():
        for item, value in items.items():
            t += 1
            out.append(Judgment(annotator, episode, item, value, t))
    return current(out)


ALWAYS = {"gate_ambiguity": 1, "TL": 1, "AE": 1, "SR": 1, "MS": 1, "MP": 1, "FG": 0}


def test_na_gating_excludes_error_free_episodes_from_denominators():
    index = fake_index(
        [("e1", "m", "active", "t"), ("e2", "m", "active", "t"), ("e3", "m", "active", "t")]
    )
    state = judgments(
        {
            # e1: one annotator sees an error (and judges ED/OC/PF), the majority does not -> NA
            ("e1", "a"): {**ALWAYS, "gate_error": 1, "ED": 1, "OC": 1, "PF": 1},
            ("e1", "b"): {**ALWAYS, "gate_error": 0},
            ("e1", "c"): {**ALWAYS, "gate_error": 0},
            # e2: majority error -> ED 2 of 3 positive (1), OC 1 of 3 (0), PF 3 of 3 (1)
            ("e2", "a"): {**ALWAYS, "gate_error": 1, "ED": 1, "OC": 1, "PF": 1},
            ("e2", "b"): {**ALWAYS, "gate_error": 1, "ED": 1, "OC": 0, "PF": 1},
            ("e2", "c"): {**ALWAYS, "gate_error": 0, "ED": 0, "OC": 0, "PF": 1},
            # e3: no error at all
            ("e3", "a"): {**ALWAYS, "gate_error": 0, "FG": 1},
            ("e3", "b"): {**ALWAYS, "gate_error": 0, "FG": 1},
            ("e3", "c"): {**ALWAYS, "gate_error": 0},
        }
    )
    c = agg.collect(index, state)
    assert c.gates["e1"]["gate_error"] == 0 and c.gates["e2"]["gate_error"] == 1
    assert c.count("na", "ED") == 2 and len(c.scored("ED")) == 1
    assert c.dropped == 3  # annotator a's ED/OC/PF on e1
    scores = agg.criterion_scores(c, index)[("m", "active")]
    assert (scores["ED"].value, scores["ED"].n) == (1.0, 1)
    assert (scores["OC"].value, scores["OC"].n) == (0.0, 1)
    assert (scores["PF"].value, scores["PF"].n) == (1.0, 1)
    assert scores["TL"].n == 3 and scores["FG"].value == pytest.approx(1 / 3)  # e3 only
    modules = agg.module_scores(scores)
    assert modules["ER"].value == pytest.approx(2 / 3) and modules["ER"].n == 3
    assert modules["RM"].value == pytest.approx((1 + 1 + 1 / 3) / 3)
    rows, left_out = agg.agreement(c)
    by = {r.label: r for r in rows}
    assert by["ED"].n == 1 and by["TL"].n == 3 and left_out == 0
    assert by["All criteria"].n == sum(r.n for r in rows[:9])


def test_a_criterion_without_applicable_episodes_is_na_not_zero():
    index = fake_index([("e1", "m", "active", "t")])
    state = judgments({(("e1", a)): {**ALWAYS, "gate_error": 0} for a in "abc"})
    scores = agg.criterion_scores(agg.collect(index, state), index)[("m", "active")]
    assert scores["ED"].value is None and scores["ED"].n == 0
    er = agg.module_scores(scores)["ER"]
    assert er.value is None and er.n == 0


def test_sensitivity_rankings_and_correlations():
    # Two conditions; under majority and permissive m1 leads, under strict m2 does.
    index = fake_index([("x", "m1", "active", "t"), ("y", "m2", "active", "t")])
    criteria = ["TL", "SR", "MS", "MP", "FG"]
    state = judgments(
        {
            **{
                ("x", a): {
                    "gate_error": 0,
                    "gate_ambiguity": 0,
                    **{k: int(a != "c") for k in criteria},
                }
                for a in "abc"
            },
            **{
                ("y", a): {
                    "gate_error": 0,
                    "gate_ambiguity": 0,
                    **{k: int(k in ("TL", "SR")) for k in criteria},
                }
                for a in "abc"
            },
        }
    )
    s = agg.sensitivity(agg.collect(index, state), index)
    assert s.means[("m1", "active")] == {"strict": 0.0, "majority": 1.0, "permissive": 1.0}
    assert s.means[("m2", "active")]["strict"] == pytest.approx(0.4)
    assert s.rankings["strict"][0] == ("m2", "active")
    assert s.rankings["majority"][0] == ("m1", "active")
    corr = {(a, b): (rho, tau) for a, b, rho, tau in s.correlations}
    assert corr[("strict", "majority")] == pytest.approx((-1.0, -1.0))
    assert corr[("majority", "permissive")] == pytest.approx((1.0, 1.0))
