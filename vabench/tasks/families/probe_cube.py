"""probe_cube: grasp_single_cube with a short settle, for probing the simulator core.

Same scene, predicate and expert as grasp_single_cube, but the reset settles for 50 steps only
(the core's tests need many resets). Not part of the benchmark suite.
"""

from __future__ import annotations

from dataclasses import replace

from vabench.tasks.families.grasp_single_cube import TASK as GRASP

TASK = replace(GRASP, name="probe_cube", settle_steps=50, observe_steps=200, suite="dev")
