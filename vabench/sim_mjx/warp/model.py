"""MuJoCo Warp models and data for a batch: model variants per world and buffer sizing.

Model variants (several object models of one family, `variants.py`) differ only in numbers:
sizes, positions, masses, inertias. MuJoCo Warp lets a model field carry one row per world
(the fields whose spec starts with "*"), so the fields that differ between variants get
n_slots rows, and each world's rows are its slot's variant: every seed of a family steps in
one batch whatever object it drew.

Contact and constraint buffers are fixed-size on the GPU. `capacity` sizes them from the scene
(objects, arms, cone type, joint limits); `failure_text` turns MuJoCo Warp's per-world overflow
bits into the message of the infrastructure error that the affected slots get.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp
from mujoco_warp._src import types as mjw_types

# Fields that may differ between variants without being batched: they serve features the
# scenes do not use (dof_length weighs velocities for sleeping, which is off) or only the
# renderer (materials, lights, cameras), which builds its own model (`RENDER_IGNORED`).
PHYSICS_IGNORED = ("dof_length", "mat_", "light_", "cam_", "tex", "bvh_")
RENDER_IGNORED = ("dof_length",)

# Overflow bits that make a world's physics untrustworthy (buffers too small). The solver's
# iteration limits (ITERATIONS, LS_ITERATIONS) are not failures: 10 Newton iterations are the
# scene's setting, as on C MuJoCo.
FAILURE_BITS = int(
    mjw.OverflowType.NEFC
    | mjw.OverflowType.NJMAX_NNZ
    | mjw.OverflowType.BROADPHASE
    | mjw.OverflowType.NARROWPHASE
    | mjw.OverflowType.CCD
    | mjw.OverflowType.HFIELD
    | mjw.OverflowType.NVMAX
    | mjw.OverflowType.EPA_HORIZON
)


@dataclasses.dataclass(frozen=True)
class Capacity:
    """Per-world buffer sizes of a MuJoCo Warp batch."""

    nconmax: int  # contacts per world (the pool holds nconmax * n_slots)
    njmax: int  # constraint rows per world


def capacity(
    model: mujoco.MjModel, nconmax: int | None = None, njmax: int | None = None
) -> Capacity:
    """Buffer sizes from the scene, unless given.

    Contacts: 16 for the arms' fingers and palm on a held object, 12 for every free object
    (its resting face on the table or a support: 4-8, and neighbours), 16 for every further
    collision geom of a free object (a basket's walls, a bowl's segments: each touches what
    leans on it), 8 per arm. Measured on C MuJoCo over the experts of every family, the most
    contacts at once were 12 for one object (grasp_single_cube), 24 for four
    (place_single_cube_heldout) and 32 for five (the basket); without the per-geom term the
    basket's 96 overflowed under the reference agent on a GPU (6 of 60 episodes), which
    piles objects against the walls as the expert does not. Rows: each contact takes `condim`
    rows with elliptic cones and 2 (condim - 1) with pyramidal ones, plus one per limited joint.
    """
    n_free = int(np.sum(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE))
    n_arms = int(
        sum(
            mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"{a}_waist") >= 0
            for a in ("left", "right")
        )
    )
    free_bodies = {
        int(model.jnt_bodyid[j])
        for j in np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
    }
    free_geoms = sum(
        1
        for g in range(model.ngeom)
        if (model.geom_contype[g] | model.geom_conaffinity[g])
        and _root_in(model, int(model.geom_bodyid[g]), free_bodies)
    )
    extra = max(0, free_geoms - n_free)
    contacts = nconmax if nconmax is not None else 16 + 12 * n_free + 16 * extra + 8 * n_arms
    condim = int(model.geom_condim.max()) if model.ngeom else 3
    elliptic = model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    per_contact = condim if elliptic else 2 * (condim - 1)
    rows = njmax if njmax is not None else contacts * per_contact + int(model.jnt_limited.sum())
    if contacts < 1 or rows < 1:
        raise ValueError(f"nconmax and njmax must be >= 1, got {contacts} and {rows}")
    return Capacity(nconmax=contacts, njmax=rows)


def _root_in(model: mujoco.MjModel, body: int, roots: set[int]) -> bool:
    """Whether `body` is one of `roots` or inside one of their subtrees."""
    while body and body not in roots:
        body = int(model.body_parentid[body])
    return body in roots


def failure_text(bits: int, cap: Capacity) -> str:
    """The infrastructure error of a world whose overflow bits are `bits`."""
    names = [
        f.name.lower()
        for f in mjw.OverflowType
        if f.value and not f.value & (f.value - 1) and bits & f.value & FAILURE_BITS
    ]
    hint = (
        f"raise simulator.njmax (now {cap.njmax})"
        if bits & (mjw.OverflowType.NEFC | mjw.OverflowType.NJMAX_NNZ)
        else f"raise simulator.nconmax (now {cap.nconmax})"
    )
    return f"MuJoCo Warp buffer overflow ({', '.join(names)}): physics not trusted; {hint}"


def failure_texts(bits: np.ndarray, cap: Capacity) -> list[str | None]:
    """Per world, `failure_text` of its overflow bits, or None where they are zero."""
    return [failure_text(int(b), cap) if b else None for b in bits]


def _array_fields(obj: Any, prefix: str = "") -> dict[str, wp.array]:
    out: dict[str, wp.array] = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name, None)
        if isinstance(value, wp.array):
            out[prefix + f.name] = value
        elif dataclasses.is_dataclass(value) and not isinstance(value, type):
            out.update(_array_fields(value, prefix + f.name + "."))
    return out


def _batchable(name: str) -> bool:
    spec = {f.name: f.type for f in dataclasses.fields(mjw_types.Model)}.get(name)
    shape = getattr(spec, "shape", ())
    return bool(shape) and shape[0] == "*"


@dataclasses.dataclass(frozen=True)
class VariantFields:
    """The device-model fields in which a family's object variants differ, with each
    variant's row of each (shape (n_variants, *row)); `variant_fields` finds them."""

    values: dict[str, np.ndarray]


