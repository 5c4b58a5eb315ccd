"""The episode thread: which images a request carries (last 4; the passive bundle whole),
placeholders in order, repair and tool turns, history compaction at the threshold with the
last 6 user turns intact, and the append-only transcript."""

from __future__ import annotations

import asyncio
import re

import pytest

from vabench.agent.conversation import (
    SUMMARY_HEADER,
    ContextLimits,
    Conversation,
    cut_middle,
)
from vabench.agent.observation import PASSIVE_VIEWS
from vabench.llm_pool import ChatRequest
from vabench.llm_pool.testing import synthetic_image
from vabench.llm_pool.tokens import TOKENS_PER_TURN, openai_image_tokens, text_tokens

PLACEHOLDER = re.compile(r"\[(?:image|five images) from step (\d+) omitted\]")


def placeholders(request: ChatRequest) -> list[int]:
    """Steps named by the request's placeholders, in order."""
    return [int(s) for turn in request.turns for s in PLACEHOLDER.findall(turn.text)]


def active_episode(n_steps: int) -> tuple[Conversation, list]:
    conv = Conversation("system", protocol="active", limits=ContextLimits(max_images=4))
    images = []
    for step in range(1, n_steps + 1):
        image = synthetic_image(seed=step)
        images.append(image)
        conv.add_observation(f"observation {step}", image, step=step)
        conv.add_reply(f'{{"action": "camera.view_side", "reason": "look {step}"}}')
    return conv, images


def bundle(step: int) -> dict:
    return {v: synthetic_image(seed=100 * step + i) for i, v in enumerate(PASSIVE_VIEWS)}


# -- image retention --------------------------------------------------------------------------


def test_openai_image_rule_matches_the_published_examples():
    # OpenAI's documented examples of the tile rule that FACTS.md names.
    assert openai_image_tokens(1024, 1024) == 765  # -> 768x768, 4 tiles
    assert openai_image_tokens(2048, 4096) == 1105  # -> 1024x2048 -> 768x1536, 6 tiles
    assert openai_image_tokens(1280, 960) == 765  # the head camera: -> 1024x768, 4 tiles


@pytest.mark.parametrize("n_steps", [1, 4, 7])
def test_only_the_last_four_images_are_sent_with_placeholders_in_order(n_steps):
    conv, images = active_episode(n_steps)
    conv.add_observation("observation now", last := synthetic_image(seed=99), step=n_steps + 1)
    request = conv.request()
    sent = [*images, last][-4:]
    assert [id(im) for im in request.images] == [id(im) for im in sent]
    assert placeholders(request) == list(range(1, n_steps + 2 - len(sent)))
    assert [t.role for t in request.turns] == ["user", "assistant"] * n_steps + ["user"]
    # The thread itself keeps every image.
    assert sum(len(e.turn.images) for e in conv.transcript) == n_steps + 1


def test_a_repair_turn_is_text_only_and_the_current_image_stays_with_its_observation():
    conv = Conversation("system", protocol="active")  # one image a request, the paper's
    images = [synthetic_image(seed=step) for step in range(1, 6)]
    for step, image in enumerate(images, start=1):
        conv.add_observation(f"observation {step}", image, step=step)
        conv.add_reply('{"action": "gripper.move_world", "axis": "z", "distance_mm": 500}')
    conv.add_repair("field 'distance_mm': must be <= 100", "observation 5", step=5)
    request = conv.request()
    # the benchmark's repair turn carries no image: the request still holds the current image
    # once, in the observation turn it came with (the paper's one current image a request)
    assert [id(im) for im in request.images] == [id(im) for im in images[-1:]]
    assert not request.turns[-1].images
    assert request.turns[-2].role == "assistant"
    assert request.turns[-3].content[-1] is images[-1]
    text = request.turns[-1].text
    assert text.startswith("observation 5\n\nYour previous reply was not accepted: field")
    assert text.endswith("Reply with one corrected command: one valid JSON object.")


