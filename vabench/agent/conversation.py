"""One episode's conversation: the append-only transcript, and the bounded context the model
sees (spec FACTS.md, "Observation sent each decision"; paper, "Persistent decision loop").

The engine appends to a `Conversation` and asks it for the next `ChatRequest`:

    conv = Conversation(system_prompt(arms, protocol, tools), protocol=protocol)
    conv.add_observation(observation_text(...), image, step=1)   # a bundle dict when passive
    event = await conv.compact_if_needed(summarize)              # None, or a record to log
    result = await pool.complete(model, conv.request())
    conv.add_reply(result.text)
    conv.add_tool_result(text, image, step=k) | conv.add_repair(error, text, step) | ...

Image retention, applied when a request is built (the thread itself keeps every image):

- the newest five-image bundle (passive) is always sent whole, and so are the images of the
  newest user turn (the observation or tool result the model is answering);
- other images are kept newest first while the request holds at most `max_images` in all
  (1: the paper's active request holds only the current image); earlier passive bundles are
  never kept; an image already kept (the same `Image` object attached twice) is not sent
  twice;
- every dropped image becomes a text placeholder such as "[image from step 7 omitted]" (one
  per dropped bundle), so the thread keeps its order and its step references.

Compaction (the reference's rule, spec PROTOCOL_FACTS.md 8): when the estimated tokens of the
context with every image counted (those a request leaves out included), plus
`output_reserve_tokens`, reach `compact_fraction * window_tokens`, the messages before the
last `keep_user_turns` user turns are replaced by a handoff summary that the same model writes
from a text-only request (`summarize`, injected so that the engine routes it through the
pool): each earlier message at most `EXCERPT_MESSAGE_CHARS` (its middle cut), the newest of
them within max(8,000, 0.6 x window) tokens. The transcript is never compacted.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from vabench.agent.observation import observation_turn, repair_text
from vabench.llm_pool.config import GenerationOptions
from vabench.llm_pool.messages import ChatRequest, Image, Part, Turn
from vabench.llm_pool.tokens import (
    ImageTokenRule,
    estimate_input_tokens,
    openai_image_tokens,
    text_tokens,
)

EntryKind = Literal["observation", "repair", "tool_result", "reply", "summary", "note"]
Summarizer = Callable[[ChatRequest], Awaitable[str]]

SUMMARY_HEADER = (
    "Summary of the earlier part of this episode, written by you (memory, not a new "
    "instruction: the system prompt and the recent observations take precedence):\n"
)
SUMMARY_INSTRUCTION = """\
The messages above are the earlier part of the current episode; images were removed (a
bracketed label only names an image, it shows nothing). They are about to be replaced by
your summary to keep the conversation within the context limit. Write a short structured
handoff for yourself:
1. Goal, Progress so far and the current phase of the task.
2. Constraints stated or learned, and the role of each arm.
3. The latest robot state and what the images last showed of the objects.
4. Attempts so far and their outcomes: rejected actions, planner failures, failed
   hypotheses, and what each taught.
5. Validated facts, open ambiguities and risks.
6. The next checks and steps, and the key steps, views and errors worth remembering.
Keep what was done apart from what is planned. Invent no coordinates, contacts, successes or
visual facts. Leave out the action schema. Plain text, at most about 400 words; do not reply
with a decision."""


@dataclass(frozen=True)
class ContextLimits:
    """The bounds of the model-visible context (FACTS defaults)."""

    window_tokens: int = 262_144
    compact_fraction: float = 0.8
    output_reserve_tokens: int = 8_192
    keep_user_turns: int = 6
    max_images: int = 1
    """Images per request besides the newest user turn's and the newest passive bundle: the
    paper's "each active API request contains only the current RGB image"."""

    def __post_init__(self) -> None:
        if self.window_tokens <= self.output_reserve_tokens:
            raise ValueError("window_tokens must exceed output_reserve_tokens")
        if not 0 < self.compact_fraction <= 1:
            raise ValueError(f"compact_fraction must be in (0, 1], got {self.compact_fraction}")
        if self.keep_user_turns < 1 or self.max_images < 1:
            raise ValueError("keep_user_turns and max_images must be at least 1")

    @property
    def compact_above(self) -> int:
        """Compaction starts when the estimate reaches this: the estimate plus the output
        reserve then reaches `compact_fraction` of the window (the reference's rule)."""
        return int(self.compact_fraction * self.window_tokens) - self.output_reserve_tokens


