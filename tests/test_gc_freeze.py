"""`gc_freeze.freeze`: what a process built to keep leaves the collector's full collections,
what it makes afterwards is still collected, and VABENCH_GC_FREEZE=0 turns it off. Each case
runs in a fresh interpreter (freezing pytest's own heap would change every later test's
collector)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

PROBE = r"""
import gc, json
from vabench import gc_freeze

kept = [[i] for i in range(200_000)]  # what a process builds to keep
frozen = gc_freeze.freeze("the probe's build")
walked = []
gc.callbacks.append(lambda phase, info: phase == "stop" and walked.append(info["collected"]))

class Node:
    pass

a, b = Node(), Node()
a.other, b.other = b, a  # a cycle made after the freeze: garbage once dropped
del a, b
before = len(gc.get_objects())
gc.collect()
print(json.dumps({"frozen": frozen, "count": gc.get_freeze_count(),
                  "tracked_before": before, "collected": sum(walked)}))
"""


def _probe(**env: str) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", PROBE],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, **env},
    )
    return json.loads(out.stdout)


def test_what_was_built_is_frozen_and_later_cycles_are_still_collected():
    got = _probe()
    assert got["frozen"] == got["count"] >= 200_000
    assert got["tracked_before"] < 10_000  # a full collection walks what came after, only
    assert got["collected"] >= 2  # the two nodes of the cycle (and their dicts)


def test_turned_off_nothing_is_frozen():
    got = _probe(VABENCH_GC_FREEZE="0")
    assert got["frozen"] == got["count"] == 0
    assert got["tracked_before"] >= 200_000
    assert got["collected"] >= 2
