"""JPEG in Warp kernels: a render pass's frames encoded on the device, two waits a pass.

Why: with nvJPEG an engine process spent twice as long in JPEG as in ray tracing, for a few
per cent of the GPU's kernel time. nvJPEG waits for the GPU inside each frame's encode call (it
sizes the output on the host) and again to retrieve each frame's bytes, and every wait queues
behind the ray tracer's megakernels. Here a pass of n frames is a handful of launches and two
waits (its lengths, then its bytes), whatever n: beside a ray-tracer-like load several times
nvJPEG's calls, and a shorter suite (docs/PERFORMANCE.md, "JPEG on the GPU"). The renderer's
default on a GPU.

What it writes: baseline sequential JPEG (ITU T.81, 8-bit, Huffman) with a JFIF header; the
IJG's quality scaling of the standard quantisation tables and the standard Huffman tables of
T.81 Annex K, which is what libjpeg writes without `optimize`; chroma subsampling 4:2:0,
4:2:2 or 4:4:4 (`ImageSettings`). The coefficients are libjpeg's up to rounding (the decoded
pixels are compared with libjpeg-turbo's in tests/test_warp_jpeg.py).

How, on the encoder's stream, for the first n worlds of a pass's packed 0x??RRGGBB pixels:

1. `_transform`: a thread per 8x8 block (image, MCU, block of the MCU) converts its pixels'
   colour, subsamples the chroma, transforms and quantises (a multiply, not a division), and
   keeps the coefficients (16 bits each, zigzag order, the DC first) for the kernels after it,
   coefficient j of every block of an image side by side (neighbouring threads write and read
   neighbouring bytes). Its own module, loops unrolled (`_transform`).
2. `_count_bits`: a thread per block sums the lengths of its Huffman codes. A block's DC is
   coded as the difference from the same component's block before it in scan order, read
   from the kept coefficients.
3. An inclusive scan of those lengths: each block's bit offset in its image's entropy data
   (`warp_scan`: Warp's own scan frees its scratch memory unordered with our streams), then
   `_pack`: the same blocks again, each writing its codes at its offset into its image's row
   of 32-bit words (most significant bit first): an atomic OR for the two words it may share
   with its neighbours, plain stores between.
4. `_count_ff`, a scan, `_sizes` and `_place`: every 0xFF byte gets its stuffed 0x00 (T.81
   B.1.1.5) while the images are copied end to end into one buffer; the last byte is padded
   with 1-bits.
5. The lengths come to the host (the wait for the kernels), then the bytes (a copy: no
   multiprocessor time), and each image gets its header and end marker.

Everything before the Huffman codes is integer arithmetic (libjpeg's fixed-point colour
conversion, a DCT with 12-bit coefficients, libjpeg's rounding of halves away from zero), the
same bits on every device and compiler, which a float DCT would not promise (fused
multiply-adds may be contracted differently). Where a quotient is exactly a half (synthetic
patterns such as a checkerboard at quality 50) this encoder and libjpeg may round it apart.

Why the coefficients are kept: otherwise the kernels that count and write the bits each
compute their block's samples and DCT, and its predecessor's DC again from its pixels: four
reads and conversions of every pixel. Kept, the kernels take about a third of the GPU time
(the same bytes: tests/test_warp_jpeg.py's goldens; docs/PERFORMANCE.md, "JPEG on the GPU").
The price: 128 bytes a block, ~3.7 MB a 1280x960 world at 4:2:0 (`bytes_per_world`, charged
to the renderer's passes).

An image whose entropy data would not fit its buffer (`CAP_BITS_PER_PIXEL`; rendered scenes
take 1.0-1.5 bits a pixel at quality 95, benchmarks/jpeg_contention.py's noisy frames 4.5) is
encoded on the host from its pixels instead (`images.encode_jpeg`): every frame gets its JPEG.
"""

# Warp kernels: a variable a dynamic loop changes is declared with its type (`int(0)`).
# ruff: noqa: UP018
from __future__ import annotations

import contextlib
import logging
import math
import struct as pystruct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from vabench.render.images import ImageSettings, encode_jpeg
from vabench.render.warp_scan import InclusiveScan
from vabench.sim_mjx.warp import streams

log = logging.getLogger(__name__)

# Forward only, loops kept as loops: with Warp's defaults (adjoint kernels, loops of up to 16
# constant iterations unrolled) this module was 21,400 lines of CUDA and took NVRTC 105 s for
# sm_90 on this 2-core host; it must compile in seconds on a fresh GPU host.
wp.set_module_options({"enable_backward": False, "max_unroll": 1})

CAP_BITS_PER_PIXEL = 8
"""Entropy data an image may take on the device, in bits a pixel; beyond it, the host encodes
that image."""
CHUNK = wp.constant(64)
"""Bytes of entropy data a thread of the byte-stuffing kernels handles."""
SAMPLING = {"420": (2, 2), "422": (2, 1), "444": (1, 1)}
"""Luma's (horizontal, vertical) sampling factors; chroma's are (1, 1)."""