@dataclass(frozen=True)
class Entry:
    """One message of the thread.

    `step` is the environment step the turn's images belong to (for placeholders);
    `image_names` names each image for its placeholder ("image from step 7" by default);
    `bundle` marks a passive five-view bundle.
    """

    kind: EntryKind
    turn: Turn
    step: int | None = None
    bundle: bool = False
    image_names: tuple[str, ...] = ()

    def placeholder(self, i: int) -> str:
        if self.bundle:
            where = f" from step {self.step}" if self.step is not None else ""
            return f"[five images{where} omitted]"
        if i < len(self.image_names):
            return f"[{self.image_names[i]} omitted]"
        if self.step is not None:
            return f"[image from step {self.step} omitted]"
        return "[earlier image omitted]"

    def record(self) -> dict[str, Any]:
        """A JSON-ready line for the episode's transcript (images counted, stored elsewhere)."""
        return {
            "kind": self.kind,
            "role": self.turn.role,
            "step": self.step,
            "text": self.turn.text,
            "images": len(self.turn.images),
        }


@dataclass(frozen=True)
class CompactionEvent:
    """What one compaction did, for the episode log."""

    step: int | None
    tokens_before: int
    tokens_after: int
    compact_above: int
    messages_summarised: int
    user_turns_kept: int
    summary: str

    @property
    def under_limit(self) -> bool:
        return self.tokens_after < self.compact_above

    def record(self) -> dict[str, Any]:
        return {
            "event": "compaction",
            "step": self.step,
            "tokens_before": self.tokens_before,
            "tokens_after": self.tokens_after,
            "compact_above": self.compact_above,
            "under_limit": self.under_limit,
            "messages_summarised": self.messages_summarised,
            "user_turns_kept": self.user_turns_kept,
            "summary": self.summary,
        }


EXCERPT_MESSAGE_CHARS = 12_000
"""A message of the compaction excerpt longer than this keeps its start and its end."""
EXCERPT_MIN_TOKENS = 8_000
EXCERPT_WINDOW_SHARE = 0.6
"""The excerpt holds the newest messages within max(8,000, 0.6 x window) tokens (the
reference's budget: 157,286 tokens at 262,144)."""


def cut_middle(text: str, limit: int) -> str:
    """`text`, or its first and last `limit // 2` characters around a note of the cut."""
    if len(text) <= limit:
        return text
    half = limit // 2
    return f"{text[:half]}\n[... {len(text) - 2 * half:,} characters left out ...]\n{text[-half:]}"


def newest_within(blocks: Sequence[str], budget: int) -> list[str]:
    """The newest `blocks` whose estimated tokens fit `budget` (at least the newest one), in
    their own order."""
    kept: list[str] = []
    total = 0
    for block in reversed(blocks):
        total += text_tokens(block)
        if kept and total > budget:
            break
        kept.append(block)
    return kept[::-1]


def _join_text(parts: Sequence[Part]) -> tuple[Part, ...]:
    """Adjacent text parts joined into one (placeholders next to text)."""
    out: list[Part] = []
    for part in parts:
        if isinstance(part, str) and out and isinstance(out[-1], str):
            out[-1] = f"{out[-1]}\n{part}"
        else:
            out.append(part)
    return tuple(out)


def _merge_roles(turns: Sequence[Turn]) -> list[Turn]:
    """Consecutive turns of one role merged (a summary before a user turn, two tool results):
    the Anthropic API wants alternating roles."""
    merged: list[Turn] = []
    for turn in turns:
        if merged and merged[-1].role == turn.role:
            merged[-1] = Turn(turn.role, _join_text(merged[-1].content + turn.content))
        else:
            merged.append(turn)
    return merged


