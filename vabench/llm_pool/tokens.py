"""Token estimates made before a call (for the TPM limiter) and by the simulated server.

An estimate only has to be close enough to pace a token-per-minute limit; the pool corrects
it with the reported usage after the call. Text: about 4 characters per token (English-like
prompts with numbers and JSON). Images: each API's published rule, from the JPEG's size read
out of its header, so the image is never decoded.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from vabench.llm_pool.messages import ChatRequest, Image

CHARS_PER_TOKEN = 4.0
TOKENS_PER_TURN = 4  # role markers and separators
UNKNOWN_IMAGE_SIZE = (1280, 960)  # the benchmark's camera; used when a header is unreadable

_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}  # start-of-frame, not DHT/DAC


def jpeg_size(head: bytes) -> tuple[int, int] | None:
    """(width, height) from the first bytes of a JPEG, or None if they do not say."""
    if head[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 9 < len(head):
        if head[i] != 0xFF:
            return None
        marker = head[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        length = int.from_bytes(head[i + 2 : i + 4], "big")
        if marker in _SOF_MARKERS:
            height = int.from_bytes(head[i + 5 : i + 7], "big")
            width = int.from_bytes(head[i + 7 : i + 9], "big")
            return (width, height) if width and height else None
        i += 2 + length
    return None


def image_size(image: Image) -> tuple[int, int]:
    if image.media_type == "image/jpeg":
        size = jpeg_size(image.head())
        if size is not None:
            return size
    return UNKNOWN_IMAGE_SIZE


def openai_image_tokens(width: int, height: int) -> int:
    """OpenAI's tile rule (detail "high"/"auto" for large images): fit within 2048x2048, scale
    the short side to 768, then 85 + 170 per 512-px tile. FACTS.md uses the same rule."""
    scale = min(1.0, 2048 / max(width, height))
    w, h = width * scale, height * scale
    scale = min(1.0, 768 / min(w, h))
    w, h = w * scale, h * scale
    return 85 + 170 * math.ceil(w / 512) * math.ceil(h / 512)


def anthropic_image_tokens(width: int, height: int) -> int:
    """Anthropic's rule: about width*height/750 after fitting the long edge within 1568 px and
    the area within ~1.15 megapixels."""
    scale = min(1.0, 1568 / max(width, height), math.sqrt(1_150_000 / (width * height)))
    return math.ceil(width * scale * height * scale / 750)


ImageTokenRule = Callable[[int, int], int]


def text_tokens(text: str) -> int:
    return math.ceil(len(text) / CHARS_PER_TOKEN)


def block_tokens(request: ChatRequest, image_rule: ImageTokenRule) -> list[int]:
    """Estimated tokens of each of `request.blocks` (a turn's overhead counted with its first
    block), so that prefix sums give the size of every prompt prefix."""
    counts = [text_tokens(request.system)] if request.system else []
    for turn in request.turns:
        for i, part in enumerate(turn.content):
            n = text_tokens(part) if isinstance(part, str) else image_rule(*image_size(part))
            counts.append(n + (TOKENS_PER_TURN if i == 0 else 0))
    return counts


def estimate_input_tokens(request: ChatRequest, image_rule: ImageTokenRule) -> int:
    """Estimated prompt tokens of a request under an API's image rule."""
    return sum(block_tokens(request, image_rule))


def stand_in_jpeg(width: int, height: int) -> bytes:
    """The header of a baseline JPEG of this size: all the token estimators read of an image."""
    sof = b"\xff\xc0\x00\x11\x08" + height.to_bytes(2, "big") + width.to_bytes(2, "big")
    sof += b"\x03" + b"\x01\x22\x00\x02\x11\x01\x03\x11\x01"  # three components
    return b"\xff\xd8" + sof + b"\xff\xd9"
