"""Model variants ("model ids") inside one batch: per-slot geometry, masses and colours.

Several task families come with several object models (two bells, two pots, ten shoes). The
variants of a family are authored with the same structure (same bodies, geoms, joints and geom
types) and differ only in numbers: sizes, positions, masses, inertias, colours. Compiling each
variant and keeping, per slot, only the model arrays that differ lets every seed of a family run
in one batch and one compiled step, whatever model id each seed draws.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from vabench.sim_mjx import jax_setup  # JAX configured before it compiles

if TYPE_CHECKING:
    from mujoco import mjx

# Static (numpy) MJX fields that may differ between variants because they only serve features
# the variants do not use (height fields).
_STATIC_MAY_DIFFER = {"geom_rbound_hfield"}


def check_same_structure(models: Sequence[mujoco.MjModel]) -> None:
    """Raise ValueError naming the first structural difference between variants."""
    m0 = models[0]
    for k, m in enumerate(models[1:], start=1):
        for field in ("nq", "nv", "nu", "nbody", "ngeom", "njnt", "nmesh", "nmeshvert"):
            if getattr(m, field) != getattr(m0, field):
                raise ValueError(
                    f"model variant {k} differs in structure from variant 0: {field} "
                    f"{getattr(m, field)} != {getattr(m0, field)}"
                )
        if not np.array_equal(m.geom_type, m0.geom_type):
            raise ValueError(f"model variant {k} differs from variant 0 in geom types")


def _static_differences(a: Any, b: Any, path: str = "") -> list[str]:
    out: list[str] = []
    if dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            out += _static_differences(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
        return out
    if isinstance(a, jax.Array):
        return out
    if isinstance(a, tuple | list) and isinstance(b, tuple | list):
        if len(a) != len(b):
            return [path]
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            out += _static_differences(x, y, f"{path}[{i}]")
        return out
    if isinstance(a, np.ndarray):
        same = a.shape == np.shape(b) and np.array_equal(a, b)
    else:
        try:
            same = bool(a == b)
        except ValueError:
            same = False
    if not same and path.rsplit(".", 1)[-1].split("[")[0] not in _STATIC_MAY_DIFFER:
        out.append(path)
    return out


class ModelVariants:
    """The MJX model of variant 0 plus, stacked over variants, the arrays that differ."""

    def __init__(self, models: Sequence[mujoco.MjModel], impl: str = "jax", device: Any = None):
        if not models:
            raise ValueError("need at least one model")
        check_same_structure(models)
        with jax_setup.quiet_stdout():  # MJX's own, not imported by the other backends
            from mujoco import mjx
        mxs = [mjx.put_model(m, impl=impl, device=device) for m in models]
        self.base = mxs[0]
        self.n = len(mxs)
        leaves0, self._treedef = jax.tree_util.tree_flatten(self.base)
        all_leaves = [leaves0]
        for k, mx in enumerate(mxs[1:], start=1):
            diffs = _static_differences(self.base, mx)
            if diffs:
                raise ValueError(f"model variant {k} differs in static fields: {diffs[:5]}")
            all_leaves.append(jax.tree_util.tree_leaves(mx))
        self.varying = [
            i
            for i, leaf in enumerate(leaves0)
            if any(not np.array_equal(np.asarray(leaf), np.asarray(v[i])) for v in all_leaves[1:])
        ]
        self.stacked = tuple(jnp.stack([v[i] for v in all_leaves]) for i in self.varying)

    def select(self, base: mjx.Model, stacked: tuple[jax.Array, ...], variant: jax.Array) -> Any:
        """The model of one slot (inside jit): base with the varying arrays of `variant`."""
        if not self.varying:
            return base
        leaves = jax.tree_util.tree_leaves(base)
        for i, arr in zip(self.varying, stacked, strict=True):
            leaves[i] = arr[variant]
        return jax.tree_util.tree_unflatten(self._treedef, leaves)
