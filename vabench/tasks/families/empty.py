"""empty: the robot and the table, nothing to do.

Scene: both arms at home, no objects. Success: never. Used to exercise the simulator core and
the replay CLI without a task.
"""

from __future__ import annotations

from vabench.tasks.base import Task

TASK = Task(
    name="empty",
    instruction="Move the grippers freely; there is no task.",
    arms=("left", "right"),
    suite="dev",
)