@dataclass
class Conversation:
    """The thread of one episode (see the module docstring)."""

    system: str
    protocol: Literal["active", "passive"] = "active"
    limits: ContextLimits = field(default_factory=ContextLimits)
    image_rule: ImageTokenRule = openai_image_tokens
    _context: list[Entry] = field(default_factory=list, init=False, repr=False)
    _transcript: list[Entry] = field(default_factory=list, init=False, repr=False)
    _compactions: list[CompactionEvent] = field(default_factory=list, init=False, repr=False)
    _built: tuple[tuple[Turn, ...], int] | None = field(default=None, init=False, repr=False)
    """The context's turns as last built and their estimated tokens, until the context changes:
    a decision asks for them twice (`compact_if_needed`, then `request`), and building them
    walks the whole thread (1.5-2.6 ms a call in a 180-call episode on a 2-core machine)."""
    _history_tokens: int | None = field(default=None, init=False, repr=False)
    """`history_tokens()` until the context changes."""

    def __post_init__(self) -> None:
        if self.protocol not in ("active", "passive"):
            raise ValueError(f"protocol: expected 'active' or 'passive', got {self.protocol!r}")

    # -- appending ------------------------------------------------------------------------
    def _append(self, entry: Entry) -> None:
        self._context.append(entry)
        self._transcript.append(entry)
        self._built = None
        self._history_tokens = None

    def _observation_entry(
        self, kind: EntryKind, text: str, images: Image | Mapping[str, Image], step: int
    ) -> Entry:
        passive = self.protocol == "passive"
        if passive == isinstance(images, Image):
            expected = "a mapping of the five views" if passive else "one Image"
            raise ValueError(f"images: the {self.protocol} protocol takes {expected}")
        return Entry(kind, observation_turn(text, images), step=step, bundle=passive)

    def add_observation(self, text: str, images: Image | Mapping[str, Image], step: int) -> None:
        """The observation before environment step `step`: its text and its image (active) or
        its five views by name (passive; sent in fixed order)."""
        self._append(self._observation_entry("observation", text, images, step))

    def add_repair(self, error: str, text: str, step: int) -> None:
        """A rejected reply: the current observation's text, the error and a request for a
        corrected command, as text only (the benchmark's repair turn: the observation's images
        stay where they are, in the turn before, and are sent from there)."""
        self._append(Entry("repair", Turn.user(repair_text(error, text)), step=step))

    def add_tool_result(
        self,
        text: str,
        images: Sequence[Image] = (),
        *,
        step: int | None = None,
        image_names: Sequence[str] = (),
    ) -> None:
        """A tool's result (JSON text) and any images it re-attaches; `step` is the step those
        images belong to, or `image_names` names each ("demonstration frame 12")."""
        turn = Turn.user(text, *images)
        self._append(Entry("tool_result", turn, step=step, image_names=tuple(image_names)))

    def add_reply(self, text: str) -> None:
        """The model's reply, verbatim (an empty reply is kept as a marker)."""
        self._append(Entry("reply", Turn.assistant(text or "(empty reply)")))

    def add_note(self, text: str) -> None:
        """Any other harness text for the model (e.g. why the episode goes on)."""
        self._append(Entry("note", Turn.user(text)))

    # -- reading --------------------------------------------------------------------------
    @property
    def transcript(self) -> tuple[Entry, ...]:
        """Every message ever added, summaries included, never compacted."""
        return tuple(self._transcript)

    @property
    def context(self) -> tuple[Entry, ...]:
        """The messages the next request is built from (after any compaction)."""
        return tuple(self._context)

    @property
    def compactions(self) -> tuple[CompactionEvent, ...]:
        return tuple(self._compactions)

    def _kept_images(self, entries: Sequence[Entry]) -> set[tuple[int, int]]:
        """(entry index, part index) of the images a request sends (see the module docstring)."""
        kept: set[tuple[int, int]] = set()
        kept_ids: set[int] = set()

        def keep(i: int, j: int, image: Image) -> None:
            kept.add((i, j))
            kept_ids.add(id(image))

        users = [i for i, e in enumerate(entries) if e.turn.role == "user"]
        bundles = [i for i, e in enumerate(entries) if e.bundle]
        always = set(users[-1:] + bundles[-1:])
        for i in sorted(always, reverse=True):
            for j, part in enumerate(entries[i].turn.content):
                if isinstance(part, Image) and id(part) not in kept_ids:
                    keep(i, j, part)
        for i in reversed(range(len(entries))):
            if i in always or entries[i].bundle:
                continue
            parts = entries[i].turn.content
            for j in reversed(range(len(parts))):
                part = parts[j]
                room = len(kept) < self.limits.max_images
                if isinstance(part, Image) and id(part) not in kept_ids and room:
                    keep(i, j, part)
        return kept

    @staticmethod
    def _turns(entries: Sequence[Entry], kept: set[tuple[int, int]]) -> list[Turn]:
        """The entries' turns with the images not in `kept` replaced by placeholders."""
        turns = []
        for i, entry in enumerate(entries):
            parts: list[Part] = []
            n_image = 0
            for j, part in enumerate(entry.turn.content):
                if not isinstance(part, Image):
                    parts.append(part)
                    continue
                if (i, j) in kept:
                    parts.append(part)
                elif not (entry.bundle and n_image > 0):  # one placeholder per bundle
                    parts.append(entry.placeholder(n_image))
                n_image += 1
            turns.append(Turn(entry.turn.role, _join_text(parts)))
        return _merge_roles(turns)

    def request(self, options: GenerationOptions | None = None) -> ChatRequest:
        """The next call: the system prompt and the context with images retained as above."""
        return ChatRequest(self._build()[0], self.system, options)

    def _build(self) -> tuple[tuple[Turn, ...], int]:
        if self._built is None:
            if not self._context:
                raise ValueError("the conversation has no turn yet")
            turns = tuple(self._turns(self._context, self._kept_images(self._context)))
            tokens = estimate_input_tokens(ChatRequest(turns, self.system), self.image_rule)
            self._built = (turns, tokens)
        return self._built

    def estimate_tokens(self) -> int:
        """Estimated input tokens of `request()` (text 4 chars/token, images by `image_rule`)."""
        return self._build()[1]

    def history_tokens(self) -> int:
        """Estimated tokens of the context with every image counted, those a request leaves
        out included: the reference's estimate, which decides compaction."""
        if self._history_tokens is None:
            every = {
                (i, j)
                for i, e in enumerate(self._context)
                for j, part in enumerate(e.turn.content)
                if isinstance(part, Image)
            }
            turns = tuple(self._turns(self._context, every))
            self._history_tokens = estimate_input_tokens(
                ChatRequest(turns, self.system), self.image_rule
            )
        return self._history_tokens

    def needs_compaction(self) -> bool:
        return self.history_tokens() >= self.limits.compact_above

    # -- compaction -----------------------------------------------------------------------
    def summary_request(self, entries: Sequence[Entry]) -> ChatRequest:
        """A text-only request asking the model to summarise `entries`: the episode's system
        prompt, then one user turn with the messages as text (images as placeholders) and
        `SUMMARY_INSTRUCTION`."""
        blocks = []
        for turn in self._turns(entries, kept=set()):
            who = "You" if turn.role == "assistant" else "Harness"
            blocks.append(f"--- {who}:\n{cut_middle(turn.text, EXCERPT_MESSAGE_CHARS)}")
        budget = max(EXCERPT_MIN_TOKENS, int(EXCERPT_WINDOW_SHARE * self.limits.window_tokens))
        kept = newest_within(blocks, budget)
        left_out = len(blocks) - len(kept)
        head = f"--- ({left_out} older messages left out.)\n\n" if left_out else ""
        body = head + "\n\n".join(kept) + "\n\n--- End of the earlier messages.\n\n"
        return ChatRequest((Turn.user(body + SUMMARY_INSTRUCTION),), self.system)

    async def compact(self, summarize: Summarizer) -> CompactionEvent | None:
        """Replace the messages before the last `keep_user_turns` user turns by a summary from
        `summarize(summary_request(...))`; None when there is nothing older to summarise.
        The event is also kept in `compactions`; the summary joins the transcript."""
        users = [i for i, e in enumerate(self._context) if e.turn.role == "user"]
        keep = self.limits.keep_user_turns
        if len(users) <= keep:
            return None
        cut = users[-keep]
        old, kept = self._context[:cut], self._context[cut:]
        before = self.history_tokens()
        summary = (await summarize(self.summary_request(old))).strip()
        if not summary:
            raise ValueError("summarize returned an empty summary")
        step = next((e.step for e in reversed(self._context) if e.step is not None), None)
        entry = Entry("summary", Turn.user(SUMMARY_HEADER + summary), step=step)
        self._context = [entry, *kept]
        self._transcript.append(entry)
        self._built = None
        self._history_tokens = None
        event = CompactionEvent(
            step=step,
            tokens_before=before,
            tokens_after=self.history_tokens(),
            compact_above=self.limits.compact_above,
            messages_summarised=len(old),
            user_turns_kept=keep,
            summary=summary,
        )
        self._compactions.append(event)
        return event

    async def compact_if_needed(self, summarize: Summarizer) -> CompactionEvent | None:
        """`compact` when `history_tokens()` reaches `limits.compact_above`."""
        if not self.needs_compaction():
            return None
        return await self.compact(summarize)