def _zigzag() -> np.ndarray:
    """The natural (row * 8 + column) index of each coefficient in zigzag order (T.81 A.3.6)."""
    cells = [(r, c) for r in range(8) for c in range(8)]
    cells.sort(key=lambda rc: (rc[0] + rc[1], rc[0] if (rc[0] + rc[1]) % 2 else -rc[0]))
    return np.array([r * 8 + c for r, c in cells], np.int32)


ZIGZAG = _zigzag()
# T.81 Annex K's tables: quantisation (K.1, K.2) in zigzag order, as a DQT segment holds them;
# Huffman (K.3, K.5) as DHT's code counts by length 1-16 and symbols.
LUMA_QUANT = bytes(
    [16, 11, 12, 14, 12, 10, 16, 14, 13, 14, 18, 17, 16, 19, 24, 40, 26, 24, 22, 22, 24, 49]
    + [35, 37, 29, 40, 58, 51, 61, 60, 57, 51, 56, 55, 64, 72, 92, 78, 64, 68, 87, 69, 55, 56]
    + [80, 109, 81, 87, 95, 98, 103, 104, 103, 62, 77, 113, 121, 112, 100, 120, 92, 101, 103, 99]
)
CHROMA_QUANT = bytes([17, 18, 18, 24, 21, 24, 47, 26, 26, 47, 99, 66, 56, 66] + [99] * 50)
DC_BITS = (
    [0, 1, 5, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0],
    [0, 3, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0],
)
DC_VALUES = bytes(range(12))
AC_BITS = (
    [0, 2, 1, 3, 3, 2, 4, 3, 5, 5, 4, 4, 0, 0, 1, 125],
    [0, 2, 1, 2, 4, 4, 3, 4, 7, 5, 4, 4, 0, 1, 2, 119],
)
AC_VALUES = (
    bytes.fromhex(
        "01020300041105122131410613516107227114328191a1082342b1c11552d1f02433627282090a16"
        "1718191a25262728292a3435363738393a434445464748494a535455565758595a63646566676869"
        "6a737475767778797a838485868788898a92939495969798999aa2a3a4a5a6a7a8a9aab2b3b4b5b6"
        "b7b8b9bac2c3c4c5c6c7c8c9cad2d3d4d5d6d7d8d9dae1e2e3e4e5e6e7e8e9eaf1f2f3f4f5f6f7f8f9fa"
    ),
    bytes.fromhex(
        "000102031104052131061241510761711322328108144291a1b1c109233352f0156272d10a162434"
        "e125f11718191a262728292a35363738393a434445464748494a535455565758595a636465666768"
        "696a737475767778797a82838485868788898a92939495969798999aa2a3a4a5a6a7a8a9aab2b3b4"
        "b5b6b7b8b9bac2c3c4c5c6c7c8c9cad2d3d4d5d6d7d8d9dae2e3e4e5e6e7e8e9eaf2f3f4f5f6f7f8f9fa"
    ),
)