def variant_fields(
    models: Sequence[mujoco.MjModel], ignore: tuple[str, ...] = PHYSICS_IGNORED
) -> VariantFields:
    """Put every variant's model on the current device and compare their fields (`ignore`:
    name prefixes whose differences do not matter to the user of the model). Depends on the
    models only, not on the batch: a renderer that builds many passes of one family finds them
    once (a pass took about half a second to build with the device's lock held, most of it
    here, and a process of the warm suite builds dozens)."""
    per_variant = [mjw.put_model(m) for m in models]
    first = _array_fields(per_variant[0])
    varying: list[str] = []
    for k, mw in enumerate(per_variant[1:], start=1):
        for name, arr in _array_fields(mw).items():
            a, b = first[name].numpy(), arr.numpy()
            if a.shape == b.shape and np.array_equal(a, b):
                continue
            if name.startswith(ignore) or name in varying:
                continue
            if "." in name or not _batchable(name):
                raise ValueError(
                    f"model variant {k} differs in {name}, which MuJoCo Warp cannot hold per world"
                )
            varying.append(name)
    return VariantFields(
        {name: np.stack([getattr(mw, name).numpy()[0] for mw in per_variant]) for name in varying}
    )


class WarpModel:
    """The device model of a batch: variant 0's model with the fields that differ between
    variants batched per world. `assign(variants)` points every world at its slot's variant.

    `ignore`: name prefixes of fields whose differences do not matter to the user of the model;
    `per_world`: fields batched whether or not they differ (the renderer's camera FOV);
    `variants`: `variant_fields(models, ignore)` when already known."""

    def __init__(
        self,
        models: Sequence[mujoco.MjModel],
        n_slots: int,
        ignore: tuple[str, ...] = PHYSICS_IGNORED,
        per_world: tuple[str, ...] = (),
        variants: VariantFields | None = None,
    ):
        self.n_slots = n_slots
        # Per variant, the rows of each varying field (shape (n_variants, *row)).
        self.values = (variants or variant_fields(models, ignore)).values
        batched = {name: n_slots for name in (*self.values, *per_world)}
        self.model = mjw.put_model(models[0], batch_sizes=batched)
        self.model.opt.warn_overflow = 0  # overflow is reported per slot (failure_text)
        self.current = np.zeros(n_slots, np.int32)

    def assign(self, variants: np.ndarray) -> None:
        """Set every world's varying fields to its slot's variant (n_slots,) when it changed."""
        variants = np.asarray(variants, np.int32)
        if np.array_equal(variants, self.current) or not self.values:
            self.current = variants.copy()
            return
        for name, rows in self.values.items():
            getattr(self.model, name).assign(rows[variants])
        self.current = variants.copy()
