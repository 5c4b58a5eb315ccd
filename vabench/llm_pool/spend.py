"""What a model's calls cost in words, and the spend caps that stop new calls.

`Pricing` is the one decision about how a cost may be shown: a model whose `prices` are not
set has no cost to show ("price not set", never "$0.00", which reads as "free"); a model of the
embedded server without prices costs nothing by construction (it runs on this machine, no
provider bills it); every other model shows dollars. `cost_text` turns a number and the pricing
of the models behind it into the words the dry-run, the live display and the report print.

`SpendCaps` keeps `limits.max_cost_usd`, per model and for the whole sweep: the spend already
recorded (read from the run directory by the sweep when it starts or resumes) plus what this
process's calls cost since, plus the upper bound of every call in flight. A call whose upper
bound (its estimated input and its whole output limit, at the model's prices) would cross a cap
is refused before it is sent (`SpendCapReached`), so a cap is never passed by this process.

A pool reaches its caps through `Caps.reserve`, which hands back a `Reservation` to settle
when the call ends: `LocalCaps` keeps them in this process; the sweep's limit board keeps them
for several processes at once (`limit_board.BoardSpend`), so worker processes and Ray engines
spend against one count, exact to the reservation.
"""

from __future__ import annotations

import enum
import math
from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol

from vabench.llm_pool.settings import Prices


class Pricing(enum.Enum):
    SET = "set"
    NOT_SET = "not set"
    EMBEDDED = "embedded"
    """The embedded server without prices: nothing is billed (a priced embedded model stands in
    for a paid endpoint, in tests and rehearsals, and is shown like one)."""


EMBEDDED_BASE_URL = "embedded"
"""A model's `base_url` in a sweep config that means "the embedded server the sweep starts"
(`config.EMBEDDED`; here too because the report reads it from a run's sweep.yaml)."""

NOT_SET_TEXT = "price not set"
EMBEDDED_TEXT = "no cost (embedded server)"


def pricing_of(prices: Prices | None, embedded: bool) -> Pricing:
    """How a model with these `prices` (None: the config sets none) is priced."""
    if prices is not None:
        return Pricing.SET
    return Pricing.EMBEDDED if embedded else Pricing.NOT_SET


def cost_text(
    usd: float, pricing: Mapping[str, Pricing], fmt: str = ",.2f", *, sign: str = "$"
) -> str:
    """`usd` spent by the models of `pricing` (name -> Pricing), in words: dollars where every
    model has prices, "price not set" where none of the paid ones has, both where some have.
    An empty mapping (pricing unknown: a run directory without its config) shows dollars.
    `sign=""` for a column whose header already says USD."""
    unset = sorted(m for m, p in pricing.items() if p is Pricing.NOT_SET)
    priced = not pricing or any(p is Pricing.SET for p in pricing.values())
    if not unset and not priced:
        return EMBEDDED_TEXT
    if not unset:
        return f"{sign}{usd:{fmt}}"
    if not priced:
        return NOT_SET_TEXT if len(pricing) == 1 else f"{NOT_SET_TEXT} ({', '.join(unset)})"
    return f"{sign}{usd:{fmt}} + {NOT_SET_TEXT} ({', '.join(unset)})"


def cost_cell(usd: float, pricing: Pricing | None) -> float | str:
    """A cost in a CSV cell: the number, or an empty cell for a model without prices (a 0.0
    there would read as free). `pricing` None: unknown (no config): the number."""
    return "" if pricing is Pricing.NOT_SET else usd


@dataclass(frozen=True)
class CapReached:
    """A spend cap that a call would cross: the model's (`model` set) or the sweep's."""

    cap: float
    spent: float
    """US dollars recorded and spent by the model (or the sweep) when the call was refused."""
    model: str | None = None

    def __str__(self) -> str:
        if self.model is None:
            return f"limits.max_cost_usd of the sweep (${self.cap:g}) reached at ${self.spent:.4f}"
        return (
            f"limits.max_cost_usd of model {self.model!r} (${self.cap:g}) reached at "
            f"${self.spent:.4f}"
        )


class SpendCaps:
    """`limits.max_cost_usd` of each model (`per_model`) and of the sweep (`total`), over
    `recorded` (US dollars per model already spent, from the run directory)."""

    def __init__(
        self,
        per_model: Mapping[str, float],
        total: float | None,
        recorded: Mapping[str, float],
    ):
        self.per_model = dict(per_model)
        self.total = total
        self.spent: dict[str, float] = defaultdict(float, recorded)
        self._held: dict[str, float] = defaultdict(float)
        """Upper bounds of the calls in flight, per model."""

    def _total_spent(self) -> float:
        return math.fsum(self.spent.values())

    def hold(self, model: str, upper_bound: float) -> CapReached | None:
        """Reserve a call's `upper_bound` for `model`; the cap it would cross, or None when
        reserved. A cap already reached refuses even a call that costs nothing."""
        cap = self.per_model.get(model)
        if cap is not None:
            mine = self.spent[model]
            if mine >= cap or mine + self._held[model] + upper_bound > cap:
                return CapReached(cap, mine, model)
        if self.total is not None:
            spent = self._total_spent()
            if spent >= self.total or spent + sum(self._held.values()) + upper_bound > self.total:
                return CapReached(self.total, spent)
        self._held[model] += upper_bound
        return None

    def settle(self, model: str, upper_bound: float, cost: float) -> None:
        """A held call ended: its reservation goes, what it cost (0 when it failed) stays."""
        self._held[model] -= upper_bound
        self.spent[model] += cost


class Reservation(Protocol):
    """A call's reserved upper bound: `settle(cost)` once it ended (0 when it failed)."""

    def settle(self, cost: float) -> None: ...


class Caps(Protocol):
    """Where a pool reserves a call's upper bound before sending it (`LocalCaps`, or the limit
    board's `limit_board.BoardSpend`)."""

    async def reserve(self, model: str, upper_bound: float) -> Reservation | CapReached: ...


@dataclass
class _LocalReservation:
    caps: SpendCaps
    model: str
    upper_bound: float

    def settle(self, cost: float) -> None:
        self.caps.settle(self.model, self.upper_bound, cost)


class LocalCaps:
    """`SpendCaps` kept in this process (one process runs every call that spends)."""

    def __init__(self, caps: SpendCaps):
        self.caps = caps

    async def reserve(self, model: str, upper_bound: float) -> Reservation | CapReached:
        reached = self.caps.hold(model, upper_bound)
        return reached if reached is not None else _LocalReservation(self.caps, model, upper_bound)
