"""`gc_freeze.freeze`: what a process built to keep leaves the collector's full collections,
what it makes afterwards is still collected, and VABENCH_GC_FREEZE=0 turns it off. Each case
runs in a fresh interpreter (freezing pytest's own heap would change every later test's
collector)."""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys

PROBE = r"""
import gc, json
from vabench import gc_freeze

kept = [[i] for i in range(200_000)]  # what a process builds to keep
gc_freeze.own_process()
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
        env={**os.environ, "VABENCH_GC_FREEZE": "1", **env},
    )
    return json.loads(out.stdout)


def test_what_was_built_is_frozen_and_later_cycles_are_still_collected():
    got = _probe()
    assert got["frozen"] == got["count"] >= 200_000
    assert got["tracked_before"] < 10_000  # a full collection walks what came after, only
    assert got["collected"] >= 2  # the two nodes of the cycle (and their dicts)


def test_a_process_not_our_own_is_never_frozen():
    """The sweep's code also runs inside other programs (this test session runs sweeps in its
    own process): only a process that says it is vabench's own worker freezes."""
    from vabench import gc_freeze

    assert gc_freeze.freeze("a test's sweep") == 0
    assert gc.get_freeze_count() == 0


def test_turned_off_nothing_is_frozen():
    got = _probe(VABENCH_GC_FREEZE="0")
    assert got["frozen"] == got["count"] == 0
    assert got["tracked_before"] >= 200_000
    assert got["collected"] >= 2


TASK_BATCH_PROBE = r"""
import asyncio, gc, json, weakref
from vabench import gc_freeze
from vabench.agent.services import task_services
from vabench.tasks import get_task

class Pool:  # a renderer that reads its states from the physics batch, as Warp's does
    def shares(self, batch):
        return True

async def main():
    gc_freeze.own_process()
    async with task_services(get_task("probe_cube"), 2, None, Pool(), backend="c") as svc:
        gc_freeze.freeze("the probe's task batch")  # as the sweep does once a batch is built
        kept = (svc.sim, svc.sim.batch, svc.sim.batch.batch, svc.render)
        refs = [weakref.ref(o) for o in kept]
        del kept
    del svc
    gc.collect()
    return [type(r()).__name__ for r in refs if r() is not None]

print(json.dumps(asyncio.run(main())))
"""


def test_a_task_batch_frozen_at_its_build_is_freed_when_its_task_ends():
    """The sweep freezes each task batch once built (`runner._run_task`); whatever of it is in
    a reference cycle could then never be collected, so its services must break their cycles
    when they close: the batch and its services go with the task."""
    out = subprocess.run(
        [sys.executable, "-c", TASK_BATCH_PROBE],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "VABENCH_GC_FREEZE": "1"},
    )
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []
