"""What the held-out variants (suite "transfer", `<base>_heldout`) share. No TASK here.

A variant keeps its base family's instruction, arms, step budget, checkpoints, latches and
predicate, and reads its base's summary (FACTS: "Held-out variants reuse the base task's
summary"). Where it differs only in objects and ranges it is data over its base: `variant`
copies the base task's fields and replaces those it names (the base family's class reads them);
where a formula differs too, `variant` builds it from the variant's own subclass.

Seed streams: a variant draws its scene from its own stream, so that seed s of a variant is not
seed s of its base with other objects: the cube and place variants draw from
`default_rng([seed, salt])` with a salt of their own (`salted`), the bottle variants from
`skills_heldout_bottles.heldout_rng`.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks.base import ObjectPoses, Task, yaw_quat


def salted_rng(seed: int, salt: int) -> np.random.Generator:
    """A variant's random stream of a seed (not the base family's `default_rng(seed)`)."""
    return np.random.default_rng([seed, salt])


def salted(salt: int) -> Callable[[int], np.random.Generator]:
    """The seed stream `salted_rng(seed, salt)` of one variant (a `Task.seed_stream`)."""
    return functools.partial(salted_rng, salt=salt)


def variant(base: Task, name: str, cls: type[Task] | None = None, **changes: Any) -> Task:
    """The held-out variant `name` of `base`: the base task's fields with `changes`, in the
    transfer suite, reading the base's summary; an instance of `cls` (a subclass of the base's
    class where a formula differs) or else of the base's own class."""
    fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(base) if f.init}
    fields.update(changes, name=name, suite="transfer", base_family=base.name)
    return (cls or type(base))(**fields)


@dataclass(frozen=True)
class Distractors:
    """Objects standing around a variant's target: each box (name, file, half-height) rests on
    the table at `ring` (min, max) from the target's centre in a uniformly drawn direction, yaw
    in `yaw_deg`, at least `min_gap` from every other box (centre to centre). None by default:
    a base family with this field has no distractors."""

    boxes: tuple[tuple[str, str, float], ...] = ()
    ring: tuple[float, float] = (0.0, 0.0)
    min_gap: float = 0.0
    yaw_deg: tuple[float, float] = (0.0, 0.0)

    @property
    def objects(self) -> tuple[tuple[str, str], ...]:
        """(name, file) of every box, as a task's `objects`."""
        return tuple((name, file) for name, file, _ in self.boxes)

    def sample(self, rng: np.random.Generator, centre: np.ndarray) -> ObjectPoses:
        placed: ObjectPoses = {}
        for name, _, half_h in self.boxes:
            for _ in range(1000):
                r, phi = rng.uniform(*self.ring), rng.uniform(-np.pi, np.pi)
                xy = centre[:2] + r * np.array([np.cos(phi), np.sin(phi)])
                if all(np.linalg.norm(xy - p[:2]) >= self.min_gap for p, _ in placed.values()):
                    break
            else:  # pragma: no cover - the variant's ring has room for its boxes
                raise RuntimeError("no room for a distractor")
            yaw = np.radians(rng.uniform(*self.yaw_deg))
            placed[name] = (np.r_[xy, rc.TABLE_Z + half_h], yaw_quat(yaw))
        return placed


NO_DISTRACTORS = Distractors()
