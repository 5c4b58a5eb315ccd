"""The model-facing side of the agent harness.

- `visibility`: the one list of model-visible observation fields, `filter_proprio`, and the
  privilege-boundary checker `find_leaks` / `assert_model_visible`.
- `prompts`: `system_prompt(arms, protocol, tools)`.
- `observation`: `build_observation` / `render_observation` / `observation_text`, and the
  user turn of an observation (`observation_turn`, the passive bundle in fixed order).
- `conversation`: `Conversation`, the episode thread: image retention, repair and tool turns,
  compaction through an injected summarizer, the append-only transcript.
- `tools`: `geometry.verify` and `camera.history` results.
- `learning_stage`: the learning sessions a run directory needs, each learned once and stored.
- `usage`: an episode's model calls and tokens estimated before it runs (the dry run's bound).

The episode loop (`engine`) is built on these; importing this package loads neither JAX nor
the simulator.
"""

from vabench.agent.conversation import (
    CompactionEvent,
    ContextLimits,
    Conversation,
    Entry,
    Summarizer,
)
from vabench.agent.observation import (
    INITIAL_VIEW,
    PASSIVE_VIEW_NAME,
    PASSIVE_VIEWS,
    ActionFeedback,
    build_observation,
    observation_text,
    observation_turn,
    render_observation,
)
from vabench.agent.prompts import system_prompt
from vabench.agent.tools import ToolResult, camera_history, geometry_result, geometry_verify
from vabench.agent.visibility import (
    OBSERVATION_FIELDS,
    Leak,
    PrivilegeLeak,
    Secret,
    VisibilityError,
    assert_model_visible,
    episode_secrets,
    filter_proprio,
    find_leaks,
)

__all__ = [
    "INITIAL_VIEW",
    "OBSERVATION_FIELDS",
    "PASSIVE_VIEWS",
    "PASSIVE_VIEW_NAME",
    "ActionFeedback",
    "CompactionEvent",
    "ContextLimits",
    "Conversation",
    "Entry",
    "Leak",
    "PrivilegeLeak",
    "Secret",
    "Summarizer",
    "ToolResult",
    "VisibilityError",
    "assert_model_visible",
    "build_observation",
    "camera_history",
    "episode_secrets",
    "filter_proprio",
    "find_leaks",
    "geometry_result",
    "geometry_verify",
    "observation_text",
    "observation_turn",
    "render_observation",
    "system_prompt",
]