def test_tool_images_count_toward_the_cap_and_the_newest_user_turn_is_sent_whole():
    conv, images = active_episode(3)
    frames = [synthetic_image(seed=50 + i) for i in range(6)]
    conv.add_tool_result(
        '{"tool": "expert.frame"}',
        frames,
        image_names=[f"demonstration frame {i}" for i in range(6)],
    )
    request = conv.request()
    assert [id(im) for im in request.images] == [id(im) for im in frames]
    assert placeholders(request) == [1, 2, 3]
    conv.add_reply('{"tool": "camera.history", "args": {"step": 1}}')
    conv.add_tool_result('{"tool": "camera.history", "step": 1}', [images[0]], step=1)
    request = conv.request()
    assert [id(im) for im in request.images] == [id(f) for f in frames[-3:]] + [id(images[0])]
    assert "[demonstration frame 0 omitted]" in request.turns[-3].text


def test_passive_bundle_is_sent_whole_and_earlier_bundles_become_one_placeholder_each():
    conv = Conversation("system", protocol="passive")
    bundles = [bundle(step) for step in (1, 2, 3)]
    for step, views in enumerate(bundles, 1):
        conv.add_observation(f"observation {step}", views, step=step)
        conv.add_reply('{"action": "gripper.close"}')
    conv.add_tool_result('{"tool": "geometry.verify"}')  # newest user turn without images
    request = conv.request()
    assert len(request.images) == 5 > conv.limits.max_images
    assert [id(im) for im in request.images] == [id(bundles[-1][v]) for v in PASSIVE_VIEWS]
    assert placeholders(request) == [1, 2]
    current = request.turns[-3]
    assert current.content[0] == "observation 3"
    assert all(not isinstance(p, str) for p in current.content[1:])  # no label beside an image
    with pytest.raises(ValueError, match="images: the passive protocol"):
        conv.add_observation("x", synthetic_image(), step=4)


# -- compaction -------------------------------------------------------------------------------


class Summarizer:
    def __init__(self, text: str = "Progress: gripper above the cube. Plan: lower 30 mm."):
        self.requests: list[ChatRequest] = []
        self.text = text

    async def __call__(self, request: ChatRequest) -> str:
        self.requests.append(request)
        return self.text


def limits_at(threshold: int) -> ContextLimits:
    """Limits whose compaction threshold 0.5 * window - reserve is exactly `threshold`."""
    return ContextLimits(window_tokens=2 * (threshold + 8192), compact_fraction=0.5, max_images=4)


def test_token_estimate_counts_text_and_images_by_the_tile_rule():
    conv = Conversation("s" * 400)
    conv.add_observation("o" * 400, synthetic_image(512, 512), step=1)
    assert conv.estimate_tokens() == 100 + (100 + TOKENS_PER_TURN) + 255  # 512 px: one tile


def test_default_limits_are_the_facts_numbers():
    limits = ContextLimits()
    assert (limits.window_tokens, limits.output_reserve_tokens) == (262_144, 8_192)
    assert limits.compact_above == int(0.8 * 262_144) - 8_192 == 201_523  # the reference's
    assert (limits.keep_user_turns, limits.max_images) == (6, 1)  # the current image only


def test_compaction_triggers_above_the_threshold_and_keeps_the_last_six_user_turns():
    conv, images = active_episode(10)
    conv.add_observation("observation 11", last := synthetic_image(seed=11), step=11)
    estimate = conv.history_tokens()
    # every image of the thread counts, the ones the request leaves out included
    assert estimate > conv.estimate_tokens()
    summarize = Summarizer()

    conv.limits = limits_at(estimate + 1)  # one token below the threshold: nothing happens
    assert asyncio.run(conv.compact_if_needed(summarize)) is None
    assert summarize.requests == []

    conv.limits = limits_at(estimate)  # at it
    kept_turns = [e.turn for e in conv.context[-11:]]  # the last 6 user turns, replies between
    event = asyncio.run(conv.compact_if_needed(summarize))
    assert event is not None and len(summarize.requests) == 1
    summary_request = summarize.requests[0]
    assert summary_request.images == []
    asked = summary_request.last_user_text
    for part in ("observation 1", "look 5", "[image from step 2 omitted]", "Progress", "failed"):
        assert part in asked, part
    assert "observation 6" not in asked  # the kept turns are not summarised

    assert all(a is b for a, b in zip([e.turn for e in conv.context[1:]], kept_turns, strict=True))
    assert conv.context[0].kind == "summary"
    request = conv.request()
    assert request.turns[0].text.startswith(SUMMARY_HEADER + summarize.text)
    assert request.turns[0].text.endswith("observation 6\n[image from step 6 omitted]")
    assert [id(im) for im in request.images] == [id(im) for im in [*images[-3:], last]]
    assert event.messages_summarised == 10 and event.user_turns_kept == 6
    assert event.tokens_before == estimate >= event.compact_above
    assert event.tokens_after == conv.history_tokens() < conv.limits.compact_above
    assert event.record()["event"] == "compaction" and event.record()["under_limit"]
    assert conv.compactions == (event,)
    # The transcript is append-only: all 21 messages, then the summary.
    kinds = [e.kind for e in conv.transcript]
    assert kinds == ["observation", "reply"] * 10 + ["observation", "summary"]