def quant_tables(quality: int) -> tuple[np.ndarray, np.ndarray]:
    """(luma, chroma) quantisation tables in zigzag order at an IJG `quality` (1-100), as
    libjpeg scales them (`jpeg_quality_scaling`, baseline: each entry 1-255)."""
    scale = 5000 // quality if quality < 50 else 200 - 2 * quality
    return tuple(  # type: ignore[return-value]
        np.clip((np.frombuffer(t, np.uint8).astype(np.int64) * scale + 50) // 100, 1, 255)
        for t in (LUMA_QUANT, CHROMA_QUANT)
    )


def huffman_codes(bits: list[int], values: bytes) -> dict[int, tuple[int, int]]:
    """symbol -> (code, length) of a table given as counts by length (T.81 C.2)."""
    codes, code, k = {}, 0, 0
    for length in range(1, 17):
        for _ in range(bits[length - 1]):
            codes[values[k]] = (code, length)
            code, k = code + 1, k + 1
        code <<= 1
    return codes


def _segment(marker: int, payload: bytes) -> bytes:
    return pystruct.pack(">BBH", 0xFF, marker, len(payload) + 2) + payload


def jpeg_header(width: int, height: int, settings: ImageSettings) -> bytes:
    """SOI, JFIF, the quantisation and Huffman tables, the frame and the scan header."""
    luma, chroma = quant_tables(settings.quality)
    h, v = SAMPLING[settings.subsampling]
    dht = b"".join(
        bytes([cls << 4 | table]) + bytes(bits) + values
        for table in (0, 1)
        for cls, bits, values in (
            (0, DC_BITS[table], DC_VALUES),
            (1, AC_BITS[table], AC_VALUES[table]),
        )
    )
    return b"".join(
        (
            b"\xff\xd8",
            _segment(0xE0, b"JFIF\x00\x01\x01\x00\x00\x01\x00\x01\x00\x00"),
            _segment(0xDB, b"\x00" + bytes(luma.tolist()) + b"\x01" + bytes(chroma.tolist())),
            _segment(
                0xC0,
                pystruct.pack(">BHHB", 8, height, width, 3)
                + bytes([1, h << 4 | v, 0, 2, 0x11, 1, 3, 0x11, 1]),
            ),
            _segment(0xC4, dht),
            _segment(0xDA, bytes([3, 1, 0x00, 2, 0x11, 3, 0x11, 0, 63, 0])),
        )
    )


imat88 = wp.types.matrix(shape=(8, 8), dtype=wp.int32)
DCT_SCALE_BITS = 12
"""The DCT matrix's entries are scaled by 2^12 and rounded: |entry| <= 2,048."""
PASS_SHIFT = wp.constant(10)
"""Bits dropped after the first (column) pass: |D f| <= 8 x 2,048 x 128 = 2^21 becomes <= 2^11,
so the second pass stays below 8 x 2^11 x 2^11 = 2^25 (no int32 overflow)."""
DCT_BITS = wp.constant(2 * DCT_SCALE_BITS - 10)
"""A coefficient's scale after both passes: 2^(12 + 12 - 10) = 2^14."""


def _dct_matrix() -> np.ndarray:
    """D with D f D^T the 2-D DCT of T.81 A.3.3 (its C(u) / 2 folded into each row), scaled by
    2^DCT_SCALE_BITS and rounded to integers."""
    u, x = np.meshgrid(np.arange(8), np.arange(8), indexing="ij")
    scale = np.where(u == 0, math.sqrt(0.5), 1.0) * 0.5
    exact = scale * np.cos((2 * x + 1) * u * np.pi / 16)
    return np.round(exact * (1 << DCT_SCALE_BITS)).astype(np.int32)


DCT = wp.constant(imat88(*_dct_matrix().flatten().tolist()))
"""D, known to the compiler: its entries become immediate operands of the unrolled products."""
ZIGZAG_AT = wp.constant(imat88(*np.argsort(ZIGZAG).tolist()))
"""Where coefficient (u, v) goes in zigzag order (the inverse of `ZIGZAG`)."""


@wp.struct
class Layout:
    """One image size and subsampling: blocks, MCUs and the per-image buffer sizes."""

    width: int
    height: int
    h: int  # luma's sampling factors
    v: int
    mcus_x: int
    blocks: int  # a MCU's: h * v luma, one Cb, one Cr
    nblocks: int  # an image's
    cap_bits: int
    cap_words: int
    chunks: int
    cap_out: int


@wp.struct
class Writer:
    """A block's bit writer: `acc` holds `nacc` bits not yet written (the first `start % 32`
    of them the previous block's, as zeros), `word` where they go; `count` the block's bits."""

    acc: wp.uint64
    nacc: int
    word: int
    first: int
    count: int


@wp.func
def _sample(packed: wp.array2d(dtype=wp.uint32), i: int, x: int, y: int, lay: Layout, comp: int):
    """Y, Cb or Cr (0-255) of pixel (x, y) of image i, the image's edge repeated beyond it:
    libjpeg's fixed-point conversion (jccolor.c, 16 fraction bits, rounded)."""
    v = packed[i, wp.min(y, lay.height - 1) * lay.width + wp.min(x, lay.width - 1)]
    r = int((v >> wp.uint32(16)) & wp.uint32(255))
    g = int((v >> wp.uint32(8)) & wp.uint32(255))
    b = int(v & wp.uint32(255))
    if comp == 0:
        return (19595 * r + 38470 * g + 7471 * b + 32768) >> 16
    if comp == 1:
        return (-11059 * r - 21709 * g + 32768 * b + (128 << 16) + 32767) >> 16
    return (32768 * r - 27439 * g - 5329 * b + (128 << 16) + 32767) >> 16


@wp.func
def _level_sample(
    packed: wp.array2d(dtype=wp.uint32), i: int, x: int, y: int, comp: int, lay: Layout
):
    """Sample (x, y) of component `comp`'s plane of image i, level-shifted: luma a pixel's,
    chroma the rounded mean of its h x v pixels (h and v are 1 or 2: a shift divides)."""
    if comp == 0:
        return _sample(packed, i, x, y, lay, 0) - 128
    s = int(0)
    for dy in range(lay.v):
        for dx in range(lay.h):
            s += _sample(packed, i, x * lay.h + dx, y * lay.v + dy, lay, comp)
    return ((s + ((lay.h * lay.v) >> 1)) >> ((lay.h >> 1) + (lay.v >> 1))) - 128


@wp.func
def _quantise(value: int, q: int, reciprocal: wp.int64):
    """round(value / (q * 2^14)), halves away from zero (libjpeg's rounding), without a
    division: floor((|value| + q 2^13) / (q 2^14)) = floor(floor((|value| + q 2^13) / 2^14) /
    q), and floor(x / q) = (x * reciprocal) >> 32 with reciprocal = floor(2^32 / q) + 1, exact
    for x < 2^32 / q (`reciprocals`; here x < 2^12: |value| < 2^25)."""
    x = (wp.abs(value) + (q << (DCT_BITS - 1))) >> DCT_BITS
    a = int((wp.int64(x) * reciprocal) >> wp.int64(32))
    if value < 0:
        return -a
    return a


def reciprocals(quant: np.ndarray) -> np.ndarray:
    """`_quantise`'s multiplier of each quantisation step q (1-255): floor(2^32 / q) + 1."""
    q = quant.astype(np.int64)
    if q.min() < 1 or q.max() > 255:
        raise ValueError(f"quantisation steps must be 1-255, got {q.min()}-{q.max()}")
    return (np.int64(1) << np.int64(32)) // q + 1


@wp.func
def _previous_block(k: int, lay: Layout):
    """The block whose DC block k's is coded against (T.81 F.1.1.5.1): the same component's
    block before it in scan order, or -1 (coded against 0) for a component's first."""
    mcu = k // lay.blocks
    b = k % lay.blocks
    luma = lay.h * lay.v
    if b < luma and b > 0:
        return k - 1
    if mcu == 0:
        return -1
    if b == 0:
        return k - lay.blocks + luma - 1
    return k - lay.blocks


@wp.func
def _writer(nacc: int, word: int, first: int):
    """A writer with nothing of its block's written yet (`Writer`)."""
    w = Writer()
    w.acc = wp.uint64(0)
    w.nacc = nacc
    w.word = word
    w.first = first
    w.count = 0
    return w


@wp.func
def _put(w: Writer, code: int, length: int, words: wp.array(dtype=wp.uint32), emit: int):
    """`length` bits of `code` after the writer's; a full word is written (emit only)."""
    out = Writer()
    out.acc = w.acc
    out.nacc = w.nacc
    out.word = w.word
    out.first = w.first
    out.count = w.count + length
    if emit == 0:
        return out
    out.acc = (w.acc << wp.uint64(length)) | wp.uint64(code)
    out.nacc = w.nacc + length
    if out.nacc >= 32:  # at most one: nacc < 32 before, length <= 27
        value = wp.uint32((out.acc >> wp.uint64(out.nacc - 32)) & wp.uint64(0xFFFFFFFF))
        if out.first == 1:  # may hold the previous block's last bits
            wp.atomic_or(words, out.word, value)
        else:  # only this block's bits
            words[out.word] = value
        out.nacc = out.nacc - 32
        out.acc = out.acc & ((wp.uint64(1) << wp.uint64(out.nacc)) - wp.uint64(1))
        out.word = out.word + 1
        out.first = 0
    return out


@wp.func
def _magnitude(value: int):
    """(size category, its bits) of a coefficient or DC difference (T.81 F.1.2.1)."""
    a = wp.abs(value)
    size = int(0)
    while a > 0:
        a = a >> 1
        size += 1
    bits = value
    if value < 0:
        bits = value + (1 << size) - 1
    return wp.vec2i(size, bits)


@wp.func
def _code_block(
    coefs: wp.array(dtype=wp.int16),
    base: int,
    stride: int,
    dc_diff: int,
    comp: int,
    codes: wp.array(dtype=int),
    lengths: wp.array(dtype=int),
    w: Writer,
    words: wp.array(dtype=wp.uint32),
    emit: int,
):
    """A block's Huffman codes: its DC difference, then its AC coefficients (quantised, in
    zigzag order from `base`, `stride` apart) as runs of zeros and values (ZRL for 16 zeros,
    EOB after the last value)."""
    table = wp.min(comp, 1) * 512  # DC table at +0, AC at +256
    m = _magnitude(dc_diff)
    w = _put(w, (codes[table + m[0]] << m[0]) | m[1], lengths[table + m[0]] + m[0], words, emit)
    run = int(0)
    for k in range(1, 64):
        value = int(coefs[base + k * stride])
        if value == 0:
            run += 1
        else:
            while run > 15:
                w = _put(w, codes[table + 256 + 0xF0], lengths[table + 256 + 0xF0], words, emit)
                run -= 16
            m = _magnitude(value)
            symbol = table + 256 + run * 16 + m[0]
            w = _put(w, (codes[symbol] << m[0]) | m[1], lengths[symbol] + m[0], words, emit)
            run = 0
    if run > 0:
        w = _put(w, codes[table + 256], lengths[table + 256], words, emit)
    return w


@wp.kernel(module="unique", module_options={"enable_backward": False, "max_unroll": 64})
def _transform(
    packed: wp.array2d(dtype=wp.uint32),
    lay: Layout,
    quant: wp.array(dtype=int),
    reciprocal: wp.array(dtype=wp.int64),
    coefs: wp.array(dtype=wp.int16),
):
    """Block k of image i, once: its samples, their DCT (D f D^T, rounded between the two
    products), quantised, in zigzag order: coefficient j at (i * 64 + j) * nblocks + k (the DC
    first: at most 1,024 in magnitude, the AC clamped to baseline's 10 bits).

    A module of its own, its loops unrolled (the rest of the encoder keeps its loops: compile
    time; the products are the compiler's own loops): with constant indices the samples and
    the products' 64 values can live in registers, D's entries are constants, and neighbouring
    threads (blocks) write neighbouring coefficients. Integer arithmetic as before, so the bytes
    are the encoder's before (the goldens)."""
    i, k = wp.tid()
    mcu = k // lay.blocks
    b = k % lay.blocks
    comp = wp.max(b - lay.h * lay.v + 1, 0)
    x0 = (mcu % lay.mcus_x) * 8  # in the component's plane
    y0 = (mcu // lay.mcus_x) * 8
    if comp == 0:
        x0 = x0 * lay.h + 8 * (b % lay.h)
        y0 = y0 * lay.v + 8 * (b // lay.h)
    f = imat88()
    for r in range(8):
        for c in range(8):
            f[r, c] = _level_sample(packed, i, x0 + c, y0 + r, comp, lay)
    t = DCT @ f
    for r in range(8):
        for c in range(8):
            t[r, c] = (t[r, c] + (1 << (PASS_SHIFT - 1))) >> PASS_SHIFT
    coef = t @ wp.transpose(DCT)
    table = wp.min(comp, 1) * 64
    at = i * 64 * lay.nblocks + k
    for u in range(8):
        for v in range(8):
            n = u * 8 + v
            value = _quantise(coef[u, v], quant[table + n], reciprocal[table + n])
            if n > 0:
                value = wp.clamp(value, -1023, 1023)  # baseline AC: 10 bits
            coefs[at + ZIGZAG_AT[u, v] * lay.nblocks] = wp.int16(value)


@wp.func
def _block_start(coefs: wp.array(dtype=wp.int16), i: int, k: int, lay: Layout):
    """Block k of image i: (where its DC is, its DC difference, its component); its
    coefficient j is nblocks * j further (`_transform`)."""
    at = i * 64 * lay.nblocks + k
    before = _previous_block(k, lay)
    dc = int(coefs[at])
    if before >= 0:
        dc = dc - int(coefs[at - k + before])
    return at, dc, wp.max(k % lay.blocks - lay.h * lay.v + 1, 0)


@wp.kernel
def _count_bits(
    coefs: wp.array(dtype=wp.int16),
    lay: Layout,
    codes: wp.array(dtype=int),
    lengths: wp.array(dtype=int),
    words: wp.array(dtype=wp.uint32),
    bits: wp.array(dtype=wp.int64),
):
    i, k = wp.tid()
    base, diff, comp = _block_start(coefs, i, k, lay)
    w = _code_block(
        coefs, base, lay.nblocks, diff, comp, codes, lengths, _writer(0, 0, 0), words, 0
    )
    bits[i * lay.nblocks + k] = wp.int64(w.count)


@wp.func
def _image_bits(ends: wp.array(dtype=wp.int64), i: int, lay: Layout):
    """(where image i's bits begin in the scan of every block's, how many it has)."""
    base = wp.int64(0)
    if i > 0:
        base = ends[i * lay.nblocks - 1]
    return base, ends[i * lay.nblocks + lay.nblocks - 1] - base


@wp.kernel
def _pack(
    coefs: wp.array(dtype=wp.int16),
    lay: Layout,
    codes: wp.array(dtype=int),
    lengths: wp.array(dtype=int),
    bits: wp.array(dtype=wp.int64),
    ends: wp.array(dtype=wp.int64),
    words: wp.array(dtype=wp.uint32),
):
    i, k = wp.tid()
    base, total = _image_bits(ends, i, lay)
    if total > wp.int64(lay.cap_bits):
        return  # the host encodes this image
    start = int(ends[i * lay.nblocks + k] - bits[i * lay.nblocks + k] - base)
    at, diff, comp = _block_start(coefs, i, k, lay)
    w = _writer(start % 32, i * lay.cap_words + start // 32, 1)
    w = _code_block(coefs, at, lay.nblocks, diff, comp, codes, lengths, w, words, 1)
    if w.nacc > 0:  # the last word, shared with the next block
        wp.atomic_or(
            words, w.word, wp.uint32((w.acc << wp.uint64(32 - w.nacc)) & wp.uint64(0xFFFFFFFF))
        )


@wp.func
def _byte(words: wp.array(dtype=wp.uint32), i: int, j: int, total: wp.int64, lay: Layout):
    """Byte j of image i's entropy data, the last one padded with 1-bits (T.81 F.1.2.3)."""
    word = words[i * lay.cap_words + j // 4]
    value = int((word >> wp.uint32(24 - 8 * (j % 4))) & wp.uint32(255))
    if wp.int64(j) == (total + wp.int64(7)) // wp.int64(8) - wp.int64(1):
        pad = int((wp.int64(8) - total % wp.int64(8)) % wp.int64(8))
        value = value | ((1 << pad) - 1)
    return value


@wp.kernel
def _count_ff(
    words: wp.array(dtype=wp.uint32),
    ends: wp.array(dtype=wp.int64),
    lay: Layout,
    ff: wp.array(dtype=int),
):
    i, c = wp.tid()
    _base, total = _image_bits(ends, i, lay)
    nbytes = int((total + wp.int64(7)) // wp.int64(8))
    count = int(0)
    if total <= wp.int64(lay.cap_bits):
        for j in range(c * CHUNK, wp.min(c * CHUNK + CHUNK, nbytes)):
            if _byte(words, i, j, total, lay) == 255:
                count += 1
    ff[i * lay.chunks + c] = count


@wp.kernel
def _sizes(
    ends: wp.array(dtype=wp.int64),
    ff_ends: wp.array(dtype=int),
    lay: Layout,
    n: int,
    sizes: wp.array(dtype=int),
):
    """sizes[i]: image i's stuffed length (-1: left to the host); sizes[n + i]: where it starts."""
    at = int(0)
    for i in range(n):
        _base, total = _image_bits(ends, i, lay)
        ff_base = int(0)
        if i > 0:
            ff_base = ff_ends[i * lay.chunks - 1]
        length = (
            int((total + wp.int64(7)) // wp.int64(8))
            + ff_ends[i * lay.chunks + lay.chunks - 1]
            - ff_base
        )
        sizes[n + i] = at
        if total > wp.int64(lay.cap_bits) or length > lay.cap_out:
            sizes[i] = -1
        else:
            sizes[i] = length
            at += length


@wp.kernel
def _place(
    words: wp.array(dtype=wp.uint32),
    ends: wp.array(dtype=wp.int64),
    ff: wp.array(dtype=int),
    ff_ends: wp.array(dtype=int),
    sizes: wp.array(dtype=int),
    lay: Layout,
    n: int,
    out: wp.array(dtype=wp.uint8),
):
    i, c = wp.tid()
    if sizes[i] < 0:
        return
    _base, total = _image_bits(ends, i, lay)
    nbytes = int((total + wp.int64(7)) // wp.int64(8))
    if c * CHUNK >= nbytes:
        return
    ff_base = int(0)
    if i > 0:
        ff_base = ff_ends[i * lay.chunks - 1]
    at = sizes[n + i] + c * CHUNK + ff_ends[i * lay.chunks + c] - ff[i * lay.chunks + c] - ff_base
    for j in range(c * CHUNK, wp.min(c * CHUNK + CHUNK, nbytes)):
        value = _byte(words, i, j, total, lay)
        out[at] = wp.uint8(value)
        at += 1
        if value == 255:
            out[at] = wp.uint8(0)
            at += 1


def load_modules(device: Any) -> None:
    """Compile (or load from Warp's cache) every kernel module of this encoder on `device`:
    this module's and `_transform`'s own."""
    for module in (_transform.module, __name__):
        wp.load_module(module, device=device)


def layout(width: int, height: int, subsampling: str) -> Any:
    """The `Layout` of images of this size and subsampling."""
    h, v = SAMPLING[subsampling]
    lay = Layout()
    lay.width, lay.height, lay.h, lay.v = width, height, h, v
    lay.mcus_x = -(-width // (8 * h))
    lay.blocks = h * v + 2
    lay.nblocks = lay.mcus_x * -(-height // (8 * v)) * lay.blocks
    lay.cap_words = -(-width * height * CAP_BITS_PER_PIXEL // 32)
    lay.cap_bits = lay.cap_words * 32
    lay.chunks = -(-lay.cap_words * 4 // CHUNK)
    lay.cap_out = lay.cap_words * 4 + lay.cap_words  # stuffing: up to a quarter more
    return lay


def bytes_per_world(width: int, height: int, subsampling: str = "444") -> int:
    """Device memory a world of a pass needs for this encoder at `subsampling` (default: 4:4:4,
    the most blocks): each block's quantised coefficients (64 x 2 bytes), bit count and offset
    (16 bytes), the entropy data, its stuffing counts and the output."""
    lay = layout(width, height, subsampling)
    return lay.nblocks * (128 + 16) + lay.cap_words * 4 + lay.chunks * 8 + lay.cap_out


@dataclass
class _Tables:
    lay: Any
    quant: wp.array
    reciprocal: wp.array
    codes: wp.array
    lengths: wp.array
    header: bytes


@dataclass
class Pending:
    """A pass's encode queued on the device (`WarpJpeg.queue`), for `WarpJpeg.finish`."""

    packed: wp.array
    n: int
    settings: ImageSettings
    tables: _Tables
    sized: Any  # the event after the lengths' copy to the host
    queued_s: float


SECONDS_LOCK = threading.Lock()
"""Held while an encoder adds to its `seconds` (several encoders share the renderer's dict)."""


class WarpJpeg:
    """Encodes up to `n_worlds` frames of `width` x `height` packed pixels (a render pass's
    `rgb_data`, (n_worlds, H * W) uint32) on `device`, on a stream of its own at `priority`
    (`streams.PRIORITIES`). Not shared between threads: a render pass owns one. `seconds`:
    where its calls spent their time, summed into the dict given (the renderer's log)."""

    def __init__(
        self,
        n_worlds: int,
        width: int,
        height: int,
        device: Any,
        priority: str = "middle",
        seconds: dict[str, float] | None = None,
    ):
        self.n_worlds, self.width, self.height = n_worlds, width, height
        self.device = wp.get_device(device)
        self.stream = streams.new_stream(self.device, priority)
        self._tables: dict[tuple[int, str], _Tables] = {}
        self._buffers: dict[str, wp.array] = {}
        self._scans: dict[str, InclusiveScan] = {}
        self._host_out: wp.array | None = None
        self.seconds = seconds if seconds is not None else {}
        self.host_encoded = 0
        """Images whose entropy data outgrew the device's buffer, encoded on the host."""

    def encode(
        self,
        packed: wp.array,
        n: int,
        settings: ImageSettings,
        queueing: Callable[[], contextlib.AbstractContextManager[Any]] | None = None,
    ) -> list[bytes]:
        """JPEG bytes of the first `n` frames of `packed` (`queue`, then `finish`)."""
        enter = queueing or contextlib.nullcontext
        with enter():
            pending = self.queue(packed, n, settings)
        return self.finish(pending, queueing)

    def queue(
        self, packed: wp.array, n: int, settings: ImageSettings, after: Any = None
    ) -> Pending:
        """Queue the encode of the first `n` frames of `packed` on this encoder's stream,
        after `after` (an event of the work that writes `packed`; None: the work queued on the
        device's current stream... or nothing on the CPU). The caller holds the device's lock
        (the renderer's `streams.queueing`); `packed` must not change until `finish`."""
        if not 0 < n <= self.n_worlds or tuple(packed.shape) != (
            self.n_worlds,
            self.width * self.height,
        ):
            raise ValueError(
                f"{n} frames of shape {tuple(packed.shape)} for an encoder of "
                f"{self.n_worlds} x {self.width}x{self.height}"
            )
        t0 = time.perf_counter()
        with wp.ScopedDevice(self.device):
            writer = wp.get_stream(self.device) if self.device.is_cuda else None
        with wp.ScopedDevice(self.device), self._on_stream():
            if self.stream is not None:  # after the frames' writer
                if after is not None:
                    self.stream.wait_event(after)
                elif writer is not None and writer is not self.stream:
                    self.stream.wait_stream(writer)
            # tables and buffers are allocated and filled on this stream: ordered before use
            t = self._prepare(settings)
            lay, buf = t.lay, self._buffers
            blocks, chunks = n * lay.nblocks, n * lay.chunks
            words, ends, ff, ff_ends = buf["words"], buf["ends"], buf["ff"], buf["ff_ends"]
            blocks_in = [buf["coefs"], lay, t.codes, t.lengths]
            wp.launch(
                _transform,
                dim=(n, lay.nblocks),
                inputs=[packed, lay, t.quant, t.reciprocal, buf["coefs"]],
            )
            wp.launch(_count_bits, dim=(n, lay.nblocks), inputs=[*blocks_in, words, buf["bits"]])
            self._scans["bits"](buf["bits"], ends, blocks)
            words[: n * lay.cap_words].zero_()
            wp.launch(_pack, dim=(n, lay.nblocks), inputs=[*blocks_in, buf["bits"], ends, words])
            wp.launch(_count_ff, dim=(n, lay.chunks), inputs=[words, ends, lay, ff])
            self._scans["ff"](ff, ff_ends, chunks)
            wp.launch(_sizes, dim=1, inputs=[ends, ff_ends, lay, n, buf["sizes"]])
            wp.launch(
                _place,
                dim=(n, lay.chunks),
                inputs=[words, ends, ff, ff_ends, buf["sizes"], lay, n, buf["out"]],
            )
            wp.copy(buf["host_sizes"], buf["sizes"], count=2 * n)
            sized = streams.record(self.stream)
        return Pending(packed, n, settings, t, sized, time.perf_counter() - t0)

    def finish(
        self,
        pending: Pending,
        queueing: Callable[[], contextlib.AbstractContextManager[Any]] | None = None,
    ) -> list[bytes]:
        """The JPEG bytes of a queued encode: waits for its lengths (without the device's
        lock), then copies its bytes out (launching inside `queueing()`)."""
        enter = queueing or contextlib.nullcontext
        t1 = time.perf_counter()
        streams.wait(pending.sized)
        n = pending.n
        host = self._buffers["host_sizes"].numpy()
        lengths, starts = host[:n].copy(), host[n : 2 * n].copy()
        total = int(lengths[lengths > 0].sum())
        t2 = time.perf_counter()
        data = self._copy_out(total, enter) if total else memoryview(b"")
        header = pending.tables.header
        out = [  # one copy of each image's bytes, out of the pinned buffer
            b"".join((header, data[starts[i] : starts[i] + lengths[i]], b"\xff\xd9"))
            if lengths[i] >= 0
            else self._on_host(pending.packed, i, pending.settings, enter)
            for i in range(n)
        ]
        with SECONDS_LOCK:
            for part, seconds in (
                ("queueing", pending.queued_s),
                ("waiting for the GPU", t2 - t1),
                ("copying out", time.perf_counter() - t2),
            ):
                self.seconds[part] = self.seconds.get(part, 0.0) + seconds
        return out

    def _prepare(self, settings: ImageSettings) -> _Tables:
        """The tables and buffers of `settings` (made once each, on the current stream: the
        encoder's, under the device's lock)."""
        key = (settings.quality, settings.subsampling)
        if key not in self._tables:
            lay = layout(self.width, self.height, settings.subsampling)
            quant = np.ones(128, np.int32)
            for t, table in enumerate(quant_tables(settings.quality)):
                quant[t * 64 + ZIGZAG] = table
            codes, lengths = np.zeros(1024, np.int32), np.zeros(1024, np.int32)
            for t in (0, 1):
                parts = ((DC_BITS[t], DC_VALUES), (AC_BITS[t], AC_VALUES[t]))
                for part, (bits, values) in enumerate(parts):
                    for symbol, (code, length) in huffman_codes(bits, values).items():
                        codes[t * 512 + part * 256 + symbol] = code
                        lengths[t * 512 + part * 256 + symbol] = length
            d = self.device
            self._tables[key] = _Tables(
                lay,
                wp.array(quant, dtype=int, device=d),
                wp.array(reciprocals(quant), dtype=wp.int64, device=d),
                wp.array(codes, dtype=int, device=d),
                wp.array(lengths, dtype=int, device=d),
                jpeg_header(self.width, self.height, settings),
            )
            self._size_buffers(lay)
        return self._tables[key]

    def _size_buffers(self, lay: Any) -> None:
        n, d = self.n_worlds, self.device
        want = {
            "coefs": (n * lay.nblocks * 64, wp.int16),
            "bits": (n * lay.nblocks, wp.int64),
            "ends": (n * lay.nblocks, wp.int64),
            "words": (n * lay.cap_words, wp.uint32),
            "ff": (n * lay.chunks, wp.int32),
            "ff_ends": (n * lay.chunks, wp.int32),
            "out": (n * lay.cap_out, wp.uint8),
            "sizes": (2 * n, int),
        }
        if (
            self._buffers
            and self.stream is not None
            and any(self._buffers[name].shape[0] < size for name, (size, _) in want.items())
        ):  # a freed array goes back to the pool unordered with this stream: nothing may use it
            # (an event that sleeps: a stream synchronisation spins a core for its whole wait,
            # blocking-sync context or not, benchmarks/gpu_waits.py)
            streams.wait(streams.record(self.stream))
        for name, (size, dtype) in want.items():
            if name not in self._buffers or self._buffers[name].shape[0] < size:
                self._buffers[name] = wp.zeros(size, dtype=dtype, device=d)
                if name in ("bits", "ff"):
                    self._scans[name] = InclusiveScan(dtype, size, d)
        if "host_sizes" not in self._buffers:
            self._buffers["host_sizes"] = wp.zeros(2 * n, dtype=int, device="cpu", pinned=d.is_cuda)

    def _on_stream(self) -> contextlib.AbstractContextManager[Any]:
        if self.stream is None:
            return contextlib.nullcontext()
        return wp.ScopedStream(self.stream, sync_enter=False)

    def _copy_out(self, total: int, enter: Callable[[], Any]) -> memoryview:
        """The first `total` bytes of the output, a view of a pinned buffer on a GPU (allocated,
        as every device-side allocation, inside `enter`: the device's lock), valid until this
        encoder's next call."""
        with enter(), wp.ScopedDevice(self.device), self._on_stream():
            if self._host_out is None or self._host_out.shape[0] < total:
                kept = self._host_out.shape[0] if self._host_out is not None else 0
                self._host_out = wp.empty(
                    max(total, 2 * kept), dtype=wp.uint8, device="cpu", pinned=self.device.is_cuda
                )
            wp.copy(self._host_out, self._buffers["out"], count=total)
            copied = streams.record(self.stream)
        streams.wait(copied)
        return memoryview(self._host_out.numpy()[:total])

    def _on_host(
        self, packed: wp.array, i: int, settings: ImageSettings, enter: Callable[[], Any]
    ) -> bytes:
        """Image i encoded on the host from its pixels (its entropy data outgrew the buffer)."""
        self.host_encoded += 1
        if self.host_encoded == 1:
            log.info(
                "warp_jpeg: an image over %d bits a pixel encoded on the host", CAP_BITS_PER_PIXEL
            )
        with enter(), wp.ScopedDevice(self.device), self._on_stream():
            pixels = packed[i].numpy()  # after this stream's work
        bgrx = pixels.view(np.uint8).reshape(self.height, self.width, 4)
        return encode_jpeg(bgrx, settings.quality, settings.subsampling, colorspace="BGRX")
