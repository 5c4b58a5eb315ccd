"""A frozen dataclass registered as a JAX pytree, changed with `.replace`:

@pytree_dataclass
class State(PyTree):
    qpos: jax.Array
    nq: int = static_field()
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

import jax
from typing_extensions import dataclass_transform

from vabench.sim_mjx import jax_setup  # noqa: F401  (JAX configured before it compiles)

T = TypeVar("T")


class PyTree:
    """The base of pytree dataclasses: `.replace` returns a copy with some fields changed."""

    def replace(self: T, **changes: Any) -> T:
        return dataclasses.replace(self, **changes)  # type: ignore[type-var]


def static_field(**kwargs: Any) -> Any:
    """A field that is pytree metadata (static under jit), not a traced leaf."""
    return dataclasses.field(metadata={"static": True}, **kwargs)


@dataclass_transform(frozen_default=True, field_specifiers=(dataclasses.field, static_field))
def pytree_dataclass(cls: type[T]) -> type[T]:
    """Frozen dataclass whose fields are leaves, except those made with `static_field`."""
    cls = dataclasses.dataclass(frozen=True)(cls)
    fields = dataclasses.fields(cls)  # type: ignore[arg-type]
    meta = [f.name for f in fields if f.metadata.get("static")]
    data = [f.name for f in fields if not f.metadata.get("static")]
    jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=meta)
    return cls
