"""The nine trajectory-level criteria of the paper (appendix "Trajectory-based capability
diagnostics"), their modules, the two applicability gates, and the rubric text annotators and
judges read.

Annotation of one episode has two stages:

1. Applicability gates. `gate_error` (g_e: the episode contains an observable execution error)
   activates ED, OC and PF; `gate_ambiguity` (the observation left a task-relevant spatial or
   geometric fact undetermined) activates AE. Each annotator votes 0 or 1; the episode's gate
   is the majority of the votes (eq. "error-applicability-vote").
2. A binary judgment (1 = positive behavioural evidence, 0 = not demonstrated) for every
   activated criterion. TL, SR, MS, MP and FG apply to every episode.

An episode whose majority gate is 0 is NA for the gated criteria and leaves their
denominators. The rubric text is written for the judge prompt too, so it avoids the
vocabulary of evaluator-only state (`vabench.agent.visibility.EVALUATOR_ONLY_TERMS`); a test
checks that.
"""

from __future__ import annotations

from dataclasses import dataclass

RUBRIC_VERSION = "va-bench-rubric-1"
"""Written into every judgment: a judgment made against another rubric text can be told apart."""


@dataclass(frozen=True)
class Criterion:
    code: str
    module: str
    name: str
    summary: str
    """One line shown beside the buttons."""
    rubric: str
    """The full positive and negative evidence rules."""
    gate: str | None = None
    """The gate that activates it; None: it applies to every episode."""


@dataclass(frozen=True)
class Gate:
    code: str
    name: str
    question: str
    rubric: str
    activates: tuple[str, ...]


MODULES: dict[str, str] = {
    "SPU": "Spatial perception and understanding",
    "RM": "Robot manipulation",
    "ER": "Error recovery",
}

GATES: dict[str, Gate] = {
    g.code: g
    for g in (
        Gate(
            "gate_error",
            "Observable execution error (g_e)",
            "Does the episode contain an observable execution error?",
            "An error is observable in the trajectory: a missed grasp, a dropped or knocked "
            "object, an unstable placement, a planner rejection or an invalid action, a "
            "motion that visibly goes wrong. If no error occurs, ED, OC and PF are NA for "
            "this episode and leave their denominators.",
            ("ED", "OC", "PF"),
        ),
        Gate(
            "gate_ambiguity",
            "Assessable ambiguity (AE gate)",
            "Is there a task-relevant ambiguity the current view cannot resolve?",
            "Some spatial or geometric fact needed by the next action (object orientation, "
            "depth, the contact region, the relative pose of two arms, the visibility of a "
            "container opening) is underdetermined in the view the model has. Without such "
            "an ambiguity, AE is NA.",
            ("AE",),
        ),
    )
}

