"""What one episode allows at the current decision."""

from __future__ import annotations

from dataclasses import dataclass

from vabench.protocol.vocabulary import BASE_TOOLS, TOOL_NAMES, ObservationProtocol


@dataclass(frozen=True)
class DecisionContext:
    """What one episode allows at the current decision.

    `arms`: ("right",) for single-arm tasks, ("left", "right") for dual-arm (`Task.arms`).
    `protocol`: "active" (camera actions allowed) or "passive" (five fixed views, none).
    `tools`: the tool names offered, `available_tools(demonstration)`.
    `camera_chain`: camera actions executed since the last robot action,
    `camera_chain_length(kinds)`, for the records; the limit of `MAX_CAMERA_CHAIN` is an
    instruction of the system prompt, never a rejection. Per decision:
    `dataclasses.replace(ctx, camera_chain=...)`.
    """

    arms: tuple[str, ...]
    protocol: ObservationProtocol = "active"
    tools: tuple[str, ...] = BASE_TOOLS
    camera_chain: int = 0

    def __post_init__(self) -> None:
        if (
            not self.arms
            or len(set(self.arms)) != len(self.arms)
            or not set(self.arms)
            <= {
                "left",
                "right",
            }
        ):
            raise ValueError(f"arms must be ('right',) or ('left', 'right'), got {self.arms!r}")
        if self.protocol not in ("active", "passive"):
            raise ValueError(f"protocol must be 'active' or 'passive', got {self.protocol!r}")
        unknown = [t for t in self.tools if t not in TOOL_NAMES]
        if unknown:
            raise ValueError(f"tools: unknown {unknown}; valid tools: {list(TOOL_NAMES)}")
        if self.camera_chain < 0:
            raise ValueError(f"camera_chain must be >= 0, got {self.camera_chain}")
