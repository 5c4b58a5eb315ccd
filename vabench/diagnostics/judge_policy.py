"""`rubric_judge`: the embedded server's stand-in for a judge model, so the judge runs without
keys or network (tests, smoke runs, a first look at the workflow).

It reads only the request (the transcript the judge sends, which holds model-visible fields
only), derives each label from simple trajectory rules (an invalid action or a planner
rejection is an observable error; a camera action followed by a robot action is exploration;
an action changed after a failure is a post-failure adjustment; ...), then flips each label
with probability `flip`, drawn from a generator seeded by the annotator line and the
transcript. Judges of one model therefore disagree now and then, deterministically, which
gives the agreement statistics something to measure. It is a stand-in, not a judge: its labels
say nothing about the behaviour beyond those rules.
"""

from __future__ import annotations

import hashlib
import random
import re
from dataclasses import dataclass, field

from vabench.diagnostics.criteria import CRITERION_CODES, GATE_CODES
from vabench.diagnostics.judge import JUDGE_MARK, STAGE_ONE, STAGE_TWO
from vabench.llm_pool.apis.base import IncomingRequest
from vabench.llm_pool.policies import PolicyError, fenced_json


@dataclass
class _Step:
    decision: str = ""
    label: str = ""
    failed: bool = False
    executed: bool = False


@dataclass
class _Trajectory:
    steps: list[_Step] = field(default_factory=list)
    rejected: int = 0
    verified_before_close: bool = False

    @classmethod
    def parse(cls, text: str) -> _Trajectory:
        t = cls()
        closed = False
        for line in text.splitlines():
            s = line.strip()
            if re.match(r"Step \d+ \(view", s):
                t.steps.append(_Step())
            elif not t.steps:
                continue
            elif s.startswith("decision: "):
                kind, _, label = s.removeprefix("decision: ").partition(" ")
                t.steps[-1].decision, t.steps[-1].label = kind, label.split(" (reason")[0]
                closed = closed or "close" in label
            elif s.startswith("executed: "):
                t.steps[-1].executed = True
                t.steps[-1].failed = "valid no" in s or "planner rejected" in s
            elif s.startswith("reply rejected"):
                t.rejected += 1
            elif s.startswith("tool geometry.verify") and not closed:
                t.verified_before_close = True
        return t


def _labels(t: _Trajectory) -> dict[str, int]:
    robot = [s for s in t.steps if s.decision == "robot"]
    kinds = [s.decision for s in t.steps]
    errors = [i for i, s in enumerate(t.steps) if s.failed]
    first_close = next((i for i, s in enumerate(t.steps) if "close" in s.label), len(t.steps))
    explored = any(k == "camera" and "robot" in kinds[i + 1 :] for i, k in enumerate(kinds))
    out = {
        "gate_error": int(bool(errors)),
        "gate_ambiguity": 1,  # the paper: every base episode had an assessable ambiguity
        "TL": int(any(s.executed and not s.failed and "move" in s.label for s in robot)),
        "AE": int(explored),
        "SR": int(len(robot) >= 2 and sum(s.failed for s in robot) < len(robot) / 2),
        "MS": int(t.rejected == 0),
        "MP": int(any("close" in s.label for s in robot[1:])),
        "FG": int(t.verified_before_close or "camera" in kinds[:first_close]),
        "ED": 0,
        "OC": 0,
        "PF": 0,
    }
    if errors:
        i = errors[0]
        failed, later = t.steps[i], t.steps[i + 1 :]
        nxt = later[0] if later else None
        out["ED"] = int(nxt is not None and (nxt.decision != "robot" or nxt.label != failed.label))
        out["OC"] = int(any(s.decision == "camera" for s in later[:2]))
        next_robot = next((s for s in later if s.decision == "robot"), None)
        out["PF"] = int(next_robot is not None and next_robot.label != failed.label)
    return out


class RubricJudge:
    def __init__(self, flip: float = 0.1):
        if not 0 <= flip <= 1:
            raise ValueError(f"flip must be in [0, 1], got {flip}")
        self.flip = flip

    async def respond(self, request: IncomingRequest) -> str:
        chat = request.chat
        if not (chat.system or "").startswith(JUDGE_MARK):
            raise PolicyError("rubric_judge answers judge requests only", status=400)
        first = chat.turns[0].text
        ask = chat.last_user_text
        if STAGE_TWO in ask:
            requested = re.search(r"Judge these criteria: ([A-Z, ]+)", ask)
            codes = [c.strip() for c in requested.group(1).split(",")] if requested else []
            codes = [c for c in codes if c in CRITERION_CODES]
        elif STAGE_ONE in ask:
            codes = list(GATE_CODES)
        else:
            raise PolicyError("rubric_judge: the request names no stage", status=400)
        labels = _labels(_Trajectory.parse(first))
        annotator = re.search(r"Annotator: (\S+)", first)
        seed = hashlib.sha256(f"{annotator.group(1) if annotator else ''}\n{first}".encode())
        rng = random.Random(int.from_bytes(seed.digest()[:8], "big"))
        flips = {code: rng.random() < self.flip for code in (*GATE_CODES, *CRITERION_CODES)}
        return fenced_json({c: labels[c] ^ int(flips[c]) for c in codes})