def test_the_compaction_excerpt_cuts_long_messages_and_keeps_the_newest_within_its_budget():
    # the budget is max(8,000, 0.6 x window) tokens: 9,831 at this small window
    conv = Conversation("system", protocol="active", limits=limits_at(1))
    budget = max(8_000, int(0.6 * conv.limits.window_tokens))
    for step in range(1, 13):
        text = f"observation {step} " + ("x" * 20_000 if step == 2 else "y" * 9_000)
        conv.add_observation(text, synthetic_image(seed=step), step=step)
        conv.add_reply(f'{{"action": "camera.view_side", "reason": "look {step}"}}')
    conv.add_observation("observation 13", synthetic_image(seed=13), step=13)
    summarize = Summarizer()
    assert asyncio.run(conv.compact(summarize)) is not None
    asked = summarize.requests[0].last_user_text
    summarised = asked.split("--- End of the earlier messages.")[0]
    assert budget - 2_500 < text_tokens(summarised) <= budget + 20  # + the note of what is left out
    # newest first: the last summarised messages are in, the oldest are left out, in order
    assert "observation 7 " in asked and "look 7" in asked
    assert "observation 1 " not in asked and "older messages left out." in asked
    assert asked.index("observation 6 ") < asked.index("observation 7 ")
    # a message over 12,000 characters keeps its start and its end around a note of the cut
    long = "observation 2 " + "x" * 20_000
    cut = cut_middle(long, 12_000)
    assert len(cut) < 12_100 and cut.startswith("observation 2 xxx") and cut.endswith("xxx")
    assert "[... 8,014 characters left out ...]" in cut
    assert cut_middle("short", 12_000) == "short"


def test_compaction_needs_more_than_six_user_turns_and_a_non_empty_summary():
    conv, _ = active_episode(5)
    conv.add_observation("observation 6", synthetic_image(seed=6), step=6)
    conv.limits = limits_at(1)
    summarize = Summarizer()
    assert asyncio.run(conv.compact_if_needed(summarize)) is None
    assert summarize.requests == []
    conv.add_reply('{"action": "gripper.open"}')
    conv.add_observation("observation 7", synthetic_image(seed=7), step=7)
    with pytest.raises(ValueError, match="empty summary"):
        asyncio.run(conv.compact(Summarizer("  ")))
    assert len(conv.context) == 13  # nothing replaced


def test_passive_compaction_keeps_the_current_bundle_whole():
    conv = Conversation("system", protocol="passive")
    for step in range(1, 9):
        views = bundle(step)
        conv.add_observation(f"observation {step}", views, step=step)
        conv.add_reply('{"action": "gripper.open"}')
    conv.add_observation("observation 9", last := bundle(9), step=9)
    conv.limits = limits_at(conv.history_tokens())
    summarize = Summarizer()
    event = asyncio.run(conv.compact_if_needed(summarize))
    assert event is not None and summarize.requests[0].images == []
    assert "[five images from step 1 omitted]" in summarize.requests[0].last_user_text
    request = conv.request()
    assert [id(im) for im in request.images] == [id(last[v]) for v in PASSIVE_VIEWS]
    assert placeholders(request) == [4, 5, 6, 7, 8]