CRITERIA: dict[str, Criterion] = {
    c.code: c
    for c in (
        Criterion(
            "TL",
            "SPU",
            "Target perception and localization",
            "Identifies the task-relevant object and localizes it well enough to guide motion.",
            "Positive: end-effector motion directed toward the correct object, camera actions "
            "that keep it in view, later operations organized around it. Negative needs clear "
            "contrary evidence: sustained motion toward an unrelated object or region, grasping "
            "a distractor, repeatedly operating far from the object. One exploratory motion "
            "is not a localization failure.",
        ),
        Criterion(
            "AE",
            "SPU",
            "Informative active exploration",
            "Acquires and uses visual evidence that resolves the ambiguity.",
            "Positive only when all three hold: (i) the model selects a semantic view or camera "
            "motion in response to the ambiguity; (ii) the new observation exposes information "
            "that reduces it; (iii) a later action or estimate is consistent with the new "
            "observation. A redundant or irrelevant view, or a view whose observation does not "
            "reduce the ambiguity, is 0; visiting an informative view and switching away "
            "without using it is 0. Uncertainty about whether an action worked belongs to ED.",
            gate="gate_ambiguity",
        ),
        Criterion(
            "SR",
            "SPU",
            "Robot-object spatial relations",
            "Interprets relative height, distance, direction and alignment correctly.",
            "Positive: successive translations or rotations reduce the visible gripper-object "
            "offset and contact, grasp or release start at a geometrically plausible state. "
            "Negative: closing while visibly above or beside the object, descending at a wrong "
            "lateral position, confusing image directions with world axes, declaring alignment "
            "while a large separation remains.",
        ),
        Criterion(
            "MS",
            "RM",
            "Manipulation-semantics understanding",
            "Uses the control commands purposefully to produce the intended physical effect.",
            "Positive: purposeful world-axis translation, local-axis rotation, aperture or "
            "dual-arm commands. Negative: meaningless rotations, uncontrolled large motions, "
            "repeated open/close without a contact opportunity, actions unrelated to the task. "
            "Numerical imprecision alone belongs to SR.",
        ),
        Criterion(
            "MP",
            "RM",
            "Goal-directed manipulation planning",
            "Builds a coherent metric action sequence from the current state to the goal.",
            "Positive: an appropriate order of approach, alignment, grasp or contact, lift or "
            "actuation, transport, placement, release and retreat, using only the phases the "
            "task needs, each reducing the relevant spatial error. Negative: large purposeless "
            "excursions, repeated movement in unrelated regions, an approach direction "
            "incompatible with the intended contact, phases that cannot lead to the goal.",
        ),
        Criterion(
            "FG",
            "RM",
            "Fine-grained pre-contact analysis",
            "Analyses fingertip placement, orientation, aperture and height before contact.",
            "Positive: a task-specific assessment of fingertip placement, gripper orientation "
            "and aperture, contact location, approach or placement height, or relative arm "
            "geometry, reflected in pre-contact decisions and actions. A generic 'be careful' "
            "without matching behaviour is insufficient. Every episode is scored; no such "
            "analysis, including never reaching an opportunity for it, is 0. A later miss does "
            "not negate it, and completing the task alone does not establish it.",
        ),
        Criterion(
            "ED",
            "ER",
            "Error detection",
            "After the error, stops treating the failed action as successful.",
            "Positive: after an observable error the agent stops the current sequence, obtains "
            "another view, rechecks the grasp, or begins a materially different adjustment. "
            "Negative: continuing the same plan while ignoring a visible miss, a dropped "
            "object, an unstable placement or repeated planner rejections.",
            gate="gate_error",
        ),
        Criterion(
            "OC",
            "ER",
            "Online correction",
            "Corrects a developing deviation before it becomes an explicit failure.",
            "Positive only when the agent notices and corrects a developing spatial deviation "
            "before it becomes an operation failure: adjusting lateral alignment or gripper "
            "orientation before closing, re-centring an object during transport, restoring "
            "bimanual levelness before the payload slips. If the error progresses into "
            "failure, or no timely correction is shown, OC is 0.",
            gate="gate_error",
        ),
        Criterion(
            "PF",
            "ER",
            "Post-failure adjustment",
            "After an explicit failure, re-evaluates and retries with a material change.",
            "Positive: after an explicit failure the agent re-evaluates the new state and "
            "changes its observation strategy, geometric hypothesis, approach or numerical "
            "parameters before retrying; the retry need not succeed. Negative: repeating the "
            "failed action without a meaningful change, persisting with a stale plan, or "
            "stopping despite a recoverable state. An error without any adjustment is 0.",
            gate="gate_error",
        ),
    )
}

CRITERION_CODES: tuple[str, ...] = tuple(CRITERIA)
GATE_CODES: tuple[str, ...] = tuple(GATES)
ITEMS: tuple[str, ...] = GATE_CODES + CRITERION_CODES
"""Everything an annotator records for one episode: the two gates, then the nine criteria."""

MODULE_CRITERIA: dict[str, tuple[str, ...]] = {
    m: tuple(c.code for c in CRITERIA.values() if c.module == m) for m in MODULES
}


def gate_of(item: str) -> str | None:
    """The gate that activates `item` (None for gates and always-applicable criteria)."""
    criterion = CRITERIA.get(item)
    return None if criterion is None else criterion.gate


def item_title(item: str) -> str:
    if item in CRITERIA:
        return f"{item}: {CRITERIA[item].name}"
    return GATES[item].name
